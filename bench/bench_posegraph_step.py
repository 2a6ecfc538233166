"""Benchmark: one Levenberg–Marquardt step piece by piece, swiftjax (sparse path) vs GTSAM 4.3.

Where the time of one LM iteration goes on a graph from ``../shared/data/posegraphs`` (lifted to
Sim(3), float64), at the given poses:

* ours: the ``advance`` program (retraction, cost, residuals, exact Jacobians, normal equations:
  everything XLA does per step) and the host solve, split into the gather of the CSC values,
  CHOLMOD's numeric factorisation and the two triangular solves;
* GTSAM: ``graph.error``, ``graph.linearize``, the COLAMD ordering, multifrontal elimination and
  back-substitution (what its LM does per iteration).

Each timing is the best of ``--repeat``, ours and GTSAM's alternating within one process.

    .venv/bin/python bench/bench_posegraph_step.py [--graph parking-garage] [--repeat 20]

Writes ``bench/results/posegraph_step-<stamp>.json``.
"""

from __future__ import annotations

import argparse
import functools
import os
import pathlib
import sys
import time

import jax
import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
jax.config.update("jax_compilation_cache_dir", os.environ.get("JAX_COMPILATION_CACHE_DIR", str(REPO / ".jax_cache")))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

from bench.common import markdown_table, write_results
from swiftjax import posegraph
from swiftjax.io.g2o import read_g2o
from swiftjax.posegraph import driver, sparse_direct
from swiftjax.posegraph.problem import bucket_size, pad_problem


def _timer(fn):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return time.perf_counter() - t0, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--graph", default="parking-garage")
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args()
    shared = pathlib.Path(os.environ.get("SWIFTJAX_SHARED", REPO.parent / "shared"))
    g = read_g2o(shared / "data" / "posegraphs" / f"{args.graph}.g2o")

    import cvxopt
    import cvxopt.cholmod as cholmod
    import gtsam
    from _gtsam_baseline import build_graph

    with jax.enable_x64(True):
        prob = posegraph.Problem(g.poses, g.edges, g.measurements, g.information, g.fixed)
        padded = pad_problem(prob, bucket_size(prob.num_nodes), bucket_size(prob.num_edges))
        static = driver._Static(damping="identity", initialization="none")
        params = {
            k: jax.numpy.asarray(v, jax.numpy.float64)
            for k, v in dict(rtol=1e-5, atol=0.0, gtol=1e-10, lambda0=1e-5, kernel_scale=1.0).items()
        }
        params["kernel"] = jax.numpy.asarray(0, jax.numpy.int32)
        solver = posegraph.HostSparse()
        bucket = driver._Bucket(padded, params, solver, static)
        problem, y, state, _ = bucket.begin(padded, params, solver)
        zero = np.zeros((padded.num_nodes, 7))
        advance_c = functools.partial(bucket.step, problem, params, solver)
        y, state, damping = jax.block_until_ready(advance_c(y, state, zero, np.asarray(True)))
        edges, mask, fixed = (np.asarray(a) for a in (problem.edges, problem.edge_mask, problem.fixed))
        ne = state.lin.ne
        diag, off, grad, damp = (np.asarray(a) for a in (ne.diag, ne.off, ne.grad, damping))
        pat = sparse_direct.pattern(padded.num_nodes, 7, edges, mask, fixed)
        values = pat.values(diag, off, damp)
        pat.solve(values, -grad.reshape(-1))  # builds the symbolic factorisation once

        graph, gvalues = build_graph(
            *(np.asarray(a) for a in (g.poses, g.edges, g.measurements, g.information, g.fixed))
        )
        gfg = graph.linearize(gvalues)
        ordering = gtsam.Ordering.ColamdGaussianFactorGraph(gfg)
        bayes = gfg.eliminateMultifrontal(ordering)

        def rhs_solve():
            x = cvxopt.matrix(-grad.reshape(-1))
            cholmod.solve(pat._symbolic, x)
            return np.asarray(x)

        ours = {
            "advance (XLA)": lambda: advance_c(y, state, zero, np.asarray(True)),
            "gather CSC values": lambda: pat.values(diag, off, damp),
            "CHOLMOD numeric": lambda: cholmod.numeric(pat._matrix, pat._symbolic),
            "CHOLMOD solve": rhs_solve,
        }
        theirs = {
            "error": lambda: graph.error(gvalues),
            "linearize": lambda: graph.linearize(gvalues),
            "COLAMD ordering": lambda: gtsam.Ordering.ColamdGaussianFactorGraph(gfg),
            "eliminate (multifrontal)": lambda: gfg.eliminateMultifrontal(ordering),
            "back-substitution": lambda: bayes.optimize(),
        }
        best = {k: float("inf") for k in [*ours, *theirs]}
        for _ in range(args.repeat):
            for table in (ours, theirs):
                for name, fn in table.items():
                    best[name] = min(best[name], _timer(fn)[0])

    ours_total = sum(best[k] for k in ours)
    theirs_total = sum(best[k] for k in theirs)
    rows = [["swiftjax", k, f"{best[k] * 1e3:.2f}"] for k in ours]
    rows.append(["swiftjax", "**per step**", f"**{ours_total * 1e3:.2f}**"])
    rows += [["GTSAM", k, f"{best[k] * 1e3:.2f}"] for k in theirs]
    rows.append(["GTSAM", "**per iteration**", f"**{theirs_total * 1e3:.2f}**"])
    print(
        f"{args.graph}: N = {prob.num_nodes}, E = {prob.num_edges}, bucket {padded.num_nodes}/{padded.num_edges}, "
        f"CSC entries {pat.nnz}; best of {args.repeat}"
    )
    print(markdown_table(["solver", "piece", "ms"], rows))
    print(f"ratio per step ours/GTSAM: {ours_total / theirs_total:.3f}")
    path = write_results(
        "posegraph_step",
        dict(
            graph=args.graph,
            repeat=args.repeat,
            milliseconds={k: v * 1e3 for k, v in best.items()},
            ours_ms=ours_total * 1e3,
            gtsam_ms=theirs_total * 1e3,
            ratio=ours_total / theirs_total,
        ),
    )
    print(f"wrote {path.relative_to(REPO)}")


if __name__ == "__main__":
    main()

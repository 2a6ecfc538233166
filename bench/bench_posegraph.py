"""Benchmark: swiftjax's Sim(3) pose-graph LM vs GTSAM 4.3 LM on the same graphs, same run.

Graphs: the synthetic circle (N nodes, N odometry + N random loop edges, sigma = 0.05 / 0.01 /
0.01) at N = 100, 1,000, 5,000, 20,000; a KITTI-like chunk chain (N = 100 and 2,000, a loop
every 300 nodes); sphere2500 and parking-garage from ../shared lifted to Sim(3) (scale 1).
Both solvers use the same relative/absolute cost-decrease tolerances and iteration cap, in
float64.  "cost" columns are *our* cost function (identical to GTSAM's graph.error, see
tests/test_posegraph_gtsam.py) at each solver's optimum.  Timings are best of ``--repeat``, ours and
GTSAM's alternating; our compile time is the first call's (``Result.compile_seconds``).  ``--init`` picks the LM start:
the given poses (dead reckoning), or our chordal initialisation; GTSAM always starts from the same
poses as our LM, and on "chordal" rows its time includes our initialisation's (measured
separately, best of ``--repeat``), as ours does.

    .venv/bin/python bench/bench_posegraph.py [--quick] [--repeat 3] [--gtsam-max-nodes 5000]

Writes ``bench/results/posegraph-<timestamp>.json`` (temp file + rename).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import tempfile
import time

import jax
import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
jax.config.update("jax_compilation_cache_dir", os.environ.get("JAX_COMPILATION_CACHE_DIR", str(REPO / ".jax_cache")))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

from swiftjax import posegraph
from swiftjax.io.g2o import read_g2o
from swiftjax.synthetic.pose_graphs import chain_graph, circle_graph


def _graphs(quick: bool, shared: pathlib.Path | None):
    sizes = [100, 1000] if quick else [100, 1000, 5000, 20000]
    for n in sizes:
        g = circle_graph(n, seed=0)
        yield (
            f"circle N={n}",
            g.initial,
            g.edges,
            g.measurements,
            np.einsum("ei,ij->eij", g.information, np.eye(7)),
            np.arange(n) == 0,
        )
    for n in [100] if quick else [100, 2000]:
        g = chain_graph(n, loop_every=300 if n > 300 else 30, seed=0)
        yield (
            f"chain N={n}",
            g.initial,
            g.edges,
            g.measurements,
            np.einsum("ei,ij->eij", g.information, np.eye(7)),
            np.arange(n) == 0,
        )
    if shared is not None and not quick:
        for name in ["sphere2500", "parking-garage"]:
            g = read_g2o(shared / "data" / "posegraphs" / f"{name}.g2o")
            yield name, g.poses, g.edges, g.measurements, g.information, g.fixed


def _atomic_json(path: pathlib.Path, payload) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        json.dump(payload, fh, indent=2)
    os.replace(tmp, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="only the small graphs")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rtol", type=float, default=1e-5, help="GTSAM's default relativeErrorTol")
    ap.add_argument("--max-steps", type=int, default=100)
    ap.add_argument(
        "--gtsam-max-nodes",
        type=int,
        default=2500,
        help="skip GTSAM above this size (random loops make its Cholesky dense: N=1,000 already takes ~100 s)",
    )
    ap.add_argument("--only", default="", help="substring filter on graph names")
    ap.add_argument("--damping", default="identity", choices=["identity", "marquardt"])
    ap.add_argument(
        "--init",
        default="both",
        choices=["none", "chordal", "both"],
        help="LM start: the given poses (dead reckoning), our chordal initialisation, or one row of each "
        "(GTSAM always starts from the same poses as our LM: for 'chordal' it is handed our chordal start, free)",
    )
    ap.add_argument("--linear-solver", default="auto", choices=["auto", "dense", "pcg", "sparse"])
    args = ap.parse_args()
    shared_env = os.environ.get("SWIFTJAX_SHARED")
    shared = pathlib.Path(shared_env) if shared_env else REPO.parent / "shared"
    shared = shared if (shared / "data").is_dir() else None

    rows = []
    with jax.enable_x64(True):
        for name, poses, edges, meas, info, fixed in _graphs(args.quick, shared):
            if args.only and args.only not in name:
                continue
            prob = posegraph.Problem(poses, edges, meas, information=info, fixed=fixed)
            for init in ["none", "chordal"] if args.init == "both" else [args.init]:
                row = _bench_graph(args, name, prob, init)
                rows.append(row)
                _print_row(row)

    stamp = time.strftime("%Y%m%d-%H%M%S")
    _atomic_json(REPO / "bench" / "results" / f"posegraph-{stamp}.json", dict(args=vars(args), rows=rows))
    print()
    print(_markdown(rows))


def _bench_graph(args, name, prob, init):
    """One row: ours and GTSAM from the same LM start, alternating run by run (best of ``--repeat``
    each), so that both see the same machine load; ours includes its initialisation's time."""
    opts = dict(
        rtol=args.rtol,
        atol=0.0,
        max_steps=args.max_steps,
        damping=args.damping,
        linear_solver=args.linear_solver,
        initialization=init,
    )
    first = posegraph.optimize(prob, posegraph.GraphOptions(**opts))
    n = prob.num_nodes
    row = dict(
        graph=name,
        init=init,
        nodes=n,
        edges=prob.num_edges,
        solver=first.linear_solver,
        bucket=list(first.bucket),
        ours_compile_seconds=first.compile_seconds,
        ours_steps=first.num_steps,
        ours_linear_iterations=first.linear_iterations,
        ours_cost=first.cost_final,
        ours_converged=first.converged,
        ours_status=first.status,
        cost_initial=first.cost_initial,
        cost_start=first.cost_start,
    )
    with_gtsam = n <= args.gtsam_max_nodes
    if with_gtsam:
        from _gtsam_baseline import solve_gtsam

        from swiftjax.posegraph.initialization import chordal_initialization

        start, init_fn = prob.poses, None
        if init == "chordal":  # GTSAM starts from our chordal poses; their cost is added to its time
            init_fn = jax.jit(chordal_initialization, static_argnums=1)
            start, _ = jax.block_until_ready(init_fn(prob, first.linear_solver))
        np_args = [np.asarray(a) for a in (start, prob.edges, prob.measurements, prob.information, prob.fixed)]
    runs, g_runs, init_runs = [first.solve_seconds], [], []
    for k in range(args.repeat):
        if k > 0:
            runs.append(posegraph.optimize(prob, posegraph.GraphOptions(**opts)).solve_seconds)
        if not with_gtsam or (g_runs and min(g_runs) > 5.0):  # slow runs: once is enough for a ratio
            continue
        if init_fn is not None:
            t0 = time.perf_counter()
            jax.block_until_ready(init_fn(prob, first.linear_solver))
            init_runs.append(time.perf_counter() - t0)
        ref = solve_gtsam(*np_args, rtol=args.rtol, atol=0.0, max_iterations=args.max_steps)
        g_runs.append(ref.seconds)
    row["ours_seconds"] = min(runs)
    if with_gtsam:
        init_seconds = min(init_runs) if init_runs else 0.0
        cost_at_gtsam = float(posegraph.cost(jax.numpy.asarray(ref.poses), prob))
        row.update(
            gtsam_seconds=min(g_runs) + init_seconds,
            gtsam_lm_seconds=min(g_runs),
            init_seconds=init_seconds,
            gtsam_iterations=ref.iterations,
            gtsam_error=ref.error_final,
            gtsam_cost=cost_at_gtsam,
            time_ratio=min(runs) / (min(g_runs) + init_seconds),
            cost_rel_vs_gtsam=(first.cost_final - cost_at_gtsam) / cost_at_gtsam,
        )
    return row


def _print_row(r) -> None:
    g = (
        f"gtsam {r['gtsam_seconds']:.3f}s it={r['gtsam_iterations']} ratio={r['time_ratio']:.3f} "
        f"cost_rel={r['cost_rel_vs_gtsam']:+.2e}"
        if "gtsam_seconds" in r
        else "gtsam skipped"
    )
    print(
        f"{r['graph']:>18} [{r['init']:>7}]: ours {r['ours_seconds']:.3f}s (+{r['ours_compile_seconds']:.1f}s compile) "
        f"steps={r['ours_steps']} cg={r['ours_linear_iterations']} {r['solver']} cost={r['ours_cost']:.6f} | {g}",
        flush=True,
    )


def _markdown(rows) -> str:
    out = [
        "| graph | start | N | E | ours (s) | compile (s) | steps | GTSAM (s) | GTSAM iters | time ours/GTSAM | cost ours | cost GTSAM (our fn) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        has = "gtsam_seconds" in r
        gs = f"{r['gtsam_seconds']:.3f}" if has else "skipped"
        gi = str(r["gtsam_iterations"]) if has else ""
        ratio = f"{r['time_ratio']:.3f}" if has else ""
        gc = f"{r['gtsam_cost']:.6f}" if has else ""
        out.append(
            f"| {r['graph']} | {r['init']} | {r['nodes']} | {r['edges']} | {r['ours_seconds']:.3f} | {r['ours_compile_seconds']:.1f} | "
            f"{r['ours_steps']} | {gs} | {gi} | {ratio} | {r['ours_cost']:.6f} | {gc} |"
        )
    return "\n".join(out)


if __name__ == "__main__":
    main()

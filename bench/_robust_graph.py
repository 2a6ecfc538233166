"""Pose-graph level of the loop-robustness benchmark: false loop edges in a KITTI-like chunk graph.

``kitti_chunk_graph(route=..., generator=...)`` builds the same graph on KITTI 05 or 08 and with
the other kinds of false edges of :data:`GENERATORS` (``bench/bench_robust_backend.py`` runs them
all); what follows describes the default (KITTI 00, ``random``).

The graph: the KITTI 00 ground-truth trajectory (``$SWIFTJAX_SHARED/data/trajectories/KITTI_00_gt.txt``)
cut into the pipeline's chunk schedule (75 frames, overlap 30: 101 chunks), one Sim(3) node per
chunk (its first camera, with a log-scale random walk of 0.01 per chunk as VGGT's scale drift),
100 odometry edges ``(t, t+1)``, the 10 true loops (chunk pairs >= 8 chunks apart whose first
cameras are within 15 m, closest first, no chunk in two of them) and false loop edges at 50, 100 and
200 % of the true count: chunk pairs >= 150 m apart whose measurement says "same place" (identity
rotation and scale, translation ~ N(0, 2 m) — what a hallucinated loop chunk hands back).

Noise: every edge has its own level (``sigma_e = f_e (0.10 m, 0.005 rad, 0.005)``,
``f_e = exp(N(0, 0.5^2))``; loops twice that), like alignments with different point counts and
residuals.  Two information settings on the same measurements:

* ``matched`` — ``Omega_e = diag(sigma_e)^-2`` (what :mod:`swiftjax.align.covariance` aims at);
* ``equal`` — ``Omega_e = I`` (the authors' pose graph).

Solvers, each compared with the *same* setting's outlier-free solve (plain LM without the false
edges): our LM (no kernel), Cauchy and GNC-TLS on the loop edges (``posegraph.optimize(problem, GraphOptions(kernel=...))``),
GTSAM 4.3's ``LevenbergMarquardtOptimizer`` and ``GncLMOptimizer`` (TLS, odometry as known inliers)
on the same graphs.  Thresholds: ``matched`` — ``c = sqrt(chi2_7^-1(0.99)) = 4.30`` (GTSAM's default
inlier probability 0.99); ``equal`` — the inlier level, ``c = 3 x`` the largest true-loop residual norm
``|r|`` of the outlier-free equal-weight solve (for a user who knows the residual level; with unit
weights no chi-squared reading exists).  Cauchy uses the same ``c``.  Distance: largest node
translation from the outlier-free answer as a percentage of the trajectory's extent (bounding-box
diagonal), and the RMS over nodes.  Times: best of ``repeat`` warm solves, our three solvers
alternating (compile excluded); GTSAM's best of ``repeat`` after them.

    python bench/_robust_graph.py [--repeat 3] [--seed 0]        # table + bench/results/robust_graph-*.json

``run(...)`` is what ``bench/bench_loop_robustness.py`` calls.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time

import jax
import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from swiftjax import posegraph, sim3
from swiftjax.posegraph import gnc

__all__ = ["kitti_chunk_graph", "clean_solve", "run", "markdown", "main"]

CHUNK, OVERLAP = 75, 30
NUM_TRUE = 10
LEVELS = (0.5, 1.0, 2.0)
NOISE = np.array([0.10, 0.10, 0.10, 0.005, 0.005, 0.005, 0.005])


def _shared(shared_dir=None, route: str = "00") -> pathlib.Path:
    for c in [shared_dir, os.environ.get("SWIFTJAX_SHARED"), REPO.parent / "shared", "/work/shared"]:
        if c and (pathlib.Path(c) / "data" / "trajectories" / f"KITTI_{route}_gt.txt").is_file():
            return pathlib.Path(c)
    raise SystemExit(f"KITTI_{route}_gt.txt not found: set SWIFTJAX_SHARED to the folder holding data/")


def _true_loops(
    pos: np.ndarray, num: int, min_sep: int = 8, radius: float = 15.0, minimum: int = 5
) -> list[tuple[int, int]]:
    """Up to ``num`` (at least ``minimum``) revisit pairs ``(a, b)``, ``b - a >= min_sep``, first
    cameras within ``radius``: the closest pair first, then greedily those sharing no chunk with a
    chosen one."""
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    a, b = np.nonzero((np.subtract.outer(np.arange(len(pos)), np.arange(len(pos))) <= -min_sep) & (d < radius))
    order = np.argsort(d[a, b])
    chosen: list[tuple[int, int]] = []
    for k in order:
        i, j = int(a[k]), int(b[k])
        if all(j != q and i != p for p, q in chosen):
            chosen.append((i, j))
        if len(chosen) == num:
            break
    if len(chosen) < minimum:
        raise RuntimeError(f"only {len(chosen)} true loops found in the chunk graph")
    return sorted(chosen)


#: Kinds of false loop edges (``kitti_chunk_graph(generator=...)``).
GENERATORS = ("random", "clustered", "slight", "gauge")
CLUSTER = NUM_TRUE // 2  # false edges per look-alike cluster: half the true loops


def _same_place(rng, k: int) -> np.ndarray:
    """``k`` hallucinated "same place" edges: identity rotation and scale, translation ~ N(0, 2 m)."""
    out = np.zeros((k, 8))
    out[:, :3] = rng.normal(size=(k, 3)) * 2.0
    out[:, 6:8] = 1.0
    return out


def _false_random(rng, truth, d, taken, count):
    """Random chunk pairs >= 150 m apart, each saying "same place" (independent of each other)."""
    n, pairs = len(truth), []
    while len(pairs) < count:
        i, j = sorted(int(v) for v in rng.integers(0, n, 2))
        if j - i >= 8 and d[i, j] > 150 and (i, j) not in taken:
            taken.add((i, j))
            pairs.append((i, j))
    return pairs, _same_place(rng, count), False


def _false_clustered(rng, truth, d, taken, count):
    """Look-alike streets: clusters of :data:`CLUSTER` edges ``(a + i, b + i)`` between two regions
    >= 150 m apart, the first saying "same place" (``Z_0``), the others what the same wrong world
    motion ``W = S_a Z_0 S_b^-1`` implies (``Z_i = S_{a+i}^-1 W S_{b+i}``): mutually consistent."""
    n, pairs, meas = len(truth), [], []
    with jax.enable_x64(True):
        while len(pairs) < count:
            k = min(CLUSTER, count - len(pairs))
            a, b = sorted(int(v) for v in rng.integers(0, n - k + 1, 2))
            cand = [(a + i, b + i) for i in range(k)]
            if b - a < 8 + k or any(d[p, q] <= 150 or (p, q) in taken for p, q in cand):
                continue
            z0 = _same_place(rng, 1)[0]
            W = sim3.compose(sim3.compose(truth[a], z0), sim3.inverse(truth[b]))
            for p, q in cand:
                taken.add((p, q))
                pairs.append((p, q))
                meas.append(np.asarray(sim3.compose(sim3.inverse(truth[p]), sim3.compose(W, truth[q])), np.float64))
    return pairs, np.stack(meas), True


def _revisit_pairs(rng, d, taken, count):
    """``count`` revisit pairs (>= 8 chunks apart) drawn among the nearest ``3 count`` not in
    ``taken`` (chunk distances ``d``), added to ``taken``."""
    n = len(d)
    a, b = np.nonzero(np.subtract.outer(np.arange(n), np.arange(n)) <= -8)
    order = [(int(a[k]), int(b[k])) for k in np.argsort(d[a, b]) if (int(a[k]), int(b[k])) not in taken]
    pick = rng.choice(min(3 * count, len(order)), count, replace=False)
    pairs = [order[k] for k in sorted(pick)]
    taken.update(pairs)
    return pairs


def _false_slight(rng, truth, d, taken, count):
    """Slightly wrong loops: revisit pairs (>= 8 chunks apart, chosen among the nearest ``3 count``
    not taken) whose measurement is the true relative pose times an error of 2-5 m and 2-5 degrees
    (random directions)."""
    pairs = _revisit_pairs(rng, d, taken, count)
    unit = rng.normal(size=(2, count, 3))
    unit /= np.linalg.norm(unit, axis=-1, keepdims=True)
    err = np.zeros((count, 7))
    err[:, :3] = unit[0] * rng.uniform(2.0, 5.0, (count, 1))
    err[:, 3:6] = unit[1] * np.deg2rad(rng.uniform(2.0, 5.0, (count, 1)))
    with jax.enable_x64(True):
        p, q = np.array(pairs).T
        rel = sim3.compose(sim3.between(truth[p], truth[q]), sim3.exp(err))
    return pairs, np.asarray(rel, np.float64), True


def _false_gauge(rng, truth, d, taken, count):
    """Loops with a wrong gauge (added after the back end was designed, held out from its tuning):
    revisit pairs chosen as :func:`_false_slight`'s whose measurement is the true relative pose
    ``(t, R, s)`` seen through a loop chunk normalised to the wrong scale, ``(g t, R ΔR, g s)``,
    ``log g = ±U(0.1, 0.3)`` (10-35 %), ``ΔR`` a rotation of 1-3 degrees about a random axis."""
    pairs = _revisit_pairs(rng, d, taken, count)
    g = np.exp(rng.choice([-1.0, 1.0], count) * rng.uniform(0.1, 0.3, count))
    axis = rng.normal(size=(count, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    err = np.zeros((count, 7))
    err[:, 3:6] = axis * np.deg2rad(rng.uniform(1.0, 3.0, (count, 1)))
    with jax.enable_x64(True):
        p, q = np.array(pairs).T
        rel = np.array(sim3.compose(sim3.between(truth[p], truth[q]), sim3.exp(err)), np.float64)
        rel[:, :3] *= g[:, None]
        rel[:, 7] *= g
    return pairs, rel, True


def kitti_chunk_graph(
    shared_dir=None, *, seed: int = 0, max_false: int = 20, route: str = "00", generator: str = "random"
) -> dict:
    """The chunk graph of KITTI ``route`` with a pool of ``max_false`` false loops of one
    ``generator`` (:data:`GENERATORS`; levels take its first ``k``).  ``num_true``: the true
    loops found (:data:`NUM_TRUE`, or fewer on a route with fewer disjoint revisits: 9 on KITTI 08)."""
    from swiftjax.io.trajectory import read_kitti

    make = {"random": _false_random, "clustered": _false_clustered, "slight": _false_slight, "gauge": _false_gauge}[
        generator
    ]
    with jax.enable_x64(True):
        P = read_kitti(_shared(shared_dir, route) / "data" / "trajectories" / f"KITTI_{route}_gt.txt")
        rng = np.random.default_rng(seed)
        starts = np.arange(0, len(P) - OVERLAP, CHUNK - OVERLAP)
        starts = starts[starts + OVERLAP < len(P)][:101]
        n = len(starts)
        R, t = P[starts, :3, :3], P[starts, :3, 3]
        log_s = np.concatenate([[0.0], np.cumsum(0.01 * rng.normal(size=n - 1))])
        truth = np.asarray(sim3.from_rst(R, t, np.exp(log_s)), np.float64)
        odo = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
        loops = np.array(_true_loops(t, NUM_TRUE))
        d = np.linalg.norm(t[:, None] - t[None], axis=-1)
        taken = {tuple(e) for e in np.concatenate([odo, loops]).tolist()}
        false, claimed, noisy = make(rng, truth, d, taken, max_false)
        edges = np.concatenate([odo, loops, np.array(false, np.int64).reshape(-1, 2)]).astype(np.int64)
        kind = np.array(["odometry"] * len(odo) + ["loop"] * len(loops) + ["false"] * len(false))
        sigma = NOISE[None] * np.exp(0.5 * rng.normal(size=(len(edges), 1)))
        sigma[kind != "odometry"] *= 2.0
        rel = np.array(sim3.between(truth[edges[:, 0]], truth[edges[:, 1]]), np.float64)
        rel[kind == "false"] = claimed
        noise = sim3.exp(rng.normal(size=(len(edges), 7)) * sigma)
        meas = np.array(sim3.compose(rel, noise), np.float64)
        if not noisy:  # a hallucinated "same place" is the measurement itself
            meas[kind == "false"] = claimed
        init = np.zeros_like(truth)
        init[0] = truth[0]
        for k in range(1, n):
            init[k] = np.asarray(sim3.normalize(sim3.compose(init[k - 1], meas[k - 1])), np.float64)
    extent = float(np.linalg.norm(t.max(0) - t.min(0)))
    return dict(
        truth=truth,
        initial=init,
        edges=edges,
        measurements=meas,
        sigma=sigma,
        kind=kind,
        extent=extent,
        starts=starts,
        route=route,
        generator=generator,
        num_true=len(loops),
    )


def _subgraph(g: dict, num_false: int, information: str):
    keep = g["kind"] != "false"
    keep[np.nonzero(g["kind"] == "false")[0][:num_false]] = True
    info = 1.0 / g["sigma"][keep] ** 2 if information == "matched" else np.ones((int(keep.sum()), 7))
    return g["edges"][keep], g["measurements"][keep], info, g["kind"][keep]


def clean_solve(g: dict, information: str):
    """``(outlier-free solve, GNC threshold c)`` of one information setting (module docstring);
    call under ``jax.enable_x64(True)``."""
    edges, meas, info, kind = _subgraph(g, 0, information)
    clean_prob = posegraph.Problem(g["initial"], edges, meas, information=info)
    clean = posegraph.optimize(clean_prob, posegraph.GraphOptions(rtol=1e-12))
    if information == "matched":
        return clean, gnc.DEFAULT_SCALE
    r = np.asarray(posegraph.residuals(clean.poses, clean_prob))
    return clean, 3.0 * float(np.linalg.norm(r[kind == "loop"], axis=1).max())


def _distances(poses, clean, extent):
    d = np.linalg.norm(np.asarray(poses)[:, :3] - np.asarray(clean)[:, :3], axis=1)
    return 100 * d.max() / extent, 100 * np.sqrt(np.mean(d**2)) / extent


def _alternating(prob, options: list[dict], repeat: int):
    """Best-of-``repeat`` result per option set, the solvers alternating (compiled once first)."""
    best = [
        posegraph.optimize(prob, posegraph.GraphOptions(**kw), throw=False) for kw in options
    ]  # LM on false loops may not converge
    for _ in range(repeat):
        for k, kw in enumerate(options):
            r = posegraph.optimize(prob, posegraph.GraphOptions(**kw), throw=False)
            best[k] = r if r.solve_seconds < best[k].solve_seconds else best[k]
    return best


def _gtsam(g, edges, meas, info, kind, repeat, c=None):
    """GTSAM LM (``c`` None) or GncLMOptimizer (TLS, threshold ``c``, odometry known inliers)."""
    import gtsam
    from _gtsam_baseline import build_graph, from_gtsam

    n = len(g["initial"])
    fixed = np.arange(n) == 0
    full = np.einsum("ei,ij->eij", info, np.eye(7))
    best_t, out, weights = np.inf, None, None
    for _ in range(max(repeat, 1)):
        graph, values = build_graph(g["initial"], edges, meas, full, fixed)
        lm = gtsam.LevenbergMarquardtParams()
        lm.setRelativeErrorTol(1e-5)
        lm.setAbsoluteErrorTol(1e-5)
        lm.setMaxIterations(100)
        t0 = time.perf_counter()
        if c is None:
            opt = gtsam.LevenbergMarquardtOptimizer(graph, values, lm)
            res = opt.optimize()
        else:
            params = gtsam.GncLMParams(lm)
            params.setLossType(gtsam.GncLossType.TLS)
            # factor 0 is node 0's NonlinearEquality (no noise model); the edges follow in order
            params.setKnownInliers([0] + [1 + k for k in np.nonzero(kind == "odometry")[0].tolist()])
            params.setAllowNonNoiseModelFactors(True)
            opt = gtsam.GncLMOptimizer(graph, values, params)
            opt.setInlierCostThresholds(0.5 * c * c)  # GTSAM's factor error is r^T Omega r / 2
            res = opt.optimize()
        dt = time.perf_counter() - t0
        if dt < best_t:
            best_t = dt
            out = np.stack([from_gtsam(res.atSimilarity3(k)) for k in range(n)])
            weights = None if c is None else np.asarray(opt.getWeights())[1:]
    return out, best_t, weights


def run(shared_dir=None, *, levels=LEVELS, seed: int = 0, repeat: int = 3, with_gtsam: bool = True) -> dict:
    """Every (information, false-loop level, solver) row; ``markdown(result)`` renders them."""
    g = kitti_chunk_graph(shared_dir, seed=seed, max_false=int(round(max(levels) * NUM_TRUE)))
    rows = []
    with jax.enable_x64(True):
        for information in ("matched", "equal"):
            clean, c = clean_solve(g, information)
            for level in levels:
                num_false = int(round(level * NUM_TRUE))
                edges, meas, info, kind = _subgraph(g, num_false, information)
                prob = posegraph.Problem(g["initial"], edges, meas, information=info, robust=kind != "odometry")
                solvers = (
                    ("LM", {}),
                    ("Cauchy", dict(kernel="cauchy", kernel_scale=c)),
                    ("GNC", dict(kernel="gnc", kernel_scale=c)),
                )
                best = _alternating(prob, [kw for _, kw in solvers], repeat)
                base = None
                for (solver, kw), res in zip(solvers, best):
                    dmax, drms = _distances(res.poses, clean.poses, g["extent"])
                    w = res.inlier_weights
                    base = res.solve_seconds if solver == "LM" else base
                    rows.append(
                        dict(
                            information=information,
                            false_loops=num_false,
                            level=level,
                            solver=f"ours {solver}",
                            threshold=c if kw else None,
                            dist_max_pct=dmax,
                            dist_rms_pct=drms,
                            seconds=res.solve_seconds,
                            x_lm=res.solve_seconds / base,
                            converged=res.converged,
                            steps=res.num_steps,
                            gnc_iterations=res.gnc_iterations,
                            false_rejected=int(np.sum(w[kind == "false"] < 0.5)),
                            true_kept=int(np.sum(w[kind == "loop"] >= 0.5)),
                        )
                    )
                if with_gtsam:
                    for solver, cc in (("LM", None), ("GncLM (TLS)", c)):
                        poses, secs, w = _gtsam(g, edges, meas, info, kind, repeat, cc)
                        dmax, drms = _distances(poses, clean.poses, g["extent"])
                        rows.append(
                            dict(
                                information=information,
                                false_loops=num_false,
                                level=level,
                                solver=f"GTSAM {solver}",
                                threshold=cc,
                                dist_max_pct=dmax,
                                dist_rms_pct=drms,
                                seconds=secs,
                                x_lm=secs / base,
                                converged=None,
                                steps=None,
                                gnc_iterations=None,
                                false_rejected=None if w is None else int(np.sum(w[kind == "false"] < 0.5)),
                                true_kept=None if w is None else int(np.sum(w[kind == "loop"] >= 0.5)),
                            )
                        )
    return dict(
        rows=rows,
        num_nodes=len(g["truth"]),
        num_true_loops=NUM_TRUE,
        extent_m=g["extent"],
        seed=seed,
        repeat=repeat,
        load_average=os.getloadavg(),
    )


def markdown(result: dict) -> str:
    head = (
        "| information | false loops | solver | max dist % extent | RMS dist % | time ms | × our LM "
        "| false rejected | true kept |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |"
    )
    lines = [head]
    for r in result["rows"]:
        opt = lambda v: "–" if v is None else str(v)
        lines.append(
            f"| {r['information']} | {r['false_loops']} ({100 * r['level']:.0f} %) | {r['solver']} "
            f"| {r['dist_max_pct']:.3f} | {r['dist_rms_pct']:.3f} | {1e3 * r['seconds']:.1f} | {r['x_lm']:.2f} "
            f"| {opt(r['false_rejected'])} | {opt(r['true_kept'])} |"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-gtsam", action="store_true")
    args = ap.parse_args(argv)
    from common import write_results

    result = run(seed=args.seed, repeat=args.repeat, with_gtsam=not args.no_gtsam)
    print(markdown(result))
    print(write_results("robust_graph", result))


if __name__ == "__main__":
    main()

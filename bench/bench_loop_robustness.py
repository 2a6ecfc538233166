"""Loop closure under perceptual aliasing: our verified loops against the authors' rule.

Routes: the demo route (``swiftjax demo``) and synthetic KITTI 00, both through the oracle
that fails like VGGT (a loop chunk whose halves share no view comes back superimposed), with
look-alike place pairs planted at ``--levels`` (0, 0.1, 0.3, 0.5: that many extra false
candidates per true loop chunk pair, :func:`swiftjax.synthetic.places.plant_aliasing`).

For each route and level the pipeline runs ONCE with the default configuration (geometric
verification, :mod:`swiftjax.loops.verification`, and the default pose graph); the other arms
reuse that run's candidates, their loop edges and the temporal chain (same run, same numbers):

* ``ours``: the pipeline's own result (accepted candidates only, the default kernel);
* ``authors``: every candidate above the threshold is an edge, equal weights, no kernel
  (SwiftVGGT's rule, ``loop_verification = "none"``, ``robust_loops = None``);
* ``verified, plain``: the accepted candidates with no kernel (verification alone);
* ``truth filter``: exactly the true candidates (by ground truth), no kernel: what a perfect
  verifier achieves with this run's candidates.  Planted look-alike tokens may sit inside a
  true loop region and move the detector onto other true pairs, so the alias-free run's ATE
  is not always reachable by any verifier; this arm separates that from verification.

* ``fixed 0.55, plain``: the same records re-decided with the fixed dense bound
  (``agreement_rule = "fixed"``, the rule the per-candidate null test replaced), no kernel;
  against ``verified, plain`` (the null test, the default) it isolates the dense rule.

Routes ``kitti05``, ``kitti06``, ``kitti08`` (ground truth from ``$SWIFTJAX_SHARED``) run
through :func:`swiftjax.synthetic.demo.trajectory_run` with the same aliasing levels.  A second table
gives per route and level the true candidates the truth filter keeps, how many of them and
how many false ones each dense rule accepts, and both rules' ATE.

Per arm: candidates, accepted, precision (accepted candidates that are true revisits,
:func:`~swiftjax.synthetic.places.evaluate_loops`, ±25 frames), recall of the ground-truth
loop regions (:func:`~swiftjax.synthetic.places.ground_truth_loops`, 5 m / 30°), and ATE
(Sim(3)-aligned, metres).  The ATE ratio is against the same arm's alias-free run.  Every
candidate's dense numbers are written with its truth label (the distributions the
verification thresholds were chosen from).  The pose-graph-level section comes from
``bench/_robust_graph.py`` when present (``run(repeat=...)``, rendered by its ``markdown``;
the candidate-level JSON is written first).

    python bench/bench_loop_robustness.py [--routes demo kitti00] [--levels 0 0.1 0.3 0.5]
        [--kitti-levels 0 0.3]   # KITTI 00 at fewer levels on a loaded machine
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from bench_pipeline import _shared
from common import markdown_table, reconstruct, write_results

HERE = pathlib.Path(__file__).resolve().parent


ROUTES = ("demo", "kitti00", "kitti05", "kitti06", "kitti08")


def _make_run(route: str, level: float):
    from swiftjax.io.trajectory import read_kitti
    from swiftjax.synthetic import demo

    if route == "demo":
        return demo.loop_route_run(aliasing=level)
    if route == "kitti00":
        return demo.kitti00_run(_shared(), aliasing=level)
    poses = read_kitti(_shared() / "data" / "trajectories" / f"KITTI_{route[-2:]}_gt.txt")
    return demo.trajectory_run(poses, name=route, aliasing=level)


def fixed_verdicts(cands: list[dict], relative: np.ndarray) -> list[bool]:
    """Each candidate's verdict under the fixed dense bound (``agreement_rule = "fixed"``,
    0.55) from the same records' numbers: the rule the null test replaced."""
    from swiftjax.loops import verification as lv
    from swiftjax.posegraph import chain_poses

    rows = [k for k, r in enumerate(cands) if "Z" in r and "dense_agreement" in r]
    out = [False] * len(cands)
    decisions = lv.verify_candidates(
        [cands[k] for k in rows], chain_poses(relative), relative, lv.VerificationConfig(agreement_rule="fixed")
    )
    for k, d in zip(rows, decisions):
        out[k] = d.accepted
    return out


def graph_poses(
    relative: np.ndarray, loop_edges: list[tuple[int, int, np.ndarray]], max_steps: int, throw: bool = True
) -> tuple[np.ndarray, bool]:
    """Chunk poses of the temporal chain plus ``loop_edges`` ``(a, b, Z)``: plain LM, equal
    weights, no kernel; ``(poses [T, 8], converged)``.  ``throw=False``: a graph that did not
    converge in ``max_steps`` keeps its last iterate and says so instead of raising."""
    from swiftjax import posegraph, sim3
    from swiftjax.posegraph import chain_poses

    chain = chain_poses(relative)
    if not loop_edges:
        return chain, True
    T = len(chain)
    edges = [(t, t + 1) for t in range(T - 1)] + [(a, b) for a, b, _ in loop_edges]
    meas = np.concatenate([relative, np.stack([z for _, _, z in loop_edges])])
    with jax.enable_x64(True):
        problem = posegraph.Problem(jnp.asarray(chain), np.asarray(edges, np.int32), jnp.asarray(meas))
        res = posegraph.optimize(problem, posegraph.GraphOptions(max_steps=max_steps), throw=throw)
        return np.asarray(sim3.normalize(res.poses), np.float64), bool(res.converged)


def _centres(result, schedule, chunk_poses: np.ndarray) -> np.ndarray:
    """Camera centres ``[N, 3]`` under other chunk poses: each frame's centre in its owner
    chunk's coordinates (recovered from the run's chained poses) mapped by ``chunk_poses``."""
    from swiftjax import sim3

    owner = np.searchsorted(schedule.starts, np.arange(result.num_frames), side="right") - 1
    with jax.enable_x64(True):
        local = sim3.act(
            sim3.inverse(jnp.asarray(result.chunk_poses_no_loops[owner])),
            jnp.asarray(result.cam_to_world_no_loops[:, :3, 3]),
        )
        return np.asarray(sim3.act(jnp.asarray(chunk_poses[owner]), local))


def run_level(route: str, level: float, out_dir: pathlib.Path) -> dict:
    from swiftjax import chunks, evaluation, pipeline
    from swiftjax.synthetic import places

    run = _make_run(route, level)
    config = pipeline.PipelineConfig()
    t0 = time.perf_counter()
    load = os.getloadavg()
    res = reconstruct(run, out_dir, config)
    wall = time.perf_counter() - t0
    schedule = chunks.chunk_schedule(res.num_frames, config.chunk_size, config.overlap)
    gt = run.ground_truth[:, :3, 3]
    gt_pairs = places.ground_truth_loops(run.ground_truth, min_separation=config.loop_min_separation)
    relative = _relative(out_dir, schedule.num_chunks)
    cands = res.loop_candidates
    with_edge = [r for r in cands if "Z" in r]
    truth = places.evaluate_loops(
        np.asarray([(r["i"], r["j"]) for r in cands], np.int64).reshape(-1, 2), gt_pairs, tolerance=25
    )
    fixed = fixed_verdicts(cands, relative)
    arms = {
        "ours": [r for r in cands if r["accepted"]],
        "authors": with_edge,
        "verified, plain": [r for r in cands if r["accepted"]],
        "fixed 0.55, plain": [r for r, ok in zip(cands, fixed) if ok],
        "truth filter": [r for r, ok in zip(cands, truth.correct) if ok and "Z" in r],
    }
    out = {
        "route": route,
        "level": level,
        "planted_pairs": [list(s) for s in run.aliasing],
        "frames": res.num_frames,
        "chunks": res.num_chunks,
        "wall_seconds": wall,
        "load_average_before": load,
        "candidates": len(cands),
        "true_candidates": int(truth.n_correct),
        "gt_regions": int(truth.n_regions),
        "regions_proposed": int(truth.n_regions_found),
        "arms": {},
    }
    for name, chosen in arms.items():
        ev = places.evaluate_loops(
            np.asarray([(r["i"], r["j"]) for r in chosen], np.int64).reshape(-1, 2), gt_pairs, tolerance=25
        )
        if name == "ours":
            ate = float(res.metrics["ate_rmse"])
        else:
            poses, _ = graph_poses(
                relative,
                [(r["chunk_j"], r["chunk_i"], np.asarray(r["Z"])) for r in chosen],
                config.max_lm_steps,
                throw=False,
            )
            ate = float(evaluation.ate(_centres(res, schedule, poses), gt).rmse)
        out["arms"][name] = {
            "accepted": len(chosen),
            "correct": int(ev.n_correct),
            "precision": ev.precision,
            "region_recall": ev.region_recall,
            "regions_found": int(ev.n_regions_found),
            "ate_rmse": ate,
        }
    out["ate_rmse_no_loops"] = float(res.metrics["ate_rmse_no_loops"])
    # the dense agreement's rule: null test (the run's) against the fixed 0.55, same records
    keep = [bool(ok) and "Z" in r for r, ok in zip(cands, truth.correct)]
    out["agreement_rules"] = {
        rule: {
            "true_accepted": sum(a and k for a, k in zip(acc, keep)),
            "truth_filter": sum(keep),
            "false_accepted": sum(a and not ok for a, ok in zip(acc, truth.correct)),
        }
        for rule, acc in (("null", [r["accepted"] for r in cands]), ("fixed", fixed))
    }
    out["candidate_records"] = [
        {
            "i": r["i"],
            "j": r["j"],
            "score": r["score"],
            "true": bool(c),
            "distance_m": float(np.linalg.norm(gt[r["i"]] - gt[r["j"]])),
            "accepted": r["accepted"],
            "reason": r["reason"],
            "accepted_fixed": f,
            **{
                k: r.get(k)
                for k in (
                    "dense_agreement",
                    "dense_overlap",
                    "null_mean",
                    "null_std",
                    "null_threshold",
                    "null_kappa",
                    "quality_min_fraction",
                    "pcm_residual",
                )
            },
        }
        for r, c, f in zip(cands, truth.correct, fixed)
    ]
    return out


def _relative(run_dir: pathlib.Path, T: int) -> np.ndarray:
    import json

    m = json.loads((run_dir / "manifest.json").read_text())
    return np.asarray([m["edges"][str(t)]["S"] for t in range(T - 1)], np.float64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--routes", nargs="+", default=["demo", "kitti00"], choices=ROUTES)
    parser.add_argument("--levels", type=float, nargs="+", default=[0.0, 0.1, 0.3, 0.5])
    parser.add_argument(
        "--kitti-levels", type=float, nargs="+", default=None, help="levels for KITTI 00 (default: --levels)"
    )
    parser.add_argument("--quick-graph", action="store_true", help="one repetition in the pose-graph section")
    parser.add_argument("--skip-graph", action="store_true", help="no pose-graph section (bench/_robust_graph.py)")
    args = parser.parse_args()

    jax.config.update(
        "jax_compilation_cache_dir",
        os.environ.get("SWIFTJAX_CACHE_DIR", str(pathlib.Path.home() / ".cache" / "swiftjax" / "jax")),
    )
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        for route in args.routes:
            levels = args.kitti_levels if (route == "kitti00" and args.kitti_levels) else args.levels
            for level in levels:
                rec = run_level(route, level, pathlib.Path(tmp) / f"{route}-{level}")
                records.append(rec)
                o = rec["arms"]["ours"]
                a = rec["arms"]["authors"]
                print(
                    f"{route} aliasing {level:.0%}: {rec['candidates']} candidates ({rec['true_candidates']} true); "
                    f"ours {o['accepted']} accepted, precision {o['precision']:.2f}, recall {o['region_recall']:.2f}, "
                    f"ATE {o['ate_rmse']:.3f} m; authors precision {a['precision']:.2f}, ATE {a['ate_rmse']:.3f} m "
                    f"({rec['wall_seconds']:.0f} s, load {rec['load_average_before'][0]:.1f})",
                    flush=True,
                )
    # ATE relative to the same arm's alias-free run
    base = {(r["route"], k): r["arms"][k]["ate_rmse"] for r in records if r["level"] == 0 for k in r["arms"]}
    rows = []
    for r in records:
        for k, a in r["arms"].items():
            b = base.get((r["route"], k))
            a["ate_ratio_to_alias_free"] = a["ate_rmse"] / b if b else None
            rows.append(
                [
                    r["route"],
                    f"{r['level']:.0%}",
                    k,
                    r["candidates"],
                    r["true_candidates"],
                    a["accepted"],
                    f"{a['precision']:.2f}",
                    f"{a['regions_found']}/{r['gt_regions']}",
                    f"{a['ate_rmse']:.3f}",
                    "-" if a["ate_ratio_to_alias_free"] is None else f"{a['ate_ratio_to_alias_free']:.2f}",
                ]
            )
    table = markdown_table(
        [
            "route",
            "aliasing",
            "rule",
            "candidates",
            "true cand.",
            "accepted",
            "precision",
            "regions found",
            "ATE (m)",
            "ATE / alias-free",
        ],
        rows,
    )
    print(table)
    # the dense agreement's rule: true candidates the truth filter keeps that each rule accepts
    rule_rows = []
    for r in records:
        n, f = r["agreement_rules"]["null"], r["agreement_rules"]["fixed"]
        ate = lambda k: r["arms"][k]["ate_rmse"]
        rule_rows.append(
            [
                r["route"],
                f"{r['level']:.0%}",
                r["candidates"],
                n["truth_filter"],
                f"{f['true_accepted']} / {f['false_accepted']}",
                f"{n['true_accepted']} / {n['false_accepted']}",
                f"{ate('fixed 0.55, plain'):.3f}",
                f"{ate('verified, plain'):.3f}",
                f"{100 * (ate('verified, plain') / ate('fixed 0.55, plain') - 1):+.1f} %",
            ]
        )
    rule_table = markdown_table(
        [
            "route",
            "aliasing",
            "candidates",
            "true (truth filter)",
            "fixed 0.55: true / false acc.",
            "null: true / false acc.",
            "ATE fixed (m)",
            "ATE null (m)",
            "null vs fixed",
        ],
        rule_rows,
    )
    print(rule_table)
    # dense-score distributions (the verification thresholds)
    dist = {"true": [], "false": []}
    for r in records:
        for c in r["candidate_records"]:
            if c["dense_agreement"] is not None:
                dist["true" if c["true"] else "false"].append(c["dense_agreement"])
    summary = {k: ({"n": len(v), "min": min(v), "max": max(v)} if v else {"n": 0}) for k, v in dist.items()}
    print("dense agreement of candidates:", summary)
    payload = {"records": records, "table": table, "rule_table": rule_table, "dense_agreement": summary}
    path = write_results("loop_robustness", payload)
    print(f"wrote {path}")
    if (HERE / "_robust_graph.py").exists() and not args.skip_graph:
        sys.path.insert(0, str(HERE))
        import _robust_graph

        graph = _robust_graph.run(repeat=1 if args.quick_graph else 3)
        print(_robust_graph.markdown(graph))
        payload["pose_graph"] = graph
        path = write_results("loop_robustness", payload)
        print(f"wrote {path} (with the pose-graph section)")


if __name__ == "__main__":
    main()

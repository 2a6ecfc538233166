"""Online reconstruction (issue 30, section 4): a synthetic drive replayed at 10 Hz through the
live engine (:class:`swiftjax.pipeline.engine.Reconstruction`).

The predictor is the synthetic oracle at a fixed cost per chunk (the GPU stand-in of
``bench_scaleout.py``: ``--cost`` seconds per prediction in all, the oracle's own time
included; the oracle is warmed up before the clock starts, and its slowest chunk is reported:
above ``--cost`` the cost is not fixed).  Frame ``k`` arrives at ``t0 + k / fps`` whether or not
the engine is busy (a car does not wait).  Measured per route and cost:

* per frame, the latency from its arrival to its first published pose (p50 / p95 / max), and
  the target ``(B - O) / fps + 1.5 x (cost + geometry of one step)``: one step's time is the
  median over the live steps of the time from a chunk's completion to its frames' poses
  (``Reconstruction.steps``' ``pose_s``); the first step's (JIT compiles included) is reported
  too (``latency_target_first_step_s``, the definition of the first version of this bench);
  ``latency_p95_steady_s``: the p95 over the frames the live steps posed after the first chunk
  (whose frames wait ``B`` frame periods, not ``B - O``); the frames after the last chunk
  boundary are posed by the short last chunk's live step when the input ends;
* the latency from a revisit to the loop's closure, in chunk periods (``B - O`` frames): the
  frames posed when the first loop-closure revision was published (the loop worker's, polled at
  every frame's arrival) minus the frames posed when the revisit's later frame was first posed;
  and in seconds from that first pose;
* the number of revisions, the live trajectory's ATE (Sim(3)) against the ground truth at
  every chunk, at the end of the drive before the final pass (as published when the last frame
  arrives: ``live_ate_m``; two chunk periods later, the loop-closure target's allowance, since
  a loop revisited in the last chunk cannot be closed before the last frame arrives:
  ``live_ate_2_periods_m``; once the loop worker has verified every proposal:
  ``live_ate_drained_m``; every frame's latest live pose when the final pass begins, the
  short last chunk's frames included: ``live_ate_end_m``), and the offline run's;
* the driver's resident memory at every live step (``steps[k]["rss_mb"]``), a quarter of the way
  through and at the end (memory flat in the sequence length, but for compiled programs), and
  what of it is data: the live JAX arrays' bytes (``jax_live_mb``) and, with
  ``--trace-memory`` (Python's ``tracemalloc``: slower, so its latencies are not the table's),
  the Python heap (``py_heap_mb``);
* the finished run compared with an offline ``reconstruct`` of the same frames: the poses
  bit for bit and every output file byte for byte (except ``metrics.json``'s timings,
  ``manifest.json`` and the chunk store's ``.npz`` zip headers).

The engine's stages are incremental: each chunk is predicted once and aligned with the one
before, its frames posed at once; loop detection, loop chunks and the pose graph run on the
engine's loop worker (:mod:`swiftjax.pipeline.engine`).  ``--warmup`` replays the route once,
untimed, before the timed arms (the JIT caches filled, as a vehicle's computer would be before
the drive); without it the first arm of the process includes the compiles.

    python bench/bench_online.py                # demo route and synthetic KITTI 00, costs 0.5 s and 2 s
    python bench/bench_online.py --quick        # demo route, 90 frames, 0.5 s (a few minutes on a CPU)
    python bench/bench_online.py --routes demo --warmup
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import tempfile
import time
import tracemalloc
from typing import Any

import numpy as np
from common import markdown_table, write_results

#: The demo's configuration (tests/test_engine.py): 30-frame chunks on the 4 m demo route.
DEMO_CONFIG = dict(
    chunk_size=30,
    overlap=10,
    loop_min_separation=50,
    loop_nms_radius=10,
    loop_half_window=8,
    point_stride=3,
    colmap_max_points=2_000,
    loop_threshold_rule="fixed",
)


class FixedCost:
    """A predictor that returns ``inner``'s prediction ``cost`` seconds after it was asked
    (its own time included; ``slowest``: the slowest inner prediction, seconds)."""

    def __init__(self, inner: Any, cost: float) -> None:
        self.inner, self.cost, self.num_frames, self.slowest = inner, float(cost), inner.num_frames, 0.0

    def predict(self, frames: np.ndarray) -> Any:
        t0 = time.perf_counter()
        pred = self.inner.predict(frames)
        spent = time.perf_counter() - t0
        self.slowest = max(self.slowest, spent)
        time.sleep(max(0.0, self.cost - spent))
        return pred

    def __getattr__(self, name: str) -> Any:  # fingerprint, frame_names, images, preprocess_geometry
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)


def _same_files(a: pathlib.Path, b: pathlib.Path) -> list[str]:
    """The output files that differ between two run directories (see the module docstring)."""
    files = {p.relative_to(a) for p in a.rglob("*") if p.is_file()} ^ {
        p.relative_to(b) for p in b.rglob("*") if p.is_file()
    }
    differ = sorted(str(p) for p in files if p.name not in ("poses_live.jsonl", "loops_live.json"))
    for p in sorted(a.rglob("*")):
        rel = p.relative_to(a)
        if (
            p.is_file()
            and (b / rel).is_file()
            and p.suffix != ".npz"
            and p.name not in ("metrics.json", "manifest.json")
        ):
            if p.read_bytes() != (b / rel).read_bytes():
                differ.append(str(rel))
    return differ


def replay(
    run: Any, config: Any, cost: float, fps: float, tmp: pathlib.Path, label: str, live_only: bool = False
) -> dict[str, Any]:
    from swiftjax import evaluation, pipeline
    from swiftjax.pipeline import reader
    from swiftjax.pipeline.engine import Reconstruction

    n, gt = run.predictor.num_frames, np.asarray(run.ground_truth)
    B, O = config.chunk_size, config.overlap
    predictor = FixedCost(run.predictor, cost)
    run.predictor.predict(np.arange(min(B, n)))  # the oracle's world and first compile: before the clock
    rec = Reconstruction(tmp / f"{label}-live", predictor, config, ground_truth=gt, overwrite=True, log=lambda s: None)
    steps: list[dict[str, Any]] = []
    revisions: list[tuple[int, int, float]] = []  # (revision, frames posed, time) when seen
    seen = 0  # engine steps seen
    t0 = time.monotonic()
    arrival = t0 + np.arange(n) / fps

    snapshots: list[np.ndarray] = []  # the live positions at each step, for the ATE after the drive

    def poll() -> None:
        # Nothing slow here: this thread is the car's clock.  (evaluation.ate is a JAX Umeyama
        # that compiles per trajectory length; called here at every step it once stalled this
        # thread for minutes: the cold backlog of the first version of this bench.)
        nonlocal seen
        if len(rec.steps) > seen:  # new first poses
            seen = len(rec.steps)
            frames, c2w = rec.poses()
            snapshots.append(c2w[:, :3, 3].copy())
            steps.append({"frames": len(frames), "revision": rec.revision, **_memory_now()})
            print(
                f"  {label}: {len(frames)} frames posed, revision {rec.revision}, {len(rec.loops)} loops, "
                f"load {os.getloadavg()[0]:.1f}",
                flush=True,
            )
        if rec.revision > (revisions[-1][0] if revisions else 0):
            revisions.append((rec.revision, len(rec.poses()[0]), time.monotonic()))

    for k in range(n):
        time.sleep(max(0.0, arrival[k] - time.monotonic()))
        rec.add_frame()
        poll()
    rec.end_of_input()  # the drive ended: the short last chunk (if any) posed live
    _, live_c2w = rec.poses()
    behind = [s["chunk"] for s in rec.steps if "loop_s" not in s and "loop_batch" not in s]
    waiting = rec.proposals_waiting
    waited = time.monotonic()
    rec.wait_for_poses()
    posed_s = time.monotonic() - waited
    poll()
    _, posed_c2w = rec.poses()
    # the loop-closure allowance: the live trajectory 2 chunk periods after the last frame (a
    # loop revisited in the last chunk cannot be closed before the last frame arrives)
    allowance = arrival[-1] + 2 * (B - O) / fps
    while time.monotonic() < allowance:
        time.sleep(min(0.05, max(0.0, allowance - time.monotonic())))
        poll()
    _, allowance_c2w = rec.poses()
    ate = lambda c2w: float(evaluation.ate(c2w, gt[: len(c2w)]).rmse) if len(c2w) >= 3 else None
    live_ate = ate(live_c2w)
    posed_ate, allowance_ate = ate(posed_c2w), ate(allowance_c2w)
    waited = time.monotonic()
    rec.wait_for_loops()
    drained_s = time.monotonic() - waited + posed_s
    poll()
    _, drained_c2w = rec.poses()
    drained_ate = float(evaluation.ate(drained_c2w, gt[: len(drained_c2w)]).rmse) if len(drained_c2w) >= 3 else None
    live_loops = [[int(lp["i"]), int(lp["j"])] for lp in rec.loops]
    engine_steps = [dict(s) for s in rec.steps]
    if live_only:  # the live phase's numbers only (no final pass, no offline run)
        rec.close()
        return {
            "route": label,
            "cost_s": cost,
            "live_ate_m": live_ate,
            "live_ate_posed_m": posed_ate,
            "live_ate_drained_m": drained_ate,
            "live_ate_2_periods_m": allowance_ate,
            "loop_chunks_behind_at_end": len(behind),
            "proposals_waiting_at_end": waiting,
            "verifications": _relative_times(rec.verifications, t0),
            "loop_worker_drain_s": drained_s,
            "revisions_seen": [[r, f, t - t0] for r, f, t in revisions],
            "live_loops": live_loops,
            "engine_steps": engine_steps,
            "load_average_1min_at_end": os.getloadavg()[0],
        }
    start_final = time.monotonic()
    final = rec.finish()
    engine_steps = [dict(s) for s in rec.steps]  # (with the short last chunk's, posed by finish())
    end = {}  # every frame's latest live pose when the final pass began
    for r in reader.read_live_poses(rec.run_dir):
        if r["reason"] != "final":
            end[r["frame"]] = r["pose"]
    end_ate = ate(np.stack([np.vstack([end[k], [0, 0, 0, 1]]) for k in sorted(end)])) if len(end) == n else None
    posed = engine_steps[-1]["frames"] if engine_steps else 0
    published = np.full(n, time.monotonic())  # (frames no live step posed: by the final pass)
    old = 0
    for s in engine_steps:  # each frame's first pose: the step that posed it
        published[old : s["frames"]] = s["posed_at"]
        old = s["frames"]
    latency = published - arrival
    for step, positions in zip(steps, snapshots):  # the live ATE at every step
        step["ate_m"] = (
            float(evaluation.ate(positions, gt[: len(positions), :3, 3]).rmse) if len(positions) >= 3 else None
        )

    offline = pipeline.reconstruct(
        run.predictor,
        tmp / f"{label}-offline",
        config,
        ground_truth=gt,
        overwrite=True,
        progress=False,
        log=lambda s: None,
    )
    identical_poses = bool(np.array_equal(final.cam_to_world, offline.cam_to_world))
    differ = _same_files(tmp / f"{label}-offline", tmp / f"{label}-live")

    loop_periods = loop_seconds = None
    if (
        revisions and live_loops
    ):  # the first loop-closure revision; its loop's later frame first posed at the step below
        later = max(live_loops[0])
        revisit = next(s for s in engine_steps if s["frames"] > later)
        loop_periods = (revisions[0][1] - revisit["frames"]) / (B - O)
        loop_seconds = revisions[0][2] - published[later]
    pose_times = [s["pose_s"] for s in engine_steps]
    step_times = [s["predict_s"] + s["geometry_s"] for s in engine_steps]  # one chunk's predict + geometry
    one_step = float(np.median(step_times)) if step_times else float("nan")
    target = (B - O) / fps + 1.5 * one_step
    p50, p95 = (float(v) for v in np.percentile(latency, [50, 95]))
    # the steady state: frames posed by the live steps after the first chunk (the first chunk's
    # frames wait B frame periods, not B - O)
    steady = latency[B:posed]
    steady_p95 = float(np.percentile(steady, 95)) if len(steady) else None
    return {
        "route": label,
        "frames": n,
        "cost_s": cost,
        "fps": fps,
        "chunk_size": B,
        "overlap": O,
        "latency_p50_s": p50,
        "latency_p95_s": p95,
        "latency_max_s": float(np.max(latency)),
        "latency_target_s": target,
        "latency_met": bool(p95 <= target),
        "latency_p95_steady_s": steady_p95,
        "latency_steady_met": None if steady_p95 is None else bool(steady_p95 <= target),
        "latency_first_chunk_max_s": float(np.max(latency[: min(B, posed)])) if posed else None,
        "latency_final_pass_frames": int(n - posed),
        "step_median_s": one_step,
        "step_max_s": float(np.max(step_times)) if step_times else None,
        "step_first_s": step_times[0] if step_times else None,
        "predict_median_s": float(np.median([s["predict_s"] for s in engine_steps])) if engine_steps else None,
        "geometry_median_s": float(np.median([s["geometry_s"] for s in engine_steps])) if engine_steps else None,
        "queued_max_s": float(np.max([s["queued_s"] for s in engine_steps])) if engine_steps else None,
        "completion_to_pose_p95_s": float(np.percentile(pose_times, 95)) if pose_times else None,
        "load_average_1min_at_end": os.getloadavg()[0],
        "loop_closure_chunk_periods": loop_periods,
        "loop_closure_s": loop_seconds,
        "loop_met": None if loop_periods is None else loop_periods <= 2,
        "live_loops": live_loops,
        "offline_loops": [[int(lp["i"]), int(lp["j"])] for lp in offline.loops],
        "revisions": rec.revision,
        "revisions_seen": [[r, f, t - t0] for r, f, t in revisions],
        "live_steps": len(engine_steps),
        "steps": steps,
        "engine_steps": engine_steps,
        "loop_chunks_behind_at_end": len(behind),
        "proposals_waiting_at_end": waiting,
        "verifications": _relative_times(rec.verifications, t0),
        "pose_drain_s": posed_s,
        "loop_worker_drain_s": drained_s,
        "final_pass_s": time.monotonic() - start_final,
        "live_ate_m": live_ate,
        "live_ate_posed_m": posed_ate,
        "live_ate_drained_m": drained_ate,
        "live_ate_2_periods_m": allowance_ate,
        "live_ate_end_m": end_ate,
        "live_ate_end_met": end_ate is not None
        and end_ate <= 1.1 * float(evaluation.ate(offline.cam_to_world, gt).rmse),
        "live_ate_met": live_ate is not None and live_ate <= 1.1 * float(evaluation.ate(offline.cam_to_world, gt).rmse),
        "live_ate_2_periods_met": allowance_ate is not None
        and allowance_ate <= 1.1 * float(evaluation.ate(offline.cam_to_world, gt).rmse),
        "offline_ate_m": float(evaluation.ate(offline.cam_to_world, gt).rmse),
        "offline_ate_no_loops_m": float(evaluation.ate(offline.cam_to_world_no_loops, gt).rmse),
        "identical_poses": identical_poses,
        "differing_files": differ,
        "identical": identical_poses and not differ,
        "slowest_oracle_predict_s": predictor.slowest,
        **_memory_growth(steps),
    }


def _rss_mb() -> float | None:
    """This process's resident memory now (MB; Linux ``/proc/self/statm``), else None."""
    try:
        pages = int(pathlib.Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def _memory_now() -> dict[str, float | None]:
    """The driver's memory now (MB): resident (``rss_mb``), the live JAX arrays' bytes
    (``jax_live_mb``) and, while ``tracemalloc`` traces, the Python heap (``py_heap_mb``)."""
    import jax

    now = {"rss_mb": _rss_mb(), "jax_live_mb": sum(a.nbytes for a in jax.live_arrays()) / 2**20}
    if tracemalloc.is_tracing():
        now["py_heap_mb"] = tracemalloc.get_traced_memory()[0] / 2**20
    return now


def _memory_growth(steps: list[dict[str, Any]]) -> dict[str, Any]:
    """The driver's memory over the live steps (:func:`_memory_now`'s kinds): at the step a
    quarter of the way through (the first when there are fewer than four: a slow machine
    poses several chunks per step) and at the last, and the growth between them (``rss_*``,
    ``jax_live_*``, ``py_heap_*``; None only for a kind never measured).  What the resident
    memory adds beyond the data is compiled programs (a new size bucket of the loop decision
    or the pose graph at each doubling of the chunks, the detector's at each doubling of the
    frames: ``O(log N)`` steps) and the allocator's free lists."""
    out: dict[str, Any] = {}
    for kind in ("rss", "jax_live", "py_heap"):
        rows = [s[f"{kind}_mb"] for s in steps if s.get(f"{kind}_mb") is not None]
        m0, m1 = (rows[len(rows) // 4], rows[-1]) if rows else (None, None)
        out |= {f"{kind}_quarter_mb": m0, f"{kind}_last_mb": m1, f"{kind}_growth_mb": None if m0 is None else m1 - m0}
    return out


def _relative_times(records: list[dict[str, Any]], t0: float) -> list[dict[str, Any]]:
    """``records`` with their ``*_at`` times (``time.monotonic()``) as seconds since ``t0``."""
    return [{k: v - t0 if k.endswith("_at") else v for k, v in r.items()} for r in records]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="demo route, 90 frames, cost 0.5 s only")
    parser.add_argument("--costs", type=float, nargs="+", default=None, help="seconds per chunk (default 0.5 2)")
    parser.add_argument("--fps", type=float, default=10.0, help="replay rate (KITTI: 10 Hz)")
    parser.add_argument("--routes", nargs="+", choices=("demo", "kitti00"), default=None)
    parser.add_argument("--kitti-frames", type=int, default=None, help="truncate synthetic KITTI 00")
    parser.add_argument("--no-write", action="store_true", help="print only (no JSON under bench/results/)")
    parser.add_argument("--live-only", action="store_true", help="the live phase only: print its numbers, no table")
    parser.add_argument("--warmup", action="store_true", help="replay each route once, untimed, first (JIT caches)")
    parser.add_argument(
        "--trace-memory", action="store_true", help="trace the Python heap at every step (tracemalloc: slower)"
    )
    args = parser.parse_args(argv)
    if args.trace_memory:
        tracemalloc.start()

    from swiftjax import pipeline
    from swiftjax.synthetic import demo

    costs = args.costs or ([0.5] if args.quick else [0.5, 2.0])
    routes = args.routes or (["demo"] if args.quick else ["demo", "kitti00"])
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for route in routes:
            for cost in ([0.0] if args.warmup else []) + costs:
                if route == "demo":
                    run = demo.loop_route_run(90 if args.quick else None, image_hw=(28, 98), spacing_m=4.0)
                    config = pipeline.PipelineConfig(**DEMO_CONFIG)
                else:
                    from bench_pipeline import _shared

                    run = demo.kitti00_run(_shared(), frames=args.kitti_frames)
                    config = pipeline.PipelineConfig()
                warm = args.warmup and cost == 0.0
                label = f"{route}-warmup" if warm else f"{route}-{cost:g}s"
                result = replay(
                    run, config, cost, 1e3 if warm else args.fps, pathlib.Path(tmp), label, args.live_only and not warm
                )
                if args.live_only and not warm:
                    summary = {k: v for k, v in result.items() if k != "engine_steps"}
                    print(f"live only: {json.dumps(summary)}", flush=True)
                    continue
                if not warm:
                    runs.append(result)
                    summary = {k: v for k, v in result.items() if not isinstance(v, (list, dict))}
                    print(f"arm done: {json.dumps(summary)}", flush=True)  # in the log, should a later arm fail
    rows = [
        [
            r["route"],
            r["frames"],
            r["cost_s"],
            r["latency_p50_s"],
            r["latency_p95_s"],
            r["latency_max_s"],
            r["latency_target_s"],
            "yes" if r["latency_met"] else "NO",
            r["latency_p95_steady_s"],
            "-" if r["loop_closure_chunk_periods"] is None else r["loop_closure_chunk_periods"],
            r["revisions"],
            r["live_ate_m"],
            r["live_ate_2_periods_m"],
            r["live_ate_drained_m"],
            r["live_ate_end_m"],
            r["offline_ate_m"],
            "yes" if r["identical"] else "NO",
            r["slowest_oracle_predict_s"],
            "-" if r["rss_quarter_mb"] is None else f"{r['rss_quarter_mb']:.0f} -> {r['rss_last_mb']:.0f}",
            "-"
            if r["jax_live_quarter_mb"] is None
            else f"{r['jax_live_quarter_mb']:.0f} -> {r['jax_live_last_mb']:.0f}",
        ]
        for r in runs
    ]
    print(
        markdown_table(
            [
                "run",
                "frames",
                "cost s",
                "latency p50 s",
                "p95 s",
                "max s",
                "target p95 s",
                "met",
                "p95 after chunk 0 s",
                "loop closure (chunk periods)",
                "revisions",
                "live ATE m",
                "live ATE +2 periods m",
                "live ATE drained m",
                "live ATE before the final pass m",
                "offline ATE m",
                "final = offline",
                "slowest oracle s",
                "RSS MB (quarter -> end)",
                "JAX arrays MB (quarter -> end)",
            ],
            rows,
        )
    )
    payload = {"argv": sys.argv[1:] if argv is None else argv, "runs": runs}
    if not args.no_write:
        print(f"wrote {write_results('online', payload)}")
    return payload


if __name__ == "__main__":
    main()

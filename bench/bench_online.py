"""Online reconstruction (issue 30, section 4): a synthetic drive replayed at 10 Hz through the
live engine (:class:`swiftjax.pipeline.engine.Reconstruction`).

The predictor is the synthetic oracle at a fixed cost per chunk (the GPU stand-in of
``bench_scaleout.py``: ``--cost`` seconds per prediction in all, the oracle's own time
included; the oracle is warmed up before the clock starts, and its slowest chunk is reported:
above ``--cost`` the cost is not fixed).  Frame ``k`` arrives at ``t0 + k / fps`` whether or not
the engine is busy (a car does not wait).  Measured per route and cost:

* per frame, the latency from its arrival to its first published pose (p50 / p95 / max), and
  the target ``(B - O) / fps + 1.5 x (cost + geometry of one step)`` (the first step's time);
* the latency from a revisit to the loop's closure, in chunk periods (``B - O`` frames): the
  frames posed when the first loop closed live minus the frames posed when the revisit's later
  frame was first posed;
* the number of revisions, the live trajectory's ATE (Sim(3)) against the ground truth at
  every chunk and at the end of the drive before the final pass, and the offline run's;
* the finished run compared with an offline ``reconstruct`` of the same frames: the poses
  bit for bit and every output file byte for byte (except ``metrics.json``'s timings,
  ``manifest.json`` and the chunk store's ``.npz`` zip headers).

The engine re-runs the stages over the whole prefix at each chunk (the incremental stages are
issue 30's next step), so the step time, and with it the latency, grows with the drive.

    python bench/bench_online.py                # demo route and synthetic KITTI 00, costs 0.5 s and 2 s
    python bench/bench_online.py --quick        # demo route, 90 frames, 0.5 s (a few minutes on a CPU)
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import tempfile
import time
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
    differ = sorted(str(p) for p in files if p.name != "poses_live.jsonl")
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


def replay(run: Any, config: Any, cost: float, fps: float, tmp: pathlib.Path, label: str) -> dict[str, Any]:
    from swiftjax import evaluation, pipeline
    from swiftjax.pipeline.engine import Reconstruction

    n, gt = run.predictor.num_frames, np.asarray(run.ground_truth)
    B, O = config.chunk_size, config.overlap
    predictor = FixedCost(run.predictor, cost)
    run.predictor.predict(np.arange(min(B, n)))  # the oracle's world and first compile: before the clock
    rec = Reconstruction(tmp / f"{label}-live", predictor, config, ground_truth=gt, overwrite=True, log=lambda s: None)
    published = np.full(n, np.nan)
    steps: list[dict[str, Any]] = []
    posed = 0
    t0 = time.monotonic()
    for k in range(n):
        time.sleep(max(0.0, t0 + k / fps - time.monotonic()))
        started = time.monotonic()
        if rec.add_frame():
            now = time.monotonic()
            frames, c2w = rec.poses()
            published[posed : len(frames)] = now
            posed = len(frames)
            step_ate = float(evaluation.ate(c2w, gt[:posed]).rmse)
            steps.append(
                {
                    "frames": posed,
                    "revision": rec.revision,
                    "loops": len(rec.result.loops),
                    "seconds": now - started,
                    "ate_m": step_ate,
                    "loop_pairs": [[int(lp["i"]), int(lp["j"])] for lp in rec.result.loops],
                }
            )
            print(
                f"  {label}: {posed} frames posed, step {now - started:.1f} s, revision {rec.revision}, "
                f"{len(rec.result.loops)} loops, live ATE {step_ate:.3f} m",
                flush=True,
            )
    _, live_c2w = rec.poses()
    live_ate = float(evaluation.ate(live_c2w, gt[: len(live_c2w)]).rmse) if len(live_c2w) >= 3 else float("nan")
    start_final = time.monotonic()
    final = rec.finish()
    published[posed:] = time.monotonic()  # the frames after the last chunk: posed by the final pass
    latency = published - (t0 + np.arange(n) / fps)

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

    closing = next((s for s in steps if s["loops"] > 0), None)
    loop_periods = None
    if closing is not None:  # the first loop closed live; its later frame was first posed at the step below
        later = max(closing["loop_pairs"][0])
        revisit = next(s["frames"] for s in steps if s["frames"] > later)
        loop_periods = (closing["frames"] - revisit) / (B - O)
    target = (B - O) / fps + 1.5 * (steps[0]["seconds"] if steps else float("nan"))
    p50, p95 = (float(v) for v in np.percentile(latency, [50, 95]))
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
        "loop_closure_chunk_periods": loop_periods,
        "loop_met": None if loop_periods is None else loop_periods <= 2,
        "revisions": rec.revision,
        "live_steps": len(steps),
        "steps": steps,
        "final_pass_s": time.monotonic() - start_final,
        "live_ate_m": live_ate,
        "offline_ate_m": float(evaluation.ate(offline.cam_to_world, gt).rmse),
        "identical_poses": identical_poses,
        "differing_files": differ,
        "identical": identical_poses and not differ,
        "slowest_oracle_predict_s": predictor.slowest,
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="demo route, 90 frames, cost 0.5 s only")
    parser.add_argument("--costs", type=float, nargs="+", default=None, help="seconds per chunk (default 0.5 2)")
    parser.add_argument("--fps", type=float, default=10.0, help="replay rate (KITTI: 10 Hz)")
    parser.add_argument("--routes", nargs="+", choices=("demo", "kitti00"), default=None)
    parser.add_argument("--kitti-frames", type=int, default=None, help="truncate synthetic KITTI 00")
    parser.add_argument("--no-write", action="store_true", help="print only (no JSON under bench/results/)")
    args = parser.parse_args(argv)

    from swiftjax import pipeline
    from swiftjax.synthetic import demo

    costs = args.costs or ([0.5] if args.quick else [0.5, 2.0])
    routes = args.routes or (["demo"] if args.quick else ["demo", "kitti00"])
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for route in routes:
            for cost in costs:
                if route == "demo":
                    run = demo.loop_route_run(90 if args.quick else None, image_hw=(28, 98), spacing_m=4.0)
                    config = pipeline.PipelineConfig(**DEMO_CONFIG)
                else:
                    from bench_pipeline import _shared

                    run = demo.kitti00_run(_shared(), frames=args.kitti_frames)
                    config = pipeline.PipelineConfig()
                runs.append(replay(run, config, cost, args.fps, pathlib.Path(tmp), f"{route}-{cost:g}s"))
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
            "-" if r["loop_closure_chunk_periods"] is None else r["loop_closure_chunk_periods"],
            r["revisions"],
            r["live_ate_m"],
            r["offline_ate_m"],
            "yes" if r["identical"] else "NO",
            r["slowest_oracle_predict_s"],
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
                "loop closure (chunk periods)",
                "revisions",
                "live ATE m",
                "offline ATE m",
                "final = offline",
                "slowest oracle s",
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

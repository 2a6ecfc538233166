"""Synthetic KITTI 00: the whole pipeline along the real KITTI 00 trajectory through the oracle.

4,541 frames at 518x154, B = 75, O = 30.  Each configuration runs in a fresh child process
(so peak RSS is that run's own) with a warm persistent compilation cache (a first,
untimed run fills it): time per stage, peak RSS, ATE with and without loop closure.
Peak RSS is measured at 600 and 4,541 frames to show it does not grow with the sequence.
Targets: geometry stages (everything but the predictor) under 24 s, peak RSS under 2 GB,
loop closure cutting ATE at least in half.

``wall - predictor`` is the whole run's wall time minus the predictor's own calls, clocked by
a wrapper outside the pipeline (so it compares versions with different stage bookkeeping).
Stage clocks (``metrics.json`` ``timings_seconds``): the predictor's calls are booked as
``predict`` (temporal chunks) and ``predict (loop chunks)``; every other stage -- align,
loop detection (with the descriptor reduction), loop chunks, pose graph, chunk store
(float16 conversion, chunk-file and manifest writes), export -- counts as geometry.  The
child runs with ``OPENBLAS_NUM_THREADS=1`` as the ``swiftjax`` CLI does (unless already set);
the load average before each run is recorded.  ``--prefetch`` is the local executor's
prefetch depth; the default 0 predicts each chunk when it is asked for, because the oracle
is CPU-bound and a prefetching thread would share the machine's cores with the geometry
stages it is meant to hide behind (``bench_scaleout.py`` measures prefetch with a
predictor that waits like a GPU).

    python bench/bench_pipeline.py [--frames 600 4541] [--irls-frames 0] [--skip-warmup] [--prefetch 0]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

from common import markdown_table, write_results

HERE = pathlib.Path(__file__).resolve().parent
CHILD = r"""
import json, os, pathlib, resource, sys, time
import jax
jax.config.update("jax_compilation_cache_dir", os.environ["SWIFTJAX_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
from swiftjax import pipeline
from swiftjax.synthetic import demo
from swiftjax.pipeline.executors import LocalExecutor
shared, frames, out, method = pathlib.Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
prefetch = int(sys.argv[5])
run = demo.kitti00_run(shared, frames=frames)

class Timed:  # the predictor's own calls, clocked outside the pipeline's stage accounting
    def __init__(self, inner):
        self.inner, self.num_frames, self.seconds = inner, inner.num_frames, 0.0
    def predict(self, f):
        t = time.perf_counter()
        try:
            return self.inner.predict(f)
        finally:
            self.seconds += time.perf_counter() - t
    def fingerprint(self):
        return self.inner.fingerprint()
    def frame_names(self):
        return self.inner.frame_names()

predictor = Timed(run.predictor)
t0 = time.perf_counter()
config = pipeline.PipelineConfig(alignment=method)
res = pipeline.reconstruct(predictor, out, config, ground_truth=run.ground_truth,
                           progress=False, overwrite=True, executor=LocalExecutor(prefetch=prefetch))
wall = time.perf_counter() - t0
peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"metrics": res.metrics, "wall": wall, "peak_rss_mb": peak_mb,
                  "predictor_seconds": predictor.seconds, "load_average_after": os.getloadavg()}))
"""


def _shared() -> pathlib.Path:
    env = os.environ.get("SWIFTJAX_SHARED")
    path = pathlib.Path(env) if env else HERE.parent.parent / "shared"
    if not (path / "data" / "trajectories" / "KITTI_00_gt.txt").exists():
        sys.exit(f"KITTI 00 ground truth not found under {path}: set SWIFTJAX_SHARED")
    return path


def run_child(frames: int, cache: str, out: str, method: str = "umeyama", prefetch: int = 0) -> dict:
    env = dict(os.environ, SWIFTJAX_CACHE_DIR=cache)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI (swiftjax.cli.main)
    load = os.getloadavg()
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(_shared()), str(frames), out, method, str(prefetch)],
        capture_output=True,
        text=True,
        env=env,
        cwd=HERE,
    )
    if proc.returncode != 0:
        sys.exit(f"child run failed:\n{proc.stderr[-3000:]}")
    rec = json.loads(proc.stdout.strip().splitlines()[-1])
    rec["load_average_before"] = load
    rec["openblas_num_threads"] = env["OPENBLAS_NUM_THREADS"]
    return rec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[600, 4541])
    parser.add_argument(
        "--irls-frames",
        type=int,
        default=4541,
        help="also run this many frames with VGGT-Long's IRLS alignment (0: skip)",
    )
    parser.add_argument("--skip-warmup", action="store_true", help="do not fill the compile cache first")
    parser.add_argument(
        "--prefetch",
        type=int,
        default=0,
        help="local executor prefetch depth (0: predict each chunk when it is asked for)",
    )
    args = parser.parse_args()

    cache = os.environ.get("SWIFTJAX_CACHE_DIR", str(pathlib.Path.home() / ".cache" / "swiftjax" / "jax"))
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_warmup:
            run_child(min(args.frames), cache, os.path.join(tmp, "warmup"), prefetch=args.prefetch)
        runs = [(f, "umeyama") for f in args.frames] + ([(args.irls_frames, "irls")] if args.irls_frames else [])
        for frames, method in runs:
            rec = run_child(frames, cache, os.path.join(tmp, f"run{frames}{method}"), method, args.prefetch)
            rec["frames"], rec["alignment"], rec["prefetch"] = frames, method, args.prefetch
            records.append(rec)
            m = rec["metrics"]
            print(
                f"{frames} frames, {method}: {rec['wall']:.1f} s, peak RSS {rec['peak_rss_mb']:.0f} MB, "
                f"loops {m['loops']}, ATE {m['ate_rmse']:.2f} m (no loops {m['ate_rmse_no_loops']:.2f} m), "
                f"load average {rec['load_average_before'][0]:.2f}",
                flush=True,
            )

    stages = [
        "predict",
        "predict (loop chunks)",
        "align",
        "loop detection",
        "loop chunks",
        "loop verification",
        "pose graph",
        "chunk store",
        "export",
    ]
    rows = []
    for rec in records:
        t = rec["metrics"]["timings_seconds"]
        geometry = sum(v for k, v in t.items() if not k.startswith("predict"))
        m = rec["metrics"]
        rows.append(
            [
                rec["frames"],
                rec["alignment"],
                m["chunks"],
                m["loops"],
                *[float(t.get(s, 0.0)) for s in stages],
                geometry,
                rec["wall"] - rec["predictor_seconds"],
                rec["peak_rss_mb"],
                m["ate_rmse_no_loops"],
                m["ate_rmse"],
                m["ate_rmse_no_loops"] / m["ate_rmse"],
                rec["load_average_before"][0],
            ]
        )
    headers = [
        "frames",
        "alignment",
        "chunks",
        "loops",
        *[f"{s} s" for s in stages],
        "geometry s (all but predict*)",
        "wall - predictor s",
        "peak RSS MB",
        "ATE no loops m",
        "ATE loops m",
        "ATE ratio",
        "load avg",
    ]
    print(markdown_table(headers, rows))
    path = write_results("pipeline", {"runs": records})
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()

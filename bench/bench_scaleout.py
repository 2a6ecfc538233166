"""Scale-out: the synthetic KITTI 00 schedule with a predictor of fixed cost per chunk.

A sleeping predictor stands in for the GPU (``--cost`` seconds per chunk, ~1 s like VGGT-1B
on an RTX 4090), returning the oracle's arrays computed beforehand (a first, untimed run
records every prediction to disk; reading them back is part of the predictor's cost, and it
also fills the compile cache).  Each configuration runs in a fresh child process (peak RSS
is the driver's own):

* ``plain oracle``: the oracle computing live, local executor without prefetch;
* ``zero cost``: the recorded arrays with no sleep, no prefetch: the host's geometry;
* ``local``: the sleeping predictor without and with prefetch (predict chunk t+1 on a thread
  while the host aligns and stores chunk t);
* ``ray W``: the sleeping predictor on a local Ray cluster of W actors.

Targets: local prefetch wall <= 1.1 x max(predict total, geometry); Ray with W
workers <= 1.2 x predict total / W + the final stages; the driver's peak RSS flat in frames
(Ray with 2 workers at ``--rss-frames`` and ``--frames``).  Ray's overhead per chunk is
measured apart: one actor, one request in flight, zero cost: round trip minus the actor's
own time, and the bytes moved per chunk.  From the measured per-chunk costs the script
projects synthetic KITTI 00 (4,541 frames) on 1, 4 and 8 GPUs.

    python bench/bench_scaleout.py [--frames 4541] [--cost 1.0] [--workers 1 2 4] [--rss-frames 600]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

from bench_pipeline import _shared  # KITTI 00 ground truth under $SWIFTJAX_SHARED
from common import markdown_table, write_results

HERE = pathlib.Path(__file__).resolve().parent

CHILD = r"""
import hashlib, json, os, pathlib, resource, sys, time
import numpy as np
import jax
jax.config.update("jax_compilation_cache_dir", os.environ["SWIFTJAX_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
from swiftjax import chunks, pipeline
from swiftjax.synthetic import demo
from swiftjax.pipeline import executors
from swiftjax.prediction import ChunkPrediction

FIELDS = ("depth", "conf", "extrinsic", "intrinsic", "descriptors", "images")

def key(frames):
    return hashlib.sha1(np.asarray(frames, np.int64).tobytes()).hexdigest()[:16]

class Recording:
    # the oracle, saving each prediction (tokens reduced to descriptors) as .npy files
    def __init__(self, inner, cache):
        self.inner, self.cache, self.num_frames = inner, pathlib.Path(cache), inner.num_frames
    def predict(self, frames):
        from swiftjax.loops.descriptors import chunk_descriptors
        pred = chunk_descriptors(self.inner.predict(frames))
        d = self.cache / key(frames)
        d.mkdir(parents=True, exist_ok=True)
        for f in FIELDS:
            np.save(d / f"{f}.npy", getattr(pred, f))
        return pred
    def fingerprint(self):
        return self.inner.fingerprint()
    def frame_names(self):
        return self.inner.frame_names()

class Sleeping:
    # the recorded arrays after `cost` seconds in all (reading included): a GPU stand-in
    def __init__(self, cache, cost):
        self.cache, self.cost = str(cache), float(cost)
        meta = json.loads((pathlib.Path(cache) / "meta.json").read_text())
        self.num_frames, self._names, self._fp = meta["frames"], meta["names"], meta["fingerprint"]
    def predict(self, frames):
        t0 = time.perf_counter()
        d = pathlib.Path(self.cache) / key(frames)
        pred = ChunkPrediction(**{f: np.load(d / f"{f}.npy") for f in FIELDS})
        time.sleep(max(0.0, self.cost - (time.perf_counter() - t0)))
        return pred
    def fingerprint(self):
        return self._fp
    def frame_names(self):
        return self._names

mode, shared, frames, cache, out, cost, workers = sys.argv[1:8]
frames, cost, workers = int(frames), float(cost), int(workers)
config = pipeline.PipelineConfig()
rec = {"load_average_before": os.getloadavg()}
if mode in ("record", "plain"):
    run = demo.kitti00_run(pathlib.Path(shared), frames=frames)
    predictor = Recording(run.predictor, cache) if mode == "record" else run.predictor
    executor = executors.LocalExecutor(prefetch=0)
else:
    predictor = Sleeping(cache, cost)
    if mode.startswith("ray"):  # a local cluster of `workers` logical CPUs (the actors sleep)
        executor = executors.RayExecutor(workers, num_cpus=workers)
    else:
        executor = executors.LocalExecutor(prefetch=1 if mode == "local1" else 0)
t0 = time.perf_counter()
if mode == "overhead":
    schedule = chunks.chunk_schedule(predictor.num_frames, config.chunk_size, config.overlap)
    reqs = [schedule.frames(t) for t in range(min(schedule.num_chunks, 20))]
    ex = executors.RayExecutor(1, num_cpus=1, max_in_flight=1)
    list(ex.map(predictor, reqs[:2]))  # actor start-up, first transfers
    ex.stats = executors.ExecutorStats()
    t1 = time.perf_counter()
    for _ in ex.map(predictor, reqs[2:]):
        pass
    n = len(reqs) - 2
    rec.update(chunks=n, round_trip_ms=1e3 * (time.perf_counter() - t1) / n,
               actor_ms=1e3 * ex.stats.predict_seconds / n, bytes_per_chunk=ex.stats.bytes / n)
    ex.close()
else:
    res = pipeline.reconstruct(predictor, out, config, progress=False, overwrite=True, log=lambda s: None,
                               executor=executor)
    rec.update(wall=time.perf_counter() - t0, timings=res.metrics["timings_seconds"], chunks=res.num_chunks,
               loop_chunks=len(res.loops), predictions=executor.stats.predictions,
               predict_seconds=executor.stats.predict_seconds, bytes=executor.stats.bytes)
    if mode == "record":
        names = predictor.frame_names()
        (pathlib.Path(cache) / "meta.json").write_text(json.dumps(
            {"frames": predictor.num_frames, "names": names, "fingerprint": predictor.fingerprint()}))
    executor.close()
rec["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(rec, default=float))
"""


def child(mode: str, frames: int, cache: str, out: str, cost: float = 0.0, workers: int = 0) -> dict:
    env = dict(
        os.environ,
        SWIFTJAX_CACHE_DIR=os.environ.get(
            "SWIFTJAX_CACHE_DIR", str(pathlib.Path.home() / ".cache" / "swiftjax" / "jax")
        ),
    )
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, mode, str(_shared()), str(frames), cache, out, str(cost), str(workers)],
        capture_output=True,
        text=True,
        env=env,
        cwd=HERE,
    )
    if proc.returncode != 0:
        sys.exit(f"child {mode} failed:\n{proc.stderr[-3000:]}")
    rec = json.loads(proc.stdout.strip().splitlines()[-1])
    rec.update(mode=mode, frames=frames, cost=cost, workers=workers)
    print(
        f"{mode:>9} W={workers} {frames} frames: "
        + (f"{rec['wall']:.1f} s, " if "wall" in rec else "")
        + f"peak RSS {rec['peak_rss_mb']:.0f} MB, load {rec['load_average_before'][0]:.1f}",
        flush=True,
    )
    return rec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=4541)
    parser.add_argument("--cost", type=float, default=1.0, help="seconds per chunk of the sleeping predictor")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--rss-frames", type=int, default=600, help="second length for the peak-RSS check (0: skip)")
    parser.add_argument("--gpu-cost", type=float, default=1.0, help="VGGT seconds per chunk for the projection")
    parser.add_argument("--report", metavar="RESULTS_JSON", help="print the tables of a written result, run nothing")
    args = parser.parse_args()
    if args.report:
        report_from(args.report)
        return

    records: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:

        def cache_for(frames: int) -> str:
            path = os.path.join(tmp, f"cache{frames}")
            if not os.path.isdir(path):
                records.append(child("record", frames, path, os.path.join(tmp, f"rec{frames}")))
            return path

        cache = cache_for(args.frames)
        out = os.path.join(tmp, "run")
        runs = {
            "plain": child("plain", args.frames, cache, out),
            "zero": child("local0", args.frames, cache, out, 0.0),
            "local0": child("local0", args.frames, cache, out, args.cost),
            "local1": child("local1", args.frames, cache, out, args.cost),
        }
        for w in args.workers:
            runs[f"ray{w}"] = child("ray", args.frames, cache, out, args.cost, w)
        overhead = child("overhead", args.frames, cache, out)
        rss_small = None
        if args.rss_frames:
            rss_small = child("ray", args.rss_frames, cache_for(args.rss_frames), out, args.cost, 2)
        records += list(runs.values()) + [overhead] + ([rss_small] if rss_small else [])

    report(args, runs, overhead, rss_small, records)


def _latest_pipeline_reference() -> dict | None:
    """The newest ``bench_pipeline.py`` run of the whole of synthetic KITTI 00 (umeyama)."""
    best = None
    for path in sorted((HERE / "results").glob("pipeline-2*.json")):
        for run in json.loads(path.read_text()).get("runs", []):
            if run.get("frames") == 4541 and run.get("alignment") == "umeyama":
                best = dict(run, source=path.name)
    return best


def project(timings: dict, temporal: int, loop_chunks: int, gpu_cost: float, overhead_s: float) -> list[list]:
    """Projected wall time on 1, 4, 8 GPUs from one run's stage times (``timings``, its
    prediction waits excluded): temporal stage max(T (c + o) / G, host work of the temporal
    chunks) + loop stage max(L (c + o) / G, host work of the loop chunks) + the rest (loop
    detection and verification, pose graph, export).  ``o`` (Ray's overhead per chunk) is
    paid with G > 1 only; model loading and actor start-up are not included."""
    host_t = sum(timings.get(k, 0.0) for k in ("align", "chunk store"))
    host_l = timings.get("loop chunks", 0.0)
    rest = sum(timings.get(k, 0.0) for k in ("loop detection", "loop verification", "pose graph", "export"))
    rows = []
    for gpus in (1, 4, 8):
        per = gpu_cost + (overhead_s if gpus > 1 else 0.0)
        stage_t = max(temporal * per / gpus, host_t)
        stage_l = max(loop_chunks * per / gpus, host_l)
        rows.append(
            [
                gpus,
                "local, prefetch" if gpus == 1 else f"ray, {gpus} workers",
                temporal + loop_chunks,
                stage_t,
                stage_l,
                rest,
                stage_t + stage_l + rest,
            ]
        )
    return rows


def report(args, runs: dict, overhead: dict, rss_small: dict | None, records: list, write: bool = True) -> None:
    zero = runs["zero"]
    n_pred = zero["predictions"]
    predict_total = n_pred * args.cost
    geometry = zero["wall"]
    t = zero["timings"]
    final = sum(t.get(k, 0.0) for k in ("loop detection", "loop verification", "pose graph", "export"))
    rows = []
    for name, rec in runs.items():
        label = {
            "plain": "plain oracle (local, no prefetch)",
            "zero": "zero cost (geometry)",
            "local0": "local, no prefetch",
            "local1": "local, prefetch 1",
        }.get(name, f"ray, {rec['workers']} workers")
        if name == "local1":
            bound = 1.1 * max(predict_total, geometry)
        elif name.startswith("ray"):
            bound = 1.2 * predict_total / rec["workers"] + final
        else:
            bound = None
        rows.append(
            [
                label,
                rec["chunks"],
                rec["predictions"] - rec["chunks"],
                rec["predictions"],
                rec["wall"],
                "" if bound is None else f"{bound:.1f}",
                "" if bound is None else ("yes" if rec["wall"] <= bound else "NO"),
                rec["bytes"] / 2**20,
                rec["peak_rss_mb"],
                rec["load_average_before"][0],
            ]
        )
    print(
        markdown_table(
            [
                "configuration",
                "chunks",
                "loop chunks",
                "predictions",
                "wall s",
                "target s",
                "met",
                "MB to driver",
                "driver peak RSS MB",
                "load avg",
            ],
            rows,
        )
    )
    print(
        f"\npredict total {predict_total:.1f} s ({n_pred} x {args.cost} s), geometry (zero-cost run) "
        f"{geometry:.1f} s, final stages {final:.1f} s"
    )
    overhead_s = max(0.0, overhead["round_trip_ms"] - overhead["actor_ms"]) / 1e3
    print(
        f"Ray overhead per chunk: {1e3 * overhead_s:.1f} ms (round trip {overhead['round_trip_ms']:.1f} ms, "
        f"actor {overhead['actor_ms']:.1f} ms), {overhead['bytes_per_chunk'] / 2**20:.1f} MB per chunk"
    )
    if rss_small:
        print(
            f"driver peak RSS, Ray 2 workers: {rss_small['peak_rss_mb']:.0f} MB at {rss_small['frames']} frames, "
            f"{runs['ray2']['peak_rss_mb'] if 'ray2' in runs else float('nan'):.0f} MB at {args.frames} frames"
        )

    headers = ["GPUs", "executor", "predictions", "temporal stage s", "loop stage s", "rest s", "projected wall s"]
    projections = {}
    ref = _latest_pipeline_reference()
    if ref is not None:
        m = ref["metrics"]
        proj = project(m["timings_seconds"], m["chunks"], m["loops"], args.gpu_cost, overhead_s)
        print(
            f"\nKITTI 00 projection, {args.gpu_cost} s per chunk on a GPU, host stage times of {ref['source']} "
            f"(4,541 frames, load {ref['load_average_before'][0]:.2f}), Ray overhead as measured here:"
        )
        print(markdown_table(headers, proj))
        projections["reference"] = {"source": ref["source"], "rows": proj}
    scale = 4541 / args.frames  # this run's host times scaled to KITTI 00's length
    loops_here = n_pred - zero["chunks"]
    proj = project(
        {k: v * scale for k, v in t.items()},
        round(zero["chunks"] * scale),
        round(loops_here * scale),
        args.gpu_cost,
        overhead_s,
    )
    print(
        f"\nKITTI 00 projection from this run's host stage times (x {scale:.2f}, load "
        f"{zero['load_average_before'][0]:.1f}):"
    )
    print(markdown_table(headers, proj))
    projections["this_run"] = proj
    if not write:
        return
    path = write_results(
        "scaleout", {"args": vars(args), "runs": records, "projection": projections, "ray_overhead_s": overhead_s}
    )
    print(f"\nwrote {path}")


def report_from(path: str) -> None:
    """``--report RESULTS.json``: the tables again from a written result."""
    data = json.loads(pathlib.Path(path).read_text())
    args = argparse.Namespace(**data["args"])
    runs, overhead, rss_small = {}, None, None
    for rec in data["runs"]:
        mode = rec["mode"]
        if mode == "record":
            continue
        if mode == "overhead":
            overhead = rec
        elif mode == "plain":
            runs["plain"] = rec
        elif mode == "local0":
            runs["zero" if rec["cost"] == 0 else "local0"] = rec
        elif mode == "local1":
            runs["local1"] = rec
        elif rec["frames"] == args.frames:
            runs[f"ray{rec['workers']}"] = rec
        else:
            rss_small = rec
    report(args, runs, overhead, rss_small, data["runs"], write=False)


if __name__ == "__main__":
    main()

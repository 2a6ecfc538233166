"""Synthetic VGGT oracle throughput at 518 x 154 (issue 7): the whole KITTI 00 pass.

Measured in one run:

* world construction around KITTI 00's ground truth (4,541 poses);
* one render block (15 frames) with the jitted JAX ray caster, best of ``--repeats``, vs
  the brute-force float64 NumPy reference renderer (:func:`render_numpy`, every object,
  no culling) on the same frames -> per-frame speed-up;
* the full oracle pass: ``predict_chunk`` over the DESIGN.md chunk schedule (B = 75,
  O = 30: 101 chunks, 7,566 chunk-frames) with depth, confidence, images and place tokens,
  after one warm-up chunk (compiles excluded) -> total seconds and frames/s.

Writes ``bench/results/bench_oracle-<timestamp>.json``.  Usage::

    .venv/bin/python bench/bench_oracle.py                 # full KITTI 00 pass
    .venv/bin/python bench/bench_oracle.py --max-chunks 20 # a quicker partial pass
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from common import best_of, markdown_table, write_results  # noqa: E402

from swiftjax.chunks import chunk_schedule  # noqa: E402
from swiftjax.io.trajectory import read_kitti  # noqa: E402
from swiftjax.synthetic.oracle import VGGTOracle, kitti_intrinsics  # noqa: E402
from swiftjax.synthetic.render import chunk_candidates, frame_planes, render_frames, render_numpy  # noqa: E402
from swiftjax.synthetic.world import build_world  # noqa: E402


def find_kitti() -> pathlib.Path:
    env = os.environ.get("SWIFTJAX_SHARED")
    for base in ([pathlib.Path(env)] if env else []) + [ROOT.parent / "shared"]:
        p = base / "data/trajectories/KITTI_00_gt.txt"
        if p.is_file():
            return p
    raise SystemExit("KITTI_00_gt.txt not found: set SWIFTJAX_SHARED to the folder holding data/")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-chunks", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--numpy-frames", type=int, default=2)
    args = ap.parse_args()
    H, W = 154, 518

    P = read_kitti(find_kitti())
    t0 = time.perf_counter()
    world = build_world(P)
    t_world = time.perf_counter() - t0

    # ---- renderer: one block of 15 frames, JAX vs the NumPy reference
    K = kitti_intrinsics(W, H)
    frames = np.arange(1500, 1515)
    origin = P[frames[0], :3, 3]
    cand = chunk_candidates(world, P[frames, :3, 3], origin)
    planes = frame_planes(world, P[frames, :3, 3], origin)
    call = lambda: render_frames(  # noqa: E731
        K.astype(np.float32), P[frames, :3, :3].astype(np.float32),
        (P[frames, :3, 3] - origin).astype(np.float32), planes.astype(np.float32), cand,
        np.int32(world.num_boxes), height=H, width=W,
    )
    call()
    t_jax = best_of(call, args.repeats) / len(frames)
    nf = args.numpy_frames
    t_np = best_of(lambda: [render_numpy(world, K, P[f], H, W) for f in frames[:nf]], 1) / nf

    # ---- the full oracle pass
    sched = chunk_schedule(len(P), 75, 30)
    n_chunks = sched.num_chunks if args.max_chunks is None else min(args.max_chunks, sched.num_chunks)
    oracle = VGGTOracle(world, P)
    t0 = time.perf_counter()
    oracle.predict_chunk(np.arange(0, 40))  # warm-up: compiles (render, pixels, tokens)
    t_compile = time.perf_counter() - t0
    oracle._cache.clear()
    chunk_frames = 0
    c0 = time.process_time()  # CPU seconds of all threads: less sensitive to other users' load
    t0 = time.perf_counter()
    for t in range(n_chunks):
        pred = oracle.predict_chunk(sched.frames(t))
        chunk_frames += pred.num_frames
    t_pass = time.perf_counter() - t0
    cpu_pass = time.process_time() - c0
    seq_frames = int(sched.ends[n_chunks - 1])
    full_estimate = t_pass * sched.num_chunks / n_chunks

    rows = [
        ["world build (KITTI 00)", f"{t_world:.2f} s", f"{world.num_boxes} boxes, {world.num_cylinders} cylinders"],
        ["render, JAX (per frame)", f"{1e3 * t_jax:.1f} ms", "best of block of 15"],
        ["render, NumPy float64 reference (per frame)", f"{1e3 * t_np:.0f} ms", f"x{t_np / t_jax:.0f} slower"],
        ["oracle warm-up (compiles)", f"{t_compile:.1f} s", ""],
        [f"oracle pass, {n_chunks}/{sched.num_chunks} chunks", f"{t_pass:.1f} s",
         f"{seq_frames / t_pass:.0f} sequence frames/s, {chunk_frames / t_pass:.0f} chunk frames/s"],
        ["  CPU time of that pass (all threads)", f"{cpu_pass:.1f} s", f"{cpu_pass / t_pass:.2f} cores busy"],
        ["full KITTI 00 pass (extrapolated)", f"{full_estimate:.1f} s", "target < 60 s"],
    ]
    print(markdown_table(["step", "time", "note"], rows))
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    path = write_results("bench_oracle", {
        "image_hw": [H, W],
        "world_build_s": t_world,
        "render_jax_per_frame_s": t_jax,
        "render_numpy_per_frame_s": t_np,
        "render_speedup_vs_numpy": t_np / t_jax,
        "oracle_compile_s": t_compile,
        "chunks": n_chunks,
        "chunks_total": sched.num_chunks,
        "pass_s": t_pass,
        "pass_cpu_s": cpu_pass,
        "sequence_frames_per_s": seq_frames / t_pass,
        "chunk_frames_per_s": chunk_frames / t_pass,
        "full_pass_estimate_s": full_estimate,
        "load_average": load,
    })
    print(f"\nwrote {path.relative_to(ROOT)}  (load average {load})")


if __name__ == "__main__":
    main()

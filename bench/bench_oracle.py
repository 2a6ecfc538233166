"""Synthetic VGGT oracle throughput at 518 x 154: the whole KITTI 00 pass.

Measured in one run, the current implementation against the previous one (renderer + oracle
at the commit pinned in ``bench/_baseline.py``, loaded from git; skipped when unavailable):

* world construction around KITTI 00's ground truth (4,541 poses);
* one render block (15 frames): the jitted JAX ray caster, current vs previous, and the
  brute-force float64 NumPy reference (:func:`render_numpy`, every object, no culling);
* one pixel block (noise, confidence, colour of 15 frames), current vs previous;
* a partial oracle pass (the first ``--ab-chunks`` chunks, both implementations, best of
  ``--ab-repeats``, alternating) -> speed-up of the whole ``predict_chunk``;
* the full oracle pass: ``predict_chunk`` over the default chunk schedule (B = 75,
  O = 30: 101 chunks, 7,566 chunk-frames) with depth, confidence, images and place tokens,
  after one warm-up chunk (compiles excluded; caches cleared), best of ``--repeats`` ->
  seconds and frames/s; XLA compilations during the pass are counted (must be 0).

The machine is shared: every timing is best-of-N, CPU seconds (all threads) are reported
next to wall seconds, and the load average is recorded before and after.  Writes
``bench/results/bench_oracle-<timestamp>.json``.  Usage::

    .venv/bin/python bench/bench_oracle.py                 # full KITTI 00 pass
    .venv/bin/python bench/bench_oracle.py --max-chunks 20 --repeats 1   # quicker
"""

from __future__ import annotations

import argparse
import logging
import os
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _baseline import PREVIOUS_COMMIT, load_previous_oracle
from common import best_of, markdown_table, write_results

from swiftjax.chunks import chunk_schedule
from swiftjax.io.trajectory import read_kitti
from swiftjax.synthetic import pixel_noise
from swiftjax.synthetic.oracle import VGGTOracle, kitti_intrinsics
from swiftjax.synthetic.render import render_numpy
from swiftjax.synthetic.world import build_world


def find_kitti() -> pathlib.Path:
    env = os.environ.get("SWIFTJAX_SHARED")
    for base in ([pathlib.Path(env)] if env else []) + [ROOT.parent / "shared"]:
        p = base / "data/trajectories/KITTI_00_gt.txt"
        if p.is_file():
            return p
    raise SystemExit("KITTI_00_gt.txt not found: set SWIFTJAX_SHARED to the folder holding data/")


def load() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


class _CompileCounter(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        if record.getMessage().startswith("Compiling "):
            self.count += 1


def render_block_call(mod, world, P, frames, H, W):
    """A zero-argument call rendering ``frames`` with ``mod``'s renderer (same inputs for both)."""
    K = kitti_intrinsics(W, H)
    origin = P[frames[0], :3, 3]
    cand = mod.chunk_candidates(world, P[frames, :3, 3], origin)
    planes = mod.frame_planes(world, P[frames, :3, 3], origin)
    args = (
        K.astype(np.float32),
        P[frames, :3, :3].astype(np.float32),
        (P[frames, :3, 3] - origin).astype(np.float32),
        planes.astype(np.float32),
        cand,
        np.int32(world.num_boxes),
    )
    return lambda: mod.render_frames(*args, height=H, width=W)


def pixel_block_call(kernel, params, orc, frames):
    """A zero-argument call of the pixel kernel ``kernel`` (with its parameter tuple ``params``) on
    the true render of ``frames``."""
    z, sem, inst = orc.render_truth(frames)
    nz = orc.noise
    scalars = np.asarray(
        [
            nz.depth_rel,
            nz.depth_rel_ref_m,
            nz.edge_log_ratio,
            nz.edge_conf,
            nz.gross_fraction,
            nz.gross_log,
            nz.sky_depth_m,
            nz.conf_max,
            nz.conf_falloff_m,
            nz.chunk_share,
        ],
        np.float32,
    )
    p = params(
        np.uint32(1),
        np.uint32(2),
        frames.astype(np.int32),
        np.full(len(frames), 0.05, np.float32),
        np.float32(0.05),
        np.float32(1e-3),
        scalars,
    )
    return lambda: kernel(z, sem, inst, p)


def best_alternating(calls: list, repeat: int) -> list[float]:
    """Best wall time of each call, timed alternately (so load changes hit all of them alike)."""
    best = [np.inf] * len(calls)
    for _ in range(repeat):
        for i, c in enumerate(calls):
            best[i] = min(best[i], best_of(c, 1))
    return best


def run_pass(orc, sched, n_chunks: int) -> tuple[float, float, int]:
    """(wall s, CPU s, chunk frames) of ``predict_chunk`` over the first ``n_chunks`` chunks, cold caches."""
    orc._cache.clear()
    getattr(orc, "_token_cache", {}).clear()
    frames = 0
    c0, t0 = time.process_time(), time.perf_counter()
    for t in range(n_chunks):
        frames += orc.predict_chunk(sched.frames(t)).num_frames
    return time.perf_counter() - t0, time.process_time() - c0, frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-chunks", type=int, default=None, help="full pass over only this many chunks")
    ap.add_argument("--repeats", type=int, default=2, help="full passes (best of)")
    ap.add_argument("--ab-chunks", type=int, default=12, help="chunks of the current-vs-previous pass")
    ap.add_argument("--ab-repeats", type=int, default=2)
    ap.add_argument("--block-repeats", type=int, default=25, help="single-block timings (best of)")
    ap.add_argument("--numpy-frames", type=int, default=1)
    args = ap.parse_args()
    H, W = 154, 518
    load_start = load()

    P = read_kitti(find_kitti())
    t0 = time.perf_counter()
    world = build_world(P)
    t_world = time.perf_counter() - t0
    prev = load_previous_oracle()
    sched = chunk_schedule(len(P), 75, 30)
    n_chunks = sched.num_chunks if args.max_chunks is None else min(args.max_chunks, sched.num_chunks)
    from swiftjax.synthetic import render as render_mod

    # ---- one render block and one pixel block, current vs previous
    frames = np.arange(1500, 1515)
    orc = VGGTOracle(world, P)
    calls = [
        render_block_call(render_mod, world, P, frames, H, W),
        pixel_block_call(pixel_noise.pixel_block, pixel_noise.PixelParams, orc, frames),
    ]
    if prev is not None:
        calls += [
            render_block_call(sys.modules["_previous_render"], world, P, frames, H, W),
            pixel_block_call(prev._pixels, prev._PixelParams, orc, frames),
        ]
    for c in calls:
        c()  # compile
    overflow = int(np.asarray(calls[0]().tile_overflow).sum())
    times = [t / len(frames) for t in best_alternating(calls, args.block_repeats)]
    t_render, t_pix = times[:2]
    t_render_prev, t_pix_prev = times[2:] if prev is not None else (None, None)
    nf = args.numpy_frames
    K = kitti_intrinsics(W, H)
    t_np = best_of(lambda: [render_numpy(world, K, P[f], H, W) for f in frames[:nf]], 1) / nf

    # ---- predict_chunk, current vs previous on the first chunks (alternating, best of)
    t0 = time.perf_counter()
    orc.predict_chunk(np.arange(0, 40))  # warm-up: compiles (render, pixels, tokens)
    t_compile = time.perf_counter() - t0
    ab = None
    if prev is not None and args.ab_chunks > 0:
        orc_prev = prev.VGGTOracle(world, P)
        orc_prev.predict_chunk(np.arange(0, 40))
        m = min(args.ab_chunks, sched.num_chunks)
        best_new, best_old = (np.inf, np.inf), (np.inf, np.inf)
        for _ in range(args.ab_repeats):
            w, c, _ = run_pass(orc_prev, sched, m)
            best_old = min(best_old, (w, c))
            w, c, _ = run_pass(orc, sched, m)
            best_new = min(best_new, (w, c))
        ab = {
            "chunks": m,
            "current_s": best_new[0],
            "current_cpu_s": best_new[1],
            "previous_s": best_old[0],
            "previous_cpu_s": best_old[1],
            "speedup_wall": best_old[0] / best_new[0],
            "speedup_cpu": best_old[1] / best_new[1],
        }

    # ---- the full pass (cold caches each time; compilations counted)
    counter = _CompileCounter()
    jax_logger = logging.getLogger("jax")
    jax_logger.addHandler(counter)
    propagate, jax_logger.propagate = jax_logger.propagate, False
    import jax

    passes = []
    load_pass = []
    with jax.log_compiles(True):
        for _ in range(args.repeats):
            passes.append(run_pass(orc, sched, n_chunks))
            load_pass.append(load())
    jax_logger.removeHandler(counter)
    jax_logger.propagate = propagate
    t_pass, cpu_pass, chunk_frames = min(passes)
    seq_frames = int(sched.ends[n_chunks - 1])
    full_estimate = t_pass * sched.num_chunks / n_chunks

    x = lambda a, b: f"x{a / b:.2f}" if a is not None else "n/a"
    rows = [
        ["world build (KITTI 00)", f"{t_world:.2f} s", f"{world.num_boxes} boxes, {world.num_cylinders} cylinders"],
        ["render, JAX, current (per frame)", f"{1e3 * t_render:.2f} ms", f"block of 15, tile overflow {overflow}"],
        [
            "render, JAX, previous (per frame)",
            f"{1e3 * t_render_prev:.2f} ms" if t_render_prev else "n/a",
            f"current is {x(t_render_prev, t_render)} faster",
        ],
        [
            "render, NumPy float64 reference (per frame)",
            f"{1e3 * t_np:.0f} ms",
            f"current is x{t_np / t_render:.0f} faster",
        ],
        ["noise/conf/colour, current (per frame)", f"{1e3 * t_pix:.2f} ms", "block of 15"],
        [
            "noise/conf/colour, previous (per frame)",
            f"{1e3 * t_pix_prev:.2f} ms" if t_pix_prev else "n/a",
            f"current is {x(t_pix_prev, t_pix)} faster",
        ],
        ["oracle warm-up (compiles)", f"{t_compile:.1f} s", ""],
    ]
    if ab is not None:
        rows += [
            [
                f"predict_chunk, first {ab['chunks']} chunks, previous",
                f"{ab['previous_s']:.2f} s",
                f"{ab['previous_cpu_s']:.2f} CPU s",
            ],
            [
                f"predict_chunk, first {ab['chunks']} chunks, current",
                f"{ab['current_s']:.2f} s",
                f"{ab['current_cpu_s']:.2f} CPU s; x{ab['speedup_wall']:.2f} wall, x{ab['speedup_cpu']:.2f} CPU",
            ],
        ]
    rows += [
        [
            f"oracle pass, {n_chunks}/{sched.num_chunks} chunks (best of {len(passes)})",
            f"{t_pass:.1f} s",
            f"{seq_frames / t_pass:.0f} sequence frames/s, {chunk_frames / t_pass:.0f} chunk frames/s",
        ],
        ["  CPU time of that pass (all threads)", f"{cpu_pass:.1f} s", f"{cpu_pass / t_pass:.2f} cores busy"],
        ["  XLA compilations during the passes", f"{counter.count}", "must be 0"],
        [
            "full KITTI 00 pass" + (" (extrapolated)" if n_chunks < sched.num_chunks else ""),
            f"{full_estimate:.1f} s",
            "target < 60 s",
        ],
    ]
    print(markdown_table(["step", "time", "note"], rows))
    load_end = load()
    path = write_results(
        "bench_oracle",
        {
            "image_hw": [H, W],
            "previous_commit": PREVIOUS_COMMIT if prev is not None else None,
            "world_build_s": t_world,
            "render_jax_per_frame_s": t_render,
            "render_previous_per_frame_s": t_render_prev,
            "render_speedup_vs_previous": (t_render_prev / t_render) if t_render_prev else None,
            "render_tile_overflow": overflow,
            "render_numpy_per_frame_s": t_np,
            "render_speedup_vs_numpy": t_np / t_render,
            "pixels_per_frame_s": t_pix,
            "pixels_previous_per_frame_s": t_pix_prev,
            "pixels_speedup_vs_previous": (t_pix_prev / t_pix) if t_pix_prev else None,
            "oracle_compile_s": t_compile,
            "ab_pass": ab,
            "chunks": n_chunks,
            "chunks_total": sched.num_chunks,
            "pass_s": t_pass,
            "pass_cpu_s": cpu_pass,
            "passes_s": [p[0] for p in passes],
            "sequence_frames_per_s": seq_frames / t_pass,
            "chunk_frames_per_s": chunk_frames / t_pass,
            "full_pass_estimate_s": full_estimate,
            "compiles_during_pass": counter.count,
            "load_average": {"start": load_start, "after_each_pass": load_pass, "end": load_end},
        },
    )
    print(f"\nwrote {path.relative_to(ROOT)}  (load average: start {load_start}, passes {load_pass}, end {load_end})")


if __name__ == "__main__":
    main()

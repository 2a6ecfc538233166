"""Loop-detection timings (swiftjax.loops) against same-run anchors.

* descriptor reduction of one chunk of patch tokens (75 x 407 x 1024 float32, 125 MB) vs
  (a) one memory-bound pass over the same tokens (``jnp.sum``) and (b) the same formula in
  NumPy;
* whitening fit on N x 1024 descriptors (eigh of the 1024 x 1024 covariance) vs NumPy;
* loop detection (blocked similarity + per-row top-8 + NMS) on N x 512 whitened descriptors
  vs the GEMM roofline anchor: the dense N x N x 512 matrix product alone (``Z @ Z.T``);
* end to end for KITTI 00 (N = 4,541 synthetic descriptors -> ``find_loops``) vs the paper's
  1.19 s (GPU workstation).

N = 4,541 (KITTI 00 synthetic descriptors) and N = 20,000 (the KITTI 00 trajectory driven
4.4 times, each copy shifted 2 km so copies do not match each other).  Best-of-N wall clock
on a shared 2-core CPU; compile times separately.

LAPACK threads: the whitening fit's ``eigh`` is a LAPACK call into OpenBLAS (XLA's GEMMs do
not use OpenBLAS).  On the shared 2-core machine, multi-threaded OpenBLAS ``ssyevd`` on
1024 x 1024 was ~10x slower than single-threaded (2.3 s vs 0.22 s, same minute), so this
script sets ``OPENBLAS_NUM_THREADS=1`` unless it is already set (``--blas-threads`` overrides).

Usage:  .venv/bin/python bench/bench_loops.py [--repeat 5] [--skip-20k] [--blas-threads N]
"""

from __future__ import annotations

import os
import sys

if "--blas-threads" in sys.argv:  # must happen before numpy / jax load OpenBLAS
    os.environ["OPENBLAS_NUM_THREADS"] = sys.argv[sys.argv.index("--blas-threads") + 1]
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from bench.bench_place_recognition import load_kitti00, synthetic_descriptors
from bench.common import best_of, markdown_table, write_results
from swiftjax import loops as L
from swiftjax.chunks import chunk_schedule
from swiftjax.loops import detection
from swiftjax.synthetic import places


def np_descriptor(tokens: np.ndarray) -> np.ndarray:
    t = tokens / np.linalg.norm(tokens, axis=-1, keepdims=True)
    g = t.mean(-2)
    return g / np.linalg.norm(g, axis=-1, keepdims=True)


def np_fit(G: np.ndarray, remove=1, dim=512, eps=1e-6):
    mu = G.mean(0)
    X = G - mu
    lam, Q = np.linalg.eigh(X.T @ X / len(G))
    lam, Q = lam[::-1], Q[:, ::-1]
    return mu, Q[:, remove : remove + dim] / np.sqrt(lam[remove : remove + dim] + eps)


def timed_first(fn):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--skip-20k", action="store_true")
    ap.add_argument(
        "--blas-threads",
        type=int,
        default=None,
        help="OPENBLAS_NUM_THREADS for LAPACK (default 1, see the module docstring)",
    )
    args = ap.parse_args()
    rep = args.repeat
    rows, out = [], {}

    # ---- descriptor reduction, one chunk
    rng = np.random.default_rng(0)
    tokens = jnp.asarray(rng.normal(size=(75, 407, 1024)).astype(np.float32))
    tok_np = np.asarray(tokens)
    first = timed_first(lambda: L.frame_descriptor(tokens))
    t_desc = best_of(lambda: L.frame_descriptor(tokens), rep)
    read_once = jax.jit(lambda x: jnp.sum(x))
    read_once(tokens)
    t_read = best_of(lambda: read_once(tokens), rep)
    t_np = best_of(lambda: np_descriptor(tok_np), max(2, rep // 2))
    gbps = tokens.nbytes / t_desc / 1e9
    rows.append(
        [
            "g0 of one chunk 75x407x1024",
            f"{t_desc * 1e3:.1f} ms",
            f"{t_desc / t_read:.2f}x one read pass ({t_read * 1e3:.1f} ms); "
            f"NumPy {t_np / t_desc:.1f}x slower; {gbps:.1f} GB/s",
            f"{first:.2f}",
        ]
    )
    out["descriptor_chunk"] = dict(t=t_desc, t_read_pass=t_read, t_numpy=t_np, first_call=first)

    # ---- KITTI 00 synthetic descriptors
    poses = load_kitti00()
    G = synthetic_descriptors(poses, places.PlaceTokenConfig(tokens_per_frame=16, seed=0))
    sets = {4541: (G, poses)}
    if not args.skip_20k:
        reps = -(-20_000 // len(poses))
        big = np.concatenate([poses] * reps)[:20_000].copy()
        big[:, 0, 3] += np.repeat(np.arange(reps) * 2000.0, len(poses))[:20_000]
        Gb = synthetic_descriptors(big, places.PlaceTokenConfig(tokens_per_frame=8, seed=0))
        sets[20_000] = (Gb, big)

    for n, (Gn, _) in sets.items():
        g1 = L.power_normalize(jnp.asarray(Gn))
        first = timed_first(lambda: L.fit_whitening(g1))
        t_fit = best_of(lambda: L.fit_whitening(g1), rep)
        g1_np = np.asarray(g1)
        t_fit_np = best_of(lambda: np_fit(g1_np), max(2, rep // 2))
        rows.append(
            [
                f"fit_whitening N={n}, d=1024 -> 512",
                f"{t_fit * 1e3:.0f} ms",
                f"NumPy (same eigh) takes {t_fit_np / t_fit:.2f}x our time",
                f"{first:.2f}",
            ]
        )
        w = L.fit_whitening(g1)
        Z = L.whiten(w, g1)
        t_wh = best_of(lambda: L.whiten(w, g1), rep)

        gemm = jax.jit(lambda z: z @ z.T)
        gemm(Z)
        t_gemm = best_of(lambda: gemm(Z), rep)
        # the same GEMM in the detector's row tiles with the cheapest epilogue (row max):
        # the compute roofline without writing N*N floats to memory
        T = detection._default_block_rows(n)

        @jax.jit
        def gemm_tiles(z):
            zp = jnp.pad(z, ((0, -(-n // T) * T - n), (0, 0)))
            return jax.lax.map(
                lambda t: jnp.max(jax.lax.dynamic_slice_in_dim(zp, t * T, T, 0) @ z.T, axis=1), jnp.arange(-(-n // T))
            )

        gemm_tiles(Z)
        t_gemm_t = best_of(lambda: gemm_tiles(Z), rep)
        first = timed_first(lambda: L.detect_loops(Z))
        t_det = best_of(lambda: L.detect_loops(Z), rep)
        cand = L.detect_loops(Z)
        gflops = 2 * n * n * Z.shape[1] / t_gemm / 1e9
        rows.append(
            [
                f"detect_loops N={n}, d'=512 (top-8, NMS)",
                f"{t_det * 1e3:.0f} ms",
                f"{t_det / t_gemm:.2f}x the dense N*N*512 GEMM alone ({t_gemm * 1e3:.0f} ms, "
                f"{gflops:.0f} GFLOP/s); {t_det / t_gemm_t:.2f}x the same GEMM in {T}-row "
                f"tiles ({t_gemm_t * 1e3:.0f} ms); {int(cand.count)} pairs before chunk filter",
                f"{first:.2f}",
            ]
        )
        out[f"n{n}"] = dict(
            t_fit=t_fit,
            t_fit_numpy=t_fit_np,
            t_whiten=t_wh,
            t_gemm=t_gemm,
            t_gemm_tiles=t_gemm_t,
            t_detect=t_det,
            detect_over_gemm=t_det / t_gemm,
            n_pairs=int(cand.count),
        )
        if n == 4541:
            dense = best_of(lambda: L.detect_loops(Z, block_rows=n), rep)
            rows.append(["  same, one dense N x N tile", f"{dense * 1e3:.0f} ms", f"{dense / t_gemm:.2f}x GEMM", "-"])
            out[f"n{n}"]["t_detect_dense"] = dense
            sched = chunk_schedule(n)
            first = timed_first(lambda: L.find_loops(Gn, sched))
            t_e2e = best_of(lambda: L.find_loops(Gn, sched), rep)
            nl = len(L.find_loops(Gn, sched))
            rows.append(
                [
                    "find_loops KITTI 00 (g0 -> loop list)",
                    f"{t_e2e * 1e3:.0f} ms",
                    f"{t_e2e / 1.19:.2f}x the paper's 1.19 s (GPU); {nl} loops; {t_e2e / t_gemm:.2f}x GEMM",
                    f"{first:.2f}",
                ]
            )
            out["find_loops_kitti00"] = dict(t=t_e2e, vs_paper=t_e2e / 1.19, first_call=first, n_loops=nl)

    print(markdown_table(["step", "best time", "vs same-run anchor", "first call s (compile)"], rows))
    out["openblas_num_threads"] = os.environ.get("OPENBLAS_NUM_THREADS")
    out["load_average"] = os.getloadavg()
    print(f"OPENBLAS_NUM_THREADS={out['openblas_num_threads']}, load average {out['load_average']}")
    path = write_results("loops", out)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

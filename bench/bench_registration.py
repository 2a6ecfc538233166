"""The co-visible registration's robust Sim(3) ICP (``swiftjax.loops.geometric.register``):
its nearest-neighbour index found by block (``geometric._nearest``) vs the former second full
reduction over ``[P, Q]`` and vs the product form ``|y|² − 2 y·x + |x|²`` (a matrix product,
centred on the target's weighted centroid to bound its float32 cancellation, then ``argmin``),
in the same run, on the batches the loop-geometry stage runs.

Rows: the peak ICP (``peaks_batch``: ``PEAK_BATCH`` jobs x ``peaks`` starts, ``peak_src_points
x peak_dst_points``, ``coarse_iterations``) and the refinement (``refine_batch``: ``REFINE_BATCH``
jobs, ``src_points x dst_points``, ``refine_iterations``), default ``GeometryOptions``.  Both
variants are compiled ahead (compile time not counted) and timed best of N on the same inputs
(two street-like point clouds, the second a rotated, scaled, noisy copy of the first); the
former's results must be bitwise equal to the block's (column "same"); the product form's
need not be (column "product same").  Wall and process CPU time, the ratios former / block and
product / block per row.

    python bench/bench_registration.py [--repeat 10]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from common import best_of, report_kernels

from swiftjax import sim3
from swiftjax.loops import geometric
from swiftjax.pipeline.loop_geometry import PEAK_BATCH, REFINE_BATCH


def _two_reductions(y, dst, w_dst):
    """The former ``_nearest``: the minimum, then the first index holding it, two full passes."""
    d2 = (y[:, 0:1] - dst[None, :, 0]) ** 2 + (y[:, 1:2] - dst[None, :, 1]) ** 2 + (y[:, 2:3] - dst[None, :, 2]) ** 2
    d2 = jnp.where(w_dst[None, :] > 0, d2, jnp.inf)
    m = jnp.min(d2, -1)
    Q = d2.shape[-1]
    k = jnp.min(jnp.where(d2 == m[:, None], jnp.arange(Q, dtype=jnp.int32)[None, :], Q - 1), -1)
    return k, jnp.sqrt(m)


def _product_form(y, dst, w_dst):
    """The product form: ``d² = |y − c|² − 2 (y − c)·(x − c) + |x − c|²`` by one ``[P, 3] x [3, Q]``
    matrix product (``c`` the targets' weighted centroid), the index by ``argmin``, the distance
    recomputed from the chosen target."""
    c = jnp.sum(dst * w_dst[:, None], 0) / jnp.maximum(jnp.sum(w_dst), 1.0)
    yc, xc = y - c, dst - c
    d2 = jnp.sum(yc * yc, -1)[:, None] - 2.0 * yc @ xc.T + jnp.sum(xc * xc, -1)[None, :]
    k = jnp.argmin(jnp.where(w_dst[None, :] > 0, d2, jnp.inf), -1).astype(jnp.int32)
    e = y - dst[k]
    return k, jnp.sqrt(jnp.sum(e * e, -1))


@contextlib.contextmanager
def _nearest_as(fn):
    """Trace with ``geometric._nearest = fn`` (jit caches cleared on the way in and out)."""
    saved = geometric._nearest
    geometric._nearest = fn
    jax.clear_caches()
    try:
        yield
    finally:
        geometric._nearest = saved
        jax.clear_caches()


def _street(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` points on two facades and a road, 40 x 12 camera heights, with noise."""
    side = rng.integers(0, 3, n)
    x = rng.uniform(-20, 20, n)
    y = np.where(side == 0, -6.0, np.where(side == 1, 6.0, rng.uniform(-6, 6, n)))
    z = np.where(side == 2, 0.0, rng.uniform(0, 4, n))
    return (np.stack([x, y, z], -1) + 0.05 * rng.normal(size=(n, 3))).astype(np.float32)


def _case(rng, batch: int, P: int, Q: int, iterations: int, tau_start: float, tau_end: float):
    src = np.stack([_street(rng, P) for _ in range(batch)])
    dst = np.stack([_street(rng, Q) for _ in range(batch)])
    S0 = np.stack([sim3.from_rst(jnp.eye(3), jnp.asarray(rng.normal(size=3), jnp.float32), 1.05) for _ in range(batch)])
    args = (src, np.ones((batch, P), np.float32), dst, np.ones((batch, Q), np.float32), np.asarray(S0))
    up = jnp.asarray([0.0, 0.0, 1.0])

    def one(s, ws, d, wd, S):
        return geometric.register(s, ws, d, wd, S, 1.0, up, 0.0, tau_start, tau_end, 0.35, iterations=iterations)

    return jax.jit(jax.vmap(one)), tuple(jnp.asarray(a) for a in args)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=10)
    args = ap.parse_args()
    o = geometric.GeometryOptions()
    rng = np.random.default_rng(0)
    cases = {
        "peak ICP": (PEAK_BATCH * o.peaks, o.peak_src_points, o.peak_dst_points, o.coarse_iterations, o.tau_start),
        "refinement": (REFINE_BATCH, o.src_points, o.dst_points, o.refine_iterations, o.coarse_tau_end),
    }
    load = os.getloadavg()
    rows, records = [], []
    for name, (batch, P, Q, iterations, tau0) in cases.items():
        fn, inputs = _case(rng, batch, P, Q, iterations, tau0, o.tau_end)
        timed, outs = {}, {}
        variants = (("block", geometric._nearest), ("former", _two_reductions), ("product", _product_form))
        for variant, nearest in variants:
            with _nearest_as(nearest):
                compiled = fn.lower(*inputs).compile()
            outs[variant] = jax.device_get(compiled(*inputs))
            wall = best_of(lambda c=compiled: c(*inputs), args.repeat)
            t0 = time.process_time()
            for _ in range(args.repeat):
                jax.block_until_ready(compiled(*inputs))
            timed[variant] = (wall, (time.process_time() - t0) / args.repeat)
        same = {
            v: all(np.array_equal(a, b, equal_nan=True) for a, b in zip(outs["block"], outs[v]))
            for v in ("former", "product")
        }
        ratio = timed["former"][0] / timed["block"][0]
        product = timed["product"][0] / timed["block"][0]
        rows.append(
            [
                name,
                f"{batch} x {P} x {Q} x {iterations + 1}",
                f"{1e3 * timed['block'][0]:.1f}",
                f"{1e3 * timed['former'][0]:.1f}",
                f"{1e3 * timed['product'][0]:.1f}",
                f"{ratio:.2f}x",
                f"{timed['former'][1] / timed['block'][1]:.2f}x",
                f"{product:.2f}x",
                "yes" if same["former"] else "NO",
                "yes" if same["product"] else "no",
            ]
        )
        records.append(
            {
                "case": name,
                "batch": batch,
                "src_points": P,
                "dst_points": Q,
                "passes": iterations + 1,
                "block_seconds": timed["block"][0],
                "former_seconds": timed["former"][0],
                "block_cpu_seconds": timed["block"][1],
                "former_cpu_seconds": timed["former"][1],
                "product_seconds": timed["product"][0],
                "product_cpu_seconds": timed["product"][1],
                "speedup": ratio,
                "product_over_block": product,
                "bitwise_equal": same["former"],
                "product_bitwise_equal": same["product"],
            }
        )
    header = [
        "batch",
        "registrations x P x Q x passes",
        "block ms",
        "former ms",
        "product ms",
        "speed-up",
        "CPU ratio",
        "product / block",
        "same",
        "product same",
    ]
    report_kernels("registration", header, rows, records, load)


if __name__ == "__main__":
    main()

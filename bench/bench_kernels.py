"""The seventh cost pass's kernels against the code they replaced, in the same run, same inputs.

Rows (each variant jitted and compiled before timing, best of ``--repeat``; the results must be
bitwise equal, column "same"):

* **dense test, 3 neighbours**: ``cross_chunk._dense_consistency`` (one pass per neighbour rank,
  each frame's target gathered) against the former loop over every target frame with the
  non-neighbour pairs masked out (kept below as the baseline), one direction, 20 frames a side
  of 154 x 518 (a token candidate's sides), stride 4;
* **dense null**: the same under the null's 16 sideways-shifted edges (``vmap``), both
  directions, as ``loops.null`` runs it;
* **median of heights**: ``_select.nanmedian`` against ``jnp.nanmedian``, 8 chunks of
  15 x 26 x 65 heights, 90 % NaN (``chunk_frame``'s band);
* **small product**: ``_products.small_matmul`` against ``@``, a chunk's 25,350 points
  against 5 anchors onto 2 axes (``path_weights``), 16 chunks.

    python bench/bench_kernels.py [--repeat 10]
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np
from common import best_of, report_kernels
from jax import lax

from swiftjax import align, camera, sim3
from swiftjax._products import small_matmul
from swiftjax._select import nanmedian
from swiftjax.loops import cross_chunk as cc
from swiftjax.loops.null import null_edges, null_offsets


def _former_dense(src, dst, S, K_ref, conf_ratio, depth_tolerance, stride, neighbours):
    """The dense test before the seventh pass: every source point projected into every target
    frame (``lax.scan`` over the frames), the pairs that are not a neighbour's masked out."""
    G, h, w = dst.depth.shape
    d_src = cc._normalised(src, K_ref, conf_ratio)[:, ::stride, ::stride]
    rays = camera.pixel_rays(K_ref, h, w)[::stride, ::stride]
    c2w = camera.camera_to_world(src.extrinsic)
    x = jnp.einsum("fij,fhwj->fhwi", c2w[:, :, :3], d_src[..., None] * rays) + c2w[:, None, None, :, 3]
    n_per = x.shape[1] * x.shape[2]
    ok = jnp.all(jnp.isfinite(x), -1).reshape(-1)
    y = sim3.act(S, jnp.where(ok[:, None], x.reshape(-1, 3), 0))
    ok = ok & jnp.all(jnp.isfinite(y), -1)
    centres = sim3.act(S, c2w[:, :, 3])
    dist = jnp.linalg.norm(centres[:, None, :] - camera.camera_to_world(dst.extrinsic)[None, :, :, 3], axis=-1)
    pair = jnp.argsort(jnp.argsort(jnp.where(jnp.isfinite(dist), dist, jnp.inf), axis=1), axis=1) < neighbours
    d_dst = cc._normalised(dst, K_ref, conf_ratio).reshape(G, -1)
    fx, fy, cx, cy, sk = K_ref[0, 0], K_ref[1, 1], K_ref[0, 2], K_ref[1, 2], K_ref[0, 1]

    def step(carry, xs):
        seen, agree, n_seen, n_agree, n_front = carry
        depth_g, E, pair_g = xs
        p = small_matmul(y, E[:, :3].T) + E[None, :, 3]
        z = p[:, 2]
        use = ok & jnp.repeat(pair_g, n_per, total_repeat_length=y.shape[0]) & (z > 0)
        zs = jnp.where(use, z, 1)
        u = jnp.round(fx * p[:, 0] / zs + sk * p[:, 1] / zs + cx)
        v = jnp.round(fy * p[:, 1] / zs + cy)
        inside = use & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        D = depth_g[jnp.where(inside, v * w + u, 0).astype(jnp.int32)]
        view = inside & jnp.isfinite(D)
        good = view & (jnp.abs(z - D) <= depth_tolerance * D)
        front = view & (z < (1 - depth_tolerance) * D)
        count = lambda m: jnp.sum(m, dtype=jnp.int32)
        return (seen | view, agree | good, n_seen + count(view), n_agree + count(good), n_front + count(front)), None

    zero = jnp.zeros((), jnp.int32)
    init = (jnp.zeros(y.shape[0], bool), jnp.zeros(y.shape[0], bool), zero, zero, zero)
    (seen, agree, n_seen, n_agree, n_front), _ = lax.scan(step, init, (d_dst, dst.extrinsic, pair.T))
    return jnp.sum(ok), jnp.sum(seen), jnp.sum(agree), n_seen, n_agree, n_front


def _new_dense(*args):
    """The current dense test, its integer counts in :func:`_former_dense`'s order."""
    r = cc._dense_consistency(*args)
    return r.num_points, r.num_seen, r.num_agree, r.pairs_seen, r.pairs_agree, r.pairs_front


def _frames(n: int, first: int, H: int, W: int, K: np.ndarray) -> align.ChunkFrames:
    """``n`` frames of a camera driving along its optical axis (0.3 per frame) towards a
    textured wall 30 units ahead of the first: depth, confidence, intrinsics, extrinsics."""
    z0 = 0.3 * np.arange(first, first + n, dtype=np.float32)
    u = np.arange(W, dtype=np.float32)[None, :]
    depth = (30.0 - z0)[:, None, None] * (1.0 + 0.03 * np.sin(u / 9.0))[None] * np.ones((1, H, 1), np.float32)
    E = np.zeros((n, 3, 4), np.float32)
    E[:, :, :3] = np.eye(3)
    E[:, 2, 3] = -z0
    return align.ChunkFrames(
        depth.astype(np.float32), np.ones((n, H, W), np.float32), np.broadcast_to(K, (n, 3, 3)).copy(), E
    )


def _time(name, shape, new, former, inputs, repeat):
    timed, outs = {}, {}
    for variant, fn in (("new", new), ("former", former)):
        compiled = jax.jit(fn).lower(*inputs).compile()
        outs[variant] = jax.device_get(compiled(*inputs))
        timed[variant] = best_of(lambda c=compiled: c(*inputs), repeat)
    leaves = zip(jax.tree_util.tree_leaves(outs["new"]), jax.tree_util.tree_leaves(outs["former"]))
    same = all(np.array_equal(a, b, equal_nan=True) for a, b in leaves)
    ratio = timed["former"] / timed["new"]
    row = [
        name,
        shape,
        f"{1e3 * timed['new']:.1f}",
        f"{1e3 * timed['former']:.1f}",
        f"{ratio:.2f}x",
        "yes" if same else "NO",
    ]
    record = {"case": name, "shape": shape, "new_seconds": timed["new"], "former_seconds": timed["former"]}
    return row, {**record, "speedup": ratio, "bitwise_equal": same}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=10)
    args = ap.parse_args()
    load = os.getloadavg()
    rng = np.random.default_rng(0)
    H, W = 154, 518
    K = np.array([[400.0, 0.0, 259.0], [0.0, 400.0, 77.0], [0.0, 0.0, 1.0]], np.float32)
    src, dst = _frames(20, 0, H, W, K), _frames(20, 10, H, W, K)
    S = np.asarray(sim3.exp(jnp.asarray([0.05, -0.02, 0.1, 0.01, 0.02, -0.01, 0.03], jnp.float32)))
    consts = (jnp.asarray(K), jnp.float32(0.5), jnp.float32(0.05))
    one = lambda dense: lambda s, d, z: dense(s, d, z, *consts, 4, 3)

    def null(dense):
        def run(s, d, z):
            depth = nanmedian(cc._normalised(d, consts[0], consts[1])[:, ::4, ::4])
            nulls = null_edges(z, d.extrinsic, depth, null_offsets(16, 0.15, 0.4))
            both = lambda e: (one(dense)(s, d, e), one(dense)(d, s, sim3.inverse(e)))
            return jax.vmap(both)(nulls)

        return run

    heights = rng.normal(-1.6, 0.2, size=(8, 15, 26, 65)).astype(np.float32)
    heights[rng.random(heights.shape) < 0.9] = np.nan
    rel = rng.normal(size=(16, 5, 25350, 3)).astype(np.float32) * 20
    basis = np.linalg.qr(rng.normal(size=(16, 3, 3)))[0][:, :, :2].astype(np.float32)
    cases = [
        (
            "dense test, 3 neighbours",
            "20 x 20 frames, 154 x 518, stride 4",
            one(_new_dense),
            one(_former_dense),
            (src, dst, S),
        ),
        ("dense null", "16 edges x 2 directions", null(_new_dense), null(_former_dense), (src, dst, S)),
        ("median of heights", "8 x 25,350 (90 % NaN)", jax.vmap(nanmedian), jax.vmap(jnp.nanmedian), (heights,)),
        (
            "small product",
            "16 x 5 x 25,350 x 3 @ 3 x 2",
            jax.vmap(small_matmul),
            jax.vmap(lambda x, M: x @ M),
            (rel, basis),
        ),
    ]
    rows, records = [], []
    for name, shape, new, former, inputs in cases:
        row, record = _time(name, shape, new, former, inputs, args.repeat)
        rows.append(row)
        records.append(record)
    report_kernels("kernels", ["kernel", "shape", "new ms", "former ms", "speed-up", "same"], rows, records, load)


if __name__ == "__main__":
    main()

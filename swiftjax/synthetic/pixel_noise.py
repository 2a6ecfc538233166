"""The synthetic oracle's pixel kernel: depth, confidence and colour of a block of frames from their
true depth, semantics and instances (the noise model is in :mod:`swiftjax.synthetic.oracle`)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax.synthetic.hash_rng import approx_normal, hash32, uniform16
from swiftjax.synthetic.world import CAR, SKY

__all__ = ["PixelParams", "pixel_block"]


class PixelParams(NamedTuple):
    frame_key: jax.Array  # uint32 [] keyed by seed
    chunk_key: jax.Array  # uint32 [] keyed by (seed, frames)
    frames: jax.Array  # [F] int32
    depth_factor: jax.Array  # [F] sigma_c s_k (1+eps)^coupling
    sigma: jax.Array  # [] chunk units per metre
    bias: jax.Array  # [] per chunk unit
    scalars: jax.Array  # [10] noise scalars


def _upsample_patches(x: jax.Array, H: int, W: int, p: int = 14) -> jax.Array:
    """``[F, ceil(H/p), ceil(W/p)]`` -> ``[F, H, W]`` by repetition (a broadcast, no gather)."""
    F, hp, wp = x.shape
    y = jnp.broadcast_to(x[:, :, None, :, None], (F, hp, p, wp, p)).reshape(F, hp * p, wp * p)
    return y[:, :H, :W]


_PALETTE = np.array(  # per semantic id: sky (unused), ground, building, pole, tree, car
    [
        [0.0, 0.0, 0.0],
        [0.42, 0.42, 0.44],
        [0.72, 0.62, 0.52],
        [0.35, 0.35, 0.38],
        [0.20, 0.45, 0.18],
        [0.70, 0.12, 0.10],
    ],
    np.float32,
)
_FACADES = np.array([[0.72, 0.62, 0.52], [0.80, 0.78, 0.70], [0.60, 0.45, 0.38], [0.55, 0.58, 0.62]], np.float32)


def _albedo(sem: jax.Array, inst: jax.Array) -> jax.Array:
    """``[F, H, W, 3]`` surface colour from semantic id and instance (where-chains, no gathers)."""
    h = hash32(inst.astype(jnp.uint32) + jnp.uint32(0x2545F491))
    base = jnp.zeros((*sem.shape, 3), jnp.float32)
    for k in range(1, len(_PALETTE)):
        base = jnp.where((sem == k)[..., None], _PALETTE[k], base)
    pick = h & jnp.uint32(3)
    for k in range(len(_FACADES)):
        base = jnp.where(((sem == 2) & (pick == k))[..., None], _FACADES[k], base)
    return base * (0.85 + 0.3 * uniform16(h, True))[..., None]


@jax.jit
def pixel_block(z: jax.Array, sem: jax.Array, inst: jax.Array, p: PixelParams):
    """Depth, confidence and colour of ``F`` frames from their true depth ``[F, H, W]``.

    One jitted function per ``(F, H, W)``.  Noise (:mod:`swiftjax.synthetic.oracle`): per pixel, one hash of
    ``(frame key, frame, pixel)`` and one of ``(chunk key, frame, pixel)``, each giving an
    approximately normal value, plus re-mixed hashes for the uniforms; patch noise is drawn
    per 14x14 patch and repeated.

    Two stages: the terms that read other pixels (the 4-neighbourhood of the log-depth, the
    patch noise repeated over 14x14 pixels) are computed first, inside a ``lax.cond`` branch
    (always taken, but XLA neither fuses nor CSEs across it), and everything else is one
    purely elementwise kernel.  Fused together, XLA treated every pixel value as re-used
    and materialised the expensive intermediates (``exp``, ``log``; docs/performance/synthetic.md).
    """
    (depth_rel, rel_ref, edge_lr, edge_conf, gross_frac, gross_log, sky_m, conf_max, falloff, share, mover_depth) = (
        p.scalars[i] for i in range(11)
    )
    F, H, W = z.shape
    fr = hash32(p.frames.astype(jnp.uint32) * jnp.uint32(0x9E3779B9))[:, None, None]
    kf = hash32(p.frame_key ^ fr)  # [F, 1, 1] per-frame bases
    kc = hash32(p.chunk_key ^ fr)
    a, b = jnp.sqrt(1.0 - share), jnp.sqrt(share)

    def neighbourhood_terms(z, sem):
        zf = jnp.where(sem == SKY, sky_m, z)  # finite stand-in for the sky
        # discontinuities: max |log z - log z_nb| over the 4-neighbourhood
        lz = jnp.log(zf)
        pad = jnp.pad(lz, ((0, 0), (1, 1), (1, 1)), mode="edge")
        nbs = [pad[:, 0:-2, 1:-1], pad[:, 2:, 1:-1], pad[:, 1:-1, 0:-2], pad[:, 1:-1, 2:]]
        lmax = jnp.maximum(jnp.maximum(nbs[0], nbs[1]), jnp.maximum(nbs[2], nbs[3]))
        lmin = jnp.minimum(jnp.minimum(nbs[0], nbs[1]), jnp.minimum(nbs[2], nbs[3]))
        edge = jnp.maximum(lmax - lz, lz - lmin) > edge_lr
        hp, wp = -(-H // 14), -(-W // 14)
        pidx = (jnp.arange(hp, dtype=jnp.uint32)[:, None] * jnp.uint32(wp) + jnp.arange(wp, dtype=jnp.uint32)[None, :])[
            None
        ]
        pf = hash32(kf ^ (pidx + jnp.uint32(0x1B873593)))
        pc = hash32(kc ^ (pidx + jnp.uint32(0x1B873593)))
        n_pat = _upsample_patches(a * approx_normal(pf) + b * approx_normal(pc), H, W)
        c_pat = _upsample_patches(approx_normal(hash32(pc + jnp.uint32(7))), H, W)
        # the largest neighbouring log-depth at discontinuities, -inf elsewhere
        return jnp.where(edge, lmax, -jnp.inf), n_pat, c_pat

    lmax_edge, n_pat, c_pat = jax.lax.cond(p.sigma > -1.0, neighbourhood_terms, neighbourhood_terms, z, sem)
    edge = lmax_edge > -jnp.inf
    sky = sem == SKY
    zf = jnp.where(sky, sky_m, z)
    # ---- noise
    pix = (jnp.arange(H, dtype=jnp.uint32)[:, None] * jnp.uint32(W) + jnp.arange(W, dtype=jnp.uint32)[None, :])[None]
    hf = hash32(kf ^ pix)  # frame-keyed
    hc = hash32(kc ^ pix)  # chunk-keyed
    hg = hash32(hf + jnp.uint32(0x68E31DA4))  # frame-keyed uniforms (gross errors)
    hq = hash32(hc + jnp.uint32(0xB5297A4D))  # chunk-keyed extras (confidence, flying pixels)
    n_depth = 0.6 * n_pat + 0.8 * (a * approx_normal(hf) + b * approx_normal(hc))
    n_conf = 0.6 * c_pat + 0.8 * approx_normal(hq)
    # ---- depth
    far_nb = jnp.minimum(jnp.exp(lmax_edge), sky_m)
    zt = jnp.where(edge, zf + uniform16(hq, False) * (far_nb - zf), zf)  # flying pixels
    rel = depth_rel * (1.0 + zt / rel_ref)
    d = zt * p.depth_factor[:, None, None] * (1.0 + p.bias * zt * p.sigma) * jnp.exp(rel * n_depth)
    gross = uniform16(hg, False) < gross_frac
    d = jnp.where(gross, d * jnp.exp(gross_log * (2.0 * uniform16(hg, True) - 1.0)), d)
    # moving cars: one depth factor per (chunk, car), so two chunks disagree on them
    n_car = approx_normal(
        hash32(p.chunk_key ^ (inst.astype(jnp.uint32) * jnp.uint32(0x9E3779B9) + jnp.uint32(0x3C6EF372)))
    )
    d = jnp.where(sem == CAR, d * jnp.exp(mover_depth * n_car), d)
    # ---- confidence
    conf = 1.0 + conf_max * jnp.exp(-zf / falloff) * jnp.exp(0.25 * n_conf)
    conf = jnp.where(edge, 1.0 + (conf - 1.0) * edge_conf, conf)
    conf = jnp.where(sky, 1.0 + 0.05 * uniform16(hq, True), conf)
    # ---- colour: a palette per semantic class, varied per instance (hash), distance shading
    albedo = _albedo(sem, inst)
    shade = (0.55 + 0.45 * jnp.exp(-zf / 60.0))[..., None]
    rows = (jnp.arange(H, dtype=jnp.float32) / H)[None, :, None, None]
    sky_rgb = jnp.asarray([0.55, 0.70, 0.92], jnp.float32) + rows * jnp.asarray([0.2, 0.15, 0.05])
    rgb = jnp.where(sky[..., None], sky_rgb, albedo * shade) * (1.0 + 0.04 * n_pat[..., None])
    img = jnp.clip(jnp.round(rgb * 255.0), 0, 255).astype(jnp.uint8)
    return d.astype(jnp.float32), conf.astype(jnp.float32), img

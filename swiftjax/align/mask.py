"""The reliability mask of an overlap (paper eq. 2), the per-frame mean confidence it uses, and
the robust depth-scale ratio that puts two chunks' overlap depths in one gauge before it.

Why a ratio: every chunk comes out of VGGT normalised to its own scale (its mean depth), so two
neighbouring chunks' depths of the same overlap frame differ by a factor ``rho`` (the gauge jump)
besides noise.  Eq. 2's test ``|D_t - D_{t+1}| < lambda_D`` is absolute: where the scene's depth
changes along the route (a car slowing from an open square into a narrow street: synthetic KITTI
08 has ``rho = 0.29`` on its first pair) it rejects every pixel and the alignment falls back to the
camera poses.  :func:`overlap_scale_ratio` estimates ``rho`` (chunk t+1 -> chunk t) as the median
of per-pixel depth ratios over the confident pixels,

    rho = median { D_t(p) / D_{t+1}(p) :  p finite, D > 0, gamma_t(p) > lambda_gamma mean(gamma_t),
                                          gamma_{t+1}(p) > lambda_gamma mean(gamma_{t+1}) },

(the median of a ratio is the ratio of the depths' common factor whatever the per-pixel noise
as long as fewer than half the confident pixels are outliers), and eq. 2 then tests
``|D_t - rho D_{t+1}| < lambda_D`` in chunk t's units (:func:`reliability_mask`'s
``scale_ratio``).  The Umeyama solve that follows is scale-equivariant, so the estimate of ``rho``
only chooses the pixels, never biases ``S``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Bool, Float, Int, Real

from swiftjax._reductions import variadic_sum
from swiftjax.align.options import AlignOptions

__all__ = ["frame_conf_mean", "masked_median", "overlap_scale_ratio", "reliability_mask", "SCALE_RATIO_RANGE"]

#: A ratio outside ``[1 / x, x]`` is not a gauge jump but a failed estimate (or a chunk in
#: pieces): :func:`overlap_scale_ratio` returns 1 (eq. 2 as the authors wrote it) instead.
SCALE_RATIO_RANGE = 100.0


def frame_conf_mean(conf: Real[ArrayLike, "*frames H W"]) -> Float[Array, "*frames"]:
    """Per-frame mean confidence over the finite pixels: ``[..., H, W] -> [...]`` (NaN if none).

    Fast path: a plain (vectorised) per-frame sum, exact when every confidence is finite;
    only when some per-frame sum is not finite does a second, masked pass run (``lax.cond``;
    a select under ``vmap``).
    """
    conf = jnp.asarray(conf)
    flat = conf.reshape(*conf.shape[:-2], -1)

    def masked(flat: Array) -> Array:
        fin = jnp.isfinite(flat)
        total, count = variadic_sum((jnp.where(fin, flat, 0), fin.astype(jnp.int32)), -1)
        return total / count.astype(total.dtype)

    plain = jnp.sum(flat, axis=-1) / flat.shape[-1]
    return jax.lax.cond(jnp.all(jnp.isfinite(plain)), lambda f: plain, masked, flat)


def masked_median(
    values: Real[ArrayLike, "..."], keep: Bool[ArrayLike, "..."]
) -> tuple[Float[Array, ""], Int[Array, ""]]:
    """Median of ``values[keep]`` with fixed shapes: ``(median, count)`` (NaN, 0 when nothing is kept).

    ``values`` and ``keep`` are flattened; the kept values are sorted to the front (the others
    become ``+inf``) and the median is the mean of the ranks ``floor((n - 1) / 2)`` and
    ``floor(n / 2)`` (NumPy's ``np.median`` of the kept values).  Jit-able; cost one sort of ``N``.
    """
    v = jnp.ravel(jnp.asarray(values))
    k = jnp.ravel(jnp.asarray(keep, bool))
    n = jnp.sum(k, dtype=jnp.int32)
    srt = jnp.sort(jnp.where(k, v, jnp.inf))
    lo = srt[jnp.maximum((n - 1) // 2, 0)]
    hi = srt[jnp.maximum(n // 2, 0)]
    hi = jnp.where(n > 1, hi, lo)
    return jnp.where(n > 0, (lo + hi) / 2, jnp.nan), n


@jax.jit
def overlap_scale_ratio(
    depth_a: Real[ArrayLike, "*frames H W"],
    depth_b: Real[ArrayLike, "*frames H W"],
    conf_a: Real[ArrayLike, "*frames H W"],
    conf_b: Real[ArrayLike, "*frames H W"],
    conf_ratio: float | Real[ArrayLike, ""] = AlignOptions.conf_ratio,
    keep: Bool[ArrayLike, "*frames H W"] | None = None,
) -> tuple[Float[Array, ""], Int[Array, ""]]:
    """Robust scale ``rho`` with ``D_a ~ rho D_b`` over all the given frames: ``(rho, count)``.

    ``rho`` is the median of ``D_a / D_b`` over the pixels that are finite, positive in both,
    confident in both (``gamma > conf_ratio * mean_frame(gamma)``, the means as
    :func:`reliability_mask`'s) and in ``keep`` (default all); computed in log space
    (``exp median log``: the same median, symmetric in ``a, b``).  ``count`` (int32) is the
    number of such pixels.  With no such pixel, or a ratio outside
    ``[1 / SCALE_RATIO_RANGE, SCALE_RATIO_RANGE]``, ``rho = 1`` (no rescaling).  Pure and jitted;
    one compile per shape and dtype (``conf_ratio`` is traced).
    """
    da, db = jnp.asarray(depth_a), jnp.asarray(depth_b)
    ca, cb = jnp.asarray(conf_a), jnp.asarray(conf_b)
    e = (Ellipsis, None, None)
    lam_c = jnp.asarray(conf_ratio, ca.dtype)
    ok = (
        jnp.isfinite(da)
        & jnp.isfinite(db)
        & jnp.isfinite(ca)
        & jnp.isfinite(cb)
        & (da > 0)
        & (db > 0)
        & (ca > lam_c * frame_conf_mean(ca)[e])
        & (cb > lam_c * frame_conf_mean(cb)[e])
    )
    if keep is not None:
        ok = ok & jnp.asarray(keep, bool)
    log_ratio = jnp.log(jnp.where(ok, da, 1)) - jnp.log(jnp.where(ok, db, 1))
    med, n = masked_median(log_ratio, ok)
    sane = jnp.isfinite(med) & (jnp.abs(med) <= jnp.log(jnp.asarray(SCALE_RATIO_RANGE, da.dtype)))
    return jnp.where(sane, jnp.exp(jnp.where(sane, med, 0)), 1).astype(da.dtype), n


@jax.jit
def reliability_mask(
    depth_a: Real[ArrayLike, "*frames H W"],
    depth_b: Real[ArrayLike, "*frames H W"],
    conf_a: Real[ArrayLike, "*frames H W"],
    conf_b: Real[ArrayLike, "*frames H W"],
    depth_threshold: float | Real[ArrayLike, ...] = AlignOptions.depth_threshold,
    conf_ratio: float | Real[ArrayLike, ...] = AlignOptions.conf_ratio,
    conf_mean_a: Real[ArrayLike, "*frames"] | None = None,
    conf_mean_b: Real[ArrayLike, "*frames"] | None = None,
    scale_ratio: float | Real[ArrayLike, ...] = 1.0,
) -> Bool[Array, "*frames H W"]:
    """Reliable overlap pixels (paper eq. 2): bool ``[..., H, W]``.

    ``|D_a - rho D_b| < depth_threshold``  and  ``gamma_a > conf_ratio * mean(gamma_a)``  and
    ``gamma_b > conf_ratio * mean(gamma_b)``, the means taken per frame over all finite
    pixels (the authors' choice); pixels where any of the four inputs is NaN/inf are never
    reliable (and do not enter the means).  The depths are the *normalised* depths
    (:func:`swiftjax.camera.normalize_depth`) of the same frames seen by the two chunks, and
    the difference is absolute, in chunk ``a``'s units after ``D_b`` is rescaled by
    ``rho = scale_ratio`` (default 1: the authors' eq. 2; :func:`overlap_scale_ratio` gives the
    robust ``rho`` that removes a gauge jump between the chunks).

    Args:
        depth_a, depth_b, conf_a, conf_b: ``[..., H, W]``.
        depth_threshold: ``lambda_D`` (scalar or broadcastable to ``[...]``; default
            :attr:`AlignOptions.depth_threshold`).
        conf_ratio: ``lambda_gamma`` (default :attr:`AlignOptions.conf_ratio`).
        conf_mean_a, conf_mean_b: optional precomputed :func:`frame_conf_mean` ``[...]``.
        scale_ratio: ``rho`` (scalar or broadcastable to ``[...]``), traced.
    """
    da, db = jnp.asarray(depth_a), jnp.asarray(depth_b)
    ca, cb = jnp.asarray(conf_a), jnp.asarray(conf_b)
    ma = frame_conf_mean(ca) if conf_mean_a is None else jnp.asarray(conf_mean_a)
    mb = frame_conf_mean(cb) if conf_mean_b is None else jnp.asarray(conf_mean_b)
    e = (Ellipsis, None, None)
    lam_d = jnp.asarray(depth_threshold, da.dtype)
    lam_c = jnp.asarray(conf_ratio, ca.dtype)
    lam_d = lam_d[e] if lam_d.ndim else lam_d
    lam_c = lam_c[e] if lam_c.ndim else lam_c
    rho = jnp.asarray(scale_ratio, da.dtype)
    rho = rho[e] if rho.ndim else rho
    fin = jnp.isfinite(da) & jnp.isfinite(db) & jnp.isfinite(ca) & jnp.isfinite(cb)
    return fin & (jnp.abs(da - rho * db) < lam_d) & (ca > lam_c * ma[e]) & (cb > lam_c * mb[e])

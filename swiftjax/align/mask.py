"""The reliability mask of an overlap (paper eq. 2) and the per-frame mean confidence it uses."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Bool, Float, Real

from swiftjax._reductions import variadic_sum
from swiftjax.align.options import AlignOptions

__all__ = ["frame_conf_mean", "reliability_mask"]


def frame_conf_mean(conf: Real[ArrayLike, "*frames H W"]) -> Float[Array, "*frames"]:
    """Per-frame mean confidence over the finite pixels: ``[..., H, W] -> [...]`` (NaN if none).

    Fast path: a plain (vectorised) per-frame sum, exact when every confidence is finite;
    only when some per-frame sum is not finite does a second, masked pass run (``lax.cond``;
    a select under ``vmap``).
    """
    conf = jnp.asarray(conf)
    flat = conf.reshape(*conf.shape[:-2], -1)

    def masked(flat):
        fin = jnp.isfinite(flat)
        total, count = variadic_sum((jnp.where(fin, flat, 0), fin.astype(jnp.int32)), -1)
        return total / count.astype(total.dtype)

    plain = jnp.sum(flat, axis=-1) / flat.shape[-1]
    return jax.lax.cond(jnp.all(jnp.isfinite(plain)), lambda f: plain, masked, flat)


@jax.jit
def reliability_mask(
    depth_a: Real[ArrayLike, "*frames H W"],
    depth_b: Real[ArrayLike, "*frames H W"],
    conf_a: Real[ArrayLike, "*frames H W"],
    conf_b: Real[ArrayLike, "*frames H W"],
    depth_threshold: float | Real[ArrayLike, "..."] = AlignOptions.depth_threshold,
    conf_ratio: float | Real[ArrayLike, "..."] = AlignOptions.conf_ratio,
    conf_mean_a: Real[ArrayLike, "*frames"] | None = None,
    conf_mean_b: Real[ArrayLike, "*frames"] | None = None,
) -> Bool[Array, "*frames H W"]:
    """Reliable overlap pixels (paper eq. 2): bool ``[..., H, W]``.

    ``|D_a - D_b| < depth_threshold``  and  ``gamma_a > conf_ratio * mean(gamma_a)``  and
    ``gamma_b > conf_ratio * mean(gamma_b)``, the means taken per frame over all finite
    pixels (the authors' choice); pixels where any of the four inputs is NaN/inf are never
    reliable (and do not enter the means).  The depths are the *normalised* depths
    (:func:`swiftjax.camera.normalize_depth`) of the same frames seen by the two chunks, and
    the difference is absolute, in the chunks' (VGGT) units.

    Args:
        depth_a, depth_b, conf_a, conf_b: ``[..., H, W]``.
        depth_threshold: ``lambda_D`` (scalar or broadcastable to ``[...]``; default
            :attr:`AlignOptions.depth_threshold`).
        conf_ratio: ``lambda_gamma`` (default :attr:`AlignOptions.conf_ratio`).
        conf_mean_a, conf_mean_b: optional precomputed :func:`frame_conf_mean` ``[...]``.
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
    fin = jnp.isfinite(da) & jnp.isfinite(db) & jnp.isfinite(ca) & jnp.isfinite(cb)
    return fin & (jnp.abs(da - db) < lam_d) & (ca > lam_c * ma[e]) & (cb > lam_c * mb[e])

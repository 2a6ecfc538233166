"""Chunk alignment: reliability mask (eq. 2), weighted Umeyama Sim(3), IRLS baseline.

SwiftVGGT aligns two neighbouring chunks with ONE closed-form weighted Umeyama solve on the
reliable overlap points (no iterations); VGGT-Long's IRLS is kept here only as a baseline.

Weighted Umeyama (Umeyama 1991, with weights ``w_i >= 0``, ``W = sum w_i``)::

    mu_x = sum w x / W,   mu_y = sum w y / W
    C    = sum w (y - mu_y)(x - mu_x)^T / W          (3 x 3, dst x src)
    s_x2 = sum w |x - mu_x|^2 / W
    C = U D V^T,  E = diag(1, 1, sign(det U det V))  (reflection fix)
    R = U E V^T,  s = tr(D E) / s_x2,  t = mu_y - s R mu_x
    rms^2 = s_y2 - tr(D E)^2 / s_x2                   (weighted mean squared residual)

so that ``dst ~= s R src + t`` (``dst ~= act(S, src)``).

Accumulation scheme (the issue asks to state it): **centred, blocked, single pass** in the
input dtype.  A rough centre ``c`` (weighted mean of a strided subsample of at most
``_CENTRE_SAMPLES`` points) is subtracted from every point before the moments are formed,
so no sum ever holds ``|x|^2 ~ 10^4`` next to a spread of ``~1``: the covariances are formed
from the centred second moments minus a *small* mean correction (``|mu - c|`` is a fraction
of the spread), which removes the catastrophic cancellation of the naive ``E[xy^T] - mu mu^T``.
All 18 moments (``W``, ``sum w x'``, ``sum w y'``, ``sum w y' x'^T``, ``sum w |x'|^2``,
``sum w |y'|^2``) are summed in ONE fused pass, in blocks of ``_BLOCK`` points whose
partial sums are then added (a two-level sum: rounding error grows like
``eps (block + N / block)`` instead of ``eps N``).  This is what makes float32 inputs of
2-3 M points at ~100 m coordinates give rotations to ~1e-6 rad (tested), and it is also the
fastest scheme measured on XLA CPU (bench/bench_align.py).  We chose it over float64
accumulation because float64 does not exist in JAX unless ``jax_enable_x64`` is on; with x64
on and float64 inputs the very same code runs in float64.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from swiftjax import sim3

__all__ = [
    "UmeyamaInfo",
    "umeyama",
]

_BLOCK = 4096  # points per partial sum
_CENTRE_SAMPLES = 1024  # at most this many strided points estimate the centring point


class UmeyamaInfo(NamedTuple):
    """Diagnostics of one (weighted) Umeyama solve; every field has the batch shape ``[...]``.

    Attributes:
        weight_sum: ``W = sum w`` over the points used (finite, positive weight).
        num_points: int32 number of points used (finite and ``w > 0``).
        rms: weighted RMS residual ``sqrt(sum w |dst - S src|^2 / W)`` (closed form, 0 if invalid).
        valid: False when fewer than 3 points are used, the weights sum to 0, the source
            points have (numerically) no spread, or the cross-covariance has rank < 2
            (collinear points: rotation about the line undetermined). ``S`` is then identity.
        singular_values: ``[..., 3]`` singular values of the cross-covariance ``C``.
    """

    weight_sum: Array
    num_points: Array
    rms: Array
    valid: Array
    singular_values: Array


class _Moments(NamedTuple):
    """Centred weighted moments (all summed, not divided), centre ``cx`` / ``cy``."""

    w: Array  # [...]
    n: Array  # [...] int32
    sx: Array  # [..., 3]   sum w (x - cx)
    sy: Array  # [..., 3]   sum w (y - cy)
    syx: Array  # [..., 3, 3] sum w (y - cy)(x - cx)^T
    sxx: Array  # [...]     sum w |x - cx|^2
    syy: Array  # [...]     sum w |y - cy|^2
    cx: Array  # [..., 3]
    cy: Array  # [..., 3]


def _rough_centre(p: Array, w: Array) -> Array:
    """Weighted mean of a strided subsample: ``p [..., N, 3], w [..., N] -> [..., 3]``.

    Falls back to the unweighted subsample mean when no sampled point has weight; ``p`` and
    ``w`` must already be sanitised (finite, ``w = 0`` where unusable).
    """
    n = p.shape[-2]
    stride = max(1, n // _CENTRE_SAMPLES)
    ps, ws = p[..., ::stride, :], w[..., ::stride]
    wsum = jnp.sum(ws, axis=-1)
    c_w = jnp.sum(ps * ws[..., None], axis=-2) / jnp.where(wsum > 0, wsum, 1)[..., None]
    c_u = jnp.mean(ps, axis=-2)
    return jnp.where((wsum > 0)[..., None], c_w, c_u)


def _block_sum(f: Array, axis_len: int) -> Array:
    """Two-level sum over the point axis (-2) of ``f [..., N, k]`` -> ``[..., k]``."""
    n = axis_len
    nb = n // _BLOCK
    if nb <= 1:
        return jnp.sum(f, axis=-2)
    head = f[..., : nb * _BLOCK, :].reshape(*f.shape[:-2], nb, _BLOCK, f.shape[-1])
    total = jnp.sum(jnp.sum(head, axis=-2), axis=-2)
    if nb * _BLOCK < n:
        total = total + jnp.sum(f[..., nb * _BLOCK :, :], axis=-2)
    return total


def _moments(src: Array, dst: Array, w: Array) -> _Moments:
    """Sanitise and accumulate the centred moments of ``src``/``dst`` with weights ``w``."""
    ok = (w > 0) & jnp.all(jnp.isfinite(src), axis=-1) & jnp.all(jnp.isfinite(dst), axis=-1)
    ok = ok & jnp.isfinite(w)
    w = jnp.where(ok, w, 0)
    x = jnp.where(ok[..., None], src, 0)
    y = jnp.where(ok[..., None], dst, 0)
    cx = jax.lax.stop_gradient(_rough_centre(x, w))
    cy = jax.lax.stop_gradient(_rough_centre(y, w))
    xc = jnp.where(ok[..., None], x - cx[..., None, :], 0)
    yc = jnp.where(ok[..., None], y - cy[..., None, :], 0)
    wx = w[..., None] * xc
    wy = w[..., None] * yc
    feats = jnp.concatenate(
        [
            w[..., None],
            wx,
            wy,
            (wy[..., :, None] * xc[..., None, :]).reshape(*wy.shape[:-1], 9),
            jnp.sum(wx * xc, axis=-1, keepdims=True),
            jnp.sum(wy * yc, axis=-1, keepdims=True),
            ok[..., None].astype(w.dtype),
        ],
        axis=-1,
    )  # [..., N, 19]
    tot = _block_sum(feats, src.shape[-2])
    return _Moments(
        w=tot[..., 0],
        n=jnp.round(tot[..., 18]).astype(jnp.int32),
        sx=tot[..., 1:4],
        sy=tot[..., 4:7],
        syx=tot[..., 7:16].reshape(*tot.shape[:-1], 3, 3),
        sxx=tot[..., 16],
        syy=tot[..., 17],
        cx=cx,
        cy=cy,
    )


def _solve(m: _Moments) -> tuple[Array, UmeyamaInfo]:
    """Closed-form Sim(3) from accumulated moments (module docstring formulas)."""
    dtype = m.sx.dtype
    eps = jnp.finfo(dtype).eps
    wpos = m.w > 0
    W = jnp.where(wpos, m.w, 1)
    mx = m.sx / W[..., None]  # mean of centred src
    my = m.sy / W[..., None]
    cov = m.syx / W[..., None, None] - my[..., :, None] * mx[..., None, :]
    sx2 = m.sxx / W - jnp.sum(mx * mx, axis=-1)
    sy2 = m.syy / W - jnp.sum(my * my, axis=-1)
    mu_x = mx + m.cx
    mu_y = my + m.cy

    finite = jnp.all(jnp.isfinite(cov), axis=(-2, -1)) & jnp.isfinite(sx2) & jnp.isfinite(sy2)
    cov_safe = jnp.where(finite[..., None, None], cov, jnp.eye(3, dtype=dtype))
    U, D, Vt = jnp.linalg.svd(cov_safe)
    d = jnp.sign(jnp.linalg.det(U) * jnp.linalg.det(Vt))
    d = jnp.where(d == 0, 1, d)
    e = jnp.stack([jnp.ones_like(d), jnp.ones_like(d), d], axis=-1)
    R = (U * e[..., None, :]) @ Vt
    trde = jnp.sum(D * e, axis=-1)

    # Spread must stand out of the rounding of the coordinates themselves.
    pos2 = jnp.sum(mu_x * mu_x, axis=-1)
    spread_ok = sx2 > jnp.maximum((100 * eps) ** 2 * pos2, jnp.finfo(dtype).tiny)
    rank_ok = D[..., 1] > 1e3 * eps * D[..., 0]
    valid = wpos & (m.n >= 3) & finite & spread_ok & rank_ok & (trde > 0)

    sx2_safe = jnp.where(valid, sx2, 1)
    s = trde / sx2_safe
    t = mu_y - s[..., None] * jnp.einsum("...ij,...j->...i", R, mu_x)
    rms = jnp.sqrt(jnp.maximum(sy2 - trde * trde / sx2_safe, 0))

    eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), R.shape)
    R = jnp.where(valid[..., None, None], R, eye)
    s = jnp.where(valid, s, 1)
    t = jnp.where(valid[..., None], t, 0)
    S = sim3.from_rst(R, t, s)
    info = UmeyamaInfo(
        weight_sum=jnp.where(finite, m.w, 0),
        num_points=m.n,
        rms=jnp.where(valid, rms, 0),
        valid=valid,
        singular_values=jnp.where(finite[..., None], D, 0),
    )
    return S, info


def umeyama(
    src: ArrayLike, dst: ArrayLike, weights: ArrayLike | None = None
) -> tuple[Array, UmeyamaInfo]:
    """Weighted Sim(3) Umeyama: ``S`` minimising ``sum w |dst - (s R src + t)|^2``.

    Args:
        src: ``[..., N, 3]`` source points.
        dst: ``[..., N, 3]`` destination points (same shape).
        weights: ``[..., N]`` non-negative weights (zeros allowed; bool masks are cast), or
            ``None`` for all ones.  Points with a non-finite coordinate or weight, or a
            weight ``<= 0``, are ignored (they never reach ``S``).

    Returns:
        ``(S [..., 8], info: UmeyamaInfo)`` with ``dst ~= act(S, src)``.  When
        ``info.valid`` is False ``S`` is the identity (finite).

    Leading batch axes solve many problems at once.  Jit-able; recompiles per shape/dtype.
    The computation runs in the dtype of ``src`` (float32, or float64 with x64 on); see the
    module docstring for the centred, blocked accumulation.
    """
    src = jnp.asarray(src)
    if not jnp.issubdtype(src.dtype, jnp.floating):
        src = src.astype(jnp.float32)
    dst = jnp.asarray(dst, dtype=src.dtype)
    if src.shape[-1] != 3 or src.shape != dst.shape:
        raise ValueError(f"umeyama: src {src.shape} and dst {dst.shape} must both be [..., N, 3]")
    if weights is None:
        w = jnp.ones(src.shape[:-1], src.dtype)
    else:
        w = jnp.asarray(weights).astype(src.dtype)
        if w.shape != src.shape[:-1]:
            raise ValueError(f"umeyama: weights {w.shape} must be {src.shape[:-1]}")
    return _solve(_moments(src, dst, w))

"""Weighted Umeyama Sim(3): centred moments in one pass, then the closed-form solve.

Weighted Umeyama (Umeyama 1991, with weights ``w_i >= 0``, ``W = sum w_i``)::

    mu_x = sum w x / W,   mu_y = sum w y / W
    C    = sum w (y - mu_y)(x - mu_x)^T / W          (3 x 3, dst x src)
    s_x2 = sum w |x - mu_x|^2 / W
    C = U D V^T,  E = diag(1, 1, sign(det U det V))  (reflection fix)
    R = U E V^T,  s = tr(D E) / s_x2,  t = mu_y - s R mu_x
    rms^2 = s_y2 - tr(D E)^2 / s_x2                   (weighted mean squared residual)

so that ``dst ~= s R src + t`` (``dst ~= act(S, src)``).

Accumulation scheme: **centred, blocked, single pass** in the input dtype.  A rough centre
``c`` (weighted mean of a strided subsample of at most ``_CENTRE_SAMPLES`` points) is
subtracted from every point before the moments are formed, so no sum ever holds
``|x|^2 ~ 10^4`` next to a spread of ``~1``: the covariances are formed from the centred
second moments minus a *small* mean correction (``|mu - c|`` is a fraction of the spread),
which removes the catastrophic cancellation of the naive ``E[xy^T] - mu mu^T``.  All 19 sums
(``W``, ``sum w x'``, ``sum w y'``, ``sum w y' x'^T``, ``sum w |x'|^2``, ``sum w |y'|^2``
and the int32 point count) are accumulated in ONE pass by a single variadic ``lax.reduce``
(:func:`swiftjax._reductions.variadic_sum`) over rows of ``_ROW`` points, whose row partials
are then added (a two-level sum: rounding error grows like ``eps (row + N / row)`` instead
of ``eps N``).  With this, float32 inputs of 2-3 M points at ~100 m coordinates give
rotations to ~1e-6 rad (tested).  Float64 accumulation is not used because float64 does not
exist in JAX unless ``jax_enable_x64`` is on; with x64 on and float64 inputs the very same
code runs in float64.  The closed-form ``rms`` has a float32 floor of about
``sqrt(eps) * spread`` (~3e-4 x the point spread).  Speed on XLA:CPU and the formulations
tried: ``docs/performance/align.md``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Bool, Float, Int, Shaped

from swiftjax import sim3, so3
from swiftjax._reductions import variadic_sum
from swiftjax.align import _kernels, checks

__all__ = ["UmeyamaInfo", "umeyama"]

_CENTRE_SAMPLES = 1024  # at most this many strided points estimate the centring point
_ROW = 2048  # points per first-level partial sum (one row of the variadic reduce)


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

    weight_sum: Float[Array, "*batch"]
    num_points: Int[Array, "*batch"]
    rms: Float[Array, "*batch"]
    valid: Bool[Array, "*batch"]
    singular_values: Float[Array, "*batch 3"]


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


def _moment_terms(xc: tuple[Array, ...], yc: tuple[Array, ...], w: Array, ok: Array) -> tuple[Array, ...]:
    """The 19 per-point terms ``(w, w x, w y, w y x^T, w|x|^2, w|y|^2, ok)`` (x, y already centred, 0 where not ok)."""
    wx = tuple(w * a for a in xc)
    wy = tuple(w * b for b in yc)
    outer = tuple(wy[i] * xc[j] for i in range(3) for j in range(3))
    sxx = wx[0] * xc[0] + wx[1] * xc[1] + wx[2] * xc[2]
    syy = wy[0] * yc[0] + wy[1] * yc[1] + wy[2] * yc[2]
    return (w, *wx, *wy, *outer, sxx, syy, ok.astype(jnp.int32))


def _sum_terms(terms: tuple[Array, ...], point_axes: int) -> tuple[Array, ...]:
    """Two-level sum of per-point terms over their trailing ``point_axes`` axes.

    Level 1: one variadic reduce over the last axis (a row of points); level 2: the row
    partials are summed over the remaining point axes.
    """
    part = variadic_sum(terms, -1)
    if point_axes == 1:
        return part
    axes = tuple(range(-(point_axes - 1), 0))
    return tuple(jnp.sum(p, axis=axes) for p in part)


def _pack_moments(tot: tuple[Array, ...], cx: Array, cy: Array) -> _Moments:
    return _Moments(
        w=tot[0],
        n=tot[18],
        sx=jnp.stack(tot[1:4], -1),
        sy=jnp.stack(tot[4:7], -1),
        syx=jnp.stack(tot[7:16], -1).reshape(*tot[0].shape, 3, 3),
        sxx=tot[16],
        syy=tot[17],
        cx=cx,
        cy=cy,
    )


def _add_moments(a: tuple[Array, ...], b: tuple[Array, ...]) -> tuple[Array, ...]:
    return tuple(x + y for x, y in zip(a, b))


def _valid_points(src: Array, dst: Array, w: Array) -> Array:
    """Points that enter the fit: positive finite weight, finite ``src`` and ``dst`` (bool ``[..., N]``)."""
    fin = jnp.isfinite
    return (w > 0) & fin(w) & jnp.all(fin(src), axis=-1) & jnp.all(fin(dst), axis=-1)


def _moments(src: Array, dst: Array, w: Array) -> _Moments:
    """Sanitise and accumulate the centred moments of ``src``/``dst`` with weights ``w``.

    The centres come from :func:`_rough_centre`; the sums from the fused kernel on CPU in
    float32 (:mod:`swiftjax.align._kernels`), else from :func:`_centred_sums`.
    """
    # The centres' strided subsample is taken first (the validity test then touches ~1024
    # points, not N; _rough_centre's own stride over it is 1, so the points are the same).
    sub = max(1, src.shape[-2] // _CENTRE_SAMPLES)
    xs, ys, ws = src[..., ::sub, :], dst[..., ::sub, :], w[..., ::sub]
    ok = _valid_points(xs, ys, ws)
    w0 = jnp.where(ok, ws, 0)
    cx = jax.lax.stop_gradient(_rough_centre(jnp.where(ok[..., None], xs, 0), w0))
    cy = jax.lax.stop_gradient(_rough_centre(jnp.where(ok[..., None], ys, 0), w0))
    T, count = _kernels.umeyama_moments(src, dst, w, jnp.concatenate([cx, cy], -1), _centred_sums)
    return _pack_moments((*(T[..., i] for i in range(18)), count), cx, cy)


def _centred_sums(src: Array, dst: Array, w: Array, centres: Array) -> tuple[Array, Array]:
    """The 18 weighted sums ``T [..., 18]`` of :func:`_moment_terms` about ``centres [..., 6] =
    (cx, cy)`` and the int32 count of valid points, in pure JAX.

    The point axis is split into rows of ``_ROW`` points (``[..., R, _ROW]``) plus a tail of
    fewer than ``_ROW`` points; both are reduced with the same variadic reduce.
    """
    ok = _valid_points(src, dst, w)
    cx, cy = centres[..., :3], centres[..., 3:]

    def terms(sl: slice, shape: tuple[int, ...]) -> tuple[Array, ...]:
        okb = ok[..., sl].reshape(shape)
        wb = jnp.where(okb, w[..., sl].reshape(shape), 0)
        e = (Ellipsis,) + (None,) * (len(shape) - ok.ndim + 1)
        xc = tuple(jnp.where(okb, src[..., sl, i].reshape(shape) - cx[..., i][e], 0) for i in range(3))
        yc = tuple(jnp.where(okb, dst[..., sl, i].reshape(shape) - cy[..., i][e], 0) for i in range(3))
        return _moment_terms(xc, yc, wb, okb)

    n = src.shape[-2]
    lead = src.shape[:-2]
    rows = n // _ROW
    if rows >= 2:
        tot = _sum_terms(terms(slice(0, rows * _ROW), (*lead, rows, _ROW)), 2)
        if rows * _ROW < n:
            tot = _add_moments(tot, _sum_terms(terms(slice(rows * _ROW, n), (*lead, n - rows * _ROW)), 1))
    else:
        tot = _sum_terms(terms(slice(0, n), (*lead, n)), 1)
    return jnp.stack(tot[:18], -1), tot[18]


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
    # R = U E V^T is the rotation nearest to C (so3.project); tr(D E) flips the smallest
    # singular value exactly when det C < 0 (when det C = 0 that value is 0 and the sign moot).
    R = so3.as_matrix(so3.project(cov_safe))
    D = jnp.linalg.svd(cov_safe, compute_uv=False)
    d = jnp.where(jnp.linalg.det(cov_safe) < 0, -1, 1).astype(dtype)
    trde = D[..., 0] + D[..., 1] + d * D[..., 2]

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


@_kernels.jit
def umeyama(
    src: Shaped[ArrayLike, "*batch N 3"],
    dst: Shaped[ArrayLike, "*batch N 3"],
    weights: Shaped[ArrayLike, "*batch N"] | None = None,
) -> tuple[Float[Array, "*batch 8"], UmeyamaInfo]:
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
    return _solve(_moments(*checks.umeyama_inputs(src, dst, weights)))

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
All 19 sums (``W``, ``sum w x'``, ``sum w y'``, ``sum w y' x'^T``, ``sum w |x'|^2``,
``sum w |y'|^2`` and the int32 point count) are accumulated in ONE pass by a single variadic
``lax.reduce`` over rows of ``_ROW`` points, whose row partials are then added (a two-level
sum: rounding error grows like ``eps (row + N / row)`` instead of ``eps N``).  XLA CPU
turns sibling ``jnp.sum`` calls into separate or badly fused loops (measured 4x slower per
extra output); the variadic reduce keeps all accumulators in one loop, and the row split
lets XLA run rows on both cores.  This is what makes float32 inputs of
2-3 M points at ~100 m coordinates give rotations to ~1e-6 rad (tested), and it is also the
fastest scheme measured on XLA CPU (bench/bench_align.py).  We chose it over float64
accumulation because float64 does not exist in JAX unless ``jax_enable_x64`` is on; with x64
on and float64 inputs the very same code runs in float64.

Chunk pairs (:func:`align_chunk_pair`) never form the world points: every point of frame
``f`` is an affine map of ``phi = (delta u~, delta v~, delta, u~, v~, 1)`` (``delta`` the
normalised depth minus a rough per-frame centre, ``u~, v~`` the pixel coordinates scaled to
``[-1, 1]``), so all moments follow from per-frame *pixel* moments
``sum m delta_p^i delta_c^j u~^k v~^l`` (6 images x powers of ``u~``: 18 terms in one
variadic reduce over each pixel row, then a tiny contraction with the powers of ``v~`` and
``sum_f M_y,f G_f M_x,f^T`` over frames).  The inputs are read once (plus the
confidences once more for their per-frame means); the centring (per-frame depth centre,
global rough world centres) keeps float32 accurate (tested far from the origin).

Known limits (measured on XLA CPU, jax 0.10.2, bench/bench_align.py).  A variadic reduce is
emitted as a scalar loop (IEEE order forbids re-associating into SIMD lanes, whatever the
reduced axis: rows, columns or 8/16-wide lanes all measured the same), so the pass costs
about 0.7 ns per term per point pair and stays compute-bound (~10-20x the memory
roofline).  Single-output sums are vectorised (XNNPACK/YNN fusions) but each re-reads
its inputs, and sibling sums are not fused; dot products ``[N, 7]^T [N, 7]`` (moments as a
GEMM) measured 4x slower than the variadic reduce, and materialising stacked feature
images was slower still, so :func:`umeyama` keeps the 19-term variadic reduce.  With
``XLA_FLAGS=--xla_cpu_enable_fast_math=true --xla_cpu_fast_math_honor_nans=true
--xla_cpu_fast_math_honor_infs=true`` the reduce took ~40 % less CPU time in an earlier
measurement; the library sets no flags.  The closed-form ``rms`` has a float32 floor of
about ``sqrt(eps) * spread`` (~3e-4 x the point spread).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

import warnings

import numpy as np

from swiftjax import camera, sim3

__all__ = [
    "UmeyamaInfo",
    "umeyama",
    "reliability_mask",
    "frame_conf_mean",
    "IRLSInfo",
    "irls_sim3",
    "irls_chunk_pair",
    "ChunkFrames",
    "AlignInfo",
    "align_chunk_pair",
    "align_chunk_pairs",
    "align_chunk_pair_checked",
    "pose_based_estimate",
]

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


_ROW = 2048  # points per first-level partial sum (one row of the variadic reduce)


def _variadic_sum(operands: tuple[Array, ...], axis: int) -> tuple[Array, ...]:
    """One ``lax.reduce`` summing all operands over ``axis`` at once (one pass, one loop).

    XLA CPU emits sibling ``jnp.sum`` calls as separate (or poorly fused) loops; a single
    variadic reduce keeps every accumulator in registers while the inputs stream through.
    """
    inits = tuple(jnp.zeros((), o.dtype) for o in operands)
    ax = axis % operands[0].ndim
    return jax.lax.reduce(operands, inits, lambda a, b: tuple(x + y for x, y in zip(a, b)), (ax,))


def _moment_terms(xc: tuple[Array, Array, Array], yc: tuple[Array, Array, Array], w: Array, ok: Array):
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
    part = _variadic_sum(terms, -1)
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


def _moments(src: Array, dst: Array, w: Array) -> _Moments:
    """Sanitise and accumulate the centred moments of ``src``/``dst`` with weights ``w``.

    The point axis is split into rows of ``_ROW`` points (``[..., R, _ROW]``) plus a tail of
    fewer than ``_ROW`` points; both are reduced with the same variadic reduce.
    """
    fin = jnp.isfinite
    ok = (w > 0) & fin(w) & jnp.all(fin(src), axis=-1) & jnp.all(fin(dst), axis=-1)
    w0 = jnp.where(ok, w, 0)
    cx = jax.lax.stop_gradient(_rough_centre(jnp.where(ok[..., None], src, 0), w0))
    cy = jax.lax.stop_gradient(_rough_centre(jnp.where(ok[..., None], dst, 0), w0))

    def terms(sl: slice, shape: tuple[int, ...]):
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
    return _pack_moments(tot, cx, cy)


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


@jax.jit
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
    if src.dtype not in (jnp.float32, jnp.float64):
        raise TypeError(
            f"umeyama: points must be float32 or float64, got {src.dtype} (the 3x3 SVD has no "
            f"{src.dtype} kernel and half precision cannot hold the moments): cast them, e.g. .astype(float32)"
        )
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


# ----------------------------------------------------------------------- reliability mask


def frame_conf_mean(conf: ArrayLike) -> Array:
    """Per-frame mean confidence over the finite pixels: ``[..., H, W] -> [...]`` (NaN if none).

    Fast path: a plain (vectorised) per-frame sum, exact when every confidence is finite;
    only when some per-frame sum is not finite does a second, masked pass run (``lax.cond``;
    a select under ``vmap``).
    """
    conf = jnp.asarray(conf)
    flat = conf.reshape(*conf.shape[:-2], -1)

    def masked(flat):
        fin = jnp.isfinite(flat)
        total, count = _variadic_sum((jnp.where(fin, flat, 0), fin.astype(jnp.int32)), -1)
        return total / count.astype(total.dtype)

    plain = jnp.sum(flat, axis=-1) / flat.shape[-1]
    return jax.lax.cond(jnp.all(jnp.isfinite(plain)), lambda f: plain, masked, flat)


@jax.jit
def reliability_mask(
    depth_a: ArrayLike,
    depth_b: ArrayLike,
    conf_a: ArrayLike,
    conf_b: ArrayLike,
    depth_threshold: float | ArrayLike = 0.2,
    conf_ratio: float | ArrayLike = 0.5,
    conf_mean_a: ArrayLike | None = None,
    conf_mean_b: ArrayLike | None = None,
) -> Array:
    """Reliable overlap pixels (paper eq. 2): bool ``[..., H, W]``.

    ``|D_a - D_b| < depth_threshold``  and  ``gamma_a > conf_ratio * mean(gamma_a)``  and
    ``gamma_b > conf_ratio * mean(gamma_b)``, the means taken per frame over all finite
    pixels (the authors' choice); pixels where any of the four inputs is NaN/inf are never
    reliable (and do not enter the means).  The depths are the *normalised* depths
    (:func:`swiftjax.camera.normalize_depth`) of the same frames seen by the two chunks, and
    the difference is absolute, in the chunks' (VGGT) units.

    Args:
        depth_a, depth_b, conf_a, conf_b: ``[..., H, W]``.
        depth_threshold: ``lambda_D`` (scalar or broadcastable to ``[...]``).
        conf_ratio: ``lambda_gamma``.
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


# ------------------------------------------------------------------------ IRLS baseline


class IRLSInfo(NamedTuple):
    """Diagnostics of :func:`irls_sim3`: ``iterations`` (int32) run and ``converged`` (bool)."""

    iterations: Array
    converged: Array


def _vggt_long_weighted_sim3(src: Array, dst: Array, w: Array) -> tuple[Array, Array, Array]:
    """VGGT-Long's ``weighted_estimate_sim3``: scale = ratio of weighted RMS spreads.

    ``w`` normalised to sum 1; ``s = sqrt(sum w |y - mu_y|^2) / sqrt(sum w |x - mu_x|^2)``;
    ``H = sum w (s x_c) y_c^T``, ``H = U S V^T``, ``R = V U^T`` (last row of ``V^T`` negated
    if ``det R < 0``), ``t = mu_y - s R mu_x``.  Returns ``(s, R, t)``.
    """
    wn = w / jnp.maximum(jnp.sum(w, axis=-1, keepdims=True), jnp.finfo(w.dtype).tiny)
    mu_x = jnp.einsum("...n,...ni->...i", wn, src)
    mu_y = jnp.einsum("...n,...ni->...i", wn, dst)
    xc = src - mu_x[..., None, :]
    yc = dst - mu_y[..., None, :]
    sc_x = jnp.sqrt(jnp.einsum("...n,...ni,...ni->...", wn, xc, xc))
    sc_y = jnp.sqrt(jnp.einsum("...n,...ni,...ni->...", wn, yc, yc))
    s = sc_y / sc_x
    H = s[..., None, None] * jnp.einsum("...n,...ni,...nj->...ij", wn, xc, yc)
    U, _, Vt = jnp.linalg.svd(H)
    V = jnp.swapaxes(Vt, -1, -2)
    R = V @ jnp.swapaxes(U, -1, -2)
    flip = jnp.linalg.det(R) < 0
    V = V.at[..., :, 2].multiply(jnp.where(flip, -1.0, 1.0)[..., None].astype(V.dtype))
    R = V @ jnp.swapaxes(U, -1, -2)
    t = mu_y - s[..., None] * jnp.einsum("...ij,...j->...i", R, mu_x)
    return s, R, t


@jax.jit
def irls_sim3(
    src: ArrayLike,
    dst: ArrayLike,
    weights: ArrayLike | None = None,
    delta: float = 0.1,
    max_iters: int = 5,
    tol: float = 1e-9,
) -> tuple[Array, IRLSInfo]:
    """VGGT-Long's robust IRLS Sim(3) (``robust_weighted_estimate_sim3``), the baseline.

    Faithful port, for comparison only (one problem, ``src``/``dst`` ``[N, 3]``)::

        (s, R, t) = weighted_estimate_sim3(src, dst, w0)
        repeat max_iters times:
            r = |dst - (s R src + t)|;  h = 1 if r <= delta else delta / r
            w = w0 h / (sum w0 h + 1e-12)
            (s', R', t') = weighted_estimate_sim3(src, dst, w)
            E = sum huber(r, delta) w0
            stop if (|s' - s| + |t' - t| < tol and angle(R' R^T) < 0.1 deg)
                    or |E_prev - E| < tol E_prev        (keeping (s, R, t))
            (s, R, t) = (s', R', t')

    Non-finite points are given zero weight (as in :func:`umeyama`).  Jit-able
    (``max_iters`` static; ``lax.while_loop``); every iteration is two passes over the points.

    Returns:
        ``(S [8], IRLSInfo)``.
    """
    src = jnp.asarray(src)
    if not jnp.issubdtype(src.dtype, jnp.floating):
        src = src.astype(jnp.float32)
    dst = jnp.asarray(dst, src.dtype)
    w0 = jnp.ones(src.shape[:-1], src.dtype) if weights is None else jnp.asarray(weights).astype(src.dtype)
    ok = jnp.all(jnp.isfinite(src), -1) & jnp.all(jnp.isfinite(dst), -1) & jnp.isfinite(w0)
    w0 = jnp.where(ok, w0, 0)
    src = jnp.where(ok[..., None], src, 0)
    dst = jnp.where(ok[..., None], dst, 0)
    dt = src.dtype

    def huber(r):
        return jnp.where(r <= delta, 0.5 * r * r, delta * (r - 0.5 * delta))

    s, R, t = _vggt_long_weighted_sim3(src, dst, w0)

    def cond(state):
        k, _, _, _, _, done = state
        return (k < max_iters) & ~done

    def body(state):
        k, s, R, t, prev_err, _ = state
        pred = s * src @ R.T + t
        r = jnp.linalg.norm(dst - pred, axis=-1)
        h = jnp.where(r > delta, delta / jnp.where(r > delta, r, 1), 1)
        cw = w0 * h
        cw = cw / (jnp.sum(cw) + 1e-12)
        s_n, R_n, t_n = _vggt_long_weighted_sim3(src, dst, cw)
        change = jnp.abs(s_n - s) + jnp.linalg.norm(t_n - t)
        angle = jnp.arccos(jnp.clip((jnp.trace(R_n @ R.T) - 1) / 2, -1.0, 1.0))
        err = jnp.sum(huber(r) * w0)
        done = ((change < tol) & (angle < jnp.deg2rad(0.1))) | (jnp.abs(prev_err - err) < tol * prev_err)
        keep = lambda old, new: jnp.where(done, old, new)  # noqa: E731
        return (k + 1, keep(s, s_n), keep(R, R_n), keep(t, t_n), jnp.where(done, prev_err, err), done)

    state = (jnp.int32(0), s, R, t, jnp.asarray(jnp.inf, dt), jnp.asarray(False))
    k, s, R, t, _, done = jax.lax.while_loop(cond, body, state)
    return sim3.from_rst(R, t, s), IRLSInfo(iterations=k, converged=done)


# ----------------------------------------------------------------- chunk-pair alignment


class ChunkFrames(NamedTuple):
    """The overlap frames of one chunk (a NamedTuple, hence a pytree).

    Attributes:
        depth: ``[O, H, W]`` depth in the chunk's units.
        conf: ``[O, H, W]`` depth confidence.
        intrinsic: ``[O, 3, 3]``.
        extrinsic: ``[O, 3, 4]`` world-to-camera in the chunk's own frame.
    """

    depth: Array
    conf: Array
    intrinsic: Array
    extrinsic: Array

    @classmethod
    def from_prediction(cls, pred, index=slice(None)) -> "ChunkFrames":
        """Frames ``index`` (a slice or index array) of a :class:`~swiftjax.prediction.ChunkPrediction`."""
        return cls(pred.depth[index], pred.conf[index], pred.intrinsic[index], pred.extrinsic[index])


class AlignInfo(NamedTuple):
    """Diagnostics of :func:`align_chunk_pair` (scalars; batch shape ``[P]`` when batched).

    Attributes:
        num_points: int32 overlap points used (reliable pixels).
        fraction_used: ``num_points / (O H W)``; ``1 - fraction_used`` were masked out.
        rms: weighted RMS residual of the fit in chunk ``t`` units (closed form; its float32
            floor is about ``3e-4 x`` the spread of the points).
        valid: the Umeyama solve was well posed (see :class:`UmeyamaInfo`).
        used_fallback_threshold: fewer than ``min_points`` passed at ``depth_threshold`` and
            the mask was recomputed with ``fallback_depth_threshold``.
        depth_threshold: the ``lambda_D`` finally used.
        pose_fallback: ``S`` comes from :func:`pose_based_estimate` (Umeyama invalid).
        umeyama: the :class:`UmeyamaInfo` of the solve.
        src_mean, src_covariance: ``[3]``, ``[3, 3]`` weighted mean and covariance of the source
            points (chunk ``t+1``'s reliable overlap points, in chunk ``t+1`` units): with ``S``'s
            scale, ``num_points`` and ``rms`` they give the edge's information matrix
            (:func:`swiftjax.align_covariance.alignment_information`).  Zeros if no point is used.
    """

    num_points: Array
    fraction_used: Array
    rms: Array
    valid: Array
    used_fallback_threshold: Array
    depth_threshold: Array
    pose_fallback: Array
    umeyama: UmeyamaInfo
    src_mean: Array
    src_covariance: Array


def _chunk_geometry(frames: ChunkFrames, K_ref: Array):
    """Per-frame ``(focal ratio r [O], B = R_c2w K_ref^-1 [O,3,3], centre c [O,3])``.

    World point of pixel ``(u, v)`` of frame ``f``: ``x = r_f D (B_f (u, v, 1)) + c_f``,
    which is ``unproject(normalize_depth(D), K_ref, camera_to_world(E))`` (eq. 1 + pinhole).
    """
    r = camera.focal_ratio(frames.intrinsic, K_ref)
    c2w = camera.camera_to_world(frames.extrinsic)
    K_inv = jnp.linalg.inv(K_ref)
    B = c2w[..., :3, :3] @ K_inv
    return r, B, c2w[..., :3, 3]


def _points_soa(depth: Array, r: Array, B: Array, c: Array, centre: Array, u: Array, v: Array):
    """Centred world points as three ``[O, H, W]`` components (see :func:`_chunk_geometry`)."""
    e = (slice(None), None, None)
    d = r[e] * depth
    out = []
    for i in range(3):
        ray = B[:, i, 0][e] * u + B[:, i, 1][e] * v + B[:, i, 2][e]
        out.append(d * ray + (c[:, i] - centre[i])[e])
    return tuple(out)


def pose_based_estimate(prev_extrinsic: ArrayLike, cur_extrinsic: ArrayLike) -> tuple[Array, Array]:
    """``S_{t->t+1}`` from the overlap cameras alone (the fallback when Umeyama is invalid).

    Each overlap frame has a camera-to-world pose in both chunks, ``P_f`` (chunk t) and
    ``Q_f`` (chunk t+1).  ``R = chordal mean of R_Pf R_Qf^T`` (SVD projection of the sum);
    ``s = sqrt(sum |c_P - mean c_P|^2 / sum |c_Q - mean c_Q|^2)`` (1 when the cameras do not
    move); ``t = mean c_P - s R mean c_Q``.  Returns ``(S [8], ok)``; ``ok`` is False (and
    ``S`` the identity) when the extrinsics are not finite.
    """
    P = camera.camera_to_world(jnp.asarray(prev_extrinsic))
    Q = camera.camera_to_world(jnp.asarray(cur_extrinsic, P.dtype))
    ok = jnp.all(jnp.isfinite(P)) & jnp.all(jnp.isfinite(Q))
    P = jnp.where(ok, P, jnp.eye(3, 4, dtype=P.dtype))
    Q = jnp.where(ok, Q, jnp.eye(3, 4, dtype=P.dtype))
    M = jnp.sum(P[:, :, :3] @ jnp.swapaxes(Q[:, :, :3], -1, -2), axis=0)
    U, _, Vt = jnp.linalg.svd(M)
    d = jnp.where(jnp.linalg.det(U @ Vt) < 0, -1.0, 1.0).astype(P.dtype)
    R = (U * jnp.stack([jnp.ones_like(d), jnp.ones_like(d), d])) @ Vt
    cp, cq = P[:, :, 3], Q[:, :, 3]
    mp, mq = cp.mean(0), cq.mean(0)
    vp, vq = jnp.sum((cp - mp) ** 2), jnp.sum((cq - mq) ** 2)
    tiny = jnp.finfo(P.dtype).eps ** 2 * (1 + jnp.sum(mq * mq))
    s = jnp.where((vq > tiny) & (vp > tiny), jnp.sqrt(vp / jnp.where(vq > tiny, vq, 1)), 1.0)
    t = mp - s * R @ mq
    S = sim3.from_rst(R, t, s)
    return jnp.where(ok, S, sim3.identity(dtype=P.dtype)), ok


# Pixel-domain moments.  For frame f of a chunk, with normalised depth d = r_f D, pixel
# (u, v) = T (u~, v~, 1) (u~, v~ in [-1, 1]) and a rough per-frame depth centre e_f
# (d = delta + e_f), the centred world point is an affine map of the feature vector
#     phi = (delta u~, delta v~, delta, u~, v~, 1):    x - c = M_f phi,
#     M_f = [B~, e_f B~[:, :2], e_f B~[:, 2] + c_f - c]   (3 x 6),  B~ = R_c2w K_ref^-1 T.
# So every Umeyama moment is M_y,f G_f M_x,f^T summed over frames, where the 6 x 6 Gram
# matrices G_f = sum m phi_y phi_x^T are gathered from the per-frame pixel moments
#     S[f, (i, j), k, l] = sum_{h, w} m delta_p^i delta_c^j u~^k v~^l   (i + j <= 2, k, l <= 2).
_PHI_U = np.array([1, 0, 0, 1, 0, 0])  # power of u~ in phi
_PHI_V = np.array([0, 1, 0, 0, 1, 0])  # power of v~
_PHI_D = np.array([1, 1, 1, 0, 0, 0])  # power of delta
_IMAGES = ((0, 0), (1, 0), (0, 1), (1, 1), (2, 0), (0, 2))  # (power of delta_p, of delta_c)
_IMG = {ij: n for n, ij in enumerate(_IMAGES)}


def _gram_index(which: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index tables ``(image, k, l)`` ``[6, 6]`` gathering ``G`` from ``S`` (``which`` in yx/xx/yy)."""
    a, b = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
    da, db = _PHI_D[a], _PHI_D[b]
    pw = {"yx": zip(da.ravel(), db.ravel()), "xx": ((0, i + j) for i, j in zip(da.ravel(), db.ravel())),
          "yy": ((i + j, 0) for i, j in zip(da.ravel(), db.ravel()))}[which]
    img = np.array([_IMG[ij] for ij in pw]).reshape(6, 6)
    return tuple(x.astype(np.int32) for x in (img, _PHI_U[a] + _PHI_U[b], _PHI_V[a] + _PHI_V[b]))


_G_YX, _G_XX, _G_YY = (_gram_index(k) for k in ("yx", "xx", "yy"))


def _pixel_grid(h: int, w: int, dtype) -> tuple[Array, Array, Array]:
    """``u~ [W]``, ``v~ [H]`` in ``[-1, 1]`` and ``T [3, 3]`` with ``(u, v, 1) = T (u~, v~, 1)``."""
    u0, v0 = (w - 1) / 2, (h - 1) / 2
    su, sv = max(u0, 1.0), max(v0, 1.0)
    ut = (jnp.arange(w, dtype=dtype) - u0) / su
    vt = (jnp.arange(h, dtype=dtype) - v0) / sv
    T = jnp.array([[su, 0, u0], [0, sv, v0], [0, 0, 1]], dtype)
    return ut, vt, T


def _pixel_moments(ok: Array, a: Array, b: Array, ut: Array, vt: Array) -> tuple[Array, Array]:
    """Per-frame pixel moments ``S [O, 6, 3, 3]`` and the int32 count of ``ok`` pixels.

    ``ok`` bool ``[O, H, W]``; ``a = ok * delta_p``, ``b = ok * delta_c`` (zero where not ok).
    One variadic reduce over the pixel rows (18 terms: 6 images x powers of ``u~``), then a
    tiny contraction over rows with the powers of ``v~``.
    """
    m = ok.astype(a.dtype)
    u1 = jnp.broadcast_to(ut, a.shape)
    u2 = u1 * u1
    images = (m, a, b, a * b, a * a, b * b)  # order of _IMAGES
    rows = _variadic_sum(tuple(t for im in images for t in (im, im * u1, im * u2)), -1)
    R = jnp.stack(rows, -1).reshape(*a.shape[:-1], 6, 3)  # [O, H, 6, 3]
    V = jnp.stack([jnp.ones_like(vt), vt, vt * vt], -1)  # [H, 3]
    S = jnp.einsum("fhik,hl->fikl", R, V)
    n = jnp.sum(rows[0].astype(jnp.int32))  # row counts are exact (<= W < 2^24)
    return S, n


def _affine_maps(B: Array, c: Array, e: Array, centre: Array, T: Array) -> Array:
    """``M_f [O, 3, 6]``: centred world point ``= M_f phi`` (see the comment above).

    ``e`` is the per-frame centre of the *normalised* depth, so the focal ratio is already in
    ``delta`` and does not appear here.
    """
    Bt = B @ T
    last = e[:, None] * Bt[:, :, 2] + c - centre
    return jnp.concatenate([Bt, e[:, None, None] * Bt[:, :, :2], last[:, :, None]], -1)


def _moments_from_pixels(
    S: Array, n: Array, My: Array, Mx: Array, cx: Array, cy: Array
) -> tuple[_Moments, Array]:
    """Combine per-frame pixel moments with the per-frame affine maps into global moments, and the
    source scatter ``sum w (x - cx)(x - cx)^T`` ``[3, 3]`` (whose trace is ``sxx``)."""
    Gyx, Gxx, Gyy = (S[:, i, k, l] for i, k, l in (_G_YX, _G_XX, _G_YY))  # [O, 6, 6]
    moments = _Moments(
        w=jnp.sum(S[:, 0, 0, 0]),
        n=n,
        sx=jnp.einsum("fia,fa->i", Mx, Gxx[:, :, 5]),
        sy=jnp.einsum("fia,fa->i", My, Gyy[:, :, 5]),
        syx=jnp.einsum("fia,fab,fjb->ij", My, Gyx, Mx),
        sxx=jnp.einsum("fia,fab,fib->", Mx, Gxx, Mx),
        syy=jnp.einsum("fia,fab,fib->", My, Gyy, My),
        cx=cx,
        cy=cy,
    )
    return moments, jnp.einsum("fia,fab,fjb->ij", Mx, Gxx, Mx)


def _source_moments(m: _Moments, sxx3: Array) -> tuple[Array, Array]:
    """Weighted mean ``[3]`` and covariance ``[3, 3]`` of the source points (zeros if ``W = 0``)."""
    W = jnp.where(m.w > 0, m.w, 1)
    mx = m.sx / W
    cov = sxx3 / W - mx[:, None] * mx[None, :]
    ok = m.w > 0
    return jnp.where(ok, mx + m.cx, 0), jnp.where(ok, cov, 0)


def _frame_depth_centre(depth: Array, r: Array, sub: tuple) -> Array:
    """Rough per-frame centre of the normalised depth: mean of a strided subsample ``[O]``."""
    d = r[:, None, None] * depth[sub]
    fin = jnp.isfinite(d)
    cnt = jnp.sum(fin, (1, 2))
    e = jnp.sum(jnp.where(fin, d, 0), (1, 2)) / jnp.maximum(cnt, 1)
    return jax.lax.stop_gradient(jnp.where(jnp.isfinite(e), e, 0))


def _align_core(
    prev: ChunkFrames,
    cur: ChunkFrames,
    K_ref: Array,
    depth_threshold: Array,
    conf_ratio: Array,
    min_points: Array,
    fallback_depth_threshold: Array,
    user_keep: Array | None = None,
) -> tuple[Array, AlignInfo]:
    dtype = prev.depth.dtype
    o, h, w = prev.depth.shape
    K_ref = K_ref.astype(dtype)
    r_p, B_p, c_p = _chunk_geometry(prev, K_ref)
    r_c, B_c, c_c = _chunk_geometry(cur, K_ref)
    mean_p = frame_conf_mean(prev.conf)
    mean_c = frame_conf_mean(cur.conf)
    e = (slice(None), None, None)

    def mask(depth_p, depth_c, conf_p, conf_c, rp, rc, mp, mc, lam, user):
        m = reliability_mask(rp[e] * depth_p, rc[e] * depth_c, conf_p, conf_c, lam, conf_ratio, mp, mc)
        return m if user is None else m & user

    u = jnp.arange(w, dtype=dtype)[None, None, :]
    v = jnp.arange(h, dtype=dtype)[None, :, None]

    # Rough centres from a strided subsample of pixels (about 8 x 8 x 16 of them).
    fs, hs, ws = max(1, o // 8), max(1, h // 8), max(1, w // 16)
    sub = (slice(None, None, fs), slice(None, None, hs), slice(None, None, ws))
    fsub = slice(None, None, fs)
    m_sub = mask(prev.depth[sub], cur.depth[sub], prev.conf[sub], cur.conf[sub],
                 r_p[fsub], r_c[fsub], mean_p[fsub], mean_c[fsub], depth_threshold,
                 None if user_keep is None else user_keep[sub])
    zero = jnp.zeros(3, dtype)
    ps = _points_soa(prev.depth[sub], r_p[fsub], B_p[fsub], c_p[fsub], zero, u[sub], v[sub])
    cs = _points_soa(cur.depth[sub], r_c[fsub], B_c[fsub], c_c[fsub], zero, u[sub], v[sub])
    fin_sub = jnp.all(jnp.isfinite(jnp.stack(ps + cs)), 0)
    w_sub = (m_sub & fin_sub).astype(dtype).reshape(-1)
    p_pts = jnp.where(fin_sub[..., None], jnp.stack(ps, -1), 0).reshape(-1, 3)
    c_pts = jnp.where(fin_sub[..., None], jnp.stack(cs, -1), 0).reshape(-1, 3)
    cy = jax.lax.stop_gradient(_rough_centre(p_pts, w_sub))  # dst = prev
    cx = jax.lax.stop_gradient(_rough_centre(c_pts, w_sub))  # src = cur
    fsub_all = (slice(None), slice(None, None, hs), slice(None, None, ws))
    e_p = _frame_depth_centre(prev.depth, r_p, fsub_all)
    e_c = _frame_depth_centre(cur.depth, r_c, fsub_all)

    # Frames whose camera parameters are not finite are dropped as a whole (zero weight);
    # their zeroed parameters keep every per-frame term finite.
    frame_ok = (
        jnp.isfinite(r_p) & jnp.isfinite(r_c)
        & jnp.all(jnp.isfinite(B_p), (-2, -1)) & jnp.all(jnp.isfinite(B_c), (-2, -1))
        & jnp.all(jnp.isfinite(c_p), -1) & jnp.all(jnp.isfinite(c_c), -1)
    )
    fo = frame_ok[:, None, None]
    keep = lambda a: jnp.where(frame_ok.reshape((-1,) + (1,) * (a.ndim - 1)), a, 0)  # noqa: E731
    ut, vt, T = _pixel_grid(h, w, dtype)
    My = _affine_maps(*(keep(a) for a in (B_p, c_p, e_p)), cy, T)
    Mx = _affine_maps(*(keep(a) for a in (B_c, c_c, e_c)), cx, T)

    def moments(lam):
        ok = fo & mask(prev.depth, cur.depth, prev.conf, cur.conf, r_p, r_c, mean_p, mean_c, lam, user_keep)
        a = jnp.where(ok, r_p[e] * prev.depth - e_p[e], 0)  # delta_p (dst = prev)
        b = jnp.where(ok, r_c[e] * cur.depth - e_c[e], 0)  # delta_c (src = cur)
        return _pixel_moments(ok, a, b, ut, vt)

    S_pix, n = moments(depth_threshold)
    few = n < min_points
    S_pix, n = jax.lax.cond(few, lambda: moments(fallback_depth_threshold), lambda: (S_pix, n))
    lam_used = jnp.where(few, fallback_depth_threshold, depth_threshold).astype(dtype)
    m, sxx3 = _moments_from_pixels(S_pix, n, My, Mx, cx, cy)
    S, uinfo = _solve(m)
    src_mean, src_cov = _source_moments(m, sxx3)
    S_pose, _ = pose_based_estimate(prev.extrinsic.astype(dtype), cur.extrinsic.astype(dtype))
    S = jnp.where(uinfo.valid, S, S_pose)
    info = AlignInfo(
        num_points=uinfo.num_points,
        fraction_used=uinfo.num_points.astype(dtype) / (o * h * w),
        rms=uinfo.rms,
        valid=uinfo.valid,
        used_fallback_threshold=few,
        depth_threshold=lam_used,
        pose_fallback=~uinfo.valid,
        umeyama=uinfo,
        src_mean=src_mean,
        src_covariance=src_cov,
    )
    return S, info


_align_core_jit = jax.jit(_align_core)
_align_core_batched = jax.jit(jax.vmap(_align_core, in_axes=(0, 0, 0, None, None, None, None, 0)))


def _as_frames(x, dtype=None) -> ChunkFrames:
    return ChunkFrames(*(jnp.asarray(getattr(x, f), dtype) for f in ChunkFrames._fields))


def _core_arguments(prev, cur, K_ref, depth_threshold, conf_ratio, min_points, fallback_depth_threshold):
    """Both chunks' frames in one floating dtype (the depth's; float32 for integer depth) and
    every option as a traced array, in the order of :func:`_align_core`."""
    prev = _as_frames(prev)
    dtype = prev.depth.dtype if jnp.issubdtype(prev.depth.dtype, jnp.floating) else jnp.float32
    return (
        _as_frames(prev, dtype),
        _as_frames(cur, dtype),
        jnp.asarray(K_ref, dtype),
        jnp.asarray(depth_threshold, dtype),
        jnp.asarray(conf_ratio, dtype),
        jnp.asarray(min_points, jnp.int32),
        jnp.asarray(fallback_depth_threshold, dtype),
    )


def align_chunk_pair(
    prev: ChunkFrames,
    cur: ChunkFrames,
    K_ref: ArrayLike,
    *,
    depth_threshold: float = 0.2,
    conf_ratio: float = 0.5,
    min_points: int = 20_000,
    fallback_depth_threshold: float = 0.25,
    mask: ArrayLike | None = None,
) -> tuple[Array, AlignInfo]:
    """``S_{t->t+1}`` (maps chunk t+1 coordinates into chunk t) from the overlap frames.

    ``prev`` holds the LAST ``O`` frames of chunk ``t`` and ``cur`` the FIRST ``O`` frames of
    chunk ``t+1`` (the same global frames).  For each chunk: depths normalised to ``K_ref``
    (eq. 1), unprojected with ``K_ref`` at integer pixels, mapped to the chunk frame with the
    inverse of that chunk's extrinsic.  Reliable pixels (eq. 2, :func:`reliability_mask`)
    weight one Umeyama solve with ``src`` = chunk t+1's points, ``dst`` = chunk t's points.
    If fewer than ``min_points`` pass, the mask is recomputed once with
    ``fallback_depth_threshold`` (the authors' rule).  If the solve is still invalid (e.g.
    empty overlap), ``S`` is :func:`pose_based_estimate` of the overlap cameras (identity if
    those are not finite either) and ``info.pose_fallback`` is set: ``S`` is always finite.

    Args:
        prev, cur: :class:`ChunkFrames` (``depth, conf [O, H, W]``, ``intrinsic [O, 3, 3]``,
            ``extrinsic [O, 3, 4]``), or any object with those attributes
            (e.g. a :class:`swiftjax.prediction.ChunkPrediction` sliced to the overlap).
        K_ref: ``[3, 3]`` reference intrinsics.
        depth_threshold, conf_ratio, min_points, fallback_depth_threshold: options
            (traced: changing them never recompiles).  Loop chunks use ``depth_threshold=0.4``.
        mask: optional bool ``[O, H, W]`` keep-mask of the overlap frames (user masks, sky;
            :mod:`swiftjax.masks`; both chunks see the same frames, so one mask): pixels where
            it is False are never reliable.  ``None`` keeps every pixel (a masked pair
            compiles once more).  A mask that keeps nothing ends in the pose fallback.

    Returns:
        ``(S [8], AlignInfo)``.  One jitted call; it compiles once per ``(O, H, W)`` and dtype.
        One pass over the pixels accumulates per-frame pixel moments (module docstring),
        plus one plain sum over the confidences for their per-frame means; the fallback
        pass runs only when needed.
    """
    args = _core_arguments(prev, cur, K_ref, depth_threshold, conf_ratio, min_points, fallback_depth_threshold)
    return _align_core_jit(*args, None if mask is None else jnp.asarray(mask, bool))


def align_chunk_pairs(
    prev: ChunkFrames,
    cur: ChunkFrames,
    K_ref: ArrayLike,
    *,
    depth_threshold: float = 0.2,
    conf_ratio: float = 0.5,
    min_points: int = 20_000,
    fallback_depth_threshold: float = 0.25,
    mask: ArrayLike | None = None,
) -> tuple[Array, AlignInfo]:
    """:func:`align_chunk_pair` for ``P`` pairs at once (``jax.vmap``, one jitted call).

    ``prev``/``cur`` fields carry a leading ``[P]`` axis; ``K_ref`` is ``[3, 3]`` (shared)
    or ``[P, 3, 3]``; ``mask`` is ``None`` or bool ``[P, O, H, W]``.  Returns ``(S [P, 8], AlignInfo with [P] fields)``.  Under ``vmap``
    the fallback-threshold pass becomes a select, so it is computed for every pair.
    """
    prev, cur, K, *options = _core_arguments(
        prev, cur, K_ref, depth_threshold, conf_ratio, min_points, fallback_depth_threshold
    )
    keep = None if mask is None else jnp.asarray(mask, bool)
    return _align_core_batched(prev, cur, jnp.broadcast_to(K, (prev.depth.shape[0], 3, 3)), *options, keep)


def _check_frames(name: str, f, shape: tuple[int, int, int] | None) -> tuple[int, int, int]:
    for field in ChunkFrames._fields:
        if not hasattr(f, field):
            raise ValueError(f"{name} has no field {field!r} (expected depth, conf, intrinsic, extrinsic)")
    d = np.shape(f.depth)
    if len(d) != 3:
        raise ValueError(f"{name}.depth must be [O, H, W], got shape {d}")
    if shape is not None and d != shape:
        raise ValueError(f"{name}.depth has shape {d} but the other chunk's overlap is {shape}")
    o = d[0]
    for field, want in (("conf", d), ("intrinsic", (o, 3, 3)), ("extrinsic", (o, 3, 4))):
        got = np.shape(getattr(f, field))
        if got != tuple(want):
            raise ValueError(f"{name}.{field} has shape {got}, expected {tuple(want)}")
    K = np.asarray(f.intrinsic, np.float64)
    if not np.all(np.isfinite(K)):
        raise ValueError(f"{name}.intrinsic has non-finite entries")
    if not (np.all(K[:, 0, 0] > 0) and np.all(K[:, 1, 1] > 0)):
        raise ValueError(f"{name}.intrinsic has a non-positive focal length (fx, fy must be > 0)")
    return d


def align_chunk_pair_checked(
    prev,
    cur,
    K_ref: ArrayLike,
    *,
    name: str = "chunk pair",
    **options,
) -> tuple[Array, AlignInfo]:
    """Host-level :func:`align_chunk_pair`: validates inputs first, warns on a fallback.

    Raises:
        ValueError: shapes do not match (``depth, conf [O, H, W]``, ``intrinsic [O, 3, 3]``,
            ``extrinsic [O, 3, 4]``, both chunks the same ``O, H, W``), ``O == 0``, or an
            intrinsic (``K_ref`` included) is non-finite or has a focal ``<= 0``.

    Warns (``RuntimeWarning``) when the Umeyama solve was invalid and the pose-based
    estimate (or identity) was returned (saying how much of the overlap a ``mask`` kept:
    a mask removing the whole overlap ends here).  The fallback depth threshold is the authors'
    normal rule, not a warning: it is reported in ``info.used_fallback_threshold``.
    The returned ``S`` is always finite.
    """
    shape = _check_frames("prev", prev, None)
    _check_frames("cur", cur, shape)
    if shape[0] == 0:
        raise ValueError("the overlap is empty: prev/cur have O = 0 frames")
    K = np.asarray(K_ref, np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K_ref must be [3, 3], got shape {K.shape}")
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K_ref must be finite with positive focal lengths, got {K.tolist()}")
    mask = options.get("mask")
    if mask is not None and tuple(np.shape(mask)) != tuple(shape):
        raise ValueError(f"mask has shape {tuple(np.shape(mask))}, expected the overlap's {tuple(shape)}")
    S, info = align_chunk_pair(prev, cur, K_ref, **options)
    if bool(info.pose_fallback):
        masked = "" if mask is None else f"; the mask keeps {100 * float(np.mean(mask)):.2f}% of its pixels"
        warnings.warn(
            f"{name}: Umeyama alignment is ill-posed ({int(info.num_points)} reliable points, "
            f"{100 * float(info.fraction_used):.2f}% of the overlap{masked}); using the estimate "
            "from the overlap camera poses instead",
            RuntimeWarning,
            stacklevel=2,
        )
    return S, info


@jax.jit
def irls_chunk_pair(
    prev: ChunkFrames, cur: ChunkFrames, K_ref: Array, depth_threshold: Array, conf_ratio: Array,
) -> tuple[Array, IRLSInfo, Array]:
    """VGGT-Long's IRLS Sim(3) (:func:`irls_sim3`) on the same reliable overlap points as
    :func:`align_chunk_pair` (the comparison baseline).

    ``prev``/``cur``: the overlap frames ``[O, H, W]`` of the earlier and later chunk; both
    are depth-normalised to ``K_ref`` (eq. 1) and unprojected with ``K_ref``; the reliable
    pixels are :func:`reliability_mask`'s, with finite points in both.  Returns ``(S, info,
    count)``: ``S [8]`` maps ``cur``'s chunk into ``prev``'s, ``count`` the number of
    reliable points.  Recompiles per ``(O, H, W)`` and dtype.
    """

    def points(f: ChunkFrames) -> tuple[Array, Array]:
        d = camera.normalize_depth(f.depth, f.intrinsic, K_ref)
        return d, camera.unproject(d, K_ref, camera.camera_to_world(f.extrinsic))

    dp, xp = points(prev)
    dc, xc = points(cur)
    ok = reliability_mask(dp, dc, prev.conf, cur.conf, depth_threshold, conf_ratio)
    ok = ok & jnp.all(jnp.isfinite(xp), -1) & jnp.all(jnp.isfinite(xc), -1)
    src = jnp.where(ok[..., None], xc, 0.0).reshape(-1, 3)
    dst = jnp.where(ok[..., None], xp, 0.0).reshape(-1, 3)
    S, info = irls_sim3(src, dst, ok.reshape(-1).astype(src.dtype))
    return S, info, jnp.sum(ok)

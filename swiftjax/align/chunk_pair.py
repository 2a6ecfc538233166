"""Chunk-pair alignment: ``S_{t->t+1}`` from the overlap frames of two neighbouring chunks.

SwiftVGGT aligns two neighbouring chunks with ONE closed-form weighted Umeyama solve
(:mod:`swiftjax.align.umeyama`) on the reliable overlap points (eq. 2,
:mod:`swiftjax.align.mask`), no iterations.

:func:`align_chunk_pair` never forms the world points: every point of frame ``f`` is an
affine map of ``phi = (delta u~, delta v~, delta, u~, v~, 1)`` (``delta`` the normalised
depth minus a rough per-frame centre, ``u~, v~`` the pixel coordinates scaled to
``[-1, 1]``), so all moments follow from per-frame *pixel* moments
``sum m delta_p^i delta_c^j u~^k v~^l`` (6 images x powers of ``u~``: 18 terms in one
variadic reduce over each pixel row, then a tiny contraction with the powers of ``v~`` and
``sum_f M_y,f G_f M_x,f^T`` over frames).  The inputs are read once (plus the confidences
once more for their per-frame means); the centring (per-frame depth centre, global rough
world centres) keeps float32 accurate (tested far from the origin).  Speed on XLA:CPU:
``docs/performance/align.md``.
"""

from __future__ import annotations

import logging
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import DTypeLike
from jaxtyping import ArrayLike, Bool, Float, Real

from swiftjax import camera, sim3, so3
from swiftjax._reductions import variadic_sum
from swiftjax.align import _kernels, checks
from swiftjax.align.mask import overlap_scale_ratio, reliability_mask
from swiftjax.align.options import OVERLAP_SCALE_RULES, AlignOptions
from swiftjax.align.umeyama import UmeyamaInfo, _Moments, _rough_centre, _solve

__all__ = [
    "ChunkFrames",
    "AlignInfo",
    "align_chunk_pair",
    "align_chunk_pairs",
    "align_chunk_pair_checked",
    "pose_based_estimate",
]

logger = logging.getLogger(__name__)


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
    def from_prediction(cls, pred: Any, index: Any = slice(None)) -> ChunkFrames:
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
            (:func:`swiftjax.align.covariance.alignment_information`).  Zeros if no point is used.
        scale_ratio: ``rho``, the factor chunk ``t+1``'s overlap depths were multiplied by
            before eq. 2 (:func:`~swiftjax.align.overlap_scale_ratio`; 1 with
            ``overlap_scale="none"``).
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
    scale_ratio: Array


def _chunk_geometry(frames: ChunkFrames, K_ref: Array) -> tuple[Array, Array, Array]:
    """Per-frame ``(focal ratio r [O], B = R_c2w K_ref^-1 [O,3,3], centre c [O,3])``.

    World point of pixel ``(u, v)`` of frame ``f``: ``x = r_f D (B_f (u, v, 1)) + c_f``,
    which is ``unproject(normalize_depth(D), K_ref, camera_to_world(E))`` (eq. 1 + pinhole).
    """
    r = camera.focal_ratio(frames.intrinsic, K_ref)
    c2w = camera.camera_to_world(frames.extrinsic)
    K_inv = jnp.linalg.inv(K_ref)
    B = c2w[..., :3, :3] @ K_inv
    return r, B, c2w[..., :3, 3]


def _points_soa(
    depth: Array, r: Array, B: Array, c: Array, centre: Array, u: Array, v: Array
) -> tuple[Array, Array, Array]:
    """Centred world points as three ``[O, H, W]`` components (see :func:`_chunk_geometry`)."""
    e = (slice(None), None, None)
    d = r[e] * depth
    out = []
    for i in range(3):
        ray = B[:, i, 0][e] * u + B[:, i, 1][e] * v + B[:, i, 2][e]
        out.append(d * ray + (c[:, i] - centre[i])[e])
    return out[0], out[1], out[2]


def pose_based_estimate(
    prev_extrinsic: Real[ArrayLike, "O 3 4"], cur_extrinsic: Real[ArrayLike, "O 3 4"]
) -> tuple[Float[Array, 8], Bool[Array, ""]]:
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
    R = so3.as_matrix(so3.project(M))
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
    pw = {
        "yx": zip(da.ravel(), db.ravel()),
        "xx": ((0, i + j) for i, j in zip(da.ravel(), db.ravel())),
        "yy": ((i + j, 0) for i, j in zip(da.ravel(), db.ravel())),
    }[which]
    img = np.array([_IMG[ij] for ij in pw]).reshape(6, 6)
    k, l = _PHI_U[a] + _PHI_U[b], _PHI_V[a] + _PHI_V[b]
    return img.astype(np.int32), k.astype(np.int32), l.astype(np.int32)


_G_YX, _G_XX, _G_YY = (_gram_index(k) for k in ("yx", "xx", "yy"))


def _pixel_grid(h: int, w: int, dtype: DTypeLike) -> tuple[Array, Array, Array]:
    """``u~ [W]``, ``v~ [H]`` in ``[-1, 1]`` and ``T [3, 3]`` with ``(u, v, 1) = T (u~, v~, 1)``."""
    u0, v0 = (w - 1) / 2, (h - 1) / 2
    su, sv = max(u0, 1.0), max(v0, 1.0)
    ut = (jnp.arange(w, dtype=dtype) - u0) / su
    vt = (jnp.arange(h, dtype=dtype) - v0) / sv
    T = jnp.array([[su, 0, u0], [0, sv, v0], [0, 0, 1]], dtype)
    return ut, vt, T


def _pixel_moments(ok: Array, a: Array, b: Array, ut: Array, vt: Array) -> tuple[Array, Array]:
    """Per-frame pixel moments ``S [O, 6, 3, 3]`` and the int32 counts ``[O]`` of ``ok`` pixels.

    ``ok`` bool ``[O, H, W]``; ``a = ok * delta_p``, ``b = ok * delta_c`` (zero where not ok).
    One variadic reduce over the pixel rows (18 terms: 6 images x powers of ``u~``), then a
    tiny contraction over rows with the powers of ``v~``.
    """
    m = ok.astype(a.dtype)
    u1 = jnp.broadcast_to(ut, a.shape)
    u2 = u1 * u1
    images = (m, a, b, a * b, a * a, b * b)  # order of _IMAGES
    rows = variadic_sum(tuple(t for im in images for t in (im, im * u1, im * u2)), -1)
    R = jnp.stack(rows, -1).reshape(*a.shape[:-1], 6, 3)  # [O, H, 6, 3]
    V = jnp.stack([jnp.ones_like(vt), vt, vt * vt], -1)  # [H, 3]
    S = jnp.einsum("...fhik,hl->...fikl", R, V)
    n = jnp.sum(rows[0].astype(jnp.int32), -1)  # row counts are exact (<= W < 2^24)
    return S, n


def _masked_pixel_moments(
    dp: Array, dc: Array, cp: Array, cc: Array, params: Array, ut: Array, vt: Array
) -> tuple[Array, Array]:
    """:func:`_pixel_moments` of the reliable pixels (eq. 2) of ``[O, H, W]`` depths and
    confidences, from the per-frame ``params [O, 6] = (r_p, r_c, e_p, e_c, gamma, lam)``:
    focal ratios, normalised-depth centres, confidence ratio (threshold ``gamma`` times the
    frame's :func:`~swiftjax.align.frame_conf_mean`) and depth threshold (the reference of the fused kernel,
    :func:`swiftjax.align._kernels.pixel_moments`, which takes the confidence means in the same
    pass)."""
    r_p, r_c, e_p, e_c, gamma, lam = (params[..., i] for i in range(6))
    e = (Ellipsis, None, None)
    ok = reliability_mask(r_p[e] * dp, r_c[e] * dc, cp, cc, lam, gamma)
    a = jnp.where(ok, r_p[e] * dp - e_p[e], 0)  # delta_p (dst = prev)
    b = jnp.where(ok, r_c[e] * dc - e_c[e], 0)  # delta_c (src = cur)
    return _pixel_moments(ok, a, b, ut, vt)


def _affine_maps(B: Array, c: Array, e: Array, centre: Array, T: Array) -> Array:
    """``M_f [O, 3, 6]``: centred world point ``= M_f phi`` (see the comment above).

    ``e`` is the per-frame centre of the *normalised* depth, so the focal ratio is already in
    ``delta`` and does not appear here.
    """
    Bt = B @ T
    last = e[:, None] * Bt[:, :, 2] + c - centre
    return jnp.concatenate([Bt, e[:, None, None] * Bt[:, :, :2], last[:, :, None]], -1)


def _moments_from_pixels(S: Array, n: Array, My: Array, Mx: Array, cx: Array, cy: Array) -> tuple[_Moments, Array]:
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


def _frame_depth_centre(depth: Array, r: Array, sub: tuple[Any, ...]) -> Array:
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
    scale_mode: Array,
    user_keep: Array | None = None,
) -> tuple[Array, AlignInfo]:
    """``scale_mode`` (int32, traced): 0 ``"none"``, 1 ``"median"``, 2 ``"auto"`` (the authors'
    solve, redone with the ratio only when even their retry leaves fewer than ``min_points``;
    a ``lax.cond``: the second solve runs only then, except under ``vmap``)."""
    args = (prev, cur, K_ref, depth_threshold, conf_ratio, min_points, fallback_depth_threshold)
    S, info = _align_once(*args, scale_mode == 1, user_keep)
    redo = (scale_mode == 2) & (info.num_points < min_points)
    return jax.lax.cond(redo, lambda: _align_once(*args, True, user_keep), lambda: (S, info))


def _align_once(
    prev: ChunkFrames,
    cur: ChunkFrames,
    K_ref: Array,
    depth_threshold: Array,
    conf_ratio: Array,
    min_points: Array,
    fallback_depth_threshold: Array,
    use_scale_ratio: Array | bool,
    user_keep: Array | None = None,
) -> tuple[Array, AlignInfo]:
    dtype = prev.depth.dtype
    o, h, w = prev.depth.shape
    K_ref = K_ref.astype(dtype)
    r_p, B_p, c_p = _chunk_geometry(prev, K_ref)
    r_c, B_c, c_c = _chunk_geometry(cur, K_ref)
    e = (slice(None), None, None)
    fs, hs, ws = max(1, o // 8), max(1, h // 8), max(1, w // 16)
    sub = (slice(None, None, fs), slice(None, None, hs), slice(None, None, ws))
    fsub = slice(None, None, fs)

    # The gauge of chunk t+1 put on chunk t's (mask.py): rho from a strided subsample of the
    # confident overlap pixels, then chunk t+1's geometry is scaled by rho about its origin
    # (depths and camera centres: its points become rho x, a similarity), so eq. 2 compares
    # depths in chunk t's units and the solve below returns S' = S diag(rho)^-1; S = S' diag(rho).
    # With rho = 1 every product below is exact: the authors' numbers bit for bit.
    rho, _ = overlap_scale_ratio(
        r_p[fsub][e] * prev.depth[sub],
        r_c[fsub][e] * cur.depth[sub],
        prev.conf[sub],
        cur.conf[sub],
        conf_ratio,
        None if user_keep is None else user_keep[sub],
    )
    rho = jax.lax.stop_gradient(jnp.where(use_scale_ratio, rho, 1).astype(dtype))
    r_c, c_c = rho * r_c, rho * c_c

    def mask(
        depth_p: Array,
        depth_c: Array,
        conf_p: Array,
        conf_c: Array,
        rp: Array,
        rc: Array,
        lam: Array,
        user: Array | None,
    ) -> Array:
        m = reliability_mask(rp[e] * depth_p, rc[e] * depth_c, conf_p, conf_c, lam, conf_ratio)
        return m if user is None else m & user

    u = jnp.arange(w, dtype=dtype)[None, None, :]
    v = jnp.arange(h, dtype=dtype)[None, :, None]

    # Rough centres from a strided subsample of pixels (about 8 x 8 x 16 of them), masked with
    # the subsample's own confidence means: any centre is exact, it only conditions the sums.
    m_sub = mask(
        prev.depth[sub],
        cur.depth[sub],
        prev.conf[sub],
        cur.conf[sub],
        r_p[fsub],
        r_c[fsub],
        depth_threshold,
        None if user_keep is None else user_keep[sub],
    )
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
        jnp.isfinite(r_p)
        & jnp.isfinite(r_c)
        & jnp.all(jnp.isfinite(B_p), (-2, -1))
        & jnp.all(jnp.isfinite(B_c), (-2, -1))
        & jnp.all(jnp.isfinite(c_p), -1)
        & jnp.all(jnp.isfinite(c_c), -1)
    )
    keep = lambda a: jnp.where(frame_ok.reshape((-1,) + (1,) * (a.ndim - 1)), a, 0)
    ut, vt, T = _pixel_grid(h, w, dtype)
    My = _affine_maps(keep(B_p), keep(c_p), keep(e_p), cy, T)
    Mx = _affine_maps(keep(B_c), keep(c_c), keep(e_c), cx, T)

    # The mask (eq. 2) and the deltas of every frame from one [O, 7] table of per-frame
    # parameters: a dropped frame gets lam = -1 (nothing passes), a pixel the user masks out a
    # NaN depth (never reliable).  The fused kernel reads the same table.
    dp = prev.depth if user_keep is None else jnp.where(user_keep, prev.depth, jnp.nan)
    gamma = jnp.broadcast_to(jnp.asarray(conf_ratio, dtype), r_p.shape)

    def moments(lam: Array) -> tuple[Array, Array]:
        lam_f = jnp.where(frame_ok, lam, -1).astype(dtype)
        params = jnp.stack([r_p, r_c, e_p, e_c, gamma, lam_f], -1)
        S, n = _kernels.pixel_moments(dp, cur.depth, prev.conf, cur.conf, params, ut, vt, _masked_pixel_moments)
        return S, jnp.sum(n)

    S_pix, n = moments(depth_threshold)
    few = n < min_points
    S_pix, n = jax.lax.cond(few, lambda: moments(fallback_depth_threshold), lambda: (S_pix, n))
    lam_used = jnp.where(few, fallback_depth_threshold, depth_threshold).astype(dtype)
    m, sxx3 = _moments_from_pixels(S_pix, n, My, Mx, cx, cy)
    S, uinfo = _solve(m)
    S = S.at[..., 7].multiply(rho)  # S' diag(rho): back to chunk t+1's own units
    uinfo = uinfo._replace(singular_values=uinfo.singular_values / rho)
    src_mean, src_cov = _source_moments(m, sxx3)
    src_mean, src_cov = src_mean / rho, src_cov / (rho * rho)
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
        scale_ratio=rho,
    )
    return S, info


_align_core_jit = _kernels.jit(_align_core)
_align_core_batched = _kernels.jit(jax.vmap(_align_core, in_axes=(0, 0, 0, None, None, None, None, None, 0)))


def _as_frames(x: Any, dtype: DTypeLike | None = None) -> ChunkFrames:
    return ChunkFrames(*(jnp.asarray(getattr(x, f), dtype) for f in ChunkFrames._fields))


def _core_arguments(prev: Any, cur: Any, K_ref: Any, options: AlignOptions) -> tuple[Any, ...]:
    """Both chunks' frames in one floating dtype (the depth's; float32 for integer depth) and
    every option as a traced array, in the order of :func:`_align_core`."""
    prev = _as_frames(prev)
    dtype = prev.depth.dtype if jnp.issubdtype(prev.depth.dtype, jnp.floating) else jnp.float32
    return (
        _as_frames(prev, dtype),
        _as_frames(cur, dtype),
        jnp.asarray(K_ref, dtype),
        jnp.asarray(options.depth_threshold, dtype),
        jnp.asarray(options.conf_ratio, dtype),
        jnp.asarray(options.min_points, jnp.int32),
        jnp.asarray(options.fallback_depth_threshold, dtype),
        jnp.asarray(OVERLAP_SCALE_RULES.index(options.overlap_scale), jnp.int32),
    )


def align_chunk_pair(
    prev: ChunkFrames,
    cur: ChunkFrames,
    K_ref: Real[ArrayLike, "3 3"],
    *,
    options: AlignOptions | None = None,
    mask: Bool[ArrayLike, "O H W"] | None = None,
) -> tuple[Float[Array, 8], AlignInfo]:
    """``S_{t->t+1}`` (maps chunk t+1 coordinates into chunk t) from the overlap frames.

    ``prev`` holds the LAST ``O`` frames of chunk ``t`` and ``cur`` the FIRST ``O`` frames of
    chunk ``t+1`` (the same global frames).  For each chunk: depths normalised to ``K_ref``
    (eq. 1), unprojected with ``K_ref`` at integer pixels, mapped to the chunk frame with the
    inverse of that chunk's extrinsic.  Reliable pixels (eq. 2, :func:`reliability_mask`)
    weight one Umeyama solve with ``src`` = chunk t+1's points, ``dst`` = chunk t's points.
    Before eq. 2, chunk t+1 is put on chunk t's scale by the robust ratio ``rho`` of the
    overlap depths (:func:`~swiftjax.align.overlap_scale_ratio` on a strided subsample), so a
    gauge jump between the chunks (each normalised to its own mean depth) does not empty the
    mask: ``options.overlap_scale="median"`` always, ``"auto"`` (default) only when the authors'
    eq. 2 and their retry leave fewer than ``min_points`` (otherwise the authors' numbers bit for
    bit), ``"none"`` never.  ``S`` is in the chunks' own units either way and
    ``info.scale_ratio`` is the ``rho`` used (1 when none).
    If fewer than ``min_points`` pass, the mask is recomputed once with
    ``fallback_depth_threshold`` (the authors' rule).  If the solve is still invalid (e.g.
    empty overlap), ``S`` is :func:`pose_based_estimate` of the overlap cameras (identity if
    those are not finite either) and ``info.pose_fallback`` is set: ``S`` is always finite.

    Args:
        prev, cur: :class:`ChunkFrames` (``depth, conf [O, H, W]``, ``intrinsic [O, 3, 3]``,
            ``extrinsic [O, 3, 4]``), or any object with those attributes
            (e.g. a :class:`swiftjax.prediction.ChunkPrediction` sliced to the overlap).
        K_ref: ``[3, 3]`` reference intrinsics.
        options: :class:`AlignOptions` (default ``AlignOptions()``; vary it with
            ``options.replace(depth_threshold=...)``); loop chunks use ``options.for_loop()``.
            Every option is traced: changing one never recompiles.
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
    args = _core_arguments(prev, cur, K_ref, AlignOptions() if options is None else options)
    return _align_core_jit(*args, None if mask is None else jnp.asarray(mask, bool))


def align_chunk_pairs(
    prev: ChunkFrames,
    cur: ChunkFrames,
    K_ref: Real[ArrayLike, "3 3"] | Real[ArrayLike, "P 3 3"],
    *,
    options: AlignOptions | None = None,
    mask: Bool[ArrayLike, "P O H W"] | None = None,
) -> tuple[Float[Array, "P 8"], AlignInfo]:
    """:func:`align_chunk_pair` for ``P`` pairs at once (``jax.vmap``, one jitted call).

    ``prev``/``cur`` fields carry a leading ``[P]`` axis; ``K_ref`` is ``[3, 3]`` (shared)
    or ``[P, 3, 3]``; ``mask`` is ``None`` or bool ``[P, O, H, W]``; ``options`` is shared by every pair.  Returns ``(S [P, 8], AlignInfo with [P] fields)``.  Under ``vmap`` the
    fallback-threshold pass becomes a select, so it is computed for every pair.
    """
    prev, cur, K, *option_args = _core_arguments(prev, cur, K_ref, AlignOptions() if options is None else options)
    keep = None if mask is None else jnp.asarray(mask, bool)
    return _align_core_batched(prev, cur, jnp.broadcast_to(K, (prev.depth.shape[0], 3, 3)), *option_args, keep)


def align_chunk_pair_checked(
    prev: Any,
    cur: Any,
    K_ref: Real[ArrayLike, "3 3"],
    *,
    name: str = "chunk pair",
    throw: bool = True,
    options: AlignOptions | None = None,
    mask: Bool[ArrayLike, "O H W"] | None = None,
) -> tuple[Float[Array, 8], AlignInfo]:
    """Host-level :func:`align_chunk_pair`: validates inputs first, warns on a fallback.

    Args:
        prev, cur, K_ref, options, mask: as :func:`align_chunk_pair`.
        name: names the pair in errors and warnings.
        throw: True: check the inputs on the host (:func:`swiftjax.align.checks.check_chunk_pair`)
            and warn when the solve fell back to the poses.  False: no host check, no warning
            and no device synchronisation; the caller reads ``info.valid`` /
            ``info.pose_fallback`` (frames with non-finite cameras are dropped either way).

    Raises (``throw=True``):
        ValueError: shapes do not match (``depth, conf [O, H, W]``, ``intrinsic [O, 3, 3]``,
            ``extrinsic [O, 3, 4]``, both chunks the same ``O, H, W``), ``O == 0``, or an
            intrinsic (``K_ref`` included) is non-finite or has a focal ``<= 0``.

    Warns (``RuntimeWarning``, ``throw=True``) when the Umeyama solve was invalid and the
    pose-based estimate (or identity) was returned (saying how much of the overlap a ``mask``
    kept: a mask removing the whole overlap ends here).  The fallback depth threshold is the
    authors' normal rule, not a warning: it is reported in ``info.used_fallback_threshold``.
    The returned ``S`` is always finite.
    """
    if throw:
        checks.check_chunk_pair(prev, cur, K_ref, mask)
    S, info = align_chunk_pair(prev, cur, K_ref, options=options, mask=mask)
    if throw and bool(info.pose_fallback):
        masked = "" if mask is None else f"; the mask keeps {100 * float(np.mean(mask)):.2f}% of its pixels"
        logger.warning(
            f"{name}: Umeyama alignment is ill-posed ({int(info.num_points)} reliable points, "
            f"{100 * float(info.fraction_used):.2f}% of the overlap{masked}); using the estimate "
            "from the overlap camera poses instead"
        )
    return S, info

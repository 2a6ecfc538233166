"""VGGT-Long's robust IRLS Sim(3), kept as the comparison baseline of the single Umeyama solve.

:func:`irls_sim3` is a faithful port of VGGT-Long's ``robust_weighted_estimate_sim3``;
:func:`irls_chunk_pair` runs it on the same reliable overlap points as
:func:`swiftjax.align.align_chunk_pair` (the pipeline's ``alignment = "irls"``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Bool, Float, Int, Real, Shaped

from swiftjax import camera, sim3
from swiftjax.align.chunk_pair import ChunkFrames
from swiftjax.align.mask import reliability_mask

__all__ = ["IRLSInfo", "irls_sim3", "irls_chunk_pair"]


class IRLSInfo(NamedTuple):
    """Diagnostics of :func:`irls_sim3`: ``iterations`` (int32) run and ``converged`` (bool)."""

    iterations: Int[Array, ""]
    converged: Bool[Array, ""]


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
    src: Real[ArrayLike, "N 3"],
    dst: Real[ArrayLike, "N 3"],
    weights: Shaped[ArrayLike, " N"] | None = None,
    delta: float | Real[Array, ""] = 0.1,  # traced when given (jit without static arguments)
    max_iters: int | Int[Array, ""] = 5,
    tol: float | Real[Array, ""] = 1e-9,
) -> tuple[Float[Array, 8], IRLSInfo]:
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

    def huber(r: Array) -> Array:
        return jnp.where(r <= delta, 0.5 * r * r, delta * (r - 0.5 * delta))

    s, R, t = _vggt_long_weighted_sim3(src, dst, w0)

    def cond(state: Any) -> Any:
        k, _, _, _, _, done = state
        return (k < max_iters) & ~done

    def body(state: Any) -> Any:
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
        keep = lambda old, new: jnp.where(done, old, new)
        return (k + 1, keep(s, s_n), keep(R, R_n), keep(t, t_n), jnp.where(done, prev_err, err), done)

    state = (jnp.int32(0), s, R, t, jnp.asarray(jnp.inf, dt), jnp.asarray(False))
    k, s, R, t, _, done = jax.lax.while_loop(cond, body, state)
    return sim3.from_rst(R, t, s), IRLSInfo(iterations=k, converged=done)


@jax.jit
def irls_chunk_pair(
    prev: ChunkFrames,
    cur: ChunkFrames,
    K_ref: Float[Array, "3 3"],
    depth_threshold: Float[Array, ""],
    conf_ratio: Float[Array, ""],
) -> tuple[Float[Array, 8], IRLSInfo, Int[Array, ""]]:
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

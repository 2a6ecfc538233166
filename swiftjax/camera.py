"""Pinhole camera helpers: unprojection, VGGT extrinsics, depth normalisation (eq. 1).

Conventions: OpenCV axes (x right, y down, z forward); intrinsics ``K`` are
``[..., 3, 3]``; VGGT's extrinsic is the world-to-camera ``[R | t]`` ``[..., 3, 4]`` in the
chunk's own frame.  Pixel ``(u, v)`` = (column, row) sits at *integer* coordinates, as in the
authors' code: a depth map ``D [H, W]`` unprojects to::

    z = D[v, u],   y = (v - cy) z / fy,   x = (u - cx - k_s (v - cy) / fy) z / fx

(``k_s = K[0, 1]`` is the skew, zero for VGGT; with it the ray is exactly ``K^-1 (u, v, 1)``).

All functions are pure, broadcast over leading batch axes and are safe under ``jax.jit`` /
``jax.vmap``; a jitted caller recompiles only when shapes or dtypes change.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float, Real

from swiftjax import sim3, so3

__all__ = [
    "pixel_rays",
    "unproject",
    "invert_extrinsic",
    "camera_to_world",
    "world_to_camera",
    "extrinsic_to_sim3",
    "sim3_to_extrinsic",
    "world_cameras",
    "focal_ratio",
    "normalize_depth",
]


def pixel_rays(K: Real[ArrayLike, "*batch 3 3"], height: int, width: int) -> Float[Array, "*batch {height} {width} 3"]:
    """Rays ``K^-1 (u, v, 1)`` at integer pixel coordinates: ``[..., 3, 3] -> [..., H, W, 3]``.

    The third component is exactly 1, so ``depth[..., None] * rays`` are camera-frame points.
    """
    K = jnp.asarray(K)
    dtype = K.dtype if jnp.issubdtype(K.dtype, jnp.floating) else jnp.float32
    K = K.astype(dtype)
    u = jnp.arange(width, dtype=dtype)
    v = jnp.arange(height, dtype=dtype)
    fx, fy = K[..., 0, 0], K[..., 1, 1]
    cx, cy, skew = K[..., 0, 2], K[..., 1, 2], K[..., 0, 1]
    e = (Ellipsis, None, None)  # broadcast per-camera scalars over [H, W]
    yr = (v[:, None] - cy[e]) / fy[e]  # [..., H, 1]
    xr = (u[None, :] - cx[e] - skew[e] * yr) / fx[e]  # [..., H, W]
    yr = jnp.broadcast_to(yr, xr.shape)
    return jnp.stack([xr, yr, jnp.ones_like(xr)], axis=-1)


def _as_sim3(T: Array) -> Array:
    """A camera-to-world transform given as Sim(3) ``[..., 8]`` or matrix ``[..., 3|4, 4]``."""
    if T.shape[-1] == 8:
        return T
    if T.ndim >= 2 and T.shape[-1] == 4 and T.shape[-2] in (3, 4):
        return sim3.from_matrix(T)
    raise ValueError(
        f"cam_to_world must be a Sim(3) [..., 8] or a [..., 3, 4] / [..., 4, 4] matrix, got shape {T.shape}"
    )


@jax.jit
def unproject(
    depth: Real[ArrayLike, "*d H W"],
    K: Real[ArrayLike, "*k 3 3"],
    cam_to_world: Real[ArrayLike, ...] | None = None,  # [..., 8] or [..., 3|4, 4]: checked below
) -> Float[Array, "... H W 3"]:
    """Depth maps to 3D points.

    Args:
        depth: ``[..., H, W]`` depth along the optical axis.
        K: ``[..., 3, 3]`` intrinsics (batch axes broadcast against ``depth``'s).
        cam_to_world: optional camera-to-world transform, either a Sim(3) ``[..., 8]`` or a
            ``[..., 4, 4]`` / ``[..., 3, 4]`` similarity matrix ``[[sR, t], ...]`` (for VGGT's
            world-to-camera extrinsics pass :func:`camera_to_world` of them).

    Returns:
        ``[..., H, W, 3]`` points, in the camera frame or (with ``cam_to_world``) in the world.
        Non-finite depths give non-finite points at those pixels (masks are the caller's job).
    """
    depth = jnp.asarray(depth)
    K = jnp.asarray(K, dtype=depth.dtype)
    h, w = depth.shape[-2:]
    pts = depth[..., None] * pixel_rays(K, h, w)
    if cam_to_world is None:
        return pts
    S = _as_sim3(jnp.asarray(cam_to_world, dtype=depth.dtype))
    return sim3.act(S[..., None, None, :], pts)


def invert_extrinsic(extrinsic: Real[ArrayLike, "*batch 3 4"]) -> Float[Array, "*batch 3 4"]:
    """Inverse of a rigid ``[R | t]``: ``[..., 3, 4] -> [..., 3, 4]`` ``[R^T | -R^T t]``.

    Maps world-to-camera to camera-to-world and back (it is its own inverse).
    """
    E = jnp.asarray(extrinsic)
    R, t = E[..., :3, :3], E[..., :3, 3]
    Rt = jnp.swapaxes(R, -1, -2)
    return jnp.concatenate([Rt, -(Rt @ t[..., None])], axis=-1)


def camera_to_world(extrinsic: Real[ArrayLike, "*batch 3 4"]) -> Float[Array, "*batch 3 4"]:
    """VGGT world-to-camera ``[..., 3, 4]`` -> camera-to-world ``[..., 3, 4]`` (pose matrix)."""
    return invert_extrinsic(extrinsic)


def world_to_camera(cam_to_world: Real[ArrayLike, "*batch 3 4"]) -> Float[Array, "*batch 3 4"]:
    """Camera-to-world ``[..., 3, 4]`` -> VGGT world-to-camera extrinsic ``[..., 3, 4]``."""
    return invert_extrinsic(cam_to_world)


def extrinsic_to_sim3(extrinsic: Real[ArrayLike, "*batch 3 4"]) -> Float[Array, "*batch 8"]:
    """VGGT world-to-camera ``[..., 3, 4]`` -> camera-to-world Sim(3) ``[..., 8]`` with ``s = 1``.

    ``R`` is converted with Shepperd's method (:func:`swiftjax.so3.from_matrix`); a slightly
    non-orthonormal ``R`` (float32 network output) gives its nearest-rotation quaternion up
    to first order.
    """
    E = jnp.asarray(extrinsic)
    R, t = E[..., :3, :3], E[..., :3, 3]
    q_c2w = so3.inverse(so3.from_matrix(R))
    q_c2w = q_c2w / jnp.linalg.norm(q_c2w, axis=-1, keepdims=True)
    c = -so3.act(q_c2w, t)  # camera centre -R^T t
    return sim3._pack(c, q_c2w, jnp.ones(E.shape[:-2], E.dtype))


def sim3_to_extrinsic(cam_to_world: Real[ArrayLike, "*batch 8"]) -> Float[Array, "*batch 3 4"]:
    """Camera-to-world Sim(3) ``[..., 8]`` -> world-to-camera ``[R^T | -R^T c]`` ``[..., 3, 4]``.

    The scale is dropped on purpose: a camera mapped by a chunk-to-world Sim(3) keeps its
    centre ``c`` and orientation ``R``; the scale only changes the units of its depths.
    """
    S = jnp.asarray(cam_to_world)
    R = so3.as_matrix(sim3.quaternion(S))
    c2w = jnp.concatenate([R, sim3.translation(S)[..., :, None]], axis=-1)
    return invert_extrinsic(c2w)


@jax.jit
def world_cameras(
    chunk_pose: Real[ArrayLike, "*batch 8"],
    extrinsic: Real[ArrayLike, "*batch 3 4"],
) -> Float[Array, "*batch 4 4"]:
    """Camera-to-world ``[..., 4, 4]`` with orthonormal rotation: a chunk-to-world ``S_t``
    composed with each camera of the chunk.

    ``chunk_pose`` is ``[8]`` or ``[S, 8]`` (each frame's chunk-to-world pose), ``extrinsic``
    ``[S, 3, 4]`` (world-to-camera in the chunk's frame).  ``S_t`` scales the chunk; the
    camera's orientation is ``R_t R_c`` and its centre ``S_t(c)``.  Recompiles per ``S``, pose
    rank and dtype.
    """
    c2w = camera_to_world(extrinsic)
    R, _, _ = sim3.to_rst(chunk_pose)
    rot = R @ c2w[..., :3, :3]
    centre = sim3.act(chunk_pose, c2w[..., :3, 3])
    top = jnp.concatenate([rot, centre[..., None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0, 0, 0, 1], rot.dtype), (*rot.shape[:-2], 1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def focal_ratio(K_src: Real[ArrayLike, "*s 3 3"], K_ref: Real[ArrayLike, "*r 3 3"]) -> Float[Array, ...]:
    """``½ (fx_ref / fx_src + fy_ref / fy_src)``: ``[..., 3, 3], [..., 3, 3] -> [...]`` (eq. 1)."""
    K_src, K_ref = jnp.asarray(K_src), jnp.asarray(K_ref)
    return 0.5 * (K_ref[..., 0, 0] / K_src[..., 0, 0] + K_ref[..., 1, 1] / K_src[..., 1, 1])


@jax.jit
def normalize_depth(
    depth: Real[ArrayLike, "*d H W"], K_src: Real[ArrayLike, "*s 3 3"], K_ref: Real[ArrayLike, "*r 3 3"]
) -> Float[Array, "... H W"]:
    """Depth normalised to the reference intrinsics (paper eq. 1).

    ``D_reg = ½ (fx_ref / fx_src + fy_ref / fy_src) · D``: a depth map predicted with focal
    ``f_src`` re-expressed as if seen with ``f_ref``, so that unprojecting ``D_reg`` with
    ``K_ref`` gives consistent geometry across frames.

    Args:
        depth: ``[..., H, W]``.
        K_src: ``[..., 3, 3]`` the frame's own intrinsics.
        K_ref: ``[3, 3]`` or ``[..., 3, 3]`` reference intrinsics (broadcast).

    Returns:
        ``[..., H, W]``.
    """
    depth = jnp.asarray(depth)
    r = focal_ratio(jnp.asarray(K_src, depth.dtype), jnp.asarray(K_ref, depth.dtype))
    return r[..., None, None] * depth

"""Co-visibility of two frame sets, from the synthetic world's true depth and poses.

For frame sets ``A`` and ``B`` (true depth maps ``z [S, H, W]`` in metres, ``inf`` on sky, true
camera-to-world poses ``T = [R | c]``, intrinsics ``K``)::

    X_A = { R_a z_a(u) K^-1 (u, 1) + c_a :  a in A, u on the pixel grid of step ``stride``,
                                            z_a(u) finite }                  (A's true surface)

    seen_B(x) = OR_{b in B} [ y = R_b^T (x - c_b),  y_z > 0,  pix = round(K y / y_z) inside
                              the image,  |y_z - z_b(pix)| <= rel_tol · y_z ]

    covis(A -> B) = |{x in X_A : seen_B(x)}| / |X_A|        (0 when X_A is empty)

A point counts as seen only when ``B``'s own depth at its pixel agrees with its depth: the
surface is visible, not hidden behind another one (and not beyond ``B``'s draw distance, where
``B`` sees sky).  ``rel_tol`` is loose (default 10 %) because the nearest-pixel lookup reads the
neighbour of an oblique surface (the road near the horizon); occluders differ by far more.
The measure is directional (a camera looking down the road sees, from afar, the surfaces of
frames 40 m ahead, which do not see it); :func:`covisibility_mutual` is the smaller of both
directions, ``min(covis(A -> B), covis(B -> A))``: each set must see the other's surfaces.

:func:`covisibility` is pure and jit-compiled with fixed shapes (the ``B`` frames are scanned
one at a time, memory ``O(|A| H W / stride^2)``); it recompiles per ``(S_A, S_B, H, W)``,
``stride`` and dtype.  Poses are float32 inside: centre them near the origin first (the
oracle subtracts the first camera's centre in float64), kilometre coordinates would cost
millimetres.  :meth:`swiftjax.synthetic.oracle.VGGTOracle.covisibility` is the host-level
call on frame indices.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

__all__ = ["surface_points", "covisibility", "covisibility_mutual"]


def surface_points(depth: jax.Array, cam_to_world: jax.Array, K: jax.Array, stride: int) -> tuple[jax.Array, jax.Array]:
    """World points of the pixel grid ``u = (stride k, stride l)`` of every frame.

    Args:
        depth: ``[S, H, W]`` z-depth in metres (non-finite: no surface).
        cam_to_world: ``[S, 4, 4]`` (or ``[S, 3, 4]``).
        K: ``[3, 3]`` intrinsics (pixel centres at integer coordinates).
        stride: static pixel step.

    Returns:
        ``(points [S * h * w, 3], valid [S * h * w] bool)`` with ``h = ceil(H / stride)``.
    """
    d = depth[:, ::stride, ::stride]
    S, h, w = d.shape
    v, u = jnp.meshgrid(jnp.arange(h, dtype=d.dtype) * stride, jnp.arange(w, dtype=d.dtype) * stride, indexing="ij")
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    valid = jnp.isfinite(d)
    z = jnp.where(valid, d, 0.0)
    cam = jnp.stack([x * z, y * z, z], -1)  # [S, h, w, 3]
    R, c = cam_to_world[:, :3, :3], cam_to_world[:, :3, 3]
    pts = jnp.einsum("sij,shwj->shwi", R, cam) + c[:, None, None, :]
    return pts.reshape(-1, 3), valid.reshape(-1)


def _seen(
    points: jax.Array, depth_b: jax.Array, cam_to_world_b: jax.Array, K: jax.Array, rel_tol: jax.Array
) -> jax.Array:
    """``seen_B(x)`` of the module docstring for ``points [P, 3]``: ``[P]`` bool."""
    H, W = depth_b.shape[1:]

    def one(seen, frame):
        z_b, T = frame
        y = (points - T[:3, 3]) @ T[:3, :3]  # R^T (x - c), row form
        yz = y[:, 2]
        front = yz > 1e-6
        yz_safe = jnp.where(front, yz, 1.0)
        u = K[0, 0] * y[:, 0] / yz_safe + K[0, 1] * y[:, 1] / yz_safe + K[0, 2]
        v = K[1, 1] * y[:, 1] / yz_safe + K[1, 2]
        ui, vi = jnp.round(u), jnp.round(v)
        inside = front & (ui >= 0) & (ui <= W - 1) & (vi >= 0) & (vi <= H - 1)
        ui = jnp.clip(ui, 0, W - 1).astype(jnp.int32)
        vi = jnp.clip(vi, 0, H - 1).astype(jnp.int32)
        zb = z_b[vi, ui]
        agree = jnp.abs(yz - zb) <= rel_tol * yz  # false on sky (zb = inf)
        return seen | (inside & agree), None

    seen, _ = jax.lax.scan(one, jnp.zeros(points.shape[0], bool), (depth_b, cam_to_world_b))
    return seen


@functools.partial(jax.jit, static_argnames=("stride",))
def covisibility(
    depth_a: jax.Array,
    cam_to_world_a: jax.Array,
    depth_b: jax.Array,
    cam_to_world_b: jax.Array,
    K: jax.Array,
    stride: int = 8,
    rel_tol: float | jax.Array = 0.1,
) -> jax.Array:
    """``covis(A -> B)`` of the module docstring: the fraction of ``A``'s true surface points
    (pixel step ``stride``) that some frame of ``B`` sees at a consistent depth.

    Args:
        depth_a, depth_b: ``[S_A, H, W]``, ``[S_B, H, W]`` true z-depth (metres, ``inf`` sky).
        cam_to_world_a, cam_to_world_b: ``[S_A, 4, 4]``, ``[S_B, 4, 4]`` true poses (one frame,
            centred near the origin: float32).
        K: ``[3, 3]`` true intrinsics of both sets.
        stride: static pixel step of ``A``'s sample grid (``B`` is looked up at every pixel).
        rel_tol: relative depth agreement (traced).

    Returns:
        float32 scalar in ``[0, 1]``.
    """
    f = jnp.float32
    pts, valid = surface_points(jnp.asarray(depth_a, f), jnp.asarray(cam_to_world_a, f), jnp.asarray(K, f), stride)
    seen = _seen(
        pts, jnp.asarray(depth_b, f), jnp.asarray(cam_to_world_b, f), jnp.asarray(K, f), jnp.asarray(rel_tol, f)
    )
    n = jnp.sum(valid)
    return jnp.sum(seen & valid) / jnp.maximum(n, 1).astype(f)


@functools.partial(jax.jit, static_argnames=("stride",))
def covisibility_mutual(
    depth_a, cam_to_world_a, depth_b, cam_to_world_b, K, stride: int = 8, rel_tol: float | jax.Array = 0.1
) -> jax.Array:
    """``min(covis(A -> B), covis(B -> A))`` (arguments as :func:`covisibility`)."""
    ab = covisibility(depth_a, cam_to_world_a, depth_b, cam_to_world_b, K, stride, rel_tol)
    ba = covisibility(depth_b, cam_to_world_b, depth_a, cam_to_world_a, K, stride, rel_tol)
    return jnp.minimum(ab, ba)

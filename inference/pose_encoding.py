"""VGGT's ``absT_quaR_FoV`` pose encoding <-> extrinsics and intrinsics.

Encoding (9 numbers per frame): ``[0:3]`` translation ``T``, ``[3:7]`` quaternion in XYZW
order (scalar last), ``[7]`` vertical field of view ``fov_h``, ``[8]`` horizontal ``fov_w``
(radians).  Extrinsic ``[R | T]`` is world-to-camera in OpenCV axes (``X_cam = R X_world + T``);
``fx = (W/2) / tan(fov_w/2)``, ``fy = (H/2) / tan(fov_h/2)``, principal point ``(W/2, H/2)``.

The functions accept NumPy arrays or torch tensors and return the same kind (torch is only
touched when it is given a tensor).
"""

from __future__ import annotations

from typing import Any, TypeVar

import numpy as np

__all__ = [
    "pose_encoding_to_extrinsics_intrinsics",
    "extrinsics_intrinsics_to_pose_encoding",
    "quat_to_mat",
    "mat_to_quat",
]

ArrayT = TypeVar("ArrayT")


def _xp(x: Any) -> Any:
    if type(x).__module__.startswith("torch"):
        import torch

        return torch
    return np


def _stack(xp: Any, items: list[Any], axis: int) -> Any:
    return xp.stack(items, axis) if xp is np else xp.stack(items, dim=axis)


def _cat(xp: Any, items: list[Any], axis: int) -> Any:
    return xp.concatenate(items, axis) if xp is np else xp.cat(items, dim=axis)


def quat_to_mat(quat: ArrayT) -> ArrayT:
    """XYZW quaternions ``[..., 4]`` (any norm) -> rotation matrices ``[..., 3, 3]``."""
    xp = _xp(quat)
    i, j, k, r = (quat[..., n] for n in range(4))  # type: ignore[index]
    two_s = 2.0 / (quat * quat).sum(-1)  # type: ignore[operator]
    o = _stack(
        xp,
        [
            1 - two_s * (j * j + k * k),
            two_s * (i * j - k * r),
            two_s * (i * k + j * r),
            two_s * (i * j + k * r),
            1 - two_s * (i * i + k * k),
            two_s * (j * k - i * r),
            two_s * (i * k - j * r),
            two_s * (j * k + i * r),
            1 - two_s * (i * i + j * j),
        ],
        -1,
    )
    return o.reshape(tuple(quat.shape[:-1]) + (3, 3))  # type: ignore[attr-defined]


def mat_to_quat(mat: Any) -> Any:
    """Rotation matrices ``[..., 3, 3]`` -> unit XYZW quaternions ``[..., 4]`` with ``w >= 0``.

    NumPy only (Shepperd's method, choosing the best-conditioned pivot per matrix).
    """
    m = np.asarray(mat, dtype=np.float64)
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = np.stack(
        [
            np.stack(
                [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1], 1 + tr], -1
            ),
            np.stack(
                [
                    1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 2, 1] - m[..., 1, 2],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 0, 1] + m[..., 1, 0],
                    1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                    m[..., 1, 2] + m[..., 2, 1],
                    m[..., 0, 2] - m[..., 2, 0],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
                    m[..., 1, 0] - m[..., 0, 1],
                ],
                -1,
            ),
        ],
        -2,
    )  # [..., 4, 4]; candidate c has its largest component at a known place
    pivots = np.stack(
        [
            1 + tr,
            1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
        ],
        -1,
    )
    best = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def pose_encoding_to_extrinsics_intrinsics(pose_enc: ArrayT, image_hw: tuple[int, int]) -> tuple[ArrayT, ArrayT]:
    """Decodes VGGT pose encodings.

    Args:
        pose_enc: ``[..., 9]`` encodings (NumPy or torch).
        image_hw: ``(H, W)`` of the images the encodings refer to.

    Returns:
        ``extrinsic [..., 3, 4]`` world-to-camera ``[R | T]`` and ``intrinsic [..., 3, 3]``.
    """
    xp = _xp(pose_enc)
    height, width = float(image_hw[0]), float(image_hw[1])
    t = pose_enc[..., :3]  # type: ignore[index]
    rot = quat_to_mat(pose_enc[..., 3:7])  # type: ignore[index]
    extrinsic = _cat(xp, [rot, t[..., None]], -1)
    fy = (height / 2.0) / xp.tan(pose_enc[..., 7] / 2.0)  # type: ignore[index]
    fx = (width / 2.0) / xp.tan(pose_enc[..., 8] / 2.0)  # type: ignore[index]
    zero = xp.zeros_like(fx)
    one = zero + 1
    intrinsic = _stack(
        xp,
        [fx, zero, zero + width / 2.0, zero, fy, zero + height / 2.0, zero, zero, one],
        -1,
    ).reshape(tuple(fx.shape) + (3, 3))
    return extrinsic, intrinsic


def extrinsics_intrinsics_to_pose_encoding(extrinsic: Any, intrinsic: Any, image_hw: tuple[int, int]) -> Any:
    """Inverse of :func:`pose_encoding_to_extrinsics_intrinsics` (NumPy): ``[..., 9]`` float."""
    e = np.asarray(extrinsic, dtype=np.float64)
    k = np.asarray(intrinsic, dtype=np.float64)
    height, width = image_hw
    fov_h = 2 * np.arctan((height / 2.0) / k[..., 1, 1])
    fov_w = 2 * np.arctan((width / 2.0) / k[..., 0, 0])
    return np.concatenate([e[..., :3, 3], mat_to_quat(e[..., :3, :3]), fov_h[..., None], fov_w[..., None]], -1)

"""Depth Anything 3's cameras: the 9-number pose encoding, the camera decoder (tokens -> pose)
and the camera encoder (known poses -> camera tokens, "pose conditioning").

Pose encoding ``[T (3), q (4, xyzw, scalar last), fov_h, fov_w]`` of the CAMERA-TO-WORLD
transform (``T`` = camera centre in the world frame).  Decoding: ``R = quat_to_mat(q)`` (any
norm), ``c2w = [R | T]``, ``w2c = [Rᵀ | -Rᵀ T]``, ``fy = (H/2) / max(tan(fov_h/2), 1e-6)``,
``fx = (W/2) / max(tan(fov_w/2), 1e-6)``, principal point ``(W/2, H/2)``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..layers import Block, Mlp
from ..pose_encoding import quat_to_mat

__all__ = [
    "CameraDec",
    "CameraEnc",
    "affine_inverse",
    "mat_to_quat_torch",
    "encode_pose",
    "decode_pose",
    "normalize_extrinsics",
]

POSE_DIM = 9


def affine_inverse(a: Tensor) -> Tensor:
    """Inverse of rigid ``[..., 3, 4]`` or ``[..., 4, 4]`` transforms (same shape): ``[Rᵀ | -Rᵀ t]``."""
    r, t = a[..., :3, :3], a[..., :3, 3:]
    rt = r.transpose(-1, -2)
    return torch.cat([torch.cat([rt, -rt @ t], dim=-1), a[..., 3:, :]], dim=-2)


def mat_to_quat_torch(m: Tensor) -> Tensor:
    """Rotation matrices ``[..., 3, 3]`` -> xyzw quaternions ``[..., 4]`` with ``w >= 0``.

    The official (PyTorch3D) rule: of the four candidates ``q_k / (2 max(|q_k|, 0.1))`` take the
    one with the largest ``|q_k| = sqrt(max(0, 1 ± m00 ± m11 ± m22))``.
    """
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    sq = torch.stack([1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], -1)
    q_abs = torch.where(sq > 0, torch.sqrt(sq.clamp_min(0)), torch.zeros_like(sq))
    cands = torch.stack(
        [
            torch.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], -1),
        ],
        -2,
    )  # [..., 4 candidates, wxyz]
    cands = cands / (2.0 * q_abs[..., None].clamp_min(0.1))
    best = q_abs.argmax(dim=-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    q = torch.cat([q[..., 1:], q[..., :1]], dim=-1)  # wxyz -> xyzw
    return torch.where(q[..., 3:4] < 0, -q, q)


def encode_pose(c2w: Tensor, intrinsics: Tensor, image_hw: tuple[int, int]) -> Tensor:
    """``[B, S, 9]`` from camera-to-world ``[B, S, 3|4, 4]`` and pixel intrinsics ``[B, S, 3, 3]``
    (``cx, cy`` are not encoded)."""
    height, width = image_hw
    quat = mat_to_quat_torch(c2w[..., :3, :3])
    fov_h = 2 * torch.atan((height / 2) / intrinsics[..., 1, 1])
    fov_w = 2 * torch.atan((width / 2) / intrinsics[..., 0, 0])
    return torch.cat([c2w[..., :3, 3], quat, fov_h[..., None], fov_w[..., None]], dim=-1).float()


def decode_pose(pose_enc: Tensor, image_hw: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """``pose_enc [B, S, 9]`` -> world-to-camera ``extrinsics [B, S, 3, 4]`` and ``intrinsics [B, S, 3, 3]``."""
    height, width = image_hw
    c2w = torch.cat([quat_to_mat(pose_enc[..., 3:7]), pose_enc[..., :3, None]], dim=-1)
    fy = (height / 2.0) / torch.clamp(torch.tan(pose_enc[..., 7] / 2.0), min=1e-6)
    fx = (width / 2.0) / torch.clamp(torch.tan(pose_enc[..., 8] / 2.0), min=1e-6)
    zero = torch.zeros_like(fx)
    k = torch.stack([fx, zero, zero + width / 2, zero, fy, zero + height / 2, zero, zero, zero + 1.0], -1)
    return affine_inverse(c2w), k.reshape(*fx.shape, 3, 3)


class CameraDec(nn.Module):
    """Camera token ``[B, S, 2C]`` -> pose encoding ``[B, S, 9]``: Linear-ReLU-Linear-ReLU, then
    ``fc_t`` (3), ``fc_qvec`` (4) and ``fc_fov`` (2, ReLU)."""

    def __init__(self, dim_in: int) -> None:
        super().__init__()
        self.backbone = nn.Sequential(nn.Linear(dim_in, dim_in), nn.ReLU(), nn.Linear(dim_in, dim_in), nn.ReLU())
        self.fc_t = nn.Linear(dim_in, 3)
        self.fc_qvec = nn.Linear(dim_in, 4)
        self.fc_fov = nn.Sequential(nn.Linear(dim_in, 2), nn.ReLU())

    def forward(self, feat: Tensor) -> Tensor:
        f = self.backbone(feat).float()
        return torch.cat([self.fc_t(f), self.fc_qvec(f), self.fc_fov(f)], dim=-1)


class CameraEnc(nn.Module):
    """Known cameras -> camera tokens ``[B, S, C]``: pose encoding of ``c2w = inverse(w2c)`` ->
    ``Mlp(9 -> C/2 -> C)`` -> LayerNorm -> 4 transformer blocks across the views -> LayerNorm."""

    def __init__(self, dim_out: int, num_heads: int = 16, trunk_depth: int = 4, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        self.trunk = nn.Sequential(
            *(Block(dim_out, num_heads, mlp_ratio, init_values=0.01) for _ in range(trunk_depth))
        )
        self.token_norm = nn.LayerNorm(dim_out)
        self.trunk_norm = nn.LayerNorm(dim_out)
        self.pose_branch = Mlp(POSE_DIM, dim_out // 2, dim_out)

    def pose_encoding(self, extrinsics: Tensor, intrinsics: Tensor, image_hw: tuple[int, int]) -> Tensor:
        """``[B, S, 9]`` from world-to-camera ``extrinsics [B, S, 4, 4]`` and ``intrinsics``."""
        return encode_pose(affine_inverse(extrinsics), intrinsics, image_hw)

    def forward(self, extrinsics: Tensor, intrinsics: Tensor, image_hw: tuple[int, int]) -> Tensor:
        tokens = self.token_norm(self.pose_branch(self.pose_encoding(extrinsics, intrinsics, image_hw)))
        return self.trunk_norm(self.trunk(tokens))


def normalize_extrinsics(w2c: Tensor) -> Tensor:
    """The official API's normalisation of known poses before the camera encoder.

    ``w2c [B, S, 4, 4]`` -> ``w2c @ inverse(w2c[:, 0])`` (view 0 becomes the identity), then all
    translations divided by the median camera-centre distance (lower median over every view of
    the batch, ``torch.median``; clamped to >= 0.1).
    """
    out = w2c @ affine_inverse(w2c[:, :1])
    dist = affine_inverse(out)[..., :3, 3].norm(dim=-1)
    median = torch.clamp(torch.median(dist), min=0.1)
    return torch.cat([torch.cat([out[..., :3, :3], out[..., :3, 3:] / median], dim=-1), out[..., 3:, :]], dim=-2)

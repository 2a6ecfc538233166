"""π³'s output heads: per-pixel linear heads (π³), MoGe-style ConvHeads (π³X), the camera head.

Module and parameter names follow the official code (``proj``, ``res_conv.N.res_conv1``,
``more_mlps``, ``fc_t``, ``fc_rot``, ``upsample_blocks``, ``output_block``), so checkpoints
load by name.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..device import without_autocast

__all__ = ["LinearPts3d", "CameraHead", "ConvHead", "svd_orthogonalize", "pose_from_raw", "view_plane_uv"]


class LinearPts3d(nn.Module):
    """One linear map per patch token to ``patch x patch`` pixels of ``out`` channels.

    ``[N, P, C]`` tokens -> ``[N, H, W, out]`` with ``pixel_shuffle`` placing channel
    ``o * p^2 + dy * p + dx`` of patch ``(r, c)`` at pixel ``(r p + dy, c p + dx)``.
    """

    def __init__(self, patch_size: int, width: int, out: int) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Linear(width, out * patch_size**2)

    def forward(self, tokens: Tensor, patches_hw: tuple[int, int]) -> Tensor:
        n = tokens.shape[0]
        feat = self.proj(tokens).transpose(-1, -2).reshape(n, -1, *patches_hw)
        return F.pixel_shuffle(feat, self.patch_size).permute(0, 2, 3, 1)


class _ResLinearBlock(nn.Module):
    """``x + relu(W3 relu(W2 relu(W1 x)))`` (official ``ResConvBlock``, 1x1 convs as Linear)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.res_conv1 = nn.Linear(dim, dim)
        self.res_conv2 = nn.Linear(dim, dim)
        self.res_conv3 = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.res_conv3(F.relu(self.res_conv2(F.relu(self.res_conv1(x))))))
        return x + y


class CameraHead(nn.Module):
    """Patch tokens of one view -> the raw pose: rotation 9-vector and translation 3-vector.

    Two residual MLP blocks per token, mean over the view's patch tokens, two ReLU layers,
    then ``fc_rot`` (9) and ``fc_t`` (3).  :func:`pose_from_raw` turns them into a 4x4
    camera-to-world matrix; it is kept out of the module so that an ONNX graph (which has no
    SVD) can stop at the raw outputs.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.res_conv = nn.ModuleList(_ResLinearBlock(dim) for _ in range(2))
        self.more_mlps = nn.Sequential(nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU())
        self.fc_t = nn.Linear(dim, 3)
        self.fc_rot = nn.Linear(dim, 9)

    def forward(self, tokens: Tensor) -> tuple[Tensor, Tensor]:
        """``tokens [N, P, C]`` -> ``(rot9 [N, 9], trans [N, 3])``, float32."""
        for blk in self.res_conv:
            tokens = blk(tokens)
        feat = self.more_mlps(tokens.mean(dim=1))
        return self.fc_rot(feat.float()), self.fc_t(feat.float())


def svd_orthogonalize(m: Tensor) -> Tensor:
    """The rotation nearest (Frobenius) to a 3x3 matrix whose ROWS are first normalised.

    ``m [..., 9]`` (row-major) -> ``R [..., 3, 3]``: with ``N`` the row-normalised matrix and
    ``N = U S V^T``, ``R = U diag(1, 1, det(U V^T)) V^T`` (reflections corrected).  Computed
    in float32 or wider as given (half types are widened to float32), outside autocast.
    """
    m = m if m.dtype in (torch.float32, torch.float64) else m.float()
    with without_autocast(m.device):
        n = F.normalize(m.reshape(*m.shape[:-1], 3, 3), p=2, dim=-1)
        u, _, vh = torch.linalg.svd(n)
        det = torch.det(u @ vh)
        fix = torch.ones_like(u[..., 0, :])
        fix = torch.cat([fix[..., :2], det[..., None]], dim=-1)
        return (u * fix[..., None, :]) @ vh


def pose_from_raw(rot9: Tensor, trans: Tensor) -> Tensor:
    """``rot9 [..., 9], trans [..., 3]`` -> camera-to-world ``[..., 4, 4]`` (OpenCV axes)."""
    rot = svd_orthogonalize(rot9)
    top = torch.cat([rot, trans[..., None]], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def view_plane_uv(height: int, width: int, aspect: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    """MoGe's normalised view-plane UV, ``[2, height, width]`` (u then v).

    Pixel centres span ``±span (n - 1) / n`` with ``span_x = a / sqrt(1 + a^2)``,
    ``span_y = 1 / sqrt(1 + a^2)``, ``a`` = the IMAGE aspect ratio ``W / H`` (not the grid's).
    """
    span_x = aspect / (1 + aspect**2) ** 0.5
    span_y = 1 / (1 + aspect**2) ** 0.5
    u = torch.linspace(-span_x * (width - 1) / width, span_x * (width - 1) / width, width, dtype=dtype, device=device)
    v = torch.linspace(
        -span_y * (height - 1) / height, span_y * (height - 1) / height, height, dtype=dtype, device=device
    )
    return torch.stack([u[None, :].expand(height, width), v[:, None].expand(height, width)], dim=0)


class _ResidualConvBlock(nn.Module):
    """``skip(x) + conv(relu(gn(conv(relu(gn(x))))))``, 3x3 convs with replicate padding."""

    def __init__(self, channels: int, hidden: int) -> None:
        super().__init__()
        self.layers = nn.Sequential(
            nn.GroupNorm(1, channels),
            nn.ReLU(),
            nn.Conv2d(channels, hidden, 3, padding=1, padding_mode="replicate"),
            nn.GroupNorm(max(hidden // 32, 1), hidden),
            nn.ReLU(),
            nn.Conv2d(hidden, channels, 3, padding=1, padding_mode="replicate"),
        )
        self.skip_connection = nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        return self.layers(x) + self.skip_connection(x)


class ConvHead(nn.Module):
    """π³X's MoGe-style dense head: tokens -> three x2 upsampling stages -> bilinear to the
    image size -> one small conv stack per output.

    Before each stage and before the outputs, two UV channels (:func:`view_plane_uv`) are
    concatenated.  Upsampler: ``ConvTranspose2d(k=2, s=2)`` then a 3x3 conv; each stage is
    followed by ``num_res_blocks`` residual blocks of hidden width ``2 x``.
    """

    def __init__(
        self,
        dim_in: int,
        dim_out: Sequence[int],
        upsample: Sequence[int],
        last_channels: int,
        num_res_blocks: int = 2,
        patch_size: int = 14,
    ) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.projects = nn.Identity()
        ins = [dim_in, *upsample[:-1]]
        self.upsample_blocks = nn.ModuleList(
            nn.Sequential(
                nn.Sequential(
                    nn.ConvTranspose2d(c_in + 2, c_out, kernel_size=2, stride=2),
                    nn.Conv2d(c_out, c_out, 3, padding=1, padding_mode="replicate"),
                ),
                *(_ResidualConvBlock(c_out, 2 * c_out) for _ in range(num_res_blocks)),
            )
            for c_in, c_out in zip(ins, upsample)
        )
        self.output_block = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(upsample[-1] + 2, last_channels, 3, padding=1, padding_mode="replicate"),
                nn.ReLU(),
                nn.Conv2d(last_channels, d, 1),
            )
            for d in dim_out
        )

    def _with_uv(self, x: Tensor, aspect: float) -> Tensor:
        uv = view_plane_uv(x.shape[-2], x.shape[-1], aspect, x.dtype, x.device)
        return torch.cat([x, uv[None].expand_as(x[:, :2])], dim=1)  # expand_as: dynamic batch in ONNX

    def forward(self, tokens: Tensor, patches_hw: tuple[int, int]) -> list[Tensor]:
        """``tokens [N, P, C]`` -> one ``[N, d, H, W]`` map per output (``H = 14 h``)."""
        ph, pw = patches_hw
        img_h, img_w = ph * self.patch_size, pw * self.patch_size
        aspect = img_w / img_h
        x = self.projects(tokens).permute(0, 2, 1).unflatten(2, (ph, pw))
        for block in self.upsample_blocks:
            x = block(self._with_uv(x, aspect))
        x = F.interpolate(x, (img_h, img_w), mode="bilinear", align_corners=False)
        x = self._with_uv(x, aspect)
        return [blk(x) for blk in self.output_block]

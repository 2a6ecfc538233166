"""VGGT's DPT depth head: four aggregator outputs -> dense depth and confidence.

Faithful to the official head including one quirk: its ``ResidualConvUnit`` applies an
in-place ReLU to its input, so the skip connection adds ``relu(x)``, not ``x``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["DPTHead", "resize_layers", "uv_pos_embed"]


@functools.lru_cache(maxsize=64)
def _uv_pos_embed_np(
    height: int, width: int, aspect: float, channels: int, omega_0: float = 100.0, float32_trig: bool = False
) -> np.ndarray:
    """Float32 ``[channels, height, width]`` sin/cos embedding of a normalised UV grid (x 0.1).

    The grid spans ``±aspect/diag`` horizontally and ``±1/diag`` vertically
    (``diag = sqrt(aspect² + 1)``), pixel centres ``(k - (n-1)/2)·2·span/n``; it is built in
    float32 (``torch.linspace``), the sin/cos in float64, then cast — as the official VGGT code
    does.  ``float32_trig``: frequencies, products and sin/cos in torch float32 instead, as the
    official Depth Anything 3 code does.
    """
    diag = (aspect**2 + 1.0) ** 0.5
    span_x, span_y = aspect / diag, 1.0 / diag
    xs = torch.linspace(-span_x * (width - 1) / width, span_x * (width - 1) / width, width, dtype=torch.float32)
    ys = torch.linspace(-span_y * (height - 1) / height, span_y * (height - 1) / height, height, dtype=torch.float32)
    u = np.broadcast_to(xs.numpy().astype(np.float64)[None, :], (height, width)).reshape(-1)
    v = np.broadcast_to(ys.numpy().astype(np.float64)[:, None], (height, width)).reshape(-1)

    def sincos(dim: int, pos: np.ndarray) -> np.ndarray:
        if float32_trig:
            omega32 = torch.arange(dim // 2, dtype=torch.float32) / (dim / 2.0)
            out32 = torch.from_numpy(pos.astype(np.float32))[:, None] * (1.0 / omega_0**omega32)[None, :]
            return torch.cat([torch.sin(out32), torch.cos(out32)], dim=1).numpy()
        omega = 1.0 / omega_0 ** (np.arange(dim // 2, dtype=np.float64) / (dim / 2.0))
        out = pos[:, None] * omega[None, :]
        return np.concatenate([np.sin(out), np.cos(out)], axis=1).astype(np.float32)

    emb = np.concatenate([sincos(channels // 2, u), sincos(channels // 2, v)], axis=1)  # [h*w, C]
    emb = emb * np.float32(0.1)
    emb = emb.reshape(height, width, channels).transpose(2, 0, 1)
    return np.ascontiguousarray(emb)


def uv_pos_embed(x: Tensor, image_h: int, image_w: int, float32_trig: bool = False) -> Tensor:
    """Adds the UV position embedding to a feature map ``x [N, C, h, w]`` of an ``image_h x image_w`` image
    (``float32_trig``: see :func:`_uv_pos_embed_np`)."""
    _, c, h, w = x.shape
    emb = _uv_pos_embed_np(int(h), int(w), image_w / image_h, int(c), float32_trig=float32_trig)
    return x + torch.from_numpy(emb).to(device=x.device, dtype=x.dtype)


def _resize(x: Tensor, size: tuple[int, int]) -> Tensor:
    return F.interpolate(x, size=size, mode="bilinear", align_corners=True)


class ResidualConvUnit(nn.Module):
    """``conv2(relu(conv1(relu(x)))) + relu(x)`` (VGGT's in-place ReLU quirk), or ``+ x`` when
    ``relu_skip`` is false (Depth Anything 3, whose ReLU is not in place)."""

    def __init__(self, features: int, relu_skip: bool = True) -> None:
        super().__init__()
        self.relu_skip = relu_skip
        self.conv1 = nn.Conv2d(features, features, kernel_size=3, padding=1)
        self.conv2 = nn.Conv2d(features, features, kernel_size=3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        r = F.relu(x)
        return self.conv2(F.relu(self.conv1(r))) + (r if self.relu_skip else x)


class FeatureFusionBlock(nn.Module):
    """``out_conv(resize(RCU2(x0 + RCU1(x1))))``; without ``resConfUnit1`` when ``has_residual`` is false."""

    def __init__(self, features: int, has_residual: bool = True, relu_skip: bool = True) -> None:
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, kernel_size=1)
        self.resConfUnit1: ResidualConvUnit | None = ResidualConvUnit(features, relu_skip) if has_residual else None
        self.resConfUnit2 = ResidualConvUnit(features, relu_skip)

    def forward(self, x: Tensor, skip: Tensor | None, size: tuple[int, int]) -> Tensor:
        if self.resConfUnit1 is not None and skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        return self.out_conv(_resize(x, size))


def resize_layers(out_channels: Sequence[int]) -> nn.ModuleList:
    """The four level re-sizers of a DPT head: ×4 and ×2 transposed convolutions, identity, a
    stride-2 3×3 convolution (patch grid -> 4×, 2×, 1×, 1/2×)."""
    oc = tuple(out_channels)
    return nn.ModuleList(
        [
            nn.ConvTranspose2d(oc[0], oc[0], kernel_size=4, stride=4),
            nn.ConvTranspose2d(oc[1], oc[1], kernel_size=2, stride=2),
            nn.Identity(),
            nn.Conv2d(oc[3], oc[3], kernel_size=3, stride=2, padding=1),
        ]
    )


class _Scratch(nn.Module):
    """Container named like the official ``scratch`` module (layerN_rn, refinenetN, output convs)."""

    def __init__(
        self, in_channels: tuple[int, int, int, int], features: int, output_dim: int, relu_skip: bool = True
    ) -> None:
        super().__init__()
        self.layer1_rn = nn.Conv2d(in_channels[0], features, kernel_size=3, padding=1, bias=False)
        self.layer2_rn = nn.Conv2d(in_channels[1], features, kernel_size=3, padding=1, bias=False)
        self.layer3_rn = nn.Conv2d(in_channels[2], features, kernel_size=3, padding=1, bias=False)
        self.layer4_rn = nn.Conv2d(in_channels[3], features, kernel_size=3, padding=1, bias=False)
        self.refinenet1 = FeatureFusionBlock(features, relu_skip=relu_skip)
        self.refinenet2 = FeatureFusionBlock(features, relu_skip=relu_skip)
        self.refinenet3 = FeatureFusionBlock(features, relu_skip=relu_skip)
        self.refinenet4 = FeatureFusionBlock(features, has_residual=False, relu_skip=relu_skip)
        self.output_conv1 = nn.Conv2d(features, features // 2, kernel_size=3, padding=1)
        self.output_conv2 = nn.Sequential(
            nn.Conv2d(features // 2, 32, kernel_size=3, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, output_dim, kernel_size=1),
        )


class DPTHead(nn.Module):
    """Dense prediction head producing depth (``exp``) and confidence (``1 + exp``)."""

    def __init__(
        self,
        dim_in: int,
        patch_size: int,
        features: int,
        out_channels: tuple[int, int, int, int],
        intermediate_layer_idx: tuple[int, int, int, int],
        output_dim: int = 2,
    ) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.intermediate_layer_idx = tuple(intermediate_layer_idx)
        self.norm = nn.LayerNorm(dim_in)
        self.projects = nn.ModuleList(nn.Conv2d(dim_in, oc, kernel_size=1) for oc in out_channels)
        self.resize_layers = resize_layers(out_channels)
        self.scratch = _Scratch(out_channels, features, output_dim)

    def forward(
        self,
        tokens: Sequence[Tensor | None],
        image_hw: tuple[int, int],
        patch_start_idx: int,
        frames_chunk_size: int | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Depth and confidence.

        Args:
            tokens: the aggregator outputs, each ``[B, S, T, 2C]`` (only the entries at
                ``intermediate_layer_idx`` are used; the others may be ``None``).
            image_hw: ``(H, W)`` of the input images.
            patch_start_idx: index of the first patch token (1 + registers).
            frames_chunk_size: frames per pass (bounds memory); ``None`` = all at once.

        Returns:
            ``depth [B, S, H, W, 1]`` and ``conf [B, S, H, W]``.
        """
        s = _at(tokens, self.intermediate_layer_idx[0]).shape[1]
        if frames_chunk_size is None or frames_chunk_size >= s:
            return self._forward_frames(tokens, image_hw, patch_start_idx, 0, s)
        parts = [
            self._forward_frames(tokens, image_hw, patch_start_idx, i, min(i + frames_chunk_size, s))
            for i in range(0, s, frames_chunk_size)
        ]
        return torch.cat([d for d, _ in parts], dim=1), torch.cat([c for _, c in parts], dim=1)

    def raw_logits(self, tokens: Sequence[Tensor | None], image_hw: tuple[int, int], patch_start_idx: int) -> Tensor:
        """Pre-activation output ``[B*S, output_dim, H, W]`` (channel 0 depth, last conf)."""
        height, width = image_hw
        h, w = height // self.patch_size, width // self.patch_size
        levels = []
        for i, layer in enumerate(self.intermediate_layer_idx):
            x = _at(tokens, layer)[:, :, patch_start_idx:]
            x = self.norm(x.reshape(-1, x.shape[-2], x.shape[-1]))  # [B*S, P, 2C]
            x = x.permute(0, 2, 1).reshape(x.shape[0], x.shape[-1], h, w)
            x = uv_pos_embed(self.projects[i](x), height, width)
            levels.append(self.resize_layers[i](x))

        sc = self.scratch
        l1, l2, l3, l4 = (
            sc.layer1_rn(levels[0]),
            sc.layer2_rn(levels[1]),
            sc.layer3_rn(levels[2]),
            sc.layer4_rn(levels[3]),
        )
        out = sc.refinenet4(l4, None, size=_hw(l3))
        out = sc.refinenet3(out, l3, size=_hw(l2))
        out = sc.refinenet2(out, l2, size=_hw(l1))
        out = sc.refinenet1(out, l1, size=(2 * l1.shape[2], 2 * l1.shape[3]))
        out = sc.output_conv1(out)
        out = _resize(out, (h * self.patch_size, w * self.patch_size))
        out = uv_pos_embed(out, height, width)
        return sc.output_conv2(out)

    def _forward_frames(
        self, tokens: Sequence[Tensor | None], image_hw: tuple[int, int], patch_start_idx: int, start: int, stop: int
    ) -> tuple[Tensor, Tensor]:
        first = _at(tokens, self.intermediate_layer_idx[0])
        b = first.shape[0]
        if start != 0 or stop != first.shape[1]:
            tokens = [
                t[:, start:stop] if i in self.intermediate_layer_idx and t is not None else None
                for i, t in enumerate(tokens)
            ]
        logits = self.raw_logits(tokens, image_hw, patch_start_idx)
        depth = torch.exp(logits[:, :-1]).permute(0, 2, 3, 1)  # [B*S, H, W, 1]
        conf = 1 + torch.exp(logits[:, -1])
        return depth.reshape(b, -1, *depth.shape[1:]), conf.reshape(b, -1, *conf.shape[1:])


def _at(tokens: Sequence[Tensor | None], layer: int) -> Tensor:
    t = tokens[layer]
    if t is None:
        raise ValueError(f"the depth head needs aggregator output {layer}, which was not kept")
    return t


def _hw(x: Tensor) -> tuple[int, int]:
    return int(x.shape[2]), int(x.shape[3])

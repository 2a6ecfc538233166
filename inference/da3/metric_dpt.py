"""The DPT head of the metric / mono models (depth + sky) and the weights-only 3D-Gaussian head.

Metric/mono DPT: no token LayerNorm, no position maps (the official DPT defaults); the main
fusion chain of :class:`~inference.da3.dualdpt.DPTTrunk`, ``output_conv1`` -> bilinear to the
image -> ``depth = exp(output_conv2)`` and ``sky = relu(sky_output_conv2)`` (both 1 channel).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .dualdpt import DPTTrunk

__all__ = ["MetricDPT", "GaussianHeadWeights"]


class MetricDPT(DPTTrunk):
    """Depth (``exp``) and sky (``relu``) of DA3Metric/DA3Mono."""

    def __init__(
        self, dim_in: int, features: int, out_channels: Sequence[int], output_dim: int = 1, patch_size: int = 14
    ) -> None:
        super().__init__(dim_in, features, out_channels, output_dim, patch_size, token_norm=False, pos_embed=False)
        self.scratch.sky_output_conv2 = nn.Sequential(
            nn.Conv2d(features // 2, 32, 3, 1, 1), nn.ReLU(), nn.Conv2d(32, 1, 1, 1, 0)
        )

    def _forward_flat(self, feats: Sequence[Tensor], image_hw: tuple[int, int]) -> dict[str, Tensor]:
        sc = self.scratch
        fused = self.upsample(sc.output_conv1(self.fuse(self.main_chain(), self.pyramid(feats, image_hw))), image_hw)
        return {"depth": torch.exp(sc.output_conv2(fused)[:, 0]), "sky": F.relu(sc.sky_output_conv2(fused)[:, 0])}


class GaussianHeadWeights(DPTTrunk):
    """Parameters of DA3-Giant's 3D-Gaussian head (``gs_head``), held so that the released
    checkpoint loads strictly; this package does not predict Gaussians and never runs it."""

    def __init__(
        self, dim_in: int, features: int, out_channels: Sequence[int], output_dim: int, patch_size: int = 14
    ) -> None:
        super().__init__(dim_in, features, out_channels, output_dim, patch_size, token_norm=False, pos_embed=True)
        merger = features // 2
        self.images_merger = nn.Sequential(
            nn.Conv2d(3, merger // 4, 3, 1, 1),
            nn.GELU(),
            nn.Conv2d(merger // 4, merger // 2, 3, 1, 1),
            nn.GELU(),
            nn.Conv2d(merger // 2, merger, 3, 1, 1),
            nn.GELU(),
        )

    def forward(self, *args: object, **kwargs: object) -> Tensor:
        raise NotImplementedError("the 3D-Gaussian head is held for checkpoint loading only")

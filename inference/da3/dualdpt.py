"""Depth Anything 3's dense heads built on VGGT's DPT pieces (:mod:`inference.dpt`).

:class:`DPTTrunk` is the part all DA3 heads share: (optional LayerNorm) -> per level 1×1 conv ->
(optional UV position map) -> resize ×4, ×2, ×1, /2 -> 3×3 conv to ``features``.  The fusion
blocks are VGGT's, except that DA3's ReLU is not in place (the residual adds ``x``, not
``relu(x)``).

:class:`DualDPT` (any-view models): two independent top-down fusion chains on the same pyramid.
Main: ``output_conv1`` at 8h×8w -> bilinear (align_corners) to H×W -> position map -> 3×3 conv,
ReLU, 1×1 -> ``depth = exp(c0)``, ``depth_conf = 1 + exp(c1)``.  Aux (rays): the finest level
only -> 5 stacked 3×3 convs -> position map -> 3×3 conv, LayerNorm over channels, ReLU, 1×1 ->
``ray = c0..5`` (direction, origin), ``ray_conf = 1 + exp(c6)``, at 8h×8w.  The official head
also computes the three coarser aux levels and discards them; they are skipped here (same
result).  One LayerNorm instance sits in all four ``output_conv2_aux`` entries, as officially.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from ..dpt import FeatureFusionBlock, _resize, _Scratch, resize_layers, uv_pos_embed

__all__ = ["DPTTrunk", "DualDPT"]


class DPTTrunk(nn.Module):
    """Token maps -> the four ``features``-wide pyramid levels (official names ``norm``,
    ``projects``, ``resize_layers``, ``scratch.layerN_rn`` + the main fusion chain)."""

    def __init__(
        self,
        dim_in: int,
        features: int,
        out_channels: Sequence[int],
        output_dim: int,
        patch_size: int = 14,
        token_norm: bool = True,
        pos_embed: bool = True,
    ) -> None:
        super().__init__()
        oc = tuple(int(c) for c in out_channels)
        self.patch_size = patch_size
        self.pos_embed = pos_embed
        self.norm: nn.Module = nn.LayerNorm(dim_in) if token_norm else nn.Identity()
        self.projects = nn.ModuleList(nn.Conv2d(dim_in, c, kernel_size=1) for c in oc)
        self.resize_layers = resize_layers(oc)
        self.scratch = _Scratch(oc, features, output_dim, relu_skip=False)  # type: ignore[arg-type]

    def forward(
        self, feats: Sequence[Tensor], image_hw: tuple[int, int], frames_chunk_size: int | None = 8
    ) -> dict[str, Tensor]:
        """``feats``: 4 × ``[B, S, P, C]`` patch tokens -> the head's outputs, each ``[B, S, ...]``.

        ``frames_chunk_size`` frames go through the head at a time (bounds memory; the result
        does not depend on it); ``None``: all at once.
        """
        b, s = feats[0].shape[:2]
        flat = [f.reshape(b * s, *f.shape[2:]) for f in feats]
        n = b * s
        step = n if frames_chunk_size is None else max(1, frames_chunk_size)
        parts = [self._forward_flat([f[i : i + step] for f in flat], image_hw) for i in range(0, n, step)]
        out = {k: torch.cat([p[k] for p in parts]) if len(parts) > 1 else parts[0][k] for k in parts[0]}
        return {k: v.reshape(b, s, *v.shape[1:]) for k, v in out.items()}

    def _forward_flat(self, feats: Sequence[Tensor], image_hw: tuple[int, int]) -> dict[str, Tensor]:
        raise NotImplementedError

    def _pos(self, x: Tensor, image_hw: tuple[int, int]) -> Tensor:
        return uv_pos_embed(x, image_hw[0], image_hw[1], float32_trig=True) if self.pos_embed else x

    def pyramid(self, feats: Sequence[Tensor], image_hw: tuple[int, int]) -> list[Tensor]:
        """``feats``: 4 × ``[N, P, C]`` patch tokens -> ``[l1, l2, l3, l4]`` after ``layerN_rn``."""
        h, w = image_hw[0] // self.patch_size, image_hw[1] // self.patch_size
        sc = self.scratch
        rn = (sc.layer1_rn, sc.layer2_rn, sc.layer3_rn, sc.layer4_rn)
        levels = []
        for i, x in enumerate(feats):
            x = self.norm(x)
            x = x.permute(0, 2, 1).reshape(x.shape[0], x.shape[-1], h, w)
            x = self._pos(self.projects[i](x), image_hw)
            levels.append(rn[i](self.resize_layers[i](x)))
        return levels

    @staticmethod
    def fuse(chain: Sequence[FeatureFusionBlock], levels: Sequence[Tensor]) -> Tensor:
        """Top-down fusion ``refinenet4 .. refinenet1`` (``chain`` in that order) -> 2× the finest level."""
        l1, l2, l3, l4 = levels
        out = chain[0](l4, None, size=_hw(l3))
        out = chain[1](out, l3, size=_hw(l2))
        out = chain[2](out, l2, size=_hw(l1))
        return chain[3](out, l1, size=(2 * l1.shape[2], 2 * l1.shape[3]))

    def main_chain(self) -> tuple[FeatureFusionBlock, ...]:
        sc = self.scratch
        return (sc.refinenet4, sc.refinenet3, sc.refinenet2, sc.refinenet1)

    def upsample(self, x: Tensor, image_hw: tuple[int, int]) -> Tensor:
        """``output_conv1`` output -> bilinear (align_corners) to the image grid -> position map."""
        h, w = image_hw[0] // self.patch_size, image_hw[1] // self.patch_size
        return self._pos(_resize(x, (h * self.patch_size, w * self.patch_size)), image_hw)


class _Permute(nn.Module):
    def __init__(self, dims: tuple[int, ...]) -> None:
        super().__init__()
        self.dims = dims

    def forward(self, x: Tensor) -> Tensor:
        return x.permute(*self.dims)


def _aux_out1(ch: int) -> nn.Sequential:
    half = ch // 2
    return nn.Sequential(
        nn.Conv2d(ch, half, 3, 1, 1),
        nn.Conv2d(half, ch, 3, 1, 1),
        nn.Conv2d(ch, half, 3, 1, 1),
        nn.Conv2d(half, ch, 3, 1, 1),
        nn.Conv2d(ch, half, 3, 1, 1),
    )


class DualDPT(DPTTrunk):
    """Depth + ray head of the any-view models (see the module docstring)."""

    AUX_LEVELS = 4

    def __init__(
        self, dim_in: int, features: int, out_channels: Sequence[int], output_dim: int = 2, patch_size: int = 14
    ) -> None:
        super().__init__(dim_in, features, out_channels, output_dim, patch_size, token_norm=True, pos_embed=True)
        sc = self.scratch
        sc.refinenet1_aux = FeatureFusionBlock(features, relu_skip=False)
        sc.refinenet2_aux = FeatureFusionBlock(features, relu_skip=False)
        sc.refinenet3_aux = FeatureFusionBlock(features, relu_skip=False)
        sc.refinenet4_aux = FeatureFusionBlock(features, has_residual=False, relu_skip=False)
        sc.output_conv1_aux = nn.ModuleList(_aux_out1(features) for _ in range(self.AUX_LEVELS))
        shared_norm = nn.LayerNorm(32)  # one instance in all four entries, as officially
        sc.output_conv2_aux = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(features // 2, 32, 3, 1, 1),
                _Permute((0, 2, 3, 1)),
                shared_norm,
                _Permute((0, 3, 1, 2)),
                nn.ReLU(),
                nn.Conv2d(32, 7, 1, 1, 0),
            )
            for _ in range(self.AUX_LEVELS)
        )

    def _forward_flat(self, feats: Sequence[Tensor], image_hw: tuple[int, int]) -> dict[str, Tensor]:
        sc = self.scratch
        levels = self.pyramid(feats, image_hw)
        main = self.fuse(self.main_chain(), levels)
        aux = self.fuse((sc.refinenet4_aux, sc.refinenet3_aux, sc.refinenet2_aux, sc.refinenet1_aux), levels)
        logits = sc.output_conv2(self.upsample(sc.output_conv1(main), image_hw))
        aux = self._pos(sc.output_conv1_aux[-1](aux), image_hw)
        aux_logits = sc.output_conv2_aux[-1](aux).permute(0, 2, 3, 1)
        return {
            "depth": torch.exp(logits[:, 0]),
            "depth_conf": torch.exp(logits[:, -1]) + 1,
            "ray": aux_logits[..., :6],
            "ray_conf": torch.exp(aux_logits[..., 6]) + 1,
        }


def _hw(x: Tensor) -> tuple[int, int]:
    return int(x.shape[2]), int(x.shape[3])

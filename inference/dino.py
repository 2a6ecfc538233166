"""The DINOv2 ViT with register tokens that VGGT uses as its patch embedding.

In the real model this is ``dinov2_vitl14_reg`` (width 1024, 24 blocks, 16 heads, 4 registers,
LayerNorm eps 1e-6, LayerScale).  Its final-LayerNorm patch tokens (``x_norm_patchtokens``)
are both the aggregator's input and the tokens SwiftVGGT uses for loop detection.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .layers import Block

__all__ = ["DinoVisionTransformer", "DinoOutput", "PatchEmbed"]

_DINO_LN_EPS = 1e-6


class PatchEmbed(nn.Module):
    """Non-overlapping ``patch x patch`` convolution: ``[N,3,H,W]`` -> ``[N, h*w, C]``."""

    def __init__(self, patch_size: int, embed_dim: int, in_chans: int = 3) -> None:
        super().__init__()
        self.proj = nn.Conv2d(in_chans, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: Tensor) -> Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class DinoOutput(dict):  # type: ignore[type-arg]
    """Plain dict with keys ``x_norm_clstoken [N,C]``, ``x_norm_regtokens [N,R,C]``,
    ``x_norm_patchtokens [N,P,C]`` and ``x_prenorm [N,1+R+P,C]`` (official names)."""


class DinoVisionTransformer(nn.Module):
    """DINOv2 ViT-with-registers forward for inference (no masking, no chunked blocks).

    Parameter names match the official ``aggregator.patch_embed.*`` entries: ``cls_token``,
    ``pos_embed``, ``register_tokens``, ``mask_token`` (unused, kept for strict loading),
    ``patch_embed.proj``, ``blocks.N``, ``norm``.
    """

    def __init__(
        self,
        img_size: int,
        patch_size: int,
        embed_dim: int,
        depth: int,
        num_heads: int,
        mlp_ratio: float,
        num_register_tokens: int,
    ) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.num_register_tokens = num_register_tokens
        grid = img_size // patch_size
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, grid * grid + 1, embed_dim))
        self.register_tokens = nn.Parameter(torch.zeros(1, num_register_tokens, embed_dim))
        self.mask_token = nn.Parameter(torch.zeros(1, embed_dim), requires_grad=False)
        self.patch_embed = PatchEmbed(patch_size, embed_dim)
        self.blocks = nn.ModuleList(
            Block(embed_dim, num_heads, mlp_ratio, init_values=1.0, norm_eps=_DINO_LN_EPS) for _ in range(depth)
        )
        self.norm = nn.LayerNorm(embed_dim, eps=_DINO_LN_EPS)
        # Set by ``static_pos_embed`` (ONNX export): a precomputed [1, 1+P, C] embedding.
        self.fixed_pos_embed: Tensor | None = None

    def interpolate_pos_encoding(self, patches_h: int, patches_w: int) -> Tensor:
        """Position embedding for an ``patches_h x patches_w`` grid, ``[1, 1 + h*w, C]``.

        The official rule: the stored embedding is used as is only for the native square grid;
        otherwise its patch part is resized with bicubic, ``antialias=True`` interpolation to
        the target size (no scale-factor offset), in float32, and the cls part is kept.
        """
        n = self.pos_embed.shape[1] - 1
        if patches_h * patches_w == n and patches_h == patches_w:
            return self.pos_embed
        pos = self.pos_embed.float()
        cls_pos, patch_pos = pos[:, :1], pos[:, 1:]
        m = int(round(n**0.5))
        dim = pos.shape[-1]
        grid = patch_pos.reshape(1, m, m, dim).permute(0, 3, 1, 2)
        grid = F.interpolate(grid, size=(patches_h, patches_w), mode="bicubic", antialias=True)
        patch_pos = grid.permute(0, 2, 3, 1).reshape(1, patches_h * patches_w, dim)
        return torch.cat((cls_pos, patch_pos), dim=1).to(self.pos_embed.dtype)

    def forward(self, x: Tensor) -> DinoOutput:
        """``x``: ``[N, 3, H, W]`` ImageNet-normalised images, ``H, W`` multiples of the patch size."""
        n, _, height, width = x.shape
        h, w = height // self.patch_size, width // self.patch_size
        tokens = self.patch_embed(x)
        tokens = torch.cat((self.cls_token.expand(n, -1, -1), tokens), dim=1)
        pos = self.fixed_pos_embed if self.fixed_pos_embed is not None else self.interpolate_pos_encoding(h, w)
        tokens = tokens + pos.to(tokens.dtype)
        # Registers are inserted after cls, after the position embedding (they get none).
        tokens = torch.cat((tokens[:, :1], self.register_tokens.expand(n, -1, -1), tokens[:, 1:]), dim=1)
        for blk in self.blocks:
            tokens = blk(tokens)
        normed = self.norm(tokens)
        r = self.num_register_tokens
        return DinoOutput(
            x_norm_clstoken=normed[:, 0],
            x_norm_regtokens=normed[:, 1 : r + 1],
            x_norm_patchtokens=normed[:, r + 1 :],
            x_prenorm=tokens,
        )

"""VGGT's aggregator: DINO patch tokens, then alternating frame-wise and global attention."""

from __future__ import annotations

from collections.abc import Collection

import torch
from torch import Tensor, nn

from .config import VGGTConfig
from .dino import DinoVisionTransformer
from .layers import Block, RopeTables, frame_rope_tables

__all__ = ["Aggregator", "AggregatorOutput"]

_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


class AggregatorOutput(dict):  # type: ignore[type-arg]
    """``tokens``: list of ``depth`` entries ``[B, S, T, 2C]`` (``cat(frame_i, global_i)``),
    ``None`` for layers not requested; ``patch_tokens``: ``[B, S, P, C]`` DINO
    ``x_norm_patchtokens``."""


def _first_and_rest(token: Tensor, batch: int, frames: int) -> Tensor:
    """``token [1, 2, X, C]`` -> ``[B*S, X, C]``: slot 0 for frame 0, slot 1 for the others."""
    first = token[:, 0:1].expand(batch, 1, *token.shape[2:])
    rest = token[:, 1:2].expand(batch, frames - 1, *token.shape[2:])
    return torch.cat([first, rest], dim=1).reshape(batch * frames, *token.shape[2:])


class Aggregator(nn.Module):
    """Alternating-attention transformer over the frames of one scene.

    Per frame the tokens are ``[camera (1), registers (R), patches (P)]``; frame blocks attend
    within a frame (``[B*S, T, C]``), global blocks across all frames (``[B, S*T, C]``).
    """

    def __init__(self, cfg: VGGTConfig) -> None:
        super().__init__()
        c = cfg.embed_dim
        self.cfg = cfg
        self.camera_token = nn.Parameter(torch.zeros(1, 2, 1, c))
        self.register_token = nn.Parameter(torch.zeros(1, 2, cfg.num_register_tokens, c))
        self.patch_embed = DinoVisionTransformer(
            img_size=cfg.img_size,
            patch_size=cfg.patch_size,
            embed_dim=c,
            depth=cfg.dino_depth,
            num_heads=cfg.dino_num_heads,
            mlp_ratio=cfg.dino_mlp_ratio,
            num_register_tokens=cfg.num_register_tokens,
        )

        def block() -> Block:
            return Block(c, cfg.num_heads, cfg.mlp_ratio, init_values=cfg.init_values, qk_norm=cfg.qk_norm)

        self.frame_blocks = nn.ModuleList(block() for _ in range(cfg.depth))
        self.global_blocks = nn.ModuleList(block() for _ in range(cfg.depth))

    def rope_tables(self, patches_h: int, patches_w: int, device: torch.device) -> RopeTables | None:
        """RoPE tables for one frame: special tokens at (0, 0), patch (r, c) at (r+1, c+1)."""
        if self.cfg.rope_freq <= 0:
            return None
        head_dim = self.cfg.embed_dim // self.cfg.num_heads
        return frame_rope_tables(patches_h, patches_w, self.cfg.patch_start_idx, head_dim, self.cfg.rope_freq, device)

    def forward(self, images: Tensor, keep: Collection[int] | None = None) -> AggregatorOutput:
        """Runs the aggregator.

        Args:
            images: ``[B, S, 3, H, W]`` RGB in [0, 1].
            keep: indices of the outputs to return (negative ones count from the end); the
                others are ``None``, which saves memory (the heads need 5 of the 24).  ``None``
                keeps all.

        Returns:
            see :class:`AggregatorOutput`.
        """
        b, s, ch, height, width = images.shape
        if ch != 3 or height % self.cfg.patch_size or width % self.cfg.patch_size:
            raise ValueError(
                f"images must be [B,S,3,H,W] with H, W multiples of {self.cfg.patch_size}; got {tuple(images.shape)}"
            )
        # ImageNet normalisation (upstream keeps these as non-persistent buffers; constants here
        # so that a model built on the meta device and loaded with assign=True is complete).
        mean = torch.tensor(_IMAGENET_MEAN, dtype=images.dtype, device=images.device).view(1, 1, 3, 1, 1)
        std = torch.tensor(_IMAGENET_STD, dtype=images.dtype, device=images.device).view(1, 1, 3, 1, 1)
        x = (images - mean) / std
        patch_tokens = self.patch_embed(x.reshape(b * s, ch, height, width))["x_norm_patchtokens"]
        _, p, c = patch_tokens.shape
        tokens = torch.cat(
            [_first_and_rest(self.camera_token, b, s), _first_and_rest(self.register_token, b, s), patch_tokens],
            dim=1,
        )  # [B*S, T, C]
        t = tokens.shape[1]
        rope = self.rope_tables(height // self.cfg.patch_size, width // self.cfg.patch_size, images.device)

        keep_set = None if keep is None else {i % self.cfg.depth for i in keep}
        outputs: list[Tensor | None] = []
        frame_idx = global_idx = 0
        block = self.cfg.aa_block_size
        for _ in range(self.cfg.depth // block):
            inter: dict[str, list[Tensor]] = {}
            for kind in self.cfg.aa_order:
                inter[kind] = []
                if kind == "frame":
                    tokens = tokens.reshape(b * s, t, c)
                    for _ in range(block):
                        tokens = self.frame_blocks[frame_idx](tokens, rope)
                        frame_idx += 1
                        inter[kind].append(tokens.reshape(b, s, t, c))
                else:
                    tokens = tokens.reshape(b, s * t, c)
                    for _ in range(block):
                        tokens = self.global_blocks[global_idx](tokens, rope)
                        global_idx += 1
                        inter[kind].append(tokens.reshape(b, s, t, c))
            for f, g in zip(inter["frame"], inter["global"]):
                wanted = keep_set is None or len(outputs) in keep_set
                outputs.append(torch.cat([f, g], dim=-1) if wanted else None)
        return AggregatorOutput(tokens=outputs, patch_tokens=patch_tokens.reshape(b, s, p, c))

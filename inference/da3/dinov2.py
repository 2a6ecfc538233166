"""The DINOv2 ViT of Depth Anything 3, with cross-view attention (``backbone.pretrained``).

Per view the tokens are ``[token 0, P patches]`` (no registers).  Blocks before ``alt_start``
attend within each view ("local"); from ``alt_start`` on, odd blocks attend over all views of a
scene jointly ("global") and even blocks stay local.  Right before block ``alt_start - 1`` the
reference view is chosen and moved to the front (:mod:`.refview`); right before block
``alt_start`` token 0 of every view is replaced by a camera token (learned: one for the
reference slot, one for the others; or given by the camera encoder).  q/k LayerNorm and 2-D RoPE
start at ``qknorm_start`` / ``rope_start``.  RoPE positions: token 0 at (0, 0); a patch at
``(row + 1, col + 1)`` in local blocks and at (1, 1) in global blocks.

The ViT building blocks are :mod:`inference.layers` (LayerNorm eps 1e-6 in the blocks, 1e-5
for q/k-norm and the final norm), with a SwiGLU feed-forward for ``vitg``.
"""

from __future__ import annotations

import dataclasses

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..dino import PatchEmbed
from ..layers import Block, RopeTables, rope_tables_2d
from .config import DA3Config
from .refview import MIN_VIEWS_FOR_SELECTION, gather_views, reference_order, restore_order, select_reference_view

__all__ = ["SwiGLUFFN", "DA3ViT", "Backbone", "BackboneOutput"]

_BLOCK_LN_EPS = 1e-6
_POS_INTERP_OFFSET = 0.1


class SwiGLUFFN(nn.Module):
    """``w3(silu(a) * b)`` with ``[a, b] = w12(x)``; the hidden width is rounded as the official
    ``SwiGLUFFNFused`` does: ``((int(2/3 * hidden) + 7) // 8) * 8`` (4096 for ViT-g)."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        hidden = (int(hidden * 2 / 3) + 7) // 8 * 8
        self.w12 = nn.Linear(dim, 2 * hidden)
        self.w3 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        a, b = self.w12(x).chunk(2, dim=-1)
        return self.w3(F.silu(a) * b)


@dataclasses.dataclass
class BackboneOutput:
    """What the ViT hands on, all in the ORIGINAL view order unless noted.

    patch_tokens: 4 × ``[B, S, P, C']`` head inputs (``C' = 2C`` with cat_token).
    cam_tokens: 4 × ``[B, S, C']`` token 0 of the same (un-normalised).
    ref_view_idx: ``[B]`` int64 chosen reference view, -1 where no selection ran.
    view_order: ``[B, S]`` int64 original index at each internal slot.
    export: ``[B, S, P, C]`` final-LayerNorm patch tokens of ``export_layer`` (or None).
    select_cls_tokens: ``[B, S, C]`` what the selector saw (or None).
    block_outputs: per block ``[B, S, 1+P, C]`` in INTERNAL order (only if asked for).
    """

    patch_tokens: list[Tensor]
    cam_tokens: list[Tensor]
    ref_view_idx: Tensor
    view_order: Tensor
    export: Tensor | None
    select_cls_tokens: Tensor | None
    block_outputs: list[Tensor]


class DA3ViT(nn.Module):
    """Parameters named like the official ``DinoVisionTransformer`` of depth_anything_3."""

    def __init__(self, cfg: DA3Config) -> None:
        super().__init__()
        self.cfg = cfg
        c = cfg.embed_dim
        grid = cfg.img_size // cfg.patch_size
        self.cls_token = nn.Parameter(torch.zeros(1, 1, c))
        if cfg.alt_start != -1:
            self.camera_token = nn.Parameter(torch.zeros(1, 2, c))
        self.pos_embed = nn.Parameter(torch.zeros(1, grid * grid + 1, c))
        self.patch_embed = PatchEmbed(cfg.patch_size, c)
        hidden = int(c * cfg.mlp_ratio)
        self.blocks = nn.ModuleList(
            Block(
                c,
                cfg.num_heads,
                cfg.mlp_ratio,
                init_values=1.0,
                qk_norm=cfg.qknorm_start != -1 and i >= cfg.qknorm_start,
                norm_eps=_BLOCK_LN_EPS,
                mlp=SwiGLUFFN(c, hidden) if cfg.swiglu else None,
            )
            for i in range(cfg.depth)
        )
        self.norm = nn.LayerNorm(c)
        # Set during ONNX export: the position embedding precomputed for the export size.
        self.fixed_pos_embed: Tensor | None = None

    def interpolate_pos_encoding(self, h: int, w: int) -> Tensor:
        """``[1, 1 + h*w, C]``: the 37×37 grid resized bicubically (no antialias) with the official
        scale factors ``((h + 0.1) / 37, (w + 0.1) / 37)`` (not ``size=(h, w)``: the sampling
        positions follow the scale factor), unless the grid is already 37×37 and square."""
        n = self.pos_embed.shape[1] - 1
        m = int(round(n**0.5))
        if h * w == n and h == w:
            return self.pos_embed
        pos = self.pos_embed.float()
        grid = pos[:, 1:].reshape(1, m, m, -1).permute(0, 3, 1, 2)
        scale = ((h + _POS_INTERP_OFFSET) / m, (w + _POS_INTERP_OFFSET) / m)
        grid = F.interpolate(grid, scale_factor=scale, mode="bicubic", antialias=False)
        if tuple(grid.shape[-2:]) != (h, w):
            raise ValueError(f"position embedding resized to {tuple(grid.shape[-2:])}, expected {(h, w)}")
        patch = grid.permute(0, 2, 3, 1).reshape(1, h * w, -1)
        return torch.cat((pos[:, :1], patch), dim=1).to(self.pos_embed.dtype)

    def _rope(self, h: int, w: int, device: torch.device) -> tuple[RopeTables, RopeTables]:
        """Tables for local blocks (patch (r+1, c+1)) and global blocks (every patch (1, 1))."""
        rows = torch.arange(h, device=device).repeat_interleave(w)
        cols = torch.arange(w, device=device).repeat(h)
        local = torch.cat([torch.zeros(1, 2, dtype=torch.long, device=device), torch.stack([rows, cols], -1) + 1])
        flat = torch.cat(
            [torch.zeros(1, 2, dtype=torch.long, device=device), torch.ones(h * w, 2, dtype=torch.long, device=device)]
        )
        head_dim = self.cfg.embed_dim // self.cfg.num_heads
        return (rope_tables_2d(local, head_dim, self.cfg.rope_freq), rope_tables_2d(flat, head_dim, self.cfg.rope_freq))

    def forward(
        self,
        images: Tensor,
        cam_tokens: Tensor | None = None,
        ref_view_strategy: str = "saddle_balanced",
        export_layer: int | None = None,
        keep_blocks: bool = False,
    ) -> BackboneOutput:
        """Runs the ViT.

        Args:
            images: ``[B, S, 3, H, W]`` ImageNet-normalised, ``H, W`` multiples of 14.
            cam_tokens: ``[B, S, C]`` camera-encoder tokens (pose conditioning; no reference
                view selection then), or None for the learned camera tokens.
            ref_view_strategy: see :mod:`.refview`.
            export_layer: block whose final-LayerNorm patch tokens to return (``alt_start - 1``
                is the per-image descriptor source).
            keep_blocks: also return every block output (for golden checks).
        """
        cfg = self.cfg
        b, s, _, height, width = images.shape
        p = cfg.patch_size
        h, w = height // p, width // p
        c = cfg.embed_dim
        x = self.patch_embed(images.reshape(b * s, 3, height, width))
        x = torch.cat((self.cls_token.expand(b * s, -1, -1), x), dim=1)
        pos = self.fixed_pos_embed if self.fixed_pos_embed is not None else self.interpolate_pos_encoding(h, w)
        x = (x + pos.to(x.dtype)).reshape(b, s, 1 + h * w, c)
        t = 1 + h * w
        rope_local = rope_global = None
        if cfg.rope_start != -1:
            rope_local, rope_global = self._rope(h, w, images.device)

        alt = cfg.alt_start
        ref = torch.full((b,), -1, dtype=torch.long, device=images.device)
        order: Tensor | None = None
        restore: Tensor | None = None
        select_cls: Tensor | None = None
        local_x = x
        patch_out: list[Tensor] = []
        cam_out: list[Tensor] = []
        blocks: list[Tensor] = []
        export: Tensor | None = None
        for i, blk in enumerate(self.blocks):
            if alt != -1 and i == alt - 1 and s >= MIN_VIEWS_FOR_SELECTION and cam_tokens is None:
                select_cls = x[:, :, 0]
                ref = select_reference_view(select_cls, ref_view_strategy)
                order, restore = reference_order(ref, s), restore_order(ref, s)
                x, local_x = gather_views(x, order), gather_views(local_x, order)
            if alt != -1 and i == alt:
                if cam_tokens is None:
                    tok = torch.cat(
                        [self.camera_token[:, :1].expand(b, 1, c), self.camera_token[:, 1:].expand(b, s - 1, c)], 1
                    )
                else:
                    tok = cam_tokens.to(x.dtype)
                # Block alt-1 is local, so the local stream is this same tensor (as in the
                # official in-place write, which changes both).
                x = torch.cat([tok[:, :, None], x[:, :, 1:]], dim=2)
                local_x = x
            is_global = alt != -1 and i >= alt and i % 2 == 1
            rope = None
            if cfg.rope_start != -1 and i >= cfg.rope_start:
                rope = rope_global if is_global else rope_local
            if is_global:
                x = blk(x.reshape(b, s * t, c), rope).reshape(b, s, t, c)
            else:
                x = blk(x.reshape(b * s, t, c), rope).reshape(b, s, t, c)
                local_x = x
            if keep_blocks:
                blocks.append(x)
            if i in cfg.out_layers:
                out = torch.cat([local_x, x], dim=-1) if cfg.cat_token else x
                if restore is not None:
                    out = gather_views(out, restore)
                cam_out.append(out[:, :, 0])
                if cfg.cat_token:
                    patch_out.append(torch.cat([out[:, :, 1:, :c], self.norm(out[:, :, 1:, c:])], dim=-1))
                else:
                    patch_out.append(self.norm(out[:, :, 1:]))
            if export_layer is not None and i == export_layer:
                export = self.norm(x[:, :, 1:] if restore is None else gather_views(x, restore)[:, :, 1:])
        view_order = order if order is not None else torch.arange(s, device=images.device).expand(b, s)
        return BackboneOutput(patch_out, cam_out, ref, view_order, export, select_cls, blocks)


class Backbone(nn.Module):
    """The official ``DinoV2`` wrapper: only holds the ViT as ``pretrained`` (parameter names)."""

    def __init__(self, cfg: DA3Config) -> None:
        super().__init__()
        self.pretrained = DA3ViT(cfg)

    def forward(self, *args: object, **kwargs: object) -> BackboneOutput:
        return self.pretrained(*args, **kwargs)  # type: ignore[arg-type]

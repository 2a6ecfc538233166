"""π³'s transformer pieces beyond the shared blocks: the head decoders, π³X's metric-token
cross-attention decoder and its pose-injection block (PRoPE attention).

The self-attention blocks are :class:`inference.layers.Block` (pre-norm, q/k LayerNorm
optional, 2-D RoPE, SDPA) with LayerNorm eps 1e-6; the head decoders use no LayerScale.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..layers import Block, LayerScale, Mlp, RopeTables, apply_rope_2d

__all__ = ["se3_inverse", "rope_block", "TransformerDecoder", "ContextDecoder", "PoseInjectBlock", "prope_attention"]

LN_EPS = 1e-6


def rope_block(dim: int, num_heads: int, layerscale: float | None, qk_norm: bool) -> Block:
    """The official ``BlockRope``: a shared :class:`Block`, LayerScale only if ``layerscale``."""
    blk = Block(dim, num_heads, 4.0, init_values=layerscale or 1.0, qk_norm=qk_norm, norm_eps=LN_EPS)
    if layerscale is None:  # official ``init_values=None``: no ls1/ls2 parameters at all
        blk.ls1 = nn.Identity()  # type: ignore[assignment]
        blk.ls2 = nn.Identity()  # type: ignore[assignment]
    return blk


class TransformerDecoder(nn.Module):
    """``linear_out(blocks(projects(x)))``: the point, confidence and camera decoders.

    Every block attends within one view (the input is ``[views, T, in_dim]``).
    """

    def __init__(self, in_dim: int, width: int, out_dim: int, depth: int, num_heads: int) -> None:
        super().__init__()
        self.projects = nn.Linear(in_dim, width)
        self.blocks = nn.ModuleList(rope_block(width, num_heads, None, qk_norm=False) for _ in range(depth))
        self.linear_out = nn.Linear(width, out_dim)

    def forward(self, x: Tensor, rope: RopeTables) -> Tensor:
        x = self.projects(x)
        for blk in self.blocks:
            x = blk(x, rope)
        return self.linear_out(x)


class _CrossAttention(nn.Module):
    """Multi-head cross-attention with separate q/k/v projections and 2-D RoPE."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.q_proj = nn.Linear(dim, dim)
        self.k_proj = nn.Linear(dim, dim)
        self.v_proj = nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)

    def _split(self, x: Tensor) -> Tensor:
        b, n, c = x.shape
        return x.reshape(b, n, self.num_heads, c // self.num_heads).transpose(1, 2)

    def forward(self, x: Tensor, ctx: Tensor, rope_x: RopeTables, rope_ctx: RopeTables) -> Tensor:
        b, n, c = x.shape
        q = apply_rope_2d(self._split(self.q_proj(x)), rope_x)
        k = apply_rope_2d(self._split(self.k_proj(ctx)), rope_ctx)
        v = self._split(self.v_proj(ctx))
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class _CrossOnlyBlock(nn.Module):
    """``x + cross_attn(norm2 x, norm_y y)`` then ``x + mlp(norm3 x)`` (no self-attention)."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.norm2 = nn.LayerNorm(dim, eps=LN_EPS)
        self.norm_y = nn.LayerNorm(dim, eps=LN_EPS)
        self.cross_attn = _CrossAttention(dim, num_heads)
        self.norm3 = nn.LayerNorm(dim, eps=LN_EPS)
        self.mlp = Mlp(dim, 4 * dim)

    def forward(self, x: Tensor, y: Tensor, rope_x: RopeTables, rope_y: RopeTables) -> Tensor:
        x = x + self.cross_attn(self.norm2(x), self.norm_y(y), rope_x, rope_y)
        return x + self.mlp(self.norm3(x))


class ContextDecoder(nn.Module):
    """π³X's metric decoder: query tokens cross-attend to all views' decoder tokens."""

    def __init__(self, in_dim: int, width: int, out_dim: int, depth: int, num_heads: int) -> None:
        super().__init__()
        self.projects_x = nn.Linear(in_dim, width)
        self.projects_y = nn.Linear(in_dim, width)
        self.blocks = nn.ModuleList(_CrossOnlyBlock(width, num_heads) for _ in range(depth))
        self.linear_out = nn.Linear(width, out_dim)

    def forward(self, x: Tensor, ctx: Tensor, rope_x: RopeTables, rope_ctx: RopeTables) -> Tensor:
        """``x [B, Q, in]`` queries, ``ctx [B, N*T, in]`` -> ``[B, Q, out]``."""
        x = self.projects_x(x)
        ctx = self.projects_y(ctx)
        for blk in self.blocks:
            x = blk(x, ctx, rope_x, rope_ctx)
        return self.linear_out(x)


def se3_inverse(T: Tensor) -> Tensor:
    """``[..., 4, 4]`` rigid transforms -> their inverses ``[R^T | -R^T t; 0 0 0 1]``."""
    rt = T[..., :3, :3].transpose(-1, -2)
    top = torch.cat([rt, -rt @ T[..., :3, 3:]], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


# ---- PRoPE (projective positional encoding) without intrinsics ------------------------------


def _rope_1d(x: Tensor, pos: Tensor, base: float, inverse: bool = False) -> Tensor:
    """Split-half 1-D RoPE on the last axis of ``x [..., P, d]`` at positions ``pos [P]``.

    Frequencies ``base^(-i / (d/2))``, ``i < d/2``; ``(a, b) -> (a cos + b sin, -a sin + b cos)``
    (the transpose, i.e. the inverse rotation, with ``inverse``).
    """
    half = x.shape[-1] // 2
    freqs = base ** (-torch.arange(half, device=x.device) / half)
    angles = pos.to(freqs.dtype)[:, None] * freqs
    cos, sin = angles.cos().to(x.dtype), angles.sin().to(x.dtype)
    a, b = x[..., :half], x[..., half:]
    if inverse:
        return torch.cat([cos * a - sin * b, sin * a + cos * b], dim=-1)
    return torch.cat([cos * a + sin * b, -sin * a + cos * b], dim=-1)


def _apply_per_view_matrix(x: Tensor, mats: Tensor) -> Tensor:
    """``x [B, h, V, P, d]`` with ``d = 4k``: each view's features, read as ``k`` 4-vectors, are
    multiplied by that view's ``mats [B, V, 4, 4]``."""
    b, h, v, p, d = x.shape
    xv = x.reshape(b, h, v, p, d // 4, 4)
    return torch.einsum("bvij,bhvpkj->bhvpki", mats, xv).reshape(b, h, v, p, d)


def prope_attention(
    q: Tensor, k: Tensor, v: Tensor, world_to_cam: Tensor, patches_hw: tuple[int, int], attn_mask: Tensor | None
) -> Tensor:
    """PRoPE attention with identity intrinsics (GTA form), as π³X's pose injection uses it.

    ``q, k, v [B, h, V*P, d]`` (views' patch tokens back to back), ``world_to_cam [B, V, 4, 4]``.
    Half of each head (``d/2``) is transformed by the view's projective matrix ``P``: queries
    by ``P^T``, keys/values by ``P^-1``, outputs by ``P``; the other two quarters get 1-D RoPE
    (base 100) on the patch column then row (0-based, no offset), keys/values/queries
    forward, outputs inverse.  ``attn_mask [B, 1, V*P, V*P]``: bool (True = attend) or additive.
    """
    ph, pw = patches_hw
    p = ph * pw
    b, h, n, d = q.shape
    cols = torch.arange(pw, device=q.device).repeat(ph)
    rows = torch.arange(ph, device=q.device).repeat_interleave(pw)
    inv = se3_inverse(world_to_cam)

    def transform(x: Tensor, mat: Tensor, inverse: bool) -> Tensor:
        a, bx, by = x.reshape(b, h, -1, p, d).split([d // 2, d // 4, d // 4], dim=-1)
        out = torch.cat(
            [_apply_per_view_matrix(a, mat), _rope_1d(bx, cols, 100.0, inverse), _rope_1d(by, rows, 100.0, inverse)],
            dim=-1,
        )
        return out.reshape(b, h, n, d)

    out = F.scaled_dot_product_attention(
        transform(q, world_to_cam.transpose(-1, -2), False),
        transform(k, inv, False),
        transform(v, inv, False),
        attn_mask=attn_mask,
    )
    return transform(out, world_to_cam, True)


class _PRoPEAttention(nn.Module):
    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.q_norm = nn.LayerNorm(dim // num_heads)  # eps 1e-5, as the shared Attention's
        self.k_norm = nn.LayerNorm(dim // num_heads)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, world_to_cam: Tensor, patches_hw: tuple[int, int], attn_mask: Tensor | None) -> Tensor:
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.num_heads, c // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)
        out = prope_attention(self.q_norm(q), self.k_norm(k), v, world_to_cam, patches_hw, attn_mask)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class PoseInjectBlock(nn.Module):
    """π³X's pose injection: returns the DELTA ``ls1(attn(norm1 x)) + ls2(mlp(norm2 x))``
    (both branches from the same ``x``; the caller adds it to the posed views' patch tokens)."""

    def __init__(self, dim: int, num_heads: int, layerscale: float = 0.01) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=LN_EPS)
        self.attn = _PRoPEAttention(dim, num_heads)
        self.ls1 = LayerScale(dim, layerscale)
        self.norm2 = nn.LayerNorm(dim, eps=LN_EPS)
        self.mlp = Mlp(dim, 4 * dim)
        self.ls2 = LayerScale(dim, layerscale)

    def forward(self, x: Tensor, cam_to_world: Tensor, patches_hw: tuple[int, int], attn_mask: Tensor | None) -> Tensor:
        """``x [B, V*P, C]``, ``cam_to_world [B, V, 4, 4]`` -> delta ``[B, V*P, C]``."""
        world_to_cam = se3_inverse(cam_to_world)
        return self.ls1(self.attn(self.norm1(x), world_to_cam, patches_hw, attn_mask)) + self.ls2(
            self.mlp(self.norm2(x))
        )

"""Transformer building blocks shared by the DINO ViT, the aggregator and the camera head.

Module and parameter names follow the official code (``norm1``, ``attn.qkv``, ``attn.q_norm``,
``ls1.gamma``, ``mlp.fc1`` ...), so checkpoints load by name.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "Attention",
    "Block",
    "LayerScale",
    "Mlp",
    "RopeTables",
    "rope_tables_2d",
    "frame_rope_tables",
    "apply_rope_2d",
]


class RopeTables(NamedTuple):
    """Cosine and sine tables of the 2-D rotary embedding for one frame's tokens.

    Both are ``[T, head_dim]``: the first half of the head dimension uses the token's row
    position, the second half its column position (angles duplicated ``cat(a, a)`` per half).
    """

    cos: Tensor
    sin: Tensor


def rope_tables_2d(positions: Tensor, head_dim: int, frequency: float) -> RopeTables:
    """Tables for :func:`apply_rope_2d`.

    Args:
        positions: ``[T, 2]`` integer ``(row, col)`` positions of one frame's tokens.
        head_dim: attention head width (divisible by 4).
        frequency: RoPE base frequency (100 in VGGT).

    Returns:
        ``RopeTables`` of float32 ``[T, head_dim]`` tensors.
    """
    half = head_dim // 2
    exponents = torch.arange(0, half, 2, device=positions.device).float() / half
    inv_freq = 1.0 / (frequency**exponents)  # [half/2]
    pos = positions.to(torch.float32)
    # Same float32 product as the official outer product (einsum "i,j->ij").
    angles_y = pos[:, 0:1] * inv_freq[None, :]
    angles_x = pos[:, 1:2] * inv_freq[None, :]
    angles = torch.cat([angles_y, angles_y, angles_x, angles_x], dim=-1)  # [T, head_dim]
    return RopeTables(angles.cos(), angles.sin())


def frame_rope_tables(
    patches_h: int, patches_w: int, num_special: int, head_dim: int, frequency: float, device: torch.device
) -> RopeTables:
    """Tables for one frame of ``num_special`` special tokens then ``patches_h x patches_w``
    patches (row-major): special tokens at (0, 0), patch ``(r, c)`` at ``(r + 1, c + 1)``
    (VGGT's aggregator and π³'s decoder)."""
    rows = torch.arange(patches_h, device=device).repeat_interleave(patches_w)
    cols = torch.arange(patches_w, device=device).repeat(patches_h)
    patch_pos = torch.stack([rows, cols], dim=-1) + 1
    special = torch.zeros(num_special, 2, dtype=patch_pos.dtype, device=device)
    return rope_tables_2d(torch.cat([special, patch_pos], dim=0), head_dim, frequency)


def _rotate_half(x: Tensor) -> Tensor:
    x1, x2 = x.chunk(2, dim=-1)
    return torch.cat((-x2, x1), dim=-1)


def apply_rope_2d(x: Tensor, rope: RopeTables) -> Tensor:
    """Rotates queries or keys.

    Args:
        x: ``[..., N, head_dim]`` with ``N`` a multiple of ``T`` (several frames of ``T``
            tokens laid out back to back, as in global attention).
        rope: tables for one frame of ``T`` tokens.

    Returns:
        ``x`` rotated, same shape.
    """
    t, d = rope.cos.shape
    lead = x.shape[:-2]
    xf = x.reshape(*lead, -1, t, d)  # [..., frames, T, d]
    y_half, x_half = xf.chunk(2, dim=-1)
    rotated = torch.cat((_rotate_half(y_half), _rotate_half(x_half)), dim=-1)
    cos = rope.cos.to(x.dtype)
    sin = rope.sin.to(x.dtype)
    out = xf * cos + rotated * sin
    return out.reshape(x.shape)


class LayerScale(nn.Module):
    """Per-channel scale ``gamma * x``."""

    def __init__(self, dim: int, init_values: float) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init_values)))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class Mlp(nn.Module):
    """``fc2(gelu(fc1(x)))`` with exact (erf) GELU."""

    def __init__(self, in_features: int, hidden_features: int, out_features: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(in_features, hidden_features)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden_features, out_features or in_features)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Attention(nn.Module):
    """Multi-head self-attention with optional per-head q/k LayerNorm and 2-D RoPE.

    Attention itself is :func:`torch.nn.functional.scaled_dot_product_attention`
    (scale ``head_dim ** -0.5``).
    """

    def __init__(self, dim: int, num_heads: int, qk_norm: bool = False) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, dim * 3)
        self.q_norm: nn.Module = nn.LayerNorm(self.head_dim) if qk_norm else nn.Identity()
        self.k_norm: nn.Module = nn.LayerNorm(self.head_dim) if qk_norm else nn.Identity()
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, rope: RopeTables | None = None) -> Tensor:
        """``x``: ``[B, N, C]`` -> ``[B, N, C]``; ``rope`` tables cover ``N`` in frames of ``T``."""
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)  # [B, heads, N, head_dim]
        q, k = self.q_norm(q), self.k_norm(k)
        if rope is not None:
            q = apply_rope_2d(q, rope)
            k = apply_rope_2d(k, rope)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class Block(nn.Module):
    """Pre-norm transformer block with LayerScale: ``x + ls1(attn(norm1 x))``, then the MLP."""

    def __init__(
        self,
        dim: int,
        num_heads: int,
        mlp_ratio: float = 4.0,
        init_values: float = 0.01,
        qk_norm: bool = False,
        norm_eps: float = 1e-5,
        mlp: nn.Module | None = None,
    ) -> None:
        """``mlp``: a feed-forward to use instead of ``Mlp(dim, dim * mlp_ratio)`` (e.g. SwiGLU)."""
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn = Attention(dim, num_heads, qk_norm=qk_norm)
        self.ls1 = LayerScale(dim, init_values)
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        self.mlp = mlp if mlp is not None else Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim, init_values)

    def forward(self, x: Tensor, rope: RopeTables | None = None) -> Tensor:
        """``x``: ``[B, N, C]`` -> ``[B, N, C]``."""
        x = x + self.ls1(self.attn(self.norm1(x), rope))
        return x + self.ls2(self.mlp(self.norm2(x)))

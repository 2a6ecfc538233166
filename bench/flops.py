"""FLOPs of one VGGT forward pass over a chunk, counted analytically.

Every matrix product and convolution of :class:`inference.model.VGGT` is counted as
``2 · (multiply-adds)``; biases, norms, activations, softmax and interpolation (``O(n)`` work
next to ``O(n·C)`` products) are not, which is the convention of
``torch.utils.flop_counter`` (the test checks the two agree exactly on the tiny model with
attention on the math backend).

For a chunk of ``S`` frames of ``H × W`` pixels, patch size ``p``, ``P = (H/p)(W/p)`` patches
and ``T = 1 + R + P`` tokens per frame (camera or class token, ``R`` registers, patches), a
pre-norm transformer block of width ``C`` and MLP width ``M`` on sequences of ``N`` tokens
costs

    F_block(N, C, M) = 2·N·C·(3C + C + 2M) + 4·N²·C          (qkv, proj, MLP; QKᵀ and AV)

so the DINO ViT and the frame blocks cost ``S · F_block(T, ...)`` each and a global block
``F_block(S·T, ...)``: global attention grows as ``S²`` and dominates long chunks
(VGGT-1B at 75 frames of 518 × 154: ~1.5e14 FLOP in all).

    python bench/flops.py [--frames 75] [--height 154] [--width 518]
"""

from __future__ import annotations

import argparse
import math
from typing import Any

__all__ = ["block_flops", "vggt_chunk_flops"]


def block_flops(tokens: int, dim: int, mlp_hidden: int, sequences: int = 1) -> int:
    """FLOPs of one transformer block on ``sequences`` sequences of ``tokens`` tokens (``F_block``)."""
    linear = 2 * tokens * dim * (3 * dim + dim + 2 * mlp_hidden)
    attention = 4 * tokens * tokens * dim
    return sequences * (linear + attention)


def _conv(out_h: int, out_w: int, c_in: int, c_out: int, k: int = 1) -> int:
    """A ``k × k`` convolution producing ``out_h × out_w`` pixels."""
    return 2 * out_h * out_w * c_in * c_out * k * k


def _dpt_flops(cfg: Any, height: int, width: int) -> int:
    """The DPT depth head on one frame (see :class:`inference.dpt.DPTHead`)."""
    p = cfg.patch_size
    h, w = height // p, width // p
    d = 2 * cfg.embed_dim
    f = cfg.dpt_features
    oc = cfg.dpt_out_channels
    h4, w4 = (h + 1) // 2, (w + 1) // 2  # the stride-2 3x3 convolution (padding 1)
    sizes = [(4 * h, 4 * w), (2 * h, 2 * w), (h, w), (h4, w4)]
    total = sum(_conv(h, w, d, c) for c in oc)  # 1x1 projections
    total += 2 * h * w * oc[0] * oc[0] * 16 + 2 * h * w * oc[1] * oc[1] * 4  # transposed convs (k = stride)
    total += _conv(h4, w4, oc[3], oc[3], 3)
    total += sum(_conv(hh, ww, c, f, 3) for (hh, ww), c in zip(sizes, oc))  # layerN_rn
    rcu = lambda hh, ww: 2 * _conv(hh, ww, f, f, 3)
    # refinenet4 (one unit) -> size of level 3; refinenets 3, 2, 1 (two units each); 1x1 out_conv
    # at the target size: level 3, 2, 1, then twice level 1.
    targets = [sizes[2], sizes[1], sizes[0], (8 * h, 8 * w)]
    inputs = [sizes[3], sizes[2], sizes[1], sizes[0]]
    for i, ((hi, wi), (ht, wt)) in enumerate(zip(inputs, targets)):
        total += (1 if i == 0 else 2) * rcu(hi, wi) + _conv(ht, wt, f, f)
    total += _conv(8 * h, 8 * w, f, f // 2, 3)  # output_conv1
    total += _conv(h * p, w * p, f // 2, 32, 3) + _conv(h * p, w * p, 32, 2)  # output_conv2
    return total


def vggt_chunk_flops(cfg: Any, frames: int, height: int, width: int) -> dict[str, int]:
    """FLOPs of :class:`inference.model.VGGT` (config ``cfg``) on one chunk, by part.

    Returns a dict with ``dino``, ``frame_attention``, ``global_attention`` (the frame and
    global blocks, linear layers included), ``aggregator`` (the three), ``camera_head``,
    ``depth_head`` and ``total``.
    """
    p = cfg.patch_size
    if height % p or width % p:
        raise ValueError(f"height {height} and width {width} must be multiples of the patch size {p}")
    c = cfg.embed_dim
    patches = (height // p) * (width // p)
    tokens = 1 + cfg.num_register_tokens + patches
    dino = frames * _conv(height // p, width // p, 3, c, p)
    dino += cfg.dino_depth * block_flops(tokens, c, int(c * cfg.dino_mlp_ratio), sequences=frames)
    mlp = int(c * cfg.mlp_ratio)
    frame_attn = cfg.depth * block_flops(tokens, c, mlp, sequences=frames)
    global_attn = cfg.depth * block_flops(frames * tokens, c, mlp)
    c2 = 2 * c
    per_iteration = (
        2 * frames * 9 * c2  # embed_pose
        + 2 * frames * c2 * 3 * c2  # adaLN modulation
        + cfg.camera_trunk_depth * block_flops(frames, c2, int(c2 * cfg.camera_mlp_ratio))
        + 2 * frames * (c2 * (c2 // 2) + (c2 // 2) * 9)  # pose branch MLP
    )
    camera = cfg.camera_iterations * per_iteration
    depth_head = frames * _dpt_flops(cfg, height, width)
    aggregator = dino + frame_attn + global_attn
    return {
        "dino": dino,
        "frame_attention": frame_attn,
        "global_attention": global_attn,
        "aggregator": aggregator,
        "camera_head": camera,
        "depth_head": depth_head,
        "total": aggregator + camera + depth_head,
    }


def main(argv: list[str] | None = None) -> None:
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from inference.config import VGGTConfig

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[30, 60, 75, 120])
    ap.add_argument("--height", type=int, default=154)
    ap.add_argument("--width", type=int, default=518)
    args = ap.parse_args(argv)
    cfg = VGGTConfig()
    print(f"VGGT-1B at {args.width}x{args.height}: TFLOP per chunk")
    for s in args.frames:
        parts = vggt_chunk_flops(cfg, s, args.height, args.width)
        row = ", ".join(f"{k} {v / 1e12:.2f}" for k, v in parts.items())
        print(
            f"  S = {s:4d}: {row}; floor at 790 TFLOP/s {parts['total'] / 790e12 * 1e3:.0f} ms "
            f"({math.floor(s / (parts['total'] / 790e12)):d} frames/s)"
        )


if __name__ == "__main__":
    main()

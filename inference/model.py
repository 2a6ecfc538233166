"""The VGGT model (aggregator + camera head + depth head) with the official parameter names."""

from __future__ import annotations

import contextlib

import torch
from torch import Tensor, nn

from .aggregator import Aggregator
from .camera_head import CameraHead
from .config import VGGTConfig
from .dpt import DPTHead

__all__ = ["VGGT"]


class VGGT(nn.Module):
    """Clean-room VGGT without the point and track heads (SwiftVGGT does not use them).

    ``state_dict()`` names and shapes equal the official ``aggregator.*``, ``camera_head.*``
    and ``depth_head.*`` entries, so the released checkpoint loads with strict key checking
    (see :func:`inference.checkpoint.load_checkpoint`).
    """

    def __init__(self, config: VGGTConfig | None = None) -> None:
        super().__init__()
        cfg = config or VGGTConfig()
        self.config = cfg
        self.aggregator = Aggregator(cfg)
        self.camera_head = CameraHead(
            dim_in=2 * cfg.embed_dim,
            trunk_depth=cfg.camera_trunk_depth,
            num_heads=cfg.camera_num_heads,
            mlp_ratio=cfg.camera_mlp_ratio,
        )
        self.depth_head = DPTHead(
            dim_in=2 * cfg.embed_dim,
            patch_size=cfg.patch_size,
            features=cfg.dpt_features,
            out_channels=cfg.dpt_out_channels,
            intermediate_layer_idx=cfg.dpt_intermediate_layer_idx,
        )

    def forward(
        self,
        images: Tensor,
        return_aggregated: bool = False,
        frames_chunk_size: int | None | str = "config",
    ) -> dict[str, Tensor | list[Tensor]]:
        """Runs VGGT on one or more scenes.

        Args:
            images: ``[B, S, 3, H, W]`` (or ``[S, 3, H, W]``) RGB in [0, 1]; ``H, W`` multiples of 14.
            return_aggregated: also return every aggregator output.
            frames_chunk_size: frames per depth-head pass; ``"config"`` uses
                ``config.dpt_frames_chunk_size``, ``None`` runs all frames at once.

        Returns:
            dict with ``pose_enc [B,S,9]``, ``pose_enc_list`` (one ``[B,S,9]`` per camera-head
            iteration), ``depth [B,S,H,W,1]``, ``depth_conf [B,S,H,W]``, ``patch_tokens
            [B,S,P,C]`` (DINO ``x_norm_patchtokens``) and, if requested, ``aggregated_tokens``
            (list of ``depth`` tensors ``[B,S,5+P,2C]``).

        Under an active autocast context only the aggregator runs in reduced precision; the
        heads run in the dtype of their weights (float32 for a float32 model), as upstream.
        """
        if images.dim() == 4:
            images = images.unsqueeze(0)
        needed = None if return_aggregated else (*self.config.dpt_intermediate_layer_idx, -1)
        agg = self.aggregator(images, keep=needed)
        tokens: list[Tensor | None] = agg["tokens"]
        chunk = self.config.dpt_frames_chunk_size if frames_chunk_size == "config" else frames_chunk_size
        head_dtype = self.camera_head.embed_pose.weight.dtype
        with _heads_without_autocast(images.device):
            head_tokens = [None if t is None else t.to(head_dtype) for t in tokens]
            last = head_tokens[-1]
            assert last is not None  # always kept
            pose_enc_list = self.camera_head(last, self.config.camera_iterations)
            depth, depth_conf = self.depth_head(
                head_tokens,
                image_hw=(int(images.shape[-2]), int(images.shape[-1])),
                patch_start_idx=self.config.patch_start_idx,
                frames_chunk_size=chunk,  # type: ignore[arg-type]
            )
        out: dict[str, Tensor | list[Tensor]] = {
            "pose_enc": pose_enc_list[-1],
            "pose_enc_list": pose_enc_list,
            "depth": depth,
            "depth_conf": depth_conf,
            "patch_tokens": agg["patch_tokens"],
        }
        if return_aggregated:
            out["aggregated_tokens"] = tokens
        return out


def _heads_without_autocast(device: torch.device) -> contextlib.AbstractContextManager[None]:
    """Disables autocast for the heads only if some autocast is active (no-op otherwise)."""
    if torch.is_autocast_enabled(device.type):
        return torch.autocast(device_type=device.type, enabled=False)
    return contextlib.nullcontext()

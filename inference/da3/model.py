"""Depth Anything 3's any-view network (:class:`DA3Net`, official ``DepthAnything3Net``) and
:func:`build_da3`.

Forward: optional camera encoder (known poses) -> DINOv2 with cross-view attention ->
DualDPT (depth, confidence, rays) -> camera decoder on the last camera token (or, with
``use_ray_pose``, cameras from the rays).  The metric / mono models (``head == "dpt"``) return
depth and sky, with the sky filled at the 0.99 quantile of the non-sky depth (official
``_process_mono_sky_estimation``).

Frames: predicted ``extrinsics`` are world-to-camera in the frame of the REFERENCE view
(``ref_view_idx``; -1 when no view was chosen: fewer than 3 views — then view 0 — or given
poses — then their frame).  Every per-view output is in the input view order.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .camera import CameraDec, CameraEnc, decode_pose
from .config import DA3Config, NestedDA3Config, preset_config
from .dinov2 import Backbone
from .dualdpt import DualDPT
from .metric_dpt import GaussianHeadWeights, MetricDPT
from .raypose import cameras_from_rays
from .refview import balance_scores
from .sky import fill_sky

__all__ = ["DA3Net", "build_da3"]


class DA3Net(nn.Module):
    """Any-view (or metric/mono) Depth Anything 3 network; parameter names are the official ones."""

    def __init__(self, config: DA3Config) -> None:
        super().__init__()
        self.config = config
        self.backbone = Backbone(config)
        oc = config.head_out_channels
        if config.head == "dualdpt":
            self.head: nn.Module = DualDPT(
                config.head_dim_in, config.head_features, oc, config.head_output_dim, config.patch_size
            )
        else:
            self.head = MetricDPT(
                config.head_dim_in, config.head_features, oc, config.head_output_dim, config.patch_size
            )
        if config.camera:
            self.cam_dec = CameraDec(config.token_dim)
            self.cam_enc = CameraEnc(config.embed_dim, config.cam_enc_heads)
        if config.gs_output_dim:
            self.gs_head = GaussianHeadWeights(
                config.head_dim_in, config.head_features, oc, config.gs_output_dim, config.patch_size
            )

    @property
    def export_layer(self) -> int:
        """The block whose patch tokens describe each image alone: ``alt_start - 1`` (the last
        one before cross-view attention and the camera token); the last block for metric/mono."""
        return self.config.alt_start - 1 if self.config.alt_start != -1 else self.config.depth - 1

    def check_input(self, images: Tensor) -> None:
        """Raises ValueError (one line) for an input the network cannot take."""
        p = self.config.patch_size
        if images.dim() != 5 or images.shape[2] != 3:
            raise ValueError(f"images: expected [B, S, 3, H, W], got shape {tuple(images.shape)}")
        if images.shape[-2] % p or images.shape[-1] % p:
            raise ValueError(f"images: H and W must be multiples of {p}, got {images.shape[-2]}x{images.shape[-1]}")

    def forward(
        self,
        images: Tensor,
        extrinsics: Tensor | None = None,
        intrinsics: Tensor | None = None,
        ref_view_strategy: str = "saddle_balanced",
        use_ray_pose: bool = False,
        ransac_sample_idx: Tensor | None = None,
        intermediates: bool = False,
        frames_chunk_size: int | None = 8,
    ) -> dict[str, Tensor]:
        """Runs the network.

        Args:
            images: ``[B, S, 3, H, W]`` ImageNet-normalised RGB, ``H, W`` multiples of 14.
            extrinsics: optional known world-to-camera ``[B, S, 4, 4]`` (pose conditioning through
                the camera encoder; the official API first normalises them: view 0 identity,
                median camera distance 1).  Needs ``intrinsics``.
            intrinsics: ``[B, S, 3, 3]`` pixels of ``images``; only used with ``extrinsics`` (the
                official network has no intrinsics-only conditioning).
            ref_view_strategy: ``first`` / ``middle`` / ``saddle_balanced`` / ``saddle_sim_range``.
            use_ray_pose: cameras from the ray map (RANSAC) instead of the camera decoder.
            ransac_sample_idx: ``[100, 8]`` RANSAC indices to use (default: global RNG draw).
            intermediates: also return the per-block tokens and head inputs.
            frames_chunk_size: frames per head pass (memory only).

        Returns:
            ``depth, depth_conf [B,S,H,W]``, ``extrinsics [B,S,3,4]`` w2c, ``intrinsics [B,S,3,3]``,
            ``ray [B,S,8h,8w,6]``, ``ray_conf [B,S,8h,8w]``, ``pose_enc [B,S,9]``,
            ``ref_view_idx [B]``, ``view_order [B,S]``, ``prealt_patch_tokens [B,S,h,w,C]``
            (input order), ``head_depth`` (the head's depth: == depth here; for metric/mono
            models before sky filling); metric/mono: ``depth``, ``sky``, ``head_depth``.
            With ``intermediates``: ``block_outputs [L,B,S,1+P,C]`` (internal order),
            ``feats_tokens [4,B,S,P,C']``, ``feats_cam_tokens [4,B,S,C']``,
            ``ref_select_cls_tokens``, ``ref_balance_scores``, ``camenc_*`` when conditioned.
        """
        cfg = self.config
        self.check_input(images)
        b, s, _, height, width = images.shape
        hw = (height, width)
        out: dict[str, Tensor] = {}
        cam_tokens = None
        if extrinsics is not None:
            if not cfg.camera:
                raise ValueError("extrinsics: this model has no camera encoder (metric/mono models take images only)")
            if intrinsics is None:
                raise ValueError("extrinsics given without intrinsics: the camera encoder needs both")
            if tuple(extrinsics.shape) != (b, s, 4, 4) or tuple(intrinsics.shape) != (b, s, 3, 3):
                raise ValueError(
                    f"extrinsics/intrinsics: expected [{b},{s},4,4] and [{b},{s},3,3], got "
                    f"{tuple(extrinsics.shape)} and {tuple(intrinsics.shape)}"
                )
            cam_tokens = self.cam_enc(extrinsics.float(), intrinsics.float(), hw)
            if intermediates:
                out["camenc_pose_encoding"] = self.cam_enc.pose_encoding(extrinsics.float(), intrinsics.float(), hw)
                out["camenc_tokens"] = cam_tokens
        elif intrinsics is not None:
            raise ValueError(
                "intrinsics without extrinsics: DA3 conditions on full cameras only "
                "(the official network ignores intrinsics alone); pass both or neither"
            )
        bb = self.backbone(
            images, cam_tokens, ref_view_strategy, export_layer=self.export_layer, keep_blocks=intermediates
        )
        h, w = height // cfg.patch_size, width // cfg.patch_size
        assert bb.export is not None
        out["prealt_patch_tokens"] = bb.export.reshape(b, s, h, w, -1)
        out["ref_view_idx"] = bb.ref_view_idx
        out["view_order"] = bb.view_order
        if intermediates:
            out["block_outputs"] = torch.stack(bb.block_outputs)
            out["feats_tokens"] = torch.stack(bb.patch_tokens)
            out["feats_cam_tokens"] = torch.stack(bb.cam_tokens)
            if bb.select_cls_tokens is not None:
                out["ref_select_cls_tokens"] = bb.select_cls_tokens
                # Diagnostic restatement in float64, as the golden generator did: the min-max
                # normalisation of near-equal similarities amplifies float32 rounding ~1e4-fold.
                # (The choice itself runs in the tokens' dtype inside the ViT, as officially.)
                out["ref_balance_scores"] = balance_scores(bb.select_cls_tokens.double()).float()
        head = self.head(bb.patch_tokens, hw, frames_chunk_size)
        out["head_depth"] = head["depth"]
        if cfg.head == "dpt":
            out["sky"] = head["sky"]
            out["depth"] = fill_sky(head["depth"], head["sky"])
            return out
        out.update(head)
        out["pose_enc"] = self.cam_dec(bb.cam_tokens[-1])
        if use_ray_pose:
            rp = cameras_from_rays(head["ray"], head["ray_conf"], hw, ransac_sample_idx)
            out["extrinsics"], out["intrinsics"] = rp.extrinsics, rp.intrinsics
            if intermediates:
                out["ransac_sample_idx"], out["ransac_homography"] = rp.sample_idx, rp.homography
        else:
            out["extrinsics"], out["intrinsics"] = decode_pose(out["pose_enc"], hw)
        return out


def build_da3(preset_or_config: str | DA3Config | NestedDA3Config, device: str | torch.device = "meta") -> nn.Module:
    """Builds :class:`DA3Net` or :class:`~inference.da3.nested.NestedDA3Net` on ``device``
    (``meta``: shapes only, no memory; load weights with ``load_da3_checkpoint``, which assigns)."""
    cfg = preset_config(preset_or_config) if isinstance(preset_or_config, str) else preset_or_config
    with torch.device(device):
        if isinstance(cfg, NestedDA3Config):
            from .nested import NestedDA3Net

            return NestedDA3Net(cfg).eval()
        return DA3Net(cfg).eval()

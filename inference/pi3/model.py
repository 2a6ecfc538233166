"""The π³ network (``yyfz/Pi3``'s ``Pi3``) with the official parameter names.

Input ``[B, N, 3, H, W]`` RGB in [0, 1] (ImageNet normalisation happens inside, with the
``image_mean`` / ``image_std`` buffers of the checkpoint).  Per view: DINOv2 ViT-L/14-reg
patch tokens (no projection), 5 register tokens prepended, then 36 decoder blocks that
alternate attention within a view (even layers) and across all views (odd layers), 2-D RoPE
on patch positions ``(row + 1, col + 1)`` with special tokens at ``(0, 0)``.  The heads read
``cat(layer 34, layer 35)`` and predict, per view, local points ``(x z, y z, z)`` with
``z = exp(raw)`` (camera frame, OpenCV axes), a confidence logit and a camera-to-world pose
(rotation by SVD orthogonalisation of a 9-vector).  There is no reference view: the world
frame is arbitrary (up to a similarity).

:class:`Pi3Base` holds what π³ and π³X share (encoder, decoder, register tokens,
normalisation); :func:`assemble` turns the raw head outputs into poses and world points and is
the only place that does so (the ONNX runner calls it too: ONNX has no SVD).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from ..dino import DinoVisionTransformer
from ..layers import RopeTables, frame_rope_tables, rope_tables_2d
from .config import Pi3Config
from .decoders import TransformerDecoder, rope_block
from .heads import CameraHead, LinearPts3d, pose_from_raw

__all__ = ["Pi3", "Pi3Base", "assemble", "Trace"]

Trace = dict[str, Tensor]

_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


def build_dino(cfg: Pi3Config, in_chans: int = 3) -> DinoVisionTransformer:
    """DINOv2 ViT with 4 registers and LayerScale 1, without ``mask_token`` (π³ deletes it)."""
    vit = DinoVisionTransformer(
        img_size=cfg.img_size,
        patch_size=cfg.patch_size,
        embed_dim=cfg.dim,
        depth=cfg.enc_depth,
        num_heads=cfg.heads(cfg.dim),
        mlp_ratio=4.0,
        num_register_tokens=4,
    )
    del vit.mask_token
    if in_chans != 3:  # π³X's depth encoder: replaced after construction, so listed last
        from ..dino import PatchEmbed

        del vit.patch_embed
        vit.patch_embed = PatchEmbed(cfg.patch_size, cfg.dim, in_chans=in_chans)
    return vit


def assemble(raw: dict[str, Tensor]) -> dict[str, Tensor]:
    """Raw head outputs -> the official output dict.

    ``raw``: ``local_points [B,N,H,W,3]``, ``conf [B,N,H,W,1]``, ``rot9 [B,N,9]``,
    ``trans [B,N,3]``, ``dino_patch_tokens``, and for π³X ``metric [B]`` and ``rays``.
    Returns ``points`` (world), ``local_points``, ``conf``, ``camera_poses`` (camera-to-world
    ``[B,N,4,4]``) and the passthrough keys; with ``metric``, points, local points and pose
    translations are multiplied by it (π³X's metric scale).
    """
    local = raw["local_points"]
    trans = raw["trans"]
    scale = raw.get("metric")
    if scale is not None:
        local = local * scale.view(-1, 1, 1, 1, 1)
        trans = trans * scale.view(-1, 1, 1)
    poses = pose_from_raw(raw["rot9"], trans)
    points = torch.einsum("bnij,bnhwj->bnhwi", poses[..., :3, :3], local) + poses[:, :, None, None, :3, 3]
    out = {k: v for k, v in raw.items() if k not in ("rot9", "trans")}
    out.update(points=points, local_points=local, camera_poses=poses)
    return out


class Pi3Base(nn.Module):
    """Encoder, register tokens and the alternating-attention decoder shared by π³ and π³X."""

    def __init__(self, cfg: Pi3Config) -> None:
        super().__init__()
        self.config = cfg
        self.encoder = build_dino(cfg)
        self.decoder = nn.ModuleList(
            rope_block(cfg.dim, cfg.heads(cfg.dim), 0.01, qk_norm=True) for _ in range(cfg.dec_depth)
        )
        self.register_token = nn.Parameter(torch.zeros(1, 1, cfg.num_register_tokens, cfg.dim))

    def _register_normalisation(self) -> None:
        # Persistent buffers (in the official checkpoint); registered last, like upstream.
        self.register_buffer("image_mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("image_std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1))

    @property
    def patch_start(self) -> int:
        return self.config.num_register_tokens

    def patches_hw(self, images: Tensor) -> tuple[int, int]:
        p = self.config.patch_size
        if images.dim() != 5 or images.shape[2] != 3 or images.shape[-2] % p or images.shape[-1] % p:
            raise ValueError(f"images must be [B,N,3,H,W] with H, W multiples of {p}; got {tuple(images.shape)}")
        return images.shape[-2] // p, images.shape[-1] // p

    def rope(self, patches_hw: tuple[int, int], device: torch.device) -> RopeTables:
        """RoPE tables of one view's ``registers + patches`` tokens."""
        cfg = self.config
        return frame_rope_tables(*patches_hw, cfg.num_register_tokens, cfg.attn_head_dim, cfg.rope_freq, device)

    def origin_rope(self, device: torch.device) -> RopeTables:
        """Tables for one token at position (0, 0) (the identity rotation)."""
        return rope_tables_2d(
            torch.zeros(1, 2, dtype=torch.long, device=device), self.config.attn_head_dim, self.config.rope_freq
        )

    def encode_images(self, images: Tensor, trace: Trace | None) -> Tensor:
        """``[B,N,3,H,W]`` in [0,1] -> DINO ``x_norm_patchtokens [B*N, P, C]``."""
        b, n, c, h, w = images.shape
        x = ((images - self.image_mean) / self.image_std).reshape(b * n, c, h, w)
        tokens = self.encoder(x)["x_norm_patchtokens"]
        if trace is not None:
            trace["encoder_input_normalized"] = x
            trace["dino_patch_tokens"] = tokens
        return tokens

    def decode(
        self,
        tokens: Tensor,
        views: int,
        patches_hw: tuple[int, int],
        rope: RopeTables,
        trace: Trace | None,
        inject: Any = None,
    ) -> Tensor:
        """``tokens [B*N, P, C]`` -> ``cat(layer[-2], layer[-1]) [B*N, R+P, 2C]``.

        ``inject(layer_index, hidden [B, N*T, C]) -> hidden`` runs after each layer (π³X's
        pose injection); ``None`` for π³.
        """
        bn, _, c = tokens.shape
        b = bn // views
        reg = self.register_token.expand(b, views, -1, -1).reshape(bn, -1, c)
        hidden = torch.cat([reg, tokens], dim=1)
        t = hidden.shape[1]
        penultimate = hidden
        depth = len(self.decoder)
        for i, blk in enumerate(self.decoder):
            hidden = blk(hidden.reshape(bn, t, c) if i % 2 == 0 else hidden.reshape(b, views * t, c), rope)
            if trace is not None:
                trace[f"decoder_layer_{i:02d}"] = hidden.reshape(bn, t, c)
            if inject is not None:
                hidden = inject(i, hidden.reshape(b, views * t, c))
            if i == depth - 2:
                penultimate = hidden
        out = torch.cat([penultimate.reshape(bn, t, c), hidden.reshape(bn, t, c)], dim=-1)
        if trace is not None:
            trace["decode_hidden_concat"] = out
            ph, pw = patches_hw
            rows = torch.arange(ph, device=out.device).repeat_interleave(pw)
            cols = torch.arange(pw, device=out.device).repeat(ph)
            pos = torch.cat(
                [torch.zeros(self.patch_start, 2, device=out.device), torch.stack([rows, cols], -1).float() + 1]
            )
            trace["decode_pos"] = pos.expand(bn, -1, -1)
        return out


class Pi3(Pi3Base):
    """Clean-room π³; ``state_dict()`` equals the official checkpoint's names and shapes."""

    def __init__(self, config: Pi3Config | None = None) -> None:
        cfg = config or Pi3Config.pi3()
        if cfg.variant != "pi3":
            raise ValueError(f"Pi3 needs a 'pi3' config, got variant {cfg.variant!r} (use inference.pi3.pi3x.Pi3X)")
        super().__init__(cfg)
        heads = cfg.heads(cfg.head_width)
        self.point_decoder = TransformerDecoder(2 * cfg.dim, cfg.head_width, cfg.point_out, cfg.head_depth, heads)
        self.point_head = LinearPts3d(cfg.patch_size, cfg.point_out, 3)
        self.conf_decoder = TransformerDecoder(2 * cfg.dim, cfg.head_width, cfg.point_out, cfg.head_depth, heads)
        self.conf_head = LinearPts3d(cfg.patch_size, cfg.point_out, 1)
        self.camera_decoder = TransformerDecoder(2 * cfg.dim, cfg.head_width, cfg.camera_out, cfg.head_depth, heads)
        self.camera_head = CameraHead(cfg.camera_out)
        self._register_normalisation()

    def forward_raw(self, images: Tensor, trace: Trace | None = None) -> dict[str, Tensor]:
        """Everything up to (not including) the SVD: see :func:`assemble` for the keys."""
        b, n, _, h, w = images.shape
        phw = self.patches_hw(images)
        rope = self.rope(phw, images.device)
        tokens = self.encode_images(images, trace)
        hidden = self.decode(tokens, n, phw, rope, trace)
        point_hidden = self.point_decoder(hidden, rope)
        conf_hidden = self.conf_decoder(hidden, rope)
        camera_hidden = self.camera_decoder(hidden, rope)
        if trace is not None:
            trace.update(point_decoder_out=point_hidden, conf_decoder_out=conf_hidden, camera_decoder_out=camera_hidden)
        s = self.patch_start
        xy, z = self.point_head(point_hidden[:, s:].float(), phw).reshape(b, n, h, w, 3).split([2, 1], dim=-1)
        z = torch.exp(z)
        conf = self.conf_head(conf_hidden[:, s:].float(), phw).reshape(b, n, h, w, 1)
        rot9, trans = self.camera_head(camera_hidden[:, s:].float())
        return {
            "local_points": torch.cat([xy * z, z], dim=-1),
            "conf": conf,
            "rot9": rot9.reshape(b, n, 9),
            "trans": trans.reshape(b, n, 3),
            "dino_patch_tokens": tokens.reshape(b, n, *tokens.shape[1:]),
        }

    def forward(self, images: Tensor, trace: Trace | None = None) -> dict[str, Tensor]:
        """``images [B,N,3,H,W]`` in [0, 1] -> ``points, local_points [B,N,H,W,3]``,
        ``conf [B,N,H,W,1]`` (logit), ``camera_poses [B,N,4,4]`` (camera-to-world),
        ``dino_patch_tokens [B,N,P,C]``.  ``trace``: a dict that receives the golden
        intermediates (``decoder_layer_XX`` ...)."""
        return assemble(self.forward_raw(images, trace))

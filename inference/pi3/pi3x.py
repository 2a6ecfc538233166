"""The π³X network (``yyfz/Pi3``'s ``Pi3X``) with the official parameter names.

Differences from π³ (:mod:`inference.pi3.model`):

* point and confidence heads are MoGe-style ConvHeads (x8 upsampling, bilinear to ``H x W``,
  UV channels); the raw depth is clamped at 15 before ``exp``; ``rays = normalize(x, y, 1)``;
* a metric token cross-attends to all views' decoder tokens (``ContextDecoder``) and
  ``metric = exp(linear)`` per batch element multiplies local points, world points and pose
  translations;
* optional conditions (``multimodal``): ray embedding (2-channel patch embed) and depth
  encoder (a DINO copy on ``[depth, valid]``) added to the DINO tokens, and poses injected
  after decoder layers 1, 9, 17, 25, 33 through PRoPE attention, only for the posed views;
  see :mod:`inference.pi3.conditioning` for the normalisation.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..dino import PatchEmbed
from .conditioning import Conditions, PreparedConditions, prepare_conditions
from .config import Pi3Config
from .decoders import ContextDecoder, PoseInjectBlock, TransformerDecoder
from .heads import CameraHead, ConvHead
from .model import Pi3Base, Trace, assemble, build_dino

__all__ = ["Pi3X"]

_CONV_HEAD_CHUNK = 64  # views per ConvHead pass (bounds memory; per-view maths, same result)


class Pi3X(Pi3Base):
    """Clean-room π³X; ``state_dict()`` equals the official checkpoint's names and shapes
    (``multimodal=False`` in the config drops the conditioning branches, as upstream's
    ``disable_multimodal()``)."""

    def __init__(self, config: Pi3Config | None = None) -> None:
        cfg = config or Pi3Config.pi3x()
        if cfg.variant != "pi3x":
            raise ValueError(f"Pi3X needs a 'pi3x' config, got variant {cfg.variant!r} (use inference.pi3.model.Pi3)")
        super().__init__(cfg)
        heads = cfg.heads(cfg.head_width)
        if cfg.multimodal:
            self.depth_encoder = build_dino(cfg, in_chans=2)
            self.depth_emb = nn.Parameter(torch.zeros(1, 1, cfg.dim))
            self.ray_embed = PatchEmbed(cfg.patch_size, cfg.dim, in_chans=2)
            self.pose_inject_blk = nn.ModuleList(
                PoseInjectBlock(cfg.dim, cfg.heads(cfg.dim)) for _ in cfg.inject_layers
            )
        self.point_decoder = TransformerDecoder(2 * cfg.dim, cfg.head_width, cfg.point_out, cfg.head_depth, heads)
        self.point_head = ConvHead(cfg.dim, (2, 1), cfg.conv_upsample, cfg.conv_last, patch_size=cfg.patch_size)
        self.camera_decoder = TransformerDecoder(2 * cfg.dim, cfg.head_width, cfg.camera_out, cfg.head_depth, heads)
        self.camera_head = CameraHead(cfg.camera_out)
        self.metric_token = nn.Parameter(torch.zeros(1, 1, 2 * cfg.dim))
        self.metric_decoder = ContextDecoder(
            2 * cfg.dim, cfg.metric_width, cfg.metric_width, cfg.head_depth, cfg.heads(cfg.metric_width)
        )
        self.metric_head = nn.Linear(cfg.metric_width, 1)
        self.conf_decoder = TransformerDecoder(2 * cfg.dim, cfg.head_width, cfg.point_out, cfg.head_depth, heads)
        self.conf_head = ConvHead(cfg.dim, (1,), cfg.conv_upsample, cfg.conv_last, patch_size=cfg.patch_size)
        self._register_normalisation()

    # ---- conditioning ----------------------------------------------------------------------
    # ``static_graph`` (set by the ONNX exporter): no data-dependent branch; every branch
    # runs and is multiplied by its mask, and the pose attention mask is additive (0 / -1e4:
    # exp underflows to exactly 0 for a masked score, and a fully masked row -- an unposed
    # view, whose delta is then zeroed -- stays finite).  Same outputs, more work.
    static_graph: bool = False

    def _add_conditions(self, tokens: Tensor, prep: PreparedConditions, trace: Trace | None) -> Tensor:
        """DINO tokens ``[V, P, C]`` + ray and depth embeddings of the views that use them."""
        if trace is not None:
            trace.update(encode_poses_normalized=prep.poses, encode_norm_factor=prep.norm_factor)
        if self.static_graph or bool(prep.mask_depth.any()):
            depth_tokens = self.depth_encoder(prep.depth_input)["x_norm_patchtokens"]
            if trace is not None:
                trace["depth_encoder_patch_tokens"] = depth_tokens
            tokens = tokens + (depth_tokens + self.depth_emb) * prep.mask_depth.reshape(-1, 1, 1).to(tokens.dtype)
        if self.static_graph or bool(prep.mask_ray.any()):
            ray_tokens = self.ray_embed(prep.rays_xy)
            if trace is not None:
                trace["ray_embed_out"] = ray_tokens
            tokens = tokens + ray_tokens * prep.mask_ray.reshape(-1, 1, 1).to(tokens.dtype)
        return tokens

    def _pose_injector(
        self, prep: PreparedConditions, views: int, patches_hw: tuple[int, int], trace: Trace | None
    ):  # a closure for Pi3Base.decode
        mask = prep.mask_pose  # [B, N]
        if not self.static_graph and not bool(mask.any()):
            return None
        b = mask.shape[0]
        p = patches_hw[0] * patches_hw[1]
        attn_mask = None
        if self.static_graph:
            m = mask.to(torch.float32)
            pair = m[:, :, None] * m[:, None, :]  # [B, N, N]
            pair = pair[:, :, None, :, None].expand(b, views, p, views, p).reshape(b, 1, views * p, views * p)
            attn_mask = (pair - 1.0) * 1e4
        elif not bool(mask.all()):  # views attend only to posed views (never built when all are posed)
            pair = mask[:, :, None] & mask[:, None, :]
            attn_mask = pair.repeat_interleave(p, dim=1).repeat_interleave(p, dim=2)[:, None]
        blocks = dict(zip(self.config.inject_layers, self.pose_inject_blk))
        s = self.patch_start

        def inject(layer: int, hidden: Tensor) -> Tensor:
            blk = blocks.get(layer)
            if blk is None:
                return hidden
            h = hidden.reshape(b, views, -1, hidden.shape[-1])
            delta = blk(h[:, :, s:].reshape(b, views * p, -1), prep.poses, patches_hw, attn_mask)
            if trace is not None:
                trace[f"pose_inject_{self.config.inject_layers.index(layer)}_out"] = delta
            delta = delta.reshape(b, views, p, -1) * mask.view(b, views, 1, 1).to(delta.dtype)
            return torch.cat([h[:, :, :s], h[:, :, s:] + delta], dim=2).reshape(hidden.shape)

        return inject

    # ---- forward -----------------------------------------------------------------------------
    def _conv_head(self, head: ConvHead, tokens: Tensor, patches_hw: tuple[int, int]) -> list[Tensor]:
        if self.static_graph:  # exported graph: one pass (a traced chunk loop would be frozen)
            return head(tokens, patches_hw)
        parts = [
            head(tokens[i : i + _CONV_HEAD_CHUNK], patches_hw) for i in range(0, tokens.shape[0], _CONV_HEAD_CHUNK)
        ]
        return [torch.cat([p[j] for p in parts], dim=0) for j in range(len(parts[0]))]

    def forward_raw(
        self, images: Tensor, conditions: Conditions | None = None, trace: Trace | None = None
    ) -> dict[str, Tensor]:
        """Everything up to (not including) the SVD: see :func:`~inference.pi3.model.assemble`.

        ``conditions=None`` skips the conditioning preamble altogether; ``Conditions()`` (no
        condition given) runs it as upstream does and gives the same outputs.
        """
        prep = None
        if conditions is not None:
            if not self.config.multimodal:
                raise ValueError("this Pi3X was built without its multimodal branches: conditions cannot be used")
            b, n, _, h, w = images.shape
            prep = prepare_conditions(conditions, b, n, h, w, images.device)
        return self.forward_prepared(images, prep, trace)

    def forward_prepared(
        self, images: Tensor, prep: PreparedConditions | None, trace: Trace | None = None
    ) -> dict[str, Tensor]:
        """:meth:`forward_raw` with the conditions already prepared (the ONNX graph's body)."""
        b, n, _, h, w = images.shape
        phw = self.patches_hw(images)
        rope = self.rope(phw, images.device)
        tokens = self.encode_images(images, trace)
        dino_tokens = tokens
        inject = None
        if prep is not None:
            tokens = self._add_conditions(tokens, prep, trace)
            inject = self._pose_injector(prep, n, phw, trace)
        if trace is not None:
            trace["encode_hidden"] = tokens
        hidden = self.decode(tokens, n, phw, rope, trace, inject)

        s = self.patch_start
        point_hidden = self.point_decoder(hidden, rope)
        camera_hidden = self.camera_decoder(hidden, rope)
        t, c2 = hidden.shape[1], hidden.shape[2]
        metric_hidden = self.metric_decoder(
            self.metric_token.expand(b, -1, -1), hidden.reshape(b, n * t, c2), self.origin_rope(images.device), rope
        )
        conf_hidden = self.conf_decoder(hidden, rope)
        if trace is not None:
            trace.update(
                point_decoder_out=point_hidden,
                camera_decoder_out=camera_hidden,
                metric_decoder_out=metric_hidden,
                conf_decoder_out=conf_hidden,
            )

        xy, z = self._conv_head(self.point_head, point_hidden[:, s:].float(), phw)
        xy = xy.permute(0, 2, 3, 1).reshape(b, n, h, w, 2)
        z = torch.exp(z.clamp(max=15.0)).permute(0, 2, 3, 1).reshape(b, n, h, w, 1)
        conf = self._conv_head(self.conf_head, conf_hidden[:, s:].float(), phw)[0]
        rot9, trans = self.camera_head(camera_hidden[:, s:].float())
        return {
            "local_points": torch.cat([xy * z, z], dim=-1),
            "rays": F.normalize(torch.cat([xy, torch.ones_like(z)], dim=-1), dim=-1),
            "conf": conf.permute(0, 2, 3, 1).reshape(b, n, h, w, 1),
            "rot9": rot9.reshape(b, n, 9),
            "trans": trans.reshape(b, n, 3),
            "metric": self.metric_head(metric_hidden.float()).reshape(b).exp(),
            "dino_patch_tokens": dino_tokens.reshape(b, n, *dino_tokens.shape[1:]),
        }

    def forward(
        self, images: Tensor, conditions: Conditions | None = None, trace: Trace | None = None
    ) -> dict[str, Tensor]:
        """``images [B,N,3,H,W]`` in [0, 1], optional :class:`Conditions` -> the π³ outputs
        (metric-scaled) plus ``rays [B,N,H,W,3]`` and ``metric [B]``."""
        return assemble(self.forward_raw(images, conditions, trace))

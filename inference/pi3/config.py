"""Sizes of the π³ and π³X networks (official ``Pi3()`` and ``Pi3X()`` and the tiny golden ones).

One :class:`Pi3Config` describes both variants: ``variant="pi3"`` builds
:class:`inference.pi3.model.Pi3`, ``variant="pi3x"`` builds :class:`inference.pi3.pi3x.Pi3X`.
The presets :meth:`Pi3Config.pi3` and :meth:`Pi3Config.pi3x` are the released models
(``yyfz233/Pi3``: 958,696,732 parameters; ``yyfz233/Pi3X``: 1,360,032,433 with the
multimodal branches); :meth:`Pi3Config.from_json` reads the golden ``tiny_config.json``.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from typing import Any, Literal

__all__ = ["Pi3Config", "Variant", "OFFICIAL_INJECT_AFTER"]

Variant = Literal["pi3", "pi3x"]

# π³X injects the pose condition after these decoder layers (official ``decode``).
OFFICIAL_INJECT_AFTER: tuple[int, ...] = (1, 9, 17, 25, 33)


@dataclasses.dataclass(frozen=True)
class Pi3Config:
    """Constructor sizes.

    Shared by both variants:
        variant: ``"pi3"`` or ``"pi3x"``.
        patch_size: ViT patch (14); image height and width must be multiples of it.
        img_size: nominal size of the DINO position-embedding grid (518 -> 37 x 37 cells).
        dim: width of the DINOv2 encoder and of the multi-view decoder (1024; no projection
            between them).
        enc_depth: DINOv2 blocks (24, ViT-L/14 with 4 registers).
        dec_depth: multi-view decoder blocks (36), even ones attend within a frame, odd ones
            across all frames.
        num_register_tokens: decoder register tokens per frame (5), position (0, 0).
        head_width: width of the point / confidence / camera transformer decoders (1024).
        head_depth: blocks of each of those decoders (5).
        point_out: output width of the point and confidence decoders (1024).
        camera_out: output width of the camera decoder = camera head width (512).
        attn_head_dim: channels per attention head, in every attention of the network (64;
            the tiny golden models use 16).
        rope_freq: base frequency of the 2-D RoPE (100).

    π³X only:
        metric_width: width of the metric-token cross-attention decoder (512).
        conv_upsample: channels of the ConvHead's three x2 upsampling stages (256, 128, 64).
        conv_last: channels of the ConvHead's output convolution (32).
        multimodal: build the conditioning branches (depth encoder, ray embedding, pose
            injection); without them the checkpoint's multimodal entries are not expected.
        inject_after: decoder layers after which the pose condition is injected (official
            1, 9, 17, 25, 33; those ``< dec_depth`` are used, one PoseInjectBlock each).
    """

    variant: Variant = "pi3"
    patch_size: int = 14
    img_size: int = 518
    dim: int = 1024
    enc_depth: int = 24
    dec_depth: int = 36
    num_register_tokens: int = 5
    head_width: int = 1024
    head_depth: int = 5
    point_out: int = 1024
    camera_out: int = 512
    attn_head_dim: int = 64
    rope_freq: float = 100.0
    metric_width: int = 512
    conv_upsample: tuple[int, int, int] = (256, 128, 64)
    conv_last: int = 32
    multimodal: bool = True
    inject_after: tuple[int, ...] = OFFICIAL_INJECT_AFTER

    def __post_init__(self) -> None:
        problems = []
        if self.variant not in ("pi3", "pi3x"):
            problems.append(f"variant must be 'pi3' or 'pi3x', got {self.variant!r}")
        widths = {"dim": self.dim, "head_width": self.head_width, "camera_out": self.camera_out}
        if self.variant == "pi3x":
            widths["metric_width"] = self.metric_width
        for name, width in widths.items():
            if name != "camera_out" and width % self.attn_head_dim:
                problems.append(f"{name} {width} is not a multiple of attn_head_dim {self.attn_head_dim}")
        if self.attn_head_dim % 8:
            problems.append(f"attn_head_dim {self.attn_head_dim} must be a multiple of 8 (2-D RoPE, PRoPE)")
        if self.dec_depth < 2 or self.dec_depth % 2:
            problems.append(f"dec_depth {self.dec_depth} must be even and >= 2 (frame/global pairs)")
        if self.variant == "pi3x" and self.point_out != self.dim:
            problems.append(f"pi3x: point_out {self.point_out} must equal dim {self.dim} (ConvHead input)")
        if problems:
            raise ValueError("invalid Pi3Config: " + "; ".join(problems))

    # ---- derived sizes -------------------------------------------------------------------
    def heads(self, width: int) -> int:
        """Attention heads of a ``width``-wide attention (``width / attn_head_dim``)."""
        return width // self.attn_head_dim

    @property
    def inject_layers(self) -> tuple[int, ...]:
        """Decoder layers followed by a pose injection (π³X with ``multimodal``)."""
        if self.variant != "pi3x" or not self.multimodal:
            return ()
        return tuple(i for i in self.inject_after if i < self.dec_depth)

    # ---- presets -------------------------------------------------------------------------
    @classmethod
    def pi3(cls) -> Pi3Config:
        """The released π³ (``Pi3(pos_type='rope100', decoder_size='large')``)."""
        return cls(variant="pi3")

    @classmethod
    def pi3x(cls, multimodal: bool = True) -> Pi3Config:
        """The released π³X (``Pi3X(use_multimodal=multimodal)``)."""
        return cls(variant="pi3x", multimodal=multimodal)

    @classmethod
    def preset(cls, name: str) -> Pi3Config:
        """``"pi3"`` or ``"pi3x"``."""
        if name == "pi3":
            return cls.pi3()
        if name == "pi3x":
            return cls.pi3x()
        raise ValueError(f"unknown π³ preset {name!r}: use 'pi3' or 'pi3x'")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], variant: Variant) -> Pi3Config:
        """Builds a config from the golden ``tiny_config.json`` (its ``tiny_ctor`` section).

        ``tiny_ctor`` holds ``dim, enc_depth, enc_img_size, dec_depth, head_dim`` (the head
        decoders' WIDTH), ``head_depth, pt_out, cam_out, metric_dim, up, last_conv,
        n_inject``; the golden models use 16 channels per attention head everywhere.
        """
        t: Mapping[str, Any] = d.get("tiny_ctor", d)
        n_inject = int(t.get("n_inject", len(OFFICIAL_INJECT_AFTER)))
        inject_after = OFFICIAL_INJECT_AFTER[:n_inject]
        cfg = cls(
            variant=variant,
            img_size=int(t["enc_img_size"]),
            dim=int(t["dim"]),
            enc_depth=int(t["enc_depth"]),
            dec_depth=int(t["dec_depth"]),
            head_width=int(t["head_dim"]),
            head_depth=int(t["head_depth"]),
            point_out=int(t["pt_out"]),
            camera_out=int(t["cam_out"]),
            attn_head_dim=int(t.get("attn_head_dim", 16)),
            metric_width=int(t.get("metric_dim", 512)),
            conv_upsample=tuple(int(x) for x in t.get("up", (256, 128, 64))),  # type: ignore[arg-type]
            conv_last=int(t.get("last_conv", 32)),
            inject_after=inject_after,
        )
        if variant == "pi3x" and len(cfg.inject_layers) != n_inject:
            raise ValueError(
                f"tiny_config: n_inject={n_inject} but decoder depth {cfg.dec_depth} leaves "
                f"{len(cfg.inject_layers)} injection points among {inject_after}"
            )
        return cfg

    @classmethod
    def from_json(cls, path: str | os.PathLike[str], variant: Variant) -> Pi3Config:
        """Reads a golden ``tiny_config.json`` (see :meth:`from_dict`)."""
        with open(path, encoding="utf-8") as f:
            return cls.from_dict(json.load(f), variant)

    def to_dict(self) -> dict[str, Any]:
        """The fields as a plain (JSON-serialisable) dict; :meth:`from_fields` inverts it."""
        return dataclasses.asdict(self)

    @classmethod
    def from_fields(cls, d: Mapping[str, Any]) -> Pi3Config:
        """Inverse of :meth:`to_dict` (also after a JSON round trip: lists become tuples)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown Pi3Config fields {unknown}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

"""Sizes of the Depth Anything 3 networks: :class:`DA3Config` (one any-view or metric/mono
network) and :class:`NestedDA3Config` (DA3-Nested = any-view giant + metric large).

The fields mirror the official yaml presets (``depth_anything_3/configs/*.yaml``, the
``resolved_config`` of the manifests in ``shared/golden/da3``), plus the ViT sizes that the
official code derives from the ViT name (``vits``/``vitb``/``vitl``/``vitg``) and that a tiny
test configuration overrides (``spec`` in ``tiny_config.json``).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from typing import Any

__all__ = ["DA3Config", "NestedDA3Config", "PRESETS", "VIT_SIZES", "preset_config"]

# ViT name -> (embed_dim, depth, num_heads): the standard DINOv2 ViT-S/B/L/g sizes.
VIT_SIZES: dict[str, tuple[int, int, int]] = {
    "vits": (384, 12, 6),
    "vitb": (768, 12, 12),
    "vitl": (1024, 24, 16),
    "vitg": (1536, 40, 24),
}
_HEADS = {"DualDPT": "dualdpt", "DPT": "dpt"}


@dataclasses.dataclass(frozen=True)
class DA3Config:
    """Constructor sizes of :class:`inference.da3.model.DA3Net`.

    Backbone (DINOv2 with cross-view attention):
        vit: ``vits``/``vitb``/``vitl``/``vitg``; ``vitg`` uses the SwiGLU feed-forward.
        embed_dim, depth, num_heads, mlp_ratio: ViT sizes (``C``, blocks, heads, MLP ratio).
        img_size, patch_size: the learned position grid is ``img_size // patch_size`` (37).
        out_layers: the four blocks whose outputs feed the head (and the camera decoder).
        alt_start: first block with cross-view attention (odd blocks from here are global,
            the camera token enters here, the reference view is chosen one block before);
            -1: a plain single-view ViT (metric / mono models).
        qknorm_start, rope_start: first block with q/k LayerNorm and with 2-D RoPE (-1: none).
        rope_freq: RoPE base frequency.
        cat_token: the head gets ``concat(local-stream tokens, tokens)`` (width ``2C``).
    Head:
        head: ``"dualdpt"`` (depth + ray, any-view) or ``"dpt"`` (depth + sky, metric/mono).
        head_dim_in, head_output_dim, head_features, head_out_channels: DPT sizes.
    Cameras:
        camera: has the camera encoder and decoder (any-view presets).
        cam_enc_heads: attention heads of the camera-encoder trunk (16 in every preset).
    gs_output_dim: width of the 3D-Gaussian head of DA3-Giant (0: none). Its weights load so
        that a released checkpoint is accepted strictly; this package never runs it.
    """

    vit: str = "vitl"
    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    img_size: int = 518
    patch_size: int = 14
    out_layers: tuple[int, ...] = (11, 15, 19, 23)
    alt_start: int = 8
    qknorm_start: int = 8
    rope_start: int = 8
    rope_freq: float = 100.0
    cat_token: bool = True
    head: str = "dualdpt"
    head_dim_in: int = 2048
    head_output_dim: int = 2
    head_features: int = 256
    head_out_channels: tuple[int, int, int, int] = (256, 512, 1024, 1024)
    camera: bool = True
    cam_enc_heads: int = 16
    gs_output_dim: int = 0

    def __post_init__(self) -> None:
        if self.vit not in VIT_SIZES:
            raise ValueError(f"DA3Config.vit: {self.vit!r} is not one of {sorted(VIT_SIZES)}")
        if self.head not in ("dualdpt", "dpt"):
            raise ValueError(f"DA3Config.head: {self.head!r} is not 'dualdpt' or 'dpt'")
        if len(self.out_layers) != 4 or not all(0 <= i < self.depth for i in self.out_layers):
            raise ValueError(f"DA3Config.out_layers: need 4 block indices in [0, {self.depth}), got {self.out_layers}")
        if self.alt_start == 0 or self.alt_start >= self.depth:
            raise ValueError(f"DA3Config.alt_start: must be -1 or in [1, {self.depth}), got {self.alt_start}")
        if self.embed_dim % self.num_heads:
            raise ValueError(f"DA3Config: embed_dim {self.embed_dim} is not divisible by num_heads {self.num_heads}")
        if self.camera and self.alt_start == -1:
            raise ValueError("DA3Config: the camera encoder/decoder need cross-view attention (alt_start >= 1)")

    @property
    def swiglu(self) -> bool:
        """Whether the ViT blocks use the SwiGLU feed-forward (``vitg``)."""
        return self.vit == "vitg"

    @property
    def token_dim(self) -> int:
        """Width of the tokens given to the head and the camera decoder (``2C`` with cat_token)."""
        return 2 * self.embed_dim if self.cat_token else self.embed_dim

    @classmethod
    def from_object_config(cls, cfg: Mapping[str, Any], vit: Mapping[str, Any] | None = None) -> DA3Config:
        """From an official ``create_object`` config of ``DepthAnything3Net`` (the yaml presets,
        ``resolved_config`` of the manifests, ``create_object_config_main`` of tiny_config.json).

        Args:
            cfg: mapping with ``net``, ``head`` and optionally ``cam_enc``, ``cam_dec``, ``gs_head``.
            vit: optional ViT size override ``{embed_dim, depth, num_heads, mlp_ratio}`` (the
                ``spec`` of tiny_config.json); default: the standard size of ``net.name``.
        """
        net, head = cfg["net"], cfg["head"]
        name = str(net["name"])
        if name not in VIT_SIZES:
            raise ValueError(f"DA3 config: unknown ViT name {name!r} (expected one of {sorted(VIT_SIZES)})")
        dim, depth, heads = VIT_SIZES[name]
        mlp_ratio = 4.0
        if vit is not None:
            dim, depth, heads = int(vit["embed_dim"]), int(vit["depth"]), int(vit["num_heads"])
            mlp_ratio = float(vit.get("mlp_ratio", 4.0))
        head_cls = str(head.get("__object__", {}).get("name", "DualDPT"))
        if head_cls not in _HEADS:
            raise ValueError(f"DA3 config: unsupported head class {head_cls!r} (expected DualDPT or DPT)")
        cam_enc = cfg.get("cam_enc")
        gs = cfg.get("gs_head") if cfg.get("gs_adapter") is not None else None
        return cls(
            vit=name,
            embed_dim=dim,
            depth=depth,
            num_heads=heads,
            mlp_ratio=mlp_ratio,
            out_layers=tuple(int(i) for i in net["out_layers"]),
            alt_start=int(net.get("alt_start", -1)),
            qknorm_start=int(net.get("qknorm_start", -1)),
            rope_start=int(net.get("rope_start", -1)),
            cat_token=bool(net.get("cat_token", True)),
            head=_HEADS[head_cls],
            head_dim_in=int(head["dim_in"]),
            head_output_dim=int(head.get("output_dim", 2 if head_cls == "DualDPT" else 1)),
            head_features=int(head.get("features", 256)),
            head_out_channels=tuple(int(c) for c in head.get("out_channels", (256, 512, 1024, 1024))),  # type: ignore[arg-type]
            camera=cfg.get("cam_dec") is not None,
            cam_enc_heads=int(cam_enc.get("num_heads", 16)) if cam_enc is not None else 16,
            gs_output_dim=int(gs["output_dim"]) if gs is not None else 0,
        )

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> DA3Config:
        """The any-view model of a ``tiny_config.json`` (``create_object_config_main`` + ``spec.main.vit``)."""
        d = _read_json(path)
        if "create_object_config_main" not in d:
            raise ValueError(f"{os.fspath(path)}: no 'create_object_config_main' section (not a DA3 config)")
        return cls.from_object_config(d["create_object_config_main"], d.get("spec", {}).get("main", {}).get("vit"))


@dataclasses.dataclass(frozen=True)
class NestedDA3Config:
    """DA3-Nested: an any-view model (``da3``) and a metric model (``da3_metric``) on the same images."""

    anyview: DA3Config
    metric: DA3Config

    @classmethod
    def from_object_config(cls, cfg: Mapping[str, Any], vits: Mapping[str, Any] | None = None) -> NestedDA3Config:
        vits = vits or {}
        return cls(
            DA3Config.from_object_config(cfg["anyview"], (vits.get("anyview") or {}).get("vit")),
            DA3Config.from_object_config(cfg["metric"], (vits.get("metric") or {}).get("vit")),
        )

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> NestedDA3Config:
        """The nested model of a ``tiny_config.json`` (``create_object_config_nested`` + ``spec.nested``)."""
        d = _read_json(path)
        if "create_object_config_nested" not in d:
            raise ValueError(f"{os.fspath(path)}: no 'create_object_config_nested' section")
        return cls.from_object_config(d["create_object_config_nested"], d.get("spec", {}).get("nested"))


def _read_json(path: str | os.PathLike[str]) -> dict[str, Any]:
    with open(path, encoding="utf-8") as f:
        d = json.load(f)
    if not isinstance(d, dict):
        raise ValueError(f"{os.fspath(path)}: not a JSON object")
    return d


def _anyview(
    vit: str,
    out_layers: tuple[int, ...],
    alt: int,
    features: int,
    out_channels: tuple[int, int, int, int],
    gs_output_dim: int = 0,
) -> DA3Config:
    dim, depth, heads = VIT_SIZES[vit]
    return DA3Config(
        vit=vit,
        embed_dim=dim,
        depth=depth,
        num_heads=heads,
        out_layers=out_layers,
        alt_start=alt,
        qknorm_start=alt,
        rope_start=alt,
        cat_token=True,
        head="dualdpt",
        head_dim_in=2 * dim,
        head_output_dim=2,
        head_features=features,
        head_out_channels=out_channels,
        camera=True,
        gs_output_dim=gs_output_dim,
    )


_METRIC_LARGE = DA3Config(
    vit="vitl",
    out_layers=(4, 11, 17, 23),
    alt_start=-1,
    qknorm_start=-1,
    rope_start=-1,
    cat_token=False,
    head="dpt",
    head_dim_in=1024,
    head_output_dim=1,
    head_features=256,
    head_out_channels=(256, 512, 1024, 1024),
    camera=False,
)
_GIANT = _anyview("vitg", (19, 27, 33, 39), 13, 256, (256, 512, 1024, 1024), gs_output_dim=38)

# The official presets (configs/<name>.yaml at commit 2c21ea8; == the manifests' resolved_config).
PRESETS: dict[str, DA3Config | NestedDA3Config] = {
    "da3-small": _anyview("vits", (5, 7, 9, 11), 4, 64, (48, 96, 192, 384)),
    "da3-base": _anyview("vitb", (5, 7, 9, 11), 4, 128, (96, 192, 384, 768)),
    "da3-large": _anyview("vitl", (11, 15, 19, 23), 8, 256, (256, 512, 1024, 1024)),
    "da3-giant": _GIANT,
    "da3metric-large": _METRIC_LARGE,
    "da3mono-large": _METRIC_LARGE,
    "da3nested-giant-large": NestedDA3Config(_GIANT, _METRIC_LARGE),
}


def preset_config(name: str) -> DA3Config | NestedDA3Config:
    """The configuration of an official preset (``da3-small`` ... ``da3nested-giant-large``)."""
    key = name.lower()
    if key not in PRESETS:
        raise ValueError(f"unknown DA3 preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[key]

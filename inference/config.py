"""Sizes of the VGGT architecture.

The defaults are the released VGGT-1B model (``facebook/VGGT-1B``).  Every size that the
official constructors expose and that a smaller test configuration may change is a field, so
one :class:`VGGTConfig` describes both the real model and the tiny golden configuration
(``tiny_config.json``, see :meth:`VGGTConfig.from_json`).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["VGGTConfig"]


@dataclasses.dataclass(frozen=True)
class VGGTConfig:
    """Constructor sizes of :class:`inference.model.VGGT`.

    Aggregator (alternating frame/global attention):
        img_size: nominal image size of the DINO position embedding grid
            (``img_size // patch_size`` = 37 cells per side for 518).
        patch_size: ViT patch size; image height and width must be multiples of it.
        embed_dim: token width ``C`` of the aggregator (and of the DINO ViT).
        depth: number of frame blocks (= number of global blocks).
        num_heads: attention heads of the aggregator blocks.
        mlp_ratio: hidden width of the block MLPs as a multiple of ``embed_dim``.
        num_register_tokens: register tokens per frame (aggregator and DINO ViT).
        qk_norm: LayerNorm on queries and keys (per head) in the aggregator blocks.
        rope_freq: base frequency of the 2-D rotary position embedding (<= 0 disables RoPE).
        init_values: LayerScale initial value of the aggregator blocks (init only).
        aa_order: order of the attention types inside one alternating step.
        aa_block_size: blocks of one type run back to back before switching type.

    DINOv2 patch embedding ViT (``dinov2_vitl14_reg`` in the real model):
        dino_depth, dino_num_heads, dino_mlp_ratio: its depth, heads and MLP ratio; its width
            is ``embed_dim``.

    Camera head:
        camera_trunk_depth, camera_num_heads, camera_mlp_ratio: its transformer trunk, which
            runs on the ``2 * embed_dim`` wide camera tokens.
        camera_iterations: refinement iterations (the official forward default is 4).

    Depth head (DPT):
        dpt_features: width of the fusion ("scratch") layers.
        dpt_out_channels: widths of the four projected token maps.
        dpt_intermediate_layer_idx: which aggregator outputs feed the four DPT levels.
        dpt_frames_chunk_size: frames per DPT pass in eager torch (bounds memory);
            ``None`` processes all frames at once.
    """

    img_size: int = 518
    patch_size: int = 14
    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    num_register_tokens: int = 4
    qk_norm: bool = True
    rope_freq: float = 100.0
    init_values: float = 0.01
    aa_order: tuple[str, ...] = ("frame", "global")
    aa_block_size: int = 1

    dino_depth: int = 24
    dino_num_heads: int = 16
    dino_mlp_ratio: float = 4.0

    camera_trunk_depth: int = 4
    camera_num_heads: int = 16
    camera_mlp_ratio: float = 4.0
    camera_iterations: int = 4

    dpt_features: int = 256
    dpt_out_channels: tuple[int, int, int, int] = (256, 512, 1024, 1024)
    dpt_intermediate_layer_idx: tuple[int, int, int, int] = (4, 11, 17, 23)
    dpt_frames_chunk_size: int | None = 8

    def __post_init__(self) -> None:
        problems = []
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if (
                f.name in _POSITIVE
                and value is not None
                and not (isinstance(value, (int, float)) and not isinstance(value, bool) and value >= _POSITIVE[f.name])
            ):
                problems.append(f"{f.name} must be >= {_POSITIVE[f.name]}, got {value!r}")
        if problems:  # the divisibility checks below would divide by zero or mislead
            raise ValueError("invalid VGGTConfig: " + "; ".join(problems))
        if self.embed_dim % self.num_heads:
            problems.append(f"embed_dim {self.embed_dim} not divisible by num_heads {self.num_heads}")
        if self.embed_dim % self.dino_num_heads:
            problems.append(f"embed_dim {self.embed_dim} not divisible by dino_num_heads {self.dino_num_heads}")
        if (2 * self.embed_dim) % self.camera_num_heads:
            problems.append(f"2*embed_dim not divisible by camera_num_heads {self.camera_num_heads}")
        if self.rope_freq > 0 and (self.embed_dim // self.num_heads) % 4:
            problems.append("RoPE 2D needs a head dim divisible by 4")
        if sorted(self.aa_order) != ["frame", "global"]:
            problems.append(f"aa_order must be a permutation of frame/global, got {self.aa_order}")
        if self.depth % self.aa_block_size:
            problems.append(f"depth {self.depth} not divisible by aa_block_size {self.aa_block_size}")
        if any(c < 1 for c in self.dpt_out_channels):
            problems.append(f"dpt_out_channels must be >= 1, got {self.dpt_out_channels}")
        if len(self.dpt_out_channels) != 4 or len(self.dpt_intermediate_layer_idx) != 4:
            problems.append("the DPT head needs exactly four out_channels and intermediate layers")
        if any(not 0 <= i < self.depth for i in self.dpt_intermediate_layer_idx):
            problems.append(f"dpt_intermediate_layer_idx {self.dpt_intermediate_layer_idx} outside [0, {self.depth})")
        if problems:
            raise ValueError("invalid VGGTConfig: " + "; ".join(problems))

    @property
    def patch_start_idx(self) -> int:
        """Index of the first patch token in an aggregator frame (1 camera + registers)."""
        return 1 + self.num_register_tokens

    @property
    def pos_embed_grid(self) -> int:
        """Cells per side of the DINO position embedding (37 for 518/14)."""
        return self.img_size // self.patch_size

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> VGGTConfig:
        """Builds a config from the golden ``tiny_config.json`` layout.

        The layout has ``aggregator_kwargs``, ``patch_embed_vit``, ``camera_head_kwargs``,
        ``camera_head_num_iterations``, ``depth_head_kwargs`` and
        ``depth_head_frames_chunk_size``; missing sections keep the 1B defaults.
        """
        _check_layout(d)
        agg: Mapping[str, Any] = d.get("aggregator_kwargs", {})
        vit: Mapping[str, Any] = d.get("patch_embed_vit", {})
        cam: Mapping[str, Any] = d.get("camera_head_kwargs", {})
        dpt: Mapping[str, Any] = d.get("depth_head_kwargs", {})
        base = cls()
        embed_dim = int(agg.get("embed_dim", base.embed_dim))
        _check_fixed(agg, {"qkv_bias": True, "proj_bias": True, "ffn_bias": True})
        _check_fixed(
            vit,
            {
                "embed_dim": embed_dim,
                "num_register_tokens": agg.get("num_register_tokens", 4),
                "interpolate_antialias": True,
                "interpolate_offset": 0.0,
                "ffn_layer": "mlp",
                "qk_norm": False,
                "layernorm_eps": 1e-6,
            },
        )
        _check_fixed(
            cam,
            {
                "dim_in": 2 * embed_dim,
                "pose_encoding_type": "absT_quaR_FoV",
                "trans_act": "linear",
                "quat_act": "linear",
                "fl_act": "relu",
            },
        )
        _check_fixed(
            dpt,
            {
                "dim_in": 2 * embed_dim,
                "output_dim": 2,
                "activation": "exp",
                "conf_activation": "expp1",
                "pos_embed": True,
                "feature_only": False,
                "down_ratio": 1,
                "patch_size": agg.get("patch_size", base.patch_size),
            },
        )
        chunk = d.get("depth_head_frames_chunk_size", base.dpt_frames_chunk_size)
        return cls(
            img_size=int(agg.get("img_size", base.img_size)),
            patch_size=int(agg.get("patch_size", base.patch_size)),
            embed_dim=embed_dim,
            depth=int(agg.get("depth", base.depth)),
            num_heads=int(agg.get("num_heads", base.num_heads)),
            mlp_ratio=float(agg.get("mlp_ratio", base.mlp_ratio)),
            num_register_tokens=int(agg.get("num_register_tokens", base.num_register_tokens)),
            qk_norm=bool(agg.get("qk_norm", base.qk_norm)),
            rope_freq=float(agg.get("rope_freq", base.rope_freq)),
            init_values=float(agg.get("init_values", base.init_values)),
            aa_order=tuple(agg.get("aa_order", base.aa_order)),
            aa_block_size=int(agg.get("aa_block_size", base.aa_block_size)),
            dino_depth=int(vit.get("depth", base.dino_depth)),
            dino_num_heads=int(vit.get("num_heads", base.dino_num_heads)),
            dino_mlp_ratio=float(vit.get("mlp_ratio", base.dino_mlp_ratio)),
            camera_trunk_depth=int(cam.get("trunk_depth", base.camera_trunk_depth)),
            camera_num_heads=int(cam.get("num_heads", base.camera_num_heads)),
            camera_mlp_ratio=float(cam.get("mlp_ratio", base.camera_mlp_ratio)),
            camera_iterations=int(d.get("camera_head_num_iterations", base.camera_iterations)),
            dpt_features=int(dpt.get("features", base.dpt_features)),
            dpt_out_channels=_four(dpt.get("out_channels", base.dpt_out_channels)),
            dpt_intermediate_layer_idx=_four(dpt.get("intermediate_layer_idx", base.dpt_intermediate_layer_idx)),
            dpt_frames_chunk_size=None if chunk is None else int(chunk),
        )

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> VGGTConfig:
        """Reads a config in the golden ``tiny_config.json`` layout (see :meth:`from_dict`)."""
        with open(path, encoding="utf-8") as f:
            return cls.from_dict(json.load(f))

    def to_dict(self) -> dict[str, Any]:
        """The fields as a plain dict (JSON-serialisable)."""
        return dataclasses.asdict(self)


#: Smallest value of each size (``dpt_frames_chunk_size`` may also be ``None``).
_POSITIVE = {
    "img_size": 1,
    "patch_size": 1,
    "embed_dim": 1,
    "depth": 1,
    "num_heads": 1,
    "mlp_ratio": 0,
    "num_register_tokens": 0,
    "aa_block_size": 1,
    "dino_depth": 1,
    "dino_num_heads": 1,
    "dino_mlp_ratio": 0,
    "camera_trunk_depth": 1,
    "camera_num_heads": 1,
    "camera_mlp_ratio": 0,
    "camera_iterations": 1,
    "dpt_features": 1,
    "dpt_frames_chunk_size": 1,
}

#: The keys of the golden layout (``tiny_config.json``): sections with the keys read or
#: checked in each, and the top-level keys that only describe the file.  Anything else is a
#: typo or another layout and is refused (it was ignored, and the checkpoint blamed).
_SECTIONS = {
    "aggregator_kwargs": {
        "img_size",
        "patch_size",
        "embed_dim",
        "depth",
        "num_heads",
        "mlp_ratio",
        "num_register_tokens",
        "qkv_bias",
        "proj_bias",
        "ffn_bias",
        "patch_embed",
        "aa_order",
        "aa_block_size",
        "qk_norm",
        "rope_freq",
        "init_values",
    },
    "patch_embed_vit": {
        "embed_dim",
        "depth",
        "num_heads",
        "mlp_ratio",
        "img_size",
        "patch_size",
        "num_register_tokens",
        "interpolate_antialias",
        "interpolate_offset",
        "block_chunks",
        "init_values",
        "ffn_layer",
        "qkv_bias",
        "proj_bias",
        "ffn_bias",
        "qk_norm",
        "layernorm_eps",
        "pos_embed_grid",
    },
    "camera_head_kwargs": {
        "dim_in",
        "trunk_depth",
        "pose_encoding_type",
        "num_heads",
        "mlp_ratio",
        "init_values",
        "trans_act",
        "quat_act",
        "fl_act",
    },
    "depth_head_kwargs": {
        "dim_in",
        "patch_size",
        "output_dim",
        "activation",
        "conf_activation",
        "features",
        "out_channels",
        "intermediate_layer_idx",
        "pos_embed",
        "feature_only",
        "down_ratio",
    },
}
_SCALARS = {"camera_head_num_iterations": int, "depth_head_frames_chunk_size": (int, type(None))}
_DESCRIPTIVE = {
    "upstream_repo",
    "upstream_commit",
    "torch_version",
    "dtype",
    "device",
    "input",
    "patch_embed_note",
    "point_head",
    "track_head",
    "param_init",
    "num_params",
    "num_state_dict_entries",
    "state_dict_keys_in_order",
    "observed_max_abs_diff",
    "sha256",
    "seed_torch_manual_seed_before_construction",
    "seed_param_perturbation_generator",
    "seed_input_generator",
}
#: Keys whose value is an integer (bools and fractions refused), and numbers.
_INTS = {
    "img_size",
    "patch_size",
    "embed_dim",
    "depth",
    "num_heads",
    "num_register_tokens",
    "aa_block_size",
    "trunk_depth",
    "features",
    "dim_in",
    "output_dim",
    "down_ratio",
    "block_chunks",
}
_NUMBERS = {"mlp_ratio", "rope_freq", "init_values", "interpolate_offset", "layernorm_eps"}


def _check_layout(d: Any) -> None:
    """The structure and value types of a golden-layout config (:meth:`VGGTConfig.from_dict`):
    an object of objects, known keys only, integers where sizes go (``ValueError`` naming the key)."""
    import difflib

    if not isinstance(d, Mapping):
        raise ValueError(f"expected a JSON object of sections (aggregator_kwargs, ...), got a {type(d).__name__}")
    known = set(_SECTIONS) | set(_SCALARS) | _DESCRIPTIVE
    for key, value in d.items():
        if key not in known:
            close = difflib.get_close_matches(key, sorted(set(_SECTIONS) | set(_SCALARS)), n=1)
            raise ValueError(f"unknown key {key!r}" + (f" (did you mean {close[0]}?)" if close else ""))
        if key in _SCALARS and not (isinstance(value, _SCALARS[key]) and not isinstance(value, bool)):
            raise ValueError(
                f"{key} must be an integer{' or null' if key.endswith('chunk_size') else ''}, got {value!r}"
            )
        if key not in _SECTIONS:
            continue
        if not isinstance(value, Mapping):
            raise ValueError(f"{key} must be an object of keyword arguments, got {value!r}")
        for k, v in value.items():
            if k not in _SECTIONS[key]:
                close = difflib.get_close_matches(k, sorted(_SECTIONS[key]), n=1)
                raise ValueError(f"unknown key {key}.{k}" + (f" (did you mean {close[0]}?)" if close else ""))
            if k in _INTS and (isinstance(v, bool) or not isinstance(v, int)):
                raise ValueError(f"{key}.{k} must be an integer, got {v!r}")
            if k in _INTS and v < (0 if k == "block_chunks" else 1):  # before the cross-section checks
                raise ValueError(f"{key}.{k} must be >= {0 if k == 'block_chunks' else 1}, got {v!r}")
            if k in _NUMBERS and (isinstance(v, bool) or not isinstance(v, (int, float))):
                raise ValueError(f"{key}.{k} must be a number, got {v!r}")
            if k in ("out_channels", "intermediate_layer_idx") and not (
                isinstance(v, list) and all(isinstance(x, int) and not isinstance(x, bool) for x in v)
            ):
                raise ValueError(f"{key}.{k} must be a list of integers, got {v!r}")


def _four(v: Sequence[Any]) -> tuple[int, int, int, int]:
    vals = tuple(int(x) for x in v)
    if len(vals) != 4:
        raise ValueError(f"expected four values, got {list(v)}")
    return vals  # type: ignore[return-value]


def _check_fixed(section: Mapping[str, Any], fixed: Mapping[str, Any]) -> None:
    """Refuses configs that change what this implementation hard-codes."""
    for key, expected in fixed.items():
        if key in section and section[key] != expected:
            raise ValueError(
                f"config sets {key}={section[key]!r}, but this VGGT implementation supports only {expected!r}"
            )

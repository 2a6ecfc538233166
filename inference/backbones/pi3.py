"""π³ and π³X as a backbone (``--model pi3 | pi3x``; the clean-room :mod:`inference.pi3`).

Preprocessing: upstream's rule (:mod:`inference.pi3.preprocess`, one mode ``resize``: PIL
LANCZOS, no crop, at most 255,000 pixels, multiples of 14, size from the first frame).
Conversion (:mod:`inference.pi3.convert`): depth = local points' z, K from the rays by least
squares, extrinsics re-based on the chunk's first camera, confidence ``sigmoid(logit)``, loop
tokens = DINO patch tokens before the decoder.  π³X's outputs are metric-scaled by its metric
token (approximately metres); ``--intrinsics`` becomes its ray condition.

The family's rows in :data:`inference.backbones.BACKBONES` are ``pi3`` and ``pi3x``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import Any

name = "pi3"
modes = ("resize",)

_PI3X_ONLY = ("metric_token", "metric_decoder.", "depth_encoder.", "ray_embed.", "pose_inject_blk.", "depth_emb")
_MULTIMODAL = ("depth_encoder.", "depth_emb", "ray_embed.", "pose_inject_blk.")


def variant_of(names: Iterable[str]) -> str | None:
    """``"pi3"`` / ``"pi3x"`` for a π³-layout checkpoint's key names, else ``None``."""
    keys = list(names)
    if not (
        "register_token" in keys
        and any(k.startswith("encoder.patch_embed.") for k in keys)
        and any(k.startswith("camera_head.fc_rot") for k in keys)
    ):
        return None
    return "pi3x" if any(k.startswith(_PI3X_ONLY) for k in keys) else "pi3"


def load_config(backbone: Any, path: Any | None) -> dict[str, Any]:
    """The preset's :class:`~inference.pi3.config.Pi3Config`, or that of a golden-layout
    ``tiny_config.json`` (``--model-config``), as a dict."""
    from inference.pi3.config import Pi3Config

    cfg = Pi3Config.preset(backbone.preset) if path is None else Pi3Config.from_json(path, backbone.preset)
    return cfg.to_dict()


def _model(config: dict[str, Any]) -> Any:
    import torch

    from inference.pi3.config import Pi3Config
    from inference.pi3.model import Pi3
    from inference.pi3.pi3x import Pi3X

    cfg = Pi3Config.from_fields(config)
    with torch.device("meta"):  # no 4-5 GB allocation: the loader assigns the file's tensors
        return Pi3(cfg) if cfg.variant == "pi3" else Pi3X(cfg)


def check_checkpoint(backbone: Any, path: Any, config: dict[str, Any]) -> None:
    """Refuses, from the safetensors header alone, a file of another family or variant, of
    other shapes, or truncated (one line); π³ files are safetensors only."""
    from inference.checkpoint import CheckpointError

    from .header import checkpoint_header, compare_shapes

    p = os.fspath(path)
    if not p.lower().endswith(".safetensors"):
        raise CheckpointError(
            f"--weights {p}: π³ checkpoints are read from .safetensors only (--model {backbone.name})"
        )
    header = checkpoint_header(p)
    got = variant_of(header)
    want = config.get("variant", backbone.preset)
    if got is None:
        raise CheckpointError(f"--weights {p} is not a π³ checkpoint (--model {backbone.name})")
    if got != want:
        raise CheckpointError(f"--weights {p} is a {got} checkpoint, not a {want} one (--model {backbone.name})")
    shapes = {k: s for k, (_, s) in header.items()}
    if want == "pi3x" and not config.get("multimodal", True):
        shapes = {k: s for k, s in shapes.items() if not k.startswith(_MULTIMODAL)}
    model = {k: tuple(v.shape) for k, v in _model(config).state_dict().items()}
    compare_shapes(p, shapes, model, f"{want} model", optional=("image_mean", "image_std"))


def preprocess(images: list[Any], mode: str) -> Any:
    from inference.pi3.preprocess import preprocess as _preprocess

    _check_mode(mode)
    return _preprocess(images)


def preprocess_geometry(height: int, width: int, mode: str) -> Any:
    from inference.pi3.preprocess import geometry

    _check_mode(mode)
    return geometry(height, width)


def _check_mode(mode: str) -> None:
    if mode not in modes:
        raise ValueError(f"π³ preprocesses with its own rule only (mode 'resize'), got mode {mode!r}")


def build_runner(
    backbone: Any, weights: str, device: str, dtype: str, config: dict[str, Any], intrinsics: Any | None = None
) -> Any:
    """A :class:`~inference.pi3.runner.Pi3TorchRunner` with ``weights`` loaded strictly;
    ``intrinsics`` (π³X: ``[3, 3]`` at the model resolution) become the ray condition."""
    import torch

    from inference.pi3.checkpoint import load_pi3_checkpoint
    from inference.pi3.runner import Pi3TorchRunner

    model = _model(config)
    load_pi3_checkpoint(model, weights)
    torch_dtype = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}[dtype]
    runner = Pi3TorchRunner(model, device=device, dtype=torch_dtype, intrinsics=intrinsics)
    runner.name = f"{backbone.name} ({weights}, {dtype})"  # named in a non-finite-output error
    return runner

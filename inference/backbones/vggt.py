"""VGGT-1B as a backbone (the clean-room model of :mod:`inference.model`, unchanged).

Preprocessing :func:`inference.preprocess.preprocess` (``crop``: width 518, or ``pad``);
outputs are already in the chunk's first-camera frame (VGGT's convention), confidence
``1 + exp``, loop tokens = the DINO ``x_norm_patchtokens`` (:class:`inference.runners.TorchRunner`).
"""

from __future__ import annotations

import os
from typing import Any

from .header import FAMILY_TEXT, checkpoint_header, compare_shapes, describe_family

name = "vggt"
modes = ("crop", "pad")
_IGNORED = ("point_head.", "track_head.")


def load_config(backbone: Any, path: Any | None) -> dict[str, Any] | None:
    """``None`` for VGGT-1B, else the :class:`~inference.config.VGGTConfig` of ``path`` as a dict."""
    if path is None:
        return None
    from inference.config import VGGTConfig

    return VGGTConfig.from_json(path).to_dict()


def _model(config: dict[str, Any] | None) -> Any:
    import torch

    from inference import VGGT, VGGTConfig

    with torch.device("meta"):  # no 5 GB allocation: load_checkpoint assigns the (mmapped) tensors
        return VGGT(VGGTConfig(**config) if config else VGGTConfig())


def check_checkpoint(backbone: Any, path: Any, config: dict[str, Any] | None) -> None:
    """A ``.safetensors`` file's family and shapes against the model (pickles are checked when loaded)."""
    from inference.checkpoint import CheckpointError

    if not os.fspath(path).lower().endswith(".safetensors"):
        return
    header = checkpoint_header(path)
    fam = describe_family(header)
    if fam != "vggt":
        raise CheckpointError(
            f"--weights {os.fspath(path)} is {FAMILY_TEXT[fam]}, not a VGGT one (--model {backbone.name})"
        )
    compare_shapes(
        path,
        {k: s for k, (_, s) in header.items() if not k.startswith(_IGNORED)},
        {k: tuple(v.shape) for k, v in _model(config).state_dict().items()},
        "VGGT model",
    )


def preprocess(images: list[Any], mode: str) -> Any:
    from inference.preprocess import preprocess as _preprocess

    return _preprocess(images, mode=mode)


def preprocess_geometry(height: int, width: int, mode: str) -> Any:
    from swiftjax.intrinsics import preprocess_geometry as _geometry

    return _geometry(height, width, mode)


def build_runner(backbone: Any, weights: str, device: str, dtype: str, config: dict[str, Any] | None) -> Any:
    import torch

    from inference import load_checkpoint
    from inference.runners import TorchRunner

    model = _model(config)
    load_checkpoint(model, weights)
    torch_dtype = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}[dtype]
    runner = TorchRunner(model, device=device, dtype=torch_dtype)
    runner.name = f"{backbone.name} ({weights}, {dtype})"  # named in a non-finite-output error
    return runner

"""Thin VGGT inference shim: a clean-room PyTorch VGGT, preprocessing, torch/ONNX runners.

Submodules and names are imported lazily, so ``import inference`` does not import torch;
``from inference import VGGT`` does.
"""

from __future__ import annotations

import importlib
from typing import Any

_NAMES = {
    "VGGTConfig": "config",
    "VGGT": "model",
    "load_checkpoint": "checkpoint",
    "read_state_dict": "checkpoint",
    "CheckpointError": "checkpoint",
    "pose_encoding_to_extrinsics_intrinsics": "pose_encoding",
    "preprocess": "preprocess",
    "load_image": "preprocess",
    "TorchRunner": "runners",
    "OnnxRunner": "runners",
    "ImagePredictor": "predictor",
    "ImageSpec": "predictor",
    "build_runner": "predictor",
    "export_onnx": "onnx_export",
}
_SUBMODULES = (
    "aggregator",
    "camera_head",
    "check_golden",
    "checkpoint",
    "config",
    "dino",
    "dpt",
    "layers",
    "model",
    "onnx_export",
    "pose_encoding",
    "predictor",
    "preprocess",
    "runners",
)

__all__ = sorted(_NAMES) + list(_SUBMODULES)


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        return getattr(importlib.import_module(f"{__name__}.{_NAMES[name]}"), name)
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

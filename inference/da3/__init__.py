"""Clean-room Depth Anything 3 (ByteDance-Seed/Depth-Anything-3 at 2c21ea8), proven equal to the
official code on ``shared/golden/da3`` (``python -m inference.check_golden DIR``).

Modules: :mod:`.config` (sizes, presets), :mod:`.dinov2` (ViT with cross-view attention),
:mod:`.refview` (reference view), :mod:`.dualdpt` / :mod:`.metric_dpt` (heads), :mod:`.camera`
(pose encoding, camera encoder/decoder), :mod:`.raypose` (cameras from rays), :mod:`.sky`,
:mod:`.model` (:class:`DA3Net`, :func:`build_da3`), :mod:`.nested` (:class:`NestedDA3Net`),
:mod:`.checkpoint` (:func:`load_da3_checkpoint`), :mod:`.golden`, :mod:`.onnx`.
Importing this package imports torch.
"""

from __future__ import annotations

from .checkpoint import CheckpointError, load_da3_checkpoint
from .config import PRESETS, DA3Config, NestedDA3Config, preset_config
from .model import DA3Net, build_da3
from .nested import NestedDA3Net

__all__ = [
    "CheckpointError",
    "DA3Config",
    "DA3Net",
    "NestedDA3Config",
    "NestedDA3Net",
    "PRESETS",
    "build_da3",
    "load_da3_checkpoint",
    "preset_config",
]

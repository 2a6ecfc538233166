"""Backbones: the networks that predict a chunk, behind one interface.

A backbone is an architecture + its configuration + checkpoint loading + preprocessing + the
conversion of its outputs to :class:`swiftjax.prediction.ChunkPrediction` (depth, confidence,
world-to-camera extrinsics and intrinsics in the chunk's FIRST camera's frame, loop tokens).
Each family lives in one module of this package (:mod:`.vggt`, :mod:`.da3`, :mod:`.pi3`) exposing a
``Family`` (a protocol); :data:`BACKBONES` names the presets the CLI's ``--model`` offers.  Another
family is one more module and its rows in :data:`BACKBONES`.

Importing this package does not import torch (the CLI resolves names and checks headers
before any model is built).
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any, Protocol

__all__ = ["Backbone", "Family", "BACKBONES", "get", "family"]


class Family(Protocol):
    """What a backbone family module provides (see :mod:`.vggt`, :mod:`.da3`)."""

    name: str
    modes: tuple[str, ...]  # preprocessing modes; the first is the default

    def load_config(self, backbone: Backbone, path: Any | None) -> dict[str, Any]:
        """The architecture as a JSON-able dict: ``path`` (a ``--model-config`` file) or the preset's."""

    def check_checkpoint(self, backbone: Backbone, path: Any, config: dict[str, Any]) -> None:
        """Refuse (``CheckpointError``, one line) a weights file of another family or another
        shape, or a truncated one, from its header alone."""

    def preprocess(self, images: list[Any], mode: str) -> Any:
        """Frames (paths / arrays) -> ``[S, 3, H, W]`` float32 RGB in [0, 1] at the model's size."""

    def preprocess_geometry(self, height: int, width: int, mode: str) -> Any:
        """:class:`swiftjax.intrinsics.PreprocessGeometry` of one original image size; a
        ``ValueError`` naming the size if the family cannot take it."""

    def build_runner(self, backbone: Backbone, weights: str, device: str, dtype: str, config: dict[str, Any]) -> Any:
        """A runner (``predict([S,3,H,W] in [0,1]) -> ChunkPrediction``) with the weights loaded."""


@dataclasses.dataclass(frozen=True)
class Backbone:
    """One ``--model`` choice.

    Attributes:
        name: the CLI name (``vggt-1b``, ``da3-small``, ...).
        family: module of this package implementing it (``vggt``, ``da3``).
        preset: the family's preset name of the full-size architecture.
        metric: whether its depth is in metres (the nested DA3 model).
        licence: licence of the released weights.
        weights_page: where the official weights are published (model page name).
    """

    name: str
    family: str
    preset: str
    metric: bool
    licence: str
    weights_page: str

    @property
    def impl(self) -> Family:
        return family(self.family)


BACKBONES: dict[str, Backbone] = {
    b.name: b
    for b in (
        Backbone(
            "vggt-1b",
            "vggt",
            "vggt-1b",
            False,
            "non-commercial (VGGT licence; commercial variant gated)",
            "facebook/VGGT-1B",
        ),
        Backbone("da3-small", "da3", "da3-small", False, "Apache-2.0", "depth-anything/DA3-SMALL"),
        Backbone("da3-base", "da3", "da3-base", False, "Apache-2.0", "depth-anything/DA3-BASE"),
        Backbone("da3-large", "da3", "da3-large", False, "CC BY-NC 4.0", "depth-anything/DA3-LARGE"),
        Backbone("da3-giant", "da3", "da3-giant", False, "CC BY-NC 4.0", "depth-anything/DA3-GIANT"),
        Backbone(
            "da3-nested-giant-large",
            "da3",
            "da3nested-giant-large",
            True,
            "CC BY-NC 4.0",
            "depth-anything/DA3NESTED-GIANT-LARGE",
        ),
        Backbone("pi3", "pi3", "pi3", False, "CC BY-NC 4.0", "yyfz233/Pi3"),
        Backbone("pi3x", "pi3", "pi3x", True, "CC BY-NC 4.0", "yyfz233/Pi3X"),
    )
}


def get(name: str) -> Backbone:
    """The backbone called ``name``; an :class:`~swiftjax.options.OptionError` (a ``ValueError``)
    naming the choices otherwise."""
    from swiftjax.options import OptionError

    try:
        return BACKBONES[name]
    except KeyError:
        raise OptionError(f"--model {name!r} is not a backbone; choose one of {', '.join(BACKBONES)}") from None


def family(name: str) -> Family:
    """The family module (imported on first use; it imports torch only when a model is built)."""
    return importlib.import_module(f"{__name__}.{name}")  # type: ignore[return-value]

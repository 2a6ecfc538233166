"""The arrays one VGGT forward pass over a chunk of frames produces.

Every predictor (the torch runner, the onnxruntime runner, the synthetic oracle) returns a
:class:`ChunkPrediction`; the pipeline consumes nothing else.  It is a plain container of
NumPy arrays on the host: the JAX core takes the fields it needs as arguments.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["ChunkPrediction"]


@dataclasses.dataclass(frozen=True)
class ChunkPrediction:
    """One chunk's predictions, ``S`` frames of ``H x W`` pixels.

    Attributes:
        depth: ``[S, H, W]`` float32 depth along the optical axis, in the chunk's own units.
        conf: ``[S, H, W]`` float32 depth confidence (VGGT: ``1 + exp(logit)``, so ``>= 1``).
        extrinsic: ``[S, 3, 4]`` float32 world-to-camera ``[R | t]`` in the chunk's frame
            (OpenCV axes; the chunk's first camera is at the origin).
        intrinsic: ``[S, 3, 3]`` float32 pinhole intrinsics ``K``.
        descriptors: ``[S, d]`` float32 per-frame place descriptors ``g0`` (l2 -> mean -> l2
            of the DINO patch tokens), or ``None`` when ``patch_tokens`` is given instead.
        patch_tokens: ``[S, P, C]`` DINO patch tokens, or ``None``.  The pipeline reduces them
            to descriptors at once and never keeps them.
        images: ``[S, H, W, 3]`` uint8 RGB colours for the point cloud, or ``None``.
    """

    depth: np.ndarray
    conf: np.ndarray
    extrinsic: np.ndarray
    intrinsic: np.ndarray
    descriptors: np.ndarray | None = None
    patch_tokens: np.ndarray | None = None
    images: np.ndarray | None = None

    def __post_init__(self) -> None:
        s, h, w = np.shape(self.depth)
        expect = {
            "conf": (s, h, w),
            "extrinsic": (s, 3, 4),
            "intrinsic": (s, 3, 3),
        }
        for name, shape in expect.items():
            got = tuple(np.shape(getattr(self, name)))
            if got != shape:
                raise ValueError(f"ChunkPrediction.{name} has shape {got}, expected {shape}")
        if self.descriptors is not None and np.shape(self.descriptors)[0] != s:
            raise ValueError(f"ChunkPrediction.descriptors has {np.shape(self.descriptors)[0]} rows for {s} frames")
        if self.patch_tokens is not None and np.shape(self.patch_tokens)[0] != s:
            raise ValueError(f"ChunkPrediction.patch_tokens has {np.shape(self.patch_tokens)[0]} frames, expected {s}")
        if self.images is not None and tuple(np.shape(self.images)) != (s, h, w, 3):
            raise ValueError(f"ChunkPrediction.images has shape {np.shape(self.images)}, expected {(s, h, w, 3)}")

    @property
    def num_frames(self) -> int:
        return int(np.shape(self.depth)[0])

    @property
    def image_hw(self) -> tuple[int, int]:
        return int(np.shape(self.depth)[1]), int(np.shape(self.depth)[2])

"""What the pipeline needs from VGGT (:class:`Predictor`) and the synthetic oracle's predictor.

The image predictor (files or a video through a torch/ONNX runner) lives with the runners:
:class:`inference.predictor.ImagePredictor`.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from swiftjax.prediction import ChunkPrediction

__all__ = ["Predictor", "OraclePredictor"]


class Predictor(Protocol):
    """What the pipeline needs from VGGT (a real runner or the synthetic oracle)."""

    num_frames: int

    def predict(self, frames: np.ndarray) -> ChunkPrediction:
        """One forward pass over the given global frame indices."""
        ...

    def fingerprint(self) -> dict[str, Any]:
        """JSON-able identity of everything that determines a prediction: ``{"frames": [one
        item per frame, e.g. name, size, mtime] or None, **rest}`` (model, preprocessing, ...).
        A changed frame re-predicts only its chunks; any other change refuses the run
        directory (:func:`swiftjax.pipeline.rundir.fingerprints`)."""
        ...

    def frame_names(self) -> list[str]:
        """A name per frame (COLMAP image names)."""
        ...

    # Optional: ``images(frames) -> [S, H, W, 3] uint8``, the frames as the model sees them,
    # without predicting (the export rewrites missing COLMAP frames from it; a predictor
    # without it has the chunks holding such frames predicted again).


class OraclePredictor:
    """:class:`Predictor` over a :class:`swiftjax.synthetic.oracle.VGGTOracle`."""

    def __init__(self, oracle: Any, description: dict[str, Any] | None = None, spec: Any = None) -> None:
        self.oracle = oracle
        self.num_frames = int(oracle.num_frames)
        self._description = description or {}
        self._spec = spec

    def spec(self) -> Any:
        """What a worker rebuilds this predictor from (:mod:`~swiftjax.pipeline.executors`):
        the recipe given (e.g. :class:`swiftjax.synthetic.demo.OracleSpec`), else this predictor."""
        if self._spec is not None:
            return self._spec
        from swiftjax.pipeline.executors import SelfSpec

        return SelfSpec(self)

    def predict(self, frames: np.ndarray) -> ChunkPrediction:
        return self.oracle.predict_chunk(np.asarray(frames))

    def images(self, frames: np.ndarray) -> np.ndarray:
        """The frames ``[S, H, W, 3]`` uint8 of the chunk ``frames`` as the oracle renders them
        (the export rewrites missing COLMAP frames from them; no model prediction is recorded)."""
        return np.asarray(self.oracle.predict_chunk(np.asarray(frames)).images)

    def fingerprint(self) -> dict[str, Any]:
        return {"frames": None, "model": ["synthetic", self.num_frames, self.oracle.seed, self._description]}

    def frame_names(self) -> list[str]:
        return [f"{k:06d}.png" for k in range(self.num_frames)]

    def preprocess_geometry(self) -> Any:
        """The oracle renders at the model's resolution: the identity map (its frames, e.g.
        the demo's 518 x 154, are the original images)."""
        from swiftjax.intrinsics import PreprocessGeometry

        hw = tuple(int(v) for v in self.oracle.image_hw)
        return PreprocessGeometry(hw, hw, 0, 0, hw)

"""The pipeline's predictor over image files or a video, through a runner.

Implements :class:`swiftjax.pipeline.predictors.Predictor` (structurally: ``num_frames``,
``predict``, ``fingerprint``, ``frame_names``), so that ``swiftjax`` never imports this
package; only the CLI joins the two.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from swiftjax.prediction import ChunkPrediction

__all__ = ["ImagePredictor"]


class ImagePredictor:
    """Predictor over image files or a video, through an ``inference`` runner.

    Frames are read with :mod:`swiftjax.io.images`, preprocessed as VGGT's loader does
    (:func:`inference.preprocess.preprocess`, ``mode``) and passed to ``runner.predict``
    (:class:`inference.runners.TorchRunner` or :class:`inference.runners.OnnxRunner`).
    """

    def __init__(self, source: Any, runner: Any, mode: str = "crop") -> None:
        self.source = source
        self.runner = runner
        self.mode = mode
        self.num_frames = len(source)

    def predict(self, frames: np.ndarray) -> ChunkPrediction:
        from inference.preprocess import preprocess

        images = preprocess([self.source.read(int(k)) for k in frames], mode=self.mode)
        return self.runner.predict(images)

    def fingerprint(self) -> list[Any]:
        return [list(item) for item in self.source.fingerprint()] + [["mode", self.mode]]

    def frame_names(self) -> list[str]:
        return list(self.source.names)

    def preprocess_geometry(self) -> Any:
        """Where the original pixels land in the model's images
        (:func:`swiftjax.intrinsics.preprocess_geometry` of the frames' common size and ``mode``)."""
        from swiftjax.intrinsics import preprocess_geometry

        return preprocess_geometry(*self.source.image_hw, self.mode)

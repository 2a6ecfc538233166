"""The pipeline's predictor over image files or a video, through a runner, and its recipe.

:class:`ImagePredictor` implements :class:`swiftjax.pipeline.predictors.Predictor`
(structurally: ``num_frames``, ``predict``, ``fingerprint``, ``frame_names``), so that
``swiftjax`` never imports this package; only the CLI joins the two.  :class:`ImageSpec` is
what a worker process (``swiftjax.pipeline.executors.RayExecutor``) builds the same
predictor from: the input, the weights, the backend, device and dtype.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from typing import Any

import numpy as np

from swiftjax.options import OptionError
from swiftjax.prediction import ChunkPrediction

from .frames import FrameLoader

__all__ = ["ImagePredictor", "ImageSpec", "build_runner", "model_identity", "weights_identity"]


class ImagePredictor:
    """Predictor over image files or a video, through an ``inference`` runner.

    Frames are read with :mod:`swiftjax.io.images`, preprocessed as the backbone's official
    loader does (``model``: a :data:`inference.backbones.BACKBONES` name; VGGT:
    :func:`inference.preprocess.preprocess`, DA3: :func:`inference.preprocess.preprocess_da3`;
    ``mode``) and passed to ``runner.predict`` (:class:`inference.runners.TorchRunner`,
    :class:`inference.runners.OnnxRunner`, :class:`inference.backbones.da3.DA3Runner`).
    ``runner`` may be a zero-argument factory, called at the first prediction (a driver
    whose predictions run on workers never loads the model).  ``spec``: the recipe
    returned by :meth:`spec` (for workers).
    """

    def __init__(
        self,
        source: Any,
        runner: Any,
        mode: str = "crop",
        spec: ImageSpec | None = None,
        identity: dict[str, Any] | None = None,
        model: str | None = None,
    ) -> None:
        from inference.backbones import get

        self.source = source
        self._runner = runner
        self.mode = mode
        self.backbone = get(model or (spec.model if spec is not None else "vggt-1b"))
        self.identity = identity or {}
        self.num_frames = len(source)
        self._spec = spec
        self._frames = FrameLoader(
            source.read,
            lambda images: self.backbone.impl.preprocess(images, self.mode),
            serial_reads=getattr(source, "paths", None) is None,
        )  # a video seeks

    @property
    def runner(self) -> Any:
        if not hasattr(self._runner, "predict") and callable(self._runner):
            self._runner = self._runner()
        return self._runner

    def predict(self, frames: np.ndarray) -> ChunkPrediction:
        return self.runner.predict(self._frames.load(frames))

    def append(self, path: str | os.PathLike[str]) -> None:
        """One more frame, the image file ``path`` (a growing folder: the live engine,
        :class:`swiftjax.pipeline.engine.Reconstruction`); read and preprocessed like the
        others when a chunk takes it.  The source must be image files."""
        append = getattr(self.source, "append", None)
        if append is None or not isinstance(path, (str, os.PathLike)):
            raise TypeError(
                f"ImagePredictor.append takes an image file's path into image files, got "
                f"{type(path).__name__} for a {type(self.source).__name__} source"
            )
        append(path)
        self.num_frames = len(self.source)

    def prefetch(self, frames: np.ndarray) -> None:
        """Start decoding a scheduled chunk's frames (:class:`inference.frames.FrameLoader`)
        while earlier chunks predict; the executor calls it when it schedules the chunk."""
        self._frames.prefetch(frames)

    def close(self) -> None:
        """Stop the decoding threads."""
        self._frames.close()

    def fingerprint(self) -> dict[str, Any]:
        """Everything that determines a chunk's prediction: each frame's file by content (name,
        size and the SHA-256 of the whole file, :mod:`swiftjax.io.file_hash`, cached by file
        identity; a video is one entry per frame naming the video file and its digest), the
        model (``identity``, else :func:`model_identity` of the ``spec``: the weights file's
        SHA-256, architecture, backend, dtype, device class) and the preprocessing."""
        from swiftjax.io.file_hash import sha256_files

        files = [list(item) for item in self.source.fingerprint()]
        paths = getattr(self.source, "paths", None)
        if paths is None and getattr(self.source, "path", None) is not None:
            paths = [self.source.path]
        digests = sha256_files(paths) if paths is not None and len(paths) == len(files) else [None] * len(files)
        files = [[item[0], item[1], d] if d is not None else item for item, d in zip(files, digests)]
        if len(files) == self.num_frames:
            frames = files
        else:  # a video: one file for every frame
            frames = [[name] + files[0][1:] for name in self.source.names]
        model = self.identity
        if not model and self._spec is not None:
            sp = self._spec
            model = model_identity(
                sp.weights,
                backend=sp.backend,
                dtype=sp.dtype,
                device_class=sp.device.split(":")[0],
                config=sp.model_config,
                model=sp.model,
            )
        return {"frames": frames, "model": model, "preprocessing": {"mode": self.mode}}

    def images(self, frames: np.ndarray) -> np.ndarray:
        """The frames ``[S, H, W, 3]`` uint8 as the model sees them (preprocessed; the
        prediction's ``images``), without running the model: the export rewrites missing
        COLMAP frames from them."""
        from inference.preprocess import to_uint8_images

        return to_uint8_images(self._frames.load(frames))

    def frame_names(self) -> list[str]:
        return list(self.source.names)

    def preprocess_geometry(self) -> Any:
        """Where the original pixels land in the model's images (the backbone's geometry of the
        frames' common size and ``mode``, e.g. :func:`swiftjax.intrinsics.preprocess_geometry`)."""
        return self.backbone.impl.preprocess_geometry(*self.source.image_hw, self.mode)

    def spec(self) -> Any:
        if self._spec is None:
            raise ValueError("this ImagePredictor has no ImageSpec: it cannot be rebuilt on a worker")
        return self._spec


def build_runner(
    weights: str | os.PathLike[str],
    backend: str = "torch",
    device: str = "cpu",
    dtype: str = "float32",
    model_config: dict[str, Any] | None = None,
    model: str = "vggt-1b",
) -> Any:
    """The runner of backbone ``model`` (:data:`inference.backbones.BACKBONES`; its preset, or
    ``model_config`` of its family) with ``weights`` loaded, or an
    :class:`~inference.runners.OnnxRunner` (VGGT graphs).  ``dtype``: ``float32``,
    ``bfloat16`` or ``float16`` (torch)."""
    from inference.backbones import get

    weights = os.fspath(weights)
    if backend == "onnx":
        from inference.runners import OnnxRunner

        if not weights.endswith(".onnx"):
            raise OptionError(f"--backend onnx needs an .onnx file (see 'swiftjax export-onnx'), got {weights}")
        providers = ["CUDAExecutionProvider", "CPUExecutionProvider"] if device.startswith("cuda") else None
        return OnnxRunner(weights, providers=providers)
    if backend != "torch":
        raise OptionError(f"backend must be 'torch' or 'onnx', got {backend!r}")
    backbone = get(model)
    return backbone.impl.build_runner(backbone, weights, device, dtype, model_config)


_RUNNERS: dict[tuple, Any] = {}  # ImageSpec.runner_factory's models, per process


@dataclasses.dataclass(frozen=True)
class ImageSpec:
    """The recipe of an :class:`ImagePredictor`: frames from ``input`` (folder, glob or
    video; every ``stride``-th; ``skip_bad`` as :func:`swiftjax.io.images.validate`), a
    runner from :func:`build_runner`'s arguments (``model``: the backbone), preprocessing ``mode``."""

    input: str
    weights: str
    backend: str = "torch"
    device: str = "cpu"
    dtype: str = "float32"
    model_config: dict[str, Any] | None = None
    mode: str = "crop"
    stride: int = 1
    skip_bad: bool = False
    model: str = "vggt-1b"

    def source(self) -> Any:
        from swiftjax.io import images

        return images.validate(images.list_frames(self.input, stride=self.stride), skip_bad=self.skip_bad)

    def runner_factory(self) -> Callable[[], Any]:
        """Loads the runner when called; one per process for the same weights, backend,
        device, dtype and model (a worker running many sequences loads the model once)."""
        key = (
            self.model,
            self.weights,
            self.backend,
            self.device,
            self.dtype,
            repr(sorted((self.model_config or {}).items())),
        )

        def load() -> Any:
            if key not in _RUNNERS:
                _RUNNERS[key] = build_runner(
                    self.weights, self.backend, self.device, self.dtype, self.model_config, self.model
                )
            return _RUNNERS[key]

        return load

    def build(self, source: Any = None) -> ImagePredictor:
        """The predictor (the model is loaded at its first prediction)."""
        return ImagePredictor(
            source if source is not None else self.source(), self.runner_factory(), mode=self.mode, spec=self
        )


def weights_identity(path: Any) -> dict[str, Any]:
    """A weights file's identity: its name, size and the SHA-256 of its whole content (hashed
    once, then cached by file identity: :mod:`swiftjax.io.file_hash`)."""
    from swiftjax.io.file_hash import sha256_file

    p = os.fspath(path)
    return {"file": os.path.basename(p), "size": int(os.stat(p).st_size), "sha256": sha256_file(p)}


def model_identity(
    weights: Any,
    *,
    backend: str,
    dtype: str,
    device_class: str,
    config: dict[str, Any] | None,
    model: str = "vggt-1b",
) -> dict[str, Any]:
    """The model part of :meth:`ImagePredictor.fingerprint`: the backbone (name, family,
    preset), its configuration, the weights file, backend, dtype and device class."""
    from inference.backbones import get

    b = get(model)
    return {
        "backbone": {"name": b.name, "family": b.family, "preset": b.preset},
        "weights": weights_identity(weights),
        "config": config,
        "backend": backend,
        "dtype": dtype,
        "device_class": device_class,
    }

"""Runners: one VGGT forward pass over a chunk of frames -> :class:`ChunkPrediction` arrays.

Both runners take ``[S, 3, H, W]`` float32 RGB in [0, 1] (what :func:`inference.preprocess`
returns) and return NumPy arrays on the host, so the JAX core never sees torch or onnxruntime.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from swiftjax.errors import SwiftjaxError
from swiftjax.prediction import ChunkPrediction

from .device import GPUMemoryError
from .pose_encoding import pose_encoding_to_extrinsics_intrinsics
from .preprocess import to_uint8_images

if TYPE_CHECKING:
    import torch

    from .model import VGGT

__all__ = ["Runner", "TorchRunner", "OnnxRunner", "ONNX_INPUT", "ONNX_OUTPUTS"]

ONNX_INPUT = "images"
ONNX_OUTPUTS = ("pose_enc", "depth", "depth_conf", "patch_tokens")


class Runner(Protocol):
    """Anything that turns a chunk of preprocessed frames into a :class:`ChunkPrediction`."""

    def predict(self, images: Any) -> ChunkPrediction:
        """``images``: ``[S, 3, H, W]`` float32 in [0, 1]."""
        ...


def _check_images(images: Any) -> np.ndarray:
    arr = np.asarray(images, dtype=np.float32)
    if arr.ndim != 4 or arr.shape[1] != 3:
        raise ValueError(f"images must be [S, 3, H, W], got shape {arr.shape}")
    return arr


#: The model outputs a chunk uses, and what each is, for messages.
_OUTPUTS = {
    "pose_enc": "camera head pose encoding",
    "depth": "depth head depth",
    "depth_conf": "depth head confidence",
    "patch_tokens": "DINO patch tokens",
    "extrinsics": "camera extrinsics",
    "intrinsics": "camera intrinsics",
    "prealt_patch_tokens": "DINO patch tokens",
    "descriptors": "loop descriptors",
    "local_points": "local point map",
    "conf": "confidence",
    "camera_poses": "camera poses",
    "dino_patch_tokens": "DINO patch tokens",
}


class ModelOutputError(SwiftjaxError, ValueError):
    """The model predicted non-finite values (the message names the model and the output)."""


def check_outputs(outputs: dict[str, np.ndarray], model: str = "VGGT") -> None:
    """Refuse non-finite model outputs, naming ``model`` and the output (``[S, ...]`` each):
    a NaN in the weights came out much later as "poses holds non-finite values", or as a run
    that wrote 0 points with exit status 0."""
    for name, a in outputs.items():
        what = _OUTPUTS.get(name, name)
        finite = np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
        if not finite.all():
            raise ModelOutputError(
                f"{model} predicted non-finite values (NaN/inf) in its {what} ({name}) for "
                f"{int((~finite).sum())} of {len(finite)} frames: the weights hold NaN/inf or overflow "
                "(check the checkpoint; with --dtype float16 try bfloat16 or float32)"
            )


def _to_prediction(
    images: np.ndarray,
    pose_enc: np.ndarray,
    depth: np.ndarray,
    conf: np.ndarray,
    tokens: np.ndarray,
    model: str = "VGGT",
    reduced: bool = False,
) -> ChunkPrediction:
    """Model outputs for one scene (leading batch axis already removed) -> ChunkPrediction;
    :class:`ModelOutputError` naming ``model`` if any is non-finite.  ``tokens``: the DINO patch
    tokens ``[S, P, C]``, or (``reduced``) their descriptors ``[S, C]``."""
    name = "descriptors" if reduced else "patch_tokens"
    check_outputs({"pose_enc": pose_enc, "depth": depth, "depth_conf": conf, name: tokens}, model)
    height, width = images.shape[-2:]
    extrinsic, intrinsic = pose_encoding_to_extrinsics_intrinsics(pose_enc.astype(np.float32), (height, width))
    return ChunkPrediction(
        depth=np.ascontiguousarray(depth.reshape(depth.shape[0], height, width), dtype=np.float32),
        conf=np.ascontiguousarray(conf, dtype=np.float32),
        extrinsic=np.ascontiguousarray(extrinsic, dtype=np.float32),
        intrinsic=np.ascontiguousarray(intrinsic, dtype=np.float32),
        **{name: np.ascontiguousarray(tokens, dtype=np.float32)},
        images=to_uint8_images(images),
    )


class TorchRunner:
    """Runs a :class:`~inference.model.VGGT` in torch.

    Args:
        model: the model (its weights stay float32).
        device: e.g. ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"mps"``.
        dtype: compute dtype of the aggregator: ``torch.float32`` (CPU default), or
            ``torch.bfloat16`` / ``torch.float16`` (GPU), applied with ``torch.autocast`` for
            the runner's device type; the heads stay in float32, as upstream.
    """

    def __init__(
        self,
        model: VGGT,
        device: str | torch.device = "cpu",
        dtype: torch.dtype | None = None,
        reduce_tokens: bool | None = None,
    ) -> None:
        import torch

        from .device import runner_device

        self.device = runner_device(device)
        self.dtype = dtype or torch.float32
        self.name = "VGGT"  # for messages; build_runner names the weights file
        self.model = model.to(self.device).eval()
        # On a GPU the DINO tokens become descriptors before they leave the device (a 75-frame
        # chunk: 300 KB instead of 125 MB); on the CPU the JAX reduction keeps its results.
        self.reduce_tokens = self.device.type == "cuda" if reduce_tokens is None else reduce_tokens

    def forward(self, images: Any) -> dict[str, Any]:
        """Raw model outputs (torch tensors, batch axis 1) for ``[S, 3, H, W]`` images; on CUDA
        the frames go up through pinned memory and attention runs on a fused kernel only
        (:mod:`inference.device`)."""

        from .device import model_math, to_device

        x = to_device(_check_images(images), self.device)[None]
        with model_math(self.device, self.dtype):
            return self.model(x)

    def predict(self, images: Any) -> ChunkPrediction:
        """See :class:`Runner`.  Out of device memory: :class:`~inference.device.GPUMemoryError`
        naming the largest chunk that fits at this image size (measured by trying)."""
        import torch

        from .descriptors import frame_descriptors
        from .device import to_host

        arr = _check_images(images)
        try:
            out = self.forward(arr)
        except torch.OutOfMemoryError:
            raise self._memory_error(arr) from None
        wanted = {k: out[k][0] for k in ("pose_enc", "depth", "depth_conf")}
        if self.reduce_tokens:
            wanted["descriptors"] = frame_descriptors(out["patch_tokens"][0])
        else:
            wanted["patch_tokens"] = out["patch_tokens"][0]
        host = to_host(wanted)
        tokens = host["descriptors"] if self.reduce_tokens else host["patch_tokens"]
        return _to_prediction(
            arr, host["pose_enc"], host["depth"], host["depth_conf"], tokens, self.name, reduced=self.reduce_tokens
        )

    def _memory_error(self, arr: np.ndarray) -> GPUMemoryError:
        import torch

        from .device import largest_chunk_that_fits

        s, _, h, w = arr.shape
        probe = np.zeros((1, 3, h, w), np.float32)

        def run(frames: int) -> None:
            self.forward(np.broadcast_to(probe, (frames, 3, h, w)))

        if self.device.type == "cuda":  # free what the failed chunk held before probing
            torch.cuda.empty_cache()
        fits = largest_chunk_that_fits(run, s, device=self.device)
        return GPUMemoryError(
            f"{self.name}: a chunk of {s} frames of {w}x{h} does not fit in the memory of {self.device}; the largest "
            f"that fits, measured now, is {fits} frames: --chunk-size {fits} (and an --overlap below it)"
            if fits
            else f"{self.name}: not even one frame of {w}x{h} fits in the memory of {self.device}"
        )


def ort_session(path: str | os.PathLike[str], providers: Sequence[str] | None = None, intra_op_threads: int = 0) -> Any:
    """An onnxruntime ``InferenceSession`` (default provider: CPU; 0 threads = its default)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = intra_op_threads
    return ort.InferenceSession(
        os.fspath(path), sess_options=opts, providers=list(providers or ["CPUExecutionProvider"])
    )


class OnnxRunner:
    """Runs a graph written by :func:`inference.onnx_export.export_onnx` with onnxruntime.

    Args:
        path: the ``.onnx`` file.
        providers: onnxruntime execution providers, e.g. ``["CUDAExecutionProvider",
            "CPUExecutionProvider"]``; default: CPU.
        intra_op_threads: threads per operator (0 = onnxruntime's default).
    """

    def __init__(
        self, path: str | os.PathLike[str], providers: Sequence[str] | None = None, intra_op_threads: int = 0
    ) -> None:
        self.session = ort_session(path, providers, intra_op_threads)
        self.name = f"the ONNX graph {os.fspath(path)}"
        inp = self.session.get_inputs()[0]
        if inp.name != ONNX_INPUT:
            raise ValueError(f"{path}: expected an input named {ONNX_INPUT!r}, got {inp.name!r}")
        self.input_shape = tuple(inp.shape)  # (1, "frames" or S, 3, H, W)
        names = [o.name for o in self.session.get_outputs()]
        missing = [n for n in ONNX_OUTPUTS if n not in names]
        if missing:
            raise ValueError(f"{path}: graph lacks outputs {missing} (has {names})")

    def forward(self, images: Any) -> dict[str, np.ndarray]:
        """Raw graph outputs (batch axis 1) for ``[S, 3, H, W]`` images."""
        arr = _check_images(images)
        for axis, (want, got) in enumerate(zip(self.input_shape[2:], arr.shape[1:]), start=2):
            if isinstance(want, int) and want != got:
                raise ValueError(
                    f"the ONNX graph was exported for input shape {self.input_shape}; got frames of shape "
                    f"{arr.shape[1:]} (axis {axis}): export again for this image size"
                )
        if isinstance(self.input_shape[1], int) and self.input_shape[1] != arr.shape[0]:
            raise ValueError(f"the ONNX graph has a fixed frame count {self.input_shape[1]}; got {arr.shape[0]} frames")
        outs = self.session.run(list(ONNX_OUTPUTS), {ONNX_INPUT: arr[None]})
        return dict(zip(ONNX_OUTPUTS, outs))

    def predict(self, images: Any) -> ChunkPrediction:
        """See :class:`Runner`."""
        arr = _check_images(images)
        out = self.forward(arr)
        return _to_prediction(
            arr, out["pose_enc"][0], out["depth"][0], out["depth_conf"][0], out["patch_tokens"][0], self.name
        )

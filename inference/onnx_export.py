"""Export of :class:`~inference.model.VGGT` to ONNX, with a torch-vs-onnxruntime check.

The graph has one input ``images [1, S, 3, H, W]`` (float32 RGB in [0, 1]; ``S`` dynamic,
``H`` and ``W`` fixed at export) and the outputs ``pose_enc [1,S,9]``, ``depth [1,S,H,W,1]``,
``depth_conf [1,S,H,W]`` and ``patch_tokens [1,S,P,C]`` — the same tensors as the torch forward.

It uses the TorchScript-based exporter (``torch.onnx.export(..., dynamo=False)``), which needs
nothing beyond torch and onnx.  Two things are fixed at export time because they depend only
on ``H`` and ``W``: the DINO position embedding (bicubic antialiased interpolation, which ONNX
cannot express exactly) is precomputed for the export size, and the RoPE / UV position tables
become constants.  The DPT head runs on all frames at once in the graph (no frame chunking).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import warnings
from collections.abc import Iterator

import numpy as np
import torch
from torch import Tensor, nn

from .model import VGGT
from .runners import ONNX_INPUT, ONNX_OUTPUTS

__all__ = ["export_onnx", "verify_onnx", "ExportReport"]

DEFAULT_OPSET = 17


@dataclasses.dataclass(frozen=True)
class ExportReport:
    """``max_abs_error[n_frames][output]``: max |ORT - torch| on random input per frame count."""

    path: str
    frames: int
    height: int
    width: int
    dynamic_frames: bool
    max_abs_error: dict[int, dict[str, float]]

    def summary(self) -> str:
        lines = [
            f"ONNX export {self.path} ({self.height}x{self.width}, frames={'dynamic' if self.dynamic_frames else self.frames})"
        ]
        for s, errs in self.max_abs_error.items():
            lines.append(f"  S={s}: " + ", ".join(f"{k} {v:.2e}" for k, v in errs.items()))
        return "\n".join(lines)


class _ExportWrapper(nn.Module):
    def __init__(self, model: VGGT) -> None:
        super().__init__()
        self.model = model

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        out = self.model(images, frames_chunk_size=None)
        return out["pose_enc"], out["depth"], out["depth_conf"], out["patch_tokens"]  # type: ignore[return-value]


@contextlib.contextmanager
def _static_pos_embed(model: VGGT, height: int, width: int) -> Iterator[None]:
    vit = model.aggregator.patch_embed
    p = model.config.patch_size
    with torch.no_grad():
        vit.fixed_pos_embed = vit.interpolate_pos_encoding(height // p, width // p).detach().clone()
    try:
        yield
    finally:
        vit.fixed_pos_embed = None


def export_onnx(
    model: VGGT,
    path: str | os.PathLike[str],
    frames: int,
    height: int,
    width: int,
    dynamic_frames: bool = True,
    opset: int = DEFAULT_OPSET,
    verify: bool = True,
    seed: int = 0,
) -> ExportReport:
    """Exports ``model`` (float32, on CPU) to ``path``.

    Args:
        model: the VGGT model; it is moved to CPU float32 eval mode for tracing.
        path: output ``.onnx`` file (models over 2 GB get their weights as external data next
            to it).
        frames: frame count of the example input used for tracing.
        height, width: image size (multiples of the patch size), fixed in the graph.
        dynamic_frames: make the frame axis dynamic.
        opset: ONNX opset (17 has LayerNormalization).
        verify: run onnxruntime against torch on random input (``frames`` frames, and
            ``frames + 1`` too when the frame axis is dynamic) and report the max errors.
        seed: seed of the random verification input.

    Returns:
        an :class:`ExportReport` (empty ``max_abs_error`` if ``verify`` is false).
    """
    p = model.config.patch_size
    if height % p or width % p:
        raise ValueError(f"height and width must be multiples of {p}, got {height}x{width}")
    model = model.to(device="cpu", dtype=torch.float32).eval()
    example = torch.rand(1, frames, 3, height, width, generator=torch.Generator().manual_seed(seed))
    dynamic_axes = None
    if dynamic_frames:
        dynamic_axes = {name: {1: "frames"} for name in (ONNX_INPUT, *ONNX_OUTPUTS)}
    path = os.fspath(path)
    with _static_pos_embed(model, height, width), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer warnings about shape-derived Python ints
        torch.onnx.export(
            _ExportWrapper(model),
            (example,),
            path,
            input_names=[ONNX_INPUT],
            output_names=list(ONNX_OUTPUTS),
            dynamic_axes=dynamic_axes,
            opset_version=opset,
            do_constant_folding=True,
            dynamo=False,
        )
    errors: dict[int, dict[str, float]] = {}
    if verify:
        counts = [frames, frames + 1] if dynamic_frames else [frames]
        errors = verify_onnx(model, path, counts, height, width, seed=seed + 1)
    return ExportReport(path, frames, height, width, dynamic_frames, errors)


def verify_onnx(
    model: VGGT, path: str | os.PathLike[str], frame_counts: list[int], height: int, width: int, seed: int = 1
) -> dict[int, dict[str, float]]:
    """Max |onnxruntime - torch| per output on seeded random ``[1, S, 3, H, W]`` inputs."""
    from .runners import OnnxRunner

    runner = OnnxRunner(path)
    gen = torch.Generator().manual_seed(seed)
    result: dict[int, dict[str, float]] = {}
    for s in frame_counts:
        x = torch.rand(s, 3, height, width, generator=gen)
        with torch.no_grad():
            ref = model(x[None], frames_chunk_size=None)
        got = runner.forward(x.numpy())
        result[s] = {
            name: float(np.max(np.abs(got[name] - ref[name].numpy())))
            for name in ONNX_OUTPUTS  # type: ignore[union-attr]
        }
    return result

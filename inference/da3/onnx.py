"""ONNX export of Depth Anything 3 (frames axis dynamic) and its onnxruntime runner.

One graph per (model, reference-view strategy, pose conditioning): inputs ``images [B,S,3,H,W]``
(ImageNet-normalised; ``S`` dynamic, ``H, W`` fixed at export) and, pose-conditioned, also
``in_extrinsics [B,S,4,4]`` (w2c) and ``in_intrinsics [B,S,3,3]``.  Outputs: ``depth, depth_conf, ray,
ray_conf, pose_enc, extrinsics, intrinsics, prealt_patch_tokens, ref_view_idx, view_order``
(see :meth:`DA3Net.forward`); a nested model's graph adds ``metric_head_depth`` and ``sky``.

Fixed at export because they depend only on ``H, W``: the DINO position embedding (the official
bicubic resize with scale factors is precomputed), the RoPE tables and the UV position maps.
The reference-view selection is in the graph only if the example has >= 3 frames (as the
official rule; export with >= 3 frames and run with >= 3).  The data-dependent steps stay on
the host in torch, shared with the eager path: sky filling and the metric alignment of the
nested model (:func:`postprocess_nested`), and the ray-pose RANSAC (:mod:`.raypose`).
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from .dinov2 import DA3ViT
from .model import DA3Net
from .nested import NestedDA3Net, metric_align
from .raypose import cameras_from_rays
from .sky import fill_sky

__all__ = ["ANYVIEW_OUTPUTS", "METRIC_OUTPUTS", "export_da3_onnx", "DA3OnnxRunner", "postprocess_nested", "OnnxBackend"]

ANYVIEW_OUTPUTS = (
    "depth",
    "depth_conf",
    "ray",
    "ray_conf",
    "pose_enc",
    "extrinsics",
    "intrinsics",
    "prealt_patch_tokens",
    "ref_view_idx",
    "view_order",
)
METRIC_OUTPUTS = ("metric_head_depth", "sky")
DEFAULT_OPSET = 17


def _metric_heads(metric: DA3Net, images: Tensor) -> tuple[Tensor, Tensor]:
    bb = metric.backbone(images)
    head = metric.head(bb.patch_tokens, tuple(images.shape[-2:]), None)
    return head["depth"], head["sky"]


class _Graph(nn.Module):
    def __init__(self, model: DA3Net | NestedDA3Net, strategy: str) -> None:
        super().__init__()
        self.model = model
        self.strategy = strategy

    def forward(
        self, images: Tensor, extrinsics: Tensor | None = None, intrinsics: Tensor | None = None
    ) -> tuple[Tensor, ...]:
        anyview = self.model.da3 if isinstance(self.model, NestedDA3Net) else self.model
        out = anyview(images, extrinsics, intrinsics, ref_view_strategy=self.strategy, frames_chunk_size=None)
        result = tuple(out[k] for k in ANYVIEW_OUTPUTS)
        if isinstance(self.model, NestedDA3Net):
            result += _metric_heads(self.model.da3_metric, images)
        return result


@contextlib.contextmanager
def _static_pos_embed(model: nn.Module, height: int, width: int) -> Iterator[None]:
    vits = [m for m in model.modules() if isinstance(m, DA3ViT)]
    with torch.no_grad():
        for vit in vits:
            p = vit.cfg.patch_size
            vit.fixed_pos_embed = vit.interpolate_pos_encoding(height // p, width // p).detach().clone()
    try:
        yield
    finally:
        for vit in vits:
            vit.fixed_pos_embed = None


def output_names(model: DA3Net | NestedDA3Net) -> tuple[str, ...]:
    return ANYVIEW_OUTPUTS + (METRIC_OUTPUTS if isinstance(model, NestedDA3Net) else ())


def export_da3_onnx(
    model: DA3Net | NestedDA3Net,
    path: str | os.PathLike[str],
    frames: int,
    height: int,
    width: int,
    ref_view_strategy: str = "saddle_balanced",
    pose_conditioned: bool = False,
    dynamic_frames: bool = True,
    opset: int = DEFAULT_OPSET,
) -> Path:
    """Exports an any-view or nested DA3 model (float32, CPU) to ``path``; returns the path.

    Args:
        frames: frame count of the traced example (>= 3 to include reference-view selection).
        height, width: image size (multiples of 14), fixed in the graph.
        ref_view_strategy: baked into the graph.
        pose_conditioned: the graph also takes ``extrinsics`` and ``intrinsics`` (camera encoder).
    """
    anyview = model.da3 if isinstance(model, NestedDA3Net) else model
    if not anyview.config.camera:
        raise ValueError("export_da3_onnx: metric/mono models are exported through their nested model")
    p = anyview.config.patch_size
    if height % p or width % p:
        raise ValueError(f"height and width must be multiples of {p}, got {height}x{width}")
    model = model.to(device="cpu", dtype=torch.float32).eval()
    gen = torch.Generator().manual_seed(0)
    example: tuple[Tensor, ...] = (torch.randn(1, frames, 3, height, width, generator=gen),)
    inputs = ["images"]
    if pose_conditioned:
        eye = torch.eye(4).expand(1, frames, 4, 4).clone()
        eye[..., :3, 3] = torch.randn(1, frames, 3, generator=gen)
        k = torch.tensor([[width, 0, width / 2], [0, width, height / 2], [0, 0, 1.0]]).expand(1, frames, 3, 3).clone()
        example += (eye, k)
        inputs += ["in_extrinsics", "in_intrinsics"]
    outputs = output_names(model)
    axes = {name: {1: "frames"} for name in (*inputs, *outputs) if name not in ("ref_view_idx",)}
    axes["view_order"] = {1: "frames"}
    path = Path(path)
    with _static_pos_embed(model, height, width), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            _Graph(model, ref_view_strategy),
            example,
            os.fspath(path),
            input_names=inputs,
            output_names=list(outputs),
            dynamic_axes=axes if dynamic_frames else None,
            opset_version=opset,
            do_constant_folding=True,
            dynamo=False,
        )
    return path


def postprocess_nested(out: dict[str, Tensor]) -> dict[str, Tensor]:
    """Host-side end of the nested model on graph outputs: sky filling of the metric depth and
    the metric alignment (:func:`~inference.da3.nested.metric_align`), as in the eager forward."""
    metric_depth = fill_sky(out["metric_head_depth"], out["sky"])
    aligned = metric_align(out, metric_depth, out["sky"])
    aligned["metric_depth"] = metric_depth
    for key in ("depth", "depth_conf", "extrinsics", "intrinsics", "ref_view_idx"):
        aligned[f"anyview_{key}"] = out[key]
    return aligned


class DA3OnnxRunner:
    """Runs an exported DA3 graph with onnxruntime (CPU) and finishes a nested model's output."""

    def __init__(self, path: str | os.PathLike[str], threads: int | None = None) -> None:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = threads
        self.session = ort.InferenceSession(os.fspath(path), opts, providers=["CPUExecutionProvider"])
        self.inputs = [i.name for i in self.session.get_inputs()]
        self.outputs = [o.name for o in self.session.get_outputs()]

    def run(
        self, images: np.ndarray, extrinsics: np.ndarray | None = None, intrinsics: np.ndarray | None = None
    ) -> dict[str, Tensor]:
        feeds = {"images": np.ascontiguousarray(images, dtype=np.float32)}
        if "in_extrinsics" in self.inputs:
            if extrinsics is None or intrinsics is None:
                raise ValueError("this DA3 graph is pose-conditioned: pass extrinsics and intrinsics")
            feeds["in_extrinsics"] = np.ascontiguousarray(extrinsics, dtype=np.float32)
            feeds["in_intrinsics"] = np.ascontiguousarray(intrinsics, dtype=np.float32)
        values = self.session.run(self.outputs, feeds)
        out = {name: torch.from_numpy(np.asarray(v)) for name, v in zip(self.outputs, values)}
        return postprocess_nested(out) if "sky" in out else out


class OnnxBackend:
    """The golden check's onnxruntime backend: exports (and caches) one graph per model, strategy
    and conditioning into ``folder``, traced with another frame count than it is run with."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._runners: dict[tuple[int, str, bool, int], DA3OnnxRunner] = {}

    def run(
        self,
        model: DA3Net | NestedDA3Net,
        images: Tensor,
        strategy: str,
        ext: Tensor | None = None,
        intr: Tensor | None = None,
        use_ray_pose: bool = False,
        ransac_sample_idx: Tensor | None = None,
    ) -> dict[str, np.ndarray]:
        b, s, _, h, w = images.shape
        key = (id(model), strategy, ext is not None, s)
        if key not in self._runners:
            trace_frames = s - 1 if s - 1 >= 3 else (s + 1 if s >= 3 else s)
            name = f"{type(model).__name__}_{strategy}{'_posed' if ext is not None else ''}_{s}.onnx"
            path = export_da3_onnx(model, self.folder / name, trace_frames, h, w, strategy, ext is not None)
            self._runners[key] = DA3OnnxRunner(path)
        out = self._runners[key].run(
            images.numpy(), None if ext is None else ext.numpy(), None if intr is None else intr.numpy()
        )
        if use_ray_pose:
            torch.manual_seed(2024)
            rp = cameras_from_rays(out["ray"], out["ray_conf"], (h, w), ransac_sample_idx)
            out.update(
                extrinsics=rp.extrinsics,
                intrinsics=rp.intrinsics,
                ransac_sample_idx=rp.sample_idx,
                ransac_homography=rp.homography,
            )
        result = {k: v.numpy() for k, v in out.items()}
        result["metric_sky"] = result.get("sky", np.zeros(0))
        return result

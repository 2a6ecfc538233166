"""ONNX export of π³ / π³X and the onnxruntime runner.

Graph inputs: ``images [1, S, 3, H, W]`` (float32 RGB in [0, 1]; ``S`` dynamic, ``H, W``
fixed), and for a π³X with its multimodal branches the PREPARED conditions
(:class:`~inference.pi3.conditioning.PreparedConditions`, computed on the host by the same
torch code as the eager model): ``depth_input [S, 2, H, W]``, ``rays_xy [S, 2, H, W]``,
``poses [1, S, 4, 4]``, ``mask_depth / mask_ray / mask_pose [1, S]`` (float 0/1).  One graph
serves the unconditioned and every (partially) conditioned run: all branches run and are
multiplied by their masks (``Pi3X.static_graph``).

Graph outputs: the raw head outputs ``local_points, conf, rot9, trans, dino_patch_tokens``
(π³X also ``rays, metric``).  ONNX has no SVD, so the pose orthogonalisation and the world
points are done on the host by :func:`inference.pi3.model.assemble`, the function the torch
model uses.  As for VGGT (:mod:`inference.onnx_export`), the DINO position embeddings are
precomputed for the export size (bicubic antialiased interpolation has no ONNX equivalent).
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from swiftjax.prediction import ChunkPrediction

from ..runners import ort_session
from .conditioning import Conditions, PreparedConditions, prepare_conditions
from .convert import to_chunk_prediction
from .model import Pi3Base, assemble

__all__ = ["export_pi3_onnx", "Pi3OnnxRunner", "RAW_OUTPUTS", "CONDITION_INPUTS"]

DEFAULT_OPSET = 17
RAW_OUTPUTS = ("local_points", "conf", "rot9", "trans", "dino_patch_tokens")
PI3X_OUTPUTS = ("rays", "metric")
CONDITION_INPUTS = ("depth_input", "rays_xy", "poses", "mask_depth", "mask_ray", "mask_pose")


def _is_conditioned(model: Pi3Base) -> bool:
    return model.config.variant == "pi3x" and model.config.multimodal


def _output_names(model: Pi3Base) -> tuple[str, ...]:
    return RAW_OUTPUTS + (PI3X_OUTPUTS if model.config.variant == "pi3x" else ())


class _Wrapper(nn.Module):
    def __init__(self, model: Pi3Base) -> None:
        super().__init__()
        self.model = model
        self.names = _output_names(model)

    def forward(self, images: Tensor, *cond: Tensor) -> tuple[Tensor, ...]:
        if cond:
            depth_input, rays_xy, poses, m_depth, m_ray, m_pose = cond
            prep = PreparedConditions(
                depth_input, rays_xy, poses, torch.ones_like(m_depth[:, 0]), m_depth, m_ray, m_pose
            )
            raw = self.model.forward_prepared(images, prep)  # type: ignore[operator]
        elif self.model.config.variant == "pi3x":
            raw = self.model.forward_prepared(images, None)  # type: ignore[operator]
        else:
            raw = self.model.forward_raw(images)  # type: ignore[operator]
        return tuple(raw[k] for k in self.names)


@contextlib.contextmanager
def _export_mode(model: Pi3Base, height: int, width: int) -> Iterator[None]:
    p = model.config.patch_size
    vits = [model.encoder] + ([model.depth_encoder] if _is_conditioned(model) else [])  # type: ignore[list-item]
    with torch.no_grad():
        for vit in vits:
            vit.fixed_pos_embed = vit.interpolate_pos_encoding(height // p, width // p).detach().clone()
    static = getattr(model, "static_graph", None)
    if static is not None:
        model.static_graph = True  # type: ignore[attr-defined]
    try:
        yield
    finally:
        for vit in vits:
            vit.fixed_pos_embed = None
        if static is not None:
            model.static_graph = static  # type: ignore[attr-defined]


def _condition_arrays(prep: PreparedConditions) -> list[Tensor]:
    return [
        prep.depth_input,
        prep.rays_xy,
        prep.poses,
        prep.mask_depth.float(),
        prep.mask_ray.float(),
        prep.mask_pose.float(),
    ]


def export_pi3_onnx(
    model: Pi3Base,
    path: str | os.PathLike[str],
    frames: int,
    height: int,
    width: int,
    opset: int = DEFAULT_OPSET,
    seed: int = 0,
) -> str:
    """Exports ``model`` (moved to CPU float32 eval) to ``path`` with a dynamic frame axis.

    Traced on seeded random images of ``frames`` frames (``>= 2``: π³X's pose condition needs
    two posed views), all conditions on.  Returns the path.
    """
    p = model.config.patch_size
    if height % p or width % p:
        raise ValueError(f"height and width must be multiples of {p}, got {height}x{width}")
    if frames < 2:
        raise ValueError(f"trace with at least 2 frames, got {frames}")
    model = model.to(device="cpu", dtype=torch.float32).eval()
    gen = torch.Generator().manual_seed(seed)
    images = torch.rand(1, frames, 3, height, width, generator=gen)
    args: list[Tensor] = [images]
    input_names = ["images"]
    dynamic: dict[str, dict[int, str]] = {"images": {1: "frames"}}
    if _is_conditioned(model):
        K = torch.tensor([[float(width), 0, width / 2], [0, float(width), height / 2], [0, 0, 1]])
        poses = torch.eye(4).repeat(1, frames, 1, 1)
        poses[..., 2, 3] = torch.arange(frames, dtype=torch.float32)
        cond = Conditions(
            intrinsics=K.expand(1, frames, 3, 3),
            depths=torch.rand(1, frames, height, width, generator=gen) + 1,
            poses=poses,
        )
        args += _condition_arrays(prepare_conditions(cond, 1, frames, height, width, torch.device("cpu")))
        input_names += list(CONDITION_INPUTS)
        dynamic.update(
            {
                "depth_input": {0: "frames"},
                "rays_xy": {0: "frames"},
                "poses": {1: "frames"},
                "mask_depth": {1: "frames"},
                "mask_ray": {1: "frames"},
                "mask_pose": {1: "frames"},
            }
        )
    names = _output_names(model)
    for name in names:
        if name != "metric":
            dynamic[name] = {1: "frames"}
    path = os.fspath(path)
    with _export_mode(model, height, width), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer warnings about shape-derived Python ints
        torch.onnx.export(
            _Wrapper(model),
            tuple(args),
            path,
            input_names=input_names,
            output_names=list(names),
            dynamic_axes=dynamic,
            opset_version=opset,
            do_constant_folding=True,
            dynamo=False,
        )
    return path


class Pi3OnnxRunner:
    """Runs a graph written by :func:`export_pi3_onnx` with onnxruntime.

    Args:
        path: the ``.onnx`` file.
        providers: onnxruntime execution providers (default: CPU).
        intra_op_threads: threads per operator (0 = onnxruntime's default).
    """

    def __init__(
        self, path: str | os.PathLike[str], providers: Sequence[str] | None = None, intra_op_threads: int = 0
    ) -> None:
        self.session = ort_session(path, providers, intra_op_threads)
        self.inputs = [i.name for i in self.session.get_inputs()]
        self.outputs = [o.name for o in self.session.get_outputs()]
        self.image_hw = tuple(self.session.get_inputs()[0].shape[3:5])
        if self.inputs[0] != "images" or not set(RAW_OUTPUTS) <= set(self.outputs):
            raise ValueError(f"{path}: not a π³ graph (inputs {self.inputs}, outputs {self.outputs})")

    @property
    def conditioned(self) -> bool:
        return "mask_pose" in self.inputs

    def forward(self, images: Any, conditions: Conditions | None = None) -> dict[str, np.ndarray]:
        """``images [S, 3, H, W]`` -> the π³ outputs without the batch axis (``metric``: ``[1]``)."""
        arr = np.asarray(images, dtype=np.float32)
        if arr.ndim != 4 or arr.shape[1] != 3:
            raise ValueError(f"images must be [S, 3, H, W], got shape {arr.shape}")
        if tuple(arr.shape[2:]) != self.image_hw:
            raise ValueError(
                f"the graph was exported for {self.image_hw[0]}x{self.image_hw[1]} images, got "
                f"{arr.shape[2]}x{arr.shape[3]}: export again for this size"
            )
        feed: dict[str, np.ndarray] = {"images": arr[None]}
        if self.conditioned:
            s, _, h, w = arr.shape
            prep = prepare_conditions(conditions or Conditions(), 1, s, h, w, torch.device("cpu"))
            feed.update({n: t.numpy() for n, t in zip(CONDITION_INPUTS, _condition_arrays(prep))})
        elif conditions is not None:
            raise ValueError("this graph takes no conditions (π³, or π³X exported without multimodal branches)")
        raw = dict(zip(self.outputs, self.session.run(self.outputs, feed)))
        out = assemble({k: torch.from_numpy(v) for k, v in raw.items()})
        return {k: (v.numpy() if k == "metric" else v[0].numpy()) for k, v in out.items()}

    def predict(self, images: Any, conditions: Conditions | None = None) -> ChunkPrediction:
        """One chunk -> :class:`ChunkPrediction` (see :mod:`inference.pi3.convert`)."""
        return to_chunk_prediction(self.forward(images, conditions), images=images)

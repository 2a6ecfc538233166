"""Depth Anything 3 as a backbone (the clean-room network of :mod:`inference.da3`).

Conventions (``shared/golden/da3/README.txt``) and what this module does with them:

* Preprocessing: the official input processor (:func:`inference.preprocess.preprocess_da3`,
  longer side 504, sides to multiples of 14; KITTI 1241 x 376 -> 504 x 154); the ImageNet
  mean/std are applied by the runner, outside the network, as the official API does.
* Frame: DA3's extrinsics are world-to-camera in the REFERENCE view's frame (the view that
  ``ref_view_strategy`` picks); :class:`~swiftjax.prediction.ChunkPrediction`'s are in the
  chunk's FIRST camera's frame.  :func:`rebase_extrinsics` maps one to the other exactly
  (``E_i' = E_i E_0^-1`` in 4 x 4 form), whatever the strategy.  Depth is per camera and does
  not change; the nested model's translations are already metric-scaled.
* Confidence ``depth_conf = 1 + exp(.) >= 1``, as VGGT's: the reliability mask
  (``gamma > lambda_gamma mean gamma``) and the point filter keep their meaning.
* Loop tokens: the patch tokens of block ``alt_start - 1`` (final LayerNorm; before any
  cross-view attention, so each depends on its own image only), ``[S, h*w, C]`` in input order,
  reduced to descriptors by the pipeline as VGGT's DINO tokens are.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np

from swiftjax.prediction import ChunkPrediction

from ..device import model_math, runner_device, to_host
from ..runners import check_outputs
from .header import FAMILY_TEXT, checkpoint_header, compare_shapes, describe_family

__all__ = ["rebase_extrinsics", "to_prediction", "DA3Runner"]

name = "da3"
modes = ("resize", "crop")
PROCESS_RES = 504
REF_VIEW_STRATEGY = "saddle_balanced"  # the official default (DA3-Streaming: saddle_balanced / middle)


# ------------------------------------------------------------------------ configuration


def _config_object(backbone: Any, config: dict[str, Any] | None) -> Any:
    """The :class:`~inference.da3.config.DA3Config` / ``NestedDA3Config`` of a JSON-able dict
    (``None``: the backbone's preset)."""
    from inference.da3.config import DA3Config, NestedDA3Config, preset_config

    if config is None:
        return preset_config(backbone.preset)

    def one(d: dict[str, Any]) -> Any:
        return DA3Config(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

    if "anyview" in config:
        return NestedDA3Config(one(config["anyview"]), one(config["metric"]))
    return one(config)


def load_config(backbone: Any, path: Any | None) -> dict[str, Any] | None:
    """``None`` for the preset, else the model of ``path`` (a ``tiny_config.json``-layout file:
    its nested section for the nested backbone, its main section otherwise) as a dict."""
    if path is None:
        return None
    from inference.da3.config import DA3Config, NestedDA3Config

    cls = NestedDA3Config if backbone.metric else DA3Config
    return dataclasses.asdict(cls.from_json(path))


# ------------------------------------------------------------------------- checkpoints


def _expected_shapes(backbone: Any, config: dict[str, Any] | None) -> dict[str, tuple[int, ...]]:
    """Checkpoint key -> shape the model expects (``model.`` prefix; the shared LayerNorm's aliases
    may be absent from files, handled by the caller)."""
    from inference.da3 import build_da3

    model = build_da3(_config_object(backbone, config), device="meta")
    return {f"model.{k}": tuple(v.shape) for k, v in model.state_dict().items()}


def check_checkpoint(backbone: Any, path: Any, config: dict[str, Any] | None) -> None:
    """The file's family (key names), completeness and every shape against the model, from the
    safetensors header alone (one line naming the first differing keys)."""
    from inference.checkpoint import CheckpointError

    p = os.fspath(path)
    if not p.lower().endswith(".safetensors"):
        raise CheckpointError(f"--weights {p}: Depth Anything 3 weights are read from .safetensors (model.safetensors)")
    header = checkpoint_header(p)
    fam = describe_family(header)
    want = "da3-nested" if backbone.metric else "da3"
    if fam != want:
        raise CheckpointError(
            f"--weights {p} is {FAMILY_TEXT[fam]}, not what --model {backbone.name} needs ({FAMILY_TEXT[want]})"
        )
    expected = _expected_shapes(backbone, config)
    got = {k: s for k, (_, s) in header.items()}
    aliases = [
        k
        for k in expected
        if ".output_conv2_aux." in k
        and ".output_conv2_aux.0." not in k
        and k.rsplit(".", 2)[-2] == "2"
        and k not in got
    ]  # the DualDPT LayerNorm stored once
    compare_shapes(p, got, {k: v for k, v in expected.items() if k not in aliases}, f"{backbone.name} model")


# ------------------------------------------------------------------------ preprocessing


def preprocess(images: list[Any], mode: str) -> np.ndarray:
    from inference.preprocess import preprocess_da3

    return preprocess_da3(images, mode=mode, process_res=PROCESS_RES)


def preprocess_geometry(height: int, width: int, mode: str) -> Any:
    from swiftjax.intrinsics import da3_preprocess_geometry

    return da3_preprocess_geometry(height, width, mode, PROCESS_RES)


# --------------------------------------------------------------------------- conversion


def rebase_extrinsics(extrinsics: np.ndarray) -> np.ndarray:
    """World-to-camera ``[S, 3, 4]`` in any world frame -> the same cameras in the frame of
    camera 0: ``E_i' = E_i E_0^-1`` (4 x 4), so ``E_0' = [I | 0]``.  Computed in float64
    (``E_0^-1 = [R_0^T | -R_0^T t_0]``), returned float32."""
    E = np.asarray(extrinsics, np.float64)
    R0, t0 = E[0, :, :3], E[0, :, 3]
    R = E[:, :, :3] @ R0.T
    t = E[:, :, 3] - R @ t0
    return np.concatenate([R, t[:, :, None]], axis=2).astype(np.float32)


def to_prediction(images: np.ndarray, out: dict[str, np.ndarray]) -> ChunkPrediction:
    """One scene's DA3 outputs (batch axis removed, NumPy) -> :class:`ChunkPrediction`.

    ``images``: ``[S, 3, H, W]`` in [0, 1] (colours).  ``out``: ``depth [S,H,W]``,
    ``depth_conf [S,H,W]``, ``extrinsics [S,3,4]`` (reference-view frame), ``intrinsics
    [S,3,3]``, ``prealt_patch_tokens [S,h,w,C]`` in input order.
    """
    from inference.preprocess import to_uint8_images

    tokens = np.asarray(out["prealt_patch_tokens"], np.float32)
    return ChunkPrediction(
        depth=np.ascontiguousarray(out["depth"], dtype=np.float32),
        conf=np.ascontiguousarray(out["depth_conf"], dtype=np.float32),
        extrinsic=rebase_extrinsics(out["extrinsics"]),
        intrinsic=np.ascontiguousarray(out["intrinsics"], dtype=np.float32),
        patch_tokens=np.ascontiguousarray(tokens.reshape(tokens.shape[0], -1, tokens.shape[-1])),
        images=to_uint8_images(images),
    )


# ------------------------------------------------------------------------------ runner


class DA3Runner:
    """Runs a clean-room DA3 network in torch: ImageNet-normalises ``[S, 3, H, W]`` frames in
    [0, 1], one forward (``ref_view_strategy``), :func:`to_prediction`.

    ``dtype``: ``torch.float32`` or a reduced type applied with ``torch.autocast`` around the
    network (the official API runs it so; the camera encoder, heads and camera decoding stay
    float32 inside the network).
    """

    def __init__(
        self, model: Any, device: Any = "cpu", dtype: Any = None, ref_view_strategy: str = REF_VIEW_STRATEGY
    ) -> None:
        import torch

        self.device = runner_device(device)
        self.dtype = dtype or torch.float32
        self.model = model.to(self.device).eval()
        self.ref_view_strategy = ref_view_strategy
        self.name = "Depth Anything 3"  # for messages; build_runner names the preset and weights

    def forward(self, images: Any) -> dict[str, Any]:
        """Raw network outputs (torch, batch axis 1) for ``[S, 3, H, W]`` frames in [0, 1]."""
        import torch

        from inference.preprocess import IMAGENET_MEAN, IMAGENET_STD

        arr = np.asarray(images, np.float32)
        if arr.ndim != 4 or arr.shape[1] != 3:
            raise ValueError(f"images must be [S, 3, H, W], got shape {arr.shape}")
        mean = np.asarray(IMAGENET_MEAN, np.float32)[:, None, None]
        std = np.asarray(IMAGENET_STD, np.float32)[:, None, None]
        x = torch.as_tensor((arr - mean) / std, device=self.device)[None]
        with model_math(self.device, self.dtype):
            return self.model(x, ref_view_strategy=self.ref_view_strategy)

    def predict(self, images: Any) -> ChunkPrediction:
        arr = np.asarray(images, np.float32)
        raw = self.forward(arr)
        # prealt_patch_tokens come back in input order (inference.da3 undoes the reference reordering)
        out = to_host(
            {k: raw[k][0] for k in ("depth", "depth_conf", "extrinsics", "intrinsics", "prealt_patch_tokens")}
        )
        check_outputs(out, self.name)
        return to_prediction(arr, out)


def build_runner(backbone: Any, weights: str, device: str, dtype: str, config: dict[str, Any] | None) -> DA3Runner:
    import torch

    from inference.da3 import build_da3, load_da3_checkpoint

    model = build_da3(_config_object(backbone, config), device="meta")
    load_da3_checkpoint(model, weights)
    torch_dtype = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}[dtype]
    runner = DA3Runner(model, device=device, dtype=torch_dtype)
    runner.name = f"{backbone.name} ({weights}, {dtype})"  # named in a non-finite-output error
    return runner

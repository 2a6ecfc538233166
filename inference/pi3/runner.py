"""A torch runner for π³ / π³X: one chunk of frames -> :class:`ChunkPrediction`."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from swiftjax.options import OptionError
from swiftjax.prediction import ChunkPrediction

from ..device import model_math, runner_device, to_host
from ..runners import ModelOutputError, check_outputs
from .conditioning import Conditions, intrinsics_condition
from .convert import to_chunk_prediction
from .model import Pi3Base

__all__ = ["Pi3TorchRunner"]


class Pi3TorchRunner:
    """Runs a :class:`~inference.pi3.model.Pi3` or :class:`~inference.pi3.pi3x.Pi3X`.

    Args:
        model: the network (float32 weights).
        device: ``"cpu"``, ``"cuda"``, ...
        dtype: compute dtype; bfloat16 / float16 run the trunk under ``torch.autocast`` (the
            heads are evaluated in float32 as upstream does, since they read ``.float()``).
        intrinsics: π³X only: ``[3, 3]`` swiftjax intrinsics at the model resolution, passed
            to every chunk as the ray condition (``--intrinsics``).
    """

    def __init__(
        self,
        model: Pi3Base,
        device: str | torch.device = "cpu",
        dtype: torch.dtype | None = None,
        intrinsics: Any | None = None,
    ) -> None:
        self.device = runner_device(device)
        self.dtype = dtype or torch.float32
        self.model = model.to(self.device).eval()
        self.name = f"π³ ({model.config.variant})"  # for messages (a non-finite output)
        if intrinsics is not None and model.config.variant != "pi3x":
            raise OptionError("--intrinsics as a condition needs π³X (π³ takes no conditions)")
        self.intrinsics = None if intrinsics is None else np.asarray(intrinsics, dtype=np.float64)

    def forward(self, images: Any, conditions: Conditions | None = None) -> dict[str, torch.Tensor]:
        """Raw outputs (batch axis 1) for ``[S, 3, H, W]`` images in [0, 1]."""
        arr = np.asarray(images, dtype=np.float32)
        if arr.ndim != 4 or arr.shape[1] != 3:
            raise ValueError(f"images must be [S, 3, H, W], got shape {arr.shape}")
        if conditions is None and self.intrinsics is not None:
            conditions = intrinsics_condition(self.intrinsics, arr.shape[0])
        x = torch.from_numpy(arr).to(self.device)[None]
        args = () if self.model.config.variant == "pi3" else (_to(conditions, self.device),)
        try:
            with model_math(self.device, self.dtype):
                return self.model(x, *args)
        except torch.linalg.LinAlgError as err:  # the pose SVD of a non-finite camera head output
            raise ModelOutputError(
                f"{self.name} predicted non-finite values (NaN/inf) in its camera poses ({err}): the weights hold "
                "NaN/inf or overflow (check the checkpoint; with --dtype float16 try bfloat16 or float32)"
            ) from None

    def predict(self, images: Any, conditions: Conditions | None = None) -> ChunkPrediction:
        """One chunk -> :class:`ChunkPrediction` (:mod:`inference.pi3.convert`)."""
        out = self.forward(images, conditions)
        scene = to_host({k: v[0] for k, v in out.items() if k != "metric"})  # one move to the host
        check_outputs(
            {k: v for k, v in scene.items() if k in ("local_points", "conf", "camera_poses", "dino_patch_tokens")},
            self.name,
        )
        return to_chunk_prediction(scene, images=images)


def _to(cond: Conditions | None, device: torch.device) -> Conditions | None:
    if cond is None:
        return None
    moved = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in vars(cond).items()}
    return Conditions(**moved)

"""Self-check of π³ / π³X against the golden tensors of the official code (``shared/golden/pi3``).

Run through ``python -m inference.check_golden DIR`` (which dispatches here when
``DIR/tiny_config.json`` is a π³ one).

* torch: every golden key (outputs and intermediates) of π³ and of the three π³X runs
  (``uncond``: no condition; ``cond``: intrinsics + depth + poses on every view;
  ``condpartial``: the masked mixture), captured through the models' ``trace`` dict;
* onnxruntime: the outputs (``points, local_points, conf, camera_poses, dino_patch_tokens``,
  π³X also ``rays, metric``) of graphs exported with a dynamic frame axis, traced with a
  different frame count than the golden one; the π³X graph takes the prepared conditions as
  inputs, so one graph serves the three runs.

Tolerance, for every key: ``|got - ref| <= 1e-4 + 1e-4 |ref|`` -- the golden README's stated
fp32-CPU tolerance (``stated_fp32_cpu_atol/rtol``), not tuned to this set.  It bounds the
kernel-order differences between two float32 implementations of the same maths (observed
<= 4e-6 on this set: 25x margin); the ``exp`` of the depth and the SVD of the pose amplify
such differences, which the relative term covers on large depths.  ``decode_pos`` (integer
positions) must be exact.
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..check_golden import Check

__all__ = ["ATOL", "RTOL", "EXACT_KEYS", "PI3X_RUNS", "REQUIRED_FILES", "run_checks", "run_pi3_checks", "torch_outputs"]

ATOL = 1e-4
RTOL = 1e-4
EXACT_KEYS = ("decode_pos",)
PI3X_RUNS = ("uncond", "cond", "condpartial")
_INPUT_KEYS = ("input_imgs", "forward_input_imgs")
REQUIRED_FILES = (
    "tiny_config.json",
    "tiny_weights.safetensors",
    "tiny_golden.npz",
    "tiny_weights_pi3x.safetensors",
    "tiny_golden_pi3x.npz",
)


def compare(backend: str, name: str, got: np.ndarray, ref: np.ndarray) -> Check:
    """``got`` vs ``ref`` under the module's tolerance (exact for :data:`EXACT_KEYS`)."""
    exact = name.rsplit(".", 1)[-1] in EXACT_KEYS
    atol, rtol = (0.0, 0.0) if exact else (ATOL, RTOL)
    got = np.asarray(got, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if got.size != ref.size:
        return Check(backend, f"{name} (shape {got.shape} != {ref.shape})", np.inf, np.inf, atol, rtol, False)
    got = got.reshape(ref.shape)
    diff = np.abs(got - ref)
    rel = diff / np.maximum(np.abs(ref), 1e-12)
    passed = bool(np.all(np.isfinite(got)) and np.all(diff <= atol + rtol * np.abs(ref)))
    return Check(backend, name, float(diff.max(initial=0.0)), float(rel.max(initial=0.0)), atol, rtol, passed)


def _load(directory: Path, variant: str) -> tuple[Any, dict[str, np.ndarray]]:
    from .checkpoint import load_pi3_checkpoint
    from .config import Pi3Config
    from .model import Pi3
    from .pi3x import Pi3X

    suffix = "" if variant == "pi3" else "_pi3x"
    cfg = Pi3Config.from_json(directory / "tiny_config.json", variant)  # type: ignore[arg-type]
    model = (Pi3 if variant == "pi3" else Pi3X)(cfg).eval()
    load_pi3_checkpoint(model, directory / f"tiny_weights{suffix}.safetensors")
    with np.load(directory / f"tiny_golden{suffix}.npz") as z:
        golden = {k: z[k] for k in z.files}
    return model, golden


def golden_conditions(golden: Mapping[str, np.ndarray], run: str) -> Any:
    """The :class:`~inference.pi3.conditioning.Conditions` of one π³X golden run."""
    import torch

    from .conditioning import Conditions

    def get(name: str) -> Any:
        key = f"{run}.cond_input.{name}"
        return torch.from_numpy(golden[key]) if key in golden else None

    return Conditions(
        intrinsics=get("intrinsics"),
        depths=get("depths"),
        poses=get("poses"),
        mask_depth=get("mask_add_depth"),
        mask_ray=get("mask_add_ray"),
        mask_pose=get("mask_add_pose"),
    )


def torch_outputs(model: Any, golden: Mapping[str, np.ndarray], run: str | None) -> dict[str, np.ndarray]:
    """Outputs and traced intermediates of one run, keyed like the golden file."""
    import torch

    images = torch.from_numpy(golden["input_imgs"])
    trace: dict[str, torch.Tensor] = {}
    with torch.no_grad():
        if run is None:
            out = model(images, trace=trace)
        else:
            out = model(images, golden_conditions(golden, run), trace=trace)
    prefix = "" if run is None else f"{run}."
    merged = {**trace, **{k: v for k, v in out.items() if k != "dino_patch_tokens"}}
    return {prefix + k: v.detach().numpy() for k, v in merged.items()}


def _compare_all(
    backend: str,
    outputs: Mapping[str, np.ndarray],
    golden: Mapping[str, np.ndarray],
    prefix: str = "",
    required: Sequence[str] | None = None,
) -> list[Check]:
    keys = (
        required
        if required is not None
        else [
            k
            for k in golden
            if k.startswith(prefix) and k.split(":")[-1] not in _INPUT_KEYS and ".cond_input." not in k
        ]
    )
    checks = []
    for k in keys:
        if k in outputs:
            checks.append(compare(backend, k, outputs[k], golden[k]))
        else:
            checks.append(Check(backend, f"{k} (not produced)", np.inf, np.inf, ATOL, RTOL, False))
    return checks


def run_checks(directory: str | Path, onnx: bool = True, onnx_dir: str | Path | None = None) -> list[Check]:
    """π³ then π³X (three runs), torch and (unless ``onnx=False``) onnxruntime."""
    d = Path(directory)
    checks: list[Check] = []
    pi3, g3 = _load(d, "pi3")
    checks += _compare_all(
        "torch",
        {f"pi3:{k}": v for k, v in torch_outputs(pi3, g3, None).items()},
        {f"pi3:{k}": v for k, v in g3.items()},
    )
    pi3x, gx = _load(d, "pi3x")
    for run in PI3X_RUNS:
        out = torch_outputs(pi3x, gx, run)
        checks += _compare_all(
            "torch",
            {f"pi3x:{k}": v for k, v in out.items()},
            {f"pi3x:{k}": v for k, v in gx.items()},
            prefix=f"pi3x:{run}.",
        )
    if onnx:
        with tempfile.TemporaryDirectory() as tmp:
            where = Path(onnx_dir) if onnx_dir is not None else Path(tmp)
            where.mkdir(parents=True, exist_ok=True)
            checks += _onnx_checks(pi3, g3, pi3x, gx, where)
    return checks


def run_pi3_checks(directory: str | Path, onnx: bool = True, onnx_path: str | Path | None = None) -> list[Check]:
    """:func:`run_checks` with ``check_golden``'s family signature (``onnx_path``: a folder)."""
    return run_checks(directory, onnx=onnx, onnx_dir=onnx_path)


def _per_scene(runner: Any, images: np.ndarray, conditions: Any = None) -> dict[str, np.ndarray]:
    """The runner (one scene per call) over every scene of ``images [B, S, 3, H, W]``, stacked
    back to the golden layout (``metric [B]``, ``dino_patch_tokens [B*S, P, C]``)."""
    import dataclasses

    import torch

    outs = []
    for b in range(images.shape[0]):
        cond = None
        if conditions is not None:
            cond = dataclasses.replace(
                conditions,
                **{
                    f.name: getattr(conditions, f.name)[b : b + 1]
                    for f in dataclasses.fields(conditions)
                    if isinstance(getattr(conditions, f.name), torch.Tensor)
                },
            )
        outs.append(runner.forward(images[b], cond))
    stacked = {k: np.stack([o[k] for o in outs]) for k in outs[0]}
    stacked["metric"] = stacked["metric"].reshape(-1) if "metric" in stacked else None
    stacked["dino_patch_tokens"] = stacked["dino_patch_tokens"].reshape(-1, *stacked["dino_patch_tokens"].shape[2:])
    return {k: v for k, v in stacked.items() if v is not None}


def _onnx_checks(
    pi3: Any, g3: Mapping[str, np.ndarray], pi3x: Any, gx: Mapping[str, np.ndarray], where: Path
) -> list[Check]:
    from .onnx import Pi3OnnxRunner, export_pi3_onnx

    checks: list[Check] = []
    s, h, w = g3["input_imgs"].shape[1], g3["input_imgs"].shape[3], g3["input_imgs"].shape[4]
    # Traced with one frame fewer than the golden input: exercises the dynamic frame axis.
    export_pi3_onnx(pi3, where / "pi3.onnx", frames=max(2, s - 1), height=h, width=w)
    out = _per_scene(Pi3OnnxRunner(where / "pi3.onnx"), g3["input_imgs"])
    keys = [k for k in ("points", "local_points", "conf", "camera_poses", "dino_patch_tokens") if k in g3]
    checks += _compare_all(
        "onnxruntime",
        {f"pi3:{k}": v for k, v in out.items()},
        {f"pi3:{k}": v for k, v in g3.items()},
        required=[f"pi3:{k}" for k in keys],
    )
    s, h, w = gx["input_imgs"].shape[1], gx["input_imgs"].shape[3], gx["input_imgs"].shape[4]
    export_pi3_onnx(pi3x, where / "pi3x.onnx", frames=max(2, s - 1), height=h, width=w)
    runner = Pi3OnnxRunner(where / "pi3x.onnx")
    for run in PI3X_RUNS:
        out = _per_scene(runner, gx["input_imgs"], golden_conditions(gx, run))
        names = ("points", "local_points", "conf", "camera_poses", "rays", "metric", "dino_patch_tokens")
        keys = [f"pi3x:{run}.{k}" for k in names if f"{run}.{k}" in gx]
        checks += _compare_all(
            "onnxruntime",
            {f"pi3x:{run}.{k}": v for k, v in out.items()},
            {f"pi3x:{k}": v for k, v in gx.items()},
            required=keys,
        )
    return checks

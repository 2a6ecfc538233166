"""Self-check of the VGGT (or Depth Anything 3) implementation against reference tensors from the official code.

Usage::

    python -m inference.check_golden DIR [--no-onnx] [--onnx-path FILE]

``DIR`` holds ``tiny_config.json``, ``tiny_weights.safetensors``, ``tiny_images.npy`` and
``tiny_golden.npz`` (the layout of ``shared/golden/vggt``).  The family is read from
``tiny_config.json``: a Depth Anything 3 set (``shared/golden/da3`` layout) is checked by
:mod:`inference.da3.golden` (its keys and tolerances are described there).  The model is built from the
config, loaded with strict key checking, run in torch and — unless ``--no-onnx`` — exported to
ONNX and run with onnxruntime.  Every golden output a backend produces is compared; a table of
max abs / rel errors is printed and the exit status is 1 if any output is beyond tolerance
(tokens and pose: atol 1e-5; depth, confidence and intrinsics: rtol 1e-4).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["Check", "TOLERANCES", "compare", "run_checks", "main"]

# output -> (atol, rtol); an element passes if |got - ref| <= atol + rtol * |ref|.
TOLERANCES: dict[str, tuple[float, float]] = {
    "patch_tokens": (1e-5, 0.0),
    "aggregated_tokens_all": (1e-5, 0.0),
    "aggregated_tokens_dpt": (1e-5, 0.0),
    "pose_enc": (1e-5, 0.0),
    "pose_enc_list": (1e-5, 0.0),
    "extrinsic": (1e-5, 0.0),
    "intrinsic": (0.0, 1e-4),
    "depth": (0.0, 1e-4),
    "depth_conf": (0.0, 1e-4),
}


@dataclasses.dataclass(frozen=True)
class Check:
    """One output of one backend compared with the golden array."""

    backend: str
    name: str
    max_abs: float
    max_rel: float
    atol: float
    rtol: float
    passed: bool


def compare(backend: str, name: str, got: np.ndarray, ref: np.ndarray) -> Check:
    """Compares ``got`` with ``ref`` (same shape required) under ``TOLERANCES[name]``."""
    atol, rtol = TOLERANCES[name]
    got = np.asarray(got, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if got.shape != ref.shape:
        return Check(backend, f"{name} (shape {got.shape} != {ref.shape})", np.inf, np.inf, atol, rtol, False)
    diff = np.abs(got - ref)
    rel = diff / np.maximum(np.abs(ref), 1e-12)
    passed = bool(np.all(diff <= atol + rtol * np.abs(ref)))
    return Check(backend, name, float(diff.max()), float(rel.max()), atol, rtol, passed)


def _torch_outputs(model: object, images: np.ndarray) -> dict[str, np.ndarray]:
    import torch

    from .pose_encoding import pose_encoding_to_extrinsics_intrinsics

    with torch.no_grad():
        out = model(torch.from_numpy(images), return_aggregated=True)  # type: ignore[operator]
    agg = torch.stack(out["aggregated_tokens"]).numpy()
    idx = list(model.config.dpt_intermediate_layer_idx)  # type: ignore[attr-defined]
    pose = out["pose_enc"].numpy()
    ext, intr = pose_encoding_to_extrinsics_intrinsics(pose, images.shape[-2:])
    return {
        "patch_tokens": out["patch_tokens"].numpy(),
        "aggregated_tokens_all": agg,
        "aggregated_tokens_dpt": agg[idx],
        "pose_enc": pose,
        "pose_enc_list": torch.stack(out["pose_enc_list"]).numpy(),
        "extrinsic": ext,
        "intrinsic": intr,
        "depth": out["depth"].numpy(),
        "depth_conf": out["depth_conf"].numpy(),
    }


def _onnx_outputs(model: object, images: np.ndarray, onnx_path: Path) -> dict[str, np.ndarray]:
    from .onnx_export import export_onnx
    from .pose_encoding import pose_encoding_to_extrinsics_intrinsics
    from .runners import OnnxRunner

    b, s, _, h, w = images.shape
    if b != 1:
        raise ValueError("the ONNX check supports one scene (B = 1)")
    # Trace with a different frame count than the golden one, so that the check also
    # exercises the dynamic frame axis.
    export_onnx(model, onnx_path, frames=max(1, s - 1), height=h, width=w, dynamic_frames=True, verify=False)  # type: ignore[arg-type]
    raw = OnnxRunner(onnx_path).forward(images[0])
    ext, intr = pose_encoding_to_extrinsics_intrinsics(raw["pose_enc"], (h, w))
    return {**raw, "extrinsic": ext, "intrinsic": intr}


def run_checks(directory: str | Path, onnx: bool = True, onnx_path: str | Path | None = None) -> list[Check]:
    """Builds, loads and runs the model on the golden inputs; returns every comparison."""
    from .checkpoint import load_checkpoint
    from .config import VGGTConfig
    from .model import VGGT

    d = Path(directory)
    model = VGGT(VGGTConfig.from_json(d / "tiny_config.json")).eval()
    load_checkpoint(model, d / "tiny_weights.safetensors")
    images = np.load(d / "tiny_images.npy").astype(np.float32)
    golden = np.load(d / "tiny_golden.npz")
    checks = _compare_all("torch", _torch_outputs(model, images), golden)
    if onnx:
        if onnx_path is None:
            with tempfile.TemporaryDirectory() as tmp:
                outputs = _onnx_outputs(model, images, Path(tmp) / "vggt.onnx")
        else:
            outputs = _onnx_outputs(model, images, Path(onnx_path))
        checks += _compare_all("onnxruntime", outputs, golden)
    return checks


def _compare_all(backend: str, outputs: Mapping[str, np.ndarray], golden: Mapping[str, np.ndarray]) -> list[Check]:
    return [compare(backend, k, v, golden[k]) for k, v in outputs.items() if k in golden and k in TOLERANCES]


def format_table(checks: Sequence[Check]) -> str:
    """A fixed-width table of the checks."""
    width = max([22, *(len(c.name) for c in checks)])
    head = f"{'backend':<12} {'output':<{width}} {'max abs':>10} {'max rel':>10} {'atol':>7} {'rtol':>7}  result"
    lines = [head, "-" * len(head)]
    for c in checks:
        lines.append(
            f"{c.backend:<12} {c.name:<{width}} {c.max_abs:>10.2e} {c.max_rel:>10.2e} {c.atol:>7.0e} {c.rtol:>7.0e}  "
            f"{'ok' if c.passed else 'FAIL'}"
        )
    return "\n".join(lines)


def _family(directory: Path) -> tuple[tuple[str, ...], Callable[..., list[Check]]]:
    """Required files and check function of the model family named by ``DIR/tiny_config.json``
    (Depth Anything 3: a ``create_object_config_main`` section; π³ / π³X: ``pi3_src_commit``;
    otherwise VGGT)."""
    config_path = directory / "tiny_config.json"
    config = json.loads(config_path.read_text(encoding="utf-8")) if config_path.is_file() else {}
    if isinstance(config, dict) and "create_object_config_main" in config:
        from .da3.golden import REQUIRED_FILES, run_da3_checks

        return REQUIRED_FILES, run_da3_checks
    if isinstance(config, dict) and "pi3_src_commit" in config:
        from .pi3.golden import REQUIRED_FILES as PI3_FILES
        from .pi3.golden import run_pi3_checks

        return PI3_FILES, run_pi3_checks
    return ("tiny_config.json", "tiny_weights.safetensors", "tiny_images.npy", "tiny_golden.npz"), run_checks


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m inference.check_golden", description=__doc__.split("\n\n")[0])
    parser.add_argument("directory", type=Path, help="folder with tiny_config.json, tiny_weights.safetensors, ...")
    parser.add_argument("--no-onnx", action="store_true", help="check torch only")
    parser.add_argument(
        "--onnx-path",
        type=Path,
        default=None,
        help="keep the exported graph at this path (DA3: a folder for its graphs)",
    )
    args = parser.parse_args(argv)
    required, run = _family(args.directory)
    missing = [n for n in required if not (args.directory / n).is_file()]
    if missing:
        print(f"error: {args.directory} lacks {', '.join(missing)}", file=sys.stderr)
        return 2
    checks = run(args.directory, onnx=not args.no_onnx, onnx_path=args.onnx_path)
    print(format_table(checks))
    failed = [c for c in checks if not c.passed]
    print(f"\n{len(checks) - len(failed)}/{len(checks)} outputs within tolerance")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())

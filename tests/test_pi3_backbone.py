"""π³ / π³X behind the backbone interface (``inference/backbones/pi3.py``): config, preprocessing
geometry, the runner end to end on the tiny golden models, checkpoint refusals."""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from inference.backbones import pi3 as family
from inference.pi3.golden import compare
from swiftjax.prediction import ChunkPrediction


@dataclasses.dataclass(frozen=True)
class _Backbone:  # the fields of inference.backbones.Backbone this module reads
    name: str
    preset: str


PI3 = _Backbone("pi3", "pi3")
PI3X = _Backbone("pi3x", "pi3x")


@pytest.fixture(scope="module")
def golden_dir(pi3_golden_dir: pathlib.Path) -> pathlib.Path:
    return pi3_golden_dir


def test_variant_of_key_names(golden_dir) -> None:
    from safetensors import safe_open

    for fname, want in (("tiny_weights.safetensors", "pi3"), ("tiny_weights_pi3x.safetensors", "pi3x")):
        with safe_open(str(golden_dir / fname), "pt") as f:
            assert family.variant_of(f.keys()) == want
    assert family.variant_of(["aggregator.camera_token", "camera_head.trunk.0.norm1.weight"]) is None


def test_config_preset_and_model_config(golden_dir) -> None:
    assert family.load_config(PI3, None)["dec_depth"] == 36
    tiny = family.load_config(PI3X, golden_dir / "tiny_config.json")
    assert tiny["variant"] == "pi3x" and tiny["dim"] == 32
    import json

    from inference.pi3.config import Pi3Config

    assert Pi3Config.from_fields(json.loads(json.dumps(tiny))) == Pi3Config.from_fields(tiny)


def test_geometry_and_modes() -> None:
    g = family.preprocess_geometry(376, 1241, "resize")
    assert g.model_hw == (266, 924) and g.top == g.left == 0
    with pytest.raises(ValueError, match="mode 'resize'"):
        family.preprocess_geometry(376, 1241, "crop")


@pytest.mark.parametrize("backbone,suffix,key", [(PI3, "", "points"), (PI3X, "_pi3x", "uncond.points")])
def test_runner_end_to_end_on_tiny_weights(golden_dir, backbone, suffix: str, key: str) -> None:
    cfg = family.load_config(backbone, golden_dir / "tiny_config.json")
    runner = family.build_runner(backbone, str(golden_dir / f"tiny_weights{suffix}.safetensors"), "cpu", "float32", cfg)
    with np.load(golden_dir / f"tiny_golden{suffix}.npz") as z:
        images, ref_points = z["input_imgs"][0], z[key]
    out = runner.forward(images)
    assert compare("torch", key, out["points"].numpy(), ref_points).passed
    pred = runner.predict(images)
    assert isinstance(pred, ChunkPrediction) and pred.depth.shape == images.shape[:1] + images.shape[2:]
    np.testing.assert_allclose(pred.extrinsic[0], np.eye(4)[:3], atol=5e-6)


def test_pi3x_runner_uses_intrinsics_as_ray_condition(golden_dir) -> None:
    cfg = family.load_config(PI3X, golden_dir / "tiny_config.json")
    K = np.array([[63.0, 0, 34.5], [0, 63.0, 20.5], [0, 0, 1]])  # the golden K, swiftjax convention
    weights = str(golden_dir / "tiny_weights_pi3x.safetensors")
    plain = family.build_runner(PI3X, weights, "cpu", "float32", cfg)
    with_k = family.build_runner(PI3X, weights, "cpu", "float32", cfg, intrinsics=K)
    with np.load(golden_dir / "tiny_golden_pi3x.npz") as z:
        images = z["input_imgs"][0]
    a, b = plain.predict(images), with_k.predict(images)
    assert np.abs(a.depth - b.depth).max() > 1e-4
    with pytest.raises(ValueError, match="needs π³X"):
        family.build_runner(
            PI3,
            str(golden_dir / "tiny_weights.safetensors"),
            "cpu",
            "float32",
            family.load_config(PI3, golden_dir / "tiny_config.json"),
            intrinsics=K,
        )


def test_check_checkpoint_refusals(golden_dir, tmp_path) -> None:
    pytest.importorskip("inference.backbones.header", reason="the backbone layer's header reader (DA3 branch)")
    from inference.checkpoint import CheckpointError

    cfg = family.load_config(PI3, golden_dir / "tiny_config.json")
    family.check_checkpoint(PI3, golden_dir / "tiny_weights.safetensors", cfg)
    with pytest.raises(CheckpointError, match="is a pi3x checkpoint, not a pi3 one"):
        family.check_checkpoint(PI3, golden_dir / "tiny_weights_pi3x.safetensors", cfg)
    with pytest.raises(CheckpointError, match="safetensors only"):
        family.check_checkpoint(PI3, tmp_path / "model.pt", cfg)
    truncated = tmp_path / "t.safetensors"
    truncated.write_bytes((golden_dir / "tiny_weights.safetensors").read_bytes()[:-100])
    with pytest.raises(CheckpointError, match="truncated"):
        family.check_checkpoint(PI3, truncated, cfg)


def test_a_nan_in_the_weights_is_named_by_the_model(golden_dir) -> None:
    """Issue 25 item 15 for π³: non-finite outputs are an error naming the model, not a run of 0 points."""
    import torch

    from inference.runners import ModelOutputError

    cfg = family.load_config(PI3, golden_dir / "tiny_config.json")
    runner = family.build_runner(PI3, str(golden_dir / "tiny_weights.safetensors"), "cpu", "float32", cfg)
    with torch.no_grad():
        next(p for n, p in runner.model.named_parameters() if n.endswith("weight") and p.ndim == 2).fill_(float("nan"))
    with np.load(golden_dir / "tiny_golden.npz") as z:
        images = z["input_imgs"][0]
    with pytest.raises(ModelOutputError, match=r"pi3 \(.*tiny_weights.safetensors, float32\) predicted non-finite"):
        runner.predict(images)

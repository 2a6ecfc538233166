"""π³ / π³X through ONNX: the golden outputs from onnxruntime, dynamic frame axis, runner errors."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from inference.pi3.golden import PI3X_RUNS, _load, compare, golden_conditions
from inference.pi3.onnx import Pi3OnnxRunner, export_pi3_onnx
from swiftjax.prediction import ChunkPrediction


@pytest.fixture(scope="module")
def golden_dir(pi3_golden_dir: pathlib.Path) -> pathlib.Path:
    return pi3_golden_dir


@pytest.fixture(scope="module")
def pi3_graph(golden_dir, tmp_path_factory):
    model, golden = _load(golden_dir, "pi3")
    s, _, h, w = golden["input_imgs"].shape[1:]
    path = export_pi3_onnx(model, tmp_path_factory.mktemp("onnx") / "pi3.onnx", frames=s - 1, height=h, width=w)
    return model, golden, Pi3OnnxRunner(path)


@pytest.fixture(scope="module")
def pi3x_graph(golden_dir, tmp_path_factory):
    model, golden = _load(golden_dir, "pi3x")
    s, _, h, w = golden["input_imgs"].shape[1:]
    path = export_pi3_onnx(model, tmp_path_factory.mktemp("onnx") / "pi3x.onnx", frames=s - 1, height=h, width=w)
    return model, golden, Pi3OnnxRunner(path)


@pytest.mark.parametrize("key", ["points", "local_points", "conf", "camera_poses", "dino_patch_tokens"])
def test_pi3_onnx_equals_golden(pi3_graph, key: str) -> None:
    _, golden, runner = pi3_graph
    out = runner.forward(golden["input_imgs"][0])  # traced with S-1 frames, run with S
    assert compare("onnxruntime", key, out[key], golden[key]).passed


@pytest.mark.parametrize("run", PI3X_RUNS)
def test_pi3x_onnx_one_graph_every_run(pi3x_graph, run: str) -> None:
    _, golden, runner = pi3x_graph
    assert runner.conditioned
    out = runner.forward(golden["input_imgs"][0], golden_conditions(golden, run))
    for key in ("points", "local_points", "conf", "camera_poses", "rays", "metric", "dino_patch_tokens"):
        ref = golden[f"{run}.{key}"]
        got = out[key] if key in ("metric", "dino_patch_tokens") else out[key][None]
        check = compare("onnxruntime", key, got, ref)
        assert check.passed, check


def test_pi3_onnx_other_frame_counts_match_torch(pi3_graph) -> None:
    model, golden, runner = pi3_graph
    imgs = torch.rand(6, 3, *golden["input_imgs"].shape[-2:], generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        ref = model(imgs[None])
    got = runner.forward(imgs.numpy())
    for key in ("local_points", "conf", "camera_poses"):
        np.testing.assert_allclose(got[key], ref[key][0].numpy(), atol=1e-4, rtol=1e-4)


def test_onnx_runner_predict_and_errors(pi3_graph) -> None:
    _, golden, runner = pi3_graph
    pred = runner.predict(golden["input_imgs"][0])
    assert isinstance(pred, ChunkPrediction) and pred.num_frames == 4
    np.testing.assert_allclose(pred.extrinsic[0], np.eye(4)[:3], atol=5e-6)
    with pytest.raises(ValueError, match="exported for 42x70"):
        runner.forward(np.zeros((2, 3, 56, 70), np.float32))
    from inference.pi3.conditioning import Conditions

    with pytest.raises(ValueError, match="takes no conditions"):
        runner.forward(golden["input_imgs"][0], Conditions())

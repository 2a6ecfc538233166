"""ONNX export + onnxruntime against the golden tensors, dynamic frames, and check_golden.

One export (inside ``run_checks``, traced with 2 frames) serves every test in this module.
"""

from __future__ import annotations

import pathlib
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from safetensors.torch import load_file, save_file

from inference.check_golden import Check, main, run_checks
from inference.checkpoint import load_checkpoint
from inference.config import VGGTConfig
from inference.model import VGGT
from inference.runners import OnnxRunner
from swiftjax.prediction import ChunkPrediction

GOLDEN_FILES = ("tiny_config.json", "tiny_weights.safetensors", "tiny_images.npy", "tiny_golden.npz")


@pytest.fixture(scope="module")
def checked(golden_dir: pathlib.Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[list[Check], pathlib.Path]:
    onnx_path = tmp_path_factory.mktemp("onnx") / "tiny.onnx"
    return run_checks(golden_dir, onnx=True, onnx_path=onnx_path), onnx_path


@pytest.fixture(scope="module")
def runner(checked: tuple[list[Check], pathlib.Path]) -> OnnxRunner:
    return OnnxRunner(checked[1], intra_op_threads=1)


@pytest.fixture(scope="module")
def tiny_model(golden_dir: pathlib.Path) -> VGGT:
    model = VGGT(VGGTConfig.from_json(golden_dir / "tiny_config.json")).eval()
    load_checkpoint(model, golden_dir / "tiny_weights.safetensors")
    return model


def test_every_golden_output_within_tolerance(checked: tuple[list[Check], pathlib.Path]) -> None:
    checks, _ = checked
    by_backend = {(c.backend, c.name): c for c in checks}
    for name in ("pose_enc", "depth", "depth_conf", "patch_tokens", "extrinsic", "intrinsic"):
        assert by_backend[("onnxruntime", name)].passed, by_backend[("onnxruntime", name)]
        assert by_backend[("torch", name)].passed, by_backend[("torch", name)]
    for name in ("aggregated_tokens_all", "aggregated_tokens_dpt", "pose_enc_list"):
        assert by_backend[("torch", name)].passed
    assert all(c.passed for c in checks), [c for c in checks if not c.passed]
    # The export was traced with 2 frames; the golden scene has 3: the frame axis is dynamic.
    assert by_backend[("onnxruntime", "depth")].max_rel < 1e-4


def test_graph_signature(runner: OnnxRunner) -> None:
    assert runner.input_shape[0] == 1 and isinstance(runner.input_shape[1], str)  # dynamic frames
    assert runner.input_shape[2:] == (3, 42, 70)
    with pytest.raises(ValueError, match="export again for this image size"):
        runner.forward(np.zeros((2, 3, 42, 56), np.float32))


@pytest.mark.parametrize("frames", [1, 4])
def test_dynamic_frame_count_matches_torch(runner: OnnxRunner, tiny_model: VGGT, frames: int) -> None:
    x = np.random.default_rng(frames).random((frames, 3, 42, 70), dtype=np.float32)
    got = runner.forward(x)
    with torch.no_grad():
        ref = tiny_model(torch.from_numpy(x)[None], frames_chunk_size=None)
    assert got["depth"].shape == (1, frames, 42, 70, 1)
    np.testing.assert_allclose(got["pose_enc"], ref["pose_enc"].numpy(), atol=1e-5)
    np.testing.assert_allclose(got["patch_tokens"], ref["patch_tokens"].numpy(), atol=1e-5)
    np.testing.assert_allclose(got["depth"], ref["depth"].numpy(), rtol=1e-4)
    np.testing.assert_allclose(got["depth_conf"], ref["depth_conf"].numpy(), rtol=1e-4)


def test_onnx_runner_prediction(runner: OnnxRunner, golden_dir: pathlib.Path) -> None:
    golden = np.load(golden_dir / "tiny_golden.npz")
    pred = runner.predict(golden["images"][0])
    assert isinstance(pred, ChunkPrediction)
    np.testing.assert_allclose(pred.depth, golden["depth"][0, ..., 0], rtol=1e-4)
    np.testing.assert_allclose(pred.extrinsic, golden["extrinsic"][0], atol=1e-5)
    np.testing.assert_allclose(pred.intrinsic, golden["intrinsic"][0], rtol=1e-4)
    assert pred.patch_tokens is not None and pred.patch_tokens.shape == golden["patch_tokens"][0].shape


def test_check_golden_cli_passes(golden_dir: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(golden_dir), "--no-onnx"]) == 0
    out = capsys.readouterr().out
    assert "depth_conf" in out and "9/9 outputs within tolerance" in out and "FAIL" not in out


def test_check_golden_cli_fails_on_wrong_weights(
    golden_dir: pathlib.Path, tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for name in GOLDEN_FILES:
        shutil.copy(golden_dir / name, tmp_path / name)
    weights = load_file(golden_dir / "tiny_weights.safetensors")
    # The README's subtlest bug: a 1e-6 instead of 1e-5 LayerNorm eps shifts tokens by ~3e-5;
    # a small weight change of the same order must be caught as well.
    weights["aggregator.frame_blocks.0.norm1.weight"] = weights["aggregator.frame_blocks.0.norm1.weight"] * 1.001
    save_file(weights, tmp_path / "tiny_weights.safetensors")
    assert main([str(tmp_path), "--no-onnx"]) == 1
    out = capsys.readouterr().out
    assert "FAIL" in out and "aggregated_tokens_all" in out


def test_check_golden_cli_missing_files(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(tmp_path)]) == 2
    assert "lacks tiny_config.json" in capsys.readouterr().err

"""Model identity through the real CLI on the tiny golden VGGT (``--model-config``): a run
directory made with one model is never reused with another (weights, dtype)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from test_faults import _env

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")
pytestmark = pytest.mark.slow


def _reconstruct(frames, out, weights, config, *extra, fault=None):
    import subprocess
    import sys

    argv = [
        sys.executable,
        "-m",
        "swiftjax.cli",
        "reconstruct",
        str(frames),
        "--weights",
        str(weights),
        "--model-config",
        str(config),
        "--out",
        str(out),
        "--chunk-size",
        "8",
        "--overlap",
        "3",
        "--min-points",
        "10",
        "--no-loop-closure",
        "--no-colmap",
        "--no-progress",
        *extra,
    ]
    return subprocess.run(argv, env=_env(fault), capture_output=True, text=True, timeout=600)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_another_model_is_refused_and_the_same_one_resumes(tmp_path, golden_dir):
    from safetensors.torch import load_file, save_file

    frames = tmp_path / "frames"
    frames.mkdir()
    base = np.random.default_rng(0).integers(0, 255, (60, 220, 3), np.uint8)
    for k in range(12):
        cv2.imwrite(str(frames / f"{k:04d}.png"), np.roll(base, 3 * k, axis=1))
    config, weights_a = golden_dir / "tiny_config.json", tmp_path / "a.safetensors"
    shutil.copyfile(golden_dir / "tiny_weights.safetensors", weights_a)
    state = load_file(str(weights_a))
    key = sorted(state)[0]
    state[key] = state[key] + 1e-3
    weights_b = tmp_path / "b.safetensors"
    save_file(state, str(weights_b))
    out = tmp_path / "run"

    first = _reconstruct(frames, out, weights_a, config, fault="chunk-recorded:0:KILL")
    assert first.returncode == -9, first.stderr[-2000:]
    fp = json.loads((out / "manifest.json").read_text())["fingerprint"]["temporal"]["identity"]["model"]
    assert fp["weights"]["file"] == "a.safetensors" and fp["dtype"] == "float32" and fp["device_class"] == "cpu"
    assert fp["config"]["embed_dim"] == 64  # the tiny architecture, from --model-config

    other = _reconstruct(frames, out, weights_b, config)
    assert other.returncode == 2 and "different model (weights)" in other.stderr and "--overwrite" in other.stderr
    other = _reconstruct(frames, out, weights_a, config, "--dtype", "bfloat16")
    assert other.returncode == 2 and "different model (dtype)" in other.stderr

    again = _reconstruct(frames, out, weights_a, config)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "12 | " in again.stdout or "frames" in again.stdout


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_weights_of_another_dtype_or_with_nan_through_the_cli(tmp_path, golden_dir):
    """float16 weights failed at the first prediction, int32 inside load_state_dict, a NaN
    output bias ran to "0 points written", exit 0 (issue 25 #15 #19 #25)."""
    from safetensors.torch import load_file, save_file

    frames = tmp_path / "frames"
    frames.mkdir()
    base = np.random.default_rng(0).integers(0, 255, (60, 220, 3), np.uint8)
    for k in range(10):
        cv2.imwrite(str(frames / f"{k:04d}.png"), np.roll(base, 3 * k, axis=1))
    config = golden_dir / "tiny_config.json"
    state = load_file(str(golden_dir / "tiny_weights.safetensors"))
    key = "camera_head.pose_branch.fc2.bias"

    nan = dict(state)
    nan[key] = nan[key].clone()
    nan[key][2] = float("nan")
    save_file(nan, str(tmp_path / "nan.safetensors"))
    run = _reconstruct(frames, tmp_path / "o_nan", tmp_path / "nan.safetensors", config)
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr[-2000:]
    assert f"hold NaN/inf values: {key}" in run.stderr and not (tmp_path / "o_nan" / "chunks").exists()

    ints = dict(state)
    ints[key] = ints[key].to(torch.int32)
    save_file(ints, str(tmp_path / "int.safetensors"))
    run = _reconstruct(frames, tmp_path / "o_int", tmp_path / "int.safetensors", config)
    assert run.returncode == 2 and "Traceback" not in run.stderr and f"{key} (int32)" in run.stderr

    save_file({k: v.half() for k, v in state.items()}, str(tmp_path / "half.safetensors"))
    run = _reconstruct(frames, tmp_path / "o_half", tmp_path / "half.safetensors", config)
    assert run.returncode == 0, run.stderr[-2000:]
    assert f"{len(state)} float16 tensor(s) cast to float32" in run.stderr
    assert (tmp_path / "o_half" / "poses_kitti.txt").is_file()

"""DA3 through the real CLI (``--model``) on the tiny golden networks: runs, resumes, refuses
another model and bad input in one line before any prediction, metric scale from the nested
model, and the same trajectory through the Ray executor."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from test_faults import _env

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")
pytestmark = pytest.mark.slow

try:
    import inference.da3  # noqa: F401

    HAVE_DA3 = True
except ImportError:
    HAVE_DA3 = False
needs_da3 = pytest.mark.skipif(not HAVE_DA3, reason="inference.da3 missing")

FLAGS = (
    "--chunk-size",
    "8",
    "--overlap",
    "3",
    "--min-points",
    "10",
    "--no-loop-closure",
    "--no-colmap",
    "--no-progress",
)


@pytest.fixture(scope="module")
def da3_dir(da3_golden_dir):
    return da3_golden_dir


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    d = tmp_path_factory.mktemp("da3") / "frames"
    d.mkdir()
    base = np.random.default_rng(0).integers(0, 255, (60, 220, 3), np.uint8)
    for k in range(12):
        cv2.imwrite(str(d / f"{k:04d}.png"), np.roll(base, 3 * k, axis=1))
    return d


def _run(frames, out, *extra, fault=None):
    argv = [sys.executable, "-m", "swiftjax.cli", "reconstruct", str(frames), "--out", str(out), *FLAGS, *extra]
    return subprocess.run(argv, env=_env(fault), capture_output=True, text=True, timeout=900)


def _tiny(da3_dir, nested=False):
    weights = "tiny_nested_weights.safetensors" if nested else "tiny_weights.safetensors"
    return (
        "--model",
        "da3-nested-giant-large" if nested else "da3-small",
        "--model-config",
        str(da3_dir / "tiny_config.json"),
        "--weights",
        str(da3_dir / weights),
    )


def _snapshot(d):
    """Every file's size and time, but the run directory's lock (taken by every run that opens it)
    and a killed run's half-written temporary files (swept by the next run that opens it)."""
    return {
        p: (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(d.rglob("*"))
        if p.is_file() and p.name != ".swiftjax.lock" and ".tmp" not in p.name
    }


@needs_da3
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_da3_small_runs_resumes_and_refuses_another_model(tmp_path, frames, da3_dir):
    out = tmp_path / "run"
    first = _run(frames, out, *_tiny(da3_dir), fault="chunk-recorded:0:KILL")
    assert first.returncode == -9, first.stderr[-2000:]
    fp = json.loads((out / "manifest.json").read_text())["fingerprint"]["temporal"]
    assert fp["identity"]["model"]["backbone"] == {"name": "da3-small", "family": "da3", "preset": "da3-small"}
    assert fp["identity"]["model"]["config"]["embed_dim"] == 64  # the tiny architecture, from --model-config
    assert fp["identity"]["preprocessing"] == {"mode": "resize"} and fp["options"]["model"] == "da3-small"

    before = _snapshot(out)
    other = _run(frames, out, *_tiny(da3_dir, nested=True))
    assert other.returncode == 2 and other.stderr.count("\n") == 1, other.stderr
    assert (
        "different model (backbone, config, weights); options model" in other.stderr and "--overwrite" in other.stderr
    )
    assert _snapshot(out) == before

    again = _run(frames, out, *_tiny(da3_dir))
    assert again.returncode == 0, again.stderr[-2000:]
    assert "resum" in (again.stdout + again.stderr).lower() or "1 of 2" in again.stdout or "chunk" in again.stdout
    poses = np.loadtxt(out / "poses_kitti.txt").reshape(-1, 3, 4)
    assert poses.shape == (12, 3, 4) and np.isfinite(poses).all()
    np.testing.assert_allclose(poses[0], np.eye(3, 4), atol=1e-5)  # the first camera is the world (re-based)


@needs_da3
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_nested_model_gives_metres_with_metric_model(tmp_path, frames, da3_dir):
    out = tmp_path / "nested"
    res = _run(frames, out, *_tiny(da3_dir, nested=True), "--metric", "model")
    assert res.returncode == 0, res.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["unit"] == "metres" and metrics["metric_scale"]["method"].startswith("model")
    assert metrics["metric_scale"]["metres_per_unit"] == pytest.approx(1.0)


def test_bad_input_is_one_line_before_any_prediction(tmp_path, frames, da3_dir, golden_dir, capsys):
    """Another family's checkpoint, a truncated file, frames the family cannot take: exit 2,
    one line, the run directory untouched."""
    from swiftjax import cli

    out = tmp_path / "run"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    before = _snapshot(out)
    cut = tmp_path / "cut.safetensors"
    data = (da3_dir / "tiny_weights.safetensors").read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    thin = tmp_path / "thin"
    thin.mkdir()
    for k in range(3):
        cv2.imwrite(str(thin / f"{k:04d}.png"), np.full((4, 2000, 3), 100, np.uint8))
    cfg = str(da3_dir / "tiny_config.json")
    cases = [
        (
            [
                str(frames),
                "--model",
                "da3-small",
                "--model-config",
                cfg,
                "--weights",
                str(golden_dir / "tiny_weights.safetensors"),
            ],
            "is a VGGT checkpoint, not what --model da3-small needs",
        ),
        (
            [
                str(frames),
                "--model",
                "vggt-1b",
                "--model-config",
                str(golden_dir / "tiny_config.json"),
                "--weights",
                str(da3_dir / "tiny_weights.safetensors"),
            ],
            "is a Depth Anything 3 (any-view) checkpoint, not a VGGT one",
        ),
        (
            [str(frames), "--model", "da3-small", "--model-config", cfg, "--weights", str(cut)],
            "cut.safetensors is truncated",
        ),
        (
            [str(frames), "--model", "da3-base", "--weights", str(da3_dir / "tiny_weights.safetensors")],
            "does not match the da3-base model: missing",
        ),
        (
            [
                str(thin),
                "--model",
                "da3-small",
                "--model-config",
                cfg,
                "--weights",
                str(da3_dir / "tiny_weights.safetensors"),
            ],
            "--model da3-small cannot take the frames of",
        ),
        (
            [
                str(frames),
                "--model",
                "da3-small",
                "--model-config",
                cfg,
                "--weights",
                str(da3_dir / "tiny_weights.safetensors"),
                "--metric",
                "model",
            ],
            "own scale needs a network that predicts metres",
        ),
        (
            [
                str(frames),
                "--model",
                "da3-small",
                "--model-config",
                cfg,
                "--weights",
                str(da3_dir / "tiny_weights.safetensors"),
                "--mode",
                "pad",
            ],
            "--mode pad is not a preprocessing of --model da3-small",
        ),
    ]
    for argv, fragment in cases:
        code = cli.main(["reconstruct", *argv, "--out", str(out), *FLAGS])
        err = capsys.readouterr().err
        assert code == 2 and fragment in err and err.count("\n") == 1, (fragment, err)
        assert _snapshot(out) == before


@needs_da3
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_da3_through_the_ray_executor_equals_the_local_run(tmp_path, frames, da3_dir):
    pytest.importorskip("ray")
    local, remote = tmp_path / "local", tmp_path / "ray"
    a = _run(frames, local, *_tiny(da3_dir))
    assert a.returncode == 0, a.stderr[-2000:]
    b = _run(frames, remote, *_tiny(da3_dir), "--executor", "ray", "--workers", "1")
    assert b.returncode == 0, b.stderr[-3000:]
    pa = np.loadtxt(local / "poses_kitti.txt")
    pb = np.loadtxt(remote / "poses_kitti.txt")
    np.testing.assert_allclose(pb, pa, atol=1e-4)

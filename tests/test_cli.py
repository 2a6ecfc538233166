"""The ``swiftjax`` command: bad input is one line and exit status 2; evaluate prints ATE/RPE."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from swiftjax import cli, evaluation
from swiftjax.io import trajectory


def run_cli(capsys, *argv):
    code = cli.main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def _assert_one_line_error(code, err, *fragments):
    assert code == 2
    lines = [line for line in err.strip().splitlines() if line.startswith("swiftjax: error:")]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for frag in fragments:
        assert frag in lines[0], lines[0]


def test_reconstruct_empty_folder(capsys, tmp_path):
    (tmp_path / "empty").mkdir()
    code, _, err = run_cli(capsys, "reconstruct", str(tmp_path / "empty"), "--weights", "w.pt", "--out", str(tmp_path / "o"))
    _assert_one_line_error(code, err, "empty")


def test_reconstruct_corrupt_image_named(capsys, tmp_path):
    cv2 = pytest.importorskip("cv2")
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in range(3):
        cv2.imwrite(str(folder / f"{k:03d}.png"), np.full((20, 30, 3), 40 * k, np.uint8))
    (folder / "003.png").write_bytes(b"not a png")
    code, _, err = run_cli(capsys, "reconstruct", str(folder), "--weights", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "o"))
    _assert_one_line_error(code, err, "003.png")


def test_reconstruct_mixed_sizes(capsys, tmp_path):
    cv2 = pytest.importorskip("cv2")
    folder = tmp_path / "imgs"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.zeros((20, 30, 3), np.uint8))
    cv2.imwrite(str(folder / "b.png"), np.zeros((21, 30, 3), np.uint8))
    code, _, err = run_cli(capsys, "reconstruct", str(folder), "--weights", "w.pt", "--out", str(tmp_path / "o"))
    _assert_one_line_error(code, err, "a.png", "b.png")


def test_reconstruct_missing_weights(capsys, tmp_path):
    cv2 = pytest.importorskip("cv2")
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in range(2):
        cv2.imwrite(str(folder / f"{k}.png"), np.zeros((20, 30, 3), np.uint8))
    code, _, err = run_cli(capsys, "reconstruct", str(folder), "--weights", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "o"))
    _assert_one_line_error(code, err, "nope.pt", "does not exist")


def test_demo_unwritable_output(capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, _, err = run_cli(capsys, "demo", "--frames", "10", "--out", str(blocker / "sub"), "--no-progress")
    _assert_one_line_error(code, err, "sub")


def test_bad_config_file_and_option(capsys, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("chunk_size = 10\noverlap = 10\n")
    code, _, err = run_cli(capsys, "demo", "--frames", "10", "--out", str(tmp_path / "o"), "--config", str(cfg))
    _assert_one_line_error(code, err, "overlap")
    cfg.write_text("bogus = 1\n")
    code, _, err = run_cli(capsys, "demo", "--frames", "10", "--out", str(tmp_path / "o"), "--config", str(cfg))
    _assert_one_line_error(code, err, "bogus")


def test_config_file_values_are_overridden_by_options(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[swiftjax]\nchunk_size = 60\noverlap = 20\n")
    args = cli.build_parser().parse_args(["demo", "--config", str(cfg), "--overlap", "25"])
    conf = cli._pipeline_config(args)  # noqa: SLF001
    assert (conf.chunk_size, conf.overlap) == (60, 25)


def test_evaluate_matches_library(capsys, tmp_path):
    rng = np.random.default_rng(0)
    ref = np.tile(np.eye(4), (50, 1, 1))
    ref[:, 0, 3] = np.arange(50.0)
    ref[:, 2, 3] = 0.02 * np.arange(50.0) ** 2  # a curve: a straight line makes Umeyama degenerate
    est = ref.copy()
    est[:, :3, 3] += rng.normal(scale=0.1, size=(50, 3))
    trajectory.write_kitti(tmp_path / "est.txt", est)
    trajectory.write_kitti(tmp_path / "ref.txt", ref)
    code, out, _ = run_cli(capsys, "evaluate", str(tmp_path / "est.txt"), str(tmp_path / "ref.txt"))
    assert code == 0
    want = evaluation.ate(est, ref).rmse
    assert f"{want:.3g}" in out


def test_evaluate_malformed_file(capsys, tmp_path):
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    (tmp_path / "ref.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    code, _, err = run_cli(capsys, "evaluate", str(tmp_path / "bad.txt"), str(tmp_path / "ref.txt"))
    _assert_one_line_error(code, err, "bad.txt")


def test_entry_point_help_runs():
    out = subprocess.run([sys.executable, "-m", "swiftjax.cli", "--help"], capture_output=True, text=True, check=True)
    for command in ("demo", "reconstruct", "evaluate", "export-onnx"):
        assert command in out.stdout

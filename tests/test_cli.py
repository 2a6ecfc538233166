"""The ``swiftjax`` command: bad input is one line and exit status 2; evaluate prints ATE/RPE."""

from __future__ import annotations

import argparse
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from swiftjax import cli, evaluation
from swiftjax.cli import arguments
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
    code, _, err = run_cli(
        capsys, "reconstruct", str(tmp_path / "empty"), "--weights", "w.pt", "--out", str(tmp_path / "o")
    )
    _assert_one_line_error(code, err, "empty")


def test_reconstruct_corrupt_image_named(capsys, tmp_path):
    cv2 = pytest.importorskip("cv2")
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in range(3):
        cv2.imwrite(str(folder / f"{k:03d}.png"), np.full((20, 30, 3), 40 * k, np.uint8))
    (folder / "003.png").write_bytes(b"not a png")
    code, _, err = run_cli(
        capsys, "reconstruct", str(folder), "--weights", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "o")
    )
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
    code, _, err = run_cli(
        capsys, "reconstruct", str(folder), "--weights", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "o")
    )
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
    conf = arguments.pipeline_config(args)
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
    code, out, _ = run_cli(capsys, "evaluate", str(tmp_path / "ref.txt"), str(tmp_path / "est.txt"))
    assert code == 0
    want = evaluation.ate(est, ref).rmse
    assert f"{want:.3g}" in out


def test_evaluate_malformed_file(capsys, tmp_path):
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    (tmp_path / "ref.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    code, _, err = run_cli(capsys, "evaluate", str(tmp_path / "ref.txt"), str(tmp_path / "bad.txt"))
    _assert_one_line_error(code, err, "bad.txt")


def test_entry_point_help_runs():
    out = subprocess.run([sys.executable, "-m", "swiftjax.cli", "--help"], capture_output=True, text=True, check=True)
    for command in ("demo", "reconstruct", "evaluate", "export-onnx"):
        assert command in out.stdout


HELP = pathlib.Path(__file__).parent / "data" / "cli_help"


@pytest.mark.parametrize(
    "command", ["swiftjax", "demo", "batch", "reconstruct", "view", "prune", "evaluate", "export-onnx"]
)
def test_help_is_the_recorded_text(command, monkeypatch):
    """Each command's --help, byte for byte, as recorded at 80 columns from the single-module
    cli.py (before it became a package; swiftjax.txt: the top level, with --quiet/--verbose
    added since).  argparse's layout changes between Python versions: recorded on 3.11."""
    if sys.version_info[:2] != (3, 11):
        pytest.skip(f"the help was recorded with Python 3.11's argparse; this is {sys.version.split()[0]}")
    monkeypatch.setenv("COLUMNS", "80")
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    text = parser.format_help() if command == "swiftjax" else sub.choices[command].format_help()
    assert text == (HELP / f"{command}.txt").read_text()
    assert list(sub.choices) == ["demo", "batch", "reconstruct", "view", "prune", "evaluate", "export-onnx"]


def test_help_through_the_module_entry_point_is_the_recorded_text():
    """``python -m swiftjax.cli demo --help`` (the package's __main__) prints the same text."""
    if sys.version_info[:2] != (3, 11):
        pytest.skip(f"the help was recorded with Python 3.11's argparse; this is {sys.version.split()[0]}")
    env = {**os.environ, "COLUMNS": "80"}
    out = subprocess.run(
        [sys.executable, "-m", "swiftjax.cli", "demo", "--help"], capture_output=True, text=True, check=True, env=env
    )
    assert out.stdout == (HELP / "demo.txt").read_text()


# ------------------------------------------------- bad input: one line, exit 2, before work


def _frames(tmp_path, n=3):
    cv2 = pytest.importorskip("cv2")
    folder = tmp_path / "imgs"
    folder.mkdir(exist_ok=True)
    for k in range(n):
        cv2.imwrite(str(folder / f"{k:03d}.png"), np.full((28, 42, 3), 40 * k, np.uint8))
    return folder


@pytest.mark.parametrize(
    "extra, fragments",
    [
        (["--device", "banana"], ["--device 'banana' is not a torch device"]),
        (["--device", "cuda"], ["--device cuda:", "use --device cpu"]),
        (["--backend", "onnx"], ["--backend onnx needs an .onnx file"]),
        (
            ["--dtype", "bfloat16", "--backend", "onnx", "--weights", "W.onnx"],
            ["--dtype bfloat16 needs --backend torch"],
        ),
    ],
)
def test_device_and_backend_errors_are_one_line(capsys, tmp_path, extra, fragments):
    pytest.importorskip("torch")
    folder = _frames(tmp_path)
    (tmp_path / "w.pt").write_bytes(b"\x80\x02junk")
    (tmp_path / "W.onnx").write_bytes(b"junk")
    argv = ["reconstruct", str(folder), "--weights", str(tmp_path / "w.pt"), "--out", str(tmp_path / "o"), *extra]
    argv = [a if a != "W.onnx" else str(tmp_path / "W.onnx") for a in argv]
    code, _, err = run_cli(capsys, *argv)
    if "cuda" in extra:
        import torch

        if torch.cuda.is_available():
            pytest.skip("a CUDA device is present here")
    _assert_one_line_error(code, err, *fragments)
    assert not (tmp_path / "o").exists()  # refused before the run directory was made


@pytest.mark.parametrize(
    "name, payload, fragments",
    [
        ("w.pt", np.random.default_rng(0).bytes(5000), ["w.pt", "corrupt"]),
        ("w.pt", b"\x80\x02" + np.random.default_rng(1).bytes(5000), ["w.pt", "corrupt"]),
        ("w.safetensors", b"\x00" * 3, ["w.safetensors"]),
        ("w.onnx", np.random.default_rng(2).bytes(5000), ["cannot load the ONNX graph", "w.onnx"]),
    ],
)
def test_corrupt_weights_are_one_line_and_not_called_unsafe(capsys, tmp_path, name, payload, fragments):
    pytest.importorskip("torch")
    folder = _frames(tmp_path)
    (tmp_path / name).write_bytes(payload)
    backend = ["--backend", "onnx"] if name.endswith(".onnx") else []
    code, _, err = run_cli(
        capsys, "reconstruct", str(folder), "--weights", str(tmp_path / name), "--out", str(tmp_path / "o"), *backend
    )
    _assert_one_line_error(code, err, *fragments)
    assert "unsafe" not in err and "refused" not in err


def test_model_config_errors(capsys, tmp_path):
    pytest.importorskip("torch")
    folder = _frames(tmp_path)
    (tmp_path / "w.safetensors").write_bytes(b"\x00" * 3)
    (tmp_path / "cfg.json").write_text("{not json")
    code, _, err = run_cli(
        capsys,
        "reconstruct",
        str(folder),
        "--weights",
        str(tmp_path / "w.safetensors"),
        "--out",
        str(tmp_path / "o"),
        "--model-config",
        str(tmp_path / "cfg.json"),
    )
    _assert_one_line_error(code, err, "--model-config", "cfg.json", "is not a VGGT config")


@pytest.mark.parametrize(
    "toml, fragments",
    [
        ("min_points = 1e400\n", ["min_points", "inf", "an integer with 3 <= value <= 100000000"]),
        ('loop_closure = "no"\n', ["loop_closure", "'no' is not a boolean"]),
        ("overlap = true\n", ["overlap", "True is not a number"]),
        ("chunk_size = 60.7\n", ["chunk_size", "60.7 is not an integer"]),
        ('robust_loops = "nope"\n', ["robust_loops", "one of gnc, cauchy, huber (or none)"]),
        ("\x00\x01binary", ["not valid TOML"]),
    ],
)
def test_config_file_errors_name_the_key(capsys, tmp_path, toml, fragments):
    cfg = tmp_path / "c.toml"
    cfg.write_text(toml)
    code, _, err = run_cli(capsys, "demo", "--frames", "10", "--out", str(tmp_path / "o"), "--config", str(cfg))
    _assert_one_line_error(code, err, *fragments)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "flags, fragments",
    [
        (["--voxel-size", "-1"], ["--voxel-size", "-1.0 is out of range", "> 0"]),
        (["--colmap-max-points", "-1"], ["--colmap-max-points", "out of range"]),
        (["--conf-ratio", "-1"], ["--conf-ratio", "out of range"]),
        (["--depth-threshold", "nan"], ["--depth-threshold", "not finite"]),
        (["--point-conf-ratio", "1e9"], ["--point-conf-ratio", "out of range"]),
        (["--chunk-size", "60.7"], ["--chunk-size", "'60.7' is not a number"]),
        (["--robust-loops", "none", "--alignment", "nope"], ["--alignment", "one of umeyama, irls"]),
        (["--out", ""], ["--out is empty"]),
    ],
)
def test_bad_options_are_refused_before_any_prediction(capsys, tmp_path, flags, fragments):
    """Defect 5: --voxel-size -1 used to fail at export, after every chunk was predicted."""
    argv = ["demo", "--frames", "10", "--out", str(tmp_path / "o"), "--no-progress", *flags]
    code, _, err = run_cli(capsys, *argv)
    _assert_one_line_error(code, err, *fragments)
    assert not (tmp_path / "o").exists()


def test_out_inside_the_input_is_refused(capsys, tmp_path):
    folder = _frames(tmp_path)
    for out in (folder, folder / "run"):
        code, _, err = run_cli(capsys, "reconstruct", str(folder), "--weights", "w.pt", "--out", str(out))
        _assert_one_line_error(code, err, "inside the input folder")
    assert sorted(p.name for p in folder.iterdir()) == ["000.png", "001.png", "002.png"]


def test_evaluate_binary_and_bad_rotation_files(capsys, tmp_path):
    (tmp_path / "bin.txt").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    (tmp_path / "ref.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5)
    code, _, err = run_cli(capsys, "evaluate", str(tmp_path / "ref.txt"), str(tmp_path / "bin.txt"))
    _assert_one_line_error(code, err, "bin.txt", "not a text KITTI trajectory file")
    rng = np.random.default_rng(0)
    ref = np.tile(np.eye(4), (40, 1, 1))
    ref[:, :3, 3] = np.cumsum(rng.normal(size=(40, 3)), axis=0)
    scaled = ref.copy()
    scaled[10:, :3, :3] *= 1.1
    trajectory.write_kitti(tmp_path / "ref.txt", ref)
    trajectory.write_kitti(tmp_path / "scaled.txt", scaled)
    code, _, err = run_cli(capsys, "evaluate", str(tmp_path / "ref.txt"), str(tmp_path / "scaled.txt"))
    _assert_one_line_error(code, err, "scaled.txt", "pose 10 (of 40)", "--fix-rotations")
    code, out, err = run_cli(
        capsys, "evaluate", str(tmp_path / "ref.txt"), str(tmp_path / "scaled.txt"), "--fix-rotations"
    )
    assert code == 0 and "rotations re-orthonormalised" in out and "scaled.txt" in out
    (tmp_path / "zeroq.txt").write_text("".join(f"{k} 0 0 {k} 0 0 0 {0 if k == 3 else 1}\n" for k in range(6)))
    code, _, err = run_cli(
        capsys,
        "evaluate",
        str(tmp_path / "zeroq.txt"),
        str(tmp_path / "zeroq.txt"),
        "--format",
        "tum",
        "--fix-rotations",
    )
    _assert_one_line_error(code, err, "zeroq.txt", "pose 3", "norm 0")


def test_help_shows_defaults_choices_and_descriptions():
    parser = cli.build_parser()
    sub = parser._subparsers._group_actions[0].choices
    texts = {name: p.format_help() for name, p in sub.items()}
    for name, p in sub.items():
        for action in p._actions:
            if action.option_strings and action.dest != "help":
                assert action.help, (name, action.option_strings)
    for command, flags in {
        "demo": ["--out", "--seed"],
        "reconstruct": ["--backend", "--dtype", "--mode", "--gt-format"],
        "evaluate": ["--format", "--align", "--delta", "--max-diff", "--offset"],
        "export-onnx": ["--frames", "--height", "--width"],
    }.items():
        for flag in flags:
            action = next(a for a in sub[command]._actions if flag in a.option_strings)
            assert "default" in sub[command]._get_formatter()._expand_help(action), (command, flag)
    assert "{umeyama,irls}" in texts["demo"] and "{gnc,cauchy,huber,none}" in texts["reconstruct"]


def test_import_cli_and_build_its_parser_does_not_import_torch():
    """``import swiftjax.cli`` (every command module) and its parser: no torch; the device is
    probed in inference.device, imported only when a command checks --device."""
    code = (
        "import sys, pkgutil, importlib, swiftjax.cli\n"
        "for m in pkgutil.iter_modules(swiftjax.cli.__path__, 'swiftjax.cli.'): importlib.import_module(m.name)\n"
        "swiftjax.cli.build_parser().parse_args(['demo'])\n"
        "assert 'torch' not in sys.modules, 'torch imported'\n"
        "assert 'inference.device' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("flags", [[], ["--quiet"]])
def test_a_library_warning_is_one_prefixed_line_on_stderr(monkeypatch, capsys, flags):
    """A warning of a swiftjax module's logger during a command: ``swiftjax: warning: ...`` on
    stderr (also under --quiet); an information line: on stdout as written (not under --quiet).
    The command's handler is removed when it returns."""
    import logging

    def command(args):
        logging.getLogger("swiftjax.pipeline.graph").warning("pose graph did not converge (max_steps)")
        logging.getLogger("swiftjax.inference.preprocess").info("swiftjax: an information line")
        return 0

    monkeypatch.setattr(cli.main_evaluate, "run", command)
    assert cli.main([*flags, "evaluate", "ref.txt", "est.txt"]) == 0
    out, err = capsys.readouterr()
    assert err.splitlines() == ["swiftjax: warning: pose graph did not converge (max_steps)"]
    assert out.splitlines() == ([] if flags else ["swiftjax: an information line"])
    assert not logging.getLogger("swiftjax").handlers and logging.getLogger("swiftjax").level == logging.NOTSET


@pytest.mark.parametrize(("device", "prefetch"), [("cpu", 1), ("cuda", 3), ("cuda:1", 3), ("mps", 1)])
def test_local_executor_predicts_further_ahead_on_a_gpu(device, prefetch):
    """--device cuda: three predictions ahead of the geometry (bench/bench_gpu.py's end-to-end
    runs measured it); elsewhere one (the model is the slow stage)."""
    args = argparse.Namespace(executor="local", workers=1, gpus_per_worker=0, ray_address=None, device=device)
    assert arguments.make_executor(args).prefetch == prefetch

"""One error family: every exception class of swiftjax and inference is a SwiftjaxError, and the
command prints those (and OSErrors naming a file) as one line with exit status 2 while a bug keeps
its traceback and exits 1."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import subprocess
import sys

import pytest

import inference
import swiftjax
from swiftjax import cli
from swiftjax.errors import SwiftjaxError


def _modules():
    for package in (swiftjax, inference):
        yield package.__name__
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            yield info.name


def test_every_exception_class_is_a_swiftjax_error():
    found, strays = [], []
    for name in _modules():
        module = importlib.import_module(name)  # an optional extra missing here fails: CI installs them all
        for cls_name, cls in inspect.getmembers(module, inspect.isclass):
            if cls.__module__ != name or not issubclass(cls, BaseException) or issubclass(cls, Warning):
                continue
            found.append(f"{name}.{cls_name}")
            if not issubclass(cls, SwiftjaxError):
                strays.append(f"{name}.{cls_name}")
    assert not strays, f"not derived from swiftjax.errors.SwiftjaxError: {strays}"
    assert len(found) >= 20  # the walk reached the packages (the family had 20 classes when this was written)


def _main_with(monkeypatch, capsys, err: BaseException):
    def command(args):
        raise err

    monkeypatch.setattr(cli.main_evaluate, "run", command)
    code = cli.main(["evaluate", "ref.txt", "est.txt"])
    return code, capsys.readouterr().err


@pytest.mark.parametrize(
    "err",
    [
        cli.CliError("--frames must be >= 1, got 0"),
        SwiftjaxError("a library's user error"),
        FileNotFoundError(2, "No such file or directory", "ref.txt"),
        MemoryError("cannot allocate"),
        ModuleNotFoundError("No module named 'viser'", name="viser"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_user_errors_are_one_line_and_exit_2(monkeypatch, capsys, err):
    code, stderr = _main_with(monkeypatch, capsys, err)
    assert code == 2
    assert stderr.strip().count("\n") == 0 and stderr.startswith("swiftjax: error: "), stderr


@pytest.mark.parametrize(
    "err",
    [
        ValueError("a shape bug"),
        KeyError("missing"),
        OSError("a socket error, no file"),
        ModuleNotFoundError("No module named 'swiftjax.nope'", name="swiftjax.nope"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_bugs_propagate(monkeypatch, capsys, err):
    with pytest.raises(type(err)):
        _main_with(monkeypatch, capsys, err)
    assert "swiftjax: error:" not in capsys.readouterr().err


def test_a_bug_in_a_command_gets_a_traceback_and_exit_1():
    code = (
        "import sys; from swiftjax import cli\n"
        "def bug(args): raise ValueError('a programming bug')\n"
        "cli.main_evaluate.run = bug\n"
        "sys.exit(cli.main(['evaluate', 'ref.txt', 'est.txt']))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" in proc.stderr and "ValueError: a programming bug" in proc.stderr
    assert "swiftjax: error:" not in proc.stderr


def test_a_user_error_through_the_command_is_one_line(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "swiftjax.cli", "evaluate", str(tmp_path / "ref.txt"), str(tmp_path / "est.txt")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("swiftjax: error: ") and "Traceback" not in proc.stderr
    assert "does not exist" in proc.stderr


def test_workers_below_one_is_checked_in_one_place(tmp_path):
    from swiftjax.pipeline import batch
    from swiftjax.pipeline.executors import ExecutorError, RayExecutor, check_workers

    for call in (
        lambda: check_workers(0),
        lambda: RayExecutor(0),
        lambda: batch.run_batch([batch.Sequence("a", "x")], tmp_path / "out", workers=0),
    ):
        with pytest.raises(ExecutorError, match="--workers must be >= 1, got 0"):
            call()


def test_user_input_errors_of_the_library_are_swiftjax_errors(tmp_path):
    """Errors a user's flag or file causes, raised below the CLI, are in the family (and keep
    ValueError for callers that catch it)."""
    import numpy as np

    from inference.backbones import get
    from inference.predictor import build_runner
    from swiftjax.io.ply import read_ply
    from swiftjax.metric_scale import combine_scales

    not_ply = tmp_path / "cloud.ply"
    not_ply.write_bytes(b"solid cube\n")
    cases = [
        (lambda: get("da3-tiny"), "--model 'da3-tiny' is not a backbone"),
        (lambda: build_runner(tmp_path / "w.pt", backend="onnx"), "--backend onnx needs an .onnx file"),
        (lambda: read_ply(not_ply), "cloud.ply is not a PLY file"),
        (lambda: combine_scales(np.full(3, np.nan), np.ones(3), 1.65), "no chunk has a valid road-plane fit"),
    ]
    for call, fragment in cases:
        with pytest.raises(SwiftjaxError, match=fragment) as err:
            call()
        assert isinstance(err.value, ValueError) and "\n" not in str(err.value)

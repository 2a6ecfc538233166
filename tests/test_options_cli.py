"""Option errors in the user's words, before any work (issues 25 #13 #17 #18 #22 #27 #29, 26 #4)."""

from __future__ import annotations

import pytest

from swiftjax import cli
from swiftjax.cli import arguments


def _main(capsys, *argv):
    code = cli.main(list(map(str, argv)))
    out = capsys.readouterr()
    return code, out.out, out.err


def _one_line_error(code, err, *fragments, absent=()):
    assert code == 2, err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("swiftjax: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    for frag in fragments:
        assert frag in lines[0], lines[0]
    for frag in absent:
        assert frag not in lines[0], lines[0]
    return lines[0]


def _config(*argv):
    return arguments.pipeline_config(cli.build_parser().parse_args(["demo", *argv]))


def test_a_small_chunk_size_scales_the_loop_window_default():
    """`--chunk-size 8` failed on loop_half_window = 10, a default the user never set."""
    assert _config("--chunk-size", "8", "--overlap", "3").loop_half_window == 4
    assert _config("--chunk-size", "9", "--overlap", "3").loop_half_window == 4
    assert _config().loop_half_window == 10  # the paper's value where it fits
    # `--chunk-size 20` failed on overlap = 30, a default too: the paper's ratio 30 / 75
    assert (_config("--chunk-size", "20").overlap, _config("--chunk-size", "20").loop_half_window) == (8, 10)
    assert _config("--chunk-size", "2").overlap == 1 and _config("--chunk-size", "31").overlap == 30
    assert _config("--chunk-size", "8", "--overlap", "3", "--loop-half-window", "2").loop_half_window == 2


def test_cross_option_errors_name_the_flags_and_the_way_out(capsys, tmp_path):
    code, _, err = _main(
        capsys, "demo", "--out", tmp_path / "o", "--chunk-size", "8", "--overlap", "3", "--loop-half-window", "6"
    )
    _one_line_error(
        code,
        err,
        "--loop-half-window: invalid value 6;",
        "--chunk-size / 2 (4)",
        "--no-loop-closure",
        absent=("loop_half_window", "chunk_size", "(the default"),
    )
    code, _, err = _main(capsys, "demo", "--out", tmp_path / "o", "--chunk-size", "20", "--overlap", "25")
    _one_line_error(code, err, "--overlap: invalid value 25;", "< --chunk-size (20)", absent=("(the default",))
    assert not (tmp_path / "o").exists()


def test_speak_marks_a_default_the_user_never_set():
    from swiftjax import options

    line = options.speak(
        "PipelineConfig.overlap: invalid value 30; allowed: 1 <= overlap < chunk_size (20)",
        ["overlap", "chunk_size"],
        {"chunk_size": "cli"},
    )
    assert line == (
        "--overlap: invalid value 30 (the default: you did not set it); allowed: 1 <= --overlap < --chunk-size (20)"
    )
    line = options.speak(
        "PipelineConfig.overlap: invalid value 30; allowed: 1 <= overlap < chunk_size (20)",
        ["overlap", "chunk_size"],
        {"chunk_size": "file"},
        "c.toml",
    )
    assert "< chunk_size (20)" in line  # a key from the file keeps the file's spelling


@pytest.mark.parametrize(
    "argv, fragments",
    [
        (["--chunk-size", str(10**23)], ["--chunk-size", "out of range", "<= 10000"]),
        (["--point-stride", str(10**23)], ["--point-stride", "out of range", "<= 1024"]),
        (["--colmap-max-points", str(10**40)], ["--colmap-max-points", "out of range"]),
        (["--seed", "-1"], ["--seed must be >= 0, got -1"]),
        (["--frames", str(10**23)], ["--frames must be <= "]),
        (["--view", "--view-port", "99999"], ["--view-port must be <= 65535, got 99999"]),
        (["--image-size", "100000x100000"], ["--image-size 100000x100000", "from 14 to 4096"]),
    ],
)
def test_huge_or_negative_integers_are_one_line(capsys, tmp_path, argv, fragments):
    code, _, err = _main(capsys, "demo", "--out", tmp_path / "o", *argv)
    _one_line_error(code, err, *fragments)
    assert not (tmp_path / "o").exists()


def test_ports_are_checked_before_the_model_loads(capsys, tmp_path):
    for port in ("70000", "-1", "0"):
        code, _, err = _main(capsys, "view", tmp_path, "--port", port)
        _one_line_error(code, err, "--port must be", port)
    # the weights do not exist: the port is reported first, before anything is loaded
    code, _, err = _main(
        capsys,
        "reconstruct",
        tmp_path,
        "--weights",
        tmp_path / "w.pt",
        "--out",
        tmp_path / "o",
        "--view",
        "--view-port",
        "99999",
    )
    _one_line_error(code, err, "--view-port must be <= 65535", absent=("w.pt",))


def test_toml_huge_integer_and_mixed_tables(capsys, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("chunk_size = 100000000000000000000000000000000\n")
    code, _, err = _main(capsys, "demo", "--out", tmp_path / "o", "--config", cfg)
    _one_line_error(code, err, "chunk_size", "c.toml", "out of range")
    cfg.write_text("chunk_size = 40\n[swiftjax]\noverlap = 10\n")  # chunk_size was silently dropped
    code, _, err = _main(capsys, "demo", "--out", tmp_path / "o", "--config", cfg)
    _one_line_error(code, err, "c.toml", "top level (chunk_size)", "[swiftjax]")
    cfg.write_text("[swiftjax]\nchunk_size = 40\noverlap = 10\n[other_tool]\nx = 1\n")  # another tool's table
    assert (_config("--config", str(cfg)).chunk_size, _config("--config", str(cfg)).overlap) == (40, 10)


def test_toml_with_a_utf8_bom_is_read(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_bytes(b"\xef\xbb\xbfchunk_size = 40\noverlap = 10\n")
    conf = _config("--config", str(cfg))
    assert (conf.chunk_size, conf.overlap) == (40, 10)


def test_a_run_that_writes_no_point_is_not_done(capsys, tmp_path):
    """'done' over an empty cloud: exit 0 and "0 points written" with no warning."""
    code, out, err = _main(
        capsys,
        "demo",
        "--frames",
        "12",
        "--chunk-size",
        "8",
        "--overlap",
        "3",
        "--no-loop-closure",
        "--no-colmap",
        "--no-progress",
        "--point-conf-ratio",
        "10",
        "--out",
        tmp_path / "o",
    )
    assert code == 1, err
    line = next(ln for ln in err.splitlines() if "0 points" in ln)
    assert "--point-conf-ratio 10" in line and str(tmp_path / "o") in line
    assert (tmp_path / "o" / "poses_kitti.txt").is_file()  # the other outputs are kept

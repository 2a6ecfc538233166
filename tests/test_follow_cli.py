"""``swiftjax reconstruct DIR --follow`` through the real CLI on the tiny golden VGGT: poses
published while a recorder still writes, the finished run equal to the offline run of the same
folder, SIGINT finishing a complete (resumable) run, and the flags' one-line errors."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from test_faults import _env
from test_pipeline_stages import assert_same_outputs

from swiftjax.io.follow import Recorder
from swiftjax.pipeline import reader
from swiftjax.pipeline.live import LIVE_NAME

pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

N, B, O = 16, 8, 3  # live steps after frames 8 and 13, the short last chunk at the end marker, the final pass


def _frames(n: int = N) -> list[np.ndarray]:
    base = np.random.default_rng(0).integers(0, 255, (60, 220, 3), np.uint8)
    return [np.roll(base, 3 * k, axis=1) for k in range(n)]


def _argv(input, out, golden_dir, *extra):
    return [
        sys.executable,
        "-m",
        "swiftjax.cli",
        "reconstruct",
        str(input),
        "--weights",
        str(golden_dir / "tiny_weights.safetensors"),
        "--model-config",
        str(golden_dir / "tiny_config.json"),
        "--out",
        str(out),
        "--chunk-size",
        str(B),
        "--overlap",
        str(O),
        "--min-points",
        "10",
        "--no-loop-closure",
        "--no-progress",
        *extra,
    ]


def _wait_for(predicate, timeout_s: float, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if proc.poll() is not None:
            raise AssertionError(f"the CLI ended early: {proc.communicate()[1][-2000:]}")
        if time.monotonic() > deadline:
            proc.kill()
            raise AssertionError("timed out waiting for the live run")
        time.sleep(0.1)


def _live_frames(run_dir) -> list[int]:
    return [r["frame"] for r in reader.read_live_poses(run_dir)] if (run_dir / LIVE_NAME).exists() else []


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_follow_publishes_while_recording_and_finishes_as_offline(tmp_path, golden_dir):
    folder, live_dir, offline_dir = tmp_path / "rec", tmp_path / "live", tmp_path / "offline"
    folder.mkdir()
    frames = _frames()
    proc = subprocess.Popen(
        _argv(folder, live_dir, golden_dir, "--follow", "--follow-timeout", "120"),
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        # The first chunk's frames, then nothing more until their poses are published.
        with Recorder(folder, frames[:B], fps=20.0, end_marker=None) as rec:
            rec.wait()
        _wait_for(lambda: len(_live_frames(live_dir)) >= B, 300, proc)
        assert sorted(p.name for p in folder.iterdir()) == [f"{k:06d}.png" for k in range(B)]  # the rest unwritten
        first = reader.read_live_poses(live_dir)
        assert [r["frame"] for r in first] == list(range(B)) and {r["reason"] for r in first} == {"new"}
        # The rest of the drive, one of them written slowly (two parts), then the end marker.
        with Recorder(folder, frames[B:], fps=10.0, names=[f"{k:06d}.png" for k in range(B, N)], split=(2,)) as rec:
            rec.wait()
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-2000:]

    records = reader.read_live_poses(live_dir)
    # (the frames after the last chunk boundary from the short last chunk, at the end marker)
    assert [(r["frame"], r["reason"]) for r in records] == [(k, "new") for k in range(N)] + [
        (k, "final") for k in range(N)
    ]
    # The finished run directory is the offline run of the same folder, file by file.
    offline = subprocess.run(
        _argv(folder, offline_dir, golden_dir), env=_env(), capture_output=True, text=True, timeout=600
    )
    assert offline.returncode == 0, offline.stderr[-2000:]
    shutil.move(live_dir / LIVE_NAME, tmp_path / LIVE_NAME)
    assert_same_outputs(offline_dir, live_dir)

    # --replay-fps: the finished folder at a frame rate through the same engine, the same run.
    replay_dir = tmp_path / "replay"
    replay = subprocess.run(
        _argv(folder, replay_dir, golden_dir, "--replay-fps", "40"),
        env=_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert replay.returncode == 0, replay.stderr[-2000:]
    assert f"{N} frames arrived (ended by end)" in replay.stdout
    assert [r["frame"] for r in reader.read_live_poses(replay_dir) if r["reason"] == "final"] == list(range(N))
    (replay_dir / LIVE_NAME).unlink()
    assert_same_outputs(offline_dir, replay_dir)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_frames_deleted_after_they_were_read_lose_nothing(tmp_path, golden_dir):
    """A recorder that deletes each frame once it was read (a ring buffer): the CLI kept every
    frame it read (hard links beside the run directory), so the live chunks and the final
    pass have them all; the finished run is the offline run of the same files, and the kept
    frames are gone after it."""
    folder, out, backup, offline_dir = tmp_path / "rec", tmp_path / "run", tmp_path / "backup", tmp_path / "offline"
    folder.mkdir()
    backup.mkdir()
    keep = tmp_path / ".run.follow-frames"
    proc = subprocess.Popen(
        _argv(folder, out, golden_dir, "--follow", "--follow-timeout", "120"),
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deleted = []
    try:
        with Recorder(folder, _frames(), fps=20.0, end_marker=None) as rec:
            rec.wait()
        for k in range(N):  # each frame deleted once the CLI has read (kept) it
            name = f"{k:06d}.png"
            _wait_for(lambda: (keep / name).exists(), 300, proc)
            os.link(folder / name, backup / name)  # the same file, for the offline run below
            (folder / name).unlink()
            deleted.append(name)
        (folder / "END").touch()
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-2000:]
    assert len(deleted) == N and not list(folder.glob("*.png")) and not keep.exists()
    assert [r["frame"] for r in reader.read_live_poses(out) if r["reason"] == "final"] == list(range(N))
    offline = subprocess.run(
        _argv(backup, offline_dir, golden_dir), env=_env(), capture_output=True, text=True, timeout=600
    )
    assert offline.returncode == 0, offline.stderr[-2000:]
    (out / LIVE_NAME).unlink()
    assert_same_outputs(offline_dir, out)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_sigint_finishes_a_complete_resumable_run(tmp_path, golden_dir):
    folder, out = tmp_path / "rec", tmp_path / "run"
    frames = _frames(11)
    with Recorder(folder, frames[:9], fps=50.0, end_marker=None) as rec:  # no end marker: only SIGINT ends it
        rec.wait()
    proc = subprocess.Popen(
        _argv(folder, out, golden_dir, "--follow"),
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _wait_for(lambda: len(_live_frames(out)) >= B, 300, proc)
        proc.send_signal(signal.SIGINT)
        stdout, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-2000:]
    n = int(re.search(r"(\d+) frames arrived \(ended by stop\)", stdout).group(1))
    assert B <= n <= 9  # stopped (add_frame never waits for the poses: every frame there may be taken)
    records = reader.read_live_poses(out)
    assert [r["frame"] for r in records if r["reason"] == "final"] == list(range(n))
    # the recorder goes on after the stop: frames the run never took, for the re-run below
    with Recorder(folder, frames[9:], fps=50.0, end_marker=None, names=["000009.png", "000010.png"]) as rec:
        rec.wait()
    # Complete and resumable: an offline run over the whole folder resumes it ("frames added")
    # and ends equal to a fresh offline run.
    again = subprocess.run(_argv(folder, out, golden_dir), env=_env(), capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-2000:]
    shutil.move(out / LIVE_NAME, tmp_path / LIVE_NAME)
    fresh = subprocess.run(
        _argv(folder, tmp_path / "fresh", golden_dir), env=_env(), capture_output=True, text=True, timeout=600
    )
    assert fresh.returncode == 0, fresh.stderr[-2000:]
    assert_same_outputs(tmp_path / "fresh", out)


def test_follow_flag_errors_are_one_line(tmp_path, golden_dir, capsys):
    from swiftjax.cli import main

    folder = tmp_path / "rec"
    folder.mkdir()
    image = tmp_path / "one.png"
    cv2.imwrite(str(image), _frames(1)[0])
    ended = tmp_path / "ended"  # the recorder stopped before its first frame
    ended.mkdir()
    (ended / "END").touch()
    base = _argv(folder, tmp_path / "out", golden_dir)[3:]
    cases = [
        ([base[0], str(ended), *base[2:], "--follow"], f"{ended}: the end marker END appeared before any frame"),
        ([*base, "--follow", "--follow-timeout", "0.3"], "no frame arrived within the follow timeout of 0.3 s"),
        ([*base, "--follow", "--follow-timeout", "-1"], "--follow-timeout must be a positive number of seconds"),
        ([*base, "--replay-fps", "0"], "--replay-fps must be a positive number"),
        ([*base, "--follow", "--replay-fps", "10"], "--follow and --replay-fps exclude each other"),
        ([*base, "--follow-timeout", "5"], "--follow-timeout needs --follow"),
        ([base[0], str(image), *base[2:], "--follow"], "not a folder"),
    ]
    # --whitening-from RUN_DIR: checked before any frame is read (one line naming RUN_DIR)
    looping = [a for a in base if a != "--no-loop-closure"]
    other, bare = tmp_path / "other", tmp_path / "bare"
    for run_dir, model in ((other, {"weights": "another"}), (bare, None)):
        run_dir.mkdir()
        fingerprint = {} if model is None else {"temporal": {"identity": {"model": model}}}
        (run_dir / "manifest.json").write_text(
            json.dumps({"config": {}, "chunks": {}, "edges": {}, "fingerprint": fingerprint})
        )
    cases += [
        ([*base, "--whitening-from", str(other)], "--whitening-from needs --follow or --replay-fps"),
        ([*base, "--follow", "--whitening-from", str(other)], "--whitening-from is for live loop detection"),
        (
            [*looping, "--follow", "--whitening-from", str(tmp_path / "nowhere")],
            f"--whitening-from: run directory {tmp_path / 'nowhere'} does not exist",
        ),
        (
            [*looping, "--follow", "--whitening-from", str(ended)],
            f"{ended} is not a swiftjax run directory (no manifest.json",
        ),
        (
            [*looping, "--follow", "--whitening-from", str(other)],
            f"--whitening-from {other}: that run used another model",
        ),
        (
            [*looping, "--follow", "--whitening-from", str(bare)],
            f"{bare}: not a run directory with recorded descriptors (no {bare / 'chunks'})",
        ),
    ]
    for argv, fragment in cases:
        code = main(argv)
        err = capsys.readouterr().err.strip()
        assert code == 2 and fragment in err and len(err.splitlines()) == 1, (argv, err)
    assert not (tmp_path / "out").exists()


def test_a_frame_of_another_size_mid_run_is_one_line(tmp_path, golden_dir, capsys):
    from swiftjax.cli import main

    folder = tmp_path / "rec"
    frames = _frames(3)
    frames[2] = frames[2][:, :200]
    with Recorder(folder, frames, fps=50.0) as rec:
        rec.wait()
    code = main(_argv(folder, tmp_path / "out", golden_dir, "--follow")[3:])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "000002.png: frame is 200x60 but the frames before it are 220x60" in err

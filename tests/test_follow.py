"""Tests for swiftjax.io.follow: a folder filled by a recorder thread, replay at a rate.

Each test drives FollowSource with a Recorder thread (or writes files itself) and checks that
the thread is gone at the end; every test runs in well under a few seconds."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from swiftjax.io import follow
from swiftjax.io.images import InputError

POLL = 0.01


@pytest.fixture(autouse=True)
def no_thread_left():
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline and set(threading.enumerate()) - before:
        time.sleep(0.01)
    assert not set(threading.enumerate()) - before, "a thread outlived the test"


def frames(n, h=24, w=32, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(n)]


def test_every_frame_once_in_order_decoded_equal(tmp_path):
    imgs = frames(8)
    names = [f"img{k}.png" for k in range(8)]  # natural order: img2 before img10 would matter
    src = follow.FollowSource(tmp_path, timeout_s=5.0, poll_s=POLL)
    with follow.Recorder(tmp_path, imgs, fps=40.0, names=names) as rec:
        got = list(src)
        rec.wait()
    assert [f.name for f in got] == names and [f.index for f in got] == list(range(8))
    for f, img in zip(got, imgs):
        np.testing.assert_array_equal(f.image, img)
        assert f.path == tmp_path / f.name
    assert all(f.arrival >= t for f, t in zip(got, rec.finished_at))  # never before the last byte
    assert np.all(np.diff([f.arrival for f in got]) >= 0)
    assert src.ended_by == "end_marker" and src.count == 8 and src.image_hw == (24, 32)


def test_natural_order_and_folder_already_complete(tmp_path):
    imgs = frames(11, seed=1)
    names = [f"f{k}.png" for k in range(11)]  # f10 sorts after f9
    with follow.Recorder(tmp_path, imgs, fps=1000.0, names=names) as rec:
        rec.wait()
    (tmp_path / ".hidden.png").write_bytes(b"x")  # skipped, as by list_frames
    (tmp_path / "notes.txt").write_text("not a frame")
    got = list(follow.FollowSource(tmp_path, timeout_s=5.0, poll_s=POLL))
    assert [f.name for f in got] == names
    np.testing.assert_array_equal(got[10].image, imgs[10])


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp"])
def test_slowly_written_file_is_not_read_early(tmp_path, ext):
    """Frame 2 is written in two halves 0.3 s apart (30 polls): it is yielded only after its
    second half, whole, and frames 3.. wait for it (name order)."""
    imgs = frames(5, seed=2)
    src = follow.FollowSource(tmp_path, timeout_s=5.0, poll_s=POLL)
    with follow.Recorder(tmp_path, imgs, fps=50.0, ext=ext, split=(2,), split_pause_s=0.3) as rec:
        got = list(src)
        rec.wait()
    assert [f.index for f in got] == list(range(5))
    assert all(f.arrival >= t for f, t in zip(got, rec.finished_at))
    assert rec.finished_at[2] - rec.finished_at[1] >= 0.25  # frame 2 was half written for 0.3 s
    if ext != ".jpg":
        for f, img in zip(got, imgs):
            np.testing.assert_array_equal(f.image, img)
    else:  # lossy: compare with the decoded bytes as written
        from swiftjax.io.images import ImageFiles

        for f in got:
            np.testing.assert_array_equal(f.image, ImageFiles([f.path]).read(0))


def test_timeout_without_any_frame_is_one_clear_error(tmp_path):
    src = follow.FollowSource(tmp_path, timeout_s=0.2, poll_s=POLL)
    t0 = time.monotonic()
    with pytest.raises(follow.FollowTimeoutError) as err:
        list(src)
    assert time.monotonic() - t0 >= 0.2
    msg = str(err.value)
    assert msg == f"{tmp_path}: no frame arrived within the follow timeout of 0.2 s"
    assert isinstance(err.value, InputError) and "\n" not in msg


def test_file_stuck_incomplete_at_the_timeout_is_named(tmp_path):
    with follow.Recorder(tmp_path, frames(2, seed=14), fps=1000.0, end_marker=None) as rec:
        rec.wait()
    data = (tmp_path / "000001.png").read_bytes()
    (tmp_path / "000001.png").write_bytes(data[:100])  # the recorder hangs mid-file, no end marker
    got = []
    with pytest.raises(
        follow.FollowError,
        match=r"000001\.png: still not a complete image after the follow timeout "
        r"of 0\.2 s",
    ):
        for f in follow.FollowSource(tmp_path, timeout_s=0.2, poll_s=POLL):
            got.append(f)
    assert [f.name for f in got] == ["000000.png"]


def test_timeout_after_frames_ends_the_run(tmp_path):
    imgs = frames(3, seed=3)
    src = follow.FollowSource(tmp_path, timeout_s=0.3, poll_s=POLL)
    with follow.Recorder(tmp_path, imgs, fps=50.0, end_marker=None) as rec:
        got = list(src)
        rec.wait()
    assert len(got) == 3 and src.ended_by == "timeout"


def test_size_change_is_an_error_after_every_earlier_frame(tmp_path):
    imgs = frames(4, seed=4) + frames(1, h=20, w=32, seed=5) + frames(2, seed=6)
    src = follow.FollowSource(tmp_path, timeout_s=5.0, poll_s=POLL)
    got = []
    with follow.Recorder(tmp_path, imgs, fps=50.0):
        with pytest.raises(follow.FrameSizeError) as err:
            for f in src:
                got.append(f)
    assert [f.index for f in got] == [0, 1, 2, 3]  # nothing lost before the bad frame
    for f, img in zip(got, imgs):
        np.testing.assert_array_equal(f.image, img)
    assert str(err.value) == (
        f"{tmp_path / '000004.png'}: frame is 32x20 but the frames before it are 32x24 "
        "(from 000000.png); all frames must have one size"
    )


def test_frame_deleted_after_it_was_read_is_harmless(tmp_path):
    imgs = frames(6, seed=7)
    src = follow.FollowSource(tmp_path, timeout_s=5.0, poll_s=POLL)
    got = []
    with follow.Recorder(tmp_path, imgs, fps=30.0) as rec:
        for f in src:
            f.path.unlink()  # the recorder's ring buffer deletes frames once read
            got.append(f)
        rec.wait()
    assert [f.index for f in got] == list(range(6)) and not list(tmp_path.glob("*.png"))
    for f, img in zip(got, imgs):
        np.testing.assert_array_equal(f.image, img)


def test_kept_frames_survive_the_recorder_deleting_them(tmp_path):
    """``keep``: each frame hard-linked aside as it is read; the recorder deleting the original
    (a ring buffer) loses nothing: the kept file is the same file (inode, name, size, mtime:
    the run's fingerprint) and decodes to the same pixels."""
    folder, keep = tmp_path / "rec", tmp_path / "kept"
    folder.mkdir()
    imgs = frames(5, seed=9)
    src = follow.FollowSource(folder, timeout_s=5.0, poll_s=POLL, keep=keep)
    got, stats = [], []
    with follow.Recorder(folder, imgs, fps=30.0) as rec:
        for f in src:
            original = folder / f.name
            stats.append(original.stat())
            assert f.path == keep / f.name and os.path.samefile(f.path, original)
            original.unlink()  # the recorder deletes what was read
            got.append(f)
        rec.wait()
    assert [f.index for f in got] == list(range(5)) and not list(folder.glob("*.png"))
    for f, img, st in zip(got, imgs, stats):
        kept = f.path.stat()
        assert (kept.st_size, kept.st_mtime_ns) == (st.st_size, st.st_mtime_ns)
        np.testing.assert_array_equal(f.image, img)
        np.testing.assert_array_equal(follow.ImageFiles([f.path]).read(0), img)  # read again: the same


def test_end_marker_before_any_frame(tmp_path):
    (tmp_path / "END").touch()
    with pytest.raises(follow.FollowError) as err:
        list(follow.FollowSource(tmp_path, timeout_s=5.0, poll_s=POLL))
    assert str(err.value) == f"{tmp_path}: the end marker END appeared before any frame"


def test_truncated_file_at_the_end_marker_is_named(tmp_path):
    with follow.Recorder(tmp_path, frames(2, seed=8), fps=1000.0) as rec:
        rec.wait()
    data = (tmp_path / "000001.png").read_bytes()
    (tmp_path / "000001.png").write_bytes(data[: len(data) // 2])  # the recorder died mid-file
    src = follow.FollowSource(tmp_path, timeout_s=5.0, poll_s=POLL)
    it = iter(src)
    assert next(it).index == 0
    with pytest.raises(
        follow.FollowError,
        match=r"000001\.png: still not a complete image \(\d+ bytes\) when the end "
        "marker END appeared",
    ):
        next(it)


def test_late_file_sorting_before_a_read_one(tmp_path):
    with follow.Recorder(tmp_path, frames(2, seed=9), fps=1000.0, names=["b.png", "c.png"], end_marker=None) as rec:
        rec.wait()
    src = follow.FollowSource(tmp_path, timeout_s=5.0, poll_s=POLL)
    it = iter(src)
    assert [next(it).name, next(it).name] == ["b.png", "c.png"]
    with follow.Recorder(tmp_path, frames(1, seed=10), fps=1000.0, names=["a.png"]) as rec:
        rec.wait()
    with pytest.raises(follow.FollowError, match=r"a\.png: arrived after c\.png was read but sorts before it"):
        next(it)


def test_stop_from_another_thread_ends_cleanly(tmp_path):
    src = follow.FollowSource(tmp_path, timeout_s=None, poll_s=0.05)
    got = []
    with follow.Recorder(tmp_path, frames(200, seed=11), fps=20.0):  # 10 s of frames, no end marker yet
        timer = threading.Timer(0.4, src.stop)
        timer.start()
        t0 = time.monotonic()
        for f in src:
            got.append(f)
        elapsed = time.monotonic() - t0
        timer.join()
    assert src.ended_by == "stop" and len(got) < 20 and elapsed < 1.5
    assert [f.index for f in got] == list(range(len(got)))


def test_bad_arguments(tmp_path):
    with pytest.raises(follow.FollowError, match=f"{tmp_path / 'nope'}: no such folder to follow"):
        follow.FollowSource(tmp_path / "nope")
    with pytest.raises(follow.FollowError, match="follow timeout must be > 0"):
        follow.FollowSource(tmp_path, timeout_s=0)
    with pytest.raises(InputError, match="replay rate must be a positive"):
        follow.ReplaySource(tmp_path, fps=0)


def test_replay_folder_at_fps(tmp_path):
    imgs = frames(6, seed=12)
    with follow.Recorder(tmp_path, imgs, fps=1000.0, end_marker=None) as rec:
        rec.wait()
    replay = follow.ReplaySource(tmp_path, fps=20.0)
    got = list(replay)
    arrivals = np.array([f.arrival for f in got])
    assert [f.index for f in got] == list(range(6)) and replay.ended_by == "end"
    assert arrivals[-1] - arrivals[0] >= 5 / 20.0 - 1e-3  # (n - 1) / fps at least
    assert np.all(arrivals - arrivals[0] >= np.arange(6) / 20.0 - 1e-3)  # no frame early (a late one catches up)
    for f, img in zip(got, imgs):
        np.testing.assert_array_equal(f.image, img)


def test_replay_video_and_stop(tmp_path):
    cv2 = pytest.importorskip("cv2")
    path = tmp_path / "drive.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (32, 24))
    for img in frames(5, seed=13):
        writer.write(img[:, :, ::-1])
    writer.release()
    replay = follow.ReplaySource(path, fps=25.0)
    got = list(replay)
    assert [f.name for f in got] == [f"drive_{k:06d}.png" for k in range(5)] and got[0].image.shape == (24, 32, 3)
    assert got[-1].arrival - got[0].arrival >= 4 / 25.0 - 1e-3
    assert all(f.path is None for f in got)
    replay = follow.ReplaySource(path, fps=5.0)
    it = iter(replay)
    next(it)
    replay.stop()
    assert list(it) == [] and replay.ended_by == "stop"

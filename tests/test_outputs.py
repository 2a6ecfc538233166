"""Self-describing outputs: TUM timestamps from the source, headers, points.png."""

from __future__ import annotations

import numpy as np
import pytest

from swiftjax.io import images


def _video(path, n, fps):
    cv2 = pytest.importorskip("cv2")
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (32, 24))
    assert vw.isOpened()
    for _ in range(n):
        vw.write(np.full((24, 32, 3), 128, np.uint8))
    vw.release()


def test_video_timestamps_are_frame_index_over_fps_with_stride(tmp_path):
    _video(tmp_path / "drive.avi", 12, 25.0)
    ts, note = images.list_frames(tmp_path / "drive.avi", stride=3).timestamps()
    np.testing.assert_allclose(ts, np.array([0, 3, 6, 9]) / 25.0, rtol=1e-12)
    assert "25 fps" in note and "stride 3" in note


def test_image_folder_timestamps(tmp_path):
    for k in range(6):
        (tmp_path / f"{k:03d}.png").write_bytes(b"")  # list_frames does not decode
    src = images.list_frames(tmp_path)
    ts, note = src.timestamps()
    np.testing.assert_array_equal(ts, np.arange(6.0))
    assert note.startswith("frame index")
    # TUM rgb.txt: "timestamp name", any order, names matched (with --stride too).
    (tmp_path / "rgb.txt").write_text("# timestamp filename\n" + "".join(
        f"{100 + 0.5 * k:.6f} rgb/{k:03d}.png\n" for k in reversed(range(6))))
    np.testing.assert_allclose(images.read_timestamps(tmp_path / "rgb.txt", src), 100 + 0.5 * np.arange(6))
    strided = images.list_frames(tmp_path, stride=2)
    np.testing.assert_allclose(images.read_timestamps(tmp_path / "rgb.txt", strided, 2), [100, 101, 102])
    # One time per line: for every input image (stride applied) or for the frames used.
    (tmp_path / "t.txt").write_text("".join(f"{0.1 * k}\n" for k in range(6)))
    np.testing.assert_allclose(images.read_timestamps(tmp_path / "t.txt", strided, 2), [0.0, 0.2, 0.4])
    np.testing.assert_allclose(images.read_timestamps(tmp_path / "t.txt", src), 0.1 * np.arange(6))


@pytest.mark.parametrize(
    "text,match",
    [
        ("1\n2\n", "has 2 times for 6 frames"),
        ("0 000.png\n1 001.png\n", "no time for frame 002.png"),
        ("0\n1\n2\n2\n4\n5\n", "times must increase"),
        ("0\n1\nabc\n3\n4\n5\n", "'abc' is not a number"),
        ("0\n1\nnan\n3\n4\n5\n", "non-finite"),
    ],
)
def test_bad_timestamps_files(tmp_path, text, match):
    for k in range(6):
        (tmp_path / f"{k:03d}.png").write_bytes(b"")
    (tmp_path / "t.txt").write_text(text)
    with pytest.raises(images.InputError, match=match):
        images.read_timestamps(tmp_path / "t.txt", images.list_frames(tmp_path))

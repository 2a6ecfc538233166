"""``swiftjax batch``: run-directory names stay inside --out, the list takes shell quoting,
a video keeps its own times and --timestamps reaches every sequence (issue 25 #11 #12 #27 #31)."""

from __future__ import annotations

import numpy as np
import pytest

from swiftjax import cli
from swiftjax.pipeline import batch

cv2 = pytest.importorskip("cv2")


def test_a_dotdot_line_is_named_after_the_folder_it_resolves_to(tmp_path):
    """A list line `..` named its run `..`: the run went to the parent of --out."""
    (tmp_path / "seqs" / "lists").mkdir(parents=True)
    lst = tmp_path / "seqs" / "lists" / "list.txt"
    lst.write_text("..\n.\n")
    items = batch.read_list(lst)
    assert batch.unique_names([i for i, _ in items]) == ["seqs", "lists"]
    with pytest.raises(batch.BatchError, match="cannot name a run directory after '/'"):
        batch.unique_names(["/"])


@pytest.mark.parametrize("name", ["..", ".", "", "a/b", "../x"])
def test_run_batch_refuses_names_that_leave_out(tmp_path, name):
    from swiftjax.synthetic import demo

    out = tmp_path / "batch" / "out"
    job = batch.Sequence(name, demo.loop_route_run(10).predictor.spec())
    with pytest.raises(batch.BatchError, match="must name a folder inside --out"):
        batch.run_batch([job], out)
    assert not (tmp_path / "batch").exists()  # nothing written anywhere


def test_batch_out_at_a_file_is_one_line(tmp_path, capsys):
    (tmp_path / "frames").mkdir()
    (tmp_path / "list.txt").write_text("frames\n")
    (tmp_path / "w.pt").write_bytes(b"")
    (tmp_path / "out").write_text("a file")
    code = cli.main(
        ["batch", str(tmp_path / "list.txt"), "--weights", str(tmp_path / "w.pt"), "--out", str(tmp_path / "out")]
    )
    err = capsys.readouterr().err
    assert code == 2 and "--out" in err and "is a file" in err and "File exists" not in err
    assert (tmp_path / "out").read_text() == "a file"


def test_list_lines_take_shell_quoting_and_hash_inside_names(tmp_path):
    """`my seq` was split into INPUT and GT; `take#1` was cut at `#`."""
    (tmp_path / "list.txt").write_text(
        "\"my seq/images\" 'gt files/my seq.txt'   # quoted\n"
        "take#1/frames\n"
        "with\\ space/frames gt.txt#not-a-comment\n"
        "  # a comment line\n"
    )
    items = batch.read_list(tmp_path / "list.txt")
    assert items == [
        (str(tmp_path / "my seq/images"), str(tmp_path / "gt files/my seq.txt")),
        (str(tmp_path / "take#1/frames"), None),
        (str(tmp_path / "with space/frames"), str(tmp_path / "gt.txt#not-a-comment")),
    ]
    (tmp_path / "bad.txt").write_text('"unclosed gt.txt\n')
    with pytest.raises(batch.BatchError, match="bad.txt:1: No closing quotation"):
        batch.read_list(tmp_path / "bad.txt")


def _video(path, n, fps):
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (32, 24))
    for _ in range(n):
        vw.write(np.full((24, 32, 3), 128, np.uint8))
    vw.release()


def _batch_times(tmp_path, monkeypatch, lst, *extra):
    """The times each sequence's reconstruct got (the model is never loaded)."""
    from swiftjax.pipeline import run

    seen = {}

    def fake_reconstruct(predictor, out, config, **kwargs):
        seen[out.name] = (kwargs.get("timestamps"), kwargs.get("timestamps_note"))
        raise RuntimeError("stop here")

    monkeypatch.setattr(run, "reconstruct", fake_reconstruct)
    (tmp_path / "w.pt").write_bytes(b"")
    code = cli.main(["batch", str(lst), "--weights", str(tmp_path / "w.pt"), "--out", str(tmp_path / "out"), *extra])
    assert code == 1  # every sequence "failed" at the fake
    return seen


def test_a_video_keeps_its_own_times_in_a_batch(tmp_path, monkeypatch, capsys):
    """batch wrote TUM times 0, 1, 2 (the frame index) where reconstruct writes the video's k / fps."""
    _video(tmp_path / "drive.avi", 9, 5.0)
    (tmp_path / "list.txt").write_text("drive.avi\n")
    seen = _batch_times(tmp_path, monkeypatch, tmp_path / "list.txt", "--stride", "2")
    times, note = seen["drive"]
    np.testing.assert_allclose(times, np.arange(0, 9, 2) / 5.0, rtol=1e-9)
    assert "fps" in note


def test_batch_timestamps_name_a_file_in_each_sequence(tmp_path, monkeypatch, capsys):
    for seq, t0 in (("a", 100.0), ("b", 200.0)):
        (tmp_path / seq / "rgb").mkdir(parents=True)
        for k in range(3):
            cv2.imwrite(str(tmp_path / seq / "rgb" / f"{k}.png"), np.full((20, 30, 3), 50 * k, np.uint8))
        (tmp_path / seq / "rgb.txt").write_text("".join(f"{t0 + 0.5 * k} rgb/{k}.png\n" for k in range(3)))
    (tmp_path / "list.txt").write_text("a/rgb\nb/rgb\n")
    seen = _batch_times(tmp_path, monkeypatch, tmp_path / "list.txt", "--timestamps", "rgb.txt")
    np.testing.assert_allclose(seen["rgb"][0], [100.0, 100.5, 101.0])
    np.testing.assert_allclose(seen["rgb_2"][0], [200.0, 200.5, 201.0])
    assert "rgb.txt" in seen["rgb"][1]
    (tmp_path / "b" / "rgb.txt").unlink()
    code = cli.main(
        [
            "batch",
            str(tmp_path / "list.txt"),
            "--weights",
            str(tmp_path / "w.pt"),
            "--out",
            str(tmp_path / "out2"),
            "--timestamps",
            "rgb.txt",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "has no rgb.txt" in err and "b/rgb" in err and not (tmp_path / "out2").exists()

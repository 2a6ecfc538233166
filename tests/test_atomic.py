"""swiftjax.io.atomic: the old file survives a failed write; no temp files are left behind."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from swiftjax.io.atomic import atomic_path, atomic_save_npz, atomic_write


def _listing(d):
    return sorted(p.name for p in d.iterdir())


def test_text_and_bytes_written(tmp_path):
    p = tmp_path / "a.txt"
    with atomic_write(p) as f:
        f.write("héllo\n")
    assert p.read_text(encoding="utf-8") == "héllo\n"
    with atomic_write(p, "wb") as f:
        f.write(b"\x00\x01")
    assert p.read_bytes() == b"\x00\x01"
    assert _listing(tmp_path) == ["a.txt"]


def test_exception_mid_write_keeps_old_file_and_no_temp(tmp_path):
    p = tmp_path / "poses.txt"
    p.write_text("old contents\n")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_write(p) as f:
            f.write("new half-writ")
            f.flush()
            raise RuntimeError("boom")
    assert p.read_text() == "old contents\n"
    assert _listing(tmp_path) == ["poses.txt"]


def test_exception_when_target_absent_creates_nothing(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with atomic_write(tmp_path / "x.bin", "wb") as f:
            f.write(b"abc")
            raise KeyboardInterrupt
    assert _listing(tmp_path) == []


def test_atomic_path_keeps_suffix_and_permissions(tmp_path):
    p = tmp_path / "plot.png"
    with atomic_path(p) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".png" and tmp != p
        tmp.write_bytes(b"png")
    assert p.read_bytes() == b"png"
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~umask  # not mkstemp's 0600
    assert _listing(tmp_path) == ["plot.png"]


def test_missing_directory_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        with atomic_write(tmp_path / "nope" / "a.txt") as f:
            f.write("x")


def test_bad_mode():
    with pytest.raises(ValueError, match="mode"):
        with atomic_write("x", "a"):
            pass


@pytest.mark.parametrize("compress", [False, True])
def test_atomic_save_npz_exact_name(tmp_path, compress):
    p = tmp_path / "chunk_0001.tmpname"  # no .npz suffix appended
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    atomic_save_npz(p, compress=compress, a=a, b=np.array([1, 2], np.uint8))
    assert _listing(tmp_path) == ["chunk_0001.tmpname"]
    with np.load(p) as z:
        np.testing.assert_array_equal(z["a"], a)
        assert z["b"].dtype == np.uint8


def test_atomic_paths_replace_all_or_none(tmp_path):
    from swiftjax.io.atomic import atomic_paths

    targets = [tmp_path / "a.png", tmp_path / "b.png"]
    targets[0].write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_paths(targets) as tmps:
            tmps[0].write_bytes(b"new a")
            raise RuntimeError("interrupted")
    assert targets[0].read_bytes() == b"old" and not targets[1].exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]  # no temp file left
    with atomic_paths(targets) as tmps:
        assert all(t.suffix == ".png" for t in tmps)
        for t, data in zip(tmps, (b"A", b"B")):
            t.write_bytes(data)
    assert [t.read_bytes() for t in targets] == [b"A", b"B"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.png"]


def test_output_set_renames_together_or_not_at_all(tmp_path):
    from swiftjax.io.atomic import atomic_paths, output_set, temp_files

    (tmp_path / "a.txt").write_text("old a")
    with pytest.raises(OSError):
        with output_set():
            with atomic_write(tmp_path / "a.txt") as f:
                f.write("new a")
            assert (tmp_path / "a.txt").read_text() == "old a"  # not renamed yet
            with atomic_paths([tmp_path / "b.bin"]) as (tmp,):
                tmp.write_bytes(b"b")
            raise OSError(28, "No space left on device")
    assert (tmp_path / "a.txt").read_text() == "old a" and not (tmp_path / "b.bin").exists()
    assert temp_files(tmp_path) == []
    with output_set():
        with atomic_write(tmp_path / "a.txt") as f:
            f.write("new a")
        with output_set():  # nested: joins the outer set
            with atomic_write(tmp_path / "a.txt") as f:
                f.write("newer a")
        with atomic_paths([tmp_path / "b.bin"]) as (tmp,):
            tmp.write_bytes(b"b")
        assert not (tmp_path / "b.bin").exists()
    assert (tmp_path / "a.txt").read_text() == "newer a" and (tmp_path / "b.bin").read_bytes() == b"b"
    assert temp_files(tmp_path) == []

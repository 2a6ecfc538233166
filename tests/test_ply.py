"""swiftjax.io.ply: exact round trips, an independent header parse, streaming, voxel downsampling."""

from __future__ import annotations

import os

import numpy as np
import pytest

from swiftjax.io import ply as ply_module
from swiftjax.io.ply import PlyStreamWriter, ply_dtype, read_ply, voxel_downsample, write_ply


def _cloud(n, seed=0):
    rng = np.random.default_rng(seed)
    p = (rng.standard_normal((n, 3)) * 100).astype(np.float32)
    c = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    k = (1 + rng.exponential(size=n)).astype(np.float32)
    return p, c, k


def _spec_reader(path):
    """Independent minimal reader from the PLY spec: header lines up to 'end_header', then
    a packed binary_little_endian body of scalar vertex properties."""
    types = {"float": "<f4", "uchar": "u1", "double": "<f8", "int": "<i4"}
    data = open(path, "rb").read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0" and lines[-1] == "end_header"
    count, fields = None, []
    for line in lines:
        w = line.split(" ")  # deliberately strict: single-space separated, no padding allowed
        if w[0] == "element":
            assert w[1] == "vertex" and len(w) == 3 and w[2] == str(int(w[2]))  # canonical count
            count = int(w[2])
        elif w[0] == "property":
            fields.append((w[2], types[w[1]]))
    dt = np.dtype(fields)
    assert len(data) - end == count * dt.itemsize  # nothing more, nothing less
    return np.frombuffer(data, dtype=dt, count=count, offset=end)


@pytest.mark.parametrize("with_colors,with_conf", [(True, True), (True, False), (False, True), (False, False)])
def test_round_trip_exact(tmp_path, with_colors, with_conf):
    p, c, k = _cloud(1000)
    c = c if with_colors else None
    k = k if with_conf else None
    path = tmp_path / "points.ply"
    write_ply(path, p, c, k)
    out = read_ply(path)
    np.testing.assert_array_equal(out.points, p)
    assert out.points.dtype == np.float32
    if with_colors:
        np.testing.assert_array_equal(out.colors, c)
        assert out.colors.dtype == np.uint8
    else:
        assert out.colors is None
    if with_conf:
        np.testing.assert_array_equal(out.conf, k)
    else:
        assert out.conf is None
    assert os.path.getsize(path) == len(ply_module._header(1000, ply_dtype(with_colors, with_conf))) + 1000 * (
        12 + 3 * with_colors + 4 * with_conf
    )


def test_independent_spec_reader(tmp_path):
    p, c, k = _cloud(257)
    write_ply(tmp_path / "a.ply", p, c, k)
    rec = _spec_reader(tmp_path / "a.ply")
    assert rec.dtype.names == ("x", "y", "z", "red", "green", "blue", "confidence")
    assert rec.dtype.itemsize == 19
    np.testing.assert_array_equal(np.stack([rec["x"], rec["y"], rec["z"]], 1), p)
    np.testing.assert_array_equal(np.stack([rec["red"], rec["green"], rec["blue"]], 1), c)
    np.testing.assert_array_equal(rec["confidence"], k)


def test_plyfile_reads_our_files(tmp_path):
    plyfile = pytest.importorskip("plyfile")
    p, c, k = _cloud(300)
    write_ply(tmp_path / "a.ply", p, c, k)
    with PlyStreamWriter(tmp_path / "b.ply") as w:
        w.append(p[:100], c[:100], k[:100])
        w.append(p[100:], c[100:], k[100:])
    for name in ("a.ply", "b.ply"):
        v = plyfile.PlyData.read(str(tmp_path / name))["vertex"]
        assert v.count == 300
        np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), p)
        np.testing.assert_array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), c)
        np.testing.assert_array_equal(v["confidence"], k)


def test_stream_equals_one_shot_and_large_count(tmp_path):
    n = 1_500_000  # ~28 MB: a count with 7 digits, batches of uneven size
    p, c, k = _cloud(n, seed=1)
    cuts = [0, 1, 700_001, 700_001, 1_200_000, n]  # includes an empty batch
    with PlyStreamWriter(tmp_path / "s.ply") as w:
        for a, b in zip(cuts[:-1], cuts[1:]):
            w.append(p[a:b], c[a:b], k[a:b])
    assert w.count == n
    rec = _spec_reader(tmp_path / "s.ply")
    assert len(rec) == n
    np.testing.assert_array_equal(np.stack([rec["x"], rec["y"], rec["z"]], 1), p)
    np.testing.assert_array_equal(rec["confidence"], k)
    out = read_ply(tmp_path / "s.ply")
    np.testing.assert_array_equal(out.colors, c)


def test_stream_header_reserve_holds_any_count():
    dt = ply_dtype()
    size = len(ply_module._header(0, dt)) + ply_module._COUNT_WIDTH
    for count in (0, 9, 10**6, 2**64 - 1):
        h = ply_module._header(count, dt, pad_to=size)
        assert len(h) == size and f"\nelement vertex {count}\n".encode() in h
        assert all(line.strip() != "comment" for line in h.decode().splitlines())  # no blank comment
    with pytest.raises(ValueError, match="does not fit"):
        ply_module._header(10**25, dt, pad_to=size)


def test_stream_empty(tmp_path):
    with PlyStreamWriter(tmp_path / "e.ply", colors=False, conf=False):
        pass
    out = read_ply(tmp_path / "e.ply")
    assert out.points.shape == (0, 3) and out.colors is None and out.conf is None


def test_stream_exception_keeps_old_file(tmp_path):
    path = tmp_path / "points.ply"
    p, c, k = _cloud(10)
    write_ply(path, p, c, k)
    before = path.read_bytes()
    with pytest.raises(RuntimeError):
        with PlyStreamWriter(path) as w:
            w.append(p, c, k)
            raise RuntimeError("inference failed")
    assert path.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["points.ply"]


def test_stream_column_mismatch_and_closed(tmp_path):
    p, c, k = _cloud(4)
    with pytest.raises(ValueError, match="conf=True but append got conf=None"):
        with PlyStreamWriter(tmp_path / "x.ply") as w:
            w.append(p, c, None)
    w = PlyStreamWriter(tmp_path / "y.ply")
    with pytest.raises(RuntimeError, match="not open"):
        w.append(p, c, k)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "args,match",
    [
        ((np.zeros((3, 2)),), r"shape \[N, 3\]"),
        ((np.zeros((3, 3)), np.zeros((3, 3))), "uint8"),
        ((np.zeros((3, 3)), np.zeros((2, 3), np.uint8)), r"shape \[3, 3\]"),
        ((np.zeros((3, 3)), None, np.zeros(4)), r"shape \[3\]"),
    ],
)
def test_write_rejects_bad_input(tmp_path, args, match):
    with pytest.raises(ValueError, match=match):
        write_ply(tmp_path / "bad.ply", *args)
    assert not any(tmp_path.iterdir())


def test_read_ascii_with_other_elements(tmp_path):
    text = (
        "ply\nformat ascii 1.0\ncomment made by hand\n"
        "element camera 2\nproperty float f\n"
        "element vertex 3\nproperty double x\nproperty double y\nproperty double z\n"
        "property uchar r\nproperty uchar g\nproperty uchar b\nproperty float nx\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "1.5\n2.5\n"
        "0 1 2 255 0 7 0.5\n-1.25 3e2 4 1 2 3 0\n5 6 7 9 8 7 1\n"
        "3 0 1 2\n"
    )
    (tmp_path / "a.ply").write_text(text)
    out = read_ply(tmp_path / "a.ply")
    np.testing.assert_array_equal(out.points, np.array([[0, 1, 2], [-1.25, 300, 4], [5, 6, 7]], np.float32))
    np.testing.assert_array_equal(out.colors, np.array([[255, 0, 7], [1, 2, 3], [9, 8, 7]], np.uint8))
    assert out.conf is None


def test_read_big_endian_with_preceding_element(tmp_path):
    p, c, k = _cloud(5)
    dt = np.dtype(
        [
            ("x", ">f8"),
            ("y", ">f8"),
            ("z", ">f8"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
            ("confidence", ">f4"),
        ]
    )
    rec = np.empty(5, dt)
    for i, a in enumerate("xyz"):
        rec[a] = p[:, i]
    rec["red"], rec["green"], rec["blue"] = c.T
    rec["confidence"] = k
    head = (
        "ply\nformat binary_big_endian 1.0\nelement meta 2\nproperty short a\nelement vertex 5\n"
        "property double x\nproperty double y\nproperty double z\nproperty uchar red\n"
        "property uchar green\nproperty uchar blue\nproperty float confidence\nend_header\n"
    )
    (tmp_path / "b.ply").write_bytes(head.encode() + np.array([7, 8], ">i2").tobytes() + rec.tobytes())
    out = read_ply(tmp_path / "b.ply")
    np.testing.assert_array_equal(out.points, p)
    np.testing.assert_array_equal(out.colors, c)
    np.testing.assert_array_equal(out.conf, k)


def test_read_errors_name_the_file(tmp_path):
    (tmp_path / "no.ply").write_text("hello\n")
    with pytest.raises(ValueError, match=r"no\.ply is not a PLY file"):
        read_ply(tmp_path / "no.ply")
    p, c, k = _cloud(10)
    write_ply(tmp_path / "t.ply", p, c, k)
    data = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[:-5])
    with pytest.raises(ValueError, match=r"t\.ply: PLY file is truncated"):
        read_ply(tmp_path / "t.ply")
    (tmp_path / "f.ply").write_text("ply\nformat ascii 1.0\nelement face 0\nproperty float q\nend_header\n")
    with pytest.raises(ValueError, match="no 'vertex' element"):
        read_ply(tmp_path / "f.ply")
    (tmp_path / "h.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\n")
    with pytest.raises(ValueError, match="no 'end_header'"):
        read_ply(tmp_path / "h.ply")


def _voxel_reference(p, k, voxel):
    """Python reference: dict from voxel cell to the best (highest conf, then earliest) index."""
    best = {}
    for i in range(len(p)):
        if not np.all(np.isfinite(p[i])):
            continue
        cell = tuple(int(v) for v in np.floor(p[i].astype(np.float64) / voxel))
        score = -np.inf if k is None else float(k[i])
        if cell not in best or score > best[cell][0]:
            best[cell] = (score, i)
    return np.sort(np.array([i for _, i in best.values()], dtype=np.int64))


@pytest.mark.parametrize("use_conf", [True, False])
def test_voxel_downsample_matches_reference(use_conf):
    rng = np.random.default_rng(3)
    p = rng.uniform(-3, 3, (3000, 3)).astype(np.float32)
    p[::97] = np.nan
    c = rng.integers(0, 256, (3000, 3), dtype=np.uint8)
    k = rng.integers(1, 5, 3000).astype(np.float32)  # many ties: earliest must win
    voxel = 0.7
    out = voxel_downsample(p, c, k if use_conf else None, voxel)
    keep = _voxel_reference(p, k if use_conf else None, voxel)
    assert len(keep) < 1000  # it really merged points
    np.testing.assert_array_equal(out.points, p[keep])
    np.testing.assert_array_equal(out.colors, c[keep])
    if use_conf:
        np.testing.assert_array_equal(out.conf, k[keep])
    else:
        assert out.conf is None


def test_voxel_downsample_special_cases():
    p = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [-0.1, 0.1, 0.1], [1e7, 1e7, 1e7], [-1e7, -1e7, -1e7]], np.float32)
    k = np.array([1.0, 2.0, 1.0, 1.0, 1.0], np.float32)
    out = voxel_downsample(p, None, k, 1.0)  # huge extent: exercises the row-key fallback
    np.testing.assert_array_equal(out.points, p[[1, 2, 3, 4]])  # -0.1 is in a different cell
    empty = voxel_downsample(np.zeros((0, 3), np.float32), None, np.zeros(0, np.float32), 0.5)
    assert empty.points.shape == (0, 3)
    with pytest.raises(ValueError, match="positive"):
        voxel_downsample(p, None, k, 0.0)


def test_header_comments_none_blank(tmp_path):
    """A streamed PLY has no blank comment line (the reserved space trails the first comment)
    and carries the comments it is given, one line each (issue 26 item 11)."""
    notes = ["unit: up to scale", "frame: the first camera's frame,  OpenCV axes"]
    with PlyStreamWriter(tmp_path / "s.ply", colors=False, conf=False, comments=notes) as w:
        w.append(np.ones((5, 3), np.float32))
    data = (tmp_path / "s.ply").read_bytes()
    head = data[: data.index(b"end_header\n")].decode().splitlines()
    comments = [ln.rstrip() for ln in head if ln.startswith("comment")]
    assert comments == [
        "comment written by swiftjax",
        "comment unit: up to scale",
        "comment frame: the first camera's frame, OpenCV axes",
    ]
    assert all(ln.split(maxsplit=1)[1:] for ln in comments)
    np.testing.assert_array_equal(_spec_reader(tmp_path / "s.ply")["x"], np.ones(5))
    write_ply(tmp_path / "o.ply", np.zeros((2, 3)), comments=["unit: metres"])
    assert b"\ncomment unit: metres\nelement vertex 2\n" in (tmp_path / "o.ply").read_bytes()


def test_run_points_ply_names_unit_and_frame(small_loop_run):
    out, result = small_loop_run
    data = (out / "points.ply").read_bytes()
    head = data[: data.index(b"end_header\n")].decode().splitlines()
    comments = [ln.rstrip() for ln in head if ln.startswith("comment")]
    assert all(len(c) > len("comment") for c in comments), comments
    assert any(c.startswith("comment unit: up to scale") for c in comments), comments
    assert any(c.startswith("comment frame: the run's world = the first camera's frame, OpenCV") for c in comments)
    np.testing.assert_allclose(result.cam_to_world[0], np.eye(4), atol=1e-6)  # what the frame comment says
    assert len(read_ply(out / "points.ply").points) == result.metrics["points"]

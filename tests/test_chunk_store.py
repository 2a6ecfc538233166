"""swiftjax.io.chunk_store: round trips within float16 tolerance, atomic saves, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from swiftjax.io import chunk_store as cs
from swiftjax.io.chunk_store import ChunkStore
from swiftjax.prediction import ChunkPrediction

S, H, W = 4, 14, 18
EPS16 = 2.0**-11  # float16 unit roundoff (round to nearest)


def _pred(seed=0, descriptors=True, images=True, tokens=False):
    rng = np.random.default_rng(seed)
    ext = np.concatenate([np.linalg.qr(rng.standard_normal((S, 3, 3)))[0], rng.standard_normal((S, 3, 1))], -1)
    k = np.tile(np.array([[300.0, 0, 9.0], [0, 301.0, 7.0], [0, 0, 1]]), (S, 1, 1))
    return ChunkPrediction(
        depth=rng.uniform(0.05, 60.0, (S, H, W)).astype(np.float32),
        conf=(1 + np.exp(rng.normal(1, 2, (S, H, W)))).astype(np.float32),
        extrinsic=ext.astype(np.float32),
        intrinsic=k.astype(np.float32),
        descriptors=rng.standard_normal((S, 32)).astype(np.float32) if descriptors else None,
        patch_tokens=rng.standard_normal((S, 5, 8)).astype(np.float32) if tokens else None,
        images=rng.integers(0, 256, (S, H, W, 3), dtype=np.uint8) if images else None,
    )


def test_round_trip_values(tmp_path):
    store = ChunkStore(tmp_path)
    pred = _pred()
    path = store.save("chunk", 3, pred, extra={"frames": np.arange(45, 49), "scale": 1.5, "tag": "x"})
    assert path == tmp_path / "chunks" / "chunk_00003.npz"
    out = store.load("chunk", 3)
    for name in ("depth", "conf"):
        got, want = getattr(out, name), getattr(pred, name)
        assert got.dtype == np.float32 and got.shape == want.shape
        rel = np.abs(got - want) / np.abs(want)
        assert rel.max() <= EPS16 * (1 + 1e-6)  # float16 round-to-nearest bound
        assert rel.max() > 1e-5  # really stored in half precision
    for name in ("extrinsic", "intrinsic", "descriptors", "images"):
        np.testing.assert_array_equal(getattr(out, name), getattr(pred, name))
    assert out.images.dtype == np.uint8 and out.patch_tokens is None
    extra = store.load_extra("chunk", 3)
    np.testing.assert_array_equal(extra["frames"], np.arange(45, 49))
    assert float(extra["scale"]) == 1.5 and str(extra["tag"]) == "x"
    with np.load(path) as z:  # the storage dtypes themselves
        assert z["depth"].dtype == np.float16 and z["conf"].dtype == np.float16
        assert z["extrinsic"].dtype == np.float32 and z["images"].dtype == np.uint8


def test_as_stored_gives_the_stored_dtypes_and_the_same_values(tmp_path):
    """``load(as_stored=True)``: depth and confidence in float16 as stored, each converting to
    exactly the float32 that the default load returns (the conversion is exact), partial loads
    too; a value outside float16's range stays float32."""
    store = ChunkStore(tmp_path)
    pred = _pred()
    pred.depth[0, 0, 0] = 1e6  # the out-of-range array is stored float32
    store.save("chunk", 0, pred)
    store.save("chunk", 1, _pred(seed=1))
    for index, depth_dtype in ((0, np.float32), (1, np.float16)):
        for frames in (None, np.array([0, 2])):
            raw = store.load("chunk", index, frames=frames, fields=(), as_stored=True)
            want = store.load("chunk", index, frames=frames, fields=())
            assert raw.depth.dtype == depth_dtype and raw.conf.dtype == np.float16
            for name in ("depth", "conf", "intrinsic", "extrinsic"):
                np.testing.assert_array_equal(getattr(raw, name).astype(np.float32), getattr(want, name))


def test_depth_error_small_against_mask_threshold(tmp_path):
    """At depths up to 10 (VGGT units) float16 moves depth by <= 0.005, 2.5 % of lambda_D = 0.2."""
    d = np.linspace(0.01, 10.0, S * H * W, dtype=np.float32).reshape(S, H, W)
    pred = _pred()
    pred = ChunkPrediction(d, pred.conf, pred.extrinsic, pred.intrinsic)
    store = ChunkStore(tmp_path)
    store.save("chunk", 0, pred)
    err = np.abs(store.load("chunk", 0).depth - d).max()
    assert 1e-4 < err <= 10.0 * EPS16 <= 0.2 * 0.025


def test_out_of_half_range_and_non_finite_kept_exact(tmp_path):
    pred = _pred()
    conf = pred.conf.copy()
    conf[0, 0, 0] = 1e6  # beyond float16's 65504: the whole array stays float32
    depth = pred.depth.copy()
    depth[1, 2, 3], depth[1, 2, 4] = np.nan, np.inf  # non-finite values survive float16
    pred = ChunkPrediction(depth, conf, pred.extrinsic, pred.intrinsic)
    store = ChunkStore(tmp_path)
    store.save("loop", 0, pred)
    out = store.load("loop", 0)
    np.testing.assert_array_equal(out.conf, conf)
    assert np.isnan(out.depth[1, 2, 3]) and out.depth[1, 2, 4] == np.inf
    assert out.descriptors is None and out.images is None


def test_half_false_is_exact_and_tokens_kept(tmp_path):
    store = ChunkStore(tmp_path, subdir="c", compress=True, half=False)
    pred = _pred(tokens=True, descriptors=False)
    store.save("chunk", 0, pred)
    out = store.load("chunk", 0)
    np.testing.assert_array_equal(out.depth, pred.depth)
    np.testing.assert_array_equal(out.conf, pred.conf)
    np.testing.assert_array_equal(out.patch_tokens, pred.patch_tokens)
    assert out.descriptors is None


def test_exists_remove_indices(tmp_path):
    store = ChunkStore(tmp_path)
    assert not store.exists("chunk", 0) and store.indices("chunk") == []
    for i in (2, 0, 11):
        store.save("chunk", i, _pred(i))
    store.save("loop", 1, _pred())
    (store.root / "notes.txt").write_text("x")
    assert store.indices("chunk") == [0, 2, 11] and store.indices("loop") == [1]
    assert store.exists("chunk", 2)
    store.remove("chunk", 2)
    store.remove("chunk", 2)  # absent: no error
    assert not store.exists("chunk", 2) and store.indices("chunk") == [0, 11]
    with pytest.raises(ValueError, match="kind must be one of"):
        store.path("frame", 0)
    with pytest.raises(ValueError, match="non-negative integer"):
        store.exists("chunk", -1)


def test_overwrite_and_atomic_failure_keeps_old_file(tmp_path, monkeypatch):
    store = ChunkStore(tmp_path)
    store.save("chunk", 0, _pred(0))
    store.save("chunk", 0, _pred(1))  # replace
    np.testing.assert_array_equal(store.load("chunk", 0).images, _pred(1).images)
    before = store.path("chunk", 0).read_bytes()

    def broken_savez(f, **arrays):
        f.write(b"PK\x03\x04 partial")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", broken_savez)
    with pytest.raises(OSError, match="disk full"):
        store.save("chunk", 0, _pred(2))
    assert store.path("chunk", 0).read_bytes() == before
    assert sorted(p.name for p in store.root.iterdir()) == ["chunk_00000.npz"]


def test_errors_name_the_file(tmp_path):
    store = ChunkStore(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"chunk_00007\.npz: no saved chunk 7"):
        store.load("chunk", 7)
    store.path("loop", 0).write_bytes(b"not a zip")
    with pytest.raises(cs.ChunkCorruptError, match=r"loop_00000\.npz: corrupt chunk file: not a \.npz"):
        store.load("loop", 0)
    np.savez(store.path("loop", 1), depth=np.zeros((1, 2, 2)))
    with pytest.raises(cs.ChunkCorruptError, match=r"loop_00001\.npz: corrupt chunk file: no format_version"):
        store.load("loop", 1)
    with pytest.raises(ValueError, match=r"extra\['bad'\]"):
        store.save("chunk", 0, _pred(), extra={"bad": np.array([{}, 1], dtype=object)})
    pred = _pred()
    bad = ChunkPrediction(pred.depth, pred.conf, pred.extrinsic, pred.intrinsic, images=pred.images.astype(np.int16))
    with pytest.raises(ValueError, match="images must be uint8"):
        store.save("chunk", 0, bad)
    assert not store.exists("chunk", 0)


def test_half_if_fits_boundary():
    assert cs.half_if_fits(np.array([65504.0], np.float32)).dtype == np.float16
    assert cs.half_if_fits(np.array([65520.0], np.float32)).dtype == np.float32
    assert cs.half_if_fits(np.array([np.inf, -1.0], np.float32)).dtype == np.float16


@pytest.mark.parametrize("compress", [False, True])
def test_partial_loads_match_full_load(tmp_path, compress):
    """frames/fields read exactly the same values as a full load (memory-mapped when stored
    uncompressed, whole-member fallback when compressed); load_array reads one field."""
    store = ChunkStore(tmp_path, compress=compress)
    pred = _pred(tokens=True)
    store.save("chunk", 0, pred)
    full = store.load("chunk", 0)
    for frames in (np.array([3, 1]), slice(1, 3), np.array([2])):
        part = store.load("chunk", 0, frames=frames)
        for name in ("depth", "conf", "extrinsic", "intrinsic", "descriptors", "patch_tokens", "images"):
            got, want = getattr(part, name), getattr(full, name)[frames]
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)
    lean = store.load("chunk", 0, frames=slice(0, 2), fields=())
    assert lean.descriptors is None and lean.images is None and lean.patch_tokens is None
    np.testing.assert_array_equal(lean.conf, full.conf[:2])
    np.testing.assert_array_equal(store.load_array("chunk", 0, "descriptors"), full.descriptors)
    np.testing.assert_array_equal(store.load_array("chunk", 0, "depth", frames=[2]), full.depth[[2]])
    assert store.load_array("chunk", 0, "depth").dtype == np.float32
    with pytest.raises(ValueError, match="optional fields"):
        store.load("chunk", 0, fields=("depth",))
    with pytest.raises(ValueError, match="field must be one of"):
        store.load_array("chunk", 0, "frames")
    with pytest.raises(IndexError, match=r"chunk_00000\.npz: frames .* out of range for depth"):
        store.load("chunk", 0, frames=[S])


def test_partial_load_reads_and_checks_only_the_selected_frames(tmp_path):
    """A memory-mapped read touches only the selected rows and verifies their CRC32s: a
    corrupted byte of frame 0 is invisible to a read of frames 1-2 (their bytes are intact)
    and named by a read of frame 0, as by a full read (defect 4: partial reads skipped the zip
    CRC and returned the flipped value)."""
    store = ChunkStore(tmp_path, half=False)
    pred = _pred()
    path = store.save("chunk", 0, pred)
    raw = bytearray(path.read_bytes())
    start = bytes(raw).find(pred.depth[0].tobytes())  # frame 0 of depth, stored float32
    assert start > 0
    raw[start : start + 4] = np.float32(-7.0).tobytes()
    path.write_bytes(bytes(raw))
    np.testing.assert_array_equal(store.load("chunk", 0, frames=[1, 2]).depth, pred.depth[1:3])
    with pytest.raises(
        cs.ChunkCorruptError, match=r"chunk_00000\.npz: corrupt chunk file: depth frame 0 fails its CRC32"
    ):
        store.load("chunk", 0, frames=[0])
    for read in (
        lambda: store.load("chunk", 0),
        lambda: store.load_array("chunk", 0, "depth", frames=slice(0, 2)),
        lambda: store.verify("chunk", 0),
    ):
        with pytest.raises(cs.ChunkCorruptError, match=r"chunk_00000\.npz: corrupt chunk file: depth") as info:
            read()
        assert info.value.field == "depth" and info.value.path == path


def _flip(path, offset):
    raw = bytearray(path.read_bytes())
    raw[offset] ^= 0x10
    path.write_bytes(bytes(raw))


@pytest.mark.parametrize("compress", [False, True])
def test_a_flipped_byte_in_any_stored_array_is_named(tmp_path, compress):
    """Every member of a chunk file (prediction fields, extras, the checksums themselves): one
    flipped bit in its data is reported as ChunkCorruptError naming the field, by a full read
    and, for per-frame fields, by a partial read of the damaged frame (uncompressed files) --
    never read back silently, never another exception type."""
    import zipfile

    store = ChunkStore(tmp_path, compress=compress)
    pred = _pred(tokens=True)
    extra = {"frames": np.arange(4), "points_xyz": np.random.default_rng(1).standard_normal((50, 3)).astype(np.float32)}
    path = store.save("chunk", 0, pred, extra=extra)
    clean = path.read_bytes()
    with zipfile.ZipFile(path) as zf:
        members = [(i.filename[:-4], i.header_offset, i.compress_size) for i in zf.infolist()]
    assert {m for m, _, _ in members} >= {
        "depth",
        "conf",
        "extrinsic",
        "intrinsic",
        "descriptors",
        "patch_tokens",
        "images",
        "extra__frames",
        "extra__points_xyz",
        "crc32__depth",
    }
    for name, header, size in members:
        path.write_bytes(clean)
        local = clean[header : header + 30]
        data_start = header + 30 + int.from_bytes(local[26:28], "little") + int.from_bytes(local[28:30], "little")
        # Inside the member's data: its last frame (uncompressed), the middle of the deflate stream.
        _flip(path, data_start + (size // 2 if compress else size - 3))
        field = name[len("crc32__") :] if name.startswith("crc32__") else name
        with pytest.raises(cs.ChunkCorruptError) as info:
            store.verify("chunk", 0)
        assert info.value.path == path and f"{path}: corrupt chunk file" in str(info.value)
        if not compress:  # a compressed member may fail to inflate before its CRC is checked
            assert info.value.field in (field, name), (name, str(info.value))
        if name in ("depth", "conf", "images", "descriptors") and not compress:
            assert info.value.frame == S - 1
            with pytest.raises(cs.ChunkCorruptError, match=f"{name} frame {S - 1}"):
                store.load("chunk", 0, frames=[S - 1])
            part = store.load("chunk", 0, frames=[0, 1])  # intact frames read fine
            np.testing.assert_array_equal(part.extrinsic, pred.extrinsic[:2])
        if name.startswith("extra__"):
            with pytest.raises(cs.ChunkCorruptError, match=name):
                store.load_extra("chunk", 0)
    path.write_bytes(clean)
    store.verify("chunk", 0)


def test_truncated_or_scrambled_container_is_corrupt_not_a_traceback(tmp_path):
    store = ChunkStore(tmp_path)
    path = store.save("chunk", 0, _pred())
    clean = path.read_bytes()
    for damaged in (clean[: len(clean) // 2], clean[:-10], clean[:100] + bytes(50) + clean[150:]):
        path.write_bytes(damaged)
        with pytest.raises(cs.ChunkCorruptError, match=r"chunk_00000\.npz: corrupt chunk file"):
            store.verify("chunk", 0)
        with pytest.raises(cs.ChunkCorruptError):
            store.load("chunk", 0, frames=[0], fields=())


def test_files_without_checksums_are_refused(tmp_path):
    store = ChunkStore(tmp_path)
    np.savez(store.path("chunk", 0), format_version=np.asarray(cs.FORMAT_VERSION), depth=np.zeros((1, 2, 2)))
    with pytest.raises(cs.ChunkCorruptError, match="no checksum"):
        store.load("chunk", 0)


def test_tail_kind_keeps_float32(tmp_path):
    store = ChunkStore(tmp_path)
    pred = _pred(descriptors=False, images=False)
    store.save("tail", 2, pred, half=False)
    out = store.load("tail", 2)
    np.testing.assert_array_equal(out.depth, pred.depth)
    assert store.indices("tail") == [2] and store.indices("chunk") == []


def test_missing_optional_field_is_none(tmp_path):
    store = ChunkStore(tmp_path)
    store.save("chunk", 0, _pred(descriptors=False, images=False))
    assert store.load_array("chunk", 0, "descriptors") is None
    assert store.load("chunk", 0, frames=[0]).images is None


def test_random_byte_flips_are_detected_or_harmless(tmp_path):
    """Anywhere in the file: a flipped byte either raises ChunkCorruptError or leaves every
    array read back bit-identical (e.g. a zip timestamp); never different data, never another
    exception."""
    store = ChunkStore(tmp_path)
    pred = _pred()
    path = store.save("chunk", 0, pred, extra={"frames": np.arange(4)})
    clean = path.read_bytes()
    want = store.load("chunk", 0)
    rng = np.random.default_rng(0)
    detected = 0
    for offset in rng.integers(0, len(clean), 60):
        raw = bytearray(clean)
        raw[offset] ^= 1 << int(rng.integers(8))
        path.write_bytes(bytes(raw))
        try:
            got = store.load("chunk", 0)
            part = store.load("chunk", 0, frames=[1, 3])
            frames = store.load_extra("chunk", 0)["frames"]
        except cs.ChunkCorruptError:
            detected += 1
            continue
        for name in ("depth", "conf", "extrinsic", "intrinsic", "descriptors", "images"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
            np.testing.assert_array_equal(getattr(part, name), getattr(want, name)[[1, 3]])
        np.testing.assert_array_equal(frames, np.arange(4))
    assert detected > 40  # the data dominates the file


def test_disk_full_names_the_file_and_leaves_nothing(tmp_path, monkeypatch):
    """Defect 9: a disk-full error was '[Errno 28]' with no file name."""
    import errno

    from swiftjax.cli.arguments import one_line

    store = ChunkStore(tmp_path)

    def full(f, **arrays):
        f.write(b"PK\x03\x04 partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez", full)
    with pytest.raises(OSError) as err:
        store.save("chunk", 4, _pred())
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(store.path("chunk", 4))
    assert "chunk_00004.npz" in one_line(err.value) and "No space left" in one_line(err.value)
    assert list(store.root.iterdir()) == []


def test_drop_dense_keeps_every_other_array_checked_and_load_says_why(tmp_path):
    """'swiftjax prune' (issue 26 item 8): a chunk file without its depth and confidence maps
    keeps every other array bit for bit (with its CRC32s), is much smaller, and a full load
    raises ChunkMismatchError naming the file (the pipeline predicts the chunk again)."""
    store = ChunkStore(tmp_path)
    pred = _pred()
    path = store.save("chunk", 2, pred, extra={"frames": np.arange(8, 12), "points_xyz": np.ones((5, 3), np.float32)})
    size = path.stat().st_size
    store.drop_dense("chunk", 2)
    assert path.stat().st_size < size - pred.depth.size * 2 * 2 + 1  # two float16 maps gone
    for name in ("extrinsic", "intrinsic", "descriptors", "images"):
        np.testing.assert_array_equal(store.load_array("chunk", 2, name), getattr(pred, name))
    assert store.load_array("chunk", 2, "depth") is None
    extra = store.load_extra("chunk", 2, names=("frames",))
    assert list(extra) == ["frames"] and np.array_equal(extra["frames"], np.arange(8, 12))
    store.verify("chunk", 2)  # every remaining array passes its CRC32
    with pytest.raises(
        cs.ChunkMismatchError,
        match=r"chunk_00002.npz: not this run's chunk file: its depth and "
        r"confidence maps were dropped",
    ):
        store.load("chunk", 2)
    assert isinstance(cs.ChunkMismatchError(path, "x"), cs.ChunkCorruptError)  # re-predicted like a corrupt file


def test_a_file_where_the_store_goes_is_named(tmp_path):
    """Issue 25 item 27: ``chunks`` being a file was 'File exists' without saying what to do."""
    from swiftjax.io.chunk_store import ChunkStore

    (tmp_path / "chunks").write_text("not a folder")
    with pytest.raises(ValueError, match=r"chunks is a file where the run keeps its chunk store .*move it away"):
        ChunkStore(tmp_path)

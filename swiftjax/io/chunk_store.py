"""The pipeline's on-disk store of per-chunk predictions: one ``.npz`` per chunk.

A run keeps every chunk's VGGT output on disk so that memory never holds more than the
chunk being processed, and so that an interrupted run resumes where it stopped.

    store = ChunkStore(run_dir)                     # files in run_dir/chunks/
    store.save("chunk", 3, prediction, extra={"frames": np.arange(90, 165)})
    store.exists("chunk", 3)                        # True
    pred = store.load("chunk", 3)                   # ChunkPrediction, float32 again
    tail = store.load("chunk", 3, frames=slice(45, 75), fields=())  # partial read
    extra = store.load_extra("chunk", 3)            # {"frames": ...}

File ``<kind>_<index:05d>.npz`` (kind ``"chunk"``, ``"loop"`` or ``"tail"``: a chunk's
last overlap frames in float32, kept until the next temporal edge is recorded), written
atomically, read without pickles.  Storage dtypes:

==============  =========  =====================================================
field           stored     why
==============  =========  =====================================================
depth, conf     float16    relative rounding error <= 2^-11 = 4.9e-4 (see below);
                           float32 if a value exceeds float16's range (65504)
extrinsic,      float32    poses / intrinsics / descriptors keep VGGT's precision
intrinsic,
descriptors,
patch_tokens
images          uint8      as given
extra           as given   any numeric arrays / scalars (no objects)
==============  =========  =====================================================

Partial reads: members are stored uncompressed by default, so :meth:`ChunkStore.load` with
``frames`` memory-maps each array inside the ``.npz`` (the zip member's data offset plus the
``.npy`` header) and reads only those frames' bytes, and ``fields`` skips the other members
altogether (the pipeline's loop chunks read 20 of 75 frames and no optional field).
Compressed files fall back to reading the whole member.

Checksums: every stored array carries CRC32s (zlib) recorded when it is written -- one per
frame for the per-frame prediction fields (``depth``, ``conf``, ``extrinsic``, ``intrinsic``,
``descriptors``, ``patch_tokens``, ``images``), one per array otherwise (``extra``) -- in a
member ``crc32__<name>``, and verified on every read, partial reads included (a memory-mapped
read of some frames checks exactly those frames' bytes).  A mismatch, or any unreadable
member, raises :class:`ChunkCorruptError` naming the file, the field and the frame, so that
the pipeline can report it and predict the chunk again.  The checksums cost a fraction of
the write itself (``bench/bench_io.py``, docs/performance/io.md).

float16 halves the biggest arrays (docs/performance/io.md).  Rounding moves a depth ``d`` by at most
``4.9e-4 d``: at VGGT-scale depths (``d`` of order 1-10) that is <= 0.005, <= 2.5 % of the
reliability mask's absolute threshold ``lambda_D = 0.2``, so only pairs already within
``~5e-4 d`` of the threshold can change side.  ``ChunkStore(..., half=False)`` keeps float32.
"""

from __future__ import annotations

import os
import pathlib
import re
import struct
import zipfile
import zlib
from typing import Any

import numpy as np

from swiftjax import _faults
from swiftjax.errors import SwiftjaxError
from swiftjax.io.atomic import atomic_write
from swiftjax.prediction import ChunkPrediction

__all__ = ["ChunkStore", "ChunkCorruptError", "ChunkMismatchError", "KINDS", "half_if_fits"]

PathLike = str | os.PathLike[str]

KINDS = ("chunk", "loop", "tail")
FORMAT_VERSION = 2  # 2: CRC32 per frame / per array
_F16_MAX = float(np.finfo(np.float16).max)  # 65504
_EXTRA = "extra__"
_CRC = "crc32__"
_HALF_FIELDS = ("depth", "conf")
_FLOAT32_FIELDS = ("extrinsic", "intrinsic", "descriptors", "patch_tokens")
_PER_FRAME = _HALF_FIELDS + _FLOAT32_FIELDS + ("images",)
_NAME = re.compile(r"^(chunk|loop|tail)_(\d{5,})\.npz$")
# What reading a damaged file can raise is open-ended (zipfile alone raises BadZipFile,
# NotImplementedError, RuntimeError, zlib.error, EOFError; the .npy header is parsed by
# ast.literal_eval): any failure while reading our own file's bytes means it is corrupt.
_READ_ERRORS = (Exception,)


class ChunkCorruptError(SwiftjaxError, ValueError):
    """A chunk file whose bytes are not those written: unreadable, or a CRC32 mismatch.

    Attributes:
        path: the file.
        field: the array (``"depth"``, ``"extra__points_xyz"``, ...) or ``None`` (the container).
        frame: the frame whose bytes differ (per-frame fields), else ``None``.
    """

    def __init__(self, path: pathlib.Path, field: str | None, frame: int | None, why: str) -> None:
        self.path, self.field, self.frame = path, field, frame
        where = "" if field is None else f" {field}" + ("" if frame is None else f" frame {frame}")
        super().__init__(f"{path}: corrupt chunk file:{where} {why}".replace(":  ", ": "))


class ChunkMismatchError(ChunkCorruptError):
    """A sound chunk file that is not the chunk the run expects (another chunk's, another
    run's, the wrong frame count): :func:`swiftjax.pipeline.rundir.check_binding`.  A
    :class:`ChunkCorruptError`, so the pipeline reports it and predicts the chunk again."""

    def __init__(self, path: pathlib.Path, why: str) -> None:
        self.path, self.field, self.frame = path, None, None
        ValueError.__init__(self, f"{path}: not this run's chunk file: {why}")


def _crc_rows(a: np.ndarray) -> np.ndarray:
    """CRC32 of each row ``a[k]`` (C order bytes): ``[len(a)]`` uint32 (one for a 0-d array)."""
    a = np.require(a, requirements="C")
    if a.ndim == 0:
        return np.asarray([zlib.crc32(a.tobytes())], np.uint32)
    return np.fromiter((zlib.crc32(memoryview(r).cast("B")) if r.size else 0 for r in a), np.uint32, len(a))


def _crc_whole(a: np.ndarray) -> np.ndarray:
    a = np.require(a, requirements="C")
    return np.asarray([zlib.crc32(memoryview(a).cast("B")) if a.size else 0], np.uint32)


def half_if_fits(x: np.ndarray) -> np.ndarray:
    """float16 when every finite value fits float16's range, else float32 (no overflow to inf).

    A float16 input is returned as is (e.g. converted by the caller on the device).
    """
    x = np.asarray(x)
    if x.dtype == np.float16:
        return x
    with np.errstate(over="ignore"):  # overflow is detected below
        half = x.astype(np.float16)
    if np.count_nonzero(np.isinf(half)) != np.count_nonzero(np.isinf(x)):  # a finite value overflowed
        return x.astype(np.float32, copy=False)
    return half


class ChunkStore:
    """Per-chunk prediction files under ``run_dir / subdir``.

    Args:
        run_dir: the run's output folder (created if missing).
        subdir: folder inside ``run_dir`` for the chunk files.
        compress: zlib-compress the ``.npz`` files (somewhat smaller, much slower to write,
            and partial reads then read whole members; off by default).
        half: store depth and confidence as float16 (default); ``False`` keeps float32 exactly.
    """

    def __init__(self, run_dir: PathLike, subdir: str = "chunks", compress: bool = False, half: bool = True) -> None:
        self.root = pathlib.Path(run_dir) / subdir
        if self.root.exists() and not self.root.is_dir():
            raise ValueError(f"{self.root} is a file where the run keeps its chunk store (a folder): move it away")
        self.root.mkdir(parents=True, exist_ok=True)
        self.compress = compress
        self.half = half

    def path(self, kind: str, index: int) -> pathlib.Path:
        """The file of ``(kind, index)``: ``<root>/<kind>_<index:05d>.npz``."""
        if kind not in KINDS:
            raise ValueError(f"chunk store kind must be one of {KINDS}, got {kind!r}")
        if int(index) != index or index < 0:
            raise ValueError(f"chunk store index must be a non-negative integer, got {index!r}")
        return self.root / f"{kind}_{int(index):05d}.npz"

    def save(
        self,
        kind: str,
        index: int,
        prediction: ChunkPrediction,
        extra: dict[str, Any] | None = None,
        half: bool | None = None,
    ) -> pathlib.Path:
        """Write one chunk atomically (replacing any previous file); returns its path.

        ``extra`` holds numeric arrays / scalars saved beside the prediction (e.g. the
        chunk's frame indices), returned by :meth:`load_extra`.  ``half`` overrides the
        store's float16 setting for this file.  Every array gets its CRC32s (module docstring).
        """
        path = self.path(kind, index)
        half = self.half if half is None else half
        arrays: dict[str, np.ndarray] = {"format_version": np.asarray(FORMAT_VERSION)}
        for name in _HALF_FIELDS:
            value = getattr(prediction, name)
            arrays[name] = half_if_fits(value) if half else np.asarray(value, dtype=np.float32)
        for name in _FLOAT32_FIELDS:
            value = getattr(prediction, name)
            if value is not None:
                arrays[name] = np.asarray(value, dtype=np.float32)
        if prediction.images is not None:
            images = np.asarray(prediction.images)
            if images.dtype != np.uint8:
                raise ValueError(f"{path}: ChunkPrediction.images must be uint8, got {images.dtype}")
            arrays["images"] = images
        for key, value in (extra or {}).items():
            value = np.asarray(value)
            if value.dtype.hasobject:
                raise ValueError(f"{path}: extra[{key!r}] is not a numeric/string array (dtype {value.dtype})")
            arrays[_EXTRA + key] = value
        return self._write(path, arrays, index if kind == "chunk" else None)

    def _write(self, path: pathlib.Path, arrays: dict[str, np.ndarray], fault_index: int | None) -> pathlib.Path:
        """``arrays`` with their member list and CRC32s, written atomically to ``path``."""
        arrays = {k: v for k, v in arrays.items() if k != "members" and not k.startswith(_CRC)}
        # The member list, so that a damaged name in the zip directory cannot hide a member.
        arrays["members"] = np.asarray(sorted(arrays), dtype=np.str_)
        arrays = {k: np.require(v, requirements="C") for k, v in arrays.items()}
        for name in list(arrays):
            arrays[_CRC + name] = _crc_rows(arrays[name]) if name in _PER_FRAME else _crc_whole(arrays[name])
        save = np.savez_compressed if self.compress else np.savez
        with atomic_write(path, "wb") as f:
            save(f, **arrays)
            f.flush()
            _faults.point("chunk-write", fault_index)
        return path

    def drop_dense(self, kind: str, index: int) -> None:
        """Rewrite ``(kind, index)`` without its dense maps (``depth``, ``conf``: most of its
        bytes), every other array kept and checked; the file then records ``dropped``, and
        :meth:`load` raises :class:`ChunkMismatchError` (the pipeline predicts the chunk again
        when it needs the maps)."""
        path, data = self._open(kind, index)
        with data:
            arrays = {
                n: _read_member(path, data, n, None)
                for n in data.files
                if not n.startswith(_CRC) and n not in ("members", *_HALF_FIELDS)
            }
        arrays["dropped"] = np.asarray(sorted(_HALF_FIELDS), dtype=np.str_)
        self._write(path, arrays, None)

    def _open(self, kind: str, index: int) -> tuple[pathlib.Path, Any]:
        path = self.path(kind, index)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no saved {kind} {index} in the chunk store {self.root}")
        try:
            with open(path, "rb") as f:
                magic = f.read(4)
            if magic != b"PK\x03\x04":
                raise ChunkCorruptError(path, None, None, f"not a .npz (zip) archive (starts with {magic!r})")
            data = np.load(path, allow_pickle=False)
        except ChunkCorruptError:
            raise
        except _READ_ERRORS as e:
            raise ChunkCorruptError(path, None, None, f"unreadable ({type(e).__name__}: {e})".splitlines()[0]) from None
        try:
            version = int(_read_member(path, data, "format_version", None)) if "format_version" in data.files else None
        except ChunkCorruptError:
            data.close()
            raise
        if version is None:
            data.close()
            raise ChunkCorruptError(path, None, None, "no format_version member (damaged, or not a chunk file)")
        if version != FORMAT_VERSION:
            data.close()
            raise ValueError(f"{path}: chunk file format {version}, this swiftjax reads format {FORMAT_VERSION}")
        try:
            listed = set(_read_member(path, data, "members", None).tolist()) if "members" in data.files else None
        except ChunkCorruptError:
            data.close()
            raise
        present = {n for n in data.files if not n.startswith(_CRC)} - {"members"}
        if listed != present:
            data.close()
            missing = sorted((listed or set()) - present)
            unexpected = sorted(present - (listed or set()))
            raise ChunkCorruptError(
                path, None, None, f"damaged member list (missing {missing or 'the list'}, unexpected {unexpected})"
            )
        return path, data

    def load(
        self,
        kind: str,
        index: int,
        frames: Any = None,
        fields: tuple[str, ...] | None = None,
        *,
        as_stored: bool = False,
    ) -> ChunkPrediction:
        """The saved prediction, every float field as float32 (images uint8).

        Args:
            frames: optional slice or integer index array into the chunk's frames: only
                those frames of every per-frame field are read (memory-mapped, see the module
                docstring).  ``None`` reads all frames.
            fields: which optional fields (``descriptors``, ``patch_tokens``, ``images``) to
                read; the others are returned as ``None``.  ``None`` reads every field.
                ``depth, conf, extrinsic, intrinsic`` are always read.
            as_stored: float fields in the dtype they are stored in (float16 for the half
                fields) instead of float32: for a caller that converts them into a buffer of its
                own (a fresh float32 copy of every field costs its page faults each time).
        """
        names = _HALF_FIELDS + _FLOAT32_FIELDS + ("images",)
        optional = ("descriptors", "patch_tokens", "images")
        chosen = optional if fields is None else tuple(fields)
        unknown = sorted(set(chosen) - set(optional))
        if unknown:
            raise ValueError(f"chunk store optional fields are {optional}, got {unknown}")
        wanted = set(chosen) | {"depth", "conf", "extrinsic", "intrinsic"}
        path, data = self._open(kind, index)
        with data:
            dropped = "dropped" in data.files
            out: dict[str, Any] = {}
            for name in names:
                if name not in wanted or name not in data.files:
                    out[name] = None
                    continue
                value = _read_member(path, data, name, frames)
                out[name] = value if name == "images" or as_stored else value.astype(np.float32)
        if out["depth"] is None and dropped:
            raise ChunkMismatchError(path, "its depth and confidence maps were dropped ('swiftjax prune')")
        if out["depth"] is None or out["extrinsic"] is None:
            raise ValueError(f"{path}: chunk file lacks depth or extrinsic arrays")
        return ChunkPrediction(**out)

    def load_array(self, kind: str, index: int, name: str, frames: Any = None) -> np.ndarray | None:
        """One prediction field (``depth``, ``conf``, ``extrinsic``, ``intrinsic``,
        ``descriptors``, ``patch_tokens`` or ``images``), float32 (images uint8), rows
        ``frames`` only if given; ``None`` if the chunk was saved without it.  Reads nothing
        else from the file."""
        names = _HALF_FIELDS + _FLOAT32_FIELDS + ("images",)
        if name not in names:
            raise ValueError(f"chunk store field must be one of {names}, got {name!r}")
        path, data = self._open(kind, index)
        with data:
            if name not in data.files:
                return None
            value = _read_member(path, data, name, frames)
        return value if name == "images" else value.astype(np.float32)

    def load_extra(self, kind: str, index: int, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
        """The ``extra`` arrays saved with the chunk (as saved); only ``names`` (those
        present) when given."""
        path, data = self._open(kind, index)
        with data:
            return {
                k[len(_EXTRA) :]: _read_member(path, data, k, None)
                for k in data.files
                if k.startswith(_EXTRA) and (names is None or k[len(_EXTRA) :] in names)
            }

    def verify(self, kind: str, index: int) -> None:
        """Read every array of ``(kind, index)`` and check its CRC32s; :class:`ChunkCorruptError` if one fails."""
        path, data = self._open(kind, index)
        with data:
            for name in data.files:
                if not name.startswith(_CRC):
                    _read_member(path, data, name, None)

    def exists(self, kind: str, index: int) -> bool:
        """Whether ``(kind, index)`` has been saved (a complete file: writes are atomic)."""
        return self.path(kind, index).is_file()

    def remove(self, kind: str, index: int) -> None:
        """Delete ``(kind, index)`` if present."""
        self.path(kind, index).unlink(missing_ok=True)

    @staticmethod
    def parse_name(name: str) -> tuple[str, int] | None:
        """``"chunk_00003.npz" -> ("chunk", 3)``; None for any other name."""
        m = _NAME.match(name)
        return (m.group(1), int(m.group(2))) if m else None

    def indices(self, kind: str) -> list[int]:
        """Sorted indices saved for ``kind``."""
        if kind not in KINDS:
            raise ValueError(f"chunk store kind must be one of {KINDS}, got {kind!r}")
        out = []
        for p in self.root.iterdir():
            m = _NAME.match(p.name)
            if m and m.group(1) == kind:
                out.append(int(m.group(2)))
        return sorted(out)


def _read_member(path: pathlib.Path, data: Any, name: str, frames: Any) -> np.ndarray:
    """Array ``name`` of an open ``.npz`` (``np.load`` result), rows ``frames`` only if given,
    its CRC32s verified (:class:`ChunkCorruptError` naming the field and frame on a mismatch).

    An uncompressed per-frame member is memory-mapped in place and only the selected rows
    (all without ``frames``) are copied out and checked; otherwise the member is read whole
    (and sliced).
    """
    if _CRC + name not in data.files:
        raise ChunkCorruptError(path, name, None, "has no checksum (the file was not written by this store)")
    try:
        crc = np.asarray(data[_CRC + name])
        if frames is None:
            # Uncompressed: copied out of a memory map (only our CRC32 pass; np.load's zip
            # reader would compute the zip CRC too and could not name the frame).
            view = _member_memmap(path, data.zip, name + ".npy")
            value, rows, length = (data[name] if view is None else np.array(view)), None, None
            del view
        else:
            view = _member_memmap(path, data.zip, name + ".npy")
            whole = data[name] if view is None else view  # compressed member: read it whole
            length = len(whole)
            try:
                picked = np.arange(length)[frames]
            except IndexError as e:
                raise IndexError(
                    f"{path}: frames {frames!r} out of range for {name} of shape {whole.shape} ({e})"
                ) from None
            rows = np.atleast_1d(picked)
            value = np.array(whole[rows])
            del view, whole
    except IndexError:
        raise
    except _READ_ERRORS as e:
        raise ChunkCorruptError(path, name, None, f"unreadable ({type(e).__name__}: {e})".splitlines()[0]) from None
    if name not in _PER_FRAME:  # one CRC for the array
        if crc.shape != (1,) or _crc_whole(value)[0] != crc[0]:
            raise ChunkCorruptError(path, name, None, "fails its CRC32 check")
        return value
    total = len(value) if rows is None else length
    if crc.shape != (total,):
        raise ChunkCorruptError(path, name, None, f"has {crc.size} checksums for {total} frames")
    got = _crc_rows(value)
    want = crc if rows is None else crc[rows]
    bad = np.flatnonzero(got != want)
    if bad.size:
        k = int(bad[0]) if rows is None else int(rows[bad[0]])
        raise ChunkCorruptError(
            path, name, k, f"fails its CRC32 check (stored {int(want[bad[0]]):08x}, read {int(got[bad[0]]):08x})"
        )
    return value if rows is None or np.ndim(picked) else value[0]


def _member_memmap(path: pathlib.Path, zf: zipfile.ZipFile, member: str) -> np.memmap | None:
    """A read-only memory map of the ``.npy`` member ``member`` of the zip ``zf`` at ``path``.

    ``None`` when the member is compressed.  The data start is the local file header's
    offset + 30 + its name and extra-field lengths (APPNOTE 4.3.7), then the ``.npy`` header.
    """
    info = zf.getinfo(member)
    if info.compress_type != zipfile.ZIP_STORED:
        return None
    with open(path, "rb") as f:
        f.seek(info.header_offset)
        local = f.read(30)
        if len(local) != 30 or local[:4] != b"PK\x03\x04":
            raise ValueError(f"bad zip local header for {member}")
        name_len, extra_len = struct.unpack("<HH", local[26:30])
        f.seek(info.header_offset + 30 + name_len + extra_len)
        major, _ = np.lib.format.read_magic(f)
        read_header = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(f)
        offset = f.tell()
    if dtype.hasobject:
        raise ValueError(f"{member} holds Python objects")
    if int(np.prod(shape)) == 0 or len(shape) == 0:
        return None
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape, order="F" if fortran else "C")

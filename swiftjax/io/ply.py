"""Point clouds as PLY: a binary little-endian writer (one shot or streamed), a reader, and
voxel downsampling.

The pipeline's ``points.ply`` holds one ``vertex`` element with the properties

    x y z : float32   world coordinates
    red green blue : uint8   colour (optional)
    confidence : float32   VGGT depth confidence (optional)

packed with no padding (19 bytes a point with both optional parts).  Every write goes
through a NumPy structured array and one ``write`` call per batch: there is no Python loop
over points.  Files are written atomically (:mod:`swiftjax.io.atomic`).

**Streaming** (:class:`PlyStreamWriter`): the vertex count must appear in the header, which
precedes the body, but the pipeline only knows it after the last chunk.  We reserve the
header's size up front: the header is written with a padding comment line sized for a
20-digit count, the body is appended chunk by chunk, and on close we seek to 0 and rewrite
the header with the true count, shrinking the padding comment so the header keeps exactly
its reserved length.  The ``element vertex N`` line itself stays canonical (no leading
zeros, no trailing spaces), so strict readers parse it; a comment line is ignored by every
reader.  This is one pass over the data and never copies the body, unlike writing the body
to a second temp file and concatenating (which doubles the I/O of a multi-GB cloud).
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Sequence
from typing import IO, Any, NamedTuple

import numpy as np

from swiftjax.errors import SwiftjaxError
from swiftjax.io.atomic import atomic_write

__all__ = [
    "PlyError",
    "PlyPoints",
    "PlyStreamWriter",
    "ply_dtype",
    "read_ply",
    "voxel_downsample",
    "write_ply",
]

PathLike = str | os.PathLike[str]


class PlyError(SwiftjaxError, ValueError):
    """A file that is not a PLY point cloud this reader takes; the message names the file."""


_COUNT_WIDTH = 20  # digits reserved for the streamed vertex count (uint64 max has 20)

# PLY type names (both spellings in the spec) -> NumPy base type (no byte order).
_PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip
_COLOUR_NAMES = (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue"))


class PlyPoints(NamedTuple):
    """A point cloud: ``points [N,3]`` float32, ``colors [N,3]`` uint8 or None, ``conf [N]``
    float32 or None."""

    points: np.ndarray
    colors: np.ndarray | None = None
    conf: np.ndarray | None = None


def ply_dtype(colors: bool = True, conf: bool = True) -> np.dtype:
    """The packed little-endian structured dtype of one vertex (12, 15, 16 or 19 bytes)."""
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if conf:
        fields += [("confidence", "<f4")]
    return np.dtype(fields)


def _header(count: int, dtype: np.dtype, pad_to: int | None = None, comments: Sequence[str] = ()) -> bytes:
    """The PLY header for ``count`` vertices of ``dtype`` with ``comments`` (one line each)
    after ``comment written by swiftjax``; padded to ``pad_to`` bytes when given (streaming)
    by trailing spaces on that first comment line, so no comment line is blank."""
    names = {"<f4": "float", "|u1": "uchar", "u1": "uchar"}
    props = "".join(f"property {names[dtype[n].str]} {n}\n" for n in dtype.names)
    first = "comment written by swiftjax"
    rest = "".join(f"comment {' '.join(str(c).split())}\n" for c in comments)
    tail = f"element vertex {count}\n{props}end_header\n"
    head = "ply\nformat binary_little_endian 1.0\n"
    if pad_to is None:
        return (head + first + "\n" + rest + tail).encode("ascii")
    fill = pad_to - len(head) - len(first) - 1 - len(rest) - len(tail)
    if fill < 0:
        raise ValueError(f"PLY vertex count {count} does not fit the reserved header")
    return (head + first + " " * fill + "\n" + rest + tail).encode("ascii")


def _check_columns(
    points: np.ndarray, colors: np.ndarray | None, conf: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"PLY points must have shape [N, 3], got {points.shape}")
    n = points.shape[0]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != (n, 3):
            raise ValueError(f"PLY colors must have shape [{n}, 3] like the points, got {colors.shape}")
        if colors.dtype != np.uint8:
            raise ValueError(f"PLY colors must be uint8 (0..255), got dtype {colors.dtype}")
    if conf is not None:
        conf = np.asarray(conf)
        if conf.shape != (n,):
            raise ValueError(f"PLY conf must have shape [{n}] like the points, got {conf.shape}")
    return points, colors, conf


def _pack(points: np.ndarray, colors: np.ndarray | None, conf: np.ndarray | None, dtype: np.dtype) -> np.ndarray:
    """Fill the structured vertex array column by column (vectorised)."""
    rec = np.empty(points.shape[0], dtype=dtype)
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    if colors is not None:
        rec["red"], rec["green"], rec["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    if conf is not None:
        rec["confidence"] = conf
    return rec


def write_ply(
    path: PathLike,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    conf: np.ndarray | None = None,
    comments: Sequence[str] = (),
) -> None:
    """Write a binary little-endian PLY atomically.

    Args:
        path: output file.
        points: ``[N, 3]`` coordinates (stored as float32).
        colors: ``[N, 3]`` uint8 RGB, or None to omit the colour properties.
        conf: ``[N]`` confidence (stored as float32), or None to omit it.
        comments: header comment lines (ASCII; e.g. the unit and frame of the coordinates).
    """
    points, colors, conf = _check_columns(points, colors, conf)
    dtype = ply_dtype(colors is not None, conf is not None)
    rec = _pack(points, colors, conf, dtype)
    with atomic_write(path, "wb") as f:
        f.write(_header(len(rec), dtype, comments=comments))
        f.write(rec.data)


class PlyStreamWriter:
    """Append a point cloud batch by batch; the file appears (atomically) on :meth:`close`.

    Holds only the batch being written.  Use as a context manager; an exception inside the
    block discards the partial file and leaves any existing ``path`` untouched::

        with PlyStreamWriter("points.ply", colors=True, conf=True) as ply:
            for chunk in chunks:
                ply.append(xyz, rgb, conf)
        ply.count  # vertices written

    Args:
        path: output file.
        colors, conf: whether the vertices carry colour / confidence; every :meth:`append`
            must then pass them.
        comments: header comment lines (ASCII; e.g. the unit and frame of the coordinates).
    """

    def __init__(self, path: PathLike, colors: bool = True, conf: bool = True, comments: Sequence[str] = ()) -> None:
        self.path = pathlib.Path(path)
        self.dtype = ply_dtype(colors, conf)
        self.count = 0
        self.comments = tuple(comments)
        self._header_size = len(_header(0, self.dtype, comments=self.comments)) + _COUNT_WIDTH
        self._ctx: Any = None
        self._file: IO[bytes] | None = None

    def __enter__(self) -> PlyStreamWriter:
        self._ctx = atomic_write(self.path, "wb")
        self._file = self._ctx.__enter__()
        self._file.write(_header(0, self.dtype, pad_to=self._header_size, comments=self.comments))
        return self

    def append(self, points: np.ndarray, colors: np.ndarray | None = None, conf: np.ndarray | None = None) -> None:
        """Append ``points [n,3]`` with ``colors [n,3]`` uint8 and ``conf [n]`` as configured."""
        if self._file is None:
            raise RuntimeError(f"PlyStreamWriter for {self.path} is not open (use it in a with block)")
        points, colors, conf = _check_columns(points, colors, conf)
        for name, given in (("red", colors), ("confidence", conf)):
            wanted = name in self.dtype.names
            if wanted != (given is not None):
                what = "colors" if name == "red" else "conf"
                raise ValueError(
                    f"PlyStreamWriter for {self.path} was opened with {what}={wanted} but append got "
                    f"{what}={'an array' if given is not None else 'None'}"
                )
        rec = _pack(points, colors, conf, self.dtype)
        self._file.write(rec.data)
        self.count += len(rec)

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> bool | None:
        f, ctx = self._file, self._ctx
        self._file = self._ctx = None
        if exc_type is None:
            try:
                f.seek(0)
                f.write(_header(self.count, self.dtype, pad_to=self._header_size, comments=self.comments))
            except BaseException as e:
                ctx.__exit__(type(e), e, e.__traceback__)  # removes the temp file
                raise
        return ctx.__exit__(exc_type, exc, tb)


_Property = tuple[str, str | None, str]  # (name, list count type or None, type)
_Element = tuple[str, int, list[_Property]]  # (name, count, properties)


def _parse_header(f: IO[bytes], path: PathLike) -> tuple[str, list[_Element], int]:
    """Parse a PLY header: returns (format, elements, header byte length)."""
    magic = f.readline()
    if magic.rstrip(b"\r\n") != b"ply":
        raise PlyError(f"{path} is not a PLY file (first line is {magic[:20]!r}, expected 'ply')")
    fmt = None
    elements: list[_Element] = []
    while True:
        raw = f.readline()
        if not raw:
            raise PlyError(f"{path}: PLY header has no 'end_header' line")
        words = raw.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyError(f"{path}: PLY property before any element: {raw!r}")
            if words[1] == "list":
                elements[-1][2].append((words[4], words[2], words[3]))
            else:
                elements[-1][2].append((words[2], None, words[1]))
        else:
            raise PlyError(f"{path}: unknown PLY header line {raw!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PlyError(f"{path}: unsupported PLY format {fmt!r}")
    for _, _, props in elements:
        for name, lt, t in props:
            for typ in (t, lt) if lt else (t,):
                if typ not in _PLY_TYPES:
                    raise PlyError(f"{path}: unknown PLY property type {typ!r} for {name!r}")
    return fmt, elements, f.tell()


def read_ply(path: PathLike) -> PlyPoints:
    """Read the ``vertex`` element of a PLY file (binary little/big endian or ascii).

    Returns :class:`PlyPoints`: ``x y z`` as float32 ``[N,3]``; ``red green blue`` (also
    ``r g b`` / ``diffuse_*``) as uint8 ``[N,3]`` if present; ``confidence`` as float32 ``[N]``
    if present.  Other vertex properties are ignored, and so are elements after the vertices;
    elements before them are skipped (binary: only if they have no list properties).
    """
    path = pathlib.Path(path)
    with open(path, "rb") as f:
        fmt, elements, offset = _parse_header(f, path)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise PlyError(f"{path}: PLY file has no 'vertex' element (elements: {names})")
    vi = names.index("vertex")
    _, count, props = elements[vi]
    if any(lt is not None for _, lt, _ in props):
        raise PlyError(f"{path}: PLY vertex element has a list property; only scalar properties are supported")
    prop_names = [p[0] for p in props]
    for axis in "xyz":
        if axis not in prop_names:
            raise PlyError(f"{path}: PLY vertex element has no {axis!r} property (has {prop_names})")

    if fmt == "ascii":
        with open(path, "rb") as f:
            f.seek(offset)
            for _, n, _ in elements[:vi]:
                for _ in range(n):  # preceding elements: one line per item
                    f.readline()
            table = np.loadtxt(f, dtype=np.float64, max_rows=count, ndmin=2) if count else np.zeros((0, len(props)))
        if table.shape != (count, len(props)):
            raise PlyError(f"{path}: PLY ascii vertex data has shape {table.shape}, header says {(count, len(props))}")
        cols = {name: table[:, i] for i, name in enumerate(prop_names)}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        for name, n, pre in elements[:vi]:
            if any(lt is not None for _, lt, _ in pre):
                raise PlyError(f"{path}: PLY element {name!r} with list properties precedes 'vertex'")
            offset += n * np.dtype([(p, order + _PLY_TYPES[t]) for p, _, t in pre]).itemsize
        dtype = np.dtype([(p, order + _PLY_TYPES[t]) for p, _, t in props])
        available = os.path.getsize(path) - offset
        if available < count * dtype.itemsize:
            raise PlyError(
                f"{path}: PLY file is truncated: header says {count} vertices of {dtype.itemsize} bytes "
                f"({count * dtype.itemsize} bytes) but only {max(available, 0)} bytes follow the header"
            )
        rec = np.fromfile(path, dtype=dtype, count=count, offset=offset)
        cols = {name: rec[name] for name in prop_names}

    def gather(names: Sequence[str], dtype: type) -> np.ndarray:
        out = np.empty((count, len(names)), dtype)
        for j, name in enumerate(names):  # one strided copy per property, not per point
            out[:, j] = cols[name]
        return out

    points = gather("xyz", np.float32)
    colors = next((gather(rgb, np.uint8) for rgb in _COLOUR_NAMES if all(c in cols for c in rgb)), None)
    conf = cols["confidence"].astype(np.float32) if "confidence" in cols else None
    return PlyPoints(points, colors, conf)


def voxel_downsample(points: np.ndarray, colors: np.ndarray | None, conf: np.ndarray | None, voxel: float) -> PlyPoints:
    """Keep one point per occupied voxel of edge ``voxel``: the one with the highest confidence.

    Keeping a real point (rather than the voxel centroid) keeps measured positions and
    unblended colours, and its confidence stays meaningful.  Ties and ``conf=None`` keep the
    earliest point.  Non-finite points are dropped.  Kept points stay in their input order.

    Args:
        points: ``[N, 3]``; colors: ``[N, 3]`` uint8 or None; conf: ``[N]`` or None.
        voxel: voxel edge length (> 0), in the points' units; voxels are aligned to the
            origin (``floor(p / voxel)``).

    Returns:
        :class:`PlyPoints` of the kept points (``M <= N``), dtypes as given.

    One ``np.unique`` (a sort, O(N log N)) over a packed int64 voxel key; no Python loop.
    """
    points, colors, conf = _check_columns(points, colors, conf)
    if not (np.isfinite(voxel) and voxel > 0):
        raise ValueError(f"voxel size must be a positive finite number, got {voxel}")
    idx = np.flatnonzero(np.isfinite(points).all(axis=1))
    cells = np.floor(points[idx] / voxel).astype(np.int64)
    if len(idx):
        cells -= cells.min(axis=0)
        ext = cells.max(axis=0) + 1
        if float(ext[0]) * float(ext[1]) * float(ext[2]) < 2.0**62:
            key = (cells[:, 0] * ext[1] + cells[:, 1]) * ext[2] + cells[:, 2]
        else:  # huge extent in voxels: fall back to exact row keys
            key = np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1)
    else:
        key = np.zeros(0, np.int64)
    if conf is not None:
        order = np.argsort(-np.asarray(conf, np.float64)[idx], kind="stable")  # best first
        _, first = np.unique(key[order], return_index=True)  # stable: first = best
        keep = np.sort(idx[order[first]])
    else:
        _, first = np.unique(key, return_index=True)
        keep = idx[np.sort(first)]
    return PlyPoints(points[keep], None if colors is None else colors[keep], None if conf is None else conf[keep])

"""Frames in: an image folder, a glob pattern, or a video file, as uint8 RGB arrays.

    source = list_frames("data/kitti/00/image_2")      # or "frames/*.png", or "drive.mp4"
    source = validate(source, skip_bad=False)          # one-line InputError on bad input
    rgb = source.read(0)                               # [H, W, 3] uint8 RGB
    batch = source.read_many(range(0, 75))             # [75, H, W, 3]

* Folder: files with extension jpg/jpeg/png/bmp/tif/tiff/webp (any case), not recursive,
  hidden files (``.name``, e.g. macOS ``._x.jpg``) skipped, in natural order (``2.png``
  before ``10.png``).
* Glob (the input contains ``*``, ``?`` or ``[``; ``**`` recurses): the matching files with
  those extensions, natural order; names are paths relative to the pattern's fixed prefix.
* Video (any other existing file): decoded with OpenCV, every ``stride``-th frame; frame
  ``k`` of the video is named ``<stem>_<k:06d>.png``.

Pixels follow VGGT's loader (PIL, no EXIF rotation: a frame's EXIF orientation is ignored,
with a warning): grayscale -> RGB, alpha composited on white (PIL's integer arithmetic),
16-bit -> 8-bit (high byte), float images taken as [0, 1].  Decoding uses OpenCV
(``opencv-python-headless``, imported lazily); :func:`validate` reads the image headers
(Pillow, a matplotlib dependency) and, for PNG and JPEG, the file's last bytes (the end
marker), then decodes every image as the run will, on a thread pool, taking a decoder's
warning (libjpeg's "Corrupt JPEG data") as damage: a damaged frame is refused, or skipped
with ``skip_bad``, before the run (``decode=False``: headers only; docs/performance/io.md).
"""

from __future__ import annotations

import contextlib
import glob as globlib
import logging
import os
import pathlib
import re
import sys
import tempfile
import threading
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from swiftjax.errors import SwiftjaxError

__all__ = [
    "IMAGE_EXTENSIONS",
    "FrameSource",
    "ImageFiles",
    "InputError",
    "VideoFrames",
    "list_frames",
    "natural_key",
    "read_timestamps",
    "to_rgb8",
    "validate",
]

logger = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]

IMAGE_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"})
_GLOB_CHARS = re.compile(r"[*?\[]")
_SEEK_FORWARD_MAX = 64  # video: grab up to this many frames forward instead of seeking


class InputError(SwiftjaxError, ValueError):
    """The user's input (frames, files) is unusable; the message is one line naming the file."""


def _cv2() -> Any:
    try:
        import cv2
    except ImportError as e:  # pragma: no cover - exercised only without opencv
        raise ImportError(
            "reading images and video needs OpenCV: pip install opencv-python-headless "
            "(or pip install 'swiftjax[inference]')"
        ) from e
    return cv2


def natural_key(name: str) -> tuple[tuple[int, int | str], ...]:
    """Sort key putting ``img2`` before ``img10`` (digit runs compare as numbers, text case-folded)."""
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p)) if p.isdigit() else (1, p.casefold()) for p in parts if p)


def to_rgb8(img: np.ndarray, name: str = "image", bgr: bool = True) -> np.ndarray:
    """Decoded pixels -> ``[H, W, 3]`` uint8 RGB, with VGGT's loader conventions.

    Args:
        img: ``[H,W]`` / ``[H,W,1]`` grey, ``[H,W,2]`` grey+alpha, ``[H,W,3]`` colour or
            ``[H,W,4]`` colour+alpha; uint8, uint16 or float in ``[0, 1]``.
        name: the file, for error messages.
        bgr: colour channels are in OpenCV's BGR(A) order (``imdecode`` output).

    16-bit keeps the high byte (``v >> 8``, as PIL does for 16-bit RGB); floats are
    ``round(255 x)`` clipped; alpha is composited on white with PIL's integer
    ``alpha_composite`` arithmetic.  Identical, by test, to ``inference.preprocess.load_image``.
    """
    if img.dtype == np.uint8:
        pass
    elif img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype.kind == "f":
        img = np.clip(np.round(img.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    else:
        raise InputError(f"{name}: unsupported pixel type {img.dtype} (expected 8/16-bit or float)")
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in (1, 2, 3, 4) or img.shape[0] < 1 or img.shape[1] < 1:
        raise InputError(f"{name}: unsupported image layout {img.shape}")
    c = img.shape[2]
    colour = img[:, :, :1].repeat(3, axis=2) if c <= 2 else (img[:, :, 2::-1] if bgr else img[:, :, :3])
    if c in (2, 4):
        return _composite_on_white(colour, img[:, :, -1])
    return np.ascontiguousarray(colour)


def _composite_on_white(colour: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """PIL ``alpha_composite(white, image)`` in its exact integer arithmetic: ``[H,W,3]`` uint8."""
    col = colour.astype(np.int64)
    a = alpha.astype(np.int64)[:, :, None]
    tmp = 128 * (col * a + 255 * (255 - a)) + (0x80 << 7)
    out = ((((tmp >> 8) + tmp) >> 8) >> 7).astype(np.uint8)
    return np.where(a == 0, np.uint8(255), out)


class FrameSource:
    """An ordered list of frames.  Subclasses: :class:`ImageFiles`, :class:`VideoFrames`.

    Attributes:
        names: one unique name per frame (used in output files).
        description: the input as the user gave it (for messages).
    """

    names: list[str]
    description: str

    def __len__(self) -> int:
        return len(self.names)

    @property
    def sizes(self) -> list[tuple[int, int]]:
        """``(height, width)`` of each frame, from the file headers (cached)."""
        raise NotImplementedError

    @property
    def image_hw(self) -> tuple[int, int]:
        """The common ``(height, width)``; :class:`InputError` if frames differ (see :func:`validate`)."""
        _check_same_size(self)
        return self.sizes[0]

    def fingerprint(self) -> list[tuple[str, int, int]]:
        """``(name, size in bytes, mtime in ns)`` of each input file, to detect a changed input
        when resuming (JSON-friendly once tuples become lists)."""
        raise NotImplementedError

    def read(self, i: int) -> np.ndarray:
        """Frame ``i`` as ``[H, W, 3]`` uint8 RGB; :class:`InputError` naming the file if it can't be decoded."""
        raise NotImplementedError

    def timestamps(self) -> tuple[np.ndarray, str]:
        """``([N] seconds, how they were obtained)``; image files have none: the frame index."""
        return np.arange(len(self), dtype=np.float64), "frame index (the input has no timestamps; see --timestamps)"

    def read_many(self, indices: Iterable[int]) -> np.ndarray:
        """Frames ``indices`` stacked as ``[n, H, W, 3]`` uint8 RGB (in the given order)."""
        idx = [int(i) for i in indices]
        frames = [self.read(i) for i in idx]
        if not frames:
            h, w = self.image_hw
            return np.zeros((0, h, w, 3), np.uint8)
        shapes = {f.shape for f in frames}
        if len(shapes) > 1:
            raise InputError(f"{self.description}: frames {idx} have different sizes {sorted(shapes)}")
        return np.stack(frames)

    def subset(self, keep: Sequence[int]) -> FrameSource:
        """A new source with only frames ``keep`` (in that order)."""
        raise NotImplementedError


def _check_complete(path: pathlib.Path, fmt: str | None) -> None:
    """Refuse a PNG or JPEG file that was cut short: its last bytes must be the format's end
    marker (PNG: the ``IEND`` chunk with its fixed CRC; JPEG: ``FF D9``, after which some
    cameras append a few padding bytes).  A 16-byte read per file, so a truncated frame is an
    error before the run (not a failure mid-way).  Other damage inside the data is found when
    the frame is decoded (``validate(decode=True)`` decodes every frame up front)."""
    if fmt not in ("PNG", "JPEG", "MPO"):
        return
    size = path.stat().st_size
    with open(path, "rb") as f:
        f.seek(max(0, size - 64))
        tail = f.read()
    if fmt == "PNG":
        ok = tail.endswith(b"IEND\xaeB`\x82")
        what = "no IEND chunk at its end"
    else:
        ok = b"\xff\xd9" in tail[-16:]  # entropy-coded data never holds FF D9 (FF is stuffed)
        what = "no end-of-image marker at its end"
    if not ok:
        raise InputError(f"{path}: image file is truncated ({fmt}, {size} bytes, {what})")


def _exif_orientation(im: Any) -> int:
    """The EXIF orientation tag (1 = as stored; 5-8 = rotated by 90 degrees) of an open image."""
    try:
        return int(im.getexif().get(0x0112, 1) or 1)
    except Exception:  # a malformed EXIF block is not our concern here
        return 1


_FD2_LOCK = threading.Lock()


@contextlib.contextmanager
def _decoder_messages() -> Any:
    """What C libraries (libjpeg, libpng inside OpenCV) write to file descriptor 2 while
    inside: ``with _decoder_messages() as said: ...`` then ``said[0]`` is the text.  One
    capture at a time (a lock): fd 2 belongs to the process."""
    box: list[str] = []
    with _FD2_LOCK, tempfile.TemporaryFile() as tmp:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(tmp.fileno(), 2)
        try:
            yield box
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            box.append(tmp.read().decode("utf-8", "replace"))


def _first_line(text: str) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[0] + (f" (+{len(lines) - 1} more)" if len(lines) > 1 else "") if lines else ""


class ImageFiles(FrameSource):
    """Frames stored as image files.

    Args:
        paths: the files, in frame order.
        names: their names (default: the file names).
        description: the input as given, for messages.
    """

    def __init__(self, paths: Sequence[PathLike], names: Sequence[str] | None = None, description: str = "") -> None:
        self.paths = [pathlib.Path(p) for p in paths]
        self.names = list(names) if names is not None else [p.name for p in self.paths]
        if len(self.names) != len(self.paths):
            raise ValueError("ImageFiles: names and paths differ in length")
        self.description = description or (str(self.paths[0].parent) if self.paths else "<no images>")
        self._sizes: list[tuple[int, int] | None] | None = None
        self.orientation: dict[int, int] = {}  # frame -> EXIF orientation, where it is not 1 (from probe)

    def probe(self, i: int, decode: bool = False) -> tuple[int, int]:
        """``(height, width)`` of frame ``i`` from its header (``decode=True``: a full decode,
        which also catches truncated data).  :class:`InputError` naming the file on failure."""
        path = self.paths[i]
        from PIL import Image

        try:
            im = Image.open(path)
        except Exception as e:  # not a format Pillow knows: let OpenCV try
            img = self._imread(path)
            if img is None:
                why = (str(e).splitlines() or [""])[0]
                raise InputError(f"{path}: cannot read image (corrupt or not an image: {why})") from None
            return int(img.shape[0]), int(img.shape[1])
        with im:
            w, h = im.size
            fmt = im.format
            orientation = _exif_orientation(im)
            if orientation != 1:
                self.orientation[i] = orientation
            if not decode:
                _check_complete(path, fmt)
            if decode:
                try:
                    im.load()
                except Exception as e:  # truncated / corrupt data
                    why = (str(e).splitlines() or [""])[0]
                    raise InputError(f"{path}: cannot decode image ({why})") from None
        if w <= 0 or h <= 0:
            raise InputError(f"{path}: image has size {w}x{h}")
        return h, w

    @staticmethod
    def _imread(path: pathlib.Path) -> np.ndarray | None:
        cv2 = _cv2()
        if not path.is_file():
            return None
        # imread can't open non-ASCII paths on every platform; decoding the bytes always works.
        data = np.fromfile(path, dtype=np.uint8)
        if data.size == 0:
            return None
        return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)  # UNCHANGED: alpha, 16-bit, no EXIF rotation

    @property
    def sizes(self) -> list[tuple[int, int]]:
        if self._sizes is None:
            self._sizes = [None] * len(self)
        for i, s in enumerate(self._sizes):
            if s is None:
                self._sizes[i] = self.probe(i)
        return list(self._sizes)  # type: ignore[arg-type]

    def fingerprint(self) -> list[tuple[str, int, int]]:
        out = []
        for name, p in zip(self.names, self.paths):
            st = p.stat()
            out.append((name, int(st.st_size), int(st.st_mtime_ns)))
        return out

    def read(self, i: int) -> np.ndarray:
        path = self.paths[i]
        img = self._imread(path)
        if img is None:
            raise InputError(f"{path}: cannot decode image (corrupt, truncated or not an image)")
        return to_rgb8(img, str(path))

    def decode_check(self, i: int) -> None:
        """Decode frame ``i`` as the run will (OpenCV) and refuse it if the decoder fails or
        reports damage: libjpeg decodes a JPEG damaged mid-file (grey rows) with only a
        warning on stderr ("Corrupt JPEG data: ..."), which is taken as an error here.
        :class:`InputError` naming the file."""
        path = self.paths[i]
        with _decoder_messages() as said:
            img = self._imread(path)
        if img is None:
            why = f": {_first_line(said[0])}" if said[0].strip() else ""
            raise InputError(f"{path}: cannot decode image (corrupt data{why})")
        if said[0].strip():
            raise InputError(f"{path}: corrupt image data (the decoder reported: {_first_line(said[0])})")
        size = self._sizes[i] if self._sizes is not None else None
        if size is not None and tuple(img.shape[:2]) != tuple(size):
            raise InputError(
                f"{path}: decodes to {img.shape[1]}x{img.shape[0]} but its header says {size[1]}x{size[0]}"
            )

    def append(self, path: PathLike, name: str | None = None) -> None:
        """Add one more file as the last frame (a folder that grows: ``--follow``)."""
        path = pathlib.Path(path)
        self.paths.append(path)
        self.names.append(name if name is not None else path.name)
        if self._sizes is not None:
            self._sizes.append(None)

    def subset(self, keep: Sequence[int]) -> ImageFiles:
        out = ImageFiles([self.paths[i] for i in keep], [self.names[i] for i in keep], self.description)
        if self._sizes is not None:
            out._sizes = [self._sizes[i] for i in keep]
        out.orientation = {k: self.orientation[i] for k, i in enumerate(keep) if i in self.orientation}
        return out


class VideoFrames(FrameSource):
    """Every ``stride``-th frame of a video file, decoded with OpenCV.

    Reading frames in increasing order is sequential decoding; a backwards or far jump seeks
    (``CAP_PROP_POS_FRAMES``).  The frame count comes from the container and is checked by
    :func:`validate` (which truncates it, with a warning, if the last frames don't decode).
    """

    def __init__(self, path: PathLike, stride: int = 1, frame_indices: Sequence[int] | None = None) -> None:
        self._cap: Any = None
        self._pos = -1  # index of the next frame the open capture will return
        self.path = pathlib.Path(path)
        self.stride = int(stride)
        self.description = str(self.path)
        cv2 = _cv2()
        cap = cv2.VideoCapture(str(self.path))
        try:
            if not cap.isOpened():
                raise InputError(f"{self.path}: cannot open video (not a video file OpenCV can decode)")
            self._hw = (int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)), int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)))
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        finally:
            cap.release()
        if frame_indices is None:
            if count <= 0:
                count = self._count_by_decoding()
            frame_indices = range(0, count, self.stride)
        self.frame_indices = [int(k) for k in frame_indices]
        self.names = [f"{self.path.stem}_{k:06d}.png" for k in self.frame_indices]

    def _count_by_decoding(self) -> int:
        cv2 = _cv2()
        cap = cv2.VideoCapture(str(self.path))
        n = 0
        while cap.grab():
            n += 1
        cap.release()
        return n

    @property
    def sizes(self) -> list[tuple[int, int]]:
        return [self._hw] * len(self)

    def fingerprint(self) -> list[tuple[str, int, int]]:
        st = self.path.stat()
        return [(f"{self.path.name}[::{self.stride}]", int(st.st_size), int(st.st_mtime_ns))]

    def _read_video_frame(self, k: int) -> np.ndarray | None:
        cv2 = _cv2()
        if self._cap is None:
            self._cap = cv2.VideoCapture(str(self.path))
            self._pos = 0
        if not (self._pos <= k <= self._pos + _SEEK_FORWARD_MAX):
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, k)
            self._pos = k
        while self._pos < k:
            if not self._cap.grab():
                return None
            self._pos += 1
        ok, frame = self._cap.read()
        if not ok:
            self._pos = -(10**9)  # force a seek next time
            return None
        self._pos = k + 1
        return frame

    def read(self, i: int) -> np.ndarray:
        k = self.frame_indices[i]
        frame = self._read_video_frame(k)
        if frame is None:
            raise InputError(f"{self.path}: cannot decode frame {k}")
        return to_rgb8(frame, f"{self.path} frame {k}")

    def timestamps(self) -> tuple[np.ndarray, str]:
        """The video's own times: frame index / frame rate (container's ``CAP_PROP_FPS``), so a
        ``stride`` keeps the original times; the frame index if the container has no rate."""
        cv2 = _cv2()
        cap = cv2.VideoCapture(str(self.path))
        try:
            fps = float(cap.get(cv2.CAP_PROP_FPS)) if cap.isOpened() else 0.0
        finally:
            cap.release()
        index = np.asarray(self.frame_indices, np.float64)
        if not (np.isfinite(fps) and fps > 0):
            return index, f"video frame index ({self.path.name} has no frame rate)"
        return index / fps, f"video time: frame index / {fps:g} fps ({self.path.name}, stride {self.stride})"

    def subset(self, keep: Sequence[int]) -> VideoFrames:
        return VideoFrames(self.path, self.stride, [self.frame_indices[i] for i in keep])

    def close(self) -> None:
        """Release the decoder (it is reopened on the next read)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __del__(self) -> None:
        self.close()


def read_timestamps(path: PathLike, source: FrameSource, stride: int = 1) -> np.ndarray:
    """Per-frame times (seconds) for ``source`` from a text file.

    Lines (``#`` comments and blank lines skipped) are either ``timestamp name`` (TUM's
    ``rgb.txt``; matched to the frames by file name, so any order and ``--stride`` work) or
    one ``timestamp`` per line, for every input image in order (before ``stride``: every
    ``stride``-th is used) or for the frames used.  Times must be finite and increasing.

    Raises:
        InputError: unreadable file, a frame without a time, a bad or decreasing value.
    """
    path = pathlib.Path(path)
    try:
        numbered = [
            (n, ln.split())
            for n, ln in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), start=1)
            if ln.strip() and not ln.lstrip().startswith("#")
        ]
    except IsADirectoryError:
        raise InputError(f"timestamps file {path} is a directory") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"timestamps file {path}: cannot read it ({err})") from None
    lines = [w for _, w in numbered]
    n = len(source)

    def number(text: str) -> float:
        try:
            return float(text)
        except ValueError:
            raise InputError(f"timestamps file {path}: {text!r} is not a number") from None

    if lines and all(len(w) >= 2 for w in lines):
        by_name: dict[str, float] = {}
        first_line: dict[str, int] = {}
        for n, w in numbered:
            name = pathlib.PurePath(w[1]).name
            if name in by_name:
                raise InputError(f"timestamps file {path} names frame {name} twice (lines {first_line[name]} and {n})")
            by_name[name], first_line[name] = number(w[0]), n
        missing = [name for name in source.names if pathlib.PurePath(name).name not in by_name]
        if missing:
            raise InputError(f"timestamps file {path} has no time for frame {missing[0]} ({len(missing)} missing)")
        t = np.array([by_name[pathlib.PurePath(name).name] for name in source.names])
    else:
        values = np.array([number(w[0]) for w in lines])
        if len(values) == n:
            t = values
        elif stride > 1 and len(values[::stride]) == n:
            t = values[::stride]
        else:
            raise InputError(
                f"timestamps file {path} has {len(values)} times for {n} frames"
                + (f" ({n} after --stride {stride})" if stride > 1 else "")
            )
    if not np.all(np.isfinite(t)):
        raise InputError(f"timestamps file {path} holds non-finite times")
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise InputError(
            f"timestamps file {path}: times must increase, but frame {k + 1} ({t[k + 1]}) <= frame {k} ({t[k]})"
        )
    return t


def _glob_root(pattern: str) -> pathlib.Path:
    """The longest leading directory of ``pattern`` with no glob characters."""
    parts = pathlib.Path(pattern).parts
    fixed: list[str] = []
    for part in parts[:-1]:
        if _GLOB_CHARS.search(part):
            break
        fixed.append(part)
    return pathlib.Path(*fixed) if fixed else pathlib.Path(".")


def _is_image(path: pathlib.Path) -> bool:
    return path.suffix.lower() in IMAGE_EXTENSIONS and not path.name.startswith(".") and path.is_file()


def list_frames(input: PathLike, stride: int = 1) -> FrameSource:
    """The frames of ``input``: an image folder, a glob pattern, or a video file.

    Args:
        input: folder / pattern / video path (see the module docstring for the rules).
        stride: keep every ``stride``-th frame (images and video alike).

    Raises:
        InputError: the input doesn't exist, the folder has no images, the pattern matches
            none, or the file is not a video OpenCV can open.
    """
    if stride < 1:
        raise InputError(f"frame stride must be >= 1, got {stride}")
    text = os.fspath(input)
    path = pathlib.Path(text)
    if path.is_dir():
        files = [p for p in path.iterdir() if _is_image(p)]
        if not files:
            exts = "/".join(sorted(e[1:] for e in IMAGE_EXTENSIONS))
            raise InputError(f"{path}: folder has no images ({exts})")
        files.sort(key=lambda p: natural_key(p.name))
        files = files[::stride]
        return ImageFiles(files, [p.name for p in files], str(path))
    if path.is_file():
        if path.suffix.lower() in IMAGE_EXTENSIONS:
            return ImageFiles([path], [path.name], str(path))
        return VideoFrames(path, stride)
    if _GLOB_CHARS.search(text):
        root = _glob_root(text)
        files = [pathlib.Path(p) for p in globlib.glob(text, recursive=True)]
        files = [p for p in files if _is_image(p)]
        if not files:
            raise InputError(f"{text}: no image files match this pattern")
        names = [p.relative_to(root).as_posix() if p.is_relative_to(root) else p.name for p in files]
        files, names = _once_per_file(files, names, text)
        order = sorted(range(len(files)), key=lambda i: natural_key(names[i]))[::stride]
        return ImageFiles([files[i] for i in order], [names[i] for i in order], text)
    raise InputError(f"{text}: no such file, folder or glob pattern")


def _once_per_file(files: list[pathlib.Path], names: list[str], pattern: str) -> tuple[list[pathlib.Path], list[str]]:
    """Each file once: ``**`` follows directory links, so a link loop (``a/loop -> ..``)
    reaches the same files again and again (12 frames became 492).  Files are told apart by
    their real path; the shortest name (fewest folders) is kept, with a warning."""
    best: dict[str, int] = {}
    for k, p in enumerate(files):
        real = os.path.realpath(p)
        j = best.get(real)
        if j is None or (names[k].count("/"), natural_key(names[k])) < (names[j].count("/"), natural_key(names[j])):
            best[real] = k
    if len(best) == len(files):
        return files, names
    keep = sorted(best.values())
    logger.warning(
        f"{pattern}: {len(files)} matches are {len(keep)} files (directory links, e.g. a link loop, reach the same "
        f"files again); each file is used once"
    )
    return [files[k] for k in keep], [names[k] for k in keep]


def _check_same_size(source: FrameSource) -> None:
    sizes = source.sizes
    for i, s in enumerate(sizes):
        if s != sizes[0]:
            rotated = {k: o for k, o in getattr(source, "orientation", {}).items() if o >= 5}
            hint = ""
            if rotated:
                k, o = next(iter(rotated.items()))
                hint = (
                    f"; note: EXIF orientation is ignored (frames are used as stored, as VGGT's loader does) and "
                    f"{len(rotated)} frames, e.g. {source.names[k]} (orientation {o}), are stored rotated by 90 "
                    f"degrees: rotate those files themselves (e.g. exiftran -ai, or mogrify -auto-orient)"
                )
            raise InputError(
                f"{source.description}: images differ in size: {source.names[0]} is {sizes[0][1]}x{sizes[0][0]} "
                f"but {source.names[i]} is {s[1]}x{s[0]} (width x height); all frames must have one size{hint}"
            )


def validate(
    source: FrameSource, skip_bad: bool = False, decode: bool = True, workers: int | None = None
) -> FrameSource:
    """Check every frame before any work starts; returns the source to use.

    Image files: each header is read, with the end marker of PNG and JPEG files (a
    truncated file), then (``decode=True``, the default) each image is decoded as the run
    will decode it, on a thread pool, and refused if the decoder fails or reports damage
    (libjpeg decodes a JPEG damaged mid-file with grey rows and only a warning; that
    warning is an error here).  Frames with an EXIF orientation get a warning: it is
    ignored, as VGGT's loader ignores it.  Video: the last listed frame is decoded; if it
    fails, the frame count is recounted by decoding and the list truncated with a warning.

    Args:
        source: from :func:`list_frames`.
        skip_bad: drop unreadable or damaged images with a warning instead of raising.
        decode: fully decode every image (``False``: headers and end markers only).
        workers: decoding threads (default: the CPU count, at most 8).

    Raises:
        InputError: no frames; an unreadable or damaged image (unless ``skip_bad``); images
            of different sizes (naming two of them).
    """
    if len(source) == 0:
        raise InputError(f"{source.description}: no frames")
    if isinstance(source, ImageFiles):
        sizes: dict[int, tuple[int, int]] = {}
        failed: dict[int, InputError] = {}
        for i in range(len(source)):
            try:
                sizes[i] = source.probe(i)
            except InputError as e:
                failed[i] = e
        source._sizes = [sizes.get(i) for i in range(len(source))]
        if decode:
            failed.update(_decode_all(source, sorted(sizes), workers))
        for i in sorted(failed):
            if not skip_bad:
                raise failed[i]
            logger.warning(f"skipping unreadable frame: {failed[i]}")
        keep = [i for i in range(len(source)) if i not in failed]
        if not keep:
            raise InputError(f"{source.description}: none of the {len(source)} images can be read")
        if len(keep) != len(source):
            source = source.subset(keep)
    elif isinstance(source, VideoFrames):
        last = len(source) - 1
        if source._read_video_frame(source.frame_indices[last]) is None:
            count = source._count_by_decoding()
            kept = [k for k in source.frame_indices if k < count]
            logger.warning(
                f"{source.path}: container says frame {source.frame_indices[last]} exists but only "
                f"{count} frames decode; using {len(kept)} frames"
            )
            source.close()
            source = source.subset(range(len(kept)))
            if len(source) == 0:
                raise InputError(f"{source.path}: video has no decodable frames")
    _check_same_size(source)
    if getattr(source, "orientation", None):
        k, o = next(iter(source.orientation.items()))
        logger.warning(
            f"{source.description}: {len(source.orientation)} frames carry an EXIF orientation (e.g. "
            f"{source.names[k]}: {o}); it is ignored, the frames are used as stored (as VGGT's loader does)"
        )
    return source


def _decode_all(source: ImageFiles, frames: Sequence[int], workers: int | None) -> dict[int, InputError]:
    """:meth:`ImageFiles.decode_check` of ``frames``: ``{frame: error}`` of the bad ones.

    The decoders report damage on the process's stderr, which names no file, so the frames
    are first decoded together on a thread pool under one capture; only when something was
    reported (or failed) are they decoded again one at a time to tell which."""
    if not frames:
        return {}
    n = workers or min(8, os.cpu_count() or 1)

    def clean(i: int) -> bool:
        img = source._imread(source.paths[i])
        return img is not None and tuple(img.shape[:2]) == tuple(source._sizes[i] or ())

    with _decoder_messages() as said, ThreadPoolExecutor(max_workers=n) as pool:
        ok = list(pool.map(clean, frames))
    if all(ok) and not said[0].strip():
        return {}
    failed: dict[int, InputError] = {}
    for i in frames:
        try:
            source.decode_check(i)
        except InputError as e:
            failed[i] = e
    if not failed and said[0].strip():
        sys.stderr.write(said[0])  # someone else's message: pass it on
    return failed

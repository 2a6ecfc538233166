"""Frames as they arrive: a folder that a recorder fills (``--follow``), and replay at a rate.

    src = FollowSource("rec/", end_marker="END", timeout_s=30.0)
    for frame in src:                       # Frame(index, name, path, image, arrival)
        feed(frame.image)                   # [H, W, 3] uint8 RGB, already decoded
    src.ended_by                            # "end_marker", "timeout" or "stop"
    # from a SIGINT handler (any thread): src.stop() -> the loop ends after the current frame

    for frame in ReplaySource("drive.mp4", fps=10.0): ...   # or an image folder / glob / list of paths

    with Recorder("rec/", frames, fps=10.0, split=(3,)):     # tests, demos, the bench
        ...                                                   # frame 3 is written in two parts

A frame is yielded once its file is complete: same non-zero size and modification time at two
polls ``poll_s`` apart, the format's end marker present (PNG ``IEND``, JPEG ``FF D9``) and a
decode to the header's size; frames come in :func:`~swiftjax.io.images.list_frames`' natural
name order (a complete frame waits for an incomplete earlier one), each with its arrival time
(``time.monotonic()``).  The stream ends at the ``end_marker`` file, after ``timeout_s`` without
a change in the folder, or at :meth:`FollowSource.stop` (thread-safe).  Errors are one-line
:class:`FollowError` exceptions (an :class:`~swiftjax.io.images.InputError`), raised after every earlier
frame was yielded.  The rules in full, and why: docs/cli.md, "How a growing folder is read".
"""

from __future__ import annotations

import os
import pathlib
import shutil
import threading
import time
from collections.abc import Iterator, Sequence
from typing import NamedTuple

import numpy as np

from swiftjax.io.images import ImageFiles, InputError, _cv2, _is_image, list_frames, natural_key

__all__ = ["Frame", "FollowError", "FollowTimeoutError", "FrameSizeError", "FollowSource", "ReplaySource", "Recorder"]

PathLike = str | os.PathLike[str]


class Frame(NamedTuple):
    """One arrived frame.

    Attributes:
        index: its position in the sequence (0, 1, ...).
        name: the file name (a video frame: ``<stem>_<k:06d>.png``).
        path: the file, or ``None`` (a video frame).
        image: ``[H, W, 3]`` uint8 RGB.
        arrival: ``time.monotonic()`` when it became available.
    """

    index: int
    name: str
    path: pathlib.Path | None
    image: np.ndarray
    arrival: float


class FollowError(InputError):
    """A followed folder (or replayed input) is unusable; one line naming the folder or file."""


class FollowTimeoutError(FollowError):
    """No frame arrived within the timeout."""


class FrameSizeError(FollowError):
    """A frame of another size than the first arrived."""


def _hw_text(hw: tuple[int, int]) -> str:
    return f"{hw[1]}x{hw[0]}"


class FollowSource:
    """The frames of a folder that grows, each yielded once it is complete (module docstring).

    Args:
        folder: the folder a recorder writes (must exist).
        end_marker: name of the file that ends the recording (``None``: no marker).
        timeout_s: end after this many seconds without a new frame (``None``: never); with no
            frame at all, :class:`FollowTimeoutError`.
        poll_s: seconds between looks at the folder (a frame is yielded ``poll_s`` to
            ``2 poll_s`` after its last byte is written).
        keep: a folder (created) where each frame's file is kept the moment it is found
            complete, before it is decoded: hard-linked (no copy; the same inode, so the same
            name, size, times and bytes), else copied with its times (another file system).
            The frame is read from there and its ``path`` is the kept file, so a recorder may
            delete a frame once it was read (a ring buffer) and the run still has it.  A file
            deleted before it was kept was never read: it is skipped, as without ``keep``.

    Attributes:
        ended_by: ``None`` while running, then ``"end_marker"``, ``"timeout"`` or ``"stop"``.
        count: frames yielded so far.
        image_hw: ``(height, width)`` of the first frame (``None`` before it).

    Iterate once (one consumer); :meth:`stop` may be called from any thread.

    Raises:
        FollowError: ``folder`` is not a folder, ``timeout_s`` or ``poll_s`` not positive.
    """

    def __init__(
        self,
        folder: PathLike,
        *,
        end_marker: str | None = "END",
        timeout_s: float | None = 60.0,
        poll_s: float = 0.05,
        keep: PathLike | None = None,
    ) -> None:
        self.folder = pathlib.Path(folder)
        self.keep = None if keep is None else pathlib.Path(keep)
        if not self.folder.is_dir():
            raise FollowError(f"{self.folder}: no such folder to follow")
        if timeout_s is not None and not timeout_s > 0:
            raise FollowError(f"follow timeout must be > 0 seconds, got {timeout_s}")
        if not poll_s > 0:
            raise FollowError(f"follow poll interval must be > 0 seconds, got {poll_s}")
        self.end_marker, self.timeout_s, self.poll_s = end_marker, timeout_s, poll_s
        self.ended_by: str | None = None
        self.count = 0
        self.image_hw: tuple[int, int] | None = None
        self._first: str | None = None
        self._stop = threading.Event()

    def stop(self) -> None:
        """End the iteration at the next look (thread-safe; frames not yet yielded are not read)."""
        self._stop.set()

    def __iter__(self) -> Iterator[Frame]:
        return self._frames()

    def _kept(self, path: pathlib.Path) -> pathlib.Path | None:
        """``path`` kept in :attr:`keep` (see the class docstring); None when it is gone."""
        assert self.keep is not None
        self.keep.mkdir(parents=True, exist_ok=True)
        kept = self.keep / path.name
        kept.unlink(missing_ok=True)  # a file of an earlier attempt: keep the current one
        try:
            os.link(path, kept)
        except FileNotFoundError:
            return None
        except OSError:  # another file system, or no hard links there
            try:
                shutil.copy2(path, kept)
            except FileNotFoundError:
                kept.unlink(missing_ok=True)
                return None
        return kept

    def _read(self, path: pathlib.Path) -> np.ndarray | None:
        """The frame's RGB pixels, or None while it is not a complete image."""
        files = ImageFiles([path], description=str(self.folder))
        try:
            hw = files.probe(0)  # header, and the end marker of PNG / JPEG
            img = files.read(0)
        except (InputError, OSError):
            return None
        return img if img.shape[:2] == hw else None

    def _frames(self) -> Iterator[Frame]:
        read: set[str] = set()
        last_key: tuple | None = None
        last_name = ""
        stats: dict[str, tuple[int, int]] = {}  # pending file -> (size, mtime) at the last look
        progress = time.monotonic()
        while True:
            if self._stop.is_set():
                self.ended_by = "stop"
                return
            # the marker first: every frame it follows is then in the listing below
            ended = self.end_marker is not None and (self.folder / self.end_marker).exists()
            try:
                listing = [
                    p for p in self.folder.iterdir() if p.name not in read and _is_image(p)
                ]  # no stat of read files
            except FileNotFoundError:
                raise FollowError(f"{self.folder}: the followed folder was removed") from None
            listing.sort(key=lambda p: natural_key(p.name))
            for p in listing:
                if last_key is not None and natural_key(p.name) < last_key:
                    raise FollowError(
                        f"{p}: arrived after {last_name} was read but sorts before it; a recorder must write frames "
                        "in name order"
                    )
            stats = {k: v for k, v in stats.items() if k in {p.name for p in listing}}  # deleted before read
            waiting: pathlib.Path | None = None
            for p in listing:
                if self._stop.is_set():
                    break
                try:
                    st = p.stat()
                except FileNotFoundError:
                    stats.pop(p.name, None)
                    continue
                now_stat, before = (st.st_size, st.st_mtime_ns), stats.get(p.name)
                stats[p.name] = now_stat
                if before != now_stat:
                    progress = time.monotonic()  # the recorder is writing: not idle
                source = p
                if before == now_stat and st.st_size > 0 and self.keep is not None:
                    kept = self._kept(p)
                    if kept is None:  # deleted before it was read
                        stats.pop(p.name, None)
                        continue
                    source = kept
                img = self._read(source) if before == now_stat and st.st_size > 0 else None
                if img is None:
                    if ended and before == now_stat:
                        raise FollowError(
                            f"{p}: still not a complete image ({st.st_size} bytes) when the end marker "
                            f"{self.end_marker} appeared"
                        )
                    waiting = p
                    break  # in name order: later frames wait for this one
                hw = img.shape[:2]
                if self.image_hw is None:
                    self.image_hw, self._first = hw, p.name
                elif hw != self.image_hw:
                    raise FrameSizeError(
                        f"{p}: frame is {_hw_text(hw)} but the frames before it are {_hw_text(self.image_hw)} (from "
                        f"{self._first}); all frames must have one size"
                    )
                read.add(p.name)
                del stats[p.name]
                last_key, last_name = natural_key(p.name), p.name
                yield Frame(self.count, p.name, source, img, time.monotonic())
                self.count += 1
                progress = time.monotonic()  # the consumer's time is not the recorder's idleness
            if self._stop.is_set():
                continue
            if ended and waiting is None:
                if self.count == 0:
                    raise FollowError(f"{self.folder}: the end marker {self.end_marker} appeared before any frame")
                self.ended_by = "end_marker"
                return
            if self.timeout_s is not None and time.monotonic() - progress > self.timeout_s:
                if waiting is not None:
                    raise FollowError(
                        f"{waiting}: still not a complete image after the follow timeout of "
                        f"{self.timeout_s:g} s without a change in the folder"
                    )
                if self.count == 0:
                    raise FollowTimeoutError(
                        f"{self.folder}: no frame arrived within the follow timeout of {self.timeout_s:g} s"
                    )
                self.ended_by = "timeout"
                return
            self._stop.wait(self.poll_s)


class ReplaySource:
    """The frames of an image folder, glob, list of image paths or video, released at ``fps``
    (frame ``k`` at ``t₀ + k / fps``, ``t₀`` the first frame's release; each decoded before its
    time): a recording played back live.

    Args:
        input: what :func:`~swiftjax.io.images.list_frames` takes, or a sequence of image paths.
        fps: frames per second (``--replay-fps``), > 0.
        stride: keep every ``stride``-th frame (as ``list_frames``).

    Attributes: ``ended_by`` (``"end"`` or ``"stop"``), ``count``, as :class:`FollowSource`.

    Raises:
        InputError: what ``list_frames`` raises; ``fps`` not positive.
    """

    def __init__(self, input: PathLike | Sequence[PathLike], fps: float, *, stride: int = 1) -> None:
        if not (fps > 0 and np.isfinite(fps)):
            raise InputError(f"replay rate must be a positive number of frames per second, got {fps}")
        if isinstance(input, (str, os.PathLike)):
            self.source = list_frames(input, stride)
        else:
            paths = [pathlib.Path(p) for p in input][::stride]
            if not paths:
                raise InputError("replay: no image paths given")
            self.source = ImageFiles(paths)
        self.fps = float(fps)
        self.ended_by: str | None = None
        self.count = 0
        self._stop = threading.Event()

    def stop(self) -> None:
        """End the replay at the next frame (thread-safe)."""
        self._stop.set()

    def __len__(self) -> int:
        return len(self.source)

    def __iter__(self) -> Iterator[Frame]:
        paths = getattr(self.source, "paths", None)
        start = 0.0
        try:
            for k in range(len(self.source)):
                img = self.source.read(k)
                if k == 0:  # the clock starts at the first frame (opening a video takes a while)
                    start = time.monotonic()
                delay = start + k / self.fps - time.monotonic()
                if self._stop.wait(max(0.0, delay)):
                    self.ended_by = "stop"
                    return
                yield Frame(k, self.source.names[k], None if paths is None else paths[k], img, time.monotonic())
                self.count += 1
            self.ended_by = "end"
        finally:
            close = getattr(self.source, "close", None)
            if close is not None:
                close()


class Recorder:
    """A recorder in a background thread: writes ``frames`` into ``folder`` at ``fps``, then the
    end marker; for tests, demos and the bench to drive :class:`FollowSource`.

    Frame ``k`` is written at ``start + k / fps`` directly under its final name (as a camera
    driver does; no temporary name), ``names[k]`` (default ``<k:06d><ext>``).  An array frame
    (``[H, W, 3]`` uint8 RGB) is encoded as ``ext`` (PNG by default: lossless); a path is
    copied byte for byte (keeping its extension).  Frames in ``split`` are written in two
    parts with ``split_pause_s`` between (a slowly written file).

    ``written`` and ``finished_at`` (``time.monotonic()`` after each file was closed) record
    what was written.  Use as a context manager (``with Recorder(...) as rec:``): the thread starts on entry and
    is stopped and joined on exit (no thread outlives the block); ``rec.wait()`` waits for the
    end, and re-raises the writer's error, if any.
    """

    def __init__(
        self,
        folder: PathLike,
        frames: Sequence[np.ndarray | PathLike],
        fps: float,
        *,
        names: Sequence[str] | None = None,
        ext: str = ".png",
        split: Sequence[int] = (),
        split_pause_s: float = 0.3,
        end_marker: str | None = "END",
        start_delay_s: float = 0.0,
    ) -> None:
        self.folder = pathlib.Path(folder)
        self.frames = list(frames)
        self.fps, self.ext, self.split, self.split_pause_s = float(fps), ext, set(split), float(split_pause_s)
        self.end_marker, self.start_delay_s = end_marker, float(start_delay_s)
        self.names = (
            list(names)
            if names is not None
            else [
                f"{k:06d}{ext if not isinstance(f, (str, os.PathLike)) else pathlib.Path(f).suffix}"
                for k, f in enumerate(self.frames)
            ]
        )
        if len(self.names) != len(self.frames):
            raise ValueError("Recorder: names and frames differ in length")
        self.written: list[pathlib.Path] = []
        self.finished_at: list[float] = []  # time.monotonic() after each file's last byte
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="swiftjax-recorder", daemon=True)

    def _bytes(self, frame: np.ndarray | PathLike) -> bytes:
        if isinstance(frame, (str, os.PathLike)):
            return pathlib.Path(frame).read_bytes()
        cv2 = _cv2()
        ok, buf = cv2.imencode(self.ext, np.ascontiguousarray(np.asarray(frame)[:, :, ::-1]))
        if not ok:
            raise ValueError(f"Recorder: cannot encode a frame of shape {np.shape(frame)} as {self.ext}")
        return buf.tobytes()

    def _run(self) -> None:
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            start = time.monotonic() + self.start_delay_s
            for k, (frame, name) in enumerate(zip(self.frames, self.names)):
                data = self._bytes(frame)
                if self._stop.wait(max(0.0, start + k / self.fps - time.monotonic())):
                    return
                path = self.folder / name
                with open(path, "wb") as f:
                    if k in self.split:
                        f.write(data[: len(data) // 2])
                        f.flush()
                        if self._stop.wait(self.split_pause_s):
                            return
                    f.write(data[len(data) // 2 :] if k in self.split else data)
                self.finished_at.append(time.monotonic())
                self.written.append(path)
            if self.end_marker is not None and not self._stop.is_set():
                (self.folder / self.end_marker).touch()
        except BaseException as err:
            self.error = err

    def start(self) -> Recorder:
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop writing (the frame being written is finished only if it is not split)."""
        self._stop.set()

    def wait(self, timeout: float | None = None) -> None:
        """Join the thread; re-raise its error."""
        self._thread.join(timeout)
        if self.error is not None:
            raise self.error

    def __enter__(self) -> Recorder:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
        self._thread.join()

"""Frames decoded and preprocessed ahead of their chunk, on a thread pool.

Decoding and resizing a chunk's frames on one core can take longer than a GPU needs to predict
the chunk (decode times: docs/performance/io.md).  :class:`FrameLoader` keeps the model fed:

* each frame is decoded and preprocessed on its own pool task (OpenCV releases the GIL, so
  the work spreads over the cores); a video, whose reader seeks, is read under a lock and only
  its preprocessing runs in parallel;
* :meth:`FrameLoader.prefetch` starts a chunk's frames as soon as the chunk is scheduled, so
  they are ready while the chunk before it predicts (the local executor calls it);
* a frame scheduled by two chunks (the overlap) is decoded once and kept until both took it.

Every frame is preprocessed alone; for frames of one size (the input check refuses mixed
sizes) that is what the batch preprocessing gives, so predictions do not change.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

__all__ = ["FrameLoader"]


class FrameLoader:
    """``load(frames) -> [S, 3, H, W]`` float32 of ``preprocess([read(k) ...])``, one frame a task.

    Args:
        read: frame index -> decoded image (``FrameSource.read``).
        preprocess: list of decoded images -> ``[n, 3, H, W]`` (the backbone's preprocessing).
        threads: pool size (default: the cores, at most 8).
        serial_reads: read one frame at a time (a video's seeking reader).
    """

    def __init__(
        self,
        read: Callable[[int], Any],
        preprocess: Callable[[list[Any]], np.ndarray],
        threads: int | None = None,
        serial_reads: bool = False,
    ) -> None:
        self._read, self._preprocess = read, preprocess
        self._threads = threads or min(8, os.cpu_count() or 1)
        self._read_lock = threading.Lock() if serial_reads else None
        self._lock = threading.Lock()
        self._pending: dict[int, tuple[Future, int]] = {}  # frame -> (its task, chunks still to take it)
        self._pool: ThreadPoolExecutor | None = None

    def _one(self, k: int) -> np.ndarray:
        if self._read_lock is None:
            image = self._read(k)
        else:
            with self._read_lock:
                image = self._read(k)
        return self._preprocess([image])[0]

    def _submit(self, k: int) -> Future:
        if self._pool is None:  # "decode-" threads: not swiftjax's writers, which a Ctrl-C joins
            self._pool = ThreadPoolExecutor(self._threads, thread_name_prefix="decode")
        return self._pool.submit(self._one, k)

    def prefetch(self, frames: Iterable[int]) -> None:
        """Start decoding ``frames`` for a later :meth:`load` of the same frames."""
        with self._lock:
            for k in map(int, frames):
                future, count = self._pending.get(k, (None, 0))
                self._pending[k] = (future or self._submit(k), count + 1)

    def load(self, frames: Iterable[int]) -> np.ndarray:
        """The preprocessed ``frames``: prefetched ones from their tasks, the others now."""
        keys = [int(k) for k in frames]
        with self._lock:
            futures = []
            for k in keys:
                future, count = self._pending.pop(k, (None, 0))
                if future is None:
                    future = self._submit(k)
                elif count > 1:  # another scheduled chunk takes it too
                    self._pending[k] = (future, count - 1)
                futures.append(future)
        return np.stack([f.result() for f in futures])

    def close(self) -> None:
        """Drop what was prefetched and stop the pool's threads."""
        with self._lock:
            for future, _ in self._pending.values():
                future.cancel()
            self._pending.clear()
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True)

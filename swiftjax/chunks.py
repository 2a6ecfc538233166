"""The chunk schedule: which frames each VGGT call sees.

Chunk ``t`` covers frames ``[t (B - O), min(t (B - O) + B, N))``; the schedule stops at the
first chunk that reaches ``N``, so only the last chunk can be short, and it always has more
than ``O`` frames.  Consecutive chunks share exactly ``O`` frames.  A sequence shorter than
one chunk is a single (short) chunk.  Host-side helpers: they run once per sequence.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["ChunkSchedule", "chunk_schedule"]


@dataclasses.dataclass(frozen=True)
class ChunkSchedule:
    """Frame ranges of the temporal chunks of an ``n_frames`` sequence.

    Attributes:
        n_frames: sequence length ``N``.
        chunk_size: ``B``.
        overlap: ``O`` (frames shared by chunks ``t`` and ``t + 1``).
        starts: ``[T]`` int first frame of each chunk.
        ends: ``[T]`` int one past the last frame of each chunk.
    """

    n_frames: int
    chunk_size: int
    overlap: int
    starts: np.ndarray
    ends: np.ndarray

    @property
    def num_chunks(self) -> int:
        return len(self.starts)

    def frames(self, t: int) -> np.ndarray:
        """Frame indices of chunk ``t``."""
        return np.arange(self.starts[t], self.ends[t])

    def overlap_frames(self, t: int) -> np.ndarray:
        """Frames shared by chunks ``t`` and ``t + 1`` (``O`` frames)."""
        return np.arange(self.starts[t + 1], self.ends[t])

    def chunk_of(self, frame: int | np.ndarray) -> int | np.ndarray:
        """The last chunk that contains ``frame`` (later chunks win in overlaps); an array of
        frames gives the array of their chunks."""
        chunk = np.searchsorted(self.starts, frame, side="right") - 1
        return int(chunk) if np.ndim(chunk) == 0 else chunk


def chunk_schedule(n_frames: int, chunk_size: int = 75, overlap: int = 30) -> ChunkSchedule:
    """Chunk starts ``0, B-O, 2(B-O), ...`` up to the first chunk that reaches ``n_frames``.

    Raises:
        ValueError: ``n_frames < 1``, ``chunk_size < 2``, ``overlap < 1`` or ``overlap >= chunk_size``.
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    if chunk_size < 2:
        raise ValueError(f"chunk_size must be >= 2, got {chunk_size}")
    if not 1 <= overlap < chunk_size:
        raise ValueError(f"overlap must satisfy 1 <= overlap < chunk_size ({chunk_size}), got {overlap}")
    step = chunk_size - overlap
    starts = [0]
    while starts[-1] + chunk_size < n_frames:
        starts.append(starts[-1] + step)
    starts_arr = np.asarray(starts, dtype=np.int64)
    ends = np.minimum(starts_arr + chunk_size, n_frames)
    return ChunkSchedule(n_frames, chunk_size, overlap, starts_arr, ends)

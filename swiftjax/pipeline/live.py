"""``poses_live.jsonl``: every pose a live run published, and every revision of it.

One JSON object a line: ``{"frame": k, "time": t, "pose": [[r00, r01, r02, tx], [..], [..]],
"revision": r, "reason": ...}`` -- the camera-to-world top 3 x 4 (the unit and axes of
``poses_kitti.txt``).  ``revision`` counts the trajectory's revisions: a new frame's first pose
carries the current one (``reason`` ``"new"``); a loop closure (``"loop closure"``) and the
final pass (``"final"``) start the next revision and publish every frame again.

An append-only log: the lines of one chunk are written, flushed and fsync'd together
(:meth:`LiveLog.append`), so after a crash the file holds every complete chunk and at most one
half-written last line, which :func:`swiftjax.pipeline.reader.read_live_poses` ignores.

``loops_live.json``: the live loop candidates (:func:`write_loops`), rewritten atomically
each time the loop worker decides: ``{"revision": r, "loops": [{"i", "j", "score",
"chunk_i", "chunk_j", "accepted", "reason", "live_chunk"}, ...]}`` -- the hypotheses of the
prefix, which the final pass decides again (the manifest records the final ones).
"""

from __future__ import annotations

import json
import os
import pathlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from swiftjax.io.atomic import atomic_write

__all__ = ["LIVE_LOOPS_NAME", "LIVE_NAME", "LiveLog", "write_loops"]

LIVE_NAME = "poses_live.jsonl"
LIVE_LOOPS_NAME = "loops_live.json"
_LOOP_FIELDS = ("i", "j", "score", "chunk_i", "chunk_j", "accepted", "reason", "live_chunk")


class LiveLog:
    """The writer of ``run_dir/poses_live.jsonl`` (appends to what a previous session wrote)."""

    def __init__(self, run_dir: str | pathlib.Path) -> None:
        self.path = pathlib.Path(run_dir) / LIVE_NAME
        self.path.parent.mkdir(parents=True, exist_ok=True)
        _drop_partial_line(self.path)  # a crash's half-written last record
        self._file = open(self.path, "ab")

    def append(
        self, frames: Sequence[int], times: Sequence[float], cam_to_world: np.ndarray, revision: int, reason: str
    ) -> None:
        """One line per frame (``cam_to_world [F, 4, 4]``), then flush and fsync: one chunk's
        poses reach the disk together."""
        lines = [
            json.dumps(
                {
                    "frame": int(k),
                    "time": float(t),
                    "pose": np.asarray(P[:3], np.float64).tolist(),
                    "revision": int(revision),
                    "reason": reason,
                }
            )
            for k, t, P in zip(frames, times, cam_to_world)
        ]
        if not lines:
            return
        self._file.write(("\n".join(lines) + "\n").encode())
        self._file.flush()
        os.fsync(self._file.fileno())

    def close(self) -> None:
        self._file.close()


def write_loops(run_dir: str | pathlib.Path, candidates: Sequence[dict[str, Any]], revision: int) -> None:
    """``run_dir/loops_live.json`` (module docstring), atomically: every live candidate's
    record (its verdict as now) and the trajectory's revision."""

    def plain(v: Any) -> Any:
        return v.item() if isinstance(v, np.generic) else v

    loops = [{k: plain(r[k]) for k in _LOOP_FIELDS if k in r} for r in candidates]
    with atomic_write(pathlib.Path(run_dir) / LIVE_LOOPS_NAME) as f:
        json.dump({"revision": int(revision), "loops": loops}, f, indent=1)


def _drop_partial_line(path: pathlib.Path) -> None:
    """Cut ``path`` after its last newline (nothing when it ends with one or does not exist)."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    data = path.read_bytes()
    if not data.endswith(b"\n"):
        with open(path, "r+b") as f:
            f.truncate(data.rfind(b"\n") + 1)
            os.fsync(f.fileno())

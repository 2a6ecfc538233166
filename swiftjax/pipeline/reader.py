"""The run directory's reader: what a run recorded, for the viewer, the engine's callers and tests.

One place that knows how the records are laid out on disk (the run's writers are
:mod:`~swiftjax.pipeline.rundir`, :mod:`~swiftjax.pipeline.export` and
:mod:`~swiftjax.pipeline.live`): ``manifest.json`` (chunks, temporal edges, loop candidates),
``chunk_poses.json`` (the final ``S_t``), ``frames.txt`` and ``poses_live.jsonl``.  Every
reader tolerates a run being written: a missing file is None, a record not finished is left
out.  Errors name the file in one line (:class:`RunReadError`).
"""

from __future__ import annotations

import json
import pathlib
from typing import Any

import numpy as np

from swiftjax.errors import SwiftjaxError

__all__ = [
    "POSE_SETS",
    "RunReadError",
    "read_json",
    "read_manifest",
    "read_chunk_poses",
    "chained_prefix",
    "loop_candidates",
    "frame_names",
    "read_live_poses",
]

#: The pose sets of ``chunk_poses.json``: chunk-to-world ``S_t`` with and without loop closure.
POSE_SETS = ("loop closure", "no loop closure")


class RunReadError(SwiftjaxError, ValueError):
    """A run directory (or one of its records) cannot be read; the message names it."""


def read_json(path: pathlib.Path) -> Any:
    try:
        return json.loads(pathlib.Path(path).read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise RunReadError(f"{path} is unreadable ({err})") from None


def read_manifest(run_dir: str | pathlib.Path) -> dict[str, Any]:
    """The run's ``manifest.json``, or :class:`RunReadError` naming what is wrong with ``run_dir``."""
    run_dir = pathlib.Path(run_dir)
    if not run_dir.exists():
        raise RunReadError(f"run directory {run_dir} does not exist")
    if not run_dir.is_dir():
        raise RunReadError(f"{run_dir} is not a directory (give the run directory written by swiftjax)")
    path = run_dir / "manifest.json"
    if not path.is_file():
        raise RunReadError(
            f"{run_dir} is not a swiftjax run directory (no manifest.json; give the --out folder of "
            "'swiftjax reconstruct' or 'swiftjax demo')"
        )
    data = read_json(path)
    if not isinstance(data, dict) or not {"config", "chunks", "edges"} <= set(data):
        raise RunReadError(f"{path} is not a swiftjax manifest (no config/chunks/edges)")
    return data


def read_chunk_poses(run_dir: str | pathlib.Path) -> dict[str, np.ndarray] | None:
    """``{pose set: [T, 8]}`` of a finished run's ``chunk_poses.json`` (:data:`POSE_SETS`), or
    None before the export wrote it."""
    path = pathlib.Path(run_dir) / "chunk_poses.json"
    if not path.is_file():
        return None
    data = read_json(path)
    return {name: np.asarray(data[name], np.float64).reshape(-1, 8) for name in POSE_SETS if name in data}


def chained_prefix(manifest: dict[str, Any]) -> tuple[int, np.ndarray]:
    """``(k, relative [k-1, 8])``: the longest prefix ``0..k-1`` of finished chunks whose
    temporal edges are all recorded, and those edges (edge ``t`` maps chunk ``t+1`` into ``t``)."""
    done = {int(c) for c, ok in manifest["chunks"].items() if ok}
    k = 0
    while k in done and (k == 0 or str(k - 1) in manifest["edges"]):
        k += 1
    rel = np.array([manifest["edges"][str(t)]["S"] for t in range(k - 1)], np.float64).reshape(-1, 8)
    return k, rel


def loop_candidates(manifest: dict[str, Any]) -> list[tuple[int, int, bool]]:
    """``(i, j, accepted)`` of every loop candidate recorded in the manifest.

    ``manifest["loops"]``, when it is a list, holds every candidate's verdict (loop
    verification); it wins.  Otherwise the loop chunks' records in ``manifest["loop_edges"]``
    are the candidates, ``accepted`` defaulting to True there (a loop edge recorded before the
    verdicts are: the run is still in its loop stage).
    """
    out: dict[tuple[int, int], bool] = {}
    for r in (manifest.get("loop_edges") or {}).values():
        if isinstance(r, dict) and "i" in r and "j" in r:
            out[int(r["i"]), int(r["j"])] = bool(r.get("accepted", True))
    candidates = manifest.get("loops")
    if isinstance(candidates, list):
        for r in candidates:
            if isinstance(r, dict) and "i" in r and "j" in r:
                out[int(r["i"]), int(r["j"])] = bool(r.get("accepted", False))
    return [(i, j, a) for (i, j), a in sorted(out.items())]


def frame_names(run_dir: str | pathlib.Path) -> list[str] | None:
    """The image name of every frame (``frames.txt``), or None before the export wrote it."""
    path = pathlib.Path(run_dir) / "frames.txt"
    if not path.is_file():
        return None
    return [ln.split(maxsplit=1)[1] for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def read_live_poses(run_dir: str | pathlib.Path) -> list[dict[str, Any]]:
    """The records of ``poses_live.jsonl`` in file order (``pose`` as a ``[3, 4]`` array); a last
    line that is not a complete record (a crash mid-write) is ignored; none before the file
    exists."""
    path = pathlib.Path(run_dir) / "poses_live.jsonl"
    if not path.is_file():
        return []
    out = []
    lines = path.read_bytes().split(b"\n")
    for k, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            record["pose"] = np.asarray(record["pose"], np.float64).reshape(3, 4)
        except (ValueError, KeyError, TypeError):
            if k >= len(lines) - 2:  # the last line (the file ends with one newline): cut by a crash
                continue
            raise RunReadError(f"{path}: line {k + 1} is not a live pose record") from None
        out.append(record)
    return out

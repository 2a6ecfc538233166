"""The run directory's records: lock, fingerprints, manifest, resume records, stage clock.

A run directory is a promise: what it holds came from this input, this model and this
configuration, and re-running finishes the job without redoing or corrupting finished work.
:class:`RunLock` keeps one writer (``run_dir/.swiftjax.lock``, ``fcntl.flock``, naming its
holder); :func:`fingerprints` gives each stage's fingerprint (frames and weights by content,
the model, the preprocessing, the stage's options), which decides what a re-run keeps;
:class:`Manifest` and :class:`ChunkRecords` record every finished chunk with its edge (an edge
always from float32 data: a chunk's last ``overlap`` frames stay float32 as ``tail_<t>`` until
the next edge is recorded), :func:`chunk_binding` / :func:`check_binding` bind each chunk file
to its index, frames and fingerprint, :func:`record_outputs` lists what the last export
wrote, :func:`open_run` refuses a foreign directory and removes a killed run's temp files.
:class:`RunContext` is what every stage receives: the records, the chunk store, the schedule,
the configuration, the stage clock and the log.  Every rule, from the user's side: docs/cli.md,
"The run directory" and "How the run directory keeps its promise".
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import logging
import os
import pathlib
import re
import socket
import time
import zlib
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from swiftjax import _faults, chunks, options
from swiftjax.errors import SwiftjaxError
from swiftjax.io import chunk_store as _chunk_store
from swiftjax.io.atomic import atomic_write, temp_files
from swiftjax.io.chunk_store import ChunkStore
from swiftjax.pipeline.user_camera import UserCamera

if TYPE_CHECKING:
    from swiftjax.pipeline.config import PipelineConfig
    from swiftjax.pipeline.executors import Executor
    from swiftjax.pipeline.predictors import Predictor

__all__ = [
    "MANIFEST_VERSION",
    "LOCK_NAME",
    "RunDirError",
    "RunLock",
    "Manifest",
    "ChunkRecords",
    "StageTimer",
    "RunContext",
    "fingerprints",
    "forget_chunk",
    "open_run",
    "grow_run",
    "chunk_binding",
    "check_binding",
    "record_outputs",
    "prune",
    "TOP_FILES",
    "progress_bar",
]

logger = logging.getLogger(__name__)

MANIFEST_VERSION = 3  # 3: per-stage fingerprints, checksummed chunk files, exact-resume records
LOCK_NAME = ".swiftjax.lock"


class RunDirError(SwiftjaxError, RuntimeError):
    """The run directory belongs to a different input or configuration (or is unusable)."""


_OVERWRITE = "overwrite it (--overwrite) or choose another output directory"


# ----------------------------------------------------------------------------------- lock


class RunLock:
    """An advisory ``fcntl.flock`` on ``run_dir/.swiftjax.lock`` naming its holder.

    :meth:`acquire` refuses (:class:`RunDirError`, one line naming the holder's pid and host)
    while another process holds it.  The file is never deleted (deleting a lock file races
    with a process about to lock it); releasing empties it.
    """

    def __init__(self, run_dir: pathlib.Path) -> None:
        self.path = run_dir / LOCK_NAME
        self._fd: int | None = None
        self.previous: dict[str, Any] | None = None

    def acquire(self) -> RunLock:
        import fcntl

        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_holder(fd)
            os.close(fd)
            who = (
                f"pid {holder.get('pid')} on {holder.get('host')}, since {holder.get('since')}"
                if holder
                else "another process"
            )
            raise RunDirError(
                f"{self.path.parent} is in use by another swiftjax run ({who}; lock file {self.path}): "
                "wait for it to finish or choose another output directory"
            ) from None
        self.previous = _read_holder(fd) or None
        me = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "since": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(me) + "\n").encode(), 0)
        os.fsync(fd)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        import fcntl

        with contextlib.suppress(OSError):
            os.ftruncate(self._fd, 0)
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None


def _read_holder(fd: int) -> dict[str, Any]:
    try:
        data = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


# --------------------------------------------------------------------------- fingerprints


def _jsonable(x: Any) -> Any:
    return json.loads(json.dumps(x))


def fingerprints(predictor: Predictor, config: PipelineConfig, camera: Any = None) -> dict[str, Any]:
    """What determines each stage's stored result (see the module docstring), JSON-able.

    ``predictor.fingerprint()`` is a dict ``{"frames": [one item per frame] or None,
    **identity}`` (model, preprocessing, ...: everything else that determines a prediction).
    ``camera`` is the user camera's fingerprint (intrinsics values, mask files), part of the
    identity.
    """
    fp = predictor.fingerprint()
    if not isinstance(fp, dict):
        raise TypeError(
            f"{type(predictor).__name__}.fingerprint() must return a dict "
            f"{{'frames': [...] or None, **identity}}, got {type(fp).__name__}"
        )
    frames = fp.get("frames")
    identity = {k: v for k, v in fp.items() if k != "frames"}
    if camera:
        identity["camera"] = camera
    n = int(predictor.num_frames)
    if frames is not None and len(frames) != n:
        raise ValueError(f"the predictor's fingerprint lists {len(frames)} frames for {n}")
    out = {
        "frames": frames,
        "temporal": {
            "num_frames": n,
            "identity": identity,
            "options": config.stage_options("temporal"),
            "chunk_format": _chunk_store.FORMAT_VERSION,
        },
    }
    for stage in options.STAGES[1:]:
        out[stage] = {"options": config.stage_options(stage)}
    return _jsonable(out)


def _changed(old: Any, new: Any) -> list[str]:
    """Keys of two dicts whose values differ (sorted)."""
    if not isinstance(old, dict) or not isinstance(new, dict):
        return [] if old == new else ["(all)"]
    return sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))


def _without_count(temporal: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in temporal.items() if k != "num_frames"}


def _describe_identity_change(old: dict[str, Any], new: dict[str, Any]) -> str:
    parts = []
    if old.get("num_frames") != new.get("num_frames"):
        parts.append(f"input frames ({old.get('num_frames')} -> {new.get('num_frames')})")
    ident = _changed(old.get("identity"), new.get("identity"))
    for key in ident:
        o = (old.get("identity") or {}).get(key)
        n = (new.get("identity") or {}).get(key)
        if isinstance(o, list) and isinstance(n, list):  # [[name, value], ...] (the user camera's)
            o, n = ({str(x[0]): x for x in v if isinstance(x, list) and x} for v in (o, n))
        sub = _changed(o, n) if isinstance(o, dict) and isinstance(n, dict) else []
        label = "input camera" if key == "camera" else key
        parts.append(f"{label}" + (f" ({', '.join(sub)})" if sub and sub != ["(all)"] else ""))
    opts = _changed(old.get("options"), new.get("options"))
    if opts:
        parts.append("options " + ", ".join(opts))
    if old.get("chunk_format") != new.get("chunk_format"):
        parts.append(f"chunk file format ({old.get('chunk_format')} -> {new.get('chunk_format')})")
    return "; ".join(parts) or "fingerprint"


# ------------------------------------------------------------------------------- manifest


class Manifest:
    """``run_dir/manifest.json``: fingerprints, configuration and finished work.

    Keys: ``version``, ``fingerprint`` (:func:`fingerprints`), ``config`` (for information),
    ``chunks`` (``{t: true}``), ``edges`` (``{t-1: record}`` for edge ``(t-1, t)``),
    ``loop_edges`` (``{"i-j": record}``).
    """

    def __init__(self, path: pathlib.Path, data: dict[str, Any]) -> None:
        self.path = path
        self.data = data
        self.previous_names: list[str] | None = None  # the last run's frame names, when the count changed

    @classmethod
    def open(
        cls,
        run_dir: pathlib.Path,
        config: dict[str, Any],
        fingerprint: dict[str, Any],
        schedule: chunks.ChunkSchedule,
        overwrite: bool,
        log: Callable[[str], None] = logger.info,
    ) -> Manifest:
        path = run_dir / "manifest.json"
        fresh = {
            "version": MANIFEST_VERSION,
            "fingerprint": fingerprint,
            "config": config,
            "chunks": {},
            "edges": {},
            "loops": None,
            "loop_edges": {},
            "outputs": {},
        }
        if path.exists() and not overwrite:
            data = cls._read(path)
            data.setdefault("outputs", {})
            old = data["fingerprint"]
            count_only = (  # frames added or removed (e.g. a repaired image skipped before): reconciled below
                old.get("frames") is not None
                and fingerprint.get("frames") is not None
                and _without_count(old["temporal"]) == _without_count(fingerprint["temporal"])
            )
            if old["temporal"] != fingerprint["temporal"] and not count_only:
                what = _describe_identity_change(old["temporal"], fingerprint["temporal"])
                raise RunDirError(f"{run_dir} holds a run with a different {what}; {_OVERWRITE}")
            manifest = cls(path, data)
            manifest._check_records(log)
            manifest._reconcile_frames(old.get("frames"), fingerprint.get("frames"), schedule, log)
            if old.get("loops") != fingerprint["loops"]:
                changed = _changed((old.get("loops") or {}).get("options"), fingerprint["loops"]["options"])
                if data["loop_edges"]:
                    log(f"swiftjax: loop options changed ({', '.join(changed)}): the loop stage runs again")
                data["loop_edges"] = {}
                data["loops"] = None
            data["fingerprint"] = fingerprint
            data["config"] = config
            manifest.save()
            return manifest
        manifest = cls(path, fresh)
        manifest.save()
        return manifest

    @staticmethod
    def _read(path: pathlib.Path) -> dict[str, Any]:
        """The manifest's JSON, checked for shape; :class:`RunDirError` otherwise."""
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise RunDirError(f"{path} is unreadable ({err}); {_OVERWRITE}") from err
        if not isinstance(data, dict):
            raise RunDirError(
                f"{path} is not a swiftjax manifest (it holds a JSON {type(data).__name__}); {_OVERWRITE}"
            )
        if data.get("version") != MANIFEST_VERSION:
            raise RunDirError(
                f"{path} has manifest version {data.get('version')!r} (this swiftjax writes {MANIFEST_VERSION}); "
                f"{_OVERWRITE}"
            )
        shape = {"fingerprint": dict, "chunks": dict, "edges": dict, "loop_edges": dict}
        bad = [k for k, kind in shape.items() if not isinstance(data.get(k), kind)]
        fp = data.get("fingerprint")
        if not bad and not (isinstance(fp.get("temporal"), dict) and isinstance(fp.get("loops"), dict)):
            bad = ["fingerprint"]
        if bad:
            raise RunDirError(f"{path} is damaged (bad or missing {', '.join(bad)}); {_OVERWRITE}")
        return data

    def _reconcile_frames(
        self,
        old: list[Any] | None,
        new: list[Any] | None,
        schedule: chunks.ChunkSchedule,
        log: Callable[[str], None],
    ) -> None:
        """Forget the chunks (and edges) that hold input frames whose files changed."""
        if old == new:
            return
        if old is None or new is None:
            raise RunDirError(f"{self.path.parent} holds a run of different input frames; {_OVERWRITE}")
        if len(old) != len(new):
            self._reconcile_count(old, new, schedule, log)
            return
        changed = [k for k, (a, b) in enumerate(zip(old, new)) if a != b]
        hit = sorted({int(c) for k in changed for c in np.flatnonzero((schedule.starts <= k) & (k < schedule.ends))})
        # A re-predicted chunk's edges need its neighbours' float32 overlaps: predict them too.
        redo = sorted({c + d for c in hit for d in (-1, 0, 1) if 0 <= c + d < schedule.num_chunks})
        for c in redo:
            self.data["chunks"].pop(str(c), None)
        for c in hit:
            self.data["edges"].pop(str(c - 1), None)
            self.data["edges"].pop(str(c), None)
        self.data["loop_edges"] = {}  # the descriptors change
        self.data["loops"] = None
        names = ", ".join(str(new[k][0]) if isinstance(new[k], list) and new[k] else str(k) for k in changed[:5])
        more = f" and {len(changed) - 5} more" if len(changed) > 5 else ""
        log(
            f"swiftjax: {len(changed)} input frame(s) changed since the last run ({names}{more}): "
            f"predicting chunk(s) {', '.join(map(str, redo))} again"
        )

    def _reconcile_count(
        self,
        old: list[Any],
        new: list[Any],
        schedule: chunks.ChunkSchedule,
        log: Callable[[str], None],
    ) -> None:
        """Frames inserted or removed (``len(old) != len(new)``): the chunks before the first
        differing frame hold the same frames in both schedules (chunk starts do not depend on
        the frame count) and are kept; every later chunk, and the last kept one (its edge to
        the next needs its float32 overlap), is predicted again."""
        p = next((k for k, (a, b) in enumerate(zip(old, new)) if a != b), min(len(old), len(new)))
        prev = chunks.chunk_schedule(len(old), schedule.chunk_size, schedule.overlap)
        keep = 0  # chunks 0 .. keep-1 hold the same frames as before
        while (
            keep < min(prev.num_chunks, schedule.num_chunks)
            and schedule.ends[keep] <= p
            and prev.starts[keep] == schedule.starts[keep]
            and prev.ends[keep] == schedule.ends[keep]
        ):
            keep += 1
        reuse = keep - 1 if 0 < keep < schedule.num_chunks else keep
        data = self.data
        self.previous_names = [str(f[0]) for f in old if isinstance(f, list) and f]
        data["chunks"] = {k: v for k, v in data["chunks"].items() if int(k) < reuse}
        data["edges"] = {k: v for k, v in data["edges"].items() if int(k) + 1 < keep}
        data["loop_edges"] = {}  # the descriptors change
        data["loops"] = None
        redo = range(reuse, schedule.num_chunks)
        where = str(new[p][0]) if p < len(new) and isinstance(new[p], list) and new[p] else f"frame {p}"
        log(
            f"swiftjax: the input has {len(new)} frames instead of {len(old)} (first difference at {where}): "
            f"keeping chunk(s) 0-{reuse - 1}, predicting chunk(s) {redo.start}-{redo.stop - 1} again"
            if reuse
            else f"swiftjax: the input has {len(new)} frames instead of {len(old)} (first difference at {where}): "
            f"predicting every chunk again"
        )

    def _check_records(self, log: Callable[[str], None]) -> None:
        """Drop the edge records that fail their checksum (edited or damaged): a temporal edge
        ``(t-1, t)`` is computed again from chunks ``t-1`` and ``t`` predicted again (its float32
        overlap is gone), a loop edge by its loop chunk; each is reported."""
        data = self.data
        for key, record in list(data["edges"].items()):
            if not _record_ok(record):
                t = int(key) + 1
                data["edges"].pop(key)
                for c in (t - 1, t):
                    data["chunks"].pop(str(c), None)
                log(
                    f"swiftjax: {self.path}: the record of edge (chunks {t - 1}/{t}) fails its checksum (edited or "
                    f"damaged): predicting chunks {t - 1} and {t} again to compute it"
                )
        for key, record in list(data["loop_edges"].items()):
            if not _record_ok(record):
                data["loop_edges"].pop(key)
                log(
                    f"swiftjax: {self.path}: the record of loop edge {key} fails its checksum (edited or damaged): "
                    "predicting its loop chunk again"
                )

    #: :meth:`save_soon` writes at most this often (seconds).  Each write is a JSON dump and
    #: two fsyncs; an interrupted run redoes at most this much finished work.
    MIN_INTERVAL = 1.0

    _last_save = float("-inf")
    _unsaved = False

    def save(self) -> None:
        for group in ("edges", "loop_edges"):
            for record in self.data[group].values():
                _seal(record)
        with atomic_write(self.path) as f:
            json.dump(self.data, f, indent=1)
        self._last_save = time.monotonic()
        self._unsaved = False

    def save_soon(self) -> None:
        """Save if the last save is ``MIN_INTERVAL`` old, else at the next call or :meth:`flush`."""
        self._unsaved = True
        if time.monotonic() - self._last_save >= self.MIN_INTERVAL:
            self.save()

    def flush(self) -> None:
        """Save changes that :meth:`save_soon` held back."""
        if self._unsaved:
            self.save()


_CHECKSUM = "crc32"


def _record_crc(record: dict[str, Any]) -> str:
    body = json.dumps({k: v for k, v in record.items() if k != _CHECKSUM}, sort_keys=True)
    return f"{zlib.crc32(body.encode()):08x}"


def _seal(record: dict[str, Any]) -> None:
    """Set ``record["crc32"]``: the CRC32 of its canonical JSON (sorted keys) without it."""
    record[_CHECKSUM] = _record_crc(record)


def _record_ok(record: Any) -> bool:
    return isinstance(record, dict) and record.get(_CHECKSUM) == _record_crc(record)


def chunk_binding(manifest: Manifest, schedule: chunks.ChunkSchedule, t: int) -> dict[str, np.ndarray]:
    """What binds chunk ``t``'s file to this run (stored in it, checked on every resume:
    :func:`check_binding`): its index, its frames and ``fingerprint``, the SHA-256 of
    everything that determines its prediction -- the temporal fingerprint (model, options,
    preprocessing, chunk format; not the frame count) and the identities of its own frames."""
    import hashlib

    fp = manifest.data["fingerprint"]
    frames = schedule.frames(t)
    own = None if fp.get("frames") is None else [fp["frames"][int(k)] for k in frames]
    body = json.dumps([_without_count(fp["temporal"]), own], sort_keys=True)
    return {
        "chunk_index": np.asarray(t, np.int64),
        "frames": np.asarray(frames, np.int64),
        "fingerprint": np.asarray(hashlib.sha256(body.encode()).hexdigest()),
    }


def check_binding(store: ChunkStore, kind: str, t: int, want: dict[str, np.ndarray], rows: int | None) -> None:
    """:class:`~swiftjax.io.chunk_store.ChunkMismatchError` naming the file unless ``(kind, t)``
    holds chunk ``t`` of this run (:func:`chunk_binding`) with ``rows`` frames in its arrays."""
    path = store.path(kind, t)
    got = store.load_extra(kind, t, names=tuple(want))
    if set(got) != set(want):
        raise _chunk_store.ChunkMismatchError(
            path, "it records no chunk index, frames or fingerprint (not written by this run)"
        )
    if int(got["chunk_index"]) != t:
        raise _chunk_store.ChunkMismatchError(path, f"it holds chunk {int(got['chunk_index'])}, not chunk {t}")
    if not np.array_equal(got["frames"], want["frames"]):
        f = got["frames"]
        span = f"frames {int(f[0])}-{int(f[-1])} ({len(f)})" if len(f) else "no frames"
        raise _chunk_store.ChunkMismatchError(
            path,
            f"it holds {span}, chunk {t} is frames {int(want['frames'][0])}-{int(want['frames'][-1])} "
            f"({len(want['frames'])})",
        )
    if str(got["fingerprint"]) != str(want["fingerprint"]):
        raise _chunk_store.ChunkMismatchError(
            path, "it was predicted from another input, model or configuration (fingerprint differs)"
        )
    if rows is not None and rows != len(want["frames"]):
        raise _chunk_store.ChunkMismatchError(
            path, f"its arrays hold {rows} frames, chunk {t} has {len(want['frames'])}"
        )


class ChunkRecords:
    """The manifest's temporal records: finished chunks and edges ``(t-1, t)``.

    Chunk ``t`` counts as finished (:meth:`chunk_done`) when it is recorded *and*, for
    ``t > 0``, so is its edge ``(t-1, t)``: an edge enters the manifest once chunk ``t``'s
    file is complete (until then it waits in :attr:`pending_edges`), so a resumed run never
    pairs a stored edge with a re-predicted chunk.  Every record is saved (fsync'd) at once.
    """

    #: Room kept free beyond the estimate (outputs, manifest, temp files), bytes.
    SPACE_MARGIN = 64 << 20

    def __init__(self, manifest: Manifest, store: ChunkStore | None = None, num_chunks: int | None = None) -> None:
        self.manifest = manifest
        self.store = store
        self.num_chunks = num_chunks
        self.pending_edges: dict[int, dict[str, Any]] = {}
        self._space_checked = False

    def chunk_done(self, t: int) -> bool:
        data = self.manifest.data
        return bool(data["chunks"].get(str(t))) and (t == 0 or str(t - 1) in data["edges"])

    def edge(self, t: int) -> dict[str, Any] | None:
        """The recorded edge ``(t-1, t)``, or None."""
        return self.manifest.data["edges"].get(str(t - 1)) if t > 0 else None

    def commit(self, done: list[int]) -> bool:
        """Record the chunks whose files are complete (and their waiting edges), saved at once;
        True if any."""
        for c in done:
            self.manifest.data["chunks"][str(c)] = True
            if c in self.pending_edges:
                self.manifest.data["edges"][str(c - 1)] = self.pending_edges.pop(c)
        if done:
            self._saved(done)
            self._check_space(done[0])
        return bool(done)

    def _check_space(self, c: int) -> None:
        """After the first chunk file this run wrote: refuse to go on when the disk cannot hold
        the remaining chunks (estimated from the first chunk's file; sizes in
        docs/performance/io.md), before the disk fills up mid-way."""
        if self._space_checked or self.store is None or self.num_chunks is None:
            return
        self._space_checked = True
        import shutil

        per_chunk = sum(
            p.stat().st_size for p in (self.store.path("chunk", c), self.store.path("tail", c)) if p.exists()
        )
        remaining = sum(1 for t in range(self.num_chunks) if not self.manifest.data["chunks"].get(str(t)))
        need = per_chunk * remaining + self.SPACE_MARGIN
        free = shutil.disk_usage(self.store.root).free
        if free < need:
            raise RunDirError(
                f"not enough free space for {self.store.root}: the {remaining} remaining chunks need about "
                f"{need / 1e9:.2f} GB ({per_chunk / 1e6:.1f} MB each), {free / 1e9:.2f} GB are free "
                "(finished chunks are kept: free some space and re-run, or choose another output directory)"
            )

    def add_edge(self, t: int, edge: dict[str, Any]) -> bool:
        """Record edge ``(t-1, t)`` now if chunk ``t``'s file is recorded (returns True), else
        with the chunk."""
        if self.manifest.data["chunks"].get(str(t)):
            self.manifest.data["edges"][str(t - 1)] = edge
            self._saved([t])
            return True
        self.pending_edges[t] = edge
        return False

    def _saved(self, chunks_: list[int]) -> None:
        self.manifest.save()
        for c in chunks_:
            if self.chunk_done(c):
                _faults.point("chunk-recorded", c)
                if self.store is not None and c > 0:
                    self.store.remove("tail", c - 1)  # edge (c-1, c) is recorded: not needed


def forget_chunk(manifest: Manifest, store: ChunkStore, t: int) -> None:
    """Forget chunk ``t`` (its file is corrupt): it is predicted again on the next pass.  Its
    edges stay recorded (they were computed from its original prediction)."""
    manifest.data["chunks"].pop(str(t), None)
    store.remove("chunk", t)
    manifest.save()


class StageTimer:
    """Wall-clock time per stage, in a fixed display order (stages that did not run stay 0).

    ``with timer("align"): ...`` books the block's time to ``"align"``.  Blocks nest: time
    spent in an inner block is booked to the inner stage only (e.g. the loop chunks'
    predictions inside the loop-chunk stage), so every second counts once.
    """

    ORDER = (  # the pipeline's order: temporal chunks, loop closure, pose graph, scale, export
        "predict",
        "align",
        "chunk store",
        "loop detection",
        "predict (loop chunks)",
        "loop chunks",
        "loop verification",
        "pose graph",
        "metric scale",
        "export",
    )

    def __init__(self) -> None:
        self.seconds: dict[str, float] = dict.fromkeys(self.ORDER, 0.0)
        self._inner: list[float] = []  # per open block: seconds booked by blocks inside it

    @contextlib.contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        self._inner.append(0.0)
        try:
            yield
        finally:
            elapsed = time.perf_counter() - t0
            inner = self._inner.pop()
            self.seconds[name] = self.seconds.get(name, 0.0) + elapsed - inner
            if self._inner:
                self._inner[-1] += elapsed


def progress_bar(iterable: Iterable, enabled: bool, **kwargs: Any) -> Iterable:
    """``iterable`` wrapped in a tqdm bar when ``enabled`` (no bar over an empty sized one:
    "loop chunks: 0loop" says nothing)."""
    if not enabled or (hasattr(iterable, "__len__") and len(iterable) == 0):  # type: ignore[arg-type]
        return iterable
    from tqdm.auto import tqdm

    return tqdm(iterable, dynamic_ncols=True, **kwargs)


@dataclasses.dataclass
class RunContext:
    """What every stage receives: the run's records, store, schedule, configuration, clock and
    log.  Nothing a stage computes is stored here (a stage returns its result,
    :mod:`swiftjax.pipeline.results`).  Stages get predictions from ``executor.map(predictor,
    ...)``, never from the predictor directly."""

    run_dir: pathlib.Path
    config: PipelineConfig
    predictor: Predictor
    schedule: chunks.ChunkSchedule
    manifest: Manifest
    store: ChunkStore
    timer: StageTimer
    executor: Executor
    progress: bool = True
    log: Callable[[str], None] = logger.info
    camera: UserCamera | None = None
    lock: RunLock | None = None

    @property
    def num_frames(self) -> int:
        return self.schedule.n_frames

    def bar(self, iterable: Iterable, **kwargs: Any) -> Iterable:
        return progress_bar(iterable, self.progress, **kwargs)

    def close(self) -> None:
        """Release the run directory's lock."""
        if self.lock is not None:
            self.lock.release()
            self.lock = None


def _writable(path: pathlib.Path) -> bool:
    probe = path / ".swiftjax-write-test"
    try:
        probe.write_bytes(b"")
        probe.unlink()
        return True
    except OSError:
        return False


#: The files a run writes at the top of its directory (the outputs record lists what one run wrote).
TOP_FILES = (
    "manifest.json",
    "poses_kitti.txt",
    "poses_tum.txt",
    "intrinsics.txt",
    "points.ply",
    "loops.txt",
    "trajectory.png",
    "points.png",
    "metrics.json",
    "chunk_poses.json",
    "frames.txt",
    "ground_truth_kitti.txt",
)
_MODEL_FILES = tuple(f"{n}.{e}" for n in ("cameras", "images", "points3D") for e in ("bin", "txt"))
_TEMP = re.compile(r"^\.(.+)\.[A-Za-z0-9_]{8}\.tmp(\.[^.]*)?$")


def _own_names(
    run_dir: pathlib.Path, frame_names: Iterable[str], recorded: Iterable[str]
) -> dict[pathlib.Path, Callable[[str], bool]]:
    """The folders a run writes in and, for each, which file names are its own."""
    from swiftjax.io.colmap import image_names

    names = list(frame_names)
    recorded = list(recorded)
    frames = (
        set(names)
        | set(image_names(names))
        | {pathlib.PurePath(r).name for r in recorded if r.startswith("colmap/images/")}
    )
    top = set(TOP_FILES) | {r for r in recorded if "/" not in r}
    return {
        run_dir: top.__contains__,
        run_dir / "chunks": lambda n: ChunkStore.parse_name(n) is not None,
        run_dir / "colmap" / "images": frames.__contains__,
        run_dir / "colmap" / "sparse" / "0": set(_MODEL_FILES).__contains__,
    }


def _clean_temp_files(
    run_dir: pathlib.Path, own: dict[pathlib.Path, Callable[[str], bool]], log: Callable[[str], None]
) -> None:
    """Remove the temp files a killed run left: only temp names of this run's own files, in its
    own folders (:func:`_own_names`; called under the lock, after the run is validated)."""
    left = []
    for folder, ours in own.items():
        for p in temp_files(folder):
            m = _TEMP.match(p.name)
            if m and ours(m.group(1)):
                left.append(p)
    for p in left:
        with contextlib.suppress(OSError):
            p.unlink()
    if left:
        log(f"swiftjax: removed {len(left)} temp file(s) of an interrupted run in {run_dir}")


def _refuse_foreign(run_dir: pathlib.Path) -> None:
    """A non-empty ``--out`` must hold a swiftjax run (its ``manifest.json``): a user's folder is
    never written into (not even with ``--overwrite``, which deletes only what a run recorded)."""
    if (run_dir / "manifest.json").is_file():
        return
    allowed = {LOCK_NAME, ".swiftjax-write-test"}
    found = sorted(
        p.name
        for p in run_dir.iterdir()
        if p.name not in allowed and not (p.name == "chunks" and p.is_dir() and not any(p.iterdir()))
    )
    if found:
        shown = ", ".join(found[:3]) + (f" and {len(found) - 3} more" if len(found) > 3 else "")
        raise RunDirError(
            f"--out {run_dir} is not empty and holds no swiftjax run (no manifest.json; it holds {shown}): "
            "choose a new or empty directory (swiftjax writes only into its own run directories)"
        )


def _remove_recorded(run_dir: pathlib.Path, log: Callable[[str], None]) -> None:
    """``--overwrite``: delete what the previous run recorded (its outputs record) and the chunk
    store's files -- nothing else (a user's files beside them survive)."""
    try:
        old = json.loads((run_dir / "manifest.json").read_text())
    except (OSError, ValueError):
        old = None
    recorded = old.get("outputs") if isinstance(old, dict) and isinstance(old.get("outputs"), dict) else {}
    removed = _remove_files(run_dir, list(recorded))
    store = run_dir / "chunks"
    if store.is_dir():
        for p in store.iterdir():
            if ChunkStore.parse_name(p.name) is not None:
                p.unlink(missing_ok=True)
                removed += 1
    if removed:
        log(f"swiftjax: --overwrite: removed {removed} file(s) of the previous run in {run_dir}")


def _remove_files(run_dir: pathlib.Path, relpaths: Iterable[str]) -> int:
    """Delete ``run_dir/relpath`` for each (paths inside ``run_dir`` only), then the folders
    that became empty; returns how many files were deleted."""
    root = run_dir.resolve()
    count = 0
    parents: set[pathlib.Path] = set()
    for rel in relpaths:
        path = run_dir / rel
        if ".." in pathlib.PurePosixPath(rel).parts or not path.resolve().is_relative_to(root):
            continue
        if path.is_file() or path.is_symlink():
            path.unlink()
            count += 1
            parents.update(p for p in path.parents if p.resolve().is_relative_to(root) and p.resolve() != root)
    for folder in sorted(parents, key=lambda p: len(p.parts), reverse=True):
        with contextlib.suppress(OSError):
            folder.rmdir()  # only when empty
    return count


def record_outputs(ctx: RunContext, files: dict[str, str | None], final: bool) -> None:
    """The outputs record: ``manifest["outputs"]`` maps every file this run's export wrote
    (relative path) to what the export checks it with next time (the CRC32 of a COLMAP frame's
    bytes), else None: ``files``, as the export lists them
    (:func:`swiftjax.pipeline.export.output_files`).

    Called twice: with ``final=False`` just before the output set is renamed into place (the
    record then lists the previous run's files too, so a kill between the renames and the
    final record leaves nothing unaccounted for); with ``final=True`` after, which deletes
    what the previous run wrote and this one did not (a stale ``ground_truth_kitti.txt``,
    ``.txt`` model, frames of a longer input, the model after ``--no-colmap``) and records
    exactly this run's files."""
    run_dir = ctx.run_dir
    old: dict[str, Any] = dict(ctx.manifest.data.get("outputs") or {})
    new = dict(files)
    if not final:
        ctx.manifest.data["outputs"] = {**old, **new}
        ctx.manifest.save()
        return
    stale = sorted(set(old) - set(new) - {"manifest.json"})
    if stale:
        _remove_files(run_dir, stale)
        ctx.log(
            f"swiftjax: removed {len(stale)} output file(s) of the previous run that this run does not write "
            f"({', '.join(stale[:3])}{' ...' if len(stale) > 3 else ''})"
        )
    ctx.manifest.data["outputs"] = new
    ctx.manifest.save()


def prune(run_dir: pathlib.Path, log: Callable[[str], None] = logger.info) -> tuple[int, int]:
    """Shrink the chunk store of a finished run: drop every chunk file's depth and confidence
    maps (:meth:`~swiftjax.io.chunk_store.ChunkStore.drop_dense`; most of ``chunks/``) and the
    tail/loop files.  Every output stays; so do what a resume reads of a finished run
    (descriptors, poses, intrinsics, the export's points), so ``swiftjax view`` and re-runs
    with export-only or pose-graph options still predict nothing.  A re-run that needs the
    dense maps (changed loop options, changed frames, a corrupt chunk) predicts those chunks
    again.  Returns the store's ``(bytes before, bytes after)``."""
    if not (run_dir / "manifest.json").is_file():
        raise RunDirError(f"{run_dir} is not a swiftjax run directory (no manifest.json)")
    lock = RunLock(run_dir).acquire()
    try:
        data = Manifest._read(run_dir / "manifest.json")
        if not data.get("outputs"):
            raise RunDirError(
                f"{run_dir} holds an unfinished run (no outputs recorded): finish it first "
                "(re-run the same command), then prune it"
            )
        store = ChunkStore(run_dir)
        size = lambda: sum(p.stat().st_size for p in store.root.iterdir() if p.is_file())
        before = size()
        for kind in ("tail", "loop"):
            for t in store.indices(kind):
                store.remove(kind, t)
        chunk_files = store.indices("chunk")
        for t in chunk_files:
            store.drop_dense("chunk", t)
        after = size()
    finally:
        lock.release()
    log(
        f"swiftjax: {store.root}: {before / 1e6:.1f} MB -> {after / 1e6:.1f} MB (the depth and confidence maps of "
        f"{len(chunk_files)} chunk files dropped); every output is kept, and so is what 'swiftjax view' and a re-run "
        "with other export or pose-graph options read (they predict nothing); a re-run that needs the dense maps "
        "(other loop options, changed frames) predicts those chunks again, at the cost of their first prediction"
    )
    return before, after


def open_run(
    predictor: Predictor,
    run_dir: pathlib.Path,
    config: PipelineConfig,
    executor: Executor,
    *,
    overwrite: bool,
    progress: bool,
    log: Callable[[str], None],
) -> RunContext:
    """Create (or reopen, for a resume) ``run_dir``: lock it, clean it, check its fingerprints
    against ``predictor`` and ``config`` and open its records (the caller closes the context)."""
    if not str(run_dir).strip():
        raise RunDirError("the output directory is empty text: give a directory")
    if run_dir.exists() and not run_dir.is_dir():
        raise RunDirError(f"output directory {run_dir} exists and is not a directory")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RunDirError(f"cannot create output directory {run_dir}: {err.strerror}") from err
    _refuse_foreign(run_dir)
    if not _writable(run_dir):
        raise RunDirError(f"output directory {run_dir} is not writable")
    lock = RunLock(run_dir).acquire()
    try:
        if lock.previous and lock.previous.get("pid"):
            log(
                f"swiftjax: taking over the lock of an interrupted run (pid {lock.previous.get('pid')} on "
                f"{lock.previous.get('host')}, no longer running)"
            )
        schedule = chunks.chunk_schedule(int(predictor.num_frames), config.chunk_size, config.overlap)
        camera = UserCamera.from_config(config, predictor)  # validated before any work
        fp = fingerprints(predictor, config, camera.fingerprint())
        if overwrite:
            _remove_recorded(run_dir, log)
        manifest = Manifest.open(run_dir, config.to_dict(), fp, schedule, overwrite, log)
        # Validated: now the temp files a killed run left (this run's names in its folders only).
        _clean_temp_files(run_dir, _own_names(run_dir, predictor.frame_names(), manifest.data["outputs"]), log)
        store = ChunkStore(run_dir)
        if manifest.previous_names is not None:  # frames added or removed: drop the chunks nobody's now
            for kind in ("chunk", "tail"):  # (the export drops its frames: export.clean)
                for t in store.indices(kind):
                    if t >= schedule.num_chunks:
                        store.remove(kind, t)
    except BaseException:
        lock.release()
        raise
    return RunContext(
        run_dir=run_dir,
        config=config,
        predictor=predictor,
        schedule=schedule,
        manifest=manifest,
        store=store,
        timer=StageTimer(),
        executor=executor,
        progress=progress,
        log=log,
        camera=camera,
        lock=lock,
    )


def grow_run(ctx: RunContext) -> None:
    """A live run's input grew: ``ctx.predictor`` (a prefix of the input) now has more frames.

    The manifest's fingerprint is replaced by the grown input's and saved (the bindings of the
    new chunks name their frames: :func:`chunk_binding`), and ``ctx.schedule`` and
    ``ctx.camera`` (its mask files) cover the new frames; what is recorded stays recorded (the
    chunks of the shorter input are chunks of the longer one).  The run directory owns its
    schedule: this is the one place that changes a context's.

    Raises:
        RunDirError: the grown input is not the old one followed by new frames (same model,
            options and first frames).
    """
    predictor, config = ctx.predictor, ctx.config
    camera = UserCamera.from_config(config, predictor)
    fp = fingerprints(predictor, config, camera.fingerprint())
    old = ctx.manifest.data["fingerprint"]
    before, after = old.get("frames"), fp.get("frames")
    prefix = (before is None and after is None) or (
        before is not None and after is not None and after[: len(before)] == before
    )
    if _without_count(old["temporal"]) != _without_count(fp["temporal"]) or not prefix:
        raise RunDirError(f"{ctx.run_dir}: the live run's input changed while it grew (not only frames added)")
    ctx.manifest.data["fingerprint"] = fp
    ctx.manifest.save()
    ctx.schedule = chunks.chunk_schedule(int(predictor.num_frames), config.chunk_size, config.overlap)
    ctx.camera = camera

"""The run directory's records: manifest, input fingerprint, resume records, stage clock.

``run_dir/manifest.json`` records the configuration, the input fingerprint (the
predictor's :meth:`~swiftjax.pipeline.predictors.Predictor.fingerprint`) and every finished
chunk, edge and loop edge.  Re-running the same command skips finished work; a changed
input or configuration is refused (:class:`RunDirError`) unless ``overwrite=True``.  Every
file is written atomically (temp file + rename).

:class:`RunContext` is what every stage receives: the records above, the chunk store, the
schedule, the configuration, the stage clock and the log.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import pathlib
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from swiftjax import chunks
from swiftjax.io.atomic import atomic_write
from swiftjax.io.chunk_store import ChunkStore
from swiftjax.pipeline.user_camera import UserCamera

if TYPE_CHECKING:
    from swiftjax.pipeline.config import PipelineConfig
    from swiftjax.pipeline.executors import Executor
    from swiftjax.pipeline.predictors import Predictor

__all__ = [
    "MANIFEST_VERSION",
    "RunDirError",
    "Manifest",
    "ChunkRecords",
    "StageTimer",
    "RunContext",
    "open_run",
    "progress_bar",
]

MANIFEST_VERSION = 2  # 2: chunk files carry their chunk-frame export points


class RunDirError(RuntimeError):
    """The run directory belongs to a different input or configuration (or is unusable)."""


class Manifest:
    """``run_dir/manifest.json``: configuration, input fingerprint and finished work."""

    def __init__(self, path: pathlib.Path, data: dict[str, Any]) -> None:
        self.path = path
        self.data = data

    @classmethod
    def open(
        cls, run_dir: pathlib.Path, config: dict[str, Any], inputs: list[Any], overwrite: bool
    ) -> Manifest:
        path = run_dir / "manifest.json"
        fresh = {
            "version": MANIFEST_VERSION,
            "config": config,
            "inputs": inputs,
            "chunks": {},
            "edges": {},
            "loops": None,
            "loop_edges": {},
        }
        if path.exists() and not overwrite:
            try:
                data = json.loads(path.read_text())
            except (OSError, json.JSONDecodeError) as err:
                raise RunDirError(f"{path} is unreadable ({err}); overwrite it (--overwrite) to start afresh") from err
            if data.get("version") != MANIFEST_VERSION:
                raise RunDirError(f"{path} has manifest version {data.get('version')}; overwrite it (--overwrite)")
            if data.get("config") != config:
                changed = sorted(
                    k for k in set(config) | set(data.get("config", {}))
                    if config.get(k) != data.get("config", {}).get(k)
                )
                raise RunDirError(
                    f"{run_dir} holds a run with a different configuration ({', '.join(changed)}); "
                    "overwrite it (--overwrite) or choose another output directory"
                )
            if data.get("inputs") != json.loads(json.dumps(inputs)):
                raise RunDirError(
                    f"{run_dir} holds a run of different input frames (names, sizes or modification "
                    "times changed); overwrite it (--overwrite) or choose another output directory"
                )
            return cls(path, data)
        manifest = cls(path, fresh)
        manifest.save()
        return manifest

    #: :meth:`save_soon` writes at most this often (seconds).  Each write is a JSON dump and
    #: two fsyncs (~16 ms measured); an interrupted run redoes at most this much finished work.
    MIN_INTERVAL = 1.0

    _last_save = float("-inf")
    _unsaved = False

    def save(self) -> None:
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


class ChunkRecords:
    """The manifest's temporal records: finished chunks and edges ``(t-1, t)``.

    An edge ``(t-1, t)`` enters the manifest once chunk ``t``'s file is complete (a resumed
    run never pairs a stored edge with a re-predicted chunk): until then it waits in
    :attr:`pending_edges`.
    """

    def __init__(self, manifest: Manifest) -> None:
        self.manifest = manifest
        self.pending_edges: dict[int, dict[str, Any]] = {}

    def chunk_done(self, t: int) -> bool:
        return bool(self.manifest.data["chunks"].get(str(t)))

    def edge(self, t: int) -> dict[str, Any] | None:
        """The recorded edge ``(t-1, t)``, or None."""
        return self.manifest.data["edges"].get(str(t - 1)) if t > 0 else None

    def commit(self, done: list[int]) -> bool:
        """Record the chunks whose files are complete (and their waiting edges); True if any."""
        for c in done:
            self.manifest.data["chunks"][str(c)] = True
            if c in self.pending_edges:
                self.manifest.data["edges"][str(c - 1)] = self.pending_edges.pop(c)
        return bool(done)

    def add_edge(self, t: int, edge: dict[str, Any]) -> bool:
        """Record edge ``(t-1, t)`` now if chunk ``t`` is recorded (returns True), else later."""
        if self.chunk_done(t):
            self.manifest.data["edges"][str(t - 1)] = edge
            return True
        self.pending_edges[t] = edge
        return False


class StageTimer:
    """Wall-clock time per stage, in a fixed display order (stages that did not run stay 0).

    ``with timer("align"): ...`` books the block's time to ``"align"``.  Blocks nest: time
    spent in an inner block is booked to the inner stage only (e.g. the loop chunks'
    predictions inside the loop-chunk stage), so every second counts once.
    """

    ORDER = (
        "predict", "predict (loop chunks)", "align", "loop detection", "loop chunks", "pose graph",
        "chunk store", "export",
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
    """``iterable`` wrapped in a tqdm bar when ``enabled``."""
    if not enabled:
        return iterable
    from tqdm.auto import tqdm

    return tqdm(iterable, dynamic_ncols=True, **kwargs)


@dataclasses.dataclass
class RunContext:
    """What every stage receives.  Stages get predictions from ``executor.map(predictor,
    ...)``, never from the predictor directly.  ``K_ref`` (the first frame's intrinsics, the
    reference of the depth normalisation) is set by the temporal stage."""

    run_dir: pathlib.Path
    config: PipelineConfig
    predictor: Predictor
    schedule: chunks.ChunkSchedule
    manifest: Manifest
    store: ChunkStore
    timer: StageTimer
    executor: Executor
    progress: bool = True
    log: Callable[[str], None] = print
    K_ref: np.ndarray | None = None
    camera: UserCamera | None = None
    scale: dict[str, Any] | None = None  # the metric-scale step's record (unit, factor, votes)
    unit: str | None = None  # the world's unit once known ("metres" with --metric; export headers)

    @property
    def num_frames(self) -> int:
        return self.schedule.n_frames

    def bar(self, iterable: Iterable, **kwargs: Any) -> Iterable:
        return progress_bar(iterable, self.progress, **kwargs)


def _writable(path: pathlib.Path) -> bool:
    probe = path / ".swiftjax-write-test"
    try:
        probe.write_bytes(b"")
        probe.unlink()
        return True
    except OSError:
        return False


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
    """Create (or reopen, for a resume) ``run_dir`` and its records for ``predictor``'s frames."""
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RunDirError(f"cannot create output directory {run_dir}: {err.strerror}") from err
    if not _writable(run_dir):
        raise RunDirError(f"output directory {run_dir} is not writable")
    schedule = chunks.chunk_schedule(int(predictor.num_frames), config.chunk_size, config.overlap)
    camera = UserCamera.from_config(config, predictor)  # validated before any work
    manifest = Manifest.open(run_dir, config.to_dict(), predictor.fingerprint() + camera.fingerprint(), overwrite)
    return RunContext(
        run_dir=run_dir, config=config, predictor=predictor, schedule=schedule, manifest=manifest,
        store=ChunkStore(run_dir), timer=StageTimer(), executor=executor, progress=progress, log=log,
        camera=camera,
    )

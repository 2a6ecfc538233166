"""The live engine: a reconstruction fed frame by frame and polled for poses.

::

    rec = Reconstruction("runs/live", predictor, config)
    for image in camera:                      # or rec.add_frame() when the predictor knows its frames
        rec.add_frame(image, time=stamp)
        frames, cam_to_world = rec.poses()    # [F], [F, 4, 4]: every frame posed so far
    result = rec.finish()                     # the offline run of the same frames

The stages keep their state between chunks, on three threads besides the caller's
(:meth:`Reconstruction.add_frame` only counts the frame and, when it completes a chunk of the
offline schedule, ``n = B + k (B - O)``, queues chunk ``k``; it never waits):

1. **Predict thread**: chunk ``k`` alone is predicted as soon as its last frame was added --
   while the pose thread still aligns chunk ``k - 1`` (at 2 s per prediction on the demo the
   prediction and the geometry no longer add up within one chunk period).  At most one
   prediction waits for the pose thread (memory stays flat).  The model is one: the predictions
   of the live chunks and of the loop chunks take turns (:class:`Turns`), the live chunk's
   first, so a chunk's first poses wait for at most one loop-chunk prediction under way.
2. **Pose thread, temporal** (:class:`~swiftjax.pipeline.temporal.TemporalStage`): chunk
   ``k`` is stored (chunk file, manifest record: :func:`~swiftjax.pipeline.rundir.grow_run`
   extends the run's fingerprint and schedule to the ``n`` frames first) and aligned with chunk
   ``k - 1`` (the float32 overlap kept in memory since the last step): one edge ``R_{k-1}``.
   After chunk 0 the alignment is compiled for the run's shapes while chunk 1's frames arrive
   (:meth:`~swiftjax.pipeline.temporal.TemporalStage.warm_up`).
3. **Pose thread, first poses**: ``S_k = S_{k-1} R_{k-1}`` on the current chunk poses
   (:func:`~swiftjax.pipeline.graph.warm_start`), and the ``B - O`` new frames' camera-to-world
   ``S_k`` composed with their cameras in chunk ``k`` are appended to ``poses_live.jsonl`` at
   once (:mod:`~swiftjax.pipeline.live`, reason ``"new"``).  Before any loop closes these are
   the offline chain's poses (``chunk_poses_no_loops``), frame ``f`` in the chunk that first
   held it; the offline export poses the last ``O`` frames of each chunk in the next one.
4. **Loop worker**: the chunk's descriptors go to an
   :class:`~swiftjax.loops.online.OnlineLoopDetector` (whitening refitted on the prefix at a
   doubling schedule, or given; threshold calibrated on the prefix); its proposals between
   non-neighbouring chunks wait in a backlog.  The worker verifies one proposal at a time: its
   loop-centric chunk predicted and aligned, its verification numbers
   (:func:`~swiftjax.pipeline.loop_closure.loop_record`), then every live candidate decided
   again (:func:`~swiftjax.pipeline.loop_closure.decide`: PCM over all, the chain padded to a
   size bucket so that it compiles once per bucket) and the candidates with their verdicts
   written to ``loops_live.json`` (:func:`~swiftjax.pipeline.live.write_loops`, atomically).
   Between two proposals it takes the chunks queued meanwhile (all together: every chunk's
   descriptors fed, one proposal pass), and the next proposal is the most novel one: the
   farthest, in chunks at either end, from the loops accepted so far.  A revisit proposes a
   loop at nearly every chunk of it; once one is accepted its neighbours add little, so they
   wait while a new revisit goes first (those still waiting at the end are left to the final
   pass).
5. **Pose graph** (loop worker): only when the set of accepted loops changed, the graph over
   the chunks is solved, warm-started from the last solution
   (:func:`~swiftjax.pipeline.graph.run` with ``warm`` and a ``capacity`` that grows by
   doubling, so that the solve compiles once per doubling), and every frame is published again
   with the next revision (reason ``"loop closure"``), each in its offline owner chunk.

The live loop records are hypotheses of the prefix, not recorded in the manifest (the final
pass decides).  The live poses are in the first chunk's units, except under ``--metric
camera-height=H`` (metres: the median vote ``H / (h_t s_t)`` of the chunks posed so far, the
offline median rule on the prefix; a frame's first pose takes the factor of its step, a
revision the factor then) and ``--metric model`` (chunk 0's metres); ``--metric gt`` applies at
the final pass.  ``loop_geometry`` candidates come at the final pass only.

:meth:`Reconstruction.finish` keeps the offline guarantee.  When the input ends between two
chunk boundaries, the schedule's short last chunk ``[start, n)`` is first posed as one more
live step (its new frames' first poses, reason ``"new"``, before the final pass: otherwise up
to ``B - O - 1`` frames would wait for the whole final pass), stored as the offline run stores
its last chunk; when it ends on a boundary, the last live chunk (stored as a chunk with a
successor) is forgotten.  Then :func:`~swiftjax.pipeline.run.reconstruct` runs over every
frame in the same run directory, resuming every chunk the live steps stored ("frames added",
:mod:`~swiftjax.pipeline.rundir`).  The finished run directory is the offline
run's (plus ``poses_live.jsonl`` and ``loops_live.json``), and its poses are published once
more as the ``"final"`` revision.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import os
import pathlib
import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import chunks, metric_scale, sim3
from swiftjax.camera import world_cameras
from swiftjax.loops.descriptors import chunk_descriptors
from swiftjax.loops.online import OnlineLoopDetector
from swiftjax.loops.options import LoopOptions
from swiftjax.options import build
from swiftjax.pipeline import export, graph, loop_closure, rundir
from swiftjax.pipeline.config import PipelineConfig
from swiftjax.pipeline.executors import LocalExecutor
from swiftjax.pipeline.live import LiveLog, write_loops
from swiftjax.pipeline.results import GraphResult, LoopEdge, LoopResult, RunResult, TemporalResult
from swiftjax.pipeline.run import reconstruct
from swiftjax.pipeline.temporal import TemporalStage
from swiftjax.posegraph import chain_poses

__all__ = ["Prefix", "Reconstruction", "Turns"]


class Turns:
    """The one model's turns.  A prediction waits while another runs; the loop worker's
    (``urgent=False``) also waits while a live chunk's is waiting, and, once, for a live chunk
    due before it would end: when ``due`` (``time.monotonic()`` at which the next live chunk
    is expected complete, set by the engine) falls within ``cost`` seconds (the last live
    prediction's) from now, it lets that chunk go first.  So a chunk's first poses wait for a
    loop-chunk prediction only when there is no gap for it (the model busier than the
    chunk period), and a loop-chunk prediction waits for at most one live one.
    ``clock``: the time source (tests)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._cond = threading.Condition()
        self._busy = False
        self._urgent = 0  # urgent predictions waiting
        self._urgent_turns = 0  # urgent predictions done
        self.due: float | None = None
        self.cost = 0.0
        self.clock = clock

    def _gap_too_short(self) -> float | None:
        """Seconds until the next live chunk is due, when a prediction started now would still
        run then (else None)."""
        if self.due is None:
            return None
        left = self.due - self.clock()
        return left if 0 < left < self.cost else None

    @contextlib.contextmanager
    def turn(self, urgent: bool) -> Iterator[None]:
        with self._cond:
            self._urgent += urgent
            seen = self._urgent_turns
            try:
                while True:
                    if self._busy or (not urgent and self._urgent):
                        self._cond.wait()
                        continue
                    wait = None if urgent or self._urgent_turns > seen else self._gap_too_short()
                    if wait is None:
                        break
                    self._cond.wait(timeout=wait)  # the live chunk, due meanwhile, goes first
            finally:
                self._urgent -= urgent
            self._busy = True
        started = self.clock()
        try:
            yield
        finally:
            with self._cond:
                self._busy = False
                if urgent:
                    self._urgent_turns += 1
                    self.cost = self.clock() - started
                self._cond.notify_all()


class Prefix:
    """The first ``n`` frames of ``predictor`` as a predictor of their own.

    Its fingerprint lists the frames one by one (the predictor's own items, else its frame
    names), so that a run directory written for fewer frames is resumed as "frames added".
    Prefixes sharing ``turns`` (:class:`Turns`) predict one at a time, the ``urgent`` ones
    first."""

    def __init__(self, predictor: Any, n: int, *, turns: Turns | None = None, urgent: bool = True) -> None:
        if not 1 <= n <= int(predictor.num_frames):
            raise ValueError(f"a prefix of {n} frames of a predictor with {predictor.num_frames}")
        self.inner, self.num_frames = predictor, int(n)
        self._last_completed: float | None = None  # when the last chunk was completed
        self._appending = threading.Lock()  # predictor.append (caller) vs its fingerprint (pose thread)
        self._turns = Turns() if turns is None else turns
        self._urgent = urgent

    def grow(self, n: int) -> None:
        """Take the first ``n`` frames now (``n`` at least the current count)."""
        if not self.num_frames <= n <= int(self.inner.num_frames):
            raise ValueError(f"a prefix of {self.num_frames} frames grown to {n} of {self.inner.num_frames}")
        self.num_frames = int(n)

    def predict(self, frames: np.ndarray) -> Any:
        if len(frames) and int(np.max(frames)) >= self.num_frames:
            raise ValueError(f"frame {int(np.max(frames))} is not among the first {self.num_frames}")
        with self._turns.turn(self._urgent):
            return self.inner.predict(frames)

    def fingerprint(self) -> dict[str, Any]:
        fp = dict(self.inner.fingerprint())
        frames = fp.pop("frames", None)
        items = list(frames[: self.num_frames]) if frames is not None else [[name] for name in self.frame_names()]
        return {"frames": items, **fp}

    def frame_names(self) -> list[str]:
        return list(self.inner.frame_names())[: self.num_frames]

    def __getattr__(self, name: str) -> Any:  # images, source, mode, prefetch ...: the inner predictor's
        if name in ("inner", "_turns", "_urgent"):
            raise AttributeError(name)
        return getattr(self.inner, name)


class Reconstruction:
    """A run fed one frame at a time (see the module docstring).

    ``predictor``: the whole input's predictor; its frames become usable as they are added
    (``add_frame(image)`` hands the image to ``predictor.append`` for a predictor on a growing
    frame source; a predictor that knows its frames, e.g. the synthetic oracle, takes
    ``add_frame()``).  ``ground_truth [N, 4, 4]``: optional, for the final run's metrics.
    ``timestamps_note``: where the ``time`` given to :meth:`add_frame` comes from
    (``poses_tum.txt``'s header, as ``reconstruct``'s).  ``whitening``: the loop detector's
    whitening instead of the prefix's (:func:`swiftjax.loops.online.load_whitening`).

    Attributes:
        revision: the trajectory's revision (``poses_live.jsonl``).
        candidates: every live loop candidate's record, with its current verdict.
        steps: per live step, ``{"chunk", "frames", "completed_at", "posed_at"}``
            (``time.monotonic()`` when the chunk's last frame was added and when its new frames
            were published), ``"pose_s"`` (the difference), ``"queued_s"``, ``"predict_s"``,
            ``"geometry_s"`` (waiting for the predict thread, predicting, storing + aligning +
            posing), ``"metres_per_unit"``; once the loop worker has run loop detection on the
            chunk ``"loop_s"`` (its seconds), ``"loop_done_at"``, ``"proposals"`` (new ones),
            ``"batch"`` (chunks taken together), or ``"loop_batch"``: the chunk whose batch
            included it.
        verifications: per proposal verified live, in order: ``{"i", "j", "chunk_i",
            "chunk_j", "proposed_chunk", "chunks_posed"`` (the chunks its decision saw)``,
            "proposed_at", "started_at", "done_at"`` (``time.monotonic()``)``, "accepted",
            "solved"`` (the accepted set changed: a solve and a revision)``, "revision",
            "stages"}`` (seconds per stage: loop-chunk prediction, alignment, verification,
            decision, pose graph, revision; "numbers" and "decision" split "loop verification").
        metres_per_unit: the live metric factor (``--metric``), None: chunk 0's units.
        result: the final run (:meth:`finish`), else None.
    """

    def __init__(
        self,
        run_dir: str | pathlib.Path,
        predictor: Any,
        config: PipelineConfig = PipelineConfig(),
        *,
        ground_truth: np.ndarray | None = None,
        executor: Any = None,
        overwrite: bool = False,
        log: Callable[[str], None] = logging.getLogger(__name__).info,
        timestamps_note: str | None = None,
        whitening: Any = None,
        whitening_source: str | None = None,
    ) -> None:
        self.run_dir, self.predictor, self.config = pathlib.Path(run_dir), predictor, config
        self.ground_truth, self.executor, self.overwrite, self.log = ground_truth, executor, overwrite, log
        self.timestamps_note = timestamps_note
        self.num_frames = 0
        self.times: list[float] = []
        self._timed = False  # a time was given (else poses_tum.txt says: the frame index)
        self.revision = 0
        self.result: RunResult | None = None
        self.candidates: list[dict[str, Any]] = []
        self.steps: list[dict[str, Any]] = []
        self._whitening, self._whitening_source = whitening, whitening_source
        self._ctx: rundir.RunContext | None = None
        self._view: Prefix | None = None
        self._export: export.ChunkExport | None = None
        self._temporal: TemporalStage | None = None
        self._detector: OnlineLoopDetector | None = None
        self._relative = np.zeros((0, 8))  # [k, 8] the temporal edges so far
        self._edges: list[dict[str, Any]] = []  # their alignment records
        self._chunk_poses = np.zeros((0, 8))  # [k+1, 8] the live chunk-to-world poses
        self._extrinsic = np.zeros((0, 3, 4))  # [n, 3, 4] each frame's camera in its latest chunk
        self._cam_to_world = np.zeros((0, 4, 4))  # [n, 4, 4] as published
        self._heights: list[float] = []  # each live chunk's ground height (--metric camera-height), else NaN
        self.metres_per_unit: float | None = None  # the live metric factor (--metric), None: chunk 0's units
        self._graph: GraphResult | None = None  # the last pose-graph solution
        self._accepted: tuple[tuple[int, int], ...] = ()
        self._live: LiveLog | None = None
        self._starts: list[int] = []  # the live chunks' first frames
        self._lock = threading.Lock()  # the poses and poses_live.jsonl: the pose thread and the loop worker
        self._last_completed: float | None = None  # when the last chunk was completed
        self._appending = threading.Lock()  # predictor.append (caller) vs its fingerprint (pose thread)
        self._turns = Turns()  # the one model: the live chunks' predictions before the loop chunks'
        self._feed: Prefix | None = None  # the frames added so far, for the live chunks' predictions
        self._chunks: queue.Queue[Any] = queue.Queue()  # (t, n, completed at): for the predict thread
        self._predicted: queue.Queue[Any] = queue.Queue(maxsize=1)  # its predictions, for the pose thread
        self._jobs: queue.Queue[Any] = queue.Queue()  # the loop jobs, for the loop worker
        self._threads: list[threading.Thread] = []
        self._skip_loops = False  # finishing: the loop jobs still queued are dropped
        self._backlog: list[Any] = []  # (proposal, chunk that proposed it, when): not verified yet
        self._settled = threading.Event()  # set while the loop worker has no proposal waiting
        self._settled.set()
        self._state: Any = None  # (ctx, t, relative, edges) of the newest chunk the loop worker took
        self.verifications: list[dict[str, Any]] = []
        self._graph_warmed: set[int] = set()  # the capacities whose decision and solve were planned
        self._ended: bool | None = None  # end_of_input() called (True: the short last chunk queued)
        self._warm: queue.Queue[Any] = queue.Queue()  # the warm-up plans, for the warm-up thread
        self._stopping = False  # the threads are being stopped: no new warm-up
        self.warm_up_errors: list[str] = []  # the warm-up plans that failed (their work compiles when needed)
        self._worker_error: BaseException | None = None
        self._loop_timer = rundir.StageTimer()  # the loop worker's clock (a StageTimer is one thread's)

    @property
    def proposals_waiting(self) -> int:
        """Loop proposals the loop worker has not verified yet."""
        return len(self._backlog)

    @property
    def loops(self) -> list[dict[str, Any]]:
        """The live loop candidates accepted now (their records)."""
        return [r for r in self.candidates if r.get("accepted")]

    def add_frame(self, frame: Any = None, time: float | None = None) -> bool:
        """Add the next frame (``time``: seconds; default its index); True when it completed a
        chunk, whose prediction and first poses then follow on the pose threads (the caller
        never waits for them: :meth:`wait_for_poses` does)."""
        if self._ended is not None:
            raise ValueError(f"frame {self.num_frames} added after the end of the input (end_of_input())")
        if frame is not None:
            append = getattr(self.predictor, "append", None)
            if append is None:
                raise TypeError(f"{type(self.predictor).__name__} takes no frames (no append()); call add_frame()")
            with self._appending:
                append(frame)
        self._raise_worker_error()
        if self.num_frames >= int(self.predictor.num_frames):
            raise ValueError(f"frame {self.num_frames} added, but the predictor has {self.predictor.num_frames} frames")
        self.num_frames += 1
        self.times.append(float(self.num_frames - 1) if time is None else float(time))
        self._timed |= time is not None
        B, O = self.config.chunk_size, self.config.overlap
        n = self.num_frames
        if n < B or (n - B) % (B - O):
            return False
        if self._feed is None:
            self._feed = Prefix(self.predictor, n, turns=self._turns, urgent=True)
        else:
            self._feed.grow(n)
        self._start_threads()
        now = _now()
        if self._last_completed is not None:  # the next chunk is due one chunk period later
            self._turns.due = now + (now - self._last_completed)
        self._last_completed = now
        self._chunks.put(((n - B) // (B - O), n, now))
        return True

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """``(frames [F], cam_to_world [F, 4, 4])`` of every frame posed so far (latest revision).
        Never waits for the pose threads (the trajectory is replaced, never changed in place)."""
        cam_to_world = self._cam_to_world
        return np.arange(len(cam_to_world)), cam_to_world.copy()

    def wait_for_poses(self) -> None:
        """Wait until every chunk completed so far is predicted and its first poses published;
        re-raises a pose thread's error."""
        self._chunks.join()
        self._predicted.join()
        self._raise_worker_error()

    def wait_for_loops(self) -> None:
        """Wait until the loop worker has done every chunk added so far (its revision, if any,
        published); re-raises its error."""
        self.wait_for_poses()
        self._jobs.join()
        self._settled.wait()
        self._raise_worker_error()

    def finish(self) -> RunResult:
        """The final pass: the offline run of every frame added; its poses published as the
        ``"final"`` revision.  The chunks completed are posed first; loop work still pending
        is dropped (the final pass decides the loops)."""
        if self.num_frames == 0:
            raise ValueError("no frame was added: nothing to reconstruct")
        n = self.num_frames
        try:
            tail = self.end_of_input()
            self._stop_threads(skip_loops=True)
            self._raise_worker_error()
            live = self._ctx is not None
            if self._ctx is not None and self._temporal is not None:
                self._temporal.finish(drop_tails=False)
                if not tail:
                    # The last live chunk was stored as one with a successor (its frames up to
                    # the next start, a float32 tail), yet the input ends with it: the final
                    # pass predicts it again as the schedule's last chunk.
                    rundir.forget_chunk(self._ctx.manifest, self._ctx.store, len(self._chunk_poses) - 1)
            self._close_stages()
            gt = None if self.ground_truth is None else np.asarray(self.ground_truth)[:n]
            result = reconstruct(
                Prefix(self.predictor, n),
                self.run_dir,
                self.config,
                ground_truth=gt,
                overwrite=self.overwrite and not live,
                progress=False,
                timestamps=self.times if self._timed else None,
                timestamps_note=self.timestamps_note,
                log=self.log,
                executor=self.executor,
            )
            self.result = result
            self.revision += 1
            self._publish(range(n), result.cam_to_world, "final")
            self._cam_to_world = result.cam_to_world
        finally:
            self.close()
        return result

    def end_of_input(self) -> bool:
        """No more frames (:meth:`finish` calls it; the caller may call it earlier, when the
        drive ends, and finish later).  When the input ends between two chunk boundaries
        (``n != B + k (B - O)``), the schedule's short last chunk ``[start, n)`` (fewer than
        ``B`` frames) is queued as a live chunk, so that its new frames get their first poses
        now, on the pose threads, rather than from the final pass.  It is stored as the offline
        run stores its last chunk (all its frames, no float32 tail), so the final pass resumes
        it and every live chunk before it.  True when the short chunk is (or was) queued.
        :meth:`add_frame` raises afterwards."""
        if self._ended is not None:
            return self._ended
        B, O = self.config.chunk_size, self.config.overlap
        n = self.num_frames
        self._ended = False
        if n == 0 or self._worker_error is not None or (n >= B and (n - B) % (B - O) == 0):
            return False  # (the last chunk was queued by add_frame)
        self._ended = True
        if self._feed is None:
            self._feed = Prefix(self.predictor, n, turns=self._turns, urgent=True)
        else:
            self._feed.grow(n)
        self._start_threads()
        self._chunks.put((chunks.chunk_schedule(n, B, O).num_chunks - 1, n, _now()))
        return True

    def close(self) -> None:
        """Stop the live stages and release the run directory (what is recorded stays: the same
        command resumes it); :meth:`finish` calls it.  The chunks completed are posed first."""
        self._stop_threads(skip_loops=True)
        self._close_stages()
        if self._live is not None:
            self._live.close()
            self._live = None

    def _close_stages(self) -> None:
        temporal, chunk_export, ctx = self._temporal, self._export, self._ctx
        self._temporal = self._export = self._ctx = None
        try:
            if temporal is not None:
                temporal.close()
        finally:
            try:
                if chunk_export is not None:
                    chunk_export.close()
            finally:
                if ctx is not None:
                    ctx.close()

    def _open(self, n: int) -> rundir.RunContext:
        """The run directory for the first ``n`` frames (created, or resumed as "frames added")."""
        self._view = Prefix(self.predictor, n, turns=self._turns, urgent=False)  # the loop chunks'
        executor = self.executor if self.executor is not None else LocalExecutor()
        ctx = rundir.open_run(
            self._view, self.run_dir, self.config, executor, overwrite=self.overwrite, progress=False, log=self.log
        )
        try:
            export.clean(ctx)
            export.check(ctx)
            self._export = export.ChunkExport(ctx)
            self._temporal = TemporalStage(ctx, self._export)
        except BaseException:
            ctx.close()
            raise
        self._ctx = ctx
        if self.config.loop_closure:
            self._detector = OnlineLoopDetector(
                build(LoopOptions, self.config),
                whitening=self._whitening,
                whitening_source=self._whitening_source,
            )
        if self._live is None:
            self._live = LiveLog(self.run_dir)
        return ctx

    # ------------------------------------------------------------------ the threads

    def _start_threads(self) -> None:
        if self._threads:
            return
        for target, name in (
            (self._predict_chunks, "swiftjax-live-predict"),
            (self._pose_chunks, "swiftjax-live-poses"),
            (self._work, "swiftjax-live-loops"),
            (self._warm_ups, "swiftjax-live-warm-up"),
        ):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def _stop_threads(self, skip_loops: bool) -> None:
        """Every chunk completed predicted and posed, then the loop worker stopped (its jobs
        still queued dropped when ``skip_loops``); the threads joined."""
        threads, self._threads = self._threads, []
        if not threads:
            return
        self._stopping = True
        predict, pose, loops, warm = threads
        self._chunks.put(None)
        predict.join()
        self._predicted.put(None)
        pose.join()
        self._skip_loops = skip_loops
        self._jobs.put(None)
        loops.join()
        self._skip_loops = False
        with contextlib.suppress(queue.Empty):  # the plans not started: dropped
            while True:
                self._warm.get_nowait()
                self._warm.task_done()
        self._warm.put(None)
        warm.join()  # (a compile under way ends first)
        self._stopping = False

    def _predict_chunks(self) -> None:
        """The predict thread: each completed chunk predicted as soon as it is complete (while
        the pose thread aligns the one before), handed to the pose thread, until ``None``."""
        while (item := self._chunks.get()) is not None:
            try:
                if self._worker_error is None:  # (failed: drain without work)
                    t, n, completed = item
                    B, O = self.config.chunk_size, self.config.overlap
                    frames = np.arange(t * (B - O), min(t * (B - O) + B, n))  # (the last: short)
                    executor = self.executor if self.executor is not None else LocalExecutor(prefetch=0)
                    started = _now()
                    stream = executor.map(self._feed, [frames], chunk_descriptors)
                    try:
                        pred = next(stream)
                    finally:
                        stream.close()
                    self._predicted.put((t, n, frames, pred, completed, started, _now()))
            except BaseException as err:  # re-raised in the caller's thread
                self._worker_error = self._worker_error or err
            finally:
                self._chunks.task_done()
        self._chunks.task_done()

    def _pose_chunks(self) -> None:
        """The pose thread: each predicted chunk stored, aligned and posed (:meth:`_step`), in
        order, until ``None``."""
        while (item := self._predicted.get()) is not None:
            try:
                if self._worker_error is None:
                    self._step(*item)
            except BaseException as err:
                self._worker_error = self._worker_error or err
            finally:
                self._predicted.task_done()
        self._predicted.task_done()

    def _step(
        self, t: int, n: int, frames: np.ndarray, pred: Any, completed: float, predict_start: float, predicted: float
    ) -> None:
        """Chunk ``t`` (the first ``n`` frames) predicted: the stages of the module docstring."""
        started = _now()
        with self._appending:  # the fingerprint reads the predictor's frame list: not while it grows
            if self._ctx is None:
                ctx = self._open(n)
            else:
                ctx = self._ctx
                assert self._view is not None
                self._view.grow(n)
                rundir.grow_run(ctx)
        assert self._temporal is not None
        assert np.array_equal(frames, ctx.schedule.frames(t))
        if ctx.manifest.data["chunks"].get(str(t)):  # a resumed run's: stored as that run's schedule said
            rundir.forget_chunk(ctx.manifest, ctx.store, t)
        extrinsic = np.asarray(pred.extrinsic, np.float64)
        last = len(frames) < self.config.chunk_size  # the input's short last chunk (finish())
        chunk = self._temporal.add(t, pred, last=last)
        del pred

        # First poses: the chunk's pose chained on the current ones, its new frames published.
        with self._lock:
            if chunk.edge is None:
                self._chunk_poses = chain_poses(np.zeros((0, 8)))
            else:
                self._relative = np.concatenate([self._relative, chunk.edge.S[None]])
                self._edges.append(chunk.edge.record)
                self._chunk_poses = graph.warm_start(self._chunk_poses, self._relative)
            self._starts.append(int(frames[0]))
            old = len(self._cam_to_world)
            grown = np.zeros((n, 3, 4))
            grown[:old] = self._extrinsic
            grown[frames] = extrinsic  # the later chunk's camera (the offline owner)
            self._extrinsic = grown
            height = chunk.ground_height
            self._heights.append(float("nan") if height is None else float(height))
            self.metres_per_unit = self._metric_factor()
            new = _scaled(_world(self._chunk_poses[t][None], extrinsic[old - int(frames[0]) :]), self.metres_per_unit)
            self._publish(range(old, n), new, "new")
            self._cam_to_world = np.concatenate([self._cam_to_world, new])
            posed = _now()
            self.steps.append(
                {
                    "chunk": t,
                    "frames": n,
                    "completed_at": completed,
                    "posed_at": posed,
                    "pose_s": posed - completed,
                    "queued_s": predict_start - completed,
                    "predict_s": predicted - predict_start,
                    "geometry_s": posed - started,
                    "metres_per_unit": self.metres_per_unit,
                }
            )

        if t == 0 and not last:  # chunk 1's alignment compiled now, while its frames arrive
            self._temporal.warm_up()
        if self._detector is not None:  # the loop work of this chunk, on the loop worker
            self._temporal.flush()  # the loop chunks read the chunk files
            snapshot = dataclasses.replace(ctx, timer=self._loop_timer)  # this step's schedule and camera
            self._jobs.put((snapshot, t, frames, chunk.descriptors, self._relative.copy(), list(self._edges)))

    def _work(self) -> None:
        """The loop worker, until ``None``: the chunk jobs queued are taken together
        (:meth:`_detect`: the detector fed every chunk, one proposal pass), then one proposal
        is verified (:meth:`_verify_next`: the most novel), and so on -- the queue is looked at
        again between two proposals, so a new chunk's proposals (a new revisit) never wait
        behind a backlog of proposals near a loop already closed."""
        while True:
            batch: list[Any] = []
            try:
                batch.append(self._jobs.get(block=not self._backlog))
            except queue.Empty:
                pass
            while batch and batch[-1] is not None:
                try:
                    batch.append(self._jobs.get_nowait())
                except queue.Empty:
                    break
            stop = bool(batch) and batch[-1] is None
            jobs = [job for job in batch if job is not None]
            try:
                if jobs and self._worker_error is None and not (stop and self._skip_loops):
                    self._detect(jobs)
                if self._backlog and not stop and self._worker_error is None:
                    self._verify_next()
                if jobs and not stop and self._worker_error is None:
                    self._plan_warm_up()
            except BaseException as err:  # re-raised in the caller's thread
                self._worker_error = self._worker_error or err
            finally:
                if stop or self._worker_error is not None:
                    self._backlog = []  # (the final pass decides the loops)
                if not self._backlog:
                    self._settled.set()
                for _ in batch:
                    self._jobs.task_done()
            if stop:
                return

    def _detect(self, jobs: list[tuple[Any, ...]]) -> None:
        """The chunks of ``jobs`` (each ``(ctx, t, frames, descriptors, relative [t, 8],
        edges)``: the run as of chunk ``t``, in order) fed to the loop detector, one proposal
        pass for them all; the proposals between non-neighbouring chunks join the backlog, and
        the newest job's run is the one the next decisions and solves see."""
        started = _now()
        assert self._detector is not None
        ctx, t, _, _, relative, edges = jobs[-1]
        with ctx.timer("loop detection"):
            for k, (_, _, frames, descriptors, _, _) in enumerate(jobs):
                found = self._detector.add(frames, descriptors, propose=k + 1 == len(jobs))
        found = [lp for lp in found if abs(lp.chunk_i - lp.chunk_j) >= 2]  # not a temporal edge's
        self._state = (ctx, t, relative, edges)
        if found:
            self._settled.clear()
            self._backlog += [(lp, t, started) for lp in found]
        with self._lock:
            for _, c, *_ in jobs[:-1]:
                self.steps[c].update(loop_batch=t)
            self.steps[t].update(loop_s=_now() - started, loop_done_at=_now(), proposals=len(found), batch=len(jobs))

    def _plan_warm_up(self) -> None:
        """After each detection: the programs the loop work will need next, queued to be
        compiled ahead on the warm-up thread (:meth:`_warm_ups`), so that no decision compiles
        when a revisit comes: the detector's next growth
        (:meth:`~swiftjax.loops.online.OnlineLoopDetector.warm_plan`), the decision and the
        pose graph of the current capacity and, once the chunks fill a quarter of it, of the
        next (:meth:`_warm_graph`).  Each once."""
        if self._detector is not None:
            while (plan := self._detector.warm_plan()) is not None:
                self._warm.put(plan)
        if self._state is None or self.config.loop_verification == "none":
            return
        T = len(self._state[2]) + 1
        C = _capacity(T)[1]
        for cap in (C, 2 * C) if 4 * T > C else (C,):
            if cap not in self._graph_warmed and T >= 4:
                self._graph_warmed.add(cap)
                assert self._temporal is not None and self._temporal.K_ref is not None
                self._warm.put(functools.partial(self._warm_graph, cap, self._state, self._temporal.K_ref))

    def _warm_ups(self) -> None:
        """The warm-up thread (at a lower OS priority where the system allows): each queued
        plan run when no live chunk is being predicted or posed, until ``None``; a plan that fails is logged and skipped (the work it stood
        for compiles when it is needed)."""
        with contextlib.suppress(OSError, AttributeError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), _WARM_UP_NICENESS)
        while (plan := self._warm.get()) is not None:
            try:
                # the live chunks first: a plan starts only while none is being predicted or posed
                while (self._chunks.unfinished_tasks or self._predicted.unfinished_tasks) and not self._stopping:
                    time.sleep(_WARM_UP_POLL_S)
                if not self._stopping:
                    plan()
            except Exception as err:  # an ahead-of-time compile: nothing depends on it
                self.warm_up_errors.append(repr(err))
                logging.getLogger(__name__).debug(f"live warm-up skipped: {err!r}")
            finally:
                self._warm.task_done()
        self._warm.task_done()

    def _warm_graph(self, capacity: int, state: tuple[Any, ...], K_ref: np.ndarray) -> None:
        """Decide two made-up loops, ``(T-1, 0)`` and ``(T-1, 1)`` nearly consistent with the chain,
        and solve the graph with them, at ``capacity`` chunks (:func:`_capacity`): the programs
        of every later decision and solve of that capacity compile now.  Nothing is kept or
        published; the run's timer and log see nothing."""
        ctx, _, relative, edges = state
        quiet = dataclasses.replace(ctx, timer=rundir.StageTimer(), log=lambda s: None)
        chain = chain_poses(relative)
        T = len(chain)
        records = []
        with jax.enable_x64(True):
            for ci, cj in ((T - 1, 0), (T - 1, 1)):
                Z = np.array(sim3.compose(sim3.inverse(jnp.asarray(chain[cj])), jnp.asarray(chain[ci])), np.float64)
                Z[:3] *= 1.01  # (not exactly consistent: the solver iterates, its every program compiles)
                stats = edges[-1]
                records.append(
                    {
                        "i": ci, "j": cj, "chunk_i": ci, "chunk_j": cj, "Z": Z.tolist(), "align_i": stats,
                        "align_j": stats, "quality_valid": True, "quality_min_fraction": 1.0,
                        "dense_agreement": 1.0, "dense_overlap": 1.0,
                    }
                )  # fmt: skip
        loop_closure.decide(quiet, relative, records, rows=capacity - 1)
        loop_edges = [LoopEdge(r["chunk_j"], r["chunk_i"], np.asarray(r["Z"])) for r in records]
        for r in records:
            r["accepted"] = True
        temporal = TemporalResult(np.zeros((0, 0), np.float32), relative, edges, K_ref)
        graph.run(
            quiet, temporal, LoopResult(records, loop_edges), scale_priors=False, capacity=(capacity - 1, capacity)
        )

    def _next_proposal(self) -> tuple[Any, int, float]:
        """The backlog's most novel proposal, removed from it: the farthest, in chunks at
        either end (``max(|c_i - a_i|, |c_j - a_j|)``), from every loop accepted so far, the
        newest first among equals.  A revisit proposes a loop at nearly every chunk of it; once
        one of them is accepted, its neighbours add little, and they wait until nothing more
        novel does (those still waiting when the drive ends are left to the final pass)."""
        anchors = [(int(r["chunk_i"]), int(r["chunk_j"])) for r in self.candidates if r.get("accepted")]

        def novelty(item: tuple[Any, int, float]) -> tuple[int, int]:
            lp = item[0]
            near = min((max(abs(lp.chunk_i - a), abs(lp.chunk_j - b)) for a, b in anchors), default=1 << 30)
            return near, lp.i

        best = max(self._backlog, key=novelty)
        self._backlog.remove(best)
        return best

    def _verify_next(self) -> None:
        """One proposal (:meth:`_next_proposal`): its loop chunk predicted and aligned, its
        verification numbers, every live candidate decided again and, when the accepted set
        changed, the pose graph over the chunks of the newest job and a revision; a record
        of it appended to :attr:`verifications`."""
        started = _now()
        booked = dict(self._loop_timer.seconds)
        lp, t_proposed, proposed_at = self._next_proposal()
        ctx, t, relative, edges = self._state
        assert self._temporal is not None and self._temporal.K_ref is not None
        K_ref = self._temporal.K_ref
        stream = ctx.executor.map(ctx.predictor, [lp.frames], loop_closure.without_tokens)
        try:
            with ctx.timer("loop chunks"):
                with ctx.timer("predict (loop chunks)"):
                    pred = next(stream)
                record = loop_closure.loop_record(ctx, lp, pred, K_ref)
                del pred
        finally:
            stream.close()
        numbers_started = _now()
        if loop_closure.needs_numbers(self.config, record):
            record.update(loop_closure.verification_numbers(ctx, lp, record, K_ref))
        numbers_s = _now() - numbers_started
        record["source"] = "tokens"
        record["live_chunk"] = t_proposed
        self.candidates.append(record)
        decide_started = _now()
        loop_closure.decide(ctx, relative, self.candidates, rows=_capacity(len(relative) + 1, 0)[0])
        decide_s = _now() - decide_started
        accepted = [r for r in self.candidates if r["accepted"]]
        key = tuple((int(r["i"]), int(r["j"])) for r in accepted)
        solved = key != self._accepted
        if solved:
            self._accepted = key
            self._solve(ctx, accepted, relative, edges, K_ref)
        write_loops(self.run_dir, self.candidates, self.revision)
        stages = {
            k: round(v - booked.get(k, 0.0), 4) for k, v in self._loop_timer.seconds.items() if v > booked.get(k, 0.0)
        }
        stages.update(numbers=round(numbers_s, 4), decision=round(decide_s, 4))  # (both "loop verification")
        self.verifications.append(
            {
                "i": lp.i,
                "j": lp.j,
                "chunk_i": lp.chunk_i,
                "chunk_j": lp.chunk_j,
                "proposed_chunk": t_proposed,
                "chunks_posed": t + 1,
                "proposed_at": proposed_at,
                "started_at": started,
                "done_at": _now(),
                "accepted": bool(record["accepted"]),
                "solved": solved,
                "revision": self.revision,
                "stages": stages,
            }
        )

    def _raise_worker_error(self) -> None:
        if self._worker_error is not None:
            err, self._worker_error = self._worker_error, None
            raise err

    def _solve(
        self,
        ctx: rundir.RunContext,
        accepted: list[dict[str, Any]],
        relative: np.ndarray,
        edges: list[dict[str, Any]],
        K_ref: np.ndarray,
    ) -> None:
        """The pose graph over the chunks of ``relative`` with the ``accepted`` loops, warm-started
        from the last solution; every frame posed so far published as the next revision (the
        chunks added meanwhile chained on)."""
        if accepted:
            loop_edges = [LoopEdge(r["chunk_j"], r["chunk_i"], np.asarray(r["Z"])) for r in accepted]
            temporal = TemporalResult(np.zeros((0, 0), np.float32), relative, edges, K_ref)
            self._graph = graph.run(
                ctx,
                temporal,
                LoopResult(accepted, loop_edges),
                warm=self._graph,
                scale_priors=False,
                capacity=_capacity(len(relative) + 1, len(loop_edges)),
            )
            solution = self._graph.chunk_poses
        else:  # every accepted loop withdrawn: the chain
            self._graph, solution = None, chain_poses(relative)
        with ctx.timer("live revision"), self._lock:
            self._chunk_poses = graph.warm_start(solution, self._relative)
            n = len(self._cam_to_world)
            owner = np.searchsorted(np.asarray(self._starts), np.arange(n), side="right") - 1  # the export's
            self.revision += 1
            self.metres_per_unit = self._metric_factor()
            self._cam_to_world = _scaled(_world(self._chunk_poses[owner], self._extrinsic[:n]), self.metres_per_unit)
            self._publish(range(n), self._cam_to_world, "loop closure")

    def _metric_factor(self) -> float | None:
        """The live metres per world unit under ``--metric`` (None without it, or before any
        chunk saw the road): ``camera-height=H``: the median vote ``H / (h_t s_t)`` of the
        chunks posed so far (:func:`swiftjax.metric_scale.combine_scales`, the offline
        ``metric_combine = "median"`` rule on the prefix); ``model``: 1 (chunk 0's metres);
        ``gt``: None (the ground truth is for the final pass's evaluation)."""
        ctx = self._ctx
        spec = None if ctx is None or ctx.camera is None else ctx.camera.metric
        if spec is None or spec[0] == "gt":
            return None
        if spec[0] == "model":
            return 1.0
        T = len(self._heights)
        try:
            m, _ = metric_scale.combine_scales(self._heights, self._chunk_poses[:T, 7], float(spec[1]))
        except ValueError:  # no road seen yet
            return None
        return m

    def _publish(self, frames: range, cam_to_world: np.ndarray, reason: str) -> None:
        if self._live is None:
            self._live = LiveLog(self.run_dir)
        self._live.append(frames, self.times[frames.start : frames.stop], cam_to_world, self.revision, reason)


#: The warm-up thread's niceness (Linux: per thread), above the live threads'.
_WARM_UP_NICENESS = 5
#: How often (seconds) a waiting warm-up plan looks whether the live chunks are done.
_WARM_UP_POLL_S = 0.05


def _capacity(num_chunks: int, loops: int = 0) -> tuple[int, int]:
    """The live pose graph's capacity ``(temporal edges, loop edges)``: ``C - 1`` and ``C`` for
    the power of two ``C >= 32`` at least the chunks and the loops, so that a drive compiles the
    solve about once per doubling of its chunks (:func:`swiftjax.pipeline.graph.run`)."""
    C = 32
    while C < max(num_chunks, loops):
        C *= 2
    return C - 1, C


def _scaled(cam_to_world: np.ndarray, m: float | None) -> np.ndarray:
    """``cam_to_world [F, 4, 4]`` with positions times ``m`` (unchanged for None)."""
    if m is None:
        return cam_to_world
    out = cam_to_world.copy()
    out[:, :3, 3] *= m
    return out


def _now() -> float:
    return time.monotonic()


def _world(chunk_poses: np.ndarray, extrinsic: np.ndarray) -> np.ndarray:
    """Camera-to-world ``[F, 4, 4]`` float64 of cameras ``extrinsic [F, 3, 4]`` in chunks posed
    ``chunk_poses [F or 1, 8]`` (:func:`swiftjax.camera.world_cameras`, as the export).  The
    rows are padded (repeating the first) to a power of two, so that a growing trajectory
    compiles ``O(log F)`` times, not once per length."""
    F = len(extrinsic)
    size = 64
    while size < F:
        size *= 2
    poses = np.broadcast_to(np.asarray(chunk_poses, np.float64), (F, 8))
    pad = np.zeros(size - F, np.int64)
    poses = np.concatenate([poses, poses[pad]]) if F else np.zeros((size, 8))
    ext = np.concatenate([np.asarray(extrinsic, np.float64), np.asarray(extrinsic, np.float64)[pad]]) if F else None
    if ext is None:
        return np.zeros((0, 4, 4))
    with jax.enable_x64(True):
        return np.asarray(world_cameras(jnp.asarray(poses), jnp.asarray(ext)), np.float64)[:F]

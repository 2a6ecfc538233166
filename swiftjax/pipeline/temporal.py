"""The temporal stage: predict -> descriptors -> chunk store -> align with the previous chunk.

For each chunk of the schedule (in order): the prediction's patch tokens are reduced to
per-frame descriptors where the executor computes it (``[N, d]`` is all that is kept;
:func:`swiftjax.loops.descriptors.chunk_descriptors`); the dense maps go to the device once,
where they are cast to float16 for the chunk store, sliced into the overlap frames for the
alignment, and handed to the export's share of the chunk (``chunk_export``, a
:class:`~swiftjax.pipeline.export.ChunkExport` given by the caller: points, frames), whose
result is stored with the chunk.  Chunk files (zip + fsync) are written by
one background thread while the next chunk is predicted.  Memory stays flat in the
sequence length: one chunk's dense arrays are in memory at a time, plus the previous
chunk's overlap frames and at most one chunk waiting for the writer.

Resume: a chunk recorded in the manifest is read back (descriptors, K_ref) instead of
predicted, and its recorded edge reused.  When the next edge is not recorded yet, the chunk's
last ``overlap`` frames are read back in float32 from its ``tail`` file (kept until that edge
is recorded), so a resumed run computes exactly the edges an uninterrupted one does, never
from the chunk store's float16 copies.  A chunk whose file fails its checksums is reported
and predicted again.  The other chunks are requested from the run's executor at the start, in
schedule order (a local one predicts the next chunk while this one is stored and aligned; a
Ray pool predicts several ahead).

Stage clocks: the wait for the predictions (descriptors included) is booked as "predict",
everything else as geometry: the float16 conversion, chunk-file and manifest writes
(and waits for the background writer) under "chunk store"; the chunk-frame export points
under "export".
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import _faults, align, metric_scale
from swiftjax.io.chunk_store import ChunkCorruptError, ChunkStore, half_if_fits
from swiftjax.loops.descriptors import chunk_descriptors
from swiftjax.pipeline import loop_geometry
from swiftjax.pipeline.alignment import align_pair, both
from swiftjax.pipeline.results import ChunkEdge, TemporalChunk, TemporalResult
from swiftjax.pipeline.rundir import ChunkRecords, RunContext, check_binding, chunk_binding, forget_chunk
from swiftjax.pipeline.user_camera import UserCamera
from swiftjax.prediction import ChunkPrediction

__all__ = ["ChunkSink", "TemporalStage", "run"]

#: The export's share of a chunk (:class:`swiftjax.pipeline.export.ChunkExport`): ``(owned
#: frames, prediction, depth, conf, keep-mask, K_ref) -> (chunk-store extras, write future)``.
ChunkSink = Callable[..., tuple[dict[str, np.ndarray], Any]]


def run(ctx: RunContext, chunk_export: ChunkSink) -> TemporalResult:
    """Every temporal chunk predicted (or read back), stored and aligned with its predecessor;
    ``chunk_export`` takes each predicted chunk's share of the outputs.  The schedule's chunks
    fed in order to a :class:`TemporalStage`."""
    schedule, timer = ctx.schedule, ctx.timer
    n = schedule.n_frames
    T = schedule.num_chunks
    stage = TemporalStage(ctx, chunk_export, num_chunks=T)
    descriptors: np.ndarray | None = None
    relative = np.zeros((max(T - 1, 0), 8))
    align_infos: list[dict[str, Any]] = []
    heights = np.full(T, np.nan) if stage.measures_heights else None
    # Recorded chunks are read back (checked; a corrupt one is forgotten), the others predicted
    # (in schedule order, by the executor).
    resumed = {}
    for t in range(T):
        if stage.records.chunk_done(t):
            r = _resume_chunk(ctx, stage.records, t)
            if r is not None:
                resumed[t] = r
    if resumed:
        ctx.log(
            f"swiftjax: resumed {len(resumed)}/{T} chunks from {ctx.store.root}"
            + (f"; predicting {T - len(resumed)}" if len(resumed) < T else "")
        )
    predictions = ctx.executor.map(
        ctx.predictor, [schedule.frames(t) for t in range(T) if t not in resumed], chunk_descriptors
    )

    try:
        for t in ctx.bar(range(T), desc="chunks", unit="chunk"):
            if t in resumed:
                step = stage.add(t, resumed=resumed.pop(t), last=t + 1 == T)
            else:
                with timer("predict"):
                    pred = next(predictions)
                _faults.point("chunk-predicted", t)
                step = stage.add(t, pred, last=t + 1 == T)
                del pred
            if descriptors is None:
                descriptors = np.zeros((n, step.descriptors.shape[1]), np.float32)
            descriptors[step.frames] = step.descriptors
            if step.edge is not None:
                relative[t - 1] = step.edge.S
                align_infos.append(step.edge.record)
            if heights is not None:
                heights[t] = step.ground_height
        stage.finish(drop_tails=True)
    finally:
        predictions.close()  # interrupted: release the chunks in flight
        stage.close()
    assert descriptors is not None and stage.K_ref is not None
    return TemporalResult(descriptors, relative, align_infos, stage.K_ref, heights)


class TemporalStage:
    """The temporal stage as a consumer of one chunk at a time: :meth:`add` stores chunk ``t``
    (predicted, or read back by :func:`_resume_chunk`), aligns it with chunk ``t - 1`` (the
    float32 overlap kept from the previous :meth:`add`) and returns its
    :class:`~swiftjax.pipeline.results.TemporalChunk` (descriptors, edge ``(t-1, t)``).

    Driven over a whole schedule by :func:`run`, and chunk by chunk, as the frames arrive, by
    the live engine (:mod:`swiftjax.pipeline.engine`).  State between chunks: the previous
    chunk's overlap frames (float32, on the device) and keep-mask, the reference intrinsics,
    and at most one chunk file waiting for the background writer; memory is flat in the
    sequence length.  ``num_chunks``: the schedule's length when known (the free-space check
    after the first chunk file), else None.
    """

    def __init__(self, ctx: RunContext, chunk_export: ChunkSink, num_chunks: int | None = None) -> None:
        self.ctx, self.chunk_export = ctx, chunk_export
        self.writer = _BackgroundWriter(ctx.store)
        self.records = ChunkRecords(ctx.manifest, ctx.store, num_chunks)
        cam = self.cam
        self.K_ref: np.ndarray | None = cam.K_ref  # known intrinsics; else the first prediction's
        self.measures_heights = cam.metric is not None and cam.metric[0] == "camera-height"
        self._prev_tail: align.ChunkFrames | None = None
        self._prev_tail_mask: jax.Array | None = None

    @property
    def cam(self) -> UserCamera:
        """The run's user camera (a growing live run's is renewed with its frames)."""
        return self.ctx.camera if self.ctx.camera is not None else UserCamera()

    def add(
        self,
        t: int,
        pred: ChunkPrediction | None = None,
        *,
        resumed: tuple[np.ndarray, np.ndarray, align.ChunkFrames | None] | None = None,
        last: bool = False,
    ) -> TemporalChunk:
        """Chunk ``t`` (``ctx.schedule.frames(t)``), from its prediction ``pred`` (with
        descriptors: :func:`swiftjax.loops.descriptors.chunk_descriptors`) or ``resumed``; the
        chunks must come in order.  ``last``: the input ends with it (it owns all its frames
        and keeps no float32 tail; else it owns the frames up to the next chunk's start)."""
        ctx = self.ctx
        config, schedule, store, manifest, timer = ctx.config, ctx.schedule, ctx.store, ctx.manifest, ctx.timer
        cam, records, O = self.cam, self.records, config.overlap
        frames = schedule.frames(t)
        S = len(frames)
        edge = records.edge(t)
        head: align.ChunkFrames | None = None
        head_mask = None
        height = None
        if resumed is not None:
            desc, intrinsic0, tail = resumed
            if self.K_ref is None:
                self.K_ref = np.asarray(intrinsic0, np.float64)
            # masks from the stored (float16) maps, as the uninterrupted run computed them
            tail_mask = (
                None
                if tail is None
                else cam.keep(
                    frames[S - O :], jnp.asarray(tail.depth, jnp.float16), jnp.asarray(tail.conf, jnp.float16)
                )
            )
            if self.measures_heights:
                with timer("chunk store"):
                    height = float(store.load_extra("chunk", t)["ground_height"])
            dirty = records.commit(self.writer.finished())
        else:
            assert pred is not None
            if pred.num_frames != len(frames):
                raise ValueError(f"the predictor returned {pred.num_frames} frames for chunk {t} of {len(frames)}")
            desc = pred.descriptors
            if self.K_ref is None:
                self.K_ref = np.asarray(pred.intrinsic[0], np.float64)
            K_ref = self.K_ref

            # One host->device copy of the dense maps, shared by the float16 store copies,
            # the export points and the alignment's overlap slices (async dispatches).
            with timer("export"):
                f32 = lambda x: jnp.asarray(x, jnp.float32)
                depth_d, conf_d = f32(pred.depth), f32(pred.conf)
                halves = _to_half(depth_d), _to_half(conf_d)
                head_d, head_c, tail_d, tail_c = _overlap_slices(depth_d, conf_d, overlap=O)
                # masks from the stored (float16) maps, as a resumed run recomputes them
                mask_d = cam.keep(frames, *halves)
                count = S if last else config.chunk_size - O  # owned: up to the next chunk's start
                points, frames_written = self.chunk_export(frames[:count], pred, depth_d, conf_d, mask_d, K_ref)
            if self.measures_heights:
                with timer("metric scale"):
                    gh = metric_scale.chunk_ground_height(
                        depth_d, conf_d, f32(pred.intrinsic), f32(K_ref), mask_d, conf_ratio=config.conf_ratio
                    )
                    height = float(gh.height)
                    points["ground_height"] = np.asarray(height)
            if config.loop_geometry:  # the geometric loop source's colours (its colour test)
                points.update(loop_geometry.stored_images(pred.images, config.chunk_size, config.geometry))

            with timer("chunk store"):
                depth, conf = (
                    np.asarray(half) if _fits_half(x) else half_if_fits(x)
                    for half, x in zip(halves, (pred.depth, pred.conf))
                )
                # Images feed the export points' colours and colmap/images/ (above): not stored.
                stored = dataclasses.replace(pred, depth=depth, conf=conf, images=None)
                # The float32 overlap for edge (t, t+1), should it be computed after a resume.
                exact_tail = (
                    None
                    if last
                    else ChunkPrediction(
                        np.asarray(pred.depth[S - O :], np.float32),
                        np.asarray(pred.conf[S - O :], np.float32),
                        np.asarray(pred.extrinsic[S - O :]),
                        np.asarray(pred.intrinsic[S - O :]),
                    )
                )
                dirty = records.commit(
                    self.writer.submit(
                        t,
                        _save_chunk,
                        store,
                        t,
                        stored,
                        chunk_binding(manifest, schedule, t),
                        points,
                        exact_tail,
                        frames_written,
                    )
                )
            head = align.ChunkFrames(head_d, head_c, pred.intrinsic[:O], pred.extrinsic[:O])
            tail = align.ChunkFrames(tail_d, tail_c, pred.intrinsic[S - O :], pred.extrinsic[S - O :])
            head_mask = None if mask_d is None else mask_d[:O]
            tail_mask = None if mask_d is None else mask_d[S - O :]
            del stored, depth, conf, depth_d, conf_d, halves, mask_d

        chunk_edge = None
        with timer("align"):
            if t > 0:
                if edge is None:
                    prev_tail = self._prev_tail
                    assert head is not None and prev_tail is not None and self.K_ref is not None
                    S_rel, diag = align_pair(
                        prev_tail,
                        head,
                        self.K_ref,
                        config,
                        False,
                        f"chunks {t - 1}/{t}",
                        mask=both(self._prev_tail_mask, head_mask),
                    )
                    edge = {"S": S_rel.tolist(), **diag}
                    dirty = records.add_edge(t, edge) or dirty
                chunk_edge = ChunkEdge(t, np.asarray(edge["S"], np.float64), edge)
            self._prev_tail, self._prev_tail_mask = tail, tail_mask
            del head, head_mask

        if dirty:
            with timer("chunk store"):
                manifest.save_soon()
        return TemporalChunk(t, frames, desc, chunk_edge, height)

    def warm_up(self) -> None:
        """Compile the temporal alignment for this run's shapes before the next chunk needs it:
        the last chunk's overlap aligned with itself (the same shapes and options as the next
        edge; the result is dropped).  The live engine calls it after chunk 0, while it waits
        for chunk 1's frames, so that chunk 1's first poses do not wait for the compile."""
        tail, K_ref = self._prev_tail, self.K_ref
        if tail is None or K_ref is None:
            return
        with self.ctx.timer("align"):
            mask = both(self._prev_tail_mask, self._prev_tail_mask)
            align_pair(tail, tail, K_ref, self.ctx.config, False, "warm-up", mask=mask)

    def flush(self) -> None:
        """Wait for the chunk files being written and record them (the chunk store then holds
        every chunk added, e.g. for a loop chunk's alignment)."""
        with self.ctx.timer("chunk store"):
            if self.records.commit(self.writer.finished(wait=True)):
                self.ctx.manifest.save_soon()  # marks the change for flush() (an earlier save may be recent)
            self.ctx.manifest.flush()

    def finish(self, drop_tails: bool) -> None:
        """Every chunk file written and recorded; ``drop_tails``: every edge is recorded, so the
        float32 tails go."""
        self.flush()
        if drop_tails:
            with self.ctx.timer("chunk store"):
                for c in self.ctx.store.indices("tail"):
                    self.ctx.store.remove("tail", c)

    def close(self) -> None:
        """Stop the writer (also when interrupted: every complete chunk file is recorded)."""
        self.writer.close()
        with contextlib.suppress(Exception):
            self.records.commit(self.writer.finished(wait=True))
        self.ctx.manifest.flush()


def _save_chunk(
    store: ChunkStore,
    t: int,
    stored: ChunkPrediction,
    binding: dict[str, np.ndarray],
    extra: dict[str, Any],
    tail: ChunkPrediction | None,
    frames_written: Any = None,
) -> None:
    """Chunk ``t``'s files, each bound to the chunk (``binding``:
    :func:`~swiftjax.pipeline.rundir.chunk_binding`): its frame PNGs (``frames_written``, the
    export's future) and the float32 tail first, so that a complete chunk file implies both."""
    if frames_written is not None:
        frames_written.result()
    if tail is not None:
        store.save("tail", t, tail, binding, half=False)
    store.save("chunk", t, stored, {**binding, **extra})


def _resume_chunk(
    ctx: RunContext, records: ChunkRecords, t: int
) -> tuple[np.ndarray, np.ndarray, align.ChunkFrames | None] | None:
    """A recorded chunk read back: ``(descriptors, intrinsic of its first frame, float32 tail
    or None when edge (t, t+1) is recorded)``; None when it must be predicted again (its file
    or its tail is missing, fails its checksums or is not this run's chunk ``t``, which is
    reported)."""
    store = ctx.store
    need_tail = t + 1 < ctx.schedule.num_chunks and records.edge(t + 1) is None
    binding = chunk_binding(ctx.manifest, ctx.schedule, t)
    try:
        with ctx.timer("chunk store"):
            if not store.exists("chunk", t):
                raise FileNotFoundError(store.path("chunk", t))
            desc = store.load_array("chunk", t, "descriptors")
            check_binding(store, "chunk", t, binding, rows=None if desc is None else len(desc))
            intrinsic0 = store.load_array("chunk", t, "intrinsic", frames=[0])[0]
            tail = None
            if need_tail:
                if not store.exists("tail", t):
                    raise FileNotFoundError(store.path("tail", t))
                check_binding(store, "tail", t, binding, rows=None)
                tail = align.ChunkFrames.from_prediction(store.load("tail", t, fields=()))
    except ChunkCorruptError as err:
        ctx.log(f"swiftjax: {err}; predicting chunk {t} again")
        forget_chunk(ctx.manifest, store, t)
        return None
    except FileNotFoundError as err:
        ctx.log(f"swiftjax: {err.args[0]} is missing; predicting chunk {t} again")
        forget_chunk(ctx.manifest, store, t)
        return None
    if desc is None:
        raise ValueError(f"{store.path('chunk', t)} has no descriptors")
    return desc, intrinsic0, tail


@jax.jit
def _to_half(x: jax.Array) -> jax.Array:
    """``x`` as float16 on the device (vectorised; NumPy's float16 cast is a scalar loop:
    docs/performance/pipeline.md).  Recompiles per shape."""
    return x.astype(jnp.float16)


def _fits_half(x: np.ndarray) -> bool:
    """``max |x| < 65520``: every value finite and stored faithfully as float16.

    The fast path of the chunk store's rule (:func:`~swiftjax.io.chunk_store.half_if_fits`):
    float16's largest finite value is 65504 and values below 65520 round down to it; NaN
    fails both comparisons.  ``False`` sends the caller to the exact rule.  Two vectorised
    NumPy reductions on the host (cheaper than the same test on the device on top of the cast;
    docs/performance/pipeline.md).
    """
    return bool(np.max(x) < 65520) and bool(np.min(x) > -65520)


@functools.partial(jax.jit, static_argnames=("overlap",))
def _overlap_slices(depth: jax.Array, conf: jax.Array, *, overlap: int) -> tuple[jax.Array, ...]:
    """``(depth[:O], conf[:O], depth[-O:], conf[-O:])``: a chunk's head (aligned with the
    previous chunk) and tail (with the next), in one dispatch."""
    S = depth.shape[0]
    return depth[:overlap], conf[:overlap], depth[S - overlap :], conf[S - overlap :]


class _BackgroundWriter:
    """Chunk-file writes (``ChunkStore.save``: zip + fsync) on one background thread.

    At most ``depth`` writes are pending; :meth:`submit` blocks on the oldest beyond that,
    so memory stays bounded.  The write of chunk ``t`` overlaps the prediction of chunk
    ``t + 1``.  :meth:`finished` returns the keys whose files are complete (in submission
    order) and re-raises a failed write's exception in the caller's thread.
    """

    def __init__(self, store: ChunkStore, depth: int = 1, synchronous: bool = False) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.store = store
        self.depth = depth
        self.synchronous = synchronous
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="swiftjax-chunk-store")
        self.pending: list[tuple[Any, Any]] = []

    def submit(self, key: Any, fn: Any, *args: Any) -> list[Any]:
        """Queue ``fn(*args)`` (a write); returns the keys finished meanwhile (see :meth:`finished`)."""
        done = []
        while len(self.pending) >= self.depth:
            done += self._pop()
        if self.synchronous:
            fn(*args)
            return done + [key]
        self.pending.append((key, self.pool.submit(fn, *args)))
        return done + self.finished()

    def finished(self, wait: bool = False) -> list[Any]:
        done = []
        while self.pending and (wait or self.pending[0][1].done()):
            done += self._pop()
        return done

    def _pop(self) -> list[Any]:
        key, future = self.pending.pop(0)
        future.result()
        return [key]

    def close(self) -> None:
        """Wait for every pending write (files are complete or removed), stop the thread."""
        self.pool.shutdown(wait=True)

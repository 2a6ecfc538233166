"""The loop stage's second candidate source: chunk pairs whose dense geometry matches.

Beside the DINO-token candidates (:mod:`swiftjax.pipeline.loop_closure`), with
``loop_geometry = true``: every temporal chunk's reliable points (``frame_stride``-th frames read
back from the chunk store, memory-mapped) become its gravity frame and reliable points
(:func:`geometries`, fixed batches of :data:`BATCH` chunks), a structure cloud
(:func:`swiftjax.loops.geometric.structure_cloud`) and a bird's-eye spectrum
(:func:`swiftjax.loops.geometric.bev_spectrum`), once per chunk; each point carries its pixel's
chromaticity (the sampled pixels the temporal stage stored, :func:`stored_images`) for the ICP's
colour test (``GeometryOptions.colour_tolerance``); with ``loop_geometry_neighbours =
k > 0`` the structure cloud is joined with its ``k`` neighbours' on each side, placed by the chain
(:func:`swiftjax.loops.geometric.merge_neighbours`, :func:`_neighbour_edges`: a joint
registration, ``(2k + 1)²`` times the ICP's work).  The candidates are the chunk
pairs that the dead-reckoned chain places within ``max(gate_min h, gate_drift x path between
them)`` of each other (:func:`_pairs`), frames more than ``loop_min_separation`` apart: on a
reverse pass the chunks that share structure are the ones whose cameras face each other across
a stretch, one or two chunks off the closest frames, so every gated pair is tried, not only the
closest (docs/performance/reverse-revisits.md), except the pairs beside a token candidate the
decision accepts (``closed``: recorded, not registered; :func:`candidates`).

Work, in fixed-size batches (:data:`JOB_BATCH`, :data:`PEAK_BATCH`, :data:`REFINE_BATCH`; the
last of each padded, and the chunks padded to a size bucket, :func:`_padded_chunks`: one compile per
bucket of chunk counts and options):

1. one placement job per candidate from the chain's prior (bird's-eye FFT search within the
   gate, Sim(3) ICP per peak: :func:`swiftjax.loops.geometric.starts_batch`,
   :func:`~swiftjax.loops.geometric.peaks_batch`); a candidate whose window holds no
   translation of the bird's-eye grid (:func:`swiftjax.loops.geometric.window_on_grid`: it
   would end "no valid placement" whatever the clouds) is recorded "not searched" instead;
2. the null, ONE per source chunk ``c_i`` shared by all its candidates: ``c_i`` placed on
   ``null_chunks`` unrelated chunks (:func:`_null_chunks`) from ``ψ = kπ, σ = 1, τ = 0`` (streets
   laid along streets, both ways) within the largest window of its candidates; run in rounds
   and stopped once every candidate of the source is at or below a null sample (exact,
   :func:`_null_settled`); the bound is :func:`swiftjax.loops.null.null_threshold` at
   ``null_false_alarm`` on the best placements' structure inliers;
3. for the candidates above it, the search along the street (:func:`_slide_search`: the peak
   ICP from the best placement shifted along the target's heading,
   :func:`~swiftjax.loops.geometric.slide_batch`), then the best placement refined on all
   points (:func:`~swiftjax.loops.geometric.refine_batch`; where the search found a rival, both,
   and the one with more structure inliers kept of those that pass the refined tests,
   :func:`_outranks`); the scale must agree with the chain's and
   the structure must be enough (:func:`swiftjax.loops.geometric.covisible_reason`, one-line
   reasons).  Every placement above the bound is plausible; the pose graph's edge is their
   mean and their spread widens its covariance
   (:func:`~swiftjax.loops.geometric.placement_moments`, :func:`graph_edge`) instead of
   rejecting an edge along a street slid along itself.  Structure on one line
   (``spread < min_spread``, recorded ``registration.straight``) does not reject the edge
   either: its covariance leaves the slide along the line and the scale to the other edges of
   the graph (:func:`~swiftjax.loops.geometric.straight_covariance`).

Every one of these programs has a fixed shape for a run (the chunk count, the batch sizes, the
frames' size): :func:`compile_ahead` traces and compiles them on a background thread, each
group beside the work before it (:func:`swiftjax.pipeline.loop_closure.run` starts it with the
token candidates), and the stage passes its batches as NumPy arrays (``jnp.asarray``, an eager
slice or a concatenate compiles a small program per shape).

Survivors go through the cross-chunk dense test over every pair of the two chunks' loaded frames
(``neighbours = 0``) and pairwise consistency with every other candidate, like the token
candidates; PCM whitens a registration edge's cycles by its own covariance
(:func:`edge_covariance`, the graph's about the verified placement), not by the drift model's
loop covariance: two placements of one revisit slid apart along a street (synthetic KITTI 08,
world 2: 35/4 and 36/4, 5 m apart) are consistent within the slide their covariances allow,
where the drift model's 0.05 chunk units made them exclude each other.  The dense test's null
(``null_samples`` times the candidate's own test) runs only where it can change the verdict
(:func:`swiftjax.loops.verification.null_needed`: an agreement below
``min(null_min_kappa, min_agreement)`` or no overlap is rejected by every null; exact).
A survivor rejected by the null's chance-corrected floor alone may still be a follower
(:mod:`swiftjax.loops.verification`, "Followers"): judged against its source's registered null
(:class:`RegisteredNull`: the dense agreement of the structure null's own placements, refined),
computed only when the decision accepts it provisionally (:func:`settle_deferred`), and
accepted only beside the verified loops it is consistent with.  No loop-centric chunk is
predicted.

Each candidate is a record marked ``source = "geometry"`` with its registration's numbers
(``registration.*``: the placements' structure inliers, plausible placements, the null's mean,
bound and samples, the search along the street's best score ``slide_score`` (−1 where it did
not run) and, where its placement and the best were both refined, whether its was kept,
``slide_kept``; after the refinement inlier ratio, RMS in camera heights, scale ratio, spread,
whether it is straight, the slide in camera heights).  The pose graph's edge
(:func:`graph_edge`) is the plausible placements' mean, its information the registration's
own residuals' widened by the placements' spread, by both chunks' model error over their
extents and, on straight structure, along the slide and the scale; ``Z`` in the record
stays the verified registration.  The records are recomputed on every run (nothing is cached
in the manifest).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from typing import Any, NamedTuple

import jax
import numpy as np

from swiftjax import align, sim3
from swiftjax.align import covariance
from swiftjax.loops import geometric as geo
from swiftjax.loops import verification as lv
from swiftjax.pipeline.rundir import RunContext

__all__ = [
    "BATCH",
    "JOB_BATCH",
    "CompileAhead",
    "PEAK_BATCH",
    "REFINE_BATCH",
    "candidates",
    "chunk_pair",
    "closing",
    "compile_ahead",
    "edge_covariance",
    "graph_edge",
    "geometries",
    "settle_deferred",
    "split_closed",
]

#: Chunks per call of :func:`geometries`' jitted :func:`swiftjax.loops.geometric.chunk_frame` (the last batch padded).
BATCH = 8


def local_frames(num_frames: int, chunk_size: int, options: geo.GeometryOptions) -> np.ndarray:
    """Positions of the ``ceil(chunk_size / frame_stride)`` frames the geometric source reads
    among a chunk's ``num_frames``, evenly spread (fixed count: the last repeated in a short
    chunk)."""
    count = -(-chunk_size // options.frame_stride)
    local = np.unique(np.round(np.linspace(0, num_frames - 1, count)).astype(np.int64))
    return np.concatenate([local, np.repeat(local[-1:], count - len(local))])


def _local(ctx: RunContext, c: int, options: geo.GeometryOptions) -> np.ndarray:
    return local_frames(len(ctx.schedule.frames(c)), ctx.config.chunk_size, options)


#: The chunk store's ``extra`` array of the geometric source's colours (:func:`stored_images`).
IMAGES = "loop_geometry_images"


def stored_images(images: np.ndarray | None, chunk_size: int, options: geo.GeometryOptions) -> dict[str, np.ndarray]:
    """What the temporal stage stores of a chunk's ``images [S, H, W, 3]`` uint8 for the colour
    test (:func:`swiftjax.loops.geometric.register`): :func:`local_frames` at the pixel grid of
    :func:`~swiftjax.loops.geometric.chunk_frame` (``[F, ⌈H / row_stride⌉, ⌈W / column_stride⌉,
    3]``, about 60 kB a KITTI chunk, where the full images would be 14 MB); nothing without
    images or with the colour test off."""
    if images is None or options.colour_tolerance >= 1.0:
        return {}
    sv, su = options.pixel_stride
    return {IMAGES: np.asarray(images)[local_frames(len(images), chunk_size, options), ::sv, ::su]}


def _sampled_images_shape(shape: tuple[int, ...], options: geo.GeometryOptions) -> tuple[int, int, int, int]:
    """``[F, ⌈H / row_stride⌉, ⌈W / column_stride⌉, 3]``: the images of ``depth [F, H, W]``
    (``shape``) at :func:`~swiftjax.loops.geometric.chunk_frame`'s pixel grid."""
    sv, su = options.pixel_stride
    return (shape[0], -(-shape[1] // sv), -(-shape[2] // su), 3)


def _images(ctx: RunContext, c: int, options: geo.GeometryOptions, shape: tuple[int, ...]) -> tuple[np.ndarray, bool]:
    """``([F, h, w, 3] uint8 colours, stored)`` of chunk ``c`` at :func:`_local`'s frames and the
    sampled pixels of ``depth [F, H, W]`` (``shape``) (:func:`stored_images`); mid grey, which
    every colour test passes, and ``stored = False`` when the store holds none of that size or
    the colour test is off."""
    want = _sampled_images_shape(shape, options)
    images = ctx.store.load_extra("chunk", c, (IMAGES,)).get(IMAGES) if options.colour_tolerance < 1.0 else None
    if images is None or images.shape != want:
        return np.full(want, 128, np.uint8), False
    return np.asarray(images, np.uint8), True


def _frames(
    ctx: RunContext, c: int, options: geo.GeometryOptions, dtype: Any = np.float32
) -> tuple[align.ChunkFrames, np.ndarray]:
    """:func:`_local`'s frames of chunk ``c`` and their global frame ids; depth and confidence
    as ``dtype`` (None: as stored)."""
    frames = ctx.schedule.frames(c)
    local = _local(ctx, c, options)
    side = align.ChunkFrames.from_prediction(ctx.store.load("chunk", c, frames=local, fields=(), as_stored=True))
    if ctx.camera is not None:  # masked pixels (user / sky) count as missing depth
        keep = ctx.camera.keep(frames[local], side.depth, side.conf)
        if keep is not None:
            side = side._replace(depth=np.where(np.asarray(keep), side.depth, np.nan))
    if dtype is not None:
        side = side._replace(depth=np.asarray(side.depth, dtype), conf=np.asarray(side.conf, dtype))
    return side, frames[local]


@functools.partial(jax.jit, static_argnames=("options",))
def _geometry(
    frames: align.ChunkFrames, images: jax.Array, K_ref: jax.Array, options: geo.GeometryOptions
) -> geo.ChunkGeometry:
    return jax.vmap(lambda f, i: geo.chunk_frame(f, K_ref, options, i))(frames, images)


def geometries(ctx: RunContext, K_ref: np.ndarray, options: geo.GeometryOptions):
    """``(ChunkGeometry [T, ...], global frame ids [T, F])`` of every chunk
    (:func:`swiftjax.loops.geometric.chunk_frame`; the polar grids of
    :func:`~swiftjax.loops.geometric.chunk_descriptors` are not needed by the co-visible search)."""
    T = ctx.schedule.num_chunks
    parts, ids = [], []
    stack: list[np.ndarray] = []

    grey: set[int] = set()  # chunks without stored colours (recorded below)

    def load(b0: int) -> list[tuple[align.ChunkFrames, np.ndarray, np.ndarray]]:
        out = []
        for c in range(b0, b0 + BATCH):
            side, frame_ids = _frames(ctx, min(c, T - 1), options, dtype=None)
            images, stored = _images(ctx, min(c, T - 1), options, np.shape(side.depth))
            if not stored:
                grey.add(min(c, T - 1))
            out.append((side, frame_ids, images))
        return out

    # the next batch is read (memory-map copies and CRC32s, which release the GIL) while this
    # one's geometry is computed (0.8 s instead of 1.0 on KITTI 00)
    with ThreadPoolExecutor(1, thread_name_prefix="swiftjax-frames") as reader:
        ahead = reader.submit(load, 0)
        for b0 in range(0, T, BATCH):
            loaded = ahead.result()
            if b0 + BATCH < T:
                ahead = reader.submit(load, b0 + BATCH)
            # One batch buffer per field, in the dtype the store keeps (float16 depth and confidence),
            # filled in place; chunk_frame converts to float32 on the device (exact).  A fresh ~40 MB
            # array per batch costs its page faults every time (np.stack: 0.85 s per batch of 8 KITTI
            # chunks against 0.01 s reused); NumPy's float16 -> float32 copy, 0.3 s on KITTI 00.
            fields = [*zip(*(frames for frames, _, _ in loaded)), tuple(im for _, _, im in loaded)]
            for f, field in enumerate(fields):
                dtype = np.result_type(*field, *stack[f : f + 1])  # float32 once a chunk stores it so
                if len(stack) <= f:
                    stack.append(np.empty((BATCH, *np.shape(field[0])), dtype))
                elif stack[f].dtype != dtype:  # (every row is written below: nothing to copy)
                    stack[f] = np.empty(stack[f].shape, dtype)
                for k, x in enumerate(field):
                    stack[f][k] = x
            n = min(BATCH, T - b0)
            out = _geometry(align.ChunkFrames(*stack[:-1]), stack[-1], np.asarray(K_ref, np.float32), options)
            # host arrays, sliced and joined by NumPy (before the refill): an eager jnp slice or
            # concatenate compiles a program per shape (13 on KITTI 00, 0.3 s of a cold run)
            parts.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[:n], out))
            ids += [f for _, f, _ in loaded[:n]]
    if grey and options.colour_tolerance < 1.0:
        ctx.log(
            f"loop geometry: {len(grey)} of {T} chunk(s) stored without colours (a run resumed with "
            "loop_geometry newly on, or a predictor without images): their matches are judged by "
            "the geometry alone"
        )
    return jax.tree_util.tree_map(lambda *a: np.concatenate(a), *parts), np.stack(ids)


class CompileAhead:
    """The stage's fixed-shape programs traced and compiled on a background thread
    (:func:`compile_ahead`), in groups the stage needs one after the other (the clouds, the
    placement, the refinement and dense test), all of them one after the other from the loop
    stage's start, beside the token candidates' work that comes before the stage (on synthetic
    KITTI 00 they are compiled by the time it begins: the stage 6.3 s instead of 8.4–8.6 with
    the placement's and the refinement's groups compiled beside the stage's own work, in the
    same A/B of ``bench/bench_hard_sequences.py``).  :meth:`wait` for a group before its first
    call; :meth:`cancel` once the rest will not run (a run whose stage registers nothing, such
    as the demo's, compiles them for nothing on this thread, beside its token work: about 3 s of
    it, the run's wall time within its noise).  A compile that fails is recorded in ``errors``
    and left to the stage (the same call then compiles there, and raises there if it must).
    ``seconds``: the thread's busy time (not in the run's stage timer, whose seconds each count
    once; the benchmark adds it to the stage's cost)."""

    def __init__(self, groups: list[list[Callable[[], Any]]]) -> None:
        import threading

        self.errors: list[str] = []
        self.seconds = 0.0
        self._done = [threading.Event() for _ in groups]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(groups,), name="swiftjax-geometry-compile", daemon=True)
        self._thread.start()

    def _run(self, groups: list[list[Callable[[], Any]]]) -> None:
        import contextlib
        import os
        import threading
        import time

        # below the stages it runs beside: it takes the CPU they leave
        with contextlib.suppress(OSError, AttributeError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), _NICENESS)
        try:
            for done, plans in zip(self._done, groups):
                start = time.perf_counter()
                for plan in plans:
                    if self._stop.is_set():
                        return
                    try:
                        plan()
                    except Exception as err:  # an ahead-of-time compile: nothing depends on it
                        self.errors.append(repr(err))
                self.seconds += time.perf_counter() - start
                done.set()
        finally:
            for done in self._done:
                done.set()

    def wait(self, group: int) -> None:
        """Block until group ``group`` is compiled (or failed)."""
        if group < len(self._done):
            self._done[group].wait()

    def cancel(self) -> None:
        """Start no further compile and wait for the one under way (the thread then ends)."""
        self._stop.set()
        self._thread.join()


#: The compile-ahead thread's niceness (Linux: per thread; elsewhere ignored).
_NICENESS = 10

#: :class:`CompileAhead`'s groups, in the order the stage needs them.
_CLOUDS, _PLACEMENT, _REFINEMENT = 0, 1, 2


def _padded_chunks(T: int) -> int:
    """The chunk count the stage's device programs are compiled for: the size bucket of ``T``
    (:func:`swiftjax.posegraph.problem.bucket_size`, 4 per doubling, at least 8), so that runs of
    similar length share their compiled programs (in the persistent cache too)."""
    from swiftjax.posegraph.problem import bucket_size

    return bucket_size(T, minimum=8)


def _pad_chunks(tree: Any, size: int) -> Any:
    """Every ``[T, ...]`` leaf of ``tree`` padded to ``[size, ...]`` with copies of its last row
    (valid values; a job never indexes them).  Chunk ``c``'s subsample key does not change:
    ``jax.random.split`` is prefix-stable (JAX's default partitionable threefry)."""
    return jax.tree_util.tree_map(lambda x: np.concatenate([x, np.repeat(x[-1:], size - len(x), 0)]), tree)


def compile_ahead(
    ctx: RunContext, K_ref: np.ndarray, options: geo.GeometryOptions = geo.GeometryOptions()
) -> CompileAhead:
    """Start compiling, on a background thread, the programs :func:`candidates` runs for this run's
    chunk count, in three groups one after the other (:class:`CompileAhead`): the clouds
    (:func:`_relative`, :func:`_geometry`, :func:`_clouds`); the placement (one batch each of :func:`_priors`,
    :func:`swiftjax.loops.geometric.starts_batch`, :func:`~swiftjax.loops.geometric.peaks_batch` and
    :func:`~swiftjax.loops.geometric.slide_batch`);
    the refinement (one batch each of :func:`~swiftjax.loops.geometric.refine_batch` and the
    placements' spread, and the dense test with its null,
    :func:`swiftjax.loops.verification.compile_candidate_numbers`).  Each is
    ``jit(f).trace(...).lower().compile()`` on the argument shapes the stage passes, so that the
    stage's calls find it compiled (``tests/test_geometric_loops.py`` checks that none is traced
    again).

    Tracing them is about 1.5 s of Python on KITTI 00 and lowering and compiling (or loading
    from the persistent cache) as much again, paid by every process, and 10 s to compile them
    on an empty cache; all of it beside the token candidates' work, and what the stage will not
    run is cancelled (the demo, whose gated pairs all lie beside token loops, cancels once its
    pairs are known).  Reads one chunk's frames here, on the caller's thread (for their
    shapes); the thread only traces and compiles."""
    side, _ = _frames(ctx, 0, options, dtype=None)
    frames = align.ChunkFrames(*(jax.ShapeDtypeStruct((BATCH, *np.shape(x)), np.asarray(x).dtype) for x in side))
    images = jax.ShapeDtypeStruct((BATCH, *_sampled_images_shape(np.shape(side.depth), options)), np.uint8)
    K = jax.ShapeDtypeStruct((3, 3), np.float32)
    T = _padded_chunks(ctx.schedule.num_chunks)
    per_chunk = jax.eval_shape(lambda f, i, k: _geometry(f, i, k, options), frames, images, K)
    geometry = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct((T, *x.shape[1:]), x.dtype), per_chunk)
    job = lambda size, *shape, dtype=np.float32: jax.ShapeDtypeStruct((size, *shape), dtype)
    edges = (job(T, 2 * options.neighbours, 8), job(T, 2 * options.neighbours, dtype=np.bool_))
    clouds, spectra = jax.eval_shape(lambda g, e, v: _clouds(g, e, v, options), geometry, *edges)
    ij = lambda size: (job(size, dtype=np.int32), job(size, dtype=np.int32))
    starts = (clouds, spectra, *ij(JOB_BATCH), job(JOB_BATCH), job(JOB_BATCH), job(JOB_BATCH, 2), job(JOB_BATCH))
    S0, corr = jax.eval_shape(lambda *a: geo.starts_batch(*a, options), *starts)
    peaks = (clouds, *ij(PEAK_BATCH), job(PEAK_BATCH, *S0.shape[1:]), job(PEAK_BATCH, *corr.shape[1:]))
    refine = (clouds, *ij(REFINE_BATCH), job(REFINE_BATCH, 8), job(REFINE_BATCH))
    K_peaks = S0.shape[1]
    moments = (
        job(REFINE_BATCH, K_peaks, 8),
        job(REFINE_BATCH, K_peaks, dtype=np.bool_),
        job(REFINE_BATCH, dtype=np.int32),
    )
    ahead = lambda f, *args: functools.partial(lambda *a: f.trace(*a).lower().compile(), *args)

    def relative() -> None:  # float64, as _relative_poses runs it
        with jax.enable_x64(True):
            _relative.trace(jax.ShapeDtypeStruct((T, 8), np.float64)).lower().compile()

    dense = _dense_config(ctx.config.verification)
    return CompileAhead(
        [
            [
                relative,
                ahead(_geometry, frames, images, K, options),
                ahead(_clouds, geometry, *edges, options),
            ],  # CLOUDS
            [
                ahead(_priors, clouds, job(JOB_BATCH, 8), *ij(JOB_BATCH)),
                ahead(geo.starts_batch, *starts, options),
                ahead(geo.peaks_batch, *peaks, options),
                ahead(geo.slide_batch, clouds, job(PEAK_BATCH, dtype=np.int32), job(PEAK_BATCH, 8), options),
            ],  # PLACEMENT
            [
                ahead(geo.refine_batch, *refine, options),
                ahead(_moments, *moments),
                functools.partial(lv.compile_candidate_numbers, side, K_ref, dense, null_when_needed=True),
            ],  # REFINEMENT
        ]
    )


def _pairs(chain: np.ndarray, clouds: geo.ChunkCloud, ids: np.ndarray, sep: int, options: geo.GeometryOptions):
    """``[(c_i, c_j, window)]``: chunk pairs (``c_i − c_j >= 2``, frames more than ``sep``
    apart) whose structure the dead-reckoned chain places within ``max(gate_min h, gate_drift x
    path)`` of each other (centres), and that window in ``c_j``'s camera heights (at most
    ``max_window``)."""
    with jax.enable_x64(True):
        centre = np.asarray(sim3.act(chain, np.asarray(clouds.origin, np.float64)))
    cam = chain[:, :3]
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(cam, axis=0), axis=1))])
    h_world = np.asarray(clouds.height) * chain[:, 7]
    h_med = float(np.nanmedian(h_world))
    mid = np.mean(np.asarray(ids, np.float64).reshape(len(chain), -1), axis=1)  # [T]
    gate = np.maximum(options.gate_min * h_med, options.gate_drift * np.abs(path[:, None] - path[None, :]))
    near = np.linalg.norm(centre[:, None] - centre[None, :], axis=-1) <= gate
    apart = np.abs(mid[:, None] - mid[None, :]) > sep
    ci, cj = np.nonzero(np.tril(near & apart, -2))  # c_j <= c_i - 2, in (c_i, c_j) order
    return [(int(a), int(b), min(float(gate[a, b]) / h_med, options.max_window)) for a, b in zip(ci, cj)]


def chunk_pair(record: dict[str, Any]) -> tuple[int, int]:
    """A candidate's chunks ``(larger, smaller)`` (:func:`swiftjax.loops.verification.chunk_pair`)."""
    return lv.chunk_pair(record)


def closing(pair: tuple[int, int], tokens: Iterable[tuple[int, int]]) -> tuple[int, int] | None:
    """The first of the accepted token candidates ``tokens`` (chunk pairs ``(larger, smaller)``)
    whose chunks each lie within one chunk of ``pair``'s (``(larger, smaller)``), or None: the
    token loop edge that closes the revisit ``pair`` would close.  The one rule behind
    :func:`swiftjax.pipeline.loop_closure.redundant_geometry` (which explains why such a
    geometric edge is rejected) and the pairs :func:`candidates` does not register (``closed``)."""
    return lv.same_revisit(pair, tokens)


def _without_edge(ci: int, cj: int, ids: np.ndarray, reason: str) -> dict[str, Any]:
    """The record of a gated pair that is not registered: ``accepted = False``, ``reason``, no
    ``Z`` (no edge), the middle frames of both chunks as ``i``, ``j`` (``ids [T, F]``)."""
    return {
        "source": "geometry",
        "i": int(ids[ci, len(ids[ci]) // 2]),
        "j": int(ids[cj, len(ids[cj]) // 2]),
        "chunk_i": int(ci),
        "chunk_j": int(cj),
        "accepted": False,
        "reason": reason,
    }


def split_closed(
    pairs: list[tuple[int, int, float]], closed: Sequence[tuple[int, int]], ids: np.ndarray
) -> tuple[list[tuple[int, int, float]], list[dict[str, Any]]]:
    """``pairs`` (``[(c_i, c_j, window)]``, :func:`_pairs`) split into those to register and the
    records of those a token candidate in ``closed`` closes (:func:`closing`): ``accepted =
    False``, a one-line reason naming the token edge, no ``Z`` (no edge), the middle frames of
    both chunks as ``i``, ``j`` (``ids [T, F]``: each chunk's loaded frames), and the token
    pair under ``_closed_by`` (popped by :func:`swiftjax.pipeline.loop_closure.run`)."""
    kept, unregistered = [], []
    for ci, cj, w in pairs:
        token = closing((ci, cj), closed)
        if token is None:
            kept.append((ci, cj, w))
            continue
        reason = (
            f"not registered: the token loop edge of chunks {token[1]} and {token[0]} closes this "
            "revisit (a geometric edge beside it is rejected as redundant)"
        )
        unregistered.append({**_without_edge(ci, cj, ids, reason), "_closed_by": token})
    return kept, unregistered


#: Placement jobs per call of :func:`swiftjax.loops.geometric.starts_batch` (the last call padded;
#: 8: its ``[B, yaws x scales, n, n]`` correlations stay in cache, 2.5 ms per job on CPU against
#: 3.7 ms with 16 on synthetic KITTI 00's jobs).
JOB_BATCH = 8
#: Placement jobs per call of :func:`swiftjax.loops.geometric.peaks_batch` (smaller: its
#: ``[B, peaks, P, Q]`` distance matrices stay in cache; 30 % less time per job than 16 on CPU).
PEAK_BATCH = 4
#: Refinements per call of :func:`swiftjax.loops.geometric.refine_batch` (the last call padded).
REFINE_BATCH = 4
#: Placement batches (starts, peaks) run at once, each on its own thread (XLA's own threads
#: keep 2 cores 1.5x as busy as one on one batch; two batches at once: the placement on
#: KITTI 00 in 3.6–3.7 s instead of 5.1–5.3).  The refinement's few, larger batches run one at
#: a time (two at once: 1.7–2.6 s instead of 1.1–1.2).
PLACEMENT_WORKERS = 2


def _null_chunks(ci: int, partners: set[int], T: int, near: set[tuple[int, int]], k: int) -> list[int]:
    """``k`` chunks evenly spread over those more than 3 chunks from ``c_i`` and from every
    chunk it is gated with (``partners``), and not paired with ``c_i`` by the gate: streets the
    source cannot be on."""
    far = lambda c: abs(c - ci) > 3 and all(abs(c - p) > 3 for p in partners)
    pool = [c for c in range(T) if far(c) and (max(c, ci), min(c, ci)) not in near]
    if len(pool) < k:
        return pool
    return [pool[int(round(x))] for x in np.linspace(0, len(pool) - 1, k)]


def _batches(n: int, size: int) -> list[np.ndarray]:
    """Index arrays of ``ceil(n / size)`` batches of ``size``, the last padded with its last index."""
    out = []
    for b0 in range(0, n, size):
        idx = np.arange(b0, min(b0 + size, n))
        out.append(np.concatenate([idx, np.repeat(idx[-1:], size - len(idx))]))
    return out


def _run_batched(
    fn: Callable[..., Any], size: int, arrays: tuple[np.ndarray, ...], pool: Executor | None = None
) -> Any:
    """``fn(*(a[idx] for a in arrays))`` over fixed-size batches of the ``n = len(arrays[0])``
    rows, concatenated in order as host arrays, ``[n, ...]`` (one compile per batch size,
    whatever ``n``).  The batches go in as NumPy arrays: ``jnp.asarray`` would compile a program
    per shape.  ``pool``: run the batches on its threads (:data:`PLACEMENT_WORKERS` at once; the
    same results, in the same order)."""
    n = len(arrays[0])

    def one(idx: np.ndarray) -> Any:
        out = fn(*(a[idx] for a in arrays))
        return jax.tree_util.tree_map(lambda x: np.asarray(x)[: min(size, n - int(idx[0]))], out)

    batches = _batches(n, size)
    parts = list(pool.map(one, batches)) if pool is not None and len(batches) > 1 else [one(i) for i in batches]
    return jax.tree_util.tree_map(lambda *x: np.concatenate(x), *parts)


def candidates(
    ctx: RunContext,
    K_ref: np.ndarray,
    taken: set[tuple[int, int]],
    verification: lv.VerificationConfig,
    options: geo.GeometryOptions = geo.GeometryOptions(),
    chain: np.ndarray | None = None,
    closed: Sequence[tuple[int, int]] = (),
    only: set[tuple[int, int]] | None = None,
    ahead: CompileAhead | None = None,
) -> list[dict[str, Any]]:
    """The geometric candidates' records (module docstring), chunk pairs in ``taken`` (the
    token source's, ``(larger, smaller)``) left out; each record with ``accepted``/``reason``
    set when its registration rejects it, else ready for :func:`verify_candidates`.
    ``chain [T, 8]``: the dead-reckoned chunk poses (the prior of every registration; without
    it no candidate is proposed).

    ``closed``: the token candidates the decision accepts (chunk pairs ``(larger, smaller)``).
    A gated pair whose chunks each lie within one chunk of one of them (:func:`closing`) is not
    registered: :func:`swiftjax.pipeline.loop_closure.redundant_geometry` would reject it
    whatever its registration (its docstring says why).  Its record keeps the candidate
    (``accepted = False``, a reason naming the token edge, no ``Z``: no edge); a source chunk
    left with no pair to register runs no null.  The others' verdicts do not depend on it:
    a source's null window is its largest over ALL its candidates, registered or not, and its
    null's early stop is exact per candidate (:func:`_null_settled`), so each registered
    pair gets the verdict it gets without the prune (the null's recorded numbers may differ
    where the stop comes earlier).  ``only``: register only these pairs (the other gated
    pairs get no record; :func:`swiftjax.pipeline.loop_closure.run` registers the pruned
    pairs whose token edge the joint decision rejects).

    Work, all in fixed-shape batches: every chunk's geometry, structure cloud and bird's-eye
    spectrum once; one placement job (:func:`swiftjax.loops.geometric.starts_batch`, then :func:`~swiftjax.loops.geometric.peaks_batch` where a peak overlaps a cell) per
    candidate and ``null_chunks`` per SOURCE chunk (its null, shared by all its candidates);
    the refinement on all points (:func:`swiftjax.loops.geometric.refine_batch`) and the dense
    test only for the candidates above their null.  ``ahead``: the programs being compiled
    (:func:`compile_ahead`): each group waited for before its first call, the rest cancelled
    once it will not run."""
    from swiftjax.loops.null import null_threshold

    if chain is None:
        return []
    chain = np.asarray(chain, np.float64)
    o = options
    if ahead is None:
        ahead = CompileAhead([])  # (nothing to wait for)
    with ctx.timer("loop geometry: clouds"):
        ahead.wait(_CLOUDS)
        g, ids = geometries(ctx, K_ref, o)
        T = len(ids)
        extent = _extents(np.asarray(g.anchors))
        # the device programs take the clouds of a bucket of chunk counts (_padded_chunks)
        size = _padded_chunks(T)
        relative = _relative_poses(chain, size)
        clouds, spectra = _clouds(_pad_chunks(g, size), *_neighbour_edges(relative, T, o.neighbours), o)
    gated = _pairs(
        chain, jax.tree_util.tree_map(lambda x: np.asarray(x)[:T], clouds), ids, ctx.config.loop_min_separation, o
    )
    near = {(ci, cj) for ci, cj, _ in gated}
    pairs = [(ci, cj, w) for ci, cj, w in gated if (ci, cj) not in taken]
    order = {(ci, cj): n for n, (ci, cj, _) in enumerate(pairs)}
    in_order = lambda records: sorted(records, key=lambda r: order[r["chunk_i"], r["chunk_j"]])
    window: dict[int, float] = {}  # the null's window: the largest of ALL the source's candidates
    for ci, _, w in pairs:
        window[ci] = max(window.get(ci, 0.0), w)
    if only is not None:
        pairs = [p for p in pairs if (p[0], p[1]) in only]
    pairs, unregistered = split_closed(pairs, closed, ids)
    if not pairs:
        ahead.cancel()
        return unregistered
    ci_, cj_ = np.asarray([p[0] for p in pairs]), np.asarray([p[1] for p in pairs])
    win = np.asarray([p[2] for p in pairs], np.float32)
    Zc = relative[cj_, ci_].astype(np.float32)
    ahead.wait(_PLACEMENT)
    psi, sigma, tau = _run_batched(
        lambda *a: _priors(clouds, *a), JOB_BATCH, (Zc, ci_.astype(np.int32), cj_.astype(np.int32))
    )
    # a window that holds no translation of the bird's-eye grid ends "no valid placement"
    # whatever the clouds (geo.window_on_grid): recorded, not searched
    reach = geo.window_on_grid(tau, win, o)
    half = o.bev_cells // 2 * o.bev_cell
    for k in np.flatnonzero(~reach):
        unregistered.append(
            _without_edge(
                int(ci_[k]),
                int(cj_[k]),
                ids,
                f"not searched: the odometry puts chunk {ci_[k]}'s structure {np.linalg.norm(tau[k]):.0f} camera "
                f"heights from chunk {cj_[k]}'s, and the window of {win[k]:.0f} around it holds no translation "
                f"of the bird's-eye search (centres at most {half:.0f} apart along each axis)",
            )
        )
    if not reach.any():
        ahead.cancel()
        return in_order(unregistered)
    ci_, cj_, win, psi, sigma, tau = (x[reach] for x in (ci_, cj_, win, psi, sigma, tau))
    P = len(ci_)
    # the null: per source chunk, null_chunks unrelated chunks from (ψ = kπ, σ = 1, τ = 0) within
    # the largest window of its candidates (streets laid along streets, both ways)
    sources = sorted(set(ci_.tolist()))
    null_of: dict[int, np.ndarray] = {}
    jobs = [
        (int(a), int(b), float(p), float(s), t, float(w)) for a, b, p, s, t, w in zip(ci_, cj_, psi, sigma, tau, win)
    ]
    for c in sources:
        partners = {int(b) for a, b in zip(ci_, cj_) if a == c} | {b for a, b in near if a == c}
        partners |= {a for a, b in near if b == c}
        nulls = _null_chunks(c, partners, T, near, o.null_chunks)
        w = window[c]
        null_of[c] = np.arange(len(jobs), len(jobs) + len(nulls))
        jobs += [(c, n, math.pi * (k % 2), 1.0, np.zeros(2, np.float32), w) for k, n in enumerate(nulls)]
    cols = [np.asarray([j[k] for j in jobs]) for k in range(6)]
    arrays = (
        cols[0].astype(np.int32),
        cols[1].astype(np.int32),
        cols[2].astype(np.float32),
        cols[3].astype(np.float32),
        np.stack(cols[4]).astype(np.float32),
        cols[5].astype(np.float32),
    )
    with (
        ctx.timer("loop geometry: placement"),
        ThreadPoolExecutor(PLACEMENT_WORKERS, thread_name_prefix="swiftjax-placement") as pool,
    ):
        K = o.peaks
        pl = geo.Placements(
            np.zeros((len(jobs), K, 8), np.float32),
            np.full((len(jobs), K), -1, np.int32),
            np.zeros((len(jobs), K), np.float32),
        )
        done = np.zeros(len(jobs), bool)

        def icp(which: np.ndarray) -> None:
            """Jobs ``which``: the bird's-eye starts, then the peak ICP where some peak overlaps
            a cell (peak_icp scores the others -1 anyway)."""
            done[which] = True
            starts = lambda *a: geo.starts_batch(clouds, spectra, *a, o)
            S0, corr = _run_batched(starts, JOB_BATCH, tuple(a[which] for a in arrays), pool)
            pl.S[which], pl.correlation[which] = S0, corr
            live = which[corr.max(-1) >= 0.5]
            if len(live):
                args = (arrays[0][live], arrays[1][live], pl.S[live], pl.correlation[live])
                got = _run_batched(lambda *a: geo.peaks_batch(clouds, *a, o), PEAK_BATCH, args, pool)
                pl.S[live], pl.scores[live] = got.S, got.scores

        icp(np.arange(P))
        cand_best = pl.scores[:P].max(-1)
        # The null's jobs in rounds, one unrelated chunk per source per round, while some
        # candidate of the source beats every null sample so far: a candidate at or below the
        # largest sample is below the final bound whatever the other samples (_null_settled).
        settled = {c: _null_settled(o.null_false_alarm, len(null_of[c])) for c in sources}
        rest = [null_of[c] for c in sources if not settled[c] and np.any(cand_best[ci_ == c] >= 0)]
        if rest:
            icp(np.concatenate(rest))
        for r in range(o.null_chunks):
            need = [
                null_of[c][r]
                for c in sources
                if settled[c]
                and len(null_of[c]) > r
                and np.any(cand_best[ci_ == c] > pl.scores[null_of[c][:r]].max(initial=-1))
            ]
            if not need:
                break
            icp(np.asarray(need))
    best = pl.scores.max(-1).astype(np.float64)  # [J]
    used = np.sum(np.asarray(clouds.weights)[:, : o.rows(o.peak_src_points)] > 0, -1).astype(np.float64)  # [T]
    thresholds = {}
    for c in sources:
        ran = null_of[c][done[null_of[c]]]
        nb = best[ran]
        pts = max(used[c], 1.0)
        if len(ran) < len(null_of[c]):  # stopped early: every candidate is at or below a sample
            thresholds[c] = (float(nb.max(initial=-1)), float(np.mean(nb)) if len(nb) else None, len(nb))
            continue
        th = null_threshold(nb / pts, np.ones(len(nb)), np.full(len(nb), pts), o.null_false_alarm, 0.0)
        thresholds[c] = (
            th.threshold * pts if math.isfinite(th.threshold) else None,
            float(np.mean(nb)) if len(nb) else None,
            len(nb),
        )
    slide_score = np.full(P, -1, np.int64)
    rival = np.full(P, -1, np.int64)  # the placement refined beside the best (_slide_search)
    searched = np.full(P, -1, np.int64)  # the slot that holds the search's placement
    if o.slide_steps:
        th_of = np.asarray([np.inf if thresholds[c][0] is None else thresholds[c][0] for c in ci_.tolist()])
        above = np.flatnonzero(pl.scores[:P].max(-1) > th_of)
        if len(above):
            with (
                ctx.timer("loop geometry: placement"),
                ThreadPoolExecutor(PLACEMENT_WORKERS, thread_name_prefix="swiftjax-placement") as pool,
            ):
                slide_score[above], searched[above], rival[above] = _slide_search(
                    pl, above, arrays[0], arrays[1], th_of[above], clouds, o, pool
                )
    records: list[dict[str, Any]] = []
    survivors = []
    registered: dict[int, RegisteredNull] = {}  # each source's, built when a candidate needs it

    def registered_null(c: int) -> RegisteredNull:
        if c not in registered:
            ran = null_of[c][done[null_of[c]] & (pl.scores[null_of[c]].max(-1) >= 0)]
            registered[c] = RegisteredNull(
                ctx, c, arrays[1][ran], pl.S[ran, np.argmax(pl.scores[ran], -1)], clouds, K_ref, o, verification
            )
        return registered[c]

    def refine(items: list[tuple[int, int, np.ndarray]]) -> list[str | None]:
        """Refine the best placements of ``items`` (record, best peak, plausible peaks) on all
        points: each record's ``Z``, ``score``, registration numbers and ``_stats``
        (:class:`_EdgeStats`) set, and its refined registration's reason
        (:func:`swiftjax.loops.geometric.covisible_reason` without the structure null, which the
        placement's score was tested against) returned."""
        # each item's best placement, then its rival from the search along the street where it
        # has one: both refined, the better one kept (_outranks)
        rows = [(n, k, kb) for n, (k, kb, _) in enumerate(items)]
        rows += [(n, k, int(rival[k])) for n, (k, _, _) in enumerate(items) if rival[k] >= 0]
        item, sk, kbs = (np.asarray(x) for x in zip(*rows))
        start = pl.S[sk, kbs].astype(np.float32)
        prior_scale = (sigma[sk] * np.asarray(clouds.height)[cj_[sk]] / np.asarray(clouds.height)[ci_[sk]]).astype(
            np.float32
        )
        with ctx.timer("loop geometry: refinement"):
            refined = _run_batched(
                lambda *a: geo.refine_batch(clouds, *a, o),
                REFINE_BATCH,
                (ci_[sk].astype(np.int32), cj_[sk].astype(np.int32), start, prior_scale),
            )
            pick = np.arange(len(items))
            numbers = [_registration_numbers(jax.tree_util.tree_map(lambda x: x[m], refined)) for m in range(len(rows))]
            for m in range(len(items), len(rows)):
                if _outranks(numbers[m], numbers[pick[item[m]]], o):
                    pick[item[m]] = m
            regs = jax.tree_util.tree_map(lambda x: x[pick], refined)
            offsets, spreads = _run_batched(
                _moments,
                REFINE_BATCH,
                (pl.S[sk[pick]], np.stack([p for _, _, p in items]), kbs[pick].astype(np.int32)),
            )
        reasons = []
        for n, (k, _, _) in enumerate(items):
            record = records[k]
            if rival[k] >= 0:
                record["registration"]["slide_kept"] = bool(kbs[pick[n]] == searched[k])
            reg0 = jax.tree_util.tree_map(lambda x: x[n], regs)
            ci, cj = int(ci_[k]), int(cj_[k])
            record["Z"] = np.asarray(reg0.S, np.float64).tolist()
            record["score"] = float(reg0.num_structure / max(int(reg0.num_points), 1))
            record["registration"].update(numbers[pick[n]])
            ev = np.linalg.eigvalsh(spreads[n][:3, :3])
            record["registration"]["slide"] = float(np.sqrt(max(ev[-1], 0.0)) / float(np.asarray(clouds.height)[ci]))
            straight = bool(reg0.spread < o.min_spread)
            record["registration"]["straight"] = straight
            record["_stats"] = _EdgeStats(
                reg0,
                float(np.asarray(clouds.height)[cj]),
                offsets[n],
                spreads[n],
                extent[[ci, cj]],
                _straight(reg0, o) if straight else np.zeros((7, 7)),
            )
            cov = edge_covariance(record["_stats"], ctx.config.edge_pixels_per_sample)
            if cov is not None:  # (none: PCM uses the drift model's loop covariance)
                record["_covariance"] = cov
            reasons.append(geo.covisible_reason(record["registration"], o, structure_null=False))
        return reasons

    def register_later(k: int, kb: int, plausible: np.ndarray) -> dict[str, Any]:
        """A sibling's deferred work (``_register``): the refinement, then, where it holds, the
        dense test without its null (the structure null rejects the record alone: only its
        view, ``dense_overlap``, is tested)."""
        (why,) = refine([(k, kb, plausible)])
        if why is not None:
            return {"quality_valid": False, "quality_reason": why}
        (side_i, _), (side_j, _) = _frames(ctx, int(ci_[k]), o), _frames(ctx, int(cj_[k]), o)
        with ctx.timer("loop geometry: verification"):
            return lv.candidate_numbers(
                side_i,
                side_j,
                np.asarray(records[k]["Z"]),
                K_ref,
                _NO_HALVES,
                _NO_HALVES,
                _plain_dense_config(verification),
            )

    for k in range(P):
        ci, cj = int(ci_[k]), int(cj_[k])
        th, null_mean, null_samples = thresholds[ci]
        kb = int(np.argmax(pl.scores[k]))
        plausible = pl.scores[k] > (th if th is not None else np.inf)
        record: dict[str, Any] = {
            "source": "geometry",
            "i": int(ids[ci, len(ids[ci]) // 2]),
            "j": int(ids[cj, len(ids[cj]) // 2]),
            "score": float(pl.scores[k, kb] / max(used[ci], 1.0)),
            "chunk_i": ci,
            "chunk_j": cj,
            "Z": np.asarray(pl.S[k, kb], np.float64).tolist(),
        }
        record["registration"] = {
            "peak_score": int(pl.scores[k, kb]),
            "peak_scores": [int(x) for x in pl.scores[k]],
            "plausible": int(plausible.sum()),
            "window": float(win[k]),
            "null_mean": null_mean,
            "null_threshold": th,
            "null_samples": null_samples,
            "yaw_deg": float(np.degrees(psi[k])),
            "neighbours": o.neighbours,
            "slide_score": int(slide_score[k]),
        }
        records.append(record)
        why = geo.covisible_reason(record["registration"], o)
        if why is None:
            survivors.append((k, kb, plausible))
        elif geo.covisible_reason(record["registration"], o, structure_null=False) is None and lv.may_sibling(
            record | {"registration_pending": True}, verification
        ):  # below the structure null alone: a sibling's refinement and dense test when accepted
            record.update(
                evidence_reason=why,
                registration_pending=True,
                quality_valid=True,
                quality_min_fraction=1.0,
                _register=functools.partial(register_later, k, kb, plausible),
            )
        else:
            record.update(accepted=False, reason=why, quality_valid=False, quality_min_fraction=1.0)

    if not survivors:
        ahead.cancel()
    else:
        ahead.wait(_REFINEMENT)
        for (k, _, _), why in zip(survivors, refine(survivors)):
            record, ci, cj = records[k], int(ci_[k]), int(cj_[k])
            record.update(quality_valid=why is None, quality_min_fraction=1.0)
            if why is not None:
                record.update(accepted=False, reason=why)
            else:
                with ctx.timer("loop geometry: verification"):
                    record.update(
                        _dense(ctx, ci, cj, record["Z"], K_ref, o, verification, functools.partial(registered_null, ci))
                    )
    return in_order(records + unregistered)


def _slide_search(
    pl: geo.Placements,
    jobs: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    bound: np.ndarray,
    clouds: geo.ChunkCloud,
    options: geo.GeometryOptions,
    pool: Executor | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The search along the street (module docstring of :mod:`swiftjax.loops.geometric`) of the
    placement jobs ``jobs [n]`` (their null bounds ``bound [n]``): the peak ICP from
    :func:`~swiftjax.loops.geometric.slide_starts` of each job's best placement, run as
    :func:`~swiftjax.loops.geometric.peaks_batch` jobs of ``peaks`` starts (the compiled
    program; the starts padded with the best itself).  The starts' best placement ``S*``, with
    score ``n*``, is written over the job's weakest placement in ``pl`` (in place) when

    * ``n*`` exceeds the best's score: it is the new best, and the best it displaced its rival;
    * or ``n*`` exceeds the null's bound and the weakest's score, and ``S*`` places the source's
      origin more than ``peak_separation / 2`` camera heights from where every placement does (a
      basin none of them is in, at the starts' own spacing; a slot without a placement, score
      −1, holds none): it is the best's rival.

    The refinement refines the best and its rival and keeps the one with more structure inliers
    (of those that pass the refined tests, :func:`_outranks`), a count on four times the
    points: the peak ICP's counts are too noisy to rank two plausible
    placements (synthetic KITTI 08, world 2: 37/3's search reached the truth's basin at the
    best's own peak score, 44, and refined it scores 412 against the best's 312).  With one
    peak the search's placement takes the best's only slot when it scores more and has no
    rival.  Returns ``[n]`` each: the starts' best score, the slot holding the search's
    placement and the rival's slot (−1: none)."""
    K = pl.S.shape[1]
    best = pl.S[jobs, np.argmax(pl.scores[jobs], -1)]
    starts = _run_batched(lambda *a: geo.slide_batch(clouds, *a, options), PEAK_BATCH, (dst[jobs], best))
    n, N = starts.shape[:2]
    rep = -(-N // K)
    starts = np.concatenate([starts, np.repeat(best[:, None], rep * K - N, 1)], 1).reshape(n * rep, K, 8)
    got = _run_batched(
        lambda *a: geo.peaks_batch(clouds, *a, options),
        PEAK_BATCH,
        (np.repeat(src[jobs], rep), np.repeat(dst[jobs], rep), starts, np.ones((n * rep, K), np.float32)),
        pool,
    )
    S, scores = got.S.reshape(n, rep * K, 8), got.scores.reshape(n, rep * K)
    top = np.argmax(scores, -1)
    top_S, top_score = S[np.arange(n), top], scores[np.arange(n), top]
    origin = np.asarray(clouds.origin, np.float64)[src[jobs]]  # where each puts the source's origin
    gap = np.linalg.norm(_act(top_S[:, None], origin[:, None]) - _act(pl.S[jobs], origin[:, None]), axis=-1)
    far = gap / np.asarray(clouds.height)[dst[jobs], None] > options.peak_separation / 2.0
    apart = np.all(far | (pl.scores[jobs] < 0), -1)  # [n] (a slot without a placement scores −1)
    searched, rival = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    for m in range(n):
        sc = pl.scores[jobs[m]]
        best_slot, weakest = int(np.argmax(sc)), int(np.argmin(sc))
        if top_score[m] > sc[best_slot]:  # the new best; the displaced best its rival
            rival[m] = best_slot if weakest != best_slot else -1  # (one peak: the best itself goes)
        elif weakest != best_slot and top_score[m] > max(bound[m], sc[weakest]) and apart[m]:
            rival[m] = weakest  # plausible, in a basin of its own: the best's rival
        else:
            continue
        searched[m] = weakest
        pl.S[jobs[m], weakest], pl.scores[jobs[m], weakest] = top_S[m], top_score[m]
    return top_score, searched, rival


def _registration_numbers(reg: geo.Registration) -> dict[str, Any]:
    """A refined registration's numbers as plain values (a record's ``registration`` keys, the
    ones :func:`swiftjax.loops.geometric.covisible_reason` tests)."""
    keys = ("inlier_ratio", "rms", "scale_ratio", "spread", "num_inliers", "num_structure", "num_points", "valid")
    return {key: _plain(getattr(reg, key)) for key in keys}


def _outranks(rival: dict[str, Any], best: dict[str, Any], options: geo.GeometryOptions) -> bool:
    """Whether the refined ``rival`` (:func:`_registration_numbers`) replaces the refined
    ``best`` of the same candidate: a refinement that passes the refined tests of
    :func:`swiftjax.loops.geometric.covisible_reason` (valid, scale within the odometry's
    range, structure, residual) outranks one that fails them; between two that both pass or
    both fail, more structure inliers.  The count alone would prefer a placement shrunk onto
    part of the target (a smaller scale brings more of the source within the Tukey radius:
    synthetic KITTI 00, world 1, a rival at 0.51 x the odometry's scale with 531 inliers) and
    so reject a candidate whose best placement passes."""
    passes = lambda reg: geo.covisible_reason({"peak_score": 0, **reg}, options, structure_null=False) is None
    return (passes(rival), rival["num_structure"]) > (passes(best), best["num_structure"])


def _act(S: np.ndarray, x: np.ndarray) -> np.ndarray:
    """:func:`swiftjax.sim3.act` on the host in float64, ``S [..., 8]`` on ``x [..., 3]``:
    ``s R(q) x + t`` with ``R(q) x = x + w u + q⃗ × u``, ``u = 2 q⃗ × x`` (a batch of any size
    compiles nothing)."""
    S, x = np.asarray(S, np.float64), np.asarray(x, np.float64)
    q, w = S[..., 3:6], S[..., 6:7]
    u = 2.0 * np.cross(q, x)
    return S[..., 7:8] * (x + w * u + np.cross(q, u)) + S[..., :3]


def _null_settled(false_alarm: float, k: int) -> bool:
    """Whether the null may stop early: its bound over ``k`` samples,
    ``m + t_{k−1}(1 − α) s sqrt(1 + 1/k)`` (:func:`swiftjax.loops.null.null_threshold`, ``s`` the
    sample standard deviation or more), is at least the largest sample whatever the samples,
    i.e. ``t_{k−1}(1 − α) sqrt(1 + 1/k) >= (k − 1)/sqrt(k)`` (Samuelson's inequality:
    ``max_i x_i − m <= s (k − 1)/sqrt(k)``).  Then a candidate at or below some sample is
    rejected by the complete null, and the remaining null jobs of its source need not run
    (α = 0.01, k = 8: 3.18 >= 2.47)."""
    from scipy import stats

    if k < 3:
        return False
    return float(stats.t.ppf(1.0 - false_alarm, k - 1)) * math.sqrt(1.0 + 1.0 / k) >= (k - 1) / math.sqrt(k)


@functools.partial(jax.jit, static_argnames=("options",))
def _clouds(geometry: geo.ChunkGeometry, edges: jax.Array, valid: jax.Array, options: geo.GeometryOptions):
    """Every chunk's :class:`~swiftjax.loops.geometric.ChunkCloud` and bird's-eye spectrum (chunk
    ``c``'s subsample drawn with the ``c``-th of ``T`` keys split from ``PRNGKey(0)``), :data:`BATCH`
    chunks at a time (``lax.map``): vmapped over all of KITTI 00's 112 (padded) chunks at once
    the program held a 381 MB temporary (every chunk's points against its anchors), 30 MB this
    way, bitwise the same clouds and 0.1 s faster (clouds and spectra in one map or two: bitwise
    the same and as fast on KITTI 00).  With ``options.neighbours = k > 0`` each
    cloud is joined with its ``2k`` neighbours' (``edges [T, 2k, 8]``, ``valid [T, 2k]``:
    :func:`_neighbour_edges`; :func:`swiftjax.loops.geometric.merge_neighbours`) before its
    spectrum."""
    keys = jax.random.split(jax.random.PRNGKey(0), geometry.height.shape[0])
    clouds = jax.lax.map(lambda chunk: geo.structure_cloud(*chunk, options), (geometry, keys), batch_size=BATCH)
    if options.neighbours:
        clouds = geo.merge_neighbours(clouds, edges, valid)
    return clouds, jax.lax.map(lambda cloud: geo.bev_spectrum(cloud, options), clouds, batch_size=BATCH)


@jax.jit
def _relative(chain: jax.Array) -> jax.Array:
    """``R [T, T, 8]``, ``R[a, b] = G_a⁻¹ G_b``: chunk ``b`` into chunk ``a``'s coordinates by the
    chain ``G [T, 8]`` (chunk to world).  Run under ``jax.enable_x64`` on float64 ``G``
    (:func:`_relative_poses`); one compile per ``T``."""
    return sim3.compose(sim3.inverse(chain)[:, None], chain[None, :])


def _relative_poses(chain: np.ndarray, size: int) -> np.ndarray:
    """Every chunk pair's ``G_a⁻¹ G_b``, ``[size, size, 8]`` float64 (:func:`_relative`): the chain
    ``[T, 8]`` padded to ``size`` chunks (the stage's bucket, :func:`_padded_chunks`: compiled
    ahead, :func:`compile_ahead`; eager float64 compositions per index shape compiled five small
    programs in the stage, 0.4 s on KITTI 00).  Rows and columns from ``T`` on repeat chunk
    ``T − 1``."""
    with jax.enable_x64(True):
        return np.asarray(_relative(_pad_chunks(np.asarray(chain, np.float64), size)), np.float64)


def _neighbour_edges(relative: np.ndarray, T: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``(edges [size, 2k, 8] float32, valid [size, 2k])`` of
    :func:`swiftjax.loops.geometric.merge_neighbours`: ``G_c⁻¹ G_{c+d}`` for ``d`` in
    :func:`~swiftjax.loops.geometric.neighbour_offsets`, read from ``relative [size, size, 8]``
    (:func:`_relative_poses` of the ``T`` chunks' chain, composed in float64), the identity and
    False where ``c + d`` or ``c`` lies outside the ``T`` chunks."""
    size = len(relative)
    offsets = geo.neighbour_offsets(k)
    c = np.arange(size)[:, None]
    n = c + np.asarray(offsets, np.int64)[None, :]
    valid = (c < T) & (n >= 0) & (n < T)
    rel = relative[np.minimum(c, T - 1), np.clip(n, 0, T - 1)]
    edges = np.where(valid[..., None], rel, np.asarray(sim3.identity(), np.float64)).astype(np.float32)
    return edges.reshape(size, len(offsets), 8), valid


@jax.jit
def _priors(clouds: geo.ChunkCloud, Z: jax.Array, ci: jax.Array, cj: jax.Array):
    """:func:`swiftjax.loops.geometric.edge_prior` of every pair ``(ψ [P], σ [P], τ [P, 2])``."""
    take = lambda c: jax.tree_util.tree_map(lambda x: x[c], clouds)
    return jax.vmap(lambda z, a, b: geo.edge_prior(z, take(a), take(b)))(Z, ci, cj)


_moments = jax.jit(jax.vmap(geo.placement_moments))


def _plain(v: Any) -> Any:
    a = np.asarray(v)
    return bool(a) if a.dtype == bool else (int(a) if a.dtype.kind in "iu" else float(a))


#: The loop-chunk halves' diagnostics that :func:`swiftjax.loops.verification.candidate_numbers`
#: takes: a registration edge has no loop chunk, so they pass.
_NO_HALVES = {"num_points": 1000, "fraction_used": 1.0, "rms": 0.0, "valid": True, "pose_fallback": False}


def _dense_config(verification: lv.VerificationConfig) -> lv.VerificationConfig:
    """The dense test of a geometric candidate (:func:`_dense`, compiled ahead by
    :func:`compile_ahead`): every frame pair of the two chunks' loaded frames."""
    return dataclasses.replace(verification, neighbours=0)


def _plain_dense_config(verification: lv.VerificationConfig) -> lv.VerificationConfig:
    """:func:`_dense_config` without the null (``agreement_rule = "fixed"``): the agreement and
    view of an edge whose verdict the null does not decide (:class:`RegisteredNull`'s samples,
    a sibling's registration)."""
    return dataclasses.replace(_dense_config(verification), agreement_rule="fixed")


def _dense(
    ctx: RunContext,
    ci: int,
    cj: int,
    Z: list[float],
    K_ref: np.ndarray,
    options: geo.GeometryOptions,
    verification: lv.VerificationConfig,
    registered: Callable[[], RegisteredNull],
) -> dict[str, Any]:
    """The cross-chunk dense test of the two chunks' loaded frames, every frame pair compared;
    its null only where it can change the verdict (:func:`swiftjax.loops.verification.null_needed`).
    Where the chance-corrected floor alone may reject it (:func:`swiftjax.loops.verification.may_follow`),
    the rest deferred: ``registered_null_pending = True`` and ``_registered``, a call made only
    when the decision accepts the candidate provisionally (:func:`settle_deferred`) that
    returns its source's registered null's keys (``registered()``, :class:`RegisteredNull`)
    and, where the null's first round stopped and the registered null is beaten, the complete
    null's (is ``a > τ``?)."""
    (side_i, _), (side_j, _) = _frames(ctx, ci, options), _frames(ctx, cj, options)
    numbers = functools.partial(
        lv.candidate_numbers, side_i, side_j, np.asarray(Z), K_ref, _NO_HALVES, _NO_HALVES, _dense_config(verification)
    )
    num = numbers(null_when_needed=True)
    if not lv.may_follow(num, verification):
        return num
    a = num["dense_agreement"]

    def settle() -> dict[str, Any]:
        out = registered().numbers(a)
        if num.get("null_stopped") and a > out["registered_null_threshold"]:  # a > τ? the complete null
            out |= numbers(null_when_needed=True, complete=True) | {"null_stopped": False}
        return out

    return num | {"registered_null_pending": True, "_registered": settle}


class RegisteredNull:
    """The dense agreement a registration reaches where it is WRONG, for source chunk ``c``
    (:mod:`swiftjax.loops.verification`, "Followers"): ``c``'s best placements on its null's
    unrelated chunks ``targets [n]`` (``starts [n, 8]``, from the placement step), refined as a
    candidate's (:func:`~swiftjax.loops.geometric.refine_batch`, the prior scale ``h_t / h_c``;
    the refinements that fail dropped) and dense-tested as a candidate is (:func:`_dense_config`).
    The bound is :func:`swiftjax.loops.null.null_threshold` (pooled) at ``null_false_alarm`` over
    the samples in view.

    Lazy and shared by the source's candidates: :data:`REFINE_BATCH` refinements at a time and
    each sample's dense test only when a candidate needs it.  :meth:`numbers` stops at the first
    sample in view at or above the candidate's agreement: exact, since the bound over ``k >= 3``
    samples is at least their largest (:func:`_null_settled`, checked for every ``k``), and below
    three in view there is no bound (the candidate is no follower either way).
    """

    def __init__(
        self,
        ctx: RunContext,
        c: int,
        targets: np.ndarray,
        starts: np.ndarray,
        clouds: geo.ChunkCloud,
        K_ref: np.ndarray,
        options: geo.GeometryOptions,
        verification: lv.VerificationConfig,
    ) -> None:
        self._ctx, self._c, self._clouds, self._K_ref, self._options = ctx, c, clouds, K_ref, options
        self._targets, self._starts = np.asarray(targets, np.int64), np.asarray(starts, np.float32)
        self._verification = verification
        self._config = _plain_dense_config(verification)
        n = len(self._targets)
        self._exact = all(_null_settled(verification.null_false_alarm, k) for k in range(3, n + 1))
        self._samples: list[tuple[float, float, float]] = []  # (score, overlap, pairs seen) per tested target
        self._ready: list[tuple[int, np.ndarray]] = []  # (target, refined edge), refined, not yet tested
        self._refined = 0  # targets refined so far
        self._source: align.ChunkFrames | None = None

    def _refine(self, k0: int, k1: int) -> list[tuple[int, np.ndarray]]:
        """``(target, refined edge)`` of ``targets[k0:k1]`` whose refinement is valid."""
        h = np.asarray(self._clouds.height)
        c, t = self._c, self._targets[k0:k1]
        with self._ctx.timer("loop geometry: refinement"):
            regs = _run_batched(
                lambda *a: geo.refine_batch(self._clouds, *a, self._options),
                REFINE_BATCH,
                (
                    np.full(len(t), c, np.int32),
                    t.astype(np.int32),
                    self._starts[k0:k1],
                    (h[t] / h[c]).astype(np.float32),
                ),
            )
        return [(int(t[k]), np.asarray(regs.S[k], np.float64)) for k in range(len(t)) if bool(regs.valid[k])]

    def _test(self, target: int, S: np.ndarray) -> tuple[float, float, float]:
        """``(agreement, overlap, pairs seen)`` of the source on ``target`` under ``S``."""
        if self._source is None:
            self._source = _frames(self._ctx, self._c, self._options)[0]
        side_i, (side_j, _) = self._source, _frames(self._ctx, target, self._options)
        num = lv.candidate_numbers(side_i, side_j, S, self._K_ref, _NO_HALVES, _NO_HALVES, self._config)
        seen = min(num["dense_i_to_j"]["pairs_seen"], num["dense_j_to_i"]["pairs_seen"])
        return num["dense_agreement"], num["dense_overlap"], float(seen)

    def _untested(self) -> bool:
        """Whether some target is still to be refined or tested."""
        return bool(self._ready) or self._refined < len(self._targets)

    def _next(self) -> bool:
        """Test one more sample (refining the next batch first when none is ready); False when
        every sample is tested."""
        while not self._ready and self._refined < len(self._targets):
            k0, self._refined = self._refined, min(self._refined + REFINE_BATCH, len(self._targets))
            self._ready = self._refine(k0, self._refined)
        if not self._ready:
            return False
        with self._ctx.timer("loop geometry: registered null"):
            self._samples.append(self._test(*self._ready.pop(0)))
        return True

    def numbers(self, agreement: float) -> dict[str, Any]:
        """The registered null's keys for a candidate whose agreement is ``agreement``:
        ``registered_null_threshold`` (NaN below three samples in view), ``_mean``, ``_std``,
        ``_samples`` (those in view), and ``registered_null_stopped`` when a sample in view
        reached ``agreement`` before all were tested (then ``_threshold`` is that sample:
        the candidate is rejected as by the complete bound)."""
        from swiftjax.loops.null import in_view, null_threshold

        v = self._verification
        while True:
            x = np.asarray(self._samples, np.float64).reshape(-1, 3)
            use = in_view(x[:, 0], x[:, 1], x[:, 2], v.min_overlap)
            top = float(x[use, 0].max(initial=-math.inf))
            if self._exact and top >= agreement and self._untested():
                return {
                    "registered_null_threshold": top,
                    "registered_null_mean": float(x[use, 0].mean()),
                    "registered_null_std": math.nan,
                    "registered_null_samples": int(use.sum()),
                    "registered_null_stopped": True,
                }
            if not self._next():
                break
        th = null_threshold(x[:, 0], x[:, 1], x[:, 2], v.null_false_alarm, v.min_overlap)
        return {
            "registered_null_threshold": th.threshold,
            "registered_null_mean": th.mean,
            "registered_null_std": th.std,
            "registered_null_samples": th.samples,
        }


def settle_deferred(decide: Callable[[list[dict[str, Any]]], None], records: list[dict[str, Any]]) -> None:
    """``decide(records)`` (in place), until no accepted record has work deferred: each
    provisionally accepted follower's registered null (``registered_null_pending``, its
    ``_registered`` call) and sibling's refinement and dense test (``registration_pending``,
    its ``_register`` call) computed, and the records decided again.  Neither takes part in the
    verified loops' consistent set, so a follower's verdict is the one every null computed first
    would give; the nulls of the followers that PCM (or the redundancy rule) rejects are never
    computed (they keep ``registered_null_pending``), nor the registrations of the siblings
    whose placements are inconsistent with their revisit's loops (a screen on the placement,
    which the refinement moves by a fraction of a camera height)."""
    while True:
        decide(records)
        pending = [r for r in records if r.get("accepted") and any(r.get(flag) for flag in _DEFERRED)]
        if not pending:
            return
        for r in pending:
            flag = next(flag for flag in _DEFERRED if r.get(flag))
            r.update(r.pop(_DEFERRED[flag])())
            del r[flag]


#: A record's deferred work: its flag and the key of the call that computes it (:func:`settle_deferred`).
_DEFERRED = {"registered_null_pending": "_registered", "registration_pending": "_register"}


def _extents(anchors: np.ndarray) -> np.ndarray:
    """``[T]`` each chunk's extent: the largest distance between two of its anchors ``[T, A, 3]``
    (camera centres spread over its loaded frames; chunk units)."""
    return np.max(np.linalg.norm(anchors[:, :, None] - anchors[:, None], axis=-1), axis=(1, 2))


class _EdgeStats(NamedTuple):
    """What :func:`graph_edge` needs of a refined registration (a record's ``_stats``)."""

    registration: geo.Registration  # the best placement, refined
    unit: float  # chunk ``c_j``'s camera height (the residuals' unit)
    offset: np.ndarray  # [7] δ̄, the plausible placements' mean about the best
    spread: np.ndarray  # [7, 7] Σ_P, their covariance
    extents: np.ndarray  # [2] chunks c_i, c_j's extents
    straight: np.ndarray  # [7, 7] Σ_L, what straight structure leaves free (zeros when not straight)


def _straight(reg: geo.Registration, options: geo.GeometryOptions) -> np.ndarray:
    """``Σ_L`` ``[7, 7]`` float64 of a refined registration on straight structure
    (:func:`swiftjax.loops.geometric.straight_covariance`): the slide over the structure's own
    length, the scale uniform over the placement's searched range ``±scale_search``."""
    with jax.enable_x64(True):
        return np.asarray(
            geo.straight_covariance(
                np.asarray(reg.S, np.float64),
                np.asarray(reg.axis, np.float64),
                np.float64(reg.axis_variance),
                np.asarray(reg.structure_mean, np.float64),
                options.scale_search**2 / 3.0,
            )
        )


def _edge_moments(stats: _EdgeStats, pixels_per_sample: float) -> tuple[np.ndarray, np.ndarray] | None:
    """``(δ̄ [7], Σ [7, 7])`` of a refined registration (:func:`graph_edge`'s terms): the
    plausible placements' mean offset about the best and the edge's covariance about that
    mean, ``Σ = Ω_reg⁻¹ + Σ_P + Σ_W + Σ_L``; None without usable statistics."""
    reg = stats.registration
    S = np.asarray(reg.S, np.float64)
    drift = lv.VerificationConfig()
    with jax.enable_x64(True):
        out = covariance.umeyama_information(
            S[7],
            np.float64(reg.num_inliers),
            np.float64(reg.rms) * stats.unit,
            np.asarray(reg.src_mean, np.float64),
            np.asarray(reg.src_covariance, np.float64),
            pixels_per_sample=pixels_per_sample,
        )
        if not bool(out.valid):
            return None
        warp = geo.warp_covariance(
            *stats.extents,
            S[7],
            drift.odo_sigma_rot,
            drift.odo_sigma_trans,
            drift.odo_sigma_scale,
        )
        cov = np.linalg.inv(np.asarray(out.information, np.float64)) + stats.spread + np.asarray(warp) + stats.straight
    offset = np.asarray(stats.offset, np.float64)
    return (offset, cov) if np.all(np.isfinite(cov)) and np.all(np.isfinite(offset)) else None


def graph_edge(record: dict[str, Any], pixels_per_sample: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The pose graph's edge of an accepted registration record: ``(Z [8], information [7, 7])``,
    or None (no usable statistics: the record's ``Z`` with the drift model alone)::

        Z = S exp(δ̄),   Ω = (Ω_reg⁻¹ + Σ_P + Σ_W + Σ_L)⁻¹

    ``S``: the refined best placement (the record's ``Z``, the verified one); ``δ̄``, ``Σ_P``:
    the plausible placements' mean offset and covariance about it
    (:func:`swiftjax.loops.geometric.placement_moments`: the edge is the Gaussian closest to
    "any plausible placement alike"; ``δ̄ = 0``, ``Σ_P = 0`` when only the best is plausible);
    ``Ω_reg`` from the registration's own inliers' residuals
    (:func:`swiftjax.align.covariance.umeyama_information`); ``Σ_W`` the two chunks' model
    error over their extents (:func:`swiftjax.loops.geometric.warp_covariance`, the drift
    model of :class:`~swiftjax.loops.verification.VerificationConfig`'s defaults, as the pose
    graph's own drift terms); ``Σ_L`` what straight structure leaves free, zero unless the
    registration's ``spread < min_spread`` (:func:`swiftjax.loops.geometric.straight_covariance`:
    the slide along the street and the scale, left to the other edges of the graph)."""
    stats: _EdgeStats | None = record.get("_stats")
    moments = None if stats is None else _edge_moments(stats, pixels_per_sample)
    if moments is None:
        return None
    offset, cov = moments
    with jax.enable_x64(True):
        Z = np.asarray(sim3.compose(np.asarray(stats.registration.S, np.float64), sim3.exp(offset)))
    info = np.linalg.inv(cov)
    info = 0.5 * (info + info.T)
    return (Z, info) if np.all(np.isfinite(info)) and np.all(np.isfinite(Z)) else None


def edge_covariance(stats: _EdgeStats, pixels_per_sample: float) -> np.ndarray | None:
    """``[7, 7]`` the covariance of a refined registration's edge about its BEST placement
    (the record's ``Z``, the one verified), for pairwise consistency
    (:func:`swiftjax.loops.verification.verify_candidates`, a record's ``_covariance``): the
    graph's covariance (:func:`graph_edge`) widened by its mean's offset, the second moment
    ``Σ + δ̄ δ̄ᵀ`` about ``S``, so that PCM judges the placement verified with the uncertainty the
    graph will give the edge; None without usable statistics."""
    moments = _edge_moments(stats, pixels_per_sample)
    if moments is None:
        return None
    offset, cov = moments
    return cov + np.outer(offset, offset)

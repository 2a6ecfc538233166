"""The host-level SwiftVGGT pipeline: chunks in, trajectory and point cloud out.

This is the imperative shell around the pure JAX core, and the only place with loops over
chunks, files and progress bars::

    schedule ─► for each chunk: predict ─► descriptors ─► export points ─► chunk store
                                 ─► align with previous
            ─► loop detection ─► loop-centric chunks: predict ─► align both halves ─► loop edges
            ─► Sim(3) pose graph (LM) ─► final pass over the store ─► poses, PLY, COLMAP, metrics

Memory stays flat in the sequence length: one chunk's dense arrays are in memory at a time
(plus the previous chunk's overlap frames and at most one chunk waiting for the background
writer), descriptors are reduced as chunks arrive (``[N, d]`` is all that is kept), and
dense outputs stream to disk.

What is computed when (measured on the synthetic KITTI 00 run, ``bench/bench_pipeline.py``):
the dense maps go to the device once per chunk; there they are cast to float16 for the
chunk store, sliced into the overlap frames for the alignment, and unprojected into the
chunk's share of the point cloud (its own frames, confidence-filtered, on the
``point_stride`` grid, in the chunk's frame).  Those points are saved in the chunk's file,
so the final pass reads only points and poses -- never the dense maps -- and applies the
optimised ``S_t``.  Chunk files (zip + fsync) are written by one background thread while
the next chunk is predicted.  Loop-centric chunks read only the 2 x ``loop_half_window``
frames they overlap from each temporal chunk's file (memory-mapped).  Images are used for
the points' colours and not stored.

Resumability: ``run_dir/manifest.json`` records the configuration, the input fingerprint
and every finished chunk, edge and loop edge.  Re-running the same command skips finished
work; a changed input or configuration is refused (:class:`RunDirError`) unless
``overwrite=True``.  Every file is written atomically (temp file + rename).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import pathlib
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import align, camera, chunks, loops, posegraph, sim3
from swiftjax.io.atomic import atomic_write
from swiftjax.io.chunk_store import ChunkStore, half_if_fits
from swiftjax.prediction import ChunkPrediction

__all__ = [
    "PipelineConfig",
    "Predictor",
    "ImagePredictor",
    "OraclePredictor",
    "RunDirError",
    "RunResult",
    "reconstruct",
    "chain_poses",
    "summary_table",
]

MANIFEST_VERSION = 2  # 2: chunk files carry their chunk-frame export points


class RunDirError(RuntimeError):
    """The run directory belongs to a different input or configuration (or is unusable)."""


# --------------------------------------------------------------------------- configuration


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Every method parameter, with the paper's / authors' defaults (DESIGN.md).

    Chunking: ``chunk_size`` (B), ``overlap`` (O).  Alignment (eq. 1-2): ``alignment``
    (``"umeyama"``, the method's single weighted solve, or ``"irls"``, VGGT-Long's
    iterative baseline on the same reliable points, for comparison), ``depth_threshold``
    (lambda_D), ``conf_ratio`` (lambda_gamma), ``min_points`` and
    ``fallback_depth_threshold`` (the authors' one-time retry), ``loop_depth_threshold``
    (loop-chunk alignment).  Loops: ``loop_closure``, ``loop_threshold`` (cosine of the
    whitened descriptors), ``loop_min_separation``, ``loop_nms_radius``, ``loop_top_k``,
    ``whitening_dim``, ``whitening_remove``, ``power_beta``, ``loop_half_window``.  Pose
    graph: ``robust_loops`` (``None``, ``"huber"`` or ``"cauchy"`` on loop edges; the
    authors use none), ``robust_scale``, ``max_lm_steps``.  Output: ``point_conf_ratio``
    (keep pixels with confidence >= ratio x frame mean), ``point_stride`` (pixel
    subsampling of the cloud), ``voxel_size`` (optional voxel downsampling per chunk),
    ``colmap_max_points``.
    """

    chunk_size: int = 75
    overlap: int = 30
    alignment: str = "umeyama"
    depth_threshold: float = 0.2
    conf_ratio: float = 0.5
    min_points: int = 20_000
    fallback_depth_threshold: float = 0.25
    loop_depth_threshold: float = 0.4
    loop_closure: bool = True
    loop_threshold: float = loops.DEFAULT_THRESHOLD
    loop_min_separation: int = 100
    loop_nms_radius: int = 25
    loop_top_k: int = 8
    whitening_dim: int = 512
    whitening_remove: int = 1
    power_beta: float = 0.5
    loop_half_window: int = 10
    robust_loops: str | None = None
    robust_scale: float = 1.0
    max_lm_steps: int = 100
    point_conf_ratio: float = 0.75
    point_stride: int = 4
    voxel_size: float | None = None
    colmap_max_points: int = 200_000

    def __post_init__(self) -> None:
        if self.chunk_size < 2:
            raise ValueError(f"chunk_size must be >= 2, got {self.chunk_size}")
        if not 1 <= self.overlap < self.chunk_size:
            raise ValueError(
                f"overlap must satisfy 1 <= overlap < chunk_size ({self.chunk_size}), got {self.overlap}"
            )
        if self.alignment not in ("umeyama", "irls"):
            raise ValueError(f"alignment must be 'umeyama' or 'irls', got {self.alignment!r}")
        if self.robust_loops not in (None, "huber", "cauchy"):
            raise ValueError(f"robust_loops must be none, 'huber' or 'cauchy', got {self.robust_loops!r}")
        if self.point_stride < 1:
            raise ValueError(f"point_stride must be >= 1, got {self.point_stride}")
        if self.loop_closure and (self.loop_half_window < 1 or 2 * self.loop_half_window > self.chunk_size):
            raise ValueError(
                f"loop_half_window must be in [1, chunk_size / 2], got {self.loop_half_window}"
            )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> PipelineConfig:
        """Build from a dict (e.g. a TOML table); unknown keys are an error naming them."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ValueError(f"unknown configuration keys: {', '.join(unknown)}")
        return cls(**values)


# ------------------------------------------------------------------------------ predictors


class Predictor(Protocol):
    """What the pipeline needs from VGGT (a real runner or the synthetic oracle)."""

    num_frames: int

    def predict(self, frames: np.ndarray) -> ChunkPrediction:
        """One forward pass over the given global frame indices."""
        ...

    def fingerprint(self) -> list[Any]:
        """JSON-able identity of the input (names, sizes, modification times, ...)."""
        ...

    def frame_names(self) -> list[str]:
        """A name per frame (COLMAP image names)."""
        ...


class ImagePredictor:
    """:class:`Predictor` over image files or a video, through an ``inference`` runner.

    Frames are read with :mod:`swiftjax.io.images`, preprocessed as VGGT's loader does
    (:func:`inference.preprocess.preprocess`, ``mode``) and passed to ``runner.predict``
    (``inference.TorchRunner`` or ``inference.OnnxRunner``).
    """

    def __init__(self, source: Any, runner: Any, mode: str = "crop") -> None:
        self.source = source
        self.runner = runner
        self.mode = mode
        self.num_frames = len(source)

    def predict(self, frames: np.ndarray) -> ChunkPrediction:
        from inference.preprocess import preprocess

        images = preprocess([self.source.read(int(k)) for k in frames], mode=self.mode)
        return self.runner.predict(images)

    def fingerprint(self) -> list[Any]:
        return [list(item) for item in self.source.fingerprint()] + [["mode", self.mode]]

    def frame_names(self) -> list[str]:
        return list(self.source.names)


class OraclePredictor:
    """:class:`Predictor` over a :class:`swiftjax.synthetic.oracle.VGGTOracle`."""

    def __init__(self, oracle: Any, description: dict[str, Any] | None = None) -> None:
        self.oracle = oracle
        self.num_frames = int(oracle.num_frames)
        self._description = description or {}

    def predict(self, frames: np.ndarray) -> ChunkPrediction:
        return self.oracle.predict_chunk(np.asarray(frames))

    def fingerprint(self) -> list[Any]:
        return [["synthetic", self.num_frames, self.oracle.seed, self._description]]

    def frame_names(self) -> list[str]:
        return [f"{k:06d}.png" for k in range(self.num_frames)]


# ------------------------------------------------------------------------------- manifest


class _Manifest:
    """``run_dir/manifest.json``: configuration, input fingerprint and finished work."""

    def __init__(self, path: pathlib.Path, data: dict[str, Any]) -> None:
        self.path = path
        self.data = data

    @classmethod
    def open(
        cls, run_dir: pathlib.Path, config: dict[str, Any], inputs: list[Any], overwrite: bool
    ) -> _Manifest:
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


# ------------------------------------------------------------------------------ results


@dataclasses.dataclass
class RunResult:
    """What :func:`reconstruct` produced (also written to ``metrics.json``)."""

    run_dir: pathlib.Path
    num_frames: int
    num_chunks: int
    loops: list[dict[str, Any]]
    chunk_poses: np.ndarray  # [T, 8] optimised chunk-to-world
    chunk_poses_no_loops: np.ndarray  # [T, 8] chained alignment only
    cam_to_world: np.ndarray  # [N, 4, 4] (rotation orthonormal)
    cam_to_world_no_loops: np.ndarray
    intrinsics: np.ndarray  # [N, 3, 3]
    timings: dict[str, float]
    metrics: dict[str, Any]


# ------------------------------------------------------------------------- pure helpers


def chain_poses(relative: np.ndarray) -> np.ndarray:
    """Chunk-to-world poses ``S_0 = I, S_{t+1} = S_t S_{t->t+1}``: ``[T-1, 8] -> [T, 8]`` float64."""
    relative = np.asarray(relative, np.float64).reshape(-1, 8)
    with jax.enable_x64(True):

        def step(s, r):
            nxt = sim3.normalize(sim3.compose(s, r))
            return nxt, nxt

        first = sim3.identity((), jnp.float64)
        if relative.shape[0] == 0:
            return np.asarray(first)[None]
        _, rest = jax.lax.scan(step, first, jnp.asarray(relative))
        return np.concatenate([np.asarray(first)[None], np.asarray(rest)], axis=0)


_as_matrix = jax.jit(sim3.as_matrix)


@jax.jit
def _world_cameras(chunk_pose: jax.Array, extrinsic: jax.Array) -> jax.Array:
    """Camera-to-world ``[S, 4, 4]`` with orthonormal rotation: ``S_t`` composed with each camera.

    ``chunk_pose`` is ``[8]`` or ``[S, 8]`` (each frame's chunk-to-world pose), ``extrinsic``
    ``[S, 3, 4]``.  ``S_t`` scales the chunk; the camera's orientation is ``R_t R_c`` and its
    centre ``S_t(c)``.  Recompiles per ``S``, pose rank and dtype (the export calls it once
    for all frames).
    """
    c2w = camera.camera_to_world(extrinsic)
    R, t, _ = sim3.to_rst(chunk_pose)
    rot = R @ c2w[..., :3, :3]
    centre = sim3.act(chunk_pose, c2w[..., :3, 3])
    top = jnp.concatenate([rot, centre[..., None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0, 0, 0, 1], rot.dtype), (*rot.shape[:-2], 1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def _chunk_points(
    depth: jax.Array, conf: jax.Array, K: jax.Array, K_ref: jax.Array, extrinsic: jax.Array,
    conf_ratio: jax.Array, *, count: int, stride: int,
) -> tuple[jax.Array, jax.Array]:
    """Chunk-frame points ``[count, h, w, 3]`` and keep-mask ``[count, h, w]`` of the first
    ``count`` frames of a chunk, pixel grid subsampled by ``stride`` (``h = ceil(H / stride)``).

    ``depth, conf [S, H, W]``, ``K [S, 3, 3]``, ``extrinsic [S, 3, 4]`` (world-to-camera in
    the chunk frame), ``K_ref [3, 3]``.  Depth is normalised to ``K_ref`` (eq. 1) and
    unprojected with ``K_ref`` (the subsampled grid's intrinsics ``diag(1/stride, 1/stride,
    1) K``) as in the alignment; pixels are kept when finite and ``conf >= conf_ratio x frame
    mean`` (mean over the subsampled grid).  The points stay in the chunk's frame: the export
    applies the optimised ``S_t``.  Jitted as ``_chunk_points_jit``: recompiles per
    ``(S, H, W)``, ``count`` and ``stride`` (two shapes per run: full chunks and the last).
    (Separate dispatches for this, :func:`_to_half` and :func:`_overlap_slices` measured
    ~25 % faster than one jitted function computing all of them: XLA CPU fused the
    consumers of the same input into a slower loop.)
    """
    depth = depth[:count, ::stride, ::stride]
    conf = conf[:count, ::stride, ::stride]
    scale_px = jnp.diag(jnp.array([1.0 / stride, 1.0 / stride, 1.0], depth.dtype))
    d = camera.normalize_depth(depth, scale_px @ K[:count], scale_px @ K_ref)
    pts = camera.unproject(d, scale_px @ K_ref, camera.camera_to_world(extrinsic[:count]))
    finite = jnp.isfinite(conf)
    mean = jnp.sum(jnp.where(finite, conf, 0), axis=(-2, -1), keepdims=True) / jnp.maximum(
        jnp.sum(finite, axis=(-2, -1), keepdims=True), 1
    )
    keep = finite & (conf >= conf_ratio * mean) & jnp.all(jnp.isfinite(pts), axis=-1)
    return pts, keep


@jax.jit
def _to_half(x: jax.Array) -> jax.Array:
    """``x`` as float16 on the device (vectorised; NumPy's float16 cast is a scalar loop,
    measured 8x slower on a KITTI chunk).  Recompiles per shape."""
    return x.astype(jnp.float16)


def _fits_half(x: np.ndarray) -> bool:
    """``max |x| < 65520``: every value finite and stored faithfully as float16.

    The fast path of the chunk store's rule (:func:`~swiftjax.io.chunk_store.half_if_fits`):
    float16's largest finite value is 65504 and values below 65520 round down to it; NaN
    fails both comparisons.  ``False`` sends the caller to the exact rule.  Two vectorised
    NumPy reductions (~2 ms for a KITTI chunk's depth; on the device the same test measured
    3-6 ms on top of the cast).
    """
    return bool(np.max(x) < 65520) and bool(np.min(x) > -65520)


@functools.partial(jax.jit, static_argnames=("overlap",))
def _overlap_slices(depth: jax.Array, conf: jax.Array, *, overlap: int) -> tuple[jax.Array, ...]:
    """``(depth[:O], conf[:O], depth[-O:], conf[-O:])``: a chunk's head (aligned with the
    previous chunk) and tail (with the next), in one dispatch."""
    S = depth.shape[0]
    return depth[:overlap], conf[:overlap], depth[S - overlap:], conf[S - overlap:]


_chunk_points_jit = jax.jit(_chunk_points, static_argnames=("count", "stride"))


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

    def submit(self, key: Any, *args: Any) -> list[Any]:
        """Queue ``store.save(*args)``; returns the keys finished meanwhile (see :meth:`finished`)."""
        done = []
        while len(self.pending) >= self.depth:
            done += self._pop()
        if self.synchronous:
            self.store.save(*args)
            return done + [key]
        self.pending.append((key, self.pool.submit(self.store.save, *args)))
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


# ---------------------------------------------------------------------------- the pipeline


class _Stages:
    """Wall-clock time per stage, in a fixed display order (stages that did not run stay 0)."""

    ORDER = (
        "predict", "predict (loop chunks)", "align", "loop detection", "loop chunks", "pose graph",
        "chunk store", "export",
    )

    def __init__(self) -> None:
        self.seconds: dict[str, float] = dict.fromkeys(self.ORDER, 0.0)

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds


def _progress(iterable: Iterable, enabled: bool, **kwargs: Any) -> Iterable:
    if not enabled:
        return iterable
    from tqdm.auto import tqdm

    return tqdm(iterable, dynamic_ncols=True, **kwargs)


def _with_descriptors(pred: ChunkPrediction) -> ChunkPrediction:
    """Reduce patch tokens to per-frame descriptors at once (tokens are never kept)."""
    if pred.descriptors is not None:
        return dataclasses.replace(pred, patch_tokens=None)
    if pred.patch_tokens is None:
        raise ValueError("the predictor returned neither descriptors nor patch tokens")
    g = np.asarray(loops.frame_descriptor(jnp.asarray(pred.patch_tokens)))
    return dataclasses.replace(pred, descriptors=g, patch_tokens=None)


@jax.jit
def _irls_chunk_pair(
    prev: align.ChunkFrames, cur: align.ChunkFrames, K_ref: jax.Array, depth_threshold: jax.Array,
    conf_ratio: jax.Array,
) -> tuple[jax.Array, align.IRLSInfo, jax.Array]:
    """VGGT-Long's IRLS Sim(3) on the same reliable overlap points (the comparison baseline)."""

    def points(f: align.ChunkFrames) -> tuple[jax.Array, jax.Array]:
        d = camera.normalize_depth(f.depth, f.intrinsic, K_ref)
        return d, camera.unproject(d, K_ref, camera.camera_to_world(f.extrinsic))

    dp, xp = points(prev)
    dc, xc = points(cur)
    ok = align.reliability_mask(dp, dc, prev.conf, cur.conf, depth_threshold, conf_ratio)
    ok = ok & jnp.all(jnp.isfinite(xp), -1) & jnp.all(jnp.isfinite(xc), -1)
    src = jnp.where(ok[..., None], xc, 0.0).reshape(-1, 3)
    dst = jnp.where(ok[..., None], xp, 0.0).reshape(-1, 3)
    S, info = align.irls_sim3(src, dst, ok.reshape(-1).astype(src.dtype))
    return S, info, jnp.sum(ok)


def _align_pair(
    prev: align.ChunkFrames, cur: align.ChunkFrames, K_ref: np.ndarray, config: PipelineConfig,
    loop: bool, name: str,
) -> tuple[np.ndarray, dict[str, Any]]:
    """``S`` mapping ``cur``'s chunk into ``prev``'s, with the configured method, and diagnostics."""
    options = _align_options(config, loop)
    if config.alignment == "irls":
        f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
        S, info, count = _irls_chunk_pair(
            align.ChunkFrames(*map(f32, prev)), align.ChunkFrames(*map(f32, cur)), f32(K_ref),
            f32(options["depth_threshold"]), f32(options["conf_ratio"]),
        )
        ok = bool(np.all(np.isfinite(np.asarray(S)))) and int(count) >= 3
        if not ok:
            S = sim3.identity((), jnp.float32)
        diag = {"num_points": int(count), "fraction_used": float(count) / np.size(prev.depth),
                "rms": float("nan"), "valid": ok, "used_fallback_threshold": False, "pose_fallback": not ok}
        return np.asarray(S, np.float64), diag
    S, info = align.align_chunk_pair_checked(prev, cur, K_ref, name=name, **options)
    return np.asarray(S, np.float64), _info_dict(info)


def _align_options(config: PipelineConfig, loop: bool) -> dict[str, Any]:
    return dict(
        depth_threshold=config.loop_depth_threshold if loop else config.depth_threshold,
        conf_ratio=config.conf_ratio,
        min_points=config.min_points,
        fallback_depth_threshold=max(
            config.fallback_depth_threshold, config.loop_depth_threshold if loop else 0.0
        ),
    )


def _info_dict(info: align.AlignInfo) -> dict[str, Any]:
    return {
        "num_points": int(info.num_points),
        "fraction_used": float(info.fraction_used),
        "rms": float(info.rms),
        "valid": bool(info.valid),
        "used_fallback_threshold": bool(info.used_fallback_threshold),
        "pose_fallback": bool(info.pose_fallback),
    }


def reconstruct(
    predictor: Predictor,
    run_dir: str | pathlib.Path,
    config: PipelineConfig = PipelineConfig(),
    *,
    ground_truth: np.ndarray | None = None,
    overwrite: bool = False,
    progress: bool = True,
    timestamps: Sequence[float] | None = None,
    log: Callable[[str], None] = print,
) -> RunResult:
    """Run SwiftVGGT over every frame of ``predictor`` and write the outputs to ``run_dir``.

    Args:
        predictor: a :class:`Predictor` (e.g. :class:`OraclePredictor`, or
            ``inference.runners``' image predictor).
        run_dir: output folder (created; resumable, see the module docstring).
        config: method parameters.
        ground_truth: optional ``[N, 4, 4]`` camera-to-world reference for ATE/RPE.
        overwrite: replace a run directory that belongs to another input/configuration.
        progress: show tqdm progress bars.
        timestamps: ``[N]`` times for ``poses_tum.txt`` (default: the frame index).
        log: where one-line messages go.

    Returns:
        :class:`RunResult`; the files are ``poses_kitti.txt``, ``poses_tum.txt``,
        ``intrinsics.txt``, ``points.ply``, ``loops.txt``, ``trajectory.png``,
        ``metrics.json``, ``colmap/{cameras,images,points3D}.txt`` and the chunk store.
    """
    run_dir = pathlib.Path(run_dir)
    n = int(predictor.num_frames)
    if n < 1:
        raise ValueError("the input has no frames")
    if ground_truth is not None:
        ground_truth = np.asarray(ground_truth, np.float64)
        if ground_truth.shape[0] != n or ground_truth.shape[1:] not in ((4, 4), (3, 4)):
            raise ValueError(f"ground truth has shape {ground_truth.shape}, expected [{n}, 4, 4]")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RunDirError(f"cannot create output directory {run_dir}: {err.strerror}") from err
    if not _writable(run_dir):
        raise RunDirError(f"output directory {run_dir} is not writable")

    schedule = chunks.chunk_schedule(n, config.chunk_size, config.overlap)
    manifest = _Manifest.open(run_dir, config.to_dict(), predictor.fingerprint(), overwrite)
    store = ChunkStore(run_dir)
    stages = _Stages()
    T = schedule.num_chunks

    # ----------------------------------------------------------------- temporal chunks
    # Stage clocks: the predictor's calls are booked as "predict" (and "predict (loop
    # chunks)"), everything else as geometry: descriptors under "loop detection"; the
    # float16 conversion, chunk-file and manifest writes (and waits for the background
    # writer) under "chunk store"; the chunk-frame export points under "export".
    descriptors: np.ndarray | None = None
    relative = np.zeros((max(T - 1, 0), 8))
    align_infos: list[dict[str, Any]] = []
    K_ref: np.ndarray | None = None
    prev_tail: align.ChunkFrames | None = None
    O = config.overlap
    writer = _BackgroundWriter(store)
    # An edge (t-1, t) enters the manifest once chunk t's file is complete (a resumed run
    # never pairs a stored edge with a re-predicted chunk).
    pending_edges: dict[int, dict[str, Any]] = {}

    def commit(done: list[int]) -> bool:
        for c in done:
            manifest.data["chunks"][str(c)] = True
            if c in pending_edges:
                manifest.data["edges"][str(c - 1)] = pending_edges.pop(c)
        return bool(done)

    try:
        for t in _progress(range(T), progress, desc="chunks", unit="chunk"):
            frames = schedule.frames(t)
            S = len(frames)
            edge = manifest.data["edges"].get(str(t - 1)) if t > 0 else None
            head: align.ChunkFrames | None = None
            if manifest.data["chunks"].get(str(t)) and store.exists("chunk", t):
                # Resume: read back only what the rest of the run needs from this chunk.
                t0 = time.perf_counter()
                desc = store.load_array("chunk", t, "descriptors")
                if K_ref is None:
                    K_ref = np.asarray(store.load_array("chunk", t, "intrinsic")[0], np.float64)
                if t > 0 and edge is None:
                    head = align.ChunkFrames.from_prediction(store.load("chunk", t, frames=slice(0, O), fields=()))
                tail = align.ChunkFrames.from_prediction(store.load("chunk", t, frames=slice(S - O, S), fields=()))
                stages.add("chunk store", time.perf_counter() - t0)
                dirty = commit(writer.finished())
            else:
                t0 = time.perf_counter()
                pred = predictor.predict(frames)
                stages.add("predict", time.perf_counter() - t0)
                if pred.num_frames != len(frames):
                    raise ValueError(
                        f"the predictor returned {pred.num_frames} frames for chunk {t} of {len(frames)}"
                    )
                t0 = time.perf_counter()
                pred = _with_descriptors(pred)
                desc = pred.descriptors
                stages.add("loop detection", time.perf_counter() - t0)
                if K_ref is None:
                    K_ref = np.asarray(pred.intrinsic[0], np.float64)

                # One host->device copy of the dense maps, shared by the float16 store copies,
                # the export points and the alignment's overlap slices (async dispatches).
                t0 = time.perf_counter()
                f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
                depth_d, conf_d = f32(pred.depth), f32(pred.conf)
                halves = _to_half(depth_d), _to_half(conf_d)
                head_d, head_c, tail_d, tail_c = _overlap_slices(depth_d, conf_d, overlap=O)
                count = int(schedule.starts[t + 1] - schedule.starts[t]) if t + 1 < T else S
                pts, keep = _chunk_points_jit(
                    depth_d, conf_d, f32(pred.intrinsic), f32(K_ref), f32(pred.extrinsic),
                    jnp.float32(config.point_conf_ratio), count=count, stride=config.point_stride,
                )
                points = _export_points(pred, pts, keep, config.point_stride)
                stages.add("export", time.perf_counter() - t0)

                t0 = time.perf_counter()
                depth, conf = (
                    np.asarray(half) if _fits_half(x) else half_if_fits(x)
                    for half, x in zip(halves, (pred.depth, pred.conf))
                )
                # Images only feed the export points' colours (taken above): not stored.
                stored = dataclasses.replace(pred, depth=depth, conf=conf, images=None)
                dirty = commit(writer.submit(t, "chunk", t, stored, {"frames": frames, **points}))
                stages.add("chunk store", time.perf_counter() - t0)
                head = align.ChunkFrames(head_d, head_c, pred.intrinsic[:O], pred.extrinsic[:O])
                tail = align.ChunkFrames(tail_d, tail_c, pred.intrinsic[S - O:], pred.extrinsic[S - O:])
                del pred, stored, depth, conf, depth_d, conf_d, halves, pts, keep

            if descriptors is None:
                descriptors = np.zeros((n, desc.shape[1]), np.float32)
            descriptors[frames] = desc

            t0 = time.perf_counter()
            if t > 0:
                if edge is None:
                    assert head is not None and prev_tail is not None
                    S_rel, diag = _align_pair(prev_tail, head, K_ref, config, False, f"chunks {t - 1}/{t}")
                    edge = {"S": S_rel.tolist(), **diag}
                    if manifest.data["chunks"].get(str(t)):
                        manifest.data["edges"][str(t - 1)] = edge
                        dirty = True
                    else:
                        pending_edges[t] = edge
                relative[t - 1] = edge["S"]
                align_infos.append(edge)
            prev_tail = tail
            del head
            stages.add("align", time.perf_counter() - t0)

            if dirty:
                t0 = time.perf_counter()
                manifest.save_soon()
                stages.add("chunk store", time.perf_counter() - t0)
        t0 = time.perf_counter()
        commit(writer.finished(wait=True))
        manifest.flush()
        stages.add("chunk store", time.perf_counter() - t0)
    finally:
        writer.close()
        with contextlib.suppress(Exception):  # interrupted: keep every complete chunk file
            commit(writer.finished(wait=True))
        manifest.flush()
    assert descriptors is not None and K_ref is not None
    chunk_poses_no_loops = chain_poses(relative)

    # --------------------------------------------------------------------- loop closure
    loop_records: list[dict[str, Any]] = []
    loop_edges: list[tuple[int, int, np.ndarray]] = []
    if config.loop_closure and T > 2:
        t0 = time.perf_counter()
        found = loops.find_loops(
            descriptors,
            schedule,
            threshold=config.loop_threshold,
            beta=config.power_beta,
            remove=config.whitening_remove,
            dim=config.whitening_dim,
            min_separation=config.loop_min_separation,
            nms_radius=config.loop_nms_radius,
            top_k=config.loop_top_k,
            half_window=config.loop_half_window,
        )
        # A loop between neighbouring chunks duplicates their temporal edge: drop it.
        found = [lp for lp in found if abs(lp.chunk_i - lp.chunk_j) >= 2]
        stages.add("loop detection", time.perf_counter() - t0)

        t0 = time.perf_counter()
        predict_seconds = 0.0
        hw2 = 2 * config.loop_half_window
        try:
            for lp in _progress(found, progress, desc="loop chunks", unit="loop"):
                key = f"{lp.i}-{lp.j}"
                record = manifest.data["loop_edges"].get(key)
                if record is None:
                    t1 = time.perf_counter()
                    pred = predictor.predict(lp.frames)
                    predict_seconds += time.perf_counter() - t1
                    halves = []
                    for half, c in ((slice(0, hw2), lp.chunk_i), (slice(hw2, 2 * hw2), lp.chunk_j)):
                        # Only the 2 x half_window frames of chunk c that the loop chunk overlaps.
                        local = lp.frames[half] - schedule.starts[c]
                        chunk_frames = store.load("chunk", c, frames=local, fields=())
                        halves.append(_align_pair(
                            align.ChunkFrames.from_prediction(chunk_frames), align.ChunkFrames.from_prediction(pred, half),
                            K_ref, config, True, f"loop ({lp.i}, {lp.j}) to chunk {c}",
                        ))
                    with jax.enable_x64(True):
                        Z = np.asarray(loops.loop_edge(jnp.asarray(halves[0][0]), jnp.asarray(halves[1][0])))
                    record = {
                        "i": lp.i, "j": lp.j, "score": lp.score, "chunk_i": lp.chunk_i,
                        "chunk_j": lp.chunk_j, "Z": Z.tolist(),
                        "align_i": halves[0][1], "align_j": halves[1][1],
                    }
                    manifest.data["loop_edges"][key] = record
                    manifest.save_soon()
                loop_records.append(record)
                # Edge (c_j, c_i): Z maps chunk c_i coordinates into chunk c_j (loops.loop_edge).
                loop_edges.append((record["chunk_j"], record["chunk_i"], np.asarray(record["Z"])))
        finally:
            manifest.flush()  # also when interrupted: keep the finished loop edges
        stages.add("loop chunks", time.perf_counter() - t0 - predict_seconds)
        stages.add("predict (loop chunks)", predict_seconds)

    # ------------------------------------------------------------------------ pose graph
    t0 = time.perf_counter()
    graph_metrics: dict[str, Any] = {}
    if loop_edges:
        edges = [(t, t + 1) for t in range(T - 1)] + [(a, b) for a, b, _ in loop_edges]
        meas = np.concatenate([relative, np.stack([z for _, _, z in loop_edges])])
        robust = np.arange(len(edges)) >= T - 1
        with jax.enable_x64(True):
            problem = posegraph.Problem(
                jnp.asarray(chunk_poses_no_loops), np.asarray(edges, np.int32), jnp.asarray(meas),
                robust=robust,
            )
            res = posegraph.optimize(
                problem, max_steps=config.max_lm_steps, kernel=config.robust_loops,
                kernel_scale=config.robust_scale,
            )
            chunk_poses = np.asarray(sim3.normalize(res.poses), np.float64)
        graph_metrics = {
            "cost_initial": res.cost_initial, "cost_final": res.cost_final,
            "iterations": res.num_steps, "converged": res.converged, "status": res.status,
            "compile_seconds": res.compile_seconds, "solve_seconds": res.solve_seconds,
        }
        if not res.converged:
            warnings.warn(f"pose graph did not converge ({res.status})", RuntimeWarning, stacklevel=2)
    else:
        chunk_poses = chunk_poses_no_loops
    stages.add("pose graph", time.perf_counter() - t0)

    # ---------------------------------------------------------------------------- export
    t0 = time.perf_counter()
    exported = _export(
        predictor, run_dir, schedule, store, config, K_ref, chunk_poses, chunk_poses_no_loops,
        progress, timestamps,
    )
    _write_loops(run_dir / "loops.txt", loop_records)
    stages.add("export", time.perf_counter() - t0)

    metrics = _metrics(
        n, T, loop_records, align_infos, graph_metrics, stages.seconds, exported, ground_truth
    )
    with atomic_write(run_dir / "metrics.json") as f:
        json.dump(metrics, f, indent=1)
    _plot(run_dir / "trajectory.png", exported, ground_truth, loop_records)
    return RunResult(
        run_dir=run_dir,
        num_frames=n,
        num_chunks=T,
        loops=loop_records,
        chunk_poses=chunk_poses,
        chunk_poses_no_loops=chunk_poses_no_loops,
        cam_to_world=exported["cam_to_world"],
        cam_to_world_no_loops=exported["cam_to_world_no_loops"],
        intrinsics=exported["intrinsics"],
        timings=dict(stages.seconds),
        metrics=metrics,
    )


def _writable(path: pathlib.Path) -> bool:
    probe = path / ".swiftjax-write-test"
    try:
        probe.write_bytes(b"")
        probe.unlink()
        return True
    except OSError:
        return False


def _export_points(
    pred: ChunkPrediction, points: jax.Array, keep: jax.Array, stride: int
) -> dict[str, np.ndarray]:
    """Chunk ``t``'s share of ``points.ply``, in the chunk's own frame, as chunk-store extras.

    The frames a chunk owns are ``[start_t, start_{t+1})`` (the later chunk wins overlaps;
    the last chunk owns all its frames).  Their pixels on the ``point_stride`` grid that pass
    the confidence filter (:func:`_chunk_points`) are taken
    while the chunk is in memory, so the export never re-reads the dense maps: it only
    applies the optimised ``S_t``.  Returns ``points_xyz [P, 3]`` float32, ``points_conf
    [P]`` float32, ``points_rgb [P, 3]`` uint8 (if the prediction has images),
    ``points_grid`` (subsampled ``h, w``) and ``image_hw``.
    """
    keep = np.asarray(keep)
    count, h, w = keep.shape
    idx = np.flatnonzero(keep)  # one compaction index for every per-pixel array
    out = {
        "points_xyz": np.asarray(points).reshape(-1, 3)[idx],
        "points_conf": np.asarray(pred.conf[:count, ::stride, ::stride], np.float32).reshape(-1)[idx],
        "points_grid": np.asarray((h, w), np.int64),
        "image_hw": np.asarray(pred.image_hw, np.int64),
    }
    if pred.images is not None:
        out["points_rgb"] = np.asarray(pred.images[:count, ::stride, ::stride]).reshape(-1, 3)[idx]
    return out


def _export(
    predictor: Predictor,
    run_dir: pathlib.Path,
    schedule: chunks.ChunkSchedule,
    store: ChunkStore,
    config: PipelineConfig,
    K_ref: np.ndarray,
    chunk_poses: np.ndarray,
    chunk_poses_no_loops: np.ndarray,
    progress: bool,
    timestamps: Sequence[float] | None,
) -> dict[str, Any]:
    """The final pass over the chunk store: world poses, points, COLMAP model.

    Reads each chunk's extrinsics, intrinsics and chunk-frame points (:func:`_export_points`;
    never the dense maps), maps the points to the world with the optimised ``S_t`` (float64,
    written as float32) and streams them into ``points.ply``.
    """
    from swiftjax.io import colmap, ply, trajectory

    n = schedule.n_frames
    T = schedule.num_chunks
    owner = np.searchsorted(schedule.starts, np.arange(n), side="right") - 1  # later chunk wins
    extrinsics = np.zeros((n, 3, 4))
    intrinsics = np.zeros((n, 3, 3))
    with jax.enable_x64(True):
        world = np.asarray(_as_matrix(jnp.asarray(chunk_poses, jnp.float64)))  # [T, 4, 4] s R | t
    rng = np.random.default_rng(0)
    colmap_pts: list[np.ndarray] = []
    colmap_rgb: list[np.ndarray] = []
    image_hw: tuple[int, int] | None = None
    total_points = 0
    with ply.PlyStreamWriter(run_dir / "points.ply") as cloud:
        for t in _progress(range(T), progress, desc="export", unit="chunk"):
            frames = schedule.frames(t)
            own = owner[frames] == t
            extrinsics[frames[own]] = store.load_array("chunk", t, "extrinsic")[own]
            intrinsics[frames[own]] = store.load_array("chunk", t, "intrinsic")[own]
            extra = store.load_extra("chunk", t)
            image_hw = (int(extra["image_hw"][0]), int(extra["image_hw"][1]))
            grid_size = int(np.prod(extra["points_grid"]))
            M = world[t]
            # s R x + t in float32 (the precision the points are written in).  einsum, not a
            # BLAS matmul: [P, 3] x [3, 3] through multi-threaded OpenBLAS measured ~60 ms per
            # chunk on a busy 2-core machine, einsum ~5 ms whatever the thread settings.
            xyz = np.einsum("nj,ij->ni", extra["points_xyz"], M[:3, :3].astype(np.float32))
            xyz += M[:3, 3].astype(np.float32)
            cf = extra["points_conf"]
            rgb = extra["points_rgb"] if "points_rgb" in extra else np.full((xyz.shape[0], 3), 200, np.uint8)
            if config.voxel_size:
                down = ply.voxel_downsample(xyz, rgb, cf, config.voxel_size)
                xyz, rgb, cf = down.points, down.colors, down.conf
            cloud.append(xyz.astype(np.float32), rgb, cf.astype(np.float32))
            total_points += xyz.shape[0]
            # A uniform sample for COLMAP's points3D.txt (text, slow for millions of points):
            # twice the budget over all pixels in expectation, cut to the budget at the end.
            take = rng.random(xyz.shape[0]) < 2.0 * config.colmap_max_points / max(1, n * grid_size)
            colmap_pts.append(xyz[take])
            colmap_rgb.append(rgb[take])

    with jax.enable_x64(True):
        ext = jnp.asarray(extrinsics, jnp.float64)
        c2w = np.asarray(_world_cameras(jnp.asarray(chunk_poses[owner], jnp.float64), ext))
        c2w_no_loops = np.asarray(_world_cameras(jnp.asarray(chunk_poses_no_loops[owner], jnp.float64), ext))

    ts = np.arange(n, dtype=np.float64) if timestamps is None else np.asarray(timestamps, np.float64)
    trajectory.write_kitti(run_dir / "poses_kitti.txt", c2w)
    trajectory.write_tum(run_dir / "poses_tum.txt", ts, c2w)
    _write_intrinsics(run_dir / "intrinsics.txt", intrinsics)
    pts_all = np.concatenate(colmap_pts) if colmap_pts else np.zeros((0, 3))
    rgb_all = np.concatenate(colmap_rgb) if colmap_rgb else np.zeros((0, 3), np.uint8)
    if pts_all.shape[0] > config.colmap_max_points:
        idx = np.sort(rng.choice(pts_all.shape[0], config.colmap_max_points, replace=False))
        pts_all, rgb_all = pts_all[idx], rgb_all[idx]
    assert image_hw is not None
    h, w = image_hw
    # After depth normalisation every frame shares K_ref (as the exported points do).
    colmap.write_colmap_text(
        run_dir / "colmap", c2w, np.broadcast_to(K_ref, (n, 3, 3)), predictor.frame_names(),
        image_size=(w, h), points=pts_all, colors=rgb_all,
    )
    return {
        "cam_to_world": c2w,
        "cam_to_world_no_loops": c2w_no_loops,
        "intrinsics": intrinsics,
        "num_points": total_points,
    }


def _write_intrinsics(path: pathlib.Path, intrinsics: np.ndarray) -> None:
    """One line per frame: ``fx fy cx cy`` (VGGT's predicted intrinsics at the model's resolution)."""
    with atomic_write(path) as f:
        f.write("# frame fx fy cx cy (pixels; principal point with integer pixel centres)\n")
        for k, K in enumerate(intrinsics):
            f.write(f"{k} {K[0, 0]:.6f} {K[1, 1]:.6f} {K[0, 2]:.6f} {K[1, 2]:.6f}\n")


def _write_loops(path: pathlib.Path, records: list[dict[str, Any]]) -> None:
    with atomic_write(path) as f:
        f.write("# i j score chunk_i chunk_j points_i points_j\n")
        for r in records:
            f.write(
                f"{r['i']} {r['j']} {r['score']:.6f} {r['chunk_i']} {r['chunk_j']} "
                f"{r['align_i']['num_points']} {r['align_j']['num_points']}\n"
            )


def _metrics(
    n: int,
    T: int,
    loop_records: list[dict[str, Any]],
    align_infos: list[dict[str, Any]],
    graph: dict[str, Any],
    timings: dict[str, float],
    exported: dict[str, Any],
    ground_truth: np.ndarray | None,
) -> dict[str, Any]:
    out: dict[str, Any] = {
        "frames": n,
        "chunks": T,
        "loops": len(loop_records),
        "points": int(exported["num_points"]),
        "timings_seconds": timings,
        "alignment": {
            "pairs": len(align_infos),
            "mean_points": float(np.mean([a["num_points"] for a in align_infos])) if align_infos else 0.0,
            "fallback_threshold_used": int(sum(a["used_fallback_threshold"] for a in align_infos)),
            "pose_fallbacks": int(sum(a["pose_fallback"] for a in align_infos)),
        },
        "pose_graph": graph,
    }
    if ground_truth is not None:
        from swiftjax import evaluation

        gt = ground_truth[:, :3, 3]
        out["ate_rmse"] = evaluation.ate(exported["cam_to_world"][:, :3, 3], gt).rmse
        out["ate_rmse_no_loops"] = evaluation.ate(exported["cam_to_world_no_loops"][:, :3, 3], gt).rmse
    return out


def _plot(
    path: pathlib.Path, exported: dict[str, Any], ground_truth: np.ndarray | None,
    loop_records: list[dict[str, Any]],
) -> None:
    """Top view of the trajectory (Sim(3)-aligned to the ground truth when given), loops drawn."""
    from swiftjax import evaluation
    from swiftjax.io import plot

    estimate = exported["cam_to_world"][:, :3, 3]
    reference = None
    title = "swiftjax trajectory"
    if ground_truth is not None:
        reference = ground_truth[:, :3, 3]
        result = evaluation.ate(estimate, reference)
        estimate = result.aligned
        title = f"ATE {result.rmse:.3g} m (Sim(3)-aligned)"
    pairs = np.array([(r["i"], r["j"]) for r in loop_records], dtype=np.int64).reshape(-1, 2)
    plot.plot_trajectory(path, estimate, reference=reference, loops=pairs, title=title)


def summary_table(result: RunResult) -> str:
    """The end-of-run summary: sizes, time per stage, ATE with and without loop closure."""
    from swiftjax.report import markdown_table

    m = result.metrics
    rows: list[list[Any]] = [
        ["frames", m["frames"]],
        ["chunks", m["chunks"]],
        ["loops closed", m["loops"]],
        ["points written", m["points"]],
    ]
    rows += [[f"time: {k} (s)", float(v)] for k, v in m["timings_seconds"].items()]
    if "ate_rmse" in m:
        rows += [
            ["ATE rmse, loop closure (m)", float(m["ate_rmse"])],
            ["ATE rmse, no loop closure (m)", float(m["ate_rmse_no_loops"])],
        ]
    return f"{result.run_dir}\n" + markdown_table(["", "value"], rows)

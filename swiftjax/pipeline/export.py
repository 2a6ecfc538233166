"""The final pass: world poses, the point cloud, the COLMAP model and the text outputs.

Each temporal chunk's share of ``points.ply`` is taken while the chunk is in memory
(:func:`chunk_points`, :func:`export_points`; saved in its chunk file, in the chunk's
frame, with the pixel each point came from), and so are its frames as PNG for the COLMAP
model (:meth:`ChunkExport.write_frames`; the chunk store keeps no images): the temporal stage
hands each chunk to a :class:`ChunkExport` it is given, and stores what it returns.
:func:`run` then reads only points and poses from the chunk store -- never the dense maps --
and applies the optimised ``S_t``.  The export owns ``colmap/images/`` (it writes, checks and
cleans it: :func:`clean`) and the list of its files in the outputs record (:func:`output_files`).

Files (every text file starts with ``#`` lines saying what it holds; evo skips them):

* ``poses_kitti.txt``, ``poses_tum.txt``: camera-to-world, with the unit of the poses (up
  to scale unless the run knows a metric scale) and, for TUM, where the times come from;
* ``intrinsics.txt``: VGGT's per-frame ``K`` at the model's resolution, and ``K_ref``;
* ``points.ply``; ``chunk_poses.json`` (``S_t`` with and without loop closure, for the
  viewer); ``frames.txt`` (frame index -> image name);
* ``colmap/images/*.png`` + ``colmap/sparse/0/{cameras,images,points3D}.bin`` (``.txt`` too
  with ``colmap_text``): a model gsplat (``--data_dir RUN/colmap``) and nerfstudio
  (``--data RUN/colmap --colmap-path sparse/0``) load as is;
* ``loops.txt``: every loop candidate with the keys its record carries.

**Why one shared camera ``K_ref`` in the COLMAP model** (not VGGT's per-frame ``K``): the
exported points are unprojected with ``K_ref`` after the depth normalisation (eq. 1), and
the poses were aligned on those points, so ``K_ref`` is the camera under which every 3-D
point lands on the pixel it came from (reprojection error ~1e-4 px, float32 rounding).
Under the per-frame ``K`` the same observations are off by ``|K_f K_ref^-1 p - p|``
(``bench/bench_colmap_export.py`` measures it on the demo).
"""

from __future__ import annotations

import json
import logging
import pathlib
import zlib
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import _faults, camera, sim3
from swiftjax._compile import LOOP_EMITTER, quick_jit
from swiftjax.align import frame_conf_mean
from swiftjax.io.atomic import atomic_path, atomic_paths, atomic_write
from swiftjax.options import OptionError
from swiftjax.pipeline.results import LoopResult, ScaleResult, TemporalResult
from swiftjax.pipeline.rundir import RunContext
from swiftjax.prediction import ChunkPrediction
from swiftjax.sampling import Reservoir

__all__ = [
    "clean",
    "check",
    "run",
    "ChunkExport",
    "chunk_points",
    "chunk_points_jit",
    "export_points",
    "output_files",
]

logger = logging.getLogger(__name__)

_CAMERA_AXES = "OpenCV camera axes (x right, y down, z forward)"


def clean(ctx: RunContext) -> None:
    """Remove the COLMAP frames of input frames that are gone (frames added or removed since the
    last run: ``ctx.manifest.previous_names``)."""
    from swiftjax.io.colmap import image_names

    if ctx.manifest.previous_names is not None:
        old, new = ctx.manifest.previous_names, list(ctx.predictor.frame_names())
        for name in (set(old) | set(image_names(old))) - (set(new) | set(image_names(new))):
            (ctx.run_dir / "colmap" / "images" / name).unlink(missing_ok=True)


def check(ctx: RunContext) -> None:
    """Refuse, before any work, output options the input cannot satisfy (``ValueError``)."""
    if ctx.config.colmap and ctx.config.colmap_original_resolution:
        original_source(ctx)
        spaced = [n for n in ctx.predictor.frame_names() if any(c.isspace() for c in n)]
        if spaced:
            raise OptionError(
                f"colmap_original_resolution keeps the input's file names, and COLMAP's names cannot hold "
                f"white space: {spaced[0]!r} ({len(spaced)} such files); rename them or export at the "
                "model's resolution (PNG names with '_')"
            )


def run(
    ctx: RunContext,
    temporal: TemporalResult,
    scaled: ScaleResult,
    loops: LoopResult,
    chunks: ChunkExport,
    timestamps: Sequence[float] | None = None,
    timestamps_note: str | None = None,
) -> dict[str, Any]:
    """Write every output of the run but the report's; returns ``cam_to_world``,
    ``cam_to_world_no_loops`` ``[N, 4, 4]``, ``intrinsics [N, 3, 3]``, ``num_points``, a
    uniform sample of the cloud (``sample_points [M, 3]``, ``sample_colors [M, 3]``, M <= 1e5)
    for ``points.png`` and ``frame_crcs`` (the COLMAP frames checked, for :func:`output_files`).

    ``chunks``: the run's :class:`ChunkExport` (the frames it wrote); ``timestamps`` ``[N]``
    seconds for ``poses_tum.txt`` (default: the frame index) and ``timestamps_note`` where they
    come from (said in the file's header)."""
    graph = scaled.graph
    with ctx.timer("export"):
        exported = _export(
            ctx,
            temporal.K_ref,
            graph.chunk_poses,
            graph.chunk_poses_no_loops,
            scaled.unit,
            chunks,
            timestamps,
            timestamps_note,
        )
        write_loops(ctx.run_dir / "loops.txt", loops.records)
    return exported


def chunk_points(
    depth: jax.Array,
    conf: jax.Array,
    K: jax.Array,
    K_ref: jax.Array,
    extrinsic: jax.Array,
    conf_ratio: jax.Array,
    mask: jax.Array | None = None,
    *,
    count: int,
    stride: int,
) -> tuple[jax.Array, jax.Array]:
    """Chunk-frame points ``[count, h, w, 3]`` and keep-mask ``[count, h, w]`` of the first
    ``count`` frames of a chunk, pixel grid subsampled by ``stride`` (``h = ceil(H / stride)``).

    ``depth, conf [S, H, W]``, ``K [S, 3, 3]``, ``extrinsic [S, 3, 4]`` (world-to-camera in
    the chunk frame), ``K_ref [3, 3]``.  Depth is normalised to ``K_ref`` (eq. 1) and
    unprojected with ``K_ref`` (the subsampled grid's intrinsics ``diag(1/stride, 1/stride,
    1) K``) as in the alignment; pixels are kept when finite and ``conf >= conf_ratio x frame
    mean`` (mean over the subsampled grid) and kept by ``mask [S, H, W]`` (user / sky masks;
    ``None``: every pixel).  The points stay in the chunk's frame: the export
    applies the optimised ``S_t``.  Jitted as :data:`chunk_points_jit`: recompiles per
    ``(S, H, W)``, ``count`` and ``stride`` (two shapes per run: full chunks and the last).
    (Separate dispatches for this, :func:`_to_half` and :func:`_overlap_slices`: one jitted
    function computing all of them was slower, XLA CPU fusing the consumers of the same input
    into one slower loop; docs/performance/pipeline.md.)
    """
    depth = depth[:count, ::stride, ::stride]
    conf = conf[:count, ::stride, ::stride]
    scale_px = jnp.diag(jnp.array([1.0 / stride, 1.0 / stride, 1.0], depth.dtype))
    d = camera.normalize_depth(depth, scale_px @ K[:count], scale_px @ K_ref)
    pts = camera.unproject(d, scale_px @ K_ref, camera.camera_to_world(extrinsic[:count]))
    finite = jnp.isfinite(conf)
    mean = frame_conf_mean(conf)[:, None, None]  # NaN for a frame without finite pixel: none kept
    keep = finite & (conf >= conf_ratio * mean) & jnp.all(jnp.isfinite(pts), axis=-1)
    if mask is not None:
        keep = keep & mask[:count, ::stride, ::stride]
    return pts, keep


chunk_points_jit = quick_jit(chunk_points, options=LOOP_EMITTER, static_argnames=("count", "stride"))


def export_points(pred: ChunkPrediction, points: jax.Array, keep: jax.Array, stride: int) -> dict[str, np.ndarray]:
    """Chunk ``t``'s share of ``points.ply``, in the chunk's own frame, as chunk-store extras.

    The frames a chunk owns are ``[start_t, start_{t+1})`` (the later chunk wins overlaps;
    the last chunk owns all its frames).  Their pixels on the ``point_stride`` grid that pass
    the confidence filter (:func:`chunk_points`) are taken
    while the chunk is in memory, so the export never re-reads the dense maps: it only
    applies the optimised ``S_t``.  Returns ``points_xyz [P, 3]`` float32, ``points_conf
    [P]`` float32, ``points_rgb [P, 3]`` uint8 (if the prediction has images),
    ``points_pixel [P]`` int32 (the flat index ``(f h + r) w + c`` into the ``[count, h, w]``
    grid: frame ``f`` of the chunk, pixel ``(c stride, r stride)``; the COLMAP observations),
    ``points_grid`` (subsampled ``h, w``) and ``image_hw``.
    """
    keep = np.asarray(keep)
    count, h, w = keep.shape
    idx = np.flatnonzero(keep)  # one compaction index for every per-pixel array
    out = {
        "points_xyz": np.asarray(points).reshape(-1, 3)[idx],
        "points_conf": np.asarray(pred.conf[:count, ::stride, ::stride], np.float32).reshape(-1)[idx],
        "points_pixel": idx.astype(np.int32),
        "points_grid": np.asarray((h, w), np.int64),
        "image_hw": np.asarray(pred.image_hw, np.int64),
    }
    if pred.images is not None:
        out["points_rgb"] = np.asarray(pred.images[:count, ::stride, ::stride]).reshape(-1, 3)[idx]
    return out


def frame_image_names(ctx: RunContext) -> list[str]:
    """The image file name of every frame in ``colmap/images/``: the input's own names with
    ``colmap_original_resolution`` (the original files are copied), else PNG names
    (:func:`swiftjax.io.colmap.image_names`) of the frames at the model's resolution."""
    from swiftjax.io.colmap import image_names

    names = ctx.predictor.frame_names()
    return list(names) if ctx.config.colmap_original_resolution else image_names(names)


def colmap_frame_paths(ctx: RunContext) -> list[str]:
    """``colmap/images/<name>`` of every frame this run's COLMAP export holds (none without
    ``colmap``), relative to the run directory."""
    return [f"colmap/images/{name}" for name in frame_image_names(ctx)] if ctx.config.colmap else []


def output_files(
    ctx: RunContext,
    targets: Sequence[pathlib.Path],
    frame_crcs: dict[str, str] | None,
) -> dict[str, str | None]:
    """The outputs record of an export (:func:`swiftjax.pipeline.rundir.record_outputs`): every
    file of ``targets`` and every COLMAP frame on disk, relative to the run directory, mapped to
    None, or, with ``frame_crcs`` (after the renames), the COLMAP frames at the model's
    resolution to the CRC32 of their bytes (checked by the next run's :func:`_check_frames`)."""
    run_dir = ctx.run_dir
    files: dict[str, str | None] = {p.relative_to(run_dir).as_posix(): None for p in map(pathlib.Path, targets)}
    for rel in colmap_frame_paths(ctx):
        if rel in files or (run_dir / rel).is_file():  # (a predictor without images writes none)
            files[rel] = None
    if frame_crcs is not None and not ctx.config.colmap_original_resolution:
        for rel in files:
            if rel.startswith("colmap/images/"):
                crc = frame_crcs.get(rel)
                files[rel] = crc if crc is not None or not (run_dir / rel).is_file() else _file_crc(run_dir / rel)
    return files


def _file_crc(path: pathlib.Path) -> str:
    crc = 0
    with open(path, "rb") as f:
        while block := f.read(1 << 22):
            crc = zlib.crc32(block, crc)
    return f"{crc:08x}"


def _check_frames(ctx: RunContext, names: list[str], frames_written: set[str]) -> tuple[set[str], dict[str, str]]:
    """The COLMAP frames at the model's resolution, checked against the outputs record
    (:func:`swiftjax.pipeline.rundir.record_outputs`): a frame missing, or one whose bytes
    fail the CRC32 recorded when it was written, is written again from the predictor's
    ``images`` (the preprocessed input; no prediction) and reported.  A predictor without
    ``images`` has the chunk holding such a frame predicted again (raises
    :class:`~swiftjax.io.chunk_store.ChunkMismatchError` on that chunk's file).  Frames this
    run wrote (``frames_written``), and those no record lists, are taken as they are (a missing
    one is warned about by :func:`_export`).  Returns the frames redrawn and the CRC32s of those
    found intact."""
    from swiftjax.io.chunk_store import ChunkMismatchError

    recorded = ctx.manifest.data.get("outputs") or {}
    folder = ctx.run_dir / "colmap" / "images"
    can_draw = getattr(ctx.predictor, "images", None) is not None
    crcs: dict[str, str] = {}
    bad: dict[int, str] = {}  # frame -> why
    for k, name in enumerate(names):
        rel = f"colmap/images/{name}"
        if rel in frames_written:
            continue
        path = folder / name
        exists = path.is_file()
        if rel not in recorded:  # no export recorded it (an older run, or colmap just turned on)
            if not exists and can_draw:
                bad[k] = "missing"
            continue
        want = recorded[rel]
        if not exists:
            bad[k] = "missing"
        elif want is None:
            bad[k] = "written at the original resolution"
        elif (got := _file_crc(path)) != want:
            bad[k] = "damaged: fails its CRC32"
        else:
            crcs[rel] = got
    if not bad:
        return set(), crcs
    shown = ", ".join(f"{names[k]} ({why})" for k, why in list(bad.items())[:3])
    more = f" and {len(bad) - 3} more" if len(bad) > 3 else ""
    by_chunk: dict[int, list[int]] = {}
    for k in bad:
        by_chunk.setdefault(int(ctx.schedule.chunk_of(k)), []).append(k)
    if not can_draw:
        t = min(by_chunk)
        raise ChunkMismatchError(
            ctx.store.path("chunk", t),
            f"its COLMAP frame(s) {shown}{more} must be written again and the predictor cannot "
            "give the frames without predicting",
        )
    folder.mkdir(parents=True, exist_ok=True)
    for t, ks in by_chunk.items():  # the images of the chunk that wrote them (the oracle's depend on it)
        frames = ctx.schedule.frames(t)
        images = np.asarray(ctx.predictor.images(frames))
        _save_pngs([folder / names[k] for k in ks], images[[k - int(frames[0]) for k in ks]])
    ctx.log(f"swiftjax: COLMAP frame(s) {shown}{more}: written again from the input (no prediction)")
    return {names[k] for k in bad}, crcs  # (renamed into place with the output set)


def original_source(ctx: RunContext) -> Any:
    """The predictor's frame source (:class:`swiftjax.io.images.FrameSource`) for
    ``colmap_original_resolution``; an :class:`~swiftjax.options.OptionError` if it has none
    (the synthetic oracle)."""
    source = getattr(ctx.predictor, "source", None)
    if source is None or not hasattr(source, "image_hw"):
        raise OptionError(
            "colmap_original_resolution needs the input images (an image folder, glob or video); "
            f"{type(ctx.predictor).__name__} has none"
        )
    return source


def _to_original_resolution(
    ctx: RunContext,
    K_ref: np.ndarray,
    model_hw: tuple[int, int],
    uv: np.ndarray,
) -> tuple[np.ndarray, tuple[int, int], np.ndarray, np.ndarray]:
    """``K_ref`` and the observations ``uv [M, 2]`` (model pixels) at the original image size,
    undoing VGGT's preprocessing (:func:`swiftjax.intrinsics.preprocess_geometry`: resize, then
    a centre crop or a white pad): ``u0 = (u - left + 1/2) / s_x - 1/2``.  Returns ``(K0,
    (W0, H0), uv0, keep)``; ``keep`` drops observations on the pad (outside the original)."""
    from swiftjax.intrinsics import preprocess_geometry, unmap_intrinsics

    h0, w0 = original_source(ctx).image_hw
    geom = preprocess_geometry(h0, w0, getattr(ctx.predictor, "mode", "crop"))
    if tuple(geom.model_hw) != tuple(model_hw):
        raise ValueError(
            f"colmap_original_resolution: the model saw {model_hw[1]}x{model_hw[0]} images, but preprocessing "
            f"{w0}x{h0} gives {geom.model_hw[1]}x{geom.model_hw[0]}"
        )
    sx, sy = geom.scale_xy
    uv0 = np.column_stack([(uv[:, 0] - geom.left + 0.5) / sx - 0.5, (uv[:, 1] - geom.top + 0.5) / sy - 0.5])
    keep = (uv0[:, 0] >= -0.5) & (uv0[:, 0] < w0 - 0.5) & (uv0[:, 1] >= -0.5) & (uv0[:, 1] < h0 - 0.5)
    return unmap_intrinsics(K_ref, geom), (int(w0), int(h0)), uv0, keep


def _copy_originals(ctx: RunContext, names: list[str]) -> None:
    """The original frames into ``colmap/images/<name>``: image files copied as they are, video
    frames decoded and written as PNG."""
    import shutil

    from PIL import Image

    source = original_source(ctx)
    folder = ctx.run_dir / "colmap" / "images"
    paths = getattr(source, "paths", None)
    for k, name in enumerate(names):
        target = folder / name
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            if paths is not None:
                shutil.copyfile(paths[k], tmp)
            else:
                Image.fromarray(source.read(k)).save(tmp, format="PNG", compress_level=1)


class ChunkExport:
    """The export's share of each temporal chunk, taken while the chunk is in memory: its points
    (:func:`chunk_points`, :func:`export_points`; kept in the chunk's file) and its frames
    (:meth:`write_frames`).  One per run; owns the frame writer's thread (:meth:`close`)."""

    def __init__(self, ctx: RunContext) -> None:
        self.ctx = ctx
        self.frames_written: set[str] = set()  # colmap/images/<name> this run wrote
        self._writer: _FrameWriter | None = None

    def __call__(
        self,
        frames: np.ndarray,
        pred: ChunkPrediction,
        depth: jax.Array,
        conf: jax.Array,
        mask: jax.Array | None,
        K_ref: np.ndarray,
    ) -> tuple[dict[str, np.ndarray], Any]:
        """Points (chunk-store extras) and the frame write's future (or None) of the chunk
        ``pred``, whose first ``len(frames)`` frames (global indices ``frames``) it owns;
        ``depth, conf [S, H, W]`` float32 and ``mask`` on the device."""
        config = self.ctx.config
        f32 = lambda x: jnp.asarray(x, jnp.float32)
        pts, keep = chunk_points_jit(
            depth,
            conf,
            f32(pred.intrinsic),
            f32(K_ref),
            f32(pred.extrinsic),
            jnp.float32(config.point_conf_ratio),
            mask,
            count=len(frames),
            stride=config.point_stride,
        )
        return export_points(pred, pts, keep, config.point_stride), self.write_frames(frames, pred)

    def write_frames(self, frames: np.ndarray, pred: ChunkPrediction) -> Any:
        """Queue the frames ``frames`` (global indices; the first ``len(frames)`` of ``pred``) as
        PNG in ``colmap/images/`` at the model's resolution -- the images the COLMAP model's
        cameras describe -- named by :func:`frame_image_names`.

        Called for each chunk while the prediction is in memory, for the frames the chunk
        owns (with ``colmap_original_resolution`` the export copies the originals instead).  The
        files are written by one background thread (at most two chunks queued) while the next
        chunk is predicted; :func:`run` waits for them.  Lossless PNG (Pillow, compression level
        1), each chunk's files synced as one batch (:func:`~swiftjax.io.atomic.atomic_paths`;
        cost: ``bench/bench_colmap_export.py``, docs/performance/pipeline.md); nothing when ``colmap`` is off or the predictor gives
        no images.  Returns the write's future (``None`` when nothing is written): the temporal
        stage's chunk write waits for it, so a chunk is recorded only once its frames are on disk
        (a resumed run never lacks the frames of a recorded chunk).
        """
        ctx = self.ctx
        if not ctx.config.colmap or ctx.config.colmap_original_resolution or pred.images is None:
            return None
        names = frame_image_names(ctx)
        targets = [ctx.run_dir / "colmap" / "images" / names[int(f)] for f in np.asarray(frames)]
        self.frames_written.update(f"colmap/images/{names[int(f)]}" for f in np.asarray(frames))
        if self._writer is None:
            self._writer = _FrameWriter()
        return self._writer.submit(targets, np.asarray(pred.images)[: len(targets)])

    def close(self) -> None:
        """Wait for the queued frame writes (re-raising a failed one) and stop their thread."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()


def _save_pngs(targets: list[pathlib.Path], images: np.ndarray) -> None:
    from PIL import Image

    for target in targets:
        target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_paths(targets) as tmps:  # one batch of syncs per chunk
        for tmp, image in zip(tmps, images):
            Image.fromarray(image).save(tmp, format="PNG", compress_level=1)


class _FrameWriter:
    """One background thread writing frame PNGs (Pillow releases the GIL while encoding);
    :meth:`submit` blocks while two chunks are queued, so memory stays bounded."""

    def __init__(self) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="swiftjax-frames")
        self.pending: list[Any] = []

    def submit(self, targets: list[pathlib.Path], images: np.ndarray) -> Any:
        while len(self.pending) >= 2:
            self.pending.pop(0).result()
        future = self.pool.submit(_save_pngs, targets, images)
        self.pending.append(future)
        return future

    def close(self) -> None:
        """Wait for every queued write (re-raising a failed one), stop the thread."""
        try:
            for future in self.pending:
                future.result()
        finally:
            self.pending = []
            self.pool.shutdown(wait=True)


_as_matrix = jax.jit(sim3.as_matrix)


def _per_frame_sample(frame: np.ndarray, per_frame: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of a uniform sample of at most ``per_frame`` points of each frame (``frame [P]``
    the points' frames), sorted: every frame with points keeps some (gsplat indexes the
    points of every image by name)."""
    key = rng.random(len(frame))
    order = np.lexsort((key, frame))
    f = frame[order]
    start = np.searchsorted(f, f, side="left")
    rank = np.arange(len(f)) - start
    return np.sort(order[rank < per_frame])


def _export(
    ctx: RunContext,
    K_ref: np.ndarray,
    chunk_poses: np.ndarray,
    chunk_poses_no_loops: np.ndarray,
    unit: str,
    chunks: ChunkExport,
    timestamps: Sequence[float] | None,
    timestamps_note: str | None,
) -> dict[str, Any]:
    """The final pass over the chunk store: world poses, points, COLMAP model.

    Reads each chunk's extrinsics, intrinsics and chunk-frame points (:func:`export_points`;
    never the dense maps), maps the points to the world with the optimised ``S_t`` (float64,
    written as float32) and streams them into ``points.ply``.
    """
    from swiftjax.io import colmap, ply

    run_dir, schedule, store, config = ctx.run_dir, ctx.schedule, ctx.store, ctx.config
    chunks.close()  # every frame the chunks queued is on disk
    redrawn: set[str] = set()
    frame_crcs: dict[str, str] = {}
    if config.colmap and not config.colmap_original_resolution:
        redrawn, frame_crcs = _check_frames(ctx, frame_image_names(ctx), chunks.frames_written)
    n = schedule.n_frames
    T = schedule.num_chunks
    owner = schedule.chunk_of(np.arange(n))  # later chunk wins
    extrinsics = np.zeros((n, 3, 4))
    intrinsics = np.zeros((n, 3, 3))
    with jax.enable_x64(True):
        world = np.asarray(_as_matrix(jnp.asarray(chunk_poses, jnp.float64)))  # [T, 4, 4] s R | t
    rng = np.random.default_rng(0)
    per_frame = max(1, config.colmap_max_points // n)
    sample: dict[str, list[np.ndarray]] = {"xyz": [], "rgb": [], "frame": [], "uv": []}
    picture = Reservoir(100_000, seed=1)  # points.png's uniform sample of the cloud
    image_hw: tuple[int, int] | None = None
    total_points = 0
    ply_comments = [f"unit: {unit}", f"frame: the run's world = the first camera's frame, {_CAMERA_AXES}"]
    with ply.PlyStreamWriter(run_dir / "points.ply", comments=ply_comments) as cloud:
        for t in ctx.bar(range(T), desc="export", unit="chunk"):
            frames = schedule.frames(t)
            own = owner[frames] == t
            extrinsics[frames[own]] = store.load_array("chunk", t, "extrinsic")[own]
            intrinsics[frames[own]] = store.load_array("chunk", t, "intrinsic")[own]
            extra = store.load_extra("chunk", t)
            image_hw = (int(extra["image_hw"][0]), int(extra["image_hw"][1]))
            gh, gw = (int(v) for v in extra["points_grid"])
            M = world[t]
            # s R x + t in float32 (the precision the points are written in).  einsum, not a
            # BLAS matmul: multi-threaded OpenBLAS on this small product is what
            # docs/performance/pipeline.md measured against it.
            xyz = np.einsum("nj,ij->ni", extra["points_xyz"], M[:3, :3].astype(np.float32))
            xyz += M[:3, 3].astype(np.float32)
            cf = extra["points_conf"]
            rgb = extra["points_rgb"] if "points_rgb" in extra else np.full((xyz.shape[0], 3), 200, np.uint8)
            # COLMAP: a uniform sample of each frame's points, each with the pixel it came from.
            pix = extra["points_pixel"].astype(np.int64)
            local = pix // (gh * gw)
            take = _per_frame_sample(local, per_frame, rng)
            sample["xyz"].append(xyz[take])
            sample["rgb"].append(rgb[take])
            sample["frame"].append(frames[local[take]])
            cell = pix[take] % (gh * gw)
            sample["uv"].append(np.column_stack([cell % gw, cell // gw]) * config.point_stride)
            if config.voxel_size:
                down = ply.voxel_downsample(xyz, rgb, cf, config.voxel_size)
                xyz, rgb, cf = down.points, down.colors, down.conf
            cloud.append(xyz.astype(np.float32), rgb, cf.astype(np.float32))
            picture.add(t, xyz, rgb, cf)
            _faults.point("export-chunk", t)
            total_points += xyz.shape[0]

    with jax.enable_x64(True):
        ext = jnp.asarray(extrinsics, jnp.float64)
        c2w = np.asarray(camera.world_cameras(jnp.asarray(chunk_poses[owner], jnp.float64), ext))
        c2w_no_loops = np.asarray(camera.world_cameras(jnp.asarray(chunk_poses_no_loops[owner], jnp.float64), ext))
    assert image_hw is not None
    h, w = image_hw
    if timestamps is None:
        ts, note = np.arange(n, dtype=np.float64), "frame index (no timestamps given)"
    else:
        ts, note = np.asarray(timestamps, np.float64), timestamps_note or "given to the run"
    _write_trajectories(run_dir, c2w, ts, unit, note)
    _write_chunk_poses(run_dir / "chunk_poses.json", chunk_poses, chunk_poses_no_loops, unit)
    names = frame_image_names(ctx)
    with atomic_write(run_dir / "frames.txt") as f:
        f.write("# frame name (colmap/images/<name> when the COLMAP export wrote the frames)\n")
        f.writelines(f"{k} {name}\n" for k, name in enumerate(names))

    cat = lambda key, shape, dt: np.concatenate(sample[key]) if sample[key] else np.zeros(shape, dt)
    pts, rgb = cat("xyz", (0, 3), np.float32), cat("rgb", (0, 3), np.uint8)
    frame, uv = cat("frame", (0,), np.int64), cat("uv", (0, 2), np.int64).astype(np.float64)
    K, size = K_ref, (w, h)  # the COLMAP model's camera
    if config.colmap and config.colmap_original_resolution:
        K, size, uv, keep = _to_original_resolution(ctx, K_ref, (h, w), uv)
        pts, rgb, frame, uv = pts[keep], rgb[keep], frame[keep], uv[keep]
    cam = ctx.camera
    ref = (
        "frame 0's K"
        if cam is None or cam.intrinsics is None
        else (
            f"the given intrinsics ({cam.intrinsics.kind} file {cam.intrinsics.source}) mapped to the model's resolution"
        )
    )
    write_intrinsics(
        run_dir / "intrinsics.txt",
        intrinsics,
        K_ref,
        (w, h),
        getattr(ctx.predictor, "mode", None),
        colmap_camera=(K, size) if config.colmap else None,
        ref=ref,
    )
    if config.colmap:
        if config.colmap_original_resolution:
            _copy_originals(ctx, names)  # every frame (renamed into place with the output set)
            redrawn = set(names)
        missing = [
            names[k]
            for k in range(n)
            if names[k] not in redrawn and not (run_dir / "colmap" / "images" / names[k]).is_file()
        ]
        if missing:
            logger.warning(
                f"colmap/images/ lacks {len(missing)} of {n} frames (e.g. {missing[0]}): the predictor gave no "
                "images, or the chunks were predicted before the COLMAP export was on"
            )
        err = _reprojection_error(pts, frame, uv, c2w, K)
        colmap.write_colmap(
            run_dir / "colmap" / "sparse" / "0",
            c2w,
            np.broadcast_to(K, (n, 3, 3)),
            names,
            image_size=size,
            points=pts,
            colors=rgb,
            errors=err,
            observations=(frame, uv),
            binary=True,
            text=config.colmap_text,
        )
    return {
        "cam_to_world": c2w,
        "cam_to_world_no_loops": c2w_no_loops,
        "intrinsics": intrinsics,
        "num_points": total_points,
        "sample_points": picture.xyz,
        "sample_colors": picture.rgb,
        "frame_crcs": frame_crcs,
    }


def _reprojection_error(
    pts: np.ndarray, frame: np.ndarray, uv: np.ndarray, c2w: np.ndarray, K: np.ndarray
) -> np.ndarray:
    """``[M]`` pixel distance between each point projected through its frame's camera (``K``)
    and the pixel it came from (float64; ~1e-4 px: the points are float32)."""
    R, c = c2w[frame, :3, :3], c2w[frame, :3, 3]
    x = np.einsum("nji,nj->ni", R, pts.astype(np.float64) - c)  # R^T (X - c)
    proj = np.einsum("ij,nj->ni", K, x)
    return np.linalg.norm(proj[:, :2] / proj[:, 2:] - uv, axis=1)


def _write_trajectories(run_dir: pathlib.Path, c2w: np.ndarray, ts: np.ndarray, unit: str, note: str) -> None:
    from swiftjax.io import trajectory

    common = [
        f"swiftjax camera-to-world poses of {len(c2w)} frames, {_CAMERA_AXES}",
        f"unit: {unit}",
    ]
    trajectory.write_kitti(
        run_dir / "poses_kitti.txt",
        c2w,
        header=[*common, "each line: the top 3x4 of the 4x4 matrix, row-major (frame order)"],
    )
    trajectory.write_tum(
        run_dir / "poses_tum.txt",
        ts,
        c2w,
        header=[*common, f"timestamps (s): {note}", "timestamp tx ty tz qx qy qz qw"],
    )


def _write_chunk_poses(path: pathlib.Path, poses: np.ndarray, poses_no_loops: np.ndarray, unit: str) -> None:
    head = {
        "description": "chunk-to-world Sim(3) S_t of every temporal chunk as (tx, ty, tz, qx, qy, qz, qw, s): "
        "x_world = s R x_chunk + t",
        "unit": unit,
    }
    rows = lambda p: ",\n".join("  " + json.dumps(r) for r in np.asarray(p, np.float64).tolist())
    with atomic_write(path) as f:  # one pose a line
        f.write(json.dumps(head, indent=1)[:-2] + ",\n")
        f.write(f' "loop closure": [\n{rows(poses)}\n ],\n "no loop closure": [\n{rows(poses_no_loops)}\n ]\n}}\n')


def write_intrinsics(
    path: pathlib.Path,
    intrinsics: np.ndarray,
    K_ref: np.ndarray,
    size_wh: tuple[int, int],
    mode: str | None = None,
    colmap_camera: tuple[np.ndarray, tuple[int, int]] | None = None,
    ref: str = "frame 0's K",
) -> None:
    """``intrinsics.txt``: a header (resolution, pixel convention, which ``K`` the point cloud
    and the COLMAP model use -- ``colmap_camera`` ``(K, (width, height))``, None when no model
    is written; ``ref`` says where ``K_ref`` comes from), then one line per frame: ``frame fx
    fy cx cy``."""
    w, h = size_wh
    fx, fy, cx, cy = K_ref[0, 0], K_ref[1, 1], K_ref[0, 2], K_ref[1, 2]
    if colmap_camera is None:
        colmap_line = "no COLMAP model written (--no-colmap)"
    else:
        Kc, (wc, hc) = colmap_camera
        same = (wc, hc) == (w, h) and np.array_equal(Kc, K_ref)
        colmap_line = (
            "colmap/sparse/0: one shared PINHOLE camera = "
            + (
                "K_ref"
                if same
                else f"K_ref at the original {wc} x {hc} images (fx {Kc[0, 0]:.6f} fy {Kc[1, 1]:.6f} "
                f"cx {Kc[0, 2]:.6f} cy {Kc[1, 2]:.6f}, preprocessing undone)"
            )
            + f" with cx + 0.5, cy + 0.5 ({Kc[0, 2] + 0.5:.6f}, {Kc[1, 2] + 0.5:.6f}: COLMAP puts the image corner "
            f"at (0, 0)), size {wc} x {hc}"
        )
    lines = [
        "swiftjax intrinsics: VGGT's predicted pinhole K of every frame (no distortion)",
        f"resolution: {w} x {h} pixels (width x height), the model's input"
        + (f" (preprocessing mode '{mode}')" if mode else ""),
        "convention: OpenCV, u = fx X/Z + cx, v = fy Y/Z + cy; pixel centres at integers "
        "(the top-left pixel's centre is (0, 0))",
        f"K_ref = {ref}: fx {fx:.6f} fy {fy:.6f} cx {cx:.6f} cy {cy:.6f}; points.ply is unprojected "
        "with K_ref after normalising each frame's depth to it (SwiftVGGT eq. 1)",
        colmap_line,
        "frame fx fy cx cy",
    ]
    with atomic_write(path) as f:
        f.writelines(f"# {line}\n" for line in lines)
        for k, K in enumerate(intrinsics):
            f.write(f"{k} {K[0, 0]:.6f} {K[1, 1]:.6f} {K[0, 2]:.6f} {K[1, 2]:.6f}\n")


#: loops.txt's leading columns (when the records carry them); the other keys follow, and
#: ``reason`` (readable text, spaces kept) closes the line.
_LOOP_FIRST = ("i", "j", "score", "chunk_i", "chunk_j", "accepted")
_LOOP_LAST = "reason"


def _flatten(record: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Scalars of a (nested) record as ``a.b`` keys; lists and arrays (the edge ``Z``) left out."""
    out: dict[str, Any] = {}
    for k, v in record.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        elif isinstance(v, (bool, int, float, str, np.generic)) or v is None:
            out[prefix + k] = v
    return out


def _cell(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.6g}"
    text = str(v)
    return "_".join(text.split()) or "-"


def write_loops(path: pathlib.Path, records: list[dict[str, Any]]) -> None:
    """``loops.txt``: a header naming every column, then one line per loop candidate.

    Columns are the scalar keys the records carry (nested dicts flattened as ``align_i.rms``;
    the edge ``Z`` is in ``manifest.json``), ``i j score chunk_i chunk_j accepted`` first and
    ``reason`` last: the reason is readable text, the rest of the line (split a row with
    ``line.split(maxsplit=len(columns) - 1)``); a value a record lacks is ``-``.  Every record
    carries its verdict ``accepted``.
    """
    rows = [_flatten(r) for r in records]
    keys: list[str] = [k for k in _LOOP_FIRST if any(k in r for r in rows)]
    for r in rows:
        keys += [k for k in r if k not in keys and k != _LOOP_LAST]
    if any(_LOOP_LAST in r for r in rows):
        keys.append(_LOOP_LAST)
    accepted = sum(1 for r in rows if r["accepted"])
    if not rows:
        count = "0 candidates: loop detection found no pair of frames that look at the same place"
    else:
        count = (
            f"{len(rows)} candidates, {accepted} accepted (edges of the pose graph), {len(rows) - accepted} rejected"
        )
    lines = [
        "swiftjax loop candidates: frames i and j (0-based) look at the same place; score = cosine of "
        "their whitened descriptors",
        count,
        "align_i / align_j: the loop chunk's alignment to chunk_i / chunk_j (num_points = reliable points used)",
    ]
    if _LOOP_LAST in keys:
        lines.append("reason: the verdict in words, the rest of the line (it holds spaces)")
    lines.append(" ".join(keys) if keys else "i j score chunk_i chunk_j")
    with atomic_write(path) as f:
        f.writelines(f"# {line}\n" for line in lines)
        for r in rows:
            cells = [_cell(r.get(k)) for k in keys if k != _LOOP_LAST]
            if _LOOP_LAST in keys:
                cells.append(" ".join(str(r.get(_LOOP_LAST) or "-").split()))
            f.write(" ".join(cells) + "\n")

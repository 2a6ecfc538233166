"""The final pass: world poses, the point cloud, the COLMAP model and the text outputs.

Each temporal chunk's share of ``points.ply`` is taken while the chunk is in memory
(:func:`chunk_points`, :func:`export_points`; saved in its chunk file, in the chunk's
frame), so :func:`run` reads only points and poses from the chunk store -- never the dense
maps -- and applies the optimised ``S_t``.  Files: ``poses_kitti.txt``, ``poses_tum.txt``,
``intrinsics.txt``, ``points.ply``, ``colmap/{cameras,images,points3D}.txt``, ``loops.txt``.
"""

from __future__ import annotations

import pathlib
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import camera, sim3
from swiftjax.io.atomic import atomic_write
from swiftjax.prediction import ChunkPrediction

if TYPE_CHECKING:
    from swiftjax import chunks
    from swiftjax.io.chunk_store import ChunkStore
    from swiftjax.pipeline.config import PipelineConfig
    from swiftjax.pipeline.graph import GraphResult
    from swiftjax.pipeline.loop_closure import LoopResult
    from swiftjax.pipeline.predictors import Predictor
    from swiftjax.pipeline.rundir import RunContext

__all__ = ["run", "chunk_points", "chunk_points_jit", "export_points", "world_cameras"]


def run(
    ctx: RunContext, graph: GraphResult, loops: LoopResult, timestamps: Sequence[float] | None = None
) -> dict[str, Any]:
    """Write every output of the run but the metrics (``report``); returns ``cam_to_world``,
    ``cam_to_world_no_loops`` ``[N, 4, 4]``, ``intrinsics [N, 3, 3]`` and ``num_points``."""
    assert ctx.K_ref is not None
    with ctx.timer("export"):
        exported = _export(
            ctx.predictor, ctx.run_dir, ctx.schedule, ctx.store, ctx.config, ctx.K_ref, graph.chunk_poses,
            graph.chunk_poses_no_loops, ctx.progress, timestamps,
        )
        _write_loops(ctx.run_dir / "loops.txt", loops.records)
    return exported


def chunk_points(
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
    applies the optimised ``S_t``.  Jitted as :data:`chunk_points_jit`: recompiles per
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


chunk_points_jit = jax.jit(chunk_points, static_argnames=("count", "stride"))


def export_points(
    pred: ChunkPrediction, points: jax.Array, keep: jax.Array, stride: int
) -> dict[str, np.ndarray]:
    """Chunk ``t``'s share of ``points.ply``, in the chunk's own frame, as chunk-store extras.

    The frames a chunk owns are ``[start_t, start_{t+1})`` (the later chunk wins overlaps;
    the last chunk owns all its frames).  Their pixels on the ``point_stride`` grid that pass
    the confidence filter (:func:`chunk_points`) are taken
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


_as_matrix = jax.jit(sim3.as_matrix)


@jax.jit
def world_cameras(chunk_pose: jax.Array, extrinsic: jax.Array) -> jax.Array:
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

    Reads each chunk's extrinsics, intrinsics and chunk-frame points (:func:`export_points`;
    never the dense maps), maps the points to the world with the optimised ``S_t`` (float64,
    written as float32) and streams them into ``points.ply``.
    """
    from swiftjax.io import colmap, ply, trajectory
    from swiftjax.pipeline.rundir import progress_bar

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
        for t in progress_bar(range(T), progress, desc="export", unit="chunk"):
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
        c2w = np.asarray(world_cameras(jnp.asarray(chunk_poses[owner], jnp.float64), ext))
        c2w_no_loops = np.asarray(world_cameras(jnp.asarray(chunk_poses_no_loops[owner], jnp.float64), ext))

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

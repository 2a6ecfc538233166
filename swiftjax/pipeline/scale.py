"""The metric-scale step (``--metric``): after the pose graph, before the export.

* ``camera-height=H``: each temporal chunk's camera height above the road ``h_t`` (chunk
  units, :func:`swiftjax.metric_scale.chunk_ground_height`, measured by the temporal stage) votes
  ``H / (h_t s_t)`` metres per world unit, ``s_t`` the scale of its chunk-to-world pose; the
  factor is the median vote (:func:`swiftjax.metric_scale.combine_scales`); with ``metric_combine =
  "prior"`` the pose graph already put a prior on each chunk's scale and solved in metres
  (:mod:`swiftjax.pipeline.graph`), so nothing is scaled here.
* ``gt``: the scale of the Sim(3) (Umeyama) alignment of the camera centres to the given
  ground truth (for evaluation: the trajectory's shape stays the estimate's).

The world is then stretched by the factor (:func:`swiftjax.metric_scale.apply_scale` on every
chunk pose), so the poses, the point cloud and the COLMAP model are all in metres.  The
loop-closed and chain-only poses get their own factors (their ``s_t`` differ).
The result (:class:`~swiftjax.pipeline.results.ScaleResult`) records ``unit``, the factors and
the vote statistics for ``metrics.json``; its ``unit`` is what the export's headers state.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import metric_scale
from swiftjax.camera import world_cameras
from swiftjax.options import OptionError
from swiftjax.pipeline.results import UNIT_METRE, UP_TO_SCALE, GraphResult, ScaleResult, TemporalResult
from swiftjax.pipeline.rundir import RunContext

__all__ = ["run"]


def run(ctx: RunContext, temporal: TemporalResult, graph: GraphResult, ground_truth: np.ndarray | None) -> ScaleResult:
    """``graph`` with every chunk pose in metres (unchanged without ``--metric``)."""
    spec = None if ctx.camera is None else ctx.camera.metric
    if spec is None:
        return ScaleResult(graph, {"unit": UP_TO_SCALE}, UP_TO_SCALE)
    kind, height = spec
    with ctx.timer("metric scale"):
        prior = graph.metrics.get("metric_prior")
        if kind == "camera-height" and prior is not None:  # the pose graph solved in metres
            record = {
                "unit": UNIT_METRE,
                "combine": "prior",
                "metres_per_unit": float(graph.chunk_poses[0, 7]),
                "metres_per_unit_no_loops": float(graph.chunk_poses_no_loops[0, 7]),
                "method": f"camera-height={height:g}",
                **prior,
                "chunk_heights": [None if not np.isfinite(h) else float(h) for h in temporal.ground_heights],
            }
            ctx.log(
                f"metric scale (camera-height={height:g}, scale priors in the pose graph): "
                f"{record['metres_per_unit']:.6g} m per unit of chunk 0"
            )
            return ScaleResult(graph, record, UNIT_METRE)
        if kind == "model":  # the network predicts metres: the world is chunk 0's, in its metres
            m, m0 = 1.0 / float(graph.chunk_poses[0, 7]), 1.0 / float(graph.chunk_poses_no_loops[0, 7])
            info = {"method": "model (the metric network's depth, chunk 0's metres)"}
        elif kind == "camera-height":
            assert temporal.ground_heights is not None
            m, stats = metric_scale.combine_scales(temporal.ground_heights, graph.chunk_poses[:, 7], height)
            m0, _ = metric_scale.combine_scales(temporal.ground_heights, graph.chunk_poses_no_loops[:, 7], height)
            info: dict[str, Any] = {
                "method": f"camera-height={height:g}",
                "combine": "median",
                **stats,
                "chunk_heights": [None if not np.isfinite(h) else float(h) for h in temporal.ground_heights],
            }
        else:
            if ground_truth is None:
                raise OptionError("--metric gt needs the ground-truth poses (--gt)")
            gt = np.asarray(ground_truth, np.float64)[:, :3, 3]
            m = _sim3_scale(ctx, graph.chunk_poses, gt)
            m0 = _sim3_scale(ctx, graph.chunk_poses_no_loops, gt)
            info = {"method": "gt (Sim(3) alignment of the camera centres)"}
    record = {"unit": UNIT_METRE, "metres_per_unit": m, "metres_per_unit_no_loops": m0, **info}
    ctx.log(f"metric scale ({info['method']}): {m:.6g} m per VGGT unit")
    scaled = graph._replace(
        chunk_poses=metric_scale.apply_scale(graph.chunk_poses, m),
        chunk_poses_no_loops=metric_scale.apply_scale(graph.chunk_poses_no_loops, m0),
    )
    return ScaleResult(scaled, record, UNIT_METRE)


def _sim3_scale(ctx: RunContext, chunk_poses: np.ndarray, gt_centres: np.ndarray) -> float:
    """Scale of the Umeyama Sim(3) taking the estimated camera centres onto ``gt_centres``."""
    from swiftjax import evaluation

    schedule = ctx.schedule
    n = schedule.n_frames
    owner = np.searchsorted(schedule.starts, np.arange(n), side="right") - 1  # as the export
    ext = np.zeros((n, 3, 4))
    for t in range(schedule.num_chunks):
        frames = schedule.frames(t)
        own = owner[frames] == t
        ext[frames[own]] = ctx.store.load_array("chunk", t, "extrinsic")[own]
    with jax.enable_x64(True):
        c2w = np.asarray(world_cameras(jnp.asarray(chunk_poses[owner], jnp.float64), jnp.asarray(ext, jnp.float64)))
    _, _, s = evaluation.umeyama_alignment(c2w[:, :3, 3], gt_centres, "sim3")
    return float(s)

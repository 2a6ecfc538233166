"""The pose-graph stage: chunk poses from the temporal chain and the loop edges.

Without loop closure the chunk poses are the chained temporal edges
(:func:`swiftjax.posegraph.chain_poses`); with loop edges, a global Sim(3)
Levenberg-Marquardt over every chunk (:func:`swiftjax.posegraph.optimize`) starts from that
chain, temporal edges plain, loop edges under the configured robust kernel.
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import posegraph, sim3
from swiftjax.pipeline.loop_closure import LoopResult
from swiftjax.pipeline.rundir import RunContext
from swiftjax.pipeline.temporal import TemporalResult
from swiftjax.posegraph import chain_poses

__all__ = ["GraphResult", "run", "chain_poses"]


class GraphResult(NamedTuple):
    """``chunk_poses [T, 8]`` optimised chunk-to-world, ``chunk_poses_no_loops [T, 8]`` the
    chain alone (float64), ``metrics`` for ``metrics.json`` (empty without loop edges),
    ``inlier_weights``: per loop edge, or None (no robust weights computed)."""

    chunk_poses: np.ndarray
    chunk_poses_no_loops: np.ndarray
    metrics: dict[str, Any]
    inlier_weights: np.ndarray | None = None


def run(ctx: RunContext, temporal: TemporalResult, loops: LoopResult) -> GraphResult:
    """Chain the temporal edges; optimise the pose graph when there are loop edges."""
    config = ctx.config
    relative = temporal.relative
    T = ctx.schedule.num_chunks
    chunk_poses_no_loops = chain_poses(relative)
    graph_metrics: dict[str, Any] = {}
    with ctx.timer("pose graph"):
        if loops.edges:
            edges = [(t, t + 1) for t in range(T - 1)] + [(e.chunk_a, e.chunk_b) for e in loops.edges]
            meas = np.concatenate([relative, np.stack([e.Z for e in loops.edges])])
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
    return GraphResult(chunk_poses, chunk_poses_no_loops, graph_metrics)

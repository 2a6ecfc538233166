"""What the stages produce: immutable values, passed explicitly from one stage to the next.

The bottom of the pipeline package (it imports no other pipeline module), so that every
stage, the run directory's reader and the engine can name them.  A stage never stores its
result on the :class:`~swiftjax.pipeline.rundir.RunContext`: it returns one of these.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, NamedTuple

import numpy as np

__all__ = [
    "UP_TO_SCALE",
    "UNIT_METRE",
    "ChunkEdge",
    "TemporalChunk",
    "TemporalResult",
    "LoopEdge",
    "LoopResult",
    "GraphResult",
    "ScaleResult",
    "RunResult",
]

#: The unit of a run's poses and points unless a metric scale is known.
UP_TO_SCALE = "up to scale (VGGT's units of the first chunk; align with Sim(3) to compare with metric poses)"
#: ... and once it is (``--metric``).
UNIT_METRE = "metres"


class ChunkEdge(NamedTuple):
    """The temporal edge ``(chunk - 1, chunk)``: ``S [8]`` float64 maps chunk ``chunk`` into
    chunk ``chunk - 1``; ``record``: ``S`` and the alignment diagnostics, as in the manifest."""

    chunk: int
    S: np.ndarray
    record: dict[str, Any]


class TemporalChunk(NamedTuple):
    """One chunk through the temporal stage (:class:`~swiftjax.pipeline.temporal.TemporalStage`):
    ``frames [S]`` its global frame indices, ``descriptors [S, d]`` float32 (per frame),
    ``edge`` the edge ``(chunk - 1, chunk)`` (None for chunk 0), ``ground_height`` the camera's
    height above the road in the chunk's units (``--metric camera-height``; NaN: no road;
    None: not measured)."""

    chunk: int
    frames: np.ndarray
    descriptors: np.ndarray
    edge: ChunkEdge | None
    ground_height: float | None = None


class TemporalResult(NamedTuple):
    """What the temporal stage produced.

    ``descriptors [N, d]`` float32 (per frame), ``relative [T-1, 8]`` float64 (edge ``t``
    maps chunk ``t+1`` into chunk ``t``), ``edges``: one record per edge (``S`` and the
    alignment diagnostics, as in the manifest), ``K_ref [3, 3]`` float64 (the user's
    intrinsics at the model's resolution, else the first frame's prediction),
    ``ground_heights [T]`` (``--metric camera-height``: the camera's height above the road
    in each chunk's units, NaN where no road was found; else ``None``).
    """

    descriptors: np.ndarray
    relative: np.ndarray
    edges: list[dict[str, Any]]
    K_ref: np.ndarray
    ground_heights: np.ndarray | None = None


class LoopEdge(NamedTuple):
    """A loop edge of the pose graph: ``Z [8]`` maps chunk ``chunk_b`` into chunk ``chunk_a``;
    ``information [7, 7]`` or None (identity)."""

    chunk_a: int
    chunk_b: int
    Z: np.ndarray
    information: np.ndarray | None = None


class LoopResult(NamedTuple):
    """``records``: one dict per loop candidate (as in the manifest and ``loops.txt``, with its
    verdict); ``edges``: the pose graph's loop edges."""

    records: list[dict[str, Any]]
    edges: list[LoopEdge]


class GraphResult(NamedTuple):
    """``chunk_poses [T, 8]`` optimised chunk-to-world, ``chunk_poses_no_loops [T, 8]`` the
    chain alone (float64), ``metrics`` for ``metrics.json`` (empty without loop edges),
    ``inlier_weights``: per loop edge (GNC: 1 kept, 0 rejected; Huber/Cauchy: IRLS weight), or
    None (no loop edges)."""

    chunk_poses: np.ndarray
    chunk_poses_no_loops: np.ndarray
    metrics: dict[str, Any]
    inlier_weights: np.ndarray | None = None


class ScaleResult(NamedTuple):
    """The metric-scale step: ``graph`` with every chunk pose in ``unit`` (:data:`UNIT_METRE`
    with ``--metric``, else :data:`UP_TO_SCALE` and the graph unchanged); ``record``: the
    factors and vote statistics for ``metrics.json`` (``{"unit": ...}`` at least)."""

    graph: GraphResult
    record: dict[str, Any]
    unit: str


@dataclasses.dataclass
class RunResult:
    """What :func:`~swiftjax.pipeline.run.reconstruct` produced (also written to ``metrics.json``)."""

    run_dir: pathlib.Path
    num_frames: int
    num_chunks: int
    loops: list[dict[str, Any]]  # the accepted loop candidates (loop edges)
    chunk_poses: np.ndarray  # [T, 8] optimised chunk-to-world
    chunk_poses_no_loops: np.ndarray  # [T, 8] chained alignment only
    cam_to_world: np.ndarray  # [N, 4, 4] (rotation orthonormal)
    cam_to_world_no_loops: np.ndarray
    intrinsics: np.ndarray  # [N, 3, 3]
    timings: dict[str, float]
    metrics: dict[str, Any]
    loop_candidates: list[dict[str, Any]] = dataclasses.field(default_factory=list)  # every one, with its verdict

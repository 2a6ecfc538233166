"""The host-level SwiftVGGT pipeline: chunks in, trajectory and point cloud out.

This is the imperative shell around the pure JAX core, and the only place with loops over
chunks, files and progress bars.  One module per stage, each a function of what the
earlier stages produced, all sharing a :class:`~swiftjax.pipeline.rundir.RunContext`::

    temporal.run      schedule ─► for each chunk: predict ─► descriptors ─► export points
                                  ─► chunk store ─► align with previous
    loop_closure.run  loop detection ─► loop-centric chunks: predict ─► align both halves
                                  ─► loop edges
    graph.run         chain of temporal edges ─► Sim(3) pose graph (LM)
    export.run        final pass over the store ─► poses, PLY, COLMAP, intrinsics, loops.txt
    report.write      metrics.json, trajectory.png

:func:`~swiftjax.pipeline.run.reconstruct` runs them in order.  The run directory's records
(manifest, input fingerprint, resume records, stage clock) are in
:mod:`~swiftjax.pipeline.rundir`, the method parameters in :mod:`~swiftjax.pipeline.config`.

Memory stays flat in the sequence length: one chunk's dense arrays are in memory at a time
(plus the previous chunk's overlap frames and at most one chunk waiting for the background
writer), descriptors are reduced as chunks arrive (``[N, d]`` is all that is kept), and
dense outputs stream to disk.  Loop-centric chunks read only the 2 x ``loop_half_window``
frames they overlap from each temporal chunk's file (memory-mapped).  Images are used for
the points' colours and not stored.

Resumability: re-running the same command skips finished work; a changed input or
configuration is refused (:class:`RunDirError`) unless ``overwrite=True``.
"""

from __future__ import annotations

from typing import Any

from swiftjax.pipeline.config import PipelineConfig
from swiftjax.pipeline.predictors import OraclePredictor, Predictor
from swiftjax.pipeline.report import summary_table
from swiftjax.pipeline.run import RunResult, reconstruct
from swiftjax.pipeline.rundir import RunDirError
from swiftjax.posegraph import chain_poses  # re-export: it lives with the pose graph

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


def __getattr__(name: str) -> Any:
    # ImagePredictor moved to the inference package (swiftjax never imports it eagerly).
    if name == "ImagePredictor":
        from inference.predictor import ImagePredictor

        return ImagePredictor
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

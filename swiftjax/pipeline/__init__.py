"""The host-level SwiftVGGT pipeline: chunks in, trajectory and point cloud out.

This is the imperative shell around the pure JAX core, and the only place with loops over
chunks, files and progress bars.  One module per stage; each takes explicit inputs and
returns an immutable result (:mod:`~swiftjax.pipeline.results`), sharing only a
:class:`~swiftjax.pipeline.rundir.RunContext` (records, store, schedule, clock)::

    temporal.run      for each chunk: predict (descriptors where the executor computes it)
                      ─► export's share (export.ChunkExport) ─► chunk store ─► align with previous
                                                                        ─► TemporalResult
    loop_closure.run  loop detection ─► loop-centric chunks: predict ─► align both halves
                                  ─► verification ─► LoopResult
    graph.run         chain of temporal edges + loop edges ─► Sim(3) pose graph ─► GraphResult
    scale.run         --metric: every chunk pose in metres ─► ScaleResult
    export.run        final pass over the store ─► poses, PLY, COLMAP, intrinsics, loops.txt
    report.write      metrics.json, trajectory.png

:func:`~swiftjax.pipeline.run.reconstruct` runs them in order;
:class:`~swiftjax.pipeline.engine.Reconstruction` is the live API (fed frame by frame, the same
stages whenever a chunk completes, poses appended to ``poses_live.jsonl``, finished as the
offline run).  The method parameters are in :mod:`~swiftjax.pipeline.config`.  A re-run skips
finished work; a changed input or configuration is refused (:class:`RunDirError`) unless
``overwrite=True``.  The layering of the modules (checked by ``tests/test_pipeline_imports.py``)
and why memory stays flat in the sequence length: docs/design.md, "The host pipeline".
"""

from __future__ import annotations

from swiftjax.pipeline.config import PipelineConfig
from swiftjax.pipeline.engine import Reconstruction
from swiftjax.pipeline.predictors import OraclePredictor, Predictor
from swiftjax.pipeline.report import summary_table
from swiftjax.pipeline.results import RunResult
from swiftjax.pipeline.run import reconstruct
from swiftjax.pipeline.rundir import RunDirError
from swiftjax.posegraph import chain_poses  # re-export: it lives with the pose graph

__all__ = [
    "PipelineConfig",
    "Predictor",
    "OraclePredictor",
    "RunDirError",
    "RunResult",
    "Reconstruction",
    "reconstruct",
    "chain_poses",
    "summary_table",
]

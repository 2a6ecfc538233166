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

:func:`~swiftjax.pipeline.run.reconstruct` runs them in order (its ``loop_candidates`` plugs in
another candidate source, e.g. an online detector; ``graph.run`` takes a warm start from the last
solution).  :class:`~swiftjax.pipeline.engine.Reconstruction` is the live API: fed frame by
frame, it runs the same stages whenever a chunk completes, appends the poses to
``poses_live.jsonl`` (:mod:`~swiftjax.pipeline.live`) and finishes as the offline run.  The import graph is layered
(``tests/test_pipeline_imports.py``): ``results`` and ``config`` at the bottom; ``alignment``
(pair alignment, shared by the temporal and loop stages), ``executors`` (they only move
arrays), ``rundir`` (the run directory's records: manifest, input fingerprint, resume records,
stage clock) and ``reader`` (the one reader of a run directory: viewer, tests) above them; the
stages; ``run`` on top.  The method parameters are in :mod:`~swiftjax.pipeline.config`.

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

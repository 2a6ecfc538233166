"""``reconstruct``: the stages in order over one run directory."""

from __future__ import annotations

import logging
import pathlib
from collections.abc import Callable, Sequence

import numpy as np

from swiftjax import _faults
from swiftjax.io.atomic import output_set
from swiftjax.io.chunk_store import ChunkCorruptError
from swiftjax.io.images import InputError
from swiftjax.options import OptionError
from swiftjax.pipeline import export, graph, loop_closure, report, rundir, scale, temporal
from swiftjax.pipeline.config import PipelineConfig
from swiftjax.pipeline.executors import Executor, LocalExecutor
from swiftjax.pipeline.predictors import Predictor
from swiftjax.pipeline.results import RunResult

__all__ = ["RunResult", "reconstruct"]

logger = logging.getLogger(__name__)


def reconstruct(
    predictor: Predictor,
    run_dir: str | pathlib.Path,
    config: PipelineConfig = PipelineConfig(),
    *,
    ground_truth: np.ndarray | None = None,
    overwrite: bool = False,
    progress: bool = True,
    timestamps: Sequence[float] | None = None,
    timestamps_note: str | None = None,
    log: Callable[[str], None] = logger.info,
    executor: Executor | None = None,
    loop_candidates: loop_closure.CandidateSource | None = None,
) -> RunResult:
    """Run SwiftVGGT over every frame of ``predictor`` and write the outputs to ``run_dir``.

    Args:
        predictor: a :class:`~swiftjax.pipeline.predictors.Predictor` (e.g.
            :class:`~swiftjax.pipeline.predictors.OraclePredictor`, or
            :class:`inference.predictor.ImagePredictor`).
        run_dir: output folder (created; resumable, see :mod:`swiftjax.pipeline.rundir`).
        config: method parameters.
        ground_truth: optional ``[N, 4, 4]`` camera-to-world reference for ATE/RPE.
        overwrite: replace a run directory that belongs to another input/configuration.
        progress: show tqdm progress bars.
        timestamps: ``[N]`` times for ``poses_tum.txt`` (default: the frame index).
        timestamps_note: where the times come from (``poses_tum.txt``'s header says it).
        log: where one-line progress messages go (default: the ``swiftjax.pipeline.run``
            logger at INFO; warnings go to the stages' loggers).
        executor: where the predictions are computed (default: a
            :class:`~swiftjax.pipeline.executors.LocalExecutor` with prefetch); the caller
            closes an executor it passes.
        loop_candidates: where the loop stage's candidates come from (default: every frame's
            descriptor, :func:`swiftjax.loops.find_loops`; e.g. an online detector).

    Returns:
        :class:`RunResult`; the files are ``poses_kitti.txt``, ``poses_tum.txt``,
        ``intrinsics.txt``, ``points.ply``, ``loops.txt``, ``trajectory.png``, ``points.png``,
        ``metrics.json``, ``chunk_poses.json``, ``frames.txt``, ``colmap/images/*.png`` +
        ``colmap/sparse/0/*.bin`` (see :mod:`swiftjax.pipeline.export`) and the chunk store.
    """
    run_dir = pathlib.Path(run_dir)
    n = int(predictor.num_frames)
    if n < 1:
        raise InputError("the input has no frames")
    if ground_truth is not None:  # checked before the run: an evaluation failure never comes after it
        ground_truth = report.check_ground_truth(ground_truth, n)
    if config.metric == "gt" and ground_truth is None:
        raise OptionError("--metric gt needs the ground-truth poses (--gt)")
    executor = executor if executor is not None else LocalExecutor()
    ctx = rundir.open_run(predictor, run_dir, config, executor, overwrite=overwrite, progress=progress, log=log)
    chunk_export = export.ChunkExport(ctx)
    try:
        export.clean(ctx)  # the frames of a previous, longer input
        export.check(ctx)
        # A chunk file found corrupt by a later stage is forgotten and the stages restart: the
        # temporal stage predicts it again (every other chunk is read back), at most once per chunk.
        for _attempt in range(ctx.schedule.num_chunks + 1):
            try:
                chain = temporal.run(ctx, chunk_export)
                _faults.point("temporal-done")
                loops = loop_closure.run(ctx, chain, loop_candidates)
                _faults.point("loops-done")
                poses = scale.run(ctx, chain, graph.run(ctx, chain, loops), ground_truth)  # --metric: in metres
                _faults.point("graph-done")
                # The outputs are renamed together at the end: a full disk or a kill mid-way
                # leaves the previous complete set (or none), never a mix.  The outputs record
                # lists them first; then what the previous run wrote and this one did not goes.
                written: list[pathlib.Path] = []

                def expect(targets: list[pathlib.Path]) -> None:
                    written[:] = targets
                    rundir.record_outputs(ctx, export.output_files(ctx, targets, None), final=False)

                with output_set(before_rename=expect):
                    exported = export.run(ctx, chain, poses, loops, chunk_export, timestamps, timestamps_note)
                    _faults.point("export-done")
                    metrics = report.write(ctx, chain, loops, poses, exported, ground_truth)
                rundir.record_outputs(ctx, export.output_files(ctx, written, exported["frame_crcs"]), final=True)
                break
            except ChunkCorruptError as err:
                t = _corrupt_chunk_index(ctx, err)
                log(f"swiftjax: {err}; predicting chunk {t} again")
                rundir.forget_chunk(ctx.manifest, ctx.store, t)
        else:  # pragma: no cover - every chunk re-predicted and still corrupt: the disk is failing
            raise rundir.RunDirError(f"chunk files in {ctx.store.root} keep failing their checksums")
    finally:
        try:
            chunk_export.close()  # no frame write outlives the run
        finally:
            ctx.close()

    return RunResult(
        run_dir=run_dir,
        num_frames=n,
        num_chunks=ctx.schedule.num_chunks,
        loops=[r for r in loops.records if r["accepted"]],
        chunk_poses=poses.graph.chunk_poses,
        chunk_poses_no_loops=poses.graph.chunk_poses_no_loops,
        cam_to_world=exported["cam_to_world"],
        cam_to_world_no_loops=exported["cam_to_world_no_loops"],
        intrinsics=exported["intrinsics"],
        timings=dict(ctx.timer.seconds),
        metrics=metrics,
        loop_candidates=loops.records,
    )


def _corrupt_chunk_index(ctx: rundir.RunContext, err: ChunkCorruptError) -> int:
    """The temporal chunk whose file ``err`` names; re-raised if it is not a chunk file."""
    m = ctx.store.parse_name(err.path.name)
    if m is None or m[0] != "chunk":
        raise err
    return m[1]

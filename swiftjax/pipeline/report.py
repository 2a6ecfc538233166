"""The run's report: ``metrics.json``, ``trajectory.png``, ``points.png``, the ground truth the
run was given (``ground_truth_kitti.txt``) and the end-of-run summary table."""

from __future__ import annotations

import json
import logging
import pathlib
from typing import Any

import numpy as np

from swiftjax.io.atomic import atomic_write
from swiftjax.io.images import InputError
from swiftjax.pipeline.results import LoopResult, RunResult, ScaleResult, TemporalResult
from swiftjax.pipeline.rundir import RunContext

__all__ = ["write", "summary_table", "check_ground_truth"]

logger = logging.getLogger(__name__)


def check_ground_truth(ground_truth: Any, n: int, name: str = "the ground truth") -> np.ndarray:
    """``ground_truth`` as float64 ``[n, 4|3, 4]``, or one line naming ``name`` (:class:`~swiftjax.io.images.InputError`, a ``ValueError``)
    when the report's ATE (a Sim(3) alignment) could not use it: another frame count, fewer
    than 3 poses, non-finite values, positions coincident or collinear (the rotation about
    the line is undetermined; the same test as :func:`swiftjax.evaluation.umeyama_alignment`).
    Called before the run starts."""
    from swiftjax import evaluation

    gt = np.asarray(ground_truth, np.float64)
    if gt.ndim != 3 or gt.shape[0] != n or gt.shape[1:] not in ((4, 4), (3, 4)):
        raise InputError(f"{name} has shape {gt.shape}, expected [{n}, 4, 4] (one pose per frame)")
    if not np.all(np.isfinite(gt)):
        raise InputError(f"{name} holds non-finite values (nan/inf)")
    if n < 3:
        raise InputError(f"{name} has {n} pose(s): the ATE's Sim(3) alignment needs at least 3 (leave out --gt)")
    pos = gt[:, :3, 3]
    try:
        evaluation.umeyama_alignment(pos, pos)
    except ValueError:
        raise InputError(
            f"{name}: its positions are coincident or collinear, so the Sim(3) alignment of the "
            "ATE is undefined (leave out --gt)"
        ) from None
    return gt


def write(
    ctx: RunContext,
    temporal: TemporalResult,
    loops: LoopResult,
    scaled: ScaleResult,
    exported: dict[str, Any],
    ground_truth: np.ndarray | None,
) -> dict[str, Any]:
    """Write ``metrics.json``, ``trajectory.png``, ``points.png`` and, with a ground truth,
    ``ground_truth_kitti.txt`` (for the viewer); returns the metrics."""
    graph = scaled.graph
    try:
        metrics = _metrics(
            ctx.num_frames,
            ctx.schedule.num_chunks,
            loops.records,
            temporal.edges,
            graph.metrics,
            ctx.timer.seconds,
            exported,
            ground_truth,
            scaled.record,
        )
    except ValueError as err:  # the evaluation failed: the run's outputs are kept, without ATE
        if ground_truth is None:
            raise
        logger.warning(f"ATE/RPE not computed ({err}); the outputs are written without them")
        ground_truth = None
        metrics = _metrics(
            ctx.num_frames,
            ctx.schedule.num_chunks,
            loops.records,
            temporal.edges,
            graph.metrics,
            ctx.timer.seconds,
            exported,
            None,
            scaled.record,
        )
    with atomic_write(ctx.run_dir / "metrics.json") as f:
        json.dump(metrics, f, indent=1)
    unit = "m" if metrics["unit"] == "metres" else None
    _plot(ctx.run_dir / "trajectory.png", exported, ground_truth, loops.records, unit)
    _plot_points(ctx.run_dir / "points.png", exported, loops.records, unit)
    if ground_truth is not None:
        from swiftjax.io import trajectory

        trajectory.write_kitti(
            ctx.run_dir / "ground_truth_kitti.txt",
            ground_truth,
            header=[
                "the ground truth given to this run: camera-to-world poses as given (metres, its own frame)",
            ],
        )
    return metrics


def _metrics(
    n: int,
    T: int,
    loop_records: list[dict[str, Any]],
    align_infos: list[dict[str, Any]],
    graph: dict[str, Any],
    timings: dict[str, float],
    exported: dict[str, Any],
    ground_truth: np.ndarray | None,
    scale: dict[str, Any] | None = None,
) -> dict[str, Any]:
    scale = scale or {"unit": "up to scale"}
    out: dict[str, Any] = {
        "unit": scale["unit"],
        "metric_scale": scale,
        "frames": n,
        "chunks": T,
        "loops": sum(bool(r.get("accepted", True)) for r in loop_records),
        "loop_candidates": [_candidate(r) for r in loop_records],
        "points": int(exported["num_points"]),
        "timings_seconds": timings,
        "alignment": {
            "pairs": len(align_infos),
            "mean_points": float(np.mean([a["num_points"] for a in align_infos])) if align_infos else 0.0,
            "fallback_threshold_used": int(sum(a["used_fallback_threshold"] for a in align_infos)),
            "pose_fallbacks": int(sum(a["pose_fallback"] for a in align_infos)),
            "zero_point_pairs": int(sum(a["num_points"] == 0 for a in align_infos)),
            # rho of each temporal pair (chunk t+1's overlap depths onto chunk t's scale)
            "scale_ratios": [float(a.get("scale_ratio", 1.0)) for a in align_infos],
        },
        "pose_graph": graph,
    }
    if ground_truth is not None:
        from swiftjax import evaluation

        gt = ground_truth[:, :3, 3]
        out["ate_rmse"] = evaluation.ate(exported["cam_to_world"][:, :3, 3], gt).rmse
        out["ate_rmse_no_loops"] = evaluation.ate(exported["cam_to_world_no_loops"][:, :3, 3], gt).rmse
        if scale["unit"] == "metres":
            # metric outputs: ATE with rotation + translation only (no alignment scale), and
            # the scale error = 1 / (the Sim(3) alignment's scale) - 1
            a = evaluation.ate(exported["cam_to_world"][:, :3, 3], gt)
            out["scale_error"] = 1.0 / a.scale - 1.0
            out["ate_rmse_se3"] = evaluation.ate(exported["cam_to_world"][:, :3, 3], gt, align="se3").rmse
            out["ate_rmse_se3_no_loops"] = evaluation.ate(
                exported["cam_to_world_no_loops"][:, :3, 3], gt, align="se3"
            ).rmse
    return out


def _candidate(r: dict[str, Any]) -> dict[str, Any]:
    """A loop candidate's numbers for ``metrics.json`` (NaN as null)."""
    keys = (
        "i",
        "j",
        "score",
        "chunk_i",
        "chunk_j",
        "accepted",
        "reason",
        "source",
        "dense_agreement",
        "dense_overlap",
        "null_threshold",
        "null_mean",
        "null_std",
        "null_samples",
        "null_kappa",
        "quality_min_fraction",
        "quality_max_rms",
        "pcm_residual",
        "registration",
        "registered_null_threshold",
        "registered_null_mean",
        "registered_null_samples",
        "registered_null_pending",
        "registration_pending",
    )
    finite = lambda v: None if isinstance(v, float) and not np.isfinite(v) else v
    return {k: finite(r[k]) for k in keys if k in r}


def _plot(
    path: pathlib.Path,
    exported: dict[str, Any],
    ground_truth: np.ndarray | None,
    loop_records: list[dict[str, Any]],
    unit: str | None = None,
) -> Any:
    """Top view of the trajectory with and without loop closure, in the run's own frame and
    unit (as ``points.png``); the ground truth Sim(3)-aligned onto it; loops drawn."""
    from swiftjax import evaluation
    from swiftjax.io import plot

    estimate = exported["cam_to_world"][:, :3, 3]
    reference = None
    title = "swiftjax trajectory"
    if ground_truth is not None:
        gt = ground_truth[:, :3, 3]
        title = f"ATE {evaluation.ate(estimate, gt).rmse:.3g} m (Sim(3)-aligned)"
        R, t, s = evaluation.umeyama_alignment(gt, estimate, "sim3")  # ground truth onto the estimate
        reference = s * gt @ R.T + t
    pairs = {
        ok: np.array(
            [(r["i"], r["j"]) for r in loop_records if bool(r.get("accepted", True)) == ok], dtype=np.int64
        ).reshape(-1, 2)
        for ok in (True, False)
    }
    return plot.plot_trajectory(
        path,
        estimate,
        reference=reference,
        loops=pairs[True],
        rejected=pairs[False],
        no_loops=exported["cam_to_world_no_loops"][:, :3, 3],
        title=title,
        unit=unit,
    )


def _plot_points(
    path: pathlib.Path, exported: dict[str, Any], loop_records: list[dict[str, Any]], unit: str | None = None
) -> Any:
    """Bird's-eye view of a uniform sample of the cloud with the cameras."""
    from swiftjax.io import plot

    pairs = np.array([(r["i"], r["j"]) for r in loop_records if r.get("accepted", True)], np.int64).reshape(-1, 2)
    return plot.plot_points(
        path,
        exported["sample_points"],
        exported["sample_colors"],
        exported["cam_to_world"],
        loops=pairs,
        unit=unit,
        title=f"swiftjax: {len(exported['sample_points']):,} of "
        f"{exported['num_points']:,} points, {len(exported['cam_to_world'])} cameras",
    )


def summary_table(result: RunResult) -> str:
    """The end-of-run summary, as a terminal table: sizes, ATE with and without loop closure
    (with a ground truth), the time per stage in pipeline order (seconds, positional
    notation), then where the outputs are and the command that shows them."""
    from swiftjax.io.tables import text_table

    m = result.metrics
    unit = "metres" if m.get("unit") == "metres" else "up to scale (no --metric)"
    rows: list[Any] = [
        f"swiftjax: finished {result.run_dir}",
        ["frames", m["frames"]],
        ["chunks", m["chunks"]],
        ["loop candidates", len(m.get("loop_candidates", []))],
        ["loops closed (verified)", m["loops"]],
        ["points written", m["points"]],
        ["unit", unit],
    ]
    if "ate_rmse" in m:
        rows += [
            ["ATE rmse, loop closure (m)", float(m["ate_rmse"])],
            ["ATE rmse, no loop closure (m)", float(m["ate_rmse_no_loops"])],
        ]
    timings = {k: float(v) for k, v in m["timings_seconds"].items() if float(v) > 0}
    rows.append("time per stage (s)")
    rows += [[k, f"{v:,.2f}"] for k, v in timings.items()]
    rows.append(["total", f"{sum(timings.values()):,.2f}"])
    table = text_table(rows)
    return (
        f"{table}\noutputs: {result.run_dir}  (points.ply, poses_kitti.txt, poses_tum.txt, colmap/, "
        f"trajectory.png, points.png, metrics.json)\nnext:    swiftjax view {_shell_quote(result.run_dir)}"
    )


def _shell_quote(path: pathlib.Path) -> str:
    import shlex

    return shlex.quote(str(path))

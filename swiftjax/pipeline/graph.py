"""The pose-graph stage: chunk poses from the temporal chain and the loop edges.

Without loop closure the chunk poses are the chained temporal edges
(:func:`swiftjax.posegraph.chain_poses`); with loop edges, a global Sim(3)
Levenberg-Marquardt over every chunk (:func:`swiftjax.posegraph.optimize`) starts from that
chain, temporal edges plain (never down-weighted), loop edges robust: GNC-TLS by default
(``robust_loops``), with the inlier threshold ``robust_scale`` in whitened units.  Before GNC
(``graph_pcm``, default on) every loop edge goes through pairwise consistency against the
odometry (:func:`swiftjax.loops.pcm.consistent_solve`): GNC starts from the maximum consistent
set, the other loop edges are out (weight 0; ``metrics["loop_pcm_kept"]``).  With equal
weights the solve weighs every edge alike, but the test and GNC's decision use each edge's own
noise covariance below (the drift model plus its alignment's statistics: an edge's inlier test
whitened by its own noise, not by a nominal one; ``bench/bench_robust_backend.py``'s
``equal-own`` arm, which held every random, clustered and gauge cell where the nominal model
dropped a true loop).

Edge information (``edge_information = "data"``): each edge's covariance is the drift model of
:mod:`swiftjax.loops.verification` (``odometry_covariance`` / ``loop_covariance``: translation
error proportional to the edge's length, fixed rotation and log-scale errors — VGGT's model
error, which point statistics cannot see) plus its own alignment's estimation covariance
(:func:`swiftjax.align.covariance.umeyama_information`: reliable-point count, residual RMS, the
source points' spread, ``edge_pixels_per_sample`` pixels per independent residual; a loop edge
combines its two half alignments, :func:`swiftjax.align.covariance.loop_edge_information`).  An
edge whose alignment has no usable statistics (the pose fallback, IRLS alignment, a run
directory from before these statistics were recorded) keeps the drift model alone, and the run
says so.  ``edge_information = "equal"``: identity for every edge (the authors' choice).

Metric scale as pose-graph priors (``--metric camera-height=H`` with ``metric_combine =
"prior"``, :func:`swiftjax.metric_scale.scale_priors`): the graph gains a fixed anchor node ``A``
(identity, the metric world) and, per chunk ``t`` with a road fit, an edge ``(A, t)`` measuring
``Z_t = (t_t^0, q_t^0, m_t)`` (the start pose's rotation and translation, the chunk's metric
factor ``m_t = H / h_t`` as scale) with information ``diag(eps w, ..., eps w, w)``, ``w =
1 / sigma^2``: the residual's log-scale entry is exactly ``log s_t - log m_t``, and ``eps =
1e-9`` keeps the matrix positive definite as :func:`swiftjax.posegraph.validate` requires
(the pull towards the start pose it adds is ``1e-9`` of the scale prior's weight, far below
every other edge's).  Chunk 0 is no longer fixed: the edge ``(A, 0)`` pins its rotation and
translation (information ``1 / pin_sigma^2``, the gauge: every other cost is invariant under a
common rigid motion, so the pin holds exactly) and carries chunk 0's own scale prior.  The
solve starts from the chain scaled by the median vote; the chain-only poses are solved the
same way on the temporal edges and the priors (so both outputs are metric).
"""

from __future__ import annotations

import logging
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import metric_scale, posegraph, sim3
from swiftjax.align import covariance
from swiftjax.loops import pcm
from swiftjax.loops import verification as lv
from swiftjax.pipeline.results import GraphResult, LoopResult, TemporalResult
from swiftjax.pipeline.rundir import RunContext
from swiftjax.posegraph import chain_poses

__all__ = ["run", "warm_start", "chain_poses", "edge_information", "loop_information", "scale_prior_problem"]

logger = logging.getLogger(__name__)


_STATS = ("S", "num_points", "rms", "src_mean", "src_covariance")


def edge_information(
    records: list[dict[str, Any]], pixels_per_sample: float, rows: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(information [K, 7, 7], valid [K])`` of alignment records (``align_pair`` diagnostics with
    ``S``, ``num_points``, ``rms``, ``src_mean``, ``src_covariance``); invalid rows are zero.
    ``rows``: computed on the records padded to ``rows`` (repeating the first; a growing graph
    compiles once per padded size, not per ``K``)."""
    k = len(records)
    ok = np.array([all(key in r for key in _STATS) and not r.get("pose_fallback", False) for r in records], bool)
    if not ok.any():
        return np.zeros((k, 7, 7)), ok
    get = lambda key, shape: np.array([r[key] if o else np.zeros(shape) for r, o in zip(records, ok)], np.float64)
    S = get("S", (8,))
    S[~ok, 6:8] = 1.0
    args = [S[:, 7], get("num_points", ()), get("rms", ()), get("src_mean", (3,)), get("src_covariance", (3, 3))]
    if rows is not None:
        args = [_pad_rows(a, rows) for a in args]
    with jax.enable_x64(True):
        out = covariance.umeyama_information(*args, pixels_per_sample=pixels_per_sample)
        info, valid = np.asarray(out.information, np.float64)[:k], np.asarray(out.valid)[:k] & ok
    return np.where(valid[:, None, None], info, 0.0), valid


def loop_information(record: dict[str, Any], pixels_per_sample: float) -> np.ndarray | None:
    """Information ``[7, 7]`` of a loop edge ``Z = S_j,loop S_i,loop^-1`` from its halves'
    records (``align_i``, ``align_j``), or None when a half has no usable statistics."""
    halves = [record.get("align_i", {}), record.get("align_j", {})]
    info, valid = edge_information(halves, pixels_per_sample)
    if not valid.all():
        return None
    with jax.enable_x64(True):
        E = covariance.EdgeInformation
        out = covariance.loop_edge_information(
            np.asarray(halves[0]["S"]),
            E(info[0], np.bool_(True)),
            np.asarray(halves[1]["S"]),
            E(info[1], np.bool_(True)),
        )
        return np.asarray(out.information, np.float64) if bool(out.valid) else None


def _pad_rows(a: np.ndarray, rows: int) -> np.ndarray:
    """``a [K, ...]`` padded to ``[max(K, rows), ...]`` by repeating its first row (``K >= 1``)."""
    return np.concatenate([a, np.repeat(a[:1], max(rows - len(a), 0), axis=0)])


def _inverse(m: np.ndarray) -> np.ndarray:
    out = np.linalg.inv(m)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def _drift_covariance(
    temporal: TemporalResult, loops: LoopResult, capacity: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The drift model's covariances ``([T-1, 7, 7], [L, 7, 7])`` of the temporal and loop edges
    (``capacity``: computed on edges padded to that many temporal / loop edges, see :func:`run`)."""
    drift = lv.VerificationConfig()
    relative = np.asarray(temporal.relative)
    Z = np.stack([e.Z for e in loops.edges]) if loops.edges else None
    if capacity is not None:
        relative = _pad_rows(relative, capacity[0])
        Z = None if Z is None else _pad_rows(Z, capacity[1])
    with jax.enable_x64(True):
        odo = np.asarray(
            lv.odometry_covariance(
                jnp.asarray(relative), drift.odo_sigma_rot, drift.odo_sigma_trans, drift.odo_sigma_scale
            ),
            np.float64,
        )[: len(temporal.relative)]
        lc = (
            np.asarray(
                lv.loop_covariance(
                    jnp.asarray(Z),
                    drift.loop_sigma_rot,
                    drift.loop_sigma_trans,
                    drift.loop_sigma_scale,
                ),
                np.float64,
            )[: len(loops.edges)]
            if Z is not None
            else np.zeros((0, 7, 7))
        )
    return odo, lc


def _graph_information(
    ctx: RunContext, temporal: TemporalResult, loops: LoopResult, capacity: tuple[int, int] | None = None
) -> np.ndarray | None:
    """``[E, 7, 7]`` for the temporal then the loop edges: the inverse of
    :func:`_data_covariance`, or None under ``edge_information = "equal"`` (identity: equal
    weights)."""
    if ctx.config.edge_information == "equal":
        return None
    return _inverse(_data_covariance(ctx, temporal, loops, capacity))


def _data_covariance(
    ctx: RunContext, temporal: TemporalResult, loops: LoopResult, capacity: tuple[int, int] | None = None
) -> np.ndarray:
    """``[E, 7, 7]`` covariance of the temporal then the loop edges.

    ``Cov_e = drift_e + Omega_align,e^-1``: the drift model of :mod:`swiftjax.loops.verification`
    (VGGT's chunk-to-chunk model error, which an alignment's point statistics cannot see; see
    docs/performance/pipeline.md for what the statistics alone give)
    plus the alignment's own estimation covariance (large only for weak alignments: few reliable
    points, a large residual; missing statistics add nothing and are reported).
    """
    pps = ctx.config.edge_pixels_per_sample
    info, valid = edge_information(temporal.edges, pps, None if capacity is None else capacity[0])
    accepted = [r for r in loops.records if r.get("accepted", True) and "Z" in r]
    if len(accepted) != len(loops.edges) or any(
        (r["chunk_j"], r["chunk_i"]) != (e.chunk_a, e.chunk_b) for r, e in zip(accepted, loops.edges)
    ):
        raise RuntimeError("pose graph: the loop edges do not match the accepted loop records")
    loop_info = [
        e.information if e.information is not None else loop_information(r, pps) for r, e in zip(accepted, loops.edges)
    ]
    odo, lc = _drift_covariance(temporal, loops, capacity)
    safe = np.where(valid[:, None, None], info, np.eye(7))
    odo = odo + np.where(valid[:, None, None], _inverse(safe), 0.0)
    lc = np.stack([c if x is None else c + _inverse(x) for c, x in zip(lc, loop_info)]) if loops.edges else lc
    missing = int((~valid).sum()) + sum(x is None for x in loop_info)
    if missing:
        ctx.log(f"pose graph: {missing} edge(s) without alignment statistics: drift model alone")
    return np.concatenate([odo, lc])


PRIOR_EPS = 1e-9  # the prior edges' weight on the non-scale entries, relative to 1 / sigma^2
PIN_SIGMA = 1e-3  # the anchor edge's standard deviation on chunk 0's rotation and translation


def scale_prior_problem(
    start: np.ndarray,
    edges: np.ndarray,
    measurements: np.ndarray,
    information: np.ndarray | None,
    robust: np.ndarray,
    priors: metric_scale.ScalePriors,
    *,
    pin_sigma: float = PIN_SIGMA,
    eps: float = PRIOR_EPS,
) -> posegraph.Problem:
    """The pose graph with per-chunk scale priors (module docstring): nodes ``0 .. T-1`` the
    chunks (none fixed), node ``T`` the fixed identity anchor; edges: the given ones, then
    ``(T, 0)`` (the pin, with chunk 0's prior) and ``(T, t)`` for every other chunk with a prior.

    ``start [T, 8]`` the metric start poses, ``edges [E, 2]``, ``measurements [E, 8]``,
    ``information [E, 7, 7]`` or None (identity), ``robust [E]``.  Host NumPy float64 in, a
    :class:`~swiftjax.posegraph.Problem` with ``T + 1`` nodes out (float64 under x64)."""
    start = np.asarray(start, np.float64)
    T = start.shape[0]
    E = len(edges)
    info = np.broadcast_to(np.eye(7), (E, 7, 7)) if information is None else np.asarray(information, np.float64)
    w = np.asarray(priors.weight, np.float64)
    pin = 1.0 / pin_sigma**2
    rows = [0] + [t for t in range(1, T) if priors.used[t]]
    Z = start[rows].copy()
    Z[:, 7] = np.where(priors.used[rows], np.exp(np.nan_to_num(priors.log_scale[rows])), start[rows, 7])
    P = np.zeros((len(rows), 7, 7))
    diag = np.arange(6)
    P[:, diag, diag] = eps * w[rows, None]
    P[0, diag, diag] = pin  # the gauge: chunk 0's rotation and translation
    P[:, 6, 6] = w[rows]
    if not priors.used[0]:  # no prior on chunk 0's scale: the pin alone (its scale free)
        P[0, 6, 6] = eps * pin
    anchor = np.array([[0, 0, 0, 0, 0, 0, 1, 1.0]])
    return posegraph.Problem(
        np.concatenate([start, anchor]),
        np.concatenate([np.asarray(edges, np.int32).reshape(E, 2), np.array([[T, t] for t in rows], np.int32)]),
        np.concatenate([np.asarray(measurements, np.float64).reshape(E, 8), Z]),
        information=np.concatenate([info, P]),
        fixed=np.arange(T + 1) == T,
        robust=np.concatenate([np.asarray(robust, bool), np.zeros(len(rows), bool)]),
    )


def _scale_priors(ctx: RunContext, temporal: TemporalResult, chain: np.ndarray) -> metric_scale.ScalePriors | None:
    """The scale priors of ``--metric camera-height=H`` with ``metric_combine = "prior"``, else None."""
    camera = getattr(ctx, "camera", None)
    spec = None if camera is None else camera.metric
    if ctx.config.metric_combine != "prior" or spec is None or spec[0] != "camera-height":
        return None
    if temporal.ground_heights is None:
        raise RuntimeError("pose graph: --metric camera-height without the chunks' ground heights")
    return metric_scale.scale_priors(temporal.ground_heights, chain[:, 7], spec[1], ctx.config.metric_prior_sigma)


def _solve(
    problem: posegraph.Problem, config: Any, kernel: Any, capacity: tuple[int, int] | None = None
) -> tuple[Any, np.ndarray]:
    posegraph.validate(problem)
    options = config.graph.replace(kernel=kernel)
    pad = True if capacity is None else (capacity[0] + 1, sum(capacity))
    res = posegraph.optimize(problem, options, throw=False, pad=pad)  # not converged: the caller warns
    return res, np.asarray(sim3.normalize(res.poses), np.float64)


def _solve_metrics(res: Any) -> dict[str, Any]:
    return {
        "cost_initial": res.cost_initial,
        "cost_final": res.cost_final,
        "iterations": res.num_steps,
        "converged": res.converged,
        "status": res.status,
        "compile_seconds": res.compile_seconds,
        "solve_seconds": res.solve_seconds,
    }


def warm_start(previous: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """Initial chunk poses ``[T, 8]`` for a graph that grew: the previous solution ``[T0, 8]``
    for its chunks, the new ones chained on from the last (``S_t = S_{t-1} R_{t-1}``, ``relative
    [T-1, 8]``), so that the solver starts next to the optimum when a few edges arrive."""
    T0, T = len(previous), len(relative) + 1
    if not 1 <= T0 <= T:
        raise ValueError(f"a warm start of {T0} chunk poses for a graph of {T} chunks")
    previous = np.asarray(previous, np.float64)
    tail = chain_poses(relative[T0 - 1 :])[1:]  # chunks T0..T-1 in chunk T0-1's frame
    with jax.enable_x64(True):
        grown = np.asarray(sim3.normalize(sim3.compose(jnp.asarray(previous[-1]), jnp.asarray(tail))), np.float64)
    return np.concatenate([previous, grown.reshape(-1, 8)])


def run(
    ctx: RunContext,
    temporal: TemporalResult,
    loops: LoopResult,
    warm: GraphResult | None = None,
    *,
    scale_priors: bool = True,
    capacity: tuple[int, int] | None = None,
) -> GraphResult:
    """Chain the temporal edges; optimise the pose graph when there are loop edges (or scale priors).

    ``warm``: the last solution of a graph with fewer edges (a live run): the loop solve starts
    from it (:func:`warm_start`) instead of the chain; offline runs start from the chain.
    ``scale_priors``: False leaves out ``--metric camera-height``'s priors (the live engine's
    poses stay in the first chunk's units until the final pass).  ``capacity``: ``(temporal
    edges, loop edges)`` that a growing graph (the live engine's) is padded to at least, so that
    its programs compile once per capacity, not per chunk (None: the exact sizes, as offline;
    the solver's own size buckets, :func:`swiftjax.posegraph.padded_sizes`)."""
    config = ctx.config
    relative = temporal.relative
    T = ctx.schedule.num_chunks
    chunk_poses_no_loops = chain_poses(relative)
    graph_metrics: dict[str, Any] = {}
    inlier_weights = None
    with ctx.timer("pose graph"):
        priors = _scale_priors(ctx, temporal, chunk_poses_no_loops) if scale_priors else None
        information = None
        if loops.edges or priors is not None:
            information = _graph_information(ctx, temporal, loops, capacity)
        if priors is not None:
            start = metric_scale.apply_scale(chunk_poses_no_loops, priors.start_factor)
            tedges = np.array([(t, t + 1) for t in range(T - 1)], np.int32).reshape(-1, 2)
            with jax.enable_x64(True):
                res0, poses0 = _solve(
                    scale_prior_problem(
                        start,
                        tedges,
                        relative,
                        None if information is None else information[: T - 1],
                        np.zeros(T - 1, bool),
                        priors,
                    ),
                    config,
                    None,
                )
            chunk_poses_no_loops = poses0[:T]
            graph_metrics["metric_prior"] = {
                **priors.stats,
                "start_factor": priors.start_factor,
                "chunks_with_prior": int(priors.used.sum()),
                "no_loops_solve": _solve_metrics(res0),
            }
            if not res0.converged:
                logger.warning(f"pose graph (chain + scale priors) did not converge ({res0.status})")
        if loops.edges:
            L = len(loops.edges)
            edges = [(t, t + 1) for t in range(T - 1)] + [(e.chunk_a, e.chunk_b) for e in loops.edges]
            meas = np.concatenate([relative, np.stack([e.Z for e in loops.edges])])
            robust = np.arange(len(edges)) >= T - 1
            with jax.enable_x64(True):
                if priors is None:
                    initial = chunk_poses_no_loops if warm is None else warm_start(warm.chunk_poses, relative)
                    problem = posegraph.Problem(
                        jnp.asarray(initial),
                        np.asarray(edges, np.int32),
                        jnp.asarray(meas),
                        information=information,
                        robust=robust,
                    )
                else:
                    problem = scale_prior_problem(start, np.asarray(edges, np.int32), meas, information, robust, priors)
                check = None
                if config.graph_pcm and config.robust_loops == "gnc":
                    cov = None
                    if information is None:  # equal weights: the inliers decided on each edge's own noise
                        cov = np.linalg.inv(np.asarray(problem.information, np.float64))
                        cov[: T - 1 + L] = _data_covariance(ctx, temporal, loops, capacity)
                    posegraph.validate(problem)
                    res, check = pcm.consistent_solve(
                        problem,
                        cov,
                        num_chain_nodes=T,
                        options=config.graph,
                        throw=False,
                        pad=True if capacity is None else (capacity[0] + 1, sum(capacity)),
                    )
                    chunk_poses = np.asarray(sim3.normalize(res.poses), np.float64)
                else:
                    res, chunk_poses = _solve(problem, config, config.robust_loops, capacity)
                chunk_poses = chunk_poses[:T]
                r = np.asarray(res.residuals, np.float64)[T - 1 : T - 1 + L]
            om = np.asarray(problem.information, np.float64)[T - 1 : T - 1 + L]
            inlier_weights = res.inlier_weights[T - 1 : T - 1 + L]
            graph_metrics.update(
                {
                    **_solve_metrics(res),
                    "robust_loops": config.robust_loops,
                    "robust_scale": config.robust_scale,
                    "edge_information": "equal" if information is None else "data",
                    "gnc_iterations": res.gnc_iterations,
                    "loop_inlier_weights": inlier_weights.tolist(),
                    "loop_whitened_residuals": np.sqrt(np.einsum("ei,eij,ej->e", r, om, r)).tolist(),
                    "loops_rejected": int(np.sum(inlier_weights < 0.5)),
                    "graph_pcm": check is not None,
                }
            )
            if check is not None:
                kept = check.kept[T - 1 : T - 1 + L]
                graph_metrics.update({"loop_pcm_kept": kept.tolist(), "pcm_threshold": check.threshold})
                if not kept.all():
                    ctx.log(
                        f"pose graph: {int((~kept).sum())} of {L} loop edge(s) inconsistent with the others "
                        "and the odometry (pairwise consistency): out before GNC"
                    )
            if config.robust_loops is not None and np.any(inlier_weights < 0.5):
                ctx.log(
                    f"pose graph: {int(np.sum(inlier_weights < 0.5))} of {len(inlier_weights)} loop edge(s) "
                    f"down-weighted as outliers ({config.robust_loops})"
                )
            if not res.converged:
                logger.warning(f"pose graph did not converge ({res.status})")
        else:
            chunk_poses = chunk_poses_no_loops
    return GraphResult(chunk_poses, chunk_poses_no_loops, graph_metrics, inlier_weights)

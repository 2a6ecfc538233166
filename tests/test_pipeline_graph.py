"""The pipeline's pose-graph stage (``swiftjax.pipeline.graph``): edge information from alignment
records, loop edges as robust GNC edges, the authors' equal weights one option away."""

from __future__ import annotations

import types

import jax
import numpy as np
import pytest
from test_align import make_pair

from swiftjax import align, posegraph, sim3
from swiftjax.align import covariance as ac
from swiftjax.pipeline import PipelineConfig, chain_poses, graph
from swiftjax.pipeline.alignment import info_dict as _info_dict
from swiftjax.pipeline.results import LoopEdge, LoopResult, TemporalResult
from swiftjax.pipeline.rundir import StageTimer


def _record(S, info):
    return {**_info_dict(info), "S": np.asarray(S, np.float64).tolist()}


def test_edge_information_of_a_record_equals_the_core_function(x64):
    prev, cur, K_ref, _ = make_pair(seed=4, o=3, h=16, w=20)
    rng = np.random.default_rng(0)
    cur = cur._replace(depth=cur.depth * (1 + 0.01 * rng.normal(size=cur.depth.shape)))
    S, info = align.align_chunk_pair(prev, cur, K_ref, options=align.AlignOptions(min_points=50))
    rec = _record(S, info)
    om, valid = graph.edge_information(
        [rec, {k: v for k, v in rec.items() if k != "src_covariance"}, {**rec, "pose_fallback": True}], 196.0
    )
    ref = ac.alignment_information(S, info, pixels_per_sample=196.0)
    np.testing.assert_array_equal(valid, [True, False, False])
    np.testing.assert_allclose(om[0], np.asarray(ref.information), rtol=1e-9)
    assert np.all(om[1:] == 0)
    # A loop edge from two halves: the core composition.
    loop = {"align_i": rec, "align_j": rec}
    want = np.asarray(ac.loop_edge_information(S, ref, S, ref).information)
    # Entries that are zero in exact arithmetic are rounding noise (~1e-11 against a scale of
    # 1e4): compared at 1e-9 of the matrix's largest entry, not relative to themselves.
    np.testing.assert_allclose(graph.loop_information(loop, 196.0), want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
    assert graph.loop_information({"align_i": rec, "align_j": {}}, 196.0) is None


def _chain_case(seed=0, T=12):
    """A square-ish route of T chunks: temporal edges with small noise, a true loop (T-1 -> 0)
    and a false one claiming chunks 3 and 8 are at the same place."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(seed)
        ang = np.linspace(0, 2 * np.pi, T, endpoint=False)
        t = np.stack([20 * np.cos(ang), 20 * np.sin(ang), np.zeros(T)], 1)
        xi = np.concatenate([np.zeros((T, 3)), np.stack([np.zeros(T), np.zeros(T), ang], 1), np.zeros((T, 1))], 1)
        truth = np.array(sim3.exp(xi), np.float64)
        truth[:, :3] = t
        rel = np.asarray(sim3.between(truth[:-1], truth[1:]), np.float64)
        noise = rng.normal(size=(T - 1, 7)) * np.array([0.05, 0.05, 0.05, 0.004, 0.004, 0.004, 0.004])
        relative = np.asarray(sim3.compose(rel, sim3.exp(noise)), np.float64)
        Z_true = np.asarray(sim3.between(truth[0], truth[T - 1]), np.float64)
        Z_false = np.array([0.5, 0, 0, 0, 0, 0, 1, 1.0])
    stats = lambda: {
        "S": [0, 0, 0, 0, 0, 0, 1, 1.0],
        "num_points": 50_000,
        "rms": 0.05,
        "src_mean": [0.0, 0.0, 8.0],
        "src_covariance": np.diag([9.0, 1.0, 16.0]).tolist(),
        "pose_fallback": False,
    }
    edges = [stats() for _ in range(T - 1)]
    records = [
        {
            "chunk_i": T - 1,
            "chunk_j": 0,
            "Z": Z_true.tolist(),
            "accepted": True,
            "align_i": stats(),
            "align_j": stats(),
        },
        {"chunk_i": 8, "chunk_j": 3, "Z": Z_false.tolist(), "accepted": True, "align_i": stats(), "align_j": stats()},
        {"chunk_i": 6, "chunk_j": 1, "accepted": False, "reason": "rejected candidate, no edge"},
    ]
    loop_edges = [LoopEdge(0, T - 1, Z_true), LoopEdge(3, 8, Z_false)]
    temporal = TemporalResult(np.zeros((1, 4)), relative, edges, np.eye(3))
    return truth, temporal, LoopResult(records, loop_edges)


def _ctx(T, **config):
    log = []
    ctx = types.SimpleNamespace(
        config=PipelineConfig(**config),
        schedule=types.SimpleNamespace(num_chunks=T),
        timer=StageTimer(),
        log=log.append,
    )
    return ctx, log


def test_false_loop_is_rejected_true_loop_kept(x64):
    truth, temporal, loop_result = _chain_case()
    T = len(truth)
    ctx, log = _ctx(T)  # defaults: GNC on loops, data-driven information
    out = graph.run(ctx, temporal, loop_result)
    np.testing.assert_array_equal(out.inlier_weights, [1.0, 0.0])
    assert out.metrics["edge_information"] == "data" and out.metrics["loops_rejected"] == 1
    assert any("down-weighted" in line for line in log)
    # The answer is the solve without the false loop (same information).
    only_true = loop_result._replace(records=loop_result.records[:1], edges=loop_result.edges[:1])
    ctx1, _ = _ctx(T, robust_loops=None)
    ref = graph.run(ctx1, temporal, only_true)
    np.testing.assert_allclose(out.chunk_poses[:, :3], ref.chunk_poses[:, :3], atol=1e-6)
    # The authors' pose graph (equal weights, no kernel) is bent by the false loop.
    ctx2, _ = _ctx(T, robust_loops=None, edge_information="equal")
    authors = graph.run(ctx2, temporal, loop_result)
    assert authors.metrics["edge_information"] == "equal"
    bend = np.abs(authors.chunk_poses[:, :3] - ref.chunk_poses[:, :3]).max()
    assert bend > 1.0 and np.abs(out.chunk_poses[:, :3] - ref.chunk_poses[:, :3]).max() < 1e-3 * bend


def test_equal_weights_decide_inliers_on_each_edges_own_covariance(x64, monkeypatch):
    """``edge_information="equal"``: the solve's weights are equal, but PCM and GNC get each
    edge's own covariance (drift model + its alignment's statistics): the inverse of the
    ``data`` information, recomputed here from the core functions per edge; the false loop
    still goes, the true one stays."""
    from swiftjax.loops import pcm

    truth, temporal, loop_result = _chain_case(seed=2)
    T = len(truth)
    edges = [dict(e) for e in temporal.edges]
    edges[4].update(num_points=30, rms=0.5)  # one weak alignment: its own covariance is larger
    temporal = temporal._replace(edges=edges)
    seen = {}
    solve = pcm.consistent_solve

    def spy(problem, cov, **kw):
        seen["cov"], seen["information"] = np.array(cov), np.asarray(problem.information)
        return solve(problem, cov, **kw)

    monkeypatch.setattr(pcm, "consistent_solve", spy)
    ctx, _ = _ctx(T, edge_information="equal")
    out = graph.run(ctx, temporal, loop_result)
    np.testing.assert_array_equal(out.inlier_weights, [1.0, 0.0])
    E = T - 1 + len(loop_result.edges)
    np.testing.assert_array_equal(seen["information"][:E], np.broadcast_to(np.eye(7), (E, 7, 7)))
    data, _ = _ctx(T)
    want = np.linalg.inv(graph._graph_information(data, temporal, loop_result))
    np.testing.assert_allclose(seen["cov"][:E], want, rtol=1e-9, atol=1e-15)
    # ... which is not the nominal drift model: the weak edge's own covariance is larger.
    odo, _ = graph._drift_covariance(temporal, loop_result)
    assert np.trace(seen["cov"][4]) > 1.5 * np.trace(odo[4])
    assert np.allclose(np.trace(seen["cov"][3]), np.trace(odo[3]), rtol=0.5)


def test_missing_statistics_fall_back_to_the_drift_model_and_say_so(x64):
    truth, temporal, loop_result = _chain_case(seed=1)
    edges = [dict(e) for e in temporal.edges]
    del edges[2]["src_mean"]
    ctx, log = _ctx(len(truth))
    out = graph.run(ctx, temporal._replace(edges=edges), loop_result)
    assert any("without alignment statistics" in line for line in log)
    np.testing.assert_array_equal(out.inlier_weights, [1.0, 0.0])


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("robust_loops", "tls", "robust_loops"),
        ("edge_information", "chi2", "edge_information"),
        ("robust_scale", 0.0, "robust_scale"),
        ("edge_pixels_per_sample", 0.5, "edge_pixels_per_sample"),
    ],
)
def test_config_validation(field, value, match):
    with pytest.raises(ValueError, match=match):
        PipelineConfig(**{field: value})


# ------------------------------------------------------------ metric scale as pose-graph priors


def _scale_case(T=6, seed=0):
    """Chunks all at the origin (so translations never couple to the scales), rotated about z,
    true chunk scales ``s_t`` (metres per chunk unit); temporal edges with log-scale noise (the
    chain's scale drift), ground heights ``H / s_t`` with small noise of their own."""
    rng = np.random.default_rng(seed)
    with jax.enable_x64(True):
        log_s = np.log(2.0) + np.cumsum(rng.normal(scale=0.05, size=T))
        xi = np.zeros((T, 7))
        xi[:, 5] = np.linspace(0, 1.0, T)
        xi[:, 6] = log_s
        truth = np.array(sim3.exp(xi), np.float64)
        truth[:, :3] = 0.0
        rel = np.asarray(sim3.between(truth[:-1], truth[1:]), np.float64)
    edge_noise = rng.normal(scale=0.04, size=T - 1)
    relative = rel.copy()
    relative[:, 7] *= np.exp(edge_noise)
    H = 1.65
    height_noise = rng.normal(scale=0.01, size=T)
    heights = H / np.exp(log_s + height_noise)
    temporal = TemporalResult(np.zeros((1, 4)), relative, [{} for _ in range(T - 1)], np.eye(3), heights)
    return truth, temporal, H, edge_noise, height_noise


def _metric_ctx(T, H, **config):
    ctx, log = _ctx(T, **config)
    ctx.camera = types.SimpleNamespace(metric=("camera-height", H))
    return ctx, log


def test_scale_priors_solve_the_log_scale_least_squares_problem(x64):
    """Known answer: with every chunk at one place the graph's scale part is linear least squares
    in l_t = log s_t: sum_t (l_t+1 - l_t - log z_t)^2 (identity information) + sum_t (l_t - log m_t)^2 / sigma^2."""
    truth, temporal, H, _, _ = _scale_case()
    T = len(truth)
    sigma = 0.05
    ctx, _ = _metric_ctx(
        T, H, edge_information="equal", metric_combine="prior", metric_prior_sigma=sigma, loop_closure=False
    )
    out = graph.run(ctx, temporal, LoopResult([], []))
    A = np.zeros((2 * T - 1, T))
    b = np.zeros(2 * T - 1)
    for t in range(T - 1):
        A[t, t], A[t, t + 1], b[t] = -1.0, 1.0, np.log(temporal.relative[t, 7])
    log_m = np.log(H / temporal.ground_heights)
    A[T - 1 :] = np.eye(T) / sigma
    b[T - 1 :] = log_m / sigma
    want = np.linalg.lstsq(A, b, rcond=None)[0]
    np.testing.assert_allclose(np.log(out.chunk_poses_no_loops[:, 7]), want, atol=1e-7)
    np.testing.assert_allclose(out.chunk_poses, out.chunk_poses_no_loops)  # no loops: the same poses
    # the rotations are the chain's (the priors only touch the scales; chunk 0 pinned at identity)
    np.testing.assert_allclose(out.chunk_poses[:, :7], graph.chain_poses(temporal.relative)[:, :7], atol=1e-7)
    m = out.metrics["metric_prior"]
    assert m["chunks_with_prior"] == T and m["chunks_gated"] == 0 and m["no_loops_solve"]["converged"]


def test_scale_priors_undo_the_chain_drift_that_the_median_cannot(x64):
    truth, temporal, H, _, _ = _scale_case(T=12, seed=2)
    T = len(truth)
    true_log_s = np.log(truth[:, 7])
    ctx, _ = _metric_ctx(
        T, H, metric_combine="prior", metric_prior_sigma=0.01, loop_closure=False, edge_information="equal"
    )  # (zero-length edges: the drift model is singular)
    prior = graph.run(ctx, temporal, LoopResult([], []))
    chain = graph.chain_poses(temporal.relative)
    m, _ = __import__("swiftjax.metric_scale", fromlist=["x"]).combine_scales(temporal.ground_heights, chain[:, 7], H)
    err_prior = np.abs(np.log(prior.chunk_poses_no_loops[:, 7]) - true_log_s).max()
    err_median = np.abs(np.log(m * chain[:, 7]) - true_log_s).max()
    assert err_prior < 0.03 < err_median


def test_a_gross_scale_vote_is_gated_out(x64):
    truth, temporal, H, _, _ = _scale_case(T=8, seed=1)
    T = len(truth)
    heights = temporal.ground_heights.copy()
    heights[5] *= 3.0  # a wall taken for the road
    heights[2] = np.nan  # no road seen
    ctx, _ = _metric_ctx(T, H, metric_combine="prior", loop_closure=False, edge_information="equal")
    out = graph.run(ctx, temporal._replace(ground_heights=heights), LoopResult([], []))
    m = out.metrics["metric_prior"]
    assert m["chunks_with_prior"] == T - 2 and m["chunks_gated"] == 1 and m["chunks_voting"] == T - 1
    assert np.abs(np.log(out.chunk_poses_no_loops[:, 7] / truth[:, 7])).max() < 0.1


def test_scale_priors_with_loop_edges_keep_the_robust_loop_verdicts(x64):
    truth, temporal, loop_result = _chain_case()
    T = len(truth)
    H = 1.65
    heights = H / truth[:, 7] * np.exp(np.random.default_rng(0).normal(scale=0.01, size=T))
    temporal = temporal._replace(ground_heights=heights)
    ctx, _ = _metric_ctx(T, H, metric_combine="prior")
    out = graph.run(ctx, temporal, loop_result)
    np.testing.assert_array_equal(out.inlier_weights, [1.0, 0.0])  # the false loop still rejected
    assert out.metrics["loops_rejected"] == 1 and out.metrics["converged"]
    assert np.abs(np.log(out.chunk_poses[:, 7] / truth[:, 7])).max() < 0.03
    # metric positions, chunk 0 pinned at the origin: the truth's (metric, scale 1 per chunk,
    # chunk 0 unrotated at (20, 0, 0)) shifted by its first position
    assert np.abs(out.chunk_poses[:, :3] - (truth[:, :3] - truth[0, :3])).max() < 1.0
    # the median path is unchanged by the new options (the default)
    ref = graph.run(_ctx(T)[0], temporal, loop_result)
    ctx_med, _ = _metric_ctx(T, H, metric_combine="median")
    np.testing.assert_array_equal(graph.run(ctx_med, temporal, loop_result).chunk_poses, ref.chunk_poses)


def test_the_prior_problem_passes_validation_and_singular_information_would_not(x64):
    """The pose graph refuses positive semi-definite (singular) information: the scale-only prior
    carries eps = 1e-9 of its weight on the other six entries to stay positive definite."""
    from swiftjax import metric_scale

    truth, temporal, H, _, _ = _scale_case()
    T = len(truth)
    chain = graph.chain_poses(temporal.relative)
    priors = metric_scale.scale_priors(temporal.ground_heights, chain[:, 7], H, 0.02)
    edges = np.array([(t, t + 1) for t in range(T - 1)], np.int32)
    args = (
        metric_scale.apply_scale(chain, priors.start_factor),
        edges,
        temporal.relative,
        None,
        np.zeros(T - 1, bool),
        priors,
    )
    problem = graph.scale_prior_problem(*args)
    posegraph.validate(problem)
    assert problem.num_nodes == T + 1 and bool(problem.fixed[T]) and not np.asarray(problem.fixed[:T]).any()
    with pytest.raises(posegraph.ProblemError, match="not positive definite"):
        posegraph.validate(graph.scale_prior_problem(*args, eps=0.0))


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("metric_combine", "mean", "metric_combine"),
        ("metric_prior_sigma", 0.0, "metric_prior_sigma"),
        ("metric_prior_sigma", float("nan"), "metric_prior_sigma"),
        ("metric_prior_sigma", 2.0, "metric_prior_sigma"),
    ],
)
def test_metric_combine_validation(field, value, match):
    with pytest.raises(ValueError, match=match):
        PipelineConfig(**{field: value})


def test_warm_start_extends_the_previous_solution_by_the_chain(x64):
    """The new chunks' start is the chain from the last solved pose: with the chain itself as the
    previous solution, the warm start is the chain (the independent reference)."""
    _, temporal, _ = _chain_case(seed=3)
    chain = chain_poses(temporal.relative)
    np.testing.assert_allclose(graph.warm_start(chain[:5], temporal.relative), chain, rtol=0, atol=1e-12)
    moved = chain[:5].copy()
    moved[:, :3] += [1.0, 2.0, 3.0]  # a previous solution shifted: the new chunks follow it
    np.testing.assert_allclose(
        graph.warm_start(moved, temporal.relative)[5:, :3], chain[5:, :3] + [1.0, 2.0, 3.0], atol=1e-9
    )
    with pytest.raises(ValueError, match="warm start of 13 chunk poses for a graph of 12"):
        graph.warm_start(np.tile(chain[:1], (13, 1)), temporal.relative)


def test_warm_started_solve_reaches_the_cold_solution(x64):
    truth, temporal, loop_result = _chain_case(seed=2)
    T = len(truth)
    cold = graph.run(_ctx(T)[0], temporal, loop_result)
    # The last solution of the graph before its last chunk arrived, then the grown graph warm-started.
    warm = graph.run(_ctx(T)[0], temporal, loop_result, warm=cold._replace(chunk_poses=cold.chunk_poses[: T - 1]))
    np.testing.assert_allclose(warm.chunk_poses[:, :3], cold.chunk_poses[:, :3], atol=1e-5)
    # Plain least squares started at its own optimum: it starts at the optimal cost and stops at once.
    plain = graph.run(_ctx(T, robust_loops=None)[0], temporal, loop_result)
    again = graph.run(_ctx(T, robust_loops=None)[0], temporal, loop_result, warm=plain)
    np.testing.assert_allclose(again.metrics["cost_initial"], plain.metrics["cost_final"], rtol=1e-6)
    assert again.metrics["iterations"] < plain.metrics["iterations"]
    # (LM's stopping tolerance leaves ~5e-4 m on a 40 m loop at the same cost, to 1e-6)
    np.testing.assert_allclose(again.chunk_poses[:, :3], plain.chunk_poses[:, :3], atol=2e-3)


@pytest.mark.parametrize("information", ["data", "equal"])
def test_pcm_before_gnc_is_the_default_and_records_its_verdicts(x64, information):
    """Two loop edges that contradict each other: PCM keeps the one the odometry supports (the
    true loop), GNC never sees the false one, and the answer is the solve with the true loop
    alone (same information).  ``graph_pcm=False`` is GNC alone (no verdicts recorded)."""
    truth, temporal, loop_result = _chain_case()
    T = len(truth)
    ctx, log = _ctx(T, edge_information=information)
    out = graph.run(ctx, temporal, loop_result)
    assert out.metrics["graph_pcm"] and out.metrics["loop_pcm_kept"] == [True, False]
    assert out.metrics["pcm_threshold"] > 0 and any("pairwise consistency" in line for line in log)
    np.testing.assert_array_equal(out.inlier_weights, [1.0, 0.0])
    only_true = loop_result._replace(records=loop_result.records[:1], edges=loop_result.edges[:1])
    ref = graph.run(_ctx(T, robust_loops=None, edge_information=information)[0], temporal, only_true)
    np.testing.assert_allclose(out.chunk_poses[:, :3], ref.chunk_poses[:, :3], atol=1e-6)
    off = graph.run(_ctx(T, edge_information=information, graph_pcm=False)[0], temporal, loop_result)
    assert not off.metrics["graph_pcm"] and "loop_pcm_kept" not in off.metrics

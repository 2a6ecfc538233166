"""The pipeline's pose-graph stage (``swiftjax.pipeline.graph``): edge information from alignment
records, loop edges as robust GNC edges, the authors' equal weights one option away."""

from __future__ import annotations

import types

import jax
import numpy as np
import pytest

from swiftjax import align, align_covariance as ac, loops, posegraph, sim3
from swiftjax.pipeline import PipelineConfig, graph
from swiftjax.pipeline.loop_closure import LoopEdge, LoopResult
from swiftjax.pipeline.rundir import StageTimer
from swiftjax.pipeline.temporal import TemporalResult, _info_dict

from test_align import make_pair


def _record(S, info):
    return {**_info_dict(info), "S": np.asarray(S, np.float64).tolist()}


def test_edge_information_of_a_record_equals_the_core_function(x64):
    prev, cur, K_ref, _ = make_pair(seed=4, o=3, h=16, w=20)
    rng = np.random.default_rng(0)
    cur = cur._replace(depth=cur.depth * (1 + 0.01 * rng.normal(size=cur.depth.shape)))
    S, info = align.align_chunk_pair(prev, cur, K_ref, min_points=50)
    rec = _record(S, info)
    om, valid = graph.edge_information([rec, {k: v for k, v in rec.items() if k != "src_covariance"},
                                        {**rec, "pose_fallback": True}], 196.0)
    ref = ac.alignment_information(S, info, pixels_per_sample=196.0)
    np.testing.assert_array_equal(valid, [True, False, False])
    np.testing.assert_allclose(om[0], np.asarray(ref.information), rtol=1e-9)
    assert np.all(om[1:] == 0)
    # A loop edge from two halves: the core composition.
    loop = {"align_i": rec, "align_j": rec}
    want = ac.loop_edge_information(S, ref, S, ref)
    np.testing.assert_allclose(graph.loop_information(loop, 196.0), np.asarray(want.information), rtol=1e-9)
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
    stats = lambda: {"S": [0, 0, 0, 0, 0, 0, 1, 1.0], "num_points": 50_000, "rms": 0.05,  # noqa: E731
                     "src_mean": [0.0, 0.0, 8.0], "src_covariance": np.diag([9.0, 1.0, 16.0]).tolist(),
                     "pose_fallback": False}
    edges = [stats() for _ in range(T - 1)]
    records = [
        {"chunk_i": T - 1, "chunk_j": 0, "Z": Z_true.tolist(), "accepted": True, "align_i": stats(), "align_j": stats()},
        {"chunk_i": 8, "chunk_j": 3, "Z": Z_false.tolist(), "accepted": True, "align_i": stats(), "align_j": stats()},
        {"chunk_i": 6, "chunk_j": 1, "accepted": False, "reason": "rejected candidate, no edge"},
    ]
    loop_edges = [LoopEdge(0, T - 1, Z_true), LoopEdge(3, 8, Z_false)]
    temporal = TemporalResult(np.zeros((1, 4)), relative, edges, np.eye(3))
    return truth, temporal, LoopResult(records, loop_edges)


def _ctx(T, **config):
    log = []
    ctx = types.SimpleNamespace(config=PipelineConfig(**config), schedule=types.SimpleNamespace(num_chunks=T),
                                timer=StageTimer(), log=log.append)
    return ctx, log


@pytest.mark.filterwarnings("ignore:pose graph did not converge")  # the authors' graph, bent by the false loop
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


def test_missing_statistics_fall_back_to_the_drift_model_and_say_so(x64):
    truth, temporal, loop_result = _chain_case(seed=1)
    edges = [dict(e) for e in temporal.edges]
    del edges[2]["src_mean"]
    ctx, log = _ctx(len(truth))
    out = graph.run(ctx, temporal._replace(edges=edges), loop_result)
    assert any("without alignment statistics" in line for line in log)
    np.testing.assert_array_equal(out.inlier_weights, [1.0, 0.0])


@pytest.mark.parametrize("field, value, match", [
    ("robust_loops", "tls", "robust_loops"),
    ("edge_information", "chi2", "edge_information"),
    ("robust_scale", 0.0, "robust_scale"),
    ("edge_pixels_per_sample", 0.5, "edge_pixels_per_sample"),
])
def test_config_validation(field, value, match):
    with pytest.raises(ValueError, match=match):
        PipelineConfig(**{field: value})

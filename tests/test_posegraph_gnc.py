"""GNC-TLS on the Sim(3) pose graph (``posegraph.optimize(problem, GraphOptions(kernel="gnc"))``): the closed-form weights,
the continuation against an independent NumPy/SciPy iteratively reweighted TLS, outlier rejection,
odometry never down-weighted, no recompiles, errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
import scipy.stats
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_posegraph import (  # batched float64 NumPy Sim(3) helpers  # float64 NumPy Sim(3), no swiftjax code
    _expm,
    _hat,
    _matrix,
    _vee,
)

from swiftjax import posegraph, sim3
from swiftjax.posegraph import gnc
from swiftjax.synthetic.pose_graphs import circle_graph


def _np_tls_weight(s: float, mu: float, c2: float) -> float:
    """GNC paper eq. (14), written case by case."""
    if s <= mu / (mu + 1) * c2:
        return 1.0
    if s >= (mu + 1) / mu * c2:
        return 0.0
    return min(1.0, max(0.0, np.sqrt(c2 * mu * (mu + 1) / s) - mu))


def test_default_scale_is_the_chi2_quantile():
    assert gnc.DEFAULT_SCALE == pytest.approx(np.sqrt(scipy.stats.chi2.ppf(0.99, 7)), rel=1e-6)


@settings(deadline=None, max_examples=60, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    s=st.lists(st.floats(0.0, 1e4), min_size=1, max_size=8),
    mu=st.floats(1e-6, 1e3),
    c=st.floats(0.1, 10.0),
)
def test_tls_weights_closed_form(x64, s, mu, c):
    s = np.asarray(s)
    w = np.asarray(jax.jit(gnc.tls_weights)(jnp.asarray(s), mu, c * c))
    ref = np.array([_np_tls_weight(v, mu, c * c) for v in s])
    np.testing.assert_allclose(w, ref, atol=1e-12)
    # Non-increasing in the residual; the transition band shrinks to {c^2} as mu grows.
    order = np.argsort(s)
    assert np.all(np.diff(w[order]) <= 1e-12)


def test_weights_are_continuous_and_limits(x64):
    c2, mu = 4.0, 0.7
    lo, hi = mu / (mu + 1) * c2, (mu + 1) / mu * c2
    eps = 1e-9
    w = np.asarray(gnc.tls_weights(jnp.array([lo - eps, lo + eps, hi - eps, hi + eps]), mu, c2))
    np.testing.assert_allclose(w, [1, 1, 0, 0], atol=1e-6)
    # mu -> infinity: TLS (1 below c^2, 0 above)
    w = np.asarray(gnc.tls_weights(jnp.array([0.99 * c2, 1.01 * c2]), 1e6, c2))
    np.testing.assert_array_equal(w, [1.0, 0.0])


def test_initial_mu(x64):
    c2 = 9.0
    sq = jnp.array([1.0, 50.0, 1e4, 3.0])
    robust = jnp.array([False, True, False, True])  # the largest residual is not robust
    assert float(gnc.initial_mu(sq, robust, c2)) == pytest.approx(c2 / (2 * 50.0 - c2))
    assert float(gnc.initial_mu(sq, jnp.array([False, False, False, True]), c2)) == -1.0  # 2*3 <= 9
    assert float(gnc.initial_mu(jnp.array([1e12]), jnp.array([True]), c2)) == gnc.MU_MIN


# ------------------------------------------------------------- continuation vs an independent reference


def _graph_with_false_loops(n=8, num_loops=5, num_false=2, seed=3):
    """A circle graph plus ``num_false`` loop edges between far-apart nodes that claim 'same place'."""
    g = circle_graph(n, num_loops=num_loops, seed=seed)
    rng = np.random.default_rng(seed + 100)
    have = {tuple(sorted(e)) for e in g.edges.tolist()}
    false = []
    while len(false) < num_false:
        i, j = sorted(int(v) for v in rng.integers(0, n, 2))
        if j - i >= n // 3 and (i, j) not in have:
            have.add((i, j))
            false.append((i, j))
    ident = np.array([0.3, -0.2, 0.0, 0, 0, 0, 1, 1.0])
    edges = np.concatenate([g.edges, false])
    meas = np.concatenate([g.measurements, np.broadcast_to(ident, (num_false, 8))])
    info = np.concatenate([g.information, np.broadcast_to(g.information[0], (num_false, 7))])
    robust = np.concatenate([g.is_loop, np.ones(num_false, bool)])
    outlier = np.concatenate([np.zeros(len(g.edges), bool), np.ones(num_false, bool)])
    return g, edges, meas, info, robust, outlier


def _hats(xi):
    """Batched 4x4 Lie-algebra matrices of ``xi [K, 7]`` (same layout as ``test_posegraph._hat``)."""
    return np.stack([_hat(x) for x in xi])


def _logms(m):
    """Batched principal matrix logarithm by eigendecomposition (as ``test_posegraph._logm``)."""
    w, v = np.linalg.eig(m)
    return np.real(v @ (np.log(w)[..., :, None] * np.linalg.inv(v)))


def _np_weighted_lsq(x0_mats, edges, meas, info, weights, fixed):
    """Float64 SciPy trust-region LS on 4x4 matrices, residual sqrt(w) L^T vee(logm(Z^-1 S_i^-1 S_j))."""
    x0 = np.stack(x0_mats)
    free = np.nonzero(~fixed)[0]
    chol = np.linalg.cholesky(np.einsum("ei,ij->eij", info, np.eye(7)))
    zinv = np.linalg.inv(np.stack([_matrix(z) for z in meas]))
    sw = np.sqrt(weights)
    i, j = edges[:, 0], edges[:, 1]

    def poses(x):
        out = x0.copy()
        out[free] = x0[free] @ _expm(_hats(x.reshape(-1, 7)))
        return out

    def raw(ms):
        lg = _logms(zinv @ np.linalg.solve(ms[i], ms[j]))
        return np.stack([_vee(a) for a in lg])

    def fun(x):
        r = raw(poses(x))
        return (sw[:, None] * np.einsum("eji,ej->ei", chol, r)).reshape(-1)

    sol = scipy.optimize.least_squares(fun, np.zeros(7 * len(free)), method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14)
    ms = poses(sol.x)
    r = raw(ms)
    return list(ms), np.einsum("ei,ei->e", r * info, r)


def _np_gnc(x0_mats, edges, meas, info, robust, fixed, c, mu_step=1.4):
    """GTSAM GncOptimizer (TLS) control flow, warm-started, with the SciPy solver above."""
    c2 = c * c
    w = np.ones(len(edges))
    ms, sq = _np_weighted_lsq(x0_mats, edges, meas, info, w, fixed)
    prev = 0.5 * np.sum(w * sq)
    s_max = sq[robust].max()
    if 2 * s_max <= c2:
        return ms, w, 0
    mu = max(c2 / (2 * s_max - c2), 1e-6)
    for it in range(1, 101):
        w = np.array([_np_tls_weight(s, mu, c2) if rb else 1.0 for s, rb in zip(sq, robust)])
        ms, sq = _np_weighted_lsq(ms, edges, meas, info, w, fixed)
        cost = 0.5 * np.sum(w * sq)
        if np.max(np.abs(w - np.round(w))) <= 1e-4 or abs(cost - prev) / max(prev, 1e-7) < 1e-5:
            return ms, w, it
        mu *= mu_step
        prev = cost
    raise AssertionError("reference GNC did not converge")


@pytest.fixture(scope="module")
def gnc_case():
    with jax.enable_x64(True):
        g, edges, meas, info, robust, outlier = _graph_with_false_loops()
        fixed = np.arange(len(g.initial)) == 0
        ref = _np_gnc([_matrix(p) for p in g.initial], edges, meas, info, robust, fixed, gnc.DEFAULT_SCALE)
        clean = posegraph.optimize(
            posegraph.Problem(g.initial, edges[~outlier], meas[~outlier], information=info[~outlier]),
            posegraph.GraphOptions(rtol=1e-14),
        )
    return g, edges, meas, info, robust, outlier, ref, clean


@pytest.mark.parametrize("linear_solver", ["dense", "sparse"])
def test_gnc_matches_numpy_reference(x64, gnc_case, linear_solver):
    g, edges, meas, info, robust, outlier, (ref_mats, ref_w, ref_it), clean = gnc_case
    prob = posegraph.Problem(g.initial, edges, meas, information=info, robust=robust)
    # The reference runs GTSAM's loop warm-started with every solve to convergence.
    res = posegraph.optimize(
        prob,
        posegraph.GraphOptions(
            kernel="gnc", rtol=1e-14, linear_solver=linear_solver, gnc_inner_rtol=1e-14, gnc_restart=False
        ),
    )
    assert res.converged, res.status
    assert res.gnc_iterations == ref_it
    np.testing.assert_allclose(res.inlier_weights, ref_w, atol=1e-6)
    np.testing.assert_array_equal(res.inlier_weights[outlier], 0.0)
    np.testing.assert_array_equal(res.inlier_weights[~robust], 1.0)  # odometry never down-weighted
    assert np.all(res.inlier_weights[robust & ~outlier] == 1.0)
    ours = np.stack([_matrix(p) for p in np.asarray(res.poses)])
    np.testing.assert_allclose(ours, np.stack(ref_mats), atol=1e-7)
    # With the outliers at weight 0 the answer is the outlier-free solve.
    np.testing.assert_allclose(np.asarray(res.poses)[:, :3], np.asarray(clean.poses)[:, :3], atol=1e-8)


def test_gnc_vs_plain_and_cauchy_and_no_recompile(x64, gnc_case):
    g, edges, meas, info, robust, outlier, _, clean = gnc_case
    prob = posegraph.Problem(g.initial, edges, meas, information=info, robust=robust)
    dist = {}
    for kernel in (None, "cauchy", "gnc"):
        res = posegraph.optimize(
            prob, posegraph.GraphOptions(kernel=kernel, kernel_scale=None if kernel == "gnc" else 3.0)
        )
        dist[kernel] = float(np.abs(np.asarray(res.poses)[:, :3] - np.asarray(clean.poses)[:, :3]).max())
        if kernel == "cauchy":  # IRLS weights at the result: the false loops are down-weighted
            assert res.inlier_weights[outlier].max() < 0.05
            np.testing.assert_array_equal(res.inlier_weights[~robust], 1.0)
    assert dist[None] > 0.5
    assert dist["gnc"] < 1e-6 < dist["cauchy"]
    # Another threshold: same bucket, traced scale, no compile (LM's program is the kernel=None one);
    # warm starts and a loose inner tolerance end at the same answer.
    for restart in (True, False):
        res = posegraph.optimize(
            prob, posegraph.GraphOptions(kernel="gnc", kernel_scale=6.0, gnc_restart=restart, rtol=1e-14)
        )
        assert res.compile_seconds == 0.0 and res.converged
        np.testing.assert_array_equal(res.inlier_weights[outlier], 0.0)
        np.testing.assert_allclose(np.asarray(res.poses)[:, :3], np.asarray(clean.poses)[:, :3], atol=1e-8)


def test_outlier_free_graph_is_the_least_squares_answer(x64):
    g = circle_graph(12, num_loops=6, seed=4)
    prob = posegraph.Problem(g.initial, g.edges, g.measurements, information=g.information, robust=g.is_loop)
    plain = posegraph.optimize(prob)
    res = posegraph.optimize(prob, posegraph.GraphOptions(kernel="gnc", kernel_scale=20.0))  # every residual below it
    assert res.gnc_iterations == 0 and res.converged
    np.testing.assert_array_equal(res.inlier_weights, 1.0)
    np.testing.assert_allclose(np.asarray(res.poses), np.asarray(plain.poses), atol=1e-8)
    # No robust edge at all: plain least squares too, whatever the threshold.
    none = posegraph.optimize(
        posegraph.Problem(g.initial, g.edges, g.measurements, information=g.information),
        posegraph.GraphOptions(kernel="gnc", kernel_scale=0.1),
    )
    assert none.gnc_iterations == 0
    np.testing.assert_allclose(np.asarray(none.poses), np.asarray(plain.poses), atol=1e-8)


def test_a_bad_odometry_edge_is_never_down_weighted(x64, gnc_case):
    g, edges, meas, info, robust, outlier, _, _ = gnc_case
    meas = meas.copy()
    meas[3] = np.asarray(sim3.compose(meas[3], sim3.exp(jnp.array([2.0, 0, 0, 0, 0, 0.3, 0]))))
    res = posegraph.optimize(
        posegraph.Problem(g.initial, edges, meas, information=info, robust=robust), posegraph.GraphOptions(kernel="gnc")
    )
    assert not robust[3]
    np.testing.assert_array_equal(res.inlier_weights[~robust], 1.0)


def test_max_iterations_is_reported_not_raised(x64, gnc_case):
    g, edges, meas, info, robust, *_ = gnc_case
    res = posegraph.optimize(
        posegraph.Problem(g.initial, edges, meas, information=info, robust=robust),
        posegraph.GraphOptions(kernel="gnc", gnc_max_iterations=1),
        throw=False,
    )
    assert not res.converged and res.status.startswith("GNC") and res.gnc_iterations == 1
    assert res.result == posegraph.LMResult.gnc_not_converged
    with pytest.raises(posegraph.SolveError, match="GNC: 1 outer iterations") as err:
        posegraph.optimize(
            posegraph.Problem(g.initial, edges, meas, information=info, robust=robust),
            posegraph.GraphOptions(kernel="gnc", gnc_max_iterations=1),
        )
    assert err.value.result.gnc_iterations == 1
    assert np.all(np.isfinite(np.asarray(res.poses)))


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(kernel="tls"), "GraphOptions.kernel: invalid value 'tls'"),
        (dict(kernel="gnc", kernel_scale=-1.0), "kernel_scale"),
        (dict(kernel="gnc", kernel_scale=float("nan")), "kernel_scale"),
        (dict(kernel="gnc", gnc_mu_step=1.0), "gnc_mu_step"),
    ],
)
def test_invalid_options(kw, match):
    with pytest.raises(ValueError, match=match):
        posegraph.GraphOptions(**kw)

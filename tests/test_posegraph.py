"""Sim(3) pose-graph LM: Jacobians, exactness against an independent SciPy reference, special
cases, host-side validation, robust kernels, size buckets, dtypes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
import scipy.optimize

from swiftjax import options, posegraph, sim3
from swiftjax.posegraph import ProblemError, sparse_direct
from swiftjax.posegraph.solver import SparseSim3LM, residual_fn
from swiftjax.synthetic.pose_graphs import chain_graph, circle_graph


def _problem(g, **kw):
    return posegraph.Problem(g.initial, g.edges, g.measurements, information=g.information, **kw)


def _canon(p):
    p = np.array(p, np.float64)
    p[:, 3:7] *= np.where(p[:, 6:7] < 0, -1.0, 1.0)
    return p


# ------------------------------------------------------------------------------ Jacobians


def test_right_jacobian_inverse_matches_sim3_forward_mode(x64):
    rng = np.random.default_rng(1)
    xi = np.concatenate(
        [
            rng.normal(size=(64, 7)) * 0.7,
            rng.normal(size=(16, 7)) * 1e-9,  # theta -> 0, sigma -> 0
            np.c_[rng.normal(size=(16, 6)), np.zeros(16)],  # sigma = 0 exactly
            np.c_[rng.normal(size=(16, 3)), np.zeros((16, 3)), rng.normal(size=16)],  # theta = 0
        ]
    )
    E = jax.jit(sim3.exp)(jnp.asarray(xi))
    ours = jax.jit(posegraph.right_jacobian_inverse_at)(E)
    ref = jax.jit(lambda e: sim3.right_jacobian_inverse(sim3.log(e)))(E)
    np.testing.assert_allclose(ours, ref, atol=1e-12, rtol=1e-12)


def test_edge_jacobians_match_jacfwd(x64):
    g = circle_graph(8, noise=(0.5, 0.3, 0.2), seed=3)  # large residuals: far from zero
    prob = _problem(g)
    poses = jnp.asarray(g.initial)
    r, j_i, j_j = jax.jit(posegraph.residuals_and_jacobians)(poses, prob)
    edges = np.asarray(prob.edges)

    def perturbed(d):  # d [N, 7]: S_n exp(d_n)
        return posegraph.residuals(sim3.compose(poses, sim3.exp(d)), prob)

    full = jax.jit(jax.jacfwd(perturbed))(jnp.zeros((8, 7)))  # [E, 7, N, 7]
    assert float(jnp.max(jnp.abs(r))) > 0.1
    for e, (i, j) in enumerate(edges):
        np.testing.assert_allclose(j_i[e], full[e, :, i, :], atol=1e-10)
        np.testing.assert_allclose(j_j[e], full[e, :, j, :], atol=1e-10)


def test_gradient_equals_autodiff_of_cost(x64):
    g = circle_graph(10, noise=(0.3, 0.1, 0.1), seed=4)
    prob = _problem(g, robust=g.is_loop)
    poses = jnp.asarray(g.initial)
    lin_fn = jax.jit(lambda y, p, code: posegraph.linearize(y, p, code, 2.0))
    grad_fn = jax.jit(jax.grad(lambda d, code: posegraph.cost(sim3.compose(poses, sim3.exp(d)), prob, code, 2.0)))
    for code in range(3):  # none, Huber, Cauchy (traced kernel code: one compile)
        lin = lin_fn(poses, prob, jnp.int32(code))
        grad = grad_fn(jnp.zeros((10, 7)), jnp.int32(code))
        grad = grad.at[0].set(0.0)  # node 0 is fixed
        np.testing.assert_allclose(lin.ne.grad, grad, rtol=1e-9, atol=1e-7 * float(jnp.max(jnp.abs(grad))))


# ----------------------------------------------------------- exactness (independent reference)


def _hat(xi):
    m = np.zeros((4, 4))
    w = xi[3:6]
    m[:3, :3] = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) + xi[6] * np.eye(3)
    m[:3, 3] = xi[:3]
    return m


def _vee(m):
    return np.array([m[0, 3], m[1, 3], m[2, 3], m[2, 1], m[0, 2], m[1, 0], np.trace(m[:3, :3]) / 3])


def _matrix(p):
    x, y, z, w = p[3:7]
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    m = np.eye(4)
    m[:3, :3] = p[7] * r
    m[:3, 3] = p[:3]
    return m


def _expm(a):
    """Matrix exponential by scaling and squaring of a 20-term Taylor series (NumPy; ``[..., 4, 4]``)."""
    k = max(0, int(np.ceil(np.log2(max(np.abs(a).sum(axis=-1).max(), 1e-300) / 0.25))))
    a = a / 2.0**k
    out = term = np.broadcast_to(np.eye(4), a.shape)
    for n in range(1, 21):
        term = term @ a / n
        out = out + term
    for _ in range(k):
        out = out @ out
    return out


def _logm(m):
    """Principal matrix logarithm by eigendecomposition (distinct eigenvalues s e^{+-i theta}, s, 1)."""
    w, v = np.linalg.eig(m)
    return np.real(v @ np.diag(np.log(w)) @ np.linalg.inv(v))


def _scipy_reference(g, fixed):
    """Float64 trust-region LS (scipy.optimize.least_squares) on 4x4 matrices: S = S0 expm(hat d),
    r = vee(logm(Z^-1 S_i^-1 S_j)), whitened by Omega = L L^T.  Shares no code with swiftjax."""
    m0 = [_matrix(p) for p in g.initial]
    free = np.nonzero(~fixed)[0]
    info = np.einsum("ei,ij->eij", g.information, np.eye(7))
    chol = np.linalg.cholesky(info)  # Omega = L L^T, whitened r_w = L^T r
    zinv = [np.linalg.inv(_matrix(z)) for z in g.measurements]

    def poses(x):
        out = list(m0)
        for k, n in enumerate(free):
            out[n] = m0[n] @ _expm(_hat(x[7 * k : 7 * k + 7]))
        return out

    def fun(x):
        ms = poses(x)
        res = []
        for e, (i, j) in enumerate(g.edges):
            r = _vee(_logm(zinv[e] @ np.linalg.solve(ms[i], ms[j])))
            res.append(chol[e].T @ r)
        return np.concatenate(res)

    sol = scipy.optimize.least_squares(
        fun, np.zeros(7 * len(free)), method="trf", jac="3-point", xtol=1e-15, ftol=1e-15, gtol=1e-15
    )
    return 0.5 * float(np.sum(fun(sol.x) ** 2)), poses(sol.x)


@pytest.fixture(scope="module")
def scipy_case():
    g = circle_graph(6, num_loops=4, noise=(0.2, 0.05, 0.05), seed=7)
    return g, _scipy_reference(g, np.arange(6) == 0)


@pytest.mark.parametrize("linear_solver", ["dense", "pcg", "sparse"])
def test_optimum_matches_scipy_reference(x64, scipy_case, linear_solver):
    g, (ref_cost, ref_mats) = scipy_case
    res = posegraph.optimize(_problem(g), posegraph.GraphOptions(rtol=1e-15, gtol=1e-13, linear_solver=linear_solver))
    assert res.converged, res.status
    assert res.cost_final == pytest.approx(ref_cost, rel=1e-9)
    ours = np.stack([_matrix(p) for p in np.asarray(res.poses)])
    np.testing.assert_allclose(ours, np.stack(ref_mats), atol=1e-7)
    # Stationarity of the exact cost at our optimum.
    prob = _problem(g)
    grad = jax.jit(jax.grad(lambda d: posegraph.cost(sim3.compose(res.poses, sim3.exp(d)), prob)))(jnp.zeros((6, 7)))
    assert float(jnp.max(jnp.abs(grad[1:]))) < 1e-6


@pytest.fixture(scope="module")
def dense_reference():
    with jax.enable_x64(True):
        g = circle_graph(16, seed=2)
        return g, posegraph.optimize(_problem(g), posegraph.GraphOptions(linear_solver="dense", rtol=1e-14))


@pytest.mark.parametrize("linear_solver, rel, atol", [("pcg", 1e-10, 1e-8), ("sparse", 1e-12, 1e-9)])
def test_linear_solvers_agree_with_dense(x64, dense_reference, linear_solver, rel, atol):
    g, a = dense_reference
    b = posegraph.optimize(_problem(g), posegraph.GraphOptions(linear_solver=linear_solver, rtol=1e-14))
    assert b.cost_final == pytest.approx(a.cost_final, rel=rel)
    np.testing.assert_allclose(_canon(b.poses), _canon(a.poses), atol=atol)
    assert a.linear_iterations == 0
    if linear_solver == "pcg":
        assert b.linear_iterations > 0


def test_auto_rule(x64):
    # auto: a chain with few loops goes to the sparse solver, random loops to PCG.
    chain = chain_graph(200, loop_every=50)
    assert posegraph.choose_linear_solver(224, num_nodes=200, edges=chain.edges) == "sparse"
    circ = circle_graph(1000)  # node-graph fill ratio 40
    assert posegraph.choose_linear_solver(1024, num_nodes=1000, edges=circ.edges) == "pcg"
    assert posegraph.choose_linear_solver(32, num_nodes=20, edges=circ.edges[:20]) == "dense"
    circ = circle_graph(200)  # fill 9.8: the direct solve when CHOLMOD is there (SuperLU: PCG)
    want = "sparse" if sparse_direct.BACKEND == "cholmod" else "pcg"
    assert posegraph.choose_linear_solver(224, num_nodes=200, edges=circ.edges) == want


def test_optimistix_least_squares_entry_point(x64):
    g = circle_graph(16, seed=5)
    prob = _problem(g)
    sol = optx.least_squares(
        residual_fn,
        SparseSim3LM(rtol=1e-12, gtol=1e-12, linear_solver="pcg"),
        prob.poses,
        args=prob,
        max_steps=50,
        throw=False,
    )
    assert sol.result == optx.RESULTS.successful
    ref = posegraph.optimize(prob, posegraph.GraphOptions(rtol=1e-12, gtol=1e-12, linear_solver="pcg"))
    # Same optimum; the padded run takes different (inexact-CG) steps, so agree to ~1e-7.
    np.testing.assert_allclose(_canon(sol.value), _canon(ref.poses), atol=1e-6)
    assert float(sol.state.lin.cost) == pytest.approx(ref.cost_final, rel=1e-12)


# ---------------------------------------------------------------------------- special cases


def test_chain_without_loops_is_unchanged(x64):
    g = chain_graph(30, loop_every=1000)
    res = posegraph.optimize(_problem(g))
    assert res.converged and res.num_steps <= 1
    assert res.cost_final < 1e-20
    np.testing.assert_allclose(res.poses, g.initial, atol=1e-12)


def test_fixed_nodes_do_not_move_and_truth_is_recovered(x64):
    g = circle_graph(16, seed=11)
    fixed = np.zeros(16, bool)
    fixed[[0, 8]] = True
    init = g.initial.copy()
    init[8] = g.truth[8]
    prob = posegraph.Problem(init, g.edges, g.measurements, information=g.information, fixed=fixed)
    res = posegraph.optimize(prob)
    np.testing.assert_array_equal(np.asarray(res.poses)[[0, 8]], init[[0, 8]])
    # Truth is recovered to the noise level (dead reckoning starts far off).
    err0 = np.abs(init[:, :3] - g.truth[:, :3]).max()
    err = np.abs(np.asarray(res.poses)[:, :3] - g.truth[:, :3]).max()
    assert err < 0.3 and err < 0.5 * err0


def test_information_forms_are_equivalent(x64):
    g = circle_graph(16, seed=6)
    e = len(g.edges)
    w = np.linspace(1.0, 3.0, e)
    forms = [w, np.repeat(w[:, None], 7, 1), w[:, None, None] * np.eye(7)]
    costs = [
        posegraph.optimize(posegraph.Problem(g.initial, g.edges, g.measurements, information=f)).cost_final
        for f in forms
    ]
    assert costs[0] == pytest.approx(costs[1], rel=1e-12) and costs[0] == pytest.approx(costs[2], rel=1e-12)
    scalar = posegraph.Problem(g.initial, g.edges, g.measurements, information=2.0)
    ident = posegraph.Problem(g.initial, g.edges, g.measurements)
    assert float(posegraph.cost(scalar.poses, scalar)) == pytest.approx(2 * float(posegraph.cost(ident.poses, ident)))


def test_same_bucket_does_not_recompile(x64):
    a = circle_graph(13, seed=1)
    b = circle_graph(15, seed=2)  # same (N, E) bucket as a: (32, 32)
    ra = posegraph.optimize(_problem(a))
    rb = posegraph.optimize(_problem(b))
    assert ra.bucket == rb.bucket == (32, 32)
    assert rb.compile_seconds == 0.0
    assert rb.poses.shape == (15, 8)
    assert posegraph.bucket_size(33) == 40 and posegraph.bucket_size(1000) == 1024


def test_bucket_sizes():
    sizes = [posegraph.bucket_size(n) for n in range(1, 5000)]
    assert all(s >= n for n, s in zip(range(1, 5000), sizes))
    assert all(s <= max(32, 1.25 * n) for n, s in zip(range(1, 5000), sizes))
    assert len(set(sizes)) <= 40


def test_float32_agrees_with_float64():
    g = circle_graph(16, seed=8)
    r32 = posegraph.optimize(
        posegraph.Problem(g.initial.astype(np.float32), g.edges, g.measurements, information=g.information)
    )
    with jax.enable_x64(True):
        r64 = posegraph.optimize(_problem(g))
    assert r32.poses.dtype == jnp.float32 and r32.converged
    assert r32.cost_final == pytest.approx(r64.cost_final, rel=1e-3)
    np.testing.assert_allclose(_canon(r32.poses), _canon(r64.poses), atol=2e-3)


# ------------------------------------------------------------------------------ robustness


def test_false_loop_moves_the_map_less_with_a_robust_kernel(x64):
    g = circle_graph(16, num_loops=8, seed=9)
    ref = posegraph.optimize(_problem(g, robust=g.is_loop)).poses
    # A false loop between far-apart nodes 2 and 10 claiming they are 0.5 units apart.
    bad = np.array([0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0])
    edges = np.concatenate([g.edges, [[2, 10]]])
    meas = np.concatenate([g.measurements, bad[None]])
    info = np.concatenate([g.information, g.information[-1:]])
    robust = np.concatenate([g.is_loop, [True]])
    prob = posegraph.Problem(g.initial, edges, meas, information=info, robust=robust)
    moved = {}
    for k, kernel in enumerate((None, "huber", "cauchy")):
        res = posegraph.optimize(prob, posegraph.GraphOptions(kernel=kernel, kernel_scale=3.0))
        moved[kernel] = float(np.abs(np.asarray(res.poses)[:, :3] - np.asarray(ref)[:, :3]).max())
        if k:
            assert res.compile_seconds == 0.0  # the kernel is a traced value: no recompile
    assert moved[None] > 0.5
    assert moved["huber"] < 0.2 * moved[None]
    assert moved["cauchy"] < 0.05 * moved[None]


def test_robust_rho_and_weight_closed_forms():
    s = jnp.array([0.0, 0.5, 1.0, 4.0, 100.0])
    k = 2.0
    np.testing.assert_allclose(posegraph.robust_rho(s, None, k), s)
    hub = np.where(s <= 4, s, 2 * k * np.sqrt(s) - 4)
    np.testing.assert_allclose(posegraph.robust_rho(s, "huber", k), hub, rtol=1e-6)
    np.testing.assert_allclose(posegraph.robust_rho(s, "cauchy", k), 4 * np.log1p(s / 4), rtol=1e-6)
    for kern in ("huber", "cauchy"):
        d = jax.vmap(jax.grad(lambda x: posegraph.robust_rho(x, kern, k)))(s + 1e-3)
        np.testing.assert_allclose(posegraph.robust_weight(s + 1e-3, kern, k), d, rtol=1e-5)


# ----------------------------------------------------------------------- host validation


def _base():
    g = circle_graph(6, num_loops=2, seed=0)
    return g.initial.copy(), g.edges.copy(), g.measurements.copy(), np.einsum("ei,ij->eij", g.information, np.eye(7))


@pytest.mark.parametrize(
    "case, match",
    [
        ("self", r"self-edges"),
        ("range", r"out of range"),
        ("duplicate", r"duplicate edges"),
        ("reversed", r"duplicate edges"),
        ("nan_meas", r"measurements: non-finite values at edges 1"),
        ("bad_scale", r"measurements: non-positive scale"),
        ("not_pd", r"information: not positive definite at edges 2"),
        ("asym", r"information: not symmetric"),
        ("disconnected", r"nodes 6 are not connected"),
        ("nan_pose", r"poses: non-finite values at nodes 3"),
        ("no_fixed", r"no node is fixed"),
    ],
)
def test_invalid_inputs_raise_clear_errors(case, match):
    poses, edges, meas, info = _base()
    fixed = None
    if case == "self":
        edges[3] = [2, 2]
    elif case == "range":
        edges[3] = [2, 17]
    elif case == "duplicate":
        edges[3] = edges[2]
    elif case == "reversed":
        edges[3] = edges[2][::-1]
    elif case == "nan_meas":
        meas[1, 0] = np.nan
    elif case == "bad_scale":
        meas[1, 7] = -1.0
    elif case == "not_pd":
        info[2, 6, 6] = -1.0
    elif case == "asym":
        info[2, 0, 1] = 5.0
    elif case == "disconnected":
        poses = np.concatenate([poses, poses[:1]])
    elif case == "nan_pose":
        poses[3, 1] = np.inf
    elif case == "no_fixed":
        fixed = np.zeros(len(poses), bool)
    prob = posegraph.Problem(poses, edges, meas, information=info, fixed=fixed)
    with pytest.raises(ProblemError, match=match):
        posegraph.optimize(prob)


def test_constructor_shape_errors():
    poses, edges, meas, info = _base()
    with pytest.raises(ProblemError, match="poses has shape"):
        posegraph.Problem(poses[:, :7], edges, meas)
    with pytest.raises(ProblemError, match="measurements has shape"):
        posegraph.Problem(poses, edges, meas[:-1])
    with pytest.raises(ProblemError, match="information has shape"):
        posegraph.Problem(poses, edges, meas, information=info[:, :6, :6])
    with pytest.raises(ProblemError, match="edges has dtype"):
        posegraph.Problem(poses, edges.astype(float), meas)


# ------------------------------------------------------------ results, options, solver objects


def test_lm_result_drives_converged_and_throw(x64):
    g = circle_graph(10, noise=(0.2, 0.1, 0.05), seed=4)
    prob = _problem(g)
    res = posegraph.optimize(prob)
    assert res.converged and res.result == posegraph.LMResult.relative_decrease
    assert res.status == posegraph.LMResult[res.result]
    short = posegraph.optimize(prob, posegraph.GraphOptions(max_steps=1), throw=False)
    assert not short.converged and short.result == posegraph.LMResult.nonlinear_max_steps_reached
    with pytest.raises(posegraph.SolveError, match="max_steps reached after 1 steps") as err:
        posegraph.optimize(prob, posegraph.GraphOptions(max_steps=1))
    assert err.value.result.num_steps == 1


def test_optimistix_throw_fails_on_a_stalled_solve(x64):
    g = circle_graph(8, seed=2)
    prob = _problem(g)
    from swiftjax.posegraph.linear_solvers import AbstractLinearSolver

    class Failing(AbstractLinearSolver):  # every step rejected: the damping grows past 1e16
        def solve(self, ne, damping, *, rtol=None, fixed=None, active=None):
            return jnp.zeros_like(ne.grad), jnp.zeros((), jnp.int32), jnp.asarray(False)

    solver = SparseSim3LM(linear_solver=Failing())
    sol = optx.least_squares(residual_fn, solver, prob.poses, args=prob, max_steps=30, throw=False)
    assert sol.state.result == posegraph.LMResult.stalled
    assert sol.result == optx.RESULTS.nonlinear_divergence
    with pytest.raises(Exception, match="diverged"):
        optx.least_squares(residual_fn, solver, prob.poses, args=prob, max_steps=30, throw=True)
    ok = optx.least_squares(residual_fn, SparseSim3LM(), prob.poses, args=prob, max_steps=50, throw=True)
    assert ok.result == optx.RESULTS.successful and bool(posegraph.solver.is_converged(ok.state.result))


def test_graph_options_are_validated_once_and_override():
    with pytest.raises(
        ValueError, match="GraphOptions.max_steps: -1 is out of range; allowed: an integer with 0 <= value <= 100000"
    ):
        posegraph.GraphOptions(max_steps=-1)
    with pytest.raises(
        ValueError, match="GraphOptions.kernel: invalid value 'tukey'; allowed: one of gnc, cauchy, huber"
    ):
        posegraph.GraphOptions(kernel="tukey")
    with pytest.raises(ValueError, match="GraphOptions.linear_solver: invalid value 'qr'"):
        posegraph.GraphOptions(linear_solver="qr")
    with pytest.raises(ValueError, match="kernel must be"):
        posegraph.robust_rho(jnp.ones(2), "tukey", 1.0)
    assert posegraph.GraphOptions(kernel="gnc").scale == posegraph.gnc.DEFAULT_SCALE
    assert posegraph.GraphOptions(kernel="huber").scale == 1.0
    g = circle_graph(6, seed=1)
    with pytest.raises(TypeError):
        posegraph.optimize(posegraph.Problem(g.initial, g.edges, g.measurements), max_steps=3)  # no keywords
    with pytest.raises(
        options.OptionError, match="unknown option 'max_step' of GraphOptions \\(did you mean max_steps\\?\\)"
    ):
        posegraph.GraphOptions().replace(max_step=3)


def test_pipeline_defaults_come_from_graph_options():
    from swiftjax.pipeline import PipelineConfig
    from swiftjax.posegraph.options import PIPELINE

    cfg = PipelineConfig()
    assert cfg.robust_loops == PIPELINE.kernel and cfg.robust_scale == PIPELINE.scale
    assert cfg.max_lm_steps == PIPELINE.max_steps == posegraph.GraphOptions().max_steps


def test_linear_solver_objects_agree(x64):
    from swiftjax.posegraph import linear

    g = circle_graph(12, seed=3)
    prob = _problem(g)
    lin = posegraph.linearize(prob.poses, prob, None, 1.0)
    damping = jnp.full((12, 7), 1e-3)
    x_dense, _, ok = posegraph.DenseCholesky().solve(lin.ne, damping)
    x_pcg, k, ok2 = posegraph.BlockJacobiPCG(max_iterations=500).solve(lin.ne, damping, rtol=1e-12)
    x_sp, _, ok3 = posegraph.HostSparse().solve(lin.ne, damping, fixed=prob.fixed, active=prob.edge_mask)
    assert bool(ok & ok2 & ok3) and int(k) > 0
    np.testing.assert_allclose(x_pcg, x_dense, atol=1e-8)
    np.testing.assert_allclose(x_sp, x_dense, atol=1e-10)
    np.testing.assert_array_equal(x_dense, linear.solve_dense(lin.ne, damping)[0])

"""Chordal initialisation of the Sim(3) pose graph: exact on noise-free graphs, equal to an
independent dense NumPy least-squares reference on noisy ones, and a better LM start."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from swiftjax import posegraph
from swiftjax.posegraph.initialization import chordal_initialization
from swiftjax.synthetic.pose_graphs import circle_graph


def _problem(g, poses=None, **kw):
    return posegraph.Problem(
        g.initial if poses is None else poses, g.edges, g.measurements, information=g.information, **kw
    )


def _rst(p):
    p = np.asarray(p, np.float64)
    return Rotation.from_quat(p[:, 3:7]).as_matrix(), p[:, 0:3], p[:, 7]


def _numpy_chordal(g, fixed):
    """Dense float64 reference of the three weighted linear least-squares problems."""
    rz, tz, sz = _rst(g.measurements)
    r0, t0, s0 = _rst(g.initial)
    info = np.asarray(g.information)  # [E, 7] diagonal
    w_t, w_r, w_s = info[:, 0:3].mean(1), info[:, 3:6].mean(1), info[:, 6]
    n = len(g.initial)
    free = np.nonzero(~fixed)[0]
    col = {int(v): k for k, v in enumerate(free)}

    def lstsq(b, x_fixed, rows_of):
        # rows_of(e) -> list of (coef_i [b, b], coef_j [b, b], rhs [b]) for x_j*cj + x_i*ci = rhs
        a_rows, rhs_rows = [], []
        for e, (i, j) in enumerate(g.edges):
            ci, cj, rhs, w = rows_of(e)
            row = np.zeros((b, b * len(free)))
            rhs = rhs.copy()
            for node, coef in ((i, ci), (j, cj)):
                if fixed[node]:
                    rhs -= coef @ x_fixed[node]
                else:
                    row[:, b * col[node] : b * col[node] + b] += coef
            a_rows.append(np.sqrt(w) * row)
            rhs_rows.append(np.sqrt(w) * rhs)
        sol = np.linalg.lstsq(np.concatenate(a_rows), np.concatenate(rhs_rows), rcond=None)[0]
        x = np.array(x_fixed, np.float64)
        x[free] = sol.reshape(-1, b)
        return x

    eye3, eye9 = np.eye(3), np.eye(9)
    x_rot = lstsq(9, r0.reshape(n, 9), lambda e: (-np.kron(eye3, rz[e].T), eye9, np.zeros(9), w_r[e]))
    u, _, vt = np.linalg.svd(x_rot.reshape(n, 3, 3))
    d = np.sign(np.linalg.det(u @ vt))
    u[:, :, 2] *= d[:, None]
    rot = np.where(fixed[:, None, None], r0, u @ vt)
    log_s = lstsq(1, np.log(s0)[:, None], lambda e: (-np.eye(1), np.eye(1), np.log(sz[e : e + 1]), w_s[e]))[:, 0]
    s = np.exp(log_s)
    i = g.edges[:, 0]
    c = s[i, None] * np.einsum("eab,eb->ea", rot[i], tz)
    t = lstsq(3, t0, lambda e: (-eye3, eye3, c[e], w_t[e] / s[i[e]] ** 2))
    return rot, t, s


def test_noise_free_graph_is_recovered_exactly(x64):
    g = circle_graph(40, num_loops=30, noise=(1e-12, 1e-12, 1e-12), seed=3)
    init, ok = jax.jit(chordal_initialization, static_argnums=1)(_problem(g), "dense")
    assert bool(ok)
    r, t, s = _rst(init)
    rt, tt, st = _rst(g.truth)
    np.testing.assert_allclose(r, rt, atol=1e-9)
    np.testing.assert_allclose(t, tt, atol=1e-7)
    np.testing.assert_allclose(s, st, rtol=1e-9)


@pytest.mark.parametrize("linear_solver", ["dense", "sparse", "pcg"])
def test_matches_dense_numpy_reference(x64, linear_solver):
    g = circle_graph(12, num_loops=8, noise=(0.3, 0.1, 0.05), seed=5)
    fixed = np.arange(12) < 2  # two anchors: fixed values enter every right-hand side
    init, ok = jax.jit(chordal_initialization, static_argnums=1)(_problem(g, fixed=fixed), linear_solver)
    assert bool(ok)
    r, t, s = _rst(init)
    rr, tr, sr = _numpy_chordal(g, fixed)
    np.testing.assert_allclose(r, rr, atol=1e-8)
    np.testing.assert_allclose(s, sr, rtol=1e-9)
    np.testing.assert_allclose(t, tr, atol=1e-7)
    np.testing.assert_array_equal(np.asarray(init)[fixed], np.asarray(g.initial)[fixed])


def test_chordal_start_reaches_the_global_minimum(x64):
    """Circle with random loops from dead reckoning: LM alone ends in a worse local minimum;
    with the chordal start it reaches the minimum found from the truth."""
    g = circle_graph(400, seed=0, noise=(0.05, 0.08, 0.01))
    plain = posegraph.optimize(_problem(g), posegraph.GraphOptions(rtol=1e-12))
    chordal = posegraph.optimize(_problem(g), posegraph.GraphOptions(rtol=1e-12, initialization="chordal"))
    from_truth = posegraph.optimize(_problem(g, poses=g.truth), posegraph.GraphOptions(rtol=1e-12))
    assert chordal.converged and from_truth.converged
    assert chordal.cost_final == pytest.approx(from_truth.cost_final, rel=1e-9)
    assert chordal.cost_start < 1e-2 * chordal.cost_initial
    assert plain.cost_final > 2.0 * from_truth.cost_final  # the reason for the option (measured: 3774 vs 1413)


def test_invalid_initialization_name():
    g = circle_graph(8, num_loops=2)
    with pytest.raises(ValueError, match="initialization"):
        posegraph.optimize(_problem(g), posegraph.GraphOptions(initialization="spanning-tree"))


@pytest.mark.parametrize("linear_solver", ["sparse", "pcg"])
def test_chordal_start_reports_the_given_cost(x64, linear_solver):
    """Both drivers (host-looped sparse, one-program PCG): ``cost_initial`` is the cost of the
    given poses, ``cost_start`` that of the chordal start, and the optimum is the same."""
    g = circle_graph(60, num_loops=20, seed=4)
    given = float(posegraph.cost(jax.numpy.asarray(g.initial), _problem(g)))
    plain = posegraph.optimize(_problem(g), posegraph.GraphOptions(rtol=1e-12, linear_solver=linear_solver))
    chordal = posegraph.optimize(
        _problem(g), posegraph.GraphOptions(rtol=1e-12, linear_solver=linear_solver, initialization="chordal")
    )
    assert plain.cost_initial == pytest.approx(given, rel=1e-12)
    assert plain.cost_start == plain.cost_initial
    assert chordal.cost_initial == pytest.approx(given, rel=1e-12)
    assert chordal.cost_start < chordal.cost_initial
    assert chordal.cost_final == pytest.approx(plain.cost_final, rel=1e-9)

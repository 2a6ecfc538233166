"""The sim3 / align / posegraph API edges are flagged or refused, never
silent NaN or a silent difference.

* ``sim3``: a non-unit quaternion means its unit version in every function (act, compose,
  inverse, as_matrix, log agree); ``log`` of an invalid element (``q = 0``, ``s <= 0``) is an
  all-NaN tangent and :func:`sim3.is_valid` flags it; ``from_rst``/``from_matrix`` refuse
  ``3 I``, reflections and ``s <= 0`` on host values; :func:`sim3.check` refuses at the host.
* ``align.umeyama`` on float16: a TypeError that says what to do.
* ``posegraph.optimize(GraphOptions(max_steps=0 / 1))``: the true initial cost, and exactly the steps asked.
* The tests' jaxtyping hook (``tests/conftest.py``) enforces the annotated shapes of the loop
  and pose-graph array functions, while the host-boundary checkers still raise their own
  ``ValueError`` naming the bad input (not the hook's ``TypeError``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from swiftjax import align, posegraph, sim3, so3
from swiftjax.synthetic.pose_graphs import circle_graph


def _element(rng, n):
    q = Rotation.random(n, random_state=int(rng.integers(1 << 30))).as_quat()
    return np.concatenate([rng.normal(size=(n, 3)), q, rng.uniform(0.5, 2.0, (n, 1))], axis=1)


def _matrix(S):
    """float64 NumPy reference: [[s R(q/|q|), t], [0, 1]] with scipy's rotation."""
    M = np.tile(np.eye(4), (len(S), 1, 1))
    M[:, :3, :3] = S[:, 7, None, None] * Rotation.from_quat(S[:, 3:7]).as_matrix()  # scipy normalises
    M[:, :3, 3] = S[:, :3]
    return M


def test_non_unit_quaternion_means_its_unit_version_everywhere(x64):
    rng = np.random.default_rng(0)
    S = _element(rng, 32)
    B = _element(rng, 32)
    scaled = S.copy()
    scaled[:, 3:7] *= rng.uniform(0.2, 5.0, (32, 1))  # same rotation, |q| != 1
    x = rng.normal(size=(32, 3))
    ref = _matrix(S)
    np.testing.assert_allclose(sim3.act(scaled, x), np.einsum("nij,nj->ni", ref[:, :3, :3], x) + S[:, :3], atol=1e-12)
    np.testing.assert_allclose(sim3.as_matrix(scaled), ref, atol=1e-12)
    np.testing.assert_allclose(sim3.as_matrix(sim3.compose(scaled, B)), ref @ _matrix(B), atol=1e-12)
    np.testing.assert_allclose(sim3.as_matrix(sim3.inverse(scaled)), np.linalg.inv(ref), atol=1e-11)
    np.testing.assert_allclose(sim3.log(scaled), sim3.log(S), atol=1e-12)
    np.testing.assert_allclose(so3.act(scaled[:, 3:7], x), so3.act(S[:, 3:7], x), atol=1e-12)
    assert np.all(np.asarray(sim3.is_valid(scaled)))


def test_invalid_elements_log_to_nan_and_are_flagged(x64):
    S = np.array(
        [
            [1, 2, 3, 0, 0, 0, 1, 1.0],  # valid
            [1, 2, 3, 0, 0, 0, 0, 1.0],  # zero quaternion
            [1, 2, 3, 0, 0, 0, 1, 0.0],  # zero scale
            [1, 2, 3, 0, 0, 0, 1, -2.0],  # negative scale
            [np.nan, 2, 3, 0, 0, 0, 1, 1.0],  # non-finite
        ]
    )
    valid = np.asarray(jax.jit(sim3.is_valid)(S))
    np.testing.assert_array_equal(valid, [True, False, False, False, False])
    xi = np.asarray(jax.jit(sim3.log)(S))
    assert np.all(np.isfinite(xi[0])) and np.all(np.isnan(xi[1:]))  # never a plausible number
    assert np.all(np.isnan(np.asarray(sim3.act(S[1], np.ones(3)))))  # q = 0 acts as NaN, not as identity
    sim3.check(S[:1], "poses")
    with pytest.raises(ValueError, match=r"poses: element 1 \(of 5\) is not a valid Sim\(3\) element.*4 bad"):
        sim3.check(S, "poses")
    with pytest.raises(ValueError, match="unit quaternion"):
        sim3.check(np.array([[0, 0, 0, 0, 0, 0, 2.0, 1]]), "Z", unit_tol=1e-3)


@pytest.mark.parametrize(
    "R, s, match",
    [
        (3.0 * np.eye(3), 1.0, "not a rotation"),
        (np.diag([1.0, 1.0, -1.0]), 1.0, "not a rotation"),  # a reflection
        (np.eye(3) + 1e-2, 1.0, "not a rotation"),
        (np.eye(3), 0.0, "scale must be > 0"),
        (np.eye(3), -1.0, "scale must be > 0"),
        (np.eye(3), np.nan, "scale must be > 0"),
    ],
)
def test_from_rst_refuses_non_rotations_on_the_host(R, s, match):
    with pytest.raises(ValueError, match=match):
        sim3.from_rst(R, np.zeros(3), s)


def test_from_rst_and_from_matrix_accept_rotations_and_stay_jittable(x64):
    rng = np.random.default_rng(1)
    R = Rotation.random(4, random_state=1).as_matrix()
    S = sim3.from_rst(R, rng.normal(size=(4, 3)), np.full(4, 2.0))
    np.testing.assert_allclose(np.asarray(sim3.as_matrix(S))[:, :3, :3], 2.0 * R, atol=1e-12)
    with pytest.raises(ValueError, match="positive determinant"):
        sim3.from_matrix(np.diag([2.0, 2.0, -2.0, 1.0]))  # a reflection
    with pytest.raises(ValueError, match="not a rotation"):
        sim3.from_matrix(np.diag([2.0, 1.0, 1.0, 1.0]))  # not a similarity
    # Under jit nothing is checked (no host round-trip): the caller checks the result.
    out = jax.jit(sim3.from_rst)(jnp.asarray(3.0 * np.eye(3)), jnp.zeros(3), jnp.asarray(1.0))
    assert out.shape == (8,)


def test_umeyama_float16_is_a_clear_type_error():
    x = np.random.default_rng(0).normal(size=(10, 3)).astype(np.float16)
    with pytest.raises(TypeError, match="float32 or float64, got float16.*astype"):
        align.umeyama(x, x)


@pytest.mark.parametrize("linear_solver", ["dense", "sparse"])
def test_max_steps_zero_and_one_report_the_true_initial_cost(x64, linear_solver):
    g = circle_graph(10, noise=(0.2, 0.1, 0.05), seed=4)
    prob = posegraph.Problem(g.initial, g.edges, g.measurements, information=g.information)
    true_cost = float(posegraph.cost(prob.poses, prob))
    assert true_cost > 1.0
    r0 = posegraph.optimize(prob, posegraph.GraphOptions(max_steps=0, linear_solver=linear_solver), throw=False)
    assert r0.cost_initial == pytest.approx(true_cost, rel=1e-12)
    assert r0.num_steps == 0 and r0.cost_final == pytest.approx(true_cost, rel=1e-12)
    np.testing.assert_allclose(np.asarray(r0.poses), np.asarray(sim3.normalize(prob.poses)), atol=1e-15)
    assert not r0.converged and r0.status == "max_steps reached"
    r1 = posegraph.optimize(prob, posegraph.GraphOptions(max_steps=1, linear_solver=linear_solver), throw=False)
    assert r1.num_steps == 1 and r1.cost_initial == pytest.approx(true_cost, rel=1e-12)
    assert r1.num_accepted + r1.num_rejected == 1  # one LM step, accepted or rejected
    assert r1.cost_final < true_cost  # one real LM step was made
    full = posegraph.optimize(prob, posegraph.GraphOptions(linear_solver=linear_solver))
    assert full.converged and full.cost_final <= r1.cost_final
    with pytest.raises(ValueError, match="GraphOptions.max_steps: -1 is out of range"):
        posegraph.GraphOptions(max_steps=-1)


def test_loop_and_posegraph_shapes_are_enforced():
    import jaxtyping

    from swiftjax import loops
    from swiftjax.loops import pcm
    from swiftjax.posegraph import linear

    assert hasattr(loops.loop_edge, "__wrapped__") and hasattr(posegraph.residuals, "__wrapped__")
    S = np.tile(np.array([0, 0, 0, 0, 0, 0, 1, 1], np.float32), (4, 1))
    with pytest.raises(jaxtyping.TypeCheckError):
        loops.loop_edge(S[:, :7], S)  # a Sim(3) element is [..., 8]
    with pytest.raises(jaxtyping.TypeCheckError):  # M loops: Z [M, 8] and loop_cov [M, 7, 7] must agree
        pcm.pairwise_consistency(S, np.zeros((3, 7, 7), np.float32), np.array([[0, 2]]), S[:1], np.zeros((2, 7, 7)))
    g = circle_graph(6, noise=(0.01, 0.01, 0.01), seed=0)
    prob = posegraph.Problem(g.initial, g.edges, g.measurements, information=g.information)
    with pytest.raises(jaxtyping.TypeCheckError):
        posegraph.residuals(np.asarray(g.initial)[:, :7], prob)  # poses are [N, 8]
    n, e = prob.num_nodes, prob.num_edges
    with pytest.raises(jaxtyping.TypeCheckError):  # diag [n, b, b] and grad [n, b]: one n
        linear.NormalEquations(jnp.zeros((n, 7, 7)), jnp.zeros((e, 7, 7)), jnp.zeros((n + 1, 7)), prob.edges)
    with pytest.raises(jaxtyping.TypeCheckError):
        posegraph.chain_poses(np.zeros((3, 7)))


def test_host_boundary_checkers_raise_their_own_value_error():
    from swiftjax import loops
    from swiftjax.chunks import chunk_schedule
    from swiftjax.loops import pcm

    g = circle_graph(6, noise=(0.01, 0.01, 0.01), seed=0)
    with pytest.raises(posegraph.ProblemError, match=r"poses has shape \(6, 7\); expected \[N, 8\]"):
        posegraph.Problem(np.asarray(g.initial)[:, :7], g.edges, g.measurements)
    with pytest.raises(ValueError, match="GraphOptions.kernel: invalid value 'tukey'"):
        posegraph.GraphOptions(kernel="tukey")
    with pytest.raises(ValueError, match="kernel must be None or one of"):
        posegraph.check_kernel(3)
    with pytest.raises(ValueError, match="GraphOptions.linear_solver: invalid value 'lu'"):
        posegraph.GraphOptions(linear_solver="lu")
    with pytest.raises(ValueError, match="LoopOptions.rule: invalid value 'auto'"):
        loops.LoopOptions(rule="auto")
    with pytest.raises(ValueError, match=r"detect_loops: Z must be \[N, d'\]"):
        loops.detect_loops(np.zeros(5, np.float32))
    with pytest.raises(ValueError, match=r"find_loops: descriptors must be \[N, d\]"):
        loops.find_loops(np.zeros(5, np.float32), chunk_schedule(5))
    with pytest.raises(ValueError, match="consistent must be square"):
        pcm.max_consistent_set(np.ones((2, 3), bool))

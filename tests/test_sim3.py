"""Sim(3) and SO(3): group axioms, closed forms vs independent references, special cases.

References: ``scipy.linalg.expm`` of the 4x4 Lie-algebra matrix (float64), jaxlie's ``SE3``
(for sigma = 0), scipy's ``Rotation`` (quaternion <-> matrix), and plain matrix algebra.
"""

from __future__ import annotations

import subprocess
import sys

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import HealthCheck, given, settings
from scipy.spatial.transform import Rotation

from swiftjax import sim3, so3

SETTINGS = settings(
    deadline=None,
    max_examples=30,
    derandomize=True,
    # The x64 fixture is meant to span all generated examples.
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
BATCH = 6  # one static batch size keeps the number of compiles small

# Rotation-angle and log-scale regimes: exact zero, tiny, small, moderate, near pi.
ANGLES = st.sampled_from([0.0, 1e-9, 1e-6, 1e-3, 0.3, 1.5, 3.0, np.pi - 1e-3])
SIGMAS = st.sampled_from([0.0, 1e-9, 1e-5, 1e-2, -0.5, 2.0, -6.9, 6.9])


def _tangents(seed: int, angle: float, sigma: float, n: int = BATCH) -> np.ndarray:
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    rho = rng.uniform(-50, 50, size=(n, 3))
    sig = np.full((n, 1), sigma) * rng.choice([-1.0, 1.0], size=(n, 1))
    return np.concatenate([rho, angle * axis, sig], axis=-1)


def _random_elements(seed: int, n: int = BATCH) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = Rotation.random(n, random_state=rng).as_quat()
    t = rng.uniform(-100, 100, size=(n, 3))
    s = np.exp(rng.uniform(-3, 3, size=(n, 1)))
    return np.concatenate([t, q, s], axis=-1)


def _algebra(xi: np.ndarray) -> np.ndarray:
    """The 4x4 Lie-algebra matrix [[sigma I + [omega]x, rho], [0, 0]]."""
    rho, omega, sigma = xi[:3], xi[3:6], xi[6]
    m = np.zeros((4, 4))
    m[:3, :3] = sigma * np.eye(3) + np.array(
        [[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]]
    )
    m[:3, 3] = rho
    return m


def _tol(dtype) -> float:
    return 2e-5 if dtype == jnp.float32 else 1e-10


def _rel(a, b, magnitude: float = 1.0) -> float:
    """Max abs difference relative to the size of the result (or of the operands)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b)) / max(1.0, magnitude, np.max(np.abs(b))))


# ------------------------------------------------------------------ independent references


@SETTINGS
@given(seed=st.integers(0, 2**31), angle=ANGLES, sigma=SIGMAS)
def test_exp_matches_matrix_exponential_float64(x64, seed, angle, sigma):
    xi = _tangents(seed, angle, sigma)
    got = np.asarray(sim3.as_matrix(sim3.exp(jnp.asarray(xi))))
    for k in range(BATCH):
        want = scipy.linalg.expm(_algebra(xi[k]))
        np.testing.assert_allclose(got[k], want, rtol=1e-10, atol=1e-10 * np.abs(want).max())


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_exp_matches_matrix_exponential_float32_and_64(dtype):
    with jax.enable_x64(dtype == jnp.float64):
        for seed, (angle, sigma) in enumerate(
            [(0.0, 0.0), (1e-5, 0.0), (0.0, 1e-4), (1e-3, 1e-3), (0.7, -0.4), (3.1, 4.0)]
        ):
            xi = _tangents(seed, angle, sigma)
            got = np.asarray(sim3.as_matrix(sim3.exp(jnp.asarray(xi, dtype))))
            want = np.stack([scipy.linalg.expm(_algebra(x)) for x in xi])
            assert _rel(got, want) < 10 * _tol(dtype), (angle, sigma)


def test_exp_with_zero_scale_matches_jaxlie_se3(x64):
    jaxlie = pytest.importorskip("jaxlie")
    # Not 1e-7: there jaxlie's own small-angle branch for V is off by ~1.5e-6 relative
    # (checked against scipy's expm, which agrees with ours to 1e-14).
    for seed, angle in enumerate([0.0, 1e-3, 0.5, 2.0, 3.1]):
        xi = _tangents(seed, angle, 0.0)
        ours = np.asarray(sim3.as_matrix(sim3.exp(jnp.asarray(xi))))
        # jaxlie's SE3 tangent is (translation part, rotation part), like ours minus sigma.
        theirs = np.stack([np.asarray(jaxlie.SE3.exp(jnp.asarray(x[:6])).as_matrix()) for x in xi])
        np.testing.assert_allclose(ours, theirs, atol=1e-11 * np.abs(theirs).max())


def test_quaternion_matrix_conversions_match_scipy(x64):
    rng = np.random.default_rng(3)
    rot = Rotation.random(200, random_state=rng)
    # Include rotations by (almost) pi about random and coordinate axes: Shepperd's hard cases.
    axes = np.concatenate([rng.normal(size=(5, 3)), np.eye(3)])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    hard = Rotation.from_rotvec(np.concatenate([np.pi * axes, (np.pi - 1e-7) * axes]))
    rot = Rotation.concatenate([rot, hard])
    q = rot.as_quat()
    np.testing.assert_allclose(so3.as_matrix(jnp.asarray(q)), rot.as_matrix(), atol=1e-14)
    q_back = np.asarray(so3.from_matrix(jnp.asarray(rot.as_matrix())))
    # Same rotation up to the quaternion sign.
    dots = np.abs(np.sum(q_back * q, axis=-1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-12)


# ------------------------------------------------------------------------- group axioms


@SETTINGS
@given(seed=st.integers(0, 2**31), dtype=st.sampled_from([jnp.float32, jnp.float64]))
def test_group_axioms(seed, dtype):
    with jax.enable_x64(dtype == jnp.float64):
        a, b, c = (jnp.asarray(_random_elements(seed + k), dtype) for k in range(3))
        mat = sim3.as_matrix
        tol = _tol(dtype)
        assert _rel(mat(sim3.compose(sim3.compose(a, b), c)), mat(sim3.compose(a, sim3.compose(b, c)))) < tol
        ident = sim3.identity((BATCH,), dtype)
        assert _rel(mat(sim3.compose(a, ident)), mat(a)) < tol
        assert _rel(mat(sim3.compose(ident, a)), mat(a)) < tol
        # a o a^-1 = I: rounding scales with |a| |a^-1|, not with |I|.
        size = float(np.max(np.abs(mat(a))) * np.max(np.abs(mat(sim3.inverse(a)))))
        assert _rel(mat(sim3.compose(a, sim3.inverse(a))), np.broadcast_to(np.eye(4), (BATCH, 4, 4)), size) < tol
        assert _rel(mat(sim3.compose(a, b)), mat(a) @ mat(b)) < tol
        assert _rel(mat(sim3.inverse(a)), np.linalg.inv(np.asarray(mat(a), np.float64))) < tol
        assert _rel(mat(sim3.between(a, b)), np.linalg.inv(np.asarray(mat(a), np.float64)) @ mat(b)) < tol


@SETTINGS
@given(seed=st.integers(0, 2**31), dtype=st.sampled_from([jnp.float32, jnp.float64]))
def test_act_matches_homogeneous_matrix(seed, dtype):
    with jax.enable_x64(dtype == jnp.float64):
        s = jnp.asarray(_random_elements(seed), dtype)
        pts = jnp.asarray(np.random.default_rng(seed).uniform(-100, 100, (BATCH, 17, 3)), dtype)
        got = sim3.act(s[:, None, :], pts)
        m = np.asarray(sim3.as_matrix(s), np.float64)
        want = np.einsum("bij,bnj->bni", m[:, :3, :3], np.asarray(pts, np.float64)) + m[:, None, :3, 3]
        assert _rel(got, want) < _tol(dtype)


@SETTINGS
@given(seed=st.integers(0, 2**31), dtype=st.sampled_from([jnp.float32, jnp.float64]))
def test_from_matrix_inverts_as_matrix(seed, dtype):
    with jax.enable_x64(dtype == jnp.float64):
        s = jnp.asarray(_random_elements(seed), dtype)
        back = sim3.from_matrix(sim3.as_matrix(s))
        assert _rel(sim3.as_matrix(back), sim3.as_matrix(s)) < _tol(dtype)
        r, t, sc = sim3.to_rst(s)
        assert _rel(sim3.as_matrix(sim3.from_rst(r, t, sc)), sim3.as_matrix(s)) < _tol(dtype)


@SETTINGS
@given(seed=st.integers(0, 2**31), angle=ANGLES, sigma=SIGMAS)
def test_adjoint_identity(x64, seed, angle, sigma):
    s = jnp.asarray(_random_elements(seed))
    xi = jnp.asarray(_tangents(seed + 1, angle, sigma) * 0.1)
    lhs = sim3.compose(sim3.compose(s, sim3.exp(xi)), sim3.inverse(s))
    rhs = sim3.exp(jnp.einsum("bij,bj->bi", sim3.adjoint(s), xi))
    assert _rel(sim3.as_matrix(lhs), sim3.as_matrix(rhs)) < 1e-9


# ---------------------------------------------------------------------- exp / log round trips


@SETTINGS
@given(
    seed=st.integers(0, 2**31),
    angle=ANGLES,
    sigma=SIGMAS,
    dtype=st.sampled_from([jnp.float32, jnp.float64]),
)
def test_log_exp_round_trip(seed, angle, sigma, dtype):
    with jax.enable_x64(dtype == jnp.float64):
        xi = jnp.asarray(_tangents(seed, angle, sigma), dtype)
        back = sim3.log(sim3.exp(xi))
        # rho's error scales with |W^-1| ~ e^|sigma|; compare relative to the element size.
        scale = 1.0 + np.exp(abs(sigma))
        np.testing.assert_allclose(back, xi, rtol=0, atol=_tol(dtype) * 50 * scale)


@SETTINGS
@given(seed=st.integers(0, 2**31), dtype=st.sampled_from([jnp.float32, jnp.float64]))
def test_exp_log_round_trip(seed, dtype):
    with jax.enable_x64(dtype == jnp.float64):
        s = jnp.asarray(_random_elements(seed), dtype)
        assert _rel(sim3.as_matrix(sim3.exp(sim3.log(s))), sim3.as_matrix(s)) < 5 * _tol(dtype)


# ------------------------------------------------------------------------ special cases


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize(
    "name,angle,sigma",
    [
        ("theta=0", 0.0, 0.7),
        ("sigma=0", 0.9, 0.0),
        ("both=0", 0.0, 0.0),
        ("both tiny", 1e-8, 1e-8),
        ("theta tiny, sigma large", 1e-6, 5.0),
        ("scale 1e-3", 0.4, np.log(1e-3)),
        ("scale 1e3", 0.4, np.log(1e3)),
    ],
)
def test_named_special_cases(dtype, name, angle, sigma):
    with jax.enable_x64(dtype == jnp.float64):
        xi = np.array([3.0, -2.0, 1.0, angle, 0.0, 0.0, sigma])
        got = np.asarray(sim3.as_matrix(sim3.exp(jnp.asarray(xi, dtype))), np.float64)
        want = scipy.linalg.expm(_algebra(xi))
        assert _rel(got, want) < 10 * _tol(dtype), name
        back = np.asarray(sim3.log(sim3.exp(jnp.asarray(xi, dtype))))
        np.testing.assert_allclose(back, xi, atol=100 * _tol(dtype), err_msg=name)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("angle", [np.pi - 1e-6, np.pi])
def test_log_near_and_at_pi(dtype, angle):
    with jax.enable_x64(dtype == jnp.float64):
        axis = np.array([1.0, 2.0, -2.0]) / 3.0
        rot = Rotation.from_rotvec(angle * axis)
        s = sim3.from_rst(jnp.asarray(rot.as_matrix(), dtype), jnp.asarray([1.0, 2.0, 3.0], dtype), 2.0)
        xi = np.asarray(sim3.log(s), np.float64)
        assert np.all(np.isfinite(xi))
        omega = xi[3:6]
        np.testing.assert_allclose(np.linalg.norm(omega), angle, atol=5e-6 if dtype == jnp.float32 else 1e-9)
        # At exactly pi both +axis and -axis are valid; otherwise it must be +axis.
        cos = abs(omega @ axis) / np.linalg.norm(omega) if angle == np.pi else omega @ axis / np.linalg.norm(omega)
        np.testing.assert_allclose(cos, 1.0, atol=1e-5)
        assert _rel(sim3.as_matrix(sim3.exp(jnp.asarray(xi, dtype))), sim3.as_matrix(s)) < 20 * _tol(dtype)


def test_log_is_invariant_to_quaternion_sign(x64):
    s = _random_elements(11, n=50)
    neg = s.copy()
    neg[:, 3:7] *= -1
    np.testing.assert_allclose(sim3.log(jnp.asarray(s)), sim3.log(jnp.asarray(neg)), atol=1e-12)


def test_so3_exp_log_small_angles_are_exact(x64):
    for theta in [0.0, 1e-12, 1e-8, 1e-4, 1e-2]:
        w = np.array([theta, -0.5 * theta, 0.25 * theta])
        q = so3.exp(jnp.asarray(w))
        np.testing.assert_allclose(q, Rotation.from_rotvec(w).as_quat(), atol=1e-15)
        np.testing.assert_allclose(so3.log(q), w, atol=1e-15)


# --------------------------------------------------------------------- jit / vmap / grad


def test_jit_vmap_log_equals_python_loop():
    s = jnp.asarray(_random_elements(5, n=32), jnp.float32)
    batched = jax.jit(jax.vmap(sim3.log))(s)
    looped = np.stack([np.asarray(sim3.log(s[i])) for i in range(32)])
    np.testing.assert_allclose(batched, looped, rtol=0, atol=1e-6 * np.abs(looped).max())


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_gradients_are_finite_at_identity(dtype):
    with jax.enable_x64(dtype == jnp.float64):
        zero = jnp.zeros(7, dtype)
        pts = jnp.ones((4, 3), dtype)

        def round_trip(xi):
            return jnp.sum(sim3.log(sim3.exp(xi)) ** 2) + jnp.sum(sim3.log(sim3.exp(xi)))

        def chain(xi):
            s = sim3.exp(xi)
            return jnp.sum(sim3.act(sim3.compose(s, sim3.inverse(s)), pts)) + jnp.sum(sim3.log(s))

        for f in (round_trip, chain):
            g = jax.jit(jax.grad(f))(zero)
            assert np.all(np.isfinite(g)), f.__name__
        # d/dxi of sum(log(exp(xi))) at 0 is exactly ones (log o exp = id).
        grad_sum = jax.jit(jax.grad(lambda x: jnp.sum(sim3.log(sim3.exp(x)))))
        np.testing.assert_allclose(grad_sum(zero), 1.0, atol=1e-6)
        # theta = 0 exactly but sigma != 0, and the quaternion log at the identity element.
        xi = jnp.asarray([1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 0.3], dtype)
        assert np.all(np.isfinite(jax.jit(jax.jacfwd(sim3.exp))(xi)))
        assert np.all(np.isfinite(jax.jit(jax.jacrev(sim3.log))(sim3.identity((), dtype))))


def test_right_jacobian_inverse_matches_finite_differences(x64):
    xi = jnp.asarray([0.3, -0.2, 0.5, 0.4, -0.3, 0.2, 0.1])
    jr_inv = jax.jit(sim3.right_jacobian_inverse)
    jinv = np.asarray(jr_inv(xi))
    eps = 1e-6
    perturbed = jax.jit(jax.vmap(lambda d: sim3.log(sim3.compose(sim3.exp(xi), sim3.exp(d)))))
    steps = eps * np.eye(7)
    central = (perturbed(jnp.asarray(steps)) - perturbed(jnp.asarray(-steps))) / (2 * eps)
    np.testing.assert_allclose(np.asarray(central).T, jinv, atol=1e-8)
    # At the identity Jr^-1 = I.
    np.testing.assert_allclose(jr_inv(jnp.zeros(7)), np.eye(7), atol=1e-14)


def test_broadcasting_of_batch_axes():
    a = jnp.asarray(_random_elements(1, n=4), jnp.float32)[:, None, :]  # [4, 1, 8]
    b = jnp.asarray(_random_elements(2, n=3), jnp.float32)[None, :, :]  # [1, 3, 8]
    c = jax.jit(sim3.compose)(a, b)
    assert c.shape == (4, 3, 8)
    np.testing.assert_allclose(
        sim3.as_matrix(c[2, 1]), sim3.as_matrix(a[2, 0]) @ sim3.as_matrix(b[0, 1]), rtol=1e-5, atol=1e-3
    )


def test_import_swiftjax_does_not_import_torch():
    code = "import sys, swiftjax, swiftjax.sim3; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_jitted_log_exp_with_tiny_log_scale_is_finite(dtype):
    # Regression: under jit XLA may fold log(exp(sigma)) to sigma while s - 1 rounds to 0.
    with jax.enable_x64(dtype == jnp.float64):
        for sigma in (1e-10, 1e-9, 3e-8, 6e-8):
            xi = jnp.asarray([3.0, -1.0, 2.0, 0.0, 0.0, 0.0, sigma], dtype)
            back = jax.jit(lambda x: sim3.log(sim3.exp(x)))(xi)
            np.testing.assert_allclose(back, xi, rtol=0, atol=50 * _tol(dtype))
            assert np.all(np.isfinite(jax.jit(sim3.right_jacobian_inverse)(xi)))


def _jr_inv_mpmath(xi: np.ndarray, dps: int = 40) -> np.ndarray:
    """``Jr^-1(xi)`` in ``dps``-digit arithmetic from the Baker-Campbell-Hausdorff formula,
    ``log(e^X e^D) = X + G(-ad_X) D + O(D^2)`` with ``G(z) = z / (e^z - 1) = 1 / F(z)``,
    ``F(z) = sum_n z^n / (n + 1)!``: a matrix function of the 7 x 7 adjoint of the algebra
    (``[[sigma I + [omega]x, [rho]x, -rho], [0, [omega]x, 0], [0, 0, 0]]``), independent of
    ``sim3.jlog``'s closed form and its branches."""
    import mpmath as mp

    with mp.workdps(dps):
        r = [mp.mpf(float(v)) for v in xi]
        rho, w, s = r[:3], r[3:6], r[6]
        hat = lambda v: [[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]
        ad = mp.zeros(7, 7)
        for i in range(3):
            for j in range(3):
                ad[i, j] = hat(w)[i][j] + (s if i == j else 0)
                ad[i, 3 + j] = hat(rho)[i][j]
                ad[3 + i, 3 + j] = hat(w)[i][j]
            ad[i, 6] = -rho[i]
        term, total, n = mp.eye(7), mp.eye(7), 1
        while mp.mnorm(term, 1) > mp.mpf(10) ** -dps:
            term = term * -ad / (n + 1)
            total += term
            n += 1
        return np.array((total**-1).tolist(), dtype=np.float64)


# (|omega|, |sigma|) -> (float64, float32) bound on max |jlog - reference| / max |reference|.
# The branch each exercises is named in sim3._winv_partials; "small theta, large sigma" is its
# stated limit (eps / theta).
JLOG_REGIMES = {
    "generic": ((0.9, 0.3), (1e-14, 2e-6)),
    "near pi": ((2.9, 0.7), (1e-14, 2e-6)),
    "large scale change": ((1.2, 4.0), (1e-14, 2e-6)),
    "sigma = 0": ((0.5, 0.0), (1e-14, 2e-6)),
    "tiny sigma": ((0.5, 1e-9), (1e-14, 2e-6)),
    "sigma just past the float64 series": ((0.1, 0.02), (1e-13, 2e-6)),
    "theta = 0": ((0.0, 0.8), (1e-14, 2e-6)),
    "theta below the small-angle threshold": ((1e-8, 0.8), (1e-14, 2e-6)),
    "small theta, large sigma (float64 limit)": ((1e-5, 0.8), (1e-10, 2e-6)),
    "small theta, large sigma (float32 limit)": ((1e-3, 0.8), (1e-12, 5e-4)),
    "|w| -> 0": ((1e-6, 1e-6), (1e-14, 2e-6)),
    "identity": ((0.0, 0.0), (1e-14, 2e-6)),
    "|w| inside the float64 series": ((0.07, 0.07), (1e-14, 2e-6)),
    "|w| outside the float64 series": ((0.08, 0.07), (1e-13, 2e-6)),
    "|w| inside the float32 series": ((0.5, 0.49), (1e-14, 2e-6)),
    "|w| outside the float32 series": ((0.5, 0.51), (1e-14, 5e-6)),
}


@pytest.mark.parametrize("regime", list(JLOG_REGIMES))
def test_jlog_matches_40_digit_reference(x64, regime):
    """``sim3.jlog`` in float64 and float32, with and without ``S``, against :func:`_jr_inv_mpmath`."""
    (angle, sigma), (tol64, tol32) = JLOG_REGIMES[regime]
    rng = np.random.default_rng(7)
    axis = rng.normal(size=(4, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    xi = np.concatenate(
        [rng.normal(size=(4, 3)) * 3, angle * axis, sigma * np.array([[1.0], [-1.0], [1.0], [-1.0]])], -1
    )
    ref = np.stack([_jr_inv_mpmath(x) for x in xi])
    scale = np.abs(ref).max()
    for dtype, tol in ((np.float64, tol64), (np.float32, tol32)):
        x = jnp.asarray(xi, dtype)
        for got in (sim3.jlog(x), sim3.jlog(x, sim3.exp(x))):  # jlog is jitted itself
            err = np.abs(np.asarray(got, np.float64) - ref).max() / scale
            assert err <= tol, f"{regime}, {np.dtype(dtype).name}: relative error {err:.2e} > {tol:.0e}"


def test_jlog_closed_form_matches_forward_mode(x64):
    xi = _tangents(5, 1.2, 0.3, n=8)
    ref = np.asarray(jax.jit(sim3.right_jacobian_inverse)(xi))
    np.testing.assert_allclose(np.asarray(jax.jit(sim3.jlog)(xi)), ref, atol=1e-9)
    np.testing.assert_allclose(np.asarray(jax.jit(sim3.jlog)(xi, sim3.exp(xi))), ref, atol=1e-9)
    np.testing.assert_allclose(np.asarray(jax.jit(so3.jlog)(xi[:, 3:6])), ref[:, 3:6, 3:6], atol=1e-9)


def test_blocked_layout_of_large_batches_matches_small_batches():
    """From 2 * sim3._BLOCK elements on, exp runs on blocked components (padded to a multiple
    of the block): same formulas, so the same values as small batches to float32 rounding."""
    n = 3 * sim3._BLOCK + 17
    xi = _tangents(9, 1.0, 0.3, n=n).astype(np.float32)
    xi[:, :3] /= 50.0
    big = np.asarray(jax.jit(sim3.exp)(xi.reshape(1, n, 7)))[0]
    small = np.concatenate([np.asarray(sim3.exp(xi[k : k + 1000])) for k in range(0, n, 1000)])
    assert big.shape == (n, 8)
    np.testing.assert_allclose(big, small, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(sim3.log(big)), xi, rtol=1e-4, atol=1e-4)


def test_mapped_layout_of_large_batches_matches_small_batches():
    """From 2 * sim3._MAP_BLOCK elements on, log runs block by block (lax.map, padded)."""
    n = 2 * sim3._MAP_BLOCK + 17
    S = _random_elements(4, n=n).astype(np.float32)
    big = np.asarray(jax.jit(sim3.log)(S))
    small = np.concatenate([np.asarray(sim3.log(S[k : k + 4000])) for k in range(0, n, 4000)])
    with jax.enable_x64(True):
        ref = np.asarray(sim3.log(S.astype(np.float64)))
    # Same formulas, another fusion: rounding differs (amplified near pi with |t| ~ 100), so
    # both are held to the float64 reference rather than to each other.
    err_big, err_small = np.abs(big - ref).max(), np.abs(small - ref).max()
    assert err_big <= 2 * err_small + 1e-6, (err_big, err_small)
    bad = S.copy()
    bad[5, 7] = -1.0
    assert np.all(np.isnan(np.asarray(jax.jit(sim3.log)(bad))[5]))

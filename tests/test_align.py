"""swiftjax.align: weighted Umeyama, reliability mask, IRLS baseline, chunk-pair alignment."""

from __future__ import annotations

import numpy as np
import jax
import jax.numpy as jnp
import pytest
from scipy.spatial.transform import Rotation

from swiftjax import align, sim3

umeyama_jit = jax.jit(align.umeyama)


def _random_sim3(rng, seed):
    R = Rotation.random(random_state=seed).as_matrix()
    s = float(np.exp(rng.uniform(np.log(0.1), np.log(10.0))))
    t = rng.uniform(-100, 100, size=3)
    return R, t, s


def _errors(S, R, t, s):
    """(rotation angle error, relative scale error, relative translation error)."""
    Rg, tg, sg = (np.asarray(a, np.float64) for a in sim3.to_rst(S))
    rot = np.linalg.norm(Rotation.from_matrix(R.T @ Rg).as_rotvec())
    return rot, abs(sg / s - 1), np.linalg.norm(tg - t) / max(np.linalg.norm(t), 1.0)


def np_weighted_umeyama(x, y, w):
    """Float64 reference written from the paper's equations (weighted Umeyama, reflection fix)."""
    x, y, w = (np.asarray(a, np.float64) for a in (x, y, w))
    W = w.sum()
    mx, my = (w @ x) / W, (w @ y) / W
    xc, yc = x - mx, y - my
    C = (yc * w[:, None]).T @ xc / W
    sx2 = (w * (xc**2).sum(1)).sum() / W
    U, D, Vt = np.linalg.svd(C)
    E = np.diag([1, 1, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    R = U @ E @ Vt
    s = np.trace(np.diag(D) @ E) / sx2
    t = my - s * R @ mx
    return R, t, s


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_umeyama_recovers_sim3_float64(x64, seed):
    rng = np.random.default_rng(seed)
    R, t, s = _random_sim3(rng, seed)
    x = rng.normal(size=(5000, 3)) * 10 + rng.uniform(-100, 100, 3)
    y = s * x @ R.T + t
    w = np.ones(5000)
    out = rng.random(5000) < 0.3  # gross outliers, removed by the weights
    y[out] += rng.normal(size=(out.sum(), 3)) * 50
    w[out] = 0
    S, info = umeyama_jit(jnp.asarray(x), jnp.asarray(y), jnp.asarray(w))
    assert S.dtype == jnp.float64
    rot, se, te = _errors(S, R, t, s)
    assert rot < 1e-10 and se < 1e-10 and te < 1e-10
    assert bool(info.valid) and int(info.num_points) == 5000 - out.sum()
    assert float(info.weight_sum) == pytest.approx(5000 - out.sum())
    assert float(info.rms) < 1e-5


@pytest.mark.parametrize("seed", [3, 4])
def test_umeyama_recovers_sim3_float32(seed):
    rng = np.random.default_rng(seed)
    R, t, s = _random_sim3(rng, seed)
    x = rng.normal(size=(20000, 3)) * 10 + rng.uniform(-100, 100, 3)
    y = s * x @ R.T + t
    w = (rng.random(20000) > 0.3).astype(np.float32)
    y[w == 0] += 1e3  # outliers
    S, info = umeyama_jit(jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32), jnp.asarray(w))
    assert S.dtype == jnp.float32 and bool(info.valid)
    rot, se, te = _errors(S, R, t, s)
    assert rot < 1e-5 and se < 1e-4 and te < 1e-4


def test_umeyama_matches_evo_unweighted(x64):
    from evo.core.geometry import umeyama_alignment

    rng = np.random.default_rng(7)
    x = rng.normal(size=(500, 3)) * 3 + 20
    R, t, s = _random_sim3(rng, 7)
    y = s * x @ R.T + t + rng.normal(size=(500, 3)) * 0.5  # noisy: solutions differ from truth
    r_e, t_e, s_e = umeyama_alignment(x.T, y.T, with_scale=True)
    S, info = umeyama_jit(jnp.asarray(x), jnp.asarray(y))
    Rg, tg, sg = (np.asarray(a) for a in sim3.to_rst(S))
    np.testing.assert_allclose(Rg, r_e, atol=1e-8)
    np.testing.assert_allclose(tg, t_e, atol=1e-8 * max(1, np.abs(t_e).max()))
    assert float(sg) == pytest.approx(s_e, rel=1e-8)
    resid = y - (s_e * x @ r_e.T + t_e)
    assert float(info.rms) == pytest.approx(np.sqrt((resid**2).sum(1).mean()), rel=1e-6)


def test_umeyama_weighted_matches_numpy_reference(x64):
    rng = np.random.default_rng(8)
    x = rng.normal(size=(3000, 3)) * 5 + 50
    R, t, s = _random_sim3(rng, 8)
    y = s * x @ R.T + t + rng.normal(size=(3000, 3)) * 2.0
    w = rng.random(3000) * (rng.random(3000) > 0.2)
    R_r, t_r, s_r = np_weighted_umeyama(x, y, w)
    S, info = umeyama_jit(jnp.asarray(x), jnp.asarray(y), jnp.asarray(w))
    Rg, tg, sg = (np.asarray(a) for a in sim3.to_rst(S))
    np.testing.assert_allclose(Rg, R_r, atol=1e-10)
    np.testing.assert_allclose(tg, t_r, atol=1e-9 * max(1, np.abs(t_r).max()))
    assert float(sg) == pytest.approx(s_r, rel=1e-10)
    res = ((y - (s_r * x @ R_r.T + t_r)) ** 2).sum(1)
    assert float(info.rms) == pytest.approx(np.sqrt((w * res).sum() / w.sum()), rel=1e-8)


def test_umeyama_reflection_fix(x64):
    # Mirrored, planar-ish data: the best orthogonal map is a reflection; we must return a rotation.
    rng = np.random.default_rng(9)
    x = rng.normal(size=(400, 3)) * np.array([10.0, 5.0, 0.01])
    y = x * np.array([1.0, 1.0, -1.0])
    S, info = umeyama_jit(jnp.asarray(x), jnp.asarray(y))
    R = np.asarray(sim3.to_rst(S)[0])
    assert np.linalg.det(R) == pytest.approx(1.0)
    R_r, t_r, s_r = np_weighted_umeyama(x, y, np.ones(400))
    np.testing.assert_allclose(R, R_r, atol=1e-9)
    assert bool(info.valid)


def test_umeyama_float32_large_cloud_accuracy_vs_float64():
    """2.4 M float32 points at ~100 m: rotation within 1e-5 rad, scale within 1e-5 (centred, blocked sums)."""
    rng = np.random.default_rng(10)
    n = 2_400_000
    R, t, s = _random_sim3(rng, 10)
    x = (rng.normal(size=(n, 3)) * np.array([20.0, 3.0, 15.0]) + np.array([100.0, -20.0, 80.0]))
    y = s * x @ R.T + t
    S, info = umeyama_jit(jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32))
    rot, se, te = _errors(S, R, t, s)
    assert rot < 1e-5 and se < 1e-5 and te < 1e-4
    assert int(info.num_points) == n


def test_umeyama_batched_matches_individual():
    rng = np.random.default_rng(11)
    xs, ys = [], []
    for k in range(4):
        R, t, s = _random_sim3(rng, 20 + k)
        x = rng.normal(size=(1000, 3)) * 4
        xs.append(x)
        ys.append(s * x @ R.T + t)
    X, Y = jnp.asarray(np.stack(xs), jnp.float32), jnp.asarray(np.stack(ys), jnp.float32)
    Sb, info = umeyama_jit(X, Y)
    assert Sb.shape == (4, 8) and info.valid.shape == (4,)
    for k in range(4):
        Sk, _ = umeyama_jit(X[k], Y[k])
        np.testing.assert_allclose(np.asarray(Sb[k]), np.asarray(Sk), atol=1e-5)


@pytest.mark.parametrize(
    "case", ["zero_weights", "identical", "collinear", "nan_points", "two_points"]
)
def test_umeyama_degenerate_inputs_are_invalid_and_finite(case):
    rng = np.random.default_rng(12)
    x = rng.normal(size=(200, 3)).astype(np.float32)
    y = 2 * x + 1
    w = np.ones(200, np.float32)
    if case == "zero_weights":
        w[:] = 0
    elif case == "identical":
        x[:] = [10.0, 20.0, 30.0]
        y[:] = [1.0, 2.0, 3.0]
    elif case == "collinear":
        x = np.outer(np.linspace(-5, 5, 200), [1.0, 2.0, 3.0]).astype(np.float32) + 7
        y = 2 * x + 1
    elif case == "nan_points":
        x[:, 0] = np.nan
    elif case == "two_points":
        w[2:] = 0
    S, info = umeyama_jit(jnp.asarray(x), jnp.asarray(y), jnp.asarray(w))
    assert not bool(info.valid)
    np.testing.assert_array_equal(np.asarray(S), np.asarray(sim3.identity()))
    assert np.all(np.isfinite(np.asarray(info.rms)))


def test_umeyama_ignores_nonfinite_points_with_zero_or_any_weight():
    rng = np.random.default_rng(13)
    x = rng.normal(size=(500, 3)).astype(np.float32) * 3
    y = 0.5 * x - 2
    x[::7, 1] = np.nan
    y[::11, 2] = np.inf
    S, info = umeyama_jit(jnp.asarray(x), jnp.asarray(y))
    assert bool(info.valid) and np.all(np.isfinite(np.asarray(S)))
    bad = np.isnan(x).any(1) | np.isinf(y).any(1)
    assert int(info.num_points) == (~bad).sum()
    np.testing.assert_allclose(np.asarray(sim3.scale(S)), 0.5, rtol=1e-5)


def test_umeyama_rejects_bad_shapes():
    with pytest.raises(ValueError, match="src"):
        align.umeyama(jnp.ones((10, 2)), jnp.ones((10, 2)))
    with pytest.raises(ValueError, match="weights"):
        align.umeyama(jnp.ones((10, 3)), jnp.ones((10, 3)), jnp.ones(9))

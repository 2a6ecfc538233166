"""Edge information from alignment statistics (:mod:`swiftjax.align.covariance`): the closed-form
Hessian against autodiff, the covariance against a Monte Carlo of the Umeyama estimate and of the
loop-edge composition, the AlignInfo moments against explicit points, degenerate inputs."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_align import make_pair

from swiftjax import align, camera, sim3
from swiftjax.align import covariance as ac


def _random_S(rng, rot=0.5, trans=2.0, log_s=0.3):
    xi = np.concatenate([rng.normal(size=3) * trans, rng.normal(size=3) * rot, [rng.normal() * log_s]])
    return np.asarray(sim3.exp(jnp.asarray(xi)))


def _points(rng, n, anisotropy=(3.0, 1.0, 0.5), offset=(1.0, -2.0, 5.0)):
    return rng.normal(size=(n, 3)) * np.asarray(anisotropy) + np.asarray(offset)


@jax.jit
def _half_hessian(Z, x, y, w):
    """``1/2 d^2/d delta^2 sum w |y - Z exp(delta) x|^2`` at ``delta = 0`` (autodiff, float64)."""

    def f(d):
        return jnp.sum(w[:, None] * (y - sim3.act(sim3.compose(Z, sim3.exp(d)), x)) ** 2)

    return 0.5 * jax.hessian(f)(jnp.zeros(7, Z.dtype))


def _whitened_gap(emp, pred):
    """``max |P^-1/2 emp P^-1/2 - I|``: 0 when the empirical covariance equals the predicted one."""
    ev, V = np.linalg.eigh(pred)
    isq = V @ np.diag(ev**-0.5) @ V.T
    return np.abs(isq @ emp @ isq - np.eye(len(pred))).max()


@settings(deadline=None, max_examples=8, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 10_000))
def test_hessian_matches_autodiff_of_the_point_cost(x64, seed):
    """``Omega sigma^2 = H`` with H = 1/2 d^2/d delta^2 sum w |y - Z exp(delta) x|^2 (autodiff)."""
    rng = np.random.default_rng(seed)
    x = _points(rng, 40)
    w = rng.uniform(0.2, 2.0, 40)
    Z = _random_S(rng)
    y = np.asarray(sim3.act(jnp.asarray(Z), jnp.asarray(x))) + 0.05 * rng.normal(size=(40, 3))
    H = np.asarray(_half_hessian(Z, x, y, w))
    rms = 0.37  # any value: Omega scales as (3n - 7) / rms^2
    out = ac.umeyama_information_from_points(x, w, Z, 40, rms)
    assert bool(out.valid)
    sigma2 = w.sum() * rms**2 / (3 * 40 - 7)
    # The linearisation drops second-order terms of the residual (curvature of exp), which are
    # O(|e|) relative: compare at the tolerance of the 0.05 noise.
    np.testing.assert_allclose(np.asarray(out.information) * sigma2, H, rtol=0, atol=0.03 * np.abs(H).max())


def test_exact_gauss_newton_hessian(x64):
    """Noise-free data: the Gauss-Newton Hessian is the exact Hessian, to rounding."""
    rng = np.random.default_rng(3)
    x = _points(rng, 25)
    Z = _random_S(rng)
    y = np.asarray(sim3.act(jnp.asarray(Z), jnp.asarray(x)))
    H = np.asarray(_half_hessian(Z, x, y, np.ones(25)))
    out = ac.umeyama_information_from_points(x, None, Z, 25, 1.0, rms_floor=0.0)
    # Omega = H / sigma^2 with sigma^2 = W rms^2 / (3 n - 7), W = n = 25, rms = 1
    np.testing.assert_allclose(
        np.asarray(out.information) * 25 / (3 * 25 - 7), H, rtol=1e-10, atol=1e-10 * np.abs(H).max()
    )


@pytest.fixture(scope="module")
def monte_carlo():
    """4,000 Umeyama solves of one point set with iid N(0, 0.02^2) noise on the destination."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(7)
        n, draws, noise = 200, 4000, 0.02
        x = _points(rng, n)
        Z = _random_S(rng)
        y0 = np.asarray(sim3.act(jnp.asarray(Z), jnp.asarray(x)))
        y = y0[None] + noise * rng.normal(size=(draws, n, 3))
        S, info = align.umeyama(jnp.broadcast_to(jnp.asarray(x), y.shape), jnp.asarray(y))
        delta = np.asarray(sim3.log(sim3.compose(sim3.inverse(S), jnp.asarray(Z))))  # Z = S exp(delta)
        omega = ac.umeyama_information_from_points(
            jnp.broadcast_to(jnp.asarray(x), y.shape), None, S, info.num_points, info.rms
        )
        return delta, np.asarray(omega.information), np.asarray(omega.valid), np.asarray(info.rms), noise


def test_covariance_matches_monte_carlo_of_umeyama(monte_carlo):
    delta, omega, valid, rms, noise = monte_carlo
    assert valid.all()
    emp = np.cov(delta.T)
    pred = np.linalg.inv(omega.mean(0))
    # 4,000 draws: sampling error of a whitened covariance entry ~ 1/sqrt(4000) = 0.016
    assert _whitened_gap(emp, pred) < 0.08
    assert np.abs(delta.mean(0)).max() < 4 * np.sqrt(np.diag(pred)).max() / np.sqrt(len(delta))
    # chi-squared: E[delta^T Omega delta] = 7
    chi2 = np.einsum("ki,kij,kj->k", delta, omega, delta)
    assert chi2.mean() == pytest.approx(7.0, rel=0.05)
    # the unbiased noise estimate behind Omega
    assert np.mean(rms**2 * 200 / (3 * 200 - 7)) == pytest.approx(noise**2, rel=0.02)


def test_effective_sample_size_scales_information(x64):
    rng = np.random.default_rng(1)
    x = _points(rng, 50)
    Z = _random_S(rng)
    a = ac.umeyama_information_from_points(x, None, Z, 50, 0.1)
    b = ac.umeyama_information_from_points(x, None, Z, 50, 0.1, pixels_per_sample=196.0)
    np.testing.assert_allclose(np.asarray(b.information) * 196.0, np.asarray(a.information), rtol=1e-12)
    # the rms floor: a noise-free fit still has finite information, set by the spread
    c = ac.umeyama_information_from_points(x, None, Z, 50, 0.0, rms_floor=1e-3)
    spread = np.sqrt(np.trace(np.cov(x.T, bias=True)))
    d = ac.umeyama_information_from_points(x, None, Z, 50, 1e-3 * spread)
    assert bool(c.valid)
    np.testing.assert_allclose(np.asarray(c.information), np.asarray(d.information), rtol=1e-12)


def test_loop_edge_information_matches_monte_carlo(x64):
    """``Z = S_j S_i^-1`` with independently perturbed halves ``S_x exp(d_x)``, d_x ~ N(0, Omega_x^-1)."""
    rng = np.random.default_rng(5)
    S_i, S_j = _random_S(rng), _random_S(rng)

    def spd(scale):
        a = rng.normal(size=(7, 7))
        return scale * (a @ a.T + 7 * np.eye(7))

    om_i, om_j = spd(1e5), spd(3e4)
    info = lambda om: ac.EdgeInformation(jnp.asarray(om), jnp.asarray(True))
    out = ac.loop_edge_information(S_i, info(om_i), S_j, info(om_j))
    assert bool(out.valid)
    k = 20_000
    d_i = rng.multivariate_normal(np.zeros(7), np.linalg.inv(om_i), size=k)
    d_j = rng.multivariate_normal(np.zeros(7), np.linalg.inv(om_j), size=k)
    Si = sim3.compose(jnp.asarray(S_i), sim3.exp(jnp.asarray(d_i)))
    Sj = sim3.compose(jnp.asarray(S_j), sim3.exp(jnp.asarray(d_j)))
    Z = np.asarray(sim3.compose(jnp.asarray(S_j), sim3.inverse(jnp.asarray(S_i))))
    Z_true = sim3.compose(Sj, sim3.inverse(Si))
    dz = np.asarray(sim3.log(sim3.compose(sim3.inverse(jnp.asarray(Z)), Z_true)))
    assert _whitened_gap(np.cov(dz.T), np.linalg.inv(np.asarray(out.information))) < 0.05
    # An invalid half makes the loop edge invalid (and zero), never a made-up number.
    bad = ac.loop_edge_information(S_i, info(om_i), S_j, ac.EdgeInformation(jnp.zeros((7, 7)), jnp.asarray(False)))
    assert not bool(bad.valid) and float(jnp.abs(bad.information).max()) == 0.0


def test_align_info_moments_equal_explicit_points(x64):
    """AlignInfo.src_mean / src_covariance (from pixel moments) equal the masked chunk t+1 points'."""
    prev, cur, K_ref, _ = make_pair(seed=11, o=5, h=20, w=33)
    rng = np.random.default_rng(1)
    cur = cur._replace(depth=cur.depth * (1 + 0.01 * rng.normal(size=cur.depth.shape)))
    S, info = align.align_chunk_pair(
        prev, cur, K_ref, options=align.AlignOptions(min_points=100, overlap_scale="median")
    )
    assert float(info.scale_ratio) != 1.0  # the moments are mapped back to chunk t+1's units
    dp = camera.normalize_depth(prev.depth, prev.intrinsic, K_ref)
    dc = camera.normalize_depth(cur.depth, cur.intrinsic, K_ref)
    m = np.asarray(
        align.reliability_mask(dp, dc, prev.conf, cur.conf, 0.2, 0.5, scale_ratio=float(info.scale_ratio))
    ).reshape(-1)  # eq. 2 after the rescale
    Xc = np.asarray(camera.unproject(dc, K_ref, camera.camera_to_world(cur.extrinsic))).reshape(-1, 3)[m]
    np.testing.assert_allclose(np.asarray(info.src_mean), Xc.mean(0), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(info.src_covariance), np.cov(Xc.T, bias=True), rtol=1e-9, atol=1e-12)
    out = ac.alignment_information(S, info)
    ref = ac.umeyama_information_from_points(Xc, None, S, int(info.num_points), float(info.rms))
    assert bool(out.valid)
    np.testing.assert_allclose(np.asarray(out.information), np.asarray(ref.information), rtol=1e-8)


def test_degenerate_inputs_are_invalid(x64):
    rng = np.random.default_rng(2)
    Z = _random_S(rng)
    line = np.outer(np.linspace(-1, 1, 30), [1.0, 2.0, 0.5]) + 3.0  # collinear: rotation about it free
    assert not bool(ac.umeyama_information_from_points(line, None, Z, 30, 0.1).valid)
    two = _points(rng, 2)
    assert not bool(ac.umeyama_information_from_points(two, None, Z, 2, 0.1).valid)
    nan = _points(rng, 20)
    out = ac.umeyama_information(1.0, 20, 0.1, jnp.full(3, jnp.nan), jnp.eye(3))
    assert not bool(out.valid) and np.all(np.asarray(out.information) == 0)
    # An alignment that fell back to the camera poses has no point statistics to speak of.
    prev, cur, K_ref, _ = make_pair(seed=3, o=2, h=8, w=8)
    cur = cur._replace(depth=np.full_like(cur.depth, np.nan))
    S, info = align.align_chunk_pair(prev, cur, K_ref, options=align.AlignOptions(min_points=10))
    assert bool(info.pose_fallback)
    assert not bool(ac.alignment_information(S, info).valid)
    del nan

"""swiftjax.align: weighted Umeyama, reliability mask, IRLS baseline, chunk-pair alignment."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
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
    x = rng.normal(size=(n, 3)) * np.array([20.0, 3.0, 15.0]) + np.array([100.0, -20.0, 80.0])
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


@pytest.mark.parametrize("case", ["zero_weights", "identical", "collinear", "nan_points", "two_points"])
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
    import jaxtyping

    # the tests' jaxtyping hook (tests/conftest.py) refuses them by their annotation first ...
    with pytest.raises(jaxtyping.TypeCheckError, match="src"):
        align.umeyama(jnp.ones((10, 2)), jnp.ones((10, 2)))
    # ... and without it (as a user runs it) umeyama's own check names the input
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        with pytest.raises(ValueError, match="src"):
            align.umeyama(jnp.ones((11, 2)), jnp.ones((11, 2)))
        with pytest.raises(ValueError, match="weights"):
            align.umeyama(jnp.ones((11, 3)), jnp.ones((11, 3)), jnp.ones(9))
    finally:
        jaxtyping.config.update("jaxtyping_disable", False)


# ------------------------------------------------------------------ mask and chunk pairs

from swiftjax import camera


def test_reliability_mask_hand_computed():
    da = np.array([[[1.0, 2.0], [3.0, 4.0]]], np.float32)
    db = np.array([[[1.1, 2.5], [3.0, np.nan]]], np.float32)
    ca = np.array([[[2.0, 2.0], [0.5, 3.5]]], np.float32)  # mean 2.0 -> threshold 1.0
    cb = np.array([[[1.0, 4.0], [4.0, np.inf]]], np.float32)  # finite mean 3.0 -> threshold 1.5
    m = np.asarray(align.reliability_mask(da, db, ca, cb, 0.2, 0.5))
    # (0,0): |dd|=0.1 ok, ca 2>1 ok, cb 1>1.5 no -> False
    # (0,1): |dd|=0.5 no; (1,0): ca 0.5 > 1 no; (1,1): NaN depth / inf conf -> False
    np.testing.assert_array_equal(m, [[[False, False], [False, False]]])
    cb2 = cb.copy()
    cb2[0, 0, 0] = 2.0  # finite mean (2+4+4)/3 = 3.333 -> threshold 1.667: 2 > 1.667
    m2 = np.asarray(align.reliability_mask(da, db, ca, cb2, 0.2, 0.5))
    np.testing.assert_array_equal(m2, [[[True, False], [False, False]]])
    np.testing.assert_allclose(np.asarray(align.frame_conf_mean(cb2)), [10.0 / 3.0], rtol=1e-6)
    m3 = np.asarray(align.reliability_mask(da, db, ca, cb2, 0.6, 0.5))
    np.testing.assert_array_equal(m3, [[[True, True], [False, False]]])  # (0,1): cb 4 ok, ca 2 ok, |dd| .5 < .6
    m3 = np.asarray(align.reliability_mask(da, db, ca, cb2, 0.6, 0.0))
    np.testing.assert_array_equal(m3, [[[True, True], [True, False]]])


def _K(fx, fy, w, h):
    return np.array([[fx, 0, w / 2 - 0.5], [0, fy, h / 2 - 0.5], [0, 0, 1.0]])


def make_pair(seed=0, o=4, h=24, w=40, s=1.02, outliers=0.3, dtype=np.float64):
    """Synthetic overlap: chunk t+1 is chunk t mapped by S_true^-1 (depths / s, new focals)."""
    rng = np.random.default_rng(seed)
    K_ref = _K(50.0, 52.0, w, h)
    R_S = Rotation.from_rotvec(rng.normal(size=3) * 0.3).as_matrix()
    t_S = rng.normal(size=3) * 3
    # chunk t cameras (world-to-camera), gently moving forward
    Kp = np.stack([_K(50.0 * (1 + 0.05 * rng.normal()), 52.0 * (1 + 0.05 * rng.normal()), w, h) for _ in range(o)])
    Kc = np.stack([_K(50.0 * (1 + 0.05 * rng.normal()), 52.0 * (1 + 0.05 * rng.normal()), w, h) for _ in range(o)])
    Ep, Ec = [], []
    for f in range(o):
        Rp_c2w = Rotation.from_rotvec(rng.normal(size=3) * 0.05).as_matrix()
        cp = np.array([0.1 * f, 0.0, 0.8 * f]) + rng.normal(size=3) * 0.05
        Ep.append(np.concatenate([Rp_c2w.T, (-Rp_c2w.T @ cp)[:, None]], 1))
        # chunk t+1 pose of the same camera: Q = S^-1 P  (rotation R_S^T R_p, centre S^-1 c)
        Rq = R_S.T @ Rp_c2w
        cq = R_S.T @ (cp - t_S) / s
        Ec.append(np.concatenate([Rq.T, (-Rq.T @ cq)[:, None]], 1))
    Ep, Ec = np.stack(Ep), np.stack(Ec)
    yy, xx = np.mgrid[0:h, 0:w]
    Dreg = 3.0 + 1.5 * np.sin(xx / 7.0 + np.arange(o)[:, None, None]) + 0.02 * yy  # normalised depth
    rp = 0.5 * (K_ref[0, 0] / Kp[:, 0, 0] + K_ref[1, 1] / Kp[:, 1, 1])
    rc = 0.5 * (K_ref[0, 0] / Kc[:, 0, 0] + K_ref[1, 1] / Kc[:, 1, 1])
    Dp = Dreg / rp[:, None, None]
    Dc = (Dreg / s) / rc[:, None, None]
    conf_p = 1 + rng.random((o, h, w)) * 3
    conf_c = 1 + rng.random((o, h, w)) * 3
    bad = rng.random((o, h, w)) < outliers
    Dc = np.where(bad, Dc + rng.uniform(1.0, 5.0, (o, h, w)), Dc)  # gross depth outliers
    prev = align.ChunkFrames(*(a.astype(dtype) for a in (Dp, conf_p, Kp, Ep)))
    cur = align.ChunkFrames(*(a.astype(dtype) for a in (Dc, conf_c, Kc, Ec)))
    return prev, cur, K_ref.astype(dtype), (R_S, t_S, s)


def np_scale_ratio(dp, dc, cp, cc, conf_ratio=0.5):
    """NumPy loops: ``exp median log(dp / dc)`` over pixels finite, positive and confident in
    both (confidence > ratio x the frame's mean over its finite pixels); 1 if none or outside [1/100, 100]."""
    logs = []
    for f in range(dp.shape[0]):
        ma = np.mean(cp[f][np.isfinite(cp[f])])
        mb = np.mean(cc[f][np.isfinite(cc[f])])
        for y in range(dp.shape[1]):
            for x in range(dp.shape[2]):
                a, b, ca, cb = float(dp[f, y, x]), float(dc[f, y, x]), float(cp[f, y, x]), float(cc[f, y, x])
                if (
                    all(np.isfinite([a, b, ca, cb]))
                    and a > 0
                    and b > 0
                    and ca > conf_ratio * ma
                    and cb > conf_ratio * mb
                ):
                    logs.append(np.log(a) - np.log(b))
    if not logs:
        return 1.0
    rho = float(np.exp(np.median(logs)))
    return rho if 1 / 100 <= rho <= 100 else 1.0


def _core_subsample(o, h, w):
    """The strided subsample ``_align_core`` estimates ``rho`` on (chunk_pair.py)."""
    fs, hs, ws = max(1, o // 8), max(1, h // 8), max(1, w // 16)
    return slice(None, None, fs), slice(None, None, hs), slice(None, None, ws)


def _reference_pair(prev, cur, K_ref, lam=0.2, conf_ratio=0.5, scale=False):
    """The long way, with the public building blocks (float64 NumPy at the end).

    ``scale``: chunk t+1's depths first put on chunk t's scale by :func:`np_scale_ratio` of the
    alignment's strided subsample (``overlap_scale="median"``); False: the authors' eq. 2 (what
    the default ``"auto"`` does when enough points pass)."""
    dp = camera.normalize_depth(prev.depth, prev.intrinsic, K_ref)
    dc = camera.normalize_depth(cur.depth, cur.intrinsic, K_ref)
    sub = _core_subsample(*np.shape(dp))
    rho = np_scale_ratio(*(np.asarray(a)[sub] for a in (dp, dc, prev.conf, cur.conf)), conf_ratio) if scale else 1.0
    m = np.asarray(align.reliability_mask(dp, dc, prev.conf, cur.conf, lam, conf_ratio, scale_ratio=rho))
    Xp = np.asarray(camera.unproject(dp, K_ref, camera.camera_to_world(prev.extrinsic))).reshape(-1, 3)
    Xc = np.asarray(camera.unproject(dc, K_ref, camera.camera_to_world(cur.extrinsic))).reshape(-1, 3)
    mm = m.reshape(-1)
    return np_weighted_umeyama(Xc[mm], Xp[mm], np.ones(mm.sum())), mm.sum()


def test_overlap_scale_ratio_matches_numpy_loops(x64):
    """``overlap_scale_ratio`` against NumPy loops on frames with NaN/inf, non-positive depths,
    gross outliers (30 %) and unconfident pixels; odd and even counts; and masked_median."""
    rng = np.random.default_rng(3)
    for o, h, w in ((3, 7, 9), (2, 4, 6), (1, 5, 5)):
        da = rng.uniform(0.5, 5.0, (o, h, w))
        db = da / 2.7 * (1 + 0.01 * rng.normal(size=da.shape))
        db = np.where(rng.random(da.shape) < 0.3, rng.uniform(0.1, 9.0, da.shape), db)
        ca, cb = rng.uniform(0.5, 3.0, da.shape), rng.uniform(0.5, 3.0, da.shape)
        da[0, 0, :3] = np.nan, -1.0, 0.0
        db[0, 1, :2] = np.inf, -2.0
        ca[0, 2, 0] = np.nan
        rho, n = align.overlap_scale_ratio(da, db, ca, cb, 0.5)
        assert float(rho) == pytest.approx(np_scale_ratio(da, db, ca, cb, 0.5), rel=1e-12)
        if da.size > 100:  # enough inliers for the median to sit on them
            assert abs(float(rho) - 2.7) < 0.1
        keep = rng.random(da.shape) < 0.5
        vals = rng.normal(size=da.shape)
        med, cnt = align.masked_median(vals, keep)
        assert int(cnt) == keep.sum() and float(med) == pytest.approx(np.median(vals[keep]), rel=1e-12)
    assert np.isnan(float(align.masked_median(np.ones(4), np.zeros(4, bool))[0]))
    # nothing confident, or a ratio beyond [1/100, 100]: rho = 1 (eq. 2 as the authors wrote it)
    one = np.ones((1, 3, 3))
    assert float(align.overlap_scale_ratio(one, np.full_like(one, np.nan), one, one)[0]) == 1.0
    assert float(align.overlap_scale_ratio(one * 500, one, one, one)[0]) == 1.0
    assert float(align.overlap_scale_ratio(one * 50, one, one, one)[0]) == pytest.approx(50)


def test_reliability_mask_scale_ratio_matches_numpy(x64):
    """Eq. 2 after the rescale, ``|D_a - rho D_b| < lambda_D`` in chunk a's units, against loops."""
    rng = np.random.default_rng(4)
    da = rng.uniform(1, 4, (2, 5, 6))
    db = da / 3.5 + rng.normal(size=da.shape) * 0.05
    ca, cb = rng.uniform(0.5, 3, da.shape), rng.uniform(0.5, 3, da.shape)
    rho = float(align.overlap_scale_ratio(da, db, ca, cb, 0.5)[0])
    m = np.asarray(align.reliability_mask(da, db, ca, cb, 0.2, 0.5, scale_ratio=rho))
    ref = np.zeros_like(m)
    for f in range(2):
        for y in range(5):
            for x in range(6):
                ref[f, y, x] = (
                    abs(da[f, y, x] - rho * db[f, y, x]) < 0.2
                    and ca[f, y, x] > 0.5 * ca[f].mean()
                    and cb[f, y, x] > 0.5 * cb[f].mean()
                )
    np.testing.assert_array_equal(m, ref)
    assert ref.sum() > 0.25 * ref.size  # about every confident pixel (noise 0.05 x 3.5 < 0.2)
    assert not np.asarray(align.reliability_mask(da, db, ca, cb, 0.2, 0.5)).any()  # as written: none


def test_align_chunk_pair_recovers_sim3_float64(x64):
    prev, cur, K_ref, (R, t, s) = make_pair(seed=1)
    S, info = align.align_chunk_pair(prev, cur, K_ref, options=align.AlignOptions(min_points=100))
    assert S.dtype == jnp.float64
    rot, se, te = _errors(S, R, t, s)
    assert rot < 1e-9 and se < 1e-9 and te < 1e-9
    assert bool(info.valid) and not bool(info.pose_fallback) and not bool(info.used_fallback_threshold)
    (R_r, t_r, s_r), n_ref = _reference_pair(prev, cur, K_ref)
    assert int(info.num_points) == n_ref
    assert float(info.fraction_used) == pytest.approx(n_ref / prev.depth.size)
    assert 0.5 < float(info.fraction_used) < 0.65  # 0.7 inliers x (11/12)^2 confident = 0.58
    assert float(info.rms) < 1e-6


def test_pixel_moment_path_equals_point_path_float64(x64):
    """The per-frame pixel-moment path gives the explicit-point Umeyama solution (float64).

    Noisy depths (the fit has a residual, so this compares solutions, not truth), a skewed
    ``K_ref`` with an off-centre principal point, and per-frame focal ratios.
    """
    prev, cur, K_ref, _ = make_pair(seed=11, o=5, h=20, w=33)
    rng = np.random.default_rng(1)
    prev = prev._replace(depth=prev.depth * (1 + 0.01 * rng.normal(size=prev.depth.shape)))
    cur = cur._replace(depth=cur.depth * (1 + 0.01 * rng.normal(size=cur.depth.shape)))
    K_ref = K_ref.copy()
    K_ref[0, 1], K_ref[0, 2], K_ref[1, 2] = 0.7, 9.0, 13.0
    S, info = align.align_chunk_pair(
        prev, cur, K_ref, options=align.AlignOptions(min_points=100, overlap_scale="median")
    )
    (R_r, t_r, s_r), n_ref = _reference_pair(prev, cur, K_ref, scale=True)
    Rg, tg, sg = (np.asarray(a) for a in sim3.to_rst(S))
    np.testing.assert_allclose(Rg, R_r, atol=1e-11)
    np.testing.assert_allclose(tg, t_r, atol=1e-10 * max(1, np.abs(t_r).max()))
    assert float(sg) == pytest.approx(s_r, rel=1e-11)
    assert int(info.num_points) == n_ref
    # rms from the closed form vs the explicit residuals
    dp = camera.normalize_depth(prev.depth, prev.intrinsic, K_ref)
    dc = camera.normalize_depth(cur.depth, cur.intrinsic, K_ref)
    rho = float(info.scale_ratio)
    assert rho == pytest.approx(
        np_scale_ratio(*(np.asarray(a)[_core_subsample(*dp.shape)] for a in (dp, dc, prev.conf, cur.conf))), rel=1e-12
    )
    m = np.asarray(align.reliability_mask(dp, dc, prev.conf, cur.conf, 0.2, 0.5, scale_ratio=rho)).reshape(-1)
    Xp = np.asarray(camera.unproject(dp, K_ref, camera.camera_to_world(prev.extrinsic))).reshape(-1, 3)[m]
    Xc = np.asarray(camera.unproject(dc, K_ref, camera.camera_to_world(cur.extrinsic))).reshape(-1, 3)[m]
    res = np.sqrt(((Xp - (s_r * Xc @ R_r.T + t_r)) ** 2).sum(1).mean())
    assert res > 1e-3 and float(info.rms) == pytest.approx(res, rel=1e-7)


def test_align_chunk_pair_float32_far_from_origin_large_overlap():
    """Float32, ~0.5 M pixel pairs, cameras ~100 units from the chunk origin, depth noise:
    rotation within 1e-5 rad and scale within 1e-5 of the float64 solution on the same mask."""
    prev, cur, K_ref, _ = make_pair(seed=12, o=6, h=154, w=518)
    shift = np.array([120.0, -30.0, 90.0])  # move chunk t's world: camera centres c -> c + shift
    Ep = prev.extrinsic.copy()
    Ep[:, :, 3] -= np.einsum("fij,j->fi", Ep[:, :, :3], shift)
    prev = prev._replace(extrinsic=Ep)
    rng = np.random.default_rng(2)
    prev = prev._replace(depth=prev.depth * (1 + 0.003 * rng.normal(size=prev.depth.shape)))
    (R_r, t_r, s_r), n_ref = _reference_pair(prev, cur, K_ref)  # float64
    f32 = lambda fr: align.ChunkFrames(*(np.asarray(a, np.float32) for a in fr))
    S, info = align.align_chunk_pair(
        f32(prev), f32(cur), K_ref.astype(np.float32), options=align.AlignOptions(min_points=100)
    )
    assert S.dtype == jnp.float32 and bool(info.valid)
    assert abs(int(info.num_points) - n_ref) <= 1e-4 * n_ref  # float32 vs float64 mask ties
    rot, se, te = _errors(S, R_r, t_r, s_r)
    assert rot < 1e-5 and se < 1e-5 and te < 1e-5


def test_align_chunk_pair_float32_close_to_float64():
    prev, cur, K_ref, (R, t, s) = make_pair(seed=2, dtype=np.float32)
    S, info = align.align_chunk_pair(prev, cur, K_ref, options=align.AlignOptions(min_points=100))
    assert S.dtype == jnp.float32 and bool(info.valid)
    rot, se, te = _errors(S, R, t, s)
    assert rot < 1e-5 and se < 1e-4 and te < 1e-4


def test_align_chunk_pair_fallback_threshold_and_batch():
    prev, cur, K_ref, _ = make_pair(seed=3, s=1.0, dtype=np.float32)
    # Shift cur's depth by 0.22 (scale-free): nothing passes at 0.2, all inliers at 0.25
    # (the authors' eq. 2: a ratio would absorb part of the shift).
    authors = align.AlignOptions(overlap_scale="none")
    cur = cur._replace(
        depth=cur.depth
        + 0.22 / (0.5 * (K_ref[0, 0] / cur.intrinsic[:, 0, 0] + K_ref[1, 1] / cur.intrinsic[:, 1, 1]))[:, None, None]
    )
    S, info = align.align_chunk_pair(prev, cur, K_ref, options=authors.replace(min_points=100))
    assert bool(info.used_fallback_threshold) and float(info.depth_threshold) == pytest.approx(0.25)
    assert bool(info.valid) and int(info.num_points) > 100 and float(info.scale_ratio) == 1.0
    S2, info2 = align.align_chunk_pair(prev, cur, K_ref, options=authors.replace(min_points=0))
    assert not bool(info2.used_fallback_threshold) and not bool(info2.valid)  # 0 points at 0.2
    # Batched form = individual calls (the default options: rho per pair).
    p2, c2, _, _ = make_pair(seed=4, dtype=np.float32)
    pb = align.ChunkFrames(*(np.stack([a, b]) for a, b in zip(prev, p2)))
    cb = align.ChunkFrames(*(np.stack([a, b]) for a, b in zip(cur, c2)))
    Sb, ib = align.align_chunk_pairs(pb, cb, K_ref, options=authors.replace(min_points=100))
    S1, _ = align.align_chunk_pair(p2, c2, K_ref, options=authors.replace(min_points=100))
    Sd, idf = align.align_chunk_pairs(pb, cb, K_ref, options=align.AlignOptions(min_points=100))
    for k, (p, c) in enumerate(((prev, cur), (p2, c2))):
        Sk, ik = align.align_chunk_pair(p, c, K_ref, options=align.AlignOptions(min_points=100))
        np.testing.assert_allclose(np.asarray(Sd[k]), np.asarray(Sk), atol=1e-5)
        assert float(idf.scale_ratio[k]) == pytest.approx(float(ik.scale_ratio), rel=1e-6)
    # "auto" with enough points at lambda_D: the authors' numbers bit for bit, rho = 1
    Sa, ia = align.align_chunk_pair(p2, c2, K_ref, options=align.AlignOptions(min_points=100))
    np.testing.assert_array_equal(np.asarray(Sa), np.asarray(S1))
    assert float(ia.scale_ratio) == 1.0 and int(ia.num_points) > 100
    # float32: the batched reductions round differently (~eps x |t| ~ 1e-6 here).
    np.testing.assert_allclose(np.asarray(Sb[0]), np.asarray(S), atol=1e-5)
    np.testing.assert_allclose(np.asarray(Sb[1]), np.asarray(S1), atol=1e-5)
    assert ib.num_points.shape == (2,) and bool(ib.used_fallback_threshold[0])


def test_align_chunk_pair_nan_pixels_never_reach_S(x64):
    prev, cur, K_ref, (R, t, s) = make_pair(seed=5)
    rng = np.random.default_rng(0)
    dp, cc = prev.depth.copy(), cur.conf.copy()
    dp[rng.random(dp.shape) < 0.05] = np.nan
    dp[rng.random(dp.shape) < 0.05] = np.inf
    cc[rng.random(cc.shape) < 0.05] = np.nan
    S, info = align.align_chunk_pair(
        prev._replace(depth=dp), cur._replace(conf=cc), K_ref, options=align.AlignOptions(min_points=100)
    )
    assert np.all(np.isfinite(np.asarray(S))) and bool(info.valid)
    rot, se, te = _errors(S, R, t, s)
    assert rot < 1e-9 and se < 1e-9 and te < 1e-9
    # A frame with a non-finite camera is dropped as a whole (its pixels are not counted).
    ep = prev.extrinsic.copy()
    ep[1, 0, 3] = np.nan
    S2, info2 = align.align_chunk_pair(
        prev._replace(extrinsic=ep), cur, K_ref, options=align.AlignOptions(min_points=100)
    )
    _, n_ref = _reference_pair(prev, cur, K_ref)
    n_frame1 = _reference_pair(*(f._replace(**{k: getattr(f, k)[1:2] for k in f._fields}) for f in (prev, cur)), K_ref)[
        1
    ]
    assert bool(info2.valid) and int(info2.num_points) == n_ref - n_frame1
    rot, se, te = _errors(S2, R, t, s)
    assert rot < 1e-9 and se < 1e-9 and te < 1e-9


def test_align_chunk_pair_checked_empty_overlap_warns_and_falls_back(x64, logged_warning):
    prev, cur, K_ref, (R, t, s) = make_pair(seed=6, outliers=0.0)
    cur_bad = cur._replace(depth=cur.depth + 10.0)  # no pixel passes either threshold (eq. 2 as written)
    with logged_warning("ill-posed"):
        S, info = align.align_chunk_pair_checked(prev, cur_bad, K_ref, options=align.AlignOptions(overlap_scale="none"))
    assert not bool(info.valid) and bool(info.pose_fallback) and int(info.num_points) == 0
    assert np.all(np.isfinite(np.asarray(S)))
    # The pose-based fallback recovers the rotation exactly and the rest approximately.
    rot, se, te = _errors(S, R, t, s)
    assert rot < 1e-9 and se < 1e-6 and te < 1e-6
    # All-NaN depths: still finite.
    S2, info2 = align.align_chunk_pair(prev, cur._replace(depth=np.full_like(cur.depth, np.nan)), K_ref)
    assert np.all(np.isfinite(np.asarray(S2))) and not bool(info2.valid)


def test_align_chunk_pair_checked_rejects_bad_inputs():
    prev, cur, K_ref, _ = make_pair(seed=7, o=2, h=4, w=6, dtype=np.float32)
    with pytest.raises(ValueError, match="cur.depth has shape"):
        align.align_chunk_pair_checked(prev, cur._replace(depth=cur.depth[:1]), K_ref)
    with pytest.raises(ValueError, match="prev.extrinsic"):
        align.align_chunk_pair_checked(prev._replace(extrinsic=prev.extrinsic[:, :3, :3]), cur, K_ref)
    K_bad = cur.intrinsic.copy()
    K_bad[0, 0, 0] = -1
    with pytest.raises(ValueError, match="focal"):
        align.align_chunk_pair_checked(prev, cur._replace(intrinsic=K_bad), K_ref)
    K_nan = K_ref.copy()
    K_nan[0, 2] = np.nan
    with pytest.raises(ValueError, match="K_ref"):
        align.align_chunk_pair_checked(prev, cur, K_nan)


def test_align_options_written_once_and_taken_everywhere():
    import dataclasses
    import inspect

    from swiftjax import options
    from swiftjax.pipeline import PipelineConfig

    opts = align.AlignOptions()
    cfg = PipelineConfig()
    for f in dataclasses.fields(align.AlignOptions):  # the pipeline's defaults are AlignOptions'
        assert getattr(cfg, f.name) == getattr(opts, f.name), f.name
    assert options.build(align.AlignOptions, cfg) == opts
    sig = inspect.signature(align.reliability_mask)
    assert sig.parameters["depth_threshold"].default == opts.depth_threshold
    assert sig.parameters["conf_ratio"].default == opts.conf_ratio
    loop = opts.for_loop()
    assert loop.depth_threshold == opts.loop_depth_threshold
    assert loop.fallback_depth_threshold == max(opts.fallback_depth_threshold, opts.loop_depth_threshold)
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.min_points = 3  # type: ignore[misc]
    # An options object built either way gives the same alignment.
    prev, cur, K_ref, _ = make_pair(seed=8, o=2, h=16, w=24, dtype=np.float32)
    S_kw, i_kw = align.align_chunk_pair(
        prev, cur, K_ref, options=align.AlignOptions(min_points=100, depth_threshold=0.3)
    )
    S_op, i_op = align.align_chunk_pair(prev, cur, K_ref, options=opts.replace(min_points=100, depth_threshold=0.3))
    np.testing.assert_array_equal(np.asarray(S_kw), np.asarray(S_op))
    assert float(i_op.depth_threshold) == pytest.approx(0.3)
    with pytest.raises(TypeError):
        align.align_chunk_pairs(prev, cur, K_ref, min_points=100)  # options only: no override keywords


def test_align_chunk_pair_checked_throw_false_reports_flags_only(logged_warning):
    prev, cur, K_ref, _ = make_pair(seed=6, o=2, h=16, w=24, outliers=0.0, dtype=np.float32)
    cur_bad = cur._replace(depth=-cur.depth)  # behind the cameras: no ratio, no pixel passes
    with logged_warning(None):  # no warning with throw=False
        S, info = align.align_chunk_pair_checked(prev, cur_bad, K_ref, throw=False)
    assert bool(info.pose_fallback) and np.all(np.isfinite(np.asarray(S)))
    K_nan = K_ref.copy()
    K_nan[0, 2] = np.nan
    _, info2 = align.align_chunk_pair_checked(prev, cur, K_nan, throw=False)  # no host check
    assert not bool(info2.valid)


# ------------------------------------------------------------------------ IRLS baseline


def np_vggt_long_irls(src, dst, w0, delta=0.1, max_iters=5, tol=1e-9):
    """NumPy float64 port of VGGT-Long's robust_weighted_estimate_sim3 (the reference)."""

    def est(x, y, w):
        w = w / w.sum()
        mx, my = w @ x, w @ y
        xc, yc = x - mx, y - my
        s = np.sqrt(np.sum(w * (yc**2).sum(1))) / np.sqrt(np.sum(w * (xc**2).sum(1)))
        H = (s * xc * np.sqrt(w)[:, None]).T @ (yc * np.sqrt(w)[:, None])
        U, _, Vt = np.linalg.svd(H)
        R = Vt.T @ U.T
        if np.linalg.det(R) < 0:
            Vt[-1, :] *= -1
            R = Vt.T @ U.T
        return s, R, my - s * R @ mx

    s, R, t = est(src, dst, w0)
    prev = np.inf
    for _ in range(max_iters):
        r = np.linalg.norm(dst - (s * src @ R.T + t), axis=1)
        h = np.where(r > delta, delta / np.maximum(r, 1e-300), 1.0)
        cw = w0 * h
        cw = cw / (cw.sum() + 1e-12)
        s2, R2, t2 = est(src, dst, cw)
        change = abs(s2 - s) + np.linalg.norm(t2 - t)
        ang = np.arccos(np.clip((np.trace(R2 @ R.T) - 1) / 2, -1, 1))
        err = np.sum(np.where(r <= delta, 0.5 * r**2, delta * (r - 0.5 * delta)) * w0)
        if (change < tol and ang < np.radians(0.1)) or abs(prev - err) < tol * prev:
            break
        s, R, t = s2, R2, t2
        prev = err
    return s, R, t


def test_irls_matches_numpy_port(x64):
    rng = np.random.default_rng(14)
    x = rng.normal(size=(2000, 3)) * 4
    R, t, s = _random_sim3(rng, 14)
    y = s * x @ R.T + t + rng.normal(size=(2000, 3)) * 0.05
    y[:300] += rng.normal(size=(300, 3)) * 5  # outliers IRLS down-weights
    w0 = rng.uniform(1, 3, 2000)
    s_r, R_r, t_r = np_vggt_long_irls(x, y, w0)
    S, info = jax.jit(align.irls_sim3)(jnp.asarray(x), jnp.asarray(y), jnp.asarray(w0))
    Rg, tg, sg = (np.asarray(a) for a in sim3.to_rst(S))
    np.testing.assert_allclose(Rg, R_r, atol=1e-9)
    np.testing.assert_allclose(tg, t_r, atol=1e-8)
    assert float(sg) == pytest.approx(s_r, rel=1e-10)
    assert 1 <= int(info.iterations) <= 5
    # Robust: much closer to the truth than a plain Umeyama on the contaminated data.
    rot_i, se_i, _ = _errors(S, R, t, s)
    S_u, _ = umeyama_jit(jnp.asarray(x), jnp.asarray(y))
    rot_u, se_u, _ = _errors(S_u, R, t, s)
    assert se_i < se_u

"""--metric: the robust road-plane fit against NumPy references, chunk heights on the oracle,
the combination over chunks and the scale applied to poses."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from swiftjax import metric_scale


def _road_scene(rng, n_road=2500, n_wall=600, n_junk=400, h=1.65, tilt=(0.04, 0.08), noise=0.01):
    """Camera-frame points: a road plane h below the camera (normal ~ up = -y), a facade
    (vertical plane) and gross outliers.  Returns points, labels (True: road), n, d."""
    n = np.array([tilt[0], -1.0, tilt[1]])
    n /= np.linalg.norm(n)
    d = -h
    xz = rng.uniform([-6, 2], [6, 30], (n_road, 2))
    y = (d - n[0] * xz[:, 0] - n[2] * xz[:, 1]) / n[1]
    road = np.stack([xz[:, 0], y, xz[:, 1]], 1) * (1 + noise * rng.normal(size=(n_road, 1)))  # depth noise
    wall = np.stack([np.full(n_wall, 5.0), rng.uniform(-3, 1.6, n_wall), rng.uniform(4, 30, n_wall)], 1)
    junk = rng.uniform([-10, -4, 1], [10, 1.6, 40], (n_junk, 3))
    pts = np.concatenate([road, wall, junk])
    lab = np.r_[np.ones(n_road, bool), np.zeros(n_wall + n_junk, bool)]
    return pts, lab, n, d


N = 6000  # every single-problem fit is padded to N points (zero weight): one compile


def _fit(x, w=None, seed=0):
    x = np.asarray(x, np.float32)
    w = np.ones(len(x), np.float32) if w is None else np.asarray(w, np.float32)
    xp = np.zeros((N, 3), np.float32)
    wp = np.zeros(N, np.float32)
    xp[: len(x)], wp[: len(x)] = x, w
    return metric_scale.fit_plane(xp, wp, jax.random.PRNGKey(seed))


def _lsq_plane(x):
    """float64 total-least-squares plane through x: (n with n_y < 0, d)."""
    mu = x.mean(0)
    _, _, vt = np.linalg.svd(x - mu)
    n = vt[-1]
    n = -n if n[1] > 0 else n
    return n, n @ mu


def _angle(a, b):
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b))


def test_fit_recovers_an_exact_plane_among_outliers():
    rng = np.random.default_rng(0)
    pts, lab, n, d = _road_scene(rng, noise=0.0)
    fit = _fit(pts)
    assert bool(fit.valid)
    np.testing.assert_allclose(np.asarray(fit.normal), n, atol=2e-5)
    assert float(fit.offset) == pytest.approx(d, rel=2e-5)
    assert float(fit.inlier_fraction) == pytest.approx(lab.mean(), abs=0.02)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noisy_fit_matches_least_squares_on_the_true_inliers(seed):
    """Reference: float64 SVD plane of the road points alone (the labels the fit never sees)."""
    rng = np.random.default_rng(seed)
    pts, lab, _, _ = _road_scene(rng)
    n_ref, d_ref = _lsq_plane(pts[lab])
    fit = _fit(pts, seed=seed)
    assert bool(fit.valid)
    assert _angle(np.asarray(fit.normal, np.float64), n_ref) < 2e-3
    assert float(fit.offset) == pytest.approx(d_ref, rel=3e-3)
    # ... and it IS the fixed point of the NumPy float64 IRLS step (Tukey at 4.685 x 1.4826
    # MAD of the residuals within 2 tau |d|, weighted PCA)
    n1, d1 = np.asarray(fit.normal, np.float64), float(fit.offset)
    res = np.abs(pts @ n1 - d1)
    band = 2 * 0.05 * abs(d1)
    inb = np.sort(res[res < band])
    c = np.clip(4.685 * 1.4826 * inb[(len(inb) - 1) // 2], 1e-3 * abs(d1), band)
    r = (pts @ n1 - d1) / c
    w = np.where(np.abs(r) < 1, (1 - r**2) ** 2, 0.0)
    mu = (w[:, None] * pts).sum(0) / w.sum()
    C = np.einsum("n,ni,nj->ij", w, pts - mu, pts - mu) / w.sum()
    n2 = np.linalg.eigh(C)[1][:, 0]
    n2 = -n2 if n2[1] > 0 else n2
    assert _angle(n2, n1) < 1e-5 and n2 @ mu == pytest.approx(d1, rel=1e-5)


def test_weights_exclude_points_and_degenerate_inputs_are_invalid():
    rng = np.random.default_rng(4)
    pts, lab, n, d = _road_scene(rng, noise=0.0)
    # a second, lower "road" the weights switch off: the fit must ignore it entirely
    fake = pts[lab] + np.array([0.0, 0.8, 0.0])
    x = np.concatenate([pts, fake]).astype(np.float32)
    w = np.r_[np.ones(len(pts)), np.zeros(len(fake))].astype(np.float32)
    fit = _fit(x, w)
    assert bool(fit.valid) and float(fit.offset) == pytest.approx(d, rel=1e-4)
    # nothing usable, or only a wall (no plane within 30 degrees of up): invalid
    assert not bool(_fit(x, np.zeros_like(w)).valid)
    assert not bool(_fit(pts[~lab][:600]).valid)
    # a plane above the camera (a ceiling) is not a road
    assert not bool(_fit(pts[lab] * np.array([1, -1, 1])).valid)


def test_batched_fit_is_per_frame():
    rng = np.random.default_rng(5)
    scenes = [_road_scene(rng, h=h, noise=0.0) for h in (1.0, 1.65, 2.5)]
    m = min(len(s[0]) for s in scenes)
    x = np.stack([s[0][:m] for s in scenes]).astype(np.float32)
    fit = metric_scale.fit_plane(x, np.ones(x.shape[:2], np.float32), jax.random.PRNGKey(7))
    assert fit.offset.shape == (3,) and bool(np.all(fit.valid))
    np.testing.assert_allclose(-np.asarray(fit.offset), [1.0, 1.65, 2.5], rtol=1e-4)


def test_chunk_height_on_the_exact_oracle_is_the_true_gauge():
    """Noise-free oracle: the camera's height in chunk units is h_true / s_true (h_true its
    height above the world's road plane, s_true the scale of the true chunk-to-world gauge)."""
    from swiftjax.synthetic import OracleNoise, VGGTOracle, WorldConfig, build_world, loop_route
    from swiftjax.synthetic.world import ground_planes

    poses = loop_route(width=60.0, length=40.0, corner_radius=10.0, laps=0.3)
    world = build_world(poses, WorldConfig(seed=2))
    K = np.array([[120.0, 0, 69.5], [0, 120.0, 27.0], [0, 0, 1]])
    oracle = VGGTOracle(
        world, poses, intrinsic=K, image_hw=(56, 140), noise=OracleNoise.off(scale_jitter=0.1), tokens=False
    )
    frames = np.arange(10, 30)
    pred = oracle.predict_chunk(frames)
    gh = metric_scale.chunk_ground_height(pred.depth, pred.conf, pred.intrinsic, K, stride=2, frame_stride=1)
    s_true = oracle.true_chunk_gauge(frames)[7]
    pl = ground_planes(world, poses[frames, :3, 3])
    h_true = np.sum(pl[:, :3] * poses[frames, :3, 3], 1) - pl[:, 3]  # ~1.65 m
    assert int(gh.num_valid) == len(frames)
    np.testing.assert_allclose(np.asarray(gh.frame_heights) * s_true, h_true, rtol=2e-4)
    assert float(gh.height) * s_true == pytest.approx(np.median(h_true), rel=2e-4)
    # a keep-mask removing the bottom half of every frame leaves no road
    keep = np.ones(pred.depth.shape, bool)
    keep[:, 28:] = False
    gh0 = metric_scale.chunk_ground_height(pred.depth, pred.conf, pred.intrinsic, K, keep, stride=2, frame_stride=1)
    assert int(gh0.num_valid) == 0 and np.isnan(float(gh0.height))


def test_combine_scales_median_ignores_bad_chunks():
    h = np.array([1.0, 1.1, np.nan, 0.9, 10.0, 1.0])  # chunk units
    s = np.array([1.0, 1.1, 1.0, 0.9, 1.0, 1.0])  # chunk-to-world scales
    m, stats = metric_scale.combine_scales(h, s, 1.65)
    votes = 1.65 / (h * s)
    assert m == pytest.approx(np.nanmedian(votes))
    assert stats["chunks_voting"] == 5 and stats["chunks"] == 6
    with pytest.raises(ValueError, match="no chunk has a valid road-plane fit"):
        metric_scale.combine_scales([np.nan, np.nan], [1.0, 1.0], 1.65)


def test_apply_scale_stretches_the_world():
    """x' = s R x + t (NumPy, scipy's quaternion convention xyzw): M_m o S acts as m S(x)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(6)
    q = Rotation.random(4, random_state=7).as_quat()
    S = np.concatenate([rng.normal(size=(4, 3)), q, rng.uniform(0.5, 2, (4, 1))], 1)
    x = rng.normal(size=(4, 3))

    def act(S, x):
        return S[:, 7:8] * Rotation.from_quat(S[:, 3:7]).apply(x) + S[:, :3]

    S2 = metric_scale.apply_scale(S, 2.5)
    np.testing.assert_allclose(act(S2, x), 2.5 * act(S, x), rtol=1e-12)
    np.testing.assert_array_equal(S2[:, 3:7], S[:, 3:7])


@pytest.mark.parametrize(
    "value, expect", [(None, None), ("gt", ("gt", None)), ("camera-height=1.65", ("camera-height", 1.65))]
)
def test_parse_metric(value, expect):
    assert metric_scale.parse_metric(value) == expect


@pytest.mark.parametrize("value", ["camera-height=0", "camera-height=-1", "camera-height=abc", "height=1.6", "metres"])
def test_parse_metric_refuses(value):
    with pytest.raises(ValueError, match="--metric"):
        metric_scale.parse_metric(value)


def test_scale_priors_gate_gross_votes_and_refuse_bad_input():
    h = np.array([1.0, 1.1, np.nan, 0.9, 3.0, 1.05])  # chunk 2 saw no road, chunk 4 a wall
    s = np.ones(6)
    p = metric_scale.scale_priors(h, s, 1.65, sigma=0.02)
    np.testing.assert_array_equal(p.used, [True, True, False, True, False, True])
    np.testing.assert_allclose(p.log_scale[p.used], np.log(1.65 / h[p.used]))
    np.testing.assert_allclose(p.weight, np.where(p.used, 1 / 0.02**2, 0.0))
    assert p.start_factor == metric_scale.combine_scales(h, s, 1.65)[0]
    assert p.stats["chunks_gated"] == 1 and p.stats["chunks_voting"] == 5
    with pytest.raises(ValueError, match="sigma must be > 0"):
        metric_scale.scale_priors(h, s, 1.65, sigma=0.0)
    with pytest.raises(ValueError, match="no chunk has a valid road-plane fit"):
        metric_scale.scale_priors(np.full(3, np.nan), np.ones(3), 1.65, sigma=0.02)

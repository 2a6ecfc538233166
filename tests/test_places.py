"""Tests for the synthetic place-token generator and the loop ground truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from swiftjax.synthetic import places

CFG = places.PlaceTokenConfig(dim=256, tokens_per_frame=8, seed=3)


def pose(x, z, yaw):
    """Camera-to-world 4x4 of a level KITTI-like camera at (x, 0, z), heading ``yaw`` about -y."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])  # optical axis R[:, 2] = (sin, 0, cos)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, (x, 0.0, z)
    return M


@pytest.fixture(scope="module")
def params():
    return places.make_place_params(CFG)


def test_tokens_deterministic_per_frame_id(params):
    rng = np.random.default_rng(0)
    poses = np.stack([pose(*rng.uniform(-50, 50, 2), rng.uniform(-3, 3)) for _ in range(12)])
    ids = np.arange(100, 112)
    a = np.asarray(places.place_tokens(params, poses, ids))
    b = np.asarray(places.place_tokens(params, poses[5:], ids[5:]))  # another "chunk"
    assert a.shape == (12, 8, 256) and a.dtype == np.float32
    np.testing.assert_array_equal(a[5:], b)  # bit-identical whichever chunk the frame is in
    # same pose, different frame id: same place signal, different noise
    c = np.asarray(places.place_tokens(params, poses[:1], ids[:1] + 1000))
    assert not np.allclose(a[0], c[0])
    signal = CFG.place_strength * np.asarray(places.place_signal(params, poses[:1]))[0]
    resid_a, resid_c = a[0] - signal, c[0] - signal
    # what is left is bias + burst + noise: its projection on u is ~ b +- b_jit
    u = np.asarray(params.bias_direction)
    assert abs(resid_a.mean(0) @ u - CFG.bias_strength) < 4 * CFG.bias_jitter
    assert not np.allclose(resid_a, resid_c)


def test_place_signal_kernel(params):
    """<phi_k(x), phi_k(y)> averages to exp(-|dp|^2 / 2 l_p^2 - |dv|^2 / 2 l_v^2)."""
    lp, lv = CFG.length_scale_m, CFG.length_scale_rad
    base = pose(10.0, 20.0, 0.3)
    cases = [
        (pose(10.0, 20.0, 0.3), 1.0),
        (pose(10.0 + lp, 20.0, 0.3), np.exp(-0.5)),
        (pose(10.0, 20.0 + 2 * lp, 0.3), np.exp(-2.0)),
        (pose(10.0, 20.0, 0.3 + lv), np.exp(-((2 * np.sin(lv / 2)) ** 2) / (2 * lv**2))),
        (pose(10.0, 20.0, 0.3 + np.pi), 0.0),  # same place, driven the other way
        (pose(500.0, -300.0, 0.3), 0.0),
    ]
    # average over many random fields (seeds) so the check is tight
    got = np.zeros(len(cases))
    seeds = range(6)
    for seed in seeds:
        p = places.make_place_params(dataclasses.replace(CFG, seed=seed))
        phi = np.asarray(places.place_signal(p, np.stack([base] + [c[0] for c in cases])))
        got += np.einsum("kd,nkd->n", phi[0], phi[1:]) / CFG.tokens_per_frame
    got /= len(seeds)
    np.testing.assert_allclose(got, [c[1] for c in cases], atol=0.03)


def test_token_statistics(params):
    """Bias along u with per-frame jitter, burst energy, noise energy as configured."""
    rng = np.random.default_rng(1)
    n = 400
    poses = np.stack([pose(*rng.uniform(-1e3, 1e3, 2), rng.uniform(-3, 3)) for _ in range(n)])
    tok = np.asarray(places.place_tokens(params, poses, np.arange(n)), np.float64)
    u = np.asarray(params.bias_direction, np.float64)
    proj = tok.mean(1) @ u
    assert abs(proj.mean() - CFG.bias_strength) < 0.2
    assert abs(proj.std() - CFG.bias_jitter) < 0.15
    resid = tok - CFG.place_strength * np.asarray(places.place_signal(params, poses))[:, :, :]
    resid -= (resid.mean(1) @ u)[:, None, None] * u
    noise = resid - resid.mean(1, keepdims=True)  # per-token part
    k = CFG.tokens_per_frame
    # E|noise - mean noise|^2 = sigma^2 (1 - 1/K)
    assert np.mean(np.sum(noise**2, -1)) == pytest.approx(CFG.noise**2 * (1 - 1 / k), rel=0.05)
    burst = resid.mean(1)  # burst + mean noise
    assert np.mean(np.sum(burst**2, -1)) == pytest.approx(CFG.burst_strength**2 + CFG.noise**2 / k, rel=0.15)
    # bursts are heavy tailed: few coordinates hold most of their energy
    top = np.sort(burst**2, axis=1)[:, -int(0.03 * CFG.dim) :].sum(1) / np.sum(burst**2, 1)
    assert np.median(top) > 0.5


def test_config_validation():
    with pytest.raises(ValueError, match="length scales"):
        places.make_place_params(places.PlaceTokenConfig(length_scale_m=0.0))
    with pytest.raises(ValueError, match="noise must be >= 0"):
        places.make_place_params(places.PlaceTokenConfig(noise=-1.0))
    with pytest.raises(ValueError, match="burst_fraction"):
        places.make_place_params(places.PlaceTokenConfig(burst_fraction=0.0))
    with pytest.raises(ValueError, match="token_diversity"):
        places.make_place_params(places.PlaceTokenConfig(token_diversity=1.5))


def _square_drive():
    """Drive a 100 m square twice (frames 0-799), then once the other way round (800-1199)."""
    lap = []
    for k in range(400):
        side, f = divmod(k, 100)
        lap.append([(f, 0, np.pi / 2), (100, f, 0.0), (100 - f, 100, -np.pi / 2), (0, 100 - f, np.pi)][side])
    back = [(x, z, yaw + np.pi) for x, z, yaw in lap[::-1]]
    return np.stack([pose(float(x), float(z), yaw) for x, z, yaw in lap + lap + back])


def test_ground_truth_loops_against_brute_force():
    poses = _square_drive()
    pairs = places.ground_truth_loops(poses, max_distance=3.0, max_angle_deg=30.0, min_separation=100)
    p, v = poses[:, :3, 3], poses[:, :3, 2]
    n = len(poses)
    i, j = np.tril_indices(n, -1)
    ok = (np.linalg.norm(p[i] - p[j], axis=1) < 3.0) & (np.sum(v[i] * v[j], 1) > np.cos(np.pi / 6)) & (i - j > 100)
    ref = np.stack([i[ok], j[ok]], 1)
    ref = ref[np.lexsort((ref[:, 1], ref[:, 0]))]
    np.testing.assert_array_equal(pairs, ref)
    assert np.all(pairs[:, 0] > pairs[:, 1])
    # the third lap passes the same places facing the other way: never a loop
    assert len(pairs) > 400 and not np.any(pairs[:, 0] >= 800)
    # laps 1 and 2 form one long loop region (corners included)
    assert len(np.unique(places.loop_regions(pairs))) == 1


def test_loop_regions_and_evaluate():
    gt = np.array([[500, 100], [510, 110], [530, 130], [900, 100], [2000, 1500]])
    reg = places.loop_regions(gt, radius=25)
    # (500,100)-(510,110)-(530,130) chain; (900,100) and (2000,1500) alone
    assert reg[0] == reg[1] == reg[2] and len(set(reg)) == 3
    det = np.array([[505, 95], [120, 530], [1200, 300], [2024, 1476]])  # 2nd given as (j, i)
    ev = places.evaluate_loops(det, gt, tolerance=25, regions=reg)
    np.testing.assert_array_equal(ev.correct, [True, True, False, True])
    assert ev.precision == 0.75 and ev.n_regions == 3 and ev.n_regions_found == 2
    assert ev.region_recall == pytest.approx(2 / 3)
    none = places.evaluate_loops(np.zeros((0, 2)), gt)
    assert none.precision == 1.0 and none.region_recall == 0.0


def test_ground_truth_rejects_bad_input():
    with pytest.raises(ValueError, match=r"\[N, 3\|4, 4\]"):
        places.ground_truth_loops(np.zeros((5, 3, 3)))
    bad = _square_drive()[:10].copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        places.ground_truth_loops(bad)


def test_ground_truth_loops_count_reverse_revisits():
    """The third lap drives the square backwards: ``direction="reverse"`` finds exactly those
    pairs (brute force), ``"any"`` is the union, and the regions are counted per direction."""
    poses = _square_drive()
    p, v = poses[:, :3, 3], poses[:, :3, 2]
    i, j = np.tril_indices(len(poses), -1)
    near = (np.linalg.norm(p[i] - p[j], axis=1) < 3.0) & (i - j > 100)
    cos = np.sum(v[i] * v[j], 1)
    c = np.cos(np.pi / 6)
    for direction, ok in (("reverse", cos < -c), ("same", cos > c), ("any", (cos > c) | (cos < -c))):
        ref = np.stack([i[near & ok], j[near & ok]], 1)
        ref = ref[np.lexsort((ref[:, 1], ref[:, 0]))]
        got = places.ground_truth_loops(poses, 3.0, 30.0, 100, direction=direction)
        np.testing.assert_array_equal(got, ref)
    rev = places.ground_truth_loops(poses, 3.0, 30.0, 100, direction="reverse")
    assert len(rev) > 300 and np.all(rev[:, 0] >= 800)  # only the backward lap
    regions = places.revisit_regions(poses, 3.0, 30.0, 100)
    np.testing.assert_array_equal(regions["reverse"][0], rev)
    assert len(np.unique(regions["same"][1])) == 1 and len(np.unique(regions["reverse"][1])) >= 1
    with pytest.raises(ValueError, match="direction"):
        places.ground_truth_loops(poses, direction="backwards")


def test_place_tokens_stay_heading_dependent():
    """A reverse revisit must not match by token: the place signal at the same spot facing the
    other way is as unrelated as a far place, while a same-direction revisit 1 m away matches."""
    import jax.numpy as jnp

    params = places.make_place_params(places.PlaceTokenConfig(seed=0))

    def pose(x, yaw):
        c, s = np.cos(yaw), np.sin(yaw)
        m = np.eye(4, dtype=np.float32)
        m[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        m[:3, 3] = [x, 0, 0]
        return m

    xs = np.linspace(0, 400, 40)
    cams = np.stack(
        [pose(x, 0.3) for x in xs]
        + [pose(x + 1.0, 0.3) for x in xs]
        + [pose(x, 0.3 + np.pi) for x in xs]
        + [pose(x + 200.0, 0.3) for x in xs]
    )
    sig = np.asarray(places.place_signal(params, jnp.asarray(cams))).reshape(4, 40, -1)
    sig = sig / np.linalg.norm(sig, axis=-1, keepdims=True)
    same = np.mean(np.sum(sig[0] * sig[1], -1))
    reverse = np.mean(np.sum(sig[0] * sig[2], -1))
    far = np.mean(np.sum(sig[0] * sig[3], -1))
    assert same > 0.8
    assert reverse < far + 0.1 and reverse < 0.5 * same

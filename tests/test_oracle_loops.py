"""The oracle that fails like VGGT: co-visibility, hallucinated loop chunks, perceptual aliasing."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_synthetic import HW, exact, route, world  # noqa: F401  (shared fixtures)

from swiftjax import camera, sim3
from swiftjax.synthetic import Hallucination, OracleNoise, VGGTOracle, places
from swiftjax.synthetic.covisibility import covisibility, covisibility_mutual
from swiftjax.synthetic.se3_np import se3_power, so3_exp


def loop_frames(i, j, h=10):
    return np.concatenate([np.arange(i - h, i + h), np.arange(j - h, j + h)])


# ------------------------------------------------------------------------- co-visibility


def ref_covisibility(depth_a, T_a, depth_b, T_b, K, stride, rel_tol):
    """float64 loop over A's sample points and B's frames (the module docstring, literally)."""
    H, W = depth_b.shape[1:]
    n = seen = 0
    for za, Ta in zip(depth_a, T_a):
        for v in range(0, H, stride):
            for u in range(0, W, stride):
                z = za[v, u]
                if not np.isfinite(z):
                    continue
                n += 1
                ray = np.linalg.solve(K, [u, v, 1.0])
                x = Ta[:3, :3] @ (z * ray) + Ta[:3, 3]
                for zb, Tb in zip(depth_b, T_b):
                    y = Tb[:3, :3].T @ (x - Tb[:3, 3])
                    if y[2] <= 1e-6:
                        continue
                    p = K @ (y / y[2])
                    ui, vi = np.round(p[0]), np.round(p[1])
                    if 0 <= ui <= W - 1 and 0 <= vi <= H - 1 and abs(y[2] - zb[int(vi), int(ui)]) <= rel_tol * y[2]:
                        seen += 1
                        break
    return seen / max(n, 1), n


@settings(deadline=None, max_examples=4, derandomize=True)
@given(shift=st.sampled_from([0, 6, 15, 40]), stride=st.sampled_from([3, 5]))
def test_covisibility_matches_numpy_loop(exact, route, shift, stride):
    A = np.arange(100, 106)
    B = np.arange(100 + shift, 106 + shift) + (0 if shift < 40 else 300)  # 40: far away, no view shared
    da, _, _ = exact.render_truth(A)
    db, _, _ = exact.render_truth(B)
    origin = route[A[0], :3, 3]
    Ta, Tb = route[A].copy(), route[B].copy()
    Ta[:, :3, 3] -= origin
    Tb[:, :3, 3] -= origin
    ref, n = ref_covisibility(da, Ta, db, Tb, exact.K, stride, 0.1)
    got = float(
        covisibility(da, Ta.astype(np.float32), db, Tb.astype(np.float32), exact.K.astype(np.float32), stride, 0.1)
    )
    assert n > 50
    # float32 projections may round a pixel-boundary point the other way: a point or two
    assert abs(got - ref) <= 2.0 / n
    if shift == 0:
        assert got == pytest.approx(1.0, abs=0.02)  # a set sees itself
    if shift == 40:
        assert got == 0.0
    mutual = min(
        got,
        float(
            covisibility(db, Tb.astype(np.float32), da, Ta.astype(np.float32), exact.K.astype(np.float32), stride, 0.1)
        ),
    )
    assert float(covisibility_mutual(da, Ta, db, Tb, exact.K, stride, 0.1)) == pytest.approx(mutual)
    assert exact.covisibility(A, B, mutual=True, stride=stride) == pytest.approx(mutual, abs=1e-6)


def test_covisibility_bad_input(exact):
    with pytest.raises(ValueError, match="non-empty 1-D integer"):
        exact.covisibility(np.array([], int), np.arange(3))
    with pytest.raises(ValueError, match=r"must lie in \[0, 618\)"):
        exact.covisibility(np.arange(3), np.array([700]))


# --------------------------------------------------------------------- hallucinated chunks


@jax.jit
def _sim3_power(H, w):
    return sim3.as_matrix(sim3.exp(w * sim3.log(sim3.from_rst(H[:3, :3], H[:3, 3], 1.0))))


def test_hallucination_weight_and_geodesic_blend():
    hz = Hallucination(covis_low=0.1, covis_high=0.4)
    for c, w in ((0.0, 1.0), (0.1, 1.0), (0.4, 0.0), (0.9, 0.0), (0.25, 0.5), (0.175, 0.84375)):
        assert hz.weight(c) == pytest.approx(w)  # smoothstep u^2 (3 - 2u), u = (0.4 - c) / 0.3
    with pytest.raises(ValueError, match="covis_low < covis_high"):
        Hallucination(covis_low=0.5, covis_high=0.3)
    with pytest.raises(ValueError, match="conf_factor"):
        Hallucination(conf_factor=0.0)
    rng = np.random.default_rng(0)
    H = np.eye(4)
    for angle in (0.3, 2.0, np.pi - 1e-4):  # a false loop may face the other way
        axis = rng.normal(size=3)
        H[:3, :3] = so3_exp(angle * axis / np.linalg.norm(axis))
        H[:3, 3] = rng.normal(size=3) * 30
        half, third = se3_power(H, 0.5), se3_power(H, 1 / 3)
        np.testing.assert_allclose(half @ half, H, atol=1e-9)  # Exp(w Log H): a one-parameter subgroup
        np.testing.assert_allclose(third @ third @ third, H, atol=1e-9)
        np.testing.assert_allclose(se3_power(H, 1.0), H, atol=1e-9)
        np.testing.assert_allclose(se3_power(H, 0.0), np.eye(4), atol=1e-12)
        # against sim3's float64 Exp/Log (an independent implementation)
        with jax.enable_x64(True):
            ref = np.asarray(_sim3_power(jnp.asarray(H), 0.37))
        np.testing.assert_allclose(se3_power(H, 0.37), ref, atol=1e-8)


def test_true_loop_chunk_is_unchanged(world, route):
    """A true revisit (demo loop (568, 73), 0.75 m apart) is bit-identical to the honest oracle."""
    frames = loop_frames(568, 73)
    on = VGGTOracle(world, route, image_hw=HW, seed=5)
    off = VGGTOracle(world, route, image_hw=HW, seed=5, hallucination=None)
    truth = on.loop_chunk_truth(frames)
    assert truth.split == 20 and truth.covisibility > on.hallucination.covis_high and truth.weight == 0.0
    a, b = on.predict_chunk(frames), off.predict_chunk(frames)
    for name in ("depth", "conf", "extrinsic", "intrinsic", "patch_tokens", "images"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    # a temporal chunk has no break: honest whatever the setting
    t = on.loop_chunk_truth(np.arange(100, 175))
    assert t.weight == 0.0 and t.split == 75 and np.array_equal(t.rebase, np.eye(4))


def _chunk_world_points(pred, gauge):
    pts = camera.unproject(pred.depth, pred.intrinsic, camera.camera_to_world(pred.extrinsic))
    with jax.enable_x64(True):
        return np.asarray(sim3.act(jnp.asarray(gauge)[None, None, None, :], jnp.asarray(np.asarray(pts, np.float64))))


def test_false_loop_chunk_is_superimposed_by_the_documented_amount(world, route):
    """The demo's false candidate (563, 139), 62.6 m apart: no shared view, so the second half
    comes back re-based by H_1 = T_a Delta T_b^-1 (its own geometry kept), conf lowered."""
    frames = loop_frames(563, 139)
    hz = Hallucination(trans_m=0.5, rot=0.03)
    o = VGGTOracle(world, route, image_hw=HW, noise=OracleNoise.off(), tokens=False, hallucination=hz)
    truth = o.loop_chunk_truth(frames)
    assert truth.covisibility == 0.0 and truth.weight == 1.0
    np.testing.assert_array_equal(truth.rebase, truth.full_rebase)
    honest_oracle = VGGTOracle(world, route, image_hw=HW, noise=OracleNoise.off(), tokens=False, hallucination=None)
    pred, honest = o.predict_chunk(frames), honest_oracle.predict_chunk(frames)
    # the first half and every depth map are the honest ones; confidence is lowered
    np.testing.assert_array_equal(pred.depth, honest.depth)
    np.testing.assert_array_equal(pred.extrinsic[:20], honest.extrinsic[:20])
    np.testing.assert_allclose(pred.conf - 1.0, (honest.conf - 1.0) * hz.conf_factor, rtol=1e-6, atol=1e-6)
    # the second half's points are the gauge applied to H_1 x_world: the loop is off by H_1
    G = o.true_chunk_gauge(frames)
    got = _chunk_world_points(pred, G)[20:]
    truth_pts, valid = o.true_world_points(frames[20:])
    H1 = truth.full_rebase
    expected = truth_pts @ H1[:3, :3].T + H1[:3, 3]
    dist = np.linalg.norm(truth_pts - route[frames[20:], None, None, :3, 3], axis=-1)
    err = np.linalg.norm(got - expected, axis=-1)
    assert np.all(err[valid] <= 2e-6 * dist[valid] + 2e-4)
    # H_1 puts B's middle camera onto A's, offset by Delta (|t| ~ trans_m, angle ~ rot)
    Ta, Tb = route[frames[10]], route[frames[30]]
    delta = np.linalg.inv(Ta) @ H1 @ Tb
    assert 0.05 < np.linalg.norm(delta[:3, 3]) < 4 * hz.trans_m * np.sqrt(3)
    angle = np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1, 1))
    assert 0.0 < angle < 4 * hz.rot * np.sqrt(3)
    # the honest answer is 62 m away: the superimposition moves B by the loop's true offset
    assert np.linalg.norm(H1[:3, 3] + H1[:3, :3] @ Tb[:3, 3] - Tb[:3, 3]) > 50.0
    # deterministic per (seed, frames)
    again = VGGTOracle(world, route, image_hw=HW, noise=OracleNoise.off(), tokens=False, hallucination=hz)
    np.testing.assert_array_equal(again.loop_chunk_truth(frames).full_rebase, H1)


def test_partial_overlap_blends_between_honest_and_hallucinated(world, route):
    """Sliding the second half along the road lowers co-visibility; w and H(w) follow."""
    hz = Hallucination(covis_low=0.0, covis_high=0.999)  # every partial overlap is in the blend
    o = VGGTOracle(world, route, image_hw=HW, noise=OracleNoise.off(), tokens=False, hallucination=hz)
    frames = np.concatenate([np.arange(558, 578), np.arange(78, 98)])  # B 15 m past the revisit
    truth = o.loop_chunk_truth(frames)
    assert 0.0 < truth.weight < 1.0
    assert truth.weight == pytest.approx(hz.weight(truth.covisibility))
    np.testing.assert_allclose(truth.rebase, se3_power(truth.full_rebase, truth.weight), atol=1e-12)
    pred = o.predict_chunk(frames)
    T_pred = np.asarray(camera.camera_to_world(pred.extrinsic), np.float64)
    G = o.true_chunk_gauge(frames)
    with jax.enable_x64(True):
        Gm = np.asarray(sim3.as_matrix(jnp.asarray(G)))
    centres = (Gm[:3, :3] @ T_pred[20:, :3, 3].T).T + Gm[:3, 3]  # predicted camera centres, world
    expected = (truth.rebase[:3, :3] @ route[frames[20:], :3, 3].T).T + truth.rebase[:3, 3]
    np.testing.assert_allclose(centres, expected, atol=2e-3)


# ----------------------------------------------------------------------------- aliasing


def test_aliasing_planted_deterministically_at_the_rate(route, shared_dir):
    from swiftjax.io.trajectory import read_kitti

    gt = places.ground_truth_loops(route)
    segs = places.plant_aliasing(route, 0.3, strict=False)
    assert segs == places.plant_aliasing(route, 0.3, strict=False)  # keyed by seed
    assert places.plant_aliasing(route, 0.0) == ()
    assert places.plant_aliasing(route[:300], 0.5) == ()  # no true loop: nothing to be relative to
    # KITTI 00: the count is round(rate * C_true), each pair far apart and away from loops
    long = read_kitti(shared_dir / "data" / "trajectories" / "KITTI_00_gt.txt")
    gtl = places.ground_truth_loops(long)
    p = long[:, :3, 3]
    kept = []  # the detector's pair NMS on the true pairs, closest cameras first
    for k in np.argsort(np.linalg.norm(p[gtl[:, 0]] - p[gtl[:, 1]], axis=1), kind="stable"):
        if all(max(abs(gtl[k, 0] - gtl[m, 0]), abs(gtl[k, 1] - gtl[m, 1])) > 25 for m in kept):
            kept.append(k)
    chunk = np.maximum(np.round((gtl[kept] - 37) / 45), 0).astype(int)
    c_true = len({(a, b) for a, b in chunk.tolist() if abs(a - b) >= 2})
    assert c_true == 29
    for rate in (0.1, 0.3, 0.5):
        s = places.plant_aliasing(long, rate, seed=4)
        assert len(s) == round(rate * c_true)
        for a, b, L in s:
            assert a - b > 100 + L
            assert np.linalg.norm(p[a : a + L, None] - p[None, b : b + L], axis=-1).min() > 50.0
            pairs = np.stack([np.arange(a, a + L), np.arange(b, b + L)], 1)
            assert np.abs(pairs[:, None] - gtl[None]).max(-1).min() > 30  # Chebyshev to true pairs
            assert not places.evaluate_loops(pairs, gtl, regions=np.zeros(len(gtl), int)).correct.any()
    assert len(segs) >= 1 and all(L == 20 for _, _, L in segs)
    for a, b, L in segs:
        pairs = np.stack([np.arange(a, a + L), np.arange(b, b + L)], 1)
        assert not places.evaluate_loops(pairs, gt, regions=np.zeros(len(gt), int)).correct.any()
    with pytest.raises(ValueError, match="room for only"):
        places.plant_aliasing(route, 5.0)
    with pytest.raises(ValueError, match="rate >= 0"):
        places.plant_aliasing(route, -0.1)


def test_aliased_tokens_share_the_documented_component(route):
    cfg = places.PlaceTokenConfig(dim=256, tokens_per_frame=8, seed=2)
    segs = ((400, 200, 20),)
    base = places.make_place_params(cfg)
    ali = places.make_place_params(dataclasses.replace(cfg, aliasing=segs, alias_strength=0.64))
    ids = np.concatenate([np.arange(190, 230), np.arange(390, 430)])
    P = route[ids].astype(np.float32)
    t0 = np.asarray(places.place_tokens(base, P, ids))
    t1 = np.asarray(places.place_tokens(ali, P, ids))
    inside = ((ids >= 200) & (ids < 220)) | ((ids >= 400) & (ids < 420))
    np.testing.assert_array_equal(t0[~inside], t1[~inside])  # frames outside: untouched, bitwise
    # inside: place part = 0.6 own + 0.8 shared (the virtual street at offset t)
    a_place = cfg.place_strength
    own = np.asarray(places.place_signal(base, P))
    virt = np.tile(np.eye(4, dtype=np.float32), (20, 1, 1))
    virt[:, 0, 3] = np.arange(20)
    virt[:, 1, 3] = 5000.0
    shared = np.asarray(places.place_signal(base, virt))
    for start in (200, 400):
        k = np.nonzero(ids == start)[0][0] + np.arange(20)
        np.testing.assert_allclose(t1[k] - t0[k], a_place * (-0.4 * own[k] + 0.8 * shared), atol=2e-5)
    # corresponding frames' noise-free place parts have cosine ~ lambda = 0.64
    sa = 0.6 * own[10:30] + 0.8 * shared
    sb = 0.6 * own[50:70] + 0.8 * shared
    cos = np.sum(sa * sb, -1) / np.linalg.norm(sa, axis=-1) / np.linalg.norm(sb, axis=-1)
    assert np.mean(cos) == pytest.approx(0.64, abs=0.08)
    with pytest.raises(ValueError, match="overlap"):
        places.make_place_params(dataclasses.replace(cfg, aliasing=((400, 200, 20), (410, 100, 5))))
    with pytest.raises(ValueError, match="alias_strength"):
        places.make_place_params(dataclasses.replace(cfg, aliasing=segs, alias_strength=1.5))


def test_depth_seen_from_the_other_side_carries_the_same_errors():
    """A street driven out and back: the oracle's depth of the frames driving back (which see
    the facades from their other end) carries VGGT's per-pixel errors as the outbound frames'
    do: after the chunk scale is divided out, the log depth error has the same spread (not 0,
    not larger)."""
    from swiftjax.synthetic import demo

    out = []
    for k in range(160):
        m = np.eye(4)
        m[:3, 3] = [0.0, 0.0, 1.0 * k]
        out.append(m)
    back = []
    for m in out[::-1]:
        b = m.copy()
        b[:3, :3] = np.diag([-1.0, 1.0, -1.0])  # yaw by pi: facing -z
        back.append(b)
    poses = np.stack(out + back)
    run = demo.trajectory_run(poses, name="out-and-back")
    orc = run.predictor.oracle
    spreads = []
    for frames in (np.arange(40, 55), np.arange(160 + 105, 160 + 120)):  # the same stretch of street
        pred = orc.predict_chunk(frames)
        truth, _, _ = orc.render_truth(frames)
        ratio = np.log(pred.depth / truth)
        ok = np.isfinite(ratio) & (truth < 40)
        res = ratio - np.nanmedian(np.where(ok, ratio, np.nan), axis=(1, 2), keepdims=True)
        spreads.append(float(np.std(res[ok])))
    fwd, rev = spreads
    assert 0.005 < fwd and 0.005 < rev
    assert 0.5 < rev / fwd < 2.0

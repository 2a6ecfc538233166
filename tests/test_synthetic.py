"""Synthetic world, renderer and VGGT oracle: truth, consistency, noise statistics, determinism."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from swiftjax import camera, sim3
from swiftjax.synthetic import OracleNoise, VGGTOracle, kitti_intrinsics, places
from swiftjax.synthetic.render import chunk_candidates, frame_planes, render_frames, render_numpy
from swiftjax.synthetic.routes import loop_route
from swiftjax.synthetic.world import BUILDING, GROUND, POLE, SKY, TREE, WorldConfig, build_world

HW = (28, 84)  # small images: every test here is about geometry and statistics, not size


@pytest.fixture(scope="module")
def route():
    return loop_route()


@pytest.fixture(scope="module")
def world(route):
    return build_world(route)


@pytest.fixture(scope="module")
def exact(world, route):
    return VGGTOracle(world, route, image_hw=HW, noise=OracleNoise.off(), tokens=False)


@pytest.fixture(scope="module")
def noisy(world, route):
    return VGGTOracle(world, route, image_hw=HW, seed=7)


# ----------------------------------------------------------------------------- routes


def test_loop_route_is_a_closed_loop_with_a_revisit(route):
    T = route
    np.testing.assert_allclose(T[0], np.eye(4), atol=1e-12)
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    assert np.all(np.abs(step - 1.0) < 0.01)  # ~1 m per frame
    # the camera looks along the direction of travel
    travel = np.diff(T[:, :3, 3], axis=0)
    cos = np.sum(travel / step[:, None] * R[:-1, :, 2], axis=1)
    assert np.all(cos > 0.99)
    # revisit: a frame > 100 frames later within 1 m of frame 0, looking the same way
    d = np.linalg.norm(T[:, :3, 3] - T[0, :3, 3], axis=1)
    later = np.nonzero((np.arange(len(T)) > 100) & (d < 1.0))[0]
    assert later.size > 0 and R[later[0], :, 2] @ R[0, :, 2] > 0.99


def test_loop_route_rejects_bad_sizes():
    with pytest.raises(ValueError, match="corner_radius"):
        loop_route(width=20.0, corner_radius=15.0)
    with pytest.raises(ValueError, match="must be > 0"):
        loop_route(laps=0.0)


# ------------------------------------------------------------------------------ world


def test_world_is_deterministic_and_keeps_the_road_clear(world, route):
    again = build_world(route)
    for a, b in zip(world, again):
        np.testing.assert_array_equal(a, b)
    other = build_world(route, WorldConfig(seed=1))
    assert other.box_center.shape != world.box_center.shape or not np.allclose(other.box_center, world.box_center)
    assert world.num_boxes > 20 and world.num_cylinders > 20
    assert set(np.unique(world.cyl_semantic)) == {POLE, TREE}
    # brute force: no camera within the clearance of any box footprint or cylinder
    cfg = WorldConfig()
    pos = route[:, :3, 3]
    for c, A, h in zip(world.box_center, world.box_axes, world.box_half):
        q = (pos - c) @ A
        dist = np.hypot(np.maximum(np.abs(q[:, 0]) - h[0], 0), np.maximum(np.abs(q[:, 1]) - h[1], 0))
        assert dist.min() >= cfg.clearance_m - 1e-9
    up = world.up
    for b, r in zip(world.cyl_base, world.cyl_radius):
        v = pos - b
        horiz = np.linalg.norm(v - np.outer(v @ up, up), axis=1) - r
        assert horiz.min() >= cfg.pole_clearance_m - 1e-9


def test_world_rejects_bad_trajectories():
    with pytest.raises(ValueError, match=r"\[N, 4, 4\]"):
        build_world(np.zeros((5, 4)))
    with pytest.raises(ValueError, match="at least 2 poses"):
        build_world(np.eye(4)[None])
    with pytest.raises(ValueError, match="only 0.00 m long"):
        build_world(np.tile(np.eye(4), (10, 1, 1)))


# --------------------------------------------------------------------------- renderer


def test_renderer_matches_float64_numpy_reference(world, route):
    h, w = 40, 120
    K = kitti_intrinsics(w, h)
    frames = np.array([0, 37, 150, 301, 444])
    origin = route[frames[0], :3, 3]
    P = route[frames]
    cand = chunk_candidates(world, P[:, :3, 3], origin)
    planes = frame_planes(world, P[:, :3, 3], origin)
    out = render_frames(
        K.astype(np.float32),
        P[:, :3, :3].astype(np.float32),
        (P[:, :3, 3] - origin).astype(np.float32),
        planes.astype(np.float32),
        cand,
        np.int32(world.num_boxes),
        height=h,
        width=w,
        k_box=40,
        k_cyl=40,  # budgets above every frame's visible set: no culling difference
        k_box_tile=16,
        k_cyl_tile=15,
    )
    assert np.all(np.asarray(out.tile_overflow) == 0)  # so every candidate was tested where visible
    depth = np.asarray(out.depth)
    sem = np.asarray(out.semantic)
    for i, f in enumerate(frames):
        ref = render_numpy(world, K, route[f], h, w)
        same_sky = np.isfinite(ref) == np.isfinite(depth[i])
        assert same_sky.mean() > 0.995  # silhouettes may flip on float32 round-off
        both = np.isfinite(ref) & np.isfinite(depth[i])
        rel = np.abs(depth[i][both] - ref[both]) / ref[both]
        assert np.median(rel) < 1e-6
        assert (rel > 1e-3).mean() < 0.01  # only silhouette pixels can hit another object
        assert np.all((sem[i] == SKY) == ~np.isfinite(depth[i]))
    # a street: ground at the bottom rows, buildings present, sky somewhere
    assert (sem[:, -1, :] == GROUND).mean() > 0.9
    assert (sem == BUILDING).mean() > 0.2 and (sem == SKY).mean() > 0.01


def _render(world, route, frames, h, w, **kw):
    K = kitti_intrinsics(w, h)
    P = route[frames]
    origin = P[0, :3, 3]
    cand = chunk_candidates(world, P[:, :3, 3], origin)
    planes = frame_planes(world, P[:, :3, 3], origin)
    out = render_frames(
        K.astype(np.float32),
        P[:, :3, :3].astype(np.float32),
        (P[:, :3, 3] - origin).astype(np.float32),
        planes.astype(np.float32),
        cand,
        np.int32(world.num_boxes),
        height=h,
        width=w,
        **kw,
    )
    return [np.asarray(a) for a in out]


def test_tile_culling_is_invisible_unless_a_tile_overflows(world, route):
    # 127 columns: the last 14-column tile is partial (padding columns are cropped)
    frames = np.array([3, 90, 180, 260, 333, 420])
    h, w = 36, 127
    full = _render(world, route, frames, h, w, k_box_tile=12, k_cyl_tile=10)  # every frame candidate
    tiled = _render(world, route, frames, h, w)  # defaults: 8 + 6 per tile
    assert np.all(full[3] == 0) and np.all(tiled[3] == 0)
    # identical up to seam pixels where two surfaces lie within 2^b float32 ulps
    assert np.mean(full[1] == tiled[1]) > 0.999 and np.mean(full[2] == tiled[2]) > 0.999
    fin = np.isfinite(full[0])
    assert np.array_equal(fin, np.isfinite(tiled[0]))
    np.testing.assert_allclose(tiled[0][fin], full[0][fin], rtol=1e-5)
    # narrow tiles (one column each) cull hardest and still agree
    narrow = _render(world, route, frames, h, w, tile_width=1)
    assert np.all(narrow[3] == 0)
    assert np.mean(full[2] == narrow[2]) > 0.999
    # a budget of one object per tile drops visible objects, and says so
    tiny = _render(world, route, frames, h, w, k_box_tile=1, k_cyl_tile=1)
    assert np.all(tiny[3] > 0)
    assert np.mean(full[2] != tiny[2]) > 0.01
    with pytest.raises(ValueError, match="<= 32"):
        _render(world, route, frames, h, w, k_box=20, k_cyl=20, k_box_tile=20, k_cyl_tile=20)


# ----------------------------------------------------------------------------- oracle


def _world_points_from_prediction(pred, gauge):
    """Unproject with the prediction's own K / extrinsics, then map with the chunk gauge."""
    pts = camera.unproject(pred.depth, pred.intrinsic, camera.camera_to_world(pred.extrinsic))
    with jax.enable_x64(True):
        return np.asarray(sim3.act(jnp.asarray(gauge)[None, None, None, :], jnp.asarray(np.asarray(pts, np.float64))))


# 200: pixel blocks gathered from two render blocks each; 150: each pixel block IS a cached
# render block (the regular schedule's case, fed to the pixel kernel on the device)
@pytest.mark.parametrize("start", [200, 150])
def test_noise_off_reproduces_true_world_points(exact, start):
    frames = np.arange(start, start + 75)
    pred = exact.predict_chunk(frames)
    G = exact.true_chunk_gauge(frames)
    truth, valid = exact.true_world_points(frames)
    got = _world_points_from_prediction(pred, G)
    dist = np.linalg.norm(truth - exact.true_cam_to_world(frames)[:, None, None, :3, 3], axis=-1)
    err = np.linalg.norm(got - truth, axis=-1)
    assert valid.mean() > 0.5
    assert np.all(err[valid] <= 2e-6 * dist[valid] + 1e-4)  # float32 depth, float64 truth
    # VGGT's gauge: first camera at the origin, mean depth = depth_units
    np.testing.assert_allclose(pred.extrinsic[0], np.eye(3, 4), atol=1e-7)
    np.testing.assert_allclose(pred.intrinsic, np.broadcast_to(exact.K, (75, 3, 3)), rtol=1e-7)
    assert pred.depth[valid].mean() == pytest.approx(2.0, rel=1e-4)
    # the gauge maps the chunk origin onto the first camera's centre
    np.testing.assert_allclose(np.asarray(sim3.translation(G)), exact.poses[start, :3, 3], atol=1e-12)


def test_noise_statistics_are_as_configured(world, route):
    # the default noise without the per-chunk depth bias, whose z-dependence would widen the
    # per-pixel spread measured below
    noisy = VGGTOracle(
        world, route, image_hw=HW, seed=7, tokens=False, noise=dataclasses.replace(OracleNoise(), depth_bias=0.0)
    )
    frames = np.arange(300, 375)
    pred = noisy.predict_chunk(frames)
    nz = noisy.noise
    z, sem, _ = noisy.render_truth(frames)
    # intrinsics: focal noise within +-2 %, principal point exact, fx and fy scaled together
    eps = pred.intrinsic[:, 0, 0] / noisy.K[0, 0] - 1.0
    assert np.all(np.abs(eps) <= nz.focal + 1e-6) and eps.std() > nz.focal / 5
    np.testing.assert_allclose(pred.intrinsic[:, 1, 1] / noisy.K[1, 1] - 1.0, eps, atol=1e-6)
    np.testing.assert_allclose(pred.intrinsic[:, :2, 2], np.broadcast_to(noisy.K[:2, 2], (75, 2)), rtol=1e-6)
    # depth normalisation (eq. 1) removes the focal coupling: D_reg / z is one constant per
    # frame up to the drift scale; its per-pixel log spread is the configured noise
    d_reg = np.asarray(camera.normalize_depth(pred.depth, pred.intrinsic, noisy.K.astype(np.float32)))
    finite = np.isfinite(z)
    lz = np.log(np.where(finite, z, nz.sky_depth_m))
    jump = np.zeros_like(finite)  # depth discontinuities over the 4-neighbourhood, as the oracle
    for axis in (1, 2):
        d = np.abs(np.diff(lz, axis=axis)) > nz.edge_log_ratio
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        jump[tuple(lo)] |= d
        jump[tuple(hi)] |= d
    ok = finite & ~jump
    ratio = np.log(d_reg / np.where(ok, z, 1.0))
    per_frame = np.array([np.median(r[m]) for r, m in zip(ratio, ok)])
    raw = np.array([np.median(r[m]) for r, m in zip(np.log(pred.depth / np.where(ok, z, 1.0)), ok)])
    # the frame-level factor creeps smoothly (drift scale + gauge) once eq. 1 removed the +-2 %
    # focal jumps that the raw depths carry
    assert np.std(np.diff(per_frame)) < 0.5 * np.std(np.diff(raw))
    np.testing.assert_allclose(raw - per_frame, np.log1p(eps), atol=1e-5)
    resid = (ratio - per_frame[:, None, None])[ok]
    near = ok & (z < 15.0)
    resid_near = (ratio - per_frame[:, None, None])[near]
    expected_near = nz.depth_rel * (1 + np.median(z[near]) / nz.depth_rel_ref_m)
    robust_std = 1.4826 * np.median(np.abs(resid_near - np.median(resid_near)))
    assert robust_std == pytest.approx(expected_near, rel=0.3)
    # gross errors: about gross_fraction of the pixels are off by more than 10 %
    gross = (np.abs(resid) > 0.1).mean()
    assert 0.3 * nz.gross_fraction < gross < 3 * nz.gross_fraction
    # confidence: >= 1, ~1 on sky, lower far away and at depth discontinuities
    assert pred.conf.min() >= 1.0
    assert pred.conf[sem == SKY].max() <= 1.05 + 1e-6
    assert np.median(pred.conf[finite & (z < 10)]) > 3 * np.median(pred.conf[finite & (z > 40)])
    assert np.median(pred.conf[jump & finite]) < 0.5 * np.median(pred.conf[~jump & finite])
    # sky depth is finite (VGGT never returns inf) and far
    assert np.all(np.isfinite(pred.depth)) and pred.depth[sem == SKY].min() > 5 * pred.depth[finite].mean()
    assert pred.images.dtype == np.uint8 and pred.images.shape == (75, *HW, 3)


def test_same_frame_in_two_chunks_agrees_up_to_gauge_and_noise(world, route, noisy):
    a, b = np.arange(90, 165), np.arange(135, 210)
    pa, pb = noisy.predict_chunk(a), noisy.predict_chunk(b)
    # depth in each chunk's units after eq. 1: the alignment mask |D_a - D_b| < 0.2 passes
    # for most confident pixels
    K_ref = pa.intrinsic[0]
    da = np.asarray(camera.normalize_depth(pa.depth[45:], pa.intrinsic[45:], K_ref))
    db = np.asarray(camera.normalize_depth(pb.depth[:30], pb.intrinsic[:30], K_ref))
    conf = (pa.conf[45:] > 0.5 * pa.conf[45:].mean()) & (pb.conf[:30] > 0.5 * pb.conf[:30].mean())
    assert conf.mean() > 0.5
    assert (np.abs(da - db)[conf] < 0.2).mean() > 0.8
    # tokens of a frame are identical in every chunk (keyed by the global frame id)
    np.testing.assert_array_equal(pa.patch_tokens[45:], pb.patch_tokens[:30])
    assert pa.patch_tokens.shape[:1] == (75,)
    # the TRUE gauges differ, the world points agree after each chunk's own gauge: without
    # drift, up to depth noise and the focal z-stretch (<= 2 % of z)
    nodrift = VGGTOracle(
        world,
        route,
        image_hw=HW,
        seed=7,
        tokens=False,
        noise=dataclasses.replace(OracleNoise(), drift_rot=0.0, drift_scale=0.0),
    )
    qa, qb = nodrift.predict_chunk(a), nodrift.predict_chunk(b)
    wa = _world_points_from_prediction(qa, nodrift.true_chunk_gauge(a))[45:]
    wb = _world_points_from_prediction(qb, nodrift.true_chunk_gauge(b))[:30]
    z, _, _ = noisy.render_truth(a[45:])
    good = conf & np.isfinite(z) & (z < 20)
    err = np.linalg.norm(wa - wb, axis=-1)[good]
    assert np.median(err / z[good]) < 0.03


def test_predictions_are_deterministic_and_history_free(world, route, noisy):
    frames = np.concatenate([np.arange(20, 40), np.arange(500, 520)])  # a loop-centric chunk
    first = noisy.predict_chunk(frames)
    fresh = VGGTOracle(world, route, image_hw=HW, seed=7)
    fresh.predict_chunk(np.arange(0, 75))  # unrelated history
    again = fresh.predict_chunk(frames)
    for name in ("depth", "conf", "extrinsic", "intrinsic", "patch_tokens", "images"):
        np.testing.assert_array_equal(getattr(first, name), getattr(again, name), err_msg=name)
    # the place tokens are per frame (cached per frame): a fresh computation agrees
    np.testing.assert_array_equal(
        first.patch_tokens,
        np.asarray(places.place_tokens(fresh.place_params, route[frames].astype(np.float32), frames.astype(np.int32))),
    )
    other_seed = VGGTOracle(world, route, image_hw=HW, seed=8, tokens=False).predict_chunk(frames)
    assert not np.array_equal(other_seed.depth, first.depth)


def test_drift_grows_along_the_chunk(world, route):
    nz = dataclasses.replace(OracleNoise.off(), drift_rot=1e-3, drift_scale=1e-3)
    o = VGGTOracle(world, route, image_hw=HW, noise=nz, tokens=False, seed=3)
    ex = VGGTOracle(world, route, image_hw=HW, noise=OracleNoise.off(), tokens=False)
    frames = np.arange(400, 475)
    p, q = o.predict_chunk(frames), ex.predict_chunk(frames)
    rot_err = np.linalg.norm(
        camera.camera_to_world(p.extrinsic)[:, :, :3] - camera.camera_to_world(q.extrinsic)[:, :, :3], axis=(1, 2)
    )
    assert rot_err[0] < 1e-6 and rot_err[-1] > 10 * rot_err[5] > 0
    # the drift scale multiplies the depth, so each frame's points move with its camera
    r = p.depth / q.depth
    assert np.allclose(np.median(r, axis=(1, 2))[[0]], 1.0, atol=1e-6)
    assert abs(np.log(np.median(r[-1]))) > 0.01


def test_bad_frame_indices_raise(noisy):
    with pytest.raises(ValueError, match=r"must lie in \[0, 618\)"):
        noisy.predict_chunk(np.array([0, 618]))
    with pytest.raises(ValueError, match="non-empty 1-D integer"):
        noisy.predict_chunk(np.array([], dtype=int))
    with pytest.raises(ValueError, match="non-empty 1-D integer"):
        noisy.predict_chunk(np.array([0.5, 1.5]))

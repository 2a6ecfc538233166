"""Masks: mask folders, sky from depth + confidence, masked alignment (and its pose fallback),
moving cars in the synthetic world."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from swiftjax import align, intrinsics, masks


def _png(path, arr):
    from PIL import Image

    Image.fromarray(arr).save(path)


def test_mask_directory_matches_by_stem_and_maps_like_the_images(tmp_path):
    g = intrinsics.preprocess_geometry(640, 480, "crop")
    names = ["000000.jpg", "000001.jpg"]
    boxes = []
    for k, name in enumerate(names):
        m = np.full((640, 480), 255, np.uint8)
        m[100 + 50 * k : 300, 40:200] = 0  # a box to drop
        _png(tmp_path / (name[:-4] + ".png"), m)
        boxes.append(m > 127)
    md = masks.MaskDirectory(tmp_path, names, g)
    out = md.read([1, 0])
    assert out.shape == (2, 518, 518) and out.dtype == bool
    np.testing.assert_array_equal(out[0], intrinsics.map_mask(boxes[1], g))
    np.testing.assert_array_equal(out[1], intrinsics.map_mask(boxes[0], g))
    assert len(md.fingerprint()) == 2


def test_mask_directory_errors(tmp_path):
    g = intrinsics.preprocess_geometry(64, 96, "crop")
    with pytest.raises(masks.MaskError, match="does not exist"):
        masks.MaskDirectory(tmp_path / "nope", ["a.png"], g)
    _png(tmp_path / "a.png", np.zeros((64, 96), np.uint8))
    with pytest.raises(masks.MaskError, match="lacks 1 of 2 masks .first: b.png"):
        masks.MaskDirectory(tmp_path, ["a.jpg", "b.jpg"], g)
    _png(tmp_path / "b.png", np.zeros((60, 96), np.uint8))
    md = masks.MaskDirectory(tmp_path, ["a.jpg", "b.jpg"], g)
    with pytest.raises(masks.MaskError, match=r"b.png is 96x60 but the images are 96x64"):
        md.read([1])
    (tmp_path / "c.png").write_bytes(b"not a png")
    with pytest.raises(masks.MaskError, match="cannot be read"):
        masks.MaskDirectory(tmp_path, ["c.jpg"], g).read([0])


def test_sky_mask_rule():
    rng = np.random.default_rng(0)
    depth = rng.uniform(5, 15, (2, 16, 24)).astype(np.float32)
    conf = rng.uniform(5, 10, (2, 16, 24)).astype(np.float32)
    depth[:, :4] = 300.0  # far ...
    conf[:, :4] = 1.02  # ... and unsure: sky
    depth[:, 4, :6] = 300.0  # far but sure: kept
    conf[:, 5, :6] = 1.0  # unsure but near: kept
    depth[1, 6, 0] = np.inf  # non-finite: sky
    sky = np.asarray(masks.sky_mask(depth, conf))
    med_d = np.median(depth[:, ::4, ::4].reshape(2, -1), 1)
    med_c = np.median(conf[:, ::4, ::4].reshape(2, -1), 1)
    ref = (depth > 5 * med_d[:, None, None]) & (conf < 0.3 * med_c[:, None, None]) | ~np.isfinite(depth)
    np.testing.assert_array_equal(sky, ref)
    assert sky[:, :4].all() and not sky[:, 4:6, :6].any() and sky[1, 6, 0]
    keep = np.asarray(masks.keep_mask(depth, conf, np.ones_like(sky), drop_sky=True))
    np.testing.assert_array_equal(keep, ~sky)
    assert masks.keep_mask(depth, conf) is None


def _pair(o=4, h=24, w=32, seed=0):
    """Two chunks seeing the same frames: chunk t+1 = chunk t mapped by a known Sim(3)."""
    rng = np.random.default_rng(seed)
    K = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    depth = rng.uniform(2, 6, (o, h, w))
    conf = rng.uniform(2, 4, (o, h, w))
    E = np.tile(np.eye(3, 4), (o, 1, 1))
    E[:, 2, 3] = -np.arange(o) * 0.5  # cameras moving forward
    E[:, 0, 3] = -0.1 * np.arange(o) ** 2
    prev = align.ChunkFrames(depth, conf, np.tile(K, (o, 1, 1)), E)
    s = 0.98  # eq. 2 compares the two chunks' depths: |6 (1 - s)| < 0.2
    cur = align.ChunkFrames(depth * s, conf, np.tile(K, (o, 1, 1)), np.concatenate([E[..., :3], E[..., 3:] * s], -1))
    f32 = lambda fr: align.ChunkFrames(*(np.asarray(a, np.float32) for a in fr))
    return f32(prev), f32(cur), K.astype(np.float32), s


def test_mask_equals_removing_the_pixels():
    prev, cur, K, s = _pair()
    rng = np.random.default_rng(1)
    keep = rng.random(prev.depth.shape) < 0.6
    S_m, info_m = align.align_chunk_pair(prev, cur, K, options=align.AlignOptions(min_points=10), mask=keep)
    nan = lambda fr: fr._replace(depth=np.where(keep, fr.depth, np.nan).astype(np.float32))
    S_n, info_n = align.align_chunk_pair(nan(prev), nan(cur), K, options=align.AlignOptions(min_points=10))
    assert int(info_m.num_points) == int(info_n.num_points) == int(keep.sum())
    np.testing.assert_allclose(np.asarray(S_m), np.asarray(S_n), atol=2e-5)
    assert float(S_m[7]) == pytest.approx(1 / s, rel=1e-4)  # maps cur (scaled by s) into prev


def test_a_mask_removing_the_whole_overlap_falls_back_to_the_poses_with_a_warning(logged_warning):
    prev, cur, K, _ = _pair()
    keep = np.zeros(prev.depth.shape, bool)
    with logged_warning(r"0 reliable points.*the mask keeps 0\.00% of its pixels.*overlap camera poses"):
        S, info = align.align_chunk_pair_checked(prev, cur, K, options=align.AlignOptions(min_points=10), mask=keep)
    assert bool(info.pose_fallback) and int(info.num_points) == 0
    S_pose, ok = align.pose_based_estimate(prev.extrinsic, cur.extrinsic)
    assert bool(ok)
    np.testing.assert_allclose(np.asarray(S), np.asarray(S_pose), atol=1e-6)
    with pytest.raises(ValueError, match="mask has shape"):
        align.align_chunk_pair_checked(prev, cur, K, mask=keep[:, :5])
    with logged_warning(None):  # an unmasked pair does not warn
        align.align_chunk_pair_checked(prev, cur, K, options=align.AlignOptions(min_points=10))


# ------------------------------------------------------------------- synthetic world

HW = (56, 140)


@pytest.fixture(scope="module")
def street():
    from swiftjax.synthetic import VGGTOracle, WorldConfig, build_world, loop_route

    poses = loop_route(width=60.0, length=40.0, corner_radius=10.0, laps=0.6)
    world = build_world(poses, WorldConfig(seed=2, num_movers=12))
    K = np.array([[120.0, 0, 69.5], [0, 120.0, 27.0], [0, 0, 1]])
    return world, poses, K, VGGTOracle(world, poses, intrinsic=K, image_hw=HW, tokens=False)


def test_movers_leave_the_static_world_unchanged_and_are_labelled(street):
    from swiftjax.synthetic import WorldConfig, build_world
    from swiftjax.synthetic.world import CAR

    world, poses, K, oracle = street
    static = build_world(poses, WorldConfig(seed=2))
    for f in ("box_center", "cyl_base", "ground_points"):
        np.testing.assert_array_equal(getattr(static, f), getattr(world, f))
    depth, sem, inst = oracle.render_truth(np.arange(0, 60))
    car = sem == CAR
    assert 0.005 < car.mean() < 0.3 and car.any(axis=(1, 2)).mean() > 0.3
    assert np.all(inst[car] >= world.num_boxes + world.num_cylinders)
    assert np.all(np.isfinite(depth[car]))


def test_car_depth_is_consistent_within_a_frame_but_not_across_chunks(street):
    """The same frames in two chunks: static pixels agree up to the chunk gauge (noise off),
    car pixels do not (one depth factor per (chunk, car))."""
    from swiftjax.synthetic import OracleNoise, VGGTOracle
    from swiftjax.synthetic.world import CAR

    world, poses, K, _ = street
    oracle = VGGTOracle(
        world,
        poses,
        intrinsic=K,
        image_hw=HW,
        tokens=False,
        noise=dataclasses.replace(OracleNoise.off(), mover_depth=0.05),
    )
    _, sem, _ = oracle.render_truth(np.arange(15, 45))
    a = oracle.predict_chunk(np.arange(0, 45)).depth[15:]
    b = oracle.predict_chunk(np.arange(15, 60)).depth[:30]
    ratio = b / a
    static = (sem != CAR) & (sem != 0)
    car = sem == CAR
    r0 = np.median(ratio[static])
    np.testing.assert_allclose(ratio[static], r0, rtol=1e-5)
    assert np.max(np.abs(ratio[car] / r0 - 1)) > 0.01
    # within one frame of one chunk, a car's pixels share one factor: they unproject onto the box
    pred = oracle.predict_chunk(np.arange(15, 60))
    true_d, sem2, inst2 = oracle.render_truth(np.arange(15, 60))
    k = int(np.argmax((sem2 == CAR).sum(axis=(1, 2))))
    ids = np.unique(inst2[k][sem2[k] == CAR])
    for i in ids:
        px = inst2[k] == i
        f = pred.depth[k][px] / true_d[k][px]
        np.testing.assert_allclose(f, f[0], rtol=1e-5)


def test_sky_mask_against_the_worlds_sky_label(street):
    """With the default oracle noise: the rule finds the sky label's pixels (and the flying
    pixels at its border, which are junk either way)."""
    _, _, _, oracle = street
    frames = np.arange(0, 45)
    pred = oracle.predict_chunk(frames)
    _, sem, _ = oracle.render_truth(frames)
    sky = np.asarray(masks.sky_mask(pred.depth, pred.conf))
    truth = sem == 0
    recall = (sky & truth).sum() / truth.sum()
    precision = (sky & truth).sum() / sky.sum()
    assert truth.mean() > 0.01 and recall > 0.98 and precision > 0.8

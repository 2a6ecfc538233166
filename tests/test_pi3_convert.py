"""π³ outputs -> ChunkPrediction: intrinsics from rays, re-based extrinsics, confidence, tokens;
and π³'s official resize rule."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from inference.pi3.convert import (
    confidence_from_logit,
    intrinsics_from_local_points,
    rebase_extrinsics,
    to_chunk_prediction,
)
from inference.pi3.preprocess import preprocess, target_size_hw

LAMBDA_GAMMA = 0.5  # AlignOptions.conf_ratio: reliability mask gamma > 0.5 mean(gamma)
POINT_FILTER = 0.75  # exported points: gamma >= 0.75 mean(gamma)


@pytest.fixture(scope="module")
def golden(shared_dir: pathlib.Path) -> dict[str, np.ndarray]:
    path = shared_dir / "golden" / "pi3" / "tiny_golden.npz"
    if not path.is_file():
        pytest.skip(f"π³ golden data not found: {path}")
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _camera_points(K: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """``depth [S,H,W] * K^-1 (u, v, 1)`` at integer pixel centres, float64 loops-free."""
    s, h, w = depth.shape
    v, u = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    pix = np.stack([u, v, np.ones_like(u)], -1)
    rays = np.einsum("sij,hwj->shwi", np.linalg.inv(K), pix)
    return depth[..., None] * rays


def _lstsq_reference(points: np.ndarray) -> np.ndarray:
    """Independent reference: ``np.linalg.lstsq`` on ``[x/z, 1] [f, c]^T = u`` per view."""
    out = []
    for p in points:  # [H, W, 3]
        h, w = p.shape[:2]
        v, u = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
        x = (p[..., 0] / p[..., 2]).ravel()
        y = (p[..., 1] / p[..., 2]).ravel()
        (fx, cx), *_ = np.linalg.lstsq(np.stack([x, np.ones_like(x)], 1), u.ravel(), rcond=None)
        (fy, cy), *_ = np.linalg.lstsq(np.stack([y, np.ones_like(y)], 1), v.ravel(), rcond=None)
        out.append([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return np.array(out)


# ---- intrinsics ---------------------------------------------------------------------------------


def test_intrinsics_recovered_exactly_from_a_known_pinhole() -> None:
    rng = np.random.default_rng(0)
    K = np.array([[[310.0, 0, 251.3], [0, 295.0, 70.2], [0, 0, 1]], [[140.0, 0, 60.0], [0, 150.0, 80.0], [0, 0, 1]]])
    depth = rng.uniform(0.5, 40.0, (2, 154, 504))
    got = intrinsics_from_local_points(_camera_points(K, depth))
    np.testing.assert_allclose(got, K, rtol=1e-10, atol=1e-8)
    # unit rays (π³X's ``rays``) give the same K: the fit only uses x/z, y/z
    rays = _camera_points(K, depth)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    np.testing.assert_allclose(intrinsics_from_local_points(rays), K, rtol=1e-10, atol=1e-8)


def test_intrinsics_centred_principal_point() -> None:
    K = np.array([[[200.0, 0, 69.5], [0, 180.0, 27.5], [0, 0, 1]]])  # centre of a 140 x 56 image
    got = intrinsics_from_local_points(_camera_points(K, np.full((1, 56, 140), 3.0)), center_principal_point=True)
    np.testing.assert_allclose(got, K, rtol=1e-12)


def test_intrinsics_least_squares_matches_lstsq_on_noisy_rays() -> None:
    rng = np.random.default_rng(1)
    K = np.array([[[120.0, 0, 69.5], [0, 118.0, 27.0], [0, 0, 1]]] * 3)
    pts = _camera_points(K, rng.uniform(1, 10, (3, 56, 140))) + rng.normal(0, 0.02, (3, 56, 140, 3))
    np.testing.assert_allclose(intrinsics_from_local_points(pts), _lstsq_reference(pts), rtol=1e-9)


def test_intrinsics_on_the_golden_local_points(golden) -> None:
    local = golden["local_points"][0].astype(np.float64)
    got = intrinsics_from_local_points(local)
    np.testing.assert_allclose(got, _lstsq_reference(local), rtol=1e-9, atol=1e-9)
    assert np.all(np.isfinite(got))


def test_intrinsics_ignore_invalid_pixels() -> None:
    K = np.array([[[100.0, 0, 30.0], [0, 90.0, 20.0], [0, 0, 1]]])
    pts = _camera_points(K, np.full((1, 42, 70), 2.0))
    pts[0, :5, :5] = np.nan
    pts[0, 10, 10, 2] = 0.0
    np.testing.assert_allclose(intrinsics_from_local_points(pts), K, rtol=1e-10)


# ---- extrinsics ---------------------------------------------------------------------------------


def _random_c2w(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 3, 3))
    R = np.linalg.qr(q)[0]
    R *= np.sign(np.linalg.det(R))[:, None, None]
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, rng.normal(size=(n, 3)) * 5
    return T


def test_rebase_puts_camera0_at_origin_and_keeps_relative_poses() -> None:
    rng = np.random.default_rng(2)
    T = _random_c2w(rng, 5)
    E = rebase_extrinsics(T)
    np.testing.assert_allclose(E[0], np.eye(4)[:3], atol=1e-12)
    # any world point X: camera i sees inv(T_i) X; in the re-based frame X' = inv(T_0) X
    X = np.append(rng.normal(size=3) * 10, 1.0)
    Xp = np.linalg.inv(T[0]) @ X
    for i in range(5):
        np.testing.assert_allclose(E[i] @ Xp, (np.linalg.inv(T[i]) @ X)[:3], atol=1e-9)


def test_rebase_on_golden_maps_world_points_to_local_points(golden) -> None:
    """The golden's world points in camera 0's frame, seen by the re-based cameras, are the
    golden's local points (the same consistency the official ``points = poses @ local`` holds)."""
    T = golden["camera_poses"][0].astype(np.float64)
    E = rebase_extrinsics(T)
    world = golden["points"][0].astype(np.float64)  # [S, H, W, 3]
    in_cam0 = np.einsum("ij,shwj->shwi", np.linalg.inv(T[0])[:3, :3], world) + np.linalg.inv(T[0])[:3, 3]
    seen = np.einsum("sij,shwj->shwi", E[:, :, :3], in_cam0) + E[:, None, None, :, 3]
    np.testing.assert_allclose(seen, golden["local_points"][0], atol=2e-5)


# ---- confidence ---------------------------------------------------------------------------------


def test_confidence_is_the_sigmoid_without_overflow() -> None:
    x = np.array([-1000.0, -20.0, -1.0, 0.0, 2.5, 30.0, 1000.0])
    got = confidence_from_logit(x)
    np.testing.assert_allclose(got, 1 / (1 + np.exp(-np.clip(x, -700, 700))), rtol=1e-6, atol=1e-30)
    assert got.dtype == np.float32 and np.all(np.isfinite(got))


def _kept(conf: np.ndarray) -> tuple[float, float]:
    mean = conf.reshape(conf.shape[0], -1).mean(-1)[:, None, None]
    return float((conf > LAMBDA_GAMMA * mean).mean()), float((conf >= POINT_FILTER * mean).mean())


def test_kept_fractions_on_the_golden(golden) -> None:
    """sigmoid keeps most pixels of the (random-weight) golden's logits; printed with ``-s``."""
    logit = golden["conf"][0, ..., 0]
    mask, points = _kept(confidence_from_logit(logit))
    print(f"\ngolden π³ conf (sigmoid): mask keeps {mask:.3f}, point filter keeps {points:.3f}")
    assert 0.5 < mask <= 1.0 and 0.3 < points <= mask


def test_kept_fractions_on_the_oracle_match_vggt_scale() -> None:
    """On the synthetic oracle's confidence (VGGT's ``1 + exp(l)``), mapping the same logit
    ``l`` through the sigmoid keeps a comparable fraction (measured; printed with ``-s``)."""
    from swiftjax.synthetic import VGGTOracle, WorldConfig, build_world, loop_route

    poses = loop_route(width=60.0, length=40.0, corner_radius=10.0, laps=0.6)
    world = build_world(poses, WorldConfig(seed=2, num_movers=12))
    K = np.array([[120.0, 0, 69.5], [0, 120.0, 27.0], [0, 0, 1]])
    pred = VGGTOracle(world, poses, intrinsic=K, image_hw=(56, 140), tokens=False).predict_chunk(np.arange(8))
    vggt_conf = np.asarray(pred.conf, np.float64)
    logit = np.log(np.maximum(vggt_conf - 1.0, 1e-30))
    v_mask, v_points = _kept(vggt_conf)
    p_mask, p_points = _kept(confidence_from_logit(logit))
    e_mask, e_points = _kept(1.0 + np.exp(logit))
    print(
        f"\noracle, VGGT 1+exp: mask {v_mask:.3f} points {v_points:.3f}; "
        f"sigmoid of the same logit: mask {p_mask:.3f} points {p_points:.3f}"
    )
    assert abs(e_mask - v_mask) < 1e-3  # the logit round trip is faithful
    assert p_mask >= v_mask - 0.1 and p_points >= v_points - 0.1
    # and the depth used by the conversion is the oracle's, unchanged, with its K recovered
    local = _camera_points(np.broadcast_to(K, (8, 3, 3)), np.asarray(pred.depth, np.float64))
    np.testing.assert_allclose(intrinsics_from_local_points(local), np.broadcast_to(K, (8, 3, 3)), rtol=1e-7)


# ---- the whole conversion -------------------------------------------------------------------------


def test_to_chunk_prediction_on_golden(golden) -> None:
    out = {k: golden[k][0] for k in ("local_points", "conf", "camera_poses")}
    out["dino_patch_tokens"] = golden["dino_patch_tokens"]  # stored [B*S, P, C], B = 1
    pred = to_chunk_prediction(out, images=golden["input_imgs"][0])
    s, h, w = golden["conf"].shape[1:4]
    np.testing.assert_array_equal(pred.depth, golden["local_points"][0, ..., 2])
    np.testing.assert_allclose(pred.conf, 1 / (1 + np.exp(-golden["conf"][0, ..., 0].astype(np.float64))), rtol=1e-6)
    np.testing.assert_allclose(pred.extrinsic[0], np.eye(4)[:3], atol=5e-6)  # float32 rotations
    np.testing.assert_array_equal(pred.patch_tokens, golden["dino_patch_tokens"])
    assert pred.patch_tokens.shape == (s, (h // 14) * (w // 14), golden["dino_patch_tokens"].shape[-1])
    assert pred.images.shape == (s, h, w, 3) and pred.images.dtype == np.uint8


# ---- preprocessing --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "hw,expect",
    [((376, 1241), (266, 924)), ((480, 640), (434, 574)), ((154, 504), (280, 910)), ((1000, 300), (924, 266))],
)
def test_official_target_size(hw, expect) -> None:
    h, w = target_size_hw(*hw)
    assert (h, w) == expect
    assert h % 14 == 0 and w % 14 == 0 and h * w <= 255_000


def test_target_size_against_the_rule_written_out() -> None:
    """Upstream's loop, transcribed literally, on many sizes (independent of the helper)."""
    import math

    rng = np.random.default_rng(3)
    for h, w in rng.integers(20, 3000, size=(200, 2)):
        scale = math.sqrt(255000 / (w * h))
        wt, ht = w * scale, h * scale
        k, m = round(wt / 14), round(ht / 14)
        while (k * 14) * (m * 14) > 255000:
            if k / m > wt / ht:
                k -= 1
            else:
                m -= 1
        assert target_size_hw(int(h), int(w)) == (max(1, m) * 14, max(1, k) * 14)


def test_preprocess_equals_pil_lanczos() -> None:
    pil = pytest.importorskip("PIL.Image")
    rng = np.random.default_rng(4)
    frames = [rng.integers(0, 256, (188, 620, 3), dtype=np.uint8) for _ in range(2)]
    frames.append(rng.integers(0, 256, (100, 100, 3), dtype=np.uint8))  # resized to the FIRST's size
    got = preprocess(frames)
    h, w = target_size_hw(188, 620)
    assert got.shape == (3, 3, h, w)
    for img, arr in zip(frames, got):
        ref = np.asarray(pil.fromarray(img).resize((w, h), pil.Resampling.LANCZOS))
        np.testing.assert_array_equal(np.round(arr.transpose(1, 2, 0) * 255).astype(np.uint8), ref)


def test_views_without_a_pinhole_get_a_nominal_camera_with_a_warning(logged_warning) -> None:
    from inference.pi3.convert import usable_intrinsics

    good = np.array([[100.0, 0, 34.5], [0, 90.0, 20.5], [0, 0, 1]])
    K = np.stack([good, good * [[-1, 1, 1], [1, 1, 1], [1, 1, 1]], np.full((3, 3), np.nan)])
    with logged_warning(r"view\(s\) \[1, 2\] describe no pinhole camera"):
        got = usable_intrinsics(K, 42, 70)
    np.testing.assert_array_equal(got[0], good)
    f = 35.0 / np.tan(np.deg2rad(30.0))
    np.testing.assert_allclose(got[1:], [[[f, 0, 34.5], [0, f, 20.5], [0, 0, 1]]] * 2)

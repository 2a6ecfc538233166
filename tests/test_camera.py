"""swiftjax.camera: unprojection, extrinsic helpers, depth normalisation (eq. 1)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from swiftjax import camera, sim3


def _K(fx=300.0, fy=310.0, cx=7.3, cy=4.1, skew=0.0):
    return np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def test_unproject_hand_computed_pixels():
    # 2x3 depth map, integer pixel centres: x = (u - cx) d / fx, y = (v - cy) d / fy.
    K = np.array([[2.0, 0.0, 1.0], [0.0, 4.0, 0.5], [0.0, 0.0, 1.0]])
    d = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    p = np.asarray(camera.unproject(jnp.asarray(d, jnp.float32), jnp.asarray(K, jnp.float32)))
    assert p.shape == (2, 3, 3)
    np.testing.assert_allclose(p[0, 0], [(0 - 1) * 1 / 2, (0 - 0.5) * 1 / 4, 1.0])
    np.testing.assert_allclose(p[0, 2], [(2 - 1) * 3 / 2, (0 - 0.5) * 3 / 4, 3.0])
    np.testing.assert_allclose(p[1, 1], [(1 - 1) * 5 / 2, (1 - 0.5) * 5 / 4, 5.0])


def test_unproject_projects_back_with_skew_and_batch():
    rng = np.random.default_rng(0)
    K = np.stack([_K(skew=0.0), _K(fx=250, fy=240, cx=3.0, cy=2.0, skew=1.5)])
    d = rng.uniform(1, 10, size=(2, 5, 8))
    p = np.asarray(camera.unproject(d, K))  # float64 input is downcast without x64
    proj = np.einsum("bij,bhwj->bhwi", K, p)
    uv = proj[..., :2] / proj[..., 2:]
    u, v = np.meshgrid(np.arange(8), np.arange(5))
    np.testing.assert_allclose(uv[..., 0], np.broadcast_to(u, (2, 5, 8)), atol=2e-4)
    np.testing.assert_allclose(uv[..., 1], np.broadcast_to(v, (2, 5, 8)), atol=2e-4)
    np.testing.assert_allclose(p[..., 2], d, rtol=1e-6)


def test_unproject_with_cam_to_world_matrix_and_sim3_agree(x64):
    rng = np.random.default_rng(1)
    R = Rotation.random(3, random_state=2).as_matrix()
    t = rng.normal(size=(3, 3)) * 5
    E = np.concatenate([R, t[..., None]], -1)  # world-to-camera
    c2w = np.asarray(camera.camera_to_world(E))
    d = rng.uniform(1, 10, size=(3, 4, 6))
    K = np.broadcast_to(_K(), (3, 3, 3))
    p_cam = np.asarray(camera.unproject(d, K))
    expect = np.einsum("bij,bhwj->bhwi", c2w[:, :, :3], p_cam) + c2w[:, None, None, :, 3]
    got_m = np.asarray(camera.unproject(d, K, c2w))
    got_s = np.asarray(camera.unproject(d, K, camera.extrinsic_to_sim3(E)))
    got_4 = np.asarray(camera.unproject(d, K, np.concatenate([c2w, np.tile([[[0, 0, 0, 1.0]]], (3, 1, 1))], 1)))
    for got in (got_m, got_s, got_4):
        np.testing.assert_allclose(got, expect, atol=1e-10)
    # Mapping back with the extrinsic gives the camera-frame points.
    back = np.einsum("bij,bhwj->bhwi", E[:, :, :3], got_s) + E[:, None, None, :, 3]
    np.testing.assert_allclose(back, p_cam, atol=1e-10)


def test_unproject_rejects_bad_transform_shape():
    with pytest.raises(ValueError, match="cam_to_world"):
        camera.unproject(jnp.ones((2, 2)), jnp.eye(3), jnp.ones((5,)))


def test_extrinsic_helpers_round_trip(x64):
    rng = np.random.default_rng(3)
    R = Rotation.random(4, random_state=4).as_matrix()
    E = np.concatenate([R, rng.normal(size=(4, 3, 1))], -1)
    c2w = np.asarray(camera.camera_to_world(E))
    np.testing.assert_allclose(c2w[:, :, :3], np.swapaxes(R, 1, 2), atol=1e-14)
    np.testing.assert_allclose(c2w[:, :, 3], -np.einsum("bji,bj->bi", R, E[:, :, 3]), atol=1e-14)
    np.testing.assert_allclose(np.asarray(camera.world_to_camera(c2w)), E, atol=1e-14)
    S = camera.extrinsic_to_sim3(E)
    np.testing.assert_allclose(np.asarray(sim3.scale(S)), 1.0)
    np.testing.assert_allclose(np.asarray(sim3.as_matrix(S))[:, :3], c2w, atol=1e-12)
    np.testing.assert_allclose(np.asarray(camera.sim3_to_extrinsic(S)), E, atol=1e-12)
    # The scale of a Sim(3) camera pose is dropped, centre and rotation kept.
    S2 = S.at[:, 7].set(3.0)
    np.testing.assert_allclose(np.asarray(camera.sim3_to_extrinsic(S2)), E, atol=1e-12)


def test_normalize_depth_eq1_hand_computed():
    K_ref = np.array([[100.0, 0, 5], [0, 200.0, 5], [0, 0, 1]])
    K_src = np.stack([np.array([[50.0, 0, 5], [0, 400.0, 5], [0, 0, 1]]), K_ref])
    d = np.array([[[1.0, 2.0]], [[3.0, 4.0]]])  # [2, 1, 2]
    got = np.asarray(camera.normalize_depth(d, K_src, K_ref))
    # frame 0: ½(100/50 + 200/400) = 1.25; frame 1: 1.
    np.testing.assert_allclose(got, [[[1.25, 2.5]], [[3.0, 4.0]]])
    np.testing.assert_allclose(np.asarray(camera.focal_ratio(K_src, K_ref)), [1.25, 1.0])

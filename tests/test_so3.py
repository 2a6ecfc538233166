"""SO(3) operations not covered by the group harness: the nearest-rotation projection."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from swiftjax import so3


def _reference_projection(m: np.ndarray) -> np.ndarray:
    """Nearest rotation in float64 NumPy: ``U diag(1, 1, det(U V^T)) V^T``."""
    u, _, vt = np.linalg.svd(np.asarray(m, np.float64))
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt


def _cases(rng: np.random.Generator) -> dict[str, np.ndarray]:
    n = 16
    rot = Rotation.random(n, random_state=rng).as_matrix()
    noisy = rot + 0.05 * rng.normal(size=(n, 3, 3))
    reflect = rot @ np.diag([1.0, 1.0, -1.0])  # det -1: nearest rotation flips the last axis
    reflect_noisy = reflect + 0.05 * rng.normal(size=(n, 3, 3))
    rank2 = rot @ np.diag([2.0, 1.0, 0.0]) @ Rotation.random(n, random_state=rng).as_matrix()
    near_rank2 = rot @ np.diag([1.0, 0.5, 1e-6]) @ Rotation.random(n, random_state=rng).as_matrix()
    scaled = 7.5 * rot
    gauss = rng.normal(size=(n, 3, 3))
    return dict(
        rotation=rot,
        noisy=noisy,
        reflection=reflect,
        reflection_noisy=reflect_noisy,
        rank2=rank2,
        near_rank2=near_rank2,
        scaled=scaled,
        gaussian=gauss,
    )


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_project_matches_numpy_reference(dtype):
    ctx = jax.enable_x64(dtype == np.float64)
    with ctx:
        rng = np.random.default_rng(0)
        tol = 2e-5 if dtype == np.float32 else 1e-10
        project = jax.jit(so3.project)
        for name, m in _cases(rng).items():
            q = np.asarray(project(m.astype(dtype)))
            assert q.shape == (*m.shape[:-2], 4) and q.dtype == dtype, name
            assert np.all(q[..., 3] >= 0), name
            np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=tol, err_msg=name)
            r = Rotation.from_quat(np.asarray(q, np.float64)).as_matrix()
            ref = _reference_projection(m.astype(dtype))
            assert np.all(np.linalg.det(r) > 0), name
            # a minimiser of |R - m|_F over rotations (for every case, unique or not) ...
            dist = np.linalg.norm(r - m, axis=(-2, -1))
            np.testing.assert_allclose(dist, np.linalg.norm(ref - m, axis=(-2, -1)), atol=10 * tol, err_msg=name)
            # ... and the minimiser where it is unique (an exact reflection has d2 = d3).
            if name != "reflection":
                np.testing.assert_allclose(r, ref, atol=tol, err_msg=name)


def test_project_of_a_rotation_is_itself_and_batches_broadcast():
    rng = np.random.default_rng(1)
    q = Rotation.random((3 * 2), random_state=rng).as_quat().reshape(3, 1, 2, 4).astype(np.float32)
    q = np.where(q[..., 3:4] < 0, -q, q)
    got = np.asarray(so3.project(so3.as_matrix(q)))
    assert got.shape == (3, 1, 2, 4)
    np.testing.assert_allclose(got, q, atol=1e-6)
    assert so3.project(np.eye(3, dtype=np.float32)).shape == (4,)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_half_angle_reads_the_quaternion_like_log(dtype):
    """``so3.half_angle`` gives ``sin(theta/2)``, ``cos(theta/2)`` of the rotation ``q`` (either sign,
    any norm) from the quaternion alone, with ``theta = |log q|``; below the small-angle threshold
    it flags ``small``, as ``log_components`` does."""
    rng = np.random.default_rng(5)
    rotvec = rng.normal(size=(64, 3))
    angle = rng.uniform(1e-2, np.pi - 1e-3, size=64)
    angle[:4] = 3e-6  # theta^2 = 9e-12: below float32's threshold (1e-7), above float64's (1e-14)
    rotvec *= (angle / np.linalg.norm(rotvec, axis=1))[:, None]
    q = Rotation.from_rotvec(rotvec).as_quat() * rng.choice([-2.0, 0.5], size=(64, 1))  # sign and norm
    theta = np.linalg.norm(rotvec, axis=1)
    with jax.enable_x64(dtype == np.float64):
        half = jax.jit(lambda q, t: so3.half_angle(so3.split(q), t))(q.astype(dtype), (theta**2).astype(dtype))
        _, ref = jax.jit(lambda q: so3.log_components(so3.split(q)))(q.astype(dtype))
    small = np.asarray(half.small)
    np.testing.assert_array_equal(small, np.asarray(ref.small))
    assert small[:4].all() == (dtype == np.float32) and not small[4:].any()
    tol = 2e-6 if dtype == np.float32 else 1e-14
    np.testing.assert_allclose(np.asarray(half.cos_half), np.cos(theta / 2), atol=tol)
    np.testing.assert_allclose(np.asarray(half.sin_half)[~small], np.sin(theta / 2)[~small], atol=tol)
    np.testing.assert_allclose(np.asarray(half.theta)[~small], theta[~small], rtol=tol)

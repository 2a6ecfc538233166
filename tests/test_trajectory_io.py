"""KITTI / TUM trajectory files: evo parity, exact round trips, malformed input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from swiftjax.io.trajectory import (
    TrajectoryFormatError,
    matrix_to_quaternion,
    quaternion_to_matrix,
    read_kitti,
    read_tum,
    read_tum_raw,
    write_kitti,
    write_tum,
)


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    P[:, :3, 3] = rng.normal(scale=100.0, size=(n, 3))
    return P


def test_read_kitti_matches_evo(shared_dir):
    from evo.tools import file_interface

    path = shared_dir / "data/trajectories/KITTI_00_gt.txt"
    P = read_kitti(path)
    ref = np.array(file_interface.read_kitti_poses_file(str(path)).poses_se3)
    assert P.shape == (4541, 4, 4) and P.dtype == np.float64
    np.testing.assert_array_equal(P, ref)


@pytest.mark.parametrize("name", ["freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt"])
def test_read_tum_matches_evo_bitwise(shared_dir, name):
    from evo.tools import file_interface

    path = shared_dir / "data/trajectories" / name
    t, P = read_tum(path)
    ref = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_array_equal(t, ref.timestamps)
    np.testing.assert_array_equal(P, np.array(ref.poses_se3))


def test_kitti_round_trip_is_bit_exact(tmp_path):
    P = _random_poses(50)
    P[3, 0, 3] = 1e-300  # extreme magnitudes survive repr()
    P[4, 1, 3] = -123456789.123456789
    write_kitti(tmp_path / "a.txt", P)
    np.testing.assert_array_equal(read_kitti(tmp_path / "a.txt"), P)
    write_kitti(tmp_path / "b.txt", P[:, :3, :])  # [N, 3, 4] accepted too
    assert (tmp_path / "a.txt").read_text() == (tmp_path / "b.txt").read_text()


def test_tum_round_trip(tmp_path, shared_dir):
    # rows as stored: bit-exact
    src = shared_dir / "data/trajectories/freiburg1_xyz-groundtruth.txt"
    t, rows = read_tum_raw(src)
    write_tum(tmp_path / "r.txt", t, rows)
    t2, rows2 = read_tum_raw(tmp_path / "r.txt")
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_array_equal(rows2, rows)
    # matrices: translations and stamps exact, rotations to float64 round-off
    P = _random_poses(200, seed=1)
    stamps = np.linspace(1305031102.1, 1305031202.7, 200)
    write_tum(tmp_path / "m.txt", stamps, P)
    t3, P3 = read_tum(tmp_path / "m.txt")
    np.testing.assert_array_equal(t3, stamps)
    np.testing.assert_array_equal(P3[:, :3, 3], P[:, :3, 3])
    np.testing.assert_allclose(P3[:, :3, :3], P[:, :3, :3], atol=2e-15, rtol=0)


def test_quaternion_conversions_against_scipy():
    R = Rotation.random(500, random_state=3)
    # include the Shepperd branch boundaries: 180-degree turns about each axis
    extra = Rotation.from_rotvec(
        np.pi * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]]) / np.array([[1], [1], [1], [np.sqrt(2)]])
    )
    mats = np.concatenate([R.as_matrix(), extra.as_matrix(), np.eye(3)[None]])
    q = matrix_to_quaternion(mats)
    q_ref = Rotation.from_matrix(mats).as_quat()
    q_ref = np.where(q_ref[:, 3:4] < 0, -q_ref, q_ref)
    # sign is ambiguous only when qw == 0: compare as rotations there
    np.testing.assert_allclose(np.abs(np.sum(q * q_ref, axis=1)), 1.0, atol=1e-14)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(quaternion_to_matrix(q), mats, atol=1e-15)
    # non-unit quaternions are normalised, zero -> identity (evo's rule)
    np.testing.assert_allclose(quaternion_to_matrix(3.0 * q[:5]), mats[:5], atol=1e-15)
    np.testing.assert_array_equal(quaternion_to_matrix(np.zeros(4)), np.eye(3))


@pytest.mark.parametrize(
    "text, reader, message",
    [
        ("1 2 3 4 5 6 7 8 9 10 11 12\n1 2 3\n", read_kitti, ":2: a KITTI line must have 12 numbers, got 3"),
        ("# c\n\n1 2 3 4 5 6 7 8 9 10 11 x\n", read_kitti, ":3: a KITTI line must hold numbers only"),
        ("1 2 3 4 5 6 7 8 9 10 11 nan\n", read_kitti, ":1: non-finite value"),
        ("# only a comment\n", read_kitti, "no KITTI poses in file"),
        ("0 1 2 3 0 0 0 1\n0 1 2 3 0 0 0 1 9\n", read_tum, ":2: a TUM line must have 8 numbers, got 9"),
    ],
)
def test_malformed_files_name_file_and_line(tmp_path, text, reader, message):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(TrajectoryFormatError) as e:
        reader(path)
    assert str(path) in str(e.value) and message in str(e.value)


def test_comma_separated_and_missing_file(tmp_path):
    path = tmp_path / "c.txt"
    path.write_text("0.5,1,2,3,0,0,0,1\n")
    t, P = read_tum(path)
    np.testing.assert_array_equal(t, [0.5])
    np.testing.assert_array_equal(P[0], [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    with pytest.raises(FileNotFoundError, match="nope.txt"):
        read_kitti(tmp_path / "nope.txt")


def test_writers_reject_bad_input(tmp_path):
    with pytest.raises(ValueError, match=r"poses must have shape \[N, 4, 4\]"):
        write_kitti(tmp_path / "x.txt", np.zeros((3, 4)))
    bad = _random_poses(2)
    bad[1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        write_kitti(tmp_path / "x.txt", bad)
    with pytest.raises(ValueError, match="timestamps must have shape"):
        write_tum(tmp_path / "x.txt", np.zeros(3), _random_poses(2))
    assert not (tmp_path / "x.txt").exists()


def test_plot_trajectory_writes_a_png(tmp_path, shared_dir):
    from swiftjax.io.plot import plot_trajectory, top_view_axes

    P = read_kitti(shared_dir / "data/trajectories/KITTI_00_gt.txt")[::10]
    assert top_view_axes(P[:, :3, 3]) == (0, 2)  # KITTI drives in the x-z plane
    est = P.copy()
    est[:, :3, 3] += np.linspace(0, 20, len(P))[:, None]
    out = tmp_path / "traj.png"
    plot_trajectory(out, est, reference=P, loops=np.array([[400, 10], [450, 20]]), title="KITTI 00")
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    with pytest.raises(ValueError, match="loops index frames outside"):
        plot_trajectory(tmp_path / "x.png", est, loops=np.array([[0, len(est)]]))
    assert not (tmp_path / "x.png").exists()

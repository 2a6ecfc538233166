"""ATE / RPE against evo on real trajectories; Chamfer against a brute-force NumPy reference."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from _extras import require_extra
from scipy.spatial.transform import Rotation

from swiftjax.evaluation import ate, chamfer, rpe, umeyama_alignment
from swiftjax.io.trajectory import read_kitti, read_tum

evo = require_extra("evo")
from evo.core import metrics, sync
from evo.core.trajectory import PosePath3D, PoseTrajectory3D


def _perturbed(P: np.ndarray, seed: int = 0) -> np.ndarray:
    """A drifting, noisy, Sim(3)-transformed copy of ``P`` (an 'estimate')."""
    rng = np.random.default_rng(seed)
    n = len(P)
    out = P.copy()
    # random-walk rotation drift and position noise, then a global similarity
    drift = np.cumsum(rng.normal(scale=2e-4, size=(n, 3)), axis=0)
    out[:, :3, :3] = Rotation.from_rotvec(drift).as_matrix() @ P[:, :3, :3]
    out[:, :3, 3] = P[:, :3, 3] + np.cumsum(rng.normal(scale=0.02, size=(n, 3)), axis=0)
    G = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix()
    out[:, :3, :3] = G @ out[:, :3, :3]
    out[:, :3, 3] = 0.37 * out[:, :3, 3] @ G.T + np.array([12.0, -3.0, 40.0])
    return out


def _evo_ape(P_est, P_ref, correct_scale=True, align=True):
    est, ref = PosePath3D(poses_se3=list(P_est)), PosePath3D(poses_se3=list(P_ref))
    if align:
        est.align(ref, correct_scale=correct_scale)
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((ref, est))
    return m.get_all_statistics()


def _evo_rpe(P_est, P_ref, delta, all_pairs, relation, correct_scale=True, align=True):
    est, ref = PosePath3D(poses_se3=list(P_est)), PosePath3D(poses_se3=list(P_ref))
    if align:
        est.align(ref, correct_scale=correct_scale)
    m = metrics.RPE(relation, delta=delta, delta_unit=metrics.Unit.frames, all_pairs=all_pairs)
    m.process_data((ref, est))
    return m.get_all_statistics()


def _assert_stats(ours, ref: dict, rtol=1e-9):
    for key in ("rmse", "mean", "median", "std", "min", "max", "sse"):
        got = getattr(ours, key)
        assert got == pytest.approx(ref[key], rel=rtol, abs=1e-12), key


@pytest.fixture(scope="module")
def kitti(shared_dir):
    ref = read_kitti(shared_dir / "data/trajectories/KITTI_00_gt.txt")
    return ref, _perturbed(ref)


@pytest.mark.parametrize("align", ["sim3", "se3", "none"])
def test_ate_matches_evo_on_kitti00(kitti, align):
    ref, est = kitti
    if align == "none":  # an unaligned comparison only makes sense in the reference frame
        est = ref.copy()
        est[:, :3, 3] += np.linspace(0, 5, len(ref))[:, None] * np.array([1.0, 0.1, -0.3])
    ours = ate(est, ref, align=align)
    theirs = _evo_ape(est, ref, correct_scale=(align == "sim3"), align=(align != "none"))
    _assert_stats(ours, theirs)
    assert ours.errors.shape == (len(ref),)
    if align == "sim3":
        assert ours.scale == pytest.approx(1 / 0.37, rel=0.05)
        assert 0.1 < ours.rmse < 100.0  # the perturbation is visible after global alignment


def test_ate_accepts_positions_and_is_exact_for_similar_trajectories(kitti):
    ref, _ = kitti
    G = Rotation.from_rotvec([0.1, 2.0, -0.4]).as_matrix()
    est = 3.3 * ref[:, :3, 3] @ G.T + np.array([1.0, 2.0, 3.0])
    r = ate(est, ref[:, :3, 3])
    assert r.rmse < 1e-9 and r.scale == pytest.approx(1 / 3.3, rel=1e-12)
    np.testing.assert_allclose(r.rotation, G.T, atol=1e-12)


def test_ate_matches_evo_on_tum_with_timestamp_association(shared_dir):
    d = shared_dir / "data/trajectories"
    t_ref, P_ref = read_tum(d / "freiburg1_xyz-groundtruth.txt")
    t_est, P_est = read_tum(d / "freiburg1_xyz-rgbdslam.txt")
    ref = PoseTrajectory3D(poses_se3=list(P_ref), timestamps=t_ref)
    est = PoseTrajectory3D(poses_se3=list(P_est), timestamps=t_est)
    ref_a, est_a = sync.associate_trajectories(ref, est, max_diff=0.01)
    A_ref, A_est = np.array(ref_a.poses_se3), np.array(est_a.poses_se3)
    ours = ate(A_est, A_ref)
    est_al = copy.deepcopy(est_a)
    est_al.align(ref_a, correct_scale=True)
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((ref_a, est_al))
    _assert_stats(ours, m.get_all_statistics())
    for delta, all_pairs in [(1, False), (10, True)]:
        ours_r = rpe(A_est, A_ref, delta=delta, all_pairs=all_pairs)
        for rel, field in [
            (metrics.PoseRelation.translation_part, "translation"),
            (metrics.PoseRelation.rotation_angle_deg, "rotation_deg"),
        ]:
            m = metrics.RPE(rel, delta=delta, delta_unit=metrics.Unit.frames, all_pairs=all_pairs)
            m.process_data((ref_a, est_al))
            _assert_stats(getattr(ours_r, field), m.get_all_statistics(), rtol=1e-9)


@pytest.mark.parametrize("delta, all_pairs, align", [(1, False, "sim3"), (10, False, "none"), (7, True, "se3")])
def test_rpe_matches_evo_on_kitti00(kitti, delta, all_pairs, align):
    ref, est = kitti
    ref, est = ref[:1500], est[:1500]  # evo's per-pair Python loop is the slow part
    if align == "none":
        est = _perturbed(ref, seed=3)
        # undo the global similarity's scale so unaligned RPE is meaningful
        est[:, :3, 3] /= 0.37
    ours = rpe(est, ref, delta=delta, all_pairs=all_pairs, align=align)
    kw = dict(correct_scale=(align == "sim3"), align=(align != "none"))
    t = _evo_rpe(est, ref, delta, all_pairs, metrics.PoseRelation.translation_part, **kw)
    r = _evo_rpe(est, ref, delta, all_pairs, metrics.PoseRelation.rotation_angle_deg, **kw)
    _assert_stats(ours.translation, t, rtol=1e-9)
    _assert_stats(ours.rotation_deg, r, rtol=1e-9)
    n_pairs = len(ref) - delta if all_pairs else (len(ref) - 1) // delta
    assert ours.pairs.shape == (n_pairs, 2)


def test_umeyama_alignment_matches_evo_geometry():
    from evo.core.geometry import umeyama_alignment as evo_umeyama

    rng = np.random.default_rng(5)
    x = rng.normal(scale=50.0, size=(500, 3)) + 1000.0
    G = Rotation.random(random_state=1).as_matrix()
    y = 0.8 * x @ G.T + np.array([3.0, 4.0, 5.0]) + rng.normal(scale=0.5, size=x.shape)
    for mode, with_scale in [("sim3", True), ("se3", False)]:
        R, t, s = umeyama_alignment(x, y, mode)
        R2, t2, s2 = evo_umeyama(x.T, y.T, with_scale)
        np.testing.assert_allclose(R, R2, atol=1e-12)
        np.testing.assert_allclose(t, t2, rtol=1e-9, atol=1e-9)
        assert s == pytest.approx(s2, rel=1e-12)


def test_bad_inputs_raise():
    P = np.tile(np.eye(4), (10, 1, 1))
    P[:, 0, 3] = np.arange(10.0)
    with pytest.raises(ValueError, match="estimated has 10 poses but reference has 9"):
        ate(P, P[:9])
    with pytest.raises(ValueError, match="align must be"):
        ate(P, P, align="sim(3)")
    with pytest.raises(ValueError, match="degenerate"):  # collinear positions
        ate(P, P)
    with pytest.raises(ValueError, match=r"positions \[N, 3\]"):
        ate(np.zeros((10, 2)), P)
    with pytest.raises(ValueError, match="delta must be an integer"):
        rpe(P, P, delta=0, align="none")
    with pytest.raises(ValueError, match="no pose pair"):
        rpe(P, P, delta=10, align="none")


# ------------------------------------------------------------------------------ chamfer


def _brute_nn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)).min(axis=1)


def test_chamfer_matches_brute_force():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(700, 3))
    b = rng.normal(size=(500, 3)) * 1.3 + 0.2
    r = chamfer(a, b, max_points=None)
    acc, comp = _brute_nn(a, b).mean(), _brute_nn(b, a).mean()
    assert r.accuracy == pytest.approx(acc, rel=1e-12)
    assert r.completeness == pytest.approx(comp, rel=1e-12)
    assert r.chamfer == pytest.approx(0.5 * (acc + comp), rel=1e-12)
    assert r.accuracy_median == pytest.approx(np.median(_brute_nn(a, b)), rel=1e-12)
    assert (r.num_pred, r.num_gt) == (700, 500)


def test_chamfer_subsampling_and_edge_cases():
    rng = np.random.default_rng(1)
    a = rng.uniform(size=(5000, 3))
    r1 = chamfer(a, a, max_points=1000, seed=3)
    assert r1.num_pred == 1000 and r1.num_gt == 1000
    assert r1.chamfer > 0  # independent subsamples of the same cloud
    assert chamfer(a, a, max_points=1000, seed=3) == r1  # deterministic in the seed
    assert chamfer(a, a, max_points=None).chamfer == 0.0
    with_nan = np.concatenate([a[:10], [[np.nan, 0, 0]]])
    assert chamfer(with_nan, a[:10], max_points=None).num_pred == 10
    with pytest.raises(ValueError, match="pred_points has no finite points"):
        chamfer(np.full((3, 3), np.nan), a)
    with pytest.raises(ValueError, match=r"gt_points must be \[N, 3\]"):
        chamfer(a, a[:, :2])


# ------------------------------------------------------------- rotations and timestamps


def test_non_orthonormal_rotations_are_refused_or_fixed(kitti):
    """A scaled 'rotation' inflated RPE silently (3.19 instead of 0.238): now refused, naming the
    pose; orthonormalize() recovers the rotation (and the original RPE)."""
    from swiftjax.evaluation import check_rotations, orthonormalize

    ref = kitti[0][:200]
    est = _perturbed(ref)
    good = rpe(est, ref).translation.rmse
    bad = est.copy()
    bad[50:, :3, :3] *= 1.05
    with pytest.raises(ValueError, match=r"estimated: pose 50 \(of 200\) has a rotation that is not orthonormal"):
        rpe(bad, ref)
    reflect = est.copy()
    reflect[7, :3, 0] *= -1
    with pytest.raises(ValueError, match="pose 7 .*det -1"):
        check_rotations(reflect, "estimated")
    fixed, change = orthonormalize(bad)
    assert change == pytest.approx(0.05, rel=0.05)
    assert rpe(fixed, ref).translation.rmse == pytest.approx(good, rel=1e-6)  # KITTI itself is orthonormal to ~1e-7
    assert check_rotations(ref, "reference") < 1e-6  # the real KITTI file passes


def _evo_associate(t_ref, t_est, max_diff, offset):
    n_ref, n_est = len(t_ref), len(t_est)
    ref = PoseTrajectory3D(
        positions_xyz=np.c_[np.arange(n_ref), np.zeros((n_ref, 2))],
        orientations_quat_wxyz=np.tile([1.0, 0, 0, 0], (n_ref, 1)),
        timestamps=t_ref,
    )
    est = PoseTrajectory3D(
        positions_xyz=np.c_[np.arange(n_est), np.zeros((n_est, 2))],
        orientations_quat_wxyz=np.tile([1.0, 0, 0, 0], (n_est, 1)),
        timestamps=t_est,
    )
    r, e = sync.associate_trajectories(ref, est, max_diff=max_diff, offset_2=offset)
    return r.positions_xyz[:, 0].astype(int), e.positions_xyz[:, 0].astype(int)


@pytest.mark.parametrize("case", ["same", "shuffled", "subsampled", "offset", "jitter", "longer_est", "ties"])
def test_associate_matches_evo(case):
    from swiftjax.evaluation import associate

    rng = np.random.default_rng(hash(case) % 2**32)
    t_ref = np.round(1000.0 + np.cumsum(rng.uniform(0.02, 0.05, 120)), 4)
    t_est, max_diff, offset = t_ref.copy(), 0.01, 0.0
    if case == "shuffled":
        t_est = t_ref[rng.permutation(len(t_ref))]
    elif case == "subsampled":
        t_est = t_ref[::3] + rng.uniform(-0.008, 0.008, len(t_ref[::3]))
    elif case == "offset":
        t_est, offset = t_ref - 1000.0, 1000.0
    elif case == "jitter":
        t_est = t_ref + rng.normal(scale=0.01, size=len(t_ref))
        max_diff = 0.015
    elif case == "longer_est":
        t_est = np.sort(np.r_[t_ref, t_ref[:-1] + 0.013])
    elif case == "ties":
        t_ref = np.arange(0.0, 10.0, 0.5)
        t_est = np.arange(0.25, 10.0, 0.5)[:12]
        max_diff = 0.25
    want = _evo_associate(t_ref, t_est, max_diff, offset)
    got = associate(t_ref, t_est, max_diff=max_diff, offset=offset)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_tum_files_are_associated_by_timestamp_in_the_cli(tmp_path, capsys, shared_dir):
    """A shuffled TUM estimate gave ATE 0.249 instead of 0.161 (rows paired), and a +1000 s
    offset was a perfect match: now both are associated by time as evo does."""
    from swiftjax import cli
    from swiftjax.io.trajectory import read_tum_raw, write_tum

    d = shared_dir / "data/trajectories"
    ref_file, est_file = d / "freiburg1_xyz-groundtruth.txt", d / "freiburg1_xyz-rgbdslam.txt"
    t_ref, P_ref = read_tum(ref_file)
    t_est, P_est = read_tum(est_file)
    ref_a, est_a = sync.associate_trajectories(
        PoseTrajectory3D(poses_se3=list(P_ref), timestamps=t_ref),
        PoseTrajectory3D(poses_se3=list(P_est), timestamps=t_est),
        max_diff=0.01,
    )
    want = f"{ate(np.array(est_a.poses_se3), np.array(ref_a.poses_se3)).rmse:.3g}"
    stamps, rows = read_tum_raw(est_file)
    perm = np.random.default_rng(0).permutation(len(stamps))
    write_tum(tmp_path / "shuffled.txt", stamps[perm], rows[perm])
    write_tum(tmp_path / "late.txt", stamps + 1000.0, rows)

    def run(est, *extra):
        code = cli.main(["evaluate", str(ref_file), str(est), "--format", "tum", *extra])
        return code, capsys.readouterr()

    code, out = run(est_file)
    assert code == 0 and want in out.out and f"associated {len(ref_a.timestamps)} poses" in out.out
    code, out = run(tmp_path / "shuffled.txt")
    assert code == 0 and want in out.out
    code, out = run(tmp_path / "late.txt")
    assert code == 2 and "only 0 of the" in out.err and "late.txt" in out.err and ref_file.name in out.err
    code, out = run(tmp_path / "late.txt", "--offset=-1000")
    assert code == 0 and want in out.out

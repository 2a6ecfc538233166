"""``swiftjax evaluate REF EST``: evo's order, refused when the files' headers say it is swapped,
TUM rows taken in time order and repeated times refused (issues 25 #14, 26 #1)."""

from __future__ import annotations

import numpy as np
import pytest

from swiftjax import cli, evaluation
from swiftjax.io import trajectory


def _run(capsys, *argv):
    code = cli.main(["evaluate", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def _one_line_error(code, err, *fragments):
    assert code == 2, err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("swiftjax: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    for frag in fragments:
        assert frag in lines[0], lines[0]


def _route(n=60, seed=0):
    rng = np.random.default_rng(seed)
    P = np.tile(np.eye(4), (n, 1, 1))
    s = np.linspace(0, 2 * np.pi, n)
    P[:, :3, 3] = np.stack([20 * np.cos(s), 10 * np.sin(s), 0.3 * s**2], axis=1)
    angles = np.cumsum(rng.normal(scale=0.05, size=n))
    c, si = np.cos(angles), np.sin(angles)
    P[:, 0, 0], P[:, 0, 2], P[:, 2, 0], P[:, 2, 2] = c, si, -si, c
    return P


def _run_files(tmp_path):
    """A run's poses_kitti.txt (up to scale: 0.1x the metric route, with noise) and its
    ground_truth_kitti.txt, with the headers swiftjax writes."""
    from swiftjax.pipeline import export, results

    gt = _route()
    est = gt.copy()
    est[:, :3, 3] = 0.1 * gt[:, :3, 3] + np.random.default_rng(1).normal(scale=0.05, size=(len(gt), 3))
    run = tmp_path / "run"
    run.mkdir()
    export._write_trajectories(run, est, np.arange(len(est), dtype=float), results.UP_TO_SCALE, "frame index")
    trajectory.write_kitti(
        run / "ground_truth_kitti.txt",
        gt,
        header=["the ground truth given to this run: camera-to-world poses as given (metres, its own frame)"],
    )
    return run, gt, est


def test_reference_comes_first_as_in_evo(capsys, tmp_path):
    """`evaluate ground_truth_kitti.txt poses_kitti.txt` printed 0.0453 (the estimate's units)
    for a true 0.393: the reference is now the first argument and the table is in its unit."""
    run, gt, est = _run_files(tmp_path)
    code, out, err = _run(capsys, run / "ground_truth_kitti.txt", run / "poses_kitti.txt")
    assert code == 0, err
    want = evaluation.ate(est, gt).rmse  # metres of the ground truth
    swapped = evaluation.ate(gt, est).rmse  # what the old order printed
    assert want > 5 * swapped
    assert f"{want:.3g}" in out and f"{swapped:.3g}" not in out
    assert "ATE translation (m)" in out and "reference: " in out and "ground_truth_kitti.txt" in out


def test_a_swapped_pair_is_refused_by_its_headers(capsys, tmp_path):
    run, _, _ = _run_files(tmp_path)
    code, _, err = _run(capsys, run / "poses_kitti.txt", run / "ground_truth_kitti.txt")
    _one_line_error(code, err, "poses_kitti.txt", "is a swiftjax estimate", "reference first")
    # only the ground truth's header tells (another tool's estimate, no header)
    trajectory.write_kitti(tmp_path / "other_est.txt", trajectory.read_kitti(run / "poses_kitti.txt"))
    code, _, err = _run(capsys, tmp_path / "other_est.txt", run / "ground_truth_kitti.txt")
    _one_line_error(code, err, "ground_truth_kitti.txt", "is a ground truth", "reference first")
    code, _, err = _run(capsys, run, run / "poses_kitti.txt")
    _one_line_error(code, err, str(run), "is a directory")


def _tum_pair(tmp_path):
    gt = _route(80, seed=2)
    t = 0.1 * np.arange(len(gt))
    est = gt.copy()
    est[:, :3, 3] += np.random.default_rng(3).normal(scale=0.2, size=(len(gt), 3))
    trajectory.write_tum(tmp_path / "ref.txt", t, gt)
    return t, gt, est


def test_tum_rows_out_of_time_order_give_the_sorted_rpe(capsys, tmp_path):
    """Shuffled TUM rows paired RPE neighbours in file order (RPE 0.108 instead of 0.105)."""
    t, gt, est = _tum_pair(tmp_path)
    perm = np.random.default_rng(4).permutation(len(t))
    trajectory.write_tum(tmp_path / "shuffled.txt", t[perm], est[perm])
    code, out, err = _run(capsys, tmp_path / "ref.txt", tmp_path / "shuffled.txt", "--format", "tum")
    assert code == 0, err
    want = evaluation.rpe(est, gt)  # time order
    wrong = evaluation.rpe(est[perm], gt[perm])  # file order
    assert abs(want.translation.rmse - wrong.translation.rmse) > 1e-3
    assert f"{want.translation.rmse:.3g}" in out and "not in time order" in out


def test_tum_repeated_timestamps_are_refused(capsys, tmp_path):
    """A repeated stamp paired one reference pose twice (ATE 0.113 instead of 0.073)."""
    t, gt, est = _tum_pair(tmp_path)
    t_dup = t.copy()
    t_dup[11] = t_dup[10]
    trajectory.write_tum(tmp_path / "dup.txt", t_dup, est)
    code, _, err = _run(capsys, tmp_path / "ref.txt", tmp_path / "dup.txt", "--format", "tum")
    _one_line_error(code, err, "dup.txt", "poses 11 and 12", "same timestamp 1.0")
    trajectory.write_tum(tmp_path / "flat.txt", np.zeros(len(t)), est)  # all-equal times: not "collinear"
    code, _, err = _run(capsys, tmp_path / "ref.txt", tmp_path / "flat.txt", "--format", "tum")
    _one_line_error(code, err, "flat.txt", "same timestamp")


def test_huge_positions_are_not_called_collinear(capsys, tmp_path):
    """Positions x 1e300 were reported as a degenerate (collinear) alignment."""
    gt = _route()
    big = gt.copy()
    big[:, :3, 3] *= 1e300
    trajectory.write_kitti(tmp_path / "ref.txt", gt)
    trajectory.write_kitti(tmp_path / "big.txt", big)
    code, _, err = _run(capsys, tmp_path / "ref.txt", tmp_path / "big.txt")
    _one_line_error(code, err, "big.txt", "estimated positions reach", "too large")
    assert "collinear" not in err


def test_messages_show_plain_numbers_not_numpy_reprs(capsys, tmp_path):
    rows = "".join(f"{1000.0 + k} {k} 0 {k * k} 0 0 0 {0.5 if k == 2 else 1}\n" for k in range(5))
    (tmp_path / "q.txt").write_text(rows)
    trajectory.write_tum(tmp_path / "ref.txt", 1000.0 + np.arange(5.0), _route(5))
    code, _, err = _run(capsys, tmp_path / "ref.txt", tmp_path / "q.txt", "--format", "tum")
    _one_line_error(code, err, "q.txt", "pose 2", "time 1002.0")
    assert "np.float64" not in err
    from swiftjax import options
    from swiftjax.pipeline import PipelineConfig

    with pytest.raises(options.OptionError) as e:
        PipelineConfig(depth_threshold=np.float64(-1000.0))
    assert "-1000.0 is out of range" in str(e.value) and "np.float64" not in str(e.value)


def test_quiet_keeps_the_table_and_drops_the_messages(capsys, tmp_path):
    """``swiftjax --quiet``: the result (the table) is printed, the information line is not;
    without it the same table and the line, on stdout as before the logger."""
    t, gt, est = _tum_pair(tmp_path)
    perm = np.random.default_rng(4).permutation(len(t))
    trajectory.write_tum(tmp_path / "shuffled.txt", t[perm], est[perm])
    argv = ["evaluate", str(tmp_path / "ref.txt"), str(tmp_path / "shuffled.txt"), "--format", "tum"]
    assert cli.main(argv) == 0
    loud = capsys.readouterr()
    assert cli.main(["--quiet", *argv]) == 0
    quiet = capsys.readouterr()
    line = f"swiftjax: {tmp_path / 'shuffled.txt'}: rows are not in time order; taken in time order"
    assert line in loud.out.splitlines() and "not in time order" not in quiet.out + quiet.err
    assert quiet.out.splitlines() == [ln for ln in loud.out.splitlines() if ln != line and "associated" not in ln]
    assert cli.main(["--verbose", *argv]) == 0
    assert "swiftjax: compilation cache" in capsys.readouterr().out  # a debug message

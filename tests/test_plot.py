"""trajectory.png and points.png (issue 26 item 10): the run's own unit on the axes, one
axis convention for both pictures (never mirrored), the trajectory without loop closure, the
ground truth visible under the estimate, the accepted loop closures drawn."""

from __future__ import annotations

import numpy as np
import pytest

from swiftjax.io import plot
from swiftjax.io.ply import read_ply
from swiftjax.pipeline import report


def _exported(out, result):
    cloud = read_ply(out / "points.ply")
    step = max(1, len(cloud.points) // 20_000)
    return {
        "cam_to_world": result.cam_to_world,
        "cam_to_world_no_loops": result.cam_to_world_no_loops,
        "sample_points": cloud.points[::step],
        "sample_colors": cloud.colors[::step],
        "num_points": len(cloud.points),
    }


def _lines(ax):
    return {ln.get_label(): ln for ln in ax.get_lines()}


def test_axis_label_follows_the_unit():
    assert plot.axis_label(0, None) == "x [up to scale]" and plot.axis_label(2, "up to scale") == "z [up to scale]"
    assert plot.axis_label(2, "m") == "z [m]" and plot.axis_label(1, "metres") == "y [m]"


@pytest.mark.parametrize("unit", [None, "m"])
def test_run_pictures_share_axes_and_unit(small_loop_run, tmp_path, unit):
    out, result = small_loop_run
    exported = _exported(out, result)
    from swiftjax.io import trajectory

    ground_truth = trajectory.read_kitti(out / "ground_truth_kitti.txt")
    traj = report._plot(tmp_path / "t.png", exported, ground_truth, result.loop_candidates, unit).axes[0]
    pts = report._plot_points(tmp_path / "p.png", exported, result.loop_candidates, unit).axes[0]
    want = "[m]" if unit else "[up to scale]"
    for ax in (traj, pts):
        assert ax.get_xlabel().endswith(want) and ax.get_ylabel().endswith(want), (ax.get_xlabel(), ax.get_ylabel())
        assert not ax.get_xlabel().startswith("-") and not ax.xaxis_inverted()
    assert traj.get_xlabel() == pts.get_xlabel() and traj.get_ylabel() == pts.get_ylabel()
    est = result.cam_to_world[:, :3, 3]
    a, b = plot.top_view_axes(est)
    cams = _lines(pts)["cameras"]
    np.testing.assert_allclose(cams.get_xdata(), est[:, a])  # the same coordinates, not mirrored
    lines = _lines(traj)
    np.testing.assert_allclose(lines["with loop closure"].get_xdata(), est[:, a])
    free = lines["without loop closure"]
    np.testing.assert_allclose(free.get_ydata(), result.cam_to_world_no_loops[:, b, 3])
    # the ground truth, aligned onto the estimate: close to it, drawn wider and below it
    gt_line, est_line = lines["ground truth"], lines["with loop closure"]
    assert np.abs(np.asarray(gt_line.get_xdata()) - est[:, a]).max() < 0.2 * np.ptp(est[:, a])
    assert gt_line.get_linewidth() >= 3 * est_line.get_linewidth() and gt_line.get_zorder() < est_line.get_zorder()
    n_acc = sum(bool(r.get("accepted", True)) for r in result.loop_candidates)
    assert n_acc >= 1 and f"loop closures ({n_acc})" in lines and f"loop closures ({n_acc})" in _lines(pts)
    loops = [ln for ln in traj.get_lines() if ln.get_color() == "tab:red"]
    assert len(loops) == n_acc and all(ln.get_zorder() > est_line.get_zorder() for ln in loops)
    assert {t.get_text() for t in traj.get_legend().get_texts()} >= {
        "ground truth",
        "with loop closure",
        "without loop closure",
        f"loop closures ({n_acc})",
    }


def test_points_picture_is_never_mirrored(tmp_path):
    """Cameras whose y axis points up (not OpenCV's down): the old picture mirrored x ('-x')."""
    n = 30
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, 3] = np.c_[np.linspace(0, 10, n), np.zeros(n), np.linspace(0, 5, n) ** 1.5]
    c2w[:, 1, 1] = c2w[:, 2, 2] = -1.0  # y up, z backwards
    pts = np.random.default_rng(0).normal(size=(500, 3)) * 3
    ax = plot.plot_points(tmp_path / "p.png", pts, np.full((500, 3), 128, np.uint8), c2w).axes[0]
    assert ax.get_xlabel() == "x [up to scale]"
    np.testing.assert_allclose(_lines(ax)["cameras"].get_xdata(), c2w[:, 0, 3])

"""The camera options through the whole pipeline: known intrinsics, metric scale, masks.

One module-scoped run on part of the small synthetic loop route (test_pipeline.py's chunk
and image shapes; no loop closure, to keep the test short) with a user-written intrinsics
file, --metric camera-height=1.65, --drop-sky and a mask folder that blanks every frame of
the first overlap.
"""

from __future__ import annotations

import dataclasses
import json
import logging

import numpy as np
import pytest

from swiftjax import evaluation, pipeline
from swiftjax.io import ply
from swiftjax.synthetic import demo
from swiftjax.synthetic.routes import loop_route

CONFIG = pipeline.PipelineConfig(
    chunk_size=40,
    overlap=15,
    loop_min_separation=60,
    loop_nms_radius=10,
    point_stride=2,
    colmap_max_points=5_000,
    loop_closure=False,
    colmap_text=True,
)
IMAGE_HW = (42, 140)


@pytest.fixture(scope="module")
def small_run():
    poses = loop_route(width=60.0, length=40.0, corner_radius=10.0, laps=0.6)
    return demo.trajectory_run(poses, seed=3, image_hw=IMAGE_HW)


def _spy(predictor, calls: list):
    """``predictor`` as the pipeline sees it, appending the frames of each ``predict`` call to ``calls``."""

    class Spy:
        num_frames = predictor.num_frames

        def predict(self, f):
            calls.append(f)
            return predictor.predict(f)

        def __getattr__(self, name):
            return getattr(predictor, name)

    return Spy()


def _write_masks(folder, n, blank):
    from PIL import Image

    folder.mkdir()
    for k in range(n):
        keep = np.full(IMAGE_HW, 0 if k in blank else 255, np.uint8)
        keep[-6:, :20] = 0  # a box in the bottom-left corner of every frame
        Image.fromarray(keep).save(folder / f"{k:06d}.png")


@pytest.fixture(scope="module")
def camera_run(small_run, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("camera")
    K = small_run.predictor.oracle.K
    (tmp / "K.txt").write_text(
        f"# the world's camera\n{float(K[0, 0])!r} {float(K[1, 1])!r} {float(K[0, 2])!r} {float(K[1, 2])!r}\n"
    )
    n = small_run.predictor.num_frames
    overlap0 = set(range(25, 40))  # chunk 0's last / chunk 1's first 15 frames
    _write_masks(tmp / "masks", n, overlap0)
    config = dataclasses.replace(
        CONFIG,
        intrinsics=str(tmp / "K.txt"),
        metric="camera-height=1.65",
        drop_sky=True,
        mask_dir=str(tmp / "masks"),
    )
    caught: list[str] = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = lambda record: caught.append(record.getMessage())  # the run's warnings
    logging.getLogger("swiftjax").addHandler(handler)
    try:
        res = pipeline.reconstruct(
            small_run.predictor,
            tmp / "run",
            config,
            ground_truth=small_run.ground_truth,
            progress=False,
            log=lambda s: None,
        )
    finally:
        logging.getLogger("swiftjax").removeHandler(handler)
    res.caught = caught
    res.config = config
    res.K = K
    return res


def test_a_fully_masked_overlap_falls_back_to_the_poses_with_a_warning(camera_run):
    assert any("chunks 0/1" in w and "the mask keeps 0.00% of its pixels" in w for w in camera_run.caught)
    assert camera_run.metrics["alignment"]["pose_fallbacks"] == 1


def test_metric_outputs_are_in_metres(camera_run, small_run):
    m = camera_run.metrics
    assert m["unit"] == "metres" and m["metric_scale"]["method"] == "camera-height=1.65"
    assert abs(m["scale_error"]) < 0.03
    gt = small_run.ground_truth[:, :3, 3]
    # without any alignment scale the trajectory is metric: the SE(3)-aligned ATE is small
    assert m["ate_rmse_se3"] == pytest.approx(evaluation.ate(camera_run.cam_to_world[:, :3, 3], gt, "se3").rmse)
    assert m["ate_rmse_se3"] < 1.0
    for name in ("poses_kitti.txt", "poses_tum.txt"):  # the headers say so
        head = [ln for ln in (camera_run.run_dir / name).read_text().splitlines() if ln.startswith("#")]
        assert any("metres" in ln for ln in head) and not any("up to scale" in ln for ln in head)
    on_disk = json.loads((camera_run.run_dir / "metrics.json").read_text())
    assert on_disk["unit"] == "metres" and on_disk["metric_scale"]["metres_per_unit"] == pytest.approx(
        m["metric_scale"]["metres_per_unit"]
    )
    # the exported cloud is metric too: its points lie on the true surfaces within a metre or so
    xyz = ply.read_ply(camera_run.run_dir / "points.ply").points
    oracle = small_run.predictor.oracle
    true_pts, valid = oracle.true_world_points(np.arange(0, small_run.predictor.num_frames, 5))
    a = evaluation.ate(camera_run.cam_to_world[:, :3, 3], gt, "se3")  # rotation + translation only
    cloud = xyz.astype(np.float64) @ a.rotation.T + a.translation
    ch = evaluation.chamfer(cloud, true_pts[valid][::7], max_points=20_000)
    assert ch.accuracy_median < 0.5


def test_known_intrinsics_are_the_reference_and_the_colmap_camera(camera_run):
    head = (camera_run.run_dir / "intrinsics.txt").read_text()
    assert "K_ref = the given intrinsics (plain file" in head
    cams = [
        ln
        for ln in (camera_run.run_dir / "colmap" / "sparse" / "0" / "cameras.txt").read_text().splitlines()
        if ln and not ln.startswith("#")
    ]
    assert len(cams) == 1
    _, model, w, h, *p = cams[0].split()
    K = camera_run.K
    assert model == "PINHOLE" and (int(w), int(h)) == (IMAGE_HW[1], IMAGE_HW[0])
    np.testing.assert_allclose([float(v) for v in p], [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5], rtol=1e-12)


def test_scale_priors_in_the_pose_graph_rerun_only_the_graph_and_export(camera_run, small_run):
    """--metric-combine prior on the same run directory: a pose-graph option, so no chunk is
    predicted again; the outputs are metric, and the chain's scale follows each chunk's road.
    (Before the test below, which changes a mask file's time: the run directory is then refused.)"""
    calls = []

    config = dataclasses.replace(camera_run.config, metric_combine="prior")
    res = pipeline.reconstruct(
        _spy(small_run.predictor, calls),
        camera_run.run_dir,
        config,
        ground_truth=small_run.ground_truth,
        progress=False,
        log=lambda s: None,
    )
    assert not calls
    m = res.metrics
    assert m["unit"] == "metres" and m["metric_scale"]["combine"] == "prior"
    assert m["metric_scale"]["chunks_with_prior"] == m["metric_scale"]["chunks_voting"] == res.num_chunks
    assert m["pose_graph"]["metric_prior"]["no_loops_solve"]["converged"]
    assert abs(m["scale_error"]) < 0.03 and m["ate_rmse_se3"] < 1.0
    assert m["metric_scale"]["metres_per_unit"] == pytest.approx(res.chunk_poses[0, 7])
    head = [ln for ln in (res.run_dir / "poses_kitti.txt").read_text().splitlines() if ln.startswith("#")]
    assert any("metres" in ln for ln in head)


def test_changed_masks_or_intrinsics_refuse_to_resume(camera_run, small_run):
    import os

    from swiftjax.pipeline.rundir import RunDirError

    mask = camera_run.run_dir.parent / "masks" / "000003.png"
    os.utime(mask, ns=(0, 0))
    with pytest.raises(RunDirError, match="different input"):
        pipeline.reconstruct(
            small_run.predictor,
            camera_run.run_dir,
            camera_run.config,
            ground_truth=small_run.ground_truth,
            progress=False,
        )


def test_bad_options_fail_before_any_work(small_run, tmp_path):
    (tmp_path / "K.txt").write_text("300 300 900 20\n")  # cx outside the 140-pixel-wide image
    calls = []
    spy = _spy(small_run.predictor, calls)  # every call below must fail before predicting

    with pytest.raises(ValueError, match="principal point .* outside the 140x42 image"):
        pipeline.reconstruct(
            spy, tmp_path / "a", dataclasses.replace(CONFIG, intrinsics=str(tmp_path / "K.txt")), progress=False
        )
    with pytest.raises(ValueError, match="--metric gt needs the ground-truth poses"):
        pipeline.reconstruct(spy, tmp_path / "b", dataclasses.replace(CONFIG, metric="gt"), progress=False)
    with pytest.raises(ValueError, match="lacks"):
        (tmp_path / "m").mkdir()
        pipeline.reconstruct(
            spy, tmp_path / "c", dataclasses.replace(CONFIG, mask_dir=str(tmp_path / "m")), progress=False
        )
    with pytest.raises(ValueError, match="--metric must be"):
        dataclasses.replace(CONFIG, metric="height=2")
    assert not calls


def test_cli_demo_refuses_a_bad_intrinsics_file_in_one_line(tmp_path, capsys):
    from swiftjax.cli import main

    (tmp_path / "K.txt").write_text("1 RADIAL 518 154 300 259 77 0.1 0.01\n")
    code = main(
        [
            "demo",
            "--frames",
            "50",
            "--out",
            str(tmp_path / "run"),
            "--intrinsics",
            str(tmp_path / "K.txt"),
            "--no-progress",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "'RADIAL' is not supported" in err[0]


def test_cli_refuses_a_bad_metric_combine_in_one_line(tmp_path, capsys):
    from swiftjax.cli import main

    code = main(
        [
            "demo",
            "--frames",
            "50",
            "--out",
            str(tmp_path / "run"),
            "--metric",
            "camera-height=1.65",
            "--metric-combine",
            "mean",
            "--no-progress",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--metric-combine" in err[0] and "median, prior" in err[0]
    assert not (tmp_path / "run").exists()

"""Self-describing outputs: TUM timestamps from the source, headers, points.png."""

from __future__ import annotations

import numpy as np
import pytest
from _extras import require_extra

from swiftjax.io import images


def _video(path, n, fps):
    cv2 = pytest.importorskip("cv2")
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (32, 24))
    assert vw.isOpened()
    for _ in range(n):
        vw.write(np.full((24, 32, 3), 128, np.uint8))
    vw.release()


def test_video_timestamps_are_frame_index_over_fps_with_stride(tmp_path):
    _video(tmp_path / "drive.avi", 12, 25.0)
    ts, note = images.list_frames(tmp_path / "drive.avi", stride=3).timestamps()
    np.testing.assert_allclose(ts, np.array([0, 3, 6, 9]) / 25.0, rtol=1e-12)
    assert "25 fps" in note and "stride 3" in note


def test_image_folder_timestamps(tmp_path):
    for k in range(6):
        (tmp_path / f"{k:03d}.png").write_bytes(b"")  # list_frames does not decode
    src = images.list_frames(tmp_path)
    ts, note = src.timestamps()
    np.testing.assert_array_equal(ts, np.arange(6.0))
    assert note.startswith("frame index")
    # TUM rgb.txt: "timestamp name", any order, names matched (with --stride too).
    (tmp_path / "rgb.txt").write_text(
        "# timestamp filename\n" + "".join(f"{100 + 0.5 * k:.6f} rgb/{k:03d}.png\n" for k in reversed(range(6)))
    )
    np.testing.assert_allclose(images.read_timestamps(tmp_path / "rgb.txt", src), 100 + 0.5 * np.arange(6))
    strided = images.list_frames(tmp_path, stride=2)
    np.testing.assert_allclose(images.read_timestamps(tmp_path / "rgb.txt", strided, 2), [100, 101, 102])
    # One time per line: for every input image (stride applied) or for the frames used.
    (tmp_path / "t.txt").write_text("".join(f"{0.1 * k}\n" for k in range(6)))
    np.testing.assert_allclose(images.read_timestamps(tmp_path / "t.txt", strided, 2), [0.0, 0.2, 0.4])
    np.testing.assert_allclose(images.read_timestamps(tmp_path / "t.txt", src), 0.1 * np.arange(6))


@pytest.mark.parametrize(
    "text,match",
    [
        ("1\n2\n", "has 2 times for 6 frames"),
        ("0 000.png\n1 001.png\n", "no time for frame 002.png"),
        ("0\n1\n2\n2\n4\n5\n", "times must increase"),
        ("0\n1\nabc\n3\n4\n5\n", "'abc' is not a number"),
        ("0\n1\nnan\n3\n4\n5\n", "non-finite"),
    ],
)
def test_bad_timestamps_files(tmp_path, text, match):
    for k in range(6):
        (tmp_path / f"{k:03d}.png").write_bytes(b"")
    (tmp_path / "t.txt").write_text(text)
    with pytest.raises(images.InputError, match=match):
        images.read_timestamps(tmp_path / "t.txt", images.list_frames(tmp_path))


# ------------------------------------------------------------------ outputs of a finished run


def test_colmap_model_is_trainer_ready(small_loop_run):
    """The layout gsplat and nerfstudio load; pycolmap reads it; every image observes points
    and every observation reprojects to its 3-D point; images exist at the camera's size."""
    pycolmap = require_extra("pycolmap")
    from PIL import Image

    from swiftjax.io import trajectory

    out, result = small_loop_run
    data = out / "colmap"  # gsplat: --data_dir RUN/colmap; nerfstudio: --data RUN/colmap --colmap-path sparse/0
    sparse = data / "sparse" / "0"
    assert sorted(p.name for p in sparse.iterdir()) == ["cameras.bin", "images.bin", "points3D.bin"]
    rec = pycolmap.Reconstruction(str(sparse))
    n = result.num_frames
    assert rec.num_images() == n and rec.num_cameras() == 1 and 0 < rec.num_points3D() <= 5_000
    (cam,) = rec.cameras.values()
    K_ref = result.intrinsics[0]
    np.testing.assert_allclose(cam.params, [K_ref[0, 0], K_ref[1, 1], K_ref[0, 2] + 0.5, K_ref[1, 2] + 0.5], rtol=1e-6)

    # gsplat's Parser: images/ holds exactly the model's images (it zips the two sorted lists),
    # every image name has point indices (its depth loss), the image size sets the K scale.
    files = sorted(str(p.relative_to(data / "images")) for p in (data / "images").rglob("*") if p.is_file())
    names = sorted(im.name for im in rec.images.values())
    assert files == names
    point_indices: dict[str, list[int]] = {}
    for im in rec.images.values():
        for p2d in im.get_observation_points2D():
            point_indices.setdefault(im.name, []).append(p2d.point3D_id)
    assert set(point_indices) == set(names)
    # nerfstudio: data/images/<name> exists with the camera's size (its full-image datamanager
    # asserts it); max_2D_matches_per_3D_point=-1 stacks every track (non-empty).
    for name in names[:: max(1, n // 25)]:
        assert Image.open(data / "images" / name).size == (cam.width, cam.height)
    kitti = trajectory.read_kitti(out / "poses_kitti.txt")
    worst = 0.0
    for pid, p in rec.points3D.items():
        assert p.track.length() == 1
        el = p.track.elements[0]
        image = rec.images[el.image_id]
        xy = image.points2D[el.point2D_idx].xy
        assert image.points2D[el.point2D_idx].point3D_id == pid
        proj = cam.img_from_cam(np.asarray(image.cam_from_world() * p.xyz)[None])[0]
        worst = max(worst, float(np.abs(proj - xy).max()))
        assert p.error < 1.0
    assert worst < 1.0, worst  # measured ~1e-3 px: float32 points
    for i in (1, n // 2, n):
        w2c = rec.images[i].cam_from_world().matrix()
        np.testing.assert_allclose(np.linalg.inv(kitti[i - 1])[:3], w2c, atol=1e-6)


def _header(path):
    return [ln[2:] for ln in path.read_text().splitlines() if ln.startswith("#")]


def test_text_outputs_describe_themselves(small_loop_run):
    import subprocess
    import sys
    from pathlib import Path

    from swiftjax.io import trajectory

    out, result = small_loop_run
    head = "\n".join(_header(out / "intrinsics.txt"))
    assert "resolution: 140 x 42 pixels" in head and "pixel centres at integers" in head
    assert "K_ref" in head and "colmap/sparse/0: one shared PINHOLE camera = K_ref with cx + 0.5" in head
    rows = np.loadtxt(out / "intrinsics.txt")
    np.testing.assert_allclose(rows[:, 1:], result.intrinsics[:, [0, 1, 0, 1], [0, 1, 2, 2]], atol=1e-6)

    loops = out / "loops.txt"
    columns = _header(loops)[-1].split()
    body = [ln.split(maxsplit=len(columns) - 1) for ln in loops.read_text().splitlines() if not ln.startswith("#")]
    assert columns[:5] == ["i", "j", "score", "chunk_i", "chunk_j"] and "align_i.num_points" in columns
    assert len(body) == len(result.loops) > 0 and all(len(r) == len(columns) for r in body)
    for r, rec in zip(body, result.loops):
        assert (int(r[0]), int(r[1])) == (rec["i"], rec["j"])
        assert float(r[2]) == pytest.approx(rec["score"], rel=1e-5)
        assert int(r[columns.index("align_j.num_points")]) == rec["align_j"]["num_points"]

    for name in ("poses_kitti.txt", "poses_tum.txt"):
        assert any(h.startswith("unit: up to scale") for h in _header(out / name)), name
    assert "timestamps (s): frame index" in "\n".join(_header(out / "poses_tum.txt"))
    np.testing.assert_allclose(trajectory.read_kitti(out / "poses_kitti.txt"), result.cam_to_world, atol=1e-12)
    ts, tum = trajectory.read_tum(out / "poses_tum.txt")
    np.testing.assert_array_equal(ts, np.arange(result.num_frames))
    evo = Path(sys.executable).with_name("evo_traj")
    if not evo.exists():
        pytest.skip("evo_traj is not installed beside this Python")
    for fmt, name in (("kitti", "poses_kitti.txt"), ("tum", "poses_tum.txt")):
        run = subprocess.run([str(evo), fmt, str(out / name), "--full_check"], capture_output=True, text=True)
        assert run.returncode == 0 and "SE(3) conform\tyes" in run.stdout, run.stdout + run.stderr


def test_points_png_shows_the_cloud(small_loop_run):
    from PIL import Image

    out, _ = small_loop_run
    img = np.asarray(Image.open(out / "points.png").convert("RGB")).astype(int)
    assert min(img.shape[:2]) >= 300 and max(img.shape[:2]) >= 600
    coloured = (img.max(-1) - img.min(-1)) > 40  # the synthetic facades, trees and the trajectory
    grey = (np.abs(img - 255).max(-1) > 60) & ~coloured  # grey road / facades
    assert coloured.mean() > 0.005 and grey.mean() > 0.02, (coloured.mean(), grey.mean())


def test_reconstruct_cli_passes_the_sources_times(tmp_path, monkeypatch):
    """``swiftjax reconstruct VIDEO --stride 2``: poses_tum.txt gets the video's own times."""
    from swiftjax import cli, pipeline

    _video(tmp_path / "drive.avi", 10, 5.0)
    (tmp_path / "w.pt").write_bytes(b"")
    seen = {}

    def fake_reconstruct(predictor, out, config, **kwargs):
        seen.update(kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.model, "make_runner", lambda *args: None)
    monkeypatch.setattr(pipeline, "reconstruct", fake_reconstruct)
    assert (
        cli.main(
            [
                "reconstruct",
                str(tmp_path / "drive.avi"),
                "--weights",
                str(tmp_path / "w.pt"),
                "--out",
                str(tmp_path / "run"),
                "--stride",
                "2",
            ]
        )
        == 130
    )
    np.testing.assert_allclose(seen["timestamps"], np.arange(0, 10, 2) / 5.0)
    assert "5 fps" in seen["timestamps_note"]


def test_trajectory_headers_carry_unit_and_time_source(tmp_path):
    from swiftjax.io import trajectory
    from swiftjax.pipeline.export import _write_trajectories

    c2w = np.tile(np.eye(4), (3, 1, 1))
    c2w[:, 0, 3] = [0.0, 1.0, 2.0]
    _write_trajectories(tmp_path, c2w, np.array([0.0, 0.4, 0.8]), "metres", "video time: frame index / 5 fps")
    assert "unit: metres" in _header(tmp_path / "poses_kitti.txt")
    assert "timestamps (s): video time: frame index / 5 fps" in _header(tmp_path / "poses_tum.txt")
    ts, poses = trajectory.read_tum(tmp_path / "poses_tum.txt")
    np.testing.assert_array_equal(ts, [0.0, 0.4, 0.8])
    np.testing.assert_allclose(poses, c2w)


@pytest.mark.parametrize("mode,size", [("crop", (600, 1036)), ("pad", (300, 700))])  # portrait: rows cropped
def test_original_resolution_undoes_the_preprocessing(tmp_path, mode, size):
    """--colmap-original-resolution: K at the original size and the observations moved with it,
    so a point still projects onto its observation; the camera module's forward map takes the
    observations back to the model's pixels; pad pixels are dropped; the originals are copied."""
    from types import SimpleNamespace

    from PIL import Image

    from swiftjax.intrinsics import map_points, preprocess_geometry
    from swiftjax.pipeline import export

    w0, h0 = size
    for k in range(2):
        Image.new("RGB", (w0, h0), (10 * k, 20, 30)).save(tmp_path / f"f{k}.jpg")
    source = images.list_frames(tmp_path)
    geom = preprocess_geometry(h0, w0, mode)
    ctx = SimpleNamespace(
        predictor=SimpleNamespace(source=source, mode=mode, frame_names=lambda: source.names),
        run_dir=tmp_path / "run",
        config=SimpleNamespace(colmap_original_resolution=True),
    )
    h, w = geom.model_hw
    K_ref = np.array([[0.9 * w, 0, w / 2 - 3.0], [0, 0.9 * w, h / 2 + 2.0], [0, 0, 1]])
    rng = np.random.default_rng(0)
    pix = np.column_stack([rng.uniform(-0.5, w - 0.5, 500), rng.uniform(-0.5, h - 0.5, 500), np.ones(500)])
    x = rng.uniform(2, 5, (500, 1)) * (pix @ np.linalg.inv(K_ref).T)  # points seen in the model's image
    proj = lambda K: (x @ K.T)[:, :2] / x[:, 2:]
    uv = proj(K_ref)
    K0, size0, uv0, keep = export._to_original_resolution(ctx, K_ref, (h, w), uv)
    assert size0 == (w0, h0)
    np.testing.assert_allclose(proj(K0), uv0, atol=1e-9)
    np.testing.assert_allclose(map_points(uv0, geom), uv, atol=1e-9)
    inside = (uv0[:, 0] >= -0.5) & (uv0[:, 0] < w0 - 0.5) & (uv0[:, 1] >= -0.5) & (uv0[:, 1] < h0 - 0.5)
    np.testing.assert_array_equal(keep, inside)
    assert keep.all() if mode == "crop" else 0 < keep.sum() < len(keep)  # pad mode: points on the pad go
    if mode == "crop":
        assert geom.top < 0 and (uv0[:, 1] > -geom.top).any()  # rows were cropped: v shifts down
    assert export.frame_image_names(ctx) == ["f0.jpg", "f1.jpg"]
    export._copy_originals(ctx, export.frame_image_names(ctx))
    assert (ctx.run_dir / "colmap" / "images" / "f1.jpg").read_bytes() == (tmp_path / "f1.jpg").read_bytes()


def test_original_resolution_needs_input_images(tmp_path):
    from swiftjax import pipeline
    from swiftjax.synthetic import demo

    run = demo.loop_route_run(20)
    with pytest.raises(ValueError, match="needs the input images"):
        pipeline.reconstruct(
            run.predictor, tmp_path, pipeline.PipelineConfig(colmap_original_resolution=True), progress=False
        )
    assert not (tmp_path / "chunks").exists() or not any((tmp_path / "chunks").iterdir())  # no work done


def test_original_resolution_end_to_end_with_tiny_vggt(tmp_path, golden_dir):
    """Image files -> tiny VGGT (pad mode: portrait frames padded to 518 x 518) ->
    ``colmap_original_resolution``: the original files under their names, a camera of the
    original size, observations inside the original image and reprojecting onto their points.
    (The crop geometry is checked in ``test_original_resolution_undoes_the_preprocessing``.)"""
    mode = "pad"
    pytest.importorskip("torch")
    pycolmap = require_extra("pycolmap")
    from PIL import Image

    from inference import VGGT, VGGTConfig, load_checkpoint
    from inference.predictor import ImagePredictor
    from inference.runners import TorchRunner
    from swiftjax import pipeline

    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (90, 60, 3), np.uint8)  # portrait: pad mode pads the sides
    for k in range(4):
        Image.fromarray(np.roll(base, 2 * k, axis=0)).save(folder / f"img_{k}.jpg", quality=95)
    model = VGGT(VGGTConfig.from_json(golden_dir / "tiny_config.json"))
    load_checkpoint(model, golden_dir / "tiny_weights.safetensors")
    predictor = ImagePredictor(images.validate(images.list_frames(folder)), TorchRunner(model), mode=mode)
    config = pipeline.PipelineConfig(
        chunk_size=4, overlap=1, min_points=10, loop_closure=False, point_stride=2, colmap_original_resolution=True
    )
    pipeline.reconstruct(predictor, tmp_path / "run", config, progress=False)

    data = tmp_path / "run" / "colmap"
    assert sorted(p.name for p in (data / "images").iterdir()) == [f"img_{k}.jpg" for k in range(4)]
    assert (data / "images" / "img_3.jpg").read_bytes() == (folder / "img_3.jpg").read_bytes()
    rec = pycolmap.Reconstruction(str(data / "sparse" / "0"))
    (cam,) = rec.cameras.values()
    assert (cam.width, cam.height) == (60, 90) and rec.num_points3D() > 0
    for p in list(rec.points3D.values())[::7]:
        el = p.track.elements[0]
        image = rec.images[el.image_id]
        xy = image.points2D[el.point2D_idx].xy
        assert 0 <= xy[0] <= 60 and 0 <= xy[1] <= 90
        proj = cam.img_from_cam(np.asarray(image.cam_from_world() * p.xyz)[None])[0]
        assert np.abs(proj - xy).max() < 1e-2
    assert "K_ref at the original 60 x 90 images" in (tmp_path / "run" / "intrinsics.txt").read_text()


def test_original_resolution_refuses_names_with_spaces_before_work(tmp_path):
    from types import SimpleNamespace

    from PIL import Image

    from swiftjax.pipeline import export

    Image.new("RGB", (40, 30)).save(tmp_path / "IMG 1.jpg")
    source = images.list_frames(tmp_path)
    ctx = SimpleNamespace(
        run_dir=tmp_path / "run",
        predictor=SimpleNamespace(source=source, frame_names=lambda: source.names),
        config=SimpleNamespace(colmap=True, colmap_original_resolution=True),
    )
    with pytest.raises(ValueError, match="cannot hold white space: 'IMG 1.jpg'"):
        export.check(ctx)

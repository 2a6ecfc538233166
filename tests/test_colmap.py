"""swiftjax.io.colmap: text model read back by pycolmap and by an independent reader."""

from __future__ import annotations

import numpy as np
import pytest
from _extras import require_extra
from scipy.spatial.transform import Rotation

from swiftjax.io.colmap import world_to_camera_qt, write_colmap, write_colmap_text

W, H = 518, 154


def _scene(n=7, m=400, seed=0):
    rng = np.random.default_rng(seed)
    rots = Rotation.random(n, random_state=seed).as_matrix()
    if n > 4:
        rots[3] = Rotation.from_rotvec([np.pi - 1e-9, 0, 0]).as_matrix()  # qw ~ 0: sign edge case
        rots[4] = np.eye(3)
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, :3] = rots
    c2w[:, :3, 3] = rng.uniform(-50, 50, (n, 3))
    k_a = np.array([[300.0, 0, 259.0], [0, 301.5, 77.0], [0, 0, 1]])
    k_b = np.array([[280.25, 0, 258.5], [0, 280.25, 76.5], [0, 0, 1]])
    ks = np.stack([k_a, k_b, k_a, k_a, k_b, k_a, k_b][:n])
    names = [f"frame_{i:06d}.png" for i in range(n)]
    pts = rng.uniform(-100, 100, (m, 3)).astype(np.float32)
    cols = rng.integers(0, 256, (m, 3), dtype=np.uint8)
    errs = rng.uniform(0, 2, m)
    return c2w, ks, names, pts, cols, errs


def _quat_wxyz_to_matrix(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _read_text_model(d):
    """Independent reader from COLMAP's documented text format."""
    cams = {}
    for line in (d / "cameras.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        w = line.split()
        cams[int(w[0])] = (w[1], int(w[2]), int(w[3]), np.array(w[4:], float))
    images = {}
    lines = [ln for ln in (d / "images.txt").read_text().split("\n") if not ln.startswith("#")]
    for first, second in zip(lines[0::2], lines[1::2]):
        if not first.strip():
            continue
        w = first.split()
        assert second == ""  # POINTS2D line present and empty
        images[int(w[0])] = (np.array(w[1:5], float), np.array(w[5:8], float), int(w[8]), w[9])
    pts = {}
    for line in (d / "points3D.txt").read_text().splitlines():
        if line.startswith("#"):
            continue
        w = line.split()
        assert len(w) == 8  # empty track
        pts[int(w[0])] = (np.array(w[1:4], float), np.array(w[4:7], int), float(w[7]))
    return cams, images, pts


def test_independent_reader(tmp_path):
    c2w, ks, names, pts, cols, errs = _scene()
    write_colmap_text(tmp_path / "sparse", c2w, ks, names, (W, H), pts, cols, errs)
    cams, images, points = _read_text_model(tmp_path / "sparse")
    assert len(cams) == 2 and set(images) == set(range(1, 8)) and set(points) == set(range(1, 401))
    for i in range(7):
        q, t, cid, name = images[i + 1]
        assert name == names[i]
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        r_cw = _quat_wxyz_to_matrix(q)
        back = np.eye(4)
        back[:3, :3] = r_cw.T
        back[:3, 3] = -r_cw.T @ t
        np.testing.assert_allclose(back, c2w[i], atol=1e-12 * max(1, np.abs(c2w[i]).max()))
        model, w, h, (fx, fy, cx, cy) = cams[cid]
        assert (model, w, h) == ("PINHOLE", W, H)
        k = ks[i]
        np.testing.assert_array_equal([fx, fy, cx, cy], [k[0, 0], k[1, 1], k[0, 2] + 0.5, k[1, 2] + 0.5])
    assert images[1][2] == 1 and images[2][2] == 2  # camera ids in order of first use
    for j in range(400):
        xyz, rgb, e = points[j + 1]
        np.testing.assert_array_equal(xyz.astype(np.float32), pts[j])  # float32 round-trips exactly
        np.testing.assert_array_equal(rgb, cols[j])
        assert abs(e - errs[j]) <= 1e-8 * max(1, errs[j])


def test_pycolmap_reads_model_and_projection_convention(tmp_path):
    pycolmap = require_extra("pycolmap")
    c2w, ks, names, pts, cols, errs = _scene()
    out = write_colmap_text(tmp_path / "m", c2w, ks, names, (W, H), pts, cols, errs)
    rec = pycolmap.Reconstruction(str(out))
    assert (rec.num_images(), rec.num_cameras(), rec.num_points3D()) == (7, 2, 400)
    for i in range(7):
        img = rec.images[i + 1]
        assert img.name == names[i]
        pose = img.cam_from_world()
        m = pose.matrix()  # 3x4 world-to-camera
        w2c = np.linalg.inv(c2w[i])
        np.testing.assert_allclose(m[:, :3], w2c[:3, :3], atol=1e-12)
        np.testing.assert_allclose(m[:, 3], w2c[:3, 3], atol=1e-10)
        cam = img.camera
        np.testing.assert_allclose(cam.params, [ks[i][0, 0], ks[i][1, 1], ks[i][0, 2] + 0.5, ks[i][1, 2] + 0.5])
        assert (cam.width, cam.height) == (W, H)
        # A world point at the centre of our integer pixel (u, v) projects to COLMAP's (u+.5, v+.5).
        u, v, depth = 17.0, 100.0, 12.5
        x_cam = depth * np.linalg.inv(ks[i]) @ np.array([u, v, 1.0])
        x_world = c2w[i, :3, :3] @ x_cam + c2w[i, :3, 3]
        uv = cam.img_from_cam(np.asarray(pose * x_world)[None])[0]
        np.testing.assert_allclose(uv, [u + 0.5, v + 0.5], atol=1e-9)
    for j in (1, 200, 400):
        p = rec.points3D[j]
        np.testing.assert_allclose(p.xyz, pts[j - 1], rtol=1e-7)
        np.testing.assert_array_equal(p.color, cols[j - 1])
        assert abs(p.error - errs[j - 1]) < 1e-8


def test_no_points_and_pixel_offset_zero(tmp_path):
    pycolmap = require_extra("pycolmap")
    c2w, ks, names, *_ = _scene(n=2)
    write_colmap_text(tmp_path, c2w, ks, names, np.array([[W, H], [W, H]]), pixel_offset=0.0)
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert rec.num_points3D() == 0
    np.testing.assert_allclose(rec.cameras[2].params, [280.25, 280.25, 258.5, 76.5])


def test_world_to_camera_qt_matches_scipy():
    c2w, *_ = _scene(n=7, seed=5)
    q, t = world_to_camera_qt(c2w)
    ref = Rotation.from_matrix(np.swapaxes(c2w[:, :3, :3], 1, 2)).as_quat()  # xyzw
    ref = ref[:, [3, 0, 1, 2]] * np.where(ref[:, 3:] < 0, -1, 1)
    ref[3] *= np.sign(ref[3][np.argmax(np.abs(ref[3]))]) * np.sign(q[3][np.argmax(np.abs(q[3]))])  # qw~0: q ~ -q
    np.testing.assert_allclose(q, ref, atol=1e-12)
    np.testing.assert_allclose(t, -np.einsum("nji,nj->ni", c2w[:, :3, :3], c2w[:, :3, 3]), atol=1e-12)


@pytest.mark.parametrize(
    "change,match",
    [
        (lambda a: a[0].__setitem__((2, slice(None, 3)), 2 * a[0][2, :3]), "pose 2 .* is not a rotation"),
        (lambda a: a[0].__setitem__((1, slice(None, 3), slice(None, 3)), -np.eye(3)), "pose 1 .*det"),
        (lambda a: a[1].__setitem__((3, 0, 1), 0.5), "intrinsics 3 .* zero-skew"),
        (lambda a: a[2].__setitem__(0, "has space.png"), "whitespace"),
        (lambda a: a[2].__setitem__(1, a[2][0]), "unique"),
        (lambda a: a[3].__setitem__(slice(None), np.nan), "non-finite"),
        (lambda a: a.__setitem__(4, np.zeros((400, 3))), "uint8"),
        (lambda a: a.__setitem__(1, a[1][:3]), r"intrinsics has shape \(3, 3, 3\)"),
    ],
)
def test_bad_input_writes_nothing(tmp_path, change, match):
    args = list(_scene())
    change(args)
    c2w, ks, names, pts, cols, errs = args
    with pytest.raises(ValueError, match=match):
        write_colmap_text(tmp_path / "m", c2w, ks, names, (W, H), pts, cols, errs)
    assert not (tmp_path / "m").exists()


def _observed_scene(n=5, m=300, seed=1):
    """Points unprojected from known pixels of known images: the observations are exact."""
    c2w, ks, names, _, cols, errs = _scene(n=n, m=m, seed=seed)
    rng = np.random.default_rng(seed)
    img = rng.integers(0, n, m)
    img[:n] = np.arange(n)  # every image observes at least one point
    uv = np.column_stack([rng.integers(0, W, m), rng.integers(0, H, m)]).astype(np.float64)
    depth = rng.uniform(1.0, 40.0, m)
    rays = np.einsum("nij,nj->ni", np.linalg.inv(ks[img]), np.column_stack([uv, np.ones(m)]))
    pts = np.einsum("nij,nj->ni", c2w[img, :3, :3], depth[:, None] * rays) + c2w[img, :3, 3]
    return c2w, ks, names, pts, cols, errs, img, uv


@pytest.mark.parametrize("fmt", ["binary", "text"])
def test_observations_reproject_in_pycolmap(tmp_path, fmt):
    """Every point has a one-element track; its 2-D point is the pixel centre (+0.5) it came
    from, and the 3-D point reprojects there through pycolmap's camera and pose."""
    pycolmap = require_extra("pycolmap")
    c2w, ks, names, pts, cols, errs, img, uv = _observed_scene()
    write_colmap(
        tmp_path,
        c2w,
        ks,
        names,
        (W, H),
        pts,
        cols,
        errs,
        observations=(img, uv),
        binary=fmt == "binary",
        text=fmt == "text",
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == (
        ["cameras.bin", "images.bin", "points3D.bin"]
        if fmt == "binary"
        else ["cameras.txt", "images.txt", "points3D.txt"]
    )
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert (rec.num_images(), rec.num_points3D()) == (5, 300)
    per_image = np.bincount(img, minlength=5)
    for i in range(5):
        assert rec.images[i + 1].num_points2D() == per_image[i] and rec.images[i + 1].name == names[i]
    for j in range(300):
        p = rec.points3D[j + 1]
        np.testing.assert_allclose(p.xyz, pts[j], rtol=1e-15, atol=1e-12)
        np.testing.assert_array_equal(p.color, cols[j])
        (el,) = p.track.elements
        assert el.image_id == img[j] + 1
        image = rec.images[el.image_id]
        p2d = image.points2D[el.point2D_idx]
        assert p2d.point3D_id == j + 1
        np.testing.assert_allclose(p2d.xy, uv[j] + 0.5, atol=1e-12)
        proj = image.camera.img_from_cam(np.asarray(image.cam_from_world() * p.xyz)[None])[0]
        assert np.abs(proj - p2d.xy).max() < 1e-6


def test_binary_and_text_models_agree(tmp_path):
    pycolmap = require_extra("pycolmap")
    c2w, ks, names, pts, cols, errs, img, uv = _observed_scene(seed=4)
    write_colmap(tmp_path, c2w, ks, names, (W, H), pts, cols, errs, observations=(img, uv), text=True)
    (tmp_path / "bin").mkdir()
    (tmp_path / "txt").mkdir()
    for p in tmp_path.glob("*.*"):
        p.rename(tmp_path / ("bin" if p.suffix == ".bin" else "txt") / p.name)
    a, b = (pycolmap.Reconstruction(str(tmp_path / d)) for d in ("bin", "txt"))
    for i in a.images:
        np.testing.assert_allclose(
            a.images[i].cam_from_world().matrix(), b.images[i].cam_from_world().matrix(), atol=1e-15
        )
        np.testing.assert_array_equal([p.xy for p in a.images[i].points2D], [p.xy for p in b.images[i].points2D])
    for c in a.cameras:
        np.testing.assert_array_equal(a.cameras[c].params, b.cameras[c].params)
    for j in a.points3D:
        np.testing.assert_array_equal(a.points3D[j].xyz, b.points3D[j].xyz)
        assert a.points3D[j].error == pytest.approx(b.points3D[j].error, rel=1e-8)


def test_bad_observations_are_refused(tmp_path):
    c2w, ks, names, pts, cols, errs, img, uv = _observed_scene()
    with pytest.raises(ValueError, match=r"one per point"):
        write_colmap(tmp_path / "a", c2w, ks, names, (W, H), pts, cols, errs, observations=(img[:-1], uv[:-1]))
    with pytest.raises(ValueError, match=r"image indices must be integers in \[0, 5\)"):
        write_colmap(tmp_path / "b", c2w, ks, names, (W, H), pts, cols, errs, observations=(img + 1, uv))
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_image_names_are_png_unique_and_without_white_space():
    from swiftjax.io.colmap import image_names

    names = ["a.jpg", "a.png", "b.JPG", "sub/c.tif", "000001.png", "noext", "IMG 7.jpg", "tab\tx.png"]
    assert image_names(names) == [
        "a.jpg.png",
        "a.png",
        "b.png",
        "sub/c.png",
        "000001.png",
        "noext.png",
        "IMG_7.png",
        "tab_x.png",
    ]

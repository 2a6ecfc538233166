"""--intrinsics: file formats, clear errors, and the resize/crop/pad map of the preprocessing."""

from __future__ import annotations

import numpy as np
import pytest

from swiftjax import intrinsics as intr

KITTI_CALIB = """\
P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P1: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.861448000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 -7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01
"""


def test_plain_file_with_comments(tmp_path):
    p = tmp_path / "K.txt"
    p.write_text("# my camera\n  718.856 718.856 607.1928 185.2157  # fx fy cx cy\n")
    c = intr.read_intrinsics(p)
    assert (c.fx, c.fy, c.cx, c.cy, c.kind) == (718.856, 718.856, 607.1928, 185.2157, "plain")
    np.testing.assert_array_equal(c.K, [[718.856, 0, 607.1928], [0, 718.856, 185.2157], [0, 0, 1]])


def test_kitti_calib_uses_p0(tmp_path):
    p = tmp_path / "calib.txt"
    p.write_text(KITTI_CALIB)
    c = intr.read_intrinsics(p)
    assert c.kind == "kitti" and (c.fx, c.fy, c.cx, c.cy) == (718.856, 718.856, 607.1928, 185.2157)
    assert c.width is None


@pytest.mark.parametrize(
    "line, expect",
    [
        ("1 PINHOLE 1241 376 718.856 718.0 607.6928 185.7157", (718.856, 718.0, 607.1928, 185.2157)),
        ("1 SIMPLE_PINHOLE 1241 376 718.856 607.6928 185.7157", (718.856, 718.856, 607.1928, 185.2157)),
        ("3 OPENCV 1241 376 718.856 718.0 607.6928 185.7157 0 0 0 0", (718.856, 718.0, 607.1928, 185.2157)),
    ],
)
def test_colmap_models_and_the_half_pixel_origin(tmp_path, line, expect):
    """COLMAP's principal point has the corner origin: cx = cx_colmap - 0.5."""
    p = tmp_path / "cameras.txt"
    p.write_text("# Camera list with one line of data per camera:\n# Number of cameras: 1\n" + line + "\n")
    c = intr.read_intrinsics(p)
    assert c.kind == "colmap" and (c.width, c.height) == (1241, 376)
    np.testing.assert_allclose((c.fx, c.fy, c.cx, c.cy), expect, rtol=0, atol=1e-9)


def test_colmap_round_trips_through_our_writer(tmp_path):
    """Our COLMAP export adds 0.5 (io.colmap); reading it back gives the same K."""
    from swiftjax.io import colmap

    K = np.array([[300.0, 0, 258.5], [0, 301.0, 76.25], [0, 0, 1]])
    colmap.write_colmap_text(tmp_path, np.eye(4)[None], K[None], ["a.png"], image_size=(518, 154))
    c = intr.read_intrinsics(tmp_path / "cameras.txt")
    np.testing.assert_allclose(c.K, K, atol=1e-12)
    assert (c.width, c.height) == (518, 154)


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "no intrinsics found"),
        ("# only a comment\n", "no intrinsics found"),
        ("718 718 607\n", "expected 4 numbers"),
        ("718 718 607 185 1\n", "expected 4 numbers"),
        ("718 abc 607 185\n", "line 1: expected numbers"),
        ("718 718 607 nan\n", "non-finite"),
        ("0 718 607 185\n", "focal lengths must be positive"),
        ("718 -718 607 185\n", "focal lengths must be positive"),
        ("718 718 607 185\n700 700 600 180\n", "got 2 lines"),
        ("P0: 1 0 0 0 0 1 0 0 0 0 1\n", "12 numbers"),
        ("P0: 700 0 600 0 0 700 180 0 0 0 2 0\n", "not K"),
        ("P0: -700 0 600 0 0 700 180 0 0 0 1 0\n", "focal lengths must be positive"),
        ("P1: 700 0 600 0 0 700 180 0 0 0 1 0\n", "no 'P0:' line"),
        ("1 SIMPLE_RADIAL 640 480 500 320 240 0.1\n", "distortion models are not supported"),
        ("1 FISHEYE_X 640 480 500 320 240\n", "'FISHEYE_X' is not supported .use PINHOLE"),
        ("1 PINHOLE 640 480 500 500 320\n", "needs 4 parameters, got 3"),
        ("1 OPENCV 640 480 500 500 320 240 0.1 0 0 0\n", "non-zero distortion"),
        ("1 PINHOLE 640 x 500 500 320 240\n", "must be integers"),
        ("1 PINHOLE 0 480 500 500 320 240\n", "size must be positive"),
        ("1 PINHOLE 640 480 0 500 320 240\n", "focal lengths must be positive"),
        ("1 PINHOLE 640 480 500 500 320 240\n2 PINHOLE 640 480 510 500 320 240\n", "2 different COLMAP cameras"),
    ],
)
def test_malformed_files_are_refused_clearly(tmp_path, text, match):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(intr.IntrinsicsError, match=match) as err:
        intr.read_intrinsics(p)
    assert str(p) in str(err.value) and "\n" not in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(intr.IntrinsicsError, match="does not exist"):
        intr.read_intrinsics(tmp_path / "nope.txt")


def test_principal_point_outside_the_image_and_size_mismatch():
    c = intr.parse_intrinsics("700 700 607 185", "K.txt")
    c.check_image_size(376, 1241)
    with pytest.raises(intr.IntrinsicsError, match=r"principal point \(607, 185\) lies outside the 500x376 image"):
        c.check_image_size(376, 500)
    with pytest.raises(intr.IntrinsicsError, match="outside"):
        intr.parse_intrinsics("700 700 -3 185", "K.txt").check_image_size(376, 1241)
    cm = intr.parse_intrinsics("1 PINHOLE 640 480 500 500 320 240", "cameras.txt")
    with pytest.raises(intr.IntrinsicsError, match="the camera is 640x480 but the images are 1241x376"):
        cm.check_image_size(376, 1241)


# ----------------------------------------------------------------------------- the map


def _hand(K, sx, sy, left, top):
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.array([[sx * fx, 0, sx * (cx + 0.5) - 0.5 + left], [0, sy * fy, sy * (cy + 0.5) - 0.5 + top], [0, 0, 1]])


K0 = np.array([[718.856, 0, 607.1928], [0, 718.856, 185.2157], [0, 0, 1.0]])


@pytest.mark.parametrize(
    "hw, mode, resized, top, left, model",
    [
        ((376, 1241), "crop", (154, 518), 0, 0, (154, 518)),  # KITTI: s_x != s_y
        ((376, 1241), "pad", (154, 518), 182, 0, (518, 518)),
        ((640, 480), "crop", (686, 518), -84, 0, (518, 518)),  # portrait: rows cropped
        ((640, 480), "pad", (518, 392), 0, 63, (518, 518)),  # portrait: columns padded
        ((480, 640), "pad", (392, 518), 63, 0, (518, 518)),
        ((154, 518), "crop", (154, 518), 0, 0, (154, 518)),  # the demo: identity
    ],
)
def test_map_against_hand_computation(hw, mode, resized, top, left, model):
    g = intr.preprocess_geometry(*hw, mode)
    assert (g.resized_hw, g.top, g.left, g.model_hw) == (resized, top, left, model)
    sx, sy = resized[1] / hw[1], resized[0] / hw[0]
    K = K0.copy()
    K[0, 2], K[1, 2] = 0.47 * hw[1], 0.52 * hw[0]
    np.testing.assert_allclose(intr.map_intrinsics(K, g), _hand(K, sx, sy, left, top), rtol=1e-14, atol=1e-12)
    np.testing.assert_allclose(intr.unmap_intrinsics(intr.map_intrinsics(K, g), g), K, atol=1e-9)
    assert g.is_identity == (hw == (154, 518))


def test_kitti_scales_differ_per_axis():
    g = intr.preprocess_geometry(376, 1241, "crop")
    K = intr.map_intrinsics(K0, g)
    assert K[0, 0] == pytest.approx(718.856 * 518 / 1241) and K[1, 1] == pytest.approx(718.856 * 154 / 376)
    assert abs(K[0, 0] / K[1, 1] - 1) > 0.015  # one scale for both would be 1.9 % off


def test_geometry_matches_inference_preprocess_sizes():
    from inference.preprocess import target_size_hw

    rng = np.random.default_rng(0)
    for _ in range(300):
        h, w = (int(v) for v in rng.integers(60, 3000, size=2))
        for mode in ("crop", "pad"):
            try:
                ref = target_size_hw(h, w, mode)
            except ValueError:
                with pytest.raises(ValueError):
                    intr.preprocess_geometry(h, w, mode)
                continue
            assert intr.preprocess_geometry(h, w, mode).resized_hw == ref


def _blob(h, w, u0, v0, sigma=5.0):
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    g = np.exp(-((u - u0) ** 2 + (v - v0) ** 2) / (2 * sigma**2))
    return np.repeat((255 * g).round().astype(np.uint8)[..., None], 3, axis=2)


@pytest.mark.parametrize(
    "hw, mode", [((640, 480), "crop"), ((640, 480), "pad"), ((376, 1241), "crop"), ((480, 640), "pad")]
)
def test_a_dot_lands_where_the_map_says(hw, mode):
    """Independent check through the real preprocessing (PIL-exact bicubic): the centroid of a
    Gaussian blob after `inference.preprocess.preprocess` is `map_points` of its centre."""
    from inference.preprocess import preprocess

    h, w = hw
    u0, v0 = 0.37 * w + 0.3, 0.58 * h - 0.2
    img = _blob(h, w, u0, v0, sigma=0.012 * max(h, w))
    out = preprocess(img, mode=mode)[0, 0].astype(np.float64)  # [H, W] in [0, 1]
    g = intr.preprocess_geometry(h, w, mode)
    assert out.shape == g.model_hw
    # the padding is white (1.0): look only at the resized image's area
    r0, c0 = max(g.top, 0), max(g.left, 0)
    area = np.zeros_like(out, bool)
    area[r0 : r0 + min(g.resized_hw[0], g.model_hw[0]), c0 : c0 + g.resized_hw[1]] = True
    wgt = np.where(area, out, 0.0)
    wgt = np.where(wgt > 0.02, wgt, 0.0)
    vv, uu = np.mgrid[: out.shape[0], : out.shape[1]]
    centroid = np.array([np.sum(wgt * uu), np.sum(wgt * vv)]) / np.sum(wgt)
    np.testing.assert_allclose(centroid, intr.map_points([u0, v0], g), atol=0.06)


def test_map_mask_boxes_crop_and_pad():
    g = intr.preprocess_geometry(640, 480, "crop")  # resized 686 x 518, rows 84.. kept
    m = np.zeros((640, 480), bool)
    m[100:300, 40:200] = True
    out = intr.map_mask(m, g)
    assert out.shape == (518, 518)
    # hand: model row r shows original row floor((r + 84 + 0.5) * 640 / 686)
    rows = np.floor((np.arange(518) + 84 + 0.5) * 640 / 686).astype(int)
    cols = np.floor((np.arange(518) + 0.5) * 480 / 518).astype(int)
    np.testing.assert_array_equal(out, m[rows[:, None], cols[None, :]])
    gp = intr.preprocess_geometry(640, 480, "pad")  # 518 x 392 at columns 63..455
    outp = intr.map_mask(np.ones((640, 480), bool), gp)
    assert outp[:, :63].sum() == 0 and outp[:, 455:].sum() == 0 and outp[:, 63:455].all()
    with pytest.raises(ValueError, match="expected the image's"):
        intr.map_mask(np.ones((10, 10), bool), gp)

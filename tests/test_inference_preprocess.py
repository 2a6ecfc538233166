"""Preprocessing: sizes, modes, odd inputs, and pixel equality with upstream's PIL pipeline."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from inference.preprocess import load_image, preprocess, resize_rgb, target_size_hw, to_uint8_images


def _photos() -> dict[str, np.ndarray]:
    data = pytest.importorskip("skimage.data")
    return {"coffee": data.coffee(), "astronaut": data.astronaut(), "chelsea": data.chelsea(), "rocket": data.rocket()}


def _upstream(img: np.ndarray, mode: str = "crop") -> np.ndarray:
    """vggt.utils.load_fn.load_and_preprocess_images for one in-memory image, with PIL."""
    Image = pytest.importorskip("PIL.Image")
    im = Image.fromarray(img)
    if im.mode == "RGBA":
        im = Image.alpha_composite(Image.new("RGBA", im.size, (255, 255, 255, 255)), im)
    im = im.convert("RGB")
    width, height = im.size
    if mode == "pad" and width < height:
        new_h = 518
        new_w = round(width * (new_h / height) / 14) * 14
    else:
        new_w = 518
        new_h = round(height * (new_w / width) / 14) * 14
    arr = np.asarray(im.resize((new_w, new_h), Image.Resampling.BICUBIC)).transpose(2, 0, 1).astype(
        np.float32
    ) / np.float32(255)
    if mode == "crop" and new_h > 518:
        start = (new_h - 518) // 2
        arr = arr[:, start : start + 518]
    if mode == "pad":
        hp, wp = 518 - arr.shape[1], 518 - arr.shape[2]
        arr = np.pad(arr, ((0, 0), (hp // 2, hp - hp // 2), (wp // 2, wp - wp // 2)), constant_values=1.0)
    return arr


# ---------------------------------------------------------------------------------------------
# sizes


@pytest.mark.parametrize(
    ("hw", "mode", "expected"),
    [
        ((480, 640), "crop", (392, 518)),  # 4:3 landscape
        ((640, 480), "crop", (686, 518)),  # 3:4 portrait, cropped to 518 afterwards
        ((376, 1241), "crop", (154, 518)),  # KITTI
        ((35, 518), "crop", (28, 518)),  # 2.5 -> 2 (Python round: half to even)
        ((21, 518), "crop", (28, 518)),  # 1.5 -> 2
        ((1, 1), "crop", (518, 518)),  # upscales tiny images too
        ((640, 480), "pad", (518, 392)),
        ((480, 640), "pad", (392, 518)),
    ],
)
def test_target_size(hw: tuple[int, int], mode: str, expected: tuple[int, int]) -> None:
    assert target_size_hw(*hw, mode=mode) == expected  # type: ignore[arg-type]


def test_too_elongated_image_is_refused() -> None:
    with pytest.raises(ValueError, match="too elongated"):
        preprocess(np.zeros((20, 2000, 3), np.uint8))
    with pytest.raises(ValueError, match="mode"):
        target_size_hw(10, 10, mode="stretch")  # type: ignore[arg-type]


@pytest.mark.parametrize("hw", [(13, 17), (1, 1), (7, 3), (518, 519), (1000, 31)])
def test_odd_sizes_give_multiples_of_14(hw: tuple[int, int]) -> None:
    img = np.random.default_rng(0).integers(0, 256, (*hw, 3), dtype=np.uint8)
    out = preprocess(img)
    assert out.dtype == np.float32 and out.shape[:2] == (1, 3)
    assert out.shape[2] % 14 == 0 and out.shape[3] == 518 and out.shape[2] <= 518
    assert 0.0 <= out.min() and out.max() <= 1.0


# ---------------------------------------------------------------------------------------------
# equality with upstream (PIL)


@pytest.mark.parametrize("mode", ["crop", "pad"])
def test_real_photos_equal_upstream_pil(mode: str) -> None:
    for name, img in _photos().items():
        np.testing.assert_array_equal(preprocess(img, mode=mode)[0], _upstream(img, mode), err_msg=name)


def test_pil_resize_equal_on_random_sizes() -> None:
    """Covers both pass orders of PIL's two-pass resampling (see resize_rgb)."""
    Image = pytest.importorskip("PIL.Image")
    rng = np.random.default_rng(7)
    vertical_first = 0
    for _ in range(40):
        h, w = (int(v) for v in rng.integers(8, 120, 2))
        nh, nw = (int(v) for v in rng.integers(4, 160, 2))
        vertical_first += nh < h and (h - nh) > 2 * (w - nw)
        img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        ref = np.asarray(Image.fromarray(img).resize((nw, nh), Image.Resampling.BICUBIC))
        np.testing.assert_array_equal(resize_rgb(img, nh, nw), ref, err_msg=f"{(h, w)} -> {(nh, nw)}")
    assert vertical_first >= 5


def test_opencv_resizers_differ_from_pil_as_documented() -> None:
    """Measures cv2.INTER_CUBIC / INTER_AREA against PIL on a real photo (the numbers in the docs)."""
    Image = pytest.importorskip("PIL.Image")
    img = _photos()["coffee"]  # 400 x 600: downscale to 518 x 350 (crop) and a strong one to 154 rows
    for (nh, nw), cubic_max, area_mean in [((350, 518), 20, 1.5), ((154, 518), 60, 1.5)]:
        ref = np.asarray(Image.fromarray(img).resize((nw, nh), Image.Resampling.BICUBIC)).astype(np.int16)
        exact = np.abs(resize_rgb(img, nh, nw, "pil") - ref)
        cubic = np.abs(resize_rgb(img, nh, nw, "cv2-cubic").astype(np.int16) - ref)
        area = np.abs(resize_rgb(img, nh, nw, "cv2-area").astype(np.int16) - ref)
        assert exact.max() == 0
        assert cubic.max() > cubic_max and area.mean() < area_mean  # INTER_CUBIC aliases; AREA is close
    with pytest.raises(ValueError, match="resample"):
        resize_rgb(img, 10, 10, "lanczos")  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# file formats


def test_files_decode_like_arrays(tmp_path: pathlib.Path) -> None:
    img = _photos()["chelsea"]
    path = tmp_path / "chelsea ü.png"  # non-ASCII path
    cv2.imwrite(str(tmp_path / "tmp.png"), img[:, :, ::-1])
    (tmp_path / "tmp.png").rename(path)
    np.testing.assert_array_equal(load_image(path), img)
    np.testing.assert_array_equal(preprocess([path, str(path)]), np.stack([_upstream(img)] * 2))


def test_grayscale_png(tmp_path: pathlib.Path) -> None:
    gray = _photos()["astronaut"].mean(axis=2).astype(np.uint8)[:300, :451]
    cv2.imwrite(str(tmp_path / "g.png"), gray)
    out = preprocess(tmp_path / "g.png")[0]
    np.testing.assert_array_equal(out[0], out[1])
    np.testing.assert_array_equal(out, _upstream(gray))


def test_rgba_png_composited_on_white(tmp_path: pathlib.Path) -> None:
    rng = np.random.default_rng(1)
    rgba = np.dstack([_photos()["coffee"][:200, :300], rng.integers(0, 256, (200, 300), dtype=np.uint8)])
    rgba[:50, :, 3] = 0  # fully transparent band -> white
    cv2.imwrite(str(tmp_path / "a.png"), rgba[:, :, [2, 1, 0, 3]])
    loaded = load_image(tmp_path / "a.png")
    assert (loaded[:50] == 255).all()
    np.testing.assert_array_equal(preprocess(tmp_path / "a.png")[0], _upstream(rgba))


def test_16bit_pngs(tmp_path: pathlib.Path) -> None:
    Image = pytest.importorskip("PIL.Image")
    rng = np.random.default_rng(2)
    rgb16 = rng.integers(0, 65536, (30, 44, 3), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "rgb16.png"), rgb16[:, :, ::-1])
    np.testing.assert_array_equal(load_image(tmp_path / "rgb16.png"), (rgb16 >> 8).astype(np.uint8))
    # PIL reads 16-bit RGB the same way (high byte) ...
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "rgb16.png").convert("RGB")), rgb16 >> 8)
    gray16 = rng.integers(0, 65536, (30, 44), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "g16.png"), gray16)
    loaded = load_image(tmp_path / "g16.png")
    np.testing.assert_array_equal(loaded, np.repeat((gray16 >> 8).astype(np.uint8)[:, :, None], 3, axis=2))
    # ... but clips 16-bit greyscale to 255 (documented difference: we keep the high byte).
    assert (np.asarray(Image.open(tmp_path / "g16.png").convert("RGB")) == np.minimum(gray16, 255)[:, :, None]).all()


def test_exif_orientation_is_ignored_like_pil(tmp_path: pathlib.Path) -> None:
    Image = pytest.importorskip("PIL.Image")
    img = _photos()["rocket"][:200, :300]
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 CW" orientation tag
    Image.fromarray(img).save(tmp_path / "r.jpg", exif=exif, quality=95)
    loaded = load_image(tmp_path / "r.jpg")
    assert loaded.shape == (200, 300, 3)  # not rotated
    pil = np.asarray(Image.open(tmp_path / "r.jpg").convert("RGB")).astype(np.int16)
    assert np.abs(loaded.astype(np.int16) - pil).max() <= 2  # same JPEG, two decoders


def test_array_inputs() -> None:
    img = _photos()["chelsea"]
    np.testing.assert_array_equal(load_image(img.astype(np.float32) / 255), img)
    np.testing.assert_array_equal(load_image(img[:, :, :1]), np.repeat(img[:, :, :1], 3, axis=2))
    with pytest.raises(ValueError, match="dtype"):
        load_image(img.astype(np.int32))
    with pytest.raises(ValueError, match="shape"):
        load_image(np.zeros((4, 4, 5), np.uint8))


def test_bad_paths(tmp_path: pathlib.Path) -> None:
    with pytest.raises(FileNotFoundError):
        preprocess(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match="cannot decode"):
        preprocess(tmp_path / "bad.png")
    with pytest.raises(ValueError, match="no images"):
        preprocess([])


# ---------------------------------------------------------------------------------------------
# modes and batches


def test_pad_mode_pads_white_centred() -> None:
    img = np.zeros((640, 480, 3), np.uint8)  # black portrait -> 392 x 518 content
    out = preprocess(img, mode="pad")[0]
    assert out.shape == (3, 518, 518)
    left = (518 - 392) // 2
    assert (out[:, :, :left] == 1.0).all() and (out[:, :, left + 392 :] == 1.0).all()
    assert (out[:, :, left : left + 392] == 0.0).all()


def test_mixed_sizes_padded_with_warning(logged_warning) -> None:
    a = np.zeros((480, 640, 3), np.uint8)  # -> 392 x 518
    b = np.zeros((376, 1241, 3), np.uint8)  # -> 154 x 518
    with logged_warning("different shapes"):
        out = preprocess([a, b])
    assert out.shape == (2, 3, 392, 518)
    top = (392 - 154) // 2
    assert (
        (out[1, :, :top] == 1.0).all()
        and (out[1, :, top : top + 154] == 0.0).all()
        and (out[1, :, top + 154 :] == 1.0).all()
    )


def test_uint8_round_trip() -> None:
    img = _photos()["coffee"]
    out = preprocess(img)
    back = to_uint8_images(out)
    np.testing.assert_array_equal(back[0], resize_rgb(img, 350, 518))


@pytest.mark.parametrize("resample", ["pil", "cv2-cubic"])
def test_resize_rows_equal_full_resize_then_crop(resample: str) -> None:
    img = _photos()["rocket"]
    for h, w, rows in [(700, 518, (91, 609)), (427, 518, (10, 20)), (800, 640, (0, 518))]:
        full = resize_rgb(img, h, w, resample)  # type: ignore[arg-type]
        np.testing.assert_array_equal(resize_rgb(img, h, w, resample, rows), full[rows[0] : rows[1]])  # type: ignore[arg-type]

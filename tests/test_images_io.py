"""swiftjax.io.images: folder / glob / video listing, pixel conversions, up-front validation."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
from PIL import Image

from swiftjax.io.images import (
    ImageFiles,
    InputError,
    VideoFrames,
    list_frames,
    natural_key,
    to_rgb8,
    validate,
)

RNG = np.random.default_rng(0)


def _rgb(h=6, w=8, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _save(path, rgb):
    Image.fromarray(rgb).save(path)


def test_natural_key():
    names = ["img10.png", "img2.png", "IMG1.png", "img2b.png", "a.png"]
    assert sorted(names, key=natural_key) == ["a.png", "IMG1.png", "img2.png", "img2b.png", "img10.png"]


def test_folder_order_extensions_hidden_and_fingerprint(tmp_path):
    smooth = np.broadcast_to(np.linspace(0, 255, 8).astype(np.uint8)[None, :, None], (6, 8, 3)).copy()
    for name in ["f10.PNG", "f2.jpg", "f1.JpEg", "f3.bmp", "f4.tif", "f5.TIFF", "f6.webp"]:
        _save(tmp_path / name, smooth if name == "f1.JpEg" else _rgb())
    (tmp_path / "._f0.jpg").write_bytes(b"appledouble")
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "sub").mkdir()
    _save(tmp_path / "sub" / "f0.png", _rgb())
    src = list_frames(tmp_path)
    assert isinstance(src, ImageFiles)
    assert src.names == ["f1.JpEg", "f2.jpg", "f3.bmp", "f4.tif", "f5.TIFF", "f6.webp", "f10.PNG"]
    assert len(src) == 7
    fp = src.fingerprint()
    st = os.stat(tmp_path / "f10.PNG")
    assert fp[-1] == ("f10.PNG", st.st_size, st.st_mtime_ns)
    assert list_frames(tmp_path, stride=3).names == ["f1.JpEg", "f4.tif", "f10.PNG"]
    src = validate(src)
    assert src.sizes == [(6, 8)] * 7 and src.image_hw == (6, 8)
    np.testing.assert_array_equal(src.read(6), _rgb())  # PNG: exact, and RGB (not BGR) order
    batch = src.read_many([6, 0])
    assert batch.shape == (2, 6, 8, 3) and batch.dtype == np.uint8
    assert np.abs(batch[1].astype(int) - smooth).max() < 12  # lossy jpeg, same picture


def test_glob_recursive_names(tmp_path, monkeypatch):
    for d in ("seq00", "seq01"):
        (tmp_path / d / "cam").mkdir(parents=True)
        for k in (1, 10, 2):
            _save(tmp_path / d / "cam" / f"{k}.png", _rgb())
    (tmp_path / "seq00" / "cam" / "meta.json").write_text("{}")
    monkeypatch.chdir(tmp_path)
    src = list_frames("seq*/cam/*")
    assert src.names == [f"seq0{s}/cam/{k}.png" for s in (0, 1) for k in (1, 2, 10)]
    src = list_frames(str(tmp_path / "**" / "*.png"))
    assert src.names[:3] == ["seq00/cam/1.png", "seq00/cam/2.png", "seq00/cam/10.png"]
    with pytest.raises(InputError, match="no image files match"):
        list_frames(str(tmp_path / "*.jpg"))


def test_missing_and_empty_inputs(tmp_path):
    with pytest.raises(InputError, match="folder has no images"):
        list_frames(tmp_path)
    with pytest.raises(InputError, match="no such file, folder or glob pattern"):
        list_frames(tmp_path / "nope")
    (tmp_path / "notes.txt").write_text("not a video")
    with pytest.raises(InputError, match=r"notes\.txt: cannot open video"):
        list_frames(tmp_path / "notes.txt")
    with pytest.raises(InputError, match="stride"):
        list_frames(tmp_path, stride=0)
    with pytest.raises(InputError, match="no frames"):
        validate(ImageFiles([], description=str(tmp_path)))


def test_pixel_conversions_match_pil(tmp_path):
    rng = np.random.default_rng(1)
    rgba = rng.integers(0, 256, (5, 7, 4), dtype=np.uint8)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    # VGGT's loader: alpha_composite on an opaque white background, then RGB.
    white = Image.new("RGBA", (7, 5), (255, 255, 255, 255))
    ref = np.asarray(Image.alpha_composite(white, Image.open(tmp_path / "a.png")).convert("RGB"))
    gray = rng.integers(0, 256, (5, 7), dtype=np.uint8)
    Image.fromarray(gray, "L").save(tmp_path / "g.png")
    la = rng.integers(0, 256, (5, 7, 2), dtype=np.uint8)
    Image.fromarray(la, "LA").save(tmp_path / "la.png")
    g16 = rng.integers(0, 65536, (5, 7), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "g16.png"), g16)
    c16 = rng.integers(0, 65536, (5, 7, 3), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "c16.png"), c16[:, :, ::-1])  # cv2 writes BGR
    Image.fromarray(gray, "L").convert("P").save(tmp_path / "p.png")

    src = list_frames(tmp_path)
    assert src.names == ["a.png", "c16.png", "g16.png", "g.png", "la.png", "p.png"]  # 'g' < 'g.png'
    out = {n: src.read(i) for i, n in enumerate(src.names)}
    assert all(v.shape == (5, 7, 3) and v.dtype == np.uint8 for v in out.values())
    np.testing.assert_array_equal(out["a.png"], ref)  # PIL's integer compositing, exactly
    np.testing.assert_array_equal(out["g.png"], np.repeat(gray[:, :, None], 3, 2))
    np.testing.assert_array_equal(out["g16.png"], np.repeat((g16 >> 8).astype(np.uint8)[:, :, None], 3, 2))
    np.testing.assert_array_equal(out["c16.png"], (c16 >> 8).astype(np.uint8))
    # grey + alpha: PIL composites it as the RGBA image it converts to.
    la_rgba = Image.open(tmp_path / "la.png").convert("RGBA")
    ref_la = np.asarray(Image.alpha_composite(white, la_rgba).convert("RGB"))
    np.testing.assert_array_equal(out["la.png"], ref_la)
    np.testing.assert_array_equal(out["p.png"], np.repeat(gray[:, :, None], 3, 2))
    # The inference shim decodes files the same way (until one calls the other: no drift).
    try:
        from inference.preprocess import load_image
    except ImportError:
        return
    for i, n in enumerate(src.names):
        np.testing.assert_array_equal(out[n], load_image(src.paths[i]), err_msg=n)


def test_to_rgb8_float_and_unsupported():
    f = np.array([[[-0.5, 0.5, 2.0]]], np.float32)  # BGR
    np.testing.assert_array_equal(to_rgb8(f), [[[255, 128, 0]]])
    np.testing.assert_array_equal(to_rgb8(f, bgr=False), [[[0, 128, 255]]])
    rgba = np.array([[[10, 20, 30, 0], [10, 20, 30, 255]]], np.uint8)
    np.testing.assert_array_equal(to_rgb8(rgba, bgr=False), [[[255, 255, 255], [10, 20, 30]]])
    with pytest.raises(InputError, match="unsupported pixel type int32"):
        to_rgb8(np.zeros((2, 2, 3), np.int32), "x.tif")
    with pytest.raises(InputError, match="unsupported image layout"):
        to_rgb8(np.zeros((2, 2, 5), np.uint8))


def test_validate_corrupt_skip_and_mixed_sizes(tmp_path, logged_warning):
    for k in range(4):
        _save(tmp_path / f"{k}.png", _rgb(seed=k))
    (tmp_path / "2.png").write_bytes(b"\x89PNG garbage")
    (tmp_path / "3.png").write_bytes(b"")
    with pytest.raises(InputError, match=r"2\.png: cannot read image"):
        validate(list_frames(tmp_path))
    with logged_warning("skipping unreadable frame") as rec:
        src = validate(list_frames(tmp_path), skip_bad=True)
    assert len(rec) == 2
    assert src.names == ["0.png", "1.png"] and src.sizes == [(6, 8), (6, 8)]
    np.testing.assert_array_equal(src.read(1), _rgb(seed=1))
    _save(tmp_path / "2.png", _rgb(h=10, w=8))
    _save(tmp_path / "3.png", _rgb())
    with pytest.raises(InputError, match=r"0\.png is 8x6 but 2\.png is 8x10"):
        validate(list_frames(tmp_path))
    with pytest.raises(InputError, match="differ in size"):
        _ = list_frames(tmp_path).image_hw
    (tmp_path / "2.png").unlink()
    (tmp_path / "3.png").unlink()
    assert len(validate(list_frames(tmp_path))) == 2
    (tmp_path / "1.png").write_bytes(b"junk")
    (tmp_path / "0.png").unlink()
    with pytest.raises(InputError, match="none of the 1 images"), logged_warning(""):
        validate(list_frames(tmp_path), skip_bad=True)


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_truncated_file_is_caught_by_its_end_marker_or_a_decode(tmp_path, ext):
    img = cv2.GaussianBlur(_rgb(200, 300, seed=3), (9, 9), 3)
    _save(tmp_path / f"a{ext}", img)
    data = (tmp_path / f"a{ext}").read_bytes()
    (tmp_path / f"a{ext}").write_bytes(data[: len(data) // 3])
    src = list_frames(tmp_path)
    with pytest.raises(InputError, match=rf"a\{ext}: image file is truncated"):
        validate(src)  # the header alone is intact: the missing end marker gives it away
    with pytest.raises(InputError, match=rf"a\{ext}: (cannot decode image|corrupt image data)"):
        src.decode_check(0)  # a full decode catches it too (the end marker is checked first)


def test_read_error_names_file(tmp_path):
    _save(tmp_path / "a.png", _rgb())
    src = list_frames(tmp_path)
    (tmp_path / "a.png").write_bytes(b"junk")
    with pytest.raises(InputError, match=r"a\.png: cannot decode image"):
        src.read(0)


def _write_video(path, n=10, h=48, w=64):
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
    assert vw.isOpened()
    for k in range(n):
        frame = np.zeros((h, w, 3), np.uint8)
        frame[:, :, 2] = 20 * k + 10  # red channel (BGR) encodes the frame index
        frame[:, :, 0] = 200  # blue
        vw.write(frame)
    vw.release()


def test_video_stride_random_access(tmp_path):
    _write_video(tmp_path / "drive.avi")
    src = validate(list_frames(tmp_path / "drive.avi", stride=3))
    assert isinstance(src, VideoFrames)
    assert src.names == ["drive_000000.png", "drive_000003.png", "drive_000006.png", "drive_000009.png"]
    assert src.sizes == [(48, 64)] * 4
    st = os.stat(tmp_path / "drive.avi")
    assert src.fingerprint() == [("drive.avi[::3]", st.st_size, st.st_mtime_ns)]
    for i in [3, 0, 1, 1, 2, 0]:  # backwards, forwards and repeated reads
        rgb = src.read(i)
        assert rgb.shape == (48, 64, 3)
        assert abs(float(rgb[..., 0].mean()) - (20 * 3 * i + 10)) < 6  # red = RGB channel 0
        assert abs(float(rgb[..., 2].mean()) - 200) < 6
    assert src.read_many([2, 3]).shape == (2, 48, 64, 3)
    src.close()


def test_video_short_count_is_truncated(tmp_path, monkeypatch, logged_warning):
    _write_video(tmp_path / "v.avi", n=5)
    src = VideoFrames(tmp_path / "v.avi", frame_indices=[0, 2, 4, 6, 8])  # container "lies"
    with logged_warning("only 5 frames decode"):
        out = validate(src)
    assert out.names == ["v_000000.png", "v_000002.png", "v_000004.png"]


def test_missing_opencv_is_a_clear_error(tmp_path, monkeypatch):
    _save(tmp_path / "a.png", _rgb())
    src = list_frames(tmp_path)
    monkeypatch.setitem(sys.modules, "cv2", None)
    with pytest.raises(ImportError, match="opencv-python-headless"):
        src.read(0)


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_truncated_image_is_refused_before_the_run(tmp_path, ext, logged_warning):
    """A truncated image passes a header check alone and would abort the run mid-way, past
    --skip-bad: the end marker is checked up front."""
    img = (np.random.default_rng(0).random((40, 60, 3)) * 255).astype(np.uint8)
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"{k}{ext}"), img)
    raw = (tmp_path / f"1{ext}").read_bytes()
    (tmp_path / f"1{ext}").write_bytes(raw[: len(raw) * 3 // 4])
    with pytest.raises(InputError, match=rf"1\{ext}: image file is truncated"):
        validate(list_frames(tmp_path))
    with logged_warning("truncated"):
        src = validate(list_frames(tmp_path), skip_bad=True)
    assert src.names == [f"0{ext}", f"2{ext}"]


# ---------------------------------------- damage a header check misses (issue 25 #9 #23)


def _smooth_jpeg(path, seed=0):
    img = cv2.GaussianBlur(_rgb(60, 80, seed=seed), (5, 5), 0)
    cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
    return img


def test_jpeg_damaged_mid_file_is_refused_or_skipped(tmp_path, logged_warning):
    """Damaged mid-file but ending in FF D9: libjpeg decodes it with grey rows and only a
    warning, which swiftjax ignored; the decoder's warning is now a corrupt frame."""
    for k in range(3):
        _smooth_jpeg(tmp_path / f"{k}.jpg", seed=k)
    raw = bytearray((tmp_path / "1.jpg").read_bytes())
    mid = len(raw) // 2
    raw[mid : mid + 200] = bytes(200)
    (tmp_path / "1.jpg").write_bytes(bytes(raw))
    assert raw[-2:] == b"\xff\xd9"
    assert cv2.imread(str(tmp_path / "1.jpg")) is not None  # OpenCV returns pixels all the same
    with pytest.raises(InputError, match=r"1\.jpg: corrupt image data \(the decoder reported: Corrupt JPEG data"):
        validate(list_frames(tmp_path))
    with logged_warning(r"skipping unreadable frame: .*1\.jpg: corrupt image data"):
        src = validate(list_frames(tmp_path), skip_bad=True)
    assert src.names == ["0.jpg", "2.jpg"]
    assert len(validate(list_frames(tmp_path), decode=False)) == 3  # the header check alone misses it


def test_png_cut_inside_with_its_end_reappended_is_found_before_the_run(tmp_path, logged_warning):
    """A PNG cut in the middle with IEND re-appended passed the header and end-marker checks
    and failed only when its chunk was predicted, past --skip-bad."""
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"{k}.png"), cv2.GaussianBlur(_rgb(60, 80, seed=k), (5, 5), 0))
    raw = (tmp_path / "2.png").read_bytes()
    (tmp_path / "2.png").write_bytes(raw[: len(raw) // 2] + raw[-12:])  # ... + the IEND chunk
    with pytest.raises(InputError, match=r"2\.png: cannot decode image"):
        validate(list_frames(tmp_path))
    with logged_warning(r"2\.png"):
        src = validate(list_frames(tmp_path), skip_bad=True)
    assert src.names == ["0.png", "1.png"]
    np.testing.assert_array_equal(src.read(1)[..., ::-1], cv2.imread(str(tmp_path / "1.png")))


def test_glob_does_not_count_files_twice_through_a_link_loop(tmp_path, logged_warning):
    """`**` followed a directory link loop: 12 frames became 492."""
    (tmp_path / "seq" / "a").mkdir(parents=True)
    for k in range(4):
        _save(tmp_path / "seq" / "a" / f"{k}.png", _rgb(seed=k))
    os.symlink("..", tmp_path / "seq" / "a" / "loop")
    with logged_warning(r"matches are 4 files"):
        src = list_frames(str(tmp_path / "seq" / "**" / "*.png"))
    assert src.names == ["a/0.png", "a/1.png", "a/2.png", "a/3.png"]
    assert sorted(os.path.realpath(p) for p in src.paths) == sorted(
        os.path.realpath(tmp_path / "seq" / "a" / f"{k}.png") for k in range(4)
    )


def test_exif_rotated_frames_are_named_in_the_size_error(tmp_path, logged_warning):
    """Phone frames rotated by EXIF were refused by raw size with no hint."""
    _save(tmp_path / "0.jpg", _rgb(20, 30))
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 CW to display
    Image.fromarray(_rgb(30, 20)).save(tmp_path / "1.jpg", exif=exif)
    with pytest.raises(InputError, match=r"EXIF orientation is ignored .* 1\.jpg \(orientation 6\)"):
        validate(list_frames(tmp_path))
    (tmp_path / "1.jpg").unlink()
    Image.fromarray(_rgb(20, 30)).save(tmp_path / "1.jpg", exif=exif)
    with logged_warning(r"EXIF orientation .*1\.jpg: 6.*ignored"):
        validate(list_frames(tmp_path))


def test_timestamps_file_naming_a_frame_twice(tmp_path):
    from swiftjax.io.images import read_timestamps

    for k in range(3):
        _save(tmp_path / f"{k}.png", _rgb(seed=k))
    times = tmp_path / "rgb.txt"
    times.write_text("# t name\n1.0 rgb/0.png\n2.0 rgb/1.png\n3.0 rgb/2.png\n4.0 rgb/1.png\n")
    with pytest.raises(InputError, match=r"names frame 1\.png twice \(lines 3 and 5\)"):
        read_timestamps(times, list_frames(tmp_path))
    with pytest.raises(InputError, match="is a directory"):
        read_timestamps(tmp_path, list_frames(tmp_path))

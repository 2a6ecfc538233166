"""The user's camera inputs that ended in "0 points written", exit 0, or a misleading line
(issue 25 #15 #27 #28): implausible focal lengths, all-black masks, a mask path that is a file,
intrinsics given as the string the help promises."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from swiftjax import intrinsics, masks


def test_intrinsics_string_is_read_as_the_four_numbers(tmp_path):
    """`--intrinsics '100 100 99.5 29.5'` was read as a path ("does not exist")."""
    intr = intrinsics.read_intrinsics("100 100 99.5 29.5")
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == (100.0, 100.0, 99.5, 29.5)
    (tmp_path / "k.txt").write_text("200 210 99.5 29.5\n")
    assert intrinsics.read_intrinsics(tmp_path / "k.txt").fy == 210.0  # a file still wins
    with pytest.raises(intrinsics.IntrinsicsError, match=r"does not exist \(or give the four numbers"):
        intrinsics.read_intrinsics(tmp_path / "nope.txt")
    with pytest.raises(intrinsics.IntrinsicsError, match="focal lengths must be positive"):
        intrinsics.read_intrinsics("-1 100 99.5 29.5")


@pytest.mark.parametrize("fx", [1e300, 1e-300, 0.5, 1e6])
def test_implausible_focal_lengths_are_refused(fx):
    """fx = 1e300 / 1e-300 passed and every point fell outside the image (0 points, exit 0)."""
    intr = intrinsics.read_intrinsics(f"{fx!r} 100 99.5 29.5")
    with pytest.raises(intrinsics.IntrinsicsError, match=r"focal length fx=.* is implausible for a 200x60 image"):
        intr.check_image_size(60, 200)


def test_plausible_focal_lengths_pass():
    for fx in (2.0, 100.0, 1e5):  # 179 degrees ... 0.1 degree on a 200-pixel side
        intrinsics.read_intrinsics(f"{fx} {fx} 99.5 29.5").check_image_size(60, 200)


def _png(path, a):
    Image.fromarray(a).save(path)


def test_all_black_masks_and_a_mask_file_are_refused_before_work(tmp_path):
    g = intrinsics.preprocess_geometry(64, 96, "crop")
    (tmp_path / "m").mkdir()
    for name in ("a", "b"):
        _png(tmp_path / "m" / f"{name}.png", np.zeros((64, 96), np.uint8))
    md = masks.MaskDirectory(tmp_path / "m", ["a.jpg", "b.jpg"], g)
    with pytest.raises(masks.MaskError, match=r"every mask in .*m is black \(2 masks keep no pixel"):
        md.check()
    keep = np.zeros((64, 96), np.uint8)
    keep[10:20, 10:20] = 255
    _png(tmp_path / "m" / "b.png", keep)
    md.check()  # one mask keeps pixels: fine
    _png(tmp_path / "m" / "a.png", np.zeros((60, 96), np.uint8))
    with pytest.raises(masks.MaskError, match=r"a.png is 96x60 but the images are 96x64"):
        md.check()  # found before work, not when the chunk is read
    (tmp_path / "file.png").write_bytes(b"x")
    with pytest.raises(masks.MaskError, match=r"--mask-dir .*file.png is a file"):
        masks.MaskDirectory(tmp_path / "file.png", ["a.jpg"], g)

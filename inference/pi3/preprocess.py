"""π³'s official image loading rule (``pi3.utils.basic.load_images_as_tensor``).

All frames are resized, without cropping, to ONE size computed from the first frame: with
``s = sqrt(L / (W H))`` (``L`` = 255,000 pixels), ``k = round(W s / 14)``, ``m = round(H s / 14)``;
while ``14k x 14m > L``, decrement ``k`` if ``k / m > W s / (H s)`` (too wide) else ``m``; the
target is ``14k x 14m``.  Resampling is PIL's LANCZOS, reproduced exactly in NumPy by
:func:`inference.preprocess.resize_rgb` (``resample="pil-lanczos"``).  Pixel values end in
[0, 1]; π³ normalises inside the network.

KITTI's 1241 x 376 becomes 924 x 266 (66 x 19 patches; 924 x 280 would exceed the limit).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from swiftjax.intrinsics import PreprocessGeometry

from ..preprocess import ImageSource, Resample, load_image, resize_rgb

__all__ = ["PIXEL_LIMIT", "target_size_hw", "geometry", "preprocess"]

PIXEL_LIMIT = 255_000


def target_size_hw(height: int, width: int, pixel_limit: int = PIXEL_LIMIT, patch: int = 14) -> tuple[int, int]:
    """The official target ``(H, W)`` for a ``width x height`` first frame (module docstring)."""
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    scale = math.sqrt(pixel_limit / (width * height))
    w_target, h_target = width * scale, height * scale
    k, m = round(w_target / patch), round(h_target / patch)
    while (k * patch) * (m * patch) > pixel_limit:
        if k / m > w_target / h_target:
            k -= 1
        else:
            m -= 1
    return max(1, m) * patch, max(1, k) * patch


def geometry(height: int, width: int, pixel_limit: int = PIXEL_LIMIT) -> PreprocessGeometry:
    """Where a ``width x height`` frame's pixels land (no crop, no pad), for
    :func:`swiftjax.intrinsics.map_intrinsics` / ``map_mask``."""
    hw = target_size_hw(height, width, pixel_limit)
    return PreprocessGeometry(original_hw=(int(height), int(width)), resized_hw=hw, top=0, left=0, model_hw=hw)


def preprocess(
    images: ImageSource | Sequence[ImageSource],
    pixel_limit: int = PIXEL_LIMIT,
    resample: Resample = "pil-lanczos",
) -> np.ndarray:
    """Loads ``images`` and resizes all of them to the first one's target size.

    Returns:
        ``[N, 3, H, W]`` float32 RGB in [0, 1], ``H, W`` multiples of 14.
    """
    sources = [images] if isinstance(images, (str, os.PathLike, np.ndarray)) else list(images)
    if not sources:
        raise ValueError("no images given")
    out = []
    size: tuple[int, int] | None = None
    for src in sources:
        rgb = load_image(src)
        if size is None:
            size = target_size_hw(rgb.shape[0], rgb.shape[1], pixel_limit)
        out.append(resize_rgb(rgb, *size, resample=resample).transpose(2, 0, 1).astype(np.float32) / np.float32(255.0))
    return np.stack(out)

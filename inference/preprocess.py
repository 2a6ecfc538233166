"""Image loading and resizing for VGGT, as upstream's ``load_and_preprocess_images``.

Upstream (PIL): open, composite RGBA onto white, convert to RGB, resize with PIL's BICUBIC
to width 518 and ``height = round(h * (518 / w) / 14) * 14`` ("crop" mode, centre-cropping
rows when the result is taller than 518) or with the longer side 518 ("pad" mode, padding with
white to 518 x 518), then ``[0, 1]`` float CHW.  Images of different sizes are padded white to
the largest size.

Here decoding uses OpenCV and the resize is, by default, an exact NumPy re-implementation of
PIL's bicubic resampling (``resample="pil"``: the same fixed-point coefficients, the same
kernel widening on downscale, horizontal then vertical pass with 8-bit rounding in between),
so the model sees the same pixels it was trained with.  OpenCV's own resizers are available
as ``resample="cv2-cubic"`` and ``"cv2-area"``; they are faster but differ from PIL (OpenCV's
bicubic uses a = -0.75 and does not widen the kernel on downscale, so it aliases; INTER_AREA
is a box filter).  ``tests/test_inference_preprocess.py`` measures these differences.

Other deliberate differences from upstream (documented, tested):
    * 16-bit images keep their high byte (``v >> 8``).  PIL does the same for 16-bit RGB but
      clips 16-bit greyscale (mode ``I;16``) to 255, which turns most such images white.
    * Any alpha channel (RGBA, grey+alpha, palette with transparency) is composited onto white
      with PIL's integer ``alpha_composite`` arithmetic; PIL does that only for RGBA-mode images
      and silently drops the alpha of the other modes.
    * EXIF orientation is ignored, as in PIL's ``Image.open`` (``cv2.IMREAD_UNCHANGED``).
    * JPEG decoding by OpenCV's libjpeg and PIL's may differ by one grey level in rare pixels.
"""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Sequence
from typing import Literal, Union

import numpy as np

__all__ = [
    "preprocess",
    "preprocess_da3",
    "load_image",
    "target_size_hw",
    "resize_rgb",
    "to_uint8_images",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
]

logger = logging.getLogger("swiftjax." + __name__)

#: What Depth Anything 3's official API normalises with (outside the network).
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

ImageSource = Union[str, "os.PathLike[str]", np.ndarray]
Mode = Literal["crop", "pad"]
Resample = Literal["pil", "pil-lanczos", "cv2-cubic", "cv2-area"]

_PRECISION_BITS = 32 - 8 - 2  # PIL Resample.c, 8 bits per channel


def load_image(src: ImageSource) -> np.ndarray:
    """Decodes one image to ``[H, W, 3]`` uint8 RGB.

    Args:
        src: a file path (any format OpenCV decodes), or an array ``[H, W]``, ``[H, W, 1]``
            (grey), ``[H, W, 2]`` (grey + alpha), ``[H, W, 3]`` (RGB) or ``[H, W, 4]`` (RGBA) of
            dtype uint8, uint16 or float in [0, 1].  Arrays are in RGB(A) order; files are
            converted from OpenCV's BGR(A).
    """
    if isinstance(src, np.ndarray):
        arr = src
        bgr = False
    else:
        import cv2

        path = os.fspath(src)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"image not found: {path}")
        data = np.fromfile(path, dtype=np.uint8)  # works with non-ASCII paths, unlike cv2.imread
        arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if arr is None:
            raise ValueError(f"cannot decode image {path}")
        bgr = True
    arr = _to_uint8(arr)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 2, 3, 4) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"unsupported image shape {arr.shape}")
    channels = arr.shape[2]
    if channels in (3, 4) and bgr:
        arr = arr[:, :, [2, 1, 0, 3][:channels]]
    if channels in (2, 4):
        return _composite_on_white(arr[:, :, :-1], arr[:, :, -1])
    if channels == 1:
        return np.ascontiguousarray(np.repeat(arr, 3, axis=2))
    return np.ascontiguousarray(arr)


def _to_uint8(arr: np.ndarray) -> np.ndarray:
    if arr.dtype == np.uint8:
        return arr
    if arr.dtype == np.uint16:
        return (arr >> 8).astype(np.uint8)
    if np.issubdtype(arr.dtype, np.floating):
        return np.clip(np.round(arr.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    raise ValueError(f"unsupported image dtype {arr.dtype} (use uint8, uint16 or float in [0, 1])")


def _composite_on_white(color: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """PIL ``alpha_composite(white, image)`` in its exact integer arithmetic -> RGB uint8."""
    if color.shape[2] == 1:
        color = np.repeat(color, 3, axis=2)
    c = color.astype(np.int64)
    a = alpha.astype(np.int64)[:, :, None]
    tmp = 128 * (c * a + 255 * (255 - a)) + (0x80 << 7)
    out = ((((tmp >> 8) + tmp) >> 8) >> 7).astype(np.uint8)
    return np.where(a == 0, np.uint8(255), out)


def target_size_hw(height: int, width: int, mode: Mode = "crop", target: int = 518, patch: int = 14) -> tuple[int, int]:
    """Resized ``(H, W)`` before cropping/padding, with upstream's rounding (Python ``round``)."""
    if mode == "crop":
        new_w = target
        new_h = round(height * (new_w / width) / patch) * patch
    elif mode == "pad":
        if width >= height:
            new_w = target
            new_h = round(height * (new_w / width) / patch) * patch
        else:
            new_h = target
            new_w = round(width * (new_h / height) / patch) * patch
    else:
        raise ValueError(f"mode must be 'crop' or 'pad', got {mode!r}")
    if new_h < patch or new_w < patch:
        raise ValueError(f"a {width}x{height} image is too elongated: it would be resized to {new_w}x{new_h}")
    return int(new_h), int(new_w)


def _pil_bicubic(x: np.ndarray) -> np.ndarray:
    """PIL's bicubic kernel (a = -0.5), support 2."""
    a = -0.5
    x = np.abs(x)
    near = ((a + 2.0) * x - (a + 3.0)) * x * x + 1
    far = (((x - 5) * x + 8) * x - 4) * a
    return np.where(x < 1.0, near, np.where(x < 2.0, far, 0.0))


def _pil_lanczos(x: np.ndarray) -> np.ndarray:
    """PIL's LANCZOS kernel: ``sinc(x) sinc(x / 3)`` on ``[-3, 3)``, support 3 (π³'s resize)."""
    return np.where((x >= -3.0) & (x < 3.0), np.sinc(x) * np.sinc(x / 3.0), 0.0)


_PIL_FILTERS = {"bicubic": (_pil_bicubic, 2.0), "lanczos": (_pil_lanczos, 3.0)}


@functools.lru_cache(maxsize=32)
def _pil_coeffs(in_size: int, out_size: int, kernel: str = "bicubic") -> tuple[np.ndarray, np.ndarray]:
    """PIL's ``precompute_coeffs`` + ``normalize_coeffs_8bpc``: first input index per output and
    fixed-point weights ``[out_size, ksize]`` (zero beyond each output's window)."""
    filt, filter_support = _PIL_FILTERS[kernel]
    scale = in_size / out_size
    filterscale = max(scale, 1.0)
    support = filter_support * filterscale
    ksize = int(np.ceil(support)) * 2 + 1
    center = (np.arange(out_size) + 0.5) * scale
    xmin = np.maximum((center - support + 0.5).astype(np.int64), 0)  # C casts truncate
    xmax = np.minimum((center + support + 0.5).astype(np.int64), in_size) - xmin
    taps = np.arange(ksize)
    inside = taps[None, :] < xmax[:, None]
    w = np.where(inside, filt((taps[None, :] + xmin[:, None] - center[:, None] + 0.5) / filterscale), 0.0)
    total = w.sum(axis=1, keepdims=True)
    w = np.where(total != 0.0, w / np.where(total != 0.0, total, 1.0), w)
    fixed = np.trunc(w * (1 << _PRECISION_BITS) + np.where(w < 0, -0.5, 0.5)).astype(np.int64)
    fixed[~inside] = 0
    xmin.flags.writeable = False
    fixed.flags.writeable = False
    return xmin, fixed


def _pil_resample_axis(
    img: np.ndarray, out_size: int, axis: int, keep: tuple[int, int] | None = None, kernel: str = "bicubic"
) -> np.ndarray:
    """One PIL resampling pass along ``axis`` (0 rows, 1 columns) of ``[H, W, C]`` uint8.

    ``keep = (start, stop)`` computes only those output indices (each output is independent).
    """
    in_size = img.shape[axis]
    starts, weights = _pil_coeffs(in_size, out_size, kernel)
    if keep is not None:
        starts, weights = starts[keep[0] : keep[1]], weights[keep[0] : keep[1]]
        out_size = len(starts)
    src = np.moveaxis(img, axis, 0).astype(np.int64)  # [in, other, C]
    acc = np.full((out_size,) + src.shape[1:], 1 << (_PRECISION_BITS - 1), dtype=np.int64)
    for k in range(weights.shape[1]):
        idx = np.minimum(starts + k, in_size - 1)
        acc += src[idx] * weights[:, k].reshape((-1,) + (1,) * (src.ndim - 1))
    out = np.clip(acc >> _PRECISION_BITS, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(np.moveaxis(out, 0, axis))


def resize_rgb(
    img: np.ndarray, height: int, width: int, resample: Resample = "pil", rows: tuple[int, int] | None = None
) -> np.ndarray:
    """Resizes ``[H, W, 3]`` uint8 to ``[height, width, 3]`` uint8.

    ``"pil"`` reproduces ``PIL.Image.resize(..., BICUBIC)`` exactly, ``"pil-lanczos"``
    ``PIL.Image.resize(..., LANCZOS)`` (π³'s loader); ``"cv2-cubic"`` is
    ``cv2.INTER_CUBIC``; ``"cv2-area"`` is ``cv2.INTER_AREA`` when shrinking, INTER_CUBIC otherwise.
    ``rows = (start, stop)`` returns only those output rows (same values as resizing fully and
    cropping; with ``"pil"`` the other rows are not computed).
    """
    h0, w0 = img.shape[:2]
    if (h0, w0) == (height, width):
        return img[slice(*rows) if rows else slice(None)].copy()
    if resample in ("pil", "pil-lanczos"):
        kernel = "lanczos" if resample == "pil-lanczos" else "bicubic"
        # Pillow runs the horizontal pass first, except when the vertical pass shrinks the
        # image by more than twice as many pixels as the horizontal one (an order that matters
        # because of the 8-bit rounding in between; found and verified empirically against
        # Pillow 13 on hundreds of random sizes, see the tests).
        vertical_first = height < h0 and (h0 - height) > 2 * (w0 - width)
        passes = [(height, 0), (width, 1)] if vertical_first else [(width, 1), (height, 0)]
        out = img
        for size, axis in passes:
            if axis == 0 and size != h0:
                out = _pil_resample_axis(out, size, 0, keep=rows, kernel=kernel)
            elif axis == 1 and size != w0:
                out = _pil_resample_axis(out, size, 1, kernel=kernel)
        if rows is not None and height == h0:
            out = out[rows[0] : rows[1]]
        return np.ascontiguousarray(out)
    import cv2

    if resample == "cv2-cubic":
        interp = cv2.INTER_CUBIC
    elif resample == "cv2-area":
        interp = cv2.INTER_AREA if (height <= h0 and width <= w0) else cv2.INTER_CUBIC
    else:
        raise ValueError(f"resample must be 'pil', 'pil-lanczos', 'cv2-cubic' or 'cv2-area', got {resample!r}")
    out = cv2.resize(img, (width, height), interpolation=interp)
    return np.ascontiguousarray(out[rows[0] : rows[1]]) if rows else out


def _pad_white(img: np.ndarray, height: int, width: int) -> np.ndarray:
    """Centre-pads ``[3, h, w]`` float with 1.0 to ``[3, height, width]`` (extra pixel bottom/right)."""
    _, h, w = img.shape
    top, left = (height - h) // 2, (width - w) // 2
    out = np.ones((img.shape[0], height, width), dtype=img.dtype)
    out[:, top : top + h, left : left + w] = img
    return out


def preprocess(
    images: ImageSource | Sequence[ImageSource],
    mode: Mode = "crop",
    target_size: int = 518,
    resample: Resample = "pil",
) -> np.ndarray:
    """Loads and resizes images for VGGT.

    Args:
        images: one path/array or a sequence of them (see :func:`load_image`).
        mode: ``"crop"``: width ``target_size``, height rounded to a multiple of 14 and
            centre-cropped to ``target_size`` if taller; ``"pad"``: longer side
            ``target_size``, padded with white to a square.
        target_size: 518 for VGGT.
        resample: see :func:`resize_rgb`.

    Returns:
        ``[N, 3, H, W]`` float32 RGB in [0, 1] (``H, W`` multiples of 14).  If the images end
        up with different sizes, each is centre-padded with white to the largest ``H`` and ``W``
        (with a warning), as upstream does.
    """
    if isinstance(images, (str, os.PathLike, np.ndarray)):
        sources: Sequence[ImageSource] = [images]
    else:
        sources = list(images)
    if not sources:
        raise ValueError("no images given")
    out: list[np.ndarray] = []
    for src in sources:
        rgb = load_image(src)
        new_h, new_w = target_size_hw(rgb.shape[0], rgb.shape[1], mode, target_size)
        rows = None
        if mode == "crop" and new_h > target_size:  # centre crop, computing only the kept rows
            start = (new_h - target_size) // 2
            rows = (start, start + target_size)
        chw = resize_rgb(rgb, new_h, new_w, resample, rows).transpose(2, 0, 1).astype(np.float32) / np.float32(255.0)
        if mode == "pad":
            chw = _pad_white(chw, target_size, target_size)
        out.append(np.ascontiguousarray(chw))
    shapes = {a.shape for a in out}
    if len(shapes) > 1:
        max_h = max(a.shape[1] for a in out)
        max_w = max(a.shape[2] for a in out)
        logger.warning(f"images have different shapes {sorted(shapes)}; padding them with white to {max_h}x{max_w}")
        out = [_pad_white(a, max_h, max_w) for a in out]
    return np.stack(out)


def _cv2_resize(img: np.ndarray, height: int, width: int, enlarge: bool) -> np.ndarray:
    import cv2

    interp = cv2.INTER_CUBIC if enlarge else cv2.INTER_AREA
    return np.ascontiguousarray(cv2.resize(img, (width, height), interpolation=interp))


def preprocess_da3(
    images: ImageSource | Sequence[ImageSource], mode: str = "resize", process_res: int = 504
) -> np.ndarray:
    """Loads and resizes images as Depth Anything 3's official input processor does.

    Per image (:func:`swiftjax.intrinsics.da3_preprocess_geometry` gives the sizes): the longer
    side to ``process_res`` with OpenCV (``INTER_CUBIC`` when enlarging, ``INTER_AREA`` when
    shrinking), then ``"resize"``: a second OpenCV resize to the nearest multiples of 14 (cubic
    if a side grows, else area), or ``"crop"``: a centre crop down to the multiples below.
    Images of different final sizes are centre-cropped to the smallest ``H`` and ``W``.

    Returns ``[N, 3, H, W]`` float32 RGB in [0, 1] (``uint8 / 255``, as ``ToTensor``); the
    ImageNet normalisation (:data:`IMAGENET_MEAN`, :data:`IMAGENET_STD`) is the runner's.
    """
    from swiftjax.intrinsics import da3_preprocess_geometry, da3_sizes

    sources = [images] if isinstance(images, (str, os.PathLike, np.ndarray)) else list(images)
    if not sources:
        raise ValueError("no images given")
    out: list[np.ndarray] = []
    for src in sources:
        rgb = load_image(src)
        h0, w0 = rgb.shape[:2]
        geom = da3_preprocess_geometry(h0, w0, mode, process_res)
        h1, w1 = da3_sizes(h0, w0, process_res)
        if (h1, w1) != (h0, w0):
            rgb = _cv2_resize(rgb, h1, w1, enlarge=process_res > max(h0, w0))
        h, w = geom.model_hw
        if mode == "resize" and (h, w) != (h1, w1):
            rgb = _cv2_resize(rgb, h, w, enlarge=h > h1 or w > w1)
        elif mode == "crop":
            rgb = rgb[-geom.top : -geom.top + h, -geom.left : -geom.left + w]
        out.append(np.ascontiguousarray(rgb.transpose(2, 0, 1), dtype=np.float32) / np.float32(255.0))
    shapes = {a.shape for a in out}
    if len(shapes) > 1:
        h = min(a.shape[1] for a in out)
        w = min(a.shape[2] for a in out)
        logger.warning(f"images have different shapes {sorted(shapes)}; centre-cropping them to {h}x{w}")
        out = [
            a[:, (a.shape[1] - h) // 2 : (a.shape[1] - h) // 2 + h, (a.shape[2] - w) // 2 : (a.shape[2] - w) // 2 + w]
            for a in out
        ]
    return np.ascontiguousarray(np.stack(out))


def to_uint8_images(images: np.ndarray) -> np.ndarray:
    """``[S, 3, H, W]`` float in [0, 1] -> ``[S, H, W, 3]`` uint8 (exact for ``preprocess`` output)."""
    arr = np.asarray(images, dtype=np.float32)
    return np.clip(np.round(arr * 255.0), 0, 255).astype(np.uint8).transpose(0, 2, 3, 1).copy()

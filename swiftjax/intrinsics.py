"""The user's camera: intrinsics files and the preprocessing's pixel geometry (host NumPy).

``--intrinsics FILE`` gives the pinhole intrinsics at the ORIGINAL image size in one of three
formats (detected from the content):

* plain: one line ``fx fy cx cy`` (``#`` comments allowed);
* KITTI ``calib.txt``: the ``P0:`` line, a 3 x 4 projection ``P = K [I | 0]`` (12 numbers,
  row-major; the other lines are ignored);
* COLMAP ``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`` with model ``PINHOLE``
  (``fx fy cx cy``), ``SIMPLE_PINHOLE`` (``f cx cy``) or ``OPENCV`` (``fx fy cx cy k1 k2 p1
  p2`` with all four distortion coefficients zero).  Any other model, or distortion, is
  refused: VGGT's images are not undistorted here.  COLMAP puts the image origin at the
  top-left CORNER (pixel centres at ``u + 0.5``); swiftjax, like OpenCV and KITTI, puts pixel
  centres at integers, so ``cx = cx_colmap - 0.5`` (and ``+ 0.5`` on export,
  :mod:`swiftjax.io.colmap`).

The images reach VGGT through :func:`inference.preprocess.preprocess` (resize so that the
width is 518 -- or the longer side in ``"pad"`` mode -- with the height rounded to a multiple
of 14, then a centre crop of the rows to 518 or a white pad to 518 x 518).  The resize maps
continuous image coordinates with the corner origin linearly (PIL/OpenCV sample output pixel
``i`` at input ``(i + 1/2) W0 / W - 1/2``), so with integer pixel centres::

    u' = s_x (u + 1/2) - 1/2 + left,   s_x = W / W0          (W: resized width)
    v' = s_y (v + 1/2) - 1/2 + top,    s_y = H / H0          (H: resized height)

(``top < 0`` for a crop, ``> 0`` for a pad), hence ``fx' = s_x fx``, ``cx' = s_x (cx + 1/2) -
1/2 + left`` and likewise for y.  Because ``H`` is rounded to a multiple of 14, ``s_x != s_y``
in general (KITTI's 1241 x 376 -> 518 x 154: ``s_x = 0.41740``, ``s_y = 0.40957``): a single
focal scale would be wrong by 2 %.  :func:`preprocess_geometry` reproduces
``inference.preprocess.target_size_hw`` without importing ``inference`` (whose package
imports torch); the tests check the two agree and that a dot drawn in an image lands where
:func:`map_points` says after the real preprocessing.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
from typing import Literal

import numpy as np

from swiftjax.errors import SwiftjaxError

__all__ = [
    "IntrinsicsError",
    "CameraIntrinsics",
    "read_intrinsics",
    "parse_intrinsics",
    "PreprocessGeometry",
    "preprocess_geometry",
    "da3_sizes",
    "da3_preprocess_geometry",
    "map_intrinsics",
    "unmap_intrinsics",
    "map_points",
    "map_mask",
]

Mode = Literal["crop", "pad"]


class IntrinsicsError(SwiftjaxError, ValueError):
    """An intrinsics file that cannot be used (the message names the file, line and problem)."""


@dataclasses.dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics at the original image size, pixel centres at integers (OpenCV).

    ``width``/``height`` are the image size the file states (COLMAP), else ``None``.
    ``kind`` is ``"plain"``, ``"kitti"`` or ``"colmap"``.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int | None = None
    height: int | None = None
    kind: str = "plain"
    source: str = ""

    @property
    def K(self) -> np.ndarray:
        """``[3, 3]`` float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def check_image_size(self, height: int, width: int) -> None:
        """Raise :class:`IntrinsicsError` if the file's size differs from the images' or the
        principal point lies outside the image (``[-1/2, W - 1/2] x [-1/2, H - 1/2]``)."""
        where = self.source or "intrinsics"
        if self.width is not None and (self.width, self.height) != (width, height):
            raise IntrinsicsError(
                f"{where}: the camera is {self.width}x{self.height} but the images are {width}x{height}"
            )
        side = max(width, height)
        for name, f in (("fx", self.fx), ("fy", self.fy)):
            if not (FOCAL_RANGE[0] * side <= f <= FOCAL_RANGE[1] * side):
                fov = 2 * math.degrees(math.atan2(side / 2, f))
                raise IntrinsicsError(
                    f"{where}: focal length {name}={f:g} px is implausible for a {width}x{height} image (a field "
                    f"of view of {fov:.3g} degrees; allowed: {FOCAL_RANGE[0]:g} to {FOCAL_RANGE[1]:g} x the "
                    f"image's larger side); every point would project outside the image or onto one pixel"
                )
        if not (-0.5 <= self.cx <= width - 0.5 and -0.5 <= self.cy <= height - 0.5):
            raise IntrinsicsError(
                f"{where}: principal point ({self.cx:g}, {self.cy:g}) lies outside the {width}x{height} image"
            )

    def to_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


#: Focal lengths accepted, as multiples of the image's larger side: fields of view from
#: about 179 degrees (0.01) to 0.06 degrees (1000).  fx = 1e300 or 1e-300 passed every check
#: and the run wrote "0 points" with exit 0.
FOCAL_RANGE = (0.01, 1000.0)


def _floats(tokens: list[str], where: str) -> list[float]:
    try:
        vals = [float(t) for t in tokens]
    except ValueError:
        raise IntrinsicsError(f"{where}: expected numbers, got {' '.join(tokens)!r}") from None
    if not all(math.isfinite(v) for v in vals):
        raise IntrinsicsError(f"{where}: non-finite value in {' '.join(tokens)!r}")
    return vals


def _check_focal(fx: float, fy: float, where: str) -> None:
    if fx <= 0 or fy <= 0:
        raise IntrinsicsError(f"{where}: focal lengths must be positive, got fx={fx:g}, fy={fy:g}")


_COLMAP_PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "OPENCV": 8}
_COLMAP_OTHER = {
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV_FISHEYE",
    "FULL_OPENCV",
    "FOV",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE",
}


def _parse_colmap(lines: list[tuple[int, list[str]]], name: str) -> CameraIntrinsics:
    cams = []
    for n, tok in lines:
        where = f"{name}: line {n}"
        model = tok[1].upper() if len(tok) > 1 else ""
        if model not in _COLMAP_PARAMS:
            why = "distortion models are not supported: undistort the images, then " if model in _COLMAP_OTHER else ""
            raise IntrinsicsError(
                f"{where}: COLMAP camera model {tok[1]!r} is not supported ({why}use PINHOLE, "
                "SIMPLE_PINHOLE or OPENCV with zero distortion)"
            )
        want = _COLMAP_PARAMS[model]
        if len(tok) != 4 + want:
            raise IntrinsicsError(f"{where}: a {model} camera needs {want} parameters, got {len(tok) - 4}")
        try:
            w, h = int(tok[2]), int(tok[3])
        except ValueError:
            raise IntrinsicsError(f"{where}: WIDTH and HEIGHT must be integers, got {tok[2]!r} {tok[3]!r}") from None
        if w <= 0 or h <= 0:
            raise IntrinsicsError(f"{where}: image size must be positive, got {w}x{h}")
        p = _floats(tok[4:], where)
        if model == "SIMPLE_PINHOLE":
            fx = fy = p[0]
            cx, cy = p[1], p[2]
        else:
            fx, fy, cx, cy = p[:4]
            if model == "OPENCV" and any(v != 0.0 for v in p[4:]):
                raise IntrinsicsError(
                    f"{where}: OPENCV camera with non-zero distortion {p[4:]} (undistort the images "
                    "first and give a PINHOLE camera)"
                )
        _check_focal(fx, fy, where)
        cams.append(CameraIntrinsics(fx, fy, cx - 0.5, cy - 0.5, w, h, "colmap", name))
    if len({dataclasses.astuple(c) for c in cams}) > 1:
        raise IntrinsicsError(f"{name}: {len(cams)} different COLMAP cameras; give the one camera of the sequence")
    return cams[0]


def _parse_kitti(n: int, tok: list[str], name: str) -> CameraIntrinsics:
    where = f"{name}: line {n}"
    if len(tok) != 13:
        raise IntrinsicsError(f"{where}: 'P0:' needs 12 numbers (a 3x4 projection matrix), got {len(tok) - 1}")
    P = np.asarray(_floats(tok[1:], where)).reshape(3, 4)
    if P[1, 0] != 0 or P[2, 0] != 0 or P[2, 1] != 0 or P[2, 2] != 1 or P[0, 1] != 0:
        raise IntrinsicsError(
            f"{where}: P0 is not K [I | t] with K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]: {P[:, :3].tolist()}"
        )
    _check_focal(P[0, 0], P[1, 1], where)
    return CameraIntrinsics(float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2]), kind="kitti", source=name)


def _looks_colmap(tok: list[str]) -> bool:
    """``CAMERA_ID MODEL ...``: a known model name, or an integer id, a name and >= 3 more tokens."""
    if len(tok) < 2:
        return False
    if tok[1].upper() in _COLMAP_PARAMS or tok[1].upper() in _COLMAP_OTHER:
        return True
    return len(tok) >= 5 and tok[0].isdigit() and tok[1][:1].isalpha()


def parse_intrinsics(text: str, name: str = "intrinsics") -> CameraIntrinsics:
    """Parse the content of an intrinsics file (module docstring for the formats)."""
    lines = []
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if line:
            lines.append((n, line.split()))
    if not lines:
        raise IntrinsicsError(f"{name}: no intrinsics found (empty or comments only)")
    kitti = [(n, tok) for n, tok in lines if tok[0] == "P0:"]
    if kitti:
        return _parse_kitti(*kitti[0], name)
    if any(tok[0].endswith(":") for _, tok in lines):
        raise IntrinsicsError(f"{name}: looks like a KITTI calib.txt but has no 'P0:' line")
    if any(_looks_colmap(tok) for _, tok in lines):
        return _parse_colmap(lines, name)
    if len(lines) != 1:
        raise IntrinsicsError(
            f"{name}: expected one line 'fx fy cx cy', a KITTI 'P0:' line or COLMAP cameras, "
            f"got {len(lines)} lines of numbers"
        )
    n, tok = lines[0]
    where = f"{name}: line {n}"
    if len(tok) != 4:
        raise IntrinsicsError(f"{where}: expected 4 numbers 'fx fy cx cy', got {len(tok)}")
    fx, fy, cx, cy = _floats(tok, where)
    _check_focal(fx, fy, where)
    return CameraIntrinsics(fx, fy, cx, cy, kind="plain", source=name)


def _is_inline(text: str) -> bool:
    """Whether ``text`` is the four numbers ``fx fy cx cy`` themselves."""
    fields = text.split()
    try:
        return len(fields) == 4 and all(isinstance(float(f), float) for f in fields)
    except ValueError:
        return False


def read_intrinsics(path: str | os.PathLike[str]) -> CameraIntrinsics:
    """Read ``path`` (plain, KITTI ``calib.txt`` or COLMAP ``cameras.txt``), or take ``path``
    itself when it is no file but the four numbers ``'fx fy cx cy'`` (as ``--intrinsics``'s
    help says); :class:`IntrinsicsError` naming the file (and line) when it does not exist or
    cannot be used."""
    p = pathlib.Path(path)
    if not p.exists() and _is_inline(os.fspath(path)):  # --intrinsics '100 100 99.5 29.5'
        return parse_intrinsics(os.fspath(path), "--intrinsics string")
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise IntrinsicsError(
            f"intrinsics file {p} does not exist (or give the four numbers: --intrinsics 'fx fy cx cy')"
        ) from None
    except (OSError, UnicodeDecodeError) as err:
        raise IntrinsicsError(f"intrinsics file {p} cannot be read: {err}") from None
    return parse_intrinsics(text, str(p))


# ---------------------------------------------------------------------- preprocessing map


@dataclasses.dataclass(frozen=True)
class PreprocessGeometry:
    """Where the original image's pixels land in the model's image.

    ``original_hw`` ``(H0, W0)`` is resized to ``resized_hw`` ``(H, W)`` and placed with its
    top-left corner at ``(top, left)`` of the ``model_hw`` image (negative: rows cropped).
    """

    original_hw: tuple[int, int]
    resized_hw: tuple[int, int]
    top: int
    left: int
    model_hw: tuple[int, int]

    @property
    def scale_xy(self) -> tuple[float, float]:
        return self.resized_hw[1] / self.original_hw[1], self.resized_hw[0] / self.original_hw[0]

    @property
    def is_identity(self) -> bool:
        return self.original_hw == self.resized_hw == self.model_hw and self.top == self.left == 0


def preprocess_geometry(
    height: int, width: int, mode: Mode = "crop", target: int = 518, patch: int = 14
) -> PreprocessGeometry:
    """The geometry of ``inference.preprocess.preprocess`` for one ``height x width`` image.

    Same rounding as ``target_size_hw`` (Python ``round`` of ``H0 * target / W0 / patch``).
    """
    if height < 1 or width < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if mode not in ("crop", "pad"):
        raise ValueError(f"mode must be 'crop' or 'pad', got {mode!r}")
    if mode == "crop" or width >= height:
        new_w = target
        new_h = round(height * (new_w / width) / patch) * patch
    else:
        new_h = target
        new_w = round(width * (new_h / height) / patch) * patch
    if new_h < patch or new_w < patch:
        raise ValueError(f"a {width}x{height} image is too elongated: it would be resized to {new_w}x{new_h}")
    if mode == "crop":
        top = -((new_h - target) // 2) if new_h > target else 0
        model = (min(new_h, target), new_w)
        left = 0
    else:
        top, left = (target - new_h) // 2, (target - new_w) // 2
        model = (target, target)
    return PreprocessGeometry((int(height), int(width)), (int(new_h), int(new_w)), int(top), int(left), model)


def da3_sizes(height: int, width: int, process_res: int = 504) -> tuple[int, int]:
    """Depth Anything 3's boundary resize (official ``upper_bound_*``): the longer side becomes
    ``process_res``, each side ``max(1, round(side * process_res / longer))`` (Python ``round``,
    half to even); unchanged when the longer side already is ``process_res``."""
    longest = max(height, width)
    if longest == process_res:
        return int(height), int(width)
    scale = process_res / float(longest)
    return max(1, int(round(height * scale))), max(1, int(round(width * scale)))


def da3_preprocess_geometry(
    height: int, width: int, mode: str = "resize", process_res: int = 504, patch: int = 14
) -> PreprocessGeometry:
    """The geometry of ``inference.preprocess.preprocess_da3`` (the official DA3 input processor).

    :func:`da3_sizes`, then each side becomes a multiple of ``patch``: ``"resize"``
    (``upper_bound_resize``, the official default) resizes again to the nearest multiple (ties
    round up), ``"crop"`` (``upper_bound_crop``) centre-crops down to the multiple below
    (offset ``(old - new) // 2``).  Both resizes are pixel-centre scalings, so together they
    are one (``scale_xy`` = final / original size).  KITTI 1241 x 376 -> 504 x 153 -> 504 x 154.

    Raises ``ValueError`` when a side would end up below one patch (the network cannot take it).
    """
    if height < 1 or width < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if mode not in ("resize", "crop"):
        raise ValueError(f"DA3 preprocessing mode must be 'resize' or 'crop', got {mode!r}")
    h1, w1 = da3_sizes(height, width, process_res)
    if mode == "resize":

        def nearest(x: int) -> int:
            down = (x // patch) * patch
            return down + patch if (down + patch - x) <= (x - down) else down

        h, w = nearest(h1), nearest(w1)
        resized, top, left = (h, w), 0, 0
    else:
        h, w = (h1 // patch) * patch, (w1 // patch) * patch
        resized, top, left = (h1, w1), -((h1 - h) // 2), -((w1 - w) // 2)
    if h < patch or w < patch:
        raise ValueError(
            f"a {width}x{height} image is too elongated for Depth Anything 3: it would become {w}x{h} pixels "
            f"(each side must be at least {patch})"
        )
    return PreprocessGeometry((int(height), int(width)), resized, int(top), int(left), (int(h), int(w)))


def _affine(geom: PreprocessGeometry) -> np.ndarray:
    """``A [3, 3]`` with ``(u', v', 1) = A (u, v, 1)`` (integer pixel centres, module docstring)."""
    sx, sy = geom.scale_xy
    return np.array(
        [
            [sx, 0.0, 0.5 * sx - 0.5 + geom.left],
            [0.0, sy, 0.5 * sy - 0.5 + geom.top],
            [0.0, 0.0, 1.0],
        ]
    )


def map_points(uv: np.ndarray, geom: PreprocessGeometry) -> np.ndarray:
    """Original pixel coordinates ``[..., 2]`` -> model pixel coordinates ``[..., 2]``."""
    uv = np.asarray(uv, np.float64)
    A = _affine(geom)
    return uv @ A[:2, :2].T + A[:2, 2]


def map_intrinsics(K: np.ndarray, geom: PreprocessGeometry) -> np.ndarray:
    """Original-size ``K [3, 3]`` -> the model resolution's ``A K`` (``fx' = s_x fx``, ``cx' =
    s_x (cx + 1/2) - 1/2 + left``, ...)."""
    return _affine(geom) @ np.asarray(K, np.float64)


def unmap_intrinsics(K: np.ndarray, geom: PreprocessGeometry) -> np.ndarray:
    """The inverse of :func:`map_intrinsics`: model-resolution ``K`` -> original size."""
    return np.linalg.solve(_affine(geom), np.asarray(K, np.float64))


def map_mask(mask: np.ndarray, geom: PreprocessGeometry) -> np.ndarray:
    """An original-size keep-mask ``[H0, W0]`` (bool) -> the model's ``[H, W]`` bool.

    Nearest-neighbour resize on the pixel-centre map (model pixel ``i`` takes original pixel
    ``floor((i + 1/2) / s)``), then the same crop / pad as the image; padding is NOT kept
    (it shows nothing of the scene).
    """
    m = np.asarray(mask, bool)
    if m.shape != geom.original_hw:
        raise ValueError(f"mask has shape {m.shape}, expected the image's {geom.original_hw}")
    H, W = geom.resized_hw
    rows = np.minimum(((np.arange(H) + 0.5) * geom.original_hw[0] / H).astype(np.int64), geom.original_hw[0] - 1)
    cols = np.minimum(((np.arange(W) + 0.5) * geom.original_hw[1] / W).astype(np.int64), geom.original_hw[1] - 1)
    resized = m[rows[:, None], cols[None, :]]
    out = np.zeros(geom.model_hw, bool)
    mh, mw = geom.model_hw
    r0, c0 = max(geom.top, 0), max(geom.left, 0)  # destination
    s0, t0 = max(-geom.top, 0), max(-geom.left, 0)  # source
    nh, nw = min(H - s0, mh - r0), min(W - t0, mw - c0)
    out[r0 : r0 + nh, c0 : c0 + nw] = resized[s0 : s0 + nh, t0 : t0 + nw]
    return out

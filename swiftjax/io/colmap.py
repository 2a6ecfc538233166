"""Export a reconstruction as a COLMAP sparse model, binary (``cameras.bin``, ``images.bin``,
``points3D.bin``) and/or text (``cameras.txt``, ``images.txt``, ``points3D.txt``).

The model opens in COLMAP's GUI, ``pycolmap.Reconstruction(dir)``, gsplat's and nerfstudio's
COLMAP loaders.  Formats (COLMAP documentation, "Output format"; binary = the same records,
little-endian, no padding):

* cameras: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``; one ``PINHOLE`` camera (``fx fy cx
  cy``, model id 1) per distinct (intrinsics, image size).  Binary record: ``uint32 id,
  int32 model, uint64 width, uint64 height, float64 params[4]``.
* images: ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then the ``POINTS2D[]`` as
  ``(X, Y, POINT3D_ID)``.  The pose is **world-to-camera** (``x_cam = R x_world + t``),
  the quaternion Hamilton, scalar first.  Binary: ``uint32 id, float64 q[4], float64
  t[3], uint32 camera_id, NAME\\0, uint64 num_points2D, (float64 x, float64 y, int64
  point3D_id)[]``.
* points3D: ``POINT3D_ID X Y Z R G B ERROR TRACK[]`` with the track as ``(IMAGE_ID,
  POINT2D_IDX)``.  Binary: ``uint64 id, float64 xyz[3], uint8 rgb[3], float64 error,
  uint64 track_length, (uint32 image_id, uint32 point2D_idx)[]``.

**Observations.**  A dense reconstruction has no feature tracks; each exported point comes
from one pixel of one frame, and that pixel is its observation (``observations=(image_index,
xy)``, one per point): the track has length 1 and the image lists the point among its
``POINTS2D``.  Loaders need this: gsplat's depth supervision indexes the points of every
image by name, nerfstudio's ``max_2D_matches_per_3D_point`` stacks each track.

**Pixel convention.**  COLMAP's image coordinates put the top-left *corner* of the image at
(0, 0), so the centre of the top-left pixel is (0.5, 0.5) (COLMAP docs on feature import;
pycolmap/panorama.py says the same, and a default COLMAP camera has ``cx = width / 2``).
swiftjax, like VGGT's unprojection ``x = (u - cx) d / fx``, puts pixel centres at integers.
A point seen at the centre of pixel ``u`` therefore has COLMAP coordinate ``u + 0.5``, and
we write ``cx_colmap = cx + 0.5``, ``cy_colmap = cy + 0.5`` and observations ``xy + 0.5``
(``pixel_offset``; focal lengths are unchanged).  Each file is written atomically.
"""

from __future__ import annotations

import os
import pathlib
import re
import struct
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import numpy as np

from swiftjax import so3
from swiftjax.io.atomic import atomic_write

__all__ = ["Observations", "image_names", "world_to_camera_qt", "write_colmap", "write_colmap_text"]

PathLike = str | os.PathLike[str]

_ORTHO_TOL = 1e-4  # max |R^T R - I| accepted for a camera-to-world rotation
_BATCH = 200_000  # points formatted / packed per operation
_PINHOLE = 1  # COLMAP's model id of PINHOLE
_from_matrix = jax.jit(so3.from_matrix)  # compiles once per (N, dtype)


class Observations(NamedTuple):
    """One 2-D observation per 3-D point: point ``j`` is seen in image ``image_index[j]``
    (0-based, input order) at ``xy[j]`` (pixels, integer pixel centres, before
    ``pixel_offset``)."""

    image_index: np.ndarray  # [M] int
    xy: np.ndarray  # [M, 2] float


def image_names(names: Sequence[str]) -> list[str]:
    """The PNG file names of frames ``names`` in ``colmap/images/``: the name with its suffix
    replaced by ``.png`` (``a.jpg -> a.png``; subfolders kept; white space, which COLMAP's
    text format cannot hold, replaced by ``_``), or ``.png`` appended to the whole name where
    two frames would collide (``a.jpg`` and ``a.png`` in one folder)."""
    clean = [re.sub(r"\s", "_", str(n)) for n in names]
    out = [str(pathlib.PurePosixPath(n).with_suffix(".png")) for n in clean]
    seen: dict[str, int] = {}
    for name in out:
        seen[name] = seen.get(name, 0) + 1
    return [o if seen[o] == 1 or n == o else f"{n}.png" for n, o in zip(clean, out)]


def _float_format(dtype: np.dtype) -> str:
    """Shortest printf format that round-trips ``dtype`` exactly."""
    return {np.dtype(np.float16): "%.5g", np.dtype(np.float32): "%.9g"}.get(np.dtype(dtype), "%.17g")


def world_to_camera_qt(cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP pose of camera-to-world matrices.

    Args:
        cam_to_world: ``[N, 4, 4]`` (or ``[N, 3, 4]``) rigid camera-to-world transforms.

    Returns:
        ``q_wxyz [N, 4]`` float64 unit quaternions of ``R_cw = R^T`` (scalar first, ``qw >= 0``)
        and ``t [N, 3]`` float64 translations ``t_cw = -R^T c``, so ``x_cam = R_cw x + t_cw``.

    The quaternion comes from :func:`swiftjax.so3.from_matrix` (Shepperd), jitted and run in
    float64 (a scoped ``jax.enable_x64``); a new ``N`` triggers one recompile.
    """
    c2w = np.asarray(cam_to_world, dtype=np.float64)
    r_cw = np.swapaxes(c2w[:, :3, :3], -1, -2)
    t_cw = -np.einsum("nij,nj->ni", r_cw, c2w[:, :3, 3])
    with jax.enable_x64(True):  # scoped: the export keeps float64 poses exact to ~1e-15
        q_xyzw = np.array(_from_matrix(r_cw), dtype=np.float64)
    q_xyzw /= np.linalg.norm(q_xyzw, axis=-1, keepdims=True)
    return q_xyzw[:, [3, 0, 1, 2]], t_cw


def _validate(cam_to_world: np.ndarray, intrinsics: np.ndarray, names: Sequence[str], sizes: np.ndarray) -> None:
    n = len(names)
    if cam_to_world.shape not in ((n, 4, 4), (n, 3, 4)):
        raise ValueError(f"COLMAP export: cam_to_world has shape {cam_to_world.shape}, expected [{n}, 4, 4]")
    if intrinsics.shape != (n, 3, 3):
        raise ValueError(f"COLMAP export: intrinsics has shape {intrinsics.shape}, expected [{n}, 3, 3]")
    if sizes.shape != (n, 2):
        raise ValueError(f"COLMAP export: image_size must be (width, height) or [{n}, 2], got {sizes.shape}")
    if not (np.isfinite(cam_to_world).all() and np.isfinite(intrinsics).all()):
        bad = np.flatnonzero(~(np.isfinite(cam_to_world).all((1, 2)) & np.isfinite(intrinsics).all((1, 2))))
        raise ValueError(f"COLMAP export: image {bad[0]} ({names[bad[0]]}) has a non-finite pose or intrinsics")
    r = cam_to_world[:, :3, :3].astype(np.float64)
    err = np.abs(np.swapaxes(r, -1, -2) @ r - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(r)
    bad = np.flatnonzero((err > _ORTHO_TOL) | (det <= 0))
    if len(bad):
        i = bad[0]
        raise ValueError(
            f"COLMAP export: pose {i} ({names[i]}) is not a rotation (|R^T R - I| = {err[i]:.2g}, "
            f"det = {det[i]:.4g}); COLMAP needs rigid camera-to-world poses (remove any scale first)"
        )
    k = intrinsics
    bad = np.flatnonzero((np.abs(k[:, 0, 1]) > 0) | (k[:, 1, 0] != 0) | (k[:, 2, :2] != 0).any(-1) | (k[:, 2, 2] != 1))
    if len(bad):
        raise ValueError(
            f"COLMAP export: intrinsics {bad[0]} ({names[bad[0]]}) is not a zero-skew pinhole K "
            f"[[fx,0,cx],[0,fy,cy],[0,0,1]]: {k[bad[0]].tolist()}"
        )
    if (k[:, 0, 0] <= 0).any() or (k[:, 1, 1] <= 0).any() or (sizes <= 0).any():
        raise ValueError("COLMAP export: focal lengths and image sizes must be positive")
    for i, name in enumerate(names):
        if not name or any(ch.isspace() for ch in name):
            raise ValueError(f"COLMAP export: image name {name!r} (image {i}) is empty or contains whitespace")
    if len(set(names)) != n:
        raise ValueError("COLMAP export: image names must be unique")


def write_colmap(
    model_dir: PathLike,
    cam_to_world: np.ndarray,
    intrinsics: np.ndarray,
    names: Sequence[str],
    image_size: tuple[int, int] | np.ndarray,
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    errors: np.ndarray | None = None,
    observations: Observations | tuple[np.ndarray, np.ndarray] | None = None,
    pixel_offset: float = 0.5,
    binary: bool = True,
    text: bool = False,
) -> pathlib.Path:
    """Write a COLMAP sparse model (binary and/or text files) to ``model_dir``.

    Args:
        model_dir: output folder (created if missing), e.g. ``colmap/sparse/0``.
        cam_to_world: ``[N, 4, 4]`` camera-to-world, orthonormal rotation (metric, no scale).
        intrinsics: ``[N, 3, 3]`` zero-skew pinhole ``K`` with integer pixel centres.
        names: ``N`` image file names, relative to the image folder (no whitespace).
        image_size: ``(width, height)`` for every image, or ``[N, 2]`` per image.
        points: ``[M, 3]`` world points, or None for an empty ``points3D``.
        colors: ``[M, 3]`` uint8 RGB (default grey 128).
        errors: ``[M]`` per-point reprojection error in pixels (default 0).
        observations: :class:`Observations` (one per point), or None for empty tracks.
        pixel_offset: added to ``cx, cy`` and to the observations (0.5: integer pixel
            centres -> COLMAP's corner origin).
        binary, text: which files to write (at least one).

    Returns:
        ``model_dir`` as a Path.  Image ids are ``1..N`` in input order; camera ids ``1..C`` in
        order of first use; point ids ``1..M``; an image's ``POINTS2D`` are its observations
        in point order.

    Raises:
        ValueError: any bad input, before anything is written.
    """
    names = [str(n) for n in names]
    n = len(names)
    c2w = np.asarray(cam_to_world)
    k = np.asarray(intrinsics, dtype=np.float64)
    sizes = np.asarray(image_size, dtype=np.int64)
    if sizes.shape == (2,):
        sizes = np.broadcast_to(sizes, (n, 2))
    if not (binary or text):
        raise ValueError("COLMAP export: choose binary and/or text output")
    _validate(c2w, k, names, sizes)
    xyz, rgb, err = _check_points(points, colors, errors)  # every check before any write
    obs = _check_observations(observations, len(xyz), n)

    out = pathlib.Path(model_dir)
    out.mkdir(parents=True, exist_ok=True)

    # Cameras: one per distinct (fx, fy, cx, cy, width, height), ids in order of first use.
    rows = np.column_stack([k[:, 0, 0], k[:, 1, 1], k[:, 0, 2] + pixel_offset, k[:, 1, 2] + pixel_offset, sizes])
    _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    camera_id = rank[inverse] + 1
    cameras = rows[np.sort(first)]
    q, t = world_to_camera_qt(c2w)

    # Points2D: image i lists its observations in point order (stable sort by image).
    if obs is None:
        order = np.zeros(0, np.int64)
        counts = np.zeros(n, np.int64)
        point2d_idx = np.zeros(0, np.int64)
        obs_xy = np.zeros((0, 2))
    else:
        order = np.argsort(obs.image_index, kind="stable")
        counts = np.bincount(obs.image_index, minlength=n)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        point2d_idx = np.empty(len(order), np.int64)
        point2d_idx[order] = np.arange(len(order)) - np.repeat(starts, counts)
        obs_xy = obs.xy.astype(np.float64) + pixel_offset
    model = _Model(cameras, camera_id, q, t, names, xyz, rgb, err, obs, order, counts, point2d_idx, obs_xy)
    if binary:
        _write_binary(out, model)
    if text:
        _write_text(out, model)
    return out


def write_colmap_text(model_dir: PathLike, *args: Any, **kwargs: Any) -> pathlib.Path:
    """:func:`write_colmap` with text files only (``cameras.txt``, ``images.txt``, ``points3D.txt``)."""
    return write_colmap(model_dir, *args, binary=False, text=True, **kwargs)


class _Model(NamedTuple):
    cameras: np.ndarray  # [C, 6] fx fy cx cy w h (COLMAP convention)
    camera_id: np.ndarray  # [N] 1-based
    q: np.ndarray  # [N, 4] wxyz
    t: np.ndarray  # [N, 3]
    names: list[str]
    xyz: np.ndarray
    rgb: np.ndarray
    err: np.ndarray
    obs: Observations | None
    order: np.ndarray  # observations sorted by image (stable)
    counts: np.ndarray  # [N] observations per image
    point2d_idx: np.ndarray  # [M] index of point j among its image's POINTS2D
    obs_xy: np.ndarray  # [M, 2] COLMAP pixel coordinates

    def points2d(self, i: int, start: int) -> tuple[np.ndarray, np.ndarray]:
        """Image ``i``'s observations: ``xy [c, 2]`` and 1-based point ids ``[c]``."""
        sel = self.order[start : start + self.counts[i]]
        return self.obs_xy[sel], sel + 1


def _check_observations(
    observations: Observations | tuple[np.ndarray, np.ndarray] | None, m: int, n: int
) -> Observations | None:
    if observations is None:
        return None
    image_index = np.asarray(observations[0])
    xy = np.asarray(observations[1], np.float64)
    if image_index.shape != (m,) or xy.shape != (m, 2):
        raise ValueError(
            f"COLMAP export: observations must be image_index [{m}] and xy [{m}, 2] (one per point), "
            f"got {image_index.shape} and {xy.shape}"
        )
    if m and (not np.issubdtype(image_index.dtype, np.integer) or image_index.min() < 0 or image_index.max() >= n):
        raise ValueError(f"COLMAP export: observation image indices must be integers in [0, {n})")
    if not np.isfinite(xy).all():
        raise ValueError("COLMAP export: observations hold non-finite pixel coordinates")
    return Observations(image_index.astype(np.int64), xy)


def _write_binary(out: pathlib.Path, model: _Model) -> None:
    cam = np.empty(
        len(model.cameras),
        np.dtype([("id", "<u4"), ("model", "<i4"), ("width", "<u8"), ("height", "<u8"), ("params", "<f8", (4,))]),
    )
    cam["id"] = np.arange(1, len(cam) + 1)
    cam["model"] = _PINHOLE
    cam["width"], cam["height"] = model.cameras[:, 4], model.cameras[:, 5]
    cam["params"] = model.cameras[:, :4]
    with atomic_write(out / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(cam)))
        f.write(cam.tobytes())

    p2d = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
    with atomic_write(out / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(model.names)))
        start = 0
        for i, name in enumerate(model.names):  # one record per image (thousands), not per point
            xy, ids = model.points2d(i, start)
            start += int(model.counts[i])
            rec = np.empty(len(ids), p2d)
            rec["x"], rec["y"], rec["id"] = xy[:, 0], xy[:, 1], ids
            f.write(struct.pack("<I4d3dI", i + 1, *model.q[i], *model.t[i], int(model.camera_id[i])))
            f.write(name.encode("utf-8") + b"\0")
            f.write(struct.pack("<Q", len(rec)))
            f.write(rec.tobytes())

    fields = [("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8"), ("track", "<u8")]
    if model.obs is not None:
        fields += [("image_id", "<u4"), ("point2d_idx", "<u4")]
    dtype = np.dtype(fields)
    m = len(model.xyz)
    with atomic_write(out / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", m))
        for a in range(0, m, _BATCH):
            b = min(a + _BATCH, m)
            rec = np.empty(b - a, dtype)
            rec["id"] = np.arange(a + 1, b + 1)
            rec["xyz"] = model.xyz[a:b]
            rec["rgb"] = model.rgb[a:b]
            rec["error"] = model.err[a:b]
            if model.obs is None:
                rec["track"] = 0
            else:
                rec["track"] = 1
                rec["image_id"] = model.obs.image_index[a:b] + 1
                rec["point2d_idx"] = model.point2d_idx[a:b]
            f.write(rec.tobytes())


def _write_text(out: pathlib.Path, model: _Model) -> None:
    n, m = len(model.names), len(model.xyz)
    with atomic_write(out / "cameras.txt") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write(f"# Number of cameras: {len(model.cameras)}\n")
        for cid, (fx, fy, cx, cy, w, h) in enumerate(model.cameras, start=1):
            params = " ".join(repr(float(v)) for v in (fx, fy, cx, cy))  # shortest exact
            f.write(f"{cid} PINHOLE {int(w)} {int(h)} {params}\n")

    with atomic_write(out / "images.txt") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        mean = len(model.order) / n if n else 0.0
        f.write(f"# Number of images: {n}, mean observations per image: {mean:g}\n")
        start = 0
        for i in range(n):  # one line pair per image (thousands); each POINTS2D line in one %
            qs = " ".join(repr(float(v)) for v in model.q[i])
            ts = " ".join(repr(float(v)) for v in model.t[i])
            xy, ids = model.points2d(i, start)
            start += int(model.counts[i])
            table = np.column_stack([xy, ids]).ravel().tolist()
            line = ("%.17g %.17g %d " * len(ids)) % tuple(table)
            f.write(f"{i + 1} {qs} {ts} {model.camera_id[i]} {model.names[i]}\n{line.rstrip()}\n")

    ff = _float_format(model.xyz.dtype)
    row = f"%d {ff} {ff} {ff} %d %d %d %.9g" + (" %d %d" if model.obs is not None else "") + "\n"
    with atomic_write(out / "points3D.txt") as f:
        f.write("# 3D point list with one line of data per point:\n")
        f.write("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        f.write(f"# Number of points: {m}, mean track length: {0 if model.obs is None else 1}\n")
        for a in range(0, m, _BATCH):
            b = min(a + _BATCH, m)
            cols = [
                np.arange(a + 1, b + 1, dtype=np.float64),
                model.xyz[a:b].astype(np.float64),
                model.rgb[a:b],
                model.err[a:b],
            ]
            if model.obs is not None:
                cols += [model.obs.image_index[a:b] + 1, model.point2d_idx[a:b]]
            table = np.column_stack(cols)  # ids < 2^53 and colours are exact in float64; %d prints them
            f.write((row * (b - a)) % tuple(table.ravel().tolist()))


def _check_points(
    points: np.ndarray | None, colors: np.ndarray | None, errors: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated ``xyz [M,3]``, ``rgb [M,3]`` uint8 (default grey) and ``err [M]`` float64."""
    xyz = np.zeros((0, 3), np.float32) if points is None else np.asarray(points)
    m = len(xyz)
    if xyz.shape != (m, 3):
        raise ValueError(f"COLMAP export: points has shape {xyz.shape}, expected [M, 3]")
    if not np.isfinite(xyz).all():
        raise ValueError(f"COLMAP export: points has {int((~np.isfinite(xyz)).any(1).sum())} non-finite rows")
    rgb = np.full((m, 3), 128, np.uint8) if colors is None else np.asarray(colors)
    if rgb.shape != (m, 3) or rgb.dtype != np.uint8:
        raise ValueError(f"COLMAP export: colors must be uint8 [{m}, 3], got {rgb.dtype} {rgb.shape}")
    err = np.zeros(m, np.float64) if errors is None else np.asarray(errors, np.float64)
    if err.shape != (m,):
        raise ValueError(f"COLMAP export: errors must have shape [{m}], got {err.shape}")
    return xyz, rgb, err

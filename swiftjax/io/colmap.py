"""Export a reconstruction as a COLMAP text model: ``cameras.txt``, ``images.txt``, ``points3D.txt``.

The model opens in COLMAP's GUI, ``pycolmap.Reconstruction(dir)``, and the usual Gaussian
splatting / NeRF loaders.  Formats (COLMAP documentation, "Output format"):

* ``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``; we write one ``PINHOLE``
  camera (``fx fy cx cy``) per distinct (intrinsics, image size).
* ``images.txt``: two lines per image, ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then
  the ``POINTS2D[]`` line (empty: we export no 2-D observations).  The pose is
  **world-to-camera** (``x_cam = R x_world + t``), the quaternion Hamilton, scalar first.
* ``points3D.txt``: ``POINT3D_ID X Y Z R G B ERROR TRACK[]``, tracks empty.

**Pixel convention.**  COLMAP's image coordinates put the top-left *corner* of the image at
(0, 0), so the centre of the top-left pixel is (0.5, 0.5) (COLMAP docs on feature import;
pycolmap/panorama.py says the same, and a default COLMAP camera has ``cx = width / 2``).
swiftjax, like VGGT's unprojection ``x = (u - cx) d / fx``, puts pixel centres at integers.
A point seen at the centre of pixel ``u`` therefore has COLMAP coordinate ``u + 0.5``, and
we write ``cx_colmap = cx + 0.5``, ``cy_colmap = cy + 0.5`` (``pixel_offset``; focal
lengths are unchanged).  Each file is written atomically.
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Sequence

import jax
import numpy as np

from swiftjax import so3
from swiftjax.io.atomic import atomic_write

__all__ = ["world_to_camera_qt", "write_colmap_text"]

PathLike = str | os.PathLike[str]

_ORTHO_TOL = 1e-4  # max |R^T R - I| accepted for a camera-to-world rotation
_BATCH = 200_000  # points formatted per string operation in points3D.txt
_from_matrix = jax.jit(so3.from_matrix)  # compiles once per (N, dtype)


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


def _validate(
    cam_to_world: np.ndarray, intrinsics: np.ndarray, names: Sequence[str], sizes: np.ndarray
) -> None:
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


def write_colmap_text(
    model_dir: PathLike,
    cam_to_world: np.ndarray,
    intrinsics: np.ndarray,
    names: Sequence[str],
    image_size: tuple[int, int] | np.ndarray,
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    errors: np.ndarray | None = None,
    pixel_offset: float = 0.5,
) -> pathlib.Path:
    """Write a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``).

    Args:
        model_dir: output folder (created if missing).
        cam_to_world: ``[N, 4, 4]`` camera-to-world, orthonormal rotation (metric, no scale).
        intrinsics: ``[N, 3, 3]`` zero-skew pinhole ``K`` with integer pixel centres.
        names: ``N`` image file names, relative to the image folder (no whitespace).
        image_size: ``(width, height)`` for every image, or ``[N, 2]`` per image.
        points: ``[M, 3]`` world points, or None for an empty ``points3D.txt``.
        colors: ``[M, 3]`` uint8 RGB (default grey 128).
        errors: ``[M]`` per-point reprojection error (default 0).
        pixel_offset: added to ``cx, cy`` (0.5: integer pixel centres -> COLMAP's corner origin).

    Returns:
        ``model_dir`` as a Path.  Image ids are ``1..N`` in input order; camera ids ``1..C`` in
        order of first use; point ids ``1..M``.
    """
    names = [str(n) for n in names]
    n = len(names)
    c2w = np.asarray(cam_to_world)
    k = np.asarray(intrinsics, dtype=np.float64)
    sizes = np.asarray(image_size, dtype=np.int64)
    if sizes.shape == (2,):
        sizes = np.broadcast_to(sizes, (n, 2))
    _validate(c2w, k, names, sizes)
    xyz, rgb, err = _check_points(points, colors, errors)  # every check before any write

    out = pathlib.Path(model_dir)
    out.mkdir(parents=True, exist_ok=True)

    # Cameras: one per distinct (fx, fy, cx, cy, width, height), ids in order of first use.
    rows = np.column_stack([k[:, 0, 0], k[:, 1, 1], k[:, 0, 2] + pixel_offset, k[:, 1, 2] + pixel_offset, sizes])
    _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    camera_id = rank[inverse] + 1
    with atomic_write(out / "cameras.txt") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write(f"# Number of cameras: {len(first)}\n")
        for cid, i in enumerate(np.sort(first), start=1):
            fx, fy, cx, cy, w, h = rows[i]
            params = " ".join(repr(float(v)) for v in (fx, fy, cx, cy))  # shortest exact
            f.write(f"{cid} PINHOLE {int(w)} {int(h)} {params}\n")

    q, t = world_to_camera_qt(c2w)
    with atomic_write(out / "images.txt") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        f.write(f"# Number of images: {n}, mean observations per image: 0\n")
        for i in range(n):  # one line per image (thousands), not per point
            qs = " ".join(repr(float(v)) for v in q[i])
            ts = " ".join(repr(float(v)) for v in t[i])
            f.write(f"{i + 1} {qs} {ts} {camera_id[i]} {names[i]}\n\n")

    _write_points3d(out / "points3D.txt", xyz, rgb, err)
    return out


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


def _write_points3d(path: pathlib.Path, xyz: np.ndarray, rgb: np.ndarray, err: np.ndarray) -> None:
    """``points3D.txt`` with empty tracks; formatted in batches by one ``%`` each (no per-point
    Python loop).  Coordinates keep their dtype's full precision (float32: 9 digits)."""
    m = len(xyz)
    ff = _float_format(xyz.dtype)
    row = f"%d {ff} {ff} {ff} %d %d %d %.9g\n"
    with atomic_write(path) as f:
        f.write("# 3D point list with one line of data per point:\n")
        f.write("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        f.write(f"# Number of points: {m}, mean track length: 0\n")
        for a in range(0, m, _BATCH):
            b = min(a + _BATCH, m)
            table = np.column_stack(
                [np.arange(a + 1, b + 1, dtype=np.float64), xyz[a:b].astype(np.float64), rgb[a:b], err[a:b]]
            )  # ids < 2^53 and colours are exact in float64; %d prints them as integers
            f.write((row * (b - a)) % tuple(table.ravel().tolist()))

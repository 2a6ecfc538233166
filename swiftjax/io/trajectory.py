"""Trajectory files: KITTI (3x4 per line) and TUM (``t tx ty tz qx qy qz qw``).

Poses are camera-to-world ``[N, 4, 4]`` float64 matrices (every trajectory swiftjax writes is
camera-to-world).  Host-side NumPy code: files are small (KITTI 00 is 4,541
lines) and this runs once per run.

Parsing rules (a superset of what evo reads, so every file evo reads, we read too):

* lines starting with ``#`` (after leading white space) and blank lines are skipped;
* values are separated by white space or commas;
* KITTI lines have exactly 12 numbers (the row-major top 3x4 of the pose), TUM lines 8;
* every value must parse as a finite float.

Anything else raises :class:`TrajectoryFormatError` naming the file and the 1-based line.

Round trips are exact: writers print every float with Python's shortest round-trip
``repr``, so ``read_kitti(write_kitti(P)) == P`` bit for bit (for the top 3x4 rows), and
``read_tum_raw(write_tum(t, rows)) == (t, rows)`` bit for bit.  Going from a rotation
matrix to a quaternion and back is not bit-exact in floating point (it agrees to ~1e-16):
write TUM rows (``[N, 7]``) rather than matrices when bit-exactness matters.

Quaternion -> matrix uses the same formula as evo (``transformations.quaternion_matrix``:
normalise, ``q <- q sqrt(2/|q|^2)``, outer product), so poses read here are bit-identical to
evo's ``PoseTrajectory3D.poses_se3``.  Matrix -> quaternion uses Shepperd's method
(largest-diagonal branch) and returns ``qw >= 0``.
"""

from __future__ import annotations

import io
import os
import pathlib
from collections.abc import Sequence

import numpy as np

from swiftjax.errors import SwiftjaxError
from swiftjax.io.atomic import atomic_write

__all__ = [
    "TrajectoryFormatError",
    "read_kitti",
    "write_kitti",
    "read_tum",
    "read_tum_raw",
    "read_header",
    "time_order",
    "write_tum",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
]

PathLike = str | os.PathLike


class TrajectoryFormatError(SwiftjaxError, ValueError):
    """A malformed trajectory file; the message names the file and the line."""


# ------------------------------------------------------------------------------- parsing


def _parse_rows(path: PathLike, width: int, fmt: str) -> np.ndarray:
    """``[N, width]`` float64 rows of a whitespace/comma separated numeric file."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{fmt} trajectory file not found: {path}")
    rows: list[list[float]] = []
    raw = path.read_bytes()
    if b"\x00" in raw[:4096]:
        raise TrajectoryFormatError(f"{path}: not a text {fmt} trajectory file (binary data, {len(raw)} bytes)")
    try:
        text_all = raw.decode("utf-8-sig")  # utf-8-sig: tolerate a BOM like evo
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise TrajectoryFormatError(
            f"{path}:{line}: not a text {fmt} trajectory file (byte {e.start} is not UTF-8)"
        ) from None
    for lineno, line in enumerate(io.StringIO(text_all, newline=None), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.replace(",", " ").split()
        if len(fields) != width:
            raise TrajectoryFormatError(
                f"{path}:{lineno}: a {fmt} line must have {width} numbers, got {len(fields)}: {text[:80]!r}"
            )
        try:
            values = [float(v) for v in fields]
        except ValueError:
            raise TrajectoryFormatError(
                f"{path}:{lineno}: a {fmt} line must hold numbers only: {text[:80]!r}"
            ) from None
        if not all(np.isfinite(values)):
            raise TrajectoryFormatError(f"{path}:{lineno}: non-finite value (nan/inf) in {fmt} line: {text[:80]!r}")
        rows.append(values)
    if not rows:
        raise TrajectoryFormatError(f"{path}: no {fmt} poses in file (empty or only comments)")
    return np.asarray(rows, dtype=np.float64)


def _atomic_write_text(path: PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (creating missing parent folders)."""
    pathlib.Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        f.write(text)


def _fmt(x: float) -> str:
    return repr(float(x))


def _comment_lines(header: Sequence[str] | None) -> list[str]:
    """``# line`` for each header line (what the readers here and evo skip)."""
    out = []
    for line in header or ():
        for part in str(line).splitlines() or [""]:
            out.append(f"# {part}".rstrip())
    return out


# ------------------------------------------------------------------------------- rotations


def quaternion_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """``[..., 4]`` quaternions ``(qx, qy, qz, qw)`` (any norm > 0) -> ``[..., 3, 3]`` rotations.

    The same arithmetic as evo's ``transformations.quaternion_matrix`` (bit-identical).
    A zero quaternion gives the identity, as in evo.
    """
    q = np.asarray(q_xyzw, dtype=np.float64)
    w, x, y, z = q[..., 3], q[..., 0], q[..., 1], q[..., 2]
    qw = np.stack([w, x, y, z], axis=-1)
    flat = qw.reshape(-1, 4)
    # np.dot per quaternion, as evo: BLAS's summation order decides the last bit of |q|^2.
    n = np.fromiter((np.dot(v, v) for v in flat), dtype=np.float64, count=flat.shape[0])
    n = n.reshape(qw.shape[:-1])
    tiny = n < np.finfo(np.float64).eps * 4.0
    qw = qw * np.sqrt(2.0 / np.where(tiny, 1.0, n))[..., None]
    o = qw[..., :, None] * qw[..., None, :]
    R = np.stack(
        [
            np.stack([1.0 - o[..., 2, 2] - o[..., 3, 3], o[..., 1, 2] - o[..., 3, 0], o[..., 1, 3] + o[..., 2, 0]], -1),
            np.stack([o[..., 1, 2] + o[..., 3, 0], 1.0 - o[..., 1, 1] - o[..., 3, 3], o[..., 2, 3] - o[..., 1, 0]], -1),
            np.stack([o[..., 1, 3] - o[..., 2, 0], o[..., 2, 3] + o[..., 1, 0], 1.0 - o[..., 1, 1] - o[..., 2, 2]], -1),
        ],
        axis=-2,
    )
    return np.where(tiny[..., None, None], np.eye(3), R)


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """``[..., 3, 3]`` rotations -> ``[..., 4]`` unit quaternions ``(qx, qy, qz, qw)``, ``qw >= 0``.

    Shepperd's method: of the four candidate formulas, use the one whose divisor
    (``4 max(qw^2, qx^2, qy^2, qz^2)``) is largest, so there is no cancellation.
    """
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cands = np.stack(
        [
            # qw largest
            np.stack(
                [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1], 1.0 + tr], -1
            ),
            # qx largest
            np.stack(
                [
                    1.0 + m00 - m11 - m22,
                    R[..., 0, 1] + R[..., 1, 0],
                    R[..., 0, 2] + R[..., 2, 0],
                    R[..., 2, 1] - R[..., 1, 2],
                ],
                -1,
            ),
            # qy largest
            np.stack(
                [
                    R[..., 0, 1] + R[..., 1, 0],
                    1.0 - m00 + m11 - m22,
                    R[..., 1, 2] + R[..., 2, 1],
                    R[..., 0, 2] - R[..., 2, 0],
                ],
                -1,
            ),
            # qz largest
            np.stack(
                [
                    R[..., 0, 2] + R[..., 2, 0],
                    R[..., 1, 2] + R[..., 2, 1],
                    1.0 - m00 - m11 + m22,
                    R[..., 1, 0] - R[..., 0, 1],
                ],
                -1,
            ),
        ],
        axis=-2,
    )  # [..., 4 candidates, 4]
    pick = np.argmax(np.stack([tr, m00, m11, m22], -1), axis=-1)
    q = np.take_along_axis(cands, pick[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def _poses_from_rows(xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    n = xyz.shape[0]
    P = np.zeros((n, 4, 4), dtype=np.float64)
    P[:, :3, :3] = quaternion_to_matrix(q_xyzw)
    P[:, :3, 3] = xyz
    P[:, 3, 3] = 1.0
    return P


def _check_poses(poses: np.ndarray, name: str) -> np.ndarray:
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"{name} must have shape [N, 4, 4] or [N, 3, 4], got {P.shape}")
    if P.shape[0] == 0:
        raise ValueError(f"{name} is empty (no poses)")
    if not np.all(np.isfinite(P)):
        raise ValueError(f"{name} holds non-finite values (nan/inf)")
    return P


# --------------------------------------------------------------------------------- KITTI


def read_kitti(path: PathLike) -> np.ndarray:
    """Read a KITTI pose file: ``N`` lines of 12 numbers -> ``[N, 4, 4]`` float64.

    Raises:
        FileNotFoundError: no such file.
        TrajectoryFormatError: a line without exactly 12 finite numbers, or no poses at all.
    """
    rows = _parse_rows(path, 12, "KITTI")
    P = np.zeros((rows.shape[0], 4, 4), dtype=np.float64)
    P[:, :3, :] = rows.reshape(-1, 3, 4)
    P[:, 3, 3] = 1.0
    return P


def write_kitti(path: PathLike, poses: np.ndarray, header: Sequence[str] | None = None) -> None:
    """Write ``[N, 4, 4]`` (or ``[N, 3, 4]``) poses as KITTI lines, atomically, exactly.

    ``header``: lines written first as ``#`` comments (evo and :func:`read_kitti` skip them).

    Raises:
        ValueError: bad shape, no poses, or non-finite values.
    """
    P = _check_poses(poses, "poses")
    lines = _comment_lines(header) + [" ".join(_fmt(v) for v in p[:3, :].reshape(12)) for p in P]
    _atomic_write_text(path, "\n".join(lines) + "\n")


# ----------------------------------------------------------------------------------- TUM


def read_tum_raw(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file as stored: ``(timestamps [N], rows [N, 7] = (tx, ty, tz, qx, qy, qz, qw))``.

    Raises:
        FileNotFoundError, TrajectoryFormatError: as :func:`read_kitti` (8 numbers per line).
    """
    rows = _parse_rows(path, 8, "TUM")
    return rows[:, 0].copy(), rows[:, 1:].copy()


def read_header(path: PathLike, max_lines: int = 64) -> list[str]:
    """The ``#`` comment lines at the top of a trajectory file (text after ``#``, stripped),
    e.g. the ``unit: ...`` line swiftjax writes; ``[]`` for a file without them."""
    out: list[str] = []
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        for _, line in zip(range(max_lines), f):
            text = line.strip()
            if text and not text.startswith("#"):
                break
            if text:
                out.append(text.lstrip("#").strip())
    return out


def time_order(path: PathLike, stamps: np.ndarray) -> np.ndarray:
    """The order that sorts ``stamps [N]`` (a TUM file's, in file order) by time, stable.

    Relative poses (RPE) pair neighbours in time, so a file whose rows are not in time order
    is read in time order; two poses at the same time have no order and one reference pose
    would be associated twice (evo pairs the first it finds), so they are refused.

    Raises:
        TrajectoryFormatError: two rows share a timestamp (naming it and the rows).
    """
    t = np.asarray(stamps, np.float64)
    order = np.argsort(t, kind="stable")
    same = np.flatnonzero(np.diff(t[order]) == 0)
    if same.size:
        a, b = sorted(int(i) for i in order[same[0] : same[0] + 2])
        raise TrajectoryFormatError(
            f"{path}: poses {a + 1} and {b + 1} (data rows) have the same timestamp {float(t[a])!r} "
            f"({same.size} repeated timestamps); each pose needs its own time"
        )
    return order


def read_tum(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file: ``(timestamps [N] float64, poses [N, 4, 4] float64)``.

    Quaternions are normalised on the way (evo's formula; a zero quaternion -> identity).
    """
    t, rows = read_tum_raw(path)
    return t, _poses_from_rows(rows[:, :3], rows[:, 3:])


def write_tum(
    path: PathLike, timestamps: np.ndarray | Sequence[float], poses: np.ndarray, header: Sequence[str] | None = None
) -> None:
    """Write TUM lines ``t tx ty tz qx qy qz qw`` atomically (``header`` lines first, as ``#`` comments).

    Args:
        path: output file.
        timestamps: ``[N]`` seconds.
        poses: ``[N, 4, 4]`` / ``[N, 3, 4]`` camera-to-world matrices (rotations converted
            with :func:`matrix_to_quaternion`), or ``[N, 7]`` rows ``(t, q_xyzw)`` written as
            given (bit-exact round trip with :func:`read_tum_raw`).

    Raises:
        ValueError: shape mismatch, no poses, or non-finite values.
    """
    t = np.asarray(timestamps, dtype=np.float64)
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim == 2 and P.shape[1] == 7:
        if not np.all(np.isfinite(P)):
            raise ValueError("poses holds non-finite values (nan/inf)")
        rows = P
    else:
        P = _check_poses(P, "poses")
        rows = np.concatenate([P[:, :3, 3], matrix_to_quaternion(P[:, :3, :3])], axis=1)
    if t.shape != (rows.shape[0],):
        raise ValueError(f"timestamps must have shape ({rows.shape[0]},), got {t.shape}")
    if rows.shape[0] == 0:
        raise ValueError("poses is empty (no poses)")
    if not np.all(np.isfinite(t)):
        raise ValueError("timestamps holds non-finite values (nan/inf)")
    lines = _comment_lines(header) + [" ".join([_fmt(ti), *(_fmt(v) for v in r)]) for ti, r in zip(t, rows)]
    _atomic_write_text(path, "\n".join(lines) + "\n")

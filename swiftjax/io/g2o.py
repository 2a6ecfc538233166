"""g2o pose-graph files (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``) lifted to Sim(3) and back.

Records (g2o's text format; one per line, ``#`` comments and blank lines ignored)::

    VERTEX_SE3:QUAT id x y z qx qy qz qw
    EDGE_SE3:QUAT   i j x y z qx qy qz qw  I11 I12 .. I16 I22 .. I66   (21 numbers, upper triangle)
    FIX id [id ...]

* Poses and measurements get scale 1: our layout ``(x, y, z, qx, qy, qz, qw, 1)``.
* The 6×6 information is in g2o's order (translation, rotation), which is the first six
  entries of our tangent ``(rho, omega, sigma)``; its rotation block is used as it is in
  rotation-vector units (the convention of GTSAM's ``readG2o``, not rescaled from g2o's
  quaternion-vector error).  The log-scale entry ``Omega[6, 6]`` is ``scale_information``
  (default: the mean of the rotation diagonal), with no cross terms.
* Node ids may be any integers: they are mapped to ``0..N-1`` in increasing id order
  (``G2oGraph.node_ids`` keeps the originals).  ``FIX`` ids become ``fixed``; when the file
  has none, the first node is fixed.
* Unknown record types are skipped with one warning per type; a malformed known record
  raises :class:`G2oError` naming the file, line number and problem.

``write_g2o`` writes the same two record types (atomically: temp file + rename); it refuses
poses or measurements with a scale other than 1 (g2o's SE(3) records cannot hold one) unless
``drop_scale=True``.
"""

from __future__ import annotations

import logging
import os
import pathlib
import tempfile
from typing import NamedTuple

import numpy as np

from swiftjax.errors import SwiftjaxError

__all__ = ["G2oGraph", "G2oError", "read_g2o", "write_g2o"]

logger = logging.getLogger(__name__)

_VERTEX = "VERTEX_SE3:QUAT"
_EDGE = "EDGE_SE3:QUAT"
_TRIU = np.triu_indices(6)


class G2oError(SwiftjaxError, ValueError):
    """A malformed g2o file."""


class G2oGraph(NamedTuple):
    """A pose graph read from g2o, in swiftjax's Sim(3) layout (NumPy float64).

    Attributes:
        poses: ``[N, 8]``.  edges: ``[E, 2]`` int64 indices into ``poses``.
        measurements: ``[E, 8]``.  information: ``[E, 7, 7]``.  fixed: ``[N]`` bool.
        node_ids: ``[N]`` the file's vertex ids.
    """

    poses: np.ndarray
    edges: np.ndarray
    measurements: np.ndarray
    information: np.ndarray
    fixed: np.ndarray
    node_ids: np.ndarray


def _floats(tokens: list[str], where: str) -> np.ndarray:
    try:
        values = np.array([float(t) for t in tokens], np.float64)
    except ValueError as exc:
        raise G2oError(f"{where}: not a number ({exc})") from None
    if not np.all(np.isfinite(values)):
        raise G2oError(f"{where}: non-finite value")
    return values


def _unit_quaternion(q: np.ndarray, where: str) -> np.ndarray:
    norm = np.linalg.norm(q)
    if not norm > 0:
        raise G2oError(f"{where}: zero quaternion")
    return q / norm


def read_g2o(path: str | os.PathLike, *, scale_information: float | None = None) -> G2oGraph:
    """Read ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT`` / ``FIX`` records (module docstring)."""
    path = pathlib.Path(path)
    vertices: dict[int, np.ndarray] = {}
    edge_ids: list[tuple[int, int]] = []
    meas: list[np.ndarray] = []
    infos: list[np.ndarray] = []
    fixed_ids: set[int] = set()
    unknown: dict[str, int] = {}
    with open(path) as fh:
        for lineno, line in enumerate(fh, 1):
            tokens = line.split("#", 1)[0].split()
            if not tokens:
                continue
            tag, rest = tokens[0], tokens[1:]
            where = f"{path}:{lineno}: {tag}"
            if tag == _VERTEX:
                if len(rest) != 8:
                    raise G2oError(f"{where}: expected id + 7 numbers, got {len(rest)} fields")
                try:
                    vid = int(rest[0])
                except ValueError:
                    raise G2oError(f"{where}: vertex id {rest[0]!r} is not an integer") from None
                if vid in vertices:
                    raise G2oError(f"{where}: vertex id {vid} defined twice")
                v = _floats(rest[1:], where)
                vertices[vid] = np.concatenate([v[:3], _unit_quaternion(v[3:7], where), [1.0]])
            elif tag == _EDGE:
                if len(rest) != 2 + 7 + 21:
                    raise G2oError(
                        f"{where}: expected 2 ids + 7 numbers + 21 information entries, got {len(rest)} fields"
                    )
                try:
                    i, j = int(rest[0]), int(rest[1])
                except ValueError:
                    raise G2oError(f"{where}: vertex ids {rest[:2]} are not integers") from None
                v = _floats(rest[2:], where)
                info6 = np.zeros((6, 6))
                info6[_TRIU] = v[7:]
                info6 = info6 + np.triu(info6, 1).T
                edge_ids.append((i, j))
                meas.append(np.concatenate([v[:3], _unit_quaternion(v[3:7], where), [1.0]]))
                infos.append(info6)
            elif tag == "FIX":
                try:
                    fixed_ids.update(int(t) for t in rest)
                except ValueError:
                    raise G2oError(f"{where}: ids {rest} are not integers") from None
            else:
                unknown[tag] = unknown.get(tag, 0) + 1
    for tag, count in unknown.items():
        logger.warning(f"{path}: skipped {count} record(s) of unknown type {tag!r}")
    if not vertices:
        raise G2oError(f"{path}: no {_VERTEX} records")
    node_ids = np.array(sorted(vertices), np.int64)
    index = {vid: k for k, vid in enumerate(node_ids.tolist())}
    for k, (i, j) in enumerate(edge_ids):
        for v in (i, j):
            if v not in index:
                raise G2oError(f"{path}: edge {k} ({i}, {j}) refers to undefined vertex {v}")
    for v in fixed_ids:
        if v not in index:
            raise G2oError(f"{path}: FIX refers to undefined vertex {v}")
    poses = np.stack([vertices[v] for v in node_ids])
    edges = np.array([(index[i], index[j]) for i, j in edge_ids], np.int64).reshape(-1, 2)
    info = np.zeros((len(infos), 7, 7))
    if infos:
        info[:, :6, :6] = np.stack(infos)
        if scale_information is None:
            sinfo = np.mean(np.diagonal(info[:, 3:6, 3:6], axis1=1, axis2=2), axis=1)
        else:
            sinfo = np.full(len(infos), float(scale_information))
        info[:, 6, 6] = sinfo
    fixed = np.isin(node_ids, list(fixed_ids)) if fixed_ids else (np.arange(len(node_ids)) == 0)
    return G2oGraph(
        poses=poses,
        edges=edges,
        measurements=np.stack(meas) if meas else np.zeros((0, 8)),
        information=info,
        fixed=fixed,
        node_ids=node_ids,
    )


def _fmt(values) -> str:
    return " ".join(f"{float(v):.17g}" for v in values)


def write_g2o(
    path: str | os.PathLike,
    poses,
    edges,
    measurements,
    information=None,
    *,
    node_ids=None,
    fixed=None,
    drop_scale: bool = False,
) -> None:
    """Write a pose graph as ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT`` (+ ``FIX``), atomically.

    Args:
        poses: ``[N, 8]``; measurements ``[E, 8]``; edges ``[E, 2]`` indices into poses.
        information: ``[E, 7, 7]`` or ``[E, 6, 6]`` (the top-left 6×6 is written) or None (identity).
        node_ids: ids to write (default ``0..N-1``).  fixed: ``[N]`` bool, written as ``FIX``.
        drop_scale: write even if a scale differs from 1 (the scale is lost).
    """
    poses = np.asarray(poses, np.float64)
    edges = np.asarray(edges)
    meas = np.asarray(measurements, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 8:
        raise ValueError(f"poses has shape {poses.shape}; expected [N, 8]")
    if meas.shape != (len(edges), 8):
        raise ValueError(f"measurements has shape {meas.shape}; expected [E, 8] = [{len(edges)}, 8]")
    if not drop_scale:
        for name, arr in (("poses", poses), ("measurements", meas)):
            bad = np.nonzero(np.abs(arr[:, 7] - 1.0) > 1e-12)[0]
            if bad.size:
                raise ValueError(
                    f"{name}: scale != 1 at rows {bad[:8].tolist()}; g2o SE(3) records cannot store "
                    "a scale (pass drop_scale=True to write anyway)"
                )
    if information is None:
        info = np.broadcast_to(np.eye(6), (len(edges), 6, 6))
    else:
        info = np.asarray(information, np.float64)[:, :6, :6]
    ids = np.arange(len(poses)) if node_ids is None else np.asarray(node_ids)
    lines = [f"{_VERTEX} {int(ids[k])} {_fmt(p[:7])}" for k, p in enumerate(poses)]
    for k, (i, j) in enumerate(edges):
        lines.append(f"{_EDGE} {int(ids[i])} {int(ids[j])} {_fmt(meas[k, :7])} {_fmt(info[k][_TRIU])}")
    if fixed is not None:
        fixed_ids = ids[np.asarray(fixed, bool)]
        if fixed_ids.size:
            lines.append("FIX " + " ".join(str(int(v)) for v in fixed_ids))
    path = pathlib.Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write("\n".join(lines) + "\n")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise

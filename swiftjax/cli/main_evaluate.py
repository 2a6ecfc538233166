"""``swiftjax evaluate``: ATE / RPE of an estimated trajectory against a reference, in evo's
order (``REF EST``) and with evo's numbers."""

from __future__ import annotations

import argparse
import logging
import pathlib
from typing import Any

from swiftjax.cli.arguments import CliError, one_line

__all__ = ["add_parser", "run"]

logger = logging.getLogger(__name__)

_ESTIMATE_HEADER = "swiftjax camera-to-world poses"  # swiftjax's poses_*.txt (pipeline/export.py)
_GROUND_TRUTH_HEADER = "the ground truth given to this run"  # its ground_truth_kitti.txt (pipeline/report.py)


def add_parser(sub: Any, **kw: Any) -> argparse.ArgumentParser:
    """The ``evaluate`` subparser (``kw``: the parser's formatter)."""
    p: argparse.ArgumentParser = sub.add_parser(
        "evaluate", help="ATE / RPE of an estimated trajectory against a reference (evo's order: REF EST)", **kw
    )
    p.add_argument(
        "reference",
        type=pathlib.Path,
        help="reference (ground-truth) poses, FIRST as in evo_ape/evo_rpe; the errors are in its unit",
    )
    p.add_argument("estimate", type=pathlib.Path, help="estimated camera-to-world poses (e.g. a run's poses_kitti.txt)")
    p.add_argument(
        "--format",
        choices=("kitti", "tum"),
        default="kitti",
        help="file format (KITTI pairs poses by row, TUM by timestamp)",
    )
    p.add_argument(
        "--align",
        choices=("sim3", "se3", "none"),
        default="sim3",
        help="alignment of the estimate before the errors (evo --align [--correct_scale])",
    )
    p.add_argument("--delta", type=int, default=1, help="RPE frame offset")
    p.add_argument(
        "--max-diff",
        type=float,
        default=0.01,
        metavar="SECONDS",
        help="TUM: largest time difference of associated poses (evo's --t_max_diff)",
    )
    p.add_argument(
        "--offset",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="TUM: time offset added to the estimate's timestamps (evo's --t_offset)",
    )
    p.add_argument(
        "--fix-rotations",
        action="store_true",
        help="re-orthonormalise rotations that are not (reported), instead of an error",
    )
    p.set_defaults(func=run)
    return p


class _RotationError(CliError):
    def __init__(self, text: str, zero: bool = False) -> None:
        super().__init__(text)
        self.zero = zero


def _read_trajectory(path: pathlib.Path, fmt: str) -> tuple[Any, Any]:
    """``(timestamps | None, poses [N, 4, 4])``; TUM quaternions must be non-zero, TUM rows
    are taken in time order (repeated times refused)."""
    import numpy as np

    from swiftjax.io import trajectory

    if path.is_dir():
        raise CliError(f"trajectory file {path} is a directory (give the {fmt.upper()} file, e.g. DIR/poses_{fmt}.txt)")
    if not path.exists():
        raise CliError(f"trajectory file {path} does not exist")
    if fmt == "kitti":
        return None, trajectory.read_kitti(path)
    stamps, rows = trajectory.read_tum_raw(path)
    order = trajectory.time_order(path, stamps)
    norms = np.linalg.norm(rows[:, 3:], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if bad.size:
        k = int(bad[0])
        raise _RotationError(
            f"{path}: pose {k} (of {len(rows)}, time {float(stamps[k])!r}) has a quaternion of norm {norms[k]:.6g}, "
            f"not a unit quaternion ({bad.size} such poses)",
            zero=bool(np.any(norms[bad] < 1e-6)),
        )
    if np.any(order != np.arange(len(order))):
        logger.info(f"swiftjax: {path}: rows are not in time order; taken in time order")
    t, poses = trajectory.read_tum(path)
    return t[order], poses[order]


def _check_order(ref_path: pathlib.Path, est_path: pathlib.Path) -> str:
    """Refuse a swapped pair that the files' own headers reveal (evo's order is ``REF EST``;
    swapped, a Sim(3) alignment prints an error in the estimate's units, a plausible-looking
    wrong number); returns the reference's unit for the table (``m`` unless its header says
    otherwise)."""
    ref_head = " ".join(_header(ref_path))
    est_head = " ".join(_header(est_path))
    swap = "swiftjax evaluate REFERENCE ESTIMATE (the reference first, as evo_ape/evo_rpe)"
    if _ESTIMATE_HEADER in ref_head:
        raise CliError(f"{ref_path} is a swiftjax estimate (its header says so) but is given as the reference: {swap}")
    if _GROUND_TRUTH_HEADER in est_head:
        raise CliError(f"{est_path} is a ground truth (its header says so) but is given as the estimate: {swap}")
    for line in _header(ref_path):
        if line.startswith("unit:"):
            unit = line[5:].strip()
            return "m" if unit.startswith("metre") else unit
    return "m"


def _header(path: pathlib.Path) -> list[str]:
    from swiftjax.io import trajectory

    try:
        return trajectory.read_header(path)
    except OSError:
        return []  # the reader names the file below


def run(args: argparse.Namespace) -> int:
    """Print the ATE / RPE table; exit status 0."""
    from swiftjax import evaluation
    from swiftjax.io import trajectory
    from swiftjax.io.tables import markdown_table

    est_path, ref_path = args.estimate, args.reference
    unit = _check_order(ref_path, est_path)
    loaded = []
    fixes = []
    for path in (est_path, ref_path):
        try:
            stamps, poses = _read_trajectory(path, args.format)
        except _RotationError as err:
            if not args.fix_rotations or err.zero:
                hint = "" if err.zero else "; --fix-rotations normalises them"
                raise CliError(f"{err}{hint}") from None
            stamps, poses = trajectory.read_tum(path)  # normalised quaternions
            order = trajectory.time_order(path, stamps)
            stamps, poses = stamps[order], poses[order]
            fixes.append(f"{path}: quaternions normalised")
        try:
            evaluation.check_rotations(poses, str(path))
        except ValueError as err:
            if not args.fix_rotations:
                raise CliError(f"{err}; --fix-rotations re-orthonormalises them (nearest rotation)") from None
            poses, change = evaluation.orthonormalize(poses)
            fixes.append(f"{path}: rotations re-orthonormalised (largest entry change {change:.3g})")
        loaded.append((stamps, poses))
    (t_est, est), (t_ref, ref) = loaded
    for line in fixes:
        logger.info(f"swiftjax: {line}")
    if args.format == "tum":
        i_ref, i_est = evaluation.associate(t_ref, t_est, max_diff=args.max_diff, offset=args.offset)
        if len(i_ref) < 3:
            raise CliError(
                f"only {len(i_ref)} of the {len(est)} poses of {est_path} match one of the {len(ref)} poses of "
                f"{ref_path} within --max-diff {args.max_diff} s (--offset {args.offset} s); 3 are needed"
            )
        logger.info(
            f"associated {len(i_ref)} poses by timestamp ({est_path}: {len(est)}, {ref_path}: {len(ref)}; "
            f"max diff {args.max_diff} s, offset {args.offset} s)"
        )
        est, ref = est[i_est], ref[i_ref]
    elif len(est) != len(ref):
        raise CliError(f"{est_path} has {len(est)} poses but {ref_path} has {len(ref)} (KITTI files pair by row)")
    try:
        a = evaluation.ate(est, ref, align=args.align)
        r = evaluation.rpe(est, ref, delta=args.delta, align=args.align)
    except ValueError as err:
        raise CliError(f"evaluating {est_path} against {ref_path} ({len(est)} poses): {one_line(err)}") from None
    rows = [
        [f"ATE translation ({unit})", a.rmse, a.mean, a.median, a.max],
        [f"RPE translation, delta {args.delta} ({unit})", *_stats(r.translation)],
        [f"RPE rotation, delta {args.delta} (deg)", *_stats(r.rotation_deg)],
    ]
    print(f"reference: {ref_path} (errors in its unit, {unit}); estimate: {est_path}")
    print(f"alignment: {args.align} (scale {a.scale:.6g}); {len(est)} poses")
    print(markdown_table(["metric", "rmse", "mean", "median", "max"], rows))
    return 0


def _stats(s: Any) -> list[float]:
    return [float(s.rmse), float(s.mean), float(s.median), float(s.max)]

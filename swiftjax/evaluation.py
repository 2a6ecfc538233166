"""Trajectory and point-cloud metrics: ATE (Umeyama-aligned), RPE, accuracy/completeness/Chamfer.

Host-level evaluation in float64 whatever JAX's x64 setting is: the alignment calls
:func:`swiftjax.align.umeyama` inside a ``jax.enable_x64(True)`` context on float64 inputs
(a float32 Umeyama misses evo by ~1e-6 relative on a 3.7 km trajectory); everything else is
float64 NumPy.

Definitions (evo 1.38's, checked number for number in ``tests/test_evaluation.py``):

* **ATE** = evo's APE, ``PoseRelation.translation_part``, after ``traj_est.align(traj_ref,
  correct_scale=...)``.  The estimate's positions are aligned to the reference's by Umeyama
  (``align="sim3"``: rotation, translation, scale = ``evo_ape --align --correct_scale``;
  ``"se3"``: rotation and translation = ``--align``; ``"none"``), then the per-pose error is
  ``e_i = |s R p_i + t - q_i|`` (metres of the reference), with statistics rmse, mean,
  median, std, min, max, sse over ``e``.
* **RPE** = evo's RPE with ``delta`` in frames on consecutive pairs ``(0, d), (d, 2d), ...``
  (``all_pairs=False``) or every ``(i, i + d)`` (``all_pairs=True``).  With aligned poses
  ``P_i`` (estimate) and ``Q_i`` (reference), ``E_i = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``;
  translation error ``|t(E_i)|``, rotation error = the angle of ``R(E_i)`` in degrees
  (evo's ``rotation_angle_deg``).  Alignment as for ATE (default ``"sim3"``, i.e.
  ``evo_rpe --align --correct_scale``; ``"none"`` is evo_rpe's own default).
* **Rotations** must be rotations: :func:`rpe` refuses a pose whose ``R`` is not orthonormal
  with positive determinant within ``rotation_tol`` (``max |R^T R - I|``, default 1e-4; the
  KITTI 00 ground truth, written with 7 significant digits, is orthonormal to 2.3e-7), naming
  the pose -- a scaled or sheared "rotation" would silently inflate RPE.
  :func:`orthonormalize` projects onto SO(3) (nearest rotation, SVD) when the user asks.
* **Association** (TUM files): :func:`associate` pairs poses by timestamp exactly as evo's
  ``sync.associate_trajectories`` (nearest time within ``max_diff`` seconds, the estimate
  shifted by ``offset``, the shorter trajectory driving), never by row.
* **Point clouds**: accuracy = mean distance from each predicted point to its nearest
  ground-truth point, completeness = mean distance from each ground-truth point to its
  nearest predicted point, Chamfer = their average (the DTU "overall" convention the VGGT
  line of papers reports), on clouds randomly subsampled to at most ``max_points`` each
  (seeded).  Nearest neighbours use scipy's ``cKDTree`` (exact, O(N log N)): a blocked JAX
  brute force is O(N M) (2e5 x 2e5 points: 4e10 distances).
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import align as _align
from swiftjax import sim3

__all__ = [
    "ErrorStats",
    "ATEResult",
    "RPEResult",
    "ChamferResult",
    "umeyama_alignment",
    "ROTATION_TOLERANCE",
    "check_rotations",
    "orthonormalize",
    "associate",
    "ate",
    "rpe",
    "chamfer",
]

#: ``sim3.to_rst`` as one program (op by op it compiled a dozen small programs on a first call).
_to_rst = jax.jit(sim3.to_rst)

Alignment = Literal["sim3", "se3", "none"]

#: Largest coordinate :func:`umeyama_alignment` accepts (its covariance squares them).
_MAX_COORDINATE = 1e100

#: Largest ``max |R^T R - I|`` accepted as a rotation (see the module docstring).
ROTATION_TOLERANCE = 1e-4


class ErrorStats(NamedTuple):
    """evo's statistics of a 1-D error array."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float

    @staticmethod
    def of(e: np.ndarray) -> ErrorStats:
        e = np.asarray(e, np.float64)
        return ErrorStats(
            rmse=float(np.sqrt(np.mean(e**2))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
            sse=float(np.sum(e**2)),
        )


class ATEResult(NamedTuple):
    """Absolute trajectory error (translation, metres of the reference).

    Attributes:
        rmse, mean, median, std, min, max, sse: statistics of ``errors``.
        errors: ``[N]`` per-pose errors ``|s R p_i + t - q_i|``.
        align: ``"sim3"``, ``"se3"`` or ``"none"``.
        rotation: ``[3, 3]``, translation: ``[3]``, scale: the alignment applied to the estimate.
        aligned: ``[N, 3]`` aligned estimated positions.
    """

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    errors: np.ndarray
    align: str
    rotation: np.ndarray
    translation: np.ndarray
    scale: float
    aligned: np.ndarray


class RPEResult(NamedTuple):
    """Relative pose error over pose pairs ``delta`` frames apart.

    Attributes:
        translation: :class:`ErrorStats` of ``|t(E_i)|`` (reference units).
        rotation_deg: :class:`ErrorStats` of the rotation angle of ``E_i`` in degrees.
        translation_errors, rotation_errors_deg: ``[M]`` per pair.
        pairs: ``[M, 2]`` int index pairs ``(i, j)``.
        delta, all_pairs, align: the settings.
    """

    translation: ErrorStats
    rotation_deg: ErrorStats
    translation_errors: np.ndarray
    rotation_errors_deg: np.ndarray
    pairs: np.ndarray
    delta: int
    all_pairs: bool
    align: str


class ChamferResult(NamedTuple):
    """Point-cloud distances (units of the inputs).

    Attributes:
        accuracy: mean predicted -> ground-truth nearest-neighbour distance.
        completeness: mean ground-truth -> predicted nearest-neighbour distance.
        chamfer: ``(accuracy + completeness) / 2``.
        accuracy_median, completeness_median: the medians of the same distances.
        num_pred, num_gt: points used after subsampling.
    """

    accuracy: float
    completeness: float
    chamfer: float
    accuracy_median: float
    completeness_median: float
    num_pred: int
    num_gt: int


# ------------------------------------------------------------------------------- helpers


def _as_poses_or_positions(x: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """``[N, 4, 4]`` / ``[N, 3, 4]`` poses or ``[N, 3]`` positions -> (positions, poses | None)."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 3 and a.shape[1:] in ((4, 4), (3, 4)):
        P = np.tile(np.eye(4), (a.shape[0], 1, 1))
        P[:, :3, :] = a[:, :3, :]
        out = (P[:, :3, 3].copy(), P)
    elif a.ndim == 2 and a.shape[1] == 3:
        out = (a, None)
    else:
        raise ValueError(f"{name} must be poses [N, 4, 4] / [N, 3, 4] or positions [N, 3], got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds non-finite values (nan/inf)")
    return out


def _check_align(align: str) -> str:
    if align not in ("sim3", "se3", "none"):
        raise ValueError(f"align must be 'sim3', 'se3' or 'none', got {align!r}")
    return align


def umeyama_alignment(
    src: np.ndarray, dst: np.ndarray, align: Alignment = "sim3"
) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R [3, 3], t [3], s)`` minimising ``sum |dst - (s R src + t)|^2`` in float64.

    ``align="sim3"`` is :func:`swiftjax.align.umeyama` run under ``jax.enable_x64(True)``;
    ``"se3"`` keeps its rotation (the rotation does not depend on the scale) with ``s = 1``
    and ``t = mean(dst) - R mean(src)`` (evo's ``with_scale=False``); ``"none"`` is identity.

    Raises:
        ValueError: shapes differ, fewer than 3 points, or a degenerate configuration
            (collinear / coincident points) for which the alignment is undefined.
    """
    _check_align(align)
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"src {src.shape} and dst {dst.shape} must both be [N, 3]")
    if align == "none":
        return np.eye(3), np.zeros(3), 1.0
    if src.shape[0] < 3:
        raise ValueError(f"Umeyama alignment needs at least 3 positions, got {src.shape[0]}")
    for name, x in (("estimated", src), ("reference", dst)):
        big = float(np.abs(x).max())
        if big > _MAX_COORDINATE:  # squares overflow: not "collinear", just too large
            raise ValueError(
                f"the {name} positions reach {big:.3g}, too large to align (squares overflow float64; at most "
                f"{_MAX_COORDINATE:.0e}): a unit or parsing error in the file?"
            )
    with jax.enable_x64(True):
        S, info = _align.umeyama(jnp.asarray(src, jnp.float64), jnp.asarray(dst, jnp.float64))
        R, t, s = (np.asarray(v, np.float64) for v in _to_rst(S))
        valid = bool(info.valid)
    if not valid:
        raise ValueError(
            "Umeyama alignment is degenerate (positions coincident or collinear): "
            "use align='none' for such trajectories"
        )
    if align == "se3":
        return R, dst.mean(axis=0) - R @ src.mean(axis=0), 1.0
    return R, t, float(s)


def check_rotations(poses: np.ndarray, name: str = "poses", tol: float = ROTATION_TOLERANCE) -> float:
    """Raise ``ValueError`` naming the first pose of ``poses [N, 3|4, 4]`` whose rotation block is
    not orthonormal within ``tol`` (``max |R^T R - I|``) or has ``det R <= 0``; returns the
    largest deviation found."""
    R = np.asarray(poses, np.float64)[:, :3, :3]
    if R.shape[0] == 0:
        return 0.0
    dev = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-2, -1))
    det = np.linalg.det(R)
    bad = np.flatnonzero((dev > tol) | (det <= 0) | ~np.isfinite(dev))
    if bad.size:
        k = int(bad[0])
        raise ValueError(
            f"{name}: pose {k} (of {R.shape[0]}) has a rotation that is not orthonormal "
            f"(max |R^T R - I| = {dev[k]:.3g} > {tol:g}, det {det[k]:.6g}; {bad.size} such poses)"
        )
    return float(dev.max())


def orthonormalize(poses: np.ndarray) -> tuple[np.ndarray, float]:
    """Each rotation block replaced by its nearest rotation (Frobenius norm: ``U diag(1, 1,
    det(U V^T)) V^T`` of its SVD): ``(poses [N, 4, 4] float64, largest change max |R' - R|)``."""
    P = np.asarray(poses, np.float64)
    out = np.tile(np.eye(4), (P.shape[0], 1, 1))
    out[:, :3, :] = P[:, :3, :]
    U, _, Vt = np.linalg.svd(out[:, :3, :3])
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    R = U @ (np.concatenate([np.ones((len(d), 2)), d[:, None]], axis=1)[:, :, None] * Vt)
    change = float(np.abs(R - out[:, :3, :3]).max()) if len(d) else 0.0
    out[:, :3, :3] = R
    return out, change


def _matching_time_indices(
    stamps_1: np.ndarray, stamps_2: np.ndarray, max_diff: float, offset_2: float
) -> tuple[np.ndarray, np.ndarray]:
    """For each stamp of ``stamps_1``, the nearest of ``stamps_2 + offset_2`` if within
    ``max_diff`` (evo's ``matching_time_indices``, ties included: on sorted stamps the earlier of
    two equidistant neighbours, else the first minimum)."""
    s2 = np.asarray(stamps_2, np.float64) + offset_2
    s1 = np.asarray(stamps_1, np.float64)
    if s2.size == 0 or s1.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if not np.all(np.diff(s2) >= 0):
        diffs = np.abs(s2[None, :] - s1[:, None])
        j = np.argmin(diffs, axis=1)
        ok = diffs[np.arange(len(s1)), j] <= max_diff
        return np.flatnonzero(ok), j[ok]
    j = np.minimum(np.searchsorted(s2, s1, side="right"), len(s2) - 1)
    ub = s2[j] - s1
    lb = np.where(j > 0, s1 - s2[np.maximum(j - 1, 0)], np.inf)
    inside = (s1 >= s2[0] - max_diff) & (s1 <= s2[-1] + max_diff)
    take_ub = (ub <= max_diff) & (ub < lb)
    take_lb = ~take_ub & (lb <= max_diff) & (lb <= ub)
    ok = inside & (take_ub | take_lb)
    best = np.where(take_ub, j, j - 1)
    return np.flatnonzero(ok), best[ok]


def associate(
    stamps_ref: np.ndarray, stamps_est: np.ndarray, max_diff: float = 0.01, offset: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(ref_idx [M], est_idx [M])`` of poses at matching times, as evo's
    ``sync.associate_trajectories(ref, est, max_diff=max_diff, offset_2=offset)``: the
    trajectory with fewer poses drives, each of its stamps taking the nearest stamp of the
    other within ``max_diff`` seconds, the estimate's stamps shifted by ``offset``.

    Raises:
        ValueError: ``max_diff < 0`` or non-finite arguments.
    """
    if not (np.isfinite(max_diff) and max_diff >= 0 and np.isfinite(offset)):
        raise ValueError(f"max_diff must be finite and >= 0 and offset finite, got {max_diff}, {offset}")
    ref = np.asarray(stamps_ref, np.float64)
    est = np.asarray(stamps_est, np.float64)
    if len(est) > len(ref):  # the reference is the shorter one and drives
        i, j = _matching_time_indices(ref, est, max_diff, offset)
        return i, j
    j, i = _matching_time_indices(est, ref, max_diff, -offset)
    return i, j


# ----------------------------------------------------------------------------------- ATE


def ate(estimated: np.ndarray, reference: np.ndarray, align: Alignment = "sim3") -> ATEResult:
    """Absolute trajectory error of ``estimated`` against ``reference`` (module docstring).

    Args:
        estimated, reference: ``[N, 4, 4]`` (or ``[N, 3, 4]``) camera-to-world poses, or
            ``[N, 3]`` positions; the same ``N`` (associate them beforehand).
        align: ``"sim3"`` (default; evo ``--align --correct_scale``), ``"se3"`` or ``"none"``.

    Raises:
        ValueError: bad shapes, different lengths, non-finite values, degenerate alignment.
    """
    _check_align(align)
    p, _ = _as_poses_or_positions(estimated, "estimated")
    q, _ = _as_poses_or_positions(reference, "reference")
    if p.shape[0] != q.shape[0]:
        raise ValueError(f"estimated has {p.shape[0]} poses but reference has {q.shape[0]}")
    if p.shape[0] == 0:
        raise ValueError("empty trajectories")
    R, t, s = umeyama_alignment(p, q, align)
    aligned = s * p @ R.T + t
    e = np.linalg.norm(aligned - q, axis=1)
    st = ErrorStats.of(e)
    return ATEResult(*st, errors=e, align=align, rotation=R, translation=t, scale=s, aligned=aligned)


# ----------------------------------------------------------------------------------- RPE


def _rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle of ``[M, 3, 3]`` rotations in radians, exactly as evo computes it.

    evo's ``so3_log_angle``: scipy ``Rotation.from_matrix`` (Shepperd quaternion, normalised)
    then the rotation-vector norm.  Matrices built from files with 7 significant digits (KITTI)
    are orthonormal only to ~1e-7; a closed form such as ``atan2(|vee(R - R^T)|/2,
    (tr R - 1)/2)`` then differs from evo by ~1e-8 relative on small angles, so we take
    evo's route to match it number for number.
    """
    from scipy.spatial.transform import Rotation

    return np.linalg.norm(Rotation.from_matrix(R).as_rotvec(), axis=-1)


def _se3_inv(P: np.ndarray) -> np.ndarray:
    out = np.tile(np.eye(4), (*P.shape[:-2], 1, 1))
    Rt = np.swapaxes(P[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, P[..., :3, 3])
    return out


def rpe(
    estimated: np.ndarray,
    reference: np.ndarray,
    delta: int = 1,
    all_pairs: bool = False,
    align: Alignment = "sim3",
    rotation_tol: float = ROTATION_TOLERANCE,
) -> RPEResult:
    """Relative pose error (module docstring): translation and rotation per ``delta`` frames.

    Args:
        estimated, reference: ``[N, 4, 4]`` / ``[N, 3, 4]`` camera-to-world poses (same ``N``).
        delta: frame distance of the pairs (>= 1).
        all_pairs: every ``(i, i + delta)`` instead of consecutive ``(k delta, (k+1) delta)``.
        align: alignment applied to the estimate first (as for :func:`ate`).
        rotation_tol: largest ``max |R^T R - I|`` accepted (:func:`check_rotations`).

    Raises:
        ValueError: bad shapes/lengths, ``delta < 1``, no pair fits in ``N`` frames, or a
            rotation block that is not a rotation.
    """
    _check_align(align)
    if int(delta) != delta or delta < 1:
        raise ValueError(f"delta must be an integer >= 1, got {delta}")
    delta = int(delta)
    p, P = _as_poses_or_positions(estimated, "estimated")
    q, Q = _as_poses_or_positions(reference, "reference")
    if P is None or Q is None:
        raise ValueError("rpe needs full poses [N, 4, 4], not positions")
    check_rotations(P, "estimated", rotation_tol)
    check_rotations(Q, "reference", rotation_tol)
    n = P.shape[0]
    if Q.shape[0] != n:
        raise ValueError(f"estimated has {n} poses but reference has {Q.shape[0]}")
    if all_pairs:
        i = np.arange(0, max(n - delta, 0))
    else:
        i = np.arange(0, n, delta)[:-1] if n > 0 else np.zeros(0, int)
    j = i + delta
    if len(i) == 0:
        raise ValueError(f"no pose pair {delta} frames apart in {n} poses")
    R, t, s = umeyama_alignment(p, q, align)
    Pa = P.copy()
    Pa[:, :3, 3] = s * P[:, :3, 3] @ R.T + t
    Pa[:, :3, :3] = R @ P[:, :3, :3]
    Q_rel = _se3_inv(Q[i]) @ Q[j]
    P_rel = _se3_inv(Pa[i]) @ Pa[j]
    E = _se3_inv(Q_rel) @ P_rel
    te = np.linalg.norm(E[:, :3, 3], axis=1)
    re = np.degrees(np.abs(_rotation_angle(E[:, :3, :3])))
    return RPEResult(
        translation=ErrorStats.of(te),
        rotation_deg=ErrorStats.of(re),
        translation_errors=te,
        rotation_errors_deg=re,
        pairs=np.stack([i, j], axis=1),
        delta=delta,
        all_pairs=all_pairs,
        align=align,
    )


# ------------------------------------------------------------------------------- Chamfer


def _points(x: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(x, np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be [N, 3] points, got shape {a.shape}")
    a = a[np.all(np.isfinite(a), axis=1)]
    if a.shape[0] == 0:
        raise ValueError(f"{name} has no finite points")
    return a


def chamfer(
    pred_points: np.ndarray,
    gt_points: np.ndarray,
    max_points: int | None = 200_000,
    seed: int = 0,
    workers: int = 1,
) -> ChamferResult:
    """Accuracy, completeness and Chamfer distance between two clouds (module docstring).

    Args:
        pred_points: ``[N, 3]`` reconstructed points (non-finite rows are dropped).
        gt_points: ``[M, 3]`` ground-truth points (same frame and units).
        max_points: subsample each cloud uniformly at random to at most this many points
            (``None``: use all).
        seed: seed of the subsampling.
        workers: threads for the KD-tree queries (scipy ``workers``).
    """
    a = _points(pred_points, "pred_points")
    b = _points(gt_points, "gt_points")
    rng = np.random.default_rng(seed)
    if max_points is not None:
        if len(a) > max_points:
            a = a[rng.choice(len(a), max_points, replace=False)]
        if len(b) > max_points:
            b = b[rng.choice(len(b), max_points, replace=False)]
    from scipy.spatial import cKDTree

    d_acc, _ = cKDTree(b).query(a, k=1, workers=workers)
    d_comp, _ = cKDTree(a).query(b, k=1, workers=workers)
    acc, comp = float(np.mean(d_acc)), float(np.mean(d_comp))
    return ChamferResult(
        accuracy=acc,
        completeness=comp,
        chamfer=0.5 * (acc + comp),
        accuracy_median=float(np.median(d_acc)),
        completeness_median=float(np.median(d_comp)),
        num_pred=int(len(a)),
        num_gt=int(len(b)),
    )

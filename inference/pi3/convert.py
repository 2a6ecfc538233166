"""π³ / π³X outputs of one chunk -> :class:`swiftjax.prediction.ChunkPrediction`.

* **depth** = the local points' ``z`` (camera frame, OpenCV axes; π³X: metric-scaled).
* **intrinsics** from the rays by linear least squares, per view: for every pixel ``(u, v)``
  (integer pixel centres, swiftjax's and upstream ``recover_intrinsic_from_rays_d``'s grid)
  ``u = f_x x/z + c_x`` and ``v = f_y y/z + c_y``; the two independent 1-D regressions give
  ``f = cov(x/z, u) / var(x/z)``, ``c = mean(u) - f mean(x/z)`` (float64).  With
  ``center_principal_point`` the centre is fixed at ``((W-1)/2, (H-1)/2)`` and only ``f`` is
  fitted (``f = sum(x/z (u - c)) / sum((x/z)^2)``).  For a perfect pinhole prediction this
  recovers ``K`` exactly, so ``depth * K^-1 (u, v, 1)`` reproduces π³'s local points.
* **extrinsics**: π³'s poses are camera-to-world in an arbitrary world frame (no reference
  view).  ``E_i = inv(T_i)``, then re-based on the chunk's first camera: ``E'_i = E_i T_0``
  (so ``E'_0 = I``), world-to-camera ``[S, 3, 4]``.  A rigid change of world frame keeps the
  depths and poses consistent (points = poses @ local points).
* **confidence**: π³'s ``conf`` is a logit; the chunk confidence is ``sigmoid(logit)`` in
  (0, 1).  The pipeline only uses confidence RELATIVE to the frame mean (reliability mask
  ``gamma > 0.5 mean(gamma)``, point filter ``gamma >= 0.75 mean(gamma)``), which a
  probability keeps meaningful: VGGT's ``1 + exp(logit)`` would let a handful of saturated
  pixels (logit 15 -> 3e6) dominate the mean and empty both masks, whereas upstream itself
  thresholds ``sigmoid(conf)`` (> 0.1 in its examples, > 0.05 in its VO pipeline).  The kept
  fractions are measured in ``tests/test_pi3_convert.py``.
* A view whose fitted focal length is not finite and positive (its rays describe no forward
  pinhole camera: only an untrained or degenerate network does that, e.g. the tiny random golden
  models) gets a nominal 60° horizontal field of view with a centred principal point instead,
  with a warning naming the fitted values, so that a run still completes.
* **patch tokens** = DINO ``x_norm_patchtokens`` before the multi-view decoder, ``[S, P, C]``
  (golden key ``dino_patch_tokens``), the layout VGGT's runners give.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from swiftjax.prediction import ChunkPrediction

from ..preprocess import to_uint8_images

__all__ = [
    "metric_scale",
    "intrinsics_from_local_points",
    "usable_intrinsics",
    "rebase_extrinsics",
    "confidence_from_logit",
    "to_chunk_prediction",
]

logger = logging.getLogger("swiftjax." + __name__)


def intrinsics_from_local_points(points: Any, center_principal_point: bool = False) -> np.ndarray:
    """Pinhole ``K [..., 3, 3]`` (float64) fitted to camera-frame points or rays ``[..., H, W, 3]``
    (module docstring).  Pixels with ``|z| <= 1e-10`` or non-finite coordinates are ignored."""
    p = np.asarray(points, dtype=np.float64)
    *lead, h, w, _ = p.shape
    z = p[..., 2]
    ok = np.isfinite(p).all(axis=-1) & (np.abs(z) > 1e-10)
    safe_z = np.where(ok, z, 1.0)
    x = np.where(ok, p[..., 0] / safe_z, 0.0).reshape(*lead, -1)
    y = np.where(ok, p[..., 1] / safe_z, 0.0).reshape(*lead, -1)
    wgt = ok.reshape(*lead, -1).astype(np.float64)
    v, u = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    if center_principal_point:
        cx = np.full(lead, (w - 1) / 2.0)
        cy = np.full(lead, (h - 1) / 2.0)
        fx = (wgt * x * (u - (w - 1) / 2.0)).sum(-1) / (wgt * x * x).sum(-1)
        fy = (wgt * y * (v - (h - 1) / 2.0)).sum(-1) / (wgt * y * y).sum(-1)
    else:
        fx, cx = _line_fit(x, u, wgt)
        fy, cy = _line_fit(y, v, wgt)
    K = np.zeros((*lead, 3, 3))
    K[..., 0, 0], K[..., 0, 2], K[..., 1, 1], K[..., 1, 2], K[..., 2, 2] = fx, cx, fy, cy, 1.0
    return K


def _line_fit(x: np.ndarray, target: np.ndarray, wgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares ``target = a x + b`` over the last axis, weights ``wgt`` (0/1)."""
    n = wgt.sum(-1)
    mx = (wgt * x).sum(-1) / n
    mt = (wgt * target).sum(-1) / n
    xc = x - mx[..., None]
    a = (wgt * xc * (target - mt[..., None])).sum(-1) / (wgt * xc * xc).sum(-1)
    return a, mt - a * mx


NOMINAL_HFOV_DEG = 60.0


def usable_intrinsics(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """``K [S, 3, 3]`` with every view whose focal lengths are not finite and positive replaced
    by a nominal 60° horizontal field of view (centred principal point), with a warning."""
    K = np.array(K, dtype=np.float64)
    f = np.stack([K[:, 0, 0], K[:, 1, 1]], -1)
    bad = ~np.all(np.isfinite(K.reshape(len(K), -1)), axis=-1) | np.any(~(f > 0), axis=-1)
    if np.any(bad):
        nominal = (width / 2.0) / np.tan(np.deg2rad(NOMINAL_HFOV_DEG) / 2.0)
        logger.warning(
            f"π³: the rays of view(s) {np.flatnonzero(bad).tolist()} describe no pinhole camera (fitted fx, fy "
            f"= {f[bad][0].round(3).tolist()}, ...); using a nominal {NOMINAL_HFOV_DEG:g}° field of view there"
        )
        K[bad] = [[nominal, 0.0, (width - 1) / 2.0], [0.0, nominal, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    return K


def rebase_extrinsics(cam_to_world: Any) -> np.ndarray:
    """``[S, 4, 4]`` camera-to-world -> ``[S, 3, 4]`` world-to-camera with camera 0 at the origin:
    ``E_i = inv(T_i) T_0`` (rigid inverse; float64 inside)."""
    T = np.asarray(cam_to_world, dtype=np.float64)
    rt = np.swapaxes(T[..., :3, :3], -1, -2)
    inv = np.zeros_like(T)
    inv[..., :3, :3] = rt
    inv[..., :3, 3:] = -rt @ T[..., :3, 3:]
    inv[..., 3, 3] = 1.0
    return (inv @ T[0])[..., :3, :]


def metric_scale(outputs: dict[str, Any]) -> float:
    """π³X's metric scale of one scene (``exp`` of the metric head on the metric token).

    π³X's outputs are already multiplied by it (depths in approximately metres); this is the
    factor itself, e.g. for ``--metric model`` bookkeeping.  π³ has none (raises KeyError).
    """
    m = outputs["metric"]
    m = m.detach().cpu().numpy() if hasattr(m, "detach") else np.asarray(m)
    if m.size != 1:
        raise ValueError(f"metric must hold one scene's scale, got shape {m.shape}")
    return float(m.reshape(()))


def confidence_from_logit(logit: Any) -> np.ndarray:
    """``sigmoid(logit)`` in float32, computed without overflow."""
    x = np.asarray(logit, dtype=np.float64)
    return (0.5 * (1.0 + np.tanh(0.5 * x))).astype(np.float32)


def to_chunk_prediction(
    outputs: dict[str, Any], images: Any | None = None, center_principal_point: bool = False
) -> ChunkPrediction:
    """One scene's outputs (batch axis removed, NumPy or torch) -> :class:`ChunkPrediction`.

    Args:
        outputs: ``local_points [S,H,W,3]``, ``conf [S,H,W,1]`` (logit), ``camera_poses
            [S,4,4]`` (camera-to-world) and ``dino_patch_tokens [S,P,C]``.
        images: the ``[S, 3, H, W]`` float [0, 1] input (colours), or ``None``.
        center_principal_point: fit only the focal lengths (see
            :func:`intrinsics_from_local_points`).
    """
    arr = {k: np.asarray(v.detach().cpu() if hasattr(v, "detach") else v) for k, v in outputs.items()}
    local = arr["local_points"].astype(np.float32)
    s, h, w, _ = local.shape
    return ChunkPrediction(
        depth=np.ascontiguousarray(local[..., 2]),
        conf=confidence_from_logit(arr["conf"].reshape(s, h, w)),
        extrinsic=rebase_extrinsics(arr["camera_poses"]).astype(np.float32),
        intrinsic=usable_intrinsics(intrinsics_from_local_points(local, center_principal_point), h, w).astype(
            np.float32
        ),
        patch_tokens=np.ascontiguousarray(arr["dino_patch_tokens"], dtype=np.float32),
        images=None if images is None else to_uint8_images(np.asarray(images)),
    )

"""Float64 NumPy SO(3)/SE(3) helpers of the synthetic oracle (host-side, per chunk: a handful of
matrices, where a jitted call would cost more than it saves)."""

from __future__ import annotations

import numpy as np

__all__ = ["se3_power", "so3_exp"]


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues, ``[..., 3] -> [..., 3, 3]`` float64."""
    w = np.asarray(w, np.float64)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    Kx = np.zeros((*w.shape[:-1], 3, 3))
    Kx[..., 0, 1], Kx[..., 0, 2], Kx[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    Kx = Kx - np.swapaxes(Kx, -1, -2)
    small = th < 1e-8
    A = np.where(small, 1.0, np.sin(th) / np.where(small, 1.0, th))
    B = np.where(small, 0.5, (1 - np.cos(th)) / np.where(small, 1.0, th**2))
    return np.eye(3) + A * Kx + B * (Kx @ Kx)


def se3_power(H: np.ndarray, w: float) -> np.ndarray:
    """``Exp(w Log H)`` of a rigid ``[4, 4]`` motion, float64: with ``omega = Log R`` (any angle up
    to pi, via SciPy's rotation vector) and ``V(omega) = I + (1 - cos t)/t^2 [omega] + (t - sin t)/t^3
    [omega]^2``, ``Log H = (V(omega)^-1 t, omega)`` and the result is ``(exp(w omega), V(w omega) w rho)``."""
    from scipy.spatial.transform import Rotation

    def V(om: np.ndarray) -> np.ndarray:
        th = float(np.linalg.norm(om))
        Kx = np.array([[0.0, -om[2], om[1]], [om[2], 0.0, -om[0]], [-om[1], om[0], 0.0]])
        if th < 1e-8:
            return np.eye(3) + 0.5 * Kx + Kx @ Kx / 6.0
        return np.eye(3) + (1 - np.cos(th)) / th**2 * Kx + (th - np.sin(th)) / th**3 * (Kx @ Kx)

    omega = Rotation.from_matrix(H[:3, :3]).as_rotvec()
    rho = np.linalg.solve(V(omega), H[:3, 3])
    out = np.eye(4)
    out[:3, :3] = so3_exp(w * omega)
    out[:3, 3] = V(w * omega) @ (w * rho)
    return out

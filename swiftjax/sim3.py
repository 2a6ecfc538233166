"""The similarity group Sim(3) as pure functions over arrays.

Layout (DESIGN.md, the same as pypose's ``Sim3``):

* an element is ``[..., 8] = (tx, ty, tz, qx, qy, qz, qw, s)``: translation, unit quaternion
  (scalar last) and positive scale; it acts on points as ``x' = s R x + t``;
* a tangent vector is ``[..., 7] = (rho, omega, sigma)`` with ``s = exp(sigma)`` (the order
  of Sophus and pypose);
* composition is ``(A o B)(x) = A(B(x))``.

Every function accepts leading batch axes and broadcasts them against each other, and is
safe under ``jax.jit``, ``jax.vmap`` and ``jax.grad`` (double-``where`` small-angle
branches: no ``0/0`` ever reaches a gradient).  Nothing here is shape-dependent beyond the
trailing axis, so a jitted caller recompiles only when batch shapes or dtypes change.

Exponential map (Sophus ``sim3.hpp``, ``calcW``; Eade, "Lie groups for computer vision",
sec. 6).  With ``theta = |omega|``, ``K = [omega]x``::

    exp(rho, omega, sigma) = (W rho, exp_SO3(omega), e^sigma)
    W = C I + A K + B K^2 = integral_0^1 e^(sigma u) exp(u K) du
    C = (e^sigma - 1) / sigma
    A = (e^sigma sin(theta) sigma + (1 - e^sigma cos(theta)) theta) / (theta (sigma^2 + theta^2))
    B = (C - ((e^sigma cos(theta) - 1) sigma + e^sigma sin(theta) theta) / (sigma^2 + theta^2)) / theta^2

Named special cases, each with its own branch and test:

* ``sigma -> 0``: ``C -> 1 + sigma/2 + sigma^2/6`` (and ``A, B`` -> the SE(3) ``V`` coefficients);
* ``theta -> 0``: ``A -> ((sigma - 1) e^sigma + 1) / sigma^2``,
  ``B -> (e^sigma (sigma^2/2 - sigma + 1) - 1) / sigma^3``;
* both -> 0: ``A -> 1/2 + sigma/3 + ..., B -> 1/6 + sigma/8 + ...`` (Taylor series);
* ``theta`` near ``pi``: handled by the quaternion log (:func:`swiftjax.so3.log`).

``1 - e^sigma cos(theta)`` is evaluated as ``2 sin^2(theta/2) - expm1(sigma) cos(theta)``, which
keeps ``A`` accurate in float32 where ``cos(theta)`` rounds to 1.

Logarithm: ``omega = log_SO3(q)``, ``sigma = log s`` and ``rho = W^-1 t`` with the closed form
``W^-1 = x I + y K + z K^2`` (``K^3 = -theta^2 K``)::

    x = 1/C,  D = C - theta^2 B,  det = D^2 + theta^2 A^2,
    y = -A / det,  z = (A^2 - B D) / (C det)

which has no division by ``theta`` at all.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from swiftjax import so3

__all__ = [
    "identity",
    "exp",
    "log",
    "compose",
    "inverse",
    "between",
    "act",
    "adjoint",
    "as_matrix",
    "from_matrix",
    "from_rst",
    "to_rst",
    "normalize",
    "translation",
    "quaternion",
    "scale",
    "right_jacobian_inverse",
]


# ----------------------------------------------------------------------------- accessors


def translation(S: ArrayLike) -> Array:
    """``t`` of ``S``: ``[..., 8] -> [..., 3]``."""
    return jnp.asarray(S)[..., 0:3]


def quaternion(S: ArrayLike) -> Array:
    """Unit quaternion ``(qx, qy, qz, qw)`` of ``S``: ``[..., 8] -> [..., 4]``."""
    return jnp.asarray(S)[..., 3:7]


def scale(S: ArrayLike) -> Array:
    """Scale ``s`` of ``S``: ``[..., 8] -> [...]``."""
    return jnp.asarray(S)[..., 7]


def _pack(t: Array, q: Array, s: Array) -> Array:
    batch = jnp.broadcast_shapes(t.shape[:-1], q.shape[:-1], s.shape)
    return jnp.concatenate(
        [
            jnp.broadcast_to(t, (*batch, 3)),
            jnp.broadcast_to(q, (*batch, 4)),
            jnp.broadcast_to(s, batch)[..., None],
        ],
        axis=-1,
    )


# ----------------------------------------------------------------------- group operations


def identity(batch_shape: tuple[int, ...] = (), dtype: jnp.dtype = jnp.float32) -> Array:
    """The identity element ``(0, 0, 0, 0, 0, 0, 1, 1)``, shape ``[*batch_shape, 8]``."""
    e = jnp.array([0, 0, 0, 0, 0, 0, 1, 1], dtype=dtype)
    return jnp.broadcast_to(e, (*batch_shape, 8))


def compose(A: ArrayLike, B: ArrayLike) -> Array:
    """``A o B``: ``(s_A R_A t_B + t_A, q_A q_B, s_A s_B)``; ``[..., 8] x [..., 8] -> [..., 8]``."""
    A, B = jnp.asarray(A), jnp.asarray(B)
    qa, sa = quaternion(A), scale(A)
    t = sa[..., None] * so3.rotate(qa, translation(B)) + translation(A)
    return _pack(t, so3.multiply(qa, quaternion(B)), sa * scale(B))


def inverse(S: ArrayLike) -> Array:
    """``S^-1 = (-(1/s) R^T t, q*, 1/s)``: ``[..., 8] -> [..., 8]``."""
    S = jnp.asarray(S)
    q_inv = so3.conjugate(quaternion(S))
    s_inv = 1.0 / scale(S)
    return _pack(-s_inv[..., None] * so3.rotate(q_inv, translation(S)), q_inv, s_inv)


def between(A: ArrayLike, B: ArrayLike) -> Array:
    """``A^-1 o B``, the relative transform that maps B's frame into A's."""
    return compose(inverse(A), B)


def act(S: ArrayLike, points: ArrayLike) -> Array:
    """Apply ``S`` to points: ``s R x + t``.

    Args:
        S: ``[..., 8]``.
        points: ``[..., 3]``; ``S``'s batch axes broadcast against the points' leading axes
            (pass ``S[..., None, :]`` to map one transform over a trailing point axis).
    """
    S, points = jnp.asarray(S), jnp.asarray(points)
    return scale(S)[..., None] * so3.rotate(quaternion(S), points) + translation(S)


def normalize(S: ArrayLike) -> Array:
    """Re-unit the quaternion of ``S`` (e.g. after many compositions)."""
    S = jnp.asarray(S)
    q = quaternion(S)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return _pack(translation(S), q, scale(S))


# ---------------------------------------------------------------------- exp / log


def _eps(dtype: jnp.dtype) -> tuple[float, float]:
    """(theta^2 threshold, |sigma| threshold for the cancellation-prone theta -> 0 limits)."""
    if jnp.finfo(dtype).bits <= 32:
        return 1e-7, 1e-1
    return 1e-14, 1e-3


def _w_coefficients(theta_sq: Array, sigma: Array) -> tuple[Array, Array, Array]:
    """``(A, B, C)`` of ``W = C I + A K + B K^2`` (module docstring), all branches jit-safe."""
    theta_eps, sigma_eps = _eps(theta_sq.dtype)
    sigma_zero = jnp.abs(sigma) < 1e-3 * theta_eps
    sigma_safe = jnp.where(sigma_zero, jnp.ones_like(sigma), sigma)
    c_coef = jnp.where(
        sigma_zero, 1.0 + sigma / 2.0 + sigma**2 / 6.0, jnp.expm1(sigma_safe) / sigma_safe
    )

    # theta -> 0: A0(sigma), B0(sigma) plus the sigma = 0 part of the theta^2 correction.
    sigma_small = jnp.abs(sigma) < sigma_eps
    ss = jnp.where(sigma_small, jnp.ones_like(sigma), sigma)
    es = jnp.exp(ss)
    a0 = jnp.where(
        sigma_small,
        0.5 + sigma / 3.0 + sigma**2 / 8.0 + sigma**3 / 30.0 + sigma**4 / 144.0,
        ((ss - 1.0) * es + 1.0) / ss**2,
    )
    b0 = jnp.where(
        sigma_small,
        1.0 / 6.0 + sigma / 8.0 + sigma**2 / 20.0 + sigma**3 / 72.0 + sigma**4 / 336.0,
        (es * (0.5 * ss**2 - ss + 1.0) - 1.0) / ss**3,
    )
    a_small = a0 - theta_sq / 24.0
    b_small = b0 - theta_sq / 120.0

    # General branch.
    theta_small = theta_sq < theta_eps
    tsq = jnp.where(theta_small, jnp.ones_like(theta_sq), theta_sq)
    theta = jnp.sqrt(tsq)
    sin_t, cos_t = jnp.sin(theta), jnp.cos(theta)
    em_re = jnp.expm1(sigma) * cos_t - 2.0 * jnp.sin(0.5 * theta) ** 2  # Re(e^z - 1)
    em_im = jnp.exp(sigma) * sin_t  # Im(e^z - 1)
    c = sigma**2 + tsq
    a_gen = (em_im * sigma - em_re * theta) / (theta * c)
    b_gen = (c_coef - (em_re * sigma + em_im * theta) / c) / tsq

    return (
        jnp.where(theta_small, a_small, a_gen),
        jnp.where(theta_small, b_small, b_gen),
        c_coef,
    )


def _apply_poly(x: Array, y: Array, z: Array, omega: Array, v: Array) -> Array:
    """``(x I + y K + z K^2) v`` with ``K = [omega]x``, via two cross products."""
    wv = jnp.cross(omega, v)
    return x[..., None] * v + y[..., None] * wv + z[..., None] * jnp.cross(omega, wv)


def exp(xi: ArrayLike) -> Array:
    """Exponential map ``[..., 7] (rho, omega, sigma) -> [..., 8]``: ``(W rho, exp(omega), e^sigma)``."""
    xi = jnp.asarray(xi)
    rho, omega, sigma = xi[..., 0:3], xi[..., 3:6], xi[..., 6]
    theta_sq = jnp.sum(omega * omega, axis=-1)
    a, b, c = _w_coefficients(theta_sq, sigma)
    t = _apply_poly(c, a, b, omega, rho)
    return _pack(t, so3.exp(omega), jnp.exp(sigma))


def log(S: ArrayLike) -> Array:
    """Logarithm ``[..., 8] -> [..., 7]`` with ``|omega| <= pi``; ``log(exp(xi)) = xi`` for ``|omega| < pi``.

    ``S`` and ``S`` with its quaternion negated give the same tangent.
    """
    S = jnp.asarray(S)
    omega = so3.log(quaternion(S))
    sigma = jnp.log(scale(S))
    theta_sq = jnp.sum(omega * omega, axis=-1)
    a, b, c = _w_coefficients(theta_sq, sigma)
    d = c - theta_sq * b
    det = d * d + theta_sq * a * a
    x = 1.0 / c
    y = -a / det
    z = (a * a - b * d) / (c * det)
    rho = _apply_poly(x, y, z, omega, translation(S))
    return jnp.concatenate([rho, omega, sigma[..., None]], axis=-1)


# ---------------------------------------------------------------- matrices and adjoint


def as_matrix(S: ArrayLike) -> Array:
    """Homogeneous matrix ``[[s R, t], [0, 1]]``: ``[..., 8] -> [..., 4, 4]``."""
    S = jnp.asarray(S)
    sr = scale(S)[..., None, None] * so3.as_matrix(quaternion(S))
    top = jnp.concatenate([sr, translation(S)[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(
        jnp.array([0, 0, 0, 1], dtype=S.dtype), (*S.shape[:-1], 1, 4)
    )
    return jnp.concatenate([top, bottom], axis=-2)


def from_rst(R: ArrayLike, t: ArrayLike, s: ArrayLike) -> Array:
    """Element from rotation ``[..., 3, 3]``, translation ``[..., 3]`` and scale ``[...]``."""
    R, t, s = jnp.asarray(R), jnp.asarray(t), jnp.asarray(s)
    return _pack(t, so3.from_matrix(R), s)


def to_rst(S: ArrayLike) -> tuple[Array, Array, Array]:
    """``(R [..., 3, 3], t [..., 3], s [...])`` of ``S``."""
    S = jnp.asarray(S)
    return so3.as_matrix(quaternion(S)), translation(S), scale(S)


def from_matrix(M: ArrayLike) -> Array:
    """Element from a ``[..., 4, 4]`` (or ``[..., 3, 4]``) similarity matrix ``[[s R, t], ...]``.

    ``s = det(sR)^(1/3)``; the rotation is read from ``sR / s``.  ``M`` must be a similarity
    with positive determinant (the result is meaningless otherwise).
    """
    M = jnp.asarray(M)
    sr = M[..., :3, :3]
    s = jnp.cbrt(jnp.linalg.det(sr))
    return from_rst(sr / s[..., None, None], M[..., :3, 3], s)


def adjoint(S: ArrayLike) -> Array:
    """Adjoint ``[..., 8] -> [..., 7, 7]`` with ``S o exp(xi) o S^-1 = exp(Ad(S) xi)``::

        Ad(S) = [[s R, [t]x R, -t],
                 [0,   R,       0],
                 [0,   0,       1]]
    """
    S = jnp.asarray(S)
    R, t, s = to_rst(S)
    batch = S.shape[:-1]
    zeros31 = jnp.zeros((*batch, 3, 1), S.dtype)
    zeros33 = jnp.zeros((*batch, 3, 3), S.dtype)
    row0 = jnp.concatenate([s[..., None, None] * R, so3.hat(t) @ R, -t[..., :, None]], axis=-1)
    row1 = jnp.concatenate([zeros33, R, zeros31], axis=-1)
    row2 = jnp.broadcast_to(jnp.array([0, 0, 0, 0, 0, 0, 1], S.dtype), (*batch, 1, 7))
    return jnp.concatenate([row0, row1, row2], axis=-2)


def right_jacobian_inverse(xi: ArrayLike) -> Array:
    """``Jr^-1(xi) = d log(exp(xi) exp(d)) / d d`` at ``d = 0``: ``[..., 7] -> [..., 7, 7]``.

    Evaluated exactly (to rounding) by forward-mode differentiation of the closed-form
    ``log o compose o exp`` above: seven JVPs per element, no series truncation, valid for
    every ``|omega| < pi``.  It is what makes a log-residual pose graph reach its true
    minimum: for ``r = log(E)``, ``log(E exp(d)) = r + Jr^-1(r) d + O(d^2)``.
    """
    xi = jnp.asarray(xi)
    batch = xi.shape[:-1]
    flat = xi.reshape(-1, 7)

    def one(x: Array) -> Array:
        return jax.jacfwd(lambda d: log(compose(exp(x), exp(d))))(jnp.zeros_like(x))

    return jax.vmap(one)(flat).reshape(*batch, 7, 7)

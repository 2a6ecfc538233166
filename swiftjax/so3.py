"""SO(3) as pure functions on unit quaternions.

Quaternions are ``[..., 4]`` arrays ``(qx, qy, qz, qw)`` (scalar last, the layout of
pypose and scipy).  Rotation vectors (tangents) are ``[..., 3]``.  Every function
accepts leading batch axes and broadcasts them; everything is jit-, vmap- and grad-safe:
small-angle branches use the double-``where`` trick so that no ``0/0`` reaches a gradient.
The public maps are ``jax.jit``-ted (one program per shape and dtype when called on concrete
arrays, inlined inside another ``jit``); the ``*_components`` helpers are plain functions.

Maths (Sola, "A micro Lie theory", 2018, eqs. 101-106; Sophus ``so3.hpp``):

* ``exp(w) = (sin(t/2) w/t, cos(t/2))`` with ``t = |w|``;
  for ``t -> 0``: ``sin(t/2)/t = 1/2 - t^2/48 + t^4/3840``.
* ``log(q) = 2 atan2(|v|, w) v/|v|`` after flipping ``q`` to ``w >= 0``, so the angle lies
  in ``[0, pi]``; for ``|v| -> 0``: ``2 atan2(n, w)/n = 2/w (1 - n^2/(3 w^2))``.
  At exactly ``pi`` (``w = 0``) both ``w`` and ``-w`` are valid logs; we return the one
  along ``v`` of the given sign.

Non-unit quaternions: every function that reads a rotation from ``q`` (:func:`act`,
:func:`as_matrix`, :func:`log`) reads the rotation of ``q / |q|``, so a quaternion that has
drifted from unit norm means the same rotation everywhere (the products of
:func:`compose` keep the norms' product).  A zero quaternion is no rotation: it gives NaN.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import DTypeLike
from jaxtyping import ArrayLike, Float, Real, Shaped

from swiftjax._elementary import arctan2_nonneg, sincos

__all__ = [
    "identity",
    "exp",
    "log",
    "jlog",
    "compose",
    "inverse",
    "between",
    "act",
    "adjoint",
    "normalize",
    "canonical",
    "hat",
    "vee",
    "as_matrix",
    "from_matrix",
    "project",
]


def _small_angle_eps(dtype: jnp.dtype) -> float:
    """Squared-angle threshold below which the Taylor branches are exact to rounding."""
    return 1e-7 if jnp.finfo(dtype).bits <= 32 else 1e-14


# ------------------------------------------------------------------ component form
#
# XLA on CPU vectorises poorly over a trailing axis of 3 or 4 (every slice and concatenate
# becomes a strided gather), so the hot paths work on *tuples of component arrays*
# ("structure of arrays"): ``split`` moves the component axis to the front once, the maths
# runs on whole arrays, ``join`` stacks and moves it back (docs/performance/sim3.md).

Vec3 = tuple[Array, Array, Array]
Quat = tuple[Array, Array, Array, Array]


def split(x: Shaped[Array, "*s k"]) -> tuple[Shaped[Array, "*s"], ...]:
    """``[..., k] -> k`` arrays of shape ``[...]`` (component axis moved to the front)."""
    return tuple(jnp.moveaxis(x, -1, 0))


def join(components: tuple[Shaped[ArrayLike, "*#s"], ...]) -> Shaped[Array, "*s k"]:
    """Inverse of :func:`split`: broadcast the components and stack them on a last axis."""
    return jnp.moveaxis(jnp.stack(jnp.broadcast_arrays(*components), axis=0), 0, -1)


def hemisphere_sign(w: Float[Array, "*s"]) -> Float[Array, "*s"]:
    """``-1`` where ``w < 0``, else ``+1`` (in ``w``'s dtype): the factor that moves a quaternion
    with real part ``w`` to the ``w >= 0`` hemisphere (the one sign convention of this module)."""
    return jnp.where(w < 0, -1.0, 1.0).astype(w.dtype)


def cross(a: Vec3, b: Vec3) -> Vec3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def dot(a: Vec3, b: Vec3) -> Float[Array, "*s"]:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


class HalfAngle(NamedTuple):
    """Shared trigonometry of a rotation by ``theta`` (computed once, reused by Sim(3)).

    ``theta_sq`` is exact; ``theta`` is ``sqrt(theta_sq)``, or 1 where ``small`` (so that
    divisions by it are safe); ``sin_half``/``cos_half`` are ``sin(theta/2)``/``cos(theta/2)``.
    """

    theta_sq: Array
    theta: Array
    sin_half: Array
    cos_half: Array
    small: Array


def exp_components(w: Vec3) -> tuple[Quat, HalfAngle]:
    """:func:`exp` on components, also returning the half-angle trigonometry."""
    theta_sq = dot(w, w)
    small = theta_sq < _small_angle_eps(theta_sq.dtype)
    theta = jnp.sqrt(jnp.where(small, jnp.ones_like(theta_sq), theta_sq))
    sin_half, cos_half = sincos(0.5 * theta)
    coeff = jnp.where(small, 0.5 - theta_sq / 48.0 + theta_sq**2 / 3840.0, sin_half / theta)
    real = jnp.where(small, 1.0 - theta_sq / 8.0 + theta_sq**2 / 384.0, cos_half)
    q = (coeff * w[0], coeff * w[1], coeff * w[2], real)
    return q, HalfAngle(theta_sq, theta, sin_half, cos_half, small)


def log_components(q: Quat) -> tuple[Vec3, HalfAngle]:
    """:func:`log` on components, also returning the half-angle trigonometry."""
    sign = hemisphere_sign(q[3])
    v = (sign * q[0], sign * q[1], sign * q[2])
    w = sign * q[3]
    n_sq = dot(v, v)
    norm_sq = n_sq + w * w
    # Relative threshold so that non-unit quaternions behave like their unit versions.
    small = n_sq < _small_angle_eps(w.dtype) * norm_sq
    safe_n = jnp.sqrt(jnp.where(small, jnp.ones_like(n_sq), n_sq))
    safe_w = jnp.where(small, w, jnp.ones_like(w))
    theta = 2.0 * arctan2_nonneg(safe_n, w)
    coeff = jnp.where(small, 2.0 / safe_w * (1.0 - n_sq / (3.0 * safe_w * safe_w)), theta / safe_n)
    omega = (coeff * v[0], coeff * v[1], coeff * v[2])
    inv_norm = jax.lax.rsqrt(norm_sq)
    half = HalfAngle(dot(omega, omega), jnp.where(small, 1.0, theta), safe_n * inv_norm, w * inv_norm, small)
    return omega, half


def half_angle(q: Quat, theta_sq: Float[Array, "*s"]) -> HalfAngle:
    """The :class:`HalfAngle` of the rotation ``q`` whose squared angle ``theta_sq = |log q|^2`` is
    known: ``sin(theta/2) = |v| / |q|`` and ``cos(theta/2) = |w| / |q|`` read off the quaternion
    (no trigonometric function).  As in :func:`log_components`, ``theta`` and ``sin_half`` are
    placeholders where ``small`` (the Taylor branches do not read them)."""
    v_sq = dot(q[:3], q[:3])
    inv_norm = jax.lax.rsqrt(v_sq + q[3] * q[3])
    small = theta_sq < _small_angle_eps(theta_sq.dtype)
    theta = jnp.sqrt(jnp.where(small, jnp.ones_like(theta_sq), theta_sq))
    sin_half = jnp.sqrt(jnp.where(small, jnp.ones_like(v_sq), v_sq)) * inv_norm
    return HalfAngle(theta_sq, theta, sin_half, hemisphere_sign(q[3]) * q[3] * inv_norm, small)


def compose_components(a: Quat, b: Quat) -> Quat:
    av, bv = a[:3], b[:3]
    c = cross(av, bv)
    return (
        a[3] * bv[0] + b[3] * av[0] + c[0],
        a[3] * bv[1] + b[3] * av[1] + c[1],
        a[3] * bv[2] + b[3] * av[2] + c[2],
        a[3] * b[3] - dot(av, bv),
    )


def inverse_components(q: Quat) -> Quat:
    return (-q[0], -q[1], -q[2], q[3])


def act_components(q: Quat, x: Vec3) -> Vec3:
    """``R(q / |q|) x = x + (2 / |q|^2) (w (v x x) + v x (v x x))`` (15 multiplies fewer than
    building ``R``).  Any non-zero ``q`` acts as its unit version (as :func:`log` reads it);
    the factor ``2 / |q|^2`` has ``q``'s shape, so broadcasting one ``q`` over many points
    costs one division.  A zero quaternion gives NaN."""
    v, w = q[:3], q[3]
    two_over_n = 2.0 / (dot(v, v) + w * w)
    uv = cross(v, x)
    uuv = cross(v, uv)
    return tuple(x[k] + two_over_n * (w * uv[k] + uuv[k]) for k in range(3))


# ------------------------------------------------------------------------- public API


def identity(batch_shape: tuple[int, ...] = (), dtype: DTypeLike = jnp.float32) -> Float[Array, ...]:
    """The identity quaternion ``(0, 0, 0, 1)`` with shape ``[*batch_shape, 4]``."""
    return jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], dtype=dtype), (*batch_shape, 4))


@jax.jit
def hat(w: Real[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Skew-symmetric matrix ``[w]x`` with ``[w]x v = w x v``: ``[..., 3] -> [..., 3, 3]``."""
    w = jnp.asarray(w)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)],
        axis=-2,
    )


@jax.jit
def vee(m: Real[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Inverse of :func:`hat` (reads the antisymmetric part): ``[..., 3, 3] -> [..., 3]``."""
    m = jnp.asarray(m)
    return 0.5 * jnp.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        axis=-1,
    )


@jax.jit
def exp(w: Real[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 4"]:
    """Exponential map, rotation vector ``[..., 3]`` -> unit quaternion ``[..., 4]``."""
    return join(exp_components(split(jnp.asarray(w)))[0])


@jax.jit
def log(q: Real[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3"]:
    """Logarithm, unit quaternion ``[..., 4]`` -> rotation vector ``[..., 3]`` with ``|w| <= pi``.

    ``q`` and ``-q`` give the same result (except at exactly ``pi``, where both ``+-w`` are
    valid).  Non-unit input is tolerated: only the direction of ``q`` matters.
    """
    return join(log_components(split(jnp.asarray(q)))[0])


@jax.jit
def compose(a: Real[ArrayLike, "*a 4"], b: Real[ArrayLike, "*b 4"]) -> Float[Array, "... 4"]:
    """Hamilton product ``a * b`` (rotation ``b`` first, then ``a``): ``[..., 4]``."""
    return join(compose_components(split(jnp.asarray(a)), split(jnp.asarray(b))))


@jax.jit
def inverse(q: Real[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Conjugate ``(-v, w)``, the inverse of a unit quaternion (of ``q / |q|`` up to the norm)."""
    q = jnp.asarray(q)
    return q * jnp.array([-1, -1, -1, 1], dtype=q.dtype)


@jax.jit
def between(a: Real[ArrayLike, "*a 4"], b: Real[ArrayLike, "*b 4"]) -> Float[Array, "... 4"]:
    """``a^-1 * b``, the rotation from ``b``'s frame into ``a``'s: ``[..., 4]``."""
    return join(compose_components(inverse_components(split(jnp.asarray(a))), split(jnp.asarray(b))))


@jax.jit
def act(q: Real[ArrayLike, "*a 4"], x: Real[ArrayLike, "*b 3"]) -> Float[Array, "... 3"]:
    """Rotate points: ``R(q) x`` for ``q [..., 4]``, ``x [..., 3]`` (broadcast)."""
    return join(act_components(split(jnp.asarray(q)), split(jnp.asarray(x))))


@jax.jit
def adjoint(q: Real[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Adjoint ``[..., 4] -> [..., 3, 3]``: ``q exp(w) q^-1 = exp(Ad(q) w)`` with ``Ad(q) = R(q)``."""
    return as_matrix(q)


@jax.jit
def normalize(q: Real[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """``q / |q|`` (e.g. after many compositions); the sign is kept."""
    c = split(jnp.asarray(q))
    inv = jax.lax.rsqrt(c[0] ** 2 + c[1] ** 2 + c[2] ** 2 + c[3] ** 2)
    return join(tuple(x * inv for x in c))


@jax.jit
def canonical(q: Real[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """``q`` or ``-q``, whichever has ``qw >= 0`` (the same rotation; the form :func:`from_matrix`
    returns and :func:`log` reads)."""
    q = jnp.asarray(q)
    return q * hemisphere_sign(q[..., 3:4])


@jax.jit
def as_matrix(q: Real[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix of ``q / |q|``: ``[..., 4] -> [..., 3, 3]`` (always a rotation, as
    :func:`act` and :func:`log` read any non-zero quaternion; NaN for a zero one)."""
    q = jnp.asarray(q)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    c = 2.0 / (xx + yy + zz + w * w)
    return jnp.stack(
        [
            jnp.stack([1 - c * (yy + zz), c * (xy - wz), c * (xz + wy)], -1),
            jnp.stack([c * (xy + wz), 1 - c * (xx + zz), c * (yz - wx)], -1),
            jnp.stack([c * (xz - wy), c * (yz + wx), 1 - c * (xx + yy)], -1),
        ],
        axis=-2,
    )


@jax.jit
def from_matrix(r: Real[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion of a rotation matrix ``[..., 3, 3] -> [..., 4]`` (Shepperd's method).

    All four candidate formulas are evaluated and the one with the largest pivot is kept, so
    the result is accurate everywhere, including rotations by ``pi``.  The sign is
    normalised to ``qw >= 0``.
    """
    r = jnp.asarray(r)
    m00, m01, m02 = r[..., 0, 0], r[..., 0, 1], r[..., 0, 2]
    m10, m11, m12 = r[..., 1, 0], r[..., 1, 1], r[..., 1, 2]
    m20, m21, m22 = r[..., 2, 0], r[..., 2, 1], r[..., 2, 2]
    # Pivots 4x^2, 4y^2, 4z^2, 4w^2 (each up to the common factor).
    pivots = jnp.stack([1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22, 1 + m00 + m11 + m22], -1)
    cands = jnp.stack(
        [
            jnp.stack([pivots[..., 0], m01 + m10, m02 + m20, m21 - m12], -1),
            jnp.stack([m01 + m10, pivots[..., 1], m12 + m21, m02 - m20], -1),
            jnp.stack([m02 + m20, m12 + m21, pivots[..., 2], m10 - m01], -1),
            jnp.stack([m21 - m12, m02 - m20, m10 - m01, pivots[..., 3]], -1),
        ],
        axis=-2,
    )
    best = jnp.argmax(pivots, axis=-1)
    q = jnp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    p = jnp.take_along_axis(pivots, best[..., None], axis=-1)
    return canonical(q * (0.5 / jnp.sqrt(p)))


def _det3(m: Array) -> Array:
    """Determinant of ``[..., 3, 3]`` by cofactors (elementwise: no LU call per matrix)."""
    return (
        m[..., 0, 0] * (m[..., 1, 1] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 1])
        - m[..., 0, 1] * (m[..., 1, 0] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 0])
        + m[..., 0, 2] * (m[..., 1, 0] * m[..., 2, 1] - m[..., 1, 1] * m[..., 2, 0])
    )


@jax.jit
def project(m: Real[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 4"]:
    """Quaternion of the rotation nearest to ``m`` in the Frobenius norm: ``[..., 3, 3] -> [..., 4]``.

    With ``m = U diag(d) V^T`` (singular values ``d1 >= d2 >= d3 >= 0``), the nearest rotation
    is ``R = U diag(1, 1, det(U V^T)) V^T`` (Umeyama 1991, eq. 39 with unit weights; Horn 1987):
    when ``det m < 0`` the axis of the smallest singular value is flipped, so the result is a
    rotation, never a reflection.  ``R`` is unique when ``d2 + d3 * det(U V^T) > 0``: always for
    ``det m > 0`` and for rank 2, not for a rank ``<= 1`` matrix nor for a reflection with
    ``d2 = d3`` (e.g. an exact reflection ``diag(1, 1, -1)``), where one of the minimisers is
    returned.  The quaternion is read by :func:`from_matrix`
    (``qw >= 0``).  Differentiable where the singular values are distinct.
    """
    m = jnp.asarray(m)
    u, _, vt = jnp.linalg.svd(m)
    d = jnp.where(_det3(u) * _det3(vt) < 0, -1.0, 1.0).astype(m.dtype)
    # R_ij = sum_k U_ik D_k V^T_kj, D = (1, 1, d), elementwise over the batch.
    u = u.at[..., :, 2].multiply(d[..., None])
    r = (
        u[..., :, 0, None] * vt[..., None, 0, :]
        + u[..., :, 1, None] * vt[..., None, 1, :]
        + u[..., :, 2, None] * vt[..., None, 2, :]
    )
    return from_matrix(r)


@jax.jit
def jlog(w: Real[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Inverse right Jacobian ``Jr^-1(w) = d log(exp(w) exp(d)) / d d`` at ``d = 0``:
    ``[..., 3] -> [..., 3, 3]``.

    Closed form (Sola et al. 2018, eq. 144; Sophus ``SO3::leftJacobianInverse(-w)``)::

        Jr^-1(w) = I + K/2 + c K^2,   K = [w]x,   c = 1/theta^2 - cot(theta/2) / (2 theta)

    with ``c -> 1/12 + theta^2/720 + theta^4/30240`` for ``theta -> 0``.  Valid for
    ``|w| < 2 pi`` (``cot(theta/2)`` has its pole at ``2 pi``).
    """
    w = jnp.asarray(w)
    dtype = w.dtype
    theta_sq = jnp.sum(w * w, -1)
    eye = jnp.eye(3, dtype=dtype)
    k = hat(w)
    k2 = w[..., :, None] * w[..., None, :] - theta_sq[..., None, None] * eye  # K^2 = w w^T - theta^2 I
    return _jlog_from(theta_sq, k, k2, eye)


def _jlog_from(theta_sq: Array, k: Array, k2: Array, eye: Array) -> Array:
    """:func:`jlog` from ``theta^2``, ``K`` and ``K^2`` (shared with :func:`swiftjax.sim3.jlog`)."""
    small = theta_sq < (1e-6 if theta_sq.dtype == jnp.float32 else 1e-8)
    tsq = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(tsq)
    c = jnp.where(
        small,
        1.0 / 12.0 + theta_sq / 720.0 + theta_sq * theta_sq / 30240.0,
        1.0 / tsq - 0.5 / (theta * jnp.tan(0.5 * theta)),
    )
    return eye + 0.5 * k + c[..., None, None] * k2

"""The similarity group Sim(3) as pure functions over arrays.

Layout (the same as pypose's ``Sim3``):

* an element is ``[..., 8] = (tx, ty, tz, qx, qy, qz, qw, s)``: translation, unit quaternion
  (scalar last) and positive scale; it acts on points as ``x' = s R x + t``;
* a tangent vector is ``[..., 7] = (rho, omega, sigma)`` with ``s = exp(sigma)`` (the order
  of Sophus and pypose);
* composition is ``(A o B)(x) = A(B(x))``.

Every function accepts leading batch axes and broadcasts them against each other, and is
safe under ``jax.jit``, ``jax.vmap`` and ``jax.grad`` (double-``where`` small-angle
branches: no ``0/0`` ever reaches a gradient).  Nothing here is shape-dependent beyond the
trailing axis, so a jitted caller recompiles only when batch shapes or dtypes change.  The
group maps are ``jax.jit``-ted themselves: called on concrete arrays (a notebook, host code)
each compiles one program per shape and dtype instead of one per primitive
(docs/performance/sim3.md); inside another ``jit`` they are inlined.  :func:`from_rst`, :func:`from_matrix` and :func:`check` are not
jitted: they refuse bad concrete input on the host.

Exponential map (Sophus ``sim3.hpp``, ``calcW``; Eade, "Lie groups for computer vision",
sec. 6).  With ``theta = |omega|``, ``K = [omega]x``::

    exp(rho, omega, sigma) = (W rho, exp_SO3(omega), e^sigma)
    W = C I + A K + B K^2 = integral_0^1 e^(sigma u) exp(u K) du
    C = (e^sigma - 1) / sigma
    A = (e^sigma sin(theta) sigma + (1 - e^sigma cos(theta)) theta) / (theta (sigma^2 + theta^2))
    B = (C - ((e^sigma cos(theta) - 1) sigma + e^sigma sin(theta) theta) / (sigma^2 + theta^2)) / theta^2

Named special cases, each with its own branch and test:

* ``sigma -> 0``: ``C -> 1 + sigma/2 + sigma^2/6`` (and ``A, B`` -> the SE(3) ``V`` coefficients);
* ``theta -> 0``: ``A -> A0 = (e^sigma - C) / sigma``, ``B -> B0 = (e^sigma - 2 A0) / (2 sigma)``
  (``F'(sigma)`` and ``F''(sigma) / 2`` for ``F(w) = (e^w - 1) / w``, from ``w F' = e^w - F``:
  relative rounding ``eps / sigma`` and ``eps / sigma^2``, where the expanded
  ``((sigma - 1) e^sigma + 1) / sigma^2`` loses ``eps / sigma^2``);
* both -> 0: ``A -> 1/2 + sigma/3 + ..., B -> 1/6 + sigma/8 + ...`` (Taylor series);
* ``theta`` near ``pi``: handled by the quaternion log (:func:`swiftjax.so3.log`).

``1 - e^sigma cos(theta)`` is evaluated as ``2 sin^2(theta/2) - expm1(sigma) cos(theta)``, which
keeps ``A`` accurate in float32 where ``cos(theta)`` rounds to 1.

Validity (the element set): finite, ``s > 0`` and ``q != 0``.  A non-unit ``q`` stands for
``q / |q|`` in every function (see :mod:`swiftjax.so3`), so :func:`act`, :func:`compose`,
:func:`as_matrix` and :func:`log` agree on it.  An invalid element is never silently turned
into a plausible number: :func:`log` returns an all-NaN tangent for ``s <= 0``, ``q = 0`` or
a non-finite value,
the others propagate NaN for ``q = 0``; :func:`is_valid` is the flag for jitted code and
:func:`check` the host-side refusal.  :func:`from_rst` and :func:`from_matrix` refuse, when
called on concrete (host) values, a matrix that is not a rotation (``3 I``, a reflection) or a
scale ``<= 0``; under ``jit`` they cannot raise, and callers check the result with
:func:`is_valid` or their own flags.

Logarithm: ``omega = log_SO3(q)``, ``sigma = log s`` and ``rho = W^-1 t`` with the closed form
``W^-1 = x I + y K + z K^2`` (``K^3 = -theta^2 K``)::

    x = 1/C,  D = C - theta^2 B,  det = D^2 + theta^2 A^2,
    y = -A / det,  z = (A^2 - B D) / (C det)

which has no division by ``theta`` at all.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import DTypeLike
from jaxtyping import ArrayLike, Bool, Float, Real

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
    "jlog",
    "right_jacobian_inverse",
    "is_valid",
    "check",
    "ROTATION_TOLERANCE",
]

#: Largest ``max |R^T R - I|`` :func:`from_rst` accepts as a rotation on the host.
ROTATION_TOLERANCE = 1e-4


# ----------------------------------------------------------------------------- accessors


def translation(S: Real[ArrayLike, "*batch 8"]) -> Float[Array, "*batch 3"]:
    """``t`` of ``S``: ``[..., 8] -> [..., 3]``."""
    return jnp.asarray(S)[..., 0:3]


def quaternion(S: Real[ArrayLike, "*batch 8"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion ``(qx, qy, qz, qw)`` of ``S``: ``[..., 8] -> [..., 4]``."""
    return jnp.asarray(S)[..., 3:7]


def scale(S: Real[ArrayLike, "*batch 8"]) -> Float[Array, "*batch"]:
    """Scale ``s`` of ``S``: ``[..., 8] -> [...]``."""
    return jnp.asarray(S)[..., 7]


# Component form (see swiftjax.so3): an element is (t: Vec3, q: Quat, s).
_Elem = tuple[so3.Vec3, so3.Quat, Array]


def _split(S: ArrayLike) -> _Elem:
    c = so3.split(jnp.asarray(S))
    return c[0:3], c[3:7], c[7]


def _join(t: so3.Vec3, q: so3.Quat, s: Array) -> Array:
    return so3.join((*t, *q, s))


def _compose_c(a: _Elem, b: _Elem) -> _Elem:
    (ta, qa, sa), (tb, qb, sb) = a, b
    rt = so3.act_components(qa, tb)
    return (
        (sa * rt[0] + ta[0], sa * rt[1] + ta[1], sa * rt[2] + ta[2]),
        so3.compose_components(qa, qb),
        sa * sb,
    )


def _inverse_c(a: _Elem) -> _Elem:
    t, q, s = a
    q_inv = so3.inverse_components(q)
    s_inv = 1.0 / s
    rt = so3.act_components(q_inv, t)
    return (-s_inv * rt[0], -s_inv * rt[1], -s_inv * rt[2]), q_inv, s_inv


def _act_c(a: _Elem, x: so3.Vec3) -> so3.Vec3:
    t, q, s = a
    rx = so3.act_components(q, x)
    return s * rx[0] + t[0], s * rx[1] + t[1], s * rx[2] + t[2]


def _pack(t: Array, q: Array, s: Array) -> Array:
    """Concatenate ``t [..., 3]``, ``q [..., 4]`` and ``s [...]`` (broadcast) into ``[..., 8]``."""
    return so3.join((*so3.split(t), *so3.split(q), s))


# ----------------------------------------------------------------------- group operations


def identity(batch_shape: tuple[int, ...] = (), dtype: DTypeLike = jnp.float32) -> Float[Array, "... 8"]:
    """The identity element ``(0, 0, 0, 0, 0, 0, 1, 1)``, shape ``[*batch_shape, 8]``."""
    e = jnp.array([0, 0, 0, 0, 0, 0, 1, 1], dtype=dtype)
    return jnp.broadcast_to(e, (*batch_shape, 8))


@jax.jit
def compose(A: Real[ArrayLike, "*a 8"], B: Real[ArrayLike, "*b 8"]) -> Float[Array, "... 8"]:
    """``A o B``: ``(s_A R_A t_B + t_A, q_A q_B, s_A s_B)``; ``[..., 8] x [..., 8] -> [..., 8]``."""
    return _join(*_compose_c(_split(A), _split(B)))


@jax.jit
def inverse(S: Real[ArrayLike, "*batch 8"]) -> Float[Array, "*batch 8"]:
    """``S^-1 = (-(1/s) R^T t, q*, 1/s)``: ``[..., 8] -> [..., 8]``."""
    return _join(*_inverse_c(_split(S)))


@jax.jit
def between(A: Real[ArrayLike, "*a 8"], B: Real[ArrayLike, "*b 8"]) -> Float[Array, "... 8"]:
    """``A^-1 o B``, the relative transform that maps B's frame into A's."""
    return _join(*_compose_c(_inverse_c(_split(A)), _split(B)))


@jax.jit
def act(S: Real[ArrayLike, "*a 8"], points: Real[ArrayLike, "*b 3"]) -> Float[Array, "... 3"]:
    """Apply ``S`` to points: ``s R x + t``.

    Args:
        S: ``[..., 8]``.
        points: ``[..., 3]``; ``S``'s batch axes broadcast against the points' leading axes
            (pass ``S[..., None, :]`` to map one transform over a trailing point axis).
    """
    return so3.join(_act_c(_split(S), so3.split(jnp.asarray(points))))


@jax.jit
def normalize(S: Real[ArrayLike, "*batch 8"]) -> Float[Array, "*batch 8"]:
    """Re-unit the quaternion of ``S`` (e.g. after many compositions)."""
    t, q, s = _split(S)
    inv = jax.lax.rsqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
    return _join(t, (q[0] * inv, q[1] * inv, q[2] * inv, q[3] * inv), s)


# ---------------------------------------------------------------------- exp / log


def _sigma_eps(dtype: jnp.dtype) -> float:
    """|sigma| below which the cancellation-prone theta -> 0 limits use their Taylor series."""
    return 1e-1 if jnp.finfo(dtype).bits <= 32 else 1e-3


class _W(NamedTuple):
    """``W = c I + a K + b K^2`` and the ``theta -> 0`` limits of ``a`` and ``b``.

    With ``F(w) = (e^w - 1) / w = integral_0^1 e^(w u) du`` on ``w = sigma + i theta``:
    ``c = F(sigma)`` and ``F(sigma + i theta) = (c - theta^2 b) + i theta a`` (on the plane
    perpendicular to ``omega``, ``K`` acts as ``i theta``), so ``a0 = F'(sigma)`` and
    ``b0 = F''(sigma) / 2``.
    """

    a: Array
    b: Array
    c: Array
    a0: Array
    b0: Array


def _w_from_parts(half: so3.HalfAngle, sigma: Array, exp_sigma: Array, expm1_sigma: Array) -> _W:
    """The coefficients of ``W`` (:class:`_W`) from precomputed trigonometry (module docstring).

    Only products and quotients here: the transcendentals (half-angle sine/cosine, ``e^sigma``,
    ``expm1(sigma)``) are computed once by the caller and shared with the rotation part.
    """
    theta_sq = half.theta_sq
    sigma_zero = jnp.abs(sigma) < 1e-10
    sigma_safe = jnp.where(sigma_zero, jnp.ones_like(sigma), sigma)
    c_coef = jnp.where(sigma_zero, 1.0 + sigma / 2.0 + sigma**2 / 6.0, expm1_sigma / sigma_safe)

    # theta -> 0: A0(sigma), B0(sigma) plus the sigma = 0 part of the theta^2 correction.
    sigma_small = jnp.abs(sigma) < _sigma_eps(sigma.dtype)
    ss = jnp.where(sigma_small, jnp.ones_like(sigma), sigma)
    a0_gen = (exp_sigma - c_coef) / ss
    a0 = jnp.where(sigma_small, 0.5 + sigma / 3.0 + sigma**2 / 8.0 + sigma**3 / 30.0 + sigma**4 / 144.0, a0_gen)
    b0 = jnp.where(
        sigma_small,
        1.0 / 6.0 + sigma / 8.0 + sigma**2 / 20.0 + sigma**3 / 72.0 + sigma**4 / 336.0,
        (exp_sigma - 2.0 * a0_gen) / (2.0 * ss),
    )

    # General branch, with sin(theta) = 2 sh ch, cos(theta) = 1 - 2 sh^2.
    theta = half.theta
    tsq = jnp.where(half.small, jnp.ones_like(theta_sq), theta_sq)
    sh_sq = half.sin_half**2
    sin_t = 2.0 * half.sin_half * half.cos_half
    em_re = expm1_sigma * (1.0 - 2.0 * sh_sq) - 2.0 * sh_sq  # Re(e^z - 1), z = sigma + i theta
    em_im = exp_sigma * sin_t  # Im(e^z - 1)
    c = sigma**2 + tsq
    a_gen = (em_im * sigma - em_re * theta) / (theta * c)
    b_gen = (c_coef - (em_re * sigma + em_im * theta) / c) / tsq

    return _W(
        jnp.where(half.small, a0 - theta_sq / 24.0, a_gen),
        jnp.where(half.small, b0 - theta_sq / 120.0, b_gen),
        c_coef,
        a0,
        b0,
    )


def _winv(w: _W, theta_sq: Array) -> tuple[Array, Array, Array, Array]:
    """``(x, y, z, u)``: ``W^-1 = x I + y K + z K^2`` (module docstring) and ``u = Re G(w)``.

    ``G = 1 / F`` (the Bernoulli generating function ``w / (e^w - 1)``) gives ``x = G(sigma)``
    and ``G(sigma + i theta) = u + i theta y = (D - i theta A) / det`` with ``D = C - theta^2 B``,
    ``det = |F(sigma + i theta)|^2 = D^2 + theta^2 A^2``; ``z = (x - u) / theta^2``, written
    without the division.
    """
    d = w.c - theta_sq * w.b
    det = d * d + theta_sq * w.a * w.a
    return 1.0 / w.c, -w.a / det, (w.a * w.a - w.b * d) / (w.c * det), d / det


def _apply_poly(x: Array, y: Array, z: Array, omega: so3.Vec3, v: so3.Vec3) -> so3.Vec3:
    """``(x I + y K + z K^2) v`` with ``K = [omega]x``, via two cross products."""
    wv = so3.cross(omega, v)
    wwv = so3.cross(omega, wv)
    return tuple(x * v[k] + y * wv[k] + z * wwv[k] for k in range(3))


#: Elements per block of the ``"blocked"`` layout of :func:`_map_components`.
_BLOCK = 1024
#: Elements per step of the ``"map"`` layout of :func:`_map_components`.
_MAP_BLOCK = 8192


def _map_components(
    fn: Callable[[tuple[Array, ...]], tuple[Array, ...]],
    x: Array,
    k_out: int,
    layout: str = "flat",
    valid: Callable[[tuple[Array, ...]], Array] | None = None,
) -> Array:
    """``fn`` (component tuple -> component tuple) applied to ``x [..., k]``: ``[..., k_out]``.

    With ``valid`` (component tuple -> bool), elements where it is false come out all-NaN; the
    test runs on the same components as ``fn``, inside the same loop (a separate pass over the
    interleaved ``[..., k]`` input was slower: docs/performance/sim3.md).

    Only the arrangement of the work differs between layouts, never the formulas:

    * ``"flat"`` (and any batch below two blocks): ``[...]``-shaped components
      (:func:`swiftjax.so3.split`), joined at the end;
    * ``"blocked"``: the batch is flattened, padded to a multiple of ``_BLOCK`` (with copies of
      its first element) and the components are ``[N / _BLOCK, _BLOCK]`` blocks, so the layout
      change in and out of the interleaved ``[..., k]`` arrays stays within one block;
    * ``"map"``: the padded batch is processed ``_MAP_BLOCK`` elements at a time by
      ``lax.map``, each slice transposed to ``[k, _MAP_BLOCK]`` components and back.

    docs/performance/sim3.md has the measurements behind the choice per function.
    """

    def apply(c: tuple[Array, ...], axis: int) -> Array:
        out = jnp.stack(jnp.broadcast_arrays(*fn(c)), axis=axis)
        return out if valid is None else jnp.where(jnp.expand_dims(valid(c), axis), out, jnp.nan)

    batch, k = x.shape[:-1], x.shape[-1]
    n = math.prod(batch)
    block = _BLOCK if layout == "blocked" else _MAP_BLOCK
    if layout == "flat" or n < 2 * block:
        return jnp.moveaxis(apply(so3.split(x), 0), 0, -1)
    pad = -n % block
    flat = x.reshape(n, k)
    if pad:
        flat = jnp.concatenate([flat, jnp.broadcast_to(flat[:1], (pad, k))])
    blocks = flat.reshape(-1, block, k)
    if layout == "blocked":
        out = apply(tuple(jnp.moveaxis(blocks, -1, 0)), -1)
    else:
        out = jax.lax.map(lambda b: apply(tuple(b.T), -1), blocks)
    return out.reshape(-1, k_out)[:n].reshape(*batch, k_out)


def _exp_c(c: tuple[Array, ...]) -> tuple[Array, ...]:
    rho, omega, sigma = c[0:3], c[3:6], c[6]
    q, half = so3.exp_components(omega)  # the half-angle trigonometry is shared with W
    exp_sigma = jnp.exp(sigma)
    w = _w_from_parts(half, sigma, exp_sigma, jnp.expm1(sigma))
    return (*_apply_poly(w.c, w.a, w.b, omega, rho), *q, exp_sigma)


def _log_c(c: tuple[Array, ...]) -> tuple[Array, ...]:
    t, q, s = c[0:3], c[3:7], c[7]
    omega, half = so3.log_components(q)  # W reuses the quaternion's half angle: no sin/cos
    sigma = jnp.log(s)
    theta_sq = half.theta_sq
    # expm1 from sigma itself, not s - 1: under jit XLA may fold log(exp(sigma)) back to sigma,
    # and s - 1 = 0 with sigma = 1e-9 would make C = 0 (a NaN translation).
    x, y, z = _winv(_w_from_parts(half, sigma, s, jnp.expm1(sigma)), theta_sq)[:3]
    return (*_apply_poly(x, y, z, omega, t), *omega, sigma)


@jax.jit
def exp(xi: Real[ArrayLike, "*batch 7"]) -> Float[Array, "*batch 8"]:
    """Exponential map ``[..., 7] (rho, omega, sigma) -> [..., 8]``: ``(W rho, exp(omega), e^sigma)``."""
    return _map_components(_exp_c, jnp.asarray(xi), 8, "blocked")


@jax.jit
def log(S: Real[ArrayLike, "*batch 8"]) -> Float[Array, "*batch 7"]:
    """Logarithm ``[..., 8] -> [..., 7]`` with ``|omega| <= pi``; ``log(exp(xi)) = xi`` for ``|omega| < pi``.

    ``S`` and ``S`` with its quaternion negated give the same tangent; a non-unit quaternion
    gives its unit version's.  Invalid elements (``s <= 0``, ``q = 0``, non-finite) give all-NaN
    tangents.
    """
    # s <= 0, q = 0 or a non-finite value is no similarity: all seven components NaN.
    return _map_components(_log_c, jnp.asarray(S), 7, "map", valid=_is_valid_c)


# ---------------------------------------------------------------- matrices and adjoint


@jax.jit
def as_matrix(S: Real[ArrayLike, "*batch 8"]) -> Float[Array, "*batch 4 4"]:
    """Homogeneous matrix ``[[s R, t], [0, 1]]``: ``[..., 8] -> [..., 4, 4]``."""
    S = jnp.asarray(S)
    sr = scale(S)[..., None, None] * so3.as_matrix(quaternion(S))
    top = jnp.concatenate([sr, translation(S)[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0, 0, 0, 1], dtype=S.dtype), (*S.shape[:-1], 1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def _is_concrete(*xs: ArrayLike) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _check_rotation_scale(R: ArrayLike, s: ArrayLike, what: str) -> None:
    """Host-side refusal of non-rotations and scales ``<= 0`` (see the module docstring)."""
    import numpy as np

    Rn = np.asarray(R, np.float64)
    sn = np.asarray(s, np.float64)
    if Rn.shape[-2:] != (3, 3):
        raise ValueError(f"{what}: R must be [..., 3, 3], got shape {Rn.shape}")
    dev = np.abs(np.swapaxes(Rn, -1, -2) @ Rn - np.eye(3)).max(axis=(-2, -1), initial=0.0)
    det = np.linalg.det(Rn) if Rn.size else np.ones(Rn.shape[:-2])
    bad = ~(dev <= ROTATION_TOLERANCE) | ~(det > 0)
    if np.any(bad):
        k = np.unravel_index(int(np.flatnonzero(bad)[0]), bad.shape) if bad.ndim else ()
        raise ValueError(
            f"{what}: R{list(k) if k else ''} is not a rotation (max |R^T R - I| = {np.asarray(dev)[k]:.3g}, "
            f"det {np.asarray(det)[k]:.6g}; {int(np.sum(bad))} of {bad.size}): a scaled matrix or a reflection"
        )
    if np.any(~(sn > 0)):
        raise ValueError(f"{what}: scale must be > 0 and finite, got {sn.reshape(-1)[np.flatnonzero(~(sn > 0))[0]]!r}")


def from_rst(
    R: Real[ArrayLike, "*r 3 3"], t: Real[ArrayLike, "*t 3"], s: Real[ArrayLike, "*s"]
) -> Float[Array, "... 8"]:
    """Element from rotation ``[..., 3, 3]``, translation ``[..., 3]`` and scale ``[...]``.

    On concrete (host) values, ``R`` must be a rotation (``max |R^T R - I| <= 1e-4``,
    ``det R > 0``) and ``s > 0``, else ``ValueError``; under ``jit`` nothing is checked.
    """
    if _is_concrete(R, s):
        _check_rotation_scale(R, s, "sim3.from_rst")
    R, t, s = jnp.asarray(R), jnp.asarray(t), jnp.asarray(s)
    return _pack(t, so3.from_matrix(R), s)


@jax.jit
def is_valid(S: Real[ArrayLike, "*batch 8"]) -> Bool[Array, "*batch"]:
    """``[..., 8] -> [...]`` bool: finite, ``s > 0`` and ``q != 0`` (jit-able flag)."""
    return _is_valid_c(so3.split(jnp.asarray(S)))


def _is_valid_c(c: tuple[Array, ...]) -> Array:
    """:func:`is_valid` on the eight components.  Finiteness as ``max_k |c_k| < inf`` (``max``
    propagates NaN): one compare per element instead of eight ``isfinite`` tests."""
    largest = jnp.abs(c[0])
    for x in c[1:]:
        largest = jnp.maximum(largest, jnp.abs(x))
    return (largest < jnp.inf) & (c[7] > 0) & (so3.dot(c[3:6], c[3:6]) + c[6] * c[6] > 0)


def check(S: ArrayLike, name: str = "S", unit_tol: float | None = None) -> None:
    """Host-side: ``ValueError`` naming ``name`` and the first bad element unless every element
    of ``S [..., 8]`` is valid (:func:`is_valid`) and, with ``unit_tol``, ``| |q| - 1 | <= unit_tol``."""
    import numpy as np

    a = np.asarray(S, np.float64)
    if a.shape[-1:] != (8,):
        raise ValueError(f"{name}: a Sim(3) array must be [..., 8], got shape {a.shape}")
    norm = np.linalg.norm(a[..., 3:7], axis=-1)
    bad = ~np.all(np.isfinite(a), axis=-1) | ~(a[..., 7] > 0) | ~(norm > 0)
    if unit_tol is not None:
        bad |= ~(np.abs(norm - 1.0) <= unit_tol)
    if np.any(bad):
        k = int(np.flatnonzero(bad.reshape(-1))[0])
        raise ValueError(
            f"{name}: element {k} (of {bad.size}) is not a valid Sim(3) element {a.reshape(-1, 8)[k].tolist()} "
            f"(needs finite values, scale > 0, a non-zero{' unit' if unit_tol is not None else ''} quaternion; "
            f"{int(bad.sum())} bad)"
        )


@jax.jit
def to_rst(
    S: Real[ArrayLike, "*batch 8"],
) -> tuple[Float[Array, "*batch 3 3"], Float[Array, "*batch 3"], Float[Array, "*batch"]]:
    """``(R [..., 3, 3], t [..., 3], s [...])`` of ``S``."""
    S = jnp.asarray(S)
    return so3.as_matrix(quaternion(S)), translation(S), scale(S)


def from_matrix(M: Real[ArrayLike, "*batch _ 4"]) -> Float[Array, "*batch 8"]:
    """Element from a ``[..., 4, 4]`` (or ``[..., 3, 4]``) similarity matrix ``[[s R, t], ...]``.

    ``s = det(sR)^(1/3)``; the rotation is read from ``sR / s``.  ``M`` must be a similarity
    with positive determinant: on concrete values anything else is a ``ValueError``
    (:func:`from_rst`); under ``jit`` the result is then meaningless.
    """
    if _is_concrete(M):
        import numpy as np

        det = np.linalg.det(np.asarray(M, np.float64)[..., :3, :3])
        if np.any(~(det > 0)):
            raise ValueError(
                f"sim3.from_matrix: the 3x3 block has determinant {det.reshape(-1)[np.flatnonzero(~(det > 0))[0]]:.6g}; "
                "a similarity needs a positive determinant (a reflection or a singular matrix is none)"
            )
    M = jnp.asarray(M)
    sr = M[..., :3, :3]
    s = jnp.cbrt(jnp.linalg.det(sr))
    return from_rst(sr / s[..., None, None], M[..., :3, 3], s)


@jax.jit
def adjoint(S: Real[ArrayLike, "*batch 8"]) -> Float[Array, "*batch 7 7"]:
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
    # [t]x R column by column (t x R e_k): elementwise, where a batched 3x3 dot would be one
    # library call per element on XLA:CPU.
    tx_r = jnp.swapaxes(jnp.cross(t[..., None, :], jnp.swapaxes(R, -1, -2)), -1, -2)
    row0 = jnp.concatenate([s[..., None, None] * R, tx_r, -t[..., :, None]], axis=-1)
    row1 = jnp.concatenate([zeros33, R, zeros31], axis=-1)
    row2 = jnp.broadcast_to(jnp.array([0, 0, 0, 0, 0, 0, 1], S.dtype), (*batch, 1, 7))
    return jnp.concatenate([row0, row1, row2], axis=-2)


#: ``|w|^2 = sigma^2 + theta^2`` below which :func:`_winv_partials` takes :func:`_winv_series`
#: (float32, float64): where the series' first omitted terms (``~2e-7 |w|^8``) reach the closed
#: forms' cancellation (``eps / |w|``).
_W_SERIES_F32 = 0.5
_W_SERIES_F64 = 1e-2


def _winv_series(sigma: Array, theta_sq: Array) -> tuple[tuple[Array, Array], tuple[Array, ...]]:
    """``((y, z), (y_q, z_q, x_s, y_s, z_s))`` as :func:`_winv_partials` returns them, from the
    Bernoulli series ``G(w) = sum_n B_n w^n / n!`` to ``B_10`` (``y`` to total degree 7 in
    ``|w|``, ``z`` to 6, ``theta^2`` counting two; the partials are these polynomials' own)."""
    s2, q = sigma * sigma, theta_sq
    y = -0.5 + sigma * (
        1 / 6
        + s2 * (-1 / 180 + s2 * (1 / 5040 - s2 / 151200))
        + q * (1 / 180 + s2 * (-1 / 1512 + s2 / 21600) + q * (1 / 5040 - s2 / 21600 + q / 151200))
    )
    z = (
        1 / 12
        + s2 * (-1 / 120 + s2 * (1 / 2016 - s2 / 43200))
        + q * (1 / 720 + s2 * (-1 / 2016 + s2 / 17280) + q * (1 / 30240 - s2 / 43200 + q / 1209600))
    )
    x_s = -0.5 + sigma * (1 / 6 + s2 * (-1 / 180 + s2 * (1 / 5040 - s2 / 151200)))  # G'(sigma)
    y_s = (
        1 / 6
        + s2 * (-1 / 60 + s2 * (1 / 1008 - s2 / 21600))
        + q * (1 / 180 + s2 * (-1 / 504 + s2 / 4320) + q * (1 / 5040 - s2 / 7200 + q / 151200))
    )
    z_s = sigma * (-1 / 60 + s2 * (1 / 504 - s2 / 7200) + q * (-1 / 1008 + s2 / 4320 - q / 21600))
    y_q = sigma * (1 / 180 + s2 * (-1 / 1512 + s2 / 21600) + q * (1 / 2520 - s2 / 10800 + q / 50400))
    z_q = 1 / 720 + s2 * (-1 / 2016 + s2 / 17280) + q * (1 / 15120 - s2 / 21600 + q / 403200)
    return (y, z), (y_q, z_q, x_s, y_s, z_s)


def _winv_partials(half: so3.HalfAngle, sigma: Array, s: Array) -> tuple[tuple[Array, ...], tuple[Array, ...]]:
    """``(x, y, z)`` of ``W^-1`` and their partial derivatives in ``theta^2`` and ``sigma``, closed form.

    ``half`` is the rotation's half-angle trigonometry (read off the quaternion: no sine or
    cosine is evaluated), ``s = e^sigma``.  Returns ``((x, y, z), (y_q, z_q, x_s, y_s, z_s))``;
    ``x = G(sigma)`` does not depend on ``theta``, so ``x_q = 0``.

    ``G(w) = w / (e^w - 1)`` is holomorphic, so on ``w = sigma + i theta``,
    ``d/d sigma G(w) = G'(w)`` and ``d/d theta G(w) = i G'(w)``.  From ``y = Im G(w) / theta`` and
    ``z = (G(sigma) - Re G(w)) / theta^2`` (:func:`_winv`)::

        x_s = G'(sigma) = -F'(sigma) / F(sigma)^2 = -a0 x^2
        y_s = Im G'(w) / theta             z_s = (x_s - Re G'(w)) / theta^2
        y_q = (Re G'(w) - y) / (2 theta^2)  z_q = (Im G'(w) / theta - 2 z) / (2 theta^2)

    with ``G'(w) = -F'(w) G(w)^2`` and ``F'(w) = (e^w - F(w)) / w``.  Imaginary parts are carried
    divided by ``theta`` (``e^sigma sin(theta) / theta`` is never ``0 / 0``).

    Named special cases, each with its own branch and test:

    * ``|w|^2 = sigma^2 + theta^2`` small (``_W_SERIES_F32``, ``_W_SERIES_F64``): the Bernoulli
      series :func:`_winv_series`, for ``y`` and ``z`` as well; the closed forms lose
      ``eps / |w|`` there, which :func:`log` tolerates (its ``y``, ``z`` multiply ``K``) but
      ``M`` does not (``y`` multiplies ``[t]x``).  A converged pose graph's residuals live here;
    * ``theta^2`` below the small-angle threshold of ``A`` and ``B`` (:func:`_w_from_parts`)
      with ``|sigma|`` outside the series: the Taylor series in ``theta^2`` gives
      ``y_s = G''(sigma) = 2 x^2 (x a0^2 - b0)``, exact in ``sigma``; ``z_s = G'''(sigma) / 2``,
      ``y_q = -G'''(sigma) / 6`` and ``z_q = -G''''(sigma) / 24`` enter the Jacobian multiplied
      by ``theta^2`` or ``theta^3`` (below rounding there), so they take the Bernoulli series'
      first terms at ``sigma = 0``: ``-sigma / 60``, ``sigma / 180`` and ``1 / 720``.

    The limit: with ``theta`` small but above that threshold and ``|sigma|`` outside the series,
    ``z_q`` cancels as ``eps / theta^4`` and enters times ``theta^3``: an error of ``eps / theta``
    relative to the Jacobian (3e-11 at ``theta = 1e-5`` in float64, 9e-5 at ``theta = 1e-3`` in
    float32; tests/test_sim3.py measures it against a 40-digit reference).
    """
    theta_sq, small = half.theta_sq, half.small
    w = _w_from_parts(half, sigma, s, jnp.expm1(sigma))
    x, y, z, u = _winv(w, theta_sq)
    x_s = -w.a0 * x * x

    tsq = jnp.where(small, jnp.ones_like(theta_sq), theta_sq)
    e_re = s * (1.0 - 2.0 * half.sin_half * half.sin_half) - (w.c - theta_sq * w.b)  # Re(e^w - F(w))
    e_im = 2.0 * s * half.sin_half * half.cos_half / half.theta - w.a  # Im(e^w - F(w)) / theta
    w_sq = sigma * sigma + tsq
    f_re = (sigma * e_re + tsq * e_im) / w_sq  # Re F'(w)
    f_im = (sigma * e_im - e_re) / w_sq  # Im F'(w) / theta
    g2_re = u * u - tsq * y * y  # G(w)^2 = g2_re + i theta g2_im
    g2_im = 2.0 * u * y
    g_re = -(f_re * g2_re - tsq * f_im * g2_im)  # Re G'(w)
    g_im = -(f_re * g2_im + f_im * g2_re)  # Im G'(w) / theta

    y_s = jnp.where(small, 2.0 * x * x * (x * w.a0 * w.a0 - w.b0), g_im)
    z_s = jnp.where(small, -sigma / 60.0, (x_s - g_re) / tsq)
    y_q = jnp.where(small, sigma / 180.0, (g_re - y) / (2.0 * tsq))
    z_q = jnp.where(small, jnp.full_like(sigma, 1.0 / 720.0), (g_im - 2.0 * z) / (2.0 * tsq))

    # |w| -> 0: the Bernoulli series (y and z also: their closed forms cancel as eps / |w|,
    # which log tolerates, its y and z multiply K, but M does not).
    near = sigma * sigma + theta_sq < (_W_SERIES_F32 if jnp.finfo(sigma.dtype).bits <= 32 else _W_SERIES_F64)
    (y_n, z_n), partials_n = _winv_series(sigma, theta_sq)
    y, z = jnp.where(near, y_n, y), jnp.where(near, z_n, z)
    partials = (y_q, z_q, x_s, y_s, z_s)
    return (x, y, z), tuple(jnp.where(near, a, b) for a, b in zip(partials_n, partials))


def _mat3(a: Array, b: Array) -> Array:
    """``a @ b`` for ``[..., 3, 3]`` as elementwise multiply-adds (XLA:CPU runs a batched dot
    as one library call per matrix)."""
    return (
        a[..., :, 0, None] * b[..., None, 0, :]
        + a[..., :, 1, None] * b[..., None, 1, :]
        + a[..., :, 2, None] * b[..., None, 2, :]
    )


@jax.jit
def jlog(xi: Real[ArrayLike, "*batch 7"], S: Real[ArrayLike, "*batch 8"] | None = None) -> Float[Array, "*batch 7 7"]:
    """Inverse right Jacobian ``Jr^-1(xi) = d log(exp(xi) exp(d)) / d d`` at ``d = 0``, closed form:
    ``[..., 7] -> [..., 7, 7]``.

    ``S`` is ``exp(xi)`` when the caller already has it (a residual ``xi = log(E)`` passes
    ``S = E``); otherwise it is computed.  With ``xi = (rho, omega, sigma)``,
    ``rho = W^-1(omega, sigma) t`` and ``S exp(d) = (t + s R rho_d + O(d^2), R exp(omega_d), s e^sigma_d)``::

        Jr^-1 = [[ s W^-1 R,  M Jr_SO3^-1(omega),  m ],
                 [ 0,         Jr_SO3^-1(omega),    0 ],
                 [ 0,         0,                   1 ]]

        M = d(W^-1 t)/d omega = y [-t]x + z ((omega.t) I + omega t^T - 2 t omega^T)
            + 2 (y_q (omega x t) + z_q omega x (omega x t)) omega^T
        m = d(W^-1 t)/d sigma = x_s t + y_s (omega x t) + z_s omega x (omega x t)

    where ``(x, y, z)(theta^2, sigma)`` are the ``W^-1`` coefficients of :func:`log` and
    ``_q``/``_s`` their partial derivatives in ``theta^2`` and ``sigma`` in closed form
    (:func:`_winv_partials`; ``x`` does not depend on ``theta``), and ``Jr_SO3^-1`` is
    :func:`swiftjax.so3.jlog`.  The half-angle sine and cosine are read off ``S``'s quaternion,
    so no trigonometric function is evaluated when ``S`` is given.  Valid for ``|omega| < pi``.
    :func:`right_jacobian_inverse` is the autodiff reference it is tested against.
    """
    r = jnp.asarray(xi)
    E = exp(r) if S is None else jnp.asarray(S)
    dtype = E.dtype
    t, s = E[..., 0:3], E[..., 7]
    w, sigma = r[..., 3:6], r[..., 6]
    theta_sq = jnp.sum(w * w, -1)
    half = so3.half_angle(so3.split(E[..., 3:7]), theta_sq)

    (x, y, z), (yq, zq, xs, ys, zs) = _winv_partials(half, sigma, s)
    x, y, z = (v[..., None, None] for v in (x, y, z))
    yq, zq, xs, ys, zs = (v[..., None] for v in (yq, zq, xs, ys, zs))

    eye = jnp.eye(3, dtype=dtype)
    outer = lambda a, b: a[..., :, None] * b[..., None, :]
    k = so3.hat(w)
    k2 = outer(w, w) - theta_sq[..., None, None] * eye  # K^2 = w w^T - theta^2 I
    winv = x * eye + y * k + z * k2
    wt = jnp.cross(w, t)
    wwt = jnp.cross(w, wt)
    wdt = jnp.sum(w * t, -1)[..., None, None]
    g_q = yq * wt + zq * wwt
    big_m = -y * so3.hat(t) + z * (wdt * eye + outer(w, t) - 2.0 * outer(t, w)) + 2.0 * outer(g_q, w)
    m = xs * t + ys * wt + zs * wwt
    jso3 = so3._jlog_from(theta_sq, k, k2, eye)  # one formula for both groups

    top = jnp.concatenate(
        [s[..., None, None] * _mat3(winv, so3.as_matrix(E[..., 3:7])), _mat3(big_m, jso3), m[..., None]], -1
    )
    middle = jnp.concatenate([jnp.zeros_like(jso3), jso3, jnp.zeros(s.shape + (3, 1), dtype)], -1)
    bottom = jnp.broadcast_to(jnp.eye(7, dtype=dtype)[6], s.shape + (1, 7))
    return jnp.concatenate([top, middle, bottom], -2)


@jax.jit
def right_jacobian_inverse(xi: Real[ArrayLike, "*batch 7"]) -> Float[Array, "*batch 7 7"]:
    """``Jr^-1(xi) = d log(exp(xi) exp(d)) / d d`` at ``d = 0``: ``[..., 7] -> [..., 7, 7]``.

    The autodiff reference for :func:`jlog` (prefer :func:`jlog`, which is closed form).
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

"""Vectorisable sine/cosine and arctangent for the Lie-group hot paths.

XLA's CPU backend lowers ``sin``, ``cos`` and ``atan2`` to scalar libm calls, while
``+ * / floor select`` vectorise (measurements in docs/performance/sim3.md).  These are the Cephes algorithms (Moshier, "Methods and Programs for Mathematical
Functions", 1989: ``sinf/cosf``, ``sin/cos``, ``atanf``, ``atan``) written with ``jnp``
arithmetic only, so XLA fuses and vectorises them.  Accuracy: a few ulp in float32 and in
float64 for ``|x| < 2^16`` (tests/test_elementary.py compares with NumPy).  They are smooth
almost everywhere, so ``jax.grad`` gives the polynomial's derivative (accurate to rounding).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jax import Array
from jaxtyping import Float

__all__ = ["sincos", "arctan2_nonneg"]

_SIN_F32 = (-1.9515295891e-4, 8.3321608736e-3, -1.6666654611e-1)
_COS_F32 = (2.443315711809948e-5, -1.388731625493765e-3, 4.166664568298827e-2)
_DP_F32 = (0.78515625, 2.4187564849853515625e-4, 3.77489497744594108e-8)

_SIN_F64 = (
    1.58962301576546568060e-10,
    -2.50507477628578072866e-8,
    2.75573136213857245213e-6,
    -1.98412698295895385996e-4,
    8.33333333332211858878e-3,
    -1.66666666666666307295e-1,
)
_COS_F64 = (
    -1.13585365213876817300e-11,
    2.08757008419747316778e-9,
    -2.75573141792967388112e-7,
    2.48015872888517045348e-5,
    -1.38888888888730564116e-3,
    4.16666666666665929218e-2,
)
_DP_F64 = (7.85398125648498535156e-1, 3.77489470793079817668e-8, 2.69515142907905952645e-15)


def _horner(z: Array, coefs: tuple[float, ...]) -> Array:
    acc = jnp.full_like(z, coefs[0])
    for c in coefs[1:]:
        acc = acc * z + c
    return acc


def _is_single(x: Array) -> bool:
    return jnp.finfo(x.dtype).bits <= 32


def sincos(x: Float[Array, "*s"]) -> tuple[Float[Array, "*s"], Float[Array, "*s"]]:
    """``(sin x, cos x)`` with Cephes' octant reduction and minimax polynomials."""
    single = _is_single(x)
    sin_c, cos_c, dp = (_SIN_F32, _COS_F32, _DP_F32) if single else (_SIN_F64, _COS_F64, _DP_F64)
    sign = jnp.where(x < 0, -1.0, 1.0).astype(x.dtype)
    ax = jnp.abs(x)
    # floor/multiply only: XLA lowers a floating-point remainder to a scalar fmod call.
    j = jnp.floor(ax * (4.0 / math.pi))
    j = j + (j - 2.0 * jnp.floor(0.5 * j))  # map zeros to origin: j even
    r = ((ax - j * dp[0]) - j * dp[1]) - j * dp[2]
    z = r * r
    s = r + r * z * _horner(z, sin_c)
    c = 1.0 - 0.5 * z + z * z * _horner(z, cos_c)
    octant = j - 8.0 * jnp.floor(0.125 * j)  # 0, 2, 4, 6
    swap = (octant == 2.0) | (octant == 6.0)
    sin_v = jnp.where(swap, c, s)
    cos_v = jnp.where(swap, s, c)
    sin_v = jnp.where(octant >= 4.0, -sin_v, sin_v) * sign
    cos_v = jnp.where((octant == 2.0) | (octant == 4.0), -cos_v, cos_v)
    return sin_v, cos_v


_ATAN_F32 = (8.05374449538e-2, -1.38776856032e-1, 1.99777106478e-1, -3.33329491539e-1)
_ATAN_P64 = (
    -8.750608600031904122785e-1,
    -1.615753718733365076637e1,
    -7.500855792314704667340e1,
    -1.228866684490136173410e2,
    -6.485021904942025371773e1,
)
_ATAN_Q64 = (
    1.0,
    2.485846490142306297962e1,
    1.650270098316988542046e2,
    4.328810604912902668951e2,
    4.853903996359136964868e2,
    1.945506571482613964425e2,
)
_MOREBITS = 6.123233995736765886130e-17


def arctan2_nonneg(y: Float[Array, "*s"], x: Float[Array, "*s"]) -> Float[Array, "*s"]:
    """``atan2(y, x)`` for ``y >= 0, x >= 0`` (not both zero), in ``[0, pi/2]``.

    Reduction: ``a = min(y, x) / max(y, x) in [0, 1]``; ``atan a`` is reduced once more about
    ``tan(pi/8)`` (``atan a = pi/4 + atan((a - 1)/(a + 1))``), then the Cephes polynomial
    (float32) or rational (float64) approximation; ``atan2 = pi/2 - atan a`` when ``y > x``.
    """
    big = y > x
    num = jnp.where(big, x, y)
    den = jnp.where(big, y, x)
    a = num / jnp.where(den == 0, jnp.ones_like(den), den)
    mid = a > 0.4142135623730950488  # tan(pi/8)
    u = jnp.where(mid, (a - 1.0) / (a + 1.0), a)
    z = u * u
    if _is_single(a):
        t = u + u * z * _horner(z, _ATAN_F32)
        base = jnp.where(mid, math.pi / 4, 0.0)
    else:
        t = u + u * z * _horner(z, _ATAN_P64) / _horner(z, _ATAN_Q64)
        base = jnp.where(mid, math.pi / 4 + 0.5 * _MOREBITS, 0.0)
    atan_a = base + t
    return jnp.where(big, (math.pi / 2 + _MOREBITS) - atan_a, atan_a)

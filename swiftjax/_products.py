"""Products with a small inner dimension, written out for XLA:CPU.

A basis, rotation or direction applied to many points (``x [..., k] @ M [k, m]`` with
``k <= 4``) is, as ``@`` or ``einsum``, a separate dot kernel on XLA:CPU that no elementwise
work fuses with; written out as a sum of scaled columns it is one fused, vectorised pass with
the work around it: ``path_weights``' product (16 chunks' 25,350 points against 5 anchors
onto 2 axes) 5.1x faster than ``@`` (``python bench/bench_kernels.py``, same run, bitwise
equal; docs/performance/reverse-revisits.md, seventh pass).

:func:`small_matmul` sums the products in order, ``((x₀ M₀ + x₁ M₁) + x₂ M₂) + …``, and passes
each product through ``where(isfinite(p), p, NaN)``, the identity on a finite product, which
keeps LLVM from contracting a product and the sum into one fused multiply-add: every product
is rounded, then added in order, as XLA:CPU's dot does for these shapes, so the result is the
dot's bit for bit (``tests/test_products.py``).  A product that overflows to ``±inf`` becomes
NaN (the dot would keep the infinity).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

__all__ = ["small_matmul"]


def small_matmul(x: Float[ArrayLike, "*a k"], M: Float[ArrayLike, "*b k m"]) -> Float[Array, "... m"]:
    """``x @ M`` for a small ``k`` (module docstring): ``x [..., k]``, ``M [..., k, m]``
    (batch axes broadcast, as ``matmul`` with each ``x`` a row vector).  Pure; ``k`` is
    unrolled.  Not for a vector ``M [k]``: XLA:CPU's matrix-vector dot adds in another order,
    so a written-out one would not be its bit for bit."""
    x, M = jnp.asarray(x), jnp.asarray(M)
    keep = lambda p: jnp.where(jnp.isfinite(p), p, jnp.nan)
    out = keep(x[..., 0:1] * M[..., 0, :])
    for c in range(1, M.shape[-2]):
        out = out + keep(x[..., c : c + 1] * M[..., c, :])
    return out

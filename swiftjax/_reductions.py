"""Multi-output reductions for the alignment hot paths.

:func:`variadic_sum` sums several arrays over one axis in a single ``lax.reduce``: one loop
carries every accumulator while the inputs stream through, instead of one loop per sum.
Its numerics and speed on XLA:CPU are discussed in ``docs/performance/align.md``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

__all__ = ["variadic_sum"]


def variadic_sum(operands: tuple[Array, ...], axis: int) -> tuple[Array, ...]:
    """One ``lax.reduce`` summing all ``operands`` (same shape) over ``axis`` at once.

    Returns one array per operand, each with ``axis`` removed, in the operands' dtypes.
    """
    inits = tuple(jnp.zeros((), o.dtype) for o in operands)
    ax = axis % operands[0].ndim
    return jax.lax.reduce(operands, inits, lambda a, b: tuple(x + y for x, y in zip(a, b)), (ax,))

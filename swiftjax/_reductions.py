"""Multi-output reductions for the alignment hot paths.

:func:`variadic_sum` sums several arrays over one axis in a single ``lax.reduce``: one loop
carries every accumulator while the inputs stream through, instead of one loop per sum.
Its numerics and speed on XLA:CPU are discussed in ``docs/performance/align.md``.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

__all__ = ["variadic_sum"]


@partial(jax.custom_jvp, nondiff_argnums=(1,))
def variadic_sum(operands: tuple[Array, ...], axis: int) -> tuple[Array, ...]:
    """One ``lax.reduce`` summing all ``operands`` (same shape) over ``axis`` at once.

    Returns one array per operand, each with ``axis`` removed, in the operands' dtypes.
    Differentiable: the sum is linear, so its JVP is the same reduce of the tangents
    (JAX has no JVP/transpose rule for a variadic ``lax.reduce``); the tangents are summed
    one by one, so forward and reverse mode both work.
    """
    inits = tuple(jnp.zeros((), o.dtype) for o in operands)
    ax = axis % operands[0].ndim
    return jax.lax.reduce(operands, inits, lambda a, b: tuple(x + y for x, y in zip(a, b)), (ax,))


@variadic_sum.defjvp
def _variadic_sum_jvp(axis: int, primals, tangents):
    # The tangents are summed one by one with jnp.sum, which JAX can transpose (reverse mode);
    # integer operands (counts) have float0 tangents, passed through as float0 zeros.
    (operands,), (dots,) = primals, tangents
    ax = axis % operands[0].ndim
    out_dots = tuple(
        jnp.sum(t, axis=ax)
        if jnp.issubdtype(o.dtype, jnp.inexact)
        else np.zeros(np.delete(o.shape, ax), jax.dtypes.float0)
        for o, t in zip(operands, dots)
    )
    return variadic_sum(operands, axis), out_dots

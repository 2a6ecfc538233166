"""Products of batches of small matrices (``[..., b, b]``, ``b <= 9``) as unrolled multiply-adds.

XLA:CPU lowers a batched ``dot_general`` (``a @ b``, ``einsum``) on ``[E, 7, 7]`` operands to one
Eigen call per matrix, dispatched through its thread pool, several times slower than
``sum_k a[..., :, k, None] * b[..., None, k, :]``: a single elementwise loop fusion that
vectorises over the batch and fuses with its neighbours.  Each function below is that sum over
the (static, small) contracted dimension (timings in ``docs/performance/posegraph.md``).

Chained products need :func:`unfused`: XLA:CPU fuses a cheap elementwise producer into every
consumer that reads it, so ``c = (a @ b) @ d`` written as sums recomputes each entry of ``a @ b``
seven times, and a four-product chain ~400 times.  ``optimization_barrier`` does not stop this
(XLA:CPU removes barriers before fusion), nor does a ``lax.cond`` (cheap branches become a select).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

__all__ = ["bmm", "bmtm", "bmv", "bmtv", "quadratic", "unfused"]

T = TypeVar("T")


def _sum(terms):
    terms = list(terms)
    total = terms[0]
    for t in terms[1:]:
        total = total + t
    return total


def bmm(a: Float[ArrayLike, "*batch m k"], b: Float[ArrayLike, "*batch k n"]) -> Float[ArrayLike, "*batch m n"]:
    """``a @ b`` for ``[..., m, k] x [..., k, n] -> [..., m, n]``."""
    return _sum(a[..., :, k, None] * b[..., None, k, :] for k in range(a.shape[-1]))


def bmtm(a: Float[ArrayLike, "*batch k m"], b: Float[ArrayLike, "*batch k n"]) -> Float[ArrayLike, "*batch m n"]:
    """``a^T @ b`` for ``[..., k, m] x [..., k, n] -> [..., m, n]``."""
    return _sum(a[..., k, :, None] * b[..., None, k, :] for k in range(a.shape[-2]))


def bmv(a: Float[ArrayLike, "*batch m k"], v: Float[ArrayLike, "*batch k"]) -> Float[ArrayLike, "*batch m"]:
    """``a @ v`` for ``[..., m, k] x [..., k] -> [..., m]``."""
    return _sum(a[..., :, k] * v[..., k, None] for k in range(a.shape[-1]))


def bmtv(a: Float[ArrayLike, "*batch k m"], v: Float[ArrayLike, "*batch k"]) -> Float[ArrayLike, "*batch m"]:
    """``a^T @ v`` for ``[..., k, m] x [..., k] -> [..., m]``."""
    return _sum(a[..., k, :] * v[..., k, None] for k in range(a.shape[-2]))


def quadratic(v: Float[ArrayLike, "*batch k"], a: Float[ArrayLike, "*batch k k"]) -> Float[ArrayLike, "*batch"]:
    """``v^T a v`` for ``[..., k] x [..., k, k] -> [...]``."""
    av = bmv(a, v)
    return _sum(v[..., k] * av[..., k] for k in range(v.shape[-1]))


def unfused(fn: Callable[..., T], *args: ArrayLike) -> T:
    """``fn(*args)``, computed in XLA kernels of its own whose outputs are materialised.

    The body of a ``lax.while_loop`` whose trip count XLA cannot know at compile time is never
    fused with the code around it.  The count is ``1 + (x != x)`` for ``x = args[0].flat[0]``:
    it is 1, and were it 2 the (pure) body would only recompute the same value.  Overhead: one loop
    iteration; what it saves on chained products: ``docs/performance/posegraph.md``.
    Forward-mode differentiable and vmappable; not reverse-mode (a ``while_loop``).
    """
    first = jnp.ravel(args[0])[0]
    trips = 1 + (first != first).astype(jnp.int32)
    out_struct = jax.eval_shape(fn, *args)
    init = (jnp.zeros((), jnp.int32), jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), out_struct))
    _, out = jax.lax.while_loop(lambda c: c[0] < trips, lambda c: (c[0] + 1, fn(*args)), init)
    return out

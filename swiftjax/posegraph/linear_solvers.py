"""The linear solvers of the pose graph as small solver objects, one ``solve`` method each.

Each solves the damped normal equations ``(H + diag(damping)) x = -g`` of
:class:`~swiftjax.posegraph.linear.NormalEquations` and returns ``(x [N, b], iterations, ok)``:

* :class:`DenseCholesky` — the dense ``bN x bN`` Cholesky (:func:`~swiftjax.posegraph.linear.solve_dense`);
* :class:`BlockJacobiPCG` — matrix-free block-Jacobi PCG (:func:`~swiftjax.posegraph.linear.solve_pcg`)
  with at most ``max_iterations`` products (static) and the Eisenstat–Walker forcing
  ``eta = clip(sqrt(|g|_inf / |g_0|_inf), 10 eps, eta_max)`` inside LM;
* :class:`HostSparse` — the host sparse direct solve (CHOLMOD, or SuperLU without cvxopt,
  :mod:`~swiftjax.posegraph.sparse_direct`) through ``jax.pure_callback``
  (:func:`~swiftjax.posegraph.linear.solve_sparse`).  :func:`swiftjax.posegraph.optimize` runs
  this case's LM loop on the host instead, so its compiled programs have no host callback.

The objects are pytrees (``equinox.Module``): static settings (``max_iterations``) are part of
the compiled program, array fields (``eta_max``) are traced, so changing them never recompiles.
:func:`linear_solver` builds one from its name; :func:`swiftjax.posegraph.choose_linear_solver`
picks the name for a graph.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Bool, Float, Int

from swiftjax.posegraph import linear

__all__ = [
    "AbstractLinearSolver",
    "DenseCholesky",
    "BlockJacobiPCG",
    "HostSparse",
    "LINEAR_SOLVERS",
    "linear_solver",
]

Solution = tuple[Float[Array, "n b"], Int[Array, ""], Bool[Array, ""]]


class AbstractLinearSolver(eqx.Module):
    """``solve(ne, damping, *, rtol, fixed, active) -> (x, iterations, ok)``.

    ``rtol``: relative residual tolerance of an iterative solver (ignored by direct ones);
    ``None`` inside LM means the solver's own forcing (:meth:`forcing`).  ``fixed [N]`` and
    ``active [E]`` prune a sparse factorisation's pattern (the blocks they remove are zero).
    """

    name = "abstract"

    def forcing(self, grad_inf: Array, grad_initial: Array) -> Array | None:
        """Relative tolerance of the linear solve inside LM (None: direct solver)."""
        return None

    def solve(
        self,
        ne: linear.NormalEquations,
        damping: Float[Array, "n b"],
        *,
        rtol: Array | float | None = None,
        fixed: Bool[Array, " n"] | None = None,
        active: Bool[Array, " e"] | None = None,
    ) -> Solution:
        raise NotImplementedError


class DenseCholesky(AbstractLinearSolver):
    """Dense Cholesky of the assembled ``bN x bN`` matrix (small graphs)."""

    name = "dense"

    def solve(self, ne, damping, *, rtol=None, fixed=None, active=None) -> Solution:
        return linear.solve_dense(ne, damping)


class BlockJacobiPCG(AbstractLinearSolver):
    """Block-Jacobi preconditioned CG, ``max_iterations`` products at most (static), Eisenstat–Walker
    forcing capped at ``eta_max`` inside LM."""

    max_iterations: int = eqx.field(static=True, default=1000)
    eta_max: Array | float = 1e-4
    name = "pcg"

    def forcing(self, grad_inf: Array, grad_initial: Array) -> Array:
        dtype = grad_inf.dtype
        ratio = grad_inf / jnp.maximum(grad_initial, jnp.finfo(dtype).tiny)
        return jnp.clip(jnp.sqrt(ratio), 10 * jnp.finfo(dtype).eps, self.eta_max)

    def solve(self, ne, damping, *, rtol=None, fixed=None, active=None) -> Solution:
        if rtol is None:
            raise ValueError("BlockJacobiPCG.solve needs rtol (LM passes its forcing)")
        return linear.solve_pcg(ne, damping, jnp.asarray(rtol, ne.grad.dtype), self.max_iterations)


class HostSparse(AbstractLinearSolver):
    """Sparse direct solve on the host (CHOLMOD / SuperLU) through ``jax.pure_callback``."""

    name = "sparse"

    def solve(self, ne, damping, *, rtol=None, fixed=None, active=None) -> Solution:
        return linear.solve_sparse(ne, damping, fixed, active)


#: The solver classes by name (``"auto"`` is resolved by :func:`swiftjax.posegraph.choose_linear_solver`).
LINEAR_SOLVERS: dict[str, type[AbstractLinearSolver]] = {
    "dense": DenseCholesky,
    "pcg": BlockJacobiPCG,
    "sparse": HostSparse,
}


def linear_solver(
    name: str, *, max_iterations: int | None = None, eta_max: Float[ArrayLike, ""] | float | None = None
) -> AbstractLinearSolver:
    """The solver object of a resolved name (``"dense"``, ``"pcg"`` or ``"sparse"``); PCG's
    settings left at ``None`` keep :class:`BlockJacobiPCG`'s defaults."""
    if name not in LINEAR_SOLVERS:
        raise ValueError(f"linear_solver must be 'auto', 'dense', 'pcg' or 'sparse', not {name!r}")
    if name == "pcg":
        given = {"max_iterations": None if max_iterations is None else int(max_iterations), "eta_max": eta_max}
        return BlockJacobiPCG(**{k: v for k, v in given.items() if v is not None})
    return LINEAR_SOLVERS[name]()

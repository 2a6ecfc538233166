"""Edge residuals of the Sim(3) pose graph and their exact analytic Jacobians.

For an edge ``e = (i, j)`` with measurement ``Z`` (paper sec. 3.4)::

    E_e = Z^-1 S_i^-1 S_j,        r_e = log(E_e)  in R^7  (rho, omega, sigma)

Right perturbations ``S <- S exp(delta)`` give ``E(delta_i, delta_j) = E exp(-Ad(S_j^-1 S_i) delta_i)
exp(delta_j)`` to first order, hence (``Jr^-1`` = inverse right Jacobian of Sim(3))::

    J_j = d r / d delta_j =  Jr^-1(r_e)
    J_i = d r / d delta_i = -Jr^-1(r_e) Ad(S_j^-1 S_i)

``Jr^-1(r)`` at ``r = log E`` is ``d log(E exp(d)) / d d`` at ``d = 0``.  We evaluate it in closed
form from its block structure (derivation in :func:`swiftjax.sim3.jlog`): only the partial
derivatives of the three scalar coefficients of ``W^-1`` are needed, in closed form from the
holomorphic ``G(w) = w / (e^w - 1)``, with the ``theta -> 0`` and ``sigma -> 0`` branches of
``sim3.log``.  The result is checked against a 40-digit mpmath reference, against
``sim3.right_jacobian_inverse`` (seven JVPs through ``log o compose o exp``) and against
``jax.jacfwd`` of the residual in the tests.

Everything here is vectorised over edges (no Python loop) and jit/vmap safe.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float, Int, Real

from swiftjax import sim3
from swiftjax.posegraph.blockmat import bmm, quadratic
from swiftjax.posegraph.kernels import kernel_code, robust_rho_weight
from swiftjax.posegraph.problem import Problem

__all__ = [
    "residuals",
    "residuals_and_jacobians",
    "residual_jacobian_factors",
    "right_jacobian_inverse_at",
    "cost",
    "edge_costs",
]


def right_jacobian_inverse_at(E: Float[ArrayLike, "*batch 8"]) -> Float[Array, "*batch 7 7"]:
    """``Jr^-1(log E) = d log(E exp(d)) / d d |_{d=0}``: ``[..., 8] -> [..., 7, 7]``.

    :func:`swiftjax.sim3.jlog` at ``xi = log E``, reusing ``E`` (closed form derived there).
    Valid for ``|omega| < pi``.
    """
    return sim3.jlog(sim3.log(E), E)


def _edge_errors(
    poses: Float[ArrayLike, "n 8"], problem: Problem
) -> tuple[Float[Array, "e 8"], Float[ArrayLike, "e 8"], Float[ArrayLike, "e 8"]]:
    """``(E_e [E, 8], S_i [E, 8], S_j [E, 8])``."""
    si = poses[problem.edges[:, 0]]
    sj = poses[problem.edges[:, 1]]
    err = sim3.compose(sim3.inverse(problem.measurements), sim3.between(si, sj))
    return err, si, sj


def residuals(poses: Float[ArrayLike, "n 8"], problem: Problem) -> Float[Array, "e 7"]:
    """``r_e = log(Z_e^-1 S_i^-1 S_j)`` for every edge: ``[N, 8] -> [E, 7]`` (padding edges included)."""
    err, _, _ = _edge_errors(poses, problem)
    return sim3.log(err)


def residual_jacobian_factors(
    poses: Float[ArrayLike, "n 8"], problem: Problem
) -> tuple[Float[Array, "e 7"], Float[Array, "e 7 7"], Float[Array, "e 7 7"]]:
    """``(r [E, 7], Jr^-1(r) [E, 7, 7], Ad(S_j^-1 S_i) [E, 7, 7])``: ``J_j = Jr^-1``, ``J_i = -Jr^-1 Ad``."""
    # The barrier materialises the gathered edge errors once: without it XLA duplicates their
    # gather and compositions into every fusion of log, jlog and the adjoint
    # (docs/performance/posegraph.md, "Barriers").
    err, si, sj = jax.lax.optimization_barrier(_edge_errors(poses, problem))
    r = sim3.log(err)
    return r, sim3.jlog(r, err), sim3.adjoint(sim3.between(sj, si))


def residuals_and_jacobians(
    poses: Float[ArrayLike, "n 8"], problem: Problem
) -> tuple[Float[Array, "e 7"], Float[Array, "e 7 7"], Float[Array, "e 7 7"]]:
    """``(r [E, 7], J_i [E, 7, 7], J_j [E, 7, 7])`` with respect to right perturbations of ``S_i, S_j``."""
    r, jr_inv, adj = residual_jacobian_factors(poses, problem)
    return r, -bmm(jr_inv, adj), jr_inv


def edge_costs(
    r: Float[Array, "e 7"],
    problem: Problem,
    kernel: str | Int[ArrayLike, ""] | None = None,
    kernel_scale: Real[ArrayLike, ""] = 1.0,
) -> tuple[Float[Array, " e"], Float[Array, " e"]]:
    """``(rho_e(r^T Omega r) [E], IRLS weight rho'_e [E])``; zero for masked edges.

    ``kernel`` is a name (``None``, ``"huber"``, ``"cauchy"``) or an integer code (traced when an array)
    (:func:`~swiftjax.posegraph.problem.kernel_code`); it applies to edges with ``problem.robust``.
    """
    sq = quadratic(r, problem.information)
    code = kernel_code(kernel) if kernel is None or isinstance(kernel, str) else kernel
    rho_k, w_k = robust_rho_weight(sq, code, jnp.asarray(kernel_scale, r.dtype))
    rho = jnp.where(problem.robust, rho_k, sq)
    w = jnp.where(problem.robust, w_k, 1.0)
    mask = problem.edge_mask.astype(r.dtype)
    return rho * mask, w * mask


def cost(
    poses: Float[ArrayLike, "n 8"],
    problem: Problem,
    kernel: str | Int[ArrayLike, ""] | None = None,
    kernel_scale: Real[ArrayLike, ""] = 1.0,
) -> Float[Array, ""]:
    """``1/2 sum_e rho_e(r_e^T Omega_e r_e)`` (GTSAM's ``graph.error`` definition)."""
    rho, _ = edge_costs(residuals(poses, problem), problem, kernel, kernel_scale)
    return 0.5 * jnp.sum(rho)

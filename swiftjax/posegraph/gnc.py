"""Graduated non-convexity with truncated least squares (GNC-TLS) for the robust edges.

Yang, Antonante, Tzoumas, Carlone, "Graduated Non-Convexity for Robust Spatial Perception: From
Non-Minimal Solvers to Global Outlier Rejection", RA-L 2020; the schedule, weight update and
stopping rules are those of GTSAM's ``GncOptimizer`` with ``GncLossType.TLS`` and its linear
scheduler.  With ``s_e = r_e^T Omega_e r_e`` (squared whitened residual) and the inlier threshold
``c`` (``kernel_scale``), the robust edges' cost is the truncated quadratic::

    rho_TLS(s) = min(s, c^2)

and GNC minimises it through the surrogate family ``rho_mu`` (convex for ``mu -> 0``, TLS for
``mu -> inf``) by alternating a weighted least-squares solve (the existing LM with ``Omega_e``
scaled by ``w_e``) and the closed-form weight update (paper eq. 14)::

    w_e = 1                                       s_e <= mu / (mu + 1) c^2
    w_e = c sqrt(mu (mu + 1) / s_e) - mu          in between
    w_e = 0                                       s_e >= (mu + 1) / mu c^2

Edges not flagged ``robust`` (odometry) keep ``w_e = 1`` always: they are known inliers.

Schedule (GTSAM ``GncOptimizer::optimize``):

1. LM with all weights 1 (plain least squares) from the start poses.
2. ``mu_0 = c^2 / (2 s_max - c^2)`` over the robust edges at that solution (paper Remark 5),
   floored at ``1e-6``; if ``2 s_max <= c^2`` every robust edge is already an inlier and the
   least-squares answer is returned (GTSAM: the same test, at the initial values).
3. Repeat up to ``max_iterations``: weights at the current poses for ``mu``; LM on the weighted
   graph from the current poses (GTSAM restarts every solve at the initial values; a warm start
   is cheaper and, the surrogate changing little per step, lands in the same basin); stop when
   every weight is within ``weights_tol`` of 0 or 1, or the weighted cost changed by less than
   ``cost_tol`` relative to the previous solve; else ``mu *= mu_step`` (1.4).

``kernel_scale`` is the inlier threshold on the whitened residual norm ``sqrt(s_e)``.  If the
information matrices match the noise, ``s_e`` of an inlier is chi-squared with 7 degrees of
freedom, so ``c = sqrt(chi2_7^-1(p))`` accepts a fraction ``p`` of inliers:
:data:`DEFAULT_SCALE` ``= sqrt(chi2_7^-1(0.99)) = 4.2982`` (GTSAM's default,
``setInlierCostThresholdsAtProbability(0.99)``; GTSAM's ``barcSq = c^2 / 2`` because its factor
error is ``s / 2``).  With unit (equal) weights the threshold must be given in the residuals'
own units (``c`` ~ a few times their spread).

The functions here are pure: :func:`tls_weights`, :func:`initial_mu` and :func:`tls_cost` take
JAX arrays (jit-able) or NumPy arrays (evaluated by NumPy, no XLA program), :func:`weight_update`
is the jit-able update of a whole problem.  The continuation loop lives in
:func:`swiftjax.posegraph.optimize` (host): it runs the bucket's compiled LM step program for
every solve and computes the weights in NumPy from the residuals that program returns
(:func:`squared_residuals`), so GNC adds no compiled program.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Bool, Float

from swiftjax.posegraph.blockmat import quadratic
from swiftjax.posegraph.factors import residuals
from swiftjax.posegraph.problem import Problem

__all__ = ["DEFAULT_SCALE", "MU_MIN", "tls_weights", "initial_mu", "weight_update", "tls_cost", "squared_residuals"]

#: ``sqrt(chi2_7^-1(0.99))``: the inlier threshold on ``sqrt(r^T Omega r)`` at probability 0.99
#: for a 7-D residual whose information matches its noise (``scipy.stats.chi2.ppf(0.99, 7)`` =
#: 18.4753; checked in the tests).
DEFAULT_SCALE = 4.298287

#: GTSAM's floor on the initial ``mu`` (a huge outlier residual would otherwise give ``mu ~ 0``).
MU_MIN = 1e-6


def _xp(*arrays):
    """NumPy for NumPy inputs (host evaluation, no XLA), else jax.numpy."""
    return np if all(isinstance(a, (np.ndarray, np.generic, float, int)) for a in arrays) else jnp


def tls_weights(
    sq: Float[ArrayLike, "*e"], mu: Float[ArrayLike, ""], c2: Float[ArrayLike, ""]
) -> Float[ArrayLike, "*e"]:
    """GNC-TLS weights (module docstring, eq. 14): ``sq [...], mu, c2 -> w [...]`` in ``[0, 1]``.

    ``sq`` the squared whitened residuals ``r^T Omega r``, ``c2`` the squared inlier threshold.
    """
    xp = _xp(sq, mu, c2)
    lower = mu / (mu + 1.0) * c2
    upper = (mu + 1.0) / mu * c2
    safe = xp.where(sq > 0, sq, 1.0)
    w = xp.sqrt(c2 * mu * (mu + 1.0) / safe) - mu
    w = xp.clip(w, 0.0, 1.0)
    return xp.where(sq >= upper, 0.0, xp.where(sq <= lower, 1.0, w))


def initial_mu(
    sq: Float[ArrayLike, " e"], robust: Bool[ArrayLike, " e"], c2: Float[ArrayLike, ""]
) -> Float[ArrayLike, ""]:
    """``mu_0 = c^2 / (2 s_max - c^2)`` over the ``robust`` edges (floored at :data:`MU_MIN`);
    ``-1`` when ``2 s_max <= c^2`` (every robust edge an inlier: no continuation needed)."""
    xp = _xp(sq, robust, c2)
    s_max = xp.max(xp.where(robust, sq, 0.0))
    excess = 2.0 * s_max - c2
    mu = c2 / xp.where(excess > 0, excess, 1.0)
    return xp.where(excess > 0, xp.maximum(mu, MU_MIN), -1.0)


def tls_cost(
    sq: Float[ArrayLike, " e"], robust: Bool[ArrayLike, " e"], mask: Bool[ArrayLike, " e"], c2: Float[ArrayLike, ""]
) -> Float[ArrayLike, ""]:
    """``1/2 sum_e rho_e(s_e)`` with ``rho = min(s, c^2)`` on robust edges, ``s`` elsewhere."""
    xp = _xp(sq, robust, mask, c2)
    rho = xp.where(robust, xp.minimum(sq, c2), sq)
    return 0.5 * xp.sum(xp.where(mask, rho, 0.0))


def squared_residuals(r: Float[ArrayLike, "e 7"], information: Float[ArrayLike, "e 7 7"]) -> Float[np.ndarray, " e"]:
    """``s_e = r_e^T Omega_e r_e`` on the host: ``[E, 7], [E, 7, 7] -> [E]`` (NumPy), summed in the
    order of :func:`swiftjax.posegraph.blockmat.quadratic`."""
    r = np.asarray(r)
    a = np.asarray(information)
    k = r.shape[-1]
    av = [sum_in_order(a[:, m, l] * r[:, l] for l in range(k)) for m in range(k)]
    return sum_in_order(r[:, m] * av[m] for m in range(k))


def sum_in_order(terms):
    """``((t0 + t1) + t2) + ...`` (the order of blockmat's unrolled sums)."""
    terms = iter(terms)
    total = next(terms)
    for t in terms:
        total = total + t
    return total


def weight_update(
    problem: Problem, poses: Float[Array, "n 8"], mu: Float[Array, ""], c2: Float[Array, ""]
) -> tuple[Float[Array, " e"], Float[Array, " e"], Problem]:
    """One GNC weight update at ``poses``: ``(s [E], w [E], weighted problem)``.

    ``w`` is :func:`tls_weights` on robust edges, 1 on the others, 0 on padding; the weighted
    problem has ``Omega_e <- w_e Omega_e`` (GTSAM's ``makeWeightedGraph``).  ``mu`` and ``c2``
    are traced: one compile per bucket serves every outer iteration.
    """
    sq = quadratic(residuals(poses, problem), problem.information)
    w = jnp.where(problem.robust, tls_weights(sq, mu, c2), 1.0)
    w = jnp.where(problem.edge_mask, w, 0.0).astype(poses.dtype)
    weighted = Problem(
        poses=problem.poses,
        edges=problem.edges,
        measurements=problem.measurements,
        information=problem.information * w[:, None, None],
        fixed=problem.fixed,
        robust=problem.robust,
        edge_mask=problem.edge_mask,
    )
    return sq, w, weighted

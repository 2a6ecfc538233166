"""Edge residuals of the Sim(3) pose graph and their exact analytic Jacobians.

For an edge ``e = (i, j)`` with measurement ``Z`` (paper sec. 3.4, DESIGN.md)::

    E_e = Z^-1 S_i^-1 S_j,        r_e = log(E_e)  in R^7  (rho, omega, sigma)

Right perturbations ``S <- S exp(delta)`` give ``E(delta_i, delta_j) = E exp(-Ad(S_j^-1 S_i) delta_i)
exp(delta_j)`` to first order, hence (``Jr^-1`` = inverse right Jacobian of Sim(3))::

    J_j = d r / d delta_j =  Jr^-1(r_e)
    J_i = d r / d delta_i = -Jr^-1(r_e) Ad(S_j^-1 S_i)

``Jr^-1(r)`` at ``r = log E`` is ``d log(E exp(d)) / d d`` at ``d = 0``.  We evaluate it in closed
form from its block structure (derivation in :func:`right_jacobian_inverse_at`): only the
derivatives of the three scalar coefficients of ``W^-1`` need differentiation, and those we take
by forward mode through :mod:`swiftjax.sim3`'s own coefficient formulas, so every special-case
branch (``theta -> 0``, ``sigma -> 0``) is shared with ``sim3.log``.  The result is checked
against ``sim3.right_jacobian_inverse`` (seven JVPs through ``log o compose o exp``) and
against ``jax.jacfwd`` of the residual in the tests.

Everything here is vectorised over edges (no Python loop) and jit/vmap safe.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from swiftjax import sim3, so3
from swiftjax.posegraph.problem import Problem, RobustKernel, robust_rho, robust_weight

__all__ = [
    "residuals",
    "residuals_and_jacobians",
    "residual_jacobian_factors",
    "right_jacobian_inverse_at",
    "cost",
    "edge_costs",
]


def _winv_coefficients(theta_sq: Array, sigma: Array) -> tuple[Array, Array, Array]:
    """``(x, y, z)`` of ``W^-1 = x I + y K + z K^2`` (the formula of ``sim3.log``)."""
    a, b, c = sim3._w_coefficients(theta_sq, sigma)  # noqa: SLF001 - shared branches on purpose
    d = c - theta_sq * b
    det = d * d + theta_sq * a * a
    return 1.0 / c, -a / det, (a * a - b * d) / (c * det)


def _so3_right_jacobian_inverse(omega: Array) -> Array:
    """``Jr^-1`` of SO(3): ``I + 1/2 K + (1/theta^2 - (1 + cos)/(2 theta sin)) K^2``, ``[..., 3, 3]``."""
    theta_sq = jnp.sum(omega * omega, axis=-1)
    small = theta_sq < (1e-6 if omega.dtype == jnp.float32 else 1e-8)
    tsq = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(tsq)
    # (1/theta^2 - (1+cos)/(2 theta sin)) = 1/theta^2 - cot(theta/2)/(2 theta)
    coef_gen = 1.0 / tsq - 0.5 / (theta * jnp.tan(0.5 * jnp.where(small, 1.0, theta)))
    coef_small = 1.0 / 12.0 + theta_sq / 720.0 + theta_sq * theta_sq / 30240.0
    coef = jnp.where(small, coef_small, coef_gen)
    k = so3.hat(omega)
    eye = jnp.eye(3, dtype=omega.dtype)
    return eye + 0.5 * k + coef[..., None, None] * (k @ k)


def right_jacobian_inverse_at(E: Array) -> Array:
    """``Jr^-1(log E) = d log(E exp(d)) / d d |_{d=0}``: ``[..., 8] -> [..., 7, 7]``.

    With ``log E = (rho, omega, sigma)``, ``rho = W^-1(omega, sigma) t`` and
    ``E exp(d) = (t + s R rho_d + O(d^2), R exp(omega_d), s e^sigma_d)``::

        Jr^-1 = [[ s W^-1 R,  M Jr_SO3^-1(omega),  m ],
                 [ 0,         Jr_SO3^-1(omega),    0 ],
                 [ 0,         0,                   1 ]]

        M = d(W^-1 t)/d omega = y [-t]x + z ((omega.t) I + omega t^T - 2 t omega^T)
            + 2 (x_q t + y_q (omega x t) + z_q omega x (omega x t)) omega^T
        m = d(W^-1 t)/d sigma = x_s t + y_s (omega x t) + z_s omega x (omega x t)

    where ``(x, y, z)(theta^2, sigma)`` are the ``W^-1`` coefficients and ``_q``/``_s`` their
    partial derivatives in ``theta^2`` and ``sigma`` (two scalar JVPs).  Valid for
    ``|omega| < pi``.
    """
    return _jr_inv(E, sim3.log(E))


def _jr_inv(E: Array, r: Array) -> Array:
    """:func:`right_jacobian_inverse_at` given ``r = log E`` already computed."""
    t = sim3.translation(E)
    q = sim3.quaternion(E)
    s = sim3.scale(E)
    omega = r[..., 3:6]
    sigma = r[..., 6]
    theta_sq = jnp.sum(omega * omega, axis=-1)

    # Partial derivatives of (x, y, z) in theta^2 and sigma: one batched JVP (two tangents).
    f = lambda a, b: jnp.stack(_winv_coefficients(a, b))  # noqa: E731
    coeffs, derivs = jax.vmap(
        lambda tan: jax.jvp(
            f, (theta_sq, sigma), (jnp.full_like(theta_sq, tan[0]), jnp.full_like(sigma, tan[1]))
        ),
        out_axes=(None, 0),
    )(jnp.eye(2, dtype=E.dtype))
    x, y, z = coeffs
    xq, yq, zq = derivs[0]
    xs, ys, zs = derivs[1]

    wt = jnp.cross(omega, t)
    wwt = jnp.cross(omega, wt)
    eye = jnp.eye(3, dtype=E.dtype)
    kw = so3.hat(omega)
    winv = x[..., None, None] * eye + y[..., None, None] * kw + z[..., None, None] * (kw @ kw)
    R = so3.as_matrix(q)
    top_left = s[..., None, None] * (winv @ R)

    outer = lambda a, b: a[..., :, None] * b[..., None, :]  # noqa: E731
    wdt = jnp.sum(omega * t, axis=-1)
    grad_q = xq[..., None] * t + yq[..., None] * wt + zq[..., None] * wwt
    M = (
        y[..., None, None] * (-so3.hat(t))
        + z[..., None, None] * (wdt[..., None, None] * eye + outer(omega, t) - 2.0 * outer(t, omega))
        + 2.0 * outer(grad_q, omega)
    )
    m = xs[..., None] * t + ys[..., None] * wt + zs[..., None] * wwt
    jso3 = _so3_right_jacobian_inverse(omega)

    batch = E.shape[:-1]
    zeros33 = jnp.zeros((*batch, 3, 3), E.dtype)
    zeros31 = jnp.zeros((*batch, 3, 1), E.dtype)
    row0 = jnp.concatenate([top_left, M @ jso3, m[..., :, None]], axis=-1)
    row1 = jnp.concatenate([zeros33, jso3, zeros31], axis=-1)
    row2 = jnp.broadcast_to(jnp.array([0, 0, 0, 0, 0, 0, 1], E.dtype), (*batch, 1, 7))
    return jnp.concatenate([row0, row1, row2], axis=-2)


def _edge_errors(poses: Array, problem: Problem) -> tuple[Array, Array, Array]:
    """``(E_e [E, 8], S_i [E, 8], S_j [E, 8])``."""
    si = poses[problem.edges[:, 0]]
    sj = poses[problem.edges[:, 1]]
    err = sim3.compose(sim3.inverse(problem.measurements), sim3.between(si, sj))
    return err, si, sj


def residuals(poses: Array, problem: Problem) -> Array:
    """``r_e = log(Z_e^-1 S_i^-1 S_j)`` for every edge: ``[N, 8] -> [E, 7]`` (padding edges included)."""
    err, _, _ = _edge_errors(poses, problem)
    return sim3.log(err)


def residual_jacobian_factors(poses: Array, problem: Problem) -> tuple[Array, Array, Array]:
    """``(r [E, 7], Jr^-1(r) [E, 7, 7], Ad(S_j^-1 S_i) [E, 7, 7])``: ``J_j = Jr^-1``, ``J_i = -Jr^-1 Ad``."""
    err, si, sj = _edge_errors(poses, problem)
    r = sim3.log(err)
    return r, _jr_inv(err, r), sim3.adjoint(sim3.between(sj, si))


def residuals_and_jacobians(poses: Array, problem: Problem) -> tuple[Array, Array, Array]:
    """``(r [E, 7], J_i [E, 7, 7], J_j [E, 7, 7])`` with respect to right perturbations of ``S_i, S_j``."""
    r, jr_inv, adj = residual_jacobian_factors(poses, problem)
    return r, -jr_inv @ adj, jr_inv


def edge_costs(
    r: Array, problem: Problem, kernel: RobustKernel | None = None, kernel_scale: float = 1.0
) -> tuple[Array, Array]:
    """``(rho_e(r^T Omega r) [E], IRLS weight rho'_e [E])``; zero for masked edges."""
    sq = jnp.einsum("ei,eij,ej->e", r, problem.information, r)
    if kernel is None:
        rho, w = sq, jnp.ones_like(sq)
    else:
        rho = jnp.where(problem.robust, robust_rho(sq, kernel, kernel_scale), sq)
        w = jnp.where(problem.robust, robust_weight(sq, kernel, kernel_scale), 1.0)
    mask = problem.edge_mask.astype(r.dtype)
    return rho * mask, w * mask


def cost(
    poses: Array, problem: Problem, kernel: RobustKernel | None = None, kernel_scale: float = 1.0
) -> Array:
    """``1/2 sum_e rho_e(r_e^T Omega_e r_e)`` (GTSAM's ``graph.error`` definition)."""
    rho, _ = edge_costs(residuals(poses, problem), problem, kernel, kernel_scale)
    return 0.5 * jnp.sum(rho)

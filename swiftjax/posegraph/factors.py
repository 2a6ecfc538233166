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
from swiftjax.posegraph.blockmat import bmm, quadratic
from swiftjax.posegraph.problem import Problem, RobustKernel, kernel_code, robust_rho_weight

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
    """:func:`right_jacobian_inverse_at` given ``r = log E`` already computed.

    On ``[..., 3, 3]`` blocks with :mod:`~swiftjax.posegraph.blockmat`'s elementwise products
    (no batched dots, which XLA:CPU runs one library call per element).  Measured, 7,168 edges:
    compile 1.0 s vs 1.4 s for the previous scalar-by-scalar form, run time equal (2.4-2.6 ms).
    """
    dtype = E.dtype
    t, s = E[..., 0:3], E[..., 7]
    w, sigma = r[..., 3:6], r[..., 6]
    theta_sq = jnp.sum(w * w, -1)

    # Partial derivatives of (x, y, z) in theta^2 and sigma: two scalar JVPs.
    f = lambda a, b: jnp.stack(_winv_coefficients(a, b))  # noqa: E731
    ones, zeros = jnp.ones_like(theta_sq), jnp.zeros_like(theta_sq)
    coeffs, d_q = jax.jvp(f, (theta_sq, sigma), (ones, zeros))
    _, d_s = jax.jvp(f, (theta_sq, sigma), (zeros, ones))
    x, y, z = (v[..., None, None] for v in coeffs)
    xq, yq, zq = (v[..., None] for v in d_q)
    xs, ys, zs = (v[..., None] for v in d_s)

    eye = jnp.eye(3, dtype=dtype)
    outer = lambda a, b: a[..., :, None] * b[..., None, :]  # noqa: E731
    k = so3.hat(w)
    k2 = outer(w, w) - theta_sq[..., None, None] * eye  # K^2 = w w^T - theta^2 I
    winv = x * eye + y * k + z * k2
    wt = jnp.cross(w, t)
    wwt = jnp.cross(w, wt)
    wdt = jnp.sum(w * t, -1)[..., None, None]
    g_q = xq * t + yq * wt + zq * wwt
    big_m = -y * so3.hat(t) + z * (wdt * eye + outer(w, t) - 2.0 * outer(t, w)) + 2.0 * outer(g_q, w)
    m = xs * t + ys * wt + zs * wwt

    # SO(3) Jr^-1 = I + K/2 + c K^2,  c = 1/theta^2 - cot(theta/2) / (2 theta)
    small = theta_sq < (1e-6 if dtype == jnp.float32 else 1e-8)
    tsq = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(tsq)
    c = jnp.where(
        small,
        1.0 / 12.0 + theta_sq / 720.0 + theta_sq * theta_sq / 30240.0,
        1.0 / tsq - 0.5 / (theta * jnp.tan(0.5 * theta)),
    )
    jso3 = eye + 0.5 * k + c[..., None, None] * k2

    top = jnp.concatenate([s[..., None, None] * bmm(winv, so3.as_matrix(E[..., 3:7])), bmm(big_m, jso3), m[..., None]], -1)
    middle = jnp.concatenate([jnp.zeros_like(jso3), jso3, jnp.zeros(s.shape + (3, 1), dtype)], -1)
    bottom = jnp.broadcast_to(jnp.eye(7, dtype=dtype)[6], s.shape + (1, 7))
    return jnp.concatenate([top, middle, bottom], -2)


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
    return r, -bmm(jr_inv, adj), jr_inv


def edge_costs(
    r: Array, problem: Problem, kernel: RobustKernel | Array | None = None, kernel_scale: float | Array = 1.0
) -> tuple[Array, Array]:
    """``(rho_e(r^T Omega r) [E], IRLS weight rho'_e [E])``; zero for masked edges.

    ``kernel`` is a name (``None``, ``"huber"``, ``"cauchy"``) or a traced integer code
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
    poses: Array, problem: Problem, kernel: RobustKernel | Array | None = None, kernel_scale: float | Array = 1.0
) -> Array:
    """``1/2 sum_e rho_e(r_e^T Omega_e r_e)`` (GTSAM's ``graph.error`` definition)."""
    rho, _ = edge_costs(residuals(poses, problem), problem, kernel, kernel_scale)
    return 0.5 * jnp.sum(rho)

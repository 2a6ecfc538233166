"""Levenberg–Marquardt on the Sim(3) manifold with block-sparse linear algebra, as an optimistix solver.

:class:`SparseSim3LM` is an ``optimistix.AbstractLeastSquaresSolver``: it runs inside
``optimistix.least_squares`` (optimistix's iteration loop, ``max_steps``, ``throw``), but
where optimistix's ``LevenbergMarquardt`` would materialise a dense Jacobian (QR) or go
matrix-free without a preconditioner, it linearises edge by edge with the exact analytic
Jacobians of :mod:`swiftjax.posegraph.factors`, assembles the block-sparse normal
equations with segment sums and solves them with one of the solver objects of
:mod:`swiftjax.posegraph.linear_solvers` (dense Cholesky, block-Jacobi PCG, host sparse
direct; :func:`swiftjax.posegraph.choose_linear_solver` picks one).  Updates are on the
manifold, ``S <- S exp(delta)``.  :func:`swiftjax.posegraph.optimize` runs the same steps from
a loop on the host (:meth:`SparseSim3LM.advance`), one compiled step program per size bucket.

Step 0 only linearises at the initial guess (so a compiled program holds one copy of the
Jacobian code); every later step::

    (H + lambda D) delta = -g
    predicted = -(g.delta + 1/2 delta^T H delta),   actual = C(S) - C(S exp(delta))
    accept if actual > 1e-3 predicted:  lambda /= 10, nu = 2
    otherwise:                          lambda *= nu, nu *= 2

The decrease on acceptance is GTSAM's fixed factor 10.  ``D = I`` by default (GTSAM's choice,
in tangent units), or Marquardt's ``D = clip(diag H)`` (``damping="marquardt"``), which along a
chain damps exactly the weak rigid-rotation directions the step needs (lever arms make the
rotation entries of ``diag H`` large).

Stopping (:class:`LMResult`): an accepted step with ``actual <= rtol * C`` (GTSAM's
relativeErrorTol, ``relative_decrease``) or ``actual <= atol`` (absoluteErrorTol,
``absolute_decrease``); ``|g|_inf <= gtol |g_0|_inf`` (``small_gradient``: the Jacobians are
exact, so ``g = 0`` is the true optimum); the model predicting a decrease below rounding
(``predicted <= 16 eps C`` while ``lambda <= 1``) or the cost itself at rounding level
(``C <= eps E``: whitened residuals of ~1e-8 sigma, e.g. a chain without loops;
``rounding_level``); or ``lambda`` exceeding ``1e16`` (``stalled``: a failure, so
``optimistix.least_squares(..., throw=True)`` raises).  The robust kernels use IRLS weights in ``H`` and the
exact gradient.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax import Array
from jaxtyping import ArrayLike, Bool, Float, Int, Real

from swiftjax import sim3
from swiftjax.posegraph import linear
from swiftjax.posegraph.factors import edge_costs, residual_jacobian_factors, residuals
from swiftjax.posegraph.linear_solvers import AbstractLinearSolver, DenseCholesky
from swiftjax.posegraph.linear_solvers import linear_solver as _linear_solver
from swiftjax.posegraph.problem import Problem

__all__ = ["SparseSim3LM", "LMState", "LMResult", "CONVERGED", "is_converged", "result_index", "linearize", "retract"]


class LMResult(optx.RESULTS):
    """Why an LM solve stopped (optimistix's ``RESULTS`` plus the LM stopping tests).

    The solver's state (:attr:`LMState.result`) and :class:`swiftjax.posegraph.Result` carry the
    reason itself; ``nonlinear_max_steps_reached`` means no stopping test was met.  Inside
    ``optimistix.least_squares``, :meth:`SparseSim3LM.terminate` reports the four converged
    reasons (:data:`CONVERGED`) as ``optimistix.RESULTS.successful`` and ``stalled`` as
    ``nonlinear_divergence`` (optimistix's loop accepts only its own enumeration), so
    ``throw=True`` raises on a stalled solve and on ``max_steps``.
    """

    relative_decrease = "relative cost decrease <= rtol"
    absolute_decrease = "absolute cost decrease <= atol"
    small_gradient = "gradient <= gtol * initial gradient"
    rounding_level = "cost or predicted decrease at rounding level"
    stalled = "stalled: damping exceeded 1e16 without progress"
    gnc_not_converged = "GNC: outer iterations without converged weights or cost"


#: The reasons that mean a converged solve.
CONVERGED = (LMResult.relative_decrease, LMResult.absolute_decrease, LMResult.small_gradient, LMResult.rounding_level)
_RUNNING = LMResult.nonlinear_max_steps_reached


def result_index(result: LMResult) -> int:
    """The host integer of a concrete result (no device op)."""
    return int(np.asarray(result._value))


def is_converged(result: LMResult) -> Bool[Array, ""]:
    """True where ``result`` is one of :data:`CONVERGED`."""
    out = result == CONVERGED[0]
    for r in CONVERGED[1:]:
        out = out | (result == r)
    return out


_LAMBDA_MAX = 1e16
_LAMBDA_MIN = 1e-14


class Linearization(eqx.Module):
    """Cost, per-edge IRLS weights ``rho'_e`` ``[E]``, residuals ``[E, 7]`` and normal equations at one iterate."""

    cost: Float[Array, ""]
    ne: linear.NormalEquations
    edge_weights: Float[Array, " e"]
    residuals: Float[Array, "e 7"]


def linearize(
    poses: Float[Array, "n 8"],
    problem: Problem,
    kernel: str | Int[ArrayLike, ""] | None,
    kernel_scale: Real[ArrayLike, ""],
) -> Linearization:
    """Residuals, exact Jacobians, IRLS weights and the assembled normal equations at ``poses``."""
    # Factors materialised before the assembly (as the edge errors are inside them): the
    # assembly's unrolled block products otherwise re-fuse the Jacobians' formulas into each
    # of their consumers, recomputing them (compile and run time: docs/performance/posegraph.md).
    r, jr_inv, adj = jax.lax.optimization_barrier(residual_jacobian_factors(poses, problem))
    rho, w = edge_costs(r, problem, kernel, kernel_scale)
    ne = linear.assemble(r, jr_inv, adj, w, problem.information, problem.edges, problem.fixed)
    return Linearization(cost=0.5 * jnp.sum(rho), ne=ne, edge_weights=w, residuals=r)


def retract(poses: Float[Array, "n 8"], delta: Float[Array, "n 7"], fixed: Bool[Array, " n"]) -> Float[Array, "n 8"]:
    """``S_n <- normalize(S_n exp(delta_n))`` for free nodes; fixed nodes unchanged bit for bit."""
    moved = sim3.normalize(sim3.compose(poses, sim3.exp(delta)))
    return jnp.where(fixed[:, None], poses, moved)


class LMState(eqx.Module):
    """LM's state; ``result`` is :data:`LMResult.nonlinear_max_steps_reached` until a stopping test is met."""

    lin: Linearization
    lam: Array
    nu: Array
    cost_initial: Array
    grad_initial: Array
    grad_inf: Array
    result: LMResult
    num_accepted: Array
    num_rejected: Array
    linear_iterations: Array

    @property
    def done(self) -> Bool[Array, ""]:
        return self.result != _RUNNING


def _as_linear_solver(value):
    return _linear_solver(value) if isinstance(value, str) else value


class SparseSim3LM(optx.AbstractLeastSquaresSolver):
    """Levenberg–Marquardt for :class:`~swiftjax.posegraph.Problem` (pass it as ``args``).

    Use through ``optimistix.least_squares(fn, solver, problem.poses, args=problem)`` where
    ``fn(y, problem)`` returns the residuals (it is traced only for its output structure; the
    solver linearises with the analytic edge Jacobians).  Float fields may be JAX arrays so
    that changing them does not recompile; ``damping`` and the linear solver's static settings
    are static.  Its defaults are the settings' defaults: :class:`~swiftjax.posegraph.GraphOptions`
    reuses them (with each setting's range and help).

    Attributes:
        rtol, atol: relative / absolute cost-decrease tolerances (GTSAM semantics).
        gtol: gradient tolerance relative to the initial gradient's max-norm.
        lambda0: initial damping.
        damping: ``"identity"`` (``D = I``) or ``"marquardt"`` (``D = clip(diag H)``); static.
        linear_solver: a solver object of :mod:`swiftjax.posegraph.linear_solvers`
            (``DenseCholesky()``, ``BlockJacobiPCG(max_iterations, eta_max)``, ``HostSparse()``)
            or its name.
        kernel, kernel_scale: robust kernel for edges with ``problem.robust`` set: a name
            (``None``/``"huber"``/``"cauchy"``, static) or an integer code array (traced, see
            :func:`~swiftjax.posegraph.kernels.kernel_code`; the driver passes codes so that
            switching kernels never recompiles).
    """

    rtol: Any = 1e-10
    atol: Any = 0.0
    norm: Callable = optx.max_norm
    gtol: Any = 1e-10
    lambda0: Any = 1e-5
    linear_solver: AbstractLinearSolver = eqx.field(default=DenseCholesky(), converter=_as_linear_solver)
    damping: str = eqx.field(static=True, default="identity")
    kernel: Any = 0
    kernel_scale: Any = 1.0

    def _linearize(self, y, problem):
        return linearize(y, problem, self.kernel, self.kernel_scale)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags) -> LMState:
        # No linearisation here: step 0 linearises at the initial guess (delta = 0), so the
        # compiled program holds exactly one copy of the residual/Jacobian code.
        problem: Problem = args
        n, e = problem.poses.shape[0], problem.edges.shape[0]
        dtype = y.dtype
        zero = jnp.zeros((), dtype)
        ne = linear.NormalEquations(
            diag=jnp.broadcast_to(jnp.eye(7, dtype=dtype), (n, 7, 7)),
            off=jnp.zeros((e, 7, 7), dtype),
            grad=jnp.zeros((n, 7), dtype),
            edges=problem.edges,
        )
        lin = Linearization(cost=zero, ne=ne, edge_weights=jnp.zeros((e,), dtype), residuals=jnp.zeros((e, 7), dtype))
        return LMState(
            lin=lin,
            lam=jnp.asarray(self.lambda0, dtype),
            nu=jnp.asarray(2.0, dtype),
            cost_initial=zero,
            grad_initial=zero,
            grad_inf=zero,
            result=LMResult.where(jnp.asarray(True), _RUNNING, _RUNNING),
            num_accepted=jnp.full((), -1, jnp.int32),
            num_rejected=jnp.zeros((), jnp.int32),
            linear_iterations=jnp.zeros((), jnp.int32),
        )

    def damping_vector(self, state: LMState) -> Array:
        """``lambda D`` as ``[N, 7]`` (``D = I`` or Marquardt's ``clip(diag H)``)."""
        ne = state.lin.ne
        if self.damping == "marquardt":
            return state.lam * linear.damping_diagonal(ne)
        if self.damping == "identity":
            return jnp.broadcast_to(state.lam, ne.grad.shape)
        raise ValueError(f"unknown damping {self.damping!r}")

    def solve_linear(self, state: LMState, problem: Problem) -> tuple[Array, Array, Array]:
        """``(H + lambda D) delta = -g`` with the configured linear solver: ``(delta, iterations, ok)``."""
        solver = self.linear_solver
        return solver.solve(
            state.lin.ne,
            self.damping_vector(state),
            rtol=solver.forcing(state.grad_inf, state.grad_initial),
            fixed=problem.fixed,
            active=problem.edge_mask,
        )

    def step(self, fn, y, args, options, state: LMState, tags):
        delta, iters, ok = self.solve_linear(state, args)
        y_next, new_state = self.advance(y, args, state, delta, iters, ok)
        return y_next, new_state, None

    def advance(
        self, y: Array, problem: Problem, state: LMState, delta: Array, iters: Array, ok: Array
    ) -> tuple[Array, LMState]:
        """Evaluate the step ``delta`` (accept/reject, damping update, stopping tests).

        Split from :meth:`step` so that a host-side loop can supply ``delta`` from a solver that
        lives outside XLA (:func:`swiftjax.posegraph.optimize` does so for ``"sparse"``).
        """
        first = state.num_accepted < 0
        lin = state.lin
        ne = lin.ne
        dtype = y.dtype
        eps = jnp.finfo(dtype).eps
        delta = jnp.where(first, 0.0, delta)

        predicted = -(jnp.sum(ne.grad * delta) + 0.5 * jnp.sum(delta * linear.matvec(ne, delta)))
        candidate = retract(y, delta, problem.fixed)
        candidate = jnp.where(first, y, candidate)
        new_lin = self._linearize(candidate, problem)
        actual = lin.cost - new_lin.cost
        ratio = actual / jnp.where(predicted > 0, predicted, 1.0)
        accept = ok & jnp.isfinite(new_lin.cost) & (predicted > 0) & (ratio > 1e-3)

        lam_accept = state.lam * 0.1
        lam = jnp.where(accept, jnp.maximum(lam_accept, _LAMBDA_MIN), state.lam * state.nu)
        nu = jnp.where(accept, 2.0, 2.0 * state.nu)
        lam = jnp.where(first, state.lam, lam)
        nu = jnp.where(first, state.nu, nu)
        take = accept | first

        y_next = jnp.where(take, candidate, y)
        lin_next = jax.tree_util.tree_map(lambda a, b: jnp.where(take, a, b), new_lin, lin)
        g_inf = jnp.max(jnp.abs(lin_next.ne.grad))
        grad_initial = jnp.where(first, g_inf, state.grad_initial)

        # Later tests take precedence (the order of the former status codes).
        where = LMResult.where
        result = where(lam > _LAMBDA_MAX, LMResult.stalled, _RUNNING)
        result = where(ok & (state.lam <= 1.0) & (predicted <= 16 * eps * lin.cost), LMResult.rounding_level, result)
        result = where(accept & (actual <= self.atol), LMResult.absolute_decrease, result)
        result = where(accept & (actual <= self.rtol * lin.cost), LMResult.relative_decrease, result)
        result = where(first, _RUNNING, result)
        # A cost at rounding level in whitened units (e.g. a chain without loops) is the minimum.
        num_edges = jnp.sum(problem.edge_mask)
        result = where(lin_next.cost <= eps * num_edges, LMResult.rounding_level, result)
        # g == 0 exactly at the start (e.g. a chain without loops) also stops here.
        result = where(g_inf <= self.gtol * grad_initial, LMResult.small_gradient, result)

        new_state = LMState(
            lin=lin_next,
            lam=lam,
            nu=nu,
            cost_initial=jnp.where(first, new_lin.cost, state.cost_initial),
            grad_initial=grad_initial,
            grad_inf=g_inf,
            result=result,
            num_accepted=state.num_accepted + take,
            num_rejected=state.num_rejected + (~take),
            linear_iterations=state.linear_iterations + jnp.where(first, 0, iters),
        )
        return y_next, new_state

    def terminate(self, fn, y, args, options, state: LMState, tags):
        # optimistix's loop takes its own RESULTS: a converged reason is ``successful``, a stall
        # is ``nonlinear_divergence`` (so ``throw=True`` raises); the reason stays in the state.
        stalled = state.result == LMResult.stalled
        return state.done, optx.RESULTS.where(stalled, optx.RESULTS.nonlinear_divergence, optx.RESULTS.successful)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


def residual_fn(poses: Float[Array, "n 8"], problem: Problem) -> Float[Array, "e 7"]:
    """The residual function handed to ``optimistix.least_squares`` (``[E, 7]``)."""
    return residuals(poses, problem)

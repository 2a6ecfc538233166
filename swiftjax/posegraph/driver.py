"""Host-level entry point: validate, pad to a size bucket, compile once, solve, report.

``optimize(problem)`` is the only function in this package that runs a loop on the host: it
validates the concrete problem (clear errors before any work), pads it to a
``(N_bucket, E_bucket)`` size bucket (:func:`swiftjax.posegraph.problem.bucket_size`), looks up —
or compiles, timing it — the bucket's two programs, runs LM's iterations and unpads the result.

The two programs of a bucket:

* *begin*: unit quaternions exactly, the LM start (the given poses or the chordal
  initialisation, :mod:`swiftjax.posegraph.initialization`) and LM's initial state;
* *step*: one LM iteration (:meth:`SparseSim3LM.step`: linear solve, retraction,
  linearisation at the candidate, accept/reject, stopping tests).  With the host sparse solver
  the linear solve runs in NumPy between calls (:mod:`swiftjax.posegraph.sparse_direct`) and the
  program is :meth:`SparseSim3LM.advance` (no host callback inside a compiled program: JAX does
  not put those in its persistent compilation cache).

The host calls *step* until a stopping test is met or ``max_steps`` is spent; GNC
(``kernel="gnc"``, :mod:`swiftjax.posegraph.gnc`) runs its continuation on the host around the
same step program (its solves are weighted least squares, kernel code 0) and computes its
weights in NumPy from the residuals the step program returns.  What triggers a compile: a new
``(N_bucket, E_bucket)`` pair, a new dtype, or a change of the static options (``damping``,
``initialization``, the resolved linear solver and its ``max_iterations``).  ``max_steps``,
tolerances, ``lambda0``, ``eta_max``, the robust ``kernel`` and ``kernel_scale`` and every GNC
setting never recompile.  With JAX's persistent compilation cache enabled (the CLI and the
test suite enable it) a bucket compiled by an earlier process is loaded from disk.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from swiftjax import sim3
from swiftjax._compile import QUICK_COMPILE
from swiftjax.errors import SwiftjaxError
from swiftjax.posegraph import gnc, sparse_direct
from swiftjax.posegraph.factors import cost
from swiftjax.posegraph.initialization import chordal_initialization
from swiftjax.posegraph.kernels import kernel_code
from swiftjax.posegraph.linear_solvers import AbstractLinearSolver, DenseCholesky, HostSparse, linear_solver
from swiftjax.posegraph.options import GraphOptions
from swiftjax.posegraph.problem import Problem, pad_problem, padded_sizes, validate
from swiftjax.posegraph.solver import CONVERGED, LMResult, LMState, SparseSim3LM, residual_fn, result_index
from swiftjax.posegraph.solver_choice import (  # re-exported: their home is solver_choice
    DENSE_MAX_NODES,
    FILL_ESTIMATE_MAX_NODES,
    SPARSE_MAX_CYCLE_FRACTION,
    SPARSE_MAX_FILL,
    choose_linear_solver,
    node_fill_ratio,
)

__all__ = [
    "optimize",
    "Result",
    "SolveError",
    "choose_linear_solver",
    "node_fill_ratio",
    "DENSE_MAX_NODES",
    "SPARSE_MAX_CYCLE_FRACTION",
    "SPARSE_MAX_FILL",
    "FILL_ESTIMATE_MAX_NODES",
]


@dataclasses.dataclass(frozen=True)
class Result:
    """Outcome of :func:`optimize` (host values; ``poses`` is a JAX array ``[N, 8]``).

    ``cost_*`` are ``1/2 sum rho(r^T Omega r)`` (GTSAM's ``graph.error`` definition):
    ``cost_initial`` at the given poses, ``cost_start`` where LM started (after the chordal
    initialisation, else the same), ``cost_final`` at the result.
    ``result`` (:class:`~swiftjax.posegraph.LMResult`) says why the solve stopped and ``status``
    in words; ``converged`` is True for the converged reasons (:data:`~swiftjax.posegraph.solver.CONVERGED`),
    False when ``max_steps`` ran out, the damping stalled or GNC's weights did not settle.
    ``compile_seconds`` is 0 when the bucket was already compiled in this process.

    ``inlier_weights`` ``[E]`` (NumPy float64): with ``kernel="gnc"`` the GNC-TLS weights of the
    final solve (1 inlier, 0 outlier, in between only if the continuation stopped early); with
    Huber/Cauchy the IRLS weight ``rho'(s_e)`` at the result; 1 for every edge not flagged
    ``robust`` and for ``kernel=None``.  ``gnc_iterations``: GNC outer iterations (weighted LM
    solves after the first, unweighted one); 0 otherwise.  With GNC, ``num_steps``,
    ``num_accepted``, ``num_rejected`` and ``linear_iterations`` are summed over every LM solve,
    ``cost_start`` is the first (unweighted) solve's start cost and ``cost_final`` the last solve's
    weighted cost ``1/2 sum w_e s_e`` (binary weights: the TLS cost without its constant
    ``c^2 / 2`` per rejected edge).  ``residuals`` ``[E, 7]`` (NumPy): ``r_e`` at ``poses``.
    """

    poses: Float[Array, "n 8"]
    cost_initial: float
    cost_start: float
    cost_final: float
    num_steps: int
    result: LMResult
    status: str
    gradient_max: float
    num_accepted: int
    num_rejected: int
    linear_iterations: int
    linear_solver: str
    bucket: tuple[int, int]
    compile_seconds: float
    solve_seconds: float
    inlier_weights: Float[np.ndarray, " e"]
    gnc_iterations: int = 0
    residuals: Float[np.ndarray, "e 7"] | None = None

    @property
    def converged(self) -> bool:
        """True when a stopping test of LM was met (and, with GNC, its weights settled)."""
        return result_index(self.result) in _CONVERGED


_CONVERGED = frozenset(result_index(r) for r in CONVERGED)
_RUNNING = result_index(LMResult.nonlinear_max_steps_reached)


class SolveError(SwiftjaxError, RuntimeError):
    """The solve did not converge (``throw=True``); ``result`` holds the :class:`Result`."""

    def __init__(self, message: str, result: Result):
        super().__init__(message)
        self.result = result


@dataclasses.dataclass(frozen=True)
class _Static:
    damping: str
    initialization: str


def _lm(params: dict[str, Array], static: _Static, solver: AbstractLinearSolver) -> SparseSim3LM:
    return SparseSim3LM(
        rtol=params["rtol"],
        atol=params["atol"],
        gtol=params["gtol"],
        lambda0=params["lambda0"],
        kernel_scale=params["kernel_scale"],
        kernel=params["kernel"],
        linear_solver=solver,
        damping=static.damping,
    )


def _normalized(problem: Problem) -> Problem:
    """The problem with unit quaternions in its poses and measurements."""
    return dataclasses.replace(
        problem, poses=sim3.normalize(problem.poses), measurements=sim3.normalize(problem.measurements)
    )


def _begin(problem: Problem, params: dict[str, Array], solver: AbstractLinearSolver, *, static: _Static):
    """First program of a bucket: ``(normalised problem, LM start, LM's initial state, cost at
    the given poses | None)``.  Unit quaternions exactly (validation allowed ``|q|`` within 1e-3
    of 1); the cost at the given poses is returned when a chordal start moved LM away from them
    (else it is the LM's first linearisation cost)."""
    problem = _normalized(problem)
    start, given = problem.poses, None
    if static.initialization == "chordal":
        start, _ = chordal_initialization(problem, solver)
        given = cost(problem.poses, problem, params["kernel"], params["kernel_scale"])
    lm = _lm(params, static, solver)
    f_struct = jax.eval_shape(residual_fn, start, problem)
    state = lm.init(residual_fn, start, problem, {}, f_struct, None, frozenset())
    return problem, start, state, given


def _step(problem: Problem, params, solver, y, state: LMState, *, static: _Static):
    """One LM iteration in XLA (dense / PCG): ``(y, state)``."""
    y, state, _ = _lm(params, static, solver).step(residual_fn, y, problem, {}, state, frozenset())
    return y, state


def _advance(problem: Problem, params, solver, y, state: LMState, delta, ok, *, static: _Static):
    """One LM iteration with a host-computed ``delta`` (sparse): ``(y, state, next damping)``."""
    lm = _lm(params, static, solver)
    y, state = lm.advance(y, problem, state, delta, jnp.zeros((), jnp.int32), ok)
    return y, state, lm.damping_vector(state)


#: XLA options of the dense path's programs: :data:`swiftjax._compile.QUICK_COMPILE`.  Its
#: buckets are small (``N_bucket <= DENSE_MAX_NODES``), so a first call's time is mostly compile
#: time (docs/performance/posegraph.md).
DENSE_COMPILER_OPTIONS = QUICK_COMPILE


def compiler_options(solver: AbstractLinearSolver) -> dict:
    """XLA compiler options of a bucket's programs (:data:`DENSE_COMPILER_OPTIONS` for the dense path)."""
    return dict(DENSE_COMPILER_OPTIONS) if isinstance(solver, DenseCholesky) else {}


class _Bucket:
    """The compiled programs of one bucket and the host loop that runs them."""

    def __init__(self, padded: Problem, params, solver: AbstractLinearSolver, static: _Static):
        self.static = static
        self.sparse = isinstance(solver, HostSparse)
        begin = jax.jit(functools.partial(_begin, static=static)).lower(padded, params, solver)
        problem, y, state, _ = begin.out_info
        if self.sparse:
            delta = jax.ShapeDtypeStruct((padded.num_nodes, 7), y.dtype)
            ok = jax.ShapeDtypeStruct((), jnp.bool_)
            step = jax.jit(functools.partial(_advance, static=static))
            step = step.lower(problem, params, solver, y, state, delta, ok)
        else:
            step = jax.jit(functools.partial(_step, static=static)).lower(problem, params, solver, y, state)
        options = compiler_options(solver)
        self.begin = begin.compile(compiler_options=options)
        self.step = step.compile(compiler_options=options)

    def solve(self, problem: Problem, params, solver, y, state0: LMState, max_steps: int) -> dict:
        """LM from ``y`` (``state0``: the begin program's initial state, independent of ``y``):
        optimistix's iteration semantics (step 0 only linearises; ``max_steps`` real steps)."""
        state = state0
        executed = 0
        if self.sparse:
            edges, mask, fixed = (np.asarray(a) for a in (problem.edges, problem.edge_mask, problem.fixed))
            dtype = np.dtype(y.dtype)
            delta = np.zeros(y.shape[:1] + (7,), dtype)
            ok = np.asarray(True)
            damping = None  # the first step (it only linearises) returns it before a solve reads it
        while executed <= max_steps and (executed == 0 or result_index(state.result) == _RUNNING):
            if self.sparse:
                if executed:
                    ne = state.lin.ne
                    delta, ok = sparse_direct.solve(
                        np.asarray(ne.diag),
                        np.asarray(ne.off),
                        np.asarray(damping),
                        -np.asarray(ne.grad),
                        edges,
                        mask,
                        fixed,
                    )
                    delta, ok = delta.astype(dtype), np.asarray(ok)
                y, state, damping = self.step(problem, params, solver, y, state, delta, ok)
            else:
                y, state = self.step(problem, params, solver, y, state)
            executed += 1
        return _report(y, state, executed - 1)


def _report(y: Array, st: LMState, num_steps: int) -> dict:
    return {
        "poses": y,
        "num_steps": num_steps,
        "result": st.result,
        "cost_initial": st.cost_initial,
        "cost_final": st.lin.cost,
        "gradient_max": st.grad_inf,
        "num_accepted": st.num_accepted,
        "num_rejected": st.num_rejected,
        "linear_iterations": st.linear_iterations,
        "edge_weights": st.lin.edge_weights,
        "residuals": st.lin.residuals,
    }


_SUMMED = ("num_steps", "num_accepted", "num_rejected", "linear_iterations")


def _weighted(problem: Problem, w: np.ndarray) -> Problem:
    """``Omega_e <- w_e Omega_e`` (GTSAM's ``makeWeightedGraph``), on the host."""
    info = np.asarray(problem.information)
    return dataclasses.replace(problem, information=jnp.asarray(info * w.astype(info.dtype)[:, None, None]))


def _gnc_continuation(lm, problem: Problem, start: Array, params, options: GraphOptions):
    """GTSAM's GNC-TLS loop (:mod:`swiftjax.posegraph.gnc`) around the bucket's LM program.

    Every solve but the last runs at ``rtol = max(rtol, inner_rtol)``; the last one, with the
    final weights, at the caller's tolerances (skipped when they are the same).  The weights are
    computed on the host from the squared whitened residuals at each solve's result.  Returns
    ``(last solve's report with step counts summed, weights [E_bucket], outer iterations, converged)``.
    """
    dtype = np.dtype(start.dtype)
    scale = options.scale
    c2 = np.asarray(scale * scale, dtype)
    information = np.asarray(problem.information)
    robust = np.asarray(problem.robust) & np.asarray(problem.edge_mask)
    mask = np.asarray(problem.edge_mask)

    def squared(out):
        return gnc.squared_residuals(np.asarray(out["residuals"]), information)

    inner = {**params, "rtol": jnp.asarray(max(options.rtol, options.gnc_inner_rtol), dtype)}
    loose = options.gnc_inner_rtol > float(params["rtol"])
    out = lm(problem, start, inner)
    totals = {k: int(out[k]) for k in _SUMMED}
    cost_initial = out["cost_initial"]
    y = out["poses"]
    weights = np.where(mask, 1.0, 0.0)
    weighted = problem
    mu0 = float(gnc.initial_mu(squared(out), robust, c2))
    it, converged = 0, True
    if mu0 > 0:  # else every robust edge is an inlier: the least-squares answer stands
        converged = False
        mu = mu0
        prev_cost = float(out["cost_final"])
        for _ in range(options.gnc_max_iterations):
            it += 1
            sq = squared(out)
            w = np.where(robust, gnc.tls_weights(sq, np.asarray(mu, dtype), c2), 1.0)
            w = np.where(mask, w, 0.0).astype(dtype)
            weighted = _weighted(problem, w)
            out = lm(weighted, start if options.gnc_restart else y, inner)
            y = out["poses"]
            for k in _SUMMED:
                totals[k] += int(out[k])
            weights = np.asarray(w, np.float64)
            cost_now = float(out["cost_final"])
            binary = np.max(np.abs(weights - np.round(weights)), initial=0.0) <= options.gnc_weights_tol
            flat = abs(cost_now - prev_cost) / max(prev_cost, 1e-7) < options.gnc_cost_tol
            if binary or flat:
                converged = True
                break
            mu *= options.gnc_mu_step
            prev_cost = cost_now
    if loose:
        out = lm(weighted, y, params)
        for k in _SUMMED:
            totals[k] += int(out[k])
    return {**out, **totals, "cost_initial": cost_initial}, weights, it, converged


_COMPILED: dict[tuple, _Bucket] = {}


def _resolve_options(options: GraphOptions | None) -> GraphOptions:
    options = GraphOptions() if options is None else options
    if not isinstance(options, GraphOptions):
        raise TypeError(f"options must be a GraphOptions, not {type(options).__name__}")
    return options


def optimize(
    problem: Problem,
    options: GraphOptions | None = None,
    *,
    throw: bool = True,
    pad: bool | tuple[int, int] = True,
) -> Result:
    """Solve the Sim(3) pose graph by Levenberg–Marquardt (see :mod:`swiftjax.posegraph.solver`).

    Args:
        problem: the graph; its ``poses`` are the initial guess and set the dtype (use
            float64 arrays under ``jax.enable_x64(True)`` for kilometre-scale maps; float32
            works and stops at rounding level).
        options: :class:`~swiftjax.posegraph.GraphOptions` (default ``GraphOptions()``; vary
            it with ``GraphOptions(max_steps=20, kernel="gnc")`` or ``options.replace(...)``).
        throw: True: validate the problem on the host first
            (:func:`~swiftjax.posegraph.validate`, a :class:`~swiftjax.posegraph.ProblemError`
            before any work) and raise :class:`SolveError` if the solve does not converge;
            False: no host checks, the outcome is in :attr:`Result.result` / ``converged``.
        pad: pad to the size bucket (compile once per bucket); False compiles for the exact size;
            ``(min_nodes, min_edges)`` pads to the bucket of at least these sizes
            (:func:`~swiftjax.posegraph.problem.padded_sizes`: a growing graph's capacity, so
            that its re-solves share one bucket).

    Returns:
        :class:`Result` with the unpadded poses.

    Raises:
        ProblemError: invalid input (``throw=True``; before any compilation or solve).
        SolveError: the solve did not converge (``throw=True``).
        ValueError: invalid options.
    """
    options = _resolve_options(options)
    raise_on_failure = bool(throw)
    if raise_on_failure:
        validate(problem)
    n, e = problem.num_nodes, problem.num_edges
    nb, eb = padded_sizes(n, e, pad)
    padded = pad_problem(problem, nb, eb)
    valid_edges = None
    if options.linear_solver == "auto":
        valid_edges = np.asarray(problem.edges)[np.asarray(problem.edge_mask)]
    solver_name = choose_linear_solver(nb, options.linear_solver, num_nodes=n, edges=valid_edges)
    dtype = padded.poses.dtype
    solver = linear_solver(
        solver_name, max_iterations=options.max_linear_iterations, eta_max=jnp.asarray(options.eta_max, dtype)
    )
    static = _Static(damping=options.damping, initialization=options.initialization)
    kernel = options.kernel
    params = {
        k: jnp.asarray(v, dtype)
        for k, v in dict(
            rtol=options.rtol,
            atol=options.atol,
            gtol=options.gtol,
            lambda0=options.lambda0,
            kernel_scale=options.scale,
        ).items()
    }
    # GNC's LM solves are weighted least squares: kernel code 0 (the kernel=None program).
    params["kernel"] = jnp.asarray(kernel_code(None if kernel == "gnc" else kernel), jnp.int32)
    key = (nb, eb, str(dtype), static, jax.tree_util.tree_structure(solver))
    compile_seconds = 0.0
    bucket = _COMPILED.get(key)
    if bucket is None:
        t0 = time.perf_counter()
        bucket = _Bucket(padded, params, solver, static)
        compile_seconds = time.perf_counter() - t0
        _COMPILED[key] = bucket
    t0 = time.perf_counter()
    problem_n, start, state0, given = bucket.begin(padded, params, solver)

    def lm(prob, y, prm):
        return bucket.solve(prob, prm, solver, y, state0, options.max_steps)

    gnc_iterations, gnc_converged = 0, True
    if kernel == "gnc":
        out, weights, gnc_iterations, gnc_converged = _gnc_continuation(lm, problem_n, start, params, options)
    else:  # LM's IRLS weights at its last accepted iterate (1 for kernel=None)
        out = lm(problem_n, start, params)
        weights = np.asarray(out["edge_weights"])
    out["cost_given"] = out["cost_initial"] if given is None else given
    out = jax.block_until_ready(out)
    solve_seconds = time.perf_counter() - t0
    result = out["result"]
    status = "max_steps reached" if result_index(result) == _RUNNING else LMResult[result]
    if not gnc_converged:
        result = LMResult.gnc_not_converged
        status = f"GNC: {options.gnc_max_iterations} outer iterations without converged weights or cost"
    res = Result(
        # unpadded on the host (a device slice, or jnp.asarray of the NumPy slice, would
        # compile a program per size n)
        poses=out["poses"] if n == nb else jax.device_put(np.ascontiguousarray(np.asarray(out["poses"])[:n])),
        cost_initial=float(out["cost_given"]),
        cost_start=float(out["cost_initial"]),
        cost_final=float(out["cost_final"]),
        num_steps=int(out["num_steps"]),
        result=result,
        status=status,
        gradient_max=float(out["gradient_max"]),
        num_accepted=int(out["num_accepted"]),
        num_rejected=int(out["num_rejected"]),
        linear_iterations=int(out["linear_iterations"]),
        linear_solver=solver_name,
        bucket=(nb, eb),
        compile_seconds=compile_seconds,
        solve_seconds=solve_seconds,
        inlier_weights=np.asarray(weights, np.float64)[:e],
        gnc_iterations=gnc_iterations,
        residuals=np.asarray(out["residuals"])[:e],
    )
    if raise_on_failure and not res.converged:
        raise SolveError(
            f"pose graph did not converge: {status} after {res.num_steps} steps "
            f"(cost {res.cost_start:.6g} -> {res.cost_final:.6g}); pass throw=False to get the result",
            res,
        )
    return res

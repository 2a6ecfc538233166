"""Host-level entry point: validate, pad to a size bucket, compile once, solve, report.

``optimize(problem)`` is the only function in this package that touches the host: it validates
the concrete problem (clear errors before any work), pads it to a ``(N_bucket, E_bucket)``
size bucket (:func:`swiftjax.posegraph.problem.bucket_size`), looks up — or compiles, timing
it — the jitted solver for that bucket, runs it and unpads the result.

Each bucket is two programs: the start (normalisation, optional chordal initialisation) and the
LM solve (dense/PCG: the whole ``optimistix.least_squares`` loop; sparse: one LM step, looped on
the host around CHOLMOD).  What triggers a compile: a new ``(N_bucket, E_bucket)`` pair, a new
dtype, or a change of the static options (``linear_solver`` as resolved, ``max_steps``,
``max_linear_iterations``, ``damping``, ``initialization``; the dense/PCG solve program does not
depend on ``initialization``, so the persistent cache serves it to both starts).
Tolerances, ``lambda0``, the robust ``kernel`` and ``kernel_scale`` are traced values and never
recompile.  ``kernel="gnc"`` (:mod:`swiftjax.posegraph.gnc`) runs GNC's continuation on the host
around the same LM program (GNC's solves are weighted least squares, kernel code 0), plus one
small weight-update program per bucket: ``mu``, the weights and the threshold are traced values, so the outer
iterations never recompile.  With JAX's persistent compilation cache enabled (the CLI and the test
suite enable it) a bucket compiled by an earlier process is loaded from disk.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax import Array

from swiftjax import sim3
from swiftjax.posegraph.problem import (
    Problem,
    RobustKernel,
    bucket_size,
    kernel_code,
    pad_problem,
    validate,
)
from swiftjax.posegraph import gnc, sparse_direct
from swiftjax.posegraph.factors import cost
from swiftjax.posegraph.initialization import chordal_initialization
from swiftjax.posegraph.solver import STATUS, SparseSim3LM, residual_fn

__all__ = [
    "optimize",
    "Result",
    "choose_linear_solver",
    "node_fill_ratio",
    "DENSE_MAX_NODES",
    "SPARSE_MAX_CYCLE_FRACTION",
    "SPARSE_MAX_FILL",
]

LinearSolver = Literal["auto", "dense", "pcg", "sparse"]

#: Largest padded node count for which "auto" picks the dense Cholesky (7 N <= 448 rows).
#: Measured (circle graph, N = 100, bucket 112): one dense Cholesky 68 ms vs one PCG solve 3.7 ms.
DENSE_MAX_NODES = 64


@dataclasses.dataclass(frozen=True)
class Result:
    """Outcome of :func:`optimize` (host values; ``poses`` is a JAX array ``[N, 8]``).

    ``cost_*`` are ``1/2 sum rho(r^T Omega r)`` (GTSAM's ``graph.error`` definition):
    ``cost_initial`` at the given poses, ``cost_start`` where LM started (after the chordal
    initialisation, else the same), ``cost_final`` at the result.
    ``converged`` is True when a stopping test (``status``) was met; False when ``max_steps``
    ran out or the damping stalled.  ``compile_seconds`` is 0 when the bucket was already
    compiled in this process.

    ``inlier_weights`` ``[E]`` (NumPy float64): with ``kernel="gnc"`` the GNC-TLS weights of the
    final solve (1 inlier, 0 outlier, in between only if the continuation stopped early); with
    Huber/Cauchy the IRLS weight ``rho'(s_e)`` at the result; 1 for every edge not flagged
    ``robust`` and for ``kernel=None``.  ``gnc_iterations``: GNC outer iterations (weighted LM
    solves after the first, unweighted one); 0 otherwise.  With GNC, ``num_steps``,
    ``num_accepted``, ``num_rejected`` and ``linear_iterations`` are summed over every LM solve,
    ``cost_start`` is the first (unweighted) solve's start cost and ``cost_final`` the last solve's
    weighted cost ``1/2 sum w_e s_e`` (binary weights: the TLS cost without its constant
    ``c^2 / 2`` per rejected edge).
    """

    poses: Array
    cost_initial: float
    cost_start: float
    cost_final: float
    num_steps: int
    converged: bool
    status: str
    gradient_max: float
    num_accepted: int
    num_rejected: int
    linear_iterations: int
    linear_solver: str
    bucket: tuple[int, int]
    compile_seconds: float
    solve_seconds: float
    inlier_weights: np.ndarray
    gnc_iterations: int = 0


@dataclasses.dataclass(frozen=True)
class _Static:
    max_steps: int
    linear_solver: str
    max_linear_iterations: int
    damping: str
    initialization: str


def _solver(params: dict[str, Array], static: _Static) -> SparseSim3LM:
    return SparseSim3LM(
        rtol=params["rtol"],
        atol=params["atol"],
        gtol=params["gtol"],
        lambda0=params["lambda0"],
        eta_max=params["eta_max"],
        kernel_scale=params["kernel_scale"],
        kernel=params["kernel"],
        linear_solver=static.linear_solver,
        max_linear_iterations=static.max_linear_iterations,
        damping=static.damping,
    )


def _start(problem: Problem, *, static: _Static) -> tuple[Problem, Array]:
    """Unit quaternions exactly (validation allowed ``|q|`` within 1e-3 of 1), and the LM start
    (the given poses or the chordal initialisation)."""
    problem = _normalized(problem)
    start = problem.poses
    if static.initialization == "chordal":
        start, _ = chordal_initialization(problem, static.linear_solver, static.max_linear_iterations)
    return problem, start


def _report(y: Array, st, num_steps: Array, cost_given: Array) -> dict[str, Array]:
    return {
        "poses": y,
        "num_steps": num_steps,
        "status": st.status,
        "cost_given": cost_given,
        "cost_initial": st.cost_initial,
        "cost_final": st.lin.cost,
        "gradient_max": st.grad_inf,
        "num_accepted": st.num_accepted,
        "num_rejected": st.num_rejected,
        "linear_iterations": st.linear_iterations,
        "edge_weights": st.lin.edge_weights,
    }


def _chordal_cost_given(problem: Problem, params, static: _Static) -> Array | None:
    """Cost at the given poses when a chordal start moved LM away from them; else None (it is
    then the LM's first linearisation cost, ``cost_initial``)."""
    if static.initialization == "chordal":
        return cost(problem.poses, problem, params["kernel"], params["kernel_scale"])
    return None


def _begin(problem: Problem, params: dict[str, Array], *, static: _Static):
    """First program of a bucket: ``(normalised problem, LM start, cost at the given poses | None)``
    (the sparse path's :func:`_host_begin` adds LM's initial state)."""
    problem, start = _start(problem, static=static)
    return problem, start, _chordal_cost_given(problem, params, static)


def _solve(problem: Problem, start: Array, params: dict[str, Array], *, static: _Static) -> dict[str, Array]:
    """Dense/PCG path, second program: ``optimistix.least_squares`` with :class:`SparseSim3LM` from
    ``start``.  It does not depend on the initialisation, so both starts share it (and its cache
    entry), and each program compiles in less time than the two together."""
    # optimistix's step 0 only linearises (cost at the start, no move), so max_steps LM steps
    # are max_steps + 1 optimistix steps: max_steps = 0 still reports the true initial cost.
    sol = optx.least_squares(
        residual_fn, _solver(params, static), start, args=problem, max_steps=static.max_steps + 1, throw=False
    )
    st = sol.state
    return _report(sol.value, st, sol.stats["num_steps"] - 1, st.cost_initial)


# The "sparse" path: the LM loop runs on the host around two cacheable XLA programs, and the
# linear solve is a plain NumPy call (no ``pure_callback`` inside the compiled programs: JAX
# does not put programs with host callbacks in its persistent compilation cache, so every
# process would recompile them — measured 8-10 s on the pipeline's 101-chunk graph).


def _host_begin(problem: Problem, params: dict[str, Array], *, static: _Static):
    """Normalise and start (chordal or given): ``(problem, start, state, damping, cost_given | None)``.

    No linearisation here (the first :func:`_host_advance`, with ``delta = 0``, is LM's step 0),
    so the residual/Jacobian code is compiled once, in the advance program.
    """
    problem, start, given = _begin(problem, params, static=static)
    solver = _solver(params, static)
    f_struct = jax.eval_shape(residual_fn, start, problem)
    state = solver.init(residual_fn, start, problem, {}, f_struct, None, frozenset())
    return problem, start, state, solver.damping_vector(state), given


def _host_advance(problem: Problem, params: dict[str, Array], y, state, delta, ok, *, static: _Static):
    """One LM step with a host-computed ``delta``: ``(y, state, next damping)``."""
    solver = _solver(params, static)
    y, state = solver.advance(y, problem, state, delta, jnp.zeros((), jnp.int32), ok)
    return y, state, solver.damping_vector(state)


def _host_solve(advance_c, problem: Problem, params, y, state, damping, static: _Static) -> dict:
    """Run the LM iterations from ``y`` with :func:`swiftjax.posegraph.sparse_direct.solve` on the
    host.  ``state``/``damping`` are LM's initial state from the begin program (it does not depend
    on the start poses, so GNC's outer iterations reuse it)."""
    edges, mask, fixed = (np.asarray(a) for a in (problem.edges, problem.edge_mask, problem.fixed))
    dtype = np.dtype(y.dtype)
    # The first advance is step 0: it only linearises (its delta is ignored, so nothing is solved).
    y, state, damping = advance_c(problem, params, y, state, np.zeros(y.shape[:1] + (7,), dtype), np.asarray(True))
    steps = 0
    while steps < static.max_steps and int(state.status) == 0:
        ne = state.lin.ne
        delta, ok = sparse_direct.solve(
            np.asarray(ne.diag), np.asarray(ne.off), np.asarray(damping), -np.asarray(ne.grad), edges, mask, fixed
        )
        y, state, damping = advance_c(problem, params, y, state, delta.astype(dtype), np.asarray(ok))
        steps += 1
    return _report(y, state, steps, state.cost_initial)


def _prepare(compiled, padded: Problem, params, static: _Static):
    """Run a bucket's first program: ``(normalised problem, LM start, cost at the given poses | None,
    lm)`` where ``lm(problem, y, params)`` runs LM from ``y`` (same graph structure, any
    information: GNC's weighted graphs) and returns :func:`_report`'s dict."""
    if static.linear_solver == "sparse":
        begin_c, advance_c = compiled
        problem_n, start, state0, damping0, given = begin_c(padded, params)

        def lm(problem, y, prm):
            return _host_solve(advance_c, problem, prm, y, state0, damping0, static)

        return problem_n, start, given, lm
    begin_c, solve_c = compiled
    problem_n, start, given = begin_c(padded, params)
    return problem_n, start, given, solve_c


def _normalized(problem: Problem) -> Problem:
    """The problem with unit quaternions in its poses and measurements."""
    return Problem(
        poses=sim3.normalize(problem.poses),
        edges=problem.edges,
        measurements=sim3.normalize(problem.measurements),
        information=problem.information,
        fixed=problem.fixed,
        robust=problem.robust,
        edge_mask=problem.edge_mask,
    )


def _gnc_program(problem: Problem, poses: Array, mu: Array, c2: Array):
    """At ``poses``: ``(GNC weights, weighted problem, mu_0)`` (one compile per bucket; all traced)."""
    sq, w, weighted = gnc.weight_update(problem, poses, mu, c2)
    return w, weighted, gnc.initial_mu(sq, problem.robust & problem.edge_mask, c2)


_SUMMED = ("num_steps", "num_accepted", "num_rejected", "linear_iterations")


def _gnc_continuation(lm, update_c, problem: Problem, start: Array, params, scale: float, options: dict):
    """GTSAM's GNC-TLS loop (:mod:`swiftjax.posegraph.gnc`) around the bucket's LM program.

    Every solve but the last runs at ``rtol = max(rtol, inner_rtol)``; the last one, with the
    final weights, at the caller's tolerances (skipped when they are the same).  Returns
    ``(last solve's report with step counts summed, weights [E_bucket], outer iterations, converged)``.
    """
    dtype = start.dtype
    c2 = jnp.asarray(scale * scale, dtype)
    inner = {**params, "rtol": jnp.maximum(params["rtol"], jnp.asarray(options["inner_rtol"], dtype))}
    loose = options["inner_rtol"] > float(params["rtol"])
    out = lm(problem, start, inner)
    totals = {k: int(out[k]) for k in _SUMMED}
    cost_initial = out["cost_initial"]
    y = out["poses"]
    weights = np.where(np.asarray(problem.edge_mask), 1.0, 0.0)
    weighted = problem
    _, _, mu0 = update_c(problem, y, jnp.asarray(1.0, dtype), c2)
    mu = float(mu0)
    it, converged = 0, True
    if mu > 0:  # else every robust edge is an inlier of the least-squares solution
        prev_cost = float(out["cost_final"])
        converged = False
        while it < options["max_iterations"]:
            it += 1
            w, weighted, _ = update_c(problem, y, jnp.asarray(mu, dtype), c2)
            out = lm(weighted, start if options["restart"] else y, inner)
            y = out["poses"]
            for k in _SUMMED:
                totals[k] += int(out[k])
            weights = np.asarray(w, np.float64)
            cost = float(out["cost_final"])
            binary = np.max(np.abs(weights - np.round(weights)), initial=0.0) <= options["weights_tol"]
            flat = abs(cost - prev_cost) / max(prev_cost, 1e-7) < options["cost_tol"]
            if binary or flat:
                converged = True
                break
            mu *= options["mu_step"]
            prev_cost = cost
    if loose:
        out = lm(weighted, y, params)
        for k in _SUMMED:
            totals[k] += int(out[k])
    return {**out, **totals, "cost_initial": cost_initial}, weights, it, converged


_COMPILED: dict[tuple, object] = {}


def _compile(padded: Problem, params: dict[str, Array], static: _Static):
    """AOT-compile the two programs of one bucket: start + solve (dense/PCG), begin + advance (sparse)."""
    if static.linear_solver != "sparse":
        begin = jax.jit(functools.partial(_begin, static=static)).lower(padded, params)
        problem, start, _ = begin.out_info
        lm_static = dataclasses.replace(static, initialization="none")
        solve = jax.jit(functools.partial(_solve, static=lm_static)).lower(problem, start, params)
        return begin.compile(), solve.compile()
    begin = jax.jit(functools.partial(_host_begin, static=static)).lower(padded, params)
    problem, y, state, _, _ = begin.out_info
    delta = jax.ShapeDtypeStruct((padded.num_nodes, 7), y.dtype)
    ok = jax.ShapeDtypeStruct((), jnp.bool_)
    advance = jax.jit(functools.partial(_host_advance, static=static))
    advance_c = advance.lower(problem, params, y, state, delta, ok).compile()
    begin_c = begin.compile()
    return begin_c, advance_c


#: "auto" picks the host sparse direct solver when the graph's cycle rank ``E - N + 1`` is at
#: most this fraction of ``N`` (a chain with few loops: small fill-in, poor PCG conditioning) ...
SPARSE_MAX_CYCLE_FRACTION = 0.05
#: ... or, for ``N <= FILL_ESTIMATE_MAX_NODES``, when the COLAMD factor of the node graph has at
#: most ``SPARSE_MAX_FILL`` times the entries of the graph.  Measured node-level fill ratios:
#: KITTI-like chains 1.5-1.9, parking-garage 2.1, smallGrid3D 5.7, random-loop circles 9.8
#: (N = 200), 15.5 (400), 40 (1,000), 203 (5,000), sphere2500 10.9.  With CHOLMOD (chordal start,
#: ``bench/bench_posegraph.py``): sphere2500 sparse 0.52 s vs PCG 3.0 s; circles sparse/PCG 0.036/0.030 s
#: (N = 200), 0.115/0.094 s (400), 0.66/0.20 s (1,000) — random loops make the graph an expander,
#: which PCG likes and a factorisation does not.  With SuperLU (no cvxopt) the direct solve is
#: 10-30x slower, hence the lower threshold.
SPARSE_MAX_FILL = 12.0 if sparse_direct.BACKEND == "cholmod" else 4.0
FILL_ESTIMATE_MAX_NODES = 3000


def node_fill_ratio(num_nodes: int, edges) -> float:
    """``nnz(L + U) / (N + 2E)`` of SuperLU (COLAMD) on the node graph's ``A + A^T + cI`` (host)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    e = np.asarray(edges)
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(num_nodes, num_nodes))
    a = (a + a.T + sp.eye(num_nodes) * (len(e) + 1.0)).tocsc()
    lu = sla.splu(a, permc_spec="COLAMD", options=dict(SymmetricMode=True))
    return (lu.L.nnz + lu.U.nnz) / (num_nodes + 2 * len(e))


def choose_linear_solver(
    num_nodes_padded: int, requested: str = "auto", *, num_nodes: int | None = None, edges=None
) -> str:
    """Resolve ``"auto"``: dense Cholesky for ``N_bucket <= DENSE_MAX_NODES``; else the host
    sparse solver when the factor stays sparse (cycle rank or fill rule above); else
    block-Jacobi PCG.  Any other ``requested`` value is returned as is (validated)."""
    if requested != "auto":
        if requested not in ("dense", "pcg", "sparse"):
            raise ValueError(f"linear_solver must be 'auto', 'dense', 'pcg' or 'sparse', not {requested!r}")
        return requested
    if num_nodes_padded <= DENSE_MAX_NODES:
        return "dense"
    if num_nodes is not None and edges is not None:
        if len(edges) - num_nodes + 1 <= SPARSE_MAX_CYCLE_FRACTION * num_nodes:
            return "sparse"
        if num_nodes <= FILL_ESTIMATE_MAX_NODES and node_fill_ratio(num_nodes, edges) <= SPARSE_MAX_FILL:
            return "sparse"
    return "pcg"


def optimize(
    problem: Problem,
    *,
    max_steps: int = 100,
    rtol: float = 1e-10,
    atol: float = 0.0,
    gtol: float = 1e-10,
    lambda0: float = 1e-5,
    damping: Literal["identity", "marquardt"] = "identity",
    initialization: Literal["none", "chordal"] = "none",
    linear_solver: LinearSolver = "auto",
    max_linear_iterations: int = 1000,
    eta_max: float = 1e-4,
    kernel: RobustKernel | Literal["gnc"] | None = None,
    kernel_scale: float | None = None,
    gnc_max_iterations: int = 100,
    gnc_mu_step: float = 1.4,
    gnc_weights_tol: float = 1e-4,
    gnc_cost_tol: float = 1e-5,
    gnc_inner_rtol: float = 1e-5,
    gnc_restart: bool = True,
    pad: bool = True,
    check: bool = True,
) -> Result:
    """Solve the Sim(3) pose graph by Levenberg–Marquardt (see :mod:`swiftjax.posegraph.solver`).

    Args:
        problem: the graph; its ``poses`` are the initial guess and set the dtype (use
            float64 arrays under ``jax.enable_x64(True)`` for kilometre-scale maps; float32
            works and stops at rounding level).
        max_steps: LM iterations (accepted + rejected); static.
        rtol, atol: stop on an accepted step whose cost decrease is ``<= rtol * cost`` or
            ``<= atol`` (GTSAM's ``relativeErrorTol`` / ``absoluteErrorTol``).
        gtol: stop when ``|g|_inf <= gtol * |g_0|_inf``.
        lambda0: initial damping ``lambda``.
        damping: ``"identity"`` damps with ``lambda I`` (GTSAM's default, in tangent units);
            ``"marquardt"`` with ``lambda clip(diag H)``.  Measured (``bench/bench_posegraph.py``):
            Marquardt scaling cripples the first steps on chains, whose lever arms make the
            rotation entries of ``diag H`` ~1e9 while the rigid-rotation directions are the
            weakest of ``H`` (KITTI-like chain N = 2,000: 54 steps vs 9 with ``lambda I``).
        initialization: ``"none"`` starts LM at ``problem.poses``; ``"chordal"`` first solves the
            three linear problems of :mod:`swiftjax.posegraph.initialization` (rotations by chordal
            relaxation, log-scales, translations) and starts there.  Measured (``bench/bench_posegraph.py``):
            synthetic circle N = 5,000 from dead reckoning: LM alone stops in a local minimum
            (cost 87,536); chordal first reaches the global one (17,500) in 4 steps.  Robust
            kernels do not enter the initialisation: keep ``"none"`` when the given poses are
            good and some loops may be false (the pipeline's case).
        linear_solver: ``"auto"`` (:func:`choose_linear_solver`), ``"dense"``, ``"pcg"`` or
            ``"sparse"`` (:mod:`swiftjax.posegraph.sparse_direct`: CHOLMOD, or SuperLU without
            cvxopt, with the LM loop on the host around two compiled programs).
        max_linear_iterations: PCG cap per LM step (static).
        eta_max: loosest PCG relative tolerance (Eisenstat–Walker forcing ``eta = min(eta_max,
            sqrt(|g|/|g0|))``).  Measured on the N = 5,000 circle from dead reckoning: 1e-2
            and 1e-3 stall (99 LM steps, cost 1.2e7 / 1.4e7), 1e-4 converges in 31 steps; from
            the chordal start 1e-3 would save 20 % (1,061 vs 1,333 PCG iterations).
        kernel, kernel_scale: robust treatment of the edges flagged ``problem.robust``, scale in
            whitened units (``sqrt(r^T Omega r)``): ``"huber"``/``"cauchy"`` (IRLS inside LM; scale
            default 1) or ``"gnc"``: graduated non-convexity with truncated least squares
            (:mod:`swiftjax.posegraph.gnc`), ``kernel_scale`` the inlier threshold ``c`` (an
            edge with ``r^T Omega r > c^2`` is rejected), default :data:`~swiftjax.posegraph.gnc.DEFAULT_SCALE`
            ``= sqrt(chi2_7^-1(0.99))``, right when the information matches the noise.  Edges not
            flagged robust are never down-weighted.
        gnc_max_iterations, gnc_mu_step, gnc_weights_tol, gnc_cost_tol: GNC's outer loop (GTSAM's
            ``maxIterations``, ``muStep``, ``weightsTol``, ``relativeCostTol``; same defaults): stop
            when every weight is within ``weights_tol`` of 0 or 1 or the weighted cost changes by
            less than ``cost_tol`` relative; ``converged`` is False if neither happens in
            ``gnc_max_iterations``.  GNC runs the bucket's LM program (the very program of
            ``kernel=None``: nothing more to compile for LM) once unweighted and then once per
            outer iteration, plus one small compiled weight-update program per bucket; ``mu``,
            the weights and ``kernel_scale`` are traced, so no outer iteration and no new
            threshold recompiles.
        gnc_inner_rtol: ``rtol`` of every GNC solve but the last (GTSAM's LM default 1e-5, which
            its GNC uses throughout); the last solve, with the final weights, runs at ``rtol``.
            Measured on the KITTI-like chunk graph (``bench/_robust_graph.py``): 1e-5 instead of
            ``rtol`` = 1e-10 takes 30-40 % fewer LM steps, same answer.
        gnc_restart: start every weighted solve at the start poses (GTSAM's choice) rather than
            at the previous solve's result.  Measured there with unit information and 10/20
            false loops: warm starts end 7-66 % of the extent off (an early, bent solve's basin
            keeps the false loops' pull), restarts 1.8-3 %; with matched information both are
            exact.
        pad: pad to the size bucket (compile once per bucket); False compiles for the exact size.
        check: validate the problem on the host first (:func:`~swiftjax.posegraph.validate`).

    Returns:
        :class:`Result` with the unpadded poses.

    Raises:
        ProblemError: invalid input (before any compilation or solve).
    """
    if check:
        validate(problem)
    if int(max_steps) != max_steps or max_steps < 0:
        raise ValueError(f"max_steps must be an integer >= 0, not {max_steps!r}")
    if initialization not in ("none", "chordal"):
        raise ValueError(f"initialization must be 'none' or 'chordal', not {initialization!r}")
    if damping not in ("identity", "marquardt"):
        raise ValueError(f"damping must be 'identity' or 'marquardt', not {damping!r}")
    if kernel not in (None, "huber", "cauchy", "gnc"):
        raise ValueError(f"kernel must be None, 'huber', 'cauchy' or 'gnc', not {kernel!r}")
    if kernel_scale is None:
        kernel_scale = gnc.DEFAULT_SCALE if kernel == "gnc" else 1.0
    scale = float(kernel_scale)
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"kernel_scale must be a positive finite number, not {kernel_scale!r}")
    gnc_options = dict(
        max_iterations=int(gnc_max_iterations), mu_step=float(gnc_mu_step),
        weights_tol=float(gnc_weights_tol), cost_tol=float(gnc_cost_tol),
        inner_rtol=float(gnc_inner_rtol), restart=bool(gnc_restart),
    )
    if kernel == "gnc" and not (gnc_options["mu_step"] > 1 and gnc_options["max_iterations"] >= 1):
        raise ValueError(
            f"GNC needs gnc_mu_step > 1 and gnc_max_iterations >= 1, got {gnc_mu_step!r}, {gnc_max_iterations!r}"
        )
    n, e = problem.num_nodes, problem.num_edges
    nb, eb = (bucket_size(n), bucket_size(e)) if pad else (n, e)
    padded = pad_problem(problem, nb, eb)
    if linear_solver == "auto":
        valid_edges = np.asarray(problem.edges)[np.asarray(problem.edge_mask)]
    else:
        valid_edges = None
    solver_name = choose_linear_solver(nb, linear_solver, num_nodes=n, edges=valid_edges)
    static = _Static(
        max_steps=int(max_steps),
        linear_solver=solver_name,
        max_linear_iterations=int(max_linear_iterations),
        damping=damping,
        initialization=initialization,
    )
    dtype = padded.poses.dtype
    params = {
        k: jnp.asarray(v, dtype)
        for k, v in dict(
            rtol=rtol, atol=atol, gtol=gtol, lambda0=lambda0, eta_max=eta_max, kernel_scale=scale
        ).items()
    }
    # GNC's LM solves are weighted least squares: kernel code 0 (the kernel=None program).
    params["kernel"] = jnp.asarray(kernel_code(None if kernel == "gnc" else kernel), jnp.int32)
    key = (nb, eb, str(dtype), static)
    compile_seconds = 0.0
    compiled = _COMPILED.get(key)
    if compiled is None:
        t0 = time.perf_counter()
        compiled = _compile(padded, params, static)
        compile_seconds = time.perf_counter() - t0
        _COMPILED[key] = compiled
    if kernel == "gnc":
        ukey = ("gnc", nb, eb, str(dtype))
        update_c = _COMPILED.get(ukey)
        if update_c is None:
            t0 = time.perf_counter()
            c2 = jnp.asarray(1.0, dtype)
            update_c = jax.jit(_gnc_program).lower(padded, padded.poses, c2, c2).compile()
            compile_seconds += time.perf_counter() - t0
            _COMPILED[ukey] = update_c
    t0 = time.perf_counter()
    problem_n, start, given, lm = _prepare(compiled, padded, params, static)
    gnc_iterations, gnc_converged = 0, True
    if kernel == "gnc":
        out, weights, gnc_iterations, gnc_converged = _gnc_continuation(
            lm, update_c, problem_n, start, params, scale, gnc_options
        )
    else:  # LM's IRLS weights at its last accepted iterate (1 for kernel=None)
        out = lm(problem_n, start, params)
        weights = np.asarray(out["edge_weights"])
    if given is not None:
        out["cost_given"] = given
    out = jax.block_until_ready(out)
    solve_seconds = time.perf_counter() - t0
    status_code = int(out["status"])
    status = STATUS[status_code] if status_code else "max_steps reached"
    converged = status_code in (1, 2, 3, 4)
    if not gnc_converged:
        status = f"GNC: {gnc_options['max_iterations']} outer iterations without converged weights or cost"
        converged = False
    return Result(
        poses=out["poses"][:n],
        cost_initial=float(out["cost_given"]),
        cost_start=float(out["cost_initial"]),
        cost_final=float(out["cost_final"]),
        num_steps=int(out["num_steps"]),
        converged=converged,
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
    )

"""Chordal initialisation of a Sim(3) pose graph: three linear least-squares problems.

Levenberg–Marquardt converges to the minimum nearest its starting point.  Dead reckoning
(composing odometry) is a poor start for large graphs with many loops: rotation errors grow
along the chain and the loop residuals wrap around ``pi``, and LM stops in a local minimum
(``docs/performance/posegraph.md`` has the numbers).  The standard remedy (Carlone et al., "Initialization techniques for 3D SLAM",
ICRA 2015 — GTSAM's ``InitializePose3``; Martinec & Pajdla 2007) relaxes ``SO(3)`` to ``R^{3x3}``,
which makes every problem linear.  With ``Z_e = S_i^-1 S_j`` for every edge ``e = (i, j)``::

    1. rotations:  min sum_e w_R |R_j - R_i R_Ze|_F^2          then project each R to SO(3) (SVD)
    2. log-scales: min sum_e w_s (l_j - l_i - log s_Ze)^2
    3. translations: min sum_e w_t / s_i^2 |t_j - t_i - s_i R_i t_Ze|^2

with fixed nodes held at their given values (they anchor every problem, so each is positive
definite on a connected graph — which :func:`~swiftjax.posegraph.validate` guarantees).  Each is
a "difference" system ``r_e = x_j - A_e x_i - c_e`` (``J_j = I``, ``J_i = -A_e``) on the same
graph, solved by one Gauss–Newton step from the given values with the LM solver's linear solver
(block size 9, 1 and 3).  Weights: ``w_R`` = mean of the rotation diagonal of ``Omega_e``,
``w_s`` its scale entry, ``w_t`` the mean translation diagonal; masked edges get zero weight.
Robust kernels are not applied here (a false loop distorts the start; LM with the kernel then
works from it).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Bool, Float

from swiftjax import sim3, so3
from swiftjax.posegraph import linear
from swiftjax.posegraph.blockmat import bmtm, bmtv, bmv
from swiftjax.posegraph.linear_solvers import AbstractLinearSolver
from swiftjax.posegraph.linear_solvers import linear_solver as make_linear_solver
from swiftjax.posegraph.problem import Problem, bucket_size

__all__ = ["chordal_initialization", "solve_difference_system"]


def solve_difference_system(
    x0: Float[Array, "n b"],
    a: Float[Array, "e b b"] | None,
    c: Float[Array, "e b"],
    weight: Float[Array, " e"],
    problem: Problem,
    linear_solver: AbstractLinearSolver | str,
    max_linear_iterations: int | None = None,
) -> tuple[Float[Array, "n b"], Bool[Array, ""]]:
    """Minimise ``sum_e w_e |x_j - A_e x_i - c_e|^2`` over the free nodes, fixed nodes at ``x0``.

    Args:
        x0: ``[N, b]`` values (fixed nodes keep theirs; free ones are the linearisation point,
            irrelevant for this linear problem).
        a: ``[E, b, b]`` or None for ``A_e = I``.
        c: ``[E, b]``.
        weight: ``[E]`` (zero for masked edges).
        problem: supplies ``edges`` and ``fixed``.
        linear_solver: a solver object of :mod:`swiftjax.posegraph.linear_solvers` (static
            settings) or its name (then ``max_linear_iterations`` caps PCG).  PCG runs to a
            relative residual of ``1e-10``.

    Returns:
        ``(x [N, b], ok)``.
    """
    solver = _as_solver(linear_solver, max_linear_iterations)
    edges, fixed = problem.edges, problem.fixed
    n, b = x0.shape
    dtype = x0.dtype
    xi, xj = x0[edges[:, 0]], x0[edges[:, 1]]
    w = weight.astype(dtype)
    if a is None:  # A = I
        r = xj - xi - c
        at = h_ii = jnp.broadcast_to(jnp.eye(b, dtype=dtype), (edges.shape[0], b, b))
        at_r = r
    else:
        r = xj - bmv(a, xi) - c
        at, h_ii, at_r = jnp.swapaxes(a, 1, 2), bmtm(a, a), bmtv(a, r)
    # J_j = I, J_i = -A:  H_jj = w I, H_ij = -w A^T, H_ii = w A^T A, g_j = w r, g_i = -w A^T r.
    wb = w[:, None, None]
    ne = linear.from_edge_blocks(
        wb * h_ii, wb * jnp.eye(b, dtype=dtype), -wb * at, -w[:, None] * at_r, w[:, None] * r, edges, fixed
    )
    damping = jnp.zeros((n, b), dtype)
    delta, _, ok = solver.solve(ne, damping, rtol=1e-10, fixed=fixed, active=problem.edge_mask)
    return x0 + delta, ok


def _as_solver(linear_solver, max_linear_iterations: int | None) -> AbstractLinearSolver:
    if isinstance(linear_solver, AbstractLinearSolver):
        return linear_solver
    return make_linear_solver(linear_solver, max_iterations=max_linear_iterations)


def _project_to_so3(m: Float[Array, "*n 3 3"]) -> Float[Array, "*n 3 3"]:
    """Nearest rotation (Frobenius) of each ``[..., 3, 3]``: ``U diag(1, 1, det(U V^T)) V^T``
    (:func:`swiftjax.so3.project`)."""
    return so3.as_matrix(so3.project(m))


def chordal_initialization(
    problem: Problem, linear_solver: AbstractLinearSolver | str = "sparse", max_linear_iterations: int | None = None
) -> tuple[Float[Array, "n 8"], Bool[Array, ""]]:
    """Initial poses ``[N, 8]`` from the three linear problems of the module docstring.

    Pure and jit-able (``linear_solver``: a solver object or its name; ``max_linear_iterations``
    caps PCG when a name is given).  Returns ``(poses, ok)``; where a linear solve fails (``ok``
    False) the given poses are returned.
    """
    linear_solver = _as_solver(linear_solver, max_linear_iterations)
    poses = problem.poses
    info = problem.information
    mask = problem.edge_mask.astype(poses.dtype)
    diag = jnp.diagonal(info, axis1=1, axis2=2)
    w_t = jnp.mean(diag[:, 0:3], axis=1) * mask
    w_r = jnp.mean(diag[:, 3:6], axis=1) * mask
    w_s = diag[:, 6] * mask
    r_z, t_z, s_z = sim3.to_rst(problem.measurements)
    r0, t0, s0 = sim3.to_rst(poses)
    e = problem.edges.shape[0]

    # 1. rotations, x = row-major vec(R): row k of R_j is (row k of R_i) R_z, i.e. A = I_3 (x) R_z^T.
    a_rot = jnp.einsum("kl,eab->ekalb", jnp.eye(3, dtype=poses.dtype), jnp.swapaxes(r_z, 1, 2)).reshape(e, 9, 9)
    x_rot, ok_r = solve_difference_system(
        r0.reshape(-1, 9), a_rot, jnp.zeros((e, 9), poses.dtype), w_r, problem, linear_solver
    )
    rot = _project_to_so3(x_rot.reshape(-1, 3, 3))
    rot = jnp.where(problem.fixed[:, None, None], r0, rot)

    # 2. log-scales.
    log_s, ok_s = solve_difference_system(
        jnp.log(s0)[:, None], None, jnp.log(s_z)[:, None], w_s, problem, linear_solver
    )
    scale = jnp.exp(log_s[:, 0])

    # 3. translations: t_j - t_i = s_i R_i t_z, weighted by 1 / s_i^2 (residual in node i's units).
    i = problem.edges[:, 0]
    c_t = scale[i, None] * bmv(rot[i], t_z)
    trans, ok_t = solve_difference_system(t0, None, c_t, w_t / scale[i] ** 2, problem, linear_solver)
    ok = ok_r & ok_s & ok_t
    out = sim3.normalize(sim3.from_rst(rot, trans, scale))
    out = jnp.where(problem.fixed[:, None], poses, out)
    return jnp.where(ok, out, poses), ok


def _chain_step(s: jax.Array, r: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One link of :func:`chain_poses` (module level: the scan's trace and compile are cached
    per length; a closure made per call compiled the scan at every call, ~0.5 s)."""
    nxt = sim3.normalize(sim3.compose(s, r))
    return nxt, nxt


def chain_poses(relative: Float[ArrayLike, "t 8"], *, pad: bool = True) -> Float[np.ndarray, "t+1 8"]:
    """Dead reckoning along a chain: ``S_0 = I, S_{t+1} = S_t S_{t->t+1}``, renormalised.

    ``relative [T-1, 8]`` (edge ``t`` maps node ``t+1`` into node ``t``) -> ``[T, 8]``
    float64 node-to-world poses (host in/out, a ``lax.scan`` in float64 inside; the
    pipeline's start for the pose graph and its "no loop closure" trajectory).

    ``pad``: the scan runs over :func:`~swiftjax.posegraph.problem.bucket_size` ``(T - 1)``
    links, identity links after the given ones (their outputs are dropped), so a chain that
    grows by one chunk per call (an online run) compiles once per bucket, not per length; the
    scan is sequential, so the first ``T`` poses are those of the exact-length scan.
    """
    relative = np.asarray(relative, np.float64).reshape(-1, 8)
    links = relative.shape[0]
    with jax.enable_x64(True):
        first = sim3.identity((), jnp.float64)
        if links == 0:
            return np.asarray(first)[None]
        if pad:
            ident = np.array([0, 0, 0, 0, 0, 0, 1, 1], np.float64)
            relative = np.concatenate([relative, np.broadcast_to(ident, (bucket_size(links) - links, 8))])
        _, rest = jax.lax.scan(_chain_step, first, jnp.asarray(relative))
        return np.concatenate([np.asarray(first)[None], np.asarray(rest)[:links]], axis=0)

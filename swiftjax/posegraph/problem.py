"""The Sim(3) pose-graph problem: data, host-side validation and size buckets.

A pose graph has ``N`` nodes (chunk-to-world transforms ``S_n``, ``[N, 8]``) and ``E`` edges
``(i, j)`` with a measurement ``Z_ij ~ S_i^-1 S_j`` (``[E, 8]``: the edge maps chunk ``j``
coordinates into chunk ``i`` coordinates) and an information matrix
``Omega_ij`` (``[E, 7, 7]``, in our tangent order ``(rho, omega, sigma)``).  The cost is
(paper sec. 3.4; the same definition as GTSAM's ``graph.error``)::

    C(S) = 1/2 sum_e  rho_e( r_e^T Omega_e r_e ),    r_e = log(Z_e^-1 S_i^-1 S_j)   (7-D)

with ``rho_e(s) = s`` for ordinary edges and a robust kernel (:mod:`swiftjax.posegraph.kernels`:
Huber or Cauchy, scale ``k`` in whitened units) for the edges flagged robust (typically the loop
edges: a false loop is the method's documented failure mode).

Padding (``pad_problem``): the jitted solver compiles once per ``(N_bucket, E_bucket, dtype,
options)``.  Padded nodes are identity poses marked fixed; padded edges have ``edge_mask``
False (weight 0), endpoints ``(0, 0)`` and identity measurements.  Buckets are the sizes
``m * 2^k >= 32`` with ``m`` in ``{4, 5, 6, 7}`` (at most 25 % padding above 32, 4 buckets
per doubling).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Bool, Float, Int

# The robust kernels live in their own module; their names stay importable from here.
from swiftjax.errors import SwiftjaxError
from swiftjax.posegraph.kernels import (  # noqa: F401
    KERNEL_CODES,
    RobustKernel,
    kernel_code,
    robust_rho,
    robust_rho_weight,
    robust_weight,
)

__all__ = [
    "Problem",
    "RobustKernel",
    "robust_rho",
    "robust_weight",
    "kernel_code",
    "robust_rho_weight",
    "validate",
    "bucket_size",
    "padded_sizes",
    "pad_problem",
    "ProblemError",
]


class ProblemError(SwiftjaxError, ValueError):
    """An invalid pose-graph input, raised on the host before any work starts."""


def _as_information(information: ArrayLike | None, num_edges: int, dtype, xp=jnp) -> Float[ArrayLike, "e 7 7"]:
    """Normalise ``information`` to ``[E, 7, 7]`` (``xp``: NumPy for concrete inputs, else jnp).

    Accepted: ``None`` (identity), a scalar weight, ``[E]`` per-edge weights, ``[E, 7]``
    diagonals, ``[E, 7, 7]`` full matrices.
    """
    eye = xp.eye(7, dtype=dtype)
    if information is None:
        return xp.broadcast_to(eye, (num_edges, 7, 7))
    info = xp.asarray(information, dtype=dtype)
    if info.ndim == 0:
        return xp.broadcast_to(info * eye, (num_edges, 7, 7))
    if info.ndim == 1 and info.shape[0] == num_edges:
        return info[:, None, None] * eye
    if info.ndim == 2 and info.shape == (num_edges, 7):
        return info[:, :, None] * eye
    if info.ndim == 3 and info.shape == (num_edges, 7, 7):
        return info
    raise ProblemError(
        f"information has shape {tuple(info.shape)}; expected a scalar, [E]={num_edges}, "
        f"[E, 7] or [E, 7, 7] with E = {num_edges}"
    )


class Problem(eqx.Module):
    """A Sim(3) pose graph (a pytree; every field is an array).

    Attributes:
        poses: ``[N, 8]`` initial chunk-to-world transforms (the solve starts here).
        edges: ``[E, 2]`` int32 node indices ``(i, j)``.
        measurements: ``[E, 8]`` relative transforms ``Z_ij ~ S_i^-1 S_j``.
        information: ``[E, 7, 7]`` information matrices in tangent order ``(rho, omega, sigma)``.
        fixed: ``[N]`` bool; fixed nodes never move (the gauge).  Default: node 0 only.
        robust: ``[E]`` bool; edges whose cost goes through the robust kernel (if one is
            chosen in :func:`swiftjax.posegraph.optimize`).  Default: none.
        edge_mask: ``[E]`` bool; False for padding edges (weight 0).  Default: all True.

    ``information`` may be given as ``None`` (identity), a scalar weight, ``[E]`` per-edge
    weights, ``[E, 7]`` diagonals or ``[E, 7, 7]``.  The dtype of every float field is the
    dtype of ``poses`` (float32 unless you pass float64 arrays under ``jax.enable_x64``).
    Construction does no validation (it must work under ``jit``);
    :func:`validate` checks a concrete problem on the host.
    """

    poses: Float[Array, "n 8"]
    edges: Int[Array, "e 2"]
    measurements: Float[Array, "e 8"]
    information: Float[Array, "e 7 7"]
    fixed: Bool[Array, " n"]
    robust: Bool[Array, " e"]
    edge_mask: Bool[Array, " e"]

    def __init__(
        self,
        poses: ArrayLike,
        edges: ArrayLike,
        measurements: ArrayLike,
        information: ArrayLike | None = None,
        fixed: ArrayLike | None = None,
        robust: ArrayLike | None = None,
        edge_mask: ArrayLike | None = None,
    ):
        # Concrete inputs are normalised with NumPy (no eager XLA kernels to compile in a fresh
        # process); traced ones (inside jit) with jnp.
        args = (poses, edges, measurements, information, fixed, robust, edge_mask)
        xp = jnp if any(isinstance(a, jax.core.Tracer) for a in args) else np
        poses = xp.asarray(poses)
        if not xp.issubdtype(poses.dtype, xp.floating):
            poses = poses.astype(np.float32)
        dtype = jax.dtypes.canonicalize_dtype(poses.dtype)
        poses = poses.astype(dtype)
        if poses.ndim != 2 or poses.shape[1] != 8:
            raise ProblemError(f"poses has shape {tuple(poses.shape)}; expected [N, 8]")
        edges = xp.asarray(edges)
        if edges.ndim != 2 or edges.shape[1] != 2:
            raise ProblemError(f"edges has shape {tuple(edges.shape)}; expected [E, 2]")
        if not xp.issubdtype(edges.dtype, xp.integer):
            raise ProblemError(f"edges has dtype {edges.dtype}; expected integers")
        num_nodes, num_edges = poses.shape[0], edges.shape[0]
        measurements = xp.asarray(measurements, dtype=dtype)
        if measurements.shape != (num_edges, 8):
            raise ProblemError(
                f"measurements has shape {tuple(measurements.shape)}; expected [E, 8] = [{num_edges}, 8]"
            )
        fixed = (xp.arange(num_nodes) == 0) if fixed is None else xp.asarray(fixed, bool)
        if fixed.shape != (num_nodes,):
            raise ProblemError(f"fixed has shape {tuple(fixed.shape)}; expected [N] = [{num_nodes}]")
        robust = xp.zeros((num_edges,), bool) if robust is None else xp.asarray(robust, bool)
        if robust.shape != (num_edges,):
            raise ProblemError(f"robust has shape {tuple(robust.shape)}; expected [E] = [{num_edges}]")
        edge_mask = xp.ones((num_edges,), bool) if edge_mask is None else xp.asarray(edge_mask, bool)
        if edge_mask.shape != (num_edges,):
            raise ProblemError(f"edge_mask has shape {tuple(edge_mask.shape)}; expected [E] = [{num_edges}]")
        # NumPy arrays go to the device by device_put: jnp.asarray of a NumPy array compiles a
        # small copy program per shape (~0.1 s each: a growing graph paid it on every call)
        put = jnp.asarray if xp is jnp else lambda a: jax.device_put(np.ascontiguousarray(a))
        self.poses = put(poses)
        self.edges = put(edges.astype(np.int32))
        self.measurements = put(measurements)
        self.information = put(_as_information(information, num_edges, dtype, xp))
        self.fixed = put(fixed)
        self.robust = put(robust)
        self.edge_mask = put(edge_mask)

    @property
    def num_nodes(self) -> int:
        return self.poses.shape[0]

    @property
    def num_edges(self) -> int:
        return self.edges.shape[0]


# ----------------------------------------------------------------------- host validation


def _first(items, n: int = 8) -> str:
    items = list(items)
    more = f" (and {len(items) - n} more)" if len(items) > n else ""
    return ", ".join(str(x) for x in items[:n]) + more


def validate(problem: Problem, *, quaternion_tol: float = 1e-3) -> None:
    """Check a concrete problem on the host; raise :class:`ProblemError` naming what is wrong.

    Checks: finite poses with positive scale and unit quaternions (``|1 - |q|| <=
    quaternion_tol``); edge indices in ``[0, N)``; no self-edges; no duplicate edges (``(i, j)``
    twice, or ``(i, j)`` and ``(j, i)``: merge them into one measurement before building the
    problem); finite measurements with positive scale and unit quaternions; symmetric
    positive-definite, finite information; at least one fixed node; every node connected to
    a fixed node (otherwise its gauge is free and the normal equations are singular).
    Only edges with ``edge_mask`` True are checked.
    """
    poses = np.asarray(problem.poses, dtype=np.float64)
    edges = np.asarray(problem.edges)
    meas = np.asarray(problem.measurements, dtype=np.float64)
    info = np.asarray(problem.information, dtype=np.float64)
    fixed = np.asarray(problem.fixed)
    valid = np.asarray(problem.edge_mask)
    n = poses.shape[0]
    if n == 0:
        raise ProblemError("the problem has no nodes")

    bad = np.nonzero(~np.all(np.isfinite(poses), axis=1))[0]
    if bad.size:
        raise ProblemError(f"poses: non-finite values at nodes {_first(bad)}")
    bad = np.nonzero(poses[:, 7] <= 0)[0]
    if bad.size:
        raise ProblemError(f"poses: non-positive scale at nodes {_first(bad)}")
    bad = np.nonzero(np.abs(np.linalg.norm(poses[:, 3:7], axis=1) - 1) > quaternion_tol)[0]
    if bad.size:
        raise ProblemError(f"poses: quaternion not unit at nodes {_first(bad)}")

    ids = np.nonzero(valid)[0]
    e = edges[ids]
    bad = ids[np.any((e < 0) | (e >= n), axis=1)]
    if bad.size:
        raise ProblemError(
            f"edges: node index out of range [0, {n}) at edges {_first(f'{k}:{tuple(edges[k])}' for k in bad)}"
        )
    bad = ids[e[:, 0] == e[:, 1]]
    if bad.size:
        raise ProblemError(f"edges: self-edges (i == j) at edges {_first(f'{k}:{tuple(edges[k])}' for k in bad)}")
    key = np.sort(e, axis=1)
    _, first_idx, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        dup = key[first_idx[counts > 1]]
        raise ProblemError(
            "edges: duplicate edges between node pairs "
            f"{_first(tuple(int(v) for v in d) for d in dup)} (merge repeated measurements of one "
            "pair into a single edge, e.g. by information-weighted averaging)"
        )

    m = meas[ids]
    bad = ids[~np.all(np.isfinite(m), axis=1)]
    if bad.size:
        raise ProblemError(f"measurements: non-finite values at edges {_first(bad)}")
    bad = ids[m[:, 7] <= 0]
    if bad.size:
        raise ProblemError(f"measurements: non-positive scale at edges {_first(bad)}")
    bad = ids[np.abs(np.linalg.norm(m[:, 3:7], axis=1) - 1) > quaternion_tol]
    if bad.size:
        raise ProblemError(f"measurements: quaternion not unit at edges {_first(bad)}")

    om = info[ids]
    bad = ids[~np.all(np.isfinite(om), axis=(1, 2))]
    if bad.size:
        raise ProblemError(f"information: non-finite values at edges {_first(bad)}")
    asym = np.abs(om - np.swapaxes(om, 1, 2)).max(axis=(1, 2)) > 1e-8 * np.maximum(np.abs(om).max(axis=(1, 2)), 1e-300)
    bad = ids[asym]
    if bad.size:
        raise ProblemError(f"information: not symmetric at edges {_first(bad)}")
    if om.shape[0]:
        eig = np.linalg.eigvalsh(om)
        bad = ids[eig[:, 0] <= 1e-12 * np.maximum(eig[:, -1], 1e-300)]
        if bad.size:
            raise ProblemError(
                f"information: not positive definite at edges {_first(bad)} "
                f"(smallest eigenvalues {_first(np.round(eig[np.isin(ids, bad), 0], 6))})"
            )

    if not fixed.any():
        raise ProblemError(
            "fixed: no node is fixed; fix at least one (e.g. chunk 0) to remove the Sim(3) gauge freedom"
        )
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ones = np.ones(len(e))
    graph = coo_matrix((ones, (e[:, 0], e[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    anchored = np.isin(labels, np.unique(labels[fixed]))
    loose = np.nonzero(~anchored)[0]
    if loose.size:
        raise ProblemError(
            f"edges: nodes {_first(loose)} are not connected to any fixed node "
            f"({loose.size} of {n}); connect them or mark one node of each component fixed"
        )


# ------------------------------------------------------------------------------- buckets


def bucket_size(n: int, minimum: int = 32) -> int:
    """Smallest size ``m * 2^k >= max(n, minimum)`` with ``m in {4, 5, 6, 7}``."""
    n = max(int(n), minimum)
    k = max(int(np.floor(np.log2(n))) - 2, 0)
    while True:
        for m in (4, 5, 6, 7):
            if m * 2**k >= n:
                return m * 2**k
        k += 1


def padded_sizes(num_nodes: int, num_edges: int, pad: bool | tuple[int, int] = True) -> tuple[int, int]:
    """The ``(N_bucket, E_bucket)`` a graph of ``num_nodes`` / ``num_edges`` is padded to.

    ``pad``: True — :func:`bucket_size` of each; False — the sizes themselves (a program per
    exact size); ``(min_nodes, min_edges)`` — :func:`bucket_size` of ``max(size, minimum)``: a
    caller that knows how large its graph will grow (an online reconstruction re-solving after
    every chunk) passes its capacity and gets one bucket, so no solve recompiles until the graph
    outgrows it.
    """
    if pad is True:
        return bucket_size(num_nodes), bucket_size(num_edges)
    if pad is False:
        return int(num_nodes), int(num_edges)
    lo_n, lo_e = (int(v) for v in pad)
    return bucket_size(max(num_nodes, lo_n)), bucket_size(max(num_edges, lo_e))


def pad_problem(problem: Problem, num_nodes: int, num_edges: int) -> Problem:
    """Pad to ``(num_nodes, num_edges)``: fixed identity nodes, masked ``(0, 0)`` identity edges."""
    n, e = problem.num_nodes, problem.num_edges
    if num_nodes < n or num_edges < e:
        raise ValueError(f"cannot pad ({n}, {e}) down to ({num_nodes}, {num_edges})")
    dtype = problem.poses.dtype
    ident = np.array([0, 0, 0, 0, 0, 0, 1, 1], dtype)
    pn, pe = num_nodes - n, num_edges - e
    if pn == 0 and pe == 0:
        return problem
    cat = lambda a, pad: np.concatenate([np.asarray(a), pad])
    return Problem(
        poses=cat(problem.poses, np.broadcast_to(ident, (pn, 8))),
        edges=cat(problem.edges, np.zeros((pe, 2), np.int32)),
        measurements=cat(problem.measurements, np.broadcast_to(ident, (pe, 8))),
        information=cat(problem.information, np.broadcast_to(np.eye(7, dtype=dtype), (pe, 7, 7))),
        fixed=cat(problem.fixed, np.ones((pn,), bool)),
        robust=cat(problem.robust, np.zeros((pe,), bool)),
        edge_mask=cat(problem.edge_mask, np.zeros((pe,), bool)),
    )

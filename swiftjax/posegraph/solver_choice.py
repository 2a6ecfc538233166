"""Which linear solver a pose graph gets: the ``"auto"`` rule and its thresholds (host only).

Dense Cholesky for small padded graphs (``N_bucket <= DENSE_MAX_NODES``, ``7 N <= 448`` rows);
else the host sparse direct solver when its factor stays sparse — few independent cycles (a
chain with few loops: small fill-in, poor PCG conditioning) or, for graphs of at most
``FILL_ESTIMATE_MAX_NODES`` nodes, a COLAMD factor of the node graph with at most
``SPARSE_MAX_FILL`` times the graph's entries; else block-Jacobi PCG (random long loops make a
graph an expander, which PCG likes and a factorisation does not).  With SciPy's SuperLU (no
cvxopt) the direct solve is an order of magnitude slower, hence the lower fill threshold.  The
measurements behind these numbers are in ``docs/performance/posegraph.md``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from swiftjax.posegraph import sparse_direct
from swiftjax.posegraph.linear_solvers import LINEAR_SOLVERS

__all__ = [
    "DENSE_MAX_NODES",
    "SPARSE_MAX_CYCLE_FRACTION",
    "SPARSE_MAX_FILL",
    "FILL_ESTIMATE_MAX_NODES",
    "LINEAR_SOLVER_CHOICES",
    "check_linear_solver",
    "node_fill_ratio",
    "choose_linear_solver",
]

#: Largest padded node count for which "auto" picks the dense Cholesky.
DENSE_MAX_NODES = 64
#: "auto" picks the host sparse solver when the cycle rank ``E - N + 1`` is at most this fraction of ``N`` ...
SPARSE_MAX_CYCLE_FRACTION = 0.05
#: ... or, for ``N <= FILL_ESTIMATE_MAX_NODES``, when :func:`node_fill_ratio` is at most this.
SPARSE_MAX_FILL = 12.0 if sparse_direct.BACKEND == "cholmod" else 4.0
FILL_ESTIMATE_MAX_NODES = 3000
#: Every accepted ``linear_solver`` value.
LINEAR_SOLVER_CHOICES: tuple[str, ...] = ("auto", *LINEAR_SOLVERS)


def node_fill_ratio(num_nodes: int, edges) -> float:
    """``nnz(L + U) / (N + 2E)`` of SuperLU (COLAMD) on the node graph's ``A + A^T + cI`` (host)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    e = np.asarray(edges)
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(num_nodes, num_nodes))
    a = (a + a.T + sp.eye(num_nodes) * (len(e) + 1.0)).tocsc()
    lu = sla.splu(a, permc_spec="COLAMD", options=dict(SymmetricMode=True))
    return (lu.L.nnz + lu.U.nnz) / (num_nodes + 2 * len(e))


def check_linear_solver(name: Any) -> str:
    """``name`` if it is one of :data:`LINEAR_SOLVER_CHOICES`, else ``ValueError``."""
    if name not in LINEAR_SOLVER_CHOICES:
        raise ValueError(f"linear_solver must be 'auto', 'dense', 'pcg' or 'sparse', not {name!r}")
    return name


def choose_linear_solver(
    num_nodes_padded: int, requested: str = "auto", *, num_nodes: int | None = None, edges=None
) -> str:
    """Resolve ``"auto"`` (module docstring) to ``"dense"``, ``"sparse"`` or ``"pcg"``; any other
    ``requested`` value is returned as is (validated)."""
    if check_linear_solver(requested) != "auto":
        return requested
    if num_nodes_padded <= DENSE_MAX_NODES:
        return "dense"
    if num_nodes is not None and edges is not None:
        if len(edges) - num_nodes + 1 <= SPARSE_MAX_CYCLE_FRACTION * num_nodes:
            return "sparse"
        if num_nodes <= FILL_ESTIMATE_MAX_NODES and node_fill_ratio(num_nodes, edges) <= SPARSE_MAX_FILL:
            return "sparse"
    return "pcg"

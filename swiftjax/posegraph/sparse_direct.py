"""Host-side sparse direct solve of block normal equations, with the symbolic analysis cached.

The block-sparse normal equations of :mod:`swiftjax.posegraph.linear` (``[N, b, b]`` diagonal
blocks, one ``[b, b]`` block per edge) keep the same sparsity pattern for every step of a
solve: only the values change.  :func:`solve` therefore builds, once per pattern (edges, active
edges, fixed nodes), the lower triangle's compressed-column structure, the map from the block
values to it (a gather, plus the duplicate positions summed) and the fill-reducing ordering plus
supernodal symbolic factorisation.  Each step then costs one gather and one numeric factorisation.

Backends, picked at import (:data:`BACKEND`):

* ``"cholmod"`` — CHOLMOD's supernodal Cholesky (AMD ordering) through ``cvxopt.cholmod``
  (install ``swiftjax[sparse]``; cvxopt is GPL-3, hence optional).
* ``"superlu"`` — SciPy's SuperLU (COLAMD, symmetric mode) on the full matrix, no cached
  analysis, an order of magnitude slower (timings in ``docs/performance/posegraph.md``).

Blocks touching a fixed node or belonging to an inactive (masked) edge are left out of the
pattern: their values are zero by construction of the normal equations, and fixed nodes get
an identity diagonal block.
"""

from __future__ import annotations

import collections
import hashlib
import threading

import numpy as np
import scipy.sparse as sp
from jaxtyping import Bool, Float, Int

__all__ = ["BACKEND", "SparsePattern", "pattern", "solve"]

try:  # pragma: no cover - which branch runs depends on the installation
    import cvxopt
    import cvxopt.cholmod as _cholmod

    BACKEND = "cholmod"
except ImportError:  # pragma: no cover
    cvxopt = _cholmod = None
    BACKEND = "superlu"


class SparsePattern:
    """Lower-triangle CSC structure of ``H`` for one graph, with its cached factorisation.

    Attributes:
        size: ``b N``.
        rows, cols: coordinates of the lower triangle's entries in CSC order (by column, then row).
        indptr: CSC column pointers (``rows`` are the CSC row indices).
        nnz: number of stored entries (:meth:`values` gathers them from the blocks).
    """

    def __init__(self, num_nodes: int, block: int, edges: np.ndarray, active: np.ndarray, fixed: np.ndarray):
        n, b = num_nodes, block
        size = n * b
        a = np.arange(b)
        rr, cc = np.meshgrid(a, a, indexing="ij")
        lower = rr >= cc
        # Diagonal blocks: data index n*b*b + r*b + c, lower part only.
        nodes = np.arange(n)
        d_rows = (b * nodes[:, None, None] + rr)[:, lower].ravel()
        d_cols = (b * nodes[:, None, None] + cc)[:, lower].ravel()
        d_idx = (nodes[:, None, None] * b * b + rr * b + cc)[:, lower].ravel()
        # Edge blocks H_ij (rows of i, columns of j); keep the copy that lies in the lower
        # triangle: H_ij itself when i > j, else H_ij^T placed at (j, i).
        e = np.asarray(edges, np.int64)
        keep = np.asarray(active, bool) & ~fixed[e[:, 0]] & ~fixed[e[:, 1]] & (e[:, 0] != e[:, 1])
        k = np.nonzero(keep)[0]
        i, j = e[k, 0], e[k, 1]
        swap = i < j
        hi, lo = np.where(swap, j, i), np.where(swap, i, j)
        base = n * b * b + k[:, None, None] * b * b
        # entry (r, c) of the placed block is H_ij[r, c] (no swap) or H_ij[c, r] (swap)
        src = np.where(swap[:, None, None], base + cc * b + rr, base + rr * b + cc)
        o_rows = (b * hi[:, None, None] + rr).ravel()
        o_cols = (b * lo[:, None, None] + cc).ravel()
        o_idx = src.ravel()
        rows = np.concatenate([d_rows, o_rows])
        cols = np.concatenate([d_cols, o_cols])
        data_idx = np.concatenate([d_idx, o_idx])
        key = cols * size + rows  # CSC order = sorted (column, row)
        ukey, pos = np.unique(key, return_inverse=True)
        self.size = size
        self.rows = (ukey % size).astype(np.int64)
        self.cols = (ukey // size).astype(np.int64)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(self.cols, minlength=size))])
        self.nnz = ukey.shape[0]
        # values = gather of each entry's first source, plus the (rare) duplicate sources added on
        # top (a third of a sparse assembly mat-vec's time).
        order = np.argsort(pos, kind="stable")
        first = np.ones(order.shape[0], bool)
        first[1:] = pos[order][1:] != pos[order][:-1]
        self._gather = data_idx[order[first]]
        self._dup_pos = pos[order[~first]]
        self._dup_src = data_idx[order[~first]]
        self._diag_pos = np.searchsorted(ukey, np.arange(size) * (size + 1))  # CSC index of (k, k)
        self._matrix = None
        self._symbolic = None

    def values(self, diag: np.ndarray, off: np.ndarray, damping: np.ndarray | None = None) -> np.ndarray:
        """CSC values of the lower triangle from the blocks ``diag [N, b, b]``, ``off [E, b, b]``,
        plus ``damping [N, b]`` on the diagonal."""
        flat = np.concatenate([np.ravel(diag), np.ravel(off)])
        values = flat[self._gather]
        if self._dup_pos.size:
            np.add.at(values, self._dup_pos, flat[self._dup_src])
        if damping is not None:
            values[self._diag_pos] += np.ravel(damping)
        return values

    def solve(self, values: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, bool]:
        """Solve ``H x = rhs`` for the symmetric ``H`` given by its lower-triangle ``values``."""
        if BACKEND == "cholmod":
            return self._solve_cholmod(values, rhs)
        return self._solve_superlu(values, rhs)

    def _solve_cholmod(self, values, rhs):
        if self._matrix is None:
            self._matrix = cvxopt.spmatrix(
                cvxopt.matrix(values), cvxopt.matrix(self.rows), cvxopt.matrix(self.cols), (self.size, self.size)
            )
            # cvxopt stores CCS sorted by (column, row): the same order as ours.
            assert np.array_equal(np.asarray(self._matrix.I).ravel(), self.rows)
            assert np.array_equal(np.asarray(self._matrix.J).ravel(), self.cols)
            self._symbolic = _cholmod.symbolic(self._matrix, uplo="L")
        else:
            self._matrix.V = cvxopt.matrix(values)
        try:
            _cholmod.numeric(self._matrix, self._symbolic)
            x = cvxopt.matrix(np.ascontiguousarray(rhs, np.float64))
            _cholmod.solve(self._symbolic, x)
        except ArithmeticError:  # not positive definite
            return np.zeros_like(rhs), False
        x = np.asarray(x).reshape(rhs.shape)
        return x, bool(np.all(np.isfinite(x)))

    def _solve_superlu(self, values, rhs):
        import scipy.sparse.linalg as sla

        low = sp.csc_matrix((values, self.rows, self.indptr), shape=(self.size, self.size))
        full = (low + low.T - sp.diags(low.diagonal())).tocsc()
        try:
            lu = sla.splu(full, permc_spec="COLAMD", options=dict(SymmetricMode=True))
        except RuntimeError:  # exactly singular
            return np.zeros_like(rhs), False
        x = lu.solve(rhs)
        return x, bool(np.all(np.isfinite(x)))


_CACHE: collections.OrderedDict[bytes, SparsePattern] = collections.OrderedDict()
_CACHE_SIZE = 8
_LOCK = threading.Lock()


def pattern(num_nodes: int, block: int, edges, active, fixed) -> SparsePattern:
    """The (cached, LRU of 8) :class:`SparsePattern` of a graph."""
    edges = np.ascontiguousarray(edges, np.int64)
    active = np.ascontiguousarray(active, bool)
    fixed = np.ascontiguousarray(fixed, bool)
    h = hashlib.blake2b(digest_size=16)
    for part in (np.array([num_nodes, block]), edges, active, fixed):
        h.update(part.tobytes())
    key = h.digest()
    with _LOCK:
        hit = _CACHE.get(key)
        if hit is not None:
            _CACHE.move_to_end(key)
            return hit
    pat = SparsePattern(num_nodes, block, edges, active, fixed)
    with _LOCK:
        _CACHE[key] = pat
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    return pat


def solve(
    diag: Float[np.ndarray, "n b b"],
    off: Float[np.ndarray, "e b b"],
    damping: Float[np.ndarray, "n b"],
    rhs: Float[np.ndarray, "n b"],
    edges: Int[np.ndarray, "e 2"],
    active: Bool[np.ndarray, " e"],
    fixed: Bool[np.ndarray, " n"],
) -> tuple[Float[np.ndarray, "n b"], bool]:
    """Solve ``(H + diag(damping)) x = rhs`` (host NumPy, float64 internally).

    Args:
        diag: ``[N, b, b]`` diagonal blocks (identity on fixed nodes).
        off: ``[E, b, b]`` block ``H_ij`` of each edge ``(i, j)``.
        damping: ``[N, b]`` added to the diagonal.
        rhs: ``[N, b]``.
        edges: ``[E, 2]``; active: ``[E]`` bool (masked edges contribute nothing);
        fixed: ``[N]`` bool.

    Returns:
        ``(x [N, b], ok)``; ``ok`` False if the matrix is not positive definite / singular.
    """
    n, b = rhs.shape
    pat = pattern(n, b, edges, active, fixed)
    values = pat.values(np.asarray(diag, np.float64), np.asarray(off, np.float64), np.asarray(damping, np.float64))
    x, ok = pat.solve(values, np.asarray(rhs, np.float64).reshape(-1))
    return x.reshape(n, b), ok

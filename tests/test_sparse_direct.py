"""Host sparse direct solver of block normal equations: both backends against a dense NumPy solve."""

from __future__ import annotations

import numpy as np
import pytest

from swiftjax.posegraph import sparse_direct


def _system(rng, n, b, edges, fixed):
    """Random SPD block system with H_ij blocks per edge (fixed nodes: identity, decoupled)."""
    e = len(edges)
    off = rng.normal(size=(e, b, b))
    couple = ~(fixed[edges[:, 0]] | fixed[edges[:, 1]])
    off *= couple[:, None, None]
    dense = np.zeros((n * b, n * b))
    for k, (i, j) in enumerate(edges):
        dense[i * b : (i + 1) * b, j * b : (j + 1) * b] += off[k]
        dense[j * b : (j + 1) * b, i * b : (i + 1) * b] += off[k].T
    # diagonal blocks: SPD and dominant enough to make the whole matrix SPD
    a = rng.normal(size=(n, b, b))
    diag = a @ np.swapaxes(a, 1, 2) + (2.0 * b * (1 + np.bincount(edges.ravel(), minlength=n)))[:, None, None] * np.eye(
        b
    )
    diag[fixed] = np.eye(b)
    for i in range(n):
        dense[i * b : (i + 1) * b, i * b : (i + 1) * b] += diag[i]
    return diag, off, dense


@pytest.mark.parametrize("backend", ["cholmod", "superlu"])
@pytest.mark.parametrize("block", [1, 3, 7])
def test_solve_matches_dense(monkeypatch, backend, block):
    if backend == "cholmod" and sparse_direct.cvxopt is None:
        pytest.skip("cvxopt (the 'sparse' extra) is not installed")
    monkeypatch.setattr(sparse_direct, "BACKEND", backend)
    rng = np.random.default_rng(block)
    n = 40
    chain = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    # loops in both directions, one pair (i, j) and (j, i) landing on the same block position
    loops = np.array([[0, 20], [35, 5], [10, 30], [30, 10]])
    edges = np.concatenate([chain, loops])
    fixed = np.zeros(n, bool)
    fixed[[0, 17]] = True
    diag, off, dense = _system(rng, n, block, edges, fixed)
    damping = rng.uniform(0.0, 1.0, size=(n, block))
    rhs = rng.normal(size=(n, block))
    rhs[fixed] = 0.0
    dense_d = dense + np.diag(damping.ravel())
    want = np.linalg.solve(dense_d, rhs.ravel()).reshape(n, block)
    active = np.ones(len(edges), bool)
    x, ok = sparse_direct.solve(diag, off, damping, rhs, edges, active, fixed)
    assert ok
    np.testing.assert_allclose(x, want, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(x[fixed], 0.0)
    # Second call hits the cached pattern (and cached symbolic factorisation) with new values.
    x2, ok2 = sparse_direct.solve(diag, 2.0 * off, damping, rhs, edges, active, fixed)
    coupling = dense - _block_diag(diag)
    want2 = np.linalg.solve(dense_d + coupling, rhs.ravel()).reshape(n, block)
    assert ok2
    np.testing.assert_allclose(x2, want2, rtol=1e-9, atol=1e-12)


def _block_diag(diag):
    n, b, _ = diag.shape
    out = np.zeros((n * b, n * b))
    for i in range(n):
        out[i * b : (i + 1) * b, i * b : (i + 1) * b] = diag[i]
    return out


def test_inactive_edges_are_ignored_and_pattern_is_cached():
    rng = np.random.default_rng(0)
    n, b = 12, 7
    edges = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    fixed = np.arange(n) == 0
    diag, off, dense = _system(rng, n, b, edges, fixed)
    rhs = rng.normal(size=(n, b))
    rhs[0] = 0
    damping = np.zeros((n, b))
    # A padding edge (0, 0) with garbage values, masked inactive: must not change the answer.
    edges_p = np.concatenate([edges, [[0, 0]]])
    off_p = np.concatenate([off, rng.normal(size=(1, b, b))])
    active = np.r_[np.ones(len(edges), bool), False]
    x, ok = sparse_direct.solve(diag, off_p, damping, rhs, edges_p, active, fixed)
    assert ok
    np.testing.assert_allclose(x, np.linalg.solve(dense, rhs.ravel()).reshape(n, b), rtol=1e-10, atol=1e-12)
    p1 = sparse_direct.pattern(n, b, edges_p, active, fixed)
    p2 = sparse_direct.pattern(n, b, edges_p.copy(), active.copy(), fixed.copy())
    assert p1 is p2
    assert sparse_direct.pattern(n, b, edges_p, np.ones(len(edges_p), bool), fixed) is not p1


@pytest.mark.parametrize("backend", ["cholmod", "superlu"])
def test_indefinite_matrix_reports_failure(monkeypatch, backend):
    if backend == "cholmod" and sparse_direct.cvxopt is None:
        pytest.skip("cvxopt (the 'sparse' extra) is not installed")
    monkeypatch.setattr(sparse_direct, "BACKEND", backend)
    n, b = 3, 2
    edges = np.array([[0, 1], [1, 2]])
    diag = np.broadcast_to(np.eye(b), (n, b, b)).copy()
    off = np.zeros((2, b, b))
    diag[1] = -np.eye(b) if backend == "cholmod" else np.zeros((b, b))  # indefinite / singular
    x, ok = sparse_direct.solve(
        diag, off, np.zeros((n, b)), np.ones((n, b)), edges, np.ones(2, bool), np.zeros(n, bool)
    )
    assert not ok
    np.testing.assert_array_equal(x, 0.0)

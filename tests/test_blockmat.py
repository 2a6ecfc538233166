"""Batched small-matrix products of ``swiftjax.posegraph.blockmat`` against NumPy's float64 matmul."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from swiftjax.posegraph import blockmat


@pytest.fixture
def operands(x64):
    rng = np.random.default_rng(0)
    return rng.normal(size=(5, 4, 3, 7)), rng.normal(size=(5, 4, 7, 6)), rng.normal(size=(5, 4, 7))


def test_products_equal_numpy(operands):
    a, b, v = operands
    sq = a[..., :3] @ np.swapaxes(a[..., :3], -1, -2)  # [5, 4, 3, 3]
    np.testing.assert_allclose(blockmat.bmm(a, b), a @ b, rtol=1e-13)
    np.testing.assert_allclose(blockmat.bmtm(b, b), np.swapaxes(b, -1, -2) @ b, rtol=1e-13)
    np.testing.assert_allclose(blockmat.bmv(a, v), np.einsum("...ij,...j->...i", a, v), rtol=1e-13)
    np.testing.assert_allclose(blockmat.bmtv(b, v), np.einsum("...ji,...j->...i", b, v), rtol=1e-13)
    w = v[..., :3]
    np.testing.assert_allclose(blockmat.quadratic(w, sq), np.einsum("...i,...ij,...j->...", w, sq, w), rtol=1e-12)


def test_unfused_returns_fn_value_and_is_not_fused(operands):
    a, b, _ = operands
    fn = lambda x, y: (blockmat.bmm(x, y), -x)
    got = jax.jit(lambda x, y: blockmat.unfused(fn, x, y))(a, b)
    want = fn(a, b)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=1e-14)
    # a NaN in the first element makes the loop run twice: the value is the same
    a_nan = a.copy()
    a_nan[0, 0, 0, 0] = np.nan
    np.testing.assert_allclose(blockmat.unfused(fn, a_nan, b)[0][1:], (a_nan @ b)[1:], rtol=1e-13)
    # the body sits in a loop of its own in the optimised program
    hlo = jax.jit(lambda x, y: blockmat.unfused(fn, x, y)[0] @ y[..., :6, :]).lower(a, b).compile().as_text()
    assert " while(" in hlo

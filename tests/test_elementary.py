"""The vectorisable sin/cos/atan2 used by SO(3)/Sim(3) against NumPy (float32 and float64)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from swiftjax._elementary import arctan2_nonneg, sincos


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sincos_within_two_ulp_of_numpy(dtype):
    rng = np.random.default_rng(0)
    special = [0.0, -0.0, np.pi, -np.pi, np.pi / 2, np.pi / 4, 3 * np.pi / 4, 1e-30, 100.0]
    x = np.concatenate([rng.uniform(-20, 20, 20000), rng.uniform(-1e-3, 1e-3, 500), special]).astype(dtype)
    with jax.enable_x64(dtype == np.float64):
        s, c = jax.jit(sincos)(jnp.asarray(x))
        assert s.dtype == dtype
    ref = x.astype(np.float64)
    eps = np.finfo(dtype).eps
    assert np.max(np.abs(np.asarray(s, np.float64) - np.sin(ref))) < 2 * eps
    assert np.max(np.abs(np.asarray(c, np.float64) - np.cos(ref))) < 2 * eps


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_arctan2_nonneg_within_two_ulp_of_numpy(dtype):
    rng = np.random.default_rng(1)
    y = np.abs(rng.normal(size=20000)).astype(dtype)
    x = np.abs(rng.normal(size=20000)).astype(dtype)
    y[:10], x[10:20] = 0, 0  # the axes
    x[20:30] = y[20:30]  # the diagonal (pi/4)
    with jax.enable_x64(dtype == np.float64):
        a = np.asarray(jax.jit(arctan2_nonneg)(jnp.asarray(y), jnp.asarray(x)), np.float64)
    ref = np.arctan2(y.astype(np.float64), x.astype(np.float64))
    assert np.max(np.abs(a - ref)) < 2 * np.finfo(dtype).eps * np.pi


def test_sincos_gradient_is_the_derivative():
    x = jnp.linspace(-4.0, 4.0, 101)
    ds = jax.vmap(jax.grad(lambda v: sincos(v)[0]))(x)
    dc = jax.vmap(jax.grad(lambda v: sincos(v)[1]))(x)
    np.testing.assert_allclose(ds, np.cos(np.asarray(x)), atol=1e-5)
    np.testing.assert_allclose(dc, -np.sin(np.asarray(x)), atol=1e-5)

"""``swiftjax._products.small_matmul``: the written-out product is XLA:CPU's dot bit for bit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from swiftjax._compile import LIGHT_COMPILE, supported
from swiftjax._products import small_matmul


def _loop(x: np.ndarray, M: np.ndarray) -> np.ndarray:
    """float32 NumPy: ``((x₀ M₀ + x₁ M₁) + x₂ M₂) + …`` with each product rounded."""
    out = (x[..., 0:1] * M[..., 0, :]).astype(np.float32)
    for c in range(1, M.shape[-2]):
        out = (out + (x[..., c : c + 1] * M[..., c, :]).astype(np.float32)).astype(np.float32)
    return out


def _dot(x: jax.Array, M: jax.Array) -> jax.Array:
    """``x @ M`` as the code wrote it before: ``@``, or for one matrix per frame the einsum
    ``"fij,fhwj->fhwi"`` of ``R = Mᵀ``."""
    if M.ndim == 2:
        return x @ M
    return jnp.einsum("fij,fhwj->fhwi", jnp.swapaxes(M[:, 0, 0], -1, -2), x)


@pytest.mark.parametrize(
    ("x_shape", "M_shape"),
    [
        ((20000, 3), (3, 3)),  # the dense test's y Rᵀ
        ((20000, 3), (3, 2)),  # a gravity frame's horizontal axes
        ((20000, 2), (2, 2)),  # a yaw in the bird's-eye plane
        ((5, 4000, 3), (3, 2)),  # points against several anchors
        ((6, 20, 30, 3), (6, 1, 1, 3, 3)),  # one rotation per frame (an einsum "fij,fhwj->fhwi")
    ],
)
def test_small_matmul_is_the_dot_bitwise(x_shape, M_shape):
    """Compiled as the pipeline compiles (the light options and XLA's defaults), the product
    equals ``x @ M`` and a float32 NumPy loop in the same order, bit for bit."""
    rng = np.random.default_rng(len(x_shape) * 10 + x_shape[-1])
    x = jnp.asarray((rng.normal(size=x_shape) * 30).astype(np.float32))
    M = jnp.asarray(rng.normal(size=M_shape).astype(np.float32))
    for options in (supported(LIGHT_COMPILE), {}):
        dot = jax.jit(lambda x, M: _dot(x - 1.5, M)).lower(x, M).compile(compiler_options=options)
        mine = jax.jit(lambda x, M: small_matmul(x - 1.5, M)).lower(x, M).compile(compiler_options=options)
        got = np.asarray(mine(x, M))
        np.testing.assert_array_equal(got, np.asarray(dot(x, M)))
    np.testing.assert_array_equal(got, _loop(np.asarray(x) - np.float32(1.5), np.asarray(M)))


def test_small_matmul_non_finite():
    """A NaN or infinite coordinate gives NaN in every output it touches; a product that
    overflows gives NaN (the guard against fused multiply-adds); the other rows are exact."""
    x = np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0], [np.inf, 0.0, 0.0], [3e38, 1.0, 0.0]], np.float32)
    M = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], np.float32) * np.array([[10.0], [1.0], [1.0]], np.float32)
    got = np.asarray(jax.jit(small_matmul)(jnp.asarray(x), jnp.asarray(M)))
    np.testing.assert_array_equal(got[0], [13.0, 5.0])
    assert np.isnan(got[1]).all()
    assert np.isnan(got[2, 0])  # inf x 10
    assert np.isnan(got[2, 1])  # inf x 0 = NaN
    assert np.isnan(got[3, 0]) and got[3, 1] == 1.0  # 3e38 x 10 overflows; 3e38 x 0 + 1 x 1

"""``swiftjax._select``: order statistics by counting are ``jnp.nanmedian``'s and NumPy's values."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from swiftjax._select import kth_smallest, nanmedian


def _cases():
    rng = np.random.default_rng(3)
    heights = rng.normal(-1.6, 0.2, size=(15, 26, 65)).astype(np.float32)
    heights[rng.random(heights.shape) < 0.9] = np.nan  # a band of the image: most pixels NaN
    ties = rng.integers(-3, 4, size=1000).astype(np.float32)
    mixed = rng.normal(size=999).astype(np.float32) * np.float32(1e3)
    mixed[::7] = np.nan
    mixed[5], mixed[11] = np.inf, -np.inf
    return {
        "heights": heights,
        "ties (even count)": ties,
        "ties (odd count)": ties[:-1],
        "mixed signs, NaN and infinities": mixed,
        "one value": np.array([np.nan, 2.5, np.nan], np.float32),
        "two values": np.array([7.0, -1.0], np.float32),
        "tiny and subnormal": np.array([1e-40, -1e-40, 0.0, 1e-45, -3e-38], np.float32),
        "all NaN": np.full(10, np.nan, np.float32),
    }


@pytest.mark.parametrize("name", list(_cases()))
def test_nanmedian_is_jnp_nanmedian(name):
    """The same float32 value as ``jnp.nanmedian`` (both jitted), and NumPy's median."""
    x = _cases()[name]
    got = np.asarray(jax.jit(nanmedian)(jnp.asarray(x)))
    want = np.asarray(jax.jit(jnp.nanmedian)(jnp.asarray(x)))
    np.testing.assert_array_equal(got, want)
    if np.isnan(x).all():
        assert np.isnan(got)
    else:
        assert got == pytest.approx(float(np.nanmedian(x.astype(np.float64))), rel=1e-6, abs=1e-45)


def test_kth_smallest_every_rank_and_vmap():
    """Every rank of a vector with ties and NaN is NumPy's sorted value; ranks outside
    ``[0, n)`` are NaN; vmapped over rows, each row its own."""
    rng = np.random.default_rng(4)
    x = rng.integers(-20, 20, size=(3, 64)).astype(np.float32) / 4
    x[0, ::5] = np.nan
    ranks = np.arange(-1, 66, dtype=np.int32)
    got = np.asarray(jax.jit(jax.vmap(kth_smallest, in_axes=(0, None)))(jnp.asarray(x), jnp.asarray(ranks)))
    for row, g in zip(x, got):
        s = np.sort(row[~np.isnan(row)])
        inside = (ranks >= 0) & (ranks < len(s))
        np.testing.assert_array_equal(g[inside], s[ranks[inside]])
        assert np.isnan(g[~inside]).all()


def test_kth_smallest_valid_mask():
    """``valid`` picks the values (NaN outside it is ignored, a value outside it too)."""
    x = jnp.asarray([5.0, 1.0, np.nan, 3.0, 2.0], jnp.float32)
    valid = jnp.asarray([True, False, False, True, True])
    np.testing.assert_array_equal(np.asarray(kth_smallest(x, jnp.arange(3), valid)), [2.0, 3.0, 5.0])


def test_other_dtypes():
    """float64 goes to ``jnp.nanmedian`` (the same value); ``kth_smallest`` refuses it by name."""
    x = np.array([3.0, np.nan, 1.0, 2.0, 10.0])
    with jax.enable_x64(True):
        got = nanmedian(jnp.asarray(x, jnp.float64))
        assert got.dtype == jnp.float64 and float(got) == 2.5
        with pytest.raises(TypeError, match="x must be float32, got float64"):
            kth_smallest(jnp.asarray(x, jnp.float64), 0)


@pytest.mark.parametrize("x64", [False, True])
def test_nanmedian_random_arrays(x64):
    """Seeded random float32 arrays (two lengths, odd and even: few compiles; random NaN, so
    every count of values) over six decades, with and without ``jax_enable_x64``: bitwise
    ``jnp.nanmedian``."""
    rng = np.random.default_rng(11)
    with jax.enable_x64(x64):
        f, g = jax.jit(nanmedian), jax.jit(jnp.nanmedian)
        for _ in range(60):
            x = (rng.normal(size=17 + _ % 2) * 10.0 ** int(rng.integers(-3, 4))).astype(np.float32)
            x[rng.random(len(x)) < 0.2] = np.nan
            got, want = np.asarray(f(jnp.asarray(x))), np.asarray(g(jnp.asarray(x)))
            assert got.dtype == want.dtype and got.tobytes() == want.tobytes(), x

"""Counter-based random numbers for the synthetic oracle: an integer hash per (key, frame, pixel).

A chunk needs ~30 M random numbers, too many for ``jax.random``'s threefry on a CPU
(docs/performance/synthetic.md); the lowbias32 integer hash gives them for a few integer ops
each, and the same counter always gives the same number (bit-identical results whatever was
computed before).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["approx_normal", "hash32", "uniform16"]


def hash32(x: jax.Array) -> jax.Array:
    """lowbias32 integer hash (uint32 -> uint32)."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x7FEB352D)
    x = x ^ (x >> 15)
    x = x * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def approx_normal(h: jax.Array) -> jax.Array:
    """Zero-mean unit-variance noise from one uint32: the sum of its 4 bytes (Irwin-Hall, |n| <= 3.46)."""
    m = jnp.uint32(0xFF)
    s = (h & m) + ((h >> 8) & m) + ((h >> 16) & m) + (h >> 24)
    return (s.astype(jnp.float32) - 510.0) * jnp.float32(1.0 / np.sqrt(4 * (256.0**2 - 1) / 12))


def uniform16(h: jax.Array, high: bool) -> jax.Array:
    """A uniform in [0, 1) from 16 bits of ``h``."""
    bits = (h >> 16) if high else (h & jnp.uint32(0xFFFF))
    return bits.astype(jnp.float32) * jnp.float32(1.0 / 65536.0)

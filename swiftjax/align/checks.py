"""Host-side input checks of the alignment (one place; clear ``ValueError`` / ``TypeError`` messages).

Shape and dtype checks run when a jitted function is traced (:func:`umeyama_inputs`);
value checks of the cameras run on the host before a chunk pair is aligned
(:func:`check_chunk_pair`, called by :func:`~swiftjax.align.align_chunk_pair_checked`
with ``throw=True``).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

__all__ = ["check_chunk_pair", "umeyama_inputs"]

_FRAME_FIELDS = ("depth", "conf", "intrinsic", "extrinsic")  # ChunkFrames._fields


def umeyama_inputs(
    src: Any, dst: Any, weights: Any
) -> tuple[Float[Array, "*b n 3"], Float[Array, "*b n 3"], Float[Array, "*b n"]]:
    """``(src, dst, w)`` as arrays of one float dtype (float32 for integer points), ``w`` all
    ones when ``weights`` is None; raises ``TypeError`` for half precision, ``ValueError`` for
    shapes other than ``src, dst [..., N, 3]``, ``weights [..., N]``.  Runs at trace time."""
    src = jnp.asarray(src)
    if not jnp.issubdtype(src.dtype, jnp.floating):
        src = src.astype(jnp.float32)
    if src.dtype not in (jnp.float32, jnp.float64):
        raise TypeError(
            f"umeyama: points must be float32 or float64, got {src.dtype} (the 3x3 SVD has no "
            f"{src.dtype} kernel and half precision cannot hold the moments): cast them, e.g. .astype(float32)"
        )
    dst = jnp.asarray(dst, dtype=src.dtype)
    if src.shape[-1] != 3 or src.shape != dst.shape:
        raise ValueError(f"umeyama: src {src.shape} and dst {dst.shape} must both be [..., N, 3]")
    if weights is None:
        w = jnp.ones(src.shape[:-1], src.dtype)
    else:
        w = jnp.asarray(weights).astype(src.dtype)
        if w.shape != src.shape[:-1]:
            raise ValueError(f"umeyama: weights {w.shape} must be {src.shape[:-1]}")
    return src, dst, w


def _check_frames(name: str, f: Any, shape: tuple[int, int, int] | None) -> tuple[int, int, int]:
    for field in _FRAME_FIELDS:
        if not hasattr(f, field):
            raise ValueError(f"{name} has no field {field!r} (expected depth, conf, intrinsic, extrinsic)")
    d = np.shape(f.depth)
    if len(d) != 3:
        raise ValueError(f"{name}.depth must be [O, H, W], got shape {d}")
    if shape is not None and d != shape:
        raise ValueError(f"{name}.depth has shape {d} but the other chunk's overlap is {shape}")
    o = d[0]
    for field, want in (("conf", d), ("intrinsic", (o, 3, 3)), ("extrinsic", (o, 3, 4))):
        got = np.shape(getattr(f, field))
        if got != tuple(want):
            raise ValueError(f"{name}.{field} has shape {got}, expected {tuple(want)}")
    K = np.asarray(f.intrinsic, np.float64)
    if not np.all(np.isfinite(K)):
        raise ValueError(f"{name}.intrinsic has non-finite entries")
    if not (np.all(K[:, 0, 0] > 0) and np.all(K[:, 1, 1] > 0)):
        raise ValueError(f"{name}.intrinsic has a non-positive focal length (fx, fy must be > 0)")
    return d


def check_chunk_pair(prev: Any, cur: Any, K_ref: Any, mask: Any = None) -> tuple[int, int, int]:
    """Check one chunk pair's overlap frames on the host; returns the overlap shape ``(O, H, W)``.

    Raises:
        ValueError: shapes do not match (``depth, conf [O, H, W]``, ``intrinsic [O, 3, 3]``,
            ``extrinsic [O, 3, 4]``, both chunks the same ``O, H, W``, ``mask [O, H, W]``),
            ``O == 0``, or an intrinsic (``K_ref`` included) is non-finite or has a focal ``<= 0``.
    """
    shape = _check_frames("prev", prev, None)
    _check_frames("cur", cur, shape)
    if shape[0] == 0:
        raise ValueError("the overlap is empty: prev/cur have O = 0 frames")
    K = np.asarray(K_ref, np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K_ref must be [3, 3], got shape {K.shape}")
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K_ref must be finite with positive focal lengths, got {K.tolist()}")
    if mask is not None and tuple(np.shape(mask)) != tuple(shape):
        raise ValueError(f"mask has shape {tuple(np.shape(mask))}, expected the overlap's {tuple(shape)}")
    return shape

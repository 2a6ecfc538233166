"""Dispatch of the alignment's moment passes: the fused FFI kernel on CPU, else pure JAX.

The fused kernels (``swiftjax/align/_ffi_kernels.cc``, built at install by ``setup.py`` when a
C++ compiler is present) do the one-pass accumulations that XLA:CPU runs as scalar loops; the
pure-JAX formulations (:mod:`swiftjax.align.umeyama`, :mod:`swiftjax.align.chunk_pair`) are
used on other platforms, for float64, when the extension is not built, or when
``SWIFTJAX_ALIGN_KERNEL=jax`` is set (read when a function is traced).  Both give the same
moments to float32 rounding (the kernel sums in 8 float32 lanes, then in double).  The
kernels have no derivative rule: differentiate the pure-JAX path.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
from jax import Array

try:  # the optional compiled extension
    from swiftjax.align import _ffi_kernels
except ImportError:  # pragma: no cover - depends on the install
    _ffi_kernels = None

__all__ = ["available", "pixel_moments", "umeyama_moments"]

_registered = False


def available(dtype) -> bool:
    """Whether the fused kernel serves ``dtype`` arrays now (float32, extension built, not disabled)."""
    if _ffi_kernels is None or os.environ.get("SWIFTJAX_ALIGN_KERNEL", "auto") == "jax":
        return False
    return jnp.dtype(dtype) == jnp.float32


def _register() -> None:
    global _registered
    if not _registered:
        for name, capsule in _ffi_kernels.handlers().items():
            jax.ffi.register_ffi_target(name, capsule, platform="cpu")
        _registered = True


def pixel_moments(dp: Array, dc: Array, cp: Array, cc: Array, params: Array, ut: Array, vt: Array, fallback):
    """``(S [F, 6, 3, 3], n)`` (``n`` the int32 count of reliable pixels) from the fused kernel
    on CPU, ``fallback()`` elsewhere.

    ``dp, dc, cp, cc [F, H, W]`` float32, ``params [F, 7] = (r_p, r_c, e_p, e_c, thr_p, thr_c,
    lam)``, ``ut [W]``, ``vt [H]``; ``fallback`` returns the same from pure JAX.
    """
    _register()
    f, h, w = dp.shape
    out = (jax.ShapeDtypeStruct((f, 6, 3, 3), jnp.float32), jax.ShapeDtypeStruct((f,), jnp.int32))
    call = jax.ffi.ffi_call("swiftjax_pixel_moments", out, vmap_method="broadcast_all")

    def fused(*args):
        S, n = call(*args)
        return S, jnp.sum(n)

    return jax.lax.platform_dependent(dp, dc, cp, cc, params, ut, vt, cpu=fused, default=lambda *a: fallback())


def umeyama_moments(src: Array, dst: Array, w: Array, centres: Array, fallback):
    """``(T [..., 18], n [...])`` centred weighted sums from the fused kernel on CPU, else ``fallback()``.

    ``src, dst [..., N, 3]``, ``w [..., N]`` float32 (unsanitised: the kernel drops points with
    ``w <= 0`` or a non-finite value), ``centres [..., 6] = (cx, cy)``.
    """
    _register()
    lead = w.shape[:-1]
    out = (jax.ShapeDtypeStruct((*lead, 18), jnp.float32), jax.ShapeDtypeStruct(lead, jnp.int32))
    call = jax.ffi.ffi_call("swiftjax_umeyama_moments", out, vmap_method="broadcast_all")
    return jax.lax.platform_dependent(
        src, dst, w, centres, cpu=lambda *a: call(*a), default=lambda *a: fallback()
    )

"""Dispatch of the alignment's moment passes: the fused FFI kernel on CPU, else pure JAX.

The fused kernels (``swiftjax/align/_ffi/kernels.cc``, built at install when a C++ compiler is
present) do the one-pass accumulations that XLA:CPU runs as scalar loops; the pure-JAX
formulations (:mod:`swiftjax.align.umeyama`, :mod:`swiftjax.align.chunk_pair`) are used on
other platforms, for float64, when the extension is not built, or when
``SWIFTJAX_ALIGN_KERNEL=jax`` is set (read when a function is traced, so it takes effect for
new shapes or a fresh ``jax.jit``).  Both give the same moments to float32 rounding (the
kernel sums in 16 float32 lanes with AVX-512, 8 otherwise, then in double).  The kernel splits
its work over XLA's intra-op thread pool and gives the same bits for any thread count; which
instruction set it runs with is ``_ffi_kernels.isa()`` (``set_isa(name)`` picks another the
CPU has: read at run time, no recompile).

Derivatives: a fused call is a ``jax.custom_jvp`` whose tangent is the pure-JAX reference's
(``jax.jvp(reference, ...)``), so ``jax.grad`` / ``jax.jacfwd`` through the alignment work on
either path and agree to float32 rounding.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import DTypeLike

from swiftjax._compile import LIGHT_COMPILE, quick_jit, supported

_ffi_kernels: Any
try:  # the optional compiled extension
    from swiftjax.align import _ffi_kernels  # type: ignore[attr-defined,no-redef]  # built by setup
except ImportError:  # pragma: no cover - depends on the install
    _ffi_kernels = None

__all__ = ["available", "compiler_options", "fused", "jit", "pixel_moments", "umeyama_moments"]

_registered = False


def available(dtype: DTypeLike) -> bool:
    """Whether the fused kernel serves ``dtype`` arrays now (float32, extension built, not disabled)."""
    if _ffi_kernels is None or os.environ.get("SWIFTJAX_ALIGN_KERNEL", "auto") == "jax":
        return False
    return bool(jnp.dtype(dtype) == jnp.float32)


def compiler_options(dtype: DTypeLike | None) -> dict[str, Any] | None:
    """XLA options of a program whose moment passes run on ``dtype`` arrays:
    :data:`swiftjax._compile.LIGHT_COMPILE` (what the running XLA accepts of it) when the fused
    kernels do the work (:func:`available`, CPU backend), else None (XLA's defaults: the
    pure-JAX passes are the hot loop)."""
    fast = dtype is not None and available(dtype) and jax.default_backend() == "cpu"
    return supported(LIGHT_COMPILE) if fast else None


def jit(fun: Callable[..., Any], **jit_kwargs: Any) -> Callable[..., Any]:
    """``jax.jit(fun)`` whose compile fits the path a call takes.

    The options are :func:`compiler_options` of the first floating argument's dtype: when the
    fused kernels do the work the rest of the program is a few hundred small operations,
    compiled with :data:`swiftjax._compile.LIGHT_COMPILE` (docs/performance/align.md).  Each
    variant compiles once per shape, dtype and static value.
    """
    quick, full = quick_jit(fun, options=LIGHT_COMPILE, **jit_kwargs), jax.jit(fun, **jit_kwargs)

    @functools.wraps(fun)
    def call(*args: Any, **kwargs: Any) -> Any:
        leaves = jax.tree_util.tree_leaves((args, kwargs))
        dtype = next((jnp.result_type(x) for x in leaves if jnp.issubdtype(jnp.result_type(x), jnp.floating)), None)
        return (full if compiler_options(dtype) is None else quick)(*args, **kwargs)

    return call


def _register() -> None:
    global _registered
    if not _registered:
        for name, capsule in _ffi_kernels.handlers().items():
            jax.ffi.register_ffi_target(name, capsule, platform="cpu")
        _registered = True


def fused(target: str, out_shapes: Callable[..., Any], reference: Callable[..., Any], *args: Array) -> Any:
    """``reference(*args)``, computed by the FFI ``target`` on CPU when :func:`available`.

    ``out_shapes(*args)`` gives the outputs' ``jax.ShapeDtypeStruct``s (those of
    ``reference``).  ``reference`` must depend on ``args`` only (no closed-over arrays that
    are differentiated): it supplies the other platforms' values and every derivative.
    """
    if not available(args[0].dtype):
        return reference(*args)
    _register()
    call = jax.ffi.ffi_call(target, out_shapes(*args), vmap_method="broadcast_all")

    @jax.custom_jvp
    def f(*a: Array) -> Any:
        return jax.lax.platform_dependent(*a, cpu=call, default=reference)

    @f.defjvp
    def f_jvp(primals: tuple[Array, ...], tangents: tuple[Array, ...]) -> tuple[Any, Any]:
        return f(*primals), jax.jvp(reference, primals, tangents)[1]

    return f(*args)


def pixel_moments(
    dp: Array, dc: Array, cp: Array, cc: Array, params: Array, ut: Array, vt: Array, reference: Callable[..., Any]
) -> tuple[Array, Array]:
    """Per-frame pixel moments ``(S [F, 6, 3, 3], n [F])`` (``n`` int32 reliable-pixel counts).

    ``dp, dc, cp, cc [F, H, W]``, ``params [F, 6] = (r_p, r_c, e_p, e_c, gamma, lam)``,
    ``ut [W]``, ``vt [H]``; ``reference`` takes the same arguments and returns the same.  The
    kernel takes each frame's confidence means (the thresholds ``gamma mean(conf)``) in the
    same pass, while the frame is in cache.
    """
    f, h, w = dp.shape[-3:]
    lead = dp.shape[:-3]
    shapes = lambda *a: (
        jax.ShapeDtypeStruct((*lead, f, 6, 3, 3), dp.dtype),
        jax.ShapeDtypeStruct((*lead, f), jnp.int32),
    )
    return fused("swiftjax_pixel_moments", shapes, reference, dp, dc, cp, cc, params, ut, vt)


def umeyama_moments(
    src: Array, dst: Array, w: Array, centres: Array, reference: Callable[..., Any]
) -> tuple[Array, Array]:
    """``(T [..., 18], n [...])``: the centred weighted sums and count of a batched Umeyama problem.

    ``src, dst [..., N, 3]``, ``w [..., N]`` (unsanitised: points with ``w <= 0`` or a
    non-finite value are dropped), ``centres [..., 6] = (cx, cy)``; ``reference`` takes the
    same arguments and returns the same.
    """
    lead = w.shape[:-1]
    shapes = lambda *a: (jax.ShapeDtypeStruct((*lead, 18), src.dtype), jax.ShapeDtypeStruct(lead, jnp.int32))
    return fused("swiftjax_umeyama_moments", shapes, reference, src, dst, w, centres)

"""XLA options for programs whose compile costs more than their runs.

On XLA:CPU most of a first call's time is LLVM: a program that runs for milliseconds (a pose
graph step, the glue around the fused alignment kernels, the pairwise loop test) can take
seconds to compile.  :data:`QUICK_COMPILE` skips LLVM's optimisation passes
(``xla_backend_optimization_level=0``) and emits fusions with XLA's older loop emitter
(``xla_cpu_use_fusion_emitters=False``); each about halves such a compile
(docs/performance/coldstart.md has the measurements and the run-time cost).

The options go with each program (``jax.jit(..., compiler_options=...)``), not through
``XLA_FLAGS``: every process, Ray workers included, compiles the program the same way, and
no other program is affected.  They are part of the compilation-cache key.

They are XLA:CPU's and XLA's own debug options, which come and go between jaxlib releases
(jaxlib 0.11 no longer has ``xla_cpu_use_fusion_emitters``, and refuses the whole compile
when it is given): :func:`supported` keeps the ones the running XLA accepts, on the CPU
backend only (on a GPU the options would slow the programs they are meant to speed up), and
every program here is compiled with that subset.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import jax

__all__ = ["LIGHT_COMPILE", "LOOP_EMITTER", "QUICK_COMPILE", "quick_jit", "supported", "to_device"]

#: XLA's loop emitter alone, LLVM optimisation kept: for programs whose run time matters but
#: whose fusions are simple element-wise loops (``export.chunk_points``).
LOOP_EMITTER = {"xla_cpu_use_fusion_emitters": False}

#: Compiler options of the programs that run briefly (see the module docstring).
QUICK_COMPILE = {"xla_backend_optimization_level": 0, **LOOP_EMITTER}

#: Between the two: LLVM at optimisation level 1 with the loop emitter.  For programs of many
#: small operations that run often (the glue around the fused alignment kernels), where level 0
#: costs run time on every call and level 2 costs compile time once.
LIGHT_COMPILE = {"xla_backend_optimization_level": 1, **LOOP_EMITTER}


def supported(options: Mapping[str, Any]) -> dict[str, Any]:
    """The entries of ``options`` that the running XLA accepts, ``{}`` off the CPU backend.

    Each option is tried once per process on a one-operation program (a few milliseconds);
    one that XLA refuses is left out, so a jaxlib that dropped or renamed an option compiles
    with XLA's default for it instead of failing.
    """
    if jax.default_backend() != "cpu":
        return {}
    return {key: value for key, value in options.items() if _accepted(key, value)}


@functools.cache
def _accepted(key: str, value: Any) -> bool:
    import jax.numpy as jnp

    lowered = jax.jit(lambda x: x + 1).lower(jnp.zeros((), jnp.float32))
    try:
        lowered.compile(compiler_options={key: value})
    except Exception:  # XLA's own error type for an unknown option differs between releases
        return False
    return True


def quick_jit(fun=None, *, options: dict = QUICK_COMPILE, **jit_kwargs):
    """``jax.jit(fun, compiler_options=options, **jit_kwargs)`` (default :data:`QUICK_COMPILE`);
    usable as a decorator, bare or with ``jit`` keywords (``@quick_jit(static_argnames=...)``).

    JAX accepts compiler options only on the outermost ``jit``: called inside another traced
    function (whose program is compiled with that function's options), this is a plain
    ``jax.jit``.  Recompiles when ``jax.jit`` would (a new shape, dtype or static value).
    The options are :func:`supported`'s subset, taken at the first call.
    """
    if fun is None:
        return lambda f: quick_jit(f, options=options, **jit_kwargs)
    plain = jax.jit(fun, **jit_kwargs)

    @functools.cache
    def tuned_jit():
        return jax.jit(fun, compiler_options=supported(options), **jit_kwargs)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((args, kwargs))):
            return plain(*args, **kwargs)
        try:
            return tuned_jit()(*args, **kwargs)
        except ValueError as e:  # traced without traced arguments (closed over by an outer jit)
            if "top-level" not in str(e):
                raise
            return plain(*args, **kwargs)

    # ahead-of-time: ``f.trace(*args).lower().compile()`` fills the cache the calls then use
    call.trace = lambda *args, **kwargs: tuned_jit().trace(*args, **kwargs)  # type: ignore[attr-defined]
    return call


def to_device(x: Any, dtype: Any = None) -> jax.Array:
    """``jnp.asarray(x, dtype)`` for a host value, without the program JAX compiles for it.

    Outside a trace, JAX 0.10's ``jnp.asarray`` of a NumPy array runs the ``stage`` primitive,
    which compiles an identity program per shape and dtype (10-40 ms each: 46 of them in a cold
    KITTI 00 run); ``jax.device_put`` of the NumPy array moves the same values without one.
    A JAX array or a tracer is converted with ``jnp.asarray`` as before."""
    import jax.numpy as jnp
    import numpy as np

    if isinstance(x, jax.Array):
        return jnp.asarray(x, dtype)
    return jax.device_put(np.asarray(x, dtype))

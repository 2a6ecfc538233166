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
"""

from __future__ import annotations

import jax

__all__ = ["LOOP_EMITTER", "QUICK_COMPILE", "quick_jit"]

#: XLA's loop emitter alone, LLVM optimisation kept: for programs whose run time matters but
#: whose fusions are simple element-wise loops (``export.chunk_points``: compile 2.3 -> 0.9 s,
#: run 188 -> 215 ms per chunk; with :data:`QUICK_COMPILE` it would run 685 ms).
LOOP_EMITTER = {"xla_cpu_use_fusion_emitters": False}

#: Compiler options of the programs that run briefly (see the module docstring).
QUICK_COMPILE = {"xla_backend_optimization_level": 0, **LOOP_EMITTER}


def quick_jit(fun=None, **jit_kwargs):
    """``jax.jit(fun, compiler_options=QUICK_COMPILE, **jit_kwargs)``; usable as a decorator,
    bare or with ``jit`` keywords (``@quick_jit(static_argnames=...)``).  Recompiles when
    ``jax.jit`` would (a new shape, dtype or static value)."""
    if fun is None:
        return lambda f: quick_jit(f, **jit_kwargs)
    return jax.jit(fun, compiler_options=dict(QUICK_COMPILE), **jit_kwargs)

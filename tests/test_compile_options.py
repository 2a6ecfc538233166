"""swiftjax._compile: the XLA options a program is compiled with are the ones the running XLA
accepts (jaxlib 0.11 dropped ``xla_cpu_use_fusion_emitters`` and refuses a compile that names
it), and none off the CPU backend."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import _compile


def test_supported_keeps_known_options_and_drops_unknown_ones():
    known = {"xla_backend_optimization_level": 0}
    assert _compile.supported(known) == known
    unknown = {"xla_no_such_option_in_any_release": True}
    assert _compile.supported({**known, **unknown}) == known
    # What the module's presets keep compiles (each kept key was tried on this XLA).
    for preset in (_compile.QUICK_COMPILE, _compile.LIGHT_COMPILE, _compile.LOOP_EMITTER):
        kept = _compile.supported(preset)
        assert set(kept) <= set(preset)
        jax.jit(lambda x: x * 2).lower(jnp.ones(3)).compile(compiler_options=kept)


def test_supported_is_empty_off_the_cpu(monkeypatch):
    monkeypatch.setattr(_compile.jax, "default_backend", lambda: "gpu")
    assert _compile.supported(_compile.QUICK_COMPILE) == {}


def test_quick_jit_runs_when_an_option_is_unknown():
    """A preset naming an option this XLA lacks still compiles and gives jax.jit's result."""
    fun = _compile.quick_jit(lambda x: jnp.sin(x) * 3, options={"xla_no_such_option_in_any_release": 1})
    x = jnp.linspace(0, 1, 5)
    np.testing.assert_array_equal(np.asarray(fun(x)), np.asarray(jax.jit(lambda x: jnp.sin(x) * 3)(x)))

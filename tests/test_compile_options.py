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


def _compiled_during(fn) -> list[str]:
    """The programs JAX compiles while ``fn()`` runs (its compile log)."""
    from tests.conftest import jax_log

    with jax_log(r"Compiling (?:jit\()?([^) ]+)") as compiled:
        fn()
    return [name for _, name in compiled]


def test_to_device_is_jnp_asarray_without_a_compile():
    """``to_device`` gives ``jnp.asarray``'s values, dtype and weak type for host inputs (NumPy
    of several dtypes, a Python float with a dtype, float64 canonicalised) and passes JAX arrays
    through; unlike ``jnp.asarray`` of a NumPy array of a new shape, it compiles nothing."""
    rng = np.random.default_rng(0)
    cases = [
        (rng.normal(size=(3, 5)), None),
        (rng.normal(size=(4,)).astype(np.float16), None),
        (rng.integers(0, 9, size=(2, 3)), None),
        (rng.normal(size=(7,)), jnp.float32),
        (0.3, jnp.float32),
        (rng.normal(size=(2,)).astype(np.float16), jnp.float32),
        (jnp.arange(3.0), jnp.float32),
    ]
    for x, dtype in cases:
        want, got = jnp.asarray(x, dtype), _compile.to_device(x, dtype)
        assert got.dtype == want.dtype and got.aval.weak_type == want.aval.weak_type
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    fresh = rng.normal(size=(13, 17)).astype(np.float32)  # a shape no other test stages
    assert _compiled_during(lambda: _compile.to_device(fresh)) == []
    assert "stage" in _compiled_during(lambda: jnp.asarray(rng.normal(size=(17, 13)).astype(np.float32)))


def test_quick_jit_compiled_ahead_is_not_traced_or_compiled_again():
    """``quick_jit(f).trace(specs).lower().compile()`` fills the cache its calls use: a call with
    arguments of those shapes compiles nothing and gives ``f``'s values."""
    f = _compile.quick_jit(lambda x, y: jnp.sin(x) * y + 1.0)
    spec = jax.ShapeDtypeStruct((19,), jnp.float32)
    assert "<lambda>" in _compiled_during(lambda: f.trace(spec, spec).lower().compile())
    x = np.linspace(0.0, 1.0, 19, dtype=np.float32)
    out: list = []
    assert _compiled_during(lambda: out.append(f(x, x))) == []
    np.testing.assert_allclose(np.asarray(out[0]), np.sin(x) * x + 1.0, rtol=1e-6)

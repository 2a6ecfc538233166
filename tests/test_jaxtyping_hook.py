"""The tests' jaxtyping hook (tests/conftest.py) covers every public array function of the core
packages: each one's array arguments and results carry a shape (``Float[Array, "n 8"]``), and
its module is one the hook checks at run time, so a shape mismatch anywhere in the suite raises."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import re

import conftest
import pytest

#: The core packages and modules whose public functions take or return arrays.
CORE_PACKAGES = ("swiftjax.align", "swiftjax.loops", "swiftjax.posegraph")
CORE_MODULES = (
    "swiftjax.sim3",
    "swiftjax.so3",
    "swiftjax.camera",
    "swiftjax.masks",
    "swiftjax.sampling",
    "swiftjax.metric_scale",
    "swiftjax._elementary",
    "swiftjax._reductions",
)

#: Core modules the hook leaves out, and why.
NOT_HOOKED = {
    "swiftjax.align.options": "options dataclasses: no array function",
    "swiftjax.loops.options": "options dataclasses: __post_init__'s own OptionError must come first",
    "swiftjax.posegraph.options": "options dataclasses: __post_init__'s own OptionError must come first",
    "swiftjax.align._ffi_kernels": "compiled extension",
    "swiftjax.align._kernels": "Pallas/FFI kernel plumbing (private), traced by the jitted callers only",
    "swiftjax.loops._checks": "host-side input checks (private); their own errors name the input",
    "swiftjax._reductions": "a jax.custom_jvp rule (variadic operands of any shape): a wrapper would hide .defjvp",
}

#: Host-boundary checkers that take any array-like on purpose: their own ValueError naming the
#: input (not a hook's type error) is what a caller sees (tests/conftest.py).
HOST_BOUNDARY = {
    "swiftjax.sim3.check",
    "swiftjax.loops.descriptors.fit_whitening",
    "swiftjax.loops.detection.detect_loops",
    "swiftjax.loops.find.find_loops",
    "swiftjax.loops.pcm.max_consistent_set",
    "swiftjax.posegraph.blockmat.unfused",
}

_SHAPED = re.compile(r"\b(?:Float|Int|Bool|Real|Num|Shaped|Integer|UInt|Inexact|Complex|Key)\d*\[[^\[\]]*\]")
_ARRAY = re.compile(r"\b(?:Array|ArrayLike|ndarray)\b")


def _core_modules() -> list[str]:
    names = list(CORE_MODULES)
    for package in CORE_PACKAGES:
        module = importlib.import_module(package)
        names += [f"{package}.{info.name}" for info in pkgutil.iter_modules(module.__path__)]
    return names


def _original(fn):
    while hasattr(fn, "__wrapped__"):
        fn = fn.__wrapped__
    return fn


def _public_functions(module_name: str):
    module = importlib.import_module(module_name)
    for name, obj in vars(module).items():
        fn = _original(obj)
        if name.startswith("_") or not inspect.isfunction(fn) or fn.__module__ != module_name:
            continue
        yield name, obj, fn


def _array_annotations(fn) -> dict[str, str]:
    return {k: str(v) for k, v in fn.__annotations__.items() if _ARRAY.search(str(v))}


def _is_hooked(obj) -> bool:
    while obj is not None:
        if inspect.isfunction(obj) and obj.__code__.co_filename.endswith("jaxtyping/_decorator.py"):
            return True
        obj = getattr(obj, "__wrapped__", None)
    return False


@pytest.mark.parametrize("module_name", _core_modules())
def test_every_core_array_module_is_hooked(module_name):
    arrays = [name for name, _, fn in _public_functions(module_name) if _array_annotations(fn)]
    if module_name in NOT_HOOKED:
        assert module_name not in conftest.JAXTYPED_MODULES, module_name
        return
    if arrays:
        assert module_name in conftest.JAXTYPED_MODULES, (module_name, arrays)


@pytest.mark.parametrize("module_name", conftest.JAXTYPED_MODULES)
def test_the_hook_is_active_on_every_listed_module(module_name):
    functions = list(_public_functions(module_name))
    annotated = [(name, obj) for name, obj, fn in functions if fn.__annotations__]
    assert annotated, module_name
    unhooked = [name for name, obj in annotated if not _is_hooked(obj)]
    assert not unhooked, (module_name, unhooked)


@pytest.mark.parametrize("module_name", _core_modules())
def test_array_arguments_and_results_carry_a_shape(module_name):
    if module_name in NOT_HOOKED:
        return  # listed with its reason
    bare = []
    for name, _, fn in _public_functions(module_name):
        if f"{module_name}.{name}" in HOST_BOUNDARY:
            continue
        for arg, text in _array_annotations(fn).items():
            if _ARRAY.search(_SHAPED.sub("", text)):
                bare.append(f"{name}({arg}: {text})")
    assert not bare, bare


def test_the_checks_can_fail():
    # an unshaped annotation is found, a shaped one is not
    assert _ARRAY.search(_SHAPED.sub("", "tuple[Float[Array, 'n 3'], Array]"))
    assert not _ARRAY.search(_SHAPED.sub("", "tuple[Float[Array, 'n 3'], Int[ArrayLike, '']] | None"))
    from swiftjax.pipeline import config

    assert not _is_hooked(config.PipelineConfig.from_dict)

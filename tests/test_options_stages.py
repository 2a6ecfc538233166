"""The stage option classes on the one schema (swiftjax.options): every field validated with a
one-line OptionError naming it, ``replace`` with one meaning, and every PipelineConfig field
that feeds a stage option reaching it through ``options.build``."""

from __future__ import annotations

import dataclasses
import inspect
import math

import pytest

from swiftjax import align, loops, options, posegraph
from swiftjax.loops.options import GeometryOptions, VerificationConfig
from swiftjax.options import OptionError
from swiftjax.pipeline import PipelineConfig
from swiftjax.posegraph.options import PIPELINE

STAGE_CLASSES = (align.AlignOptions, posegraph.GraphOptions, loops.LoopOptions, VerificationConfig, GeometryOptions)
#: Every option class on the schema.
SCHEMA_CLASSES = STAGE_CLASSES


def _bad_values(s: options.Spec) -> list[object]:
    """Values the schema ``s`` must refuse (one per rule it states)."""
    bad: list[object] = []
    if not s.optional:
        bad.append(None)
    if s.kind is bool:
        return bad + ["no", 1]
    if s.kind is str:
        return bad + [3] + (["not-a-choice"] if s.choices is not None else [])
    bad += ["1", True]
    if s.kind is int:
        bad += [1.5, options.INT_LIMIT + 1]
    if s.kind is float and s.finite:
        bad += [math.nan, math.inf]
    if s.low is not None:
        bad.append(s.low if s.low_open else (s.low - 1 if s.kind is int else s.low - 1e-3))
    if s.high is not None:
        bad.append(s.high if s.high_open else (s.high + 1 if s.kind is int else s.high + 1e-3))
    return bad


CASES = [
    pytest.param(cls, name, value, id=f"{cls.__name__}.{name}={value!r}")
    for cls in SCHEMA_CLASSES
    for name, s in options.specs(cls).items()
    for value in _bad_values(s)
]


def test_every_stage_field_is_declared_with_the_schema():
    for cls in SCHEMA_CLASSES:
        declared = set(options.specs(cls))  # a field without option() (or nested()) is a TypeError here
        nested = {f.name for f in dataclasses.fields(cls)} - declared
        assert nested == ({"verification_config"} if cls is loops.LoopOptions else set()), cls
        for name, s in options.specs(cls).items():
            assert s.help and s.stage is None, (cls, name)  # stage: the pipeline config's fields only


@pytest.mark.parametrize("cls, name, value", CASES)
def test_the_schema_refuses_a_bad_value_naming_the_field(cls, name, value):
    with pytest.raises(OptionError) as err:
        cls(**{name: value})
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{cls.__name__}.{name}: "), message
    assert isinstance(err.value, ValueError)  # callers catching ValueError keep working
    with pytest.raises(OptionError, match=f"{cls.__name__}.{name}: "):
        cls().replace(**{name: value})  # replace validates the same way


def test_cross_field_rules_stay_in_post_init():
    with pytest.raises(
        OptionError, match="VerificationConfig.null_samples: invalid value 5; allowed: an even integer >= 4"
    ):
        VerificationConfig(null_samples=5)
    with pytest.raises(
        OptionError, match="VerificationConfig.null_min_shift: invalid value 0.5; allowed: 0 < null_min_shift <= "
    ):
        VerificationConfig(null_min_shift=0.5, null_max_shift=0.2)
    with pytest.raises(
        OptionError, match="GraphOptions.gnc_mu_step: invalid value 1.0; allowed: GNC needs gnc_mu_step > 1"
    ):
        posegraph.GraphOptions(kernel="gnc", gnc_mu_step=1.0)
    assert posegraph.GraphOptions(gnc_mu_step=1.0).gnc_mu_step == 1.0  # only GNC needs it
    with pytest.raises(
        OptionError, match="LoopOptions.verification_config: invalid value 3; allowed: a VerificationConfig"
    ):
        loops.LoopOptions(verification_config=3)


def test_values_are_normalised_like_the_pipeline_config():
    import numpy as np

    o = loops.LoopOptions(beta=1, dim=np.int64(64), adapt_to_length=np.bool_(False))
    assert (type(o.beta), type(o.dim), type(o.adapt_to_length)) == (float, int, bool)
    assert o == loops.LoopOptions(beta=1.0, dim=64, adapt_to_length=False)


# ----------------------------------------------------------------------------- replace


def test_replace_is_a_validated_copy_and_none_is_a_value():
    a = align.AlignOptions()
    b = a.replace(depth_threshold=0.3)
    assert (a.depth_threshold, b.depth_threshold) == (0.2, 0.3) and b.min_points == a.min_points
    # None is a value: refused by a field that is not optional (AlignOptions used to drop it) ...
    with pytest.raises(OptionError, match="AlignOptions.depth_threshold: invalid value None"):
        a.replace(depth_threshold=None)
    # ... and kept by one that is
    g = posegraph.GraphOptions(kernel="gnc", kernel_scale=3.0)
    assert g.replace(kernel=None, kernel_scale=None) == posegraph.GraphOptions()
    assert loops.LoopOptions(max_loops=5).replace(max_loops=None).max_loops is None
    for cls in SCHEMA_CLASSES:
        o = cls()
        assert o.replace() == o and options.replace(o) == o
        with pytest.raises(OptionError, match=f"unknown option 'no_such' of {cls.__name__}"):
            o.replace(no_such=1)
    with pytest.raises(OptionError, match=r"unknown option 'top_kk' of LoopOptions \(did you mean top_k\?\)"):
        loops.LoopOptions().replace(top_kk=3)


# ----------------------------------------------------------------------------- config -> stages


def _another(s: options.Spec, value: object, stage_spec: options.Spec) -> object:
    """A value of both schemas different from ``value``."""
    if s.kind is bool:
        return not value
    if s.choices is not None:
        return next(c for c in s.choices if c != value)
    assert isinstance(value, (int, float))
    steps = (1, -1, 2) if s.kind is int else (0.01, -0.01, 0.1 * abs(value) + 0.05)
    for step in steps:
        try:
            new = options.coerce(stage_spec, "x", options.coerce(s, "x", value + step))
        except OptionError:
            continue
        return new
    raise AssertionError(f"no other value for {s}")


def _mapped() -> dict[str, tuple[type, str]]:
    out = {}
    for name, s in options.specs(PipelineConfig).items():
        if s.target is not None:
            out[name] = s.target
    return out


def test_every_mapped_config_field_arrives_in_its_stage_options():
    mapped = _mapped()
    # every stage class is fed, and the mapping is the one the pipeline used to write by hand
    assert {cls for cls, _ in mapped.values()} == set(STAGE_CLASSES)
    assert mapped["loop_min_separation"] == (loops.LoopOptions, "min_separation")
    assert mapped["whitening_dim"] == (loops.LoopOptions, "dim")
    assert mapped["loop_pcm"] == (VerificationConfig, "pcm")
    assert mapped["robust_loops"] == (posegraph.GraphOptions, "kernel")
    assert mapped["max_lm_steps"] == (posegraph.GraphOptions, "max_steps")
    assert mapped["loop_geometry_neighbours"] == (GeometryOptions, "neighbours")
    assert mapped["loop_null_model"] == (VerificationConfig, "null_model")
    assert mapped["loop_followers"] == (VerificationConfig, "followers")
    assert mapped["loop_siblings"] == (VerificationConfig, "siblings")
    assert len(mapped) == 27
    default = PipelineConfig()
    changes = {}
    for name, (cls, field) in mapped.items():
        changes[name] = _another(options.specs(PipelineConfig)[name], getattr(default, name), options.specs(cls)[field])
    config = dataclasses.replace(default, **changes)
    built = {cls: options.build(cls, config) for cls in STAGE_CLASSES}
    for name, (cls, field) in mapped.items():
        assert getattr(built[cls], field) == changes[name] != getattr(cls(), field), name
    # the nested verification thresholds arrive through LoopOptions too
    assert built[loops.LoopOptions].verification_config == built[VerificationConfig]
    # the fields no config field feeds keep the stage class's defaults
    for cls in STAGE_CLASSES:
        targeted = {field for c, field in mapped.values() if c is cls}
        for f in dataclasses.fields(cls):
            if f.name not in targeted and f.name != "verification_config":
                assert getattr(built[cls], f.name) == getattr(cls(), f.name), (cls, f.name)


def test_default_config_builds_the_stage_defaults():
    config = PipelineConfig()
    assert options.build(align.AlignOptions, config) == align.AlignOptions()
    assert options.build(loops.LoopOptions, config) == loops.LoopOptions()
    assert options.build(posegraph.GraphOptions, config) == posegraph.GraphOptions(
        kernel=config.robust_loops, kernel_scale=config.robust_scale
    )


def test_a_target_must_name_a_stage_field():
    with pytest.raises(TypeError, match="option target LoopOptions.no_such is not a field"):
        options.option(1, "x", stage="loops", target=(loops.LoopOptions, "no_such"))
    with pytest.raises(TypeError, match="option target LoopOptions.verification_config is not a field"):
        options.option(stage="loops", target=(loops.LoopOptions, "verification_config"))
    with pytest.raises(TypeError, match="needs a default and a help text"):
        options.option(1, stage="loops")


#: The config fields whose schema narrows the stage field's (the command line's own bounds) or
#: whose default is the pipeline's own choice (PIPELINE): every other mapped field
#: takes the whole schema of its stage field.
NARROWED = {
    "min_points": {"low": (3, 0)},
    "loop_min_separation": {"low": (1, 0)},
    "robust_scale": {"optional": (False, True)},
}
PIPELINE_DEFAULTS = {"robust_loops", "robust_scale"}


def test_a_mapped_config_field_is_declared_once_in_its_stage_class():
    config_fields = {f.name: f for f in dataclasses.fields(PipelineConfig)}
    config_specs = options.specs(PipelineConfig)
    for name, (cls, field) in _mapped().items():
        stage_field = next(f for f in dataclasses.fields(cls) if f.name == field)
        mine, theirs = config_specs[name], options.spec(stage_field)
        differ = {
            k: (getattr(mine, k), getattr(theirs, k))
            for k in ("kind", "low", "high", "low_open", "high_open", "choices", "optional", "finite")
            if getattr(mine, k) != getattr(theirs, k)
        }
        assert differ == NARROWED.get(name, {}), name
        # the help is the stage field's, its {references} in the config's names
        assert options.spec(config_fields[name]).help == theirs.help, name
        if name in PIPELINE_DEFAULTS:
            assert config_fields[name].default == getattr(PIPELINE, field if field != "kernel_scale" else "scale")
        else:
            assert config_fields[name].default == stage_field.default, name
    # a reference to another field is written in the words of the class shown
    assert "fixed (loop_threshold)" in config_specs["loop_threshold_rule"].help
    assert "fixed (threshold)" in options.specs(loops.LoopOptions)["rule"].help
    assert "must reach loop_min_agreement" in config_specs["loop_agreement"].help
    assert "must reach min_agreement" in options.specs(VerificationConfig)["agreement_rule"].help
    assert "{" not in "".join(s.help for s in config_specs.values())


def test_config_accessors_are_the_built_stage_objects():
    config = PipelineConfig(loop_top_k=3, depth_threshold=0.3, loop_pcm=False, max_lm_steps=7, robust_loops="huber")
    assert config.align == align.AlignOptions(depth_threshold=0.3)
    assert config.loops == loops.LoopOptions(top_k=3, verification_config=VerificationConfig(pcm=False))
    assert config.verification == config.loops.verification_config == VerificationConfig(pcm=False)
    assert config.graph == posegraph.GraphOptions(max_steps=7, kernel="huber", kernel_scale=PIPELINE.scale)
    assert PipelineConfig().graph == PIPELINE


def test_default_stage_options_are_the_recorded_ones():
    """The run directory fingerprints each stage by these values: a changed default would make
    every existing run redo its stages (hash of the default config of 151f7dd; since issue 28's
    ``loop_geometry_neighbours``, ``loop_null_model`` (whose default ``trend`` replaced the
    pooled null), ``loop_followers`` and ``loop_siblings`` (now off by default), a run directory made before them
    redoes its loop stage once, saying so, and keeps its chunks)."""
    import hashlib
    import json

    config = PipelineConfig()
    stages = {s: config.stage_options(s) for s in options.STAGES}
    digest = hashlib.sha256(json.dumps(stages, sort_keys=True).encode()).hexdigest()
    assert digest == "eb9af25cb273e60faf6a67f2e889b01d7a9d227b1cc8f7c352beea3f1817a8a7", stages


def test_no_override_keywords_on_the_stage_entry_points():
    for fn, allowed in (
        (loops.find_loops, {"descriptors", "schedule", "options", "throw", "return_details"}),
        (posegraph.optimize, {"problem", "options", "throw", "pad"}),
        (align.align_chunk_pair, {"prev", "cur", "K_ref", "options", "mask"}),
        (align.align_chunk_pairs, {"prev", "cur", "K_ref", "options", "mask"}),
        (align.align_chunk_pair_checked, {"prev", "cur", "K_ref", "name", "throw", "options", "mask"}),
    ):
        params = inspect.signature(fn).parameters
        assert set(params) == allowed, fn.__name__
        assert not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()), fn.__name__


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(tau_end=4.0), r"GeometryOptions\.tau_end: invalid value 4\.0; allowed: at most tau_start = 3\.0$"),
        (
            dict(coarse_tau_start=0.4),
            r"GeometryOptions\.coarse_tau_end: invalid value 0\.5; allowed: at most coarse_tau_start = 0\.4$",
        ),
        (
            dict(coarse_src_points=2048),
            r"GeometryOptions\.coarse_src_points: invalid value 2048; allowed: at most src_points = 1024 \(its first",
        ),
        (
            dict(dst_points=1024),
            r"GeometryOptions\.coarse_dst_points: invalid value 4096; allowed: at most dst_points = 1024 \(its first",
        ),
    ],
)
def test_geometry_options_cross_field_rules(changes, match):
    with pytest.raises(OptionError, match=match):
        GeometryOptions(**changes)
    assert GeometryOptions(row_stride=3, column_stride=4).pixel_stride == (3, 4)


def test_graph_options_take_the_solver_objects_defaults():
    from swiftjax.posegraph.linear_solvers import BlockJacobiPCG, linear_solver
    from swiftjax.posegraph.solver import SparseSim3LM

    lm, pcg, g = SparseSim3LM(), BlockJacobiPCG(), posegraph.GraphOptions()
    assert (g.rtol, g.atol, g.gtol, g.lambda0, g.damping) == (lm.rtol, lm.atol, lm.gtol, lm.lambda0, lm.damping)
    assert (g.max_linear_iterations, g.eta_max) == (pcg.max_iterations, pcg.eta_max)
    assert linear_solver("pcg") == pcg and linear_solver("pcg", max_iterations=7).max_iterations == 7

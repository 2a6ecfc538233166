"""The typed option schema (swiftjax.options): one declaration per PipelineConfig field gives
validation, the CLI flags and TOML parsing."""

from __future__ import annotations

import dataclasses
import math
import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swiftjax import cli, options
from swiftjax.cli import arguments
from swiftjax.options import OptionError
from swiftjax.pipeline import PipelineConfig

SPECS = options.specs(PipelineConfig)


def test_every_field_has_a_schema_a_flag_and_a_description():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, type(parser._subparsers._group_actions[0])))
    for command in ("demo", "reconstruct"):
        p = sub.choices[command]
        flags = {s for a in p._actions for s in a.option_strings}
        helps = {s: a.help for a in p._actions for s in a.option_strings}
        for f in dataclasses.fields(PipelineConfig):
            s = SPECS[f.name]
            assert s.stage in options.STAGES and len(s.help) > 15, f.name
            flag = options.flag(f.name)
            assert flag in flags, flag
            assert "default:" in helps[flag] and s.help in helps[flag]
            if s.choices:
                assert all(c in helps[flag] for c in s.choices)
            if s.kind is bool:
                assert "--no-" + flag[2:] in flags


@pytest.mark.parametrize(
    "table, fragment",
    [
        ({"loop_closure": "no"}, "loop_closure (c.toml): 'no' is not a boolean; allowed: true or false"),
        ({"loop_closure": 1}, "loop_closure (c.toml): 1 is not a boolean"),
        ({"overlap": True}, "overlap (c.toml): True is not a number; allowed: an integer with 1 <= value <= 9999"),
        (
            {"chunk_size": 60.7},
            "chunk_size (c.toml): 60.7 is not an integer; allowed: an integer with 2 <= value <= 10000",
        ),
        ({"chunk_size": 60.0}, "chunk_size (c.toml): 60.0 is not an integer"),
        ({"min_points": math.inf}, "min_points (c.toml): inf"),  # what TOML makes of 1e400
        ({"conf_ratio": -1}, "conf_ratio (c.toml): -1 is out of range; allowed: a finite number with 0 <= value <= 10"),
        ({"depth_threshold": math.nan}, "depth_threshold (c.toml): nan is not finite"),
        ({"depth_threshold": -1.0}, "depth_threshold (c.toml): -1.0 is out of range; allowed: a finite number > 0"),
        ({"point_conf_ratio": 1e9}, "point_conf_ratio (c.toml): 1000000000.0 is out of range"),
        ({"voxel_size": -1.0}, "voxel_size (c.toml): -1.0 is out of range; allowed: a finite number > 0 (or none)"),
        ({"colmap_max_points": -1}, "colmap_max_points (c.toml): -1 is out of range"),
        ({"robust_loops": "tukey"}, "robust_loops (c.toml): invalid value 'tukey'; allowed: one of gnc, cauchy, huber"),
        ({"alignment": "UMEYAMA"}, "alignment (c.toml): invalid value 'UMEYAMA'; allowed: one of umeyama, irls"),
        ({"chunk_sise": 60}, "unknown configuration key 'chunk_sise' in c.toml (did you mean chunk_size?)"),
    ],
)
def test_toml_values_are_typed_never_truthy(table, fragment):
    with pytest.raises(OptionError) as err:
        options.from_sources(PipelineConfig, table, file_name="c.toml")
    assert fragment in str(err.value) and "\n" not in str(err.value)


def test_none_spelling_and_int_to_float():
    cfg = options.from_sources(PipelineConfig, {"robust_loops": "none", "voxel_size": "none", "depth_threshold": 1})
    assert cfg.robust_loops is None and cfg.voxel_size is None
    assert isinstance(cfg.depth_threshold, float) and cfg == PipelineConfig(depth_threshold=1.0, robust_loops=None)
    assert PipelineConfig(depth_threshold=1).to_dict() == PipelineConfig(depth_threshold=1.0).to_dict()
    cfg = options.from_sources(PipelineConfig, {"chunk_size": 60}, {"chunk_size": "50", "robust_loops": "huber"})
    assert cfg.chunk_size == 50 and cfg.robust_loops == "huber"  # the flag wins


def test_cross_option_rules():
    with pytest.raises(
        OptionError, match=r"^PipelineConfig.overlap: invalid value 75; allowed: 1 <= overlap < chunk_size \(75\)"
    ):
        PipelineConfig(overlap=75)
    with pytest.raises(OptionError, match="loop_half_window"):
        PipelineConfig(chunk_size=10, overlap=3, loop_half_window=6)
    PipelineConfig(chunk_size=10, overlap=3, loop_half_window=6, loop_closure=False)  # unused then


def test_stage_options_partition_the_fields():
    c = PipelineConfig()
    parts = [c.stage_options(s) for s in options.STAGES]
    assert sum(len(p) for p in parts) == len(dataclasses.fields(PipelineConfig))
    assert "voxel_size" in parts[options.STAGES.index("export")]
    assert "chunk_size" in parts[options.STAGES.index("temporal")]


def _check_accepted(cfg):
    for name, s in SPECS.items():
        v = getattr(cfg, name)
        if v is None:
            assert s.optional, name
            continue
        assert type(v) is s.kind, (name, v)
        if s.kind in (int, float):
            assert math.isfinite(v) or not s.finite
            assert s.low is None or v > s.low or (v == s.low and not s.low_open), (name, v)
            assert s.high is None or v < s.high or (v == s.high and not s.high_open), (name, v)
        if s.choices:
            assert v in s.choices


_values = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(["no", "yes", "true", "none", "huber", "irls", "1", "0.5", "", "nan", "1e400"]),
)


@settings(deadline=None, max_examples=300)
@given(st.dictionaries(st.sampled_from(sorted(SPECS)), _values, max_size=4))
def test_random_toml_values_never_reach_the_pipeline_unvalidated(table):
    try:
        cfg = options.from_sources(PipelineConfig, table, file_name="x.toml")
    except OptionError as err:
        assert "\n" not in str(err) and re.match(r"(\w+ \(x\.toml\)|PipelineConfig\.\w+): |unknown", str(err)), err
        return
    _check_accepted(cfg)


@settings(deadline=None, max_examples=200)
@given(
    st.dictionaries(
        st.sampled_from(sorted(n for n, s in SPECS.items() if s.kind is not bool)),
        st.text(max_size=8) | st.sampled_from(["-1", "1e400", "nan", "60.7", "none", "75", "0"]),
        max_size=3,
    )
)
def test_random_command_line_values_are_validated_like_toml(flags):
    argv = ["demo"]
    for name, text in flags.items():
        argv.append(f"{options.flag(name)}={text}")
    try:
        args = cli.build_parser().parse_args(argv)
    except SystemExit:  # argparse refused the token itself (e.g. a value starting with '-')
        return
    try:
        cfg = arguments.pipeline_config(args)
    except cli.CliError as err:
        assert "\n" not in str(err) and "invalid" in str(err)
        return
    _check_accepted(cfg)

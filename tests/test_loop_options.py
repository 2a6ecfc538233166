"""LoopOptions (defaults written once), the schedule-taking loop-chunk API and ``throw=`` of
swiftjax.loops."""

from __future__ import annotations

import dataclasses
import importlib

import jax
import numpy as np
import pytest
from test_loops import planted

from swiftjax import loops as L
from swiftjax.chunks import chunk_schedule
from swiftjax.loops import verification as V
from swiftjax.loops.options import LoopOptions
from swiftjax.options import OptionError, build
from swiftjax.pipeline.config import PipelineConfig


def test_pipeline_config_takes_the_loop_defaults():
    o = build(LoopOptions, PipelineConfig())
    assert o == LoopOptions()  # every PipelineConfig loop default is LoopOptions's
    cfg = PipelineConfig(loop_top_k=3, loop_min_agreement=0.6, loop_pcm=False, whitening_dim=64)
    o = build(LoopOptions, cfg)
    assert (o.top_k, o.dim, o.verification_config.min_agreement, o.verification_config.pcm) == (3, 64, 0.6, False)


def test_function_defaults_come_from_loop_options():
    import inspect

    d = LoopOptions()
    sig = inspect.signature(L.detect_loops).parameters
    assert (
        sig["threshold"].default,
        sig["min_separation"].default,
        sig["nms_radius"].default,
        sig["top_k"].default,
        sig["nms"].default,
        sig["false_alarms"].default,
    ) == (d.threshold, d.min_separation, d.nms_radius, d.top_k, d.nms, d.false_alarms)
    sig = inspect.signature(L.fit_whitening).parameters
    assert (sig["remove"].default, sig["dim"].default, sig["eps"].default) == (d.remove, d.dim, d.eps)
    from swiftjax.align import AlignOptions

    for fn in (V.dense_consistency, V.cross_chunk_consistency):  # the dense test takes the VerificationConfig
        sig = inspect.signature(fn).parameters
        assert sig["config"].default is None and "stride" not in sig
        assert sig["conf_ratio"].default == AlignOptions().conf_ratio  # λ_γ, the alignment's


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"rule": "auto"}, "LoopOptions.rule: invalid value 'auto'; allowed: one of adaptive"),
        ({"fit_on": "g0"}, "LoopOptions.fit_on: invalid value 'g0'"),
        ({"nms": "box"}, "LoopOptions.nms: invalid value 'box'"),
        ({"false_alarms": 1.0}, "LoopOptions.false_alarms: 1.0 is out of range"),
        ({"top_k": 0}, "LoopOptions.top_k: 0 is out of range; allowed: an integer with 1 <= value <= 1000"),
        ({"verification": "maybe"}, "LoopOptions.verification: invalid value 'maybe'"),
    ],
)
def test_loop_options_reject_bad_values(bad, match):
    with pytest.raises(OptionError, match=match):
        LoopOptions(**bad)


def test_find_loops_takes_an_options_object_only():
    G = planted(n=600, d=256, seed=19, loops=((400, 50, 30), (560, 300, 20)), noise=0.05)
    sched = chunk_schedule(600)
    b = L.find_loops(G, sched, LoopOptions(dim=128, rule="fixed", threshold=0.7))
    c = L.find_loops(G, sched, LoopOptions(dim=128).replace(rule="fixed", threshold=0.7))
    key = lambda loops: [(lp.i, lp.j, lp.score, lp.frames.tolist()) for lp in loops]
    assert key(b) == key(c) and len(b) == 2
    with pytest.raises(TypeError):
        L.find_loops(G, sched, dim=128)  # no override keywords


def test_find_loops_throw_false_leaves_nonfinite_rows_out(logged_warning):
    G = planted(n=600, d=256, seed=19, loops=((400, 50, 30), (560, 300, 20)), noise=0.05)
    sched = chunk_schedule(600)
    bad = G.copy()
    bad[3, 0] = np.nan
    bad[410] = np.inf  # inside the first planted loop region
    with pytest.raises(ValueError, match="NaN or Inf"):
        L.find_loops(bad, sched, LoopOptions(dim=128))
    with logged_warning("2 descriptor row"):
        loops, details = L.find_loops(
            bad, sched, LoopOptions(dim=128, rule="fixed", threshold=0.7), throw=False, return_details=True
        )
    np.testing.assert_array_equal(details["nonfinite_rows"], [3, 410])
    assert {(lp.i - lp.j) for lp in loops} == {350, 260}
    assert all(410 != lp.i and 3 != lp.j for lp in loops)
    # the adaptive rule too: the non-finite rows never become candidates
    with logged_warning("2 descriptor row"):
        _, details = L.find_loops(bad, sched, LoopOptions(dim=128), throw=False, return_details=True)
    c = details["candidates"]
    assert not np.isin(np.asarray(c.pairs)[: int(c.count)], [3, 410]).any()


def test_detect_and_fit_throw_false_skip_the_host_check():
    rng = np.random.default_rng(0)
    Z = rng.normal(size=(300, 16)).astype(np.float32)
    Z[17] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        L.detect_loops(Z, 0.5)
    cand = L.detect_loops(Z, 0.5, throw=False)
    assert not np.any(np.asarray(cand.pairs)[: int(cand.count)] == 17)
    with pytest.raises(ValueError, match="NaN or Inf"):
        L.fit_whitening(Z, dim=8)
    w = L.fit_whitening(Z, dim=8, throw=False)
    assert not np.all(np.isfinite(np.asarray(w.projection)))


def test_loop_chunk_frames_takes_the_schedule_and_vmaps_over_the_ends():
    sched = chunk_schedule(400)
    with pytest.raises(TypeError, match="unexpected keyword"):
        L.loop_chunk_frames(1, 2, sched, chunk_size=75)
    # vmap over the ends, schedule closed over: row by row the single calls
    ends_i, ends_j = np.array([399, 250]), np.array([0, 50])
    lc = jax.vmap(lambda a, b: L.loop_chunk_frames(a, b, sched))(ends_i, ends_j)
    for k in range(2):
        one = L.loop_chunk_frames(int(ends_i[k]), int(ends_j[k]), sched)
        for a, b in zip(lc, one):
            np.testing.assert_array_equal(np.asarray(a)[k], b)


def test_chunk_of_arrays():
    sched = chunk_schedule(400)
    frames = np.arange(400)
    np.testing.assert_array_equal(sched.chunk_of(frames), [sched.chunk_of(int(f)) for f in frames])
    assert isinstance(sched.chunk_of(5), int)


def test_loop_verification_lives_in_the_loops_package_only():
    # the top-level compatibility module is gone (issue 31): one import path, named everywhere
    import pathlib

    import swiftjax

    root = pathlib.Path(swiftjax.__file__).parent
    assert not (root / "loop_verification.py").exists()
    stale = [p.name for p in root.rglob("*.py") if "swiftjax.loop_verification" in p.read_text(encoding="utf-8")]
    assert stale == []
    assert importlib.import_module("swiftjax.loops.verification").verify_candidates is V.verify_candidates


def test_loops_keeps_its_public_names():
    import __future__

    import sys
    import types

    before = [
        "frame_descriptor",
        "power_normalize",
        "Whitening",
        "fit_whitening",
        "whiten",
        "LoopCandidates",
        "ThresholdCalibration",
        "calibrate_threshold",
        "detect_loops",
        "LoopChunk",
        "loop_chunk_frames",
        "filter_by_chunks",
        "loop_edge",
        "Loop",
        "find_loops",
        "DEFAULT_THRESHOLD",
        "AUTHORS_THRESHOLD",
        "DEFAULT_FALSE_ALARMS",
        "THRESHOLD_RULES",
    ]
    assert set(before) <= set(L.__all__)
    assert len(L.__all__) == len(set(L.__all__))
    # __all__ is exactly what the package exposes (a name imported but not listed, or listed but gone, fails)
    exposed = {
        n
        for n, v in vars(L).items()
        if not n.startswith("_") and not isinstance(v, (types.ModuleType, __future__._Feature))
    }
    assert exposed == set(L.__all__)
    # each function and class is the one its defining submodule of swiftjax.loops holds under that name
    for name in L.__all__:
        obj = getattr(L, name)
        if isinstance(obj, (type, types.FunctionType)) or hasattr(obj, "__wrapped__"):
            assert obj.__module__.startswith("swiftjax.loops."), name
            assert getattr(sys.modules[obj.__module__], name) is obj, name
    assert dataclasses.is_dataclass(L.LoopOptions) and L.LoopOptions.__dataclass_params__.frozen

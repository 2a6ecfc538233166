"""The pipeline's stages compose to the same outputs however the run is carried out.

Every output file of a run (poses, PLY, COLMAP, intrinsics, loops, plot, chunk store,
metrics without the timings) must be the same bytes when the run was interrupted and
resumed during the loop stage (after the temporal chunks are recorded nothing is
recomputed from the float16 chunk store that the uninterrupted run computed from the
predictions).
"""

from __future__ import annotations

import json
import pathlib
import zipfile

import numpy as np
import pytest
from test_pipeline import CountingPredictor, FailingPredictor, Interrupted

from swiftjax import pipeline
from swiftjax.synthetic import demo
from swiftjax.synthetic.routes import loop_route

CONFIG = pipeline.PipelineConfig(
    chunk_size=30,
    overlap=10,
    loop_min_separation=50,
    loop_nms_radius=10,
    loop_half_window=8,
    point_stride=3,
    colmap_max_points=2_000,
)
IMAGE_HW = (28, 98)


def _without_timings(metrics: dict) -> dict:
    out = dict(metrics)
    out.pop("timings_seconds", None)
    out["pose_graph"] = {
        k: v for k, v in out.get("pose_graph", {}).items() if k not in ("compile_seconds", "solve_seconds")
    }
    return out


def assert_same_outputs(a: pathlib.Path, b: pathlib.Path, *, manifest: bool = True) -> None:
    """Every file under ``a`` and ``b`` equal: bytes, except ``metrics.json`` (timings
    dropped) and chunk ``.npz`` files (member by member: zip headers carry write times)."""
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert files_a == files_b
    assert any(p.suffix == ".ply" for p in files_a) and any(p.parts[0] == "colmap" for p in files_a)
    for rel in files_a:
        x, y = a / rel, b / rel
        if rel.name == "metrics.json":
            assert _without_timings(json.loads(x.read_text())) == _without_timings(json.loads(y.read_text())), rel
        elif rel.name == "manifest.json":
            if manifest:
                assert json.loads(x.read_text()) == json.loads(y.read_text()), rel
        elif rel.suffix == ".npz":
            with zipfile.ZipFile(x) as zx, zipfile.ZipFile(y) as zy:
                assert sorted(zx.namelist()) == sorted(zy.namelist()), rel
                for name in zx.namelist():
                    assert zx.read(name) == zy.read(name), (rel, name)
        else:
            assert x.read_bytes() == y.read_bytes(), rel


@pytest.fixture(scope="module")
def route():
    poses = loop_route(width=40.0, length=25.0, corner_radius=8.0, laps=1.35)
    return demo.trajectory_run(poses, seed=5, image_hw=IMAGE_HW)


@pytest.fixture(scope="module")
def reference(route, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("reference")
    res = pipeline.reconstruct(route.predictor, run_dir, CONFIG, ground_truth=route.ground_truth, progress=False)
    assert len(res.loops) >= 2  # the resume test interrupts the second loop chunk
    return res


def test_run_interrupted_in_the_loop_stage_resumes_to_identical_outputs(route, reference, tmp_path):
    T, L = reference.num_chunks, len(reference.loops)
    run_dir = tmp_path / "resumed"
    failing = FailingPredictor(route.predictor, fail_at=T + 2)  # the second loop chunk
    with pytest.raises(Interrupted):
        pipeline.reconstruct(failing, run_dir, CONFIG, ground_truth=route.ground_truth, progress=False)
    recorded = json.loads((run_dir / "manifest.json").read_text())
    assert len(recorded["chunks"]) == T and len(recorded["edges"]) == T - 1
    assert len(recorded["loop_edges"]) == 1
    again = CountingPredictor(route.predictor)
    out = pipeline.reconstruct(again, run_dir, CONFIG, ground_truth=route.ground_truth, progress=False)
    assert again.calls == L - 1  # only the loop chunks not recorded
    np.testing.assert_array_equal(out.chunk_poses, reference.chunk_poses)
    assert_same_outputs(run_dir, reference.run_dir)


def test_the_loop_stage_takes_its_candidates_from_the_source_it_is_given(route, reference, tmp_path):
    """``reconstruct(loop_candidates=...)``: the loop stage verifies what the source proposes
    (here the default detector's candidates less all but the first), nothing else."""
    from swiftjax import loops

    seen, proposed = [], []

    def first_only(descriptors, schedule, options):
        seen.append((descriptors.shape[0], schedule.num_chunks))
        found = [lp for lp in loops.find_loops(descriptors, schedule, options) if abs(lp.chunk_i - lp.chunk_j) >= 2]
        proposed.extend(found[:1])
        return found[:1]

    res = pipeline.reconstruct(
        route.predictor,
        tmp_path / "run",
        CONFIG,
        ground_truth=route.ground_truth,
        progress=False,
        loop_candidates=first_only,
        log=lambda s: None,
    )
    assert seen == [(route.predictor.num_frames, reference.num_chunks)] and len(proposed) == 1
    assert [(r["i"], r["j"]) for r in res.loop_candidates] == [(proposed[0].i, proposed[0].j)]
    assert len(reference.loop_candidates) >= 2  # the default source proposes more

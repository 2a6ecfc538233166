"""End-to-end pipeline on a small synthetic loop route: outputs, loop closure, resumability.

One module-scoped run (small images, short chunks) is shared by the checks; it exercises
every stage: prediction through the oracle, alignment, loop detection and loop-centric
chunks, the pose graph and the export pass.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from _extras import require_extra

from swiftjax import chunks, evaluation, pipeline
from swiftjax.io import ply, trajectory
from swiftjax.synthetic import demo
from swiftjax.synthetic.routes import loop_route

CONFIG = pipeline.PipelineConfig(
    chunk_size=40,
    overlap=15,
    loop_min_separation=60,
    loop_nms_radius=10,
    point_stride=2,
    colmap_max_points=5_000,
)
IMAGE_HW = (42, 140)


class CountingPredictor:
    """Wraps a predictor and counts the frames it was asked for."""

    def __init__(self, inner):
        self.inner = inner
        self.num_frames = inner.num_frames
        self.calls = 0

    def predict(self, frames):
        self.calls += 1
        return self.inner.predict(frames)

    def fingerprint(self):
        return self.inner.fingerprint()

    def frame_names(self):
        return self.inner.frame_names()


#: A look-alike pair planted in the small route's place tokens (frames 187-206 resemble
#: 86-105, ~60 m apart): the detector proposes a false loop, verification must reject it.
ALIASING = ((187, 86, 20),)


@pytest.fixture(scope="module")
def small_run():
    poses = loop_route(width=60.0, length=40.0, corner_radius=10.0, laps=1.3)
    return demo.trajectory_run(poses, seed=3, image_hw=IMAGE_HW, aliasing=ALIASING)


def loop_chunks_predicted(result):
    """Candidates that got a loop chunk (all but those between neighbouring chunks)."""
    return sum("align_i" in r for r in result.loop_candidates)


@pytest.fixture(scope="module")
def result(small_run, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("run")
    predictor = CountingPredictor(small_run.predictor)
    res = pipeline.reconstruct(predictor, run_dir, CONFIG, ground_truth=small_run.ground_truth, progress=False)
    res.calls = predictor.calls
    return res


def test_every_chunk_and_loop_chunk_was_predicted_once(result):
    schedule = chunks.chunk_schedule(result.num_frames, CONFIG.chunk_size, CONFIG.overlap)
    assert result.num_chunks == schedule.num_chunks
    assert result.calls == schedule.num_chunks + loop_chunks_predicted(result)


def test_loop_closure_finds_the_revisit_and_reduces_drift(result, small_run):
    assert len(result.loops) >= 1
    for lp in result.loops:
        assert lp["i"] - lp["j"] > CONFIG.loop_min_separation
        # A true revisit: the two frames are close in the world.
        gap = np.linalg.norm(small_run.ground_truth[lp["i"], :3, 3] - small_run.ground_truth[lp["j"], :3, 3])
        assert gap < 5.0
    m = result.metrics
    assert m["pose_graph"]["converged"]
    assert m["ate_rmse"] < m["ate_rmse_no_loops"]
    extent = np.ptp(small_run.ground_truth[:, :3, 3], axis=0).max()
    assert m["ate_rmse"] < 0.02 * extent


def test_loop_candidates_are_verified_and_recorded(result, small_run):
    """The planted look-alike is proposed and rejected; every candidate is in loops.txt,
    metrics.json and the manifest with its verdict."""
    gt = small_run.ground_truth[:, :3, 3]
    cands = result.loop_candidates
    gap = {(r["i"], r["j"]): np.linalg.norm(gt[r["i"]] - gt[r["j"]]) for r in cands}
    false = [r for r in cands if gap[r["i"], r["j"]] > 20.0]
    assert false and not any(r["accepted"] for r in false)
    assert all(
        any(w in r["reason"] for w in ("disagree", "than under wrong edges", "do not see", "pairwise")) for r in false
    )
    assert [r for r in cands if r["accepted"]] == result.loops and len(result.loops) >= 1
    lines = (result.run_dir / "loops.txt").read_text().splitlines()
    keys = [x for x in lines if x.startswith("#")][-1][2:].split()
    rows = [dict(zip(keys, x.split(maxsplit=len(keys) - 1))) for x in lines if not x.startswith("#")]
    assert [(int(x["i"]), int(x["j"]), x["accepted"] == "yes", x["reason"]) for x in rows] == [
        (r["i"], r["j"], r["accepted"], " ".join(r["reason"].split())) for r in cands
    ]
    metrics = json.loads((result.run_dir / "metrics.json").read_text())
    assert [(c["i"], c["j"], c["accepted"]) for c in metrics["loop_candidates"]] == [
        (r["i"], r["j"], r["accepted"]) for r in cands
    ]
    manifest = json.loads((result.run_dir / "manifest.json").read_text())
    for r in cands:
        if "align_i" in r:
            stored = manifest["loop_edges"][f"{r['i']}-{r['j']}"]
            assert stored["accepted"] == r["accepted"] and stored["dense_agreement"] == r["dense_agreement"]


def test_trajectory_files_round_trip_with_orthonormal_rotations(result):
    kitti = trajectory.read_kitti(result.run_dir / "poses_kitti.txt")
    assert kitti.shape == (result.num_frames, 4, 4)
    np.testing.assert_allclose(kitti, result.cam_to_world, atol=1e-6 * np.abs(result.cam_to_world).max())
    R = kitti[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-6)
    stamps, tum = trajectory.read_tum(result.run_dir / "poses_tum.txt")
    np.testing.assert_array_equal(stamps, np.arange(result.num_frames))
    np.testing.assert_allclose(tum[:, :3, 3], kitti[:, :3, 3], atol=1e-6 * np.abs(kitti).max())
    # ATE recomputed from the written file agrees with metrics.json.
    metrics = json.loads((result.run_dir / "metrics.json").read_text())
    assert metrics["loops"] == len(result.loops)


def test_point_cloud_lies_on_the_true_surfaces(result, small_run):
    cloud = ply.read_ply(result.run_dir / "points.ply")
    assert cloud.points.shape[0] == result.metrics["points"] > 1000
    assert cloud.colors is not None and cloud.conf is not None
    # Map the estimated cloud into the true world frame with the trajectory's Sim(3) alignment
    # and compare to true points of a few frames (Chamfer accuracy, metres).
    a = evaluation.ate(result.cam_to_world[:, :3, 3], small_run.ground_truth[:, :3, 3])
    pts = a.scale * cloud.points.astype(np.float64) @ a.rotation.T + a.translation
    oracle = small_run.predictor.oracle
    frames = np.arange(0, result.num_frames, 25)
    gt_pts, valid = oracle.true_world_points(frames)
    gt = gt_pts[valid][::7]
    sample = pts[np.random.default_rng(0).choice(len(pts), 20_000, replace=False)]
    ch = evaluation.chamfer(sample, gt)
    assert ch.accuracy < 1.0  # median-ish metres on a ~60 m route with a 0.5 m ATE budget


def test_colmap_model_reads_back(result):
    pycolmap = require_extra("pycolmap")
    rec = pycolmap.Reconstruction(str(result.run_dir / "colmap" / "sparse" / "0"))
    assert rec.num_reg_images() == result.num_frames
    assert rec.num_points3D() > 100


def test_rerun_resumes_without_predicting(small_run, result):
    predictor = CountingPredictor(small_run.predictor)
    again = pipeline.reconstruct(predictor, result.run_dir, CONFIG, ground_truth=small_run.ground_truth, progress=False)
    assert predictor.calls == 0
    np.testing.assert_array_equal(again.cam_to_world, result.cam_to_world)


def test_changed_config_or_input_is_refused_unless_overwrite(small_run, result, tmp_path):
    other = dataclasses.replace(CONFIG, depth_threshold=0.3)
    with pytest.raises(pipeline.RunDirError, match="depth_threshold"):
        pipeline.reconstruct(small_run.predictor, result.run_dir, other, progress=False)
    shorter = demo.trajectory_run(small_run.ground_truth[:100], seed=3, image_hw=IMAGE_HW)
    with pytest.raises(pipeline.RunDirError, match="different input"):
        pipeline.reconstruct(shorter.predictor, result.run_dir, CONFIG, progress=False)
    # --overwrite on a fresh copy of the run directory starts afresh.
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(result.run_dir, copy)
    out = pipeline.reconstruct(
        shorter.predictor, copy, dataclasses.replace(CONFIG, loop_closure=False), overwrite=True, progress=False
    )
    assert out.num_frames == 100


def test_single_short_chunk_runs(tmp_path, small_run):
    few = demo.trajectory_run(small_run.ground_truth[:12], seed=1, image_hw=IMAGE_HW)
    out = pipeline.reconstruct(few.predictor, tmp_path / "few", CONFIG, progress=False)
    assert out.num_chunks == 1 and out.loops == []
    assert trajectory.read_kitti(tmp_path / "few" / "poses_kitti.txt").shape == (12, 4, 4)


def test_chain_poses_composes_relative_edges(x64):
    from swiftjax import sim3

    rng = np.random.default_rng(0)
    rel = np.asarray(sim3.exp(rng.normal(scale=0.3, size=(5, 7))))
    chained = pipeline.chain_poses(rel)
    m = np.eye(4)
    np.testing.assert_allclose(chained[0], np.asarray(sim3.identity((), np.float64)))
    for k in range(5):
        m = m @ np.asarray(sim3.as_matrix(rel[k]))
        np.testing.assert_allclose(np.asarray(sim3.as_matrix(chained[k + 1])), m, atol=1e-10)


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="overlap"):
        pipeline.PipelineConfig(chunk_size=30, overlap=30)
    with pytest.raises(ValueError, match="unknown configuration key 'bogus'"):
        pipeline.PipelineConfig.from_dict({"bogus": 1})


def test_irls_alignment_option_runs_the_baseline(tmp_path, small_run):
    few = demo.trajectory_run(small_run.ground_truth[:70], seed=2, image_hw=IMAGE_HW)
    out_u = pipeline.reconstruct(few.predictor, tmp_path / "u", CONFIG, progress=False)
    out_i = pipeline.reconstruct(
        few.predictor, tmp_path / "i", dataclasses.replace(CONFIG, alignment="irls"), progress=False
    )
    # Same reliable points, a different estimator: the chunk poses agree closely, not exactly.
    np.testing.assert_allclose(out_i.chunk_poses, out_u.chunk_poses, atol=5e-2)
    assert not np.array_equal(out_i.chunk_poses, out_u.chunk_poses)


class Interrupted(Exception):
    pass


class FailingPredictor(CountingPredictor):
    """Raises on call ``fail_at`` (1-based), like a Ctrl-C in the middle of a run."""

    def __init__(self, inner, fail_at):
        super().__init__(inner)
        self.fail_at = fail_at

    def predict(self, frames):
        if self.calls + 1 == self.fail_at:
            raise Interrupted
        return super().predict(frames)


def test_interrupted_run_resumes_after_the_last_complete_chunk(small_run, result, tmp_path):
    """Chunk files are written in the background and recorded in the manifest (fsync'd) as
    each completes: an interruption keeps every complete chunk, and the re-run predicts only
    the rest.  The outputs are bit-identical to the uninterrupted run's (the edge (2, 3) is
    re-aligned from chunk 2's float32 tail, not its float16 copy; the tail is removed once
    that edge is recorded)."""
    run_dir = tmp_path / "interrupted"
    failing = FailingPredictor(small_run.predictor, fail_at=4)
    with pytest.raises(Interrupted):
        pipeline.reconstruct(failing, run_dir, CONFIG, ground_truth=small_run.ground_truth, progress=False)
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert sorted(manifest["chunks"]) == ["0", "1", "2"] and sorted(manifest["edges"]) == ["0", "1"]
    assert [p.name for p in sorted((run_dir / "chunks").glob("tail_*"))] == ["tail_00002.npz"]
    again = CountingPredictor(small_run.predictor)
    out = pipeline.reconstruct(again, run_dir, CONFIG, ground_truth=small_run.ground_truth, progress=False)
    assert again.calls == result.num_chunks - 3 + loop_chunks_predicted(result)
    np.testing.assert_array_equal(out.cam_to_world, result.cam_to_world)
    np.testing.assert_array_equal(out.chunk_poses, result.chunk_poses)
    for name in ("points.ply", "poses_kitti.txt", "poses_tum.txt", "intrinsics.txt", "loops.txt"):
        assert (run_dir / name).read_bytes() == (result.run_dir / name).read_bytes(), name
    assert not list((run_dir / "chunks").glob("tail_*"))


def test_finished_run_records_every_chunk_and_rerun_predicts_nothing(small_run, result):
    """Defect 3: the final commit did not mark the manifest dirty, so a run without loop
    closure never recorded its last chunk and edge, and a re-run re-predicted it."""
    manifest = json.loads((result.run_dir / "manifest.json").read_text())
    assert sorted(map(int, manifest["chunks"])) == list(range(result.num_chunks))
    assert sorted(map(int, manifest["edges"])) == list(range(result.num_chunks - 1))


def test_chunk_files_hold_export_points_not_images(result):
    """The chunk store keeps the dense maps (float16) and the chunk's share of the cloud in the
    chunk frame; mapped by the optimised chunk poses those are exactly the PLY's points."""
    from swiftjax import sim3
    from swiftjax.io.chunk_store import ChunkStore

    store = ChunkStore(result.run_dir)
    cloud = ply.read_ply(result.run_dir / "points.ply")
    offset = 0
    for t in range(result.num_chunks):
        assert store.load("chunk", t, frames=[0]).images is None
        extra = store.load_extra("chunk", t)
        local = extra["points_xyz"].astype(np.float64)
        M = np.asarray(sim3.as_matrix(np.asarray(result.chunk_poses[t], np.float32)), np.float64)
        want = local @ M[:3, :3].T + M[:3, 3]
        got = cloud.points[offset : offset + len(local)]
        np.testing.assert_allclose(got, want, atol=1e-5 * max(1.0, np.abs(want).max()))
        np.testing.assert_array_equal(cloud.conf[offset : offset + len(local)], extra["points_conf"])
        offset += len(local)
    assert offset == cloud.points.shape[0]

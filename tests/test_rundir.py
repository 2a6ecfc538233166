"""The run directory's promise: lock, per-stage fingerprints, records, hygiene.

In-process checks on a small synthetic route (the fault-injection suite drives the real CLI
in subprocesses: tests/test_faults.py)."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil

import numpy as np
import pytest
from test_pipeline import CountingPredictor
from test_pipeline_stages import assert_same_outputs

from swiftjax import pipeline
from swiftjax.io.atomic import temp_files
from swiftjax.pipeline import rundir
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


class FramePredictor(CountingPredictor):
    """A predictor whose input frames carry a file identity (as image files do): bumping
    ``version[k]`` is 'frame k's file changed' (its prediction does not: the oracle)."""

    def __init__(self, inner, version=None):
        super().__init__(inner)
        self.version = version if version is not None else [0] * inner.num_frames
        self.predicted: list[int] = []

    def predict(self, frames):
        self.predicted.append(tuple(int(f) for f in frames))
        return super().predict(frames)

    def fingerprint(self):
        return {"frames": [[f"{k:06d}.png", v] for k, v in enumerate(self.version)], "model": "oracle"}

    def images(self, frames):
        return self.inner.images(frames)


@pytest.fixture(scope="module")
def route():
    poses = loop_route(width=60.0, length=30.0, corner_radius=8.0, laps=1.3, spacing_m=1.5)
    return demo.trajectory_run(poses, seed=5, image_hw=IMAGE_HW)


@pytest.fixture(scope="module")
def reference(route, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("ref")
    p = FramePredictor(route.predictor)
    res = pipeline.reconstruct(p, run_dir, CONFIG, progress=False, log=lambda s: None)
    assert res.loops, "the route must close a loop"
    return run_dir, res, p


def _copy(reference, tmp_path, name="copy"):
    dst = tmp_path / name
    shutil.copytree(reference[0], dst)
    return dst


def test_lock_refuses_a_second_writer_and_names_the_holder(tmp_path):
    first = rundir.RunLock(tmp_path).acquire()
    try:
        with pytest.raises(rundir.RunDirError, match=rf"in use by another swiftjax run \(pid {os.getpid()} on "):
            rundir.RunLock(tmp_path).acquire()
    finally:
        first.release()
    again = rundir.RunLock(tmp_path).acquire()  # released: free again
    again.release()


def test_stale_lock_is_taken_over(route, reference, tmp_path):
    run_dir = _copy(reference, tmp_path)
    (run_dir / rundir.LOCK_NAME).write_text(json.dumps({"pid": 999999, "host": "gone", "since": "x"}))
    logs: list[str] = []
    pipeline.reconstruct(FramePredictor(route.predictor), run_dir, CONFIG, progress=False, log=logs.append)
    assert any("taking over the lock" in line and "999999" in line for line in logs)
    assert (run_dir / rundir.LOCK_NAME).read_text() == ""  # released at the end


@pytest.mark.parametrize(
    "content, fragment",
    [
        ("[]", "holds a JSON list"),
        ("null", "holds a JSON NoneType"),
        ("{", "is unreadable"),
        ('{"version": 3}', "is damaged"),
        ('{"version": 1}', "manifest version 1"),
    ],
)
def test_bad_manifest_is_named_with_overwrite_suggested(route, tmp_path, content, fragment):
    (tmp_path / "manifest.json").write_text(content)
    with pytest.raises(rundir.RunDirError, match=fragment) as err:
        pipeline.reconstruct(route.predictor, tmp_path, CONFIG, progress=False)
    assert "--overwrite" in str(err.value) and "manifest.json" in str(err.value)


def test_temp_files_of_a_killed_run_are_removed(route, reference, tmp_path):
    """Issue 25 item 2: the cleanup walked the whole tree and removed other runs' and the
    user's temp files; now only this run's temp names in its own folders, after validation."""
    run_dir = _copy(reference, tmp_path)
    ours = [
        (run_dir, ".points.ply.abcd1234.tmp.ply"),
        (run_dir / "chunks", ".chunk_00002.npz.zz99yy88.tmp.npz"),
        (run_dir / "colmap" / "sparse" / "0", ".images.txt.q1w2e3r4.tmp.txt"),
    ]
    (run_dir / "other_run" / "chunks").mkdir(parents=True)
    theirs = [
        (run_dir, ".report.docx.abcd1234.tmp"),
        (run_dir / "colmap", ".images.txt.q1w2e3r4.tmp.txt"),
        (run_dir / "other_run" / "chunks", ".chunk_00001.npz.zz99yy88.tmp.npz"),
    ]
    for d, name in ours + theirs:
        (d / name).write_bytes(b"partial")
    with pytest.raises(rundir.RunDirError, match="depth_threshold"):  # refused: nothing removed
        pipeline.reconstruct(
            route.predictor,
            run_dir,
            dataclasses.replace(CONFIG, depth_threshold=0.3),
            progress=False,
            log=lambda s: None,
        )
    assert all((d / name).exists() for d, name in ours + theirs)
    logs: list[str] = []
    pipeline.reconstruct(FramePredictor(route.predictor), run_dir, CONFIG, progress=False, log=logs.append)
    assert any("removed 3 temp file(s)" in line for line in logs)
    assert not any((d / name).exists() for d, name in ours)
    assert all((d / name).read_bytes() == b"partial" for d, name in theirs)


def test_a_user_folder_is_refused_and_overwrite_deletes_only_the_runs_files(route, reference, tmp_path):
    """Issue 25 item 1: --out at a user's folder replaced 4 of 5 files; --overwrite deleted the
    user's chunks/*.npz."""
    user = tmp_path / "user"
    files = {
        "points.ply": b"mine",
        "metrics.json": b"{}",
        "colmap/images/00000.png": b"png",
        "chunks/chunk_00007.npz": b"npz",
        "colmap/sparse/0/cameras.bin": b"bin",
    }
    for rel, data in files.items():
        (user / rel).parent.mkdir(parents=True, exist_ok=True)
        (user / rel).write_bytes(data)
    for overwrite in (False, True):
        with pytest.raises(
            rundir.RunDirError,
            match=r"is not empty and holds no swiftjax run \(no manifest.json; it holds "
            r"chunks, colmap, metrics.json",
        ):
            pipeline.reconstruct(route.predictor, user, CONFIG, overwrite=overwrite, progress=False)
    assert sorted(str(p.relative_to(user)) for p in user.rglob("*") if p.is_file()) == sorted(files)
    assert all((user / rel).read_bytes() == data for rel, data in files.items())
    # a real run with the user's files beside it: --overwrite deletes the run's files only
    run_dir = _copy(reference, tmp_path)
    (run_dir / "notes.txt").write_text("mine")
    (run_dir / "colmap" / "images" / "my_photo.jpg").write_bytes(b"jpg")
    (run_dir / "chunks" / "README").write_text("mine")
    res = pipeline.reconstruct(
        route.predictor,
        run_dir,
        dataclasses.replace(CONFIG, colmap=False),
        overwrite=True,
        progress=False,
        log=lambda s: None,
    )
    assert (run_dir / "notes.txt").read_text() == "mine" and (run_dir / "chunks" / "README").read_text() == "mine"
    assert (run_dir / "colmap" / "images" / "my_photo.jpg").read_bytes() == b"jpg"
    assert not list((run_dir / "colmap" / "images").glob("0*.png")) and not (run_dir / "colmap" / "sparse").exists()
    assert res.num_chunks == len(list((run_dir / "chunks").glob("chunk_*.npz")))


def _record(run_dir):
    return json.loads((run_dir / "manifest.json").read_text())


def test_export_only_options_predict_nothing_and_leave_no_stale_output(route, reference, tmp_path):
    """Issue 26 item 3 (every export option re-runs the export alone, colmap and
    colmap_original_resolution included) and issue 25 item 10 (the output set is exactly what
    the last run wrote: no ground_truth_kitti.txt without a ground truth, no .txt model beside
    the .bin, no model after colmap=False)."""
    from swiftjax import options

    export_options = sorted(k for k, s in options.specs(pipeline.PipelineConfig).items() if s.stage == "export")
    assert export_options == ["colmap", "colmap_max_points", "colmap_original_resolution", "colmap_text", "voxel_size"]
    run_dir = _copy(reference, tmp_path)
    p = FramePredictor(route.predictor)
    gt = route.ground_truth

    def run(*, ground_truth=None, **change):
        logs: list[str] = []
        res = pipeline.reconstruct(
            p,
            run_dir,
            dataclasses.replace(CONFIG, **change),
            ground_truth=ground_truth,
            progress=False,
            log=logs.append,
        )
        assert p.calls == 0, change  # no chunk (nor loop chunk) predicted
        np.testing.assert_array_equal(res.cam_to_world, reference[1].cam_to_world)
        files = {q.relative_to(run_dir).as_posix() for q in run_dir.rglob("*") if q.is_file()}
        assert set(_record(run_dir)["outputs"]) == {
            f for f in files if not f.startswith("chunks/") and f not in (".swiftjax.lock", "manifest.json")
        }
        return res, files, logs

    res, files, _ = run(ground_truth=gt, colmap_text=True, voxel_size=0.5, colmap_max_points=500)
    assert "ground_truth_kitti.txt" in files and "colmap/sparse/0/images.txt" in files
    assert res.metrics["points"] < reference[1].metrics["points"]
    _, files, logs = run()
    assert "ground_truth_kitti.txt" not in files and "colmap/sparse/0/images.txt" not in files
    assert any("removed 4 output file(s) of the previous run" in line for line in logs), logs
    _, files, _ = run(colmap=False)
    assert not any(f.startswith("colmap/") for f in files) and not (run_dir / "colmap").exists()
    _, _, logs = run()  # colmap on again: the frames are drawn from the predictor's images, not predicted
    assert any("written again from the input (no prediction)" in line for line in logs)
    assert_same_outputs(run_dir, reference[0])
    with pytest.raises(ValueError, match="colmap_original_resolution needs the input images"):
        run(colmap_original_resolution=True)  # an export option: checked, never "different options"


def test_deleted_or_damaged_colmap_frames_are_rewritten(route, reference, tmp_path):
    """Issue 25 item 7: deleted or damaged COLMAP frames were never rewritten or reported."""
    run_dir = _copy(reference, tmp_path)
    images = run_dir / "colmap" / "images"
    (images / "000010.png").unlink()
    raw = bytearray((images / "000100.png").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (images / "000100.png").write_bytes(bytes(raw))
    p = FramePredictor(route.predictor)
    logs: list[str] = []
    pipeline.reconstruct(p, run_dir, CONFIG, progress=False, log=logs.append)
    assert p.calls == 0
    line = next(ln for ln in logs if "COLMAP frame(s)" in ln)
    assert "000010.png (missing)" in line and "000100.png (damaged: fails its CRC32)" in line
    assert_same_outputs(run_dir, reference[0])


def test_swapped_foreign_and_short_chunk_files_are_named_and_repredicted(route, reference, tmp_path):
    """Issue 25 items 5 and 26: chunk_00002.npz copied over chunk_00001.npz, or another run's
    chunk (another frame count), was used with exit 0 (or failed with 'shape mismatch')."""
    other = tmp_path / "other"
    pipeline.reconstruct(
        route.predictor,
        other,
        dataclasses.replace(CONFIG, chunk_size=40, overlap=10),
        progress=False,
        log=lambda s: None,
    )
    run_dir = _copy(reference, tmp_path)
    chunk_dir = run_dir / "chunks"
    shutil.copy(chunk_dir / "chunk_00002.npz", chunk_dir / "chunk_00001.npz")
    shutil.copy(other / "chunks" / "chunk_00003.npz", chunk_dir / "chunk_00003.npz")
    p = FramePredictor(route.predictor)
    logs: list[str] = []
    pipeline.reconstruct(p, run_dir, CONFIG, progress=False, log=logs.append)
    one = next(ln for ln in logs if "chunk_00001.npz: not this run's chunk file" in ln)
    assert "it holds chunk 2, not chunk 1" in one and "predicting chunk 1 again" in one
    three = next(ln for ln in logs if "chunk_00003.npz: not this run's chunk file" in ln)
    assert "(40), chunk 3 is frames 60-89 (30)" in three and "predicting chunk 3 again" in three
    assert sorted(p.predicted) == [tuple(range(20, 50)), tuple(range(60, 90))]
    assert reference[1].num_chunks > 3
    assert_same_outputs(run_dir, reference[0])


def test_an_edited_edge_record_is_reported_and_recomputed(route, reference, tmp_path):
    """Issue 25 item 6: one changed digit of an edge's S changed every output, exit 0."""
    run_dir = _copy(reference, tmp_path)
    m = _record(run_dir)
    m["edges"]["2"]["S"][0] += 1e-3
    loop = next(iter(m["loop_edges"]))
    m["loop_edges"][loop]["Z"][1] += 1e-3
    (run_dir / "manifest.json").write_text(json.dumps(m))
    p = FramePredictor(route.predictor)
    logs: list[str] = []
    pipeline.reconstruct(p, run_dir, CONFIG, progress=False, log=logs.append)
    assert any("the record of edge (chunks 2/3) fails its checksum" in ln for ln in logs), logs
    assert any(f"the record of loop edge {loop} fails its checksum" in ln for ln in logs), logs
    temporal = [f for f in p.predicted if f in (tuple(range(40, 70)), tuple(range(60, 90)))]
    assert len(temporal) == 2 and len(p.predicted) == 3  # chunks 2 and 3, and the loop chunk
    assert_same_outputs(run_dir, reference[0])


def test_export_only_option_change_reruns_only_the_export(route, reference, tmp_path):
    """Defect 5: fixing an export option forced a full redo ('different configuration')."""
    run_dir = _copy(reference, tmp_path)
    p = FramePredictor(route.predictor)
    cfg = dataclasses.replace(CONFIG, voxel_size=0.5, colmap_max_points=500)
    res = pipeline.reconstruct(p, run_dir, cfg, progress=False, log=lambda s: None)
    assert p.calls == 0
    np.testing.assert_array_equal(res.cam_to_world, reference[1].cam_to_world)
    assert res.metrics["points"] < reference[1].metrics["points"]  # the export did re-run


def test_loop_option_change_reruns_only_the_loop_stage(route, reference, tmp_path):
    run_dir = _copy(reference, tmp_path)
    p = FramePredictor(route.predictor)
    logs: list[str] = []
    cfg = dataclasses.replace(CONFIG, loop_depth_threshold=0.5)
    res = pipeline.reconstruct(p, run_dir, cfg, progress=False, log=logs.append)
    assert p.calls == len(res.loops)  # the loop chunks only
    assert any("loop options changed (loop_depth_threshold)" in line for line in logs)
    fresh = pipeline.reconstruct(route.predictor, tmp_path / "fresh", cfg, progress=False, log=lambda s: None)
    np.testing.assert_array_equal(res.cam_to_world, fresh.cam_to_world)


@pytest.mark.parametrize(
    "change, fragment",
    [
        ({"depth_threshold": 0.3}, "options depth_threshold"),
        ({"point_stride": 2}, "options point_stride"),
        ({"chunk_size": 32}, "options chunk_size"),
    ],
)
def test_temporal_option_change_is_refused(route, reference, tmp_path, change, fragment):
    with pytest.raises(rundir.RunDirError, match=fragment):
        pipeline.reconstruct(route.predictor, reference[0], dataclasses.replace(CONFIG, **change), progress=False)


def test_model_identity_change_is_refused(route, reference):
    """Defect 1: another model's run directory was reused without a word."""

    class OtherModel(FramePredictor):
        def fingerprint(self):
            return {**super().fingerprint(), "model": "another oracle"}

    with pytest.raises(rundir.RunDirError, match="different model"):
        pipeline.reconstruct(OtherModel(route.predictor), reference[0], CONFIG, progress=False)


def test_changed_frame_files_repredict_only_their_chunks(route, reference, tmp_path):
    """Defect 7's second half: a repaired (changed) image forced every chunk to be redone.
    Frame 45 lies in chunks 2 (40-69) and 1 (20-49): those and their neighbours are predicted
    again; the result equals a fresh run."""
    run_dir = _copy(reference, tmp_path)
    version = [0] * route.predictor.num_frames
    version[45] = 1
    p = FramePredictor(route.predictor, version)
    logs: list[str] = []
    res = pipeline.reconstruct(p, run_dir, CONFIG, progress=False, log=logs.append)
    from swiftjax import chunks

    schedule = chunks.chunk_schedule(route.predictor.num_frames, CONFIG.chunk_size, CONFIG.overlap)
    chunk_of = {tuple(schedule.frames(t).tolist()): t for t in range(schedule.num_chunks)}
    redone = sorted(chunk_of[f] for f in p.predicted if f in chunk_of)
    assert redone == [0, 1, 2, 3] and p.calls == 4 + len(res.loops)
    assert any("1 input frame(s) changed" in line and "000045.png" in line for line in logs)
    np.testing.assert_array_equal(res.cam_to_world, reference[1].cam_to_world)  # same predictions: same result


class SkippingPredictor(FramePredictor):
    """The input with frame ``skip`` left out (as ``--skip-bad`` leaves out a truncated image):
    the frames after it shift down by one."""

    def __init__(self, inner, skip):
        super().__init__(inner)
        self.skip = skip
        self.num_frames = inner.num_frames - 1

    def predict(self, frames):
        frames = np.asarray(frames)
        return super().predict(np.where(frames < self.skip, frames, frames + 1))

    def fingerprint(self):
        frames = super().fingerprint()["frames"]
        return {"frames": frames[: self.skip] + frames[self.skip + 1 :], "model": "oracle"}

    def frame_names(self):
        names = self.inner.frame_names()
        return names[: self.skip] + names[self.skip + 1 :]


def test_a_repaired_skipped_frame_repredicts_only_the_chunks_from_it(route, reference, tmp_path):
    """Defect 7's second half, with --skip-bad: a run without the truncated frame 75, then the
    repaired image: the input has one frame more.  Chunks 0-2 (frames 0-69) hold the same
    frames in both runs: 0 and 1 are kept, 2 is predicted again (its edge to chunk 3 needs its
    float32 overlap), 3 onwards hold other frames.  The result equals an uninterrupted run on
    the repaired input, and the other direction (a frame removed) works the same way."""
    from swiftjax import chunks

    run_dir = tmp_path / "run"
    pipeline.reconstruct(SkippingPredictor(route.predictor, 75), run_dir, CONFIG, progress=False, log=lambda s: None)
    p = FramePredictor(route.predictor)
    logs: list[str] = []
    res = pipeline.reconstruct(p, run_dir, CONFIG, progress=False, log=logs.append)
    n = route.predictor.num_frames
    schedule = chunks.chunk_schedule(n, CONFIG.chunk_size, CONFIG.overlap)
    chunk_of = {tuple(schedule.frames(t).tolist()): t for t in range(schedule.num_chunks)}
    redone = sorted(chunk_of[f] for f in p.predicted if f in chunk_of)
    assert redone == list(range(2, schedule.num_chunks))
    assert any(
        f"the input has {n} frames instead of {n - 1} (first difference at 000075.png)" in line
        and f"keeping chunk(s) 0-1, predicting chunk(s) 2-{schedule.num_chunks - 1} again" in line
        for line in logs
    ), logs
    np.testing.assert_array_equal(res.cam_to_world, reference[1].cam_to_world)
    assert_same_outputs(run_dir, reference[0])
    # and back: frame 75 left out again (fewer frames): the same chunks kept, the rest redone
    q = SkippingPredictor(route.predictor, 75)
    back = pipeline.reconstruct(q, run_dir, CONFIG, progress=False, log=lambda s: None)
    fresh = pipeline.reconstruct(
        SkippingPredictor(route.predictor, 75), tmp_path / "fresh", CONFIG, progress=False, log=lambda s: None
    )
    assert (
        len(q.predicted) - len(back.loops)
        == chunks.chunk_schedule(n - 1, CONFIG.chunk_size, CONFIG.overlap).num_chunks - 2
    )
    np.testing.assert_array_equal(back.cam_to_world, fresh.cam_to_world)
    assert_same_outputs(run_dir, tmp_path / "fresh")


def test_a_full_disk_in_the_export_leaves_the_previous_complete_output_set(route, reference, tmp_path, monkeypatch):
    """Defect 9: a disk-full error left a partial output set (new poses and cloud, no or an old
    metrics.json).  The outputs are now renamed together at the end: the error names the file
    and every output is the previous run's, byte for byte; no temp file is left."""
    import errno

    from swiftjax.pipeline import report

    run_dir = _copy(reference, tmp_path)

    class FullDisk:
        @staticmethod
        def dump(*args, **kwargs):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(report, "json", FullDisk)  # metrics.json: the set's last file
    cfg = dataclasses.replace(CONFIG, voxel_size=0.5)  # an export-only change: a different cloud
    with pytest.raises(OSError, match=r"No space left on device \(writing .*metrics\.json\)"):
        pipeline.reconstruct(FramePredictor(route.predictor), run_dir, cfg, progress=False, log=lambda s: None)
    assert_same_outputs(run_dir, reference[0], manifest=False)
    assert not [p for d in [run_dir, *run_dir.rglob("*")] if d.is_dir() for p in temp_files(d)]
    # a first run that fails so leaves no outputs at all (the chunks and the manifest stay)
    fresh = tmp_path / "fresh"
    with pytest.raises(OSError, match="No space left"):
        pipeline.reconstruct(FramePredictor(route.predictor), fresh, CONFIG, progress=False, log=lambda s: None)
    assert sorted(p.name for p in fresh.iterdir() if p.is_file() and not p.name.startswith(".")) == ["manifest.json"]
    monkeypatch.undo()
    res = pipeline.reconstruct(FramePredictor(route.predictor), run_dir, cfg, progress=False, log=lambda s: None)
    assert res.metrics["points"] < reference[1].metrics["points"]  # with space again: the new set, complete


def test_max_lm_steps_zero_and_one_in_metrics_json(route, reference, tmp_path):
    """Defect 9 through the pipeline: --max-lm-steps 0 wrote cost_initial 0.0, iterations -1;
    --max-lm-steps 1 took no step.  A pose-graph option: only the graph and the export run."""
    run_dir = _copy(reference, tmp_path)
    full = reference[1].metrics["pose_graph"]
    out = {}
    for steps in (0, 1):
        p = FramePredictor(route.predictor)
        res = pipeline.reconstruct(
            p, run_dir, dataclasses.replace(CONFIG, max_lm_steps=steps), progress=False, log=lambda s: None
        )
        assert p.calls == 0
        out[steps] = json.loads((run_dir / "metrics.json").read_text())["pose_graph"]
        assert {k: out[steps][k] for k in ("cost_initial", "iterations")} == {
            k: res.metrics["pose_graph"][k] for k in ("cost_initial", "iterations")
        }
    # (with GNC the reported costs are the last weighted solve's, so they depend on the steps
    # taken: not compared with the full run's)
    assert np.isfinite(out[0]["cost_initial"]) and out[0]["cost_initial"] > 0 and full["cost_initial"] > 0
    assert out[0]["iterations"] == 0 and out[1]["iterations"] >= 1


def test_overwrite_starts_afresh_and_removes_old_chunks(route, reference, tmp_path):
    run_dir = _copy(reference, tmp_path)
    res = pipeline.reconstruct(
        route.predictor,
        run_dir,
        dataclasses.replace(CONFIG, chunk_size=40),
        overwrite=True,
        progress=False,
        log=lambda s: None,
    )
    assert sorted(int(p.stem.split("_")[1]) for p in (run_dir / "chunks").glob("chunk_*")) == list(
        range(res.num_chunks)
    )


def test_rerun_of_a_finished_run_changes_nothing(route, reference, tmp_path):
    run_dir = _copy(reference, tmp_path)
    before = {p.name: p.stat().st_ino for p in (run_dir / "chunks").iterdir()}
    p = FramePredictor(route.predictor)
    pipeline.reconstruct(p, run_dir, CONFIG, progress=False, log=lambda s: None)
    assert p.calls == 0
    assert {q.name: q.stat().st_ino for q in (run_dir / "chunks").iterdir()} == before
    assert_same_outputs(run_dir, reference[0])


def test_a_disk_too_small_is_refused_after_the_first_chunk(route, tmp_path, monkeypatch):
    """Defect 9: --frames 100000 wrote 24 GB before it was stopped; now the first chunk file
    gives the estimate and the run stops with what it needs (finished chunks kept)."""
    import shutil as sh

    real = sh.disk_usage

    def small(path):
        u = real(path)
        return type(u)(u.total, u.used, 10 << 20)  # 10 MB free

    monkeypatch.setattr(sh, "disk_usage", small)
    p = FramePredictor(route.predictor)
    with pytest.raises(rundir.RunDirError, match=r"not enough free space .*remaining chunks need about .* MB each"):
        pipeline.reconstruct(p, tmp_path / "run", CONFIG, progress=False, log=lambda s: None)
    assert p.calls <= 3  # stopped at once (the executor predicts ahead while chunk 0 is written)
    assert json.loads((tmp_path / "run" / "manifest.json").read_text())["chunks"]  # chunk 0 kept


def test_weights_and_frames_are_fingerprinted_by_their_whole_content(tmp_path, monkeypatch):
    """Issue 25 items 3 and 4: weights changed after the first MiB, or a frame changed, with
    size and modification time kept, were not detected (predictions reused or mixed).  The
    digest is SHA-256 of the whole file (checked against hashlib), cached by (device, inode,
    size, mtime, ctime): restoring mtime does not restore ctime, so the edit is seen."""
    import hashlib

    from inference.predictor import ImagePredictor, weights_identity
    from swiftjax.io import file_hash, images

    monkeypatch.setenv("SWIFTJAX_HASH_CACHE", str(tmp_path / "hashes.json"))

    def edit_keeping_size_and_mtime(path, offset):
        st = path.stat()
        raw = bytearray(path.read_bytes())
        raw[offset] ^= 0x01
        path.write_bytes(bytes(raw))
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
        assert (path.stat().st_size, path.stat().st_mtime_ns) == (st.st_size, st.st_mtime_ns)
        return bytes(raw)

    weights = tmp_path / "model.safetensors"
    weights.write_bytes(np.random.default_rng(0).bytes(3 << 20))
    before = weights_identity(weights)
    assert before["sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
    raw = edit_keeping_size_and_mtime(weights, (2 << 20) + 17)  # after the first MiB
    after = weights_identity(weights)
    assert after["sha256"] == hashlib.sha256(raw).hexdigest() != before["sha256"]
    reads = []
    monkeypatch.setattr(file_hash, "_digest", lambda p: reads.append(p) or "x")
    assert weights_identity(weights) == after and not reads  # hashed once: cached by identity

    monkeypatch.undo()
    monkeypatch.setenv("SWIFTJAX_HASH_CACHE", str(tmp_path / "hashes.json"))
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(1)
    from PIL import Image

    for k in range(3):
        Image.fromarray(rng.integers(0, 255, (20, 30, 3), np.uint8)).save(folder / f"{k:03d}.png")
    predictor = ImagePredictor(images.list_frames(str(folder)), runner=None, identity={"model": "m"})
    first = predictor.fingerprint()["frames"]
    path = folder / "001.png"
    edit_keeping_size_and_mtime(path, path.stat().st_size - 20)  # inside the image data
    second = predictor.fingerprint()["frames"]
    assert first[0] == second[0] and first[2] == second[2]
    assert second[1] == ["001.png", path.stat().st_size, hashlib.sha256(path.read_bytes()).hexdigest()] != first[1]


def test_an_unusable_ground_truth_is_refused_before_the_run_and_an_evaluation_failure_keeps_the_outputs(
    route, reference, tmp_path, monkeypatch, capsys, logged_warning
):
    """Issue 25 item 24: a collinear or too-short --gt failed only after the whole run,
    discarded the outputs, named no file and suggested align='none'."""
    from swiftjax import cli, evaluation

    gt = route.ground_truth.copy()
    gt[:, :3, 3] = np.arange(len(gt))[:, None] * np.array([1.0, 0.5, 0.0])  # a straight line
    p = FramePredictor(route.predictor)
    with pytest.raises(ValueError, match="the ground truth: its positions are coincident or collinear") as err:
        pipeline.reconstruct(p, tmp_path / "line", CONFIG, ground_truth=gt, progress=False)
    assert "align=" not in str(err.value) and p.calls == 0 and not (tmp_path / "line").exists()
    # through the CLI: one line naming the file, exit 2, before the model (there is none) loads
    from PIL import Image

    for rows, fragment in ((gt[:4], "its positions are coincident or collinear"), (gt[:2], "needs at least 3")):
        frames = tmp_path / f"frames{len(rows)}"
        frames.mkdir()
        for k in range(len(rows)):
            Image.fromarray(np.full((20, 30, 3), 40 * k, np.uint8)).save(frames / f"{k:03d}.png")
        path = tmp_path / f"gt{len(rows)}.txt"
        path.write_text("".join(" ".join(f"{v:.6f}" for v in T[:3].ravel()) + "\n" for T in rows))
        code = cli.main(
            [
                "reconstruct",
                str(frames),
                "--weights",
                str(tmp_path / "none.pt"),
                "--gt",
                str(path),
                "--out",
                str(tmp_path / "cli"),
            ]
        )
        lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and f"ground-truth file {path}" in lines[0], lines
        assert fragment in lines[0] and "align=" not in lines[0], lines
    # an evaluation failure after the run: the outputs are written, without ATE, and it is said
    run_dir = _copy(reference, tmp_path)

    def failing_ate(*args, **kwargs):
        raise ValueError("Umeyama alignment is degenerate")

    monkeypatch.setattr(evaluation, "ate", failing_ate)
    with logged_warning(r"ATE/RPE not computed \(Umeyama"):
        res = pipeline.reconstruct(
            FramePredictor(route.predictor),
            run_dir,
            CONFIG,
            ground_truth=route.ground_truth,
            progress=False,
            log=lambda s: None,
        )
    assert "ate_rmse" not in res.metrics
    assert_same_outputs(run_dir, reference[0])


def test_prune_keeps_every_output_and_a_rerun_predicts_only_what_needs_the_maps(route, reference, tmp_path):
    """Issue 26 item 8: the chunk store is most of a run directory; 'swiftjax prune' drops its
    dense maps, keeps every deliverable, and says what resuming then costs."""
    from swiftjax import cli

    run_dir = _copy(reference, tmp_path)
    code = cli.main(["prune", str(run_dir)])
    assert code == 0
    before = sum(p.stat().st_size for p in (reference[0] / "chunks").iterdir())
    after = sum(p.stat().st_size for p in (run_dir / "chunks").iterdir())
    assert after < 0.6 * before
    outputs = [q for q in (reference[0]).rglob("*") if q.is_file() and q.parent.name != "chunks"]
    assert all((run_dir / q.relative_to(reference[0])).read_bytes() == q.read_bytes() for q in outputs)
    p = FramePredictor(route.predictor)
    res = pipeline.reconstruct(
        p, run_dir, dataclasses.replace(CONFIG, colmap_max_points=500), progress=False, log=lambda s: None
    )
    assert p.calls == 0  # export-only change: nothing predicted
    np.testing.assert_array_equal(res.cam_to_world, reference[1].cam_to_world)
    cfg = dataclasses.replace(CONFIG, loop_depth_threshold=0.5)  # the loop stage reads the dense maps
    logs: list[str] = []
    res = pipeline.reconstruct(p, run_dir, cfg, progress=False, log=logs.append)
    assert any("depth and confidence maps were dropped ('swiftjax prune'); predicting chunk" in ln for ln in logs)
    fresh = pipeline.reconstruct(route.predictor, tmp_path / "fresh", cfg, progress=False, log=lambda s: None)
    np.testing.assert_array_equal(res.cam_to_world, fresh.cam_to_world)
    (tmp_path / "unfinished").mkdir()
    with pytest.raises(rundir.RunDirError, match="not a swiftjax run directory"):
        rundir.prune(tmp_path / "unfinished")


def test_a_fingerprint_that_is_not_a_dict_is_refused():
    """The list form ("one opaque identity of the whole input") is gone: a predictor's
    fingerprint lists its frames or says None, beside its identity."""

    class ListFingerprint:
        num_frames = 3

        def fingerprint(self):
            return ["input.mp4", 1234]

    with pytest.raises(TypeError, match=r"ListFingerprint.fingerprint\(\) must return a dict"):
        rundir.fingerprints(ListFingerprint(), pipeline.PipelineConfig())

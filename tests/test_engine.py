"""The live engine (swiftjax.pipeline.engine): poses while the frames arrive, revised when a loop
closes, and a finished run directory equal to the offline run of the same frames."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from test_pipeline_stages import assert_same_outputs

from swiftjax import pipeline
from swiftjax.pipeline import reader
from swiftjax.pipeline.engine import Prefix, Reconstruction
from swiftjax.pipeline.live import LIVE_NAME, LiveLog
from swiftjax.synthetic import demo

#: The CLI demo of tests/test_demo_outputs.py (155 frames, 8 chunks, one verified loop).
CONFIG = pipeline.PipelineConfig(
    chunk_size=30,
    overlap=10,
    loop_min_separation=50,
    loop_nms_radius=10,
    loop_half_window=8,
    point_stride=3,
    colmap_max_points=2_000,
    loop_threshold_rule="fixed",
)


def test_live_log_survives_a_half_written_line(tmp_path):
    c2w = np.tile(np.eye(4), (3, 1, 1))
    c2w[:, 0, 3] = [1.0, 2.0, 3.0]
    log = LiveLog(tmp_path)
    log.append([0, 1], [0.0, 0.1], c2w[:2], 0, "new")
    log.close()
    with open(tmp_path / LIVE_NAME, "ab") as f:  # a crash in the middle of the next chunk's line
        f.write(b'{"frame": 2, "time": 0.2, "pose": [[1, 0')
    got = reader.read_live_poses(tmp_path)
    assert [r["frame"] for r in got] == [0, 1] and got[1]["pose"][0, 3] == 2.0
    log = LiveLog(tmp_path)  # the next session drops the half line and appends after it
    log.append([2], [0.2], c2w[2:], 1, "loop closure")
    log.close()
    got = reader.read_live_poses(tmp_path)
    assert [(r["frame"], r["revision"], r["reason"]) for r in got] == [
        (0, 0, "new"),
        (1, 0, "new"),
        (2, 1, "loop closure"),
    ]
    np.testing.assert_array_equal(got[2]["pose"], c2w[2, :3])
    lines = (tmp_path / LIVE_NAME).read_text().splitlines()
    assert all(json.loads(line) for line in lines) and len(lines) == 3


def test_prefix_fingerprint_lists_the_frames():
    run = demo.loop_route_run(40, image_hw=(28, 98))
    fp = Prefix(run.predictor, 25).fingerprint()
    assert fp["frames"] == [[f"{k:06d}.png"] for k in range(25)]
    assert fp["model"] == run.predictor.fingerprint()["model"]
    with pytest.raises(ValueError, match="not among the first 25"):
        Prefix(run.predictor, 25).predict(np.arange(20, 30))


@pytest.mark.slow
def test_engine_publishes_live_poses_and_finishes_as_offline(tmp_path):
    run = demo.loop_route_run(None, image_hw=(28, 98), spacing_m=4.0)
    n = run.predictor.num_frames
    live_dir, offline_dir = tmp_path / "live", tmp_path / "offline"
    rec = Reconstruction(live_dir, run.predictor, CONFIG, ground_truth=run.ground_truth, log=lambda s: None)
    steps = []  # (frames posed, revision, poses, the step's run)
    for _ in range(n):
        if rec.add_frame():
            frames, c2w = rec.poses()
            steps.append((len(frames), rec.revision, c2w, rec.result))
    final = rec.finish()
    B, O = CONFIG.chunk_size, CONFIG.overlap
    assert [s[0] for s in steps] == list(range(B, n + 1, B - O))

    records = reader.read_live_poses(live_dir)
    revisions = [r["revision"] for r in records]
    assert revisions == sorted(revisions)
    # The loop closes on the way (the demo route's revisit), then the final pass: two revisions.
    assert rec.revision == 2 and sorted({r["reason"] for r in records}) == ["final", "loop closure", "new"]
    closing = next(k for k, s in enumerate(steps) if s[1] == 1)
    assert len(steps[closing][3].loops) >= 1 and all(len(s[3].loops) == 0 for s in steps[:closing])
    # Every frame's first pose is the step's that posed it; a revision republishes every frame with
    # that step's poses (the graph's at that revision).
    first = {}
    for r in records:
        first.setdefault(r["frame"], r)
    last_step = steps[-1][0]  # the frames after the last complete chunk are posed by the final pass
    assert sorted(first) == list(range(n))
    before, at = steps[closing - 1][0], steps[closing][0]  # the closing step publishes its new frames too
    assert [first[k]["reason"] for k in range(n)] == (
        ["new"] * before + ["loop closure"] * (at - before) + ["new"] * (last_step - at) + ["final"] * (n - last_step)
    )
    for count, revision, c2w, _result in steps:
        for k in range(count):
            latest = [r for r in records if r["frame"] == k and r["revision"] <= revision][-1]
            np.testing.assert_array_equal(latest["pose"], c2w[k, :3])
    loop_lines = [r for r in records if r["reason"] == "loop closure"]
    assert [r["frame"] for r in loop_lines] == list(range(steps[closing][0]))
    np.testing.assert_array_equal(np.stack([r["pose"] for r in loop_lines]), steps[closing][3].cam_to_world[:, :3])
    final_lines = [r for r in records if r["reason"] == "final"]
    np.testing.assert_array_equal(np.stack([r["pose"] for r in final_lines]), final.cam_to_world[:, :3])

    # The finished run directory is the offline run of the same frames, file by file.
    offline = pipeline.reconstruct(
        Prefix(run.predictor, n), offline_dir, CONFIG, ground_truth=run.ground_truth, progress=False, log=lambda s: None
    )
    np.testing.assert_array_equal(offline.cam_to_world, final.cam_to_world)
    shutil.move(live_dir / LIVE_NAME, tmp_path / LIVE_NAME)
    assert_same_outputs(offline_dir, live_dir)

"""The live engine (swiftjax.pipeline.engine): poses while the frames arrive, revised when a loop
closes, and a finished run directory equal to the offline run of the same frames."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
from test_pipeline_stages import assert_same_outputs

from swiftjax import chunks, pipeline
from swiftjax.pipeline import reader
from swiftjax.pipeline.engine import Prefix, Reconstruction
from swiftjax.pipeline.live import LIVE_LOOPS_NAME, LIVE_NAME, LiveLog
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


def test_prefix_grows_but_never_past_its_predictor():
    run = demo.loop_route_run(40, image_hw=(28, 98))
    view = Prefix(run.predictor, 25)
    view.grow(30)
    assert view.num_frames == 30 and len(view.frame_names()) == 30
    with pytest.raises(ValueError, match="grown to 20"):
        view.grow(20)
    with pytest.raises(ValueError, match="grown to 41"):
        view.grow(41)


def _matrix(S: np.ndarray) -> np.ndarray:
    """``[8] (t, q xyzw, s)`` -> ``[4, 4] [[s R, t], [0, 1]]`` in float64 (NumPy, independent of swiftjax.sim3)."""
    x, y, z, w = np.asarray(S[3:7], np.float64) / np.linalg.norm(S[3:7])
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = S[7] * R, S[:3]
    return M


def _camera_to_world(chunk: np.ndarray, extrinsic: np.ndarray) -> np.ndarray:
    """Camera-to-world ``[4, 4]`` (orthonormal rotation) of a camera ``extrinsic [3, 4]``
    (world-to-camera in its chunk) in a chunk whose chunk-to-world matrix is ``chunk [4, 4]``."""
    E = np.eye(4)
    E[:3] = extrinsic
    P = chunk @ np.linalg.inv(E)
    P[:3, :3] /= np.cbrt(np.linalg.det(P[:3, :3]))
    return P


@pytest.mark.slow
def test_engine_publishes_live_poses_and_finishes_as_offline(tmp_path):
    from swiftjax import evaluation
    from swiftjax.io.chunk_store import ChunkStore

    run = demo.loop_route_run(None, image_hw=(28, 98), spacing_m=4.0)
    n = run.predictor.num_frames
    live_dir, offline_dir = tmp_path / "live", tmp_path / "offline"
    rec = Reconstruction(live_dir, run.predictor, CONFIG, ground_truth=run.ground_truth, log=lambda s: None)
    steps = []  # frames posed after each live step
    for _ in range(n):
        if rec.add_frame():
            rec.wait_for_poses()  # (the pose threads predict and pose the chunk)
            steps.append(len(rec.poses()[0]))
    rec.wait_for_loops()
    live_loops = json.loads((live_dir / LIVE_LOOPS_NAME).read_text())
    final = rec.finish()
    B, O = CONFIG.chunk_size, CONFIG.overlap
    schedule = chunks.chunk_schedule(n, B, O)
    T = schedule.num_chunks
    assert steps == list(range(B, n + 1, B - O))
    # The input ends between two boundaries (155 frames: 150 + 5): finish() posed the short
    # last chunk [140, 155) as one more live step before the final pass.
    assert steps[-1] < n and T == len(steps) + 1
    assert [s["chunk"] for s in rec.steps] == list(range(T))
    assert rec.steps[-1]["frames"] == n

    # The finished run directory is the offline run of the same frames, file by file.
    offline = pipeline.reconstruct(
        Prefix(run.predictor, n), offline_dir, CONFIG, ground_truth=run.ground_truth, progress=False, log=lambda s: None
    )
    np.testing.assert_array_equal(offline.cam_to_world, final.cam_to_world)
    records = reader.read_live_poses(live_dir)
    shutil.move(live_dir / LIVE_NAME, tmp_path / LIVE_NAME)
    shutil.move(live_dir / LIVE_LOOPS_NAME, tmp_path / LIVE_LOOPS_NAME)
    assert_same_outputs(offline_dir, live_dir)

    # First poses: every frame once, in order, from the step that completed its chunk; before
    # the loop closes they are the offline chain's (the same temporal edges, chained in float64
    # here) with the frame's camera in the first chunk that held it.
    first = {}
    for r in records:
        first.setdefault(r["frame"], r)
    assert sorted(first) == list(range(n))
    new = [r for r in records if r["reason"] == "new"]
    assert [r["frame"] for r in new] == list(range(n))  # the tail's too: none waits for the final pass
    reasons = [r["reason"] for r in records]
    assert max(i for i, r in enumerate(reasons) if r == "new") < reasons.index("final")
    manifest = json.loads((offline_dir / "manifest.json").read_text())
    chain = [np.eye(4)]
    for t in range(1, T):
        chain.append(chain[-1] @ _matrix(np.asarray(manifest["edges"][str(t - 1)]["S"])))
    store = ChunkStore(offline_dir)
    unrevised = [r for r in records if r["reason"] == "new" and r["revision"] == 0]
    assert len(unrevised) >= 100  # the loop closes late in the drive
    owned_offline = 0
    for r in unrevised:
        k = r["frame"]
        t = 0 if k < B else (k - B) // (B - O) + 1  # the step that first posed k
        ext = store.load_array("chunk", t, "extrinsic")[k - int(schedule.starts[t])]
        np.testing.assert_allclose(r["pose"], _camera_to_world(chain[t], ext)[:3], atol=1e-5)
        if schedule.chunk_of(k) == t:  # the offline export poses k in the same chunk
            np.testing.assert_allclose(r["pose"], offline.cam_to_world_no_loops[k, :3], atol=1e-6)
            owned_offline += 1
    assert owned_offline > len(unrevised) // 2

    # The loop the offline run accepts is accepted live: a revision republishes every frame
    # posed then with the loop-closed graph, which pulls the trajectory towards the truth.
    assert [(r["i"], r["j"]) for r in rec.loops] == [(lp["i"], lp["j"]) for lp in offline.loops]
    # loops_live.json: every live candidate with its verdict, at the revision it produced
    assert [(r["i"], r["j"], r["accepted"]) for r in live_loops["loops"]] == [
        (r["i"], r["j"], r["accepted"]) for r in rec.candidates
    ]
    assert live_loops["revision"] == 1 and all(isinstance(r["reason"], str) for r in live_loops["loops"])
    closing = [r for r in records if r["reason"] == "loop closure"]
    assert {r["revision"] for r in closing} == {1}
    m = len(closing)
    assert [r["frame"] for r in closing] == list(range(m)) and m >= rec.loops[0]["i"]
    revised = np.stack([np.vstack([r["pose"], [0, 0, 0, 1]]) for r in closing])
    chained = np.stack([np.vstack([first[k]["pose"], [0, 0, 0, 1]]) for k in range(m)])
    gt = np.asarray(run.ground_truth)[:m]
    ate_revised, ate_chained = (float(evaluation.ate(P, gt).rmse) for P in (revised, chained))
    assert ate_revised < 0.8 * ate_chained, (ate_revised, ate_chained)
    # ... and the final pass: revision 2, every frame, the offline poses.
    final_lines = [r for r in records if r["reason"] == "final"]
    assert {r["revision"] for r in final_lines} == {2} and rec.revision == 2
    np.testing.assert_array_equal(np.stack([r["pose"] for r in final_lines]), final.cam_to_world[:, :3])


@pytest.mark.parametrize("n", [20, 50, 61])
def test_finish_poses_the_last_chunk_live_and_equals_offline(tmp_path, n):
    """Inputs that end before one chunk (20 < B), on a chunk boundary (50 = B + (B - O)) or
    just after one (61): at ``end_of_input()`` every frame gets a first pose (reason "new";
    after a boundary from one more live step, the short last chunk's), no frame can be added
    any more, and the finished run's poses are the offline run's of the same frames."""
    run = demo.loop_route_run(None, image_hw=(28, 98), spacing_m=4.0)
    config = dataclasses.replace(CONFIG, loop_closure=False)
    rec = Reconstruction(tmp_path / "live", Prefix(run.predictor, n + 1), config, log=lambda s: None)
    for _ in range(n):
        rec.add_frame()
    B, O = config.chunk_size, config.overlap
    assert rec.end_of_input() == (n < B or (n - B) % (B - O) != 0)
    rec.wait_for_poses()
    assert len(rec.poses()[0]) == n
    with pytest.raises(ValueError, match="after the end of the input"):
        rec.add_frame()
    final = rec.finish()
    T = chunks.chunk_schedule(n, B, O).num_chunks
    assert [s["chunk"] for s in rec.steps] == list(range(T))
    records = reader.read_live_poses(tmp_path / "live")
    reasons = [r["reason"] for r in records]
    assert [r["frame"] for r in records if r["reason"] == "new"] == list(range(n))
    assert reasons[n:] == ["final"] * n
    offline = pipeline.reconstruct(
        Prefix(run.predictor, n), tmp_path / "offline", config, progress=False, log=lambda s: None
    )
    np.testing.assert_array_equal(offline.cam_to_world, final.cam_to_world)
    for name in (LIVE_NAME, LIVE_LOOPS_NAME):  # the live run's own files
        (tmp_path / "live" / name).unlink(missing_ok=True)
    assert_same_outputs(tmp_path / "offline", tmp_path / "live")


@pytest.mark.slow
def test_live_poses_in_metres_under_metric_camera_height(tmp_path):
    """``--metric camera-height=H`` live: each chunk's road height votes ``H / (h_t s_t)`` (the
    offline median rule on the prefix); the factor equals the one recomputed from the heights
    the chunk files record and the chain of the manifest's edges (NumPy here), and the live
    trajectory is metric: small without any scale alignment, unlike the same poses unscaled.
    No thread outlives close()."""
    import threading

    from swiftjax import evaluation
    from swiftjax.io.chunk_store import ChunkStore
    from swiftjax.synthetic.routes import loop_route

    before = set(threading.enumerate())
    run = demo.trajectory_run(
        loop_route(width=60.0, length=40.0, corner_radius=10.0, laps=0.6), seed=3, image_hw=(42, 140)
    )
    config = dataclasses.replace(CONFIG, metric="camera-height=1.65", loop_closure=False)
    rec = Reconstruction(tmp_path / "live", run.predictor, config, log=lambda s: None)
    try:
        for _ in range(run.predictor.num_frames):
            rec.add_frame()
        rec.wait_for_poses()
        frames, live = rec.poses()
        m = rec.metres_per_unit
    finally:
        rec.close()
    manifest = json.loads((tmp_path / "live" / "manifest.json").read_text())  # (saved once closed)
    assert not set(threading.enumerate()) - before
    T = len(rec.steps)
    store = ChunkStore(tmp_path / "live")  # (complete once closed)
    heights = np.array([float(store.load_extra("chunk", t)["ground_height"]) for t in range(T)])
    scales, S = [1.0], np.eye(4)
    for t in range(1, T):
        S = S @ _matrix(np.asarray(manifest["edges"][str(t - 1)]["S"]))
        scales.append(float(np.cbrt(np.linalg.det(S[:3, :3]))))
    votes = 1.65 / (heights * np.asarray(scales))
    votes = votes[np.isfinite(votes) & (votes > 0)]
    assert len(votes) >= T // 2 and m == rec.steps[-1]["metres_per_unit"]
    np.testing.assert_allclose(m, np.median(votes), rtol=1e-6)
    gt = np.asarray(run.ground_truth)[: len(frames), :3, 3]
    metric_ate = evaluation.ate(live[:, :3, 3], gt, "se3").rmse  # no scale alignment
    assert metric_ate < 1.0, metric_ate
    if abs(np.log(m)) > np.log(1.5):  # the same poses in chunk units are visibly not metric
        assert evaluation.ate(live[:, :3, 3] / m, gt, "se3").rmse > 2 * metric_ate


def test_turns_live_chunk_first_and_loop_chunks_in_the_gaps():
    """Turns (the one model): a loop-chunk prediction lets a waiting live one go first, and
    also one due before it would end (fake clock: the order cannot depend on the machine's
    speed); it never waits for more than one live prediction, and goes at once when the gap
    is long enough or the live chunk is overdue.  No thread outlives the test."""
    import threading

    from swiftjax.pipeline.engine import Turns

    now = [0.0]
    turns = Turns(clock=lambda: now[0])
    order: list[str] = []

    def take(name, urgent, hold=None):
        with turns.turn(urgent):
            order.append(name)
            if hold is not None:
                hold.wait(10)

    def run(*threads):
        for th in threads:
            th.start()
        for th in threads:
            th.join(20)
            assert not th.is_alive()

    # a live prediction waiting beats a loop chunk waiting, once the running one ends
    release = threading.Event()
    first = threading.Thread(target=take, args=("running", True, release))
    first.start()
    while not order:
        pass
    loop = threading.Thread(target=take, args=("loop", False))
    loop.start()
    live = threading.Thread(target=take, args=("live", True))
    live.start()
    while turns._urgent == 0:  # the live one is waiting
        pass
    release.set()
    for th in (first, loop, live):
        th.join(20)
        assert not th.is_alive()
    assert order == ["running", "live", "loop"]

    # the next live chunk is due in 5 s, a live prediction takes 10 s: the loop chunk waits for it
    turns.cost, turns.due = 10.0, now[0] + 5.0
    order.clear()
    loop = threading.Thread(target=take, args=("loop", False))
    loop.start()
    loop.join(0.3)
    assert loop.is_alive() and order == []  # (the fake clock stands still: it waits for the live one)
    run(threading.Thread(target=take, args=("live", True)))
    loop.join(20)
    assert order == ["live", "loop"]  # ... and for that one only, though the gap is still short

    # a gap long enough, or a live chunk overdue: at once
    for cost, due in ((1.0, 5.0), (10.0, -1.0)):
        turns.cost, turns.due = cost, now[0] + due
        order.clear()
        run(threading.Thread(target=take, args=("loop", False)))
        assert order == ["loop"]


def test_loop_worker_verifies_the_most_novel_proposal_first(tmp_path):
    """The loop worker verifies one proposal at a time, the farthest (in chunks, at either end)
    from the accepted loops, the newest first among equals: a new revisit before the
    neighbours of a loop already closed, which wait until nothing more novel does."""
    from types import SimpleNamespace as L

    run = demo.loop_route_run(40, image_hw=(28, 98), spacing_m=4.0)
    rec = Reconstruction(tmp_path / "live", run.predictor, CONFIG, log=lambda s: None)
    rec.candidates = [{"chunk_i": 20, "chunk_j": 3, "accepted": True}, {"chunk_i": 30, "chunk_j": 9, "accepted": False}]
    near = [L(chunk_i=20 + k, chunk_j=3 + k, i=1000 + k) for k in range(1, 4)]  # the accepted loop's revisit
    far = L(chunk_i=40, chunk_j=10, i=2000)  # another revisit
    newest_far = L(chunk_i=41, chunk_j=11, i=2050)
    by_rejected = L(chunk_i=30, chunk_j=9, i=1500)  # near a rejected loop only: novel
    rec._backlog = [(lp, 0, 0.0) for lp in (*near, far, newest_far, by_rejected)]
    order = []
    while rec.proposals_waiting:
        order.append(rec._next_proposal()[0])
    assert order == [newest_far, far, by_rejected, near[2], near[1], near[0]]
    rec.close()


def test_live_decisions_padded_to_a_capacity_equal_the_exact_ones():
    """``decide(..., rows=C - 1)`` (the live engine: the chain extended by identity edges so
    that the consistency programs compile once per capacity) accepts and rejects as the exact
    chain does, with the same PCM residuals up to rounding."""
    from types import SimpleNamespace

    from swiftjax import sim3
    from swiftjax.pipeline import loop_closure, rundir
    from swiftjax.posegraph import chain_poses

    rng = np.random.default_rng(0)
    T = 12
    relative = np.zeros((T - 1, 8))
    relative[:, 0] = 1.0 + 0.05 * rng.normal(size=T - 1)
    relative[:, 3:7] = [0, np.sin(0.1), 0, np.cos(0.1)]
    relative[:, 7] = 1.0
    chain = chain_poses(relative)

    def record(ci, cj, shift=0.0):
        Z = np.asarray(sim3.compose(sim3.inverse(chain[cj]), chain[ci]), np.float64)
        Z[0] += shift
        return {
            "i": 10 * ci, "j": 10 * cj, "chunk_i": ci, "chunk_j": cj, "Z": Z.tolist(), "quality_valid": True,
            "quality_min_fraction": 1.0, "dense_agreement": 0.9, "dense_overlap": 0.9,
        }  # fmt: skip

    ctx = SimpleNamespace(config=CONFIG, timer=rundir.StageTimer())
    exact = [record(11, 2), record(10, 1), record(9, 0, shift=25.0), record(8, 3)]
    padded = [dict(r) for r in exact]
    loop_closure.decide(ctx, relative, exact)
    loop_closure.decide(ctx, relative, padded, rows=63)
    assert [r["accepted"] for r in exact] == [True, True, False, True]
    assert [(r["accepted"], r["reason"]) for r in padded] == [(r["accepted"], r["reason"]) for r in exact]
    np.testing.assert_allclose(
        [r["pcm_residual"] for r in padded], [r["pcm_residual"] for r in exact], rtol=1e-9, atol=1e-9
    )

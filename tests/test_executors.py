"""Executors: local (with and without prefetch) and a real local Ray cluster give the same
run, bit for bit; a Ray actor killed mid-run is restarted and the run completes identically
without recomputing a recorded chunk; bad executor input fails in one line.

One Ray cluster (``num_cpus=2``, no dashboard, loopback) serves the module; it is shut down
at the end and no Ray process may outlive it.
"""

from __future__ import annotations

import collections
import os
import pathlib
import sys
import threading
import time

import numpy as np
import psutil
import pytest
from test_pipeline_stages import CONFIG, IMAGE_HW, assert_same_outputs, reference, route  # noqa: F401 (fixtures)

from swiftjax import chunks, pipeline
from swiftjax.pipeline.executors import ExecutorError, LocalExecutor, RayExecutor, start_local_ray
from swiftjax.synthetic import demo

ray = pytest.importorskip("ray")  # the test extra installs it; skipped only outside it


def _ray_processes() -> list[psutil.Process]:
    """Ray's processes started from this one (GCS, raylet, workers, agents)."""
    out = []
    for p in psutil.Process().children(recursive=True):
        with __import__("contextlib").suppress(psutil.Error):
            if "ray" in " ".join(p.cmdline()) or p.name() in ("gcs_server", "raylet"):
                out.append(p)
    return out


@pytest.fixture(scope="module")
def cluster():
    assert not ray.is_initialized()
    start_local_ray(num_cpus=2)
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the test specs below
    try:
        yield ray
    finally:
        ray.shutdown()
        deadline = time.monotonic() + 20
        while _ray_processes() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert _ray_processes() == []


def test_local_executor_without_prefetch_writes_the_same_outputs(route, reference, tmp_path):
    executor = LocalExecutor(prefetch=0)
    pipeline.reconstruct(
        route.predictor, tmp_path / "sync", CONFIG, ground_truth=route.ground_truth, progress=False, executor=executor
    )
    assert executor.stats.predictions == reference.num_chunks + len(reference.loops)
    assert_same_outputs(tmp_path / "sync", reference.run_dir)


class LoggedSpec:
    """Builds the route's predictor, slowed down, logging every finished prediction to a file
    (shared by every actor process, appended line by line)."""

    def __init__(self, inner, log: pathlib.Path, delay: float):
        self.inner, self.log, self.delay = inner, log, delay

    def build(self):
        return LoggedPredictor(self.inner.build(), self.log, self.delay)


class LoggedPredictor:
    def __init__(self, inner, log, delay):
        self.inner, self.log, self.delay = inner, log, delay
        self.num_frames = inner.num_frames

    def predict(self, frames):
        self._write(f"start {frames[0]}-{frames[-1]} {os.getpid()}")
        time.sleep(self.delay)
        pred = self.inner.predict(frames)
        self._write(f"done {frames[0]}-{frames[-1]} {os.getpid()}")
        return pred

    def _write(self, line):
        with open(self.log, "a") as f:
            f.write(line + "\n")

    def fingerprint(self):
        return self.inner.fingerprint()

    def frame_names(self):
        return self.inner.frame_names()


class Driver:
    """The driver's view of a :class:`LoggedPredictor` (never predicts itself)."""

    def __init__(self, route_predictor, spec):
        self.inner, self._spec = route_predictor, spec
        self.num_frames = route_predictor.num_frames

    def spec(self):
        return self._spec

    def predict(self, frames):
        raise AssertionError("the driver must not predict")

    def fingerprint(self):
        return self.inner.fingerprint()

    def frame_names(self):
        return self.inner.frame_names()


def test_ray_executor_writes_the_local_outputs(cluster, route, reference, tmp_path):
    log = tmp_path / "predictions.log"
    predictor = Driver(route.predictor, LoggedSpec(route.predictor.spec(), log, 0.0))
    with RayExecutor(2) as executor:
        pipeline.reconstruct(
            predictor, tmp_path / "ray", CONFIG, ground_truth=route.ground_truth, progress=False, executor=executor
        )
        assert len({ray.get(a.pid.remote()) for a in executor.actors}) == 2
    assert ray.is_initialized()  # the executor did not own the cluster
    done = [line.split() for line in log.read_text().splitlines() if line.startswith("done")]
    assert len(done) == reference.num_chunks + len(reference.loops)
    assert len({pid for _, _, pid in done}) == 2  # both actors predicted
    assert executor.stats.bytes > 0
    assert_same_outputs(tmp_path / "ray", reference.run_dir)


class KillingExecutor(RayExecutor):
    """After taking the ``at``-th prediction, a thread kills actor 0 (Ray restarts it) as soon
    as the log shows it inside a prediction."""

    def __init__(self, *args, at: int, log: pathlib.Path, **kwargs):
        super().__init__(*args, **kwargs)
        self.at, self.log, self.taken, self.killed_pid = at, log, 0, None
        self.killer: threading.Thread | None = None

    def map(self, predictor, requests, prepare=None):
        for pred in super().map(predictor, requests, prepare):
            self.taken += 1
            if self.taken == self.at:
                self.killed_pid = str(ray.get(self.actors[0].pid.remote()))
                self.killer = threading.Thread(target=self._kill, args=(self.actors[0],))
                self.killer.start()
            yield pred

    def _kill(self, actor):
        deadline = time.monotonic() + 60
        while not _inside_prediction(self.log, self.killed_pid) and time.monotonic() < deadline:
            time.sleep(0.005)
        ray.kill(actor, no_restart=False)


def _inside_prediction(log: pathlib.Path, pid: str) -> bool:
    entries = [line.split() for line in log.read_text().splitlines()]
    last = [kind for kind, _, p in entries if p == pid]
    return bool(last) and last[-1] == "start"


def test_killed_actor_is_restarted_and_no_recorded_chunk_is_predicted_again(cluster, route, reference, tmp_path):
    log = tmp_path / "predictions.log"
    predictor = Driver(route.predictor, LoggedSpec(route.predictor.spec(), log, 0.4))
    with KillingExecutor(2, at=3, log=log) as executor:
        pipeline.reconstruct(
            predictor, tmp_path / "killed", CONFIG, ground_truth=route.ground_truth, progress=False, executor=executor
        )
        executor.killer.join()
        restarted = ray.get(executor.actors[0].pid.remote())
    assert executor.killed_pid is not None and str(restarted) != executor.killed_pid
    entries = [line.split() for line in log.read_text().splitlines()]
    done = collections.Counter(key for kind, key, _ in entries if kind == "done")
    started = collections.Counter(key for kind, key, _ in entries if kind == "start")
    schedule = chunks.chunk_schedule(route.predictor.num_frames, CONFIG.chunk_size, CONFIG.overlap)
    keys = [f"{f[0]}-{f[-1]}" for f in (schedule.frames(t) for t in range(schedule.num_chunks))]
    # The kill interrupted a prediction of the killed actor, which the restarted one redid.
    interrupted = [
        k
        for kind, k, pid in entries
        if kind == "start" and pid == executor.killed_pid and ["done", k, pid] not in entries
    ]
    assert len(interrupted) == 1 and started[interrupted[0]] == 2 and done[interrupted[0]] == 1
    assert any(pid == str(restarted) for _, _, pid in entries)
    # Chunks taken (and so recorded) before the kill were predicted once; every chunk was.
    assert [done[k] for k in keys[:3]] == [1, 1, 1]
    assert sum(done.values()) == reference.num_chunks + len(reference.loops)
    assert_same_outputs(tmp_path / "killed", reference.run_dir)


def test_bad_executor_input_is_refused_in_one_line(monkeypatch, capsys, tmp_path):
    from swiftjax import cli

    with pytest.raises(ExecutorError, match="--workers must be >= 1"):
        RayExecutor(0)
    cases = [
        (["--workers", "0"], "--workers must be >= 1, got 0"),
        (["--workers", "2"], "--workers need --executor ray"),
        (["--executor", "ray", "--ray-address", "127.0.0.1:9"], "cannot reach the Ray cluster at 127.0.0.1:9"),
        (["--executor", "ray", "--ray-address", "nonsense"], "is not HOST:PORT"),
    ]
    for flags, message in cases:
        assert cli.main(["demo", "--out", str(tmp_path / "run"), *flags]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err, err
    monkeypatch.setitem(sys.modules, "ray", None)  # as if the extra were not installed
    assert cli.main(["demo", "--out", str(tmp_path / "run"), "--executor", "ray"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install 'swiftjax[ray]'" in err, err
    assert not (tmp_path / "run").exists()  # refused before any work


class BrokenSpec:
    """A sequence whose third chunk cannot be read (raises inside the worker)."""

    def __init__(self, inner):
        self.inner = inner

    def build(self):
        return BrokenPredictor(self.inner.build())


class BrokenPredictor(LoggedPredictor):
    def __init__(self, inner):
        super().__init__(inner, None, 0.0)
        self.calls = 0

    def predict(self, frames):
        self.calls += 1
        if self.calls == 3:
            raise ValueError(f"frame {frames[0]} of this sequence is corrupt")
        return self.inner.predict(frames)


def test_batch_on_ray_reports_the_broken_sequence_and_finishes_the_others(cluster, route, tmp_path):
    from swiftjax.pipeline import batch

    runs = [demo.trajectory_run(route.ground_truth[:55], seed=s, image_hw=IMAGE_HW) for s in (1, 2, 3)]
    jobs = [
        batch.Sequence("first", runs[0].predictor.spec(), runs[0].ground_truth),
        batch.Sequence("broken", BrokenSpec(runs[1].predictor.spec()), runs[1].ground_truth),
        batch.Sequence("third", runs[2].predictor.spec(), runs[2].ground_truth),
    ]
    lines = []
    rows = batch.run_batch(jobs, tmp_path, CONFIG, executor="ray", workers=2, log=lines.append)
    assert [r["sequence"] for r in rows] == ["first", "broken", "third"]
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    assert rows[1]["error"] == "ValueError: frame 40 of this sequence is corrupt"
    assert len(lines) == 3 and any("FAILED" in line and "broken" in line for line in lines)
    for row in (rows[0], rows[2]):
        assert row["frames"] == 55 and row["chunks"] == 3 and np.isfinite(row["ate_rmse"])
        poses = np.loadtxt(pathlib.Path(row["run_dir"]) / "poses_kitti.txt")
        assert poses.shape == (55, 12) and np.all(np.isfinite(poses))
    recorded = __import__("json").loads((tmp_path / "batch.json").read_text())
    assert [r["status"] for r in recorded["sequences"]] == ["ok", "failed", "ok"]
    table = batch.batch_table(rows)
    assert "broken" in table and "corrupt" in table
    assert ray.is_initialized()  # the batch used the module's cluster, did not shut it down


def test_batch_list_parsing(tmp_path):
    from swiftjax.pipeline import batch

    (tmp_path / "list.txt").write_text(
        "# sequences\nseq/00/images gt/00.txt\n\n/abs/path/01   # no ground truth\nvideo.mp4 gt/v.txt\n"
    )
    items = batch.read_list(tmp_path / "list.txt")
    assert items == [
        (str(tmp_path / "seq/00/images"), str(tmp_path / "gt/00.txt")),
        ("/abs/path/01", None),
        (str(tmp_path / "video.mp4"), str(tmp_path / "gt/v.txt")),
    ]
    assert batch.unique_names([i for i, _ in items] + ["/x/01"]) == ["00", "01", "video", "01_2"]
    (tmp_path / "bad.txt").write_text("a b c\n")
    with pytest.raises(batch.BatchError, match="bad.txt:1: expected 'INPUT"):
        batch.read_list(tmp_path / "bad.txt")
    (tmp_path / "empty.txt").write_text("# nothing\n")
    with pytest.raises(batch.BatchError, match="names no sequence"):
        batch.read_list(tmp_path / "empty.txt")
    for name in ("b", "a"):
        (tmp_path / "folders" / name / "images").mkdir(parents=True)
    (tmp_path / "folders" / "a" / "gt.txt").write_text("")
    assert batch.sequence_folders(tmp_path / "folders") == [
        (str(tmp_path / "folders/a/images"), str(tmp_path / "folders/a/gt.txt")),
        (str(tmp_path / "folders/b/images"), None),
    ]


def test_batch_cli_builds_one_image_sequence_per_line(tmp_path, monkeypatch, capsys):
    """``swiftjax batch LIST``: one ImageSpec job per line (absolute paths, ground truth), the
    execution options passed through, the table printed, exit 1 when a sequence failed."""
    from inference.predictor import ImageSpec
    from swiftjax import cli
    from swiftjax.pipeline import batch

    (tmp_path / "w.pt").write_bytes(b"")
    (tmp_path / "list.txt").write_text("a/images gt/a.txt\nb\n")
    seen = {}

    def fake_run_batch(jobs, out, config, **kwargs):
        seen.update(jobs=jobs, out=out, **kwargs)
        return [
            {"sequence": "a", "status": "ok", "frames": 10, "loops": 0, "ate_rmse": 0.5, "seconds": 1.0},
            {"sequence": "b", "status": "failed", "error": "InputError: no frames", "seconds": 0.1},
        ]

    monkeypatch.setattr(batch, "run_batch", fake_run_batch)
    code = cli.main(
        [
            "batch",
            str(tmp_path / "list.txt"),
            "--weights",
            str(tmp_path / "w.pt"),
            "--out",
            str(tmp_path / "out"),
            "--device",
            "cuda",
            "--dtype",
            "bfloat16",
            "--stride",
            "2",
        ]
    )
    assert code == 1
    out, err = capsys.readouterr()
    assert "| a | ok | 10 | 0 | 0.5 |" in out and "InputError: no frames" in out
    assert "1 of 2 sequences failed: b" in err
    jobs = seen["jobs"]
    assert [j.name for j in jobs] == ["a", "b"]
    assert jobs[0].ground_truth == str(tmp_path / "gt/a.txt") and jobs[1].ground_truth is None
    assert jobs[0].spec == ImageSpec(
        input=str(tmp_path / "a/images"), weights=str(tmp_path / "w.pt"), device="cuda", dtype="bfloat16", stride=2
    )
    assert seen["executor"] == "local" and seen["workers"] == 1

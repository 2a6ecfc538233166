"""Many sequences: every sequence its own resumable run, spread over the executor's workers.

    jobs = [Sequence("00", spec, ground_truth="gt/00.txt"), ...]
    rows = run_batch(jobs, "runs/batch", config, executor="ray", workers=4, gpus_per_worker=1)

Each sequence runs :func:`~swiftjax.pipeline.run.reconstruct` in ``out/<name>/`` (re-running
the batch resumes every unfinished run and skips the finished work).  With the local
executor the sequences run one after another in this process; with Ray, each of
``workers`` actors (``num_gpus`` / ``num_cpus`` each) runs one sequence at a time, building
the sequence's predictor from its picklable spec (a model is loaded once per actor process
and reused: :func:`inference.predictor.build_runner` caches it).  A failing sequence is
reported (its row says why) and the others finish.  ``out/batch.json`` holds every row.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import time
from collections.abc import Callable, Sequence as Seq
from typing import Any

import numpy as np

from swiftjax.io.atomic import atomic_write
from swiftjax.pipeline.config import PipelineConfig

__all__ = ["Sequence", "BatchError", "read_list", "sequence_folders", "run_batch", "batch_table"]


class BatchError(ValueError):
    """The batch's list or folder is unusable (before any sequence runs)."""


@dataclasses.dataclass(frozen=True)
class Sequence:
    """One sequence of a batch.

    ``spec``: a picklable recipe whose ``build()`` returns the predictor (e.g.
    :class:`inference.predictor.ImageSpec`, :class:`swiftjax.demo.OracleSpec`);
    ``ground_truth``: ``[N, 4, 4]`` poses, a trajectory file (``gt_format``), or None.
    """

    name: str
    spec: Any
    ground_truth: Any = None
    gt_format: str = "kitti"


def read_list(path: str | os.PathLike[str]) -> list[tuple[str, str | None]]:
    """``(input, ground truth or None)`` per line of a batch list: ``INPUT [GT]``, blank
    lines and ``#`` comments skipped, relative paths relative to the list's folder."""
    path = pathlib.Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise BatchError(f"cannot read the batch list {path}: {err.strerror or err}") from err
    base = path.parent
    out = []
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if len(fields) > 2:
            raise BatchError(f"{path}:{number}: expected 'INPUT [GROUND_TRUTH]', got {len(fields)} fields")
        resolve = lambda p: p if os.path.isabs(p) else str(base / p)  # noqa: E731
        out.append((resolve(fields[0]), resolve(fields[1]) if len(fields) == 2 else None))
    if not out:
        raise BatchError(f"the batch list {path} names no sequence")
    return out


#: Ground-truth file names looked for in a sequence folder (:func:`sequence_folders`).
GT_NAMES = ("gt.txt", "groundtruth.txt", "poses.txt")


def sequence_folders(folder: str | os.PathLike[str]) -> list[tuple[str, str | None]]:
    """``(input, ground truth or None)`` per subfolder of ``folder`` (sorted by name): the
    frames are the subfolder's images, or those of its ``images/`` folder if it has one; the
    ground truth is its first file named as in :data:`GT_NAMES`."""
    folder = pathlib.Path(folder)
    subs = sorted(p for p in folder.iterdir() if p.is_dir()) if folder.is_dir() else []
    if not subs:
        raise BatchError(f"{folder} has no sequence folders")
    out = []
    for sub in subs:
        frames = sub / "images" if (sub / "images").is_dir() else sub
        gt = next((str(sub / n) for n in GT_NAMES if (sub / n).is_file()), None)
        out.append((str(frames), gt))
    return out


def unique_names(inputs: Seq[str]) -> list[str]:
    """A run-directory name per input: its folder (or file) name, made unique with ``_2``..."""
    names: list[str] = []
    for item in inputs:
        p = pathlib.Path(item.rstrip("/"))
        base = (p.parent.name if p.name == "images" else p.stem) or "sequence"
        name, k = base, 2
        while name in names:
            name, k = f"{base}_{k}", k + 1
        names.append(name)
    return names


def run_sequence(job: Sequence, out: str, config: PipelineConfig, overwrite: bool,
                 jax_cache_dir: str | None = None) -> dict[str, Any]:
    """One sequence, in this process (or a worker's): its row of the batch table.  Every
    error is the row's ``error`` (first line), never raised; KeyboardInterrupt is."""
    from swiftjax.pipeline.executors import LocalExecutor
    from swiftjax.pipeline.run import reconstruct

    if jax_cache_dir:
        import jax

        jax.config.update("jax_compilation_cache_dir", jax_cache_dir)
    run_dir = pathlib.Path(out) / job.name
    row: dict[str, Any] = {"sequence": job.name, "run_dir": str(run_dir), "status": "failed"}
    t0 = time.perf_counter()
    try:
        gt = job.ground_truth
        if isinstance(gt, (str, os.PathLike)):
            from swiftjax.io import trajectory

            gt = trajectory.read_kitti(gt) if job.gt_format == "kitti" else trajectory.read_tum(gt)[1]
        predictor = job.spec.build()
        if gt is not None and len(gt) != predictor.num_frames:
            raise ValueError(f"ground truth has {len(gt)} poses for {predictor.num_frames} frames")
        result = reconstruct(predictor, run_dir, config, ground_truth=gt, overwrite=overwrite, progress=False,
                             log=lambda line: None, executor=LocalExecutor())
    except Exception as err:  # noqa: BLE001 -- a failing sequence is reported, the others go on
        row["error"] = f"{type(err).__name__}: {' '.join(str(err).split()) or type(err).__name__}"
    else:
        m = result.metrics
        row.update(status="ok", frames=result.num_frames, chunks=result.num_chunks, loops=int(m["loops"]))
        if "ate_rmse" in m:
            row["ate_rmse"] = float(m["ate_rmse"])
    row["seconds"] = time.perf_counter() - t0
    return row


class _SequenceActor:
    """A Ray actor running whole sequences, one at a time (its models stay loaded)."""

    def run(self, job: Sequence, out: str, config: PipelineConfig, overwrite: bool,
            jax_cache_dir: str | None) -> dict[str, Any]:
        return run_sequence(job, out, config, overwrite, jax_cache_dir)


def run_batch(
    jobs: Seq[Sequence],
    out: str | os.PathLike[str],
    config: PipelineConfig = PipelineConfig(),
    *,
    executor: str = "local",
    workers: int = 1,
    gpus_per_worker: float = 0.0,
    cpus_per_worker: float = 1.0,
    ray_address: str | None = None,
    overwrite: bool = False,
    log: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Run every sequence (see the module docstring); one row per sequence, in ``jobs``'
    order, also written to ``out/batch.json``.  ``log`` gets a line per finished sequence."""
    out = pathlib.Path(out)
    names = [j.name for j in jobs]
    if not jobs:
        raise BatchError("the batch has no sequence")
    if len(set(names)) != len(names):
        raise BatchError(f"sequence names must be unique, got {names}")
    if workers < 1:
        raise BatchError(f"--workers must be >= 1, got {workers}")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows: list[dict[str, Any] | None] = [None] * len(jobs)

    def done(k: int, row: dict[str, Any]) -> None:
        rows[k] = row
        status = f"ATE {row['ate_rmse']:.3g} m" if "ate_rmse" in row else row["status"]
        if row["status"] != "ok":
            status = f"FAILED: {row['error']}"
        log(f"[{sum(r is not None for r in rows)}/{len(jobs)}] {row['sequence']}: {status} ({row['seconds']:.1f} s)")

    from swiftjax.pipeline.executors import _jax_cache_dir

    cache = _jax_cache_dir()
    if executor == "local":
        if workers != 1 or gpus_per_worker or ray_address:
            raise BatchError("--workers, --gpus-per-worker and --ray-address need --executor ray")
        for k, job in enumerate(jobs):
            done(k, run_sequence(job, str(out), config, overwrite, cache))
    elif executor == "ray":
        _run_on_ray(jobs, str(out), config, overwrite, cache, done, workers, gpus_per_worker, cpus_per_worker,
                    ray_address)
    else:
        raise BatchError(f"executor must be 'local' or 'ray', got {executor!r}")
    final = [r for r in rows if r is not None]
    with atomic_write(out / "batch.json") as f:
        json.dump({
            "executor": executor, "workers": workers, "gpus_per_worker": gpus_per_worker,
            "seconds": time.perf_counter() - t0, "config": config.to_dict(), "sequences": final,
        }, f, indent=1, default=_json_default)
    return final


def _run_on_ray(jobs, out, config, overwrite, cache, done, workers, gpus, cpus, address) -> None:
    from swiftjax.pipeline.executors import RayExecutor

    pool = RayExecutor(workers, gpus_per_worker=gpus, cpus_per_worker=cpus, address=address)
    ray = pool.ray
    try:
        actor_cls = ray.remote(_SequenceActor).options(
            num_cpus=cpus, num_gpus=gpus, max_restarts=pool.max_restarts, max_task_retries=pool.max_task_retries,
        )
        actors = [actor_cls.remote() for _ in range(workers)]
        pool.actors = actors  # closed (killed) with the pool
        free = list(actors)
        running: dict[Any, tuple[int, Any]] = {}
        queue = list(enumerate(jobs))
        while queue or running:
            while queue and free:
                k, job = queue.pop(0)
                actor = free.pop(0)
                running[actor.run.remote(job, out, config, overwrite, cache)] = (k, actor)
            ready, _ = ray.wait(list(running), num_returns=1)
            k, actor = running.pop(ready[0])
            free.append(actor)
            try:
                row = ray.get(ready[0])
            except Exception as err:  # the worker itself failed (died past its restarts, ...)
                row = {"sequence": jobs[k].name, "run_dir": str(pathlib.Path(out) / jobs[k].name), "status": "failed",
                       "error": f"worker failed: {str(err).strip().splitlines()[0]}", "seconds": float("nan")}
            done(k, row)
    finally:
        pool.close()


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def batch_table(rows: Seq[dict[str, Any]]) -> str:
    """The summary table: sequence, status, frames, loops, ATE (where ground truth was
    given), time, and the error of a failed sequence."""
    from swiftjax.report import markdown_table

    body = [
        [r["sequence"], r["status"], r.get("frames", ""), r.get("loops", ""),
         f"{r['ate_rmse']:.4g}" if "ate_rmse" in r else "", f"{r['seconds']:.1f}", r.get("error", "")]
        for r in rows
    ]
    return markdown_table(["sequence", "status", "frames", "loops", "ATE rmse (m)", "time (s)", "error"], body)

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
import logging
import os
import pathlib
import shlex
import time
from collections.abc import Callable
from collections.abc import Sequence as Seq
from typing import Any

import numpy as np

from swiftjax.errors import SwiftjaxError
from swiftjax.io.atomic import atomic_write
from swiftjax.io.images import InputError
from swiftjax.pipeline.config import PipelineConfig

__all__ = ["Sequence", "BatchError", "read_list", "sequence_folders", "run_batch", "batch_table"]

logger = logging.getLogger(__name__)


class BatchError(SwiftjaxError, ValueError):
    """The batch's list or folder is unusable (before any sequence runs)."""


@dataclasses.dataclass(frozen=True)
class Sequence:
    """One sequence of a batch.

    ``spec``: a picklable recipe whose ``build()`` returns the predictor (e.g.
    :class:`inference.predictor.ImageSpec`, :class:`swiftjax.synthetic.demo.OracleSpec`);
    ``ground_truth``: ``[N, 4, 4]`` poses, a trajectory file (``gt_format``), or None;
    ``timestamps``: a times file (as ``reconstruct --timestamps``), or None: the frames'
    own times (a video's), else the frame index.
    """

    name: str
    spec: Any
    ground_truth: Any = None
    gt_format: str = "kitti"
    timestamps: str | None = None


def read_list(path: str | os.PathLike[str]) -> list[tuple[str, str | None]]:
    """``(input, ground truth or None)`` per line of a batch list: ``INPUT [GT]``, blank
    lines and comments skipped, relative paths relative to the list's folder.

    Fields are split as a POSIX shell splits words (:mod:`shlex`): quote a path holding
    spaces (``"my seq" gt.txt``), or escape them (``my\\ seq``); ``#`` starts a comment at
    the start of a line or after white space only, so ``take#1/frames`` is one path."""
    path = pathlib.Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise BatchError(f"cannot read the batch list {path}: {getattr(err, 'strerror', None) or err}") from err
    base = path.parent
    out = []
    for number, line in enumerate(text.splitlines(), start=1):
        try:
            fields = shlex.split(_strip_comment(line))
        except ValueError as err:  # an unclosed quote
            raise BatchError(f"{path}:{number}: {err} in {line.strip()!r}") from None
        if not fields:
            continue
        if len(fields) > 2:
            raise BatchError(
                f"{path}:{number}: expected 'INPUT [GROUND_TRUTH]', got {len(fields)} fields {fields} "
                "(quote a path that holds spaces)"
            )
        if any(not f.strip() for f in fields):
            raise BatchError(f"{path}:{number}: an empty path")
        resolve = lambda p: p if os.path.isabs(p) else str(base / p)
        out.append((resolve(fields[0]), resolve(fields[1]) if len(fields) == 2 else None))
    if not out:
        raise BatchError(f"the batch list {path} names no sequence")
    return out


def _strip_comment(line: str) -> str:
    """``line`` up to its comment: a ``#`` outside quotes at the start or after white space."""
    quote = None
    for k, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (k == 0 or line[k - 1].isspace()):
            return line[:k]
    return line


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
    """A run-directory name per input: the name of its folder (or file stem) after resolving
    the path (``..`` or ``.`` name the folder they point to), ``<parent>`` for a frames folder
    called ``images``; made unique with ``_2``...  A path without a name (``/``) is refused."""
    names: list[str] = []
    for item in inputs:
        p = pathlib.Path(item).resolve()
        base = p.parent.name if p.name == "images" else p.stem
        if base in ("", ".", ".."):
            raise BatchError(f"cannot name a run directory after {item!r}: give the sequence's own folder")
        name, k = base, 2
        while name in names:
            name, k = f"{base}_{k}", k + 1
        names.append(name)
    return names


def _run_dir(out: pathlib.Path, name: str) -> pathlib.Path:
    """``out / name``, which must be a folder directly inside ``out`` (a name ``..`` wrote a
    sequence's run into the parent of ``--out``)."""
    if name in ("", ".", "..") or pathlib.PurePath(name).name != name or "/" in name or "\\" in name:
        raise BatchError(f"sequence name {name!r} is not a folder name (it must name a folder inside --out)")
    return out / name


def sequence_timestamps(inputs: Seq[str], name: str) -> list[str]:
    """The times file ``name`` of each sequence (``--timestamps NAME``): in the input's folder,
    or beside it when the frames are a subfolder (TUM: ``seq/rgb/`` and ``seq/rgb.txt``), or
    beside a video.  :class:`BatchError` naming the first sequence that has none."""
    if pathlib.PurePath(name).name != name:
        raise BatchError(f"--timestamps {name!r}: give a file name, found in each sequence's folder")
    out = []
    for item in inputs:
        p = pathlib.Path(item)
        places = [p / name, p.parent / name] if p.is_dir() else [p.parent / name]
        found = next((q for q in places if q.is_file()), None)
        if found is None:
            raise BatchError(
                f"--timestamps {name}: sequence {item} has no {name} (looked in "
                f"{', '.join(str(q.parent) for q in places)})"
            )
        out.append(str(found))
    return out


def run_sequence(
    job: Sequence, out: str, config: PipelineConfig, overwrite: bool, jax_cache_dir: str | None = None
) -> dict[str, Any]:
    """One sequence, in this process (or a worker's): its row of the batch table.  Every
    error is the row's ``error`` (first line), never raised; KeyboardInterrupt is."""
    from swiftjax.pipeline.executors import LocalExecutor
    from swiftjax.pipeline.run import reconstruct

    if jax_cache_dir:
        import jax

        jax.config.update("jax_compilation_cache_dir", jax_cache_dir)
    run_dir = _run_dir(pathlib.Path(out), job.name)
    row: dict[str, Any] = {"sequence": job.name, "run_dir": str(run_dir), "status": "failed"}
    t0 = time.perf_counter()
    try:
        gt = job.ground_truth
        if isinstance(gt, (str, os.PathLike)):
            from swiftjax.io import trajectory

            gt = trajectory.read_kitti(gt) if job.gt_format == "kitti" else trajectory.read_tum(gt)[1]
        predictor = job.spec.build()
        if gt is not None and len(gt) != predictor.num_frames:
            raise InputError(f"ground truth has {len(gt)} poses for {predictor.num_frames} frames")
        times, note = _times(job, predictor)
        result = reconstruct(
            predictor,
            run_dir,
            config,
            ground_truth=gt,
            overwrite=overwrite,
            progress=False,
            log=lambda line: None,
            executor=LocalExecutor(),
            timestamps=times,
            timestamps_note=note,
        )
    except Exception as err:
        row["error"] = f"{type(err).__name__}: {' '.join(str(err).split()) or type(err).__name__}"
    else:
        m = result.metrics
        row.update(status="ok", frames=result.num_frames, chunks=result.num_chunks, loops=int(m["loops"]))
        if "ate_rmse" in m:
            row["ate_rmse"] = float(m["ate_rmse"])
    row["seconds"] = time.perf_counter() - t0
    return row


def _times(job: Sequence, predictor: Any) -> tuple[Any, str | None]:
    """A sequence's times for ``poses_tum.txt``, as ``reconstruct`` takes them: its times
    file, else its source's own (a video's frame times), else ``(None, None)`` (frame index)."""
    source = getattr(predictor, "source", None)
    if job.timestamps is not None:
        from swiftjax.io import images

        return images.read_timestamps(job.timestamps, source, getattr(job.spec, "stride", 1)), f"from {job.timestamps}"
    if source is not None and hasattr(source, "timestamps"):
        return source.timestamps()
    return None, None


class _SequenceActor:
    """A Ray actor running whole sequences, one at a time (its models stay loaded)."""

    def run(
        self, job: Sequence, out: str, config: PipelineConfig, overwrite: bool, jax_cache_dir: str | None
    ) -> dict[str, Any]:
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
    log: Callable[[str], None] = logger.info,
) -> list[dict[str, Any]]:
    """Run every sequence (see the module docstring); one row per sequence, in ``jobs``'
    order, also written to ``out/batch.json``.  ``log`` gets a line per finished sequence."""
    out = pathlib.Path(out)
    names = [j.name for j in jobs]
    if not jobs:
        raise BatchError("the batch has no sequence")
    if len(set(names)) != len(names):
        raise BatchError(f"sequence names must be unique, got {names}")
    from swiftjax.pipeline.executors import check_workers

    check_workers(workers)
    for name in names:
        _run_dir(out, name)
    if out.exists() and not out.is_dir():
        raise BatchError(f"--out {out} is a file: give a folder for the runs and batch.json")
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
        _run_on_ray(
            jobs, str(out), config, overwrite, cache, done, workers, gpus_per_worker, cpus_per_worker, ray_address
        )
    else:
        raise BatchError(f"executor must be 'local' or 'ray', got {executor!r}")
    final = [r for r in rows if r is not None]
    with atomic_write(out / "batch.json") as f:
        json.dump(
            {
                "executor": executor,
                "workers": workers,
                "gpus_per_worker": gpus_per_worker,
                "seconds": time.perf_counter() - t0,
                "config": config.to_dict(),
                "sequences": final,
            },
            f,
            indent=1,
            default=_json_default,
        )
    return final


def _run_on_ray(jobs, out, config, overwrite, cache, done, workers, gpus, cpus, address) -> None:
    from swiftjax.pipeline.executors import RayExecutor

    pool = RayExecutor(workers, gpus_per_worker=gpus, cpus_per_worker=cpus, address=address)
    ray = pool.ray
    try:
        actor_cls = ray.remote(_SequenceActor).options(
            num_cpus=cpus,
            num_gpus=gpus,
            max_restarts=pool.max_restarts,
            max_task_retries=pool.max_task_retries,
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
                row = {
                    "sequence": jobs[k].name,
                    "run_dir": str(pathlib.Path(out) / jobs[k].name),
                    "status": "failed",
                    "error": f"worker failed: {str(err).strip().splitlines()[0]}",
                    "seconds": float("nan"),
                }
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
    from swiftjax.io.tables import markdown_table

    body = [
        [
            r["sequence"],
            r["status"],
            r.get("frames", ""),
            r.get("loops", ""),
            f"{r['ate_rmse']:.4g}" if "ate_rmse" in r else "",
            f"{r['seconds']:.1f}",
            r.get("error", ""),
        ]
        for r in rows
    ]
    return markdown_table(["sequence", "status", "frames", "loops", "ATE rmse (m)", "time (s)", "error"], body)

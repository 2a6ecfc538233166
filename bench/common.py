"""Shared helpers for the bench/ scripts: timing, tables and JSON results.

Every bench script prints a markdown table and writes one JSON file per run under
``bench/results/<name>-<UTC timestamp>.json`` (temp file + rename).  Timings are best-of-N
wall-clock seconds with inputs already on the device; compile time is measured separately
(first call minus a steady-state call, via ``jax.jit(...).lower().compile()``).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import pathlib
import platform
import time
from collections.abc import Callable
from typing import Any

from swiftjax.io.tables import markdown_table  # (re-exported for the bench scripts too)

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def block(x: Any) -> Any:
    """Wait for every array in a pytree (JAX dispatch is asynchronous)."""
    import jax

    return jax.block_until_ready(x)


def best_of(fn: Callable[[], Any], repeat: int = 10, min_time: float = 0.0) -> float:
    """Best wall time of ``fn()`` over ``repeat`` calls (results blocked on)."""
    best = float("inf")
    start_all = time.perf_counter()
    n = 0
    while n < repeat or time.perf_counter() - start_all < min_time:
        t0 = time.perf_counter()
        block(fn())
        best = min(best, time.perf_counter() - t0)
        n += 1
    return best


def compile_time(jitted: Callable, *args: Any, **kwargs: Any) -> tuple[Callable, float]:
    """AOT-compile ``jitted`` for these arguments; returns (compiled, seconds)."""
    t0 = time.perf_counter()
    compiled = jitted.lower(*args, **kwargs).compile()
    return compiled, time.perf_counter() - t0


def reconstruct(run: Any, out_dir: pathlib.Path, config: Any, overwrite: bool = True) -> Any:
    """``pipeline.reconstruct`` of a synthetic run (``swiftjax.synthetic.demo``) into ``out_dir``
    (overwriting it unless ``overwrite`` is False), with its ground truth, quietly (no progress
    bar, no log)."""
    from swiftjax import pipeline

    return pipeline.reconstruct(
        run.predictor,
        out_dir,
        config,
        ground_truth=run.ground_truth,
        progress=False,
        overwrite=overwrite,
        log=lambda s: None,
    )


def machine_info() -> dict[str, Any]:
    import jax

    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
    }


def write_results(name: str, payload: dict[str, Any]) -> pathlib.Path:
    """Write ``payload`` (+ machine info, timestamp) to ``bench/results/name-<stamp>.json``."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    path = RESULTS / f"{name}-{stamp}.json"
    tmp = path.with_suffix(".json.tmp")
    body = {"benchmark": name, "timestamp": stamp, "machine": machine_info(), **payload}
    tmp.write_text(json.dumps(body, indent=2, default=float))
    os.replace(tmp, path)
    return path


def report_kernels(name: str, header: list[str], rows: list[list[str]], records: list[dict], load: Any) -> pathlib.Path:
    """The tail of a kernel benchmark: its table, the load average before (``load``, taken when
    it started) and now, and ``{"records", "load_average_before", "load_average_after"}``
    written as ``name`` (:func:`write_results`); returns the JSON's path."""
    print(markdown_table(header, rows))
    after = os.getloadavg()
    print(f"load average before: {load[0]:.2f}, after: {after[0]:.2f}")
    path = write_results(name, {"records": records, "load_average_before": load, "load_average_after": after})
    print(f"wrote {path}")
    return path

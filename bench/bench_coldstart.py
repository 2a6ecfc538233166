"""Cold start: ``swiftjax demo`` in fresh processes with an empty (and a warm) compile cache,
and the first call of the notebook entry points in a fresh process.

One command (the table is printed, the JSON goes to ``bench/results/coldstart-<stamp>.json``)::

    SWIFTJAX_SHARED=/work/shared python bench/bench_coldstart.py            # cold + warm demo, notebook
    python bench/bench_coldstart.py --modes cold --repeat 2                  # cold only, twice
    python bench/bench_coldstart.py --xla-flags "--xla_backend_optimization_level=1"   # try a flag

Each demo run is a new ``python`` process running ``swiftjax.cli.main(["demo", ...])`` with
``SWIFTJAX_CACHE_DIR`` pointing at a new empty folder (``cold``) or at the folder a cold run
just filled (``warm``).  Inside the child, ``jax.monitoring`` listeners record every backend
compile (function name, wall seconds, thread), tracing and lowering time and persistent-cache
hits; the stage clock (:class:`swiftjax.pipeline.rundir.StageTimer`) is wrapped so each compile
is booked to the stage open in the main thread when it ran (compiles on the prediction thread
are the synthetic oracle's: ``predict (thread)``).  Wall times on a shared machine are noisy:
the JSON carries the load average before and after each run and the process CPU time; compare
ratios taken in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Any

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

COMPILE = "/jax/core/compile/backend_compile_duration"
TRACE = "/jax/core/compile/jaxpr_trace_duration"
LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"


# ------------------------------------------------------------------------------ child side


def _install_listeners() -> dict[str, Any]:
    """jax.monitoring listeners filling ``rec`` (compiles, trace/lower sums, cache hits)."""
    import threading

    import jax

    rec: dict[str, Any] = {"compiles": [], "trace_s": 0.0, "lower_s": 0.0, "cache_hits": 0, "stage": ["(setup)"]}

    def span(event: str, start: float, end: float, **kw: Any) -> None:
        if event == COMPILE:
            main = threading.current_thread() is threading.main_thread()
            rec["compiles"].append(
                {
                    "fun": kw.get("fun_name", "?"),
                    "s": end - start,
                    "t": start,
                    "stage": rec["stage"][-1] if main else "predict (thread)",
                }
            )

    def duration(event: str, secs: float, **kw: Any) -> None:
        if event == TRACE:
            rec["trace_s"] += secs
        elif event == LOWER:
            rec["lower_s"] += secs

    def event(name: str, **kw: Any) -> None:
        if name == "/jax/compilation_cache/cache_hits":
            rec["cache_hits"] += 1

    jax.monitoring.register_event_time_span_listener(span)
    jax.monitoring.register_event_duration_secs_listener(duration)
    jax.monitoring.register_event_listener(event)
    return rec


def _wrap_stage_timer(rec: dict[str, Any]) -> None:
    import contextlib
    import threading

    from swiftjax.pipeline import rundir

    inner = rundir.StageTimer.__call__

    @contextlib.contextmanager
    def call(self, name):
        main = threading.current_thread() is threading.main_thread()
        if main:
            rec["stage"].append(name)
        try:
            with inner(self, name):
                yield
        finally:
            if main:
                rec["stage"].pop()

    rundir.StageTimer.__call__ = call


def _child_demo(out: str, result: str, extra: list[str]) -> None:
    t_start = time.perf_counter()
    rec = _install_listeners()
    _wrap_stage_timer(rec)
    from swiftjax.cli import main

    t_imported = time.perf_counter()
    code = main(["demo", "--out", out, "--overwrite", "--no-progress", *extra])
    t_end = time.perf_counter()
    metrics = json.loads((pathlib.Path(out) / "metrics.json").read_text())
    ru = __import__("resource").getrusage(__import__("resource").RUSAGE_SELF)
    rec.pop("stage")
    rec.update(
        code=code,
        import_s=t_imported - t_start,
        main_s=t_end - t_imported,
        cpu_s=ru.ru_utime + ru.ru_stime,
        timings=metrics.get("timings_seconds", {}),
        pose_graph=metrics.get("pose_graph", {}),
        ate=metrics.get("ate"),
    )
    pathlib.Path(result).write_text(json.dumps(rec, default=float))


def _child_notebook(result: str) -> None:
    """First (and second) call of the notebook entry points, each in this fresh process."""
    t0 = time.perf_counter()
    rec = _install_listeners()
    import jax
    import jax.numpy as jnp
    import numpy as np

    from swiftjax import align, posegraph, sim3

    rec["import_s"] = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    rows = []

    def timed(name: str, fn) -> None:
        n0 = len(rec["compiles"])
        t = time.perf_counter()
        jax.block_until_ready(fn())
        first = time.perf_counter() - t
        t = time.perf_counter()
        jax.block_until_ready(fn())
        second = time.perf_counter() - t
        comp = rec["compiles"][n0:]
        rows.append(
            {
                "call": name,
                "first_s": first,
                "second_s": second,
                "programs": len(comp),
                "compile_s": sum(c["s"] for c in comp),
                "functions": sorted({c["fun"] for c in comp}),
            }
        )

    xi = jnp.asarray(rng.normal(size=(1000, 7)) * 0.3, jnp.float32)
    timed("sim3.exp [1000, 7]", lambda: sim3.exp(xi))
    timed("jax.jit(sim3.exp) [1000, 7]", lambda: jax.jit(sim3.exp)(xi))
    src = jnp.asarray(rng.normal(size=(10_000, 3)), jnp.float32)
    dst = jnp.asarray(np.asarray(src) * 2.0 + 1.0, jnp.float32)
    timed("align.umeyama [10000, 3]", lambda: align.umeyama(src, dst))

    O, H, W = 30, 154, 518
    K = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]], np.float32)
    depth = (5.0 + rng.random((O, H, W))).astype(np.float32)
    conf = (1.0 + rng.random((O, H, W))).astype(np.float32)
    ext = np.tile(np.eye(4, dtype=np.float32)[:3], (O, 1, 1))
    f = align.ChunkFrames(depth, conf, np.tile(K, (O, 1, 1)), ext)
    timed(f"align.align_chunk_pair [{O}, {H}, {W}]", lambda: align.align_chunk_pair(f, f, K)[0])

    n = 12
    rel = np.tile(np.array([1.0, 0, 0, 0, 0, 0, 1, 1]), (n - 1, 1))
    poses = posegraph.chain_poses(rel)
    edges = np.array([(i, i + 1) for i in range(n - 1)] + [(0, n - 1)], np.int32)
    meas = np.concatenate([rel, np.array([[n - 1.0, 0, 0, 0, 0, 0, 1, 1]])])
    with jax.enable_x64(True):
        problem = posegraph.Problem(jnp.asarray(poses), edges, jnp.asarray(meas))
        timed(f"posegraph.optimize ({n} nodes, {len(edges)} edges, float64)", lambda: posegraph.optimize(problem).poses)
    rec["rows"] = rows
    rec.pop("stage")
    pathlib.Path(result).write_text(json.dumps(rec, default=float))


# ------------------------------------------------------------------------------ parent side


def _run_child(args: list[str], env: dict[str, str], timeout: float) -> tuple[dict[str, Any], float]:
    with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as fh:
        result = fh.name
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, __file__, "--child", *args, "--result", result],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout[-4000:] + proc.stderr[-4000:])
        raise SystemExit(f"child {args[0]} failed with status {proc.returncode}")
    data = json.loads(pathlib.Path(result).read_text())
    os.unlink(result)
    return data, wall


def _summarise(data: dict[str, Any], wall: float, load: tuple[float, float]) -> dict[str, Any]:
    comp = data["compiles"]
    by_stage: dict[str, float] = {}
    by_fun: dict[str, list[float]] = {}
    for c in comp:
        by_stage[c["stage"]] = by_stage.get(c["stage"], 0.0) + c["s"]
        by_fun.setdefault(c["fun"], []).append(c["s"])
    top = sorted(((sum(v), len(v), k) for k, v in by_fun.items()), reverse=True)
    small = [c for c in comp if c["s"] < 0.25]
    return {
        "wall_s": wall,
        "import_s": data["import_s"],
        "main_s": data["main_s"],
        "cpu_s": data["cpu_s"],
        "load_before": load[0],
        "load_after": load[1],
        "programs": len(comp),
        "cache_hits": data["cache_hits"],
        "compile_s": sum(c["s"] for c in comp),
        "trace_s": data["trace_s"],
        "lower_s": data["lower_s"],
        "small_programs": len(small),
        "small_compile_s": sum(c["s"] for c in small),
        "timings": data["timings"],
        "compile_by_stage": by_stage,
        "top_functions": [{"fun": k, "compile_s": s, "count": n} for s, n, k in top[:25]],
        "pose_graph_compile_s": data["pose_graph"].get("compile_seconds"),
        "ate": data.get("ate"),
        "compiles": comp,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--child", choices=("demo", "notebook"), help=argparse.SUPPRESS)
    p.add_argument("--result", help=argparse.SUPPRESS)
    p.add_argument("--out", help="demo output folder (default: a temporary folder)")
    p.add_argument("--modes", default="cold,warm", help="comma list of cold, warm (warm reuses the cold run's cache)")
    p.add_argument("--repeat", type=int, default=1, help="cold/warm pairs to run")
    p.add_argument("--no-notebook", action="store_true", help="skip the notebook first-call timings")
    p.add_argument("--xla-flags", default=None, help="XLA_FLAGS for the children (default: inherited)")
    p.add_argument("--demo-args", default="", help="extra `swiftjax demo` arguments, one string")
    p.add_argument("--label", default="", help="a name for this configuration in the JSON")
    p.add_argument("--timeout", type=float, default=1800.0)
    args = p.parse_args()

    if args.child == "demo":
        _child_demo(args.out, args.result, args.demo_args.split())
        return
    if args.child == "notebook":
        _child_notebook(args.result)
        return

    import numpy as np  # noqa: F401  (parent only formats)

    from bench.common import markdown_table, write_results

    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    env.setdefault("SWIFTJAX_SHARED", str(ROOT.parent / "shared"))
    if args.xla_flags is not None:
        env["XLA_FLAGS"] = args.xla_flags
    modes = [m for m in args.modes.split(",") if m]
    work = pathlib.Path(tempfile.mkdtemp(prefix="swiftjax-coldstart-"))
    runs: list[dict[str, Any]] = []
    try:
        for r in range(args.repeat):
            cache = work / f"cache{r}"
            for mode in modes:
                if mode == "cold":
                    shutil.rmtree(cache, ignore_errors=True)
                cache.mkdir(exist_ok=True)
                out = args.out or str(work / "demo")
                child_env = dict(env, SWIFTJAX_CACHE_DIR=str(cache))
                load0 = os.getloadavg()[0]
                data, wall = _run_child(
                    ["demo", "--out", out, "--demo-args=" + args.demo_args], child_env, args.timeout
                )
                s = _summarise(data, wall, (load0, os.getloadavg()[0]))
                s.update(mode=mode, repeat=r)
                runs.append(s)
                print(
                    f"[{mode} #{r}] wall {wall:.1f} s, demo {s['main_s']:.1f} s, compile {s['compile_s']:.1f} s "
                    f"in {s['programs']} programs, load {load0:.1f}->{s['load_after']:.1f}",
                    flush=True,
                )
        notebook = None
        if not args.no_notebook:
            load0 = os.getloadavg()[0]
            nb_env = dict(env)
            nb_env.pop("SWIFTJAX_CACHE_DIR", None)
            data, wall = _run_child(["notebook"], nb_env, args.timeout)
            notebook = {
                "wall_s": wall,
                "import_s": data["import_s"],
                "rows": data["rows"],
                "load_before": load0,
                "load_after": os.getloadavg()[0],
            }
    finally:
        shutil.rmtree(work, ignore_errors=True)

    stages = [
        "predict",
        "predict (loop chunks)",
        "align",
        "loop detection",
        "loop chunks",
        "loop verification",
        "pose graph",
        "chunk store",
        "export",
    ]
    header = ["", *[f"{s['mode']} #{s['repeat']}" for s in runs]]
    rows = [
        ["process wall (s)", *[f"{s['wall_s']:.1f}" for s in runs]],
        ["  import + CLI set-up (s)", *[f"{s['import_s']:.1f}" for s in runs]],
        ["  demo, `done in` (s)", *[f"{s['main_s']:.1f}" for s in runs]],
        ["process CPU (s)", *[f"{s['cpu_s']:.1f}" for s in runs]],
        ["compiled programs (cache hits)", *[f"{s['programs']} ({s['cache_hits']})" for s in runs]],
        ["backend compile, sum (s)", *[f"{s['compile_s']:.1f}" for s in runs]],
        ["  programs < 0.25 s: count / s", *[f"{s['small_programs']} / {s['small_compile_s']:.1f}" for s in runs]],
        ["trace + lower (s)", *[f"{s['trace_s'] + s['lower_s']:.1f}" for s in runs]],
        ["pose graph compile_seconds", *[f"{s['pose_graph_compile_s'] or 0:.2f}" for s in runs]],
    ]
    for st in stages:
        rows.append(
            [
                f"stage {st}: wall / compile (s)",
                *[f"{s['timings'].get(st, 0):.1f} / {s['compile_by_stage'].get(st, 0):.1f}" for s in runs],
            ]
        )
    rows.append(
        ["compile on prediction thread (s)", *[f"{s['compile_by_stage'].get('predict (thread)', 0):.1f}" for s in runs]]
    )
    rows.append(["compile outside stages (s)", *[f"{s['compile_by_stage'].get('(setup)', 0):.1f}" for s in runs]])
    rows.append(["load average before -> after", *[f"{s['load_before']:.1f} -> {s['load_after']:.1f}" for s in runs]])
    print()
    print(markdown_table(header, rows))
    if runs:
        cold = next((s for s in runs if s["mode"] == "cold"), runs[0])
        print(f"\nlargest compiles ({cold['mode']} #{cold['repeat']}):")
        print(
            markdown_table(
                ["function", "programs", "compile (s)"],
                [[t["fun"], str(t["count"]), f"{t['compile_s']:.2f}"] for t in cold["top_functions"][:15]],
            )
        )
    if notebook:
        print(
            f"\nnotebook, fresh process, no persistent cache (import {notebook['import_s']:.1f} s, load "
            f"{notebook['load_before']:.1f}):"
        )
        print(
            markdown_table(
                ["first call", "first (s)", "second (s)", "programs", "compile (s)"],
                [
                    [
                        r["call"],
                        f"{r['first_s']:.3f}",
                        f"{r['second_s']:.4f}",
                        str(r["programs"]),
                        f"{r['compile_s']:.2f}",
                    ]
                    for r in notebook["rows"]
                ],
            )
        )
    path = write_results(
        "coldstart",
        {
            "label": args.label,
            "xla_flags": env.get("XLA_FLAGS", ""),
            "demo_args": args.demo_args,
            "runs": runs,
            "notebook": notebook,
            "loadavg_end": os.getloadavg(),
        },
    )
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()

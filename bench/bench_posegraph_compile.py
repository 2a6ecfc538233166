"""Benchmark: the pose graph's cold compile on the demo's shapes, in fresh processes with an empty cache.

The demo's pose graph (14 chunks, 13 odometry + 4 loop edges, float64, GNC on the loop edges,
full 7 x 7 information) pads to the smallest bucket ``(32, 32)`` and takes the dense path.
Each run starts a new Python process with an empty ``JAX_COMPILATION_CACHE_DIR`` and reports:
``compile_seconds`` (what ``metrics.json`` records as ``pose_graph.compile_seconds``), the wall
time of the first ``optimize`` call, every XLA compilation of that call (program name and
seconds, from ``jax_log_compiles``), and the solve time of a second, warm call.  The machine's
load average is recorded with each run.

    .venv/bin/python bench/bench_posegraph_compile.py [--repeat 3] [--kernel gnc|none] [--baseline OTHER_CHECKOUT]

``--baseline`` runs another checkout (e.g. ``git worktree add /tmp/base <commit>``) alternately
with this one, so both see the same machine load.

``--growing`` measures the robust back end as an online run calls it: the KITTI 00 chunk graph
of ``bench/_robust_graph.py`` (``slight`` false loops at 100 %, matched information) cut to its
first ``T`` chunks for ``T = --first .. --last`` (one more chunk per call, each loop and false loop
joining when its later chunk arrives), :func:`swiftjax.loops.pcm.consistent_solve` (PCM, GNC,
data snooping, float64) once per ``T`` in one fresh process with an empty compilation cache.
Per call: the XLA compilations (count, seconds, programs), the wall time and the final poses;
with ``--baseline`` the two checkouts' poses are compared call by call (the padded programs
against the exact-size ones).  Writes ``bench/results/posegraph_compile_growing-<stamp>.json``.

    .venv/bin/python bench/bench_posegraph_compile.py --growing [--first 24] [--last 101] [--capacity 101 130] [--baseline OTHER]

``--capacity N E`` adds a run of this checkout with ``pad=(N, E)`` (the capacity an online run
knows: every size up to it in one bucket).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

REPO = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

#: The children's record of XLA compiles, ``records = [(program, seconds), ...]``, read off JAX's
#: compile log (after ``import jax``).
RECORD_COMPILES = r"""records = []
class _H(logging.Handler):
    def emit(self, rec):
        m = re.search(r"Finished XLA compilation of (\S+) in ([0-9.e-]+) sec", rec.getMessage())
        if m:
            records.append((m.group(1), float(m.group(2))))
jax.config.update("jax_log_compiles", True)
logging.getLogger("jax").addHandler(_H())
logging.getLogger("jax").setLevel(logging.WARNING)
"""

CHILD = (
    r"""
import json, logging, os, re, sys, time
t_import = time.perf_counter()
import numpy as np, jax
"""
    + RECORD_COMPILES
    + r"""from swiftjax import posegraph
try:
    from swiftjax.synthetic.pose_graphs import chain_graph
except ImportError:  # a checkout from before the move (for A/B runs with --repo)
    from swiftjax.synthetic.pose_graphs import chain_graph
kernel = None if sys.argv[1] == "none" else sys.argv[1]
t_ready = time.perf_counter()
with jax.enable_x64(True):
    g = chain_graph(14, loop_every=3, seed=0)
    info = np.einsum("ek,kl->ekl", g.information, np.eye(7))
    prob = posegraph.Problem(g.initial, g.edges, g.measurements, information=info, robust=g.is_loop)
    records.clear()  # the graph's generation ran eager sim3 ops
    t0 = time.perf_counter()
    first = posegraph.optimize(prob, posegraph.GraphOptions(kernel=kernel))
    t1 = time.perf_counter()
    n_first = len(records)
    second = posegraph.optimize(prob, posegraph.GraphOptions(kernel=kernel))
print(json.dumps(dict(
    import_seconds=t_ready - t_import, compile_seconds=first.compile_seconds, first_call_seconds=t1 - t0,
    solve_seconds_warm=second.solve_seconds, bucket=first.bucket, linear_solver=first.linear_solver,
    status=first.status, num_steps=first.num_steps, cost_final=first.cost_final,
    compiles=records[:n_first], compiles_second_call=records[n_first:], load=os.getloadavg(),
)))
"""
)


GROWING = (
    r"""
import json, logging, os, re, sys, time
import numpy as np, jax
"""
    + RECORD_COMPILES
    + r"""sys.path.insert(0, "bench")
import _robust_graph as rg
from swiftjax import posegraph
from swiftjax.loops import pcm
from swiftjax.posegraph import gnc
first, last = int(sys.argv[1]), int(sys.argv[2])
capacity = json.loads(sys.argv[3])  # None or [max_nodes, max_edges]: consistent_solve's pad
g = rg.kitti_chunk_graph(None, seed=0, route="00", generator="slight", max_false=rg.NUM_TRUE)
kind, edges = g["kind"], g["edges"]
calls = []
with jax.enable_x64(True):
    for T in range(first, last + 1):
        keep = edges.max(1) < T
        prob = posegraph.Problem(
            g["initial"][:T], edges[keep], g["measurements"][keep],
            information=1.0 / g["sigma"][keep] ** 2, robust=kind[keep] != "odometry",
        )
        records.clear()
        t0 = time.perf_counter()
        extra = {} if capacity is None else {"pad": tuple(capacity)}
        res, check = pcm.consistent_solve(
            prob, None, options=posegraph.GraphOptions(kernel_scale=gnc.DEFAULT_SCALE), throw=False, **extra
        )
        wall = time.perf_counter() - t0
        calls.append(dict(
            nodes=T, edges=int(keep.sum()), loops=int(np.sum(kind[keep] == "loop")),
            false_loops=int(np.sum(kind[keep] == "false")), wall_seconds=wall,
            compiles=len(records), compile_seconds=sum(s for _, s in records), programs=sorted({n for n, _ in records}),
            kept_false=int(np.sum(res.inlier_weights[kind[keep] == "false"] >= 0.5)),
            poses=np.asarray(res.poses, np.float64).tolist(), load=os.getloadavg()[0],
        ))
print(json.dumps(calls))
"""
)


def run_growing(first: int, last: int, repo: pathlib.Path = REPO, capacity=None) -> list[dict]:
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=cache, PYTHONPATH=str(repo))
        out = subprocess.run(
            [sys.executable, "-c", GROWING, str(first), str(last), json.dumps(capacity)],
            capture_output=True,
            text=True,
            env=env,
            check=True,
            cwd=repo,
        )
    return json.loads(out.stdout.strip().splitlines()[-1])


def growing_main(args) -> None:
    import numpy as np

    from bench.common import markdown_table, write_results

    checkouts = [("this", REPO, None)]
    if args.capacity:
        checkouts.append(("this, pad=capacity", REPO, args.capacity))
    if args.baseline:
        checkouts.append(("baseline", args.baseline.resolve(), None))
    runs = {name: run_growing(args.first, args.last, repo, cap) for name, repo, cap in checkouts}
    summary = {}
    for name, calls in runs.items():
        warm = calls[1:]  # the first call compiles everything in either checkout
        summary[name] = dict(
            calls=len(calls),
            compiles_total=sum(c["compiles"] for c in calls),
            compile_seconds_total=sum(c["compile_seconds"] for c in calls),
            wall_seconds_total=sum(c["wall_seconds"] for c in calls),
            calls_after_first_with_compiles=sum(c["compiles"] > 0 for c in warm),
            compile_seconds_after_first=sum(c["compile_seconds"] for c in warm),
            wall_seconds_after_first=sum(c["wall_seconds"] for c in warm),
            false_loops_kept_max=max(c["kept_false"] for c in calls),
            load=[min(c["load"] for c in calls), max(c["load"] for c in calls)],
        )
    diffs = {}
    for name in runs:
        if name != "this":
            diff = [
                float(np.abs(np.asarray(a["poses"])[:, :3] - np.asarray(b["poses"])[:, :3]).max())
                for a, b in zip(runs["this"], runs[name])
            ]
            diffs[name] = dict(max_m=max(diff), per_call_m=diff)
    summary["translation_difference_from_this"] = diffs
    head = [
        "checkout",
        "calls",
        "XLA compiles",
        "compile s",
        "wall s",
        "calls after the first that compile",
        "compile s after the first",
        "load",
    ]
    rows = [
        [
            name,
            v["calls"],
            v["compiles_total"],
            f"{v['compile_seconds_total']:.1f}",
            f"{v['wall_seconds_total']:.1f}",
            v["calls_after_first_with_compiles"],
            f"{v['compile_seconds_after_first']:.1f}",
            f"{v['load'][0]:.1f}-{v['load'][1]:.1f}",
        ]
        for name, v in summary.items()
        if name in runs
    ]
    print(markdown_table(head, rows))
    for name, d in diffs.items():
        print(f"largest node translation difference, {name} vs this: {d['max_m']:.3g} m")
    for calls in runs.values():
        for c in calls:
            c.pop("poses")
    result = {"first": args.first, "last": args.last, "capacity": args.capacity, "summary": summary, "runs": runs}
    print(write_results("posegraph_compile_growing", result))


def run_once(kernel: str, repo: pathlib.Path = REPO) -> dict:
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=cache, PYTHONPATH=str(repo))
        out = subprocess.run(
            [sys.executable, "-c", CHILD, kernel], capture_output=True, text=True, env=env, check=True, cwd=repo
        )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--kernel", default="gnc", choices=("gnc", "cauchy", "none"))
    ap.add_argument(
        "--baseline",
        type=pathlib.Path,
        default=None,
        help="another checkout (e.g. an older commit's worktree) run alternately with this one",
    )
    ap.add_argument("--growing", action="store_true", help="the robust back end on a growing graph (docstring)")
    ap.add_argument("--first", type=int, default=24, help="--growing: chunks at the first call")
    ap.add_argument("--last", type=int, default=101, help="--growing: chunks at the last call")
    ap.add_argument(
        "--capacity",
        type=int,
        nargs=2,
        metavar=("NODES", "EDGES"),
        help="--growing: also run this checkout with consistent_solve(..., pad=(NODES, EDGES))",
    )
    args = ap.parse_args()
    if args.growing:
        growing_main(args)
        return
    from bench.common import markdown_table, write_results

    checkouts = [("this", REPO)] + ([("baseline", args.baseline.resolve())] if args.baseline else [])
    runs = []
    for _ in range(args.repeat):
        for name, repo in checkouts:
            runs.append({"checkout": name, **run_once(args.kernel, repo)})
    rows = []
    for k, r in enumerate(runs):
        big = sorted(r["compiles"], key=lambda c: -c[1])[:3]
        rows.append(
            {
                "run": k,
                "checkout": r["checkout"],
                "compile s": f"{r['compile_seconds']:.2f}",
                "first call s": f"{r['first_call_seconds']:.2f}",
                "XLA programs": len(r["compiles"]),
                "largest": ", ".join(f"{n} {s:.2f}" for n, s in big),
                "warm solve s": f"{r['solve_seconds_warm']:.3f}",
                "load": f"{r['load'][0]:.1f}",
            }
        )
    print(markdown_table(list(rows[0]), [list(r.values()) for r in rows]))
    best = {}
    for name, _ in checkouts:
        mine = [r for r in runs if r["checkout"] == name]
        best[name] = min(r["compile_seconds"] for r in mine)
        print(
            f"{name}: best compile_seconds {best[name]:.2f} s (load {min(r['load'][0] for r in mine):.1f}-"
            f"{max(r['load'][0] for r in mine):.1f})"
        )
    write_results("posegraph_compile", {"kernel": args.kernel, "runs": runs, "best_compile_seconds": best})


if __name__ == "__main__":
    main()

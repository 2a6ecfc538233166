"""The loop threshold that calibrates itself, against the tuned constant and the authors' rule.

For each route (the demo's loop route, 618 frames; synthetic KITTI 00, 4,541 frames), each
place-token generator (:class:`swiftjax.synthetic.places.PlaceTokenConfig` variants with a
different dimension, hubness, noise, burst rate) and each whitening (ours: fitted on g1;
the authors' quirk: fitted on g0, applied to g1) the whole detector runs
(:func:`swiftjax.loops.find_loops`: top-8, separation 100, NMS +-25, one loop per chunk pair,
loops between neighbouring chunks dropped as the pipeline does) with

* ``fixed``: the constant 0.43 (``DEFAULT_THRESHOLD``, tuned on the default generator);
* ``adaptive``: the per-sequence rule ``tau = mu + Phi^-1(1 - alpha / n) sigma`` from the
  frames' best scores (:func:`swiftjax.loops.calibrate_threshold`, alpha = 1e-3);
* ``authors``: 0.98 with the whitening fitted on g0 (only in the g0 rows).

Candidate level, no aliasing and no geometric verification (the verification's bench is
``bench/bench_loop_robustness.py``): ``P`` = correct candidates / candidates, ``R`` = true
loop regions with a candidate / regions (ground truth: cameras < 5 m and < 30 degrees apart,
> 100 frames; a candidate is correct within 25 frames of a true pair at both ends).  The
safe window is the range of thresholds with P = 1 and every region found (``lo`` = the
weakest region's best score, ``hi`` = the best false score), also in units of the fitted
null (``k = (score - mu) / sigma``): a rule with a fixed ``k`` works where the k-window
contains it.

Usage:  .venv/bin/python bench/bench_loop_threshold.py [--seeds 0] [--routes demo kitti00]
Data:   $SWIFTJAX_SHARED/data/trajectories/KITTI_00_gt.txt (or ../shared beside the repo).
Writes bench/results/loop_threshold-<timestamp>.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import pathlib
import sys
import time

import jax
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from bench.bench_place_recognition import load_kitti00, synthetic_descriptors
from bench.common import markdown_table, write_results
from swiftjax import loops as L
from swiftjax.chunks import chunk_schedule
from swiftjax.loops import descriptors, detection, loop_chunk
from swiftjax.synthetic import places
from swiftjax.synthetic.routes import loop_route

GENERATORS = {
    "default (d 1024, K 16)": {},
    "noise x1.6": {"noise": 1.6},
    "bursts x2, 2 %": {"burst_strength": 3.0, "burst_fraction": 0.02},
    "d 512, K 8": {"dim": 512, "tokens_per_frame": 8},
    "hubness: d 384, bias 6+-2": {"dim": 384, "bias_strength": 6.0, "bias_jitter": 2.0},
}


_best = jax.jit(detection._row_topk, static_argnums=(1, 2, 3))  # each frame's best separated score


def evaluate(found, gt, regions):
    pairs = np.array([(lp.i, lp.j) for lp in found], np.int64).reshape(-1, 2)
    ev = places.evaluate_loops(pairs, gt, regions=regions)
    return ev.precision, ev.n_regions_found, ev.n_regions, len(found)


def every_candidate(Z, sched):
    """All candidates at any threshold (NMS and the chunk filter are prefix-consistent in the
    threshold), loops between neighbouring chunks dropped: ``(pairs [M, 2], scores [M])``."""
    kept = L.filter_by_chunks(L.detect_loops(Z, -1.0, max_loops=4096), sched)
    c = int(kept.count)
    lc = loop_chunk._loop_chunks(
        np.maximum(np.asarray(kept.pairs), 0), np.asarray(sched.starts, np.int32), np.asarray(sched.ends, np.int32), 10
    )
    ok = (np.abs(np.asarray(lc.chunk_i) - np.asarray(lc.chunk_j)) >= 2)[:c] & np.asarray(lc.valid)[:c]
    return np.asarray(kept.pairs)[:c][ok], np.asarray(kept.scores)[:c][ok]


def safe_window(pairs, scores, gt, regions):
    """(hi, lo): best false score and the weakest region's best correct score."""
    from scipy.spatial import cKDTree

    pairs = pairs.astype(np.float64)
    ev = places.evaluate_loops(pairs, gt, regions=regions)
    best = np.full(int(regions.max()) + 1, -np.inf)
    for k, nb in enumerate(cKDTree(gt.astype(np.float64)).query_ball_point(pairs, 25, p=np.inf)):
        for r in set(regions[nb].tolist()):
            best[r] = max(best[r], scores[k])
    hi = float(scores[~ev.correct].max()) if (~ev.correct).any() else -np.inf
    return hi, float(best.min())


def run(name, poses, config, fit_on, sched, gt, regions):
    G = synthetic_descriptors(poses, config)
    out = {}

    def detect(**kw):
        found = L.find_loops(G, sched, L.LoopOptions(fit_on=fit_on, **kw), return_details=True)
        loops = [lp for lp in found[0] if abs(lp.chunk_i - lp.chunk_j) >= 2]
        return loops, found[1]

    for rule in ("fixed", "adaptive") + (("authors",) if fit_on == "raw" else ()):
        t0 = time.perf_counter()
        found, det = detect(rule=rule)
        seconds = time.perf_counter() - t0
        p, nf, nr, nc = evaluate(found, gt, regions)
        out[rule] = {
            "threshold": det["threshold"],
            "precision": p,
            "regions_found": nf,
            "regions": nr,
            "candidates": nc,
            "seconds": seconds,
            "ok": bool(p == 1.0 and nf == nr),
        }
    # the safe window and the fitted null, on the descriptors the rules saw
    Z = np.asarray(det["z"])
    hi, lo = safe_window(*every_candidate(Z, sched), gt, regions)
    best = np.asarray(_best(descriptors._l2(Z), 100, 1, detection._default_block_rows(len(Z)))[0])[:, 0]
    cal = L.calibrate_threshold(best)
    mu, sigma = float(cal.mu), float(cal.sigma)
    out["window"] = {
        "hi": hi,
        "lo": lo,
        "k_hi": (hi - mu) / sigma,
        "k_lo": (lo - mu) / sigma,
        "mu": mu,
        "sigma": sigma,
        "k": float(cal.k),
        "k_fixed": (L.DEFAULT_THRESHOLD - mu) / sigma,
    }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--routes", nargs="+", default=["demo", "kitti00"], choices=["demo", "kitti00"])
    args = ap.parse_args()

    routes = {"demo": loop_route, "kitti00": load_kitti00}
    rows, results = [], []
    for rname in args.routes:
        poses = routes[rname]()
        n = len(poses)
        sched = chunk_schedule(n)
        gt = places.ground_truth_loops(poses)
        regions = places.loop_regions(gt)
        loop_frames = np.unique(gt).size
        print(
            f"{rname}: {n} frames, {len(gt)} true pairs in {int(regions.max()) + 1} regions, "
            f"{100 * (1 - loop_frames / n):.0f} % of frames without a revisit",
            flush=True,
        )
        for seed in args.seeds:
            for gname, kw in GENERATORS.items():
                cfg = dataclasses.replace(places.PlaceTokenConfig(seed=seed), **kw)
                for fit_on in ("power", "raw"):
                    r = run(rname, poses, cfg, fit_on, sched, gt, regions)
                    w = r["window"]

                    def cell(rule):
                        x = r[rule]
                        return f"{x['precision']:.2f} / {x['regions_found']}/{x['regions']} @ {x['threshold']:.3f}" + (
                            "" if x["ok"] else " x"
                        )

                    window = (
                        f"({w['hi']:.3f}, {w['lo']:.3f}) k ({w['k_hi']:.1f}, {w['k_lo']:.1f})"
                        if w["lo"] > w["hi"]
                        else f"none ({w['lo']:.3f} <= {w['hi']:.3f})"
                    )
                    rows.append(
                        [
                            rname,
                            seed,
                            gname,
                            "g1 (ours)" if fit_on == "power" else "g0 (authors)",
                            cell("fixed"),
                            cell("adaptive"),
                            cell("authors") if "authors" in r else "-",
                            window,
                            f"{w['k']:.2f}",
                            f"{w['k_fixed']:.1f}",
                        ]
                    )
                    print(" | ".join(str(c) for c in rows[-1]), flush=True)
                    results.append(
                        {"route": rname, "seed": seed, "generator": gname, "config": kw, "fit_on": fit_on, **r}
                    )
    headers = [
        "route",
        "seed",
        "generator",
        "whitening fit",
        "fixed 0.43: P / regions @ tau",
        "adaptive: P / regions @ tau",
        "authors 0.98",
        "safe window (score, k)",
        "k adaptive",
        "k of 0.43",
    ]
    print(markdown_table(headers, rows))
    ok = lambda rule: sum(x[rule]["ok"] for x in results if rule in x)
    separable = [x for x in results if x["window"]["lo"] > x["window"]["hi"]]
    print(
        f"P = 1 with every region: fixed {ok('fixed')}/{len(results)}, adaptive {ok('adaptive')}/{len(results)}, "
        f"authors {ok('authors')}/{len(results) // 2}; cases some threshold separates: {len(separable)}"
    )
    path = write_results(
        "loop_threshold",
        {
            "load_average": list(os.getloadavg()),
            "false_alarms": L.DEFAULT_FALSE_ALARMS,
            "default_threshold": L.DEFAULT_THRESHOLD,
            "authors_threshold": L.AUTHORS_THRESHOLD,
            "results": results,
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

"""The user's camera on synthetic KITTI 00: known vs predicted K, metric scale, masks.

Every table compares runs of the full pipeline on the same oracle (its default noise: the
focal length off by up to +-2 % per frame, depth noise, drift), one after the other in this
process (warm compile cache; the load average before each run is recorded):

1. ``--intrinsics``: predicted K_ref (the first frame's) vs the true K from a file.  ATE
   (Sim(3)-aligned) and point accuracy / completeness (:func:`swiftjax.evaluation.chamfer`,
   metres) of ``points.ply`` against the world's true surfaces (every ``--gt-every``-th
   frame's true depth, sky and cars excluded), the cloud mapped by the trajectory's Sim(3)
   alignment.
2. ``--metric camera-height=1.65`` (same run as known K): the scale error (1 / the Sim(3)
   alignment's scale - 1), ATE and accuracy with an SE(3) alignment only (metres, no scale),
   with the chunks' factors combined by their median (``--metric-combine median``) and as
   priors on each chunk's scale in the pose graph (``--metric-combine prior``, for each
   ``--prior-sigmas`` value; the same run directory, so only the pose graph and the export
   run again on the same predictions), with and without loop closure.
   (``--metric gt`` is that Sim(3) scale itself, error 0 by construction: not run here.)
3. Masks on a world with ``--cars`` moving cars: none vs the true car masks (PNG folder) vs
   box masks (each car's bounding box) vs ``--drop-sky``; plus the sky rule's precision /
   recall against the world's sky label.

    python bench/bench_camera.py                 # whole KITTI 00 (4,541 frames)
    python bench/bench_camera.py --frames 1500   # a shorter part on a loaded machine
    python bench/bench_camera.py --only scale    # table 2 alone (median vs prior)
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import pathlib
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from common import markdown_table, write_results
from common import reconstruct as reconstruct_run

from swiftjax import evaluation, masks, pipeline
from swiftjax.io.ply import read_ply
from swiftjax.synthetic import demo
from swiftjax.synthetic.world import CAR, SKY


def _shared() -> pathlib.Path:
    env = os.environ.get("SWIFTJAX_SHARED")
    return pathlib.Path(env) if env else pathlib.Path(__file__).resolve().parents[2] / "shared"


def true_surfaces(oracle, frames: np.ndarray, stride: int = 4, max_points: int = 400_000) -> np.ndarray:
    """World points of the true static surfaces seen by ``frames`` (sky and cars excluded)."""
    out = []
    for k in range(0, len(frames), 15):
        f = frames[k : k + 15]
        pts, valid = oracle.true_world_points(f)
        _, sem, _ = oracle.render_truth(f)
        keep = valid & (sem != CAR) & (sem != SKY)
        sub = (slice(None), slice(None, None, stride), slice(None, None, stride))
        out.append(pts[sub][keep[sub]])
    p = np.concatenate(out)
    rng = np.random.default_rng(0)
    return p[rng.choice(len(p), max_points, replace=False)] if len(p) > max_points else p


def evaluate(res, gt: np.ndarray, surfaces: np.ndarray) -> dict:
    est = res.cam_to_world[:, :3, 3]
    pts = read_ply(res.run_dir / "points.ply").points.astype(np.float64)
    out = {"load_average_before": res.load_before}
    for align in ("sim3", "se3") if res.metrics["unit"] == "metres" else ("sim3",):
        a = evaluation.ate(est, gt[:, :3, 3], align=align)
        cloud = a.scale * pts @ a.rotation.T + a.translation
        ch = evaluation.chamfer(cloud, surfaces, max_points=200_000)
        out[align] = {
            "ate": a.rmse,
            "scale": a.scale,
            "accuracy": ch.accuracy,
            "completeness": ch.completeness,
            "accuracy_median": ch.accuracy_median,
        }
    out["ate_no_loops"] = evaluation.ate(res.cam_to_world_no_loops[:, :3, 3], gt[:, :3, 3]).rmse
    out["alignment"] = res.metrics["alignment"]
    out["metric_scale"] = res.metrics.get("metric_scale")
    out["scale_error"] = res.metrics.get("scale_error")
    out["wall_seconds"] = res.wall
    return out


def metric_scores(res, gt: np.ndarray) -> dict:
    """Scale error and SE(3) (no scale) ATE of a metric run, with and without loop closure."""
    out = {}
    for name, c2w in (("loops", res.cam_to_world), ("no_loops", res.cam_to_world_no_loops)):
        a = evaluation.ate(c2w[:, :3, 3], gt[:, :3, 3])
        out[name] = {
            "scale_error": 1.0 / a.scale - 1.0,
            "ate_se3": evaluation.ate(c2w[:, :3, 3], gt[:, :3, 3], "se3").rmse,
            "ate_sim3": a.rmse,
        }
    out["pose_graph_seconds"] = res.timings.get("pose graph")
    return out


def reconstruct(run, out: pathlib.Path, config, overwrite: bool = True) -> object:
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    res = reconstruct_run(run, out, config, overwrite)
    res.wall = time.perf_counter() - t0
    res.load_before = load
    print(f"  {out.name}: {res.wall:.0f} s (load {load:.1f})", flush=True)
    return res


def write_masks(oracle, n: int, folder: pathlib.Path, boxes: bool) -> None:
    """True car masks (or each car's bounding box per frame) as PNGs named like the frames."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for k in range(0, n, 15):
        f = np.arange(k, min(k + 15, n))
        _, sem, inst = oracle.render_truth(f)
        for i, frame in enumerate(f):
            keep = sem[i] != CAR
            if boxes:
                for c in np.unique(inst[i][~keep]):
                    rows, cols = np.nonzero(inst[i] == c)
                    keep[max(rows.min() - 2, 0) : rows.max() + 3, max(cols.min() - 2, 0) : cols.max() + 3] = False
            Image.fromarray(np.where(keep, 255, 0).astype(np.uint8)).save(folder / f"{frame:06d}.png")


def sky_scores(oracle, n: int, chunks: int = 6) -> dict:
    tp = fp = fn = 0
    for s in np.linspace(0, n - 75, chunks).astype(int):
        f = np.arange(s, s + 75)
        pred = oracle.predict_chunk(f)
        _, sem, _ = oracle.render_truth(f)
        sky = np.asarray(masks.sky_mask(pred.depth, pred.conf))
        truth = sem == SKY
        tp += int((sky & truth).sum())
        fp += int((sky & ~truth).sum())
        fn += int((~sky & truth).sum())
    return {
        "precision": tp / max(tp + fp, 1),
        "recall": tp / max(tp + fn, 1),
        "sky_fraction": (tp + fn) / (75 * chunks * 154 * 518),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=None, help="first N frames of KITTI 00 (default: all 4,541)")
    ap.add_argument("--cars", type=int, default=150, help="moving cars in the masks world")
    ap.add_argument("--gt-every", type=int, default=5, help="true surfaces from every k-th frame")
    ap.add_argument(
        "--only", default="k,masks", help="comma list of: k (tables 1-2), scale (table 2 alone), masks (table 3)"
    )
    ap.add_argument(
        "--prior-sigmas", default="0.01,0.02,0.05", help="metric_prior_sigma values of table 2's prior runs"
    )
    ap.add_argument(
        "--mask-variants",
        default="no mask,true car masks,box car masks,drop sky",
        help="comma list of the masks table's runs",
    )
    ap.add_argument("--work", type=pathlib.Path, default=None, help="run directories (default: a temp folder)")
    args = ap.parse_args()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    work = args.work or pathlib.Path(tempfile.mkdtemp(prefix="bench_camera_"))
    only = set(args.only.split(","))
    config = pipeline.PipelineConfig()
    payload: dict = {"frames": args.frames, "cars": args.cars, "runs": {}}

    if "k" in only or "scale" in only:
        run = demo.kitti00_run(_shared(), frames=args.frames)
        oracle = run.predictor.oracle
        n = oracle.num_frames
        K = oracle.K  # the world's true intrinsics at 518 x 154 (= the original images here)
        kfile = work / "K.txt"
        kfile.parent.mkdir(parents=True, exist_ok=True)
        kfile.write_text(f"{float(K[0, 0])!r} {float(K[1, 1])!r} {float(K[0, 2])!r} {float(K[1, 2])!r}\n")
        print(f"static world, {n} frames: true surfaces ...", flush=True)
        surfaces = true_surfaces(oracle, np.arange(0, n, args.gt_every))
        metric_cfg = dataclasses.replace(config, intrinsics=str(kfile), metric="camera-height=1.65")
        variants = {"known K + camera-height=1.65": metric_cfg}
        if "k" in only:
            variants = {"predicted K": config, **variants}
        for name, cfg in variants.items():
            res = reconstruct(run, work / name.replace(" ", "_").replace("=", ""), cfg)
            payload["runs"][name] = evaluate(res, run.ground_truth, surfaces)
        r = payload["runs"]["known K + camera-height=1.65"]
        r["metric"] = metric_scores(res, run.ground_truth)
        metric_dir = res.run_dir
        rk = payload["runs"]
        rows = [
            [
                name,
                r["sim3"]["ate"],
                r["ate_no_loops"],
                r["sim3"]["accuracy"],
                r["sim3"]["completeness"],
                r["load_average_before"],
            ]
            for name, r in rk.items()
        ]
        print(
            markdown_table(["K_ref", "ATE m (Sim(3))", "ATE no loops m", "accuracy m", "completeness m", "load"], rows)
        )
        # the same predictions, the chunks' factors as pose-graph priors (only graph + export re-run)
        payload["scale"] = {
            "median": {**r["metric"], "accuracy_se3": r["se3"]["accuracy"], "metric_scale": r["metric_scale"]}
        }
        for sigma in [float(v) for v in args.prior_sigmas.split(",") if v]:
            cfg = dataclasses.replace(metric_cfg, metric_combine="prior", metric_prior_sigma=sigma)
            res = reconstruct(run, metric_dir, cfg, overwrite=False)
            ev = evaluate(res, run.ground_truth, surfaces)
            payload["scale"][f"prior sigma={sigma:g}"] = {
                **metric_scores(res, run.ground_truth),
                "accuracy_se3": ev["se3"]["accuracy"],
                "metric_scale": res.metrics["metric_scale"],
                "load_average_before": res.load_before,
            }
        rows = [
            [
                name,
                v["loops"]["scale_error"],
                v["loops"]["ate_se3"],
                v["loops"]["ate_sim3"],
                v["no_loops"]["scale_error"],
                v["no_loops"]["ate_se3"],
                v["no_loops"]["ate_sim3"],
                v["accuracy_se3"],
                v["pose_graph_seconds"],
            ]
            for name, v in payload["scale"].items()
        ]
        print(
            markdown_table(
                [
                    "--metric-combine",
                    "scale error",
                    "ATE m SE(3) (no scale)",
                    "ATE m Sim(3)",
                    "no loops: scale error",
                    "no loops: ATE m SE(3)",
                    "no loops: ATE m Sim(3)",
                    "accuracy m SE(3)",
                    "pose graph s",
                ],
                rows,
            )
        )

    if "masks" in only:
        run = demo.kitti00_run(_shared(), frames=args.frames, moving_cars=args.cars)
        oracle = run.predictor.oracle
        n = oracle.num_frames
        print(f"world with {args.cars} moving cars, {n} frames: masks and true surfaces ...", flush=True)
        for boxes in (False, True):
            write_masks(oracle, n, work / ("masks_box" if boxes else "masks_true"), boxes)
        surfaces = true_surfaces(oracle, np.arange(0, n, args.gt_every))
        payload["sky"] = sky_scores(oracle, n)
        variants = {
            "no mask": config,
            "true car masks": dataclasses.replace(config, mask_dir=str(work / "masks_true")),
            "box car masks": dataclasses.replace(config, mask_dir=str(work / "masks_box")),
            "drop sky": dataclasses.replace(config, drop_sky=True),
        }
        for name, cfg in variants.items():
            if name not in args.mask_variants.split(","):
                continue
            res = reconstruct(run, work / name.replace(" ", "_"), cfg)
            payload["runs"]["cars: " + name] = evaluate(res, run.ground_truth, surfaces)
        rows = [
            [
                name,
                r["sim3"]["ate"],
                r["ate_no_loops"],
                r["sim3"]["accuracy"],
                r["sim3"]["completeness"],
                r["alignment"]["mean_points"],
                r["load_average_before"],
            ]
            for name, r in payload["runs"].items()
            if name.startswith("cars: ")
        ]
        print(
            markdown_table(
                ["masks", "ATE m", "ATE no loops m", "accuracy m", "completeness m", "reliable points / pair", "load"],
                rows,
            )
        )
        print("sky rule vs the sky label:", payload["sky"])
    print(write_results("camera", payload))


if __name__ == "__main__":
    main()

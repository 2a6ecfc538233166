"""The COLMAP export's choices, measured on the demo route (oracle, 518x154 frames).

* Camera: the model uses one shared ``K_ref``; how far off would VGGT's per-frame ``K`` put
  the observations?  Each exported point is re-projected through its frame's camera with
  ``K_ref`` and with that frame's own ``K`` (``intrinsics.txt``): pixel error stats.
* Frames: writing each frame as an image while its chunk is in memory -- PNG (Pillow,
  compression 1, the export's choice; lossless), PNG (OpenCV), JPEG q95 (Pillow) -- ms and
  KB per frame, against the predictor's time per frame in the same run.
* Export stage and whole run with the COLMAP model on vs off (``--colmap`` /
  ``--no-colmap``: frames + binary model), alternating fresh runs.

    python bench/bench_colmap_export.py [--frames 300] [--repeat 2]
"""

from __future__ import annotations

import argparse
import io
import os
import pathlib
import tempfile
import time

import numpy as np
from common import markdown_table, write_results

from swiftjax import pipeline
from swiftjax.synthetic import demo


def _run(frames: int, out: pathlib.Path, colmap: bool) -> tuple[float, pipeline.RunResult]:
    run = demo.loop_route_run(frames)
    t0 = time.perf_counter()
    result = pipeline.reconstruct(
        run.predictor,
        out,
        pipeline.PipelineConfig(colmap=colmap),
        ground_truth=run.ground_truth,
        progress=False,
        log=lambda _: None,
    )
    return time.perf_counter() - t0, result


def _reprojection(out: pathlib.Path) -> dict[str, float]:
    import pycolmap

    rec = pycolmap.Reconstruction(str(out / "colmap" / "sparse" / "0"))
    per_frame = np.loadtxt(out / "intrinsics.txt")[:, 1:]  # fx fy cx cy, integer pixel centres
    (cam,) = rec.cameras.values()
    err_ref, err_own = [], []
    for p in rec.points3D.values():
        el = p.track.elements[0]
        image = rec.images[el.image_id]
        xy = image.points2D[el.point2D_idx].xy
        x = np.asarray(image.cam_from_world() * p.xyz)
        err_ref.append(np.linalg.norm(cam.img_from_cam(x[None])[0] - xy))
        fx, fy, cx, cy = per_frame[el.image_id - 1]
        own = np.array([fx * x[0] / x[2] + cx + 0.5, fy * x[1] / x[2] + cy + 0.5])
        err_own.append(np.linalg.norm(own - xy))
    a, b = np.asarray(err_ref), np.asarray(err_own)
    f = per_frame[:, 0]
    return {
        "points": len(a),
        "K_ref_median_px": float(np.median(a)),
        "K_ref_max_px": float(a.max()),
        "own_K_median_px": float(np.median(b)),
        "own_K_p95_px": float(np.percentile(b, 95)),
        "own_K_max_px": float(b.max()),
        "fx_spread_percent": float(100 * (f.max() - f.min()) / np.median(f)),
    }


def _encoders(images: np.ndarray) -> dict[str, tuple[float, float]]:
    """ms and KB per frame of each encoder (best of 2 passes over the frames)."""
    from PIL import Image

    def pil(fmt: str, **kw):
        def enc(im):
            buf = io.BytesIO()
            Image.fromarray(im).save(buf, format=fmt, **kw)
            return buf.tell()

        return enc

    encoders = {
        "PNG, Pillow, level 1 (the export)": pil("PNG", compress_level=1),
        "PNG, Pillow, level 6": pil("PNG", compress_level=6),
        "JPEG q95, Pillow": pil("JPEG", quality=95),
    }
    try:
        import cv2

        encoders["PNG, OpenCV, level 1"] = lambda im: len(
            cv2.imencode(".png", im[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1])[1]
        )
    except ImportError:
        pass
    out = {}
    for name, enc in encoders.items():
        best, size = float("inf"), 0.0
        for _ in range(2):
            t0 = time.perf_counter()
            size = float(np.mean([enc(im) for im in images]))
            best = min(best, time.perf_counter() - t0)
        out[name] = (1e3 * best / len(images), size / 1e3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    results: dict = {"frames": args.frames, "load_average_start": os.getloadavg()}
    with tempfile.TemporaryDirectory() as tmp:
        d = pathlib.Path(tmp)
        _run(min(args.frames, 120), d / "warm", True)  # compile caches
        runs = {True: [], False: []}
        last = None
        for k in range(args.repeat):
            for colmap in (True, False):  # alternating, fresh directories
                wall, res = _run(args.frames, d / f"r{k}{int(colmap)}", colmap)
                runs[colmap].append(
                    {"wall_s": wall, "export_s": res.timings["export"], "predict_s": res.timings["predict"]}
                )
                if colmap:
                    last = (d / f"r{k}{int(colmap)}", res)
        assert last is not None
        out, res = last
        reproj = _reprojection(out)
        frames = demo.loop_route_run(80).predictor.predict(np.arange(75)).images
        enc = _encoders(frames)
        size_mb = sum(p.stat().st_size for p in (out / "colmap" / "images").iterdir()) / 1e6
    on = {k: min(r[k] for r in runs[True]) for k in runs[True][0]}
    off = {k: min(r[k] for r in runs[False]) for k in runs[False][0]}
    predict_ms = 1e3 * on["predict_s"] / args.frames
    results.update(
        reprojection=reproj,
        encoders=enc,
        colmap_on=runs[True],
        colmap_off=runs[False],
        images_mb=size_mb,
        load_average_end=os.getloadavg(),
    )

    print(
        markdown_table(
            ["camera in the model", "median px", "max px"],
            [
                ["shared K_ref (the export)", reproj["K_ref_median_px"], reproj["K_ref_max_px"]],
                ["each frame's own K", reproj["own_K_median_px"], reproj["own_K_max_px"]],
            ],
        )
    )
    print(f"per-frame fx spread: {reproj['fx_spread_percent']:.2f} % of the median; {reproj['points']} points")
    print(
        markdown_table(
            ["frame encoder", "ms / frame", "KB / frame", "vs predict / frame"],
            [[name, ms, kb, ms / predict_ms] for name, (ms, kb) in enc.items()],
        )
    )
    print(
        markdown_table(
            ["", "COLMAP on", "COLMAP off", "on - off"],
            [
                ["export stage (s)", on["export_s"], off["export_s"], on["export_s"] - off["export_s"]],
                ["whole run (s)", on["wall_s"], off["wall_s"], on["wall_s"] - off["wall_s"]],
            ],
        )
    )
    print(f"colmap/images: {size_mb:.1f} MB for {args.frames} frames; load {results['load_average_start']}")
    write_results("colmap_export", results)


if __name__ == "__main__":
    main()

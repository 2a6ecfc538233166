"""File-format layer throughput: swiftjax.io vs the obvious baselines, same inputs, one run.

* PLY write/read of N points (xyz f32 + rgb u8 + conf f32): ours (one structured write /
  ``np.fromfile``) vs ``plyfile`` (if installed) vs a per-point ``struct.pack`` loop.
* COLMAP ``points3D.txt`` of N points: ours (batched ``%`` formatting) vs ``np.savetxt``.
* Input validation per KITTI-sized PNG (1241x376): header-only probe vs a full OpenCV decode;
  the preflight's decode check (``validate(decode=True)``) per PNG / JPEG frame, on one
  thread and on the pool, against the header-only check.
* Chunk store, one KITTI chunk (75x154x518, images, 1024-D descriptors): float16 vs float32
  vs zlib-compressed float16, size and save/load time.

    python bench/bench_io.py [--n 500000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import pathlib
import struct
import tempfile

import numpy as np
from common import best_of, markdown_table, write_results

from swiftjax.io.chunk_store import ChunkStore
from swiftjax.io.colmap import write_colmap
from swiftjax.io.images import list_frames, validate
from swiftjax.io.ply import PlyStreamWriter, ply_dtype, read_ply, write_ply
from swiftjax.prediction import ChunkPrediction


def _loop_ply(path: pathlib.Path, p: np.ndarray, c: np.ndarray, k: np.ndarray) -> None:
    with open(path, "wb") as f:
        f.write(
            (
                "ply\nformat binary_little_endian 1.0\n"
                f"element vertex {len(p)}\nproperty float x\nproperty float y\nproperty float z\n"
                "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty float confidence\n"
                "end_header\n"
            ).encode()
        )
        pack = struct.Struct("<fffBBBf").pack
        for i in range(len(p)):
            f.write(pack(*p[i].tolist(), *c[i].tolist(), float(k[i])))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=500_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    n, rep = args.n, args.repeat
    rng = np.random.default_rng(0)
    p = rng.standard_normal((n, 3)).astype(np.float32)
    c = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    k = rng.uniform(1, 10, n).astype(np.float32)
    rows: list[list] = []
    results: dict = {"n_points": n}

    with tempfile.TemporaryDirectory() as tmp:
        d = pathlib.Path(tmp)
        # ---------------------------------------------------------------- PLY
        t_ours = best_of(lambda: write_ply(d / "a.ply", p, c, k), rep)

        def stream() -> None:
            with PlyStreamWriter(d / "s.ply") as w:
                for a in range(0, n, 100_000):
                    w.append(p[a : a + 100_000], c[a : a + 100_000], k[a : a + 100_000])

        t_stream = best_of(stream, rep)
        m = min(n, 100_000)  # the loop is slow: time it on fewer points, report per point
        t_loop = best_of(lambda: _loop_ply(d / "l.ply", p[:m], c[:m], k[:m]), 1) * n / m
        rows += [
            ["PLY write", "ours (one structured write)", t_ours, 1.0],
            ["PLY write", "ours, streamed in 100k batches", t_stream, t_stream / t_ours],
            ["PLY write", "per-point struct.pack loop", t_loop, t_loop / t_ours],
        ]
        t_read = best_of(lambda: read_ply(d / "a.ply"), rep)
        rows.append(["PLY read", "ours (np.fromfile)", t_read, 1.0])
        try:
            import plyfile

            def plyfile_write() -> None:  # pack + write + the fsync ours does: like for like
                rec = np.empty(n, ply_dtype())
                rec["x"], rec["y"], rec["z"] = p.T
                rec["red"], rec["green"], rec["blue"] = c.T
                rec["confidence"] = k
                plyfile.PlyData([plyfile.PlyElement.describe(rec, "vertex")]).write(str(d / "pf.ply"))
                with open(d / "pf.ply", "rb+") as f:
                    os.fsync(f.fileno())

            def plyfile_read() -> tuple[np.ndarray, np.ndarray]:  # default (memory-mapped), copied out
                v = plyfile.PlyData.read(str(d / "a.ply"))["vertex"]
                return np.stack([v["x"], v["y"], v["z"]], 1), np.stack([v["red"], v["green"], v["blue"]], 1)

            t_pw = best_of(plyfile_write, rep)
            t_pr = best_of(plyfile_read, rep)
            rows += [
                ["PLY write", "plyfile (+ fsync)", t_pw, t_pw / t_ours],
                ["PLY read", "plyfile (mmap, copied out)", t_pr, t_pr / t_read],
            ]
        except ImportError:
            pass

        # ---------------------------------------------------------------- COLMAP points3D.txt
        mc = min(n, 200_000)
        err = np.zeros(mc)
        one = (np.eye(4)[None], np.array([[[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]]), ["a.png"], (100, 100))
        t_c = best_of(lambda: write_colmap(d / "m", *one, p[:mc], c[:mc], err, binary=False, text=True), rep)
        table = np.column_stack([np.arange(1, mc + 1), p[:mc].astype(np.float64), c[:mc], err])
        t_s = best_of(lambda: np.savetxt(d / "q3.txt", table, fmt="%d %.9g %.9g %.9g %d %d %d %.9g"), rep)
        rows += [
            [f"points3D.txt ({mc} pts)", "ours (batched % format)", t_c, 1.0],
            [f"points3D.txt ({mc} pts)", "np.savetxt", t_s, t_s / t_c],
        ]

        # ---------------------------------------------------------------- image validation
        import cv2

        img = cv2.GaussianBlur(rng.integers(0, 256, (376, 1241, 3), dtype=np.uint8), (9, 9), 3)
        (d / "imgs").mkdir()
        for i in range(20):
            cv2.imwrite(str(d / "imgs" / f"{i:06d}.png"), img)
        src = list_frames(d / "imgs")
        t_h = best_of(lambda: [src.probe(i) for i in range(20)], rep) / 20
        t_dec = best_of(lambda: [src.read(i) for i in range(20)], rep) / 20
        rows += [
            ["validate one 1241x376 PNG", "header probe (Pillow)", t_h, 1.0],
            ["validate one 1241x376 PNG", "full decode (OpenCV)", t_dec, t_dec / t_h],
        ]
        # the preflight decode check (validate(decode=True)): per frame, 1 thread vs the pool
        for ext in ("png", "jpg"):
            folder = d / f"pre_{ext}"
            folder.mkdir()
            for i in range(20):
                cv2.imwrite(str(folder / f"{i:06d}.{ext}"), img)
            t_v0 = best_of(lambda: validate(list_frames(folder), decode=False), rep) / 20
            for workers in (1, None):
                t_v = best_of(lambda: validate(list_frames(folder), workers=workers), rep) / 20
                label = f"validate(decode=True), {'1 thread' if workers == 1 else 'thread pool'}"
                rows.append([f"preflight one 1241x376 {ext.upper()}", label, t_v, t_v / t_v0])
            rows.append([f"preflight one 1241x376 {ext.upper()}", "validate(decode=False) (headers)", t_v0, 1.0])

        # ---------------------------------------------------------------- chunk store
        s, h, w = 75, 154, 518
        yy, xx = np.mgrid[0:h, 0:w]
        depth = ((2 + 30 * (yy / h) ** 2)[None] * rng.uniform(0.9, 1.1, (s, 1, 1))).astype(np.float32)
        pred = ChunkPrediction(
            depth=depth,
            conf=(1 + np.exp(rng.normal(1, 1.5, (s, h, w)))).astype(np.float32),
            extrinsic=np.tile(np.eye(3, 4, dtype=np.float32), (s, 1, 1)),
            intrinsic=np.tile(np.eye(3, dtype=np.float32), (s, 1, 1)),
            descriptors=rng.standard_normal((s, 1024)).astype(np.float32),
            images=rng.integers(0, 256, (s, h, w, 3), dtype=np.uint8),
        )
        base = None
        for label, kw in [
            ("float16 depth/conf", {}),
            ("float32 (half=False)", {"half": False}),
            ("float16 + zlib", {"compress": True}),
        ]:
            store = ChunkStore(d / label.replace(" ", "_"), **kw)
            t_w = best_of(lambda: store.save("chunk", 0, pred), rep)
            t_l = best_of(lambda: store.load("chunk", 0), rep)
            size = store.path("chunk", 0).stat().st_size / 1e6
            base = base or (t_w, t_l, size)
            rows.append([f"chunk store save ({size:.0f} MB)", label, t_w, t_w / base[0]])
            rows.append(["chunk store load", label, t_l, t_l / base[1]])
            results[f"chunk_size_mb[{label}]"] = size

    print(markdown_table(["task", "method", "best s", "time / ours"], rows))
    results["rows"] = [dict(zip(["task", "method", "seconds", "ratio_to_ours"], r)) for r in rows]
    print(write_results("io", results))


if __name__ == "__main__":
    main()

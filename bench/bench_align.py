"""CPU microbenchmark: chunk alignment (issue 4), swiftjax vs VGGT-Long's IRLS.

For KITTI chunks at VGGT resolution (518 x 154) and overlaps O = 10, 30, 60 it times, in one
run and on the same inputs (already on the device, best of ``--repeats``):

* ``align_chunk_pair`` (mask + depth normalisation + unprojection + one Umeyama, float32,
  jitted) and ``umeyama`` alone on the ``O H W`` point pairs with mask weights;
* the IRLS baseline (``irls_sim3``, jitted, same mask / points) and a plain NumPy port of
  VGGT-Long's loop as a user would run it (float64, boolean indexing, 5 iterations);
* a vectorised float64 NumPy Umeyama (the anchor of the issue);
* the memory roofline: one jitted pass reading every input byte once (``jnp.sum`` of each
  input array);

and prints ratios (speed-up vs IRLS / NumPy, time / roofline) plus the float32 accuracy
against a float64 reference.  Writes ``bench/results/bench_align-<timestamp>.json``.

Usage::

    .venv/bin/python bench/bench_align.py                 # O = 10, 30, 60
    .venv/bin/python bench/bench_align.py --overlaps 30 --repeats 20
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from swiftjax import align, camera, sim3  # noqa: E402
from swiftjax.align import chunk_pair  # noqa: E402

H, W = 154, 518


# --------------------------------------------------------------------------- inputs


def make_overlap(o: int, seed: int = 0, s_true: float = 1.004):
    """KITTI-like overlap: forward-moving cameras, depths 2-40 VGGT units, noise, 30 % outliers."""
    rng = np.random.default_rng(seed)
    K_ref = np.array([[360.0, 0, W / 2], [0, 360.0, H / 2], [0, 0, 1]])
    R_S = Rotation.from_rotvec(rng.normal(size=3) * 0.05).as_matrix()
    t_S = rng.normal(size=3) * 2.0 + np.array([0, 0, 20.0])
    Kp = np.repeat(K_ref[None], o, 0) * np.array([1 + 0.01 * rng.normal(size=(o, 1, 1))]).reshape(o, 1, 1)
    Kp[:, 2, 2] = 1
    Kc = np.repeat(K_ref[None], o, 0) * np.array([1 + 0.01 * rng.normal(size=(o, 1, 1))]).reshape(o, 1, 1)
    Kc[:, 2, 2] = 1
    Ep, Ec = [], []
    for f in range(o):
        Rp = Rotation.from_rotvec([0, 0.01 * f, 0]).as_matrix()
        cp = np.array([0.02 * f, 0.0, 0.8 * f]) + 30.0
        Ep.append(np.concatenate([Rp.T, (-Rp.T @ cp)[:, None]], 1))
        Rq = R_S.T @ Rp
        cq = R_S.T @ (cp - t_S) / s_true
        Ec.append(np.concatenate([Rq.T, (-Rq.T @ cq)[:, None]], 1))
    yy, xx = np.mgrid[0:H, 0:W]
    base = 2.0 + 38.0 * (yy[None] / H) ** 2 * (1 + 0.3 * np.sin(xx[None] / 40.0 + np.arange(o)[:, None, None]))
    rp = np.asarray(camera.focal_ratio(Kp, K_ref))
    rc = np.asarray(camera.focal_ratio(Kc, K_ref))
    # 0.3 % relative depth noise in each chunk: residuals of ~0.1 units at 20 units depth,
    # so VGGT-Long's Huber weights (delta = 0.1) actually reweight and IRLS iterates.
    Dp = base * (1 + 0.003 * rng.normal(size=(o, H, W))) / rp[:, None, None]
    Dc = (base / s_true) * (1 + 0.003 * rng.normal(size=(o, H, W))) / rc[:, None, None]
    bad = rng.random((o, H, W)) < 0.3
    Dc = np.where(bad, Dc + rng.uniform(1, 5, (o, H, W)), Dc)
    cp_ = 1 + rng.random((o, H, W)) * 4
    cc_ = 1 + rng.random((o, H, W)) * 4
    f32 = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
    prev = align.ChunkFrames(f32(Dp), f32(cp_), f32(Kp), f32(Ep))
    cur = align.ChunkFrames(f32(Dc), f32(cc_), f32(Kc), f32(Ec))
    return prev, cur, K_ref.astype(np.float32), (R_S, t_S, s_true)


def numpy_points_and_mask(prev, cur, K_ref, lam=0.2, ratio=0.5):
    """NumPy (float64) mask + unprojection as VGGT-Long-style code does it."""
    def pts(fr):
        r = 0.5 * (K_ref[0, 0] / fr.intrinsic[:, 0, 0] + K_ref[1, 1] / fr.intrinsic[:, 1, 1])
        d = fr.depth.astype(np.float64) * r[:, None, None]
        u, v = np.meshgrid(np.arange(W), np.arange(H))
        x = (u - K_ref[0, 2]) * d / K_ref[0, 0]
        y = (v - K_ref[1, 2]) * d / K_ref[1, 1]
        P = np.stack([x, y, d], -1)
        E = fr.extrinsic.astype(np.float64)
        Rt = np.swapaxes(E[:, :, :3], 1, 2)
        c = -np.einsum("fij,fj->fi", Rt, E[:, :, 3])
        return np.einsum("fij,fhwj->fhwi", Rt, P) + c[:, None, None], d

    Pp, dp = pts(prev)
    Pc, dc = pts(cur)
    mp = prev.conf.reshape(len(dp), -1).mean(1)[:, None, None]
    mc = cur.conf.reshape(len(dc), -1).mean(1)[:, None, None]
    m = (np.abs(dp - dc) < lam) & (prev.conf > ratio * mp) & (cur.conf > ratio * mc)
    return Pc[m], Pp[m]


def numpy_weighted_estimate_sim3(src, tgt, w):
    """VGGT-Long ``weighted_estimate_sim3`` (NumPy, as published)."""
    w = w / np.sum(w)
    mu_s = np.sum(w[:, None] * src, 0)
    mu_t = np.sum(w[:, None] * tgt, 0)
    sc, tc = src - mu_s, tgt - mu_t
    s = np.sqrt(np.sum(w * np.sum(tc**2, 1))) / np.sqrt(np.sum(w * np.sum(sc**2, 1)))
    Hm = (s * sc * np.sqrt(w)[:, None]).T @ (tc * np.sqrt(w)[:, None])
    U, _, Vt = np.linalg.svd(Hm)
    R = Vt.T @ U.T
    if np.linalg.det(R) < 0:
        Vt[-1, :] *= -1
        R = Vt.T @ U.T
    return s, R, mu_t - s * R @ mu_s


def numpy_irls(src, tgt, w0, delta=0.1, max_iters=5, tol=1e-9):
    """VGGT-Long ``robust_weighted_estimate_sim3`` (NumPy loop)."""
    s, R, t = numpy_weighted_estimate_sim3(src, tgt, w0)
    prev = np.inf
    for _ in range(max_iters):
        r = np.linalg.norm(tgt - (s * src @ R.T + t), axis=1)
        h = np.ones_like(r)
        big = r > delta
        h[big] = delta / r[big]
        cw = w0 * h
        cw /= np.sum(cw) + 1e-12
        s2, R2, t2 = numpy_weighted_estimate_sim3(src, tgt, cw)
        change = abs(s2 - s) + np.linalg.norm(t2 - t)
        ang = np.arccos(min(1.0, max(-1.0, (np.trace(R2 @ R.T) - 1) / 2)))
        err = np.sum(np.where(r <= delta, 0.5 * r**2, delta * (r - 0.5 * delta)) * w0)
        if (change < tol and ang < np.radians(0.1)) or abs(prev - err) < tol * prev:
            break
        s, R, t = s2, R2, t2
        prev = err
    return s, R, t


def numpy_umeyama(x, y):
    """Vectorised float64 NumPy Umeyama (unweighted), the issue's 55 ms anchor."""
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    C = yc.T @ xc / len(x)
    sx2 = (xc**2).sum() / len(x)
    U, D, Vt = np.linalg.svd(C)
    e = np.array([1, 1, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    R = (U * e) @ Vt
    s = (D * e).sum() / sx2
    return s, R, my - s * R @ mx


# --------------------------------------------------------------------------- timing


def best_of(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best


def timed_compile(jfn, *args) -> tuple[float, object]:
    t0 = time.perf_counter()
    compiled = jfn.lower(*args).compile()
    return time.perf_counter() - t0, compiled


def rot_err(S, R):
    Rg = np.asarray(sim3.to_rst(S)[0], np.float64)
    return float(np.linalg.norm(Rotation.from_matrix(R.T @ Rg).as_rotvec()))


def run_case(o: int, repeats: int, slow_repeats: int) -> dict:
    prev_np, cur_np, K_ref_np, (R_S, t_S, s_true) = make_overlap(o)
    prev = jax.device_put(align.ChunkFrames(*map(jnp.asarray, prev_np)))
    cur = jax.device_put(align.ChunkFrames(*map(jnp.asarray, cur_np)))
    K_ref = jax.device_put(jnp.asarray(K_ref_np))
    opts = tuple(chunk_pair._core_arguments(prev, cur, K_ref, align.AlignOptions())[3:])
    n = o * H * W
    res: dict = {"O": o, "H": H, "W": W, "point_pairs": n}

    # --- full chunk-pair alignment
    c_align, f_align = timed_compile(chunk_pair._align_core_jit, prev, cur, K_ref, *opts)
    S_al, info = f_align(prev, cur, K_ref, *opts)
    res["align_compile_s"] = c_align
    res["align_s"] = best_of(lambda: f_align(prev, cur, K_ref, *opts), repeats)
    res["align_points_used"] = int(info.num_points)
    res["align_rot_err_rad"] = rot_err(S_al, R_S)
    res["align_scale_rel_err"] = float(abs(float(sim3.scale(S_al)) / s_true - 1))
    src64, dst64 = numpy_points_and_mask(prev_np, cur_np, K_ref_np.astype(np.float64))
    s_r, R_r, _ = numpy_umeyama(src64, dst64)
    res["align_f32_rot_err_vs_f64_rad"] = rot_err(S_al, R_r)
    res["align_f32_scale_rel_err_vs_f64"] = float(abs(float(sim3.scale(S_al)) / s_r - 1))
    res["align_points_numpy"] = int(len(src64))

    roof_align = jax.jit(lambda p, c: sum(jnp.sum(a) for a in (*p, *c)))
    roof_align(prev, cur).block_until_ready()
    res["align_roofline_s"] = best_of(lambda: roof_align(prev, cur), repeats)
    res["align_input_bytes"] = int(sum(np.asarray(a).nbytes for a in (*prev_np, *cur_np)))

    # Jitted IRLS baseline, same mask/points (mask + unprojection + IRLS).
    def irls_pipeline(p, c, K):
        dp = camera.normalize_depth(p.depth, p.intrinsic, K)
        dc = camera.normalize_depth(c.depth, c.intrinsic, K)
        m = align.reliability_mask(dp, dc, p.conf, c.conf, 0.2, 0.5)
        Xp = camera.unproject(dp, K, camera.camera_to_world(p.extrinsic)).reshape(-1, 3)
        Xc = camera.unproject(dc, K, camera.camera_to_world(c.extrinsic)).reshape(-1, 3)
        return align.irls_sim3(Xc, Xp, m.reshape(-1))

    c_irls, f_irls = timed_compile(jax.jit(irls_pipeline), prev, cur, K_ref)
    S_ir, ir_info = f_irls(prev, cur, K_ref)
    res["irls_align_s"] = best_of(lambda: f_irls(prev, cur, K_ref), max(3, repeats // 3))
    res["irls_iterations"] = int(ir_info.iterations)

    def numpy_full():
        src, dst = numpy_points_and_mask(prev_np, cur_np, K_ref_np.astype(np.float64))
        return numpy_irls(src, dst, np.ones(len(src)))

    res["numpy_irls_align_s"] = best_of(numpy_full, slow_repeats)

    # --- Umeyama alone on the O H W point pairs with mask weights
    dp = camera.normalize_depth(prev.depth, prev.intrinsic, K_ref)
    dc = camera.normalize_depth(cur.depth, cur.intrinsic, K_ref)
    m = align.reliability_mask(dp, dc, prev.conf, cur.conf, 0.2, 0.5).reshape(-1).astype(jnp.float32)
    Xp = camera.unproject(dp, K_ref, camera.camera_to_world(prev.extrinsic)).reshape(-1, 3)
    Xc = camera.unproject(dc, K_ref, camera.camera_to_world(cur.extrinsic)).reshape(-1, 3)
    src, dst, w = (jax.device_put(jnp.asarray(np.asarray(a))) for a in (Xc, Xp, m))
    c_um, f_um = timed_compile(jax.jit(align.umeyama), src, dst, w)
    S_um, _ = f_um(src, dst, w)
    res["umeyama_compile_s"] = c_um
    res["umeyama_s"] = best_of(lambda: f_um(src, dst, w), repeats)
    roof_um = jax.jit(lambda a, b, c: jnp.sum(a) + jnp.sum(b) + jnp.sum(c))
    roof_um(src, dst, w).block_until_ready()
    res["umeyama_roofline_s"] = best_of(lambda: roof_um(src, dst, w), repeats)
    res["umeyama_input_bytes"] = int(3 * n * 4 * 2 + n * 4)
    _, f_ir = timed_compile(jax.jit(align.irls_sim3), src, dst, w)
    res["irls_umeyama_s"] = best_of(lambda: f_ir(src, dst, w), max(3, repeats // 3))

    s64, d64, w64 = (np.asarray(a, np.float64) for a in (src, dst, w))
    sel = w64 > 0
    s_sel, d_sel = s64[sel], d64[sel]
    res["numpy_irls_umeyama_s"] = best_of(lambda: numpy_irls(s_sel, d_sel, np.ones(len(s_sel))), slow_repeats)
    res["numpy_umeyama_s"] = best_of(lambda: numpy_umeyama(s_sel, d_sel), max(3, slow_repeats))
    # float32 accuracy vs the float64 reference on the same masked points
    s_r, R_r, t_r = numpy_umeyama(s_sel, d_sel)
    res["umeyama_f32_rot_err_vs_f64_rad"] = rot_err(S_um, R_r)
    res["umeyama_f32_scale_rel_err_vs_f64"] = float(abs(float(sim3.scale(S_um)) / s_r - 1))

    for k in ("align", "umeyama"):
        t = res[f"{k}_s"]
        res[f"{k}_speedup_vs_irls"] = res[f"irls_{k}_s"] / t
        res[f"{k}_speedup_vs_numpy_irls"] = res[f"numpy_irls_{k}_s"] / t
        res[f"{k}_over_roofline"] = t / res[f"{k}_roofline_s"]
    res["umeyama_speedup_vs_numpy_umeyama"] = res["numpy_umeyama_s"] / res["umeyama_s"]
    return res


def table(rows: list[dict]) -> str:
    out = [
        "| O | pairs | what | swiftjax f32 | compile | IRLS (jit) | NumPy IRLS | roofline | × vs IRLS | × vs NumPy | ÷ roofline |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        for k, label in (("align", "align_chunk_pair"), ("umeyama", "umeyama")):
            out.append(
                f"| {r['O']} | {r['point_pairs'] / 1e6:.2f} M | {label} | {1e3 * r[f'{k}_s']:.1f} ms | "
                f"{r[f'{k}_compile_s']:.2f} s | {1e3 * r[f'irls_{k}_s']:.0f} ms | "
                f"{1e3 * r[f'numpy_irls_{k}_s']:.0f} ms | {1e3 * r[f'{k}_roofline_s']:.1f} ms | "
                f"{r[f'{k}_speedup_vs_irls']:.1f} | {r[f'{k}_speedup_vs_numpy_irls']:.1f} | "
                f"{r[f'{k}_over_roofline']:.2f} |"
            )
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--overlaps", type=int, nargs="+", default=[10, 30, 60])
    ap.add_argument("--repeats", type=int, default=15, help="best-of repeats for jitted runs (>= 10)")
    ap.add_argument("--slow-repeats", type=int, default=3, help="best-of repeats for the NumPy baselines")
    ap.add_argument("--out", type=pathlib.Path, default=ROOT / "bench" / "results")
    args = ap.parse_args()

    rows = []
    for o in args.overlaps:
        r = run_case(o, args.repeats, args.slow_repeats)
        rows.append(r)
        print(f"O={o}: done", file=sys.stderr, flush=True)
    print(table(rows))
    for r in rows:
        print(
            f"O={r['O']}: numpy float64 vectorised Umeyama {1e3 * r['numpy_umeyama_s']:.1f} ms "
            f"(swiftjax umeyama x{r['umeyama_speedup_vs_numpy_umeyama']:.1f}); f32 vs f64: rot "
            f"{r['umeyama_f32_rot_err_vs_f64_rad']:.1e} rad, scale {r['umeyama_f32_scale_rel_err_vs_f64']:.1e}; "
            f"align f32 vs f64 NumPy on the same mask: rot {r['align_f32_rot_err_vs_f64_rad']:.1e} rad, scale "
            f"{r['align_f32_scale_rel_err_vs_f64']:.1e} ({r['align_points_used']} vs {r['align_points_numpy']} points); "
            f"IRLS iterations {r['irls_iterations']}"
        )
    if len(rows) > 1:
        per_pt = [r["align_s"] / r["point_pairs"] * 1e9 for r in rows]
        print("align_chunk_pair ns/point-pair by O:", ", ".join(f"{r['O']}: {p:.2f}" for r, p in zip(rows, per_pt)))
    meta = {
        "benchmark": "bench_align",
        "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "load_avg": os.getloadavg(),
        "repeats": args.repeats,
        "slow_repeats": args.slow_repeats,
        "rows": rows,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"bench_align-{time.strftime('%Y%m%d-%H%M%S')}.json"
    fd, tmp = tempfile.mkstemp(dir=args.out, suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        json.dump(meta, fh, indent=1)
    os.replace(tmp, path)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

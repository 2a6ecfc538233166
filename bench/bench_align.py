"""CPU microbenchmark: chunk alignment, swiftjax vs VGGT-Long's IRLS and Open3D, against the memory roofline.

For KITTI chunks at VGGT resolution (518 x 154) and overlaps O = 10, 30, 60 it times, in one
run and on the same inputs (already on the device, best of ``--repeats``):

* ``align_chunk_pair`` (mask + depth normalisation + unprojection + one Umeyama, float32,
  jitted) and ``umeyama`` alone on the ``O H W`` point pairs with mask weights, each with the
  fused FFI kernel (when built) and with the pure-JAX formulation (``SWIFTJAX_ALIGN_KERNEL=jax``);
* the IRLS baseline (``irls_sim3``, jitted, same mask / points) and a plain NumPy port of
  VGGT-Long's loop as a user would run it (float64, boolean indexing, 5 iterations);
* a vectorised float64 NumPy Umeyama and, when installed (``pip install .[bench]``),
  Open3D's ``TransformationEstimationPointToPoint(with_scaling=True)`` on the same reliable
  pairs (the correspondences are built before the clock starts);
* the memory roofline: one jitted pass reading every input byte once (``jnp.sum`` of each
  input array), and ``np.sum`` over the same arrays;
* at O = 30, every formulation of the pixel-moment pass tried (``formulations``), each
  against the roofline of its own four input images.

Wall and process CPU times are both recorded (CPU time is the work done, which a loaded
machine does not inflate); ratios are from the same run.  Writes
``bench/results/bench_align-<timestamp>.json`` with the load average before and after.

Usage::

    .venv/bin/python bench/bench_align.py                 # O = 10, 30, 60 + formulations
    .venv/bin/python bench/bench_align.py --overlaps 30 --repeats 20
"""

from __future__ import annotations

import argparse
import contextlib
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

import jax
import jax.numpy as jnp
from scipy.spatial.transform import Rotation

from swiftjax import align, camera, sim3
from swiftjax.align import _kernels, chunk_pair

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
    f32 = lambda a: np.ascontiguousarray(a, np.float32)
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
    """Vectorised float64 NumPy Umeyama (unweighted): the NumPy anchor of the tables."""
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


_CPU: dict[str, float] = {}  # process CPU time of the last best_of, by label


def best_of(fn, repeats: int, label: str | None = None) -> float:
    """Best wall time of ``repeats`` calls; the best process CPU time goes to ``_CPU[label]``."""
    best, best_cpu = np.inf, np.inf
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    if label is not None:
        _CPU[label] = best_cpu
    return best


@contextlib.contextmanager
def kernel_mode(mode: str):
    """``SWIFTJAX_ALIGN_KERNEL`` set to ``mode`` ("auto" or "jax") while tracing inside."""
    old = os.environ.get("SWIFTJAX_ALIGN_KERNEL")
    os.environ["SWIFTJAX_ALIGN_KERNEL"] = mode
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("SWIFTJAX_ALIGN_KERNEL", None)
        else:
            os.environ["SWIFTJAX_ALIGN_KERNEL"] = old


def _open3d_version() -> str | None:
    try:
        import open3d as o3d
    except ImportError:
        return None
    return o3d.__version__


def open3d_estimate():
    """Open3D's point-to-point Sim(3) estimate ``f(src, dst) -> 4x4`` on given pairs, or None."""
    try:
        import open3d as o3d
    except ImportError:
        return None
    est = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=True)

    def prepare(src, dst):
        p = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(src, np.float64)))
        q = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(dst, np.float64)))
        idx = np.arange(len(src), dtype=np.int32)
        corr = o3d.utility.Vector2iVector(np.stack([idx, idx], 1))
        return lambda: est.compute_transformation(p, q, corr)

    return prepare


def library_jit(fun):
    """``jax.jit(fun)`` with the compiler options the library gives it on the current path
    (``align._kernels.compiler_options``, read under ``kernel_mode``), as a fresh jit so that
    ``.lower().compile()`` can be timed."""
    return jax.jit(lambda *a: fun(*a), compiler_options=_kernels.compiler_options(jnp.float32))


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

    # --- full chunk-pair alignment, fused kernel ("auto": used when built) and pure JAX
    res["kernel_built"] = _kernels._ffi_kernels is not None
    for mode, key in (("auto", "align"), ("jax", "align_jax")):
        with kernel_mode(mode):
            c_align, f_align = timed_compile(library_jit(chunk_pair._align_core), prev, cur, K_ref, *opts)
        S_m, info = f_align(prev, cur, K_ref, *opts)
        res[f"{key}_compile_s"] = c_align
        res[f"{key}_s"] = best_of(lambda: f_align(prev, cur, K_ref, *opts), repeats, key)
        res[f"{key}_cpu_s"] = _CPU[key]
        if key == "align":
            S_al = S_m
            res["align_points_used"] = int(info.num_points)
    res["align_kernel"] = "ffi" if _kernels._ffi_kernels is not None else "jax"
    res["align_rot_err_rad"] = rot_err(S_al, R_S)
    res["align_scale_rel_err"] = float(abs(float(sim3.scale(S_al)) / s_true - 1))
    src64, dst64 = numpy_points_and_mask(prev_np, cur_np, K_ref_np.astype(np.float64))
    s_r, R_r, _ = numpy_umeyama(src64, dst64)
    res["align_f32_rot_err_vs_f64_rad"] = rot_err(S_al, R_r)
    res["align_f32_scale_rel_err_vs_f64"] = float(abs(float(sim3.scale(S_al)) / s_r - 1))
    res["align_points_numpy"] = int(len(src64))

    roof_align = jax.jit(lambda p, c: sum(jnp.sum(a) for a in (*p, *c)))
    roof_align(prev, cur).block_until_ready()
    res["align_roofline_s"] = best_of(
        lambda: roof_align(prev, cur), 3 * repeats, "roof"
    )  # the roofline is the fastest read: more tries
    res["align_roofline_cpu_s"] = _CPU["roof"]
    arrays_np = [np.asarray(a) for a in (*prev_np, *cur_np)]
    res["align_roofline_numpy_s"] = best_of(lambda: [np.sum(a) for a in arrays_np], repeats)
    res["align_input_bytes"] = int(sum(a.nbytes for a in arrays_np))
    prepare = open3d_estimate()
    if prepare is not None:  # Open3D on the reliable pairs the solve uses (fewer than O H W)
        res["open3d_align_s"] = best_of(prepare(src64, dst64), max(3, slow_repeats))

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
    for mode, key in (("auto", "umeyama"), ("jax", "umeyama_jax")):
        with kernel_mode(mode):
            c_um, f_um = timed_compile(library_jit(align.umeyama.__wrapped__), src, dst, w)
        S_m, _ = f_um(src, dst, w)
        if key == "umeyama":
            S_um = S_m
        res[f"{key}_compile_s"] = c_um
        res[f"{key}_s"] = best_of(lambda: f_um(src, dst, w), repeats, key)
        res[f"{key}_cpu_s"] = _CPU[key]
    roof_um = jax.jit(lambda a, b, c: jnp.sum(a) + jnp.sum(b) + jnp.sum(c))
    roof_um(src, dst, w).block_until_ready()
    res["umeyama_roofline_s"] = best_of(lambda: roof_um(src, dst, w), 3 * repeats, "roof_um")
    res["umeyama_roofline_cpu_s"] = _CPU["roof_um"]
    um_np = [np.asarray(a) for a in (src, dst, w)]
    res["umeyama_roofline_numpy_s"] = best_of(lambda: [np.sum(a) for a in um_np], repeats)
    res["umeyama_input_bytes"] = int(3 * n * 4 * 2 + n * 4)
    _, f_ir = timed_compile(jax.jit(align.irls_sim3), src, dst, w)
    res["irls_umeyama_s"] = best_of(lambda: f_ir(src, dst, w), max(3, repeats // 3))

    s64, d64, w64 = (np.asarray(a, np.float64) for a in (src, dst, w))
    sel = w64 > 0
    s_sel, d_sel = s64[sel], d64[sel]
    res["numpy_irls_umeyama_s"] = best_of(lambda: numpy_irls(s_sel, d_sel, np.ones(len(s_sel))), slow_repeats)
    res["numpy_umeyama_s"] = best_of(lambda: numpy_umeyama(s_sel, d_sel), max(3, slow_repeats))
    if prepare is not None:
        res["open3d_umeyama_s"] = best_of(prepare(s_sel, d_sel), max(3, slow_repeats))
    # float32 accuracy vs the float64 reference on the same masked points
    s_r, R_r, t_r = numpy_umeyama(s_sel, d_sel)
    res["umeyama_f32_rot_err_vs_f64_rad"] = rot_err(S_um, R_r)
    res["umeyama_f32_scale_rel_err_vs_f64"] = float(abs(float(sim3.scale(S_um)) / s_r - 1))

    for k in ("align", "umeyama"):
        t = res[f"{k}_s"]
        res[f"{k}_speedup_vs_irls"] = res[f"irls_{k}_s"] / t
        res[f"{k}_speedup_vs_numpy_irls"] = res[f"numpy_irls_{k}_s"] / t
        res[f"{k}_over_roofline"] = t / res[f"{k}_roofline_s"]
        res[f"{k}_cpu_over_roofline_cpu"] = res[f"{k}_cpu_s"] / res[f"{k}_roofline_cpu_s"]
        res[f"{k}_jax_over_roofline"] = res[f"{k}_jax_s"] / res[f"{k}_roofline_s"]
        res[f"{k}_jax_cpu_over_roofline_cpu"] = res[f"{k}_jax_cpu_s"] / res[f"{k}_roofline_cpu_s"]
        if f"open3d_{k}_s" in res:
            res[f"{k}_speedup_vs_open3d"] = res[f"open3d_{k}_s"] / t
    res["umeyama_speedup_vs_numpy_umeyama"] = res["numpy_umeyama_s"] / res["umeyama_s"]
    return res


# ------------------------------------------------------------- pixel-moment formulations


def formulations(o: int, repeats: int) -> list[dict]:
    """The pixel-moment pass of ``align_chunk_pair`` (mask + 18 weighted row sums + the
    ``v~`` contraction, ``S [O, 6, 3, 3]``) in every formulation tried, on the same four
    ``[O, H, W]`` float32 images, against one jitted read of those images."""
    from swiftjax._reductions import variadic_sum

    prev_np, cur_np, _, _ = make_overlap(o)
    dp, cp, dc, cc = (jnp.asarray(a) for a in (prev_np.depth, prev_np.conf, cur_np.depth, cur_np.conf))
    ut = jnp.linspace(-1, 1, W, dtype=jnp.float32)
    vt = jnp.linspace(-1, 1, H, dtype=jnp.float32)
    U = jnp.stack([jnp.ones_like(ut), ut, ut * ut], -1)  # [W, 3]
    V = jnp.stack([jnp.ones_like(vt), vt, vt * vt], -1)  # [H, 3]
    thr_p, thr_c = 0.5 * jnp.mean(cp, (1, 2)), 0.5 * jnp.mean(cc, (1, 2))
    e_p, e_c = jnp.mean(dp, (1, 2)), jnp.mean(dc, (1, 2))
    lam = 0.2

    def images(dp, dc, cp, cc, tp, tc, ep, ec):
        x = (Ellipsis, None, None)
        ok = (
            jnp.isfinite(dp)
            & jnp.isfinite(dc)
            & jnp.isfinite(cp)
            & jnp.isfinite(cc)
            & (jnp.abs(dp - dc) < lam)
            & (cp > tp[x])
            & (cc > tc[x])
        )
        a = jnp.where(ok, dp - ep[x], 0)
        b = jnp.where(ok, dc - ec[x], 0)
        m = ok.astype(dp.dtype)
        return m, a, b, a * b, a * a, b * b

    args = (dp, dc, cp, cc, thr_p, thr_c, e_p, e_c)

    def variadic(*a):  # the pure-JAX path: 18 row sums in one variadic reduce
        ims = images(*a)
        u1 = jnp.broadcast_to(ut, ims[0].shape)
        rows = variadic_sum(tuple(t for im in ims for t in (im, im * u1, im * u1 * u1)), -1)
        return jnp.einsum("fhik,hl->fikl", jnp.stack(rows, -1).reshape(o, H, 6, 3), V)

    def per_frame(body):
        return lambda *a: jax.lax.map(lambda x: body(*x), a)

    def variadic_frame(*a):
        ims = images(*a)
        u1 = jnp.broadcast_to(ut, ims[0].shape)
        rows = variadic_sum(tuple(t for im in ims for t in (im, im * u1, im * u1 * u1)), -1)
        return jnp.einsum("hik,hl->ikl", jnp.stack(rows, -1).reshape(H, 6, 3), V)

    def single_sums(*a):  # 18 single-output row sums (each its own vectorised reduce)
        ims = images(*a)
        rows = [jnp.sum(t, -1) for im in ims for t in (im, im * ut, im * ut * ut)]
        return jnp.einsum("fhik,hl->fikl", jnp.stack(rows, -1).reshape(o, H, 6, 3), V)

    def gemm_stacked(*a):  # images materialised [O, 6, H, W] x [W, 3]
        R = jnp.einsum("fihw,wk->fihk", jnp.stack(images(*a), 1), U)
        return jnp.einsum("fihk,hl->fikl", R, V)

    def gemm_basis(*a):  # [O, 6, HW] x [HW, 9] (one well-shaped GEMM per overlap)
        B = (V[:, None, None, :] * U[None, :, :, None]).reshape(H * W, 9)
        return jnp.einsum("fip,pq->fiq", jnp.stack(images(*a), 1).reshape(o, 6, H * W), B).reshape(o, 6, 3, 3)

    def gemm_image_frame(*a):  # per frame, per image [H, W] x [W, 3] then [3, H] x [H, 3]
        return jnp.stack([(im @ U).T @ V for im in images(*a)])

    def columns(*a):  # single-output reductions over the major axis (H) first
        cols = [jnp.sum(im * V[:, l][None, :, None], 1) for im in images(*a) for l in range(3)]
        return jnp.einsum("filw,wk->fikl", jnp.stack(cols, 1).reshape(o, 6, 3, W), U)

    cands = {
        "variadic reduce over rows (pure-JAX path)": variadic,
        "variadic reduce, frame by frame (lax.map)": per_frame(variadic_frame),
        "18 single-output sums": single_sums,
        "GEMM, stacked images [O,6,H,W] x [W,3]": gemm_stacked,
        "GEMM, [O,6,HW] x [HW,9] basis": gemm_basis,
        "GEMM per frame and image [H,W] x [W,3]": per_frame(gemm_image_frame),
        "column sums over H, then [W,3]": columns,
    }
    if _kernels._ffi_kernels is not None:
        ones = jnp.ones((o,), jnp.float32)
        params = jnp.stack(
            [ones, ones, e_p, e_c, jnp.full((o,), 0.5, jnp.float32), jnp.full((o,), lam, jnp.float32)], -1
        )
        cands["fused FFI kernel (jax.ffi, C++)"] = lambda *a: _kernels.pixel_moments(
            a[0], a[1], a[2], a[3], params, ut, vt, chunk_pair._masked_pixel_moments
        )[0]
    roof = jax.jit(lambda *a: sum(jnp.sum(x) for x in a[:4]))
    roof(*args).block_until_ready()
    t_roof = best_of(lambda: roof(*args), 3 * repeats, "roof")
    c_roof = _CPU["roof"]
    ref = np.asarray(jax.jit(variadic)(*args), np.float64).reshape(o, 6, 3, 3)
    out = []
    for name, fn in cands.items():
        f = jax.jit(fn)
        got = np.asarray(f(*args), np.float64).reshape(o, 6, 3, 3)
        t = best_of(lambda: f(*args), max(3, repeats // 3), name)
        err = float(np.max(np.abs(got - ref) / (np.abs(ref) + 1e-3 * np.abs(ref).max())))
        out.append(
            {
                "formulation": name,
                "s": t,
                "cpu_s": _CPU[name],
                "over_roofline": t / t_roof,
                "cpu_over_roofline_cpu": _CPU[name] / c_roof,
                "max_rel_diff_vs_variadic": err,
                "roofline_s": t_roof,
                "roofline_cpu_s": c_roof,
            }
        )
        print(
            f"  {name}: {1e3 * t:.1f} ms (cpu {1e3 * _CPU[name]:.1f} ms), {t / t_roof:.1f}x roofline",
            file=sys.stderr,
            flush=True,
        )
    return out


def table(rows: list[dict]) -> str:
    out = [
        "| O | pairs | what | swiftjax f32 | ÷ roofline (wall / cpu) | pure-JAX path ÷ roofline (wall / cpu) | "
        "× vs Open3D | × vs IRLS (jit) | × vs NumPy IRLS | roofline |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        for k, label in (("align", "align_chunk_pair"), ("umeyama", "umeyama")):
            o3d = f"{r[f'{k}_speedup_vs_open3d']:.1f}" if f"{k}_speedup_vs_open3d" in r else "n/a"
            out.append(
                f"| {r['O']} | {r['point_pairs'] / 1e6:.2f} M | {label} | {1e3 * r[f'{k}_s']:.1f} ms | "
                f"{r[f'{k}_over_roofline']:.2f} / {r[f'{k}_cpu_over_roofline_cpu']:.2f} | "
                f"{r[f'{k}_jax_over_roofline']:.1f} / {r[f'{k}_jax_cpu_over_roofline_cpu']:.1f} | {o3d} | "
                f"{r[f'{k}_speedup_vs_irls']:.1f} | {r[f'{k}_speedup_vs_numpy_irls']:.1f} | "
                f"{1e3 * r[f'{k}_roofline_s']:.1f} ms |"
            )
    return "\n".join(out)


def formulation_table(rows: list[dict]) -> str:
    out = [
        "| pixel-moment formulation (O = 30) | time | ÷ roofline (wall / cpu) | max rel. diff |",
        "|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r['formulation']} | {1e3 * r['s']:.1f} ms | {r['over_roofline']:.1f} / "
            f"{r['cpu_over_roofline_cpu']:.1f} | {r['max_rel_diff_vs_variadic']:.0e} |"
        )
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--overlaps", type=int, nargs="+", default=[10, 30, 60])
    ap.add_argument("--repeats", type=int, default=15, help="best-of repeats for jitted runs (>= 10)")
    ap.add_argument("--slow-repeats", type=int, default=3, help="best-of repeats for the NumPy baselines")
    ap.add_argument(
        "--formulations-overlap", type=int, default=30, help="O of the pixel-moment formulation comparison (0: skip it)"
    )
    ap.add_argument("--out", type=pathlib.Path, default=ROOT / "bench" / "results")
    args = ap.parse_args()

    load_before = os.getloadavg()
    rows = []
    for o in args.overlaps:
        r = run_case(o, args.repeats, args.slow_repeats)
        rows.append(r)
        print(f"O={o}: done", file=sys.stderr, flush=True)
    forms = [] if args.formulations_overlap == 0 else formulations(args.formulations_overlap, args.repeats)
    print(table(rows))
    if forms:
        print()
        print(formulation_table(forms))
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
        "load_avg_before": load_before,
        "kernel_built": _kernels._ffi_kernels is not None,
        "open3d": _open3d_version(),
        "repeats": args.repeats,
        "slow_repeats": args.slow_repeats,
        "rows": rows,
        "formulations": forms,
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

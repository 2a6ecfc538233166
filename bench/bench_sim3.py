"""Sim(3) throughput: jitted swiftjax vs a plain NumPy implementation of the same formulas.

Batched exp, log, compose and act on 1e6 float32 elements (act also on 1e7 points under one
transform), CPU.  Compile time is reported separately from run time (best of N, inputs
already on the device); wall time and process CPU time (all threads) are both recorded, with
the load average before and after, and every ratio is against NumPy in the same run.
Target: >= 5x NumPy for exp and log on a quiet machine (load average < 1).

A second table times the layouts tried for exp and log (the same component formulas,
``sim3._exp_c`` / ``sim3._log_c``, arranged differently; docs/performance/sim3.md).

    python bench/bench_sim3.py [--n 1048576] [--points 10000000] [--repeat 10] [--no-layouts]
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from common import best_of, compile_time, markdown_table, write_results

from swiftjax import sim3, so3


def cpu_best_of(fn, repeat: int) -> float:
    """Best process CPU time (all threads) of ``fn()`` over ``repeat`` calls after one warm-up."""
    jax.block_until_ready(fn())
    best = float("inf")
    for _ in range(repeat):
        t0 = time.process_time()
        jax.block_until_ready(fn())
        best = min(best, time.process_time() - t0)
    return best


# ------------------------------------------------------------- layouts tried for exp / log


def layout_flat(fn):
    """Components ``[N]``; XLA fuses the formulas into the final ``[N, k]`` interleaving copy."""
    return jax.jit(lambda x: so3.join(fn(so3.split(x))))


def layout_soa(fn):
    """``[k, N]`` in, ``[m, N]`` out: no interleave at all (the caller holds structure of arrays)."""
    return jax.jit(lambda x: jnp.stack(fn(tuple(x)), 0))


def layout_transpose_once(fn):
    """``[N, k]`` -> ``[k, N]`` -> kernel -> ``[m, N]`` -> ``[N, m]`` as three programs (interleave once)."""
    tin, kernel, tout = jax.jit(lambda x: x.T), layout_soa(fn), jax.jit(lambda y: y.T)
    return lambda x: tout(kernel(tin(x)))


def layout_blocked(fn, block):
    """Components ``[N / block, block]``: the layout change stays inside one block."""

    def f(x):
        n, k = x.shape
        out = jnp.stack(fn(tuple(jnp.moveaxis(x.reshape(n // block, block, k), -1, 0))), -1)
        return out.reshape(n, -1)

    return jax.jit(f)


def layout_lax_map(fn, block):
    """``lax.map`` over ``block``-element slices, each transposed to ``[k, block]`` and back."""

    def f(x):
        n, k = x.shape
        return jax.lax.map(lambda b: jnp.stack(fn(tuple(b.T)), -1), x.reshape(n // block, block, k)).reshape(n, -1)

    return jax.jit(f)


# ----------------------------------------------------------------- NumPy baseline (same maths)


def _np_rotate(q, x):
    v, w = q[..., :3], q[..., 3:4]
    uv = np.cross(v, x)
    return x + 2.0 * (w * uv + np.cross(v, uv))


def _np_qmul(a, b):
    av, aw, bv, bw = a[..., :3], a[..., 3:4], b[..., :3], b[..., 3:4]
    return np.concatenate([aw * bv + bw * av + np.cross(av, bv), aw * bw - np.sum(av * bv, -1, keepdims=True)], -1)


def _np_wcoef(theta_sq, sigma):
    """General-branch A, B, C (the benchmark inputs avoid the small-angle branches)."""
    theta = np.sqrt(theta_sq)
    c = np.expm1(sigma) / sigma
    em_re = np.expm1(sigma) * np.cos(theta) - 2.0 * np.sin(0.5 * theta) ** 2
    em_im = np.exp(sigma) * np.sin(theta)
    cc = sigma**2 + theta_sq
    a = (em_im * sigma - em_re * theta) / (theta * cc)
    b = (c - (em_re * sigma + em_im * theta) / cc) / theta_sq
    return a, b, c


def _np_poly(x, y, z, w, v):
    wv = np.cross(w, v)
    return x[..., None] * v + y[..., None] * wv + z[..., None] * np.cross(w, wv)


def np_exp(xi):
    rho, w, sigma = xi[..., :3], xi[..., 3:6], xi[..., 6]
    tsq = np.sum(w * w, -1)
    a, b, c = _np_wcoef(tsq, sigma)
    theta = np.sqrt(tsq)
    q = np.concatenate([(np.sin(0.5 * theta) / theta)[..., None] * w, np.cos(0.5 * theta)[..., None]], -1)
    return np.concatenate([_np_poly(c, a, b, w, rho), q, np.exp(sigma)[..., None]], -1)


def np_log(s):
    q = np.where(s[..., 6:7] < 0, -s[..., 3:7], s[..., 3:7])
    n = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    w = (2.0 * np.arctan2(n, q[..., 3:4]) / n) * q[..., :3]
    sigma = np.log(s[..., 7])
    tsq = np.sum(w * w, -1)
    a, b, c = _np_wcoef(tsq, sigma)
    d = c - tsq * b
    det = d * d + tsq * a * a
    rho = _np_poly(1.0 / c, -a / det, (a * a - b * d) / (c * det), w, s[..., :3])
    return np.concatenate([rho, w, sigma[..., None]], -1)


def np_compose(a, b):
    t = a[..., 7:8] * _np_rotate(a[..., 3:7], b[..., :3]) + a[..., :3]
    return np.concatenate([t, _np_qmul(a[..., 3:7], b[..., 3:7]), a[..., 7:8] * b[..., 7:8]], -1)


def np_act(s, x):
    return s[..., 7:8] * _np_rotate(s[..., 3:7], x) + s[..., :3]


# --------------------------------------------------------------------------------- main


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1 << 20)
    parser.add_argument("--points", type=int, default=10_000_000)
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--no-layouts", action="store_true", help="skip the table of layouts tried")
    args = parser.parse_args()
    load_before = os.getloadavg()

    rng = np.random.default_rng(0)
    xi = rng.uniform(-1.0, 1.0, (args.n, 7)).astype(np.float32)
    xi[:, 6] += np.where(xi[:, 6] >= 0, 0.05, -0.05)  # stay off the small-sigma branch in NumPy
    s_np = np_exp(xi.astype(np.float64)).astype(np.float32)
    s2_np = np_exp(xi[::-1].astype(np.float64)).astype(np.float32)
    pts_n = rng.uniform(-100, 100, (args.n, 3)).astype(np.float32)
    pts_big = rng.uniform(-100, 100, (args.points, 3)).astype(np.float32)
    one = s_np[:1]

    dev = jax.device_put
    xi_d, s_d, s2_d, pn_d, pb_d, one_d = map(dev, (xi, s_np, s2_np, pts_n, pts_big, one))
    cases = [
        ("exp", jax.jit(sim3.exp), (xi_d,), lambda: np_exp(xi), args.n),
        ("log", jax.jit(sim3.log), (s_d,), lambda: np_log(s_np), args.n),
        ("compose", jax.jit(sim3.compose), (s_d, s2_d), lambda: np_compose(s_np, s2_np), args.n),
        ("act (one S per point)", jax.jit(sim3.act), (s_d, pn_d), lambda: np_act(s_np, pts_n), args.n),
        ("act (one S, 1e7 points)", jax.jit(sim3.act), (one_d, pb_d), lambda: np_act(one, pts_big), args.points),
    ]

    # Sanity: the two implementations agree (float32 tolerance).
    np.testing.assert_allclose(np.asarray(sim3.exp(xi_d[:1000])), np_exp(xi[:1000]), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(sim3.log(s_d[:1000])), np_log(s_np[:1000]), rtol=1e-3, atol=1e-3)

    rows, records = [], []
    for name, jitted, jargs, np_fn, count in cases:
        compiled, t_compile = compile_time(jitted, *jargs)
        t_jax = best_of(lambda: compiled(*jargs), args.repeat)
        t_np = best_of(np_fn, max(3, args.repeat // 3))
        c_jax = cpu_best_of(lambda: compiled(*jargs), args.repeat)
        c_np = cpu_best_of(np_fn, max(3, args.repeat // 3))
        rows.append([name, count, t_compile, t_jax * 1e3, t_np * 1e3, count / t_jax / 1e6, t_np / t_jax, c_np / c_jax])
        records.append(
            dict(
                op=name,
                count=count,
                compile_s=t_compile,
                jax_s=t_jax,
                numpy_s=t_np,
                speedup=t_np / t_jax,
                jax_cpu_s=c_jax,
                numpy_cpu_s=c_np,
                cpu_speedup=c_np / c_jax,
                load=os.getloadavg(),
            )
        )
    headers = [
        "op (float32)",
        "elements",
        "compile s",
        "swiftjax ms",
        "NumPy ms",
        "M elem/s",
        "× NumPy",
        "× NumPy (CPU time)",
    ]
    print(markdown_table(headers, rows))

    layouts = []
    if not args.no_layouts:
        if args.n % 8192:
            parser.error("the layout table needs --n a multiple of 8192 (or pass --no-layouts)")
        xi_t, s_t = jax.device_put(np.ascontiguousarray(xi.T)), jax.device_put(np.ascontiguousarray(s_np.T))
        lrows = []
        for op, fn, x_d, x_t, np_fn in [
            ("exp", sim3._exp_c, xi_d, xi_t, lambda: np_exp(xi)),
            ("log", sim3._log_c, s_d, s_t, lambda: np_log(s_np)),
        ]:
            t_np = best_of(np_fn, max(3, args.repeat // 3))
            c_np = cpu_best_of(np_fn, max(3, args.repeat // 3))
            variants = [
                ("flat components, interleaving output fusion", layout_flat(fn), x_d),
                ("[k, N] in, [m, N] out (no interleave)", layout_soa(fn), x_t),
                ("transpose in, kernel, transpose out (3 programs)", layout_transpose_once(fn), x_d),
                *[(f"blocked [N/{b}, {b}] components", layout_blocked(fn, b), x_d) for b in (256, 1024, 4096)],
                ("lax.map over 8192-element blocks", layout_lax_map(fn, 8192), x_d),
                (f"library sim3.{op}", jax.jit(getattr(sim3, op)), x_d),
            ]
            for label, f, arg in variants:
                t = best_of(lambda: f(arg), args.repeat)
                c = cpu_best_of(lambda: f(arg), args.repeat)
                lrows.append([op, label, t * 1e3, t_np / t, c * 1e3, c_np / c])
                layouts.append(
                    dict(
                        op=op,
                        layout=label,
                        jax_s=t,
                        numpy_s=t_np,
                        speedup=t_np / t,
                        jax_cpu_s=c,
                        numpy_cpu_s=c_np,
                        cpu_speedup=c_np / c,
                        load=os.getloadavg(),
                    )
                )
        print()
        print(markdown_table(["op", "layout", "wall ms", "× NumPy", "CPU ms", "× NumPy (CPU)"], lrows))

    path = write_results(
        "sim3",
        {
            "n": args.n,
            "points": args.points,
            "results": records,
            "layouts": layouts,
            "load_before": load_before,
            "load_after": os.getloadavg(),
        },
    )
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()

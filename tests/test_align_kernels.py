"""The fused FFI kernels of swiftjax.align against the pure-JAX formulation (float32 tolerance)."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_align import make_pair

from swiftjax import align
from swiftjax.align import _kernels, chunk_pair

if _kernels._ffi_kernels is None and os.environ.get("CI"):
    raise RuntimeError("CI must build the fused align kernels (pip install -e . with a C++17 compiler)")
pytestmark = pytest.mark.skipif(
    _kernels._ffi_kernels is None,
    reason="the optional compiled extension swiftjax.align._ffi_kernels is not built "
    "(pip install -e . with a C++17 compiler builds it)",
)


ISAS = _kernels._ffi_kernels.isas() if _kernels._ffi_kernels is not None else []


@pytest.fixture(params=ISAS)
def isa(request):
    """Each instruction set this CPU runs the kernels with (AVX-512 / AVX2 / baseline loops)."""
    kernels = _kernels._ffi_kernels
    before = kernels.isa()
    kernels.set_isa(request.param)
    yield request.param
    kernels.set_isa(before)


def _both(monkeypatch, fn, *args):
    """``fn(*args)`` traced once with the fused kernel and once with pure JAX (fresh jits)."""
    out = {}
    for mode in ("auto", "jax"):
        monkeypatch.setenv("SWIFTJAX_ALIGN_KERNEL", mode)
        out[mode] = jax.jit(lambda *a: fn(*a))(*args)
    return out["auto"], out["jax"]


def _core(prev, cur, K_ref, keep=None, **kw):
    opts = align.AlignOptions().replace(**kw)
    args = chunk_pair._core_arguments(prev, cur, K_ref, opts)
    return lambda *a: chunk_pair._align_core(*a, keep), args


def _close(S_k, S_j, atol=2e-5):
    np.testing.assert_allclose(np.asarray(S_k), np.asarray(S_j), atol=atol)


def test_available_only_for_float32(monkeypatch):
    monkeypatch.delenv("SWIFTJAX_ALIGN_KERNEL", raising=False)
    assert _kernels.available(jnp.float32) and not _kernels.available(jnp.float64)
    monkeypatch.setenv("SWIFTJAX_ALIGN_KERNEL", "jax")
    assert not _kernels.available(jnp.float32)


def test_chunk_pair_kernel_matches_jax(monkeypatch, isa):
    prev, cur, K_ref, _ = make_pair(seed=2, dtype=np.float32)
    rng = np.random.default_rng(0)
    dp, cc, cp = prev.depth.copy(), cur.conf.copy(), prev.conf.copy()
    dp[rng.random(dp.shape) < 0.05] = np.nan
    dp[rng.random(dp.shape) < 0.02] = np.inf
    cc[rng.random(cc.shape) < 0.02] = np.inf  # an infinite confidence is never reliable
    cc[2] = np.nan  # no finite confidence: the frame's mean is NaN, nothing of it is reliable
    cp[3, ::2] = np.nan  # the mean over the finite half (the kernel's second, masked pass)
    ep = prev.extrinsic.copy()
    ep[1, 0, 3] = np.nan  # a dropped frame
    prev = prev._replace(depth=dp, extrinsic=ep, conf=cp)
    cur = cur._replace(conf=cc)
    keep = rng.random(prev.depth.shape) > 0.1
    for mask in (None, jnp.asarray(keep)):
        fn, args = _core(prev, cur, K_ref, mask, min_points=100)
        (S_k, i_k), (S_j, i_j) = _both(monkeypatch, fn, *args)
        assert int(i_k.num_points) == int(i_j.num_points) > 100
        assert bool(i_k.valid) and bool(i_j.valid)
        _close(S_k, S_j)
        np.testing.assert_allclose(np.asarray(i_k.src_mean), np.asarray(i_j.src_mean), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(np.asarray(i_k.src_covariance), np.asarray(i_j.src_covariance), rtol=1e-4, atol=1e-5)


def test_gauge_jump_3p5x_kernel_and_jax(monkeypatch):
    """Chunk t+1 in a gauge 3.5x smaller (depths and camera centres / 3.5, synthetic KITTI 08's
    first pair): the authors' eq. 2 keeps no point and falls back to the poses; with the robust
    ratio both paths keep every confident pixel and recover S (scale 3.5) to float32 rounding."""
    prev, cur, K_ref, (R, t, s) = make_pair(seed=13, s=3.5, outliers=0.0, dtype=np.float32)
    dc = np.asarray(cur.depth)
    fn, args = _core(prev, cur, K_ref, min_points=100, overlap_scale="none")
    (_, i_k), (_, i_j) = _both(monkeypatch, fn, *args)
    assert int(i_k.num_points) == int(i_j.num_points) == 0 and bool(i_k.pose_fallback)
    fn, args = _core(prev, cur, K_ref, min_points=100)  # "auto": the authors' keep 0 < min_points, redone
    (S_k, i_k), (S_j, i_j) = _both(monkeypatch, fn, *args)
    conf_ok = (
        (prev.conf > 0.5 * prev.conf.mean((1, 2), keepdims=True))
        & (cur.conf > 0.5 * cur.conf.mean((1, 2), keepdims=True))
        & np.isfinite(dc)
    )
    assert int(i_k.num_points) == int(i_j.num_points) == int(conf_ok.sum())  # every confident pixel
    assert float(i_k.scale_ratio) == pytest.approx(3.5, rel=1e-5)
    _close(S_k, S_j)
    from swiftjax import sim3

    Rg, tg, sg = (np.asarray(a, np.float64) for a in sim3.to_rst(S_k))
    np.testing.assert_allclose(Rg, R, atol=1e-4)
    np.testing.assert_allclose(tg, t, atol=1e-3 * max(1, np.abs(t).max()))
    assert float(sg) == pytest.approx(s, rel=1e-4)


def test_chunk_pair_kernel_fallback_threshold_and_batch(monkeypatch):
    prev, cur, K_ref, _ = make_pair(seed=3, s=1.0, dtype=np.float32)
    r = 0.5 * (K_ref[0, 0] / cur.intrinsic[:, 0, 0] + K_ref[1, 1] / cur.intrinsic[:, 1, 1])
    cur = cur._replace(
        depth=cur.depth + 0.22 / r[:, None, None]
    )  # only the fallback threshold passes (eq. 2 as written)
    fn, args = _core(prev, cur, K_ref, min_points=100, overlap_scale="none")
    (S_k, i_k), (S_j, i_j) = _both(monkeypatch, fn, *args)
    assert bool(i_k.used_fallback_threshold) and int(i_k.num_points) == int(i_j.num_points)
    _close(S_k, S_j)
    p2, c2, _, _ = make_pair(seed=4, dtype=np.float32)
    pb = align.ChunkFrames(*(np.stack([a, b]) for a, b in zip(prev, p2)))
    cb = align.ChunkFrames(*(np.stack([a, b]) for a, b in zip(cur, c2)))
    monkeypatch.delenv("SWIFTJAX_ALIGN_KERNEL", raising=False)
    Sb, ib = align.align_chunk_pairs(
        pb, cb, K_ref, options=align.AlignOptions(min_points=100, overlap_scale="none")
    )  # vmap over the FFI call
    _close(Sb[0], S_j)
    assert int(ib.num_points[0]) == int(i_j.num_points)


def test_umeyama_kernel_matches_jax_and_float64(monkeypatch, isa):
    rng = np.random.default_rng(1)
    x = (rng.normal(size=(2, 7001, 3)) * 5 + 100).astype(np.float32)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    y = (1.3 * x @ R.T + np.array([1.0, -2.0, 3.0]) + rng.normal(size=x.shape) * 0.01).astype(np.float32)
    w = rng.random((2, 7001)).astype(np.float32)
    w[0, :7] = np.nan
    w[1, :50] = 0
    x[1, 3, 1] = np.inf
    (S_k, i_k), (S_j, i_j) = _both(monkeypatch, align.umeyama.__wrapped__, x, y, w)
    np.testing.assert_array_equal(np.asarray(i_k.num_points), np.asarray(i_j.num_points))
    _close(S_k, S_j, atol=5e-4)  # |t| ~ 100: float32 rounding of two summation orders
    with jax.enable_x64(True):
        S64, _ = align.umeyama(x.astype(np.float64), y.astype(np.float64), w.astype(np.float64))
    err_k = np.abs(np.asarray(S_k, np.float64) - np.asarray(S64)).max()
    err_j = np.abs(np.asarray(S_j, np.float64) - np.asarray(S64)).max()
    assert err_k <= max(2 * err_j, 1e-4)  # the kernel (lanes + double blocks) is no less accurate


def test_kernels_are_deterministic_and_isas_agree():
    """The kernels split the work over XLA's thread pool; each item writes its own slots, so a
    call gives the same bits every time.  The instruction sets sum in different lane orders:
    they agree to float32 rounding."""
    prev, cur, K_ref, _ = make_pair(seed=9, dtype=np.float32)
    rng = np.random.default_rng(9)
    x = (rng.normal(size=(50_001, 3)) * 3).astype(np.float32)
    y = (0.7 * x + 1.0 + rng.normal(size=x.shape) * 0.01).astype(np.float32)
    w = rng.random(50_001).astype(np.float32)
    kernels, before = _kernels._ffi_kernels, _kernels._ffi_kernels.isa()
    out = {}
    try:
        for name in ISAS:
            kernels.set_isa(name)
            runs = [
                (
                    align.align_chunk_pair(prev, cur, K_ref, options=align.AlignOptions(min_points=100))[0],
                    align.umeyama(x, y, w)[0],
                )
                for _ in range(3)
            ]
            for S_pair, S_um in runs[1:]:
                np.testing.assert_array_equal(np.asarray(S_pair), np.asarray(runs[0][0]))
                np.testing.assert_array_equal(np.asarray(S_um), np.asarray(runs[0][1]))
            out[name] = runs[0]
    finally:
        kernels.set_isa(before)
    for name in ISAS:
        _close(out[name][0], out[ISAS[0]][0])
        _close(out[name][1], out[ISAS[0]][1], atol=1e-4)
    with pytest.raises(ValueError, match="instruction sets"):
        kernels.set_isa("sse9")


def test_kernel_derivatives_are_the_pure_jax_ones(monkeypatch):
    """The fused calls carry the reference's JVP: grad through umeyama and align_chunk_pair
    matches the pure-JAX path (both paths' values agree to float32 rounding)."""
    rng = np.random.default_rng(5)
    x = (rng.normal(size=(3001, 3)) * 2).astype(np.float32)
    y = (0.8 * x[:, ::-1] + 1.0 + rng.normal(size=x.shape) * 0.01).astype(np.float32)
    w = rng.random(3001).astype(np.float32)

    def loss_umeyama(y):
        S, _ = align.umeyama.__wrapped__(x, y, w)
        return jnp.sum(S * jnp.arange(1.0, 9.0))

    prev, cur, K_ref, _ = make_pair(seed=6, dtype=np.float32)

    def loss_pair(depth):
        fn, args = _core(prev._replace(depth=depth), cur, K_ref, min_points=100)
        S, _ = fn(*args)
        return jnp.sum(S * jnp.arange(1.0, 9.0))

    for loss, arg, atol in ((loss_umeyama, y, 1e-4), (loss_pair, prev.depth, 1e-5)):
        (v_k, g_k), (v_j, g_j) = _both(monkeypatch, jax.value_and_grad(loss), jnp.asarray(arg))
        assert np.all(np.isfinite(np.asarray(g_j))) and np.abs(np.asarray(g_j)).max() > 0
        np.testing.assert_allclose(float(v_k), float(v_j), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(np.asarray(g_k), np.asarray(g_j), atol=atol, rtol=1e-3)


def test_quick_compiled_entry_points_nest_inside_a_users_jit():
    """umeyama / align_chunk_pair carry compiler options, which JAX takes only on the outermost
    jit: inside a user's jit (traced arguments, or constants closed over) they are plain jits."""
    rng = np.random.default_rng(7)
    x = rng.normal(size=(500, 3)).astype(np.float32)
    y = (1.5 * x + 2.0).astype(np.float32)
    S_top, _ = align.umeyama(x, y)
    S_arg, _ = jax.jit(lambda a, b: align.umeyama(a, b))(x, y)
    S_const, _ = jax.jit(lambda: align.umeyama(jnp.asarray(x), jnp.asarray(y)))()
    np.testing.assert_allclose(np.asarray(S_arg), np.asarray(S_top), atol=1e-6)
    np.testing.assert_allclose(np.asarray(S_const), np.asarray(S_top), atol=1e-6)
    assert abs(float(S_top[7]) - 1.5) < 1e-5
    prev, cur, K_ref, _ = make_pair(seed=8, dtype=np.float32)
    S_pair, _ = align.align_chunk_pair(prev, cur, K_ref, options=align.AlignOptions(min_points=100))
    S_in, _ = jax.jit(lambda p, c: align.align_chunk_pair(p, c, K_ref, options=align.AlignOptions(min_points=100)))(
        prev, cur
    )
    np.testing.assert_allclose(np.asarray(S_in), np.asarray(S_pair), atol=1e-5)

"""Geometric place recognition and registration (:mod:`swiftjax.loops.geometric`) against
NumPy loops, closed forms and the invariances the module docstring claims."""

from __future__ import annotations

import dataclasses
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from swiftjax import sim3
from swiftjax.loops import geometric as G


def _grid_numpy(q, w, rings, sectors, max_radius, max_height):
    """Scan Context grid, one point at a time."""
    grid = np.zeros((rings, sectors))
    count = 0
    for (x, y, z), wi in zip(np.asarray(q, np.float64), np.asarray(w)):
        rho = math.hypot(x, y)
        if wi <= 0 or rho >= max_radius:
            continue
        count += 1
        theta = math.atan2(y, x) % (2 * math.pi)
        r = min(int(rho / max_radius * rings), rings - 1)
        k = min(int(theta / (2 * math.pi) * sectors), sectors - 1)
        grid[r, k] = max(grid[r, k], min(max(z, 0.0), max_height))
    return grid, count


def _street(rng, n=3000):
    """A small street-like cloud (camera heights): road, facades with gaps, a few poles."""
    road = np.c_[rng.uniform(-15, 15, n // 3), rng.uniform(-4, 4, n // 3), np.zeros(n // 3)]
    xs = rng.uniform(-15, 15, n // 3)
    left = np.c_[xs, 6 + 0.5 * np.sin(xs), rng.uniform(0, 4 + 2 * (np.sin(xs / 3) > 0), n // 3)]
    m = n - 2 * (n // 3)
    poles = rng.choice(6, m)
    cx = np.array([-12, -7, -1, 4, 9, 13.0])[poles]
    cy = np.array([-5, -6, -5.5, -7, -5, -6.5])[poles]
    right = np.c_[cx + rng.normal(0, 0.2, m), cy + rng.normal(0, 0.2, m), rng.uniform(0, 3, m)]
    return np.concatenate([road, left, right]).astype(np.float32)


def test_polar_grid_against_numpy_loop():
    rng = np.random.default_rng(0)
    q = rng.uniform(-12, 12, (500, 3)).astype(np.float32)
    w = (rng.uniform(size=500) > 0.2).astype(np.float32)
    got, count = G.polar_grid(q, w, 6, 12, 10.0, 5.0)
    ref, ref_count = _grid_numpy(q, w, 6, 12, 10.0, 5.0)
    np.testing.assert_allclose(np.asarray(got), ref, atol=1e-6)
    assert int(count) == ref_count


def test_signature_is_rotation_invariant():
    """A rotation about up by whole sectors rolls the grid exactly and leaves the signature
    unchanged; any other angle changes it by the sector quantisation only (much less than a
    different place)."""
    rng = np.random.default_rng(1)
    q = _street(rng, 20000)
    w = np.ones(len(q), np.float32)
    R, S = 10, 36
    g0, _ = G.polar_grid(q, w, R, S, 20.0, 8.0)
    for m in (1, 7, 18):
        phi = m * 2 * np.pi / S + 1e-4  # off the sector boundaries by a hair, in the same cell
        c, s = np.cos(phi), np.sin(phi)
        rot = q @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]], np.float32)
        g1, _ = G.polar_grid(rot, w, R, S, 20.0, 8.0)
        same = np.mean(np.isclose(np.asarray(g1), np.roll(np.asarray(g0), m, axis=1), atol=1e-5))
        assert same > 0.97  # only points within 1e-4 rad of a boundary may change cell
        d, shift = G.scan_context_distance(g0, g1)
        assert int(shift) == (-m) % S or int(shift) == m  # G_b[:, k + m*] = G_a[:, k]
    # another place: an open square (scattered blocks of other heights)
    sq = np.random.default_rng(7)
    other, _ = G.polar_grid(
        np.c_[sq.uniform(-18, 18, (len(q), 2)), sq.choice([0, 0, 1, 5], len(q)) * sq.uniform(size=len(q))].astype(
            np.float32
        ),
        w,
        R,
        S,
        20.0,
        8.0,
    )
    sig = G.grid_signature(jnp.stack([g0, g1, other]))
    d_rot = 1 - float(sig[0] @ sig[1])
    d_other = 1 - float(sig[0] @ sig[2])
    assert d_rot < 1e-4 and d_rot < d_other / 20
    for phi in rng.uniform(0, 2 * np.pi, 5):  # arbitrary angles: small, never a different place
        c, s = np.cos(phi), np.sin(phi)
        g2, _ = G.polar_grid(q @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]], np.float32), w, R, S, 20.0, 8.0)
        sig2 = G.grid_signature(g2)
        assert 1 - float(sig[0] @ sig2) < d_other / 2


def test_scan_context_shift_gives_the_yaw():
    rng = np.random.default_rng(2)
    g = rng.uniform(0, 3, (8, 24)) * (rng.uniform(size=(8, 24)) > 0.5)
    for m in (0, 5, 12, 23):
        d, shift = G.scan_context_distance(g, np.roll(g, m, axis=1))
        assert int(shift) == m and float(d) < 1e-6


def _sim3(rng, s):
    axis = rng.normal(size=3)
    R = np.asarray(jax.scipy.linalg.expm(jnp.asarray(np.cross(np.eye(3), axis / np.linalg.norm(axis) * 0.4))))
    return sim3.from_rst(jnp.asarray(R, jnp.float32), jnp.asarray(rng.normal(size=3), jnp.float32), s)


def test_register_recovers_a_known_sim3():
    """dst = S (src) exactly: the ICP from a start a few degrees and decimetres off lands on S
    (closed form: every residual 0)."""
    rng = np.random.default_rng(3)
    src = _street(rng, 1500)
    S_true = _sim3(rng, 2.5)
    dst = np.asarray(sim3.act(S_true, src))
    S0 = sim3.compose(
        S_true,
        sim3.from_rst(
            jnp.asarray(np.asarray(jax.scipy.linalg.expm(jnp.asarray(np.cross(np.eye(3), [0, 0, 0.05])))), jnp.float32),
            jnp.asarray([0.3, -0.2, 0.0], jnp.float32),
            1.03,
        ),
    )
    up = np.asarray(
        sim3.act(S_true, np.array([[0, 0, 1.0]], np.float32)) - sim3.act(S_true, np.zeros((1, 3), np.float32))
    )[0]
    up = up / np.linalg.norm(up)
    ground = float(up @ np.asarray(sim3.act(S_true, np.zeros((1, 3), np.float32)))[0])
    reg = G.register(src, np.ones(len(src)), dst, np.ones(len(dst)), S0, 2.5, up, ground, 1.0, 0.05, 0.3, iterations=12)
    np.testing.assert_allclose(np.asarray(sim3.as_matrix(reg.S)), np.asarray(sim3.as_matrix(S_true)), atol=2e-3)
    assert bool(reg.valid) and float(reg.rms) < 1e-3 and float(reg.inlier_ratio) > 0.99
    assert abs(float(reg.scale_ratio) - 1 / 1.03) < 1e-3
    assert (
        G.registration_reason(
            {k: np.asarray(v).item() if np.asarray(v).ndim == 0 else v for k, v in reg._asdict().items()},
            G.GeometryOptions(max_rms=0.01),
        )
        is None
    )


def _register_numpy(src, w_src, dst, w_dst, S0, unit, taus, colours=None, tol=np.inf):
    """Reference ICP in float64 NumPy: nearest neighbour by a loop, Tukey weights (zero for a
    pair whose ``colours`` differ by more than ``tol`` in a channel), weighted Umeyama."""
    S = np.asarray(sim3.as_matrix(S0), np.float64)
    for tau in taus * unit:
        y = src @ S[:3, :3].T + S[:3, 3]
        nn = np.empty(len(y), int)
        r = np.empty(len(y))
        for p in range(len(y)):
            d = np.where(w_dst > 0, np.linalg.norm(dst - y[p], axis=1), np.inf)
            nn[p] = np.argmin(d)
            r[p] = d[nn[p]]
        w = w_src * np.where(r < tau, (1 - (r / tau) ** 2) ** 2, 0.0)
        if colours is not None:
            w = w * (np.max(np.abs(colours[0] - colours[1][nn]), 1) <= tol)
        x, z = src, dst[nn]
        W = w.sum()
        mx, mz = (w[:, None] * x).sum(0) / W, (w[:, None] * z).sum(0) / W
        C = ((w[:, None] * (z - mz)).T @ (x - mx)) / W
        U, D, Vt = np.linalg.svd(C)
        E = np.diag([1, 1, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
        R = U @ E @ Vt
        s = np.trace(np.diag(D) @ E) / ((w * np.sum((x - mx) ** 2, 1)).sum() / W)
        S = np.eye(4)
        S[:3, :3] = s * R
        S[:3, 3] = mz - s * R @ mx
    return S


def test_register_against_numpy_reference():
    """Noisy, partially overlapping clouds: the JAX ICP and the float64 NumPy loop agree."""
    rng = np.random.default_rng(4)
    src = _street(rng, 400)
    S_true = _sim3(rng, 0.7)
    dst = np.asarray(sim3.act(S_true, _street(np.random.default_rng(4), 400))) + rng.normal(0, 0.01, (400, 3))
    w_src = (rng.uniform(size=400) > 0.1).astype(np.float64)
    w_dst = (rng.uniform(size=400) > 0.1).astype(np.float64)
    S0 = sim3.compose(S_true, sim3.from_rst(jnp.eye(3), jnp.asarray([0.2, 0.1, 0.0]), 1.0))
    taus = 1.0 * (0.1 / 1.0) ** (np.arange(6) / 5)
    ref = _register_numpy(src.astype(np.float64), w_src, dst, w_dst, S0, 0.7, taus)
    up = np.array([0, 0, 1.0])
    reg = G.register(src, w_src, dst, w_dst, S0, 0.7, up, 0.0, 1.0, 0.1, 0.3, iterations=6)
    np.testing.assert_allclose(np.asarray(sim3.as_matrix(reg.S)), ref, atol=2e-3)


def _painted_street(rng, n_road=400, n_wall=800, block=8.0, half=24.0):
    """A straight street: road and one straight facade at ``y = 6`` painted in blocks of
    ``block`` metres (the four facade paints of the synthetic oracle, in turn), grey road."""
    paints = np.array([[184, 158, 133], [204, 199, 179], [153, 115, 97], [140, 148, 158]], np.uint8)
    road = np.c_[rng.uniform(-half, half, n_road), rng.uniform(-4, 4, n_road), np.zeros(n_road)]
    x = rng.uniform(-half, half, n_wall)
    wall = np.c_[x, 6 + rng.normal(0, 0.03, n_wall), rng.uniform(0.5, 4, n_wall)]
    rgb = np.concatenate([np.full((n_road, 3), 90, np.uint8), paints[np.floor(x / block).astype(int) % 4]])
    return np.concatenate([road, wall]).astype(np.float32), rgb


def test_chromaticity_closed_form():
    """``(rgb + 1) / (r + g + b + 3)``: rows sum to 1, grey is ``1/3``, and halving the
    brightness (distance shading) moves a paint by less than the smallest difference between
    two of the oracle's facade paints, 0.033."""
    rgb = np.array([[184, 158, 133], [92, 79, 66], [90, 90, 90], [0, 0, 0]], np.uint8)
    c = np.asarray(G.chromaticity(rgb))
    np.testing.assert_allclose(c, (rgb + 1.0) / (rgb.sum(1, keepdims=True) + 3.0), rtol=1e-6)
    np.testing.assert_allclose(c.sum(1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(c[2:], 1.0 / 3.0, rtol=1e-6)
    assert np.max(np.abs(c[0] - c[1])) < 0.002


def test_register_colour_test_against_numpy_reference():
    """The colour test inside the ICP (a pair of different paint is no match) against the float64
    NumPy loop with the same test, from a start slid along the painted street."""
    rng = np.random.default_rng(8)
    src, rgb = _painted_street(rng, 150, 250)
    S_true = _sim3(rng, 0.9)
    dst = np.asarray(sim3.act(S_true, src)) + rng.normal(0, 0.01, src.shape).astype(np.float32)
    c = np.asarray(G.chromaticity(rgb), np.float64)
    w = np.ones(len(src))
    S0 = sim3.compose(S_true, sim3.from_rst(jnp.eye(3), jnp.asarray([1.5, 0.2, 0.0]), 1.0))
    taus = 2.0 * (0.2 / 2.0) ** (np.arange(6) / 5)
    ref = _register_numpy(src.astype(np.float64), w, dst.astype(np.float64), w, S0, 0.9, taus, (c, c), 0.03)
    up = np.asarray(sim3.act(S_true, np.float32([0, 0, 1])) - sim3.act(S_true, np.zeros(3, np.float32)))
    reg = G.register(
        src,
        w,
        dst,
        w,
        S0,
        0.9,
        up / np.linalg.norm(up),
        0.0,
        2.0,
        0.2,
        0.3,
        iterations=6,
        colours=(c, c),
        colour_tolerance=0.03,
    )
    np.testing.assert_allclose(np.asarray(sim3.as_matrix(reg.S)), ref, atol=2e-3)


def test_colour_test_scores_a_street_slid_along_itself():
    """A straight facade maps onto itself under a slide along it: 5 m along the street the plain
    ICP finds as many structure inliers as at the truth (the slide is invisible to the
    geometry, ``straight_covariance``'s free direction).  With the colour test the painted
    blocks tell them apart: the slid placement keeps only the points whose block did not
    change paint, the truth keeps them all (the structure score of the co-visible search and
    of its null, :func:`~swiftjax.loops.geometric.peak_icp`)."""
    rng = np.random.default_rng(9)
    src, rgb = _painted_street(rng)
    dst, rgb_dst = _painted_street(np.random.default_rng(10), 500, 1000, half=30.0)  # the same street, longer
    c, c_dst = np.asarray(G.chromaticity(rgb)), np.asarray(G.chromaticity(rgb_dst))
    w, w_dst = np.ones(len(src), np.float32), np.ones(len(dst), np.float32)
    up = np.float32([0, 0, 1])
    slid = sim3.from_rst(jnp.eye(3), jnp.asarray([5.0, 0.0, 0.0]), 1.0)
    score = lambda S0, **k: int(
        G.register(src, w, dst, w_dst, S0, 1.0, up, 0.0, 0.25, 0.25, 0.35, iterations=1, **k).num_structure
    )
    coloured = dict(colours=(c, c_dst), colour_tolerance=0.03)
    plain_truth, plain_slid = score(sim3.identity()), score(slid)
    assert abs(plain_truth - plain_slid) < 0.1 * plain_truth
    truth, slide = score(sim3.identity(), **coloured), score(slid, **coloured)
    assert truth > 0.9 * plain_truth  # nothing lost where the paint matches
    # 5 m of every 8 m block moves onto the next paint: about 3/8 of the facade still agrees
    assert slide < 0.55 * truth


def test_slide_starts_closed_form():
    """``slide_starts``: the placement translated along the target's heading ``e₁`` (the first
    column of its basis) by ``(−1, +1, −2, +2, …) peak_separation / 2`` camera heights, as
    4 x 4 matrices ``T(t) S``; ``slide_batch`` gives the same per job."""
    rng = np.random.default_rng(21)
    S = _sim3(rng, 1.3)
    B, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    h = 1.7
    b = G.ChunkCloud(jnp.zeros((4, 3)), jnp.ones(4), jnp.zeros(3), jnp.asarray(B, jnp.float32), jnp.float32(h))
    o = G.GeometryOptions(slide_steps=2, peak_separation=3.0)
    got = np.asarray(sim3.as_matrix(G.slide_starts(S, b, o)), np.float64)
    want = []
    for d in (-1.5, 1.5, -3.0, 3.0):
        T = np.eye(4)
        T[:3, 3] = d * h * B[:, 0]
        want.append(T @ np.asarray(sim3.as_matrix(S), np.float64))
    np.testing.assert_allclose(got, np.stack(want), atol=2e-5)
    stack = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), b)
    batched = G.slide_batch(stack, jnp.asarray([1, 0]), jnp.stack([S, S]), o)
    np.testing.assert_allclose(np.asarray(batched[1]), np.asarray(G.slide_starts(S, b, o)), atol=1e-6)


def test_slide_search_finds_the_placement_between_two_peaks():
    """A painted street whose best bird's-eye peak landed 5 m along it and whose other peaks are
    off the street: the peak ICP from starts ``±2, ±4, ±6`` m along the heading reaches the
    truth (its paint agrees everywhere, the slid placement's on 3/8 of each block), which then
    replaces the weakest peak; the slid placement stays a placement.  From the truth nothing
    scores more and nothing changes."""
    from swiftjax.pipeline import loop_geometry

    rng = np.random.default_rng(12)
    src, rgb = _painted_street(rng, 300, 700)
    dst, rgb_dst = _painted_street(np.random.default_rng(13), 500, 1000, half=30.0)
    n = len(dst)
    order = rng.permutation(len(src)), rng.permutation(n)
    pad = lambda x: np.concatenate([x, np.zeros((n - len(x), *x.shape[1:]), x.dtype)])
    points = np.stack([pad(src[order[0]]), dst[order[1]]]).astype(np.float32)
    weights = np.stack([pad(np.ones(len(src), np.float32)), np.ones(n, np.float32)])
    colours = np.stack([pad(np.asarray(G.chromaticity(rgb))[order[0]]), np.asarray(G.chromaticity(rgb_dst))[order[1]]])
    origin = np.float32([[0, 0, 1], [0, 0, 1]])  # cameras one height above the road
    clouds = G.ChunkCloud(*(jnp.asarray(x) for x in (points, weights, origin, np.stack([np.eye(3)] * 2), np.ones(2))))
    clouds = clouds._replace(colours=jnp.asarray(colours, jnp.float32))
    o = G.GeometryOptions(slide_steps=3, peak_separation=4.0)
    shift = lambda x: np.asarray(sim3.from_rst(jnp.eye(3), jnp.asarray([x, 0.0, 0.0]), 1.0), np.float32)
    far = lambda y: np.asarray(sim3.from_rst(jnp.eye(3), jnp.asarray([0.0, y, 0.0]), 1.0), np.float32)
    S0 = np.stack([far(40.0), shift(5.0), far(-40.0)])[None]
    peaks = G.peaks_batch(clouds, jnp.asarray([0]), jnp.asarray([1]), jnp.asarray(S0), jnp.ones((1, 3)), o)
    pl = G.Placements(np.array(peaks.S), np.array(peaks.scores), np.ones((1, 3), np.float32))
    slid = pl.scores[0, 1]
    assert np.argmax(pl.scores[0]) == 1 and abs(pl.S[0, 1, 0] - 5.0) < 0.5, pl.scores
    src_i, dst_i = np.asarray([0], np.int32), np.asarray([1], np.int32)
    search = lambda pl, o=o, bound=0.0: loop_geometry._slide_search(
        pl, np.asarray([0]), src_i, dst_i, np.asarray([bound]), clouds, o
    )
    boosted = G.Placements(pl.S.copy(), pl.scores.copy(), pl.correlation.copy())
    top, searched, rival = search(pl)
    best = int(np.argmax(pl.scores[0]))
    assert top[0] == pl.scores[0, best] > slid and searched[0] == best and rival[0] == 1
    # the truth's basin: across the street and in height to a few centimetres; along it within
    # the nearest start's metre (the ICP has no pull along a facade: colour only removes matches)
    assert abs(pl.S[0, best, 0]) <= 1.05 and np.abs(pl.S[0, best, 1:3]).max() < 0.1, pl.S[0, best]
    assert pl.scores[0, 1] == slid and best in (0, 2)  # the weakest replaced, the slid one kept
    before = (pl.S.copy(), pl.scores.copy())
    # from the truth: whatever basin the search finds scores less and the best stays; with a
    # bound above it nothing is plausible and nothing changes
    again = G.Placements(pl.S.copy(), pl.scores.copy(), pl.correlation)
    top, _, _ = search(again)
    assert top[0] < again.scores[0, best] and np.argmax(again.scores[0]) == best
    np.testing.assert_array_equal(again.S[0, best], before[0][0, best])
    assert search(pl, bound=float(top[0]))[2][0] == -1
    np.testing.assert_array_equal(pl.S, before[0])
    np.testing.assert_array_equal(pl.scores, before[1])
    # the slid peak scored above everything the search finds: the truth's basin, plausible and
    # 5 heights away, is the best's rival in the weakest slot, the best untouched
    boosted.scores[0, 1] = 10 * slid
    weakest = int(np.argmin(boosted.scores[0]))
    top, searched, rival = search(boosted)
    assert searched[0] == rival[0] == weakest and boosted.scores[0, weakest] == top[0]
    assert abs(boosted.S[0, weakest, 0]) <= 1.05 and np.argmax(boosted.scores[0]) == 1
    # a slot without a placement (score −1; its S all zeros maps every point to the origin, a
    # height from where the truth puts the source's camera) is no basin: the rival still goes in
    empty = G.Placements(pl.S.copy(), pl.scores.copy(), pl.correlation.copy())
    empty.scores[0, 1] = 10 * slid
    empty.S[0, weakest], empty.scores[0, weakest] = 0.0, -1
    top, searched, rival = search(empty)
    assert searched[0] == rival[0] == weakest and empty.scores[0, weakest] == top[0] > 0
    # one peak: the search's placement takes the slid best's only slot, nothing left to refine beside it
    one = G.Placements(np.array(peaks.S[:, 1:2]), np.array(peaks.scores[:, 1:2]), np.ones((1, 1), np.float32))
    top, searched, rival = search(one, o.replace(peaks=1))
    assert rival[0] == -1 and searched[0] == 0 and one.scores[0, 0] == top[0] > slid and abs(one.S[0, 0, 0]) <= 1.05


def test_host_act_is_sim3_act():
    """``loop_geometry._act`` (float64 NumPy, no compile per batch) against ``sim3.act``."""
    from swiftjax.pipeline import loop_geometry

    rng = np.random.default_rng(5)
    S = np.stack([np.asarray(_sim3(rng, s), np.float64) for s in (0.3, 1.0, 4.0)])
    x = rng.normal(size=(3, 3)) * 20
    with jax.enable_x64(True):
        want = np.asarray(sim3.act(jnp.asarray(S), jnp.asarray(x)))
    # (float32 quaternions, unit to about 1e-7: the two formulas differ by that)
    np.testing.assert_allclose(loop_geometry._act(S, x), want, rtol=2e-6, atol=2e-5)


def test_refined_rival_outranks_the_best_only_when_it_passes():
    """``loop_geometry._outranks``: of the best's and the rival's refinements, one that passes the
    refined tests (valid, scale within ``max_scale_ratio`` of the odometry's, ``min_structure``,
    ``max_rms``) is kept before one that fails them, whatever their counts; between two that
    both pass or both fail, more structure inliers (a tie keeps the best)."""
    from swiftjax.pipeline import loop_geometry

    o = G.GeometryOptions()
    ok = dict(valid=True, scale_ratio=1.05, num_structure=300, spread=0.3, rms=0.1, inlier_ratio=0.8)
    more = dict(ok, num_structure=400)
    failing = {
        "shrunk": dict(more, scale_ratio=0.51, num_structure=531),  # 00, world 1: 72/9's rival
        "grown": dict(more, scale_ratio=1.4),
        "invalid": dict(more, valid=False),
        "rough": dict(more, rms=0.3),
        "bare": dict(ok, num_structure=o.min_structure - 1),
    }
    outranks = lambda rival, best: loop_geometry._outranks(rival, best, o)
    assert outranks(more, ok) and not outranks(ok, more) and not outranks(dict(ok), ok)
    for name, bad in failing.items():
        assert G.covisible_reason({"peak_score": 0, **bad}, o, structure_null=False) is not None, name
        assert not outranks(bad, ok) and outranks(ok, bad), name
    assert outranks(failing["shrunk"], failing["invalid"]) and not outranks(failing["bare"], failing["rough"])
    # the numbers of a real registration, as plain values
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(200, 3)).astype(np.float32) * 5
    reg = G.register(
        pts,
        np.ones(200, np.float32),
        pts,
        np.ones(200, np.float32),
        sim3.identity(),
        1.0,
        jnp.asarray([0.0, 0.0, 1.0]),
        -10.0,
    )
    numbers = loop_geometry._registration_numbers(reg)
    assert numbers["valid"] is True and numbers["num_points"] == 200 and isinstance(numbers["num_structure"], int)
    assert numbers["rms"] == pytest.approx(float(reg.rms)) and numbers["scale_ratio"] == pytest.approx(1.0, abs=1e-4)


def test_degenerate_registration_is_rejected_and_finite():
    """A flat featureless road: no structure, the candidate is rejected with a reason; the
    edge is finite."""
    rng = np.random.default_rng(5)
    road = np.c_[rng.uniform(-20, 20, 800), rng.uniform(-4, 4, 800), np.zeros(800)].astype(np.float32)
    S0 = sim3.from_rst(jnp.eye(3), jnp.zeros(3), 1.0)
    reg = G.register(
        road,
        np.ones(800),
        road + np.float32([3, 0, 0]),
        np.ones(800),
        S0,
        1.0,
        np.float32([0, 0, 1]),
        0.0,
        iterations=8,
    )
    assert np.all(np.isfinite(np.asarray(reg.S)))
    plain = {k: np.asarray(v).item() if np.asarray(v).ndim == 0 else v for k, v in reg._asdict().items()}
    why = G.registration_reason(plain, G.GeometryOptions())
    assert why is not None and "degenerate" in why
    # and a scale far from the camera-height ratio is named as such
    plain.update(valid=True, scale_ratio=2.0)
    assert "scale" in G.registration_reason(plain, G.GeometryOptions())
    # no points at all: invalid, finite
    reg = G.register(road, np.zeros(800), road, np.ones(800), S0, 1.0, np.float32([0, 0, 1]), 0.0, iterations=4)
    assert not bool(reg.valid) and np.all(np.isfinite(np.asarray(reg.S)))


def test_register_straight_structure_axis_against_numpy():
    """A straight street (road and one straight facade): the registration's structure
    statistics (the inlying structure's centroid, principal horizontal axis and its variance
    ``λ₁``, ``spread = λ₂ / λ₁``) against NumPy on the same placement; the spread is below
    ``min_spread`` (a line), the axis along the facade."""
    rng = np.random.default_rng(21)
    road = np.c_[rng.uniform(-20, 20, 400), rng.uniform(-4, 4, 400), np.zeros(400)]
    wall = np.c_[rng.uniform(-20, 20, 600), 6 + rng.normal(0, 0.05, 600), rng.uniform(0.5, 4, 600)]
    src = np.concatenate([road, wall]).astype(np.float32)
    S_true = _sim3(rng, 1.3)
    dst = np.asarray(sim3.act(S_true, src)) + rng.normal(0, 0.01, src.shape).astype(np.float32)
    up = np.asarray(sim3.act(S_true, np.float32([0, 0, 1])) - sim3.act(S_true, np.zeros(3, np.float32)))
    up = up / np.linalg.norm(up)
    ground = float(up @ np.asarray(sim3.act(S_true, np.zeros(3, np.float32))))
    w = np.ones(len(src), np.float32)
    reg = G.register(src, w, dst, w, S_true, 1.3, up, ground, 0.5, 0.2, 0.3, iterations=4)
    # NumPy: the same inliers and structure, from the registration's own placement
    M = np.asarray(sim3.as_matrix(reg.S), np.float64)
    y = src.astype(np.float64) @ M[:3, :3].T + M[:3, 3]
    r = np.array([np.min(np.linalg.norm(dst - p, axis=1)) for p in y])
    struct = (r < 0.2 * 1.3) & ((y @ up - ground) / 1.3 >= 0.3)
    ys = y[struct]
    ms = ys.mean(0)
    P = np.eye(3) - np.outer(up, up)
    h = (ys - ms) @ P
    ev, evec = np.linalg.eigh(h.T @ h / len(ys))
    assert int(reg.num_structure) == int(struct.sum())
    np.testing.assert_allclose(np.asarray(reg.structure_mean), ms, atol=1e-3)
    assert float(reg.axis_variance) == pytest.approx(ev[2], rel=1e-3)
    assert abs(float(np.asarray(reg.axis) @ evec[:, 2])) == pytest.approx(1.0, abs=1e-5)
    assert float(reg.spread) == pytest.approx(ev[1] / ev[2], rel=1e-2, abs=1e-5)
    assert float(reg.spread) < G.GeometryOptions().min_spread
    wall_axis = np.asarray(sim3.act(S_true, np.float32([1, 0, 0])) - sim3.act(S_true, np.zeros(3, np.float32)))
    assert abs(float(np.asarray(reg.axis) @ wall_axis / np.linalg.norm(wall_axis))) > 0.999


def _line_points_stay_on_line(S, xi, x_a, m, d):
    """The largest distance of ``S exp(ξ) x_a`` from the line ``m + t d`` (float64)."""
    y = np.asarray(sim3.act(sim3.compose(S, sim3.exp(xi)), x_a))
    rel = y - m
    return np.max(np.linalg.norm(rel - np.outer(rel @ d, d), axis=1))


def test_straight_covariance_frees_exactly_what_a_line_cannot_see(x64):
    """``Σ_L`` of an edge onto a line: rank two, its range exactly the first-order motions
    that keep the line's points on the line (a slide along it and a scaling about a point of
    it; a perturbation in its range moves them off the line only at second order, one outside
    it at first order), and its two variances in closed form (``λ₁ / s²`` along the slide,
    ``scale_variance`` along the scaling, projected on the unit slide and scale directions)."""
    rng = np.random.default_rng(22)
    S = jnp.asarray(np.asarray(_sim3(rng, 1.7), np.float64))
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    m = rng.normal(size=3) * 3
    lam = 40.0
    x_a = np.asarray(sim3.act(sim3.inverse(S), m + np.outer(np.linspace(-10, 10, 21), d)))
    cov = np.asarray(G.straight_covariance(S, d, lam, m, 0.01))
    assert cov.dtype == np.float64
    np.testing.assert_allclose(cov, cov.T, atol=1e-12)
    ev, vec = np.linalg.eigh(cov)
    assert np.all(ev[:5] < 1e-10 * ev[-1]) and ev[5] > 1e-6
    eps = 1e-4
    for k in (5, 6):  # in the range: off the line at second order only
        assert _line_points_stay_on_line(S, eps * vec[:, k], x_a, m, d) < 1e-6 * eps
    for k in range(5):  # outside it: off the line at first order
        off = vec[:, k] - vec[:, 5:] @ (vec[:, 5:].T @ vec[:, k])
        assert _line_points_stay_on_line(S, eps * off / np.linalg.norm(off), x_a, m, d) > 1e-3 * eps
    # closed form: the slide u = (Rᵀ d, 0, 0), the scaling v = (−S⁻¹ m, 0, 1)
    s = float(np.asarray(S)[7])  # 1.7 in float32
    R = np.asarray(sim3.as_matrix(S))[:3, :3] / s
    u = np.r_[R.T @ d, np.zeros(4)]
    v = np.r_[-np.asarray(sim3.act(sim3.inverse(S), m)), np.zeros(3), 1.0]
    np.testing.assert_allclose(cov, lam / s**2 * np.outer(u, u) + 0.01 * np.outer(v, v), rtol=1e-9, atol=1e-12)


def test_straight_registration_is_kept_by_the_covisible_verdict_not_the_plain_one():
    """Straight structure (``spread < min_spread``) rejects a plain registration (no covariance
    to leave the slide to the graph) but not a co-visible one (its edge gets ``Σ_L``); too few
    structure inliers reject both, in one line."""
    o = G.GeometryOptions()
    reg = dict(valid=True, scale_ratio=1.0, num_structure=400, spread=0.5 * o.min_spread, rms=0.1, inlier_ratio=0.8)
    reg.update(peak_score=90, null_threshold=40.0)
    assert "degenerate" in G.registration_reason(reg, o)
    assert G.covisible_reason(reg, o) is None and G.covisible_reason(reg, o, structure_null=False) is None
    few = {**reg, "num_structure": o.min_structure - 1}
    for why in (G.registration_reason(few, o), G.covisible_reason(few, o)):
        assert why is not None and "degenerate" in why and "\n" not in why


def test_chunk_descriptors_reverse_pass_matches(shared_dir):
    """Two oracle chunks of synthetic KITTI 08 driving one street in opposite directions:
    their signatures are closer than those of chunks of other streets, the Scan Context yaw
    is ~180 degrees from the forward axes, and no signature is NaN.  Too few points: invalid."""
    from swiftjax import align, chunks
    from swiftjax.io.trajectory import read_kitti
    from swiftjax.synthetic import demo

    poses = read_kitti(shared_dir / "data" / "trajectories" / "KITTI_08_gt.txt")[:2000]
    run = demo.trajectory_run(poses, name="k08")
    orc = run.predictor.oracle
    sch = chunks.chunk_schedule(len(poses), 75, 30)
    opts = G.GeometryOptions()
    sel = [4, 38, 10, 23]  # 4 and 38: the same street, opposite directions; 10, 23: elsewhere
    fr = []
    for c in sel:
        p = orc.predict_chunk(sch.frames(c))
        i = np.arange(0, 75, opts.frame_stride)
        fr.append(align.ChunkFrames(p.depth[i], p.conf[i], p.intrinsic[i], p.extrinsic[i]))
    stack = align.ChunkFrames(*(np.stack(x) for x in zip(*fr)))
    desc = G.chunk_descriptors(stack, orc.K, opts)
    assert np.all(np.isfinite(np.asarray(desc.signatures)))
    assert np.asarray(desc.valid).all()
    d, best = G.signature_distances(desc.signatures, desc.valid)
    d = np.asarray(d)
    assert d[0, 1] < min(d[0, 2], d[0, 3], d[1, 2], d[1, 3])
    empty = stack._replace(conf=np.zeros_like(stack.conf))
    assert not np.asarray(G.chunk_descriptors(empty, orc.K, opts).valid).any()


def test_bench_hard_sequences_quick(shared_dir, monkeypatch, tmp_path):
    """The benchmark's smoke test (``--quick``): the pipeline with ``loop_geometry`` on runs
    through synthetic KITTI 08's start; every candidate carries its source and a one-line
    verdict, every geometric one its registration numbers or why it got none; every arm's
    ATE is finite (never a NaN pose)."""
    import pathlib
    import sys

    monkeypatch.setenv("SWIFTJAX_SHARED", str(shared_dir))
    monkeypatch.setenv("SWIFTJAX_CACHE_DIR", str(tmp_path / "cache"))
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "bench"))
    import bench_hard_sequences

    out = bench_hard_sequences.main(["--quick", "--frames", "400"])
    (rec,) = out["records"]
    assert set(rec["arms"]) == {
        "tokens (defaults)",
        "tokens + geometry",
        "authors",
        "truth edges",
        "pipeline (its own graph)",
    }
    assert all(np.isfinite(a["ate_rmse"]) for a in rec["arms"].values())
    assert rec["loop_geometry_seconds"] > 0  # the geometric source ran on every chunk
    # KITTI 08's first 400 frames hold no revisit: nothing the geometry proposes may be accepted.
    assert rec["regions"] == {"same": 0, "reverse": 0}
    assert not any(c["accepted"] for c in rec["candidate_records"])
    for c in rec["candidate_records"]:
        assert c["source"] in ("tokens", "geometry") and c["reason"] and "\n" not in c["reason"]
        if c["source"] == "geometry" and c["registration"] is not None:
            assert all(np.isfinite(v) for v in c["registration"].values() if isinstance(v, float))
    assert "truth edges" in out["table"]
    # every temporal edge's error against the truth, whitened by the run's own covariance
    cal = rec["edge_calibration"]["by_source"]
    assert cal["temporal"]["edges"] == rec["chunks"] - 1 and cal["tokens"]["edges"] == cal["geometry"]["edges"] == 0
    assert 0 < cal["temporal"]["mean_whitened_error_sq"] < np.inf
    per_component = np.asarray(cal["temporal"]["mean_marginal_by_component"])  # rho, omega, sigma
    assert per_component.shape == (7,) and np.all(per_component > 0) and np.all(np.isfinite(per_component))
    assert cal["tokens"]["mean_marginal_by_component"] is None


def test_geometric_records_in_loops_txt_and_metrics(tmp_path):
    """A geometric candidate's source and registration numbers reach ``loops.txt`` and
    ``metrics.json``'s candidate list (marked ``source: geometry``), its reason on one line."""
    from swiftjax.pipeline import export, report

    rec = {
        "i": 3000,
        "j": 120,
        "score": 0.7,
        "chunk_i": 66,
        "chunk_j": 2,
        "accepted": False,
        "reason": "degenerate registration: 12 structure inliers, spread 0.004",
        "source": "geometry",
        "Z": [0, 0, 0, 0, 0, 0, 1, 1.0],
        "registration": {
            "inlier_ratio": 0.41,
            "rms": 0.12,
            "scale_ratio": 1.02,
            "spread": 0.004,
            "num_inliers": 300,
            "num_structure": 12,
            "num_points": 1024,
            "valid": True,
        },
    }
    tok = {
        "i": 900,
        "j": 100,
        "score": 0.9,
        "chunk_i": 20,
        "chunk_j": 2,
        "accepted": True,
        "reason": "verified",
        "source": "tokens",
        "dense_agreement": 0.8,
    }
    export.write_loops(tmp_path / "loops.txt", [tok, rec])
    lines = (tmp_path / "loops.txt").read_text().splitlines()
    comments = [ln for ln in lines if ln.startswith("#")]
    header = comments[-1].lstrip("# ").split()  # the column names; "reason" (with spaces) closes each row
    rows = [dict(zip(header, line.split(maxsplit=len(header) - 1))) for line in lines[len(comments) :]]
    assert rows[1]["source"] == "geometry" and rows[0]["source"] == "tokens"
    assert rows[1]["registration.inlier_ratio"] == "0.41" and rows[0]["registration.inlier_ratio"] == "-"
    assert rows[1]["reason"] == "degenerate registration: 12 structure inliers, spread 0.004"
    cand = report._candidate(rec)
    assert cand["source"] == "geometry" and cand["registration"]["spread"] == 0.004 and "Z" not in cand


def test_odometry_gate():
    """Chunks on an out-and-back drive: the chunk driven back over the same stretch passes the
    gate (with its window in camera heights), a chunk far away or too close in time does not
    (distances by hand)."""
    from types import SimpleNamespace

    from swiftjax.pipeline.loop_geometry import _pairs

    x = np.array([0, 50, 100, 150, 100, 50, 0, 300.0])  # metres; chunk 7 jumps far away
    chain = np.zeros((8, 8))
    chain[:, 0] = x
    chain[:, 6] = 1.0  # identity rotation (qw last)
    chain[:, 7] = 1.0
    clouds = SimpleNamespace(origin=np.zeros((8, 3)), height=np.full(8, 1.65))
    ids = np.arange(8)[:, None] * 100 + np.arange(3)[None, :]  # chunk c: frames 100 c ..
    got = {(a, b): w for a, b, w in _pairs(chain, clouds, ids, 150, G.GeometryOptions(gate_min=15.0, gate_drift=0.1))}
    # 5 and 1: same place, 200 m of path apart -> 0 m <= max(24.75, 20); window 24.75 m / 1.65 = 15 h
    assert (5, 1) in got and (6, 0) in got and (4, 2) in got
    assert got[(5, 1)] == pytest.approx(15.0)
    # 6 and 0: 300 m of path -> window 30 m / 1.65 m
    assert got[(6, 0)] == pytest.approx(30.0 / 1.65)
    # 2 and 0: 100 m apart, path 100 m -> 100 > max(24.75, 10); 7 is 300 m from 6
    assert (2, 0) not in got and (3, 1) not in got and (7, 6) not in got and (7, 0) not in got
    # frames closer than the separation: not proposed
    assert not _pairs(chain, clouds, ids, 800, G.GeometryOptions())


def _rodrigues(u, theta):
    K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]], np.float64)
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def test_yaw_step_is_the_closed_form_rotation_about_up():
    """Points rotated about a tilted up axis by 2.5 rad and shifted: one 4-DoF step recovers the
    rotation (Rodrigues, float64) and translation exactly, the scale untouched."""
    rng = np.random.default_rng(8)
    y = rng.normal(size=(60, 3))
    up = np.array([0.1, 0.2, 0.97])
    up /= np.linalg.norm(up)
    R = _rodrigues(up, 2.5)
    z = y @ R.T + [1.0, -2.0, 0.5]
    D, ok = G._yaw_step(
        jnp.asarray(y, jnp.float32), jnp.asarray(z, jnp.float32), jnp.ones(60), jnp.asarray(up, jnp.float32)
    )
    M = np.asarray(sim3.as_matrix(D), np.float64)
    assert bool(ok)
    np.testing.assert_allclose(M[:3, :3], R, atol=1e-5)
    np.testing.assert_allclose(M[:3, 3], [1.0, -2.0, 0.5], atol=1e-4)
    # no weight: invalid, finite
    D, ok = G._yaw_step(
        jnp.asarray(y, jnp.float32), jnp.asarray(z, jnp.float32), jnp.zeros(60), jnp.asarray(up, jnp.float32)
    )
    assert not bool(ok)


def test_path_weights_against_numpy_loop():
    rng = np.random.default_rng(9)
    pts = rng.uniform(-30, 30, (400, 3)).astype(np.float32)
    w = (rng.uniform(size=400) > 0.3).astype(np.float32)
    anchors = np.float32([[-10, 0, 1], [0, 0, 1], [10, 2, 1]])
    basis = np.asarray(_rodrigues(np.array([1.0, 0, 0]), 0.1), np.float32)  # up tilted about x
    g = G.ChunkGeometry(pts, w, anchors, basis, np.float32(1.5), np.arange(3, dtype=np.int32))
    got = np.asarray(G.path_weights(jax.tree_util.tree_map(jnp.asarray, g), 6.0))
    ref = np.zeros(400)
    for n in range(400):
        for a in anchors:
            xy = (pts[n] - a) @ basis[:, :2] / 1.5
            if w[n] > 0 and xy @ xy < 36.0:
                ref[n] = w[n]
    np.testing.assert_array_equal(got, ref)


def _corner(rng, n):
    """:func:`_street` with a building at one end: the street's facades alone are nearly
    symmetric under a half turn (``sin`` is odd), the building is not."""
    m = n // 4
    side = rng.choice(3, m)
    t = rng.uniform(0, 1, m)
    x = np.where(side == 0, 8 + 6 * t, np.where(side == 1, 8.0, 14.0))
    y = np.where(side == 0, -9.0, -9 - 4 * t)
    building = np.c_[x, y, rng.uniform(0, 5, m)]
    return np.concatenate([_street(rng, n - m), building]).astype(np.float32)


def _reverse_pass(rng, s_true, phi, offset):
    """Chunk a: a street with a building at one end (:func:`_corner`; camera heights 1, up z,
    anchors along x); chunk b: the same street from
    its other end, ``x_b = S(x_a)`` with a 180 degree yaw about up, scale ``s_true`` and a shift;
    b's gravity basis turned by ``phi`` about up and its anchors ``offset`` along the road
    from a's (b's cameras drove the same road, not through a's anchor points)."""
    R_true = _rodrigues(np.array([0.0, 0, 1]), np.pi) @ _rodrigues(np.array([1.0, 0, 0]), 0.03)
    S_true = sim3.from_rst(jnp.asarray(R_true, jnp.float32), jnp.asarray([4.0, -3.0, 1.0], jnp.float32), s_true)
    pts = rng.permutation(_corner(rng, 6000))
    src, dst = pts[::2], np.asarray(sim3.act(S_true, pts))  # b saw more of the street than a
    anchors_a = np.float32([[x, 0, 1] for x in (-12, -6, 0, 6, 12)])
    anchors_b = np.asarray(sim3.act(S_true, anchors_a[::-1] + np.float32([offset, 0, 0])))
    basis_a = np.eye(3, dtype=np.float32)
    basis_b = np.asarray(R_true @ _rodrigues(np.array([0.0, 0, 1]), phi), np.float32)
    return S_true, R_true, src, dst, anchors_a, anchors_b, basis_a, basis_b


@pytest.mark.parametrize("s_true", [3.0, 0.4])
def test_register_hypotheses_finds_a_reverse_revisit(s_true):
    """The same street driven the other way (180 degree yaw, 3x or 0.4x scale, gravity basis
    turned, anchors off by 2.5 camera heights along the road): the best of the several starts
    (every anchor pair at its Scan Context yaw and yaw + pi) registers to the true Sim(3)
    (closed form)."""
    rng = np.random.default_rng(10)
    S_true, R_true, src, dst, aa, ab, Ba, Bb = _reverse_pass(rng, s_true, 0.7, 2.5)
    opts = G.GeometryOptions(rings=10, sectors=36, max_radius=20.0, tau_start=3.0, tau_end=0.15, iterations=30)
    grid = lambda pts, a, B, h: G.polar_grid(
        G._normalised(jnp.asarray(pts), jnp.asarray(a), jnp.asarray(B), h),
        np.ones(len(pts), np.float32),
        10,
        36,
        20.0,
        8.0,
    )[0]
    ga = jnp.stack([grid(src, a, Ba, 1.0) for a in aa])
    gb = jnp.stack([grid(dst, a, Bb, s_true) for a in ab])
    S0, anchors, yaw = G.coarse_hypotheses(ga, gb, aa, Ba, 1.0, ab, Bb, s_true)
    assert S0.shape == (50, 8) and anchors.shape == (50, 2)
    np.testing.assert_allclose(np.asarray(jnp.mod(yaw[1::2] - yaw[::2], 2 * np.pi)), np.pi, atol=1e-5)
    up = Bb[:, 2]
    ground = float(up @ np.asarray(sim3.translation(S_true)))
    ws, wd = np.ones(len(src), np.float32), np.ones(len(dst), np.float32)
    src_s, ws_s = G.subsample(src, ws, 1024, jax.random.PRNGKey(0))
    reg, k, scores = G.register_hypotheses(src_s, ws_s, dst, wd, S0, s_true, up, ground, opts)
    M, M_true = np.asarray(sim3.as_matrix(reg.S), np.float64), np.asarray(sim3.as_matrix(S_true), np.float64)
    R = M[:3, :3] / np.cbrt(np.linalg.det(M[:3, :3]))
    assert np.degrees(np.arccos(np.clip((np.trace(R.T @ R_true) - 1) / 2, -1, 1))) < 0.1
    assert abs(float(sim3.scale(reg.S)) / s_true - 1) < 1e-3
    np.testing.assert_allclose(M[:3, 3], M_true[:3, 3], atol=0.01 * s_true)
    assert bool(reg.valid) and float(reg.inlier_ratio) > 0.95 and float(reg.rms) < 1e-3
    assert int(scores[int(k)]) == int(np.max(np.asarray(scores)))


def test_register_hypotheses_without_a_camera_height_is_rejected_not_nan():
    """A chunk whose camera height is unknown (no road seen: NaN): every start is NaN, the
    result is the identity (finite), invalid, and the candidate's reason says so in one line."""
    rng = np.random.default_rng(11)
    _, _, src, dst, aa, ab, Ba, Bb = _reverse_pass(rng, 2.0, 0.0, 0.0)
    g = jnp.ones((5, 10, 36))
    S0, _, _ = G.coarse_hypotheses(g, g, aa, Ba, float("nan"), ab, Bb, 2.0)
    assert not np.isfinite(np.asarray(S0)).all()
    reg, _, scores = G.register_hypotheses(
        src[:512], np.ones(512), dst[:1024], np.ones(1024), S0, 2.0, Bb[:, 2], 0.0, G.GeometryOptions()
    )
    assert np.all(np.isfinite(np.asarray(reg.S))) and not bool(reg.valid) and np.all(np.asarray(scores) == -1)
    plain = {k: np.asarray(v).item() if np.asarray(v).ndim == 0 else v for k, v in reg._asdict().items()}
    why = G.registration_reason(plain, G.GeometryOptions())
    assert why is not None and "\n" not in why and "registration failed" in why


def test_bev_raster_against_numpy_loop():
    """Occupancy of random points (some outside the grid, some unweighted, some not finite)
    against a NumPy loop."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-7, 7, (500, 2)).astype(np.float32)
    w = (rng.uniform(size=500) > 0.3).astype(np.float32)
    xy[:3], w[:3] = [[np.nan, 0.0], [0.0, np.inf], [-np.inf, 1.0]], 1.0
    got = np.asarray(G.bev_raster(xy, w, 16, 0.75))
    ref = np.zeros((16, 16))
    for (x, y), wn in zip(xy, w):
        if not np.isfinite([x, y]).all():
            continue
        i, j = int(np.floor(x / 0.75)) + 8, int(np.floor(y / 0.75)) + 8
        if wn > 0 and 0 <= i < 16 and 0 <= j < 16:
            ref[i, j] = 1.0
    np.testing.assert_array_equal(got, ref)


def test_edge_prior_closed_form():
    """``(ψ, σ, τ)`` of a known edge between two gravity frames, worked by hand: a's frame the
    identity at the origin with h = 1, b's frame turned 90 degrees about up at (1, 0, 0) with
    h = 2; Z: yaw 0.7 rad, scale 1.5, translation (3, 4, 0)."""
    a = G.ChunkCloud(jnp.zeros((4, 3)), jnp.ones(4), jnp.zeros(3), jnp.eye(3), jnp.float32(1.0))
    Bb = jnp.asarray(_rodrigues(np.array([0.0, 0, 1]), np.pi / 2), jnp.float32)
    b = G.ChunkCloud(jnp.zeros((4, 3)), jnp.ones(4), jnp.asarray([1.0, 0, 0]), Bb, jnp.float32(2.0))
    Z = sim3.from_rst(jnp.asarray(_rodrigues(np.array([0.0, 0, 1]), 0.7), jnp.float32), jnp.asarray([3.0, 4, 0]), 1.5)
    psi, sigma, tau = G.edge_prior(Z, a, b)
    # M = Bbᵀ Rz(0.7) I = Rz(0.7 − π/2); σ = 1.5·1/2; τ = Bbᵀ((3, 4, 0) − (1, 0, 0))/2 = Rz(−π/2)(2, 4)/2 = (2, −1)
    assert float(psi) == pytest.approx(0.7 - np.pi / 2, abs=1e-6)
    assert float(sigma) == pytest.approx(0.75, abs=1e-6)
    np.testing.assert_allclose(np.asarray(tau), [2.0, -1.0], atol=1e-5)


def _clouds(src, dst, aa, ab, Ba, Bb, s_true, h_b=None):
    a = G.ChunkCloud(jnp.asarray(src), jnp.ones(len(src)), jnp.asarray(aa.mean(0)), jnp.asarray(Ba), jnp.float32(1.0))
    b = G.ChunkCloud(
        jnp.asarray(dst),
        jnp.ones(len(dst)),
        jnp.asarray(ab.mean(0)),
        jnp.asarray(Bb),
        jnp.float32(s_true if h_b is None else h_b),
    )
    return a, b


@pytest.mark.parametrize("s_true", [3.0, 0.4])
def test_register_covisible_recovers_a_reverse_revisit_from_a_poor_prior(s_true):
    """The same street driven the other way (180 degree yaw, scale 3x or 0.4x, b's gravity
    basis turned): from an odometry prior 6 camera heights off along the street, 2 degrees off
    in yaw and 10 % off in scale, the search within a 12 h window and the ICP give the true
    Sim(3) (closed form), with the scale ratio against the prior (1 / 1.1)."""
    rng = np.random.default_rng(12)
    S_true, R_true, src, dst, aa, ab, Ba, Bb = _reverse_pass(rng, s_true, 0.7, 2.5)
    a, b = _clouds(src, dst[:4096], aa, ab, Ba, Bb, s_true)
    off = sim3.from_rst(
        jnp.asarray(_rodrigues(np.array([0.0, 0, 1]), np.radians(2.0)), jnp.float32),
        jnp.asarray(Bb[:, 0] * 6.0 * s_true, jnp.float32),
        1.1,
    )
    psi, sigma, tau = G.edge_prior(sim3.compose(off, S_true), a, b)
    opts = G.GeometryOptions(refine_iterations=12, tau_end=0.15)
    cov = G.register_covisible(a, b, psi, sigma, tau, 12.0, opts)
    reg = cov.registration
    M, M_true = np.asarray(sim3.as_matrix(reg.S), np.float64), np.asarray(sim3.as_matrix(S_true), np.float64)
    R = M[:3, :3] / np.cbrt(np.linalg.det(M[:3, :3]))
    assert np.degrees(np.arccos(np.clip((np.trace(R.T @ R_true) - 1) / 2, -1, 1))) < 0.2
    assert abs(float(sim3.scale(reg.S)) / s_true - 1) < 3e-3
    np.testing.assert_allclose(M[:3, 3], M_true[:3, 3], atol=0.05 * s_true)
    assert bool(reg.valid) and float(reg.scale_ratio) == pytest.approx(1 / 1.1, rel=5e-3)
    assert cov.scores.shape == (opts.peaks,) and float(cov.ambiguity) < 1.0


def test_register_covisible_bad_input_rejected_not_nan():
    """No camera height (NaN) or too few structure points: the result is finite, the verdict a
    one-line reason (never a NaN pose)."""
    rng = np.random.default_rng(13)
    _, _, src, dst, aa, ab, Ba, Bb = _reverse_pass(rng, 2.0, 0.0, 0.0)
    a, b = _clouds(src, dst[:4096], aa, ab, Ba, Bb, 2.0, h_b=float("nan"))
    cov = G.register_covisible(a, b, 0.0, 1.0, jnp.zeros(2), 10.0)
    assert np.all(np.isfinite(np.asarray(cov.registration.S))) and not bool(cov.registration.valid)
    assert int(np.max(np.asarray(cov.scores))) == -1  # no placement without a camera height
    plain = {k: float(np.asarray(getattr(cov.registration, k))) for k in ("rms", "scale_ratio", "spread")}
    plain.update(valid=False, num_structure=0, peak_score=int(np.max(np.asarray(cov.scores))), null_threshold=1.0)
    why = G.covisible_reason(plain, G.GeometryOptions())
    assert why and "\n" not in why and "failed" in why
    # a handful of points: valid ICP maybe, but too few structure inliers
    w = np.zeros(len(src), np.float32)
    w[:10] = 1.0
    a2 = a._replace(weights=jnp.asarray(w))
    _, b2 = _clouds(src, dst[:4096], aa, ab, Ba, Bb, 2.0)
    cov = G.register_covisible(a2, b2, np.pi, 1.0, jnp.zeros(2), 10.0)
    reg = {k: np.asarray(v).item() for k, v in cov.registration._asdict().items() if np.asarray(v).ndim == 0}
    reg.update(peak_score=max(int(np.max(np.asarray(cov.scores))), 1), null_threshold=0.0)
    assert np.all(np.isfinite(np.asarray(cov.registration.S)))
    why = G.covisible_reason(reg, G.GeometryOptions())
    assert why is not None and "\n" not in why


def test_peak_icp_drops_a_placement_whose_scale_left_the_verdicts_range():
    """A peak whose ICP moved the scale out of ``[1 / max_scale_ratio, max_scale_ratio]`` of
    its start's is no placement (−1), every other peak as without the rule: against a NumPy
    recomputation of ``s / s₀`` from the unrestricted placements, with the bound put between
    the peaks' own scale changes."""
    rng = np.random.default_rng(12)
    S_true, _, src, dst, aa, ab, Ba, Bb = _reverse_pass(rng, 2.0, 0.7, 2.5)
    a, b = _clouds(src, dst[:4096], aa, ab, Ba, Bb, 2.0)
    off = sim3.from_rst(jnp.eye(3), jnp.asarray(Bb[:, 0] * 4.0, jnp.float32), 1.15)
    psi, sigma, tau = G.edge_prior(sim3.compose(off, S_true), a, b)
    free = G.GeometryOptions(max_scale_ratio=100.0)
    S0, corr = G.bev_starts(a, b, psi, sigma, tau, 12.0, free)
    loose = G.peak_icp(a, b, S0, corr, free)
    change = np.abs(np.log(np.asarray(sim3.scale(loose.S), np.float64) / np.asarray(sim3.scale(S0), np.float64)))
    placed = np.asarray(loose.scores) >= 0
    assert placed.sum() >= 2 and np.ptp(change[placed]) > 1e-4, change  # two peaks whose changes differ
    bound = float(np.exp(np.mean(np.sort(change[placed])[-2:])))  # between the two largest changes
    tight = G.peak_icp(a, b, S0, corr, free.replace(max_scale_ratio=bound))
    want = np.where(change <= np.log(bound), np.asarray(loose.scores), -1)
    np.testing.assert_array_equal(np.asarray(tight.scores), want)
    assert (np.asarray(tight.scores) == -1).sum() == (~placed).sum() + 1
    np.testing.assert_array_equal(np.asarray(tight.S), np.asarray(loose.S))  # the same ICP, only scored


def test_batched_placements_equal_one_pair_at_a_time():
    """``starts_batch`` + ``peaks_batch`` (chunks gathered from stacked clouds, the target's
    spectrum computed once by ``bev_spectrum``) give each job's ``place_covisible`` result."""
    rng = np.random.default_rng(21)
    _, _, src, dst, aa, ab, Ba, Bb = _reverse_pass(rng, 2.0, 0.3, 1.0)
    n = min(len(src), len(dst))
    a, b = _clouds(src[:n], dst[:n], aa, ab, Ba, Bb, 2.0)
    stack = jax.tree_util.tree_map(lambda x, y: jnp.stack([x, y]), a, b)
    o = G.GeometryOptions()
    spectra = jax.vmap(lambda c: G.bev_spectrum(c, o))(stack)
    src_i, dst_i = jnp.array([0, 0, 1]), jnp.array([1, 1, 0])
    psi, sigma = jnp.array([np.pi, np.pi - 0.03, 0.2]), jnp.array([1.0, 1.1, 0.9])
    tau, window = jnp.array([[0.0, 0.0], [3.0, -1.0], [0.0, 2.0]]), jnp.array([10.0, 6.0, 12.0])
    S0, corr = G.starts_batch(stack, spectra, src_i, dst_i, psi, sigma, tau, window, o)
    got = G.peaks_batch(stack, src_i, dst_i, S0, corr, o)
    for k in range(3):
        one = (a, b) if int(src_i[k]) == 0 else (b, a)
        want = G.place_covisible(*one, psi[k], sigma[k], tau[k], window[k], o)
        np.testing.assert_array_equal(np.asarray(got.scores[k]), np.asarray(want.scores))
        np.testing.assert_allclose(np.asarray(got.S[k]), np.asarray(want.S), atol=2e-4)
        np.testing.assert_allclose(np.asarray(corr[k]), np.asarray(want.correlation), atol=1e-3)


def test_placement_moments_closed_form():
    """Placements ``S_k = S_best exp(δ_k)`` with known ``δ_k`` (a street slid along x): the mean
    offset and covariance are NumPy's mean and (biased) covariance of the plausible ``δ_k``
    only, the covariance rank one along the slide."""
    S_best = sim3.from_rst(
        jnp.asarray(_rodrigues(np.array([0.0, 0, 1]), 2.5), jnp.float32), jnp.array([4.0, -2, 1]), 1.7
    )
    deltas = np.zeros((4, 7), np.float32)
    deltas[1, 0], deltas[2, 0], deltas[3, :] = 3.0, -6.0, [1, 2, 3, 0.1, 0.2, 0.3, 0.05]
    S = sim3.compose(S_best[None], sim3.exp(jnp.asarray(deltas)))
    plausible = np.array([True, True, True, False])
    mean, cov = (np.asarray(x) for x in G.placement_moments(S, jnp.asarray(plausible), 0))
    d = deltas[plausible].astype(np.float64)
    np.testing.assert_allclose(mean, d.mean(0), atol=2e-5)
    np.testing.assert_allclose(cov, np.cov(d.T, bias=True), atol=2e-4)
    assert mean[0] == pytest.approx(-1.0, rel=1e-4) and cov[0, 0] == pytest.approx((1 + 16 + 25) / 3, rel=1e-4)
    assert np.linalg.matrix_rank(cov, tol=1e-3) == 1
    alone = G.placement_moments(S, jnp.array([True, False, False, False]), 0)
    assert all(np.all(np.asarray(x) == 0) for x in alone)


def test_graph_edge_is_the_placements_mean_widened_along_the_slide(x64):
    """A registration edge with plausible placements along the street: the graph's edge is
    ``S exp(δ̄)``, its information ``(Ω_reg⁻¹ + Σ_P + Σ_W)⁻¹`` (PCM's covariance about ``S``:
    that plus ``δ̄ δ̄ᵀ``) — the direction across the street and yaw keep the information of the
    residuals and the chunks' model error, the slide direction keeps little.  Against NumPy / closed forms: ``Ω_reg`` from the core
    function, ``Σ_W`` diagonal."""
    from swiftjax.align.covariance import umeyama_information
    from swiftjax.loops.verification import VerificationConfig
    from swiftjax.pipeline.loop_geometry import _EdgeStats, edge_covariance, graph_edge

    S = np.array([1.0, -2, 0.5, 0, 0, np.sin(0.3), np.cos(0.3), 1.25])
    reg = G.Registration(
        S=jnp.asarray(S),
        rms=jnp.float32(0.1),
        inlier_ratio=jnp.float32(0.6),
        num_inliers=jnp.int32(800),
        num_structure=jnp.int32(400),
        spread=jnp.float32(0.1),
        scale_ratio=jnp.float32(1.0),
        valid=jnp.asarray(True),
        src_mean=jnp.array([0.0, 0.0, 5.0]),
        src_covariance=jnp.diag(jnp.array([100.0, 9.0, 4.0])),
        num_points=jnp.int32(1024),
        axis=jnp.array([1.0, 0.0, 0.0]),
        axis_variance=jnp.float32(25.0),
        structure_mean=jnp.zeros(3),
    )
    slide = np.zeros((7, 7))
    slide[0, 0] = 16.0  # 4 units along x
    offset = np.array([-2.0, 0, 0, 0, 0, 0, 0])
    extents = np.array([3.0, 5.0])
    plain = np.asarray(  # Ω_reg: the registration's residuals alone
        umeyama_information(1.25, 800.0, 0.1, reg.src_mean, reg.src_covariance, pixels_per_sample=1.0).information
    )
    none = np.zeros((7, 7))
    Z0, warped = graph_edge({"_stats": _EdgeStats(reg, 1.0, np.zeros(7), none, extents, none)}, 1.0)
    Z, wide = graph_edge({"_stats": _EdgeStats(reg, 1.0, offset, slide, extents, none)}, 1.0)
    line = np.asarray(G.straight_covariance(S, reg.axis, reg.axis_variance, reg.structure_mean, 0.01))
    _, straight = graph_edge({"_stats": _EdgeStats(reg, 1.0, np.zeros(7), none, extents, line)}, 1.0)
    d = VerificationConfig()
    # Σ_W in closed form: chunk a's extent in its units, chunk b's divided by the scale
    warp = np.diag(
        [d.odo_sigma_trans**2 * (3.0**2 + (5.0 / 1.25) ** 2)] * 3
        + [2 * d.odo_sigma_rot**2] * 3
        + [2 * d.odo_sigma_scale**2]
    )
    np.testing.assert_allclose(np.linalg.inv(warped), np.linalg.inv(plain) + warp, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.linalg.inv(wide), np.linalg.inv(plain) + warp + slide, rtol=1e-9, atol=1e-12)
    cov_p, cov_w = np.linalg.inv(warped), np.linalg.inv(wide)
    assert cov_w[0, 0] == pytest.approx(cov_p[0, 0] + 16.0)
    # straight structure: Σ_L added to the same covariance (the slide and the scale left free)
    np.testing.assert_allclose(np.linalg.inv(straight), np.linalg.inv(plain) + warp + line, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cov_w[1:, 1:], cov_p[1:, 1:], rtol=1e-9)
    # the edge: S itself without an offset; S exp(δ̄) = S moved by -2 along its own x (rotated, scaled)
    np.testing.assert_allclose(Z0, S, atol=1e-12)
    R = np.array([[np.cos(0.6), -np.sin(0.6), 0], [np.sin(0.6), np.cos(0.6), 0], [0, 0, 1]])
    np.testing.assert_allclose(Z[:3], S[:3] + 1.25 * R @ np.array([-2.0, 0, 0]), atol=1e-9)
    np.testing.assert_allclose(Z[3:], S[3:], atol=1e-12)
    # PCM's covariance about the verified S: the graph's plus the mean's offset, Σ + δ̄ δ̄ᵀ
    about_S = edge_covariance(_EdgeStats(reg, 1.0, offset, slide, extents, none), 1.0)
    want = np.linalg.inv(plain) + warp + slide
    want[0, 0] += 4.0
    np.testing.assert_allclose(about_S, want, rtol=1e-9, atol=1e-12)


def test_warp_covariance_is_the_drift_model_over_each_chunk():
    """``Σ_W``: the temporal drift model (``pcm.odometry_covariance``) of two straight paths as
    long as the chunks, chunk ``b``'s in chunk ``a``'s units, equal to the closed form (float32
    here, without a dtype warning)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = np.asarray(G.warp_covariance(2.0, 6.0, 0.5, 0.01, 0.05, 0.04))
    assert got.dtype == np.float32
    want = np.diag([0.05**2 * (4.0 + 144.0)] * 3 + [2e-4] * 3 + [2 * 0.04**2])
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert np.allclose(np.asarray(G.warp_covariance(0.0, 0.0, 1.0, 0.01, 0.05, 0.04))[:3, :3], 0.0, atol=1e-20)


def test_null_early_stop_is_exact():
    """The null may stop early (``_null_settled``) only where its bound exceeds every sample
    whatever the samples (Samuelson's inequality): then a candidate at or below some sample is
    rejected by the complete null.  Checked against ``null_threshold`` on random and extreme
    samples; the rule refuses where it would not hold (large k or large α)."""
    from swiftjax.loops.null import null_threshold
    from swiftjax.pipeline.loop_geometry import _null_settled

    assert _null_settled(0.01, 8) and not _null_settled(0.01, 16) and not _null_settled(0.3, 8)
    assert not _null_settled(0.01, 2)
    rng = np.random.default_rng(5)
    for k in (3, 5, 8):
        assert _null_settled(0.01, k)
        for trial in range(200):
            n = 256
            x = rng.integers(0, 80, k) if trial % 2 else np.r_[np.zeros(k - 1), rng.integers(1, 200)]
            th = null_threshold(x / n, np.ones(k), np.full(k, n), 0.01, 0.0).threshold * n
            assert th >= x.max() - 1e-9


def test_registered_null_stops_exactly():
    """``RegisteredNull.numbers`` tests its samples one at a time and stops at the first in
    view at or above the candidate's agreement; the verdict (``a > registered_null_threshold``)
    is the complete bound's (``null_threshold`` over every sample) on random samples, some out
    of view, for agreements around them, and its tests are never more than the samples."""
    from types import SimpleNamespace

    from swiftjax.loops.null import null_threshold
    from swiftjax.loops.options import VerificationConfig
    from swiftjax.pipeline.loop_geometry import RegisteredNull
    from swiftjax.pipeline.rundir import StageTimer

    rng = np.random.default_rng(11)
    v = VerificationConfig()
    stopped = 0
    for trial in range(300):
        n = int(rng.integers(0, 9))
        samples = np.c_[
            rng.beta(2, 12, n), rng.choice([0.05, 0.9], n, p=[0.2, 0.8]), rng.integers(1, 2000, n)
        ]  # pairs seen (1: a refinement that fails)
        tested = []

        class Fed(RegisteredNull):
            def _refine(self, k0, k1):
                return [(k, np.zeros(8)) for k in range(k0, k1) if samples[k, 2] > 300]  # some refinements fail

            def _test(self, target, S):
                tested.append(target)
                return tuple(samples[target])

        null = Fed(SimpleNamespace(timer=StageTimer()), 0, np.arange(n), np.zeros((n, 8)), None, None, None, v)
        valid = samples[samples[:, 2] > 300]
        full = null_threshold(valid[:, 0], valid[:, 1], valid[:, 2], v.null_false_alarm, v.min_overlap)
        for a in rng.uniform(0.0, 0.5, 3):
            got = null.numbers(float(a))
            assert (a > got["registered_null_threshold"]) == (a > full.threshold), (trial, a)
            if got.get("registered_null_stopped"):  # stopped before the last sample, at one >= a
                assert len(tested) < len(valid) and got["registered_null_threshold"] >= a
            else:
                assert got["registered_null_threshold"] == pytest.approx(full.threshold, nan_ok=True)
        assert len(tested) == len(set(tested)) <= len(valid)
        stopped += len(tested) < len(valid)
    assert stopped > 10


def test_bev_starts_z_score_against_numpy_loop():
    """``bev_starts`` against a NumPy loop: ``a``'s raster per (yaw, scale), the circular
    overlap count ``C(m) = Σ_x D_b[x + m] D_a[x]`` by direct sums, ``z = (C − N p)/sqrt(N p (1 −
    p))`` with ``N = Σ D_a`` and ``p = Σ D_b / n²``; the first start is ``_start`` at the
    (yaw, scale, translation) of the largest ``z`` in the window, and its returned count is
    that ``C``."""
    n, c = 16, 0.75
    o = G.GeometryOptions(
        bev_cells=n, bev_cell=c, yaw_steps=3, yaw_search=10.0, scale_steps=3, scale_search=0.2, peaks=2
    )
    rng = np.random.default_rng(30)
    pa = np.c_[rng.uniform(-4, 4, (60, 2)), rng.uniform(0.5, 2, 60)].astype(np.float32)
    pb = np.c_[rng.uniform(-5, 5, (90, 2)), rng.uniform(0.5, 2, 90)].astype(np.float32)
    a = G.ChunkCloud(jnp.asarray(pa), jnp.ones(60), jnp.zeros(3), jnp.eye(3), jnp.float32(1.0))
    b = G.ChunkCloud(jnp.asarray(pb), jnp.ones(90), jnp.zeros(3), jnp.eye(3), jnp.float32(1.0))

    def raster(xy):
        D = np.zeros((n, n))
        for x, y in xy:
            i, j = int(np.floor(x / c)) + n // 2, int(np.floor(y / c)) + n // 2
            if 0 <= i < n and 0 <= j < n:
                D[i, j] = 1.0
        return D

    Db = raster(pb[:, :2].astype(np.float64))
    Db = np.maximum(Db, np.maximum(np.roll(Db, 1, 0), np.roll(Db, -1, 0)))
    Db = np.maximum(Db, np.maximum(np.roll(Db, 1, 1), np.roll(Db, -1, 1)))
    p = Db.sum() / n**2
    psi, sigma, tau, window = 0.3, 1.1, np.array([0.5, -0.75]), 4.0
    shifts = np.fft.fftfreq(n, 1.0 / n) * c
    best = (-np.inf, None)
    for y in np.deg2rad(np.linspace(-10, 10, 3)):
        for e in np.linspace(-0.2, 0.2, 3):
            R = np.array([[np.cos(psi + y), -np.sin(psi + y)], [np.sin(psi + y), np.cos(psi + y)]])
            Da = raster(sigma * np.exp(e) * pa[:, :2].astype(np.float64) @ R.T)
            N = Da.sum()
            for mi in range(n):
                for mj in range(n):
                    t = np.array([shifts[mi], shifts[mj]])
                    if np.sum((t - tau) ** 2) > window**2:
                        continue
                    C = sum(Db[(i + mi) % n, (j + mj) % n] * Da[i, j] for i in range(n) for j in range(n))
                    z = (C - N * p) / np.sqrt(N * p * (1 - p))
                    if z > best[0] + 1e-6:
                        best = (z, (psi + y, sigma * np.exp(e), t, C))
    spectrum = jnp.fft.rfft2(jnp.asarray(Db, jnp.float32))
    S0, count = G.bev_starts(a, b, psi, sigma, jnp.asarray(tau), window, o, spectrum)
    yaw, scale, t, C = best[1]
    want = G._start(a, b, jnp.float32(yaw), jnp.float32(scale), jnp.asarray(t, jnp.float32))
    np.testing.assert_allclose(np.asarray(S0[0]), np.asarray(want), atol=1e-4)
    assert float(count[0]) == pytest.approx(C, abs=1e-3)


def test_window_on_grid_against_the_grid_translations():
    """``window_on_grid`` against the grid enumerated: false only where no translation
    ``c {−n/2, …, n/2 − 1}²`` lies within the window (what makes skipping such a job exact), and
    true wherever one does; and a job it rejects gets ``bev_starts``' "no placement" (every
    peak's count −1) whatever the clouds."""
    n, c = 16, 0.75
    o = G.GeometryOptions(bev_cells=n, bev_cell=c, yaw_steps=3, scale_steps=3, peaks=2)
    shifts = np.fft.fftfreq(n, 1.0 / n) * c
    grid = np.stack(np.meshgrid(shifts, shifts, indexing="ij"), -1).reshape(-1, 2)
    rng = np.random.default_rng(32)
    tau = rng.uniform(-14.0, 14.0, (400, 2)).astype(np.float32)
    window = rng.uniform(0.2, 4.0, 400).astype(np.float32)
    got = np.asarray(G.window_on_grid(tau, window, o))
    inside = np.any(np.sum((grid[None] - tau[:, None]) ** 2, -1) <= window[:, None] ** 2, -1)
    assert np.all(got[inside]), "a window holding a grid translation must be searched"
    assert 50 < np.sum(~got) < 350, "both outcomes must be exercised"
    assert np.sum(inside) < np.sum(got), "the one-cell margin keeps some empty windows: never the other way"
    pa = np.c_[rng.uniform(-4, 4, (60, 2)), rng.uniform(0.5, 2, 60)].astype(np.float32)
    a = G.ChunkCloud(jnp.asarray(pa), jnp.ones(60), jnp.zeros(3), jnp.eye(3), jnp.float32(1.0))
    for k in np.flatnonzero(~got)[:3]:
        _, count = G.bev_starts(a, a, 0.0, 1.0, jnp.asarray(tau[k]), window[k], o)
        np.testing.assert_array_equal(np.asarray(count), -1.0)


def test_bev_starts_scale_is_unbiased_from_the_true_prior():
    """A street seen from above is lines (facades, kerbs, poles): a raster scaled up covers more
    cells and overlaps more of the target's dilated raster, so the raw overlap count picks the
    largest scale tried.  From the true prior (yaw, scale and translation exact), the z-score
    picks the true scale (δ = 0) for the best start, on both driving directions."""
    rng = np.random.default_rng(31)
    for s_true in (2.0, 0.5):
        S_true, R_true, src, dst, aa, ab, Ba, Bb = _reverse_pass(rng, s_true, 0.0, 0.0)
        a, b = _clouds(src, dst[:4096], aa, ab, Ba, Bb, s_true)
        psi, sigma, tau = G.edge_prior(S_true, a, b)
        o = G.GeometryOptions(scale_steps=5, scale_search=0.18)
        S0, count = G.bev_starts(a, b, psi, sigma, tau, 8.0, o)
        assert float(count[0]) > 0
        assert float(sim3.scale(S0[0])) == pytest.approx(s_true, rel=1e-4)


def test_scale_sweep_against_numpy_loop():
    """``scale_sweep``'s scores against a NumPy loop (brute-force nearest neighbours, Tukey
    score of the source rescaled about its weighted centroid), and its choice: the best scale,
    the unscaled start kept on a tie."""
    rng = np.random.default_rng(32)
    src = rng.uniform(-5, 5, (200, 3)).astype(np.float32)
    w = (rng.uniform(size=200) > 0.2).astype(np.float32)
    dst = (1.06 * src + np.float32([0.3, -0.2, 0.1])).astype(np.float32)
    S = sim3.from_rst(jnp.eye(3), jnp.asarray([0.3, -0.2, 0.1], jnp.float32), 1.0)
    S_best, scores = G.scale_sweep(src, w, dst, np.ones(200, np.float32), S, 0.5, 0.09, 7)
    m = (w[:, None] * src).sum(0) / w.sum()
    want = []
    for d in np.linspace(-0.09, 0.09, 7):
        y = 1.0 * (m + np.exp(d) * (src - m)) + np.array([0.3, -0.2, 0.1])
        r = np.sqrt(((y[:, None, :] - dst[None, :, :]) ** 2).sum(-1)).min(1)
        want.append(np.sum(w * np.where(r < 0.5, (1 - (r / 0.5) ** 2) ** 2, 0.0)))
    np.testing.assert_allclose(np.asarray(scores), want, rtol=1e-4, atol=1e-3)
    k = int(np.argmax(want))
    assert float(sim3.scale(S_best)) == pytest.approx(np.exp(np.linspace(-0.09, 0.09, 7)[k]), rel=1e-5)
    flat, _ = G.scale_sweep(src, np.zeros(200, np.float32), dst, np.ones(200, np.float32), S, 0.5, 0.09, 7)
    np.testing.assert_allclose(np.asarray(flat), np.asarray(S), atol=1e-6)  # all scores 0: S kept


def test_refine_placement_recovers_the_scale_the_icp_keeps():
    """The reverse street (known Sim(3), closed form) started 7 % too large in scale (half a
    bird's-eye scale step) at the true rotation and centre: the robust ICP alone keeps most of
    the scale error; with the scale sweep first the refined scale is within 1 % of the truth."""
    rng = np.random.default_rng(33)
    s_true = 2.0
    S_true, R_true, src, dst, aa, ab, Ba, Bb = _reverse_pass(rng, s_true, 0.0, 0.0)
    a, b = _clouds(src[:1024], dst[:4096], aa, ab, Ba, Bb, s_true)
    m = jnp.asarray(src[:1024].mean(0))
    e = float(np.exp(0.07))
    S0 = sim3.compose(S_true, sim3.from_rst(jnp.eye(3), (1.0 - e) * m, e))  # 7 % larger about the centroid
    with_sweep = G.refine_placement(a, b, S0, s_true, G.GeometryOptions())
    without = G.refine_placement(a, b, S0, s_true, G.GeometryOptions(refine_scale_steps=1))
    assert abs(float(sim3.scale(with_sweep.S)) / s_true - 1) < 0.01
    assert abs(float(sim3.scale(without.S)) / s_true - 1) > 0.03  # measured 4.6 %: the ICP keeps 2/3 of it


def test_redundant_geometric_edges_beside_token_edges_are_rejected():
    """``redundant_geometry``: an accepted geometric candidate whose chunks are each within one
    chunk of an accepted token candidate's (either order) is rejected with a one-line reason;
    one two chunks off, one beside a REJECTED token candidate, and the token candidates
    themselves are untouched (checked against the rule written out as a loop)."""
    from swiftjax.pipeline.loop_closure import redundant_geometry

    recs = [
        {"chunk_i": 75, "chunk_j": 9, "accepted": True, "source": "tokens"},
        {"chunk_i": 8, "chunk_j": 76, "accepted": True, "source": "geometry"},  # beside 75/9
        {"chunk_i": 77, "chunk_j": 9, "accepted": True, "source": "geometry"},  # 2 chunks off
        {"chunk_i": 40, "chunk_j": 3, "accepted": False, "source": "tokens"},
        {"chunk_i": 40, "chunk_j": 4, "accepted": True, "source": "geometry"},  # beside a rejected one
        {"chunk_i": 60, "chunk_j": 20, "accepted": False, "source": "geometry", "reason": "null"},
    ]
    before = [dict(r) for r in recs]
    redundant_geometry(recs)
    for r, b in zip(recs, before):
        near = (
            b["source"] == "geometry"
            and b["accepted"]
            and any(
                t["source"] == "tokens"
                and t["accepted"]
                and abs(max(t["chunk_i"], t["chunk_j"]) - max(b["chunk_i"], b["chunk_j"])) <= 1
                and abs(min(t["chunk_i"], t["chunk_j"]) - min(b["chunk_i"], b["chunk_j"])) <= 1
                for t in before
            )
        )
        assert r["accepted"] == (b["accepted"] and not near)
        if near:
            assert r["reason"].startswith("redundant") and "\n" not in r["reason"]
        else:
            assert r.get("reason") == b.get("reason")
    assert [r["accepted"] for r in recs] == [True, False, True, False, True, False]


def test_nearest_is_argmin_bitwise_and_the_numpy_loop():
    """``_nearest``'s block-wise index is ``argmin``'s, bit for bit, for finite points: ties
    (duplicate target points, across a block boundary), masked targets, an all-masked target,
    a target count that is not a multiple of the block (padded), inside ``vmap`` as the ICP
    runs it; a non-finite source point gets a non-finite distance (never an inlier); and the
    nearest point of a float64 NumPy loop."""
    rng = np.random.default_rng(11)
    y = rng.normal(size=(300, 3)).astype(np.float32) * 3
    dst = rng.normal(size=(500, 3)).astype(np.float32) * 3
    dst[250:260] = dst[240:250]  # exact ties: the first index wins
    y[:5] = dst[240:245]
    w = (rng.uniform(size=500) > 0.2).astype(np.float32)
    w[240:250] = 1.0
    y[7] = np.nan
    y[8, 1] = np.inf

    @jax.jit
    def argmin(y, d, w):  # the former _nearest: same d², argmin's pair reduction
        d2 = (y[:, 0:1] - d[None, :, 0]) ** 2 + (y[:, 1:2] - d[None, :, 1]) ** 2 + (y[:, 2:3] - d[None, :, 2]) ** 2
        d2 = jnp.where(w[None, :] > 0, d2, jnp.inf)
        return jnp.argmin(d2, -1), jnp.sqrt(jnp.min(d2, -1))

    for ww in (w, np.zeros_like(w)):
        k, r = jax.jit(G._nearest)(jnp.asarray(y), jnp.asarray(dst), jnp.asarray(ww))
        k0, r0 = argmin(jnp.asarray(y), jnp.asarray(dst), jnp.asarray(ww))
        fin = np.all(np.isfinite(y), -1)
        np.testing.assert_array_equal(np.asarray(k)[fin], np.asarray(k0)[fin])
        np.testing.assert_array_equal(np.asarray(r)[fin], np.asarray(r0)[fin])
        assert not np.any(np.isfinite(np.asarray(r)[~fin]))
    assert G._block_size(500) == 32 and 500 % 32 and 240 // 32 != 259 // 32  # padded; ties span blocks
    ys, ds = np.stack([y, y[::-1]]), np.stack([dst, dst[::-1]])
    kv, rv = jax.jit(jax.vmap(G._nearest))(jnp.asarray(ys), jnp.asarray(ds), jnp.asarray(np.stack([w, w[::-1]])))
    k0, r0 = jax.vmap(argmin)(jnp.asarray(ys), jnp.asarray(ds), jnp.asarray(np.stack([w, w[::-1]])))
    fin = np.all(np.isfinite(ys), -1)
    np.testing.assert_array_equal(np.asarray(kv)[fin], np.asarray(k0)[fin])
    np.testing.assert_array_equal(np.asarray(rv)[fin], np.asarray(r0)[fin])
    k = np.asarray(k := jax.jit(G._nearest)(jnp.asarray(y), jnp.asarray(dst), jnp.asarray(w))[0])
    for p in range(len(y)):
        if not np.all(np.isfinite(y[p])):
            continue
        d = np.where(w > 0, np.sum((y[p].astype(np.float64) - dst.astype(np.float64)) ** 2, -1), np.inf)
        assert abs(d[k[p]] - d.min()) <= 1e-4 * max(d.min(), 1.0)
    assert list(k[:5]) == list(range(240, 245))


def test_closed_pairs_are_exactly_the_ones_redundant_geometry_rejects():
    """``loop_geometry.split_closed`` leaves unregistered exactly the gated pairs that
    ``redundant_geometry`` rejects when every candidate is accepted (random token pairs and
    gated pairs); each such pair's record is a rejected geometric candidate with a one-line
    reason naming the token edge, no ``Z`` (no edge) and its chunks' middle frames."""
    from swiftjax.pipeline.loop_closure import redundant_geometry
    from swiftjax.pipeline.loop_geometry import split_closed

    rng = np.random.default_rng(40)
    T = 60
    ids = np.arange(T * 10).reshape(T, 10)
    for _ in range(20):
        tokens = [(int(a), int(a) - int(d)) for a, d in zip(rng.integers(10, T, 6), rng.integers(2, 10, 6))]
        gated = sorted({(int(a), int(a) - int(d)) for a, d in zip(rng.integers(10, T, 80), rng.integers(2, 10, 80))})
        pairs = [(ci, cj, 3.0) for ci, cj in gated]
        kept, unregistered = split_closed(pairs, tokens, ids)
        assert sorted([(a, b) for a, b, _ in kept] + [(r["chunk_i"], r["chunk_j"]) for r in unregistered]) == gated
        recs = [{"chunk_i": a, "chunk_j": b, "accepted": True, "source": "tokens"} for a, b in tokens]
        recs += [{"chunk_i": b, "chunk_j": a, "accepted": True, "source": "geometry"} for a, b in gated]  # either order
        redundant_geometry(recs)
        rejected = {(r["chunk_j"], r["chunk_i"]) for r in recs if r["source"] == "geometry" and not r["accepted"]}
        assert {(r["chunk_i"], r["chunk_j"]) for r in unregistered} == rejected
        for r in unregistered:
            assert r["source"] == "geometry" and r["accepted"] is False and "Z" not in r
            assert r["reason"].startswith("not registered") and "\n" not in r["reason"]
            y, x = r["_closed_by"][1], r["_closed_by"][0]
            assert f"chunks {y} and {x}" in r["reason"] and r["_closed_by"] in tokens
            assert (r["i"], r["j"]) == (ids[r["chunk_i"], 5], ids[r["chunk_j"], 5])


def _loop_candidate(ci, cj, source, t=(0.0, 0.0, 0.0), agreement=0.9):
    """A candidate record that passes the dense test (``t``: its edge's translation; the chain
    is the identity, so any ``t`` far from 0 is pairwise inconsistent with a ``t = 0`` one)."""
    return {
        "i": 10 * ci + 5,
        "j": 10 * cj + 5,
        "score": 0.5,
        "chunk_i": ci,
        "chunk_j": cj,
        "source": source,
        "Z": [*t, 0.0, 0.0, 0.0, 1.0, 1.0],
        "quality_valid": True,
        "quality_min_fraction": 1.0,
        "dense_agreement": agreement,
        "dense_overlap": 0.9,
    }


@pytest.mark.parametrize("case", ["closed", "rejected jointly"])
def test_decide_with_geometry_equals_the_unpruned_decision(case, monkeypatch):
    """``loop_closure._decide_with_geometry`` with a stand-in registration (the records below;
    the real ``split_closed``): the pairs beside a provisionally accepted token candidate are
    never registered, and the verdicts equal those of the unpruned path (every gated pair
    registered, one joint decision).  ``"rejected jointly"``: the lone token candidate is
    accepted alone but pairwise inconsistent with two geometric edges, so the joint decision
    rejects it; the pairs left unregistered beside it are then registered and accepted, as
    without the prune (21/5 verified, 20/6, rejected by its dense test alone, a sibling of
    21/5: :mod:`swiftjax.loops.verification`, "Siblings")."""
    from types import SimpleNamespace

    from swiftjax.pipeline import loop_closure, loop_geometry
    from swiftjax.pipeline.config import PipelineConfig
    from swiftjax.pipeline.rundir import StageTimer

    T = 50
    ids = np.arange(T * 10).reshape(T, 10)
    bad = (300.0, 0.0, 0.0) if case == "rejected jointly" else (0.0, 0.0, 0.0)
    tokens = [_loop_candidate(20, 5, "tokens", bad)]
    table = {
        (21, 5): _loop_candidate(21, 5, "geometry"),  # beside the token candidate
        (20, 6): _loop_candidate(20, 6, "geometry", agreement=0.2),  # beside it, rejected anyway
        (40, 10): _loop_candidate(40, 10, "geometry"),
        (42, 12): _loop_candidate(42, 12, "geometry"),
    }
    registered: list[list[tuple[int, int]]] = []

    def candidates(ctx, K_ref, taken, verification, options=None, chain=None, closed=(), only=None, ahead=None):
        pairs = [(ci, cj, 3.0) for ci, cj in table if (ci, cj) not in taken]
        pairs = [p for p in pairs if only is None or (p[0], p[1]) in only]
        pairs, unregistered = loop_geometry.split_closed(pairs, closed, ids)
        registered.append([(ci, cj) for ci, cj, _ in pairs])
        return [dict(table[ci, cj]) for ci, cj, _ in pairs] + unregistered

    monkeypatch.setattr(loop_geometry, "candidates", candidates)
    config = PipelineConfig(loop_geometry=True, loop_siblings=True)  # siblings (off by default) through both paths
    ctx = SimpleNamespace(config=config, timer=StageTimer(), log=lambda s: None)
    relative = np.tile([0, 0, 0, 0, 0, 0, 1, 1.0], (T - 1, 1))
    temporal = SimpleNamespace(relative=relative, K_ref=None)
    unpruned = [dict(r) for r in tokens] + [dict(r) for r in table.values()]
    loop_closure.decide(ctx, relative, unpruned)
    want = {(r["source"], loop_geometry.chunk_pair(r)) for r in unpruned if r["accepted"]}

    geometric = loop_closure._decide_with_geometry(ctx, temporal, tokens)
    got = {(r["source"], loop_geometry.chunk_pair(r)) for r in tokens + geometric if r["accepted"]}
    assert got == want
    assert sorted(loop_geometry.chunk_pair(r) for r in geometric) == sorted(table)
    by_pair = {loop_geometry.chunk_pair(r): r for r in geometric}
    if case == "closed":
        assert want == {("tokens", (20, 5)), ("geometry", (40, 10)), ("geometry", (42, 12))}
        assert registered == [[(40, 10), (42, 12)]]  # the two beside the token edge never registered
        for pair in ((21, 5), (20, 6)):
            r = by_pair[pair]
            assert not r["accepted"] and "Z" not in r and r["reason"].startswith("not registered")
    else:
        assert want == {("geometry", (21, 5)), ("geometry", (20, 6)), ("geometry", (40, 10)), ("geometry", (42, 12))}
        assert by_pair[20, 6]["reason"].startswith("sibling of the loop of chunks 5 and 21")
        assert registered == [[(40, 10), (42, 12)], [(21, 5), (20, 6)]]
        assert all("Z" in r for r in geometric)


@pytest.mark.parametrize("k", [0, 1])
def test_compile_ahead_compiles_every_program_the_stage_runs(tmp_path, k):
    """The geometric stage's fixed-shape programs are traced on the compile-ahead thread
    (:func:`swiftjax.pipeline.loop_geometry.compile_ahead`) with the argument shapes the stage then
    passes: none is traced again when the placement, the refinement, the spreads and the dense
    test run; no compile failed and the thread is gone after ``wait``.  (42 x 140 frames:
    fewer reliable points than the registration's subsample, padded with zero-weight rows.)
    The chunks padded to their size bucket give the real chunks' clouds bitwise.  ``k``: the
    joint registration's neighbours (its clouds are the single ones merged).  With ``k = 0``
    every structure-null reject's deferred registration (a sibling's ``_register``) is run: its
    refined edge with the refinement's reason, or its dense test without the null, equal to an
    independent recompute."""
    import threading

    from swiftjax import pipeline
    from swiftjax.pipeline import export, loop_geometry, rundir, temporal
    from swiftjax.pipeline.executors import LocalExecutor
    from swiftjax.posegraph import chain_poses
    from swiftjax.synthetic import demo
    from swiftjax.synthetic.routes import loop_route
    from tests.conftest import SMALL_RUN_CONFIG, jax_log

    poses = loop_route(width=120.0, length=80.0, corner_radius=10.0, laps=1.3)
    run = demo.trajectory_run(poses, seed=3, image_hw=(42, 140))
    out = tmp_path / "run"
    pipeline.reconstruct(
        run.predictor, out, pipeline.PipelineConfig(**SMALL_RUN_CONFIG), progress=False, log=lambda _: None
    )
    config = pipeline.PipelineConfig(**SMALL_RUN_CONFIG, loop_geometry=True, loop_siblings=True)  # deferred work
    ctx = rundir.open_run(
        run.predictor, out, config, LocalExecutor(), overwrite=False, progress=False, log=lambda _: None
    )
    try:
        chain = temporal.run(ctx, export.ChunkExport(ctx))
        with jax_log(r"Finished tracing (\S+) for jit") as traced:  # (thread, program)
            jax.clear_caches()  # (the same shapes compiled by an earlier test would not be traced at all)
            o = G.GeometryOptions(neighbours=k)
            poses = chain_poses(chain.relative)
            ahead = loop_geometry.compile_ahead(ctx, chain.K_ref, o)
            records = loop_geometry.candidates(
                ctx, chain.K_ref, set(), config.verification, o, chain=poses, ahead=ahead
            )
            ahead.cancel()
            stage = [name for thread, name in traced if thread != "swiftjax-geometry-compile"]
            compiled_ahead = [name for thread, name in traced if thread == "swiftjax-geometry-compile"]
            # the chunks padded to their size bucket: the real chunks' clouds are bitwise the
            # unpadded ones (the subsample keys are prefix-stable)
            g, ids = loop_geometry.geometries(ctx, chain.K_ref, o)
            T = len(ids)
            relative = loop_geometry._relative_poses(poses, T)
            exact = loop_geometry._clouds(g, *loop_geometry._neighbour_edges(relative, T, k), o)
            size = loop_geometry._padded_chunks(T + 1)
            padded = loop_geometry._pad_chunks(g, size)
            padded = loop_geometry._clouds(
                padded, *loop_geometry._neighbour_edges(loop_geometry._relative_poses(poses, size), T, k), o
            )
            for a, b in zip(jax.tree_util.tree_leaves(exact), jax.tree_util.tree_leaves(padded)):
                np.testing.assert_array_equal(np.asarray(b)[:T], np.asarray(a))
            if k:  # the joint clouds are the single ones merged (merge_neighbours)
                single = loop_geometry._clouds(
                    g, *loop_geometry._neighbour_edges(relative, T, 0), o.replace(neighbours=0)
                )
                merged = G.merge_neighbours(single[0], *loop_geometry._neighbour_edges(relative, T, k))
                got, want = np.asarray(exact[0].points), np.asarray(merged.points)  # (one fused program: ulps)
                np.testing.assert_allclose(got, want, rtol=0, atol=1e-6 * np.abs(want).max())
                np.testing.assert_array_equal(np.asarray(exact[0].weights), np.asarray(merged.weights))
        if not k:  # a sibling's deferred registration (settle_deferred calls it once accepted)
            from swiftjax.loops import verification as V

            pending = [r for r in records if r.get("registration_pending")]
            branches = set()
            for r in pending:
                placement = list(r["Z"])
                assert r["evidence_reason"].startswith("no more structure inliers") and "accepted" not in r
                got = r.pop("_register")()
                assert r["Z"] != placement
                branches.add(got.get("quality_valid", True))
                if got.get("quality_valid") is False:  # the refinement's own reason
                    assert got["quality_reason"] == G.covisible_reason(r["registration"], o, structure_null=False)
                    continue
                # the refined edge's dense test, without its null (its view is what is tested)
                (side_i, _), (side_j, _) = (loop_geometry._frames(ctx, c, o) for c in (r["chunk_i"], r["chunk_j"]))
                plain = dataclasses.replace(config.verification, neighbours=0, agreement_rule="fixed")
                no_halves = loop_geometry._NO_HALVES
                want = V.candidate_numbers(side_i, side_j, np.asarray(r["Z"]), chain.K_ref, no_halves, no_halves, plain)
                assert got == want and "null_threshold" not in got
            assert branches == {True, False}, len(pending)  # both kinds on this route
    finally:
        ctx.close()
    assert ahead.errors == []
    assert not any(t.name == "swiftjax-geometry-compile" for t in threading.enumerate())
    ran = set(ctx.timer.seconds)
    assert {"loop geometry: placement", "loop geometry: refinement"} <= ran, ran  # the stage ran them
    assert any(r.get("accepted") is not False for r in records)  # some survived to the refinement
    # (starts_batch, _geometry and _clouds are first traced inside compile_ahead's eval_shape)
    programs = [
        *("_relative", "_priors", "peaks_batch", "slide_batch", "refine_batch", "placement_moments"),
        *("_cross_jit", "_null_jit"),
    ]
    assert set(programs) <= set(compiled_ahead), compiled_ahead  # (the dense test's null too)
    assert "act" in stage  # (the chain's x64 sim3.act is not compiled ahead: the log sees the stage's traces)
    assert [p for p in [*programs, "starts_batch"] if p in stage] == [], stage


def test_subsample_draws_without_replacement_and_pads_fewer_rows():
    """``subsample``: ``n`` distinct weighted rows when there are more, exactly the weighted rows
    (each once) padded with zero-weight rows when there are fewer, also when the input has fewer
    than ``n`` rows at all (small images; before, ``top_k`` refused ``n > N``)."""
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(50, 3)).astype(np.float32)
    w = (rng.random(50) < 0.6).astype(np.float32)
    key = jax.random.PRNGKey(1)
    for n in (10, int(w.sum()) + 5, 80):
        p, ws = (np.asarray(x) for x in G.subsample(pts, w, n, key))
        assert p.shape == (n, 3) and ws.shape == (n,)
        chosen = p[ws > 0]
        assert len(chosen) == min(n, int(w.sum()))
        weighted = {tuple(r) for r in pts[w > 0]}
        assert all(tuple(r) in weighted for r in chosen) and len({tuple(r) for r in chosen}) == len(chosen)
        if n > w.sum():
            assert {tuple(r) for r in chosen} == weighted


def test_compile_ahead_groups_wait_and_cancel():
    """``CompileAhead``: groups run in order on one thread, one after the other from the start;
    ``wait(k)`` returns once group ``k`` is done; ``cancel`` starts no further plan, waits for
    the one under way and ends the thread; a failing plan is recorded, not raised, and the next
    runs."""
    import threading

    from swiftjax.pipeline.loop_geometry import CompileAhead

    ran: list[str] = []
    gate, started = threading.Event(), threading.Event()

    def plan(name, block=False, fail=False):
        def run():
            if block:
                started.set()
                gate.wait(10)
            if fail:
                raise RuntimeError(name)
            ran.append(name)

        return run

    job = CompileAhead([[plan("a"), plan("bad", fail=True), plan("b")], [plan("c", block=True)], [plan("d")]])
    job.wait(0)
    assert ran[:2] == ["a", "b"] and job.errors == ["RuntimeError('bad')"]
    assert started.wait(10)  # the next group follows at once: "c" is under way when cancel comes
    timer = threading.Timer(0.2, gate.set)
    timer.start()
    job.cancel()
    timer.join()
    assert ran == ["a", "b", "c"]  # "c" finished, "d" never started
    assert not job._thread.is_alive() and job.seconds > 0
    job.wait(2)  # (every group counts as done after a cancel: no wait hangs)
    empty = CompileAhead([])
    empty.wait(0)
    empty.cancel()


def test_run_batched_on_threads_is_the_same_in_order():
    """``loop_geometry._run_batched`` with a thread pool (the placement's) returns the batches'
    results bit for bit and in row order, as without it and as one call on all rows: 11 rows in
    batches of 4 (the last padded and cut), a tuple output; and the pool runs the batches on
    its threads."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from swiftjax.pipeline.loop_geometry import PLACEMENT_WORKERS, _run_batched

    rng = np.random.default_rng(12)
    a = rng.normal(size=(11, 5)).astype(np.float32)
    b = rng.integers(0, 9, 11).astype(np.int32)
    names = set()

    @jax.jit
    def fn(x, k):
        return jnp.cumsum(x * x, -1), k * 2 + 1

    def on_thread(x, k):  # fn, noting the thread it runs on
        names.add(threading.current_thread().name)
        return fn(x, k)

    plain = _run_batched(fn, 4, (a, b))
    with ThreadPoolExecutor(PLACEMENT_WORKERS, thread_name_prefix="test-pool") as pool:
        pooled = _run_batched(on_thread, 4, (a, b), pool)
    whole = fn(a, b)
    for got in (plain, pooled):
        assert got[0].shape == (11, 5) and got[1].shape == (11,)
        np.testing.assert_array_equal(got[0], np.asarray(whole[0]))
        np.testing.assert_array_equal(got[1], 2 * b + 1)
    assert names and all(n.startswith("test-pool") for n in names)


def test_geometries_keep_the_stored_dtype_until_the_device(small_loop_run, tmp_path):
    """``geometries`` fills its batch buffers in the store's dtype (float16 depth and confidence,
    float32 for a chunk that had to keep it) and converts on the device: bitwise the geometry
    of float32 batches converted on the host, with the last chunk stored float32 (its batch's
    buffers widened after a float16 batch)."""
    import shutil

    from swiftjax import align, pipeline
    from swiftjax.pipeline import loop_geometry, rundir
    from swiftjax.pipeline.executors import LocalExecutor
    from swiftjax.synthetic import demo
    from swiftjax.synthetic.routes import loop_route
    from tests.conftest import SMALL_RUN_CONFIG

    src, _ = small_loop_run
    out = tmp_path / "run"
    shutil.copytree(src, out)
    poses = loop_route(width=60.0, length=40.0, corner_radius=10.0, laps=1.3)
    run = demo.trajectory_run(poses, seed=3, image_hw=(42, 140))
    config = pipeline.PipelineConfig(**SMALL_RUN_CONFIG, loop_geometry=True)
    ctx = rundir.open_run(
        run.predictor, out, config, LocalExecutor(), overwrite=False, progress=False, log=lambda _: None
    )
    try:
        store, o = ctx.store, G.GeometryOptions()
        last = ctx.schedule.num_chunks - 1  # in the second batch: its buffers widen to float32
        assert last >= loop_geometry.BATCH
        store.save("chunk", last, store.load("chunk", last), extra=store.load_extra("chunk", last), half=False)
        dtypes = [loop_geometry._frames(ctx, c, o, dtype=None)[0].depth.dtype for c in (0, last)]
        assert dtypes == [np.float16, np.float32]
        K = np.asarray(loop_geometry._frames(ctx, 0, o)[0].intrinsic[0], np.float32)
        got, ids = loop_geometry.geometries(ctx, K, o)
        T = len(ids)
        want = []
        for b0 in range(0, T, loop_geometry.BATCH):
            chunks = [min(c, T - 1) for c in range(b0, b0 + loop_geometry.BATCH)]
            frames = [loop_geometry._frames(ctx, c, o, dtype=np.float32)[0] for c in chunks]
            batch = align.ChunkFrames(*(np.stack(x) for x in zip(*frames)))
            images = np.stack([loop_geometry._images(ctx, c, o, f.depth.shape)[0] for c, f in zip(chunks, frames)])
            part = loop_geometry._geometry(batch, images, K, o)
            want.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[: min(loop_geometry.BATCH, T - b0)], part))
        want = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *want)
    finally:
        ctx.close()
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        np.testing.assert_array_equal(a, b)


def test_stored_images_are_the_geometry_pixels_and_read_back(tmp_path):
    """What the temporal stage stores for the colour test (``stored_images``) is the images at
    the geometric source's frames (``local_frames``) and pixel grid; ``_images`` reads it back,
    and ``chunk_frame`` gives each reliable point the chromaticity of its own pixel (the full
    images and the stored ones alike).  A store without them, or the colour test off
    (``colour_tolerance = 1``), gives mid grey: every pair agrees."""
    import types

    from swiftjax import align
    from swiftjax.io.chunk_store import ChunkStore
    from swiftjax.pipeline import loop_geometry
    from swiftjax.prediction import ChunkPrediction

    rng = np.random.default_rng(3)
    S, H, W, chunk = 23, 30, 50, 25
    o = G.GeometryOptions()
    images = rng.integers(0, 256, (S, H, W, 3), dtype=np.uint8)
    depth = rng.uniform(2.0, 9.0, (S, H, W)).astype(np.float32)
    K = np.array([[40.0, 0, 25], [0, 40.0, 15], [0, 0, 1]], np.float32)
    extrinsic = np.tile(np.eye(3, 4, dtype=np.float32), (S, 1, 1))
    pred = ChunkPrediction(depth, np.full((S, H, W), 2.0, np.float32), extrinsic, np.tile(K, (S, 1, 1)))
    local = loop_geometry.local_frames(S, chunk, o)
    np.testing.assert_array_equal(local, np.unique(np.round(np.linspace(0, S - 1, -(-chunk // o.frame_stride)))))
    extra = loop_geometry.stored_images(images, chunk, o)
    want = images[local][:, :: o.row_stride, :: o.column_stride]
    np.testing.assert_array_equal(extra[loop_geometry.IMAGES], want)
    store = ChunkStore(tmp_path)
    store.save("chunk", 0, pred, extra=extra)
    store.save("chunk", 1, pred)
    ctx = types.SimpleNamespace(store=store)
    shape = (len(local), H, W)
    got, stored = loop_geometry._images(ctx, 0, o, shape)
    np.testing.assert_array_equal(got, want)
    assert stored
    got, stored = loop_geometry._images(ctx, 1, o, shape)
    assert np.all(got == 128) and not stored
    got, stored = loop_geometry._images(ctx, 0, o.replace(colour_tolerance=1.0), shape)
    assert np.all(got == 128) and not stored
    assert loop_geometry.stored_images(images, chunk, o.replace(colour_tolerance=1.0)) == {}
    frames = align.ChunkFrames(depth[local], pred.conf[local], pred.intrinsic[local], extrinsic[local])
    g_full = G.chunk_frame(frames, K, o, images[local])
    g_stored = G.chunk_frame(frames, K, o, want)
    np.testing.assert_array_equal(np.asarray(g_full.colours), np.asarray(g_stored.colours))
    rgb = want.reshape(-1, 3).astype(np.float64)
    np.testing.assert_allclose(np.asarray(g_stored.colours), (rgb + 1) / (rgb.sum(1, keepdims=True) + 3), rtol=1e-6)


def _rt_matrix(R, t, s):
    """The 4 x 4 matrix of ``x -> s R x + t`` (float64)."""
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = s * np.asarray(R, np.float64), np.asarray(t, np.float64)
    return M


@pytest.mark.parametrize("k", [1, 2])
def test_merge_neighbours_against_numpy_loop(k):
    """Joint registration's clouds (:func:`swiftjax.loops.geometric.merge_neighbours` with the
    pipeline's :func:`~swiftjax.pipeline.loop_geometry._neighbour_edges`): chunk ``c``'s merged
    cloud is its own rows interleaved with each neighbour's mapped by ``G_c⁻¹ G_n`` (4 x 4
    matrices in float64, a NumPy loop), weights zero for a neighbour outside the sequence and
    for the padded chunks; origin, basis and height stay the chunk's own; the first
    ``rows(n)`` rows hold ``n`` rows of every chunk."""
    from swiftjax.pipeline import loop_geometry as lg

    rng = np.random.default_rng(7)
    T, Q, size = 5, 6, 7  # two padded chunks
    mats = []
    chain = np.zeros((T, 8))
    for c in range(T):
        R = np.asarray(jax.scipy.linalg.expm(jnp.asarray(np.cross(np.eye(3), rng.normal(size=3) * 0.5))))
        t, s = rng.normal(size=3) * 20, float(np.exp(rng.normal() * 0.3))
        mats.append(_rt_matrix(R, t, s))
        with jax.enable_x64(True):
            chain[c] = np.asarray(sim3.from_rst(jnp.asarray(R), jnp.asarray(t), s))
    clouds = G.ChunkCloud(
        rng.normal(size=(size, Q, 3)).astype(np.float32) * 5,
        (rng.random((size, Q)) > 0.2).astype(np.float32),
        rng.normal(size=(size, 3)).astype(np.float32),
        np.tile(np.eye(3, dtype=np.float32), (size, 1, 1)),
        rng.random(size).astype(np.float32) + 1,
    )
    edges, valid = lg._neighbour_edges(lg._relative_poses(chain, size), T, k)
    merged = G.merge_neighbours(clouds, edges, valid)
    offsets = [*range(-k, 0), *range(1, k + 1)]
    assert merged.points.shape == (size, (2 * k + 1) * Q, 3)
    for c in range(size):
        groups_p, groups_w = [clouds.points[c].astype(np.float64)], [clouds.weights[c]]
        for d in offsets:
            n = c + d
            if c < T and 0 <= n < T:
                M = np.linalg.inv(mats[c]) @ mats[n]
                groups_p.append(clouds.points[n] @ M[:3, :3].T + M[:3, 3])
                groups_w.append(clouds.weights[n])
            else:  # the chunk's own rows under the identity, weight 0
                groups_p.append(clouds.points[c].astype(np.float64))
                groups_w.append(np.zeros(Q, np.float32))
        want_w = np.stack(groups_w, 1).reshape(-1)
        np.testing.assert_array_equal(np.asarray(merged.weights[c]), want_w)
        got = np.asarray(merged.points[c]).reshape(Q, 2 * k + 1, 3)
        for m, p in enumerate(groups_p):
            scale = 1.0 + np.abs(p).max()
            np.testing.assert_allclose(got[:, m], p, atol=2e-5 * scale, err_msg=f"chunk {c}, group {m}")
        assert valid[c].tolist() == [c < T and 0 <= c + d < T for d in offsets]
    for field in ("origin", "basis", "height"):
        np.testing.assert_array_equal(np.asarray(getattr(merged, field)), getattr(clouds, field))
    o = G.GeometryOptions(neighbours=k)
    first = np.asarray(merged.points[2, : o.rows(2)]).reshape(2, 2 * k + 1, 3)[:, 0]
    np.testing.assert_array_equal(first, clouds.points[2, :2])  # the chunk's own first rows lead


def test_neighbours_option_range_and_rows():
    """``neighbours`` below 0 is refused naming the field; ``rows(n) = n (2k + 1)``; the
    pipeline config feeds it (``loop_geometry_neighbours``)."""
    from swiftjax import options, pipeline

    with pytest.raises(options.OptionError, match="neighbours"):
        G.GeometryOptions(neighbours=-1)
    assert G.GeometryOptions().rows(256) == 256 and G.GeometryOptions(neighbours=2).rows(256) == 1280
    assert pipeline.PipelineConfig(loop_geometry_neighbours=1).geometry.neighbours == 1
    assert pipeline.PipelineConfig().geometry == G.GeometryOptions()


def test_joint_registration_recovers_a_known_sim3_through_the_chain():
    """Three chunks of one street (poles every 6 h on both sides, a building at one end), each
    in its own gauge (yaw ±0.1 rad, scale 0.9 / 1.2, 30 h apart), merged by the chain
    (:func:`~swiftjax.loops.geometric.merge_neighbours`), registered onto the street seen from
    its other end (180 degrees, scale 2; the prior one pole spacing off along the street): the
    true Sim(3) (closed form), with about three times the single chunk's structure inliers.  With
    the neighbours placed by wrong edges (identities) the score falls: the merge is what places
    them."""
    from swiftjax.pipeline import loop_geometry as lg

    rng = np.random.default_rng(3)
    pts = []
    for k in range(-9, 10):
        for side in (-5.0, 5.0):
            n = 40
            pts.append(np.c_[k * 6.0 + rng.normal(0, 0.15, n), side + rng.normal(0, 0.15, n), rng.uniform(0, 4, n)])
    t = rng.uniform(0, 1, 400)
    pts.append(np.c_[24 + 12 * t, np.full(400, -8.0) + rng.normal(0, 0.1, 400), rng.uniform(0, 5, 400)])
    W = rng.permutation(np.concatenate(pts).astype(np.float32))

    def rigid(yaw, t, s):
        R = jnp.asarray(_rodrigues(np.array([0.0, 0, 1]), yaw), jnp.float32)
        return np.asarray(sim3.from_rst(R, jnp.asarray(t, jnp.float32), s))

    chain = np.stack([rigid(0.1, [-30, 0, 0], 0.9), rigid(0.0, [0, 0, 0], 1.0), rigid(-0.1, [30, 0, 0], 1.2)])
    Q = 1024
    points, weights = np.zeros((3, Q, 3), np.float32), np.zeros((3, Q), np.float32)
    for c, (lo, hi) in enumerate([(-45, -15), (-15, 15), (15, 45)]):
        seen = W[(W[:, 0] >= lo) & (W[:, 0] < hi)][:Q]
        points[c, : len(seen)] = np.asarray(sim3.act(sim3.inverse(jnp.asarray(chain[c])), seen))
        weights[c, : len(seen)] = 1.0
    clouds = G.ChunkCloud(
        points,
        weights,
        np.tile(np.float32([0, 0, 1]), (3, 1)),
        np.tile(np.eye(3, dtype=np.float32), (3, 1, 1)),
        np.ones(3, np.float32),
    )
    S_true = rigid(np.pi, [4.0, -3.0, 0.0], 2.0)
    dst = np.asarray(sim3.act(jnp.asarray(S_true), W[np.abs(W[:, 0]) < 50][: 3 * Q]))
    b = G.ChunkCloud(
        jnp.asarray(dst),
        jnp.ones(len(dst)),
        sim3.act(jnp.asarray(S_true), jnp.float32([0, 0, 1])),
        jnp.asarray(_rodrigues(np.array([0.0, 0, 1]), np.pi), jnp.float32),
        jnp.float32(2.0),
    )
    prior = sim3.compose(jnp.asarray(rigid(0.0, [-12.0, 0.0, 0.0], 1.0)), jnp.asarray(S_true))
    single = jax.tree_util.tree_map(lambda x: x[1], clouds)
    edges, valid = lg._neighbour_edges(lg._relative_poses(chain, 3), 3, 1)
    joint = jax.tree_util.tree_map(lambda x: x[1], G.merge_neighbours(clouds, edges, valid))
    wrong = jax.tree_util.tree_map(
        lambda x: x[1], G.merge_neighbours(clouds, np.zeros_like(edges) + sim3.identity(), valid)
    )
    o = G.GeometryOptions(neighbours=1)
    run = lambda a, opts: G.register_covisible(a, b, *G.edge_prior(prior, a, b), 12.0, opts)
    got, one, bad = run(joint, o), run(single, G.GeometryOptions()), run(wrong, o)
    M, M_true = np.asarray(sim3.as_matrix(got.registration.S)), np.asarray(sim3.as_matrix(jnp.asarray(S_true)))
    assert bool(got.registration.valid)
    np.testing.assert_allclose(M[:3, 3], M_true[:3, 3], atol=0.05)
    assert float(sim3.scale(got.registration.S)) == pytest.approx(2.0, rel=1e-3)
    assert float(got.scores.max()) > 2.5 * float(one.scores.max())
    assert float(bad.scores.max()) < 0.6 * float(got.scores.max())

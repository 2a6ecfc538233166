"""Tests for swiftjax.loops against float64 NumPy references of the paper's equations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swiftjax import loops as L
from swiftjax import sim3
from swiftjax.chunks import chunk_schedule

# ------------------------------------------------------------------------ NumPy references


def ref_l2(x):
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def ref_descriptor(tokens):
    return ref_l2(ref_l2(np.asarray(tokens, np.float64)).mean(-2))


def ref_power(g, beta):
    g = np.asarray(g, np.float64)
    return ref_l2(np.sign(g) * np.abs(g) ** beta)


def ref_whitening(G, remove, dim, eps):
    G = np.asarray(G, np.float64)
    mu = G.mean(0)
    X = G - mu
    lam, Q = np.linalg.eigh(X.T @ X / len(G))
    lam, Q = lam[::-1], Q[:, ::-1]
    kept = slice(remove, remove + dim)
    return mu, Q[:, kept] / np.sqrt(np.maximum(lam[kept], 0) + eps), lam[kept], Q[:, :remove]


def ref_detect(Z, thr, sep, r, k, nms):
    """Dense float64 reference: masked similarity, per-row top-k, threshold, sort, greedy NMS."""
    Z = ref_l2(np.asarray(Z, np.float64))
    n = len(Z)
    S = Z @ Z.T
    idx = np.arange(n)
    S = np.where(np.abs(idx[:, None] - idx[None]) > sep, S, -np.inf)
    cands = []
    for i in range(n):
        for j in np.argsort(-S[i], kind="stable")[: min(k, n)]:
            if S[i, j] > thr:
                cands.append((S[i, j], max(i, j), min(i, j)))
    cands.sort(key=lambda c: -c[0])
    out, suppressed = [], set()
    for s, i, j in cands:
        if nms == "frame":
            if i in suppressed or j in suppressed:
                continue
            suppressed.update(range(i - r, i + r + 1))
            suppressed.update(range(j - r, j + r + 1))
        elif any(abs(i - a) <= r and abs(j - b) <= r for a, b, _ in out):
            continue
        out.append((i, j, s))
    return out


def planted(n=300, d=24, seed=0, loops=((210, 30, 25), (280, 120, 12)), noise=0.15):
    """Random unit descriptors with planted revisits: frames a..a+len resemble b..b+len."""
    rng = np.random.default_rng(seed)
    Z = rng.normal(size=(n, d))
    for a, b, length in loops:
        Z[a : a + length] = Z[b : b + length] + noise * rng.normal(size=(length, d))
    return ref_l2(Z).astype(np.float32)


# ----------------------------------------------------------------------------- descriptors


def test_frame_descriptor_matches_reference(x64):
    tokens = np.random.default_rng(0).normal(size=(2, 3, 7, 16)) * np.array([1.0, 5.0, 0.1, 3.0] * 4)
    g = L.frame_descriptor(jnp.asarray(tokens))
    assert g.shape == (2, 3, 16) and g.dtype == jnp.float64
    np.testing.assert_allclose(g, ref_descriptor(tokens), rtol=1e-13, atol=1e-15)


def test_frame_descriptor_float32_and_per_token_normalisation():
    rng = np.random.default_rng(1)
    tokens = rng.normal(size=(5, 11, 32)).astype(np.float32)
    g = np.asarray(L.frame_descriptor(tokens))
    np.testing.assert_allclose(g, ref_descriptor(tokens), atol=2e-6)
    # every token is l2-normalised first, so rescaling single tokens changes nothing
    scaled = tokens * rng.uniform(0.01, 100, size=(5, 11, 1)).astype(np.float32)
    np.testing.assert_allclose(L.frame_descriptor(scaled), g, atol=2e-6)
    # bf16 tokens are accumulated in float32
    g16 = L.frame_descriptor(jnp.asarray(tokens, jnp.bfloat16))
    assert g16.dtype == jnp.float32
    np.testing.assert_allclose(g16, g, atol=2e-2)


def test_frame_descriptor_zero_tokens_stay_finite():
    g = L.frame_descriptor(jnp.zeros((2, 4, 8)))
    assert np.all(np.asarray(g) == 0)


def test_power_normalize_matches_reference(x64):
    g = np.random.default_rng(2).normal(size=(9, 33)) ** 3
    for beta in (0.5, 0.25, 1.0):
        np.testing.assert_allclose(L.power_normalize(jnp.asarray(g), beta), ref_power(g, beta), rtol=1e-13)
    unit = ref_l2(g)
    np.testing.assert_allclose(L.power_normalize(jnp.asarray(unit), 1.0), unit, rtol=1e-13)


def test_power_normalize_compresses_bursts():
    g = np.full((1, 100), 0.1, np.float32)
    g[0, 0] = 10.0  # one bursty coordinate
    share_before = ref_l2(g)[0, 0] ** 2
    share_after = float(L.power_normalize(g)[0, 0]) ** 2
    assert share_before > 0.99  # 100 / (100 + 99 * 0.01)
    assert share_after == pytest.approx(10.0 / (10.0 + 99 * 0.1), rel=1e-5)  # ~0.5


# ----------------------------------------------------------------------------- whitening


def _fit_data(n=400, d=48, seed=3):
    rng = np.random.default_rng(seed)
    scales = np.geomspace(10.0, 0.1, d)
    G = rng.normal(size=(n, d)) * scales
    G = G @ np.linalg.qr(rng.normal(size=(d, d)))[0]  # rotate: no axis-aligned structure
    return G + 5.0 * rng.normal(size=d)


def _align_signs(A, B):
    """Flip the columns of A to match B's sign (eigenvectors are defined up to sign)."""
    return A * np.sign(np.sum(A * B, axis=0, keepdims=True))


def test_fit_whitening_matches_reference(x64):
    G = _fit_data()
    w = L.fit_whitening(jnp.asarray(G), remove=2, dim=20, eps=1e-6)
    mu, W, lam, Qr = ref_whitening(G, 2, 20, 1e-6)
    assert w.projection.shape == (48, 20) and w.dim == 20 and not w.clamped
    np.testing.assert_allclose(w.mean, mu, rtol=1e-12)
    np.testing.assert_allclose(w.eigenvalues, lam, rtol=1e-10)
    np.testing.assert_allclose(_align_signs(np.asarray(w.projection), W), W, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(_align_signs(np.asarray(w.removed), Qr), Qr, atol=1e-10)
    Z = np.asarray(L.whiten(w, jnp.asarray(G)))
    ref = ref_l2((G - mu) @ W)
    np.testing.assert_allclose(np.abs(Z), np.abs(ref), atol=1e-10)


def test_whitening_identity_covariance_and_annihilates_removed(x64):
    G = _fit_data(seed=4)
    w = L.fit_whitening(jnp.asarray(G), remove=1, dim=30, eps=0.0)
    X = (G - np.asarray(w.mean)) @ np.asarray(w.projection)
    np.testing.assert_allclose(X.T @ X / len(G), np.eye(30), atol=1e-9)
    q1 = np.asarray(w.removed)[:, 0]
    assert np.max(np.abs(np.asarray(w.projection).T @ q1)) < 1e-10
    # with eps the covariance is diag(lam / (lam + eps))
    w2 = L.fit_whitening(jnp.asarray(G), remove=1, dim=30, eps=0.5)
    X2 = (G - np.asarray(w2.mean)) @ np.asarray(w2.projection)
    lam = np.asarray(w2.eigenvalues)
    np.testing.assert_allclose(X2.T @ X2 / len(G), np.diag(lam / (lam + 0.5)), atol=1e-9)


def test_whitening_float32_close_to_float64():
    G = _fit_data(seed=5).astype(np.float32)
    w = L.fit_whitening(G, remove=1, dim=16)
    mu, W, _, _ = ref_whitening(G, 1, 16, 1e-6)
    Z = np.asarray(L.whiten(w, G))
    np.testing.assert_allclose(np.abs(Z), np.abs(ref_l2((G - mu) @ W)), atol=2e-3)


def test_whitening_dim_clamped_to_rank():
    rng = np.random.default_rng(6)
    w = L.fit_whitening(rng.normal(size=(20, 16)).astype(np.float32), remove=1, dim=512)
    assert w.dim == 15 and w.clamped and w.dim_requested == 512
    w = L.fit_whitening(rng.normal(size=(10, 16)).astype(np.float32), remove=1, dim=512)
    assert w.dim == 8 and w.clamped  # rank of 10 centred samples is 9, minus 1 removed
    with pytest.raises(ValueError, match="nothing is left"):
        L.fit_whitening(rng.normal(size=(2, 16)).astype(np.float32), remove=1)


def test_whitening_max_samples_subsamples_evenly(x64):
    G = _fit_data(n=100, seed=7)
    w = L.fit_whitening(jnp.asarray(G), remove=1, dim=10, max_samples=50)
    assert w.n_samples == 50
    rows = np.round(np.linspace(0, 99, 50)).astype(int)
    np.testing.assert_allclose(w.mean, G[rows].mean(0), rtol=1e-12)


def test_fit_whitening_rejects_nan_and_bad_shapes():
    G = _fit_data(n=50, d=8, seed=8).astype(np.float32)
    G[7, 3] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf in 1 row.*row 7"):
        L.fit_whitening(G)
    # the function's own check (a host boundary, annotated loosely: not the jaxtyping hook's TypeError)
    with pytest.raises(ValueError, match=r"fit_whitening: G must be \[N, d\], got shape \(5,\)"):
        L.fit_whitening(np.zeros(5, np.float32))


def test_fit_whitening_jits():
    G = _fit_data(n=60, d=12, seed=9).astype(np.float32)
    w = jax.jit(lambda g: L.fit_whitening(g, remove=1, dim=5))(G)
    w2 = L.fit_whitening(G, remove=1, dim=5)
    np.testing.assert_allclose(np.abs(w.projection), np.abs(w2.projection), rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------------------- detection


@pytest.mark.parametrize("nms", ["pair", "frame"])
def test_detect_loops_matches_dense_reference(x64, nms):
    Z = planted(seed=10).astype(np.float64)
    ref = ref_detect(Z, 0.3, 100, 5, 8, nms)
    got = L.detect_loops(jnp.asarray(Z), 0.3, min_separation=100, nms_radius=5, top_k=8, nms=nms)
    lst = got.to_list()
    assert len(ref) > 3
    assert [(i, j) for i, j, _ in lst] == [(i, j) for i, j, _ in ref]
    np.testing.assert_allclose([s for *_, s in lst], [s for *_, s in ref], rtol=1e-12)
    # padding rows
    c = int(got.count)
    assert np.all(np.asarray(got.pairs)[c:] == -1) and np.all(np.isneginf(np.asarray(got.scores)[c:]))
    assert not bool(got.truncated)


@pytest.mark.parametrize("nms", ["pair", "frame"])
def test_detect_loops_blocked_equals_dense(nms):
    Z = planted(seed=11)
    dense = L.detect_loops(Z, 0.2, nms_radius=4, block_rows=len(Z), nms=nms)
    for rows in (1, 7, 64):
        blocked = L.detect_loops(Z, 0.2, nms_radius=4, block_rows=rows, nms=nms)
        _assert_same_loops(blocked.to_list(), dense.to_list())


def _assert_same_loops(a, b):
    # a different tile shape changes the GEMM's float32 rounding (~1 ulp), not the pairs
    assert [(i, j) for i, j, _ in a] == [(i, j) for i, j, _ in b]
    np.testing.assert_allclose([s for *_, s in a], [s for *_, s in b], rtol=1e-6)


def _check_constraints(lst, sep, r, nms):
    for i, j, _ in lst:
        assert i > j and i - j > sep
    scores = [s for *_, s in lst]
    assert scores == sorted(scores, reverse=True)
    for a in range(len(lst)):
        for b in range(a):
            (i, j, _), (p, q, _) = lst[a], lst[b]
            if nms == "pair":
                assert abs(i - p) > r or abs(j - q) > r
            else:
                assert min(abs(x - y) for x in (i, j) for y in (p, q)) > r


@settings(deadline=None, max_examples=12)
@given(seed=st.integers(0, 10_000), thr=st.floats(-0.2, 0.6), nms=st.sampled_from(["pair", "frame"]))
def test_detect_loops_constraints_property(seed, thr, nms):
    Z = planted(n=300, d=24, seed=seed, noise=0.5)
    got = L.detect_loops(Z, thr, min_separation=100, nms_radius=9, top_k=4, nms=nms)
    lst = got.to_list()
    _check_constraints(lst, 100, 9, nms)
    assert all(s > thr for *_, s in lst)
    _assert_same_loops(L.detect_loops(Z, thr, 100, 9, 4, block_rows=37, nms=nms).to_list(), lst)


def test_detect_loops_finds_planted_loops():
    lst = L.detect_loops(planted(seed=12), 0.8, nms_radius=5).to_list()
    assert lst and all(i - j in (180, 160) for i, j, _ in lst)  # only the planted offsets


def test_detect_loops_degenerate_sizes():
    one = L.detect_loops(np.ones((1, 8), np.float32), 0.0)
    assert int(one.count) == 0 and one.to_list() == []
    few = L.detect_loops(planted(n=90, seed=13, loops=()), -1.0, min_separation=100)
    assert int(few.count) == 0
    # exactly min_separation + 2 frames: one admissible pair (N-1, 0)
    edge = L.detect_loops(planted(n=102, seed=14, loops=()), -1.0, min_separation=100)
    assert edge.to_list()[0][:2] == (101, 0) and int(edge.count) == 1


def test_detect_loops_rejects_nan_at_host_boundary():
    Z = planted(seed=15)
    Z[17] = np.nan
    with pytest.raises(ValueError, match="detect_loops: descriptors Z contains NaN or Inf.*row 17"):
        L.detect_loops(Z, 0.5)
    with pytest.raises(ValueError, match=r"LoopOptions.nms \(detect_loops\): invalid value 'box'"):
        L.detect_loops(planted(seed=15), 0.5, nms="box")


def test_detect_loops_under_jit_ignores_nan_rows():
    Z = planted(seed=16)
    clean = L.detect_loops(Z, 0.8, nms_radius=5).to_list()
    Z[5] = np.nan  # frame 5 is in no planted loop
    got = jax.jit(lambda z: L.detect_loops(z, 0.8, nms_radius=5))(Z)
    _assert_same_loops(got.to_list(), clean)


def test_detect_loops_truncation_flag():
    got = L.detect_loops(planted(seed=17), -1.0, nms_radius=0, max_loops=3)
    assert int(got.count) == 3 and bool(got.truncated)


# ----------------------------------------------------------------------- chunks and edges


def ref_loop_chunk(f, sched, h):
    best = None
    for t in range(sched.num_chunks):
        s, e = sched.starts[t], sched.ends[t]
        if s <= f < e:
            room = min(f - s, e - 1 - f)
            if best is None or room > best[0]:
                best = (room, t)
    t = best[1]
    s, e = sched.starts[t], sched.ends[t]
    w0 = min(max(f - h, s), max(e - 2 * h, s))
    return t, np.arange(w0, w0 + 2 * h)


@pytest.mark.parametrize("n", [400, 4541])
def test_loop_chunk_frames_all_frames(n):
    sched = chunk_schedule(n)
    i = np.arange(n - 1, -1, -1)
    j = np.arange(n)
    fn = jax.vmap(lambda a, b: L.loop_chunk_frames(a, b, sched, 10))
    lc = jax.tree.map(np.asarray, fn(i, j))
    assert lc.frames.shape == (n, 40)
    for k in range(0, n, 1 if n < 1000 else 7):
        ti, fi = ref_loop_chunk(i[k], sched, 10)
        tj, fj = ref_loop_chunk(j[k], sched, 10)
        np.testing.assert_array_equal(lc.frames[k], np.concatenate([fi, fj]))
        assert (lc.chunk_i[k], lc.chunk_j[k]) == (ti, tj)
        assert lc.frames[k][lc.local_i[k]] == i[k] and lc.frames[k][lc.local_j[k]] == j[k]
        for frames, t in ((fi, ti), (fj, tj)):  # each half inside its chunk
            assert sched.starts[t] <= frames[0] and frames[-1] < sched.ends[t]
        assert lc.valid[k] == (fi[-1] < fj[0] or fj[-1] < fi[0])  # halves must not overlap


def test_loop_chunk_frames_borders():
    sched = chunk_schedule(400)  # starts 0, 45, ..., 360; last chunk [360, 400)
    lc = L.loop_chunk_frames(399, 0, sched)
    np.testing.assert_array_equal(lc.frames, np.r_[380:400, 0:20])  # shifted inward at both ends
    assert (int(lc.chunk_i), int(lc.chunk_j), int(lc.local_i), int(lc.local_j)) == (8, 0, 19, 20)
    lc = L.loop_chunk_frames(250, 72, sched)
    # 72 is 2 frames from chunk 0's end but 27 frames into chunk 1 [45, 120): centred there
    assert int(lc.chunk_j) == 1
    np.testing.assert_array_equal(lc.frames[20:], np.arange(62, 82))
    lc = L.loop_chunk_frames(250, 50, sched)
    assert int(lc.chunk_j) == 0  # room 24 in chunk 0 vs 5 in chunk 1
    np.testing.assert_array_equal(lc.frames[20:], np.arange(40, 60))
    assert bool(lc.valid)


def test_loop_chunk_frames_short_sequence_invalid():
    sched = chunk_schedule(15)
    lc = L.loop_chunk_frames(14, 0, sched)
    assert not bool(lc.valid)


def test_filter_by_chunks():
    sched = chunk_schedule(400)
    pairs = np.array([[300, 100], [310, 95], [200, 150], [390, 20], [60, 50], [-1, -1]], np.int32)
    scores = np.array([0.9, 0.8, 0.7, 0.6, 0.5, -np.inf], np.float32)
    cand = L.LoopCandidates(pairs, scores, jnp.int32(5), jnp.bool_(False))
    out = L.filter_by_chunks(cand, sched).to_list()
    # (310, 95) shares chunks (6, 1) with the better (300, 100) (95 and 100 are most central
    # in chunk 1 = [45, 120)); (200, 150) lies in chunk 3 = [135, 210); (60, 50) in chunk 0
    assert [(i, j) for i, j, _ in out] == [(300, 100), (390, 20)]
    # reference: chunk assignment as loop_chunk_frames
    for i, j, _ in out:
        lc = L.loop_chunk_frames(i, j, sched)
        assert (int(lc.chunk_i), int(lc.chunk_j)) == (ref_loop_chunk(i, sched, 0)[0], ref_loop_chunk(j, sched, 0)[0])


def test_loop_edge_maps_chunk_i_into_chunk_j(x64):
    rng = np.random.default_rng(18)

    def rand_sim3():
        return sim3.exp(jnp.asarray(rng.normal(size=7) * [1, 1, 1, 0.5, 0.5, 0.5, 0.2]))

    S_ci, S_cj, L_loop = rand_sim3(), rand_sim3(), rand_sim3()  # chunk->world, loop->world
    S_i_loop = sim3.compose(sim3.inverse(S_ci), L_loop)  # loop -> chunk c_i
    S_j_loop = sim3.compose(sim3.inverse(S_cj), L_loop)  # loop -> chunk c_j
    E = L.loop_edge(S_i_loop, S_j_loop)
    expect = np.linalg.inv(np.asarray(sim3.as_matrix(S_cj))) @ np.asarray(sim3.as_matrix(S_ci))
    np.testing.assert_allclose(sim3.as_matrix(E), expect, atol=1e-10)
    np.testing.assert_allclose(
        sim3.as_matrix(E),
        np.asarray(sim3.as_matrix(S_j_loop)) @ np.linalg.inv(np.asarray(sim3.as_matrix(S_i_loop))),
        atol=1e-10,
    )


# ----------------------------------------------------------------------------- host level


def test_find_loops_planted_and_errors():
    G = planted(n=600, d=256, seed=19, loops=((400, 50, 30), (560, 300, 20)), noise=0.05)
    sched = chunk_schedule(600)
    loops = L.find_loops(G, sched, L.LoopOptions(dim=128, threshold=0.7))
    assert {(lp.i - lp.j) for lp in loops} == {350, 260}
    for lp in loops:
        assert lp.frames.shape == (40,) and lp.frames[lp.local_i] == lp.i and lp.frames[lp.local_j] == lp.j
    bad = G.copy()
    bad[3, 0] = np.inf
    with pytest.raises(ValueError, match="find_loops: descriptors contains NaN or Inf"):
        L.find_loops(bad, sched)
    with pytest.raises(ValueError, match="schedule is for 500 frames"):
        L.find_loops(G, chunk_schedule(500))
    with pytest.raises(ValueError, match="LoopOptions.fit_on: invalid value 'g0'; allowed: one of power, raw"):
        L.LoopOptions(fit_on="g0")
    assert L.find_loops(G[:50], chunk_schedule(50)) == []


def test_synthetic_kitti00_every_region_no_false_loop(shared_dir):
    """The acceptance benchmark: synthetic tokens along KITTI 00, the full default pipeline
    (g0 per chunk -> power -> whitening -> detection -> chunk filter) finds every loop region
    with precision 1.0 (bench/bench_place_recognition.py has the ablation)."""
    from swiftjax.io.trajectory import read_kitti
    from swiftjax.synthetic import places

    poses = read_kitti(shared_dir / "data" / "trajectories" / "KITTI_00_gt.txt")
    n = len(poses)
    params = places.make_place_params(places.PlaceTokenConfig(tokens_per_frame=16, seed=0))
    G = np.concatenate(
        [
            np.asarray(L.frame_descriptor(places.place_tokens(params, poses[idx], idx)))
            for idx in (np.minimum(np.arange(s, s + 75), n - 1) for s in range(0, n, 75))
        ]
    )[:n]
    loops = L.find_loops(G, chunk_schedule(n))
    gt = places.ground_truth_loops(poses)
    ev = places.evaluate_loops(np.array([(lp.i, lp.j) for lp in loops]), gt)
    assert ev.n_regions == 5
    assert ev.precision == 1.0 and ev.n_regions_found == 5, ev
    assert len({(lp.chunk_i, lp.chunk_j) for lp in loops}) == len(loops)

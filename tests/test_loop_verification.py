"""Tests for swiftjax.loops.verification against float64 NumPy loops and Monte Carlo draws."""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from swiftjax import align, camera, sim3
from swiftjax.loops import verification as V

# ------------------------------------------------------------------------------ scenes

H, W = 12, 16
K = np.array([[14.0, 0.0, 7.5], [0.0, 13.0, 5.5], [0.0, 0.0, 1.0]])


def rot(axis_angle):
    w = np.asarray(axis_angle, np.float64)
    th = np.linalg.norm(w)
    if th < 1e-12:
        return np.eye(3)
    k = w / th
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx


def sim3_np(R, t, s):
    with jax.enable_x64(True):
        return np.asarray(sim3.from_rst(jnp.asarray(R), jnp.asarray(t), jnp.asarray(s)))


def render_planes(c2w, planes, Kf):
    """Depth of the nearest of several planes ``n·x = d`` seen by cameras ``c2w [F, 3, 4]``."""
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    out = []
    for E in c2w:
        R, c = E[:, :3], E[:, 3]
        y = (v - Kf[1, 2]) / Kf[1, 1]
        x = (u - Kf[0, 2]) / Kf[0, 0]
        ray = np.stack([x, y, np.ones_like(x)], -1) @ R.T  # world direction per unit depth
        best = np.full((H, W), np.inf)
        for n, d in planes:
            den = ray @ n
            z = (d - n @ c) / np.where(np.abs(den) > 1e-9, den, np.nan)
            best = np.where((z > 0) & (z < best), z, best)
        out.append(best)
    return np.stack(out)


def scene(seed=0, F=3, G=4, focal_jitter=0.03):
    """Source frames in chunk i, target frames in chunk j = S(chunk i) of the same planes.

    Returns ``(src, dst, S_dst_src)``; depths are rendered exactly (then disturbed a little
    and given a few NaNs / low-confidence pixels), per-frame focal errors with the depth
    scaled by the same factor (so eq. 1 undoes them).
    """
    rng = np.random.default_rng(seed)
    planes = [
        (np.array([0.0, -1.0, 0.0]), -1.5),
        (np.array([1.0, 0.0, 0.3]) / np.hypot(1, 0.3), 3.0),
        (np.array([0.0, 0.0, 1.0]), 9.0),
    ]
    src_c2w = np.stack(
        [np.concatenate([rot(0.05 * rng.normal(size=3)), [[0.3 * k], [0.0], [0.5 * k]]], 1) for k in range(F)]
    )
    S = sim3_np(rot([0.1, -0.4, 0.2]), np.array([2.0, -0.5, 1.0]), 1.7)
    R_s, t_s, s_s = rot([0.1, -0.4, 0.2]), np.array([2.0, -0.5, 1.0]), 1.7
    # the same planes in chunk j coordinates: x' = s R x + t  ->  n'·x' = s d + n'·t, n' = R n
    planes_j = [(R_s @ n, s_s * d + (R_s @ n) @ t_s) for n, d in planes]
    dst_c2w = []
    for k in range(G):  # cameras near the mapped source cameras
        base = src_c2w[min(k, F - 1)]
        R = R_s @ base[:, :3] @ rot(0.03 * rng.normal(size=3))
        c = s_s * R_s @ base[:, 3] + t_s + 0.1 * rng.normal(size=3)
        dst_c2w.append(np.concatenate([R, c[:, None]], 1))
    dst_c2w = np.stack(dst_c2w)

    def frames(c2w, planes_, n):
        eps = focal_jitter * rng.uniform(-1, 1, size=n)
        Ks = np.tile(K, (n, 1, 1))
        Ks[:, 0, 0] *= 1 + eps
        Ks[:, 1, 1] *= 1 + eps
        depth = render_planes(c2w, planes_, K) * (1 + eps)[:, None, None]  # zoom ambiguity
        depth *= np.exp(0.01 * rng.normal(size=depth.shape))
        bad = rng.random(depth.shape) < 0.1
        depth = np.where(bad, depth * rng.uniform(0.5, 1.5, size=depth.shape), depth)
        depth[rng.random(depth.shape) < 0.03] = np.nan
        conf = 1 + 5 * rng.random(depth.shape)
        ext = np.asarray(camera.invert_extrinsic(c2w))
        return align.ChunkFrames(depth, conf, Ks, ext)

    return frames(src_c2w, planes, F), frames(dst_c2w, planes_j, G), S


# -------------------------------------------------------------------------- references


def ref_dense(src, dst, S, K_ref, stride, conf_ratio, tol, neighbours):
    """Loop over points and target frames, float64, straight from the docstring."""
    src = [np.asarray(a, np.float64) for a in src]
    dst = [np.asarray(a, np.float64) for a in dst]
    S = np.asarray(S, np.float64)
    q = S[3:7] / np.linalg.norm(S[3:7])
    x_, y_, z_, w_ = q
    Rs = np.array(
        [
            [1 - 2 * (y_ * y_ + z_ * z_), 2 * (x_ * y_ - z_ * w_), 2 * (x_ * z_ + y_ * w_)],
            [2 * (x_ * y_ + z_ * w_), 1 - 2 * (x_ * x_ + z_ * z_), 2 * (y_ * z_ - x_ * w_)],
            [2 * (x_ * z_ - y_ * w_), 2 * (y_ * z_ + x_ * w_), 1 - 2 * (x_ * x_ + y_ * y_)],
        ]
    )
    act = lambda p: S[7] * Rs @ p + S[:3]

    def normalised(depth, conf, Ks):
        out = np.full(depth.shape, np.nan)
        for f in range(depth.shape[0]):
            r = 0.5 * (K_ref[0, 0] / Ks[f, 0, 0] + K_ref[1, 1] / Ks[f, 1, 1])
            c = conf[f]
            mean = np.mean(c[np.isfinite(c)])
            d = r * depth[f]
            ok = np.isfinite(d) & (d > 0) & np.isfinite(c) & (c > conf_ratio * mean)
            out[f] = np.where(ok, d, np.nan)
        return out

    ds, cs, Kss, Es = src
    dd, cd, Ksd, Ed = dst
    Dn_src = normalised(ds, cs, Kss)
    Dn_dst = normalised(dd, cd, Ksd)
    Kinv = np.linalg.inv(K_ref)
    F, G = ds.shape[0], dd.shape[0]
    centres_dst = [-(E[:, :3].T @ E[:, 3]) for E in Ed]
    n_pts = n_seen = n_agree = p_seen = p_agree = p_front = 0
    for f in range(F):
        R, t = Es[f][:, :3], Es[f][:, 3]
        c_f = act(-(R.T @ t))
        dist = np.array([np.linalg.norm(c_f - c) for c in centres_dst])
        near = set(np.argsort(dist, kind="stable")[:neighbours].tolist()) if 0 < neighbours < G else set(range(G))
        for v in range(0, H, stride):
            for u in range(0, W, stride):
                d = Dn_src[f, v, u]
                if not np.isfinite(d):
                    continue
                x = R.T @ (d * (Kinv @ np.array([u, v, 1.0])) - t)
                y = act(x)
                n_pts += 1
                seen = agree = False
                for g in near:
                    p = Ed[g][:, :3] @ y + Ed[g][:, 3]
                    if p[2] <= 0:
                        continue
                    uu = np.round(K_ref[0, 0] * p[0] / p[2] + K_ref[0, 1] * p[1] / p[2] + K_ref[0, 2])
                    vv = np.round(K_ref[1, 1] * p[1] / p[2] + K_ref[1, 2])
                    if not (0 <= uu <= W - 1 and 0 <= vv <= H - 1):
                        continue
                    D = Dn_dst[g, int(vv), int(uu)]
                    if not np.isfinite(D):
                        continue
                    seen = True
                    p_seen += 1
                    if abs(p[2] - D) <= tol * D:
                        agree = True
                        p_agree += 1
                    if p[2] < (1 - tol) * D:
                        p_front += 1
                n_seen += seen
                n_agree += agree
    return dict(
        num_points=n_pts,
        num_seen=n_seen,
        num_agree=n_agree,
        pairs_seen=p_seen,
        pairs_agree=p_agree,
        pairs_front=p_front,
    )


# ------------------------------------------------------------------------ dense tests

ALL_PIXELS = V.VerificationConfig(stride=1, neighbours=0)  # every source pixel, every target frame


@pytest.mark.parametrize("stride,neighbours", [(1, 0), (2, 2)])
def test_dense_consistency_matches_numpy_loops(x64, stride, neighbours):
    src, dst, S = scene(seed=1)
    got = V.dense_consistency(
        src, dst, S, K, V.VerificationConfig(stride=stride, depth_tolerance=0.05, neighbours=neighbours)
    )
    want = ref_dense(src, dst, S, K, stride, 0.5, 0.05, neighbours)
    for k, v in want.items():
        assert int(getattr(got, k)) == v, k
    assert want["pairs_seen"] > 50 and 0 < want["pairs_agree"] < want["pairs_seen"]
    assert float(got.agreement) == pytest.approx(want["pairs_agree"] / want["pairs_seen"])
    assert float(got.overlap) == pytest.approx(want["num_seen"] / want["num_points"])
    assert float(got.consistency) == pytest.approx(want["num_agree"] / want["num_points"])


def test_dense_consistency_true_edge_agrees_wrong_edge_does_not():
    src, dst, S = scene(seed=2)
    good = V.dense_consistency(src, dst, S, K, ALL_PIXELS)
    assert float(good.agreement) > 0.6 and float(good.overlap) > 0.8  # 10 % gross depth errors
    with jax.enable_x64(True):  # 1.5 m sideways and 20 degrees of yaw: a different place
        wrong = np.asarray(sim3.compose(jnp.asarray(S), jnp.asarray(sim3_np(rot([0, 0.35, 0]), [1.5, 0, 0], 1.0))))
    bad = V.dense_consistency(src, dst, wrong, K, ALL_PIXELS)
    assert float(bad.agreement) < 0.5 * float(good.agreement)


def test_dense_consistency_nonfinite_edge_and_empty_source():
    src, dst, S = scene(seed=3)
    nan = V.dense_consistency(src, dst, np.full(8, np.nan), K)
    assert int(nan.num_points) == 0 and float(nan.agreement) == 0 and float(nan.overlap) == 0
    empty = align.ChunkFrames(np.full_like(src.depth, np.nan), src.conf, src.intrinsic, src.extrinsic)
    res = V.dense_consistency(empty, dst, S, K)
    assert int(res.num_points) == 0 and float(res.consistency) == 0


def test_cross_chunk_consistency_batched_equals_both_directions():
    a, b = scene(seed=4), scene(seed=5)
    stack = lambda x, y: align.ChunkFrames(*(np.stack([p, q]) for p, q in zip(x, y)))
    Z = np.stack([a[2], b[2]])
    cfg = V.VerificationConfig(stride=2, neighbours=2)
    cc = V.cross_chunk_consistency(stack(a[0], b[0]), stack(a[1], b[1]), Z, K, cfg)
    for m, (src, dst, S) in enumerate((a, b)):
        fwd = V.dense_consistency(src, dst, S, K, cfg)
        back = V.dense_consistency(dst, src, np.asarray(sim3.inverse(jnp.asarray(S, jnp.float32))), K, cfg)
        assert int(cc.i_to_j.pairs_agree[m]) == int(fwd.pairs_agree)
        assert abs(int(cc.j_to_i.pairs_agree[m]) - int(back.pairs_agree)) <= 1  # float32 inverse
        assert float(cc.score[m]) == pytest.approx(min(float(cc.i_to_j.agreement[m]), float(cc.j_to_i.agreement[m])))


def test_loop_chunk_quality():
    src, dst, S = scene(seed=6)
    _, ok = align.align_chunk_pair(src, src, K)
    bad = ok._replace(pose_fallback=jnp.asarray(True), num_points=jnp.asarray(2, jnp.int32))
    q = V.loop_chunk_quality(ok, bad)
    assert int(q.min_points) == 2 and not bool(q.valid)
    q = V.loop_chunk_quality(ok, ok)
    assert bool(q.valid) and float(q.min_fraction) == pytest.approx(float(ok.fraction_used))


# ----------------------------------------------------------------------------- PCM


def chain_problem(seed, T=12, loops=((1, 8), (2, 10), (0, 11), (4, 9))):
    """A random chain of temporal edges and loop edges exactly consistent with it (4x4 maths)."""
    rng = np.random.default_rng(seed)
    M = np.tile(np.eye(4), (T - 1, 1, 1))
    for e in range(T - 1):
        M[e, :3, :3] = np.exp(0.05 * rng.normal()) * rot(0.2 * rng.normal(size=3))
        M[e, :3, 3] = rng.normal(size=3) + [3, 0, 0]
    Xm = [np.eye(4)]
    for e in range(T - 1):
        Xm.append(Xm[-1] @ M[e])
    Xm = np.stack(Xm)
    nodes = np.asarray(loops, np.int32)
    Zm = np.linalg.inv(Xm[nodes[:, 0]]) @ Xm[nodes[:, 1]]
    with jax.enable_x64(True):
        to = lambda A: np.asarray(sim3.from_matrix(jnp.asarray(A)))
        return to(M), to(Xm), nodes, to(Zm)


def test_pairwise_consistency_residual_matches_explicit_cycle(x64):
    rel, X, nodes, Z = chain_problem(0)
    rng = np.random.default_rng(1)
    Zn = np.asarray(sim3.compose(jnp.asarray(Z), sim3.exp(jnp.asarray(0.05 * rng.normal(size=(len(Z), 7))))))
    odo = V.odometry_covariance(jnp.asarray(rel), 0.01, 0.02, 0.01)
    lc = V.loop_covariance(jnp.asarray(Zn), 0.01, 0.05, 0.01)
    m = np.asarray(V.pairwise_consistency(jnp.asarray(X), odo, jnp.asarray(nodes), jnp.asarray(Zn), lc))
    assert np.allclose(m, m.T) and np.all(np.diag(m) == 0)
    # explicit cycle with 4x4 matrices: Z_a^-1 (X_pa^-1 X_pb) Z_b (X_qb^-1 X_qa), conjugated
    # into the world frame by X_qa; covariance by explicit sums over each span's edges
    mat = lambda S: np.asarray(sim3.as_matrix(jnp.asarray(S)))
    Xm, Zm, inv = mat(X), mat(Zn), np.linalg.inv
    pairs = list(itertools.combinations(range(len(Z)), 2))
    E = []
    for a, b in pairs:
        (pa, qa), (pb, qb) = nodes[a], nodes[b]
        cyc = inv(Zm[a]) @ inv(Xm[pa]) @ Xm[pb] @ Zm[b] @ inv(Xm[qb]) @ Xm[qa]
        E.append(Xm[qa] @ cyc @ inv(Xm[qa]))
    r = np.asarray(sim3.log(sim3.from_matrix(jnp.asarray(np.stack(E)))))
    Ad = np.asarray(sim3.adjoint(jnp.asarray(X)))
    C = [Ad[e + 1] @ np.asarray(odo)[e] @ Ad[e + 1].T for e in range(len(rel))]
    L = np.asarray(lc)
    for (a, b), rk in zip(pairs, r):
        (pa, qa), (pb, qb) = nodes[a], nodes[b]
        spans = set(range(pa, qa)) ^ set(range(pb, qb))
        cov = sum((C[e] for e in spans), np.zeros((7, 7)))
        cov = cov + Ad[qa] @ L[a] @ Ad[qa].T + Ad[qb] @ L[b] @ Ad[qb].T
        assert m[a, b] == pytest.approx(math.sqrt(rk @ np.linalg.solve(cov, rk)), rel=1e-6)


def test_pairwise_consistency_is_chi2_under_the_model(x64):
    """Monte Carlo: perturb every edge by its covariance; m² averages to 7 (χ²_7)."""
    rel, X, nodes, Z = chain_problem(2)
    odo = np.asarray(V.odometry_covariance(jnp.asarray(rel), 0.004, 0.01, 0.004))
    lc = np.asarray(V.loop_covariance(jnp.asarray(Z), 0.004, 0.01, 0.004))
    rng = np.random.default_rng(3)
    n = 300
    d_odo = rng.normal(size=(n, len(rel), 7)) * np.sqrt(np.diagonal(odo, axis1=1, axis2=2))
    d_loop = rng.normal(size=(n, len(Z), 7)) * np.sqrt(np.diagonal(lc, axis1=1, axis2=2))
    mat = lambda S: np.asarray(sim3.as_matrix(jnp.asarray(S)))
    rel_n = mat(rel) @ mat(sim3.exp(jnp.asarray(d_odo)))  # [n, E, 4, 4]
    Xs = [np.broadcast_to(np.eye(4), (n, 4, 4))]
    for e in range(len(rel)):
        Xs.append(Xs[-1] @ rel_n[:, e])
    Xs = np.asarray(sim3.from_matrix(jnp.asarray(np.stack(Xs, 1))))
    Zs = np.asarray(sim3.compose(jnp.asarray(Z), sim3.exp(jnp.asarray(d_loop))))
    m = np.asarray(
        jax.vmap(V.pairwise_consistency, in_axes=(0, None, None, 0, None))(
            jnp.asarray(Xs), jnp.asarray(odo), jnp.asarray(nodes), jnp.asarray(Zs), jnp.asarray(lc)
        )
    )
    iu = np.triu_indices(len(Z), 1)
    assert np.mean(m[:, iu[0], iu[1]] ** 2, axis=0) == pytest.approx(np.full(len(iu[0]), 7.0), rel=0.2)
    # a wrong loop (2 units off) is far outside
    Zw = Z.copy()
    Zw[1] = np.asarray(sim3.compose(jnp.asarray(Z[1]), sim3.exp(jnp.asarray([2.0, 0, 0, 0, 0, 0, 0]))))
    mw = np.asarray(
        V.pairwise_consistency(jnp.asarray(X), jnp.asarray(odo), jnp.asarray(nodes), jnp.asarray(Zw), jnp.asarray(lc))
    )
    assert np.all(mw[1, [0, 2, 3]] > 3 * math.sqrt(7))


def brute_clique(A, w):
    m = len(A)
    best = (0, -np.inf, [])
    for size in range(m, 0, -1):
        for sub in itertools.combinations(range(m), size):
            if all(A[a, b] for a, b in itertools.combinations(sub, 2)):
                key = (size, float(sum(w[k] for k in sub)))
                if key[:2] > best[:2]:
                    best = (*key, list(sub))
        if best[0]:
            break
    return best


@pytest.mark.parametrize("seed", range(6))
def test_max_consistent_set_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 11))
    A = rng.random((m, m)) < 0.6
    A = A | A.T
    w = rng.random(m)
    got = V.max_consistent_set(A, w)
    size, weight, _ = brute_clique(A, w)
    assert len(got) == size and sum(w[k] for k in got) == pytest.approx(weight)
    assert all(A[a, b] for a, b in itertools.combinations(got, 2))
    assert V.max_consistent_set(np.zeros((0, 0), bool)) == []


# ----------------------------------------------------------------------- decisions


def record(ci, cj, Z, agreement=0.8, overlap=0.9, valid=True, fraction=0.5):
    return {
        "chunk_i": ci,
        "chunk_j": cj,
        "Z": list(map(float, Z)),
        "dense_agreement": agreement,
        "dense_overlap": overlap,
        "quality_valid": valid,
        "quality_min_fraction": fraction,
    }


def test_verify_candidates_rules_and_pcm(x64):
    rel, X, nodes, Z = chain_problem(4)
    # loop edge (p -> q) is recorded as c_j = p, c_i = q with Z mapping c_i into c_j
    recs = [record(int(q), int(p), z) for (p, q), z in zip(nodes, Z)]
    far = np.asarray(sim3.compose(jnp.asarray(Z[0]), sim3.exp(jnp.asarray([4.0, 1, 0, 0, 0.3, 0, 0]))))
    recs.append(record(int(nodes[0, 1]), int(nodes[0, 0]), far))  # geometric liar: passes dense, fails PCM
    recs.append(record(5, 1, np.full(8, np.nan)))
    recs.append(record(7, 2, Z[0], valid=False))
    recs.append(record(7, 2, Z[0], fraction=0.001))
    recs.append(record(7, 2, Z[0], agreement=0.2))
    recs.append(record(7, 2, Z[0], overlap=0.01))
    recs.append(record(7, 2, Z[0], agreement=float("nan")))
    out = V.verify_candidates(recs, X, rel)
    assert [d.accepted for d in out] == [True] * 4 + [False] * 7
    assert "pairwise inconsistent" in out[4].reason
    assert "not finite" in out[5].reason and "invalid" in out[6].reason and "thin" in out[7].reason
    assert "agreement" in out[8].reason and "overlap" in out[9].reason and "not computable" in out[10].reason
    assert all(math.isfinite(d.pcm_residual) for d in out[:5])
    assert V.verify_candidates([], X, rel) == []
    single = V.verify_candidates([recs[4]], X, rel)  # nothing to be inconsistent with
    assert single[0].accepted and single[0].reason == "verified"
    off = V.verify_candidates(recs[:5], X, rel, V.VerificationConfig(pcm=False))
    assert all(d.accepted for d in off)


def test_pcm_whitens_a_record_by_its_own_covariance(x64):
    """A record's ``_covariance`` (a registration edge's own,
    :func:`swiftjax.pipeline.loop_geometry.edge_covariance`) replaces the drift model's loop
    covariance in its cycles: the drift model's own matrix gives the same residuals; one wide
    along the edge's error accepts it; a record stored the other way round (``Z⁻¹`` with
    ``Ad(Z) Σ Ad(Z)ᵀ``, the covariance of the inverse's right perturbation) is the same edge."""
    rel, X, nodes, Z = chain_problem(4)
    c = V.VerificationConfig()
    recs = [record(int(q), int(p), z) for (p, q), z in zip(nodes, Z)]
    delta = np.array([1.0, 0.3, 0.0, 0.0, 0.05, 0.0, 0.0])  # 20 loop sigmas along x
    far = np.asarray(sim3.compose(jnp.asarray(Z[0]), sim3.exp(jnp.asarray(delta))))
    p0, q0 = int(nodes[0, 0]), int(nodes[0, 1])
    liar = record(q0, p0, far)
    base = V.verify_candidates([*recs, liar], X, rel)
    assert [d.accepted for d in base] == [True] * 4 + [False]
    drift = np.asarray(V.loop_covariance(jnp.asarray(far), c.loop_sigma_rot, c.loop_sigma_trans, c.loop_sigma_scale))
    same = V.verify_candidates([*recs, liar | {"_covariance": drift}], X, rel)
    assert [d.pcm_residual for d in same] == pytest.approx([d.pcm_residual for d in base], rel=1e-9)
    wide = drift + np.outer(delta, delta)  # its error lies within it: δᵀ (Σ + δ δᵀ)⁻¹ δ < 1
    own = V.verify_candidates([*recs, liar | {"_covariance": wide}], X, rel)
    assert [d.accepted for d in own] == [True] * 5
    assert own[4].pcm_residual < 1.5 < 5 < base[4].pcm_residual
    Ad = np.asarray(sim3.adjoint(jnp.asarray(far)))
    step = 1e-6 * delta  # (Z exp δ)⁻¹ = Z⁻¹ exp(−Ad(Z) δ), checked to first order
    moved = sim3.compose(jnp.asarray(far), sim3.inverse(sim3.compose(jnp.asarray(far), sim3.exp(jnp.asarray(step)))))
    assert np.asarray(sim3.log(moved)) == pytest.approx(-Ad @ step, abs=1e-11)
    flipped = record(p0, q0, np.asarray(sim3.inverse(jnp.asarray(far)))) | {"_covariance": Ad @ wide @ Ad.T}
    back = V.verify_candidates([*recs, flipped], X, rel)
    assert [d.accepted for d in back] == [True] * 5
    assert [d.pcm_residual for d in back] == pytest.approx([d.pcm_residual for d in own], rel=1e-6)


def null_record(ci, cj, Z, agreement, mean=0.05, tau=0.1, registered=None, **extra):
    """A record judged by the null rule: ``κ = (a − mean)/(1 − mean)``; ``registered``: the
    registered null's bound (a registration edge, :mod:`swiftjax.pipeline.loop_geometry`)."""
    r = record(ci, cj, Z, agreement=agreement) | {"null_threshold": tau, "null_mean": mean, "null_std": 0.01}
    if registered is not None:
        r["registered_null_threshold"] = registered
    return r | extra


@pytest.mark.parametrize(
    ("numbers", "expected"),
    [
        ({"null_threshold": 0.1, "null_mean": 0.05}, True),  # significant, κ = 0.179 < 0.2
        ({"null_threshold": 0.3, "null_mean": 0.05}, False),  # not significant
        ({"null_threshold": 0.1, "null_mean": 0.0}, False),  # κ = 0.22: verified without it
        ({"null_stopped": True, "null_threshold": 0.1, "null_mean": 0.05}, True),  # significance open
        ({"null_skipped": True}, False),  # a < κ_min: rejected whatever the null
        ({"null_threshold": 0.1, "null_mean": 0.05, "dense_overlap": 0.1}, False),  # not in view
        ({"null_threshold": float("nan"), "null_mean": float("nan")}, False),  # no null: the fixed bound
    ],
)
def test_may_follow_only_below_the_kappa_floor(numbers, expected):
    r = {"dense_agreement": 0.22, "dense_overlap": 0.9} | numbers
    assert V.may_follow(r, V.VerificationConfig()) is expected
    assert not V.may_follow(r, V.VerificationConfig(followers=False))
    assert not V.may_follow(r, V.VerificationConfig(agreement_rule="fixed"))


def test_followers_join_only_verified_loops_they_are_consistent_with(x64):
    rel, X, nodes, Z = chain_problem(4)
    strong = [null_record(int(q), int(p), z, 0.5) for (p, q), z in zip(nodes[:2], Z[:2])]
    weak = [null_record(int(q), int(p), z, 0.22, registered=0.15) for (p, q), z in zip(nodes[2:], Z[2:])]
    far = np.asarray(sim3.compose(jnp.asarray(Z[3]), sim3.exp(jnp.asarray([4.0, 1, 0, 0, 0.3, 0, 0]))))
    liar = null_record(int(nodes[3, 1]), int(nodes[3, 0]), far, 0.21, registered=0.15)  # a follower, wrong edge
    below = null_record(int(nodes[2, 1]), int(nodes[2, 0]), Z[2], 0.22, registered=0.25)  # not above its null
    out = V.verify_candidates([*strong, *weak, liar, below], X, rel)
    assert [d.accepted for d in out] == [True, True, True, True, False, False]
    assert all(d.reason.startswith("verified;") for d in out[:2])
    assert all(d.reason.startswith("follower;") for d in out[2:4])
    assert "pairwise inconsistent" in out[4].reason
    assert "no more than registrations on unrelated chunks: 0.220 <= 0.250" in out[5].reason
    # followers never make a set of their own, whatever their number
    alone = V.verify_candidates([*weak, liar], X, rel)
    assert not any(d.accepted for d in alone)
    assert all("no verified loop" in d.reason for d in alone)
    off = V.verify_candidates([*strong, *weak], X, rel, V.VerificationConfig(pcm=False))
    assert [d.accepted for d in off] == [True, True, False, False]
    # without followers the floor rejects them as before
    plain = V.verify_candidates([*strong, *weak], X, rel, V.VerificationConfig(followers=False))
    assert [d.accepted for d in plain] == [True, True, False, False]
    assert "chance-corrected agreement 0.179 < 0.2" in plain[2].reason


def test_followers_nulls_computed_only_when_accepted(x64):
    """``settle_deferred``: a pending follower is accepted provisionally, its registered null
    computed only then, and the records decided again; the verdicts equal those with every
    null computed first, and PCM's rejects never compute theirs."""
    from swiftjax.pipeline.loop_geometry import settle_deferred

    rel, X, nodes, Z = chain_problem(4)
    far = np.asarray(sim3.compose(jnp.asarray(Z[3]), sim3.exp(jnp.asarray([4.0, 1, 0, 0, 0.3, 0, 0]))))
    bounds = [None, None, 0.15, 0.25, 0.15]  # the registered nulls: the fourth is not beaten
    edges = [*zip(nodes, Z), (nodes[3], far)]
    calls = []

    def records(pending):
        out = []
        for k, ((p, q), z) in enumerate(edges):
            r = null_record(int(q), int(p), z, 0.5 if bounds[k] is None else 0.21)
            if bounds[k] is not None and pending:
                r |= {
                    "registered_null_pending": True,
                    "_registered": lambda k=k: calls.append(k) or {"registered_null_threshold": bounds[k]},
                }
            elif bounds[k] is not None:
                r["registered_null_threshold"] = bounds[k]
            out.append(r)
        return out

    def decide(recs):
        for r, d in zip(recs, V.verify_candidates(recs, X, rel)):
            r.update(accepted=d.accepted, reason=d.reason)

    lazy, eager = records(True), records(False)
    settle_deferred(decide, lazy)
    decide(eager)
    assert [r["accepted"] for r in lazy] == [r["accepted"] for r in eager] == [True, True, True, False, False]
    assert [r["reason"] for r in lazy] == [r["reason"] for r in eager]
    assert sorted(calls) == [2, 3]  # the liar (4) is rejected by PCM: its null never computed
    assert lazy[4]["registered_null_pending"] and "registered_null_pending" not in lazy[2]
    # a null stopped after its first round (κ settled, a > τ open): provisionally a follower
    # even where the first round's τ is above a; judged on the complete null once computed
    (p, q), z = edges[2]
    for tau, accepted in ((0.25, False), (0.1, True)):
        stopped = null_record(int(q), int(p), z, 0.21, tau=0.3, null_stopped=True)
        full = {"null_threshold": tau, "null_stopped": False, "registered_null_threshold": 0.15}
        stopped |= {"registered_null_pending": True, "_registered": lambda full=full: full}
        recs = [*records(False)[:2], stopped]
        settle_deferred(decide, recs)
        assert recs[2]["accepted"] is accepted, recs[2]["reason"]
        assert accepted or "no better than under wrong edges: agreement 0.210 <= 0.250" in recs[2]["reason"]


def test_candidate_numbers_from_record_dicts():
    src, dst, S = scene(seed=7)
    half = {"num_points": 900, "fraction_used": 0.4, "rms": 0.02, "valid": True, "pose_fallback": False}
    out = V.candidate_numbers(src, dst, S, K, half, dict(half, fraction_used=0.3, rms=0.05))
    cc = V.cross_chunk_consistency(
        *(align.ChunkFrames(*(np.asarray(a)[None] for a in f)) for f in (src, dst)), S[None], K
    )
    assert out["dense_agreement"] == pytest.approx(float(cc.score[0]))
    assert out["dense_i_to_j"]["pairs_agree"] == int(cc.i_to_j.pairs_agree[0])
    assert out["quality_valid"] and out["quality_min_fraction"] == pytest.approx(0.3)
    assert out["quality_max_rms"] == pytest.approx(0.05) and out["quality_min_points"] == 900
    assert not V.candidate_numbers(src, dst, S, K, half, dict(half, pose_fallback=True))["quality_valid"]


# ------------------------------------------------------------------ pipeline hooks


class _Ctx:
    """The parts of a RunContext the loop-closure decisions use."""

    def __init__(self, **config):
        from swiftjax.pipeline import PipelineConfig
        from swiftjax.pipeline.rundir import StageTimer

        self.config = PipelineConfig(**config)
        self.timer = StageTimer()
        self.lines = []
        self.log = self.lines.append


def test_pipeline_decisions_all_rejected_none_option_and_empty(x64):
    from swiftjax.pipeline import loop_closure
    from swiftjax.pipeline.results import TemporalResult

    rel, X, nodes, Z = chain_problem(5)
    temporal = TemporalResult(np.zeros((12, 4)), rel, [], K)
    bad = [record(int(q), int(p), z, agreement=0.1) for (p, q), z in zip(nodes, Z)]
    ctx = _Ctx()
    loop_closure.decide(ctx, temporal.relative, bad)
    loop_closure._log_decisions(ctx, bad)
    assert not any(r["accepted"] for r in bad)
    assert "every candidate was rejected" in ctx.lines[-1] and "without loop closure" in ctx.lines[-1]
    ctx = _Ctx(loop_verification="none")
    loop_closure.decide(ctx, temporal.relative, bad)
    assert all(r["accepted"] and "without verification" in r["reason"] for r in bad)
    loop_closure._log_decisions(ctx, [])
    assert "no loop candidates" in ctx.lines[-1]
    with pytest.raises(ValueError, match="loop_verification"):
        _Ctx(loop_verification="maybe")


def test_loops_txt_and_plot_with_rejected_candidates(tmp_path):
    from swiftjax.io import plot
    from swiftjax.pipeline import export

    recs = [
        {
            "i": 150,
            "j": 20,
            "score": 0.7,
            "chunk_i": 5,
            "chunk_j": 0,
            "align_i": {"num_points": 10},
            "align_j": {"num_points": 12},
            "dense_agreement": 0.8,
            "dense_overlap": 0.9,
            "accepted": True,
            "reason": "verified",
        },
        {
            "i": 60,
            "j": 30,
            "score": 0.5,
            "chunk_i": 2,
            "chunk_j": 1,
            "accepted": False,
            "reason": "chunks 1 and 2 are neighbours (their temporal edge)",
        },
    ]
    export.write_loops(tmp_path / "loops.txt", recs)
    lines = (tmp_path / "loops.txt").read_text().splitlines()
    keys = [x for x in lines if x.startswith("#")][-1][2:].split()
    assert keys[-1] == "reason"
    rows = [dict(zip(keys, x.split(maxsplit=len(keys) - 1))) for x in lines if not x.startswith("#")]
    assert (
        rows[0]["accepted"] == "yes" and rows[0]["dense_agreement"] == "0.8" and rows[0]["align_i.num_points"] == "10"
    )
    assert rows[1]["accepted"] == "no" and rows[1]["dense_agreement"] == "-"
    assert rows[1]["reason"] == "chunks 1 and 2 are neighbours (their temporal edge)"  # readable, not snake_case
    assert "# 2 candidates, 1 accepted (edges of the pose graph), 1 rejected" in lines
    export.write_loops(tmp_path / "none.txt", [])
    text = (tmp_path / "none.txt").read_text()
    assert "0 candidates: loop detection found no pair" in text and "all were used" not in text
    assert [x for x in text.splitlines() if not x.startswith("#")] == []
    est = np.cumsum(np.ones((200, 3)), axis=0)
    plot.plot_trajectory(tmp_path / "t.png", est, loops=[[150, 20]], rejected=[[60, 30]])
    assert (tmp_path / "t.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="rejected"):
        plot.plot_trajectory(tmp_path / "u.png", est, rejected=[[260, 30]])


def _edge(X, p, q, wrong=False):
    """Loop edge chunk ``q`` into chunk ``p`` from the chain ``X``: exactly consistent, or far off."""
    Z = sim3.compose(sim3.inverse(jnp.asarray(X[p])), jnp.asarray(X[q]))
    if wrong:
        Z = sim3.compose(Z, sim3.exp(jnp.asarray([4.0, 1, 0, 0, 0.3, 0, 0])))
    return np.asarray(Z)


def geo_record(X, p, q, agreement=0.5, wrong=False, **extra):
    """A registration edge ``q -> p`` (``p < q``) judged by the null rule (:func:`null_record`)."""
    return null_record(q, p, _edge(X, p, q, wrong), agreement) | {"source": "geometry"} | extra


SKIPPED = {"null_skipped": True}  # a < κ_min: the dense test's evidence alone rejects it
FLOOR = (
    "agreement 0.090 < 0.2 (the chance-corrected agreement (a - m)/(1 - m) <= a for every null mean m; null not run)"
)
STRUCTURE = "no more structure inliers than against unrelated chunks: 33 <= 43 (false-alarm rate 0.01)"


def test_siblings_join_a_loop_of_their_revisit_only(x64):
    """A registration edge rejected by its evidence alone is accepted beside a verified loop of
    the same revisit (each chunk within one chunk of the loop's) when consistent with every
    accepted loop; a wrong one, one beside no loop, one beside a sibling only, one not in view,
    a token candidate and a joint registration keep the verdicts they get without siblings."""
    rel, X, _, _ = chain_problem(4)
    loops = [geo_record(X, 1, 8), geo_record(X, 2, 10), geo_record(X, 0, 11)]
    weak = [
        geo_record(X, 3, 10, 0.09, **SKIPPED),  # beside 2/10: the dense test's floor alone
        geo_record(X, 2, 9, 0.3, evidence_reason=STRUCTURE),  # beside 1/8 and 2/10: the structure null
        geo_record(X, 1, 11, 0.09, wrong=True, **SKIPPED),  # beside 0/11 and 2/10, its edge wrong
        geo_record(X, 5, 7, 0.09, **SKIPPED),  # beside no loop
        geo_record(X, 4, 10, 0.09, **SKIPPED),  # beside the sibling 3/10 only
        geo_record(X, 3, 10, 0.09, **SKIPPED) | {"dense_overlap": 0.05},  # not in view
        {k: v for k, v in geo_record(X, 3, 9, 0.09, **SKIPPED).items() if k != "source"},  # a token candidate
        geo_record(X, 2, 11, 0.09, registration={"neighbours": 1}, **SKIPPED),  # a joint registration
    ]
    on = V.VerificationConfig(siblings=True)
    out = V.verify_candidates([*loops, *weak], X, rel, on)
    assert [d.accepted for d in out] == [True] * 5 + [False] * 6, [d.reason for d in out]
    assert all(d.reason.startswith("verified; pairwise consistent with 4 other loop(s)") for d in out[:3])
    assert (
        out[3].reason
        == f"sibling of the loop of chunks 2 and 10 (the same revisit); pairwise consistent with 4 other loop(s); alone: depths agree little whatever the null: {FLOOR}"
    )
    assert out[4].reason.startswith("sibling of the loop of chunks 1 and 8 (the same revisit)")
    assert out[4].reason.endswith("alone: " + STRUCTURE)
    assert out[3].pcm_residual < 1e-3 and out[4].pcm_residual < 1e-3  # exactly consistent
    off = V.verify_candidates([*loops, *weak], X, rel)  # the default: siblings off (module docstring)
    assert not V.VerificationConfig().siblings
    assert [d.accepted for d in off] == [True] * 3 + [False] * 8
    assert off[4].reason == STRUCTURE and off[3].reason.endswith(FLOOR)
    assert [d.reason for d in out[5:]] == [d.reason for d in off[5:]]
    no_pcm = V.VerificationConfig(siblings=True, pcm=False)
    assert [d.accepted for d in V.verify_candidates([*loops, *weak], X, rel, no_pcm)] == [True] * 3 + [False] * 8
    # siblings never make a revisit of their own: beside a follower-less, verified-less set, all rejected
    assert not any(d.accepted for d in V.verify_candidates(weak, X, rel, on))
    # one verified loop is enough (no PCM between loops, but the sibling's short cycle is tested)
    one = V.verify_candidates([loops[1], weak[0], weak[2]], X, rel, on)
    assert [d.accepted for d in one] == [True, True, False]


def test_siblings_registered_only_when_their_placement_is_accepted(x64):
    """``settle_deferred``: a sibling below the structure null is judged on its placement, its
    refinement and view computed only when accepted so, and decided again on the refined edge
    (or rejected with its refinement's reason)."""
    from swiftjax.pipeline.loop_geometry import settle_deferred

    rel, X, _, _ = chain_problem(4)
    loops = [geo_record(X, 1, 8), geo_record(X, 2, 10), geo_record(X, 0, 11)]
    calls = []
    near = np.asarray(sim3.compose(jnp.asarray(_edge(X, 3, 10)), sim3.exp(jnp.asarray([0.02, 0, 0, 0, 0.002, 0, 0]))))

    def pending(p, q, Z, result):
        r = geo_record(X, p, q, evidence_reason=STRUCTURE, registration_pending=True)
        for key in ("dense_agreement", "dense_overlap", "null_threshold", "null_mean", "null_std"):
            del r[key]
        return r | {"Z": list(map(float, Z)), "_register": lambda: calls.append((q, p)) or result}

    refined = {"Z": list(map(float, _edge(X, 3, 10))), "dense_agreement": 0.12, "dense_overlap": 0.8}
    scale = "registration scale 0.70 x the odometry's, outside [0.77, 1.30]"
    recs = [
        *loops,
        pending(3, 10, near, refined),  # its placement near the truth: registered, accepted on the refined edge
        pending(2, 9, _edge(X, 2, 9, wrong=True), {}),  # its placement wrong: never registered
        pending(1, 11, _edge(X, 1, 11), {"quality_valid": False, "quality_reason": scale}),  # refinement fails
    ]

    def decide(rs):
        for r, d in zip(rs, V.verify_candidates(rs, X, rel, V.VerificationConfig(siblings=True))):
            r.update(accepted=d.accepted, reason=d.reason)

    settle_deferred(decide, recs)
    assert [r["accepted"] for r in recs] == [True] * 4 + [False] * 2, [r["reason"] for r in recs]
    assert sorted(calls) == [(10, 3), (11, 1)]
    assert recs[3]["Z"] == refined["Z"] and "registration_pending" not in recs[3] and "_register" not in recs[3]
    assert recs[3]["reason"].startswith("sibling of the loop of chunks 2 and 10") and recs[3]["reason"].endswith(
        STRUCTURE
    )
    assert recs[4]["reason"] == STRUCTURE and recs[4]["registration_pending"]
    assert recs[5]["reason"] == scale

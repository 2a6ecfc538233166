"""Tests for swiftjax.loops.null (the dense test's per-candidate null) against NumPy loops."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_loop_verification import K, chain_problem, record, ref_dense, scene

from swiftjax import align, sim3
from swiftjax.loops import null as N
from swiftjax.loops import verification as V

# -------------------------------------------------------------------------- references


def ref_quat_matrix(q):
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def ref_null_edges(Z, dst, K_ref, stride, conf_ratio, offsets):
    """The null edges from the docstring, in float64 NumPy with explicit loops."""
    depth, conf, Ks, E = (np.asarray(a, np.float64) for a in dst)
    up, ahead = np.zeros(3), np.zeros(3)
    for g in range(E.shape[0]):
        up -= E[g, 1, :3]  # camera y axis in chunk coordinates (OpenCV: y down)
        ahead += E[g, 2, :3]
    up /= np.linalg.norm(up)
    ahead -= up * (up @ ahead)
    ahead /= np.linalg.norm(ahead)
    side = np.cross(up, ahead)
    values = []
    for g in range(E.shape[0]):
        r = 0.5 * (K_ref[0, 0] / Ks[g, 0, 0] + K_ref[1, 1] / Ks[g, 1, 1])
        mean = np.mean(conf[g][np.isfinite(conf[g])])
        for v in range(0, depth.shape[1], stride):
            for u in range(0, depth.shape[2], stride):
                d, c = r * depth[g, v, u], conf[g, v, u]
                if np.isfinite(d) and d > 0 and np.isfinite(c) and c > conf_ratio * mean:
                    values.append(d)
    median = float(np.median(values))
    Z = np.asarray(Z, np.float64)
    R, t, s = ref_quat_matrix(Z[3:7]), Z[:3], Z[7]
    out = []
    for delta in offsets:  # y' = (s R x + t) + delta d side
        out.append((R, t + delta * median * side, s))
    return out


def as_sim3(R, t, s):
    with jax.enable_x64(True):
        return np.asarray(sim3.from_rst(jnp.asarray(R), jnp.asarray(t), jnp.asarray(s)))


def ref_score(src, dst, S, K_ref, stride, conf_ratio, tol, neighbours):
    """``min`` of both directions' agreement and overlap, from :func:`ref_dense`."""
    R, t, s = ref_quat_matrix(S[3:7]), S[:3], S[7]
    inv = as_sim3(R.T, -(R.T @ t) / s, 1 / s)
    a = ref_dense(src, dst, S, K_ref, stride, conf_ratio, tol, neighbours)
    b = ref_dense(dst, src, inv, K_ref, stride, conf_ratio, tol, neighbours)
    agree = lambda x: x["pairs_agree"] / x["pairs_seen"] if x["pairs_seen"] else 0.0
    over = lambda x: x["num_seen"] / x["num_points"] if x["num_points"] else 0.0
    return min(agree(a), agree(b)), min(over(a), over(b)), min(a["pairs_seen"], b["pairs_seen"])


# ---------------------------------------------------------------------------- null edges


def test_null_offsets_are_symmetric_and_spaced():
    got = N.null_offsets(8, 0.15, 0.4)
    np.testing.assert_allclose(got, [0.15, 0.2333333, 0.3166667, 0.4, -0.15, -0.2333333, -0.3166667, -0.4], rtol=1e-6)


def test_null_consistency_matches_numpy_loops(x64):
    src, dst, S = scene(seed=11)
    cfg = V.VerificationConfig(stride=2, neighbours=2, null_samples=4, null_min_shift=0.1, null_max_shift=0.3)
    offsets = N.null_offsets(4, 0.1, 0.3)
    want = [
        ref_score(src, dst, as_sim3(*e), K, 2, 0.5, cfg.depth_tolerance, 2)
        for e in ref_null_edges(S, dst, K, 2, 0.5, offsets)
    ]
    one = lambda f: align.ChunkFrames(*(np.asarray(a)[None] for a in f))
    got = N.null_consistency(one(src), one(dst), np.asarray(S)[None], K, cfg)
    assert got.score.shape == (1, 4)
    for k, (score, overlap, seen) in enumerate(want):
        assert float(got.score[0, k]) == pytest.approx(score, abs=1e-12), k
        assert float(got.overlap[0, k]) == pytest.approx(overlap, abs=1e-12), k
        assert int(got.pairs_seen[0, k]) == seen, k
    # the null edges are wrong: each agrees less than the true edge
    true = ref_score(src, dst, np.asarray(S), K, 2, 0.5, cfg.depth_tolerance, 2)[0]
    assert max(w[0] for w in want) < 0.8 * true


# ------------------------------------------------------------------------------ decision


def test_null_threshold_is_the_t_prediction_bound():
    rng = np.random.default_rng(0)
    score = 0.2 + 0.03 * rng.standard_normal(16)
    overlap = np.full(16, 0.8)
    seen = np.full(16, 10**6)  # the binomial floor is negligible
    got = N.null_threshold(score, overlap, seen, 0.01, 0.2)
    m, s = np.mean(score), np.std(score, ddof=1)
    t_15_099 = 2.6025  # Student's t, 15 degrees of freedom, upper 1 % (tables)
    assert got.samples == 16 and got.mean == pytest.approx(m) and got.std == pytest.approx(s)
    assert got.threshold == pytest.approx(m + t_15_099 * s * math.sqrt(1 + 1 / 16), abs=2e-4)
    # samples out of view are left out; fewer than three: no threshold
    overlap[:6] = 0.1
    part = N.null_threshold(score, overlap, seen, 0.01, 0.2)
    t_9_099 = 2.8214
    assert part.samples == 10 and part.mean == pytest.approx(np.mean(score[6:]))
    s10 = np.std(score[6:], ddof=1)
    assert part.threshold == pytest.approx(np.mean(score[6:]) + t_9_099 * s10 * math.sqrt(1.1), abs=2e-4)
    overlap[:14] = 0.0
    assert math.isnan(N.null_threshold(score, overlap, seen, 0.01, 0.2).threshold)
    # identical null draws: the spread is floored by a proportion's standard error
    flat = N.null_threshold(np.full(8, 0.3), np.ones(8), np.full(8, 400), 0.01, 0.2)
    assert flat.std == pytest.approx(math.sqrt(0.3 * 0.7 / 400))


def test_sided_null_bounds_each_shift_direction():
    """Two nulls, one per shift direction (:func:`swiftjax.loops.null.null_threshold`, model ``sided``):
    the bound is the larger of the two sides' t prediction bounds (8 samples each: Student's
    ``t_7``), the mean the larger mean; a bimodal sample (one side keeps the road's agreement at
    every shift, synthetic KITTI 06's true candidate 20/2) no longer inflates ``s`` past the
    candidate; a side with fewer than three samples in view leaves the other to decide; with
    neither, the sides pooled."""
    plus = np.asarray([0.451, 0.454, 0.459, 0.46, 0.464, 0.467, 0.472, 0.479])
    minus = np.asarray([0.195, 0.158, 0.127, 0.097, 0.076, 0.061, 0.049, 0.039])
    score, overlap, seen = np.concatenate([plus, minus]), np.full(16, 0.8), np.full(16, 10**6)
    t_7_099 = 2.9980  # Student's t, 7 degrees of freedom, upper 1 % (tables)
    bound = lambda x: np.mean(x) + t_7_099 * np.std(x, ddof=1) * math.sqrt(1 + 1 / 8)
    got = N.null_threshold(score, overlap, seen, 0.01, 0.2, model="sided")
    assert got.threshold == pytest.approx(max(bound(plus), bound(minus)), abs=2e-4)
    assert got.mean == pytest.approx(np.mean(plus)) and got.std == pytest.approx(np.std(plus, ddof=1))
    assert got.samples == 16
    # with the shifts given, the sides are their signs, in whatever order the samples come
    delta = N.null_offsets(16, 0.15, 0.4)
    order = np.random.default_rng(3).permutation(16)
    assert N.null_threshold(score, overlap, seen, 0.01, 0.2, model="sided", offsets=delta) == got
    shuffled = N.null_threshold(score[order], overlap, seen, 0.01, 0.2, model="sided", offsets=delta[order])
    assert shuffled.threshold == pytest.approx(got.threshold) and shuffled.mean == pytest.approx(got.mean)
    pooled = N.null_threshold(score, overlap, seen, 0.01, 0.2)
    assert got.threshold < 0.682 < pooled.threshold  # the true candidate's agreement
    assert N.chance_corrected(0.682, got.mean) > 0.2
    # a unimodal null: each side's bound, the larger, is at least the pooled one's mean
    rng = np.random.default_rng(1)
    flat = 0.2 + 0.03 * rng.standard_normal(16)
    one = N.null_threshold(flat, overlap, seen, 0.01, 0.2, model="sided")
    assert one.threshold == pytest.approx(max(bound(flat[:8]), bound(flat[8:])), abs=2e-4)
    # a side mostly out of view (two samples left): its largest sample and its mean still bound
    part = overlap.copy()
    part[8:14] = 0.0
    only = N.null_threshold(score, part, seen, 0.01, 0.2, model="sided")
    assert only.threshold == pytest.approx(bound(plus), abs=2e-4) and only.samples == 10
    high = score.copy()
    high[14] = 0.9  # one of the two in view agreed 0.9
    one_high = N.null_threshold(high, part, seen, 0.01, 0.2, model="sided")
    assert one_high.threshold == 0.9
    assert one_high.mean == pytest.approx(max(np.mean(plus), (0.9 + minus[7]) / 2))
    # neither side has three in view: the sides pooled (four samples here)
    few = np.zeros(16)
    few[[0, 1, 8, 9]] = 0.8
    pooled4 = N.null_threshold(score, few, seen, 0.01, 0.2, model="sided")
    assert pooled4 == N.null_threshold(score, few, seen, 0.01, 0.2) and pooled4.samples == 4


def ref_line_bound(x, y, ends, t):
    """The upper prediction bound of a straight-line fit at ``ends`` (float64 loops, the textbook
    formula; Student's ``t`` from tables): ``(bounds, fitted values)``."""
    n = len(x)
    xb = sum(x) / n
    yb = sum(y) / n
    sxx = sum((v - xb) ** 2 for v in x)
    b = sum((u - xb) * (v - yb) for u, v in zip(x, y)) / sxx
    a = yb - b * xb
    s = math.sqrt(sum((v - a - b * u) ** 2 for u, v in zip(x, y)) / (n - 2))
    fit = [a + b * e for e in ends]
    return [f + t * s * math.sqrt(1 + 1 / n + (e - xb) ** 2 / sxx) for f, e in zip(fit, ends)], fit


def test_trend_null_bounds_a_line_in_the_shift_per_side():
    """Model ``trend``: per shift direction the least-squares line in ``|δ|`` and its prediction
    bound at both ends of the range (Student's ``t_6`` for 8 samples), the larger side's bound
    and fitted end; the two captured nulls that each other rule gets wrong: the test route's true
    candidate (agreement 0.828; both sides fall with the shift, the sided bound is 0.875) and
    KITTI 06's (0.682; one side flat, the other falling, the pooled bound is 0.795)."""
    off = N.null_offsets(16, 0.15, 0.4)
    x = list(np.abs(off[:8]))
    t_6_099 = 3.1427  # Student's t, 6 degrees of freedom, upper 1 % (tables)
    seen, overlap = np.full(16, 10**6), np.full(16, 0.8)  # the binomial floor is negligible
    cases = {
        0.828: ([0.64, 0.61, 0.53, 0.49, 0.45, 0.41, 0.33, 0.28], [0.6, 0.54, 0.51, 0.47, 0.43, 0.36, 0.3, 0.24]),
        0.682: (
            [0.451, 0.454, 0.459, 0.46, 0.464, 0.467, 0.472, 0.479],
            [0.195, 0.158, 0.127, 0.097, 0.076, 0.061, 0.049, 0.039],
        ),
    }
    for a, (plus, minus) in cases.items():
        score = np.asarray(plus + minus)
        got = N.null_threshold(score, overlap, seen, 0.01, 0.2, model="trend", offsets=off)
        sides = [ref_line_bound(x, y, (0.15, 0.4), t_6_099) for y in (plus, minus)]
        assert got.threshold == pytest.approx(max(max(b) for b, _ in sides), abs=3e-4)
        assert got.mean == pytest.approx(max(max(f) for _, f in sides), abs=1e-9)
        assert got.samples == 16
        assert got.threshold < a and N.chance_corrected(a, got.mean) > 0.2  # accepted
        other = [N.null_threshold(score, overlap, seen, 0.01, 0.2, model=m) for m in ("pooled", "sided")]
        assert max(t.threshold for t in other) > a  # rejected by one of them
    # a side whose agreement RISES with the shift (toward the true place of a wrong edge) is
    # bounded at its far end
    rising = np.asarray([0.1, 0.12, 0.15, 0.2, 0.26, 0.33, 0.41, 0.5] + [0.1] * 8)
    got = N.null_threshold(rising, overlap, seen, 0.01, 0.2, model="trend", offsets=off)
    bounds, fit = ref_line_bound(x, list(rising[:8]), (0.15, 0.4), t_6_099)
    assert got.threshold == pytest.approx(bounds[1], abs=3e-4) and got.threshold > 0.5
    assert got.mean == pytest.approx(fit[1])
    # the samples' own offsets decide the sides (here shuffled) and the range (in view or not)
    perm = np.random.default_rng(2).permutation(16)
    shuffled = N.null_threshold(rising[perm], overlap, seen, 0.01, 0.2, model="trend", offsets=off[perm])
    assert shuffled.threshold == pytest.approx(got.threshold) and shuffled.mean == pytest.approx(got.mean)
    part = overlap.copy()
    part[[0, 7]] = 0.0  # both ends out of view: still bounded at 0.15 and 0.4
    cut = N.null_threshold(rising, part, seen, 0.01, 0.2, model="trend", offsets=off)
    b6, _ = ref_line_bound(x[1:7], list(rising[1:7]), (0.15, 0.4), 3.7469)  # t_4
    assert cut.threshold == pytest.approx(b6[1], abs=3e-4) and cut.samples == 14
    # a side with fewer than four in view: its largest sample and mean; neither side: pooled
    part = overlap.copy()
    part[8:13] = 0.0  # three of the minus side in view
    three = N.null_threshold(rising, part, seen, 0.01, 0.2, model="trend", offsets=off)
    assert three.threshold == pytest.approx(bounds[1], abs=3e-4) and three.samples == 11
    few = np.zeros(16)
    few[[0, 1, 2, 8, 9]] = 0.8
    pooled = N.null_threshold(rising, few, seen, 0.01, 0.2, model="trend", offsets=off)
    assert pooled == N.null_threshold(rising, few, seen, 0.01, 0.2) and pooled.samples == 5
    with pytest.raises(ValueError, match="needs the samples' offsets"):
        N.null_threshold(rising, overlap, seen, 0.01, 0.2, model="trend")
    with pytest.raises(ValueError, match="one of trend, pooled, sided"):
        N.null_threshold(rising, overlap, seen, 0.01, 0.2, model="tuned")


def test_chance_corrected_agreement():
    assert N.chance_corrected(0.4, 0.05) == pytest.approx(0.35 / 0.95)
    assert N.chance_corrected(0.3, 0.3) == pytest.approx(0.0)


def null_record(ci, cj, Z, agreement, mean, std, samples=16):
    t = {16: 2.6025}[samples]
    r = record(ci, cj, Z, agreement=agreement)
    r.update(
        null_mean=mean, null_std=std, null_samples=samples, null_threshold=mean + t * std * math.sqrt(1 + 1 / samples)
    )
    return r


def test_null_rule_accepts_a_low_true_agreement_and_rejects_a_chance_one(x64):
    rel, X, nodes, Z = chain_problem(4)
    p, q = (int(v) for v in nodes[0])
    recs = [
        null_record(q, p, Z[0], 0.40, 0.05, 0.02),  # true, below 0.55, far above its null
        null_record(q, p, Z[0], 0.30, 0.30, 0.03),  # false: its null agrees as much
        null_record(q, p, Z[0], 0.17, 0.037, 0.014),  # hallucinated: significant, but kappa 0.138
    ]
    null = V.verify_candidates(recs, X, rel, V.VerificationConfig(pcm=False))
    fixed = V.verify_candidates(recs, X, rel, V.VerificationConfig(pcm=False, agreement_rule="fixed"))
    assert [d.accepted for d in null] == [True, False, False]
    assert [d.accepted for d in fixed] == [False, False, False]
    assert "no better than under wrong edges" in null[1].reason and "0.300 <= " in null[1].reason
    assert "chance-corrected agreement 0.138 < 0.2" in null[2].reason
    # a record without its null (e.g. written by an older version) falls back to the fixed bound
    old = record(q, p, Z[0], agreement=0.5)
    assert "no null" in V.verify_candidates([old], X, rel)[0].reason


def test_fixed_rule_gives_the_former_verdicts(x64):
    rel, X, nodes, Z = chain_problem(4)
    p, q = (int(v) for v in nodes[0])
    recs = [null_record(q, p, Z[0], a, 0.05, 0.02) for a in (0.2, 0.54, 0.549, 0.55, 0.56, 0.9)]
    got = V.verify_candidates(recs, X, rel, V.VerificationConfig(pcm=False, agreement_rule="fixed"))
    assert [d.accepted for d in got] == [False, False, False, True, True, True]
    assert got[1].reason == "depths disagree across the loop: agreement 0.540 < 0.55"


@pytest.mark.parametrize("model", ["trend", "pooled", "sided"])
def test_candidate_numbers_carry_the_null(model):
    src, dst, S = scene(seed=7)
    half = {"num_points": 900, "fraction_used": 0.4, "rms": 0.02, "valid": True, "pose_fallback": False}
    cfg = V.VerificationConfig(null_samples=8, null_model=model)
    out = V.candidate_numbers(src, dst, S, K, half, half, cfg)
    one = lambda f: align.ChunkFrames(*(np.asarray(a)[None] for a in f))
    nc = N.null_consistency(one(src), one(dst), np.asarray(S)[None], K, cfg)
    offsets = N.null_offsets(8, cfg.null_min_shift, cfg.null_max_shift)
    th = N.null_threshold(
        nc.score[0],
        nc.overlap[0],
        nc.pairs_seen[0],
        cfg.null_false_alarm,
        cfg.min_overlap,
        model=model,
        offsets=offsets,
    )
    assert out["null_samples"] == th.samples and out["null_mean"] == pytest.approx(th.mean)
    assert out["null_kappa"] == pytest.approx(N.chance_corrected(out["dense_agreement"], th.mean))
    assert out["null_threshold"] == pytest.approx(th.threshold) and out["null_std"] == pytest.approx(th.std)
    assert V.VerificationConfig().null_model == "trend"  # the default
    fixed = V.candidate_numbers(src, dst, S, K, half, half, V.VerificationConfig(agreement_rule="fixed"))
    assert not any(k.startswith("null_") for k in fixed)


@pytest.mark.parametrize(
    "kw,match",
    [
        (
            {"agreement_rule": "tuned"},
            "VerificationConfig.agreement_rule: invalid value 'tuned'; allowed: one of null, fixed",
        ),
        ({"null_samples": 5}, "VerificationConfig.null_samples: invalid value 5; allowed: an even integer >= 4"),
        ({"null_false_alarm": 0.0}, "VerificationConfig.null_false_alarm: 0.0 is out of range"),
        ({"null_min_kappa": 1.0}, "VerificationConfig.null_min_kappa: 1.0 is out of range"),
        ({"null_min_shift": 0.5, "null_max_shift": 0.2}, "null_min_shift <= null_max_shift"),
    ],
)
def test_verification_config_rejects_bad_null_options(kw, match):
    with pytest.raises(ValueError, match=match):
        V.VerificationConfig(**kw)


def test_pipeline_option_reaches_the_verification_config():
    from swiftjax.options import build
    from swiftjax.pipeline import PipelineConfig

    assert build(V.VerificationConfig, PipelineConfig()).agreement_rule == "null"
    assert build(V.VerificationConfig, PipelineConfig(loop_agreement="fixed")).agreement_rule == "fixed"
    with pytest.raises(ValueError, match="loop_agreement"):
        PipelineConfig(loop_agreement="tuned")


def test_null_needed_is_exact(x64):
    """A candidate the null cannot save (null_needed False) is rejected by every complete null:
    checked by brute force over agreements, overlaps and null means/spreads (and no null)."""
    rel, X, nodes, Z = chain_problem(4)
    p, q = (int(v) for v in nodes[0])
    cfg = V.VerificationConfig(pcm=False)
    rng = np.random.default_rng(3)
    nulls = [(m, s) for m in (0.0, 0.01, 0.05, 0.2, 0.5, 0.9, 0.999) for s in (0.0, 0.01, 0.1)]
    nulls += [tuple(x) for x in rng.uniform(0, 1, (40, 2)) * [1.0, 0.2]]
    for a in (*np.linspace(0.0, 1.0, 41), 0.1999, 0.2, math.nan):
        for ov in (0.1, 0.2, 0.9, math.nan):
            skip = not V.null_needed(a, ov, cfg)
            recs = [null_record(q, p, Z[0], a, m, s) for m, s in nulls] + [record(q, p, Z[0], a, ov)]
            for r in recs:
                r["dense_overlap"] = ov
            got = V.verify_candidates(recs, X, rel, cfg)
            if skip:  # every null (and none) rejects it; so does the record without its null
                assert not any(d.accepted for d in got), (a, ov)
                r = record(q, p, Z[0], a, ov)
                r["null_skipped"] = True
                assert not V.verify_candidates([r], X, rel, cfg)[0].accepted
            else:  # some null accepts it: the null is needed (κ_min = 0.2 <= a, overlap seen)
                assert math.isfinite(a) and ov >= cfg.min_overlap and a >= 0.2
                assert V.verify_candidates([null_record(q, p, Z[0], a, 0.0, 0.0)], X, rel, cfg)[0].accepted or a == 0.0


def test_candidate_numbers_null_when_needed():
    """Without the null where it cannot change the verdict; the same numbers elsewhere."""
    src, dst, S = scene(seed=7)
    half = {"num_points": 900, "fraction_used": 0.4, "rms": 0.02, "valid": True, "pose_fallback": False}
    cfg = V.VerificationConfig(null_samples=4)
    full = V.candidate_numbers(src, dst, S, K, half, half, cfg)
    lazy = V.candidate_numbers(src, dst, S, K, half, half, cfg, null_when_needed=True)
    assert full.keys() == lazy.keys() and "null_skipped" not in lazy  # the true edge agrees: the null decides
    for k in full:
        np.testing.assert_equal(lazy[k], full[k])
    wrong = np.asarray(S, np.float64).copy()
    wrong[:3] += [6.0, 0.0, 4.0]  # slid away: little agrees
    full = V.candidate_numbers(src, dst, wrong, K, half, half, cfg)
    lazy = V.candidate_numbers(src, dst, wrong, K, half, half, cfg, null_when_needed=True)
    assert full["dense_agreement"] < 0.2 and lazy["null_skipped"]
    assert {k for k in full if not k.startswith("null_")} == {k for k in lazy if not k.startswith("null_")}
    for k in full:
        if not k.startswith("null_"):
            np.testing.assert_equal(lazy[k], full[k])


@pytest.mark.parametrize("samples", [4, 6, 16])
def test_null_rounds_split_each_side(samples):
    """Two disjoint rounds that together are every edge; each takes every other offset of each
    side, so both sides (first +delta, then -delta) and the range of delta are in the first."""
    first, second = N.null_rounds(samples)
    assert sorted([*first, *second]) == list(range(samples))
    offsets = N.null_offsets(samples, 0.15, 0.4)
    half = samples // 2
    want = [l for l in range(half) if l % 2 == 0]
    np.testing.assert_array_equal(first, want + [half + l for l in want])
    assert offsets[first].min() < 0 < offsets[first].max()
    assert np.all(offsets[first][: len(want)] > 0) and np.all(offsets[first][len(want) :] < 0)
    assert abs(offsets[first][0]) == pytest.approx(0.15)


def test_kappa_settled_is_exact(x64):
    """Whenever the first round settles a candidate, every completion of the null (values in
    [0, 1], in view or not, both rules) rejects it, and so do the first round's own numbers;
    where it does not, the completion that agrees nowhere gives kappa >= kappa_min (the bound
    is tight)."""
    rel, X, nodes, Z = chain_problem(4)
    p, q = (int(v) for v in nodes[0])
    rng = np.random.default_rng(0)
    cfg = V.VerificationConfig(pcm=False)
    first, second = N.null_rounds(16)
    settled = open_ = 0

    off = N.null_offsets(16, cfg.null_min_shift, cfg.null_max_shift)

    def verdict(a, score, overlap, seen, model, offsets):
        th = N.null_threshold(score, overlap, seen, cfg.null_false_alarm, cfg.min_overlap, model=model, offsets=offsets)
        r = record(q, p, Z[0], agreement=a)
        r.update(null_threshold=th.threshold, null_mean=th.mean, null_std=th.std, null_samples=th.samples)
        return V.verify_candidates([r], X, rel, cfg)[0].accepted

    for _ in range(300):
        a = float(rng.uniform(0.2, 0.6))
        s1 = rng.uniform(0, 0.4, 8) * rng.uniform(0.2, 1.0)
        o1 = np.where(rng.uniform(size=8) < 0.85, 0.5, 0.01)  # some drawn samples out of view
        n1 = np.full(8, 500.0)
        stop = N.kappa_settled(a, s1, o1, n1, 8, cfg.null_min_kappa, cfg.min_overlap)
        if stop:
            settled += 1
            for model in ("trend", "pooled", "sided"):
                assert not verdict(a, s1, o1, n1, model, off[first])  # the first round's numbers
                for completion in range(6):
                    s2 = [np.zeros(8), np.ones(8), rng.uniform(0, 1, 8)][completion % 3]
                    o2 = np.full(8, 0.5 if completion < 3 else 0.01)  # all in view / none
                    s, o = np.empty(16), np.empty(16)
                    s[first], s[second], o[first], o[second] = s1, s2, o1, o2
                    assert not verdict(a, s, o, np.full(16, 500.0), model, off), (a, s1, completion)
        elif (o1 >= cfg.min_overlap).sum() >= 3:
            open_ += 1
            k = int((o1 >= cfg.min_overlap).sum())
            m_low = s1[o1 >= cfg.min_overlap].sum() / (k + 8)
            assert N.chance_corrected(a, m_low) >= cfg.null_min_kappa
    assert settled > 30 and open_ > 30


def test_candidate_numbers_null_in_rounds():
    """Where the first round settles the verdict the second is not drawn: the first round's
    numbers (K/2 samples), null_stopped, and the complete null's verdict.  ``complete`` draws
    both rounds whatever the first gives: the complete null's numbers, equal to all ``K`` at once."""
    src, dst, S = scene(seed=7)
    half = {"num_points": 900, "fraction_used": 0.4, "rms": 0.02, "valid": True, "pose_fallback": False}
    rel, X, nodes, Z = chain_problem(4)
    for kappa, stops in ((0.2, False), (0.5, True)):  # agreement 0.54, null mean 0.26: kappa 0.37
        cfg = V.VerificationConfig(null_samples=8, null_min_kappa=kappa, null_model="pooled", pcm=False)
        full = V.candidate_numbers(src, dst, S, K, half, half, cfg)
        lazy = V.candidate_numbers(src, dst, S, K, half, half, cfg, null_when_needed=True)
        assert lazy.get("null_stopped", False) is stops and "null_stopped" not in full
        assert lazy["null_samples"] == (4 if stops else full["null_samples"])
        complete = V.candidate_numbers(src, dst, S, K, half, half, cfg, null_when_needed=True, complete=True)
        assert complete.keys() == full.keys()
        for k in full:
            np.testing.assert_equal(complete[k], full[k])
            if not stops:
                np.testing.assert_equal(lazy[k], full[k])
        verdicts = [
            V.verify_candidates(
                [{**record(1, 8, Z[0]), **{k: v for k, v in r.items() if k.startswith(("dense", "null"))}}], X, rel, cfg
            )[0]
            for r in (full, lazy)
        ]
        assert verdicts[0].accepted == verdicts[1].accepted == (not stops)

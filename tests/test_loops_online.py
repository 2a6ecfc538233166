"""Tests for swiftjax.loops.online: prefix whitening on a doubling schedule, proposals as chunks
arrive, the final pass bit-identical to find_loops, and --whitening-from's loader."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from swiftjax import loops as L
from swiftjax.chunks import chunk_schedule
from swiftjax.io.chunk_store import ChunkStore
from swiftjax.loops import detection, online
from swiftjax.prediction import ChunkPrediction


def ref_l2(x):
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def planted(n, d, seed, loops, noise):
    """Random unit descriptors with planted revisits: frames a..a+len resemble b..b+len."""
    rng = np.random.default_rng(seed)
    G = rng.normal(size=(n, d))
    for a, b, length in loops:
        G[a : a + length] = G[b : b + length] + noise * rng.normal(size=(length, d))
    return ref_l2(G).astype(np.float32)


def chunk_copies(G, sched, seed=0, jitter=1e-3):
    """Each chunk's own copy of its frames' descriptors (overlap frames differ per chunk, as two
    VGGT calls differ), and the [N, d] array the temporal stage assembles (later chunk wins)."""
    rng = np.random.default_rng(seed)
    chunks, assembled = [], np.zeros_like(G)
    for t in range(sched.num_chunks):
        f = sched.frames(t)
        g = ref_l2(G[f] + jitter * rng.normal(size=(len(f), G.shape[1]))).astype(np.float32)
        chunks.append((f, g))
        assembled[f] = g
    return chunks, assembled


def feed(det, chunks):
    return [det.add(f, g) for f, g in chunks]


def _same_loops(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert (x.i, x.j, x.chunk_i, x.chunk_j, x.local_i, x.local_j) == (
            y.i,
            y.j,
            y.chunk_i,
            y.chunk_j,
            y.local_i,
            y.local_j,
        )
        assert np.float32(x.score).tobytes() == np.float32(y.score).tobytes()
        np.testing.assert_array_equal(x.frames, y.frames)


@pytest.mark.parametrize("rule", ["adaptive", "fixed", "authors"])
def test_finish_bit_identical_to_find_loops(rule):
    n = 700
    G = planted(n, 64, seed=1, loops=((450, 60, 40), (640, 300, 30)), noise=0.1)
    sched = chunk_schedule(n)
    chunks, assembled = chunk_copies(G, sched)
    o = L.LoopOptions(rule=rule, threshold=0.6)
    det = online.OnlineLoopDetector(o)
    proposals = feed(det, chunks)
    assert sum(map(len, proposals)) >= 1 or rule == "authors"  # 0.98 on these descriptors: none
    np.testing.assert_array_equal(det.descriptors, assembled)
    got, got_d = det.finish(return_details=True)
    ref, ref_d = L.find_loops(assembled, sched, o, return_details=True)
    assert len(ref) >= 2 or rule == "authors"
    _same_loops(got, ref)
    for key in ("z", "g1"):
        np.testing.assert_array_equal(np.asarray(got_d[key]), np.asarray(ref_d[key]))
    np.testing.assert_array_equal(np.asarray(got_d["whitening"].projection), np.asarray(ref_d["whitening"].projection))
    # the chunks as added are the schedule
    _same_loops(det.finish(sched), ref)
    # the whole-sequence whitening the loader uses is find_loops' own
    w = online.fit_sequence_whitening(assembled, o)
    np.testing.assert_array_equal(np.asarray(w.projection), np.asarray(ref_d["whitening"].projection))


def _ref_whitening(G, remove, dim, eps):
    G = np.asarray(G, np.float64)
    mu = G.mean(0)
    lam, Q = np.linalg.eigh((G - mu).T @ (G - mu) / len(G))
    lam, Q = lam[::-1], Q[:, ::-1]
    kept = slice(remove, remove + dim)
    return mu, Q[:, kept] / np.sqrt(np.maximum(lam[kept], 0) + eps), lam[kept]


def test_prefix_whitening_equals_numpy_pca_of_the_prefix():
    """After each refit the whitening is the float64 NumPy PCA whitening of the power-normalised
    prefix (d' = max(8, n // 4) capped at dim), to float32 precision."""
    rng = np.random.default_rng(3)
    d, n = 48, 400
    scales = np.geomspace(10.0, 0.1, d)
    G = (rng.normal(size=(n, d)) * scales) @ np.linalg.qr(rng.normal(size=(d, d)))[0] + 3.0 * rng.normal(size=d)
    G = G.astype(np.float32)
    o = L.LoopOptions(min_separation=20, dim=16)
    sched = chunk_schedule(n, 40, 10)
    det = online.OnlineLoopDetector(o)
    checked = 0
    for t in range(sched.num_chunks):
        f = sched.frames(t)
        det.add(f, G[f])
        if det.fits and det.fits[-1] == det.n:
            m = det.n
            g1 = ref_l2(np.sign(G[:m].astype(np.float64)) * np.abs(G[:m].astype(np.float64)) ** o.beta)
            mu, W, lam = _ref_whitening(g1, o.remove, min(o.dim, max(8, m // 4)), o.eps)
            w = det.whitening
            np.testing.assert_allclose(np.asarray(w.mean), mu, atol=1e-6)
            np.testing.assert_allclose(np.asarray(w.eigenvalues), lam, rtol=2e-4)
            Z = np.asarray(L.whiten(w, L.power_normalize(G[:m], o.beta)))
            np.testing.assert_allclose(np.abs(Z), np.abs(ref_l2((g1 - mu) @ W)), atol=2e-3)
            checked += 1
    assert det.fits == [70, 100, 190, 340] and checked == 4  # m = 42: the first ends >= 42, 84, 168, 336


def test_refit_schedule_doubles_from_the_minimum():
    o = L.LoopOptions(min_separation=30)
    m = online.min_descriptors(o)
    assert m == 62
    n = 560
    G = planted(n, 32, seed=2, loops=(), noise=0.0)
    sched = chunk_schedule(n, 50, 10)
    det = online.OnlineLoopDetector(o)
    compiled = detection._detect_loops._cache_size()
    feed(det, [(sched.frames(t), G[sched.frames(t)]) for t in range(sched.num_chunks)])
    # doubling buckets: at most two detect_loops compiles per whitening (14 chunks here)
    assert detection._detect_loops._cache_size() - compiled <= 2 * len(det.fits)
    ends = list(sched.ends)
    expected, level = [], m
    for e in ends:  # independent: the first chunk end reaching m, 2m, 4m, ... (skipping passed levels)
        if e >= level:
            expected.append(int(e))
            while level <= e:
                level *= 2
    assert det.fits == expected == [90, 130, 250, 530]
    # nothing is proposed, nor whitened, before m frames
    det2 = online.OnlineLoopDetector(o)
    assert det2.add(np.arange(50), G[:50]) == [] and det2.whitening is None and det2.threshold == np.inf
    assert not online.refit_due(61, None, 62) and online.refit_due(62, None, 62)
    assert not online.refit_due(123, 62, 62) and online.refit_due(124, 62, 62) and not online.refit_due(247, 130, 62)


@pytest.fixture(scope="module")
def demo_route():
    from swiftjax.synthetic import places
    from swiftjax.synthetic.routes import loop_route

    poses = loop_route()
    params = places.make_place_params(places.PlaceTokenConfig())
    sched = chunk_schedule(len(poses))
    chunks = []
    for t in range(sched.num_chunks):
        f = sched.frames(t)
        chunks.append((f, np.asarray(L.frame_descriptor(places.place_tokens(params, poses[f].astype(np.float32), f)))))
    return poses, sched, chunks


def test_demo_route_true_loop_proposed_within_two_chunks_no_false_one(demo_route):
    """The demo route (618 frames, 1.25 laps): the revisit starts at the ground truth's first
    loop frame; the online detector proposes a true loop at most 2 chunks after the chunk that
    brings that frame, and nothing false (ground truth: position and heading)."""
    from swiftjax.synthetic import places

    poses, sched, chunks = demo_route
    gt = places.ground_truth_loops(poses)
    revisit = int(gt[:, 0].min())
    revisit_chunk = next(t for t, (f, _) in enumerate(chunks) if revisit in f)
    det = online.OnlineLoopDetector()
    first_true = None
    for t, new in enumerate(feed(det, chunks)):
        if new:
            ev = places.evaluate_loops(np.array([(lp.i, lp.j) for lp in new]), gt)
            assert ev.precision == 1.0, (t, new)
            first_true = t if first_true is None else first_true
    assert first_true is not None and first_true - revisit_chunk <= 2, (first_true, revisit_chunk)
    assert len(det.proposed) >= 2
    # the final pass is the offline one
    _same_loops(det.finish(), L.find_loops(det.descriptors, sched))


def _write_run(run_dir, chunks, d):
    store = ChunkStore(run_dir)
    for t, (f, g) in enumerate(chunks):
        s = len(f)
        pred = ChunkPrediction(
            np.ones((s, 2, 3), np.float32),
            np.ones((s, 2, 3), np.float32),
            np.zeros((s, 3, 4), np.float32),
            np.tile(np.eye(3, dtype=np.float32), (s, 1, 1)),
            descriptors=g[:, :d],
        )
        store.save("chunk", t, pred, extra={"frames": np.asarray(f, np.int64)})


def test_whitening_from_run_dir(tmp_path):
    n = 400
    G = planted(n, 32, seed=5, loops=((300, 40, 30),), noise=0.1)
    sched = chunk_schedule(n)
    chunks, assembled = chunk_copies(G, sched, seed=1)
    run = tmp_path / "run"
    _write_run(run, chunks, 32)
    np.testing.assert_array_equal(online.recorded_descriptors(run), assembled)
    o = dataclasses.replace(L.LoopOptions(), min_separation=50)
    w = online.load_whitening(run, o, descriptor_dim=32)
    _, details = L.find_loops(assembled, sched, o, return_details=True)
    np.testing.assert_array_equal(np.asarray(w.projection), np.asarray(details["whitening"].projection))
    np.testing.assert_array_equal(np.asarray(w.mean), np.asarray(details["whitening"].mean))
    # a given whitening is used from the start: no refit; the final pass is still offline's
    det = online.OnlineLoopDetector(o, whitening=w, whitening_source=str(run))
    feed(det, chunks)
    assert det.fits == [] and det.whitening is w
    assert [(lp.i, lp.j) for lp in det.proposed][:1] and all(lp.i >= 300 for lp in det.proposed)
    _same_loops(det.finish(), L.find_loops(assembled, sched, o))

    # refusals: one line naming the path
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(online.WhiteningSourceError, match=f"{empty}: not a run directory .*no {empty / 'chunks'}"):
        online.load_whitening(empty)
    assert not (empty / "chunks").exists()  # looking created nothing
    with pytest.raises(online.WhiteningSourceError, match=f"{run}: its descriptors are 32-D but this run's are 64-D"):
        online.load_whitening(run, descriptor_dim=64)
    (tmp_path / "bare" / "chunks").mkdir(parents=True)
    with pytest.raises(online.WhiteningSourceError, match="no chunk files"):
        online.load_whitening(tmp_path / "bare")
    gap = tmp_path / "gap"
    _write_run(gap, [chunks[0], chunks[2]], 32)
    with pytest.raises(online.WhiteningSourceError, match="miss the descriptors of 15 frame"):
        online.load_whitening(gap)
    det = online.OnlineLoopDetector(o, whitening=w, whitening_source=str(run))
    with pytest.raises(ValueError, match=f"{run}: its whitening is for 32-D descriptors but this run's are 16-D"):
        det.add(np.arange(10), G[:10, :16])
    for err in (online.WhiteningSourceError("x"),):
        assert isinstance(err, ValueError) and len(str(err).splitlines()) == 1


def test_add_rejects_out_of_order_frames_and_nan():
    det = online.OnlineLoopDetector()
    G = planted(100, 8, seed=0, loops=(), noise=0.0)
    det.add(np.arange(50), G[:50])
    with pytest.raises(ValueError, match="frames 60..69 do not continue the 50 frames seen"):
        det.add(np.arange(60, 70), G[60:70])
    bad = G[40:60].copy()
    bad[3, 0] = np.nan
    with pytest.raises(ValueError, match="descriptors of frames 40..59 contains NaN"):
        det.add(np.arange(40, 60), bad)
    with pytest.raises(ValueError, match="no frame was added"):
        online.OnlineLoopDetector().finish()


def test_coalesced_chunks_propose_once_and_finish_unchanged():
    """``add(..., propose=False)`` (the engine's loop worker catching up): the chunks fed
    without a pass are tested at the next proposing ``add``, so a planted loop is proposed
    as when every chunk proposes; no refit happens in between; ``finish`` is still
    ``find_loops`` bit for bit."""
    n = 400
    G = planted(n, 32, seed=5, loops=((300, 40, 30),), noise=0.1)
    sched = chunk_schedule(n)
    chunks, assembled = chunk_copies(G, sched, seed=1)
    o = dataclasses.replace(L.LoopOptions(), min_separation=50)
    every = online.OnlineLoopDetector(o)
    feed(every, chunks)
    batched = online.OnlineLoopDetector(o)
    passes = []
    for k, (f, g) in enumerate(chunks):
        last = k + 1 == len(chunks)
        propose = last or k % 3 == 2
        fits = list(batched.fits)
        out = batched.add(f, g, propose=propose)
        if not propose:
            assert out == [] and batched.fits == fits  # recorded only
        else:
            passes.append(batched.n)
    assert set(batched.fits) <= set(passes)
    pairs = lambda det: {(lp.chunk_i, lp.chunk_j) for lp in det.proposed}
    assert pairs(every) and pairs(every) == pairs(batched)
    assert all(lp.i >= 300 for lp in batched.proposed)
    _same_loops(batched.finish(), L.find_loops(assembled, sched, o))
    _same_loops(batched.finish(), every.finish())


def test_warm_up_compiles_ahead_and_changes_nothing():
    """``warm_up`` (the engine's loop worker when idle) compiles the programs of the next
    buffer / chunk-table growth and of the next refit, once each (then returns False), and the
    proposals, fits and threshold are those of a detector never warmed up."""
    n = 400
    G = planted(n, 32, seed=5, loops=((300, 40, 30),), noise=0.1)
    sched = chunk_schedule(n)
    chunks, _ = chunk_copies(G, sched, seed=1)
    o = dataclasses.replace(L.LoopOptions(), min_separation=50)
    plain, warmed = online.OnlineLoopDetector(o), online.OnlineLoopDetector(o)
    from swiftjax.loops.detection import _detect_loops

    compiled, grown = 0, []
    for f, g in chunks:
        cap = None if warmed._G is None else warmed._G.shape[0]
        programs = _detect_loops._cache_size()
        a, b = plain.add(f, g), warmed.add(f, g)
        if cap is not None and warmed._G.shape[0] > cap and warmed._warmed:
            grown.append(_detect_loops._cache_size() - programs)  # warmed: no new detection program
        _same_loops(a, b)
        assert warmed.fits == plain.fits and warmed.threshold == plain.threshold
        while warmed.warm_up():
            compiled += 1
        assert not warmed.warm_up()
    assert compiled >= 3 and grown and not any(grown)
    _same_loops(warmed.proposed, plain.proposed)

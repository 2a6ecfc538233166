"""The loop-closure stage: find loops -> loop-centric chunks -> align both halves -> loop edges.

Loops are found from the per-frame descriptors (:func:`swiftjax.loops.find_loops`); a loop
between neighbouring chunks duplicates their temporal edge and is dropped.  Each loop
``(i, j)`` gets a loop-centric chunk of the ``2 x loop_half_window`` frames around ``i`` and
``j``; each half is aligned with the temporal chunk it overlaps, reading only those frames
from the chunk's file (memory-mapped), and the two alignments give the loop edge
(:func:`swiftjax.loops.loop_edge`).  Finished loop edges are recorded in the manifest.

Every candidate is a hypothesis (``loop_verification = "geometric"``, the default): its
temporal chunks' own frames around both ends are checked against each other under the
candidate edge, its loop chunk's alignments are checked, and the survivors must be pairwise
consistent (:mod:`swiftjax.loops.verification`).  Each candidate, accepted or not, is a record
with its numbers, ``accepted`` and a one-line ``reason``; only accepted ones become edges.
``loop_verification = "none"`` is the authors' rule: every candidate is an edge.

``loop_geometry = true`` adds a second candidate source beside the tokens, chunk pairs whose
dense geometry matches whichever way the revisit was driven, with edges from registering the
two chunks' point clouds (:mod:`swiftjax.pipeline.loop_geometry`); records carry ``source``
(``tokens`` or ``geometry``).  A gated pair beside an accepted token candidate is recorded but not
registered (:func:`redundant_geometry` would reject it; :func:`_decide_with_geometry`).  Its
programs compile on a background thread (:func:`swiftjax.pipeline.loop_geometry.compile_ahead`),
all of them beside the token candidates' work.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import _faults, align, loops, sim3
from swiftjax.loops import verification as lv
from swiftjax.pipeline import loop_geometry
from swiftjax.pipeline.alignment import align_pair, both
from swiftjax.pipeline.config import PipelineConfig
from swiftjax.pipeline.results import LoopEdge, LoopResult, TemporalResult
from swiftjax.pipeline.rundir import RunContext
from swiftjax.pipeline.user_camera import UserCamera
from swiftjax.posegraph import chain_poses
from swiftjax.prediction import ChunkPrediction

__all__ = [
    "CandidateSource",
    "decide",
    "loop_record",
    "needs_numbers",
    "redundant_geometry",
    "run",
    "verification_numbers",
    "without_tokens",
]


#: A loop candidate source: ``(descriptors [N, d], schedule, options) -> [Loop]`` over the frames
#: seen so far (offline: :func:`swiftjax.loops.find_loops` over the whole sequence).
CandidateSource = Callable[[np.ndarray, Any, loops.LoopOptions], list[loops.Loop]]


def run(ctx: RunContext, temporal: TemporalResult, candidates: CandidateSource | None = None) -> LoopResult:
    """Loop edges from ``temporal``'s descriptors and the chunk store (none when loop closure
    is off or there are fewer than three chunks); ``candidates``: where the loop candidates
    come from (default: every frame's descriptor, :func:`swiftjax.loops.find_loops`)."""
    config = ctx.config
    if not (config.loop_closure and ctx.schedule.num_chunks > 2):
        return LoopResult([], [])
    # the geometric source's programs compile on a thread while the token candidates are worked on
    ahead = loop_geometry.compile_ahead(ctx, temporal.K_ref, config.geometry) if config.loop_geometry else None
    try:
        return _run(ctx, temporal, candidates, ahead)
    finally:
        if ahead is not None:
            ahead.cancel()  # no thread outlives the stage (also when interrupted)


def _run(
    ctx: RunContext,
    temporal: TemporalResult,
    candidates: CandidateSource | None,
    ahead: loop_geometry.CompileAhead | None,
) -> LoopResult:
    """:func:`run` once loop closure is on; ``ahead``: the geometric source's compiles under way."""
    config, schedule, manifest, timer = ctx.config, ctx.schedule, ctx.manifest, ctx.timer
    K_ref = temporal.K_ref
    loop_records: list[dict[str, Any]] = []
    loop_edges: list[LoopEdge] = []
    with timer("loop detection"):
        found = (candidates or loops.find_loops)(temporal.descriptors, schedule, config.loops)
        # A loop between neighbouring chunks duplicates their temporal edge: drop it.
        neighbours = [lp for lp in found if abs(lp.chunk_i - lp.chunk_j) < 2]
        found = [lp for lp in found if abs(lp.chunk_i - lp.chunk_j) >= 2]

    # The loop chunks not recorded yet, predicted in order by the executor (fanned out on a pool).
    todo: dict[str, np.ndarray] = {}  # insertion-ordered: the first occurrence of each loop
    for lp in found:
        if f"{lp.i}-{lp.j}" not in manifest.data["loop_edges"]:
            todo.setdefault(f"{lp.i}-{lp.j}", lp.frames)
    predictions = ctx.executor.map(ctx.predictor, list(todo.values()), without_tokens)
    with timer("loop chunks"):
        try:
            for lp in ctx.bar(found, desc="loop chunks", unit="loop"):
                key = f"{lp.i}-{lp.j}"
                record = manifest.data["loop_edges"].get(key)
                if record is None:
                    with timer("predict (loop chunks)"):
                        pred = next(predictions)
                    record = loop_record(ctx, lp, pred, K_ref)
                    manifest.data["loop_edges"][key] = record
                    manifest.save()  # recorded (fsync'd) before the next loop chunk
                    _faults.point("loop-recorded", len(loop_records))
                if needs_numbers(config, record):
                    record.update(verification_numbers(ctx, lp, record, K_ref))
                    manifest.save()
                loop_records.append(record)
        finally:
            predictions.close()
            manifest.flush()  # also when interrupted: keep the finished loop edges
    for r in loop_records:
        r.setdefault("source", "tokens")
    # The decisions depend on all candidates: recomputed every run, written beside the numbers.
    geometric: list[dict[str, Any]] = []
    if ahead is not None:  # the second candidate source (swiftjax.pipeline.loop_geometry)
        geometric = _decide_with_geometry(ctx, temporal, loop_records, ahead)
    else:
        decide(ctx, temporal.relative, loop_records)
    loop_records += geometric
    for r in loop_records:
        if r["accepted"]:
            # Edge (c_j, c_i): Z maps chunk c_i coordinates into chunk c_j (loops.loop_edge);
            # a registration's is its plausible placements' mean (loop_geometry.graph_edge).
            edge = loop_geometry.graph_edge(r, config.edge_pixels_per_sample) if r["source"] == "geometry" else None
            Z, info = edge if edge is not None else (np.asarray(r["Z"]), None)
            loop_edges.append(LoopEdge(r["chunk_j"], r["chunk_i"], Z, info))
    for r in geometric:
        r.pop("_stats", None)
        r.pop("_closed_by", None)
        r.pop("_registered", None)
        r.pop("_covariance", None)
        r.pop("_register", None)
    loop_records += [
        {
            "i": lp.i,
            "j": lp.j,
            "score": lp.score,
            "chunk_i": lp.chunk_i,
            "chunk_j": lp.chunk_j,
            "accepted": False,
            "reason": f"chunks {lp.chunk_j} and {lp.chunk_i} are neighbours (their temporal edge)",
            "source": "tokens",
        }
        for lp in neighbours
    ]
    # Every candidate's verdict, also those without a loop chunk (the viewer reads this list).
    manifest.data["loops"] = [
        {k: r[k] for k in ("i", "j", "score", "chunk_i", "chunk_j", "accepted", "reason", "source") if k in r}
        for r in loop_records
    ]
    manifest.save_soon()
    manifest.flush()
    _log_decisions(ctx, loop_records)
    return LoopResult(loop_records, loop_edges)


def _decide_with_geometry(
    ctx: RunContext,
    temporal: TemporalResult,
    tokens: list[dict[str, Any]],
    ahead: loop_geometry.CompileAhead | None = None,
) -> list[dict[str, Any]]:
    """The geometric candidates' records (:func:`swiftjax.pipeline.loop_geometry.candidates`),
    decided together with the token candidates ``tokens`` (both decided in place); ``ahead``:
    the geometric programs' compiles under way (:func:`~swiftjax.pipeline.loop_geometry.compile_ahead`).

    The gated pairs beside a token candidate that the decision accepts are not registered
    (``closed``, :func:`~swiftjax.pipeline.loop_geometry.closing`): :func:`redundant_geometry`
    would reject them whatever their numbers.  Which token candidates are accepted is known
    before the geometric ones are registered from a provisional decision of the token
    candidates alone; the joint decision (PCM over both sources) may reject one of them, and
    then the pairs it left unregistered that no jointly accepted token candidate closes are
    registered and everything is decided again, until no such pair is left.  The verdicts
    then equal those without the prune, unless the unregistered pairs, had they reached PCM,
    would have changed the maximum consistent set (docs/performance/reverse-revisits.md)."""
    config = ctx.config
    taken = {loop_geometry.chunk_pair(r) for r in tokens}
    closed: list[tuple[int, int]] = []
    if config.loop_verification != "none":  # without verification nothing is redundant
        provisional = [dict(r) for r in tokens]
        decide(ctx, temporal.relative, provisional)
        closed = [loop_geometry.chunk_pair(r) for r in provisional if r["accepted"]]
    chain = chain_poses(temporal.relative)
    with ctx.timer("loop geometry"):
        geometric = loop_geometry.candidates(
            ctx, temporal.K_ref, taken, config.verification, config.geometry, chain=chain, closed=closed, ahead=ahead
        )
    pool = [r for r in geometric if "accepted" not in r]  # the ones the decision decides
    settle = functools.partial(decide, ctx, temporal.relative)  # deferred work when accepted
    with ctx.timer("loop geometry"):  # (the decisions book their own time: "loop verification")
        loop_geometry.settle_deferred(settle, tokens + pool)
    while True:
        accepted = [loop_geometry.chunk_pair(r) for r in tokens if r["accepted"]]
        reopen = {
            loop_geometry.chunk_pair(r)
            for r in geometric
            if "_closed_by" in r and loop_geometry.closing(loop_geometry.chunk_pair(r), accepted) is None
        }
        if not reopen:
            return geometric
        ctx.log(f"loop geometry: {len(reopen)} pair(s) left unregistered beside a token loop the decision rejects")
        with ctx.timer("loop geometry"):
            more = loop_geometry.candidates(
                ctx, temporal.K_ref, taken, config.verification, config.geometry, chain=chain, only=reopen, ahead=ahead
            )
        new = {loop_geometry.chunk_pair(r): r for r in more}
        geometric = [new.get(loop_geometry.chunk_pair(r), r) for r in geometric]
        pool += [r for r in more if "accepted" not in r]
        with ctx.timer("loop geometry"):
            loop_geometry.settle_deferred(settle, tokens + pool)


def loop_record(ctx: RunContext, lp: loops.Loop, pred: ChunkPrediction, K_ref: np.ndarray) -> dict[str, Any]:
    """The record of loop ``lp`` from its loop-centric chunk's prediction ``pred``: each half
    aligned with the temporal chunk it overlaps (only those frames read from the chunk's file),
    the loop edge ``Z`` (:func:`swiftjax.loops.loop_edge`) and the halves' diagnostics."""
    config, schedule, store = ctx.config, ctx.schedule, ctx.store
    cam = ctx.camera if ctx.camera is not None else UserCamera()
    hw2 = 2 * config.loop_half_window
    halves = []
    for half, c in ((slice(0, hw2), lp.chunk_i), (slice(hw2, 2 * hw2), lp.chunk_j)):
        # Only the 2 x half_window frames of chunk c that the loop chunk overlaps.
        local = lp.frames[half] - schedule.starts[c]
        chunk_frames = store.load("chunk", c, frames=local, fields=())
        # keep-masks (user / sky) of those frames, as each chunk saw them
        mask = both(
            cam.keep(lp.frames[half], chunk_frames.depth, chunk_frames.conf),
            cam.keep(lp.frames[half], pred.depth[half], pred.conf[half]),
        )
        halves.append(
            align_pair(
                align.ChunkFrames.from_prediction(chunk_frames),
                align.ChunkFrames.from_prediction(pred, half),
                K_ref,
                config,
                True,
                f"loop ({lp.i}, {lp.j}) to chunk {c}",
                mask=mask,
            )
        )
    with jax.enable_x64(True):
        Z = np.asarray(loops.loop_edge(jnp.asarray(halves[0][0]), jnp.asarray(halves[1][0])))
    return {
        "i": lp.i,
        "j": lp.j,
        "score": lp.score,
        "chunk_i": lp.chunk_i,
        "chunk_j": lp.chunk_j,
        "Z": Z.tolist(),
        "align_i": halves[0][1],
        "align_j": halves[1][1],
    }


def needs_numbers(config: PipelineConfig, record: dict[str, Any]) -> bool:
    """Whether ``record`` still lacks the numbers geometric verification decides on."""
    return config.loop_verification == "geometric" and not (
        "dense_agreement" in record and (config.loop_agreement == "fixed" or "null_threshold" in record)
    )


def verification_numbers(ctx: RunContext, lp: loops.Loop, record: dict[str, Any], K_ref: np.ndarray) -> dict[str, Any]:
    """:func:`swiftjax.loops.verification.candidate_numbers` of one candidate: the temporal
    chunks' own frames around ``i`` (chunk ``c_i``) and ``j`` (chunk ``c_j``), read from the
    store (the frames the loop chunk's halves overlap)."""
    hw2 = 2 * ctx.config.loop_half_window
    sides = []
    for half, c in ((slice(0, hw2), lp.chunk_i), (slice(hw2, 2 * hw2), lp.chunk_j)):
        local = lp.frames[half] - ctx.schedule.starts[c]
        side = align.ChunkFrames.from_prediction(ctx.store.load("chunk", c, frames=local, fields=()))
        keep = None if ctx.camera is None else ctx.camera.keep(lp.frames[half], side.depth, side.conf)
        if keep is not None:  # masked pixels (user / sky) count as missing depth
            side = side._replace(depth=np.where(np.asarray(keep), np.asarray(side.depth, np.float32), np.nan))
        sides.append(side)
    with ctx.timer("loop verification"):
        return lv.candidate_numbers(
            sides[0],
            sides[1],
            np.asarray(record["Z"]),
            K_ref,
            record["align_i"],
            record["align_j"],
            ctx.config.verification,
        )


def without_tokens(pred: ChunkPrediction) -> ChunkPrediction:
    """A loop chunk's prediction without its patch tokens (its alignment needs none; on a Ray
    worker they never cross the network)."""
    return dataclasses.replace(pred, patch_tokens=None)


def decide(ctx: RunContext, relative: np.ndarray, records: list[dict[str, Any]], *, rows: int | None = None) -> None:
    """Set ``accepted``, ``reason`` (and ``pcm_residual``) on every record, in place, given the
    temporal edges ``relative [T-1, 8]`` (the chain the candidates are checked against).

    ``rows`` (the live engine, which decides again as the chain grows): the chain is extended
    by identity edges to ``max(T - 1, rows)`` edges, so that the consistency programs compile
    once per ``rows``, not once per chunk count.  The loops only reach chunks ``< T``: the
    padded chunks enter no cycle (the same decisions, up to rounding)."""
    if ctx.config.loop_verification == "none":
        for r in records:
            r.update(accepted=True, reason="accepted without verification (loop_verification = none)")
        return
    if rows is not None:
        relative = np.asarray(relative, np.float64).reshape(-1, 8)
        identity = np.asarray(sim3.identity(), np.float64)
        relative = np.concatenate([relative, np.tile(identity, (max(rows - len(relative), 0), 1))])
    with ctx.timer("loop verification"):
        decisions = lv.verify_candidates(records, chain_poses(relative), relative, ctx.config.verification)
    for r, d in zip(records, decisions):
        r.update(accepted=d.accepted, reason=d.reason, pcm_residual=d.pcm_residual)
    redundant_geometry(records)


def redundant_geometry(records: list[dict[str, Any]]) -> None:
    """Reject, in place, every accepted geometric candidate (``source = "geometry"``) whose two
    chunks each lie within one chunk of an accepted token candidate's: that revisit is closed.

    The two sources do not measure an edge equally well.  A token edge comes from one
    loop-centric VGGT chunk that sees both places at once; a geometric edge registers two
    chunks reconstructed apart, each warped by its own model error over its whole extent, and
    the registration's optimum lies where those warps put it: on synthetic KITTI 00 the
    registration's own Tukey score is higher at its placement than at the truth's in 5 of 7
    pairs, 0.4–1.7 camera heights from it (docs/performance/reverse-revisits.md).  Measured
    against the oracle's true chunk gauges, the accepted token edges there are 0.14–1.07 m
    and 0.35–1.6° off, the geometric ones 0.56–2.56 m and 1.1–2.2°, all seven beside token
    edges (chunks one apart: neighbouring chunks share their overlap frames, the same place).
    Added to the token edges they cost ATE 2.95 → 3.18 m with their own information, 3.04 m
    with a tenth of it, 2.98 m with the true edge in their place: where a token edge closes the
    revisit, a geometric one adds its error and no constraint.  Where none does (a reverse
    revisit, which tokens cannot match: synthetic KITTI 08) the geometric edge is the loop.

    The rule is :func:`swiftjax.pipeline.loop_geometry.closing`; :func:`run` does not even
    register the gated pairs it would reject beside the token candidates accepted before the
    geometric ones are decided (:func:`_decide_with_geometry`), so here it rejects the ones
    registered beside a token candidate that only the joint decision accepts."""
    tokens = [
        loop_geometry.chunk_pair(r) for r in records if r.get("accepted") and r.get("source", "tokens") == "tokens"
    ]
    for r in records:
        if r.get("source") != "geometry" or not r.get("accepted"):
            continue
        near = loop_geometry.closing(loop_geometry.chunk_pair(r), tokens)
        if near is not None:
            x, y = near
            r.update(
                accepted=False,
                reason=f"redundant: the token loop edge of chunks {y} and {x} closes this revisit "
                "(a registration of two chunks reconstructed apart is the less accurate edge)",
            )


def _log_decisions(ctx: RunContext, records: list[dict[str, Any]]) -> None:
    """One line per run: candidates, accepted, and what happens when none is accepted."""
    if not records:
        ctx.log("loop closure: no loop candidates; the run continues without loop closure")
        return
    accepted = sum(r["accepted"] for r in records)
    line = f"loop closure: {len(records)} candidate(s), {accepted} accepted"
    if accepted == 0:
        line += "; every candidate was rejected (see loops.txt), the run continues without loop closure"
    ctx.log(line)

"""Geometric verification of loop candidates: a DINO match is a hypothesis, not an edge.

A loop candidate ``(i, j)`` (frames, ``i > j``) comes with a loop-centric chunk whose two
halves were aligned to their temporal chunks ``c_i`` and ``c_j``, giving the candidate edge
``Z = S_{j,loop} S_{i,loop}⁻¹`` (:func:`swiftjax.loops.loop_edge`), which maps chunk ``c_i``
coordinates into chunk ``c_j`` coordinates (pose-graph edge ``c_j → c_i``, ``Z ≈ S_{c_j}⁻¹
S_{c_i}``).  VGGT given two sets of frames that share no view still returns one coherent
reconstruction, so ``Z`` alone proves nothing.  Three tests that do not trust the loop chunk:

1. **Cross-chunk dense consistency** (:mod:`swiftjax.loops.cross_chunk`): the temporal
   chunks' own depths around both ends must agree under ``Z``, more than the same two chunks
   agree by chance under clearly wrong edges (:mod:`swiftjax.loops.null`; or, with
   ``agreement_rule = "fixed"``, more than the constant ``min_agreement``).
2. **Loop-chunk quality** (:func:`loop_chunk_quality`): each half's alignment to its temporal
   chunk must be a valid Umeyama solve (no pose fallback) on enough reliable points
   (``fraction_used``), with its residual recorded.
3. **Pairwise consistency** (PCM, :mod:`swiftjax.loops.pcm`): two loop edges and the
   odometry between their ends must close a cycle, within the odometry's drift.

**Followers** (``followers``; registration edges of :mod:`swiftjax.pipeline.loop_geometry`
only).  A reverse revisit's two chunks face away from each other: even the TRUE edge's depths
agree little (synthetic KITTI 08's reverse pairs under the oracle's true chunk gauges: κ
0.05-0.13), so the floor ``κ >= κ_min`` of test 1 rejects most of them whatever their edge.
A registration edge whose agreement is significant under its shifted null (``a > τ``) and at
least ``κ_min`` in itself (``a >= κ_min``, :func:`null_needed`), but below the chance-corrected
floor, is judged against what a registration reaches where it is WRONG instead: the source
chunk's own best placements on unrelated chunks, refined and dense-tested like the candidate
(``registered_null_threshold``, the bound at ``null_false_alarm`` over those in view).  Beating
it makes the candidate a follower: weaker evidence than a verified loop, so it is accepted only
when it is pairwise consistent with every loop of the maximum consistent set of the verified
ones (and with the followers accepted before it, by decreasing agreement), never on its own.

**Siblings** (``siblings``; registration edges only).  A revisit spans several chunk pairs,
and some of its true ones carry no evidence of their own above their nulls: on synthetic KITTI
08, 36/3 has fewer structure inliers than chunk 36 placed on unrelated chunks (33 <= 43) and,
refined, agrees no more than those placements do; 32/14 agrees at 0.091 (0.075 under the
oracle's true edge).  Nothing in the two chunks tells them from the same source's wrong
placements (32/16, 39 m off: 0.107).  What does is an accepted loop of the SAME revisit: a
loop whose chunks each lie within one chunk of the candidate's (:func:`same_revisit`;
neighbouring chunks share their overlap frames, the same place) closes a cycle with it over at
most one temporal edge per side, so the cycle's whitened residual (PCM) tests the candidate's
edge against that loop's within one temporal edge's drift per side and the two loop edges'
noise, not the drift of the tens of edges between far chunks (which let almost any far pair
through: on 08, 36 of the 46 registration edges of chunks 84-89, 12-141 m off).  A
registration edge whose registration is valid, in view under its edge (``dense_overlap >=
min_overlap``) and rejected by its evidence alone (the structure null, ``evidence_reason``, or
the dense test's nulls) is a sibling of the first verified loop or follower of its revisit
when it is pairwise consistent with every accepted loop and every sibling accepted before it.
Siblings never support one another (no chain along a street), never enter the maximum
consistent set, and keep their evidence's line in their reason.  They are registrations of
single chunks only (:func:`may_sibling` says why joint registrations are not).

Siblings are OFF by default.  The rule was built on one synthetic world (seed 0, where its two
edges on 08 were 2.1 and 4.4 m off and moved ATE by 0.05 m).  In three other worlds along the
same route (``bench/bench_hard_sequences.py --seeds 1 2 3``) it added four edges, three of them
6.5–9.7 m off (beside a verified loop that was itself 9.9 m off, or beside a right one), and ATE
got worse in both worlds where it added any (16.94 → 17.43 m, 20.18 → 20.31 m).  By
construction it never closes a revisit of its own, and a consistency test against one loop
cannot be more accurate than that loop's edge.

This module holds the decision rule (:func:`verify_candidates`, thresholds in
:class:`VerificationConfig`) and re-exports the tests' functions.  The fixed thresholds were
chosen from measured distributions of true and false candidates (docs/performance/loops.md);
the dense agreement's bound is calibrated per candidate by default.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from swiftjax import align, sim3
from swiftjax.loops.cross_chunk import (
    ConsistencyInfo,
    CrossCheck,
    compile_cross_chunk,
    cross_chunk_consistency,
    dense_consistency,
)
from swiftjax.loops.null import (
    NullCheck,
    chance_corrected,
    compile_null,
    config_offsets,
    kappa_settled,
    null_consistency,
    null_rounds,
    null_threshold,
)
from swiftjax.loops.options import VerificationConfig
from swiftjax.loops.pcm import loop_covariance, max_consistent_set, odometry_covariance, pairwise_consistency

__all__ = [
    "ConsistencyInfo",
    "dense_consistency",
    "CrossCheck",
    "cross_chunk_consistency",
    "NullCheck",
    "null_consistency",
    "null_threshold",
    "chance_corrected",
    "LoopQuality",
    "loop_chunk_quality",
    "candidate_numbers",
    "compile_candidate_numbers",
    "null_needed",
    "odometry_covariance",
    "loop_covariance",
    "pairwise_consistency",
    "max_consistent_set",
    "VerificationConfig",
    "Decision",
    "chunk_pair",
    "may_sibling",
    "same_revisit",
    "verify_candidates",
]


class LoopQuality(NamedTuple):
    """The loop chunk's own numbers (both half alignments; ``[...]`` fields).

    Attributes:
        min_points: int32 ``min`` of the two halves' reliable point counts.
        min_fraction: ``min`` of the two ``fraction_used``.
        max_rms: ``max`` of the two Umeyama RMS residuals (temporal-chunk units).
        valid: both solves valid and neither fell back to the pose-based estimate.
    """

    min_points: jax.Array
    min_fraction: jax.Array
    max_rms: jax.Array
    valid: jax.Array


def loop_chunk_quality(info_i: Any, info_j: Any) -> LoopQuality:
    """:class:`LoopQuality` of the two halves' alignments (any batch shape; jit-able).

    ``info_i``, ``info_j``: :class:`~swiftjax.align.AlignInfo`, or anything with its fields
    ``num_points``, ``fraction_used``, ``rms``, ``valid``, ``pose_fallback`` (e.g. the
    pipeline's per-half record dicts, whose keys are those names).
    """
    get = lambda x, k: jnp.asarray(x[k] if isinstance(x, dict) else getattr(x, k))
    return LoopQuality(
        min_points=jnp.minimum(get(info_i, "num_points"), get(info_j, "num_points")),
        min_fraction=jnp.minimum(get(info_i, "fraction_used"), get(info_j, "fraction_used")),
        max_rms=jnp.maximum(get(info_i, "rms"), get(info_j, "rms")),
        valid=(
            get(info_i, "valid") & get(info_j, "valid") & ~get(info_i, "pose_fallback") & ~get(info_j, "pose_fallback")
        ),
    )


def compile_candidate_numbers(
    frames: align.ChunkFrames,
    K_ref: Float[ArrayLike, "3 3"],
    config: VerificationConfig | None = None,
    *,
    null_when_needed: bool = False,
) -> None:
    """Compile ahead of time the programs :func:`candidate_numbers` runs on two chunks' frames
    of ``frames``' shapes (``[F, H, W]``, ``jax.ShapeDtypeStruct``s or arrays): the
    cross-chunk test and its null (:func:`~swiftjax.loops.cross_chunk.compile_cross_chunk`,
    :func:`~swiftjax.loops.null.compile_null`; its rounds with ``null_when_needed``, as
    :func:`candidate_numbers` runs it)."""
    config = config or VerificationConfig()
    one = align.ChunkFrames(*(jax.ShapeDtypeStruct((1, *np.shape(a)), np.float32) for a in frames))
    Z = jax.ShapeDtypeStruct((1, 8), np.float32)
    K = jax.ShapeDtypeStruct(np.shape(K_ref), np.float32)
    compile_cross_chunk(one, one, Z, K, config)
    compile_null(one, one, Z, K, config, rounds=null_when_needed)


def candidate_numbers(
    side_i: align.ChunkFrames,
    side_j: align.ChunkFrames,
    Z: Float[ArrayLike, "8"],
    K_ref: Float[ArrayLike, "3 3"],
    info_i: Any,
    info_j: Any,
    config: VerificationConfig | None = None,
    *,
    null_when_needed: bool = False,
    complete: bool = False,
) -> dict[str, Any]:
    """The verification numbers of one candidate as a plain dict (host level, for records).

    ``side_i``/``side_j``: ``[F, H, W]`` frames of the temporal chunks around both ends (as
    :func:`cross_chunk_consistency`, without the candidate axis); ``Z [8]`` maps c_i into
    c_j; ``info_i``/``info_j`` the halves' alignment diagnostics (:func:`loop_chunk_quality`).
    Keys: ``dense_agreement``, ``dense_overlap`` (the smaller direction's), ``dense_i_to_j``
    and ``dense_j_to_i`` (every :class:`ConsistencyInfo` field), ``quality_valid``,
    ``quality_min_points``, ``quality_min_fraction``, ``quality_max_rms``; with
    ``config.agreement_rule = "null"`` also the null's ``null_threshold`` (τ under
    ``config.null_model``, :func:`~swiftjax.loops.null.null_threshold`: with ``trend`` and
    ``sided`` the larger of the two shift directions' bounds; NaN when fewer than three null
    edges see the other chunk), ``null_mean`` (κ's ``m``; with ``trend`` and ``sided`` the
    larger direction's), ``null_std``, ``null_samples`` (``K'``) and ``null_kappa`` (the chance-corrected agreement;
    :mod:`swiftjax.loops.null`).
    With ``null_when_needed`` the null (``K`` times the candidate's own test) runs only when it
    can change the verdict (:func:`null_needed`); otherwise ``null_skipped = True`` stands in
    for its keys and :func:`verify_candidates` rejects the candidate on its own numbers.  Where
    it runs, it runs in the two rounds of :func:`~swiftjax.loops.null.null_rounds`, the second
    only when the first leaves the verdict open (:func:`~swiftjax.loops.null.kappa_settled`):
    otherwise ``null_stopped = True`` and the null's keys are the first round's numbers, which
    reject the candidate as the complete null would (the verdict is exact; the numbers are
    those of ``K/2`` samples).  ``complete`` (with ``null_when_needed``): both rounds drawn
    whatever the first gives, the complete null in the programs the rounds compile (all ``K``
    at once is another program, not compiled ahead: 1.33 s on KITTI 00 against 0.16 s).
    """
    config = config or VerificationConfig()
    one = lambda f: align.ChunkFrames(*(np.asarray(a, np.float32)[None] for a in f))
    Z = np.asarray(Z, np.float32)[None]
    cc = cross_chunk_consistency(one(side_i), one(side_j), Z, K_ref, config)
    plain = lambda info: {
        k: float(np.asarray(v)[0]) if np.asarray(v).dtype.kind == "f" else int(np.asarray(v)[0])
        for k, v in info._asdict().items()
    }
    q = loop_chunk_quality(info_i, info_j)
    null: dict[str, Any] = {}
    agreement = float(np.asarray(cc.score)[0])
    overlap = float(min(np.asarray(cc.i_to_j.overlap)[0], np.asarray(cc.j_to_i.overlap)[0]))
    if config.agreement_rule == "null" and null_when_needed and not null_needed(agreement, overlap, config):
        null = {"null_skipped": True}
    elif config.agreement_rule == "null":
        score, null_overlap, seen, offsets, stop = _null_samples(
            one(side_i), one(side_j), Z, K_ref, config, agreement, in_rounds=null_when_needed, stop=not complete
        )
        th = null_threshold(
            score,
            null_overlap,
            seen,
            config.null_false_alarm,
            config.min_overlap,
            model=config.null_model,
            offsets=offsets,
        )
        null = {
            "null_threshold": th.threshold,
            "null_mean": th.mean,
            "null_std": th.std,
            "null_samples": th.samples,
            "null_kappa": chance_corrected(agreement, th.mean),
            **({"null_stopped": True} if stop else {}),
        }
    return {
        "dense_agreement": agreement,
        "dense_overlap": overlap,
        "dense_i_to_j": plain(cc.i_to_j),
        "dense_j_to_i": plain(cc.j_to_i),
        "quality_valid": bool(q.valid),
        "quality_min_points": int(q.min_points),
        "quality_min_fraction": float(q.min_fraction),
        "quality_max_rms": float(q.max_rms),
        **null,
    }


def _null_samples(
    side_i: align.ChunkFrames,
    side_j: align.ChunkFrames,
    Z: np.ndarray,
    K_ref: Float[ArrayLike, "3 3"],
    config: VerificationConfig,
    agreement: float,
    *,
    in_rounds: bool,
    stop: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """One candidate's null samples (``[1, ...]`` frames and ``Z [1, 8]``): ``(score, overlap,
    pairs_seen, offsets, stopped)``, each ``[E]`` with the samples' shifts ``δ``.  All ``K`` at
    once, or ``in_rounds`` (:func:`~swiftjax.loops.null.null_rounds`) with the second round
    drawn only when the first leaves the verdict open (:func:`~swiftjax.loops.null.kappa_settled`;
    ``stopped``: it did not, ``E = K/2``; ``stop = False``: the second round drawn always)."""
    offsets = config_offsets(config)
    draw = lambda edges: [np.asarray(a)[0] for a in null_consistency(side_i, side_j, Z, K_ref, config, edges=edges)]
    if not in_rounds:
        return *draw(None), offsets, False
    first, second = null_rounds(config.null_samples)
    drawn = draw(first)
    if stop and kappa_settled(agreement, *drawn, len(second), config.null_min_kappa, config.min_overlap):
        return *drawn, offsets[first], True
    order = np.argsort(np.concatenate([first, second]))
    return *(np.concatenate([a, b])[order] for a, b in zip(drawn, draw(second))), offsets, False


def null_needed(agreement: float, overlap: float, config: VerificationConfig) -> bool:
    """Whether the null (``agreement_rule = "null"``) can change the verdict of a candidate
    whose own dense test gave ``agreement`` and ``overlap`` (:func:`_dense_reason`, host level).

    It cannot when the candidate is rejected whatever the null: a non-finite number, ``overlap
    < min_overlap``, or ``agreement < min(null_min_kappa, min_agreement)``.  The last because
    every null sample is an agreement in ``[0, 1]``, so their mean ``m`` is too, and the
    chance-corrected agreement ``κ(m) = (a − m) / (1 − m)`` has ``dκ/dm = (a − 1) / (1 − m)² <= 0``:
    ``κ <= κ(0) = a < κ_min`` (``m = 1``: ``κ <= 0``); when the null is not computable the fixed
    bound rejects ``a < min_agreement``.  Exact: the verdict is the one the complete null gives.
    """
    if not (math.isfinite(agreement) and math.isfinite(overlap)) or overlap < config.min_overlap:
        return False
    return bool(agreement >= min(config.null_min_kappa, config.min_agreement))


def may_follow(numbers: dict[str, Any], config: VerificationConfig) -> bool:
    """Whether a registration edge with :func:`candidate_numbers`' ``numbers`` is rejected by
    the chance-corrected floor alone, so that beating its registered null would make it a
    follower (module docstring; host level): ``followers`` on, the null rule, in view, ``a >=
    min(null_min_kappa, min_agreement)`` (the null was run, :func:`null_needed`), and ``κ <
    null_min_kappa`` either settled after the null's first round (``null_stopped``; whether
    ``a > τ`` is then open) or with ``a > τ``."""
    a, ov = float(numbers.get("dense_agreement", math.nan)), float(numbers.get("dense_overlap", math.nan))
    if not (config.followers and config.agreement_rule == "null" and math.isfinite(a) and math.isfinite(ov)):
        return False
    if ov < config.min_overlap or numbers.get("null_skipped"):
        return False
    if numbers.get("null_stopped"):
        return True
    tau = float(numbers.get("null_threshold", math.nan))
    return math.isfinite(tau) and a > tau and chance_corrected(a, float(numbers["null_mean"])) < config.null_min_kappa


def _follows(r: dict[str, Any], config: VerificationConfig) -> bool:
    """Whether record ``r`` passes the dense test only as a follower: :func:`may_follow` with
    the complete null (not stopped) and ``a > registered_null_threshold``, or, provisionally,
    with those still to be computed (``registered_null_pending``)."""
    if not may_follow(r, config):
        return False
    if r.get("registered_null_pending"):
        return True
    registered = float(r.get("registered_null_threshold", math.nan))
    return not r.get("null_stopped") and float(r["dense_agreement"]) > registered


def same_revisit(pair: tuple[int, int], loops: Iterable[tuple[int, int]]) -> tuple[int, int] | None:
    """The first of ``loops`` (chunk pairs ``(larger, smaller)``) whose chunks each lie within one
    chunk of ``pair``'s (``(larger, smaller)``), or None: a loop of the same revisit.  Neighbouring
    chunks share their overlap frames, so their places are the same place (host level)."""
    a, b = pair
    return next(((x, y) for x, y in loops if abs(x - a) <= 1 and abs(y - b) <= 1), None)


def may_sibling(r: dict[str, Any], config: VerificationConfig) -> bool:
    """Whether record ``r``, once its evidence rejects it, may still be a sibling (module
    docstring; host level): ``siblings`` and ``pcm`` on, a registration edge (``source =
    "geometry"``) of single chunks (``registration.neighbours`` 0 or absent) and in view under
    its edge (``dense_overlap >= min_overlap``), or with its refinement and dense test still to
    be computed (``registration_pending``).

    Single chunks: a joint registration (``neighbours = k > 0``) registers each chunk merged
    with its ``k`` neighbours on each side, so two pairs of a revisit one chunk apart share
    ``2k`` of the ``2k + 1`` chunks of each cloud: their agreement is one registration agreeing
    with itself, not evidence (synthetic KITTI 08 with ``k = 1``: 38/2, 12.6 m off, consistent
    with the verified 38/3)."""
    if not (config.siblings and config.pcm and r.get("source") == "geometry"):
        return False
    if (r.get("registration") or {}).get("neighbours", 0):
        return False
    if r.get("registration_pending"):
        return True
    ov = float(r.get("dense_overlap", math.nan))
    return math.isfinite(float(r.get("dense_agreement", math.nan))) and math.isfinite(ov) and ov >= config.min_overlap


def chunk_pair(record: dict[str, Any]) -> tuple[int, int]:
    """A candidate record's chunks ``(larger, smaller)`` (the pairs :func:`same_revisit` compares)."""
    return max(int(record["chunk_i"]), int(record["chunk_j"])), min(int(record["chunk_i"]), int(record["chunk_j"]))


# ----------------------------------------------------------------------- decisions


class Decision(NamedTuple):
    """Outcome for one candidate.

    Attributes:
        accepted: the candidate becomes a loop edge.
        reason: one line saying why.
        pcm_residual: the largest whitened cycle residual against the other PCM survivors
            (NaN when PCM did not run for this candidate).
    """

    accepted: bool
    reason: str
    pcm_residual: float = math.nan


def _dense_reason(r: dict[str, Any], config: VerificationConfig) -> str | None:
    """Why the dense numbers of record ``r`` reject it, or ``None``."""
    agreement = float(r.get("dense_agreement", math.nan))
    overlap = float(r.get("dense_overlap", math.nan))
    if not (math.isfinite(agreement) and math.isfinite(overlap)):
        return "dense consistency not computable"
    if overlap < config.min_overlap:
        return f"the temporal chunks do not see each other under the edge: overlap {overlap:.3f} < {config.min_overlap}"
    if config.agreement_rule == "null":
        if r.get("registered_null_pending") and _follows(r, config):  # provisionally (verify_candidates)
            return None
        if r.get("null_skipped"):  # null_needed: rejected whatever the null
            return (
                f"depths agree little whatever the null: agreement {agreement:.3f} < "
                f"{min(config.null_min_kappa, config.min_agreement)} (the chance-corrected agreement "
                "(a - m)/(1 - m) <= a for every null mean m; null not run)"
            )
        tau = float(r.get("null_threshold", math.nan))
        if math.isfinite(tau):
            null = f"null {float(r['null_mean']):.3f} +- {float(r['null_std']):.3f}"
            registered = (  # a follower candidate's second null (module docstring)
                f", and no more than registrations on unrelated chunks: {agreement:.3f} <= "
                f"{float(r['registered_null_threshold']):.3f}"
                if "registered_null_threshold" in r
                else ""
            )
            if agreement <= tau:
                return (
                    f"depths agree no better than under wrong edges: agreement {agreement:.3f} <= "
                    f"{tau:.3f} ({null}, false-alarm rate {config.null_false_alarm:g}){registered}"
                )
            kappa = chance_corrected(agreement, float(r["null_mean"]))
            if kappa < config.null_min_kappa and not _follows(r, config):
                return (
                    f"depths agree little more than under wrong edges: chance-corrected agreement "
                    f"{kappa:.3f} < {config.null_min_kappa} (agreement {agreement:.3f}, {null}){registered}"
                )
            return None
        if agreement < config.min_agreement:  # the null is not computable: the fixed bound
            return (
                f"depths disagree across the loop: agreement {agreement:.3f} < {config.min_agreement} "
                "(no null: fewer than three wrong edges see the other chunk)"
            )
        return None
    if agreement < config.min_agreement:
        return f"depths disagree across the loop: agreement {agreement:.3f} < {config.min_agreement}"
    return None


def verify_candidates(
    records: Sequence[dict[str, Any]],
    chain_poses: Float[ArrayLike, "T 8"],
    relative: Float[ArrayLike, "T-1 8"],
    config: VerificationConfig = VerificationConfig(),
) -> list[Decision]:
    """Accept or reject every candidate (host level), from the numbers in its record.

    Each record needs ``chunk_i``, ``chunk_j``, ``Z`` (``[8]``, c_i into c_j),
    ``dense_agreement`` and ``dense_overlap`` (the smaller direction's, :class:`CrossCheck`;
    NaN when they could not be computed), ``quality_valid`` and ``quality_min_fraction``
    (:class:`LoopQuality`), and with ``agreement_rule = "null"`` ``null_threshold``,
    ``null_mean``, ``null_std`` (:func:`candidate_numbers`; a record without them falls back
    to ``min_agreement``).  The rule, in order: a non-finite ``Z``, an invalid or thin
    loop-chunk alignment, no overlap or depths that agree no better than under wrong edges
    (``dense_agreement <= null_threshold`` or a chance-corrected agreement below
    ``null_min_kappa``; ``"fixed"``: ``< min_agreement``) reject the candidate; the survivors
    (two or more) go through PCM and only a maximum consistent set is kept (ties: larger total
    ``dense_agreement``).  Each cycle is whitened by its loop edges' covariances: a record's
    ``_covariance`` (``[7, 7]``, of the right perturbation of its ``Z``: a registration edge's
    own, :func:`swiftjax.pipeline.loop_geometry.edge_covariance`, the one the pose graph gives
    it) where it has one, else the drift model's (:func:`loop_covariance`).  Followers
    (``followers``, module docstring: a registration edge below ``null_min_kappa`` that beats ``registered_null_threshold``) take
    no part in that set: each, by decreasing ``dense_agreement``, is accepted when it is
    pairwise consistent with every loop of the set and every follower accepted before it, and
    rejected when the set is empty or PCM is off.  A follower whose registered null is still
    to be computed (``registered_null_pending``) is judged as if it beat it: the caller
    computes the null of each one accepted so and decides again
    (:func:`swiftjax.pipeline.loop_geometry.settle_deferred`).  Siblings (``siblings``, module
    docstring: a registration edge rejected by its evidence alone, :func:`may_sibling`; a
    record's ``evidence_reason`` is such a rejection, its registration's structure null) are
    tested last, by decreasing ``dense_agreement``: each is accepted beside the first loop of
    the set or follower of its revisit (:func:`same_revisit`) when pairwise consistent with
    every loop accepted so far, its reason ending with its evidence's line; one whose
    refinement and dense test are still to be computed (``registration_pending``) is judged on
    its placement, and computed and decided again when accepted so.  A record's
    ``quality_reason`` replaces the loop chunk's line when ``quality_valid`` is false.

    Args:
        records: the candidates (not modified).
        chain_poses: ``[T, 8]`` dead-reckoning chunk poses.
        relative: ``[T-1, 8]`` temporal edges.
        config: :class:`VerificationConfig`.

    Returns:
        One :class:`Decision` per record, in order.
    """
    out: list[Decision] = [Decision(False, "")] * len(records)
    alive: list[int] = []
    hopeful: list[int] = []  # rejected by their evidence alone: siblings if their revisit is closed
    for k, r in enumerate(records):
        Z = np.asarray(r["Z"], np.float64)
        fraction = float(r.get("quality_min_fraction", 0.0))
        if Z.shape != (8,) or not np.all(np.isfinite(Z)):
            out[k] = Decision(False, "loop edge is not finite")
        elif not r.get("quality_valid", False):
            out[k] = Decision(False, r.get("quality_reason", "loop chunk alignment invalid (pose fallback)"))
        elif not fraction >= config.min_fraction:
            out[k] = Decision(
                False, f"loop chunk alignment thin: {fraction:.3f} of the overlap reliable < {config.min_fraction}"
            )
        elif (why := r.get("evidence_reason") or _dense_reason(r, config)) is not None:
            out[k] = Decision(False, why)
            if may_sibling(r, config):
                hopeful.append(k)
        else:
            alive.append(k)
    follows = [_follows(records[k], config) for k in alive]
    homes = [chunk_pair(records[k]) for k in alive]
    hopeful = [k for k in hopeful if same_revisit(chunk_pair(records[k]), homes) is not None]
    if not (config.pcm and len(alive) >= 2) and not (alive and hopeful):
        for k, weak in zip(alive, follows):
            out[k] = (
                Decision(False, "a follower with no verified loop to be consistent with (PCM off or no other loop)")
                if weak
                else Decision(True, "verified")
            )
        return out
    tested = alive + hopeful
    nodes, Zs, own = [], [], {}
    for a, k in enumerate(tested):  # each loop as the edge p -> q with p < q, Z ~ S_p^-1 S_q
        ci, cj = int(records[k]["chunk_i"]), int(records[k]["chunk_j"])
        Z = np.asarray(records[k]["Z"], np.float64)  # maps c_i into c_j: edge c_j -> c_i
        C = records[k].get("_covariance")
        if cj > ci:
            with jax.enable_x64(True):
                if C is not None:  # (Z exp δ)⁻¹ = Z⁻¹ exp(−Ad(Z) δ): Σ of the inverse is Ad(Z) Σ Ad(Z)ᵀ
                    A = np.asarray(sim3.adjoint(jnp.asarray(Z)))
                    C = A @ np.asarray(C, np.float64) @ A.T
                Z = np.asarray(sim3.inverse(jnp.asarray(Z)))
        if C is not None:
            own[a] = np.asarray(C, np.float64)
        nodes.append((min(ci, cj), max(ci, cj)))
        Zs.append(Z)
    # padded to a power of two (>= 8) so that one compile serves many candidate counts
    n, na = len(tested), len(alive)
    size = max(8, 1 << (n - 1).bit_length())
    nodes += [(0, 1)] * (size - n)
    Zs += [np.array([0, 0, 0, 0, 0, 0, 1, 1.0])] * (size - n)
    with jax.enable_x64(True):
        Zj = jnp.asarray(np.stack(Zs))
        odo = odometry_covariance(
            jnp.asarray(relative, jnp.float64),
            config.odo_sigma_rot,
            config.odo_sigma_trans,
            config.odo_sigma_scale,
        )
        lc = np.array(loop_covariance(Zj, config.loop_sigma_rot, config.loop_sigma_trans, config.loop_sigma_scale))
        for a, C in own.items():
            lc[a] = C
        lc = jnp.asarray(lc)
        m = np.asarray(
            pairwise_consistency(jnp.asarray(chain_poses, jnp.float64), odo, jnp.asarray(nodes, jnp.int32), Zj, lc)
        )[:n, :n]
    agreement = [float(records[k].get("dense_agreement", math.nan)) for k in tested]
    strong = [a for a in range(na) if not follows[a]]
    ok = m <= config.pcm_threshold
    clique = {strong[a] for a in max_consistent_set(ok[np.ix_(strong, strong)], [agreement[a] for a in strong])}
    verified = len(clique)
    for a in sorted((a for a in range(na) if follows[a]), key=lambda a: -agreement[a]):
        if verified and all(ok[a, b] for b in clique):
            clique.add(a)
    accepted, sibling_of = set(clique), {}  # siblings: beside the clique's loops, never each other's
    loops = [chunk_pair(records[tested[b]]) for b in sorted(clique)]
    by_agreement = lambda a: (-agreement[a] if math.isfinite(agreement[a]) else math.inf, a)
    for a in sorted(range(na, n), key=by_agreement):
        home = same_revisit(chunk_pair(records[tested[a]]), loops)
        if verified and home is not None and all(ok[a, b] for b in accepted):
            accepted.add(a)
            sibling_of[a] = home
    for a in sibling_of:
        k, (x, y) = tested[a], sibling_of[a]
        out[k] = Decision(
            True,
            f"sibling of the loop of chunks {y} and {x} (the same revisit); pairwise consistent with "
            f"{len(accepted) - 1} other loop(s); alone: {out[k].reason}",
            float(np.max(m[a, sorted(accepted)])),
        )
    for a, k in enumerate(alive):
        worst = float(np.max(m[a, :na])) if na > 1 else 0.0
        if a in clique:
            out[k] = Decision(
                True,
                ("follower" if follows[a] else "verified")
                + f"; pairwise consistent with {len(accepted) - 1} other loop(s)",
                worst,
            )
        elif follows[a] and not verified:
            out[k] = Decision(False, "a follower with no verified loop to be consistent with", worst)
        else:
            bad = max(float(m[a, b]) for b in clique) if clique else math.inf
            out[k] = Decision(
                False,
                f"pairwise inconsistent with the {len(clique)} accepted loop(s): whitened cycle "
                f"residual {bad:.1f} > {config.pcm_threshold}",
                worst,
            )
    return out

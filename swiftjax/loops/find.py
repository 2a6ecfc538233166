"""The host-level call from per-frame descriptors to the final loop list (:func:`find_loops`)."""

from __future__ import annotations

import logging
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from swiftjax.chunks import ChunkSchedule
from swiftjax.loops import detection
from swiftjax.loops._checks import _check_finite
from swiftjax.loops.descriptors import fit_whitening, power_normalize, whiten
from swiftjax.loops.detection import detect_loops
from swiftjax.loops.loop_chunk import _loop_chunks, filter_by_chunks
from swiftjax.loops.options import AUTHORS_THRESHOLD, LoopOptions

__all__ = ["Loop", "find_loops"]

logger = logging.getLogger(__name__)


class Loop(NamedTuple):
    """One detected loop (host-side, plain Python/NumPy values).

    Attributes:
        i, j: frame indices, ``i > j``.
        score: cosine similarity of the whitened descriptors.
        frames: ``[40]`` int64 loop-centric chunk frames (around ``i`` first, then ``j``).
        chunk_i, chunk_j: temporal chunks the two halves are aligned to.
        local_i, local_j: positions of ``i`` and ``j`` in ``frames``.
    """

    i: int
    j: int
    score: float
    frames: np.ndarray
    chunk_i: int
    chunk_j: int
    local_i: int
    local_j: int


def _warn_no_candidate(Z, o: LoopOptions, details: dict) -> None:
    """The adaptive threshold found no candidate: say loudly that its assumption may have failed
    (issue 25 item 32).

    :func:`calibrate_threshold` fits the null on the lower 40 % of the frames' best scores, so
    it assumes that fewer than 60 % of the frames revisit.  A route driven several times (a race
    track, a delivery robot: ``swiftjax demo --frames 1200`` is 2.4 laps, every frame has a match
    on another lap) breaks it: the fitted "null" is the revisits themselves and ``tau`` lands
    above all of them.  From the best scores alone "no revisit at all" and "nearly every frame
    revisits" give the same empty result (both are one population), so no rule on them can tell
    the two apart; the warning names both and the remedy (``rule="fixed"``: its candidates are
    verified geometrically as usual).  ``details["no_candidate_warning"]`` records it, with the
    fraction of frames whose best score passes the fixed threshold.
    """
    best = np.asarray(
        detection._row_topk(jnp.asarray(Z), o.min_separation, 1, detection._default_block_rows(Z.shape[0]))[0]
    )[:, 0]
    best = best[np.isfinite(best)]
    above = float(np.mean(best > o.threshold)) if best.size else 0.0
    details["no_candidate_warning"] = {"frames_above_fixed_threshold": above}
    logger.warning(
        f"find_loops: the adaptive loop threshold ({details['threshold']:.3f}, false_alarms={o.false_alarms:g}) "
        f"leaves no loop candidate among {best.size} frames. Either the route never revisits a place, or it "
        "revisits most of its frames (several laps): the calibration fits its null on the lower 40% of the "
        "frames' best scores and assumes fewer than 60% of the frames revisit. "
        f"{100 * above:.0f}% of the frames have a match above the fixed threshold {o.threshold:g}; if the route "
        "has laps, set loop_threshold_rule='fixed' (its candidates are verified as usual)"
    )


def find_loops(
    descriptors: ArrayLike,  # [N, d]: checked here, with a ValueError (host boundary)
    schedule: ChunkSchedule,
    options: LoopOptions | None = None,
    *,
    throw: bool = True,
    return_details: bool = False,
):
    """All loops of a sequence from its per-frame descriptors ``g⁰ [N, d]``, in one call.

    The threshold (``rule``): ``"adaptive"`` (default) calibrates it per sequence from the
    frames' own best scores (:func:`calibrate_threshold`, ``false_alarms`` = ``α``);
    ``"fixed"`` uses ``threshold`` (the constant :data:`DEFAULT_THRESHOLD`, tuned on one
    generator); ``"authors"`` is the authors' rule, :data:`AUTHORS_THRESHOLD` on descriptors
    whitened by a PCA fitted on ``g⁰`` (``fit_on="raw"`` forced, no length adaptation of the
    threshold).  Whatever the rule, the threshold used is ``details["threshold"]``.

    Short sequences (``adapt_to_length``): PCA whitening of ``N`` samples into ``d' >~ N/4``
    dimensions whitens the sampling noise too and flattens every cosine, so ``d' <= max(8,
    N // 4)``.  With few dimensions the cosine of two unrelated whitened descriptors spreads
    as ``1/sqrt(d')``, so the threshold is raised to at least five such standard deviations,
    ``5/sqrt(d')`` (the floor applies to ``rule="fixed"`` only: the adaptive rule measures
    the spread itself).  Neither changes anything for ``N >= 4 dim``.

    ``power_normalize`` → ``fit_whitening`` (on ``g¹`` when ``fit_on="power"``, the default,
    consistent: fitted on what it is applied to; ``fit_on="raw"`` fits on ``g⁰`` as the
    authors' code does) → ``whiten`` → ``detect_loops`` → ``filter_by_chunks`` →
    ``loop_chunk_frames`` per loop.

    Args:
        descriptors: ``[N, d]`` per-frame ``g⁰`` (:func:`frame_descriptor` of each chunk's
            tokens, rows of the frames in order; in overlaps any copy, they are per-frame).
        schedule: :class:`swiftjax.chunks.ChunkSchedule` of the sequence (``n_frames == N``).
        options: :class:`~swiftjax.loops.options.LoopOptions` (default ``LoopOptions()``; vary
            it with ``LoopOptions(rule="fixed", threshold=0.7)`` or ``options.replace(...)``).
        throw: ``True``: non-finite descriptors are a ``ValueError``.  ``False``: their rows
            are left out of the whitening fit and never match (a warning names them;
            ``details["nonfinite_rows"]`` lists them).
        return_details: also return a dict with the intermediate arrays.

    Returns:
        ``list[Loop]`` sorted by score (and the details dict if asked).  Loops whose
        loop-centric chunk is not well formed (a chunk shorter than ``2·half_window``) are
        dropped with a warning.

    Raises:
        ValueError: non-finite descriptors (``throw=True``), wrong shapes, mismatched
            schedule.
    """
    G = np.asarray(descriptors)
    if G.ndim != 2:
        raise ValueError(f"find_loops: descriptors must be [N, d], got shape {G.shape}")
    n = G.shape[0]
    if schedule.n_frames != n:
        raise ValueError(f"find_loops: schedule is for {schedule.n_frames} frames but descriptors has {n} rows")
    finite = np.all(np.isfinite(G), axis=1)
    if throw:
        _check_finite(G, "find_loops: descriptors")
    elif not finite.all():
        bad = np.flatnonzero(~finite)
        logger.warning(
            f"find_loops: {len(bad)} descriptor row(s) contain NaN or Inf (first at row {int(bad[0])}); "
            "those frames are left out of the whitening and never match"
        )
    o = LoopOptions() if options is None else options
    n_fit = int(finite.sum())
    threshold, fit_on, dim = effective_settings(o, n_fit)
    g1 = power_normalize(G, o.beta)
    details = {
        "g1": g1,
        "rule": o.rule,
        "threshold": float("inf") if o.rule == "adaptive" else float(threshold),
        "nonfinite_rows": np.flatnonzero(~finite),
    }
    if n <= o.min_separation + 1 or n < 3:
        return ([], details) if return_details else []
    fit = G if fit_on == "raw" else g1
    if n_fit < n:
        fit = np.asarray(fit)[finite]
    w = fit_whitening(fit, o.remove, dim, o.eps, o.max_samples)
    Z = whiten(w, g1)
    cand = detect_loops(
        Z,
        threshold,
        o.min_separation,
        o.nms_radius,
        o.top_k,
        o.max_loops,
        nms=o.nms,
        calibrate=o.rule == "adaptive",
        false_alarms=o.false_alarms,
        throw=n_fit == n,
    )
    details["threshold"] = float(cand.threshold)
    if o.rule == "adaptive" and int(cand.count) == 0 and details["threshold"] < 1.0:
        _warn_no_candidate(Z, o, details)
    if o.rule == "adaptive" and n > o.min_separation + 1 and details["threshold"] >= 1.0:
        logger.warning(
            f"find_loops: the calibrated loop threshold is {details['threshold']:.3f} >= 1 (false_alarms="
            f"{o.false_alarms:g}): the frames' best scores show no revisit standing out of their own null, so "
            "there is no loop candidate; rule='fixed' with a chosen threshold (and loop verification) "
            "forces candidates"
        )
    if bool(cand.truncated):
        logger.warning(f"find_loops: NMS stopped at max_loops={o.max_loops}; more loops may exist")
    kept = filter_by_chunks(cand, schedule)
    loops = as_loops(kept, schedule, o.half_window)
    details.update(whitening=w, z=Z, candidates=cand, filtered=kept)
    return (loops, details) if return_details else loops


def effective_settings(o: LoopOptions, n_fit: int) -> tuple[float, str, int]:
    """``(threshold, fit_on, d′)`` that :func:`find_loops` uses for ``n_fit`` finite descriptors:
    ``rule="authors"`` forces :data:`AUTHORS_THRESHOLD` and ``fit_on="raw"``; ``adapt_to_length``
    caps ``d′`` at ``max(8, n_fit // 4)`` and floors a fixed threshold at ``5/sqrt(d′)``."""
    threshold, fit_on, dim = o.threshold, o.fit_on, o.dim
    if o.rule == "authors":
        threshold, fit_on = AUTHORS_THRESHOLD, "raw"
    if o.adapt_to_length:
        dim = min(dim, max(8, n_fit // 4))
        if o.rule == "fixed":
            threshold = max(threshold, 5.0 / float(np.sqrt(dim)))
    return threshold, fit_on, dim


def as_loops(kept, schedule: ChunkSchedule, hw: int) -> list[Loop]:
    """The :class:`Loop` list of filtered candidates ``kept`` (:func:`filter_by_chunks` output):
    each with its loop-centric chunk in ``schedule``; loops without a well-formed one are
    dropped with a warning."""
    c = int(kept.count)
    loops: list[Loop] = []
    if c:
        # all M buffer rows at once (one compile per buffer size, not per loop count)
        lc = jax.tree.map(
            np.asarray,
            _loop_chunks(
                jnp.maximum(kept.pairs, 0),
                jnp.asarray(schedule.starts, jnp.int32),
                jnp.asarray(schedule.ends, jnp.int32),
                hw,
            ),
        )
        pairs = np.asarray(kept.pairs)
        scores = np.asarray(kept.scores)
        for k in range(c):
            if not lc.valid[k]:
                logger.warning(
                    f"find_loops: loop ({pairs[k, 0]}, {pairs[k, 1]}) has no well-formed "
                    f"{4 * hw}-frame loop chunk (a chunk is shorter than {2 * hw} frames); dropped"
                )
                continue
            loops.append(
                Loop(
                    int(pairs[k, 0]),
                    int(pairs[k, 1]),
                    float(scores[k]),
                    lc.frames[k].astype(np.int64),
                    int(lc.chunk_i[k]),
                    int(lc.chunk_j[k]),
                    int(lc.local_i[k]),
                    int(lc.local_j[k]),
                )
            )
    return loops

"""The host-level call from per-frame descriptors to the final loop list (:func:`find_loops`)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax.loops._checks import _check_finite
from swiftjax.loops.descriptors import fit_whitening, power_normalize, whiten
from swiftjax.loops.detection import detect_loops
from swiftjax.loops.loop_chunk import _loop_chunks, filter_by_chunks
from swiftjax.loops.options import AUTHORS_THRESHOLD, DEFAULT_FALSE_ALARMS, DEFAULT_THRESHOLD, THRESHOLD_RULES

__all__ = ["Loop", "find_loops"]


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


def find_loops(
    descriptors,
    schedule,
    *,
    rule: str = "adaptive",
    threshold: float = DEFAULT_THRESHOLD,
    false_alarms: float = DEFAULT_FALSE_ALARMS,
    beta: float = 0.5,
    remove: int = 1,
    dim: int = 512,
    eps: float = 1e-6,
    max_samples: int = 50_000,
    fit_on: str = "power",
    min_separation: int = 100,
    nms_radius: int = 25,
    top_k: int = 8,
    max_loops: int | None = None,
    nms: str = "pair",
    half_window: int = 10,
    adapt_to_length: bool = True,
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
    dimensions whitens the sampling noise too and flattens every cosine (measured: ``N = 238``,
    ``d' = 236`` -> best far-apart similarity 0.03; ``d' = 59`` -> true revisits at 0.85-0.92),
    so ``d' <= max(8, N // 4)``.  With few dimensions the cosine of two unrelated whitened
    descriptors spreads as ``1/sqrt(d')``, so the threshold is raised to at least five such
    standard deviations, ``5/sqrt(d')`` (0.65 at ``d' = 59``; at ``d' = 512`` the default 0.43
    is already ten; the floor applies to ``rule="fixed"`` only: the adaptive rule measures
    the spread itself).  Neither changes anything for ``N >= 4 dim`` (KITTI 00: none).

    ``power_normalize`` → ``fit_whitening`` (on ``g¹`` when ``fit_on="power"``, the default,
    consistent: fitted on what it is applied to; ``fit_on="raw"`` fits on ``g⁰`` as the
    authors' code does) → ``whiten`` → ``detect_loops`` → ``filter_by_chunks`` →
    ``loop_chunk_frames`` per loop.

    Args:
        descriptors: ``[N, d]`` per-frame ``g⁰`` (:func:`frame_descriptor` of each chunk's
            tokens, rows of the frames in order; in overlaps any copy, they are per-frame).
        schedule: :class:`swiftjax.chunks.ChunkSchedule` of the sequence (``n_frames == N``).
        return_details: also return a dict with the intermediate arrays.

    Returns:
        ``list[Loop]`` sorted by score (and the details dict if asked).  Loops whose
        loop-centric chunk is not well formed (a chunk shorter than ``2·half_window``) are
        dropped with a warning.

    Raises:
        ValueError: non-finite descriptors, wrong shapes, mismatched schedule, unknown
            ``fit_on`` or ``rule``, ``false_alarms`` outside ``(0, 1)``.
    """
    import warnings

    G = np.asarray(descriptors)
    if G.ndim != 2:
        raise ValueError(f"find_loops: descriptors must be [N, d], got shape {G.shape}")
    n = G.shape[0]
    if schedule.n_frames != n:
        raise ValueError(
            f"find_loops: schedule is for {schedule.n_frames} frames but descriptors has {n} rows"
        )
    _check_finite(G, "find_loops: descriptors")
    if fit_on not in ("power", "raw"):
        raise ValueError(f"find_loops: fit_on must be 'power' or 'raw', got {fit_on!r}")
    if rule not in THRESHOLD_RULES:
        raise ValueError(f"find_loops: rule must be one of {THRESHOLD_RULES}, got {rule!r}")
    if not 0.0 < false_alarms < 1.0:
        raise ValueError(f"find_loops: false_alarms must be in (0, 1), got {false_alarms}")
    if rule == "authors":
        threshold, fit_on = AUTHORS_THRESHOLD, "raw"
    if adapt_to_length:
        dim = min(dim, max(8, n // 4))
        if rule == "fixed":
            threshold = max(threshold, 5.0 / float(np.sqrt(dim)))
    g1 = power_normalize(G, beta)
    details = {"g1": g1, "rule": rule, "threshold": float("inf") if rule == "adaptive" else float(threshold)}
    if n <= min_separation + 1 or n < 3:
        return ([], details) if return_details else []
    w = fit_whitening(G if fit_on == "raw" else g1, remove, dim, eps, max_samples)
    Z = whiten(w, g1)
    cand = detect_loops(Z, threshold, min_separation, nms_radius, top_k, max_loops, nms=nms,
                        calibrate=rule == "adaptive", false_alarms=false_alarms)
    details["threshold"] = float(cand.threshold)
    if rule == "adaptive" and n > min_separation + 1 and details["threshold"] >= 1.0:
        warnings.warn(
            f"find_loops: the calibrated loop threshold is {details['threshold']:.3f} >= 1 (false_alarms="
            f"{false_alarms:g}): the frames' best scores show no revisit standing out of their own null, so "
            "there is no loop candidate; rule='fixed' with a chosen threshold (and loop verification) "
            "forces candidates",
            stacklevel=2,
        )
    if bool(cand.truncated):
        warnings.warn(
            f"find_loops: NMS stopped at max_loops={max_loops}; more loops may exist", stacklevel=2
        )
    kept = filter_by_chunks(cand, schedule.starts, schedule.chunk_size, n)
    c = int(kept.count)
    loops: list[Loop] = []
    if c:
        # all M buffer rows at once (one compile per buffer size, not per loop count)
        lc = jax.tree.map(np.asarray, _loop_chunks(
            jnp.maximum(kept.pairs, 0), jnp.asarray(schedule.starts), schedule.chunk_size, n,
            half_window,
        ))
        pairs = np.asarray(kept.pairs)
        scores = np.asarray(kept.scores)
        for k in range(c):
            if not lc.valid[k]:
                warnings.warn(
                    f"find_loops: loop ({pairs[k, 0]}, {pairs[k, 1]}) has no well-formed "
                    f"{4 * half_window}-frame loop chunk (a chunk is shorter than {2 * half_window} "
                    "frames); dropped",
                    stacklevel=2,
                )
                continue
            loops.append(
                Loop(int(pairs[k, 0]), int(pairs[k, 1]), float(scores[k]),
                     lc.frames[k].astype(np.int64), int(lc.chunk_i[k]), int(lc.chunk_j[k]),
                     int(lc.local_i[k]), int(lc.local_j[k]))
            )
    details.update(whitening=w, z=Z, candidates=cand, filtered=kept)
    return (loops, details) if return_details else loops


"""Loop detection from VGGT's own DINO patch tokens (SwiftVGGT, Sec. "loop detection").

No separate VPR network: each frame's DINO patch tokens become one place descriptor, and
loops are cosine-similarity matches far apart in time.  The steps::

    tokens [K, d] ──ℓ2 each──► mean ──ℓ2──► g⁰ [d]                       frame_descriptor
    g⁰ ──sign(g)|g|^β──► ℓ2 ──► g¹                                        power_normalize
    {g¹} ──PCA: drop top r, keep d′, W = Q (Λ + ε)^-½──► Whitening       fit_whitening
    g¹ ──(g − μ) W──► ℓ2 ──► ẑ [d′]                                       whiten
    ẑ ──cos sim, top-k per frame, > τ, |i−j| > sep, NMS ±r──► pairs       detect_loops
      (τ per sequence from the frames' best scores, or fixed)             calibrate_threshold
    pairs ──drop pairs inside one chunk, best per chunk pair──► loops     filter_by_chunks
    loop ──20 + 20 frames around both ends──► loop-centric chunk          loop_chunk_frames
    S_{i,loop}, S_{j,loop} ──► S_{j,loop} S_{i,loop}⁻¹                    loop_edge

Modules, one idea each:

* :mod:`swiftjax.loops.options`: the stage's defaults and threshold rules;
* :mod:`swiftjax.loops.descriptors`: ``g⁰``, power normalisation, PCA whitening;
* :mod:`swiftjax.loops.detection`: similarity, per-frame top-k, threshold calibration, NMS;
* :mod:`swiftjax.loops.loop_chunk`: loop-centric chunks, the chunk filter, the loop edge;
* :mod:`swiftjax.loops.find`: :func:`find_loops`, the one host-level call from descriptors
  to the final loop list;
* :mod:`swiftjax.loops.online`: the same as chunks arrive (prefix whitening refitted on a
  doubling schedule or loaded from another run, proposals of each new chunk against all
  earlier frames), with ``find_loops`` itself as the final pass;
* :mod:`swiftjax.loops.verification`: geometric verification of the candidates, the
  decision rule (:mod:`swiftjax.loops.cross_chunk`: the dense cross-chunk test;
  :mod:`swiftjax.loops.null`: its null distribution per candidate;
  :mod:`swiftjax.loops.pcm`: pairwise consistency of loop edges).

``frame_descriptor`` runs per chunk as tokens arrive (the pipeline never holds all tokens:
4,500 frames × 407 tokens × 1024 floats is 7.5 GB); only ``[N, d]`` descriptors are kept.

All array functions are pure and jit-able with static shapes; host-level wrappers
(:func:`find_loops`, and :func:`detect_loops` / :func:`fit_whitening` when called with
concrete arrays) reject NaN/Inf and bad shapes with a clear error before work starts.
"""

from __future__ import annotations

from swiftjax.loops.descriptors import Whitening, fit_whitening, frame_descriptor, power_normalize, whiten
from swiftjax.loops.detection import LoopCandidates, ThresholdCalibration, calibrate_threshold, detect_loops
from swiftjax.loops.find import Loop, find_loops
from swiftjax.loops.loop_chunk import LoopChunk, filter_by_chunks, loop_chunk_frames, loop_edge
from swiftjax.loops.options import (
    AGREEMENT_RULES,
    AUTHORS_THRESHOLD,
    DEFAULT_FALSE_ALARMS,
    DEFAULT_THRESHOLD,
    NULL_MODELS,
    THRESHOLD_RULES,
    VERIFICATION_RULES,
    LoopOptions,
)

__all__ = [
    "LoopOptions",
    "AGREEMENT_RULES",
    "NULL_MODELS",
    "frame_descriptor",
    "power_normalize",
    "Whitening",
    "fit_whitening",
    "whiten",
    "LoopCandidates",
    "ThresholdCalibration",
    "calibrate_threshold",
    "detect_loops",
    "LoopChunk",
    "loop_chunk_frames",
    "filter_by_chunks",
    "loop_edge",
    "Loop",
    "find_loops",
    "DEFAULT_THRESHOLD",
    "AUTHORS_THRESHOLD",
    "DEFAULT_FALSE_ALARMS",
    "THRESHOLD_RULES",
    "VERIFICATION_RULES",
]

"""Loop candidates from whitened descriptors: similarity, per-frame top-k, threshold, NMS.

::

    ẑ ──cos sim, top-k per frame, > τ, |i−j| > sep, NMS ±r──► pairs       detect_loops
      (τ per sequence from the frames' best scores, or fixed)             calibrate_threshold
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import ArrayLike, Float

from swiftjax.loops._checks import _check_finite, _is_concrete
from swiftjax.loops.descriptors import _l2
from swiftjax.loops.options import LoopOptions, check_values

_DEFAULTS = LoopOptions()

__all__ = ["LoopCandidates", "ThresholdCalibration", "calibrate_threshold", "detect_loops"]


class LoopCandidates(NamedTuple):
    """Loop pairs found by :func:`detect_loops` (static shapes; a pytree).

    Attributes:
        pairs: ``[M, 2]`` int32 ``(i, j)`` with ``i > j``; rows ``>= count`` are ``-1``.
        scores: ``[M]`` cosine similarity, descending over the first ``count`` rows; ``-inf``
            after.
        count: int32 scalar, number of valid rows.
        truncated: bool scalar, ``True`` when NMS stopped because ``M`` pairs were accepted
            (more loops may exist; raise ``max_loops``).
        threshold: float scalar, the threshold the candidates passed (the calibrated one
            for ``rule="adaptive"``).
    """

    pairs: jax.Array
    scores: jax.Array
    count: jax.Array
    truncated: jax.Array
    threshold: jax.Array | None = None

    def to_list(self) -> list[tuple[int, int, float]]:
        """Host-side trimmed list ``[(i, j, score), ...]`` sorted by score."""
        c = int(self.count)
        p = np.asarray(self.pairs)[:c]
        s = np.asarray(self.scores)[:c]
        return [(int(a), int(b), float(x)) for (a, b), x in zip(p, s)]


def _default_max_loops(n: int, nms_radius: int, top_k: int, nms: str) -> int:
    if nms == "frame":
        # Accepted pairs have all their ends pairwise > nms_radius apart, so 2M ends fit
        # into N frames: M <= ceil(N / (r + 1)) / 2.  Never truncates.
        return max(1, -(-n // (nms_radius + 1)) // 2 + 1)
    # "pair": at most one accepted pair per candidate; cap the buffer (checked per step).
    return max(1, min(n * top_k, 2048))


def _default_block_rows(n: int) -> int:
    # Small tiles keep the masked [T, N] similarity cache-resident between the GEMM, the mask
    # and top-k (the tile sizes: docs/performance/loops.md).
    return min(n, 128 if n <= 8192 else 256)


class ThresholdCalibration(NamedTuple):
    """A per-sequence threshold from the frames' best scores (:func:`calibrate_threshold`).

    Attributes (float32 scalars): ``threshold`` ``τ = μ + k σ``; ``mu``, ``sigma`` of the
    Gaussian null fitted to the lower quantiles; ``k = Φ̄⁻¹(α / n)``; ``n`` frames with a
    temporally separated partner (``τ = +inf`` when ``n < 2``: no candidate).
    """

    threshold: jax.Array
    mu: jax.Array
    sigma: jax.Array
    k: jax.Array
    n: jax.Array


def _quantile_sorted(x_sorted: jax.Array, n: jax.Array, p: float) -> jax.Array:
    """Linear-interpolation quantile (NumPy's default) of the first ``n`` entries of a sorted array."""
    pos = p * (n - 1).astype(x_sorted.dtype)
    lo = jnp.floor(pos).astype(jnp.int32)
    hi = jnp.minimum(lo + 1, jnp.maximum(n - 1, 0))
    frac = pos - lo
    return x_sorted[lo] * (1.0 - frac) + x_sorted[hi] * frac


@functools.partial(jax.jit, static_argnames=("quantiles",))
def calibrate_threshold(
    best: Float[ArrayLike, " N"],
    false_alarms: float | Float[ArrayLike, ""] = _DEFAULTS.false_alarms,
    quantiles: tuple[float, float] = (0.1, 0.4),
) -> ThresholdCalibration:
    """The loop threshold of one sequence from ``best [N]``, each frame's best similarity
    among temporally separated frames (``-inf``: no such frame; ignored).

    Derivation.  A frame without a revisit has a best score ``b`` drawn from a null
    distribution that depends on the descriptors (dimension, hubness, noise, sequence length
    -- the reason one constant does not transfer); a false candidate is exactly such a
    frame with ``b > τ``.  Model the null as ``N(μ, σ²)`` and estimate it robustly from the
    lower part of the observed ``b``, which frames with a revisit (high ``b``) do not reach
    (``q`` the empirical quantile, ``z = Φ⁻¹``, ``p = quantiles``)::

        σ = (q(p₂) − q(p₁)) / (z(p₂) − z(p₁)),   μ = q(p₂) − z(p₂) σ

    then choose ``τ`` so that the expected number of null frames above it is ``α``
    (``false_alarms``) among the ``n`` frames: ``n Φ̄((τ − μ)/σ) = α``, i.e.
    ``τ = μ + Φ̄⁻¹(α / n) σ``.

    Two biases: with a fraction ``r`` of frames on a revisit, the overall quantile ``p`` is
    the null's ``p / (1 − r)``, which inflates ``μ`` and ``σ`` (a higher, conservative
    ``τ``); and best-of-many scores are right-skewed (Gumbel-like: a shorter lower tail than
    the Gaussian's), which shrinks the lower-quantile ``σ``.  The plain fit above is kept
    (why, and how it compares with the fixed threshold: ``docs/performance/loops.md``).  It
    assumes that fewer than ``1 − p₂`` (60 %) of the frames revisit.

    Pure and jit-compiled (``quantiles`` static; ``false_alarms`` traced); ``q`` is NumPy's
    linear-interpolation quantile over the finite entries.  Recompiles per ``N`` and dtype.
    """
    b = jnp.asarray(best)
    b = b.astype(jnp.promote_types(b.dtype, jnp.float32))
    finite = jnp.isfinite(b)
    n = jnp.sum(finite).astype(jnp.int32)
    srt = jnp.sort(jnp.where(finite, b, jnp.inf))
    p1, p2 = quantiles
    z1, z2 = jax.scipy.special.ndtri(p1), jax.scipy.special.ndtri(p2)
    q1, q2 = _quantile_sorted(srt, n, p1), _quantile_sorted(srt, n, p2)
    sigma = (q2 - q1) / (z2 - z1)
    mu = q2 - z2 * sigma
    k = -jax.scipy.special.ndtri(jnp.asarray(false_alarms, b.dtype) / jnp.maximum(n, 1).astype(b.dtype))
    tau = jnp.where(n >= 2, mu + k * sigma, jnp.inf)
    return ThresholdCalibration(tau, mu, sigma, k, n)


def detect_loops(
    Z: ArrayLike,  # [N, d']: checked here, with a ValueError naming Z (host boundary)
    threshold: float | Float[ArrayLike, ""] = _DEFAULTS.threshold,
    min_separation: int = _DEFAULTS.min_separation,
    nms_radius: int = _DEFAULTS.nms_radius,
    top_k: int = _DEFAULTS.top_k,
    max_loops: int | None = _DEFAULTS.max_loops,
    block_rows: int | None = None,
    nms: str = _DEFAULTS.nms,
    calibrate: bool = False,
    false_alarms: float = _DEFAULTS.false_alarms,
    *,
    throw: bool = True,
) -> LoopCandidates:
    """Loop candidates from descriptors ``Z [N, d′]`` (rows ℓ2-normalised here again).

    ``calibrate=True`` replaces ``threshold`` by :func:`calibrate_threshold` of the rows'
    best masked similarities (the first column of step 2's top-k: no extra pass) with
    ``false_alarms``; the threshold used is returned in ``LoopCandidates.threshold``.

    1. similarity ``s_ij = ẑ_i · ẑ_j``, masked to ``|i − j| > min_separation``;
    2. per frame ``i`` its ``top_k`` most similar (unmasked) frames; each ``(i, j)`` with
       ``s_ij > threshold`` is a candidate, written as ``(max, min)`` (a pair found from both
       ends appears twice; NMS drops the copy);
    3. candidates sorted by similarity, then greedy NMS in that order:

       * ``nms="pair"`` (default): a candidate ``(i, j)`` is suppressed when an accepted pair
         ``(a, b)`` has ``|i − a| <= r`` *and* ``|j − b| <= r`` (the ``±r`` box around both
         ends in the similarity matrix);
       * ``nms="frame"`` (VGGT-Long style): accepting ``(a, b)`` suppresses every frame in
         ``[a − r, a + r]`` and ``[b − r, b + r]``; a candidate touching a suppressed frame is
         dropped.  A place visited three times then yields only two of its three loops.

    The separation mask is applied *before* the per-row top-k (otherwise a frame's top-k are
    its temporal neighbours and no loop survives).  The ``N × N`` matrix is never built:
    rows are processed in tiles of ``block_rows`` (default 128 rows, 256 above N = 8,192),
    keeping only each row's top-k; the pairs are identical for every tile size (the scores
    can differ in the last float32 bit: the GEMM rounds differently per tile shape).  NMS is a ``lax.while_loop``
    over the valid candidates (it stops at the first candidate below the threshold or after
    ``max_loops`` acceptances).

    Args:
        Z: ``[N, d′]`` float descriptors.
        threshold: cosine threshold (traced; no recompile when it changes).
        min_separation, nms_radius, top_k, max_loops, block_rows: static ints;
            ``max_loops=None``: for ``nms="frame"`` the upper bound
            ``ceil(N / (nms_radius + 1)) / 2 + 1`` (never truncates); for ``"pair"``
            ``min(N·top_k, 2048)`` (``truncated`` reports when it was reached).
        nms: ``"pair"`` or ``"frame"`` (static).
        calibrate: static bool; false_alarms: traced ``α`` in ``(0, 1)``.

    Returns:
        :class:`LoopCandidates` with ``max_loops`` rows.  ``N = 1`` or ``N <= min_separation + 1``
        give ``count = 0``.

    Recompiles per ``(N, d′)``, dtype and static option.  Called with a concrete ``Z`` and
    ``throw=True`` it first rejects NaN/Inf rows (and a non-finite threshold) with a
    ``ValueError`` (host boundary); with ``throw=False``, or under an outer ``jit``, a
    non-finite similarity simply never becomes a candidate.
    """
    if jnp.ndim(Z) != 2:
        raise ValueError(f"detect_loops: Z must be [N, d'], got shape {jnp.shape(Z)}")
    if min_separation < 0 or nms_radius < 0 or top_k < 1:
        raise ValueError(
            f"detect_loops needs min_separation >= 0, nms_radius >= 0, top_k >= 1; got "
            f"{min_separation}, {nms_radius}, {top_k}"
        )
    n = jnp.shape(Z)[0]
    if n < 1:
        raise ValueError("detect_loops: Z has no rows")
    check_values({"nms": nms}, "detect_loops")
    if max_loops is None:
        max_loops = _default_max_loops(n, nms_radius, top_k, nms)
    if max_loops < 1:
        raise ValueError(f"detect_loops: max_loops must be >= 1, got {max_loops}")
    if block_rows is None:
        block_rows = _default_block_rows(n)
    if throw and _is_concrete(Z, threshold):
        _check_finite(Z, "detect_loops: descriptors Z")
        if not np.isfinite(np.asarray(threshold)):
            raise ValueError(f"detect_loops: threshold must be finite, got {threshold}")
    if _is_concrete(false_alarms) and not 0.0 < float(false_alarms) < 1.0:
        raise ValueError(f"detect_loops: false_alarms must be in (0, 1), got {false_alarms}")
    return _detect_loops(
        jnp.asarray(Z),
        jnp.asarray(threshold, jnp.float32),
        jnp.asarray(false_alarms, jnp.float32),
        min_separation,
        nms_radius,
        min(top_k, n),
        max_loops,
        min(max(1, block_rows), n),
        nms,
        bool(calibrate),
    )


def _row_topk(Z: jax.Array, min_separation: int, top_k: int, block_rows: int):
    """Per-row top-k of the masked similarity, tile by tile: ``([N, k] scores, [N, k] cols)``."""
    n = Z.shape[0]
    n_tiles = -(-n // block_rows)
    Zp = jnp.pad(Z, ((0, n_tiles * block_rows - n), (0, 0)))
    cols = jnp.arange(n)
    neg = jnp.asarray(-jnp.inf, Z.dtype)

    def tile(t):
        rows = t * block_rows + jnp.arange(block_rows)
        zt = lax.dynamic_slice_in_dim(Zp, t * block_rows, block_rows, 0)
        s = zt @ Z.T  # [T, N]
        ok = jnp.abs(rows[:, None] - cols[None, :]) > min_separation
        s = jnp.where(ok & jnp.isfinite(s), s, neg)
        return lax.top_k(s, top_k)

    vals, idx = lax.map(tile, jnp.arange(n_tiles))
    return vals.reshape(-1, top_k)[:n], idx.reshape(-1, top_k)[:n]


@functools.partial(
    jax.jit,
    static_argnames=("min_separation", "nms_radius", "top_k", "max_loops", "block_rows", "nms", "calibrate"),
)
def _detect_loops(Z, threshold, false_alarms, min_separation, nms_radius, top_k, max_loops, block_rows, nms, calibrate):
    n = Z.shape[0]
    Z = _l2(Z.astype(jnp.promote_types(Z.dtype, jnp.float32)))
    vals, idx = _row_topk(Z, min_separation, top_k, block_rows)
    if calibrate:
        threshold = calibrate_threshold(vals[:, 0], false_alarms).threshold.astype(threshold.dtype)
    rows = jnp.broadcast_to(jnp.arange(n)[:, None], idx.shape)
    a, b = rows.reshape(-1), idx.reshape(-1)
    hi, lo = jnp.maximum(a, b), jnp.minimum(a, b)
    score = vals.reshape(-1)
    valid = score > threshold  # -inf (masked) and NaN are never valid
    key = jnp.where(valid, -score, jnp.inf)
    order = jnp.argsort(key, stable=True)
    hi, lo, score = hi[order], lo[order], score[order]
    n_valid = jnp.sum(valid)

    r = nms_radius
    width = 2 * r + 1
    ones = jnp.ones((width,), bool)

    def cond(state):
        pos, count, *_ = state
        return (pos < n_valid) & (count < max_loops)

    def body(state):
        pos, count, sup, out_p, out_s = state
        i, j = hi[pos], lo[pos]
        if nms == "frame":
            accept = ~(sup[i + r] | sup[j + r])  # sup is padded by r on both sides
            for f in (i, j):
                cur = lax.dynamic_slice_in_dim(sup, f, width)
                sup = lax.dynamic_update_slice_in_dim(sup, cur | (ones & accept), f, 0)
        else:  # "pair": suppressed by an accepted pair within ±r at both ends
            near = (jnp.abs(out_p[:, 0] - i) <= r) & (jnp.abs(out_p[:, 1] - j) <= r)
            accept = ~jnp.any(near & (jnp.arange(max_loops) < count))
        slot = jnp.where(accept, count, max_loops)  # out-of-range write is dropped
        out_p = out_p.at[slot].set(jnp.stack([i, j]).astype(jnp.int32), mode="drop")
        out_s = out_s.at[slot].set(score[pos], mode="drop")
        return pos + 1, count + accept.astype(jnp.int32), sup, out_p, out_s

    init = (
        jnp.int32(0),
        jnp.int32(0),
        jnp.zeros((n + 2 * r,) if nms == "frame" else (1,), bool),
        jnp.full((max_loops, 2), -1, jnp.int32),
        jnp.full((max_loops,), -jnp.inf, Z.dtype),
    )
    pos, count, _, out_p, out_s = lax.while_loop(cond, body, init)
    truncated = (count >= max_loops) & (pos < n_valid)
    return LoopCandidates(out_p, out_s, count, truncated, threshold)

"""The dense test's null distribution: how well do THESE two chunks agree under a wrong edge?

The cross-chunk dense test (:mod:`swiftjax.loops.cross_chunk`) scores a candidate edge ``Z``
(c_i coordinates into c_j's) by ``a(Z) = min(agreement_{i→j}, agreement_{j→i})``.  What a false
edge scores depends on the scene, so a constant bound on ``a`` read off one route sits in the
wrong place on another.  Each candidate is compared instead with the agreement the SAME two
clouds give under ``K`` edges that are clearly wrong but keep what every street shares (road
plane and direction): a sideways shift.  Why this perturbation, why ``κ`` and the measured
distributions: docs/design.md, "The per-candidate null"; docs/performance/loops.md.

**Null edges.**  ``Z_k = P_k Z`` with ``P_k`` a sideways translation in c_j coordinates::

    u   = −normalize(Σ_g R_g[1, :])               up: minus the cameras' mean y axis (OpenCV, y down)
    f   = normalize((I − u uᵀ) Σ_g R_g[2, :])     the cameras' mean viewing direction, horizontal
    P_k = translation by δ_k d̃ (u × f)           d̃: median normalised depth of the target's reliable pixels
    δ_k = ±(δ_min + (δ_max − δ_min) · l / (K/2 − 1)),  l = 0 … K/2 − 1

(``δ_min = 0.15``, ``δ_max = 0.4``; fixed offsets: deterministic, one compile for every candidate).

**Decision** (host level, :func:`null_threshold`, :func:`chance_corrected`).  With the ``K'``
null samples whose ``overlap`` reaches ``min_overlap``, mean ``m`` and sample deviation ``s``
(floored at the standard error of a proportion ``m`` on the fewest pairs in view of one null
sample), the candidate is accepted when both hold::

    a(Z) > τ = m + t_{K'−1}(1 − α) · s · sqrt(1 + 1/K')          not chance
    κ = (a(Z) − m) / (1 − m) >= κ_min                            more than chance, by enough

``τ`` is the one-sided upper prediction bound of one more null draw (``α = 0.01``; with
``K = 16``, ``τ = m + 2.68 s``); ``κ`` is Cohen's chance-corrected agreement
(``κ_min = 0.2``).  That is the ``pooled`` model; the default, ``trend``, bounds ``τ`` and ``m``
per shift direction along a line in the shift (below).

**Two sides, a line in the shift** (:func:`null_threshold`'s ``model``,
``VerificationConfig.null_model``; the default ``trend``).  The samples are no ``K`` draws of
one distribution: each is a smooth function of its shift.  The shifts toward either side of
the street are two families (where one side is open, a square, a junction, a row of parked
cars, a shift toward it keeps the road's agreement at every ``δ`` while a shift the other way
walks the façades off theirs: synthetic KITTI 06, a true candidate, ``0.45 … 0.48`` against
``0.20 … 0.04``), and within a family the agreement falls (or rises) steadily with ``|δ|``
(the nearer shifts still half-align the façades: ``0.64 → 0.28`` on the test route of
``tests/test_pipeline_stages.py``).  Pooled (``pooled``, the rule before), the sample
deviation ``s`` measures the gap between the sides and the trend, not the noise, and puts
``τ`` above a true candidate (06: 0.795 against 0.682); bounded per side as draws of their
own (``sided``), the trend alone does (the test route: 0.875 against 0.828).  ``trend`` fits
per side the least-squares line ``a(x) = â + b̂ (x − x̄)`` in ``x = |δ|`` over the ``n`` samples
in view and bounds a wrong edge of that family anywhere in the shifts' range by the line's
one-sided prediction bound, largest at an end ``e`` of the range::

    τ_side = max_e  â + b̂ (e − x̄) + t_{n−2}(1 − α) s sqrt(1 + 1/n + (e − x̄)² / S_xx)

(``s``: the residual deviation, floored as above; ``S_xx = Σ (x − x̄)²``); the candidate must
beat both sides, ``τ = max(τ₊, τ₋)``, and ``κ``'s ``m`` is the larger fitted end (at least the
side's mean): a wrong edge of either family passes with probability at most ``α`` at every
shift in the range.  On the captured nulls of five routes at three aliasing levels
(docs/performance/loops.md) it accepts every true candidate's dense test (the pooled rule
loses one on KITTI 06, the sided one one on the test route) and rejects every false one.

Pure and jit-compiled (:func:`null_consistency`): the existing dense test, batched with
``vmap`` over the ``K`` null edges and the ``M`` candidates; fixed shapes.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int, Real

from swiftjax import align, sim3
from swiftjax._compile import LIGHT_COMPILE, quick_jit, to_device
from swiftjax._select import nanmedian
from swiftjax.loops.cross_chunk import _ALIGN, _dense_consistency, _normalised, _traced_args, traced_specs
from swiftjax.loops.options import VerificationConfig

__all__ = [
    "null_offsets",
    "config_offsets",
    "null_edges",
    "null_rounds",
    "NullCheck",
    "null_consistency",
    "compile_null",
    "NullThreshold",
    "null_threshold",
    "in_view",
    "chance_corrected",
    "kappa_settled",
]


def null_offsets(samples: int, min_shift: float, max_shift: float) -> Float[np.ndarray, " K"]:
    """The ``K = samples`` (even, >= 4) sideways offsets ``δ_k`` of the null edges ``[K]``
    (fractions of the median depth): ``K/2`` evenly spaced in ``[min_shift, max_shift]``,
    each with both signs."""
    half = np.linspace(min_shift, max_shift, samples // 2)
    return np.concatenate([half, -half])


def null_edges(
    Z: Float[ArrayLike, "8"],
    dst_extrinsic: Float[ArrayLike, "G 3 4"],
    depth: Float[ArrayLike, ""],
    offsets: Float[ArrayLike, " K"],
) -> Float[jax.Array, "K 8"]:
    """The null edges ``Z_k = P_k Z`` (module docstring): ``Z [8]`` maps the source chunk into
    the target chunk, ``dst_extrinsic [G, 3, 4]`` the target frames (world-to-camera in the
    target chunk), ``depth`` the scene depth ``d̃`` (target chunk units), ``offsets [K]``
    ``δ_k``.  Returns ``[K, 8]``; jit-able, recompiles per ``G``, ``K`` and dtype."""
    Z = jnp.asarray(Z)
    E = jnp.asarray(dst_extrinsic, Z.dtype)
    unit = lambda v: v / jnp.maximum(jnp.linalg.norm(v), jnp.finfo(Z.dtype).tiny)
    up = unit(-jnp.sum(E[:, 1, :3], axis=0))  # world direction of camera g's y axis: R_g[1, :]
    ahead = jnp.sum(E[:, 2, :3], axis=0)
    side = unit(jnp.cross(up, unit(ahead - up * jnp.dot(up, ahead))))
    t = (jnp.asarray(offsets, Z.dtype) * jnp.asarray(depth, Z.dtype))[:, None] * side  # [K, 3]
    P = jnp.concatenate([t, jnp.broadcast_to(sim3.identity(dtype=Z.dtype)[3:], (t.shape[0], 5))], axis=-1)
    return sim3.compose(P, Z)


class NullCheck(NamedTuple):
    """:func:`null_consistency` of ``M`` candidates under ``K`` null edges each.

    Attributes:
        score: ``[M, K]`` ``min`` of both directions' ``agreement`` under each null edge.
        overlap: ``[M, K]`` ``min`` of both directions' ``overlap``.
        pairs_seen: int32 ``[M, K]`` ``min`` of both directions' pairs in view.
    """

    score: jax.Array
    overlap: jax.Array
    pairs_seen: jax.Array


@quick_jit(options=LIGHT_COMPILE, static_argnames=("stride", "neighbours"))
def _null_jit(side_i, side_j, Z, K_ref, conf_ratio, depth_tolerance, offsets, stride, neighbours):
    def edge(fi, fj, z):
        a = _dense_consistency(fi, fj, z, K_ref, conf_ratio, depth_tolerance, stride, neighbours)
        b = _dense_consistency(fj, fi, sim3.inverse(z), K_ref, conf_ratio, depth_tolerance, stride, neighbours)
        return (
            jnp.minimum(a.agreement, b.agreement),
            jnp.minimum(a.overlap, b.overlap),
            jnp.minimum(a.pairs_seen, b.pairs_seen),
        )

    def candidate(fi, fj, z):
        d = _normalised(fj, K_ref, conf_ratio)[:, ::stride, ::stride]
        nulls = null_edges(z, fj.extrinsic, nanmedian(d), offsets)
        return NullCheck(*jax.vmap(edge, in_axes=(None, None, 0))(fi, fj, nulls))

    return jax.vmap(candidate)(side_i, side_j, Z)


def null_consistency(
    side_i: align.ChunkFrames,
    side_j: align.ChunkFrames,
    Z: Float[ArrayLike, "M 8"],
    K_ref: Float[ArrayLike, "3 3"],
    config: VerificationConfig | None = None,
    *,
    conf_ratio: float = _ALIGN.conf_ratio,
    edges: Int[ArrayLike, " E"] | None = None,
) -> NullCheck:
    """The dense test of :func:`~swiftjax.loops.cross_chunk.cross_chunk_consistency` under the
    ``K = config.null_samples`` null edges of each of ``M`` candidates (arguments as there);
    ``edges``: only these of the ``K`` (indices into :func:`null_offsets`, e.g. a round of
    :func:`null_rounds`; ``E = K`` when None).

    Returns :class:`NullCheck` with ``[M, E]`` fields.  Recompiles per ``(M, F, H, W)``,
    dtype, ``E``, ``stride`` and ``neighbours``.  Cost: ``E`` times the candidate's own test.
    """
    config = VerificationConfig() if config is None else config
    args = _traced_args(side_i, side_j, Z, K_ref, conf_ratio, config)
    offsets = config_offsets(config)
    if edges is not None:
        offsets = offsets[np.asarray(edges)]
    return _null_jit(*args[:6], to_device(offsets, args[0].depth.dtype), *args[6:])


def config_offsets(config: VerificationConfig) -> Float[np.ndarray, " K"]:
    """``config``'s null offsets ``δ_k [K]`` (:func:`null_offsets` of ``null_samples``,
    ``null_min_shift``, ``null_max_shift``), on the host."""
    return null_offsets(config.null_samples, config.null_min_shift, config.null_max_shift)


def compile_null(
    side_i,
    side_j,
    Z,
    K_ref,
    config: VerificationConfig | None = None,
    *,
    conf_ratio: float = _ALIGN.conf_ratio,
    rounds: bool = False,
) -> None:
    """Compile :func:`null_consistency`'s program ahead of time for arguments of these shapes
    (``jax.ShapeDtypeStruct``s or arrays), as :func:`~swiftjax.loops.cross_chunk.compile_cross_chunk`:
    for all ``K`` edges at once, or with ``rounds`` for the edges of each of :func:`null_rounds`."""
    config = VerificationConfig() if config is None else config
    args = traced_specs(side_i, side_j, Z, K_ref, conf_ratio, config)
    counts = {len(r) for r in null_rounds(config.null_samples)} if rounds else {config.null_samples}
    for E in sorted(counts):
        offsets = jax.ShapeDtypeStruct((E,), args[0].depth.dtype)
        _null_jit.trace(*args[:6], offsets, *args[6:]).lower().compile()


def null_rounds(samples: int) -> tuple[Int[np.ndarray, " E1"], Int[np.ndarray, " E2"]]:
    """The ``K = samples`` null edges (indices into :func:`null_offsets`) in two rounds: every
    other offset of each side, ``l = 0, 2, …`` then ``l = 1, 3, …`` of both ``+δ_l`` and ``−δ_l``,
    so that the first round already spans both sides and the whole range of ``δ`` (and splits
    into the same two sides, first ``+δ`` then ``−δ``, for :func:`null_threshold`'s ``sided``
    model)."""
    half = samples // 2
    l = np.arange(half)
    return np.concatenate([l[0::2], half + l[0::2]]), np.concatenate([l[1::2], half + l[1::2]])


class NullThreshold(NamedTuple):
    """:func:`null_threshold`'s result: ``threshold`` τ (NaN when fewer than three null samples
    see the other chunk), the null's ``mean`` and ``std`` (with its floor), ``samples`` ``K'``."""

    threshold: float
    mean: float
    std: float
    samples: int


def in_view(
    score: Float[ArrayLike, " K"], overlap: Float[ArrayLike, " K"], seen: Real[ArrayLike, " K"], min_overlap: float
) -> Bool[np.ndarray, " K"]:
    """The null samples that say something about chance agreement: finite, ``overlap >=
    min_overlap`` and some pair in view (host level)."""
    return np.isfinite(score) & (np.asarray(overlap) >= min_overlap) & (np.asarray(seen) > 0)


def null_threshold(
    score: Float[ArrayLike, " K"],
    overlap: Float[ArrayLike, " K"],
    pairs_seen: Real[ArrayLike, " K"],
    false_alarm: float,
    min_overlap: float,
    *,
    model: str = "pooled",
    offsets: Float[ArrayLike, " K"] | None = None,
) -> NullThreshold:
    """The null's bound ``τ`` on a wrong edge's agreement, from its samples in view (host
    level; ``model``: :data:`~swiftjax.loops.options.NULL_MODELS`, module docstring).

    ``pooled``: ``τ = m + t_{K'−1}(1 − α) s sqrt(1 + 1/K')`` over the samples in view,
    ``s = max(sample std, sqrt(m (1 − m) / n_min))`` with ``n_min`` the fewest pairs in view
    among them.

    ``sided`` ("Two sides"): the pooled bound over the samples of each shift direction, by the
    sign of ``offsets [K]`` (the samples' ``δ``) or, without them, the first ``K/2`` samples
    (``+δ``, :func:`null_offsets`' order) and the last ``K/2`` (``−δ``).  ``trend`` ("A line
    in the shift"; needs ``offsets``): per shift direction the least-squares
    line in ``|δ|`` and its prediction bound at both ends of the direction's range.  With
    either, the candidate must beat both directions, so ``threshold`` and ``mean`` (κ's ``m``)
    are the larger direction's (the conservative one), ``std`` the direction's whose bound is
    the larger, ``samples`` ``K'`` both together.  A direction with too few samples in view
    for its bound (``sided``: 1–2, ``trend``: 1–3) bounds by its largest sample and its mean (a
    wrong edge of that family agreed that much); with no direction of its own bound, the
    samples pooled (NaN below three in all)."""
    score, overlap, seen = (np.asarray(x, np.float64).reshape(-1) for x in (score, overlap, pairs_seen))
    if model not in ("trend", "pooled", "sided"):
        raise ValueError(f"null_threshold: model must be one of trend, pooled, sided; got {model!r}")
    if model == "pooled":
        return _pooled(score, overlap, seen, false_alarm, min_overlap)
    if offsets is None and model == "trend":
        raise ValueError("null_threshold: model 'trend' needs the samples' offsets")
    if offsets is None:  # sided without the shifts: null_offsets' order, +δ first
        delta = np.where(np.arange(len(score)) < len(score) // 2, 1.0, -1.0)
    else:
        delta = np.asarray(offsets, np.float64).reshape(-1)
    parts = [delta > 0, delta < 0]
    if model == "sided":
        bound = lambda p: _pooled(score[p], overlap[p], seen[p], false_alarm, min_overlap)
    else:
        bound = lambda p: _line(np.abs(delta[p]), score[p], overlap[p], seen[p], false_alarm, min_overlap)
    bounds = []
    for p in parts:
        t = bound(p)
        if math.isfinite(t.threshold):
            bounds.append(t)
        elif t.samples:  # too few in view for a bound: their largest and their mean
            x = score[p][in_view(score[p], overlap[p], seen[p], min_overlap)]
            bounds.append(NullThreshold(float(x.max()), float(x.mean()), math.nan, t.samples))
    if not any(math.isfinite(t.std) for t in bounds):
        return _pooled(score, overlap, seen, false_alarm, min_overlap)
    top = max(bounds, key=lambda t: t.threshold)
    return NullThreshold(top.threshold, max(t.mean for t in bounds), top.std, sum(t.samples for t in bounds))


def _pooled(
    score: np.ndarray, overlap: np.ndarray, seen: np.ndarray, false_alarm: float, min_overlap: float
) -> NullThreshold:
    """:func:`null_threshold` with ``model = "pooled"`` (its docstring)."""
    from scipy import stats

    use = in_view(score, overlap, seen, min_overlap)
    k = int(use.sum())
    if k < 3:
        return NullThreshold(math.nan, math.nan, math.nan, k)
    m = float(score[use].mean())
    s = max(float(score[use].std(ddof=1)), math.sqrt(m * (1 - m) / float(seen[use].min())))
    t = float(stats.t.ppf(1.0 - false_alarm, k - 1))
    return NullThreshold(m + t * s * math.sqrt(1.0 + 1.0 / k), m, s, k)


def _line(
    x: np.ndarray, score: np.ndarray, overlap: np.ndarray, seen: np.ndarray, false_alarm: float, min_overlap: float
) -> NullThreshold:
    """One shift direction's bound under ``model = "trend"`` (module docstring, "A line in the
    shift"): the line ``â + b̂ (x − x̄)`` fitted to the ``n >= 4`` samples in view at shifts
    ``x = |δ|``, ``s = max(residual std on n − 2 degrees of freedom, sqrt(ȳ (1 − ȳ) / n_min))``,
    and the larger of its upper prediction bounds at the ends ``e`` of ``x``'s range (all of
    ``x``, in view or not)::

        τ = max_e  â + b̂ (e − x̄) + t_{n−2}(1 − α) s sqrt(1 + 1/n + (e − x̄)² / S_xx)

    ``mean``: the larger fitted end, clipped to ``[0, 1]`` (at least ``ȳ``: the line passes
    through ``(x̄, ȳ)``).  NaN threshold (and std) below four samples in view."""
    from scipy import stats

    use = in_view(score, overlap, seen, min_overlap)
    n = int(use.sum())
    xs, y = x[use], score[use]
    sxx = float(np.sum((xs - xs.mean()) ** 2)) if n else 0.0
    if n < 4 or sxx <= 0.0:
        return NullThreshold(math.nan, math.nan, math.nan, n)
    xb, yb = float(xs.mean()), float(y.mean())
    slope = float(np.sum((xs - xb) * (y - yb))) / sxx
    residual = y - (yb + slope * (xs - xb))
    s = max(math.sqrt(float(np.sum(residual**2)) / (n - 2)), math.sqrt(yb * (1 - yb) / float(seen[use].min())))
    t = float(stats.t.ppf(1.0 - false_alarm, n - 2))
    ends = np.array([x.min(), x.max()])
    fit = yb + slope * (ends - xb)
    tau = fit + t * s * np.sqrt(1.0 + 1.0 / n + (ends - xb) ** 2 / sxx)
    return NullThreshold(float(tau.max()), float(np.clip(fit.max(), 0.0, 1.0)), s, n)


def chance_corrected(agreement: float, null_mean: float) -> float:
    """Cohen's ``κ = (a − m) / (1 − m)``: the fraction of the pairs that do not agree by chance
    (``m``, the null's mean agreement) that agree under the candidate edge (``a``)."""
    return (agreement - null_mean) / max(1.0 - null_mean, 1e-12)


def kappa_settled(
    agreement: float,
    score: Float[ArrayLike, " E"],
    overlap: Float[ArrayLike, " E"],
    pairs_seen: Real[ArrayLike, " E"],
    remaining: int,
    min_kappa: float,
    min_overlap: float,
) -> bool:
    """Whether a candidate of ``agreement`` is rejected by the chance-corrected test whatever
    the ``remaining`` null samples not drawn yet, given the ``E`` drawn (host level; exact).

    With ``k >= 3`` of the drawn samples in view (:func:`null_threshold`'s rule; the complete
    null then has a finite bound) summing to ``Σ``, the complete null's pooled mean is
    ``m = (Σ + Σ') / (k + k')`` over the ``k' <= remaining`` further samples in view, each an
    agreement in ``[0, 1]``, so ``m >= m_low = Σ / (k + remaining)`` (all of them in view and
    agreeing nowhere); the ``sided`` and ``trend`` models' mean, the larger side's (its mean or
    its larger fitted end, at least its mean), is at least the pooled one.
    ``κ(m) = (a − m) / (1 − m)`` falls as ``m`` grows (:func:`swiftjax.loops.verification.null_needed`),
    so ``κ(m_low) < κ_min`` rejects the candidate under every completion.  The drawn samples'
    own mean ``Σ / k >= m_low`` gives a ``κ`` below ``κ_min`` too: their numbers, recorded in
    place of the complete null's, give the same verdict."""
    score, overlap, seen = (np.asarray(x, np.float64).reshape(-1) for x in (score, overlap, pairs_seen))
    use = in_view(score, overlap, seen, min_overlap)
    k = int(use.sum())
    if k < 3:
        return False
    return chance_corrected(agreement, float(score[use].sum()) / (k + remaining)) < min_kappa

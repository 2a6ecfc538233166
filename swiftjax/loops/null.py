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
(``κ_min = 0.2``).

**Two sides** (:func:`null_threshold` with ``sided = True``; ``VerificationConfig.null_sided``). The
shifts toward either side of the street are two nulls, not one: where one side is open (a
square, a junction, a row of parked cars) a shift toward it keeps the road's agreement at every
``δ`` while a shift the other way walks the façades off theirs (synthetic KITTI 06, a true
candidate: ``0.45 … 0.48`` against ``0.20 … 0.04``). Pooled, such a sample is no normal draw:
its ``s`` measures the gap between the sides (0.19 there) and puts ``τ`` above the true
candidate (0.795 against 0.682). Each side is bounded on its own (``K/2`` samples,
``t_{K/2−1}``) and the candidate must beat both, ``τ = max(τ₊, τ₋)``, ``m = max(m₊, m₋)``: a
wrong edge like either family passes with probability at most ``α``.  It is not the default:
with half the samples the t factor grows (``t₇`` against ``t₁₅``), and a side whose agreement
falls steadily with ``δ`` (the nearer shifts still half-align its façades) then bounds above a
true candidate that the pooled null passes (the test route of ``tests/test_pipeline_stages.py``:
agreement 0.828 against 0.875; pooled 0.780).

Pure and jit-compiled (:func:`null_consistency`): the existing dense test, batched with
``vmap`` over the ``K`` null edges and the ``M`` candidates; fixed shapes.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, Int, Real

from swiftjax import align, sim3
from swiftjax._compile import LIGHT_COMPILE, quick_jit, to_device
from swiftjax._select import nanmedian
from swiftjax.loops.cross_chunk import _ALIGN, _dense_consistency, _normalised, _traced_args, traced_specs
from swiftjax.loops.options import VerificationConfig

__all__ = [
    "null_offsets",
    "null_edges",
    "null_rounds",
    "NullCheck",
    "null_consistency",
    "compile_null",
    "NullThreshold",
    "null_threshold",
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
    offsets = _offsets(config) if edges is None else _offsets(config)[np.asarray(edges)]
    return _null_jit(*args[:6], to_device(offsets, args[0].depth.dtype), *args[6:])


def _offsets(config: VerificationConfig) -> Float[np.ndarray, " K"]:
    """``config``'s null offsets (:func:`null_offsets`), on the host."""
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
    into the same two sides, first ``+δ`` then ``−δ``, for :func:`null_threshold`'s ``sided``)."""
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


def _in_view(score: np.ndarray, overlap: np.ndarray, seen: np.ndarray, min_overlap: float) -> np.ndarray:
    """The null samples that say something about chance agreement: finite, ``overlap >=
    min_overlap`` and some pair in view."""
    return np.isfinite(score) & (overlap >= min_overlap) & (seen > 0)


def null_threshold(
    score: Float[ArrayLike, " K"],
    overlap: Float[ArrayLike, " K"],
    pairs_seen: Real[ArrayLike, " K"],
    false_alarm: float,
    min_overlap: float,
    *,
    sided: bool = False,
) -> NullThreshold:
    """``τ = m + t_{K'−1}(1 − α) s sqrt(1 + 1/K')`` over the null samples in view (host level;
    module docstring).  ``s = max(sample std, sqrt(m (1 − m) / n_min))`` with ``n_min`` the
    fewest pairs in view among them.

    ``sided`` (``VerificationConfig.null_sided``; module docstring, "Two sides"): each shift direction
    a null of its own, the bound above over the first ``K/2`` samples (shifts ``+δ``,
    :func:`null_offsets`) and over the last ``K/2`` (``−δ``); the candidate must beat both, so
    ``threshold = max(τ₊, τ₋)`` and ``mean = max(m₊, m₋)`` (κ's ``m``: the larger, the
    conservative one); ``std`` is the side's whose bound is the larger, ``samples`` ``K'`` both
    sides' together.  A side with only one or two samples in view has no t bound: it bounds by
    its largest sample and its mean (a wrong edge of that family agreed that much).  With no
    side of three, the two sides pooled (NaN below three in all)."""
    from scipy import stats

    score, overlap, seen = (np.asarray(x, np.float64).reshape(-1) for x in (score, overlap, pairs_seen))
    if sided:
        return _sided(score, overlap, seen, false_alarm, min_overlap)
    use = _in_view(score, overlap, seen, min_overlap)
    k = int(use.sum())
    if k < 3:
        return NullThreshold(math.nan, math.nan, math.nan, k)
    m = float(score[use].mean())
    s = max(float(score[use].std(ddof=1)), math.sqrt(m * (1 - m) / float(seen[use].min())))
    t = float(stats.t.ppf(1.0 - false_alarm, k - 1))
    return NullThreshold(m + t * s * math.sqrt(1.0 + 1.0 / k), m, s, k)


def _sided(
    score: np.ndarray, overlap: np.ndarray, seen: np.ndarray, false_alarm: float, min_overlap: float
) -> NullThreshold:
    """:func:`null_threshold` with ``sided = True`` (its docstring)."""
    half = len(score) // 2
    parts = (slice(None, half), slice(half, None))
    sides = [null_threshold(score[p], overlap[p], seen[p], false_alarm, min_overlap) for p in parts]
    if not any(math.isfinite(t.threshold) for t in sides):
        return null_threshold(score, overlap, seen, false_alarm, min_overlap)
    bounds = []
    for t, p in zip(sides, parts):
        if math.isfinite(t.threshold):
            bounds.append(t)
        elif t.samples:  # one or two in view: their largest and their mean
            x = score[p][_in_view(score[p], overlap[p], seen[p], min_overlap)]
            bounds.append(NullThreshold(float(x.max()), float(x.mean()), math.nan, t.samples))
    top = max(bounds, key=lambda t: t.threshold)
    return NullThreshold(top.threshold, max(t.mean for t in bounds), top.std, sum(t.samples for t in sides))


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
    agreeing nowhere); the sided rule's mean, the larger side's, is at least the pooled one.
    ``κ(m) = (a − m) / (1 − m)`` falls as ``m`` grows (:func:`swiftjax.loops.verification.null_needed`),
    so ``κ(m_low) < κ_min`` rejects the candidate under every completion.  The drawn samples'
    own mean ``Σ / k >= m_low`` gives a ``κ`` below ``κ_min`` too: their numbers, recorded in
    place of the complete null's, give the same verdict."""
    score, overlap, seen = (np.asarray(x, np.float64).reshape(-1) for x in (score, overlap, pairs_seen))
    use = _in_view(score, overlap, seen, min_overlap)
    k = int(use.sum())
    if k < 3:
        return False
    return chance_corrected(agreement, float(score[use].sum()) / (k + remaining)) < min_kappa

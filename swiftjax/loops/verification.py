"""Geometric verification of loop candidates: a DINO match is a hypothesis, not an edge.

A loop candidate ``(i, j)`` (frames, ``i > j``) comes with a loop-centric chunk whose two
halves were aligned to their temporal chunks ``c_i`` and ``c_j``, giving the candidate edge
``Z = S_{j,loop} S_{i,loop}⁻¹`` (:func:`swiftjax.loops.loop_edge`), which maps chunk ``c_i``
coordinates into chunk ``c_j`` coordinates (pose-graph edge ``c_j → c_i``, ``Z ≈ S_{c_j}⁻¹
S_{c_i}``).  VGGT given two sets of frames that share no view still returns one coherent
reconstruction, so ``Z`` alone proves nothing.  Three tests that do not trust the loop chunk:

1. **Cross-chunk dense consistency** (:func:`dense_consistency`,
   :func:`cross_chunk_consistency`).  The temporal chunks' *own* predictions around both ends
   must agree under ``Z``, like eq. 2 across the loop.  Reliable points of the ``c_i`` frames
   around ``i`` (eq. 2's ingredients: depth normalised to ``K_ref`` (eq. 1), confidence
   ``γ > λ_γ · mean_frame(γ)``), pixel grid subsampled by ``stride``::

       x = E_f⁻¹ (r_f D_f(u, v) K_ref⁻¹ (u, v, 1)ᵀ)          point of frame f in c_i coordinates
       y = Z x = s R x + t                                    the same point in c_j coordinates
       p = E_g y,  z' = p_z,  (u', v') = round(π(K_ref p))    in each c_j frame g around j

   Each source frame is compared with the ``neighbours`` target frames whose cameras are
   nearest to its own camera mapped by ``Z``.  A (point, target frame) pair is *in view*
   when ``z' > 0``, ``(u', v')`` is inside the image and the stored pixel of ``g`` is
   reliable; it *agrees* when ``|z' − D̂_g(u', v')| <= τ · D̂_g(u', v')`` (``D̂`` the
   normalised stored depth, ``τ = depth_tolerance``, relative, so free of each chunk's
   arbitrary units).  The statistics: ``agreement = #agreeing pairs / #pairs in view`` and
   ``overlap = #points in view of some frame / #reliable points``; the symmetric direction
   (``c_j → c_i`` with ``Z⁻¹``) is computed too and the candidate's score is the smaller
   ``agreement``.  A true revisit sees the same surfaces from nearby cameras: most pairs
   agree.  A hallucinated edge either maps the points out of view (``overlap ≈ 0``: the
   frames are far apart) or superimposes two different streets, where only surfaces that
   every street shares (the road plane seen from the same camera height) agree.

2. **Loop-chunk quality** (:func:`loop_chunk_quality`): each half's alignment to its temporal
   chunk must be a valid Umeyama solve (no pose fallback) on enough reliable points
   (``fraction_used``), with its residual recorded.

3. **Pairwise consistency** (PCM, Mangelson et al. ICRA 2018, as Kimera-RPGO;
   :func:`pairwise_consistency`, :func:`max_consistent_set`).  Two loop edges ``a``, ``b``
   and the odometry chain between their ends form a cycle that must be the identity up to
   the odometry's accumulated uncertainty.  With dead-reckoning chunk poses ``X_t``
   (chained temporal edges) every loop ``k = (p_k → q_k)``, ``p_k < q_k``, implies the drift
   ``D_k = X_{p_k} Z_k X_{q_k}⁻¹`` (identity for perfect odometry); the cycle is
   ``E_ab = D_a⁻¹ D_b`` (``= X_{q_a} (Z_a⁻¹ X_{p_a}⁻¹ X_{p_b} Z_b X_{q_b}⁻¹ X_{q_a}) X_{q_a}⁻¹``,
   the loop through both edges conjugated into the world frame).  To first order a right
   perturbation ``δ_e`` of temporal edge ``e`` moves every ``X_t``, ``t > e``, by the left
   world perturbation ``w_e = Ad(X_{e+1}) δ_e``, and ``D_k`` by ``-Σ_{e ∈ [p_k, q_k)} w_e``
   on the right, so with world covariances ``C_e = Ad(X_{e+1}) Σ_e Ad(X_{e+1})ᵀ`` and their
   prefix sums ``P_t = Σ_{e < t} C_e``::

       Σ_ab = P[a] + P[b] − 2 P[a ∩ b] + Ad(X_{q_a}) Σ_{Z_a} Ad(X_{q_a})ᵀ + (same for b)
       m_ab = sqrt(rᵀ Σ_ab⁻¹ r),   r = log(E_ab)                      (whitened residual)

   (``P[[p, q)] = P_q − P_p``; the linearisation is at ``E_ab = I``, the hypothesis being
   tested).  ``m_ab <= threshold`` makes ``a`` and ``b`` consistent; the accepted loops are
   a maximum clique of the consistency graph (exact Bron–Kerbosch with pivoting on the host,
   fine for the tens of candidates a sequence has; ties broken by the larger sum of dense
   consistency scores).  The per-edge covariances ``Σ_e`` come from a drift model
   (:func:`odometry_covariance`): VGGT's chunk-to-chunk error is model error (drift), which
   the alignment's own statistics do not see.

Everything is pure and jit-compiled with static shapes (masks, never boolean indexing);
:func:`cross_chunk_consistency` is batched over candidates with ``vmap`` and loops over the
target frames with ``lax.scan``.  The decision rule and its thresholds live in
:class:`VerificationConfig` / :func:`verify_candidates` (host level).  The thresholds were
chosen from measured distributions of true and false candidates (docs/performance/loops.md).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxtyping import Array, ArrayLike, Bool, Float, Int

from swiftjax import align, camera, sim3
from swiftjax.loops.options import VerificationConfig

_DEFAULTS = VerificationConfig()

__all__ = [
    "ConsistencyInfo",
    "dense_consistency",
    "CrossCheck",
    "cross_chunk_consistency",
    "LoopQuality",
    "loop_chunk_quality",
    "candidate_numbers",
    "odometry_covariance",
    "loop_covariance",
    "pairwise_consistency",
    "max_consistent_set",
    "VerificationConfig",
    "Decision",
    "verify_candidates",
]


# ------------------------------------------------------------------ dense consistency


class ConsistencyInfo(NamedTuple):
    """Result of :func:`dense_consistency` (every field has the batch shape ``[...]``).

    Pairs are (point, target frame) with the target among the source frame's ``neighbours``
    nearest cameras.

    Attributes:
        num_points: int32 reliable source points (finite positive depth, confidence above
            ``λ_γ`` times the frame mean, on the ``stride`` grid).
        num_seen: int32 of those seen by at least one target frame (in front of the camera,
            inside the image, on a reliable target pixel).
        num_agree: int32 of those whose depth agrees in at least one target frame.
        pairs_seen: int32 (point, target frame) pairs in view.
        pairs_agree: int32 (point, target frame) pairs in view whose depth agrees.
        pairs_front: int32 pairs in view whose point lies in front of the target's surface
            (``z' < (1 − τ) D̂``: a free-space violation, recorded, not used).
        overlap: ``num_seen / num_points`` (0 when there are no points).
        agreement: ``pairs_agree / pairs_seen`` (0 when nothing is seen), the verification
            statistic.
        consistency: ``num_agree / num_points``.
    """

    num_points: jax.Array
    num_seen: jax.Array
    num_agree: jax.Array
    pairs_seen: jax.Array
    pairs_agree: jax.Array
    pairs_front: jax.Array
    overlap: jax.Array
    agreement: jax.Array
    consistency: jax.Array


def _normalised(frames: align.ChunkFrames, K_ref: jax.Array, conf_ratio: jax.Array):
    """Normalised depth (eq. 1) with NaN where a pixel is not reliable: ``[F, H, W]``."""
    d = camera.normalize_depth(frames.depth, frames.intrinsic, K_ref)
    mean = align.frame_conf_mean(frames.conf)
    ok = (
        jnp.isfinite(d) & (d > 0) & jnp.isfinite(frames.conf)
        & (frames.conf > conf_ratio * mean[:, None, None])
    )
    return jnp.where(ok, d, jnp.nan)


def _dense_consistency(src, dst, S, K_ref, conf_ratio, depth_tolerance, stride: int, neighbours: int) -> ConsistencyInfo:
    dtype = src.depth.dtype
    K_ref = K_ref.astype(dtype)
    F = src.depth.shape[0]
    G, h, w = dst.depth.shape
    # source points on the stride grid, in source chunk coordinates, then mapped by S
    d_src = _normalised(src, K_ref, conf_ratio)[:, ::stride, ::stride]  # [F, h', w']
    rays = camera.pixel_rays(K_ref, h, w)[::stride, ::stride]  # [h', w', 3]
    c2w = camera.camera_to_world(src.extrinsic)  # [F, 3, 4]
    cam = d_src[..., None] * rays  # NaN where unreliable
    x = jnp.einsum("fij,fhwj->fhwi", c2w[:, :, :3], cam) + c2w[:, None, None, :, 3]
    n_per = x.shape[1] * x.shape[2]
    ok = jnp.all(jnp.isfinite(x), -1).reshape(-1)
    y = sim3.act(S, jnp.where(ok[:, None], x.reshape(-1, 3), 0))  # [P, 3]
    ok = ok & jnp.all(jnp.isfinite(y), -1)
    # frame pairs: each source frame is compared with its `neighbours` nearest target cameras
    # (centres after S); 0 = all target frames
    centres = sim3.act(S, c2w[:, :, 3])  # [F, 3]
    dst_c2w = camera.camera_to_world(dst.extrinsic.astype(dtype))
    dist = jnp.linalg.norm(centres[:, None, :] - dst_c2w[None, :, :, 3], axis=-1)  # [F, G]
    dist = jnp.where(jnp.isfinite(dist), dist, jnp.inf)
    if 0 < neighbours < G:
        rank = jnp.argsort(jnp.argsort(dist, axis=1), axis=1)
        pair = rank < neighbours
    else:
        pair = jnp.ones((F, G), bool)
    d_dst = _normalised(dst, K_ref, conf_ratio).reshape(G, -1)  # [G, H W]
    fx, fy, cx, cy, sk = K_ref[0, 0], K_ref[1, 1], K_ref[0, 2], K_ref[1, 2], K_ref[0, 1]
    tol = jnp.asarray(depth_tolerance, dtype)

    def step(carry, xs):
        seen, agree, n_seen, n_agree, n_front = carry
        depth_g, E, pair_g = xs
        p = y @ E[:, :3].T + E[:, 3]
        z = p[:, 2]
        use = ok & jnp.repeat(pair_g, n_per, total_repeat_length=y.shape[0]) & (z > 0)
        zs = jnp.where(use, z, 1)
        u = jnp.round(fx * p[:, 0] / zs + sk * p[:, 1] / zs + cx)
        v = jnp.round(fy * p[:, 1] / zs + cy)
        inside = use & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        idx = jnp.where(inside, v * w + u, 0).astype(jnp.int32)
        D = depth_g[idx]
        view = inside & jnp.isfinite(D)
        good = view & (jnp.abs(z - D) <= tol * D)
        front = view & (z < (1 - tol) * D)
        count = lambda m: jnp.sum(m, dtype=jnp.int32)  # noqa: E731
        return (seen | view, agree | good, n_seen + count(view), n_agree + count(good),
                n_front + count(front)), None

    P = y.shape[0]
    zero = jnp.zeros((), jnp.int32)
    init = (jnp.zeros(P, bool), jnp.zeros(P, bool), zero, zero, zero)
    (seen, agree, n_seen, n_agree, n_front), _ = lax.scan(
        step, init, (d_dst, dst.extrinsic.astype(dtype), pair.T)
    )
    num = jnp.sum(ok).astype(jnp.int32)
    num_seen = jnp.sum(seen).astype(jnp.int32)
    num_agree = jnp.sum(agree).astype(jnp.int32)
    ratio = lambda a, b: jnp.where(b > 0, a.astype(dtype) / jnp.maximum(b, 1).astype(dtype), 0)  # noqa: E731
    return ConsistencyInfo(
        num_points=num, num_seen=num_seen, num_agree=num_agree, pairs_seen=n_seen,
        pairs_agree=n_agree, pairs_front=n_front, overlap=ratio(num_seen, num),
        agreement=ratio(n_agree, n_seen), consistency=ratio(num_agree, num),
    )


def _frames(x, dtype=None) -> align.ChunkFrames:
    f = align.ChunkFrames(*(jnp.asarray(getattr(x, k)) for k in align.ChunkFrames._fields))
    if dtype is None:
        dtype = f.depth.dtype if f.depth.dtype in (jnp.float32, jnp.float64) else jnp.float32
    return align.ChunkFrames(*(a.astype(dtype) for a in f))


@functools.partial(jax.jit, static_argnames=("stride", "neighbours"))
def _dense_consistency_jit(src, dst, S, K_ref, conf_ratio, depth_tolerance, stride, neighbours):
    return _dense_consistency(src, dst, S, K_ref, conf_ratio, depth_tolerance, stride, neighbours)


def dense_consistency(
    src: align.ChunkFrames,
    dst: align.ChunkFrames,
    S_dst_src: Float[ArrayLike, "8"],
    K_ref: Float[ArrayLike, "3 3"],
    *,
    stride: int = _DEFAULTS.stride,
    conf_ratio: float = 0.5,
    depth_tolerance: float = _DEFAULTS.depth_tolerance,
    neighbours: int = _DEFAULTS.neighbours,
) -> ConsistencyInfo:
    """How many reliable points of ``src`` land on agreeing depth in ``dst`` under ``S``.

    Args:
        src: :class:`~swiftjax.align.ChunkFrames` ``depth, conf [F, H, W]``, ``intrinsic
            [F, 3, 3]``, ``extrinsic [F, 3, 4]`` (world-to-camera in the source chunk).
        dst: the same for ``G`` frames of the target chunk (same ``H, W``).
        S_dst_src: Sim(3) ``[8]`` mapping source chunk coordinates into target chunk
            coordinates (for a loop edge ``Z`` from c_i's frames into c_j's: ``Z``).
        K_ref: ``[3, 3]`` reference intrinsics (both chunks' depths are normalised to it).
        stride: static source pixel subsampling (``F · ceil(H/stride) · ceil(W/stride)``
            points; the targets are looked up at full resolution, nearest pixel).
        neighbours: static; each source frame is compared with this many target frames,
            those whose cameras are nearest to its camera mapped by ``S`` (0: all).
        conf_ratio: ``λ_γ``, as eq. 2 (both sides).
        depth_tolerance: relative depth agreement ``τ``.

    Returns:
        :class:`ConsistencyInfo` (module docstring for the equations).  A non-finite ``S``
        or input pixel never counts as agreeing (the point or pixel is dropped).

    One jitted call; recompiles per ``(F, G, H, W)``, dtype (float32 for float16 input),
    ``stride`` and ``neighbours``; the other options are traced.  Cost: ``G`` passes over the
    ``P`` source points (``lax.scan``), each a projection and one gather.
    """
    src = _frames(src)
    dst = _frames(dst, src.depth.dtype)
    dt = src.depth.dtype
    return _dense_consistency_jit(
        src, dst, jnp.asarray(S_dst_src, dt), jnp.asarray(K_ref, dt), jnp.asarray(conf_ratio, dt),
        jnp.asarray(depth_tolerance, dt), stride, neighbours,
    )


class CrossCheck(NamedTuple):
    """:func:`cross_chunk_consistency` of candidates ``[M]``.

    Attributes:
        i_to_j: :class:`ConsistencyInfo` of c_i's frames around ``i`` mapped by ``Z`` into
            c_j's frames around ``j``.
        j_to_i: the reverse direction (``Z⁻¹``).
        score: ``min(i_to_j.agreement, j_to_i.agreement)`` ``[M]``.
    """

    i_to_j: ConsistencyInfo
    j_to_i: ConsistencyInfo
    score: jax.Array


@functools.partial(jax.jit, static_argnames=("stride", "neighbours"))
def _cross_jit(side_i, side_j, Z, K_ref, conf_ratio, depth_tolerance, stride, neighbours):
    def one(fi, fj, z):
        a = _dense_consistency(fi, fj, z, K_ref, conf_ratio, depth_tolerance, stride, neighbours)
        b = _dense_consistency(fj, fi, sim3.inverse(z), K_ref, conf_ratio, depth_tolerance, stride, neighbours)
        return CrossCheck(a, b, jnp.minimum(a.agreement, b.agreement))

    return jax.vmap(one)(side_i, side_j, Z)


def cross_chunk_consistency(
    side_i: align.ChunkFrames,
    side_j: align.ChunkFrames,
    Z: Float[ArrayLike, "M 8"],
    K_ref: Float[ArrayLike, "3 3"],
    *,
    stride: int = _DEFAULTS.stride,
    conf_ratio: float = 0.5,
    depth_tolerance: float = _DEFAULTS.depth_tolerance,
    neighbours: int = _DEFAULTS.neighbours,
) -> CrossCheck:
    """Both directions of :func:`dense_consistency` for ``M`` loop candidates at once (vmap).

    Args:
        side_i: frames of temporal chunk ``c_i`` around ``i`` with a leading candidate axis
            (``depth, conf [M, F, H, W]``, ``intrinsic [M, F, 3, 3]``, ``extrinsic [M, F, 3, 4]``);
            in the pipeline the ``2h`` frames the loop chunk's first half overlaps.
        side_j: the same for chunk ``c_j`` around ``j``.
        Z: ``[M, 8]`` loop edges mapping ``c_i`` into ``c_j`` (:func:`swiftjax.loops.loop_edge`).
        K_ref, stride, conf_ratio, depth_tolerance, neighbours: as :func:`dense_consistency`.

    Returns:
        :class:`CrossCheck` with ``[M]`` fields.  Recompiles per ``(M, F, H, W)``, dtype and
        ``stride``.
    """
    si = _frames(side_i)
    dt = si.depth.dtype
    sj = _frames(side_j, dt)
    return _cross_jit(
        si, sj, jnp.asarray(Z, dt), jnp.asarray(K_ref, dt), jnp.asarray(conf_ratio, dt),
        jnp.asarray(depth_tolerance, dt), stride, neighbours,
    )


# ---------------------------------------------------------------------- loop quality


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
    get = lambda x, k: jnp.asarray(x[k] if isinstance(x, dict) else getattr(x, k))  # noqa: E731
    return LoopQuality(
        min_points=jnp.minimum(get(info_i, "num_points"), get(info_j, "num_points")),
        min_fraction=jnp.minimum(get(info_i, "fraction_used"), get(info_j, "fraction_used")),
        max_rms=jnp.maximum(get(info_i, "rms"), get(info_j, "rms")),
        valid=(get(info_i, "valid") & get(info_j, "valid")
               & ~get(info_i, "pose_fallback") & ~get(info_j, "pose_fallback")),
    )


def candidate_numbers(
    side_i: align.ChunkFrames,
    side_j: align.ChunkFrames,
    Z: Float[ArrayLike, "8"],
    K_ref: Float[ArrayLike, "3 3"],
    info_i: Any,
    info_j: Any,
    config: VerificationConfig | None = None,
) -> dict[str, Any]:
    """The verification numbers of one candidate as a plain dict (host level, for records).

    ``side_i``/``side_j``: ``[F, H, W]`` frames of the temporal chunks around both ends (as
    :func:`cross_chunk_consistency`, without the candidate axis); ``Z [8]`` maps c_i into
    c_j; ``info_i``/``info_j`` the halves' alignment diagnostics (:func:`loop_chunk_quality`).
    Keys: ``dense_agreement``, ``dense_overlap`` (the smaller direction's), ``dense_i_to_j``
    and ``dense_j_to_i`` (every :class:`ConsistencyInfo` field), ``quality_valid``,
    ``quality_min_points``, ``quality_min_fraction``, ``quality_max_rms``.
    """
    config = config or VerificationConfig()
    one = lambda f: align.ChunkFrames(*(np.asarray(a, np.float32)[None] for a in f))  # noqa: E731
    cc = cross_chunk_consistency(
        one(side_i), one(side_j), np.asarray(Z, np.float32)[None], K_ref, stride=config.stride,
        depth_tolerance=config.depth_tolerance, neighbours=config.neighbours,
    )
    plain = lambda info: {k: float(np.asarray(v)[0]) if np.asarray(v).dtype.kind == "f" else int(np.asarray(v)[0])  # noqa: E731
                          for k, v in info._asdict().items()}
    q = loop_chunk_quality(info_i, info_j)
    return {
        "dense_agreement": float(np.asarray(cc.score)[0]),
        "dense_overlap": float(min(np.asarray(cc.i_to_j.overlap)[0], np.asarray(cc.j_to_i.overlap)[0])),
        "dense_i_to_j": plain(cc.i_to_j),
        "dense_j_to_i": plain(cc.j_to_i),
        "quality_valid": bool(q.valid),
        "quality_min_points": int(q.min_points),
        "quality_min_fraction": float(q.min_fraction),
        "quality_max_rms": float(q.max_rms),
    }


# ------------------------------------------------------------------- pairwise (PCM)


@jax.jit
def odometry_covariance(
    relative: Float[ArrayLike, "*batch 8"], sigma_rot: float | Float[ArrayLike, ""],
    sigma_trans: float | Float[ArrayLike, ""], sigma_scale: float | Float[ArrayLike, ""],
) -> Float[Array, "*batch 7 7"]:
    """Drift model of the temporal edges: diagonal covariances ``[E, 7, 7]`` in ``(ρ, ω, σ)``.

    For edge ``Z_e = (t, R, s)`` (right perturbation ``Z_e exp(δ)``): ``std(ρ) = sigma_trans ·
    |t| / s`` (relative to the edge's own translation, expressed in the source chunk's
    units), ``std(ω) = sigma_rot`` rad, ``std(σ) = sigma_scale``.  ``relative`` is ``[E, 8]``.
    """
    Z = jnp.asarray(relative)
    rho = sigma_trans * jnp.linalg.norm(sim3.translation(Z), axis=-1) / sim3.scale(Z)
    rho = jnp.maximum(rho, jnp.finfo(Z.dtype).tiny)
    ones = jnp.ones_like(rho)
    var = jnp.stack([rho, rho, rho] + [sigma_rot * ones] * 3 + [sigma_scale * ones], -1) ** 2
    return var[..., :, None] * jnp.eye(7, dtype=Z.dtype)


@jax.jit
def loop_covariance(
    Z: Float[ArrayLike, "*batch 8"], sigma_rot: float | Float[ArrayLike, ""],
    sigma_trans: float | Float[ArrayLike, ""], sigma_scale: float | Float[ArrayLike, ""],
) -> Float[Array, "*batch 7 7"]:
    """Covariance ``[M, 7, 7]`` of loop edges ``Z [M, 8]``: ``std(ρ) = sigma_trans`` in the
    source chunk's units (VGGT normalises each chunk's scene scale), ``sigma_rot``, ``sigma_scale``."""
    Z = jnp.asarray(Z)
    ones = jnp.ones(Z.shape[:-1], Z.dtype)
    var = jnp.stack([sigma_trans * ones] * 3 + [sigma_rot * ones] * 3 + [sigma_scale * ones], -1) ** 2
    return var[..., :, None] * jnp.eye(7, dtype=Z.dtype)


@jax.jit
def pairwise_consistency(
    chain_poses: Float[ArrayLike, "T 8"],
    odometry_cov: Float[ArrayLike, "T-1 7 7"],
    loop_nodes: Int[ArrayLike, "M 2"],
    Z: Float[ArrayLike, "M 8"],
    loop_cov: Float[ArrayLike, "M 7 7"],
) -> Float[Array, "M M"]:
    """Whitened cycle residuals ``m_ab`` of every pair of loop edges (PCM): ``[M, M]``.

    Args:
        chain_poses: ``[T, 8]`` dead-reckoning chunk-to-world poses ``X_t`` (chained
            temporal edges, ``X_{t+1} = X_t Z_{t→t+1}``).
        odometry_cov: ``[T-1, 7, 7]`` covariance of each temporal edge's right perturbation.
        loop_nodes: ``[M, 2]`` int ``(p, q)``, ``p < q``: loop edge ``p → q``, ``Z ≈ S_p⁻¹ S_q``.
        Z: ``[M, 8]`` loop measurements.
        loop_cov: ``[M, 7, 7]`` covariance of each loop edge's right perturbation.

    Returns:
        ``[M, M]`` symmetric, zero diagonal; ``m_ab = sqrt(rᵀ Σ_ab⁻¹ r)``, ``r = log(D_a⁻¹ D_b)``
        (module docstring).  Run it in float64 (``jax.enable_x64``) for long sequences: the
        world-frame covariances carry lever arms of the route's size.  Recompiles per
        ``(T, M)`` and dtype.
    """
    X = jnp.asarray(chain_poses)
    dt = X.dtype
    Z = jnp.asarray(Z, dt)
    p, q = jnp.asarray(loop_nodes)[:, 0], jnp.asarray(loop_nodes)[:, 1]
    Ad = sim3.adjoint(X)  # [T, 7, 7]
    C = Ad[1:] @ jnp.asarray(odometry_cov, dt) @ jnp.swapaxes(Ad[1:], -1, -2)
    P = jnp.concatenate([jnp.zeros((1, 7, 7), dt), jnp.cumsum(C, axis=0)])  # [T, 7, 7]
    D = sim3.compose(sim3.compose(X[p], Z), sim3.inverse(X[q]))  # [M, 8]
    Aq = Ad[q]
    L = Aq @ jnp.asarray(loop_cov, dt) @ jnp.swapaxes(Aq, -1, -2)  # [M, 7, 7]
    span = P[q] - P[p]
    lo = jnp.maximum(p[:, None], p[None, :])
    hi = jnp.minimum(q[:, None], q[None, :])
    inter = jnp.where((hi > lo)[..., None, None], P[jnp.maximum(hi, lo)] - P[lo], 0)
    cov = span[:, None] + span[None, :] - 2 * inter + L[:, None] + L[None, :]  # [M, M, 7, 7]
    E = sim3.compose(sim3.inverse(D)[:, None], D[None, :])  # [M, M, 8]
    r = sim3.log(E)
    eye = jnp.eye(r.shape[0], dtype=bool)
    cov = jnp.where(eye[..., None, None], jnp.eye(7, dtype=dt), cov)
    m2 = jnp.einsum("abi,abi->ab", r, jnp.linalg.solve(cov, r[..., None])[..., 0])
    m = jnp.sqrt(jnp.maximum(m2, 0))
    m = jnp.where(jnp.isfinite(m), m, jnp.inf)
    return jnp.where(eye, 0, 0.5 * (m + m.T))


def max_consistent_set(
    consistent: Bool[ArrayLike, "M M"], weights: Sequence[float] | Float[ArrayLike, " M"] | None = None
) -> list[int]:
    """A maximum clique of the boolean consistency graph ``consistent [M, M]`` (host).

    Exact: Bron–Kerbosch with pivoting (Tomita et al. 2006), exponential in the worst case
    but instant for the tens of candidates of a sequence.  Among cliques of the maximum size
    the one with the largest sum of ``weights`` wins (then the lexicographically smallest).
    The diagonal is ignored; an empty graph gives ``[]``.
    """
    A = np.asarray(consistent, bool)
    m = A.shape[0]
    if A.shape != (m, m):
        raise ValueError(f"max_consistent_set: consistent must be square, got {A.shape}")
    A = A & A.T & ~np.eye(m, dtype=bool)
    w = np.zeros(m) if weights is None else np.asarray(weights, np.float64)
    nbrs = [set(np.flatnonzero(A[k]).tolist()) for k in range(m)]
    best: list[Any] = [(-1, -np.inf), []]

    def expand(R: list[int], P: set[int], X: set[int]) -> None:
        if not P and not X:
            key = (len(R), float(w[R].sum()) if R else 0.0)
            if key > best[0] or (key == best[0] and sorted(R) < best[1]):
                best[0], best[1] = key, sorted(R)
            return
        if len(R) + len(P) < best[0][0]:
            return  # cannot reach the best size
        pivot = max(P | X, key=lambda u: len(P & nbrs[u]))
        for v in sorted(P - nbrs[pivot]):
            expand(R + [v], P & nbrs[v], X & nbrs[v])
            P = P - {v}
            X = X | {v}

    if m:
        expand([], set(range(m)), set())
    return best[1]


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
        return (f"the temporal chunks do not see each other under the edge: overlap {overlap:.3f} "
                f"< {config.min_overlap}")
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
    (:class:`LoopQuality`).  The rule, in order: a non-finite ``Z``, an invalid or thin
    loop-chunk alignment, no overlap or disagreeing depths reject the candidate; the
    survivors (two or more) go through PCM and only a maximum consistent set is kept (ties:
    larger total ``dense_agreement``).

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
    for k, r in enumerate(records):
        Z = np.asarray(r["Z"], np.float64)
        fraction = float(r.get("quality_min_fraction", 0.0))
        if Z.shape != (8,) or not np.all(np.isfinite(Z)):
            out[k] = Decision(False, "loop edge is not finite")
        elif not r.get("quality_valid", False):
            out[k] = Decision(False, "loop chunk alignment invalid (pose fallback)")
        elif not fraction >= config.min_fraction:
            out[k] = Decision(
                False, f"loop chunk alignment thin: {fraction:.3f} of the overlap reliable < {config.min_fraction}"
            )
        elif (why := _dense_reason(r, config)) is not None:
            out[k] = Decision(False, why)
        else:
            alive.append(k)
    if not (config.pcm and len(alive) >= 2):
        for k in alive:
            out[k] = Decision(True, "verified")
        return out
    nodes, Zs = [], []
    for k in alive:  # each loop as the edge p -> q with p < q, Z ~ S_p^-1 S_q
        ci, cj = int(records[k]["chunk_i"]), int(records[k]["chunk_j"])
        Z = np.asarray(records[k]["Z"], np.float64)  # maps c_i into c_j: edge c_j -> c_i
        if cj > ci:
            with jax.enable_x64(True):
                Z = np.asarray(sim3.inverse(jnp.asarray(Z)))
        nodes.append((min(ci, cj), max(ci, cj)))
        Zs.append(Z)
    # padded to a power of two (>= 8) so that one compile serves many candidate counts
    n = len(alive)
    size = max(8, 1 << (n - 1).bit_length())
    nodes += [(0, 1)] * (size - n)
    Zs += [np.array([0, 0, 0, 0, 0, 0, 1, 1.0])] * (size - n)
    with jax.enable_x64(True):
        Zj = jnp.asarray(np.stack(Zs))
        odo = odometry_covariance(
            jnp.asarray(relative, jnp.float64), config.odo_sigma_rot, config.odo_sigma_trans,
            config.odo_sigma_scale,
        )
        lc = loop_covariance(Zj, config.loop_sigma_rot, config.loop_sigma_trans, config.loop_sigma_scale)
        m = np.asarray(pairwise_consistency(
            jnp.asarray(chain_poses, jnp.float64), odo, jnp.asarray(nodes, jnp.int32), Zj, lc
        ))[:n, :n]
    clique = set(max_consistent_set(
        m <= config.pcm_threshold, [float(records[k]["dense_agreement"]) for k in alive]
    ))
    for a, k in enumerate(alive):
        worst = float(np.max(m[a])) if len(alive) > 1 else 0.0
        if a in clique:
            out[k] = Decision(True, f"verified; pairwise consistent with {len(clique) - 1} other loop(s)", worst)
        else:
            bad = max(float(m[a, b]) for b in clique) if clique else math.inf
            out[k] = Decision(
                False, f"pairwise inconsistent with the {len(clique)} accepted loop(s): whitened cycle "
                f"residual {bad:.1f} > {config.pcm_threshold}", worst,
            )
    return out

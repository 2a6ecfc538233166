"""Cross-chunk dense consistency of a loop candidate: do the temporal chunks agree across the loop?

A candidate edge ``Z`` maps chunk ``c_i`` coordinates into chunk ``c_j``'s
(:func:`swiftjax.loops.loop_edge`).  The temporal chunks' *own* predictions around both ends
(not the loop chunk's) must agree under ``Z``, like eq. 2 across the loop
(:func:`dense_consistency`, :func:`cross_chunk_consistency`).  Reliable points of the ``c_i`` frames
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

Pure and jit-compiled with static shapes (masks, never boolean indexing);
:func:`cross_chunk_consistency` is batched over candidates with ``vmap`` and loops with
``lax.scan`` over the neighbour ranks: pass ``r`` takes every source frame's ``r``-th nearest
target frame (its extrinsic and depth map gathered per frame), so a token candidate's test
does ``neighbours`` passes over its points, not one per target frame with the other pairs
masked out (identical counts; for 20 frames a side 5.4x faster, its null 6.8x:
``python bench/bench_kernels.py``).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import ArrayLike, Float

from swiftjax import align, camera, sim3
from swiftjax._compile import LIGHT_COMPILE, quick_jit, to_device
from swiftjax._products import small_matmul
from swiftjax.loops.options import VerificationConfig

__all__ = ["ConsistencyInfo", "dense_consistency", "CrossCheck", "cross_chunk_consistency", "compile_cross_chunk"]

_DEFAULTS = VerificationConfig()
_ALIGN = align.AlignOptions()  # conf_ratio: λ_γ, the alignment's (eq. 2)


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
    ok = jnp.isfinite(d) & (d > 0) & jnp.isfinite(frames.conf) & (frames.conf > conf_ratio * mean[:, None, None])
    return jnp.where(ok, d, jnp.nan)


def _dense_consistency(
    src, dst, S, K_ref, conf_ratio, depth_tolerance, stride: int, neighbours: int
) -> ConsistencyInfo:
    dtype = src.depth.dtype
    K_ref = K_ref.astype(dtype)
    F = src.depth.shape[0]
    G, h, w = dst.depth.shape
    # source points on the stride grid, in source chunk coordinates, then mapped by S
    d_src = _normalised(src, K_ref, conf_ratio)[:, ::stride, ::stride]  # [F, h', w']
    rays = camera.pixel_rays(K_ref, h, w)[::stride, ::stride]  # [h', w', 3]
    c2w = camera.camera_to_world(src.extrinsic)  # [F, 3, 4]
    cam = d_src[..., None] * rays  # NaN where unreliable
    x = small_matmul(cam, jnp.swapaxes(c2w[:, :, :3], -1, -2)[:, None, None]) + c2w[:, None, None, :, 3]
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
    if 0 < neighbours < G:  # rank r's target of each source frame (stable: ties by index)
        targets = jnp.argsort(dist, axis=1)[:, :neighbours].T  # [neighbours, F]
    else:
        targets = jnp.broadcast_to(jnp.arange(G)[:, None], (G, F))  # every target frame
    d_dst = _normalised(dst, K_ref, conf_ratio).reshape(G, -1)  # [G, H W]
    dst_E = dst.extrinsic.astype(dtype)
    fx, fy, cx, cy, sk = K_ref[0, 0], K_ref[1, 1], K_ref[0, 2], K_ref[1, 2], K_ref[0, 1]
    tol = jnp.asarray(depth_tolerance, dtype)
    y, ok = y.reshape(F, n_per, 3), ok.reshape(F, n_per)

    # One pass per rank: every source frame's points against that frame's target of the rank
    # (its own extrinsic and depth map, gathered), not one pass per target frame over every
    # point with the other frames masked out (G / neighbours times the work: 20 / 3 for a
    # token candidate).  The same (point, target) pairs either way, so the same counts.
    def step(carry, g):
        seen, agree, n_seen, n_agree, n_front = carry
        E = dst_E[g]  # [F, 3, 4]
        p = small_matmul(y, jnp.swapaxes(E[:, :, :3], -1, -2)[:, None]) + E[:, None, :, 3]  # y Rᵀ + t
        z = p[..., 2]
        use = ok & (z > 0)
        zs = jnp.where(use, z, 1)
        u = jnp.round(fx * p[..., 0] / zs + sk * p[..., 1] / zs + cx)
        v = jnp.round(fy * p[..., 1] / zs + cy)
        inside = use & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        idx = jnp.where(inside, v * w + u, 0).astype(jnp.int32)
        D = d_dst[g[:, None], idx]  # [F, n_per]
        view = inside & jnp.isfinite(D)
        good = view & (jnp.abs(z - D) <= tol * D)
        front = view & (z < (1 - tol) * D)
        count = lambda m: jnp.sum(m, dtype=jnp.int32)
        return (seen | view, agree | good, n_seen + count(view), n_agree + count(good), n_front + count(front)), None

    zero = jnp.zeros((), jnp.int32)
    init = (jnp.zeros((F, n_per), bool), jnp.zeros((F, n_per), bool), zero, zero, zero)
    (seen, agree, n_seen, n_agree, n_front), _ = lax.scan(step, init, targets)
    num = jnp.sum(ok).astype(jnp.int32)
    num_seen = jnp.sum(seen).astype(jnp.int32)
    num_agree = jnp.sum(agree).astype(jnp.int32)
    ratio = lambda a, b: jnp.where(b > 0, a.astype(dtype) / jnp.maximum(b, 1).astype(dtype), 0)
    return ConsistencyInfo(
        num_points=num,
        num_seen=num_seen,
        num_agree=num_agree,
        pairs_seen=n_seen,
        pairs_agree=n_agree,
        pairs_front=n_front,
        overlap=ratio(num_seen, num),
        agreement=ratio(n_agree, n_seen),
        consistency=ratio(num_agree, num),
    )


def _frames(x, dtype=None) -> align.ChunkFrames:
    """``x``'s arrays on the device in ``dtype`` (None: the depth's float dtype, float32 for
    another), converted on the host (an eager ``astype`` or ``jnp.asarray`` compiles per shape)."""
    if dtype is None:
        dtype = jax.dtypes.canonicalize_dtype(x.depth.dtype)
        dtype = dtype if dtype in (jnp.float32, jnp.float64) else jnp.float32
    return align.ChunkFrames(*(to_device(getattr(x, k), dtype) for k in align.ChunkFrames._fields))


@functools.partial(jax.jit, static_argnames=("stride", "neighbours"))
def _dense_consistency_jit(src, dst, S, K_ref, conf_ratio, depth_tolerance, stride, neighbours):
    return _dense_consistency(src, dst, S, K_ref, conf_ratio, depth_tolerance, stride, neighbours)


def _traced_args(src, dst, S, K_ref, conf_ratio: float, config: VerificationConfig) -> tuple:
    """The jitted programs' arguments: frames and numbers in the source's float dtype, then the
    static ``stride`` and ``neighbours``."""
    src = _frames(src)
    dt = src.depth.dtype
    dst = _frames(dst, dt)
    return (
        src,
        dst,
        to_device(S, dt),
        to_device(K_ref, dt),
        to_device(conf_ratio, dt),
        to_device(config.depth_tolerance, dt),
        config.stride,
        config.neighbours,
    )


def dense_consistency(
    src: align.ChunkFrames,
    dst: align.ChunkFrames,
    S_dst_src: Float[ArrayLike, 8],
    K_ref: Float[ArrayLike, "3 3"],
    config: VerificationConfig | None = None,
    *,
    conf_ratio: float = _ALIGN.conf_ratio,
) -> ConsistencyInfo:
    """How many reliable points of ``src`` land on agreeing depth in ``dst`` under ``S``.

    Args:
        src: :class:`~swiftjax.align.ChunkFrames` ``depth, conf [F, H, W]``, ``intrinsic
            [F, 3, 3]``, ``extrinsic [F, 3, 4]`` (world-to-camera in the source chunk).
        dst: the same for ``G`` frames of the target chunk (same ``H, W``).
        S_dst_src: Sim(3) ``[8]`` mapping source chunk coordinates into target chunk
            coordinates (for a loop edge ``Z`` from c_i's frames into c_j's: ``Z``).
        K_ref: ``[3, 3]`` reference intrinsics (both chunks' depths are normalised to it).
        config: :class:`~swiftjax.loops.options.VerificationConfig` (default
            ``VerificationConfig()``); the test reads three of its fields:

            * ``stride``: static source pixel subsampling (``F · ceil(H/stride) ·
              ceil(W/stride)`` points; the targets are looked up at full resolution, nearest
              pixel);
            * ``neighbours``: static; each source frame is compared with this many target
              frames, those whose cameras are nearest to its camera mapped by ``S`` (0: all);
            * ``depth_tolerance``: relative depth agreement ``τ``.
        conf_ratio: ``λ_γ``, as eq. 2 (both sides; default the alignment's,
            ``AlignOptions().conf_ratio``).

    Returns:
        :class:`ConsistencyInfo` (module docstring for the equations).  A non-finite ``S``
        or input pixel never counts as agreeing (the point or pixel is dropped).

    One jitted call; recompiles per ``(F, G, H, W)``, dtype (float32 for float16 input),
    ``stride`` and ``neighbours``; the other options are traced.  Cost: ``neighbours`` passes
    (``G`` when every frame) over the ``P`` source points (``lax.scan``), each a projection and
    one gather.
    """
    config = _DEFAULTS if config is None else config
    return _dense_consistency_jit(*_traced_args(src, dst, S_dst_src, K_ref, conf_ratio, config))


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


@quick_jit(options=LIGHT_COMPILE, static_argnames=("stride", "neighbours"))
def _cross_jit(side_i, side_j, Z, K_ref, conf_ratio, depth_tolerance, stride, neighbours):
    def one(fi, fj, z):
        a = _dense_consistency(fi, fj, z, K_ref, conf_ratio, depth_tolerance, stride, neighbours)
        b = _dense_consistency(fj, fi, sim3.inverse(z), K_ref, conf_ratio, depth_tolerance, stride, neighbours)
        return CrossCheck(a, b, jnp.minimum(a.agreement, b.agreement))

    return jax.vmap(one)(side_i, side_j, Z)


def traced_specs(side_i, side_j, Z, K_ref, conf_ratio: float, config: VerificationConfig) -> tuple:
    """The jitted programs' arguments (``_traced_args``) as ``jax.ShapeDtypeStruct``s, for
    arguments given as ``jax.ShapeDtypeStruct``s: what an ahead-of-time compile traces on."""
    arrays = jax.eval_shape(lambda *a: _traced_args(*a, conf_ratio, config)[:6], side_i, side_j, Z, K_ref)
    return (*arrays, config.stride, config.neighbours)


def compile_cross_chunk(
    side_i, side_j, Z, K_ref, config: VerificationConfig | None = None, *, conf_ratio: float = _ALIGN.conf_ratio
) -> None:
    """Compile :func:`cross_chunk_consistency`'s program ahead of time for arguments of these
    shapes (``jax.ShapeDtypeStruct``s or arrays); its calls with such arguments then find it
    compiled."""
    config = _DEFAULTS if config is None else config
    _cross_jit.trace(*traced_specs(side_i, side_j, Z, K_ref, conf_ratio, config)).lower().compile()


def cross_chunk_consistency(
    side_i: align.ChunkFrames,
    side_j: align.ChunkFrames,
    Z: Float[ArrayLike, "M 8"],
    K_ref: Float[ArrayLike, "3 3"],
    config: VerificationConfig | None = None,
    *,
    conf_ratio: float = _ALIGN.conf_ratio,
) -> CrossCheck:
    """Both directions of :func:`dense_consistency` for ``M`` loop candidates at once (vmap).

    Args:
        side_i: frames of temporal chunk ``c_i`` around ``i`` with a leading candidate axis
            (``depth, conf [M, F, H, W]``, ``intrinsic [M, F, 3, 3]``, ``extrinsic [M, F, 3, 4]``);
            in the pipeline the ``2h`` frames the loop chunk's first half overlaps.
        side_j: the same for chunk ``c_j`` around ``j``.
        Z: ``[M, 8]`` loop edges mapping ``c_i`` into ``c_j`` (:func:`swiftjax.loops.loop_edge`).
        K_ref, config, conf_ratio: as :func:`dense_consistency`.

    Returns:
        :class:`CrossCheck` with ``[M]`` fields.  Recompiles per ``(M, F, H, W)``, dtype,
        ``stride`` and ``neighbours``.
    """
    config = _DEFAULTS if config is None else config
    return _cross_jit(*_traced_args(side_i, side_j, Z, K_ref, conf_ratio, config))

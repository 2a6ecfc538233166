"""Place recognition and loop edges from the dense geometry, whichever way the revisit is driven.

A forward camera's DINO descriptor (:mod:`swiftjax.loops.descriptors`) cannot match a street
seen from its other end; the chunks' own reliable points can.  Each chunk's points are
summarised in a bird's-eye polar grid that does not depend on the direction of travel (Scan
Context, Kim & Kim 2018, on a VGGT chunk instead of a lidar sweep); chunk pairs far apart in
time whose grids match are registered (Sim(3) ICP, scale included).  Why several starts, the
measured limits and the failure modes: docs/design.md, "Geometric loop candidates".

**Gravity frame** (:func:`chunk_frame`).  With camera-to-chunk rotations ``R_f`` and centres
``c_f`` of the chunk's frames (OpenCV: the camera's y axis points down)::

    u = −normalize(Σ_f R_f e_y),   e1 = normalize((I − u uᵀ) Σ_f R_f e_z),   e2 = u × e1,   B = [e1 e2 u]

``h`` = median ``y`` of the camera-frame road points (below the horizon, lower central band):
the unit of length, which removes the chunk's arbitrary scale.  Around each of ``A`` anchors
``a`` (camera centres spread over the chunk) a point ``x`` becomes::

    q = Bᵀ (x − a) / h,   ρ = |q_xy|,   θ = atan2(q_y, q_x) mod 2π,   z = q_z + 1

**Polar grid** (:func:`polar_grid`): ``N_r`` rings of width ``ρ_max / N_r`` times ``N_s``
sectors of ``2π / N_s``; cell ``(r, k)`` holds ``max(0, min(z, z_max))`` over its reliable
points (0 when empty, like the road).  A rotation about ``u`` by ``m`` sectors rolls the grid,
``G'[:, k] = G[:, k − m]``, so the signature ``σ = vec|F| / ‖vec|F|‖`` with
``F_r(ω) = Σ_k G[r, k] e^{−2πiωk/N_s}`` is heading-free (shift theorem), scale-free (units of
``h``) and translation-free (around the anchor).

**Matching** (:func:`signature_distances`, :func:`scan_context_distance`)::

    d_σ(a, b) = min over anchor pairs (1 − σ_a · σ_b)
    d_SC(m) = mean over non-empty columns k of (1 − cos(G_a[:, k], G_b[:, k + m])),
    m* = argmin d_SC(m),   ψ = m* 2π / N_s
    s₀ = h_b / h_a,   R₀ = B_b R_z(ψ) B_aᵀ,   t₀ = a_b − s₀ R₀ a_a          (the coarse edge)

**Registration** (:func:`register`): ``n`` iterations of robust ICP on fixed-size subsamples
(brute-force nearest neighbours, Tukey weights ``w_p = (1 − (r_p/τ_k)²)²`` for ``r_p < τ_k``,
``τ_k`` shrinking geometrically from ``τ_0`` to ``τ_n`` in camera heights, one weighted
:func:`swiftjax.align.umeyama` per iteration).  Verdict on the last iteration: the inlier
ratio among points above the road (``z > z_ground``), the inliers' ``rms``, ``s / s₀`` (≈ 1)
and the structure's spread ``λ₂ / λ₁`` (horizontal covariance of the inlying structure).
:func:`coarse_hypotheses` / :func:`register_hypotheses` start from every anchor pair at its
yaw and yaw + π (``2 A²`` starts, ``vmap``) with a gravity-aligned ICP that solves only yaw and
translation::

    θ = atan2(Σ w u·(a × b), Σ w a·b),   a, b: horizontal parts of the centred pairs

**Co-visible chunk pairs** (:func:`register_covisible`; the pipeline runs its steps batched).  A reverse
revisit's chunks at the same place look away from each other; the pairs that share structure
are the ones facing each other across a stretch, and the odometry chain's prior between them is
good in yaw (≤ 2° on synthetic KITTI 08) but 8–30 camera heights off in translation.  With
the prior ``(ψ, σ, τ)`` (:func:`edge_prior`, normalised frames ``q = Bᵀ(x − o)/h``), both
structure clouds are rasterised (:func:`bev_raster`) and correlated by FFT over translations
for a few yaws ``ψ ± yaw_search`` and scales ``σ e^{±scale_search}``; the ``peaks`` best
translations within ``window`` of ``τ`` (:func:`bev_starts`) are refined by the Sim(3) ICP
(:func:`peak_icp`) and scored by their structure inliers ``n_k``.  Verdict
(:func:`covisible_reason`): the best ``n`` above the null's bound ``θ`` (the same source
registered onto unrelated chunks, :func:`swiftjax.loops.null.null_threshold`), then the best
placement refined on all points (:func:`refine_placement`): scale ratio, structure, residual.
Between the two, a candidate above ``θ`` is also searched along the street
(:func:`slide_starts`, ``slide_steps``): the bird's-eye correlation of a street seen from its
two ends peaks where the most structure overlaps, not where it belongs, and its peaks are kept
``peak_separation`` apart, so the true placement can lie between two peaks, in the basin of
neither.  The peak ICP runs again from the best placement shifted along the target's heading
by ``±k peak_separation / 2`` (``k = 1 … slide_steps``); the starts' best placement replaces
the weakest peak when it scores more than the best peak, or when it is plausible and lands in a
basin none of the placements is in, and the refinement keeps whichever of it and the best has
more structure inliers on all points, a refinement that passes the refined tests (scale,
structure, residual) before one that fails them
(:func:`swiftjax.pipeline.loop_geometry._slide_search`, ``_outranks``).
(Synthetic KITTI 08, world 2: 36/4 and 37/3 placed 7.4 and 9.9 m off the truth by their best
peaks, 45 and 44 structure inliers; from the truth the same ICP scores 50 and 48, refined 411
and 412 against the slid placements' 296 and 312.)

**Colour** (``GeometryOptions.colour_tolerance``).  Each point carries its pixel's
chromaticity ``c = (rgb + 1) / (r + g + b + 3)`` (:func:`chromaticity`: brightness, so distance
shading and exposure, divided out); in the placements' and the refinement's ICP a nearest
neighbour of another paint, ``max_c |c_p − c_{k(p)}| > colour_tolerance``, is no match
(:func:`register`).  A placement on an unrelated street keeps geometric neighbours but few of
the same paint, so the structure score separates true from null placements far better
(synthetic KITTI 08, refined placements: true 0.9–0.99 of the geometric inliers keep their
paint, null samples 0.0–0.5); a slide along a street that crosses a change of paint loses the
points that moved onto the other block.  The test only removes matches: it adds no pull along
the street (a same-paint neighbour is the nearest one within a block).  Chunks stored without
images get mid grey everywhere: every pair agrees, the geometry alone decides.

**A street slid along itself** is a 1-D degeneracy, not a wrong answer: several placements
``P = {k : n_k > θ}`` (each explained by no unrelated chunk) lie along the street.  Instead
of rejecting the edge, the pose graph gets their mean and spread (:func:`placement_moments`,
the Gaussian closest to "any plausible placement alike")::

    δ_k = log(S_best⁻¹ S_k),   δ̄ = mean_{k ∈ P} δ_k,   Σ_P = mean_{k ∈ P} (δ_k − δ̄)(δ_k − δ̄)ᵀ,
    Z = S_best exp(δ̄),   Ω = (Ω_reg⁻¹ + Σ_P)⁻¹

(``Ω_reg``: the registration's own information from its residuals,
:func:`swiftjax.align.covariance.umeyama_information`).  ``Σ_P`` is large along the slide and
zero across it, in yaw and in scale: the loop edge constrains only the well-determined
directions.  Every registration edge also carries both chunks' own model error over their
extents, ``Σ_W`` (:func:`warp_covariance`, the temporal edges' drift model over a chunk's
length), which its residuals cannot see: ``Ω = (Ω_reg⁻¹ + Σ_P + Σ_W)⁻¹``.  **Structure on
one line** (a straight street: ``spread = λ₂ / λ₁ < min_spread``) maps onto itself under a
slide along the line and a scaling about a point of it, which point-to-point residuals cannot
see either; such an edge is kept, its covariance widened by ``Σ_L`` over those two directions
(:func:`straight_covariance`: the slide over the structure's own length, the scale over the
searched range), ``Ω = (Ω_reg⁻¹ + Σ_P + Σ_W + Σ_L)⁻¹``, the other five directions kept.
Nothing is read off a route: ``θ`` comes from the null at ``null_false_alarm``, ``Σ_W`` from
the drift model, ``Σ_L`` from the structure and the search range.

**Joint registration** (``GeometryOptions.neighbours = k``, :func:`merge_neighbours`): each
chunk's cloud joined with its ``k`` neighbours' on each side, placed by the odometry chain's
relative Sim(3) ``G_c⁻¹ G_n`` (the temporal alignment's own edges), rows interleaved; the
placement, null and refinement then use ``(2k + 1)`` times the rows (the same density over a
stretch ``2k + 1`` chunks long).  Over three chunks a reverse pass shares a longer, bent
stretch of structure with the other, which breaks the slide along the street and lifts the
right placement above the null (synthetic KITTI 08: all three reverse regions instead of
two); the nearest-neighbour passes grow ``(2k + 1)²``-fold.

**Cost** (the pipeline, :mod:`swiftjax.pipeline.loop_geometry`): each chunk's structure cloud
and bird's-eye spectrum once (:func:`bev_spectrum`); fixed-size ``vmap`` batches of jobs
(:func:`starts_batch`, :func:`peaks_batch`, :func:`refine_batch`), one compile per (chunk
count, options); one null per source chunk, stopped early where exact; the refinement and the
dense test only above the null.  The ICP's nearest-neighbour pass (:func:`_nearest`, most of
its time) is one distance pass that keeps each block's minimum, the index then searched in one
block (bitwise ``argmin``'s); the refinement's scale sweep runs its passes one scale at a time
(each pass's distances are materialised by XLA:CPU).  The pipeline runs two placement batches
at a time (:data:`swiftjax.pipeline.loop_geometry.PLACEMENT_WORKERS`).  A job whose window
holds no translation of the bird's-eye grid (:func:`window_on_grid`) is not run at all.  Where
the time goes on synthetic KITTI 00 (1,002 gated candidates, 395 of them beyond the grid, 91
closed by a token loop; ~290 null jobs): the peak ICP of the ~740 jobs whose peaks overlap a
cell, the bird's-eye starts (FFTs) of ~800 jobs, the clouds, the refinements and dense tests
above the null; the numbers are in docs/performance/reverse-revisits.md.

Failure modes: a chain more than ``max_window`` off, chunks of very different structure
density (the null's spread grows), reverse views of little shared structure (the structure
count stays within the null's spread: most reverse pairs on synthetic KITTI 08).

Pure, jit-compiled, static shapes, ``vmap`` over chunks; one compile per (frames per chunk,
image size, :class:`GeometryOptions`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Bool, Complex, Float, Int, Key, UInt8, UInt32

from swiftjax import align, camera, sim3, so3
from swiftjax._products import small_matmul
from swiftjax._select import nanmedian
from swiftjax.align.mask import frame_conf_mean
from swiftjax.loops.options import GeometryOptions

__all__ = [
    "GeometryOptions",
    "ChunkGeometry",
    "chunk_frame",
    "polar_grid",
    "grid_signature",
    "ChunkDescriptors",
    "chunk_descriptors",
    "signature_distances",
    "scan_context_distance",
    "coarse_edge",
    "Registration",
    "register",
    "subsample",
    "path_weights",
    "coarse_hypotheses",
    "register_hypotheses",
    "ChunkCloud",
    "structure_cloud",
    "neighbour_offsets",
    "merge_neighbours",
    "edge_prior",
    "bev_raster",
    "bev_spectrum",
    "bev_starts",
    "window_on_grid",
    "Placements",
    "peak_icp",
    "place_covisible",
    "starts_batch",
    "peaks_batch",
    "scale_sweep",
    "refine_placement",
    "refine_batch",
    "placement_moments",
    "warp_covariance",
    "straight_covariance",
    "Covisible",
    "register_covisible",
    "covisible_reason",
]


# ----------------------------------------------------------------------- per chunk


class ChunkGeometry(NamedTuple):
    """A chunk's reliable points and gravity frame (batch axes ``[...]`` in front).

    Attributes:
        points: ``[..., N, 3]`` reliable points in the chunk's coordinates (0 where unused).
        weights: ``[..., N]`` 1 for a reliable point, else 0.
        anchors: ``[..., A, 3]`` anchor positions (camera centres).
        basis: ``[..., 3, 3]`` columns ``e1, e2, u`` (``u`` up).
        height: ``[...]`` the camera height ``h`` (chunk units; NaN when no road was seen).
        anchor_frames: ``[..., A]`` int32 positions of the anchors among the loaded frames.
        colours: ``[..., N, 3]`` the points' chromaticity (:func:`chromaticity`), or None when
            the chunk's images were not given (colour then never rejects a match).
    """

    points: Array
    weights: Array
    anchors: Array
    basis: Array
    height: Array
    anchor_frames: Array
    colours: Array | None = None


def chunk_frame(
    frames: align.ChunkFrames,
    K_ref: Float[ArrayLike, "3 3"],
    options: GeometryOptions,
    images: UInt8[ArrayLike, "F H W 3"] | None = None,
) -> ChunkGeometry:
    """:class:`ChunkGeometry` of one chunk's frames ``[F, H, W]`` (module docstring).

    Depths are normalised to ``K_ref`` (eq. 1) and unprojected through each frame's pose; a
    pixel is reliable when its depth is finite and positive and its confidence exceeds
    ``conf_ratio`` times its frame's mean.  ``images`` (the frames' RGB ``[F, H, W, 3]``, or
    already at the sampled pixels): each point's :func:`chromaticity`.  Pure; jit it (or use
    :func:`chunk_descriptors`).
    """
    depth = jnp.asarray(frames.depth, jnp.float32)
    conf = jnp.asarray(frames.conf, jnp.float32)
    K_ref = jnp.asarray(K_ref, jnp.float32)
    sv, su = options.pixel_stride
    sub = (slice(None), slice(None, None, sv), slice(None, None, su))
    Ks = jnp.diag(jnp.array([1.0 / su, 1.0 / sv, 1.0], jnp.float32)) @ K_ref
    d = camera.normalize_depth(depth[sub], jnp.asarray(frames.intrinsic, jnp.float32), K_ref)
    cam_pts = camera.unproject(d, Ks)  # [F, h, w, 3] camera frame
    c2w = camera.camera_to_world(jnp.asarray(frames.extrinsic, jnp.float32))  # [F, 3, 4]
    R, c = c2w[..., :3], c2w[..., 3]
    pts = small_matmul(cam_pts, jnp.swapaxes(R, -1, -2)[:, None, None]) + c[:, None, None, :]
    cf = conf[sub]
    mean = frame_conf_mean(conf)
    ok = (
        jnp.isfinite(d)
        & (d > 0)
        & jnp.isfinite(cf)
        & (cf > options.conf_ratio * mean[:, None, None])
        & jnp.all(jnp.isfinite(pts), -1)
    )
    # gravity and heading from the camera path
    up = -jnp.sum(R[..., 1], 0)
    up = up / jnp.maximum(jnp.linalg.norm(up), 1e-12)
    fwd = jnp.sum(R[..., 2], 0)
    fwd = fwd - jnp.dot(fwd, up) * up
    e1 = fwd / jnp.maximum(jnp.linalg.norm(fwd), 1e-12)
    basis = jnp.stack([e1, jnp.cross(up, e1), up], -1)
    # camera height: road points straight ahead, lower central band of the image
    h, w = d.shape[-2:]
    v = jnp.arange(h, dtype=jnp.float32)[:, None] * sv
    u = jnp.arange(w, dtype=jnp.float32)[None, :] * su
    H, W = depth.shape[-2:]
    cy, cx = K_ref[1, 2], K_ref[0, 2]
    band = (v > cy + 0.5 * (H - cy)) & (jnp.abs(u - cx) < W / 6.0)
    ys = jnp.where(ok & band[None], cam_pts[..., 1], jnp.nan)
    height = nanmedian(ys)  # jnp.nanmedian's value, counted instead of sorted
    F = depth.shape[0]
    idx = jnp.asarray(np.round(np.linspace(0, F - 1, options.anchors)).astype(np.int32))
    return ChunkGeometry(
        points=jnp.where(ok[..., None], pts, 0.0).reshape(-1, 3),
        weights=ok.reshape(-1).astype(jnp.float32),
        anchors=c[idx],
        basis=basis,
        height=jnp.where(height > 0, height, jnp.nan),
        anchor_frames=idx,
        colours=None if images is None else chromaticity(_sampled(jnp.asarray(images), d.shape, sub)).reshape(-1, 3),
    )


def _sampled(images: Array, shape: tuple[int, ...], sub: tuple[slice, ...]) -> Array:
    """``images`` at the sampled pixels: as given when already of the sampled ``shape``
    (:func:`swiftjax.pipeline.loop_geometry.stored_images`), else sliced by ``sub``."""
    return images if images.shape[:3] == tuple(shape) else images[sub]


def chromaticity(images: UInt8[ArrayLike, "*b 3"]) -> Float[Array, "*b 3"]:
    """``c = (rgb + 1) / (r + g + b + 3)``: the colour of a pixel with its brightness divided
    out (the ``+1`` keeps dark pixels finite and near grey).  A surface's chromaticity does not
    change with distance shading or exposure, which scale all three channels alike; two
    surfaces of different paint differ in it (the four facade paints of synthetic KITTI by
    0.033–0.106 in the largest channel).  ``[..., 3]`` float32, each row summing to 1."""
    rgb = jnp.asarray(images, jnp.float32) + 1.0
    return rgb / jnp.sum(rgb, -1, keepdims=True)


def _normalised(
    points: Float[Array, "N 3"], anchor: Float[Array, "3"], basis: Float[Array, "3 3"], height: Float[ArrayLike, ""]
) -> Float[Array, "N 3"]:
    """``q = Bᵀ (x − a) / h`` with ``z = q_z + 1``: ``[N, 3]`` (module docstring)."""
    q = (points - anchor) @ basis / height
    return q.at[:, 2].add(1.0)


def polar_grid(
    q: Float[ArrayLike, "N 3"],
    weights: Float[ArrayLike, " N"],
    rings: int,
    sectors: int,
    max_radius: float,
    max_height: float,
) -> tuple[Float[Array, "R S"], Int[Array, ""]]:
    """Scan Context grid of normalised points ``q`` (module docstring): ``([rings, sectors], count)``.

    Cell value ``max(0, min(z, max_height))`` over the points with ``weights > 0`` and ``ρ <
    max_radius`` falling in it (0 when empty); ``count``: int32 number of such points.  Pure;
    jit-able (``rings``, ``sectors`` static).
    """
    q = jnp.asarray(q, jnp.float32)
    rho = jnp.hypot(q[:, 0], q[:, 1])
    theta = jnp.mod(jnp.arctan2(q[:, 1], q[:, 0]), 2 * jnp.pi)
    ok = (jnp.asarray(weights) > 0) & (rho < max_radius) & jnp.all(jnp.isfinite(q), -1)
    ring = jnp.clip(jnp.floor(rho / max_radius * rings).astype(jnp.int32), 0, rings - 1)
    sector = jnp.clip(jnp.floor(theta / (2 * jnp.pi) * sectors).astype(jnp.int32), 0, sectors - 1)
    cell = jnp.where(ok, ring * sectors + sector, rings * sectors)  # the extra cell: unused points
    val = jnp.clip(jnp.where(ok, q[:, 2], 0.0), 0.0, max_height)
    grid = jax.ops.segment_max(val, cell, num_segments=rings * sectors + 1)[:-1]
    return jnp.maximum(grid, 0.0).reshape(rings, sectors), jnp.sum(ok).astype(jnp.int32)


def grid_signature(grid: Float[ArrayLike, "*b R S"]) -> Float[Array, "*b D"]:
    """The rotation-invariant signature ``vec|rfft_θ(G)| / ‖·‖``: ``[..., R, S] -> [..., R (S//2+1)]``."""
    g = jnp.asarray(grid)
    mag = jnp.abs(jnp.fft.rfft(g, axis=-1)).reshape(*g.shape[:-2], -1)
    n = jnp.linalg.norm(mag, axis=-1, keepdims=True)
    return mag / jnp.maximum(n, 1e-12)


class ChunkDescriptors(NamedTuple):
    """Per chunk and anchor: ``grids [T, A, R, S]``, ``signatures [T, A, D]``, ``counts [T, A]``
    (points in the grid), ``valid [T, A]`` (a camera height and ``min_points`` points), and the
    chunks' :class:`ChunkGeometry` (``[T, ...]``)."""

    grids: Array
    signatures: Array
    counts: Array
    valid: Array
    geometry: ChunkGeometry


@functools.partial(jax.jit, static_argnames=("options",))
def chunk_descriptors(
    frames: align.ChunkFrames, K_ref: Float[ArrayLike, "3 3"], options: GeometryOptions = GeometryOptions()
) -> ChunkDescriptors:
    """:class:`ChunkDescriptors` of ``T`` chunks' loaded frames (``ChunkFrames`` fields
    ``[T, F, H, W]`` / ``[T, F, 3, 3|4]``); vmapped over chunks and anchors.  Recompiles per
    ``(T, F, H, W)`` and ``options``."""
    geo = jax.vmap(lambda f: chunk_frame(f, K_ref, options))(frames)

    def one(g: ChunkGeometry):
        def at(a):
            q = _normalised(g.points, a, g.basis, g.height)
            return polar_grid(q, g.weights, options.rings, options.sectors, options.max_radius, options.max_height)

        return jax.vmap(at)(g.anchors)

    grids, counts = jax.vmap(one)(geo)
    valid = jnp.isfinite(geo.height)[:, None] & (counts >= options.min_points)
    return ChunkDescriptors(grids, grid_signature(grids), counts, valid, geo)


# ----------------------------------------------------------------------- matching


@jax.jit
def signature_distances(
    signatures: Float[ArrayLike, "T A D"], valid: Bool[ArrayLike, "T A"]
) -> tuple[Float[Array, "T T"], Int[Array, "T T 2"]]:
    """``(d [T, T], best [T, T, 2])``: per chunk pair the smallest ``1 − σ_a · σ_b`` over
    valid anchor pairs (``inf`` when none) and the anchors achieving it."""
    s = jnp.asarray(signatures)
    T, A, _ = s.shape
    d = 1.0 - jnp.einsum("iad,jbd->ijab", s, s)
    ok = jnp.asarray(valid)
    d = jnp.where(ok[:, None, :, None] & ok[None, :, None, :], d, jnp.inf).reshape(T, T, A * A)
    k = jnp.argmin(d, -1)
    return jnp.min(d, -1), jnp.stack([k // A, k % A], -1).astype(jnp.int32)


@jax.jit
def scan_context_distance(
    grid_a: Float[ArrayLike, "*#b R S"], grid_b: Float[ArrayLike, "*#b R S"]
) -> tuple[Float[Array, "*#b"], Int[Array, "*#b"]]:
    """``(d_SC(m*), m*)`` (module docstring): the column-wise cosine distance at the best
    sector shift, with ``G_b[:, k + m*]`` matching ``G_a[:, k]``; columns empty in both grids do
    not count (1 when no column counts).  Batched over leading axes."""
    a = jnp.asarray(grid_a)
    b = jnp.asarray(grid_b)
    S = a.shape[-1]
    m = jnp.arange(S)
    idx = (m[:, None] + jnp.arange(S)[None, :]) % S  # [shift, column]
    bs = jnp.moveaxis(jnp.take(b, idx, axis=-1), -2, -3)  # [..., shift, R, S]
    na = jnp.linalg.norm(a, axis=-2)  # [..., S]
    nb = jnp.linalg.norm(bs, axis=-2)  # [..., shift, S]
    dot = jnp.sum(a[..., None, :, :] * bs, axis=-2)
    either = (na[..., None, :] > 0) | (nb > 0)
    cos = jnp.where((na[..., None, :] > 0) & (nb > 0), dot / jnp.maximum(na[..., None, :] * nb, 1e-12), 0.0)
    cnt = jnp.sum(either, -1)
    d = jnp.where(cnt > 0, jnp.sum(jnp.where(either, 1.0 - cos, 0.0), -1) / jnp.maximum(cnt, 1), 1.0)
    best = jnp.argmin(d, -1)
    return jnp.take_along_axis(d, best[..., None], -1)[..., 0], best.astype(jnp.int32)


def _rot_z(psi: Array) -> Array:
    c, s = jnp.cos(psi), jnp.sin(psi)
    z, o = jnp.zeros_like(psi), jnp.ones_like(psi)
    return jnp.stack([jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2)


@jax.jit
def coarse_edge(
    anchor_a: Float[ArrayLike, "*#b 3"],
    basis_a: Float[ArrayLike, "*#b 3 3"],
    height_a: Float[ArrayLike, "*#b"],
    anchor_b: Float[ArrayLike, "*#b 3"],
    basis_b: Float[ArrayLike, "*#b 3 3"],
    height_b: Float[ArrayLike, "*#b"],
    yaw: Float[ArrayLike, "*#b"],
) -> Float[Array, "*#b 8"]:
    """The coarse Sim(3) ``[8]`` from chunk ``a`` into chunk ``b``: ``s₀ = h_b / h_a``,
    ``R₀ = B_b R_z(ψ) B_aᵀ``, ``t₀ = a_b − s₀ R₀ a_a`` (module docstring)."""
    R = jnp.asarray(basis_b) @ _rot_z(jnp.asarray(yaw, jnp.float32)) @ jnp.swapaxes(jnp.asarray(basis_a), -1, -2)
    s = jnp.asarray(height_b) / jnp.asarray(height_a)
    R = so3.as_matrix(so3.project(R))
    t = jnp.asarray(anchor_b) - s[..., None] * jnp.einsum("...ij,...j->...i", R, jnp.asarray(anchor_a))
    return sim3.from_rst(R, t, s)


# ----------------------------------------------------------------------- registration


def subsample(
    points: Float[ArrayLike, "N D"],
    weights: Float[ArrayLike, " N"],
    n: int,
    key: Key[ArrayLike, ""] | UInt32[ArrayLike, "2"],
) -> tuple[Float[Array, "n D"], Float[Array, " n"]]:
    """``n`` of the points with ``weights > 0``, drawn without replacement (all of them, padded
    with zero-weight rows, when fewer): ``(points [n, 3], weights [n])``.  Fixed shape: the
    ``n`` largest of ``1[w > 0] + U(0, 1)`` (``key``).  Fewer than ``n`` rows (small images):
    zero-weight rows are appended first (static: ``N`` is known when traced)."""
    points, w = jnp.asarray(points), jnp.asarray(weights)
    if n > w.shape[0]:
        points = jnp.concatenate([points, jnp.zeros((n - w.shape[0], points.shape[1]), points.dtype)])
        w = jnp.concatenate([w, jnp.zeros(n - w.shape[0], w.dtype)])
    score = (w > 0).astype(jnp.float32) + jax.random.uniform(jnp.asarray(key), w.shape)
    _, idx = jax.lax.top_k(score, n)
    return points[idx], jnp.where(w[idx] > 0, w[idx], 0.0)


class Registration(NamedTuple):
    """Result of :func:`register` (batch axes ``[...]`` in front).

    Attributes:
        S: ``[..., 8]`` the Sim(3) from ``a`` into ``b``.
        rms: RMS of the inliers' residuals in camera heights of ``b``.
        inlier_ratio: inliers among the source's structure points (``z >= ground_band``).
        num_inliers: int32 inliers (all points).
        num_structure: int32 inlying structure points.
        spread: ``λ₂ / λ₁`` of the inlying structure's horizontal covariance.
        scale_ratio: ``s / s₀``.
        valid: every Umeyama solve valid and everything finite.
        src_mean, src_covariance: ``[..., 3]``, ``[..., 3, 3]`` of the inliers (source units),
            the statistics of :func:`swiftjax.align.covariance.umeyama_information`.
        num_points: int32 source points used.
        axis: ``[..., 3]`` the principal horizontal direction of the inlying structure (unit,
            ``b``'s frame): the street's direction where ``spread`` is small.
        axis_variance: ``λ₁``, the inlying structure's horizontal variance along ``axis``
            (``b``'s units²).
        structure_mean: ``[..., 3]`` the inlying structure's centroid (``b``'s frame).
    """

    S: Array
    rms: Array
    inlier_ratio: Array
    num_inliers: Array
    num_structure: Array
    spread: Array
    scale_ratio: Array
    valid: Array
    src_mean: Array
    src_covariance: Array
    num_points: Array
    axis: Array
    axis_variance: Array
    structure_mean: Array


def _block_size(Q: int) -> int:
    """The block of :func:`_nearest`'s index search: the power of two nearest ``sqrt(Q)`` from
    above (32 for 1,024 targets, 64 for 4,096), so that both of its passes over ``[P, Q / b]``
    and ``[P, b]`` are small beside the distance pass."""
    return 1 << max(math.ceil(math.log2(max(Q, 1)) / 2), 0)


def _nearest(y: Array, dst: Array, w_dst: Array) -> tuple[Array, Array]:
    """Brute-force nearest neighbour of each ``y [P, 3]`` among the ``dst [Q, 3]`` with weight:
    ``(index [P], distance [P])``.

    ``d²_pq = Σ_c (y_pc − x_qc)²`` coordinate by coordinate: one fused elementwise pass and
    reduction over ``[P, Q]`` (no ``[P, Q, 3]`` intermediate, no rank-3 matrix product, whose
    ``|y|² − 2 y·x + |x|²`` also cancels in float32); 2.8x faster on CPU than the product form.

    The index is not a second pass over ``[P, Q]`` (``argmin``'s (value, index) pair reduction,
    which XLA:CPU does not vectorise, or a second plain reduction): the one pass keeps the
    minimum of each block of ``b`` targets (:func:`_block_size`, the targets padded to ``G b``
    with masked rows), and the index is searched in the first block holding the minimum only::

        m_pg = min_{q ∈ block g} d²_pq,   m_p = min_g m_pg,   g_p = min {g : m_pg = m_p}
        k_p = g_p b + min {i : d²_{p, g_p b + i} = m_p}

    ``d²`` of the block is recomputed by the same expression, so it equals the pass's bit for bit
    and ``k_p`` is the first minimiser, as ``argmin``: bitwise the ``argmin`` / ``min`` result for
    every finite ``y_p`` (the block's own ``argmin`` stands in should a compiler ever round the
    two differently).  Cost: the ``[P, Q]`` pass plus ``[P, Q / b]`` and ``[P, b]``; against the
    two full reductions, the pipeline's batches of Sim(3) ICP run 1.11–1.15x (peak ICP,
    256 x 1,024) and 1.24–1.38x (refinement, 1,024 x 4,096) faster, results bitwise equal
    (``python bench/bench_registration.py``).
    A non-finite ``y_p`` gets a non-finite distance (NaN or inf: the vectorised ``min`` need not
    propagate NaN) and an arbitrary index, which :func:`register` never uses (its weight is 0:
    ``r < τ`` is false)."""
    Q = dst.shape[0]
    b = _block_size(Q)
    G = -(-Q // b)
    if G * b > Q:  # masked rows: never a minimum
        dst = jnp.concatenate([dst, jnp.zeros((G * b - Q, 3), dst.dtype)])
        w_dst = jnp.concatenate([w_dst, jnp.zeros(G * b - Q, w_dst.dtype)])

    def squared(x: Array, w: Array) -> Array:  # [P, n] from x [P or 1, n, 3]
        d2 = (y[:, 0:1] - x[..., 0]) ** 2 + (y[:, 1:2] - x[..., 1]) ** 2 + (y[:, 2:3] - x[..., 2]) ** 2
        return jnp.where(w > 0, d2, jnp.inf)

    mb = jnp.min(squared(dst[None], w_dst[None]).reshape(-1, G, b), -1)  # [P, G]
    m = jnp.min(mb, -1)
    first = lambda hit, n: jnp.min(jnp.where(hit, jnp.arange(n, dtype=jnp.int32)[None, :], n - 1), -1)
    g = first(mb == m[:, None], G)
    e2 = squared(dst.reshape(G, b, 3)[g], w_dst.reshape(G, b)[g])  # [P, b]: the block again
    hit = e2 == m[:, None]
    i = jnp.where(jnp.any(hit, -1), first(hit, b), jnp.argmin(e2, -1).astype(jnp.int32))
    return jnp.minimum(g * b + i, Q - 1), jnp.sqrt(m)


def _tukey(r: Array, tau: Array) -> Array:
    """Tukey's biweight of residuals ``r`` at radius ``τ``: ``(1 − (r/τ)²)²`` for ``r < τ``, else 0
    (a non-finite ``r`` gets 0)."""
    return jnp.where(r < tau, (1.0 - (r / tau) ** 2) ** 2, 0.0)


def _yaw_step(y: Array, z: Array, w: Array, up: Array) -> tuple[Array, Array]:
    """The weighted least-squares rotation about ``up`` and translation ``D`` taking ``y [P, 3]``
    onto ``z [P, 3]`` (scale fixed): with the weighted means ``ȳ, z̄`` and the horizontal parts
    ``a = (I − u uᵀ)(y − ȳ)``, ``b = (I − u uᵀ)(z − z̄)``, ``θ = atan2(Σ w u·(a × b), Σ w a·b)``,
    ``R = R_u(θ)`` (Rodrigues), ``t = z̄ − R ȳ``.  ``(D [8], valid)``."""
    W = jnp.sum(w)
    my = jnp.sum(w[:, None] * y, 0) / jnp.maximum(W, 1e-30)
    mz = jnp.sum(w[:, None] * z, 0) / jnp.maximum(W, 1e-30)
    P = jnp.eye(3) - jnp.outer(up, up)
    a, b = (y - my) @ P, (z - mz) @ P
    theta = jnp.arctan2(jnp.sum(w * (jnp.cross(a, b) @ up)), jnp.sum(w * jnp.sum(a * b, -1)))
    K = jnp.cross(jnp.eye(3), up)  # [u]x: row k is e_k × u, (e_k × u)·v = (u × v)_k
    R = jnp.eye(3) + jnp.sin(theta) * K + (1.0 - jnp.cos(theta)) * K @ K
    D = sim3.from_rst(R, mz - R @ my, jnp.ones((), y.dtype))
    return D, (W > 0) & jnp.all(jnp.isfinite(D))


@functools.partial(jax.jit, static_argnames=("iterations", "four_dof"))
def register(
    src: Float[ArrayLike, "P 3"],
    w_src: Float[ArrayLike, " P"],
    dst: Float[ArrayLike, "Q 3"],
    w_dst: Float[ArrayLike, " Q"],
    S0: Float[ArrayLike, "8"],
    unit: Float[ArrayLike, ""],
    up: Float[ArrayLike, "3"],
    ground: Float[ArrayLike, ""],
    tau_start: float | Float[ArrayLike, ""] = 3.0,
    tau_end: float | Float[ArrayLike, ""] = 0.25,
    ground_band: float | Float[ArrayLike, ""] = 0.35,
    *,
    iterations: int = 16,
    four_dof: bool = False,
    colours: tuple[Float[ArrayLike, "P 3"], Float[ArrayLike, "Q 3"]] | None = None,
    colour_tolerance: float | Float[ArrayLike, ""] = math.inf,
) -> Registration:
    """Robust Sim(3) ICP of ``src`` onto ``dst`` from ``S0`` (module docstring).

    Args:
        src, w_src: ``[P, 3]`` points of chunk ``a`` and their weights (0: unused).
        dst, w_dst: ``[Q, 3]`` points of chunk ``b``.
        S0: ``[8]`` the starting Sim(3) (:func:`coarse_edge`).
        unit: ``h_b``, the camera height in ``b``'s units (radii and RMS are in it).
        up: ``[3]`` ``b``'s up direction; ``ground``: the road's height along ``up`` in ``b``
            (``up · x = ground`` on the road), so that ``z = (up · x − ground) / unit``.
        tau_start, tau_end, ground_band: camera heights.
        iterations: static.
        four_dof: static; each step solves only a rotation about ``up`` and a translation
            (:func:`_yaw_step`, gravity-aligned, the scale stays ``S0``'s): the coarse stage,
            where a full Sim(3) step from a far start can shrink the cloud onto a few
            neighbours (``s → 0``, every residual small).
        colours: ``(c_src [P, 3], c_dst [Q, 3])`` the points' :func:`chromaticity`, or None.
            A pair whose colours differ, ``max_c |c_p − c_{k(p)}| > colour_tolerance``, is no
            match: its weight is 0 in every step and it is no inlier (colour as a
            correspondence test, as in coloured ICP, Park, Zhou & Koltun 2017: a street slid
            onto the next building's facade, or a placement on an unrelated street, keeps its
            geometric neighbours but not their paint).

    Returns:
        :class:`Registration`.  Pure; recompiles per ``(P, Q, iterations, four_dof)`` and whether
        ``colours`` is given.
    """
    src = jnp.asarray(src, jnp.float32)
    dst = jnp.asarray(dst, jnp.float32)
    w_src = jnp.asarray(w_src, jnp.float32)
    w_dst = jnp.asarray(w_dst, jnp.float32)
    unit = jnp.asarray(unit, jnp.float32)
    up = jnp.asarray(up, jnp.float32)
    ratio = (jnp.asarray(tau_end, jnp.float32) / jnp.asarray(tau_start, jnp.float32)) ** (1.0 / max(iterations - 1, 1))
    taus = jnp.asarray(tau_start, jnp.float32) * ratio ** jnp.arange(iterations, dtype=jnp.float32) * unit

    if colours is None:
        agree = lambda k: jnp.ones(k.shape, bool)
    else:
        c_src, c_dst = (jnp.asarray(c, jnp.float32) for c in colours)
        tol = jnp.asarray(colour_tolerance, jnp.float32)
        agree = lambda k: jnp.max(jnp.abs(c_src - c_dst[k]), -1) <= tol

    def step(carry, tau):
        S, ok = carry
        k, r = _nearest(sim3.act(S, src), dst, w_dst)
        w = w_src * _tukey(r, tau) * agree(k)
        if four_dof:
            D, good = _yaw_step(sim3.act(S, src), dst[k], w, up)
            S_new = sim3.compose(D, S)
        else:
            S_new, info = align.umeyama(src, dst[k], w)
            good = info.valid
        good = good & jnp.all(jnp.isfinite(S_new))
        return (jnp.where(good, S_new, S), ok & good), None

    S0 = jnp.asarray(S0, jnp.float32)
    (S, ok), _ = jax.lax.scan(step, (S0, jnp.asarray(True)), taus)
    y = sim3.act(S, src)
    k, r = _nearest(y, dst, w_dst)
    tau = taus[-1]
    used = w_src > 0
    inl = used & (r < tau) & agree(k)
    z = (y @ up - ground) / unit
    struct = used & (z >= ground_band)
    inl_s = inl & struct
    n_inl = jnp.sum(inl)
    rms = jnp.sqrt(jnp.sum(jnp.where(inl, r * r, 0.0)) / jnp.maximum(n_inl, 1)) / unit
    wi = inl.astype(jnp.float32)
    mean = jnp.sum(src * wi[:, None], 0) / jnp.maximum(n_inl, 1)
    dc = (src - mean) * wi[:, None]
    cov = dc.T @ dc / jnp.maximum(n_inl, 1)
    # horizontal spread of the inlying structure, in b's gravity frame
    ys = jnp.where(inl_s[:, None], y, 0.0)
    ns = jnp.sum(inl_s)
    ms = jnp.sum(ys, 0) / jnp.maximum(ns, 1)
    P = jnp.eye(3) - jnp.outer(up, up)
    hs = jnp.where(inl_s[:, None], (y - ms) @ P, 0.0)
    ev, evec = jnp.linalg.eigh(hs.T @ hs / jnp.maximum(ns, 1))  # ascending; [0] ≈ 0 (the up axis)
    spread = ev[1] / jnp.maximum(ev[2], 1e-30)
    s0 = sim3.scale(S0)
    finite = jnp.all(jnp.isfinite(S)) & jnp.isfinite(rms)
    return Registration(
        S=jnp.where(finite, S, S0),
        rms=jnp.where(finite, rms, jnp.inf),
        inlier_ratio=jnp.sum(inl_s) / jnp.maximum(jnp.sum(struct), 1),
        num_inliers=n_inl.astype(jnp.int32),
        num_structure=ns.astype(jnp.int32),
        spread=spread,
        scale_ratio=sim3.scale(S) / s0,
        valid=ok & finite,
        src_mean=mean,
        src_covariance=cov,
        num_points=jnp.sum(used).astype(jnp.int32),
        axis=evec[:, 2],
        axis_variance=ev[2],
        structure_mean=ms,
    )


def _placement_reason(
    reg: dict, options: GeometryOptions, failed: str, *, scale_of: str, straight_ok: bool = False
) -> str | None:
    """The checks every registration verdict starts with (:func:`registration_reason`,
    :func:`covisible_reason`): a failed solve (``failed`` says how), a scale outside
    ``[1 / max_scale_ratio, max_scale_ratio]`` times the prior's (``scale_of`` names it), or too
    little structure, or (unless ``straight_ok``: the edge then leaves what a straight street
    cannot fix to the odometry, :func:`straight_covariance`) too straight; ``None`` when all
    pass."""
    if not reg["valid"]:
        return f"registration failed ({failed})"
    r = options.max_scale_ratio
    if not (1.0 / r <= reg["scale_ratio"] <= r):
        return f"registration scale {reg['scale_ratio']:.2f} x {scale_of}, outside [{1 / r:.2f}, {r:.2f}]"
    if reg["num_structure"] < options.min_structure or (not straight_ok and reg["spread"] < options.min_spread):
        return (
            f"degenerate registration: {reg['num_structure']} structure inliers, spread "
            f"{reg['spread']:.3f} (a featureless or straight road leaves the edge free)"
        )
    return None


def registration_reason(reg: dict, options: GeometryOptions) -> str | None:
    """Why a registration's numbers (a :class:`Registration` as plain floats) reject the
    candidate, in one line, or ``None``."""
    why = _placement_reason(
        reg, options, "an Umeyama solve was degenerate or not finite", scale_of="the camera-height ratio"
    )
    if why is not None:
        return why
    if not reg["inlier_ratio"] >= options.min_inlier_ratio:
        return f"registration inlier ratio {reg['inlier_ratio']:.2f} < {options.min_inlier_ratio}"
    if not reg["rms"] <= options.max_rms:
        return f"registration residual {reg['rms']:.3f} camera heights > {options.max_rms}"
    return None


def sector_yaw(shift: int | Int[ArrayLike, "*b"], sectors: int) -> float | Float[ArrayLike, "*b"]:
    """The yaw ``ψ = m 2π / N_s`` of a sector shift."""
    return shift * (2 * math.pi / sectors)


# ----------------------------------------------------------------------- several starts


def path_weights(geometry: ChunkGeometry, max_radius: float) -> Float[Array, "*b N"]:
    """``[..., N]`` the weights of the reliable points lying within ``max_radius`` camera
    heights (horizontally, in the chunk's gravity frame) of one of its anchors: the part of the
    chunk's cloud the camera path saw from close by (what both passes of a street share)."""

    def one(g: ChunkGeometry) -> Array:
        rel = g.points[None, :, :] - g.anchors[:, None, :]  # [A, N, 3]
        xy = small_matmul(rel, g.basis[:, :2]) / g.height  # [A, N, 2]
        near = jnp.any(jnp.sum(xy * xy, -1) < max_radius**2, 0)
        return jnp.where(near & jnp.isfinite(g.height), g.weights, 0.0)

    lead = geometry.weights.shape[:-1]
    flat = jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[len(lead) :]), geometry)
    return jax.vmap(one)(flat).reshape(*lead, -1)


@jax.jit
def coarse_hypotheses(
    grids_a: Float[ArrayLike, "A R S"],
    grids_b: Float[ArrayLike, "A R S"],
    anchors_a: Float[ArrayLike, "A 3"],
    basis_a: Float[ArrayLike, "3 3"],
    height_a: Float[ArrayLike, ""],
    anchors_b: Float[ArrayLike, "A 3"],
    basis_b: Float[ArrayLike, "3 3"],
    height_b: Float[ArrayLike, ""],
) -> tuple[Float[Array, "2*A*A 8"], Int[Array, "2*A*A 2"], Float[Array, " 2*A*A"]]:
    """Every start of the registration of chunk ``a`` onto ``b``: ``(S0 [2 A², 8], anchors
    [2 A², 2] int32, yaw [2 A²])``.

    The signature's best anchor pair is often far from the true correspondence (the polar grid
    is only weakly sensitive to where along a street it is taken), and a street is nearly
    symmetric end to end, so one start is not enough.  For every anchor pair ``(α, β)``
    the Scan Context shift ``m*_{αβ}`` of their grids gives the yaw ``ψ = m* 2π / N_s``; each
    pair contributes :func:`coarse_edge` at ``ψ`` and at ``ψ + π`` (anchors of a reverse pass
    coincide to a few camera heights for some pair: the cameras drove the same road).
    Order: ``(α, β, yaw)`` row-major.  Pure; recompiles per ``(A, R, S)``.
    """
    ga, gb = jnp.asarray(grids_a), jnp.asarray(grids_b)
    A, S = ga.shape[0], ga.shape[-1]
    _, shift = scan_context_distance(ga[:, None], gb[None, :])  # [A, A]
    psi = shift.astype(jnp.float32) * (2 * jnp.pi / S)
    yaw = jnp.stack([psi, psi + jnp.pi], -1)  # [A, A, 2]
    ia, ib = jnp.meshgrid(jnp.arange(A), jnp.arange(A), indexing="ij")
    ia, ib = jnp.broadcast_to(ia[..., None], yaw.shape), jnp.broadcast_to(ib[..., None], yaw.shape)
    aa, ab = jnp.asarray(anchors_a)[ia.reshape(-1)], jnp.asarray(anchors_b)[ib.reshape(-1)]
    S0 = coarse_edge(aa, basis_a, height_a, ab, basis_b, height_b, yaw.reshape(-1))
    return S0, jnp.stack([ia.reshape(-1), ib.reshape(-1)], -1).astype(jnp.int32), jnp.mod(yaw.reshape(-1), 2 * jnp.pi)


@functools.partial(jax.jit, static_argnames=("options",))
def register_hypotheses(
    src: Float[ArrayLike, "P 3"],
    w_src: Float[ArrayLike, " P"],
    dst: Float[ArrayLike, "Q 3"],
    w_dst: Float[ArrayLike, " Q"],
    S0: Float[ArrayLike, "H 8"],
    unit: Float[ArrayLike, ""],
    up: Float[ArrayLike, "3"],
    ground: Float[ArrayLike, ""],
    options: GeometryOptions = GeometryOptions(),
) -> tuple[Registration, Int[Array, ""], Int[Array, " H"]]:
    """The registration of ``src`` onto ``dst`` from the best of ``H`` starts: ``(Registration,
    chosen int32, scores [H])``.

    A coarse robust ICP (:func:`register` with ``four_dof``: yaw about gravity and translation,
    the scale held at the start's camera-height ratio; ``coarse_iterations``, Tukey radius
    ``coarse_tau_start → coarse_tau_end``) runs from every start at once (``vmap``) on the first
    ``coarse_src_points`` / ``coarse_dst_points`` rows of the subsamples (:func:`subsample`
    puts the chosen points first, in random order); each is scored by its inlying structure
    points (``num_structure``: road points match under any yaw, so they do not count), an
    invalid solve by −1.  The best is refined by the full ICP (``iterations``, ``tau_start →
    tau_end``, all rows).  ``scale_ratio`` of the result is ``s`` against the chosen START's
    scale (the camera-height ratio ``s₀``), not against the coarse result.  Pure; recompiles per
    ``(P, Q, H, options)``.
    """
    S0 = jnp.asarray(S0, jnp.float32)
    o = options
    pc, qc = min(o.coarse_src_points, src.shape[0]), min(o.coarse_dst_points, dst.shape[0])
    src, w_src, dst, w_dst = (jnp.asarray(x, jnp.float32) for x in (src, w_src, dst, w_dst))

    def coarse(s0):
        return register(
            src[:pc],
            w_src[:pc],
            dst[:qc],
            w_dst[:qc],
            s0,
            unit,
            up,
            ground,
            o.coarse_tau_start,
            o.coarse_tau_end,
            o.ground_band,
            iterations=o.coarse_iterations,
            four_dof=True,
        )

    rough = jax.vmap(coarse)(S0)
    scores = jnp.where(rough.valid & jnp.all(jnp.isfinite(S0), -1), rough.num_structure, -1)
    k = jnp.argmax(scores).astype(jnp.int32)
    start = jnp.where(scores[k] >= 0, rough.S[k], sim3.identity())
    reg = register(
        src, w_src, dst, w_dst, start, unit, up, ground, o.tau_start, o.tau_end, o.ground_band, iterations=o.iterations
    )
    ok = reg.valid & (scores[k] >= 0)
    return (
        reg._replace(
            S=jnp.where(ok, reg.S, sim3.identity()), scale_ratio=sim3.scale(reg.S) / sim3.scale(start), valid=ok
        ),
        k,
        scores,
    )


# ----------------------------------------------------------------------- co-visible chunk pairs


class ChunkCloud(NamedTuple):
    """A chunk's structure in its gravity frame (batch axes ``[...]`` in front).

    Attributes:
        points: ``[..., Q, 3]`` structure points (chunk units): reliable, near the camera path
            (:func:`path_weights`), at least ``structure_height`` above the road; drawn by
            :func:`subsample` (the chosen points first).
        weights: ``[..., Q]`` 1 for a point, 0 for padding.
        origin: ``[..., 3]`` the mean of the anchors (camera centres).
        basis: ``[..., 3, 3]`` the gravity frame ``[e1 e2 u]``.
        height: ``[...]`` the camera height ``h``.
        colours: ``[..., Q, 3]`` the points' chromaticity, or None (no images: colour never
            rejects a match, :func:`register`).
    """

    points: Array
    weights: Array
    origin: Array
    basis: Array
    height: Array
    colours: Array | None = None


@functools.partial(jax.jit, static_argnames=("options",))
def structure_cloud(
    geometry: ChunkGeometry,
    key: Key[ArrayLike, ""] | UInt32[ArrayLike, "2"],
    options: GeometryOptions = GeometryOptions(),
) -> ChunkCloud:
    """:class:`ChunkCloud` of one chunk's :class:`ChunkGeometry` (``dst_points`` rows; vmap it
    over chunks with one key each).  ``z = u·(x − o)/h + 1 >= structure_height`` keeps what
    stands above the road (the road matches under any placement)."""
    g = geometry
    o = jnp.mean(g.anchors, 0)
    w = path_weights(g, options.max_radius)
    z = (g.points - o) @ g.basis[:, 2] / g.height + 1.0
    keep = (w > 0) & (z >= options.structure_height) & jnp.isfinite(g.height)
    rows = g.points if g.colours is None else jnp.concatenate([g.points, g.colours], -1)
    rows, ws = subsample(rows, keep.astype(jnp.float32), options.dst_points, key)
    return ChunkCloud(rows[:, :3], ws, o, g.basis, g.height, None if g.colours is None else rows[:, 3:])


def neighbour_offsets(k: int) -> tuple[int, ...]:
    """The chunk offsets ``d = −k … −1, 1 … k`` of a chunk's ``2k`` neighbours, in the order of
    :func:`merge_neighbours`' ``edges`` and ``valid`` columns."""
    return (*range(-k, 0), *range(1, k + 1))


def merge_neighbours(clouds: ChunkCloud, edges: Float[ArrayLike, "T M 8"], valid: Bool[ArrayLike, "T M"]) -> ChunkCloud:
    """Every chunk's structure cloud joined with ``M = 2k`` neighbours' (the joint registration
    of :attr:`GeometryOptions.neighbours` ``= k``): neighbour ``m`` of chunk ``c`` is placed in
    ``c``'s coordinates by ``edges[c, m] = G_c⁻¹ G_n`` (the odometry chain's relative Sim(3),
    ``n`` the neighbour); where ``valid[c, m]`` is False (no such chunk) the rows are chunk
    ``c``'s own under ``edges[c, m]`` (the identity) with zero weights, whatever the other
    chunks (padding included); ``colours`` travel with their points::

        X'_c[(M + 1) q + 0] = X_c[q],   X'_c[(M + 1) q + 1 + m] = E_{c,m}(X_{n(c,m)}[q]),

    rows ``q < Q`` interleaved, so that the first ``(M + 1) n`` rows hold the first ``n`` rows of
    every chunk (the subsamples' order, :func:`subsample`: :meth:`GeometryOptions.rows`).  The
    origin, gravity basis and camera height stay chunk ``c``'s own, so a placement of the merged
    cloud is an edge between the two middle chunks.  ``clouds``: ``[T, Q, ...]``, neighbour
    ``c + d`` for ``d`` in :func:`neighbour_offsets` (``M = 2k``; ``valid`` marks the ones
    inside the sequence).  Pure; ``[T, (M + 1) Q, 3]`` out, one compile per shape."""
    T = clouds.points.shape[0]
    k = jnp.asarray(edges).shape[1] // 2
    offsets = jnp.asarray(neighbour_offsets(k), jnp.int32)
    valid = jnp.asarray(valid, bool)
    nb = jnp.where(valid, (jnp.arange(T)[:, None] + offsets[None, :]) % T, jnp.arange(T)[:, None])  # [T, M]
    moved = sim3.act(jnp.asarray(edges, jnp.float32)[:, :, None, :], clouds.points[nb])  # [T, M, Q, 3]
    w = clouds.weights[nb] * valid.astype(clouds.weights.dtype)[..., None]  # [T, M, Q]
    points = jnp.concatenate([clouds.points[:, None], moved], 1)  # [T, M + 1, Q, 3]
    weights = jnp.concatenate([clouds.weights[:, None], w], 1)
    rows = lambda x: jnp.swapaxes(x, 1, 2).reshape(T, -1, *x.shape[3:])  # [T, M + 1, Q, ...] interleaved
    colours = None if clouds.colours is None else jnp.concatenate([clouds.colours[:, None], clouds.colours[nb]], 1)
    return clouds._replace(
        points=rows(points), weights=rows(weights), colours=None if colours is None else rows(colours)
    )


def edge_prior(
    Z: Float[ArrayLike, "8"], a: ChunkCloud, b: ChunkCloud
) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, "2"]]:
    """The yaw ``ψ``, relative scale ``σ`` and translation ``τ [2]`` of an edge ``Z`` (``a``
    into ``b``) in the two chunks' normalised gravity frames ``q = Bᵀ(x − o)/h``::

        M = B_bᵀ R_Z B_a,   ψ = atan2(M₁₀, M₀₀),   σ = s_Z h_a / h_b,   τ = [B_bᵀ (Z(o_a) − o_b) / h_b]_xy

    so that ``q_b ≈ σ R(ψ) q_a + τ`` horizontally.  Pure."""
    Z = jnp.asarray(Z, jnp.float32)
    s = sim3.scale(Z)
    R = sim3.as_matrix(Z)[..., :3, :3] / s
    M = b.basis.T @ R @ a.basis
    tau = b.basis.T @ (sim3.act(Z, a.origin) - b.origin) / b.height
    return jnp.arctan2(M[1, 0], M[0, 0]), s * a.height / b.height, tau[:2]


def bev_raster(
    xy: Float[ArrayLike, "N 2"], weights: Float[ArrayLike, " N"], cells: int, cell: float
) -> Float[Array, "C C"]:
    """Bird's-eye occupancy ``[cells, cells]``: cell ``(⌊x/c⌋ + n/2, ⌊y/c⌋ + n/2)`` is 1 when a
    point with ``weights > 0`` falls in it.  One scatter that sets 1 (points off the grid
    dropped): 1.5x faster on CPU than counting points per cell and clipping at 1, the same
    raster.  Pure; ``cells`` static."""
    xy = jnp.asarray(xy, jnp.float32)
    ix = jnp.floor(xy[:, 0] / cell).astype(jnp.int32) + cells // 2
    iy = jnp.floor(xy[:, 1] / cell).astype(jnp.int32) + cells // 2
    ok = (
        (jnp.asarray(weights) > 0) & (ix >= 0) & (ix < cells) & (iy >= 0) & (iy < cells) & jnp.all(jnp.isfinite(xy), -1)
    )
    idx = jnp.where(ok, ix * cells + iy, cells * cells)
    return jnp.zeros(cells * cells, jnp.float32).at[idx].set(1.0, mode="drop").reshape(cells, cells)


def _start(a: ChunkCloud, b: ChunkCloud, psi: Array, sigma: Array, t: Array) -> Array:
    """The Sim(3) ``[8]`` of ``q_b = σ R(ψ) q_a + t`` in chunk units: ``s = σ h_b / h_a``,
    ``R = B_b R_z(ψ) B_aᵀ``, ``t' = o_b + h_b B_b [t, 0] − s R o_a``."""
    R = so3.as_matrix(so3.project(b.basis @ _rot_z(psi) @ a.basis.T))
    s = sigma * b.height / a.height
    tt = b.origin + b.height * b.basis @ jnp.stack([t[0], t[1], jnp.zeros_like(t[0])]) - s * R @ a.origin
    return sim3.from_rst(R, tt, s)


def bev_spectrum(b: ChunkCloud, options: GeometryOptions) -> Complex[Array, "C C2"]:
    """``F(D_b)``: the 2-D real FFT ``[bev_cells, bev_cells // 2 + 1]`` of chunk ``b``'s
    bird's-eye structure raster (:func:`bev_raster` in its normalised gravity frame
    ``q = Bᵀ(x − o)/h``, dilated by one cell, ``D ← max(D, shifts of D by ±1 cell)``).  It
    depends on ``b`` alone: computed once per chunk and reused by every pair it is the target
    of (:func:`bev_starts`).  Pure; vmap it over chunks."""
    n, c = options.bev_cells, options.bev_cell
    qb = small_matmul(b.points - b.origin, b.basis[:, :2]) / b.height
    D = bev_raster(qb, b.weights, n, c)
    for ax in (0, 1):
        D = jnp.maximum(D, jnp.maximum(jnp.roll(D, 1, ax), jnp.roll(D, -1, ax)))
    return jnp.fft.rfft2(D)


def bev_starts(
    a: ChunkCloud,
    b: ChunkCloud,
    psi: Float[ArrayLike, ""],
    sigma: Float[ArrayLike, ""],
    tau: Float[ArrayLike, "2"],
    window: Float[ArrayLike, ""],
    options: GeometryOptions,
    spectrum: Complex[ArrayLike, "C C2"] | None = None,
) -> tuple[Float[Array, "K 8"], Float[Array, " K"]]:
    """The ``peaks`` best placements of ``a`` on ``b``: ``(S0 [peaks, 8], correlation [peaks])``.

    ``a``'s structure is rasterised (:func:`bev_raster`) in its normalised gravity frame for
    every yaw ``ψ + δψ`` (``yaw_steps`` over ``±yaw_search``°) and scale ``σ e^{δ}``
    (``scale_steps`` over ``±scale_search``); the cross-correlation with ``b``'s dilated raster
    ``D_b`` over translations is one FFT, ``C(τ') = F⁻¹[F(D_b) · conj F(D_a)]`` (``spectrum``:
    ``F(D_b)`` from :func:`bev_spectrum`, computed here when None): the number of ``a``'s
    occupied cells that land on ``b``'s structure.

    **Scale without bias.**  ``C`` cannot compare scales: ``a``'s raster has ``N(δ) = Σ D_a``
    occupied cells, and structure seen from above is mostly lines (facades, kerbs), so ``N``
    grows like ``e^{δ}``; a placement a few per cent too large keeps nearly every cell within
    the dilation of ``b``'s, so ``argmax_δ C`` sits at the largest scale tried (on synthetic
    KITTI 00 from the TRUE prior: +0.10 in log-scale on average over ten chunk pairs, the
    ICP then keeps most of it: edges 12–14 % too large).  The fraction ``C / N`` is biased the
    other way (a shrunk raster packs into fewer cells: −0.05).  Against chance, a placement
    whose ``N`` cells fall on ``b``'s raster independently with ``b``'s fill fraction
    ``p = Σ D_b / n²`` (``F(D_b)`` at frequency 0 over ``n²``) overlaps ``C ~ Bin(N, p)``;
    each (yaw, scale) is scored by its z-score::

        z(τ') = (C(τ') − N p) / sqrt(N p (1 − p))

    the overlap in standard deviations above what that raster reaches by chance, comparable
    across ``N`` (the same pairs, seven noisy and seven noise-free: the best start at the true
    scale in 12 of 14, ±0.18 in two, mean 0.00).  At one (yaw, scale) ``z`` ranks translations
    as ``C`` does.

    Over the translations with ``|τ' − τ| <= window`` (the odometry's uncertainty) the best
    (yaw, scale) per translation by ``z`` is taken and ``peaks`` maxima of ``z`` at least
    ``peak_separation`` apart are returned, in order, with their overlap count ``C`` (−1 when
    the window holds no more translations).  Pure.
    """
    n, c = options.bev_cells, options.bev_cell
    qa = small_matmul(a.points - a.origin, a.basis[:, :2]) / a.height
    FD = bev_spectrum(b, options) if spectrum is None else jnp.asarray(spectrum)
    lin = lambda half, k: jnp.linspace(-half, half, k) if k > 1 else jnp.zeros(1)
    dy, ds = jnp.meshgrid(
        jnp.deg2rad(lin(options.yaw_search, options.yaw_steps)),
        lin(options.scale_search, options.scale_steps),
        indexing="ij",
    )
    dy, ds = dy.reshape(-1), ds.reshape(-1)
    shift = jnp.fft.fftfreq(n, 1.0 / n) * c
    tx, ty = (x.reshape(-1) for x in jnp.meshgrid(shift, shift, indexing="ij"))
    psi, sigma, tau = jnp.asarray(psi, jnp.float32), jnp.asarray(sigma, jnp.float32), jnp.asarray(tau, jnp.float32)

    fill = jnp.clip(jnp.real(FD[0, 0]) / (n * n), 1e-6, 1.0 - 1e-6)  # p = Σ D_b / n²

    def surface(y, e):
        xy = small_matmul(sigma * jnp.exp(e) * qa, _rot_z(psi + y)[:2, :2].T)
        Da = bev_raster(xy, a.weights, n, c)
        C = jnp.fft.irfft2(FD * jnp.conj(jnp.fft.rfft2(Da)), s=(n, n)).reshape(-1)
        N = jnp.sum(Da)
        return C, (C - N * fill) / jnp.sqrt(jnp.maximum(N * fill * (1.0 - fill), 1e-12))

    C, z = jax.vmap(surface)(dy, ds)  # [Y, n²] each
    which = jnp.argmax(z, 0)
    count = jnp.take_along_axis(C, which[None], 0)[0]
    inside = (tx - tau[0]) ** 2 + (ty - tau[1]) ** 2 <= jnp.asarray(window) ** 2
    best = jnp.where(inside, jnp.max(z, 0), -jnp.inf)
    ks, vals = [], []
    for _ in range(options.peaks):
        k = jnp.argmax(best)
        ks.append(k)
        vals.append(jnp.where(best[k] > -jnp.inf, count[k], -1.0))
        best = jnp.where((tx - tx[k]) ** 2 + (ty - ty[k]) ** 2 < options.peak_separation**2, -jnp.inf, best)
    k = jnp.stack(ks)
    S0 = jax.vmap(
        lambda kk: _start(a, b, psi + dy[which[kk]], sigma * jnp.exp(ds[which[kk]]), jnp.stack([tx[kk], ty[kk]]))
    )(k)
    return S0, jnp.stack(vals)


def window_on_grid(
    tau: Float[ArrayLike, "*b 2"], window: Float[ArrayLike, "*b"], options: GeometryOptions
) -> Bool[np.ndarray, "*b"]:
    """Whether :func:`bev_starts`' window ``|τ' − τ| <= window`` may hold a translation of its
    correlation grid, ``τ' ∈ c {−n/2, …, n/2 − 1}²`` (``n = bev_cells``, ``c = bev_cell``):
    bool ``[*b]``.

    The grid is the product of two 1-D grids, so the translation nearest ``τ`` is per axis
    ``τ*_x = c clip(round(τ_x / c), −n/2, n/2 − 1)``; the test is ``|τ* − τ| <= window + c``
    (one cell of margin against rounding at the boundary).  Where it is false, no translation
    is inside: every ``z`` of :func:`bev_starts` is ``−∞``, each peak's correlation ``−1``, and
    :func:`peak_icp` scores the job −1 ("no valid placement") whatever the clouds; the
    pipeline does not run such a job (a chain that puts the chunks farther apart than the
    window plus the grid's half-width).  Host side (NumPy, float64): it decides which jobs
    run, and costs no compile."""
    n, c = options.bev_cells, options.bev_cell
    tau = np.asarray(tau, np.float64)
    near = c * np.clip(np.round(tau / c), -(n // 2), n // 2 - 1)
    return np.linalg.norm(near - tau, axis=-1) <= np.asarray(window, np.float64) + c


class Placements(NamedTuple):
    """The refined placements of one source on one target (:func:`place_covisible`; batch axes
    ``[...]`` in front).

    Attributes:
        S: ``[..., K, 8]`` each correlation peak after the peak ICP (Sim(3), ``a`` into ``b``).
        scores: ``[..., K]`` int32 structure inliers of each (−1: an invalid solve or a peak
            outside the window).
        correlation: ``[..., K]`` the bird's-eye correlation at the peaks (overlapping cells).
    """

    S: Array
    scores: Array
    correlation: Array


def _colour_test(a: ChunkCloud, b: ChunkCloud, p: int, q: int, options: GeometryOptions) -> dict[str, Any]:
    """:func:`register`'s colour arguments for the first ``p`` rows of ``a`` on the first ``q``
    of ``b``: none unless both clouds carry colours."""
    if a.colours is None or b.colours is None:
        return {}
    return {"colours": (a.colours[:p], b.colours[:q]), "colour_tolerance": options.colour_tolerance}


def peak_icp(
    a: ChunkCloud,
    b: ChunkCloud,
    S0: Float[ArrayLike, "K 8"],
    correlation: Float[ArrayLike, " K"],
    options: GeometryOptions = GeometryOptions(),
) -> Placements:
    """:class:`Placements` from the starts ``S0`` of :func:`bev_starts`: each refined by the
    robust Sim(3) ICP (:func:`register`, ``coarse_iterations``, ``τ: tau_start → tau_end``) on
    the first ``peak_src_points`` / ``peak_dst_points`` rows and scored by its structure
    inliers ``n_k``; a peak that overlaps no cell (``correlation < 1/2``: the correlation
    counts overlapping cells) is no placement (−1), nor is one whose ICP moved the scale out
    of the range the verdict allows, ``s / s₀ ∉ [1 / max_scale_ratio, max_scale_ratio]``
    against its start ``s₀``: a source shrunk onto a speck of the target, where every point
    is an inlier (synthetic KITTI 08, world 2: chunk 32 placed on the unrelated chunk 89 ended
    at 0.9 % of its start's scale with 255 of 256 points inliers, and as a null sample that
    raised the bound its true revisit 15 had to beat from 24 to 317).  Cost: ``peaks x
    coarse_iterations`` brute-force nearest-neighbour passes of ``peak_src_points x
    peak_dst_points``.  Pure."""
    o = options
    up = b.basis[:, 2]
    ground = up @ b.origin - b.height
    ps, pd = o.rows(o.peak_src_points), o.rows(o.peak_dst_points)

    def refine(s0):
        return register(
            a.points[:ps],
            a.weights[:ps],
            b.points[:pd],
            b.weights[:pd],
            s0,
            b.height,
            up,
            ground,
            o.tau_start,
            o.tau_end,
            o.ground_band,
            iterations=o.coarse_iterations,
            **_colour_test(a, b, ps, pd, o),
        )

    corr = jnp.asarray(correlation)
    regs = jax.vmap(refine)(jnp.asarray(S0))
    log_ratio = jnp.abs(jnp.log(sim3.scale(regs.S) / sim3.scale(jnp.asarray(S0))))
    in_range = log_ratio <= jnp.log(o.max_scale_ratio)
    ok = regs.valid & in_range & (corr >= 0.5) & jnp.isfinite(a.height) & jnp.isfinite(b.height)
    return Placements(regs.S, jnp.where(ok, regs.num_structure, -1).astype(jnp.int32), corr)


def slide_starts(
    S: Float[ArrayLike, "8"], b: ChunkCloud, options: GeometryOptions = GeometryOptions()
) -> Float[Array, "N 8"]:
    """``[2 slide_steps, 8]`` starts along the target's street: the placement ``S`` (``a`` into
    ``b``) shifted in ``b`` along its heading ``e₁`` (the first column of ``b.basis``)::

        S_k = T(d_k h_b e₁) ∘ S,   d_k = ±j peak_separation / 2,   j = 1 … slide_steps

    ordered ``(−1, +1, −2, +2, …)`` steps; ``T(t)`` the pure translation.  Half the peaks'
    separation: a truth between two peaks kept ``peak_separation`` apart lies within a quarter
    of it of some start (the peak ICP's first Tukey radius, ``tau_start``, is 3 camera heights
    at the defaults).  Pure."""
    o = options
    j = np.repeat(np.arange(1, o.slide_steps + 1), 2) * np.tile([-1.0, 1.0], o.slide_steps)
    d = jnp.asarray(j * o.peak_separation / 2.0, jnp.float32) * b.height
    t = d[:, None] * b.basis[:, 0][None, :]
    shift = sim3.from_rst(jnp.broadcast_to(jnp.eye(3), (len(j), 3, 3)), t, jnp.ones(len(j)))
    return sim3.compose(shift, jnp.asarray(S, jnp.float32)[None])


@functools.partial(jax.jit, static_argnames=("options",))
def slide_batch(
    clouds: ChunkCloud,
    dst: Int[ArrayLike, " B"],
    S: Float[ArrayLike, "B 8"],
    options: GeometryOptions = GeometryOptions(),
) -> Float[Array, "B N 8"]:
    """:func:`slide_starts` of ``B`` placements onto the chunks ``dst`` of the stacked
    ``clouds [T, ...]``.  One compile per ``(T, B, options)``."""
    take = lambda c: jax.tree_util.tree_map(lambda x: x[c], clouds)
    return jax.vmap(lambda c, s: slide_starts(s, take(c), options))(jnp.asarray(dst), S)


def place_covisible(
    a: ChunkCloud,
    b: ChunkCloud,
    psi: Float[ArrayLike, ""],
    sigma: Float[ArrayLike, ""],
    tau: Float[ArrayLike, "2"],
    window: Float[ArrayLike, ""],
    options: GeometryOptions = GeometryOptions(),
    spectrum: Complex[ArrayLike, "C C2"] | None = None,
) -> Placements:
    """:class:`Placements` of ``a`` on ``b`` from the prior ``(ψ, σ, τ)`` within ``window``
    camera heights: :func:`bev_starts` then :func:`peak_icp`.  Pure."""
    S0, corr = bev_starts(a, b, psi, sigma, tau, window, options, spectrum)
    return peak_icp(a, b, S0, corr, options)


def _take(clouds: ChunkCloud, index: Array) -> ChunkCloud:
    return jax.tree_util.tree_map(lambda x: x[index], clouds)


def _over_pairs(fn: Callable[..., Any], clouds: ChunkCloud, src: ArrayLike, dst: ArrayLike, *jobs: ArrayLike) -> Any:
    """``fn(clouds[src[k]], clouds[dst[k]], *(x[k] for x in jobs))`` for ``k < B`` (``vmap``)."""

    def one(i: Array, j: Array, *job: Array) -> Any:
        return fn(_take(clouds, i), _take(clouds, j), *job)

    return jax.vmap(one)(jnp.asarray(src), jnp.asarray(dst), *(jnp.asarray(x) for x in jobs))


@functools.partial(jax.jit, static_argnames=("options",))
def starts_batch(
    clouds: ChunkCloud,
    spectra: Complex[ArrayLike, "T C C2"],
    src: Int[ArrayLike, " B"],
    dst: Int[ArrayLike, " B"],
    psi: Float[ArrayLike, " B"],
    sigma: Float[ArrayLike, " B"],
    tau: Float[ArrayLike, "B 2"],
    window: Float[ArrayLike, " B"],
    options: GeometryOptions = GeometryOptions(),
) -> tuple[Float[Array, "B K 8"], Float[Array, "B K"]]:
    """:func:`bev_starts` of ``B`` jobs at once (``vmap``): chunk ``src[k]`` (of the stacked
    ``clouds [T, ...]``) onto chunk ``dst[k]`` (its spectrum ``spectra[dst[k]]``, from
    :func:`bev_spectrum`) from the prior ``(psi, sigma, tau, window)[k]``.  One compile per
    ``(T, B, options)``: the caller pads its jobs to a multiple of ``B``."""
    sp = jnp.asarray(spectra)[jnp.asarray(dst)]
    return _over_pairs(
        lambda a, b, p, s, t, w, f: bev_starts(a, b, p, s, t, w, options, f),
        clouds,
        src,
        dst,
        psi,
        sigma,
        tau,
        window,
        sp,
    )


@functools.partial(jax.jit, static_argnames=("options",))
def peaks_batch(
    clouds: ChunkCloud,
    src: Int[ArrayLike, " B"],
    dst: Int[ArrayLike, " B"],
    S0: Float[ArrayLike, "B K 8"],
    correlation: Float[ArrayLike, "B K"],
    options: GeometryOptions = GeometryOptions(),
) -> Placements:
    """:func:`peak_icp` of ``B`` jobs at once (``vmap``).  One compile per ``(T, B, options)``."""

    return _over_pairs(lambda a, b, s, c: peak_icp(a, b, s, c, options), clouds, src, dst, S0, correlation)


def scale_sweep(
    src: Float[ArrayLike, "P 3"],
    w_src: Float[ArrayLike, " P"],
    dst: Float[ArrayLike, "Q 3"],
    w_dst: Float[ArrayLike, " Q"],
    S: Float[ArrayLike, "8"],
    tau: Float[ArrayLike, ""],
    half_range: float,
    steps: int,
) -> tuple[Float[Array, "8"], Float[Array, " K"]]:
    """The placement ``S`` rescaled about the source's centroid to the best of ``steps`` scales:
    ``(S ∘ D_k*, scores [steps])``.

    The robust ICP (:func:`register`) barely moves the scale: on a street the scale along it
    is as free as a slide (facade points scaled along the facade keep their neighbours), and
    the cross-street displacement a wrong scale makes (``δ`` times the street's half width,
    0.5–1 camera heights at ``δ`` = 0.1) leaves the Tukey radius, which shrinks to
    ``τ_end`` within a few iterations, before the scale has moved; the structure that still
    fits is what matches at the wrong scale.  Measured on synthetic KITTI 00 from the TRUE
    edge prior, noise off: starts at ``δ = ±0.18`` end their peak ICP at ``±0.14…0.24``; so
    the edge's scale is the bird's-eye grid's (:func:`bev_starts`, steps of ``2 scale_search
    / (scale_steps − 1)``) within a few per cent.  Here the scale is searched directly::

        D_k(x) = m + e^{δ_k} (x − m),   δ_k ∈ linspace(−half_range, half_range, steps),
        score_k = Σ_p w_p ρ(r_p),   ρ(r) = (1 − (r/τ)²)² [r < τ],   r_p = min_q |S D_k(x_p) − y_q|

    (``m``: the weighted mean of the source points; the Tukey score of :func:`register` at the
    radius ``τ``, in ``b``'s units), ``k* = argmax score_k``, the unscaled ``S`` (``δ = 0``)
    kept unless another scale scores strictly higher.  A wrong scale moves the facades across
    the street out of ``τ``; the right one brings them in.  Cost: ``steps`` nearest-neighbour
    passes, one after the other (``lax.map``; XLA:CPU materialises each pass's ``[P, Q]``
    distances for its reduction, so all at once would hold ``steps`` of them: 576 MB for the
    refinement's batch of 4, faulted in afresh on every call, against 64 MB).  Pure; ``steps``
    static (odd)."""
    src = jnp.asarray(src, jnp.float32)
    w = jnp.asarray(w_src, jnp.float32)
    dst, w_dst = jnp.asarray(dst, jnp.float32), jnp.asarray(w_dst, jnp.float32)
    S = jnp.asarray(S, jnp.float32)
    tau = jnp.asarray(tau, jnp.float32)
    m = jnp.sum(w[:, None] * src, 0) / jnp.maximum(jnp.sum(w), 1e-30)
    deltas = jnp.linspace(-half_range, half_range, steps) if steps > 1 else jnp.zeros(1)

    def scaled(d: Array) -> Array:
        e = jnp.exp(d)
        return sim3.compose(S, sim3.from_rst(jnp.eye(3), (1.0 - e) * m, e))

    Sk = jax.vmap(scaled)(deltas)
    # one scale at a time: XLA:CPU materialises each [P, Q] distance matrix for its reduction,
    # and all scales at once (vmap) would make that steps x P x Q (576 MB for the refinement's
    # batch of 4, fresh pages every call)
    r = jax.lax.map(lambda s: _nearest(sim3.act(s, src), dst, w_dst)[1], Sk)
    scores = jax.vmap(lambda rk: jnp.sum(w * _tukey(rk, tau)))(r)
    mid = steps // 2
    k = jnp.argmax(scores)
    k = jnp.where(scores[k] > scores[mid], k, mid)
    return jnp.where(jnp.all(jnp.isfinite(Sk[k])), Sk[k], S), scores


def refine_placement(
    a: ChunkCloud,
    b: ChunkCloud,
    S: Float[ArrayLike, "8"],
    prior_scale: Float[ArrayLike, ""],
    options: GeometryOptions = GeometryOptions(),
) -> Registration:
    """The chosen placement ``S`` refined on all rows: its scale searched first
    (:func:`scale_sweep`, ``refine_scale_steps`` over ± half a bird's-eye scale step,
    ``scale_search / (scale_steps − 1)``, at the Tukey radius ``coarse_tau_end``), then
    :func:`register` (``src_points x dst_points``, ``refine_iterations``, ``τ: coarse_tau_end →
    tau_end``); ``scale_ratio`` against ``prior_scale`` (the chain's ``σ h_b / h_a``), ``S`` the
    identity when invalid.  Pure."""
    o = options
    up = b.basis[:, 2]
    ground = up @ b.origin - b.height
    if o.refine_scale_steps > 1:
        S, _ = scale_sweep(
            a.points[: o.rows(o.src_points)],
            a.weights[: o.rows(o.src_points)],
            b.points,
            b.weights,
            S,
            o.coarse_tau_end * b.height,
            o.scale_search / max(o.scale_steps - 1, 1),
            o.refine_scale_steps,
        )
    reg = register(
        a.points[: o.rows(o.src_points)],
        a.weights[: o.rows(o.src_points)],
        b.points,
        b.weights,
        S,
        b.height,
        up,
        ground,
        o.coarse_tau_end,
        o.tau_end,
        o.ground_band,
        iterations=o.refine_iterations,
        **_colour_test(a, b, o.rows(o.src_points), b.points.shape[0], o),
    )
    ok = reg.valid & jnp.all(jnp.isfinite(jnp.asarray(S))) & jnp.isfinite(a.height) & jnp.isfinite(b.height)
    return reg._replace(
        S=jnp.where(ok, reg.S, sim3.identity()),
        scale_ratio=sim3.scale(reg.S) / jnp.asarray(prior_scale, jnp.float32),
        valid=ok,
    )


@functools.partial(jax.jit, static_argnames=("options",))
def refine_batch(
    clouds: ChunkCloud,
    src: Int[ArrayLike, " B"],
    dst: Int[ArrayLike, " B"],
    S: Float[ArrayLike, "B 8"],
    prior_scale: Float[ArrayLike, " B"],
    options: GeometryOptions = GeometryOptions(),
) -> Registration:
    """:func:`refine_placement` of ``B`` jobs at once (``vmap``, chunks gathered from the
    stacked ``clouds [T, ...]``).  One compile per ``(T, B, options)``.  ``[B, ...]``."""

    return _over_pairs(lambda a, b, s, p: refine_placement(a, b, s, p, options), clouds, src, dst, S, prior_scale)


def placement_moments(
    S: Float[ArrayLike, "K 8"], plausible: Bool[ArrayLike, " K"], best: Int[ArrayLike, ""]
) -> tuple[Float[Array, " 7"], Float[Array, "7 7"]]:
    """The edge's mean offset ``[7]`` and covariance ``[7, 7]`` over its plausible placements
    (tangent order ``(ρ, ω, σ)``, right perturbation of ``S[best]`` as in
    :mod:`swiftjax.align.covariance`)::

        δ_k = log(S_best⁻¹ S_k),   δ̄ = Σ_{k ∈ P} δ_k / |P|,   Σ_P = Σ_{k ∈ P} (δ_k − δ̄)(δ_k − δ̄)ᵀ / |P|

    ``P``: the placements whose structure inliers exceed what the source reaches on unrelated
    chunks (the null's bound), the best among them.  With the true edge equally likely to be
    any plausible placement, ``S_best exp(δ̄)`` and ``Σ_P`` are the mean and covariance of that
    mixture: the Gaussian closest to it (moment matching), the pose graph's edge
    (:func:`swiftjax.pipeline.loop_geometry.graph_edge`).  A street slid along itself gives
    placements on a line: ``Σ_P`` has rank one, large along the street and zero across it, in
    yaw and in scale; the registration's own covariance and the chunks' model error are added
    to it.  Zeros when only the best is plausible.  Pure."""
    S = jnp.asarray(S, jnp.float32)
    d = sim3.log(sim3.compose(sim3.inverse(S[best])[None], S))  # [K, 7]
    d = d.at[best].set(0.0)  # δ_best = 0 exactly (not log's rounding)
    w = jnp.asarray(plausible).astype(jnp.float32)
    w = jnp.where(jnp.all(jnp.isfinite(d), -1), w, 0.0)
    d = jnp.where((w > 0)[:, None], d, 0.0)
    n = jnp.maximum(jnp.sum(w), 1.0)
    mean = jnp.einsum("k,ki->i", w, d) / n
    c = d - mean
    return mean, jnp.einsum("k,ki,kj->ij", w, c, c) / n


def warp_covariance(
    extent_a: Float[ArrayLike, ""],
    extent_b: Float[ArrayLike, ""],
    scale: Float[ArrayLike, ""],
    sigma_rot: float | Float[ArrayLike, ""],
    sigma_trans: float | Float[ArrayLike, ""],
    sigma_scale: float | Float[ArrayLike, ""],
) -> Float[Array, "7 7"]:
    """The two chunks' own model error as a covariance ``[7, 7]`` of their registration edge
    ``Z`` (chunk ``a`` into chunk ``b``; tangent ``(ρ, ω, σ)``, right perturbation, ``ρ`` in
    chunk ``a``'s units)::

        Σ_W = Σ_odo(L_a) + Σ_odo(L_b / s),   Σ_odo(L) = diag(σ_t² L² I₃, σ_r² I₃, σ_s²)

    ``L_c``: chunk ``c``'s extent (the largest distance between two of its anchors, in its own
    units); ``s``: the edge's scale (a length of chunk ``b`` is ``1/s`` of it in ``a``'s
    units).  ``Σ_odo`` is the drift model of a temporal edge
    (:func:`swiftjax.loops.pcm.odometry_covariance`) over a path as long as the chunk: VGGT's
    model error across one chunk's whole extent.  A token loop edge measures the revisit in
    one loop-centric chunk that sees both places; a registration ties two chunks reconstructed
    apart, each warped over its whole extent, and its optimum lies where those warps put it.
    Its residuals cannot see that (each chunk is fitted to itself): on synthetic KITTI 08 the
    registration edges' errors against the truth, whitened by ``Ω_reg⁻¹ + Σ_P`` and the loop
    drift, averaged ``m² = 58`` (``χ²₇``: 7); with ``Σ_W`` 5, beside 08's temporal edges' 3.6
    (3.5–7.8 on the five routes of ``bench/bench_hard_sequences.py``, ``edge_calibration``)
    and the token edges' 3.2–6.5.  Pure; float64 under ``jax_enable_x64`` (as the pipeline
    calls it), else float32."""
    from swiftjax.loops.pcm import odometry_covariance

    dtype = jnp.result_type(float)  # float64 under jax_enable_x64, else float32
    L = jnp.stack([jnp.asarray(extent_a, dtype), jnp.asarray(extent_b, dtype)])
    s = jnp.stack([jnp.ones((), L.dtype), jnp.asarray(scale, L.dtype)])
    zero = jnp.zeros_like(L)
    # a pure translation of length L_c (in b's units for chunk b: scale s), identity rotation
    path = jnp.stack([L, zero, zero, zero, zero, zero, jnp.ones_like(L), s], -1)
    return jnp.sum(odometry_covariance(path, sigma_rot, sigma_trans, sigma_scale), 0)


def straight_covariance(
    S: Float[ArrayLike, "8"],
    axis: Float[ArrayLike, "3"],
    axis_variance: Float[ArrayLike, ""],
    structure_mean: Float[ArrayLike, "3"],
    scale_variance: float | Float[ArrayLike, ""],
) -> Float[Array, "7 7"]:
    """What a registration on straight structure cannot fix, as a covariance ``[7, 7]`` of its
    edge ``S`` (chunk ``a`` into chunk ``b``; tangent ``(ρ, ω, σ)``, right perturbation
    ``S exp(ξ)``, ``ρ`` in ``a``'s units).

    Structure on a line (a straight street's facades and kerbs: ``spread = λ₂ / λ₁`` small)
    maps onto itself under a slide along the line and under a scaling about a point of it, so
    the nearest-neighbour residuals, which :func:`swiftjax.align.covariance.umeyama_information`
    turns into an information as if every correspondence were right, cannot see either (the
    degenerate directions of Zhang, Kaess & Singh 2016, "On degeneracy of optimization-based
    state estimation problems", left to the other edges of the graph).  To first order
    ``S exp(ξ) x ≈ S(x + ρ + ω × x + σ x)``, so a slide by ``ℓ`` along ``b``'s axis ``d``
    and a scaling by ``e^δ`` about the structure's centroid ``m`` (``d``, ``m`` in ``b``'s
    frame; ``d_a = Rᵀ d``, ``m_a = S⁻¹ m``) are::

        ξ_slide = (ℓ d_a / s, 0, 0),   ξ_scale = δ (−m_a, 0, 1)

    Each is modelled as uniform over what the data allows: the slide over the structure's own
    length (variance ``λ₁``, the structure's variance along its axis, ``b``'s units²), the
    scale over the range the placement searched (``scale_variance``, :func:`bev_starts`'
    ``±scale_search``: ``scale_search² / 3``)::

        Σ_L = (λ₁ / s²) u uᵀ + scale_variance · v vᵀ,   u = (d_a, 0, 0),   v = (−m_a, 0, 1)

    rank two; the other five directions (across the street, height, the three rotations) keep
    the residuals' information.  Pure; float64 under ``jax_enable_x64``, else float32."""
    dtype = jnp.result_type(float)
    S = jnp.asarray(S, dtype)
    s = sim3.scale(S)
    d_a = so3.act(so3.inverse(sim3.quaternion(S)), jnp.asarray(axis, dtype))  # Rᵀ d
    m_a = sim3.act(sim3.inverse(S), jnp.asarray(structure_mean, dtype))
    zero = jnp.zeros(3, dtype)
    u = jnp.concatenate([d_a, zero, jnp.zeros(1, dtype)])
    v = jnp.concatenate([-m_a, zero, jnp.ones(1, dtype)])
    slide = jnp.asarray(axis_variance, dtype) / s**2
    return slide * jnp.outer(u, u) + jnp.asarray(scale_variance, dtype) * jnp.outer(v, v)


def _ambiguity(pl: Placements, best: Array, separation: Array, probe: Array, w_probe: Array) -> Array:
    """The structure inliers of the best placement more than ``separation`` (chunk-``b`` units,
    RMS over the probe points) away from ``S[best]``, over the best's."""
    here = sim3.act(pl.S[best], probe)
    moved = jax.vmap(
        lambda S: jnp.sqrt(
            jnp.sum(w_probe * jnp.sum((sim3.act(S, probe) - here) ** 2, -1)) / jnp.maximum(jnp.sum(w_probe), 1.0)
        )
    )(pl.S)
    alt = jnp.max(jnp.where(moved > separation, pl.scores, 0))
    return alt / jnp.maximum(pl.scores[best], 1).astype(jnp.float32)


class Covisible(NamedTuple):
    """Result of :func:`register_covisible` (batch axes ``[...]`` in front).

    Attributes:
        registration: :class:`Registration` of the best placement (``scale_ratio`` against the
            prior's scale ``σ h_b / h_a``).
        ambiguity: structure inliers of the best placement more than ``peak_separation``
            camera heights away from it, over the best's (a street slid along itself).
        scores: ``[peaks]`` structure inliers of every refined placement.
        placements: ``[peaks, 8]`` the placements (:class:`Placements`).
    """

    registration: Registration
    ambiguity: Array
    scores: Array
    placements: Array


@functools.partial(jax.jit, static_argnames=("options",))
def register_covisible(
    a: ChunkCloud,
    b: ChunkCloud,
    psi: Float[ArrayLike, ""],
    sigma: Float[ArrayLike, ""],
    tau: Float[ArrayLike, "2"],
    window: Float[ArrayLike, ""],
    options: GeometryOptions = GeometryOptions(),
) -> Covisible:
    """Register chunk ``a``'s structure onto chunk ``b``'s from a prior ``(ψ, σ, τ)``
    (:func:`edge_prior` of the odometry chain) searched within ``window`` camera heights: the
    placements of :func:`place_covisible`, the best (most structure inliers) refined on all
    rows (:func:`refine_placement`).  The pipeline runs the two steps separately, batched
    (:func:`starts_batch`, :func:`peaks_batch`, :func:`refine_batch`), refining only the candidates that pass the
    null.  Pure."""
    pl = place_covisible(a, b, psi, sigma, tau, window, options)
    k = jnp.argmax(pl.scores)
    amb = _ambiguity(pl, k, options.peak_separation * b.height, a.points[:64], a.weights[:64])
    prior_scale = jnp.asarray(sigma, jnp.float32) * b.height / a.height
    reg = refine_placement(a, b, pl.S[k], prior_scale, options)
    reg = reg._replace(valid=reg.valid & (pl.scores[k] >= 0))
    reg = reg._replace(S=jnp.where(reg.valid, reg.S, sim3.identity()))
    return Covisible(reg, amb, pl.scores, pl.S)


def covisible_reason(reg: dict, options: GeometryOptions, *, structure_null: bool = True) -> str | None:
    """Why a co-visible registration's numbers reject the candidate, in one line, or ``None``.

    ``reg`` (plain floats): ``peak_score``, the best placement's structure inliers
    (:class:`Placements`, −1 when none is valid); ``null_threshold``, the bound those reach on
    unrelated chunks at false-alarm rate ``null_false_alarm`` (None when not computable); and,
    when the candidate passed those two tests, the refined :class:`Registration`'s numbers
    (``valid``, ``scale_ratio``, ``num_structure``, ``spread``, ``rms``).  A second plausible
    placement does not reject the candidate: it widens the edge's covariance
    (:func:`placement_moments`).  ``structure_null = False``: every test but the null's (a
    sibling's registration, :mod:`swiftjax.loops.verification`, whose evidence is judged apart).
    """
    if not reg["peak_score"] >= 0:
        return "registration failed (no valid placement: every peak's Umeyama solve degenerate or not finite)"
    if not structure_null:
        return None if "valid" not in reg else _refined_reason(reg, options)
    th = reg.get("null_threshold")
    if th is None or not math.isfinite(th):
        return "registration null not computable (fewer than three unrelated chunks)"
    if not reg["peak_score"] > th:
        return (
            f"no more structure inliers than against unrelated chunks: {reg['peak_score']} <= "
            f"{th:.0f} (false-alarm rate {options.null_false_alarm:g})"
        )
    if "valid" not in reg:
        return None
    return _refined_reason(reg, options)


def _refined_reason(reg: dict, options: GeometryOptions) -> str | None:
    """The refined registration's tests of :func:`covisible_reason`: valid, scale, structure,
    residual.  Straight structure does not reject (:func:`straight_covariance`)."""
    why = _placement_reason(
        reg,
        options,
        "the refinement's Umeyama solve degenerate or not finite",
        scale_of="the odometry's",
        straight_ok=True,
    )
    if why is not None:
        return why
    if not reg["rms"] <= options.max_rms:
        return f"registration residual {reg['rms']:.3f} camera heights > {options.max_rms}"
    return None

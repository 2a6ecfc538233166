"""Metric scale from a known camera height: robust road-plane fits (pure JAX) and their combination.

A driving camera sits ``H`` metres above the road.  In a chunk's (VGGT) units the road under
frame ``f`` is a plane ``n . x = d`` in that camera's frame, ``x = D_reg(u, v) K_ref^-1 (u, v,
1)`` with the depth normalised to ``K_ref`` (eq. 1), and the camera's height is ``h_f = -d``
(``n`` points up, towards the camera: ``n . (0, -1, 0) > 0`` in OpenCV axes, so road points
have ``n . x = -h``).  The chunk's metric factor is ``m_t = H / h_t`` (metres per chunk unit)
with ``h_t`` the median of its frames' heights, and since the chunk-to-world ``S_t`` scales
chunk lengths by ``s_t``, every chunk votes ``m_t / s_t`` metres per world unit; the run's
factor is their median (:func:`combine_scales`).  Applying it (:func:`apply_scale`, ``x ->
m x`` on the world) turns every output into metres.

The alternative combination (:func:`scale_priors`, ``metric_combine = "prior"``) puts each
chunk's own factor into the pose graph as a prior on its scale: in a metric world the
chunk-to-world scale of chunk ``t`` should be ``s_t = m_t``, so the pose graph gains the
cost ``1/2 (log s_t - log m_t)^2 / sigma^2`` per chunk (a Sim(3) edge from a fixed anchor
whose information weighs only the log-scale entry of the residual, since that entry of
``log(Z^-1 S_t)`` is exactly ``log s_t - log z``; :func:`swiftjax.pipeline.graph.run`
assembles it).  A single factor cannot undo the chain's scale drift; per-chunk priors can.
Chunks whose vote ``m_t / s_t`` lies more than ``gate x max(1.4826 MAD, sigma)`` from the
median (in log) are left out: the median's robustness for gross failures (a wall taken for
the road), least squares for the rest.

Why per frame in the camera's own frame: the road bends and climbs over a 75-frame chunk,
but under one camera it is a plane, and its height needs no pose at all (a pose error
cannot leak into the scale).  Why a relative inlier band: a depth error ``eps`` moves a road
point off the plane by ``eps h`` along the normal, so ``|n . x - d| < tau |d|`` means "depth
within ``tau`` of the plane's", whatever the chunk's units.

Fit (:func:`fit_plane`): ``num_hypotheses`` RANSAC planes through 3 points drawn with
probability proportional to the weights (fixed shapes: inverse-CDF sampling), kept
only if tilted less than ``max_tilt_deg`` from ``up`` and below the camera; score = weighted
inlier count; the best is refined by ``iterations`` IRLS steps (Tukey biweight with scale
``c = 4.685 x 1.4826 MAD`` of the residuals within ``2 tau |d|``, clipped to ``[1e-3 |d|,
2 tau |d|]``, so the band adapts to the depth noise and the feet of walls and poles drop
out (docs/cli.md, "How the road plane is fitted"); weighted PCA: normal = eigenvector of the smallest eigenvalue of the weighted
covariance, ``d = n . mu``).  No boolean indexing: points that must not count have weight 0.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike
from jaxtyping import Bool, Float, Shaped
from numpy.typing import ArrayLike as HostArrayLike

from swiftjax import camera
from swiftjax.errors import SwiftjaxError

__all__ = [
    "MetricScaleError",
    "PlaneFit",
    "fit_plane",
    "ground_points",
    "GroundHeight",
    "chunk_ground_height",
    "combine_scales",
    "ScalePriors",
    "scale_priors",
    "METRIC_COMBINE",
    "apply_scale",
    "parse_metric",
]


class MetricScaleError(SwiftjaxError, ValueError):
    """The input gives no metric scale (no road seen, ...): one line saying why."""


_UP = (0.0, -1.0, 0.0)  # OpenCV camera: y points down


class PlaneFit(NamedTuple):
    """A plane ``n . x = d`` (batch shape ``[...]``).

    Attributes:
        normal: ``[..., 3]`` unit normal with ``n . up > 0``.
        offset: ``[...]`` ``d``; the camera (origin) is ``-d`` above the plane.
        inlier_fraction: ``[...]`` weighted fraction of the points within ``tau |d|`` of the plane.
        valid: ``[...]`` at least 3 weighted points, an admissible RANSAC hypothesis, and a
            finite refined plane below the origin.
    """

    normal: Array
    offset: Array
    inlier_fraction: Array
    valid: Array


def _weighted_plane(x: Array, w: Array, up: Array) -> tuple[Array, Array]:
    """Weighted least-squares plane of ``x [N, 3]``: ``(n [3], d)``; ``n`` = the smallest
    eigenvector of ``sum w (x - mu)(x - mu)^T``, oriented along ``up``."""
    W = jnp.maximum(jnp.sum(w), jnp.finfo(x.dtype).tiny)
    mu = jnp.sum(w[:, None] * x, 0) / W
    xc = x - mu
    C = jnp.einsum("n,ni,nj->ij", w, xc, xc) / W
    _, vecs = jnp.linalg.eigh(C)
    n = vecs[:, 0]
    n = jnp.where(jnp.dot(n, up) < 0, -n, n)
    return n, jnp.dot(n, mu)


def _fit_one(
    x: Array, w: Array, key: Array, up: Array, num_hypotheses: int, iterations: int, tau: Array, cos_tilt: Array
) -> PlaneFit:
    dtype = x.dtype
    ok = (w > 0) & jnp.all(jnp.isfinite(x), -1) & jnp.isfinite(w)
    w = jnp.where(ok, w, 0).astype(dtype)
    x = jnp.where(ok[:, None], x, 0)
    enough = jnp.sum(ok) >= 3
    # inverse-CDF sampling with probability w / sum w: 3 K uniforms (not K x N Gumbels)
    cdf = jnp.cumsum(w)
    u = jax.random.uniform(key, (num_hypotheses, 3), dtype) * cdf[-1]
    idx = jnp.clip(jnp.searchsorted(cdf, u, side="right"), 0, x.shape[0] - 1)
    p = x[idx]  # [K, 3, 3]
    n = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    norm = jnp.linalg.norm(n, axis=-1)
    n = n / jnp.where(norm > 0, norm, 1)[:, None]
    n = jnp.where((n @ up < 0)[:, None], -n, n)
    d = jnp.sum(n * p[:, 0], -1)
    admissible = (norm > 0) & (n @ up >= cos_tilt) & (d < 0)
    resid = jnp.abs(x @ n.T - d[None, :])  # [N, K]
    score = jnp.sum(w[:, None] * (resid < tau * jnp.abs(d)[None, :]), 0)
    score = jnp.where(admissible, score, -1)
    best = jnp.argmax(score)
    n0, d0 = n[best], d[best]

    def irls(_, nd):
        n_, d_ = nd
        band = 2 * tau * jnp.abs(d_)
        res = jnp.abs(x @ n_ - d_)
        # Tukey's scale from the points in the band: c = 4.685 x 1.4826 MAD (clipped to the band)
        in_band = (w > 0) & (res < band)
        srt = jnp.sort(jnp.where(in_band, res, jnp.inf))
        mad = srt[jnp.maximum(jnp.sum(in_band) - 1, 0) // 2]
        c = jnp.clip(4.685 * 1.4826 * mad, 1e-3 * jnp.abs(d_), band)
        r = (x @ n_ - d_) / jnp.where(c > 0, c, 1)
        rw = jnp.where(jnp.abs(r) < 1, (1 - r * r) ** 2, 0) * w
        n2, d2 = _weighted_plane(x, rw, up)
        good = (jnp.sum(rw > 0) >= 3) & jnp.all(jnp.isfinite(n2)) & jnp.isfinite(d2)
        return jnp.where(good, n2, n_), jnp.where(good, d2, d_)

    n1, d1 = jax.lax.fori_loop(0, iterations, irls, (n0, d0))
    inl = jnp.sum(w * (jnp.abs(x @ n1 - d1) < tau * jnp.abs(d1))) / jnp.maximum(jnp.sum(w), jnp.finfo(dtype).tiny)
    valid = enough & (score[best] >= 3) & jnp.all(jnp.isfinite(n1)) & jnp.isfinite(d1) & (d1 < 0)
    return PlaneFit(n1, d1, inl, valid)


@functools.partial(jax.jit, static_argnames=("num_hypotheses", "iterations"))
def fit_plane(
    points: Float[ArrayLike, "*b n 3"],
    weights: Shaped[ArrayLike, "*b n"],
    key: Shaped[ArrayLike, "..."],
    up: Float[ArrayLike, "3"] = _UP,
    *,
    num_hypotheses: int = 64,
    iterations: int = 8,
    inlier_scale: float | Float[ArrayLike, ""] = 0.05,
    max_tilt_deg: float | Float[ArrayLike, ""] = 30.0,
) -> PlaneFit:
    """Robust plane ``n . x = d`` below the origin: RANSAC + IRLS (module docstring).

    Args:
        points: ``[..., N, 3]``.
        weights: ``[..., N]`` non-negative (0: not a candidate; bool masks are cast).
        key: a ``jax.random.PRNGKey`` (``[2]`` uint32); leading batch axes get independent
            keys split from it.
        up: ``[3]`` direction the normal must be within ``max_tilt_deg`` of (default: the
            OpenCV camera's up, ``(0, -1, 0)``).
        num_hypotheses, iterations: RANSAC samples and IRLS steps (static: recompile).
        inlier_scale: ``tau``, the inlier band relative to the plane's distance ``|d|``.
        max_tilt_deg: largest admissible angle between ``n`` and ``up``.

    Returns:
        :class:`PlaneFit` with batch shape ``[...]``.  Recompiles per shape, dtype and the
        static arguments; ``inlier_scale`` and ``max_tilt_deg`` are traced.
    """
    x = jnp.asarray(points)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.float32)
    w = jnp.asarray(weights).astype(x.dtype)
    if x.shape[-1] != 3 or w.shape != x.shape[:-1]:
        raise ValueError(f"fit_plane: points {x.shape} must be [..., N, 3] and weights {w.shape} [..., N]")
    up = jnp.asarray(up, x.dtype)
    up = up / jnp.linalg.norm(up)
    tau = jnp.asarray(inlier_scale, x.dtype)
    cos_tilt = jnp.cos(jnp.deg2rad(jnp.asarray(max_tilt_deg, x.dtype)))
    batch = x.shape[:-2]
    n_items = int(np.prod(batch)) if batch else 1
    key = jnp.asarray(key)
    keys = jax.random.split(key, n_items) if batch else key[None]
    xf = x.reshape(n_items, *x.shape[-2:])
    wf = w.reshape(n_items, w.shape[-1])
    fit = jax.vmap(lambda a, b, k: _fit_one(a, b, k, up, num_hypotheses, iterations, tau, cos_tilt))(xf, wf, keys)
    return jax.tree_util.tree_map(lambda a: a.reshape(*batch, *a.shape[1:]), fit)


def ground_points(
    depth: Float[ArrayLike, "S H W"],
    conf: Float[ArrayLike, "S H W"],
    intrinsic: Float[ArrayLike, "S 3 3"],
    K_ref: Float[ArrayLike, "3 3"],
    keep: Bool[ArrayLike, "S H W"] | None = None,
    conf_ratio: float | Float[ArrayLike, ""] = 0.5,
    stride: int | tuple[int, int] = 4,
) -> tuple[Float[Array, "S h w 3"], Float[Array, "S h w"]]:
    """Candidate road points of each frame in its camera frame, on a pixel grid of ``stride``
    rows x columns (one int: both).

    ``depth, conf [S, H, W]``, ``intrinsic [S, 3, 3]`` (the frames' predicted K), ``K_ref
    [3, 3]``, ``keep [S, H, W]`` bool (user / sky masks) or ``None``.  Points are
    ``D_reg K_ref^-1 (u, v, 1)`` (eq. 1); the weight is 1 for pixels below the horizon
    (``v > cy_ref``: rays pointing down), finite, with ``conf > conf_ratio x`` the frame's
    mean confidence (eq. 2's confidence half) and kept by the mask; else 0.

    Returns ``(points [S, h, w, 3], weights [S, h, w])``, ``h = ceil(H / stride_rows)``.
    """
    depth = jnp.asarray(depth)
    conf = jnp.asarray(conf, depth.dtype)
    K_ref = jnp.asarray(K_ref, depth.dtype)
    sv, su = (stride, stride) if isinstance(stride, int) else stride
    sub = (slice(None), slice(None, None, sv), slice(None, None, su))
    scale_px = jnp.diag(jnp.array([1.0 / su, 1.0 / sv, 1.0], depth.dtype))
    Ks = scale_px @ K_ref
    d = camera.normalize_depth(depth[sub], jnp.asarray(intrinsic, depth.dtype), K_ref)
    pts = camera.unproject(d, Ks)
    c = conf[sub]
    fin = jnp.isfinite(c)
    mean = jnp.sum(jnp.where(fin, c, 0), (-2, -1)) / jnp.maximum(jnp.sum(fin, (-2, -1)), 1)
    w = fin & (c > jnp.asarray(conf_ratio, c.dtype) * mean[:, None, None]) & jnp.all(jnp.isfinite(pts), -1)
    w = w & (pts[..., 1] > 0)
    if keep is not None:
        w = w & jnp.asarray(keep, bool)[sub]
    return pts, w.astype(depth.dtype)


class GroundHeight(NamedTuple):
    """Camera height above the road in a chunk's units.

    Attributes:
        height: ``[]`` median of the valid frames' heights (NaN if none).
        frame_heights: ``[S]`` ``-d`` of each frame's plane (NaN where invalid).
        num_valid: ``[]`` int32 frames with a valid plane.
        inlier_fraction: ``[S]``.
    """

    height: Array
    frame_heights: Array
    num_valid: Array
    inlier_fraction: Array


@functools.partial(jax.jit, static_argnames=("stride", "frame_stride", "num_hypotheses", "iterations"))
def chunk_ground_height(
    depth: Float[ArrayLike, "S H W"],
    conf: Float[ArrayLike, "S H W"],
    intrinsic: Float[ArrayLike, "S 3 3"],
    K_ref: Float[ArrayLike, "3 3"],
    keep: Bool[ArrayLike, "S H W"] | None = None,
    key: Shaped[ArrayLike, "..."] | None = None,
    *,
    conf_ratio: float | Float[ArrayLike, ""] = 0.5,
    stride: int | tuple[int, int] = (4, 8),
    frame_stride: int = 5,
    num_hypotheses: int = 64,
    iterations: int = 8,
    inlier_scale: float | Float[ArrayLike, ""] = 0.05,
    max_tilt_deg: float | Float[ArrayLike, ""] = 30.0,
) -> GroundHeight:
    """The camera's height above the road in a chunk: per-frame :func:`fit_plane` on
    :func:`ground_points` of every ``frame_stride``-th frame, then the median over them.

    Shapes as :func:`ground_points` (``frame_heights`` / ``inlier_fraction`` are
    ``[ceil(S / frame_stride)]``).  Defaults: every 5th frame, 4 x 8-pixel grid (at 518 x 154:
    ~1,300 candidates below the horizon), 64 hypotheses.  One jitted
    call; recompiles per ``(S, H, W)``, dtype, ``keep`` given or not, and the static
    arguments.  ``key`` defaults to ``PRNGKey(0)`` (deterministic)."""
    fs = slice(None, None, frame_stride)
    keep = None if keep is None else jnp.asarray(keep)[fs]
    pts, w = ground_points(
        jnp.asarray(depth)[fs], jnp.asarray(conf)[fs], jnp.asarray(intrinsic)[fs], K_ref, keep, conf_ratio, stride
    )
    S = pts.shape[0]
    key = jax.random.PRNGKey(0) if key is None else key
    fit = fit_plane(
        pts.reshape(S, -1, 3),
        w.reshape(S, -1),
        key,
        num_hypotheses=num_hypotheses,
        iterations=iterations,
        inlier_scale=inlier_scale,
        max_tilt_deg=max_tilt_deg,
    )
    h = jnp.where(fit.valid, -fit.offset, jnp.nan)
    return GroundHeight(jnp.nanmedian(h), h, jnp.sum(fit.valid).astype(jnp.int32), fit.inlier_fraction)


def combine_scales(
    chunk_heights: HostArrayLike, chunk_scales: HostArrayLike, camera_height: float
) -> tuple[float, dict]:
    """Metres per world unit from every chunk's ground height: ``median_t (H / h_t / s_t)``.

    ``chunk_heights [T]`` (chunk units; NaN: no road seen), ``chunk_scales [T]`` the scales
    ``s_t`` of the chunk-to-world poses.  Host NumPy (T numbers).  Returns ``(m, stats)``
    with ``stats`` = number of voting chunks and the relative spread (MAD / median) of the
    votes.  Raises ``ValueError`` when no chunk saw the road.
    """
    h = np.asarray(chunk_heights, np.float64)
    s = np.asarray(chunk_scales, np.float64)
    votes = camera_height / (h * s)
    ok = np.isfinite(votes) & (votes > 0)
    if not np.any(ok):
        raise MetricScaleError("--metric camera-height: no chunk has a valid road-plane fit (is the road visible?)")
    v = votes[ok]
    m = float(np.median(v))
    mad = float(np.median(np.abs(v - m)))
    return m, {"chunks_voting": int(ok.sum()), "chunks": int(h.size), "relative_mad": mad / m}


#: How the chunks' metric factors are combined (``metric_combine``; module docstring).
METRIC_COMBINE = ("median", "prior")


class ScalePriors(NamedTuple):
    """Per-chunk scale priors of a metric pose graph (host NumPy, ``[T]`` each).

    Attributes:
        log_scale: ``log m_t = log(H / h_t)``, the chunk's metres per chunk unit (NaN: unused).
        weight: ``1 / sigma^2`` on ``log s_t`` (0: unused).
        used: chunks with a prior (a valid road fit that passed the gate).
        start_factor: the median vote ``median_t m_t / s_t`` (:func:`combine_scales`): metres per
            world unit of the given poses, to start the solve from a metric world.
        stats: ``chunks``, ``chunks_voting``, ``chunks_gated`` (left out as gross outliers),
            ``relative_mad`` of the votes, ``sigma``, ``gate``.
    """

    log_scale: np.ndarray
    weight: np.ndarray
    used: np.ndarray
    start_factor: float
    stats: dict


def scale_priors(
    chunk_heights: HostArrayLike, chunk_scales: HostArrayLike, camera_height: float, sigma: float, gate: float = 5.0
) -> ScalePriors:
    """The pose-graph scale priors of ``metric_combine = "prior"`` (module docstring).

    ``chunk_heights [T]`` ground heights in chunk units (NaN: no road), ``chunk_scales [T]`` the
    scales ``s_t`` of the poses the solve starts from, ``camera_height`` ``H`` in metres,
    ``sigma`` the standard deviation of one chunk's ``log m_t`` (> 0), ``gate`` the outlier
    gate in robust standard deviations.  Raises ``ValueError`` when no chunk saw the road.
    """
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"scale_priors: sigma must be > 0, got {sigma!r}")
    h = np.asarray(chunk_heights, np.float64)
    s = np.asarray(chunk_scales, np.float64)
    start, stats = combine_scales(h, s, camera_height)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_m = np.log(camera_height / h)
        dev = np.abs(log_m - np.log(s) - np.log(start))
    ok = np.isfinite(log_m) & (h > 0)
    mad = float(np.median(dev[ok]))
    used = ok & (dev <= gate * max(1.4826 * mad, sigma))
    weight = np.where(used, 1.0 / sigma**2, 0.0)
    stats = {**stats, "chunks_gated": int(ok.sum() - used.sum()), "sigma": float(sigma), "gate": float(gate)}
    return ScalePriors(np.where(used, log_m, np.nan), weight, used, start, stats)


def apply_scale(poses: HostArrayLike, m: float) -> Float[np.ndarray, "*b 8"]:
    """``M_m o S`` for Sim(3) poses ``[..., 8]``: translation and scale times ``m`` (the world
    stretched by ``m``; rotations unchanged).  Host NumPy float64."""
    S = np.array(poses, np.float64, copy=True)
    S[..., :3] *= m
    S[..., 7] *= m
    return S


def parse_metric(value: str | None) -> tuple[str, float | None] | None:
    """``None``, ``"gt"``, ``"model"`` (a metric network's own metres) or ``"camera-height=H"``
    (metres > 0) -> ``(kind, H)``; ``ValueError`` otherwise."""
    if value is None or value == "" or value == "none":
        return None
    if value == "gt":
        return ("gt", None)
    if value == "model":
        return ("model", None)
    if value.startswith("camera-height="):
        try:
            h = float(value.split("=", 1)[1])
        except ValueError:
            h = float("nan")
        if not (np.isfinite(h) and h > 0):
            raise ValueError(f"--metric camera-height=H needs a height in metres > 0, got {value!r}")
        return ("camera-height", h)
    raise ValueError(f"--metric must be 'camera-height=H' (metres), 'gt' or 'model', got {value!r}")

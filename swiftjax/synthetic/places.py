"""Synthetic DINO-like patch tokens that carry a place signal, for loop-detection benchmarks.

Tokens with what the SwiftVGGT paper relies on and fights against: a place signal that
depends smoothly on position *and* heading, a strong shared direction ("dataset bias", the
hubness the whitening drops), bursts (what the power normalisation compresses) and per-token
noise (why each: docs/design.md, "Synthetic place tokens").

Token ``k`` of a frame with camera centre ``p`` (metres) and optical axis ``v`` (unit vector,
world frame), global frame id ``f``::

    x_k = a_place · (sqrt(1 - rho) · phi_0(p, v) + sqrt(rho) · phi_k(p, v))
          + (b + b_jit · eps_f) · u  +  burst_f  +  sigma · n_{f,k} / sqrt(d)

    phi_k(p, v) = sqrt(2/d) · cos(Omega_k^p p + Omega_k^v v + c_k)    k = 0..K  (random Fourier features)
    Omega_k^p ~ N(0, I / l_p^2),  Omega_k^v ~ N(0, I / l_v^2),  c_k ~ U[0, 2 pi)

so ``E[phi_k(x) · phi_k(y)] = exp(-|p_x - p_y|^2 / (2 l_p^2) - |v_x - v_y|^2 / (2 l_v^2))``
(|v_x - v_y| ≈ the angle between the two optical axes, in radians, for small angles) and
``|phi_k| ≈ 1``.  ``phi_0`` is the part of the place every patch sees (its mean over patches),
each token index ``k >= 1`` adds its own field (different patches see different things) with
weight ``rho`` (``token_diversity``).  ``u`` is a fixed random unit vector; ``eps_f ~ N(0, 1)``;
``burst_f = s_burst · m_f ⊙ eta_f / sqrt(p_burst d)`` with ``m_f ~ Bernoulli(p_burst)^d`` and
``eta_f ~ N(0, I)``; ``n_{f,k} ~ N(0, I)``.

**Perceptual aliasing** (optional; off by default): look-alike places, pairs of far-apart route
segments ``(s_a, s_b, L)`` (``aliasing``) whose frames share a place component of strength
``lambda`` (``alias_strength``).  Frame ``f = s_a + t`` and frame ``s_b + t`` (``0 <= t < L``) both
replace their place component ``phi(p, v)`` by::

    sqrt(1 - lambda) · phi(p_f, v_f)  +  sqrt(lambda) · phi(q_m(t), e_z)
    q_m(t) = (t, 5000 + 100 m, 0) metres       (segment pair m: a virtual street, 1 m per frame)

so the noise-free place components of two corresponding frames have expected cosine
``lambda`` (``lambda = 1``: a full copy).  :func:`plant_aliasing` chooses the segments
deterministically for a trajectory at a rate relative to its true loop regions; the planted
pairs are false loops by construction.  To turn it on::

    segs = plant_aliasing(cam_to_world, rate=0.3)              # ~30 % extra false candidates
    cfg = PlaceTokenConfig(aliasing=segs)                      # alias_strength 0.9
    # or: swiftjax.synthetic.demo.loop_route_run(aliasing=0.3) / trajectory_run(..., aliasing=0.3)

Everything random about a frame is keyed by its **global frame id** (``jax.random.fold_in``):
:func:`place_tokens` is stateless, so a frame in a temporal and in a loop-centric chunk gets
bit-identical tokens.  Host-level ground truth for the benchmark: :func:`ground_truth_loops`,
:func:`loop_regions`, :func:`evaluate_loops` (precision and region recall).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "PlaceTokenConfig",
    "PlaceTokenParams",
    "make_place_params",
    "place_tokens",
    "place_signal",
    "camera_centres_and_axes",
    "ground_truth_loops",
    "loop_regions",
    "revisit_regions",
    "LoopEvaluation",
    "evaluate_loops",
    "plant_aliasing",
    "DEFAULT_ALIAS_STRENGTH",
]

#: ``lambda`` of the planted look-alike places unless set: their candidates then score like
#: true revisits (KITTI 00: 0.50-0.59 against 0.32-0.79; 0.8 left some below 0.43).
DEFAULT_ALIAS_STRENGTH = 0.9


@dataclasses.dataclass(frozen=True)
class PlaceTokenConfig:
    """Static description of the synthetic token distribution (see the module docstring).

    Attributes:
        dim: token dimension ``d`` (DINOv2-L / VGGT: 1024).
        tokens_per_frame: ``K`` tokens per frame (VGGT on KITTI: 407; the oracle uses 8-16).
        length_scale_m: ``l_p``, place-signal correlation length in metres.
        length_scale_rad: ``l_v``, place-signal correlation length of the viewing direction,
            in radians.
        place_strength: ``a_place`` (the place signal has norm ≈ ``a_place`` per token).
        token_diversity: ``rho`` in ``[0, 1]``, share of the place signal specific to each
            token (0: all tokens carry the same place vector).
        bias_strength: ``b``, mean amplitude of the shared direction ``u``.
        bias_jitter: ``b_jit``, per-frame standard deviation of that amplitude.
        burst_strength: ``s_burst``, expected norm of the per-frame burst vector.
        burst_fraction: ``p_burst``, fraction of coordinates that burst in a frame.
        noise: ``sigma``, expected norm of the per-token i.i.d. noise.
        seed: seed of the fixed random field, bias direction and noise stream.
        aliasing: look-alike segment pairs ``((s_a, s_b, L), ...)`` of global frame ids
            (module docstring; :func:`plant_aliasing`); ``()``: none.
        alias_strength: ``lambda`` in ``[0, 1]``, the shared share of their place component.
    """

    dim: int = 1024
    tokens_per_frame: int = 16
    length_scale_m: float = 4.0
    length_scale_rad: float = 0.35
    place_strength: float = 1.0
    token_diversity: float = 0.5
    bias_strength: float = 3.0
    bias_jitter: float = 1.0
    burst_strength: float = 1.5
    burst_fraction: float = 0.01
    noise: float = 1.0
    seed: int = 0
    aliasing: tuple[tuple[int, int, int], ...] = ()
    alias_strength: float = DEFAULT_ALIAS_STRENGTH


class PlaceTokenParams(NamedTuple):
    """The arrays of one synthetic token distribution (a pytree; pass it through ``jit``).

    Attributes:
        position_freqs: ``[K + 1, d, 3]`` ``Omega^p`` (1/metres); row 0 is the shared field.
        direction_freqs: ``[K + 1, d, 3]`` ``Omega^v`` (1/radians).
        phases: ``[K + 1, d]`` ``c``.
        bias_direction: ``[d]`` unit vector ``u``.
        noise_key: ``[2]`` uint32 raw PRNG key of the per-frame stream.
        scalars: ``[8]`` float32 ``(a_place, b, b_jit, s_burst, p_burst, sigma, rho, lambda)``.
        alias_segments: ``[P, 3]`` int32 look-alike segment pairs ``(s_a, s_b, L)``
            (``P = 0``: no aliasing; ``P`` is a shape, so it is part of the compile key).
    """

    position_freqs: jax.Array
    direction_freqs: jax.Array
    phases: jax.Array
    bias_direction: jax.Array
    noise_key: jax.Array
    scalars: jax.Array
    alias_segments: jax.Array


def _check_aliasing(segments, strength: float) -> np.ndarray:
    segs = np.asarray(segments, np.int64).reshape(-1, 3)
    if not 0.0 <= strength <= 1.0:
        raise ValueError(f"alias_strength must be in [0, 1], got {strength}")
    if len(segs) == 0:
        return segs
    if np.any(segs[:, :2] < 0) or np.any(segs[:, 2] < 1):
        raise ValueError(f"aliasing segments need s_a, s_b >= 0 and L >= 1, got {segs.tolist()}")
    iv = np.concatenate([segs[:, [0, 2]], segs[:, [1, 2]]])  # (start, length) of every segment
    iv = iv[np.argsort(iv[:, 0])]
    if np.any(iv[1:, 0] < iv[:-1, 0] + iv[:-1, 1]):
        raise ValueError(f"aliasing segments overlap (a frame may look like one other place only): {segs.tolist()}")
    return segs


def make_place_params(config: PlaceTokenConfig = PlaceTokenConfig()) -> PlaceTokenParams:
    """Draw the fixed parts of the distribution (field frequencies, bias direction) from ``seed``.

    Host-level; raises ``ValueError`` for non-positive dimensions or length scales, negative
    strengths, or ``burst_fraction`` outside ``(0, 1]``.
    """
    c = config
    if c.dim < 1 or c.tokens_per_frame < 1:
        raise ValueError(f"dim and tokens_per_frame must be >= 1, got {c.dim}, {c.tokens_per_frame}")
    if not (c.length_scale_m > 0 and c.length_scale_rad > 0):
        raise ValueError(
            f"length scales must be > 0, got length_scale_m={c.length_scale_m}, length_scale_rad={c.length_scale_rad}"
        )
    for name in ("place_strength", "bias_strength", "bias_jitter", "burst_strength", "noise"):
        if getattr(c, name) < 0:
            raise ValueError(f"{name} must be >= 0, got {getattr(c, name)}")
    if not 0 <= c.token_diversity <= 1:
        raise ValueError(f"token_diversity must be in [0, 1], got {c.token_diversity}")
    if not 0 < c.burst_fraction <= 1:
        raise ValueError(f"burst_fraction must be in (0, 1], got {c.burst_fraction}")
    segs = _check_aliasing(c.aliasing, c.alias_strength)
    k_pos, k_dir, k_phase, k_bias, k_noise = jax.random.split(jax.random.PRNGKey(c.seed), 5)
    shape = (c.tokens_per_frame + 1, c.dim, 3)
    bias = jax.random.normal(k_bias, (c.dim,), jnp.float32)
    return PlaceTokenParams(
        position_freqs=jax.random.normal(k_pos, shape, jnp.float32) / c.length_scale_m,
        direction_freqs=jax.random.normal(k_dir, shape, jnp.float32) / c.length_scale_rad,
        phases=jax.random.uniform(k_phase, shape[:2], jnp.float32, 0.0, 2 * np.pi),
        bias_direction=bias / jnp.linalg.norm(bias),
        noise_key=jnp.asarray(jax.random.key_data(k_noise), jnp.uint32),
        scalars=jnp.asarray(
            [
                c.place_strength,
                c.bias_strength,
                c.bias_jitter,
                c.burst_strength,
                c.burst_fraction,
                c.noise,
                c.token_diversity,
                c.alias_strength,
            ],
            jnp.float32,
        ),
        alias_segments=jnp.asarray(segs, jnp.int32).reshape(-1, 3),
    )


def camera_centres_and_axes(cam_to_world: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``[..., 3|4, 4]`` camera-to-world → centres ``[..., 3]`` and optical axes ``[..., 3]``.

    The optical axis is the camera's +z (OpenCV) in world coordinates, ``R[:, 2]``.
    """
    m = jnp.asarray(cam_to_world)
    return m[..., :3, 3], m[..., :3, 2]


def place_signal(params: PlaceTokenParams, cam_to_world: jax.Array) -> jax.Array:
    """The noise-free place component ``sqrt(1 - rho) phi_0 + sqrt(rho) phi_k``, ``k = 1..K``:
    ``[S, 3|4, 4]`` → ``[S, K, d]`` float32 (without the factor ``a_place``).

    ``E[<phi_k(x), phi_k(y)>]`` is the squared-exponential kernel of the module docstring.
    """
    p, v = camera_centres_and_axes(jnp.asarray(cam_to_world, jnp.float32))
    arg = (
        jnp.einsum("kdc,sc->skd", params.position_freqs, p)
        + jnp.einsum("kdc,sc->skd", params.direction_freqs, v)
        + params.phases
    )
    d = params.phases.shape[-1]
    phi = jnp.sqrt(2.0 / d) * jnp.cos(arg)
    rho = params.scalars[6]
    return jnp.sqrt(1.0 - rho) * phi[:, :1] + jnp.sqrt(rho) * phi[:, 1:]


def _frame_extras(params: PlaceTokenParams, frame_id: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Per-frame bias+burst vector ``[d]`` and per-token noise ``[K, d]`` for one frame id."""
    _, b, b_jit, s_burst, p_burst, sigma = params.scalars[:6]
    k_count, d = params.phases.shape
    k_count -= 1
    key = jax.random.fold_in(jax.random.wrap_key_data(params.noise_key), frame_id)
    k_eps, k_mask, k_eta, k_noise = jax.random.split(key, 4)
    eps = jax.random.normal(k_eps, (), jnp.float32)
    mask = jax.random.uniform(k_mask, (d,), jnp.float32) < p_burst
    eta = jax.random.normal(k_eta, (d,), jnp.float32)
    burst = s_burst * jnp.where(mask, eta, 0.0) / jnp.sqrt(p_burst * d)
    shared = (b + b_jit * eps) * params.bias_direction + burst
    noise = sigma * jax.random.normal(k_noise, (k_count, d), jnp.float32) / jnp.sqrt(d)
    return shared, noise


def _alias_share(params: PlaceTokenParams, frame_ids: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Per frame ``lambda`` (0 outside every look-alike segment) and the virtual pose
    ``[S, 4, 4]`` of the shared place (module docstring)."""
    seg = params.alias_segments  # [P, 3]
    f = frame_ids[:, None]
    ta, tb = f - seg[None, :, 0], f - seg[None, :, 1]
    in_a = (ta >= 0) & (ta < seg[None, :, 2])
    in_b = (tb >= 0) & (tb < seg[None, :, 2])
    hit = in_a | in_b  # [S, P]; at most one True per row (segments are disjoint)
    m = jnp.argmax(hit, axis=1)
    t = jnp.where(
        jnp.take_along_axis(in_a, m[:, None], 1)[:, 0],
        jnp.take_along_axis(ta, m[:, None], 1)[:, 0],
        jnp.take_along_axis(tb, m[:, None], 1)[:, 0],
    )
    lam = jnp.where(jnp.any(hit, axis=1), params.scalars[7], 0.0)
    S = frame_ids.shape[0]
    virtual = jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), (S, 4, 4))
    centre = jnp.stack([t.astype(jnp.float32), 5000.0 + 100.0 * m.astype(jnp.float32), jnp.zeros(S)], -1)
    return lam, virtual.at[:, :3, 3].set(centre)


@jax.jit
def place_tokens(params: PlaceTokenParams, cam_to_world: jax.Array, frame_ids: jax.Array) -> jax.Array:
    """Synthetic patch tokens ``[S, K, d]`` float32 for ``S`` cameras (module docstring formula).

    Args:
        params: :class:`PlaceTokenParams` from :func:`make_place_params`.
        cam_to_world: ``[S, 4, 4]`` (or ``[S, 3, 4]``) camera-to-world poses in a fixed world
            frame, metres.
        frame_ids: ``[S]`` int global frame ids; they key all per-frame randomness, so a frame
            gets the same tokens whichever chunk it is generated in.

    Pure and jit-compiled; recompiles for each new ``S`` (and ``K``, ``d``, number of
    look-alike segment pairs).
    """
    a_place = params.scalars[0]
    frame_ids = jnp.asarray(frame_ids, jnp.int32)
    signal = place_signal(params, cam_to_world)
    if params.alias_segments.shape[0]:  # static: no aliasing, no extra work
        lam, virtual = _alias_share(params, frame_ids)
        # a second field evaluation only for a batch that holds a look-alike frame
        signal = jax.lax.cond(
            jnp.any(lam > 0.0),
            lambda sig: (
                jnp.sqrt(1.0 - lam)[:, None, None] * sig + jnp.sqrt(lam)[:, None, None] * place_signal(params, virtual)
            ),
            lambda sig: sig,
            signal,
        )
    shared, noise = jax.vmap(_frame_extras, in_axes=(None, 0))(params, frame_ids)
    return a_place * signal + shared[:, None, :] + noise


# ----------------------------------------------------------------------------- ground truth


def _np_centres_axes(cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    m = np.asarray(cam_to_world, np.float64)
    if m.ndim != 3 or m.shape[1:] not in ((3, 4), (4, 4)):
        raise ValueError(f"cam_to_world must have shape [N, 3|4, 4], got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError("cam_to_world contains NaN or Inf")
    return m[:, :3, 3], m[:, :3, 2]


def ground_truth_loops(
    cam_to_world: np.ndarray,
    max_distance: float = 5.0,
    max_angle_deg: float = 30.0,
    min_separation: int = 100,
    direction: str = "same",
) -> np.ndarray:
    """True loop pairs of a trajectory: ``[M, 2]`` int64 ``(i, j)``, ``i > j``, sorted.

    A pair is a loop when the camera centres are closer than ``max_distance`` metres and
    ``i - j > min_separation`` frames, and its optical axes ``v_i, v_j`` fit ``direction``:
    ``"same"`` (the default): they differ by less than ``max_angle_deg`` (``v_i · v_j >
    cos``), a revisit driven the same way; ``"reverse"``: by more than ``180° −
    max_angle_deg`` (``v_i · v_j < −cos``), the street driven the other way (KITTI 08's
    revisits); ``"any"``: either.  (A car parked for more than ``min_separation`` frames would
    also qualify; KITTI 00 has no such stop.)  Host-level (scipy KD-tree), O(N log N + M).
    """
    from scipy.spatial import cKDTree

    if direction not in ("same", "reverse", "any"):
        raise ValueError(f"direction must be 'same', 'reverse' or 'any', got {direction!r}")
    p, v = _np_centres_axes(cam_to_world)
    pairs = cKDTree(p).query_pairs(max_distance, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), np.int64)
    pairs = np.sort(pairs, axis=1)[:, ::-1].astype(np.int64)  # i > j
    cos = np.einsum("nc,nc->n", v[pairs[:, 0]], v[pairs[:, 1]])
    dist = np.linalg.norm(p[pairs[:, 0]] - p[pairs[:, 1]], axis=1)  # strict: the tree uses <=
    c = np.cos(np.deg2rad(max_angle_deg))
    heading = {"same": cos > c, "reverse": cos < -c, "any": (cos > c) | (cos < -c)}[direction]
    keep = (dist < max_distance) & heading & (pairs[:, 0] - pairs[:, 1] > min_separation)
    pairs = pairs[keep]
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def revisit_regions(
    cam_to_world: np.ndarray,
    max_distance: float = 5.0,
    max_angle_deg: float = 30.0,
    min_separation: int = 100,
    radius: int = 25,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Same-direction and reverse revisits counted separately: ``{"same": (pairs, regions),
    "reverse": (pairs, regions)}``, each :func:`ground_truth_loops` with that ``direction``
    and its :func:`loop_regions` labels."""
    out = {}
    for direction in ("same", "reverse"):
        pairs = ground_truth_loops(cam_to_world, max_distance, max_angle_deg, min_separation, direction)
        out[direction] = (pairs, loop_regions(pairs, radius))
    return out


def loop_regions(pairs: np.ndarray, radius: int = 25) -> np.ndarray:
    """Label each pair with its loop region: ``[M]`` int, ``0 .. R-1``.

    Two pairs are in one region when they are connected by a chain of pairs each within
    ``radius`` frames of the next at both ends (Chebyshev distance in ``(i, j)``).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = np.asarray(pairs).reshape(-1, 2)
    m = len(pairs)
    if m == 0:
        return np.zeros((0,), np.int64)
    edges = cKDTree(pairs.astype(np.float64)).query_pairs(radius, p=np.inf, output_type="ndarray")
    graph = (
        coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(m, m))
        if len(edges)
        else coo_matrix((m, m))
    )
    return connected_components(graph, directed=False)[1].astype(np.int64)


class LoopEvaluation(NamedTuple):
    """Scores of a detected loop list against ground truth (host-level NumPy).

    Attributes:
        precision: correct detections / detections (1.0 when nothing is detected).
        region_recall: fraction of ground-truth loop regions with at least one correct
            detection.
        n_detected, n_correct: detection counts.
        n_regions, n_regions_found: ground-truth region counts.
        correct: ``[D]`` bool, per detection.
    """

    precision: float
    region_recall: float
    n_detected: int
    n_correct: int
    n_regions: int
    n_regions_found: int
    correct: np.ndarray


def evaluate_loops(
    detected: np.ndarray, gt_pairs: np.ndarray, tolerance: int = 25, regions: np.ndarray | None = None
) -> LoopEvaluation:
    """A detection ``(i, j)`` is correct when some true pair ``(a, b)`` has ``|i-a| <= tolerance``
    and ``|j-b| <= tolerance`` (either orientation of the detected pair is accepted).

    ``regions`` are :func:`loop_regions` labels of ``gt_pairs`` (computed when omitted).
    """
    from scipy.spatial import cKDTree

    det = np.asarray(detected, np.int64).reshape(-1, 2)
    det = np.stack([det.max(1), det.min(1)], 1)
    gt = np.asarray(gt_pairs, np.int64).reshape(-1, 2)
    if regions is None:
        regions = loop_regions(gt, tolerance)
    n_regions = int(regions.max()) + 1 if len(regions) else 0
    if len(det) == 0 or len(gt) == 0:
        return LoopEvaluation(
            1.0 if len(det) == 0 else 0.0,
            0.0 if n_regions else 1.0,
            len(det),
            0,
            n_regions,
            0,
            np.zeros(len(det), bool),
        )
    tree = cKDTree(gt.astype(np.float64))
    near = tree.query_ball_point(det.astype(np.float64), tolerance, p=np.inf)
    correct = np.array([len(n) > 0 for n in near])
    found = set()
    for n in near:
        found.update(int(r) for r in regions[n])
    n_found = len(found)
    return LoopEvaluation(
        precision=float(correct.mean()),
        region_recall=n_found / n_regions,
        n_detected=len(det),
        n_correct=int(correct.sum()),
        n_regions=n_regions,
        n_regions_found=n_found,
        correct=correct,
    )


def plant_aliasing(
    cam_to_world: np.ndarray,
    rate: float,
    *,
    length: int = 20,
    chunk_stride: int = 45,
    nms_radius: int = 25,
    min_distance_m: float = 50.0,
    min_separation: int = 100,
    margin: int = 30,
    gap: int = 10,
    seed: int = 0,
    strict: bool = True,
) -> tuple[tuple[int, int, int], ...]:
    """Look-alike segment pairs for :class:`PlaceTokenConfig` ``aliasing``, deterministic per ``seed``.

    The number of pairs is ``round(rate · C_true)`` (at least one for ``rate > 0`` when the
    trajectory has a true loop; none without one), ``C_true`` an estimate of the true
    candidates the detector returns: the :func:`ground_truth_loops` pairs thinned as the
    detector's pair NMS does (closest cameras first, suppressing pairs within ``nms_radius``
    frames at both ends), then counted once per chunk pair ``(c_i, c_j)``, ``|c_i - c_j| >= 2``
    (frame ``f`` in chunk ``round((f - 37) / chunk_stride)``, the default schedule B = 75,
    O = 30).  A look-alike pair of ``length = 20`` frames yields about one candidate, so
    ``rate`` is the planted false candidates relative to the true ones (0.1, 0.3, 0.5: 10, 30,
    50 % extra).  The realised count of false candidates is decided by NMS, the chunk filter
    and the threshold, so report it (KITTI 00's numbers: docs/performance/synthetic.md).
    Each pair ``(s_a, s_b, length)``: ``s_a > s_b``, more than
    ``min_separation + length`` frames apart, every camera of one segment more than
    ``min_distance_m`` from every camera of the other (a false loop), every pair
    ``(s_a + t, s_b + t)`` more than ``margin`` frames (Chebyshev, both ends) from every true
    loop pair (so :func:`evaluate_loops` never counts its candidates as correct; a segment
    may lie inside a true loop region's frames), and no segment within ``gap`` frames of
    another planted segment.  Drawn by rejection
    sampling from ``numpy.random.default_rng(seed)``.  ``strict=False`` returns the pairs that
    fit instead of raising when there is no room for all of them.

    Raises:
        ValueError: ``rate < 0``, ``length < 1``, or (``strict``) no room for the pairs.
    """
    p, _ = _np_centres_axes(cam_to_world)
    if not rate >= 0 or length < 1:
        raise ValueError(f"plant_aliasing needs rate >= 0 and length >= 1, got rate={rate}, length={length}")
    n = len(p)
    gt = ground_truth_loops(cam_to_world)
    dist = np.linalg.norm(p[gt[:, 0]] - p[gt[:, 1]], axis=1)
    alive = np.ones(len(gt), bool)
    kept = []
    for k in np.argsort(dist, kind="stable"):
        if alive[k]:
            kept.append(k)
            alive &= ~((np.abs(gt[:, 0] - gt[k, 0]) <= nms_radius) & (np.abs(gt[:, 1] - gt[k, 1]) <= nms_radius))
    chunk = np.maximum(np.round((gt[kept].reshape(-1, 2) - 37) / chunk_stride), 0).astype(np.int64)
    c_true = len({(a, b) for a, b in chunk.tolist() if abs(a - b) >= 2})
    if rate == 0 or c_true == 0:
        return ()
    count = max(1, int(round(rate * c_true)))
    from scipy.spatial import cKDTree

    tree = cKDTree(np.concatenate([gt, gt[:, ::-1]]).astype(np.float64))
    busy = np.zeros(n + 2 * gap, bool)  # frames near planted segments (padded by gap)

    def free(s: int) -> bool:
        return not busy[s : s + length + 2 * gap].any()

    rng = np.random.default_rng(seed)
    out: list[tuple[int, int, int]] = []
    for _ in range(20_000):
        if len(out) == count:
            break
        a, b = sorted(rng.integers(0, n - length + 1, 2).tolist(), reverse=True)
        if a - b <= min_separation + length or not (free(a) and free(b)):
            continue
        d = np.linalg.norm(p[a : a + length, None] - p[None, b : b + length], axis=-1)
        if d.min() <= min_distance_m:
            continue
        t = np.arange(length)
        near = tree.query_ball_point(np.stack([a + t, b + t], 1).astype(np.float64), margin, p=np.inf)
        if any(len(x) for x in near):
            continue
        out.append((int(a), int(b), int(length)))
        for s in (a, b):
            busy[s : s + length + 2 * gap] = True
    if len(out) < count:
        if not strict:
            return tuple(sorted(out))
        raise ValueError(
            f"plant_aliasing: room for only {len(out)} of {count} look-alike pairs of {length} frames "
            f"in {n} frames (rate={rate}); lower rate, length, min_distance_m or margin"
        )
    return tuple(sorted(out))

"""A "VGGT oracle": what VGGT returns for a chunk of frames, from a world whose truth we know.

``VGGTOracle(world, cam_to_world, K, image_hw, noise, seed).predict_chunk(frames)`` returns
the :class:`~swiftjax.prediction.ChunkPrediction` arrays the real runners return, with
VGGT's kinds of error.  Notation: chunk frames ``f_0 .. f_{S-1}`` (``frames``), true
camera-to-world ``T_k = [R_k | c_k]``, true depth ``z`` (metres), chunk index ``k``.

**Gauge** (what VGGT normalises away).  Chunk coordinates are the first camera's frame
scaled by ``sigma_c = depth_units / mean(z) * exp(scale_jitter * n_c)`` (mean over the
chunk's finite true depths): ``x_c = sigma_c R_0^T (x_w - c_0)``.  The TRUE chunk-to-world
Sim(3) is ``G_c = (t = c_0, R = R_0, s = 1 / sigma_c)`` (:meth:`VGGTOracle.true_chunk_gauge`).

**Poses.**  True camera-to-chunk ``(R_0^T R_k, sigma_c R_0^T (c_k - c_0))`` warped by a slow
drift ``D_k = (exp(k w_c), scale exp(k delta_c))`` (rotation about the chunk origin and a
scale that creeps along the chunk; ``w_c ~ N(0, drift_rot^2 I)``, ``delta_c ~ N(0,
drift_scale^2)`` per chunk), then per-frame jitter (rotation ``pose_rot`` rad, translation
``pose_trans`` chunk units); frame 0 stays exactly at the origin.  The depth of frame ``k``
carries the drift scale ``exp(k delta_c)``, so the frame's points move with its camera (the
chunk's geometry is consistently warped, which is what makes chunk-to-chunk alignment drift).

**Intrinsics.**  ``fx, fy <- (1 + eps_f) fx, fy`` with ``eps_f`` uniform in
``+-focal`` (principal point exact), and the frame's depth multiplied by
``(1 + eps_f)^focal_depth_coupling`` (VGGT's zoom ambiguity: a larger focal comes with a larger
depth; the paper's depth normalisation eq. 1 undoes exactly this).

**Depth.**  ``d = z sigma_c s_k (1+eps_f) (1 + bias_c z sigma_c) exp(rel(z) n)`` with
``rel(z) = depth_rel (1 + z / depth_rel_ref_m)`` (noise grows with distance), ``n`` a unit
normal made of a 14x14-patch-correlated part and a per-pixel part (``n = 0.6 n_patch +
0.8 n_pixel``), ``bias_c ~ N(0, depth_bias^2)`` per chunk (per chunk unit of depth).  At depth
discontinuities (neighbouring log-depths differ by more than ``edge_log_ratio``) the depth is a
"flying pixel" between the two surfaces; a fraction ``gross_fraction`` of pixels is off by a
factor ``exp(U(-gross_log, gross_log))``; sky gets ``sky_depth_m`` (finite, as VGGT).

**Confidence** (``>= 1``, like VGGT's ``1 + exp(.)``): ``1 + conf_max exp(-z / conf_falloff_m)
exp(0.25 n')``, times ``edge_conf`` at discontinuities, and ``1 + 0.05 u`` on sky.

**Moving cars** (``num_movers > 0``): rendered per frame at their pose at that frame
(:func:`swiftjax.synthetic.world.mover_boxes`); each car's depth in a chunk is multiplied by
``exp(mover_depth n)``, ``n`` drawn per (chunk, car).

**Loop-centric chunks: VGGT's failure on unrelated frames.**  A frame list with a break
(``f_{k+1} != f_k + 1``; the pipeline's loop chunks: 20 frames around ``i``, then 20 around
``j``) is split at its first break into halves ``A = f_0..f_k`` and ``B = f_{k+1}..``.  Their
co-visibility ``c = min(covis(A -> B), covis(B -> A))`` is measured in the world
(:mod:`swiftjax.synthetic.covisibility`: the fraction of one half's true surface points that
the other half's frames see at a consistent depth).  Given frames that share no view, VGGT
still returns one coherent-looking reconstruction, the halves superimposed; so does the oracle.
With ``a`` and ``b`` the middle frames of ``A`` and ``B`` and a small random offset
``Delta = (exp([n_r] rot), n_t trans_m)`` (``n_r, n_t ~ N(0, I)``, keyed by ``(seed, frames)``),
the re-basing of ``B`` onto ``A``'s cameras is the rigid world motion::

    H_1 = T_a Delta T_b^-1          (B's middle camera lands on A's, offset by Delta)
    H(w) = Exp(w Log H_1),   w = smoothstep((c_high - c) / (c_high - c_low))  in [0, 1]

and ``B``'s cameras become ``H(w) T_k``; everything else (depth maps, so ``B``'s own geometry,
the chunk gauge, noise) is computed as for an honest chunk.  Confidence of every frame of the
chunk is lowered as ``1 + (conf - 1)(1 - w (1 - conf_factor))``.  So ``c >= c_high`` (a true
revisit) gives ``w = 0``: the prediction is bit-identical to the honest one; ``c <= c_low`` (no
shared view) gives ``H_1``: ``B``'s points in the chunk frame are the chunk gauge applied to
``H_1 x_world`` -- the loop edge derived from this chunk is off by ``H_1`` (superimposed at
``a``), not by VGGT's usual noise.  :meth:`VGGTOracle.loop_chunk_truth` returns ``(c, w, H(w))``
for any frame list; :class:`Hallucination` holds the constants (``hallucination=None``: honest
for every chunk).

**Determinism.**  Every random quantity of a FRAME is keyed by ``(seed, frame)``, every
quantity of a CHUNK by ``(seed, frames)``; a fraction ``chunk_share`` of each frame-level noise
is re-drawn per chunk.  Results are bit-identical for the same ``(seed, frames)`` whatever was
computed before.  Why the model looks like this, and how frames are rendered in cached blocks
(one compile per image size): docs/design.md, "The synthetic VGGT oracle"; its cost:
docs/performance/synthetic.md.
"""

from __future__ import annotations

import collections
import zlib
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import sim3
from swiftjax.prediction import ChunkPrediction
from swiftjax.synthetic import places
from swiftjax.synthetic.covisibility import covisibility as _covisibility
from swiftjax.synthetic.noise import Hallucination, OracleNoise
from swiftjax.synthetic.pixel_noise import PixelParams, pixel_block
from swiftjax.synthetic.render import (
    chunk_candidates,
    composite_movers,
    frame_movers,
    frame_planes,
    render_frames,
    render_movers,
)
from swiftjax.synthetic.se3_np import se3_power, so3_exp
from swiftjax.synthetic.world import World

__all__ = ["Hallucination", "LoopChunkTruth", "OracleNoise", "VGGTOracle", "kitti_intrinsics"]


def kitti_intrinsics(width: int = 518, height: int = 154) -> np.ndarray:
    """KITTI odometry camera 0 (``fx = fy = 718.856, cx = 607.19, cy = 185.22`` at 1241x376)
    resized to ``width x height``: ``[3, 3]`` float64."""
    sx, sy = width / 1241.0, height / 376.0
    return np.array([[718.856 * sx, 0.0, 607.1928 * sx], [0.0, 718.856 * sy, 185.2157 * sy], [0.0, 0.0, 1.0]])


class LoopChunkTruth(NamedTuple):
    """What the oracle does with a frame list (:meth:`VGGTOracle.loop_chunk_truth`).

    Attributes:
        split: frames in the first half ``A`` (the list's length when it has no break).
        covisibility: ``min(covis(A -> B), covis(B -> A))`` (1.0 without a break).
        weight: hallucination weight ``w`` in ``[0, 1]``.
        rebase: ``[4, 4]`` float64 ``H(w)``, the world motion applied to ``B``'s cameras.
        full_rebase: ``[4, 4]`` float64 ``H_1`` (what ``w = 1`` would apply).
    """

    split: int
    covisibility: float
    weight: float
    rebase: np.ndarray
    full_rebase: np.ndarray


class _Block(NamedTuple):
    depth: jax.Array  # [F, H, W] float32 metres (inf: sky), kept on the device
    semantic: jax.Array  # [F, H, W] int8
    instance: jax.Array  # [F, H, W] int32
    frames: np.ndarray  # [F] the frame of each slot (the last frame repeats past the end)
    depth_sum: np.ndarray  # [F] float64 sum of each frame's finite depths
    depth_count: np.ndarray  # [F] int64 number of finite depths


@jax.jit
def _block_stats(depth: jax.Array, semantic: jax.Array):
    """int8 semantics and per-row sums / counts of the finite depths ``[F, H]`` (float32 rows
    of ``W`` values; the host adds the rows in float64)."""
    fin = jnp.isfinite(depth)
    return (
        semantic.astype(jnp.int8),
        jnp.sum(jnp.where(fin, depth, 0.0), axis=2),
        jnp.sum(fin, axis=2, dtype=jnp.int32),
    )


class VGGTOracle:
    """Stand-in for VGGT over a synthetic world (module docstring).

    Args:
        world: the scene (:func:`swiftjax.synthetic.world.build_world`).
        cam_to_world: ``[N, 4, 4]`` true camera-to-world poses (metres, OpenCV cameras).
        intrinsic: ``[3, 3]`` true intrinsics at ``image_hw`` (default: :func:`kitti_intrinsics`).
        image_hw: ``(H, W)`` (default ``(154, 518)``, VGGT's KITTI size).
        noise: :class:`OracleNoise` (``OracleNoise.off()`` for the exact truth).
        seed: seed of every random quantity.
        place_config: :class:`~swiftjax.synthetic.places.PlaceTokenConfig` for the patch
            tokens (default: its defaults with ``seed``); ``tokens=False`` skips them.
        block: frames per render block (fixed; one compile per image size).
        far: the world's draw distance in metres.
        k_box, k_cyl: per-frame object budgets of the renderer.
        cache_blocks: rendered blocks kept in memory (LRU); place tokens of the last
            ``cache_blocks * block`` frames are kept too.
        hallucination: :class:`Hallucination` (default) for loop-centric chunks whose halves
            share no view, or ``None`` (every chunk honest).
    """

    def __init__(
        self,
        world: World,
        cam_to_world: np.ndarray,
        intrinsic: np.ndarray | None = None,
        image_hw: tuple[int, int] = (154, 518),
        noise: OracleNoise = OracleNoise(),
        seed: int = 0,
        place_config: places.PlaceTokenConfig | None = None,
        tokens: bool = True,
        block: int = 15,
        far: float = 80.0,
        k_box: int = 12,
        k_cyl: int = 10,
        cache_blocks: int = 12,
        hallucination: Hallucination | None = Hallucination(),
    ) -> None:
        T = np.asarray(cam_to_world, np.float64)
        if T.ndim != 3 or T.shape[1:] not in ((4, 4), (3, 4)) or T.shape[0] < 1:
            raise ValueError(f"cam_to_world must have shape [N, 4, 4], got {T.shape}")
        if not np.all(np.isfinite(T)):
            raise ValueError("cam_to_world holds non-finite values (nan/inf)")
        self.poses = np.tile(np.eye(4), (T.shape[0], 1, 1))
        self.poses[:, :3, :] = T[:, :3, :]
        h, w = (int(image_hw[0]), int(image_hw[1]))
        if h < 2 or w < 2:
            raise ValueError(f"image_hw must be at least (2, 2), got {image_hw}")
        self.image_hw = (h, w)
        K = kitti_intrinsics(w, h) if intrinsic is None else np.asarray(intrinsic, np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"intrinsic must be a finite [3, 3] matrix with positive focals, got {K}")
        self.K = K
        self.world = world
        self.noise = noise
        self.seed = int(seed)
        self.block = int(block)
        self.far, self.k_box, self.k_cyl = float(far), int(k_box), int(k_cyl)
        self._cache: collections.OrderedDict[int, _Block] = collections.OrderedDict()
        self._token_cache: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self._cache_blocks = int(cache_blocks)
        self._tokens = tokens
        if tokens:
            cfg = place_config or places.PlaceTokenConfig(seed=self.seed)
            self.place_params = places.make_place_params(cfg)
        self._frame_key = np.uint32(zlib.crc32(np.int64(self.seed).tobytes()))
        self.hallucination = hallucination
        self._loop_truth: collections.OrderedDict[bytes, LoopChunkTruth] = collections.OrderedDict()

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])

    # ------------------------------------------------------------------ ground truth

    def _check_frames(self, frames) -> np.ndarray:
        f = np.asarray(frames)
        if f.ndim != 1 or f.size == 0 or not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"frame_indices must be a non-empty 1-D integer array, got {f!r:.80}")
        if f.min() < 0 or f.max() >= self.num_frames:
            raise ValueError(f"frame_indices must lie in [0, {self.num_frames}), got range [{f.min()}, {f.max()}]")
        return f.astype(np.int64)

    def _render_block(self, b: int) -> _Block:
        if b in self._cache:
            self._cache.move_to_end(b)
            return self._cache[b]
        F = self.block
        idx = np.minimum(np.arange(b * F, (b + 1) * F), self.num_frames - 1)
        P = self.poses[idx]
        origin = P[0, :3, 3]
        cand = chunk_candidates(self.world, P[:, :3, 3], origin, far=self.far)
        planes = frame_planes(self.world, P[:, :3, 3], origin)
        out = render_frames(
            self.K.astype(np.float32),
            P[:, :3, :3].astype(np.float32),
            (P[:, :3, 3] - origin).astype(np.float32),
            planes.astype(np.float32),
            cand,
            np.int32(self.world.num_boxes),
            height=self.image_hw[0],
            width=self.image_hw[1],
            k_box=self.k_box,
            k_cyl=self.k_cyl,
            far=self.far,
        )
        if self.world.movers is not None and self.world.movers.num:
            cars = frame_movers(self.world, idx, origin, far=self.far)
            car_depth, car_id = render_movers(
                self.K.astype(np.float32),
                P[:, :3, :3].astype(np.float32),
                (P[:, :3, 3] - origin).astype(np.float32),
                *cars,
                height=self.image_hw[0],
                width=self.image_hw[1],
            )
            offset = np.int32(self.world.num_boxes + self.world.num_cylinders)
            out = composite_movers(out, car_depth, car_id, offset, far=self.far)
        sem, row_sum, row_count = _block_stats(out.depth, out.semantic)
        blk = _Block(
            out.depth,
            sem,
            out.instance,
            idx,
            np.asarray(row_sum).sum(axis=1, dtype=np.float64),
            np.asarray(row_count).sum(axis=1, dtype=np.int64),
        )
        self._cache[b] = blk
        while len(self._cache) > self._cache_blocks:
            self._cache.popitem(last=False)
        return blk

    def render_truth(self, frames) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True ``(depth [S, H, W] metres (inf: sky), semantic [S, H, W] int8, instance [S, H, W] int32)``.

        ``instance``: box index for buildings, ``num_boxes +`` cylinder index for poles and
        trees, ``num_boxes + num_cylinders +`` car index for moving cars (semantic
        :data:`~swiftjax.synthetic.world.CAR`), ``-1`` for ground and sky.
        """
        f = self._check_frames(frames)
        blocks = self._blocks(f)
        return tuple(np.stack([np.asarray(blocks[i // self.block][k])[i % self.block] for i in f]) for k in range(3))

    def _blocks(self, f: np.ndarray) -> dict[int, _Block]:
        return {int(b): self._render_block(int(b)) for b in np.unique(f // self.block)}

    def true_cam_to_world(self, frames) -> np.ndarray:
        """``[S, 4, 4]`` float64 true camera-to-world poses."""
        return self.poses[self._check_frames(frames)].copy()

    def true_world_points(self, frames) -> tuple[np.ndarray, np.ndarray]:
        """``(points [S, H, W, 3] float64 world, valid [S, H, W] bool)``; sky is invalid (NaN)."""
        f = self._check_frames(frames)
        depth, _, _ = self.render_truth(f)
        h, w = self.image_hw
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        K = self.K
        y = (v - K[1, 2]) / K[1, 1]
        x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
        rays = np.stack([x, y, np.ones_like(x)], -1)
        valid = np.isfinite(depth)
        z = np.where(valid, depth, np.nan).astype(np.float64)
        cam = z[..., None] * rays
        P = self.poses[f]
        pts = np.einsum("sij,shwj->shwi", P[:, :3, :3], cam) + P[:, None, None, :3, 3]
        return pts, valid

    def _chunk_sigma(self, f: np.ndarray, blocks: dict[int, _Block]) -> float:
        F = self.block
        total = sum(blocks[i // F].depth_sum[i % F] for i in f)
        count = sum(blocks[i // F].depth_count[i % F] for i in f)
        mean = float(total / count) if count else self.far
        rng = self._chunk_rng(f, 0)
        return self.noise.depth_units / mean * float(np.exp(self.noise.scale_jitter * rng.normal()))

    def _chunk_key(self, f: np.ndarray) -> int:
        return zlib.crc32(np.asarray(f, np.int64).tobytes(), zlib.crc32(np.int64(self.seed).tobytes()))

    def _chunk_rng(self, f: np.ndarray, stream: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, self._chunk_key(f), stream, 1])

    def _frame_rng(self, frame: int, stream: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, int(frame), stream, 2])

    def true_chunk_gauge(self, frames) -> np.ndarray:
        """The TRUE chunk-to-world Sim(3) ``[8]`` float64: ``x_world = s R x_chunk + t``."""
        f = self._check_frames(frames)
        sigma = self._chunk_sigma(f, self._blocks(f))
        T0 = self.poses[f[0]]
        with jax.enable_x64(True):
            return np.asarray(sim3.from_rst(T0[:3, :3], T0[:3, 3], 1.0 / sigma), np.float64)

    def covisibility(self, frames_a, frames_b, *, mutual: bool = False, stride: int = 8, rel_tol: float = 0.1) -> float:
        """``covis(A -> B)`` (or ``min`` of both directions when ``mutual``) of two frame lists,
        from the true depth and poses (:mod:`swiftjax.synthetic.covisibility`).

        Raises ``ValueError`` for empty, non-integer or out-of-range frame lists."""
        fa, fb = self._check_frames(frames_a), self._check_frames(frames_b)
        return self._covisibility(fa, fb, mutual, stride, rel_tol)

    def _covisibility(self, fa, fb, mutual, stride, rel_tol) -> float:
        (da, _, _), (db, _, _) = self.render_truth(fa), self.render_truth(fb)
        origin = self.poses[fa[0], :3, 3]
        Ta, Tb = self.poses[fa].copy(), self.poses[fb].copy()
        Ta[:, :3, 3] -= origin  # float64 centring, float32 inside
        Tb[:, :3, 3] -= origin
        K = self.K.astype(np.float32)
        ab = float(_covisibility(da, Ta.astype(np.float32), db, Tb.astype(np.float32), K, stride, rel_tol))
        if not mutual:
            return ab
        return min(ab, float(_covisibility(db, Tb.astype(np.float32), da, Ta.astype(np.float32), K, stride, rel_tol)))

    def loop_chunk_truth(self, frame_indices) -> LoopChunkTruth:
        """Co-visibility of the halves of a frame list and the re-basing the oracle applies to its
        second half (module docstring, "Loop-centric chunks").  A list without a break, or an
        oracle with ``hallucination=None``, is honest: ``weight = 0``, ``rebase = I``.
        Deterministic per ``(seed, frame_indices)``; cached."""
        f = self._check_frames(frame_indices)
        key = f.tobytes()
        if key in self._loop_truth:
            return self._loop_truth[key]
        breaks = np.nonzero(np.diff(f) != 1)[0]
        eye = np.eye(4)
        hz = self.hallucination
        if len(breaks) == 0 or hz is None:
            return LoopChunkTruth(len(f), 1.0, 0.0, eye, eye)
        k = int(breaks[0]) + 1
        A, B = f[:k], f[k:]
        c = self._covisibility(A, B, True, hz.stride, hz.rel_tol)
        w = hz.weight(c)
        rng = self._chunk_rng(f, 5)
        delta = np.eye(4)
        delta[:3, :3] = so3_exp(rng.normal(scale=hz.rot, size=3))
        delta[:3, 3] = rng.normal(scale=hz.trans_m, size=3)
        Ta, Tb = self.poses[A[len(A) // 2]], self.poses[B[len(B) // 2]]
        H1 = Ta @ delta @ np.linalg.inv(Tb)
        H = eye if w == 0.0 else (H1 if w == 1.0 else se3_power(H1, w))
        out = LoopChunkTruth(k, c, w, H, H1)
        self._loop_truth[key] = out
        while len(self._loop_truth) > 256:
            self._loop_truth.popitem(last=False)
        return out

    # ------------------------------------------------------------------- prediction

    def _focal_eps(self, f: np.ndarray) -> np.ndarray:
        nz = self.noise
        a, b = np.sqrt(1 - nz.chunk_share), np.sqrt(nz.chunk_share)
        crng = self._chunk_rng(f, 3)
        eps = np.array([a * self._frame_rng(i, 3).uniform(-1, 1) + b * crng.uniform(-1, 1) for i in f])
        return nz.focal * np.clip(eps, -1.0, 1.0)

    def _place_tokens(self, f: np.ndarray) -> np.ndarray:
        """Tokens ``[S, K, d]`` of frames ``f``; per frame, computed once while cached.

        :func:`~swiftjax.synthetic.places.place_tokens` depends on the frame alone, so a
        cached frame's tokens are the ones a fresh call would return."""
        F = self.block
        cache = self._token_cache
        missing = [i for i in dict.fromkeys(f.tolist()) if i not in cache]
        for j in range(0, len(missing), F):
            m = missing[j : j + F]
            mp = np.asarray(m + [m[-1]] * (F - len(m)))  # fixed block size: one compile
            out = np.asarray(
                places.place_tokens(self.place_params, self.poses[mp].astype(np.float32), mp.astype(np.int32))
            )
            for k, i in enumerate(m):
                cache[i] = out[k]
        tokens = np.stack([cache[i] for i in f.tolist()])
        for i in f.tolist():
            cache.move_to_end(i)
        while len(cache) > max(self._cache_blocks * F, len(f)):
            cache.popitem(last=False)
        return tokens

    def predict_chunk(self, frame_indices) -> ChunkPrediction:
        """VGGT's outputs for ``frame_indices`` ``[S]`` (module docstring for the model).

        Deterministic per ``(seed, frame_indices)``.  Raises ``ValueError`` for an empty,
        non-integer or out-of-range index array.
        """
        f = self._check_frames(frame_indices)
        nz = self.noise
        S = len(f)
        blocks = self._blocks(f)
        sigma = self._chunk_sigma(f, blocks)
        rng = self._chunk_rng(f, 1)
        w_c = rng.normal(scale=nz.drift_rot, size=3)
        delta_c = rng.normal(scale=nz.drift_scale)
        bias_c = rng.normal(scale=nz.depth_bias)
        eps = self._focal_eps(f)

        # ---- poses (host float64: S small matrices); a hallucinated second half is re-based
        T = self.poses[f]
        truth = self.loop_chunk_truth(f)
        if truth.weight > 0.0:
            T = T.copy()
            T[truth.split :] = truth.rebase @ T[truth.split :]
        R0, c0 = T[0, :3, :3], T[0, :3, 3]
        R_ck = R0.T @ T[:, :3, :3]
        t_ck = sigma * (T[:, :3, 3] - c0) @ R0
        k = np.arange(S, dtype=np.float64)
        R_D = so3_exp(k[:, None] * w_c)
        s_k = np.exp(k * delta_c)
        jr = np.array([self._frame_rng(i, 4).normal(size=3) for i in f]) * nz.pose_rot
        jt = self._chunk_rng(f, 4).normal(size=(S, 3)) * nz.pose_trans
        jr[0] = 0.0
        jt[0] = 0.0
        R_pred = R_D @ R_ck @ so3_exp(jr)
        t_pred = s_k[:, None] * np.einsum("sij,sj->si", R_D, t_ck) + jt
        extrinsic = np.concatenate(
            [np.swapaxes(R_pred, 1, 2), -np.einsum("sji,sj->si", R_pred, t_pred)[..., None]], axis=2
        )
        K = np.tile(self.K, (S, 1, 1))
        K[:, 0, 0] *= 1.0 + eps
        K[:, 1, 1] *= 1.0 + eps
        depth_factor = sigma * s_k * (1.0 + eps) ** nz.focal_depth_coupling

        # ---- pixels, in fixed blocks of `block` frames: a cached render block is used as it
        # is (on the device) when the chunk's block of frames is exactly that render block
        # (the regular schedule: chunk starts are multiples of B - O = 45 = 3 blocks)
        F = self.block
        n_blk = -(-S // F)
        pad = n_blk * F - S
        padi = lambda a: np.concatenate([a, np.repeat(a[-1:], pad, axis=0)]) if pad else a
        ft, dft = padi(f), padi(depth_factor)
        scalars = np.asarray(
            [
                nz.depth_rel,
                nz.depth_rel_ref_m,
                nz.edge_log_ratio,
                nz.edge_conf,
                nz.gross_fraction,
                nz.gross_log,
                nz.sky_depth_m,
                nz.conf_max,
                nz.conf_falloff_m,
                nz.chunk_share,
                nz.mover_depth,
            ],
            np.float32,
        )
        ckey = np.uint32(self._chunk_key(f))
        outs = []
        for j in range(n_blk):
            fj = ft[j * F : (j + 1) * F]
            blk = blocks[int(fj[0]) // F]
            if np.array_equal(fj, blk.frames):
                z, sem, inst = blk.depth, blk.semantic, blk.instance
            else:
                z, sem, inst = (np.stack([np.asarray(blocks[i // F][k])[i % F] for i in fj]) for k in range(3))
            p = PixelParams(
                np.uint32(self._frame_key),
                ckey,
                fj.astype(np.int32),
                dft[j * F : (j + 1) * F].astype(np.float32),
                np.float32(sigma),
                np.float32(bias_c),
                scalars,
            )
            outs.append(pixel_block(z, sem, inst, p))
        depth = np.concatenate([np.asarray(o[0]) for o in outs])[:S]
        conf = np.concatenate([np.asarray(o[1]) for o in outs])[:S]
        if truth.weight > 0.0:
            conf = 1.0 + (conf - 1.0) * np.float32(1.0 - truth.weight * (1.0 - self.hallucination.conf_factor))
        images = np.concatenate([np.asarray(o[2]) for o in outs])[:S]
        tokens = self._place_tokens(f) if self._tokens else None
        return ChunkPrediction(
            depth=depth,
            conf=conf,
            extrinsic=extrinsic.astype(np.float32),
            intrinsic=K.astype(np.float32),
            patch_tokens=tokens,
            images=images,
        )

"""The loop stage's second candidate source: chunk pairs whose dense geometry matches.

Beside the DINO-token candidates (:mod:`swiftjax.pipeline.loop_closure`), with
``loop_geometry = true``: every temporal chunk's reliable points (``frame_stride``-th frames read
back from the chunk store, memory-mapped) become :func:`swiftjax.loops.geometric.chunk_descriptors`
(in fixed batches of :data:`BATCH` chunks) and a structure cloud
(:func:`swiftjax.loops.geometric.structure_cloud`).  The candidates are the chunk pairs that
the dead-reckoned chain places within ``max(gate_min h, gate_drift x path between them)`` of
each other (:func:`_pairs`), frames more than ``loop_min_separation`` apart: on a reverse pass
the chunks that share structure are the ones whose cameras face each other across a stretch,
one or two chunks off the closest frames, so every gated pair is tried, not only the closest
(docs/performance/reverse-revisits.md).  Each is registered from the chain's prior
(:func:`swiftjax.loops.geometric.register_covisible`: bird's-eye FFT search within the gate,
Sim(3) ICP per peak) and, in the same batch, against ``null_chunks`` unrelated chunks
(:func:`_null_chunks`) from the same prior; a candidate must keep more structure inliers than
the null's prediction bound (:func:`swiftjax.loops.null.null_threshold` at
``null_false_alarm``), no second placement ``peak_separation`` away may keep more than
``max_ambiguity`` of them, and the scale must agree with the chain's
(:func:`swiftjax.loops.geometric.covisible_reason`, one-line reasons).  Survivors go through the
cross-chunk dense test over all frame pairs of the two chunks and pairwise consistency with every
other candidate, like the token candidates.  No loop-centric chunk is predicted.

Each candidate is a record marked ``source = "geometry"`` with its registration's numbers
(``registration.*``: inlier ratio, RMS in camera heights, scale ratio, spread, ambiguity, the
null's mean and bound); the accepted edge's information comes from the registration's own
residuals (:func:`swiftjax.align.covariance.umeyama_information` on its inliers).  The records
are recomputed on every run (nothing is cached in the manifest).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import align
from swiftjax.align import covariance
from swiftjax.loops import geometric as geo
from swiftjax.loops import verification as lv
from swiftjax.pipeline.rundir import RunContext

__all__ = ["BATCH", "descriptors", "candidates", "edge_information"]

#: Chunks per call of :func:`swiftjax.loops.geometric.chunk_descriptors` (the last batch padded).
BATCH = 8


def _frames(ctx: RunContext, c: int, options: geo.GeometryOptions) -> tuple[align.ChunkFrames, np.ndarray]:
    """``ceil(chunk_size / frame_stride)`` frames of chunk ``c``, evenly spread (fixed count), and
    their global frame ids."""
    frames = ctx.schedule.frames(c)
    count = -(-ctx.config.chunk_size // options.frame_stride)
    local = np.unique(np.round(np.linspace(0, len(frames) - 1, count)).astype(np.int64))
    local = np.concatenate([local, np.repeat(local[-1:], count - len(local))])
    side = align.ChunkFrames.from_prediction(ctx.store.load("chunk", c, frames=local, fields=()))
    if ctx.camera is not None:  # masked pixels (user / sky) count as missing depth
        keep = ctx.camera.keep(frames[local], side.depth, side.conf)
        if keep is not None:
            side = side._replace(depth=np.where(np.asarray(keep), np.asarray(side.depth, np.float32), np.nan))
    return side._replace(depth=np.asarray(side.depth, np.float32), conf=np.asarray(side.conf, np.float32)), frames[
        local
    ]


def descriptors(ctx: RunContext, K_ref: np.ndarray, options: geo.GeometryOptions):
    """``(ChunkDescriptors [T, ...], global frame ids [T, F])`` of every chunk."""
    T = ctx.schedule.num_chunks
    parts, ids = [], []
    for b0 in range(0, T, BATCH):
        chunk_ids = [min(c, T - 1) for c in range(b0, b0 + BATCH)]
        loaded = [_frames(ctx, c, options) for c in chunk_ids]
        stack = align.ChunkFrames(*(np.stack(x) for x in zip(*(f for f, _ in loaded))))
        d = geo.chunk_descriptors(stack, K_ref, options)
        n = min(BATCH, T - b0)
        parts.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[:n], d))
        ids += [f for _, f in loaded[:n]]
    return jax.tree_util.tree_map(lambda *a: np.concatenate(a), *parts), np.stack(ids)


def _pairs(chain: np.ndarray, clouds: geo.ChunkCloud, ids: np.ndarray, sep: int, options: geo.GeometryOptions):
    """``[(c_i, c_j, window)]``: chunk pairs (``c_i − c_j >= 2``, frames more than ``sep``
    apart) whose structure the dead-reckoned chain places within ``max(gate_min h, gate_drift x
    path)`` of each other (centres), and that window in ``c_j``'s camera heights (at most
    ``max_window``)."""
    T = len(chain)
    with jax.enable_x64(True):
        from swiftjax import sim3

        centre = np.asarray(sim3.act(jnp.asarray(chain), jnp.asarray(np.asarray(clouds.origin), jnp.float64)))
    cam = chain[:, :3]
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(cam, axis=0), axis=1))])
    h_world = np.asarray(clouds.height) * chain[:, 7]
    h_med = float(np.nanmedian(h_world))
    out = []
    for ci in range(T):
        for cj in range(ci - 1):
            if not abs(float(np.mean(ids[ci])) - float(np.mean(ids[cj]))) > sep:
                continue
            gate = max(options.gate_min * h_med, options.gate_drift * abs(path[ci] - path[cj]))
            if np.linalg.norm(centre[ci] - centre[cj]) <= gate:
                out.append((ci, cj, min(gate / h_med, options.max_window)))
    return out


@functools.lru_cache(maxsize=4)
def _batched(options: geo.GeometryOptions):
    """:func:`swiftjax.loops.geometric.register_covisible` of one source against a batch of
    targets (the candidate and its null chunks), jitted once per options."""
    return jax.jit(
        jax.vmap(functools.partial(geo.register_covisible, options=options), in_axes=(None, 0, None, None, 0, None))
    )


def _null_chunks(ci: int, cj: int, T: int, near: set[tuple[int, int]], k: int) -> list[int]:
    """``k`` chunks evenly spread over those more than 3 chunks from ``c_i`` and ``c_j`` and not
    paired with ``c_i`` by the gate: streets the source cannot be on."""
    pool = [c for c in range(T) if abs(c - ci) > 3 and abs(c - cj) > 3 and (max(c, ci), min(c, ci)) not in near]
    if len(pool) < k:
        return pool
    return [pool[int(round(x))] for x in np.linspace(0, len(pool) - 1, k)]


def candidates(
    ctx: RunContext,
    K_ref: np.ndarray,
    taken: set[tuple[int, int]],
    verification: lv.VerificationConfig,
    options: geo.GeometryOptions = geo.GeometryOptions(),
    chain: np.ndarray | None = None,
) -> list[dict[str, Any]]:
    """The geometric candidates' records (module docstring), chunk pairs in ``taken`` (the
    token source's, ``(larger, smaller)``) left out; each record with ``accepted``/``reason``
    set when its registration rejects it, else ready for :func:`verify_candidates`.
    ``chain [T, 8]``: the dead-reckoned chunk poses (the prior of every registration; without
    it no candidate is proposed)."""
    from swiftjax import sim3
    from swiftjax.loops.null import null_threshold

    if chain is None:
        return []
    chain = np.asarray(chain, np.float64)
    desc, ids = descriptors(ctx, K_ref, options)
    T = len(ids)
    g = jax.tree_util.tree_map(jnp.asarray, desc.geometry)
    keys = jax.random.split(jax.random.PRNGKey(0), T)
    clouds = jax.vmap(lambda gg, k: geo.structure_cloud(gg, k, options))(g, keys)
    pairs = _pairs(chain, clouds, ids, ctx.config.loop_min_separation, options)
    near = {(ci, cj) for ci, cj, _ in pairs}
    take = lambda c: jax.tree_util.tree_map(lambda a: a[c], clouds)
    batch = _batched(options)
    records = []
    for ci, cj, window in pairs:
        if (ci, cj) in taken:
            continue
        with jax.enable_x64(True):
            Zc = np.asarray(sim3.compose(sim3.inverse(jnp.asarray(chain[cj])), jnp.asarray(chain[ci])))
        a, b = take(ci), take(cj)
        psi, sigma, tau = geo.edge_prior(Zc, a, b)
        nulls = _null_chunks(ci, cj, T, near, options.null_chunks)
        dst = [cj, *nulls]
        taus = jnp.stack([tau] + [jnp.zeros(2, jnp.float32)] * len(nulls))
        with ctx.timer("loop geometry: registration"):
            cov = batch(a, take(np.asarray(dst)), psi, sigma, taus, jnp.float32(window))
        regs = jax.tree_util.tree_map(np.asarray, cov.registration)
        reg0 = jax.tree_util.tree_map(lambda x: x[0], cov.registration)
        n_struct = regs.num_structure.astype(np.float64)
        pts = float(max(regs.num_points[0], 1))
        null = null_threshold(
            n_struct[1:] / pts, np.ones(len(nulls)), np.full(len(nulls), pts), options.null_false_alarm, 0.0
        )
        record: dict[str, Any] = {
            "source": "geometry",
            "i": int(ids[ci, len(ids[ci]) // 2]),
            "j": int(ids[cj, len(ids[cj]) // 2]),
            "score": float(n_struct[0] / pts),
            "chunk_i": int(ci),
            "chunk_j": int(cj),
            "Z": np.asarray(reg0.S, np.float64).tolist(),
        }
        record["registration"] = {
            k: _plain(getattr(reg0, k))
            for k in (
                "inlier_ratio",
                "rms",
                "scale_ratio",
                "spread",
                "num_inliers",
                "num_structure",
                "num_points",
                "valid",
            )
        }
        record["registration"].update(
            ambiguity=float(cov.ambiguity[0]),
            window=float(window),
            null_mean=float(np.mean(n_struct[1:])) if len(nulls) else None,
            null_threshold=float(null.threshold * pts) if math.isfinite(null.threshold) else None,
            yaw_deg=float(np.degrees(psi)),
        )
        record["_stats"] = (reg0, float(b.height))
        why = geo.covisible_reason(record["registration"], options)
        record.update(quality_valid=why is None, quality_min_fraction=1.0)
        if why is not None:
            record.update(accepted=False, reason=why)
        else:
            with ctx.timer("loop geometry: verification"):
                record.update(_dense(ctx, ci, cj, record["Z"], K_ref, options, verification))
        records.append(record)
    return records


def _plain(v: Any) -> Any:
    a = np.asarray(v)
    return bool(a) if a.dtype == bool else (int(a) if a.dtype.kind in "iu" else float(a))


def _dense(
    ctx: RunContext,
    ci: int,
    cj: int,
    Z: list[float],
    K_ref: np.ndarray,
    options: geo.GeometryOptions,
    verification: lv.VerificationConfig,
) -> dict[str, Any]:
    """The cross-chunk dense test of the two chunks' loaded frames, every frame pair compared."""
    import dataclasses

    (side_i, _), (side_j, _) = _frames(ctx, ci, options), _frames(ctx, cj, options)
    info = {"num_points": 1000, "fraction_used": 1.0, "rms": 0.0, "valid": True, "pose_fallback": False}
    return lv.candidate_numbers(
        side_i, side_j, np.asarray(Z), K_ref, info, info, dataclasses.replace(verification, neighbours=0)
    )


def edge_information(record: dict[str, Any], pixels_per_sample: float) -> np.ndarray | None:
    """Information ``[7, 7]`` of a registration edge from its own inliers' residuals, or None."""
    stats = record.get("_stats")
    if stats is None:
        return None
    reg, unit = stats
    with jax.enable_x64(True):
        out = covariance.umeyama_information(
            np.float64(np.asarray(reg.S)[7]),
            np.float64(reg.num_inliers),
            np.float64(reg.rms) * unit,
            np.asarray(reg.src_mean, np.float64),
            np.asarray(reg.src_covariance, np.float64),
            pixels_per_sample=pixels_per_sample,
        )
        info = np.asarray(out.information, np.float64)
    return info if bool(out.valid) and np.all(np.isfinite(info)) and not math.isnan(info[0, 0]) else None

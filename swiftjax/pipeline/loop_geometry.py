"""The loop stage's second candidate source: chunk pairs whose dense geometry matches.

Beside the DINO-token candidates (:mod:`swiftjax.pipeline.loop_closure`), with
``loop_geometry = true``: every temporal chunk's reliable points (``frame_stride``-th frames read
back from the chunk store, memory-mapped) become :func:`swiftjax.loops.geometric.chunk_descriptors`
(in fixed batches of :data:`BATCH` chunks: one compile per run); chunk pairs at least
``loop_min_separation`` frames apart whose signatures match are registered
(:func:`swiftjax.loops.geometric.register`, both yaw hypotheses ``ψ`` and ``ψ + π`` of the
Scan Context shift, since a street is nearly symmetric end to end; the one with more structure
inliers kept) and their edge is checked like every other candidate (the cross-chunk dense test
over all frame pairs of the two chunks: a reverse revisit's nearest cameras face each other,
and pairwise consistency).  No loop-centric chunk is predicted.

Candidate chunk pairs must also lie near each other under the dead-reckoned chain (within
``gate_min`` camera heights or ``gate_drift`` of the path driven between them: the odometry's
drift), as Scan Context's users gate by the odometry: a signature alone is ambiguous among
the many look-alike streets of a city.

Each candidate is a record marked ``source = "geometry"`` with its registration's numbers
(``registration.*``: inlier ratio, RMS in camera heights, scale ratio, spread); a
registration that fails its own test (:func:`swiftjax.loops.geometric.registration_reason`) is
rejected with that reason before verification.  The accepted edge's information comes from
the registration's own residuals (:func:`swiftjax.align.covariance.umeyama_information` on its
inliers).  The records are recomputed on every run (nothing is cached in the manifest).
"""

from __future__ import annotations

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


def _gate(chain: np.ndarray, g: Any, best: np.ndarray, options: geo.GeometryOptions) -> np.ndarray:
    """``[T, T]`` bool: the best anchors of the two chunks lie within ``max(gate_min h,
    gate_drift x path length between them)`` of each other under the dead-reckoned chain."""
    import jax.numpy as jnp

    from swiftjax import sim3

    T = len(chain)
    with jax.enable_x64(True):
        anchors = np.asarray(sim3.act(jnp.asarray(chain)[:, None, :], jnp.asarray(g.anchors, jnp.float64)))
    centre = chain[:, :3]
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centre, axis=0), axis=1))])
    h_world = np.nanmedian(np.asarray(g.height) * chain[:, 7])
    a, b = np.meshgrid(np.arange(T), np.arange(T), indexing="ij")
    d = np.linalg.norm(anchors[a, best[..., 0]] - anchors[b, best[..., 1]], axis=-1)
    return d <= np.maximum(options.gate_min * h_world, options.gate_drift * np.abs(path[a] - path[b]))


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
    ``chain [T, 8]``: the dead-reckoned chunk poses; pairs whose anchors lie too far apart
    under them are not proposed (:func:`_gate`)."""
    desc, ids = descriptors(ctx, K_ref, options)
    T = len(ids)
    dist, best = (np.asarray(a) for a in geo.signature_distances(desc.signatures, desc.valid))
    g = desc.geometry
    if chain is not None:
        dist = np.where(_gate(np.asarray(chain, np.float64), g, best, options), dist, np.inf)
    sep = ctx.config.loop_min_separation
    pairs: dict[tuple[int, int], float] = {}
    for a in range(T):
        order = [
            b
            for b in np.argsort(dist[a])
            if abs(int(b) - a) >= 2
            and np.isfinite(dist[a, b])
            and dist[a, b] <= options.max_distance
            and abs(int(ids[a, best[a, b, 0]]) - int(ids[b, best[a, b, 1]])) > sep
        ]
        for b in order[: options.top_k]:
            key = (max(a, int(b)), min(a, int(b)))
            if key not in taken:
                pairs[key] = float(dist[a, b])
    records = []
    for (ci, cj), dsig in sorted(pairs.items(), key=lambda kv: kv[1]):
        ai, aj = best[ci, cj]
        sc, shift = (np.asarray(x) for x in geo.scan_context_distance(desc.grids[ci, ai], desc.grids[cj, aj]))
        record: dict[str, Any] = {
            "source": "geometry",
            "i": int(ids[ci, ai]),
            "j": int(ids[cj, aj]),
            "score": float(1.0 - sc),
            "chunk_i": int(ci),
            "chunk_j": int(cj),
            "signature_distance": dsig,
            "scan_context_distance": float(sc),
        }
        if not sc <= options.max_sc_distance:
            record.update(accepted=False, reason=f"Scan Context distance {float(sc):.3f} > {options.max_sc_distance}")
            records.append(record)
            continue
        with ctx.timer("loop geometry: registration"):
            reg, unit = _register(g, ci, ai, cj, aj, int(shift), options)
        record["Z"] = np.asarray(reg.S, np.float64).tolist()
        record["registration"] = {
            k: _plain(getattr(reg, k))
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
        record["registration"]["yaw_deg"] = float(np.degrees(geo.sector_yaw(int(shift), options.sectors)))
        record["_stats"] = (reg, unit)
        why = geo.registration_reason(record["registration"], options)
        # the loop-chunk fields of the decision rule: the registration stands in for the loop chunk
        record.update(quality_valid=why is None, quality_min_fraction=float(reg.inlier_ratio))
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


def _register(g: geo.ChunkGeometry, ci: int, ai: int, cj: int, aj: int, shift: int, options: geo.GeometryOptions):
    """The better of the two yaw hypotheses' registrations of chunk ``ci`` onto ``cj``."""
    key = jax.random.PRNGKey(ci * 100003 + cj)

    def near(c, a):
        q = geo._normalised(jnp.asarray(g.points[c]), g.anchors[c, a], g.basis[c], g.height[c])
        return jnp.asarray(g.weights[c]) * (jnp.hypot(q[:, 0], q[:, 1]) < options.max_radius)

    src, ws = geo.subsample(g.points[ci], near(ci, ai), options.src_points, key)
    dst, wd = geo.subsample(g.points[cj], near(cj, aj), options.dst_points, jax.random.fold_in(key, 1))
    up = jnp.asarray(g.basis[cj][:, 2])
    ground = up @ jnp.asarray(g.anchors[cj, aj]) - g.height[cj]
    best = None
    for m in (shift, shift + options.sectors // 2):
        S0 = geo.coarse_edge(
            g.anchors[ci, ai],
            g.basis[ci],
            g.height[ci],
            g.anchors[cj, aj],
            g.basis[cj],
            g.height[cj],
            geo.sector_yaw(m % options.sectors, options.sectors),
        )
        reg = geo.register(
            src,
            ws,
            dst,
            wd,
            S0,
            g.height[cj],
            up,
            ground,
            options.tau_start,
            options.tau_end,
            options.ground_band,
            iterations=options.iterations,
        )
        if best is None or float(reg.num_structure) > float(best.num_structure):
            best = reg
    return best, float(g.height[cj])


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

"""Loop-centric chunks: which frames a loop's chunk holds, the chunk filter, the loop edge.

::

    pairs ──drop pairs inside one chunk, best per chunk pair──► loops     filter_by_chunks
    loop ──20 + 20 frames around both ends──► loop-centric chunk          loop_chunk_frames
    S_{i,loop}, S_{j,loop} ──► S_{j,loop} S_{i,loop}⁻¹                    loop_edge
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from swiftjax import sim3
from swiftjax.chunks import ChunkSchedule
from swiftjax.loops.detection import LoopCandidates
from swiftjax.loops.options import LoopOptions

_DEFAULTS = LoopOptions()

__all__ = ["LoopChunk", "loop_chunk_frames", "filter_by_chunks", "loop_edge"]


class LoopChunk(NamedTuple):
    """The loop-centric chunk of one loop ``(i, j)``, ``i > j`` (a pytree; vmap-able).

    Attributes:
        frames: ``[4h]`` int32 frame indices: ``2h`` frames around ``i`` (the later end) then
            ``2h`` around ``j``; each half lies inside one temporal chunk (shifted inward at
            chunk borders and sequence ends).
        chunk_i, chunk_j: int32 temporal chunk of each half (the chunk containing the frame in
            which its window needs the least shift; ties go to the earlier chunk).
        local_i, local_j: int32 positions of frames ``i`` and ``j`` inside ``frames``.
        valid: bool; ``False`` when a chunk is shorter than ``2h`` frames or the two halves
            overlap (then ``frames`` is still well-formed but should not be used).
    """

    frames: jax.Array
    chunk_i: jax.Array
    chunk_j: jax.Array
    local_i: jax.Array
    local_j: jax.Array
    valid: jax.Array


def _chunk_window(f, starts, ends, half_window: int):
    """Best chunk for frame ``f`` and the start of its ``2h`` window inside that chunk."""
    contains = (starts <= f) & (f < ends)
    room = jnp.minimum(f - starts, ends - 1 - f)  # frames available on the shorter side
    c = jnp.argmax(jnp.where(contains, room, -1))
    s, e = starts[c], ends[c]
    w0 = jnp.clip(f - half_window, s, jnp.maximum(e - 2 * half_window, s))
    ok = contains[c] & (e - s >= 2 * half_window)
    return c.astype(jnp.int32), w0, ok


def _bounds(schedule: ChunkSchedule) -> tuple[jax.Array, jax.Array]:
    """``(starts, ends)`` of ``schedule`` as int32 device arrays."""
    return jnp.asarray(schedule.starts, jnp.int32), jnp.asarray(schedule.ends, jnp.int32)


@functools.partial(jax.jit, static_argnames=("half_window",))
def _loop_chunk_frames(i, j, starts, ends, half_window: int) -> LoopChunk:
    i = jnp.asarray(i, jnp.int32)
    j = jnp.asarray(j, jnp.int32)
    ci, wi, oki = _chunk_window(i, starts, ends, half_window)
    cj, wj, okj = _chunk_window(j, starts, ends, half_window)
    h2 = 2 * half_window
    rng = jnp.arange(h2, dtype=jnp.int32)
    frames = jnp.concatenate([wi + rng, wj + rng])
    disjoint = (wi + h2 <= wj) | (wj + h2 <= wi)
    return LoopChunk(frames, ci, cj, i - wi, h2 + j - wj, oki & okj & disjoint)


def loop_chunk_frames(
    i: Int[ArrayLike, ""], j: Int[ArrayLike, ""], schedule: ChunkSchedule, half_window: int = _DEFAULTS.half_window
) -> LoopChunk:
    """Frames of the loop-centric chunk of loop ``(i, j)``: ``loop_chunk_frames(i, j, schedule,
    half_window=10)`` (20 + 20 = 40 frames).

    For each end ``f`` (``i`` first, then ``j``) the window ``[f − h, f + h)`` is placed
    inside the temporal chunk ``[s, e)`` holding ``f`` with the most room around it, shifted
    inward at chunk borders: its start is ``clip(f − h, s, e − 2h)``, with ``s, e`` the
    schedule's ``starts`` and ``ends``.  The pair is taken as given (call with ``i > j`` to
    get the later range first).

    Args:
        i, j: int scalars (or batch with ``jax.vmap``).
        schedule: the :class:`~swiftjax.chunks.ChunkSchedule` of the sequence.
        half_window: static int ``h`` (default ``LoopOptions().half_window``).

    Recompiles per number of chunks ``T`` and ``half_window``.
    """
    starts, ends = _bounds(schedule)
    return _loop_chunk_frames(i, j, starts, ends, half_window)


@jax.jit
def _filter_by_chunks(candidates: LoopCandidates, starts, ends) -> LoopCandidates:
    m = candidates.pairs.shape[0]
    valid = jnp.arange(m) < candidates.count
    i = jnp.where(valid, candidates.pairs[:, 0], 0)
    j = jnp.where(valid, candidates.pairs[:, 1], 0)
    same_chunk = jnp.any(
        (starts[None] <= jnp.minimum(i, j)[:, None]) & (jnp.maximum(i, j)[:, None] < ends[None]),
        axis=1,
    )
    ci = jax.vmap(lambda f: _chunk_window(f, starts, ends, 0)[0])(i)
    cj = jax.vmap(lambda f: _chunk_window(f, starts, ends, 0)[0])(j)
    keep0 = valid & ~same_chunk
    same_pair = (ci[:, None] == ci[None, :]) & (cj[:, None] == cj[None, :])
    earlier = jnp.arange(m)[None, :] < jnp.arange(m)[:, None]
    # candidates are sorted by score, so "an earlier kept row with the same chunk pair"
    # means a better loop already represents this chunk pair
    keep = keep0 & ~jnp.any(same_pair & earlier & keep0[None, :], axis=1)
    order = jnp.argsort(~keep, stable=True)  # kept rows first, score order preserved
    count = jnp.sum(keep).astype(jnp.int32)
    rowok = jnp.arange(m) < count
    pairs = jnp.where(rowok[:, None], candidates.pairs[order], -1)
    scores = jnp.where(rowok, candidates.scores[order], -jnp.inf)
    return LoopCandidates(pairs, scores, count, candidates.truncated, candidates.threshold)


def filter_by_chunks(candidates: LoopCandidates, schedule: ChunkSchedule) -> LoopCandidates:
    """The authors' post-processing of NMS output: drop pairs whose two frames lie in one
    temporal chunk of ``schedule`` (a :class:`~swiftjax.chunks.ChunkSchedule`), and keep only the best-scoring loop per pair of
    chunks ``(c_i, c_j)`` (chunks assigned as in :func:`loop_chunk_frames`).  Order (by score)
    is preserved.

    ``O(M²)`` comparisons over the ``M`` candidate rows (``M`` is a few hundred).  One jitted
    call; recompiles per ``M`` and number of chunks.
    """
    starts, ends = _bounds(schedule)
    return _filter_by_chunks(candidates, starts, ends)


@functools.partial(jax.jit, static_argnames=("half_window",))
def _loop_chunks(pairs, starts, ends, half_window):
    """:func:`loop_chunk_frames` for every row of ``pairs [M, 2]``."""
    return jax.vmap(lambda a, b: _loop_chunk_frames(a, b, starts, ends, half_window))(pairs[:, 0], pairs[:, 1])


@jax.jit
def loop_edge(
    S_i_loop: Float[ArrayLike, "*batch 8"], S_j_loop: Float[ArrayLike, "*batch 8"]
) -> Float[Array, "*batch 8"]:
    """Loop edge ``S_{j,loop} · S_{i,loop}⁻¹``, Sim(3) ``[..., 8]``.

    ``S_{x,loop}`` maps loop-chunk coordinates into temporal chunk ``c_x``'s coordinates
    (the alignment of the loop chunk's ``x`` half to its temporal chunk).  The result maps
    chunk ``c_i`` coordinates into chunk ``c_j`` coordinates, so in the pose-graph
    convention (edge ``a → b`` maps ``b`` into ``a``, ``≈ S_a⁻¹ S_b``) it is the edge
    ``c_j → c_i``: ``≈ S_{c_j}⁻¹ S_{c_i}``.
    """
    return sim3.compose(S_j_loop, sim3.inverse(S_i_loop))

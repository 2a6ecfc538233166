"""Loop detection without the future: proposals as chunks arrive, the offline pass at the end.

Offline, :func:`~swiftjax.loops.find_loops` whitens and calibrates on *every* frame, so it
cannot start before the end.  :class:`OnlineLoopDetector` is fed each chunk's per-frame
descriptors ``g⁰`` (``add(frames, descriptors)``; a later chunk's copy of an overlap frame
replaces the earlier one, as offline) and proposes loop candidates of the prefix seen so far;
:meth:`OnlineLoopDetector.finish` is ``find_loops`` on the whole sequence, so the final loop
list is the offline one, bit for bit.  After each chunk (``n`` frames seen)::

    whitening W_k fitted on the first n_k frames   (refit schedule below, or given)
    Z = ℓ2((g¹_{0..n-1} − μ_k) W_k), padded with NaN rows to a bucket
    candidates = detect_loops(Z, calibrate on the prefix's best scores)   (as offline, on n rows)
      ──keep pairs whose later frame i is new──► filter_by_chunks (chunks seen so far)
      ──Loop list──not within ±nms_radius (both ends) of an earlier proposal──► proposals

"New" later frames: this chunk's, and at the first detection every frame.  Refits
(:func:`refit_due`) happen when ``n`` first reaches ``m``, ``2m``, ``4m``, ... with
``m`` = :func:`min_descriptors` ``= 2 (min_separation + 1)`` (202 at the defaults); each is
:func:`fit_sequence_whitening`, the fit ``find_loops`` makes for ``n`` frames.  Below ``m``
nothing is proposed.  Why ``m``, what is lost early in a sequence and the false-alarm count per
drive: docs/design.md, "Online loop detection"; cost per chunk: docs/performance/loops.md.

Shapes and compiles: descriptors live in a host buffer of ``cap = m 2^k ≥ n`` rows (doubling
buckets), the whitened prefix is NaN-padded to it (a NaN row never matches and is ignored by
the calibration), so :func:`~swiftjax.loops.detect_loops` compiles once per bucket and
whitening dimension: ``O(log n)`` compiles in a drive, as are the fits and the chunk filter
(chunk starts padded to a power-of-two count).

``--whitening-from RUN_DIR``: :func:`load_whitening` fits on the descriptors an offline run
recorded in its chunk files (which :func:`~swiftjax.pipeline.rundir.prune` keeps), as
``find_loops`` did for that run.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import pathlib
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from swiftjax.chunks import ChunkSchedule
from swiftjax.io.images import InputError
from swiftjax.loops._checks import _check_finite
from swiftjax.loops.descriptors import Whitening, fit_whitening, power_normalize, whiten
from swiftjax.loops.detection import LoopCandidates, detect_loops
from swiftjax.loops.find import Loop, as_loops, effective_settings, find_loops
from swiftjax.loops.loop_chunk import filter_by_chunks
from swiftjax.loops.options import LoopOptions

__all__ = [
    "OnlineLoopDetector",
    "WhiteningSourceError",
    "fit_sequence_whitening",
    "load_whitening",
    "min_descriptors",
    "recorded_descriptors",
    "refit_due",
]

_NO_CHUNK = 2**30  # start = end of a padding chunk: it contains no frame


def min_descriptors(options: LoopOptions) -> int:
    """``m = 2 (min_separation + 1)``: the first whitening fit and the first proposal wait
    for ``m`` frames (the module docstring derives it)."""
    return 2 * (options.min_separation + 1)


def refit_due(n: int, fitted_at: int | None, minimum: int) -> bool:
    """Whether ``n`` descriptors call for a new fit when the last one used ``fitted_at``
    (``None``: none yet): ``n`` has reached the next size of ``m, 2m, 4m, ...`` above
    ``fitted_at``."""
    if n < minimum:
        return False
    if fitted_at is None:
        return True
    level = minimum
    while level <= fitted_at:
        level *= 2
    return n >= level


def fit_sequence_whitening(descriptors: Float[ArrayLike, "N d"], options: LoopOptions | None = None) -> Whitening:
    """The whitening :func:`~swiftjax.loops.find_loops` fits for ``descriptors [N, d]`` (``g⁰``,
    finite): ``fit_whitening`` of ``g¹ = power_normalize(g⁰)`` (or of ``g⁰`` for
    ``fit_on="raw"`` / ``rule="authors"``) with ``d′`` from
    :func:`~swiftjax.loops.find.effective_settings`.  Bit-identical to ``find_loops``'s
    ``details["whitening"]``.  Recompiles per ``N``."""
    o = LoopOptions() if options is None else options
    G = np.asarray(descriptors)
    _check_finite(G, "fit_sequence_whitening: descriptors")
    _, fit_on, dim = effective_settings(o, G.shape[0])
    fit = G if fit_on == "raw" else power_normalize(G, o.beta)
    return fit_whitening(fit, o.remove, dim, o.eps, o.max_samples)


class WhiteningSourceError(InputError):
    """``--whitening-from RUN_DIR`` is unusable; the message is one line naming the path."""


def recorded_descriptors(run_dir: str | os.PathLike[str]) -> Float[np.ndarray, "N d"]:
    """The per-frame descriptors ``g⁰ [N, d]`` float32 an offline run recorded in
    ``run_dir/chunks/chunk_*.npz`` (each file's ``descriptors`` rows at its ``frames``; in
    overlaps the later chunk's copy, as the temporal stage assembles them).

    Raises:
        WhiteningSourceError: no chunk store, no chunk file, a file without descriptors or
            frames, an unreadable file, or frames not covering ``0 .. N-1``.
    """
    from swiftjax.io.chunk_store import ChunkCorruptError, ChunkStore

    run = pathlib.Path(run_dir)
    root = run / "chunks"
    if not root.is_dir():
        raise WhiteningSourceError(f"{run}: not a run directory with recorded descriptors (no {root})")
    store = ChunkStore(run)
    chunks = store.indices("chunk")
    if not chunks:
        raise WhiteningSourceError(f"{root}: no chunk files (chunk_*.npz), so no descriptors to fit a whitening on")
    rows: dict[int, np.ndarray] = {}
    d = None
    for t in chunks:
        path = store.path("chunk", t)
        try:
            desc = store.load_array("chunk", t, "descriptors")
            frames = store.load_extra("chunk", t, names=("frames",)).get("frames")
        except (ChunkCorruptError, OSError) as err:
            raise WhiteningSourceError(f"{path}: cannot read its descriptors ({err})") from None
        if desc is None or frames is None or desc.ndim != 2 or len(desc) != len(frames):
            raise WhiteningSourceError(f"{path}: records no per-frame descriptors with their frames")
        if d is not None and desc.shape[1] != d:
            raise WhiteningSourceError(f"{path}: {desc.shape[1]}-D descriptors, other chunk files have {d}-D")
        d = desc.shape[1]
        for f, g in zip(np.asarray(frames, np.int64), desc):
            rows[int(f)] = g
    n = max(rows) + 1
    if len(rows) != n or min(rows) != 0:
        missing = sorted(set(range(n)) - set(rows))
        raise WhiteningSourceError(
            f"{root}: the chunk files miss the descriptors of {len(missing)} frame(s), first {missing[0]}"
        )
    return np.stack([rows[f] for f in range(n)]).astype(np.float32)


def load_whitening(
    run_dir: str | os.PathLike[str], options: LoopOptions | None = None, *, descriptor_dim: int | None = None
) -> Whitening:
    """The whitening of the offline run in ``run_dir`` (``--whitening-from RUN_DIR``):
    :func:`fit_sequence_whitening` of :func:`recorded_descriptors`, i.e. the one its
    ``find_loops`` used (same ``options``).

    Raises:
        WhiteningSourceError: one line naming the path: nothing usable recorded, non-finite
            descriptors, too few frames to fit, or ``descriptor_dim`` given and different from
            the recorded dimension.
    """
    G = recorded_descriptors(run_dir)
    if descriptor_dim is not None and G.shape[1] != descriptor_dim:
        raise WhiteningSourceError(
            f"{pathlib.Path(run_dir)}: its descriptors are {G.shape[1]}-D but this run's are {descriptor_dim}-D "
            "(another model?): its whitening does not apply"
        )
    try:
        return fit_sequence_whitening(G, options)
    except ValueError as err:
        raise WhiteningSourceError(
            f"{pathlib.Path(run_dir)}: cannot fit a whitening on its descriptors ({err})"
        ) from None


@functools.partial(jax.jit, static_argnames="width")
def _whitened_prefix(w: Whitening, G: jax.Array, n: jax.Array, beta: jax.Array, width: int) -> jax.Array:
    """``ẑ`` of the first ``n`` rows of ``G [cap, d]``, NaN below (no match, not calibrated),
    with zero columns after ``d′`` up to ``width`` (a prefix whose ``d′`` grows with its
    length, :func:`~swiftjax.loops.find.effective_settings`, keeps one detection program per
    ``cap``; zeros add nothing to a similarity): ``[cap, max(d′, width)]``.  Recompiles per
    ``(cap, d, d′, width)``."""
    Z = whiten(w, power_normalize(G, beta))
    Z = jnp.pad(Z, ((0, 0), (0, max(width - Z.shape[1], 0))))
    return jnp.where((jnp.arange(G.shape[0]) < n)[:, None], Z, jnp.nan)


@jax.jit
def _later_end_from(cand: LoopCandidates, first: jax.Array) -> LoopCandidates:
    """The candidates whose later frame ``i >= first`` (score order kept).  Recompiles per ``M``."""
    m = cand.pairs.shape[0]
    keep = (jnp.arange(m) < cand.count) & (cand.pairs[:, 0] >= first)
    order = jnp.argsort(~keep, stable=True)
    count = jnp.sum(keep).astype(jnp.int32)
    row = jnp.arange(m) < count
    return cand._replace(
        pairs=jnp.where(row[:, None], cand.pairs[order], -1),
        scores=jnp.where(row, cand.scores[order], -jnp.inf),
        count=count,
    )


def _bucket(n: int, base: int) -> int:
    size = base
    while size < n:
        size *= 2
    return size


class OnlineLoopDetector:
    """Loop candidates of the prefix as chunks arrive; the offline loops at :meth:`finish`.

    Args:
        options: the loop options (``LoopOptions()``), as for ``find_loops``.
        whitening: a whitening to use throughout instead of refitting on the prefix
            (:func:`load_whitening`); ``whitening_source`` names where it came from (for
            messages).

    Attributes:
        n: frames seen (``0 .. n-1``).
        whitening: the whitening in use (``None`` before the first fit).
        fits: the prefix sizes at which the whitening was (re)fitted.
        threshold: the last prefix threshold (``inf`` before the first detection).
        proposed: every proposal so far (:class:`~swiftjax.loops.Loop`), in order.

    Not thread-safe (one caller feeds it).  Frames must arrive in order: each ``add`` starts
    at or before ``n`` (an overlap) and ends after it.
    """

    def __init__(
        self,
        options: LoopOptions | None = None,
        *,
        whitening: Whitening | None = None,
        whitening_source: str | None = None,
    ) -> None:
        self.options = LoopOptions() if options is None else options
        self.minimum = min_descriptors(self.options)
        self.given = whitening is not None
        self.whitening = whitening
        self.whitening_source = whitening_source or "the given whitening"
        self.fits: list[int] = []
        self.threshold = float("inf")
        self.proposed: list[Loop] = []
        self.n = 0
        self._G: np.ndarray | None = None  # [cap, d] host buffer
        self._starts: list[int] = []
        self._ends: list[int] = []
        self._fixed_threshold: float | None = None
        self._tested = 0  # frames 0.._tested-1 were tested as a loop's later end
        self._warmed: set[tuple[str, int, int]] = set()  # what warm_up compiled

    @property
    def descriptors(self) -> np.ndarray:
        """``[n, d]`` float32, the prefix as the temporal stage assembles it (a copy)."""
        if self._G is None:
            return np.zeros((0, 0), np.float32)
        return self._G[: self.n].copy()

    def _schedule(self, padded: bool, rows: int | None = None) -> ChunkSchedule:
        """The chunks as added (``padded``: with chunks holding no frame up to ``rows``, by
        default the chunk count's bucket, so that the programs compile once per bucket)."""
        starts, ends = np.asarray(self._starts, np.int64), np.asarray(self._ends, np.int64)
        if padded:
            t = _bucket(len(starts), 4) if rows is None else rows
            starts = np.concatenate([starts, np.full(t - len(starts), _NO_CHUNK)])
            ends = np.concatenate([ends, np.full(t - len(ends), _NO_CHUNK)])
        size = int(max(e - s for s, e in zip(self._starts, self._ends)))
        overlap = max([0] + [e - s for s, e in zip(self._starts[1:], self._ends[:-1])])
        return ChunkSchedule(self.n, size, overlap, starts, ends)

    def add(self, frames: ArrayLike, descriptors: ArrayLike, *, propose: bool = True) -> list[Loop]:
        """Feed one chunk: ``frames [S]`` (consecutive indices) and their ``descriptors [S, d]``
        ``g⁰``.  Returns the new proposals (loops of the prefix whose chunk pair was not
        proposed before), each a :class:`~swiftjax.loops.Loop` whose loop-centric chunk lies
        in the chunks seen so far.

        ``propose=False``: only record the chunk (no refit, no detection; returns ``[]``); the
        next proposing ``add`` tests every frame not tested yet as a loop's later end, so
        feeding chunks ``a, b, c`` with ``propose`` only on ``c`` proposes what ``c``'s
        prefix holds for all three (a worker catching up does one pass, not three).

        Raises:
            ValueError: frames not consecutive or not continuing the prefix, shape mismatch,
                non-finite descriptors.
            WhiteningSourceError: a descriptor dimension other than the given whitening's
                (naming ``whitening_source``; one line).
        """
        f = np.asarray(frames, np.int64).reshape(-1)
        G = np.asarray(descriptors, np.float32)
        if G.ndim != 2 or len(G) != len(f) or len(f) == 0:
            raise ValueError(f"OnlineLoopDetector.add: descriptors {G.shape} for {len(f)} frames (want [S, d], S >= 1)")
        if np.any(np.diff(f) != 1) or f[0] > self.n or f[-1] < self.n:
            raise ValueError(
                f"OnlineLoopDetector.add: frames {f[0]}..{f[-1]} do not continue the {self.n} frames seen "
                "(consecutive, starting at or before the next frame)"
            )
        _check_finite(G, f"OnlineLoopDetector.add: descriptors of frames {f[0]}..{f[-1]}")
        d = G.shape[1]
        if self._G is not None and d != self._G.shape[1]:
            raise ValueError(f"OnlineLoopDetector.add: {d}-D descriptors after {self._G.shape[1]}-D ones")
        if self.given and d != self.whitening.mean.shape[-1]:
            raise WhiteningSourceError(
                f"{self.whitening_source}: its whitening is for {self.whitening.mean.shape[-1]}-D descriptors but "
                f"this run's are {d}-D"
            )
        end = int(f[-1]) + 1
        cap = _bucket(end, self.minimum)
        if self._G is None or self._G.shape[0] < cap:
            grown = np.zeros((cap, d), np.float32)
            if self._G is not None:
                grown[: self.n] = self._G[: self.n]
            self._G = grown
        self._G[f] = G
        self.n = end
        self._starts.append(int(f[0]))
        self._ends.append(end)
        if not propose:
            return []
        if not self.given and refit_due(self.n, self.fits[-1] if self.fits else None, self.minimum):
            self.whitening = fit_sequence_whitening(self._G[: self.n], self.options)
            self.fits.append(self.n)
            self._fixed_threshold = effective_settings(self.options, self.n)[0]
        if self.whitening is None or self.n < self.minimum:
            return []
        return self._propose(int(f[0]))

    def _propose(self, first: int) -> list[Loop]:
        o = self.options
        if self._fixed_threshold is None:  # a given whitening: the fixed rule's floor for its d'
            self._fixed_threshold = effective_settings(
                dataclasses.replace(o, dim=self.whitening.dim_requested), self.whitening.dim_requested * 4
            )[0]
        assert self._G is not None
        found, threshold = self._detect(self._G, min(first, self._tested), self._schedule(padded=True))
        self.threshold = threshold
        self._tested = self.n
        new: list[Loop] = []
        r = o.nms_radius
        for lp in found:
            # a loop within ±r of an earlier proposal at both ends is that proposal again
            if not any(abs(lp.i - p.i) <= r and abs(lp.j - p.j) <= r for p in self.proposed + new):
                new.append(lp)
        self.proposed += new
        return new

    def _detect(
        self,
        G: np.ndarray,
        first: int,
        schedule: ChunkSchedule,
        whitening: Whitening | None = None,
        n: int | None = None,
    ) -> tuple[list[Loop], float]:
        """``(loops, threshold)``: the loops among the first :attr:`n` rows of ``G [cap, d]``
        (the rest ignored) whose later frame is at least ``first``, each with its loop chunk in
        ``schedule`` (padded), and the prefix threshold (``n``: the prefix size, by default
        :attr:`n`).  Compiles per ``cap`` and ``schedule`` size (and whitening, ``whitening`` or the current one)."""
        o = self.options
        w = self.whitening if whitening is None else whitening
        assert w is not None and self._fixed_threshold is not None
        width = min(o.dim, G.shape[1])
        Z = _whitened_prefix(w, jnp.asarray(G), jnp.int32(self.n if n is None else n), jnp.float32(o.beta), width)
        cand = detect_loops(
            Z,
            self._fixed_threshold,
            o.min_separation,
            o.nms_radius,
            o.top_k,
            o.max_loops,
            nms=o.nms,
            calibrate=o.rule == "adaptive",
            false_alarms=o.false_alarms,
            throw=False,
        )
        threshold = float(cand.threshold)
        cand = _later_end_from(cand, jnp.int32(first))
        return as_loops(filter_by_chunks(cand, schedule), schedule, o.half_window), threshold

    def warm_up(self) -> bool:
        """:meth:`warm_plan`, run at once: True when it compiled something."""
        plan = self.warm_plan()
        if plan is None:
            return False
        plan()
        return True

    def warm_plan(self) -> Callable[[], None] | None:
        """The next program set the prefix's growth will need, to compile ahead while the
        caller has time (each once; None when all are planned): the whitening fit of the next
        refit's prefix size (predicted from the chunk stride; fitted on the prefix's rows
        repeated), then detection on the descriptor buffer of twice the size and on the chunk
        table of twice the chunks (on the current prefix).  The plan holds copies: it may run on another thread
        while chunks are added.  Its results are dropped: nothing the detector proposes or
        records changes."""
        if self._G is None or self.whitening is None or self._fixed_threshold is None or len(self._ends) < 2:
            return None
        cap, rows, d, n = self._G.shape[0], _bucket(len(self._starts), 4), self._G.shape[1], self.n
        prefix = self._G[:n].copy()
        if not self.given and ("fit", cap, 0) not in self._warmed:
            self._warmed.add(("fit", cap, 0))
            level = self.minimum
            while level <= self.fits[-1]:
                level *= 2
            stride = max(self._ends[-1] - self._ends[-2], 1)
            size = self._ends[-1] + max(-(-(level - self._ends[-1]) // stride), 1) * stride
            options = self.options

            def fit() -> None:
                fit_sequence_whitening(np.resize(prefix, (size, d)), options)

            return fit
        w = self.whitening
        for size, b in ((cap, 2 * rows), (2 * cap, rows), (2 * cap, 2 * rows)):
            if ("detect", size, b) in self._warmed:
                continue
            self._warmed.add(("detect", size, b))
            schedule = self._schedule(padded=True, rows=b)

            def detect(size: int = size, schedule: ChunkSchedule = schedule) -> None:
                G = np.zeros((size, d), np.float32)
                G[:n] = prefix
                self._detect(G, n, schedule, w, n=n)

            return detect
        return None

    def finish(
        self, schedule: ChunkSchedule | None = None, **kwargs: Any
    ) -> list[Loop] | tuple[list[Loop], dict[str, Any]]:
        """Loop detection over the whole sequence exactly as offline: ``find_loops(descriptors,
        schedule, options, **kwargs)`` (``schedule``: the chunks as added, by default; with
        ``return_details=True`` also its details).  The result is the offline one, bit for bit
        (same inputs, same call)."""
        if self.n == 0:
            raise ValueError("OnlineLoopDetector.finish: no frame was added")
        return find_loops(
            self.descriptors, self._schedule(padded=False) if schedule is None else schedule, self.options, **kwargs
        )

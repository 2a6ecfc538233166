"""Synthetic Sim(3) pose graphs with known truth (tests, notebooks and ``bench/bench_posegraph.py``).

* :func:`circle_graph` — the benchmark anchor graph: ``N`` nodes on a circle, ``N`` odometry
  edges ``(i, i+1 mod N)`` and ``N`` random loop edges, noise ``sigma = 0.05`` translation,
  ``0.01`` rotation, ``0.01`` log-scale (information ``diag(1/sigma^2)``).
* :func:`chain_graph` — a KITTI-like chunk chain: a smooth random drive with per-chunk scale
  drift, odometry edges ``(t, t+1)`` and a loop edge every ``loop_every`` nodes back to a node
  ``loop_every`` earlier.

Measurements are ``Z = T_i^-1 T_j exp(n)``, ``n ~ N(0, diag(sigma^2))`` in our tangent order;
the initial guess is dead reckoning (odometry composed from node 0, which is fixed at truth).
Host-side NumPy + :mod:`swiftjax.sim3`, always float64 (x64 is enabled locally).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from swiftjax import sim3

__all__ = ["SyntheticGraph", "circle_graph", "chain_graph", "NOISE"]

#: (translation, rotation, log-scale) standard deviations of the anchor benchmark.
NOISE = (0.05, 0.01, 0.01)


class SyntheticGraph(NamedTuple):
    truth: np.ndarray  # [N, 8]
    initial: np.ndarray  # [N, 8]
    edges: np.ndarray  # [E, 2] int
    measurements: np.ndarray  # [E, 8]
    information: np.ndarray  # [E, 7] (diagonal)
    is_loop: np.ndarray  # [E] bool


def _sigma_vector(noise: tuple[float, float, float]) -> np.ndarray:
    t, r, s = noise
    return np.array([t, t, t, r, r, r, s], np.float64)


def _measure(truth, edges, noise, rng):
    sig = _sigma_vector(noise)
    rel = np.asarray(sim3.between(truth[edges[:, 0]], truth[edges[:, 1]]), np.float64)
    n = rng.normal(size=(len(edges), 7)) * sig
    meas = np.asarray(sim3.compose(rel, sim3.exp(n)), np.float64)
    info = np.broadcast_to(1.0 / sig**2, (len(edges), 7)).copy()
    return meas, info


def _dead_reckoning(truth, edges, meas):
    n = truth.shape[0]
    init = np.zeros_like(truth)
    init[0] = truth[0]
    odo = {(int(i), int(j)): k for k, (i, j) in enumerate(edges)}
    for t in range(1, n):
        k = odo[(t - 1, t)]
        init[t] = np.asarray(sim3.normalize(sim3.compose(init[t - 1], meas[k])), np.float64)
    return init


def _loops(n, num_loops, rng, exclude):
    pairs: set[tuple[int, int]] = set()
    while len(pairs) < num_loops:
        i, j = sorted(rng.integers(0, n, size=2).tolist())
        if j - i < 2 or (i, j) in exclude or (i == 0 and j == n - 1):
            continue
        pairs.add((i, j))
    return np.array(sorted(pairs), np.int64).reshape(-1, 2)


def circle_graph(
    n: int,
    *,
    num_loops: int | None = None,
    noise: tuple[float, float, float] = NOISE,
    scale_spread: float = 0.1,
    seed: int = 0,
) -> SyntheticGraph:
    """Circle of ``n`` nodes (radius ``n / 2 pi``, 1 unit apart), ``n`` odometry + ``num_loops``
    (default ``n``) random loop edges; true scales ``exp(N(0, scale_spread^2))``.  Always float64."""
    with jax.enable_x64(True):
        return _circle_graph(n, num_loops, noise, scale_spread, seed)


def _circle_graph(n, num_loops, noise, scale_spread, seed) -> SyntheticGraph:
    rng = np.random.default_rng(seed)
    num_loops = n if num_loops is None else num_loops
    ang = 2 * np.pi * np.arange(n) / n
    radius = n / (2 * np.pi)
    t = np.stack([radius * np.cos(ang), radius * np.sin(ang), 0.2 * rng.normal(size=n)], 1)
    omega = np.stack([0.05 * rng.normal(size=n), 0.05 * rng.normal(size=n), ang + np.pi / 2], 1)
    q = np.asarray(sim3.exp(np.concatenate([np.zeros((n, 3)), omega, np.zeros((n, 1))], 1)))[:, 3:7]
    s = np.exp(scale_spread * rng.normal(size=n))
    truth = np.concatenate([t, q, s[:, None]], 1)
    odo = np.stack([np.arange(n), (np.arange(n) + 1) % n], 1)
    odo_set = {(min(a, b), max(a, b)) for a, b in odo.tolist()}
    loops = _loops(n, num_loops, rng, odo_set)
    edges = np.concatenate([odo, loops]).astype(np.int64)
    meas, info = _measure(truth, edges, noise, rng)
    init = _dead_reckoning(truth, edges, meas)
    is_loop = np.concatenate([np.zeros(len(odo), bool), np.ones(len(loops), bool)])
    return SyntheticGraph(truth, init, edges, meas, info, is_loop)


def chain_graph(
    n: int,
    *,
    loop_every: int = 300,
    noise: tuple[float, float, float] = NOISE,
    scale_drift: float = 0.02,
    seed: int = 0,
) -> SyntheticGraph:
    """KITTI-like chain: ``n - 1`` odometry edges and one loop edge ``(t - loop_every, t)``
    for every ``t`` that is a positive multiple of ``loop_every`` (none when ``n <= loop_every``).
    Always float64."""
    with jax.enable_x64(True):
        return _chain_graph(n, loop_every, noise, scale_drift, seed)


def _chain_graph(n, loop_every, noise, scale_drift, seed) -> SyntheticGraph:
    rng = np.random.default_rng(seed)
    heading = np.cumsum(0.05 * rng.normal(size=n))
    step = np.stack([np.cos(heading), np.sin(heading), 0.01 * rng.normal(size=n)], 1) * 10.0
    t = np.cumsum(step, axis=0) - step[0]
    omega = np.stack([0.01 * rng.normal(size=n), 0.01 * rng.normal(size=n), heading], 1)
    q = np.asarray(sim3.exp(np.concatenate([np.zeros((n, 3)), omega, np.zeros((n, 1))], 1)))[:, 3:7]
    s = np.exp(np.cumsum(scale_drift * rng.normal(size=n)))
    truth = np.concatenate([t, q, s[:, None]], 1)
    odo = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    ends = np.arange(loop_every, n, loop_every)
    loops = np.stack([ends - loop_every, ends], 1).reshape(-1, 2)
    edges = np.concatenate([odo, loops]).astype(np.int64)
    meas, info = _measure(truth, edges, noise, rng)
    init = _dead_reckoning(truth, edges, meas)
    is_loop = np.concatenate([np.zeros(len(odo), bool), np.ones(len(loops), bool)])
    return SyntheticGraph(truth, init, edges, meas, info, is_loop)

"""GTSAM 4.3 baseline for the same Sim(3) pose graph (tests and benchmark only; lazy ``gtsam`` import).

Conventions translated here (checked in ``tests/test_posegraph_gtsam.py``):

* GTSAM's ``Similarity3(R, t, s)`` maps ``p -> s (R p + t)``; our element ``(t, q, s)`` maps
  ``p -> s R p + t``, so ours is ``Similarity3(R, t / s, s)``.
* GTSAM orders its tangent ``[omega, u, lambda]``; at the identity ``u`` = our ``rho`` and
  ``lambda`` = our ``sigma``, so an information matrix is permuted ``(rho, omega, sigma) ->
  (omega, rho, sigma)``.
* ``BetweenFactorSimilarity3`` has the residual ``Logmap(Z^-1 S_i^-1 S_j)`` in GTSAM's own
  Logmap and an approximate Jacobian away from zero residual; ``graph.error`` is
  ``1/2 sum r^T Omega r`` in GTSAM's coordinates.  Compare solutions with *our* cost
  function evaluated at both optima.
* Fixed nodes become ``NonlinearEqualitySimilarity3`` (hard constraints).
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

__all__ = ["GtsamResult", "to_gtsam", "from_gtsam", "build_graph", "solve_gtsam", "TANGENT_PERMUTATION"]

#: ``ours[TANGENT_PERMUTATION]`` is in GTSAM's order ``[omega, u, lambda]``.
TANGENT_PERMUTATION = np.array([3, 4, 5, 0, 1, 2, 6])


class GtsamResult(NamedTuple):
    poses: np.ndarray  # [N, 8], our layout
    error_initial: float  # GTSAM's own graph.error
    error_final: float
    iterations: int
    seconds: float  # optimizer construction + optimize()


def to_gtsam(pose: np.ndarray):
    """Our ``(t, q_xyzw, s)`` -> ``gtsam.Similarity3``."""
    import gtsam

    t, q, s = pose[0:3], pose[3:7], float(pose[7])
    rot = gtsam.Rot3.Quaternion(float(q[3]), float(q[0]), float(q[1]), float(q[2]))
    return gtsam.Similarity3(rot, np.asarray(t, np.float64) / s, s)


def from_gtsam(sim) -> np.ndarray:
    """``gtsam.Similarity3`` -> our ``(t, q_xyzw, s)``."""
    q = sim.rotation().toQuaternion()
    s = float(sim.scale())
    t = np.asarray(sim.translation(), np.float64) * s
    quat = np.array([q.x(), q.y(), q.z(), q.w()])
    if quat[3] < 0:
        quat = -quat
    return np.concatenate([t, quat, [s]])


def build_graph(poses, edges, measurements, information, fixed):
    """``(gtsam.NonlinearFactorGraph, gtsam.Values)`` of the graph: ``BetweenFactorSimilarity3`` per
    edge (information permuted to GTSAM's tangent order), ``NonlinearEqualitySimilarity3`` per
    fixed node."""
    import gtsam

    poses = np.asarray(poses, np.float64)
    info = np.asarray(information, np.float64)
    perm = TANGENT_PERMUTATION
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for n, p in enumerate(poses):
        values.insert(n, to_gtsam(p))
        if fixed[n]:
            graph.add(gtsam.NonlinearEqualitySimilarity3(n, to_gtsam(p)))
    for k, (i, j) in enumerate(np.asarray(edges)):
        om = info[k][np.ix_(perm, perm)]
        noise = gtsam.noiseModel.Gaussian.Information(om)
        graph.add(
            gtsam.BetweenFactorSimilarity3(int(i), int(j), to_gtsam(np.asarray(measurements[k], np.float64)), noise)
        )
    return graph, values


def solve_gtsam(
    poses: np.ndarray,
    edges: np.ndarray,
    measurements: np.ndarray,
    information: np.ndarray,
    fixed: np.ndarray,
    *,
    rtol: float = 1e-5,
    atol: float = 1e-5,
    max_iterations: int = 100,
) -> GtsamResult:
    """GTSAM LM (multifrontal Cholesky, default ordering) on the graph; returns our layout."""
    import gtsam

    graph, values = build_graph(poses, edges, measurements, information, fixed)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(rtol)
    params.setAbsoluteErrorTol(atol)
    params.setMaxIterations(max_iterations)
    t0 = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    out = opt.optimize()
    seconds = time.perf_counter() - t0
    result = np.stack([from_gtsam(out.atSimilarity3(n)) for n in range(len(poses))])
    return GtsamResult(result, float(graph.error(values)), float(graph.error(out)), int(opt.iterations()), seconds)

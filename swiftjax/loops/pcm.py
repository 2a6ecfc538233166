"""Pairwise consistency of loop edges (PCM): which loops agree with each other and the odometry.

PCM (Mangelson et al. ICRA 2018, as Kimera-RPGO; :func:`pairwise_consistency`,
:func:`max_consistent_set`): two loop edges ``a``, ``b`` and the odometry chain between their
ends form a cycle that must be the identity up to the odometry's accumulated uncertainty.  With
dead-reckoning chunk poses ``X_t`` every loop ``k = (p_k → q_k)``, ``p_k < q_k``, implies the
drift ``D_k = X_{p_k} Z_k X_{q_k}⁻¹``; the cycle is ``E_ab = D_a⁻¹ D_b``.  A right perturbation
``δ_e`` of temporal edge ``e`` moves ``D_k`` by ``−Σ_{e ∈ [p_k, q_k)} Ad(X_{e+1}) δ_e``, so with
world covariances ``C_e = Ad(X_{e+1}) Σ_e Ad(X_{e+1})ᵀ`` and prefix sums ``P_t = Σ_{e < t} C_e``
(``P[[p, q)] = P_q − P_p``; linearised at ``E_ab = I``, the hypothesis tested)::

    Σ_ab = P[a] + P[b] − 2 P[a ∩ b] + Ad(X_{q_a}) Σ_{Z_a} Ad(X_{q_a})ᵀ + (same for b)
    m_ab = sqrt(rᵀ Σ_ab⁻¹ r),   r = log(E_ab)                      (whitened residual)

``m_ab <= threshold`` makes ``a`` and ``b`` consistent; the accepted loops are a maximum clique
of the consistency graph (exact Bron–Kerbosch with pivoting on the host; ties broken by the
larger sum of dense consistency scores).  ``Σ_e`` comes from a drift model
(:func:`odometry_covariance`).  :func:`graph_consistency` runs the same test over every loop
edge of a pose graph (Kimera-RPGO's recipe, before GNC) with the derived threshold
(:func:`consistency_threshold`; ``m_ab²`` is chi-squared with 7 degrees of freedom for two
inliers, and the ``N = M (M − 1) / 2`` pair tests share the error budget, Bonferroni)::

    threshold = sqrt(chi2_7⁻¹(1 − (1 − p) / N))          (p = 0.99: 5.36 for M = 10, 6.23 for M = 30)

``odometry_check=True`` adds Kimera's per-edge test (``m_k`` with ``Σ = P[[p, q)] + Ad Σ_Z Adᵀ``,
the same threshold over ``N + M`` tests).  :func:`consistent_solve` is the whole back end: PCM,
GNC-TLS on the consistent set, then data snooping of the loops on the solved map
(:func:`data_snooping`: Baarda's test ``T_e = r_eᵀ (Σ_e ∓ J_e H⁻¹ J_eᵀ)⁺ r_e ~ chi2_7``,
:func:`snooping_statistics`, the bound ``chi2_7⁻¹(1 − (1 − p) / M)`` shared by the ``M`` loops).
What PCM cannot reject, why ``odometry_check`` is off, how the back end treats equal weights
and what no residual test can find: docs/design.md, "Pairwise consistency".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from swiftjax import sim3
from swiftjax._compile import quick_jit

__all__ = [
    "odometry_covariance",
    "loop_covariance",
    "pairwise_consistency",
    "max_consistent_set",
    "consistency_threshold",
    "GraphConsistency",
    "graph_consistency",
    "snooping_statistics",
    "data_snooping",
    "consistent_solve",
]


@jax.jit
def odometry_covariance(
    relative: Float[ArrayLike, "*batch 8"],
    sigma_rot: float | Float[ArrayLike, ""],
    sigma_trans: float | Float[ArrayLike, ""],
    sigma_scale: float | Float[ArrayLike, ""],
) -> Float[Array, "*batch 7 7"]:
    """Drift model of the temporal edges: diagonal covariances ``[E, 7, 7]`` in ``(ρ, ω, σ)``.

    For edge ``Z_e = (t, R, s)`` (right perturbation ``Z_e exp(δ)``): ``std(ρ) = sigma_trans ·
    |t| / s`` (relative to the edge's own translation, expressed in the source chunk's
    units), ``std(ω) = sigma_rot`` rad, ``std(σ) = sigma_scale``.  ``relative`` is ``[E, 8]``.
    """
    Z = jnp.asarray(relative)
    rho = sigma_trans * jnp.linalg.norm(sim3.translation(Z), axis=-1) / sim3.scale(Z)
    rho = jnp.maximum(rho, jnp.finfo(Z.dtype).tiny)
    ones = jnp.ones_like(rho)
    var = jnp.stack([rho, rho, rho] + [sigma_rot * ones] * 3 + [sigma_scale * ones], -1) ** 2
    return var[..., :, None] * jnp.eye(7, dtype=Z.dtype)


@jax.jit
def loop_covariance(
    Z: Float[ArrayLike, "*batch 8"],
    sigma_rot: float | Float[ArrayLike, ""],
    sigma_trans: float | Float[ArrayLike, ""],
    sigma_scale: float | Float[ArrayLike, ""],
) -> Float[Array, "*batch 7 7"]:
    """Covariance ``[M, 7, 7]`` of loop edges ``Z [M, 8]``: ``std(ρ) = sigma_trans`` in the
    source chunk's units (VGGT normalises each chunk's scene scale), ``sigma_rot``, ``sigma_scale``."""
    Z = jnp.asarray(Z)
    ones = jnp.ones(Z.shape[:-1], Z.dtype)
    var = jnp.stack([sigma_trans * ones] * 3 + [sigma_rot * ones] * 3 + [sigma_scale * ones], -1) ** 2
    return var[..., :, None] * jnp.eye(7, dtype=Z.dtype)


@quick_jit  # runs once per pipeline on M <= a few hundred loops: compile dominates
def pairwise_consistency(
    chain_poses: Float[ArrayLike, "T 8"],
    odometry_cov: Float[ArrayLike, "T-1 7 7"],
    loop_nodes: Int[ArrayLike, "M 2"],
    Z: Float[ArrayLike, "M 8"],
    loop_cov: Float[ArrayLike, "M 7 7"],
) -> Float[Array, "M M"]:
    """Whitened cycle residuals ``m_ab`` of every pair of loop edges (PCM): ``[M, M]``.

    Args:
        chain_poses: ``[T, 8]`` dead-reckoning chunk-to-world poses ``X_t`` (chained
            temporal edges, ``X_{t+1} = X_t Z_{t→t+1}``).
        odometry_cov: ``[T-1, 7, 7]`` covariance of each temporal edge's right perturbation.
        loop_nodes: ``[M, 2]`` int ``(p, q)``, ``p < q``: loop edge ``p → q``, ``Z ≈ S_p⁻¹ S_q``.
        Z: ``[M, 8]`` loop measurements.
        loop_cov: ``[M, 7, 7]`` covariance of each loop edge's right perturbation.

    Returns:
        ``[M, M]`` symmetric, zero diagonal; ``m_ab = sqrt(rᵀ Σ_ab⁻¹ r)``, ``r = log(D_a⁻¹ D_b)``
        (module docstring).  Run it in float64 (``jax.enable_x64``) for long sequences: the
        world-frame covariances carry lever arms of the route's size.  Recompiles per
        ``(T, M)`` and dtype.
    """
    X = jnp.asarray(chain_poses)
    dt = X.dtype
    Z = jnp.asarray(Z, dt)
    p, q = jnp.asarray(loop_nodes)[:, 0], jnp.asarray(loop_nodes)[:, 1]
    Ad = sim3.adjoint(X)  # [T, 7, 7]
    C = Ad[1:] @ jnp.asarray(odometry_cov, dt) @ jnp.swapaxes(Ad[1:], -1, -2)
    P = jnp.concatenate([jnp.zeros((1, 7, 7), dt), jnp.cumsum(C, axis=0)])  # [T, 7, 7]
    D = sim3.compose(sim3.compose(X[p], Z), sim3.inverse(X[q]))  # [M, 8]
    Aq = Ad[q]
    L = Aq @ jnp.asarray(loop_cov, dt) @ jnp.swapaxes(Aq, -1, -2)  # [M, 7, 7]
    span = P[q] - P[p]
    lo = jnp.maximum(p[:, None], p[None, :])
    hi = jnp.minimum(q[:, None], q[None, :])
    inter = jnp.where((hi > lo)[..., None, None], P[jnp.maximum(hi, lo)] - P[lo], 0)
    cov = span[:, None] + span[None, :] - 2 * inter + L[:, None] + L[None, :]  # [M, M, 7, 7]
    E = sim3.compose(sim3.inverse(D)[:, None], D[None, :])  # [M, M, 8]
    r = sim3.log(E)
    eye = jnp.eye(r.shape[0], dtype=bool)
    cov = jnp.where(eye[..., None, None], jnp.eye(7, dtype=dt), cov)
    m2 = jnp.einsum("abi,abi->ab", r, jnp.linalg.solve(cov, r[..., None])[..., 0])
    m = jnp.sqrt(jnp.maximum(m2, 0))
    m = jnp.where(jnp.isfinite(m), m, jnp.inf)
    return jnp.where(eye, 0, 0.5 * (m + m.T))


def max_consistent_set(
    consistent: ArrayLike,  # bool [M, M]: checked here, with a ValueError (host boundary)
    weights: Sequence[float] | Float[ArrayLike, " M"] | None = None,
    pair_cost: Float[ArrayLike, "M M"] | None = None,
) -> list[int]:
    """A maximum clique of the boolean consistency graph ``consistent [M, M]`` (host).

    Exact: Bron–Kerbosch with pivoting (Tomita et al. 2006), exponential in the worst case
    but instant for the tens of candidates of a sequence.  Among cliques of the maximum size
    the one with the smallest sum of ``pair_cost [M, M]`` over its pairs wins (when given), then
    the one with the largest sum of ``weights``, then the lexicographically smallest.
    The diagonal is ignored; an empty graph gives ``[]``.
    """
    A = np.asarray(consistent, bool)
    m = A.shape[0]
    if A.shape != (m, m):
        raise ValueError(f"max_consistent_set: consistent must be square, got {A.shape}")
    A = A & A.T & ~np.eye(m, dtype=bool)
    w = np.zeros(m) if weights is None else np.asarray(weights, np.float64)
    cost = np.zeros((m, m)) if pair_cost is None else np.asarray(pair_cost, np.float64)
    nbrs = [set(np.flatnonzero(A[k]).tolist()) for k in range(m)]
    best: list[Any] = [(-1, -np.inf, -np.inf), []]

    def expand(R: list[int], P: set[int], X: set[int]) -> None:
        if not P and not X:
            key = (len(R), -0.5 * float(cost[np.ix_(R, R)].sum()) if R else 0.0, float(w[R].sum()) if R else 0.0)
            if key > best[0] or (key == best[0] and sorted(R) < best[1]):
                best[0], best[1] = key, sorted(R)
            return
        if len(R) + len(P) < best[0][0]:
            return  # cannot reach the best size
        pivot = max(P | X, key=lambda u: len(P & nbrs[u]))
        for v in sorted(P - nbrs[pivot]):
            expand(R + [v], P & nbrs[v], X & nbrs[v])
            P = P - {v}
            X = X | {v}

    if m:
        expand([], set(range(m)), set())
    return best[1]


def consistency_threshold(num_loops: int, probability: float = 0.99, *, extra_tests: int = 0) -> float:
    """The PCM bound on ``m_ab`` (module docstring): ``sqrt(chi2_7⁻¹(1 − (1 − p) / N))`` with
    ``N = M (M − 1) / 2 + extra_tests`` (at least 1) tests sharing the error budget ``1 − p``."""
    from scipy.stats import chi2

    if not 0.0 < probability < 1.0:
        raise ValueError(f"consistency probability must be in (0, 1), not {probability!r}")
    tests = max(num_loops * (num_loops - 1) // 2 + extra_tests, 1)
    return float(np.sqrt(chi2.isf((1.0 - probability) / tests, 7)))


def _put(a: np.ndarray) -> Array:
    """A NumPy array on the device without a program (``jnp.asarray`` compiles a copy per shape)."""
    return jax.device_put(np.ascontiguousarray(a))


@quick_jit  # one program per size bucket instead of a compile per primitive
def _linearize(poses: Float[Array, "N 8"], problem: Any) -> tuple[Array, Array, Array]:
    """:func:`swiftjax.posegraph.residuals_and_jacobians`, jitted: ``(r [E, 7], J_i, J_j [E, 7, 7])``."""
    from swiftjax.posegraph import residuals_and_jacobians

    return residuals_and_jacobians(poses, problem)


def snooping_statistics(
    problem: Any, poses: Float[ArrayLike, "N 8"], active: Bool[ArrayLike, " E"], *, pad: bool | tuple[int, int] = True
) -> tuple[Float[np.ndarray, " E"], Int[np.ndarray, " E"]]:
    """Baarda's test statistic of every edge at a least-squares solution (host, float64):
    ``(T [E], dof [E])``.

    Linearise at ``poses`` (right perturbations of the free nodes; ``J_e`` the ``[7, 7 n]`` block
    row of edge ``e``), ``H = Σ_{e active} J_eᵀ Ω_e J_e`` the normal matrix of the ``active``
    edges (bool ``[E]``; ``Ω_e = problem.information`` is the noise model, ``Σ_e = Ω_e⁻¹``).  If
    every active edge is an inlier, the least-squares residual ``r_e`` of an active edge has the
    covariance ``Q_e = Σ_e − J_e H⁻¹ J_eᵀ``, and the residual of an edge left out (its prediction
    from the others) ``Q_e = Σ_e + J_e H⁻¹ J_eᵀ``; so::

        T_e = r_eᵀ Q_e⁺ r_e  ~  chi2(dof_e),   dof_e = rank Q_e

    (the w-test of data snooping, Baarda 1968, for a 7-D observation; for an active edge it is
    the test of its leave-one-out prediction, which is why a wrong edge the map has bent to
    cannot hide: ``Q_e`` shrinks with the bending).  ``Q_e`` is used whitened, ``I ∓ Wᵀ J_e H⁻¹
    J_eᵀ W`` (``Ω_e = W Wᵀ``): eigenvalues in ``[0, 1]`` (the redundancy numbers) for an active
    edge; directions with redundancy below ``1e-9`` (that nothing else checks) are left out of
    ``T`` and ``dof``.  Dense ``H``: ``O((7 n)³)``, fine for the hundreds of chunks of a sequence.

    Compiles: the linearisation is the one XLA program, run on the problem padded as
    :func:`swiftjax.posegraph.optimize` pads it (``pad``:
    :func:`~swiftjax.posegraph.problem.padded_sizes`; padded nodes fixed, padded edges
    masked), so it recompiles only for a new ``(N_bucket, E_bucket)`` (or dtype); the padded
    rows are dropped before the host algebra, which sees exactly the unpadded graph.
    """
    import scipy.linalg

    from swiftjax.posegraph import pad_problem, padded_sizes

    edges = np.asarray(problem.edges, np.int64)
    E, N = len(edges), problem.num_nodes
    nb, eb = padded_sizes(N, E, pad)
    with jax.enable_x64(True):
        x = np.asarray(poses, np.float64)
        x = np.concatenate([x, np.broadcast_to(np.asarray([0, 0, 0, 0, 0, 0, 1, 1.0]), (nb - N, 8))])
        r, Ji, Jj = _linearize(x, pad_problem(problem, nb, eb))
    r, Ji, Jj = (np.asarray(a, np.float64)[:E] for a in (r, Ji, Jj))
    free = ~np.asarray(problem.fixed, bool)
    col = np.cumsum(free) - 1
    nf = int(free.sum())
    active = np.asarray(active, bool)
    J = np.zeros((E, 7, nf, 7))
    rows = np.arange(E)
    for end, Jb in ((edges[:, 0], Ji), (edges[:, 1], Jj)):
        ok = free[end]
        J[rows[ok], :, col[end[ok]], :] += Jb[ok]  # an edge's two ends are distinct nodes
    J = J.reshape(E, 7, 7 * nf)
    om = np.asarray(problem.information, np.float64)
    W = np.linalg.cholesky(0.5 * (om + np.swapaxes(om, -1, -2)))  # Ω = W Wᵀ
    Jw = np.einsum("eji,eja->eia", W, J)  # Wᵀ J_e
    Ja = Jw[active].reshape(-1, 7 * nf)
    H, rhs = Ja.T @ Ja, Jw.reshape(-1, 7 * nf).T
    try:
        HiJ = scipy.linalg.cho_solve(scipy.linalg.cho_factor(H), rhs)
    except np.linalg.LinAlgError:  # a gauge the fixed nodes leave free: the minimum-norm inverse
        HiJ = np.linalg.pinv(H, hermitian=True) @ rhs
    A = np.einsum("eia,aej->eij", Jw, HiJ.reshape(7 * nf, E, 7))  # Wᵀ J_e H⁻¹ J_eᵀ W
    Q = np.eye(7) + np.where(active, -1.0, 1.0)[:, None, None] * A
    lam, V = np.linalg.eigh(0.5 * (Q + np.swapaxes(Q, -1, -2)))
    u = np.einsum("eij,ej->ei", np.swapaxes(V, -1, -2), np.einsum("eji,ej->ei", W, r))
    keep = lam > 1e-9
    T = np.sum(np.where(keep, u**2 / np.where(keep, lam, 1.0), 0.0), -1)
    return T, keep.sum(-1)


class GraphConsistency(NamedTuple):
    """Outcome of :func:`graph_consistency` (host NumPy).

    ``kept [E]``: False exactly for the loop edges outside the maximum consistent set (every
    other edge True); ``loop_edges [M]``: the indices of the tested loop edges;
    ``residuals [M, M]``: ``m_ab``; ``odometry_residuals [M]``: ``m_k`` against the odometry
    alone (computed always, used with ``odometry_check``); ``threshold``; ``problem``: the input
    with ``edge_mask &= kept`` (the graph GNC starts from); ``readmitted [E]`` / ``snooped [E]``
    (from :func:`consistent_solve`, else None): the loop edges data snooping put back (PCM or GNC
    had left them out and they fit the solved map) / took out (:func:`data_snooping`).
    """

    kept: np.ndarray
    loop_edges: np.ndarray
    residuals: np.ndarray
    odometry_residuals: np.ndarray
    threshold: float
    problem: Any
    readmitted: np.ndarray | None = None
    snooped: np.ndarray | None = None


def _chain_edges(edges: np.ndarray, plain: np.ndarray, num: int) -> np.ndarray:
    """Index of the plain edge ``(t, t + 1)`` for every ``t < num − 1`` (ValueError if one is missing)."""
    index = {(int(a), int(b)): k for k, (a, b) in enumerate(edges) if plain[k]}
    missing = [t for t in range(num - 1) if (t, t + 1) not in index]
    if missing:
        raise ValueError(
            f"graph_consistency: no odometry edge ({missing[0]}, {missing[0] + 1}) among the "
            "non-robust edges (the test needs the chain t -> t + 1)"
        )
    return np.array([index[(t, t + 1)] for t in range(num - 1)], np.int64)


def graph_consistency(
    problem: Any,
    covariance: Float[ArrayLike, "E 7 7"] | None = None,
    *,
    num_chain_nodes: int | None = None,
    probability: float = 0.99,
    odometry_check: bool = False,
    pad: bool | tuple[int, int] = True,
) -> GraphConsistency:
    """Pairwise consistency of every loop edge of a pose graph before its robust solve (host).

    Args:
        problem: a :class:`swiftjax.posegraph.Problem`; its loop edges are the ``robust`` ones
            (both ends below ``num_chain_nodes``), its odometry the non-robust edges
            ``(t, t + 1)``, ``t < num_chain_nodes − 1`` (all must be present).  Other edges
            (priors, an anchor) are neither tested nor used.
        covariance: ``[E, 7, 7]`` covariance of each edge's right perturbation; default the
            inverse of ``problem.information`` (right when the information matches the noise).
            Give the noise model here when the solve's weights do not describe the noise (equal
            weights).
        num_chain_nodes: the chain's length (default every node).
        probability: ``p`` of :func:`consistency_threshold`.
        odometry_check: also reject a loop whose own cycle with the odometry fails (module
            docstring).

    A loop edge ``(a, b)`` with ``a > b`` is tested as ``(b, a)`` with ``Z⁻¹`` and covariance
    ``Ad(Z) Σ Ad(Z)ᵀ`` (``(Z exp δ)⁻¹ = Z⁻¹ exp(−Ad(Z) δ)``).  Runs
    :func:`pairwise_consistency` in float64 and :func:`max_consistent_set`.  Compiles: with
    ``pad`` (:func:`~swiftjax.posegraph.problem.padded_sizes`; True by default) the chain is
    padded to ``T_bucket`` nodes by identity links of zero covariance and the ``M`` loops (plus
    the virtual one below) to ``M_bucket`` by ``(0, 0)`` identity loops of unit covariance;
    their rows and columns are dropped, so the programs recompile only for a new
    ``(T_bucket, M_bucket)`` (with ``pad=(min_nodes, min_edges)``: ``M_bucket`` at least the
    bucket of ``min_edges − min_nodes + 2``); ``pad=False`` compiles per ``(T, M)``.  Ties between cliques of one size go to the most consistent one
    (the smallest sum of ``m_ab²`` over its pairs), then to the one that agrees best with the
    odometry (the smallest sum of ``m_k``: of two inconsistent loops alone, the one the
    odometry supports).
    """
    from swiftjax.posegraph import bucket_size, chain_poses

    edges = np.asarray(problem.edges, np.int64)
    E = len(edges)
    mask = np.asarray(problem.edge_mask, bool)
    robust = np.asarray(problem.robust, bool) & mask
    T = problem.num_nodes if num_chain_nodes is None else int(num_chain_nodes)
    meas = np.asarray(problem.measurements, np.float64)
    if covariance is None:
        info = np.asarray(problem.information, np.float64)
        cov = np.linalg.inv(np.where(mask[:, None, None], info, np.eye(7)))
    else:
        cov = np.asarray(covariance, np.float64)
        if cov.shape != (E, 7, 7):
            raise ValueError(f"graph_consistency: covariance has shape {cov.shape}; expected [E, 7, 7] = [{E}, 7, 7]")
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    chain = _chain_edges(edges, mask & ~robust, T)
    loop = np.flatnonzero(robust & (edges.max(1) < T) & (edges[:, 0] != edges[:, 1]))
    M = len(loop)
    kept = np.ones(E, bool)
    Tb, Mb = T, M + 1
    if pad is not False:
        lo_n, lo_e = (0, 0) if pad is True else (int(v) for v in pad)
        Tb, Mb = bucket_size(max(T, lo_n)), bucket_size(max(M + 1, lo_e - lo_n + 2))
    ident = np.array([0, 0, 0, 0, 0, 0, 1, 1], np.float64)
    with jax.enable_x64(True):
        odo = np.concatenate([meas[chain], np.broadcast_to(ident, (Tb - T, 8))])
        X = chain_poses(odo, pad=pad is not False)
        odo_cov = np.concatenate([cov[chain], np.zeros((Tb - T, 7, 7))])
        # the M loops, a virtual identity loop (0, 0) with zero covariance (its pair with loop
        # k is loop k's cycle with the odometry alone), then (0, 0) identity padding of unit
        # covariance
        nodes = np.concatenate([edges[loop], np.zeros((Mb - M, 2), np.int64)])
        Z = np.concatenate([meas[loop], np.broadcast_to(ident, (Mb - M, 8))])
        L = np.concatenate([cov[loop], np.zeros((1, 7, 7)), np.broadcast_to(np.eye(7), (Mb - M - 1, 7, 7))])
        flip = nodes[:, 0] > nodes[:, 1]
        if flip.any():  # on every row: one program per M_bucket
            Ad = np.asarray(sim3.adjoint(Z))
            Zi = np.asarray(sim3.inverse(Z))
            L = np.where(flip[:, None, None], Ad @ L @ np.swapaxes(Ad, -1, -2), L)
            Z = np.where(flip[:, None], Zi, Z)
            nodes = np.where(flip[:, None], nodes[:, ::-1], nodes)
        m = np.asarray(pairwise_consistency(X, odo_cov, nodes, Z, L), np.float64)
    m, m_odo = m[:M, :M], m[:M, M]
    threshold = consistency_threshold(M, probability, extra_tests=M if odometry_check else 0)
    ok = m <= threshold
    alone = m_odo <= threshold if odometry_check else np.ones(M, bool)
    ok &= alone[:, None] & alone[None, :]
    clique = [k for k in max_consistent_set(ok, -m_odo, pair_cost=np.where(ok, m**2, 0)) if alone[k]]
    kept[loop] = np.isin(np.arange(M), clique)
    out = dataclasses.replace(problem, edge_mask=_put(mask & kept))
    return GraphConsistency(kept, loop, m, m_odo, threshold, out)


def data_snooping(
    problem: Any,
    result: Any,
    active: Bool[ArrayLike, " E"],
    loop_edges: Int[ArrayLike, " M"],
    *,
    probability: float = 0.99,
    options: Any = None,
    throw: bool = True,
    pad: bool | tuple[int, int] = True,
) -> tuple[Any, Bool[np.ndarray, " E"], Bool[np.ndarray, " E"], Bool[np.ndarray, " E"]]:
    """Iterative data snooping of the loop edges around a robust solve (host):
    ``(Result, active [E], removed [E], readmitted [E])``.

    ``problem``'s information is the noise model; ``result`` a solve of it on the ``active``
    edges (bool ``[E]``); ``loop_edges`` ``[M]`` the edge indices under test.  Every other edge
    stays as ``active`` says.  With :func:`snooping_statistics` at the current solve and the
    error budget ``1 − p`` shared by the ``M`` loop tests (Bonferroni, as
    :func:`consistency_threshold`)::

        reject   the active loop with the smallest  P(chi2(dof_e) > T_e) < (1 − p) / M
        else readmit the left-out loop with the largest P(chi2(dof_e) > T_e) >= (1 − p) / M

    one edge per step, each step followed by a plain least-squares solve (``options`` with
    ``kernel=None``, from the current poses); an edge rejected here is never readmitted, so at
    most ``2 M`` steps.  Stops when no active loop fails and no left-out loop fits.  When
    nothing changes ``result`` is returned as it is.  ``pad`` goes to
    :func:`snooping_statistics` and every :func:`swiftjax.posegraph.optimize` (one program set
    per size bucket).
    """
    from scipy.stats import chi2

    from swiftjax import posegraph

    options = (posegraph.GraphOptions() if options is None else options).replace(kernel=None)
    active = np.array(active, bool)
    loops = np.asarray(loop_edges, np.int64)
    removed = np.zeros_like(active)
    readmitted = np.zeros_like(active)
    alpha = (1.0 - probability) / max(len(loops), 1)
    for _ in range(2 * len(loops)):
        T, dof = snooping_statistics(problem, result.poses, active, pad=pad)
        pval = np.where(dof > 0, chi2.sf(T, np.maximum(dof, 1)), 1.0)
        inside = loops[active[loops]]
        outside = loops[~active[loops] & ~removed[loops]]
        if inside.size and pval[inside].min() < alpha:
            k = inside[np.argmin(pval[inside])]
            active[k], removed[k] = False, True
        elif outside.size and pval[outside].max() >= alpha:
            k = outside[np.argmax(pval[outside])]
            active[k], readmitted[k] = True, True
        else:
            break
        start = jnp.asarray(result.poses, jnp.asarray(problem.poses).dtype)
        result = posegraph.optimize(
            dataclasses.replace(problem, poses=start, edge_mask=_put(active)), options, throw=throw, pad=pad
        )
        result = dataclasses.replace(result, inlier_weights=active.astype(np.float64))
    return result, active, removed, readmitted


def consistent_solve(
    problem: Any,
    covariance: Float[ArrayLike, "E 7 7"] | None = None,
    *,
    num_chain_nodes: int | None = None,
    probability: float = 0.99,
    odometry_check: bool = False,
    options: Any = None,
    throw: bool = True,
    pad: bool | tuple[int, int] = True,
) -> tuple[Any, GraphConsistency]:
    """PCM over every loop edge (:func:`graph_consistency`), GNC-TLS on the consistent set, then
    data snooping of the loops (:func:`data_snooping`): ``(Result, GraphConsistency)`` (host;
    Kimera-RPGO's recipe with Baarda's test after it).

    ``options``: the :class:`~swiftjax.posegraph.GraphOptions` of every
    :func:`swiftjax.posegraph.optimize` call (default ``GraphOptions()``; ``kernel`` is set to
    ``"gnc"``; its ``kernel_scale`` is the inlier threshold in the noise model's whitened
    units); ``throw`` is :func:`~swiftjax.posegraph.optimize`'s.  With
    ``covariance`` None the noise model is ``problem.information``.  With a ``covariance`` (the
    noise model when the solve's information is something else, e.g. equal weights): GNC and the
    snooping run on the problem with ``information = covariance⁻¹`` to decide the inliers, then
    plain least squares with ``problem.information`` on the edges they kept, from the same start.

    Why snooping after GNC: a maximum clique is one of possibly several, and loops that are
    slightly wrong pass many pair tests (a few metres is inside the odometry's drift over a
    long revisit), so the clique can hold them and leave a true loop out; on the solved map a
    wrong loop the map has bent to shows a small residual against ``Σ_e`` (GNC's test) but not
    against ``Σ_e − J H⁻¹ Jᵀ``, and a left-out loop is judged by its prediction from the map
    (``Σ_e + J H⁻¹ Jᵀ``), not by ``Σ_e`` alone.  ``Result.inlier_weights``: GNC's when snooping
    changed nothing, else 1 for the kept edges and 0 for the others; ``gnc_iterations``: GNC's
    outer iterations.  ``GraphConsistency.readmitted`` / ``snooped``: the loop edges snooping
    put back / took out.

    What compiles (``pad``, default True: every program runs on the graph padded to a size
    bucket, :func:`swiftjax.posegraph.problem.padded_sizes`, padded nodes fixed and padded
    edges masked with weight 0, and the answer equals the exact-size solve to float rounding):
    the chain's scan per ``bucket_size(T − 1)``, :func:`pairwise_consistency` per
    ``(T_bucket, M_bucket)``, the LM programs and the snooping linearisation per
    ``(N_bucket, E_bucket)``, each also per dtype and per static option
    (:class:`~swiftjax.posegraph.GraphOptions`' ``max_steps``, ``damping``, ``initialization``,
    the resolved linear solver); nothing else (thresholds, probabilities, weights, the loops'
    values never recompile).  A graph that grows by one chunk or loop per call therefore
    compiles only when it crosses into a new bucket (4 buckets per doubling); a caller that
    knows its capacity passes ``pad=(max_nodes, max_edges)`` and compiles once for every size
    up to it.  ``pad=False``: programs for the exact sizes (a compile per call on a growing
    graph).
    """
    from swiftjax import posegraph

    check = graph_consistency(
        problem,
        covariance,
        num_chain_nodes=num_chain_nodes,
        probability=probability,
        odometry_check=odometry_check,
        pad=pad,
    )
    options = (posegraph.GraphOptions() if options is None else options).replace(kernel="gnc")
    decide = check.problem
    if covariance is not None:  # GNC decides on the graph whitened by the noise model
        cov = np.asarray(covariance, np.float64)
        info = np.linalg.inv(0.5 * (cov + np.swapaxes(cov, -1, -2)))
        info = _put((0.5 * (info + np.swapaxes(info, -1, -2))).astype(np.asarray(problem.poses).dtype))
        decide = dataclasses.replace(decide, information=info)
    res = posegraph.optimize(decide, options, throw=throw, pad=pad)
    active = np.asarray(decide.edge_mask, bool) & (res.inlier_weights >= 0.5)
    res2, active, snooped, readmitted = data_snooping(
        decide, res, active, check.loop_edges, probability=probability, options=options, throw=throw, pad=pad
    )
    res = res if res2 is res else dataclasses.replace(res2, gnc_iterations=res.gnc_iterations)
    check = check._replace(readmitted=readmitted, snooped=snooped)
    if covariance is None:
        return res, check
    final = posegraph.optimize(
        dataclasses.replace(problem, edge_mask=_put(active)), options.replace(kernel=None), throw=throw, pad=pad
    )
    return dataclasses.replace(final, inlier_weights=res.inlier_weights, gnc_iterations=res.gnc_iterations), check

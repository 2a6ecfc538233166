"""Information matrices of Sim(3) alignments: how well one Umeyama solve pins its edge down.

A pose-graph edge ``Z`` estimated by the weighted Umeyama solve of :mod:`swiftjax.align`
(``dst ~= s R src + t``) has an error that we write as a right perturbation, ``Z_true = Z exp(delta)``
— the pose graph's residual ``r = log(Z^-1 S_i^-1 S_j)`` is ``delta`` at the truth — so its
information matrix is the inverse covariance of ``delta`` (tangent order ``(rho, omega, sigma)``).

**Derivation.**  Linearise the point-to-point cost ``f(delta) = sum_i w_i |y_i - Z exp(delta) x_i|^2``
at the solution: ``exp(delta) x = x + rho + omega x x + sigma x + O(delta^2)``, so the residual's
Jacobian is ``J_i = -s R G_i`` with ``G_i = [I, -[x_i]x, x_i]`` (3 x 7) and ``J_i^T J_i = s^2 G_i^T G_i``
(``R`` drops out).  With ``W = sum w``, ``m = sum w x / W`` and ``M = sum w x x^T / W`` (moments of the
*source* points in the source frame; ``q = tr M``)::

    H = sum_i w_i J_i^T J_i = s^2 W A,     A = [[ I,      -[m]x,      m ],
                                                [ [m]x,   q I - M,    0 ],
                                                [ m^T,    0,          q ]]

(``G^T G``'s omega-sigma block is ``[x]x x = 0``).  Independent, isotropic residuals of variance
``sigma^2`` per coordinate give ``Cov(delta) = sigma^2 H^-1`` (Gauss–Markov; the Umeyama solve is the
exact minimiser, so this is also the Laplace approximation of its error), with the unbiased
``sigma^2 = sum w |e|^2 / (3 n - 7) = W rms^2 / (3 n - 7)`` (``n`` points, 7 parameters).  Hence::

    Omega = H / sigma^2 = s^2 (3 n - 7) / rms^2 * A * (n_eff / n)

The last factor is the one modelling choice: the pixels of a predicted depth map are not independent
samples (VGGT's errors are smooth over a ViT patch and beyond), so ``n_eff = n / pixels_per_sample``
independent residuals are assumed (``pixels_per_sample = 1``: the textbook iid formula, what the
Monte-Carlo test checks).  ``rms`` is floored at ``rms_floor`` times the source spread
``sqrt(tr(M - m m^T))`` (float32's closed-form ``rms`` bottoms out near ``3e-4 x`` the spread; a
noise-free fit would otherwise claim infinite information).

A loop edge ``Z = S_j,loop S_i,loop^-1`` (:func:`swiftjax.loops.loop_edge`) combines two independent
half alignments: with ``S_x,true = S_x exp(d_x)``, ``Z_true = Z exp(Ad(S_i,loop) (d_j - d_i))``, so
``Cov(Z) = Ad(S_i,loop) (Cov_i + Cov_j) Ad(S_i,loop)^T`` (:func:`loop_edge_information`).

Every function is pure, jit-able and takes leading batch axes; each compiles once per shape/dtype.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float, Real

from swiftjax import sim3, so3

if TYPE_CHECKING:
    from swiftjax.align.chunk_pair import AlignInfo

__all__ = [
    "EdgeInformation",
    "source_moments",
    "umeyama_information",
    "umeyama_information_from_points",
    "alignment_information",
    "loop_edge_information",
    "DEFAULT_RMS_FLOOR",
]

#: ``rms`` is floored at this fraction of the source points' spread (see the module docstring).
DEFAULT_RMS_FLOOR = 1e-3


class EdgeInformation(NamedTuple):
    """An edge's information matrix and whether it could be formed.

    Attributes:
        information: ``[..., 7, 7]`` symmetric positive definite when ``valid``; zeros otherwise.
        valid: False when fewer than 3 points were used (``3 n - 7 <= 0``), a moment is not finite,
            or ``A`` is singular (all source points collinear: the rotation about their line is free).
    """

    information: Array
    valid: Array


@jax.jit
def source_moments(
    src: Float[ArrayLike, "*b n 3"], weights: Float[ArrayLike, "*b n"] | None = None
) -> tuple[Float[Array, "*b 3"], Float[Array, "*b 3 3"]]:
    """``(m [..., 3], C [..., 3, 3])``: weighted mean and covariance ``sum w (x - m)(x - m)^T / W`` of
    ``src [..., N, 3]`` (points with a non-finite coordinate or ``w <= 0`` ignored; zeros if none)."""
    src = jnp.asarray(src)
    w = jnp.ones(src.shape[:-1], src.dtype) if weights is None else jnp.asarray(weights, src.dtype)
    ok = (w > 0) & jnp.isfinite(w) & jnp.all(jnp.isfinite(src), -1)
    w = jnp.where(ok, w, 0)
    x = jnp.where(ok[..., None], src, 0)
    W = jnp.sum(w, -1)
    Ws = jnp.where(W > 0, W, 1)[..., None]
    m = jnp.sum(w[..., None] * x, -2) / Ws
    d = jnp.where(ok[..., None], x - m[..., None, :], 0)
    C = jnp.einsum("...n,...ni,...nj->...ij", w, d, d) / Ws[..., None]
    return m, C


@jax.jit
def umeyama_information(
    scale: Float[ArrayLike, "*b"],
    num_points: Real[ArrayLike, "*b"],
    rms: Float[ArrayLike, "*b"],
    src_mean: Float[ArrayLike, "*b 3"],
    src_covariance: Float[ArrayLike, "*b 3 3"],
    *,
    pixels_per_sample: Float[ArrayLike, ""] = 1.0,
    rms_floor: Float[ArrayLike, ""] = DEFAULT_RMS_FLOOR,
) -> EdgeInformation:
    """``Omega = s^2 (3 n - 7) / rms^2 * A(m, M) * n_eff / n`` (module docstring).

    Args:
        scale: ``[...]`` the estimate's scale ``s``.
        num_points: ``[...]`` points used ``n``.
        rms: ``[...]`` weighted RMS residual ``sqrt(sum w |dst - S src|^2 / W)`` (dst units).
        src_mean, src_covariance: ``[..., 3]``, ``[..., 3, 3]`` weighted mean and covariance of the
            source points (:func:`source_moments`; :class:`swiftjax.align.AlignInfo` carries them).
        pixels_per_sample: ``n / n_eff`` (traced).
        rms_floor: ``rms`` floor as a fraction of ``sqrt(tr src_covariance)`` (traced).

    Returns:
        :class:`EdgeInformation` (``[..., 7, 7]``).  Pure; one compile per shape/dtype.
    """
    m = jnp.asarray(src_mean)
    dtype = m.dtype if jnp.issubdtype(m.dtype, jnp.floating) else jnp.float32
    m = m.astype(dtype)
    C = jnp.asarray(src_covariance, dtype)
    s = jnp.asarray(scale, dtype)
    n = jnp.asarray(num_points).astype(dtype)
    rms = jnp.asarray(rms, dtype)
    M = C + m[..., :, None] * m[..., None, :]
    q = jnp.trace(M, axis1=-2, axis2=-1)
    eye = jnp.eye(3, dtype=dtype)
    k = so3.hat(m)
    zero31 = jnp.zeros(m.shape + (1,), dtype)
    top = jnp.concatenate([jnp.broadcast_to(eye, k.shape), -k, m[..., :, None]], -1)
    mid = jnp.concatenate([k, q[..., None, None] * eye - M, zero31], -1)
    bottom = jnp.concatenate([m, jnp.zeros_like(m), q[..., None]], -1)[..., None, :]
    A = jnp.concatenate([top, mid, bottom], -2)

    spread = jnp.sqrt(jnp.maximum(jnp.trace(C, axis1=-2, axis2=-1), 0))
    r = jnp.maximum(rms, jnp.asarray(rms_floor, dtype) * spread)
    dof = 3 * n - 7
    factor = s * s * dof / jnp.where(r > 0, r * r, 1) / jnp.asarray(pixels_per_sample, dtype)
    omega = factor[..., None, None] * A
    # A is PSD by construction (a sum of G^T G); it is singular iff the points are collinear.
    # Test on the scatter's second eigenvalue (A's own conditioning mixes units).
    ev = jnp.linalg.eigvalsh(C)
    finite = jnp.all(jnp.isfinite(omega), (-2, -1)) & jnp.isfinite(s)
    valid = (dof > 0) & (r > 0) & finite & (ev[..., 1] > 1e-12 * jnp.maximum(ev[..., 2], jnp.finfo(dtype).tiny))
    omega = 0.5 * (omega + jnp.swapaxes(omega, -1, -2))
    return EdgeInformation(jnp.where(valid[..., None, None], omega, 0), valid)


@jax.jit
def umeyama_information_from_points(
    src: Float[ArrayLike, "*b n 3"],
    weights: Float[ArrayLike, "*b n"] | None,
    S: Float[ArrayLike, "*b 8"],
    num_points: Real[ArrayLike, "*b"],
    rms: Float[ArrayLike, "*b"],
    **options: Float[ArrayLike, ""],
) -> EdgeInformation:
    """:func:`umeyama_information` of an :func:`swiftjax.align.umeyama` solve from its source points
    (``src [..., N, 3]``, ``weights [..., N]`` or None, ``S [..., 8]`` and the solve's
    ``UmeyamaInfo.num_points`` / ``.rms``).  One extra pass over ``src``."""
    m, C = source_moments(src, weights)
    return umeyama_information(jnp.asarray(S)[..., 7], num_points, rms, m, C, **options)


@jax.jit
def alignment_information(
    S: Float[ArrayLike, "*b 8"], info: AlignInfo, **options: Float[ArrayLike, ""]
) -> EdgeInformation:
    """Information of an :func:`swiftjax.align.align_chunk_pair` edge from its ``(S, AlignInfo)``.

    Invalid (``valid`` False) also when the alignment fell back to the camera poses
    (``info.pose_fallback``): the point statistics then say nothing about ``S``.
    """
    out = umeyama_information(
        jnp.asarray(S)[..., 7], info.num_points, info.rms, info.src_mean, info.src_covariance, **options
    )
    valid = out.valid & ~jnp.asarray(info.pose_fallback)
    return EdgeInformation(jnp.where(valid[..., None, None], out.information, 0), valid)


def _covariance(info: Array) -> Array:
    # Cholesky-based inverse of an SPD 7x7 (cho_solve against the identity).
    L = jnp.linalg.cholesky(info)
    eye = jnp.broadcast_to(jnp.eye(7, dtype=info.dtype), info.shape)
    return jax.scipy.linalg.cho_solve((L, True), eye)


@jax.jit
def loop_edge_information(
    S_i_loop: Float[ArrayLike, "*b 8"],
    info_i: EdgeInformation,
    S_j_loop: Float[ArrayLike, "*b 8"],
    info_j: EdgeInformation,
) -> EdgeInformation:
    """Information of ``Z = S_j,loop S_i,loop^-1`` from its two half alignments::

        Cov(Z) = Ad(S_i,loop) (Omega_i^-1 + Omega_j^-1) Ad(S_i,loop)^T

    (module docstring).  ``S_x_loop [..., 8]``; valid when both halves are.
    """
    S_i = jnp.asarray(S_i_loop)
    valid = info_i.valid & info_j.valid
    eye = jnp.eye(7, dtype=S_i.dtype)
    safe = lambda a: jnp.where(valid[..., None, None], a, eye)
    cov = _covariance(safe(info_i.information)) + _covariance(safe(info_j.information))
    ad = sim3.adjoint(S_i)
    cov_z = ad @ cov @ jnp.swapaxes(ad, -1, -2)
    omega = _covariance(0.5 * (cov_z + jnp.swapaxes(cov_z, -1, -2)))
    omega = 0.5 * (omega + jnp.swapaxes(omega, -1, -2))
    valid = valid & jnp.all(jnp.isfinite(omega), (-2, -1))
    return EdgeInformation(jnp.where(valid[..., None, None], omega, 0), valid)

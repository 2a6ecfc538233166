"""Place descriptors from DINO patch tokens and their PCA whitening.

::

    tokens [K, d] ──ℓ2 each──► mean ──ℓ2──► g⁰ [d]                       frame_descriptor
    g⁰ ──sign(g)|g|^β──► ℓ2 ──► g¹                                        power_normalize
    {g¹} ──PCA: drop top r, keep d′, W = Q (Λ + ε)^-½──► Whitening       fit_whitening
    g¹ ──(g − μ) W──► ℓ2 ──► ẑ [d′]                                       whiten

``frame_descriptor`` runs per chunk as tokens arrive (the pipeline never holds all tokens:
4,500 frames × 407 tokens × 1024 floats is 7.5 GB); only ``[N, d]`` descriptors are kept
(:func:`chunk_descriptors`, which an executor applies where the prediction is computed).
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from swiftjax.loops._checks import _check_finite, _is_concrete
from swiftjax.loops.options import LoopOptions
from swiftjax.prediction import ChunkPrediction

_DEFAULTS = LoopOptions()

__all__ = ["frame_descriptor", "power_normalize", "Whitening", "fit_whitening", "whiten"]

_NORM_EPS = 1e-12  # as torch.nn.functional.normalize


def _l2(x: jax.Array, axis: int = -1) -> jax.Array:
    """``x / max(|x|, 1e-12)`` along ``axis`` (a zero vector stays zero)."""
    n = jnp.linalg.norm(x, axis=axis, keepdims=True)
    return x / jnp.maximum(n, _NORM_EPS)


@jax.jit
def frame_descriptor(tokens: Float[ArrayLike, "*batch K d"]) -> Float[Array, "*batch d"]:
    """Place descriptor ``g⁰`` of each frame: ``[..., K, d]`` → ``[..., d]``.

    ``g⁰ = ℓ2( (1/K) Σ_k ℓ2(x_k) )`` (each patch token ℓ2-normalised, averaged, ℓ2 again).
    The mean is accumulated in float32 whatever the token dtype (bf16/f16 tokens are
    upcast).  Recompiles per input shape/dtype.
    """
    x = jnp.asarray(tokens)
    x = x.astype(jnp.promote_types(x.dtype, jnp.float32))
    return _l2(jnp.mean(_l2(x), axis=-2))


@jax.jit
def power_normalize(
    g: Float[ArrayLike, "*batch d"], beta: float | Float[ArrayLike, ""] = _DEFAULTS.beta
) -> Float[Array, "*batch d"]:
    """Signed power normalisation ``g¹ = ℓ2(sign(g) |g|^β)``, ``[..., d]`` → ``[..., d]``.

    ``beta`` is traced (changing it does not recompile); ``β = 1`` is the identity on unit
    vectors.
    """
    g = jnp.asarray(g)
    return _l2(jnp.sign(g) * jnp.abs(g) ** beta)


class Whitening(eqx.Module):
    """A PCA whitening fitted on one sequence's descriptors (a pytree).

    Attributes:
        mean: ``[d]`` ``μ``.
        projection: ``[d, d′]`` ``W = Q_kept (Λ_kept + ε)^-½`` (columns in decreasing
            eigenvalue order, after the ``removed`` top components).
        eigenvalues: ``[d′]`` ``Λ_kept`` (covariance eigenvalues, descending).
        removed: ``[d, r]`` the dropped top eigenvectors ``q_1 .. q_r`` (``Wᵀ q = 0``).
        removed_eigenvalues: ``[r]``.
        dim_requested: the requested ``d′`` (static).
        clamped: static bool, ``True`` when ``d′ < dim_requested`` because the covariance has
            fewer than ``remove + dim_requested`` components (``d′ = min(dim, d − r, N − 1 − r)``).
        n_samples: static number of descriptors the covariance was computed from.
    """

    mean: jax.Array
    projection: jax.Array
    eigenvalues: jax.Array
    removed: jax.Array
    removed_eigenvalues: jax.Array
    dim_requested: int = eqx.field(static=True)
    clamped: bool = eqx.field(static=True)
    n_samples: int = eqx.field(static=True)

    @property
    def dim(self) -> int:
        """The kept dimension ``d′``."""
        return self.projection.shape[-1]


def _whitening_dims(n: int, d: int, remove: int, dim: int, max_samples: int) -> tuple[int, int]:
    if remove < 0 or dim < 1 or max_samples < 2:
        raise ValueError(
            f"fit_whitening needs remove >= 0, dim >= 1, max_samples >= 2; got remove={remove}, "
            f"dim={dim}, max_samples={max_samples}"
        )
    m = min(n, max_samples)
    rank = min(d, m - 1)  # centred covariance rank bound
    kept = min(dim, rank - remove)
    if kept < 1:
        raise ValueError(
            f"fit_whitening: {n} descriptors of dimension {d} give a covariance of rank <= {rank}, "
            f"nothing is left after removing {remove} component(s)"
        )
    return m, kept


def fit_whitening(
    G: ArrayLike,  # [N, d]: checked here, with a ValueError naming G (host boundary)
    remove: int = _DEFAULTS.remove,
    dim: int = _DEFAULTS.dim,
    eps: float = _DEFAULTS.eps,
    max_samples: int = _DEFAULTS.max_samples,
    *,
    throw: bool = True,
) -> Whitening:
    """PCA whitening of descriptors ``G [N, d]``.

    ``μ = mean(G)``, ``C = (G − μ)ᵀ(G − μ) / M`` (biased covariance) over ``M = min(N,
    max_samples)`` descriptors (evenly spaced rows when ``N > max_samples``, deterministic),
    ``C = Q Λ Qᵀ`` (``eigh``, sorted descending), the top ``remove`` components dropped
    (they carry the shared "dataset bias" that causes hubness), the next ``d′`` kept,
    ``W = Q (Λ + ε)^-½``.  So ``(G − μ) W`` has covariance ``Λ/(Λ + ε)`` (≈ identity) on the
    fit set and ``Wᵀ q_r = 0`` for every dropped ``q_r``.

    ``d′ = min(dim, d − remove, M − 1 − remove)``: a request larger than the available rank
    is clamped and ``clamped`` says so.  The eigen-decomposition runs in the input dtype.
    Jit-able (``remove``, ``dim``, ``max_samples`` static; ``eps`` traced); recompiles per
    ``G`` shape.  Called with a concrete array and ``throw=True`` it first rejects NaN/Inf
    rows (host boundary); with ``throw=False`` that check is skipped and non-finite rows make
    the whitening non-finite (test ``jnp.isfinite(w.projection).all()``).

    Raises:
        ValueError: ``G`` not 2-D, nothing left after ``remove``, or (``throw=True``)
            non-finite values.
    """
    if jnp.ndim(G) != 2:
        raise ValueError(f"fit_whitening: G must be [N, d], got shape {jnp.shape(G)}")
    n, d = jnp.shape(G)
    _whitening_dims(n, d, remove, dim, max_samples)
    if throw and _is_concrete(G):
        _check_finite(G, "fit_whitening: descriptors G")
    return _fit_whitening(jnp.asarray(G), jnp.asarray(eps), remove, dim, max_samples)


@functools.partial(jax.jit, static_argnames=("remove", "dim", "max_samples"))
def _fit_whitening(G, eps, remove: int, dim: int, max_samples: int) -> Whitening:
    n, d = G.shape
    m, kept = _whitening_dims(n, d, remove, dim, max_samples)
    G = G.astype(jnp.promote_types(G.dtype, jnp.float32))
    if m < n:
        G = G[np.round(np.linspace(0, n - 1, m)).astype(np.int64)]
    mu = jnp.mean(G, axis=0)
    X = G - mu
    C = X.T @ X / m
    C = 0.5 * (C + C.T)
    lam, Q = jnp.linalg.eigh(C)  # ascending
    lam, Q = lam[::-1], Q[:, ::-1]
    lam = jnp.maximum(lam, 0.0)  # round-off can make tiny eigenvalues negative
    lam_kept = lam[remove : remove + kept]
    W = Q[:, remove : remove + kept] / jnp.sqrt(lam_kept + eps)
    return Whitening(
        mean=mu,
        projection=W,
        eigenvalues=lam_kept,
        removed=Q[:, :remove],
        removed_eigenvalues=lam[:remove],
        dim_requested=dim,
        clamped=kept < dim,
        n_samples=m,
    )


@jax.jit
def whiten(w: Whitening, G: Float[ArrayLike, "*batch d"]) -> Float[Array, "*batch dk"]:
    """Whitened descriptors ``ẑ = ℓ2((G − μ) W)``: ``[..., d]`` → ``[..., d′]``."""
    return _l2((jnp.asarray(G) - w.mean) @ w.projection)


def chunk_descriptors(pred: ChunkPrediction) -> ChunkPrediction:
    """``pred`` with its patch tokens ``[S, K, d]`` reduced to frame descriptors ``[S, d]``
    (:func:`frame_descriptor`) and the tokens dropped; a prediction that carries descriptors
    already only drops its tokens.  Host side (one device round trip per chunk)."""
    if pred.descriptors is not None:
        return dataclasses.replace(pred, patch_tokens=None)
    if pred.patch_tokens is None:
        raise ValueError("the predictor returned neither descriptors nor patch tokens")
    g = np.asarray(frame_descriptor(jnp.asarray(pred.patch_tokens)))
    return dataclasses.replace(pred, descriptors=g, patch_tokens=None)

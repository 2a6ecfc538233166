"""Robust kernels of the pose-graph cost: the kernel names, their codes, ``rho`` and ``rho'``.

For the squared whitened residual ``s = r^T Omega r`` of an edge flagged robust, with scale
``k`` in whitened units:

* Huber:  ``rho(s) = s`` for ``s <= k^2``, ``2 k sqrt(s) - k^2`` above  (weight ``min(1, k/sqrt(s))``);
* Cauchy: ``rho(s) = k^2 log(1 + s / k^2)``                            (weight ``1 / (1 + s/k^2)``).

``"gnc"`` (graduated non-convexity with truncated least squares, :mod:`swiftjax.posegraph.gnc`)
is not a kernel inside LM but a continuation around it; it is a valid choice wherever a kernel
is chosen (:func:`swiftjax.posegraph.optimize`, :class:`~swiftjax.posegraph.GraphOptions`,
the pipeline's ``robust_loops``).  Every name is checked here, by :func:`check_kernel`.

Inside the compiled solver the kernel is a *traced* integer code (:func:`kernel_code`,
:func:`robust_rho_weight`), so switching kernels never recompiles.
"""

from __future__ import annotations

from typing import Any, Literal

import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float, Int, Real

__all__ = [
    "RobustKernel",
    "KERNELS",
    "ROBUST_CHOICES",
    "KERNEL_CODES",
    "check_kernel",
    "kernel_code",
    "robust_rho",
    "robust_weight",
    "robust_rho_weight",
]

RobustKernel = Literal["huber", "cauchy"]

#: The IRLS kernels applied inside LM.
KERNELS: tuple[str, ...] = ("huber", "cauchy")
#: Every robust choice, in the order the CLI and the option schema list them (``None``: plain
#: least squares).
ROBUST_CHOICES: tuple[str, ...] = ("gnc", "cauchy", "huber")
#: Traced codes of the kernels (0: none).
KERNEL_CODES = {None: 0, "huber": 1, "cauchy": 2}


def check_kernel(kernel: Any, *, gnc: bool = True) -> str | None:
    """Return ``kernel`` if it is a known name (``None``, a kernel of :data:`KERNELS`, or
    ``"gnc"`` when ``gnc`` is True); else raise ``ValueError`` naming the choices."""
    allowed = ROBUST_CHOICES if gnc else tuple(k for k in ROBUST_CHOICES if k in KERNELS)
    if kernel is None or (isinstance(kernel, str) and kernel in allowed):
        return kernel
    names = ", ".join(repr(k) for k in allowed)
    raise ValueError(f"kernel must be None or one of {names}, not {kernel!r}")


def kernel_code(kernel: str | None) -> int:
    """Integer code of a kernel name (0 none, 1 Huber, 2 Cauchy) for :func:`robust_rho_weight`."""
    return KERNEL_CODES[check_kernel(kernel, gnc=False)]


def robust_rho(s: Float[Array, "*e"], kernel: str | None, k: Real[ArrayLike, ""]) -> Float[Array, "*e"]:
    """``rho(s)`` for squared whitened residuals ``s = r^T Omega r`` (module docstring)."""
    kernel = check_kernel(kernel, gnc=False)
    if kernel is None:
        return s
    k2 = k * k
    if kernel == "huber":
        safe = jnp.where(s > k2, s, k2)
        return jnp.where(s > k2, 2.0 * k * jnp.sqrt(safe) - k2, s)
    return k2 * jnp.log1p(s / k2)


def robust_weight(s: Float[Array, "*e"], kernel: str | None, k: Real[ArrayLike, ""]) -> Float[Array, "*e"]:
    """``rho'(s)``: the IRLS weight of an edge (1 for ``kernel=None``)."""
    kernel = check_kernel(kernel, gnc=False)
    if kernel is None:
        return jnp.ones_like(s)
    k2 = k * k
    if kernel == "huber":
        safe = jnp.where(s > k2, s, k2)
        return jnp.where(s > k2, k / jnp.sqrt(safe), 1.0)
    return 1.0 / (1.0 + s / k2)


def robust_rho_weight(
    s: Float[Array, "*e"], code: Int[ArrayLike, ""], k: Real[ArrayLike, ""]
) -> tuple[Float[Array, "*e"], Float[Array, "*e"]]:
    """``(rho(s), rho'(s))`` with the kernel chosen by a *traced* integer ``code`` (no recompile)."""
    code = jnp.asarray(code)
    rho = jnp.select([code == 1, code == 2], [robust_rho(s, "huber", k), robust_rho(s, "cauchy", k)], s)
    w = jnp.select(
        [code == 1, code == 2],
        [robust_weight(s, "huber", k), robust_weight(s, "cauchy", k)],
        jnp.ones_like(s),
    )
    return rho, w

"""Block-sparse Gauss–Newton normal equations of the pose graph and their linear solvers.

With per-edge Jacobian blocks ``J_i, J_j`` (``[E, 7, 7]``), weighted information
``W_e = rho'_e Omega_e`` and residuals ``r_e``, the normal equations ``H delta = -g`` have

* diagonal blocks  ``H_nn = sum_{e: i=n} J_i^T W J_i + sum_{e: j=n} J_j^T W J_j``  (``[N, 7, 7]``, segment sums),
* one off-diagonal block per edge  ``H_ij = J_i^T W J_j``  (``[E, 7, 7]``; ``H_ji = H_ij^T``),
* gradient  ``g_n = sum_{e: i=n} J_i^T W r + sum_{e: j=n} J_j^T W r``  (``[N, 7]``).

Fixed nodes (gauge, padding) get ``H_nn = I``, zero gradient and zero coupling, so their
update is exactly zero.  Every solver takes the Levenberg–Marquardt damping as a vector
``[N, b]`` added to the diagonal (``lambda`` times ones, or Marquardt's ``lambda clip(diag H)``,
:func:`damping_diagonal`; the choice is the solver's, :mod:`swiftjax.posegraph.solver`).
The batched ``7 x 7`` products are :mod:`swiftjax.posegraph.blockmat`'s unrolled multiply-adds.

Solvers (chosen statically; :func:`swiftjax.posegraph.choose_linear_solver` is the "auto" rule):

* :func:`solve_dense` — assemble the ``7N x 7N`` matrix with scatter-adds and factor it with a
  dense Cholesky.  ``O(N^3)``; the fastest choice for small graphs (one BLAS call).
* :func:`solve_pcg` — matrix-free conjugate gradients, ``H v`` from the stored blocks with one
  segment sum per product (``O(E)``), preconditioned by the inverses of the damped ``7 x 7``
  diagonal blocks (block Jacobi), relative-residual tolerance ``eta`` (Eisenstat–Walker
  forcing, set by the caller) and a fixed iteration cap (static).
The solver objects of :mod:`swiftjax.posegraph.linear_solvers` wrap these functions.

* :func:`solve_sparse` — a sparse direct solve on the host through ``jax.pure_callback``
  (:mod:`swiftjax.posegraph.sparse_direct`: CHOLMOD, or SuperLU without cvxopt; the right tool
  for chains with few loops and meshes, whose conditioning defeats PCG).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Bool, Float, Int

from swiftjax.posegraph import sparse_direct
from swiftjax.posegraph.blockmat import bmm, bmtm, bmtv, bmv, unfused

__all__ = [
    "NormalEquations",
    "assemble",
    "from_edge_blocks",
    "matvec",
    "damping_diagonal",
    "solve_dense",
    "solve_pcg",
    "solve_sparse",
]


class NormalEquations(eqx.Module):
    """Block-sparse normal equations (see module docstring).

    Attributes:
        diag: ``[N, 7, 7]`` diagonal blocks (identity for fixed nodes), undamped.
        off: ``[E, 7, 7]`` off-diagonal block ``H_ij`` of each edge.
        grad: ``[N, 7]`` gradient ``J^T W r``.
        edges: ``[E, 2]`` int32 ``(i, j)``.
    """

    diag: Float[Array, "n b b"]
    off: Float[Array, "e b b"]
    grad: Float[Array, "n b"]
    edges: Int[Array, "e 2"]


def assemble(
    r: Float[Array, "e 7"],
    jr_inv: Float[Array, "e 7 7"],
    adj: Float[Array, "e 7 7"],
    weight: Float[Array, " e"],
    information: Float[Array, "e 7 7"],
    edges: Int[Array, "e 2"],
    fixed: Bool[Array, " n"],
) -> NormalEquations:
    """Normal equations from residuals ``[E, 7]`` and Jacobian factors ``[E, 7, 7]``.

    Uses ``J_j = Jr^-1`` and ``J_i = -Jr^-1 Ad`` (``adj = Ad(S_j^-1 S_i)``) so that with
    ``B = J_j^T W J_j`` and ``b = J_j^T W r``::

        H_jj = B,  H_ij = -Ad^T B,  H_ii = Ad^T B Ad,  g_j = b,  g_i = -Ad^T b
    """
    # Each product level in kernels of its own (blockmat.unfused); the last one fuses into the
    # scatter's operand.
    wj = unfused(lambda a, c, jr: bmm(a * c[:, None, None], jr), information, weight, jr_inv)
    big_b, b = unfused(lambda jr, wj, r: (bmtm(jr, wj), bmtv(wj, r)), jr_inv, wj, r)
    adt_b, g_i = unfused(lambda ad, bb, b: (bmtm(ad, bb), -bmtv(ad, b)), adj, big_b, b)
    return from_edge_blocks(bmm(adt_b, adj), big_b, -adt_b, g_i, b, edges, fixed)


def from_edge_blocks(
    h_ii: Float[Array, "e b b"],
    h_jj: Float[Array, "e b b"],
    h_ij: Float[Array, "e b b"],
    g_i: Float[Array, "e b"],
    g_j: Float[Array, "e b"],
    edges: Int[Array, "e 2"],
    fixed: Bool[Array, " n"],
) -> NormalEquations:
    """Sum per-edge blocks into the normal equations (segment sums over the edge ends).

    ``h_ii, h_jj, h_ij [E, b, b]`` and ``g_i, g_j [E, b]`` are edge ``(i, j)``'s contributions
    to ``H_ii, H_jj, H_ij`` and ``g_i, g_j``.  Blocks touching a fixed node are dropped and fixed
    nodes get ``H_nn = I``, so their update is exactly zero.
    """
    n, dtype = fixed.shape[0], g_i.dtype
    free_i = (~fixed[edges[:, 0]]).astype(dtype)
    free_j = (~fixed[edges[:, 1]]).astype(dtype)
    h_ii = h_ii * free_i[:, None, None]
    h_jj = h_jj * free_j[:, None, None]
    h_ij = h_ij * (free_i * free_j)[:, None, None]
    g_i = g_i * free_i[:, None]
    g_j = g_j * free_j[:, None]
    ends = jnp.concatenate([edges[:, 0], edges[:, 1]])
    seg = lambda a, b: jax.ops.segment_sum(jnp.concatenate([a, b]), ends, num_segments=n)
    diag = jnp.where(fixed[:, None, None], jnp.eye(g_i.shape[-1], dtype=dtype), seg(h_ii, h_jj))
    return NormalEquations(diag=diag, off=h_ij, grad=seg(g_i, g_j), edges=edges)


def matvec(
    ne: NormalEquations, v: Float[Array, "n b"], damping: Float[Array, "n b"] | None = None
) -> Float[Array, "n b"]:
    """``(H + diag(damping)) v`` for ``v [N, b]`` (``damping [N, b]`` or None).

    Both off-diagonal products go through one segment sum (faster than one scatter per direction).
    """
    n = v.shape[0]
    i, j = ne.edges[:, 0], ne.edges[:, 1]
    out = bmv(ne.diag, v)
    if damping is not None:
        out = out + damping * v
    coupled = jnp.concatenate([bmv(ne.off, v[j]), bmtv(ne.off, v[i])])
    return out + jax.ops.segment_sum(coupled, jnp.concatenate([i, j]), num_segments=n)


def damping_diagonal(ne: NormalEquations) -> Float[Array, "n b"]:
    """Marquardt scaling ``clip(diag(H), 1e-6, 1e32)``: ``[N, 7]``."""
    d = jnp.diagonal(ne.diag, axis1=1, axis2=2)
    return jnp.clip(d, 1e-6, 1e32)


def solve_dense(
    ne: NormalEquations, damping: Float[Array, "n b"]
) -> tuple[Float[Array, "n b"], Int[Array, ""], Bool[Array, ""]]:
    """Solve ``(H + diag(damping)) x = -g`` by dense Cholesky.

    Returns ``(x [N, 7], iterations (0), ok)``; ``ok`` is False if the factorisation failed
    (non-finite factor), in which case the caller rejects the step.
    """
    n, b = ne.grad.shape
    i, j = ne.edges[:, 0], ne.edges[:, 1]
    h = jnp.zeros((n, n, b, b), ne.diag.dtype)
    h = h.at[i, j].add(ne.off)
    h = h.at[j, i].add(jnp.swapaxes(ne.off, 1, 2))
    idx = jnp.arange(n)
    h = h.at[idx, idx].add(ne.diag + jax.vmap(jnp.diag)(damping))
    h = jnp.transpose(h, (0, 2, 1, 3)).reshape(b * n, b * n)
    factor = jax.scipy.linalg.cho_factor(h, lower=True)
    x = jax.scipy.linalg.cho_solve(factor, -ne.grad.reshape(-1)).reshape(n, b)
    ok = jnp.all(jnp.isfinite(x))
    return jnp.where(ok, x, 0.0), jnp.zeros((), jnp.int32), ok


def solve_pcg(
    ne: NormalEquations, damping: Float[Array, "n b"], tol: Float[ArrayLike, ""], max_iterations: int
) -> tuple[Float[Array, "n b"], Int[Array, ""], Bool[Array, ""]]:
    """Block-Jacobi preconditioned CG for ``(H + diag(damping)) x = -g``.

    Stops when ``||res||_2 <= tol * ||g||_2`` or after ``max_iterations`` (static) products.
    Returns ``(x [N, 7], iterations, ok)``; a capped (unconverged) solve is still a descent
    direction and is returned with ``ok`` True; ``ok`` is False only on non-finite values.
    """
    dtype = ne.grad.dtype
    blocks = ne.diag + jax.vmap(jnp.diag)(damping)
    precond = jnp.linalg.inv(blocks)
    b = -ne.grad
    apply_m = lambda v: bmv(precond, v)
    apply_a = lambda v: matvec(ne, v, damping)
    vdot = lambda a, c: jnp.sum(a * c)
    target = (tol * jnp.sqrt(vdot(b, b))) ** 2

    x0 = jnp.zeros_like(b)
    z0 = apply_m(b)
    init = (x0, b, z0, z0, vdot(b, z0), vdot(b, b), jnp.zeros((), jnp.int32))

    def cond(c):
        _, _, _, _, rz, rr, k = c
        return (k < max_iterations) & (rr > target) & (rz > 0)

    def body(c):
        x, r, _, p, rz, _, k = c
        ap = apply_a(p)
        pap = vdot(p, ap)
        alpha = jnp.where(pap > 0, rz / jnp.where(pap > 0, pap, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * ap
        z = apply_m(r)
        rz_new = vdot(r, z)
        beta = rz_new / jnp.where(rz > 0, rz, 1.0)
        p = z + beta * p
        rz_new = jnp.where(pap > 0, rz_new, jnp.zeros((), dtype))  # breakdown: stop
        return x, r, z, p, rz_new, vdot(r, r), k + 1

    x, _, _, _, _, _, k = jax.lax.while_loop(cond, body, init)
    ok = jnp.all(jnp.isfinite(x))
    return jnp.where(ok, x, 0.0), k, ok


def _host_sparse_solve(dtype, diag, off, damping, grad, edges, active, fixed):
    """NumPy side of :func:`solve_sparse` (see :mod:`swiftjax.posegraph.sparse_direct`).

    Float arrays travel as raw 32-bit words (``[..., words]`` uint32): JAX canonicalises callback
    operands and results with the *callback thread's* x64 flag, which differs from the caller's
    under a ``jax.enable_x64(True)`` context, and would silently round float64 to float32.
    """

    def unwords(a):
        a = np.ascontiguousarray(np.asarray(a, np.uint32))
        return a.view(dtype).reshape(a.shape[:-1])

    diag, off, damping, grad = (unwords(a) for a in (diag, off, damping, grad))
    x, ok = sparse_direct.solve(diag, off, damping, -grad, np.asarray(edges), np.asarray(active), np.asarray(fixed))
    n, b = grad.shape
    x = np.ascontiguousarray(x.astype(dtype))
    return x.view(np.uint32).reshape(n, b, -1), np.asarray(ok)


def solve_sparse(
    ne: NormalEquations,
    damping: Float[Array, "n b"],
    fixed: Bool[Array, " n"] | None = None,
    active: Bool[Array, " e"] | None = None,
) -> tuple[Float[Array, "n b"], Int[Array, ""], Bool[Array, ""]]:
    """Solve ``(H + diag(damping)) x = -g`` with a sparse direct factorisation on the host.

    Through ``jax.pure_callback`` into :func:`swiftjax.posegraph.sparse_direct.solve`: CHOLMOD's
    supernodal Cholesky with the ordering and symbolic factorisation cached per graph (SuperLU
    without ``cvxopt``).  Its cost is set by the fill-in of the factor: near-linear for chains
    with few loops (KITTI-like) and meshes like sphere2500, where block-Jacobi PCG needs
    hundreds of iterations per step; random long loops make the factor dense (PCG is faster
    there).  ``fixed [N]`` / ``active [E]`` (default: none fixed / all active) only prune the
    pattern; the blocks they remove must be zero.  Returns ``(x [N, b], iterations (0), ok)``.
    """
    n, b = ne.grad.shape
    e = ne.edges.shape[0]
    fixed = jnp.zeros((n,), bool) if fixed is None else fixed
    active = jnp.ones((e,), bool) if active is None else active
    words = jnp.dtype(ne.grad.dtype).itemsize // 4
    out_shapes = (
        jax.ShapeDtypeStruct((n, b, words), jnp.uint32),
        jax.ShapeDtypeStruct((), jnp.bool_),
    )
    dtype = jnp.dtype(ne.grad.dtype)

    def words_of(a):
        w = jax.lax.bitcast_convert_type(a, jnp.uint32)
        return w if words > 1 else w[..., None]

    raw, ok = jax.pure_callback(
        functools.partial(_host_sparse_solve, np.dtype(dtype.name)),
        out_shapes,
        words_of(ne.diag),
        words_of(ne.off),
        words_of(damping),
        words_of(ne.grad),
        ne.edges,
        active,
        fixed,
        vmap_method="sequential",
    )
    raw = raw if words > 1 else raw[..., 0]
    x = jax.lax.bitcast_convert_type(raw, ne.grad.dtype).reshape(n, b)
    return jnp.where(ok, x, 0.0), jnp.zeros((), jnp.int32), ok

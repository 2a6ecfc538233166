"""One test harness for both groups (jaxlie's ``@general_group_test`` style).

Every test below runs over (``so3``, ``sim3``) x batch axes ``()``, ``(1,)``, ``(3, 1, 2, 1)`` x
sampling regimes:

* ``uniform``: uniformly random rotations (plus translations and log-scales for Sim(3));
* ``normal``: standard-normal tangents (rotation angle capped below ``pi``);
* ``near_identity``: tangents of size ~1e-5, the first element exactly zero;
* ``near_pi``: rotation angle ``pi - 1e-4``;
* ``sophus``: ``exp(a) exp(pi) exp(-a)`` (Sophus's test set: a rotation by exactly ``pi`` about
  a random axis, seen from a random frame).

Both modules expose the same operations (``identity``, ``compose``, ``inverse``, ``between``,
``act``, ``adjoint``, ``normalize``, ``exp``, ``log``, ``jlog``, ``as_matrix``); the harness
uses nothing else, so a third group plugs in with one :class:`Group` entry.  References are
plain matrix algebra and float64 central differences.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import zlib
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from swiftjax import sim3, so3

BATCHES = [(), (1,), (3, 1, 2, 1)]
REGIMES = ["uniform", "normal", "near_identity", "near_pi", "sophus"]


@dataclasses.dataclass(frozen=True, eq=False)  # hashed by identity (a static jit argument)
class Group:
    name: str
    module: types.ModuleType
    tangent_dim: int
    rotation: slice  # where the rotation vector sits in a tangent
    quaternion: slice  # where the quaternion sits in an element
    uniform: Callable[[np.random.Generator, tuple[int, ...]], np.ndarray]

    def act_by_matrix(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        m = np.asarray(self.module.as_matrix(x), np.float64)
        return np.einsum("...ij,...j->...i", m[..., :3, :3], p) + (m[..., :3, 3] if m.shape[-1] == 4 else 0.0)


def _uniform_so3(rng, batch):
    n = int(np.prod(batch))
    return Rotation.random(max(n, 1), random_state=rng).as_quat()[:n].reshape(*batch, 4)


def _uniform_sim3(rng, batch):
    t = rng.uniform(-5, 5, (*batch, 3))
    s = np.exp(rng.uniform(-1, 1, (*batch, 1)))
    return np.concatenate([t, _uniform_so3(rng, batch), s], -1)


GROUPS = {
    "so3": Group("so3", so3, 3, slice(0, 3), slice(0, 4), _uniform_so3),
    "sim3": Group("sim3", sim3, 7, slice(3, 6), slice(3, 7), _uniform_sim3),
}


def _axes(rng, batch):
    a = rng.normal(size=(*batch, 3))
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def sample(group: Group, batch: tuple[int, ...], regime: str) -> tuple[np.ndarray, np.ndarray]:
    """``(element, tangent)`` in float64 with ``element = exp(tangent)`` (to rounding)."""
    rng = np.random.default_rng(zlib.crc32(f"{group.name}{batch}{regime}".encode()))
    mod, rot = group.module, group.rotation
    if regime in ("uniform", "sophus"):
        if regime == "uniform":
            x = group.uniform(rng, batch)
        else:
            a = rng.normal(size=(*batch, group.tangent_dim))
            mid = rng.normal(size=(*batch, group.tangent_dim))
            mid[..., rot] = np.pi * _axes(rng, batch)
            x = mod.compose(mod.compose(mod.exp(a), mod.exp(mid)), mod.exp(-a))
        x = np.asarray(x, np.float64)
        return x, np.asarray(mod.log(x), np.float64)
    xi = rng.normal(size=(*batch, group.tangent_dim))
    angle = np.linalg.norm(xi[..., rot], axis=-1, keepdims=True)
    if regime == "normal":
        xi[..., rot] *= np.minimum(1.0, 3.0 / angle)
    elif regime == "near_identity":
        xi *= 1e-5
        xi.reshape(-1, group.tangent_dim)[0] = 0.0
    elif regime == "near_pi":
        xi[..., rot] = (np.pi - 1e-4) * _axes(rng, batch)
    return np.asarray(mod.exp(xi), np.float64), xi


#: The regimes away from an angle of exactly pi, where log is discontinuous (its derivative does
#: not exist and ``omega``, ``-omega`` are both logs): derivative tests are not generated there.
OFF_PI = [r for r in REGIMES if r != "sophus"]


def lie_group_test(*dtypes: type, regimes: list[str] = REGIMES) -> Callable:
    """Parametrize a test ``f(group, batch, regime[, dtype])`` over groups, batches and ``regimes``."""

    def decorate(f: Callable) -> Callable:
        f = pytest.mark.parametrize("regime", regimes)(f)
        f = pytest.mark.parametrize("batch", BATCHES, ids=lambda b: "x".join(map(str, b)) or "scalar")(f)
        f = pytest.mark.parametrize("group", list(GROUPS.values()), ids=list(GROUPS))(f)
        if dtypes:
            f = pytest.mark.parametrize("dtype", dtypes, ids=lambda d: np.dtype(d).name)(f)
        return f

    return decorate


def assert_close(actual, desired, dtype=np.float64, scale: float = 1.0, what: str = "") -> None:
    """The one tolerance of this file: ``atol = rtol = scale * eps(dtype)``-based."""
    tol = scale * (2e-4 if np.dtype(dtype) == np.float32 else 1e-9)
    np.testing.assert_allclose(
        np.asarray(actual, np.float64), np.asarray(desired, np.float64), rtol=tol, atol=tol, err_msg=what
    )


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def _matrix(group: Group, x) -> np.ndarray:
    return np.asarray(group.module.as_matrix(x), np.float64)


def _points(batch):
    return np.random.default_rng(7).normal(size=(*batch, 3))


# -------------------------------------------------------------------------- group axioms


@lie_group_test(np.float32, np.float64)
def test_identity_inverse_and_between(group, batch, regime, dtype):
    mod = group.module
    x, _ = sample(group, batch, regime)
    y, _ = sample(group, batch, "uniform")
    x, y = x.astype(dtype), y.astype(dtype)
    e = mod.identity(batch, dtype)
    assert e.shape == x.shape and e.dtype == dtype
    assert_close(_matrix(group, mod.compose(e, x)), _matrix(group, x), dtype)
    assert_close(_matrix(group, mod.compose(x, mod.inverse(x))), _matrix(group, e), dtype, 10)
    assert_close(_matrix(group, mod.inverse(x)), np.linalg.inv(_matrix(group, x)), dtype, 10)
    assert_close(_matrix(group, mod.between(x, y)), _matrix(group, mod.compose(mod.inverse(x), y)), dtype, 10)
    assert mod.compose(x, y).dtype == dtype


@lie_group_test(np.float32, np.float64)
def test_associativity_and_normalize(group, batch, regime, dtype):
    mod = group.module
    x, _ = sample(group, batch, regime)
    y, _ = sample(group, batch, "uniform")
    z, _ = sample(group, batch, "normal")
    x, y, z = x.astype(dtype), y.astype(dtype), z.astype(dtype)
    left = mod.compose(mod.compose(x, y), z)
    right = mod.compose(x, mod.compose(y, z))
    assert_close(_matrix(group, left), _matrix(group, right), dtype, 10)
    drifted = np.array(x)
    drifted[..., group.quaternion] *= 1.3
    n = np.asarray(mod.normalize(drifted))
    assert_close(np.linalg.norm(n[..., group.quaternion], axis=-1), np.ones(batch), dtype)
    assert_close(n, x, dtype)


# ----------------------------------------------------------------------- exp and log


@lie_group_test(np.float32, np.float64)
def test_exp_log_round_trips(group, batch, regime, dtype):
    mod = group.module
    x, xi = sample(group, batch, regime)
    x, xi = x.astype(dtype), xi.astype(dtype)
    back = np.asarray(mod.log(x))
    assert back.shape == xi.shape and back.dtype == dtype
    # exp(log(x)) = x for every element, including rotations by exactly pi ...
    assert_close(_matrix(group, mod.exp(back)), _matrix(group, x), dtype, 10)
    # ... and log(exp(xi)) = xi where the angle is below pi (log's branch cut).
    if regime != "sophus":
        scale = 100 if regime == "near_pi" else 10  # float32: |v| = sin(theta/2) loses digits near pi
        assert_close(mod.log(mod.exp(xi)), xi, dtype, scale)


@lie_group_test(np.float32, np.float64, regimes=OFF_PI)
def test_log_ignores_quaternion_sign(group, batch, regime, dtype):
    """``log(-q) = log(q)``, also at ``pi - 1e-4`` (exactly at pi ``omega`` and ``-omega`` are both logs)."""
    x, _ = sample(group, batch, regime)
    flipped = np.array(x)
    flipped[..., group.quaternion] *= -1
    assert_close(group.module.log(flipped.astype(dtype)), group.module.log(x.astype(dtype)), dtype, 10)


# ------------------------------------------------------------------ adjoint and action


@lie_group_test(np.float64)
def test_adjoint_identity(group, batch, regime, dtype):
    """``x exp(xi) x^-1 = exp(Ad(x) xi)``."""
    mod = group.module
    x, _ = sample(group, batch, regime)
    _, xi = sample(group, batch, "normal")
    ad = np.asarray(mod.adjoint(x))
    assert ad.shape == (*batch, group.tangent_dim, group.tangent_dim)
    lhs = mod.compose(mod.compose(x, mod.exp(xi)), mod.inverse(x))
    rhs = mod.exp(np.einsum("...ij,...j->...i", ad, xi))
    assert_close(_matrix(group, lhs), _matrix(group, rhs), dtype, 100)


@lie_group_test(np.float32, np.float64)
def test_act_matches_matrix(group, batch, regime, dtype):
    x, _ = sample(group, batch, regime)
    p = _points(batch)
    got = group.module.act(x.astype(dtype), p.astype(dtype))
    assert got.shape == p.shape and got.dtype == dtype
    assert_close(got, group.act_by_matrix(x, p), dtype, 10)


# ---------------------------------------------------------------- Jacobians and gradients


def _central_difference(f, x, u, eps=1e-6):
    return (np.asarray(f(x + eps * u)) - np.asarray(f(x - eps * u))) / (2 * eps)


# Jitted once per (group, shape): the regimes share the compiled programs.
@functools.partial(jax.jit, static_argnums=0)
def _log_of_right_perturbation(group, x, e):
    return group.module.log(group.module.compose(x, group.module.exp(e)))


@functools.partial(jax.jit, static_argnums=0)
def _jlog(group, xi):
    return group.module.jlog(xi)


def _f(group, t, y, p):
    """``(log(y exp(t)), act(exp(t), p))``: exercises exp, log, compose and act."""
    mod = group.module
    return jnp.concatenate([mod.log(mod.compose(y, mod.exp(t))), mod.act(mod.exp(t), p)], -1)


_f_jit = jax.jit(_f, static_argnums=0)


@functools.partial(jax.jit, static_argnums=0)
def _forward_and_reverse(group, t, y, p, u, v):
    f = functools.partial(_f, group, y=y, p=p)
    return jax.jvp(f, (t,), (u,))[1], jax.vjp(f, t)[1](v)[0]


@lie_group_test(regimes=OFF_PI)
def test_jlog_matches_numerical_derivative(group, batch, regime):
    """``jlog(xi) d = d/de log(exp(xi) exp(e d))`` at ``e = 0`` (float64 central differences)."""
    x, xi = sample(group, batch, regime)
    d = np.random.default_rng(3).normal(size=xi.shape)
    jr_inv = np.asarray(_jlog(group, xi))
    assert jr_inv.shape == (*batch, group.tangent_dim, group.tangent_dim)
    numeric = _central_difference(lambda e: _log_of_right_perturbation(group, x, e), np.zeros_like(xi), d)
    assert_close(np.einsum("...ij,...j->...i", jr_inv, d), numeric, scale=1e4)


@lie_group_test(regimes=OFF_PI)
def test_gradients_forward_reverse_and_numerical_agree(group, batch, regime):
    """``f(xi) = (log(y exp(xi)), act(exp(xi), p))``: ``J u`` by ``jvp``, ``v^T J`` by ``vjp`` and
    by central differences, checked against each other."""
    _, xi = sample(group, batch, regime)
    y, _ = sample(group, batch, "near_identity")
    p = _points(batch)
    rng = np.random.default_rng(11)
    u = rng.normal(size=xi.shape)
    v = rng.normal(size=(*batch, group.tangent_dim + 3))
    ju, vj = _forward_and_reverse(group, xi, y, p, u, v)
    assert np.all(np.isfinite(ju)) and np.all(np.isfinite(vj))
    assert_close(np.sum(v * ju), np.sum(vj * u), scale=10)  # forward vs reverse
    numeric = _central_difference(lambda t: _f_jit(group, t, y, p), xi, u)
    assert_close(ju, numeric, scale=1e4)  # forward vs numerical


def test_annotated_shapes_are_enforced():
    """tests/conftest.py installs jaxtyping's import hook: a wrongly-shaped call raises."""
    import sys

    assert "swiftjax.sim3" in sys.modules and hasattr(sim3.exp, "__wrapped__")
    with pytest.raises(Exception, match="(?i)type|shape"):
        sim3.exp(np.zeros((2, 6), np.float32))  # a tangent is [..., 7]
    with pytest.raises(Exception, match="(?i)type|shape"):
        so3.act(np.zeros(4, np.float32), np.zeros(2, np.float32))  # points are [..., 3]

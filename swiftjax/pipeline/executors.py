"""Executors: where the predictions of a run are computed.

The temporal and loop stages hand an executor the chunks they need, in schedule order, and
consume the :class:`~swiftjax.prediction.ChunkPrediction` s in that order::

    stream = executor.map(predictor, [frames_0, frames_1, ...], prepare)   # an iterator
    for frames in ...: pred = next(stream)                                 # same order

Executors only move arrays: ``prepare`` (e.g. the loop package's token -> descriptor
reduction, :func:`swiftjax.loops.descriptors.chunk_descriptors`) is the caller's, applied to
each prediction where it is computed (on a Ray worker: before it crosses the network).

An executor never reorders, drops or repeats a request; what a stage has recorded in the
manifest is never requested (so never recomputed).  At most a bounded number of requests
are in flight, so memory stays flat in the sequence length.

* :class:`LocalExecutor` (default): in this process.  With ``prefetch >= 1`` a thread
  predicts chunk ``t+1`` while the host aligns and stores chunk ``t``.
* :class:`RayExecutor`: a pool of Ray actors, each building its predictor once from a
  picklable spec (:func:`predictor_spec`) and keeping it (the model) loaded; ``num_gpus`` /
  ``num_cpus`` per actor; a dead actor is restarted and its chunks retried.  A local
  cluster (the default) listens on the loopback interface only, without the dashboard and
  with Ray's token authentication on; a remote cluster is joined only through an explicit
  ``address``.  Needs the ``ray`` extra (``pip install 'swiftjax[ray]'``).

Predictions are bit-identical whichever executor computes them (the predictors are
deterministic per frame set), so are the outputs of the run.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import os
import socket
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol

import numpy as np

from swiftjax.errors import SwiftjaxError
from swiftjax.prediction import ChunkPrediction

__all__ = [
    "Executor",
    "ExecutorError",
    "ExecutorStats",
    "LocalExecutor",
    "RayExecutor",
    "PredictorSpec",
    "SelfSpec",
    "predictor_spec",
    "import_ray",
    "start_local_ray",
    "check_ray_address",
    "check_workers",
    "prediction_nbytes",
]


#: What a stage asks an executor to apply to each prediction where it is computed.
Prepare = Callable[[ChunkPrediction], ChunkPrediction]


class ExecutorError(SwiftjaxError, RuntimeError):
    """An executor cannot be set up (missing extra, unreachable cluster, bad option)."""


def check_workers(workers: int) -> None:
    """``--workers`` (Ray actors) must be at least 1; :class:`ExecutorError` otherwise."""
    if workers < 1:
        raise ExecutorError(f"--workers must be >= 1, got {workers}")


@dataclasses.dataclass
class ExecutorStats:
    """Counters of one executor: ``predictions`` returned, ``bytes`` of their arrays (what a
    remote executor moved to the driver), ``predict_seconds`` spent inside the predictors
    (summed over workers), ``wait_seconds`` the consumer waited for results."""

    predictions: int = 0
    bytes: int = 0
    predict_seconds: float = 0.0
    wait_seconds: float = 0.0


class Executor(Protocol):
    """Computes predictions for a stage, in request order."""

    stats: ExecutorStats

    def map(
        self,
        predictor: Any,
        requests: Sequence[np.ndarray],
        prepare: Prepare | None = None,
    ) -> Iterator[ChunkPrediction]:
        """``prepare(predictor.predict(frames))`` for each ``frames`` of ``requests``, in order.
        Close the iterator (or exhaust it) to release what is in flight."""
        ...

    def close(self) -> None:
        """Release workers (idempotent)."""
        ...


def prediction_nbytes(pred: ChunkPrediction) -> int:
    """Bytes of the prediction's arrays."""
    return int(sum(v.nbytes for v in vars(pred).values() if isinstance(v, np.ndarray)))


def _timed_predict(
    predictor: Any,
    frames: np.ndarray,
    prepare: Prepare | None = None,
) -> tuple[ChunkPrediction, float]:
    t0 = time.perf_counter()
    pred = predictor.predict(frames)
    if prepare is not None:
        pred = prepare(pred)
    return pred, time.perf_counter() - t0


# ---------------------------------------------------------------------------------- local


class LocalExecutor:
    """Predictions in this process.

    ``prefetch``: how many requests are predicted ahead of the consumer on one background
    thread (0: synchronous, each prediction when it is asked for).  With ``prefetch = 1``
    the predictor works on chunk ``t+1`` while the host aligns and stores chunk ``t``; at
    most ``prefetch`` predictions wait beside the one being consumed.  The predictor is
    called from one thread only, in request order; a predictor with a ``prefetch(frames)``
    method is told each request as it is scheduled (the image predictor starts decoding it).
    """

    workers = 1

    def __init__(self, prefetch: int = 1) -> None:
        if prefetch < 0:
            raise ValueError(f"prefetch must be >= 0, got {prefetch}")
        self.prefetch = int(prefetch)
        self.stats = ExecutorStats()

    def map(
        self,
        predictor: Any,
        requests: Sequence[np.ndarray],
        prepare: Prepare | None = None,
    ) -> Iterator[ChunkPrediction]:
        if self.prefetch == 0:
            for frames in requests:
                t0 = time.perf_counter()
                pred, seconds = _timed_predict(predictor, frames, prepare)
                self._count(pred, seconds, time.perf_counter() - t0)
                yield pred
            return
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="swiftjax-predict")
        pending: collections.deque = collections.deque()
        prefetch = getattr(predictor, "prefetch", None)  # e.g. decode a chunk's frames as it is scheduled
        try:
            for frames in requests:
                if prefetch is not None:
                    prefetch(frames)
                pending.append(pool.submit(_timed_predict, predictor, frames, prepare))
                if len(pending) > self.prefetch:
                    yield self._take(pending)
            while pending:
                yield self._take(pending)
        finally:
            for future in pending:  # closed early: drop what has not started
                future.cancel()
            pool.shutdown(wait=True)

    def _take(self, pending: collections.deque) -> ChunkPrediction:
        t0 = time.perf_counter()
        pred, seconds = pending.popleft().result()
        self._count(pred, seconds, time.perf_counter() - t0)
        return pred

    def _count(self, pred: ChunkPrediction, predict_seconds: float, wait_seconds: float) -> None:
        self.stats.predictions += 1
        self.stats.predict_seconds += predict_seconds
        self.stats.wait_seconds += wait_seconds

    def close(self) -> None:
        pass


# ---------------------------------------------------------------------------- predictor specs


class PredictorSpec(Protocol):
    """A picklable recipe for a predictor, built once per worker (e.g. loads the weights)."""

    def build(self) -> Any: ...


@dataclasses.dataclass(frozen=True)
class SelfSpec:
    """The spec of a predictor that pickles as it is (cheap to send to a worker)."""

    predictor: Any

    def build(self) -> Any:
        return self.predictor


def predictor_spec(predictor: Any) -> PredictorSpec:
    """``predictor.spec()`` if it has one (e.g. weights path + device, or the oracle's
    world parameters), else the predictor itself, which must then pickle."""
    make = getattr(predictor, "spec", None)
    return make() if callable(make) else SelfSpec(predictor)


# ------------------------------------------------------------------------------------ ray


def import_ray() -> Any:
    """``ray``, or :class:`ExecutorError` naming the extra to install."""
    try:
        import ray
    except ImportError as err:
        raise ExecutorError("the Ray executor needs the 'ray' extra: pip install 'swiftjax[ray]'") from err
    return ray


def check_ray_address(address: str, timeout: float = 3.0) -> None:
    """Refuse, within seconds, an address where no Ray cluster answers (``ray.init`` retries
    for about 20 s, then fails with a screen of log lines).  ``host:port`` must accept a TCP
    connection within ``timeout`` seconds and answer as a Ray GCS (its cluster id, with
    this machine's token if the cluster uses token authentication); a ``ray://`` (Ray
    Client) address only the connection; ``"auto"`` (the cluster started on this machine by
    ``ray start``) is left to Ray."""
    if address == "auto":
        return
    scheme, _, hostport = address.rpartition("://")
    hostport = hostport.rstrip("/")
    host, sep, port = hostport.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ExecutorError(f"--ray-address {address!r} is not HOST:PORT (e.g. 10.0.0.5:6379 or ray://10.0.0.5:10001)")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            pass
    except OSError as err:
        raise ExecutorError(f"cannot reach the Ray cluster at {address}: {err.strerror or err}") from err
    if scheme:
        return
    import_ray()
    from ray._private.authentication.authentication_token_setup import (
        maybe_enable_token_auth_if_token_available,
    )
    from ray._raylet import GcsClient

    quiet = logging.getLogger("ray._private.authentication")
    level, quiet.level = quiet.level, logging.ERROR
    try:
        maybe_enable_token_auth_if_token_available(warn_if_disabled=False)  # as ray.init(address=...)
    finally:
        quiet.setLevel(level)
    try:
        with _native_stderr_silenced():  # Ray's C++ client logs each failed attempt
            _ = GcsClient(address=hostport).cluster_id
    except Exception as err:
        raise ExecutorError(f"no Ray cluster answers at {address}: {_first_line(err)}") from err


@contextlib.contextmanager
def _native_stderr_silenced() -> Iterator[None]:
    """File descriptor 2 to /dev/null for the block (native libraries write there directly)."""
    import sys

    sys.stderr.flush()
    saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


@contextlib.contextmanager
def _loopback_only(ray: Any) -> Iterator[None]:
    """Make the local cluster's processes bind to 127.0.0.1 (Ray binds every interface by
    default).  Ray takes the node address from ``get_node_ip_address``, which answers the
    loopback address where multi-node clusters are off (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER
    = 0``, read by the cluster's processes from the environment, and by this one from
    ``ray_constants``)."""
    from ray._private import ray_constants

    name = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
    old_env, old_flag = os.environ.get(name), ray_constants.ENABLE_RAY_CLUSTER
    os.environ[name] = "0"
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = old_flag
        if old_env is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = old_env


def start_local_ray(num_cpus: int | None = None, num_gpus: int | None = None) -> Any:
    """``ray.init`` of a cluster on this machine: loopback only, no dashboard, token
    authentication on (Ray's unauthenticated job API was exploited: CVE-2023-48022).
    Returns ``ray``.  Refuses ``RAY_AUTH_MODE=disabled``."""
    ray = import_ray()
    mode = os.environ.get("RAY_AUTH_MODE")
    if mode is not None and mode.lower() != "token":
        raise ExecutorError(
            f"RAY_AUTH_MODE={mode}: swiftjax starts a local Ray cluster only with token authentication "
            "(unset RAY_AUTH_MODE or set it to 'token')"
        )
    with _loopback_only(ray), warnings.catch_warnings():
        # Ray starts its processes with fork + exec, which JAX's fork warning does not tell apart.
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        # RAY_AUTH_MODE unset: Ray (>= 2.59) turns token authentication on for a new local
        # cluster (and generates ~/.ray/auth_token once); both are checked below.
        ray.init(
            num_cpus=num_cpus,
            num_gpus=num_gpus,
            include_dashboard=False,
            logging_level="ERROR",
            log_to_driver=True,
            configure_logging=True,
        )
    ip = ray.util.get_node_ip_address()
    problem = None
    if ip != "127.0.0.1":
        problem = f"came up on {ip}, not on the loopback interface"
    elif os.environ.get("RAY_AUTH_MODE", "").lower() != "token":
        problem = "came up without token authentication"
    if problem:
        ray.shutdown()
        raise ExecutorError(f"the local Ray cluster {problem}: refused")
    return ray


class _PredictorActor:
    """A Ray actor: builds its predictor once (restarts build it again) and serves chunks.

    ``jax_cache_dir``: the driver's persistent compilation cache, so that the workers do
    not compile what the driver (or an earlier worker) already compiled."""

    def __init__(self, spec: PredictorSpec, jax_cache_dir: str | None = None) -> None:
        if jax_cache_dir:
            import jax

            jax.config.update("jax_compilation_cache_dir", jax_cache_dir)
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
        self.predictor = spec.build()

    def predict(self, frames: np.ndarray, prepare: Prepare | None = None) -> tuple[ChunkPrediction, float]:
        """The prediction, ``prepare`` applied here: e.g. its patch tokens reduced to frame
        descriptors (a VGGT chunk's tokens, [S, P, 1024] float32, 125 MB for 75 frames of
        518 x 154, are twice its dense maps, and never cross the network)."""
        return _timed_predict(self.predictor, frames, prepare)

    def pid(self) -> int:
        return os.getpid()


class RayExecutor:
    """Predictions on a pool of Ray actors.

    Args:
        workers: actors in the pool (each holds one predictor, e.g. one model on one GPU).
        gpus_per_worker, cpus_per_worker: Ray resources of each actor (``num_gpus`` /
            ``num_cpus``; fractional GPUs share a device).
        address: an existing cluster (``ray start --head`` prints it; ``ray://`` for Ray
            Client); None starts a local one (:func:`start_local_ray`) that :meth:`close`
            shuts down.  If Ray is already initialised in this process, that is used.
        num_cpus: CPUs of a local cluster (default: all).
        max_in_flight: requests submitted ahead of the consumer (default ``2 x workers``).
        max_restarts, max_task_retries: a dead actor is restarted (rebuilding its predictor
            from the spec) and its pending chunks retried, this many times.

    Requests go to the actors round robin; results are taken in request order.
    """

    def __init__(
        self,
        workers: int = 1,
        *,
        gpus_per_worker: float = 0.0,
        cpus_per_worker: float = 1.0,
        address: str | None = None,
        num_cpus: int | None = None,
        max_in_flight: int | None = None,
        max_restarts: int = 3,
        max_task_retries: int = 3,
    ) -> None:
        check_workers(workers)
        if gpus_per_worker < 0 or cpus_per_worker < 0:
            raise ExecutorError("--gpus-per-worker and CPUs per worker must be >= 0")
        if max_in_flight is not None and max_in_flight < 1:
            raise ExecutorError(f"max_in_flight must be >= 1, got {max_in_flight}")
        self.workers = int(workers)
        self.gpus_per_worker = float(gpus_per_worker)
        self.cpus_per_worker = float(cpus_per_worker)
        self.max_in_flight = int(max_in_flight or 2 * workers)
        self.max_restarts = int(max_restarts)
        self.max_task_retries = int(max_task_retries)
        self.stats = ExecutorStats()
        self.actors: list[Any] = []
        self._spec_key: Any = None
        self._owns_cluster = False
        self.ray = import_ray()
        if address is not None:
            check_ray_address(address)
        if not self.ray.is_initialized():
            if address is not None:
                try:
                    self.ray.init(address=address, logging_level="ERROR")
                except Exception as err:  # Ray raises ConnectionError, RuntimeError, ...
                    raise ExecutorError(f"cannot join the Ray cluster at {address}: {_first_line(err)}") from err
            else:
                start_local_ray(num_cpus=num_cpus)
            self._owns_cluster = True
        self._check_resources()

    def _check_resources(self) -> None:
        total = self.ray.cluster_resources()
        need = {"CPU": self.cpus_per_worker * self.workers, "GPU": self.gpus_per_worker * self.workers}
        for name, amount in need.items():
            if amount > 0 and total.get(name, 0.0) < amount:
                raise ExecutorError(
                    f"{self.workers} workers need {amount:g} {name}s but the Ray cluster has "
                    f"{total.get(name, 0.0):g}: lower --workers or the {name}s per worker"
                )

    def _pool(self, predictor: Any) -> list[Any]:
        """The actors for ``predictor`` (started on first use; a new predictor replaces them)."""
        if self.actors and self._spec_key is predictor:
            return self.actors
        self._kill_actors()
        spec = predictor_spec(predictor)
        actor_cls = self.ray.remote(_PredictorActor).options(
            num_cpus=self.cpus_per_worker,
            num_gpus=self.gpus_per_worker,
            max_restarts=self.max_restarts,
            max_task_retries=self.max_task_retries,
        )
        cache = _jax_cache_dir()
        try:
            # The spec by value (a restarted actor needs it again; a put object could be gone).
            self.actors = [actor_cls.remote(spec, cache) for _ in range(self.workers)]
        except Exception as err:  # pickling
            raise ExecutorError(
                f"the predictor cannot be sent to Ray workers ({_first_line(err)}); give it a picklable spec()"
            ) from err
        self._spec_key = predictor
        return self.actors

    def map(
        self,
        predictor: Any,
        requests: Sequence[np.ndarray],
        prepare: Prepare | None = None,
    ) -> Iterator[ChunkPrediction]:
        requests = list(requests)
        if not requests:
            return
        actors = self._pool(predictor)
        pending: collections.deque = collections.deque()
        submitted = 0
        try:
            while submitted < len(requests) or pending:
                while submitted < len(requests) and len(pending) < self.max_in_flight:
                    actor = actors[submitted % len(actors)]
                    pending.append(actor.predict.remote(np.asarray(requests[submitted]), prepare))
                    submitted += 1
                t0 = time.perf_counter()
                pred, seconds = self.ray.get(pending.popleft())
                self.stats.wait_seconds += time.perf_counter() - t0
                self.stats.predictions += 1
                self.stats.predict_seconds += seconds
                self.stats.bytes += prediction_nbytes(pred)
                yield pred
        finally:
            for ref in pending:  # closed early: the chunks are not needed any more
                with contextlib.suppress(Exception):
                    self.ray.cancel(ref)

    def _kill_actors(self) -> None:
        for actor in self.actors:
            with contextlib.suppress(Exception):
                self.ray.kill(actor, no_restart=True)
        self.actors = []
        self._spec_key = None

    def close(self) -> None:
        """Stop the actors; shut down the cluster if this executor started or joined it."""
        self._kill_actors()
        if self._owns_cluster and self.ray.is_initialized():
            self.ray.shutdown()
        self._owns_cluster = False

    def __enter__(self) -> RayExecutor:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _jax_cache_dir() -> str | None:
    import sys

    jax = sys.modules.get("jax")
    return jax.config.jax_compilation_cache_dir if jax is not None else None


def _first_line(err: BaseException) -> str:
    text = str(err).strip() or type(err).__name__
    return text.splitlines()[0]

"""Shared test configuration.

* JAX's persistent compilation cache is on (``$JAX_COMPILATION_CACHE_DIR``, default
  ``~/.cache/swiftjax/jax-tests``, outside the checkout so that a fresh clone on the same
  machine reuses it), so a second test run skips most XLA compiles.
* ``shared_dir``: the read-only reference folder (``$SWIFTJAX_SHARED`` or ``../shared``);
  tests that need it skip with a clear reason when it is absent (CI always has it).
* ``x64``: runs a test with ``jax_enable_x64`` on, for float64 reference checks only.
* jaxtyping's import hook with beartype over ``JAXTYPED_MODULES``: a call whose shapes do not
  match the annotations (``Float[Array, "*batch 8"]`` ...) raises.
* ``small_loop_run``: one finished small run with loop closure and ground truth (the shapes
  of ``test_pipeline.py``'s, so the compile cache serves both), shared by the output tests.
* Compiled executables are dropped between test modules once the process holds many memory
  mappings (``_release_compiled_code``): XLA's CPU backend maps about three regions per compiled
  executable and keeps every executable alive in JAX's caches, so one process that compiles
  the whole suite's ~20,000 programs crosses Linux's ``vm.max_map_count`` (65,530 by default);
  the next ``mmap`` fails inside the JIT and the process dies with a segmentation fault (CI exit
  139, at whichever test happened to be compiling then).
"""

from __future__ import annotations

import contextlib
import os
import pathlib
from collections.abc import Iterator

# Shapes in annotations are enforced in the tests: jaxtyping's import hook wraps every function
# of these modules with a runtime checker.  It must be installed before anything imports
# swiftjax (this file is imported before any test module).  One module name per line.
#
# The modules of array functions are listed one by one (tests/test_jaxtyping_hook.py checks that
# every core module with a public array function is here, or says why not).  Left out on purpose: the option
# modules (swiftjax.loops.options, swiftjax.posegraph.options: host-boundary dataclasses whose
# __post_init__ raises a ValueError naming the bad value, which a Literal annotation checked
# first would hide) and the packages' __init__ modules.  Inside the listed
# modules the host-boundary checkers take ArrayLike / Any for the same reason (sim3.check,
# fit_whitening, detect_loops, Problem(...)): their own ValueError is what callers see.
import jaxtyping

JAXTYPED_MODULES = [
    "swiftjax.sim3",
    "swiftjax.so3",
    "swiftjax._elementary",
    "swiftjax.camera",
    "swiftjax.masks",
    "swiftjax.metric_scale",
    "swiftjax.align.umeyama",
    "swiftjax.align.chunk_pair",
    "swiftjax.align.mask",
    "swiftjax.align.irls",
    "swiftjax.align.checks",
    "swiftjax.align.covariance",
    "swiftjax.loops.descriptors",
    "swiftjax.loops.detection",
    "swiftjax.loops.loop_chunk",
    "swiftjax.loops.find",
    "swiftjax.loops.cross_chunk",
    "swiftjax.loops.null",
    "swiftjax.loops.pcm",
    "swiftjax.loops.online",
    "swiftjax.loops.geometric",
    "swiftjax.loops.verification",
    "swiftjax.posegraph.problem",
    "swiftjax.posegraph.kernels",
    "swiftjax.posegraph.blockmat",
    "swiftjax.posegraph.factors",
    "swiftjax.posegraph.linear",
    "swiftjax.posegraph.linear_solvers",
    "swiftjax.posegraph.sparse_direct",
    "swiftjax.posegraph.solver_choice",
    "swiftjax.posegraph.initialization",
    "swiftjax.posegraph.solver",
    "swiftjax.posegraph.gnc",
    "swiftjax.posegraph.driver",
]
# PEP 484's numeric tower (an ``int`` where ``float`` is annotated, as mypy and pyright accept it).
jaxtyping.install_import_hook(JAXTYPED_MODULES, "beartype.beartype(conf=beartype.BeartypeConf(is_pep484_tower=True))")

import jax
import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]

CACHE = os.environ.get("JAX_COMPILATION_CACHE_DIR", str(pathlib.Path.home() / ".cache" / "swiftjax" / "jax-tests"))
jax.config.update("jax_compilation_cache_dir", CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


#: Drop JAX's compiled executables after a test module once the process holds this many memory
#: mappings (half of Linux's default ``vm.max_map_count``).  Measured: ~3.2 mappings per compiled
#: executable, all returned by ``jax.clear_caches()``; the persistent cache serves the recompiles.
MAX_MAPPINGS = 32_000


def _mapping_count() -> int:
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux: no such limit to stay under
        return 0


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    yield
    if _mapping_count() > MAX_MAPPINGS:
        import gc

        jax.clear_caches()
        gc.collect()


@contextlib.contextmanager
def jax_log(pattern: str) -> Iterator[list[tuple[str, str]]]:
    """JAX's compile log while the block runs (``jax_log_compiles``): ``(thread name, group 1)``
    of every message that ``re.match``-es ``pattern``, e.g. ``r"Compiling (?:jit\\()?([^) ]+)"``
    (the programs compiled) or ``r"Finished tracing (\\S+) for jit"`` (traced)."""
    import logging
    import re

    found: list[tuple[str, str]] = []

    class Matches(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            m = re.match(pattern, record.getMessage())
            if m:
                found.append((record.threadName, m.group(1)))

    handler, logger = Matches(), logging.getLogger("jax")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    jax.config.update("jax_log_compiles", True)
    try:
        yield found
    finally:
        jax.config.update("jax_log_compiles", False)
        logger.removeHandler(handler)
        logger.setLevel(level)


def find_shared() -> pathlib.Path | None:
    """The shared reference folder, or None."""
    env = os.environ.get("SWIFTJAX_SHARED")
    candidates = [pathlib.Path(env)] if env else []
    candidates.append(REPO.parent / "shared")
    for c in candidates:
        if (c / "data").is_dir() and (c / "golden").is_dir():
            return c
    return None


@pytest.fixture(scope="session")
def shared_dir() -> pathlib.Path:
    path = find_shared()
    if path is None and os.environ.get("CI"):
        pytest.fail("CI must have the shared reference data at ../shared or $SWIFTJAX_SHARED")
    if path is None:
        pytest.skip(
            "shared reference data not found: set SWIFTJAX_SHARED to the folder holding "
            "data/ and golden/, or place it at ../shared beside the repository"
        )
    return path


@pytest.fixture
def logged_warning(caplog):
    """``with logged_warning(r"pattern"):`` the block logs a warning of the ``swiftjax`` logger
    whose message matches ``pattern`` (``re.search``); ``logged_warning(None)``: it logs none.
    ``as found``: the block's warning messages.
    swiftjax's run messages go through :mod:`logging`, not :mod:`warnings`."""
    import contextlib
    import logging
    import re

    @contextlib.contextmanager
    def expect(pattern):
        caplog.clear()
        messages: list[str] = []  # the block's warnings, filled when it ends
        with caplog.at_level(logging.WARNING, logger="swiftjax"):
            yield messages
        messages += [
            r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name.startswith("swiftjax")
        ]
        if pattern is None:
            assert not messages, messages
        else:
            assert any(re.search(pattern, m) for m in messages), f"no warning matching {pattern!r}: {messages}"

    return expect


@pytest.fixture
def x64():
    """Enable float64 in JAX for the duration of one test."""
    with jax.enable_x64(True):
        yield


def _golden(shared_dir: pathlib.Path, family: str, name: str) -> pathlib.Path:
    d = shared_dir / "golden" / family
    if not (d / "tiny_golden.npz").is_file():
        pytest.fail(f"the shared folder {shared_dir} has no {name} golden tensors in {d}")
    return d


@pytest.fixture(scope="session")
def golden_dir(shared_dir: pathlib.Path) -> pathlib.Path:
    """``shared/golden/vggt``: tensors from the official VGGT code on a tiny configuration."""
    return _golden(shared_dir, "vggt", "VGGT")


@pytest.fixture(scope="session")
def da3_golden_dir(shared_dir: pathlib.Path) -> pathlib.Path:
    """``shared/golden/da3``: tensors from the official Depth Anything 3 code on tiny networks."""
    return _golden(shared_dir, "da3", "DA3")


@pytest.fixture(scope="session")
def pi3_golden_dir(shared_dir: pathlib.Path) -> pathlib.Path:
    """``shared/golden/pi3``: tensors from the official π³ / π³X code on tiny configurations."""
    d = shared_dir / "golden" / "pi3"
    if not (d / "tiny_golden.npz").is_file():
        pytest.fail(f"the shared folder {shared_dir} has no π³ golden tensors in {d}")
    return d


#: ``small_loop_run``'s configuration (``test_pipeline.py``'s CONFIG).
SMALL_RUN_CONFIG = dict(
    chunk_size=40, overlap=15, loop_min_separation=60, loop_nms_radius=10, point_stride=2, colmap_max_points=5_000
)


@pytest.fixture(scope="session")
def small_loop_run(tmp_path_factory):
    """``(run_dir, RunResult)`` of a finished synthetic loop run (42x140 frames, 9 chunks)."""
    from swiftjax import pipeline
    from swiftjax.synthetic import demo
    from swiftjax.synthetic.routes import loop_route

    poses = loop_route(width=60.0, length=40.0, corner_radius=10.0, laps=1.3)
    run = demo.trajectory_run(poses, seed=3, image_hw=(42, 140))
    out = tmp_path_factory.mktemp("small_loop_run") / "run"
    result = pipeline.reconstruct(
        run.predictor,
        out,
        pipeline.PipelineConfig(**SMALL_RUN_CONFIG),
        ground_truth=run.ground_truth,
        progress=False,
        log=lambda _: None,
    )
    return out, result

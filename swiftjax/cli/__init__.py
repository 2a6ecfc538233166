"""The ``swiftjax`` command: ``demo``, ``batch``, ``reconstruct``, ``view``, ``prune``, ``evaluate``,
``export-onnx``, one module each (``main_<command>``: its parser and its ``run``), their shared
option groups in :mod:`~swiftjax.cli.arguments`.

Bad input (a :class:`~swiftjax.errors.SwiftjaxError`, an ``OSError`` naming its file) ends
with a one-line ``swiftjax: error: ...`` and exit status 2 (``--debug`` shows its traceback);
anything else is a bug and keeps its traceback (exit status 1).  Messages go through the
``swiftjax`` logger, which the command prints: information on stdout as it is written,
warnings and errors on stderr as ``swiftjax: warning: ...`` / ``swiftjax: error: ...``;
``--quiet`` keeps only warnings and errors, ``--verbose`` adds debug messages.  JAX's
persistent compilation cache is enabled (``$SWIFTJAX_CACHE_DIR``, default
``~/.cache/swiftjax/jax``), so only the first run of a given shape pays for XLA compilation.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import pathlib
import sys
import time
import warnings
from collections.abc import Iterator, Sequence

from swiftjax.cli import (
    main_batch,
    main_demo,
    main_evaluate,
    main_export_onnx,
    main_prune,
    main_reconstruct,
    main_view,
)
from swiftjax.cli.arguments import CliError, HelpFormatter, check_int_flags, one_line
from swiftjax.errors import SwiftjaxError

__all__ = ["CliError", "build_parser", "main"]

logger = logging.getLogger(__name__)

#: The commands in the order ``swiftjax --help`` lists them.
COMMANDS = (main_demo, main_batch, main_reconstruct, main_view, main_prune, main_evaluate, main_export_onnx)

#: The commands whose run ends with "done in ... s".
_RUNS = ("demo", "reconstruct", "batch")


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command (each command module adds its own subparser)."""
    parser = argparse.ArgumentParser(
        prog="swiftjax",
        description="SwiftVGGT large-scale reconstruction (JAX geometry core).",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("--quiet", action="store_true", help="print only warnings and errors")
    verbosity.add_argument("--verbose", action="store_true", help="print debug messages too")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub, formatter_class=HelpFormatter)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: ``sys.argv[1:]``), run the command; its exit status (2: bad input)."""
    # NumPy's LAPACK (the whitening fit's eigh) is much slower multi-threaded on a small, busy
    # machine (docs/performance/pipeline.md); XLA does not use OpenBLAS.  Must be set before
    # numpy is imported.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING if args.quiet else logging.DEBUG if args.verbose else logging.INFO
    with _messages_to_terminal(level):
        _enable_compilation_cache()
        try:
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("default")
                check_int_flags(args)
                code: int = args.func(args)
            if args.command in _RUNS:
                logger.info(f"done in {time.perf_counter() - t0:.1f} s")
            return code
        except KeyboardInterrupt:
            _quiesce()
            print("swiftjax: interrupted (finished chunks are kept; re-run to resume)", file=sys.stderr)
            return 130
        except Exception as err:
            if args.debug or not _prints_one_line(err):
                raise  # a bug: its traceback, exit status 1
            print(f"swiftjax: error: {_error_line(err)}", file=sys.stderr)
            return 2


# ------------------------------------------------------------------------ messages


class _TerminalHandler(logging.Handler):
    """A message as the user reads it: information on stdout as written, warnings and errors
    on stderr after ``swiftjax: warning:`` / ``swiftjax: error:``.  The streams are looked up
    at each message (a caller may have replaced ``sys.stdout``, as pytest's capture does)."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
            if record.levelno >= logging.ERROR:
                stream, text = sys.stderr, f"swiftjax: error: {text}"
            elif record.levelno >= logging.WARNING:
                stream, text = sys.stderr, f"swiftjax: warning: {text}"
            else:
                stream = sys.stdout
            stream.write(text + "\n")
            stream.flush()
        except Exception:
            self.handleError(record)


@contextlib.contextmanager
def _messages_to_terminal(level: int) -> Iterator[None]:
    """The ``swiftjax`` logger at ``level`` printed by :class:`_TerminalHandler` for one command
    (removed afterwards: ``main`` may run many times in one process)."""
    root = logging.getLogger("swiftjax")
    handler = _TerminalHandler()
    previous = root.level
    root.addHandler(handler)
    root.setLevel(level)
    try:
        yield
    finally:
        root.removeHandler(handler)
        root.setLevel(previous)


# -------------------------------------------------------------------------- set-up


def _enable_compilation_cache() -> None:
    import jax

    cache = os.environ.get("SWIFTJAX_CACHE_DIR", str(pathlib.Path.home() / ".cache" / "swiftjax" / "jax"))
    try:
        pathlib.Path(cache).mkdir(parents=True, exist_ok=True)
    except OSError:
        logger.debug(f"swiftjax: compilation cache {cache} is not writable: every run compiles")
        return  # an unwritable cache only costs compile time
    jax.config.update("jax_compilation_cache_dir", cache)
    # Every program, also the small ones (each costs a file write on the first run, a read after).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    logger.debug(f"swiftjax: compilation cache {cache}")


# -------------------------------------------------------------------------- errors

#: Top-level packages of the optional extras (pyproject.toml): a missing one is a one-line error.
_EXTRA_PACKAGES = frozenset({"torch", "onnx", "onnxruntime", "cv2", "safetensors", "viser", "ray", "cvxopt"})


def _prints_one_line(err: BaseException) -> bool:
    """A user-facing error: a :class:`~swiftjax.errors.SwiftjaxError`, an ``OSError`` naming its
    file, running out of memory, or a missing optional extra.  Anything else is a bug."""
    if isinstance(err, (SwiftjaxError, MemoryError)):
        return True
    if isinstance(err, OSError):
        return err.filename is not None
    return isinstance(err, ModuleNotFoundError) and (err.name or "").split(".")[0] in _EXTRA_PACKAGES


def _error_line(err: BaseException) -> str:
    """The one line of a user-facing error, with what to do for memory and missing extras."""
    if isinstance(err, MemoryError):
        return f"out of memory ({one_line(err)}); use smaller inputs, chunks or images"
    if isinstance(err, ImportError):
        return f"{one_line(err)} (install the extra: pip install 'swiftjax[inference]')"
    return one_line(err)


def _quiesce(timeout: float = 60.0) -> None:
    """After a Ctrl-C, before the interpreter finalises: wait for the computations JAX still
    runs on its own threads and join swiftjax's writer threads, so that none of them calls
    into a finalising interpreter ('Fatal Python error: PyThreadState_Get ... finalizing')."""
    import threading

    jax = sys.modules.get("jax")
    if jax is not None:
        with contextlib.suppress(Exception):
            jax.effects_barrier()
        with contextlib.suppress(Exception):
            for array in jax.live_arrays():
                array.block_until_ready()
    deadline = time.monotonic() + timeout
    for thread in threading.enumerate():
        if thread is not threading.current_thread() and not thread.daemon and thread.name.startswith("swiftjax-"):
            thread.join(max(0.0, deadline - time.monotonic()))

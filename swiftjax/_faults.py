"""Fault injection for the test suite: kill this process at a named point of a run.

Only tests set ``SWIFTJAX_FAULT``; unset (always, for users) :func:`point` is one dictionary
lookup.  The variable holds ``NAME[:INDEX][:SIGNAL]``, e.g. ``chunk-write:2:KILL`` (SIGKILL
when chunk 2's temp file is written, before it is renamed into place) or ``temporal-done::INT``
(SIGINT, i.e. a Ctrl-C, when the temporal stage has finished).  ``INDEX`` empty matches every
index; ``SIGNAL`` is ``INT`` (default), ``KILL`` or ``STOP`` (the process freezes, e.g. to
hold the run directory's lock while a test starts a second writer).  The points are listed in :data:`POINTS`.

SIGINT is delivered to the main thread (Python raises ``KeyboardInterrupt`` there at its next
bytecode), so a point reached on a background thread interrupts the main thread's work, as a
real Ctrl-C would.  SIGKILL ends the process at once, wherever it is.
"""

from __future__ import annotations

import os
import signal

__all__ = ["POINTS", "point"]

ENV = "SWIFTJAX_FAULT"

#: Every fault point, in the order a run reaches them.
POINTS = (
    "chunk-predicted",  # chunk t predicted, nothing of it stored yet
    "chunk-write",  # chunk t's temp file complete, not yet renamed (a write in progress)
    "chunk-recorded",  # chunk t (and edge t-1) recorded in the manifest
    "temporal-done",  # every chunk and temporal edge recorded
    "loop-recorded",  # loop edge k recorded
    "loops-done",
    "graph-done",
    "export-chunk",  # export: chunk t's points appended to the (temporary) PLY
    "export-done",  # every output written (not yet renamed into place), metrics.json excepted
)


def point(name: str, index: int | None = None) -> None:
    """Signal this process if ``$SWIFTJAX_FAULT`` names this point (and index)."""
    spec = os.environ.get(ENV)
    if not spec:
        return
    parts = spec.split(":")
    if parts[0] != name:
        return
    want = parts[1] if len(parts) > 1 else ""
    if want and (index is None or int(want) != int(index)):
        return
    sig = parts[2] if len(parts) > 2 and parts[2] else "INT"
    os.kill(os.getpid(), {"KILL": signal.SIGKILL, "STOP": signal.SIGSTOP}.get(sig, signal.SIGINT))

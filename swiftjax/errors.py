"""The one base of swiftjax's user-facing errors.

Every error raised for bad input (a flag, a file, a configuration, a checkpoint) derives from
:class:`SwiftjaxError`; the ``swiftjax`` command prints such an error as one line and exits
with status 2, while anything else (a bug) keeps its traceback.  The classes keep a second,
built-in base (``ValueError``, ``RuntimeError``) where callers catch that.
"""

from __future__ import annotations

__all__ = ["SwiftjaxError"]


class SwiftjaxError(Exception):
    """Base of every user-facing swiftjax error: its message is one line naming the input and
    what is wrong with it."""

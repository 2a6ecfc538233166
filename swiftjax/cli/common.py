"""What every command shares: :class:`CliError` and the one-line form of an error."""

from __future__ import annotations

import sys

from swiftjax.errors import SwiftjaxError

__all__ = ["CliError", "is_user_error", "one_line"]


class CliError(SwiftjaxError):
    """A user-facing error: printed as one line, exit status 2."""


def one_line(err: BaseException) -> str:
    """The error's message on one line (an ``OSError``: its reason and its file name)."""
    text = str(err) or type(err).__name__
    if isinstance(err, OSError) and err.filename:
        text = f"{err.strerror or text}: {err.filename}"
    return " ".join(text.split())


def is_user_error(err: BaseException) -> bool:
    """A checkpoint error (without importing torch to name its class) or a value error."""
    checkpoint = sys.modules.get("inference.checkpoint")
    return isinstance(err, ValueError) or (
        checkpoint is not None and isinstance(err, getattr(checkpoint, "CheckpointError", ()))
    )

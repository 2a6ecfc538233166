"""Plain-text tables for the CLI summary and the bench/ scripts."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

__all__ = ["format_value", "markdown_table"]


def format_value(v: Any) -> str:
    """Three significant digits for moderate floats, scientific notation otherwise."""
    if isinstance(v, bool) or not isinstance(v, float):
        return str(v)
    if v == 0 or 1e-3 <= abs(v) < 1e5:
        return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"
    return f"{v:.2e}"


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-markdown table (also readable as plain text)."""
    lines = ["| " + " | ".join(headers) + " |", "| " + " | ".join("---" for _ in headers) + " |"]
    lines += ["| " + " | ".join(format_value(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)

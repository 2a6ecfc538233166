"""Plain-text tables: the CLI's end-of-run summary (:func:`text_table`) and the bench/
scripts' markdown tables (:func:`markdown_table`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

__all__ = ["format_value", "format_fixed", "markdown_table", "text_table"]


def format_value(v: Any) -> str:
    """Three significant digits for moderate floats, scientific notation otherwise."""
    if isinstance(v, bool) or not isinstance(v, float):
        return str(v)
    if v == 0 or 1e-3 <= abs(v) < 1e5:
        return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"
    return f"{v:.2e}"


def format_fixed(v: Any, significant: int = 3, max_decimals: int = 6) -> str:
    """A number in positional notation, never scientific: integers with thousands separators,
    floats with ``significant`` digits (at most ``max_decimals`` decimals, so 1.8e-05 reads
    ``0.000018`` and 2e-9 reads ``0``)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return str(v)
    if isinstance(v, int):
        return f"{v:,}"
    if not math.isfinite(v):
        return str(v)
    if v == 0:
        return "0"
    decimals = min(max_decimals, max(0, significant - 1 - math.floor(math.log10(abs(v)))))
    text = f"{v:,.{decimals}f}"
    return "0" if float(text.replace(",", "")) == 0 else text


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-markdown table (also readable as plain text)."""
    lines = ["| " + " | ".join(headers) + " |", "| " + " | ".join("---" for _ in headers) + " |"]
    lines += ["| " + " | ".join(format_value(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def text_table(rows: Sequence[Sequence[Any] | str], indent: int = 2) -> str:
    """A terminal table: the first column left-aligned, the others right-aligned, columns two
    spaces apart; a row that is a plain string is a section heading (flush left).  Values
    are formatted by :func:`format_fixed` unless they are strings already."""
    cells = [[v if isinstance(v, str) else format_fixed(v) for v in row] for row in rows if not isinstance(row, str)]
    ncol = max((len(r) for r in cells), default=0)
    widths = [max((len(r[c]) for r in cells if c < len(r)), default=0) for c in range(ncol)]
    lines, it = [], iter(cells)
    for row in rows:
        if isinstance(row, str):
            lines.append(row)
            continue
        r = next(it)
        parts = [r[0].ljust(widths[0])] + [v.rjust(widths[c + 1]) for c, v in enumerate(r[1:])]
        lines.append(" " * indent + "  ".join(parts).rstrip())
    return "\n".join(lines)

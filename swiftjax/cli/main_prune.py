"""``swiftjax prune``: shrink a finished run directory (its chunk store's dense maps)."""

from __future__ import annotations

import argparse
import pathlib
from typing import Any

__all__ = ["add_parser", "run"]


def add_parser(sub: Any, **kw: Any) -> argparse.ArgumentParser:
    """The ``prune`` subparser (``kw``: the parser's formatter)."""
    p: argparse.ArgumentParser = sub.add_parser(
        "prune",
        help="shrink a finished run directory: drop the chunk store's dense maps, keep every output",
        description="Drop the depth and confidence maps from the chunk files of a finished run (most of "
        "chunks/). Every output is kept; 'swiftjax view' and re-runs with other export or pose-graph "
        "options still predict nothing; a re-run that needs the maps (other loop or temporal "
        "options, changed frames) predicts those chunks again.",
        **kw,
    )
    p.add_argument("run_dir", type=pathlib.Path, help="the --out folder of a finished run")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Prune; exit status 0."""
    from swiftjax.pipeline import rundir

    rundir.prune(args.run_dir)
    return 0

"""``swiftjax view``: the web viewer (viser) of a run directory, finished or running."""

from __future__ import annotations

import argparse
import pathlib
from typing import Any

from swiftjax.cli import runs
from swiftjax.cli.arguments import CliError

__all__ = ["add_parser", "run"]


def add_parser(sub: Any, **kw: Any) -> argparse.ArgumentParser:
    """The ``view`` subparser (``kw``: the parser's formatter)."""
    p: argparse.ArgumentParser = sub.add_parser(
        "view", help="web viewer (viser) of a run directory, finished or running", **kw
    )
    p.add_argument("run_dir", type=pathlib.Path, help="the --out folder of a run")
    p.add_argument("--port", type=int, default=8080, help="port to serve on")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (0.0.0.0 shares it on the network)")
    p.add_argument("--max-points", type=int, default=1_000_000, help="point budget (uniform sample)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Serve until Ctrl-C; exit status 0."""
    viewer = runs.import_viewer()
    try:
        v = viewer.serve(args.run_dir, host=args.host, port=args.port, max_points=args.max_points)
    except viewer.ViewerError as err:
        raise CliError(str(err)) from None
    try:
        v.watch()
    except KeyboardInterrupt:
        pass
    finally:
        v.close()
    return 0

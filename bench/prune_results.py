"""Keep only the latest result JSON of each bench script in ``bench/results/``.

A result file is ``<name>-<UTC timestamp>.json`` (:func:`bench.common.write_results`); the
script is the part of ``<name>`` before its first ``-`` (``pipeline-baseline-<commit>`` runs
belong to ``bench_pipeline.py`` as ``pipeline`` does).  The newest file of each script, by the
timestamp in its name, is kept and the others are deleted; they stay in git history.

    python bench/prune_results.py            # delete
    python bench/prune_results.py --dry-run  # list what would go
"""

from __future__ import annotations

import argparse
import pathlib
import re

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
_STAMP = re.compile(r"-(\d{8})[T-]?(\d{6})Z?$")


def series(path: pathlib.Path) -> tuple[str, str] | None:
    """``(script, sortable timestamp)`` of a result file, or None for other files."""
    m = _STAMP.search(path.stem)
    if m is None:
        return None
    return path.stem.split("-", 1)[0], m.group(1) + m.group(2)


def stale(results: pathlib.Path = RESULTS) -> list[pathlib.Path]:
    """Every result file that is not the newest of its script."""
    newest: dict[str, tuple[str, pathlib.Path]] = {}
    out = []
    for p in sorted(results.glob("*.json")):
        key = series(p)
        if key is None:
            continue
        script, stamp = key
        if script in newest and newest[script][0] >= stamp:
            out.append(p)
            continue
        if script in newest:
            out.append(newest[script][1])
        newest[script] = (stamp, p)
    return sorted(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dry-run", action="store_true", help="list the files, delete nothing")
    args = ap.parse_args()
    for p in stale():
        print(("would delete " if args.dry_run else "deleted ") + str(p.relative_to(RESULTS.parent.parent)))
        if not args.dry_run:
            p.unlink()


if __name__ == "__main__":
    main()

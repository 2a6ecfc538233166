"""``swiftjax batch``: many sequences, each its own resumable run, spread over the workers."""

from __future__ import annotations

import argparse
import dataclasses
import os
import pathlib
from typing import Any

from swiftjax.cli import arguments, model, runs
from swiftjax.cli.arguments import CliError

__all__ = ["add_parser", "run"]


def add_parser(sub: Any, **kw: Any) -> argparse.ArgumentParser:
    """The ``batch`` subparser (``kw``: the parser's formatter)."""
    p: argparse.ArgumentParser = sub.add_parser(
        "batch", help="many sequences, each its own resumable run, spread over the workers", **kw
    )
    p.add_argument(
        "list",
        type=pathlib.Path,
        help="text file with one 'INPUT [GROUND_TRUTH]' per line (shell quoting: \"my seq\" gt.txt; '#' "
        "starts a comment at a line's start or after a space), or a folder of sequence folders "
        "(frames in it or in its images/, ground truth in gt.txt, groundtruth.txt or poses.txt)",
    )
    p.add_argument(
        "--out",
        type=pathlib.Path,
        required=True,
        metavar="DIR",
        help="one run directory per sequence, and batch.json; required",
    )
    p.add_argument(
        "--timestamps",
        default=None,
        metavar="NAME",
        help="each sequence's times file for poses_tum.txt, found in its folder or beside its frames "
        "folder or video (e.g. rgb.txt; the format of reconstruct --timestamps; default: a video's "
        "own times, else the frame index)",
    )
    arguments.add_image_options(p)
    arguments.add_run_options(p)
    arguments.add_method_options(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run the command; its exit status (1 if a sequence failed)."""
    from swiftjax.pipeline import batch

    if args.list.is_dir():
        items = batch.sequence_folders(args.list)
    elif args.list.is_file():
        items = batch.read_list(args.list)
    else:
        raise CliError(f"batch list {args.list} does not exist (a text file of inputs or a folder of sequences)")
    args.input = "."  # image_spec's input: replaced per sequence below
    spec = model.image_spec(args)
    names = batch.unique_names([inp for inp, _ in items])
    times = (
        batch.sequence_timestamps([inp for inp, _ in items], args.timestamps)
        if args.timestamps
        else [None] * len(items)
    )
    jobs = [
        batch.Sequence(
            name,
            dataclasses.replace(spec, input=os.path.abspath(inp)),
            os.path.abspath(gt) if gt else None,
            args.gt_format,
            t,
        )
        for name, (inp, gt), t in zip(names, items, times)
    ]
    return runs.run_batch(args, jobs)

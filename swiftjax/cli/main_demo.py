"""``swiftjax demo``: a synthetic loop route through the full pipeline (no weights needed)."""

from __future__ import annotations

import argparse
import contextlib
from typing import Any

from swiftjax.cli import arguments, runs
from swiftjax.cli.arguments import CliError

__all__ = ["add_parser", "run"]

#: Largest side of the synthetic camera (``demo --image-size``): 100000x100000 asked for
#: 30 GB per frame and hung on the failed allocation.
MAX_SIDE = 4096


def add_parser(sub: Any, **kw: Any) -> argparse.ArgumentParser:
    """The ``demo`` subparser (``kw``: the parser's formatter)."""
    p: argparse.ArgumentParser = sub.add_parser(
        "demo", help="synthetic loop route through the full pipeline (no weights needed)", **kw
    )
    p.add_argument("--frames", type=int, default=None, help="frames of the route (default: all, ~620)")
    p.add_argument("--out", default="runs/demo", metavar="DIR", help="run directory")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic world and oracle")
    p.add_argument("--image-size", default="154x518", metavar="HxW", help="synthetic camera image size")
    p.add_argument(
        "--frame-spacing",
        type=float,
        default=1.0,
        metavar="METRES",
        help="distance between frames along the route (4: the whole route in ~155 frames)",
    )
    p.add_argument(
        "--batch",
        type=int,
        default=None,
        metavar="K",
        help="K routes (seeds SEED..SEED+K-1) as a batch of runs in OUT/route_NN (see 'swiftjax batch')",
    )
    arguments.add_run_options(p)
    arguments.add_view_options(p)
    arguments.add_method_options(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run the command; its exit status."""
    from swiftjax import pipeline
    from swiftjax.synthetic import demo

    out = args.out = arguments.out_dir(args.out)
    if args.batch is not None:
        return _batch(args)
    config = arguments.pipeline_config(args)
    if args.frames is not None and args.frames < 1:
        raise CliError(f"--frames must be >= 1, got {args.frames}")
    try:
        h, w = (int(v) for v in args.image_size.lower().split("x"))
    except ValueError:
        raise CliError(f"--image-size must be HEIGHTxWIDTH, e.g. 154x518, got {args.image_size!r}") from None
    if not (14 <= h <= MAX_SIDE and 14 <= w <= MAX_SIDE):
        raise CliError(f"--image-size {args.image_size}: height and width must be from 14 to {MAX_SIDE} pixels")
    if not (args.frame_spacing > 0 and args.frame_spacing < 1e3):
        raise CliError(f"--frame-spacing must be in (0, 1000) metres, got {args.frame_spacing}")
    with contextlib.closing(arguments.make_executor(args)) as executor, runs.LiveView(args) as live:
        route = demo.loop_route_run(args.frames, seed=args.seed, image_hw=(h, w), spacing_m=args.frame_spacing)
        result = pipeline.reconstruct(
            route.predictor,
            out,
            config,
            ground_truth=route.ground_truth,
            overwrite=args.overwrite,
            progress=not args.no_progress,
            executor=executor,
        )
        runs.print_summary(result)
        live.wait()
    return runs.empty_result(result, config)


def _batch(args: argparse.Namespace) -> int:
    """``demo --batch K``: K synthetic routes (seeds ``seed .. seed + K - 1``) as a batch."""
    from swiftjax.pipeline import batch
    from swiftjax.synthetic import demo

    if args.batch < 1:
        raise CliError(f"--batch must be >= 1, got {args.batch}")
    if getattr(args, "view", False):
        raise CliError("--view shows one run: it does not combine with --batch")
    arguments.check_executor_args(args)
    jobs = []
    for k in range(args.batch):
        route = demo.loop_route_run(args.frames, seed=args.seed + k)
        jobs.append(batch.Sequence(f"route_{args.seed + k:02d}", route.predictor.spec(), route.ground_truth))
    return runs.run_batch(args, jobs)

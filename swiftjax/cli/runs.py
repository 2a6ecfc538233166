"""What the run commands (demo, reconstruct, batch) share: the batch driver, the output
directory's checks, the summary and the empty-run verdict, the live viewer of ``--view``."""

from __future__ import annotations

import argparse
import importlib
import logging
import pathlib
import sys
import time
from typing import Any

from swiftjax.cli.arguments import CliError, check_executor_args, pipeline_config

__all__ = [
    "LiveView",
    "check_out_not_in_input",
    "empty_result",
    "import_viewer",
    "load_ground_truth",
    "print_summary",
    "run_batch",
]

logger = logging.getLogger(__name__)


def run_batch(args: argparse.Namespace, jobs: list[Any]) -> int:
    """``jobs`` through :func:`swiftjax.pipeline.batch.run_batch`; exit 1 if a sequence failed."""
    from swiftjax.pipeline import batch

    cpus = check_executor_args(args)
    config = pipeline_config(args)
    rows = batch.run_batch(
        jobs,
        args.out,
        config,
        executor=args.executor,
        workers=args.workers,
        gpus_per_worker=args.gpus_per_worker,
        cpus_per_worker=cpus,
        ray_address=args.ray_address,
        overwrite=args.overwrite,
    )
    print(batch.batch_table(rows))
    print(f"{args.out / 'batch.json'}")
    failed = [r["sequence"] for r in rows if r["status"] != "ok"]
    if failed:
        print(f"swiftjax: {len(failed)} of {len(rows)} sequences failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


def check_out_not_in_input(out: pathlib.Path, source: Any, folder: pathlib.Path | None = None) -> None:
    """Refuse an output directory inside the input folder (outputs would mix with, and on the
    next run be read as, frames); ``folder``: a followed folder (no frame in it yet)."""
    roots = {pathlib.Path(p).parent.resolve() for p in getattr(source, "paths", [])} | (
        {folder.resolve()} if folder is not None else set()
    )
    target = out.resolve()
    for root in roots:
        if target == root or target.is_relative_to(root):
            raise CliError(f"--out {out} is inside the input folder {root}: choose a directory outside the frames")


def load_ground_truth(path: pathlib.Path, fmt: str) -> Any:
    """``--gt`` in ``--gt-format``: camera-to-world poses ``[N, 4, 4]``."""
    from swiftjax.io import trajectory

    if not path.exists():
        raise CliError(f"ground-truth file {path} does not exist")
    return trajectory.read_kitti(path) if fmt == "kitti" else trajectory.read_tum(path)[1]


def print_summary(result: Any) -> None:
    """The run's summary table on stdout."""
    from swiftjax.pipeline import summary_table

    print(summary_table(result))


def empty_result(result: Any, config: Any) -> int:
    """Exit status 1 and a loud line when the run wrote no point ("done" over an empty
    cloud was exit 0), naming the options that drop pixels and were set."""
    if int(result.metrics.get("points", 1)) > 0:
        return 0
    culprits = [
        f"{flag} {value}"
        for flag, value in (
            ("--point-conf-ratio", config.point_conf_ratio),
            ("--mask-dir", config.mask_dir),
            ("--drop-sky", config.drop_sky or None),
            ("--intrinsics", config.intrinsics),
            ("--voxel-size", config.voxel_size),
        )
        if value is not None and not (flag == "--point-conf-ratio" and value == 0.75)
    ]
    why = f"check {', '.join(culprits)}" if culprits else "the model's depths or confidences are unusable"
    logger.error(
        f"the run wrote 0 points (every pixel was dropped; {why}); the trajectory and the other "
        f"outputs are in {result.run_dir}"
    )
    return 1


class LiveView:
    """``--view``: a viewer of the run directory while it is written, kept open after the run."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.live = None
        if getattr(args, "view", False):
            viewer = import_viewer()
            try:
                self.live = viewer.LiveViewer(
                    args.out, host=args.view_host, port=args.view_port, max_points=args.view_max_points
                )
            except viewer.ViewerError as err:
                raise CliError(str(err)) from None

    def __enter__(self) -> LiveView:
        return self

    def wait(self) -> None:
        """Keep serving the finished run until Ctrl-C."""
        if self.live is None:
            return
        self.live.refresh_now()
        logger.info("swiftjax: run finished; the viewer stays open (Ctrl-C to stop)")
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass

    def __exit__(self, *exc: Any) -> None:
        if self.live is not None:
            self.live.close()


def import_viewer() -> Any:
    """:mod:`swiftjax.viewer`, or a one-line error naming the extra when viser is missing."""
    try:
        importlib.import_module("viser")
    except ImportError:
        raise CliError("the viewer needs viser: pip install 'swiftjax[view]'") from None
    from swiftjax import viewer

    return viewer

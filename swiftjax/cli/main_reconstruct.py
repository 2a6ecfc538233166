"""``swiftjax reconstruct``: images (folder, glob or video) to a trajectory and a point cloud,
offline or live (``--follow`` a folder that a recorder fills, ``--replay-fps``)."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import pathlib
import shutil
import sys
from typing import Any

from swiftjax.cli import arguments, model, runs
from swiftjax.cli.arguments import CliError, one_line

__all__ = ["add_parser", "run"]

logger = logging.getLogger(__name__)


def add_parser(sub: Any, **kw: Any) -> argparse.ArgumentParser:
    """The ``reconstruct`` subparser (``kw``: the parser's formatter)."""
    p: argparse.ArgumentParser = sub.add_parser(
        "reconstruct", help="images (folder, glob or video) -> trajectory and point cloud", **kw
    )
    p.add_argument("input", help="image folder, glob pattern or video file")
    p.add_argument("--out", required=True, metavar="DIR", help="run directory (resumable); required")
    arguments.add_image_options(p)
    p.add_argument("--gt", type=pathlib.Path, metavar="FILE", help="ground-truth poses for ATE (default: none)")
    p.add_argument(
        "--timestamps",
        type=pathlib.Path,
        metavar="FILE",
        help="per-frame times for poses_tum.txt: 'time name' lines (TUM rgb.txt) or one time per image "
        "(default: a video's own times, else the frame index)",
    )
    group = p.add_argument_group("live input (poses while the frames arrive: poses_live.jsonl)")
    group.add_argument(
        "--follow",
        action="store_true",
        help="INPUT is a folder that a recorder fills: frames are taken once complete, in name order, "
        "until an END file appears in it, --follow-timeout, or Ctrl-C (then the run finishes with "
        "the frames so far); the finished run is the offline run of those frames",
    )
    group.add_argument(
        "--follow-timeout",
        type=float,
        default=None,
        metavar="SECONDS",
        help="with --follow: end after this many seconds without a new frame (default: 60)",
    )
    group.add_argument(
        "--replay-fps",
        type=float,
        default=None,
        metavar="FPS",
        help="replay INPUT (folder, glob or video) at FPS frames per second through the live engine",
    )
    group.add_argument(
        "--whitening-from",
        type=pathlib.Path,
        default=None,
        metavar="RUN_DIR",
        help="with --follow or --replay-fps: live loop detection whitens with the whitening of the "
        "finished run RUN_DIR (same model; fitted on the descriptors its chunk files record) "
        "instead of refitting on the frames seen so far (default: refit on the prefix)",
    )
    arguments.add_run_options(p)
    arguments.add_view_options(p)
    arguments.add_method_options(p)
    p.set_defaults(func=run)
    return p


def _check_live_flags(args: argparse.Namespace) -> None:
    """``--follow``, ``--follow-timeout`` and ``--replay-fps``, before any work."""
    if args.follow and args.replay_fps is not None:
        raise CliError(
            "--follow and --replay-fps exclude each other (follow a growing folder, or replay a finished one)"
        )
    if args.follow_timeout is not None and not args.follow:
        raise CliError("--follow-timeout needs --follow")
    if args.follow_timeout is not None and not (args.follow_timeout > 0 and math.isfinite(args.follow_timeout)):
        raise CliError(f"--follow-timeout must be a positive number of seconds, got {args.follow_timeout:g}")
    if args.replay_fps is not None and not (args.replay_fps > 0 and math.isfinite(args.replay_fps)):
        raise CliError(f"--replay-fps must be a positive number of frames per second, got {args.replay_fps:g}")
    if args.follow:
        if not pathlib.Path(args.input).is_dir():
            raise CliError(f"--follow {args.input}: not a folder (--follow watches a folder that a recorder fills)")
        used = [
            flag
            for flag, on in (
                ("--gt", args.gt is not None),
                ("--timestamps", args.timestamps is not None),
                ("--stride", args.stride != 1),
                ("--skip-bad", args.skip_bad),
                ("--executor ray", args.executor != "local"),
            )
            if on
        ]
        if used:
            raise CliError(f"{', '.join(used)} cannot be used with --follow (the frames are not known in advance)")
    if args.whitening_from is not None and not (args.follow or args.replay_fps is not None):
        raise CliError(
            "--whitening-from needs --follow or --replay-fps (an offline run fits its whitening on every frame)"
        )
    if (args.follow or args.replay_fps is not None) and args.executor != "local":
        raise CliError("--follow and --replay-fps run with --executor local")


def _reconstruct_live(args: argparse.Namespace, rec: Any, frames: Any, times: Any, check_first: Any) -> Any:
    """Feed ``rec`` (:class:`~swiftjax.pipeline.engine.Reconstruction`) the ``frames`` of a
    :class:`~swiftjax.io.follow.FollowSource` (each its file) or a
    :class:`~swiftjax.io.follow.ReplaySource` (the predictor knows them); the first SIGINT
    stops the source and the run finishes as a complete run, a second one interrupts."""
    import signal

    def stop(signum: int, frame: Any) -> None:
        # A plain write, not the logger: a signal handler must not take the logging lock.
        print(
            "swiftjax: stopping at the next frame; the run finishes with the frames so far (Ctrl-C again to interrupt)",
            file=sys.stderr,
        )
        frames.stop()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    previous = signal.signal(signal.SIGINT, stop)
    try:
        for frame in frames:
            if frame.index == 0:
                check_first(frame)
            rec.add_frame(frame.path if args.follow else None, time=times(frame.index))
    finally:
        signal.signal(signal.SIGINT, previous)
    if rec.num_frames == 0:
        raise CliError(f"{args.input}: stopped before any frame arrived: nothing to reconstruct")
    logger.info(f"swiftjax: {rec.num_frames} frames arrived (ended by {frames.ended_by}); final pass")
    return rec.finish()


def _whitening_from(args: argparse.Namespace, config: Any, predictor: Any) -> Any:
    """``--whitening-from RUN_DIR``'s whitening, before any frame is predicted: RUN_DIR must be
    a run of the same model (its manifest's model identity) whose chunk files record the
    descriptors (:func:`swiftjax.loops.online.load_whitening`, with this run's loop options).

    Raises:
        WhiteningSourceError: one line naming RUN_DIR (not a run, another model, nothing usable).
    """
    from swiftjax.loops.online import WhiteningSourceError, load_whitening
    from swiftjax.loops.options import LoopOptions
    from swiftjax.options import build
    from swiftjax.pipeline import reader

    run_dir = args.whitening_from
    try:
        manifest = reader.read_manifest(run_dir)
    except reader.RunReadError as err:
        raise WhiteningSourceError(f"--whitening-from: {one_line(err)}") from None
    recorded = (manifest.get("fingerprint") or {}).get("temporal", {}).get("identity", {}).get("model")
    ours = {k: v for k, v in predictor.fingerprint().items() if k != "frames"}.get("model")
    if (
        recorded is not None
        and ours is not None
        and json.dumps(recorded, sort_keys=True) != json.dumps(ours, sort_keys=True)
    ):
        raise WhiteningSourceError(
            f"--whitening-from {run_dir}: that run used another model than this one (its manifest's model "
            "identity differs), so its descriptors' whitening does not apply"
        )
    return load_whitening(run_dir, build(LoopOptions, config))


def kept_frames_dir(out: pathlib.Path) -> pathlib.Path:
    """Where ``--follow`` keeps the frames it read (``OUT/../.OUT.follow-frames``): beside the run
    directory, not in it (the finished run directory is the offline run's, file by file)."""
    return out.parent / f".{out.name}.follow-frames"


def run(args: argparse.Namespace) -> int:
    """Run the command; its exit status (1: the run wrote no point)."""
    keep = kept_frames_dir(pathlib.Path(args.out)) if args.follow and args.out.strip() else None
    try:
        code = _run(args)
    except BaseException:
        if keep is not None and keep.is_dir():
            if not (pathlib.Path(args.out) / "manifest.json").exists():
                shutil.rmtree(keep, ignore_errors=True)  # no run to resume: nothing worth keeping
            else:
                logger.info(
                    f"swiftjax: the frames this run read are kept in {keep} (the recorder may have deleted some)"
                )
        raise
    if keep is not None:
        shutil.rmtree(keep, ignore_errors=True)
    return code


def _run(args: argparse.Namespace) -> int:
    from swiftjax import pipeline
    from swiftjax.io import images

    # Everything is checked before the first prediction: options, output, input, GT, runner.
    config = arguments.pipeline_config(args)
    out = arguments.out_dir(args.out)
    if args.stride < 1:
        raise CliError(f"--stride must be >= 1, got {args.stride}")
    _check_live_flags(args)
    if args.whitening_from is not None and not config.loop_closure:
        raise CliError("--whitening-from is for live loop detection, which --no-loop-closure turns off")
    if args.follow:  # frames join the source as they arrive (ImagePredictor.append)
        from swiftjax.io.follow import FollowSource

        # Each frame is kept (hard link) beside the run directory as it is read, so that a
        # recorder may delete it (a ring buffer): the live chunks and the final pass read it
        # there; removed once the run is finished (kept if it fails: its frames, to resume).
        keep = kept_frames_dir(out)
        live: Any = FollowSource(args.input, timeout_s=args.follow_timeout or 60.0, keep=keep)
        source = images.ImageFiles([], description=str(args.input))
        runs.check_out_not_in_input(out, source, pathlib.Path(args.input))
    else:
        source = images.validate(images.list_frames(args.input, stride=args.stride), skip_bad=args.skip_bad)
        runs.check_out_not_in_input(out, source)
    gt = runs.load_ground_truth(args.gt, args.gt_format) if args.gt is not None else None
    if gt is not None and len(gt) != len(source):
        raise CliError(f"ground truth {args.gt} has {len(gt)} poses for {len(source)} frames")
    if gt is not None:  # before the run: a reference the ATE cannot use is named now, not after the run
        from swiftjax.pipeline.report import check_ground_truth

        check_ground_truth(gt, len(source), name=f"ground-truth file {args.gt}")
    if args.timestamps is not None:
        timestamps = images.read_timestamps(args.timestamps, source, args.stride)
        note = f"from {args.timestamps}"
    else:
        timestamps, note = source.timestamps()
    model.check_runner_options(args, check_device=getattr(args, "executor", "local") == "local")
    from inference.predictor import ImagePredictor

    spec = model.image_spec(args, checked=True)  # its model identity is part of the run directory's fingerprint
    backbone = model.backbone_named(spec.model)

    def check_size(frame: Any = None) -> None:
        hw = source.image_hw if frame is None else frame.image.shape[:2]
        try:  # an image size the network cannot take
            backbone.impl.preprocess_geometry(*hw, spec.mode)
        except ValueError as err:
            raise CliError(f"--model {spec.model} cannot take the frames of {args.input}: {one_line(err)}") from None

    if not args.follow:
        check_size()
    if args.replay_fps is not None:
        from swiftjax.io.follow import ReplaySource

        live = ReplaySource(
            getattr(source, "paths", None) or args.input,
            args.replay_fps,
            stride=1 if hasattr(source, "paths") else args.stride,
        )
    if len(source) < config.chunk_size and not args.follow:
        logger.info(f"swiftjax: {len(source)} frames, fewer than one chunk: running a single chunk")
    executor = arguments.make_executor(args)
    with contextlib.closing(executor):
        if args.executor == "local":  # load the model now: a bad checkpoint fails before any work
            runner: Any = model.make_runner(args, spec)
        else:  # each worker loads its own (ImageSpec)
            runner = spec.runner_factory()
        predictor = ImagePredictor(source, runner, mode=spec.mode, spec=spec)
        whitening = _whitening_from(args, config, predictor) if args.whitening_from is not None else None
        with contextlib.closing(predictor), runs.LiveView(args) as view:
            if args.follow or args.replay_fps is not None:
                from swiftjax.pipeline.engine import Reconstruction

                rec = Reconstruction(
                    out,
                    predictor,
                    config,
                    ground_truth=gt,
                    executor=executor,
                    overwrite=args.overwrite,
                    timestamps_note=note,
                    whitening=whitening,
                    whitening_source=None if whitening is None else str(args.whitening_from),
                )
                result = _reconstruct_live(
                    args, rec, live, lambda k: float(k if args.follow else timestamps[k]), check_size
                )
            else:
                result = pipeline.reconstruct(
                    predictor,
                    out,
                    config,
                    ground_truth=gt,
                    overwrite=args.overwrite,
                    progress=not args.no_progress,
                    timestamps=timestamps,
                    timestamps_note=note,
                    executor=executor,
                )
            runs.print_summary(result)
            view.wait()
    return runs.empty_result(result, config)

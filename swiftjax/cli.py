"""The ``swiftjax`` command: ``demo``, ``reconstruct``, ``batch``, ``view``, ``evaluate``, ``export-onnx``.

Bad input (a :class:`~swiftjax.errors.SwiftjaxError`, an ``OSError`` naming its file) ends
with a one-line ``swiftjax: error: ...`` and exit status 2 (``--debug`` shows its traceback);
anything else is a bug and keeps its traceback (exit status 1).  JAX's persistent compilation cache is enabled
(``$SWIFTJAX_CACHE_DIR``, default ``~/.cache/swiftjax/jax``), so only the first run of a
given shape pays for XLA compilation.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import math
import os
import pathlib
import sys
import time
import warnings
from collections.abc import Sequence
from typing import Any

import tomllib

from swiftjax.errors import SwiftjaxError

__all__ = ["main"]


class CliError(SwiftjaxError):
    """A user-facing error: printed as one line, exit status 2."""


# ------------------------------------------------------------------------------ set-up


def _enable_compilation_cache() -> None:
    import jax

    cache = os.environ.get("SWIFTJAX_CACHE_DIR", str(pathlib.Path.home() / ".cache" / "swiftjax" / "jax"))
    try:
        pathlib.Path(cache).mkdir(parents=True, exist_ok=True)
    except OSError:
        return  # an unwritable cache only costs compile time
    jax.config.update("jax_compilation_cache_dir", cache)
    # Every program, also the small ones (each costs a file write on the first run, a read after).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def _add_method_options(parser: argparse.ArgumentParser) -> None:
    """One ``--option`` per :class:`PipelineConfig` field, from its schema (:mod:`swiftjax.options`)."""
    from swiftjax import options
    from swiftjax.pipeline import PipelineConfig

    group = parser.add_argument_group(
        "method parameters (paper defaults; a flag overrides the --config file, which overrides the default)"
    )
    options.add_arguments(group, PipelineConfig)
    parser.add_argument(
        "--config",
        type=pathlib.Path,
        metavar="FILE",
        help="TOML file of method parameters (top level or a [swiftjax] table; keys as the flags, with _)",
    )


def _pipeline_config(args: argparse.Namespace) -> Any:
    """The configuration from ``--config`` and the flags, validated by the schema before any work."""
    from swiftjax import options
    from swiftjax.pipeline import PipelineConfig

    values: dict[str, Any] = {}
    if args.config is not None:
        values.update(_read_config_table(args.config))
    flags = {f.name: getattr(args, f.name, None) for f in dataclasses.fields(PipelineConfig)}
    try:
        config = options.from_sources(
            PipelineConfig, values, flags, file_name=str(args.config) if args.config else None
        )
    except (TypeError, ValueError) as err:
        raise CliError(f"invalid configuration: {err}") from err
    given = {k for k, v in flags.items() if v is not None} | set(values)
    scaled = [
        f"{options.flag(f.name)} {getattr(config, f.name)}"
        for f in dataclasses.fields(PipelineConfig)
        if f.name not in given and getattr(config, f.name) != f.default
    ]
    if scaled:
        print(f"swiftjax: --chunk-size {config.chunk_size}: defaults scaled to fit it: {', '.join(scaled)}")
    return config


def _read_config_table(path: pathlib.Path) -> dict[str, Any]:
    """The method options of a ``--config`` TOML file: its top level or its ``[swiftjax]``
    table, not both (top-level keys beside the table would be silently dropped).  A UTF-8
    byte-order mark (Windows editors write one) is accepted."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError as err:
        raise CliError(f"config file {path} does not exist") from err
    except IsADirectoryError as err:
        raise CliError(f"config file {path} is a directory") from err
    try:
        data = tomllib.loads(raw.decode("utf-8-sig"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise CliError(f"config file {path} is not valid TOML: {err}") from err
    if "swiftjax" not in data:
        return data
    table = data["swiftjax"]
    if not isinstance(table, dict):
        raise CliError(f"config file {path}: [swiftjax] must be a table")
    others = [k for k, v in data.items() if k != "swiftjax" and not isinstance(v, dict)]  # other tables: other tools
    if others:
        raise CliError(
            f"config file {path} has keys both at the top level ({', '.join(others)}) and in a [swiftjax] "
            "table: put every option in one of them"
        )
    return table


def _common_run_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a run directory that holds another input, model or configuration (deletes only "
        "the files its manifest records). What is fingerprinted: each input frame's content "
        "(name, size, SHA-256 of the whole file; a video: the video file's), the weights file's "
        "SHA-256 (whole file, cached by device, inode, size, mtime and ctime), the model "
        "configuration, backend, dtype, device class, preprocessing mode, --intrinsics and "
        "--mask-dir contents, and the options by stage: a changed temporal option needs "
        "--overwrite, a changed frame re-predicts only its chunks, loop options re-run the loop "
        "stage, pose-graph and export options (--colmap*, --voxel-size) re-run only those",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    group = parser.add_argument_group("execution (where the VGGT predictions run)")
    group.add_argument(
        "--executor",
        choices=("local", "ray"),
        default="local",
        help="local: this process, predicting the next chunk while the host aligns (default); "
        "ray: a pool of Ray actors (pip install 'swiftjax[ray]')",
    )
    group.add_argument(
        "--workers", type=int, default=1, metavar="N", help="Ray actors, each with one model (default 1)"
    )
    group.add_argument(
        "--gpus-per-worker",
        type=float,
        default=0.0,
        metavar="G",
        help="GPUs per Ray actor (default 0; 1 = one GPU each)",
    )
    group.add_argument(
        "--ray-address",
        default=None,
        metavar="ADDR",
        help="join this Ray cluster (from 'ray start --head'); default: a local cluster on loopback",
    )


def _check_executor_args(args: argparse.Namespace) -> float:
    """Validate the execution options; returns the CPUs per Ray worker."""
    from swiftjax.pipeline.executors import check_workers

    check_workers(args.workers)
    if args.gpus_per_worker < 0:
        raise CliError(f"--gpus-per-worker must be >= 0, got {args.gpus_per_worker:g}")
    if args.executor == "local":
        ray_only = [
            flag
            for flag, used in (
                ("--workers", args.workers != 1),
                ("--gpus-per-worker", args.gpus_per_worker),
                ("--ray-address", args.ray_address is not None),
            )
            if used
        ]
        if ray_only:
            raise CliError(f"{', '.join(ray_only)} need --executor ray")
    return 1.0 if args.gpus_per_worker == 0 else 0.0  # a GPU worker mostly waits for its GPU


def _make_executor(args: argparse.Namespace) -> Any:
    """The executor of ``--executor`` (validated before any work)."""
    from swiftjax.pipeline.executors import LocalExecutor, RayExecutor

    cpus = _check_executor_args(args)
    if args.executor == "local":
        return LocalExecutor()
    return RayExecutor(
        args.workers, gpus_per_worker=args.gpus_per_worker, cpus_per_worker=cpus, address=args.ray_address
    )


def _run_batch(args: argparse.Namespace, jobs: list[Any]) -> int:
    """``jobs`` through :func:`swiftjax.pipeline.batch.run_batch`; exit 1 if a sequence failed."""
    from swiftjax.pipeline import batch

    cpus = _check_executor_args(args)
    config = _pipeline_config(args)
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


def _cmd_batch(args: argparse.Namespace) -> int:
    from swiftjax.pipeline import batch

    if args.list.is_dir():
        items = batch.sequence_folders(args.list)
    elif args.list.is_file():
        items = batch.read_list(args.list)
    else:
        raise CliError(f"batch list {args.list} does not exist (a text file of inputs or a folder of sequences)")
    args.input = "."  # _image_spec's input: replaced per sequence below
    spec = _image_spec(args)
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
    return _run_batch(args, jobs)


def _out_dir(text: str) -> pathlib.Path:
    """``--out``: a non-empty path (``--out ""`` would write into the current directory)."""
    if not text.strip():
        raise CliError("--out is empty: give the output directory")
    return pathlib.Path(text)


def _check_out_not_in_input(out: pathlib.Path, source: Any, folder: pathlib.Path | None = None) -> None:
    """Refuse an output directory inside the input folder (outputs would mix with, and on the
    next run be read as, frames); ``folder``: a followed folder (no frame in it yet)."""
    roots = {pathlib.Path(p).parent.resolve() for p in getattr(source, "paths", [])} | (
        {folder.resolve()} if folder is not None else set()
    )
    target = out.resolve()
    for root in roots:
        if target == root or target.is_relative_to(root):
            raise CliError(f"--out {out} is inside the input folder {root}: choose a directory outside the frames")


# ---------------------------------------------------------------------------- commands


def _print_summary(result: Any) -> None:
    from swiftjax.pipeline import summary_table

    print(summary_table(result))


def _empty_result(result: Any, config: Any) -> int:
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
    print(
        f"swiftjax: error: the run wrote 0 points (every pixel was dropped; {why}); the trajectory and the other "
        f"outputs are in {result.run_dir}",
        file=sys.stderr,
    )
    return 1


def _cmd_demo(args: argparse.Namespace) -> int:
    from swiftjax import pipeline
    from swiftjax.synthetic import demo

    out = args.out = _out_dir(args.out)
    if args.batch is not None:
        return _demo_batch(args)
    config = _pipeline_config(args)
    if args.frames is not None and args.frames < 1:
        raise CliError(f"--frames must be >= 1, got {args.frames}")
    try:
        h, w = (int(v) for v in args.image_size.lower().split("x"))
    except ValueError:
        raise CliError(f"--image-size must be HEIGHTxWIDTH, e.g. 154x518, got {args.image_size!r}") from None
    if not (14 <= h <= _DEMO_MAX_SIDE and 14 <= w <= _DEMO_MAX_SIDE):
        raise CliError(f"--image-size {args.image_size}: height and width must be from 14 to {_DEMO_MAX_SIDE} pixels")
    if not (args.frame_spacing > 0 and args.frame_spacing < 1e3):
        raise CliError(f"--frame-spacing must be in (0, 1000) metres, got {args.frame_spacing}")
    with contextlib.closing(_make_executor(args)) as executor, _LiveView(args) as live:
        run = demo.loop_route_run(args.frames, seed=args.seed, image_hw=(h, w), spacing_m=args.frame_spacing)
        result = pipeline.reconstruct(
            run.predictor,
            out,
            config,
            ground_truth=run.ground_truth,
            overwrite=args.overwrite,
            progress=not args.no_progress,
            executor=executor,
        )
        _print_summary(result)
        live.wait()
    return _empty_result(result, config)


#: Largest side of the synthetic camera (``demo --image-size``): 100000x100000 asked for
#: 30 GB per frame and hung on the failed allocation.
_DEMO_MAX_SIDE = 4096


def _demo_batch(args: argparse.Namespace) -> int:
    """``demo --batch K``: K synthetic routes (seeds ``seed .. seed + K - 1``) as a batch."""
    from swiftjax.pipeline import batch
    from swiftjax.synthetic import demo

    if args.batch < 1:
        raise CliError(f"--batch must be >= 1, got {args.batch}")
    if getattr(args, "view", False):
        raise CliError("--view shows one run: it does not combine with --batch")
    _check_executor_args(args)
    jobs = []
    for k in range(args.batch):
        run = demo.loop_route_run(args.frames, seed=args.seed + k)
        jobs.append(batch.Sequence(f"route_{args.seed + k:02d}", run.predictor.spec(), run.ground_truth))
    return _run_batch(args, jobs)


class _LiveView:
    """``--view``: a viewer of the run directory while it is written, kept open after the run."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.live = None
        if getattr(args, "view", False):
            viewer = _import_viewer()
            try:
                self.live = viewer.LiveViewer(
                    args.out, host=args.view_host, port=args.view_port, max_points=args.view_max_points
                )
            except viewer.ViewerError as err:
                raise CliError(str(err)) from None

    def __enter__(self) -> _LiveView:
        return self

    def wait(self) -> None:
        """Keep serving the finished run until Ctrl-C."""
        if self.live is None:
            return
        self.live.refresh_now()
        print("swiftjax: run finished; the viewer stays open (Ctrl-C to stop)")
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass

    def __exit__(self, *exc: Any) -> None:
        if self.live is not None:
            self.live.close()


def _import_viewer() -> Any:
    try:
        importlib.import_module("viser")
    except ImportError:
        raise CliError("the viewer needs viser: pip install 'swiftjax[view]'") from None
    from swiftjax import viewer

    return viewer


def _cmd_view(args: argparse.Namespace) -> int:
    viewer = _import_viewer()
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


def _cmd_prune(args: argparse.Namespace) -> int:
    from swiftjax.pipeline import rundir

    rundir.prune(args.run_dir)
    return 0


def _view_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("live viewer (the 'view' extra)")
    group.add_argument("--view", action="store_true", help="watch the run in a web viewer as chunks arrive")
    group.add_argument("--view-port", type=int, default=8080, help="port of the viewer")
    group.add_argument("--view-host", default="127.0.0.1", help="0.0.0.0 shares the viewer on the network")
    group.add_argument("--view-max-points", type=int, default=1_000_000, help="point budget of the viewer")


def _load_ground_truth(path: pathlib.Path, fmt: str) -> Any:
    from swiftjax.io import trajectory

    if not path.exists():
        raise CliError(f"ground-truth file {path} does not exist")
    return trajectory.read_kitti(path) if fmt == "kitti" else trajectory.read_tum(path)[1]


def _torch_device(text: str) -> Any:
    """``--device`` as a ``torch.device`` that exists here; :class:`CliError` otherwise."""
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError, TypeError):
        raise CliError(f"--device {text!r} is not a torch device (cpu, cuda, cuda:N, mps)") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch build has no CUDA" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise CliError(f"--device {text}: {why} (torch {torch.__version__}); use --device cpu")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise CliError(f"--device {text}: only {torch.cuda.device_count()} CUDA device(s) are visible")
    elif device.type == "mps":
        if not torch.backends.mps.is_available():
            raise CliError(f"--device {text}: this torch build or machine has no MPS support; use --device cpu")
    elif device.type != "cpu":
        raise CliError(f"--device {text}: device type {device.type!r} is not supported (cpu, cuda, mps)")
    return device


def _model_config(args: argparse.Namespace, backbone: Any = None) -> Any:
    """The architecture of ``--model-config`` for the backbone's family (``None``: its preset),
    as the JSON-able dict the runner is rebuilt from.  Without ``backbone``: a VGGTConfig."""
    from inference import VGGTConfig

    if backbone is None:
        config = _model_config(args, _backbone_named("vggt-1b"))
        return VGGTConfig(**config) if config else VGGTConfig()
    if args.model_config is None:
        return None
    try:
        return backbone.impl.load_config(backbone, args.model_config)
    except FileNotFoundError:
        raise CliError(f"--model-config {args.model_config} does not exist") from None
    except (OSError, ValueError, TypeError, KeyError) as err:  # JSONDecodeError is a ValueError
        raise CliError(
            f"--model-config {args.model_config} is not a {backbone.family.upper()} config (--model {backbone.name}): "
            f"{_one_line(err)}"
        ) from None


def _backbone_named(name: str) -> Any:
    from inference.backbones import get

    return get(name)


def _backbone(args: argparse.Namespace) -> Any:
    """The ``--model`` (flag or TOML ``model``) backbone."""
    return _backbone_named(_pipeline_config(args).model)


def _mode(args: argparse.Namespace, backbone: Any) -> str:
    """``--mode`` checked against the family's modes (default: its first, the official one)."""
    modes = backbone.impl.modes
    if args.mode is None:
        return modes[0]
    if args.mode not in modes:
        raise CliError(
            f"--mode {args.mode} is not a preprocessing of --model {backbone.name} (use {' or '.join(modes)})"
        )
    return args.mode


def _check_weights(args: argparse.Namespace) -> pathlib.Path:
    weights = pathlib.Path(args.weights)
    if not weights.exists():
        raise CliError(f"weights file {weights} does not exist")
    if not weights.is_file():
        raise CliError(f"weights file {weights} is not a file")
    return weights


def _check_runner_options(args: argparse.Namespace, check_device: bool = True) -> None:
    """Device, backend, dtype, mode and the weights file's header (family, shapes, complete)
    checked before any input is read or weights loaded (``check_device=False`` where the model
    runs on workers, whose devices are theirs)."""
    weights = _check_weights(args)
    backbone = _backbone(args)
    _mode(args, backbone)
    if args.backend == "onnx" and backbone.family != "vggt":
        raise CliError(f"--backend onnx runs VGGT graphs; --model {backbone.name} needs --backend torch")
    if args.backend == "onnx":
        if weights.suffix.lower() != ".onnx":
            raise CliError(f"--backend onnx needs an .onnx file (see 'swiftjax export-onnx'), got {weights}")
        if args.dtype != "float32":
            raise CliError(f"--dtype {args.dtype} needs --backend torch (an ONNX graph's precision is fixed at export)")
        if args.model_config is not None:
            raise CliError("--model-config needs --backend torch (an ONNX graph holds its own architecture)")
        if args.device != "cpu" and check_device:
            import onnxruntime as ort

            if not args.device.startswith("cuda"):
                raise CliError(f"--device {args.device}: the ONNX backend runs on cpu or cuda")
            if "CUDAExecutionProvider" not in ort.get_available_providers():
                raise CliError(
                    f"--device {args.device}: onnxruntime has no CUDA provider here "
                    f"(has {', '.join(ort.get_available_providers())}; install onnxruntime-gpu)"
                )
    else:
        if weights.suffix.lower() == ".onnx":
            raise CliError(f"{weights} is an ONNX graph: pass --backend onnx")
        if check_device:
            _torch_device(args.device)
        config = _model_config(args, backbone)
        try:
            backbone.impl.check_checkpoint(backbone, weights, config)
        except Exception as err:  # CheckpointError, without importing torch to name it
            if _is_user_error(err):
                raise CliError(_one_line(err)) from None
            raise


def _image_spec(args: argparse.Namespace, checked: bool = False) -> Any:
    """The :class:`~inference.predictor.ImageSpec` of the flags (``checked``: the runner options
    were checked already)."""
    from inference.predictor import ImageSpec

    if not checked:
        _check_runner_options(args, check_device=False)  # a worker checks its own device
    backbone = _backbone(args)
    model_config = None if args.backend == "onnx" else _model_config(args, backbone)
    return ImageSpec(  # absolute paths: a worker may run elsewhere
        input=os.path.abspath(args.input),
        weights=os.path.abspath(args.weights),
        backend=args.backend,
        device=args.device,
        dtype=args.dtype,
        model_config=model_config,
        mode=_mode(args, backbone),
        stride=args.stride,
        skip_bad=args.skip_bad,
        model=backbone.name,
    )


def _make_runner(args: argparse.Namespace, spec: Any) -> Any:
    """The runner of ``spec``, loaded now: a bad checkpoint or graph is a one-line error before any work."""
    from inference.predictor import build_runner

    try:
        return build_runner(spec.weights, spec.backend, spec.device, spec.dtype, spec.model_config, spec.model)
    except Exception as err:  # checkpoint, onnxruntime (InvalidProtobuf, Fail, ...) errors
        if _is_user_error(err):
            raise CliError(_one_line(err)) from None
        if args.backend == "onnx":
            raise CliError(f"cannot load the ONNX graph {args.weights}: {_one_line(err)}") from None
        raise


def _is_user_error(err: BaseException) -> bool:
    """A checkpoint error (without importing torch to name its class) or a value error."""
    checkpoint = sys.modules.get("inference.checkpoint")
    return isinstance(err, ValueError) or (
        checkpoint is not None and isinstance(err, getattr(checkpoint, "CheckpointError", ()))
    )


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
    if (args.follow or args.replay_fps is not None) and args.executor != "local":
        raise CliError("--follow and --replay-fps run with --executor local")


def _reconstruct_live(args: argparse.Namespace, rec: Any, frames: Any, times: Any, check_first: Any) -> Any:
    """Feed ``rec`` (:class:`~swiftjax.pipeline.engine.Reconstruction`) the ``frames`` of a
    :class:`~swiftjax.io.follow.FollowSource` (each its file) or a
    :class:`~swiftjax.io.follow.ReplaySource` (the predictor knows them); the first SIGINT
    stops the source and the run finishes as a complete run, a second one interrupts."""
    import signal

    def stop(signum: int, frame: Any) -> None:
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
    print(f"swiftjax: {rec.num_frames} frames arrived (ended by {frames.ended_by}); final pass")
    return rec.finish()


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from swiftjax import pipeline
    from swiftjax.io import images

    # Everything is checked before the first prediction: options, output, input, GT, runner.
    config = _pipeline_config(args)
    out = _out_dir(args.out)
    if args.stride < 1:
        raise CliError(f"--stride must be >= 1, got {args.stride}")
    _check_live_flags(args)
    if args.follow:  # frames join the source as they arrive (ImagePredictor.append)
        from swiftjax.io.follow import FollowSource

        live: Any = FollowSource(args.input, timeout_s=args.follow_timeout or 60.0)
        source = images.ImageFiles([], description=str(args.input))
        _check_out_not_in_input(out, source, pathlib.Path(args.input))
    else:
        source = images.validate(images.list_frames(args.input, stride=args.stride), skip_bad=args.skip_bad)
        _check_out_not_in_input(out, source)
    gt = _load_ground_truth(args.gt, args.gt_format) if args.gt is not None else None
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
    _check_runner_options(args, check_device=getattr(args, "executor", "local") == "local")
    from inference.predictor import ImagePredictor

    spec = _image_spec(args, checked=True)  # its model identity is part of the run directory's fingerprint
    backbone = _backbone_named(spec.model)

    def check_size(frame: Any = None) -> None:
        hw = source.image_hw if frame is None else frame.image.shape[:2]
        try:  # an image size the network cannot take
            backbone.impl.preprocess_geometry(*hw, spec.mode)
        except ValueError as err:
            raise CliError(f"--model {spec.model} cannot take the frames of {args.input}: {_one_line(err)}") from None

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
        print(f"swiftjax: {len(source)} frames, fewer than one chunk: running a single chunk")
    executor = _make_executor(args)
    with contextlib.closing(executor):
        if args.executor == "local":  # load the model now: a bad checkpoint fails before any work
            runner: Any = _make_runner(args, spec)
        else:  # each worker loads its own (ImageSpec)
            runner = spec.runner_factory()
        predictor = ImagePredictor(source, runner, mode=spec.mode, spec=spec)
        with contextlib.closing(predictor), _LiveView(args) as view:
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
            _print_summary(result)
            view.wait()
    return _empty_result(result, config)


def _read_trajectory(path: pathlib.Path, fmt: str) -> tuple[Any, Any]:
    """``(timestamps | None, poses [N, 4, 4])``; TUM quaternions must be non-zero, TUM rows
    are taken in time order (repeated times refused)."""
    import numpy as np

    from swiftjax.io import trajectory

    if path.is_dir():
        raise CliError(f"trajectory file {path} is a directory (give the {fmt.upper()} file, e.g. DIR/poses_{fmt}.txt)")
    if not path.exists():
        raise CliError(f"trajectory file {path} does not exist")
    if fmt == "kitti":
        return None, trajectory.read_kitti(path)
    stamps, rows = trajectory.read_tum_raw(path)
    order = trajectory.time_order(path, stamps)
    norms = np.linalg.norm(rows[:, 3:], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if bad.size:
        k = int(bad[0])
        raise _RotationError(
            f"{path}: pose {k} (of {len(rows)}, time {float(stamps[k])!r}) has a quaternion of norm {norms[k]:.6g}, "
            f"not a unit quaternion ({bad.size} such poses)",
            zero=bool(np.any(norms[bad] < 1e-6)),
        )
    if np.any(order != np.arange(len(order))):
        print(f"swiftjax: {path}: rows are not in time order; taken in time order")
    t, poses = trajectory.read_tum(path)
    return t[order], poses[order]


_ESTIMATE_HEADER = "swiftjax camera-to-world poses"  # swiftjax's poses_*.txt (pipeline/export.py)
_GROUND_TRUTH_HEADER = "the ground truth given to this run"  # its ground_truth_kitti.txt (pipeline/report.py)


def _check_evaluate_order(ref_path: pathlib.Path, est_path: pathlib.Path) -> str:
    """Refuse a swapped pair that the files' own headers reveal (evo's order is ``REF EST``;
    swapped, a Sim(3) alignment prints an error in the estimate's units, a plausible-looking
    wrong number); returns the reference's unit for the table (``m`` unless its header says
    otherwise)."""
    ref_head = " ".join(_header(ref_path))
    est_head = " ".join(_header(est_path))
    swap = "swiftjax evaluate REFERENCE ESTIMATE (the reference first, as evo_ape/evo_rpe)"
    if _ESTIMATE_HEADER in ref_head:
        raise CliError(f"{ref_path} is a swiftjax estimate (its header says so) but is given as the reference: {swap}")
    if _GROUND_TRUTH_HEADER in est_head:
        raise CliError(f"{est_path} is a ground truth (its header says so) but is given as the estimate: {swap}")
    for line in _header(ref_path):
        if line.startswith("unit:"):
            unit = line[5:].strip()
            return "m" if unit.startswith("metre") else unit
    return "m"


def _header(path: pathlib.Path) -> list[str]:
    from swiftjax.io import trajectory

    try:
        return trajectory.read_header(path)
    except OSError:
        return []  # the reader names the file below


class _RotationError(CliError):
    def __init__(self, text: str, zero: bool = False) -> None:
        super().__init__(text)
        self.zero = zero


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from swiftjax import evaluation
    from swiftjax.io import trajectory
    from swiftjax.io.tables import markdown_table

    est_path, ref_path = args.estimate, args.reference
    unit = _check_evaluate_order(ref_path, est_path)
    loaded = []
    fixes = []
    for path in (est_path, ref_path):
        try:
            stamps, poses = _read_trajectory(path, args.format)
        except _RotationError as err:
            if not args.fix_rotations or err.zero:
                hint = "" if err.zero else "; --fix-rotations normalises them"
                raise CliError(f"{err}{hint}") from None
            stamps, poses = trajectory.read_tum(path)  # normalised quaternions
            order = trajectory.time_order(path, stamps)
            stamps, poses = stamps[order], poses[order]
            fixes.append(f"{path}: quaternions normalised")
        try:
            evaluation.check_rotations(poses, str(path))
        except ValueError as err:
            if not args.fix_rotations:
                raise CliError(f"{err}; --fix-rotations re-orthonormalises them (nearest rotation)") from None
            poses, change = evaluation.orthonormalize(poses)
            fixes.append(f"{path}: rotations re-orthonormalised (largest entry change {change:.3g})")
        loaded.append((stamps, poses))
    (t_est, est), (t_ref, ref) = loaded
    for line in fixes:
        print(f"swiftjax: {line}")
    if args.format == "tum":
        i_ref, i_est = evaluation.associate(t_ref, t_est, max_diff=args.max_diff, offset=args.offset)
        if len(i_ref) < 3:
            raise CliError(
                f"only {len(i_ref)} of the {len(est)} poses of {est_path} match one of the {len(ref)} poses of "
                f"{ref_path} within --max-diff {args.max_diff} s (--offset {args.offset} s); 3 are needed"
            )
        print(
            f"associated {len(i_ref)} poses by timestamp ({est_path}: {len(est)}, {ref_path}: {len(ref)}; "
            f"max diff {args.max_diff} s, offset {args.offset} s)"
        )
        est, ref = est[i_est], ref[i_ref]
    elif len(est) != len(ref):
        raise CliError(f"{est_path} has {len(est)} poses but {ref_path} has {len(ref)} (KITTI files pair by row)")
    try:
        a = evaluation.ate(est, ref, align=args.align)
        r = evaluation.rpe(est, ref, delta=args.delta, align=args.align)
    except ValueError as err:
        raise CliError(f"evaluating {est_path} against {ref_path} ({len(est)} poses): {_one_line(err)}") from None
    rows = [
        [f"ATE translation ({unit})", a.rmse, a.mean, a.median, a.max],
        [f"RPE translation, delta {args.delta} ({unit})", *_stats(r.translation)],
        [f"RPE rotation, delta {args.delta} (deg)", *_stats(r.rotation_deg)],
    ]
    print(f"reference: {ref_path} (errors in its unit, {unit}); estimate: {est_path}")
    print(f"alignment: {args.align} (scale {a.scale:.6g}); {len(est)} poses")
    print(markdown_table(["metric", "rmse", "mean", "median", "max"], rows))
    return 0


def _stats(s: Any) -> list[float]:
    return [float(s.rmse), float(s.mean), float(s.median), float(s.max)]


def _cmd_export_onnx(args: argparse.Namespace) -> int:
    import torch

    from inference import VGGT, export_onnx, load_checkpoint
    from inference.checkpoint import CheckpointError

    weights = _check_weights(args)
    for name in ("frames", "height", "width"):
        if getattr(args, name) < 1:
            raise CliError(f"--{name} must be >= 1, got {getattr(args, name)}")
    config = _model_config(args)
    with torch.device("meta"):
        model = VGGT(config)
    try:
        load_checkpoint(model, weights)
    except CheckpointError as err:
        raise CliError(_one_line(err)) from None
    report = export_onnx(model, args.out, frames=args.frames, height=args.height, width=args.width)
    print(report.summary())
    return 0


# ------------------------------------------------------------------------------ parser


def _image_options(parser: argparse.ArgumentParser) -> None:
    """The model and the frames' preprocessing (reconstruct, batch)."""
    parser.add_argument(
        "--weights",
        required=True,
        help="weights of the --model network (VGGT: .pt/.pth/.safetensors, .onnx with --backend onnx; "
        "DA3: the official model.safetensors); required",
    )
    parser.add_argument(
        "--model-config",
        type=pathlib.Path,
        default=None,
        metavar="FILE",
        help="a custom size of the --model network's family as JSON (the golden tiny_config.json "
        "layout of that family; default: the preset of --model)",
    )
    parser.add_argument("--backend", choices=("torch", "onnx"), default="torch", help="inference engine")
    parser.add_argument("--device", default="cpu", help="torch device: cpu, cuda, cuda:N, mps")
    parser.add_argument(
        "--dtype",
        choices=("float32", "bfloat16", "float16"),
        default="float32",
        help="aggregator compute dtype (torch autocast; the heads stay float32)",
    )
    parser.add_argument(
        "--mode",
        choices=("crop", "pad", "resize"),
        default=None,
        help="preprocessing: VGGT crop (default) or pad; DA3 resize (default: longer side 504, sides "
        "to the nearest multiple of 14, the official upper_bound_resize) or crop",
    )
    parser.add_argument("--stride", type=int, default=1, help="use every k-th frame")
    parser.add_argument("--skip-bad", action="store_true", help="skip unreadable images with a warning")
    parser.add_argument("--gt-format", choices=("kitti", "tum"), default="kitti", help="ground-truth file format")


class _HelpFormatter(argparse.HelpFormatter):
    """Shows every option's default (method options write theirs into the help text)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text or not action.option_strings or action.default in (None, argparse.SUPPRESS):
            return text
        if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            return text
        return f"{text} (default: %(default)s)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="swiftjax",
        description="SwiftVGGT large-scale reconstruction (JAX geometry core).",
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)

    def add(name: str, **kw: Any) -> argparse.ArgumentParser:
        return sub.add_parser(name, formatter_class=_HelpFormatter, **kw)

    p = add("demo", help="synthetic loop route through the full pipeline (no weights needed)")
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
    _common_run_options(p)
    _view_options(p)
    _add_method_options(p)
    p.set_defaults(func=_cmd_demo)

    p = add("batch", help="many sequences, each its own resumable run, spread over the workers")
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
    _image_options(p)
    _common_run_options(p)
    _add_method_options(p)
    p.set_defaults(func=_cmd_batch)

    p = add("reconstruct", help="images (folder, glob or video) -> trajectory and point cloud")
    p.add_argument("input", help="image folder, glob pattern or video file")
    p.add_argument("--out", required=True, metavar="DIR", help="run directory (resumable); required")
    _image_options(p)
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
    _common_run_options(p)
    _view_options(p)
    _add_method_options(p)
    p.set_defaults(func=_cmd_reconstruct)

    p = add("view", help="web viewer (viser) of a run directory, finished or running")
    p.add_argument("run_dir", type=pathlib.Path, help="the --out folder of a run")
    p.add_argument("--port", type=int, default=8080, help="port to serve on")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (0.0.0.0 shares it on the network)")
    p.add_argument("--max-points", type=int, default=1_000_000, help="point budget (uniform sample)")
    p.set_defaults(func=_cmd_view)

    p = add(
        "prune",
        help="shrink a finished run directory: drop the chunk store's dense maps, keep every output",
        description="Drop the depth and confidence maps from the chunk files of a finished run (most of "
        "chunks/). Every output is kept; 'swiftjax view' and re-runs with other export or pose-graph "
        "options still predict nothing; a re-run that needs the maps (other loop or temporal "
        "options, changed frames) predicts those chunks again.",
    )
    p.add_argument("run_dir", type=pathlib.Path, help="the --out folder of a finished run")
    p.set_defaults(func=_cmd_prune)

    p = add("evaluate", help="ATE / RPE of an estimated trajectory against a reference (evo's order: REF EST)")
    p.add_argument(
        "reference",
        type=pathlib.Path,
        help="reference (ground-truth) poses, FIRST as in evo_ape/evo_rpe; the errors are in its unit",
    )
    p.add_argument("estimate", type=pathlib.Path, help="estimated camera-to-world poses (e.g. a run's poses_kitti.txt)")
    p.add_argument(
        "--format",
        choices=("kitti", "tum"),
        default="kitti",
        help="file format (KITTI pairs poses by row, TUM by timestamp)",
    )
    p.add_argument(
        "--align",
        choices=("sim3", "se3", "none"),
        default="sim3",
        help="alignment of the estimate before the errors (evo --align [--correct_scale])",
    )
    p.add_argument("--delta", type=int, default=1, help="RPE frame offset")
    p.add_argument(
        "--max-diff",
        type=float,
        default=0.01,
        metavar="SECONDS",
        help="TUM: largest time difference of associated poses (evo's --t_max_diff)",
    )
    p.add_argument(
        "--offset",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="TUM: time offset added to the estimate's timestamps (evo's --t_offset)",
    )
    p.add_argument(
        "--fix-rotations",
        action="store_true",
        help="re-orthonormalise rotations that are not (reported), instead of an error",
    )
    p.set_defaults(func=_cmd_evaluate)

    p = add("export-onnx", help="export VGGT to ONNX for onnxruntime")
    p.add_argument("--weights", required=True, help="VGGT weights (.pt/.pth/.safetensors); required")
    p.add_argument(
        "--model-config",
        type=pathlib.Path,
        default=None,
        metavar="FILE",
        help="VGGT architecture as JSON (default: VGGT-1B)",
    )
    p.add_argument("--out", type=pathlib.Path, required=True, metavar="FILE", help="the .onnx file; required")
    p.add_argument("--frames", type=int, default=75, help="frames of the example input (the frame axis stays dynamic)")
    p.add_argument("--height", type=int, default=154, help="image height the graph is exported for")
    p.add_argument("--width", type=int, default=518, help="image width the graph is exported for")
    p.set_defaults(func=_cmd_export_onnx)
    return parser


#: The plain integer flags' ranges (``dest: (low, high)``), checked before any work: a port
#: outside 1..65535 failed only when the viewer started (after the model load), 10**23 frames
#: or a negative seed deep inside NumPy.  Method options have theirs in their schema.
_INT_FLAGS = {
    "port": (1, 65535),
    "view_port": (1, 65535),
    "workers": (1, 4096),
    "stride": (1, 10**6),
    "frames": (1, 10**7),
    "seed": (0, 2**32 - 1),
    "batch": (1, 10**4),
    "delta": (1, 10**7),
    "max_points": (1, 10**9),
    "view_max_points": (1, 10**9),
    "height": (1, 16_384),
    "width": (1, 16_384),
}


def _check_int_flags(args: argparse.Namespace) -> None:
    for dest, (low, high) in _INT_FLAGS.items():
        value = getattr(args, dest, None)
        if value is None:
            continue
        flag = "--" + dest.replace("_", "-")
        if value < low:
            raise CliError(f"{flag} must be >= {low}, got {value}")
        if value > high:
            raise CliError(f"{flag} must be <= {high}, got {value}")


def main(argv: Sequence[str] | None = None) -> int:
    # NumPy's LAPACK (the whitening fit's eigh) is much slower multi-threaded on a small, busy
    # machine (docs/performance/pipeline.md); XLA does not use OpenBLAS.  Must be set before
    # numpy is imported.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser = build_parser()
    args = parser.parse_args(argv)
    _enable_compilation_cache()
    try:
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            _check_int_flags(args)
            code = args.func(args)
        if args.command in ("demo", "reconstruct", "batch"):
            print(f"done in {time.perf_counter() - t0:.1f} s")
        return code
    except KeyboardInterrupt:
        _quiesce()
        print("swiftjax: interrupted (finished chunks are kept; re-run to resume)", file=sys.stderr)
        return 130
    except Exception as err:
        if args.debug or not _prints_one_line(err):
            raise  # a bug: its traceback, exit status 1
        print(f"swiftjax: error: {_error_line(err)}", file=sys.stderr)
        return 2


#: Top-level packages of the optional extras (pyproject.toml): a missing one is a one-line error.
_EXTRA_PACKAGES = frozenset({"torch", "onnx", "onnxruntime", "cv2", "safetensors", "viser", "ray", "cvxopt"})


def _prints_one_line(err: BaseException) -> bool:
    """A user-facing error: a :class:`~swiftjax.errors.SwiftjaxError`, an ``OSError`` naming its
    file, running out of memory, or a missing optional extra.  Anything else is a bug."""
    if isinstance(err, (SwiftjaxError, MemoryError)):
        return True
    if isinstance(err, OSError):
        return err.filename is not None
    return isinstance(err, ModuleNotFoundError) and (err.name or "").split(".")[0] in _EXTRA_PACKAGES


def _error_line(err: BaseException) -> str:
    """The one line of a user-facing error, with what to do for memory and missing extras."""
    if isinstance(err, MemoryError):
        return f"out of memory ({_one_line(err)}); use smaller inputs, chunks or images"
    if isinstance(err, ImportError):
        return f"{_one_line(err)} (install the extra: pip install 'swiftjax[inference]')"
    return _one_line(err)


def _quiesce(timeout: float = 60.0) -> None:
    """After a Ctrl-C, before the interpreter finalises: wait for the computations JAX still
    runs on its own threads and join swiftjax's writer threads, so that none of them calls
    into a finalising interpreter ('Fatal Python error: PyThreadState_Get ... finalizing')."""
    import threading

    jax = sys.modules.get("jax")
    if jax is not None:
        with contextlib.suppress(Exception):
            jax.effects_barrier()
        with contextlib.suppress(Exception):
            for array in jax.live_arrays():
                array.block_until_ready()
    deadline = time.monotonic() + timeout
    for thread in threading.enumerate():
        if thread is not threading.current_thread() and not thread.daemon and thread.name.startswith("swiftjax-"):
            thread.join(max(0.0, deadline - time.monotonic()))


def _one_line(err: BaseException) -> str:
    text = str(err) or type(err).__name__
    if isinstance(err, OSError) and err.filename:
        text = f"{err.strerror or text}: {err.filename}"
    return " ".join(text.split())


if __name__ == "__main__":
    sys.exit(main())

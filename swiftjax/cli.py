"""The ``swiftjax`` command: ``demo``, ``reconstruct``, ``view``, ``evaluate``, ``export-onnx``.

Bad input ends with a one-line ``swiftjax: error: ...`` and exit status 2, never a
traceback (``--debug`` shows it).  JAX's persistent compilation cache is enabled
(``$SWIFTJAX_CACHE_DIR``, default ``~/.cache/swiftjax/jax``), so only the first run of a
given shape pays for XLA compilation.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import pathlib
import sys
import time
import tomllib
import warnings
from collections.abc import Sequence
from typing import Any

__all__ = ["main"]


class CliError(Exception):
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
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


def _add_method_options(parser: argparse.ArgumentParser) -> None:
    """One ``--option`` per :class:`PipelineConfig` field (default: the config file's, else the paper's)."""
    from swiftjax.pipeline import PipelineConfig

    group = parser.add_argument_group("method parameters (paper defaults)")
    for field in dataclasses.fields(PipelineConfig):
        flag = "--" + field.name.replace("_", "-")
        default = field.default
        note = field.metadata.get("help", "")
        note = f"{note} " if note else ""
        if isinstance(default, bool):
            group.add_argument(flag, dest=field.name, action=argparse.BooleanOptionalAction, default=None,
                               help=f"{note}(default {default})")
        else:
            kind = {int: int, float: float}.get(type(default), str)
            if field.name == "voxel_size":
                kind = float
            group.add_argument(flag, dest=field.name, type=kind, default=None, metavar=field.name.upper(),
                               help=f"{note}(default {default})")
    parser.add_argument("--config", type=pathlib.Path, help="TOML file of method parameters (options override it)")


def _pipeline_config(args: argparse.Namespace) -> Any:
    from swiftjax.pipeline import PipelineConfig

    values: dict[str, Any] = {}
    if args.config is not None:
        try:
            with open(args.config, "rb") as f:
                data = tomllib.load(f)
        except FileNotFoundError as err:
            raise CliError(f"config file {args.config} does not exist") from err
        except tomllib.TOMLDecodeError as err:
            raise CliError(f"config file {args.config} is not valid TOML: {err}") from err
        values.update(data.get("swiftjax", data))
    for field in dataclasses.fields(PipelineConfig):
        v = getattr(args, field.name, None)
        if v is not None:
            values[field.name] = None if (field.name == "robust_loops" and v == "none") else v
    try:
        return PipelineConfig.from_dict(values)
    except (TypeError, ValueError) as err:
        raise CliError(f"invalid configuration: {err}") from err


def _common_run_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--overwrite", action="store_true", help="replace a run directory of another input/config")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    group = parser.add_argument_group("execution (where the VGGT predictions run)")
    group.add_argument("--executor", choices=("local", "ray"), default="local",
                       help="local: this process, predicting the next chunk while the host aligns (default); "
                            "ray: a pool of Ray actors (pip install 'swiftjax[ray]')")
    group.add_argument("--workers", type=int, default=1, metavar="N", help="Ray actors, each with one model (default 1)")
    group.add_argument("--gpus-per-worker", type=float, default=0.0, metavar="G",
                       help="GPUs per Ray actor (default 0; 1 = one GPU each)")
    group.add_argument("--ray-address", default=None, metavar="ADDR",
                       help="join this Ray cluster (from 'ray start --head'); default: a local cluster on loopback")


def _check_executor_args(args: argparse.Namespace) -> float:
    """Validate the execution options; returns the CPUs per Ray worker."""
    if args.workers < 1:
        raise CliError(f"--workers must be >= 1, got {args.workers}")
    if args.gpus_per_worker < 0:
        raise CliError(f"--gpus-per-worker must be >= 0, got {args.gpus_per_worker:g}")
    if args.executor == "local":
        ray_only = [flag for flag, used in (("--workers", args.workers != 1), ("--gpus-per-worker", args.gpus_per_worker),
                                            ("--ray-address", args.ray_address is not None)) if used]
        if ray_only:
            raise CliError(f"{', '.join(ray_only)} need --executor ray")
    return 1.0 if args.gpus_per_worker == 0 else 0.0  # a GPU worker mostly waits for its GPU


def _make_executor(args: argparse.Namespace) -> Any:
    """The executor of ``--executor`` (validated before any work)."""
    from swiftjax.pipeline.executors import LocalExecutor, RayExecutor

    cpus = _check_executor_args(args)
    if args.executor == "local":
        return LocalExecutor()
    return RayExecutor(args.workers, gpus_per_worker=args.gpus_per_worker, cpus_per_worker=cpus,
                       address=args.ray_address)


def _run_batch(args: argparse.Namespace, jobs: list[Any]) -> int:
    """``jobs`` through :func:`swiftjax.pipeline.batch.run_batch`; exit 1 if a sequence failed."""
    from swiftjax.pipeline import batch

    cpus = _check_executor_args(args)
    config = _pipeline_config(args)
    rows = batch.run_batch(
        jobs, args.out, config, executor=args.executor, workers=args.workers, gpus_per_worker=args.gpus_per_worker,
        cpus_per_worker=cpus, ray_address=args.ray_address, overwrite=args.overwrite,
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
    jobs = [
        batch.Sequence(name, dataclasses.replace(spec, input=os.path.abspath(inp)),
                       os.path.abspath(gt) if gt else None, args.gt_format)
        for name, (inp, gt) in zip(names, items)
    ]
    return _run_batch(args, jobs)


# ---------------------------------------------------------------------------- commands


def _print_summary(result: Any) -> None:
    from swiftjax.pipeline import summary_table

    print(summary_table(result))


def _cmd_demo(args: argparse.Namespace) -> int:
    from swiftjax import demo, pipeline

    if args.batch is not None:
        return _demo_batch(args)
    config = _pipeline_config(args)
    with contextlib.closing(_make_executor(args)) as executor, _LiveView(args) as live:
        run = demo.loop_route_run(args.frames, seed=args.seed)
        result = pipeline.reconstruct(
            run.predictor, args.out, config, ground_truth=run.ground_truth, overwrite=args.overwrite,
            progress=not args.no_progress, executor=executor,
        )
        _print_summary(result)
        live.wait()
    return 0


def _demo_batch(args: argparse.Namespace) -> int:
    """``demo --batch K``: K synthetic routes (seeds ``seed .. seed + K - 1``) as a batch."""
    from swiftjax import demo
    from swiftjax.pipeline import batch

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
                self.live = viewer.LiveViewer(args.out, host=args.view_host, port=args.view_port,
                                              max_points=args.view_max_points)
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
        import viser  # noqa: F401
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


def _view_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("live viewer (the 'view' extra)")
    group.add_argument("--view", action="store_true", help="watch the run in a web viewer as chunks arrive")
    group.add_argument("--view-port", type=int, default=8080)
    group.add_argument("--view-host", default="127.0.0.1", help="0.0.0.0 shares the viewer on the network")
    group.add_argument("--view-max-points", type=int, default=1_000_000)


def _load_ground_truth(path: pathlib.Path, fmt: str) -> Any:
    from swiftjax.io import trajectory

    if not path.exists():
        raise CliError(f"ground-truth file {path} does not exist")
    return trajectory.read_kitti(path) if fmt == "kitti" else trajectory.read_tum(path)[1]


def _image_spec(args: argparse.Namespace) -> Any:
    from inference.predictor import ImageSpec

    weights = pathlib.Path(args.weights)
    if not weights.exists():
        raise CliError(f"weights file {weights} does not exist")
    if args.backend == "onnx" and weights.suffix != ".onnx":
        raise CliError(f"--backend onnx needs an .onnx file (see 'swiftjax export-onnx'), got {weights}")
    return ImageSpec(  # absolute paths: a worker may run elsewhere
        input=os.path.abspath(args.input), weights=os.path.abspath(weights), backend=args.backend, device=args.device, dtype=args.dtype,
        mode=args.mode, stride=args.stride, skip_bad=args.skip_bad,
    )


def _make_runner(args: argparse.Namespace) -> Any:
    from inference.predictor import build_runner

    spec = _image_spec(args)
    return build_runner(spec.weights, spec.backend, spec.device, spec.dtype)


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from swiftjax import pipeline
    from swiftjax.io import images

    config = _pipeline_config(args)
    source = images.validate(images.list_frames(args.input, stride=args.stride), skip_bad=args.skip_bad)
    gt = _load_ground_truth(args.gt, args.gt_format) if args.gt is not None else None
    if gt is not None and len(gt) != len(source):
        raise CliError(f"ground truth {args.gt} has {len(gt)} poses for {len(source)} frames")
    if args.timestamps is not None:
        timestamps = images.read_timestamps(args.timestamps, source, args.stride)
        note = f"from {args.timestamps}"
    else:
        timestamps, note = source.timestamps()
    if len(source) < config.chunk_size:
        print(f"swiftjax: {len(source)} frames, fewer than one chunk: running a single chunk")
    from inference.predictor import ImagePredictor

    spec = _image_spec(args)
    executor = _make_executor(args)
    with contextlib.closing(executor):
        if args.executor == "local":  # load the model now: a bad checkpoint fails before any work
            runner: Any = _make_runner(args)
        else:  # each worker loads its own (ImageSpec)
            runner = spec.runner_factory()
        predictor = ImagePredictor(source, runner, mode=args.mode, spec=spec)
        with _LiveView(args) as live:
            result = pipeline.reconstruct(
                predictor, args.out, config, ground_truth=gt, overwrite=args.overwrite, progress=not args.no_progress,
                timestamps=timestamps, timestamps_note=note, executor=executor,
            )
            _print_summary(result)
            live.wait()
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from swiftjax import evaluation
    from swiftjax.report import markdown_table

    est = _load_ground_truth(args.estimate, args.format)
    ref = _load_ground_truth(args.reference, args.format)
    if len(est) != len(ref):
        raise CliError(f"{args.estimate} has {len(est)} poses but {args.reference} has {len(ref)}")
    a = evaluation.ate(est, ref, align=args.align)
    r = evaluation.rpe(est, ref, delta=args.delta, align=args.align)
    rows = [
        ["ATE translation (m)", a.rmse, a.mean, a.median, a.max],
        [f"RPE translation, delta {args.delta} (m)", *_stats(r.translation)],
        [f"RPE rotation, delta {args.delta} (deg)", *_stats(r.rotation_deg)],
    ]
    print(f"alignment: {args.align} (scale {a.scale:.6g}); {len(est)} poses")
    print(markdown_table(["metric", "rmse", "mean", "median", "max"], rows))
    return 0


def _stats(s: Any) -> list[float]:
    return [float(s.rmse), float(s.mean), float(s.median), float(s.max)]


def _cmd_export_onnx(args: argparse.Namespace) -> int:
    import torch

    from inference import VGGT, VGGTConfig, export_onnx, load_checkpoint

    weights = pathlib.Path(args.weights)
    if not weights.exists():
        raise CliError(f"weights file {weights} does not exist")
    with torch.device("meta"):
        model = VGGT(VGGTConfig())
    load_checkpoint(model, weights)
    report = export_onnx(model, args.out, frames=args.frames, height=args.height, width=args.width)
    print(report.summary())
    return 0


# ------------------------------------------------------------------------------ parser


def _image_options(parser: argparse.ArgumentParser) -> None:
    """The model and the frames' preprocessing (reconstruct, batch)."""
    parser.add_argument("--weights", required=True,
                        help="VGGT-1B weights (.pt/.pth/.safetensors; .onnx with --backend onnx)")
    parser.add_argument("--backend", choices=("torch", "onnx"), default="torch")
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cuda:0 (default cpu)")
    parser.add_argument("--dtype", choices=("float32", "bfloat16", "float16"), default="float32")
    parser.add_argument("--mode", choices=("crop", "pad"), default="crop", help="VGGT preprocessing mode")
    parser.add_argument("--stride", type=int, default=1, help="use every k-th frame")
    parser.add_argument("--skip-bad", action="store_true", help="skip unreadable images with a warning")
    parser.add_argument("--gt-format", choices=("kitti", "tum"), default="kitti", help="ground-truth file format")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="swiftjax", description="SwiftVGGT large-scale reconstruction (JAX geometry core)."
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="synthetic loop route through the full pipeline (no weights needed)")
    p.add_argument("--frames", type=int, default=None, help="frames of the route (default: all, ~620)")
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/demo"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch", type=int, default=None, metavar="K",
                   help="K routes (seeds SEED..SEED+K-1) as a batch of runs in OUT/route_NN (see 'swiftjax batch')")
    _common_run_options(p)
    _view_options(p)
    _add_method_options(p)
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("batch", help="many sequences, each its own resumable run, spread over the workers")
    p.add_argument("list", type=pathlib.Path,
                   help="text file with one 'INPUT [GROUND_TRUTH]' per line, or a folder of sequence folders "
                        "(frames in it or in its images/, ground truth in gt.txt, groundtruth.txt or poses.txt)")
    p.add_argument("--out", type=pathlib.Path, required=True, help="one run directory per sequence, and batch.json")
    _image_options(p)
    _common_run_options(p)
    _add_method_options(p)
    p.set_defaults(func=_cmd_batch)

    p = sub.add_parser("reconstruct", help="images (folder, glob or video) -> trajectory and point cloud")
    p.add_argument("input", help="image folder, glob pattern or video file")
    p.add_argument("--out", type=pathlib.Path, required=True)
    _image_options(p)
    p.add_argument("--gt", type=pathlib.Path, help="ground-truth poses for ATE")
    p.add_argument("--timestamps", type=pathlib.Path,
                   help="per-frame times for poses_tum.txt: 'time name' lines (TUM rgb.txt) or one time per image "
                        "(default: a video's own times, else the frame index)")
    _common_run_options(p)
    _view_options(p)
    _add_method_options(p)
    p.set_defaults(func=_cmd_reconstruct)

    p = sub.add_parser("view", help="web viewer (viser) of a run directory, finished or running")
    p.add_argument("run_dir", type=pathlib.Path, help="the --out folder of a run")
    p.add_argument("--port", type=int, default=8080)
    p.add_argument("--host", default="127.0.0.1", help="address to bind (0.0.0.0 shares it on the network)")
    p.add_argument("--max-points", type=int, default=1_000_000, help="point budget (uniform sample)")
    p.set_defaults(func=_cmd_view)

    p = sub.add_parser("evaluate", help="ATE / RPE of an estimated trajectory against a reference")
    p.add_argument("estimate", type=pathlib.Path)
    p.add_argument("reference", type=pathlib.Path)
    p.add_argument("--format", choices=("kitti", "tum"), default="kitti")
    p.add_argument("--align", choices=("sim3", "se3", "none"), default="sim3")
    p.add_argument("--delta", type=int, default=1, help="RPE frame offset")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("export-onnx", help="export VGGT-1B to ONNX for onnxruntime")
    p.add_argument("--weights", required=True)
    p.add_argument("--out", type=pathlib.Path, required=True)
    p.add_argument("--frames", type=int, default=75)
    p.add_argument("--height", type=int, default=154)
    p.add_argument("--width", type=int, default=518)
    p.set_defaults(func=_cmd_export_onnx)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    # NumPy's LAPACK (the whitening fit's eigh) measured ~10x slower multi-threaded on a busy
    # 2-core machine; XLA does not use OpenBLAS.  Must be set before numpy is imported.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser = build_parser()
    args = parser.parse_args(argv)
    _enable_compilation_cache()
    from swiftjax.io.images import InputError
    from swiftjax.io.trajectory import TrajectoryFormatError
    from swiftjax.pipeline import RunDirError

    from swiftjax.pipeline.batch import BatchError
    from swiftjax.pipeline.executors import ExecutorError

    user_errors = (CliError, InputError, RunDirError, TrajectoryFormatError, ExecutorError, BatchError, ValueError,
                   OSError)
    try:
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            code = args.func(args)
        if args.command in ("demo", "reconstruct", "batch"):
            print(f"done in {time.perf_counter() - t0:.1f} s")
        return code
    except KeyboardInterrupt:
        print("swiftjax: interrupted (finished chunks are kept; re-run to resume)", file=sys.stderr)
        return 130
    except user_errors as err:
        if args.debug:
            raise
        print(f"swiftjax: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except ImportError as err:
        if args.debug:
            raise
        print(f"swiftjax: error: {_one_line(err)} (install the extra: pip install 'swiftjax[inference]')",
              file=sys.stderr)
        return 2


def _one_line(err: BaseException) -> str:
    text = str(err) or type(err).__name__
    if isinstance(err, OSError) and err.filename:
        text = f"{err.strerror or text}: {err.filename}"
    return " ".join(text.split())


if __name__ == "__main__":
    sys.exit(main())

"""The option groups shared by the commands, their reading and checks before any work, and
:class:`CliError`.

Method options (:class:`~swiftjax.pipeline.PipelineConfig`, from their schema), ``--config``
files, run and execution options, the live viewer, the model and its frames; the plain integer
flags' ranges.  Every check raises :class:`CliError` before work starts.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import pathlib
import sys
from typing import Any

import tomllib

from swiftjax.errors import SwiftjaxError

__all__ = [
    "CliError",
    "INT_FLAGS",
    "HelpFormatter",
    "add_image_options",
    "add_method_options",
    "add_run_options",
    "add_view_options",
    "check_executor_args",
    "check_int_flags",
    "is_user_error",
    "make_executor",
    "one_line",
    "out_dir",
    "pipeline_config",
    "read_config_table",
]

logger = logging.getLogger(__name__)


class CliError(SwiftjaxError):
    """A user-facing error: printed as one line, exit status 2."""


def one_line(err: BaseException) -> str:
    """The error's message on one line (an ``OSError``: its reason and its file name)."""
    text = str(err) or type(err).__name__
    if isinstance(err, OSError) and err.filename:
        text = f"{err.strerror or text}: {err.filename}"
    return " ".join(text.split())


def is_user_error(err: BaseException) -> bool:
    """A checkpoint error (without importing torch to name its class) or a value error."""
    checkpoint = sys.modules.get("inference.checkpoint")
    return isinstance(err, ValueError) or (
        checkpoint is not None and isinstance(err, getattr(checkpoint, "CheckpointError", ()))
    )


class HelpFormatter(argparse.HelpFormatter):
    """Shows every option's default (method options write theirs into the help text)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text or not action.option_strings or action.default in (None, argparse.SUPPRESS):
            return text
        if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            return text
        return f"{text} (default: %(default)s)"


# ------------------------------------------------------------------ method options


def add_method_options(parser: argparse.ArgumentParser) -> None:
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


def pipeline_config(args: argparse.Namespace) -> Any:
    """The configuration from ``--config`` and the flags, validated by the schema before any work."""
    from swiftjax import options
    from swiftjax.pipeline import PipelineConfig

    values: dict[str, Any] = {}
    if args.config is not None:
        values.update(read_config_table(args.config))
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
        logger.info(f"swiftjax: --chunk-size {config.chunk_size}: defaults scaled to fit it: {', '.join(scaled)}")
    return config


def read_config_table(path: pathlib.Path) -> dict[str, Any]:
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


# ------------------------------------------------------------ run and execution


def add_run_options(parser: argparse.ArgumentParser) -> None:
    """``--overwrite``, ``--no-progress`` and where the predictions run (demo, batch, reconstruct)."""
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


def check_executor_args(args: argparse.Namespace) -> float:
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


def make_executor(args: argparse.Namespace) -> Any:
    """The executor of ``--executor`` (validated before any work)."""
    from swiftjax.pipeline.executors import LocalExecutor, RayExecutor

    cpus = check_executor_args(args)
    if args.executor == "local":
        # On a GPU, three predictions ahead: the model keeps running through the geometry's
        # slower chunks (its first compiles, the export); measured on an H200, warm, 600 frames:
        # end to end 0.62 -> 0.72 of the predict-only rate (bench/results/gpu-20261204T181340Z.json).
        # Elsewhere one: the model is the slow stage and each prediction held costs memory.
        gpu = str(getattr(args, "device", "cpu")).startswith("cuda")
        return LocalExecutor(prefetch=3 if gpu else 1)
    return RayExecutor(
        args.workers, gpus_per_worker=args.gpus_per_worker, cpus_per_worker=cpus, address=args.ray_address
    )


def out_dir(text: str) -> pathlib.Path:
    """``--out``: a non-empty path (``--out ""`` would write into the current directory)."""
    if not text.strip():
        raise CliError("--out is empty: give the output directory")
    return pathlib.Path(text)


def add_view_options(parser: argparse.ArgumentParser) -> None:
    """``--view`` and its server's options (demo, reconstruct)."""
    group = parser.add_argument_group("live viewer (the 'view' extra)")
    group.add_argument("--view", action="store_true", help="watch the run in a web viewer as chunks arrive")
    group.add_argument("--view-port", type=int, default=8080, help="port of the viewer")
    group.add_argument("--view-host", default="127.0.0.1", help="0.0.0.0 shares the viewer on the network")
    group.add_argument("--view-max-points", type=int, default=1_000_000, help="point budget of the viewer")


def add_image_options(parser: argparse.ArgumentParser) -> None:
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


# ------------------------------------------------------------------ integer flags

#: The plain integer flags' ranges (``dest: (low, high)``), checked before any work: a port
#: outside 1..65535 failed only when the viewer started (after the model load), 10**23 frames
#: or a negative seed deep inside NumPy.  Method options have theirs in their schema.
INT_FLAGS = {
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


def check_int_flags(args: argparse.Namespace) -> None:
    """Every flag of :data:`INT_FLAGS` that the command has, within its range."""
    for dest, (low, high) in INT_FLAGS.items():
        value = getattr(args, dest, None)
        if value is None:
            continue
        flag = "--" + dest.replace("_", "-")
        if value < low:
            raise CliError(f"{flag} must be >= {low}, got {value}")
        if value > high:
            raise CliError(f"{flag} must be <= {high}, got {value}")

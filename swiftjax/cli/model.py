"""The network of a run: ``--model``, ``--weights``, ``--model-config``, ``--backend``,
``--device``, ``--dtype`` and ``--mode`` checked before any input is read, and the runner loaded.

Nothing here imports torch at import time; the device itself is probed by
:func:`inference.device.check_device`.
"""

from __future__ import annotations

import argparse
import os
import pathlib
from typing import Any

from swiftjax.cli.arguments import CliError, is_user_error, one_line, pipeline_config

__all__ = [
    "backbone",
    "backbone_named",
    "check_runner_options",
    "check_weights",
    "image_spec",
    "make_runner",
    "mode",
    "model_config",
]


def model_config(args: argparse.Namespace, backbone: Any = None) -> Any:
    """The architecture of ``--model-config`` for the backbone's family (``None``: its preset),
    as the JSON-able dict the runner is rebuilt from.  Without ``backbone``: a VGGTConfig."""
    from inference import VGGTConfig

    if backbone is None:
        config = model_config(args, backbone_named("vggt-1b"))
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
            f"{one_line(err)}"
        ) from None


def backbone_named(name: str) -> Any:
    """The registry entry of ``--model name`` (:mod:`inference.backbones`)."""
    from inference.backbones import get

    return get(name)


def backbone(args: argparse.Namespace) -> Any:
    """The ``--model`` (flag or TOML ``model``) backbone."""
    return backbone_named(pipeline_config(args).model)


def mode(args: argparse.Namespace, backbone: Any) -> str:
    """``--mode`` checked against the family's modes (default: its first, the official one)."""
    modes = backbone.impl.modes
    if args.mode is None:
        return modes[0]
    if args.mode not in modes:
        raise CliError(
            f"--mode {args.mode} is not a preprocessing of --model {backbone.name} (use {' or '.join(modes)})"
        )
    return args.mode


def check_weights(args: argparse.Namespace) -> pathlib.Path:
    """``--weights``: an existing file."""
    weights = pathlib.Path(args.weights)
    if not weights.exists():
        raise CliError(f"weights file {weights} does not exist")
    if not weights.is_file():
        raise CliError(f"weights file {weights} is not a file")
    return weights


def check_runner_options(args: argparse.Namespace, check_device: bool = True) -> None:
    """Device, backend, dtype, mode and the weights file's header (family, shapes, complete)
    checked before any input is read or weights loaded (``check_device=False`` where the model
    runs on workers, whose devices are theirs)."""
    weights = check_weights(args)
    net = backbone(args)
    mode(args, net)
    if args.backend == "onnx" and net.family != "vggt":
        raise CliError(f"--backend onnx runs VGGT graphs; --model {net.name} needs --backend torch")
    if args.backend == "onnx":
        if weights.suffix.lower() != ".onnx":
            raise CliError(f"--backend onnx needs an .onnx file (see 'swiftjax export-onnx'), got {weights}")
        if args.dtype != "float32":
            raise CliError(f"--dtype {args.dtype} needs --backend torch (an ONNX graph's precision is fixed at export)")
        if args.model_config is not None:
            raise CliError("--model-config needs --backend torch (an ONNX graph holds its own architecture)")
        if check_device:
            _check_device(args.device, "onnx")
    else:
        if weights.suffix.lower() == ".onnx":
            raise CliError(f"{weights} is an ONNX graph: pass --backend onnx")
        if check_device:
            _check_device(args.device, "torch")
        config = model_config(args, net)
        try:
            net.impl.check_checkpoint(net, weights, config)
        except Exception as err:  # CheckpointError, without importing torch to name it
            if is_user_error(err):
                raise CliError(one_line(err)) from None
            raise


def _check_device(text: str, backend: str) -> None:
    from inference.device import DeviceError, check_device

    try:
        check_device(text, backend, name="--device")
    except DeviceError as err:
        raise CliError(str(err)) from None


def image_spec(args: argparse.Namespace, checked: bool = False) -> Any:
    """The :class:`~inference.predictor.ImageSpec` of the flags (``checked``: the runner options
    were checked already)."""
    from inference.predictor import ImageSpec

    if not checked:
        check_runner_options(args, check_device=False)  # a worker checks its own device
    net = backbone(args)
    config = None if args.backend == "onnx" else model_config(args, net)
    return ImageSpec(  # absolute paths: a worker may run elsewhere
        input=os.path.abspath(args.input),
        weights=os.path.abspath(args.weights),
        backend=args.backend,
        device=args.device,
        dtype=args.dtype,
        model_config=config,
        mode=mode(args, net),
        stride=args.stride,
        skip_bad=args.skip_bad,
        model=net.name,
    )


def make_runner(args: argparse.Namespace, spec: Any) -> Any:
    """The runner of ``spec``, loaded now: a bad checkpoint or graph is a one-line error before any work."""
    from inference.predictor import build_runner

    try:
        return build_runner(spec.weights, spec.backend, spec.device, spec.dtype, spec.model_config, spec.model)
    except Exception as err:  # checkpoint, onnxruntime (InvalidProtobuf, Fail, ...) errors
        if is_user_error(err):
            raise CliError(one_line(err)) from None
        if args.backend == "onnx":
            raise CliError(f"cannot load the ONNX graph {args.weights}: {one_line(err)}") from None
        raise

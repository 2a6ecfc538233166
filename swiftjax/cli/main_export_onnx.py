"""``swiftjax export-onnx``: VGGT as an ONNX graph for onnxruntime."""

from __future__ import annotations

import argparse
import pathlib
from typing import Any

from swiftjax.cli import model
from swiftjax.cli.arguments import CliError, one_line

__all__ = ["add_parser", "run"]


def add_parser(sub: Any, **kw: Any) -> argparse.ArgumentParser:
    """The ``export-onnx`` subparser (``kw``: the parser's formatter)."""
    p: argparse.ArgumentParser = sub.add_parser("export-onnx", help="export VGGT to ONNX for onnxruntime", **kw)
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
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Export; exit status 0."""
    import torch

    from inference import VGGT, export_onnx, load_checkpoint
    from inference.checkpoint import CheckpointError

    weights = model.check_weights(args)
    for name in ("frames", "height", "width"):
        if getattr(args, name) < 1:
            raise CliError(f"--{name} must be >= 1, got {getattr(args, name)}")
    config = model.model_config(args)
    with torch.device("meta"):
        net = VGGT(config)
    try:
        load_checkpoint(net, weights)
    except CheckpointError as err:
        raise CliError(one_line(err)) from None
    report = export_onnx(net, args.out, frames=args.frames, height=args.height, width=args.width)
    print(report.summary())
    return 0

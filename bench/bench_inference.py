"""VGGT inference on CPU: torch eager vs onnxruntime, frames/second and peak memory.

Two configurations with seeded random weights: ``tiny`` (the golden test config, width 64)
and ``mid`` (a ViT-S-sized VGGT, width 384, 12+12 aggregator blocks, 12 DINO blocks), on
KITTI-shaped frames (518 x 154 by default).  Each (config, backend) runs in its own child
process so that its peak resident memory (``ru_maxrss``) is its own; the ONNX graph is exported
by the parent first.  Reported: best-of-N seconds per chunk, frames/second, peak RSS and the
peak increase during inference over the RSS after loading, and onnxruntime/torch ratios.

    python bench/bench_inference.py [--configs tiny mid] [--frames 8] [--height 154]
                                    [--width 518] [--repeat 3] [--threads 2]

``--presets [MODEL ...]``: instead, the full-size ``--model`` backbones with random weights
(speed does not depend on the values) on one chunk of KITTI-shaped frames (DA3 504 x 154, VGGT
518 x 154; ``--frames``, default 8 here, 75 = one KITTI chunk).  Each (preset, backend, dtype)
runs in its own child: built on ``meta``, materialised on the CPU, filled with small random
values; ``runner.predict`` (normalisation, forward, conversion to ChunkPrediction) is timed once
after a 3-frame warm-up.  Parameters are checked against ``shared/golden/da3/manifest_*.json``.
``--max-frames PRESET=N`` caps a slow preset (global attention is quadratic in the frames, so
fewer frames understate a full chunk's time; the table says how many were measured).
onnxruntime (``--onnx-presets``) where the graph fits protobuf's 2 GB.

    python bench/bench_inference.py --presets da3-small da3-base --frames 75 --dtypes float32
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common import markdown_table, write_results

CONFIGS: dict[str, dict[str, object]] = {
    "tiny": dict(
        embed_dim=64,
        depth=6,
        num_heads=4,
        dino_depth=2,
        dino_num_heads=4,
        camera_trunk_depth=4,
        camera_num_heads=4,
        dpt_features=32,
        dpt_out_channels=(16, 32, 64, 64),
        dpt_intermediate_layer_idx=(1, 3, 4, 5),
    ),
    "mid": dict(
        embed_dim=384,
        depth=12,
        num_heads=6,
        dino_depth=12,
        dino_num_heads=6,
        camera_trunk_depth=2,
        camera_num_heads=6,
        dpt_features=128,
        dpt_out_channels=(48, 96, 192, 384),
        dpt_intermediate_layer_idx=(2, 5, 8, 11),
    ),
}


def _status_mb(field: str) -> float:
    """``VmRSS`` / ``VmHWM`` (peak RSS) of this process from /proc, in MiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _reset_peak() -> None:
    """Resets VmHWM to the current RSS (Linux >= 4.0), so the peak that follows is inference's own."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def _build(config: str):  # type: ignore[no-untyped-def]
    import torch

    from inference.config import VGGTConfig
    from inference.model import VGGT

    torch.manual_seed(0)
    return VGGT(VGGTConfig(**CONFIGS[config])).eval()  # type: ignore[arg-type]


def child(args: argparse.Namespace) -> None:
    """Runs one (config, backend) and prints one JSON line."""
    import numpy as np
    import torch

    torch.set_num_threads(args.threads)
    x = np.random.default_rng(0).random((args.frames, 3, args.height, args.width), dtype=np.float32)
    if args.backend == "torch":
        from inference.runners import TorchRunner

        runner = TorchRunner(_build(args.config), "cpu")
        n_params = sum(p.numel() for p in runner.model.parameters())
    else:
        from inference.runners import OnnxRunner

        runner = OnnxRunner(args.onnx, intra_op_threads=args.threads)  # type: ignore[assignment]
        n_params = 0
    loaded = _status_mb("VmRSS")
    _reset_peak()
    with np.errstate(all="ignore"):  # random weights may give FoV 0 -> infinite focal length
        runner.predict(x)  # warm-up (allocator, ORT arena)
        best = float("inf")
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            runner.predict(x)
            best = min(best, time.perf_counter() - t0)
    peak = _status_mb("VmHWM")
    print(
        json.dumps(
            dict(
                seconds=best,
                rss_loaded_mb=loaded,
                peak_mb=peak,
                peak_increase_mb=max(peak - loaded, 0.0),
                params=n_params,
            )
        )
    )


def _run_child(args: argparse.Namespace, config: str, backend: str, onnx: str) -> dict[str, float]:
    cmd = [
        sys.executable,
        __file__,
        "--child",
        "--config",
        config,
        "--backend",
        backend,
        "--onnx",
        onnx,
        "--frames",
        str(args.frames),
        "--height",
        str(args.height),
        "--width",
        str(args.width),
        "--repeat",
        str(args.repeat),
        "--threads",
        str(args.threads),
    ]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=REPO)
    return json.loads(out.stdout.strip().splitlines()[-1])


@dataclasses.dataclass
class Row:
    config: str
    params_m: float
    torch_fps: float
    ort_fps: float
    torch_peak_mb: float
    ort_peak_mb: float
    torch_inc_mb: float
    ort_inc_mb: float
    export_s: float
    max_err: dict[str, float]


KITTI_HW = {"vggt": (154, 518), "da3": (154, 504), "pi3": (154, 504)}
MANIFEST = {
    "da3-small": "da3-small",
    "da3-base": "da3-base",
    "da3-large": "da3-large",
    "da3-giant": "da3-giant",
    "da3-nested-giant-large": "da3nested-giant-large",
}


def random_model(name: str, device: str = "cpu"):  # type: ignore[no-untyped-def]
    """The preset's network on ``device`` with small random weights (no checkpoint needed)."""
    import torch

    from inference.backbones import get

    b = get(name)
    if b.family == "vggt":
        from inference import VGGT, VGGTConfig

        with torch.device("meta"):
            model = VGGT(VGGTConfig())
    elif b.family == "pi3":
        from inference.backbones.pi3 import _model, load_config

        model = _model(load_config(b, None))
    else:
        from inference.da3 import build_da3

        model = build_da3(b.preset, device="meta")
    model = model.to_empty(device=device)
    gen = torch.Generator(device=device).manual_seed(0)
    with torch.no_grad():
        for pname, p in model.named_parameters():
            if pname.endswith("bias"):
                p.zero_()
            elif p.ndim == 1:  # norm weights, LayerScale
                p.fill_(1.0 if "norm" in pname else 0.1)
            else:
                p.normal_(0.0, 0.02, generator=gen)
        for pname, p in model.named_parameters():  # nested: no sky, so the metric alignment has pixels
            if "sky_output_conv2" in pname and pname.endswith("bias"):
                p.fill_(-10.0)
        # to_empty leaves buffers as uninitialised memory (π³'s input normalisation turned every
        # output into NaN): each gets its real value or the build stops here.
        from inference.preprocess import IMAGENET_MEAN, IMAGENET_STD

        values = {"image_mean": IMAGENET_MEAN, "image_std": IMAGENET_STD}
        for bname, buf in model.named_buffers():
            leaf = bname.rsplit(".", 1)[-1]
            if leaf not in values:
                raise RuntimeError(f"{name}: buffer {bname} has no value in a random model")
            buf.copy_(torch.tensor(values[leaf], dtype=buf.dtype).reshape(buf.shape))
    return b, model.eval()


def preset_child(args: argparse.Namespace) -> None:
    """Runs one (preset, backend, dtype) and prints one JSON line."""
    import numpy as np
    import torch

    torch.set_num_threads(args.threads)
    b, model = random_model(args.preset)
    params = sum(p.numel() for p in model.parameters())
    h, w = KITTI_HW[b.family]
    x = np.random.default_rng(0).random((args.frames, 3, h, w), dtype=np.float32)
    dtype = {"float32": torch.float32, "bfloat16": torch.bfloat16}[args.dtype]
    if args.backend == "onnxruntime":
        from inference.backbones.da3 import DA3Runner

        runner = DA3Runner(model)
        from inference.da3.onnx import DA3OnnxRunner, export_da3_onnx

        with tempfile.TemporaryDirectory() as tmp:
            path = export_da3_onnx(model, Path(tmp) / "g.onnx", frames=3, height=h, width=w)
            runner.model = _OrtModel(DA3OnnxRunner(path, threads=args.threads))
            del model
            _time(runner, x, args, params)
        return
    if b.family == "vggt":
        from inference.runners import TorchRunner

        runner = TorchRunner(model, "cpu", dtype=dtype)
    elif b.family == "pi3":
        from inference.pi3.runner import Pi3TorchRunner

        runner = Pi3TorchRunner(model, "cpu", dtype=dtype)
    else:
        from inference.backbones.da3 import DA3Runner

        runner = DA3Runner(model, "cpu", dtype=dtype)
    _time(runner, x, args, params)


class _OrtModel:
    """An onnxruntime graph behind :class:`DA3Runner`'s ``model(x, ref_view_strategy=...)`` call."""

    def __init__(self, ort_runner):  # type: ignore[no-untyped-def]
        self.ort = ort_runner

    def __call__(self, x, ref_view_strategy="saddle_balanced"):  # type: ignore[no-untyped-def]
        return self.ort.run(x.numpy())

    def to(self, *a, **k):  # type: ignore[no-untyped-def]
        return self

    def eval(self):  # type: ignore[no-untyped-def]
        return self


def _time(runner, x, args, params) -> None:  # type: ignore[no-untyped-def]
    import numpy as np

    loaded = _status_mb("VmRSS")
    with np.errstate(all="ignore"):
        runner.predict(x[:3])  # warm-up
        _reset_peak()
        t0 = time.perf_counter()
        runner.predict(x)
        seconds = time.perf_counter() - t0
    peak = _status_mb("VmHWM")
    print(json.dumps(dict(seconds=seconds, params=params, rss_loaded_mb=loaded, peak_mb=peak)))


def presets_main(args: argparse.Namespace) -> None:
    """The full-size presets' table (``--presets``; module docstring)."""
    caps = {k: int(v) for k, v in (item.split("=") for item in args.max_frames)}
    shared = Path(os.environ.get("SWIFTJAX_SHARED", REPO.parent / "shared"))
    rows, records = [], []
    for preset in args.presets:
        frames = min(args.frames, caps.get(preset, args.frames))
        runs = [("torch", d) for d in args.dtypes] + (
            [("onnxruntime", "float32")] if preset in args.onnx_presets else []
        )
        for backend, dtype in runs:
            cmd = [
                sys.executable,
                __file__,
                "--child",
                "--preset",
                preset,
                "--backend",
                backend,
                "--dtype",
                dtype,
                "--frames",
                str(frames),
                "--threads",
                str(args.threads),
            ]
            try:
                out = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=args.timeout, check=True)
                r = json.loads(out.stdout.strip().splitlines()[-1])
            except subprocess.TimeoutExpired:
                r = {"error": f"over {args.timeout:g} s"}
            except subprocess.CalledProcessError as err:
                r = {"error": (err.stderr.strip().splitlines() or ["failed"])[-1][:120]}
            manifest = shared / "golden" / "da3" / f"manifest_{MANIFEST.get(preset, '-')}.json"
            if "params" in r and manifest.is_file():
                r["manifest_params"] = json.loads(manifest.read_text())["total_params"]
            rec = dict(preset=preset, backend=backend, dtype=dtype, frames=frames, **r)
            records.append(rec)
            print(json.dumps(rec), file=sys.stderr)
            if "error" in r:
                rows.append([preset, backend, dtype, frames, "-", "-", "-", "-", r["error"]])
            else:
                rows.append(
                    [
                        preset,
                        backend,
                        dtype,
                        frames,
                        r["params"] / 1e6,
                        r["seconds"],
                        frames / r["seconds"],
                        r["peak_mb"] / 1024,
                        "" if r.get("manifest_params") in (None, r["params"]) else f"manifest {r['manifest_params']}",
                    ]
                )
    print(
        f"\nBackbones on this CPU ({args.threads} threads), random weights, one chunk of KITTI-shaped frames "
        f"(DA3 504x154, VGGT 518x154), runner.predict after a 3-frame warm-up; peak = child's peak RSS\n"
    )
    print(
        markdown_table(
            ["model", "backend", "dtype", "frames", "params (M)", "seconds", "frames/s", "peak GiB", "note"], rows
        )
    )
    path = write_results(
        "inference_backbones",
        {
            "args": {
                k: v
                for k, v in vars(args).items()
                if k in ("presets", "frames", "max_frames", "dtypes", "onnx_presets", "threads")
            },
            "rows": records,
        },
    )
    print(f"\nresults: {path.relative_to(REPO)}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--configs", nargs="+", default=["tiny", "mid"], choices=sorted(CONFIGS))
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--height", type=int, default=154)
    p.add_argument("--width", type=int, default=518)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument(
        "--presets",
        nargs="*",
        default=None,
        metavar="MODEL",
        help="full-size --model presets with random weights instead of the configs (no names: all)",
    )
    p.add_argument(
        "--max-frames", nargs="*", default=[], metavar="PRESET=N", help="--presets: frames cap of a slow preset"
    )
    p.add_argument("--dtypes", nargs="+", default=["float32", "bfloat16"], help="--presets: torch compute dtypes")
    p.add_argument(
        "--onnx-presets",
        nargs="*",
        default=["da3-small"],
        metavar="PRESET",
        help="--presets: those also run with onnxruntime",
    )
    p.add_argument("--timeout", type=float, default=900.0, help="--presets: seconds per child")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--preset", default=None, help=argparse.SUPPRESS)
    p.add_argument("--dtype", default="float32", help=argparse.SUPPRESS)
    p.add_argument("--config", default="tiny", help=argparse.SUPPRESS)
    p.add_argument("--backend", default="torch", help=argparse.SUPPRESS)
    p.add_argument("--onnx", default="", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        (preset_child if args.preset else child)(args)
        return
    if args.presets is not None:
        args.presets = args.presets or [
            "da3-small",
            "da3-base",
            "da3-large",
            "da3-giant",
            "da3-nested-giant-large",
            "vggt-1b",
        ]
        presets_main(args)
        return

    import torch

    from inference.onnx_export import export_onnx

    torch.set_num_threads(args.threads)
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        for config in args.configs:
            onnx = str(Path(tmp) / f"{config}.onnx")
            t0 = time.perf_counter()
            report = export_onnx(
                _build(config), onnx, frames=2, height=args.height, width=args.width, dynamic_frames=True, verify=False
            )
            export_s = time.perf_counter() - t0
            from inference.onnx_export import verify_onnx

            errs = verify_onnx(_build(config), report.path, [args.frames], args.height, args.width)[args.frames]
            t = _run_child(args, config, "torch", onnx)
            o = _run_child(args, config, "onnxruntime", onnx)
            rows.append(
                Row(
                    config,
                    t["params"] / 1e6,
                    args.frames / t["seconds"],
                    args.frames / o["seconds"],
                    t["peak_mb"],
                    o["peak_mb"],
                    t["peak_increase_mb"],
                    o["peak_increase_mb"],
                    export_s,
                    errs,
                )
            )
            print(f"{config}: done", file=sys.stderr)

    headers = [
        "config",
        "params (M)",
        "torch fps",
        "ORT fps",
        "ORT/torch speed",
        "torch peak MB",
        "ORT peak MB",
        "ORT/torch peak",
        "torch +MB",
        "ORT +MB",
        "export s",
        "max abs err depth / pose",
    ]
    table = [
        [
            r.config,
            r.params_m,
            r.torch_fps,
            r.ort_fps,
            r.ort_fps / r.torch_fps,
            r.torch_peak_mb,
            r.ort_peak_mb,
            r.ort_peak_mb / r.torch_peak_mb,
            r.torch_inc_mb,
            r.ort_inc_mb,
            r.export_s,
            f"{r.max_err['depth']:.1e} / {r.max_err['pose_enc']:.1e}",
        ]
        for r in rows
    ]
    print(
        f"\nVGGT CPU inference, {args.frames} frames of {args.width}x{args.height}, {args.threads} threads, "
        f"best of {args.repeat}; peak = the child process's peak RSS during inference (model loaded), "
        f"+MB = that peak minus the RSS after loading\n"
    )
    print(markdown_table(headers, table))
    path = write_results(
        "inference",
        {
            "args": {k: v for k, v in vars(args).items() if k not in ("child", "config", "backend", "onnx")},
            "rows": [dataclasses.asdict(r) for r in rows],
        },
    )
    print(f"\nresults: {path.relative_to(REPO)}")


if __name__ == "__main__":
    main()

"""VGGT inference on CPU: torch eager vs onnxruntime, frames/second and peak memory.

Two configurations with seeded random weights: ``tiny`` (the golden test config, width 64)
and ``mid`` (a ViT-S-sized VGGT, width 384, 12+12 aggregator blocks, 12 DINO blocks), on
KITTI-shaped frames (518 x 154 by default).  Each (config, backend) runs in its own child
process so that its peak resident memory (``ru_maxrss``) is its own; the ONNX graph is exported
by the parent first.  Reported: best-of-N seconds per chunk, frames/second, peak RSS and the
peak increase during inference over the RSS after loading, and onnxruntime/torch ratios.

    python bench/bench_inference.py [--configs tiny mid] [--frames 8] [--height 154]
                                    [--width 518] [--repeat 3] [--threads 2]

π³ / π³X rows (``--pi3 pi3 pi3x``; ``--configs`` may then be empty): the FULL-SIZE models
(958.7 M / 992.5 M parameters; π³X without its multimodal branches, i.e. unconditioned) with
seeded random weights (built on ``meta``, then ``normal(0, 0.02)``), torch eager on CPU only
(an ONNX graph of a 4 GB model needs external data; the tiny graphs are checked for
correctness by ``check_golden``).  Reported: wall and process-CPU seconds per chunk of
``--pi3-frames`` frames at ``--width x --height`` (504 x 154: Pi-Long's KITTI size), peak RSS.

    python bench/bench_inference.py --configs --pi3 pi3 pi3x --pi3-frames 2 --width 504 --repeat 1
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

from common import markdown_table, write_results  # noqa: E402

CONFIGS: dict[str, dict[str, object]] = {
    "tiny": dict(
        embed_dim=64, depth=6, num_heads=4, dino_depth=2, dino_num_heads=4, camera_trunk_depth=4, camera_num_heads=4,
        dpt_features=32, dpt_out_channels=(16, 32, 64, 64), dpt_intermediate_layer_idx=(1, 3, 4, 5),
    ),
    "mid": dict(
        embed_dim=384, depth=12, num_heads=6, dino_depth=12, dino_num_heads=6, camera_trunk_depth=2, camera_num_heads=6,
        dpt_features=128, dpt_out_channels=(48, 96, 192, 384), dpt_intermediate_layer_idx=(2, 5, 8, 11),
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
    print(json.dumps(dict(seconds=best, rss_loaded_mb=loaded, peak_mb=peak,
                          peak_increase_mb=max(peak - loaded, 0.0), params=n_params)))


def _build_pi3(variant: str):  # type: ignore[no-untyped-def]
    """A full-size π³ / π³X (unconditioned) with seeded random weights, built without a
    second copy (meta device, then materialised in place)."""
    import torch

    from inference.pi3.config import Pi3Config
    from inference.pi3.model import Pi3
    from inference.pi3.pi3x import Pi3X

    with torch.device("meta"):
        model = Pi3(Pi3Config.pi3()) if variant == "pi3" else Pi3X(Pi3Config.pi3x(multimodal=False))
    model = model.to_empty(device="cpu")
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0.0, 0.02, generator=gen)
        model.image_mean.copy_(torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        model.image_std.copy_(torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))
    return model.eval()


def pi3_child(args: argparse.Namespace) -> None:
    """Runs one full-size π³ variant in torch and prints one JSON line."""
    import numpy as np
    import torch

    torch.set_num_threads(args.threads)
    model = _build_pi3(args.config)
    x = torch.from_numpy(np.random.default_rng(0).random((1, args.pi3_frames, 3, args.height, args.width),
                                                        dtype=np.float32))
    loaded = _status_mb("VmRSS")
    _reset_peak()
    best_wall = best_cpu = float("inf")
    with torch.inference_mode():
        for _ in range(args.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            model(x)
            best_wall = min(best_wall, time.perf_counter() - t0)
            best_cpu = min(best_cpu, time.process_time() - c0)
    peak = _status_mb("VmHWM")
    print(json.dumps(dict(seconds=best_wall, cpu_seconds=best_cpu, rss_loaded_mb=loaded, peak_mb=peak,
                          peak_increase_mb=max(peak - loaded, 0.0),
                          params=sum(p.numel() for p in model.parameters()))))


def _run_pi3_child(args: argparse.Namespace, variant: str) -> dict[str, float]:
    cmd = [sys.executable, __file__, "--child", "--pi3-child", "--config", variant, "--pi3-frames",
           str(args.pi3_frames), "--height", str(args.height), "--width", str(args.width),
           "--repeat", str(args.repeat), "--threads", str(args.threads)]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=REPO)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _run_child(args: argparse.Namespace, config: str, backend: str, onnx: str) -> dict[str, float]:
    cmd = [sys.executable, __file__, "--child", "--config", config, "--backend", backend, "--onnx", onnx,
           "--frames", str(args.frames), "--height", str(args.height), "--width", str(args.width),
           "--repeat", str(args.repeat), "--threads", str(args.threads)]
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--configs", nargs="*", default=["tiny", "mid"], choices=sorted(CONFIGS))
    p.add_argument("--pi3", nargs="*", default=[], choices=["pi3", "pi3x"], help="full-size π³ rows (torch, CPU)")
    p.add_argument("--pi3-frames", type=int, default=2, help="frames per π³ chunk")
    p.add_argument("--pi3-child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--height", type=int, default=154)
    p.add_argument("--width", type=int, default=518)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--config", default="tiny", help=argparse.SUPPRESS)
    p.add_argument("--backend", default="torch", help=argparse.SUPPRESS)
    p.add_argument("--onnx", default="", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        pi3_child(args) if args.pi3_child else child(args)
        return

    import torch

    from inference.onnx_export import export_onnx

    torch.set_num_threads(args.threads)
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp:
        for config in args.configs:
            onnx = str(Path(tmp) / f"{config}.onnx")
            t0 = time.perf_counter()
            report = export_onnx(_build(config), onnx, frames=2, height=args.height, width=args.width,
                                 dynamic_frames=True, verify=False)
            export_s = time.perf_counter() - t0
            from inference.onnx_export import verify_onnx

            errs = verify_onnx(_build(config), report.path, [args.frames], args.height, args.width)[args.frames]
            t = _run_child(args, config, "torch", onnx)
            o = _run_child(args, config, "onnxruntime", onnx)
            rows.append(Row(config, t["params"] / 1e6, args.frames / t["seconds"], args.frames / o["seconds"],
                            t["peak_mb"], o["peak_mb"], t["peak_increase_mb"], o["peak_increase_mb"], export_s, errs))
            print(f"{config}: done", file=sys.stderr)

    pi3_rows = []
    for variant in args.pi3:
        r = _run_pi3_child(args, variant)
        pi3_rows.append(dict(model=variant, **r))
        print(f"{variant}: done", file=sys.stderr)

    headers = ["config", "params (M)", "torch fps", "ORT fps", "ORT/torch speed", "torch peak MB", "ORT peak MB",
               "ORT/torch peak", "torch +MB", "ORT +MB", "export s", "max abs err depth / pose"]
    table = [
        [r.config, r.params_m, r.torch_fps, r.ort_fps, r.ort_fps / r.torch_fps, r.torch_peak_mb, r.ort_peak_mb,
         r.ort_peak_mb / r.torch_peak_mb, r.torch_inc_mb, r.ort_inc_mb, r.export_s,
         f"{r.max_err['depth']:.1e} / {r.max_err['pose_enc']:.1e}"]
        for r in rows
    ]
    if rows:
        print(f"\nVGGT CPU inference, {args.frames} frames of {args.width}x{args.height}, {args.threads} threads, "
              f"best of {args.repeat}; peak = the child process's peak RSS during inference (model loaded), "
              f"+MB = that peak minus the RSS after loading\n")
        print(markdown_table(headers, table))
    if pi3_rows:
        print(f"\nπ³ / π³X full size (random weights), torch CPU, {args.pi3_frames} frames of {args.width}x"
              f"{args.height} per chunk, {args.threads} threads, best of {args.repeat}; peak = peak RSS during "
              f"inference (weights included), +MB = peak minus the RSS after loading\n")
        print(markdown_table(
            ["model", "params (M)", "s / chunk", "CPU s / chunk", "s / frame", "peak MB", "+MB"],
            [[r["model"], r["params"] / 1e6, r["seconds"], r["cpu_seconds"], r["seconds"] / args.pi3_frames,
              r["peak_mb"], r["peak_increase_mb"]] for r in pi3_rows]))
    skip = ("child", "config", "backend", "onnx", "pi3_child")
    name = "inference" if rows else "inference_pi3"  # a π³-only run keeps the VGGT rows' file
    path = write_results(name, {"args": {k: v for k, v in vars(args).items() if k not in skip},
                                       "rows": [dataclasses.asdict(r) for r in rows], "pi3_rows": pi3_rows})
    print(f"\nresults: {path.relative_to(REPO)}")


if __name__ == "__main__":
    main()

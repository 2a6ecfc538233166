"""The real workload on one GPU: VGGT-1B chunks measured against the hardware's own matmul rate.

One command, one JSON and one log (about 8 minutes on an H200):

1. the device, torch / CUDA versions and the measured bf16 matmul rate (8192³, best of 10);
2. VGGT-1B with random weights at 518 × 154 for chunks of 30 / 60 / 75 / 120 frames: seconds
   per chunk (CUDA events, after a warm-up), frames/s, FLOPs counted by :mod:`flops`, achieved
   TFLOP/s and its fraction of the measured matmul rate (whole model and aggregator alone),
   peak allocated / reserved memory; an out-of-memory chunk size is recorded, not fatal;
3. the precision modes at one chunk size: float32, bf16 autocast (float32 weights) and bf16
   weights (aggregator cast, heads float32): time and the depth / pose difference to float32;
   the attention backend that ran is asserted (flash or memory-efficient; never a silent math
   fallback) and recorded;
4. the tiny golden VGGT on the device in float32 against ``golden/vggt`` (``--golden``; the
   shared folder does not travel to a GPU machine: copy ``golden/vggt`` beside the script);
5. an end-to-end :func:`swiftjax.pipeline.reconstruct` of a synthetic route (the oracle's
   renders written as PNG files, ``--e2e-frames``) with the random-weight model: wall time,
   predict share, GPU idle share and the pipeline's own stage times;
6. every other ``--model`` backbone (DA3 presets, π³; ``--backbones``) with random weights at
   the chunk size of section 3 through its own runner in bf16: seconds per chunk, frames/s and
   peak memory;
7. last, ``torch.compile`` of the aggregator (``--compile``): the one section whose time is not
   known in advance.  The JSON and the log are rewritten after every section (a run cut short
   keeps what it measured), and a section that fails is recorded and the next one runs.

``--smoke`` runs every section on the CPU with the tiny configuration and two chunks in
seconds (the test suite runs it, so the script cannot rot). Results go to
``bench/results/gpu-<stamp>.json`` (``--json`` elsewhere) and the log to ``--log``.

    python bench/bench_gpu.py [--smoke] [--chunks 30 60 75 120] [--golden DIR] [--e2e-frames 600]

On a GPU machine that has torch, JAX and the project's other packages but not ``../shared``
(the device tool's H200 image): ``mkdir -p .gpu_data/golden && cp -r ../shared/golden/vggt
.gpu_data/golden/`` here, carry ``.gpu_data``, and run ``PYTHONPATH=$PWD python3
bench/bench_gpu.py --json $OUT/gpu.json --log $OUT/gpu.log`` there.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import pathlib
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from common import machine_info
from flops import vggt_chunk_flops

LOG: list[str] = []

#: The sections, in the order they run (``--sections`` picks some).
SECTIONS = ["matmul", "chunks", "precision", "golden", "precision_golden", "end_to_end", "backbones", "compile"]

#: The other backbones timed by default (section 6): every DA3 preset and π³.
BACKBONES = ["da3-small", "da3-base", "da3-large", "da3-giant", "da3-nested-giant-large", "pi3"]


def log(msg: str) -> None:
    print(msg, flush=True)
    LOG.append(msg)


# ----------------------------------------------------------------------------------------------
# device helpers


class Clock:
    """Seconds of GPU work between ``start`` and ``stop`` (CUDA events), wall time on the CPU."""

    def __init__(self, device: Any) -> None:
        import torch

        self.cuda = device.type == "cuda"
        self.torch = torch

    @contextlib.contextmanager
    def measure(self) -> Iterator[list[float]]:
        out: list[float] = []
        if self.cuda:
            start = self.torch.cuda.Event(enable_timing=True)
            stop = self.torch.cuda.Event(enable_timing=True)
            start.record()
            yield out
            stop.record()
            stop.synchronize()
            out.append(start.elapsed_time(stop) / 1e3)
        else:
            t0 = time.perf_counter()
            yield out
            out.append(time.perf_counter() - t0)


def matmul_rate(device: Any, n: int, dtype: Any, repeat: int = 10) -> float:
    """Best FLOP/s of an ``n × n × n`` matrix product (``2n³`` FLOP)."""
    import torch

    a = torch.randn(n, n, device=device, dtype=dtype)
    b = torch.randn(n, n, device=device, dtype=dtype)
    clock = Clock(device)
    best = math.inf
    for _ in range(repeat + 1):  # the first is the warm-up
        with clock.measure() as t:
            a @ b
        best = min(best, t[0])
    return 2 * n**3 / best


def attention_backends(device: Any, dtype: Any) -> list[Any]:
    """The fused SDPA backends allowed on ``device``: flash for half precision, else memory-
    efficient; on the CPU torch's own (flash-for-CPU or math): nothing to assert there."""
    from torch.nn.attention import SDPBackend

    if device.type != "cuda":
        return [SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH]
    half = dtype in (__import__("torch").bfloat16, __import__("torch").float16)
    return [SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION] if half else [SDPBackend.EFFICIENT_ATTENTION]


def which_attention_backend(device: Any, dtype: Any, dim: int = 1024, heads: int = 16) -> str:
    """The first backend of :func:`attention_backends` that runs a VGGT-shaped attention alone
    (a fused kernel refuses a shape it cannot take; the math path is never allowed on CUDA)."""
    import torch
    import torch.nn.functional as F
    from torch.nn.attention import sdpa_kernel

    q = torch.randn(1, heads, 128, dim // heads, device=device, dtype=dtype)
    for backend in attention_backends(device, dtype):
        try:
            with sdpa_kernel([backend]):
                F.scaled_dot_product_attention(q, q, q)
            return backend.name
        except RuntimeError:
            continue
    raise RuntimeError(f"no fused attention backend runs on {device} in {dtype}: refusing the math fallback")


# ----------------------------------------------------------------------------------------------
# models


def random_vggt(config: Any, device: Any, seed: int = 0) -> Any:
    """A VGGT with random weights built directly on ``device`` (no 5 GB host copy).

    Every layer gets torch's default initialisation (``reset_parameters``), tokens
    N(0, 0.02²), LayerScale 0.01; the camera head's last bias gives a unit quaternion and
    FoV 1 rad, so poses and intrinsics are finite (speed does not depend on the values).
    """
    import torch

    from inference.model import VGGT

    torch.manual_seed(seed)
    with torch.device("meta"):
        model = VGGT(config)
    model = model.to_empty(device=device).eval().requires_grad_(False)
    for module in model.modules():
        if hasattr(module, "reset_parameters"):
            module.reset_parameters()
    for name, p in model.named_parameters(recurse=True):
        leaf = name.rsplit(".", 1)[-1]
        if leaf == "gamma":
            p.fill_(0.01)
        elif leaf.endswith("token") or leaf.endswith("tokens") or leaf == "pos_embed":
            p.normal_(0.0, 0.02)
    # The camera head adds its output once per iteration: the bias sums to a unit quaternion
    # and a 1 rad field of view, the (shrunk) weights keep the rest small.
    head = model.camera_head.pose_branch.fc2
    head.weight.mul_(1e-3)
    head.bias.zero_()
    head.bias[6:9] = 1.0 / config.camera_iterations
    return model


def tiny_config(golden: pathlib.Path) -> Any:
    from inference.config import VGGTConfig

    return VGGTConfig.from_json(golden / "tiny_config.json")


class Precision:
    """How a model runs in reduced precision: ``float32``, ``autocast`` (float32 weights,
    bf16 autocast over the aggregator; the heads in float32, as upstream) or ``weights``
    (the aggregator's weights cast to bf16, the heads float32)."""

    def __init__(self, model: Any, mode: str, dtype: Any) -> None:
        import torch

        self.model, self.mode, self.dtype = model, mode, dtype
        if mode == "weights":
            model.aggregator.to(dtype)
        self.torch = torch

    def __call__(self, images: Any) -> dict[str, Any]:
        from inference.device import model_math

        torch = self.torch
        if self.mode == "weights":
            with torch.inference_mode():
                return self.model(images.to(self.dtype))
        with model_math(images.device, torch.float32 if self.mode == "float32" else self.dtype):
            return self.model(images)


def pose_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Largest rotation angle (degrees) and translation difference between pose encodings."""
    from scipy.spatial.transform import Rotation

    qa, qb = a[..., 3:7].reshape(-1, 4), b[..., 3:7].reshape(-1, 4)
    angle = (Rotation.from_quat(qa).inv() * Rotation.from_quat(qb)).magnitude()
    return float(np.degrees(angle).max()), float(np.abs(a[..., :3] - b[..., :3]).max())


def depth_difference(a: np.ndarray, b: np.ndarray) -> float:
    """Median relative depth difference."""
    return float(np.median(np.abs(a - b) / np.maximum(np.abs(b), 1e-12)))


# ----------------------------------------------------------------------------------------------
# sections


def chunk_sweep(
    model: Any, config: Any, device: Any, chunks: list[int], hw: tuple[int, int], dtype: Any, rate: float, repeat: int
) -> list[dict[str, Any]]:
    """Section 2: seconds, FLOP/s and memory per chunk size (bf16 autocast, the default runner)."""
    import torch
    from torch.nn.attention import sdpa_kernel

    clock = Clock(device)
    run = Precision(model, "autocast" if dtype != torch.float32 else "float32", dtype)
    rows = []
    for s in chunks:
        flops = vggt_chunk_flops(config, s, *hw)
        row: dict[str, Any] = {
            "frames": s,
            "tflop": flops["total"] / 1e12,
            "aggregator_tflop": flops["aggregator"] / 1e12,
        }
        x = torch.rand(1, s, 3, *hw, device=device)
        try:
            if device.type == "cuda":
                torch.cuda.empty_cache()
                torch.cuda.reset_peak_memory_stats()
            with sdpa_kernel(attention_backends(device, dtype)):
                run(x)  # warm-up
                times, agg_times = [], []
                for _ in range(repeat):
                    with clock.measure() as t:
                        run(x)
                    times.append(t[0])
                    with (
                        clock.measure() as t,
                        torch.inference_mode(),
                        torch.autocast(device_type=device.type, dtype=dtype, enabled=dtype != torch.float32),
                    ):
                        model.aggregator(x)
                    agg_times.append(t[0])
            sec, agg = min(times), min(agg_times)
            row.update(
                seconds=sec,
                frames_per_s=s / sec,
                tflops=flops["total"] / sec / 1e12,
                fraction_of_matmul=flops["total"] / sec / rate,
                aggregator_seconds=agg,
                aggregator_fraction_of_matmul=flops["aggregator"] / agg / rate,
            )
            if device.type == "cuda":
                row.update(
                    peak_allocated_gb=torch.cuda.max_memory_allocated() / 2**30,
                    peak_reserved_gb=torch.cuda.max_memory_reserved() / 2**30,
                )
        except torch.OutOfMemoryError as err:
            row.update(error=f"out of memory: {str(err).splitlines()[0]}")
        finally:
            del x
        rows.append(row)
        log(
            f"  S = {s:4d}: "
            + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items() if k != "frames")
        )
    return rows


def precision_modes(
    make_model: Callable[[], Any],
    device: Any,
    frames: int,
    hw: tuple[int, int],
    dtype: Any,
    repeat: int,
    images: Any = None,
) -> list[dict[str, Any]]:
    """Section 3: float32 vs bf16 autocast vs bf16 weights on the same input (``images``
    ``[1, S, 3, H, W]``, default random)."""
    import torch
    from torch.nn.attention import sdpa_kernel

    clock = Clock(device)
    x = (
        images
        if images is not None
        else torch.rand(1, frames, 3, *hw, device=device, generator=torch.Generator(device=device).manual_seed(1))
    )
    rows, ref = [], None
    for mode in ("float32", "autocast", "weights"):
        run = Precision(make_model(), mode, dtype)
        mode_dtype = torch.float32 if mode == "float32" else dtype
        with sdpa_kernel(attention_backends(device, mode_dtype)):
            out = run(x)
            times = []
            for _ in range(repeat):
                with clock.measure() as t:
                    run(x)
                times.append(t[0])
        depth = out["depth"].float().cpu().numpy()
        pose = out["pose_enc"].float().cpu().numpy()
        row = {
            "mode": mode,
            "seconds": min(times),
            "attention_backend": which_attention_backend(
                device, mode_dtype, run.model.config.embed_dim, run.model.config.num_heads
            ),
        }
        if ref is None:
            ref = (depth, pose)
        else:
            rot, trans = pose_difference(pose, ref[1])
            row.update(
                depth_median_rel_diff=depth_difference(depth, ref[0]), rotation_diff_deg=rot, translation_diff=trans
            )
        rows.append(row)
        log(
            f"  {mode:>8}: "
            + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items() if k != "mode")
        )
        del run
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return rows


def compile_measure(
    model: Any, device: Any, frames: int, hw: tuple[int, int], dtype: Any, repeat: int
) -> dict[str, Any]:
    """``torch.compile`` of the aggregator: first call (compile) and steady seconds vs eager."""
    import torch

    clock = Clock(device)
    x = torch.rand(1, frames, 3, *hw, device=device)
    ctx = lambda: torch.autocast(device_type=device.type, dtype=dtype, enabled=dtype != torch.float32)
    with torch.inference_mode(), ctx():
        model.aggregator(x)
        eager = []
        for _ in range(repeat):
            with clock.measure() as t:
                model.aggregator(x)
            eager.append(t[0])
        compiled = torch.compile(model.aggregator)
        t0 = time.perf_counter()
        compiled(x)
        if device.type == "cuda":
            torch.cuda.synchronize()
        first = time.perf_counter() - t0
        steady = []
        for _ in range(repeat):
            with clock.measure() as t:
                compiled(x)
            steady.append(t[0])
    row = {"eager_seconds": min(eager), "compile_first_call_seconds": first, "compiled_seconds": min(steady)}
    row["chunks_to_pay_back"] = (first / max(min(eager) - min(steady), 1e-9)) if min(steady) < min(eager) else None
    log("  " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
    return row


def golden_model(golden: pathlib.Path, device: Any) -> Any:
    """The tiny golden VGGT with its reference weights, on ``device``."""
    from inference.checkpoint import load_checkpoint
    from inference.model import VGGT

    model = VGGT(tiny_config(golden)).eval()
    load_checkpoint(model, golden / "tiny_weights.safetensors")
    return model.to(device)


def golden_images(golden: pathlib.Path, device: Any) -> Any:
    import torch

    return torch.from_numpy(np.load(golden / "tiny_images.npy").astype(np.float32)).to(device)


def golden_on_device(golden: pathlib.Path, device: Any) -> dict[str, Any]:
    """Section 4: the tiny golden VGGT on ``device`` in float32 against the reference tensors."""
    import torch

    from inference.check_golden import TOLERANCES, compare
    from inference.device import model_math

    model = golden_model(golden, device)
    images = golden_images(golden, device)
    ref = np.load(golden / "tiny_golden.npz")
    with model_math(device, torch.float32):  # float32 without TF32, as the runner's float32
        out = model(images)
    got = {
        "patch_tokens": out["patch_tokens"],
        "pose_enc": out["pose_enc"],
        "depth": out["depth"],
        "depth_conf": out["depth_conf"],
    }
    checks = [compare(device.type, k, v.float().cpu().numpy(), ref[k]) for k, v in got.items() if k in TOLERANCES]
    for c in checks:
        log(f"  {c.name:<14} max abs {c.max_abs:.2e} max rel {c.max_rel:.2e} {'ok' if c.passed else 'FAIL'}")
    return {
        "passed": all(c.passed for c in checks),
        "checks": [{"name": c.name, "max_abs": c.max_abs, "max_rel": c.max_rel, "passed": c.passed} for c in checks],
    }


def backbone_sweep(
    presets: list[str], device: Any, frames: int, hw: tuple[int, int] | None, dtype: Any, repeat: int
) -> list[dict[str, Any]]:
    """Section 6: each ``--model`` backbone (random weights, bench_inference's initialisation) at
    ``frames`` per chunk through its own runner in ``dtype``: seconds per chunk (CUDA events
    around ``predict``: upload, network, conversion, download), frames/s and peak memory.
    ``hw`` None: the backbone's KITTI size (504 × 154 for DA3 and π³, 518 × 154 for VGGT)."""
    import torch
    from bench_inference import KITTI_HW, random_model

    clock = Clock(device)
    rows = []
    for name in presets:
        row: dict[str, Any] = {"model": name, "frames": frames}
        try:
            b, model = random_model(name, device=str(device))
            row["params"] = sum(p.numel() for p in model.parameters())
            h, w = hw or KITTI_HW[b.family]
            row["image_hw"] = [h, w]
            if b.family == "vggt":
                from inference.runners import TorchRunner as Runner
            elif b.family == "pi3":
                from inference.pi3.runner import Pi3TorchRunner as Runner
            else:
                from inference.backbones.da3 import DA3Runner as Runner
            runner = Runner(model, device, dtype=dtype)
            x = np.random.default_rng(0).random((frames, 3, h, w), dtype=np.float32)
            if device.type == "cuda":
                torch.cuda.empty_cache()
                torch.cuda.reset_peak_memory_stats()
            with np.errstate(all="ignore"):
                runner.predict(x)  # warm-up
                times = []
                for _ in range(repeat):
                    with clock.measure() as t:
                        runner.predict(x)
                    times.append(t[0])
            row.update(seconds=min(times), frames_per_s=frames / min(times))
            if device.type == "cuda":
                row.update(
                    peak_allocated_gb=torch.cuda.max_memory_allocated() / 2**30,
                    peak_reserved_gb=torch.cuda.max_memory_reserved() / 2**30,
                )
            del runner, model
        except Exception as err:  # one preset's failure is recorded; the others still run
            row["error"] = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
        if device.type == "cuda":
            torch.cuda.empty_cache()
        rows.append(row)
        log(
            f"  {name:>22}: "
            + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items() if k != "model")
        )
    return rows


class TimedRunner:
    """A :class:`inference.runners.TorchRunner` whose device time per chunk is recorded."""

    def __init__(self, runner: Any, device: Any) -> None:
        self.runner, self.clock, self.seconds = runner, Clock(device), []

    def predict(self, images: Any) -> Any:
        with self.clock.measure() as t:
            out = self.runner.predict(images)
        self.seconds.append(t[0])
        return out


def write_frames(folder: pathlib.Path, frames: int, hw: tuple[int, int], oracle: bool = True) -> float:
    """PNG files of ``frames`` frames of size ``hw``; seconds.  ``oracle``: the oracle's renders of
    the demo route; else a noise texture sliding sideways (no renderer to compile: ``--smoke``)."""
    import cv2

    t0 = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    if oracle:
        from swiftjax.synthetic.demo import loop_route_run

        predictor = loop_route_run(frames, image_hw=hw, aliasing=0.0).predictor
        batches = (np.arange(s, min(s + 50, frames)) for s in range(0, frames, 50))
        pairs = ((k, img) for ids in batches for k, img in zip(ids, predictor.predict(ids).images))
    else:
        base = np.random.default_rng(0).integers(0, 255, (*hw, 3), np.uint8)
        pairs = ((k, np.roll(base, 3 * k, axis=1)) for k in range(frames))
    for k, img in pairs:
        cv2.imwrite(str(folder / f"{k:06d}.png"), img[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return time.perf_counter() - t0


def end_to_end(
    model: Any,
    device: Any,
    dtype: Any,
    frames: int,
    chunk: int,
    overlap: int,
    render_hw: tuple[int, int],
    workdir: pathlib.Path,
    oracle: bool = True,
    prefetches: tuple[int, ...] = (1, 1, 3),
) -> dict[str, Any]:
    """Section 5: the whole pipeline over PNG files with the random-weight model (the geometry
    on JAX's default backend: ``JAX_PLATFORMS=cpu`` puts it on the host, as on a CPU machine).

    One reconstruction per entry of ``prefetches`` (the local executor's predictions ahead of
    the geometry), each into its own run directory: the first is cold (every JAX program
    compiled in it, no persistent cache), the later ones find the programs compiled, as a
    second run of the CLI with its compilation cache does.  The row is the first run's, with
    every run's numbers under ``runs``."""
    import jax

    from inference.predictor import ImagePredictor
    from inference.runners import TorchRunner
    from swiftjax import pipeline
    from swiftjax.io import images
    from swiftjax.pipeline.config import PipelineConfig
    from swiftjax.pipeline.executors import LocalExecutor

    render_s = write_frames(workdir / "frames", frames, render_hw, oracle)
    source = images.validate(images.list_frames(workdir / "frames"))
    config = PipelineConfig(chunk_size=chunk, overlap=overlap, min_points=10, loop_half_window=min(10, chunk // 2))
    rows = []
    for k, prefetch in enumerate(prefetches):
        runner = TimedRunner(TorchRunner(model, device=device, dtype=dtype), device)
        predictor = ImagePredictor(source, runner, identity={"bench": "random weights"})
        t0 = time.perf_counter()
        result = pipeline.reconstruct(
            predictor,
            workdir / f"run{k}",
            config,
            executor=LocalExecutor(prefetch=prefetch),
            progress=False,
            log=lambda m: None,
        )
        wall = time.perf_counter() - t0
        busy = float(sum(runner.seconds))
        predict_only = (chunk - overlap) / (busy / len(runner.seconds))
        row = {
            "run": "cold" if k == 0 else "warm",
            "prefetch": prefetch,
            "frames": frames,
            "chunks": len(runner.seconds),
            "render_seconds": render_s,
            "wall_seconds": wall,
            "predict_seconds": busy,
            "predict_share": busy / wall,
            "gpu_idle_share": 1 - busy / wall,
            "frames_per_s": frames / wall,
            "predict_only_new_frames_per_s": predict_only,
            "e2e_over_predict_only": (frames / wall) / predict_only,
            "stage_seconds": {k: float(v) for k, v in result.timings.items()},
            "jax": f"{jax.__version__} on {jax.default_backend()}",
        }
        rows.append(row)
        log(
            "  "
            + ", ".join(
                f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items() if k != "stage_seconds"
            )
        )
        log("  stages: " + ", ".join(f"{k} {v:.2f} s" for k, v in row["stage_seconds"].items()))
    return {**rows[0], "runs": rows}


# ----------------------------------------------------------------------------------------------


def default_golden() -> pathlib.Path | None:
    """``golden/vggt`` under ``$SWIFTJAX_SHARED``, ``../shared`` or the repository's git-ignored
    ``.gpu_data/`` (what travels to a GPU machine: ``cp -r ../shared/golden/vggt .gpu_data/golden/``)."""
    for cand in (os.environ.get("SWIFTJAX_SHARED"), HERE.parents[1] / "shared", HERE.parent / ".gpu_data"):
        if cand and (pathlib.Path(cand) / "golden" / "vggt" / "tiny_config.json").is_file():
            return pathlib.Path(cand) / "golden" / "vggt"
    return None


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--smoke", action="store_true", help="CPU, tiny config, two chunks: every section in seconds")
    ap.add_argument("--device", default=None, help="default: cuda if available, else cpu")
    ap.add_argument("--chunks", type=int, nargs="+", default=[30, 60, 75, 120])
    ap.add_argument("--modes-chunk", type=int, default=75, help="chunk size of the precision-mode section")
    ap.add_argument("--height", type=int, default=154)
    ap.add_argument("--width", type=int, default=518)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--matmul", type=int, default=8192, help="n of the n^3 matmul-rate probe")
    ap.add_argument("--golden", type=pathlib.Path, default=None, help="folder in the golden/vggt layout")
    ap.add_argument("--e2e-frames", type=int, default=600)
    ap.add_argument("--e2e-render", default="376x1241", help="HxW of the PNG frames (KITTI's size)")
    ap.add_argument(
        "--compile",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="measure torch.compile of the aggregator (default: on CUDA)",
    )
    ap.add_argument(
        "--backbones", nargs="*", default=None, metavar="MODEL", help="--model presets timed per chunk (no names: none)"
    )
    ap.add_argument(
        "--sections", nargs="+", default=None, choices=SECTIONS, help="run only these sections (default: all)"
    )
    ap.add_argument("--json", type=pathlib.Path, default=None)
    ap.add_argument("--log", type=pathlib.Path, default=None)
    args = ap.parse_args(argv)

    import torch

    golden = args.golden or default_golden()
    if args.smoke:
        if golden is None:
            raise SystemExit("--smoke needs the tiny golden VGGT: --golden DIR or $SWIFTJAX_SHARED")
        args.device = args.device or "cpu"
        args.chunks, args.modes_chunk, args.repeat, args.matmul = [4, 6], 4, 1, 256
        args.height, args.width, args.e2e_frames, args.e2e_render = 28, 42, 10, "60x220"
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    dtype = torch.bfloat16
    hw = (args.height, args.width)
    render_hw = tuple(int(v) for v in args.e2e_render.split("x"))
    started = time.perf_counter()
    results: dict[str, Any] = {
        "smoke": args.smoke,
        "device": str(device),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "image_hw": list(hw),
        "machine": machine_info(),
    }
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        results.update(device_name=props.name, device_memory_gb=props.total_memory / 2**30)
    log(f"== device {results.get('device_name', device)} torch {torch.__version__} cuda {torch.version.cuda}")
    out = Recorder(results, args.json, args.log, smoke=args.smoke, only=args.sections)

    def matmul() -> dict[str, Any]:
        mm_dtype = dtype if device.type == "cuda" else torch.float32
        rate = matmul_rate(device, args.matmul, mm_dtype)
        log(f"== matmul {args.matmul}^3 {mm_dtype}: {rate / 1e12:.1f} TFLOP/s")
        return {"n": args.matmul, "dtype": str(mm_dtype), "tflops": rate / 1e12}

    out.section("matmul", matmul)
    rate = out.results.get("matmul", {}).get("tflops", 0.0) * 1e12 or math.nan

    from inference.config import VGGTConfig

    config = tiny_config(golden) if args.smoke else VGGTConfig()
    model = random_vggt(config, device)
    results["params"] = sum(p.numel() for p in model.parameters())
    log(f"== VGGT ({results['params'] / 1e6:.1f} M params, random weights) at {hw[1]}x{hw[0]}, bf16 autocast")
    out.section("chunks", lambda: chunk_sweep(model, config, device, args.chunks, hw, dtype, rate, args.repeat))

    log(f"== precision modes at S = {args.modes_chunk}")
    out.section(
        "precision",
        lambda: precision_modes(lambda: random_vggt(config, device), device, args.modes_chunk, hw, dtype, args.repeat),
    )

    if golden is not None:
        log(f"== tiny golden VGGT on {device.type} (float32) against {golden}")
        out.section("golden", lambda: golden_on_device(golden, device))
        log("== precision modes on the tiny golden VGGT (its seeded weights and images)")

        def golden_precision() -> list[dict[str, Any]]:
            images = golden_images(golden, device)
            return precision_modes(
                lambda: golden_model(golden, device),
                device,
                images.shape[1],
                tuple(images.shape[-2:]),
                dtype,
                args.repeat,
                images=images,
            )

        out.section("precision_golden", golden_precision)
    else:
        log("== golden: skipped (no golden/vggt folder: --golden DIR)")

    chunk, overlap = (6, 2) if args.smoke else (75, 30)
    log(
        f"== end to end: {args.e2e_frames} PNG frames ({render_hw[1]}x{render_hw[0]}), chunk {chunk}, overlap {overlap}"
    )

    def e2e() -> dict[str, Any]:
        with tempfile.TemporaryDirectory() as tmp:
            return end_to_end(
                model,
                device,
                dtype,
                args.e2e_frames,
                chunk,
                overlap,
                render_hw,
                pathlib.Path(tmp),
                not args.smoke,
                (1, 2) if args.smoke else (1, 1, 3),
            )

    out.section("end_to_end", e2e)
    backbones = args.backbones if args.backbones is not None else (["da3-small"] if args.smoke else BACKBONES)
    if backbones:
        log(f"== backbones at S = {args.modes_chunk} ({dtype} autocast, their own runners)")
        out.section(
            "backbones",
            lambda: backbone_sweep(
                backbones, device, args.modes_chunk, (28, 42) if args.smoke else None, dtype, args.repeat
            ),
        )
    # Last: compiling the 1B aggregator is the one section whose time is not known in advance,
    # and everything before it is already on disk if the run's time limit cuts it short.
    if args.compile if args.compile is not None else device.type == "cuda":
        log(f"== torch.compile of the aggregator at S = {args.modes_chunk}")
        out.section(
            "compile",
            lambda: compile_measure(random_vggt(config, device), device, args.modes_chunk, hw, dtype, args.repeat),
        )
    results["total_seconds"] = time.perf_counter() - started
    log(f"== done in {results['total_seconds']:.0f} s")
    path = out.write(final=True)
    if path is not None:
        log(f"results: {path}")
    out.write_log()
    return results


class Recorder:
    """The results and the log, written after every section (temp file + rename), so a run cut
    short by its time limit keeps what it measured; a section that raises is recorded as
    ``{"error": ...}`` and the next one runs (one GPU run must not be lost to one section)."""

    def __init__(
        self,
        results: dict[str, Any],
        json_path: pathlib.Path | None,
        log_path: pathlib.Path | None,
        smoke: bool,
        only: list[str] | None = None,
    ) -> None:
        self.results, self.json_path, self.log_path, self.smoke = results, json_path, log_path, smoke
        self.only = only
        self.path: pathlib.Path | None = None

    def section(self, name: str, fn: Callable[[], Any]) -> None:
        if self.only is not None and name not in self.only:
            return
        t0 = time.perf_counter()
        try:
            self.results[name] = fn()
        except Exception as err:  # recorded and reported; the run goes on
            import traceback

            log(f"  {name} FAILED: {type(err).__name__}: {err}")
            log("".join(traceback.format_exception(err)[-6:]))
            self.results[name] = {"error": f"{type(err).__name__}: {err}"}
            if self.smoke:
                raise
        self.results.setdefault("section_seconds", {})[name] = time.perf_counter() - t0
        self.write()

    def write(self, final: bool = False) -> pathlib.Path | None:
        from common import write_results

        if self.json_path is not None:
            tmp = self.json_path.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(self.results, indent=2, default=float))
            os.replace(tmp, self.json_path)
            self.path = self.json_path
        elif final and not self.smoke:
            self.path = write_results("gpu", self.results)
        self.write_log()
        return self.path

    def write_log(self) -> None:
        if self.log_path is not None:
            tmp = self.log_path.with_suffix(".log.tmp")
            tmp.write_text("\n".join(LOG) + "\n")
            os.replace(tmp, self.log_path)


if __name__ == "__main__":
    main()

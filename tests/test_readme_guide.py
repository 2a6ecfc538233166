"""The README reads as a user's guide (issue 26 items 6, 7, 11): the benchmark tables live on
the docs' benchmark pages (linked), the user's sections exist and say true things (checked
against the code where the code decides), the viewer caption's numbers match the viewer."""

from __future__ import annotations

import json
import pathlib
import re

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text(encoding="utf-8")
PERFORMANCE = (REPO / "docs" / "performance" / "index.md").read_text(encoding="utf-8")


def _section(title: str) -> str:
    m = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## )", README, re.S | re.M)
    assert m, f"README has no section '## {title}'"
    return m.group(1)


def test_benchmark_tables_moved_to_the_docs():
    assert len(README.encode()) < 40_000, len(README.encode())  # was 63 KB, mostly tables
    table_rows = [ln for ln in README.splitlines() if ln.startswith("|")]
    assert len(table_rows) < 30, len(table_rows)
    assert "](docs/performance/index.md)" in _section("Benchmarks")
    assert '--8<-- "README.md:benchmarks"' not in PERFORMANCE  # the page holds the tables itself
    for heading in (
        "### Sim(3) (`python bench/bench_sim3.py`)",
        "### Pose graph (`python bench/bench_posegraph.py`)",
        "### Measured (`python bench/bench_camera.py`)",
        "### VGGT inference on CPU",
    ):
        assert heading in PERFORMANCE and heading not in README, heading


def test_your_images_section_and_tutorial():
    text = _section("Your own images, from Python")
    for line in (
        "images.list_frames(",
        'build_runner("model.pt", device="cuda", dtype="bfloat16")',
        "ImagePredictor(source, runner",
        "pipeline.reconstruct(predictor",
        "swiftjax view",
    ):
        assert line in text, line
    assert "(notebooks/00_your_images.ipynb)" in text and (REPO / "notebooks" / "00_your_images.ipynb").is_file()


def test_gpu_section_says_what_is_and_is_not_known():
    text = " ".join(_section("The real model and a GPU").split())
    assert "facebook/VGGT-1B" in text and "non-commercial" in text and "gated" in text
    # The GPU figures quoted are the measured ones (bench_gpu.py's latest JSON), with random weights said.
    (result,) = sorted((REPO / "bench" / "results").glob("gpu-*.json"))[-1:]
    gpu = json.loads(result.read_text())
    chunk = next(r for r in gpu["chunks"] if r["frames"] == 75)
    warm = [r for r in gpu["end_to_end"]["runs"] if r["run"] == "warm"][-1]
    assert "random weights" in text and "`python bench/bench_gpu.py`" in text
    for quoted in (
        f"{chunk['seconds']:.2f} s per chunk",
        f"{chunk['frames_per_s']:.0f} frames/s",
        f"{round(100 * chunk['aggregator_fraction_of_matmul'])} % of the measured bf16 matmul",
        f"{chunk['peak_reserved_gb']:.1f} GB reserved",
        f"{warm['frames_per_s']:.0f} frames/s warm, {warm['e2e_over_predict_only']:.2f} of the predict-only rate",
    ):
        assert quoted in text, quoted
    assert "constraints.txt" in text and "--index-url https://download.pytorch.org/whl/" in text
    pinned = re.search(r"^torch==(\S+)$", (REPO / "constraints.txt").read_text(), re.M).group(1)
    assert f"pip install torch=={pinned} --index-url" in text  # the pinned version, so the constraint holds
    assert "--dtype bfloat16" in text and "weights stay float32" in text and "heads run in float32" in text


def test_bfloat16_keeps_weights_and_heads_float32(golden_dir):
    """What the GPU section says --dtype bfloat16 does, checked on the tiny model (CPU autocast)."""
    torch = pytest.importorskip("torch")
    from inference import VGGT, VGGTConfig, load_checkpoint
    from inference.runners import TorchRunner

    model = VGGT(VGGTConfig.from_json(golden_dir / "tiny_config.json"))
    load_checkpoint(model, golden_dir / "tiny_weights.safetensors")
    runner = TorchRunner(model, dtype=torch.bfloat16)
    images = torch.rand(2, 3, 42, 70).numpy()
    out = runner.forward(images)
    assert all(p.dtype == torch.float32 for p in runner.model.parameters())
    assert out["depth"].dtype == torch.float32 and out["pose_enc"].dtype == torch.float32


def test_viewer_caption_matches_the_viewer_default():
    from swiftjax import cli

    caption = " ".join(README[README.index("![swiftjax view") :].split("\n\n")[1].split())
    budget = int(re.search(r"--max-points (\d+)", caption).group(1))
    shown = int(re.search(r"([\d,]+) of the [\d.]+ M points", caption).group(1).replace(",", ""))
    assert shown == budget
    view = cli.build_parser()._subparsers._group_actions[0].choices["view"]
    default = next(a.default for a in view._actions if "--max-points" in a.option_strings)
    assert f"the default shows {default:,}" in caption

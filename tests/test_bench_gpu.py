"""bench/bench_gpu.py --smoke: every section of the GPU benchmark runs on the CPU (tiny VGGT,
two chunks), so the script the GPU run depends on cannot rot; its numbers are checked where
they can be (FLOPs, golden, precision differences, shares)."""

from __future__ import annotations

import json
import math
import pathlib
import sys

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("cv2")

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "bench"))
pytestmark = pytest.mark.slow


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_bench_gpu_smoke_runs_every_section(tmp_path, shared_dir):
    import bench_gpu
    from flops import vggt_chunk_flops

    out = tmp_path / "gpu.json"
    results = bench_gpu.main(
        [
            "--smoke",
            "--golden",
            str(shared_dir / "golden" / "vggt"),
            "--json",
            str(out),
            "--log",
            str(tmp_path / "gpu.log"),
        ]
    )
    assert json.loads(out.read_text())["chunks"] == json.loads(json.dumps(results["chunks"], default=float))
    assert "== end to end" in (tmp_path / "gpu.log").read_text()
    config = bench_gpu.tiny_config(shared_dir / "golden" / "vggt")
    for row in results["chunks"]:
        assert row["tflop"] * 1e12 == pytest.approx(vggt_chunk_flops(config, row["frames"], 28, 42)["total"])
        assert row["seconds"] > 0 and row["tflops"] == pytest.approx(row["tflop"] / row["seconds"])
    assert results["golden"]["passed"]
    modes = {r["mode"]: r for r in results["precision_golden"]}
    assert set(modes) == {"float32", "autocast", "weights"}
    # bf16 keeps 8 bits of mantissa: depth within a few 1e-3 of float32, never identical or wild.
    for mode in ("autocast", "weights"):
        assert 0 < modes[mode]["depth_median_rel_diff"] < 2e-2
        assert math.isfinite(modes[mode]["rotation_diff_deg"])
    e2e = results["end_to_end"]
    assert e2e["chunks"] == 2 and e2e["frames"] == 10
    assert 0 < e2e["predict_share"] <= 1 and e2e["gpu_idle_share"] == pytest.approx(1 - e2e["predict_share"])
    assert {"predict", "align", "export"} <= set(e2e["stage_seconds"])
    # One reconstruction per prefetch: the first cold (the row is its), the later ones warm.
    runs = e2e["runs"]
    assert [(r["run"], r["prefetch"]) for r in runs] == [("cold", 1), ("warm", 2)]
    assert runs[0]["wall_seconds"] == e2e["wall_seconds"] and all(r["chunks"] == 2 for r in runs)
    (backbone,) = results["backbones"]
    assert backbone["model"] == "da3-small" and "error" not in backbone
    assert backbone["frames_per_s"] == pytest.approx(backbone["frames"] / backbone["seconds"])
    assert set(results["section_seconds"]) >= {"matmul", "chunks", "precision", "golden", "end_to_end", "backbones"}


def test_a_failing_section_is_recorded_and_the_next_one_runs(tmp_path):
    """On a GPU run (not --smoke) one section's exception must not lose the others: it is
    recorded as an error and the JSON is on disk after every section."""
    import bench_gpu

    out = tmp_path / "gpu.json"
    rec = bench_gpu.Recorder({}, out, tmp_path / "gpu.log", smoke=False)
    rec.section("first", lambda: 1 / 0)
    assert json.loads(out.read_text())["first"] == {"error": "ZeroDivisionError: division by zero"}
    rec.section("second", lambda: {"ok": 1})
    written = json.loads(out.read_text())
    assert written["second"] == {"ok": 1} and set(written["section_seconds"]) == {"first", "second"}
    assert "first FAILED: ZeroDivisionError" in (tmp_path / "gpu.log").read_text()

"""bench/bench_online.py --quick: the demo route replayed at 10 Hz through the live engine ends
as the offline run (poses bit for bit, every output file byte for byte), and every frame got a
pose with a finite latency of at least its own wait for the chunk's last frame."""

from __future__ import annotations

import math
import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "bench"))
pytestmark = pytest.mark.slow


def test_bench_online_quick_ends_as_offline_with_finite_latencies(capsys):
    import bench_online

    (run,) = bench_online.main(["--quick", "--no-write"])["runs"]
    assert run["identical_poses"] and run["differing_files"] == [] and run["identical"]
    B, O, fps = run["chunk_size"], run["overlap"], run["fps"]
    assert run["live_steps"] == (run["frames"] - B) // (B - O) + 1
    latencies = [run["latency_p50_s"], run["latency_p95_s"], run["latency_max_s"]]
    assert all(math.isfinite(v) for v in latencies) and latencies == sorted(latencies)
    # Frame 0 waits for frame B - 1 (at least (B - 1) / fps), plus the predictor's fixed cost.
    assert run["latency_max_s"] >= (B - 1) / fps + run["cost_s"]
    assert run["revisions"] >= 1  # the final pass at least
    assert math.isfinite(run["live_ate_m"]) and math.isfinite(run["offline_ate_m"])
    assert run["latency_final_pass_frames"] == 0 and math.isfinite(run["live_ate_end_m"])  # every frame posed live
    # the memory at every step: resident, and the live JAX arrays (data: a part of it)
    assert all(0 < s["jax_live_mb"] < s["rss_mb"] for s in run["steps"])
    assert run["jax_live_growth_mb"] == run["jax_live_last_mb"] - run["jax_live_quarter_mb"]
    assert "final = offline" in capsys.readouterr().out

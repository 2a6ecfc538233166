"""The end-of-run console (issue 26 item 9): a table that reads as a table, timings in
pipeline order and positional notation, where the outputs are and the next command, "resumed
T/T chunks" on a re-run, no empty progress bar."""

from __future__ import annotations

import re
import shutil

from swiftjax.io.tables import format_fixed, text_table
from swiftjax.pipeline.report import summary_table
from swiftjax.pipeline.rundir import StageTimer, progress_bar

SCIENTIFIC = re.compile(r"\d[eE][+-]?\d")


def test_format_fixed_is_positional():
    assert format_fixed(1.76e-05) == "0.000018"
    assert format_fixed(2e-9) == "0" and format_fixed(0.0) == "0"
    assert format_fixed(701576) == "701,576" and format_fixed(1234.5) == "1,234"
    assert format_fixed(0.18449) == "0.184" and format_fixed(13.04) == "13.0"
    for v in (1e-12, 3.3e-7, 1e20, 123456789.0, -4.2e-5):
        assert not SCIENTIFIC.search(format_fixed(v)), v


def test_text_table_aligns_columns():
    out = text_table(["head", ["a", 1], ["longer name", 1234.5], ["c", "x y"]]).splitlines()
    assert out[0] == "head"
    assert len({len(line) for line in out[1:]}) == 1  # right-aligned values end in one column
    assert out[2].split() == ["longer", "name", "1,234"]


def test_summary_reads_as_a_table_in_pipeline_order(small_loop_run):
    out, result = small_loop_run
    text = summary_table(result)
    lines = text.splitlines()
    assert "|" not in text and not SCIENTIFIC.search(text), text
    assert lines[-1] == f"next:    swiftjax view {out}"
    assert lines[-2].startswith(f"outputs: {out}  (points.ply")
    rows = lines[1 : lines.index("time per stage (s)")]
    assert len({len(r) for r in rows}) == 1, rows  # one value column
    assert any(r.split()[:1] == ["unit"] and "up to scale" in r for r in rows)
    timed = [r.rsplit(None, 1)[0].strip() for r in lines[lines.index("time per stage (s)") + 1 : -2]]
    assert timed[-1] == "total" and len(timed) >= 6
    order = list(StageTimer.ORDER)
    assert [order.index(k) for k in timed[:-1]] == sorted(order.index(k) for k in timed[:-1]), timed
    assert timed[:3] == ["predict", "align", "chunk store"] and "export" == timed[-2]
    seconds = [float(r.rsplit(None, 1)[1].replace(",", "")) for r in lines if r.strip().split()[:1] == ["total"]]
    assert abs(seconds[0] - sum(v for v in result.metrics["timings_seconds"].values() if v > 0)) < 0.02


def test_rerun_says_resumed(small_loop_run, tmp_path):
    from swiftjax import pipeline
    from swiftjax.synthetic import demo
    from swiftjax.synthetic.routes import loop_route
    from tests.conftest import SMALL_RUN_CONFIG

    out, result = small_loop_run
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    poses = loop_route(width=60.0, length=40.0, corner_radius=10.0, laps=1.3)
    run = demo.trajectory_run(poses, seed=3, image_hw=(42, 140))
    lines: list[str] = []
    pipeline.reconstruct(
        run.predictor,
        copy,
        pipeline.PipelineConfig(**SMALL_RUN_CONFIG),
        ground_truth=run.ground_truth,
        progress=False,
        log=lines.append,
    )
    T = result.num_chunks
    assert f"swiftjax: resumed {T}/{T} chunks from {copy / 'chunks'}" in lines, lines


def test_no_bar_over_nothing():
    assert progress_bar([], True) == [] and progress_bar((), True) == ()
    bar = progress_bar([1, 2], True, disable=True)
    assert type(bar).__name__ == "tqdm" or hasattr(bar, "update")

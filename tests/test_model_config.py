"""``--model-config``: validated as the options are, before the model loads (issue 25 #20)."""

from __future__ import annotations

import json

import pytest

from inference.config import VGGTConfig
from swiftjax import cli


def _golden(golden_dir):
    return json.loads((golden_dir / "tiny_config.json").read_text())


@pytest.mark.parametrize(
    "edit, fragment",
    [
        (lambda d: [d], "expected a JSON object of sections"),
        (lambda d: {**d, "aggregator_kwargs": "x"}, "aggregator_kwargs must be an object"),
        (
            lambda d: {**d, "aggregator_kwargs": {**d["aggregator_kwargs"], "num_heads": 0}},
            "num_heads must be >= 1, got 0",
        ),
        (lambda d: {**d, "camera_head_num_iterations": 0}, "camera_iterations must be >= 1, got 0"),
        (lambda d: {**d, "depth_head_frames_chunk_size": 0}, "dpt_frames_chunk_size must be >= 1, got 0"),
        (
            lambda d: {**d, "aggregator_kwargs": {**d["aggregator_kwargs"], "patch_size": 0}},
            "patch_size must be >= 1, got 0",
        ),
        (
            lambda d: {**d, "aggregator_kwargs": {**d["aggregator_kwargs"], "embed_dimm": 64}},
            "unknown key aggregator_kwargs.embed_dimm (did you mean embed_dim?)",
        ),
        (
            lambda d: {**d, "camera_head_kwarg": {}},
            "unknown key 'camera_head_kwarg' (did you mean camera_head_kwargs?)",
        ),
        (
            lambda d: {**d, "aggregator_kwargs": {**d["aggregator_kwargs"], "depth": 2.5}},
            "aggregator_kwargs.depth must be an integer",
        ),
        (
            lambda d: {**d, "aggregator_kwargs": {**d["aggregator_kwargs"], "depth": True}},
            "must be an integer, got True",
        ),
        (lambda d: {**d, "camera_head_num_iterations": "4"}, "camera_head_num_iterations must be an integer"),
    ],
)
def test_malformed_model_config_is_one_line_before_the_model_loads(capsys, tmp_path, golden_dir, edit, fragment):
    cfg = tmp_path / "model.json"
    cfg.write_text(json.dumps(edit(_golden(golden_dir))))
    with pytest.raises(ValueError, match=__import__("re").escape(fragment)):
        VGGTConfig.from_json(cfg)
    # through the CLI: the frames are fine, the weights file is a dummy never opened
    import cv2
    import numpy as np

    (tmp_path / "f").mkdir()
    for k in range(2):
        cv2.imwrite(str(tmp_path / "f" / f"{k}.png"), np.full((28, 42, 3), 9 * k, np.uint8))
    (tmp_path / "w.safetensors").write_bytes(b"not read")
    code = cli.main(
        [
            "reconstruct",
            str(tmp_path / "f"),
            "--weights",
            str(tmp_path / "w.safetensors"),
            "--model-config",
            str(cfg),
            "--out",
            str(tmp_path / "o"),
        ]
    )
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("swiftjax: error:")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert "--model-config" in lines[0] and fragment in lines[0] and "checkpoint" not in lines[0]


def test_the_golden_config_still_reads(golden_dir):
    c = VGGTConfig.from_json(golden_dir / "tiny_config.json")
    assert (c.embed_dim, c.depth, c.num_heads, c.dino_depth, c.dpt_out_channels) == (64, 6, 4, 2, (16, 32, 64, 64))

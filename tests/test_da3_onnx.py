"""DA3 through ONNX (frames axis dynamic) and onnxruntime == torch == the official golden."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")

from inference.da3 import DA3Config, NestedDA3Config, build_da3, load_da3_checkpoint
from inference.da3.onnx import DA3OnnxRunner, export_da3_onnx


@pytest.fixture(scope="module")
def da3_dir(shared_dir: pathlib.Path) -> pathlib.Path:
    return shared_dir / "golden" / "da3"


@pytest.fixture(scope="module")
def golden(da3_dir):
    return dict(np.load(da3_dir / "tiny_golden.npz"))


def rel_err(got, ref) -> float:
    got, ref = np.asarray(got, np.float64), np.asarray(ref, np.float64)
    return float(np.abs(got - ref).max() / max(np.abs(ref).max(), 1e-30))


@pytest.mark.parametrize("posed", [False, True], ids=["saddle", "pose-conditioned"])
def test_any_view_graph_equals_torch_and_golden(da3_dir, golden, tmp_path, posed):
    net = build_da3(DA3Config.from_json(da3_dir / "tiny_config.json"), device="cpu")
    load_da3_checkpoint(net, da3_dir / "tiny_weights.safetensors")
    path = export_da3_onnx(net, tmp_path / "da3.onnx", frames=3, height=42, width=70, pose_conditioned=posed)
    runner = DA3OnnxRunner(path)
    prefix = "posecond_" if posed else "saddle_"
    images = golden["images"]
    ext, intr = (golden["posecond_in_extrinsics"], golden["posecond_in_intrinsics"]) if posed else (None, None)
    out = runner.run(images, ext, intr)  # 4 frames through a graph traced with 3
    for k in ("depth", "depth_conf", "extrinsics", "intrinsics", "ray", "ray_conf", "pose_enc"):
        assert rel_err(out[k], golden[prefix + k]) < 1e-4, k
    np.testing.assert_array_equal(out["ref_view_idx"].numpy(), golden[prefix + "ref_view_idx"])
    # 5 frames (another count again) against eager torch
    x = torch.randn(1, 5, 3, 42, 70, generator=torch.Generator().manual_seed(7))
    e5 = torch.eye(4).repeat(1, 5, 1, 1)
    e5[..., :3, 3] = torch.linspace(0, 1, 15).reshape(1, 5, 3)
    k5 = torch.from_numpy(golden["posecond_in_intrinsics"][:, :1]).repeat(1, 5, 1, 1)
    with torch.no_grad():
        ref = net(x, e5 if posed else None, k5 if posed else None)
    got = runner.run(x.numpy(), e5.numpy() if posed else None, k5.numpy() if posed else None)
    for k in ("depth", "depth_conf", "extrinsics", "prealt_patch_tokens", "view_order"):
        assert rel_err(got[k], ref[k]) < 1e-4, k


def test_nested_graph_with_host_side_metric_alignment(da3_dir, golden, tmp_path):
    net = build_da3(NestedDA3Config.from_json(da3_dir / "tiny_config.json"), device="cpu")
    load_da3_checkpoint(net, da3_dir / "tiny_nested_weights.safetensors")
    path = export_da3_onnx(net, tmp_path / "nested.onnx", frames=3, height=42, width=70)
    out = DA3OnnxRunner(path).run(golden["images"])
    tol = json.loads((da3_dir / "tiny_config.json").read_text())["tolerance"]["rel_default"]
    for k in ("depth", "depth_conf", "extrinsics", "metric_depth", "metric_depth_scaled", "scale_factor"):
        assert rel_err(out[k], golden["nested_" + k]) < tol, k

"""The clean-room VGGT against the official code's golden tensors, and the 1B manifest."""

from __future__ import annotations

import json
import pathlib
from typing import Any

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from inference.check_golden import TOLERANCES, compare
from inference.checkpoint import load_checkpoint
from inference.config import VGGTConfig
from inference.model import VGGT
from inference.pose_encoding import (
    extrinsics_intrinsics_to_pose_encoding,
    pose_encoding_to_extrinsics_intrinsics,
    quat_to_mat,
)
from inference.runners import TorchRunner
from swiftjax.prediction import ChunkPrediction


@pytest.fixture(scope="module")
def golden(golden_dir: pathlib.Path) -> dict[str, np.ndarray]:
    with np.load(golden_dir / "tiny_golden.npz") as z:
        return {k: z[k] for k in z.files}


@pytest.fixture(scope="module")
def tiny_model(golden_dir: pathlib.Path) -> VGGT:
    model = VGGT(VGGTConfig.from_json(golden_dir / "tiny_config.json")).eval()
    load_checkpoint(model, golden_dir / "tiny_weights.safetensors")
    return model


@pytest.fixture(scope="module")
def traced(tiny_model: VGGT, golden: dict[str, np.ndarray]) -> dict[str, Any]:
    """One forward pass on the golden images, with the debug intermediates captured by hooks."""
    captured: dict[str, Any] = {}
    vit = tiny_model.aggregator.patch_embed
    scratch = tiny_model.depth_head.scratch
    hooks = [
        vit.register_forward_pre_hook(lambda m, a: captured.__setitem__("normalized_images", a[0])),
        vit.norm.register_forward_pre_hook(lambda m, a: captured.__setitem__("dino_x_prenorm", a[0])),
        vit.register_forward_hook(lambda m, a, o: captured.__setitem__("dino", o)),
        scratch.output_conv1.register_forward_hook(lambda m, a, o: captured.__setitem__("dpt_output_conv1", o)),
        scratch.output_conv2.register_forward_hook(lambda m, a, o: captured.__setitem__("dpt_output_conv2_raw", o)),
    ]
    try:
        with torch.no_grad():
            out = tiny_model(torch.from_numpy(golden["images"]), return_aggregated=True)
    finally:
        for h in hooks:
            h.remove()
    return {"out": out, **captured}


# ---------------------------------------------------------------------------------------------
# config


def test_config_defaults_are_the_1b_model() -> None:
    cfg = VGGTConfig()
    assert (cfg.embed_dim, cfg.depth, cfg.num_heads, cfg.dino_depth, cfg.dino_num_heads) == (1024, 24, 16, 24, 16)
    assert cfg.dpt_intermediate_layer_idx == (4, 11, 17, 23)
    assert cfg.dpt_out_channels == (256, 512, 1024, 1024) and cfg.dpt_features == 256
    assert cfg.patch_start_idx == 5 and cfg.pos_embed_grid == 37


def test_config_from_json(golden_dir: pathlib.Path) -> None:
    cfg = VGGTConfig.from_json(golden_dir / "tiny_config.json")
    assert (cfg.embed_dim, cfg.depth, cfg.num_heads, cfg.num_register_tokens) == (64, 6, 4, 4)
    assert (cfg.dino_depth, cfg.dino_num_heads) == (2, 4)
    assert (cfg.camera_trunk_depth, cfg.camera_num_heads, cfg.camera_iterations) == (4, 4, 4)
    assert (cfg.dpt_features, cfg.dpt_out_channels, cfg.dpt_intermediate_layer_idx) == (
        32,
        (16, 32, 64, 64),
        (1, 3, 4, 5),
    )
    assert cfg.rope_freq == 100 and cfg.qk_norm and cfg.aa_order == ("frame", "global")


def test_config_refuses_what_it_cannot_build(golden_dir: pathlib.Path) -> None:
    raw = json.loads((golden_dir / "tiny_config.json").read_text())
    raw["aggregator_kwargs"]["qkv_bias"] = False
    with pytest.raises(ValueError, match="qkv_bias"):
        VGGTConfig.from_dict(raw)
    with pytest.raises(ValueError, match="num_heads"):
        VGGTConfig(embed_dim=64, num_heads=5)
    with pytest.raises(ValueError, match="dpt_intermediate_layer_idx"):
        VGGTConfig(depth=4, dpt_intermediate_layer_idx=(1, 2, 3, 4))


# ---------------------------------------------------------------------------------------------
# parameter names and shapes


def test_tiny_state_dict_order_equals_official(golden_dir: pathlib.Path, tiny_model: VGGT) -> None:
    official = json.loads((golden_dir / "tiny_config.json").read_text())["state_dict_keys_in_order"]
    assert list(tiny_model.state_dict()) == official


def test_1b_state_dict_equals_manifest(golden_dir: pathlib.Path) -> None:
    manifest = json.loads((golden_dir / "vggt_1b_state_dict_manifest.json").read_text())
    heads = ("aggregator.", "camera_head.", "depth_head.")
    expected = [(n, tuple(s), d) for n, s, d in manifest["entries"] if n.startswith(heads)]
    with torch.device("meta"):
        model = VGGT()
    got = [(n, tuple(t.shape), str(t.dtype).replace("torch.", "")) for n, t in model.state_dict().items()]
    assert got == expected  # names, shapes, dtypes and order
    numel = {
        top: sum(int(np.prod(s)) for n, s, _ in got if n.startswith(top + "."))
        for top in ("aggregator", "camera_head", "depth_head")
    }
    assert numel == {k: v for k, v in manifest["numel_per_top_level_module"].items() if k in numel}
    assert numel["aggregator"] == 909_112_320
    assert dict(model.named_buffers()) == {}  # ImageNet mean/std are not state


# ---------------------------------------------------------------------------------------------
# golden forward


@pytest.mark.parametrize(
    "name",
    [
        "patch_tokens",
        "aggregated_tokens_all",
        "aggregated_tokens_dpt",
        "pose_enc",
        "pose_enc_list",
        "depth",
        "depth_conf",
    ],
)
def test_golden_outputs(traced: dict[str, Any], golden: dict[str, np.ndarray], tiny_model: VGGT, name: str) -> None:
    out = traced["out"]
    agg = torch.stack(out["aggregated_tokens"]).numpy()
    got = {
        "patch_tokens": out["patch_tokens"].numpy(),
        "aggregated_tokens_all": agg,
        "aggregated_tokens_dpt": agg[list(tiny_model.config.dpt_intermediate_layer_idx)],
        "pose_enc": out["pose_enc"].numpy(),
        "pose_enc_list": torch.stack(out["pose_enc_list"]).numpy(),
        "depth": out["depth"].numpy(),
        "depth_conf": out["depth_conf"].numpy(),
    }[name]
    check = compare("torch", name, got, golden[name])
    assert check.passed, check
    atol, rtol = TOLERANCES[name]
    np.testing.assert_allclose(got, golden[name], atol=atol, rtol=rtol)


def test_golden_intermediates(traced: dict[str, Any], golden: dict[str, np.ndarray], tiny_model: VGGT) -> None:
    b, s, _, h, w = golden["images"].shape
    np.testing.assert_allclose(
        traced["normalized_images"].numpy().reshape(b, s, 3, h, w), golden["normalized_images"], atol=1e-6
    )
    pos = tiny_model.aggregator.patch_embed.interpolate_pos_encoding(h // 14, w // 14).detach().numpy()
    np.testing.assert_allclose(pos, golden["dino_pos_embed_interpolated"], atol=1e-6)
    dino = traced["dino"]
    t = dino["x_prenorm"].shape[1]
    np.testing.assert_allclose(
        traced["dino_x_prenorm"].numpy().reshape(b, s, t, -1), golden["dino_x_prenorm"], atol=1e-5
    )
    np.testing.assert_allclose(
        dino["x_norm_clstoken"].numpy().reshape(b, s, -1), golden["dino_x_norm_clstoken"], atol=1e-5
    )
    np.testing.assert_allclose(
        dino["x_norm_regtokens"].numpy().reshape(b, s, 4, -1), golden["dino_x_norm_regtokens"], atol=1e-5
    )
    conv1 = traced["dpt_output_conv1"].numpy()
    np.testing.assert_allclose(
        conv1.reshape(golden["dpt_output_conv1"].shape), golden["dpt_output_conv1"], atol=1e-4, rtol=1e-4
    )
    raw = traced["dpt_output_conv2_raw"].numpy()
    np.testing.assert_allclose(
        raw.reshape(golden["dpt_output_conv2_raw"].shape), golden["dpt_output_conv2_raw"], atol=1e-5
    )


def test_depth_head_chunking_matches_single_pass(tiny_model: VGGT, golden: dict[str, np.ndarray]) -> None:
    x = torch.from_numpy(golden["images"])
    with torch.no_grad():
        one = tiny_model(x, frames_chunk_size=None)
        chunked = tiny_model(x, frames_chunk_size=2)  # chunks of 2 + 1 frames
    np.testing.assert_allclose(chunked["depth"].numpy(), one["depth"].numpy(), rtol=1e-5)
    np.testing.assert_allclose(chunked["depth_conf"].numpy(), one["depth_conf"].numpy(), rtol=1e-5)


def test_model_rejects_image_size_not_multiple_of_patch(tiny_model: VGGT) -> None:
    with pytest.raises(ValueError, match="multiples of 14"):
        tiny_model(torch.zeros(1, 2, 3, 42, 71))


def test_meta_model_loads_by_assignment(golden_dir: pathlib.Path, golden: dict[str, np.ndarray]) -> None:
    with torch.device("meta"):
        model = VGGT(VGGTConfig.from_json(golden_dir / "tiny_config.json"))
    load_checkpoint(model, golden_dir / "tiny_weights.safetensors")
    with torch.no_grad():
        pose = model.eval()(torch.from_numpy(golden["images"]))["pose_enc"].numpy()
    np.testing.assert_allclose(pose, golden["pose_enc"], atol=1e-5)


# ---------------------------------------------------------------------------------------------
# runner


def test_torch_runner_returns_chunk_prediction(tiny_model: VGGT, golden: dict[str, np.ndarray]) -> None:
    images = golden["images"][0]
    pred = TorchRunner(tiny_model, "cpu").predict(images)
    assert isinstance(pred, ChunkPrediction)
    s, _, h, w = images.shape
    assert pred.depth.shape == (s, h, w) and pred.depth.dtype == np.float32
    np.testing.assert_allclose(pred.depth, golden["depth"][0, ..., 0], rtol=1e-4)
    np.testing.assert_allclose(pred.conf, golden["depth_conf"][0], rtol=1e-4)
    np.testing.assert_allclose(pred.extrinsic, golden["extrinsic"][0], atol=1e-5)
    np.testing.assert_allclose(pred.intrinsic, golden["intrinsic"][0], rtol=1e-5)
    np.testing.assert_allclose(pred.patch_tokens, golden["patch_tokens"][0], atol=1e-5)
    assert pred.images is not None and pred.images.dtype == np.uint8 and pred.images.shape == (s, h, w, 3)
    np.testing.assert_array_equal(pred.images, np.round(images.transpose(0, 2, 3, 1) * 255).astype(np.uint8))


def test_torch_runner_bfloat16_autocast(tiny_model: VGGT, golden: dict[str, np.ndarray]) -> None:
    runner = TorchRunner(tiny_model, "cpu", dtype=torch.bfloat16)
    out = runner.forward(golden["images"][0])
    assert out["pose_enc"].dtype == torch.float32 and out["depth"].dtype == torch.float32  # heads stay fp32
    for name in ("pose_enc", "depth", "depth_conf", "patch_tokens"):
        got, ref = out[name].float().numpy(), golden[name]
        err = np.abs(got - ref).max() / np.abs(ref).max()
        assert 0 < err < 0.02, (name, err)  # really ran in bf16, and still close
    assert all(p.dtype == torch.float32 for p in tiny_model.parameters())


# ---------------------------------------------------------------------------------------------
# pose encoding


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_pose_encoding_matches_golden(golden: dict[str, np.ndarray], backend: str) -> None:
    hw = tuple(int(v) for v in golden["image_size_hw"])
    pose = golden["pose_enc"] if backend == "numpy" else torch.from_numpy(golden["pose_enc"])
    ext, intr = pose_encoding_to_extrinsics_intrinsics(pose, hw)
    ext, intr = np.asarray(ext), np.asarray(intr)
    assert ext.dtype == np.float32 and intr.dtype == np.float32
    np.testing.assert_allclose(ext, golden["extrinsic"], atol=1e-6)
    np.testing.assert_allclose(intr, golden["intrinsic"], rtol=1e-6)
    h, w = hw
    np.testing.assert_array_equal(intr[..., 0, 2], w / 2)  # principal point at the centre, not (W-1)/2
    np.testing.assert_array_equal(intr[..., 1, 2], h / 2)
    fx = (w / 2) / np.tan(golden["pose_enc"][..., 8] / 2)  # fx from fov_w (index 8), fy from fov_h (7)
    np.testing.assert_allclose(intr[..., 0, 0], fx, rtol=1e-6)


def test_pose_encoding_round_trip() -> None:
    rng = np.random.default_rng(0)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    enc = np.concatenate([rng.normal(size=(50, 3)), q, rng.uniform(0.3, 2.0, size=(50, 2))], axis=-1)
    ext, intr = pose_encoding_to_extrinsics_intrinsics(enc, (154, 518))
    r = ext[:, :, :3]
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    np.testing.assert_allclose(extrinsics_intrinsics_to_pose_encoding(ext, intr, (154, 518)), enc, atol=1e-10)


def test_quat_to_mat_is_xyzw_and_scale_invariant() -> None:
    half = np.pi / 4  # 90 degrees about z, XYZW
    q = np.array([0.0, 0.0, np.sin(half), np.cos(half)])
    np.testing.assert_allclose(quat_to_mat(q), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(quat_to_mat(3.0 * q), quat_to_mat(q), atol=1e-12)


def test_aggregator_keeps_only_requested_outputs(tiny_model: VGGT, golden: dict[str, np.ndarray]) -> None:
    with torch.no_grad():
        out = tiny_model.aggregator(torch.from_numpy(golden["images"]), keep=(1, -1))
    kept = [i for i, t in enumerate(out["tokens"]) if t is not None]
    assert kept == [1, 5]
    np.testing.assert_allclose(out["tokens"][5].numpy(), golden["aggregated_tokens_all"][5], atol=1e-5)

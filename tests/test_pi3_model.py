"""The clean-room π³ / π³X against the official code's golden tensors, manifests, strict loading."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from inference.checkpoint import CheckpointError
from inference.pi3.checkpoint import load_pi3_checkpoint
from inference.pi3.config import Pi3Config
from inference.pi3.golden import PI3X_RUNS, compare, golden_conditions, torch_outputs
from inference.pi3.model import Pi3
from inference.pi3.pi3x import Pi3X


@pytest.fixture(scope="module")
def golden_dir(pi3_golden_dir: pathlib.Path) -> pathlib.Path:
    return pi3_golden_dir


def _npz(path: pathlib.Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


@pytest.fixture(scope="module")
def pi3(golden_dir: pathlib.Path) -> Pi3:
    model = Pi3(Pi3Config.from_json(golden_dir / "tiny_config.json", "pi3")).eval()
    load_pi3_checkpoint(model, golden_dir / "tiny_weights.safetensors")
    return model


@pytest.fixture(scope="module")
def pi3x(golden_dir: pathlib.Path) -> Pi3X:
    model = Pi3X(Pi3Config.from_json(golden_dir / "tiny_config.json", "pi3x")).eval()
    load_pi3_checkpoint(model, golden_dir / "tiny_weights_pi3x.safetensors")
    return model


@pytest.fixture(scope="module")
def pi3_run(pi3: Pi3, golden_dir: pathlib.Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    golden = _npz(golden_dir / "tiny_golden.npz")
    return torch_outputs(pi3, golden, None), golden


@pytest.fixture(scope="module")
def pi3x_runs(pi3x: Pi3X, golden_dir: pathlib.Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    golden = _npz(golden_dir / "tiny_golden_pi3x.npz")
    out: dict[str, np.ndarray] = {}
    for run in PI3X_RUNS:
        out.update(torch_outputs(pi3x, golden, run))
    return out, golden


PI3_KEYS = [
    "points",
    "local_points",
    "conf",
    "camera_poses",
    "encoder_input_normalized",
    "dino_patch_tokens",
    *[f"decoder_layer_{i:02d}" for i in range(10)],
    "decode_hidden_concat",
    "decode_pos",
    "point_decoder_out",
    "conf_decoder_out",
    "camera_decoder_out",
]


@pytest.mark.parametrize("key", PI3_KEYS)
def test_pi3_equals_official_golden(pi3_run, key: str) -> None:
    out, golden = pi3_run
    assert key in golden
    check = compare("torch", key, out[key], golden[key])
    assert check.passed, check


def test_pi3_covers_every_golden_key(pi3_run) -> None:
    out, golden = pi3_run
    assert set(golden) - {"input_imgs", "forward_input_imgs"} <= set(out)
    assert set(PI3_KEYS) == set(golden) - {"input_imgs", "forward_input_imgs"}


@pytest.mark.parametrize("run", PI3X_RUNS)
def test_pi3x_every_key_equals_official_golden(pi3x_runs, run: str) -> None:
    out, golden = pi3x_runs
    keys = [k for k in golden if k.startswith(f"{run}.") and ".cond_input." not in k]
    assert len(keys) > 20
    checks = [compare("torch", k, out[k], golden[k]) if k in out else k for k in keys]
    failed = [c for c in checks if isinstance(c, str) or not c.passed]
    assert not failed, failed


@pytest.mark.parametrize("run", PI3X_RUNS)
def test_pi3x_conditioning_changes_the_output(pi3x_runs, run: str) -> None:
    """The conditioned runs differ from the unconditioned one (the paths are not no-ops), and
    their intermediates of the conditioning itself match the official ones."""
    out, golden = pi3x_runs
    if run == "uncond":
        assert "uncond.pose_inject_0_out" not in out
        np.testing.assert_array_equal(out["uncond.encode_norm_factor"], [1.0])
        return
    for key in (
        "ray_embed_out",
        "depth_encoder_patch_tokens",
        "pose_inject_0_out",
        "pose_inject_1_out",
        "encode_poses_normalized",
        "encode_norm_factor",
        "encode_hidden",
    ):
        assert compare("torch", key, out[f"{run}.{key}"], golden[f"{run}.{key}"]).passed
    assert np.abs(out[f"{run}.points"] - out["uncond.points"]).max() > 1e-3


def test_partial_pose_mask_only_moves_posed_views(pi3x, golden_dir) -> None:
    """Injection adds the delta to the posed views only (condpartial: view 3 unposed)."""
    golden = _npz(golden_dir / "tiny_golden_pi3x.npz")
    trace: dict[str, torch.Tensor] = {}
    with torch.no_grad():
        pi3x(torch.from_numpy(golden["input_imgs"]), golden_conditions(golden, "condpartial"), trace=trace)
    before, after = trace["decoder_layer_01"], trace["decoder_layer_02"]
    assert before.shape == after.shape
    # layer 2 is frame-wise: view 3's output depends only on view 3's (un-injected) input.
    cond = golden_conditions(golden, "condpartial")
    cond.mask_pose = torch.zeros_like(cond.mask_pose)
    trace0: dict[str, torch.Tensor] = {}
    with torch.no_grad():
        pi3x(torch.from_numpy(golden["input_imgs"]), cond, trace=trace0)
    torch.testing.assert_close(trace["decoder_layer_02"][3], trace0["decoder_layer_02"][3], rtol=0, atol=1e-6)
    assert (trace["decoder_layer_02"][:3] - trace0["decoder_layer_02"][:3]).abs().max() > 1e-4


# ---- full-size presets vs the official manifests -------------------------------------------


@pytest.mark.parametrize(
    "preset,manifest,params",
    [
        ("pi3", "manifest_pi3.json", 958_696_732),
        ("pi3x", "manifest_pi3x.json", 1_360_032_433),
    ],
)
def test_preset_matches_manifest_on_meta(golden_dir, preset: str, manifest: str, params: int) -> None:
    with open(golden_dir / manifest, encoding="utf-8") as f:
        entries = {name: tuple(shape) for name, shape, _ in json.load(f)["entries"]}
    cfg = Pi3Config.preset(preset)
    with torch.device("meta"):
        model = (Pi3 if preset == "pi3" else Pi3X)(cfg)
    state = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert set(state) == set(entries), (sorted(set(state) - set(entries))[:5], sorted(set(entries) - set(state))[:5])
    assert state == entries
    assert sum(p.numel() for p in model.parameters()) == params


def test_pi3x_without_multimodal_drops_exactly_the_multimodal_parts(golden_dir) -> None:
    with torch.device("meta"):
        model = Pi3X(Pi3Config.pi3x(multimodal=False))
    assert sum(p.numel() for p in model.parameters()) == 992_465_329  # README: without multimodal parts


# ---- strict loading ----------------------------------------------------------------------------


def test_load_refuses_pickles(tmp_path, golden_dir) -> None:
    model = Pi3(Pi3Config.from_json(golden_dir / "tiny_config.json", "pi3"))
    path = tmp_path / "model.pt"
    torch.save(model.state_dict(), path)
    with pytest.raises(CheckpointError, match="safetensors only"):
        load_pi3_checkpoint(model, path)


def test_load_refuses_the_other_variant_listing_keys(golden_dir) -> None:
    model = Pi3(Pi3Config.from_json(golden_dir / "tiny_config.json", "pi3"))
    with pytest.raises(CheckpointError, match=r"\d+ unexpected key\(s\):\n    conf_head\.output_block") as e:
        load_pi3_checkpoint(model, golden_dir / "tiny_weights_pi3x.safetensors")
    # π³'s linear heads are not in the π³X file
    assert "4 missing key(s):\n    point_head.proj.weight" in str(e.value)


def test_load_refuses_missing_and_misshapen(tmp_path, golden_dir) -> None:
    from safetensors.torch import load_file, save_file

    state = load_file(str(golden_dir / "tiny_weights.safetensors"))
    model = Pi3(Pi3Config.from_json(golden_dir / "tiny_config.json", "pi3"))
    broken = dict(state)
    del broken["decoder.3.attn.qkv.weight"]
    broken["register_token"] = torch.zeros(1, 1, 4, 32)
    save_file(broken, str(tmp_path / "broken.safetensors"))
    with pytest.raises(CheckpointError) as e:
        load_pi3_checkpoint(model, tmp_path / "broken.safetensors")
    msg = str(e.value)
    assert "1 missing key(s):\n    decoder.3.attn.qkv.weight" in msg
    assert "register_token: checkpoint (1, 1, 4, 32) vs model (1, 1, 5, 32)" in msg


def test_pi3x_file_without_image_normalisation_loads(tmp_path, golden_dir) -> None:
    """The released π³X file may lack image_mean/std (upstream loads it non-strictly)."""
    from safetensors.torch import load_file, save_file

    state = load_file(str(golden_dir / "tiny_weights_pi3x.safetensors"))
    del state["image_mean"], state["image_std"]
    save_file(state, str(tmp_path / "x.safetensors"))
    for device in ("cpu", "meta"):
        with torch.device(device):
            model = Pi3X(Pi3Config.from_json(golden_dir / "tiny_config.json", "pi3x"))
        load_pi3_checkpoint(model, tmp_path / "x.safetensors")
        torch.testing.assert_close(model.image_std.flatten(), torch.tensor([0.229, 0.224, 0.225]))
        assert not any(t.is_meta for t in model.state_dict().values())


def test_pi3x_without_multimodal_skips_those_entries(golden_dir) -> None:
    cfg = Pi3Config.from_json(golden_dir / "tiny_config.json", "pi3x")
    import dataclasses

    model = Pi3X(dataclasses.replace(cfg, multimodal=False)).eval()
    report = load_pi3_checkpoint(model, golden_dir / "tiny_weights_pi3x.safetensors")
    assert report.ignored and all(k.startswith(("depth_", "ray_embed", "pose_inject")) for k in report.ignored)
    golden = _npz(golden_dir / "tiny_golden_pi3x.npz")
    with torch.no_grad():
        out = model(torch.from_numpy(golden["input_imgs"]))
    assert compare("torch", "points", out["points"].numpy(), golden["uncond.points"]).passed


def test_meta_model_gets_the_checkpoint_assigned(golden_dir) -> None:
    cfg = Pi3Config.from_json(golden_dir / "tiny_config.json", "pi3")
    with torch.device("meta"):
        model = Pi3(cfg)
    load_pi3_checkpoint(model, golden_dir / "tiny_weights.safetensors")
    assert not any(t.is_meta for t in model.state_dict().values())


def test_pi3x_batch_of_scenes_equals_each_scene_alone(pi3x, golden_dir) -> None:
    """B = 2 (the golden scene and a flipped copy, each with its own conditions) gives every
    scene's own outputs: per-scene normalisation, metric token and pose masks."""
    import dataclasses

    golden = _npz(golden_dir / "tiny_golden_pi3x.npz")
    imgs = torch.from_numpy(golden["input_imgs"])
    c = golden_conditions(golden, "condpartial")
    other = dataclasses.replace(c, depths=c.depths.flip(-1) * 2.0, mask_pose=torch.tensor([[True, True, False, False]]))
    both = dataclasses.replace(
        c,
        **{
            f: torch.cat([getattr(c, f), getattr(other, f)])
            for f in ("intrinsics", "depths", "poses", "mask_depth", "mask_ray", "mask_pose")
        },
    )
    with torch.no_grad():
        batch = pi3x(torch.cat([imgs, imgs.flip(-1)]), both)
        first = pi3x(imgs, c)
        second = pi3x(imgs.flip(-1), other)
    for key in ("points", "conf", "camera_poses", "metric"):
        torch.testing.assert_close(batch[key][:1], first[key], atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(batch[key][1:], second[key], atol=1e-4, rtol=1e-4)


def test_svd_orthogonalize_is_float32_rotation_under_bf16_autocast() -> None:
    """The pose head's orthogonalisation runs outside autocast (a bf16 ``det`` has no CUDA
    kernel; a bf16 product would leave R off orthonormal by ~1e-2): under a bf16 autocast it
    gives the float32 call's rotation, orthonormal to float32 rounding, also from bf16 input."""
    from inference.pi3.heads import svd_orthogonalize

    m = torch.randn(5, 9, generator=torch.Generator().manual_seed(3))
    ref = svd_orthogonalize(m)
    with torch.autocast(device_type="cpu", dtype=torch.bfloat16):
        got = svd_orthogonalize(m)
        from_bf16 = svd_orthogonalize(m.bfloat16())
    assert got.dtype == from_bf16.dtype == torch.float32
    assert torch.equal(got, ref)
    eye = torch.eye(3).expand(5, 3, 3)
    torch.testing.assert_close(got @ got.transpose(-1, -2), eye, atol=2e-6, rtol=0)
    torch.testing.assert_close(torch.det(got), torch.ones(5), atol=2e-6, rtol=0)

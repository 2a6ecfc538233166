"""Strict loading of DA3 checkpoints in the official layout, and every preset on ``meta``."""

from __future__ import annotations

import json
import pathlib

import pytest
import torch
from safetensors.torch import load_file, save_file

from inference.checkpoint import CheckpointError
from inference.da3 import PRESETS, DA3Config, NestedDA3Config, build_da3, load_da3_checkpoint
from inference.da3.checkpoint import alias_groups, expected_checkpoint_keys

ALIAS = "model.head.scratch.output_conv2_aux.{}.2.weight"


@pytest.fixture(scope="module")
def da3_dir(shared_dir: pathlib.Path) -> pathlib.Path:
    return shared_dir / "golden" / "da3"


@pytest.fixture(scope="module")
def tiny_state(da3_dir) -> dict[str, torch.Tensor]:
    return load_file(str(da3_dir / "tiny_weights.safetensors"))


def tiny(da3_dir, device="cpu"):
    return build_da3(DA3Config.from_json(da3_dir / "tiny_config.json"), device=device)


def write(tmp_path, state, name="w.safetensors") -> pathlib.Path:
    path = tmp_path / name
    save_file({k: v.contiguous() for k, v in state.items()}, str(path))
    return path


def test_official_file_loads_and_fills_the_six_aliases(da3_dir, tiny_state):
    absent = json.loads((da3_dir / "tiny_config.json").read_text())["alias_names_absent_from_files"]
    main_absent = [k for k in absent if not k.startswith("model.da3.")]
    assert len(main_absent) == 6 and not set(main_absent) & set(tiny_state)
    net = tiny(da3_dir)
    load_da3_checkpoint(net, da3_dir / "tiny_weights.safetensors")
    sd = net.state_dict()
    for k in range(4):  # one shared LayerNorm under four names, equal to the stored .0.2 tensor
        assert torch.equal(sd[ALIAS.format(k)[len("model.") :]], tiny_state[ALIAS.format(0)])
    assert sd[ALIAS.format(3)[6:]].data_ptr() == sd[ALIAS.format(0)[6:]].data_ptr()
    assert sorted(expected_checkpoint_keys(net)) == sorted(tiny_state)


def test_meta_build_loads_by_assignment(da3_dir, tiny_state):
    net = tiny(da3_dir, device="meta")
    load_da3_checkpoint(net, da3_dir / "tiny_weights.safetensors")
    assert not any(t.is_meta for t in net.state_dict().values())
    assert net.head.scratch.output_conv2_aux[1][2] is net.head.scratch.output_conv2_aux[0][2]
    ref = tiny(da3_dir)
    load_da3_checkpoint(ref, da3_dir / "tiny_weights.safetensors")
    x = torch.randn(1, 3, 3, 28, 42, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        torch.testing.assert_close(net(x)["depth"], ref(x)["depth"], rtol=0, atol=0)


def test_nested_file_loads(da3_dir):
    net = build_da3(NestedDA3Config.from_json(da3_dir / "tiny_config.json"), device="meta")
    report = load_da3_checkpoint(net, da3_dir / "tiny_nested_weights.safetensors")
    assert report.loaded == len(load_file(str(da3_dir / "tiny_nested_weights.safetensors")))


def test_aliases_present_and_equal_are_accepted(da3_dir, tiny_state, tmp_path):
    state = dict(tiny_state)
    for k in (1, 2, 3):
        state[ALIAS.format(k)] = state[ALIAS.format(0)].clone()
        state[ALIAS.format(k).replace("weight", "bias")] = state[ALIAS.format(0).replace("weight", "bias")].clone()
    load_da3_checkpoint(tiny(da3_dir), write(tmp_path, state))


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s.pop("model.cam_dec.fc_t.weight"), "1 missing key(s): model.cam_dec.fc_t.weight"),
        (
            lambda s: s.update({"model.head.extra.weight": torch.zeros(2)}),
            "1 unexpected key(s): model.head.extra.weight",
        ),
        (lambda s: s.update({"model.cam_dec.fc_t.bias": torch.zeros(4)}), "model.cam_dec.fc_t.bias (4,) vs model (3,)"),
        (lambda s: s.update({ALIAS.format(2): s[ALIAS.format(0)] + 1}), "alias(es) differing"),
        (lambda s: s.pop(ALIAS.format(0)), "missing key(s): model.head.scratch.output_conv2_aux.0.2.weight"),
    ],
    ids=["missing", "extra", "shape", "alias-conflict", "kept-alias-missing"],
)
def test_strict_refusals_name_the_keys(da3_dir, tiny_state, tmp_path, edit, message):
    state = dict(tiny_state)
    edit(state)
    with pytest.raises(CheckpointError) as e:
        load_da3_checkpoint(tiny(da3_dir), write(tmp_path, state))
    assert message in str(e.value) and "\n" not in str(e.value)


def test_wrong_prefix_is_refused(da3_dir, tiny_state, tmp_path):
    state = {k[len("model.") :]: v for k, v in tiny_state.items()}  # a bare network state_dict
    with pytest.raises(CheckpointError, match="no key starts with 'model.'"):
        load_da3_checkpoint(tiny(da3_dir), write(tmp_path, state))
    state = {"module." + k: v for k, v in tiny_state.items()}
    with pytest.raises(CheckpointError, match="unexpected key"):
        load_da3_checkpoint(tiny(da3_dir), write(tmp_path, state))


def test_any_view_file_into_nested_model_is_refused(da3_dir):
    net = build_da3(NestedDA3Config.from_json(da3_dir / "tiny_config.json"), device="meta")
    with pytest.raises(CheckpointError, match="missing key"):
        load_da3_checkpoint(net, da3_dir / "tiny_weights.safetensors")


def test_truncated_file_and_pickles_are_refused(da3_dir, tmp_path):
    data = (da3_dir / "tiny_weights.safetensors").read_bytes()
    (tmp_path / "cut.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_da3_checkpoint(tiny(da3_dir), tmp_path / "cut.safetensors")
    (tmp_path / "w.pt").write_bytes(b"PK\x03\x04")
    with pytest.raises(CheckpointError, match="only .safetensors"):
        load_da3_checkpoint(tiny(da3_dir), tmp_path / "w.pt")


@pytest.mark.parametrize("preset", list(PRESETS))
def test_preset_builds_on_meta_with_the_manifest(da3_dir, preset):
    manifest = json.loads((da3_dir / f"manifest_{preset}.json").read_text())
    cfg = PRESETS[preset]
    resolved = manifest["resolved_config"]
    parsed = (
        NestedDA3Config.from_object_config(resolved)
        if "anyview" in resolved
        else DA3Config.from_object_config(resolved)
    )
    assert parsed == cfg  # the hard-coded preset is the official yaml
    net = build_da3(preset)
    got = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    want = {name: tuple(shape) for name, shape, _ in manifest["entries"]}
    # Names and shapes exactly (loading is by name; only the registration order inside the
    # fusion blocks, shared with VGGT's, differs from the official state_dict order).
    assert got == want, sorted(set(got) ^ set(want))[:10]
    assert sum(p.numel() for p in net.parameters()) == manifest["total_params"]
    assert len(expected_checkpoint_keys(net)) == manifest["expected_checkpoint_keys_count"]
    dropped = {("model." + n) for g in alias_groups(net) for n in g[1:]}
    assert dropped == set(manifest["checkpoint_alias_names_absent"])

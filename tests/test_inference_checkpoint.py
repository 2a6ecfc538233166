"""Checkpoint loading: formats, strict key checking, and refusal of bad or unsafe files."""

from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest

torch = pytest.importorskip("torch")
from safetensors.torch import save_file

from inference.checkpoint import CheckpointError, load_checkpoint, read_state_dict
from inference.config import VGGTConfig
from inference.model import VGGT

# A very small model: every test builds its own copy in milliseconds.
SMALL = VGGTConfig(
    embed_dim=32,
    depth=2,
    num_heads=2,
    dino_depth=1,
    dino_num_heads=2,
    camera_trunk_depth=1,
    camera_num_heads=2,
    dpt_features=16,
    dpt_out_channels=(8, 8, 16, 16),
    dpt_intermediate_layer_idx=(0, 1, 1, 1),
)


def _model(seed: int = 0) -> VGGT:
    torch.manual_seed(seed)
    return VGGT(SMALL)


def _state(seed: int = 0) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in _model(seed).state_dict().items()}


def _assert_same_weights(model: VGGT, state: dict[str, torch.Tensor]) -> None:
    got = model.state_dict()
    assert set(got) == set(state)
    for k, v in state.items():
        assert torch.equal(got[k], v), k


@pytest.mark.parametrize("suffix", [".safetensors", ".pt", ".pth"])
def test_round_trip(tmp_path: pathlib.Path, suffix: str) -> None:
    state = _state(1)
    path = tmp_path / f"w{suffix}"
    save_file(state, path) if suffix == ".safetensors" else torch.save(state, path)
    model = _model(0)
    report = load_checkpoint(model, path)
    assert report.loaded == len(state) and report.ignored == ()
    _assert_same_weights(model, state)


def test_wrapped_state_dict_and_ignored_heads(tmp_path: pathlib.Path) -> None:
    state = _state(1)
    extra = {"point_head.norm.weight": torch.ones(3), "track_head.tracker.x": torch.zeros(2, 2)}
    path = tmp_path / "model.pt"
    torch.save({"model": {**state, **extra}}, path)
    model = _model(0)
    report = load_checkpoint(model, path)
    assert sorted(report.ignored) == sorted(extra)
    _assert_same_weights(model, state)


def test_missing_file() -> None:
    with pytest.raises(FileNotFoundError, match="VGGT checkpoint not found"):
        load_checkpoint(_model(), "/nonexistent/model.pt")


def test_wrong_keys_are_all_listed(tmp_path: pathlib.Path) -> None:
    state = _state(1)
    state["aggregator.camera_tokens"] = state.pop("aggregator.camera_token")  # renamed
    del state["depth_head.scratch.output_conv2.2.bias"]  # missing
    state["depth_head.norm.weight"] = torch.ones(7)  # wrong shape
    path = tmp_path / "w.safetensors"
    save_file(state, path)
    model = _model(0)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(model, path)
    msg = str(err.value)
    assert "2 missing key(s)" in msg and "aggregator.camera_token\n" in msg
    assert "depth_head.scratch.output_conv2.2.bias" in msg
    assert "1 unexpected key(s)" in msg and "aggregator.camera_tokens" in msg
    assert "1 shape mismatch key(s)" in msg and "depth_head.norm.weight: checkpoint (7,) vs model (64,)" in msg
    _assert_same_weights(model, before)  # nothing was half-loaded


def test_config_mismatch_is_reported(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "w.safetensors"
    save_file(_state(), path)
    with pytest.raises(CheckpointError, match="shape mismatch") as err:
        load_checkpoint(VGGT(VGGTConfig(**{**SMALL.to_dict(), "dpt_features": 8})), path)
    assert "is the model config the one" in str(err.value)


@pytest.mark.parametrize("suffix", [".safetensors", ".pt"])
def test_truncated_file(tmp_path: pathlib.Path, suffix: str) -> None:
    path = tmp_path / f"w{suffix}"
    state = _state()
    save_file(state, path) if suffix == ".safetensors" else torch.save(state, path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_checkpoint(_model(), path)


def test_garbage_file(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "w.safetensors"
    path.write_bytes(b"\x00" * 3)
    with pytest.raises(CheckpointError):
        read_state_dict(path)


class _Exploit:
    """Pickles to a call of os.system: loading it with plain pickle would run a command."""

    def __init__(self, marker: pathlib.Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (os.system, (f"touch {self.marker}",))


def test_malicious_pickle_is_refused(tmp_path: pathlib.Path) -> None:
    marker = tmp_path / "pwned"
    path = tmp_path / "model.pt"
    torch.save({"aggregator.camera_token": torch.zeros(1), "evil": _Exploit(marker)}, path)
    with pytest.raises(CheckpointError, match="refused to load") as err:
        load_checkpoint(_model(), path)
    assert "system" in str(err.value)  # names the forbidden global
    assert not marker.exists()


def test_not_a_state_dict(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "model.pt"
    torch.save([torch.zeros(2)], path)
    with pytest.raises(CheckpointError, match="does not hold a state_dict"):
        load_checkpoint(_model(), path)


def test_unknown_suffix(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "model.npz"
    np.savez(path, a=np.zeros(2))
    with pytest.raises(CheckpointError, match="unknown checkpoint format"):
        load_checkpoint(_model(), path)


@pytest.mark.parametrize("head", [b"", b"\x80\x02", b"PK\x03\x04"])
def test_random_bytes_are_corrupt_not_unsafe(tmp_path: pathlib.Path, head: bytes) -> None:
    """Defect 6: a .pt of random bytes was reported as an 'unsafe pickle'."""
    path = tmp_path / "model.pt"
    path.write_bytes(head + np.random.default_rng(0).bytes(4000))
    with pytest.raises(CheckpointError) as err:
        read_state_dict(path)
    text = str(err.value)
    assert str(path) in text and "unsafe" not in text and "refused" not in text
    assert "corrupt" in text


# ------------------------------------------- dtypes and values (issue 25 #15 #19 #25)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float64])
def test_floating_weights_of_another_precision_are_cast_and_said(tmp_path: pathlib.Path, dtype, logged_warning) -> None:
    """float16 / float64 weights passed the checks and failed at the first prediction."""
    state = {k: v.to(dtype) for k, v in _state(1).items()}
    save_file(state, str(tmp_path / "w.safetensors"))
    model = _model(2)
    with logged_warning(rf"{len(state)} {str(dtype)[6:]} tensor\(s\) cast to float32"):
        report = load_checkpoint(model, tmp_path / "w.safetensors")
    assert "cast to float32" in report.cast
    _assert_same_weights(model, {k: v.to(torch.float32) for k, v in state.items()})
    assert all(v.dtype == torch.float32 for v in model.state_dict().values())


@pytest.mark.parametrize("dtype", [torch.int32, torch.bool])
def test_integer_or_boolean_weights_are_refused_by_name(tmp_path: pathlib.Path, dtype) -> None:
    """int32 / bool tensors failed inside load_state_dict with a torch traceback."""
    state = _state()
    key = "camera_head.pose_branch.fc2.bias"
    state[key] = torch.ones_like(state[key], dtype=dtype)
    torch.save(state, tmp_path / "w.pt")
    with pytest.raises(
        CheckpointError, match=rf"1 tensor\(s\) of a non-floating-point dtype .*{key} \({str(dtype)[6:]}\)"
    ):
        load_checkpoint(_model(), tmp_path / "w.pt")


def test_nan_weights_are_refused_by_name(tmp_path: pathlib.Path) -> None:
    """One NaN output bias ran to "0 points written", exit 0; all-NaN weights ended in
    "poses holds non-finite values"."""
    state = _state()
    key = "camera_head.pose_branch.fc2.bias"
    state[key][3] = float("nan")
    save_file(state, str(tmp_path / "w.safetensors"))
    with pytest.raises(CheckpointError, match=rf"1 tensor\(s\) hold NaN/inf values: {key}"):
        load_checkpoint(_model(), tmp_path / "w.safetensors")
    save_file({k: torch.full_like(v, float("nan")) for k, v in state.items()}, str(tmp_path / "all.safetensors"))
    with pytest.raises(CheckpointError, match=rf"{len(state)} tensor\(s\) hold NaN/inf values"):
        load_checkpoint(_model(), tmp_path / "all.safetensors")


def test_non_finite_model_output_names_the_model_and_the_output() -> None:
    """Weights that go bad after loading (or overflow): the runner names the output."""
    from inference.runners import ModelOutputError, TorchRunner

    model = _model()
    with torch.no_grad():
        model.camera_head.pose_branch.fc2.bias[3] = float("nan")
    runner = TorchRunner(model)
    runner.name = "VGGT (w.safetensors, float32)"
    images = np.random.default_rng(0).random((2, 3, 28, 42)).astype(np.float32)
    with pytest.raises(
        ModelOutputError,
        match=r"VGGT \(w.safetensors, float32\) predicted non-finite values .* "
        r"camera head pose encoding \(pose_enc\) for 2 of 2 frames",
    ):
        runner.predict(images)

"""The torch runner's device path (inference.device): what runs on the CPU here is exactly what
ran before; the GPU-only steps (descriptors on the device, the memory probe) are checked on the
CPU by forcing them."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def tiny(golden_dir):
    from inference import VGGT, VGGTConfig, load_checkpoint

    model = VGGT(VGGTConfig.from_json(golden_dir / "tiny_config.json"))
    load_checkpoint(model, golden_dir / "tiny_weights.safetensors")
    return model, np.load(golden_dir / "tiny_images.npy")[0].astype(np.float32)


def test_cpu_runner_keeps_patch_tokens_and_golden_values(tiny, golden_dir):
    from inference.runners import TorchRunner

    model, images = tiny
    runner = TorchRunner(model)
    assert runner.reduce_tokens is False  # the CPU keeps the JAX reduction (results unchanged)
    pred = runner.predict(images)
    golden = np.load(golden_dir / "tiny_golden.npz")
    assert pred.descriptors is None
    np.testing.assert_allclose(pred.patch_tokens, golden["patch_tokens"][0], atol=1e-5, rtol=0)
    np.testing.assert_allclose(pred.depth, golden["depth"][0, ..., 0], rtol=1e-4, atol=0)


def test_descriptors_on_the_device_equal_the_host_reduction(tiny):
    from inference.runners import TorchRunner
    from swiftjax.loops import frame_descriptor

    model, images = tiny
    full = TorchRunner(model).predict(images)
    reduced = TorchRunner(model, reduce_tokens=True).predict(images)
    assert reduced.patch_tokens is None and reduced.descriptors.shape == (images.shape[0], full.patch_tokens.shape[-1])
    np.testing.assert_allclose(reduced.descriptors, np.asarray(frame_descriptor(full.patch_tokens)), atol=2e-7, rtol=0)
    np.testing.assert_array_equal(reduced.depth, full.depth)


@pytest.mark.parametrize(
    ("limit", "frames", "expect"), [(7, 75, 7), (1, 30, 1), (0, 8, 0), (74, 75, 74), (33, 120, 33)]
)
def test_largest_chunk_that_fits_is_found_by_trying(limit, frames, expect):
    from inference.device import largest_chunk_that_fits

    tried = []

    def run(s):
        tried.append(s)
        if s > limit:
            raise torch.OutOfMemoryError("CUDA out of memory (simulated)")

    assert largest_chunk_that_fits(run, frames, device=torch.device("cpu")) == expect
    assert len(tried) <= 2 * int(np.ceil(np.log2(frames))) + 1  # halving, then bisection


def test_out_of_memory_names_the_largest_chunk_that_fits(tiny, monkeypatch):
    from inference.device import GPUMemoryError
    from inference.runners import TorchRunner

    model, images = tiny
    runner = TorchRunner(model)
    real = runner.forward

    def forward(x):  # a device that holds at most 2 frames of this size
        if np.shape(x)[0] > 2:
            raise torch.OutOfMemoryError("CUDA out of memory (simulated)")
        return real(x)

    monkeypatch.setattr(runner, "forward", forward)
    with pytest.raises(
        GPUMemoryError, match=r"a chunk of 4 frames of 70x42 does not fit .* is 2 frames: --chunk-size 2"
    ):
        runner.predict(np.concatenate([images, images])[:4])


def test_to_host_and_to_device_are_plain_copies_on_the_cpu():
    from inference.device import to_device, to_host

    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    t = to_device(a, torch.device("cpu"))
    out = to_host({"a": t.to(torch.bfloat16), "b": t})
    assert out["a"].dtype == np.float32 and np.array_equal(out["b"], a) and np.array_equal(out["a"], a)


def test_share_gpu_with_jax_turns_preallocation_off_unless_the_user_chose():
    from inference.device import runner_device, share_gpu_with_jax

    env: dict[str, str] = {}
    assert share_gpu_with_jax(env) and env == {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    env = {"XLA_PYTHON_CLIENT_PREALLOCATE": "true"}
    assert not share_gpu_with_jax(env) and env == {"XLA_PYTHON_CLIENT_PREALLOCATE": "true"}
    # A CPU runner leaves the environment alone (no GPU to share).
    import os

    before = os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE")
    assert runner_device("cpu") == torch.device("cpu")
    assert os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE") == before

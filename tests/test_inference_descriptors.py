"""inference.descriptors (torch, on the model's device) equals swiftjax.loops.frame_descriptor (JAX)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")


@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_torch_descriptors_equal_the_jax_reduction(dtype):
    from inference.descriptors import frame_descriptors
    from swiftjax.loops import frame_descriptor

    rng = np.random.default_rng(0)
    tokens = rng.normal(size=(5, 37, 64)).astype(np.float32) * rng.uniform(0.1, 10, size=(5, 37, 1)).astype(np.float32)
    tokens[1, 3] = 0.0  # a zero token stays zero (no NaN)
    t = torch.from_numpy(tokens).to(getattr(torch, dtype))
    got = frame_descriptors(t).numpy()
    ref = np.asarray(frame_descriptor(t.float().numpy()))
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-7)
    np.testing.assert_allclose(np.linalg.norm(got, axis=-1), 1.0, atol=1e-6)


def test_torch_descriptors_of_a_zero_frame_are_zero():
    from inference.descriptors import frame_descriptors

    assert torch.count_nonzero(frame_descriptors(torch.zeros(2, 4, 8))) == 0

"""bench/flops.py: the analytic FLOP count of a VGGT chunk against torch's own flop counter.

``torch.utils.flop_counter`` counts every matrix product and convolution the model actually
dispatches (attention on the math backend, so that it is made of countable ``bmm``s); the
analytic formula must give the same number exactly, per part, on several chunk shapes.
"""

from __future__ import annotations

import pathlib
import sys

import pytest

torch = pytest.importorskip("torch")

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "bench"))

from flops import block_flops, vggt_chunk_flops


@pytest.fixture(scope="module")
def tiny_vggt(shared_dir):
    from inference.config import VGGTConfig
    from inference.model import VGGT

    torch.manual_seed(0)
    cfg = VGGTConfig.from_json(shared_dir / "golden" / "vggt" / "tiny_config.json")
    return VGGT(cfg).eval().requires_grad_(False)


@pytest.mark.parametrize(("frames", "height", "width"), [(4, 28, 42), (3, 42, 70), (5, 56, 28)])
def test_vggt_flops_equal_torch_flop_counter(tiny_vggt, frames, height, width):
    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.utils.flop_counter import FlopCounterMode

    x = torch.rand(1, frames, 3, height, width)
    with torch.no_grad(), sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as counter:
        tiny_vggt(x)
    by_module = {k: sum(v.values()) for k, v in counter.get_flop_counts().items()}
    ours = vggt_chunk_flops(tiny_vggt.config, frames, height, width)
    assert ours["total"] == counter.get_total_flops()
    assert ours["aggregator"] == by_module["VGGT.aggregator"]
    assert ours["camera_head"] == by_module["VGGT.camera_head"]
    assert ours["depth_head"] == by_module["VGGT.depth_head"]


def test_global_attention_grows_quadratically_in_frames():
    # F_block(S·T) - S·F_block(T) = 4·C·T²·S·(S - 1): the cross-frame part of global attention.
    t, c, m = 60, 32, 128
    for s in (2, 5, 30):
        assert block_flops(s * t, c, m) - block_flops(t, c, m, sequences=s) == 4 * c * t * t * s * (s - 1)


def test_vggt_1b_chunk_is_of_order_1e14():
    from inference.config import VGGTConfig

    parts = vggt_chunk_flops(VGGTConfig(), 75, 154, 518)
    assert 1.4e14 < parts["total"] < 1.7e14
    assert parts["global_attention"] > 0.6 * parts["total"]  # global attention dominates


def test_vggt_flops_refuse_sizes_off_the_patch_grid():
    from inference.config import VGGTConfig

    with pytest.raises(ValueError, match="multiples of the patch size 14"):
        vggt_chunk_flops(VGGTConfig(), 4, 150, 518)

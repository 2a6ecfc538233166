"""Sky handling of Depth Anything 3's metric/mono and nested models.

A pixel is sky where the sky map is ``>= 0.3`` (``non_sky = sky < 0.3``).  Sky pixels get the
0.99 quantile (linear interpolation) of the non-sky depth, computed on at most 100 000 values
drawn with replacement from the global torch RNG when there are more (as officially).
Data-dependent (boolean selections): eager torch, outside ONNX graphs.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["SKY_THRESHOLD", "non_sky_mask", "sky_quantile", "fill_sky"]

SKY_THRESHOLD = 0.3
MAX_QUANTILE_SAMPLES = 100_000
MIN_PIXELS = 10


def non_sky_mask(sky: Tensor) -> Tensor:
    """``sky < 0.3``."""
    return sky < SKY_THRESHOLD


def sky_quantile(depth: Tensor, non_sky: Tensor, q: float = 0.99) -> Tensor:
    """The ``q`` quantile of ``depth[non_sky]`` (sampled with replacement above 100 000 values)."""
    values = depth[non_sky]
    if values.numel() > MAX_QUANTILE_SAMPLES:
        values = values[torch.randint(0, values.numel(), (MAX_QUANTILE_SAMPLES,), device=values.device)]
    return torch.quantile(values, q)


def fill_sky(depth: Tensor, sky: Tensor) -> Tensor:
    """Metric/mono output rule: sky pixels := the 0.99 quantile of the non-sky depth, unless there
    are at most 10 sky or at most 10 non-sky pixels (over the whole batch)."""
    ns = non_sky_mask(sky)
    if int(ns.sum()) <= MIN_PIXELS or int((~ns).sum()) <= MIN_PIXELS:
        return depth
    return torch.where(ns, depth, sky_quantile(depth, ns).to(depth.dtype))

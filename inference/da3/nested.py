"""DA3-Nested (official ``NestedDepthAnything3Net``): an any-view model for geometry and a
metric model for scale, on the same images.

With ``O`` the any-view output and ``M`` the metric output (sky already filled):

1. ``M_depth *= mean(fx, fy) / 300`` with ``O``'s intrinsics (metres for a 300 px focal).
2. ``non_sky = M_sky < 0.3`` (more than 10 pixels required); ``m`` = median of ``O_conf`` over
   non-sky pixels (at most 100 000 sampled without replacement); alignment mask =
   ``O_conf >= m & non_sky & M_depth > 0.01 & O_depth > 0.001``.
3. Least squares ``s = Σ M_depth O_depth / Σ O_depth²`` over the mask; ``O_depth *= s`` and
   the w2c translations ``*= s``.
4. Sky pixels: depth ``min(0.99 quantile of the non-sky depth, 200)``, confidence 1.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..runners import ModelOutputError
from .config import NestedDA3Config
from .model import DA3Net
from .sky import MAX_QUANTILE_SAMPLES, MIN_PIXELS, non_sky_mask, sky_quantile

__all__ = ["NestedDA3Net", "metric_align"]

FOCAL_REFERENCE_PX = 300.0
SKY_DEPTH_CAP = 200.0


def metric_align(anyview: dict[str, Tensor], metric_depth: Tensor, metric_sky: Tensor) -> dict[str, Tensor]:
    """Steps 1-4 of the module docstring; returns the aligned outputs plus ``metric_depth_scaled``,
    ``scale_factor [1]`` (float64) and ``is_metric [1]``."""
    k = anyview["intrinsics"]
    scaled = metric_depth * ((k[..., 0, 0] + k[..., 1, 1]) / 2)[..., None, None] / FOCAL_REFERENCE_PX
    ns = non_sky_mask(metric_sky)
    if int(ns.sum()) <= MIN_PIXELS:
        raise ModelOutputError("metric alignment: fewer than 11 non-sky pixels (the images look like sky only)")
    depth, conf = anyview["depth"], anyview["depth_conf"]
    conf_ns = conf[ns]
    if conf_ns.numel() > MAX_QUANTILE_SAMPLES:
        conf_ns = conf_ns.flatten()[torch.randperm(conf_ns.numel(), device=conf_ns.device)[:MAX_QUANTILE_SAMPLES]]
    median = torch.quantile(conf_ns, 0.5)
    mask = (conf >= median) & ns & (scaled > 0.01) & (depth > 0.001)
    d, m = depth[mask], scaled[mask]
    s = torch.dot(m, d) / torch.dot(d, d).clamp_min(1e-12)
    depth = depth * s
    ext = anyview["extrinsics"].clone()
    ext[..., :3, 3] = ext[..., :3, 3] * s
    sky_depth = torch.clamp(sky_quantile(depth, ns), max=SKY_DEPTH_CAP)
    out = dict(anyview)
    out.update(
        depth=torch.where(ns, depth, sky_depth.to(depth.dtype)),
        depth_conf=torch.where(ns, conf, torch.ones_like(conf)),
        extrinsics=ext,
        metric_depth_scaled=scaled,
        scale_factor=s.detach().double().reshape(1),
        is_metric=torch.ones(1, dtype=torch.long),
    )
    return out


class NestedDA3Net(nn.Module):
    """``da3`` (any-view) + ``da3_metric`` (metric) with the metric alignment of the module docstring."""

    def __init__(self, config: NestedDA3Config) -> None:
        super().__init__()
        self.config = config
        self.da3 = DA3Net(config.anyview)
        self.da3_metric = DA3Net(config.metric)

    def forward(
        self,
        images: Tensor,
        extrinsics: Tensor | None = None,
        intrinsics: Tensor | None = None,
        ref_view_strategy: str = "saddle_balanced",
        intermediates: bool = False,
        **kwargs: object,
    ) -> dict[str, Tensor]:
        """As :meth:`DA3Net.forward`, plus ``sky`` (metric sky map), ``metric_depth`` (metric
        branch, sky filled), ``metric_depth_scaled``, ``scale_factor``, ``is_metric``; with
        ``intermediates`` also ``anyview_*`` (before alignment) and ``metric_*``."""
        o = self.da3(images, extrinsics, intrinsics, ref_view_strategy, intermediates=intermediates, **kwargs)  # type: ignore[arg-type]
        m = self.da3_metric(images, intermediates=intermediates)
        out = metric_align(o, m["depth"], m["sky"])
        out["sky"], out["metric_depth"] = m["sky"], m["depth"]
        if intermediates:
            out["metric_head_depth"] = m["head_depth"]
            out["metric_block_outputs"] = m["block_outputs"]
            for key in ("depth", "depth_conf", "extrinsics", "intrinsics", "ref_view_idx", "block_outputs"):
                out[f"anyview_{key}"] = o[key]
        return out

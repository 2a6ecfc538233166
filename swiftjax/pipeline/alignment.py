"""Pair alignment with the run's configuration: the temporal edges and the loop-chunk halves.

One function, :func:`align_pair`, below both the temporal and the loop-closure stage: ``S``
mapping one chunk's frames into another's (:func:`swiftjax.align.align_chunk_pair_checked`, or
the IRLS variant), with the diagnostics the pose graph forms an edge's information from.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from swiftjax import align, sim3
from swiftjax.pipeline.config import PipelineConfig

__all__ = ["align_pair", "both", "info_dict"]


def both(a: jax.Array | None, b: jax.Array | None) -> jax.Array | None:
    """The pixels both keep-masks keep (``None``: no mask)."""
    return a if b is None else b if a is None else a & b


def align_pair(
    prev: align.ChunkFrames,
    cur: align.ChunkFrames,
    K_ref: np.ndarray,
    config: PipelineConfig,
    loop: bool,
    name: str,
    mask: jax.Array | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """``S`` mapping ``cur``'s chunk into ``prev``'s, with the configured method, and diagnostics.

    ``mask``: keep-mask ``[O, H, W]`` of the overlap frames (masked pixels are never reliable)."""
    options = _align_options(config, loop)
    if config.alignment == "irls":
        if mask is not None:  # a masked pixel is a non-finite one (never reliable)
            prev, cur = (
                f._replace(depth=jnp.where(mask, jnp.asarray(f.depth, jnp.float32), jnp.nan)) for f in (prev, cur)
            )
        f32 = lambda x: jnp.asarray(x, jnp.float32)
        S, info, count = align.irls_chunk_pair(
            align.ChunkFrames(*map(f32, prev)),
            align.ChunkFrames(*map(f32, cur)),
            f32(K_ref),
            f32(options.depth_threshold),
            f32(options.conf_ratio),
        )
        ok = bool(np.all(np.isfinite(np.asarray(S)))) and int(count) >= 3
        if not ok:
            S = sim3.identity((), jnp.float32)
        diag = {
            "num_points": int(count),
            "fraction_used": float(count) / np.size(prev.depth),
            "rms": float("nan"),
            "valid": ok,
            "used_fallback_threshold": False,
            "pose_fallback": not ok,
            "scale_ratio": 1.0,
        }
        return np.asarray(S, np.float64), diag
    S, info = align.align_chunk_pair_checked(prev, cur, K_ref, name=name, mask=mask, options=options)
    S = np.asarray(S, np.float64)
    # S and the source moments with the diagnostics: what the edge information is formed from
    # (swiftjax.pipeline.graph.edge_information), also for loop-chunk halves.
    return S, {**info_dict(info), "S": S.tolist()}


def _align_options(config: PipelineConfig, loop: bool) -> align.AlignOptions:
    options = config.align
    return options.for_loop() if loop else options


def info_dict(info: align.AlignInfo) -> dict[str, Any]:
    return {
        "num_points": int(info.num_points),
        "fraction_used": float(info.fraction_used),
        "rms": float(info.rms),
        "valid": bool(info.valid),
        "used_fallback_threshold": bool(info.used_fallback_threshold),
        "pose_fallback": bool(info.pose_fallback),
        "scale_ratio": float(info.scale_ratio),
        "src_mean": np.asarray(info.src_mean, np.float64).tolist(),
        "src_covariance": np.asarray(info.src_covariance, np.float64).tolist(),
    }

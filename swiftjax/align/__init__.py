"""Chunk alignment: reliability mask (eq. 2), weighted Umeyama Sim(3), IRLS baseline.

SwiftVGGT aligns two neighbouring chunks with ONE closed-form weighted Umeyama solve on the
reliable overlap points (no iterations); VGGT-Long's IRLS is kept only as a baseline.

Modules:

* ``swiftjax/align/umeyama.py`` (the attribute ``swiftjax.align.umeyama`` is the function;
  ``importlib.import_module("swiftjax.align.umeyama")`` is the module): weighted Umeyama (centred one-pass moments, closed-form solve).
* :mod:`swiftjax.align.mask`: the reliability mask and the per-frame mean confidence.
* :mod:`swiftjax.align.chunk_pair`: :class:`ChunkFrames`, :class:`AlignInfo`,
  :func:`align_chunk_pair` (per-frame pixel moments) and the pose-based fallback.
* :mod:`swiftjax.align.irls`: VGGT-Long's IRLS baseline.
* :mod:`swiftjax.align.options`: :class:`AlignOptions`, the stage's defaults.
* :mod:`swiftjax.align.checks`: host-side input checks.
* :mod:`swiftjax.align.covariance`: information matrices of alignment and loop edges.
"""

from swiftjax.align import covariance as covariance  # the submodule, as align.covariance
from swiftjax.align.chunk_pair import (
    AlignInfo,
    ChunkFrames,
    align_chunk_pair,
    align_chunk_pair_checked,
    align_chunk_pairs,
    pose_based_estimate,
)
from swiftjax.align.irls import IRLSInfo, irls_chunk_pair, irls_sim3
from swiftjax.align.mask import frame_conf_mean, masked_median, overlap_scale_ratio, reliability_mask
from swiftjax.align.options import AlignOptions
from swiftjax.align.umeyama import UmeyamaInfo, umeyama

__all__ = [
    "AlignOptions",
    "UmeyamaInfo",
    "umeyama",
    "frame_conf_mean",
    "reliability_mask",
    "overlap_scale_ratio",
    "masked_median",
    "IRLSInfo",
    "irls_sim3",
    "irls_chunk_pair",
    "AlignInfo",
    "ChunkFrames",
    "align_chunk_pair",
    "align_chunk_pair_checked",
    "align_chunk_pairs",
    "pose_based_estimate",
]

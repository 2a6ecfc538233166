"""The alignment stage's options, with their defaults written once.

:class:`AlignOptions` is taken by :func:`~swiftjax.align.align_chunk_pair`,
:func:`~swiftjax.align.align_chunk_pairs`, :func:`~swiftjax.align.align_chunk_pair_checked`,
:func:`~swiftjax.align.reliability_mask` (its defaults) and
:class:`~swiftjax.pipeline.PipelineConfig` (and so the CLI flags and the TOML keys).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from swiftjax import options
from swiftjax.options import option

__all__ = ["AlignOptions", "OVERLAP_SCALE_RULES"]

#: How chunk t+1's overlap depths are put on chunk t's scale before eq. 2: ``"none"`` (the
#: authors' eq. 2, absolute differences of the chunks' own normalised depths), ``"median"``
#: (always rescaled by the robust ratio of :func:`~swiftjax.align.overlap_scale_ratio`) or
#: ``"auto"`` (the authors' eq. 2 and retry; rescaled only when they keep fewer than
#: ``min_points``: a gauge jump).  The order is the traced code of the jitted alignment.
OVERLAP_SCALE_RULES = ("none", "median", "auto")


@dataclasses.dataclass(frozen=True)
class AlignOptions:
    """Options of one chunk-pair alignment (paper eq. 1-2 and the authors' retry rule).

    Attributes:
        depth_threshold: ``lambda_D``: a pixel is reliable when the two chunks' normalised
            depths differ by less than this (absolute, in the chunks' units).
        conf_ratio: ``lambda_gamma``: and both confidences exceed this times their frame's mean.
        min_points: fewest reliable points before the mask is recomputed once with
            ``fallback_depth_threshold``.
        fallback_depth_threshold: the depth threshold of that one-time retry.
        loop_depth_threshold: ``depth_threshold`` when a loop chunk is aligned to its temporal
            chunks (:meth:`for_loop`).
        overlap_scale: :data:`OVERLAP_SCALE_RULES`: ``"median"`` rescales chunk t+1's overlap
            depths by the robust ratio ``rho`` (:func:`~swiftjax.align.overlap_scale_ratio`)
            before eq. 2, so ``lambda_D`` is in chunk t's units whatever the two chunks' gauges;
            ``"none"`` is the authors' eq. 2; ``"auto"`` (default) is the authors' unless their
            mask and retry keep fewer than ``min_points``, then ``"median"`` (why ``"auto"``:
            docs/performance/align.md, "The overlap scale").

    Every field is a traced argument of the jitted alignment: changing one never recompiles.

    Raises:
        swiftjax.options.OptionError: a value outside its field's schema.
    """

    depth_threshold: float = option(
        0.2,
        "reliability mask: max |D_t - D_t+1| of normalised overlap depths (lambda_D)",
        low=0.0,
        low_open=True,
    )
    conf_ratio: float = option(
        0.5,
        "reliability mask: keep pixels with confidence > ratio x frame mean (lambda_gamma)",
        low=0.0,
        high=10.0,
    )
    min_points: int = option(
        20_000,
        "fewest reliable points before the one-time retry with {fallback_depth_threshold}",
        low=0,
        high=10**8,
    )
    fallback_depth_threshold: float = option(
        0.25, "depth threshold of the retry when fewer than {min_points} are reliable", low=0.0, low_open=True
    )
    loop_depth_threshold: float = option(
        0.4, "depth threshold when aligning a loop chunk to its temporal chunks", low=0.0, low_open=True
    )
    overlap_scale: str = option(
        "auto",
        "put chunk t+1's overlap depths on chunk t's scale (robust median ratio) before the reliability "
        "mask: median (always), auto (only when the authors' mask keeps fewer than {min_points}) or none "
        "(the authors' eq. 2)",
        choices=OVERLAP_SCALE_RULES,
    )

    def __post_init__(self) -> None:
        options.validate(self)

    def replace(self, **changes: Any) -> AlignOptions:
        """A validated copy with ``changes`` (:func:`swiftjax.options.replace`)."""
        return options.replace(self, **changes)

    def for_loop(self) -> AlignOptions:
        """The options of a loop-chunk alignment: ``depth_threshold = loop_depth_threshold``,
        and the retry threshold never tighter than it."""
        return dataclasses.replace(
            self,
            depth_threshold=self.loop_depth_threshold,
            fallback_depth_threshold=max(self.fallback_depth_threshold, self.loop_depth_threshold),
        )

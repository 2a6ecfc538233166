"""The alignment stage's options, with their defaults written once.

:class:`AlignOptions` is taken by :func:`~swiftjax.align.align_chunk_pair`,
:func:`~swiftjax.align.align_chunk_pairs`, :func:`~swiftjax.align.align_chunk_pair_checked`,
:func:`~swiftjax.align.reliability_mask` (its defaults) and
:class:`~swiftjax.pipeline.PipelineConfig` (and so the CLI flags and the TOML keys).
"""

from __future__ import annotations

import dataclasses
from typing import Any

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
        ValueError: ``overlap_scale`` not in :data:`OVERLAP_SCALE_RULES`.
    """

    depth_threshold: float = 0.2
    conf_ratio: float = 0.5
    min_points: int = 20_000
    fallback_depth_threshold: float = 0.25
    loop_depth_threshold: float = 0.4
    overlap_scale: str = "auto"

    def __post_init__(self) -> None:
        if self.overlap_scale not in OVERLAP_SCALE_RULES:
            raise ValueError(
                f"AlignOptions: overlap_scale must be one of {OVERLAP_SCALE_RULES}, got {self.overlap_scale!r}"
            )

    def replace(self, **changes: Any) -> AlignOptions:
        """A copy with ``changes`` applied (``None`` values are ignored)."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})

    def for_loop(self) -> AlignOptions:
        """The options of a loop-chunk alignment: ``depth_threshold = loop_depth_threshold``,
        and the retry threshold never tighter than it."""
        return dataclasses.replace(
            self,
            depth_threshold=self.loop_depth_threshold,
            fallback_depth_threshold=max(self.fallback_depth_threshold, self.loop_depth_threshold),
        )

    @classmethod
    def from_config(cls, config: Any) -> AlignOptions:
        """The fields of ``config`` (e.g. a :class:`~swiftjax.pipeline.PipelineConfig`) that
        share their names with this class's."""
        return cls(**{f.name: getattr(config, f.name) for f in dataclasses.fields(cls)})

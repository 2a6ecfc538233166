"""Method parameters of a run: :class:`PipelineConfig`."""

from __future__ import annotations

import dataclasses
from typing import Any

from swiftjax import loops
from swiftjax.posegraph.gnc import DEFAULT_SCALE as _GNC_SCALE

__all__ = ["PipelineConfig"]


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Every method parameter, with the paper's / authors' defaults (DESIGN.md).

    Chunking: ``chunk_size`` (B), ``overlap`` (O).  Alignment (eq. 1-2): ``alignment``
    (``"umeyama"``, the method's single weighted solve, or ``"irls"``, VGGT-Long's
    iterative baseline on the same reliable points, for comparison), ``depth_threshold``
    (lambda_D), ``conf_ratio`` (lambda_gamma), ``min_points`` and
    ``fallback_depth_threshold`` (the authors' one-time retry), ``loop_depth_threshold``
    (loop-chunk alignment).  Loops: ``loop_closure``, ``loop_threshold_rule``
    (``"adaptive"``: calibrated per sequence, :func:`swiftjax.loops.calibrate_threshold`, with
    ``loop_false_alarms``; ``"fixed"``: ``loop_threshold``, the cosine of the whitened
    descriptors; ``"authors"``: 0.98 with the whitening fitted on g0), ``loop_min_separation``, ``loop_nms_radius``, ``loop_top_k``,
    ``whitening_dim``, ``whitening_remove``, ``power_beta``, ``loop_half_window``.  Loop
    verification (:mod:`swiftjax.loop_verification`): ``loop_verification`` (``"geometric"``:
    every candidate must pass the cross-chunk dense test, the loop-chunk quality test and
    pairwise consistency before it becomes an edge; ``"none"``: the authors' rule, every
    candidate above the threshold is an edge), ``loop_min_agreement`` (the dense test's
    bound), ``loop_pcm`` (the pairwise test).  Pose
    graph: ``robust_loops`` (``"gnc"``: graduated non-convexity with truncated least squares on
    the loop edges, :mod:`swiftjax.posegraph.gnc`; ``"huber"``, ``"cauchy"``, or ``None``, the
    authors' plain least squares), ``robust_scale`` (the kernel's scale / GNC's inlier threshold
    in whitened units; default ``sqrt(chi2_7^-1(0.99))``), ``edge_information`` (``"data"``: every
    edge's information from its own alignment, :func:`swiftjax.pipeline.graph.edge_information`;
    ``"equal"``: identity for every edge, the authors' choice), ``edge_pixels_per_sample`` (the
    pixels per independent residual in that information: one 14 x 14 ViT patch), ``max_lm_steps``.  Output: ``point_conf_ratio``
    (keep pixels with confidence >= ratio x frame mean), ``point_stride`` (pixel
    subsampling of the cloud), ``voxel_size`` (optional voxel downsampling per chunk),
    ``colmap`` (write the COLMAP model and its frames, ``colmap/``), ``colmap_text`` (its
    ``.txt`` files beside the ``.bin``), ``colmap_original_resolution`` (the model at the
    original image size, with the original files, as VGGT's own COLMAP export),
    ``colmap_max_points``.  The user's camera (:mod:`swiftjax.pipeline.user_camera`):
    ``intrinsics`` (a file: ``fx fy cx cy``, KITTI ``calib.txt`` or COLMAP ``cameras.txt``, at
    the original image size), ``metric`` (``"camera-height=H"`` in metres or ``"gt"``: every
    output in metres), ``mask_dir`` (one PNG per frame, white = keep), ``drop_sky``.
    """

    chunk_size: int = 75
    overlap: int = 30
    alignment: str = "umeyama"
    depth_threshold: float = 0.2
    conf_ratio: float = 0.5
    min_points: int = 20_000
    fallback_depth_threshold: float = 0.25
    loop_depth_threshold: float = 0.4
    loop_closure: bool = True
    loop_threshold_rule: str = "adaptive"
    loop_threshold: float = loops.DEFAULT_THRESHOLD
    loop_false_alarms: float = loops.DEFAULT_FALSE_ALARMS
    loop_min_separation: int = 100
    loop_nms_radius: int = 25
    loop_top_k: int = 8
    whitening_dim: int = 512
    whitening_remove: int = 1
    power_beta: float = 0.5
    loop_half_window: int = 10
    loop_verification: str = "geometric"
    loop_min_agreement: float = 0.55
    loop_pcm: bool = True
    robust_loops: str | None = dataclasses.field(default="gnc", metadata={
        "help": "robust loop edges: gnc (graduated non-convexity, truncated least squares), cauchy, huber, "
                "or none (the authors' plain least squares)"})
    robust_scale: float = dataclasses.field(default=_GNC_SCALE, metadata={
        "help": "kernel scale / GNC inlier threshold on sqrt(r^T Omega r); sqrt(chi2_7(0.99)) by default"})
    edge_information: str = dataclasses.field(default="data", metadata={
        "help": "edge information: data (drift model + each alignment's own statistics) or equal "
                "(identity, the authors')"})
    edge_pixels_per_sample: float = dataclasses.field(default=196.0, metadata={
        "help": "pixels per independent residual in an alignment's information (one 14x14 ViT patch)"})
    max_lm_steps: int = 100
    point_conf_ratio: float = 0.75
    point_stride: int = 4
    voxel_size: float | None = None
    colmap: bool = True
    colmap_text: bool = False
    colmap_original_resolution: bool = False
    colmap_max_points: int = 200_000
    intrinsics: str | None = dataclasses.field(default=None, metadata={
        "help": "known intrinsics at the original image size: 'fx fy cx cy', a KITTI calib.txt (P0) "
                "or a COLMAP cameras.txt (PINHOLE / SIMPLE_PINHOLE / undistorted OPENCV)"})
    metric: str | None = dataclasses.field(default=None, metadata={
        "help": "metric scale: 'camera-height=H' (metres above the road) or 'gt' (from --gt)"})
    mask_dir: str | None = dataclasses.field(default=None, metadata={
        "help": "one PNG per frame, named like the frame, at the image size; white = keep"})
    drop_sky: bool = dataclasses.field(default=False, metadata={
        "help": "leave out sky pixels (far and unsure: depth > 5x the frame median, confidence < 0.3x)"})

    def __post_init__(self) -> None:
        if self.chunk_size < 2:
            raise ValueError(f"chunk_size must be >= 2, got {self.chunk_size}")
        if not 1 <= self.overlap < self.chunk_size:
            raise ValueError(
                f"overlap must satisfy 1 <= overlap < chunk_size ({self.chunk_size}), got {self.overlap}"
            )
        if self.alignment not in ("umeyama", "irls"):
            raise ValueError(f"alignment must be 'umeyama' or 'irls', got {self.alignment!r}")
        if self.robust_loops not in (None, "huber", "cauchy", "gnc"):
            raise ValueError(f"robust_loops must be none, 'huber', 'cauchy' or 'gnc', got {self.robust_loops!r}")
        if not self.robust_scale > 0:
            raise ValueError(f"robust_scale must be > 0, got {self.robust_scale}")
        if self.edge_information not in ("data", "equal"):
            raise ValueError(f"edge_information must be 'data' or 'equal', got {self.edge_information!r}")
        if not self.edge_pixels_per_sample >= 1:
            raise ValueError(f"edge_pixels_per_sample must be >= 1, got {self.edge_pixels_per_sample}")
        if self.loop_verification not in ("geometric", "none"):
            raise ValueError(
                f"loop_verification must be 'geometric' or 'none', got {self.loop_verification!r}"
            )
        if not 0.0 <= self.loop_min_agreement <= 1.0:
            raise ValueError(f"loop_min_agreement must be in [0, 1], got {self.loop_min_agreement}")
        if self.loop_threshold_rule not in loops.THRESHOLD_RULES:
            raise ValueError(
                f"loop_threshold_rule must be one of {', '.join(loops.THRESHOLD_RULES)}, got {self.loop_threshold_rule!r}"
            )
        if not 0.0 < self.loop_false_alarms < 1.0:
            raise ValueError(f"loop_false_alarms must be in (0, 1), got {self.loop_false_alarms}")
        if self.point_stride < 1:
            raise ValueError(f"point_stride must be >= 1, got {self.point_stride}")
        from swiftjax.metric import parse_metric

        parse_metric(self.metric)  # ValueError naming the option
        if self.loop_closure and (self.loop_half_window < 1 or 2 * self.loop_half_window > self.chunk_size):
            raise ValueError(
                f"loop_half_window must be in [1, chunk_size / 2], got {self.loop_half_window}"
            )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> PipelineConfig:
        """Build from a dict (e.g. a TOML table); unknown keys are an error naming them."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ValueError(f"unknown configuration keys: {', '.join(unknown)}")
        return cls(**values)

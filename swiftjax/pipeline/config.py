"""Method parameters of a run: :class:`PipelineConfig`, one typed schema (:mod:`swiftjax.options`).

Every field is declared with :func:`swiftjax.options.option`: type, range, choices, help and
the stage it belongs to; a field that feeds a stage's options names it (``target=``) and takes
its schema from it, and ``config.align`` / ``config.loops`` / ``config.verification`` /
``config.geometry`` / ``config.graph`` are the stage options objects (:func:`swiftjax.options.build`).  The CLI flags, the TOML keys, validation and the run directory's
per-stage fingerprints all derive from these declarations.  To add an option, add one field
in the same style (its flag ``--name-with-dashes`` appears by itself).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from swiftjax import options
from swiftjax.align import AlignOptions
from swiftjax.loops.options import GeometryOptions, LoopOptions, VerificationConfig
from swiftjax.metric_scale import METRIC_COMBINE
from swiftjax.options import option
from swiftjax.posegraph.options import PIPELINE as _GRAPH
from swiftjax.posegraph.options import GraphOptions

__all__ = ["PipelineConfig", "BACKBONE_NAMES", "METRIC_BACKBONES"]

#: The networks ``--model`` offers (``inference.backbones.BACKBONES`` implements them; a test
#: keeps the two lists equal, so that ``swiftjax`` can validate the option without importing it).
BACKBONE_NAMES = ("vggt-1b", "da3-small", "da3-base", "da3-large", "da3-giant", "da3-nested-giant-large", "pi3", "pi3x")
#: Those whose depth is in metres (``--metric model``).
METRIC_BACKBONES = ("da3-nested-giant-large", "pi3x")


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Every method parameter of a run, with the paper's / the authors' defaults.

    Frozen; one field per option, declared with :func:`swiftjax.options.option` (type, range or
    choices, help text, stage), which is where each option is documented: ``swiftjax
    reconstruct --help``, the Options page of the documentation (docs/options.md, generated
    from these declarations) and docs/method.md for the equations.  The TOML keys are the field
    names, the CLI flags the same with dashes (``--chunk-size``, ``--[no-]loop-closure``).  An
    instance is valid: the schema and the cross-option rules are checked when it is built.

    A field that feeds a stage option (``target=(StageClass, "field")``) is declared by that
    stage field: its default, help, range and choices are written once, in the stage class.
    The stage objects of a config: ``config.align``, ``config.loops``, ``config.verification``
    (``= config.loops.verification_config``), ``config.geometry`` (the geometric loop source's
    :class:`~swiftjax.loops.options.GeometryOptions`), ``config.graph`` (:func:`swiftjax.options.build`).
    """

    model: str = option(
        "vggt-1b",
        "the network that predicts each chunk (reconstruct, batch; --model-config picks a custom size of "
        "its family; the demo's synthetic oracle ignores it)",
        choices=BACKBONE_NAMES,
        stage="temporal",
    )
    chunk_size: int = option(75, "frames per chunk (B)", low=2, high=10_000, stage="temporal")
    overlap: int = option(
        30,
        "frames shared by neighbouring chunks (O), 1 <= O < chunk_size; default 30, or the "
        "paper's 30/75 of a chunk of 30 frames or fewer",
        low=1,
        high=9_999,
        stage="temporal",
    )
    alignment: str = option(
        "umeyama",
        "chunk alignment: the method's single weighted Umeyama solve, or VGGT-Long's IRLS baseline",
        choices=("umeyama", "irls"),
        stage="temporal",
    )
    depth_threshold: float = option(target=(AlignOptions, "depth_threshold"), stage="temporal")
    conf_ratio: float = option(target=(AlignOptions, "conf_ratio"), stage="temporal")
    min_points: int = option(target=(AlignOptions, "min_points"), low=3, stage="temporal")
    fallback_depth_threshold: float = option(target=(AlignOptions, "fallback_depth_threshold"), stage="temporal")
    overlap_scale: str = option(target=(AlignOptions, "overlap_scale"), stage="temporal")
    loop_depth_threshold: float = option(target=(AlignOptions, "loop_depth_threshold"), stage="loops")
    loop_closure: bool = option(True, "detect loops and add loop edges to the pose graph", stage="loops")
    loop_threshold_rule: str = option(target=(LoopOptions, "rule"), stage="loops")
    loop_threshold: float = option(target=(LoopOptions, "threshold"), stage="loops")
    loop_false_alarms: float = option(target=(LoopOptions, "false_alarms"), stage="loops")
    loop_min_separation: int = option(target=(LoopOptions, "min_separation"), low=1, stage="loops")
    loop_nms_radius: int = option(target=(LoopOptions, "nms_radius"), stage="loops")
    loop_top_k: int = option(target=(LoopOptions, "top_k"), stage="loops")
    whitening_dim: int = option(target=(LoopOptions, "dim"), stage="loops")
    whitening_remove: int = option(target=(LoopOptions, "remove"), stage="loops")
    power_beta: float = option(target=(LoopOptions, "beta"), stage="loops")
    loop_half_window: int = option(target=(LoopOptions, "half_window"), stage="loops")
    loop_verification: str = option(target=(LoopOptions, "verification"), stage="loops")
    loop_min_agreement: float = option(target=(VerificationConfig, "min_agreement"), stage="loops")
    loop_agreement: str = option(target=(VerificationConfig, "agreement_rule"), stage="loops")
    loop_pcm: bool = option(target=(VerificationConfig, "pcm"), stage="loops")
    loop_null_model: str = option(target=(VerificationConfig, "null_model"), stage="loops")
    loop_followers: bool = option(target=(VerificationConfig, "followers"), stage="loops")
    loop_siblings: bool = option(target=(VerificationConfig, "siblings"), stage="loops")
    loop_geometry: bool = option(
        False,
        "experimental: a second loop candidate source: chunk pairs whose dense geometry matches (any driving "
        "direction), edges by point-cloud registration (swiftjax.loops.geometric)",
        stage="loops",
    )
    loop_geometry_neighbours: int = option(target=(GeometryOptions, "neighbours"), stage="loops")
    # The pipeline's own pose-graph defaults (GNC at the chi-squared 0.99 threshold, posegraph.PIPELINE).
    robust_loops: str | None = option(_GRAPH.kernel, target=(GraphOptions, "kernel"), stage="graph")
    robust_scale: float = option(_GRAPH.scale, target=(GraphOptions, "kernel_scale"), optional=False, stage="graph")
    graph_pcm: bool = option(
        True,
        "pose graph: pairwise consistency of every loop edge against the odometry before GNC, which starts "
        "from the maximum consistent set (Kimera-RPGO); false: GNC alone",
        stage="graph",
    )
    edge_information: str = option(
        "data",
        "edge information: data (drift model + each alignment's own statistics) or equal (identity weights, the "
        "authors'; the robust back end still decides inliers on each edge's own noise)",
        choices=("data", "equal"),
        stage="graph",
    )
    edge_pixels_per_sample: float = option(
        196.0,
        "pixels per independent residual in an alignment's information (one 14x14 ViT patch)",
        low=1.0,
        stage="graph",
    )
    max_lm_steps: int = option(target=(GraphOptions, "max_steps"), stage="graph")
    point_conf_ratio: float = option(
        0.75,
        "point cloud: keep pixels with confidence >= ratio x frame mean (stored with the chunks)",
        low=0.0,
        high=10.0,
        stage="temporal",
    )
    point_stride: int = option(
        4,
        "point cloud: keep every k-th pixel in each direction (stored with the chunks)",
        low=1,
        high=1024,
        stage="temporal",
    )
    voxel_size: float | None = option(
        None,
        "point cloud: voxel edge for per-chunk downsampling (none: no downsampling)",
        kind=float,
        low=0.0,
        low_open=True,
        optional=True,
        stage="export",
    )
    colmap: bool = option(
        True,
        "write the COLMAP model and its frames (colmap/; the frames are written while each chunk is "
        "predicted; turned on for a finished run, the export draws them from the input, predicting nothing)",
        stage="export",
    )
    colmap_text: bool = option(False, "also write the COLMAP model's .txt files beside the .bin", stage="export")
    colmap_original_resolution: bool = option(
        False,
        "the COLMAP model at the original image size, with the original files, as VGGT's own export "
        "(the temporal stage then writes no model-resolution frames; turned off again, the export draws "
        "them from the input)",
        stage="export",
    )
    colmap_max_points: int = option(
        200_000, "most points written to the COLMAP model", low=0, high=10**9, stage="export"
    )
    intrinsics: str | None = option(
        None,
        "known intrinsics at the original image size: 'fx fy cx cy', a KITTI calib.txt (P0) "
        "or a COLMAP cameras.txt (PINHOLE / SIMPLE_PINHOLE / undistorted OPENCV)",
        kind=str,
        optional=True,
        stage="temporal",
    )
    metric: str | None = option(
        None,
        "metric scale: 'camera-height=H' (metres above the road), 'gt' (from --gt) or 'model' (the metric "
        "network's own metres: --model da3-nested-giant-large)",
        kind=str,
        optional=True,
        stage="temporal",
    )
    metric_combine: str = option(
        "median",
        "--metric camera-height: combine the chunks' scale factors by their median (one factor for "
        "the world) or as a prior on each chunk's scale in the pose graph",
        choices=METRIC_COMBINE,
        stage="graph",
    )
    metric_prior_sigma: float = option(
        0.02,
        "metric_combine = prior: standard deviation of one chunk's log-scale factor from its road plane",
        low=0.0,
        high=1.0,
        low_open=True,
        stage="graph",
    )
    mask_dir: str | None = option(
        None,
        "one PNG per frame, named like the frame, at the image size; white = keep",
        kind=str,
        optional=True,
        stage="temporal",
    )
    drop_sky: bool = option(
        False,
        "leave out sky pixels (far and unsure: depth > 5x the frame median, confidence < 0.3x)",
        stage="temporal",
    )

    def __post_init__(self) -> None:
        # Each field against its schema (type, range, finiteness, choices), then the rules
        # that involve two fields.  A PipelineConfig that exists is valid.
        options.validate(self)
        if not self.overlap < self.chunk_size:
            raise options.invalid(
                "PipelineConfig.overlap", self.overlap, f"1 <= overlap < chunk_size ({self.chunk_size})"
            )
        from swiftjax.metric_scale import parse_metric

        try:
            parse_metric(self.metric)
        except ValueError as err:
            raise options.OptionError(f"PipelineConfig.metric: {err}") from None
        if self.metric == "model" and self.model not in METRIC_BACKBONES:
            raise options.OptionError(
                f"PipelineConfig.metric: the network's own scale needs a network that predicts metres "
                f"({' or '.join(METRIC_BACKBONES)}), not {self.model}"
            )
        if self.loop_closure and 2 * self.loop_half_window > self.chunk_size:
            half = self.chunk_size // 2
            raise options.invalid(
                "PipelineConfig.loop_half_window",
                self.loop_half_window,
                f"1 <= loop_half_window <= chunk_size / 2 ({half}) with loop closure on: give loop_half_window "
                f"<= {half}, a larger chunk_size, or loop_closure=false",
            )

    @classmethod
    def dependent_defaults(cls, given: dict[str, Any]) -> dict[str, Any]:
        """Defaults that follow the options the user gave (:func:`swiftjax.options.from_sources`):
        ``loop_half_window`` is the paper's 10, or ``chunk_size // 2`` when a smaller chunk
        cannot hold the loop-centric windows; ``overlap`` is the paper's 30, or
        ``round(chunk_size * 30 / 75)`` when the chunk holds 30 frames or fewer.  A value the
        user gave is kept and checked."""
        chunk = given.get("chunk_size", _FIELD_DEFAULTS["chunk_size"])
        overlap = _FIELD_DEFAULTS["overlap"]
        if overlap >= chunk:  # the paper's ratio, O / B = 30 / 75
            overlap = max(1, round(chunk * _FIELD_DEFAULTS["overlap"] / _FIELD_DEFAULTS["chunk_size"]))
        return {"loop_half_window": max(1, min(_FIELD_DEFAULTS["loop_half_window"], chunk // 2)), "overlap": overlap}

    # The stage options objects of this config (options.build at each access).
    align = options.built(AlignOptions)
    loops = options.built(LoopOptions)
    verification = options.built(VerificationConfig)  # = loops.verification_config
    geometry = options.built(GeometryOptions)  # the geometric loop source (loop_geometry)
    graph = options.built(GraphOptions)  # the pipeline's GNC defaults (posegraph.PIPELINE)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> PipelineConfig:
        """Build from a dict (e.g. a TOML table) through the schema: unknown keys and values of
        the wrong type or range are an :class:`~swiftjax.options.OptionError` naming them."""
        return options.from_sources(cls, values)

    def stage_options(self, stage: str) -> dict[str, Any]:
        """The options of one stage (:data:`swiftjax.options.STAGES`), as JSON-able values."""
        return options.stage_options(type(self), self.to_dict(), stage)


_FIELD_DEFAULTS = {f.name: f.default for f in dataclasses.fields(PipelineConfig)}

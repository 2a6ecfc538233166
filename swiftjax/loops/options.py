"""The loop stage's options: every default of detection, loop chunks and verification, once.

:class:`LoopOptions` is the one place the loop defaults are written.  The array functions
(:func:`~swiftjax.loops.power_normalize`, :func:`~swiftjax.loops.fit_whitening`,
:func:`~swiftjax.loops.calibrate_threshold`, :func:`~swiftjax.loops.detect_loops`,
:func:`~swiftjax.loops.loop_chunk_frames`, the dense tests of
:mod:`swiftjax.loops.verification`) take their keyword defaults from ``LoopOptions()``;
:func:`~swiftjax.loops.find_loops` takes a whole ``LoopOptions``; the pipeline's
``PipelineConfig`` loop fields (and so the CLI flags and TOML keys, which derive from them)
take their defaults from it too.  Where each number comes from is documented in
``docs/performance/loops.md``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from swiftjax import options
from swiftjax.options import nested, option

__all__ = [
    "LoopOptions",
    "VerificationConfig",
    "GeometryOptions",
    "DEFAULT_THRESHOLD",
    "AUTHORS_THRESHOLD",
    "DEFAULT_FALSE_ALARMS",
    "THRESHOLD_RULES",
    "FIT_ON",
    "NMS_RULES",
    "VERIFICATION_RULES",
    "AGREEMENT_RULES",
    "NULL_MODELS",
]

#: Cosine threshold on *whitened* descriptors ẑ (d′ = 512) for ``rule="fixed"``.  The
#: authors' 0.98 does not transfer: whitened similarities of true revisits are ~0.4-0.8.
#: Chosen on the synthetic KITTI 00 benchmark (bench/bench_place_recognition.py); re-measure
#: on real VGGT tokens.
DEFAULT_THRESHOLD = 0.43

#: The authors' cosine threshold, on descriptors whitened by a PCA fitted on g⁰ and applied to
#: g¹ (their code's quirk); ``LoopOptions(rule="authors")``.
AUTHORS_THRESHOLD = 0.98

#: ``α`` of :func:`~swiftjax.loops.calibrate_threshold`: the expected number of frames
#: WITHOUT a revisit whose best match still passes the threshold, per sequence.
DEFAULT_FALSE_ALARMS = 1e-3

#: ``LoopOptions(rule=...)``: ``"adaptive"`` (default, :func:`~swiftjax.loops.calibrate_threshold`),
#: ``"fixed"`` (``threshold``), ``"authors"`` (0.98, whitening fitted on g⁰).
THRESHOLD_RULES = ("adaptive", "fixed", "authors")

#: What the whitening is fitted on: ``"power"`` (g¹, what it is applied to) or ``"raw"`` (g⁰).
FIT_ON = ("power", "raw")

#: Non-maximum suppression of :func:`~swiftjax.loops.detect_loops`.
NMS_RULES = ("pair", "frame")

#: ``"geometric"``: every candidate is verified (:mod:`swiftjax.loops.verification`);
#: ``"none"``: every candidate above the threshold is a loop edge (the authors' rule).
VERIFICATION_RULES = ("geometric", "none")

#: How the dense agreement of a candidate is judged: ``"null"`` against the agreement the same
#: two chunks give under clearly wrong edges (:mod:`swiftjax.loops.null`, no tuned constant);
#: ``"fixed"``: against ``min_agreement`` (0.55, read off KITTI 00 and the demo).
AGREEMENT_RULES = ("null", "fixed")
#: How the dense test's null samples bound a wrong edge's agreement
#: (:func:`swiftjax.loops.null.null_threshold`): a line in the shift per side, both sides pooled,
#: or each side's samples as draws of their own.
NULL_MODELS = ("trend", "pooled", "sided")


@dataclasses.dataclass(frozen=True)
class VerificationConfig:
    """Thresholds of :func:`~swiftjax.loops.verification.verify_candidates`.

    Chosen from measured distributions of true and false candidates (the numbers and the
    benchmarks behind them: ``docs/performance/loops.md``).  The dense agreement is judged per
    candidate against its own null distribution (``agreement_rule = "null"``,
    :mod:`swiftjax.loops.null`: the one-sided prediction bound at false-alarm rate
    ``null_false_alarm`` and a chance-corrected agreement of at least ``null_min_kappa``, over ``null_samples`` edges shifted sideways by
    ``null_min_shift``..``null_max_shift`` of the median depth); ``agreement_rule = "fixed"`` uses
    ``min_agreement = 0.55``, which sits in the gap between the true and false candidates'
    dense scores of KITTI 00 and the demo, on the precision side (another route's true
    candidates scored 0.34-0.44: it does not transfer);
    ``pcm_threshold`` is ``sqrt(χ²_7(0.999))``; the drift sigmas are of the order of the
    measured temporal-edge and loop-edge errors of the synthetic routes (real VGGT's drift is
    not measured here: they are options).

    Attributes:
        agreement_rule: :data:`AGREEMENT_RULES`.
        min_agreement: ``agreement_rule = "fixed"`` (and the fallback of ``"null"`` when
            fewer than three null edges see the other chunk): the smaller direction's
            ``agreement`` (pairs in view whose depth agrees) must reach this.
        null_samples: ``K``, null edges per candidate (even, >= 4).
        null_false_alarm: ``α``, the probability that a chance agreement passes the null's
            significance test.
        null_min_kappa: ``κ_min``, the least chance-corrected agreement
            ``(a − m) / (1 − m)`` (Landis and Koch's "fair").
        null_min_shift, null_max_shift: the null edges' sideways offsets, fractions of the
            target chunk's median depth.
        null_model: :data:`NULL_MODELS`, how the null samples bound a wrong edge's agreement
            (:func:`swiftjax.loops.null.null_threshold`): ``trend`` (each shift direction's
            agreement a line in the shift, the candidate above both lines' prediction bounds
            over the shifts' range), ``pooled`` (both directions' samples one normal sample,
            the rule before it) or ``sided`` (each direction's samples their own normal
            sample); docs/performance/loops.md for what each does on which route.
        min_overlap: the smaller direction's ``overlap`` (reliable points seen at all).
        depth_tolerance: relative depth agreement ``τ``.
        stride: source pixel subsampling of the dense test.
        neighbours: nearest target frames each source frame is compared with.
        min_fraction: each half alignment's ``fraction_used`` must reach this.
        pcm: run the pairwise test (with two or more candidates left).
        followers: a registration edge of the geometric source that passes the null's
            significance test but not ``null_min_kappa`` may still be accepted when it beats
            the agreement its source's registrations reach on unrelated chunks
            (``registered_null_threshold``), only beside verified loops it is consistent with
            (:mod:`swiftjax.loops.verification`, "Followers").
        siblings: a registration edge of the geometric source whose own evidence does not
            beat its nulls may still be accepted beside an accepted loop of the same revisit
            (each chunk within one chunk of the loop's), when consistent with every accepted
            loop (:mod:`swiftjax.loops.verification`, "Siblings").
        pcm_threshold: whitened cycle residual bound, ``sqrt(χ²_7(0.999)) = 4.93``.
        odo_sigma_rot, odo_sigma_trans, odo_sigma_scale: drift model of a temporal edge
            (:func:`~swiftjax.loops.verification.odometry_covariance`).
        loop_sigma_rot, loop_sigma_trans, loop_sigma_scale: of a loop edge
            (:func:`~swiftjax.loops.verification.loop_covariance`).
    """

    agreement_rule: str = option(
        "null",
        "loop verification: null (the dense agreement must beat what the same two chunks give under "
        "clearly wrong edges, per candidate) or fixed (must reach {min_agreement})",
        choices=AGREEMENT_RULES,
    )
    min_agreement: float = option(
        0.55, "loop verification: the dense test's bound (fraction of agreeing pixels)", low=0.0, high=1.0
    )
    null_samples: int = option(16, "null edges per candidate (even)", low=4)
    null_false_alarm: float = option(
        0.01, "false-alarm rate of the null test", low=0.0, high=1.0, low_open=True, high_open=True
    )
    null_min_kappa: float = option(0.2, "least chance-corrected agreement", low=0.0, high=1.0, high_open=True)
    null_min_shift: float = option(0.15, "smallest null offset (of the median depth)", low=0.0, low_open=True)
    null_max_shift: float = option(0.4, "largest null offset (of the median depth)", low=0.0, low_open=True)
    null_model: str = option(
        "trend",
        "how the null samples bound a wrong edge's agreement: a line in the shift per shift direction, "
        "one normal sample, or one per direction",
        choices=NULL_MODELS,
    )
    min_overlap: float = option(0.2, "least fraction of reliable points seen", low=0.0, high=1.0)
    depth_tolerance: float = option(0.05, "relative depth agreement", low=0.0, low_open=True)
    stride: int = option(4, "source pixel subsampling of the dense test", low=1)
    neighbours: int = option(3, "nearest target frames per source frame (0: every frame)", low=0)
    min_fraction: float = option(0.05, "least fraction_used of each half alignment", low=0.0, high=1.0)
    pcm: bool = option(True, "loop verification: the pairwise consistency test")
    followers: bool = option(
        True,
        "loop verification: a registration edge below the least chance-corrected agreement that beats its "
        "source's registrations on unrelated chunks joins the verified loops it is consistent with",
    )
    siblings: bool = option(
        False,
        "loop verification: a registration edge whose own evidence does not beat its nulls joins an accepted "
        "loop of the same revisit (each chunk within one of its own) when consistent with every accepted loop",
    )
    pcm_threshold: float = option(4.93, "whitened cycle residual bound", low=0.0, low_open=True)
    odo_sigma_rot: float = option(0.01, "temporal-edge drift: rotation sigma", low=0.0, low_open=True)
    odo_sigma_trans: float = option(0.05, "temporal-edge drift: translation sigma", low=0.0, low_open=True)
    odo_sigma_scale: float = option(0.04, "temporal-edge drift: log-scale sigma", low=0.0, low_open=True)
    loop_sigma_rot: float = option(0.015, "loop-edge drift: rotation sigma", low=0.0, low_open=True)
    loop_sigma_trans: float = option(0.05, "loop-edge drift: translation sigma", low=0.0, low_open=True)
    loop_sigma_scale: float = option(0.03, "loop-edge drift: log-scale sigma", low=0.0, low_open=True)

    def __post_init__(self) -> None:
        options.validate(self)
        if self.null_samples % 2:
            raise options.invalid("VerificationConfig.null_samples", self.null_samples, "an even integer >= 4")
        if not self.null_min_shift <= self.null_max_shift:
            raise options.invalid(
                "VerificationConfig.null_min_shift",
                self.null_min_shift,
                f"0 < null_min_shift <= null_max_shift ({self.null_max_shift})",
            )

    def replace(self, **changes: Any) -> VerificationConfig:
        """A validated copy with ``changes`` (:func:`swiftjax.options.replace`)."""
        return options.replace(self, **changes)


@dataclasses.dataclass(frozen=True)
class LoopOptions:
    """Every option of the loop stage, with its default (frozen; ``replace`` to vary).

    Descriptors (:mod:`swiftjax.loops.descriptors`):
        beta: signed power ``β`` of :func:`~swiftjax.loops.power_normalize`.
        remove: leading PCA components dropped by the whitening (``r``).
        dim: descriptor dimension kept by the whitening (``d′``).
        eps: whitening regulariser ``ε`` in ``W = Q (Λ + ε)^-½``.
        max_samples: most descriptors the whitening's covariance is computed from.
        fit_on: ``"power"`` (fit on g¹, what it is applied to) or ``"raw"`` (g⁰, the
            authors' code).
        adapt_to_length: cap ``d′`` at ``max(8, N // 4)`` on short sequences and floor the
            fixed threshold at ``5/sqrt(d′)`` (:func:`~swiftjax.loops.find_loops`).

    Detection (:mod:`swiftjax.loops.detection`):
        rule: :data:`THRESHOLD_RULES`.
        threshold: cosine threshold of ``rule="fixed"``.
        false_alarms: ``α`` of ``rule="adaptive"``, in ``(0, 1)``.
        min_separation: fewest frames between the two frames of a loop.
        nms_radius: non-maximum suppression radius ``r`` (frames).
        top_k: most candidates per frame before suppression.
        max_loops: NMS buffer size (``None``: the bound of
            :func:`~swiftjax.loops.detect_loops`).
        nms: :data:`NMS_RULES`.

    Loop chunks (:mod:`swiftjax.loops.loop_chunk`):
        half_window: ``h``; the loop-centric chunk holds ``2h`` frames around each end (the
            depth threshold of its alignment is an alignment option, ``AlignOptions``).

    Verification (:mod:`swiftjax.loops.verification`):
        verification: :data:`VERIFICATION_RULES`.
        verification_config: the thresholds of the geometric tests.

    Raises:
        swiftjax.options.OptionError: an unknown rule / ``fit_on`` / ``nms`` or a value out of range.
    """

    beta: float = option(0.5, "signed power applied to the descriptors (beta)", low=0.0, high=1.0, low_open=True)
    remove: int = option(1, "leading PCA components dropped by the whitening (r)", low=0, high=65_536)
    dim: int = option(512, "descriptor dimension kept by the PCA whitening (d')", low=1, high=65_536)
    eps: float = option(1e-6, "whitening regulariser", low=0.0)
    max_samples: int = option(50_000, "most descriptors the whitening is fitted on", low=2)
    fit_on: str = option("power", "what the whitening is fitted on", choices=FIT_ON)
    adapt_to_length: bool = option(True, "adapt d' and the fixed threshold to short sequences")
    rule: str = option(
        "adaptive",
        "how the loop threshold is set (see swiftjax.loops): adaptive (calibrated on the scene's own "
        "similarity distribution), fixed ({threshold}) or authors",
        choices=THRESHOLD_RULES,
    )
    threshold: float = option(
        DEFAULT_THRESHOLD,
        "cosine similarity of whitened descriptors above which a frame pair is a loop candidate",
        low=-1.0,
        high=1.0,
    )
    false_alarms: float = option(
        DEFAULT_FALSE_ALARMS,
        "adaptive threshold: accepted rate of false loop candidates",
        low=0.0,
        high=1.0,
        low_open=True,
        high_open=True,
    )
    min_separation: int = option(100, "fewest frames between the two frames of a loop", low=0, high=10**7)
    nms_radius: int = option(25, "non-maximum suppression radius of loop candidates (frames)", low=0, high=10**7)
    top_k: int = option(8, "most loop candidates kept per frame before suppression", low=1, high=1000)
    max_loops: int | None = option(None, "NMS buffer size (none: the bound)", kind=int, low=1, optional=True)
    nms: str = option("pair", "non-maximum suppression rule", choices=NMS_RULES)
    half_window: int = option(
        10,
        "frames taken around each end of a loop for the loop-centric chunk (1 <= w <= chunk_size / 2; "
        "default 10, or chunk_size / 2 when that is smaller)",
        low=1,
        high=5_000,
    )
    verification: str = option(
        "geometric",
        "geometric: a candidate must pass the cross-chunk dense test, the loop-chunk quality test and "
        "pairwise consistency to become an edge; none: every candidate above the threshold is one (the authors)",
        choices=VERIFICATION_RULES,
    )
    verification_config: VerificationConfig = nested(VerificationConfig)

    def __post_init__(self) -> None:
        options.validate(self)

    def replace(self, **changes: Any) -> LoopOptions:
        """A validated copy with ``changes`` (:func:`swiftjax.options.replace`)."""
        return options.replace(self, **changes)


def check_values(values: dict[str, Any], where: str) -> None:
    """Reject the entries of ``values`` (``LoopOptions`` field names; others are ignored) that
    no ``LoopOptions`` accepts: an :class:`~swiftjax.options.OptionError` naming ``where`` and
    the field (the schema of :class:`LoopOptions`; for array functions that take single
    options as arguments)."""
    table = options.specs(LoopOptions)
    for key, value in values.items():
        if key in table:
            options.coerce(table[key], f"LoopOptions.{key} ({where})", value)


@dataclasses.dataclass(frozen=True)
class GeometryOptions:
    """Options of the geometric loop source (every field is static: a change recompiles).

    Declared with :func:`swiftjax.options.option` (ranges checked at construction, an
    :class:`~swiftjax.options.OptionError` naming the field); the Tukey schedules must not grow
    (``tau_end <= tau_start``) and the coarse subsamples are the first points of the fine ones.

    Attributes:
        frame_stride: every ``frame_stride``-th frame of a chunk is read (host level).
        row_stride, column_stride: the pixel grid sampled in those frames.
        anchors: anchors per chunk (camera centres spread evenly over the loaded frames).
        rings, sectors: the polar grid ``N_r x N_s``.
        max_radius: ``ρ_max`` in camera heights (24 h ≈ 40 m at KITTI's 1.65 m).
        max_height: ``z_max``, heights are clipped there (camera heights).
        conf_ratio: reliable points: confidence ``> conf_ratio x`` the frame mean (eq. 2's λ_γ).
        min_points: fewest reliable points near an anchor for a signature.
        ground_band: points with ``z < ground_band`` are road (not structure).
        max_distance: largest signature distance ``d_σ`` of a candidate.
        max_sc_distance: largest Scan Context distance ``d_SC(m*)`` of a candidate.
        top_k: best matches kept per chunk.
        gate_min, gate_drift: the odometry gate of the pipeline's candidates (camera heights;
            fraction of the path driven between the two chunks).
        src_points, dst_points: registration subsample sizes ``P``, ``Q``.
        iterations: ICP iterations ``n``.
        tau_start, tau_end: Tukey radius schedule ``τ_0 → τ_n`` (camera heights).
        min_inlier_ratio: the verdict's bound on the structure inlier ratio.
        max_rms: the verdict's bound on the inliers' RMS (camera heights).
        max_scale_ratio: ``s / s₀`` must lie in ``[1 / r, r]``.
        min_spread: ``λ₂ / λ₁`` of the inlying structure's horizontal spread.
        min_structure: fewest inlying structure points.
        coarse_src_points, coarse_dst_points, coarse_iterations, coarse_tau_start, coarse_tau_end:
            the coarse ICP
            run from every start hypothesis (:func:`register_hypotheses`): the first points of
            the registration subsamples, its iterations and its Tukey radii.  The target keeps
            all ``dst_points`` rows by default: with a sparser target the structure-inlier score
            cannot tell a street's half turn from the truth (tests: the corner scene).
        colour_tolerance: the co-visible search's colour test: a nearest-neighbour pair whose
            chromaticities (:func:`swiftjax.loops.geometric.chromaticity`) differ by more than
            this in some channel is no match (:func:`swiftjax.loops.geometric.register`);
            1: colour unused (chromaticities differ by less).  It must lie between one
            surface's chromaticity noise (the same paint seen twice: shading and exposure scale
            all channels alike) and the difference between paints.
        slide_steps: the co-visible search along the street: a candidate above the null is
            also ICP'd from its best placement shifted ``±k peak_separation / 2`` along the
            target's heading, ``k = 1 … slide_steps``
            (:func:`swiftjax.loops.geometric.slide_starts`); 0: the bird's-eye peaks only.
        neighbours: the co-visible search's joint registration: each chunk's structure cloud
            merged with those of the ``neighbours`` chunks on each side, placed by the odometry
            chain (:func:`swiftjax.loops.geometric.merge_neighbours`); the placement, the null
            and the refinement then run on ``2 neighbours + 1`` times the rows
            (:meth:`rows`), so their time grows about ``(2 neighbours + 1)²``-fold.  0: each
            chunk alone.
    """

    frame_stride: int = option(5, "every k-th frame of a chunk is read", low=1)
    row_stride: int = option(6, "rows between sampled pixels", low=1)
    column_stride: int = option(8, "columns between sampled pixels", low=1)
    anchors: int = option(5, "anchors (camera centres) per chunk", low=1)
    rings: int = option(20, "rings N_r of the polar grid", low=1)
    sectors: int = option(60, "sectors N_s of the polar grid", low=1)
    max_radius: float = option(24.0, "grid radius rho_max (camera heights)", low=0.0, low_open=True)
    max_height: float = option(8.0, "heights clipped at z_max (camera heights)", low=0.0, low_open=True)
    conf_ratio: float = option(0.5, "reliable: confidence > ratio x frame mean", low=0.0, high=10.0)
    min_points: int = option(200, "fewest reliable points near an anchor", low=1)
    ground_band: float = option(0.35, "points below this height are road (camera heights)", low=0.0)
    max_distance: float = option(0.25, "largest signature distance of a candidate", low=0.0, low_open=True)
    max_sc_distance: float = option(0.45, "largest Scan Context distance of a candidate", low=0.0, low_open=True)
    top_k: int = option(2, "best matches kept per chunk", low=1)
    gate_min: float = option(15.0, "odometry gate floor (camera heights)", low=0.0)
    gate_drift: float = option(0.1, "odometry gate per path length driven", low=0.0)
    src_points: int = option(1024, "registration source subsample P", low=1)
    dst_points: int = option(4096, "registration target subsample Q", low=1)
    iterations: int = option(16, "ICP iterations", low=1)
    tau_start: float = option(3.0, "first Tukey radius (camera heights)", low=0.0, low_open=True)
    tau_end: float = option(0.25, "last Tukey radius (camera heights)", low=0.0, low_open=True)
    min_inlier_ratio: float = option(0.5, "verdict: least structure inlier ratio", low=0.0, high=1.0)
    max_rms: float = option(0.2, "verdict: largest inlier RMS (camera heights)", low=0.0, low_open=True)
    max_scale_ratio: float = option(1.3, "verdict: s / s0 within [1/r, r]", low=1.0)
    min_spread: float = option(0.02, "verdict: least horizontal spread lambda_2 / lambda_1", low=0.0, high=1.0)
    min_structure: int = option(60, "verdict: fewest inlying structure points", low=0)
    coarse_src_points: int = option(256, "coarse ICP: source points (first of the subsample)", low=1)
    coarse_dst_points: int = option(4096, "coarse ICP: target points (first of the subsample)", low=1)
    coarse_iterations: int = option(8, "coarse ICP iterations", low=1)
    coarse_tau_start: float = option(3.0, "coarse ICP: first Tukey radius", low=0.0, low_open=True)
    coarse_tau_end: float = option(0.5, "coarse ICP: last Tukey radius", low=0.0, low_open=True)
    bev_cells: int = option(128, "co-visible search: bird's-eye grid cells per side", low=8)
    bev_cell: float = option(0.75, "co-visible search: bird's-eye cell (camera heights)", low=0.0, low_open=True)
    structure_height: float = option(0.5, "co-visible search: structure above the road (camera heights)", low=0.0)
    yaw_search: float = option(4.0, "co-visible search: yaw around the chain's (degrees)", low=0.0)
    yaw_steps: int = option(5, "co-visible search: yaws tried", low=1)
    scale_search: float = option(0.18, "co-visible search: log-scale around the chain's", low=0.0)
    scale_steps: int = option(3, "co-visible search: scales tried", low=1)
    peaks: int = option(3, "co-visible search: correlation peaks refined", low=1)
    peak_separation: float = option(4.0, "co-visible search: distinct placements (camera heights)", low=0.0)
    max_window: float = option(40.0, "co-visible search: largest translation window (camera heights)", low=1.0)
    slide_steps: int = option(
        3, "co-visible search: starts on each side of the best placement along the street (0: none)", low=0
    )
    peak_src_points: int = option(256, "co-visible search: source points refined per peak", low=1)
    peak_dst_points: int = option(1024, "co-visible search: target points refined per peak", low=1)
    refine_iterations: int = option(6, "co-visible search: ICP iterations of the best placement on all rows", low=1)
    refine_scale_steps: int = option(
        9, "co-visible search: scales tried about the best placement before its ICP (odd; 1: none)", low=1
    )
    null_chunks: int = option(8, "verdict: unrelated chunks the source is also registered against", low=3)
    null_false_alarm: float = option(
        1e-2, "verdict: false-alarm rate of the registration null", low=0.0, high=1.0, low_open=True, high_open=True
    )
    colour_tolerance: float = option(
        0.03,
        "co-visible search: largest chromaticity difference of a match (1: colour unused)",
        low=0.0,
        high=1.0,
        low_open=True,
    )
    neighbours: int = option(
        0,
        "co-visible search: chunks merged on each side of both chunks of a pair, a joint registration "
        "(1: three chunks each; 4-8x the stage's time)",
        low=0,
        high=4,
    )

    def __post_init__(self) -> None:
        options.validate(self)
        # (a, b, why): a must not exceed b.
        for a, b, why in (
            ("tau_end", "tau_start", ""),
            ("coarse_tau_end", "coarse_tau_start", ""),
            ("coarse_src_points", "src_points", " (its first points)"),
            ("coarse_dst_points", "dst_points", " (its first points)"),
            ("peak_src_points", "src_points", " (its first points)"),
            ("peak_dst_points", "dst_points", " (its first points)"),
        ):
            if getattr(self, a) > getattr(self, b):
                raise options.invalid(
                    f"GeometryOptions.{a}", getattr(self, a), f"at most {b} = {getattr(self, b)!r}{why}"
                )
        if self.refine_scale_steps % 2 == 0:
            raise options.invalid("GeometryOptions.refine_scale_steps", self.refine_scale_steps, "an odd integer")

    def rows(self, n: int) -> int:
        """Rows of a merged structure cloud that hold ``n`` rows of each of its ``2 neighbours + 1``
        chunks (:func:`swiftjax.loops.geometric.merge_neighbours` interleaves them)."""
        return n * (2 * self.neighbours + 1)

    @property
    def pixel_stride(self) -> tuple[int, int]:
        """``(row_stride, column_stride)``."""
        return self.row_stride, self.column_stride

    def replace(self, **changes: Any) -> GeometryOptions:
        """A validated copy with ``changes`` (:func:`swiftjax.options.replace`)."""
        return options.replace(self, **changes)

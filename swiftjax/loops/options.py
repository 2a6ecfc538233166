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

__all__ = [
    "LoopOptions",
    "VerificationConfig",
    "DEFAULT_THRESHOLD",
    "AUTHORS_THRESHOLD",
    "DEFAULT_FALSE_ALARMS",
    "THRESHOLD_RULES",
    "FIT_ON",
    "NMS_RULES",
    "VERIFICATION_RULES",
    "AGREEMENT_RULES",
]

#: Cosine threshold on *whitened* descriptors ẑ (d′ = 512) for ``rule="fixed"``.  The
#: authors' 0.98 does not transfer: whitened similarities of true revisits are ~0.4-0.8.
#: Chosen on the synthetic KITTI 00 benchmark (bench/bench_place_recognition.py); re-measure
#: on real VGGT tokens.
DEFAULT_THRESHOLD = 0.43

#: The authors' cosine threshold, on descriptors whitened by a PCA fitted on g⁰ and applied to
#: g¹ (their code's quirk); ``find_loops(rule="authors")``.
AUTHORS_THRESHOLD = 0.98

#: ``α`` of :func:`~swiftjax.loops.calibrate_threshold`: the expected number of frames
#: WITHOUT a revisit whose best match still passes the threshold, per sequence.
DEFAULT_FALSE_ALARMS = 1e-3

#: ``find_loops(rule=...)``: ``"adaptive"`` (default, :func:`~swiftjax.loops.calibrate_threshold`),
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
        min_overlap: the smaller direction's ``overlap`` (reliable points seen at all).
        depth_tolerance: relative depth agreement ``τ``.
        stride: source pixel subsampling of the dense test.
        neighbours: nearest target frames each source frame is compared with.
        min_fraction: each half alignment's ``fraction_used`` must reach this.
        pcm: run the pairwise test (with two or more candidates left).
        pcm_threshold: whitened cycle residual bound, ``sqrt(χ²_7(0.999)) = 4.93``.
        odo_sigma_rot, odo_sigma_trans, odo_sigma_scale: drift model of a temporal edge
            (:func:`~swiftjax.loops.verification.odometry_covariance`).
        loop_sigma_rot, loop_sigma_trans, loop_sigma_scale: of a loop edge
            (:func:`~swiftjax.loops.verification.loop_covariance`).
    """

    agreement_rule: str = "null"
    min_agreement: float = 0.55
    null_samples: int = 16
    null_false_alarm: float = 0.01
    null_min_kappa: float = 0.2
    null_min_shift: float = 0.15
    null_max_shift: float = 0.4
    min_overlap: float = 0.2
    depth_tolerance: float = 0.05
    stride: int = 4
    neighbours: int = 3
    min_fraction: float = 0.05
    pcm: bool = True
    pcm_threshold: float = 4.93
    odo_sigma_rot: float = 0.01
    odo_sigma_trans: float = 0.05
    odo_sigma_scale: float = 0.04
    loop_sigma_rot: float = 0.015
    loop_sigma_trans: float = 0.05
    loop_sigma_scale: float = 0.03

    def __post_init__(self) -> None:
        if self.agreement_rule not in AGREEMENT_RULES:
            raise ValueError(
                "VerificationConfig: agreement_rule must be "
                + " or ".join(map(repr, AGREEMENT_RULES))
                + f", got {self.agreement_rule!r}"
            )
        if self.null_samples < 4 or self.null_samples % 2:
            raise ValueError(f"VerificationConfig: null_samples must be even and >= 4, got {self.null_samples}")
        if not 0.0 < self.null_false_alarm < 1.0:
            raise ValueError(f"VerificationConfig: null_false_alarm must be in (0, 1), got {self.null_false_alarm}")
        if not 0.0 <= self.null_min_kappa < 1.0:
            raise ValueError(f"VerificationConfig: null_min_kappa must be in [0, 1), got {self.null_min_kappa}")
        if not 0.0 < self.null_min_shift <= self.null_max_shift:
            raise ValueError(
                "VerificationConfig: need 0 < null_min_shift <= null_max_shift, got "
                f"{self.null_min_shift}, {self.null_max_shift}"
            )


@dataclasses.dataclass(frozen=True)
class LoopOptions:
    """Every option of the loop stage, with its default (frozen; ``dataclasses.replace`` to vary).

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
        ValueError: an unknown rule / ``fit_on`` / ``nms`` or a value out of range.
    """

    beta: float = 0.5
    remove: int = 1
    dim: int = 512
    eps: float = 1e-6
    max_samples: int = 50_000
    fit_on: str = "power"
    adapt_to_length: bool = True
    rule: str = "adaptive"
    threshold: float = DEFAULT_THRESHOLD
    false_alarms: float = DEFAULT_FALSE_ALARMS
    min_separation: int = 100
    nms_radius: int = 25
    top_k: int = 8
    max_loops: int | None = None
    nms: str = "pair"
    half_window: int = 10
    verification: str = "geometric"
    verification_config: VerificationConfig = VerificationConfig()

    def __post_init__(self) -> None:
        check_values(dataclasses.asdict(self), "LoopOptions")


def check_values(values: dict[str, Any], where: str) -> None:
    """Reject the entries of ``values`` (``LoopOptions`` field names; others are ignored)
    that no ``LoopOptions`` accepts, naming ``where`` in the error."""
    choices = {"rule": THRESHOLD_RULES, "fit_on": FIT_ON, "nms": NMS_RULES, "verification": VERIFICATION_RULES}
    for key, allowed in choices.items():
        if key in values and values[key] not in allowed:
            if key == "rule":
                raise ValueError(f"{where}: rule must be one of {allowed}, got {values[key]!r}")
            raise ValueError(f"{where}: {key} must be " + " or ".join(map(repr, allowed)) + f", got {values[key]!r}")
    if "false_alarms" in values and not 0.0 < float(values["false_alarms"]) < 1.0:
        raise ValueError(f"{where}: false_alarms must be in (0, 1), got {values['false_alarms']}")
    for key, low in (
        ("remove", 0),
        ("dim", 1),
        ("max_samples", 2),
        ("min_separation", 0),
        ("nms_radius", 0),
        ("top_k", 1),
        ("half_window", 1),
    ):
        if key in values and values[key] < low:
            raise ValueError(f"{where}: {key} must be >= {low}, got {values[key]}")
    if values.get("max_loops") is not None and values["max_loops"] < 1:
        raise ValueError(f"{where}: max_loops must be >= 1, got {values['max_loops']}")

"""The synthetic oracle's error model: :class:`OracleNoise` (what VGGT gets wrong in every chunk)
and :class:`Hallucination` (what it returns for a loop-centric chunk whose halves share no view).

The equations each field enters are in :mod:`swiftjax.synthetic.oracle`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Hallucination", "OracleNoise"]


@dataclasses.dataclass(frozen=True)
class OracleNoise:
    """Every error of the oracle (:mod:`swiftjax.synthetic.oracle`); defaults make drift visible without loops.

    Angles in radians, ``*_m`` in metres, depth noise relative, pose translation in chunk units.
    """

    depth_units: float = 2.0
    scale_jitter: float = 0.03
    drift_rot: float = 1e-4  # rad per frame, per axis
    drift_scale: float = 4e-4  # log-scale per frame
    pose_rot: float = 2e-4
    pose_trans: float = 2e-3
    focal: float = 0.02
    focal_depth_coupling: float = 1.0
    depth_rel: float = 0.01
    depth_rel_ref_m: float = 20.0
    depth_bias: float = 0.005
    edge_log_ratio: float = 0.1
    edge_conf: float = 0.15
    gross_fraction: float = 0.01
    gross_log: float = 0.7
    sky_depth_m: float = 300.0
    conf_max: float = 20.0
    conf_falloff_m: float = 25.0
    chunk_share: float = 0.5
    mover_depth: float = 0.05  # log-std of a car's depth factor, drawn per (chunk, car)

    @classmethod
    def off(cls, depth_units: float = 2.0, scale_jitter: float = 0.0) -> OracleNoise:
        """No error at all: depths, poses and intrinsics are the truth in the chunk gauge."""
        return cls(
            depth_units=depth_units,
            scale_jitter=scale_jitter,
            drift_rot=0.0,
            drift_scale=0.0,
            pose_rot=0.0,
            pose_trans=0.0,
            focal=0.0,
            depth_rel=0.0,
            depth_bias=0.0,
            edge_log_ratio=np.inf,
            gross_fraction=0.0,
        )


@dataclasses.dataclass(frozen=True)
class Hallucination:
    """How a loop-centric chunk whose halves share no view comes back (:mod:`swiftjax.synthetic.oracle`).

    Attributes:
        covis_low: mutual co-visibility at or below which the second half is fully re-based.
        covis_high: at or above which the chunk is honest (bit-identical to ``hallucination=None``).
        rot: standard deviation per axis of the offset ``Delta``'s rotation, radians.
        trans_m: standard deviation per axis of its translation, metres.
        conf_factor: factor on ``conf - 1`` at full hallucination (``w = 1``).
        stride: pixel step of the co-visibility sample grid.
        rel_tol: relative depth agreement of the co-visibility test.
    """

    covis_low: float = 0.05
    covis_high: float = 0.3
    rot: float = 0.02
    trans_m: float = 0.3
    conf_factor: float = 0.5
    stride: int = 8
    rel_tol: float = 0.1

    def __post_init__(self) -> None:
        if not 0.0 <= self.covis_low < self.covis_high:
            raise ValueError(
                f"Hallucination needs 0 <= covis_low < covis_high, got {self.covis_low}, {self.covis_high}"
            )
        if self.rot < 0 or self.trans_m < 0 or not 0 < self.conf_factor <= 1:
            raise ValueError(
                f"Hallucination needs rot, trans_m >= 0 and conf_factor in (0, 1], got {self.rot}, "
                f"{self.trans_m}, {self.conf_factor}"
            )
        if self.stride < 1 or self.rel_tol <= 0:
            raise ValueError(f"Hallucination needs stride >= 1, rel_tol > 0, got {self.stride}, {self.rel_tol}")

    def weight(self, covisibility: float) -> float:
        """``w = smoothstep((c_high - c) / (c_high - c_low))``: 1 at ``c <= c_low``, 0 at ``c >= c_high``."""
        u = min(max((self.covis_high - float(covisibility)) / (self.covis_high - self.covis_low), 0.0), 1.0)
        return u * u * (3.0 - 2.0 * u)

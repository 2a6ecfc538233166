"""The pose graph's options: :class:`GraphOptions`, every default written once.

:func:`swiftjax.posegraph.optimize` takes a ``GraphOptions`` (or its fields as keywords), the
pipeline's :class:`~swiftjax.pipeline.PipelineConfig` and the CLI take their pose-graph
defaults from :data:`PIPELINE` (the pipeline's choice: GNC on the loop edges).  Validation
happens at construction: a ``GraphOptions`` that exists is valid.

What recompiles: ``max_steps``, ``damping``, ``initialization``, the resolved
``linear_solver`` and ``max_linear_iterations`` are static (part of the compiled programs);
tolerances, ``lambda0``, ``eta_max``, ``kernel``/``kernel_scale`` and every GNC setting are
traced or host values and never recompile.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

from swiftjax.posegraph.gnc import DEFAULT_SCALE
from swiftjax.posegraph.kernels import check_kernel
from swiftjax.posegraph.solver_choice import check_linear_solver

__all__ = ["GraphOptions", "PIPELINE", "DAMPINGS", "INITIALIZATIONS"]

DAMPINGS = ("identity", "marquardt")
INITIALIZATIONS = ("none", "chordal")


@dataclasses.dataclass(frozen=True)
class GraphOptions:
    """Options of :func:`swiftjax.posegraph.optimize`.

    Attributes:
        max_steps: LM iterations (accepted + rejected); static.
        rtol, atol: stop on an accepted step whose cost decrease is ``<= rtol * cost`` or
            ``<= atol`` (GTSAM's ``relativeErrorTol`` / ``absoluteErrorTol``).
        gtol: stop when ``|g|_inf <= gtol * |g_0|_inf``.
        lambda0: initial damping ``lambda``.
        damping: ``"identity"`` damps with ``lambda I`` (GTSAM's default, in tangent units);
            ``"marquardt"`` with ``lambda clip(diag H)``, which along chains damps exactly the
            weak rigid-rotation directions the step needs.
        initialization: ``"none"`` starts LM at ``problem.poses``; ``"chordal"`` first solves the
            three linear problems of :mod:`swiftjax.posegraph.initialization` and starts there
            (the global basin on large graphs with many loops).  Robust kernels do not enter
            the initialisation: keep ``"none"`` when the given poses are good and some loops
            may be false (the pipeline's case).
        linear_solver: ``"auto"`` (:func:`~swiftjax.posegraph.choose_linear_solver`),
            ``"dense"``, ``"pcg"`` or ``"sparse"`` (:mod:`swiftjax.posegraph.linear_solvers`).
        max_linear_iterations: PCG cap per LM step (static).
        eta_max: loosest PCG relative tolerance (Eisenstat–Walker forcing
            ``eta = min(eta_max, sqrt(|g|/|g0|))``).
        kernel, kernel_scale: robust treatment of the edges flagged ``problem.robust``
            (:mod:`swiftjax.posegraph.kernels`), scale in whitened units ``sqrt(r^T Omega r)``:
            ``"huber"``/``"cauchy"`` (IRLS inside LM; scale default 1) or ``"gnc"``
            (:mod:`swiftjax.posegraph.gnc`; ``kernel_scale`` the inlier threshold ``c``, default
            :data:`~swiftjax.posegraph.gnc.DEFAULT_SCALE` ``= sqrt(chi2_7^-1(0.99))``).
            Edges not flagged robust are never down-weighted.
        gnc_max_iterations, gnc_mu_step, gnc_weights_tol, gnc_cost_tol: GNC's outer loop (GTSAM's
            ``maxIterations``, ``muStep``, ``weightsTol``, ``relativeCostTol``; same defaults).
        gnc_inner_rtol: ``rtol`` of every GNC solve but the last (GTSAM's LM default); the last
            solve, with the final weights, runs at ``rtol``.
        gnc_restart: start every weighted solve at the start poses (GTSAM's choice) rather than
            at the previous solve's result.
    """

    max_steps: int = 100
    rtol: float = 1e-10
    atol: float = 0.0
    gtol: float = 1e-10
    lambda0: float = 1e-5
    damping: Literal["identity", "marquardt"] = "identity"
    initialization: Literal["none", "chordal"] = "none"
    linear_solver: Literal["auto", "dense", "pcg", "sparse"] = "auto"
    max_linear_iterations: int = 1000
    eta_max: float = 1e-4
    kernel: Literal["huber", "cauchy", "gnc"] | None = None
    kernel_scale: float | None = None
    gnc_max_iterations: int = 100
    gnc_mu_step: float = 1.4
    gnc_weights_tol: float = 1e-4
    gnc_cost_tol: float = 1e-5
    gnc_inner_rtol: float = 1e-5
    gnc_restart: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.max_steps, bool) or int(self.max_steps) != self.max_steps or self.max_steps < 0:
            raise ValueError(f"max_steps must be an integer >= 0, not {self.max_steps!r}")
        if self.initialization not in INITIALIZATIONS:
            raise ValueError(f"initialization must be 'none' or 'chordal', not {self.initialization!r}")
        if self.damping not in DAMPINGS:
            raise ValueError(f"damping must be 'identity' or 'marquardt', not {self.damping!r}")
        check_kernel(self.kernel)
        check_linear_solver(self.linear_solver)
        if self.kernel_scale is not None:
            scale = float(self.kernel_scale)
            if not (math.isfinite(scale) and scale > 0):
                raise ValueError(f"kernel_scale must be a positive finite number, not {self.kernel_scale!r}")
        if self.kernel == "gnc" and not (self.gnc_mu_step > 1 and self.gnc_max_iterations >= 1):
            raise ValueError(
                f"GNC needs gnc_mu_step > 1 and gnc_max_iterations >= 1, got {self.gnc_mu_step!r}, "
                f"{self.gnc_max_iterations!r}"
            )

    @property
    def scale(self) -> float:
        """``kernel_scale`` resolved: :data:`~swiftjax.posegraph.gnc.DEFAULT_SCALE` for GNC, else 1."""
        if self.kernel_scale is None:
            return DEFAULT_SCALE if self.kernel == "gnc" else 1.0
        return float(self.kernel_scale)

    def replace(self, **changes) -> GraphOptions:
        """A copy with ``changes`` (validated)."""
        return dataclasses.replace(self, **changes)


#: The pipeline's pose-graph defaults (``PipelineConfig.robust_loops``, ``robust_scale``,
#: ``max_lm_steps``): GNC on the loop edges at the chi-squared 0.99 threshold.
PIPELINE = GraphOptions(kernel="gnc", kernel_scale=DEFAULT_SCALE)

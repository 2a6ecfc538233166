"""The pose graph's options: :class:`GraphOptions`, every default written once.

:func:`swiftjax.posegraph.optimize` takes a ``GraphOptions``, the
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
from typing import Any, Literal

from swiftjax import options
from swiftjax.options import option
from swiftjax.posegraph.gnc import DEFAULT_SCALE
from swiftjax.posegraph.kernels import ROBUST_CHOICES
from swiftjax.posegraph.linear_solvers import BlockJacobiPCG
from swiftjax.posegraph.solver import SparseSim3LM
from swiftjax.posegraph.solver_choice import LINEAR_SOLVER_CHOICES

__all__ = ["GraphOptions", "PIPELINE", "DAMPINGS", "INITIALIZATIONS"]

DAMPINGS = ("identity", "marquardt")
INITIALIZATIONS = ("none", "chordal")

# The solver objects declare their own settings' defaults; GraphOptions reuses them (and adds
# each one's schema: help, range, choices), so a default is written once.
_LM = SparseSim3LM()
_PCG = BlockJacobiPCG()


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

    max_steps: int = option(
        100, "most Levenberg-Marquardt steps of the pose graph (0: report the initial cost only)", low=0, high=100_000
    )
    rtol: float = option(_LM.rtol, "relative cost-decrease tolerance", low=0.0)
    atol: float = option(_LM.atol, "absolute cost-decrease tolerance", low=0.0)
    gtol: float = option(_LM.gtol, "gradient tolerance relative to the first", low=0.0)
    lambda0: float = option(_LM.lambda0, "initial damping", low=0.0, low_open=True)
    damping: Literal["identity", "marquardt"] = option(_LM.damping, "damping matrix", choices=DAMPINGS)
    initialization: Literal["none", "chordal"] = option("none", "initial poses", choices=INITIALIZATIONS)
    linear_solver: Literal["auto", "dense", "pcg", "sparse"] = option(
        "auto", "linear solver of each LM step", choices=LINEAR_SOLVER_CHOICES
    )
    max_linear_iterations: int = option(_PCG.max_iterations, "PCG cap per LM step", low=1)
    eta_max: float = option(_PCG.eta_max, "loosest PCG relative tolerance", low=0.0, low_open=True)
    kernel: Literal["huber", "cauchy", "gnc"] | None = option(
        None,
        "robust loop edges: gnc (graduated non-convexity, truncated least squares), cauchy, huber, "
        "or none (the authors' plain least squares)",
        kind=str,
        choices=ROBUST_CHOICES,
        optional=True,
    )
    kernel_scale: float | None = option(
        None,
        "kernel scale / GNC inlier threshold on sqrt(r^T Omega r); sqrt(chi2_7(0.99)) by default",
        kind=float,
        low=0.0,
        low_open=True,
        optional=True,
    )
    gnc_max_iterations: int = option(100, "GNC outer iterations", low=0)
    gnc_mu_step: float = option(1.4, "GNC mu step", low=0.0, low_open=True)
    gnc_weights_tol: float = option(1e-4, "GNC weights tolerance", low=0.0)
    gnc_cost_tol: float = option(1e-5, "GNC relative cost tolerance", low=0.0)
    gnc_inner_rtol: float = option(1e-5, "rtol of every GNC solve but the last", low=0.0)
    gnc_restart: bool = option(True, "start every weighted GNC solve at the start poses")

    def __post_init__(self) -> None:
        options.validate(self)
        if self.kernel == "gnc" and not (self.gnc_mu_step > 1 and self.gnc_max_iterations >= 1):
            raise options.invalid(
                "GraphOptions.gnc_mu_step",
                self.gnc_mu_step,
                f"GNC needs gnc_mu_step > 1 and gnc_max_iterations >= 1 (given {self.gnc_max_iterations})",
            )

    @property
    def scale(self) -> float:
        """``kernel_scale`` resolved: :data:`~swiftjax.posegraph.gnc.DEFAULT_SCALE` for GNC, else 1."""
        if self.kernel_scale is None:
            return DEFAULT_SCALE if self.kernel == "gnc" else 1.0
        return float(self.kernel_scale)

    def replace(self, **changes: Any) -> GraphOptions:
        """A validated copy with ``changes`` (:func:`swiftjax.options.replace`)."""
        return options.replace(self, **changes)


#: The pipeline's pose-graph defaults (``PipelineConfig.robust_loops``, ``robust_scale``,
#: ``max_lm_steps``): GNC on the loop edges at the chi-squared 0.99 threshold.
PIPELINE = GraphOptions(kernel="gnc", kernel_scale=DEFAULT_SCALE)

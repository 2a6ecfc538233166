"""Global Sim(3) pose-graph optimisation (paper sec. 3.4): LM over all chunk transforms.

    from swiftjax import posegraph
    problem = posegraph.Problem(poses0, edges, measurements, information=w, fixed=None)
    result = posegraph.optimize(problem)          # -> Result(poses, cost_initial, cost_final, ...)
    result = posegraph.optimize(problem, kernel="gnc")   # GNC-TLS on the robust edges
    result.inlier_weights                         # [E]: 0 for rejected edges

Modules: :mod:`~swiftjax.posegraph.problem` (data, validation, robust kernels, size buckets),
:mod:`~swiftjax.posegraph.factors` (residuals and exact Jacobians),
:mod:`~swiftjax.posegraph.linear` (block-sparse normal equations, dense Cholesky, PCG),
:mod:`~swiftjax.posegraph.sparse_direct` (host CHOLMOD/SuperLU with the symbolic analysis cached),
:mod:`~swiftjax.posegraph.initialization` (chordal initialisation: three linear least squares),
:mod:`~swiftjax.posegraph.solver` (the optimistix-compatible LM solver),
:mod:`~swiftjax.posegraph.gnc` (graduated non-convexity with truncated least squares),
:mod:`~swiftjax.posegraph.driver` (host entry point ``optimize``).
"""

from swiftjax.posegraph.driver import DENSE_MAX_NODES, Result, choose_linear_solver, optimize
from swiftjax.posegraph.problem import (
    Problem,
    ProblemError,
    bucket_size,
    kernel_code,
    pad_problem,
    robust_rho,
    robust_weight,
    validate,
)
from swiftjax.posegraph.factors import (
    cost,
    edge_costs,
    residuals,
    residuals_and_jacobians,
    right_jacobian_inverse_at,
)
from swiftjax.posegraph.initialization import chain_poses, chordal_initialization
from swiftjax.posegraph import gnc
from swiftjax.posegraph.solver import STATUS, SparseSim3LM, linearize, retract

__all__ = [
    "DENSE_MAX_NODES",
    "Problem",
    "ProblemError",
    "Result",
    "STATUS",
    "SparseSim3LM",
    "bucket_size",
    "chain_poses",
    "choose_linear_solver",
    "chordal_initialization",
    "cost",
    "edge_costs",
    "gnc",
    "kernel_code",
    "linearize",
    "optimize",
    "pad_problem",
    "residuals",
    "residuals_and_jacobians",
    "retract",
    "right_jacobian_inverse_at",
    "robust_rho",
    "robust_weight",
    "validate",
]

"""Global Sim(3) pose-graph optimisation (paper sec. 3.4): LM over all chunk transforms.

    from swiftjax import posegraph
    problem = posegraph.Problem(poses0, edges, measurements, information=w, fixed=None)
    result = posegraph.optimize(problem)          # -> Result(poses, cost_initial, cost_final, ...)
    result = posegraph.optimize(problem, posegraph.GraphOptions(kernel="gnc"))   # GNC-TLS on the robust edges
    result = posegraph.optimize(problem, posegraph.GraphOptions(max_steps=20), throw=False)
    result.inlier_weights                         # [E]: 0 for rejected edges
    result.result                                 # LMResult: why LM stopped

Modules: :mod:`~swiftjax.posegraph.problem` (data, validation, size buckets),
:mod:`~swiftjax.posegraph.kernels` (robust kernels and their names),
:mod:`~swiftjax.posegraph.factors` (residuals and exact Jacobians),
:mod:`~swiftjax.posegraph.blockmat` (batched small-matrix products),
:mod:`~swiftjax.posegraph.linear` (block-sparse normal equations, dense Cholesky, PCG),
:mod:`~swiftjax.posegraph.linear_solvers` (the linear solvers as solver objects),
:mod:`~swiftjax.posegraph.solver_choice` (which linear solver a graph gets),
:mod:`~swiftjax.posegraph.sparse_direct` (host CHOLMOD/SuperLU with the symbolic analysis cached),
:mod:`~swiftjax.posegraph.initialization` (chordal initialisation: three linear least squares),
:mod:`~swiftjax.posegraph.solver` (the optimistix-compatible LM solver and :class:`LMResult`),
:mod:`~swiftjax.posegraph.gnc` (graduated non-convexity with truncated least squares),
:mod:`~swiftjax.posegraph.options` (:class:`GraphOptions`),
:mod:`~swiftjax.posegraph.driver` (host entry point ``optimize``).
Synthetic graphs with known truth: :mod:`swiftjax.synthetic.pose_graphs`.
"""

from swiftjax.posegraph import gnc
from swiftjax.posegraph.driver import Result, SolveError, optimize
from swiftjax.posegraph.factors import (
    cost,
    edge_costs,
    residuals,
    residuals_and_jacobians,
    right_jacobian_inverse_at,
)
from swiftjax.posegraph.initialization import chain_poses, chordal_initialization
from swiftjax.posegraph.kernels import KERNELS, ROBUST_CHOICES, check_kernel, kernel_code, robust_rho, robust_weight
from swiftjax.posegraph.linear_solvers import BlockJacobiPCG, DenseCholesky, HostSparse
from swiftjax.posegraph.options import GraphOptions
from swiftjax.posegraph.problem import Problem, ProblemError, bucket_size, pad_problem, padded_sizes, validate
from swiftjax.posegraph.solver import LMResult, SparseSim3LM, linearize, retract
from swiftjax.posegraph.solver_choice import DENSE_MAX_NODES, choose_linear_solver

__all__ = [
    "BlockJacobiPCG",
    "DENSE_MAX_NODES",
    "DenseCholesky",
    "GraphOptions",
    "HostSparse",
    "KERNELS",
    "LMResult",
    "Problem",
    "ProblemError",
    "ROBUST_CHOICES",
    "Result",
    "SolveError",
    "SparseSim3LM",
    "bucket_size",
    "chain_poses",
    "check_kernel",
    "choose_linear_solver",
    "chordal_initialization",
    "cost",
    "edge_costs",
    "gnc",
    "kernel_code",
    "linearize",
    "optimize",
    "pad_problem",
    "padded_sizes",
    "residuals",
    "residuals_and_jacobians",
    "retract",
    "right_jacobian_inverse_at",
    "robust_rho",
    "robust_weight",
    "validate",
]

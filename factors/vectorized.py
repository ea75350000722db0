"""The numpy bundle-adjustment backend (a facade; the pieces live in their modules).

- :mod:`~ari_sfm.factors.packed_problem`: RigGraph's problem packed into arrays (residuals and
  Jacobians from the models' batched kernels, the chain rule to the tangent spaces);
- :mod:`~ari_sfm.solver.schur`: normal equations and their Schur-complement solve;
- :mod:`~ari_sfm.solver.levenberg_marquardt`: GTSAM's LM loop, generic over a problem;
- :mod:`~ari_sfm.factors.marginals`: covariances of the global variables, keyed as gtsam.Marginals;
- :mod:`~ari_sfm.factors.extra_factors`: user factors linearised by GTSAM into the normal equations;
- :mod:`~ari_sfm.factors.backend`: the backend switch (optimize_graph, resolve_backend).
"""
from __future__ import annotations

from ..geometry import se3_exp
from ..solver.levenberg_marquardt import STOP_RULES, LMParams, LMReport
from .backend import (
                      BACKENDS,
                      GraphSolution,
                      VectorizedSolution,
                      optimize_graph,
                      optimize_vectorized,
                      resolve_backend,
                      solve_graph,
                      solve_vectorized,
)
from .marginals import CovarianceTable
from .packed_problem import INVALID_RESIDUAL, VectorizedProblem
from .variables import Variables

__all__ = ["BACKENDS", "STOP_RULES", "INVALID_RESIDUAL", "CovarianceTable", "LMParams", "LMReport", "Variables",
           "VectorizedProblem", "GraphSolution", "VectorizedSolution", "optimize_graph", "optimize_vectorized",
           "resolve_backend", "se3_exp", "solve_graph", "solve_vectorized"]

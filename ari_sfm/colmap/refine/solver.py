"""The points problem's solver: Levenberg-Marquardt on the robust (Huber) cost of a
:class:`~ari_sfm.colmap.refine.problem.RefractiveProblem`, the points eliminated by the Schur complement
(:mod:`ari_sfm.solver.schur`); a window prior and a scale bar or baseline as terms of the cost. Used by
refine-colmap and, with the gauge added, by volume self-calibration."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ari_sfm.geometry import unit3_basis

from ...solver.schur import assemble_from_observations, model_decrease, solve_damped
from .plane import WindowPrior
from .problem import RefractiveProblem, State, huber_cost, huber_weights
from .scale_bar import Baseline, ScaleBar


@dataclass(frozen=True)
class SolveResult:
    """A refinement's end: the state, the robust cost before and after, accepted steps, whether it converged."""

    state: State
    cost: float
    initial_cost: float
    iterations: int
    converged: bool
    linearizations: int = 0  # Jacobian evaluations (numpy backend)
    system: Any = None  # the normal equations at ``state`` when LM's last linearization was there (numpy backend)


class Solver:
    """A problem with its robust loss as an :class:`ari_sfm.solver.levenberg_marquardt.LMProblem`
    (points eliminated by the bundle-adjustment core :mod:`ari_sfm.solver.schur`, blocks of 3;
    Marquardt damping ``lambda * diag``)."""

    linearized_error_is_error = True  # a linearization's error is the robust cost at its point

    def __init__(self, problem: RefractiveProblem, huber_px: float | None, prior: WindowPrior | None = None,
                 bar: ScaleBar | None = None, baseline: Baseline | None = None) -> None:
        self.problem = problem
        self.huber_px = huber_px
        self.prior = prior
        self.bar = bar
        self.baseline = baseline
        self.P = len(problem.model.point3D_ids)
        self.size = problem.layout.size + (6 if bar is not None else 0)  # the bar's two points are reduced

    def cost(self, state: State) -> float:
        return (huber_cost(self.problem.residuals(state), self.huber_px) + self._prior_cost(state)
                + (0.0 if self.bar is None else self.bar.cost(state.xyz))
                + (0.0 if self.baseline is None else self.baseline.cost(state)))

    def _prior_cost(self, state: State) -> float:
        return 0.0 if self.prior is None else self.prior.cost(state.normals, state.distances)

    def _add_prior(self, ne, state: State) -> None:
        """The declared plane's prior rows (whitened) added to the normal equations and the error."""
        lay, prior = self.problem.layout, self.prior
        if prior is None:
            return
        J_n, J_d = prior.jacobians()
        s = prior.sigmas
        for w, (n, d) in enumerate(zip(state.normals, state.distances)):
            e = prior.errors(n, float(d)) / s
            J = np.column_stack([J_n @ unit3_basis(n), J_d]) / s[:, None]  # columns [e1, e2, d]
            cols = lay.window[w]
            used = cols >= 0
            J, cols = J[:, used], cols[used]
            ne.U[np.ix_(cols, cols)] += J.T @ J
            ne.g_global[cols] += J.T @ e
        ne.error += self._prior_cost(state)

    error = cost  # LMProblem's name

    def linearize(self, state: State):
        lin = self.problem.linearize(state)
        if self.bar is not None:
            lin = self._bar_points_reduced(lin)
        w = huber_weights(lin.residuals, self.huber_px)
        ne = assemble_from_observations(lin.residuals, lin.J_g, lin.index, lin.J_p, self.problem.model.obs_point,
                                        self.P, self.size, w, marquardt=True)
        ne.error = huber_cost(lin.residuals, self.huber_px)
        if self.bar is not None or self.baseline is not None:
            ne.damping = np.diag(ne.U).copy()  # damping from the images only (the bar is stiff)
        if self.prior is not None:
            self._add_prior(ne, state)
        if self.bar is not None:
            e, J = self.bar.error(state.xyz), self.bar.jacobian(state.xyz)
            cols = np.arange(self.size - 6, self.size)
            ne.U[np.ix_(cols, cols)] += np.outer(J, J)
            ne.g_global[cols] += J * e
            ne.error += 0.5 * e * e
        if self.baseline is not None:
            e = self.baseline.error(state)
            cols, J = self.baseline.jacobian(state, self.problem.layout)
            ne.U[np.ix_(cols, cols)] += np.outer(J, J)
            ne.g_global[cols] += J * e
            ne.error += 0.5 * e * e
        return ne

    def _bar_points_reduced(self, lin):
        """The scale bar's two points as reduced variables (columns size-6.. size-1): their
        observations' point Jacobians moved into J_g, their Schur blocks left empty."""
        base = self.problem.layout.size
        op = self.problem.model.obs_point
        M = len(op)
        J_g = np.concatenate([lin.J_g, np.zeros((M, 2, 3))], axis=2)
        index = np.concatenate([lin.index, -np.ones((M, 3), int)], axis=1)
        J_p = lin.J_p.copy()
        for k, p in enumerate((self.bar.a, self.bar.b)):
            obs = np.flatnonzero(op == p)
            J_g[obs, :, -3:] = J_p[obs]
            index[obs, -3:] = base + 3 * k + np.arange(3)
            J_p[obs] = 0.0
        return replace(lin, J_g=J_g, index=index, J_p=J_p)

    def solve(self, ne, lam: float):
        return solve_damped(ne, lam)

    def model_decrease(self, ne, step) -> float:
        return model_decrease(ne, *step)

    def retract(self, state: State, step) -> State:
        dg, dp = step
        if self.bar is not None:
            base = self.problem.layout.size
            dp = dp.copy()
            dp[self.bar.a], dp[self.bar.b] = dg[base:base + 3], dg[base + 3:base + 6]
            dg = dg[:base]
        return self.problem.retract(state, dg, dp)

    def run(self, state: State, max_iterations: int, progress=None,
            relative_tolerance: float | None = None) -> SolveResult:
        """The numpy backend: points Schur + the project's Levenberg-Marquardt (GTSAM's algorithm);
        ``relative_tolerance``: LM's (default RELATIVE_TOLERANCE)."""
        from ...solver.levenberg_marquardt import LMParams, levenberg_marquardt

        tol = RELATIVE_TOLERANCE if relative_tolerance is None else relative_tolerance
        res = levenberg_marquardt(self, state, max_iterations, tol, LMParams(lambda_initial=1e-4), progress=progress)
        r = res.report
        return SolveResult(res.x, r.error, r.initial_error, r.iterations,
                           r.stop in ("converged", "small_cost_change", "zero_error", "no_model_decrease"),
                           r.linearizations, res.system_at_x)

    def run_gtsam(self, state: State, max_iterations: int) -> SolveResult:
        """The GTSAM backend (one CustomFactor per image, GTSAM's LM)."""
        from .gtsam_graph import GtsamRefinement

        refined, iterations = GtsamRefinement(self.problem, self.huber_px, self.prior, self.bar).optimize(
            state, max_iterations)
        return SolveResult(refined, self.cost(refined), self.cost(state), iterations, iterations < max_iterations)


RELATIVE_TOLERANCE = 1e-7  # LM stops when a step lowers the robust cost by less than this fraction

"""The points problem's solver: Levenberg-Marquardt on the robust (Huber) cost of a refractive problem.

The cost is a :class:`~ari_sfm.colmap.refine.problem.RefractiveProblem`'s, the points eliminated by the
Schur complement (:mod:`ari_sfm.solver.schur`); a window prior and a scale bar or baseline are terms of the
cost. Used by refine-colmap and, with the gauge added, by volume self-calibration.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ...solver.bundle import BundleAdjustment, RowTerm
from ...solver.schur import NormalEquations, assemble_from_observations
from .plane import WindowPrior
from .problem import Linearization, RefractiveProblem, State, huber_cost, huber_weights
from .scale_bar import Baseline, ScaleBar
from .terms import BaselineTerm, ScaleBarTerm, WindowPriorTerm


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


class PointObservations:
    """The points problem's observations as a bundle-adjustment block.

    The robust (Huber) cost of a :class:`~ari_sfm.colmap.refine.problem.RefractiveProblem`, the points
    eliminated (blocks of 3), a scale bar's two points moved into the reduced variables (the bar couples them).

    Args:
        problem: The refractive problem.
        huber_px: The Huber threshold (px); None: plain least squares.
        bar: A scale bar, whose points become reduced columns ``size - 6 .. size``.
    """

    linearized_error_is_error = True  # a linearization's error is the robust cost at its point

    def __init__(self, problem: RefractiveProblem, huber_px: float | None, bar: ScaleBar | None = None) -> None:
        self.problem = problem
        self.huber_px = huber_px
        self.bar = bar
        self.P = len(problem.model.point3D_ids)
        self.size = problem.layout.size + (6 if bar is not None else 0)

    def error(self, x: State) -> float:
        """The robust cost of every observation.

        Args:
            x: The state.

        Returns:
            The sum of the Huber losses (inf where a point is not beyond its window).
        """
        return huber_cost(self.problem.residuals(x), self.huber_px)

    def linearize(self, x: State) -> NormalEquations:
        """The observations' normal equations, points eliminated, Marquardt damping.

        Args:
            x: The linearisation point.

        Returns:
            The system (its error the robust cost).
        """
        lin = self.problem.linearize(x)
        if self.bar is not None:
            lin = self._bar_points_reduced(lin)
        w = huber_weights(lin.residuals, self.huber_px)
        ne = assemble_from_observations(lin.residuals, lin.J_g, lin.index, lin.J_p, self.problem.model.obs_point,
                                        self.P, self.size, w, marquardt=True)
        ne.error = huber_cost(lin.residuals, self.huber_px)
        return ne

    def _bar_points_reduced(self, lin: Linearization) -> Linearization:
        """The scale bar's two points as reduced variables (columns size-6.. size-1): their
        observations' point Jacobians moved into J_g, their Schur blocks left empty."""
        assert self.bar is not None
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

    def retract(self, x: State, step: tuple[np.ndarray, np.ndarray]) -> State:
        """The state moved by (reduced step, point steps); the bar's points by their reduced columns.

        Args:
            x: The state.
            step: (reduced step (size,), point steps (P, 3)).

        Returns:
            The moved state.
        """
        dg, dp = step
        if self.bar is not None:
            base = self.problem.layout.size
            dp = dp.copy()
            dp[self.bar.a], dp[self.bar.b] = dg[base:base + 3], dg[base + 3:base + 6]
            dg = dg[:base]
        return self.problem.retract(x, dg, dp)


class Solver(BundleAdjustment[State]):
    """refine-colmap's and self-calibration's bundle adjustment.

    The observations of a :class:`~ari_sfm.colmap.refine.problem.RefractiveProblem` plus its terms, solved by
    the project's Levenberg-Marquardt (:meth:`run`) or GTSAM's (:meth:`run_gtsam`) on the same terms.

    Args:
        problem: The refractive problem.
        huber_px: The Huber threshold (px); None: plain least squares.
        prior: A declared window plane's prior.
        bar: A scale bar between two points.
        baseline: A baseline between two camera centres.
        terms: Further terms (self-calibration's gauge and intrinsics prior), after those above.
        damp_observations_only: Marquardt's damping from the observations alone; default: with a bar, a
            baseline or further terms (stiff rows are constraints).
    """

    def __init__(self, problem: RefractiveProblem, huber_px: float | None, prior: WindowPrior | None = None,
                 bar: ScaleBar | None = None, baseline: Baseline | None = None, terms: Sequence[RowTerm[State]] = (),
                 damp_observations_only: bool | None = None) -> None:
        self.problem = problem
        self.huber_px = huber_px
        self.prior = prior
        self.bar = bar
        self.baseline = baseline
        block = PointObservations(problem, huber_px, bar)
        self.P = block.P
        self.size = block.size
        own: list[RowTerm] = []
        if prior is not None:
            own.append(WindowPriorTerm(prior, problem.layout))
        if bar is not None:
            own.append(ScaleBarTerm(bar, problem.layout.size))
        if baseline is not None:
            own.append(BaselineTerm(baseline, problem.layout))
        if damp_observations_only is None:
            damp_observations_only = bar is not None or baseline is not None or bool(terms)
        self.row_terms: list[RowTerm[State]] = [*own, *terms]
        super().__init__(block, self.row_terms, damp_observations_only)

    def cost(self, state: State) -> float:
        """The whole cost (observations and terms).

        Args:
            state: The state.

        Returns:
            The cost.
        """
        return self.error(state)

    def run(self, state: State, max_iterations: int, progress=None,
            relative_tolerance: float | None = None) -> SolveResult:
        """Solve with the numpy backend: points Schur + the project's Levenberg-Marquardt (GTSAM's algorithm).

        Args:
            state: The start.
            max_iterations: Cap on LM's accepted steps.
            progress: Called with (accepted steps, error) after each linearisation's trials; None: not called.
            relative_tolerance: LM stops when the relative cost decrease is below it (default
                :data:`RELATIVE_TOLERANCE`).

        Returns:
            The result, with the number of linearizations and the normal equations at the solution when LM's
            last linearization was there.
        """
        from ...solver.levenberg_marquardt import LMParams, levenberg_marquardt

        tol = RELATIVE_TOLERANCE if relative_tolerance is None else relative_tolerance
        res = levenberg_marquardt(self, state, max_iterations, tol, LMParams(lambda_initial=1e-4), progress=progress)
        r = res.report
        return SolveResult(res.x, r.error, r.initial_error, r.iterations,
                           r.stop in ("converged", "small_cost_change", "zero_error", "no_model_decrease"),
                           r.linearizations, res.system_at_x)

    def run_gtsam(self, state: State, max_iterations: int) -> SolveResult:
        """Solve with the GTSAM backend (one CustomFactor per image, GTSAM's LM).

        Args:
            state: The start.
            max_iterations: Cap on GTSAM's iterations.

        Returns:
            The result; converged when GTSAM stopped before ``max_iterations``.
        """
        from .gtsam_graph import GtsamRefinement

        refined, iterations = GtsamRefinement(self.problem, self.huber_px, terms=self.row_terms, bar=self.bar).optimize(
            state, max_iterations)
        return SolveResult(refined, self.cost(refined), self.cost(state), iterations, iterations < max_iterations)


RELATIVE_TOLERANCE = 1e-7  # LM stops when a step lowers the robust cost by less than this fraction

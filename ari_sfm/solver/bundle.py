"""The one bundle-adjustment problem: observations whose small blocks are eliminated, plus terms.

Every adjustment ari-sfm runs is a :class:`BundleAdjustment`: an observation block (the rig's views of
targets, whose target frames the Schur complement eliminates, or the points problem's observations of
points, whose points it eliminates) and terms on the same variables (a declared window's prior, a scale
bar, a baseline, self-calibration's gauge and intrinsics prior, a researcher's GTSAM factors). What is
held is chosen by one :class:`Selection`. The three configurations:

- the rig calibration: :class:`~ari_sfm.factors.packed_problem.VectorizedProblem`'s views, the user's
  factors as a term;
- refine-colmap: :class:`~ari_sfm.colmap.refine.problem.RefractiveProblem`'s observations, the window
  prior, the scale bar or the baseline as terms (:mod:`ari_sfm.colmap.refine.terms`);
- self-calibration: the same observations (the particles as points), the gauge and the intrinsics prior
  as terms (:mod:`ari_sfm.particles.landmarks`).

A term written as whitened rows (:class:`RowTerm`) is written once: the numpy backend adds its rows to
the normal equations here, the GTSAM backend wraps the same rows as one ``gtsam.CustomFactor``
(:meth:`ari_sfm.colmap.refine.gtsam_graph.GtsamRefinement.term_factor`).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

import numpy as np

from .schur import NormalEquations, model_decrease, solve_damped

StateT = TypeVar("StateT")  # a problem's values: opaque to the solver
StateIn = TypeVar("StateIn", contravariant=True)  # the same, where only read (a term)
Step = tuple[np.ndarray, np.ndarray]  # (global step, block steps)


@dataclass(frozen=True)
class Selection:
    """What an adjustment estimates; the rest is held at its start.

    Attributes:
        intrinsics: Estimate the cameras' free intrinsic parameters.
        window: Estimate the windows (their normals, and their distances when ``window_distance``).
        window_normal: Estimate the windows' normals (with ``window``).
        window_distance: Estimate the windows' distances (with ``window``; unobservable in air).
        held_frames: The frames (rig poses) held; None: the first one, the gauge of the world.
    """

    intrinsics: bool = True
    window: bool = True
    window_normal: bool = True
    window_distance: bool = False
    held_frames: tuple[int, ...] | None = None

    def frames_held(self, n_frames: int) -> np.ndarray:
        """Which frames are held.

        Args:
            n_frames: How many frames the problem has.

        Returns:
            (n_frames,) booleans.
        """
        held = np.zeros(n_frames, bool)
        held[[0] if self.held_frames is None else list(self.held_frames)] = True
        return held


@dataclass(frozen=True)
class Rows:
    """Whitened residual rows of a term on the reduced (global) variables.

    Attributes:
        e: (R,) whitened errors.
        J: (R, q) their derivatives along the tangent columns ``cols``.
        cols: (q,) the reduced columns of ``J``.
    """

    e: np.ndarray
    J: np.ndarray
    cols: np.ndarray


def add_rows(system: NormalEquations, rows: Rows) -> None:
    """Add a term's whitened rows to the normal equations (J^T J, J^T e and 0.5 e.e).

    Args:
        system: The normal equations, changed in place.
        rows: The term's rows at the linearisation point.
    """
    cols = rows.cols
    if len(cols) == 0:
        return
    system.U[np.ix_(cols, cols)] += rows.J.T @ rows.J
    system.g_global[cols] += rows.J.T @ rows.e
    system.error += 0.5 * float(rows.e @ rows.e)


class Term(Protocol[StateIn]):
    """A term of the cost besides the observations: its error and its share of the normal equations."""

    def error(self, x: StateIn) -> float:
        """The term's cost (0.5 |whitened error|^2) at ``x``."""
        ...

    def add_to(self, system: NormalEquations, x: StateIn) -> None:
        """Add the term's linearisation at ``x`` to ``system``.

        Args:
            system: The normal equations; their U, g_global and error are changed in place.
            x: The linearisation point.
        """
        ...


class RowTerm(ABC, Generic[StateT]):
    """A term given by whitened rows on the reduced variables: written once, used by both backends."""

    linearized_error_is_error = True

    @abstractmethod
    def rows(self, x: StateT) -> Rows:
        """The term's whitened rows at ``x``.

        Args:
            x: The problem's state.

        Returns:
            The rows (errors, Jacobian, columns).
        """

    @abstractmethod
    def columns(self) -> np.ndarray:
        """The reduced columns the term may depend on (the GTSAM factor's keys).

        Returns:
            The columns (q,): those its rows may have nonzero derivatives on (a term whose rows are dense
            over the variables names the ones they depend on).
        """

    def error(self, x: StateT) -> float:
        """0.5 |e|^2 at ``x``.

        Args:
            x: The problem's state.

        Returns:
            The term's cost.
        """
        e = self.rows(x).e
        return 0.5 * float(e @ e)

    def add_to(self, system: NormalEquations, x: StateT) -> None:
        """Add the rows at ``x`` to ``system``.

        Args:
            system: The normal equations, changed in place.
            x: The linearisation point.
        """
        add_rows(system, self.rows(x))


class ObservationBlock(Protocol[StateT]):
    """The observations of an adjustment: residuals whose small blocks (frames or points) are eliminated."""

    @property
    def linearized_error_is_error(self) -> bool:
        """Whether a linearisation's error is the nonlinear error at its point."""
        ...

    def error(self, x: StateT) -> float:
        """The observations' cost at ``x``."""
        ...

    def linearize(self, x: StateT) -> NormalEquations:
        """The observations' normal equations at ``x``."""
        ...

    def retract(self, x: StateT, step: Step) -> StateT:
        """``x`` moved by ``step``.

        Args:
            x: The state.
            step: (global step, block steps).

        Returns:
            The moved state.
        """
        ...


class BundleAdjustment(Generic[StateT]):
    """Observations plus terms as one Levenberg-Marquardt problem.

    An :class:`ari_sfm.solver.levenberg_marquardt.LMProblem`.

    Args:
        observations: The observation block.
        terms: The terms added to its cost, in order.
        damp_observations_only: Marquardt's damping scales from the observations alone (a stiff term,
            e.g. a gauge or a scale bar, is a constraint and must not stiffen the damping).
    """

    def __init__(self, observations: ObservationBlock[StateT], terms: Sequence[Term[StateT]] = (),
                 damp_observations_only: bool = False) -> None:
        self.observations = observations
        self.terms = list(terms)
        self.damp_observations_only = damp_observations_only

    @property
    def linearized_error_is_error(self) -> bool:
        """True when the observations' and every term's linearised error is their error."""
        return bool(self.observations.linearized_error_is_error
                    and all(getattr(t, "linearized_error_is_error", True) for t in self.terms))

    @property
    def linearize_trials(self) -> bool:
        """Whether LM linearises its trial points (the observation block's choice)."""
        return bool(getattr(self.observations, "linearize_trials", False))

    def error(self, x: StateT) -> float:
        """The whole cost at ``x``.

        Args:
            x: The state.

        Returns:
            The observations' cost plus every term's, summed in order.
        """
        total = self.observations.error(x)
        for t in self.terms:
            total += t.error(x)
        return total

    def linearize(self, x: StateT) -> NormalEquations:
        """The normal equations at ``x``: the observations', then each term's rows added.

        Args:
            x: The linearisation point.

        Returns:
            The system (its error the whole cost's linearisation).
        """
        system = self.observations.linearize(x)
        if self.damp_observations_only:
            system.damping = np.diag(system.U).copy()
        for t in self.terms:
            t.add_to(system, x)
        return system

    @staticmethod
    def solve(system: NormalEquations, lam: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The damped step (:func:`ari_sfm.solver.schur.solve_damped`).

        Args:
            system: The normal equations.
            lam: The damping.

        Returns:
            (global step, block steps), or None when a damped block is not positive definite.
        """
        return solve_damped(system, lam)

    @staticmethod
    def model_decrease(system: NormalEquations, step: tuple[np.ndarray, np.ndarray]) -> float:
        """The decrease the linear model predicts for ``step``.

        Args:
            system: The normal equations.
            step: (global step, block steps).

        Returns:
            -(g . step + 0.5 step^T H step).
        """
        return model_decrease(system, *step)

    def retract(self, x: StateT, step: Step) -> StateT:
        """``x`` moved by ``step`` (the observation block's manifold).

        Args:
            x: The state.
            step: (global step, block steps).

        Returns:
            The moved state.
        """
        return self.observations.retract(x, step)

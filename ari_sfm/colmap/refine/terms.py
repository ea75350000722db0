"""The points problem's terms besides the observations, each written once as whitened rows.

A declared window plane's prior (:class:`WindowPriorTerm`), a scale bar between two points
(:class:`ScaleBarTerm`) and a baseline between two camera centres (:class:`BaselineTerm`). The numpy
backend adds their rows to the normal equations (:class:`ari_sfm.solver.bundle.BundleAdjustment`); the
GTSAM backend wraps the same rows as factors (:meth:`~ari_sfm.colmap.refine.gtsam_graph.GtsamRefinement.term_factor`).
Self-calibration's gauge and intrinsics prior are terms of the same kind (:mod:`ari_sfm.particles.landmarks`).
"""
from __future__ import annotations

import numpy as np

from ari_sfm.geometry import unit3_basis
from ari_sfm.solver.bundle import Rows, RowTerm
from ari_sfm.solver.schur import NormalEquations

from .plane import WindowPrior
from .problem import Layout, State
from .scale_bar import Baseline, ScaleBar


class WindowPriorTerm(RowTerm[State]):
    """A declared plane's prior on every window's normal and distance (:mod:`.plane`).

    Args:
        prior: The prior (its errors, Jacobians and sigmas).
        layout: The problem's reduced layout (where each window's normal and distance are).
    """

    def __init__(self, prior: WindowPrior, layout: Layout) -> None:
        self.prior = prior
        self.layout = layout

    def window_rows(self, state: State, w: int) -> Rows:
        """Window ``w``'s whitened rows on its estimated columns.

        Args:
            state: The problem's state.
            w: The window's index.

        Returns:
            Its rows (errors over the prior's sigmas; columns [e1, e2, distance] where estimated).
        """
        prior, s = self.prior, self.prior.sigmas
        n, d = state.normals[w], float(state.distances[w])
        J_n, J_d = prior.jacobians()
        e = prior.errors(n, d) / s
        J = np.column_stack([J_n @ unit3_basis(n), J_d]) / s[:, None]  # columns [e1, e2, d]
        cols = self.layout.window[w]
        used = cols >= 0
        return Rows(e, J[:, used], cols[used])

    def rows(self, x: State) -> Rows:
        """Every window's rows stacked (a window's columns are its own).

        Args:
            x: The problem's state.

        Returns:
            The stacked rows.
        """
        parts = [self.window_rows(x, w) for w in range(len(x.normals))]
        cols = np.concatenate([p.cols for p in parts]).astype(int)
        J = np.zeros((sum(len(p.e) for p in parts), len(cols)))
        r = c = 0
        for p in parts:
            J[r:r + len(p.e), c:c + len(p.cols)] = p.J
            r, c = r + len(p.e), c + len(p.cols)
        return Rows(np.concatenate([p.e for p in parts]), J, cols)

    def columns(self) -> np.ndarray:
        """The windows' estimated columns."""
        cols = self.layout.window.ravel()
        return cols[cols >= 0]

    def error(self, x: State) -> float:
        """0.5 |e|^2 summed window by window.

        Args:
            x: The problem's state.

        Returns:
            The prior's cost.
        """
        return self.prior.cost(x.normals, x.distances)

    def add_to(self, system: NormalEquations, x: State) -> None:
        """Add each window's rows (J^T J and J^T e on its columns) and the prior's cost.

        Args:
            system: The normal equations, changed in place.
            x: The linearisation point.
        """
        for w in range(len(x.normals)):
            r = self.window_rows(x, w)
            system.U[np.ix_(r.cols, r.cols)] += r.J.T @ r.J
            system.g_global[r.cols] += r.J.T @ r.e
        system.error += self.error(x)


class ScaleBarTerm(RowTerm[State]):
    """A scale bar: its two points, moved out of the Schur elimination, ``length_mm`` apart.

    Args:
        bar: The bar (point indices, length).
        first_column: The reduced column of the first point's x (the second point's follow).
    """

    def __init__(self, bar: ScaleBar, first_column: int) -> None:
        self.bar = bar
        self.first_column = first_column

    def rows(self, x: State) -> Rows:
        """The bar's one whitened row.

        Args:
            x: The problem's state.

        Returns:
            (length - L) / sigma and its derivative along the two points' columns.
        """
        e, J = self.bar.error(x.xyz), self.bar.jacobian(x.xyz)
        return Rows(np.array([e]), J[None, :], self.columns())

    def columns(self) -> np.ndarray:
        """The two points' six reduced columns."""
        return np.arange(self.first_column, self.first_column + 6)

    def error(self, x: State) -> float:
        """0.5 e^2.

        Args:
            x: The problem's state.

        Returns:
            The bar's cost.
        """
        return self.bar.cost(x.xyz)


class BaselineTerm(RowTerm[State]):
    """A baseline: two images' camera centres ``length_mm`` apart.

    Args:
        baseline: The baseline (images, their frames and cameras, length).
        layout: The problem's reduced layout.
    """

    def __init__(self, baseline: Baseline, layout: Layout) -> None:
        self.baseline = baseline
        self.layout = layout

    def rows(self, x: State) -> Rows:
        """The baseline's one whitened row.

        Args:
            x: The problem's state.

        Returns:
            (distance - L) / sigma and its derivative along the two images' frame and sensor columns.
        """
        cols, J = self.baseline.jacobian(x, self.layout)
        return Rows(np.array([self.baseline.error(x)]), J[None, :], cols)

    def columns(self) -> np.ndarray:
        """The two images' frame and sensor columns."""
        b, lay = self.baseline, self.layout
        cols = np.concatenate([lay.frames[b.frames[k]] for k in (0, 1)] + [lay.sensors[b.cameras[k]] for k in (0, 1)])
        return np.unique(cols[cols >= 0])

    def error(self, x: State) -> float:
        """0.5 e^2.

        Args:
            x: The problem's state.

        Returns:
            The baseline's cost.
        """
        return self.baseline.cost(x)

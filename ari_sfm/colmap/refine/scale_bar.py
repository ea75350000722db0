"""The scale as a term of the refinement: two point3Ds whose distance is known (a scale bar), or two
images whose camera centres are a known distance apart (a baseline, e.g. from navigation).

Residual ``(|X_a - X_b| - L) / sigma`` (dimensionless, added to the cost as ``0.5 r^2`` beside the
pixel residuals), with ``sigma = BAR_SIGMA_REL * L``: stiff enough that the result keeps the bar's
length (the cost is nearly flat along the scale), soft enough to stay a least-squares term. The two
points are moved out of the Schur elimination into the reduced variables (the bar couples them),
:class:`ari_sfm.colmap.refine.solver.Solver` does that. A baseline is the same residual on two
images' camera centres ``C = -R^T t`` of their ``cam_from_world = sensor_from_rig * rig_from_world``;
its variables (frame and sensor poses) are reduced variables already.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

Points = np.ndarray | Mapping[int, np.ndarray]  # the points (N, 3), or the bar's two by index

BAR_SIGMA_REL = 1e-4  # the bar's (and the baseline's) sigma as a fraction of its length


@dataclass(frozen=True)
class ScaleBar:
    """Points ``a`` and ``b`` (indices into the model's points) are ``length_mm`` apart."""

    a: int
    b: int
    length_mm: float

    @property
    def sigma_mm(self) -> float:
        return BAR_SIGMA_REL * self.length_mm

    def length(self, xyz: Points) -> float:
        return float(np.linalg.norm(xyz[self.a] - xyz[self.b]))

    def error(self, xyz: Points) -> float:
        return (self.length(xyz) - self.length_mm) / self.sigma_mm

    def cost(self, xyz: Points) -> float:
        return 0.5 * self.error(xyz) ** 2

    def jacobian(self, xyz: Points) -> np.ndarray:
        """(6,) d error / d [X_a, X_b]."""
        u = xyz[self.a] - xyz[self.b]
        u = u / np.linalg.norm(u)
        return np.r_[u, -u] / self.sigma_mm


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@dataclass(frozen=True)
class Baseline:
    """Images ``a`` and ``b`` (indices into the model's images; ``frames``: their rig frames,
    ``cameras``: their COLMAP cameras) have camera centres ``length_mm`` apart."""

    a: int
    b: int
    frames: tuple[int, int]
    cameras: tuple[int, int]
    length_mm: float

    @property
    def sigma_mm(self) -> float:
        return BAR_SIGMA_REL * self.length_mm

    def centre(self, state: Any, k: int) -> np.ndarray:
        """Image ``(a, b)[k]``'s camera centre in the world: ``-P.R^T (P.t + S.R^T S.t)``.

        Args:
            state: the refinement's state.
            k: 0 for image ``a``, 1 for ``b``.

        Returns:
            The centre (3,).
        """
        i = (self.a, self.b)[k]
        P, S = state.rig_from_world[self.frames[k]], state.sensor_from_rig[i]
        return -P.R.T @ (P.t + S.R.T @ S.t)

    def length(self, state: Any) -> float:
        return float(np.linalg.norm(self.centre(state, 0) - self.centre(state, 1)))

    def error(self, state: Any) -> float:
        return (self.length(state) - self.length_mm) / self.sigma_mm

    def cost(self, state: Any) -> float:
        return 0.5 * self.error(state) ** 2

    def jacobian(self, state: Any, layout: Any) -> tuple[np.ndarray, np.ndarray]:
        """The reduced columns the error depends on and d error / d those columns.

        The problem's tangents: a pose moves to ``(exp(w) R, t + v)``, columns ``[w, v]``; held poses have none.

        Args:
            state: the refinement's state.
            layout: the problem's layout (the frames' and sensors' columns).

        Returns:
            The columns and the derivatives.
        """
        d = self.centre(state, 0) - self.centre(state, 1)
        u = d / np.linalg.norm(d) / self.sigma_mm
        grad = np.zeros(layout.size + 1)  # index -1 (held) lands in the last, dropped entry
        for k, sign in ((0, 1.0), (1, -1.0)):
            i = (self.a, self.b)[k]
            P, S = state.rig_from_world[self.frames[k]], state.sensor_from_rig[i]
            c = S.R.T @ S.t
            frame_cols, sensor_cols = layout.frames[self.frames[k]], layout.sensors[self.cameras[k]]
            gu = sign * u
            np.add.at(grad, frame_cols[:3], gu @ (-P.R.T @ _skew(P.t + c)))  # C = -R^T (t + c)
            np.add.at(grad, frame_cols[3:], gu @ (-P.R.T))
            dC_dc = -P.R.T
            np.add.at(grad, sensor_cols[:3], gu @ dC_dc @ (S.R.T @ _skew(S.t)))  # c = Rs^T ts
            np.add.at(grad, sensor_cols[3:], gu @ dC_dc @ S.R.T)
        grad = grad[:-1]
        cols = np.flatnonzero(grad)
        return cols, grad[cols]

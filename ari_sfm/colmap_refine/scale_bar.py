"""The scale bar as a term of the refinement: two point3Ds whose distance is known.

Residual ``(|X_a - X_b| - L) / sigma`` (dimensionless, added to the cost as ``0.5 r^2`` beside the
pixel residuals), with ``sigma = BAR_SIGMA_REL * L``: stiff enough that the result keeps the bar's
length (the cost is nearly flat along the scale), soft enough to stay a least-squares term. The two
points are moved out of the Schur elimination into the reduced variables (the bar couples them),
:class:`ari_sfm.colmap_refine.refine.Solver` does that.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BAR_SIGMA_REL = 1e-4  # the bar's sigma as a fraction of its length


@dataclass(frozen=True)
class ScaleBar:
    """Points ``a`` and ``b`` (indices into the model's points) are ``length_mm`` apart."""

    a: int
    b: int
    length_mm: float

    @property
    def sigma_mm(self) -> float:
        return BAR_SIGMA_REL * self.length_mm

    def length(self, xyz: np.ndarray) -> float:
        return float(np.linalg.norm(xyz[self.a] - xyz[self.b]))

    def error(self, xyz: np.ndarray) -> float:
        return (self.length(xyz) - self.length_mm) / self.sigma_mm

    def cost(self, xyz: np.ndarray) -> float:
        return 0.5 * self.error(xyz) ** 2

    def jacobian(self, xyz: np.ndarray) -> np.ndarray:
        """(6,) d error / d [X_a, X_b]."""
        u = xyz[self.a] - xyz[self.b]
        u = u / np.linalg.norm(u)
        return np.r_[u, -u] / self.sigma_mm

"""Projection models: how a camera ray crosses the window.

- :mod:`.pinhole`: the plain pinhole with OpenCV distortion (no window).
- :mod:`.ari`: the paper's ARI equation (Eq. 1), a paraxial pinhole that sees
  the scene shifted along the window normal.
- :mod:`.exact`: Snell's law at both faces of the plate (Newton forward,
  closed-form backward).

All share the conventions stated in :mod:`.pinhole` (OpenCV camera frame and
pixels, mm, ``params = [fx, fy, cx, cy, k1, k2, p1, p2, k3]``).
"""
from .ari import AriJacobians, AriModel, ari_shift_mm
from .exact import ConvergenceError, ExactJacobians, ExactModel, solve_incidence
from .pinhole import PinholeModel

__all__ = [
    "PinholeModel",
    "AriModel",
    "AriJacobians",
    "ari_shift_mm",
    "ExactModel",
    "ExactJacobians",
    "ConvergenceError",
    "solve_incidence",
]

"""Standard deviations of the estimated parameters from gtsam.Marginals.

The graph's factors use a unit pixel sigma, so the marginal covariances are
scaled by the residual variance per coordinate, sigma^2 = SSR / (2N - p),
estimated at the optimum (with the exact model this is the detector noise;
with the paraxial model it also holds its model error).
"""
from __future__ import annotations

import logging
from typing import Sequence

import gtsam
import numpy as np

from ..models.pinhole import PARAM_NAMES
from ..results import CameraUncertainty, Uncertainty
from . import keys as K_
from .rig_graph import RigGraph

log = logging.getLogger(__name__)


def _std(variance: float, what: str) -> float | None:
    """sqrt(variance), or None (with a warning) when the covariance is not positive there:
    the parameter is not determined by the data (numerically singular information)."""
    if np.isfinite(variance) and variance >= 0.0:
        return float(np.sqrt(variance))
    log.warning("uncertainty of %s not determined (variance %.3g): the data barely constrain it", what, variance)
    return None


def residual_sigma_px(rg: RigGraph, residuals: Sequence[tuple[object, np.ndarray]] | None = None) -> float:
    """sigma per pixel coordinate from the residuals at the current values
    (``residuals``: rg.residuals(), when already at hand)."""
    res = np.concatenate([r.reshape(-1) for _, r in (rg.residuals() if residuals is None else residuals)])
    n_params = rg.values.dim()
    dof = max(res.size - n_params, 1)
    return float(np.sqrt(np.sum(res**2) / dof))


def rig_uncertainty(rg: RigGraph, sigma_px: float | None = None, marginals=None,
                    residuals: Sequence[tuple[object, np.ndarray]] | None = None) -> Uncertainty:
    """Standard deviations: per camera fx fy cx cy (and distortion) in px, the
    relative pose of each camera to camera 0 (rotation in degrees, translation in
    mm, as RMS error magnitudes), the normal's angle in degrees (RMS), and the
    window distance in mm when it is estimated.

    ``marginals``: default ``gtsam.Marginals(rg.graph, rg.values)``; the numpy
    backend's ``VectorizedProblem.marginals()`` gives the same covariances
    without linearising the graph through its Python callbacks. ``residuals``:
    rg.residuals(), when already at hand."""
    sigma = residual_sigma_px(rg, residuals) if sigma_px is None else sigma_px
    if marginals is None:
        marginals = gtsam.Marginals(rg.graph, rg.values)
    s2 = sigma**2
    cameras = {}
    for c, name in enumerate(rg.camera_names):
        cov = marginals.marginalCovariance(K_.K(c)) * s2
        intrinsics = {PARAM_NAMES[i]: _std(cov[i, i], f"{name} {PARAM_NAMES[i]}") for i in range(cov.shape[0])}
        if c > 0:
            pc = marginals.marginalCovariance(K_.C(c)) * s2
            rot = _std(np.trace(pc[:3, :3]), f"{name} rotation")
            cameras[name] = CameraUncertainty(intrinsics, True, None if rot is None else float(np.degrees(rot)),
                                              _std(np.trace(pc[3:, 3:]), f"{name} translation"))
        else:
            cameras[name] = CameraUncertainty(intrinsics)
    cov_n = marginals.marginalCovariance(K_.N) * s2
    normal = _std(np.trace(cov_n), "the normal")
    distance = (_std(marginals.marginalCovariance(K_.H)[0, 0] * s2, "the window distance")
                if rg.estimate_distance else None)
    return Uncertainty(sigma, cameras, None if normal is None else float(np.degrees(normal)), rg.estimate_distance,
                       distance)

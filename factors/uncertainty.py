"""Marginal covariances and standard deviations of the estimated parameters, in physical units.

The view factors are whitened by the pixel sigma (``RigGraph.sigma_px``, per
coordinate: given, or estimated from the residuals), so the inverse of the
information matrix is already a covariance in the variables' own units
(px for intrinsics, rad and mm for poses in their Pose3 tangent space, rad for
the normal's Unit3 tangent, mm for the distance). :func:`marginal_covariances`
is the one function that returns them, whichever backend solved the graph:
``gtsam.Marginals`` of the graph, or the numpy backend's Schur complement
(the same numbers, see tests/test_vectorized.py). :func:`rig_uncertainty`
turns them into the standard deviations written to calibration.json.
"""
from __future__ import annotations

import logging

import gtsam
import numpy as np

from ..models.pinhole import PARAM_NAMES
from ..results import CameraUncertainty, Uncertainty, WindowUncertainty
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


def marginal_covariances(rg: RigGraph, solved=None, sigma_px: float | None = None) -> dict[int, np.ndarray]:
    """Marginal covariances of the rig's global variables at the graph's current values, by key.

    The keys: K(c) (px), C(c) for c > 0 (Pose3 tangent [rad, mm]; camera 0 is the world, no variable),
    N(w) (each window's normal, its 2-D Unit3 tangent, rad) and H(w) (mm, when estimated). The units are
    physical because the view factors carry ``rg.sigma_px``.

    Args:
        rg: the solved graph.
        solved (VectorizedProblem | None): the numpy backend's problem at these values
            (``solve_graph(...).problem``); None: ``gtsam.Marginals(rg.graph, rg.values)``.
        sigma_px: rescale to this pixel sigma (exact only when every factor is a view factor: with user
            factors rebuild the graph with :meth:`RigGraph.with_sigma` instead); None: the graph's.

    Returns:
        The covariance of each variable by its gtsam key.
    """
    marginals = solved.marginals() if solved is not None else gtsam.Marginals(rg.graph, rg.values)
    keys = [K_.K(c) for c in range(len(rg.camera_names))] + [K_.C(c) for c in range(1, len(rg.camera_names))]
    for w in range(rg.n_windows):
        keys += [K_.window_normal(w)] + ([K_.window_plane(w)] if rg.estimate_distance else [])
    scale = 1.0 if sigma_px is None else (sigma_px / rg.sigma_px) ** 2
    return {k: np.asarray(marginals.marginalCovariance(k), float) * scale for k in keys}


def rig_uncertainty(rg: RigGraph, covariances: dict[int, np.ndarray] | None = None,
                    sigma_px: float | None = None) -> Uncertainty:
    """Standard deviations of the calibration, as written to calibration.json.

    Per camera fx fy cx cy (and distortion) in px; the relative pose of each camera to camera 0 (rotation in
    degrees, translation in mm, as RMS error magnitudes); the normal's angle in degrees (RMS); and the window
    distance in mm when it is estimated (with several windows, each window's: the distance's as its near
    face's position along its normal).

    Args:
        rg: the solved graph.
        covariances: :func:`marginal_covariances` of the graph (computed when not given).
        sigma_px: the pixel sigma the deviations rest on (default the graph's).

    Returns:
        The :class:`~ari_sfm.results.Uncertainty`.
    """
    cov = marginal_covariances(rg) if covariances is None else covariances
    cameras = {}
    for c, name in enumerate(rg.camera_names):
        ck = cov[K_.K(c)]
        intrinsics = {PARAM_NAMES[i]: _std(ck[i, i], f"{name} {PARAM_NAMES[i]}") for i in range(ck.shape[0])}
        if c > 0:
            pc = cov[K_.C(c)]
            rot = _std(np.trace(pc[:3, :3]), f"{name} rotation")
            cameras[name] = CameraUncertainty(intrinsics, True, None if rot is None else float(np.degrees(rot)),
                                              _std(np.trace(pc[3:, 3:]), f"{name} translation"))
        else:
            cameras[name] = CameraUncertainty(intrinsics)
    windows = []
    for w in range(rg.n_windows):
        normal = _std(np.trace(cov[K_.window_normal(w)]), "the normal")
        distance = _std(cov[K_.window_plane(w)][0, 0], "the window distance") if rg.estimate_distance else None
        windows.append(WindowUncertainty(None if normal is None else float(np.degrees(normal)), distance))
    names = rg.window_names if rg.n_windows > 1 else []
    return Uncertainty(float(rg.sigma_px if sigma_px is None else sigma_px), cameras, windows[0].normal_deg,
                       rg.estimate_distance, windows[0].distance_mm, dict(zip(names, windows)))

"""Standard deviations of the refined window, focal lengths and scale, and the warnings they imply.

Covariance of the reduced variables (cameras, poses, window; the points eliminated):
``s0^2 S^-1`` with ``S = H_gg - W V^-1 W^T`` the undamped Schur complement at the solution
(:func:`ari_sfm.solver.schur.global_covariance`, the bundle-adjustment core's) and ``s0^2`` the a-posteriori variance
factor (Huber-weighted residuals over the degrees of freedom), so the sigmas follow the residuals actually
reached. The gauge (the first frame) is held; the scale is a direction of the problem, determined
by refraction only (or by a scale bar), so a scale the images barely determine shows as a large
``scale_rel`` and, through it, a large distance sigma. A parameter the data do not determine at all
(a singular or indefinite S) has an inf or NaN sigma: it is listed in ``weak`` and written null.

``scale_rel``: the relative sigma of the scene's scale, measured as the RMS distance of the frames'
centres from their mean (a function of the frame poses, linearized).
"""
from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from ...solver.schur import global_covariance
from .problem import huber_weights
from .report import RefineUncertainty

log = logging.getLogger(__name__)

WEAK_NORMAL_DEG = 1.0  # a port normal sigma above this is "barely determined"
WEAK_DISTANCE_REL = 0.2  # a distance sigma above this fraction of the distance
WEAK_SCALE_REL = 0.01  # a scale sigma above 1 %
WEAK_FOCAL_REL = 0.01  # a focal-length sigma above 1 %


def _frame_spread_gradient(state: Any, frame_cols: np.ndarray, size: int) -> tuple[float, np.ndarray]:
    """The RMS distance s of the frame centres from their mean, and ds/d(reduced variables) (size,).
    A frame (R, t) moves to (exp(w) R, t + v): dC = -R^T [t]x w - R^T v with C = -R^T t."""
    R = np.array([p.R for p in state.rig_from_world])
    t = np.array([p.t for p in state.rig_from_world])
    C = -np.einsum("nji,nj->ni", R, t)
    d = C - C.mean(axis=0)
    F = len(C)
    s = float(np.sqrt(np.sum(d * d) / F))
    grad = np.zeros(size + 1)
    if s == 0.0:
        return s, grad[:size]
    dsdC = d / (F * s)  # the mean's gradient sums to zero against d
    for f in range(F):
        cols = frame_cols[f]
        if cols[0] < 0:
            continue
        tx = np.array([[0.0, -t[f, 2], t[f, 1]], [t[f, 2], 0.0, -t[f, 0]], [-t[f, 1], t[f, 0], 0.0]])
        grad[cols[:3]] += dsdC[f] @ (-R[f].T @ tx)
        grad[cols[3:]] += dsdC[f] @ (-R[f].T)
    return s, grad[:size]


def uncertainty(solver: Any, state: Any, names: list[str], system: Any = None) -> RefineUncertainty:
    """The sigmas (1 sigma) of ``solver``'s refined ``state`` (see the module docstring).

    A parameter the data barely determine is logged as a warning with its remedy and listed in ``weak``.

    Args:
        solver: The points problem's solver (:class:`~ari_sfm.colmap.refine.solver.Solver`).
        state: The refined state.
        names: Each camera's name (``camera<id>``), in the model's camera order.
        system: ``solver``'s normal equations at ``state``, if LM left them (else linearized here).

    Returns:
        ``normal_deg``, ``distance_mm`` per housing (mount camera) or of the world window, ``fx_px`` per
        camera (the lens behind the window), ``scale_rel``, ``sigma0`` and the list ``weak``.
    """
    problem = solver.problem
    model, lay = problem.model, problem.layout
    ne = solver.linearize(state) if system is None else system
    residuals = problem.residuals(state)
    w = huber_weights(residuals, solver.huber_px)
    chi2 = float(np.sum(w * np.sum(residuals ** 2, axis=1)))
    reduced_points = 2 if solver.bar is not None else 0
    dof = 2 * len(residuals) - solver.size - 3 * (len(state.xyz) - reduced_points)
    s0 = float(np.sqrt(chi2 / dof)) if dof > 0 else float("nan")
    cov = s0 ** 2 * global_covariance(ne)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    window_names = names if problem.mount == "camera" else ["world"]
    out: dict = {"sigma0": s0, "normal_deg": {}, "distance_mm": {}, "fx_px": {}, "scale_rel": None, "weak": []}
    for k, name in enumerate(window_names):
        cols = lay.window[k]
        if cols[0] >= 0:
            var = np.trace(cov[np.ix_(cols[:2], cols[:2])])  # inf when undetermined
            out["normal_deg"][name] = float(np.degrees(np.sqrt(np.maximum(var, 0.0))))
        if cols[2] >= 0:
            out["distance_mm"][name] = float(sd[cols[2]])
    for c, name in enumerate(names):
        free = np.flatnonzero(model.param_map[c].any(axis=0))
        fx = [j for j, col in enumerate(free) if model.param_map[c][0, col] != 0.0]
        if fx:
            out["fx_px"][name] = float(sd[lay.intrinsics[c][fx[0]]])
    s, grad = _frame_spread_gradient(state, lay.frames, solver.size)
    if s > 0.0:
        var = float(grad @ cov @ grad)  # NaN when the scale leans on an undetermined direction
        out["scale_rel"] = float(np.sqrt(var) / s) if var >= 0.0 else (math.nan if math.isnan(var) else 0.0)
    return RefineUncertainty(s0, out["normal_deg"], out["distance_mm"], out["fx_px"], out["scale_rel"],
                             tuple(_weak(out, state, model, problem.mount, names)))


def _weak(u: dict, state: Any, model: Any, mount: str, names: list[str]) -> list[str]:
    """Warnings (logged) for parameters the data barely determine, with the remedy; their names."""
    weak = []
    face = "interface.plane" + (" (in the camera frame)" if mount == "camera" else " (in the COLMAP world, mm)")
    for name, sig in u["normal_deg"].items():
        if not sig <= WEAK_NORMAL_DEG:  # NaN / inf too: not determined at all
            weak.append(f"normal_deg.{name}")
            log.warning("refine-colmap: the port normal of %s is barely determined by these images (+-%.2g deg, "
                        "1 sigma): declare it in WINDOW.yaml (%s normal, sigma_deg for a prior)", name, sig, face)
    for k, (name, sig) in enumerate(u["distance_mm"].items()):
        d = float(state.distances[k])
        if not sig <= WEAK_DISTANCE_REL * max(abs(d), 1.0):
            weak.append(f"distance_mm.{name}")
            log.warning("refine-colmap: the port distance of %s is barely determined by these images (%.3g +- %.2g mm, "
                        "1 sigma): declare it in WINDOW.yaml (%s point_mm, sigma_mm for a prior)", name, d, sig, face)
    if u["scale_rel"] is not None and not u["scale_rel"] <= WEAK_SCALE_REL:
        weak.append("scale_rel")
        log.warning("refine-colmap: the scale is barely determined by these images (+-%.2g %%, 1 sigma): declare a "
                    "scale_bar in WINDOW.yaml (two point3D ids and their distance)", 100.0 * u["scale_rel"])
    for c, (name, sig) in enumerate(u["fx_px"].items()):
        fx = float(model.params9(c, state.colmap_params[c])[0])
        if not sig <= WEAK_FOCAL_REL * fx:
            weak.append(f"fx_px.{name}")
            log.warning("refine-colmap: the focal length of %s is barely determined (%.1f +- %.2g px, 1 sigma): add "
                        "oblique views or views at other distances", name, fx, sig)
    return weak

"""The RT baseline: Feng et al.'s ray-tracing calibration as the paper's Section 3.3 describes it.

For each corner the camera-side ray starts at the observed pixel's direction
through the current intrinsics; it is traced through the window with vector
Snell's law (near face, glass, far face, medium) and corrected until it
passes through the corner; the pixel of the converged ray is compared with
the observed one. Intrinsics, extrinsics (camera poses and board poses) and
the interface (normal; distance under water) are optimised on that pixel
error by Levenberg-Marquardt (scipy.optimize.least_squares, numeric
Jacobian), started from Zhang's calibration with the window ignored and the
window normal along camera 0's optical axis. Calibration records only (no
stacking: RT has no expansion centre).

The trace is this module's own iteration (a fixed-point correction of the
incidence tangent with the paraxial gain), not :class:`ExactModel`'s Newton
solve; both are Snell's law, so a converged trace and the exact model agree
to rounding, which the tests check. A saved rt calibration projects and
back-projects through ExactModel (same physics, with rays).

In air the window's distance does not change any pixel (a plate only shifts
rays sideways by an amount set by angle and thickness): it is held at the
dataset's hint or a default and stored as ``fixed_distance_mm``.
"""
from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from ..calibration.evaluate import residual_stats
from ..geometry import unit
from ..records import Dataset, Interface
from ..results import OptimizerReport, OptimizerRun
from .bundle import camera_calibrations, intrinsics_vector, project_directions, start_bundle

if TYPE_CHECKING:
    from ..calibration.record import Calibration

log = logging.getLogger(__name__)

TRACE_TOL_MM = 1e-11  # stop when the traced ray misses the corner by less than this
TRACE_MAX_ITER = 100


def _refract(v: np.ndarray, normal: np.ndarray, eta: float) -> np.ndarray:
    """Vector Snell's law of unit rays v (N, 3) crossing a face with unit normal (N, 3) along the light."""
    c = np.einsum("ij,ij->i", v, normal)
    cos_t = np.sqrt(1.0 - eta * eta * (1.0 - c * c))
    return eta * v + (cos_t - eta * c)[:, None] * normal


def trace(v: np.ndarray, normal: np.ndarray, h: np.ndarray, d: float, n: float, n_m: float,
          depth: np.ndarray) -> np.ndarray:
    """Where unit camera rays cross the plane ``normal . X = depth`` after the window.

    Args:
        v: unit camera rays (N, 3).
        normal: the window's unit normal per ray (N, 3), camera frame.
        h: the near-face distance per ray (N,) (mm).
        d: the plate thickness (mm).
        n: the glass index.
        n_m: the medium index.
        depth: the plane's offset per ray (N,) (mm).

    Returns:
        The crossing points (N, 3).
    """
    c = np.einsum("ij,ij->i", v, normal)
    p = v * (h / c)[:, None]  # near face
    vg = _refract(v, normal, 1.0 / n)
    p = p + vg * (d / np.einsum("ij,ij->i", vg, normal))[:, None]  # far face
    vm = _refract(vg, normal, n / n_m)
    L = depth - h - d
    return p + vm * (L / np.einsum("ij,ij->i", vm, normal))[:, None]


def trace_to_points(start: np.ndarray, X: np.ndarray, normal: np.ndarray, h: np.ndarray, d: float, n: float,
                    n_m: float) -> tuple[np.ndarray, int]:
    """Unit camera-side rays that reach camera-frame points through the window.

    Each step traces the ray to the point's depth and moves its incidence tangent by the miss over the
    paraxial depth ``h + d/n + L/n_m``. Rays that do not converge are NaN (logged).

    Args:
        start: the first directions (N, 3) (the observed pixels' rays).
        X: the camera-frame points (N, 3).
        normal: the window's unit normal per point (N, 3), camera frame.
        h: the near-face distance per point (N,) (mm).
        d: the plate thickness (mm).
        n: the glass index.
        n_m: the medium index.

    Returns:
        The rays (N, 3) (NaN for points not beyond the far face) and the iterations used.
    """
    depth = np.einsum("ij,ij->i", X, normal)
    L = depth - h - d
    gain = 1.0 / (h + d / n + L / n_m)
    v = unit(np.asarray(start, float))
    v = np.where((np.einsum("ij,ij->i", v, normal) > 0.1)[:, None], v, normal)  # a start away from the window
    active = L > 0.0
    v[~active] = np.nan
    it = 0
    for it in range(1, TRACE_MAX_ITER + 1):  # noqa: B007 (the count is returned)
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        nv = normal[idx]
        miss = X[idx] - trace(v[idx], nv, h[idx], d, n, n_m, depth[idx])
        c = np.einsum("ij,ij->i", v[idx], nv)
        tangent = v[idx] / c[:, None] - nv + miss * gain[idx, None]
        v[idx] = unit(nv + tangent)
        done = np.linalg.norm(miss, axis=1) < TRACE_TOL_MM
        active[idx[done]] = False
    if active.any():
        log.warning("rt: %d rays did not converge in %d trace iterations", int(active.sum()), TRACE_MAX_ITER)
        v[active] = np.nan
    return v, it


def _normal(base: np.ndarray, ab: np.ndarray) -> np.ndarray:
    """The unit normal at tangent coordinates ``ab`` (2,) around ``base``."""
    e1 = unit(np.cross(base, [1.0, 0.0, 0.0] if abs(base[0]) < 0.9 else [0.0, 1.0, 0.0]))
    return unit(base + ab[0] * e1 + ab[1] * np.cross(base, e1))


def calibrate_rt(dataset: Dataset, distortion: bool = False, max_iterations: int = 100) -> Calibration:
    """The ray-tracing bundle adjustment (see the module docstring) on the calibration records.

    Args:
        dataset: the dataset, with observations; one window for every camera.
        distortion: estimate k1 k2 p1 p2 k3.
        max_iterations: scipy's evaluations are capped at twice this.

    Returns:
        The rt :class:`~ari_sfm.calibration.record.Calibration`.

    Raises:
        AriSfmError: the rig has several windows, or the fitted window passes behind a camera.
    """
    from ..calibration import Calibration

    t0 = time.perf_counter()
    if dataset.windows:
        from ..errors import AriSfmError

        raise AriSfmError(dataset.rig_path, "model rt (the paper's ray-tracing baseline) models one window for every "
                                            "camera; this rig has several (interfaces): use the exact model")
    iface = dataset.interface
    underwater = iface.medium_index != 1.0
    bundle, zhang = start_bundle(dataset, distortion, 3 if underwater else 2)
    normal0 = np.array([0.0, 0.0, 1.0])  # camera 0's optical axis: the usual start for a window in front
    # The dataset's hint, else 10 mm in front of the camera nearest the window (as calibrate does).
    distance0 = iface.distance_mm if iface.distance_mm is not None else float(
        max(normal0 @ p.inverse().t for p in bundle.cam_start) + 10.0)
    pts = bundle.points
    d, n, n_m = iface.thickness_mm, iface.index, iface.medium_index
    start_uv = pts.uv

    def state(x: np.ndarray):
        intr, cams, glob, frames = bundle.split(x)
        normal_world = _normal(normal0, glob[:2])
        distance = glob[2] if underwater else distance0
        return intr, cams, normal_world, distance, frames

    def pixels(x: np.ndarray) -> np.ndarray:
        intr, cams, normal_world, distance, frames = state(x)
        X = bundle.cam_points(cams, frames)
        normals = np.stack([c.R @ normal_world for c in cams])
        h = np.array([distance - normal_world @ c.inverse().t for c in cams])
        # The paper's start: the observed pixel's ray through the current intrinsics.
        first = np.c_[(start_uv - intr[pts.camera, 2:4]) / intr[pts.camera, 0:2], np.ones(len(pts))]
        v, _ = trace_to_points(first, X, normals[pts.camera], h[pts.camera], d, n, n_m)
        return project_directions(intr, pts.camera, v)

    def residuals(x: np.ndarray) -> np.ndarray:
        return (pixels(x) - pts.uv).ravel()

    x0 = np.concatenate([np.concatenate([intrinsics_vector(zhang[name], distortion) for name in bundle.names]),
                         np.zeros(6 * (len(bundle.names) - 1)), np.zeros(2), [distance0] if underwater else [],
                         np.zeros(6 * len(bundle.frame_start))])
    result = bundle.solve(x0, residuals, max_nfev=max_iterations * 2)
    elapsed = time.perf_counter() - t0
    intr, cams, normal_world, distance, frames = state(result.x)
    if any(normal_world @ c.inverse().t >= distance for c in cams):
        raise AriSfmError(dataset.rig_path, "rt: the fitted window passes behind a camera (bad start or data)")
    res = (pixels(result.x) - pts.uv)
    per_camera = {name: res[pts.camera == c] for c, name in enumerate(bundle.names)}
    log.info("rt: %d function evaluations, %.1f ms, rmse %.4f px", result.nfev, elapsed * 1e3,
             residual_stats([res]).rmse_px)
    optimizer = OptimizerReport({"rt": OptimizerRun(elapsed, "scipy.least_squares(lm), numeric Jacobian",
                                                    nfev=int(result.nfev), status=int(result.status))})
    return Calibration(
        model="rt",
        interface=Interface(d, n, n_m, float(distance) if underwater else None),
        normal_world=normal_world,
        cameras=camera_calibrations(dataset, bundle, intr, cams, per_camera),
        frames=dict(zip(pts.frames, frames)),
        residuals=residual_stats([res]),
        time_s=elapsed,
        optimizer=optimizer,
        target=dataset.target,
        fixed_distance_mm=None if underwater else float(distance0),
    )


def project_rt(calibration: Calibration, camera: str, X_world: np.ndarray) -> np.ndarray:
    """Pixels of world points by this module's trace (for comparing with the saved ExactModel).

    Args:
        calibration: an rt calibration.
        camera: the camera's name.
        X_world: world points (N, 3).

    Returns:
        The pixels (N, 2).
    """
    cam = calibration.cameras[camera]
    X = cam.cam_from_world.apply(np.asarray(X_world, float).reshape(-1, 3))
    normal = calibration.normal_cam(camera)
    h = calibration.distance_mm(camera)
    if h is None:
        h = calibration.fixed_distance_mm - calibration.normal_world @ cam.cam_from_world.inverse().t
    iface = calibration.interface
    N = len(X)
    v, _ = trace_to_points(X, X, np.tile(normal, (N, 1)), np.full(N, h), iface.thickness_mm, iface.index,
                           iface.medium_index)
    intr = np.r_[cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], cam.dist][None, :]
    return project_directions(intr, np.zeros(N, int), v)

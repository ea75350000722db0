"""Triangulation through the window: many points at once, any number of cameras.

Two public functions, both vectorised over P points (what particle tracking
needs: thousands of particles per frame, 2-8 cameras):

- :func:`triangulate_rays`: the linear least-squares point of C rays per
  point (the "midpoint" of the rays) and how far the rays miss each other.
- :func:`triangulate_pixels`: pixels of the same points in several cameras
  -> world points, through a :class:`~ari_sfm.calibration.record.Calibration`'s own
  model: linear initialisation from the scene-side rays
  (``Calibration.rays_world``: after the window, so refraction is in them),
  then Levenberg-Marquardt on the reprojection error through
  ``Calibration.project_world`` for all points at once (one 3x3 normal
  equation per point). Through the exact model (exact, rt, truth) both steps run
  per point in one compiled kernel (:func:`ari_sfm.models.kernels.triangulate_exact`,
  the same algorithm, slices of points handed out in turn to one thread per core): no
  intermediate arrays.

Ray gap (``ray_gap_mm``, the ``points.json`` key). For a point with rays
``o_c + s d_c`` (unit ``d_c``) the linear point X minimises
``sum_c |(I - d_c d_c^T)(X - o_c)|^2``, and::

    ray_gap_mm = 2 * sqrt(mean_c dist(X, ray_c)^2)

For two rays X is the midpoint of their common perpendicular, each ray is at
half its length from X, so ``ray_gap_mm`` is exactly the distance between the
two rays (how far they missed each other, as DATASET_FORMAT.md defines it);
for more rays it is the same quantity's natural generalisation (twice the RMS
point-to-ray distance). It is a property of the rays alone, so
:func:`triangulate_pixels` reports it from the linear solve, not from the
refined point. For a model without ``rays_world`` (e.g. a polynomial mapping)
it is the first-order equivalent at the refined point: the distance from X to
camera c's ray is ``|J_c^+ r_c|`` (J_c the 2x3 Jacobian of the projection, r_c
the pixel residual: the smallest 3D move that removes the residual).
"""
from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..calibration.record import Calibration
from ..errors import AriSfmError
from ..models import kernels
from ..models.exact import ExactModel

log = logging.getLogger(__name__)

MAX_ITERATIONS = 50  # Levenberg-Marquardt iterations (from the ray initialisation 2-3 are needed)
STEP_TOL_MM = 1e-6  # a point has converged when its step is below this (relative to 1 + |X|); the step is taken
NUMERIC_STEP_MM = 1e-4  # central-difference step for models without analytic Jacobians
MIN_DET = 1e-14  # det of the 3x3 ray normal matrix below this: rays (nearly) parallel -> NaN
PARALLEL_MIN_POINTS = 2000  # points per thread of the exact model's triangulation kernel (fewer: one thread)
SLICES_PER_THREAD = 8  # slices of points per thread, handed out in turn (a loaded core does fewer)
PARALLEL_CHUNK_POINTS = 500  # but no slice smaller than this (each kernel call costs ~10 us)

Projector = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


# --------------------------------------------------------------------------- rays


def triangulate_rays(origins: np.ndarray, directions: np.ndarray,
                     valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Find the least-squares point of C rays per point.

    Points with fewer than two valid rays, or with (nearly) parallel rays, get NaN.

    Args:
        origins: the rays' origins (P, C, 3).
        directions: the rays' directions (P, C, 3), not necessarily unit.
        valid: which rays count (P, C) bool (default: all).

    Returns:
        ``X`` (P, 3) and ``ray_gap_mm`` (P,) (see the module docstring: for two rays the distance
        between them).

    Raises:
        ValueError: if the arrays' shapes do not match.
    """
    o = np.asarray(origins, dtype=float)
    d = np.asarray(directions, dtype=float)
    if o.ndim != 3 or o.shape[2] != 3 or d.shape != o.shape:
        raise ValueError(f"origins and directions must both be (P, C, 3); got {o.shape} and {d.shape}")
    P, C, _ = o.shape
    v = np.ones((P, C), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if v.shape != (P, C):
        raise ValueError(f"valid must be (P, C) = {(P, C)}, got {v.shape}")
    with np.errstate(invalid="ignore", divide="ignore"):
        d = d / np.linalg.norm(d, axis=2, keepdims=True)
    v = v & np.isfinite(o).all(axis=2) & np.isfinite(d).all(axis=2)
    w = v.astype(float)
    o0 = np.where(v[..., None], o, 0.0)
    d0 = np.where(v[..., None], d, 0.0)
    # A = sum_c (I - d d^T), b = sum_c (I - d d^T) o
    A = w.sum(axis=1)[:, None, None] * np.eye(3) - np.einsum("pci,pcj->pij", d0, d0)
    b = o0.sum(axis=1) - np.einsum("pci,pc->pi", d0, np.einsum("pci,pci->pc", d0, o0))
    X, det = solve_sym3(A, b)
    ok = (v.sum(axis=1) >= 2) & (det > MIN_DET)
    X[~ok] = np.nan
    gap = np.full(P, np.nan)
    if ok.any():
        gap[ok] = 2.0 * np.sqrt(_mean_sq_ray_distance(X[ok], o0[ok], d0[ok], w[ok]))
    return X, gap


def solve_sym3(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve many symmetric 3x3 systems A x = b by the adjugate.

    Args:
        A: the symmetric matrices (Q, 3, 3).
        b: the right-hand sides (Q, 3).

    Returns:
        x (Q, 3) (non-finite where A is singular) and det(A) (Q,).
    """
    a, bb, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - bb * f, bb * e - c * d
    c11, c12, c22 = a * f - c * c, bb * c - a * e, a * d - bb * bb
    det = a * c00 + bb * c01 + c * c02
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        x = np.stack([c00 * b[:, 0] + c01 * b[:, 1] + c02 * b[:, 2],
                      c01 * b[:, 0] + c11 * b[:, 1] + c12 * b[:, 2],
                      c02 * b[:, 0] + c12 * b[:, 1] + c22 * b[:, 2]], axis=1) * inv[:, None]
    return x, det


def _mean_sq_ray_distance(X: np.ndarray, o: np.ndarray, d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Mean over the valid rays (weights w in {0, 1}) of the squared distance of X (Q, 3) to each ray."""
    r = X[:, None, :] - o
    perp = r - np.einsum("qci,qci->qc", r, d)[..., None] * d
    return (w * np.einsum("qci,qci->qc", perp, perp)).sum(axis=1) / w.sum(axis=1)


# --------------------------------------------------------------------------- pixels


def has_rays(calibration: Calibration) -> bool:
    """Tell whether the calibration's model back-projects pixels (``rays_world``); a polynomial model does not.

    The registry says so (``ModelSpec.rays``); a calibration whose ``rays_world`` still fails (a subclass
    standing in for a model without rays) counts as without.

    Args:
        calibration: the calibration.

    Returns:
        True if its model has rays.
    """
    if not calibration.spec.rays:
        return False
    name = next(iter(calibration.cameras))
    cam = calibration.cameras[name]
    try:
        calibration.rays_world(name, np.array([[cam.K[0, 2], cam.K[1, 2]]]))
    except (NotImplementedError, AriSfmError, ValueError, AttributeError) as exc:
        log.info("model %s has no rays_world (%s): triangulating by Gauss-Newton on project_world",
                 calibration.model, exc)
        return False
    return True


def _projector(calibration: Calibration, camera: str) -> Projector:
    """X_world (Q, 3) -> pixels (Q, 2) and d pixels / d X_world (Q, 2, 3) for one camera."""
    if calibration.spec.analytic_jacobians:  # its projection_model gives J_point (ari_sfm.models.registry)
        model = calibration.projection_model(camera)
        pose = calibration.cameras[camera].cam_from_world

        def analytic(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            jac = model.project_with_jacobians(pose.apply(X))
            return jac.uv, jac.J_point @ pose.R  # d uv/d X_world = d uv/d X_cam  R

        return analytic

    def numeric(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Q = len(X)
        h = NUMERIC_STEP_MM
        steps = np.concatenate([X] + [X + s * h * e for e in np.eye(3) for s in (1.0, -1.0)])
        uv = np.asarray(calibration.project_world(camera, steps), dtype=float).reshape(7, Q, 2)
        J = np.stack([(uv[1 + 2 * k] - uv[2 + 2 * k]) / (2.0 * h) for k in range(3)], axis=2)
        return uv[0], J

    return numeric


def _evaluate(projectors: list[Projector], X: np.ndarray, uv: np.ndarray, valid: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals (Q, C, 2), Jacobians (Q, C, 2, 3) (zero where not valid) and costs (Q,) (inf if a pixel is NaN)."""
    Q, C = valid.shape
    r = np.zeros((Q, C, 2))
    J = np.zeros((Q, C, 2, 3))
    for c, project in enumerate(projectors):
        m = valid[:, c]
        if m.any():
            pred, Jc = project(X[m])
            r[m, c] = pred - uv[m, c]
            J[m, c] = Jc
    with np.errstate(invalid="ignore"):
        cost = np.einsum("qck,qck->q", r, r)
    cost[~np.isfinite(cost)] = np.inf
    return r, J, cost


def refine_points(projectors: list[Projector], X0: np.ndarray, uv: np.ndarray, valid: np.ndarray,
                  max_iterations: int = MAX_ITERATIONS, damping: float = 1e-6
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine every point at once by Levenberg-Marquardt on its reprojection error.

    Each point has its own damping (Marquardt: ``lambda diag(J^T J)``), adapted per step.

    Args:
        projectors: one per camera: X_world (Q, 3) -> pixels (Q, 2) and their Jacobians (Q, 2, 3).
        X0: the start (P, 3), world frame.
        uv: the observed pixels (P, C, 2).
        valid: which observations count (P, C) bool.
        max_iterations: the most iterations.
        damping: the starting damping (small: near Gauss-Newton).

    Returns:
        X (P, 3), the final residuals (P, C, 2) and Jacobians (P, C, 2, 3).
    """
    X = X0.copy()
    r, J, cost = _evaluate(projectors, X, uv, valid)
    lam = np.full(len(X), float(damping))
    active = np.isfinite(cost) & np.isfinite(X).all(axis=1)
    for _ in range(max_iterations):
        idx = np.flatnonzero(active)
        if not len(idx):
            break
        Ja, ra = J[idx], r[idx]
        A = np.einsum("qcki,qckj->qij", Ja, Ja)
        g = np.einsum("qcki,qck->qi", Ja, ra)
        diag = np.einsum("qii->qi", A)
        A_damped = A + (lam[idx][:, None] * np.maximum(diag, 1e-12))[:, :, None] * np.eye(3)
        step = -solve_sym3(A_damped, g)[0]
        X_new = X[idx] + step
        r_new, J_new, cost_new = _evaluate(projectors, X_new, uv[idx], valid[idx])
        better = cost_new <= cost[idx]
        keep = idx[better]
        X[keep], r[keep], J[keep], cost[keep] = X_new[better], r_new[better], J_new[better], cost_new[better]
        lam[keep] = np.maximum(lam[keep] / 10.0, 1e-12)
        lam[idx[~better]] *= 10.0
        small = np.linalg.norm(step, axis=1) <= STEP_TOL_MM * (1.0 + np.linalg.norm(X_new, axis=1))
        stuck = lam[idx] > 1e12
        active[idx[small | stuck]] = False
    else:
        if active.any():
            log.warning("triangulation: %d of %d points not converged after %d iterations",
                        int(active.sum()), len(X), max_iterations)
    return X, r, J


def _tracks_array(calibration: Calibration, tracks: Mapping[str, np.ndarray]) -> tuple[list[str], np.ndarray]:
    """Camera names and pixels (P, C, 2) of a {camera: (P, 2)} mapping, checked."""
    cameras = list(tracks)
    if len(cameras) < 2:
        raise AriSfmError(None, f"triangulation needs at least 2 cameras, got {len(cameras)}")
    missing = [c for c in cameras if c not in calibration.cameras]
    if missing:
        raise AriSfmError(None, f"camera(s) {', '.join(missing)} not in the calibration "
                                f"(its cameras: {', '.join(calibration.cameras)})")
    arrays = [np.asarray(tracks[c], dtype=float) for c in cameras]
    P = len(arrays[0])
    for c, a in zip(cameras, arrays):
        if a.shape != (P, 2):
            raise AriSfmError(None, f"pixels of camera {c} must be ({P}, 2) like the first camera's, got {a.shape}")
    return cameras, np.stack(arrays, axis=1)


def triangulate_pixels(calibration: Calibration, tracks: Mapping[str, np.ndarray], refine: bool = True
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate pixel tracks seen through the window into world points.

    Initialisation: the linear point of the calibration's scene-side rays;
    for a model without ``rays_world``, every point starts at the centroid of
    the calibration frames' target origins. Points seen by fewer than two cameras are NaN.

    Args:
        calibration: the calibration.
        tracks: {camera: (P, 2) pixels}, NaN where a camera did not see the point; at least 2 cameras.
        refine: Levenberg-Marquardt on the reprojection error through ``project_world`` (always on
            when the model has no rays).

    Returns:
        ``X`` (P, 3) in the calibration's world frame, ``ray_gap_mm`` (P,) (module docstring) and
        ``reprojection_rmse_px`` (P,) (``sqrt(mean_c |uv_c - project_c(X)|^2)`` over the cameras that saw
        the point).

    Raises:
        AriSfmError: with fewer than 2 cameras, a camera not in the calibration, or pixel arrays of
            different shapes.
    """
    cameras, uv = _tracks_array(calibration, tracks)
    exact = _exact_cameras(calibration, cameras)
    if exact is not None:
        return _triangulate_exact(exact, uv, refine)
    P, C, _ = uv.shape
    valid = np.isfinite(uv).all(axis=2)
    enough = valid.sum(axis=1) >= 2
    projectors = [_projector(calibration, c) for c in cameras]
    rays = has_rays(calibration)
    if rays:
        origins = np.full((P, C, 3), np.nan)
        directions = np.full((P, C, 3), np.nan)
        for c, cam in enumerate(cameras):
            m = valid[:, c]
            if m.any():
                origins[m, c], directions[m, c] = calibration.rays_world(cam, uv[m, c])
        X, gap = triangulate_rays(origins, directions, valid & enough[:, None])
    else:
        X = np.full((P, 3), np.nan)
        X[enough] = _centroid_start(calibration)
        gap = np.full(P, np.nan)
    if refine or not rays:
        X, r, J = refine_points(projectors, X, uv, valid & enough[:, None], damping=1e-6 if rays else 1e-3)
    else:
        r, J, _ = _evaluate(projectors, X, uv, valid & enough[:, None])
    n = np.maximum(valid.sum(axis=1), 1)
    with np.errstate(invalid="ignore"):
        rmse = np.sqrt(np.einsum("pck,pck->p", r, r) / n)
    rmse[~enough | ~np.isfinite(X).all(axis=1)] = np.nan
    if not rays:
        gap = 2.0 * np.sqrt(_first_order_sq_distance(r, J, valid) / n)
        gap[~enough | ~np.isfinite(X).all(axis=1)] = np.nan
    X[~enough] = np.nan
    return X, gap, rmse


def _exact_cameras(calibration: Calibration, cameras: list[str]) -> tuple[np.ndarray, ...] | None:
    """The arrays :func:`ari_sfm.models.kernels.triangulate_exact` takes (R, t, params, unit normals,
    [h, d, n, n_m] per camera) when every camera's model is the exact one (exact, rt, truth), else None."""
    if not (calibration.spec.window and calibration.spec.rays):
        return None
    models = [calibration.projection_model(c) for c in cameras]
    if not all(type(m) is ExactModel for m in models):
        return None
    poses = [calibration.cameras[c].cam_from_world for c in cameras]
    return (np.array([p.R for p in poses], dtype=float), np.array([p.t for p in poses], dtype=float),
            np.array([m.pinhole.params for m in models], dtype=float),
            np.array([m.normal_cam for m in models], dtype=float),
            np.array([[m.distance_mm, m.thickness_mm, m.index, m.medium_index] for m in models], dtype=float))


def _triangulate_exact(cameras: tuple[np.ndarray, ...], uv: np.ndarray, refine: bool
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`triangulate_pixels` through the exact model: one compiled kernel per point (rays, linear
    point, Levenberg-Marquardt with analytic Jacobians), slices of points on one thread per core."""
    uv = np.ascontiguousarray(uv, dtype=float)
    P = len(uv)
    X, gap, rmse = np.full((P, 3), np.nan), np.full(P, np.nan), np.full(P, np.nan)
    unconverged, undistort_failed = np.zeros(P, dtype=bool), np.zeros(P, dtype=np.int64)

    def run(a: int, b: int) -> None:
        kernels.triangulate_exact(uv[a:b], *cameras, bool(refine), MAX_ITERATIONS, 1e-6, STEP_TOL_MM, MIN_DET,
                                  X[a:b], gap[a:b], rmse[a:b], unconverged[a:b], undistort_failed[a:b])

    workers = min(_cores(), P // PARALLEL_MIN_POINTS)
    if workers <= 1:
        run(0, P)
    else:  # the kernel releases the GIL; slices handed out in turn, so a thread the machine slows does fewer
        bounds = np.linspace(0, P, min(P // PARALLEL_CHUNK_POINTS, SLICES_PER_THREAD * workers) + 1).astype(int)
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="ari-triangulate") as pool:
            list(pool.map(run, bounds[:-1], bounds[1:]))
    if undistort_failed.any():
        log.warning("undistortion did not converge for %d pixels; their rays are NaN", int(undistort_failed.sum()))
    if unconverged.any():
        log.warning("triangulation: %d of %d points not converged after %d iterations",
                    int(unconverged.sum()), len(X), MAX_ITERATIONS)
    return X, gap, rmse


def _cores() -> int:
    """CPU cores this process may run on (its affinity mask where the system has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _first_order_sq_distance(r: np.ndarray, J: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Sum over valid cameras of |J^T (J J^T)^-1 r|^2 = r^T (J J^T)^-1 r: squared distance of X to each ray."""
    JJt = np.einsum("pcki,pcli->pckl", J, J)
    JJt[~valid] = np.eye(2)
    with np.errstate(invalid="ignore"):
        sol = np.linalg.solve(JJt, r[..., None])[..., 0]
    return np.where(valid, np.einsum("pck,pck->pc", r, sol), 0.0).sum(axis=1)


def _centroid_start(calibration: Calibration) -> np.ndarray:
    """The centroid of the calibration frames' target origins (world), the start for models without rays."""
    if not calibration.frames:
        raise AriSfmError(None, f"model {calibration.model} has no rays and the calibration lists no frames "
                                "to start the triangulation from")
    return np.mean([p.t for p in calibration.frames.values()], axis=0)

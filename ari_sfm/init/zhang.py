"""Zhang's planar calibration (closed form via OpenCV) for K and the generalised extrinsics.

With the ARI model the window only shifts the scene by delta along the normal,
so the camera is a pinhole with the true K and R (paper Eqs. 6-10): Zhang's
method on the refracted views gives K and the *generalised* extrinsics [R t],
whose translation still contains the shift (removed in :mod:`interface_pose`).
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..geometry import Pose
from ..helper_thread import shared_map
from ..models.pinhole import pinhole_pixels
from ..records import CameraSpec, Observation, Target
from .opencv_threads import one_cv2_thread


@dataclass(frozen=True)
class ZhangResult:
    """K, distortion and the generalised cam_from_target of every view."""

    K: np.ndarray
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    cam_from_target: dict[str, Pose]  # generalised (virtual-pinhole) poses by frame
    rms_px: float
    also: dict[str, Pose] = field(default_factory=dict)  # the ``also`` views' poses (iterative PnP) by frame

log = logging.getLogger(__name__)


def object_points(target: Target, ids: np.ndarray) -> np.ndarray:
    """Give the target-frame coordinates of corner ids.

    Args:
        target: the calibration target.
        ids: the corner ids (N,).

    Returns:
        The coordinates (N, 3), target frame, mm.

    Raises:
        KeyError: naming the first id the target does not have.
    """
    all_ids, xyz = target.points_3d_readonly  # ids ascending; built once per target
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    n = len(all_ids)
    if target.ids_are_rows:  # ids 0..n-1 (every board): an id is its row
        if len(ids) and ids.view(np.uint64).max() >= n:  # (a negative id is a huge unsigned one)
            raise KeyError(int(ids[np.flatnonzero((ids < 0) | (ids >= n))[0]]))
        return xyz[ids]
    pos = np.searchsorted(all_ids, ids)
    unknown = ((pos >= len(all_ids)) | (all_ids[np.minimum(pos, len(all_ids) - 1)] != ids) if len(all_ids)
               else ids == ids)
    if unknown.any():
        raise KeyError(int(ids[np.flatnonzero(unknown)[0]]))
    return xyz[pos]


def initial_K(spec: CameraSpec) -> np.ndarray:
    """A starting K from the camera's hints: K, else focal_px, else a 50-degree field."""
    if spec.K is not None:
        return np.array(spec.K, dtype=float)  # a copy: cv2.calibrateCamera writes into its K argument
    w, h = spec.image_size
    f = spec.focal_px if spec.focal_px is not None else 0.5 * w / np.tan(np.radians(25.0))
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])


def held_intrinsics(spec: CameraSpec) -> str | None:
    """Tell what ``--fix-intrinsics`` holds of a camera.

    Args:
        spec: the camera's declaration (its hints).

    Returns:
        "K" (a K hint, with its dist), "focal" (a focal_px hint: fx = fy), or None (no hint).
    """
    if spec.K is not None:
        return "K"
    return "focal" if spec.focal_px is not None else None


def _zhang_K(obj: list[np.ndarray], img: list[np.ndarray], threads: int = 1) -> np.ndarray | None:
    """Zhang's closed-form K (no skew) from the views' homographies (OpenCV's, on up to ``threads``
    threads: :func:`~ari_sfm.helper_thread.shared_map`): each view gives two linear constraints h1^T B h2 = 0,
    h1^T B h1 = h2^T B h2 on B = K^-T K^-1 (B11, B22, B13, B23, B33); None when they do not determine
    a camera (fewer than 3 views, degenerate poses)."""
    homographies = shared_map(lambda oi: cv2.findHomography(oi[0][:, :2], oi[1], 0)[0], list(zip(obj, img)), threads)
    if any(H is None for H in homographies):
        return None
    H = np.array([h / np.linalg.norm(h[:, :2]) for h in homographies]).reshape(-1, 3, 3)

    def v(a: int, b: int) -> np.ndarray:
        ha, hb = H[:, :, a], H[:, :, b]
        return np.stack([ha[:, 0] * hb[:, 0], ha[:, 1] * hb[:, 1], ha[:, 0] * hb[:, 2] + ha[:, 2] * hb[:, 0],
                         ha[:, 1] * hb[:, 2] + ha[:, 2] * hb[:, 1], ha[:, 2] * hb[:, 2]], axis=1)

    rows = np.stack([v(0, 1), v(0, 0) - v(1, 1)], axis=1).reshape(-1, 5)  # two per view, in view order
    if len(rows) < 6:
        return None
    b11, b22, b13, b23, b33 = np.linalg.svd(rows)[2][-1]
    cx, cy = -b13 / b11, -b23 / b22
    lam = b33 - b13 * b13 / b11 - b23 * b23 / b22
    if not (lam / b11 > 0 and lam / b22 > 0):
        return None
    return np.array([[np.sqrt(lam / b11), 0, cx], [0, np.sqrt(lam / b22), cy], [0, 0, 1.0]])


def _closed_form_K(obj: list[np.ndarray], img: list[np.ndarray], spec: CameraSpec, threads: int = 1) -> np.ndarray:
    """K without an iterative fit: the hint ``K`` as given; else, for a planar target, Zhang's closed
    form (:func:`_zhang_K`), or when its principal point is outside the image, the focal lengths of
    cv2.initCameraMatrix2D (principal point at the image centre); else :func:`initial_K`."""
    if spec.K is not None:
        return np.array(spec.K, dtype=float)
    w, h = spec.image_size
    if all(np.all(o[:, 2] == 0) for o in obj):
        K = _zhang_K(obj, img, threads)
        if K is not None and np.isfinite(K).all() and 0 <= K[0, 2] <= w - 1 and 0 <= K[1, 2] <= h - 1 \
                and 0.8 < K[0, 0] / K[1, 1] < 1.25:
            return K
        K = cv2.initCameraMatrix2D([o.astype(np.float32) for o in obj], [i.astype(np.float32) for i in img],
                                   (int(w), int(h)))
        fx, fy = K[0, 0], K[1, 1]
        if np.isfinite(K).all() and fx > 0 and fy > 0 and 0.8 < fx / fy < 1.25:
            return np.array([[fx, 0, (w - 1) / 2], [0, fy, (h - 1) / 2], [0, 0, 1.0]])
    return initial_K(spec)


@one_cv2_thread()
def calibrate_zhang(
    target: Target, spec: CameraSpec, views: Sequence[Observation], distortion: bool = False,
    hold: str | None = None, threads: int = 1, also: Sequence[Observation] = (),
) -> ZhangResult:
    """Give the closed-form start of a camera from planar (or, with a K hint, any) views.

    K comes from the homographies (Zhang's closed form), with no distortion; each view's generalised
    pose by PnP (IPPE for a planar target, iterative otherwise). No iterative calibration
    (cv2.calibrateCamera) runs here: the bundle adjustment that follows refines K, distortion and poses.

    Args:
        target: the calibration target.
        spec: the camera's declaration (image size, hints).
        views: the camera's calibration views.
        distortion: unused (the start has no distortion); kept for the signature.
        hold: "K" or "focal" (see :func:`held_intrinsics`): start from the hint exactly as calibrate will
            hold it (a K hint with its distortion, a focal hint with the principal point at the image centre).
        threads: run the per-view OpenCV calls on up to this many threads
            (:func:`~ari_sfm.helper_thread.shared_map`; the same result).
        also: more views posed with that K by :func:`solve_pnp` (a camera's stacking poses), returned in
            ``ZhangResult.also``; not part of K or the RMS.

    Returns:
        K, the distortion, every view's generalised cam_from_target and the reprojection RMS (px).

    Raises:
        ValueError: if PnP fails for a view.
    """
    obj = [object_points(target, v.ids).astype(np.float64) for v in views]
    img = [v.pixels.astype(np.float64).reshape(-1, 2) for v in views]
    K = initial_K(spec) if hold == "focal" else _closed_form_K(obj, img, spec, threads)
    dist = np.zeros(5)
    if hold == "K" and spec.dist is not None:
        dist = np.resize(np.asarray(spec.dist, float), 5).copy()

    def pnp(view: tuple[Observation, np.ndarray | None, np.ndarray | None]) -> Pose:
        v, o, i = view
        if o is None or i is None:  # an ``also`` view
            return solve_pnp(target, K, dist, v)
        planar = bool(np.all(o[:, 2] == 0))
        return _pnp_pose(o, i, K, dist, cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_ITERATIVE, v.frame)

    found = shared_map(pnp, list(zip(views, obj, img)) + [(v, None, None) for v in also], threads)
    found, also_found = found[:len(views)], found[len(views):]
    poses = {v.frame: pose for v, pose in zip(views, found)}
    extra = {v.frame: pose for v, pose in zip(also, also_found)}
    cam_points = [pose.apply(o) for pose, o in zip(found, obj)]
    if not views:
        return ZhangResult(K, dist, poses, 0.0, extra)
    uv = pinhole_pixels(np.concatenate(cam_points), np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist])
    res = uv - np.concatenate(img)  # every view's reprojection at once (the pinhole kernel)
    return ZhangResult(K, dist, poses, float(np.sqrt(np.sum(res * res) / len(res))), extra)


def dlt_projection(X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Estimate the 3x4 projection matrix of one view by the normalised DLT.

    Args:
        X: the 3D points (N, 3), N >= 6, not coplanar.
        uv: their pixels (N, 2).

    Returns:
        The 3x4 projection matrix (up to scale).
    """
    def normaliser(p: np.ndarray) -> np.ndarray:
        c, s = p.mean(axis=0), np.sqrt(p.shape[1]) / np.mean(np.linalg.norm(p - p.mean(axis=0), axis=1))
        T = np.eye(p.shape[1] + 1)
        T[:-1, :-1] *= s
        T[:-1, -1] = -s * c
        return T

    T2, T3 = normaliser(uv), normaliser(X)
    xn = (np.c_[uv, np.ones(len(uv))] @ T2.T)[:, :2]
    Xn = np.c_[X, np.ones(len(X))] @ T3.T
    rows = []
    for (u, v), P in zip(xn, Xn):
        rows.append(np.r_[P, np.zeros(4), -u * P])
        rows.append(np.r_[np.zeros(4), P, -v * P])
    _, _, vt = np.linalg.svd(np.array(rows))
    return np.linalg.inv(T2) @ vt[-1].reshape(3, 4) @ T3


MIN_DEPTH_RATIO = 0.02  # a body whose third extent is below this fraction of its largest is "nearly planar"


def _hinted_K(spec: CameraSpec) -> np.ndarray | None:
    """The K a hint gives: K as given, or focal_px with the principal point at the image centre."""
    if spec.K is not None:
        return np.array(spec.K, dtype=float)
    if spec.focal_px is not None:
        w, h = spec.image_size
        return np.array([[spec.focal_px, 0, (w - 1) / 2], [0, spec.focal_px, (h - 1) / 2], [0, 0, 1.0]])
    return None


def _dlt_K(target: Target, spec: CameraSpec, views: Sequence[Observation]) -> np.ndarray:
    """K by DLT per view (median over views); ValueError, asking for a focal hint, when the
    body is nearly planar or too shallow for DLT (principal point outside the image)."""
    for v in views:
        X = object_points(target, v.ids)
        s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
        if len(X) < 6 or s[2] < MIN_DEPTH_RATIO * s[0]:
            raise ValueError(f"frame {v.frame}: the body is nearly planar as seen ({len(X)} points, depth "
                             f"{s[2] / max(s[0], 1e-12):.3f} of its extent): DLT cannot start K; "
                             "give cameras.<name>.focal_px (or K) in rig.yaml")
    Ks = []
    for v in views:
        P = dlt_projection(object_points(target, v.ids), v.pixels)
        P = P * np.sign(np.linalg.det(P[:, :3]))  # points in front of the camera
        K = cv2.decomposeProjectionMatrix(P)[0]
        K = K @ np.diag(np.sign(np.diag(K)))  # RQ's sign ambiguity: positive focal lengths
        Ks.append(K / K[2, 2])
    K0 = np.median(Ks, axis=0)
    K0[0, 1] = 0.0
    w, h = spec.image_size
    fx, fy, cx, cy = K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]
    if not (np.isfinite(K0).all() and 0 <= cx <= w - 1 and 0 <= cy <= h - 1 and 0.8 < fx / fy < 1.25):
        raise ValueError(f"the body is too shallow for DLT (its K start has fx {fx:.0f}, fy {fy:.0f}, principal "
                         f"point ({cx:.0f}, {cy:.0f}) px): give cameras.<name>.focal_px (or K) in rig.yaml")
    return K0


def calibrate_dlt(
    target: Target, spec: CameraSpec, views: Sequence[Observation], distortion: bool = False,
    hold: str | None = None, threads: int = 1, also: Sequence[Observation] = (), centred: bool = False,
) -> ZhangResult:
    """Give K and the generalised extrinsics from a 3D target (several planes; one view is enough).

    K comes from the hint when the dataset gives one (``K`` as given, ``focal_px`` with the principal
    point at the image centre), else from DLT per view (median over views); then each view's pose by
    PnP with that K (the bundle adjustment refines both). A body too shallow for DLT starts with the
    principal point at the image centre and the focal length from a resection over it
    (:func:`focal_by_resection`).

    Args:
        target: the 3D calibration target.
        spec: the camera's declaration (image size, hints).
        views: the camera's calibration views.
        distortion: unused (the start has no distortion); kept for the signature.
        hold: see :func:`calibrate_zhang`.
        threads: see :func:`calibrate_zhang`.
        also: see :func:`calibrate_zhang`.
        centred: hold the principal point at the image centre in any case.

    Returns:
        K, the distortion, every view's generalised cam_from_target and the reprojection RMS (px).

    Raises:
        ValueError: if the views do not determine the focal length (a focal_px hint is needed) or PnP fails.
    """
    K0 = _hinted_K(spec)
    if K0 is None:
        try:
            K0 = _dlt_K(target, spec, views)
        except ValueError as exc:  # too shallow for DLT: the focal length of a centred camera, if the views tell it
            log.info("%s: %s; trying a resection with the principal point at the image centre", spec.name, exc)
            K0 = None
        w, h = spec.image_size
        if centred and K0 is not None:
            K0 = np.array([[0.5 * (K0[0, 0] + K0[1, 1]), 0, (w - 1) / 2], [0, 0.5 * (K0[0, 0] + K0[1, 1]), (h - 1) / 2],
                           [0, 0, 1.0]])
        if K0 is None:
            f = focal_by_resection(target, spec, views)
            K0 = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    elif centred and spec.K is None:
        w, h = spec.image_size
        K0[0, 2], K0[1, 2] = (w - 1) / 2, (h - 1) / 2
    hinted = CameraSpec(spec.name, spec.image_size, None, K0, spec.dist)
    return calibrate_zhang(target, hinted, views, distortion, hold, threads, also)


def calibrate_views(target: Target, spec: CameraSpec, views: Sequence[Observation], distortion: bool = False,
                    hold: str | None = None, threads: int = 1, also: Sequence[Observation] = (),
                    centred: bool = False) -> ZhangResult:
    """Start a camera: Zhang's method for planar targets, DLT/PnP for 3D ones.

    Args:
        target: the calibration target.
        spec: the camera's declaration (image size, hints).
        views: the camera's calibration views.
        distortion: unused (the start has no distortion); kept for the signature.
        hold: see :func:`calibrate_zhang`.
        threads: see :func:`calibrate_zhang`.
        also: see :func:`calibrate_zhang`.
        centred: (3D bodies) see :func:`calibrate_dlt`.

    Returns:
        K, the distortion, every view's generalised cam_from_target and the reprojection RMS (px).

    Raises:
        ValueError: if the start fails (see :func:`calibrate_zhang`, :func:`calibrate_dlt`).
    """
    if target.is_planar():
        return calibrate_zhang(target, spec, views, distortion, hold, threads, also)
    return calibrate_dlt(target, spec, views, distortion, hold, threads, also, centred)


FOCAL_RANGE = (0.3, 30.0)  # focal lengths searched by focal_by_resection, in image widths (a 120 to 2 deg field)
FOCAL_SAMPLES = 60  # log-spaced focal lengths of its first pass
FOCAL_DETERMINED = 0.2  # a focal length that fits as well 20 % off (within the noise) is not determined


@one_cv2_thread()
def focal_by_resection(target: Target, spec: CameraSpec, views: Sequence[Observation]) -> float:
    """Find the focal length of a camera whose principal point is at the image centre, from views of a 3D body.

    Each candidate focal length gets each view's PnP pose (square pixels, no distortion); the sum of the
    views' squared reprojection errors is minimised over log-spaced candidates, then by a bounded 1-D
    search around the best.

    Args:
        target: the 3D calibration target.
        spec: the camera's declaration (its image size).
        views: the camera's calibration views.

    Returns:
        The focal length (px).

    Raises:
        ValueError: asking for focal_px when the views do not determine it (the minimum at the end of the
            range, or a focal length 20 % off fits as well).
    """
    from scipy.optimize import minimize_scalar

    w, h = spec.image_size
    data = [(object_points(target, v.ids).astype(np.float64), v.pixels.astype(np.float64)) for v in views]

    def cost(log_f: float) -> float:
        f = float(np.exp(log_f))
        K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
        total = 0.0
        for X, uv in data:
            try:
                ok, rvec, tvec = cv2.solvePnP(X, uv, K, None, flags=cv2.SOLVEPNP_SQPNP)
            except cv2.error:  # SQPnP refuses a small point spread: the iterative solver then
                try:
                    ok, rvec, tvec = cv2.solvePnP(X, uv, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
                except cv2.error:
                    return np.inf
            if not ok:
                return np.inf
            proj, _ = cv2.projectPoints(X, rvec, tvec, K, None)
            total += float(np.sum((proj.reshape(-1, 2) - uv) ** 2))
        return total

    grid = np.linspace(np.log(FOCAL_RANGE[0] * w), np.log(FOCAL_RANGE[1] * w), FOCAL_SAMPLES)
    costs = np.array([cost(g) for g in grid])
    k = int(np.argmin(costs))
    if k in (0, len(grid) - 1) or not np.isfinite(costs[k]):
        raise ValueError(f"the body is too shallow for DLT and its views do not determine the focal length "
                         f"(the best lies at {np.exp(grid[k]):.0f} px, the end of the range searched): give "
                         f"cameras.<name>.focal_px (or K) in rig.yaml")
    best = minimize_scalar(cost, bounds=(grid[k - 1], grid[k + 1]), method="bounded")
    log_f, minimum = (best.x, best.fun) if best.fun <= costs[k] else (grid[k], costs[k])
    f = float(np.exp(log_f))
    # determined? the profile of the cost over the focal length must rise by the noise variance (one sigma)
    # within FOCAL_DETERMINED of it (the noise from the residuals at the minimum: 7 parameters a view)
    count = sum(len(uv) for _, uv in data)
    noise = minimum / max(2 * count - 7 * len(data), 1)
    rise = min(cost(log_f + np.log1p(FOCAL_DETERMINED)), cost(log_f + np.log1p(-FOCAL_DETERMINED))) - minimum
    if not rise > noise:
        raise ValueError(f"the body is too shallow for DLT and its views do not determine the focal length "
                         f"(from {f:.0f} px, {100 * FOCAL_DETERMINED:.0f} % more or less fits as well): give "
                         f"cameras.<name>.focal_px (or K) in rig.yaml")
    log.info("%s: focal length %.0f px from a resection of its 3D body (principal point at the image centre; "
             "no focal_px hint)", spec.name, f)
    return f


@one_cv2_thread()
def solve_pnp(target: Target, K: np.ndarray, dist: np.ndarray, view: Observation) -> Pose:
    """Give the generalised cam_from_target of one view with known K (iterative PnP).

    Args:
        target: the calibration target.
        K: the 3x3 intrinsic matrix.
        dist: the distortion coefficients (OpenCV order).
        view: the view.

    Returns:
        The generalised (virtual-pinhole) cam_from_target.

    Raises:
        ValueError: if PnP fails.
    """
    return _pnp_pose(object_points(target, view.ids), view.pixels.astype(np.float64), K, dist,
                     cv2.SOLVEPNP_ITERATIVE, view.frame)


def _pnp_pose(obj: np.ndarray, pixels: np.ndarray, K: np.ndarray, dist: np.ndarray, flags: int, frame: str) -> Pose:
    """cam_from_target of one view by cv2.solvePnP with ``flags``; ValueError naming ``frame`` if it fails."""
    ok, rvec, tvec = cv2.solvePnP(obj, pixels, K, dist, flags=flags)
    if not ok:
        raise ValueError(f"PnP failed for frame {frame}")
    return Pose(cv2.Rodrigues(rvec)[0], np.asarray(tvec, float).reshape(3))

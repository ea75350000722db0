"""Zhang's planar calibration (via OpenCV) for K and the generalised extrinsics.

With the ARI model the window only shifts the scene by delta along the normal,
so the camera is a pinhole with the true K and R (paper Eqs. 6-10): Zhang's
method on the refracted views gives K and the *generalised* extrinsics [R t],
whose translation still contains the shift (removed in :mod:`interface_pose`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from ..geometry import Pose
from ..records import CameraSpec, Observation, Target


@dataclass(frozen=True)
class ZhangResult:
    """K, distortion and the generalised cam_from_target of every view."""

    K: np.ndarray
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    cam_from_target: dict[str, Pose]  # generalised (virtual-pinhole) poses by frame
    rms_px: float


def object_points(target: Target, ids: np.ndarray) -> np.ndarray:
    """Target-frame coordinates (N, 3) of corner ids."""
    all_ids, xyz = target.points_3d()
    index = {int(i): k for k, i in enumerate(all_ids)}
    return xyz[[index[int(i)] for i in ids]]


def initial_K(spec: CameraSpec) -> np.ndarray:
    """A starting K from the camera's hints: K, else focal_px, else a 50-degree field."""
    if spec.K is not None:
        return np.asarray(spec.K, float)
    w, h = spec.image_size
    f = spec.focal_px if spec.focal_px is not None else 0.5 * w / np.tan(np.radians(25.0))
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])


def calibrate_zhang(
    target: Target, spec: CameraSpec, views: Sequence[Observation], distortion: bool = False
) -> ZhangResult:
    """cv2.calibrateCamera on planar views (needs >= 3 views of >= 6 corners each)."""
    obj = [object_points(target, v.ids).astype(np.float32) for v in views]
    img = [v.pixels.astype(np.float32).reshape(-1, 1, 2) for v in views]
    flags = cv2.CALIB_USE_INTRINSIC_GUESS
    if not distortion:
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    K0 = initial_K(spec)
    dist0 = np.zeros(5)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        obj, img, tuple(int(s) for s in spec.image_size), K0, dist0, flags=flags, criteria=criteria
    )
    poses = {
        v.frame: Pose(cv2.Rodrigues(r)[0], np.asarray(t, float).reshape(3)) for v, r, t in zip(views, rvecs, tvecs)
    }
    return ZhangResult(np.asarray(K, float), np.asarray(dist, float).reshape(-1)[:5], poses, float(rms))


def solve_pnp(target: Target, K: np.ndarray, dist: np.ndarray, view: Observation) -> Pose:
    """The generalised cam_from_target of one view with known K (iterative PnP)."""
    obj = object_points(target, view.ids)
    ok, rvec, tvec = cv2.solvePnP(obj, view.pixels.astype(np.float64), K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError(f"PnP failed for frame {view.frame}")
    return Pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3))

"""A declared window (DATASET_FORMAT 1.1 ``interface.plane``) as a factor of the rig graph.

The plane is given in the coordinates of one target frame f: a unit normal
n_t and a point p_t of the camera-side face. With world = camera 0 and
world_T_target = (R, t) the pose X(f):

- normal_world = R n_t, so the normal error is the chordal difference
  ``e_n = N - R n_t`` (3 rows; ~ the angle in rad for small errors);
- distance = normal_world . (R p_t + t) = n_t . p_t + (R n_t) . t, so the
  distance error is ``e_h = H - n_t . p_t - (R n_t) . t`` (1 row, mm).

Jacobians in GTSAM's tangent spaces (Pose3 right-perturbed, rotation first;
Unit3 N = retract in its basis B): de_n/dN = B, de_n/dw = R [n_t]x,
de_n/dv = 0; de_h/dH = 1, de_h/dw = t^T R [n_t]x, de_h/dv = -n_t^T.
A sigma of 0 holds the part fixed, as a prior far tighter than the images.
"""
from __future__ import annotations

import gtsam
import numpy as np

from ..geometry import Pose, skew, unit
from ..records import WindowPlane
from . import keys as K_

FIXED_SIGMA_RAD = 1e-6  # "held fixed": 6e-5 deg, far below what the images say
FIXED_SIGMA_MM = 1e-4


def plane_in_world(plane: WindowPlane, world_from_target: Pose) -> tuple[np.ndarray, float]:
    """The declared plane in the world, given its frame's pose.

    Args:
        plane: the declared plane, in its target frame's coordinates.
        world_from_target: the pose of that frame.

    Returns:
        The unit normal in the world (3,), and the camera-side face's offset ``normal . X`` in the world (mm;
            for camera 0's window, the distance from camera 0, the world's origin).
    """
    n_w = unit(world_from_target.R @ np.asarray(plane.normal, float))
    return n_w, float(n_w @ world_from_target.apply(np.asarray(plane.point_mm, float)[None, :])[0])


def plane_errors(plane: WindowPlane, values: gtsam.Values, frame_key: int, with_distance: bool,
                 want_jacobians: bool, window: int = 0) -> tuple[np.ndarray, list[np.ndarray]]:
    """Unwhitened errors of the plane factor and its Jacobians.

    Args:
        plane: the declared plane.
        values: the variables' values.
        frame_key: the key of the plane's frame X(f).
        with_distance: include the distance error e_h (H(w) is a variable).
        want_jacobians: compute the Jacobians.
        window: the window's index w.

    Returns:
        The errors [e_n (3), e_h (1, with ``with_distance``)] and the Jacobians in key order
            [N(w), X(f), H(w)] (empty without ``want_jacobians``).
    """
    n_t, p_t = np.asarray(plane.normal, float), np.asarray(plane.point_mm, float)
    N = values.atUnit3(K_.window_normal(window))
    X = values.atPose3(frame_key)
    R, t = X.rotation().matrix(), np.asarray(X.translation(), float)
    Rn = R @ n_t
    e = [N.point3() - Rn]
    if with_distance:
        e.append(np.array([float(values.atVector(K_.window_plane(window))[0]) - n_t @ p_t - Rn @ t]))
    error = np.concatenate(e)
    if not want_jacobians:
        return error, []
    rows = len(error)
    H_n, H_x = np.zeros((rows, 2)), np.zeros((rows, 6))
    H_n[:3] = np.asarray(N.basis(), float)
    H_x[:3, :3] = R @ skew(n_t)
    Hs = [H_n, H_x]
    if with_distance:
        H_x[3, :3] = t @ R @ skew(n_t)
        H_x[3, 3:] = -n_t
        H_h = np.zeros((rows, 1))
        H_h[3, 0] = 1.0
        Hs.append(H_h)
    return error, Hs


def window_plane_factor(plane: WindowPlane, frame_index: int, with_distance: bool, window: int = 0
                        ) -> gtsam.CustomFactor:
    """One factor tying a window's normal and plane to the declared plane.

    Ties N(w), the frame pose X(frame_index) and (with ``with_distance``) the plane H(w). A sigma of 0 in the
    declared plane holds that part fixed.

    Args:
        plane: the declared plane, with its sigmas (deg, mm).
        frame_index: the index f of the plane's frame X(f).
        with_distance: tie H(w) too (the distance is a variable).
        window: the window's index w.

    Returns:
        The CustomFactor.
    """
    sigma_n = np.radians(plane.sigma_deg) if plane.sigma_deg > 0 else FIXED_SIGMA_RAD
    sigma_h = plane.sigma_mm if plane.sigma_mm > 0 else FIXED_SIGMA_MM
    sigmas = np.array([sigma_n] * 3 + ([sigma_h] if with_distance else []))
    frame_key = K_.X(frame_index)
    keys = [K_.window_normal(window), frame_key] + ([K_.window_plane(window)] if with_distance else [])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        e, Hs = plane_errors(plane, values, frame_key, with_distance, H is not None, window)
        if H is not None:
            for i, Hi in enumerate(Hs):
                H[i] = Hi
        return e

    return gtsam.CustomFactor(gtsam.noiseModel.Diagonal.Sigmas(sigmas), keys, error)

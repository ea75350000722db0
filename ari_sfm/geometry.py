"""Rotations, poses and the window-normal chart, stated once.

Conventions (see CONTRIBUTING.md):
- ``cam_from_world`` (R, t): X_cam = R X_world + t.  ``world_from_target``:
  X_world = R X_target + t.  GTSAM's Pose3 for a camera is ``world_T_cam``
  (camera to world); :func:`pose3_from_cam_from_world` and
  :func:`cam_from_world_from_pose3` are the only places that convert.
- Pose3 tangent vectors are [rotation(3), translation(3)], right-perturbed:
  T * Exp(xi); :func:`se3_exp` is GTSAM's Pose3.Expmap for many twists at once
  (the numpy bundle adjustment retracts every pose with it).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix(es) [v]_x of shape (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotation_from_rotvec(w: np.ndarray | Sequence[float]) -> np.ndarray:
    """Rodrigues: rotation matrix of the rotation vector w (radians)."""
    w = np.asarray(w, dtype=float)
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3) + skew(w)
    k = skew(w / theta)
    return np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * k @ k


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle in degrees of the rotation ``Ra^T Rb``.

    Args:
        Ra: the first rotation matrix (3, 3).
        Rb: the second rotation matrix (3, 3).

    Returns:
        The angle between the two rotations, in degrees.
    """
    c = (np.trace(np.asarray(Ra).T @ np.asarray(Rb)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between two vectors.

    Args:
        a: the first vector (3,), any non-zero length.
        b: the second vector (3,), any non-zero length.

    Returns:
        The angle in degrees, in [0, 180].
    """
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


@dataclass(frozen=True)
class Pose:
    """A rigid transform named by what it maps (e.g. cam_from_world): X_a = R X_b + t."""

    R: np.ndarray
    t: np.ndarray

    @staticmethod
    def identity() -> Pose:
        return Pose(np.eye(3), np.zeros(3))

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Map points (N, 3) or (3,)."""
        return np.asarray(X, float) @ self.R.T + self.t

    def inverse(self) -> Pose:
        return Pose(self.R.T, -self.R.T @ self.t)

    def compose(self, other: Pose) -> Pose:
        """self * other: a_from_b * b_from_c = a_from_c."""
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = self.R, self.t
        return M

    def to_json(self) -> dict:
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @staticmethod
    def from_json(d: dict) -> Pose:
        return Pose(np.asarray(d["R"], float).reshape(3, 3), np.asarray(d["t"], float).reshape(3))


def mean_pose(poses: Sequence[Pose]) -> Pose:
    """Chordal mean of the rotations, arithmetic mean of the translations."""
    return mean_poses([poses])[0]


def mean_poses(groups: Sequence[Sequence[Pose]]) -> list[Pose]:
    """:func:`mean_pose` of each group (the groups of one size at once)."""
    means: dict[int, Pose] = {}
    by_size: dict[int, list[int]] = {}
    for g, poses in enumerate(groups):
        by_size.setdefault(len(poses), []).append(g)
    for size, index in by_size.items():
        R = np.array([[p.R for p in groups[g]] for g in index]).reshape(len(index), size, 3, 3)
        t = np.array([[p.t for p in groups[g]] for g in index]).reshape(len(index), size, 3)
        total = R[:, 0].copy()
        for k in range(1, size):  # summed in order, as sum() does
            total += R[:, k]
        u, _, vt = np.linalg.svd(total)
        d = np.ones((len(index), 3))
        d[:, 2] = np.linalg.det(u @ vt)
        R_mean = (u * d[:, None, :]) @ vt
        t_mean = np.mean(t, axis=1)
        for j, g in enumerate(index):
            means[g] = Pose(R_mean[j], t_mean[j])
    return [means[g] for g in range(len(groups))]


def pose3_from_cam_from_world(cam_from_world: Pose):
    """GTSAM Pose3 world_T_cam of a camera given cam_from_world (the one conversion)."""
    import gtsam

    inv = cam_from_world.inverse()
    return gtsam.Pose3(gtsam.Rot3(inv.R), inv.t)


def cam_from_world_from_pose3(world_T_cam) -> Pose:
    """cam_from_world of a camera given its GTSAM Pose3 world_T_cam (the one conversion)."""
    return Pose(world_T_cam.rotation().matrix(), world_T_cam.translation()).inverse()


def pose3_from_pose(p: Pose):
    """GTSAM Pose3 with the same meaning as p (a_from_b -> a_T_b)."""
    import gtsam

    return gtsam.Pose3(gtsam.Rot3(p.R), np.asarray(p.t, float))


def pose_from_pose3(p) -> Pose:
    return Pose(p.rotation().matrix(), np.asarray(p.translation(), float))


def unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# --------------------------------------------------------------------------- S^2: unit normals


def unit3_basis(n: np.ndarray) -> np.ndarray:
    """The (3, 2) tangent basis of a unit vector, as ``gtsam.Unit3.basis()``.

    ``b1 = n x a / |n x a|`` with a the axis of n's smallest component, ``b2 = n x b1``: every window
    normal's 2-dof tangent space.

    Args:
        n: the unit vector (3,).

    Returns:
        The basis ``[b1, b2]`` as columns (3, 2).
    """
    n = np.asarray(n, float)
    m = np.abs(n)
    axis = np.zeros(3)
    axis[0 if m[0] <= m[1] and m[0] <= m[2] else 1 if m[1] <= m[0] and m[1] <= m[2] else 2] = 1.0
    b1 = np.cross(n, axis)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(n, b1)])


def unit3_retract(n: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The unit vector n moved by a tangent step, as ``gtsam.Unit3.retract``.

    The exponential map: ``cos|xi| n + sin|xi| xi / |xi|`` with ``xi = B v``, B the basis of
    :func:`unit3_basis`.

    Args:
        n: the unit vector (3,).
        v: the tangent step (2,) in n's basis.

    Returns:
        The moved unit vector (3,).
    """
    n = np.asarray(n, float)
    xi = unit3_basis(n) @ np.asarray(v, float)
    theta = float(np.linalg.norm(xi))
    out = n + xi if theta < np.finfo(float).eps else np.cos(theta) * n + (np.sin(theta) / theta) * xi
    return out / np.linalg.norm(out)


# --------------------------------------------------------------------------- SE(3), batched


def se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM's Pose3.Expmap of many twists.

    R = I + A W + B W^2, t = v + B w x v + C w x (w x v) with A = sin t / t,
    B = (1 - cos t) / t^2, C = (t - sin t) / t^3 (Taylor series for small t); compiled
    (:mod:`ari_sfm.se3_kernel`).

    Args:
        xi: twists (N, 6) = [w, v], rotation first.

    Returns:
        Rotations (N, 3, 3) and translations (N, 3).
    """
    from .se3_kernel import se3_exp_kernel

    return se3_exp_kernel(np.ascontiguousarray(np.asarray(xi, float).reshape(-1, 6)))


def retract_poses(R: np.ndarray, t: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Right perturbation ``T Exp(xi)`` of many poses, as Pose3.retract (compiled: :mod:`ari_sfm.se3_kernel`).

    Args:
        R: rotations (N, 3, 3).
        t: translations (N, 3).
        xi: twists (N, 6) = [w, v].

    Returns:
        The retracted rotations (N, 3, 3) and translations (N, 3).
    """
    from .se3_kernel import retract_poses_kernel

    return retract_poses_kernel(np.ascontiguousarray(R, float), np.ascontiguousarray(t, float),
                                np.ascontiguousarray(np.asarray(xi, float).reshape(-1, 6)))

"""Rotations, poses and the window-normal chart, stated once.

Conventions (see CONTRIBUTING.md):
- ``cam_from_world`` (R, t): X_cam = R X_world + t.  ``world_from_target``:
  X_world = R X_target + t.  GTSAM's Pose3 for a camera is ``world_T_cam``
  (camera to world); :func:`pose3_from_cam_from_world` and
  :func:`cam_from_world_from_pose3` are the only places that convert.
- Pose3 tangent vectors are [rotation(3), translation(3)], right-perturbed:
  T * Exp(xi).
"""
from __future__ import annotations

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


def rotation_from_rotvec(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrix of the rotation vector w (radians)."""
    w = np.asarray(w, dtype=float)
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3) + skew(w)
    k = skew(w / theta)
    return np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * k @ k


def rotvec_from_rotation(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rotation_from_rotvec` (radians)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_rotvec()


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle in degrees of the rotation Ra^T Rb."""
    c = (np.trace(np.asarray(Ra).T @ np.asarray(Rb)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between two vectors."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


@dataclass(frozen=True)
class Pose:
    """A rigid transform named by what it maps (e.g. cam_from_world): X_a = R X_b + t."""

    R: np.ndarray
    t: np.ndarray

    @staticmethod
    def identity() -> "Pose":
        return Pose(np.eye(3), np.zeros(3))

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Map points (N, 3) or (3,)."""
        return np.asarray(X, float) @ self.R.T + self.t

    def inverse(self) -> "Pose":
        return Pose(self.R.T, -self.R.T @ self.t)

    def compose(self, other: "Pose") -> "Pose":
        """self * other: a_from_b * b_from_c = a_from_c."""
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = self.R, self.t
        return M

    def to_json(self) -> dict:
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @staticmethod
    def from_json(d: dict) -> "Pose":
        return Pose(np.asarray(d["R"], float).reshape(3, 3), np.asarray(d["t"], float).reshape(3))


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

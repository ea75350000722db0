"""Removing the window from the generalised extrinsics (paper Eqs. 11-12).

Eq. 11 writes the generalised extrinsics as B = A [R_WI t_WI; 0 1] with
A = R_IC X_R, where X_R = [I | t_R] shifts by delta = d (1 - 1/n) along the
normal. Since A's 3x3 block is a rotation, Eq. 12 has the unique solution
R = R_B (rotation unchanged) and t = t_B + delta n_cam: the real target sits
delta farther along the normal than the virtual pinhole sees it. In this
project the interface frame is represented by the normal alone, so T_WI is the
real cam_from_target pose returned here.
"""
from __future__ import annotations

import numpy as np

from ..geometry import Pose


def real_cam_from_target(generalised: Pose, normal_cam: np.ndarray, shift_mm: float) -> Pose:
    """Give the physical cam_from_target from the generalised (virtual-pinhole) one (paper Eq. 12).

    Args:
        generalised: the virtual pinhole's cam_from_target.
        normal_cam: the window normal in the camera frame (3,).
        shift_mm: delta = d (1 - 1/n), how much farther along the normal the real target sits (mm).

    Returns:
        The physical cam_from_target (rotation unchanged).
    """
    return Pose(generalised.R, generalised.t + shift_mm * np.asarray(normal_cam, float))


def solve_eq12(A: np.ndarray, B: np.ndarray) -> Pose:
    """Solve B = A [R t; 0 1] for (R, t) by linear least squares (the paper's Eq. 12 system).

    The literal form of the paper's step; it equals :func:`real_cam_from_target` when
    A = [R_IC | R_IC t_R].

    Args:
        A: the 3x4 matrix R_IC X_R.
        B: the 3x4 generalised extrinsics.

    Returns:
        The pose (R, t).
    """
    M = np.zeros((12, 12))
    rhs = np.zeros(12)
    for i in range(3):
        for j in range(3):  # columns of R
            M[4 * i + j, 3 * j : 3 * j + 3] = A[i, :3]
            rhs[4 * i + j] = B[i, j]
        M[4 * i + 3, 9:12] = A[i, :3]
        rhs[4 * i + 3] = B[i, 3] - A[i, 3]
    x = np.linalg.lstsq(M, rhs, rcond=None)[0]
    return Pose(x[:9].reshape(3, 3).T, x[9:12])

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
    """The physical cam_from_target given the generalised (virtual-pinhole) one."""
    return Pose(generalised.R, generalised.t + shift_mm * np.asarray(normal_cam, float))


def solve_eq12(A: np.ndarray, B: np.ndarray) -> Pose:
    """Solve B = A [R t; 0 1] for (R, t) by linear least squares (the paper's Eq. 12 system).

    A and B are 3x4. Kept as the literal form of the paper's step; it equals
    :func:`real_cam_from_target` when A = [R_IC | R_IC t_R].
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

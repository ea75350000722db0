"""GTSAM's Pose3.Expmap and the right-perturbation retraction of many poses, compiled (numba,
``cache=True``): the one copy behind :func:`ari_sfm.geometry.se3_exp` and
:func:`~ari_sfm.geometry.retract_poses`, which the numpy bundle adjustment calls on every trial.

The arithmetic is that of the formulas of :func:`~ari_sfm.geometry.se3_exp`'s docstring evaluated by
numpy's ``@`` (OpenBLAS: a fused multiply-add chain ``fma(a2, b2, fma(a1, b1, a0 b0))``) and ``einsum``
(three terms as ``(x0 + x2) + x1``), written out below, so the poses are numpy's to the last bit.
"""
from __future__ import annotations

import numpy as np

from .kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first
from .models.kernels import fma as _fma  # an intrinsic: inlined LLVM, no cached code of that module's

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(inline="always", **_JIT)
def _dot3(a0, a1, a2, b0, b1, b2):
    """numpy's 3x3 ``@`` entry (OpenBLAS's order)."""
    return _fma(a2, b2, _fma(a1, b1, a0 * b0))


@njit(inline="always", **_JIT)
def _exp_one(xi, n, dR, dt):
    """Expmap of twist ``xi[n]`` into dR (3, 3) and dt (3,)."""
    w0, w1, w2, v0, v1, v2 = xi[n, 0], xi[n, 1], xi[n, 2], xi[n, 3], xi[n, 4], xi[n, 5]
    th2 = (w0 * w0 + w2 * w2) + w1 * w1  # einsum's order
    if th2 < 1e-6:
        A = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
        B = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
        C = 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0
    else:
        th = np.sqrt(th2)
        s2 = np.sin(0.5 * th)
        A = np.sin(th) / th
        B = 2.0 * s2 * s2 / (th * th)
        C = (1.0 - A) / (th * th)
    W = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    for i in range(3):
        for j in range(3):
            W2 = _dot3(W[i][0], W[i][1], W[i][2], W[0][j], W[1][j], W[2][j])
            dR[i, j] = ((1.0 if i == j else 0.0) + A * W[i][j]) + B * W2
    x0, x1, x2 = w1 * v2 - w2 * v1, w2 * v0 - w0 * v2, w0 * v1 - w1 * v0
    y0, y1, y2 = w1 * x2 - w2 * x1, w2 * x0 - w0 * x2, w0 * x1 - w1 * x0
    dt[0] = (v0 + B * x0) + C * y0
    dt[1] = (v1 + B * x1) + C * y1
    dt[2] = (v2 + B * x2) + C * y2


@njit(**_JIT)
def se3_exp_kernel(xi):
    """Rotations (N, 3, 3) and translations (N, 3) of twists xi (N, 6) = [w, v]."""
    R, t = np.empty((len(xi), 3, 3)), np.empty((len(xi), 3))
    for n in range(len(xi)):
        _exp_one(xi, n, R[n], t[n])
    return R, t


@njit(**_JIT)
def retract_poses_kernel(R, t, xi):
    """``T Exp(xi)`` of poses T = (R, t): ``(R dR, t + R dt)`` with ``(dR, dt) = Exp(xi)``.

    Args:
        R: rotations (N, 3, 3).
        t: translations (N, 3).
        xi: twists (N, 6) = [w, v].

    Returns:
        The retracted rotations (N, 3, 3) and translations (N, 3).
    """
    R_out, t_out = np.empty((len(xi), 3, 3)), np.empty((len(xi), 3))
    dR, dt = np.empty((3, 3)), np.empty(3)
    for n in range(len(xi)):
        _exp_one(xi, n, dR, dt)
        for i in range(3):
            for j in range(3):
                R_out[n, i, j] = _dot3(R[n, i, 0], R[n, i, 1], R[n, i, 2], dR[0, j], dR[1, j], dR[2, j])
            t_out[n, i] = t[n, i] + ((R[n, i, 0] * dt[0] + R[n, i, 2] * dt[2]) + R[n, i, 1] * dt[1])
    return R_out, t_out

"""refine-colmap's chain rule, compiled (numba, ``cache=True``).

The exact model's Jacobians in the camera frame (point, normal, distance;
:func:`ari_sfm.models.exact.exact_project`) carried to the problem's tangent spaces (:mod:`.problem`'s
module docstring) in one pass over the observations.

Per observation o and pixel row j (row vectors; ``x`` the cross product, ``j^T [v]x = j x v``):
``a = R X`` and an image pose perturbation (w, v) of cam_from_world gives ``dX_cam = -[a]x w + v``::

    J_w = a x J_X          J_v = J_X
    mount world (n_cam = R n_w, h = plane - n_w . C):
      J_w += n_cam x J_n + J_h (n_cam x t)      J_v += J_h n_cam
      window [e1 e2] = (J_n R) B - J_h (C . B),  window d = J_h
    mount camera: window [e1 e2] = J_n B_c, window d = J_h
    frame (rig_from_world) = [J_w S, J_v S]   sensor (sensor_from_rig) = [J_w - J_v x (S P t), J_v]
    point = J_X R
"""
from __future__ import annotations

from ...kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def chain_observations(J_X, J_n, J_h, a, R, t, S, StP, world, n_cam, B, centres, out, frame0, sensor0, window0,
                       J_p):
    """Fill the observations' frame, sensor and window columns of ``out`` and their point Jacobians (module docstring).

    Args:
        J_X: d uv / d X_cam (M, 2, 3) from the exact model.
        J_n: d uv / d n_cam (M, 2, 3) from the exact model.
        J_h: d uv / d h (M, 2) from the exact model.
        a: ``R X`` (M, 3), the rotated point.
        R: each observation's image's cam_from_world rotation (M, 3, 3).
        t: its cam_from_world translation (M, 3).
        S: its sensor's rotation (sensor_from_rig) (M, 3, 3).
        StP: ``S (rig_from_world t)`` (M, 3).
        world: mount world (else mount camera).
        n_cam: the window's normal in the camera frame (M, 3) (mount world only).
        B: the normal's tangent basis (M, 3, 2) (world: the world normal's).
        centres: the camera centres C in the world (M, 3) (mount world only).
        out: the rows (M, 2, .), filled at columns frame0.. (6), sensor0.. (6), window0.. (3).
        frame0: the frame's (rig_from_world) first column in ``out``.
        sensor0: the sensor's (sensor_from_rig) first column in ``out``.
        window0: the window's first column in ``out`` ([e1, e2, distance]).
        J_p: out, the point Jacobians (M, 2, 3).
    """
    M = J_X.shape[0]
    jw = [0.0, 0.0, 0.0]
    jv = [0.0, 0.0, 0.0]
    for o in range(M):
        for r in range(2):
            j0, j1, j2 = J_X[o, r, 0], J_X[o, r, 1], J_X[o, r, 2]
            a0, a1, a2 = a[o, 0], a[o, 1], a[o, 2]
            jw[0] = a1 * j2 - a2 * j1
            jw[1] = a2 * j0 - a0 * j2
            jw[2] = a0 * j1 - a1 * j0
            jv[0], jv[1], jv[2] = j0, j1, j2
            h = J_h[o, r]
            n0, n1, n2 = J_n[o, r, 0], J_n[o, r, 1], J_n[o, r, 2]
            if world:
                c0, c1, c2 = n_cam[o, 0], n_cam[o, 1], n_cam[o, 2]
                t0, t1, t2 = t[o, 0], t[o, 1], t[o, 2]
                jw[0] += c1 * n2 - c2 * n1 + h * (c1 * t2 - c2 * t1)
                jw[1] += c2 * n0 - c0 * n2 + h * (c2 * t0 - c0 * t2)
                jw[2] += c0 * n1 - c1 * n0 + h * (c0 * t1 - c1 * t0)
                jv[0] += h * c0
                jv[1] += h * c1
                jv[2] += h * c2
                cb0 = centres[o, 0] * B[o, 0, 0] + centres[o, 1] * B[o, 1, 0] + centres[o, 2] * B[o, 2, 0]
                cb1 = centres[o, 0] * B[o, 0, 1] + centres[o, 1] * B[o, 1, 1] + centres[o, 2] * B[o, 2, 1]
                m0 = n0 * R[o, 0, 0] + n1 * R[o, 1, 0] + n2 * R[o, 2, 0]  # J_n R
                m1 = n0 * R[o, 0, 1] + n1 * R[o, 1, 1] + n2 * R[o, 2, 1]
                m2 = n0 * R[o, 0, 2] + n1 * R[o, 1, 2] + n2 * R[o, 2, 2]
                out[o, r, window0] = m0 * B[o, 0, 0] + m1 * B[o, 1, 0] + m2 * B[o, 2, 0] - h * cb0
                out[o, r, window0 + 1] = m0 * B[o, 0, 1] + m1 * B[o, 1, 1] + m2 * B[o, 2, 1] - h * cb1
            else:
                out[o, r, window0] = n0 * B[o, 0, 0] + n1 * B[o, 1, 0] + n2 * B[o, 2, 0]
                out[o, r, window0 + 1] = n0 * B[o, 0, 1] + n1 * B[o, 1, 1] + n2 * B[o, 2, 1]
            out[o, r, window0 + 2] = h
            for c in range(3):
                out[o, r, frame0 + c] = jw[0] * S[o, 0, c] + jw[1] * S[o, 1, c] + jw[2] * S[o, 2, c]
                out[o, r, frame0 + 3 + c] = jv[0] * S[o, 0, c] + jv[1] * S[o, 1, c] + jv[2] * S[o, 2, c]
                J_p[o, r, c] = j0 * R[o, 0, c] + j1 * R[o, 1, c] + j2 * R[o, 2, c]
            p0, p1, p2 = StP[o, 0], StP[o, 1], StP[o, 2]
            out[o, r, sensor0] = jw[0] - (jv[1] * p2 - jv[2] * p1)
            out[o, r, sensor0 + 1] = jw[1] - (jv[2] * p0 - jv[0] * p2)
            out[o, r, sensor0 + 2] = jw[2] - (jv[0] * p1 - jv[1] * p0)
            out[o, r, sensor0 + 3] = jv[0]
            out[o, r, sensor0 + 4] = jv[1]
            out[o, r, sensor0 + 5] = jv[2]

"""The view factor's chain rule to the tangent spaces, compiled (numba, ``cache=True``).

The one copy, called by the GTSAM factor (:func:`~ari_sfm.factors.view_factor.view_residuals`, through
:func:`chain_rows`) and by the numpy backend (:meth:`~ari_sfm.factors.packed_problem.VectorizedProblem.linearize`,
through :func:`accumulate_views`, which also forms each view's normal equations in the same pass, and
:func:`add_camera`, which adds a camera's to the whole system). The model's derivatives come in as arrays
(the physics stays in :mod:`ari_sfm.models.kernels`), the Huber weights from :mod:`~ari_sfm.factors.robust`.

One corner of one camera and one view, pixel row j (row vectors; ``j x v`` is ``j^T [v]x``), from
the model's ``J_X``, ``J_n`` (3,) and ``J_h`` (scalar) at ``X = R_ct P + t_ct``
(:mod:`~ari_sfm.factors.view_factor`'s module docstring derives it)::

    target pose (rotation, translation):  J_A x (-P),  J_A        with J_A = J_X R_ct
    camera pose (rotation):                J_X x X + J_n x n_cam   with n_cam = R_cw n_world
    camera pose (translation):             J_h a - J_X             with a = -(n_world R_wc)
    normal (Unit3 tangent):                J_n M + J_h b           with M = R_cw B, b = -(t_wc B)
    distance:                              J_h

Row layout: ``[X(f) (6) | K(c) (n_params, the model's J_params) | C(c) (6) | N (2) | H (1, if estimated)]``;
camera 0 (the world) has no pose variable: its C columns are zero.
"""
from __future__ import annotations

import numpy as np

from ..kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first
from ..models.kernels import fma  # an intrinsic: inlined LLVM, no cached code of that module's

_JIT = dict(cache=True, nogil=True)  # no division anywhere: numba's default error model compiles faster


@njit(inline="always", **_JIT)
def _tangent_row(J_point, J_normal, J_distance, o, j, X_cam, P, R_ct, n_cam, cam_shift, normal_map, normal_shift,
                 pose, distance, k, kn, row):
    """Pixel row j of corner o into ``row`` (module docstring): the target pose at 0..6, the camera pose
    at k..k + 6 (only with ``pose``), the normal at kn, kn + 1, the distance at kn + 2 (with ``distance``);
    the intrinsics' columns 6..k are left to the caller."""
    j0, j1, j2 = J_point[o, j, 0], J_point[o, j, 1], J_point[o, j, 2]
    a0 = j0 * R_ct[0, 0] + j1 * R_ct[1, 0] + j2 * R_ct[2, 0]  # J_A = J_X R_ct
    a1 = j0 * R_ct[0, 1] + j1 * R_ct[1, 1] + j2 * R_ct[2, 1]
    a2 = j0 * R_ct[0, 2] + j1 * R_ct[1, 2] + j2 * R_ct[2, 2]
    p0, p1, p2 = -P[o, 0], -P[o, 1], -P[o, 2]
    row[0] = a1 * p2 - a2 * p1
    row[1] = a2 * p0 - a0 * p2
    row[2] = a0 * p1 - a1 * p0
    row[3] = a0
    row[4] = a1
    row[5] = a2
    n0, n1, n2 = J_normal[o, j, 0], J_normal[o, j, 1], J_normal[o, j, 2]
    h = J_distance[o, j]
    if pose:
        x0, x1, x2 = X_cam[o, 0], X_cam[o, 1], X_cam[o, 2]
        c0, c1, c2 = n_cam[0], n_cam[1], n_cam[2]
        row[k] = (j1 * x2 - j2 * x1) + (n1 * c2 - n2 * c1)
        row[k + 1] = (j2 * x0 - j0 * x2) + (n2 * c0 - n0 * c2)
        row[k + 2] = (j0 * x1 - j1 * x0) + (n0 * c1 - n1 * c0)
        row[k + 3] = h * cam_shift[0] - j0
        row[k + 4] = h * cam_shift[1] - j1
        row[k + 5] = h * cam_shift[2] - j2
    row[kn] = (n0 * normal_map[0, 0] + n1 * normal_map[1, 0] + n2 * normal_map[2, 0]) + h * normal_shift[0]
    row[kn + 1] = (n0 * normal_map[0, 1] + n1 * normal_map[1, 1] + n2 * normal_map[2, 1]) + h * normal_shift[1]
    if distance:
        row[kn + 2] = h


@njit(**_JIT)
def rig_transforms(world_R_cam, world_t_cam, world_R_target, world_t_target, view_camera, view_frame, normal_world,
                   distance, with_distance):
    """The packed problem's per-view and per-camera quantities (its ``_Transforms``).

    R_ct = R_cw R_wt and t_ct = R_cw (t_wt - t_wc) per view, n_c = R_cw n_w and (with ``with_distance``)
    h_c = h - t_wc . n_w per camera, R_cw = R_wc^T.

    Args:
        world_R_cam: each camera's world_T_cam rotation (C, 3, 3).
        world_t_cam: each camera's world_T_cam translation (C, 3).
        world_R_target: each frame's world_T_target rotation (F, 3, 3).
        world_t_target: each frame's world_T_target translation (F, 3).
        view_camera: each view's camera (V,).
        view_frame: each view's frame (V,).
        normal_world: the window's unit normal n_w in the world (3,).
        distance: the window's plane offset h (mm).
        with_distance: compute h_c.

    Returns:
        R_ct (V, 3, 3), t_ct (V, 3), n_c (C, 3) and h_c (C,) (empty without ``with_distance``).
    """
    V, C = view_camera.shape[0], world_R_cam.shape[0]
    R_ct, t_ct = np.empty((V, 3, 3)), np.empty((V, 3))
    for v in range(V):
        R, Rt, c = world_R_cam[view_camera[v]], world_R_target[view_frame[v]], view_camera[v]
        for i in range(3):  # row i of R_cw: column i of R_wc
            for j in range(3):
                R_ct[v, i, j] = fma(R[2, i], Rt[2, j], fma(R[1, i], Rt[1, j], R[0, i] * Rt[0, j]))
        d0 = world_t_target[view_frame[v], 0] - world_t_cam[c, 0]
        d1 = world_t_target[view_frame[v], 1] - world_t_cam[c, 1]
        d2 = world_t_target[view_frame[v], 2] - world_t_cam[c, 2]
        for i in range(3):
            t_ct[v, i] = (R[0, i] * d0 + R[1, i] * d1) + R[2, i] * d2
    n_c, h_c = np.empty((C, 3)), np.empty(C if with_distance else 0)
    n0, n1, n2 = normal_world[0], normal_world[1], normal_world[2]
    for c in range(C):
        R = world_R_cam[c]
        for i in range(3):
            n_c[c, i] = (R[0, i] * n0 + R[1, i] * n1) + R[2, i] * n2
        if with_distance:
            t = world_t_cam[c]
            tn = (t[0] * n0 + t[1] * n1) + t[2] * n2 if C == 1 else fma(t[2], n2, fma(t[0], n0, t[1] * n1))
            h_c[c] = distance - tn
    return R_ct, t_ct, n_c, h_c


@njit(**_JIT)
def transform_points(P, R_view, t_view, view_start):
    """``R P + t`` of corners grouped by view.

    Args:
        P: the corners (m, 3).
        R_view: each view's rotation R (nv, 3, 3).
        t_view: each view's translation t (nv, 3).
        view_start: view v's corners are ``view_start[v]:view_start[v + 1]`` (nv + 1,).

    Returns:
        The transformed corners (m, 3).
    """
    X = np.empty_like(P)
    for v in range(len(view_start) - 1):
        R, t = R_view[v], t_view[v]
        for o in range(view_start[v], view_start[v + 1]):
            q0, q1, q2 = P[o, 0], P[o, 1], P[o, 2]
            for i in range(3):
                X[o, i] = q0 * R[i, 0] + q1 * R[i, 1] + q2 * R[i, 2] + t[i]
    return X


@njit(**_JIT)
def chain_rows(J_point, J_normal, J_distance, X_cam, P, R_view, view_start, n_cam, cam_shift, normal_map,
               normal_shift, pose, distance, n_params, out):
    """Every corner's tangent-space rows into ``out`` (module docstring's row layout).

    The intrinsics' columns 6..6 + n_params and, for a camera without a pose (camera 0), its pose columns
    are left as the caller's (zeros).

    Args:
        J_point: d uv / d X_cam (m, 2, 3) from the model.
        J_normal: d uv / d n_cam (m, 2, 3) from the model.
        J_distance: d uv / d h_c (m, 2) from the model.
        X_cam: the camera-frame points (m, 3).
        P: the target-frame points (m, 3).
        R_view: each view's R_ct (nv, 3, 3).
        view_start: view v's corners are ``view_start[v]:view_start[v + 1]`` (nv + 1,).
        n_cam: the window's normal in the camera frame, R_cw n_world (3,)
            (:func:`~ari_sfm.factors.view_factor.camera_terms`).
        cam_shift: ``a`` = -(n_world R_wc) (3,).
        normal_map: ``M`` = R_cw B (3, 2), B the normal's Unit3 tangent basis.
        normal_shift: ``b`` = -(t_wc B) (2,).
        pose: the camera has a pose variable (not camera 0).
        distance: fill the H column (the distance is a variable).
        n_params: the number of intrinsics columns.
        out: the rows (m, 2, >= 6 + n_params + 8 (+1)), filled in place.
    """
    k = 6 + n_params
    for v in range(len(view_start) - 1):
        R_ct = R_view[v]
        for o in range(view_start[v], view_start[v + 1]):
            for j in range(2):
                _tangent_row(J_point, J_normal, J_distance, o, j, X_cam, P, R_ct, n_cam, cam_shift, normal_map,
                             normal_shift, pose, distance, k, k + 6, out[o, j])


@njit(**_JIT)
def accumulate_views(J_point, J_normal, J_distance, J_params, X_cam, P, R_view, view_start, n_cam, cam_shift,
                     normal_map, normal_shift, pose, distance, row_scale, residual, V, g_frame, W, U, g_camera, bad):
    """One camera's normal equations, in its own arrays (zeros in, filled in place).

    Each view's ``A^T A`` of its whitened rows ``A = [J_frame | J_camera | r]`` (filled in a scratch of the
    largest view's size, multiplied by BLAS), summed over the camera's views; :func:`add_camera` adds them
    to the whole system. The rows are :func:`chain_rows`' with the intrinsics from ``J_params``, without the
    pose columns when the camera has none (camera 0). The outputs are by view v and camera-local column
    (L of them: intrinsics, pose if any, normal, distance).

    Args:
        J_point: d uv / d X_cam (m, 2, 3) from the model.
        J_normal: d uv / d n_cam (m, 2, 3) from the model.
        J_distance: d uv / d h_c (m, 2) from the model.
        X_cam: the camera-frame points (m, 3).
        P: the target-frame points (m, 3).
        R_view: each view's R_ct (nv, 3, 3).
        view_start: view v's corners are ``view_start[v]:view_start[v + 1]`` (nv + 1,).
        n_cam: the window's normal in the camera frame, R_cw n_world (3,)
            (:func:`~ari_sfm.factors.view_factor.camera_terms`).
        cam_shift: ``a`` = -(n_world R_wc) (3,).
        normal_map: ``M`` = R_cw B (3, 2), B the normal's Unit3 tangent basis.
        normal_shift: ``b`` = -(t_wc B) (2,).
        pose: the camera has a pose variable (not camera 0).
        distance: fill the H column (the distance is a variable).
        J_params: d uv / d intrinsics (m, 2, n_params) from the model.
        row_scale: each corner's Jacobian scale (m,): sqrt of the IRLS weight over sigma.
        residual: the residuals (m, 2), already whitened.
        V: out, J_frame^T J_frame per view (nv, 6, 6).
        g_frame: out, J_frame^T r per view (nv, 6).
        W: out, J_frame^T J_camera per view (nv, 6, L).
        U: out, J_camera^T J_camera summed over the views (L, L).
        g_camera: out, J_camera^T r summed over the views (L,).
        bad: out (m,): set True where a Jacobian entry is not finite.

    Returns:
        The sum of the squared (whitened) residuals.
    """
    n_params = J_params.shape[2]
    L = U.shape[0]
    K = 6 + L
    k = 6 + n_params
    kn = k + 6 if pose else k
    most = 0
    for v in range(len(view_start) - 1):
        most = max(most, view_start[v + 1] - view_start[v])
    A = np.empty((2 * most, K + 1))  # one view's rows
    err2 = 0.0
    for v in range(len(view_start) - 1):
        R_ct = R_view[v]
        first, n = view_start[v], view_start[v + 1] - view_start[v]
        for o in range(first, first + n):
            s = row_scale[o]
            for j in range(2):
                row = A[2 * (o - first) + j]
                _tangent_row(J_point, J_normal, J_distance, o, j, X_cam, P, R_ct, n_cam, cam_shift, normal_map,
                             normal_shift, pose, distance, k, kn, row)
                for i in range(n_params):
                    row[6 + i] = J_params[o, j, i]
                check = 0.0
                for i in range(K):
                    row[i] *= s
                    check += row[i]
                if not np.isfinite(check):
                    bad[o] = True
                row[K] = residual[o, j]
        Av = A[:2 * n]
        H = np.dot(Av.T, Av)
        for a in range(6):
            for b in range(6):
                V[v, a, b] = H[a, b]
            g_frame[v, a] = H[a, K]
            for b in range(L):
                W[v, a, b] = H[a, 6 + b]
        for a in range(L):
            for b in range(L):
                U[a, b] += H[6 + a, 6 + b]
            g_camera[a] += H[6 + a, K]
        err2 += H[K, K]
    return err2


@njit(**_JIT)
def add_camera(V_c, g_frame_c, W_c, U_c, g_camera, view_frame, cols, V, g_frame, W, U, g_global):
    """One camera's normal equations (:func:`accumulate_views`' arrays) added to the whole system's, in place.

    The cameras are added one after the other, in their order, whichever thread formed each.

    Args:
        V_c: the camera's per-view frame blocks (nv, 6, 6).
        g_frame_c: its per-view frame gradients (nv, 6).
        W_c: its per-view couplings (nv, 6, L).
        U_c: its camera-local block (L, L).
        g_camera: its camera-local gradient (L,).
        view_frame: each view's frame (nv,).
        cols: the global column of each camera-local one (L,).
        V: the system's frame blocks (F, 6, 6), added to.
        g_frame: the system's frame gradients (F, 6), added to.
        W: the system's couplings (F, 6, G), added to.
        U: the system's global block (G, G), added to.
        g_global: the system's global gradient (G,), added to.
    """
    L = cols.shape[0]
    for v in range(view_frame.shape[0]):
        f = view_frame[v]
        for a in range(6):
            for b in range(6):
                V[f, a, b] += V_c[v, a, b]
            g_frame[f, a] += g_frame_c[v, a]
            for b in range(L):
                W[f, a, cols[b]] += W_c[v, a, b]
    for a in range(L):
        for b in range(L):
            U[cols[a], cols[b]] += U_c[a, b]
        g_global[cols[a]] += g_camera[a]

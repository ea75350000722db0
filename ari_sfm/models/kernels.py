"""The compiled physics: pinhole + OpenCV distortion, the exact model's Newton solve and analytic
Jacobians, Snell back-projection and triangulation through the window (numba, ``cache=True``).

These kernels are THE implementation: :mod:`.pinhole`, :mod:`.ari`, :mod:`.exact`, the numpy
bundle adjustment, the GTSAM factors, refine-colmap and :mod:`ari_sfm.reconstruction.triangulate` all call them
through the public functions of those modules. The maths is derived in the docstrings of
:mod:`.pinhole` (distortion) and :mod:`.exact` (incidence equation, implicit-function Jacobians).
The per-point parts work on scalars; a batch solves the incidence equation of all its points in
lock-step and allocates its outputs and a few (m,) arrays. A kernel calls only kernels of this
module (the reason: docs/design/models.md).

Compilation: the first call of each kernel in a fresh install compiles it and numba caches the
machine code: in ``NUMBA_CACHE_DIR`` when set, else next to this file (``__pycache__``), else,
when that folder is read-only (a system site-packages), in its user-wide cache
(``~/.cache/numba``); later processes load it in milliseconds.
"""
from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from ..kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first

NEWTON_MAX_ITER = 20  # a cap; the paper camera needs 5 (air) to 6 (water) over its whole image
NEWTON_REL_TOL = 1e-12  # stop when |step| <= tol * w; quadratic convergence leaves ~1e-24 + rounding
NEWTON_NOT_CONVERGED = -1  # solve_w status: no convergence within max_iter
NEWTON_NOT_FINITE = -2  # solve_w status: a non-finite Newton step

UNDISTORT_TOL_PX = 1e-12  # stop when the step (in pixels) is below this
UNDISTORT_FAIL_PX = 1e-9  # a final residual above this marks the point as failed (NaN)
UNDISTORT_MAX_ITER = 50

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@intrinsic
def fma(typingctx, a, b, c):
    """``a * b + c`` rounded once: LLVM's ``llvm.fma.f64`` (the CPU's fused multiply-add, else libm's).

    A numba intrinsic: compiled code calls it as ``fma(a, b, c)`` on float64 values.

    Args:
        typingctx: numba's typing context (passed by numba, not by the caller).
        a: the first factor.
        b: the second factor.
        c: the addend.

    Returns:
        The intrinsic's signature and code generator (in compiled code: the float64 ``a * b + c``).
    """
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        return builder.call(builder.module.declare_intrinsic("llvm.fma", [d], ir.FunctionType(d, [d, d, d])), args)

    return sig, codegen


# --------------------------------------------------------------------------- pinhole + distortion


@njit(inline="always", **_JIT)
def distort_point(x, y, dist, J_xy, J_dist):
    """OpenCV distortion of one normalised point, with its Jacobians.

    Args:
        x: undistorted normalised x.
        y: undistorted normalised y.
        dist: distortion ``[k1, k2, p1, p2, k3]`` (5,).
        J_xy: output (2, 2), filled with d xyd / d xy.
        J_dist: output (2, 5), filled with d xyd / d [k1, k2, p1, p2, k3].

    Returns:
        The distorted point ``(xd, yd)``.
    """
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    cross = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y  # symmetric off-diagonal
    J_xy[0, 0] = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    J_xy[0, 1] = cross
    J_xy[1, 0] = cross
    J_xy[1, 1] = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    r4 = r2 * r2
    J_dist[0, 0], J_dist[1, 0] = x * r2, y * r2
    J_dist[0, 1], J_dist[1, 1] = x * r4, y * r4
    J_dist[0, 2], J_dist[1, 2] = 2.0 * x * y, r2 + 2.0 * y * y
    J_dist[0, 3], J_dist[1, 3] = r2 + 2.0 * x * x, 2.0 * x * y
    J_dist[0, 4], J_dist[1, 4] = x * r4 * r2, y * r4 * r2
    return xd, yd


@njit(inline="always", **_JIT)
def pinhole_point(D0, D1, D2, params, n_params, jacobians, uv, J_point, J_params, J_xy, J_dist):
    """Pixel of one camera-frame direction D, written into ``uv`` (NaN if D2 <= 0).

    Args:
        D0: x of D.
        D1: y of D.
        D2: z of D.
        params: intrinsics (9,) ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]``.
        n_params: number of leading ``params`` columns in ``J_params``.
        jacobians: fill ``J_point`` and ``J_params``.
        uv: output pixel (2,).
        J_point: output (2, 3), d uv / d D (with ``jacobians``).
        J_params: output (2, n_params), d uv / d params[:n_params] (with ``jacobians``).
        J_xy: scratch (2, 2).
        J_dist: scratch (2, 5).
    """
    if D2 > 0.0:
        x, y = D0 / D2, D1 / D2
    else:
        x, y = np.nan, np.nan
    fx, fy = params[0], params[1]
    xd, yd = distort_point(x, y, params[4:], J_xy, J_dist)
    uv[0] = xd * fx + params[2]
    uv[1] = yd * fy + params[3]
    if not jacobians:
        return
    inv_z = 1.0 / D2
    # diag(f) J_xy [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
    for k in range(2):
        f = fx if k == 0 else fy
        a, b = f * J_xy[k, 0], f * J_xy[k, 1]
        J_point[k, 0] = a * inv_z
        J_point[k, 1] = b * inv_z
        J_point[k, 2] = a * (-x * inv_z) + b * (-y * inv_z)
    for j in range(n_params):
        J_params[0, j] = 0.0
        J_params[1, j] = 0.0
    J_params[0, 0] = xd
    J_params[1, 1] = yd
    J_params[0, 2] = 1.0
    J_params[1, 3] = 1.0
    for j in range(4, n_params):
        J_params[0, j] = fx * J_dist[0, j - 4]
        J_params[1, j] = fy * J_dist[1, j - 4]


@njit(**_JIT)
def pinhole_batch(D, params, n_params, jacobians):
    """Pinhole projection of camera-frame directions.

    Args:
        D: directions (m, 3).
        params: intrinsics (9,).
        n_params: number of leading ``params`` columns in ``J_params``.
        jacobians: compute the Jacobians.

    Returns:
        Pixels (m, 2), J_point (m, 2, 3) and J_params (m, 2, n_params); the Jacobians are empty (0, ...)
            arrays without ``jacobians``.
    """
    m = D.shape[0]
    uv = np.empty((m, 2))
    mj = m if jacobians else 1
    J_point = np.empty((mj, 2, 3))
    J_params = np.empty((mj, 2, n_params))
    J_xy = np.empty((2, 2))
    J_dist = np.empty((2, 5))
    for i in range(m):
        k = i if jacobians else 0
        pinhole_point(D[i, 0], D[i, 1], D[i, 2], params, n_params, jacobians, uv[i], J_point[k], J_params[k],
                      J_xy, J_dist)
    if not jacobians:
        return uv, J_point[:0], J_params[:0]
    return uv, J_point, J_params


@njit(**_JIT)
def ari_batch(X, params, nc, dn_dv, thickness, index, medium_index, h, n_params, jacobians):
    """The ARI projection of camera-frame points, one plate thickness per point.

    The model is :func:`ari_sfm.models.ari.ari_project`'s (its docstring and module derive it).

    Args:
        X: camera-frame points (m, 3).
        params: intrinsics (9,).
        nc: unit window normal (3,), camera frame.
        dn_dv: d n / d v (3, 3) of the free normal vector
            (:func:`~ari_sfm.models.ari.unit_normal_and_projector`).
        thickness: plate thickness per point (m,).
        index: glass index.
        medium_index: medium index.
        h: near-face distance (mm; unused in air).
        n_params: number of leading ``params`` columns in ``J_params``.
        jacobians: compute the Jacobians.

    Returns:
        uv (m, 2), J_point and J_normal (m, 2, 3), J_params (m, 2, n_params), J_thickness and J_distance
            (m, 2); the Jacobians are empty (0, ...) arrays without ``jacobians``.
    """
    m = X.shape[0]
    b = 1.0 / medium_index - 1.0
    da_dd, da_dh = 1.0 / index - 1.0 / medium_index, 1.0 - 1.0 / medium_index
    mj = m if jacobians else 0
    uv = np.empty((m, 2))
    J_point, J_normal, J_params = np.empty((mj, 2, 3)), np.empty((mj, 2, 3)), np.empty((mj, 2, n_params))
    J_thickness, J_distance = np.empty((mj, 2)), np.empty((mj, 2))
    J_pin, J_par, J_xy, J_dist, free = np.empty((2, 3)), np.empty((2, n_params)), np.empty((2, 2)), np.empty((2, 5)), \
        np.empty(3)
    for i in range(m):
        d = thickness[i]
        si = h + d / index - (h + d) / medium_index  # X_app = X + s n_c, s = a + b z
        if b != 0.0:
            si = si + b * fma(X[i, 2], nc[2], fma(X[i, 0], nc[0], X[i, 1] * nc[1]))
        pinhole_point(X[i, 0] + si * nc[0], X[i, 1] + si * nc[1], X[i, 2] + si * nc[2], params, n_params, jacobians,
                      uv[i], J_pin, J_params[i] if jacobians else J_par, J_xy, J_dist)
        if not jacobians:
            continue
        for k in range(2):
            J = J_pin[k]
            pn = fma(J[2], nc[2], fma(J[0], nc[0], J[1] * nc[1]))  # J_pin n_c
            if b != 0.0:  # d X_app / d X = I + b n n^T; d X_app / d n (free, at unit n) = s I + b n X^T
                for j in range(3):
                    J_point[i, k, j] = J[j] + b * pn * nc[j]
                    free[j] = si * J[j] + b * pn * X[i, j]
            else:
                for j in range(3):
                    J_point[i, k, j] = J[j]
                    free[j] = si * J[j]
            for j in range(3):  # then d n / d v
                J_normal[i, k, j] = fma(free[2], dn_dv[2, j], fma(free[1], dn_dv[1, j], free[0] * dn_dv[0, j]))
            J_thickness[i, k] = da_dd * pn
            J_distance[i, k] = da_dh * pn
    return uv, J_point, J_normal, J_params, J_thickness, J_distance


@njit(**_JIT)
def distort_batch(xy, dist):
    """OpenCV distortion of normalised points, with its Jacobians.

    Args:
        xy: undistorted normalised points (N, 2).
        dist: distortion ``[k1, k2, p1, p2, k3]`` (5,).

    Returns:
        xyd (N, 2), J_xy (N, 2, 2) and J_dist (N, 2, 5) (see :func:`distort_point`).
    """
    m = xy.shape[0]
    xyd = np.empty((m, 2))
    J_xy = np.empty((m, 2, 2))
    J_dist = np.empty((m, 2, 5))
    for i in range(m):
        xyd[i, 0], xyd[i, 1] = distort_point(xy[i, 0], xy[i, 1], dist, J_xy[i], J_dist[i])
    return xyd, J_xy, J_dist


@njit(inline="always", **_JIT)
def undistort_point(xd, yd, dist, fx, fy, J_xy, J_dist):
    """Undistorted normalised coordinates of one distorted point, by Newton from (xd, yd).

    Newton stops when the step is below UNDISTORT_TOL_PX px; a final residual above UNDISTORT_FAIL_PX px
    fails the point (NaN). A non-finite input gives NaN without failing.

    Args:
        xd: distorted normalised x.
        yd: distorted normalised y.
        dist: distortion ``[k1, k2, p1, p2, k3]`` (5,).
        fx: focal length in x (px), to measure steps in pixels.
        fy: focal length in y (px).
        J_xy: scratch (2, 2).
        J_dist: scratch (2, 5).

    Returns:
        ``(x, y, failed)``.
    """
    if not (math.isfinite(xd) and math.isfinite(yd)):
        return np.nan, np.nan, False
    x, y = xd, yd
    for _ in range(UNDISTORT_MAX_ITER):
        cx, cy = distort_point(x, y, dist, J_xy, J_dist)
        rx, ry = cx - xd, cy - yd
        det = J_xy[0, 0] * J_xy[1, 1] - J_xy[0, 1] * J_xy[1, 0]
        sx = (J_xy[1, 1] * rx - J_xy[0, 1] * ry) / det
        sy = (J_xy[0, 0] * ry - J_xy[1, 0] * rx) / det
        x -= sx
        y -= sy
        if max(abs(sx) * fx, abs(sy) * fy) <= UNDISTORT_TOL_PX:
            break
        if not (math.isfinite(sx) and math.isfinite(sy)) or max(abs(x), abs(y)) > 1e3:
            break
    cx, cy = distort_point(x, y, dist, J_xy, J_dist)
    if not (max(abs(cx - xd) * fx, abs(cy - yd) * fy) <= UNDISTORT_FAIL_PX):
        return np.nan, np.nan, True
    return x, y, False


@njit(**_JIT)
def undistort_batch(xyd, dist, fx, fy):
    """Undistorted normalised coordinates of distorted ones (see :func:`undistort_point`).

    Args:
        xyd: distorted normalised points (N, 2).
        dist: distortion ``[k1, k2, p1, p2, k3]`` (5,).
        fx: focal length in x (px).
        fy: focal length in y (px).

    Returns:
        Undistorted xy (N, 2), NaN where failed, and the failed mask (N,).
    """
    m = xyd.shape[0]
    xy = np.empty((m, 2))
    failed = np.zeros(m, dtype=np.bool_)
    J_xy = np.empty((2, 2))
    J_dist = np.empty((2, 5))
    for i in range(m):
        xy[i, 0], xy[i, 1], failed[i] = undistort_point(xyd[i, 0], xyd[i, 1], dist, fx, fy, J_xy, J_dist)
    return xy, failed


# --------------------------------------------------------------------------- exact model, forward


@njit(inline="always", **_JIT)
def newton_step(w, rho, L, h, d, n2, m2):
    """One Newton step on ``Psi(w) = w H(w rho) - 1`` (module docstring of :mod:`.exact`).

    Args:
        w: the current w = u / rho.
        rho: radial offset.
        L: medium column length.
        h: near-face distance (mm).
        d: plate thickness (mm).
        n2: squared glass index.
        m2: squared medium index.

    Returns:
        The step ``Psi(w) / Psi'(w)``, to subtract from w.
    """
    u = w * rho
    Gn = 1.0 / math.sqrt(n2 + (n2 - 1.0) * u * u)
    Gm = 1.0 / math.sqrt(m2 + (m2 - 1.0) * u * u)
    psi = w * (h + d * Gn + L * Gm) - 1.0
    dpsi = h + d * n2 * (Gn * Gn * Gn) + L * m2 * (Gm * Gm * Gm)  # = rho'(u) > 0
    return psi / dpsi


@njit(inline="always", **_JIT)
def solve_w(rho, L, h, d, n, n_m, max_iter, w0=0.0):
    """Newton for one point until ``|step| <= NEWTON_REL_TOL |w|``.

    From w = 0 it converges monotonically; from a guess ``w0`` (e.g. the previous solve of a nearby point) it
    falls back to w = 0 if the guess does not converge.

    Args:
        rho: radial offset.
        L: medium column length.
        h: near-face distance (mm).
        d: plate thickness (mm).
        n: glass index.
        n_m: medium index.
        max_iter: cap on the Newton steps of each attempt.
        w0: the start (0: from w = 0 only).

    Returns:
        ``(w, steps)``; steps is NEWTON_NOT_CONVERGED or NEWTON_NOT_FINITE on failure.
    """
    n2, m2 = n * n, n_m * n_m
    w = w0
    for attempt in range(2 if w0 != 0.0 else 1):
        w = w0 if attempt == 0 else 0.0
        for it in range(1, max_iter + 1):
            step = newton_step(w, rho, L, h, d, n2, m2)
            w = w - step
            if not math.isfinite(step):
                break
            if abs(step) <= NEWTON_REL_TOL * abs(w):
                return w, it
    return w, (NEWTON_NOT_FINITE if not math.isfinite(w) else NEWTON_NOT_CONVERGED)


@njit(**_JIT)
def solve_w_lanes(rho, L, h, d, n, n_m, max_iter, w):
    """Newton from w = 0 for many points in lock-step.

    Every point takes the steps of the slowest, which stops when all steps are <= NEWTON_REL_TOL |w| (the
    extra steps of converged points change w by rounding only).

    Args:
        rho: radial offsets (m,) (0 stands in for a point without a ray).
        L: medium column lengths (m,) (1 stands in for a point without a ray).
        h: near-face distance (mm).
        d: plate thickness per point (m,).
        n: glass index.
        n_m: medium index.
        max_iter: cap on the Newton steps.
        w: output (m,), filled with the solved w.

    Returns:
        The steps taken (or NEWTON_NOT_CONVERGED / NEWTON_NOT_FINITE) and the number of failed points.
    """
    m = rho.shape[0]
    n2, m2 = n * n, n_m * n_m
    for i in range(m):
        w[i] = 0.0
    for it in range(1, max_iter + 1):
        worst = 0.0
        for i in range(m):
            step = newton_step(w[i], rho[i], L[i], h, d[i], n2, m2)
            wi = w[i] - step
            w[i] = wi
            worst = max(worst, abs(step) - NEWTON_REL_TOL * abs(wi))
        if worst <= 0.0:
            return it, 0
        if not math.isfinite(worst):
            break
    bad = 0
    not_finite = False
    for i in range(m):
        step = newton_step(w[i], rho[i], L[i], h, d[i], n2, m2)
        if not math.isfinite(step):
            not_finite = True
            bad += 1
        elif abs(step) > NEWTON_REL_TOL * abs(w[i] - step):
            bad += 1
    return (NEWTON_NOT_FINITE if not_finite else NEWTON_NOT_CONVERGED), max(bad, 1)


@njit(**_JIT)
def solve_w_batch(rho, L, h, d, n, n_m, max_iter):
    """w of many points (radial offsets and medium columns), solved in lock-step.

    Args:
        rho: radial offsets (N,).
        L: medium column lengths (N,).
        h: near-face distance (mm).
        d: plate thickness, (1,) for all points or (N,) one per point.
        n: glass index.
        n_m: medium index.
        max_iter: cap on the Newton steps.

    Returns:
        w (N,), the steps taken (or a failure status) and the number of failed points.
    """
    m = rho.shape[0]
    dd = np.empty(m)
    for i in range(m):
        dd[i] = d[0] if d.shape[0] == 1 else d[i]
    w = np.empty(m)
    steps, failures = solve_w_lanes(rho, L, h, dd, n, n_m, max_iter, w)
    return w, steps, failures


@njit(**_JIT)
def _incidence_lanes(X, nc, h, d, n, n_m, max_iter, z, r, L, w):
    """Depth z, radial vector r, medium column L (filled) and w (NaN where L <= 0 or X is not finite)
    of X (m, 3); returns the steps taken (or a failure status) and the failed points."""
    m = X.shape[0]
    rho = np.empty(m)
    Lw = np.empty(m)
    dd = np.empty(m)
    for i in range(m):
        zi = X[i, 0] * nc[0] + X[i, 1] * nc[1] + X[i, 2] * nc[2]
        r0, r1, r2 = X[i, 0] - zi * nc[0], X[i, 1] - zi * nc[1], X[i, 2] - zi * nc[2]
        di = d[0] if d.shape[0] == 1 else d[i]
        Li = zi - h - di
        z[i], L[i], dd[i] = zi, Li, di
        r[i, 0], r[i, 1], r[i, 2] = r0, r1, r2
        if Li > 0.0 and math.isfinite(X[i, 0] + X[i, 1] + X[i, 2]):
            rho[i], Lw[i] = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2), Li
        else:
            rho[i], Lw[i] = 0.0, 1.0  # a stand-in: no ray (w set to NaN below)
    steps, failures = solve_w_lanes(rho, Lw, h, dd, n, n_m, max_iter, w)
    for i in range(m):
        if not (L[i] > 0.0 and math.isfinite(X[i, 0] + X[i, 1] + X[i, 2])):
            w[i] = np.nan
    return steps, failures


@njit(**_JIT)
def incidence_batch(X, nc, h, d, n, n_m, max_iter):
    """Depth, radial vector, medium column and solved w of camera-frame points.

    Args:
        X: camera-frame points (m, 3).
        nc: unit window normal (3,), camera frame.
        h: near-face distance (mm).
        d: plate thickness, (1,) for all points or (m,) one per point.
        n: glass index.
        n_m: medium index.
        max_iter: cap on the Newton steps.

    Returns:
        z (m,), r (m, 3), L (m,) and w (m,) (NaN where L <= 0 or X is not finite), the steps taken (or a
            failure status) and the number of failed points.
    """
    m = X.shape[0]
    z, r, L, w = np.empty(m), np.empty((m, 3)), np.empty(m), np.empty(m)
    steps, failures = _incidence_lanes(X, nc, h, d, n, n_m, max_iter, z, r, L, w)
    return z, r, L, w, steps, failures


@njit(inline="always", **_JIT)
def exact_pixel(X0, X1, X2, z, r0, r1, r2, L, w, params, nc, dn_dv, h, d, n, n_m, n_params, jacobians,
                uv, J_point, J_normal, J_params, J_td, J_pin, J_xy, J_dist, window_jacobians=True):
    """Pixel of one camera-frame point with its solved incidence w, and its Jacobians.

    Args:
        X0: x of the camera-frame point X.
        X1: y of X.
        X2: z of X.
        z: depth n_c . X.
        r0: x of the radial vector r = X - z n_c.
        r1: y of r.
        r2: z of r.
        L: medium column length.
        w: the solved w = u / rho (NaN: no ray).
        params: intrinsics (9,).
        nc: unit window normal (3,), camera frame.
        dn_dv: d n / d v (3, 3) of the free normal vector.
        h: near-face distance (mm).
        d: plate thickness (mm).
        n: glass index.
        n_m: medium index.
        n_params: number of leading ``params`` columns in ``J_params``.
        jacobians: fill the Jacobians.
        uv: output pixel (2,).
        J_point: output (2, 3), d uv / d X.
        J_normal: output (2, 3), d uv / d the free normal vector (via ``dn_dv``).
        J_params: output (2, n_params).
        J_td: output (2, 2), ``[d uv / d thickness, d uv / d distance]``.
        J_pin: scratch (2, 3).
        J_xy: scratch (2, 2).
        J_dist: scratch (2, 5).
        window_jacobians: fill ``J_normal`` and ``J_td`` too (triangulation needs ``J_point`` only).
    """
    pinhole_point(nc[0] + w * r0, nc[1] + w * r1, nc[2] + w * r2, params, n_params, jacobians,
                  uv, J_pin, J_params, J_xy, J_dist)
    if not jacobians:
        return
    # implicit function theorem on the incidence equation (module docstring of .exact)
    u = w * math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    n2, m2 = n * n, n_m * n_m
    Gn = 1.0 / math.sqrt(n2 + (n2 - 1.0) * u * u)
    Gm = 1.0 / math.sqrt(m2 + (m2 - 1.0) * u * u)
    Gn3, Gm3 = Gn * Gn * Gn, Gm * Gm * Gm
    P = h + d * n2 * Gn3 + L * m2 * Gm3  # rho'(u) = dPsi/dw
    K = d * (n2 - 1.0) * Gn3 + L * (m2 - 1.0) * Gm3  # H'(u) = -u K
    w3K = w * w * w * K
    wGm = w * Gm
    for k in range(2):
        Jr = J_pin[k, 0] * r0 + J_pin[k, 1] * r1 + J_pin[k, 2] * r2  # J_pin @ r
        Jn = J_pin[k, 0] * nc[0] + J_pin[k, 1] * nc[1] + J_pin[k, 2] * nc[2]  # J_pin @ n
        # dw/dX = (w^3 K r - w G_m n) / P ;  dw/dn (free n) = (-w^3 K z r - w G_m X) / P  (r . n = 0)
        # dD/dX = w (I - n n^T) + r dw/dX^T ;  dD/dn = (1 - w z) I - w n X^T + r dw/dn^T
        J_point[k, 0] = w * (J_pin[k, 0] - Jn * nc[0]) + Jr * ((w3K * r0 - wGm * nc[0]) / P)
        J_point[k, 1] = w * (J_pin[k, 1] - Jn * nc[1]) + Jr * ((w3K * r1 - wGm * nc[1]) / P)
        J_point[k, 2] = w * (J_pin[k, 2] - Jn * nc[2]) + Jr * ((w3K * r2 - wGm * nc[2]) / P)
        if not window_jacobians:
            continue
        a = 1.0 - w * z
        jn0 = a * J_pin[k, 0] - w * Jn * X0 + Jr * ((-(w3K * z) * r0 - wGm * X0) / P)
        jn1 = a * J_pin[k, 1] - w * Jn * X1 + Jr * ((-(w3K * z) * r1 - wGm * X1) / P)
        jn2 = a * J_pin[k, 2] - w * Jn * X2 + Jr * ((-(w3K * z) * r2 - wGm * X2) / P)
        for j in range(3):
            J_normal[k, j] = jn0 * dn_dv[0, j] + jn1 * dn_dv[1, j] + jn2 * dn_dv[2, j]
        J_td[k, 0] = Jr * (w * (Gm - Gn) / P)
        J_td[k, 1] = Jr * (w * (Gm - 1.0) / P)


@njit(inline="always", **_JIT)
def exact_point(X0, X1, X2, params, nc, dn_dv, h, d, n, n_m, n_params, jacobians,
                uv, J_point, J_normal, J_params, J_td, J_pin, J_xy, J_dist, u0=0.0, window_jacobians=True):
    """:func:`exact_pixel` of one point with its own Newton solve.

    Args:
        X0: x of the camera-frame point.
        X1: y of the point.
        X2: z of the point.
        params: as in :func:`exact_pixel`.
        nc: as in :func:`exact_pixel`.
        dn_dv: as in :func:`exact_pixel`.
        h: as in :func:`exact_pixel`.
        d: as in :func:`exact_pixel`.
        n: as in :func:`exact_pixel`.
        n_m: as in :func:`exact_pixel`.
        n_params: as in :func:`exact_pixel`.
        jacobians: as in :func:`exact_pixel`.
        uv: as in :func:`exact_pixel`.
        J_point: as in :func:`exact_pixel`.
        J_normal: as in :func:`exact_pixel`.
        J_params: as in :func:`exact_pixel`.
        J_td: as in :func:`exact_pixel`.
        J_pin: as in :func:`exact_pixel`.
        J_xy: as in :func:`exact_pixel`.
        J_dist: as in :func:`exact_pixel`.
        u0: the incidence tan t to start Newton from (a nearby point's; see :func:`solve_w`); 0: from w = 0.
        window_jacobians: as in :func:`exact_pixel`.

    Returns:
        The Newton steps (negative: failure; 0: no ray, L <= 0) and the solved tan t.
    """
    z = X0 * nc[0] + X1 * nc[1] + X2 * nc[2]
    r0, r1, r2 = X0 - z * nc[0], X1 - z * nc[1], X2 - z * nc[2]
    L = z - h - d
    steps = 0
    rho = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    if L > 0.0 and math.isfinite(X0 + X1 + X2):
        w, steps = solve_w(rho, L, h, d, n, n_m, NEWTON_MAX_ITER, u0 / rho if rho > 0.0 else 0.0)
    else:
        w = np.nan
    exact_pixel(X0, X1, X2, z, r0, r1, r2, L, w, params, nc, dn_dv, h, d, n, n_m, n_params, jacobians,
                uv, J_point, J_normal, J_params, J_td, J_pin, J_xy, J_dist, window_jacobians)
    return steps, w * rho


@njit(**_JIT)
def exact_batch(X, params, nc, dn_dv, h, d, n, n_m, n_params, jacobians):
    """The exact projection of camera-frame points.

    Args:
        X: camera-frame points (m, 3).
        params: intrinsics (9,).
        nc: unit window normal (3,), camera frame.
        dn_dv: d n / d v (3, 3) of the free normal vector.
        h: near-face distance (mm).
        d: plate thickness, (1,) for all points or (m,) one per point.
        n: glass index.
        n_m: medium index.
        n_params: number of leading ``params`` columns in ``J_params``.
        jacobians: compute the Jacobians.

    Returns:
        uv (m, 2), J_point and J_normal (m, 2, 3), J_params (m, 2, n_params), J_thickness and J_distance
            (m, 2) (empty (0, ...) arrays without ``jacobians``), the Newton steps taken (or a failure
            status) and the number of failed points.
    """
    m = X.shape[0]
    z, r, L, w = np.empty(m), np.empty((m, 3)), np.empty(m), np.empty(m)
    steps, failures = _incidence_lanes(X, nc, h, d, n, n_m, NEWTON_MAX_ITER, z, r, L, w)
    mj = m if jacobians else 1
    uv = np.empty((m, 2))
    J_point = np.empty((mj, 2, 3))
    J_normal = np.empty((mj, 2, 3))
    J_params = np.empty((mj, 2, n_params))
    J_td = np.empty((mj, 2, 2))
    J_pin = np.empty((2, 3))
    J_xy = np.empty((2, 2))
    J_dist = np.empty((2, 5))
    for i in range(m):
        k = i if jacobians else 0
        di = d[0] if d.shape[0] == 1 else d[i]
        exact_pixel(X[i, 0], X[i, 1], X[i, 2], z[i], r[i, 0], r[i, 1], r[i, 2], L[i], w[i], params, nc, dn_dv,
                    h, di, n, n_m, n_params, jacobians, uv[i], J_point[k], J_normal[k], J_params[k], J_td[k],
                    J_pin, J_xy, J_dist)
    if not jacobians:
        J_point, J_normal, J_params, J_td = J_point[:0], J_normal[:0], J_params[:0], J_td[:0]
    return uv, J_point, J_normal, J_params, J_td[:, :, 0].copy(), J_td[:, :, 1].copy(), steps, failures


# --------------------------------------------------------------------------- exact model, backward


@njit(inline="always", **_JIT)
def exact_ray(u, v, params, nc, h, d, n, n_m, J_xy, J_dist, origin, direction):
    """Medium-side ray of one pixel by vector Snell at both faces.

    Args:
        u: pixel column.
        v: pixel row.
        params: intrinsics (9,).
        nc: unit window normal (3,), camera frame.
        h: near-face distance (mm).
        d: plate thickness (mm).
        n: glass index.
        n_m: medium index.
        J_xy: scratch (2, 2).
        J_dist: scratch (2, 5).
        origin: output (3,), the ray's point on the far face.
        direction: output (3,), its unit direction (NaN if the pixel's ray misses the window).

    Returns:
        Whether undistortion failed, and tan t of the camera-side ray (t its incidence).
    """
    xd, yd = (u - params[2]) / params[0], (v - params[3]) / params[1]
    x, y, failed = undistort_point(xd, yd, params[4:], params[0], params[1], J_xy, J_dist)
    return failed, snell_ray(x, y, nc, h, d, n, n_m, origin, direction)


@njit(inline="always", **_JIT)
def snell_ray(x, y, nc, h, d, n, n_m, origin, direction):
    """:func:`exact_ray` from the undistorted normalised coordinates.

    Args:
        x: undistorted normalised x.
        y: undistorted normalised y.
        nc: unit window normal (3,), camera frame.
        h: near-face distance (mm).
        d: plate thickness (mm).
        n: glass index.
        n_m: medium index.
        origin: output (3,), the ray's point on the far face.
        direction: output (3,), its unit direction.

    Returns:
        tan t of the camera-side ray.
    """
    s = 1.0 / math.sqrt(x * x + y * y + 1.0)
    v0, v1, v2 = x * s, y * s, s
    c = v0 * nc[0] + v1 * nc[1] + v2 * nc[2]
    if not c > 0.0:
        c = np.nan
    t = h / c  # hits the near face n_c . X = h
    eta = 1.0 / n
    c_g = math.sqrt(1.0 - eta * eta * (1.0 - c * c)) if c == c else np.nan
    a = c_g - eta * c
    g0, g1, g2 = eta * v0 + a * nc[0], eta * v1 + a * nc[1], eta * v2 + a * nc[2]
    tg = d / c_g  # n_c . v_g = c_g
    origin[0], origin[1], origin[2] = v0 * t + g0 * tg, v1 * t + g1 * tg, v2 * t + g2 * tg
    eta = n / n_m
    arg = 1.0 - eta * eta * (1.0 - c_g * c_g)
    c_m = math.sqrt(arg) if arg >= 0.0 else np.nan
    a = c_m - eta * c_g
    m0, m1, m2 = eta * g0 + a * nc[0], eta * g1 + a * nc[1], eta * g2 + a * nc[2]
    norm = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    direction[0], direction[1], direction[2] = m0 / norm, m1 / norm, m2 / norm
    return math.sqrt(max(1.0 - c * c, 0.0)) / c


@njit(**_JIT)
def exact_rays_batch(uv, params, nc, h, d, n, n_m):
    """Medium-side rays of pixels (see :func:`exact_ray`).

    Args:
        uv: pixels (N, 2).
        params: intrinsics (9,).
        nc: unit window normal (3,), camera frame.
        h: near-face distance (mm).
        d: plate thickness (mm).
        n: glass index.
        n_m: medium index.

    Returns:
        Origins (N, 3), unit directions (N, 3) and the undistortion failures (N,).
    """
    m = uv.shape[0]
    origins = np.empty((m, 3))
    directions = np.empty((m, 3))
    failed = np.zeros(m, dtype=np.bool_)
    J_xy = np.empty((2, 2))
    J_dist = np.empty((2, 5))
    for i in range(m):
        failed[i] = exact_ray(uv[i, 0], uv[i, 1], params, nc, h, d, n, n_m, J_xy, J_dist, origins[i], directions[i])[0]
    return origins, directions, failed


# --------------------------------------------------------------------------- triangulation
# The per-point triangulation calls each piece of physics (exact_ray, exact_point: inline="always") at a
# single site, so numba compiles one copy of it into the loop: no call with a dozen array arguments per
# camera and evaluation, and no more compiled code (nor cold start) than the calls had.


@njit(inline="always", **_JIT)
def _solve_sym3(A, b, x):
    """x = A^-1 b for a symmetric 3x3 A by the adjugate; returns det(A)."""
    a, bb, c = A[0, 0], A[0, 1], A[0, 2]
    d, e, f = A[1, 1], A[1, 2], A[2, 2]
    c00, c01, c02 = d * f - e * e, c * e - bb * f, bb * e - c * d
    c11, c12, c22 = a * f - c * c, bb * c - a * e, a * d - bb * bb
    det = a * c00 + bb * c01 + c * c02
    inv = 1.0 / det
    x[0] = (c00 * b[0] + c01 * b[1] + c02 * b[2]) * inv
    x[1] = (c01 * b[0] + c11 * b[1] + c12 * b[2]) * inv
    x[2] = (c02 * b[0] + c12 * b[1] + c22 * b[2]) * inv
    return det


@njit(inline="always", **_JIT)
def _undistort_lanes(xy, it, active, params, J_xy, J_dist):
    """:func:`undistort_point` of every active camera at once (the same steps, stop and result to the last bit,
    the cameras' independent Newton steps interleaved). ``xy`` (C, 4): per camera [xd, yd, x, y], x and y
    filled (NaN when undistortion fails or the pixel is not finite); ``it`` (C,) int64 scratch; ``active`` (C,)
    the cameras to undistort (cleared); J_xy (C, 2, 2), J_dist (C, 2, 5) scratch. Returns the failures."""
    C = xy.shape[0]
    failures = 0
    for c in range(C):
        it[c] = 0
        xy[c, 2], xy[c, 3] = xy[c, 0], xy[c, 1]
        if active[c] and not (math.isfinite(xy[c, 0]) and math.isfinite(xy[c, 1])):
            active[c] = False
            xy[c, 2], xy[c, 3] = np.nan, np.nan
            it[c] = -1  # not finite: NaN, not a failure
    pending = True
    while pending:
        pending = False
        for c in range(C):
            if not active[c]:
                continue
            dist, fx, fy = params[c, 4:], params[c, 0], params[c, 1]
            Jc = J_xy[c]
            x, y = xy[c, 2], xy[c, 3]
            cx, cy = distort_point(x, y, dist, Jc, J_dist[c])
            rx, ry = cx - xy[c, 0], cy - xy[c, 1]
            det = Jc[0, 0] * Jc[1, 1] - Jc[0, 1] * Jc[1, 0]
            sx = (Jc[1, 1] * rx - Jc[0, 1] * ry) / det
            sy = (Jc[0, 0] * ry - Jc[1, 0] * rx) / det
            x -= sx
            y -= sy
            xy[c, 2], xy[c, 3] = x, y
            it[c] += 1
            if (max(abs(sx) * fx, abs(sy) * fy) <= UNDISTORT_TOL_PX
                    or not (math.isfinite(sx) and math.isfinite(sy)) or max(abs(x), abs(y)) > 1e3
                    or it[c] == UNDISTORT_MAX_ITER):
                active[c] = False
            else:
                pending = True
    for c in range(C):
        if it[c] <= 0:
            continue
        dist, fx, fy = params[c, 4:], params[c, 0], params[c, 1]
        cx, cy = distort_point(xy[c, 2], xy[c, 3], dist, J_xy[c], J_dist[c])
        if not (max(abs(cx - xy[c, 0]) * fx, abs(cy - xy[c, 1]) * fy) <= UNDISTORT_FAIL_PX):
            xy[c, 2], xy[c, 3] = np.nan, np.nan
            failures += 1
            it[c] = -2  # failed
    return failures


@njit(inline="always", **_JIT)
def _solve_w_lanes_of(lanes, state, active, C, max_iter, window):
    """:func:`solve_w` of every active camera at once: each camera's Newton steps, restart and stop exactly as
    solve_w takes them (the same w to the last bit), the cameras' independent steps interleaved (each step is
    a chain of square roots and divisions: one camera's latency hides another's). ``lanes`` (C, 10): per camera
    [X0, X1, X2, z, r0, r1, r2, L, rho, w] with w the start (w0); ``state`` (C, 2) int64 scratch; ``active``
    (C,) the cameras to solve (cleared)."""
    for c in range(C):
        state[c, 0] = 0  # steps taken in this attempt
        state[c, 1] = 1 if lanes[c, 9] != 0.0 else 0  # a restart from w = 0 left (solve_w's second attempt)
    pending = True
    while pending:
        pending = False
        for c in range(C):
            if not active[c]:
                continue
            n, n_m = window[c, 2], window[c, 3]
            step = newton_step(lanes[c, 9], lanes[c, 8], lanes[c, 7], window[c, 0], window[c, 1], n * n, n_m * n_m)
            w = lanes[c, 9] - step
            lanes[c, 9] = w
            state[c, 0] += 1
            if math.isfinite(step) and abs(step) <= NEWTON_REL_TOL * abs(w):
                active[c] = False  # converged
            elif not math.isfinite(step) or state[c, 0] == max_iter:  # this attempt failed
                if state[c, 1] == 1:
                    state[c, 1] = 0
                    state[c, 0] = 0
                    lanes[c, 9] = 0.0
                    pending = True
                else:
                    active[c] = False  # failed: w as solve_w leaves it
            else:
                pending = True


@njit(inline="always", **_JIT)
def _cost_and_normal(Xw, uv, p, ok, R, t, params, nc, window, jacobians, A, g, scratch, u_start, lanes, state,
                     active):
    """Reprojection cost of world point Xw over the cameras ok[c] (pixels uv[p]) and, with ``jacobians``,
    the Gauss-Newton matrix A = J^T J and gradient g = J^T r (world coordinates). Cost inf if a pixel
    is NaN. Each camera's Newton solve starts from u_start[c] (tan t), which gets the solved one; the
    cameras' solves run interleaved (:func:`_solve_w_lanes_of`), then each camera's pixel and Jacobian
    (:func:`exact_pixel`) in camera order: what :func:`exact_point` gives, camera after camera."""
    C = uv.shape[1]
    J_point, J_normal, J_params, J_td, J_pin, J_xy, J_dist, dn_dv, pix = scratch
    for i in range(3):
        g[i] = 0.0
        for j in range(3):
            A[i, j] = 0.0
    for c in range(C):  # exact_point's set-up of each camera's solve
        active[c] = False
        if not ok[c]:
            continue
        X0 = R[c, 0, 0] * Xw[0] + R[c, 0, 1] * Xw[1] + R[c, 0, 2] * Xw[2] + t[c, 0]
        X1 = R[c, 1, 0] * Xw[0] + R[c, 1, 1] * Xw[1] + R[c, 1, 2] * Xw[2] + t[c, 1]
        X2 = R[c, 2, 0] * Xw[0] + R[c, 2, 1] * Xw[1] + R[c, 2, 2] * Xw[2] + t[c, 2]
        z = X0 * nc[c, 0] + X1 * nc[c, 1] + X2 * nc[c, 2]
        r0, r1, r2 = X0 - z * nc[c, 0], X1 - z * nc[c, 1], X2 - z * nc[c, 2]
        L = z - window[c, 0] - window[c, 1]
        rho = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        lanes[c, 0], lanes[c, 1], lanes[c, 2], lanes[c, 3] = X0, X1, X2, z
        lanes[c, 4], lanes[c, 5], lanes[c, 6], lanes[c, 7], lanes[c, 8] = r0, r1, r2, L, rho
        if L > 0.0 and math.isfinite(X0 + X1 + X2):
            lanes[c, 9] = u_start[c] / rho if rho > 0.0 else 0.0
            active[c] = True
        else:
            lanes[c, 9] = np.nan
    _solve_w_lanes_of(lanes, state, active, C, NEWTON_MAX_ITER, window)
    cost = 0.0
    for c in range(C):
        if not ok[c]:
            continue
        w = lanes[c, 9]
        exact_pixel(lanes[c, 0], lanes[c, 1], lanes[c, 2], lanes[c, 3], lanes[c, 4], lanes[c, 5], lanes[c, 6],
                    lanes[c, 7], w, params[c], nc[c], dn_dv, window[c, 0], window[c, 1], window[c, 2], window[c, 3], 4,
                    jacobians, pix, J_point, J_normal, J_params, J_td, J_pin, J_xy, J_dist, False)
        u_solved = w * lanes[c, 8]
        if math.isfinite(u_solved):
            u_start[c] = u_solved
        r0, r1 = pix[0] - uv[p, c, 0], pix[1] - uv[p, c, 1]
        cost += r0 * r0 + r1 * r1
        if not jacobians:
            continue
        for k in range(2):
            rk = r0 if k == 0 else r1
            Jw0 = J_point[k, 0] * R[c, 0, 0] + J_point[k, 1] * R[c, 1, 0] + J_point[k, 2] * R[c, 2, 0]
            Jw1 = J_point[k, 0] * R[c, 0, 1] + J_point[k, 1] * R[c, 1, 1] + J_point[k, 2] * R[c, 2, 1]
            Jw2 = J_point[k, 0] * R[c, 0, 2] + J_point[k, 1] * R[c, 1, 2] + J_point[k, 2] * R[c, 2, 2]
            g[0] += Jw0 * rk
            g[1] += Jw1 * rk
            g[2] += Jw2 * rk
            A[0, 0] += Jw0 * Jw0
            A[0, 1] += Jw0 * Jw1
            A[0, 2] += Jw0 * Jw2
            A[1, 1] += Jw1 * Jw1
            A[1, 2] += Jw1 * Jw2
            A[2, 2] += Jw2 * Jw2
    A[1, 0], A[2, 0], A[2, 1] = A[0, 1], A[0, 2], A[1, 2]
    if not math.isfinite(cost):
        cost = np.inf
    return cost


# C901: a compiled kernel kept in one piece: each piece of physics inlined at one site (the note above
# _solve_sym3) and its scratch arrays allocated once for all points; split, each piece would be a call with a
# dozen array arguments
@njit(**_JIT)
def triangulate_exact(uv, R, t, params, nc, window, refine, max_iterations, damping, step_tol, min_det,  # noqa: C901
                      X_out, gap_out, rmse_out, unconverged, undistort_failed):
    """World points of pixel tracks through the exact model of C cameras.

    Per point: back-projection, the least-squares point of the rays (``ray_gap_mm``), then, with ``refine``,
    Levenberg-Marquardt on the reprojection error with the analytic Jacobians (the algorithm of
    :func:`ari_sfm.reconstruction.triangulate.refine_points`, per point). Points seen by fewer than two
    cameras, or whose rays give no point, are left unwritten in the outputs. Releases the GIL: threads may run
    it on separate slices of points.

    Args:
        uv: pixel tracks (P, C, 2), NaN where a camera does not see the point.
        R: cam_from_world rotations (C, 3, 3).
        t: cam_from_world translations (C, 3).
        params: intrinsics (C, 9).
        nc: unit window normals (C, 3), each in its camera's frame.
        window: ``[h, d, n, n_m]`` per camera (C, 4).
        refine: run Levenberg-Marquardt from the linear point.
        max_iterations: cap on the Levenberg-Marquardt iterations.
        damping: the initial lambda of Marquardt's damping ``lambda diag(J^T J)``.
        step_tol: converged when ``|step| <= step_tol (1 + |X|)``.
        min_det: the smallest determinant of the rays' normal matrix accepted for the linear point.
        X_out: output (P, 3), the world points.
        gap_out: output (P,), the ray gap (mm).
        rmse_out: output (P,), the reprojection RMSE (px) over the cameras that saw the point.
        unconverged: output (P,), set where Levenberg-Marquardt did not converge.
        undistort_failed: output (P,), incremented by the number of the point's pixels whose undistortion
            failed.
    """
    C = uv.shape[1]
    J_xy = np.empty((2, 2))
    J_dist = np.empty((2, 5))
    o = np.empty((C, 3))
    dd = np.empty((C, 3))
    ok = np.zeros(C, dtype=np.bool_)
    seen = np.zeros(C, dtype=np.bool_)
    u_start = np.zeros(C)
    oc = np.empty(3)
    dc = np.empty(3)
    A = np.empty((3, 3))
    b = np.empty(3)
    X = np.empty(3)
    scratch = (np.empty((2, 3)), np.empty((2, 3)), np.empty((2, 9)), np.empty((2, 2)), np.empty((2, 3)),
               J_xy, J_dist, np.zeros((3, 3)), np.empty(2))
    An = np.empty((3, 3))
    g = np.empty(3)
    X_new = np.empty(3)
    step = np.empty(3)
    A_new = np.empty((3, 3))
    g_new = np.empty(3)
    Ad = np.empty((3, 3))
    lanes = np.empty((C, 10))
    state = np.zeros((C, 2), dtype=np.int64)
    active = np.zeros(C, dtype=np.bool_)
    und = np.empty((C, 4))
    und_it = np.zeros(C, dtype=np.int64)
    J_xy_l = np.empty((C, 2, 2))
    J_dist_l = np.empty((C, 2, 5))
    for p in range(uv.shape[0]):
        n_seen = 0
        for c in range(C):
            seen[c] = math.isfinite(uv[p, c, 0]) and math.isfinite(uv[p, c, 1])
            ok[c] = False
            n_seen += seen[c]
        if n_seen < 2:
            continue
        # scene-side rays in the world (X_world = R^T (X_cam - t)); A = sum (I - d d^T), b = sum (I - d d^T) o
        for i in range(3):
            b[i] = 0.0
            for j in range(3):
                A[i, j] = 0.0
        n_ok = 0
        for c in range(C):  # exact_ray of each seen pixel: the undistortions interleaved, then Snell
            active[c] = seen[c]
            if seen[c]:
                und[c, 0], und[c, 1] = ((uv[p, c, 0] - params[c, 2]) / params[c, 0],
                                        (uv[p, c, 1] - params[c, 3]) / params[c, 1])
        undistort_failed[p] += _undistort_lanes(und, und_it, active, params, J_xy_l, J_dist_l)
        for c in range(C):
            if not seen[c]:
                continue
            u_ray = snell_ray(und[c, 2], und[c, 3], nc[c], window[c, 0], window[c, 1], window[c, 2], window[c, 3],
                              oc, dc)
            u_start[c] = u_ray if math.isfinite(u_ray) else 0.0  # the observed pixel's incidence: a close start
            for i in range(3):
                o[c, i] = (R[c, 0, i] * (oc[0] - t[c, 0]) + R[c, 1, i] * (oc[1] - t[c, 1])
                           + R[c, 2, i] * (oc[2] - t[c, 2]))
                dd[c, i] = R[c, 0, i] * dc[0] + R[c, 1, i] * dc[1] + R[c, 2, i] * dc[2]
            norm = math.sqrt(dd[c, 0] ** 2 + dd[c, 1] ** 2 + dd[c, 2] ** 2)
            fin = math.isfinite(norm)
            for i in range(3):
                dd[c, i] /= norm
                fin = fin and math.isfinite(o[c, i]) and math.isfinite(dd[c, i])
            if not fin:
                continue
            ok[c] = True
            n_ok += 1
            do = dd[c, 0] * o[c, 0] + dd[c, 1] * o[c, 1] + dd[c, 2] * o[c, 2]
            for i in range(3):
                A[i, i] += 1.0
                b[i] += o[c, i] - dd[c, i] * do
                for j in range(3):
                    A[i, j] -= dd[c, i] * dd[c, j]
        det = _solve_sym3(A, b, X)
        if n_ok < 2 or not det > min_det:
            continue
        sq = 0.0
        for c in range(C):
            if ok[c]:
                r0, r1, r2 = X[0] - o[c, 0], X[1] - o[c, 1], X[2] - o[c, 2]
                s = r0 * dd[c, 0] + r1 * dd[c, 1] + r2 * dd[c, 2]
                q0, q1, q2 = r0 - s * dd[c, 0], r1 - s * dd[c, 1], r2 - s * dd[c, 2]
                sq += q0 * q0 + q1 * q1 + q2 * q2
        gap_out[p] = 2.0 * math.sqrt(sq / n_ok)
        # Levenberg-Marquardt on the reprojection error, Marquardt damping lam diag(J^T J). One evaluation
        # site: the first evaluates the linear point (its cost, with ``refine`` its normal equations), each
        # later one the step's point X_new, accepted if its cost is not higher.
        for i in range(3):
            X_new[i] = X[i]
        cost = np.inf
        lam = damping
        converged = False
        lm = False  # whether Levenberg-Marquardt runs (refine, and the linear point's cost is finite)
        iterations = 0
        while True:
            cost_new = _cost_and_normal(X_new, uv, p, seen, R, t, params, nc, window, refine, A_new, g_new,
                                        scratch, u_start, lanes, state, active)
            if iterations == 0 or cost_new <= cost:
                if iterations > 0:
                    lam = max(lam / 10.0, 1e-12)
                cost = cost_new
                for i in range(3):
                    X[i] = X_new[i]
                    g[i] = g_new[i]
                    for j in range(3):
                        An[i, j] = A_new[i, j]
            else:
                lam *= 10.0
            if iterations == 0:
                lm = refine and math.isfinite(cost)
                if not lm:
                    break
            elif lam > 1e12:
                converged = True
                break
            if iterations == max_iterations:
                break
            iterations += 1
            for i in range(3):
                for j in range(3):
                    Ad[i, j] = An[i, j]
                Ad[i, i] += lam * max(An[i, i], 1e-12)
            _solve_sym3(Ad, g, step)
            for i in range(3):
                X_new[i] = X[i] - step[i]
            step_norm = math.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2)
            new_norm = math.sqrt(X_new[0] ** 2 + X_new[1] ** 2 + X_new[2] ** 2)
            if step_norm <= step_tol * (1.0 + new_norm):
                # converged: refine_points would also stop after this step. The step is taken without
                # evaluating its point (what is left of the error is second order in the step), its cost
                # the linear model's, |r - J step|^2 (what is left: third order)
                predicted = cost
                for i in range(3):
                    X[i] = X_new[i]
                    predicted -= 2.0 * g[i] * step[i]
                    for j in range(3):
                        predicted += step[i] * An[i, j] * step[j]
                cost = max(predicted, 0.0)
                converged = True
                break
        if lm:
            unconverged[p] = not converged
        X_out[p, 0], X_out[p, 1], X_out[p, 2] = X[0], X[1], X[2]
        if math.isfinite(cost):  # inf: a pixel the point does not reach (NaN projection), no RMSE
            rmse_out[p] = math.sqrt(cost / n_seen)

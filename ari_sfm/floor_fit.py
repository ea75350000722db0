"""The quality gate's floor fit, compiled: each plane's corners mapped to their pixels by a homography
(the normalised DLT) and a smooth polynomial warp in image coordinates, a free map that any camera
behind any flat window is, so that its residuals estimate the detection noise (:mod:`ari_sfm.quality`).

Per plane (numba, ``cache=True``, no LAPACK: its small factorisations written out):

- points normalised (Hartley: centred, RMS radius sqrt(2)); the DLT's homography is the least
  eigenvector of ``A^T A`` (9 x 9, accumulated point by point), found by inverse iteration from e9
  through its Cholesky factor (``A^T A`` shifted by 1e-13 of its trace, so exact points stay
  invertible); each step shrinks the error by the eigenvalue ratio, ~1e-3 even at 10 px of noise:
  that of ``cv2.findHomography(..., 0)`` before its refinement;
- the warp: the least-squares polynomial (terms ``s_x^i s_y^j``, i + j <= degree, of the normalised
  pixels / sqrt(2)) of the homography's residuals, by Cholesky of its normal matrix; a column whose
  pivot is below ``PIVOT`` of its own norm lies in the span of the others (a board of two rows) and
  is left out, which is the least-squares fit of numpy's lstsq on a rank-deficient design.
"""
from __future__ import annotations

import math

import numpy as np

from .kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first

_JIT = dict(cache=True, nogil=True, error_model="numpy")
SHIFT = 1e-13  # of A^T A's trace, added to its diagonal
INVERSE_ITERATIONS = 4
PIVOT = 1e-8  # a warp column's Cholesky pivot below this share of its squared norm: dependent, left out


@njit(**_JIT)
def _normalise(p, v):
    """Centre (2,) and scale of plane v's points p[v] (n, 2): RMS radius sqrt(2) after."""
    n = p.shape[1]
    cx, cy = 0.0, 0.0
    for i in range(n):
        cx += p[v, i, 0]
        cy += p[v, i, 1]
    cx, cy = cx / n, cy / n
    r2 = 0.0
    for i in range(n):
        dx, dy = p[v, i, 0] - cx, p[v, i, 1] - cy
        r2 += dx * dx + dy * dy
    return cx, cy, math.sqrt(2.0) / max(math.sqrt(r2 / n), 1e-12)


@njit(**_JIT)
def _cholesky(G, L, keep, pivot):
    """Lower Cholesky factor of the symmetric G (p, p) into L, leaving out (``keep`` False, zero
    column) each column whose pivot is not above ``pivot`` x its diagonal entry."""
    p = G.shape[0]
    for j in range(p):
        s = G[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        keep[j] = s > pivot * G[j, j] and s > 0.0
        L[j, j] = math.sqrt(s) if keep[j] else 0.0
        for i in range(j + 1, p):
            if keep[j]:
                t = G[i, j]
                for k in range(j):
                    t -= L[i, k] * L[j, k]
                L[i, j] = t / L[j, j]
            else:
                L[i, j] = 0.0
        for i in range(j):
            L[i, j] = 0.0


@njit(**_JIT)
def _cholesky_solve(L, keep, b, x):
    """x = G^-1 b (p,) through the factor (the left-out columns' unknowns 0)."""
    p = L.shape[0]
    for i in range(p):
        t = b[i]
        for k in range(i):
            t -= L[i, k] * x[k]
        x[i] = t / L[i, i] if keep[i] else 0.0
    for i in range(p - 1, -1, -1):
        if not keep[i]:
            x[i] = 0.0
            continue
        t = x[i]
        for k in range(i + 1, p):
            t -= L[k, i] * x[k]
        x[i] = t / L[i, i]


@njit(**_JIT)
def plane_homographies(xy, uv):
    """The DLT homographies (V, 3, 3) of V planes' points ``xy`` to their pixels ``uv`` (each (V, n, 2),
    n >= 4), up to scale; not finite when the points are not."""
    V, n = xy.shape[0], xy.shape[1]
    H = np.empty((V, 3, 3))
    M, L, keep = np.empty((9, 9)), np.empty((9, 9)), np.empty(9, dtype=np.bool_)
    m = M.shape[0]  # 9: the DLT's unknowns
    r1, r2, h, y = np.zeros(9), np.zeros(9), np.empty(9), np.empty(9)
    for v in range(V):
        ax0, ay0, sa = _normalise(xy, v)
        bx0, by0, sb = _normalise(uv, v)
        for a in range(m):
            for b in range(m):
                M[a, b] = 0.0
        for i in range(n):
            ax, ay = (xy[v, i, 0] - ax0) * sa, (xy[v, i, 1] - ay0) * sa
            bx, by = (uv[v, i, 0] - bx0) * sb, (uv[v, i, 1] - by0) * sb
            for k in range(2):  # the DLT's two rows of this point (r1[3:6] and r2[:3] stay 0)
                row, b = (r1, bx) if k == 0 else (r2, by)
                row[3 * k] = ax
                row[3 * k + 1] = ay
                row[3 * k + 2] = 1.0
                row[6] = -b * ax
                row[7] = -b * ay
                row[8] = -b
            for a in range(m):
                for b in range(a + 1):
                    M[a, b] += r1[a] * r1[b] + r2[a] * r2[b]
        trace = 0.0
        for a in range(m):
            trace += M[a, a]
            for b in range(a):
                M[b, a] = M[a, b]
        for a in range(m):
            M[a, a] += SHIFT * trace
        _cholesky(M, L, keep, 0.0)
        for a in range(m):
            h[a] = 1.0 if a == 8 else 0.0
        for _ in range(INVERSE_ITERATIONS + 1):  # the first step from e9
            _cholesky_solve(L, keep, h, y)
            norm = 0.0
            for a in range(m):
                norm += y[a] * y[a]
            norm = math.sqrt(norm)
            for a in range(m):
                h[a] = y[a] / norm
        # H = Tb^-1 h Ta, T = [[s, 0, -s cx], [0, s, -s cy], [0, 0, 1]]
        for r in range(3):
            g0, g1 = h[3 * r] * sa, h[3 * r + 1] * sa
            H[v, r, 0] = g0
            H[v, r, 1] = g1
            H[v, r, 2] = h[3 * r + 2] - g0 * ax0 - g1 * ay0
        for r in range(2):
            c = bx0 if r == 0 else by0
            for k in range(3):
                H[v, r, k] = H[v, r, k] / sb + c * H[v, 2, k]
    return H


@njit(**_JIT)
def warp_residuals(xy, uv, degree):
    """Residuals (V, n, 2) of V planes' corners ``xy`` (target plane) against their pixels ``uv`` (each
    (V, n, 2)) after the homography and the polynomial warp of ``degree`` (module docstring), scaled by
    sqrt(n / (n - p)) for the p parameters fitted per coordinate (the warp's terms and the homography's
    4); and which planes were fitted (V,) (finite points, every corner in front of the homography)."""
    V, n = xy.shape[0], xy.shape[1]
    H = plane_homographies(xy, uv)
    terms = (degree + 1) * (degree + 2) // 2
    scale = math.sqrt(n / (n - terms - 4))
    r = np.zeros((V, n, 2))
    fitted = np.zeros(V, dtype=np.bool_)
    A = np.empty((n, terms))
    G, L, keep = np.empty((terms, terms)), np.empty((terms, terms)), np.empty(terms, dtype=np.bool_)
    rhs, coef = np.empty((2, terms)), np.empty((2, terms))
    px, py = np.empty(degree + 1), np.empty(degree + 1)
    for v in range(V):
        ok = True
        for a in range(3):
            for b in range(3):
                ok = ok and math.isfinite(H[v, a, b])
        bx0, by0, sb = _normalise(uv, v)
        for i in range(n):
            w = xy[v, i, 0] * H[v, 2, 0] + xy[v, i, 1] * H[v, 2, 1] + H[v, 2, 2]
            ok = ok and abs(w) > 1e-12
            for k in range(2):
                r[v, i, k] = uv[v, i, k] - (xy[v, i, 0] * H[v, k, 0] + xy[v, i, 1] * H[v, k, 1] + H[v, k, 2]) / w
            sx, sy = (uv[v, i, 0] - bx0) * sb / math.sqrt(2.0), (uv[v, i, 1] - by0) * sb / math.sqrt(2.0)
            px[0] = 1.0
            py[0] = 1.0
            for d in range(degree):
                px[d + 1] = px[d] * sx
                py[d + 1] = py[d] * sy
            t = 0
            for a in range(degree + 1):
                for b in range(degree + 1 - a):
                    A[i, t] = px[a] * py[b]
                    t += 1
        fitted[v] = ok
        if not ok:
            for i in range(n):
                r[v, i, 0] = 0.0
                r[v, i, 1] = 0.0
            continue
        for a in range(terms):
            for b in range(a + 1):
                s = 0.0
                for i in range(n):
                    s += A[i, a] * A[i, b]
                G[a, b] = s
                G[b, a] = s
            for k in range(2):
                s = 0.0
                for i in range(n):
                    s += A[i, a] * r[v, i, k]
                rhs[k, a] = s
        _cholesky(G, L, keep, PIVOT)
        for k in range(2):
            _cholesky_solve(L, keep, rhs[k], coef[k])
        for i in range(n):
            for k in range(2):
                s = r[v, i, k]
                for a in range(terms):
                    s -= A[i, a] * coef[k, a]
                r[v, i, k] = s * scale
    return r, fitted

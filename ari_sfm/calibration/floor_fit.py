"""The quality gate's floor fit, compiled (:mod:`ari_sfm.calibration.quality`).

Each view's corners are mapped to their pixels by the most flexible free map of the calibration
model's own structure, so that its residuals estimate what the data allow:

- a planar view (a board; one plane of a body): a homography (the normalised DLT of the plane's 2D
  coordinates) and a smooth polynomial warp W of the predicted pixels: any camera behind any flat
  window (and any lens) images a plane so;
- a non-planar view (a 3D body seen once): one free projective camera (the normalised DLT of the 3D
  points, 11 dof, refined by ``CAMERA_STEPS`` Gauss-Newton steps jointly with the rest), W, and a
  non-central term ``zeta (s - e) (a + b |s - e|^2)`` over all the view's points. A camera behind a
  window into water is not central: its rays cross the axis along the window's normal at points that
  move with the incidence angle, so a point's pixel moves, beyond what one centre explains, along the
  line to the normal's vanishing point e, by the inverse depth (zeta, centred, under the camera)
  times a function of the angle. A body's planes are not each given their own map, and the term is
  one radial field scaled by depth, so a placement error between planes stays in the residuals.

Per view (numba, ``cache=True``, no LAPACK: its small factorisations written out), in normalised
coordinates (Hartley: centred, RMS radius sqrt(k) in k dimensions):

- the DLT's map is the least eigenvector of ``A^T A`` (9 x 9 for a plane, 12 x 12 for a body,
  accumulated point by point), found by inverse iteration from the last unit vector through its
  Cholesky factor (``A^T A`` shifted by 1e-13 of its trace, so exact points stay invertible);
- W: the least-squares polynomial (terms ``s_x^i s_y^j``, i + j <= degree, of the predicted pixels /
  sqrt(2)) of the map's residuals, by Cholesky of its normal matrix; a column whose pivot is below
  ``PIVOT`` of its own norm lies in the span of the others (a board of two rows) and is left out,
  which is the least-squares fit of numpy's lstsq on a rank-deficient design. Everything else is
  fitted to the residuals with W projected out;
- the non-central term: its columns for any e are combinations of 12 fixed vectors, so the sum of
  squares is a function of e through their 12 x 12 Gram matrix: e starts from the linear fit
  ``zeta (a s + t)`` (e = -t / a), then damped Newton steps on it;
- the camera's Gauss-Newton step: the prediction's derivatives and the term's columns at e, least
  squares on the residuals; alternating with e, each step kept while the sum of squares falls.
"""
from __future__ import annotations

import math

import numpy as np

from ..kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first

_JIT = dict(cache=True, nogil=True, error_model="numpy")
SHIFT = 1e-13  # of A^T A's trace, added to its diagonal
INVERSE_ITERATIONS = 4
PIVOT = 1e-8  # a warp column's Cholesky pivot below this share of its squared norm: dependent, left out
RADIAL_PARAMETERS = 4  # the non-central term's a, b and centre e
RADIAL_ITERATIONS = 20  # damped Newton steps on the centre e (each a few 12 x 12 products)
RADIAL_BASIS = 12  # (u, v) vectors whose combinations are the non-central term's columns for any centre
RADIAL_VECTORS = 9  # the distinct parts of those vectors (_radial_vectors)
# the part (index into _radial_vectors, -1: zero) of each basis vector in u and in v
BASIS_U = np.array([1, 0, -1, 6, 3, 4, 8, -1, 1, 2, -1, -1])
BASIS_V = np.array([2, -1, 0, 7, 4, 5, -1, 8, -1, -1, 1, 2])
CAMERA_STEPS = 2  # Gauss-Newton steps of the DLT's map, alternating with the centre e (a third: < 1 % of the floor)
MAX_CENTRE = 1e3  # |e| (normalised pixels) beyond which the linear start's centre is not trusted (start at 0)


@njit(**_JIT)
def _normalise(p, v, c):
    """Centre ``c`` (k,) and scale of view v's points p[v] (n, k): RMS radius sqrt(k) after."""
    n, k = p.shape[1], p.shape[2]
    for j in range(k):
        s = 0.0
        for i in range(n):
            s += p[v, i, j]
        c[j] = s / n
    r2 = 0.0
    for i in range(n):
        for j in range(k):
            d = p[v, i, j] - c[j]
            r2 += d * d
    return math.sqrt(k) / max(math.sqrt(r2 / n), 1e-12)


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
def _dlt(src, uv, v, ca, cb, h):
    """View v's normalised DLT: its points' centre ``ca`` (k,) and the pixels' ``cb`` (2,) filled, the map
    of the normalised points to the normalised pixels into ``h`` (3 (k + 1),: rows of P, unit norm);
    returns the two scales (sa, sb)."""
    n, k = src.shape[1], src.shape[2]
    q = k + 1  # homogeneous source coordinates
    m = 3 * q  # the DLT's unknowns
    M, L, keep = np.zeros((m, m)), np.empty((m, m)), np.empty(m, dtype=np.bool_)
    r1, r2, y, a = np.zeros(m), np.zeros(m), np.empty(m), np.empty(q)
    sa = _normalise(src, v, ca)
    sb = _normalise(uv, v, cb)
    for i in range(n):
        for j in range(k):
            a[j] = (src[v, i, j] - ca[j]) * sa
        a[k] = 1.0
        bx, by = (uv[v, i, 0] - cb[0]) * sb, (uv[v, i, 1] - cb[1]) * sb
        for j in range(q):  # the DLT's two rows of this point (r1[q:2q] and r2[:q] stay 0)
            r1[j] = a[j]
            r2[q + j] = a[j]
            r1[2 * q + j] = -bx * a[j]
            r2[2 * q + j] = -by * a[j]
        for j1 in range(m):
            for j2 in range(j1 + 1):
                M[j1, j2] += r1[j1] * r1[j2] + r2[j1] * r2[j2]
    trace = 0.0
    for j1 in range(m):
        trace += M[j1, j1]
        for j2 in range(j1):
            M[j2, j1] = M[j1, j2]
    for j in range(m):
        M[j, j] += SHIFT * trace
    _cholesky(M, L, keep, 0.0)
    for j in range(m):
        h[j] = 1.0 if j == m - 1 else 0.0
    for _ in range(INVERSE_ITERATIONS + 1):  # the first step from the last unit vector
        _cholesky_solve(L, keep, h, y)
        norm = 0.0
        for j in range(m):
            norm += y[j] * y[j]
        norm = math.sqrt(norm)
        for j in range(m):
            h[j] = y[j] / norm
    return sa, sb


@njit(**_JIT)
def projective_maps(src, uv):
    """Fit the normalised DLT map of each view's points to their pixels.

    Args:
        src: V views' points (V, n, k): k = 2, a plane's coordinates, gives homographies; k = 3, a body's,
            projective cameras; n >= 4 (k = 2) or 6 (k = 3).
        uv: their pixels (V, n, 2).

    Returns:
        The maps (V, 3, k + 1), up to scale; not finite when the points are not.
    """
    V, k = src.shape[0], src.shape[2]
    q = k + 1
    P = np.empty((V, 3, q))
    h, ca, cb = np.empty(3 * q), np.empty(k), np.empty(2)
    for v in range(V):
        sa, sb = _dlt(src, uv, v, ca, cb, h)
        # P = Tb^-1 h Ta, Ta = [[sa I, -sa ca], [0, 1]], Tb likewise in 2D
        for r in range(3):
            t = h[q * r + k]
            for j in range(k):
                g = h[q * r + j] * sa
                P[v, r, j] = g
                t -= g * ca[j]
            P[v, r, k] = t
        for r in range(2):
            for j in range(q):
                P[v, r, j] = P[v, r, j] / sb + cb[r] * P[v, 2, j]
    return P


@njit(**_JIT)
def _project_out(A, L, keep, x, out, coef, rhs):
    """out = x minus its least-squares fit by the rows of A (p, n: the columns of the design, stored as
    rows), G = A A^T factored in (L, keep); out may be x."""
    p, n = A.shape
    for a in range(p):
        t = 0.0
        for i in range(n):
            t += A[a, i] * x[i]
        rhs[a] = t
    _cholesky_solve(L, keep, rhs, coef)
    if out is not x:
        for i in range(n):
            out[i] = x[i]
    for a in range(p):
        c = coef[a]
        for i in range(n):
            out[i] -= A[a, i] * c


@njit(**_JIT)
def _solve_small(M, b, x):
    """x = M^-1 b for a small symmetric positive (semi)definite M (Cholesky; a dependent column's unknown 0)."""
    m = M.shape[0]
    L, keep = np.empty((m, m)), np.empty(m, dtype=np.bool_)
    _cholesky(M, L, keep, PIVOT)
    _cholesky_solve(L, keep, b, x)


@njit(**_JIT)
def _radial_vectors(sx, sy, zeta, A, L, keep, D):
    """The non-central term's columns ``zeta (s - e) (a + b |s - e|^2)`` are, for any e, combinations of 12
    fixed (u part, v part) vectors (``_radial_coefficients``) whose parts are 9 distinct vectors (``BASIS_U``,
    ``BASIS_V``): zeta times 1, s_x, s_y, s_x^2, s_x s_y, s_y^2, s_x |s|^2, s_y |s|^2, |s|^2; into D (9, n),
    each projected out of W."""
    n, p = sx.shape[0], A.shape[0]
    coef, rhs = np.empty(p), np.empty(p)
    for i in range(n):
        x, y, z = sx[i], sy[i], zeta[i]
        q = x * x + y * y
        D[0, i], D[1, i], D[2, i] = z, z * x, z * y
        D[3, i], D[4, i], D[5, i] = z * x * x, z * x * y, z * y * y
        D[6, i], D[7, i], D[8, i] = z * x * q, z * y * q, z * q
    for c in range(D.shape[0]):
        _project_out(A, L, keep, D[c], D[c], coef, rhs)


@njit(**_JIT)
def _radial_coefficients(e, alpha, gamma):
    """The basis coefficients (12,) of ``zeta (s - e)`` (alpha) and ``zeta (s - e) |s - e|^2`` (gamma), the
    basis s, (1, 0), (0, 1), s |s|^2, s s_x, s s_y, (|s|^2, 0), (0, |s|^2), (s_x, 0), (s_y, 0), (0, s_x),
    (0, s_y) (each times zeta): (s - e)|s - e|^2 = s|s|^2 - 2 (e.s) s + |e|^2 s - |s|^2 e + 2 (e.s) e - |e|^2 e."""
    ex, ey = e[0], e[1]
    e2 = ex * ex + ey * ey
    for c in range(RADIAL_BASIS):
        alpha[c], gamma[c] = 0.0, 0.0
    alpha[0], alpha[1], alpha[2] = 1.0, -ex, -ey
    gamma[3], gamma[4], gamma[5], gamma[0] = 1.0, -2.0 * ex, -2.0 * ey, e2
    gamma[6], gamma[7] = -ex, -ey
    gamma[8], gamma[9], gamma[10], gamma[11] = 2.0 * ex * ex, 2.0 * ex * ey, 2.0 * ex * ey, 2.0 * ey * ey
    gamma[1], gamma[2] = -e2 * ex, -e2 * ey


@njit(**_JIT)
def _radial_cost(e, gram, g, rr, beta, alpha, gamma):
    """The W-projected residuals' sum of squares (``rr``) less the non-central term's least-squares fit at
    centre e, from the basis' Gram matrix (12, 12) and inner products with the residuals ``g`` (12,); the
    term's (a, b) into beta (alpha, gamma: scratch (12,), left holding e's coefficients)."""
    _radial_coefficients(e, alpha, gamma)
    b0, b1, m00, m01, m11 = 0.0, 0.0, 0.0, 0.0, 0.0
    for c in range(RADIAL_BASIS):
        b0 += alpha[c] * g[c]
        b1 += gamma[c] * g[c]
        ga, gg = 0.0, 0.0
        for d in range(RADIAL_BASIS):
            ga += gram[c, d] * alpha[d]
            gg += gram[c, d] * gamma[d]
        m00 += alpha[c] * ga
        m01 += alpha[c] * gg
        m11 += gamma[c] * gg
    det = m00 * m11 - m01 * m01
    if det > PIVOT * m00 * m11 and m00 > 0.0:
        beta[0], beta[1] = (m11 * b0 - m01 * b1) / det, (m00 * b1 - m01 * b0) / det
    else:  # the two columns dependent (or zero): the first alone
        beta[0], beta[1] = (b0 / m00 if m00 > 0.0 else 0.0), 0.0
    return rr - beta[0] * b0 - beta[1] * b1


@njit(**_JIT)
def _radial_gram(D, ru, rv, gram, g):
    """The non-central basis' Gram matrix into ``gram`` and its inner products with the residuals (ru, rv)
    into ``g``, from those of D's vectors; returns the residuals' sum of squares."""
    n, nd = ru.shape[0], D.shape[0]
    GD, gu, gv = np.empty((nd, nd)), np.zeros(nd), np.zeros(nd)
    rr = 0.0
    for i in range(n):
        rr += ru[i] * ru[i] + rv[i] * rv[i]
    for c in range(nd):
        for i in range(n):
            gu[c] += D[c, i] * ru[i]
            gv[c] += D[c, i] * rv[i]
        for d in range(c + 1):
            t = 0.0
            for i in range(n):
                t += D[c, i] * D[d, i]
            GD[c, d] = t
            GD[d, c] = t
    for c in range(RADIAL_BASIS):  # the basis' Gram matrix and inner products from its parts'
        uc, vc = BASIS_U[c], BASIS_V[c]
        g[c] = (gu[uc] if uc >= 0 else 0.0) + (gv[vc] if vc >= 0 else 0.0)
        for d in range(RADIAL_BASIS):
            ud, vd = BASIS_U[d], BASIS_V[d]
            gram[c, d] = (GD[uc, ud] if uc >= 0 and ud >= 0 else 0.0) + (GD[vc, vd] if vc >= 0 and vd >= 0 else 0.0)
    return rr


@njit(**_JIT)
def _radial_start(gram, g, e):
    """The centre e (2,) from the linear fit ``zeta (a s + t)`` (e = -t / a; zeta s (shared), zeta (u only),
    zeta (v only) are basis vectors 0, 1, 2), else (0, 0)."""
    M, x = np.empty((3, 3)), np.zeros(3)
    for c in range(3):
        for d in range(3):
            M[c, d] = gram[c, d]
    _solve_small(M, g[:3].copy(), x)
    e[0], e[1] = 0.0, 0.0
    if abs(x[0]) > 1e-12 and math.isfinite(x[0]):
        e[0], e[1] = -x[1] / x[0], -x[2] / x[0]
        if not (math.isfinite(e[0]) and math.isfinite(e[1])) or abs(e[0]) + abs(e[1]) > MAX_CENTRE:
            e[0], e[1] = 0.0, 0.0


@njit(**_JIT)
def _radial_fit(D, ru, rv, out, e, start, beta):
    """The non-central term's fit (module docstring) of the W-projected residuals (ru, rv) over the projected
    vectors ``D`` (``_radial_vectors``): residuals into out (2, n), its centre e (2,) refined in place, its
    (a, b) into beta; returns the sum of squares. e starts (``start``) from the linear fit ``zeta (a s + t)``
    (e = -t / a), else from e; then damped Newton steps on the sum of squares (a function of e alone: the
    rest is linear, through the basis' 12 x 12 Gram matrix), its derivatives by central differences."""
    n = ru.shape[0]
    gram, g = np.empty((RADIAL_BASIS, RADIAL_BASIS)), np.empty(RADIAL_BASIS)
    alpha, gamma = np.empty(RADIAL_BASIS), np.empty(RADIAL_BASIS)
    nd = D.shape[0]
    rr = _radial_gram(D, ru, rv, gram, g)
    if start:
        _radial_start(gram, g, e)
    cost = _radial_cost(e, gram, g, rr, beta, alpha, gamma)
    trial, probe = np.empty(2), np.empty(2)
    f, H, Hd, grad = np.empty((3, 3)), np.empty((2, 2)), np.empty((2, 2)), np.empty(2)
    damping = 1e-3
    for _ in range(RADIAL_ITERATIONS):
        step = 1e-4 * (1.0 + abs(e[0]) + abs(e[1]))  # f: the cost at e + (i - 1, j - 1) step
        for i in range(3):
            for j in range(3):
                probe[0], probe[1] = e[0] + (i - 1) * step, e[1] + (j - 1) * step
                f[i, j] = _radial_cost(probe, gram, g, rr, beta, alpha, gamma) if (i, j) != (1, 1) else cost
        grad[0], grad[1] = (f[2, 1] - f[0, 1]) / (2 * step), (f[1, 2] - f[1, 0]) / (2 * step)
        H[0, 0] = (f[2, 1] - 2.0 * cost + f[0, 1]) / (step * step)
        H[1, 1] = (f[1, 2] - 2.0 * cost + f[1, 0]) / (step * step)
        H[0, 1] = (f[2, 2] - f[2, 0] - f[0, 2] + f[0, 0]) / (4.0 * step * step)
        H[1, 0] = H[0, 1]
        accepted = False
        while damping < 1e8:
            Hd[:, :] = H
            scale = abs(H[0, 0]) + abs(H[1, 1]) + 1e-300
            Hd[0, 0] += damping * scale
            Hd[1, 1] += damping * scale
            det = Hd[0, 0] * Hd[1, 1] - Hd[0, 1] * Hd[1, 0]
            if det > 0.0 and Hd[0, 0] > 0.0:
                trial[0] = e[0] - (Hd[1, 1] * grad[0] - Hd[0, 1] * grad[1]) / det
                trial[1] = e[1] - (Hd[0, 0] * grad[1] - Hd[1, 0] * grad[0]) / det
                c = _radial_cost(trial, gram, g, rr, beta, alpha, gamma)
                if c < cost:
                    accepted = True
                    break
            damping *= 10.0
        if not accepted:
            break
        damping = max(damping / 100.0, 1e-6)
        moved = abs(trial[0] - e[0]) + abs(trial[1] - e[1])
        e[0], e[1] = trial[0], trial[1]
        relative = (cost - c) / max(cost, 1e-300)
        cost = c
        if moved < 1e-10 or relative < 1e-10:
            break
    cost = _radial_cost(e, gram, g, rr, beta, alpha, gamma)
    wu, wv = np.zeros(nd), np.zeros(nd)
    _radial_parts(beta[0], beta[1], alpha, gamma, wu, wv)
    for i in range(n):
        out[0, i], out[1, i] = ru[i], rv[i]
    for c in range(nd):
        for i in range(n):
            out[0, i] -= wu[c] * D[c, i]
            out[1, i] -= wv[c] * D[c, i]
    return cost


@njit(**_JIT)
def _radial_parts(x, y, alpha, gamma, wu, wv):
    """The weights (9,) of D's vectors in the u and v parts of ``x alpha + y gamma`` (basis coefficients)."""
    for c in range(wu.shape[0]):
        wu[c], wv[c] = 0.0, 0.0
    for c in range(RADIAL_BASIS):
        w = x * alpha[c] + y * gamma[c]
        if BASIS_U[c] >= 0:
            wu[BASIS_U[c]] += w
        if BASIS_V[c] >= 0:
            wv[BASIS_V[c]] += w


@njit(**_JIT)
def _fit_view(a, b, h, degree, radial, e, start, out, cols):
    """One view's free map at its current map ``h`` (normalised DLT coordinates: points ``a`` (n, k + 1),
    homogeneous; pixels ``b`` (n, 2)): the residuals (2, n) after W at the predicted pixels and (``radial``)
    the non-central term (centre ``e`` refined, from the linear start if ``start``) into ``out``; with
    ``cols`` (3 (k + 1) + 2, 2, n; else (0, 2, n)) also one Gauss-Newton step of h in place
    (``_gauss_newton_step``), jointly with W's and the non-central term's coefficients at that e (e is refined
    by the next call: alternating).
    Returns False when a point is not in front of the map (its prediction not finite)."""
    n = a.shape[0]
    terms = (degree + 1) * (degree + 2) // 2
    pu, pv, w = np.empty(n), np.empty(n), np.empty(n)
    sx, sy, zeta, ru, rv = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    in_front, mean_inverse = _predict(a, b, h, w, pu, pv, ru, rv, zeta)
    if not in_front:
        return False
    spread = 0.0  # zeta: the inverse depth centred, scaled to RMS 1 (0 when it does not vary)
    for i in range(n):
        zeta[i] = zeta[i] / mean_inverse - 1.0
        spread += zeta[i] * zeta[i] / n
    spread = math.sqrt(spread)
    radial = radial and spread > 1e-12
    A = np.empty((terms, n))  # W's design, a row per term
    _warp_design(pu, pv, zeta, spread, degree, sx, sy, A)
    G, L, keep = np.empty((terms, terms)), np.empty((terms, terms)), np.empty(terms, dtype=np.bool_)
    coef, rhs = np.empty(terms), np.empty(terms)
    for c in range(terms):
        for d in range(c + 1):
            t = 0.0
            for i in range(n):
                t += A[c, i] * A[d, i]
            G[c, d] = t
            G[d, c] = t
    _cholesky(G, L, keep, PIVOT)
    _project_out(A, L, keep, ru, ru, coef, rhs)
    _project_out(A, L, keep, rv, rv, coef, rhs)
    beta = np.zeros(2)  # (a, b) of the non-central term
    D = np.empty((RADIAL_VECTORS if radial else 0, n))
    if radial:
        _radial_vectors(sx, sy, zeta, A, L, keep, D)
        _radial_fit(D, ru, rv, out, e, start, beta)
    else:
        for i in range(n):
            out[0, i], out[1, i] = ru[i], rv[i]
    if cols.shape[0] > 0:
        _gauss_newton_step(a, h, w, pu, pv, ru, rv, A, L, keep, coef, rhs, D, e, radial, cols)
    return True


@njit(**_JIT)
def _predict(a, b, h, w, pu, pv, ru, rv, zeta):
    """The map ``h``'s prediction of the points ``a`` (n, q) against their pixels ``b``: into w the third
    coordinate, (pu, pv) the pixels, (ru, rv) the residuals, zeta the inverse depth 1 / w. Returns whether
    every point is in front of the map (its prediction finite) and zeta's mean (so far)."""
    n, q = a.shape[0], a.shape[1]
    mean_inverse = 0.0
    for i in range(n):
        t0, t1, t2 = 0.0, 0.0, 0.0
        for j in range(q):
            t0 += h[j] * a[i, j]
            t1 += h[q + j] * a[i, j]
            t2 += h[2 * q + j] * a[i, j]
        if not (abs(t2) > 1e-12 and math.isfinite(t0) and math.isfinite(t1) and math.isfinite(t2)):
            return False, mean_inverse
        w[i], pu[i], pv[i] = t2, t0 / t2, t1 / t2
        ru[i], rv[i] = b[i, 0] - pu[i], b[i, 1] - pv[i]
        zeta[i] = 1.0 / t2
        mean_inverse += zeta[i] / n
    return True, mean_inverse


@njit(**_JIT)
def _warp_design(pu, pv, zeta, spread, degree, sx, sy, A):
    """W's design A (terms, n) at the predicted pixels (pu, pv) (scaled into sx, sy), and zeta (centred)
    scaled by its RMS ``spread`` in place (0 when it does not vary)."""
    px, py = np.empty(degree + 1), np.empty(degree + 1)
    for i in range(pu.shape[0]):
        zeta[i] = zeta[i] / spread if spread > 1e-12 else 0.0
        sx[i], sy[i] = pu[i] / math.sqrt(2.0), pv[i] / math.sqrt(2.0)  # W at the predicted pixels
        px[0] = 1.0
        py[0] = 1.0
        for d in range(degree):
            px[d + 1] = px[d] * sx[i]
            py[d + 1] = py[d] * sy[i]
        t = 0
        for c in range(degree + 1):
            for d in range(degree + 1 - c):
                A[t, i] = px[c] * py[d]
                t += 1


@njit(**_JIT)
def _gauss_newton_step(a, h, w, pu, pv, ru, rv, A, L, keep, coef, rhs, D, e, radial, cols):
    """One Gauss-Newton step of the map ``h`` in place (``_fit_view``): the prediction's derivatives (u, v
    parts) projected out of W (its design A, factor L, kept columns), and (``radial``) the non-central
    term's columns at e over its vectors D (already projected), then their least squares on the W-projected
    residuals (ru, rv)."""
    n, q = a.shape[0], a.shape[1]
    m = 3 * q
    E = np.empty((3 * q, n))  # the derivatives' distinct parts: a_j / w, -pu a_j / w, -pv a_j / w
    for j in range(q):
        for i in range(n):
            E[j, i] = a[i, j] / w[i]
            E[q + j, i] = -pu[i] * E[j, i]
            E[2 * q + j, i] = -pv[i] * E[j, i]
    for c in range(3 * q):
        _project_out(A, L, keep, E[c], E[c], coef, rhs)
    for j in range(q):
        for i in range(n):
            cols[j, 0, i], cols[j, 1, i] = E[j, i], 0.0  # d (pu, pv) / d h[j]
            cols[q + j, 0, i], cols[q + j, 1, i] = 0.0, E[j, i]  # ... / d h[q + j]
            cols[2 * q + j, 0, i], cols[2 * q + j, 1, i] = E[q + j, i], E[2 * q + j, i]  # ... / d h[2 q + j]
    if radial:
        alpha, gamma = np.empty(RADIAL_BASIS), np.empty(RADIAL_BASIS)
        wu, wv = np.empty(RADIAL_VECTORS), np.empty(RADIAL_VECTORS)
        _radial_coefficients(e, alpha, gamma)
        for col, (x, y) in ((m, (1.0, 0.0)), (m + 1, (0.0, 1.0))):
            _radial_parts(x, y, alpha, gamma, wu, wv)
            for i in range(n):
                cols[col, 0, i], cols[col, 1, i] = 0.0, 0.0
            for c in range(RADIAL_VECTORS):
                for i in range(n):
                    cols[col, 0, i] += wu[c] * D[c, i]
                    cols[col, 1, i] += wv[c] * D[c, i]
    p = cols.shape[0] if radial else m
    M, g, x = np.zeros((p, p)), np.zeros(p), np.zeros(p)
    for c in range(p):
        for i in range(n):
            g[c] += cols[c, 0, i] * ru[i] + cols[c, 1, i] * rv[i]
        for d in range(c + 1):
            t = 0.0
            for i in range(n):
                t += cols[c, 0, i] * cols[d, 0, i] + cols[c, 1, i] * cols[d, 1, i]
            M[c, d] = t
            M[d, c] = t
    _solve_small(M, g, x)
    for j in range(m):
        h[j] += x[j]


@njit(**_JIT)
def warp_residuals(src, uv, degree, radial):
    """Fit each view's free map (module docstring) and give the residuals.

    The DLT's map is refined by ``CAMERA_STEPS`` Gauss-Newton steps (a body) jointly with the warp W at
    the predicted pixels and (a body, ``radial``) the non-central term. The residuals are scaled by
    sqrt(2n / (2n - 2p - d)) for the p terms of W per coordinate, the d dof of the map (8 a homography,
    11 a camera) and the non-central term's 4.

    Args:
        src: V views' points (V, n, k): k = 2 a plane, k = 3 a body.
        uv: their pixels (V, n, 2).
        degree: the degree of the polynomial warp W.
        radial: fit the non-central term (bodies only).

    Returns:
        The residuals (V, n, 2) in px, and which views were fitted (V,) bool (finite points, every point in
        front of the map); an unfitted view's residuals are 0.
    """
    V, n, k = src.shape[0], src.shape[1], src.shape[2]
    q = k + 1
    radial = radial and k == 3
    terms = (degree + 1) * (degree + 2) // 2
    scale = math.sqrt(2.0 * n / (2.0 * n - 2.0 * terms - (3 * q - 1) - (RADIAL_PARAMETERS if radial else 0)))
    r = np.zeros((V, n, 2))
    fitted = np.zeros(V, dtype=np.bool_)
    h, ca, cb, e = np.empty(3 * q), np.empty(k), np.empty(2), np.zeros(2)
    a, b, out, best = np.empty((n, q)), np.empty((n, 2)), np.empty((2, n)), np.empty((2, n))
    steps = CAMERA_STEPS if k == 3 else 0  # a plane's homography is a function of the pixels: W holds it
    cols = np.empty((3 * q + (2 if radial else 0), 2, n))
    none = np.empty((0, 2, n))
    for v in range(V):
        sa, sb = _dlt(src, uv, v, ca, cb, h)
        ok = math.isfinite(sa) and math.isfinite(sb)
        e[0], e[1] = 0.0, 0.0
        for j in range(3 * q):
            ok = ok and math.isfinite(h[j])
        for i in range(n):
            for j in range(k):
                a[i, j] = (src[v, i, j] - ca[j]) * sa
            a[i, k] = 1.0
            b[i, 0], b[i, 1] = (uv[v, i, 0] - cb[0]) * sb, (uv[v, i, 1] - cb[1]) * sb
        lowest = math.inf  # each step kept while the residuals' sum of squares falls
        for step in range(steps + 1):
            if not ok or not _fit_view(a, b, h, degree, radial, e, step == 0, out, cols if step < steps else none):
                break
            cost = 0.0
            for i in range(n):
                cost += out[0, i] * out[0, i] + out[1, i] * out[1, i]
            if not cost < lowest:
                break
            lowest = cost
            for i in range(n):
                best[0, i], best[1, i] = out[0, i], out[1, i]
        fitted[v] = ok and math.isfinite(lowest)
        if fitted[v]:
            for i in range(n):
                r[v, i, 0] = best[0, i] / sb * scale  # normalised pixels -> pixels
                r[v, i, 1] = best[1, i] / sb * scale
    return r, fitted

"""Normal equations with the 3D points eliminated (Schur complement).

For residuals r (M, 2) with Jacobians J_g (reduced variables, scattered by an index) and J_p (one
3D point per observation), the damped normal equations

    [H_gg  W ] [dg]     [g_g]
    [W^T   V ] [dp] = - [g_p]

have V block-diagonal (3 x 3 per point): ``(H_gg - W V^-1 W^T) dg = -g_g + W V^-1 g_p`` is solved
densely (its size is the number of camera, pose and window parameters), then
``dp = -V^-1 (g_p + W^T dg)`` point by point. W is never formed: each observation keeps its
block ``B_o = J_g,o^T J_p,o`` (q x 3) and its columns, so memory is linear in the observations
(plus the dense reduced matrix).

The reduced system is built once per linearization (:func:`reduce_points`): with
``V_p^-1 = L_p L_p^T`` (a 3 x 3 Cholesky per point), ``W V^-1 W^T = Y Y^T`` where Y's column
block of point p is the sum of its observations' ``B_o L_p``, scattered to their rows; Y is
filled densely for a chunk of points at a time and each chunk adds one BLAS ``Y^T Y`` product.

Robust loss: Huber on each observation's pixel distance, by iteratively reweighted least squares
(weights ``min(1, k / |r|)``). Damping: Marquardt's, ``lambda * diag`` (floored). The point blocks
are damped with the lambda of the linearization's first trial (``V_p + lambda_0 diag V_p``, in the
reduced system built then); every trial damps the reduced system with its own lambda
(``S + lambda diag H_gg``). The first trial (the one LM usually accepts) is therefore the exact
Marquardt step of the whole system; a later trial keeps the points' damping at lambda_0 while the
camera block's grows, which still shrinks the camera step toward gradient descent and, with the
points eliminated exactly for it, is the Marquardt step of the points-eliminated problem. LM
judges every trial by the decrease the *whole undamped* model predicts for the joint step
(:func:`model_decrease`), so acceptance is unchanged.

The Levenberg-Marquardt loop is the rig backend's (:mod:`ari_sfm.factors.levenberg_marquardt`):
:class:`ari_sfm.colmap_refine.refine.Solver` gives it these systems, :func:`solve_damped` and
:func:`model_decrease`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from .problem import Linearization

log = logging.getLogger(__name__)

DIAG_FLOOR = 1e-9


def huber_weights(residuals: np.ndarray, huber_px: float | None) -> np.ndarray:
    """IRLS weights (M,) of the Huber loss on each observation's pixel distance (1 without a loss)."""
    if huber_px is None:
        return np.ones(len(residuals))
    s = np.linalg.norm(residuals, axis=1)
    return np.where(s <= huber_px, 1.0, huber_px / np.maximum(s, 1e-300))


def huber_cost(residuals: np.ndarray, huber_px: float | None) -> float:
    """Sum over observations of rho(|r|): |r|^2 / 2 inside the threshold, k |r| - k^2 / 2 outside."""
    s = np.linalg.norm(residuals, axis=1)
    if not np.all(np.isfinite(s)):
        return float("inf")
    if huber_px is None:
        return float(0.5 * np.sum(s * s))
    return float(np.sum(np.where(s <= huber_px, 0.5 * s * s, huber_px * s - 0.5 * huber_px ** 2)))


@dataclass
class NormalEquations:
    """The system's pieces at one linearization (undamped; the reduced system cached per point damping)."""

    H: np.ndarray  # (G, G)
    g: np.ndarray  # (G,)
    V: np.ndarray  # (P, 3, 3)
    gp: np.ndarray  # (P, 3)
    B: np.ndarray  # (M, q, 3) per observation J_g^T J_p (weighted)
    index: np.ndarray  # (M, q) its reduced columns, G where none
    obs_point: np.ndarray  # (M,)
    error: float = 0.0  # the robust cost at the linearization point (LM's system.error)
    reduced: Any = None  # ReducedSystem, built by the first solve_damped
    damping: Any = None  # (G,) the diagonal Marquardt's damping scales (default diag H): the images' part only,
    #                      so that a stiff prior term (a scale bar) does not freeze its variables' other directions

    def W_times(self, dp: np.ndarray) -> np.ndarray:
        """W dp (G,) for point steps dp (P, 3)."""
        v = np.einsum("nij,nj->ni", self.B, dp[self.obs_point])
        return np.bincount(self.index.ravel(), v.ravel(), len(self.g) + 1)[:len(self.g)]

    def Wt_times(self, dg: np.ndarray) -> np.ndarray:
        """W^T dg (P, 3) for a reduced step dg (G,)."""
        v = np.einsum("nij,ni->nj", self.B, np.append(dg, 0.0)[self.index])
        P = len(self.gp)
        return np.stack([np.bincount(self.obs_point, v[:, j], P) for j in range(3)], axis=1)


@dataclass(frozen=True)
class ReducedSystem:
    """``S = H - W V_0^-1 W^T`` and ``b = -g + W V_0^-1 g_p`` with the points damped by lambda_0."""

    S: np.ndarray
    b: np.ndarray
    Vinv: np.ndarray  # (P, 3, 3) (V + lambda_0 diag V)^-1
    lam_points: float


def model_decrease(ne: NormalEquations, step: tuple[np.ndarray, np.ndarray]) -> float:
    """-(g . step + 0.5 step^T H step) of the whole (undamped) system, points included: the cost
    decrease the linearization predicts for ``step`` = (dg, dp)."""
    dg, dp = step
    quadratic = dg @ ne.H @ dg + 2.0 * dg @ ne.W_times(dp) + np.einsum("pi,pij,pj->", dp, ne.V, dp)
    return float(-(ne.g @ dg + np.sum(ne.gp * dp) + 0.5 * quadratic))


def build_normal_equations(lin: Linearization, obs_point: np.ndarray, num_points: int, size: int,
                           weights: np.ndarray) -> NormalEquations:
    """Weighted normal equations of a linearization (the point blocks kept separate)."""
    sw = np.sqrt(weights)[:, None, None]
    Jg, Jp = lin.J_g * sw, lin.J_p * sw
    r = lin.residuals * sw[:, :, 0]
    idx = np.where(lin.index >= 0, lin.index, size)  # a dummy column `size`, dropped
    G1 = size + 1
    q = idx.shape[1]
    H = np.zeros((G1, G1))
    # observations with the same columns (an image's, in practice) add one dense block J^T J
    keys, group = _unique_rows(idx)
    order = np.argsort(group, kind="stable")
    starts = np.searchsorted(group[order], np.arange(len(keys) + 1))
    for k, cols in enumerate(keys):
        J = Jg[order[starts[k]:starts[k + 1]]].reshape(-1, q)
        H[np.ix_(cols, cols)] += J.T @ J  # a row's real columns are distinct (the dummy's value is dropped)
    g = np.bincount(idx.ravel(), np.einsum("nki,nk->ni", Jg, r).ravel(), G1)[:size]
    V = np.stack([np.bincount(obs_point, v, num_points) for v in
                  np.einsum("nki,nkj->nij", Jp, Jp).reshape(-1, 9).T], axis=1).reshape(-1, 3, 3)
    gp = np.stack([np.bincount(obs_point, v, num_points) for v in np.einsum("nki,nk->ni", Jp, r).T], axis=1)
    B = np.matmul(np.swapaxes(Jg, 1, 2), Jp)
    return NormalEquations(H[:size, :size].copy(), g, V, gp, B, idx, obs_point)


def _unique_rows(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of an int array (M, q) and each row's group: by a 64-bit hash of the row,
    checked (np.unique over rows, ~10x slower, if two rows share a hash)."""
    weights = np.random.default_rng(0).integers(1, 2 ** 62, idx.shape[1], dtype=np.int64)
    with np.errstate(over="ignore"):
        h = idx.astype(np.int64) @ weights
    _, first, group = np.unique(h, return_index=True, return_inverse=True)
    keys = idx[first]
    if not np.array_equal(keys[group.ravel()], idx):
        keys, group = np.unique(idx, axis=0, return_inverse=True)
    return keys, group.ravel()


Y_CHUNK_ENTRIES = 2_000_000  # floats of one dense chunk of Y (3 columns per point, G + 1 rows)


def reduce_points(ne: NormalEquations, lam_points: float) -> ReducedSystem:
    """The reduced system with the point blocks damped by ``lam_points * diag`` (module docstring)."""
    G, P = len(ne.g), len(ne.gp)
    dV = np.maximum(np.diagonal(ne.V, axis1=1, axis2=2), DIAG_FLOOR)
    Vd = ne.V + lam_points * dV[:, :, None] * np.eye(3)
    Vd[np.trace(ne.V, axis1=1, axis2=2) == 0.0] = np.eye(3)  # points moved into the reduced variables
    Vinv = np.linalg.inv(Vd)
    Vinv = 0.5 * (Vinv + np.swapaxes(Vinv, 1, 2))
    L = np.linalg.cholesky(Vinv)
    Z = np.matmul(ne.B, L[ne.obs_point])  # (M, q, 3)
    order = np.argsort(ne.obs_point, kind="stable")
    starts = np.searchsorted(ne.obs_point[order], np.arange(P + 1))
    G1 = G + 1
    per = max(1, Y_CHUNK_ENTRIES // (3 * G1))
    S = ne.H.copy()
    for p0 in range(0, P, per):
        p1 = min(P, p0 + per)
        obs = order[starts[p0]:starts[p1]]
        col = 3 * (ne.obs_point[obs] - p0)[:, None, None] + np.arange(3)  # (m, 1, 3)
        flat = (col * G1 + ne.index[obs][:, :, None]).ravel()  # Y^T stored (3n, G + 1), row-major
        Yt = np.bincount(flat, Z[obs].ravel(), 3 * (p1 - p0) * G1).reshape(3 * (p1 - p0), G1)[:, :G]
        S -= Yt.T @ Yt
    u = np.einsum("pij,pj->pi", Vinv, ne.gp)
    b = -ne.g + ne.W_times(u)
    return ReducedSystem(S, b, Vinv, lam_points)


def solve_damped(ne: NormalEquations, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Reduced step dg (G,) and point steps dp (P, 3) of the system damped by ``lam * diag`` (the
    points by the first trial's lambda: module docstring)."""
    if ne.reduced is None:
        ne.reduced = reduce_points(ne, lam)
    red = ne.reduced
    dH = np.maximum(np.diag(ne.H) if ne.damping is None else ne.damping, DIAG_FLOOR)
    S = red.S + np.diag(lam * dH)
    try:
        dg = cho_solve(cho_factor(S), red.b)
    except (np.linalg.LinAlgError, ValueError):
        if not np.all(np.isfinite(S)):
            return None
        dg = np.linalg.lstsq(S, red.b, rcond=None)[0]
    dp = -np.einsum("pij,pj->pi", red.Vinv, ne.gp + ne.Wt_times(dg))
    return dg, dp

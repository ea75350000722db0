"""Normal equations with the 3D points eliminated (Schur complement).

For residuals r (M, 2) with Jacobians J_g (reduced variables, scattered by an index) and J_p (one
3D point per observation), the damped normal equations

    [H_gg  W ] [dg]     [g_g]
    [W^T   V ] [dp] = - [g_p]

have V block-diagonal (3 x 3 per point): ``(H_gg - W V^-1 W^T) dg = -g_g + W V^-1 g_p`` is solved
densely (its size is the number of camera, pose and window parameters), then
``dp = -V^-1 (g_p + W^T dg)`` point by point. W is held sparse, so memory is linear in the
observations (plus the dense reduced matrix).

Robust loss: Huber on each observation's pixel distance, by iteratively reweighted least squares
(weights ``min(1, k / |r|)``). Damping: Marquardt's, ``lambda * diag`` (floored) on both blocks.

The Levenberg-Marquardt loop is the rig backend's (:mod:`ari_sfm.factors.levenberg_marquardt`):
:class:`ari_sfm.colmap_refine.refine.Solver` gives it these systems, :func:`solve_damped` and
:func:`model_decrease`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import sparse
from scipy.linalg import cho_factor, cho_solve

from .problem import Linearization

log = logging.getLogger(__name__)

PAIR_CHUNK_ENTRIES = 4_000_000  # floats per chunk of observation-pair products
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
    """The damped system's pieces at one linearization (undamped diagonals kept for lambda)."""

    H: np.ndarray  # (G, G)
    g: np.ndarray  # (G,)
    V: np.ndarray  # (P, 3, 3)
    gp: np.ndarray  # (P, 3)
    W: Any  # (G + 1, 3P) sparse: sum over observations of J_g^T J_p (row G: unused columns)
    error: float = 0.0  # the robust cost at the linearization point (LM's system.error)


def model_decrease(ne: NormalEquations, step: tuple[np.ndarray, np.ndarray]) -> float:
    """-(g . step + 0.5 step^T H step) of the whole (undamped) system, points included: the cost
    decrease the linearization predicts for ``step`` = (dg, dp)."""
    dg, dp = step
    Wdp = (ne.W @ dp.ravel())[:len(ne.g)]
    quadratic = dg @ ne.H @ dg + 2.0 * dg @ Wdp + np.einsum("pi,pij,pj->", dp, ne.V, dp)
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
    H = np.zeros(G1 * G1)
    chunk = max(1, PAIR_CHUNK_ENTRIES // (q * q))
    for s in range(0, len(r), chunk):
        blk = np.matmul(np.swapaxes(Jg[s:s + chunk], 1, 2), Jg[s:s + chunk])
        flat = (idx[s:s + chunk, :, None] * G1 + idx[s:s + chunk, None, :]).ravel()
        H += np.bincount(flat, blk.ravel(), G1 * G1)
    g = np.bincount(idx.ravel(), np.einsum("nki,nk->ni", Jg, r).ravel(), G1)[:size]
    V = np.stack([np.bincount(obs_point, v, num_points) for v in
                  np.einsum("nki,nkj->nij", Jp, Jp).reshape(-1, 9).T], axis=1).reshape(-1, 3, 3)
    gp = np.stack([np.bincount(obs_point, v, num_points) for v in np.einsum("nki,nk->ni", Jp, r).T], axis=1)
    B = np.matmul(np.swapaxes(Jg, 1, 2), Jp)
    rows = np.broadcast_to(idx[:, :, None], B.shape).ravel()
    cols = np.broadcast_to((3 * obs_point)[:, None, None] + np.arange(3), B.shape).ravel()
    W = sparse.csr_matrix((B.ravel(), (rows, cols)), shape=(G1, 3 * num_points))
    return NormalEquations(H.reshape(G1, G1)[:size, :size], g, V, gp, W)


def solve_damped(ne: NormalEquations, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Reduced step dg (G,) and point steps dp (P, 3) of the system damped by ``lam * diag``
    (``W V^-1 W^T``: two sparse products)."""
    size = len(ne.g)
    P = len(ne.gp)
    dH = np.maximum(np.diag(ne.H), DIAG_FLOOR)
    H = ne.H + np.diag(lam * dH)
    dV = np.maximum(np.diagonal(ne.V, axis1=1, axis2=2), DIAG_FLOOR)
    Vinv = np.linalg.inv(ne.V + lam * dV[:, :, None] * np.eye(3))
    W = ne.W
    vr = np.broadcast_to((3 * np.arange(P))[:, None, None] + np.arange(3)[:, None], (P, 3, 3)).ravel()
    vc = np.broadcast_to((3 * np.arange(P))[:, None, None] + np.arange(3)[None, :], (P, 3, 3)).ravel()
    WV = W @ sparse.csr_matrix((Vinv.ravel(), (vr, vc)), shape=(3 * P, 3 * P))
    S = H - (WV @ W.T).toarray()[:size, :size]
    rhs = -ne.g + (WV @ ne.gp.ravel())[:size]
    try:
        dg = cho_solve(cho_factor(S), rhs)
    except np.linalg.LinAlgError:
        dg = np.linalg.lstsq(S, rhs, rcond=None)[0]
    Wt_dg = (W.T @ np.append(dg, 0.0)).reshape(P, 3)
    dp = -np.einsum("pij,pj->pi", Vinv, ne.gp + Wt_dg)
    return dg, dp

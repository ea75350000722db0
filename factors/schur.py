"""Normal equations of a bundle adjustment with many small frame blocks, solved by the Schur complement.

The variables split into frames (one 6-dof block each, independent of each
other given the rest) and G global variables (intrinsics, camera poses, the
normal, the distance). The Gauss-Newton system ``H delta = -g`` then reads::

    [V   W] [d_frame ]     [g_frame ]      V block diagonal (F blocks 6 x 6),
    [W^T U] [d_global] = - [g_global],     W (F, 6, G), U (G, G).

The frames are eliminated: ``S = U - W^T V^-1 W`` (dense G x G, small), solved
by Cholesky, and the frame steps are back-substituted. The same complement,
inverted, gives the marginal covariances of the global variables.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg.lapack


@dataclass
class NormalEquations:
    """J^T J and J^T r (whitened residuals r) split into frame and global blocks."""

    V: np.ndarray  # (F, 6, 6)
    g_frame: np.ndarray  # (F, 6)
    W: np.ndarray  # (F, 6, G) frame-global coupling
    U: np.ndarray  # (G, G)
    g_global: np.ndarray  # (G,)
    error: float  # 0.5 r^T r at the linearisation point (gtsam's oldLinearizedError)

    @staticmethod
    def zeros(n_frames: int, n_global: int) -> "NormalEquations":
        F, G = n_frames, n_global
        return NormalEquations(np.zeros((F, 6, 6)), np.zeros((F, 6)), np.zeros((F, 6, G)), np.zeros((G, G)),
                               np.zeros(G), 0.0)


def solve_damped(sys: NormalEquations, lam: float) -> tuple[np.ndarray, np.ndarray] | None:
    """(global step, frame steps) of ``(H + lam I) delta = -g`` via the Schur complement; None if not PD."""
    F, G = sys.V.shape[0], sys.U.shape[0]
    Vd = sys.V + lam * np.eye(6)
    try:
        np.linalg.cholesky(Vd)
    except np.linalg.LinAlgError:
        return None
    V_inv = np.linalg.inv(Vd)
    Y = np.matmul(V_inv, sys.W)  # (F, 6, G)
    W2, Y2 = sys.W.reshape(6 * F, G), Y.reshape(6 * F, G)
    S = sys.U - W2.T @ Y2
    S[np.diag_indices(G)] += lam
    rhs = -sys.g_global + Y2.T @ sys.g_frame.reshape(6 * F)  # W^T V^-1 g_f
    # scipy.linalg.cho_factor / cho_solve (upper), without their wrappers' overhead
    c, info = scipy.linalg.lapack.dpotrf(S, lower=0, clean=0, overwrite_a=1)
    if info != 0:
        return None
    d_global, info = scipy.linalg.lapack.dpotrs(c, rhs, lower=0)
    if info != 0:
        return None
    if not np.all(np.isfinite(d_global)):
        return None
    d_frame = -np.einsum("fij,fj->fi", V_inv, sys.g_frame + sys.W @ d_global)
    return d_global, d_frame


def model_decrease(sys: NormalEquations, d_global: np.ndarray, d_frame: np.ndarray) -> float:
    """Decrease of the linearised error 0.5 |J d + r|^2 from d = 0: -(g.d + 0.5 d^T H d)."""
    Wd = sys.W @ d_global  # (F, 6)
    quad = d_global @ sys.U @ d_global + 2.0 * np.einsum("fi,fi->", d_frame, Wd)
    quad += np.einsum("fi,fij,fj->", d_frame, sys.V, d_frame)
    lin = sys.g_global @ d_global + np.einsum("fi,fi->", sys.g_frame, d_frame)
    return -(lin + 0.5 * quad)


def global_covariance(sys: NormalEquations, fixed: np.ndarray) -> np.ndarray:
    """(G, G) covariance of the global variables, H^-1 restricted to them: the inverse of the Schur
    complement of the frames; the ``fixed`` columns (not variables) get zero rows and columns."""
    F, G = sys.V.shape[0], sys.U.shape[0]
    V_inv = np.linalg.inv(sys.V)
    W2 = sys.W.reshape(6 * F, G)
    S = sys.U - W2.T @ np.matmul(V_inv, sys.W).reshape(6 * F, G)
    free = np.setdiff1d(np.arange(G), fixed)
    cov = np.zeros((G, G))
    cov[np.ix_(free, free)] = np.linalg.inv(S[np.ix_(free, free)])
    return cov

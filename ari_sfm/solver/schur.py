"""The bundle-adjustment core: normal equations with many small independent blocks, solved by the
Schur complement. Shared by the rig calibration (:mod:`ari_sfm.factors.packed_problem`: the blocks
are the target frames, k = 6) and refine-colmap (:class:`ari_sfm.colmap.refine.refine.Solver`: the
blocks are the 3D points, k = 3).

The variables split into N blocks of k (independent of each other given the rest) and G global
variables (intrinsics, camera poses, the window). The Gauss-Newton system ``H delta = -g`` reads::

    [V   W] [d_block ]     [g_block ]      V block diagonal (N blocks k x k),
    [W^T U] [d_global] = - [g_global],     U (G, G).

The coupling W is held in one of two layouts:

- dense, ``W`` (N, k, G): every block couples to most global columns (the rig's frames);
- entries, ``W`` (E, k, q) with ``W_rows`` (E,) and ``W_cols`` (E, q): entry e adds ``W[e]`` at
  block ``W_rows[e]`` and global columns ``W_cols[e]`` (G: none). One entry per observation
  (COLMAP's points): W is never formed, memory stays linear in the observations.

The blocks are eliminated: ``S = U - W^T V^-1 W`` (dense G x G) and ``b = -g_global + W^T V^-1
g_block`` are built once per block damping (:func:`reduce`; dense: one product ``W^T (V^-1 W)``;
entries: with ``V_n^-1 = L_n L_n^T``, ``W^T V^-1 W = Y^T Y`` where Y's rows for block n are the sum
of its entries' ``L_n^T W_e`` scattered to their columns; Y is filled densely for a chunk of blocks
at a time, over the columns that chunk touches only, one BLAS product per chunk, the blocks taken in
the order of their entries' smallest median column), S is solved by Cholesky and the block steps
back-substituted (``d_block = -V^-1 (g_block + W d_global)``).

Damping, by the system's ``marquardt`` flag:

- False (GTSAM's, the rig): ``H + lambda I`` on every variable; the reduced system is rebuilt for
  every lambda trial (the exact damped step); None when not positive definite.
- True (Marquardt's, refine-colmap): ``lambda * diag`` (floored at DIAG_FLOOR; the global part's
  diagonal from ``damping`` if given). The blocks are damped with the lambda of the linearisation's
  first trial (the reduced system is built once per linearisation); every trial damps S with its own
  lambda. The first trial (the one LM usually accepts) is the exact Marquardt step of the whole
  system; a later one keeps the blocks' damping at lambda_0 while the global block's grows (the
  Marquardt step of the blocks-eliminated problem). A block with V = 0 (a point moved into the global
  variables) is left out. A singular S is solved by least squares.

LM (:mod:`ari_sfm.solver.levenberg_marquardt`) judges every trial by the decrease the whole
undamped model predicts for the joint step (:func:`model_decrease`). The inverse of the undamped
complement is the covariance of the global variables (:func:`global_covariance`).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.linalg.lapack

log = logging.getLogger(__name__)

DIAG_FLOOR = 1e-9  # Marquardt damping: the smallest diagonal entry damped
Y_CHUNK_ENTRIES = 2_000_000  # entries layout: Y is filled for this many floats' worth of blocks (k rows each,
#                              G + 1 columns at most) at a time
RANK_TOLERANCE = 64 * np.finfo(float).eps  # global_covariance: Jacobi-scaled eigenvalue / largest below: undetermined
CLEARLY_DETERMINED = 1e8  # _clearly_determined: the largest trusted Frobenius norm of a scaled block's inverse
NULL_SHARE = 1e-6  # global_covariance: a variable with more than this share in undetermined directions is one


@dataclass
class NormalEquations:
    """J^T J and J^T r (whitened residuals r) split into block and global parts (module docstring).
    The names say "frame" for a block (the rig's); refine-colmap's blocks are points."""

    V: np.ndarray  # (N, k, k)
    g_frame: np.ndarray  # (N, k)
    W: np.ndarray  # (N, k, G) dense, or (E, k, q) entries
    U: np.ndarray  # (G, G)
    g_global: np.ndarray  # (G,)
    error: float  # the cost at the linearisation point (0.5 r^T r; gtsam's oldLinearizedError)
    W_rows: np.ndarray | None = None  # (E,) each entry's block (entries layout)
    W_cols: np.ndarray | None = None  # (E, q) each entry's global columns, G where none (entries layout)
    marquardt: bool = False  # damping lambda * diag (else lambda I), blocks damped at the first trial's lambda
    damping: np.ndarray | None = None  # (G,) Marquardt's scales of the global part (default diag U)
    reduced: Any = field(default=None, repr=False)  # the ReducedSystem last built

    @staticmethod
    def zeros(n_frames: int, n_global: int, k: int = 6) -> NormalEquations:
        """A dense-layout system of zeros.

        Args:
            n_frames: the number of blocks N.
            n_global: the number of global variables G.
            k: the block size.

        Returns:
            The :class:`NormalEquations` with V (N, k, k), W (N, k, G), U (G, G) and the gradients zero.
        """
        N, G = n_frames, n_global
        return NormalEquations(np.zeros((N, k, k)), np.zeros((N, k)), np.zeros((N, k, G)), np.zeros((G, G)),
                               np.zeros(G), 0.0)

    def coupling_to_blocks(self, d_global: np.ndarray) -> np.ndarray:
        """W d_global (N, k)."""
        if self.W_rows is None:
            return self.W @ d_global
        v = np.einsum("nki,ni->nk", self.W, np.append(d_global, 0.0)[self.W_cols])
        N, k = self.g_frame.shape
        return np.stack([np.bincount(self.W_rows, v[:, j], N) for j in range(k)], axis=1)

    def coupling_to_global(self, d_block: np.ndarray) -> np.ndarray:
        """W^T d_block (G,)."""
        G = len(self.g_global)
        if self.W_rows is None:
            return np.einsum("nkg,nk->g", self.W, d_block)
        assert self.W_cols is not None  # the entries layout has both
        v = np.einsum("nki,nk->ni", self.W, d_block[self.W_rows])
        return np.bincount(self.W_cols.ravel(), v.ravel(), G + 1)[:G]


@dataclass(frozen=True)
class ReducedSystem:
    """``S = U - W V_d^-1 W^T`` and ``b = -g_global + W^T V_d^-1 g_block`` with the blocks damped by
    ``lam_blocks`` (V_d); ``V_inv`` = V_d^-1 (N, k, k)."""

    S: np.ndarray
    b: np.ndarray
    V_inv: np.ndarray
    lam_blocks: float


def reduce(sys: NormalEquations, lam_blocks: float) -> ReducedSystem | None:
    """The reduced system with the blocks damped by ``lam_blocks``.

    Args:
        sys: the normal equations.
        lam_blocks: the blocks' damping lambda (``lambda I``, or ``lambda diag`` with ``sys.marquardt``).

    Returns:
        The :class:`ReducedSystem`, or None when a damped block is not positive definite (GTSAM's damping).
    """
    N, k = sys.g_frame.shape
    G = len(sys.g_global)
    if sys.marquardt:
        dV = np.maximum(np.diagonal(sys.V, axis1=1, axis2=2), DIAG_FLOOR)
        Vd = sys.V + lam_blocks * dV[:, :, None] * np.eye(k)
        Vd[np.trace(sys.V, axis1=1, axis2=2) == 0.0] = np.eye(k)  # blocks moved into the global variables
    else:
        Vd = sys.V + lam_blocks * np.eye(k)
        try:
            np.linalg.cholesky(Vd)
        except np.linalg.LinAlgError:
            return None
    V_inv = np.linalg.inv(Vd)
    if sys.W_rows is None:
        Y = np.matmul(V_inv, sys.W)  # (N, k, G)
        W2, Y2 = sys.W.reshape(k * N, G), Y.reshape(k * N, G)
        S = sys.U - W2.T @ Y2
        b = -sys.g_global + Y2.T @ sys.g_frame.reshape(k * N)  # W^T V^-1 g_block
        return ReducedSystem(S, b, V_inv, lam_blocks)
    from .schur_kernels import fill_y

    V_inv = 0.5 * (V_inv + np.swapaxes(V_inv, 1, 2))
    L = np.linalg.cholesky(V_inv)
    rows, cols = sys.W_rows, sys.W_cols
    assert cols is not None  # the entries layout has both
    # blocks ordered by their entries' smallest median column (the median skips the columns every entry
    # shares, e.g. the intrinsics, and lands on a frame's)
    first = np.full(N, G)
    np.minimum.at(first, rows, np.sort(cols, axis=1)[:, cols.shape[1] // 2])
    rank = np.empty(N, np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(N)
    ranked = rank[rows]
    order = np.argsort(ranked, kind="stable")
    starts = np.searchsorted(ranked[order], np.arange(N + 1))
    per = max(1, Y_CHUNK_ENTRIES // (k * (G + 1)))
    S = sys.U.copy()
    local = np.full(G + 1, -1, np.int64)
    for r0 in range(0, N, per):
        r1 = min(N, r0 + per)
        touched = np.unique(cols[order[starts[r0]:starts[r1]]])
        touched = touched[touched < G]
        local[touched] = np.arange(len(touched))
        local[G] = len(touched)  # the dummy column, dropped
        Y = np.empty((k * (r1 - r0), len(touched) + 1))
        fill_y(sys.W, rows, rank, cols, local, L, order, starts[r0], starts[r1], r0, Y)
        Yg = Y[:, :-1]
        if len(touched) == G:
            S -= Yg.T @ Yg
        else:
            S[np.ix_(touched, touched)] -= Yg.T @ Yg
    u = np.einsum("nij,nj->ni", V_inv, sys.g_frame)
    b = -sys.g_global + sys.coupling_to_global(u)
    return ReducedSystem(S, b, V_inv, lam_blocks)


def _cholesky_solve(S: np.ndarray, b: np.ndarray, overwrite: bool) -> np.ndarray | None:
    """S^-1 b by Cholesky (LAPACK directly: scipy's cho_factor / cho_solve without their checks); None
    if S is not positive definite. ``overwrite``: S may be overwritten."""
    c, info = scipy.linalg.lapack.dpotrf(S, lower=0, clean=0, overwrite_a=int(overwrite))
    if info != 0:
        return None
    x, info = scipy.linalg.lapack.dpotrs(c, b, lower=0)
    return x if info == 0 else None


def solve_damped(sys: NormalEquations, lam: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The steps of the system damped by ``lam`` (module docstring).

    Args:
        sys: the normal equations; its ``reduced`` system is built or reused.
        lam: the damping lambda.

    Returns:
        The global step (G,) and the block steps (N, k), or None if the damped system cannot be solved.
    """
    if sys.marquardt:
        lam_blocks = lam if sys.reduced is None else sys.reduced.lam_blocks  # the first trial's
    else:
        lam_blocks = lam
    if sys.reduced is None or sys.reduced.lam_blocks != lam_blocks:
        red = reduce(sys, lam_blocks)
        if red is None:
            return None
        sys.reduced = red
    red = sys.reduced
    G = len(sys.g_global)
    if sys.marquardt:
        scale = np.maximum(np.diag(sys.U) if sys.damping is None else sys.damping, DIAG_FLOOR)
        S = red.S + np.diag(lam * scale)
    else:
        S = red.S.copy()
        S[np.diag_indices(G)] += lam
    if not np.all(np.isfinite(S)):
        return None
    d_global = _cholesky_solve(S, red.b, overwrite=not sys.marquardt)  # Marquardt's falls back on S
    if d_global is None:
        if not sys.marquardt:
            return None
        d_global = np.linalg.lstsq(S, red.b, rcond=None)[0]
    if not np.all(np.isfinite(d_global)):
        return None
    d_block = -np.einsum("nij,nj->ni", red.V_inv, sys.g_frame + sys.coupling_to_blocks(d_global))
    return d_global, d_block


def model_decrease(sys: NormalEquations, d_global: np.ndarray, d_block: np.ndarray) -> float:
    """Decrease of the linearised cost from d = 0 for the joint step, undamped: ``-(g.d + 0.5 d^T H d)``.

    Args:
        sys: the normal equations.
        d_global: the global step (G,).
        d_block: the block steps (N, k).

    Returns:
        The predicted decrease.
    """
    Wd = sys.coupling_to_blocks(d_global)  # (N, k)
    quad = d_global @ sys.U @ d_global + 2.0 * np.einsum("fi,fi->", d_block, Wd)
    quad += np.einsum("fi,fij,fj->", d_block, sys.V, d_block)
    lin = sys.g_global @ d_global + np.einsum("fi,fi->", sys.g_frame, d_block)
    return float(-(lin + 0.5 * quad))


def _scaled_eigh(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigen-decomposition of ``D^-1 A D^-1`` with ``D = sqrt(diag A)`` (Jacobi scaling, so that the
    variables' units do not decide what is small): (eigenvalues, eigenvectors, D); a zero or
    non-finite diagonal entry is scaled by 1 (its row and column zeroed)."""
    d = np.diagonal(A, axis1=-2, axis2=-1)
    good = np.isfinite(d) & (d > 0.0)
    D = np.where(good, np.sqrt(np.where(good, d, 1.0)), 1.0)
    As = np.where(good[..., :, None] & good[..., None, :], A, 0.0) / (D[..., :, None] * D[..., None, :])
    As = 0.5 * (As + np.swapaxes(As, -1, -2))
    w, Q = np.linalg.eigh(np.nan_to_num(As, nan=0.0, posinf=0.0, neginf=0.0))
    return w, Q, D


def _clearly_determined(V: np.ndarray) -> bool:
    """Whether every block of ``V`` (N, k, k) has all its Jacobi-scaled eigenvalues above
    ``RANK_TOLERANCE`` x the largest, shown without eigenvalues: a scaled block ``As`` (unit diagonal)
    has its largest eigenvalue <= k and, when positive definite, its least >= 1 / ||As^-1||_F; the
    inverse is trusted only while ``||As^-1||_F <= CLEARLY_DETERMINED`` (its rounding then ~1e-8
    relative), which proves the ratio above 1 / (k 1e8), far above the tolerance; positive definite by
    Cholesky. False decides nothing."""
    d = np.diagonal(V, axis1=1, axis2=2)
    if not (np.all(np.isfinite(V)) and np.all(d > 0.0)):
        return False
    D = np.sqrt(d)
    As = V / (D[:, :, None] * D[:, None, :])
    As = 0.5 * (As + np.swapaxes(As, 1, 2))
    try:
        np.linalg.cholesky(As)  # positive definite: no negative eigenvalue
        inv = np.linalg.inv(As)
    except np.linalg.LinAlgError:
        return False
    return bool(np.all(np.einsum("nij,nij->n", inv, inv) <= CLEARLY_DETERMINED ** 2))


def _determined_blocks(V: np.ndarray) -> tuple[np.ndarray, int]:
    """The blocks with every direction the data do not determine held.

    ``V`` (N, k, k): a direction with a Jacobi-scaled eigenvalue below ``RANK_TOLERANCE`` x the largest, or
    negative, is given the block's largest eigenvalue instead: a prior that holds that direction of the block,
    so that the blocks can be eliminated (exact when H is positive semi-definite: an undetermined block
    direction then couples to no global variable). Returns the blocks and how many were changed. A zero block
    (a block moved into the global variables) is kept. Blocks shown far from singular by their inverse
    (:func:`_clearly_determined`) skip the eigen-decompositions.
    """
    if _clearly_determined(V):
        return V, 0
    w, Q, D = _scaled_eigh(V)
    top = w.max(axis=1, keepdims=True)
    bad = np.any(w <= RANK_TOLERANCE * top, axis=1) & (np.trace(V, axis1=1, axis2=2) != 0.0)
    bad |= ~np.all(np.isfinite(V), axis=(1, 2))
    if not bad.any():
        return V, 0
    top = np.maximum(top, 1e-300)
    w = np.where(w > RANK_TOLERANCE * top, w, top)
    held = np.einsum("nij,nj,nkj->nik", Q, w, Q) * (D[:, :, None] * D[:, None, :])
    return np.where(bad[:, None, None], held, V), int(bad.sum())


def global_covariance(sys: NormalEquations, fixed: np.ndarray | None = None) -> np.ndarray:
    """Covariance of the global variables: H^-1 restricted to them, the inverse of the undamped Schur complement.

    A singular or indefinite information matrix is a fact about the data, not an error: a block
    direction the data do not determine is held (:func:`_determined_blocks`); a global variable
    with a component along an undetermined direction of the complement (Jacobi-scaled eigenvalue
    below ``RANK_TOLERANCE`` x the largest, or negative) gets variance inf and NaN covariances;
    the determined ones get the pseudo-inverse restricted to the determined subspace.

    Args:
        sys: the normal equations (undamped).
        fixed: the columns that are not variables; they get zero rows and columns.

    Returns:
        The covariance (G, G).
    """
    G = len(sys.g_global)
    V, n_held = _determined_blocks(sys.V)
    if n_held:  # blocks the data do not place (e.g. a frame seen in a lost optimum)
        log.warning("%d of %d blocks of the normal equations are singular: their undetermined directions held",
                    n_held, len(V))
    empty = np.trace(V, axis1=1, axis2=2) == 0.0  # blocks no factor touches (their coupling rows are zero too)
    if empty.any():
        V = V.copy()
        V[empty] = np.eye(V.shape[1])
    if n_held or empty.any():
        sys = replace(sys, V=V, reduced=None)
    red = reduce(sys, 0.0)
    if red is None:  # cannot be: _determined_blocks left every block positive definite
        raise RuntimeError("the undamped blocks are not positive definite")
    free = np.arange(G) if fixed is None else np.setdiff1d(np.arange(G), fixed)
    S = red.S[np.ix_(free, free)]
    cov = np.zeros((G, G))
    try:
        Li = np.linalg.inv(np.linalg.cholesky(S))
        inv = Li.T @ Li
        if np.all(np.isfinite(inv)):
            cov[np.ix_(free, free)] = inv
            return cov
    except np.linalg.LinAlgError:
        pass
    w, Q, D = _scaled_eigh(S)
    top = max(float(w.max(initial=0.0)), 1e-300)
    null = w <= RANK_TOLERANCE * top
    inv = (Q[:, ~null] / w[~null]) @ Q[:, ~null].T / np.outer(D, D)
    undetermined = np.sum(Q[:, null] ** 2, axis=1) > NULL_SHARE
    inv[undetermined, :] = np.nan
    inv[:, undetermined] = np.nan
    inv[undetermined, undetermined] = np.inf
    cov[np.ix_(free, free)] = inv
    return cov


def assemble_from_observations(residuals: np.ndarray, J_global: np.ndarray, cols: np.ndarray,
                               J_block: np.ndarray, rows: np.ndarray, n_blocks: int, n_global: int,
                               weights: np.ndarray | None = None, marquardt: bool = True) -> NormalEquations:
    """Normal equations (entries layout) of per-observation residuals and Jacobians.

    Args:
        residuals: whitened residuals (M, d).
        J_global: each observation's Jacobian on its global columns (M, d, q).
        cols: the global columns (M, q), -1 where none.
        J_block: each observation's Jacobian on its block (M, d, k).
        rows: each observation's block (M,).
        n_blocks: the number of blocks N.
        n_global: the number of global variables G.
        weights: each observation's weight (M,) (IRLS); None: 1.
        marquardt: the system's damping (Marquardt's ``lambda * diag``, else ``lambda I``).

    Returns:
        The :class:`NormalEquations`, its ``error`` left 0.
    """
    from .schur_kernels import assemble_entries

    G = n_global
    idx = np.where(cols >= 0, cols, G)  # a dummy column G, dropped
    w = np.ones(len(rows)) if weights is None else np.asarray(weights, float)
    U, g, V, gb, W = assemble_entries(np.ascontiguousarray(residuals, float), np.ascontiguousarray(J_global, float),
                                      idx, np.ascontiguousarray(J_block, float), np.asarray(rows), w, n_blocks, G)
    U = U[:G, :G]
    U = U + U.T - np.diag(np.diag(U))  # the kernel fills each pair of columns once
    return NormalEquations(V, gb, W, U, g[:G], 0.0, W_rows=rows, W_cols=idx, marquardt=marquardt)

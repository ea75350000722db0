"""Compiled accumulations of the bundle-adjustment core (:mod:`ari_sfm.solver.schur`), entries layout:
the normal equations from per-observation Jacobians, and the Schur complement's Y matrix. One pass
over the observations each, no temporaries of the observations' size (numba, ``cache=True``)."""
from __future__ import annotations

import numpy as np

from ..kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def assemble_entries(residuals, J_global, cols, J_block, rows, weights, n_blocks, n_global):
    """Weighted normal equations of observations (entries layout).

    Args:
        residuals: residual rows r (M, d).
        J_global: Jacobians on the global columns (M, d, q).
        cols: the global columns (M, q), ``n_global`` where none.
        J_block: Jacobians on the blocks (M, d, k).
        rows: each observation's block (M,).
        weights: each observation's weight (M,).
        n_blocks: the number of blocks N.
        n_global: the number of global variables G.

    Returns:
        U (G+1, G+1) (each pair of columns added once, in one of its two triangles) and g (G+1,), the last
            row and column the dummy column's; V (N, k, k), g_block (N, k) and W (M, k, q).
    """
    M, d, q = J_global.shape
    k = J_block.shape[2]
    G1 = n_global + 1
    U = np.zeros((G1, G1))
    g = np.zeros(G1)
    V = np.zeros((n_blocks, k, k))
    gb = np.zeros((n_blocks, k))
    W = np.empty((M, k, q))
    P = np.empty((q, q))  # one observation's J_global^T J_global
    for o in range(M):
        w = weights[o]
        n = rows[o]
        c = cols[o]
        Jg, Jb, res = J_global[o], J_block[o], residuals[o]  # (d, q), (d, k), (d,)
        P[:] = 0.0
        We = W[o]
        We[:] = 0.0
        Vn, gbn = V[n], gb[n]
        for r in range(d):  # the row index outermost: the inner loops run over contiguous columns
            Jr, Br, e = Jg[r], Jb[r], w * res[r]
            for i in range(q):
                wi = w * Jr[i]
                g[c[i]] += e * Jr[i]
                Pi = P[i]
                for j in range(i, q):
                    Pi[j] += wi * Jr[j]
            for a in range(k):
                wa = w * Br[a]
                gbn[a] += e * Br[a]
                for b in range(k):
                    Vn[a, b] += wa * Br[b]
                Wa = We[a]
                for i in range(q):
                    Wa[i] += wa * Jr[i]
        for i in range(q):
            Urow, Pi = U[c[i]], P[i]
            for j in range(i, q):
                Urow[c[j]] += Pi[j]
    return U, g, V, gb, W


@njit(**_JIT)
def fill_y(W, rows, rank, cols, local, L, order, start, stop, r0, Y):
    """Fill Y with the rows of the blocks ranked r0.. (one chunk), ``W^T V^-1 W = sum over chunks of Y^T Y``.

    Block n's k rows (at ``k (rank[n] - r0)``) are the sum of its entries' ``L_n^T W_e``, entry column c at
    Y's column ``local[c]``.

    Args:
        W: the entries' coupling (E, k, q).
        rows: each entry's block (E,).
        rank: each block's rank (N,).
        cols: each entry's global columns (E, q).
        local: Y's column of each global column (G + 1,).
        L: ``V_n^-1 = L_n L_n^T`` per block (N, k, k).
        order: the entries in the order of their blocks' ranks (E,).
        start: first of the chunk's entries in ``order``.
        stop: end of the chunk's entries in ``order``.
        r0: the rank of the chunk's first block.
        Y: output (k (r1 - r0), columns), zeroed and filled.
    """
    k, q = W.shape[1], W.shape[2]
    Y[:] = 0.0
    for t in range(start, stop):
        e = order[t]
        n = rows[e]
        base = k * (rank[n] - r0)
        c, We, Ln = cols[e], W[e], L[n]
        for a in range(k):
            Ya = Y[base + a]
            for i in range(q):
                s = 0.0
                for b in range(k):
                    s += Ln[b, a] * We[b, i]
                Ya[local[c[i]]] += s

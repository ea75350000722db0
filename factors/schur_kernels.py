"""Compiled accumulations of the bundle-adjustment core (:mod:`ari_sfm.factors.schur`), entries layout:
the normal equations from per-observation Jacobians, and the Schur complement's block products. One pass
over the observations each, no temporaries of the observations' size (numba, ``cache=True``)."""
from __future__ import annotations

import numpy as np
from numba import njit

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def assemble_entries(residuals, J_global, cols, J_block, rows, weights, n_blocks, n_global):
    """Weighted normal equations of observations (residual rows r (M, d), ``J_global`` (M, d, q) at
    ``cols`` (M, q; ``n_global`` = none), ``J_block`` (M, d, k) on block ``rows``): U (G+1, G+1) and
    g (G+1,) (the last row and column the dummy's), V (N, k, k), g_block (N, k), W (M, k, q)."""
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
def subtract_block_products(W, rows, cols, L, order, starts, S):
    """S -= W^T V^-1 W block by block (entries layout), on S's upper triangle only: for block n with
    entries ``order[starts[n]:starts[n+1]]``, ``Y_n = L_n^T W_n`` on the global columns its entries
    touch (dense on those only), then ``S[c, c'] -= (Y_n^T Y_n)[c, c']`` for c <= c'. Cost per block: k
    times its columns squared / 2 (a point of a short track: ~50 columns of thousands)."""
    k, q = W.shape[1], W.shape[2]
    G = S.shape[0]
    N = len(starts) - 1
    pos = -np.ones(G + 1, np.int64)
    local = np.empty(G + 1, np.int64)
    Y = np.zeros((k, G + 1))
    P = np.zeros((64, 64))  # the local Gram matrix (grown when a block touches more columns)
    for n in range(N):
        m = 0
        Ln = L[n]
        for t in range(starts[n], starts[n + 1]):
            e = order[t]
            c, We = cols[e], W[e]
            for i in range(q):
                ci = c[i]
                if ci >= G:
                    continue
                j = pos[ci]
                if j < 0:
                    j = m
                    pos[ci] = m
                    local[m] = ci
                    for a in range(k):
                        Y[a, m] = 0.0
                    m += 1
                for a in range(k):
                    s = 0.0
                    for b in range(k):
                        s += Ln[b, a] * We[b, i]
                    Y[a, j] += s
        if P.shape[0] < m:
            P = np.zeros((2 * m, 2 * m))
        for i in range(m):
            Pi = P[i]
            for j in range(i, m):
                Pi[j] = 0.0
        for a in range(k):  # the local Gram matrix, upper triangle, contiguous inner loop
            Ya = Y[a]
            for i in range(m):
                yai = Ya[i]
                Pi = P[i]
                for j in range(i, m):
                    Pi[j] += yai * Ya[j]
        for i in range(m):
            ci = local[i]
            Pi = P[i]
            for j in range(i, m):
                cj = local[j]
                if ci <= cj:
                    S[ci, cj] -= Pi[j]
                else:
                    S[cj, ci] -= Pi[j]
        for i in range(m):
            pos[local[i]] = -1

"""The bundle-adjustment core (ari_sfm.solver.schur) against dense solves of the full normal equations;
the unit-normal chart (ari_sfm.geometry.unit3_*) against gtsam.Unit3.

Both layouts and both damping policies: dense coupling with blocks of 6 (the rig's frames, lambda I)
and per-observation entries with blocks of 3 (COLMAP's points, Marquardt's lambda diag); the step,
the predicted decrease and the covariance of the global variables to 1e-10.
"""
from __future__ import annotations

import numpy as np
import pytest

from ari_sfm.solver.schur import (
    NormalEquations,
    assemble_from_observations,
    global_covariance,
    model_decrease,
    solve_damped,
)


def _random_observations(rng: np.random.Generator, n_blocks: int, n_global: int, per_block: int, q: int):
    """Observations (2 rows each) of random blocks of 3 and random global columns (some -1)."""
    M = n_blocks * per_block
    rows = np.repeat(np.arange(n_blocks), per_block)
    cols = np.array([rng.choice(n_global, q, replace=False) for _ in range(M)])
    cols[rng.random((M, q)) < 0.1] = -1
    return (rng.normal(size=(M, 2)), rng.normal(size=(M, 2, q)), cols, rng.normal(size=(M, 2, 3)), rows)


def _dense_jacobian(J_g, cols, J_b, rows, n_blocks: int, n_global: int, weights: np.ndarray) -> np.ndarray:
    """The whole whitened Jacobian: global columns first, then the blocks."""
    M, d, k = J_b.shape
    J = np.zeros((M * d, n_global + k * n_blocks))
    for o in range(M):
        use = cols[o] >= 0
        J[d * o:d * o + d, cols[o][use]] = J_g[o][:, use] * np.sqrt(weights[o])
        J[d * o:d * o + d, n_global + k * rows[o] + np.arange(k)] = J_b[o] * np.sqrt(weights[o])
    return J


def _close(a: np.ndarray, b: np.ndarray, tol: float = 1e-10) -> bool:
    return bool(np.max(np.abs(a - b)) <= tol * max(np.max(np.abs(b)), 1.0))


def test_entries_layout_blocks_of_3_marquardt_step_is_the_full_damped_step():
    """Points (k = 3) with a sparse coupling: at the first trial every variable is damped by lambda
    diag; a later trial damps the global part with its own lambda and the points with the first's."""
    rng = np.random.default_rng(3)
    N, G = 40, 15
    r, J_g, cols, J_b, rows = _random_observations(rng, N, G, 4, 6)
    w = rng.uniform(0.2, 1.0, len(rows))
    ne = assemble_from_observations(r, J_g, cols, J_b, rows, N, G, w, marquardt=True)
    J = _dense_jacobian(J_g, cols, J_b, rows, N, G, w)
    rw = (r * np.sqrt(w)[:, None]).ravel()
    H, g = J.T @ J, J.T @ rw
    d = np.maximum(np.diag(H), 1e-9)
    for lam_global, lam_points in ((1e-3, 1e-3), (1e-1, 1e-3)):
        full = np.linalg.solve(H + np.diag(np.r_[np.full(G, lam_global), np.full(3 * N, lam_points)] * d), -g)
        dg, dp = solve_damped(ne, lam_global)
        assert _close(dg, full[:G]) and _close(dp.ravel(), full[G:])
        step = np.r_[dg, dp.ravel()]
        assert _close(np.array(model_decrease(ne, dg, dp)), np.array(-(g @ step + 0.5 * step @ H @ step)))


def test_dense_layout_blocks_of_6_gtsam_step_is_the_full_damped_step():
    """Frames (k = 6) with a dense coupling, GTSAM's damping lambda I on every variable, the reduced
    system rebuilt per trial; the whole cost's predicted decrease; the covariance is inv(H)'s block."""
    rng = np.random.default_rng(4)
    N, G, k = 7, 12, 6
    A = rng.normal(size=(10 * N * k, N * k + G))  # a dense whole Jacobian, blocks made independent below
    block_of_row = np.repeat(np.arange(N), 10 * k)
    for n in range(N):
        A[np.ix_(block_of_row != n, G + k * n + np.arange(k))] = 0.0
    r = rng.normal(size=len(A))
    H, g = A.T @ A, A.T @ r
    ne = NormalEquations.zeros(N, G)
    ne.U, ne.g_global = H[:G, :G].copy(), g[:G].copy()
    for n in range(N):
        b = G + k * n + np.arange(k)
        ne.V[n], ne.g_frame[n], ne.W[n] = H[np.ix_(b, b)], g[b], H[np.ix_(b, np.arange(G))]
    for lam in (1e-5, 1e-1, 10.0):
        full = np.linalg.solve(H + lam * np.eye(len(H)), -g)
        dg, df = solve_damped(ne, lam)
        assert _close(dg, full[:G]) and _close(df.ravel(), full[G:])
        step = np.r_[dg, df.ravel()]
        assert _close(np.array(model_decrease(ne, dg, df)), np.array(-(g @ step + 0.5 * step @ H @ step)))
    fixed = np.array([2, 5])
    free = np.setdiff1d(np.arange(G), fixed)
    keep = np.r_[free, np.arange(G, len(H))]
    ref = np.linalg.inv(H[np.ix_(keep, keep)])[:len(free), :len(free)]
    cov = global_covariance(ne, fixed)
    assert _close(cov[np.ix_(free, free)], ref)
    assert not cov[fixed].any() and not cov[:, fixed].any()


def test_entries_layout_covariance_is_inverse_h_restricted():
    """Points eliminated with a sparse coupling: the global variables' covariance is inv(H)'s block."""
    rng = np.random.default_rng(5)
    N, G = 25, 9
    r, J_g, cols, J_b, rows = _random_observations(rng, N, G, 5, 5)
    ne = assemble_from_observations(r, J_g, cols, J_b, rows, N, G)
    J = _dense_jacobian(J_g, cols, J_b, rows, N, G, np.ones(len(rows)))
    assert _close(global_covariance(ne), np.linalg.inv(J.T @ J)[:G, :G])


def test_both_layouts_give_the_same_step():
    """One system written both ways (entries with blocks of 6, and dense): the same step."""
    rng = np.random.default_rng(6)
    N, G, k = 6, 10, 6
    M = 30
    rows, cols = rng.integers(0, N, M), np.array([rng.choice(G, 4, replace=False) for _ in range(M)])
    r, J_g, J_b = rng.normal(size=(M, 3)), rng.normal(size=(M, 3, 4)), rng.normal(size=(M, 3, k))
    rows[:N] = np.arange(N)  # every block observed
    sparse = assemble_from_observations(r, J_g, cols, J_b, rows, N, G, marquardt=False)
    dense = NormalEquations(sparse.V.copy(), sparse.g_frame.copy(), np.zeros((N, k, G)), sparse.U.copy(),
                            sparse.g_global.copy(), 0.0)
    for e in range(M):
        dense.W[rows[e]][:, cols[e]] += sparse.W[e]
    for lam in (1e-4, 1.0):
        a, b = solve_damped(sparse, lam), solve_damped(dense, lam)
        assert _close(a[0], b[0]) and _close(a[1], b[1])
    assert _close(global_covariance(sparse), global_covariance(dense))


@pytest.mark.parametrize("marquardt", [False, True])
def test_a_singular_system(marquardt):
    """A global column no observation touches: GTSAM's damping at lambda 0 gives None (not positive
    definite); Marquardt's still solves (least squares), the free column's step 0."""
    rng = np.random.default_rng(7)
    N, G = 10, 6
    r, J_g, cols, J_b, rows = _random_observations(rng, N, G, 4, 3)
    cols[cols == 5] = -1
    ne = assemble_from_observations(r, J_g, cols, J_b, rows, N, G, marquardt=marquardt)
    out = solve_damped(ne, 0.0)
    if marquardt:
        assert out is not None and abs(out[0][5]) < 1e-12 and np.all(np.isfinite(out[1]))
    else:
        assert out is None


def test_unit_normal_chart_is_gtsams_unit3():
    """The one chart of window normals (refine-colmap's problem; the rig holds gtsam.Unit3 itself):
    basis and retraction equal gtsam.Unit3's, near the optical axis and anywhere, small and large steps."""
    gtsam = pytest.importorskip("gtsam")
    from ari_sfm.geometry import unit3_basis, unit3_retract

    rng = np.random.default_rng(8)
    for k in range(300):
        n = rng.normal(size=3) if k % 2 else np.array([0.0, 0.0, 1.0]) + 1e-3 * rng.normal(size=3)
        n /= np.linalg.norm(n)
        v = rng.normal(size=2) * 10.0 ** rng.uniform(-12, 0)
        B = unit3_basis(n)
        assert np.allclose(B, gtsam.Unit3(n).basis(), atol=1e-14, rtol=0)
        assert np.allclose(B.T @ B, np.eye(2), atol=1e-14) and np.allclose(n @ B, 0.0, atol=1e-14)
        assert np.allclose(unit3_retract(n, v), gtsam.Unit3(n).retract(v).point3(), atol=1e-14, rtol=0)

"""global_covariance on normal equations the data do not fully determine (issue 14): a singular or
indefinite information matrix gives inf sigmas for the undetermined variables and the exact
covariance of the determined ones, never an exception."""
from __future__ import annotations

import json

import numpy as np

from ari_sfm.solver.schur import NormalEquations, assemble_from_observations, global_covariance

N, K, G, M = 5, 3, 4, 12  # blocks, block size, globals, residuals per block


def _system(J_blocks: np.ndarray, J_global: np.ndarray) -> NormalEquations:
    """Dense-layout normal equations of residual Jacobians (N, M, K) on the blocks and (N, M, G) on the globals."""
    V = np.einsum("nmi,nmj->nij", J_blocks, J_blocks)
    W = np.einsum("nmi,nmg->nig", J_blocks, J_global)
    U = np.einsum("nmg,nmh->gh", J_global, J_global)
    return NormalEquations(V, np.zeros((N, K)), W, U, np.zeros(G), 0.0)


def _global_cov_of_full(J_blocks: np.ndarray, J_global: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The globals' covariance by inverting the whole J^T J over the block columns and the ``keep`` globals."""
    rows = []
    for n in range(N):
        blk = np.zeros((M, N * K))
        blk[:, n * K:(n + 1) * K] = J_blocks[n]
        rows.append(np.hstack([blk, J_global[n][:, keep]]))
    J = np.vstack(rows)
    J = J[:, np.any(J != 0.0, axis=0) | (np.arange(J.shape[1]) >= N * K)]
    return np.linalg.inv(J.T @ J)[-len(keep):, -len(keep):]


def _random(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(N, M, K)), rng.normal(size=(N, M, G)) * np.array([1.0, 10.0, 0.1, 1000.0])


def test_full_rank_matches_the_inverse():
    Jb, Jg = _random(0)
    cov = global_covariance(_system(Jb, Jg))
    np.testing.assert_allclose(cov, _global_cov_of_full(Jb, Jg, np.arange(G)), rtol=1e-9)


def test_a_global_the_data_do_not_see_is_inf_the_others_exact():
    Jb, Jg = _random(1)
    Jg[:, :, 2] = 0.0
    cov = global_covariance(_system(Jb, Jg))
    assert np.isinf(cov[2, 2]) and np.all(np.isnan(np.delete(cov[2], 2)))
    keep = np.array([0, 1, 3])
    np.testing.assert_allclose(cov[np.ix_(keep, keep)], _global_cov_of_full(Jb, Jg, keep), rtol=1e-8)


def test_globals_seen_only_as_a_sum_are_both_inf_the_rest_exact():
    Jb, Jg = _random(2)
    Jg[:, :, 1] = Jg[:, :, 0]  # only g0 + g1 is observed
    cov = global_covariance(_system(Jb, Jg))
    assert np.isinf(cov[0, 0]) and np.isinf(cov[1, 1])
    keep = np.array([0, 2, 3])  # g0 standing for the sum
    ref = _global_cov_of_full(Jb, Jg, keep)
    np.testing.assert_allclose(cov[np.ix_([2, 3], [2, 3])], ref[1:, 1:], rtol=1e-6)


def test_a_singular_block_is_held_not_an_exception():
    """A block direction no residual sees (V singular; LinAlgError before issue 14): the globals keep
    the covariance of the problem without that direction."""
    Jb, Jg = _random(3)
    Jb[1, :, 0] = 0.0
    cov = global_covariance(_system(Jb, Jg))
    np.testing.assert_allclose(cov, _global_cov_of_full(Jb, Jg, np.arange(G)), rtol=1e-8)


def test_fixed_columns_are_zero():
    Jb, Jg = _random(4)
    cov = global_covariance(_system(Jb, Jg), fixed=np.array([3]))
    assert np.all(cov[3] == 0.0) and np.all(cov[:, 3] == 0.0)
    np.testing.assert_allclose(cov[:3, :3], _global_cov_of_full(Jb, Jg, np.arange(3)), rtol=1e-9)


def test_entries_layout_singular_block_and_unseen_global():
    """refine-colmap's layout (Marquardt damping, one entry per observation): a point with one
    coordinate no residual sees (V singular) and a global no observation touches."""
    Jb, Jg = _random(5)
    Jb[2, :, 1] = 0.0
    Jg[:, :, 2] = 0.0
    resid = np.zeros((N * M, 1))
    cols = np.tile(np.arange(G), (N * M, 1))
    ne = assemble_from_observations(resid, Jg.reshape(N * M, 1, G), cols, Jb.reshape(N * M, 1, K),
                                    np.repeat(np.arange(N), M), N, G)
    cov = global_covariance(ne)
    assert np.isinf(cov[2, 2])
    keep = np.array([0, 1, 3])
    np.testing.assert_allclose(cov[np.ix_(keep, keep)], _global_cov_of_full(Jb, Jg, keep), rtol=1e-8)


def test_refine_report_writes_an_undetermined_sigma_as_null():
    """refine.json is strict JSON: a sigma global_covariance left inf/NaN is written null."""
    from ari_sfm.colmap.refine.report import RefineUncertainty

    u = RefineUncertainty(0.3, {"world": float("inf")}, {"world": 2.0}, {"camera1": float("nan")}, float("nan"),
                          ("normal_deg.world",))
    d = json.loads(json.dumps(u.to_json(), allow_nan=False))
    assert d["normal_deg"]["world"] is None and d["distance_mm"]["world"] == 2.0
    assert d["fx_px"]["camera1"] is None and d["scale_rel"] is None


def test_the_quick_determined_test_never_passes_a_block_the_eigenvalues_call_undetermined():
    """_clearly_determined (no eigen-decomposition) against the eigenvalue rule it stands in for, on
    blocks of condition 1 to 1e20, indefinite ones and badly scaled ones: it may defer (False), never err."""
    from ari_sfm.solver.schur import RANK_TOLERANCE, _clearly_determined, _scaled_eigh

    rng = np.random.default_rng(7)
    said_yes = 0
    for trial in range(400):
        Q = np.linalg.qr(rng.normal(size=(6, 6)))[0]
        w = np.logspace(0, -rng.uniform(0, 20), 6)
        if trial % 5 == 0:
            w[rng.integers(6)] *= -1e-3 if trial % 10 else -1.0  # indefinite
        scale = np.diag(10 ** rng.uniform(-6, 6, 6))  # units: the Jacobi scaling must undo them
        block = scale @ (Q * w) @ Q.T @ scale
        blocks = np.stack([block, np.eye(6)])
        ws = _scaled_eigh(blocks)[0]
        determined = np.all(ws > RANK_TOLERANCE * ws.max(axis=1, keepdims=True))
        if _clearly_determined(blocks):
            assert determined, (trial, ws)
            said_yes += 1
    assert said_yes > 100  # and it does pass the well-conditioned ones (the point of it)
    assert _clearly_determined(np.stack([np.diag([4.0, 1, 1, 1, 1, 1e-6])] * 3))
    assert not _clearly_determined(np.stack([np.eye(6), np.diag([1.0, 1, 1, 1, 1, 0])]))

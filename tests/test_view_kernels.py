"""The compiled chain rule and per-view normal equations (ari_sfm.factors.view_kernels) against the numpy
code they replaced (main e40d0d9's view_factor.chain_to_tangents and VectorizedProblem.linearize, kept
here as the oracles), to 1e-12."""
from __future__ import annotations

import numpy as np
import pytest

from ari_sfm.factors.rig_graph import RigGraph, RigState, default_distance_mm
from ari_sfm.factors.vectorized import VectorizedProblem
from ari_sfm.factors.view_factor import chain_to_tangents
from ari_sfm.geometry import rotation_from_rotvec, skew
from ari_sfm.init.rig import initialise_rig
from ari_sfm.simulate import make_scene


def _cross_rows(J: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise J_a x v for J (M, 2, 3), v (M, 3)."""
    out = np.empty_like(J)
    vx, vy, vz = v[:, None, 0], v[:, None, 1], v[:, None, 2]
    jx, jy, jz = J[:, :, 0], J[:, :, 1], J[:, :, 2]
    out[:, :, 0] = jy * vz - jz * vy
    out[:, :, 1] = jz * vx - jx * vz
    out[:, :, 2] = jx * vy - jy * vx
    return out


def _numpy_chain(out, n_params, J_point, J_normal, J_distance, X_cam, P, JA, normal_world, basis, R_wc, t_wc,
                 distance) -> None:
    """The oracle: chain_to_tangents as it was in numpy (JA = J_point R_cam_target per view)."""
    M, k = len(X_cam), 6 + n_params
    Jn2 = J_normal.reshape(2 * M, 3)
    R_cw = np.eye(3) if R_wc is None else R_wc.T
    if R_wc is not None:
        out[:, :, k:k + 3] = _cross_rows(J_point, X_cam) + (Jn2 @ skew(R_cw @ normal_world)).reshape(M, 2, 3)
        out[:, :, k + 3:k + 6] = J_distance[:, :, None] * (-(normal_world @ R_wc)) - J_point
    out[:, :, k + 6:k + 8] = (Jn2 @ (R_cw @ basis)).reshape(M, 2, 2) + J_distance[:, :, None] * (-(t_wc @ basis))
    if distance:
        out[:, :, k + 8] = J_distance
    out[:, :, :3] = _cross_rows(JA, -P)
    out[:, :, 3:6] = JA


@pytest.mark.parametrize("pose,distance", [(False, False), (True, False), (True, True), (False, True)])
def test_chain_rows_equal_the_numpy_chain_rule(pose, distance):
    rng = np.random.default_rng(3)
    sizes = [7, 1, 12]
    view_start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    M, n_p = int(view_start[-1]), 9
    Jp, Jn, Jd = rng.normal(size=(M, 2, 3)) * 1e3, rng.normal(size=(M, 2, 3)) * 1e3, rng.normal(size=(M, 2))
    X, P = rng.normal(size=(M, 3)) * 100, rng.normal(size=(M, 3)) * 100
    R_view = np.array([rotation_from_rotvec(rng.normal(size=3)) for _ in sizes])
    n_w = rng.normal(size=3)
    n_w /= np.linalg.norm(n_w)
    basis = np.linalg.qr(np.c_[n_w, rng.normal(size=(3, 2))])[0][:, 1:]
    R_wc = rotation_from_rotvec(rng.normal(size=3)) if pose else None
    t_wc = rng.normal(size=3) * 100 if pose else np.zeros(3)
    width = 6 + n_p + 8 + (1 if distance else 0)
    ours, ref = np.zeros((M, 2, width)), np.zeros((M, 2, width))
    chain_to_tangents(ours, n_p, Jp, Jn, Jd, X, P, R_view, view_start, n_w, basis, R_wc, t_wc, distance)
    corner_view = np.repeat(np.arange(len(sizes)), sizes)
    JA = np.einsum("mij,mjk->mik", Jp, R_view[corner_view])
    _numpy_chain(ref, n_p, Jp, Jn, Jd, X, P, JA, n_w, basis, R_wc, t_wc, distance)
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


def _numpy_linearize(problem: VectorizedProblem, x) -> tuple:
    """The oracle: the normal equations as VectorizedProblem.linearize formed them in numpy (each view's
    A^T A by one batched product of its whitened rows), from the rows of evaluate_views' camera rows."""
    C, F, G, K = len(problem.camera_names), len(problem.frame_names), problem.n_global, 6 + problem.local_dim
    tr = problem._transforms(x)
    V, g_f = np.zeros((F, 6, 6)), np.zeros((F, 6))
    W, U, g_g = np.zeros((F, 6, G)), np.zeros((G, G)), np.zeros(G)
    err2 = 0.0
    for c in range(C):
        s, e = int(problem.camera_corners[c]), int(problem.camera_corners[c + 1])
        if e == s:
            continue
        out = problem._camera_rows(x, tr, c, problem.huber_px) * problem.corner_inv_sigma[s:e, None, None]
        for v in range(int(problem.camera_views[c]), int(problem.camera_views[c + 1])):
            A = out[problem.view_start[v] - s:problem.view_start[v + 1] - s].reshape(-1, K + 1)
            Hv = A.T @ A
            f = problem.view_frame[v]
            V[f] += Hv[:6, :6]
            g_f[f] += Hv[:6, K]
            cols = problem.camera_cols[c]
            W[f][:, cols] += Hv[:6, 6:K]
            U[np.ix_(cols, cols)] += Hv[6:K, 6:K]
            g_g[cols] += Hv[6:K, K]
            err2 += Hv[K, K]
    return V, g_f, W, U, g_g, 0.5 * err2


@pytest.mark.parametrize("name,model,huber_px,sigma_px", [
    ("paper_single", "ari", 0.3, 1.0),
    ("binocular", "exact", 0.3, 0.4),
    ("binocular_underwater", "exact", None, 2.0),
])
def test_linearize_equals_the_numpy_normal_equations(name, model, huber_px, sigma_px):
    ds = make_scene(name, seed=0).dataset
    rig = initialise_rig(ds, False)
    distance = ds.interface.distance_mm or default_distance_mm(rig.normal_world, rig.cam_from_world)
    state = RigState.from_initialisation(rig, distance)
    rg = RigGraph.build(ds.observations, ds.target, ds.interface, ds.camera_names, state, model=model,
                        estimate_distance=ds.interface.medium_index != 1.0, huber_px=huber_px, sigma_px=sigma_px)
    problem = VectorizedProblem.from_rig_graph(rg, huber_px=huber_px)
    sys = problem.linearize(problem.x)
    V, g_f, W, U, g_g, err = _numpy_linearize(problem, problem.x)
    for ours, ref in ((sys.V, V), (sys.g_frame, g_f), (sys.W, W), (sys.U, U), (sys.g_global, g_g)):
        np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    excess = sys.error - err  # the Huber loss's excess over the rows' 0.5 r^T r
    assert excess >= 0.0 and (huber_px is not None or excess == pytest.approx(0.0, abs=1e-9 * err))
    assert sys.error == pytest.approx(problem.error(), rel=1e-12)


@pytest.mark.parametrize("cameras", [1, 2, 4])
def test_rig_transforms_are_the_poses_composed(cameras):
    """rig_transforms against the poses composed in numpy: R_ct = R_wc^T R_wt, t_ct = R_wc^T (t_wt - t_wc),
    n_c = R_wc^T n_w, h_c = h - t_wc . n_w, to 1e-12 (the kernel reproduces numpy's own bits; tested on
    the calibrations)."""
    from ari_sfm.factors.view_kernels import rig_transforms

    rng = np.random.default_rng(cameras)
    R_wc = np.array([rotation_from_rotvec(rng.normal(0, 0.5, 3)) for _ in range(cameras)])
    R_wt = np.array([rotation_from_rotvec(rng.normal(0, 0.5, 3)) for _ in range(5)])
    t_wc, t_wt = rng.normal(0, 300, (cameras, 3)), rng.normal(0, 300, (5, 3))
    vc, vf = rng.integers(0, cameras, 12), rng.integers(0, 5, 12)
    n_w = rng.normal(size=3)
    n_w /= np.linalg.norm(n_w)
    for with_distance in (False, True):
        R_ct, t_ct, n_c, h_c = rig_transforms(R_wc, t_wc, R_wt, t_wt, vc, vf, n_w, 42.0, with_distance)
        for v in range(12):
            c, f = vc[v], vf[v]
            np.testing.assert_allclose(R_ct[v], R_wc[c].T @ R_wt[f], rtol=0, atol=1e-14)
            np.testing.assert_allclose(t_ct[v], R_wc[c].T @ (t_wt[f] - t_wc[c]), rtol=0, atol=1e-12)
        np.testing.assert_allclose(n_c, np.einsum("cji,j->ci", R_wc, n_w), rtol=0, atol=1e-15)
        if with_distance:
            np.testing.assert_allclose(h_c, 42.0 - t_wc @ n_w, rtol=0, atol=1e-12)
        else:
            assert h_c.shape == (0,)

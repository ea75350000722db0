"""The compiled kernels (ari_sfm/models/kernels.py) against independent routes, on random cameras.

Each reference is computed here without the kernels: OpenCV's projectPoints for the pinhole
and its distortion, a scalar trigonometric Snell trace (sin t = n sin t_g = n_m sin t_m) for the
forward solve, the back-projection round trip, central differences for the Jacobians.
Tolerance 1e-10 px on pixels (the issue's "same numbers as today").
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from ari_sfm.io import parse_calibration
from ari_sfm.models import ExactModel, PinholeModel
from ari_sfm.models.exact import exact_pixels, exact_project, incidence

INDEX = 1.5168


def random_camera(rng: np.random.Generator, medium: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """params (with distortion), a tilted unnormalised normal, thickness and distance."""
    params = np.r_[rng.uniform(1500, 4000), 0.0, rng.uniform(900, 1300), rng.uniform(700, 1100),
                   rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(-5e-4, 5e-4), rng.uniform(-5e-4, 5e-4),
                   rng.uniform(-0.02, 0.02)]
    params[1] = params[0] * rng.uniform(0.998, 1.002)
    normal = np.r_[rng.uniform(-0.25, 0.25, 2), 1.0] * rng.uniform(0.5, 2.0)
    return params, normal, rng.uniform(2.0, 40.0), rng.uniform(10.0, 80.0)


def scene_points(rng: np.random.Generator, n: int = 400) -> np.ndarray:
    z = rng.uniform(150.0, 900.0, n)
    return np.c_[rng.uniform(-0.35, 0.35, (n, 2)) * z[:, None], z]


def snell_radial_offset(D: np.ndarray, nc: np.ndarray, z: np.ndarray, h: float, d: float, medium: float) -> np.ndarray:
    """Radial offset at depth z of camera rays D traced through the plate with angles (no kernel)."""
    cos_t = (D @ nc) / np.linalg.norm(D, axis=1)
    t = np.arccos(np.clip(cos_t, -1.0, 1.0))
    t_g = np.arcsin(np.sin(t) / INDEX)
    t_m = np.arcsin(np.sin(t) / medium)
    return h * np.tan(t) + d * np.tan(t_g) + (z - h - d) * np.tan(t_m)


@pytest.mark.parametrize("medium", [1.0, 1.333])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_projection_obeys_snell_and_opencv(medium, seed):
    rng = np.random.default_rng(seed)
    params, normal, d, h = random_camera(rng, medium)
    nc = normal / np.linalg.norm(normal)
    X = scene_points(rng)
    z, r, L, w, _ = incidence(X, nc, h, d, INDEX, medium)
    D = nc + w[:, None] * r  # the camera-side ray the kernel solved for
    rho = np.linalg.norm(r, axis=1)
    assert np.allclose(snell_radial_offset(D, nc, z, h, d, medium), rho, rtol=0, atol=1e-9 * rho.max())
    K = np.array([[params[0], 0, params[2]], [0, params[1], params[3]], [0, 0, 1.0]])
    uv_cv2 = cv2.projectPoints(D, np.zeros(3), np.zeros(3), K, params[4:])[0].reshape(-1, 2)
    uv = exact_pixels(X, params, normal, d, INDEX, medium, h)
    assert np.abs(uv - uv_cv2).max() < 1e-10 * params[0] / 1000  # ~1e-10 px at these focal lengths
    model = ExactModel(PinholeModel.from_params(params), normal, d, INDEX, medium, h)
    assert np.abs(model.project(X) - uv).max() < 1e-10


@pytest.mark.parametrize("medium", [1.0, 1.333])
def test_back_projection_round_trip(medium):
    rng = np.random.default_rng(7)
    params, normal, d, h = random_camera(rng, medium)
    model = ExactModel(PinholeModel.from_params(params), normal, d, INDEX, medium, h)
    uv = rng.uniform([0, 0], [2400, 2000], (300, 2))
    origins, directions = model.backproject(uv)
    nc = model.normal_cam
    assert np.allclose(origins @ nc, h + d, atol=1e-9)  # the origins lie on the far face
    s = rng.uniform(50.0, 800.0, len(uv))
    assert np.abs(model.project(origins + s[:, None] * directions) - uv).max() < 1e-9


@pytest.mark.parametrize("medium", [1.0, 1.333])
def test_jacobians_match_central_differences(medium):
    rng = np.random.default_rng(11)
    params, normal, d, h = random_camera(rng, medium)
    X = scene_points(rng, 50)
    jac = exact_project(X, params, normal, d, INDEX, medium, h)

    def uv(X=X, params=params, normal=normal, d=d, h=h):
        return exact_pixels(X, params, normal, d, INDEX, medium, h)

    def diff(f, x0, step):
        cols = []
        for i in range(len(x0)):
            e = np.zeros_like(x0)
            e[i] = step
            cols.append((f(x0 + e) - f(x0 - e)) / (2 * step))
        return np.stack(cols, axis=-1)

    J_point = np.stack([(uv(X=X + 1e-4 * e) - uv(X=X - 1e-4 * e)) / 2e-4 for e in np.eye(3)], -1)
    assert np.allclose(jac.J_point, J_point, rtol=1e-5, atol=1e-6)
    assert np.allclose(jac.J_normal, diff(lambda v: uv(normal=v), normal, 1e-7), rtol=1e-5, atol=1e-4)
    p_steps = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-8, 1e-8, 1e-7])
    J_params = np.stack([(uv(params=params + s * e) - uv(params=params - s * e)) / (2 * s)
                         for s, e in zip(p_steps, np.eye(9))], -1)
    assert np.allclose(jac.J_params, J_params, rtol=1e-5, atol=1e-4)
    assert np.allclose(jac.J_thickness, (uv(d=d + 1e-5) - uv(d=d - 1e-5)) / 2e-5, rtol=1e-5, atol=1e-6)
    assert np.allclose(jac.J_distance, (uv(h=h + 1e-5) - uv(h=h - 1e-5)) / 2e-5, rtol=1e-5, atol=1e-6)
    if medium == 1.0:  # in air h is unobservable: its Jacobian is zero to rounding
        assert np.abs(jac.J_distance).max() < 1e-9


def test_undistort_round_trip():
    rng = np.random.default_rng(3)
    params = random_camera(rng, 1.0)[0]
    pin = PinholeModel.from_params(params)
    xy = rng.uniform(-0.4, 0.4, (500, 2))
    assert np.abs(pin.undistort(pin.distort(xy)) - xy).max() * params[0] < 1e-10


@pytest.fixture(scope="module")
def arc4_truth():
    from ari_sfm.simulate import make_scene

    return parse_calibration(make_scene("arc4", seed=0, sigma_px=0.0).truth)


def test_triangulation_kernel_is_the_numpy_algorithm(arc4_truth):
    """The compiled per-point triangulation gives the points of the numpy route (rays -> linear point ->
    Levenberg-Marquardt through ExactModel.project_with_jacobians) and recovers noise-free truth."""
    from ari_sfm.reconstruction import triangulate as T

    cal = arc4_truth
    rng = np.random.default_rng(0)
    centres = np.array([p.t for p in cal.frames.values()])
    X_true = rng.uniform(centres.min(axis=0) - 20, centres.max(axis=0) + 20, (300, 3))
    tracks = {c: cal.project_world(c, X_true) for c in cal.cameras}
    tracks[next(iter(cal.cameras))][:20] = np.nan  # some points seen by fewer cameras
    X, gap, rmse = T.triangulate_pixels(cal, tracks)
    seen = sum(np.isfinite(t[:, 0]) for t in tracks.values()) >= 2
    assert seen.sum() > 250
    assert np.nanmax(np.linalg.norm(X[seen] - X_true[seen], axis=1)) < 1e-6
    assert np.all(np.isnan(X[~seen]))
    noisy = {c: t + rng.normal(0, 0.3, t.shape) for c, t in tracks.items()}
    cameras, uv = T._tracks_array(cal, noisy)
    valid = np.isfinite(uv).all(axis=2)
    valid &= (valid.sum(axis=1) >= 2)[:, None]
    origins = np.full(uv.shape[:2] + (3,), np.nan)
    directions = np.full_like(origins, np.nan)
    for c, cam in enumerate(cameras):
        m = valid[:, c]
        origins[m, c], directions[m, c] = cal.rays_world(cam, uv[m, c])
    X0, gap0 = T.triangulate_rays(origins, directions, valid)
    X1, r1, _ = T.refine_points([T._projector(cal, c) for c in cameras], X0, uv, valid)
    rmse1 = np.sqrt(np.einsum("pck,pck->p", r1, r1) / np.maximum(valid.sum(axis=1), 1))
    for refine, X_ref in ((False, X0), (True, X1)):
        X, gap, rmse = T.triangulate_pixels(cal, noisy, refine=refine)
        ok = np.isfinite(X_ref).all(axis=1)
        assert np.array_equal(ok, np.isfinite(X).all(axis=1))
        tol = 1e-9 if not refine else 1e-3 * T.STEP_TOL_MM * (1 + np.abs(X_ref).max())  # both take the last step
        assert np.abs(X[ok] - X_ref[ok]).max() < tol
        assert np.allclose(gap[ok], gap0[ok], rtol=1e-9, atol=1e-12)
    assert np.allclose(rmse[ok], rmse1[ok], rtol=1e-8)
    assert 0.1 < np.median(rmse[ok]) < 0.5  # the 0.3 px noise, not a converged-to-nothing point

"""The quality gate's floor (ari_sfm.calibration.quality.corner_floor, ari_sfm.calibration.floor_fit) against
simulated truth: what the data allow, measured the way the model sees them, on every kind of target.

- It is a floor: on exact-physics simulations (boards, 3D bodies under water behind a window close to the
  cameras, a multi-plane body, lens distortion, pixels quantised to 0.5 px) the true model's residuals and
  the exact model's fit are within 0.9-1.1 x the floor; the free map reaches the noise (a close window
  under water is not a central camera: the inverse-depth term takes it).
- A body seen once is one rigid body: a plane's placement error is not absorbed by its own map, so the
  floor rises with it.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.calibration.floor_fit import (
    BASIS_U,
    BASIS_V,
    RADIAL_BASIS,
    RADIAL_VECTORS,
    _radial_coefficients,
    _radial_vectors,
    warp_residuals,
)
from ari_sfm.calibration.quality import _view_points, corner_floor, robust_rmse_px
from ari_sfm.init.zhang import object_points
from ari_sfm.simulate import PLACEHOLDER_ROOT, make_scene
from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment
from ari_sfm.simulate.scenarios import build_geometry, ptv_misplaced
from ari_sfm.simulate.scene import observe, to_dataset

SQRT2 = np.sqrt(2.0)


def _truth_rmse(dataset, exact) -> float:
    """The robust RMSE of the data against the noise-free pixels: what the true model leaves."""
    by_key = {(o.camera, o.set, o.frame, o.added_mm): o.pixels for o in exact}
    return robust_rmse_px(o.pixels - by_key[(o.camera, o.set, o.frame, o.added_mm)] for o in dataset.observations
                          if o.set in ("calibration", "stacking"))


def _body_residuals(dataset, radial: bool = True, degree: int = 5) -> np.ndarray:
    """Every body view's free-map residuals, one view at a time."""
    out = []
    for o in dataset.observations:
        X = object_points(dataset.target, o.ids)
        r, fitted = warp_residuals(X[None].copy(), np.asarray(o.pixels, float)[None].copy(), degree, radial)
        assert fitted.all()
        out.append(r[0])
    return np.concatenate(out)


@pytest.mark.parametrize("name,dist", [("body3d_water", None), ("body3d_shallow", None),
                                       ("body3d_water", [-0.05, 0.0, 0.0, 0.0, 0.0])])
def test_a_close_window_under_water_is_taken_by_the_inverse_depth_term(name, dist):
    """Noise-free 3D bodies behind 6 mm of glass 30-50 mm from the cameras, water behind: the DLT's camera and
    an image warp left 0.3 px of the window's non-central refraction (0.04 px with the camera refined with the
    warp); with the inverse-depth term < 0.005 px, 4-10 x less."""
    ds = make_scene(name, seed=0, sigma_px=0.0, dist=dist).dataset
    central = robust_rmse_px([_body_residuals(ds, radial=False)])
    floor = robust_rmse_px([_body_residuals(ds)])
    assert floor < 0.005 and central > 4.0 * floor


def test_the_particle_calibration_body_floor_is_its_noise():
    """`simulate particles`' calibration (a 3-level body, 3 views, 4 cameras, 10 mm glass, water): the
    per-plane floor was 1.2 px, 17 x the corners' noise (27-dot planes seen through a close window under
    water: their warp could not take the refraction); now the floor is the noise."""
    exp = simulate_particle_experiment(ParticleSimOptions(num_frames=1, particles_per_frame=10))
    floor = corner_floor(exp.calibration_dataset)
    noise = 0.05 * SQRT2  # calibration_sigma_px per coordinate
    assert 0.9 * noise < floor.rmse_px < 1.15 * noise
    assert floor.dof == 8 * (2 * 81 - 57)  # 8 views of 81 corners, less W's 2 x 21 terms, the camera's 11, e, a, b


@pytest.mark.parametrize("name,sigma,fixed", [("paper_single", 0.05, False), ("binocular_underwater", 0.05, False),
                                              ("body3d_water", 0.05, False), ("body3d_shallow", 0.1, False),
                                              ("ptv_multiplane", 0.0, True)])
def test_the_exact_model_fits_to_its_floor(name, sigma, fixed):
    """Exact physics, the right model: the true model's residuals and the exact calibration's fit are each
    within 0.9-1.1 x the floor (ptv_multiplane: pixels quantised to 0.5 px, OpenPTV's, fixed focal lengths,
    the declared window; the rest Gaussian noise)."""
    scene = make_scene(name, seed=1, sigma_px=sigma)
    floor = corner_floor(scene.dataset)
    assert 0.9 < _truth_rmse(scene.dataset, scene.exact_observations) / floor.rmse_px < 1.1
    q = calibrate(scene.dataset, model="exact", uncertainty=False, fix_intrinsics=fixed).quality
    assert q.ok and q.floor_rmse_px == floor.rmse_px
    assert 0.9 < q.robust_rmse_px / floor.rmse_px < 1.1


def test_a_body_seen_once_keeps_each_planes_placement_error():
    """ptv_multiplane's plate placed at each depth with an error (0.1 mm, 0.05 deg), declared as the one rigid
    body it was meant to be: the floor rises with the misfit (the per-plane floor stayed at the quantisation,
    0.25 px, and failed a rigid calibration that fits 0.46 px), the rigid calibration fits within 1.1 x it
    and passes."""
    rng = np.random.default_rng(0)
    geometry = build_geometry("ptv_multiplane", rng)
    moved = observe(replace(geometry, target=ptv_misplaced(geometry.target, 0.1, 0.05, np.random.default_rng(1))))
    clean = to_dataset(geometry, observe(geometry), PLACEHOLDER_ROOT, seen=observe(geometry))
    placed = to_dataset(geometry, moved, PLACEHOLDER_ROOT, seen=moved)
    assert corner_floor(placed).rmse_px > 1.4 * corner_floor(clean).rmse_px
    q = calibrate(placed, model="exact", fix_intrinsics=True, uncertainty=False).quality
    assert q.ok and q.robust_rmse_px > 1.4 * corner_floor(clean).rmse_px
    assert q.robust_rmse_px < 1.1 * q.floor_rmse_px


def test_one_plane_moved_is_not_absorbed_by_the_body_map():
    """A central camera (no window) over a 3-plane body, one plane's dots 0.3 mm off in x: every plane fitted
    by its own map sees only the noise; the body's one map cannot absorb the shift."""
    rng = np.random.default_rng(3)
    gx, gy = np.meshgrid(np.linspace(-60, 60, 12), np.linspace(-40, 40, 9))
    X = np.concatenate([np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, z)] for z in (0.0, -10.0, -20.0)])
    K = np.array([[3400.0, 0.0, 640.0], [0.0, 3400.0, 512.0], [0.0, 0.0, 1.0]])
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    moved = X.copy()
    moved[X[:, 2] == -10.0, 0] += 0.3
    xc = moved @ R.T + np.array([0.0, 0.0, 600.0])
    uv = xc[:, :2] / xc[:, 2:] * 3400.0 + K[:2, 2] + rng.normal(0, 0.05, (len(X), 2))
    per_plane = np.concatenate([warp_residuals(X[on, :2][None].copy(), uv[on][None].copy(), 4, False)[0][0]
                                for on in (X[:, 2] == z for z in (0.0, -10.0, -20.0))])
    body = warp_residuals(X[None].copy(), uv[None].copy(), 5, True)[0][0]
    assert robust_rmse_px([per_plane]) < 1.2 * 0.05 * SQRT2
    assert robust_rmse_px([body]) > 3.0 * 0.05 * SQRT2


def test_a_board_view_of_a_3d_target_is_a_plane():
    """A points3d target whose view is one plane (not z = 0) is fitted as a plane (its own 2D axes);
    a non-planar view keeps its 3 coordinates."""
    rng = np.random.default_rng(0)
    P = rng.uniform(-50, 50, (30, 2))
    axes = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    plane = P @ axes[:, :2].T + np.array([5.0, -3.0, 100.0])
    flat = _view_points(plane)
    assert flat.shape == (30, 2)
    assert np.allclose(np.linalg.norm(flat[:, None] - flat[None], axis=2), np.linalg.norm(P[:, None] - P[None], axis=2))
    assert _view_points(plane + np.c_[np.zeros((30, 2)), rng.normal(0, 1.0, 30)]).shape == (30, 3)


def test_the_non_central_basis_makes_its_columns_for_any_centre():
    """zeta (s - e) and zeta (s - e) |s - e|^2 as combinations of the 12 basis vectors (their 9 parts)."""
    rng = np.random.default_rng(5)
    n = 40
    sx, sy, zeta = rng.normal(size=n), rng.normal(size=n), rng.normal(size=n)
    D = np.empty((RADIAL_VECTORS, n))
    none = np.empty((0, n))
    _radial_vectors(sx, sy, zeta, none, np.empty((0, 0)), np.empty(0, dtype=bool), D)  # nothing projected out
    basis = np.zeros((RADIAL_BASIS, 2, n))
    for c in range(RADIAL_BASIS):
        for k, index in enumerate((BASIS_U[c], BASIS_V[c])):
            if index >= 0:
                basis[c, k] = D[index]
    for e in (np.array([0.0, 0.0]), np.array([0.7, -2.5]), np.array([-40.0, 13.0])):
        alpha, gamma = np.empty(RADIAL_BASIS), np.empty(RADIAL_BASIS)
        _radial_coefficients(e, alpha, gamma)
        u = np.stack([sx - e[0], sy - e[1]])
        np.testing.assert_allclose(np.tensordot(alpha, basis, 1), zeta * u, atol=1e-12)
        np.testing.assert_allclose(np.tensordot(gamma, basis, 1), zeta * u * np.sum(u * u, axis=0),
                                   rtol=1e-12, atol=1e-9 * (1 + e @ e) ** 1.5)


def test_a_sparse_body_view_keeps_a_warp_high_enough_for_the_window():
    """25 corners per view of body3d_water (a random subset of each): W's degree is lowered to what 2 corners a
    term allow (3: a third of each view's coordinates left), not to 2 (3 corners a term), which left the floor
    2.3 px, 30 x the noise, the window's refraction unfitted."""
    scene = make_scene("body3d_water", seed=0, sigma_px=0.05)
    rng = np.random.default_rng(0)
    picked = []
    for o in scene.dataset.observations:
        keep = np.sort(rng.choice(len(o.ids), 25, replace=False))
        picked.append(replace(o, ids=o.ids[keep], pixels=o.pixels[keep]))
    floor = corner_floor(replace(scene.dataset, observations=tuple(picked)))
    assert 0.9 * 0.05 * SQRT2 < floor.rmse_px < 1.4 * 0.05 * SQRT2

"""Analytical initialisation: expansion centre (TLS lines + intersection), Eq. 5, Eq. 12."""
from __future__ import annotations

import numpy as np
import pytest

from ari_sfm.geometry import Pose, rotation_from_rotvec
from ari_sfm.init.expansion_center import (
    expansion_center,
    fit_line_tls,
    fit_lines,
    normal_from_expansion_center,
    trajectories,
)
from ari_sfm.init.interface_pose import real_cam_from_target, solve_eq12
from ari_sfm.models import ExactModel, PinholeModel
from ari_sfm.records import Observation, Target

K = np.array([[3478.0, 0, 1230.0], [0, 3478.0, 1015.0], [0, 0, 1]])


def _stacking(normal_cam, sigma, seed=0, model=ExactModel, outlier=False):
    rng = np.random.default_rng(seed)
    target = Target("checkerboard", 20.0, (11, 8))
    ids, P = target.points_3d()
    R = rotation_from_rotvec([0.05, -0.04, 0.02])
    X = P @ R.T + np.array([-100.0, -70.0, 400.0])
    obs = []
    for added in range(0, 60, 10):
        m = model(PinholeModel(K), normal_cam, 50.0 + added, 1.5168, 1.0, 40.0)
        uv = m.project(X) + rng.normal(0, sigma, (len(X), 2))
        if outlier:
            uv[5] += [30.0, -20.0]  # one corner mis-detected in every image
        obs.append(Observation("cam0", "stacking", "s0", ids, uv, added_mm=float(added)))
    return obs


def _normal(tilt_deg, azimuth=0.7):
    t = np.radians(tilt_deg)
    return np.array([np.sin(t) * np.cos(azimuth), np.sin(t) * np.sin(azimuth), np.cos(t)])


def test_tls_line_recovers_a_noisy_line():
    rng = np.random.default_rng(1)
    s = np.linspace(-50, 50, 6)
    d = np.array([0.6, 0.8])
    pts = np.array([3.0, 4.0]) + s[:, None] * d + rng.normal(0, 1e-3, (6, 2))
    _, direction, _, rms = fit_line_tls(pts)
    assert abs(abs(direction @ d) - 1) < 1e-9
    assert rms < 2e-3


@pytest.mark.parametrize("tilt", [0.02, 6.0, 20.0])
def test_expansion_center_is_the_projection_of_the_normal(tilt):
    """Exact Snell physics: corner tracks meet at e ~ K n within noise (sigma 0.05 px)."""
    n = _normal(tilt)
    truth = (K @ n / n[2])[:2]
    ec = expansion_center(_stacking(n, 0.05))
    err = np.linalg.norm(ec.center_px - truth)
    assert err < 1.0, err
    assert err < 5 * np.linalg.norm(ec.std_px) + 0.05  # the reported standard error is honest
    assert np.all(ec.std_px < 1.0)


def test_expansion_center_noise_free_is_exact():
    n = _normal(6.0)
    ec = expansion_center(_stacking(n, 0.0))
    assert np.linalg.norm(ec.center_px - (K @ n / n[2])[:2]) < 1e-6


def test_expansion_center_rejects_an_outlier_track():
    n = _normal(6.0)
    clean = expansion_center(_stacking(n, 0.05))
    dirty = expansion_center(_stacking(n, 0.05, outlier=True))
    # a constant offset keeps the track straight but moves its line; it must be rejected
    assert not dirty.inliers.all()
    assert np.linalg.norm(dirty.center_px - clean.center_px) < 0.2


def test_normal_from_expansion_center_is_eq5():
    n = _normal(7.0, 2.0)
    e = (K @ n / n[2])[:2]
    np.testing.assert_allclose(normal_from_expansion_center(e, K), n, atol=1e-12)


def test_eq12_solution_equals_the_shift_form():
    """Solving B = A T_WI (paper Eq. 12) gives R unchanged and t + delta n."""
    n = _normal(5.0)
    delta = 50.0 * (1 - 1 / 1.5168)
    A = np.hstack([np.eye(3), -delta * n[:, None]])  # X_app = X - delta n: [I | -delta n]
    T = Pose(rotation_from_rotvec([0.2, -0.1, 0.3]), np.array([10.0, -5.0, 400.0]))
    B = A @ T.matrix()
    sol = solve_eq12(A, B)
    np.testing.assert_allclose(sol.R, T.R, atol=1e-9)
    np.testing.assert_allclose(sol.t, T.t, atol=1e-9)
    generalised = Pose(B[:, :3], B[:, 3])
    shifted = real_cam_from_target(generalised, n, delta)
    np.testing.assert_allclose(shifted.t, T.t, atol=1e-9)


def test_degenerate_stacking_is_a_clear_error():
    """Tracks that do not move (no plates added) cannot locate the centre."""
    obs = _stacking(_normal(6.0), 0.0)[:1]
    obs = [obs[0], Observation("cam0", "stacking", "s0", obs[0].ids, obs[0].pixels.copy(), added_mm=10.0)]
    with pytest.raises(ValueError, match="trajector"):
        expansion_center(obs)


def test_tracks_and_lines_equal_the_per_corner_fits():
    """trajectories and fit_lines (vectorised over all corners, closed-form 2 x 2 TLS) against the per-corner
    dictionary and SVD fits they replaced (main e40d0d9), on records in another order with corners missing."""
    rng = np.random.default_rng(2)
    obs = []
    for o in _stacking(_normal(6.0), 0.05)[::-1]:
        keep = np.sort(rng.choice(len(o.ids), 60, replace=False))
        obs.append(Observation(o.camera, o.set, o.frame, o.ids[keep], o.pixels[keep], added_mm=o.added_mm))
    tracks = {}
    for o in obs:
        for i, px in zip(o.ids.tolist(), o.pixels):
            tracks.setdefault((o.frame, int(i)), []).append((float(o.added_mm or 0.0), px))
    ref = {k: np.array([p for _, p in sorted(v, key=lambda e: e[0])]) for k, v in tracks.items() if len(v) >= 2}
    ours = trajectories(obs)
    assert list(ours) == list(ref) and all(np.array_equal(ours[k], ref[k]) for k in ref)
    lines = fit_lines(obs)
    assert lines.id.tolist() == [i for _, i in ref]
    for k, pts in enumerate(ref.values()):
        centroid = pts.mean(axis=0)
        _, s, vt = np.linalg.svd(pts - centroid, full_matrices=False)
        np.testing.assert_allclose(lines.centroid[k], centroid, rtol=1e-14)
        assert abs(abs(lines.direction[k] @ vt[0]) - 1.0) < 1e-14
        assert lines.spread[k] == pytest.approx(s[0] ** 2, rel=1e-12)
        assert lines.rms_px[k] == pytest.approx(s[1] / np.sqrt(len(pts)), rel=1e-9)
        assert lines.offset[k] == pytest.approx(lines.normal[k] @ centroid, rel=1e-14)

"""Lens distortion and the window, both recovered; a free-distortion pinhole absorbs the
window on calibration views but the stacking observations expose it."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.calibration.evaluate import observation_residuals, residual_stats
from ari_sfm.geometry import angle_between_deg
from ari_sfm.init.zhang import object_points
from ari_sfm.simulate import make_scene

DIST = [-0.06, 0.08, 4e-4, -3e-4, 0.0]
FLOOR = 0.05 * np.sqrt(2)


@pytest.fixture(scope="module")
def distorted():
    return make_scene("paper_single", seed=0, dist=DIST)


def test_exact_with_distortion_recovers_lens_and_window(distorted):
    truth = distorted.truth
    K = np.array(truth["cameras"]["cam0"]["K"])
    cal = calibrate(distorted.dataset, model="exact", distortion=True)
    c = cal.cameras["cam0"]
    assert cal.residuals.rmse_px <= 1.2 * FLOOR
    assert abs(c.K[0, 0] / K[0, 0] - 1) < 5e-4
    assert angle_between_deg(cal.normal_world, truth["interface"]["normal_world"]) < 0.1
    assert abs(c.dist[0] - DIST[0]) < 0.005  # k1
    assert np.all(np.abs(c.dist[2:4] - DIST[2:4]) < 2e-4)  # p1 p2
    # k2 and k3 trade off over the field of view: compare the radial profile instead
    r2 = np.linspace(0, 0.12, 50)  # (r/f)^2 up to the image corner
    radial = lambda d: 1 + d[0] * r2 + d[1] * r2**2 + d[4] * r2**3  # noqa: E731
    assert np.max(np.abs(radial(c.dist) - radial(DIST))) < 2e-4
    assert "k1" in cal.uncertainty.cameras["cam0"].intrinsics


def test_without_distortion_terms_the_fit_fails(distorted):
    cal = calibrate(distorted.dataset, model="exact", distortion=False)
    assert cal.residuals.rmse_px > 3 * FLOOR


def test_free_distortion_pinhole_absorbs_the_window_but_not_the_stacking(single_scene):
    """PHYSICS.md: a pinhole with free distortion fits calibration views to ~0.08 px with the
    wrong geometry; one target pose cannot explain the stacking images without the window."""
    ds = single_scene.dataset
    views = ds.select("calibration")
    obj = [object_points(ds.target, v.ids).astype(np.float32) for v in views]
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, [v.pixels.astype(np.float32) for v in views],
                                             tuple(ds.cameras["cam0"].image_size), None, None)
    assert rms < 0.12  # the window is absorbed on the calibration views
    stack = ds.select("stacking")
    X = np.concatenate([object_points(ds.target, o.ids) for o in stack])
    uv = np.concatenate([o.pixels for o in stack])
    _, rvec, tvec = cv2.solvePnP(X, uv, K, dist)
    proj = cv2.projectPoints(X, rvec, tvec, K, dist)[0].reshape(-1, 2)
    stacking_rmse = float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, axis=1))))
    assert stacking_rmse > 10 * FLOOR, stacking_rmse
    ours = calibrate(ds, model="exact")
    stack_fit = residual_stats(r for _, r in observation_residuals(ours, stack, ds.target))
    assert stack_fit.rmse_px < 1.2 * FLOOR  # the window model explains the stacking

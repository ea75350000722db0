"""3D bodies seen in one view per camera, without a focal length hint (a lab's raw PTV calibration).

- a body too shallow for DLT starts from a resection over the focal length (principal point at the
  image centre) and calibrates to the noise floor with the focal length recovered;
- a principal point the views leave undetermined (one view of a sparse, shallow body) is held at the
  image centre and said so (``principal_point`` "auto"), which determines the rotations the free
  solution leaves loose; "free" and "centre" do what they say.
"""
from __future__ import annotations

import logging
import math
from dataclasses import replace

import pytest

from ari_sfm.calibration.calibrate import PRINCIPAL_POINT_MAX_SIGMA, CalibrationOptions, calibrate
from ari_sfm.init.zhang import focal_by_resection
from ari_sfm.simulate import ScenarioOverrides, make_scene


def _without_hints(dataset):
    return replace(dataset, cameras={n: replace(c, focal_px=None, K=None) for n, c in dataset.cameras.items()})


def test_focal_by_resection_is_an_apparent_focal_length():
    """A pinhole resection through a window into water sees the scene closer by the water's apparent depth:
    its focal length is the true one magnified, by less than the water's index (the start the bundle
    adjustment corrects: next test)."""
    scene = make_scene("body3d_shallow", seed=1, sigma_px=0.05)
    ds = _without_hints(scene.dataset)
    for cam in scene.geometry.cameras:
        f = focal_by_resection(ds.target, ds.cameras[cam.name], ds.select("calibration", cam.name))
        n_m = scene.geometry.window_of(cam.name).medium_index
        assert 1.1 * cam.K[0, 0] < f < 1.1 * n_m * cam.K[0, 0]


def test_a_shallow_body_without_hints_calibrates_to_the_floor():
    scene = make_scene("body3d_shallow", seed=1, sigma_px=0.05)
    cal = calibrate(_without_hints(scene.dataset), model="exact")
    assert cal.quality.ok and cal.residuals.rmse_px == pytest.approx(0.05 * math.sqrt(2), rel=0.05)
    for name, cam in cal.cameras.items():
        truth = scene.truth["cameras"][name]["K"]
        assert cam.K[0, 0] == pytest.approx(truth[0][0], rel=0.003)
        assert abs(cam.K[0, 2] - truth[0][2]) < 3 * cal.uncertainty.cameras[name].intrinsics["cx"] + 0.5


@pytest.fixture(scope="module")
def sparse_body():
    """One view of a 16-point body 3 mm deep at 600 mm, 1 px noise: the principal point is not determined."""
    return make_scene("body3d_water", seed=2, sigma_px=1.0,
                      overrides=ScenarioOverrides(depth_mm=3.0, distance_mm=600.0, cells=4, pitch_mm=40.0))


def test_an_undetermined_principal_point_is_held_and_said(sparse_body, caplog):
    ds = sparse_body.dataset
    free = calibrate(ds, model="exact", principal_point="free")
    limit = PRINCIPAL_POINT_MAX_SIGMA * max(ds.cameras["cam0"].image_size)
    loose = [n for n, s in free.uncertainty.cameras.items() if max(s.intrinsics["cx"], s.intrinsics["cy"]) > limit]
    assert loose  # the free solution leaves them undetermined
    with caplog.at_level(logging.WARNING, logger="ari_sfm.calibration.calibrate"):
        auto = calibrate(ds, model="exact")
    assert "held at the image centre" in caplog.text
    for name in loose:
        w, h = ds.cameras[name].image_size
        assert auto.cameras[name].K[0, 2] == pytest.approx((w - 1) / 2, abs=1e-3)
        assert auto.cameras[name].K[1, 2] == pytest.approx((h - 1) / 2, abs=1e-3)
    # holding what the view cannot tell determines the rotations the free solution leaves loose
    worst = lambda cal: max(s.rotation_deg for s in cal.uncertainty.cameras.values() if s.relative_pose)  # noqa: E731
    assert worst(auto) < 0.5 * worst(free)


def test_principal_point_modes(sparse_body):
    ds = sparse_body.dataset
    centre = calibrate(ds, model="exact", principal_point="centre", uncertainty=False)
    for name, cam in centre.cameras.items():
        w, h = ds.cameras[name].image_size
        assert (cam.K[0, 2], cam.K[1, 2]) == pytest.approx(((w - 1) / 2, (h - 1) / 2), abs=1e-3)
    with pytest.raises(ValueError, match="principal_point must be one of"):
        CalibrationOptions(principal_point="middle")

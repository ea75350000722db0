"""Multi-camera rigs behind one window (exact Snell simulations, sigma 0.05 px).

Tolerances: ari is paraxial, and cameras looking 10-15 deg obliquely through
the window limit it (an independent reference: ~1.7 deg relative rotation,
~1 deg normal on the binocular rig), so it must only converge near the truth;
exact must reach the noise floor.
"""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import Pose, angle_between_deg, rotation_angle_deg
from ari_sfm.io import calibration_to_json
from ari_sfm.simulate import make_scene

FLOOR = 0.05 * np.sqrt(2)


def rig_errors(cal, truth) -> dict:
    out = {"normal_deg": angle_between_deg(cal.normal_world, truth["interface"]["normal_world"]), "cameras": {}}
    for name, c in cal.cameras.items():
        t = truth["cameras"][name]
        K = np.array(t["K"])
        pose = Pose.from_json(t["cam_from_world"])
        out["cameras"][name] = {
            "fx_rel": abs(c.K[0, 0] / K[0, 0] - 1), "fy_rel": abs(c.K[1, 1] / K[1, 1] - 1),
            "rotation_deg": rotation_angle_deg(c.cam_from_world.R, pose.R),
            "translation_mm": float(np.linalg.norm(c.cam_from_world.inverse().t - pose.inverse().t)),
        }
    if cal.interface.distance_mm is not None:
        out["distance_mm"] = abs(cal.interface.distance_mm - truth["interface"]["distance_mm"])
    return out


def assert_exact_tolerances(cal, truth):
    e = rig_errors(cal, truth)
    assert cal.residuals.rmse_px <= 1.2 * FLOOR, cal.residuals
    assert e["normal_deg"] < 0.1, e
    for name, c in e["cameras"].items():
        assert c["fx_rel"] < 5e-4 and c["fy_rel"] < 5e-4, (name, c)
        assert c["rotation_deg"] < 0.03 and c["translation_mm"] < 0.1, (name, c)
    return e


@pytest.fixture(scope="module")
def binocular():
    return make_scene("binocular", seed=0)


def test_binocular_ari_converges(binocular):
    cal = calibrate(binocular.dataset, model="ari")
    e = rig_errors(cal, binocular.truth)
    assert e["normal_deg"] < 2.0, e
    assert e["cameras"]["cam1"]["rotation_deg"] < 3.0, e


def test_binocular_exact_reaches_the_noise_floor(binocular):
    cal = calibrate(binocular.dataset, model="exact")
    assert_exact_tolerances(cal, binocular.truth)
    assert cal.interface.distance_mm is None  # unobservable with air behind the plate


def test_underwater_exact_recovers_the_window_distance():
    scene = make_scene("binocular_underwater", seed=0)
    cal = calibrate(scene.dataset, model="exact")
    e = assert_exact_tolerances(cal, scene.truth)
    assert e["distance_mm"] < 1.0, e
    assert abs(cal.distance_mm("cam1") - scene.truth["cameras"]["cam1"]["distance_mm"]) < 1.0


def test_arc4_partial_visibility_all_cameras_exact():
    scene = make_scene("arc4", seed=0)
    cal = calibrate(scene.dataset, model="exact")
    assert_exact_tolerances(cal, scene.truth)


def test_initialisation_threads_do_not_change_the_result():
    """initialise_rig runs the cameras' initialisations on a thread pool (OpenCV on one
    thread in each): bit-identical to one by one, and the caller's cv2 thread count is back."""
    import cv2

    from ari_sfm.init.rig import initialise_rig

    ds = make_scene("arc4", seed=0).dataset
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(3)
        serial, pooled = initialise_rig(ds, workers=1), initialise_rig(ds, workers=4)
        assert cv2.getNumThreads() == 3
    finally:
        cv2.setNumThreads(before)
    assert list(pooled.cameras) == list(serial.cameras) == list(ds.camera_names)
    for n, c in serial.cameras.items():
        p = pooled.cameras[n]
        assert np.array_equal(c.K, p.K) and np.array_equal(c.normal_cam, p.normal_cam)
        assert c.zhang_rms_px == p.zhang_rms_px
        assert list(c.cam_from_target) == list(p.cam_from_target)
        for f, pose in c.cam_from_target.items():
            assert np.array_equal(pose.R, p.cam_from_target[f].R) and np.array_equal(pose.t, p.cam_from_target[f].t)
    for n, pose in serial.cam_from_world.items():
        assert np.array_equal(pose.R, pooled.cam_from_world[n].R) and np.array_equal(pose.t, pooled.cam_from_world[n].t)
    assert np.array_equal(serial.normal_world, pooled.normal_world)


def test_camera_sharing_no_frame_is_named(binocular):
    """A camera that shares no frame with the others is a clear error naming it."""
    ds = binocular.dataset
    obs = tuple(replace(o, frame=o.frame + "_alone") if o.camera == "cam1" else o for o in ds.observations)
    with pytest.raises(AriSfmError, match="cam1"):
        calibrate(replace(ds, observations=obs), model="ari")


def test_uncertainty_matches_the_spread_over_noise_seeds(binocular):
    """Marginal standard deviations agree with the scatter over 20 noise draws within a factor 1.5."""
    errors, predicted = [], []
    truth = binocular.truth
    t_pose = Pose.from_json(truth["cameras"]["cam1"]["cam_from_world"])
    for seed in range(20):
        rng = np.random.default_rng(1000 + seed)
        obs = tuple(replace(o, pixels=o.pixels + rng.normal(0, 0.05, o.pixels.shape))
                    for o in binocular.exact_observations)
        cal = calibrate(replace(binocular.dataset, observations=obs), model="exact")
        u = cal.uncertainty
        c1 = cal.cameras["cam1"]
        errors.append([
            cal.cameras["cam0"].K[0, 0] - truth["cameras"]["cam0"]["K"][0][0],
            cal.cameras["cam1"].K[1, 2] - truth["cameras"]["cam1"]["K"][1][2],
            angle_between_deg(cal.normal_world, truth["interface"]["normal_world"]),
            rotation_angle_deg(c1.cam_from_world.R, t_pose.R),
            float(np.linalg.norm(c1.cam_from_world.inverse().t - t_pose.inverse().t)),
        ])
        predicted.append([u.cameras["cam0"].intrinsics["fx"], u.cameras["cam1"].intrinsics["cy"], u.normal_deg,
                          u.cameras["cam1"].rotation_deg, u.cameras["cam1"].translation_mm])
    rms = np.sqrt(np.mean(np.square(errors), axis=0))  # magnitudes: RMS of the error (truth is known)
    pred = np.mean(predicted, axis=0)
    ratio = rms / pred
    assert np.all(ratio > 1 / 1.5) and np.all(ratio < 1.5), dict(zip(["fx", "cy", "normal", "rot", "trans"], ratio))


def test_uncertainty_is_finite_or_none_and_valid_json():
    """Paraxial ari under water barely constrains the window distance (its marginal variance can come out
    negative numerically): the std is then None with a warning, never NaN, and calibration.json stays JSON."""
    scene = make_scene("binocular_underwater", seed=0)
    cal = calibrate(scene.dataset, model="ari")
    u = cal.uncertainty
    assert u.estimates_distance  # under water
    values = [u.normal_deg, u.distance_mm] + [v for c in u.cameras.values() for v in c.to_json().values()]
    assert all(v is None or (np.isfinite(v) and v >= 0) for v in values), u
    json.dumps(calibration_to_json(cal), allow_nan=False)

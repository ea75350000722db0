"""3D calibration bodies (type points3d): DLT / PnP initialisation instead of Zhang."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.geometry import Pose, angle_between_deg
from ari_sfm.models import ExactModel, PinholeModel
from ari_sfm.records import CameraSpec, Observation, Target


def _two_level_body() -> Target:
    """A stepped plate: 11 x 8 points, 10 mm pitch, the lower four rows 15 mm higher."""
    pts = {}
    for r in range(8):
        for c in range(11):
            pts[r * 11 + c] = (c * 10.0, r * 10.0, -15.0 if r >= 4 else 0.0)
    return Target(type="points3d", points=pts)


@pytest.fixture(scope="module")
def body_scene(single_scene):
    """The paper_single rig and poses, observing a 3D body instead of the board."""
    truth = single_scene.truth
    target = _two_level_body()
    ids, P = target.points_3d()
    cam = truth["cameras"]["cam0"]
    K = np.array(cam["K"])
    iface = truth["interface"]
    rng = np.random.default_rng(5)
    obs = []
    for o in single_scene.dataset.observations:
        pose = Pose.from_json(truth["frames"][o.frame]["world_from_target"])
        model = ExactModel(PinholeModel(K), np.array(cam["normal_cam"]), iface["thickness_mm"] + (o.added_mm or 0.0),
                           iface["index"], 1.0, iface["distance_mm"])
        uv = model.project(pose.apply(P)) + rng.normal(0, 0.05, (len(P), 2))
        obs.append(Observation(o.camera, o.set, o.frame, ids, uv, o.added_mm))
    return replace(single_scene.dataset, target=target, observations=tuple(obs)), truth


def test_points3d_without_hint_by_dlt(body_scene):
    ds, truth = body_scene
    cal = calibrate(ds, model="exact")
    K = np.array(truth["cameras"]["cam0"]["K"])
    assert abs(cal.cameras["cam0"].K[0, 0] / K[0, 0] - 1) < 5e-4
    assert angle_between_deg(cal.normal_world, truth["interface"]["normal_world"]) < 0.1
    assert cal.residuals.rmse_px < 1.2 * 0.05 * np.sqrt(2)


def test_points3d_with_known_K_held_fixed(body_scene):
    ds, truth = body_scene
    K = np.array(truth["cameras"]["cam0"]["K"])
    spec = ds.cameras["cam0"]
    ds = replace(ds, cameras={"cam0": CameraSpec(spec.name, spec.image_size, None, K, None)})
    cal = calibrate(ds, model="exact", fix_intrinsics=True)
    np.testing.assert_allclose(cal.cameras["cam0"].K, K, atol=1e-6)
    assert angle_between_deg(cal.normal_world, truth["interface"]["normal_world"]) < 0.1

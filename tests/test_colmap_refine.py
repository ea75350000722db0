"""refine-colmap: the exact refractive refinement of a COLMAP reconstruction made behind a window.

Truth from ari_sfm.simulate.port_survey (exact Snell physics); COLMAP's side is pycolmap's own
bundle adjustment (PINHOLE cameras) of a model built from the simulated correspondences.
"""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.colmap import adapter
from ari_sfm.colmap.refine import refine_colmap, write_refined
from ari_sfm.colmap.refine.problem import RefractiveProblem, State
from ari_sfm.colmap.refine.solver import Solver
from ari_sfm.colmap.refine.truth import colmap_truth_errors, truth_errors, window_errors
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import Pose
from ari_sfm.io import load_calibration
from ari_sfm.simulate.port_survey import port_survey, tank_rig

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def colmap_start(truth, focal_scale: float):
    """The model COLMAP would hold: PINHOLE cameras (focal times ``focal_scale``) at the simulated
    correspondences, then pycolmap's own bundle adjustment (its pinhole optimum)."""
    params = [np.r_[p[:2] * focal_scale, p[2:4]] for p in truth.params]
    rec = adapter.reconstruction_from_arrays(params, truth.image_size, truth.sensor_from_rig, truth.rig_from_world,
                                             truth.image_camera, truth.image_frame, truth.xyz, truth.obs_image,
                                             truth.obs_point, truth.obs_uv)
    return rec, adapter.bundle_adjust(rec)


def truth_state(truth, model) -> State:
    """The simulated truth as a refinement state (COLMAP PINHOLE parameters: pixel origin + 0.5)."""
    params = tuple(np.r_[p[:2], p[2:4] + adapter.COLMAP_PIXEL_OFFSET] for p in truth.params)
    sensors = tuple(truth.sensor_from_rig[c] for c in truth.image_camera)
    if truth.mount == "camera":
        normals, dists = np.array(truth.normal_cam), np.array(truth.distance_mm)
    else:
        normals, dists = truth.normal_world[None, :], np.array([truth.plane_mm])
    return State(params, truth.rig_from_world, sensors, normals, dists, truth.xyz[model.point3D_ids - 1].copy())


def poses_of(state: State, model) -> dict[int, Pose]:
    R, t = state.cam_from_world(model)
    return {int(i): Pose(R[k], t[k]) for k, i in enumerate(model.image_ids)}


def noise_limited(truth, rec, mount: str) -> dict:
    """Errors of the same refinement started at the truth: what the noise alone leaves."""
    model = adapter.model_from_reconstruction(rec)
    problem = RefractiveProblem(model, truth.interface, mount, estimate_distance=True)
    res = Solver(problem, 2.0).run(truth_state(truth, model), 50)
    e = np.linalg.norm(problem.residuals(res.state), axis=1)
    out = truth_errors(truth, model, res.state.xyz, poses_of(res.state, model))
    out.update(window_errors(truth, res.state.normals, res.state.distances, res.state.rig_from_world[0]))
    out["rms_px"] = float(np.sqrt(np.mean(e ** 2)))
    return out


# ----------------------------------------------------------------------------- Jacobians

@pytest.mark.parametrize("mount", ["camera", "world"])
def test_jacobians_match_central_differences(mount):
    truth = (port_survey(num_images=5, num_points=150, focal_px=1300, area_mm=(1500, 1000)) if mount == "camera"
             else tank_rig(num_frames=3, num_points=120))
    rec = adapter.reconstruction_from_arrays(list(truth.params), truth.image_size, truth.sensor_from_rig,
                                             truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz,
                                             truth.obs_image, truth.obs_point, truth.obs_uv)
    model = adapter.model_from_reconstruction(rec)
    problem = RefractiveProblem(model, truth.interface, mount, estimate_distance=True)
    state = truth_state(truth, model)
    lin = problem.linearize(state)
    assert np.allclose(lin.residuals, problem.residuals(state))
    rng = np.random.default_rng(3)
    scale = np.ones(problem.layout.size)
    for ix in problem.layout.intrinsics:
        scale[ix] = 1e3  # pixels-sized intrinsics take bigger steps
    for _ in range(3):
        dg = rng.normal(0.0, 1e-6, problem.layout.size) * scale
        dp = rng.normal(0.0, 1e-5, state.xyz.shape)
        numeric = (problem.residuals(problem.retract(state, dg, dp))
                   - problem.residuals(problem.retract(state, -dg, -dp))) / 2.0
        analytic = (np.einsum("nij,nj->ni", lin.J_g, np.append(dg, 0.0)[lin.index])
                    + np.einsum("nij,nj->ni", lin.J_p, dp[model.obs_point]))
        assert np.max(np.abs(numeric - analytic)) < 1e-6 * np.max(np.abs(analytic))


# ----------------------------------------------------------------------------- recovery of the truth

def scale_bar_of(truth, model) -> tuple[int, int, float]:
    """Two far-apart points and their true distance (a scale bar a surveyor would place)."""
    X = truth.xyz[model.point3D_ids - 1]
    a, b = int(np.argmin(X[:, 0] + X[:, 1])), int(np.argmax(X[:, 0] + X[:, 1]))
    return int(model.point3D_ids[a]), int(model.point3D_ids[b]), float(np.linalg.norm(X[a] - X[b]))


def refined_errors(truth, start, result) -> dict:
    model = adapter.model_from_reconstruction(start)
    out = truth_errors(truth, model, result.state.xyz, poses_of(result.state, model))
    out.update(window_errors(truth, result.state.normals, result.state.distances, result.state.rig_from_world[0]))
    return out


@pytest.fixture(scope="module")
def survey():
    """A camera in a flat-port housing (22 mm, 8 mm acrylic, water), 10 images over a relief at 2 m,
    sigma 0.5 px; COLMAP's pinhole optimum of it, the refinement with a scale bar, and the
    noise-limited errors (the same refinement started at the truth)."""
    truth = port_survey(num_images=10, num_points=800, focal_px=1300, area_mm=(1800, 1200), sigma_px=0.5)
    _, start = colmap_start(truth, truth.interface.medium_index)
    model = adapter.model_from_reconstruction(start)
    result = refine_colmap(start, truth.interface, "camera", scale_bar=scale_bar_of(truth, model))
    return truth, start, result, noise_limited(truth, start, "camera")


def test_survey_points_and_cameras_recovered(survey):
    truth, start, result, limit = survey
    got, colmap = refined_errors(truth, start, result), colmap_truth_errors(truth, start)
    assert got["points_rms_mm"] <= 3.0 * limit["points_rms_mm"]
    assert colmap["points_rms_mm"] > 10.0 * got["points_rms_mm"]  # the pinhole optimum is wrong in shape
    assert got["centres_rms_mm"] <= 3.0 * limit["centres_rms_mm"]
    assert abs(got["scale_error_pct"]) < 0.5  # the scale bar holds the scale


def test_survey_reprojection_at_noise_floor(survey):
    truth, _, result, limit = survey
    after = result.report.after.rms_px
    assert after <= 1.02 * limit["rms_px"]
    assert after <= truth.sigma_px * np.sqrt(2.0)  # the floor sigma sqrt(2) less the fitted dofs
    assert result.report.before.rms_px > 2.0 * after


def test_survey_port_recovered(survey):
    truth, start, result, limit = survey
    got = refined_errors(truth, start, result)
    assert got["normal_deg"] <= 3.0 * limit["normal_deg"] + 0.02
    assert got["distance_mm"] <= 3.0 * limit["distance_mm"] + 1.0
    fx_true = truth.params[0][0]
    assert abs(result.state.colmap_params[0][0] / fx_true - 1.0) < 0.005  # the lens focal, not n_m times it


def test_world_mount_two_camera_rig():
    """A 2-camera rig moved along a tank wall (one window fixed in the world)."""
    truth = tank_rig(num_frames=6, num_points=400)
    _, start = colmap_start(truth, 1.0)
    model = adapter.model_from_reconstruction(start)
    result = refine_colmap(start, truth.interface, "world", scale_bar=scale_bar_of(truth, model))
    limit = noise_limited(truth, start, "world")
    got, colmap = refined_errors(truth, start, result), colmap_truth_errors(truth, start)
    assert got["points_rms_mm"] <= 3.0 * limit["points_rms_mm"]
    assert colmap["points_rms_mm"] > 5.0 * got["points_rms_mm"]
    assert got["normal_deg"] <= 3.0 * limit["normal_deg"] + 0.02
    assert got["distance_mm"] <= 3.0 * limit["distance_mm"] + 1.0
    assert result.report.after.rms_px <= 1.02 * limit["rms_px"]
    # the rig's second sensor: refined relative pose close to the truth
    sensor = result.state.sensor_from_rig[int(np.flatnonzero(model.image_camera == 1)[0])]
    assert np.linalg.norm(sensor.inverse().t - truth.sensor_from_rig[1].inverse().t) < 3.0


# ----------------------------------------------------------------------------- CLI, outputs, bad input

WINDOW_YAML = """interface:
  thickness_mm: 8
  index: 1.49
  medium_index: 1.333
mount: camera
"""


@pytest.fixture(scope="module")
def small_model(tmp_path_factory):
    truth = port_survey(num_images=6, num_points=300, focal_px=1300, area_mm=(1200, 800), sigma_px=0.3)
    _, start = colmap_start(truth, truth.interface.medium_index)
    folder = tmp_path_factory.mktemp("colmap") / "sparse"
    folder.mkdir()
    start.write(str(folder))
    return truth, start, folder


def test_cli_writes_model_calibration_and_report(small_model, tmp_path):
    truth, start, folder = small_model
    (tmp_path / "WINDOW.yaml").write_text(WINDOW_YAML)
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["refine-colmap", str(folder), "--window", str(tmp_path / "WINDOW.yaml"),
                                    "-o", str(out)])
    assert res.exit_code == 0, res.output
    rec = adapter.read_colmap(out)
    assert sorted(rec.images) == sorted(start.images) and sorted(rec.point3D_ids()) == sorted(start.point3D_ids())
    assert rec.compute_mean_reprojection_error() < 1.0  # COLMAP's own cameras (OPENCV) fit the refined points
    report = __import__("json").loads((out / "refine.json").read_text())
    assert set(report["before"]["per_image_rms_px"]) == {str(i) for i in start.images}
    cal = load_calibration(out / "calibration.json")
    exact = cal.projection_model("camera1")
    h = report["window"]["distance_mm"]["camera1"]
    assert exact.distance_mm == pytest.approx(h)
    assert np.allclose(exact.normal_cam, report["window"]["normal_cam"]["camera1"])
    # the calibration's exact camera, at the image poses it records, reproduces the observations
    poses = cal.refine_colmap.images_cam_from_world
    model = adapter.model_from_reconstruction(rec)
    k = 0
    pose = poses[int(model.image_ids[k])]
    sel = model.obs_image == k
    uv = exact.project(pose.apply(model.xyz[model.obs_point[sel]]))
    assert np.sqrt(np.mean(np.sum((uv - model.obs_uv[sel]) ** 2, axis=1))) < 3 * truth.sigma_px


@pytest.mark.parametrize("text, message", [
    ("interface:\n  index: 1.49\nmount: camera\n", "missing key 'interface.thickness_mm'"),
    ("interface:\n  thickness_mm: 8\n  index: 1.49\n", "missing key 'mount'"),
    ("interface:\n  thickness_mm: 8\n  index: 1.49\nmount: housing\n", "mount must be one of camera, world"),
])
def test_bad_window_yaml_one_line(small_model, tmp_path, text, message):
    _, _, folder = small_model
    (tmp_path / "WINDOW.yaml").write_text(text)
    res = CliRunner().invoke(main, ["refine-colmap", str(folder), "--window", str(tmp_path / "WINDOW.yaml"),
                                    "-o", str(tmp_path / "out")])
    assert res.exit_code == 1
    lines = res.output.strip().splitlines()
    assert lines[-1].startswith("error: ") and "WINDOW.yaml" in lines[-1] and message in lines[-1]
    assert not (tmp_path / "out").exists()


def test_model_without_points_one_line(small_model, tmp_path):
    _, start, _ = small_model
    empty = adapter.pycolmap.Reconstruction(start)
    for pid in list(empty.point3D_ids()):
        empty.delete_point3D(pid)
    (tmp_path / "m").mkdir()
    empty.write(str(tmp_path / "m"))
    (tmp_path / "WINDOW.yaml").write_text(WINDOW_YAML)
    res = CliRunner().invoke(main, ["refine-colmap", str(tmp_path / "m"), "--window", str(tmp_path / "WINDOW.yaml"),
                                    "-o", str(tmp_path / "out")])
    assert res.exit_code == 1 and "no points3D" in res.output.strip().splitlines()[-1]


def test_camera_model_that_cannot_be_held(small_model):
    truth, start, _ = small_model
    rec = adapter.pycolmap.Reconstruction(start)
    cam = rec.camera(1)
    cam.model = adapter.pycolmap.CameraModelId.OPENCV_FISHEYE
    cam.params = np.r_[cam.params[:4], 0.0, 0.0, 0.0, 0.0]
    with pytest.raises(AriSfmError, match="OPENCV_FISHEYE cannot be held"):
        refine_colmap(rec, truth.interface, "camera")


# ----------------------------------------------------------------------------- GTSAM backend

@pytest.mark.parametrize("mount", ["camera", "world"])
def test_gtsam_backend_same_answer(mount):
    """numpy (points Schur) and GTSAM (one CustomFactor per image) from the same perturbed start reach
    the same optimum: residuals, window and the point cloud's shape. The scale is compared after
    similarity alignment: it is a near-flat direction of the cost that the two LMs walk differently."""
    from ari_sfm.colmap.refine.gtsam_graph import GtsamRefinement
    from ari_sfm.colmap.refine.truth import similarity

    truth = (port_survey(num_images=6, num_points=120, focal_px=1300, area_mm=(1200, 800), sigma_px=0.2)
             if mount == "camera" else tank_rig(num_frames=3, num_points=100))
    rec = adapter.reconstruction_from_arrays(list(truth.params), truth.image_size, truth.sensor_from_rig,
                                             truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz,
                                             truth.obs_image, truth.obs_point, truth.obs_uv)
    model = adapter.model_from_reconstruction(rec)
    problem = RefractiveProblem(model, truth.interface, mount, estimate_distance=True)
    rng = np.random.default_rng(1)
    start = problem.retract(truth_state(truth, model), rng.normal(0.0, 1e-3, problem.layout.size),
                            rng.normal(0.0, 0.5, (len(model.point3D_ids), 3)))
    ours = Solver(problem, 2.0).run(start, 100).state
    theirs, _ = GtsamRefinement(problem, 2.0).optimize(start, 12)
    assert np.max(np.abs(problem.residuals(ours) - problem.residuals(theirs))) < 1e-4
    assert np.max(np.abs(ours.normals - theirs.normals)) < 1e-5
    s, R, t = similarity(theirs.xyz, ours.xyz)
    assert np.max(np.abs(s * theirs.xyz @ R.T + t - ours.xyz)) < 1e-3  # mm
    assert abs(s - 1.0) < 0.01


# ----------------------------------------------------------------------------- end to end: images -> COLMAP -> refine

def test_end_to_end_rendered_survey_through_colmap_sift(tmp_path):
    """12 rendered 640 x 480 images of a relief behind a flat port (exact physics), COLMAP's own CPU SIFT,
    exhaustive matching and incremental mapping, then refine-colmap. Scale from a known baseline (the
    first and last camera centres, as navigation would give); errors after similarity alignment of the
    camera centres; the points are judged by their height above/below the true relief."""
    import json

    from ari_sfm.colmap.refine.truth import similarity
    from ari_sfm.records import Interface
    from ari_sfm.simulate.port_survey import relief_height, write_port_survey

    truth, images = write_port_survey(tmp_path / "survey", num_images=12, supersample=1)
    rec = adapter.structure_from_motion(images, tmp_path / "colmap", focal_px=600 * 1.333, max_features=1000)
    assert rec.num_reg_images() >= 10
    meta = json.loads((tmp_path / "survey" / "truth.json").read_text())
    model = adapter.model_from_reconstruction(rec)
    names = [rec.image(int(i)).name for i in model.image_ids]
    true_centres = np.array([Pose.from_json(meta["images"][n]).inverse().t for n in names])

    def errors(xyz, poses):
        centres = np.array([poses[int(i)].inverse().t for i in model.image_ids])
        s, R, t = similarity(centres, true_centres)
        X = s * xyz @ R.T + t
        return (float(np.sqrt(np.mean(np.sum((s * centres @ R.T + t - true_centres) ** 2, axis=1)))),
                float(np.sqrt(np.mean((X[:, 2] - relief_height(X[:, :2], 2000.0, 150.0)) ** 2))))

    colmap_poses = {int(i): Pose(np.array(rec.image(int(i)).cam_from_world().rotation.matrix()),
                                 np.array(rec.image(int(i)).cam_from_world().translation)) for i in model.image_ids}
    interface = Interface(**meta["interface"])
    # COLMAP's units are arbitrary (the scene is a few units deep): one line asks for units_mm or a scale bar
    with pytest.raises(AriSfmError, match="give units_mm .* or a scale_bar"):
        refine_colmap(rec, interface, "camera", max_iterations=30)
    # a scale bar between two far-apart points3D, their true positions from one observation each
    # (back-projected through the true camera onto the relief)
    from ari_sfm.simulate.port_survey import _hit_relief, port_survey

    sim = port_survey(seed=0, num_images=12, num_points=10, image_size=(640, 480), focal_px=600.0,
                      area_mm=(1600.0, 1200.0), min_views=1)  # write_port_survey's cameras
    along = (model.xyz - model.xyz.mean(axis=0)) @ np.linalg.svd(model.xyz - model.xyz.mean(axis=0))[2][0]
    ends = []
    for k in (int(np.argmin(along)), int(np.argmax(along))):
        o = int(np.flatnonzero(model.obs_point == k)[0])
        i = int(names[model.obs_image[o]][5:9]) - 1
        origin, direction = sim.model(i).backproject(model.obs_uv[o][None])
        world = sim.cam_from_world(i).inverse()
        ends.append(_hit_relief(world.apply(origin), direction @ world.R.T, 2000.0, 150.0)[0])
    bar = (int(model.point3D_ids[np.argmin(along)]), int(model.point3D_ids[np.argmax(along)]),
           float(np.linalg.norm(ends[0] - ends[1])))
    result = refine_colmap(rec, interface, "camera", scale_bar=bar, max_iterations=30)
    centres_before, surface_before = errors(model.xyz, colmap_poses)
    centres_after, surface_after = errors(result.state.xyz, poses_of(result.state, model))
    centres = np.array([poses_of(result.state, model)[int(i)].inverse().t for i in model.image_ids])
    assert abs(similarity(centres, true_centres)[0] - 1.0) < 0.005  # the bar holds the scale (was 35 % off)
    u = result.report.uncertainty
    assert abs(result.state.distances[0] - meta["camera"]["distance_mm"]) < 3.0 * u.distance_mm["camera1"]
    assert centres_after < 3.0 and surface_after < 5.0  # mm: SIFT-noise-limited
    assert centres_before > 10.0 * centres_after and surface_before > 10.0 * surface_after
    assert result.report.after.rms_px < 0.6 * result.report.before.rms_px
    from ari_sfm.geometry import angle_between_deg

    assert angle_between_deg(result.state.normals[0], np.array(meta["camera"]["normal_cam"])) < 0.6


def test_window_yaml_scale_bar_and_units(tmp_path):
    from ari_sfm.colmap.refine.window import load_window

    path = tmp_path / "WINDOW.yaml"
    path.write_text(WINDOW_YAML + "scale_bar:\n  point3D_ids: [12, 873]\n  distance_mm: 500\n")
    spec = load_window(path)
    assert spec.scale_bar == (12, 873, 500.0) and spec.mount == "camera"
    assert spec.interface.medium_index == pytest.approx(1.333)
    path.write_text(WINDOW_YAML + "units_mm: -2\n")
    with pytest.raises(AriSfmError, match="units_mm"):
        load_window(path)


# ----------------------------------------------------------------------------- a declared window (interface.plane)

def declared(truth, sigma_deg: float = 0.0, sigma_mm: float = 0.0, tilt_deg: float = 0.0, offset_mm: float = 0.0):
    """The simulated housing's port as a WindowPlane in the camera frame, optionally moved (tilted about
    the camera's x axis, the face shifted along the normal)."""
    from ari_sfm.geometry import rotation_from_rotvec
    from ari_sfm.records import WindowPlane

    n = rotation_from_rotvec([np.radians(tilt_deg), 0.0, 0.0]) @ truth.normal_cam[0]
    return WindowPlane("camera", n, n * (truth.distance_mm[0] + offset_mm), sigma_deg, sigma_mm)


def test_declared_plane_held_is_the_window(survey):
    """The true port declared and held: the window is the truth, not estimated, and the points are at
    least as accurate as when the window is estimated."""
    from dataclasses import replace

    truth, start, free, _ = survey
    model = adapter.model_from_reconstruction(start)
    held = refine_colmap(start, replace(truth.interface, plane=declared(truth)), "camera",
                         scale_bar=scale_bar_of(truth, model))
    assert np.allclose(held.state.normals[0], truth.normal_cam[0], atol=1e-12)
    assert held.state.distances[0] == pytest.approx(truth.distance_mm[0], abs=1e-9)
    assert "none: held at the declared plane" in held.report.estimated
    got, without = refined_errors(truth, start, held), refined_errors(truth, start, free)
    assert got["points_rms_mm"] <= 1.02 * without["points_rms_mm"]
    assert got["centres_rms_mm"] <= 1.05 * without["centres_rms_mm"] + 0.1
    assert held.report.after.rms_px <= truth.sigma_px * np.sqrt(2.0)


def test_declared_plane_prior_pulls_as_its_sigma_shrinks(small_model):
    """A plane declared 1 deg and 6 mm off the truth with a prior: the refined window moves toward it
    as the sigmas shrink, and a tight prior lands on it."""
    from dataclasses import replace

    from ari_sfm.geometry import angle_between_deg

    truth, start, _ = small_model
    angles, offsets = [], []
    for sigma_deg, sigma_mm in ((5.0, 50.0), (0.2, 2.0), (0.002, 0.02)):
        plane = declared(truth, sigma_deg, sigma_mm, tilt_deg=1.0, offset_mm=6.0)
        res = refine_colmap(start, replace(truth.interface, plane=plane), "camera", units_mm=1.0)
        angles.append(angle_between_deg(res.state.normals[0], plane.normal))
        offsets.append(abs(res.state.distances[0] - plane.normal @ plane.point_mm))
        assert "prior" in res.report.plane.normal and "prior" in res.report.plane.distance
    assert angles[0] > angles[1] > angles[2] and offsets[0] > offsets[1] > offsets[2]
    # the images alone pull the normal well away from the wrong plane (the distance, started there, weakly)
    assert angles[0] > 0.3 and offsets[0] > 0.2
    assert angles[2] < 0.01 and offsets[2] < 0.1


@pytest.mark.parametrize("held_normal", [False, True])
def test_declared_plane_prior_same_on_gtsam(held_normal):
    """The plane's prior (and a held normal) in the numpy LM and in the GTSAM graph: the same optimum."""
    from ari_sfm.colmap.refine.gtsam_graph import GtsamRefinement
    from ari_sfm.colmap.refine.plane import window_prior

    truth = port_survey(num_images=6, num_points=120, focal_px=1300, area_mm=(1200, 800), sigma_px=0.2)
    rec = adapter.reconstruction_from_arrays(list(truth.params), truth.image_size, truth.sensor_from_rig,
                                             truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz,
                                             truth.obs_image, truth.obs_point, truth.obs_uv)
    model = adapter.model_from_reconstruction(rec)
    plane = declared(truth, 0.0 if held_normal else 0.3, 1.5, tilt_deg=0.5, offset_mm=3.0)
    problem = RefractiveProblem(model, truth.interface, "camera", estimate_distance=True, hold_normal=held_normal)
    prior = window_prior(plane, True)
    start = truth_state(truth, model)
    if held_normal:
        start = State(start.colmap_params, start.rig_from_world, start.sensor_from_rig, plane.normal[None, :],
                      start.distances, start.xyz)
    rng = np.random.default_rng(2)
    start = problem.retract(start, rng.normal(0.0, 1e-3, problem.layout.size),
                            rng.normal(0.0, 0.5, (len(model.point3D_ids), 3)))
    ours = Solver(problem, 2.0, prior).run(start, 100).state
    theirs, _ = GtsamRefinement(problem, 2.0, prior).optimize(start, 50)
    assert np.max(np.abs(ours.normals - theirs.normals)) < 1e-5
    assert abs(ours.distances[0] - theirs.distances[0]) < 1e-3
    # a flat valley (the scale): both stop within 1e-5 of the same cost, residuals within 1 % of sigma
    solver = Solver(problem, 2.0, prior)
    assert abs(solver.cost(ours) - solver.cost(theirs)) < 1e-5 * solver.cost(ours)
    assert np.max(np.abs(problem.residuals(ours) - problem.residuals(theirs))) < 0.01 * truth.sigma_px
    assert solver.cost(ours) < solver.cost(start)
    if held_normal:
        assert np.array_equal(ours.normals, start.normals) and np.array_equal(theirs.normals, start.normals)


PLANE_YAML = WINDOW_YAML.replace("mount: camera\n", "") + "  plane:\n{plane}mount: {mount}\n"


@pytest.mark.parametrize("plane, mount, message", [
    ("    frame: f000\n    normal: [0, 0, 1]\n    point_mm: [0, 0, 22]\n", "camera", "interface.plane.frame"),
    ("    normal: [0, 0, 2]\n    point_mm: [0, 0, 22]\n", "camera", "interface.plane.normal must be a unit vector"),
    ("    normal: [0, 0, -1]\n    point_mm: [0, 0, 22]\n", "camera", "interface.plane.normal must point from"),
    ("    normal: [0, 0, 1]\n    point_mm: [0, 0, -5]\n", "camera", "interface.plane.point_mm: the camera-side face"),
    ("    normal: [0, 0, 1]\n    point_mm: [0, 0, 22]\n    sigma_mm: -1\n", "camera", "interface.plane.sigma_mm"),
    ("    normal: [0, 0, 1]\n    point_mm: [0, 0, -100]\n", "world", "camera centres are not on the camera side"),
    ("    frame: camera\n    normal: [0, 0, 1]\n    point_mm: [0, 0, 500]\n", "world", "interface.plane.frame"),
])
def test_bad_plane_one_line(small_model, tmp_path, plane, mount, message):
    _, _, folder = small_model
    (tmp_path / "WINDOW.yaml").write_text(PLANE_YAML.format(plane=plane, mount=mount))
    res = CliRunner().invoke(main, ["refine-colmap", str(folder), "--window", str(tmp_path / "WINDOW.yaml"),
                                    "-o", str(tmp_path / "out")])
    assert res.exit_code == 1, res.output
    lines = res.output.strip().splitlines()
    assert lines[-1].startswith("error: ") and "WINDOW.yaml" in lines[-1] and message in lines[-1], lines[-1]
    assert not (tmp_path / "out").exists()


def test_cli_simulate_port_survey_small(tmp_path):
    """`ari-sfm simulate port_survey` at a quarter of the size: 12 PNG images of that size with texture,
    truth.json with the documented keys, and the truth's poses reproduce the relief through the port."""
    import json

    import cv2

    out = tmp_path / "survey"
    res = CliRunner().invoke(main, ["simulate", "port_survey", "-o", str(out), "--image-scale", "0.25"])
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in (out / "images").glob("*.png"))
    assert names == [f"image{i:04d}.png" for i in range(1, 13)]
    img = cv2.imread(str(out / "images" / names[0]), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (120, 160) and img.std() > 10.0  # textured, not blank
    meta = json.loads((out / "truth.json").read_text())
    assert {"interface", "camera", "relief", "images"} <= set(meta)
    assert {"thickness_mm", "index", "medium_index"} <= set(meta["interface"])
    assert {"image_size", "params", "normal_cam", "distance_mm"} <= set(meta["camera"])
    assert meta["camera"]["image_size"] == [160, 120] and meta["camera"]["params"][0] == pytest.approx(150.0)
    assert sorted(meta["images"]) == names
    assert np.linalg.norm(meta["camera"]["normal_cam"]) == pytest.approx(1.0)
    # every camera centre above the relief (z down), looking down
    for pose in meta["images"].values():
        p = Pose.from_json(pose)
        assert p.inverse().t[2] < meta["relief"]["depth_mm"] - 2 * meta["relief"]["amplitude_mm"]
        assert p.R[2, 2] > 0.9


def test_declared_plane_held_mount_world():
    """mount world: the tank wall declared in the COLMAP model's world (here the simulation's, mm) and
    held: the window is the wall and the points are at least as accurate as with the wall estimated."""
    from dataclasses import replace

    from ari_sfm.records import WindowPlane

    truth = tank_rig(num_frames=4, num_points=300)
    rec = adapter.reconstruction_from_arrays(list(truth.params), truth.image_size, truth.sensor_from_rig,
                                             truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz,
                                             truth.obs_image, truth.obs_point, truth.obs_uv)
    model = adapter.model_from_reconstruction(rec)
    wall = WindowPlane("world", truth.normal_world, truth.normal_world * truth.plane_mm)
    free = refine_colmap(rec, truth.interface, "world", units_mm=1.0)
    held = refine_colmap(rec, replace(truth.interface, plane=wall), "world", units_mm=1.0)
    assert np.allclose(held.state.normals[0], truth.normal_world, atol=1e-12)
    assert held.state.distances[0] == pytest.approx(truth.plane_mm, abs=1e-9)
    got, without = refined_errors(truth, rec, held), refined_errors(truth, rec, free)
    assert got["points_rms_mm"] <= 1.02 * without["points_rms_mm"]
    assert held.report.plane.frame == "world" and held.report.plane.normal == "held"
    assert np.array_equal(model.point3D_ids, adapter.model_from_reconstruction(held.refractive).point3D_ids)


# ----------------------------------------------------------------------------- units, scale bar, uncertainty

def test_scale_bar_held_by_the_solver_and_sigmas_cover_the_truth(survey):
    """The bar is a term of the solver: the refined bar keeps its length and the scale is right; the
    reported sigmas (Schur complement) cover the true port within 3 sigma and are not absurdly large."""
    truth, start, result, _ = survey
    r = result.report
    assert r.scale_bar.refined_mm == pytest.approx(r.scale_bar.declared_mm, rel=1e-3)
    assert abs(refined_errors(truth, start, result)["scale_error_pct"]) < 0.5
    u = r.uncertainty
    err = window_errors(truth, result.state.normals, result.state.distances)
    assert 0.0 < u.normal_deg["camera1"] < 1.0 and 0.0 < u.distance_mm["camera1"] < 10.0  # 10 images: weak
    assert err["normal_deg"] < 3.0 * u.normal_deg["camera1"]
    assert err["distance_mm"] < 3.0 * u.distance_mm["camera1"]
    assert u.scale_rel < 5e-3 and u.fx_px["camera1"] > 0.0 and "scale_rel" not in u.weak
    assert u.sigma0 == pytest.approx(truth.sigma_px, rel=0.3)


def test_sigmas_match_the_spread_over_noise_draws():
    """The reported sigma of the port distance and normal against the spread of the estimates over
    independent noise draws of one survey (started at the truth: the sigma describes the optimum)."""
    draws = []
    for seed in range(6):
        truth = port_survey(seed=0, num_images=8, num_points=500, focal_px=1300, area_mm=(1600, 1100), sigma_px=0.5)
        rng = np.random.default_rng(100 + seed)
        truth = __import__("dataclasses").replace(truth,
                                                  obs_uv=truth.obs_uv_exact + rng.normal(0, 0.5, truth.obs_uv.shape))
        rec = adapter.reconstruction_from_arrays(list(truth.params), truth.image_size, truth.sensor_from_rig,
                                                 truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz,
                                                 truth.obs_image, truth.obs_point, truth.obs_uv)
        model = adapter.model_from_reconstruction(rec)
        problem = RefractiveProblem(model, truth.interface, "camera", estimate_distance=True)
        from ari_sfm.colmap.refine.scale_bar import ScaleBar
        from ari_sfm.colmap.refine.uncertainty import uncertainty

        a, b, mm = scale_bar_of(truth, model)
        where = {int(p): k for k, p in enumerate(model.point3D_ids)}
        solver = Solver(problem, None, bar=ScaleBar(where[a], where[b], mm))
        res = solver.run(truth_state(truth, model), 30)
        u = uncertainty(solver, res.state, ["camera1"])
        draws.append((res.state.distances[0], u.distance_mm["camera1"]))
    d, s = np.array(draws).T
    assert np.std(d) < 2.5 * np.mean(s) and np.std(d) > 0.3 * np.mean(s)
    assert np.all(np.abs(d - 22.0) < 4.0 * s)


def test_without_a_scale_bar_the_scale_is_reported_weak(small_model, caplog):
    truth, start, _ = small_model
    with caplog.at_level("WARNING"):
        result = refine_colmap(start, truth.interface, "camera")
    u = result.report.uncertainty
    assert "scale_rel" in u.weak and u.scale_rel > 0.01
    assert any("scale is barely determined" in m and "scale_bar" in m for m in caplog.messages)


def test_scene_in_arbitrary_units_asks_for_units(small_model, tmp_path):
    """COLMAP's units are arbitrary: a scene a few units deep read as mm lies inside the port. One line
    asks for units_mm or a scale bar (no crash); with units_mm the same model runs."""
    truth, start, _ = small_model
    rec = adapter.pycolmap.Reconstruction(start)
    rec.transform(adapter.pycolmap.Sim3d(0.01, adapter.pycolmap.Rotation3d(), np.zeros(3)))
    with pytest.raises(AriSfmError, match="give units_mm .* or a scale_bar"):
        refine_colmap(rec, truth.interface, "camera", max_iterations=3)
    res = refine_colmap(rec, truth.interface, "camera", units_mm=100.0, max_iterations=3)
    assert np.isfinite(res.report.after.rms_px)


# ----------------------------------------------------------------------------- bad inputs: one line each

def run_cli(folder, tmp_path, *extra, window=None, out=None):
    path = tmp_path / "WINDOW.yaml"
    path.write_text(window if window is not None else WINDOW_YAML)
    out = out if out is not None else tmp_path / "out"
    return CliRunner().invoke(main, ["refine-colmap", str(folder), "--window", str(path), "-o", str(out), *extra])


def one_line_error(res, *words):
    assert res.exit_code == 1, res.output
    last = res.output.strip().splitlines()[-1]
    assert last.startswith("error: ") and "Traceback" not in res.output, res.output
    assert "ARI_SFM_DEBUG" not in res.output, res.output
    for w in words:
        assert w in last, last
    return last


def copy_model(folder, tmp_path):
    import shutil

    dst = tmp_path / "model"
    shutil.copytree(folder, dst)
    return dst


def test_out_is_the_input_model_refused(small_model, tmp_path):
    _, _, folder = small_model
    model = copy_model(folder, tmp_path)
    before = {p.name: p.read_bytes() for p in model.iterdir()}
    one_line_error(run_cli(model, tmp_path, out=model), "MODEL_DIR", "overwrite")
    assert {p.name: p.read_bytes() for p in model.iterdir()} == before


@pytest.mark.parametrize("extra, words", [
    (["--huber-px", "-1"], ["--huber-px", "> 0"]),
    (["--huber-px", "nan"], ["--huber-px", "finite"]),
    (["--max-iterations", "0"], ["--max-iterations", ">= 1"]),
])
def test_bad_options_one_line(small_model, tmp_path, extra, words):
    _, _, folder = small_model
    one_line_error(run_cli(folder, tmp_path, *extra), *words)
    assert not (tmp_path / "out").exists()


def test_max_iterations_has_help():
    res = CliRunner().invoke(main, ["refine-colmap", "--help"])
    assert "--max-iterations" in res.output and "Levenberg-Marquardt" in res.output


@pytest.mark.parametrize("bad", ["file", "proc", "readonly"])
def test_bad_out_folder_checked_before_the_refinement(small_model, tmp_path, bad, monkeypatch):
    _, _, folder = small_model
    import ari_sfm.colmap.refine as cr

    monkeypatch.setattr(cr, "refine_colmap", lambda *a, **k: pytest.fail("refined before checking -o"))
    if bad == "file":
        out = tmp_path / "a_file"
        out.write_text("x")
    elif bad == "proc":
        out = __import__("pathlib").Path("/proc/x")
    else:
        if os.geteuid() == 0:
            pytest.skip("root writes anywhere")
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        out = ro / "out"
    one_line_error(run_cli(folder, tmp_path, out=out), "-o/--out")


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_missing_model_file_named(small_model, tmp_path, name):
    _, _, folder = small_model
    model = copy_model(folder, tmp_path)
    (model / name).unlink()
    one_line_error(run_cli(model, tmp_path), name, "missing")


@pytest.mark.parametrize("name, named", [("cameras.bin", "cameras.bin"), ("points3D.bin", "model"),
                                         ("images.bin", "model")])
def test_truncated_model_file_refused(small_model, tmp_path, name, named):
    """A truncated cameras.bin used to run (1207 px -> 0.57 px on garbage): now one line."""
    _, _, folder = small_model
    model = copy_model(folder, tmp_path)
    data = (model / name).read_bytes()
    (model / name).write_bytes(data[:len(data) - 2])
    one_line_error(run_cli(model, tmp_path), named, "truncated or damaged")


@pytest.mark.parametrize("yaml_extra, words", [
    ("scale_bar:\n  point3D_ids: [1.7, 2.9]\n  distance_mm: 100\n", ["scale_bar.point3D_ids", "integers"]),
    ("scale_bar:\n  point3D_ids: [1, 999999]\n  distance_mm: 100\n", ["scale_bar.point3D_ids", "999999"]),
    ("units_mm: 1e300\n", ["units_mm", "mm per model unit"]),
    ("units_mm: 1e-300\n", ["units_mm", "check units_mm"]),
])
def test_bad_scale_one_line(small_model, tmp_path, yaml_extra, words):
    _, _, folder = small_model
    one_line_error(run_cli(folder, tmp_path, window=WINDOW_YAML + yaml_extra), "WINDOW.yaml", *words)
    assert not (tmp_path / "out").exists()


def test_nan_point_named(small_model, tmp_path):
    _, start, _ = small_model
    rec = adapter.pycolmap.Reconstruction(start)
    pid = sorted(rec.point3D_ids())[3]
    rec.point3D(pid).xyz = np.array([np.nan, 0.0, 1.0])
    (tmp_path / "m").mkdir()
    rec.write(str(tmp_path / "m"))
    one_line_error(run_cli(tmp_path / "m", tmp_path), f"point3D {pid}", "non-finite")


def test_too_few_points_refused(small_model, tmp_path):
    """3 points used to "converge" to 0.000 px: too few observations for the unknowns."""
    _, start, _ = small_model
    rec = adapter.pycolmap.Reconstruction(start)
    for pid in sorted(rec.point3D_ids())[3:]:
        rec.delete_point3D(pid)
    (tmp_path / "m").mkdir()
    rec.write(str(tmp_path / "m"))
    one_line_error(run_cli(tmp_path / "m", tmp_path), "too few observations")


def test_full_disk_leaves_no_partial_file(small_model, tmp_path, monkeypatch):
    """A write failing midway (ENOSPC while writing points3D.bin) leaves OUT's earlier results as they
    were and no partial or temporary file."""
    import errno

    from ari_sfm.colmap.refine import refine as refine_module

    _, _, folder = small_model
    out = tmp_path / "out"
    assert run_cli(folder, tmp_path, "--max-iterations", "2", out=out).exit_code == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def full_disk(reconstruction, where):
        (where / "cameras.bin").write_bytes(b"\0" * 16)
        (where / "points3D.bin").write_bytes(b"\0" * 7)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(refine_module, "_write_model", full_disk)
    one_line_error(run_cli(folder, tmp_path, "--max-iterations", "3", out=out), "No space left on device")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_schur_step_is_the_damped_full_system_step():
    """The reduced camera system (built once per linearization) gives the step of the whole damped
    system: at the first trial lambda damps every block (Marquardt, lambda diag); a later trial damps
    the camera block with its own lambda and the points with the first trial's."""
    from ari_sfm.colmap.refine.problem import huber_weights
    from ari_sfm.solver.schur import assemble_from_observations, solve_damped

    truth = port_survey(num_images=5, num_points=150, focal_px=1300, area_mm=(1500, 1000))
    rec = adapter.reconstruction_from_arrays(list(truth.params), truth.image_size, truth.sensor_from_rig,
                                             truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz,
                                             truth.obs_image, truth.obs_point, truth.obs_uv)
    model = adapter.model_from_reconstruction(rec)
    problem = RefractiveProblem(model, truth.interface, "camera", estimate_distance=True)
    lin = problem.linearize(truth_state(truth, model))
    w = huber_weights(lin.residuals, 0.5)  # some observations down-weighted
    G, P = problem.layout.size, len(model.point3D_ids)
    ne = assemble_from_observations(lin.residuals, lin.J_g, lin.index, lin.J_p, model.obs_point, P, G, w)
    J = np.zeros((2 * len(w), G + 3 * P))  # the dense whole Jacobian, whitened
    for o in range(len(w)):
        cols = lin.index[o] >= 0
        J[2 * o:2 * o + 2, lin.index[o][cols]] = lin.J_g[o][:, cols] * np.sqrt(w[o])
        J[2 * o:2 * o + 2, G + 3 * model.obs_point[o] + np.arange(3)] = lin.J_p[o] * np.sqrt(w[o])
    r = (lin.residuals * np.sqrt(w)[:, None]).ravel()
    A, b = J.T @ J, -J.T @ r
    d = np.maximum(np.diag(A), 1e-9)
    for lam_cameras, lam_points in ((1e-3, 1e-3), (1e-1, 1e-3)):  # the first trial, then a later one
        damping = np.r_[np.full(G, lam_cameras), np.full(3 * P, lam_points)] * d
        full = np.linalg.solve(A + np.diag(damping), b)
        dg, dp = solve_damped(ne, lam_cameras)
        assert np.allclose(dg, full[:G], rtol=1e-7, atol=1e-10 * np.abs(full).max())
        assert np.allclose(dp.ravel(), full[G:], rtol=1e-7, atol=1e-10 * np.abs(full).max())


def test_restarts_when_the_distance_runs_toward_zero(small_model, monkeypatch):
    """A refined distance far below every start candidate counts as "ran toward 0"; then the other
    starts are refined too and the lowest cost is kept."""
    from dataclasses import replace as dc_replace

    from ari_sfm.colmap.refine import refine as refine_module

    truth, start, _ = small_model
    model = adapter.model_from_reconstruction(start)
    problem = RefractiveProblem(model, truth.interface, "camera", estimate_distance=True)
    state = truth_state(truth, model)
    assert not refine_module._collapsed(state, problem, (10.0, 30.0, 100.0))  # 22 mm
    assert refine_module._collapsed(dc_replace(state, distances=np.array([0.5])), problem, (10.0, 30.0, 100.0))
    monkeypatch.setattr(refine_module, "_collapsed", lambda *args: True)
    result = refine_colmap(start, truth.interface, "camera", max_iterations=10)
    restarts = result.report.restarts
    assert len(restarts) == 2
    assert result.report.cost_final <= min(r["cost"] for r in restarts) + 1e-9


def test_the_report_record_is_refine_json(survey, tmp_path):
    """refine_colmap's RefineReport: read by attribute; its to_json() is refine.json as documented
    (docs/DATASET_FORMAT.md), the file write_refined writes."""
    truth, start, result, _ = survey
    r = result.report
    write_refined(result, tmp_path / "out")
    j = json.loads((tmp_path / "out" / "refine.json").read_text())
    assert j == json.loads(json.dumps(r.to_json()))
    assert set(j) == {"mount", "model", "backend", "units_mm", "interface", "counts", "estimated", "scale",
                      "distance_search", "restarts", "iterations", "converged", "linearizations", "uncertainty",
                      "cost", "time_s", "before", "after", "pinhole_approximation", "window", "scale_bar"}
    assert j["after"] == {"model": "exact", "rms_px": r.after.rms_px, "mean_px": r.after.mean_px,
                          "per_image_rms_px": {str(i): v for i, v in r.after.per_image_rms_px.items()}}
    assert set(j["pinhole_approximation"]) == {"camera_model", "rms_px", "per_image_rms_px"}
    assert j["linearizations"] == {"final": r.linearizations, "search": r.search_linearizations}
    assert j["cost"] == {"start": r.cost_start, "final": r.cost_final} and r.cost_final <= r.cost_start
    assert j["window"]["distance_mm"]["camera1"] == r.window.distance_of("camera1") == result.state.distances[0]
    assert set(j["uncertainty"]) == {"sigma0", "normal_deg", "distance_mm", "fx_px", "scale_rel", "weak"}
    assert j["scale_bar"]["ids"] == list(r.scale_bar.ids) and r.counts.images == len(start.images)


def test_distance_still_at_zero_after_the_restarts_is_named(small_model, monkeypatch, caplog):
    """A distance that ran toward 0 from every start is not reported silently: one warning naming it
    and the remedy, and the port distance in uncertainty.weak."""
    from ari_sfm.colmap.refine import refine as refine_module

    truth, start, _ = small_model
    monkeypatch.setattr(refine_module, "_collapsed", lambda *args: True)
    with caplog.at_level("WARNING", logger="ari_sfm.colmap.refine.refine"):
        result = refine_colmap(start, truth.interface, "camera", max_iterations=10)
    assert "distance_mm.camera1" in result.report.uncertainty.weak
    assert any("ran to" in r.message and "scale_bar" in r.message and "interface.plane" in r.message
               for r in caplog.records)


def test_units_far_too_small_run_the_distance_down_and_say_so(small_model, caplog):
    """Reproduced: with units_mm 10x too small (the scene 10x too near) the port distance follows the
    scale far below the true 22 mm (the data fix only distance / scale); the result says the distance
    and the scale are barely determined and names the remedy (a scale bar), not a silent success."""
    truth, start, _ = small_model
    with caplog.at_level("WARNING"):
        result = refine_colmap(start, truth.interface, "camera", units_mm=0.1)
    assert result.state.distances[0] < 0.5 * truth.distance_mm[0]
    weak = result.report.uncertainty.weak
    assert "distance_mm.camera1" in weak and "scale_rel" in weak
    assert any("port distance" in r.message and "barely determined" in r.message for r in caplog.records)
    assert any("scale_bar" in r.message for r in caplog.records)

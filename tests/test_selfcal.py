"""Volume self-calibration through the window: disparity peaks among ghosts, the corrected rig against
the simulation's rig B (from the truth and from a target calibration of the simulated body, every camera
moved), its sigmas against its errors, the held gauge, the trust checks on a wrong start, the outputs
(together or not at all, never over an input), the GTSAM backend, the report and the command line."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.geometry import rotation_angle_deg
from ari_sfm.io import load_calibration
from ari_sfm.particles.disparity import Cells, ParticleSet, _joint_peak, disparity_map
from ari_sfm.particles.landmarks import (
    Gauge,
    IntrinsicsPrior,
    free_intrinsics,
    landmark_model,
    motion_jacobians,
    pairwise_sum_mm,
    refine_with_landmarks,
    window_gauge,
    window_planes,
)
from ari_sfm.particles.selfcal import SelfCalOptions, converged, disparity_json, self_calibrate, write_self_calibration
from ari_sfm.particles.truth import score_experiment
from ari_sfm.particles.volume import Volume
from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment, write_particle_experiment

SIGMA_PX = 0.1
SMALL = ParticleSimOptions(particles_per_frame=400, num_frames=2, sigma_px=SIGMA_PX, seed=11)  # cams 1-3 drifted


@pytest.fixture(scope="module")
def experiment():
    return simulate_particle_experiment(SMALL)


@pytest.fixture(scope="module")
def volume(experiment):
    return Volume(experiment.volume_min_mm, experiment.volume_max_mm)


@pytest.fixture(scope="module")
def corrected(experiment, volume):
    """Self-calibration of the drifted experiment from rig A's calibration (~7 s)."""
    return self_calibrate(experiment.truth_a, dict(enumerate(experiment.detections)), SelfCalOptions(), volume=volume)


def _relative_rotation_error_deg(cal, truth, name: str) -> float:
    first = next(iter(cal.cameras))

    def rel(c):
        return c.cameras[name].cam_from_world.R @ c.cameras[first].cam_from_world.R.T

    return rotation_angle_deg(rel(cal), rel(truth))


ALL_MOVED = ParticleSimOptions(particles_per_frame=400, num_frames=2, sigma_px=SIGMA_PX, seed=11,
                               drift_cameras=(0, 1, 2, 3))  # camera 0 bumped too


@pytest.fixture(scope="module")
def from_target(tmp_path_factory):
    """Every camera moved after the target calibration; self-calibrated from ari-sfm's own exact-model
    calibration (with distortion) of the simulated body, as a lab would (~10 s)."""
    from ari_sfm.calibration.calibrate import calibrate
    from ari_sfm.io import load_dataset

    exp = simulate_particle_experiment(ALL_MOVED)
    folder = tmp_path_factory.mktemp("all_moved")
    write_particle_experiment(exp, folder, render_frames=0)
    start = calibrate(load_dataset(folder / "calibration"), model="exact", distortion=True)
    result = self_calibrate(start, dict(enumerate(exp.detections)), SelfCalOptions(),
                            volume=Volume(exp.volume_min_mm, exp.volume_max_mm))
    return exp, start, result


# --------------------------------------------------------------------------- disparity maps


def test_cells_index_their_own_centres():
    cells = Cells(np.array([-30.0, -20, 380]), np.array([30.0, 20, 410]), (4, 3, 2))
    assert np.array_equal(cells.index(cells.centres()), np.arange(24))
    assert cells.index(np.array([[-1e3, 1e3, 395.0]]))[0] == 0 + 4 * (2 + 3 * 1)  # outside: the nearest cell


def test_joint_peak_finds_the_drift_among_ten_times_more_ghosts():
    rng = np.random.default_rng(0)
    drift = np.array([[-2.7, 0.1], [0.0, 1.7], [1.9, 2.8], [0.9, -4.6]])  # one offset per camera (px)
    true = drift + rng.normal(0.0, 0.08, (30, 4, 2))
    r, a = 5.0 * np.sqrt(rng.uniform(size=(300, 4, 1))), rng.uniform(0, 2 * np.pi, (300, 4, 1))
    ghosts = np.concatenate([r * np.cos(a), r * np.sin(a)], axis=2)  # uniform over the 5 px tolerance disc
    centre, inside = _joint_peak(np.concatenate([true, ghosts]), 0.5)
    assert np.abs(centre - drift).max() < 0.05
    assert inside[:30].sum() >= 29 and inside[30:].sum() == 0


def test_disparity_map_counts_and_inliers_of_one_cell():
    rng = np.random.default_rng(1)
    P, C = 200, 3
    d = np.where(np.arange(P)[:, None, None] < 50, np.array([0.8, -0.4]), rng.uniform(-4, 4, (P, C, 2)))
    d[:50] += rng.normal(0.0, 0.05, (50, C, 2))
    d[60:70, 2] = np.nan  # 3-camera matches
    particles = ParticleSet(np.zeros((P, C, 2)), np.zeros((P, 3)), np.zeros(P, int))
    cells = Cells(np.full(3, -1.0), np.full(3, 1.0), (1, 1, 1))
    m = disparity_map(["a", "b", "c"], cells, particles, d, 0.5, 1.5)
    assert np.array_equal(np.flatnonzero(m.inlier), np.arange(50))
    assert np.allclose(m.vector_px[:, 0], [0.8, -0.4], atol=0.03)
    assert m.count[:, 0].tolist() == [50, 50, 50] and m.total[:, 0].tolist() == [200, 200, 190]
    assert np.allclose(m.rms_px, np.hypot(0.8, 0.4), atol=0.03)


# --------------------------------------------------------------------------- the corrected rig


def test_the_drift_shows_and_the_disparity_falls_to_the_noise(corrected):
    before, after = corrected.before.rms_px, corrected.after.rms_px
    assert before.max() > 1.5  # drifted cameras move their images by px
    assert np.all(after <= 1.5 * SIGMA_PX), after  # PHYSICS.md: ~1.1 sigma for 4 cameras
    assert corrected.after.inlier.sum() >= 0.95 * 2 * 400 * 0.9
    assert corrected.report.converged
    ghost_fit = replace(corrected.after, rms_px=np.array([0.11, 0.62, 0.43, 0.21]))  # a correction from a ghost peak
    assert not converged(ghost_fit, SelfCalOptions())


def test_camera_rotations_recover_rig_b(experiment, corrected):
    a, b, c = experiment.truth_a, experiment.truth_b, corrected.calibration
    for name in b.cameras:
        if name != "cam0":
            assert _relative_rotation_error_deg(a, b, name) > 0.03  # the drift was there
        assert _relative_rotation_error_deg(c, b, name) < 0.02, name


def test_the_window_and_the_gauge_are_held(experiment, corrected):
    a, c = experiment.truth_a, corrected.calibration
    n_a, h_a = window_planes(a)
    n_c, h_c = window_planes(c)
    assert np.array_equal(n_c, n_a) and np.allclose(h_c, h_a, atol=1e-9)  # the window's plane: the lab's
    assert c.interface.thickness_mm == a.interface.thickness_mm

    def centres(cal):
        return np.array([k.cam_from_world.inverse().t for k in cal.cameras.values()])

    assert abs(pairwise_sum_mm(centres(c)) - pairwise_sum_mm(centres(a))) < 0.05  # the scale (sigma 0.01 mm)
    # the rig's mean motion along the motions keeping the window (rotation about n, in-plane shift) is nil
    gauge = Gauge.of(a, [False], 400.0)
    moved = centres(c) - centres(a)
    n = n_a[0]
    in_plane = moved - np.outer(moved @ n, n)
    assert np.linalg.norm(in_plane.mean(axis=0)) < 0.02, in_plane
    assert not np.array_equal(c.cameras["cam0"].cam_from_world.R, a.cameras["cam0"].cam_from_world.R)  # it may move
    sc = c.self_calibration
    assert "window's plane" in sc.held[0] and "pair of camera centres" in sc.scale_how
    assert len(gauge.twists) == 3


def test_window_gauge_motions():
    n = np.array([0.0, 0.1, 1.0]) / np.linalg.norm([0.0, 0.1, 1.0])
    water = window_gauge(n[None], [False])
    assert water.shape == (3, 6)
    for om_v in water:  # rotation about n only, translation within the plane only
        assert np.linalg.norm(np.cross(om_v[:3], n)) < 1e-12 and abs(om_v[3:] @ n) < 1e-12
    assert window_gauge(n[None], [True]).shape == (4, 6)  # in air the distance is not seen either
    side = np.array([1.0, 0.0, 0.0])
    assert window_gauge(np.stack([n, side]), [False, False]).shape[0] == 1  # two walls: only their common line
    assert window_gauge(n[None], [False], complement=True).shape == (3, 6)


def test_motion_jacobians_against_numerical_derivatives(experiment):
    from ari_sfm.colmap.refine.problem import RefractiveProblem, State

    cal = experiment.truth_b
    landmarks = _true_landmarks(experiment, cal, 20)
    model = landmark_model(cal, landmarks, ())
    normals, planes = window_planes(cal)
    problem = RefractiveProblem(model, cal.interface, "world", False, hold_window=True, held_frames=np.zeros(0, int),
                                hold_intrinsics=True)
    state = State(model.colmap_params, model.rig_from_world, model.sensor_from_rig, normals, planes, model.xyz)
    gauge = Gauge.of(experiment.truth_a, [False], 400.0)
    e0, J = gauge.rows(state, problem.layout)
    G, h = problem.layout.size, 1e-7
    numeric = np.zeros_like(J)
    for k in range(G):
        step = np.zeros(G)
        step[k] = h
        plus = gauge.rows(problem.retract(state, step, np.zeros_like(state.xyz)), problem.layout)[0]
        step[k] = -h
        minus = gauge.rows(problem.retract(state, step, np.zeros_like(state.xyz)), problem.layout)[0]
        numeric[:, k] = (plus - minus) / (2 * h)
    # the log's first-order Jacobian is exact only at the start (rho = 0): 1e-3 relative at 0.05 deg
    assert np.abs(numeric - J).max() <= 2e-3 * np.abs(J).max()
    J_rho, J_C = motion_jacobians(state, problem.layout)
    assert J_rho.shape == (4, 3, G) and J_C.shape == (4, 3, G)


def test_every_camera_moved_recovered_from_a_target_calibration(from_target):
    """Camera 0 moved too: the relative rotations come out nearer rig B's than the start's, within 0.03 deg on
    this small experiment (800 particles; 10 x 2000: benchmarks/bench_selfcal.py --cases), and each error
    within 3 sigma of calibration.json's uncertainty."""
    exp, start, result = from_target
    b, c = exp.truth_b, result.calibration
    start_errors = [_relative_rotation_error_deg(start, b, n) for n in exp.cameras[1:]]
    errors = [_relative_rotation_error_deg(c, b, n) for n in exp.cameras[1:]]
    assert max(start_errors) > 0.04  # the drift (and the target calibration's own error) was there
    assert max(errors) < 0.03 and max(errors) < 0.75 * max(start_errors), (errors, start_errors)
    for n, e in zip(exp.cameras[1:], errors):
        sigma = c.uncertainty.cameras[n].rotation_deg
        assert 0.0 < sigma < 0.06 and e < 3.0 * sigma, (n, e, sigma)
    assert result.report.passed and result.report.converged
    assert max(result.after.rms_px) <= 1.5 * SIGMA_PX


def test_every_camera_moved_within_0_02_deg_from_a_20_view_body_calibration(tmp_path):
    """The issue's goal at full size (10 frames x 2000 particles, every camera moved by 0.05 deg and 0.3 mm,
    camera 0 included; the case where the first round widens its tolerance to 12 px): self-calibrated from
    ari-sfm's own exact-model calibration of 20 views of the body, the rotations relative to camera 0 end
    within 0.02 deg of rig B's (measured 0.0064-0.0132), each within 3 of its sigma (~11 s; the 9 drifts of
    benchmarks/bench_selfcal.py --cases: docs/guide/particles.md)."""
    from ari_sfm.calibration.calibrate import calibrate
    from ari_sfm.io import load_dataset

    exp = simulate_particle_experiment(ParticleSimOptions(seed=5, drift_cameras=(0, 1, 2, 3), calibration_frames=20))
    write_particle_experiment(exp, tmp_path, render_frames=0)
    start = calibrate(load_dataset(tmp_path / "calibration"), model="exact", distortion=True)
    result = self_calibrate(start, dict(enumerate(exp.detections)), SelfCalOptions(),
                            volume=Volume(exp.volume_min_mm, exp.volume_max_mm))
    b, c = exp.truth_b, result.calibration
    assert max(_relative_rotation_error_deg(start, b, n) for n in exp.cameras[1:]) > 0.05  # it moved
    for n in exp.cameras[1:]:
        error, sigma = _relative_rotation_error_deg(c, b, n), c.uncertainty.cameras[n].rotation_deg
        assert error < 0.02 and error < 3.0 * sigma, (n, error, sigma)
    assert result.report.passed and max(r.tolerance_px for r in result.report.rounds) > SelfCalOptions().tolerance_px


def test_the_output_holds_its_own_residuals_and_uncertainty(from_target):
    _, start, result = from_target
    c = result.calibration
    assert c.residuals.count == result.report.rounds[-2].adjustment.observations  # the particles' images
    assert 0.08 < c.residuals.rmse_px < 0.2  # the particles' reprojection, not the body's 0.07 px
    assert abs(c.uncertainty.sigma_px - SIGMA_PX) < 0.02
    assert not c.stages and "stages" not in c.extra and c.quality is None and c.optimizer is None and not c.frames
    assert c.uncertainty.cameras["cam0"].intrinsics["fx"] < start.uncertainty.cameras["cam0"].intrinsics["fx"]
    assert c.uncertainty.cameras["cam1"].relative_pose and not c.uncertainty.cameras["cam0"].relative_pose
    for r in result.report.rounds:
        if r.adjustment is not None:
            assert r.adjustment.stop != "max_iterations" and r.adjustment.iterations <= 20


def test_a_wrong_start_is_refused_or_fails_its_checks(experiment, volume):
    """A start whose cameras are 1 deg off (60 px; 0.15-0.35 deg are corrected: measured 0.01-0.05 deg
    after): no true match within the widest tolerance, so either no peak is found (an error) or what is
    fitted fails the checks."""
    from ari_sfm.errors import AriSfmError
    from ari_sfm.geometry import Pose, rotation_from_rotvec

    rng = np.random.default_rng(1)
    cams = dict(experiment.truth_a.cameras)
    for n in experiment.cameras[1:]:
        p = cams[n].cam_from_world
        axis = rng.normal(size=3)
        cams[n] = replace(cams[n], cam_from_world=Pose(rotation_from_rotvec(axis / np.linalg.norm(axis)
                                                                             * np.radians(1.0)) @ p.R, p.t))
    wrong = replace(experiment.truth_a, cameras=cams)
    try:
        result = self_calibrate(wrong, dict(enumerate(experiment.detections)), SelfCalOptions(), volume=volume)
    except AriSfmError as exc:
        assert "no confident matches" in exc.message
        return
    assert not result.report.passed
    assert not result.calibration.self_calibration.passed


def test_trust_checks_catch_a_fit_onto_ghosts(corrected, experiment):
    """The checks on a corrected rig pass; the same checks fail for a result that matches few images or
    ended far from where the start could reach."""
    from ari_sfm.particles.selfcal import trust_checks

    options = SelfCalOptions()
    last = [r for r in corrected.rounds][-1]
    frames = sorted(range(len(experiment.detections)))
    det = dict(enumerate(experiment.detections))
    from ari_sfm.particles.disparity import ParticleSet as PS

    few = PS(np.zeros((20, 4, 2)) + np.nan, np.zeros((20, 3)), np.zeros(20, int))
    checks = {c.name: c for c in trust_checks(experiment.truth_a, corrected.calibration, det, frames, few,
                                               corrected.after, 5.0, options)}
    assert not checks["matched_share"].passed and not checks["in_reach"].passed
    assert all(c.passed for c in corrected.report.checks if c.fatal)
    del last


def test_matching_with_the_corrected_calibration_is_as_good_as_with_the_truth(experiment, volume, corrected):
    truth, truth_rms = score_experiment(experiment, volume, experiment.truth_b)
    drifted, _ = score_experiment(experiment, volume, experiment.truth_a)
    after, after_rms = score_experiment(experiment, volume, corrected.calibration)
    assert drifted.found_fraction < 0.1  # PHYSICS.md: the drifted calibration finds almost nothing
    assert truth.found_fraction >= 0.95 and truth.ghost_fraction <= 0.05
    assert after.found_fraction >= 0.95, after
    assert after.ghost_fraction <= 0.05, after  # >= 95 % of the particles with the right image in every camera
    # positions: the held scale is rig A's (the sum of all pairwise camera distances); rig B's moved cameras
    # changed it (PHYSICS.md: particles barely determine it), which scales positions about the volume
    # (RMS radius ~22 mm) after a rigid alignment
    def centres(cal):
        return np.array([k.cam_from_world.inverse().t for k in cal.cameras.values()])

    scale_error = abs(pairwise_sum_mm(centres(experiment.truth_b)) / pairwise_sum_mm(centres(corrected.calibration))
                      - 1)
    assert after_rms <= 1.5 * truth_rms + 25.0 * scale_error, (after_rms, truth_rms, scale_error)


def test_outputs_load_and_hold_the_maps(corrected, tmp_path):
    write_self_calibration(corrected, tmp_path)
    cal = load_calibration(tmp_path / "calibration.json")  # an ordinary calibration
    assert cal.model == "exact"
    sc = cal.self_calibration
    assert sc.frames == (0, 1) and sc.particles_used > 0
    assert set(sc.disparity_rms_px) == set(cal.cameras)
    assert sc == corrected.report  # the record read back is the one written
    d = json.loads((tmp_path / "disparity.json").read_text())
    assert d == json.loads(json.dumps(disparity_json(corrected)))
    for when in ("before", "after"):
        for cam in d[when]["cameras"].values():
            assert len(cam["vector_px"]) == len(cam["count"]) == 27
            assert sum(cam["count"]) <= sum(cam["total"])


# --------------------------------------------------------------------------- the bundle adjustment


def _true_landmarks(exp, calibration, count: int = 120) -> ParticleSet:
    """The first particles of frame 0 seen by every camera, their true images, triangulated with ``calibration``."""
    from ari_sfm.reconstruction.triangulate import triangulate_pixels

    det, ids = exp.detections[0], exp.particle_ids[0]
    common = set(range(len(exp.positions[0])))
    for c in exp.cameras:
        common &= set(ids[c].tolist())
    chosen = sorted(common)[:count]
    pixels = np.stack([det[c][np.argsort(ids[c])][np.searchsorted(np.sort(ids[c]), chosen)] for c in exp.cameras], 1)
    xyz = triangulate_pixels(calibration, {c: pixels[:, k] for k, c in enumerate(exp.cameras)})[0]
    return ParticleSet(pixels, xyz, np.zeros(len(chosen), int))


def _adjust(exp, start, landmarks, mode="prior", backend="numpy"):
    gauge = Gauge.of(start, [False], 400.0)
    prior = IntrinsicsPrior.of(start, free_intrinsics(start, mode), mode)
    return refine_with_landmarks(start, landmarks, gauge, prior, backend=backend)


def test_gtsam_backend_solves_the_same_problem(experiment):
    landmarks = _true_landmarks(experiment, experiment.truth_a, 40)
    numpy_r = _adjust(experiment, experiment.truth_a, landmarks, "held")
    gtsam_r = _adjust(experiment, experiment.truth_a, landmarks, "held", backend="gtsam")
    for name in experiment.cameras:
        assert rotation_angle_deg(numpy_r.calibration.cameras[name].cam_from_world.R,
                                  gtsam_r.calibration.cameras[name].cam_from_world.R) < 1e-4
        assert np.allclose(numpy_r.calibration.cameras[name].cam_from_world.t,
                           gtsam_r.calibration.cameras[name].cam_from_world.t, atol=1e-4)
    a = gtsam_r.adjustment
    assert abs(a.sum_baselines_final_mm - a.sum_baselines_held_mm) < 0.05


def test_gtsam_backend_is_refused_for_large_rounds(experiment, monkeypatch):
    import ari_sfm.particles.landmarks as lm
    from ari_sfm.errors import AriSfmError

    monkeypatch.setattr(lm, "GTSAM_MAX_LANDMARKS", 10)
    with pytest.raises(AriSfmError, match="numpy backend"):
        _adjust(experiment, experiment.truth_a, _true_landmarks(experiment, experiment.truth_a, 40), backend="gtsam")


def test_intrinsics_held_or_moved_within_their_priors(experiment):
    """Held: unchanged. With the start's sigmas (0.5 px here) as priors: moved, within a few sigma. Free
    (no prior): a principal point trades against a rotation and a focal length against depth, so they
    wander far more (why priors are the default)."""
    from ari_sfm.results import CameraUncertainty, Uncertainty

    a = experiment.truth_a
    unc = Uncertainty(0.05, {n: CameraUncertainty({"fx": 0.5, "fy": 0.5, "cx": 0.5, "cy": 0.5}) for n in a.cameras},
                      None)
    a = replace(a, uncertainty=unc)
    landmarks = _true_landmarks(experiment, a, 300)
    held = _adjust(experiment, a, landmarks, "held").calibration
    prior = _adjust(experiment, a, landmarks, "prior").calibration
    free = _adjust(experiment, a, landmarks, "free").calibration
    spread = {"prior": 0.0, "free": 0.0}
    for name in a.cameras:
        K0 = a.cameras[name].K
        assert np.array_equal(held.cameras[name].K, K0)
        assert not np.array_equal(prior.cameras[name].K, K0)
        assert np.array_equal(prior.cameras[name].dist, a.cameras[name].dist)  # no distortion in the start: held
        for label, cal in (("prior", prior), ("free", free)):
            d = cal.cameras[name].K - K0
            spread[label] = max(spread[label], abs(d[0, 0]), abs(d[1, 1]), abs(d[0, 2]), abs(d[1, 2]))
    assert spread["prior"] < 2.0 < spread["free"], spread


def test_intrinsics_prior_with_a_joint_covariance(experiment):
    """A joint covariance of every camera's intrinsics as the prior (IntrinsicsPrior.with_covariance): its
    rows are the Mahalanobis distance (noise^2 d^T Cov^-1 d); a diagonal covariance is the sigmas alone; with
    correlations the numpy and GTSAM backends solve the same problem."""
    from types import SimpleNamespace

    from ari_sfm.results import CameraUncertainty, Uncertainty

    a = experiment.truth_a
    unc = Uncertainty(0.05, {n: CameraUncertainty({"fx": 0.5, "fy": 0.5, "cx": 0.5, "cy": 0.5}) for n in a.cameras},
                      None)
    a = replace(a, uncertainty=unc)
    sigmas_only = IntrinsicsPrior.of(a, free_intrinsics(a, "prior"), "prior")
    C, F = sigmas_only.values.shape
    rng = np.random.default_rng(3)
    A = rng.normal(size=(C * F, C * F))
    S = A @ A.T + 0.5 * np.eye(C * F)  # positive definite, strongly correlated
    corr = S / np.sqrt(np.outer(np.diag(S), np.diag(S)))
    cov = 0.25 * corr  # sigma 0.5 px everywhere
    joint = sigmas_only.with_covariance(cov)
    assert np.allclose(joint.sigmas, 0.5)
    delta = rng.normal(0.0, 0.5, (C, F))
    layout = SimpleNamespace(intrinsics=[np.arange(F) + 10 * c for c in range(C)])
    state = SimpleNamespace(colmap_params=list(sigmas_only.values + delta))
    e, J, cols = joint.rows(state, layout, 0.1)
    d = delta.ravel()
    assert float(e @ e) == pytest.approx(0.01 * float(d @ np.linalg.solve(cov, d)), rel=1e-9)
    assert np.allclose(J @ d, e) and cols.tolist() == [10 * c + j for c in range(C) for j in range(F)]

    landmarks = _true_landmarks(experiment, a, 40)
    gauge = Gauge.of(a, [False], 400.0)
    alone = refine_with_landmarks(a, landmarks, gauge, sigmas_only).calibration
    diagonal = refine_with_landmarks(a, landmarks, gauge, sigmas_only.with_covariance(np.diag(np.full(C * F, 0.25))))
    numpy_r = refine_with_landmarks(a, landmarks, gauge, joint).calibration
    gtsam_r = refine_with_landmarks(a, landmarks, gauge, joint, backend="gtsam").calibration
    assert max(np.abs(numpy_r.cameras[n].K - alone.cameras[n].K).max() for n in a.cameras) > 1e-3  # it weighs
    for name in a.cameras:
        assert np.allclose(diagonal.calibration.cameras[name].K, alone.cameras[name].K, atol=1e-6)
        assert np.allclose(numpy_r.cameras[name].K, gtsam_r.cameras[name].K, atol=1e-3)
        assert rotation_angle_deg(numpy_r.cameras[name].cam_from_world.R,
                                  gtsam_r.cameras[name].cam_from_world.R) < 1e-4


def test_a_guessed_principal_point_is_weighed_as_unknown_and_said(experiment, corrected):
    """A start that held cam1's principal point at a guess (calibrate's image centre when its views leave it
    undetermined: a sigma of 1e-4 px) 20 px off: weighed as that sigma, the self-calibrated rotation of cam1
    inherits the 20 px (0.18 deg, > 3 sigma); weighed as an unknown (UNKNOWN_PRIOR_PX), as self-calibration
    does, the particles pull it to ~4 px and its sigma contains the error (0.06 deg); the checks warn. A K declared
    known (every intrinsic held) is not a guess."""
    from ari_sfm.particles.landmarks import UNKNOWN_PRIOR_PX, guessed_principal_points
    from ari_sfm.particles.selfcal import trust_checks
    from ari_sfm.results import CameraUncertainty, Uncertainty

    a = experiment.truth_a
    sig = {n: {"fx": 0.5, "fy": 0.5, "cx": 0.5, "cy": 0.5} for n in a.cameras}
    sig["cam1"] = {"fx": 0.5, "fy": 0.5, "cx": 1e-4, "cy": 1e-4}
    K = a.cameras["cam1"].K.copy()
    K[0, 2] += 20.0
    start = replace(a, cameras={**a.cameras, "cam1": replace(a.cameras["cam1"], K=K)},
                    uncertainty=Uncertainty(0.05, {n: CameraUncertainty(v) for n, v in sig.items()}, None))
    assert guessed_principal_points(start) == ["cam1"] and guessed_principal_points(a) == []
    known = Uncertainty(0.05, {n: CameraUncertainty({k: 1e-4 for k in v}) for n, v in sig.items()}, None)
    assert guessed_principal_points(replace(a, uncertainty=known)) == []
    prior = IntrinsicsPrior.of(start, free_intrinsics(start, "prior"), "prior")
    assert prior.sigmas[1, 2] == prior.sigmas[1, 3] == UNKNOWN_PRIOR_PX and prior.sigmas[0, 2] == 0.5

    landmarks = _true_landmarks(experiment, start, 400)
    gauge = Gauge.of(start, [False], 400.0)
    trusted = replace(prior, sigmas=np.where(prior.sigmas == UNKNOWN_PRIOR_PX, 1e-4, prior.sigmas))
    for weighed, contains in ((trusted, False), (prior, True)):
        r = refine_with_landmarks(start, landmarks, gauge, weighed)
        error = _relative_rotation_error_deg(r.calibration, experiment.truth_b, "cam1")
        sigma = r.covariance.cameras["cam1"].rotation_rel_deg
        assert (error < 2.0 * sigma if contains else error > 3.0 * sigma), (error, sigma)

    det = dict(enumerate(experiment.detections))
    frames = sorted(det)
    particles = ParticleSet(landmarks.pixels, landmarks.xyz, landmarks.frame)
    for cal, passed in ((start, False), (experiment.truth_a, True)):
        check = {c.name: c for c in trust_checks(cal, corrected.calibration, det, frames, particles,
                                                 corrected.after, 5.0, SelfCalOptions())}["start_principal_points"]
        assert check.passed == passed and not check.fatal


# --------------------------------------------------------------------------- the command line


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("selfcal_sim")
    write_particle_experiment(simulate_particle_experiment(replace(SMALL, particles_per_frame=250)), out,
                              render_frames=0)
    return out


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _cli_error(args) -> str:
    r = _run(args)
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.output.strip().splitlines() if "frame/s" not in ln]  # without the progress bar
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    assert "Traceback" not in r.output
    return lines[0]


def test_cli_self_calibrate_writes_a_calibration_every_command_loads(written, tmp_path):
    out = tmp_path / "sc"
    r = _run(["self-calibrate", written / "experiment", "--calibration", written / "truth" / "rig_a.json", "-o", out,
              "--workers", "0", "--cells", 2, 2, 1])
    assert r.exit_code == 0, r.output
    assert "cam3: disparity RMS" in r.output and "held: the window's plane" in r.output
    assert "round 1: matching at 5 px" in r.output  # the progress bar (stderr) names the round and tolerance
    cal = load_calibration(out / "calibration.json")
    sc = cal.self_calibration
    assert max(v.after for v in sc.disparity_rms_px.values()) <= 1.5 * SIGMA_PX
    assert sc.passed is True and {c.name for c in sc.checks} >= {"matched_share", "in_reach"}
    assert sc.inputs is not None and sc.inputs.workers == 0
    r = _run(["particles", written / "experiment", "--calibration", out / "calibration.json", "-o", tmp_path / "p",
              "--workers", "0"])
    assert r.exit_code == 0, r.output
    r = _run(["report", out])  # the report of a self-calibration folder: no dataset/observations notes
    assert r.exit_code == 0, r.output
    page = (out / "report.html").read_text()
    assert "Volume self-calibration" in page and 'alt="disparity maps"' in page
    assert "dataset not found" not in page and "no observations found" not in page
    assert "passed its checks" in page and "rotation relative to the first camera" in page


def test_cli_particles_warns_of_a_stale_calibration(written, tmp_path, caplog):
    r = _run(["particles", written / "experiment", "--calibration", written / "truth" / "rig_a.json", "-o",
              tmp_path / "p", "--workers", "0"])
    assert r.exit_code == 0, r.output
    warned = [m for m in caplog.messages if "does not fit these images" in m]
    assert warned and "self-calibrate" in warned[0]
    caplog.clear()
    r = _run(["particles", written / "experiment", "--calibration", written / "truth" / "rig_b.json", "-o",
              tmp_path / "p2", "--workers", "0"])
    assert r.exit_code == 0 and not any("does not fit" in m for m in caplog.messages)


def test_cli_wrong_start_exits_3_with_the_flag(written, tmp_path, monkeypatch):
    """A result failing its checks is written with self_calibration.passed false and exits 3 (calibrate's
    quality gate's code)."""
    import ari_sfm.particles.selfcal as sc_mod

    monkeypatch.setattr(sc_mod, "MIN_MATCHED_SHARE", 1.01)  # no rig can match more images than it has
    out = tmp_path / "sc"
    r = _run(["self-calibrate", written / "experiment", "--calibration", written / "truth" / "rig_a.json", "-o", out,
              "--workers", "0", "--cells", 2, 2, 1])
    assert r.exit_code == 3, r.output
    assert "FAILED" in r.output
    assert load_calibration(out / "calibration.json").self_calibration.passed is False


def test_cli_refuses_to_overwrite_its_input(written, tmp_path):
    import shutil

    cal = tmp_path / "cal" / "calibration.json"
    cal.parent.mkdir()
    shutil.copy(written / "truth" / "rig_a.json", cal)
    before = cal.read_bytes()
    for out in (cal.parent, tmp_path):
        line = _cli_error(["self-calibrate", written / "experiment", "--calibration", cal, "-o", out,
                           "--workers", "0"])
        assert "would hold an input" in line
    assert cal.read_bytes() == before


def test_no_partial_output_on_a_full_disk(corrected, tmp_path, monkeypatch):
    import errno

    import ari_sfm.io as io_mod
    from ari_sfm.errors import AriSfmError

    out = tmp_path / "sc"

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io_mod, "calibration_to_json", full)  # disparity.json written first, then this fails
    with pytest.raises(AriSfmError, match="No space left"):
        write_self_calibration(corrected, out)
    assert not any(out.iterdir())  # neither file, no temporary folder
    monkeypatch.undo()
    write_self_calibration(corrected, out)
    assert sorted(p.name for p in out.iterdir()) == ["calibration.json", "disparity.json"]


def test_cli_bad_inputs_are_one_line(written, tmp_path):
    exp, cal = written / "experiment", written / "truth" / "rig_a.json"
    assert "not found" in _cli_error(["self-calibrate", exp, "--calibration", tmp_path / "none.json", "-o",
                                      tmp_path / "o1", "--workers", "0"])
    other = json.loads(cal.read_text())
    other["cameras"]["camX"] = other["cameras"].pop("cam3")
    (tmp_path / "other.json").write_text(json.dumps(other))
    assert "another rig" in _cli_error(["self-calibrate", exp, "--calibration", tmp_path / "other.json", "-o",
                                        tmp_path / "o2", "--workers", "0"])
    line = _cli_error(["self-calibrate", exp, "--calibration", cal, "-o", tmp_path / "o3", "--workers", "0",
                       "--tolerance-px", 0.2, "--max-tolerance-px", 0.2, "--final-tolerance-px", 0.1])
    assert "no confident matches" in line and "--max-tolerance-px" in line
    assert not (tmp_path / "o3" / "calibration.json").exists()
    assert "--min-cameras" in _cli_error(["self-calibrate", exp, "--calibration", cal, "-o", tmp_path / "o4",
                                          "--min-cameras", 2])
    pinhole = json.loads(cal.read_text())
    pinhole["model"] = "pinhole"
    (tmp_path / "pinhole.json").write_text(json.dumps(pinhole))
    assert "exact" in _cli_error(["self-calibrate", exp, "--calibration", tmp_path / "pinhole.json", "-o",
                                  tmp_path / "o5", "--workers", "0"])


def test_dask_local_cluster_gives_the_serial_result(written, tmp_path):
    from ari_sfm.particles.selfcal import self_calibrate_dataset

    args = (written / "experiment", written / "truth" / "rig_a.json")
    options = SelfCalOptions(cells=(2, 2, 1), max_rounds=2, threads=1)
    serial = self_calibrate_dataset(*args, tmp_path / "serial", options, workers=0)
    dask = self_calibrate_dataset(*args, tmp_path / "dask", options, workers=1)  # frames as tasks on a LocalCluster
    for name in serial.calibration.cameras:
        assert np.array_equal(serial.calibration.cameras[name].cam_from_world.R,
                              dask.calibration.cameras[name].cam_from_world.R)
    assert json.loads((tmp_path / "serial" / "disparity.json").read_text()) == \
        json.loads((tmp_path / "dask" / "disparity.json").read_text())

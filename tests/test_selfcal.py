"""Volume self-calibration through the window: disparity peaks among ghosts, the corrected rig against
the simulation's rig B, the held gauge, the outputs, the GTSAM backend and the command line."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.io import load_calibration
from ari_sfm.cli import main
from ari_sfm.geometry import rotation_angle_deg
from ari_sfm.metrics import rigid_alignment
from ari_sfm.particles.disparity import Cells, ParticleSet, _joint_peak, disparity_map
from ari_sfm.particles.match import match_frame
from ari_sfm.particles.selfcal import (SelfCalOptions, converged, disparity_json, refine_with_landmarks, self_calibrate,
                                       sum_baselines_mm, write_self_calibration)
from ari_sfm.particles.truth import score_frame, true_ids
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
    rel = lambda c: c.cameras[name].cam_from_world.R @ c.cameras[first].cam_from_world.R.T
    return rotation_angle_deg(rel(cal), rel(truth))


def _score_and_aligned_rms(exp, volume, calibration, tolerance_px: float = 0.5):
    """Found / ghost score of matching every frame, and the 3D RMS of the correct particles after a rigid
    alignment onto the truth."""
    total, P, Q = None, [], []
    for f, det in enumerate(exp.detections):
        m = match_frame(calibration, det, tolerance_px, volume=volume, min_cameras=3)
        s = score_frame(m.xyz, m.rows, exp.cameras, exp.particle_ids[f], exp.positions[f])
        total = s if total is None else total + s
        ids = true_ids(m.rows, exp.cameras, exp.particle_ids[f])
        first = ids.max(axis=1)
        ok = np.all((ids < 0) | (ids == first[:, None]), axis=1)
        P.append(m.xyz[ok])
        Q.append(exp.positions[f][first[ok]])
    P, Q = np.concatenate(P), np.concatenate(Q)
    if not len(P):
        return total, float("nan")
    R, t = rigid_alignment(P, Q)
    return total, float(np.sqrt(np.mean(np.sum((P @ R.T + t - Q) ** 2, axis=1))))


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


def test_the_gauge_is_held(experiment, corrected):
    a, c = experiment.truth_a, corrected.calibration
    assert np.array_equal(c.cameras["cam0"].cam_from_world.R, a.cameras["cam0"].cam_from_world.R)
    assert np.array_equal(c.normal_world, a.normal_world)
    assert c.interface == a.interface
    assert abs(sum_baselines_mm(c) - sum_baselines_mm(a)) < 1e-3
    for name in a.cameras:
        assert np.array_equal(c.cameras[name].K, a.cameras[name].K)
    assert "sum of the distances" in c.extra["self_calibration"]["scale"]["how"]


def test_matching_with_the_corrected_calibration_is_as_good_as_with_the_truth(experiment, volume, corrected):
    truth, truth_rms = _score_and_aligned_rms(experiment, volume, experiment.truth_b)
    drifted, _ = _score_and_aligned_rms(experiment, volume, experiment.truth_a)
    after, after_rms = _score_and_aligned_rms(experiment, volume, corrected.calibration)
    assert drifted.found_fraction < 0.1  # PHYSICS.md: the drifted calibration finds almost nothing
    assert truth.found_fraction >= 0.95 and truth.ghost_fraction <= 0.05
    assert after.found_fraction >= 0.95, after
    assert after.ghost_fraction <= 0.05, after  # >= 95 % of the particles with the right image in every camera
    assert after_rms <= 1.5 * truth_rms, (after_rms, truth_rms)


def test_outputs_load_and_hold_the_maps(corrected, tmp_path):
    write_self_calibration(corrected, tmp_path)
    cal = load_calibration(tmp_path / "calibration.json")  # an ordinary calibration
    assert cal.model == "exact"
    sc = cal.extra["self_calibration"]
    assert sc["frames"] == [0, 1] and sc["particles_used"] > 0
    assert set(sc["disparity_rms_px"]) == set(cal.cameras)
    d = json.loads((tmp_path / "disparity.json").read_text())
    assert d == json.loads(json.dumps(disparity_json(corrected)))
    for when in ("before", "after"):
        for name, cam in d[when]["cameras"].items():
            assert len(cam["vector_px"]) == len(cam["count"]) == 27
            assert sum(cam["count"]) <= sum(cam["total"])


# --------------------------------------------------------------------------- the bundle adjustment


def _true_landmarks(exp, calibration, count: int = 120) -> ParticleSet:
    """The first particles of frame 0 seen by every camera, their true images, triangulated with ``calibration``."""
    from ari_sfm.triangulate import triangulate_pixels

    det, ids = exp.detections[0], exp.particle_ids[0]
    common = set(range(len(exp.positions[0])))
    for c in exp.cameras:
        common &= set(ids[c].tolist())
    chosen = sorted(common)[:count]
    pixels = np.stack([det[c][np.argsort(ids[c])][np.searchsorted(np.sort(ids[c]), chosen)] for c in exp.cameras], 1)
    xyz = triangulate_pixels(calibration, {c: pixels[:, k] for k, c in enumerate(exp.cameras)})[0]
    return ParticleSet(pixels, xyz, np.zeros(len(chosen), int))


def test_gtsam_backend_solves_the_same_problem(experiment):
    landmarks = _true_landmarks(experiment, experiment.truth_a, 40)
    numpy_cal, _ = refine_with_landmarks(experiment.truth_a, landmarks, SelfCalOptions())
    gtsam_cal, report = refine_with_landmarks(experiment.truth_a, landmarks, SelfCalOptions(backend="gtsam"))
    for name in experiment.cameras:
        assert rotation_angle_deg(numpy_cal.cameras[name].cam_from_world.R,
                                  gtsam_cal.cameras[name].cam_from_world.R) < 1e-4
        assert np.allclose(numpy_cal.cameras[name].cam_from_world.t, gtsam_cal.cameras[name].cam_from_world.t,
                           atol=1e-4)
    assert abs(report.sum_baselines_final_mm - report.sum_baselines_held_mm) < 1e-3


def test_window_and_intrinsics_only_move_when_asked(experiment):
    a = experiment.truth_a
    landmarks = _true_landmarks(experiment, a, 300)
    held, _ = refine_with_landmarks(a, landmarks, SelfCalOptions())
    free, _ = refine_with_landmarks(a, landmarks, SelfCalOptions(refine_window=True, refine_intrinsics=True))
    assert np.array_equal(held.normal_world, a.normal_world) and held.interface == a.interface
    assert not np.array_equal(free.normal_world, a.normal_world)
    assert free.interface.distance_mm != a.interface.distance_mm  # under water the distance is estimated
    for name in a.cameras:
        assert np.array_equal(held.cameras[name].K, a.cameras[name].K)
        assert not np.array_equal(free.cameras[name].K, a.cameras[name].K)
        assert np.array_equal(free.cameras[name].dist, a.cameras[name].dist)  # distortion stays held
        assert abs(free.cameras[name].K[0, 0] / a.cameras[name].K[0, 0] - 1) < 0.01


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
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    assert "Traceback" not in r.output
    return lines[0]


def test_cli_self_calibrate_writes_a_calibration_every_command_loads(written, tmp_path):
    out = tmp_path / "sc"
    r = _run(["self-calibrate", written / "experiment", "--calibration", written / "truth" / "rig_a.json", "-o", out,
              "--workers", "0", "--cells", 2, 2, 1])
    assert r.exit_code == 0, r.output
    assert "cam3: disparity RMS" in r.output and "scale held" in r.output
    cal = load_calibration(out / "calibration.json")
    assert max(v["after"] for v in cal.extra["self_calibration"]["disparity_rms_px"].values()) <= 1.5 * SIGMA_PX
    r = _run(["particles", written / "experiment", "--calibration", out / "calibration.json", "-o", tmp_path / "p",
              "--workers", "0"])
    assert r.exit_code == 0, r.output
    r = _run(["report", out])  # the report of a self-calibration folder shows the disparity maps
    assert r.exit_code == 0, r.output
    page = (out / "report.html").read_text()
    assert "Volume self-calibration" in page and 'alt="disparity maps"' in page


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
    options = SelfCalOptions(cells=(2, 2, 1), max_rounds=2)
    serial = self_calibrate_dataset(*args, tmp_path / "serial", options, workers=0)
    dask = self_calibrate_dataset(*args, tmp_path / "dask", options, workers=1)  # frames as tasks on a LocalCluster
    for name in serial.calibration.cameras:
        assert np.array_equal(serial.calibration.cameras[name].cam_from_world.R,
                              dask.calibration.cameras[name].cam_from_world.R)
    assert json.loads((tmp_path / "serial" / "disparity.json").read_text()) == \
        json.loads((tmp_path / "dask" / "disparity.json").read_text())

"""Particles behind the window: the simulator, the refracted epipolar curves, matching against the truth,
the data contract (1.2), detection from images, and the command line's one-line errors."""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.geometry import rotation_angle_deg
from ari_sfm.io import load_calibration
from ari_sfm.particles.match import _candidates, footprint_mm_per_px, match_frame
from ari_sfm.particles.truth import score_frame
from ari_sfm.particles.volume import Volume
from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment, write_particle_experiment

SMALL = ParticleSimOptions(particles_per_frame=300, num_frames=2, seed=3)


@pytest.fixture(scope="session")
def experiment():
    return simulate_particle_experiment(SMALL)


@pytest.fixture(scope="session")
def written(experiment, tmp_path_factory):
    out = tmp_path_factory.mktemp("particles_sim")
    write_particle_experiment(experiment, out, render_frames=1)
    return out


def _volume(exp) -> Volume:
    return Volume(exp.volume_min_mm, exp.volume_max_mm)


def _score(exp, f, m):
    return score_frame(m.xyz, m.rows, exp.cameras, exp.particle_ids[f], exp.positions[f])


# --------------------------------------------------------------------------- simulator


def test_simulated_rig_b_is_rig_a_with_the_drift(experiment):
    """Rig B moves cameras 1-3 by 0.05 deg and 0.3 mm; camera 0 (the world) and the window stay."""
    a, b = experiment.truth_a, experiment.truth_b
    assert np.allclose(a.normal_world, b.normal_world)
    for k, cam in enumerate(experiment.cameras):
        Ra, Rb = a.cameras[cam].cam_from_world.R, b.cameras[cam].cam_from_world.R
        move = np.linalg.norm(a.cameras[cam].cam_from_world.inverse().t - b.cameras[cam].cam_from_world.inverse().t)
        if k == 0:
            assert rotation_angle_deg(Ra, Rb) < 1e-12 and move < 1e-12
        else:
            assert rotation_angle_deg(Ra, Rb) == pytest.approx(0.05, abs=1e-9)
            assert move == pytest.approx(0.3, abs=1e-9)


def test_detections_are_exact_projections_plus_the_noise(experiment):
    """Each detection is its true particle's exact Snell projection through rig B, with ~0.1 px noise."""
    f = 0
    res = []
    for cam in experiment.cameras:
        ids = experiment.particle_ids[f][cam]
        uv = experiment.truth_b.project_world(cam, experiment.positions[f][ids])
        res.append(experiment.detections[f][cam] - uv)
    res = np.concatenate(res)
    assert np.std(res) == pytest.approx(0.1, rel=0.1)
    assert np.abs(np.mean(res, axis=0)).max() < 0.01


def test_written_layout_loads(written):
    from ari_sfm.io import load_dataset
    from ari_sfm.io.particles import load_particle_dataset, read_detections

    calib = load_dataset(written / "calibration")
    assert calib.target.type == "points3d" and len(calib.observations) == 4 * SMALL.calibration_frames
    ds = load_particle_dataset(written / "experiment")
    det = read_detections(ds.detections, ds.cameras)
    assert sorted(det.frames.tolist()) == [0, 1]
    assert ds.image_path("cam2", 0).is_file() and ds.volume.frame == "cam0"
    truth = pq.read_table(written / "truth" / "detections.parquet")
    assert truth.num_rows == len(det.frame)
    assert load_calibration(written / "truth" / "rig_b.json").model == "truth"


def test_board_start_changes_only_rig_a_target(experiment, tmp_path):
    """calibration_target 'board': rig A calibrated on a planar checkerboard, every view tilted 10-40 deg and
    seen whole by every camera; the rig, its drift and the particles are those of the body's experiment (same
    seed); calibrated as a user would (exact model, distortion), rig A's fx fy cx cy come out within 4 of
    their sigmas; one window only."""
    from dataclasses import replace

    from ari_sfm.calibration.calibrate import calibrate
    from ari_sfm.io import load_dataset
    from ari_sfm.simulate.particles import BOARD

    exp = simulate_particle_experiment(replace(SMALL, calibration_target="board", calibration_frames=10))
    for name in exp.cameras:
        assert np.array_equal(exp.truth_b.cameras[name].cam_from_world.R,
                              experiment.truth_b.cameras[name].cam_from_world.R)
    assert all(np.array_equal(a, b) for a, b in zip(exp.positions, experiment.positions))
    write_particle_experiment(exp, tmp_path, render_frames=0)
    ds = load_dataset(tmp_path / "calibration")
    assert ds.target.type == "checkerboard" and ds.target.inner_corners == BOARD.inner_corners
    assert len(ds.observations) == 4 * 10 and all(len(o.ids) == 88 for o in ds.observations)
    normals = [exp.rig_a.calibration[f].R[:, 2] for f in exp.rig_a.calibration]
    axis = np.mean(normals, axis=0) / np.linalg.norm(np.mean(normals, axis=0))
    tilts = [math.degrees(math.acos(min(1.0, abs(n @ axis)))) for n in normals]
    assert max(tilts) > 15.0  # tilted views (a board facing the rig in every view leaves the focal length free)
    cal = calibrate(ds, model="exact", distortion=True)
    assert cal.quality.ok, cal.quality.why
    for name in exp.cameras:
        sig = cal.uncertainty.cameras[name].intrinsics
        err = np.asarray(cal.cameras[name].params[:4]) - np.asarray(exp.truth_a.cameras[name].params[:4])
        for k, key in enumerate(("fx", "fy", "cx", "cy")):
            assert abs(err[k]) < 4.0 * sig[key], (name, key, err[k], sig[key])
    with pytest.raises(ValueError, match="one side"):
        simulate_particle_experiment(replace(SMALL, calibration_target="board", windows=2))
    with pytest.raises(ValueError, match="calibration_target"):
        simulate_particle_experiment(replace(SMALL, calibration_target="plate"))


# --------------------------------------------------------------------------- geometry of the matching


def test_volume_clips_rays_to_the_box():
    v = Volume(np.array([-1.0, -2.0, 10.0]), np.array([1.0, 2.0, 20.0]))
    o = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.08, 0.0, 1.0] / np.linalg.norm([0.08, 0.0, 1.0]), [0.0, 0.0, 1.0]])
    s0, s1 = v.clip_rays(o, d)
    assert s0[0] == pytest.approx(10.0) and s1[0] == pytest.approx(20.0)
    k = math.sqrt(1.0 + 0.08 ** 2)  # leaves through x = 1 at z = 12.5
    assert s0[1] == pytest.approx(10.0 * k) and s1[1] == pytest.approx(12.5 * k)
    assert np.isnan(s0[2]) and np.isnan(s1[2])  # misses the box


def test_refracted_epipolar_curve_passes_through_the_true_image(experiment):
    """Noise-free images: every true partner lies within 0.01 px of the sampled curve (the polyline of exact
    projections is the curve to far below the noise), though the curve bows off its chord by more than that."""
    cal, f = experiment.truth_b, 0
    cams = experiment.cameras
    vol = _volume(experiment)
    exact = experiment.exact_pixels[f]
    ref, other = cams[0], cams[2]
    o, d = cal.rays_world(ref, exact[ref])
    s0, s1 = vol.clip_rays(o, d)
    i, j = _candidates(cal, other, exact[other], o, d, s0, s1, 0.01)
    pid_ref, pid_other = experiment.particle_ids[f][ref], experiment.particle_ids[f][other]
    pairs = set(zip(pid_ref[i].tolist(), pid_other[j].tolist()))
    common = set(pid_ref.tolist()) & set(pid_other.tolist())
    assert all((p, p) in pairs for p in common)
    # the curve bends: its middle is off the chord of its ends by more than the 0.01 px tolerance above
    mid = 0.5 * (s0 + s1)
    ends = [cal.project_world(other, o + s[:, None] * d) for s in (s0, mid, s1)]
    chord = ends[2] - ends[0]
    normal = np.stack([-chord[:, 1], chord[:, 0]], 1) / np.linalg.norm(chord, axis=1, keepdims=True)
    bow = np.abs(np.einsum("ij,ij->i", ends[1] - ends[0], normal))
    assert np.nanmax(bow) > 0.02


def test_footprint_matches_the_focal_length_and_the_water(experiment):
    """mm per px at ~410 mm through 10 mm glass into water: between the air pinhole's z/f and it over n_water."""
    cal = experiment.truth_b
    centre = 0.5 * (experiment.volume_min_mm + experiment.volume_max_mm)
    fp = footprint_mm_per_px(cal, experiment.cameras, centre)
    for k, cam in enumerate(experiment.cameras):
        z = np.linalg.norm(centre - cal.cameras[cam].cam_from_world.inverse().t)
        f = cal.cameras[cam].K[0, 0]
        assert z / f / 1.333 < fp[k] < z / f


# --------------------------------------------------------------------------- matching against the truth


def test_true_calibration_finds_the_particles(experiment):
    """With rig B's calibration: >= 95 % found, <= 5 % ghosts, 3D error at the noise level
    (0.1 px ~ 0.012 mm per image; measured 0.02 mm RMS)."""
    total = None
    for f in range(SMALL.num_frames):
        m = match_frame(experiment.truth_b, experiment.detections[f], 0.5, volume=_volume(experiment))
        s = _score(experiment, f, m)
        total = s if total is None else total + s
        assert (m.ray_gap_mm < 0.5 * footprint_mm_per_px(experiment.truth_b, experiment.cameras,
                                                           experiment.volume_min_mm + 15).max()).all()
    assert total.found_fraction >= 0.95
    assert total.ghost_fraction <= 0.05
    assert total.rms_error_mm < 0.04


def test_noise_free_images_round_trip_to_the_particles(experiment):
    """Exact (noise-free) images: every particle found, its point at the truth to 1e-6 mm and its rays
    through it (ray gap ~0): the curves, the triangulation and the truth share one physics."""
    m = match_frame(experiment.truth_b, experiment.exact_pixels[0], 0.5, volume=_volume(experiment))
    s = _score(experiment, 0, m)
    assert s.found == s.seen == SMALL.particles_per_frame and s.ghosts == 0
    assert s.rms_error_mm < 1e-6
    assert m.ray_gap_mm.max() < 1e-6


def test_rows_index_each_detection_once(experiment):
    m = match_frame(experiment.truth_b, experiment.detections[0], 0.5, volume=_volume(experiment))
    for k in range(m.rows.shape[1]):
        used = m.rows[m.rows[:, k] >= 0, k]
        assert len(used) == len(np.unique(used))
    assert (m.num_cameras >= 3).all()


def test_drifted_calibration_loses_the_particles(experiment):
    """Rig A's calibration after the 0.05 deg / 0.3 mm drift shifts images by px: at 0.5 px almost nothing
    matches (what volume self-calibration is for)."""
    m = match_frame(experiment.truth_a, experiment.detections[0], 0.5, volume=_volume(experiment))
    assert _score(experiment, 0, m).found_fraction < 0.2


def test_three_cameras_suffice(experiment):
    """A camera's images removed: the others still find the particles (3-camera combinations)."""
    det = dict(experiment.detections[0])
    det["cam3"] = np.empty((0, 2))
    m = match_frame(experiment.truth_b, det, 0.5, volume=_volume(experiment))
    s = score_frame(m.xyz, m.rows, experiment.cameras, {**experiment.particle_ids[0], "cam3": np.empty(0, int)},
                    experiment.positions[0])
    assert s.found_fraction >= 0.95 and s.ghost_fraction <= 0.05
    assert (m.rows[:, 3] == -1).all()


def test_depth_range_alone_works(experiment):
    z0, z1 = experiment.volume_min_mm[2], experiment.volume_max_mm[2]
    m = match_frame(experiment.truth_b, experiment.detections[0], 0.5, depth_range_mm=(z0, z1))
    assert _score(experiment, 0, m).found_fraction >= 0.95


# --------------------------------------------------------------------------- the contract and the CLI


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _hand_written_experiment(exp, folder: Path) -> Path:
    """A particle experiment as another lab would write it: rig.json without target, detections through
    pyarrow with int32 frames, float32 pixels, no intensity, rows interleaved across cameras."""
    folder.mkdir(parents=True, exist_ok=True)
    rig = {"format": "ari-sfm/1",
           "interface": {"thickness_mm": 10.0, "index": 1.5168, "medium_index": 1.333},
           "cameras": {c: {"image_size": [2448, 2048]} for c in exp.cameras},
           "particles": {"detections": "tracks/centres.parquet",
                         "volume_mm": {"min": exp.volume_min_mm.tolist(), "max": exp.volume_max_mm.tolist()}}}
    (folder / "rig.json").write_text(json.dumps(rig))
    frame, cam, u, v, pid = [], [], [], [], []
    for f in range(len(exp.detections)):
        for c in exp.cameras:
            n = len(exp.detections[f][c])
            frame += [f] * n
            cam += [c] * n
            u += exp.detections[f][c][:, 0].tolist()
            v += exp.detections[f][c][:, 1].tolist()
            pid += exp.particle_ids[f][c].tolist()
    order = np.random.default_rng(0).permutation(len(frame))
    table = pa.table({"camera": pa.array(np.asarray(cam)[order].tolist(), pa.string()),
                      "frame": pa.array(np.asarray(frame)[order], pa.int32()),
                      "u": pa.array(np.asarray(u)[order], pa.float32()),
                      "v": pa.array(np.asarray(v)[order], pa.float32())})
    (folder / "tracks").mkdir(exist_ok=True)
    pq.write_table(table, folder / "tracks" / "centres.parquet")
    np.save(folder / "pid.npy", np.asarray(pid)[order])
    return folder


def test_contract_round_trip_of_a_hand_written_experiment(experiment, written, tmp_path):
    """particles.parquet and rig.json written by hand are read; particles3d.parquet has the contract's
    columns, and its row_<camera> columns point at rows of the same true particle."""
    folder = _hand_written_experiment(experiment, tmp_path / "lab")
    out = tmp_path / "out"
    r = _run(["particles", folder, "--calibration", written / "truth" / "rig_b.json", "-o", out, "--workers", "0"])
    assert r.exit_code == 0, r.output
    t = pq.read_table(out / "particles3d.parquet")
    for col in ("frame", "x", "y", "z", "ray_gap_mm", "cameras") + tuple(f"row_{c}" for c in experiment.cameras):
        assert col in t.column_names
    assert t.schema.field("frame").type == pa.int64() and t.schema.field("row_cam0").type == pa.int64()
    pid = np.load(folder / "pid.npy")
    rows = np.stack([t.column(f"row_{c}").to_numpy() for c in experiment.cameras], 1)
    ids = np.where(rows >= 0, pid[np.maximum(rows, 0)], -1)
    first = ids.max(axis=1)
    correct = np.all((ids == -1) | (ids == first[:, None]), axis=1)
    assert correct.mean() >= 0.95
    assert len(t) >= 0.95 * 2 * SMALL.particles_per_frame
    summary = json.loads((out / "particles3d.json").read_text())
    assert summary["particles"] == len(t) and summary["tolerance_px"] == 0.5
    assert set(summary["frames"]) == {"0", "1"} and summary["matched_fraction"] > 0.9


def _cli_error(args) -> str:
    r = _run(args)
    assert r.exit_code == 1, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    assert "Traceback" not in r.output
    return lines[0]


def _copy_experiment(written: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "exp"
    shutil.copytree(written / "experiment", dst, ignore=shutil.ignore_patterns("images"))
    return dst


def test_bad_inputs_are_one_line(written, tmp_path):
    cal = written / "truth" / "rig_b.json"
    exp = _copy_experiment(written, tmp_path)
    # missing parquet
    (exp / "particles.parquet").rename(exp / "moved.parquet")
    assert "no such file" in _cli_error(["particles", exp, "--calibration", cal, "-o", tmp_path / "o1",
                                         "--workers", "0"])
    # a camera not in rig.yaml
    t = pq.read_table(exp / "moved.parquet")
    cams = t.column("camera").to_pylist()
    cams[5] = "cam9"
    pq.write_table(t.set_column(t.column_names.index("camera"), "camera", pa.array(cams)), exp / "particles.parquet")
    assert "cam9" in _cli_error(["particles", exp, "--calibration", cal, "-o", tmp_path / "o2", "--workers", "0"])
    # NaN u
    u = t.column("u").to_numpy().copy()
    u[7] = np.nan
    pq.write_table(t.set_column(t.column_names.index("u"), "u", pa.array(u)), exp / "particles.parquet")
    assert "finite" in _cli_error(["particles", exp, "--calibration", cal, "-o", tmp_path / "o3", "--workers", "0"])
    pq.write_table(t, exp / "particles.parquet")
    # a calibration of another rig
    other = json.loads(cal.read_text())
    other["cameras"]["camX"] = other["cameras"].pop("cam3")
    (tmp_path / "other.json").write_text(json.dumps(other))
    assert "another rig" in _cli_error(["particles", exp, "--calibration", tmp_path / "other.json", "-o",
                                        tmp_path / "o4", "--workers", "0"])
    # -o equal to the dataset
    assert "dataset folder" in _cli_error(["particles", exp, "--calibration", cal, "-o", exp, "--workers", "0"])
    assert "dataset folder" in _cli_error(["detect-particles", written / "experiment", "-o", written / "experiment",
                                           "--workers", "0"])
    # images only: no detections to match
    rig = (exp / "rig.yaml").read_text().replace("detections: particles.parquet", "")
    (tmp_path / "imgonly").mkdir()
    (tmp_path / "imgonly" / "rig.yaml").write_text(rig)
    assert "detect-particles" in _cli_error(["particles", tmp_path / "imgonly", "--calibration", cal, "-o",
                                             tmp_path / "o6", "--workers", "0"])
    # more cameras than the rig has
    assert "--min-cameras" in _cli_error(["particles", exp, "--calibration", cal, "-o", tmp_path / "o5",
                                          "--workers", "0", "--min-cameras", "5"])


def test_simulate_particles_cli(tmp_path):
    r = _run(["simulate", "particles", "-o", tmp_path / "sim", "--particles", "50", "--frames", "2",
              "--render-frames", "0", "--cameras", "3", "--drift-cameras", "2", "--drift-deg", "0.1"])
    assert r.exit_code == 0, r.output
    a = json.loads((tmp_path / "sim" / "truth" / "rig_a.json").read_text())
    b = json.loads((tmp_path / "sim" / "truth" / "rig_b.json").read_text())
    assert list(a["cameras"]) == ["cam0", "cam1", "cam2"]
    angle = rotation_angle_deg(np.array(a["cameras"]["cam2"]["cam_from_world"]["R"]),
                               np.array(b["cameras"]["cam2"]["cam_from_world"]["R"]))
    assert angle == pytest.approx(0.1, abs=1e-9)
    assert a["cameras"]["cam1"] == b["cameras"]["cam1"]
    assert "--drift-cameras" in _cli_error(["simulate", "particles", "-o", tmp_path / "x", "--drift-cameras", "7"])
    r = _run(["simulate", "particles", "-o", tmp_path / "board", "--particles", "50", "--frames", "1",
              "--render-frames", "0", "--calibration-target", "board", "--calibration-views", "4"])
    assert r.exit_code == 0, r.output
    rig = yaml.safe_load((tmp_path / "board" / "calibration" / "rig.yaml").read_text())
    assert rig["target"]["type"] == "checkerboard" and len(rig["calibration"]) == 4
    assert "--calibration-target" in _cli_error(["simulate", "particles", "-o", tmp_path / "y", "--calibration-target",
                                                 "board", "--windows", "2"])
    assert "--calibration-views" in _cli_error(["simulate", "particles", "-o", tmp_path / "z",
                                                "--calibration-views", "0"])

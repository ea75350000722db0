"""Reconstruction through the window (paper Sec. 5) on exact-physics simulations.

Binocular rig, 50 mm N-BK7 plate, 11 stage frames (-10..10 mm), sigma 0.05 px,
calibrated with model='exact' (and 'ari'). Triangulation round trips, the
metrics against truth, points.json / .ply files, and every bad input.
"""
from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.calibration.record import Calibration
from ari_sfm.cli import main
from ari_sfm.errors import AriSfmError
from ari_sfm.io import parse_calibration, save_calibration
from ari_sfm.reconstruction.metrics import (
    ReconstructionMetrics,
    reconstruction_metrics,
    rigid_alignment,
    save_point_clouds,
)
from ari_sfm.reconstruction.reconstruct import Points, reconstruct
from ari_sfm.reconstruction.triangulate import triangulate_pixels, triangulate_rays
from ari_sfm.simulate import make_scene, simulate

# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def scene():
    return make_scene("binocular", seed=0, sigma_px=0.05)


@pytest.fixture(scope="module")
def cal_exact(scene):
    return calibrate(scene.dataset, model="exact", uncertainty=False)


@pytest.fixture(scope="module")
def cal_ari(scene):
    return calibrate(scene.dataset, model="ari", uncertainty=False)


@pytest.fixture(scope="module")
def truth_cal(scene):
    return parse_calibration(scene.truth)


@pytest.fixture(scope="module")
def exact_result(scene, cal_exact):
    points = reconstruct(scene.dataset, cal_exact)
    return points, reconstruction_metrics(points, scene.dataset.target, scene.truth)


@pytest.fixture(scope="module")
def files(tmp_path_factory, cal_exact):
    """The binocular dataset and its truth on disk, with the exact calibration beside them."""
    out = tmp_path_factory.mktemp("recon")
    ds, truth = simulate("binocular", out / "sim", seed=0, images=False)
    save_calibration(cal_exact, out / "calibration.json")
    return ds, truth, out / "calibration.json"


def _truth_points(scene) -> np.ndarray:
    return np.concatenate([np.asarray(v["xyz"]) for v in scene.truth["reconstruction_points_world"].values()])


class NoRaysCalibration(Calibration):
    """A calibration whose model cannot back-project (as the polynomial model 'pf'): rays_world raises."""

    def rays_world(self, camera, uv):
        raise ValueError("this model maps world points to pixels only")


def _without_rays(cal: Calibration) -> Calibration:
    return NoRaysCalibration(**{f: getattr(cal, f) for f in cal.__dataclass_fields__})


# --------------------------------------------------------------------------- triangulate_rays


def test_triangulate_rays_two_skew_rays_gap_is_their_distance():
    # ray 0 along x through (0, 0, 0); ray 1 along y through (0, 0, 2): common perpendicular z, length 2
    o = np.array([[[5.0, 0.0, 0.0], [0.0, -3.0, 2.0]]])
    d = np.array([[[2.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])  # directions need not be unit
    X, gap = triangulate_rays(o, d, np.ones((1, 2), bool))
    assert np.allclose(X, [[0.0, 0.0, 1.0]], atol=1e-12)
    assert gap[0] == pytest.approx(2.0, abs=1e-12)


def test_triangulate_rays_many_rays_through_points_and_degenerate_cases():
    rng = np.random.default_rng(1)
    P, C = 500, 4
    X_true = rng.normal(size=(P, 3)) * 50 + [0, 0, 500]
    centres = np.array([[-100, 0, 0], [100, 0, 0], [0, 80, 0], [0, -80, 10.0]])
    o = np.broadcast_to(centres, (P, C, 3)).copy()
    d = X_true[:, None, :] - o
    valid = rng.random((P, C)) < 0.8
    valid[0] = [True, False, False, False]  # one ray: no point
    valid[1] = [True, True, False, False]
    d[1, 1] = d[1, 0]  # two parallel rays: no point
    o[1, 1] = o[1, 0] + 1.0
    d[~valid] = np.nan  # invalid rays may hold anything
    X, gap = triangulate_rays(o, d, valid)
    ok = valid.sum(axis=1) >= 2
    ok[1] = False
    assert np.isnan(X[~ok]).all() and np.isnan(gap[~ok]).all()
    assert np.abs(X[ok] - X_true[ok]).max() < 1e-9
    assert gap[ok].max() < 1e-9


# --------------------------------------------------------------------------- triangulate_pixels


@pytest.mark.parametrize("which", ["truth", "exact", "ari", "no_rays"])
def test_round_trip_recovers_points_to_1e6_mm(which, scene, truth_cal, cal_exact, cal_ari):
    """sigma 0: project truth points with a calibration, triangulate with it, get them back."""
    cal = {"truth": truth_cal, "exact": cal_exact, "ari": cal_ari, "no_rays": _without_rays(cal_exact)}[which]
    X = _truth_points(scene)
    tracks = {c: cal.project_world(c, X) for c in cal.cameras}
    Y, gap, rmse = triangulate_pixels(cal, tracks)
    assert np.abs(Y - X).max() < 1e-6
    assert gap.max() < 1e-6 and rmse.max() < 1e-6


def test_round_trip_four_cameras_partial_visibility():
    """arc4 truth: points seen by 2-4 of 4 cameras (NaN elsewhere); one camera only gives NaN."""
    arc = make_scene("arc4", seed=0, sigma_px=0.0)
    cal = parse_calibration(arc.truth)
    ids, board = arc.dataset.target.points_3d()
    X = np.concatenate([cal.frames[f].apply(board) for f in sorted(cal.frames)[:8]])
    tracks = {}
    for c, cam in cal.cameras.items():
        uv = cal.project_world(c, X)
        w, h = cam.image_size
        inside = (uv[:, 0] > 0) & (uv[:, 0] < w - 1) & (uv[:, 1] > 0) & (uv[:, 1] < h - 1)
        uv[~inside] = np.nan
        tracks[c] = uv
    names = list(tracks)
    for k in range(5):  # the first points: one camera only
        for c in names[1:]:
            tracks[c][k] = np.nan
        tracks[names[0]][k] = 1000.0
    seen = sum(np.isfinite(t[:, 0]) for t in tracks.values())
    assert (seen >= 2).sum() > 100 and set(np.unique(seen)) >= {1, 2, 3}
    Y, gap, rmse = triangulate_pixels(cal, tracks)
    ok = seen >= 2
    assert np.abs(Y[ok] - X[ok]).max() < 1e-6
    assert np.isnan(Y[~ok]).all() and np.isnan(gap[~ok]).all() and np.isnan(rmse[~ok]).all()


def test_model_without_rays_gives_the_same_points(scene, cal_exact):
    """Start from the frames' centroid + numeric Jacobians: the same reprojection optimum as rays + analytic."""
    tracks = {}
    for o in scene.dataset.select("reconstruction"):
        if o.frame == "r004":
            tracks[o.camera] = o.pixels
    X1, gap1, rmse1 = triangulate_pixels(cal_exact, tracks)
    X2, gap2, rmse2 = triangulate_pixels(_without_rays(cal_exact), tracks)
    assert np.abs(X1 - X2).max() < 1e-6
    assert np.abs(rmse1 - rmse2).max() < 1e-6
    assert np.allclose(gap2, gap1, rtol=0.05, atol=1e-4)  # first-order gap ~ the rays' gap


def test_refinement_lowers_the_reprojection_error(scene, cal_exact):
    tracks = {o.camera: o.pixels for o in scene.dataset.select("reconstruction") if o.frame == "r000"}
    _, gap0, rmse0 = triangulate_pixels(cal_exact, tracks, refine=False)
    _, gap1, rmse1 = triangulate_pixels(cal_exact, tracks, refine=True)
    assert np.array_equal(gap0, gap1)  # a property of the rays, not of the refined point
    assert np.sum(rmse1**2) <= np.sum(rmse0**2)


# --------------------------------------------------------------------------- reconstruction accuracy


def test_exact_reconstruction_meets_the_papers_figures(exact_result):
    """exact model, sigma 0.05 px: measured 0.017 mm vs truth, flatness 0.016, stage 0.004, corners 0.006."""
    points, m = exact_result
    assert m.num_frames == 11 and m.num_points == 11 * 88
    assert m.truth.aligned_rms_mm < 0.05
    assert m.truth.unaligned_rms_mm < 0.1
    assert m.flatness_mm.rmse < 0.03
    stage = m.stage
    assert stage.reference_frame == "r005"  # stage_mm = 0
    assert stage.plane_distance_error_mm.max < 0.02
    assert stage.displacement_error_mm.max < 0.02
    assert abs(stage.travel_scale - 1.0) < 1e-3
    assert m.inter_corner_mm.rmse < 0.02
    assert m.inter_corner_mm.count == 11 * (10 * 8 + 11 * 7)  # every horizontal and vertical pair
    assert m.reprojection_rmse_px < 0.05  # 2 cameras, 3 dof: sigma sqrt(2 / 4) px per point = 0.035
    text = json.dumps(m.to_json(), allow_nan=False)  # JSON, and read back into the same record
    assert ReconstructionMetrics.from_json(json.loads(text)) == m
    assert m.frames["r005"].stage.displacement_error_mm == 0.0 and m.frames["r005"].plane.inliers <= 88


def test_ari_reconstruction(scene, cal_ari):
    """ari model: paraxial bias; measured 0.092 mm vs truth after alignment, flatness 0.052,
    stage 0.099 max, corners 0.0076 mm RMSE (and ~0.9 deg of rotation, 7.6 mm unaligned)."""
    points = reconstruct(scene.dataset, cal_ari)
    m = reconstruction_metrics(points, scene.dataset.target, scene.truth)
    assert m.num_points == 968
    assert m.truth.aligned_rms_mm < 0.15
    assert m.flatness_mm.rmse < 0.08
    assert m.stage.plane_distance_error_mm.max < 0.15
    assert m.inter_corner_mm.rmse < 0.015


def test_rigid_alignment_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(50, 3)) * 30
    w = np.array([0.1, -0.2, 0.3])
    from ari_sfm.geometry import rotation_from_rotvec

    R = rotation_from_rotvec(w)
    B = A @ R.T + [1.0, 2.0, 3.0]
    R_est, t_est = rigid_alignment(A, B)
    assert np.allclose(R_est, R, atol=1e-12) and np.allclose(t_est, [1, 2, 3], atol=1e-12)


# --------------------------------------------------------------------------- files


def test_points_json_and_ply_round_trip(exact_result, tmp_path):
    from ari_sfm.deps import require_open3d

    points, _ = exact_result
    points.save(tmp_path / "points.json", "calibration.json")
    back = Points.load(tmp_path / "points.json")
    assert back.calibration == "calibration.json" and list(back.frames) == list(points.frames)
    for name, f in points.frames.items():
        g = back.frames[name]
        assert g.stage_mm == f.stage_mm and np.array_equal(g.ids, f.ids)
        assert np.array_equal(g.xyz, f.xyz) and np.array_equal(g.ray_gap_mm, f.ray_gap_mm)
    o3d = require_open3d()
    written = save_point_clouds(points, tmp_path / "clouds")
    assert set(written) == set(points.frames) | {"all"}
    for name, f in points.frames.items():
        cloud = o3d.io.read_point_cloud(str(written[name]))
        assert len(cloud.points) == len(f)
        assert np.allclose(np.asarray(cloud.points), f.xyz, atol=1e-9)
    assert len(o3d.io.read_point_cloud(str(written["all"])).points) == points.num_points
    assert not list((tmp_path / "clouds").glob(".*"))  # no temporary file left


def test_cli_reconstruct_writes_points_metrics_and_clouds(files, tmp_path):
    from ari_sfm.deps import require_open3d
    from ari_sfm.io import load_points

    ds, truth, cal = files
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["reconstruct", str(ds), "--calibration", str(cal), "-o", str(out),
                                  "--truth", str(truth)])
    assert r.exit_code == 0, r.output
    for needle in ("968 points", "flatness", "stage", "inter-corner", "vs truth"):
        assert needle in r.output
    pts = load_points(out / "points.json")
    assert len(pts["frames"]) == 11 and all(len(f["ray_gap_mm"]) == 88 for f in pts["frames"].values())
    assert (out / pts["calibration"]).resolve() == cal.resolve()  # relative to points.json
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["format"] == "ari-sfm-reconstruction-metrics/1" and metrics["model"] == "exact"
    assert metrics["truth"]["aligned"]["rms_mm"] < 0.05
    o3d = require_open3d()
    assert len(o3d.io.read_point_cloud(str(out / "clouds" / "all.ply")).points) == 968
    assert len(list((out / "clouds").glob("r*.ply"))) == 11


def test_cli_help():
    r = CliRunner().invoke(main, ["reconstruct", "--help"])
    assert r.exit_code == 0 and "--calibration" in r.output and "--truth" in r.output


# --------------------------------------------------------------------------- bad inputs


def _one_camera(dataset, frames):
    """The dataset with cam1's records of ``frames`` removed (seen by cam0 only)."""
    obs = tuple(o for o in dataset.observations
                if not (o.set == "reconstruction" and o.frame in frames and o.camera == "cam1"))
    return dataset.with_observations(obs)


def test_frame_seen_by_one_camera_is_skipped_with_a_warning(scene, cal_exact, caplog):
    with caplog.at_level(logging.WARNING, logger="ari_sfm.reconstruction.reconstruct"):
        points = reconstruct(_one_camera(scene.dataset, {"r003"}), cal_exact)
    assert "r003" not in points.frames and len(points.frames) == 10
    assert any("r003" in rec.message and "cam0 only" in rec.message for rec in caplog.records)


def test_no_frame_with_two_cameras_is_an_error(scene, cal_exact):
    frames = {f"r{k:03d}" for k in range(11)}
    with pytest.raises(AriSfmError, match="no reconstruction frame can be triangulated.*r000 \\(seen by cam0 only\\)"):
        reconstruct(_one_camera(scene.dataset, frames), cal_exact)


def test_calibration_from_another_rig_is_an_error(scene, cal_exact):
    arc = parse_calibration(make_scene("arc4", seed=0).truth)
    with pytest.raises(AriSfmError, match="another rig: its cameras cam0, cam1, cam2, cam3"):
        reconstruct(scene.dataset, arc)
    cams = dict(cal_exact.cameras, cam1=replace(cal_exact.cameras["cam1"], image_size=(1224, 1024)))
    with pytest.raises(AriSfmError, match="another rig: camera cam1 has image size 1224x1024"):
        reconstruct(scene.dataset, replace(cal_exact, cameras=cams))
    thin = replace(cal_exact, interface=replace(cal_exact.interface, thickness_mm=10.0))
    with pytest.raises(AriSfmError, match="window thickness_mm 10"):
        reconstruct(scene.dataset, thin)


def test_no_reconstruction_frames_is_an_error():
    arc = make_scene("arc4", seed=0)
    with pytest.raises(AriSfmError, match="no reconstruction frames"):
        reconstruct(arc.dataset, parse_calibration(arc.truth))


def test_truth_without_a_frame_is_an_error(exact_result, scene):
    points, _ = exact_result
    truth = dict(scene.truth, reconstruction_points_world={
        k: v for k, v in scene.truth["reconstruction_points_world"].items() if k != "r007"})
    with pytest.raises(AriSfmError, match="frame r007 is not in the truth"):
        reconstruction_metrics(points, scene.dataset.target, truth)


def _edit_json(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def _drop_cam1_recon(ds: Path) -> None:
    _edit_json(ds / "observations.json", lambda o: o.update(observations=[
        r for r in o["observations"] if not (r["set"] == "reconstruction" and r["camera"] == "cam1")]))


def _drop_truth_frame(truth: Path) -> None:
    _edit_json(truth, lambda t: t["reconstruction_points_world"].pop("r004"))


def _four_camera_calibration(cal: Path) -> None:
    _edit_json(cal, lambda c: c["cameras"].update(cam2=c["cameras"]["cam1"]))


def _other_image_size(cal: Path) -> None:
    _edit_json(cal, lambda c: c["cameras"]["cam1"].update(image_size=[640, 480]))


BAD = {  # what to break (dataset folder, truth file, calibration file) -> text the error must contain
    "frames seen by one camera": (_drop_cam1_recon, None, None, "seen by cam0 only"),
    "truth without a frame": (None, _drop_truth_frame, None, "frame r004 is not in the truth"),
    "calibration with other cameras": (None, None, _four_camera_calibration, "another rig"),
    "calibration with other image size": (None, None, _other_image_size, "image size 640x480"),
    "missing calibration": (None, None, lambda c: c.unlink(), "file not found"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_cli_bad_input_one_line_error_exit_1_no_points(case, files, tmp_path):
    import shutil

    ds0, truth0, cal0 = files
    ds = Path(shutil.copytree(ds0, tmp_path / "ds"))
    truth = Path(shutil.copy(truth0, tmp_path / "truth.json"))
    cal = Path(shutil.copy(cal0, tmp_path / "calibration.json"))
    break_ds, break_truth, break_cal, needle = BAD[case]
    for fn, arg in ((break_ds, ds), (break_truth, truth), (break_cal, cal)):
        if fn:
            fn(arg)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["reconstruct", str(ds), "--calibration", str(cal), "-o", str(out),
                                  "--truth", str(truth)])
    assert r.exit_code == 1, r.output
    errors = [ln for ln in r.output.splitlines() if ln.startswith("error: ")]
    assert len(errors) == 1 and needle in errors[0], r.output
    assert "Traceback" not in r.output
    assert not (out / "points.json").exists() and not (out / "metrics.json").exists()

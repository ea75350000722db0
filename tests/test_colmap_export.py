"""export-colmap: the ari rig as COLMAP pinhole cameras, checked by pycolmap's own projection.

pycolmap is called here directly (not through the adapter) so that the test
is an independent check of what COLMAP's tools will read.
"""
from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from click.testing import CliRunner

from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.cli import main
from ari_sfm.colmap.adapter import COLMAP_PIXEL_OFFSET, colmap_from_opencv_px, export_colmap, opencv_from_colmap_px
from ari_sfm.io import load_calibration, load_dataset, save_calibration, save_points
from ari_sfm.simulate import simulate


@pytest.fixture(scope="module")
def binocular(tmp_path_factory):
    """(dataset, truth points.json path) of the simulated binocular rig."""
    out = tmp_path_factory.mktemp("colmap_sim")
    ds_dir, truth_path = simulate("binocular", out, images=False)
    truth = json.loads(Path(truth_path).read_text())
    frames = {k: dict(v, ray_gap_mm=[0.0] * len(v["ids"])) for k, v in truth["reconstruction_points_world"].items()}
    points = out / "points.json"
    save_points(points, frames, "truth.json")
    return load_dataset(ds_dir), points


@pytest.fixture(scope="module")
def binocular_ari(binocular):
    return calibrate(binocular[0], model="ari", uncertainty=False)


def _cam_from_world(image):
    """pycolmap >= 3.12: a method; 3.11: a property."""
    pose = image.cam_from_world
    return pose() if callable(pose) else pose


def colmap_vs_ours(rec, calibration, camera_names: dict[int, str]) -> np.ndarray:
    """|pycolmap projection - Calibration.project_world| (px) for every track element."""
    diffs = []
    for point in rec.points3D.values():
        for el in point.track.elements:
            image = rec.image(el.image_id)
            uv_colmap = image.camera.img_from_cam(_cam_from_world(image) * point.xyz)
            ours = calibration.project_world(camera_names[image.camera_id], point.xyz[None])[0]
            diffs.append(np.abs(np.asarray(uv_colmap).ravel() - COLMAP_PIXEL_OFFSET - ours).max())
    return np.array(diffs)


def test_pixel_convention():
    assert np.allclose(colmap_from_opencv_px([[0.0, 0.0]]), [[0.5, 0.5]])
    assert np.allclose(opencv_from_colmap_px(colmap_from_opencv_px([[3.2, -1.0]])), [[3.2, -1.0]])


def test_ari_export_matches_our_projection(binocular, binocular_ari, tmp_path):
    dataset, points = binocular
    cal = binocular_ari
    export = export_colmap(cal, tmp_path / "model", dataset, points)
    assert not export.warnings and all(v.exact for v in export.cameras.values())
    rec = pycolmap.Reconstruction(str(tmp_path / "model"))  # what COLMAP's tools read
    assert rec.num_cameras() == 2 and rec.num_points3D() == len(export.point3D_ids) > 1000
    n_images = sum(1 for o in dataset.observations if o.set in ("calibration", "reconstruction"))
    assert rec.num_images() == n_images
    names = {cid: name for name, cid in export.camera_ids.items()}
    for cid, name in names.items():
        cam = rec.camera(cid)
        assert cam.model_name == "PINHOLE" and (cam.width, cam.height) == tuple(cal.cameras[name].image_size)
        assert np.allclose(cam.params, [*np.diag(cal.cameras[name].K)[:2], *(cal.cameras[name].K[:2, 2] + 0.5)])
    diff = colmap_vs_ours(rec, cal, names)
    assert len(diff) == rec.compute_num_observations() and diff.max() < 1e-6, diff.max()
    # the virtual camera: the calibrated pose with its centre moved by delta along the normal
    delta = cal.interface.shift_mm
    for image in rec.images.values():
        name = names[image.camera_id]
        pose = _cam_from_world(image)
        expected_t = cal.cameras[name].cam_from_world.t - delta * cal.normal_cam(name)
        assert np.allclose(pose.translation, expected_t, atol=1e-9)
        assert np.allclose(pose.rotation.matrix(), cal.cameras[name].cam_from_world.R, atol=1e-12)
    # 2D points are the detections in COLMAP's pixel convention
    obs = {(o.camera, o.frame): o for o in dataset.observations if o.set != "stacking"}
    for (camera, frame), image_id in export.image_ids.items():
        xy = np.array([p.xy for p in rec.image(image_id).points2D])
        assert np.allclose(xy, obs[(camera, frame)].pixels + 0.5, atol=1e-12)
    # a rig with the first camera as reference, one frame per calibration / reconstruction frame
    if hasattr(rec, "rigs"):
        assert rec.num_rigs() == 1 and rec.num_frames() == len(cal.frames) + len(dataset.reconstruction)
    # ari on exact physics: the reprojection error COLMAP reports is the calibration's own misfit
    mean_error = np.mean([p.error for p in rec.points3D.values() if p.track.length() > 0])
    assert np.isfinite(mean_error)


def test_distortion_models(binocular, binocular_ari, tmp_path):
    """OPENCV (k1 k2 p1 p2) and FULL_OPENCV (with k3) agree with our distortion to 1e-6 px."""
    dataset, _ = binocular
    for dist, model_name in (([-0.08, 0.05, 3e-4, -2e-4, 0.0], "OPENCV"),
                             ([-0.08, 0.05, 3e-4, -2e-4, 0.02], "FULL_OPENCV")):
        cams = {n: replace(c, dist=np.array(dist)) for n, c in binocular_ari.cameras.items()}
        cal = replace(binocular_ari, cameras=cams)
        export = export_colmap(cal, tmp_path / model_name, dataset)
        rec = pycolmap.Reconstruction(str(tmp_path / model_name))
        assert {c.model_name for c in rec.cameras.values()} == {model_name}
        diff = colmap_vs_ours(rec, cal, {cid: n for n, cid in export.camera_ids.items()})
        assert diff.max() < 1e-6, (model_name, diff.max())


def test_exact_model_is_approximated_and_warned(binocular, tmp_path, caplog):
    dataset, points = binocular
    cal = calibrate(dataset, model="exact", uncertainty=False)
    with caplog.at_level(logging.WARNING, logger="ari_sfm.colmap.adapter"):
        export = export_colmap(cal, tmp_path / "model", dataset, points)
    assert any("best ari approximation" in r.getMessage() for r in caplog.records)
    assert export.warnings and not any(v.exact for v in export.cameras.values())
    names = {cid: n for n, cid in export.camera_ids.items()}
    diff = colmap_vs_ours(pycolmap.Reconstruction(str(tmp_path / "model")), cal, names)
    worst = max(v.max_px for v in export.cameras.values())
    assert diff.max() < worst + 1e-6  # the reported error is the true one
    assert all(v.rms_px < 0.6 for v in export.cameras.values())  # binocular 10-15 deg oblique: ~0.4 px
    # keeping K and R (shift only) is worse: the paraxial error is not absorbed
    shift_only = export_colmap(cal, tmp_path / "shift", dataset, points, approximation="shift")
    for name, v in shift_only.cameras.items():
        assert v.rms_px > export.cameras[name].rms_px


def test_underwater_is_a_pure_shift_approximation(tmp_path, caplog):
    ds_dir, _ = simulate("binocular_underwater", tmp_path / "sim", images=False)
    dataset = load_dataset(ds_dir)
    cal = calibrate(dataset, model="ari", uncertainty=False)
    with caplog.at_level(logging.WARNING, logger="ari_sfm.colmap.adapter"):
        export = export_colmap(cal, tmp_path / "model", dataset, approximation="shift")
    assert any("pure-shift" in r.getMessage() for r in caplog.records)
    for name, v in export.cameras.items():
        assert not v.exact and np.isfinite(v.rms_px)
        # shift only: K and R are the calibration's
        assert np.allclose(v.K, cal.cameras[name].K)
        assert np.allclose(v.cam_from_world.R, cal.cameras[name].cam_from_world.R)


def test_point_cloud_opens_in_open3d(binocular, binocular_ari, tmp_path):
    from ari_sfm.deps import require_open3d

    o3d = require_open3d()
    export = export_colmap(binocular_ari, tmp_path / "model", binocular[0], binocular[1])
    cloud = o3d.io.read_point_cloud(str(export.ply_path))
    assert len(cloud.points) == len(export.point3D_ids)
    xyz = np.asarray(cloud.points)
    some = np.array([export.reconstruction.point3D(pid).xyz for pid in list(export.point3D_ids.values())[:50]])
    assert np.all(np.isfinite(xyz)) and np.min(np.linalg.norm(xyz[:, None] - some[None], axis=2), axis=0).max() < 1e-3


def test_cli_export_and_cameras_only(binocular, binocular_ari, tmp_path):
    dataset, points = binocular
    cal_path = tmp_path / "out" / "calibration.json"
    save_calibration(binocular_ari, cal_path)
    r = CliRunner().invoke(main, ["export-colmap", str(cal_path), "-o", str(tmp_path / "model"),
                                  "--dataset", str(dataset.root), "--points", str(points)])
    assert r.exit_code == 0, r.output
    assert "PINHOLE" in r.output and "exact" in r.output
    assert pycolmap.Reconstruction(str(tmp_path / "model")).num_points3D() > 1000
    # no dataset and no observations.json beside the calibration: cameras and poses only
    export = export_colmap(load_calibration(cal_path), tmp_path / "bare")
    assert export.reconstruction.num_cameras() == 2 and export.reconstruction.num_points3D() == 0
    r = CliRunner().invoke(main, ["export-colmap", str(tmp_path / "missing.json"), "-o", str(tmp_path / "x")])
    assert r.exit_code == 1 and r.output.startswith("error:")

"""The refractive COLMAP fork's FLATPORT cameras (colmap_underwater), both ways.

The fork's projection is transcribed here from its ``src/colmap/sensor/models_refrac.h`` and
``ray3d.h`` (FlatPort::CamFromImg, CamFromImgPoint, IterativeProjection, ComputeRefraction,
RayPlaneIntersection) and COLMAP's OpenCV camera model (distortion, iterative undistortion),
independently of ari_sfm.models: it reads only the written text files, and must give our exact
model's pixels to 1e-6 px. Reading the files back must give the calibration again.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.calibration.record import Calibration
from ari_sfm.cli import main
from ari_sfm.colmap.fork import export_colmap_fork, import_colmap_fork
from ari_sfm.errors import AriSfmError
from ari_sfm.io import load_calibration, parse_calibration, save_calibration
from ari_sfm.simulate import make_scene

# ----------------------------------------------------------------------------- the fork, transcribed

N_PARAMS = {"PINHOLE": 4, "OPENCV": 8, "FULL_OPENCV": 12}


def distort(model: str, p: np.ndarray, u: float, v: float) -> tuple[float, float]:
    """COLMAP's OpenCV / FullOpenCV Distortion: (u, v) + (du, dv)."""
    if model == "PINHOLE":
        return u, v
    k1, k2, p1, p2 = p[4:8]
    k3, k4, k5, k6 = p[8:12] if model == "FULL_OPENCV" else (0.0, 0.0, 0.0, 0.0)
    u2, v2, uv = u * u, v * v, u * v
    r2 = u2 + v2
    radial = (1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3) / (1 + k4 * r2 + k5 * r2 ** 2 + k6 * r2 ** 3)
    return u * radial + 2 * p1 * uv + p2 * (r2 + 2 * u2), v * radial + 2 * p2 * uv + p1 * (r2 + 2 * v2)


def img_from_cam_air(model: str, p: np.ndarray, X: np.ndarray) -> np.ndarray:
    u, v = distort(model, p, X[0] / X[2], X[1] / X[2])
    return np.array([p[0] * u + p[2], p[1] * v + p[3]])


def cam_from_img_air(model: str, p: np.ndarray, x: float, y: float) -> np.ndarray:
    """Normalised undistorted (u, v): COLMAP's IterativeUndistortion (Newton, numeric Jacobian)."""
    target = np.array([(x - p[2]) / p[0], (y - p[3]) / p[1]])
    uv = target.copy()
    if model == "PINHOLE":
        return uv
    for _ in range(100):
        step = np.maximum(1e-10, np.abs(uv) * 1e-6)
        J = np.zeros((2, 2))
        for k in range(2):
            e = np.zeros(2)
            e[k] = step[k]
            J[:, k] = (np.array(distort(model, p, *(uv + e))) - np.array(distort(model, p, *(uv - e)))) / (2 * step[k])
        delta = np.linalg.solve(J, target - np.array(distort(model, p, *uv)))
        uv = uv + delta
        if np.max(np.abs(delta)) < 1e-15:
            break
    return uv


def refract(normal: np.ndarray, n1: float, n2: float, v: np.ndarray) -> np.ndarray:
    """ray3d.h ComputeRefraction."""
    if n1 == n2:
        return v
    r = n1 / n2
    c = normal @ v
    v = r * v - (r * c - np.sqrt(1.0 - r * r * (1.0 - c * c))) * normal
    return v / np.linalg.norm(v)


def plane_hit(ori: np.ndarray, direction: np.ndarray, normal: np.ndarray, dist: float) -> float:
    """ray3d.h RayPlaneIntersection: the plane {x: normal . x = dist}."""
    return ((dist * normal - ori) @ normal) / (direction @ normal)


def flatport_cam_from_img(model, p, refrac, x, y):
    """FlatPort::CamFromImg: the refracted ray (origin on the outer face, direction) of pixel (x, y)."""
    n, dist, thick, na, ng, nw = refrac[:3], refrac[3], refrac[4], *refrac[5:8]
    direction = np.append(cam_from_img_air(model, p, x, y), 1.0)
    direction = direction / np.linalg.norm(direction)
    ori = plane_hit(np.zeros(3), direction, n, dist) * direction
    direction = refract(n, na, ng, direction)
    ori = ori + plane_hit(ori, direction, n, dist + thick) * direction
    return ori, refract(n, ng, nw, direction)


def flatport_cam_from_img_point(model, p, refrac, x, y, d):
    """FlatPort::CamFromImgPoint: the point of the refracted ray at distance d from the camera centre."""
    ori, direction = flatport_cam_from_img(model, p, refrac, x, y)
    b = ori @ direction
    lam = -b + np.sqrt(b * b - ori @ ori + d * d)  # the root >= 0 (|direction| = 1)
    return ori + lam * direction


def flatport_img_from_cam(model, p, refrac, X):
    """FlatPort::ImgFromCam: the in-air projection, then IterativeProjection (Gauss-Newton)."""
    xy = img_from_cam_air(model, p, X)
    d = np.linalg.norm(X)
    for _ in range(100):
        steps = np.maximum(1e-6, np.abs(1e-9 * xy))
        err = flatport_cam_from_img_point(model, p, refrac, *xy, d) - X
        J = np.zeros((3, 2))
        for k in range(2):
            e = np.zeros(2)
            e[k] = steps[k]
            J[:, k] = (flatport_cam_from_img_point(model, p, refrac, *(xy + e), d)
                       - flatport_cam_from_img_point(model, p, refrac, *(xy - e), d)) / (2 * steps[k])
        step = np.linalg.solve(J.T @ J, J.T @ err)
        xy = xy - step
        if step @ step < 1e-10:
            break
    return xy


def read_fork_text(folder):
    """cameras.txt -> {id: (model, params, refrac)}; images.txt -> [(camera id, name, R, t)]."""
    from scipy.spatial.transform import Rotation

    cams = {}
    for line in (folder / "cameras.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        items = line.split()
        model, n = items[1], N_PARAMS[items[1]]
        assert items[4 + n] == "FLATPORT"
        cams[int(items[0])] = (model, np.array(items[4:4 + n], float), np.array(items[5 + n:], float))
    images = []
    lines = [ln for ln in (folder / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    for first in lines[0::2]:
        items = first.split()
        w, x, y, z = map(float, items[1:5])
        images.append((int(items[8]), items[9], Rotation.from_quat([x, y, z, w]).as_matrix(),
                       np.array(items[5:8], float)))
    return cams, images


def read_fork_points(folder) -> dict[int, np.ndarray]:
    """points3D.txt -> {id: xyz}."""
    xyz = {}
    for line in (folder / "points3D.txt").read_text().splitlines():
        if not line.startswith("#"):
            items = line.split()
            xyz[int(items[0])] = np.array(items[1:4], float)
    return xyz


# ----------------------------------------------------------------------------- scenes

@pytest.fixture(scope="module", params=["binocular_underwater", "binocular"])
def scene(request):
    """A rig under water (distance observable) and one in air, lenses with k1..k3 and tangential terms."""
    return make_scene(request.param, seed=3, dist=[-0.05, 0.02, 3e-4, -2e-4, 0.004])


def truth_calibration(scene) -> Calibration:
    return parse_calibration(scene.truth)


def test_fork_projection_equals_ours_and_reads_back(scene, tmp_path):
    """Exported: the fork's own FLATPORT projection (transcribed above, in its metres) of the target
    corners gives our exact model's pixels (+0.5, COLMAP's pixel origin) to 1e-6 px; imported back:
    the same intrinsics, poses, window and projection."""
    cal = truth_calibration(scene)
    out = tmp_path / "fork"
    written = export_colmap_fork(cal, out, scene.dataset.observations)
    assert written.cameras == 2 and written.images > 10 and written.points3D > 100
    cams, images = read_fork_text(out)
    points = read_fork_points(out)
    assert len(points) == written.points3D and all(np.all(np.isfinite(X)) for X in points.values())
    assert {m for m, _, _ in cams.values()} == {"FULL_OPENCV"}
    assert all(refrac[3] < 1.0 for _, _, refrac in cams.values())  # metres: int_dist ~0.05-0.1
    ids, xyz = cal.target.points_3d()
    worst = 0.0
    for camera_id, name, R, t in images[::4]:
        camera, frame = name.split("/")
        X_world = cal.frames[frame].apply(xyz[::7])
        ours = cal.project_world(camera, X_world) + 0.5
        model, p, refrac = cams[camera_id]
        X_cam = (X_world / 1000.0) @ R.T + t  # the fork's world is in metres
        fork = np.array([flatport_img_from_cam(model, p, refrac, X) for X in X_cam])
        ok = np.all(np.isfinite(ours), axis=1)
        worst = max(worst, float(np.max(np.abs(fork[ok] - ours[ok]))))
    assert worst < 1e-6, worst

    back = import_colmap_fork(out)
    assert back.model == "exact" and list(back.cameras) == list(cal.cameras)
    assert back.interface.thickness_mm == pytest.approx(cal.interface.thickness_mm, rel=1e-12)
    assert back.interface.index == cal.interface.index and back.interface.medium_index == cal.interface.medium_index
    for name, c in cal.cameras.items():
        b = back.cameras[name]
        np.testing.assert_allclose(b.params, c.params, rtol=1e-12, atol=1e-9)
        rel = b.cam_from_world.compose(back.cameras["cam0"].cam_from_world.inverse())
        rel_true = c.cam_from_world.compose(cal.cameras["cam0"].cam_from_world.inverse())
        np.testing.assert_allclose(rel.R, rel_true.R, atol=1e-12)
        np.testing.assert_allclose(rel.t, rel_true.t, atol=1e-9)
        np.testing.assert_allclose(back.normal_cam(name), cal.normal_cam(name), atol=1e-12)
        assert back.projection_model(name).distance_mm == pytest.approx(cal.projection_model(name).distance_mm,
                                                                        abs=1e-9)
        X_cam = c.cam_from_world.apply(cal.frames[next(iter(cal.frames))].apply(xyz))
        np.testing.assert_allclose(back.projection_model(name).project(X_cam),
                                   cal.projection_model(name).project(X_cam),
                                   atol=1e-8)


def test_cli_round_trip_and_refractive_token(scene, tmp_path):
    """export-colmap-fork then import-colmap-fork through the command line (mm units here), and the
    later fork's form with a REFRAC token before FLATPORT reads the same."""
    cal = truth_calibration(scene)
    save_calibration(cal, tmp_path / "calibration.json")
    runner = CliRunner()
    r = runner.invoke(main, ["export-colmap-fork", str(tmp_path / "calibration.json"), "-o", str(tmp_path / "fork"),
                             "--units-mm", "1"])
    assert r.exit_code == 0, r.output
    text = (tmp_path / "fork" / "cameras.txt").read_text()
    refrac = [float(x) for x in text.splitlines()[-1].split("FLATPORT")[1].split()]
    assert refrac[3] == pytest.approx(cal.projection_model("cam1").distance_mm)  # mm units: int_dist in mm
    (tmp_path / "fork" / "cameras.txt").write_text(text.replace(" FLATPORT ", " REFRAC FLATPORT "))
    r = runner.invoke(main, ["import-colmap-fork", str(tmp_path / "fork"), "-o", str(tmp_path / "back"),
                             "--units-mm", "1"])
    assert r.exit_code == 0, r.output
    back = load_calibration(tmp_path / "back" / "calibration.json")
    for name, c in cal.cameras.items():
        np.testing.assert_allclose(back.cameras[name].params, c.params, rtol=1e-12, atol=1e-9)
        assert back.projection_model(name).distance_mm == pytest.approx(cal.projection_model(name).distance_mm,
                                                                        abs=1e-9)


def test_single_camera_survey_reads_its_housing(tmp_path):
    """A fork model of one moving camera (a survey): the camera and its housing, at the identity."""
    (tmp_path / "cameras.txt").write_text(
        "# a camera of the fork's examples (metres)\n"
        "1 OPENCV 4000 3000 2300 2300 2000 1500 0.04 0.04 0.001 -0.002 FLATPORT 0.0034340874001528117 "
        "0.0053178590745536457 0.99997996350855389 0.017195078129667741 0.0019 1 1.473 1.334\n")
    (tmp_path / "images.txt").write_text(
        "1 1 0 0 0 0 0 0 1 a.png\n\n2 0.9998476951563913 0.01745240643728351 0 0 0.1 0 0 1 b.png\n\n")
    cal = import_colmap_fork(tmp_path)
    c = cal.cameras["cam1"]
    assert c.K[0, 2] == 1999.5 and c.K[1, 2] == 1499.5 and c.dist.tolist() == [0.04, 0.04, 0.001, -0.002, 0.0]
    np.testing.assert_allclose(c.cam_from_world.R, np.eye(3))
    assert cal.interface.distance_mm == pytest.approx(17.195078129667741)
    assert cal.interface.thickness_mm == pytest.approx(1.9) and cal.interface.medium_index == 1.334


BAD_CAMERAS = {
    "no flatport": ("1 PINHOLE 640 480 500 500 320 240\n", "no FLATPORT block"),
    "housing not air": ("1 PINHOLE 640 480 500 500 320 240 FLATPORT 0 0 1 0.02 0.005 1.1 1.5 1.33\n", "na = 1.1"),
    "dome port": ("1 PINHOLE 640 480 500 500 320 240 DOMEPORT 0 0 0 0.02 0.005 1 1.5 1.33\n", "DOMEPORT"),
    "short block": ("1 PINHOLE 640 480 500 500 320 240 FLATPORT 0 0 1 0.02\n", "8 parameters"),
    "not unit": ("1 PINHOLE 640 480 500 500 320 240 FLATPORT 0 0 2 0.02 0.005 1 1.5 1.33\n", "unit vector"),
    "text": ("1 PINHOLE 640 480 500 500 320 x FLATPORT 0 0 1 0.02 0.005 1 1.5 1.33\n", "not a number"),
}


@pytest.mark.parametrize("case", sorted(BAD_CAMERAS))
def test_bad_fork_cameras_one_line(case, tmp_path):
    text, needle = BAD_CAMERAS[case]
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "cameras.txt").write_text(text)
    r = CliRunner().invoke(main, ["import-colmap-fork", str(tmp_path / "m"), "-o", str(tmp_path / "out")])
    assert r.exit_code == 1
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    assert "cameras.txt" in lines[0] and needle in lines[0], r.output
    assert not (tmp_path / "out" / "calibration.json").exists()


def test_export_refuses_the_paraxial_model_and_missing_folder(tmp_path, scene):
    data = dict(scene.truth, model="ari")
    (tmp_path / "cal.json").write_text(json.dumps(data))
    r = CliRunner().invoke(main, ["export-colmap-fork", str(tmp_path / "cal.json"), "-o", str(tmp_path / "fork")])
    assert r.exit_code == 1 and r.output.count("\n") == 1 and "model ari" in r.output and "exact" in r.output, r.output
    assert not (tmp_path / "fork" / "cameras.txt").exists()
    with pytest.raises(AriSfmError, match="cameras.txt"):
        import_colmap_fork(tmp_path)


def test_refined_model_moves_to_the_fork(tmp_path):
    """A refine-colmap output (simulated flat-port survey through pycolmap's bundle adjustment, refined a few
    iterations) exported with its COLMAP model: every image at its real pose with its 2D points, the refined
    points; the fork's projection of each point through its image gives our exact model's pixels to 1e-6 px,
    and its cameras read back as the refined housings."""
    from ari_sfm.colmap import adapter
    from ari_sfm.colmap.refine import refine_colmap, write_refined
    from ari_sfm.simulate.port_survey import port_survey

    truth = port_survey(num_images=5, num_points=200, focal_px=1300, area_mm=(1200, 800), sigma_px=0.3)
    rec = adapter.bundle_adjust(adapter.reconstruction_from_arrays(
        truth.params, truth.image_size, truth.sensor_from_rig, truth.rig_from_world, truth.image_camera,
        truth.image_frame, truth.xyz, truth.obs_image, truth.obs_point, truth.obs_uv))
    result = refine_colmap(rec, truth.interface, "camera", units_mm=1.0, max_iterations=3)
    write_refined(result, tmp_path / "refined")
    r = CliRunner().invoke(main, ["export-colmap-fork", str(tmp_path / "refined" / "calibration.json"),
                                  "-o", str(tmp_path / "fork"), "--units-mm", "1"])
    assert r.exit_code == 0, r.output
    cal = load_calibration(tmp_path / "refined" / "calibration.json")
    cams, images = read_fork_text(tmp_path / "fork")
    assert len(images) == 5 and len(cams) == 1
    xyz = read_fork_points(tmp_path / "fork")
    assert len(xyz) > 100
    name = next(iter(cal.cameras))
    lines = [ln for ln in (tmp_path / "fork" / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    worst = 0.0
    for (camera_id, _, R, t), points in zip(images, lines[1::2]):
        items = points.split()
        pids = [int(p) for p in items[2::3]][::9]
        X_cam = np.array([xyz[p] for p in pids]) @ R.T + t
        ours = cal.projection_model(name).project(X_cam) + 0.5
        model, p, refrac = cams[camera_id]
        fork = np.array([flatport_img_from_cam(model, p, refrac, X) for X in X_cam])
        worst = max(worst, float(np.max(np.abs(fork - ours))))
        observed = np.array(items, float).reshape(-1, 3)[::9, :2]
        assert np.sqrt(np.mean(np.sum((observed - ours) ** 2, axis=1))) < 3.0  # the refined fit (sigma 0.3)
    assert worst < 1e-6, worst
    back = import_colmap_fork(tmp_path / "fork", units_mm=1.0)
    b = next(iter(back.cameras.values()))
    np.testing.assert_allclose(b.params, cal.cameras[name].params, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(back.normal_cam(b.name), cal.normal_cam(name), atol=1e-12)
    assert back.projection_model(b.name).distance_mm == pytest.approx(cal.projection_model(name).distance_mm)

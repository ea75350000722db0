"""OpenPTV in and out: import an experiment, export a calibration, cross-checked with liboptv's formulas.

``liboptv_pixels`` below is an independent transcription of liboptv's forward projection
(``imgcoord.c: img_coord`` = ``flat_image_coord`` with ``multimed.c: trans_Cam_Point``,
``multimed_r_nlay``, ``back_trans_Point``; then ``trafo.c: flat_to_dist``,
``distort_brown_affin``, ``metric_to_pixel``), reading the files as ``calibration.c: read_ori``
and ``parameters.c: read_control_par`` do. It returns OpenPTV pixels, whose (0, 0) is the
top-left pixel's corner (``segmentation.c`` adds 0.5 to centroids of pixel indices).
The test data come from liboptv/tests/testing_fodder/test_cavity (see tests/data/openptv/README.md).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.calibration.record import Calibration, CameraCalibration
from ari_sfm.cli import main
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import Pose
from ari_sfm.io import load_calibration, load_dataset, save_calibration
from ari_sfm.openptv import export_openptv, import_experiment
from ari_sfm.openptv.conventions import cam_from_world
from ari_sfm.openptv.files import read_addpar, read_control_par, read_ori
from ari_sfm.records import Interface

FODDER = Path(__file__).parent / "data" / "openptv" / "test_cavity"
OPENCV_FROM_OPENPTV_PX = -0.5  # segmentation.c: target centre = 0.5 + mean pixel index


# ----------------------------------------------------------------------------- liboptv, transcribed


def _rotation(omega, phi, kappa):
    """calibration.c: rotation_matrix."""
    cp, sp, co, so, ck, sk = np.cos(phi), np.sin(phi), np.cos(omega), np.sin(omega), np.cos(kappa), np.sin(kappa)
    return np.array([[cp * ck, -cp * sk, sp],
                     [co * sk + so * sp * ck, co * ck - so * sp * sk, -so * cp],
                     [so * sk - co * sp * ck, so * ck + co * sp * sk, co * cp]])


def _floats(path):
    return [float(t) for t in Path(path).read_text().split()]


def read_liboptv_camera(ori_path, ptv_par):
    """read_ori + read_control_par (+ the .addpar beside the .ori, default when absent)."""
    v = _floats(ori_path)
    addpar_path = Path(str(ori_path)[:-4] + ".addpar")
    ap = _floats(addpar_path) if addpar_path.is_file() else [0, 0, 0, 0, 0, 1, 0]
    lines = [ln.strip() for ln in Path(ptv_par).read_text().splitlines() if ln.strip()]
    imx, imy, pix_x, pix_y, _, n1, n2, n3, d = lines[-9:]
    return dict(x0=np.array(v[0:3]), dm=_rotation(*v[3:6]), xh=v[15], yh=v[16], cc=v[17], glass=np.array(v[18:21]),
                k1=ap[0], k2=ap[1], k3=ap[2], p1=ap[3], p2=ap[4], scx=ap[5], she=ap[6], imx=int(imx), imy=int(imy),
                pix_x=float(pix_x), pix_y=float(pix_y), n1=float(n1), n2=float(n2), n3=float(n3), d=float(d))


def liboptv_pixels(X, cam, tol=1e-12, n_iter=1000):
    """img_coord + metric_to_pixel for world points X (N, 3): OpenPTV pixels (N, 2).

    liboptv's multimed_r_nlay stops at |rdiff| <= 0.001 mm after at most 40 iterations;
    ``tol`` and ``n_iter`` default to a converged solution here."""
    out = []
    G, d = cam["glass"], cam["d"]
    nG = np.linalg.norm(G)
    X0 = cam["x0"]
    for pos in np.asarray(X, float):
        # trans_Cam_Point
        dist_cam_glas = X0 @ G / nG - nG - d
        dist_point_glas = pos @ G / nG - nG
        cross_c = X0 - G * (dist_cam_glas / nG)
        cross_p = pos - G * (dist_point_glas / nG)
        z0_t = dist_cam_glas + d
        temp = cross_p - (cross_c - G * (d / nG))
        r, Z = np.linalg.norm(temp), dist_point_glas
        # multimed_r_nlay (camera at (0, 0, z0_t), point at (r, 0, Z))
        rq, it = r, 0
        while True:
            beta1 = np.arctan(rq / (z0_t - Z))
            beta2 = np.arcsin(np.sin(beta1) * cam["n1"] / cam["n2"])
            beta3 = np.arcsin(np.sin(beta1) * cam["n1"] / cam["n3"])
            rbeta = (z0_t - d) * np.tan(beta1) - Z * np.tan(beta3) + d * np.tan(beta2)
            rdiff = r - rbeta
            rq += rdiff
            it += 1
            if abs(rdiff) <= tol or it >= n_iter:
                break
        X_t = r * (rq / r if r != 0 else 1.0)
        # back_trans_Point
        after_glass = cross_c - G * (d / nG)
        temp = cross_p - after_glass
        nVe = np.linalg.norm(temp)
        virtual = after_glass - G * (-Z / nG)
        if nVe > 0:
            virtual = virtual - temp * (-X_t / nVe)
        # flat_image_coord
        v = cam["dm"].T @ (virtual - X0)
        x, y = -cam["cc"] * v[0] / v[2], -cam["cc"] * v[1] / v[2]
        # flat_to_dist, distort_brown_affin
        x, y = x + cam["xh"], y + cam["yh"]
        rr = np.hypot(x, y)
        radial = cam["k1"] * rr**2 + cam["k2"] * rr**4 + cam["k3"] * rr**6
        xd = x + x * radial + cam["p1"] * (rr**2 + 2 * x * x) + 2 * cam["p2"] * x * y
        yd = y + y * radial + cam["p2"] * (rr**2 + 2 * y * y) + 2 * cam["p1"] * x * y
        x1, y1 = cam["scx"] * xd - np.sin(cam["she"]) * yd, np.cos(cam["she"]) * yd
        # metric_to_pixel
        out.append([x1 / cam["pix_x"] + cam["imx"] / 2.0, cam["imy"] / 2.0 - y1 / cam["pix_y"]])
    return np.array(out)


def liboptv_ray(u_optv, v_optv, cam):
    """pixel_to_metric, dist_to_flat (for k = p = 0: undo scx, she, then subtract xh, yh), then
    ray_tracing.c: old_ray_tracing: the ray's point on the glass-water face and its unit direction in
    the medium (world frame)."""
    assert cam["k1"] == cam["k2"] == cam["k3"] == cam["p1"] == cam["p2"] == 0
    x = (u_optv - cam["imx"] / 2.0) * cam["pix_x"]
    y = (cam["imy"] / 2.0 - v_optv) * cam["pix_y"]
    y = y / np.cos(cam["she"])
    x = (x + y * np.sin(cam["she"])) / cam["scx"] - cam["xh"]
    y = y - cam["yh"]
    b = cam["dm"] @ (np.array([x, y, -cam["cc"]]) / np.sqrt(x * x + y * y + cam["cc"] ** 2))
    c = np.linalg.norm(cam["glass"])
    bn = cam["glass"] / c
    d1 = -(bn @ cam["x0"] - (c + cam["d"])) / (bn @ b)
    Xb1 = cam["x0"] + b * d1

    def refract(a, ratio):
        n = a @ bn
        bp = a - bn * n
        if np.linalg.norm(bp) > 0:
            bp = bp / np.linalg.norm(bp)
        p = np.sqrt(1 - n * n) * ratio
        return p * bp - np.sqrt(1 - p * p) * bn

    a2 = refract(b, cam["n1"] / cam["n2"])
    Xb2 = Xb1 + cam["d"] / abs(bn @ a2) * a2
    return Xb2, refract(a2, cam["n2"] / cam["n3"])


# ----------------------------------------------------------------------------- an experiment on disk


def _body():
    v = np.loadtxt(FODDER / "cal" / "target_on_a_side.txt")
    return v[:, 0].astype(int), v[:, 1:]


def write_ptv_par(path, cams, n=(1.0, 1.33, 1.46), d=6.0, pix=0.012):
    lines = [str(len(cams))]
    for k in cams:
        lines += [f"img/cam{k}.10003", f"cal/cam{k}.tif"]
    lines += ["1", "0", "1", "1280", "1024", str(pix), str(pix), "0", *map(str, n), str(d)]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def write_plane(fix_path, crd_path, ids, xyz, cam):
    """A .fix and its .crd: the points' OpenPTV pixels by liboptv's formulas (5 decimals, as liboptv writes)."""
    px = liboptv_pixels(xyz, cam)
    fix_path.parent.mkdir(parents=True, exist_ok=True)
    fix_path.write_text("".join(f"{i:3d}  {p[0]:10.5f}  {p[1]:10.5f}  {p[2]:10.5f}\n" for i, p in zip(ids, xyz)))
    crd_path.write_text("".join(f"{i:3d}  {p[0]:9.5f}  {p[1]:9.5f}\n" for i, p in zip(ids, px)))


@pytest.fixture()
def experiment(tmp_path):
    """cam1 and cam2 of test_cavity (one window), single plane via cal_ori.par, .crd from liboptv's formulas."""
    root = tmp_path / "exp"
    write_ptv_par(root / "parameters" / "ptv.par", (1, 2))
    (root / "cal").mkdir(parents=True)
    for k in (1, 2):
        shutil.copy(FODDER / "cal" / f"cam{k}.tif.ori", root / "cal")
    shutil.copy(FODDER / "cal" / "cam1.tif.addpar", root / "cal")
    shutil.copy(FODDER / "cal" / "target_on_a_side.txt", root / "cal")
    (root / "parameters" / "cal_ori.par").write_text(
        "cal/target_on_a_side.txt\ncal/cam1.tif\ncal/cam1.tif.ori\ncal/cam2.tif\ncal/cam2.tif.ori\n1\n1\n0\n")
    ids, xyz = _body()
    for k in (1, 2):
        cam = read_liboptv_camera(root / "cal" / f"cam{k}.tif.ori", root / "parameters" / "ptv.par")
        crd = liboptv_pixels(xyz, cam)
        (root / "cal" / f"cam{k}.tif.crd").write_text(
            "".join(f"{i:3d}  {p[0]:9.5f}  {p[1]:9.5f}\n" for i, p in zip(ids, crd)))
    return root


# ----------------------------------------------------------------------------- import


def test_import_reads_cameras_window_body_and_pixels(experiment, tmp_path):
    rig = import_experiment(experiment, tmp_path / "ds")
    ds = load_dataset(rig)
    assert list(ds.cameras) == ["cam1", "cam2"]
    for cam in ds.cameras.values():
        assert cam.image_size == (1280, 1024)
        assert cam.focal_px == pytest.approx(70.0 / 0.012, rel=1e-12)  # cc / pixel size
    iface = ds.interface
    assert (iface.thickness_mm, iface.index, iface.medium_index) == (6.0, 1.33, 1.46)  # d, n2, n3 (n1 = 1)
    # glass vector (0, 0, -125): G points to the cameras, |G| to the glass-water face, +d to the camera side
    assert iface.plane.frame == "f000"
    np.testing.assert_allclose(iface.plane.normal, [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(iface.plane.point_mm, [0, 0, -131.0], atol=1e-12)
    assert iface.plane.sigma_deg == 0 and iface.plane.sigma_mm == 0
    ids, xyz = _body()
    assert ds.target.type == "points3d" and sorted(ds.target.points) == ids.tolist()
    np.testing.assert_array_equal([ds.target.points[i] for i in ids], xyz)
    assert [e.key for e in ds.calibration] == ["f000"]
    crd = np.loadtxt(experiment / "cal" / "cam2.tif.crd")
    obs = {o.camera: o for o in ds.observations}
    np.testing.assert_array_equal(obs["cam2"].ids, crd[:, 0].astype(int))
    np.testing.assert_allclose(obs["cam2"].pixels, crd[:, 1:] - 0.5, atol=1e-12)  # corner -> centre convention


def test_import_known_crd_point_lands_on_opencv_pixel(experiment, tmp_path):
    """The sensor centre, OpenPTV pixel (640, 512) of a 1280 x 1024 image, is OpenCV's (639.5, 511.5)."""
    crd = experiment / "cal" / "cam1.tif.crd"
    lines = crd.read_text().splitlines()
    lines[0] = "  1  640.00000  512.00000"
    crd.write_text("\n".join(lines) + "\n")
    ds = load_dataset(import_experiment(experiment, tmp_path / "ds"))
    cam1 = next(o for o in ds.observations if o.camera == "cam1")
    np.testing.assert_array_equal(cam1.pixels[cam1.ids.tolist().index(1)], [639.5, 511.5])


def test_testing_fodder_cameras_project_like_liboptv(experiment, tmp_path):
    """An .ori converted to (K, cam_from_world, window) and projected by ari-sfm's exact model gives
    liboptv's pixels for test_cavity's cam1 and cam2 (their .crd here), to < 1e-4 px."""
    ds = load_dataset(import_experiment(experiment, tmp_path / "ds"))
    ids, xyz = _body()
    for obs in ds.observations:
        ori = read_ori(experiment / "cal" / f"{obs.camera}.tif.ori")
        pose = cam_from_world(ori)
        f = ori.cc / 0.012
        K = np.array([[f, 0, 640 - 0.5 + ori.xh / 0.012], [0, f, 512 - 0.5 - ori.yh / 0.012], [0, 0, 1]])
        plane = ds.interface.plane
        centre = pose.inverse().t  # the contract's distance_mm: from the (first) camera's centre
        cal = Calibration("exact",
                          Interface(6.0, 1.33, 1.46, distance_mm=float(plane.normal @ (plane.point_mm - centre))),
                          plane.normal, {obs.camera: CameraCalibration(obs.camera, (1280, 1024), K, np.zeros(5), pose)},
                          {"f000": Pose.identity()})
        uv = cal.project_world(obs.camera, xyz[np.searchsorted(ids, obs.ids)])
        exact = liboptv_pixels(xyz[np.searchsorted(ids, obs.ids)],
                               read_liboptv_camera(experiment / "cal" / f"{obs.camera}.tif.ori",
                                                   experiment / "parameters" / "ptv.par"))
        np.testing.assert_allclose(uv, exact + OPENCV_FROM_OPENPTV_PX, atol=1e-9)
        assert np.abs(uv - obs.pixels).max() < 1e-4  # the .crd holds 5 decimals


def test_import_multi_planes_is_one_rigid_body(experiment, tmp_path):
    (experiment / "parameters" / "multi_planes.par").write_text("2\nimg/calib_a_cam\nimg/calib_b_cam\n")
    ids, xyz = _body()
    shifted = xyz + [0.0, 0.0, 10.0]
    for k in (1, 2):
        cam = read_liboptv_camera(experiment / "cal" / f"cam{k}.tif.ori", experiment / "parameters" / "ptv.par")
        write_plane(experiment / "img" / f"calib_a_cam{k}.tif.fix", experiment / "img" / f"calib_a_cam{k}.tif.crd",
                    ids, xyz, cam)
        write_plane(experiment / "img" / f"calib_b_cam{k}.tif.fix", experiment / "img" / f"calib_b_cam{k}.tif.crd",
                    ids[:40], shifted[:40], cam)
    crd_b = experiment / "img" / "calib_b_cam2.tif.crd"
    lines = crd_b.read_text().splitlines()
    lines[3] = "  4  -999.00000  -999.00000"  # OpenPTV's "not detected"
    crd_b.write_text("\n".join(lines) + "\n")
    ds = load_dataset(import_experiment(experiment, tmp_path / "ds"))
    points = ds.target.points
    assert len(points) == 73 + 40 and len(ds.calibration) == 1  # one frame: the planes are one body
    np.testing.assert_array_equal(points[100 + 5], shifted[4])  # plane b (index 1): id 5 -> 105 (ids < 100)
    np.testing.assert_array_equal(points[5], xyz[4])
    obs = {o.camera: o for o in ds.observations}
    assert len(obs["cam1"].ids) == 113 and len(obs["cam2"].ids) == 112 and 104 not in obs["cam2"].ids


@pytest.mark.parametrize("breakage, file, message", [
    (lambda r: (r / "parameters" / "ptv.par").unlink(), "ptv.par", "file not found"),
    (lambda r: (r / "parameters" / "ptv.par").write_text("2\na\nb\nc\n1\n"), "ptv.par", "lines for 2 cameras"),
    (lambda r: (r / "parameters" / "ptv.par").write_text(
        (r / "parameters" / "ptv.par").read_text().replace("1.46", "water")), "ptv.par", "'water' is not a number"),
    (lambda r: (r / "cal" / "cam1.tif.ori").write_text("1 2 3\n"), "cam1.tif.ori", "expected 21 numbers"),
    (lambda r: (r / "cal" / "cam1.tif.crd").write_text(
        (r / "cal" / "cam1.tif.crd").read_text().replace(" 73  ", " 74  ")), "cam1.tif.crd", "ids do not match"),
    (lambda r: (r / "parameters" / "cal_ori.par").unlink(), "parameters", "neither multi_planes.par nor cal_ori.par"),
    (lambda r: (r / "parameters" / "multi_planes.par").write_text("3\nimg/a\nimg/b\n"), "multi_planes.par",
     "expected the number of planes"),
    (lambda r: ((r / "parameters" / "multi_planes.par").write_text("1\nimg/a\n"),
                (r / "parameters" / "cal_ori.par").unlink()), "a1.tif.fix", "file not found (named by multi_planes"),
    (lambda r: (r / "cal" / "cam2.tif.crd").unlink(), "cam2.tif.crd", "file not found"),
    (lambda r: (r / "cal" / "cam2.tif.crd").write_text("  1  -1.25  0.5\n" + "".join(
        (r / "cal" / "cam2.tif.crd").read_text().splitlines(True)[1:])), "cam2.tif.crd", "outside the 1280 x 1024"),
    (lambda r: (r / "cal" / "target_on_a_side.txt").write_text("1 2 3\n"), "target_on_a_side.txt", "expected 4"),
])
def test_import_bad_input_is_one_line_naming_the_file(experiment, tmp_path, breakage, file, message):
    breakage(experiment)
    with pytest.raises(AriSfmError) as err:
        import_experiment(experiment, tmp_path / "ds")
    assert file in str(err.value.path) and message in err.value.message
    assert not (tmp_path / "ds").exists()  # nothing half-written
    r = CliRunner().invoke(main, ["import", "openptv", str(experiment), "-o", str(tmp_path / "ds2")])
    assert r.exit_code == 1 and r.output.count("\n") == 1 and r.output.startswith("error: ")


def test_import_gives_each_wall_its_window(cavity_without_ori, tmp_path):
    """test_cavity's cam1, cam2 look through the window at z = -131..-125, cam3, cam4 through the opposite wall:
    two windows (DATASET_FORMAT 1.3), each plane declared from its cameras' glass vector in frame f000."""
    root, _ = cavity_without_ori
    for k in range(1, 5):  # the lab's .ori files back
        shutil.copy(FODDER / "cal" / f"cam{k}.tif.ori", root / "cal" / f"cam{k}.tif.ori")
    ds = load_dataset(import_experiment(root, tmp_path / "ds"))
    assert [(w.name, w.cameras) for w in ds.windows] == [("minus_z", ("cam1", "cam2")), ("plus_z", ("cam3", "cam4"))]
    for w, sign in zip(ds.windows, (1.0, -1.0)):
        plane = w.interface.plane
        assert plane.frame == "f000" and plane.sigma_deg == 0.0 and plane.sigma_mm == 0.0
        np.testing.assert_allclose(plane.normal, [0, 0, sign], atol=1e-15)  # from the cameras into the water
        assert plane.normal @ plane.point_mm == pytest.approx(-131.0)  # the camera-side face, 125 + 6 mm out
        assert (w.interface.thickness_mm, w.interface.index, w.interface.medium_index) == (6.0, 1.33, 1.46)


def test_import_windows_option_and_its_errors(cavity_without_ori, tmp_path):
    root, _ = cavity_without_ori
    r = CliRunner().invoke(main, ["import", "openptv", str(root), "-o", str(tmp_path / "ds"),
                                  "--windows", "cam1,cam3;cam2,cam4"])
    assert r.exit_code == 0, r.output
    ds = load_dataset(tmp_path / "ds")
    assert [w.cameras for w in ds.windows] == [("cam1", "cam3"), ("cam2", "cam4")]
    assert all(w.interface.plane is None for w in ds.windows)  # the user's grouping: planes left to calibrate
    for groups, message in (("cam1,cam2;cam3", "camera cam4 is in no group"), ("cam1,cam2;cam2,cam3,cam4",
                            "camera cam2 is in two groups"), ("cam1,cam9;cam2,cam3,cam4", "cam9 is not a camera")):
        r = CliRunner().invoke(main, ["import", "openptv", str(root), "-o", str(tmp_path / "ds2"), "--windows", groups])
        assert r.exit_code == 1 and r.output.startswith("error: --windows: ") and message in r.output, r.output
        assert not (tmp_path / "ds2").exists()


def test_import_n1_not_air_and_nearly_equal_glass_vectors(experiment, tmp_path):
    """n1 != 1: Snell's law keeps the ratios (index n2/n1, medium n3/n1); glass vectors that differ a little
    give cam1's plane as a prior whose sigmas are the spread."""
    write_ptv_par(experiment / "parameters" / "ptv.par", (1, 2), n=(1.1, 1.5, 1.43))
    ori = experiment / "cal" / "cam2.tif.ori"
    ori.write_text(ori.read_text().replace("0.000000000000000  -125.000000000000000",
                                           "0.500000000000000  -125.000000000000000"))
    ds = load_dataset(import_experiment(experiment, tmp_path / "ds"))
    assert ds.interface.index == pytest.approx(1.5 / 1.1) and ds.interface.medium_index == pytest.approx(1.3)
    plane = ds.interface.plane
    np.testing.assert_allclose(plane.normal, [0, 0, 1], atol=1e-15)
    assert plane.sigma_deg == pytest.approx(np.degrees(np.arctan2(0.5, 125)), rel=1e-9)
    assert plane.sigma_mm > 0


def test_import_cli(experiment, tmp_path):
    r = CliRunner().invoke(main, ["import", "openptv", str(experiment), "-o", str(tmp_path / "ds")])
    assert r.exit_code == 0, r.output
    assert "2 cameras (cam1, cam2), 73 body points, 146 observations" in r.output
    r = CliRunner().invoke(main, ["import", "openptv", str(experiment), "-o", str(tmp_path / "ds")])
    assert r.exit_code == 1 and "already exists" in r.output


# ----------------------------------------------------------------------------- export


def _rot(axis, deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = [(1, 2), (0, 2), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def simulated_calibration(dist0=(0, 0, 0, 0, 0), centred=False, medium=1.333, distance=300.0):
    """Two cameras behind a 6 mm window into water, an exact-model calibration with known numbers."""
    normal = np.array([0.05, -0.03, 1.0])
    normal /= np.linalg.norm(normal)
    cx, cy = (639.5, 511.5) if centred else (655.3, 498.7)
    K0 = np.array([[2900.0, 0, cx], [0, 2905.0, cy], [0, 0, 1]])
    K1 = np.array([[3100.0, 0, 630.2], [0, 3100.0, 520.9], [0, 0, 1]])
    R1 = _rot(1, -14.0) @ _rot(0, 2.0)
    cams = {"left": CameraCalibration("left", (1280, 1024), K0, np.array(dist0, float), Pose.identity()),
            "right": CameraCalibration("right", (1280, 1024), K1, np.zeros(5), Pose(R1, -R1 @ [150.0, 5.0, 10.0]))}
    frame = Pose(_rot(0, 160.0) @ _rot(2, 20.0), np.array([20.0, -10.0, 520.0]))
    return Calibration("exact", Interface(6.0, 1.49, medium, distance_mm=distance), normal, cams, {"f000": frame},
                       fixed_distance_mm=300.0 if distance is None else None)  # in air: where it was fitted


def _exported_opencv(out, number):
    """(K, dist, cam_from_target) of an exported camera, back from liboptv's numbers (the test's own algebra)."""
    cam = read_liboptv_camera(out / "cal" / f"cam{number}.tif.ori", out / "parameters" / "ptv.par")
    cc, scx = cam["cc"], cam["scx"]
    K = np.array([[scx * cc / cam["pix_x"], 0, cam["imx"] / 2 + scx * cam["xh"] / cam["pix_x"] - 0.5],
                  [0, cc / cam["pix_y"], cam["imy"] / 2 - cam["yh"] / cam["pix_y"] - 0.5], [0, 0, 1]])
    dist = np.array([cam["k1"] * cc**2, cam["k2"] * cc**4, -cam["p2"] * cc, cam["p1"] * cc, cam["k3"] * cc**6])
    R = np.diag([1.0, -1.0, -1.0]) @ cam["dm"].T
    return K, dist, Pose(R, -R @ cam["x0"]), cam


@pytest.mark.parametrize("dist0", [(0, 0, 0, 0, 0), (-0.08, 0.12, 3e-4, -2e-4, 0.01)])
def test_export_round_trip_every_parameter(tmp_path, dist0):
    cal = simulated_calibration(dist0, centred=True)
    save_calibration(cal, tmp_path / "calibration.json")
    summary = export_openptv(tmp_path / "calibration.json", tmp_path / "optv", pixel_size_mm=0.0055)
    assert summary.frame == "f000" and summary.numbers == {"left": 1, "right": 2} and not summary.fit_error_px
    control = read_control_par(tmp_path / "optv" / "parameters" / "ptv.par")
    assert (control.n1, control.n2, control.n3, control.d) == (1.0, 1.49, 1.333, 6.0)
    assert (control.imx, control.imy, control.pix_x, control.pix_y) == (1280, 1024, 0.0055, 0.0055)
    frame = cal.frames["f000"]
    for number, c in enumerate(cal.cameras.values(), start=1):
        K, dist, pose, raw = _exported_opencv(tmp_path / "optv", number)
        np.testing.assert_allclose(K, c.K, rtol=0, atol=1e-8)
        np.testing.assert_allclose(dist, c.dist, rtol=1e-9, atol=1e-15)
        truth = c.cam_from_world.compose(frame)
        np.testing.assert_allclose(pose.R, truth.R, atol=1e-11)
        np.testing.assert_allclose(pose.t, truth.t, atol=1e-8)
        # the glass vector: -normal in target coordinates, |G| + d = distance of the camera-side face
        G = raw["glass"]
        normal_t = frame.R.T @ cal.normal_world
        np.testing.assert_allclose(-G / np.linalg.norm(G), normal_t, atol=1e-14)
        face_t = frame.inverse().apply(cal.interface.distance_mm * cal.normal_world)
        assert np.linalg.norm(G) + 6.0 == pytest.approx(G / np.linalg.norm(G) @ face_t, abs=1e-9)
    assert read_addpar(tmp_path / "optv" / "cal" / "cam2.tif.addpar").is_identity()


@pytest.mark.parametrize("dist0, centred, medium", [
    ((0, 0, 0, 0, 0), False, 1.333),
    ((-0.08, 0.12, 3e-4, -2e-4, 0.01), True, 1.333),
    ((0, 0, 0, 0, 0), False, 1.0),
])
def test_exported_ori_reprojects_like_ari_sfm(tmp_path, dist0, centred, medium):
    """Body points through the exported .ori/.addpar/ptv.par with liboptv's formulas vs ari-sfm's exact model."""
    cal = simulated_calibration(dist0, centred=centred, medium=medium,
                                distance=None if medium == 1.0 else 300.0)
    save_calibration(cal, tmp_path / "calibration.json")
    export_openptv(tmp_path / "calibration.json", tmp_path / "optv")
    _, body = _body()
    X_world = cal.frames["f000"].apply(body)
    for number, name in enumerate(cal.cameras, start=1):
        cam = read_liboptv_camera(tmp_path / "optv" / "cal" / f"cam{number}.tif.ori",
                                  tmp_path / "optv" / "parameters" / "ptv.par")
        ours = cal.project_world(name, X_world)
        theirs = liboptv_pixels(body, cam) + OPENCV_FROM_OPENPTV_PX
        assert np.isfinite(ours).all() and ours.min() > 0
        assert np.abs(ours - theirs).max() < 1e-6


def test_exported_ori_traces_rays_like_ari_sfm(tmp_path):
    """Pixels back-projected through the exported files with liboptv's ray_tracing give ari-sfm's rays."""
    cal = simulated_calibration()
    save_calibration(cal, tmp_path / "calibration.json")
    export_openptv(tmp_path / "calibration.json", tmp_path / "optv")
    target_from_world = cal.frames["f000"].inverse()
    uv = np.array([[0.0, 0.0], [639.5, 511.5], [1279.0, 100.0], [300.0, 1000.0]])
    for number, name in enumerate(cal.cameras, start=1):
        cam = read_liboptv_camera(tmp_path / "optv" / "cal" / f"cam{number}.tif.ori",
                                  tmp_path / "optv" / "parameters" / "ptv.par")
        origins, directions = cal.rays_world(name, uv)
        for (u, v), o, dirn in zip(uv, target_from_world.apply(origins), directions @ target_from_world.R.T):
            point, direction = liboptv_ray(u - OPENCV_FROM_OPENPTV_PX, v - OPENCV_FROM_OPENPTV_PX, cam)
            np.testing.assert_allclose(point, o, atol=1e-9)
            np.testing.assert_allclose(direction, dirn, atol=1e-12)


def test_export_fits_distortion_about_an_offcentre_principal_point(tmp_path):
    cal = simulated_calibration((-0.08, 0.12, 3e-4, -2e-4, 0.0), centred=False)
    save_calibration(cal, tmp_path / "calibration.json")
    summary = export_openptv(tmp_path / "calibration.json", tmp_path / "optv")
    assert set(summary.fit_error_px) == {"left"} and summary.fit_error_px["left"] < 0.05
    _, body = _body()
    cam = read_liboptv_camera(tmp_path / "optv" / "cal" / "cam1.tif.ori", tmp_path / "optv" / "parameters" / "ptv.par")
    ours = cal.project_world("left", cal.frames["f000"].apply(body))
    diff = ours - liboptv_pixels(body, cam) - OPENCV_FROM_OPENPTV_PX
    assert np.abs(diff).max() <= summary.fit_error_px["left"] + 1e-6


def test_export_of_testing_fodder_cameras_gives_back_their_ori(experiment, tmp_path):
    """A calibration made of test_cavity's cam1, cam2 in OpenPTV's world (frame f000 = identity) exports to
    .ori files equal to the originals (same position, rotation, cc, glass vector) and the same ptv.par values."""
    cams, oris = {}, {}
    for k in (1, 2):
        ori = oris[k] = read_ori(FODDER / "cal" / f"cam{k}.tif.ori")
        K = np.array([[70 / 0.012, 0, 639.5], [0, 70 / 0.012, 511.5], [0, 0, 1]])
        cams[f"cam{k}"] = CameraCalibration(f"cam{k}", (1280, 1024), K, np.zeros(5), cam_from_world(ori))
    first = cams["cam1"].cam_from_world.inverse().t  # distance_mm is from the first camera's centre
    cal = Calibration("exact", Interface(6.0, 1.33, 1.46, distance_mm=-131.0 - first[2]), np.array([0, 0, 1.0]),
                      cams, {"f000": Pose.identity()})
    save_calibration(cal, tmp_path / "calibration.json")
    out = tmp_path / "exp_copy"
    shutil.copytree(experiment, out)
    r = CliRunner().invoke(main, ["export-openptv", str(tmp_path / "calibration.json"), "-o", str(out)])
    assert r.exit_code == 0, r.output
    for k in (1, 2):
        back = read_ori(out / "cal" / f"cam{k}.tif.ori")
        np.testing.assert_allclose(back.position, oris[k].position, atol=1e-9)
        np.testing.assert_allclose(_rotation(*back.angles), _rotation(*oris[k].angles), atol=1e-12)
        np.testing.assert_allclose(back.glass, oris[k].glass, atol=1e-12)
        assert (back.xh, back.yh) == pytest.approx((0, 0), abs=1e-12) and back.cc == pytest.approx(70, abs=1e-12)
    before = read_control_par(experiment / "parameters" / "ptv.par")
    # same names, flags, sizes, pixel size and multimedia values
    assert read_control_par(out / "parameters" / "ptv.par") == before


def test_export_keeps_a_padded_ptv_par_layout(tmp_path):
    """A 2-camera ptv.par padded to four cameras (the Tcl/Tk layout older liboptv reads) keeps its padding;
    only pixel size and the multimedia lines change."""
    cal = simulated_calibration()
    save_calibration(cal, tmp_path / "calibration.json")
    ptv_par = tmp_path / "optv" / "parameters" / "ptv.par"
    ptv_par.parent.mkdir(parents=True)
    padded = ["2", "img/a", "cal/a.tif", "img/b", "cal/b.tif", "---", "---", "---", "---",
              "1", "1", "1", "1280", "1024", "0.01", "0.01", "0", "1", "1.5", "1.0", "3"]
    ptv_par.write_text("\n".join(padded) + "\n")
    export_openptv(tmp_path / "calibration.json", tmp_path / "optv", pixel_size_mm=0.02)
    lines = ptv_par.read_text().split()
    assert lines[:13] == padded[:13] and lines[14:16] == ["0.02", "0.02"]
    assert lines[17:] == ["1.0", "1.49", "1.333", "6.0"]
    assert (tmp_path / "optv" / "cal" / "b.tif.ori").is_file()
    assert (tmp_path / "optv" / "cal" / "a.tif.addpar").is_file()


def test_export_bad_input_is_one_line(tmp_path):
    cal = simulated_calibration()
    save_calibration(cal, tmp_path / "calibration.json")
    r = CliRunner().invoke(main, ["export-openptv", str(tmp_path / "calibration.json"), "-o", str(tmp_path / "o"),
                                  "--frame", "f999"])
    assert r.exit_code == 1 and "no calibration frame 'f999'" in r.output and r.output.count("\n") == 1
    # the world origin (camera 0's centre) is on the camera side of the window: no glass vector can say that
    r = CliRunner().invoke(main, ["export-openptv", str(tmp_path / "calibration.json"), "-o", str(tmp_path / "o"),
                                  "--frame", "world"])
    assert r.exit_code == 1 and "glass vector cannot express" in r.output
    assert not (tmp_path / "o").exists()


# ----------------------------------------------------------------------------- import -> calibrate


def test_import_then_calibrate_exact_recovers_testing_fodder_cameras(experiment, tmp_path):
    r = CliRunner().invoke(main, ["import", "openptv", str(experiment), "-o", str(tmp_path / "ds")])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["calibrate", str(tmp_path / "ds"), "-o", str(tmp_path / "cal"), "--model", "exact"])
    assert r.exit_code == 0, r.output
    cal = load_calibration(tmp_path / "cal" / "calibration.json")
    assert cal.residuals.rmse_px < 0.01  # the .crd are liboptv's exact pixels to 5 decimals
    for k in (1, 2):
        assert cal.cameras[f"cam{k}"].K[0, 0] == pytest.approx(70 / 0.012, rel=1e-3)


@pytest.mark.parametrize("value", ["inf", "1e300", "1e-12", "nan", "-0.01"])
def test_export_refuses_an_unphysical_pixel_size(tmp_path, value):
    """--pixel-size-mm inf / 1e300 / 1e-12 wrote .ori files holding nan or inf."""
    save_calibration(simulated_calibration(), tmp_path / "calibration.json")
    r = CliRunner().invoke(main, ["export-openptv", str(tmp_path / "calibration.json"), "-o", str(tmp_path / "o"),
                                  "--pixel-size-mm", value])
    assert r.exit_code == 1 and r.output.count("\n") == 1, r.output
    assert r.output.startswith("error: --pixel-size-mm: must be a pixel size in mm between 0.0001 and 1 (got ")
    assert not (tmp_path / "o").exists()


def test_export_refuses_an_existing_ptv_par_with_an_unphysical_pixel_size(tmp_path):
    save_calibration(simulated_calibration(), tmp_path / "calibration.json")
    export_openptv(tmp_path / "calibration.json", tmp_path / "o")
    ptv_par = tmp_path / "o" / "parameters" / "ptv.par"
    lines = ptv_par.read_text().splitlines()
    lines[-7] = "1e300"  # pix_x (then pix_y, chfield, n1, n2, n3, d)
    ptv_par.write_text("\n".join(lines) + "\n")
    ori = (tmp_path / "o" / "cal" / "cam1.tif.ori").read_text()
    with pytest.raises(AriSfmError) as err:
        export_openptv(tmp_path / "calibration.json", tmp_path / "o")
    assert err.value.path == str(ptv_par) and err.value.message.startswith("pixel size x must be a pixel size in mm")
    assert (tmp_path / "o" / "cal" / "cam1.tif.ori").read_text() == ori


def test_export_with_cal_a_file_writes_nothing(tmp_path):
    """OUT/cal a file: ptv.par was written before the .ori failed."""
    save_calibration(simulated_calibration(), tmp_path / "calibration.json")
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "cal").write_text("not a folder")
    r = CliRunner().invoke(main, ["export-openptv", str(tmp_path / "calibration.json"), "-o", str(tmp_path / "o")])
    assert r.exit_code == 1
    assert r.output == f"error: {tmp_path / 'o' / 'cal'}: is a file, so cam1.tif.ori cannot be written there\n"
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["cal"]


@pytest.mark.parametrize("name", ["../../outside/cam1.tif", "/ABS/cam1.tif"])
def test_export_never_writes_outside_the_output_folder(tmp_path, name):
    """An existing ptv.par's calibration image names led the .ori/.addpar files outside -o."""
    name = name.replace("/ABS", str(tmp_path / "abs"))
    save_calibration(simulated_calibration(), tmp_path / "calibration.json")
    export_openptv(tmp_path / "calibration.json", tmp_path / "o")
    ptv_par = tmp_path / "o" / "parameters" / "ptv.par"
    lines = ptv_par.read_text().splitlines()
    lines[2] = name  # camera 1's calibration image
    ptv_par.write_text("\n".join(lines) + "\n")
    before = {p: p.read_bytes() for p in (tmp_path / "o").rglob("*") if p.is_file()}
    r = CliRunner().invoke(main, ["export-openptv", str(tmp_path / "calibration.json"), "-o", str(tmp_path / "o")])
    assert r.exit_code == 1 and r.output.startswith(f"error: {ptv_par}: calibration image name leads outside"), r.output
    assert {p: p.read_bytes() for p in (tmp_path / "o").rglob("*") if p.is_file()} == before
    assert not (tmp_path / "outside").exists() and not (tmp_path / "abs").exists()


@pytest.mark.parametrize("breakage, file, message", [
    (lambda r: write_ptv_par(r / "parameters" / "ptv.par", (1, 2), n=(1.0, 6.0, 1.46)), "parameters/ptv.par",
     "not importable: interface.index must be <= 5 (got 6.0)"),
    (lambda r: write_ptv_par(r / "parameters" / "ptv.par", (1, 2), d=1e5), "parameters/ptv.par",
     "not importable: interface.thickness_mm must be <= 10000 mm"),
    (lambda r: write_ptv_par(r / "parameters" / "ptv.par", (1, 2), pix=1e-9), "cal/cam1.tif.ori",
     "not importable: cameras.cam1.focal_px must be <= 1e+07 px"),
    (None, None, None),  # a .fix point at 1e300 (below)
])
def test_import_errors_name_the_openptv_file_not_a_temporary_rig(experiment, tmp_path, breakage, file, message):
    """Errors named the deleted temporary rig.yaml (.ds.xyz/rig.yaml) instead of ptv.par."""
    if file is None:  # a .fix point at 1e300 imported, then failed inside OpenCV
        fix = experiment / "cal" / "target_on_a_side.txt"
        lines = fix.read_text().splitlines()
        pid = lines[0].split()[0]
        lines[0] = f"{pid}  1e300  0.0  0.0"
        fix.write_text("\n".join(lines) + "\n")
        file, message = "cal/target_on_a_side.txt", f"point {int(pid)} at [1e+300, 0.0, 0.0]: beyond 10000 mm"
    else:
        breakage(experiment)
    r = CliRunner().invoke(main, ["import", "openptv", str(experiment), "-o", str(tmp_path / "ds")])
    assert r.exit_code == 1 and r.output.startswith(f"error: {experiment / file}: {message}"), r.output
    assert r.output.count("\n") == 1 and "rig.yaml" not in r.output
    assert not (tmp_path / "ds").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".ds.")]


def test_import_refuses_to_write_into_the_experiment(experiment):
    before = sorted(p.relative_to(experiment) for p in experiment.rglob("*"))
    r = CliRunner().invoke(main, ["import", "openptv", str(experiment), "-o", str(experiment)])
    assert r.exit_code == 1 and r.output == f"error: {experiment}: already exists and is not empty: give a new folder\n"
    assert sorted(p.relative_to(experiment) for p in experiment.rglob("*")) == before


# ----------------------------------------------------------------------------- import from images and clicks

CLICKED_IDS = ((2, 3, 71, 73), (2, 3, 71, 73), (1, 3, 69, 73), (1, 3, 69, 73))  # test_cavity's man_ori.par


def _render_calibration_image(optv_px, seed):
    """A 1280 x 1024 8-bit image of bright 10 px dots at OpenPTV pixels ``optv_px`` (OpenCV: - 0.5), with
    specks in the water and noise."""
    from ari_sfm.simulate.particles import render_particle_image
    from ari_sfm.simulate.render import add_discs

    rng = np.random.default_rng(seed)
    image = add_discs(np.full((1024, 1280), 20.0), optv_px + OPENCV_FROM_OPENPTV_PX, 10.0, 200.0)
    image += render_particle_image(rng.uniform([0, 0], [1280, 1024], (300, 2)), (1280, 1024), 2.0, peak=120.0,
                                   background=0.0, noise_sigma=0.0)
    image += rng.normal(0.0, 2.0, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


@pytest.fixture()
def cavity_without_ori(tmp_path):
    """test_cavity as a lab keeps it without OpenPTV's calibration: ptv.par, cal_ori.par, the body, a
    multi_planes.par naming files never made, man_ori.par / man_ori.dat (clicks 1-3 px off, whole pixels)
    and the four calibration images (rendered where liboptv puts the body with the .ori, then removed).
    Returns the folder and the true OpenCV pixels per camera {id: (u, v)}."""
    return _rendered_cavity(tmp_path, keep_ori=False)


@pytest.fixture()
def cavity_with_ori(tmp_path):
    """The same with OpenPTV's .ori and .addpar files kept (a lab that calibrated in OpenPTV before)."""
    return _rendered_cavity(tmp_path, keep_ori=True)


def _rendered_cavity(tmp_path, keep_ori: bool):
    import cv2

    root = tmp_path / "cavity"
    shutil.copytree(FODDER, root)
    (root / "parameters" / "multi_planes.par").write_text("3\nimg/calib_a_cam\nimg/calib_b_cam\nimg/calib_c_cam")
    ids, xyz = _body()
    rng = np.random.default_rng(4)
    truth, par, dat = {}, [], []
    for k in range(1, 5):
        cam = read_liboptv_camera(root / "cal" / f"cam{k}.tif.ori", root / "parameters" / "ptv.par")
        px = liboptv_pixels(xyz, cam)
        assert cv2.imwrite(str(root / "cal" / f"cam{k}.tif"), _render_calibration_image(px, k))
        truth[f"cam{k}"] = dict(zip(ids.tolist(), px + OPENCV_FROM_OPENPTV_PX))
        for pid in CLICKED_IDS[k - 1]:
            par.append(f"{pid}\n")
            u, v = np.rint(px[ids == pid][0] + rng.uniform(-2.5, 2.5, 2))
            dat.append(f"{u:f} {v:f}\n")
        if not keep_ori:
            (root / "cal" / f"cam{k}.tif.ori").unlink()
    if not keep_ori:
        (root / "cal" / "cam1.tif.addpar").unlink()
    (root / "parameters" / "man_ori.par").write_text("".join(par))
    (root / "man_ori.dat").write_text("".join(dat))
    return root, truth


def test_import_images_and_clicks_without_ori_then_detect(cavity_without_ori, tmp_path):
    """No .ori, no .crd: the dataset holds the images (copied) and the clicks (OpenCV pixels), a window without
    a plane; detect identifies every body point of every camera at its true pixel."""
    root, truth = cavity_without_ori
    r = CliRunner().invoke(main, ["import", "openptv", str(root), "-o", str(tmp_path / "ds")])
    assert r.exit_code == 0, r.output
    assert "4 cameras (cam1, cam2, cam3, cam4), 73 body points, 0 observations, 4 calibration images, clicked " \
           "points for 4 cameras" in r.output
    ds = load_dataset(tmp_path / "ds")
    assert ds.observations is None and not (tmp_path / "ds" / "observations.json").exists()
    # two windows told from the cameras' viewing directions (resected from the clicks), ptv.par's d, n2, n3
    # (n1 = 1), no plane without the .ori
    assert [(w.name, w.cameras) for w in ds.windows] == [("minus_z", ("cam1", "cam2")), ("plus_z", ("cam3", "cam4"))]
    assert all(w.interface == Interface(6.0, 1.33, 1.46) for w in ds.windows)
    assert all(cam.focal_px is None and cam.K is None for cam in ds.cameras.values())
    entry = ds.calibration[0]
    for k in range(1, 5):
        copied = entry.images[f"cam{k}"]
        assert copied == tmp_path / "ds" / "cal" / f"cam{k}.tif"
        assert copied.read_bytes() == (root / "cal" / f"cam{k}.tif").read_bytes()
    clicks = [line.split() for line in (root / "man_ori.dat").read_text().splitlines()]
    assert list(entry.manual_points["cam3"]) == [1, 3, 69, 73]
    assert entry.manual_points["cam3"][69] == (float(clicks[10][0]) - 0.5, float(clicks[10][1]) - 0.5)
    r = CliRunner().invoke(main, ["detect", str(tmp_path / "ds"), "-o", str(tmp_path / "det")])
    assert r.exit_code == 0, r.output
    records = json.loads((tmp_path / "det" / "observations.json").read_text())["observations"]
    assert [o["camera"] for o in records] == ["cam1", "cam2", "cam3", "cam4"]
    for o in records:
        true = np.array([truth[o["camera"]][i] for i in o["ids"]])
        assert len(o["ids"]) >= 70  # of 73 (a speck on a dot may leave it out)
        assert np.abs(np.array(o["pixels"]) - true).max() < 0.3  # right ids, accurate centres


def test_import_with_some_crd_identifies_the_other_cameras(cavity_without_ori, tmp_path):
    """cam1 has OpenPTV's .crd: its observations are imported; calibrate's detection identifies cam2..cam4 only."""
    from ari_sfm.detection import ensure_observations

    root, truth = cavity_without_ori
    ids = sorted(truth["cam1"])
    (root / "cal" / "cam1.tif.crd").write_text("".join(
        f"{i:3d}  {truth['cam1'][i][0] + 0.5:9.5f}  {truth['cam1'][i][1] + 0.5:9.5f}\n" for i in ids))
    ds = load_dataset(import_experiment(root, tmp_path / "ds"))
    assert [o.camera for o in ds.observations] == ["cam1"] and len(ds.observations[0].ids) == 73
    full = ensure_observations(ds)
    assert [o.camera for o in full.observations] == ["cam1", "cam2", "cam3", "cam4"]
    assert full.observations[0] is ds.observations[0]
    for o in full.observations[1:]:
        np.testing.assert_allclose(o.pixels, [truth[o.camera][i] for i in o.ids], atol=0.3)


@pytest.mark.parametrize("breakage, file, message", [
    (lambda r: (r / "parameters" / "man_ori.par").write_text(
        (r / "parameters" / "man_ori.par").read_text().replace("69\n", "99\n", 1)), "man_ori.par",
     "cam3: clicked point 99 is not a point of the calibration body"),
    (lambda r: (r / "man_ori.dat").write_text("1300.0 20.0\n" + "".join(
        (r / "man_ori.dat").read_text().splitlines(True)[1:])), "man_ori.dat",
     "cam1: clicked point 2 at (1300, 20) is outside the 1280 x 1024 image"),
    (lambda r: (r / "man_ori.dat").write_text("".join((r / "man_ori.dat").read_text().splitlines(True)[:9])),
     "man_ori.dat", "9 lines for 4 cameras"),
    (lambda r: (r / "cal" / "cam2.tif").unlink(), "cam2.tif.crd",
     "file not found, and no calibration image cam2.tif to find the body in"),
])
def test_import_bad_clicks_or_missing_image_is_one_line(cavity_without_ori, tmp_path, breakage, file, message):
    root, _ = cavity_without_ori
    breakage(root)
    r = CliRunner().invoke(main, ["import", "openptv", str(root), "-o", str(tmp_path / "ds")])
    assert r.exit_code == 1 and r.output.count("\n") == 1, r.output
    assert r.output.startswith("error: ") and file in r.output and message in r.output, r.output
    assert not (tmp_path / "ds").exists()


def test_import_multi_planes_par_with_its_files_is_still_read(experiment, tmp_path):
    """A multi_planes.par is read when its files exist (test_import_multi_planes_is_one_rigid_body); when they do
    not, cal_ori.par's body is, with a warning naming the first missing file."""
    (experiment / "parameters" / "multi_planes.par").write_text("2\nimg/calib_a_cam\nimg/calib_b_cam\n")
    ds = load_dataset(import_experiment(experiment, tmp_path / "ds"))
    assert ds.target.num_ids() == 73 and [len(o.ids) for o in ds.observations] == [73, 73]


def test_raw_cavity_calibrates_behind_two_windows(cavity_without_ori, tmp_path):
    """The lab's folder without OpenPTV's calibration (images rendered where OpenPTV's .ori put the body) imports
    and calibrates from its images and clicks alone: two windows, each near the wall the .ori files declare
    (within 3 sigma), the cameras' poses near theirs, at the detection noise."""
    from ari_sfm.calibration.calibrate import calibrate
    from ari_sfm.geometry import angle_between_deg

    root, _ = cavity_without_ori
    cal = calibrate(load_dataset(import_experiment(root, tmp_path / "ds")), model="exact")
    assert cal.quality.ok and cal.residuals.rmse_px < 0.3
    frame = cal.frames["f000"]  # world_from_body (OpenPTV's world)
    for w, sign in zip(cal.windows, (1.0, -1.0)):
        sigma = cal.uncertainty.windows[w.name]
        n_body = frame.R.T @ w.normal_world
        assert angle_between_deg(n_body, [0, 0, sign]) < max(3 * sigma.normal_deg, 0.5), (w.name, sigma)
    for k in range(1, 5):
        ori = read_ori(FODDER / "cal" / f"cam{k}.tif.ori")
        centre = frame.inverse().apply(cal.cameras[f"cam{k}"].cam_from_world.inverse().t[None])[0]
        assert np.linalg.norm(centre - ori.position) < 0.05 * np.linalg.norm(ori.position)


def test_cavity_with_ori_calibrates_through_each_cameras_own_declared_window(cavity_with_ori, tmp_path):
    """With OpenPTV's .ori files the two walls are declared (held as OpenPTV holds them): each camera's body
    dots are identified through its own window (cam3 and cam4 through the +z wall, not the -z one), and the
    calibration reaches the detection noise with the cameras where the .ori put them."""
    from ari_sfm.calibration.calibrate import calibrate

    root, _ = cavity_with_ori
    ds = load_dataset(import_experiment(root, tmp_path / "ds"))
    assert [w.interface.plane is not None for w in ds.windows] == [True, True]
    cal = calibrate(ds, model="exact")
    assert cal.quality.ok and cal.residuals.rmse_px < 0.3
    frame = cal.frames["f000"]
    for k in range(1, 5):
        ori = read_ori(FODDER / "cal" / f"cam{k}.tif.ori")
        centre = frame.inverse().apply(cal.cameras[f"cam{k}"].cam_from_world.inverse().t[None])[0]
        assert np.linalg.norm(centre - ori.position) < 0.02 * np.linalg.norm(ori.position)


@pytest.mark.parametrize("tilts,expected", [
    ((20, -20, 160, 200), [[0, 1], [2, 3]]),  # opposite walls (test_cavity)
    ((15, -25, 90 + 20, 90 - 20), [[0, 1], [2, 3]]),  # adjacent walls at 90 deg, cameras tilted apart
    ((10, -10, 0, 5), [[0, 1, 2, 3]]),  # one wall
])
def test_windows_from_viewing_directions(tilts, expected, caplog):
    """Optical axes in the body frame (turned about y from +z by the angles) grouped by side (average linkage)."""
    from ari_sfm.openptv.windows import windows_from_axes

    axes = [np.array([np.sin(np.radians(t)), 0.0, np.cos(np.radians(t))]) for t in tilts]
    names = [f"cam{k + 1}" for k in range(4)]
    windows = windows_from_axes(names, axes, 6.0, 1.5, 1.33)
    assert [list(w.cameras) for w in windows] == [[names[k] for k in g] for g in expected]
    assert len({w.name for w in windows}) == len(windows)


def test_windows_from_viewing_directions_warns_when_unclear(caplog):
    """Adjacent walls whose cameras tilt toward each other: the groups are not clear-cut, said so."""
    import logging

    from ari_sfm.openptv.windows import windows_from_axes

    axes = [np.array([np.sin(np.radians(t)), 0.0, np.cos(np.radians(t))]) for t in (-26, 26, 90 - 26, 90 + 26)]
    with caplog.at_level(logging.WARNING, logger="ari_sfm.openptv.windows"):
        windows_from_axes(["a", "b", "c", "d"], axes, 6.0, 1.5, 1.33)
    assert "a guess" in caplog.text and "--windows" in caplog.text


def test_an_imported_experiment_runs_its_particles_without_editing(cavity_without_ori, tmp_path):
    """sequence.par's images (``img_1/cam1.%d``, frames 10000..10001), criteria.par's observation volume and
    targ_rec.par's detector settings become the dataset's ``particles:``: after calibrating from the images and clicks,
    detect-particles and particles run on the imported dataset as it is and find the particles (rendered where OpenPTV's
    .ori put them)."""
    import cv2

    from ari_sfm.simulate.particle_images import render_particle_image

    root, _ = cavity_without_ori
    params = root / "parameters"
    (params / "sequence.par").write_text("img_1/cam1.%d\nimg_1/cam2.%d\nimg_1/cam3.%d\nimg_1/cam4.%d\n10000\n10001\n")
    (params / "criteria.par").write_text("-40\n-20\n20\n40\n-20\n20\n0.02\n0.02\n0.02\n0.02\n33\n0.05\n")
    (params / "targ_rec.par").write_text("9\n9\n9\n11\n100\n4\n500\n2\n100\n2\n100\n150\n2\n")  # test_cavity's
    rng = np.random.default_rng(7)
    (root / "img_1").mkdir()
    truth = {}
    for frame in (10000, 10001):
        X = rng.uniform([-30, -20, -15], [30, 20, 15], size=(60, 3))
        truth[frame] = X
        for k in range(1, 5):
            cam = read_liboptv_camera(FODDER / "cal" / f"cam{k}.tif.ori", root / "parameters" / "ptv.par")
            uv = liboptv_pixels(X, cam) + OPENCV_FROM_OPENPTV_PX
            img = render_particle_image(uv, (1280, 1024), 4.0, peak=150.0, rng=rng)
            assert cv2.imwrite(str(root / "img_1" / f"cam{k}.{frame}.png"), img)
            (root / "img_1" / f"cam{k}.{frame}.png").rename(root / "img_1" / f"cam{k}.{frame}")
    ds = tmp_path / "ds"
    for args in (["import", "openptv", str(root), "-o", str(ds)], ["calibrate", str(ds), "-o", str(tmp_path / "cal")],
                 ["detect-particles", str(ds), "-o", str(tmp_path / "det"), "--workers", "0"],
                 ["particles", str(ds), "--calibration", str(tmp_path / "cal" / "calibration.json"),
                  "--detections", str(tmp_path / "det" / "particles.parquet"), "-o", str(tmp_path / "p3d"),
                  "--workers", "0"]):
        r = CliRunner().invoke(main, args)
        assert r.exit_code == 0, (args[0], r.output)
        if args[0] == "import":  # targ_rec.par's thresholds and sizes are the detector's settings
            import yaml

            detect = yaml.safe_load((ds / "rig.yaml").read_text())["particles"]["detect"]
            tokens = [int(t) for t in (params / "targ_rec.par").read_text().split()[:13]]
            assert detect["threshold"] == {f"cam{k}": tokens[k - 1] for k in range(1, 5)}
            assert (detect["min_pixels"], detect["max_pixels"], detect["min_sum"]) == (tokens[5], tokens[6], tokens[11])
    import pyarrow.parquet as pq

    from ari_sfm.io import load_calibration

    table = pq.read_table(tmp_path / "p3d" / "particles3d.parquet").to_pydict()
    frames, xyz = np.array(table["frame"]), np.array([table["x"], table["y"], table["z"]]).T
    body_from_world = load_calibration(tmp_path / "cal" / "calibration.json").frames["f000"].inverse()
    for frame, X in truth.items():
        found = body_from_world.apply(xyz[frames == frame])
        d = np.linalg.norm(found[:, None] - X[None], axis=2).min(axis=1)
        assert len(found) >= 0.8 * len(X) and np.median(d) < 0.5, (frame, len(found), np.median(d))

"""The 3D error against a reference geometry (issue 10, item 8): a reconstruction of a simulated target
registered onto a mesh of the true target planes moved by a known rigid transform."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import rotation_from_rotvec
from ari_sfm.io import parse_calibration
from ari_sfm.reconstruction.reconstruct import reconstruct
from ari_sfm.reconstruction.reference import ReferenceErrors, reference_errors
from ari_sfm.simulate import make_scene, simulate

o3d = pytest.importorskip("open3d")

# the known transform from the calibration's world to the reference's coordinates
R_KNOWN = rotation_from_rotvec(np.deg2rad([8.0, -5.0, 20.0]))
T_KNOWN = np.array([40.0, -25.0, 300.0])


def board_mesh(poses: dict[str, tuple[np.ndarray, np.ndarray]], target, path: Path) -> Path:
    """A PLY mesh of each board (its corner grid plus one square all round) at world_from_target (R, t),
    moved by (R_KNOWN, T_KNOWN)."""
    s = target.square_mm
    cols, rows = target.inner_corners
    outline = np.array([[-s, -s, 0.0], [cols * s, -s, 0.0], [cols * s, rows * s, 0.0], [-s, rows * s, 0.0]])
    verts, tris = [], []
    for k, (R, t) in enumerate(poses.values()):
        verts.append(outline @ R.T + t)
        tris += [[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]]
    world = np.concatenate(verts)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(world @ R_KNOWN.T + T_KNOWN),
                                     o3d.utility.Vector3iVector(np.array(tris)))
    assert o3d.io.write_triangle_mesh(str(path), mesh)
    return path


def plane_distances(points, poses) -> np.ndarray:
    """The known 3D error normal to the board: n . (X - t) of every reconstructed point, frame by frame."""
    return np.concatenate([(points.frames[f].xyz - poses[f][1]) @ poses[f][0][:, 2] for f in points.frames])


@pytest.fixture(scope="module")
def tilted_boards():
    """The binocular scene's 15 calibration boards (15 orientations) triangulated with the true rig."""
    scene = make_scene("binocular", seed=0)
    cal = parse_calibration(scene.truth, "truth.json")
    obs = tuple(replace(o, set="reconstruction") for o in scene.dataset.observations if o.set == "calibration")
    points = reconstruct(replace(scene.dataset, observations=obs, calibration=(), reconstruction=()), cal)
    poses = {f: (np.array(scene.truth["frames"][f]["world_from_target"]["R"]),
                 np.array(scene.truth["frames"][f]["world_from_target"]["t"])) for f in points.frames}
    return scene, points, poses


def test_registration_recovers_the_known_transform_and_the_known_error(tilted_boards, tmp_path):
    """Registration finds (R_KNOWN, T_KNOWN) to 0.02 deg / 0.05 mm; each point-to-mesh distance is the point's
    known distance to its true board to 0.01 mm; the rms is the known rms within 2 % (least squares can only
    go below the truth's)."""
    scene, points, poses = tilted_boards
    known = np.abs(plane_distances(points, poses))
    r = reference_errors(points, board_mesh(poses, scene.dataset.target, tmp_path / "boards.ply"))
    M = np.array(r.registration.reference_from_world)
    dR = M[:3, :3] @ R_KNOWN.T
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.02
    assert np.linalg.norm(M[:3, 3] - T_KNOWN) < 0.05
    assert r.kind == "mesh" and r.count == points.num_points == len(known)
    known_rms = float(np.sqrt(np.mean(known**2)))
    assert 0.98 * known_rms <= r.distance_mm.rms <= known_rms * 1.0001
    assert 0.005 < known_rms < 0.05  # a real error to find (0.05 px pixel noise), not zero
    assert set(r.frames) == set(points.frames)
    xyz = np.concatenate([f.xyz for f in points.frames.values()])
    o3d_scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "boards.ply"))
    center = np.asarray(mesh.vertices).mean(axis=0)
    o3d_scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh.translate(-center)))
    per_point = o3d_scene.compute_distance(
        o3d.core.Tensor((xyz @ M[:3, :3].T + M[:3, 3] - center).astype(np.float32))).numpy()
    assert np.max(np.abs(per_point - known)) < 0.01
    assert abs(r.distance_mm.max - known.max()) < 0.01
    j = r.to_json()  # metrics.json's `reference` (docs/DATASET_FORMAT.md), and back
    assert set(j) == {"path", "kind", "count", "registration", "distance_mm", "frames"}
    assert set(j["registration"]) == {"reference_from_world", "rotation_deg", "translation_mm", "fitness",
                                      "inlier_rmse_mm"}
    assert set(j["distance_mm"]) == {"mean", "rms", "max", "p95"} and j["distance_mm"]["rms"] == r.distance_mm.rms
    assert ReferenceErrors.from_json(json.loads(json.dumps(j))).to_json() == j


def test_a_point_cloud_reference_registers_too(tilted_boards, tmp_path):
    """A cloud of the boards (~2 mm spacing): the same transform, less precisely (nearest samples and
    their estimated normals); distances include the sampling."""
    scene, points, poses = tilted_boards
    mesh = o3d.io.read_triangle_mesh(str(board_mesh(poses, scene.dataset.target, tmp_path / "boards.ply")))
    n = 50_000
    cloud = mesh.sample_points_uniformly(number_of_points=n)
    spacing = np.sqrt(mesh.get_surface_area() / n)  # ~1.9 mm
    assert o3d.io.write_point_cloud(str(tmp_path / "boards_cloud.ply"), cloud)
    r = reference_errors(points, tmp_path / "boards_cloud.ply")
    M = np.array(r.registration.reference_from_world)
    dR = M[:3, :3] @ R_KNOWN.T
    assert r.kind == "cloud"
    angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    print(f"cloud reference: rotation error {angle:.4f} deg, translation error "
          f"{np.linalg.norm(M[:3, 3] - T_KNOWN):.4f} mm, "
          f"distance rms {r.distance_mm.rms:.4f} mm")
    assert angle < 0.1 and np.linalg.norm(M[:3, 3] - T_KNOWN) < 0.25  # measured 0.037 deg, 0.061 mm
    assert r.distance_mm.rms < spacing  # ~ the nearest sample's distance, not the reconstruction's error


@pytest.mark.parametrize("content, message", [(None, "reference geometry not found"),
                                              (b"ply\nformat ascii 1.0\nend_header\n", "no triangles or points read"),
                                              (b"not a mesh", "not a PLY file")])
def test_bad_reference_is_one_line(tilted_boards, tmp_path, content, message):
    _, points, _ = tilted_boards
    path = tmp_path / "ref.ply"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(AriSfmError) as info:
        reference_errors(points, path)
    assert info.value.path == str(path) and message in info.value.message


def test_cli_reconstruct_with_reference_writes_metrics_and_report(tmp_path):
    """`reconstruct --reference` on the stage frames (parallel boards) with the true rig: metrics.json holds the
    reference error, equal to the known plane distances' rms within 2 %; `report` shows it."""
    ds, truth_path = simulate("binocular", tmp_path / "sim", seed=0, images=False)
    truth = json.loads(Path(truth_path).read_text())
    from ari_sfm.records import Target

    target = Target(type="checkerboard", square_mm=10.0, inner_corners=(11, 8))
    poses = {}
    for f, rec in truth["reconstruction_points_world"].items():
        X = dict(zip(rec["ids"], np.asarray(rec["xyz"], float)))
        x_axis = (X[10] - X[0]) / np.linalg.norm(X[10] - X[0])
        y_axis = (X[77] - X[0]) / np.linalg.norm(X[77] - X[0])
        poses[f] = (np.stack([x_axis, y_axis, np.cross(x_axis, y_axis)], axis=1), X[0])
    ref = board_mesh(poses, target, tmp_path / "boards.ply")
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["reconstruct", str(ds), "--calibration", str(truth_path), "-o", str(out),
                                  "--reference", str(ref)])
    assert r.exit_code == 0, r.output
    m = json.loads((out / "metrics.json").read_text())
    from ari_sfm.reconstruction.reconstruct import Points

    known = np.abs(plane_distances(Points.load(out / "points.json"), poses))
    known_rms = float(np.sqrt(np.mean(known**2)))
    assert 0.98 * known_rms <= m["reference"]["distance_mm"]["rms"] <= known_rms * 1.0001
    assert "vs reference mesh: distance rms" in r.output
    # the report needs a calibration.json in OUT: the truth's, as the calibration that made the points
    (out / "calibration.json").write_text(Path(truth_path).read_text())
    r = CliRunner().invoke(main, ["report", str(out), "--dataset", str(ds)])
    assert r.exit_code == 0, r.output
    assert "3D error vs reference mesh boards.ply" in (out / "report.html").read_text()


def test_cli_bad_reference_fails_before_writing(tmp_path):
    ds, truth_path = simulate("binocular", tmp_path / "sim", seed=0, images=False)
    r = CliRunner().invoke(main, ["reconstruct", str(ds), "--calibration", str(truth_path), "-o", str(tmp_path / "o"),
                                  "--reference", str(tmp_path / "missing.ply")])
    assert r.exit_code == 1 and r.output.strip() == f"error: {tmp_path / 'missing.ply'}: reference geometry not found"
    assert not (tmp_path / "o" / "points.json").exists()


def _boards_vertices_faces(tilted_boards, tmp_path):
    scene, _, poses = tilted_boards
    mesh = o3d.io.read_triangle_mesh(str(board_mesh(poses, scene.dataset.target, tmp_path / "boards.ply")))
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def _write(path: Path, vertices: np.ndarray, faces: np.ndarray | None = None, ascii: bool = False) -> Path:
    if faces is None:
        geometry = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(vertices))
        assert o3d.io.write_point_cloud(str(path), geometry, write_ascii=ascii)
    else:
        geometry = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces))
        assert o3d.io.write_triangle_mesh(str(path), geometry, write_ascii=ascii)
    return path


@pytest.mark.parametrize("case, message", [
    ("truncated binary mesh", "truncated: its header declares 60 vertex, 30 face"),
    ("truncated ascii mesh", "truncated: its header declares 90 rows (60 vertex, 30 face), the file has"),
    ("truncated cloud", "truncated: its header declares 50000 vertex"),
    ("out of range", "coordinates up to 8.3e+30: out of range (lengths in mm, at most 1e+07)"),
    ("one point", "degenerate: all its 100 points are one point"),
    ("one line", "degenerate: all its 100 points lie on one line"),
    ("far and small", "registration failed: 3% of the 1320 reconstructed points lie within 16.4 mm"),
])
def test_reference_that_cannot_give_a_figure_is_refused(tilted_boards, tmp_path, capfd, case, message):
    """A far, degenerate, out-of-range or truncated reference printed results (registration fitness ~0,
    distances 4.99e30 mm) or RPly's own error line."""
    _, points, _ = tilted_boards
    vertices, faces = _boards_vertices_faces(tilted_boards, tmp_path)
    path = tmp_path / "ref.ply"
    if case.startswith("truncated"):
        if case == "truncated cloud":
            cloud = o3d.io.read_triangle_mesh(str(tmp_path / "boards.ply")).sample_points_uniformly(50_000)
            _write(path, np.asarray(cloud.points))
        else:
            _write(path, vertices, faces, ascii="ascii" in case)
        data = path.read_bytes()
        path.write_bytes(data[:len(data) * 2 // 3])
    elif case == "out of range":
        _write(path, vertices * 1e28, faces)
    elif case == "one point":
        _write(path, np.tile([[1.0, 2.0, 3.0]], (100, 1)))
    elif case == "one line":
        _write(path, np.outer(np.linspace(0, 100, 100), [1.0, 2.0, 2.0]))
    else:  # the boards 1000 x smaller (a reference in m) and 5 m away
        _write(path, vertices * 1e-3 + 5000.0, faces)
    capfd.readouterr()
    with pytest.raises(AriSfmError) as info:
        reference_errors(points, path)
    assert info.value.path == str(path) and info.value.message.startswith(message), info.value.message
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == ""  # no RPly or Open3D line of its own

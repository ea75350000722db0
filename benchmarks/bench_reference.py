"""The 3D error against a reference geometry (ari_sfm.reconstruction.reference): accuracy of the registration and time.

    python benchmarks/bench_reference.py

Scene: the binocular scenario (seed 0, sigma 0.05 px); its 15 calibration
boards (15 orientations, 1320 corners) triangulated with the true rig. The
reference: a mesh of the true boards (each corner grid plus one square all
round) moved by a known rigid motion (8, -5, 20 deg; 40, -25, 300 mm), and a
50 000-point cloud sampled from it. Printed: the error of the recovered
motion, the point-to-surface distance rms against the known rms (each
point's distance to its true board), and the time of reference_errors.
"""
from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d

from ari_sfm.geometry import rotation_from_rotvec
from ari_sfm.io import parse_calibration
from ari_sfm.reconstruction.reconstruct import reconstruct
from ari_sfm.reconstruction.reference import reference_errors
from ari_sfm.simulate import make_scene

R_KNOWN = rotation_from_rotvec(np.deg2rad([8.0, -5.0, 20.0]))
T_KNOWN = np.array([40.0, -25.0, 300.0])


def main() -> None:
    scene = make_scene("binocular", seed=0)
    cal = parse_calibration(scene.truth, "truth.json")
    obs = tuple(replace(o, set="reconstruction") for o in scene.dataset.observations if o.set == "calibration")
    points = reconstruct(replace(scene.dataset, observations=obs, calibration=(), reconstruction=()), cal)
    target = scene.dataset.target
    s, (cols, rows) = target.square_mm, target.inner_corners
    outline = np.array([[-s, -s, 0.0], [cols * s, -s, 0.0], [cols * s, rows * s, 0.0], [-s, rows * s, 0.0]])
    verts, tris, known = [], [], []
    for k, name in enumerate(points.frames):
        pose = scene.truth["frames"][name]["world_from_target"]
        R, t = np.array(pose["R"]), np.array(pose["t"])
        verts.append(outline @ R.T + t)
        tris += [[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]]
        known.append(np.abs((points.frames[name].xyz - t) @ R[:, 2]))
    known = np.concatenate(known)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.concatenate(verts) @ R_KNOWN.T + T_KNOWN),
                                     o3d.utility.Vector3iVector(np.array(tris)))
    with tempfile.TemporaryDirectory() as tmp:
        mesh_path, cloud_path = Path(tmp) / "boards.ply", Path(tmp) / "boards_cloud.ply"
        o3d.io.write_triangle_mesh(str(mesh_path), mesh)
        o3d.utility.random.seed(0)
        o3d.io.write_point_cloud(str(cloud_path), mesh.sample_points_uniformly(number_of_points=50_000))
        print(f"{points.num_points} points in {len(points.frames)} boards; known distance rms "
              f"{np.sqrt(np.mean(known**2)):.5f} mm, max {known.max():.5f} mm")
        print(f"{'reference':10s} {'rotation err (deg)':>18s} {'translation err (mm)':>20s} {'rms (mm)':>9s} "
              f"{'max (mm)':>9s} {'time (s)':>8s}")
        for label, path in (("mesh", mesh_path), ("cloud 50k", cloud_path)):
            t0 = time.perf_counter()
            r = reference_errors(points, path)
            elapsed = time.perf_counter() - t0
            M = np.array(r.registration.reference_from_world)
            dR = M[:3, :3] @ R_KNOWN.T
            angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
            print(f"{label:10s} {angle:18.4f} {np.linalg.norm(M[:3, 3] - T_KNOWN):20.4f} "
                  f"{r.distance_mm.rms:9.5f} {r.distance_mm.max:9.5f} {elapsed:8.2f}")


if __name__ == "__main__":
    main()

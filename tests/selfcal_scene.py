"""A small 4-camera particle experiment behind 10 mm of glass into water, for tests/test_selfcal.py
(exact model; no matcher involved): rig A (the target calibration), rig B (cameras 1 and 2 moved),
particles per frame and their noisy detections with true ids."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ari_sfm.calibration import Calibration, CameraCalibration
from ari_sfm.geometry import Pose, rotation_from_rotvec
from ari_sfm.records import Interface

VOLUME_CENTRE_LAB = np.array([0.0, 0.0, 420.0])
VOLUME_HALF_MM = np.array([30.0, 20.0, 15.0])
IMAGE_SIZE = (1280, 1024)


def _look_at(centre: np.ndarray, target: np.ndarray) -> Pose:
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return Pose(R, -R @ centre)


def rig_a() -> Calibration:
    """Rig A (see :func:`rig_and_world_from_lab`)."""
    return rig_and_world_from_lab()[0]


def rig_and_world_from_lab() -> tuple[Calibration, Pose]:
    """Four cameras ~435 mm from the volume, 60 mm from a 10 mm glass plate, water behind; world = camera 0."""
    centres = [np.array(c) for c in ([-90.0, -70, 0], [90.0, -70, 0], [90.0, 70, 0], [-90.0, 70, 0])]
    K = np.array([[3500.0, 0, 639.5], [0, 3500.0, 511.5], [0, 0, 1]])
    interface = Interface(10.0, 1.5, 1.333, 60.0)
    normal_lab = np.array([0.0, 0.0, 1.0])
    cams = {}
    for k, c in enumerate(centres):
        pose = _look_at(c, VOLUME_CENTRE_LAB)
        for _ in range(4):  # turn the camera until the volume's centre, seen through the window, is at the image centre
            lab = Calibration("exact", interface, normal_lab,
                              {"c": CameraCalibration("c", IMAGE_SIZE, K, np.zeros(5), pose)}, {})
            ray = np.linalg.solve(K, np.r_[lab.project_world("c", VOLUME_CENTRE_LAB[None])[0], 1.0])
            axis = np.cross(ray / np.linalg.norm(ray), [0.0, 0.0, 1.0])
            turn = rotation_from_rotvec(axis / max(np.linalg.norm(axis), 1e-300) * np.arcsin(min(np.linalg.norm(axis), 1.0)))
            pose = Pose(turn @ pose.R, turn @ pose.t)
        cams[f"cam{k}"] = pose
    world_from_lab = cams["cam0"]
    lab_from_world = world_from_lab.inverse()
    cams = {n: CameraCalibration(n, IMAGE_SIZE, K.copy(), np.zeros(5), p.compose(lab_from_world)) for n, p in cams.items()}
    cal = Calibration("exact", replace(interface, distance_mm=60.0 - normal_lab @ lab_from_world.t),
                      world_from_lab.R @ normal_lab, cams, {})
    return cal, world_from_lab


def drifted(cal: Calibration, cameras=("cam1", "cam2"), angle_deg: float = 0.05, shift_mm: float = 0.3,
            seed: int = 1) -> Calibration:
    """Rig B: the named cameras moved by a small rigid motion (random axis and direction)."""
    rng = np.random.default_rng(seed)
    cams = dict(cal.cameras)
    for n in cameras:
        axis = rng.normal(size=3)
        move = rng.normal(size=3)
        delta = Pose(rotation_from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis)),
                     shift_mm * move / np.linalg.norm(move))
        cams[n] = replace(cams[n], cam_from_world=delta.compose(cams[n].cam_from_world))
    return replace(cal, cameras=cams)


@dataclass(frozen=True)
class Experiment:
    xyz: dict  # frame -> (P, 3) world
    detections: dict  # frame -> {camera: (N, 2)}
    ids: dict  # frame -> {camera: (N,)} true particle index of each detection


def experiment(rig: Calibration, frames: int = 3, particles: int = 300, sigma_px: float = 0.1,
               seed: int = 2) -> Experiment:
    rng = np.random.default_rng(seed)
    world_from_lab = rig_and_world_from_lab()[1]
    xyz, dets, ids = {}, {}, {}
    for f in range(frames):
        X = world_from_lab.apply(VOLUME_CENTRE_LAB + rng.uniform(-1, 1, (particles, 3)) * VOLUME_HALF_MM)
        xyz[f], dets[f], ids[f] = X, {}, {}
        for n in rig.cameras:
            uv = rig.project_world(n, X) + rng.normal(0.0, sigma_px, (particles, 2))
            inside = np.isfinite(uv).all(axis=1) & (uv[:, 0] > 0) & (uv[:, 1] > 0) \
                & (uv[:, 0] < IMAGE_SIZE[0] - 1) & (uv[:, 1] < IMAGE_SIZE[1] - 1)
            order = rng.permutation(np.flatnonzero(inside))
            dets[f][n], ids[f][n] = uv[order], order
    return Experiment(xyz, dets, ids)

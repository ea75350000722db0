"""Errors of a refined (or COLMAP) reconstruction against simulated truth, after similarity alignment."""
from __future__ import annotations

from typing import Any

import numpy as np

from ari_sfm.colmap.adapter import COLMAP_PIXEL_OFFSET, ColmapModel, model_from_reconstruction
from ari_sfm.geometry import Pose, angle_between_deg
from ari_sfm.simulate.port_survey import SfmTruth

from .problem import State


def similarity(A: np.ndarray, B: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity with ``B ~ s R A + t`` (Umeyama).

    Args:
        A: (N, 3) points.
        B: (N, 3) the same points elsewhere.

    Returns:
        (s, R, t).
    """
    ma, mb = A.mean(axis=0), B.mean(axis=0)
    a, b = A - ma, B - mb
    U, S, Vt = np.linalg.svd(b.T @ a)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / np.sum(a * a))
    return s, R, mb - s * R @ ma


def truth_errors(truth: SfmTruth, model: ColmapModel, xyz: np.ndarray, cam_from_world: dict[int, Pose]
                 ) -> dict[str, float]:
    """Point RMS (mm) after the similarity best aligning the points to the truth, camera-centre RMS and scale error.

    Points and images are matched by id (point3D_id k + 1 = truth point k, image_id i + 1 = truth image i, as
    reconstruction_from_arrays writes them).

    Args:
        truth: the simulation.
        model: the COLMAP model's arrays (its ids).
        xyz: (P, 3) the estimated points.
        cam_from_world: the estimated poses by image id.

    Returns:
        ``points_rms_mm``, ``centres_rms_mm`` (under the same similarity) and ``scale_error_pct``.
    """
    X_true = truth.xyz[model.point3D_ids - 1]
    s, R, t = similarity(xyz, X_true)
    e = s * xyz @ R.T + t - X_true
    centres = np.array([p.inverse().t for p in (cam_from_world[int(i)] for i in model.image_ids)])
    c_true = np.array([truth.cam_from_world(int(i) - 1).inverse().t for i in model.image_ids])
    ec = s * centres @ R.T + t - c_true
    return {"points_rms_mm": float(np.sqrt(np.mean(np.sum(e ** 2, axis=1)))),
            "centres_rms_mm": float(np.sqrt(np.mean(np.sum(ec ** 2, axis=1)))),
            "scale_error_pct": float(100.0 * (1.0 / s - 1.0))}


def colmap_truth_errors(truth: SfmTruth, rec: Any) -> dict[str, float]:
    """:func:`truth_errors` of a COLMAP reconstruction as it stands (its pinhole poses and points).

    Args:
        truth: the simulation.
        rec: the pycolmap.Reconstruction.

    Returns:
        As :func:`truth_errors`.
    """
    model = model_from_reconstruction(rec)
    poses = {int(i): Pose(np.array(rec.image(int(i)).cam_from_world().rotation.matrix()),
                          np.array(rec.image(int(i)).cam_from_world().translation)) for i in model.image_ids}
    return truth_errors(truth, model, model.xyz, poses)


def window_errors(truth: SfmTruth, normals: np.ndarray, distances: np.ndarray,
                  first_rig_from_world: Pose | None = None) -> dict[str, float]:
    """Normal angle (deg) and distance (mm) errors of the refined window.

    Args:
        truth: the simulation.
        normals: the refined normals (per housing, or the world window's).
        distances: the refined distances.
        first_rig_from_world: the estimate's first frame (mount world: the errors are in its rig coordinates).

    Returns:
        ``normal_deg`` and ``distance_mm`` (mount camera: of the worst housing).
    """
    if truth.mount == "camera":
        ang = max(angle_between_deg(n, m) for n, m in zip(normals, truth.normal_cam))
        dist = max(abs(d - h) for d, h in zip(distances, truth.distance_mm))
    else:
        est, tru = first_rig_from_world, truth.rig_from_world[0]
        if est is None or truth.normal_world is None or truth.plane_mm is None:
            raise ValueError("mount world: the estimate's first frame and the truth's world window are needed")
        ang = angle_between_deg(est.R @ normals[0], tru.R @ truth.normal_world)
        dist = abs((float(distances[0]) - normals[0] @ est.inverse().t)
                   - (truth.plane_mm - truth.normal_world @ tru.inverse().t))
    return {"normal_deg": float(ang), "distance_mm": float(dist)}


def truth_state(truth: SfmTruth, model: ColmapModel) -> State:
    """The simulated truth as a refine-colmap state of ``model`` (ids as in :func:`truth_errors`).

    The start of the truth-started refinement, the yardstick of a refinement from COLMAP's model.

    Args:
        truth: the simulation.
        model: the COLMAP model's arrays.

    Returns:
        The state.
    """
    params = tuple(np.r_[p[:2], p[2:4] + COLMAP_PIXEL_OFFSET] for p in truth.params)
    sensors = tuple(truth.sensor_from_rig[c] for c in model.image_camera)
    frames = tuple(truth.rig_from_world[int(f) - 1] for f in model.frame_ids)
    if truth.mount == "camera":
        normals, distances = np.array(truth.normal_cam), np.array(truth.distance_mm)
    else:
        if truth.normal_world is None:
            raise ValueError("mount world: the truth has no world window")
        normals, distances = truth.normal_world[None, :], np.array([truth.plane_mm])
    return State(params, frames, sensors, normals, distances, truth.xyz[model.point3D_ids - 1].copy())

"""refine-colmap's outputs from the refined state: the refractive cameras as a calibration, the refined model,
its best approximation in COLMAP's camera models, and the report (refine.json)."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ari_sfm.calibration.origin import RefineColmapFrames
from ari_sfm.calibration.record import Calibration, CameraCalibration
from ari_sfm.colmap import adapter
from ari_sfm.geometry import Pose, rotation_from_rotvec
from ari_sfm.models import PinholeModel

from .options import Approximation, Mount
from .paraxial import convert
from .plan import Reached, Setup, camera_names
from .plane import declared_window
from .problem import RefractiveProblem, State
from .report import (
    BaselineReport,
    DeclaredPlaneReport,
    Plate,
    RefineCounts,
    RefineReport,
    Reprojection,
    ScaleBarReport,
    WindowEstimate,
)


def opencv_params(model: adapter.ColmapModel, c: int, colmap_params: np.ndarray) -> np.ndarray:
    """Camera ``c``'s parameters as COLMAP OPENCV ``[fx fy cx cy k1 k2 p1 p2]`` (COLMAP pixels).

    Args:
        model: the COLMAP model.
        c: the camera's index.
        colmap_params: its parameters in its own COLMAP model.

    Returns:
        The OPENCV parameters.
    """
    p9 = model.params9(c, colmap_params)
    return np.r_[p9[:2], p9[2:4] + adapter.COLMAP_PIXEL_OFFSET, p9[4:8]]


def rms(per_image: dict[int, float]) -> float:
    """The RMS of per-image RMS values (NaN without images)."""
    v = np.array(list(per_image.values()))
    return float(np.sqrt(np.mean(v ** 2))) if len(v) else float("nan")


def per_image_rms(model: adapter.ColmapModel, residuals: np.ndarray) -> dict[int, float]:
    """Each image's RMS reprojection error (px) by COLMAP image id.

    Args:
        model: the COLMAP model.
        residuals: (M, 2) residuals of its observations.

    Returns:
        image id -> RMS (images without observations left out).
    """
    e2 = np.sum(residuals ** 2, axis=1)
    sums = np.bincount(model.obs_image, e2, len(model.image_ids))
    counts = np.bincount(model.obs_image, minlength=len(model.image_ids))
    return {int(i): float(np.sqrt(sums[k] / counts[k])) for k, i in enumerate(model.image_ids) if counts[k]}


def calibration(model: adapter.ColmapModel, problem: RefractiveProblem, state: State, mount: str,
                cam_from_world: dict[int, Pose]) -> Calibration:
    """The refractive cameras as a Calibration (exact model).

    Mount camera: each camera in its housing's frame (the port's near face the plane z = distance_mm), the
    images' poses beside them; mount world: the cameras at their first image's pose in the COLMAP world (mm).

    Args:
        model: the COLMAP model.
        problem: the refractive problem (its plate).
        state: the refined state.
        mount: ``camera`` or ``world``.
        cam_from_world: every image's refined pose by COLMAP image id.

    Returns:
        The calibration (its ``refine_colmap`` record: how it sits in the COLMAP model).
    """
    cams = {}
    names = camera_names(model)
    if mount == "camera":
        plane = float(np.max(state.distances))
        normal_world = np.array([0.0, 0.0, 1.0])
    else:
        plane = float(state.distances[0])
        normal_world = state.normals[0]
    for c, name in enumerate(names):
        p9 = model.params9(c, state.colmap_params[c])
        K = PinholeModel.from_params(p9).K
        if mount == "camera":
            n = state.normals[c]
            v = np.cross([0.0, 0.0, 1.0], n)
            sin = float(np.linalg.norm(v))
            R = np.eye(3) if sin < 1e-15 else rotation_from_rotvec(v / sin * np.arctan2(sin, n[2]))  # R e_z = n_c
            pose = Pose(R, -R @ np.array([0.0, 0.0, plane - state.distances[c]]))
        else:
            i = int(np.flatnonzero(model.image_camera == c)[0])
            pose = cam_from_world[int(model.image_ids[i])]
        cams[name] = CameraCalibration(name, model.image_sizes[c], K, p9[4:].copy(), pose)
    frame_note = ("each camera's housing frame: the port's near face is the plane z = distance_mm; "
                  "image poses: extra images_cam_from_world" if mount == "camera" else "the COLMAP model's world (mm)")
    frames = RefineColmapFrames(str(mount), frame_note, {n: int(cid) for n, cid in zip(names, model.camera_ids)},
                                {int(i): p for i, p in cam_from_world.items()})
    interface = replace(problem.interface, distance_mm=plane)
    return Calibration("exact", interface, normal_world, cams, {}, refine_colmap=frames)


def state_reconstruction(rec: Any, model: adapter.ColmapModel, problem: RefractiveProblem, state: State) -> Any:
    """A copy of ``rec`` with ``state``'s cameras, frame poses, rig sensors and points.

    Args:
        rec: the input pycolmap.Reconstruction.
        model: its arrays.
        problem: the refractive problem (which sensors are free).
        state: the state.

    Returns:
        The pycolmap.Reconstruction.
    """
    sensors = {int(model.camera_ids[c]): state.sensor_from_rig[int(np.flatnonzero(model.image_camera == c)[0])]
               for c in range(len(model.camera_ids)) if problem.layout.sensors[c, 0] >= 0}
    return adapter.refined_reconstruction(rec, model, state.colmap_params, state.rig_from_world, sensors, state.xyz)


def window_parts(hold_normal: bool, estimate_distance: bool, declared: bool) -> str:
    """What of the window is estimated, in words, for the report.

    Args:
        hold_normal: the normal is held.
        estimate_distance: the distance is estimated.
        declared: a plane is declared.

    Returns:
        The words.
    """
    parts = [p for p, free in (("normal", not hold_normal), ("distance", estimate_distance)) if free]
    why = "held at the declared plane" if declared else "distance held: unobservable in air"
    if not parts:
        return f"(none: {why})"
    return " and ".join(parts) + ("" if len(parts) == 2 else f" ({why})") + (" with the declared plane's prior"
                                                                               if declared else "")


@dataclass(frozen=True)
class Outputs:
    """The refinement's results beside its state: the COLMAP model to hand to COLMAP's tools (the refined
    points, the cameras as their best approximation in COLMAP's models), the refractive model itself, the
    calibration."""

    reconstruction: Any  # pycolmap.Reconstruction: the approximation
    refractive: Any  # pycolmap.Reconstruction: the refined state (its cameras are not pinhole cameras of the images)
    calibration: Calibration
    approximation_px: dict[int, float]  # the approximation's per-image RMS on the refined points


def outputs(rec: Any, s: Setup, state: State) -> Outputs:
    """The refined model, its COLMAP approximation and the calibration of ``state``.

    Args:
        rec: the input pycolmap.Reconstruction.
        s: the refinement's setup.
        state: the refined state.

    Returns:
        The outputs.
    """
    cmodel, problem, opts = s.model, s.problem, s.options
    R, t = state.cam_from_world(cmodel)
    cam_from_world = {int(i): Pose(R[k], t[k]) for k, i in enumerate(cmodel.image_ids)}
    refractive = state_reconstruction(rec, cmodel, problem, state)
    virtual = convert(cmodel, problem, state, -1)
    opencv = ({int(cid): opencv_params(cmodel, c, virtual.colmap_params[c]) for c, cid in enumerate(cmodel.camera_ids)
               if cmodel.camera_models[c] != "FULL_OPENCV"} if opts.approximation == Approximation.OPENCV else None)
    approx = adapter.pinhole_approximation(state_reconstruction(rec, cmodel, problem, virtual), opencv)
    approx_rms = adapter.image_residuals_px(approx, replace(cmodel, xyz=virtual.xyz))  # its points are the state's
    cal = calibration(cmodel, problem, state, opts.mount, cam_from_world)
    return Outputs(approx, refractive, cal, approx_rms)


def refine_report(s: Setup, reached: Reached, out: Outputs, before: dict[int, float], seconds: float
                  ) -> RefineReport:
    """What the refinement did and found (refine.json).

    Args:
        s: the refinement's setup.
        reached: where its stages left it.
        out: its outputs (the approximation's residuals).
        before: COLMAP's own per-image RMS of the input.
        seconds: its time.

    Returns:
        The report.
    """
    cmodel, problem, opts, scale, plane = s.model, s.problem, s.options, s.scale, s.plane
    result, start, sigmas = reached.result, reached.start, reached.sigmas
    assert result is not None and start is not None and sigmas is not None  # every stage ran
    state = result.state
    residuals = problem.residuals(state)
    e = np.linalg.norm(residuals, axis=1)
    ids = camera_names(cmodel)
    window = (WindowEstimate(normal_cam={n: state.normals[c].copy() for c, n in enumerate(ids)},
                             distance_mm={n: float(state.distances[c]) for c, n in enumerate(ids)})
              if opts.mount == Mount.CAMERA else WindowEstimate(normal_world=state.normals[0].copy(),
                                                                plane_mm=float(state.distances[0])))
    bar, base, interface = scale.bar, scale.baseline, s.interface
    return RefineReport(
        mount=opts.mount.value, model=opts.model, backend=opts.backend.value, units_mm=scale.units_mm,
        interface=Plate(interface.thickness_mm, interface.index, interface.medium_index),
        counts=RefineCounts(len(cmodel.camera_ids), len(cmodel.frame_ids), len(cmodel.image_ids),
                            len(cmodel.point3D_ids), len(cmodel.obs_image), problem.layout.size),
        estimated="intrinsics per camera, rig_from_world per frame (the first held: gauge), sensor_from_rig per "
                  "non-reference sensor, window " + window_parts(s.hold_normal, s.estimate_distance, plane is not None)
                  + " per " + ("camera (housing)" if opts.mount == Mount.CAMERA else "world") + ", 3D points",
        scale=("held by the scale bar (a term of the solver)" if bar is not None else
               "held by the baseline between two images' camera centres (a term of the solver)" if base is not None
               else "the input's units times units_mm, refined by refraction (weakly observable through the plate)"),
        distance_search=start.search, restarts=reached.restarts,
        iterations=reached.iterations, converged=result.converged,
        linearizations=reached.linearizations, search_linearizations=sum(c.linearizations for c in start.search),
        uncertainty=sigmas, cost_start=float(result.initial_cost), cost_final=float(result.cost),
        time_s=seconds,
        before=Reprojection("COLMAP pinhole", rms(before), before),
        after=Reprojection("exact", float(np.sqrt(np.mean(e ** 2))), per_image_rms(cmodel, residuals),
                           mean_px=float(np.mean(e))),
        pinhole_approximation=Reprojection(opts.approximation.value.upper()
                                           if opts.approximation == Approximation.OPENCV else "input's",
                                           rms(out.approximation_px), out.approximation_px, model_key="camera_model"),
        window=window,
        plane=None if plane is None else DeclaredPlaneReport(
            plane.frame, declared_window(plane)[0], np.asarray(plane.point_mm, float),
            "held" if s.hold_normal else f"prior {plane.sigma_deg:g} deg",
            f"prior {plane.sigma_mm:g} mm" if s.estimate_distance else "held"),
        scale_bar=None if bar is None or opts.scale_bar is None else ScaleBarReport(
            (int(opts.scale_bar[0]), int(opts.scale_bar[1])), bar.length_mm, bar.sigma_mm, bar.length(state.xyz)),
        baseline=None if base is None else BaselineReport(
            (cmodel.image_names[base.a], cmodel.image_names[base.b]), base.length_mm, base.sigma_mm,
            base.length(state)))

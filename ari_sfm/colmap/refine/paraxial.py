"""refine-colmap's start state: COLMAP's model read as paraxial virtual cameras, and the moves between them
and the refractive cameras.

A camera behind a plate with a medium n_m sees the scene as a pinhole with focal n_m f whose centre sits
``n_m a`` behind it along the normal (``a`` the ari model's apparent offset): :func:`convert` goes from those
virtual cameras to the refractive start (focal lengths divided by n_m, centres moved forward) and back. The
window starts on the optical axis (mount camera) or on the mean viewing direction (mount world)
(:func:`initial_state`), at a distance (:func:`with_distance`) or at the declared plane
(:func:`declared_start`). The scale is the cost's near-flat direction (:func:`scaled`, :func:`to_scale`).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ari_sfm.colmap import adapter
from ari_sfm.errors import AriSfmError, ErrorPath
from ari_sfm.geometry import Pose
from ari_sfm.models import AriModel, PinholeModel
from ari_sfm.records import Interface, WindowPlane

from .plane import declared_window
from .problem import RefractiveProblem, State
from .scale_bar import Baseline, ScaleBar

PLANE_FRAMES = {"camera": "camera", "world": "world"}  # the only frame interface.plane may name, per mount


def paraxial_offset_mm(interface: Interface, normal_cam: np.ndarray, h: float) -> float:
    """How far the paraxial virtual centre sits behind the real one along the normal: ``n_m a``.

    Args:
        interface: the plate.
        normal_cam: the window's unit normal in the camera frame.
        h: the window's distance from the camera centre (mm).

    Returns:
        The offset in mm.
    """
    ari = AriModel(PinholeModel(np.eye(3)), normal_cam, interface.thickness_mm, interface.index,
                   interface.medium_index, h)
    a = float(ari.apparent_points(np.zeros(3))[0] @ ari.normal_cam)
    return interface.medium_index * a


def _focal_rows(model: adapter.ColmapModel, c: int) -> np.ndarray:
    """Mask of camera c's COLMAP parameters that are focal lengths."""
    return np.asarray(model.param_map[c][:2].any(axis=0))


def convert(model: adapter.ColmapModel, problem: RefractiveProblem, state: State, direction: int) -> State:
    """Paraxial virtual cameras -> refractive start (``direction`` +1), or back (-1).

    Focal lengths are divided (multiplied) by n_m, each frame's centre moved by +-n_m a along its window normal.

    Args:
        model: the COLMAP model.
        problem: the refractive problem (its plate and window layout).
        state: the state to convert.
        direction: +1 virtual -> refractive, -1 refractive -> virtual.

    Returns:
        The converted state.
    """
    nm = problem.interface.medium_index
    params = []
    for c, p in enumerate(state.colmap_params):
        p = p.copy()
        p[_focal_rows(model, c)] *= nm ** (-direction)
        params.append(p)
    normals, dists = problem.image_windows(state)
    frames = list(state.rig_from_world)
    R, t = state.cam_from_world(model)
    for f in range(len(frames)):
        i = int(np.flatnonzero(model.image_frame == f)[0])
        n_world = R[i].T @ normals[i]
        shift = direction * paraxial_offset_mm(problem.interface, normals[i], max(float(dists[i]), 1e-3))
        pose = frames[f]
        centre = -pose.R.T @ pose.t + shift * n_world
        frames[f] = Pose(pose.R, -pose.R @ centre)
    return replace(state, colmap_params=tuple(params), rig_from_world=tuple(frames))


def initial_state(model: adapter.ColmapModel, mount: str, units: float) -> State:
    """COLMAP's model as the virtual cameras' state, lengths times ``units`` (mm per model unit).

    Args:
        model: the COLMAP model.
        mount: ``camera`` (the window on each optical axis, distance 0) or ``world`` (on the mean viewing
            direction).
        units: mm per unit of the model.

    Returns:
        The state (the window's distance still to be set: :func:`with_distance`).
    """
    frames = tuple(Pose(p.R, p.t * units) for p in model.rig_from_world)
    sensors = tuple(Pose(p.R, p.t * units) for p in model.sensor_from_rig)
    C = len(model.camera_ids)
    state = State(tuple(p.copy() for p in model.colmap_params), frames, sensors, np.zeros((1, 3)), np.zeros(1),
                  model.xyz * units)
    if mount == "camera":
        return replace(state, normals=np.tile([0.0, 0.0, 1.0], (C, 1)), distances=np.zeros(C))
    R, _ = state.cam_from_world(model)
    axis = R[:, 2, :].mean(axis=0)  # optical axes in the world: rows z of cam_from_world
    return replace(state, normals=(axis / np.linalg.norm(axis))[None, :])


def with_distance(model: adapter.ColmapModel, state: State, mount: str, h: float) -> State:
    """``state`` with the window ``h`` in front of every camera (mount world: of the farthest camera centre).

    Args:
        model: the COLMAP model.
        state: the state.
        mount: ``camera`` or ``world``.
        h: the distance (mm).

    Returns:
        The state with its window distances set.
    """
    if mount == "camera":
        return replace(state, distances=np.full(len(state.distances), h))
    R, t = state.cam_from_world(model)
    centres = -np.einsum("nji,nj->ni", R, t)
    return replace(state, distances=np.array([float(np.max(centres @ state.normals[0])) + h]))


def restart_at(model: adapter.ColmapModel, problem: RefractiveProblem, state: State, mount: str, h: float) -> State:
    """``state`` with its window moved to distance ``h``, paraxially (the virtual cameras kept).

    Args:
        model: the COLMAP model.
        problem: the refractive problem.
        state: a refractive state.
        mount: ``camera`` or ``world``.
        h: the new distance (mm).

    Returns:
        The refractive state at that distance.
    """
    return convert(model, problem, with_distance(model, convert(model, problem, state, -1), mount, h), +1)


def scaled(state: State, s: float, window: bool = True) -> State:
    """Every length of ``state`` times ``s``: the cost's near-flat direction.

    Args:
        state: the state.
        s: the factor.
        window: whether the window distances scale too (False: a declared plane stays where it was declared).

    Returns:
        The scaled state (points, translations, window distances unless ``window`` is False).
    """
    return replace(state, xyz=state.xyz * s, rig_from_world=tuple(Pose(p.R, p.t * s) for p in state.rig_from_world),
                   sensor_from_rig=tuple(Pose(p.R, p.t * s) for p in state.sensor_from_rig),
                   distances=state.distances * s if window else state.distances)


def to_scale(state: State, bar: ScaleBar | None, baseline: Baseline | None, window: bool) -> tuple[State, float]:
    """``state`` rescaled so that its scale bar or baseline has its declared length.

    Args:
        state: the state.
        bar: the scale bar, if any (it wins over ``baseline``).
        baseline: the baseline, if any.
        window: whether the window distances scale too (:func:`scaled`).

    Returns:
        The rescaled state and the factor (1 with neither).
    """
    s = (bar.length_mm / bar.length(state.xyz) if bar is not None else
         baseline.length_mm / baseline.length(state) if baseline is not None else 1.0)
    return scaled(state, s, window), s


def declared_start(model: adapter.ColmapModel, state: State, mount: str, plane: WindowPlane, path: ErrorPath) -> State:
    """The start with the window at the declared plane, checked.

    Args:
        model: the COLMAP model.
        state: the virtual cameras' state (:func:`initial_state`).
        mount: ``camera`` or ``world``.
        plane: the declared plane (WINDOW.yaml ``interface.plane``).
        path: the file named in errors.

    Returns:
        The state with the window at the plane.

    Raises:
        AriSfmError: the plane names another frame, its normal points against the view, or a camera is not on
            the camera side of its face (one line naming the field).
    """
    where = "interface.plane"
    if plane.frame != PLANE_FRAMES[mount]:
        raise AriSfmError(path, f"{where}.frame: refine-colmap has no target frames: with mount {mount} the plane is "
                                f"in the {'COLMAP world (mm)' if mount == 'world' else 'camera (housing) frame'}; "
                                f"omit frame or write {PLANE_FRAMES[mount]!r} (got {plane.frame!r})")
    n, d = declared_window(plane)
    if mount == "camera":
        if n[2] <= 0:
            raise AriSfmError(path, f"{where}.normal must point from the camera into the scene (z > 0 in the camera "
                                    f"frame; got {n.round(4).tolist()})")
        if d <= 0:
            raise AriSfmError(path, f"{where}.point_mm: the camera-side face must be in front of the camera "
                                    f"(normal . point_mm > 0; got {d:.6g} mm)")
        return replace(state, normals=np.tile(n, (len(state.normals), 1)), distances=np.full(len(state.distances), d))
    R, t = state.cam_from_world(model)
    centres = -np.einsum("nji,nj->ni", R, t)
    if float(np.mean(R[:, 2, :] @ n)) <= 0:
        raise AriSfmError(path, f"{where}.normal must point from the cameras into the scene (got "
                                f"{n.round(4).tolist()}, against the cameras' mean viewing direction)")
    behind = int(np.sum(centres @ n >= d))
    if behind:
        raise AriSfmError(path, f"{where}.point_mm: {behind} of {len(centres)} camera centres are not on the camera "
                                f"side of the declared face (normal . X = {d:.6g} mm in the COLMAP world, in mm)")
    return replace(state, normals=n[None, :], distances=np.array([d]))

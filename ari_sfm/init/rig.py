"""Analytical initialisation of a rig: per camera (expansion centre, Zhang, Eq. 5,
Eqs. 11-12), then the cameras joined through shared frames over a spanning tree.
"""
from __future__ import annotations

import logging
import os
from collections import deque
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import AriSfmError
from ..geometry import Pose, mean_pose, mean_poses, unit
from ..helper_thread import shared_map
from ..records import Dataset
from .expansion_center import ExpansionCenter, expansion_center, normal_from_expansion_center
from .interface_pose import real_cam_from_target
from .opencv_threads import one_cv2_thread
from .zhang import calibrate_views, held_intrinsics

log = logging.getLogger(__name__)

MIN_VIEWS = 3  # views of a planar target per camera (Zhang)
NO_NORMAL_MESSAGE = ("no stacking observations and no interface.plane: the ari model cannot observe the window "
                     "normal (the normal is not observable); use --model exact (Snell's law observes it through "
                     "refraction) or declare the window as interface.plane (DATASET_FORMAT.md 1.1)")
MIN_VIEWS_3D = 1  # views of a 3D body (>= 6 non-coplanar points): one is complete (DLT / PnP)


@dataclass(frozen=True)
class CameraInit:
    """One camera's analytic estimate (its own frame is the reference)."""

    name: str
    K: np.ndarray
    dist: np.ndarray
    expansion: ExpansionCenter | None
    normal_cam: np.ndarray | None
    cam_from_target: dict[str, Pose]  # real poses of calibration frames and stacking poses
    zhang_rms_px: float


@dataclass(frozen=True)
class RigInit:
    """The whole rig in the world frame (camera 0's frame)."""

    cameras: dict[str, CameraInit]
    cam_from_world: dict[str, Pose]
    normal_world: np.ndarray  # window 0's (the only one of a one-window rig)
    world_from_target: dict[str, Pose]  # calibration frames and stacking poses
    stacking_poses: tuple[str, ...] = field(default_factory=tuple)
    normal_observed: bool = True  # False: no stacking, normal_world is camera 0's optical axis (a start only)
    window_normals: tuple[np.ndarray, ...] = ()  # every window's normal (the dataset's window order)
    normals_observed: tuple[bool, ...] = ()  # per window: from its cameras' expansion centres (else an axis)

    def __post_init__(self) -> None:
        if not self.window_normals:  # built for one window
            object.__setattr__(self, "window_normals", (self.normal_world,))
            object.__setattr__(self, "normals_observed", (self.normal_observed,))


def _shift(thickness_mm: float, index: float) -> float:
    return thickness_mm * (1.0 - 1.0 / index)


def initialise_camera(dataset: Dataset, name: str, distortion: bool = False,
                      fix_intrinsics: bool = False, threads: int = 1, centred: bool = False) -> CameraInit:
    """Initialise one camera: its expansion centre, K, window normal and real target poses.

    Args:
        dataset: the dataset (its observations loaded).
        name: the camera's name.
        distortion: estimate the lens distortion (k1 k2 p1 p2 k3).
        fix_intrinsics: hold here too the hints the calibration will hold (:func:`~.zhang.held_intrinsics`),
            so the poses are those of the held K.
        threads: run the per-view OpenCV calls on up to this many threads (the same result).
        centred: hold the principal point at the image centre (the poses solved with it there).

    Returns:
        The camera's analytic estimate (the normal None without stacking).

    Raises:
        AriSfmError: with too few calibration views, or when the start or the expansion centre fails.
    """
    views = [o for o in dataset.select("calibration", name) if len(o.ids) >= 6]
    need = MIN_VIEWS if dataset.target.is_planar() else MIN_VIEWS_3D
    if len(views) < need:
        raise AriSfmError(dataset.rig_path,
                          f"camera {name} has {len(views)} calibration views with >= 6 corners (need >= {need})")
    stacking = dataset.select("stacking", name)
    firsts = [min((o for o in stacking if o.frame == pose), key=lambda o: o.added_mm or 0.0)
              for pose in sorted({o.frame for o in stacking})]  # each stacking pose's thinnest view: its PnP
    try:
        spec = dataset.cameras[name]
        zhang = calibrate_views(dataset.target, spec, views, distortion,
                                held_intrinsics(spec) if fix_intrinsics else None, threads, also=firsts,
                                centred=centred)
    except (ValueError, cv2.error) as exc:  # DLT refused, or OpenCV refused the start
        msg = str(exc).strip().splitlines()[-1] if isinstance(exc, cv2.error) else str(exc)
        raise AriSfmError(dataset.rig_path, f"camera {name}: {msg}") from None
    iface = dataset.interface_of(name)
    expansion, normal = None, None
    if stacking:
        try:
            expansion = expansion_center(stacking)
        except ValueError as exc:
            raise AriSfmError(dataset.observations_path or dataset.rig_path, f"camera {name}: {exc}") from None
        normal = normal_from_expansion_center(expansion.center_px, zhang.K)
    poses: dict[str, Pose] = {}
    for frame, gen in zhang.cam_from_target.items():
        poses[frame] = real_cam_from_target(gen, normal if normal is not None else np.zeros(3),
                                            _shift(iface.thickness_mm, iface.index))
    for first in firsts:
        shift = _shift(iface.thickness_mm + (first.added_mm or 0.0), iface.index)
        poses[first.frame] = real_cam_from_target(zhang.also[first.frame],
                                                  normal if normal is not None else np.zeros(3),
                                                  shift)
    return CameraInit(name, zhang.K, zhang.dist, expansion, normal, poses, zhang.rms_px)


def join_rig(names: Sequence[str], cam_from_target: dict[str, dict[str, Pose]],
             path: str | Path | None = None) -> tuple[dict[str, Pose], dict[str, Pose]]:
    """Join the cameras into a rig: every camera's cam_from_world and every frame's world_from_target.

    Relative poses are chordal means over shared frames along a breadth-first
    tree from camera 0; a frame's pose is the mean over the cameras that see it.

    Args:
        names: the camera names, camera 0 (the world) first.
        cam_from_target: camera -> frame -> its cam_from_target.
        path: the file named in the error.

    Returns:
        cam_from_world of every camera (world = camera 0) and world_from_target of every frame.

    Raises:
        AriSfmError: if a camera shares no frame with camera 0 or its neighbours.
    """
    cam_from_world = {names[0]: Pose.identity()}
    queue = deque([names[0]])
    while queue:
        parent = queue.popleft()
        for child in sorted(names, key=lambda c: -len(set(cam_from_target[c]) & set(cam_from_target[parent]))):
            shared = sorted(set(cam_from_target[child]) & set(cam_from_target[parent]))
            if child in cam_from_world or not shared:
                continue
            rel = mean_pose([cam_from_target[child][f].compose(cam_from_target[parent][f].inverse()) for f in shared])
            cam_from_world[child] = rel.compose(cam_from_world[parent])
            queue.append(child)
    missing = [n for n in names if n not in cam_from_world]
    if missing:
        raise AriSfmError(path, f"camera {missing[0]} shares no frame with camera {names[0]} or its neighbours: "
                                "the rig cannot be joined")
    frames = sorted(set().union(*(set(p) for p in cam_from_target.values())))
    world_from_cam = {n: cam_from_world[n].inverse() for n in names}
    means = mean_poses([[world_from_cam[n].compose(cam_from_target[n][f]) for n in names if f in cam_from_target[n]]
                        for f in frames])
    world_from_target = dict(zip(frames, means))
    return cam_from_world, world_from_target


def _initialise_cameras(dataset: Dataset, names: list[str], distortion: bool, workers: int | None,
                        fix_intrinsics: bool = False, centred: frozenset[str] = frozenset()) -> dict[str, CameraInit]:
    """:func:`initialise_camera` of every camera, on up to ``workers`` threads (default: one per
    camera, at most os.cpu_count()); threads left over split each camera's per-view OpenCV calls
    (a single camera: its views on two threads). OpenCV releases the GIL and runs on one thread in
    each worker, so each camera's result is the same as on its own; they are collected in camera
    order, and the first failing camera in that order raises, as when run one by one."""
    available = workers if workers is not None else (os.cpu_count() or 1)
    n_workers = min(len(names), available)
    threads = max(1, available // max(n_workers, 1))
    if n_workers <= 1:
        return {n: initialise_camera(dataset, n, distortion, fix_intrinsics, threads, n in centred) for n in names}
    if n_workers == 2:  # the caller and the kept helper thread, each taking the next camera (no thread started)
        inits = shared_map(lambda n: initialise_camera(dataset, n, distortion, fix_intrinsics, threads, n in centred),
                           names, threads=2, min_items=2)
        return dict(zip(names, inits))
    with ThreadPoolExecutor(max_workers=n_workers, thread_name_prefix="ari-init") as pool:
        futures = {n: pool.submit(initialise_camera, dataset, n, distortion, fix_intrinsics, threads, n in centred)
                   for n in names}
        return {n: futures[n].result() for n in names}


# One switch for all its cv2 calls, worker threads included: cv2.setNumThreads is process-wide,
# and the contexts opened inside the workers only nest in this one.
@one_cv2_thread()  # bit-identical across processes
def initialise_rig(dataset: Dataset, distortion: bool = False, workers: int | None = None,
                   fix_intrinsics: bool = False, centred: frozenset[str] = frozenset()) -> RigInit:
    """Initialise every camera concurrently, then chain relative poses from camera 0 over shared frames.

    OpenCV runs on one thread per worker meanwhile (see :func:`ari_sfm.init.opencv_threads.one_cv2_thread`);
    the result does not depend on ``workers``.

    Args:
        dataset: the dataset (its observations loaded).
        distortion: estimate the lens distortion (k1 k2 p1 p2 k3).
        workers: the most threads (default one per camera, up to os.cpu_count()).
        fix_intrinsics: hold the intrinsics hints the calibration will hold.
        centred: the cameras whose principal point is held at the image centre.

    Returns:
        The whole rig in the world frame (camera 0's frame).

    Raises:
        AriSfmError: if a camera cannot be initialised or the rig cannot be joined.
    """
    names = dataset.camera_names
    cams = _initialise_cameras(dataset, names, distortion, workers, fix_intrinsics, centred)
    # Camera graph: edges weighted by the number of shared frames (calibration and stacking).
    cam_from_world, world_from_target = join_rig(names, {n: c.cam_from_target for n, c in cams.items()},
                                                 dataset.rig_path)
    window_normals, observed = [], []
    for window in dataset.window_list():
        normals = [cam_from_world[n].R.T @ cams[n].normal_cam for n in window.cameras if cams[n].normal_cam is not None]
        # without stacking: the mean of the window's cameras' optical axes (oblique cameras usually look through a
        # wall from either side of its normal), a start for the exact model or a declared plane
        axis = unit(np.mean([cam_from_world[n].R.T @ np.array([0.0, 0.0, 1.0]) for n in window.cameras], axis=0))
        window_normals.append(unit(np.mean(normals, axis=0)) if normals else axis)
        observed.append(bool(normals))
    if not dataset.windows:  # one window: camera 0's axis (the world's z), as the start it has always been
        window_normals[0] = window_normals[0] if observed[0] else np.array([0.0, 0.0, 1.0])
    stacking = tuple(sorted({o.frame for o in dataset.select("stacking")}))
    return RigInit(cams, cam_from_world, window_normals[0], world_from_target, stacking, all(observed),
                   tuple(window_normals), tuple(observed))

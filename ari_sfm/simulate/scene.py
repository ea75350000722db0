"""Synthetic truth and what the cameras see of it, with exact Snell physics.

A :class:`Geometry` is the ground truth of a simulated experiment: cameras,
one window (or several, each with its cameras), target poses.  :func:`observe` projects every target corner with
:class:`~ari_sfm.models.exact.ExactModel` (Snell's law at both faces, never
the paraxial ARI equation); :func:`to_dataset`
and :func:`truth_dict` turn the result into the project's records and the
``calibration.json`` form of the truth (``model: truth``).

Frames: the world frame is camera 0's frame.  The window is the plane
``normal_world . X = distance_mm`` (its near surface) with the glass between
that plane and ``distance_mm + thickness_mm``; stacking adds glass on the
far side (the near surface stays, the target does not move).
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ari_sfm.geometry import Pose
from ari_sfm.io.dataset import target_to_json
from ari_sfm.models.exact import ExactModel
from ari_sfm.models.pinhole import PinholeModel
from ari_sfm.records import CameraSpec, Dataset, Entry, Interface, Observation, Target, Window, WindowPlane

logger = logging.getLogger(__name__)

TRUTH_FORMAT = "ari-sfm-calibration/1"
MARGIN_PX = 10.0  # a camera sees a frame only if every corner is this far inside its image


@dataclass(frozen=True)
class CameraTruth:
    """One simulated camera: intrinsics (no skew), image size (w, h) and pose."""

    name: str
    K: np.ndarray
    image_size: tuple[int, int]
    cam_from_world: Pose
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    focal_hint_px: float | None = None  # the nominal focal a user would write in rig.yaml

    @property
    def center_world(self) -> np.ndarray:
        """The camera centre in the world frame."""
        return self.cam_from_world.inverse().t

    @property
    def pinhole(self) -> PinholeModel:
        return PinholeModel(self.K, self.dist)

    def scaled(self, scale: float) -> CameraTruth:
        """Give the same camera with its image scaled (pixel centres stay OpenCV).

        A pixel u maps to ``scale (u + 0.5) - 0.5``, so fx, fy scale and
        cx, cy follow the pixel map; projections scale exactly.

        Args:
            scale: the image scale factor.

        Returns:
            The scaled camera (its focal hint scaled too).
        """
        K = self.K.copy()
        K[0, 0] *= scale
        K[1, 1] *= scale
        K[0, 2] = scale * (K[0, 2] + 0.5) - 0.5
        K[1, 2] = scale * (K[1, 2] + 0.5) - 0.5
        w, h = self.image_size
        hint = None if self.focal_hint_px is None else self.focal_hint_px * scale
        return replace(self, K=K, image_size=(int(round(w * scale)), int(round(h * scale))),
                       focal_hint_px=hint)


@dataclass(frozen=True)
class WindowTruth:
    """The plate: unit normal (world, camera -> scene), near surface at ``distance_mm``
    from the world origin (camera 0's centre) along the normal."""

    normal_world: np.ndarray
    distance_mm: float
    thickness_mm: float
    index: float
    medium_index: float = 1.0

    def normal_cam(self, camera: CameraTruth) -> np.ndarray:
        return camera.cam_from_world.R @ self.normal_world

    def camera_distance_mm(self, camera: CameraTruth) -> float:
        """Distance from the camera centre to the near surface along the normal."""
        return float(self.distance_mm - self.normal_world @ camera.center_world)

    def depth_beyond_far_face(self, X_world: np.ndarray, added_mm: float = 0.0) -> np.ndarray:
        """Give the signed distance of points beyond the far face of the (stacked) plate.

        Args:
            X_world: the points (N, 3), world frame, mm.
            added_mm: the glass stacked on the plate (mm).

        Returns:
            The signed distances (N,), mm; positive beyond the far face.
        """
        return np.asarray(X_world, float) @ self.normal_world - (
            self.distance_mm + self.thickness_mm + added_mm)

    def model(self, camera: CameraTruth, added_mm: float = 0.0) -> ExactModel:
        """Build the exact Snell model of a camera looking through the plate.

        Args:
            camera: the camera.
            added_mm: the glass stacked on the plate (mm).

        Returns:
            The exact model, in the camera's frame.
        """
        return ExactModel(camera.pinhole, self.normal_cam(camera), self.thickness_mm + added_mm,
                          self.index, medium_index=self.medium_index,
                          distance_mm=self.camera_distance_mm(camera))


@dataclass(frozen=True)
class WindowGroup:
    """One of several windows (a tank seen through more than one wall) and the cameras behind it."""

    name: str
    window: WindowTruth
    cameras: tuple[str, ...]


@dataclass(frozen=True)
class StackingPose:
    """A target pose imaged with several plate stacks (the target does not move)."""

    name: str
    world_from_target: Pose
    added_mm: tuple[float, ...]


@dataclass(frozen=True)
class ReconstructionFrame:
    """A target pose of the accuracy experiment; ``stage_mm`` along the stage line."""

    name: str
    world_from_target: Pose
    stage_mm: float


@dataclass(frozen=True)
class Geometry:
    """The full truth of a simulated experiment (before any observation)."""

    target: Target
    window: WindowTruth
    cameras: tuple[CameraTruth, ...]
    calibration: Mapping[str, Pose]  # frame -> world_from_target
    stacking: tuple[StackingPose, ...] = ()
    reconstruction: tuple[ReconstructionFrame, ...] = ()
    stage_direction_world: np.ndarray | None = None  # unit direction of the stage line
    margin_px: float = MARGIN_PX
    scale: float = 1.0  # image scale applied to the cameras (1 = as designed)
    declared_plane: WindowPlane | None = None  # the window as the dataset declares it (interface.plane)
    pixel_step_px: float | None = None  # the dataset's pixels are rounded to this step (after the noise)
    windows: tuple[WindowGroup, ...] = ()  # several windows (``window`` is then the first one's); (): one for all

    def window_of(self, camera: str) -> WindowTruth:
        """The window a camera looks through."""
        for g in self.windows:
            if camera in g.cameras:
                return g.window
        if self.windows:
            raise KeyError(camera)
        return self.window

    def window_groups(self) -> tuple[WindowGroup, ...]:
        """Every window with its cameras (one named ``window`` for all when not several)."""
        return self.windows or (WindowGroup("window", self.window, tuple(c.name for c in self.cameras)),)

    def camera(self, name: str) -> CameraTruth:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(name)

    def scaled(self, scale: float) -> Geometry:
        """All cameras scaled by ``scale``; the margin scales too, so visibility is unchanged."""
        if scale == 1.0:
            return self
        step = None if self.pixel_step_px is None else self.pixel_step_px * scale
        return replace(self, cameras=tuple(c.scaled(scale) for c in self.cameras),
                       margin_px=self.margin_px * scale, scale=self.scale * scale, pixel_step_px=step)

    def frames(self) -> dict[str, Pose]:
        """world_from_target of every frame: stacking poses, calibration, reconstruction."""
        out = {s.name: s.world_from_target for s in self.stacking}
        out.update(self.calibration)
        out.update({r.name: r.world_from_target for r in self.reconstruction})
        return out


# --------------------------------------------------------------------------- projection


def project(window: WindowTruth, camera: CameraTruth, X_world: np.ndarray,
            added_mm: float = 0.0) -> np.ndarray:
    """Project world points through the window with the exact Snell model.

    Args:
        window: the window the camera looks through.
        camera: the camera.
        X_world: the points (N, 3), world frame, mm.
        added_mm: the glass stacked on the plate (mm).

    Returns:
        The exact pixels (N, 2), NaN where no ray exists.
    """
    X_cam = camera.cam_from_world.apply(np.asarray(X_world, float))
    return window.model(camera, added_mm).project(X_cam)


def inside(uv: np.ndarray, image_size: tuple[int, int], margin_px: float) -> bool:
    """Tell whether every pixel is finite and at least ``margin_px`` inside the image.

    Args:
        uv: the pixels (N, 2).
        image_size: the image size (w, h).
        margin_px: the least distance from the border (px).

    Returns:
        True if every pixel is inside.
    """
    w, h = image_size
    uv = np.asarray(uv, float)
    if not np.all(np.isfinite(uv)):
        return False
    return bool(np.all(uv[:, 0] >= margin_px) and np.all(uv[:, 0] <= w - 1 - margin_px)
                and np.all(uv[:, 1] >= margin_px) and np.all(uv[:, 1] <= h - 1 - margin_px))


def expansion_center_px(camera: CameraTruth, normal_cam: np.ndarray) -> np.ndarray:
    """Give the true expansion centre K n_c / n_c[2] (may lie outside the image).

    Args:
        camera: the camera.
        normal_cam: the window normal in the camera frame (3,).

    Returns:
        The expansion centre (2,), px.
    """
    p = camera.K @ np.asarray(normal_cam, float)
    return p[:2] / p[2]


# --------------------------------------------------------------------------- observations


def observe(geometry: Geometry) -> tuple[Observation, ...]:
    """Make every record the cameras make, noise-free (exact Snell projection of every corner).

    A camera records a frame only if all corners lie ``margin_px`` inside its
    image.  Order: stacking (pose, added, camera), calibration, reconstruction.

    Args:
        geometry: the experiment's truth.

    Returns:
        The observations.
    """
    ids, pts = geometry.target.points_3d()
    out: list[Observation] = []

    def record(set_name: str, frame: str, pose: Pose, added: float = 0.0, **extra) -> None:
        X = pose.apply(pts)
        for cam in geometry.cameras:
            uv = project(geometry.window_of(cam.name), cam, X, added)
            if inside(uv, cam.image_size, geometry.margin_px):
                out.append(Observation(camera=cam.name, set=set_name, frame=frame, ids=ids.copy(),
                                       pixels=uv, **extra))

    for s in geometry.stacking:
        for added in s.added_mm:
            record("stacking", s.name, s.world_from_target, added, added_mm=float(added))
    for name, pose in geometry.calibration.items():
        record("calibration", name, pose)
    for r in geometry.reconstruction:
        record("reconstruction", r.name, r.world_from_target, stage_mm=float(r.stage_mm))
    return tuple(out)


# --------------------------------------------------------------------------- records


def image_path(set_name: str, camera: str, frame: str, added_mm: float | None = None) -> Path:
    """Give where the image of one record lives inside a dataset folder.

    Args:
        set_name: ``stacking``, ``calibration`` or ``reconstruction``.
        camera: the camera's name.
        frame: the frame's name.
        added_mm: the glass stacked on the plate (mm), for a stacking record.

    Returns:
        The image's path, relative to the dataset folder.
    """
    if set_name == "stacking":
        return Path("stack") / f"{camera}_{frame}_{int(round(added_mm or 0.0)):02d}.png"
    folder = "calib" if set_name == "calibration" else "recon"
    return Path(folder) / f"{camera}_{frame}.png"


def to_dataset(geometry: Geometry, observations: tuple[Observation, ...] | None, root: Path,
               seen: tuple[Observation, ...], with_images: bool = False) -> Dataset:
    """Build the :class:`Dataset` a user would hold.

    It holds the target, the window as declared (``geometry.declared_plane`` becomes
    ``interface.plane``), the cameras with the nominal focal hint, and one entry per (pose, stack) /
    frame listing the cameras that saw it.

    Args:
        geometry: the experiment's truth.
        observations: the records filling the dataset, their pixels rounded to ``geometry.pixel_step_px``
            when it is set; None: detect from images.
        root: the dataset folder.
        seen: the records that decide which cameras list an image (the noise-free ones).
        with_images: list the image paths in the entries.

    Returns:
        The dataset.
    """
    w = geometry.window
    interface = Interface(thickness_mm=w.thickness_mm, index=w.index, medium_index=w.medium_index,
                          plane=geometry.declared_plane)
    windows = tuple(Window(g.name, Interface(g.window.thickness_mm, g.window.index, g.window.medium_index), g.cameras)
                    for g in geometry.windows)
    if windows:
        interface = windows[0].interface
    step = geometry.pixel_step_px
    if observations is not None and step:
        observations = tuple(replace(o, pixels=np.round(o.pixels / step) * step) for o in observations)
    cameras = {c.name: CameraSpec(name=c.name, image_size=c.image_size, focal_px=c.focal_hint_px)
               for c in geometry.cameras}
    by_key: dict[tuple, list[str]] = {}
    for o in seen:
        by_key.setdefault((o.set, o.frame, o.added_mm), []).append(o.camera)

    def images(set_name: str, frame: str, added: float | None) -> dict[str, Path]:
        if not with_images:
            return {}
        return {cam: root / image_path(set_name, cam, frame, added) for cam in by_key.get((set_name, frame, added), [])}

    stacking = tuple(Entry(set="stacking", key=s.name, images=images("stacking", s.name, float(a)),
                           added_mm=float(a))
                     for s in geometry.stacking for a in s.added_mm
                     if ("stacking", s.name, float(a)) in by_key)
    calibration = tuple(Entry(set="calibration", key=name, images=images("calibration", name, None))
                        for name in geometry.calibration if ("calibration", name, None) in by_key)
    reconstruction = tuple(Entry(set="reconstruction", key=r.name,
                                 images=images("reconstruction", r.name, None), stage_mm=float(r.stage_mm))
                           for r in geometry.reconstruction if ("reconstruction", r.name, None) in by_key)
    return Dataset(root=root, rig_path=root / "rig.yaml", target=geometry.target, interface=interface,
                   cameras=cameras, stacking=stacking, calibration=calibration,
                   reconstruction=reconstruction, observations=observations,
                   observations_path=None if observations is None else root / "observations.json", windows=windows)


def truth_dict(geometry: Geometry, scenario: str, seed: int, sigma_px: float) -> dict:
    """Give the truth in the ``calibration.json`` form (model ``truth``) plus the scenario keys.

    Args:
        geometry: the experiment's truth.
        scenario: the scenario's name.
        seed: the random seed.
        sigma_px: the observation noise (px).

    Returns:
        The JSON-ready dict.
    """
    cameras = {}
    for cam in geometry.cameras:
        w = geometry.window_of(cam.name)
        n_c = w.normal_cam(cam)
        cameras[cam.name] = {
            "image_size": [int(cam.image_size[0]), int(cam.image_size[1])],
            "K": cam.K.tolist(),
            "dist": np.asarray(cam.dist, float).tolist(),
            "cam_from_world": cam.cam_from_world.to_json(),
            "normal_cam": n_c.tolist(),
            "distance_mm": w.camera_distance_mm(cam),
            "expansion_center_px": expansion_center_px(cam, n_c).tolist(),
        }
        if geometry.windows:
            cameras[cam.name]["window"] = next(g.name for g in geometry.windows if cam.name in g.cameras)
    ids, pts = geometry.target.points_3d()
    frames = {name: {"world_from_target": pose.to_json()} for name, pose in geometry.frames().items()}
    recon_points = {r.name: {"stage_mm": float(r.stage_mm), "ids": ids.tolist(),
                             "xyz": r.world_from_target.apply(pts).tolist()}
                    for r in geometry.reconstruction}
    def window_json(w: WindowTruth, first: CameraTruth) -> dict:
        return {"normal_world": np.asarray(w.normal_world, float).tolist(), "thickness_mm": float(w.thickness_mm),
                "index": float(w.index), "medium_index": float(w.medium_index),
                "distance_mm": w.camera_distance_mm(first)}

    if geometry.windows:
        windows = {"interfaces": {g.name: {"cameras": list(g.cameras),
                                           **window_json(g.window, geometry.camera(g.cameras[0]))}
                                  for g in geometry.windows}}
    else:
        windows = {"interface": window_json(geometry.window, geometry.cameras[0])}
    truth = {
        "format": TRUTH_FORMAT,
        "model": "truth",
        **windows,
        "cameras": cameras,
        "frames": frames,
        "scenario": scenario,
        "seed": int(seed),
        "sigma_px": float(sigma_px),
        "image_scale": float(geometry.scale),
        "target": target_to_json(geometry.target),  # the contract's form: calibration.json's target
        "stacking": {s.name: {"added_mm": [float(a) for a in s.added_mm]} for s in geometry.stacking},
        "reconstruction_points_world": recon_points,
    }
    if geometry.stage_direction_world is not None:
        truth["stage_direction_world"] = np.asarray(geometry.stage_direction_world, float).tolist()
    return truth


def check_geometry(geometry: Geometry, clearance_mm: float = 5.0) -> None:
    """Raise ValueError unless the experiment is physically valid.

    Every camera is on the near side of the window, and every target corner
    lies at least ``clearance_mm`` beyond the far face of the thickest stack
    used with it (the plate is between the cameras and the targets).

    Args:
        geometry: the experiment's truth.
        clearance_mm: the least clearance (mm) of cameras and targets from the plate.

    Raises:
        ValueError: if the experiment is not physically valid.
    """
    for g in geometry.window_groups():
        if abs(np.linalg.norm(g.window.normal_world) - 1.0) > 1e-9:
            raise ValueError(f"window {g.name}'s normal is not a unit vector")
    for cam in geometry.cameras:
        w = geometry.window_of(cam.name)
        h = w.camera_distance_mm(cam)
        if h <= clearance_mm:
            raise ValueError(f"camera {cam.name} is {h:.1f} mm from the window's near surface")
        if w.normal_cam(cam)[2] <= 0.0:
            raise ValueError(f"camera {cam.name} looks away from the window")
    _, pts = geometry.target.points_3d()
    for g in geometry.window_groups():
        w = g.window
        for s in geometry.stacking:
            depth = w.depth_beyond_far_face(s.world_from_target.apply(pts), max(s.added_mm, default=0.0))
            if depth.min() < clearance_mm:
                raise ValueError(f"stacking pose {s.name} is not beyond the far face of the stacked plate")
        for name, pose in list(geometry.calibration.items()) + [
                (r.name, r.world_from_target) for r in geometry.reconstruction]:
            if w.depth_beyond_far_face(pose.apply(pts)).min() < clearance_mm:
                raise ValueError(f"frame {name} is not beyond the far face of window {g.name}")

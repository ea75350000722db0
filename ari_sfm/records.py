"""Immutable records shared by every stage: target, window, cameras, observations, dataset.

Loading and validation live in :mod:`ari_sfm.io`; these classes only hold data.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TypeVar

import numpy as np

T = TypeVar("T")

SETS = ("stacking", "calibration", "reconstruction")


@dataclass(frozen=True)
class Target:
    """A calibration target in its own frame (mm).

    ``type`` is ``checkerboard`` (inner_corners [cols, rows], square_mm),
    ``charuco`` (squares [cols, rows], square_mm, marker_mm, dictionary),
    ``circles`` (a dot board, DATASET_FORMAT 1.1: circle_grid [cols, rows],
    spacing_mm, layout ``symmetric`` | ``asymmetric``, optional diameter_mm) or
    ``points3d`` (points {id: xyz}; optional diameter_mm, its dots' size, DATASET_FORMAT 1.3).
    """

    type: str
    square_mm: float = 0.0
    inner_corners: tuple[int, int] | None = None
    squares: tuple[int, int] | None = None
    marker_mm: float | None = None
    dictionary: str | None = None
    points: Mapping[int, tuple[float, float, float]] | None = None
    circle_grid: tuple[int, int] | None = None  # circles: [cols, rows] in OpenCV's patternSize order
    spacing_mm: float = 0.0  # circles: s of OpenCV's calcBoardCornerPositions
    layout: str = "symmetric"  # circles: symmetric | asymmetric
    diameter_mm: float | None = None  # circles: printed dot diameter; points3d: dot diameter; if declared

    def required(self, value: T | None, name: str) -> T:
        """Return a field that this target's type must have.

        :func:`ari_sfm.io.dataset.parse_target` checks the fields when the target is loaded.

        Args:
            value: the field's value.
            name: the field's name, for the error message.

        Returns:
            ``value`` when it is not None.

        Raises:
            ValueError: ``value`` is None.
        """
        if value is None:
            raise ValueError(f"a {self.type} target without {name}")
        return value

    @property
    def grid(self) -> tuple[int, int] | None:
        """(cols, rows) of a square lattice of points, id ``r * cols + c`` at (c, r) x :attr:`pitch_mm`
        (plus a constant offset); None for other targets (points3d, asymmetric dot grids)."""
        if self.type == "checkerboard":
            return self.inner_corners
        if self.type == "charuco" and self.squares is not None:
            return (self.squares[0] - 1, self.squares[1] - 1)
        if self.type == "circles" and self.layout == "symmetric":
            return self.circle_grid
        return None

    @property
    def pitch_mm(self) -> float:
        """Distance between neighbouring points of :attr:`grid` (square or dot spacing)."""
        return self.spacing_mm if self.type == "circles" else self.square_mm

    def points_3d(self) -> tuple[np.ndarray, np.ndarray]:
        """All (ids, xyz) of the target: ids (N,) int, xyz (N, 3) in mm, target frame (new arrays)."""
        ids, xyz = self.points_3d_readonly
        return ids.copy(), xyz.copy()

    @cached_property
    def points_3d_readonly(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`points_3d` computed once per target, as read-only arrays (for
        look-ups done per view, e.g. :func:`ari_sfm.init.zhang.object_points`).
        The record is frozen; its ``points`` mapping must not be changed either."""
        ids: np.ndarray
        xyz: np.ndarray
        if self.type == "points3d":
            points = self.required(self.points, "points")
            ids = np.array(sorted(points), dtype=int)
            xyz = np.array([points[i] for i in ids], dtype=float).reshape(-1, 3)
        elif self.type == "circles":  # OpenCV's calcBoardCornerPositions for circle grids
            cols, rows = self.required(self.circle_grid, "circle_grid")
            r, c = np.divmod(np.arange(cols * rows), cols)
            x = (2 * c + r % 2) if self.layout == "asymmetric" else c
            xyz = np.stack([x * self.spacing_mm, r * self.spacing_mm, np.zeros(cols * rows)], axis=1).astype(float)
            ids = np.arange(cols * rows)
        else:
            cols, rows = self.required(self.grid, "grid")
            r, c = np.divmod(np.arange(cols * rows), cols)
            xyz = np.stack([c * self.square_mm, r * self.square_mm, np.zeros(cols * rows)], axis=1)
            if self.type == "charuco":  # OpenCV puts ChArUco corner (c, r) at ((c+1) s, (r+1) s)
                xyz[:, :2] += self.square_mm
            ids, xyz = np.arange(cols * rows), xyz.astype(float)
        ids.flags.writeable = False
        xyz.flags.writeable = False
        return ids, xyz

    def num_ids(self) -> int:
        return len(self.points_3d_readonly[0])

    @cached_property
    def ids_are_rows(self) -> bool:
        """Whether the point ids are 0..n-1 (every board): an id is then its row in :attr:`points_3d_readonly`."""
        ids = self.points_3d_readonly[0]
        return bool(len(ids) and ids[0] == 0 and ids[-1] == len(ids) - 1)

    def is_planar(self) -> bool:
        return self.type != "points3d" or bool(np.ptp(self.points_3d_readonly[1][:, 2]) == 0.0)


@dataclass(frozen=True)
class WindowPlane:
    """The window as built (DATASET_FORMAT 1.1 ``interface.plane``), in the coordinates of
    the target frame ``frame``: the unit ``normal`` (cameras -> scene) and a point
    ``point_mm`` on the camera-side face. A sigma of 0 holds that part fixed; > 0 makes it
    a prior (``sigma_deg`` on the normal's direction, ``sigma_mm`` on the face's position
    along the normal)."""

    frame: str
    normal: np.ndarray  # (3,) unit
    point_mm: np.ndarray  # (3,)
    sigma_deg: float = 0.0
    sigma_mm: float = 0.0


@dataclass(frozen=True)
class Interface:
    """The flat window: plate thickness (mm), glass index, index of the medium behind it."""

    thickness_mm: float
    index: float
    medium_index: float = 1.0
    distance_mm: float | None = None  # optional hint: the window's first camera's centre to near surface
    plane: WindowPlane | None = None  # optional: the window's declared pose (DATASET_FORMAT 1.1)

    @property
    def shift_mm(self) -> float:
        """The paraxial shift d (1 - 1/n) of the scene toward the camera (air behind)."""
        return self.thickness_mm * (1.0 - 1.0 / self.index)


@dataclass(frozen=True)
class Window:
    """One window of a rig and the cameras that look through it (DATASET_FORMAT 1.3 ``interfaces``;
    a rig with one ``interface`` has one window, named ``window``, for every camera)."""

    name: str
    interface: Interface
    cameras: tuple[str, ...]


SINGLE_WINDOW = "window"  # the name of the one window of a rig declared with ``interface``


@dataclass(frozen=True)
class CameraSpec:
    """A camera of the rig as the dataset declares it (optional hints may be None)."""

    name: str
    image_size: tuple[int, int]  # (width, height) px
    focal_px: float | None = None
    K: np.ndarray | None = None
    dist: np.ndarray | None = None


@dataclass(frozen=True)
class Entry:
    """One stacking / calibration / reconstruction entry of rig.yaml.

    ``key`` is the ``pose`` of a stacking entry and the ``frame`` otherwise.
    ``manual_points`` (calibration entries of a ``points3d`` body, DATASET_FORMAT 1.3):
    per camera a few clicked body points, {point id: (u, v)} in OpenCV pixels, from
    which :mod:`ari_sfm.body` identifies the body's dots in that camera's image.
    """

    set: str
    key: str
    images: Mapping[str, Path] = field(default_factory=dict)
    added_mm: float | None = None
    stage_mm: float | None = None
    window: str | None = None  # stacking with several windows: the window the plates were added to
    manual_points: Mapping[str, Mapping[int, tuple[float, float]]] = field(default_factory=dict)  # (1.3) clicks


@dataclass(frozen=True)
class Observation:
    """Detected target corners in one image.

    ``frame`` is the ``pose`` for a stacking record, the ``frame`` otherwise.
    ``added_mm`` is the plate thickness added for stacking records (else None).
    """

    camera: str
    set: str
    frame: str
    ids: np.ndarray  # (N,) int
    pixels: np.ndarray  # (N, 2) float, OpenCV pixel convention
    added_mm: float | None = None
    stage_mm: float | None = None


@dataclass(frozen=True)
class Dataset:
    """A dataset folder as loaded from rig.yaml / rig.json (see DATASET_FORMAT.md).

    ``interface`` is the window of a one-window rig; with several windows (``windows``, DATASET_FORMAT
    1.3) it is the first window's, and every per-camera question goes through :meth:`interface_of`."""

    root: Path
    rig_path: Path
    target: Target
    interface: Interface
    cameras: Mapping[str, CameraSpec]
    stacking: tuple[Entry, ...] = ()
    calibration: tuple[Entry, ...] = ()
    reconstruction: tuple[Entry, ...] = ()
    observations: tuple[Observation, ...] | None = None  # None: detect from images
    observations_path: Path | None = None
    windows: tuple[Window, ...] = ()  # several windows (1.3), each camera behind one; (): `interface` for all

    def __post_init__(self) -> None:
        if self.windows:
            check_windows(self.windows, list(self.cameras))

    @property
    def camera_names(self) -> list[str]:
        return list(self.cameras)

    def window_list(self) -> tuple[Window, ...]:
        """Every window with its cameras (one window named ``window`` for a rig with one ``interface``)."""
        return self.windows or (Window(SINGLE_WINDOW, self.interface, tuple(self.cameras)),)

    def window_of(self, camera: str) -> Window:
        """The window a camera looks through."""
        for w in self.window_list():
            if camera in w.cameras:
                return w
        raise KeyError(camera)

    def interface_of(self, camera: str) -> Interface:
        """The plate a camera looks through (its window's)."""
        return self.window_of(camera).interface

    @property
    def medium_index(self) -> float:
        """The medium behind every window (one tank: the windows agree)."""
        return self.window_list()[0].interface.medium_index

    def entries(self) -> tuple[Entry, ...]:
        return self.stacking + self.calibration + self.reconstruction

    def with_observations(self, observations: tuple[Observation, ...], path: Path | None = None) -> Dataset:
        from dataclasses import replace

        return replace(self, observations=tuple(observations), observations_path=path)

    def select(self, set_name: str, camera: str | None = None) -> list[Observation]:
        """The observations of one set (and camera).

        Args:
            set_name: ``stacking``, ``calibration`` or ``reconstruction``.
            camera: only this camera's observations; None for every camera.

        Returns:
            The matching observations, in the dataset's order (empty without observations).
        """
        obs = self.observations or ()
        return [o for o in obs if o.set == set_name and (camera is None or o.camera == camera)]


def check_windows(windows: tuple[Window, ...], cameras: list[str]) -> None:
    """Check that a rig's windows and cameras fit together.

    Every camera is behind exactly one window, every window has a camera, the window names are distinct
    and the windows share one medium.

    Args:
        windows: the rig's windows.
        cameras: the names of the rig's cameras.

    Raises:
        ValueError: one of the conditions does not hold.
    """
    names = [w.name for w in windows]
    if len(set(names)) != len(names):
        raise ValueError(f"window names repeat: {names}")
    seen: dict[str, str] = {}
    for w in windows:
        if not w.cameras:
            raise ValueError(f"window {w.name} has no camera")
        for c in w.cameras:
            if c not in cameras:
                raise ValueError(f"window {w.name} names camera {c}, which the rig does not declare")
            if c in seen:
                raise ValueError(f"camera {c} is behind windows {seen[c]} and {w.name}: one window per camera")
            seen[c] = w.name
    missing = [c for c in cameras if c not in seen]
    if missing:
        raise ValueError(f"camera {missing[0]} is behind no window (every camera is listed under one window)")
    media = {w.interface.medium_index for w in windows}
    if len(media) > 1:
        raise ValueError(f"the windows' medium_index differ ({sorted(media)}): one tank has one medium")

"""The calibration result: the record calibration.json holds, and the models it implies.

Read, validated and written by :mod:`ari_sfm.io.calibration_file` (``load_calibration``,
``save_calibration``, ``parse_calibration``, ``calibration_to_json``), as the dataset is by
:mod:`ari_sfm.io.dataset`."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..geometry import Pose
from ..models.polynomial import PolynomialMap
from ..models.registry import ModelSpec, model_spec
from ..records import SINGLE_WINDOW, Interface, Target
from ..results import OptimizerReport, OutlierReport, PfWorld, ResidualStats, StageRecord, Uncertainty
from .origin import ImportedFrom, RefineColmapFrames
from .quality import Quality

if TYPE_CHECKING:
    from ..particles.selfcal_report import SelfCalReport  # (the particles package imports this module)


@dataclass(frozen=True)
class CameraCalibration:
    """One calibrated camera."""

    name: str
    image_size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    cam_from_world: Pose
    expansion_center_px: np.ndarray | None = None  # measured from stacking
    expansion_center_std_px: np.ndarray | None = None
    rmse_px: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)  # keys of cameras.<name> this version does not know
    pf: PolynomialMap | None = None  # model pf: its world-to-pixel polynomial (cameras.<name>.pf), else None

    @property
    def params(self) -> np.ndarray:
        """[fx fy cx cy k1 k2 p1 p2 k3]."""
        return np.concatenate([[self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]], np.resize(self.dist, 5)])


@dataclass(frozen=True)
class WindowCalibration:
    """One calibrated window: its plate, its normal in the world and the cameras behind it."""

    name: str
    interface: Interface  # distance_mm: the first of ``cameras``' centre to the near face (None: unobservable)
    normal_world: np.ndarray | None  # None for models without a window
    cameras: tuple[str, ...]
    fixed_distance_mm: float | None = None  # exact model in air: the distance (same reference) it is evaluated at

    def plane_mm(self, calibration: Calibration) -> float | None:
        """The near face as the world plane ``normal_world . X = plane_mm``.

        Args:
            calibration: The calibration this window belongs to (its first camera's centre is the reference).

        Returns:
            The plane's offset in mm: from ``distance_mm``, else from ``fixed_distance_mm`` (in air); None
            without either or without a normal.
        """
        d = self.interface.distance_mm if self.interface.distance_mm is not None else self.fixed_distance_mm
        if d is None or self.normal_world is None:
            return None
        return float(d + self.normal_world @ calibration.cameras[self.cameras[0]].cam_from_world.inverse().t)


@dataclass(frozen=True)
class Calibration:
    """A calibrated rig (world = the first camera's frame) behind one window, or several (``windows``).

    With one window, ``interface``, ``normal_world`` and ``fixed_distance_mm`` are it, for every camera;
    with several (DATASET_FORMAT 1.3), ``windows`` lists them and those three fields repeat the first
    window's: per-camera questions go through :meth:`window_of`."""

    model: str
    interface: Interface  # distance_mm: the first camera's centre to the near surface, None if unobservable
    normal_world: np.ndarray | None  # None for models without a window (ModelSpec.window: pinhole)
    cameras: dict[str, CameraCalibration]
    frames: dict[str, Pose]  # world_from_target of calibration frames
    stacking_poses: dict[str, Pose] = field(default_factory=dict)
    residuals: ResidualStats | None = None  # on the corners it was fitted on (None: not computed, e.g. truth)
    time_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)  # top-level keys this version does not know, kept as read
    target: Target | None = None  # the target it was calibrated with (for evaluate)
    fixed_distance_mm: float | None = None  # camera 0 centre to near surface at which an exact-Snell model
    # (ModelSpec.needs_distance) is evaluated in air, where no pixel depends on it and interface.distance_mm is
    # null: the value it was calibrated with, required then (no default), None otherwise
    uncertainty: Uncertainty | None = None  # standard deviations (bundle-adjusted models, when asked for)
    outliers: OutlierReport | None = None  # corners beyond k sigma after convergence (bundle-adjusted models)
    pf_world: PfWorld | None = None  # model pf: the calibration whose frames are its world (required then)
    quality: Quality | None = None  # the quality gate's verdict (ari, exact; ari_sfm.calibration.quality)
    optimizer: OptimizerReport | None = None  # how each stage's solve went (not a result: times)
    windows: tuple[WindowCalibration, ...] = ()  # several windows (1.3); (): one, the fields above, for all
    stages: tuple[StageRecord, ...] = ()  # the stages it went through, in order (bundle-adjusted models)
    self_calibration: SelfCalReport | None = None  # what `self-calibrate` did (its calibrations only)
    refine_colmap: RefineColmapFrames | None = None  # how refine-colmap's calibration sits in its COLMAP model
    imported_from: ImportedFrom | None = None  # the other tool's model it was imported from
    window_ignored: bool = False  # a pinhole baseline's: the window left out of the model on purpose

    def __post_init__(self) -> None:
        spec = self.spec  # an unknown model name fails here
        if self.windows:
            from ..records import Window, check_windows

            check_windows(tuple(Window(w.name, w.interface, w.cameras) for w in self.windows), list(self.cameras))
            first, mine = self.windows[0], self.interface
            same = (first.interface.thickness_mm, first.interface.index, first.interface.medium_index,
                    first.interface.distance_mm, first.fixed_distance_mm) == (
                mine.thickness_mm, mine.index, mine.medium_index, mine.distance_mm, self.fixed_distance_mm)
            if not same or (first.normal_world is None) != (self.normal_world is None) or (
                    first.normal_world is not None and self.normal_world is not None
                    and not np.array_equal(first.normal_world, self.normal_world)):
                raise ValueError("interface, normal_world and fixed_distance_mm must be the first window's")
        for w in self.window_list():
            if spec.needs_distance and w.interface.distance_mm is None and w.fixed_distance_mm is None:
                raise ValueError(f"model {self.model} with interface.distance_mm null needs fixed_distance_mm "
                                 "(the distance it was evaluated "
                                 f"at){'' if not self.windows else ' for window ' + w.name}")
        if spec.projection == "polynomial" and (self.pf_world is None
                                                or any(c.pf is None for c in self.cameras.values())):
            raise ValueError(f"model {self.model} needs pf_world and every camera's pf polynomial")

    @property
    def spec(self) -> ModelSpec:
        """The model's registry entry (:mod:`ari_sfm.models.registry`)."""
        return model_spec(self.model, None)

    def window_list(self) -> tuple[WindowCalibration, ...]:
        """Every window with its cameras (one window named ``window`` for every camera when not several)."""
        return self.windows or (WindowCalibration(SINGLE_WINDOW, self.interface, self.normal_world, tuple(self.cameras),
                                                  self.fixed_distance_mm),)

    def window_of(self, camera: str) -> WindowCalibration:
        """The window a camera looks through."""
        for w in self.window_list():
            if camera in w.cameras:
                return w
        raise KeyError(camera)

    def interface_of(self, camera: str) -> Interface:
        """The plate a camera looks through."""
        return self.window_of(camera).interface

    def normal_cam(self, camera: str) -> np.ndarray:
        """The normal of a camera's window in its frame (the zero vector for a model without one: pinhole)."""
        normal = self.window_of(camera).normal_world
        if normal is None:
            return np.zeros(3)
        return self.cameras[camera].cam_from_world.R @ normal

    def distance_mm(self, camera: str) -> float | None:
        """The distance from a camera's centre to its window's near surface (None where unobservable)."""
        w = self.window_of(camera)
        if w.interface.distance_mm is None or w.normal_world is None:
            return None
        return self._from_reference(w, camera, float(w.interface.distance_mm))

    def evaluation_distance_mm(self, camera: str) -> float | None:
        """The distance a Snell model of the camera is evaluated at.

        Args:
            camera: A camera of the calibration.

        Returns:
            :meth:`distance_mm`, or in air the one it was calibrated with (``fixed_distance_mm``, moved to this
            camera's centre); None when the calibration has neither.
        """
        d = self.distance_mm(camera)
        w = self.window_of(camera)
        if d is not None or w.fixed_distance_mm is None or w.normal_world is None:
            return d
        return self._from_reference(w, camera, float(w.fixed_distance_mm))

    def _from_reference(self, w: WindowCalibration, camera: str, distance: float) -> float:
        """A distance given from the window's first camera's centre, moved to ``camera``'s."""
        centre = self.cameras[camera].cam_from_world.inverse().t
        reference = self.cameras[w.cameras[0]].cam_from_world.inverse().t
        return float(distance - w.normal_world @ (centre - reference))

    def projection_model(self, camera: str, added_mm: float = 0.0, model: str | None = None):
        """The camera's projection model in its own frame, the class the registry names for the model.

        Args:
            camera: A camera of the calibration.
            added_mm: Glass added to the window's plate (a stacking view's), in mm.
            model: Another model to build from this calibration's parameters (e.g. "exact" of an ari
                calibration), or None: the calibration's own.

        Returns:
            model (AriModel | ExactModel | PinholeModel | PolynomialModel): ExactModel for exact, rt and truth;
                PinholeModel when the window is ignored; PolynomialModel (pf) projects world points only.

        Raises:
            ValueError: added glass for a model without a window or for pf; a Snell model without a distance.
        """
        from ..models import PinholeModel

        cam = self.cameras[camera]
        spec = self.spec if model is None else model_spec(model, None)
        if not spec.window or spec.projection == "polynomial":
            if added_mm:
                raise ValueError(f"model {spec.name} cannot project through added glass (added_mm={added_mm})")
            if spec.projection == "polynomial":
                from ..models.polynomial import PolynomialModel

                assert cam.pf is not None  # a pf calibration has every camera's polynomial (__post_init__)
                return PolynomialModel(cam.pf, cam.cam_from_world.inverse())
            return PinholeModel(cam.K, cam.dist)
        distance = self.distance_mm(camera)
        if distance is None and spec.needs_distance:
            distance = self.evaluation_distance_mm(camera)
            if distance is None:
                raise ValueError(f"model {spec.name} needs a window distance: this calibration has neither "
                                 "interface.distance_mm nor fixed_distance_mm")
        iface = self.interface_of(camera)
        return spec.projection_class()(PinholeModel(cam.K, cam.dist), self.normal_cam(camera),
                                       iface.thickness_mm + added_mm, iface.index, iface.medium_index, distance)

    def project_world(self, camera: str, X_world: np.ndarray, added_mm: float = 0.0) -> np.ndarray:
        """Pixels of world points seen by a camera through the window.

        Args:
            camera: A camera of the calibration.
            X_world: World points (N, 3), mm.
            added_mm: Glass added to the window's plate, in mm.

        Returns:
            Pixels (N, 2); NaN where a point has no image.
        """
        X_cam = self.cameras[camera].cam_from_world.apply(np.asarray(X_world, float).reshape(-1, 3))
        return self.projection_model(camera, added_mm).project(X_cam)

    def rays_world(self, camera: str, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The scene-side rays of pixels, in the world frame.

        Args:
            camera: A camera of the calibration.
            uv: Pixels (N, 2).

        Returns:
            (origins (N, 3), unit directions (N, 3)).
        """
        origins, directions = self.projection_model(camera).backproject(np.asarray(uv, float).reshape(-1, 2))
        world_from_cam = self.cameras[camera].cam_from_world.inverse()
        return world_from_cam.apply(origins), directions @ world_from_cam.R.T

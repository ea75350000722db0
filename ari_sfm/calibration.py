"""The calibration result: the record calibration.json holds, and the models it implies.

Read, validated and written by :mod:`ari_sfm.io.calibration_file` (``load_calibration``,
``save_calibration``, ``parse_calibration``, ``calibration_to_json``), as the dataset is by :mod:`ari_sfm.io.dataset`."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .geometry import Pose
from .models.registry import ModelSpec, model_spec
from .records import Interface, Target
from .results import OptimizerReport, OutlierReport, PfWorld, ResidualStats, Uncertainty
from .quality import Quality


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
    pf: Any = None  # model pf: its world-to-pixel PolynomialMap (ari_sfm.baselines.polynomial), cameras.<name>.pf

    @property
    def params(self) -> np.ndarray:
        """[fx fy cx cy k1 k2 p1 p2 k3]."""
        return np.concatenate([[self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]], np.resize(self.dist, 5)])


@dataclass(frozen=True)
class Calibration:
    """A calibrated rig behind one window (world = the first camera's frame)."""

    model: str
    interface: Interface  # distance_mm: camera 0 centre to near surface, None if unobservable
    normal_world: np.ndarray | None  # None for models without a window (ModelSpec.window: pinhole)
    cameras: dict[str, CameraCalibration]
    frames: dict[str, Pose]  # world_from_target of calibration frames
    stacking_poses: dict[str, Pose] = field(default_factory=dict)
    residuals: ResidualStats | None = None  # on the corners it was fitted on (None: not computed, e.g. truth)
    time_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)  # other top-level keys (stages, ...), kept as read
    target: Target | None = None  # the target it was calibrated with (for evaluate)
    fixed_distance_mm: float | None = None  # camera 0 centre to near surface at which an exact-Snell model
    # (ModelSpec.needs_distance) is evaluated in air, where no pixel depends on it and interface.distance_mm is
    # null: the value it was calibrated with, required then (no default), None otherwise
    uncertainty: Uncertainty | None = None  # standard deviations (bundle-adjusted models, when asked for)
    outliers: OutlierReport | None = None  # corners beyond k sigma after convergence (bundle-adjusted models)
    pf_world: PfWorld | None = None  # model pf: the calibration whose frames are its world (required then)
    quality: Quality | None = None  # the quality gate's verdict (ari, exact; ari_sfm.quality)
    optimizer: OptimizerReport | None = None  # how each stage's solve went (not a result: times)

    def __post_init__(self) -> None:
        spec = self.spec  # an unknown model name fails here
        if spec.needs_distance and self.interface.distance_mm is None and self.fixed_distance_mm is None:
            raise ValueError(f"model {self.model} with interface.distance_mm null needs fixed_distance_mm "
                             "(the distance it was evaluated at)")
        if spec.projection == "polynomial" and (self.pf_world is None or any(c.pf is None for c in self.cameras.values())):
            raise ValueError(f"model {self.model} needs pf_world and every camera's pf polynomial")

    @property
    def spec(self) -> ModelSpec:
        """The model's registry entry (:mod:`ari_sfm.models.registry`)."""
        return model_spec(self.model, None)

    def normal_cam(self, camera: str) -> np.ndarray:
        """The window normal in a camera's frame (the zero vector for a model without one: pinhole)."""
        if self.normal_world is None:
            return np.zeros(3)
        return self.cameras[camera].cam_from_world.R @ self.normal_world

    def distance_mm(self, camera: str) -> float | None:
        """The distance from a camera's centre to the window's near surface."""
        if self.interface.distance_mm is None or self.normal_world is None:
            return None
        centre = self.cameras[camera].cam_from_world.inverse().t
        return float(self.interface.distance_mm - self.normal_world @ centre)

    def projection_model(self, camera: str, added_mm: float = 0.0, model: str | None = None):
        """The camera's projection model in its own frame, the class the registry names for the model
        (or for ``model``): AriModel, ExactModel (exact, rt, truth), PinholeModel (the window ignored)
        or the pf polynomial (world points only)."""
        from .models import PinholeModel

        cam = self.cameras[camera]
        spec = self.spec if model is None else model_spec(model, None)
        if not spec.window or spec.projection == "polynomial":
            if added_mm:
                raise ValueError(f"model {spec.name} cannot project through added glass (added_mm={added_mm})")
            if spec.projection == "polynomial":
                from .models.polynomial import PolynomialMap, PolynomialModel

                return PolynomialModel(cam.pf, cam.cam_from_world.inverse())
            return PinholeModel(cam.K, cam.dist)
        distance = self.distance_mm(camera)
        if distance is None and spec.needs_distance:
            if self.fixed_distance_mm is None:
                raise ValueError(f"model {spec.name} needs a window distance: this calibration has neither "
                                 "interface.distance_mm nor fixed_distance_mm")
            distance = self.fixed_distance_mm - float(self.normal_world @ cam.cam_from_world.inverse().t)
        return spec.projection_class()(PinholeModel(cam.K, cam.dist), self.normal_cam(camera),
                                       self.interface.thickness_mm + added_mm, self.interface.index,
                                       self.interface.medium_index, distance)

    def project_world(self, camera: str, X_world: np.ndarray, added_mm: float = 0.0) -> np.ndarray:
        """Pixels (N, 2) of world points (N, 3) seen by a camera through the window."""
        X_cam = self.cameras[camera].cam_from_world.apply(np.asarray(X_world, float).reshape(-1, 3))
        return self.projection_model(camera, added_mm).project(X_cam)

    def rays_world(self, camera: str, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scene-side rays (origins (N, 3), unit directions (N, 3)) in the world frame of pixels (N, 2)."""
        origins, directions = self.projection_model(camera).backproject(np.asarray(uv, float).reshape(-1, 2))
        world_from_cam = self.cameras[camera].cam_from_world.inverse()
        return world_from_cam.apply(origins), directions @ world_from_cam.R.T

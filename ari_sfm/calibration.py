"""The calibration result: what calibration.json holds, and the models it implies."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import AriSfmError
from .io.calibration_checks import check_calibration_values
from .geometry import Pose
from .models.registry import ModelSpec, model_spec
from .records import Interface, Target
from .results import OptimizerReport, OutlierReport, PfWorld, ResidualStats, Uncertainty
from .quality import Quality

FORMAT = "ari-sfm-calibration/1"


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

    # ---- calibration.json -------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        cams = {}
        for name, c in self.cameras.items():
            entry: dict[str, Any] = {
                "image_size": [int(s) for s in c.image_size],
                "K": c.K.tolist(),
                "dist": np.resize(c.dist, 5).tolist(),
                "cam_from_world": c.cam_from_world.to_json(),
            }
            if self.normal_world is not None:
                entry["normal_cam"] = self.normal_cam(name).tolist()
            if c.expansion_center_px is not None:
                entry["expansion_center_px"] = np.asarray(c.expansion_center_px).tolist()
            if c.expansion_center_std_px is not None:
                entry["expansion_center_std_px"] = np.asarray(c.expansion_center_std_px).tolist()
            entry["distance_mm"] = self.distance_mm(name)
            if c.rmse_px is not None:
                entry["rmse_px"] = c.rmse_px
            if c.pf is not None:
                entry["pf"] = c.pf.to_json(self.pf_world.model)
            entry.update(c.extra)
            cams[name] = entry
        out = {
            "format": FORMAT,
            "model": self.model,
            "interface": {
                "normal_world": None if self.normal_world is None else np.asarray(self.normal_world).tolist(),
                "thickness_mm": self.interface.thickness_mm,
                "index": self.interface.index,
                "medium_index": self.interface.medium_index,
                "distance_mm": self.interface.distance_mm,
            },
            "cameras": cams,
            "frames": {f: {"world_from_target": p.to_json()} for f, p in self.frames.items()},
        }
        if self.stacking_poses:
            out["stacking_poses"] = {f: {"world_from_target": p.to_json()} for f, p in self.stacking_poses.items()}
        if self.target is not None:
            from .io.dataset import target_to_json

            out["target"] = target_to_json(self.target)
        out["residuals"] = {} if self.residuals is None else self.residuals.to_json()
        out["time_s"] = self.time_s
        if self.optimizer is not None:
            out["optimizer"] = self.optimizer.to_json()
        out.update(self.extra)
        for key, record in (("pf_world", self.pf_world), ("uncertainty", self.uncertainty),
                            ("outliers", self.outliers), ("quality", self.quality)):
            if record is not None:
                out[key] = record.to_json()
        if self.fixed_distance_mm is not None:
            out["fixed_distance_mm"] = self.fixed_distance_mm
        return out

    def save(self, path: str | Path) -> None:
        """Write calibration.json atomically."""
        from .io import write_json_atomic

        write_json_atomic(Path(path), self.to_json())

    @staticmethod
    def from_json(data: Any, path: str | Path = "calibration.json") -> "Calibration":
        """Parse and validate a calibration.json mapping."""
        try:
            return _parse(data, path)
        except AriSfmError:
            raise
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            what = f"missing key {exc}" if isinstance(exc, KeyError) else str(exc)
            raise AriSfmError(path, f"malformed calibration: {what}") from None


def _finite(a: Any, shape: tuple[int, ...], what: str, path: Any) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.shape != shape:
        raise AriSfmError(path, f"{what} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise AriSfmError(path, f"{what} contains non-finite values")
    return arr


def _pose(d: Any, what: str, path: Any) -> Pose:
    R = _finite(d["R"], (3, 3), f"{what}.R", path)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise AriSfmError(path, f"{what}.R is not a rotation matrix")
    return Pose(R, _finite(d["t"], (3,), f"{what}.t", path))


def _check_bounds(cams: dict[str, CameraCalibration], thickness: float, path: Any) -> None:
    """The sane physical bounds of the rig file (io.dataset) hold for a calibration too."""
    from .io.dataset import MAX_FOCAL_PX, MAX_IMAGE_SIDE_PX, MAX_LENGTH_MM
    from .io.structured import check_at_most

    check_at_most(thickness, MAX_LENGTH_MM, path, "interface.thickness_mm", " mm")
    for name, c in cams.items():
        if min(c.image_size) < 1:
            raise AriSfmError(path, f"cameras.{name}.image_size must be two integers >= 1 (got {list(c.image_size)})")
        check_at_most(max(c.image_size), MAX_IMAGE_SIDE_PX, path, f"cameras.{name}.image_size", " px")
        fx, fy = float(c.K[0, 0]), float(c.K[1, 1])
        if fx <= 0 or fy <= 0:
            raise AriSfmError(path, f"cameras.{name}.K must have positive focal lengths (got fx={fx:g}, fy={fy:g})")
        check_at_most(max(fx, fy), MAX_FOCAL_PX, path, f"cameras.{name}.K focal length", " px")


def _parse(data: Any, path: Any) -> Calibration:
    if not isinstance(data, dict):
        raise AriSfmError(path, "calibration must be a JSON object")
    if data.get("format") != FORMAT:
        raise AriSfmError(path, f"unknown format {data.get('format')!r} (expected {FORMAT!r})")
    spec = model_spec(data["model"], path)
    model = spec.name
    check_calibration_values(data, path, window=spec.window)  # rig.yaml's bounds (ari_sfm.io.calibration_checks)
    iface = data["interface"]
    thickness, index = float(iface["thickness_mm"]), float(iface["index"])
    medium = float(iface.get("medium_index", 1.0))
    if not (math.isfinite(thickness) and thickness >= 0):
        raise AriSfmError(path, f"interface.thickness_mm must be >= 0 (got {thickness})")
    if not (math.isfinite(index) and index >= 1) or not (math.isfinite(medium) and medium >= 1):
        raise AriSfmError(path, "interface.index and medium_index must be >= 1")
    distance = iface.get("distance_mm")
    if iface["normal_world"] is None and not spec.window:
        normal = None
    else:
        normal = _finite(iface["normal_world"], (3,), "interface.normal_world", path)
    if normal is not None and abs(np.linalg.norm(normal) - 1) > 1e-6:
        raise AriSfmError(path, "interface.normal_world must be a unit vector")
    cams = {}
    if not isinstance(data["cameras"], dict) or not data["cameras"]:
        raise AriSfmError(path, "cameras must be a non-empty object")
    known = {"image_size", "K", "dist", "cam_from_world", "normal_cam", "expansion_center_px",
             "expansion_center_std_px", "rmse_px", "distance_mm", *spec.camera_keys}
    pf_world = _record(PfWorld, data, "pf_world", path) if spec.projection == "polynomial" else None
    if spec.projection == "polynomial" and pf_world is None:
        raise AriSfmError(path, f"pf_world is missing (model {model} names the calibration its world comes from)")
    for name, c in data["cameras"].items():
        ec = c.get("expansion_center_px")
        es = c.get("expansion_center_std_px")
        for key in spec.camera_keys:
            if key not in c:
                raise AriSfmError(path, f"cameras.{name}.{key} is missing (model {model} stores its parameters there)")
        poly = None
        if spec.projection == "polynomial":  # the polynomial is the model: validate it here, not at the first projection
            from .models.polynomial import PolynomialMap

            try:
                poly = PolynomialMap.from_json(c["pf"])
            except (KeyError, TypeError, ValueError) as exc:
                raise AriSfmError(path, f"cameras.{name}.pf: {exc}") from None
            if c["pf"].get("world", pf_world.model) != pf_world.model:
                raise AriSfmError(path, f"cameras.{name}.pf.world is {c['pf']['world']!r}, pf_world.model "
                                        f"{pf_world.model!r}: one world for all cameras")
        cams[name] = CameraCalibration(
            name,
            tuple(int(s) for s in c["image_size"]),
            _finite(c["K"], (3, 3), f"cameras.{name}.K", path),
            np.resize(_finite(c.get("dist", [0] * 5), (len(c.get("dist", [0] * 5)),), f"cameras.{name}.dist", path), 5),
            _pose(c["cam_from_world"], f"cameras.{name}.cam_from_world", path),
            None if ec is None else np.asarray(ec, float),
            None if es is None else np.asarray(es, float),
            c.get("rmse_px"),
            {k: v for k, v in c.items() if k not in known},
            poly,
        )
    _check_bounds(cams, thickness, path)
    frames = {f: _pose(v["world_from_target"], f"frames.{f}", path) for f, v in data.get("frames", {}).items()}
    stacking = {f: _pose(v["world_from_target"], f"stacking_poses.{f}", path) for f, v in data.get("stacking_poses", {}).items()}
    reserved = {"format", "model", "interface", "cameras", "frames", "stacking_poses", "residuals", "time_s", "target",
                "fixed_distance_mm", "uncertainty", "outliers", "pf_world", "quality", "optimizer"}
    fixed = data.get("fixed_distance_mm")
    if fixed is not None:
        fixed = float(fixed)
        if not math.isfinite(fixed):
            raise AriSfmError(path, f"fixed_distance_mm must be a finite number (got {data['fixed_distance_mm']!r})")
    if spec.needs_distance and distance is None and fixed is None:
        raise AriSfmError(path, f"fixed_distance_mm is missing: model {model} with interface.distance_mm null is "
                                "evaluated at the distance it was calibrated with (in air no pixel depends on it)")
    if "target" in data:
        from .io.dataset import parse_target

        target = parse_target(data["target"], Path(path))
    else:
        target = None
    return Calibration(
        model, Interface(thickness, index, medium, None if distance is None else float(distance)), normal, cams,
        frames, stacking, _record(ResidualStats, data, "residuals", path), float(data.get("time_s", 0.0)),
        {k: v for k, v in data.items() if k not in reserved}, target, fixed,
        _record(Uncertainty, data, "uncertainty", path), _record(OutlierReport, data, "outliers", path), pf_world,
        _record(Quality, data, "quality", path), _record(OptimizerReport, data, "optimizer", path),
    )


def _record(cls, data: dict, key: str, path: Any):
    """``cls.from_json(data[key])`` (None when the key is absent, null or {}), errors naming the key."""
    value = data.get(key)
    if not value:
        return None
    if not isinstance(value, dict):
        raise AriSfmError(path, f"{key} must be an object")
    try:
        return cls.from_json(value)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        what = f"missing key {exc}" if isinstance(exc, KeyError) else str(exc)
        raise AriSfmError(path, f"{key}: {what}") from None


def load_calibration(path: str | Path) -> Calibration:
    """Read and validate calibration.json (or a simulator's truth.json)."""
    from .io import read_structured

    return Calibration.from_json(read_structured(Path(path)), path)


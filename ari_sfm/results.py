"""What a calibration reports besides its parameters, as records: residual statistics, parameter
uncertainty, outliers, the world a pf fit was made in, and the optimizer's report.

Each record is frozen, writes exactly the calibration.json (and compare.json)
fragment the format defines (``to_json``) and reads it back (``from_json``,
raising ``ValueError``/``KeyError``/``TypeError`` on a malformed fragment: the
caller names the file). The layout is DATASET_FORMAT.md's; nothing here changes it.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .calibration.outliers import Outlier
from .models.pinhole import PARAM_NAMES


def _float_or_none(value: Any) -> float | None:
    return None if value is None else float(value)


@dataclass(frozen=True)
class ResidualStats:
    """Pixel residuals summarised: ``rmse_px = sqrt(mean(du^2 + dv^2))``, the mean and largest distance,
    how many corners; ``per_camera`` the same per camera where a breakdown was asked for (evaluate)."""

    rmse_px: float
    mae_px: float
    max_px: float
    count: int
    per_camera: Mapping[str, ResidualStats] | None = None

    @classmethod
    def of(cls, residuals: Iterable[np.ndarray]) -> ResidualStats:
        """The statistics of residual arrays (each (M, 2)); NaN and count 0 for none."""
        arrays = [np.asarray(r, float).reshape(-1, 2) for r in residuals]
        d = np.linalg.norm(np.concatenate(arrays), axis=1) if arrays else np.zeros(0)
        if len(d) == 0:
            return cls(float("nan"), float("nan"), float("nan"), 0)
        return cls(float(np.sqrt(np.mean(d**2))), float(np.mean(d)), float(np.max(d)), int(len(d)))

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"rmse_px": self.rmse_px, "mae_px": self.mae_px, "max_px": self.max_px,
                               "count": self.count}
        if self.per_camera is not None:
            out["per_camera"] = {c: s.to_json() for c, s in self.per_camera.items()}
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> ResidualStats:
        per = d.get("per_camera")
        return cls(float(d["rmse_px"]), float(d["mae_px"]), float(d["max_px"]), int(d["count"]),
                   None if per is None else {c: cls.from_json(s) for c, s in per.items()})


@dataclass(frozen=True)
class CameraUncertainty:
    """Standard deviations of one camera's parameters (None: the data do not determine it)."""

    intrinsics: Mapping[str, float | None]  # fx fy cx cy (px), with distortion also k1 k2 p1 p2 k3
    relative_pose: bool = False  # the pose relative to camera 0 was estimated (every camera but the first)
    rotation_deg: float | None = None  # RMS rotation error of that pose
    translation_mm: float | None = None  # RMS translation error of that pose

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = dict(self.intrinsics)
        if self.relative_pose:
            out["rotation_deg"] = self.rotation_deg
            out["translation_mm"] = self.translation_mm
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> CameraUncertainty:
        unknown = set(d) - set(PARAM_NAMES) - {"rotation_deg", "translation_mm"}
        if unknown:
            raise ValueError(f"unknown uncertainty key(s) {', '.join(sorted(unknown))}")
        intr = {k: _float_or_none(d[k]) for k in PARAM_NAMES if k in d}
        relative = "rotation_deg" in d or "translation_mm" in d
        return cls(intr, relative, _float_or_none(d.get("rotation_deg")), _float_or_none(d.get("translation_mm")))


@dataclass(frozen=True)
class WindowUncertainty:
    """One window's standard deviations (a rig with several windows)."""

    normal_deg: float | None  # RMS angle error of its normal
    distance_mm: float | None = None  # of its near face's position along its normal (when estimated)

    def to_json(self) -> dict[str, Any]:
        return {"normal_deg": self.normal_deg, "distance_mm": self.distance_mm}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> WindowUncertainty:
        return cls(_float_or_none(d.get("normal_deg")), _float_or_none(d.get("distance_mm")))


@dataclass(frozen=True)
class Uncertainty:
    """Standard deviations from the bundle adjustment's marginals, scaled by the residual sigma."""

    sigma_px: float  # residual sigma per pixel coordinate that scales them
    cameras: Mapping[str, CameraUncertainty]
    normal_deg: float | None  # RMS angle error of the window normal (the first window's with several)
    estimates_distance: bool = False  # the window distance was estimated (medium behind the window)
    distance_mm: float | None = None  # its standard deviation
    windows: Mapping[str, WindowUncertainty] = field(default_factory=dict)  # several windows: each one's

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"sigma_px": self.sigma_px, "cameras": {n: c.to_json() for n, c in self.cameras.items()},
                               "normal_deg": self.normal_deg}
        if self.estimates_distance:
            out["distance_mm"] = self.distance_mm
        if self.windows:
            out["windows"] = {n: w.to_json() for n, w in self.windows.items()}
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Uncertainty:
        windows = {str(n): WindowUncertainty.from_json(w) for n, w in (d.get("windows") or {}).items()}
        return cls(float(d["sigma_px"]), {n: CameraUncertainty.from_json(c) for n, c in d["cameras"].items()},
                   _float_or_none(d["normal_deg"]), "distance_mm" in d, _float_or_none(d.get("distance_mm")), windows)


@dataclass(frozen=True)
class OutlierReport:
    """Corners beyond ``threshold_sigma`` robust sigmas after convergence, and whether they were dropped."""

    sigma_px: float  # robust sigma per coordinate (1.4826 MAD)
    threshold_sigma: float
    excluded: bool  # dropped and the last stage re-run
    corners: tuple[Outlier, ...] = field(default_factory=tuple)

    def to_json(self) -> dict[str, Any]:
        return {"sigma_px": self.sigma_px, "threshold_sigma": self.threshold_sigma, "excluded": self.excluded,
                "corners": [o.to_json() for o in self.corners]}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> OutlierReport:
        if not isinstance(d["excluded"], bool):
            raise ValueError("outliers.excluded must be true or false")
        return cls(float(d["sigma_px"]), float(d["threshold_sigma"]), d["excluded"],
                   tuple(Outlier.from_json(o) for o in d["corners"]))


@dataclass(frozen=True)
class PfWorld:
    """The calibration whose board poses gave a pf fit its world coordinates."""

    model: str  # its model (ari or exact)
    time_s: float  # its calibration time (not pf's)
    note: str = ("K, cam_from_world and normal_world are the world calibration's; "
                 "pixels come from each camera's pf polynomial")

    def to_json(self) -> dict[str, Any]:
        return {"model": self.model, "time_s": self.time_s, "note": self.note}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> PfWorld:
        if not isinstance(d["model"], str):
            raise ValueError("pf_world.model must be a model name")
        return cls(d["model"], float(d["time_s"]), str(d.get("note", cls.note)))


@dataclass(frozen=True)
class OptimizerRun:
    """How one optimizer run of a calibration went: calibration.json ``optimizer.<stage>``. Not a result
    (times differ between runs); the bundle adjustment fills iterations, sigma_px (and error_evaluations,
    numpy backend), the scipy baselines nfev and status."""

    time_s: float
    backend: str
    iterations: int | None = None  # accepted Levenberg-Marquardt steps
    sigma_px: float | None = None  # the pixel sigma its view factors were whitened by
    error_evaluations: int | None = None  # cost evaluations (numpy backend)
    nfev: int | None = None  # scipy.optimize.least_squares' function evaluations
    status: int | None = None  # and its status
    extra: Mapping[str, Any] = field(default_factory=dict)  # other keys, kept as read

    _ORDER = ("iterations", "nfev", "status", "time_s", "backend", "sigma_px", "error_evaluations")

    def to_json(self) -> dict[str, Any]:
        out = {k: getattr(self, k) for k in self._ORDER if getattr(self, k) is not None}
        out.update(self.extra)
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> OptimizerRun:
        def opt(key: str, kind: type):
            return None if d.get(key) is None else kind(d[key])

        return cls(float(d["time_s"]), str(d["backend"]), opt("iterations", int), opt("sigma_px", float),
                   opt("error_evaluations", int), opt("nfev", int), opt("status", int),
                   {k: v for k, v in d.items() if k not in cls._ORDER})


@dataclass(frozen=True)
class OptimizerReport:
    """Every optimizer run of a calibration, by stage (``ari``, ``exact``, ...; a baseline's own name), in order."""

    runs: Mapping[str, OptimizerRun]

    def to_json(self) -> dict[str, Any]:
        return {stage: run.to_json() for stage, run in self.runs.items()}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> OptimizerReport:
        if not isinstance(d, Mapping):
            raise TypeError(f"optimizer must be a mapping of stages (got {type(d).__name__})")
        return cls({str(stage): OptimizerRun.from_json(run) for stage, run in d.items()})


@dataclass(frozen=True)
class StageCamera:
    """One camera's intrinsics after a stage: calibration.json ``stages[].cameras.<name>`` (a file written by
    another tool may give fx alone)."""

    fx: float
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    dist: tuple[float, ...] = ()

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"fx": self.fx}
        out.update({k: getattr(self, k) for k in ("fy", "cx", "cy") if getattr(self, k) is not None})
        if self.dist:
            out["dist"] = list(self.dist)
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> StageCamera:
        return cls(float(d["fx"]), _float_or_none(d.get("fy")), _float_or_none(d.get("cx")),
                   _float_or_none(d.get("cy")), tuple(float(v) for v in d.get("dist") or ()))


@dataclass(frozen=True)
class StageWindow:
    """One window after a stage (several windows): its normal and near-face offset from the world origin
    (None where the data do not observe it)."""

    normal_world: tuple[float, ...] | None  # 3 components (read leniently)
    plane_mm: float | None

    def to_json(self) -> dict[str, Any]:
        return {"normal_world": None if self.normal_world is None else list(self.normal_world),
                "plane_mm": self.plane_mm}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> StageWindow:
        n = d.get("normal_world")
        return cls(None if n is None else tuple(float(v) for v in n), _float_or_none(d.get("plane_mm")))


@dataclass(frozen=True)
class StageRecord:
    """One stage a calibration went through (e.g. the paraxial ``ari`` start, then ``exact``): calibration.json
    ``stages[]``, its residuals on the corners it was fitted on and its parameters. Read leniently, as the
    report shows stages written by other tools: ``name`` for ``stage``, a ``residuals`` object for the
    top-level figures; figures absent are None, other keys kept in ``extra``."""

    stage: str
    model: str | None = None
    distortion: bool | None = None
    rmse_px: float | None = None
    max_px: float | None = None
    count: int | None = None
    normal_world: tuple[float, ...] | None = None  # 3 components (read leniently)
    distance_mm: float | None = None
    cameras: Mapping[str, StageCamera] = field(default_factory=dict)
    windows: tuple[StageWindow, ...] = ()  # several windows only
    extra: Mapping[str, Any] = field(default_factory=dict)  # other keys, kept as read

    _KEYS = ("stage", "name", "model", "distortion", "rmse_px", "max_px", "count", "residuals", "normal_world",
             "distance_mm", "cameras", "windows")

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "stage": self.stage, "model": self.model, "distortion": self.distortion, "rmse_px": self.rmse_px,
            "max_px": self.max_px, "count": self.count,
            "normal_world": None if self.normal_world is None else list(self.normal_world),
            "distance_mm": self.distance_mm, "cameras": {n: c.to_json() for n, c in self.cameras.items()}}
        if self.windows:
            out["windows"] = [w.to_json() for w in self.windows]
        out.update(self.extra)
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any], position: int = 0) -> StageRecord:
        """Read one ``stages`` entry leniently.

        Args:
            d: the entry, as read from calibration.json.
            position: its place in the ``stages`` list (0-based); ``position + 1`` names an entry
                without ``stage`` or ``name``.

        Returns:
            The stage's record.

        Raises:
            TypeError: ``d`` is not a mapping.
        """
        if not isinstance(d, Mapping):
            raise TypeError(f"stages[{position}] must be an object")
        res = d["residuals"] if isinstance(d.get("residuals"), Mapping) else d

        def num(m: Mapping[str, Any], key: str) -> float | None:
            v = m.get(key)
            return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None

        count = res.get("count")
        normal = d.get("normal_world")
        cameras = d["cameras"] if isinstance(d.get("cameras"), Mapping) else {}
        windows = d["windows"] if isinstance(d.get("windows"), list) else []
        return cls(str(d.get("stage", d.get("name", position + 1))),
                   None if d.get("model") is None else str(d["model"]),
                   None if d.get("distortion") is None else bool(d["distortion"]),
                   num(res, "rmse_px"), num(res, "max_px"),
                   int(count) if isinstance(count, int) and not isinstance(count, bool) else None,
                   None if normal is None else tuple(float(v) for v in normal), num(d, "distance_mm"),
                   {str(n): StageCamera.from_json(c) for n, c in cameras.items()
                    if isinstance(c, Mapping) and isinstance(c.get("fx"), (int, float))},
                   tuple(StageWindow.from_json(w) for w in windows if isinstance(w, Mapping)),
                   {k: v for k, v in d.items() if k not in cls._KEYS})


def stages_from_json(value: Any) -> tuple[StageRecord, ...]:
    """calibration.json's ``stages`` list as records (TypeError when it is not a list)."""
    if not isinstance(value, list):
        raise TypeError("stages must be a list")
    return tuple(StageRecord.from_json(d, k) for k, d in enumerate(value))

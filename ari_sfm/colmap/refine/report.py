"""refine-colmap's report as frozen records: :class:`RefineReport` (``to_json()`` is refine.json, the
contract of docs/DATASET_FORMAT.md) and its parts. Built at the end of
:func:`~ari_sfm.colmap.refine.refine.refine_colmap`; read by the CLI, ``ari-sfm sfm`` and the benchmarks."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Plate:
    """The plate refined through (WINDOW.yaml's interface)."""

    thickness_mm: float
    index: float
    medium_index: float

    def to_json(self) -> dict[str, float]:
        return {"thickness_mm": self.thickness_mm, "index": self.index, "medium_index": self.medium_index}


@dataclass(frozen=True)
class RefineCounts:
    """The size of the refined problem."""

    cameras: int
    frames: int
    images: int
    points3D: int  # noqa: N815 (refine.json's key)
    observations: int
    reduced_variables: int  # the points-eliminated system's columns

    def to_json(self) -> dict[str, int]:
        return {"cameras": self.cameras, "frames": self.frames, "images": self.images, "points3D": self.points3D,
                "observations": self.observations, "reduced_variables": self.reduced_variables}


@dataclass(frozen=True)
class Reprojection:
    """Reprojection errors (px) of one model of the cameras: refine.json's ``before``, ``after`` and
    ``pinhole_approximation`` (the last names its model under ``camera_model``)."""

    model: str
    rms_px: float
    per_image_rms_px: Mapping[int, float]  # by COLMAP image_id
    mean_px: float | None = None  # ``after`` only
    model_key: str = "model"  # the JSON key of ``model``

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {self.model_key: self.model, "rms_px": self.rms_px}
        if self.mean_px is not None:
            out["mean_px"] = self.mean_px
        out["per_image_rms_px"] = dict(self.per_image_rms_px)
        return out


@dataclass(frozen=True)
class RefineUncertainty:
    """1-sigma standard deviations at the solution (:func:`ari_sfm.colmap.refine.uncertainty.uncertainty`):
    by housing name (``camera<id>``, or ``world`` for mount world)."""

    sigma0: float  # the a-posteriori pixel sigma
    normal_deg: Mapping[str, float] = field(default_factory=dict)
    distance_mm: Mapping[str, float] = field(default_factory=dict)
    fx_px: Mapping[str, float] = field(default_factory=dict)
    scale_rel: float | None = None  # None with one frame
    weak: tuple[str, ...] = ()  # what the data barely determine, e.g. "distance_mm.camera1", "scale_rel"

    def to_json(self) -> dict[str, Any]:
        """A sigma the data do not determine (inf or NaN: a singular information matrix) is written null."""
        def finite(v: float | None) -> float | None:
            return v if v is not None and math.isfinite(v) else None

        return {"sigma0": finite(self.sigma0), "normal_deg": {k: finite(v) for k, v in self.normal_deg.items()},
                "distance_mm": {k: finite(v) for k, v in self.distance_mm.items()},
                "fx_px": {k: finite(v) for k, v in self.fx_px.items()}, "scale_rel": finite(self.scale_rel),
                "weak": list(self.weak)}


@dataclass(frozen=True)
class WindowEstimate:
    """The refined window: per housing (mount camera: ``normal_cam``, ``distance_mm``) or of the world
    (mount world: ``normal_world``, ``plane_mm``)."""

    normal_cam: Mapping[str, np.ndarray] | None = None
    distance_mm: Mapping[str, float] | None = None
    normal_world: np.ndarray | None = None
    plane_mm: float | None = None

    def distance_of(self, name: str) -> float | None:
        """Housing ``name``'s distance (mount camera), or the world plane's offset (mount world)."""
        return self.distance_mm.get(name) if self.distance_mm is not None else self.plane_mm

    def to_json(self) -> dict[str, Any]:
        if self.normal_cam is not None:
            return {"normal_cam": {n: np.asarray(v, float).tolist() for n, v in self.normal_cam.items()},
                    "distance_mm": dict(self.distance_mm or {})}
        return {"normal_world": np.asarray(self.normal_world, float).tolist(), "plane_mm": self.plane_mm}


@dataclass(frozen=True)
class DeclaredPlaneReport:
    """WINDOW.yaml's interface.plane and how it entered the refinement."""

    frame: str
    declared_normal: np.ndarray
    point_mm: np.ndarray
    normal: str  # "held" or "prior <sigma> deg"
    distance: str  # "held" or "prior <sigma> mm"

    def to_json(self) -> dict[str, Any]:
        return {"frame": self.frame, "declared_normal": np.asarray(self.declared_normal, float).tolist(),
                "point_mm": np.asarray(self.point_mm, float).tolist(), "normal": self.normal,
                "distance": self.distance}


@dataclass(frozen=True)
class ScaleBarReport:
    """The declared scale bar and its length after the refinement."""

    ids: tuple[int, int]  # COLMAP point3D ids
    declared_mm: float
    sigma_mm: float  # the bar's sigma in the solver
    refined_mm: float

    def to_json(self) -> dict[str, Any]:
        return {"ids": [int(i) for i in self.ids], "declared_mm": self.declared_mm, "sigma_mm": self.sigma_mm,
                "refined_mm": self.refined_mm}


@dataclass(frozen=True)
class BaselineReport:
    """The declared baseline (two images' camera centres) and its length after the refinement."""

    images: tuple[str, str]  # image names
    declared_mm: float
    sigma_mm: float  # its sigma in the solver
    refined_mm: float

    def to_json(self) -> dict[str, Any]:
        return {"images": list(self.images), "declared_mm": self.declared_mm, "sigma_mm": self.sigma_mm,
                "refined_mm": self.refined_mm}


@dataclass(frozen=True)
class RefineReport:
    """What refine-colmap did and found; ``to_json()`` is refine.json (docs/DATASET_FORMAT.md)."""

    mount: str
    model: str
    backend: str
    units_mm: float
    interface: Plate
    counts: RefineCounts
    estimated: str  # in words
    scale: str  # in words
    distance_search: tuple[Mapping[str, Any], ...]  # per start distance, as the search wrote it
    restarts: tuple[Mapping[str, Any], ...]  # the other starts refined when the distance ran toward 0
    iterations: int
    converged: bool
    linearizations: int  # of the final solve (and the bar's pre-solve)
    search_linearizations: int
    uncertainty: RefineUncertainty
    cost_start: float
    cost_final: float
    time_s: float
    before: Reprojection  # COLMAP's pinhole model
    after: Reprojection  # the exact refractive model
    pinhole_approximation: Reprojection  # the COLMAP cameras written
    window: WindowEstimate
    plane: DeclaredPlaneReport | None = None
    scale_bar: ScaleBarReport | None = None
    baseline: BaselineReport | None = None

    def to_json(self) -> dict[str, Any]:
        out = {
            "mount": self.mount, "model": self.model, "backend": self.backend, "units_mm": self.units_mm,
            "interface": self.interface.to_json(), "counts": self.counts.to_json(),
            "estimated": self.estimated, "scale": self.scale,
            "distance_search": [dict(c) for c in self.distance_search],
            "restarts": [dict(r) for r in self.restarts],
            "iterations": self.iterations, "converged": self.converged,
            "linearizations": {"final": self.linearizations, "search": self.search_linearizations},
            "uncertainty": self.uncertainty.to_json(),
            "cost": {"start": self.cost_start, "final": self.cost_final},
            "time_s": self.time_s,
            "before": self.before.to_json(), "after": self.after.to_json(),
            "pinhole_approximation": self.pinhole_approximation.to_json(),
            "window": self.window.to_json(),
        }
        if self.plane is not None:
            out["plane"] = self.plane.to_json()
        if self.scale_bar is not None:
            out["scale_bar"] = self.scale_bar.to_json()
        if self.baseline is not None:
            out["baseline"] = self.baseline.to_json()
        return out

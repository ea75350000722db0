"""Where a calibration came from, beyond its cameras and windows: the records calibration.json keeps
for a calibration imported from another tool (``imported_from``) and for refine-colmap's, which sits in
a COLMAP model (``refine_colmap``). Plain records with ``to_json`` / ``from_json``."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..geometry import Pose


@dataclass(frozen=True)
class ImportedFrom:
    """The model a calibration was imported from: its format, its path as given, and the millimetres in
    one of its length units."""

    format: str
    path: str
    units_mm: float

    def to_json(self) -> dict[str, Any]:
        return {"format": self.format, "path": self.path, "units_mm": self.units_mm}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> ImportedFrom:
        units = d["units_mm"]
        if not isinstance(d["format"], str) or not isinstance(d["path"], str):
            raise ValueError("format and path must be strings")
        if isinstance(units, bool) or not isinstance(units, (int, float)) or not (math.isfinite(units) and units > 0):
            raise ValueError(f"units_mm must be a positive number (got {units!r})")
        return cls(d["format"], d["path"], float(units))


MOUNTS = ("camera", "world")  # refine-colmap's: a port on each camera's housing, or one window in the world


@dataclass(frozen=True)
class RefineColmapFrames:
    """How refine-colmap's calibration sits in its COLMAP model: the mount, what frame the cameras' poses
    are in (in words), each camera's COLMAP camera id and, with mount ``camera`` (each camera its own housing
    frame), every COLMAP image's real cam_from_world by image id."""

    mount: str
    world: str
    camera_ids: Mapping[str, int]
    images_cam_from_world: Mapping[int, Pose]

    def to_json(self) -> dict[str, Any]:
        return {"mount": self.mount, "world": self.world, "camera_ids": dict(self.camera_ids),
                "images_cam_from_world": {str(i): p.to_json() for i, p in self.images_cam_from_world.items()}}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> RefineColmapFrames:
        if d["mount"] not in MOUNTS:
            raise ValueError(f"mount must be one of {', '.join(MOUNTS)} (got {d['mount']!r})")
        if not isinstance(d["world"], str):
            raise ValueError("world must be a string")
        ids, poses = d["camera_ids"], d.get("images_cam_from_world", {})
        if not isinstance(ids, Mapping) or not all(isinstance(v, int) and not isinstance(v, bool)
                                                   for v in ids.values()):
            raise ValueError("camera_ids must map camera names to COLMAP camera ids")
        if not isinstance(poses, Mapping):
            raise ValueError("images_cam_from_world must map image ids to poses")
        return cls(d["mount"], d["world"], {str(k): int(v) for k, v in ids.items()},
                   {int(k): Pose.from_json(p) for k, p in poses.items()})

"""``points.json`` (format ``ari-sfm-points/1``): triangulated target points per reconstruction frame."""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.errors import AriSfmError
from ari_sfm.io.atomic import write_json_atomic
from ari_sfm.io.observations import check_format, check_unique_ids
from ari_sfm.io.structured import (
    as_finite_float,
    as_float_array,
    as_int_array,
    as_mapping,
    as_name,
    as_str,
    read_structured,
    require,
)

FORMAT = "ari-sfm-points/1"


def _parse_frame(data: Any, path: Path, name: str) -> dict[str, Any]:
    where = f"frames.{name}"
    data = as_mapping(data, path, where)
    stage = data.get("stage_mm")
    stage = None if stage is None else as_finite_float(stage, path, f"{where}.stage_mm")
    ids = as_int_array(require(data, "ids", path, where), path, f"{where}.ids")
    xyz = as_float_array(require(data, "xyz", path, where), path, f"{where}.xyz", (-1, 3))
    gap = as_float_array(require(data, "ray_gap_mm", path, where), path, f"{where}.ray_gap_mm", (-1,))
    if not len(ids) == len(xyz) == len(gap):
        raise AriSfmError(path, f"{where}: {len(ids)} ids, {len(xyz)} xyz and {len(gap)} ray_gap_mm (must be equal)")
    if (gap < 0).any():
        raise AriSfmError(path, f"{where}.ray_gap_mm must be >= 0 (got {gap[gap < 0][0]:g})")
    check_unique_ids(ids, path, where)
    return {"stage_mm": stage, "ids": ids, "xyz": xyz, "ray_gap_mm": gap}


def parse_points(data: Any, path: Path) -> dict[str, Any]:
    """Validate the parsed content of a points file (see :func:`load_points`).

    Args:
        data: the file's parsed content.
        path: the file, for error messages.

    Returns:
        The points, as :func:`load_points` returns them (with ``provenance``: a mapping or None).

    Raises:
        AriSfmError: a frame is invalid (one line naming it).
    """
    check_format(data, path, FORMAT)
    calibration = data.get("calibration")
    calibration = None if calibration is None else as_str(calibration, path, "calibration")
    frames = as_mapping(require(data, "frames", path), path, "frames")
    out: dict[str, dict[str, Any]] = {}
    for raw, frame in frames.items():
        name = as_name(raw, path, "frames name")
        out[name] = _parse_frame(frame, path, name)
    provenance = data.get("provenance")
    provenance = None if provenance is None else dict(as_mapping(provenance, path, "provenance"))
    return {"format": FORMAT, "calibration": calibration, "frames": out, "provenance": provenance}


def load_points(path: str | Path) -> dict[str, Any]:
    """Read and validate ``points.json``.

    Checks: ids unique integers, xyz finite (N, 3), ray_gap_mm finite >= 0, equal lengths.

    Args:
        path: the file.

    Returns:
        ``{"format", "calibration": str | None, "frames": {name: {"stage_mm": float | None, "ids": (N,)
        int64, "xyz": (N, 3) float, "ray_gap_mm": (N,) float}}, "provenance": mapping | None}``.

    Raises:
        AriSfmError: the file cannot be read or is invalid (one line naming the key).
    """
    path = Path(path)
    return parse_points(read_structured(path), path)


def points_to_json(frames: Mapping[str, Mapping[str, Any]], calibration_name: str,
                   provenance: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Build the ``points.json`` mapping.

    Args:
        frames: reconstruction frame name -> ``{"stage_mm" (optional), "ids", "xyz", "ray_gap_mm"}``;
            stage_mm is written only where set.
        calibration_name: the calibration file that produced the points.
        provenance: see :mod:`ari_sfm.provenance`; written when given.

    Returns:
        The mapping (not yet validated: see :func:`parse_points`).
    """
    out: dict[str, Any] = {}
    for name, frame in frames.items():
        rec: dict[str, Any] = {}
        if frame.get("stage_mm") is not None:
            rec["stage_mm"] = frame["stage_mm"]
        for key in ("ids", "xyz", "ray_gap_mm"):
            value = frame.get(key)
            rec[key] = np.asarray(value).tolist() if isinstance(value, np.ndarray) else value
        out[str(name)] = rec
    data = {"format": FORMAT, "calibration": calibration_name, "frames": out}
    if provenance is not None:
        data["provenance"] = dict(provenance)
    return data


def save_points(path: str | Path, frames: Mapping[str, Mapping[str, Any]], calibration_name: str,
                provenance: Mapping[str, Any] | None = None) -> None:
    """Validate and write ``points.json`` atomically.

    Args:
        path: the file to write.
        frames: reconstruction frame name -> ``{"stage_mm" (optional), "ids", "xyz", "ray_gap_mm"}``
            (arrays or lists).
        calibration_name: the calibration file that produced the points.
        provenance: see :mod:`ari_sfm.provenance`; written when given.

    Raises:
        AriSfmError: a bad frame (nothing is written), or the file cannot be written.
    """
    path = Path(path)
    data = points_to_json(frames, calibration_name, provenance)
    parse_points(data, path)
    write_json_atomic(path, data)

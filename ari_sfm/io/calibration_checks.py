"""The values of a calibration.json (or a simulator's truth.json) held to the bounds of rig.yaml.

A hand-edited or foreign calibration with an index of 6, a 3-number ``dist``,
a window 1e6 mm away or 0 mm thick used to be evaluated into NaN or nonsense
numbers; :func:`check_calibration_values` refuses it in one line naming the key.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from ari_sfm.errors import AriSfmError
from ari_sfm.io.dataset import MAX_INDEX, MAX_LENGTH_MM
from ari_sfm.io.structured import as_float_array, as_float_at_least, as_positive_float, check_at_most

CALIBRATION_DIST_LENGTHS = (4, 5)  # k1 k2 p1 p2 [k3]: what the models use (calibration.json writes 5)


def check_calibration_values(data: Any, path: str | Path, window: bool = True) -> None:
    """AriSfmError naming the key of the first value outside rig.yaml's bounds: ``interface.thickness_mm``
    (> 0 for a model with a window, >= 0 otherwise), ``index`` and ``medium_index`` (1..MAX_INDEX),
    ``distance_mm`` and ``fixed_distance_mm`` (0 < d <= MAX_LENGTH_MM, or null), each camera's ``dist``
    (4 or 5 finite numbers). Structure errors are left to the parser."""
    if not isinstance(data, Mapping):
        return
    iface = data.get("interface")
    if isinstance(iface, Mapping):
        thickness = iface.get("thickness_mm")
        if thickness is not None:
            where = "interface.thickness_mm"
            value = as_positive_float(thickness, path, where) if window else as_float_at_least(thickness, path, where, 0.0)
            check_at_most(value, MAX_LENGTH_MM, path, where, " mm")
        for key in ("index", "medium_index"):
            if iface.get(key) is not None:
                index = as_float_at_least(iface[key], path, f"interface.{key}", 1.0)
                check_at_most(index, MAX_INDEX, path, f"interface.{key}")
        if iface.get("distance_mm") is not None:
            _distance(iface["distance_mm"], path, "interface.distance_mm")
    if data.get("fixed_distance_mm") is not None:
        _distance(data["fixed_distance_mm"], path, "fixed_distance_mm")
    cameras = data.get("cameras")
    if isinstance(cameras, Mapping):
        for name, camera in cameras.items():
            if isinstance(camera, Mapping) and camera.get("dist") is not None:
                dist = as_float_array(camera["dist"], path, f"cameras.{name}.dist", (-1,))
                if len(dist) not in CALIBRATION_DIST_LENGTHS:
                    raise AriSfmError(path, f"cameras.{name}.dist must have 4 or 5 numbers, k1 k2 p1 p2 [k3] "
                                            f"(got {len(dist)})")


def _distance(value: Any, path: str | Path, where: str) -> float:
    return check_at_most(as_positive_float(value, path, where), MAX_LENGTH_MM, path, where, " mm")

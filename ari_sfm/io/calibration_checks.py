"""The values of a calibration.json (or a simulator's truth.json) held to the bounds of rig.yaml.

:func:`check_calibration_values` refuses a value out of bounds (an index of 6, a 3-number ``dist``, a
window 1e6 mm away or 0 mm thick) in one line naming the key.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.errors import AriSfmError
from ari_sfm.io.dataset import MAX_INDEX, MAX_LENGTH_MM, MIN_FOCAL_PX, check_at_least
from ari_sfm.io.structured import (
    as_finite_float,
    as_float_array,
    as_float_at_least,
    as_int_pair,
    as_positive_float,
    check_at_most,
)

CALIBRATION_DIST_LENGTHS = (4, 5)  # k1 k2 p1 p2 [k3]: what the models use (calibration.json writes 5)


def check_calibration_values(data: Any, path: str | Path, window: bool = True) -> None:
    """Check a calibration's values against rig.yaml's bounds.

    Checked: ``interface.thickness_mm`` (> 0 for a model with a window, >= 0 otherwise), ``index`` and
    ``medium_index`` (1..MAX_INDEX), ``distance_mm`` and ``fixed_distance_mm`` (|offset| <= MAX_LENGTH_MM,
    or null; every camera in front of the window, at most MAX_LENGTH_MM from it), each camera's
    ``image_size``, K focal length (>= MIN_FOCAL_PX) and ``dist`` (4 or 5 finite numbers). Structure errors
    are left to the parser.

    Args:
        data: the parsed calibration.json (or truth.json) content; anything but a mapping is not checked.
        path: the file, for error messages.
        window: the model has a window (its thickness must then be > 0).

    Raises:
        AriSfmError: naming the key of the first value outside the bounds.
    """
    if not isinstance(data, Mapping):
        return
    windows = []
    if isinstance(data.get("interface"), Mapping):
        cameras = list(data["cameras"]) if isinstance(data.get("cameras"), Mapping) else []
        windows.append(("interface", data["interface"], cameras))
    if isinstance(data.get("interfaces"), Mapping):
        for name, iface in data["interfaces"].items():
            if isinstance(iface, Mapping):
                listed = iface.get("cameras")
                windows.append((f"interfaces.{name}", iface, list(listed) if isinstance(listed, list) else []))
    for where, iface, cameras in windows:
        _check_window(iface, where, cameras, data, path, window)
    if data.get("fixed_distance_mm") is not None:
        fixed = _offset(data["fixed_distance_mm"], path, "fixed_distance_mm")
        if isinstance(data.get("interface"), Mapping) and windows:
            _check_camera_distances(data, data["interface"], fixed, windows[0][2], "fixed_distance_mm", path)
    camera_data = data.get("cameras")
    if isinstance(camera_data, Mapping):
        for name, camera in camera_data.items():
            if isinstance(camera, Mapping) and camera.get("image_size") is not None:  # 2448.5 was cut to 2448
                as_int_pair(camera["image_size"], path, f"cameras.{name}.image_size", minimum=1)
            if isinstance(camera, Mapping) and camera.get("K") is not None:
                K = as_float_array(camera["K"], path, f"cameras.{name}.K", (3, 3))
                if min(K[0, 0], K[1, 1]) > 0:  # a sign error is the parser's message
                    check_at_least(float(min(K[0, 0], K[1, 1])), MIN_FOCAL_PX, path, f"cameras.{name}.K focal length",
                                   " px")
            if isinstance(camera, Mapping) and camera.get("dist") is not None:
                dist = as_float_array(camera["dist"], path, f"cameras.{name}.dist", (-1,))
                if len(dist) not in CALIBRATION_DIST_LENGTHS:
                    raise AriSfmError(path, f"cameras.{name}.dist must have 4 or 5 numbers, k1 k2 p1 p2 [k3] "
                                            f"(got {len(dist)})")


def _check_window(iface: Mapping, where: str, cameras: list, data: Mapping, path: str | Path, window: bool) -> None:
    """One window's thickness, indices and distance (its cameras in front of it)."""
    thickness = iface.get("thickness_mm")
    if thickness is not None:
        key = f"{where}.thickness_mm"
        value = as_positive_float(thickness, path, key) if window else as_float_at_least(thickness, path, key, 0.0)
        check_at_most(value, MAX_LENGTH_MM, path, key, " mm")
    for key in ("index", "medium_index"):
        if iface.get(key) is not None:
            index = as_float_at_least(iface[key], path, f"{where}.{key}", 1.0)
            check_at_most(index, MAX_INDEX, path, f"{where}.{key}")
    if iface.get("distance_mm") is not None:
        distance = _offset(iface["distance_mm"], path, f"{where}.distance_mm")
        _check_camera_distances(data, iface, distance, cameras, f"{where}.distance_mm", path)
    if iface.get("fixed_distance_mm") is not None:
        fixed = _offset(iface["fixed_distance_mm"], path, f"{where}.fixed_distance_mm")
        _check_camera_distances(data, iface, fixed, cameras, f"{where}.fixed_distance_mm", path)


def _offset(value: Any, path: str | Path, where: str) -> float:
    """A window distance (mm, any sign here; the cameras' side is checked apart)."""
    value = as_finite_float(value, path, where)
    check_at_most(abs(value), MAX_LENGTH_MM, path, f"|{where}|", " mm")
    return value


def _check_camera_distances(data: Mapping, iface: Mapping, distance: float, cameras: list, where: str,
                            path: str | Path) -> None:
    """Each of the window's cameras lies in front of its near face, at most MAX_LENGTH_MM from it; the distance is
    given from the first camera's centre (a malformed normal or pose is left to the parser)."""
    try:
        normal = np.asarray(iface["normal_world"], dtype=float).reshape(3)
        poses = {name: (np.asarray(data["cameras"][name]["cam_from_world"]["R"], float).reshape(3, 3),
                        np.asarray(data["cameras"][name]["cam_from_world"]["t"], float).reshape(3))
                 for name in cameras}
    except (KeyError, TypeError, ValueError, AttributeError):
        return
    if not poses or not np.isfinite(normal).all() or not all(np.isfinite(R).all() and np.isfinite(t).all()
                                                             for R, t in poses.values()):
        return
    R0, t0 = poses[cameras[0]]
    reference = float(normal @ (-R0.T @ t0))
    for name, (R, t) in poses.items():
        h = distance - (float(normal @ (-R.T @ t)) - reference)  # camera centre to the near face along the normal
        if not 0.0 < h <= MAX_LENGTH_MM:
            raise AriSfmError(path, f"{where} {distance:g} puts camera {name} {h:.4g} mm from the "
                                    "window's near face (must be in front of it, "
                                    f"0 < distance <= {MAX_LENGTH_MM:g} mm)")

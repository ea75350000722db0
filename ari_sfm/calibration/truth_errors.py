"""A calibration's parameter errors against a simulator's truth (truth.json, calibration.json form).

Frames are compared where both calibrations agree on them: the window normal and distance in the
first camera's frame, the other cameras' poses relative to the first (``cam_from_cam0``), so the
two worlds need not coincide.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..errors import AriSfmError
from ..geometry import angle_between_deg
from .record import Calibration


@dataclass(frozen=True)
class CameraErrors:
    """One camera's errors (calibrated minus true)."""

    name: str
    fx_pct: float
    fy_pct: float
    cx_px: float
    cy_px: float
    k1: float  # radial distortion coefficient difference
    rotation_deg: float | None  # of cam_from_<first camera>; None for the first camera
    translation_mm: float | None


@dataclass(frozen=True)
class WindowErrors:
    """One window's errors, in the frame of its first camera (a rig with several windows)."""

    name: str
    normal_deg: float | None
    distance_mm: float | None  # its first camera's centre to it; None where either has none


@dataclass(frozen=True)
class CalibrationErrors:
    """Errors of a calibration against the truth."""

    reference_camera: str
    normal_deg: float | None  # None: a model without a window (the first camera's window with several)
    distance_mm: float | None  # first camera's centre to the window; None where either has none
    cameras: tuple[CameraErrors, ...]
    windows: tuple[WindowErrors, ...] = ()  # several windows: each one's

    def to_json(self) -> dict[str, Any]:
        out = {"reference_camera": self.reference_camera, "normal_deg": self.normal_deg,
               "distance_mm": self.distance_mm, "cameras": [asdict(c) for c in self.cameras]}
        if self.windows:
            out["windows"] = [asdict(w) for w in self.windows]
        return out


def calibration_errors(cal: Calibration, truth: Calibration) -> CalibrationErrors:
    """Give a calibration's parameter errors against the truth (module docstring: the frames compared).

    Args:
        cal: the calibration.
        truth: the simulator's truth, with the same camera names.

    Returns:
        The errors (calibrated minus true).

    Raises:
        AriSfmError: if a camera of ``cal`` is not in the truth.
    """
    missing = [n for n in cal.cameras if n not in truth.cameras]
    if missing:
        raise AriSfmError("truth", f"camera {missing[0]} is not in the truth (its cameras: {', '.join(truth.cameras)})")
    first = next(iter(cal.cameras))
    windows = tuple(_window_errors(cal, truth, w.name, w.cameras[0]) for w in cal.window_list())
    mine = next(w for w in windows if first in cal.window_of(first).cameras and w.name == cal.window_of(first).name)
    normal, distance = mine.normal_deg, mine.distance_mm
    cams = []
    for name, c in cal.cameras.items():
        t = truth.cameras[name]
        p, q = c.params, t.params
        rotation = translation = None
        if name != first:
            rel = c.cam_from_world.compose(cal.cameras[first].cam_from_world.inverse())
            rel_true = t.cam_from_world.compose(truth.cameras[first].cam_from_world.inverse())
            cos = (np.trace(rel.R @ rel_true.R.T) - 1.0) / 2.0
            rotation = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
            translation = float(np.linalg.norm(rel.t - rel_true.t))
        cams.append(CameraErrors(name, 100.0 * (p[0] / q[0] - 1.0), 100.0 * (p[1] / q[1] - 1.0), p[2] - q[2],
                                 p[3] - q[3], p[4] - q[4], rotation, translation))
    return CalibrationErrors(first, normal, distance, tuple(cams), windows if cal.windows else ())


def _window_errors(cal: Calibration, truth: Calibration, name: str, camera: str) -> WindowErrors:
    """A window's normal and distance errors, seen from ``camera`` (its first)."""
    normal = distance = None
    if cal.window_of(camera).normal_world is not None and truth.window_of(camera).normal_world is not None:
        normal = angle_between_deg(cal.normal_cam(camera), truth.normal_cam(camera))
        d_cal, d_true = cal.distance_mm(camera), truth.distance_mm(camera)
        if d_cal is not None and d_true is not None:
            distance = d_cal - d_true
    return WindowErrors(name, normal, distance)

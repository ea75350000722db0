"""Calibration: the result record and how it is made, judged and compared.

- ``record``: :class:`Calibration` (what calibration.json holds) and its cameras and windows;
- ``calibrate``: :func:`~ari_sfm.calibration.calibrate.calibrate`, a plan of stages, and its options;
- ``quality``, ``floor_fit``: the quality gate and the noise floor it judges against;
- ``outliers``, ``evaluate``, ``compare``: corners beyond k sigma, reprojection errors on any
  observations, the paper's comparison of models;
- ``origin``, ``truth_errors``: where a calibration came from; its errors against a simulation's truth.

``from ari_sfm.calibration import Calibration`` reads the record (the package imports nothing else).
"""
from __future__ import annotations

from .record import Calibration, CameraCalibration, WindowCalibration

__all__ = ["Calibration", "CameraCalibration", "WindowCalibration"]

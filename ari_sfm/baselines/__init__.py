"""The methods the paper compares ARI with (Section 3.3), and the usual "ignore the window" start.

- :mod:`.ray_tracing` (``rt``): Feng et al.'s ray-tracing bundle adjustment;
- :mod:`.polynomial` (``pf``): Paolillo et al.'s 3x3x3 polynomial, world to pixels;
- :mod:`.pinhole` (``pinhole``, ``pinhole_dist``): plain OpenCV cameras, window ignored;
- :mod:`.bundle`: what the least-squares baselines share (Zhang start, rig join, numeric Jacobian).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..calibration.calibrate import CalibrationOptions
    from ..calibration.record import Calibration
    from ..records import Dataset

# The calibrators ari_sfm.models.registry names, one per model: (dataset with observations,
# CalibrationOptions) -> Calibration. rt and pinhole use ``distortion`` and ``max_iterations``;
# pf fits in the world of an ari calibration made with all the options.


def calibrate_rt_model(dataset: Dataset, options: CalibrationOptions) -> Calibration:
    from .ray_tracing import calibrate_rt

    return calibrate_rt(dataset, bool(options.distortion), options.max_iterations)  # resolved by calibrate


def calibrate_pinhole_model(dataset: Dataset, options: CalibrationOptions) -> Calibration:
    from .pinhole import calibrate_pinhole

    return calibrate_pinhole(dataset, bool(options.distortion), options.max_iterations)  # resolved


def calibrate_pinhole_dist_model(dataset: Dataset, options: CalibrationOptions) -> Calibration:
    from .pinhole import calibrate_pinhole

    return calibrate_pinhole(dataset, True, options.max_iterations)


def calibrate_pf_model(dataset: Dataset, options: CalibrationOptions) -> Calibration:
    from .polynomial import calibrate_pf

    return calibrate_pf(dataset, options=options)

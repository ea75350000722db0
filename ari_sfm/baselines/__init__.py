"""The methods the paper compares ARI with (Section 3.3), and the usual "ignore the window" start.

- :mod:`.ray_tracing` (``rt``): Feng et al.'s ray-tracing bundle adjustment;
- :mod:`.polynomial` (``pf``): Paolillo et al.'s 3x3x3 polynomial, world to pixels;
- :mod:`.pinhole` (``pinhole``, ``pinhole_dist``): plain OpenCV cameras, window ignored;
- :mod:`.bundle`: what the least-squares baselines share (Zhang start, rig join, numeric Jacobian).
"""
from __future__ import annotations

BASELINES = ("rt", "pf", "pinhole", "pinhole_dist")


def calibrate_baseline(dataset, model: str, options) -> "Calibration":  # noqa: F821
    """Run baseline ``model`` on a dataset with observations (``options``: CalibrationOptions).

    rt and pinhole use ``distortion`` and ``max_iterations``; pf fits in the
    world of an ari calibration made with all the options.
    """
    from dataclasses import asdict

    if model == "rt":
        from .ray_tracing import calibrate_rt

        return calibrate_rt(dataset, options.distortion, options.max_iterations)
    if model in ("pinhole", "pinhole_dist"):
        from .pinhole import calibrate_pinhole

        return calibrate_pinhole(dataset, model == "pinhole_dist" or options.distortion, options.max_iterations)
    if model == "pf":
        from .polynomial import calibrate_pf

        return calibrate_pf(dataset, **asdict(options))
    raise ValueError(f"unknown baseline {model!r} (known: {', '.join(BASELINES)})")

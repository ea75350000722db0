"""Every model ari-sfm knows, named once: what it projects with, what it has, who calibrates it.

The command line's choices, :func:`ari_sfm.calibrate`, ``compare``, the
triangulation, ``evaluate`` and calibration.json loading all read this table;
an unknown name anywhere is the one-line :class:`~ari_sfm.errors.AriSfmError`
of :func:`model_spec`. Calibrators are named as ``"module:function"`` and
imported only when called (the baselines pull in scipy's least squares).
"""
from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..errors import AriSfmError

PROJECTIONS = ("ari", "exact", "pinhole", "polynomial")  # the projection classes a model can use


@dataclass(frozen=True)
class ModelSpec:
    """One model: its name, how it projects, what calibration.json holds for it, how it is calibrated."""

    name: str
    summary: str  # one line for --help
    projection: str  # "ari": AriModel, "exact": ExactModel, "pinhole": PinholeModel (window ignored),
    # "polynomial": the pf PolynomialModel (world points to pixels only)
    bundle: bool  # calibrated by calibrate()'s window bundle adjustment (RigGraph, factors/)
    calibrator: str | None  # "module:function" (dataset, options) -> Calibration for the others; None with
    # bundle False: not calibrated, only loaded (a simulator's truth.json)
    camera_keys: tuple[str, ...] = ()  # per-camera calibration.json keys the model needs (pf: its polynomial)
    distortion: bool = False  # always estimates k1 k2 p1 p2 k3 (pinhole_dist)
    params_per_camera: int | None = None  # fixed parameter count (pf's 40); None: intrinsics + window
    compared: bool = True  # among `ari-sfm compare`'s default models
    one_window: bool = False  # its calibrator models one window for every camera (not a rig's several)

    def __post_init__(self) -> None:
        if self.projection not in PROJECTIONS:
            raise ValueError(f"model {self.name}: projection must be one of {', '.join(PROJECTIONS)}")
        if self.bundle and self.calibrator is not None:
            raise ValueError(f"model {self.name}: a bundle-adjusted model has no separate calibrator")

    @property
    def window(self) -> bool:
        """Has a window normal (calibration.json interface.normal_world is not null)."""
        return self.projection != "pinhole"

    @property
    def rays(self) -> bool:
        """Back-projects pixels to scene rays (Calibration.rays_world); the pf polynomial does not."""
        return self.projection != "polynomial"

    @property
    def analytic_jacobians(self) -> bool:
        """Its projection gives d pixel / d point analytically (used by the triangulation)."""
        return self.projection in ("ari", "exact")

    @property
    def calibratable(self) -> bool:
        return self.bundle or self.calibrator is not None

    @property
    def needs_distance(self) -> bool:
        """Exact Snell needs the window's distance even in air, where the data do not fix it
        (calibration.json then holds ``fixed_distance_mm``: the value it was calibrated with)."""
        return self.projection == "exact"

    def calibrate(self, dataset, options) -> Any:
        """Run this model's calibrator (not for bundle models: :func:`ari_sfm.calibrate` runs those).

        Args:
            dataset (Dataset): the dataset, with observations.
            options (CalibrationOptions): the calibration options
                (:class:`~ari_sfm.calibration.calibrate.CalibrationOptions`).

        Returns:
            The :class:`~ari_sfm.calibration.record.Calibration` the calibrator made.

        Raises:
            ValueError: the model has no separate calibrator.
        """
        if self.calibrator is None:
            raise ValueError(f"model {self.name} has no separate calibrator")
        module, function = self.calibrator.split(":")
        fn: Callable = getattr(importlib.import_module(module), function)
        return fn(dataset, options)

    def projection_class(self) -> type:
        """AriModel, ExactModel or PinholeModel (the pf polynomial is built from its coefficients instead)."""
        from . import AriModel, ExactModel, PinholeModel

        classes = {"ari": AriModel, "exact": ExactModel, "pinhole": PinholeModel}
        if self.projection not in classes:
            raise ValueError(f"model {self.name} projects with its {self.projection}, not a camera model class")
        return classes[self.projection]


_SPECS = (
    ModelSpec("ari", "the paper's paraxial ARI model (analytic start + bundle adjustment)", "ari", bundle=True,
              calibrator=None),
    ModelSpec("exact", "Snell's law at both faces, refined from the ari result", "exact", bundle=True,
              calibrator=None),
    ModelSpec("rt", "Feng et al.'s ray-tracing bundle adjustment (saved as exact Snell)", "exact", bundle=False,
              calibrator="ari_sfm.baselines:calibrate_rt_model", one_window=True),
    ModelSpec("pf", "Paolillo et al.'s 3x3x3 world-to-pixel polynomial per camera", "polynomial", bundle=False,
              calibrator="ari_sfm.baselines:calibrate_pf_model", camera_keys=("pf",), params_per_camera=40),
    ModelSpec("pinhole", "plain OpenCV camera, window ignored", "pinhole", bundle=False,
              calibrator="ari_sfm.baselines:calibrate_pinhole_model"),
    ModelSpec("pinhole_dist", "plain OpenCV camera with distortion, window ignored", "pinhole", bundle=False,
              calibrator="ari_sfm.baselines:calibrate_pinhole_dist_model", distortion=True, compared=False),
    ModelSpec("truth", "a simulator's truth.json (exact Snell; loaded, never calibrated)", "exact", bundle=False,
              calibrator=None, compared=False),
)
MODELS: dict[str, ModelSpec] = {s.name: s for s in _SPECS}
CALIBRATABLE: tuple[str, ...] = tuple(s.name for s in _SPECS if s.calibratable)
COMPARED: tuple[str, ...] = tuple(s.name for s in _SPECS if s.compared)  # compare's default
BUNDLE: tuple[str, ...] = tuple(s.name for s in _SPECS if s.bundle)  # also the worlds pf can fit in


def model_spec(name: Any, where: str | None = "model", calibratable: bool = False) -> ModelSpec:
    """The spec of a model name.

    Args:
        name: the model's name (anything else is an error).
        where: what the error names: a file or an option.
        calibratable: require a model that can be calibrated (not only loaded).

    Returns:
        The :class:`ModelSpec`.

    Raises:
        AriSfmError: an unknown name, or (with ``calibratable``) a model that is only loaded.
    """
    spec = MODELS.get(name) if isinstance(name, str) else None
    if spec is None:
        raise AriSfmError(where,
                          f"unknown model {name!r} (known: {', '.join(CALIBRATABLE if calibratable else MODELS)})")
    if calibratable and not spec.calibratable:
        raise AriSfmError(where,
                          f"model {name!r} is loaded, never calibrated (calibrate with: {', '.join(CALIBRATABLE)})")
    return spec


def bundle_factories() -> dict[str, type]:
    """Projection class of each bundle-adjusted model (the factor graph's MODELS)."""
    return {name: MODELS[name].projection_class() for name in BUNDLE}

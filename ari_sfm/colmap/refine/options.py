"""refine-colmap's options as one frozen record, its modes as enums.

The modes are :class:`ari_sfm.options.Choice` enums (each equals its string; refine.json, calibration.json and
messages read as with plain strings). A light module: the command line reads it without pycolmap.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ari_sfm.options import Choice, with_overrides

from .settings import HUBER_PX, MAX_ITERATIONS


class Mount(Choice):
    """How the window is mounted: a housing per COLMAP camera, or one window fixed in the world."""

    CAMERA = "camera"
    WORLD = "world"


class Approximation(Choice):
    """The COLMAP cameras written beside the refractive result: OPENCV (the lens distortion absorbs much of
    the port), or the input's camera models."""

    OPENCV = "opencv"
    PINHOLE = "pinhole"


class Backend(Choice):
    """The bundle-adjustment solver: numpy (points eliminated by the Schur complement, this package's LM) or
    GTSAM (one CustomFactor per image, GTSAM's LM)."""

    NUMPY = "numpy"
    GTSAM = "gtsam"


MODELS = ("exact",)  # the refractive models refine-colmap refines with


@dataclass(frozen=True)
class RefineColmapOptions:
    """Options of :func:`~ari_sfm.colmap.refine.refine_colmap`, each with its default.

    ``mount``: ``camera`` (a housing per COLMAP camera) or ``world`` (one window fixed in the world);
    ``model``: the refractive model (``exact``); ``units_mm``: mm per unit of the COLMAP model (a start);
    ``scale_bar``: ``(point3D_id, point3D_id, mm)``; ``baseline``: ``(image, image, mm)``, two images (names or
    COLMAP image ids) whose camera centres are ``mm`` apart (numpy backend); ``huber_px``: the Huber threshold
    (None: plain least squares); ``max_iterations``: the final refinement's cap on accepted LM steps;
    ``distances_mm``: the start search's distance candidates (None: the defaults); ``approximation``: the COLMAP
    cameras written; ``backend``: the final refinement's solver (the start search stays numpy).
    """

    mount: Mount = Mount.CAMERA
    model: str = "exact"
    units_mm: float | None = None
    scale_bar: tuple[int, int, float] | None = None
    baseline: tuple[str | int, str | int, float] | None = None
    huber_px: float | None = HUBER_PX
    max_iterations: int = MAX_ITERATIONS
    distances_mm: tuple[float, ...] | None = None
    approximation: Approximation = Approximation.OPENCV
    backend: Backend = Backend.NUMPY

    def __post_init__(self) -> None:
        """Strings converted to modes; an unknown model or mode is one line of ValueError."""
        if self.model not in MODELS:
            raise ValueError(f"refine-colmap: model {self.model!r} is not supported ({', '.join(MODELS)})")
        object.__setattr__(self, "backend", Backend.parse(self.backend, "backend"))
        object.__setattr__(self, "approximation", Approximation.parse(self.approximation, "approximation"))
        object.__setattr__(self, "mount", Mount.parse(self.mount, "mount"))

    @property
    def scale_given(self) -> bool:
        """Whether the options give the scale (units_mm, a scale bar or a baseline)."""
        return self.units_mm is not None or self.scale_bar is not None or self.baseline is not None


def refine_options(options: RefineColmapOptions | None, overrides: dict[str, Any]) -> RefineColmapOptions:
    """``options`` (default: the defaults) with the keyword ``overrides`` applied.

    Args:
        options: the record, or None for the defaults.
        overrides: option names and values (refine_colmap's keyword form).

    Returns:
        The options record.

    Raises:
        TypeError: an unknown option name, or ``options`` not a record.
        ValueError: a value no option takes (one line).
    """
    return with_overrides(RefineColmapOptions, options, overrides, "refine_colmap")

"""refine-colmap's options as one frozen record, its modes as enums.

The modes are ``(str, Enum)``: a mode equals its string (``Mount.CAMERA == "camera"``), prints and formats as
it and is written to JSON as it, so refine.json, calibration.json, messages and string comparisons are what
they were with plain strings. A record built from strings converts them; a string that names no mode is one
line of ``ValueError`` naming the allowed values. A light module: the command line reads it without pycolmap.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from enum import Enum
from typing import Any, TypeVar

from .settings import HUBER_PX, MAX_ITERATIONS

C = TypeVar("C", bound="Choice")


class Choice(str, Enum):
    """A mode of an options record: its value is its string (``str()``, f-strings, JSON and ``==`` see it)."""

    def __str__(self) -> str:
        """The mode's string."""
        return str(self.value)

    @classmethod
    def parse(cls: type[C], value: object, name: str) -> C:
        """``value`` (a mode or its string) as a mode of this enum.

        Args:
            value: a member of this enum, or the string of one.
            name: the option's name, for the error.

        Returns:
            The member.

        Raises:
            ValueError: one line naming the option and the allowed values.
        """
        try:
            return cls(value)
        except ValueError:
            allowed = ", ".join(m.value for m in cls)
            raise ValueError(f"{name} must be one of {allowed} (got {value!r})") from None


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
    names = {f.name for f in fields(RefineColmapOptions)}
    unknown = set(overrides) - names
    if unknown:
        raise TypeError(f"unknown refine_colmap option(s): {', '.join(sorted(unknown))} "
                        f"(known: {', '.join(sorted(names))})")
    if options is None:
        return RefineColmapOptions(**overrides)
    if not isinstance(options, RefineColmapOptions):
        raise TypeError(f"options must be a RefineColmapOptions (got {type(options).__name__})")
    return replace(options, **overrides)

"""One image of a 3D calibration body -> its identified points: clicked points, dots, identification.

:func:`find_body` chains :mod:`.identify` (the start camera from the clicks), :mod:`.dots` (the dots, their
size from a hint or from the blobs at the clicked points) and :mod:`.identify` again (the matching).
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ari_sfm.records import Target

from .camera import BodyWindow
from .dots import DotOptions, Dots, alike, dot_diameter_at, find_dots
from .identify import (
    BodyMatch,
    ClickError,
    IdentifyOptions,
    clicked_points,
    identify_body,
    projected_spacing,
    start_cameras,
    unexplained_dots,
)

log = logging.getLogger(__name__)

UNEXPLAINED_FRACTION = 0.2  # of the dots like the body's among the identified ones, at most this share unexplained
UNEXPLAINED_MIN = 3  # (and always this many: a stray bubble or two)


@dataclass(frozen=True)
class BodyHints:
    """What the dataset says about a view beyond its clicks.

    Attributes:
        focal_px: A focal length to start from (px), or None.
        aspect: fy / fx.
        window: The window in the body's frame (the exact model), or None (pinhole).
        diameter_mm: The dots' diameter (mm), or None.
    """

    focal_px: float | None = None
    aspect: float = 1.0
    window: BodyWindow | None = None
    diameter_mm: float | None = None


def find_body(image: np.ndarray, target: Target, clicks: Mapping[int, tuple[float, float]],
              hints: BodyHints = BodyHints(), dots: DotOptions = DotOptions(),
              options: IdentifyOptions = IdentifyOptions()) -> BodyMatch:
    """Identify the body points in one image from a few clicked points.

    The dot diameter in pixels: ``dots.diameter_px`` if set, else ``hints.diameter_mm`` scaled by the
    start camera (focal length over the body's depth), else the median size of the blobs at the clicked
    points (within the search radius), else no size limit.

    Args:
        image: Grey image, 8- or 16-bit.
        target: The body (its 3D points).
        clicks: ``{id: (u, v)}``, >= 4 clicked points (OpenCV pixels).
        hints: What the dataset says about the view beyond its clicks.
        dots: How dots are found.
        options: How dots are matched to body points.

    Returns:
        The identified body points.

    Raises:
        ClickError: The clicks do not fit the body, or the identification they lead to leaves more than
            max(UNEXPLAINED_MIN, UNEXPLAINED_FRACTION x their number) of the dots like the body's among
            the identified ones unexplained.
    """
    height, width = np.asarray(image).shape[:2]
    size = (int(width), int(height))
    ids, xyz = target.points_3d_readonly
    starts = start_cameras(ids, xyz, clicks, size, hints.focal_px, hints.aspect, hints.window, options)
    camera = starts[0][0]
    diameter = dots.diameter_px
    if diameter is None and hints.diameter_mm is not None:
        depth = float(np.median((np.asarray(xyz) @ camera.rotation.T + camera.params[3:6])[:, 2]))
        diameter = hints.diameter_mm * camera.focal_px / depth
    if diameter is None:
        radius = options.tolerance_px or options.tolerance_fraction * projected_spacing(camera, xyz, size)
        diameter = dot_diameter_at(image, clicked_points(ids, xyz, clicks)[2], radius, dots)
        if diameter is None:
            log.warning("no dot found within %.1f px of the clicked points: dots of any size are taken", radius)
    found = find_dots(image, DotOptions(diameter, dots.threshold_sigma, dots.min_contrast, dots.max_elongation))
    match = identify_body(found.centres, ids, xyz, clicks, size, hints.focal_px, hints.aspect, hints.window,
                          options, starts)
    _check_explained(match, found, xyz)
    log.debug("%d of %d body points in view identified (%d dots of %s px; left out: %d ambiguous, %d off the "
             "model; %.2f px RMS)", len(match.ids), match.visible, len(found),
             "any size" if diameter is None else f"{diameter:.1f}", len(match.ambiguous), len(match.off_model),
             match.rms_px)
    return match


def _check_explained(match: BodyMatch, found: Dots, xyz: np.ndarray) -> None:
    """ClickError when more than max(UNEXPLAINED_MIN, UNEXPLAINED_FRACTION x their number) of the dots of the
    body's size and brightness among the identified ones have no body point projected near them."""
    inside, unexplained = unexplained_dots(match, found.centres, xyz)
    like = alike(found, match.dot_indices)
    among, stray = int((inside & like).sum()), int((unexplained & like).sum())
    if stray > max(UNEXPLAINED_MIN, UNEXPLAINED_FRACTION * among):
        raise ClickError(f"the clicked points lead to a camera that explains only {among - stray} of the {among} "
                         "body dots among the identified ones (a wrong id among the clicks?)")

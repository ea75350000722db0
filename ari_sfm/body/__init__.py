"""3D calibration bodies from their images (DATASET_FORMAT 1.3): dots found in a real tank image and
identified as body points from a few clicked points.

- :mod:`.dots`: bright dots among walls, glare and particles (:func:`find_dots`);
- :mod:`.camera`: the camera that matches (pinhole with k1, or the exact model through a declared window),
  its fit and its start from the clicks;
- :mod:`.identify`: the sortgrid iteration (:func:`identify_body`), ambiguous points left out;
- :mod:`.find`: one image, end to end (:func:`find_body`).
"""
from .camera import BodyWindow, MatchCamera
from .dots import DotOptions, Dots, find_dots
from .find import BodyHints, find_body
from .identify import BodyMatch, ClickError, IdentifyOptions, identify_body

__all__ = ["BodyHints", "BodyMatch", "BodyWindow", "ClickError", "DotOptions", "Dots", "IdentifyOptions",
           "MatchCamera", "find_body", "find_dots", "identify_body"]

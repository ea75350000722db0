"""WINDOW.yaml: the plate and how it is mounted, for refine-colmap.

    interface:            # the data contract's keys (DATASET_FORMAT interface)
      thickness_mm: 8
      index: 1.49
      medium_index: 1.333 # optional, 1 (air) by default
      plane:              # optional: the window as built (see colmap/refine/plane.py)
        normal: [0, 0, 1] # mount camera: in the camera (housing) frame; world: the COLMAP world
        point_mm: [0, 0, 22]  # a point of the camera-side face (world: COLMAP coordinates in mm)
        sigma_deg: 0.5    # optional; absent or 0: held, > 0: a prior
        sigma_mm: 1.0
    mount: camera         # camera: a housing per COLMAP camera; world: one window fixed in the world
    units_mm: 1.0         # optional: mm per unit of the COLMAP model
    scale_bar:            # optional, instead of units_mm: two point3D ids and their distance
      point3D_ids: [12, 873]
      distance_mm: 500
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from ari_sfm.errors import AriSfmError
from ari_sfm.io import as_int_array, as_mapping, as_positive_float, read_structured, require
from ari_sfm.io.dataset import parse_interface
from ari_sfm.io.structured import warn_unknown_keys
from ari_sfm.records import Interface

from .options import Mount

log = logging.getLogger(__name__)

WINDOW_KEYS = ("interface", "mount", "units_mm", "scale_bar")


@dataclass(frozen=True)
class WindowSpec:
    """A parsed WINDOW.yaml."""

    interface: Interface
    mount: Mount
    units_mm: float | None = None
    scale_bar: tuple[int, int, float] | None = None


def load_window(path: str | Path) -> WindowSpec:
    """Read and validate WINDOW.yaml.

    Args:
        path: the file.

    Returns:
        The plate, the mount and the scale it gives.

    Raises:
        AriSfmError: one line naming the file and the key.
    """
    path = Path(path)
    data = as_mapping(read_structured(path), path, "")
    warn_unknown_keys(data, WINDOW_KEYS, path)
    raw = require(data, "interface", path)
    mount = require(data, "mount", path)
    try:
        mount = Mount.parse(mount, "mount")
    except ValueError as exc:
        raise AriSfmError(path, str(exc)) from None
    if isinstance(raw, dict) and isinstance(raw.get("plane"), dict) and raw["plane"].get("frame") is None:
        raw = dict(raw, plane=dict(raw["plane"], frame=mount.value))  # no target frames here: the mount's frame
    interface = parse_interface(raw, path)
    units = data.get("units_mm")
    units = None if units is None else as_positive_float(units, path, "units_mm")
    bar = data.get("scale_bar")
    if bar is not None:
        bar = as_mapping(bar, path, "scale_bar")
        ids = as_int_array(require(bar, "point3D_ids", path, "scale_bar"), path, "scale_bar.point3D_ids")
        if len(ids) != 2 or ids[0] == ids[1]:
            raise AriSfmError(path, f"scale_bar.point3D_ids must be two different point3D ids (got {ids.tolist()})")
        length = as_positive_float(require(bar, "distance_mm", path, "scale_bar"), path, "scale_bar.distance_mm")
        bar = (int(ids[0]), int(ids[1]), length)
    return WindowSpec(interface, mount, units, bar)

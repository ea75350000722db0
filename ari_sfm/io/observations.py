"""``observations.json`` (format ``ari-sfm-observations/1``): detected corners, one record per image."""
from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.errors import AriSfmError
from ari_sfm.io.atomic import write_json_atomic
from ari_sfm.io.structured import (
    as_finite_float,
    as_float_array,
    as_int_array,
    as_list,
    as_mapping,
    as_name,
    as_nonnegative_float,
    read_structured,
    require,
    show,
    warn_unknown_keys,
)
from ari_sfm.records import SETS, Observation, Target

FORMAT = "ari-sfm-observations/1"
RECORD_KEYS = ("camera", "set", "pose", "frame", "added_mm", "stage_mm", "ids", "pixels")


def check_format(data: Any, path: Path, expected: str) -> None:
    """Check that a file's top level is a mapping whose ``format`` is ``expected``.

    Args:
        data: the file's parsed content.
        path: the file, for error messages.
        expected: the format string, e.g. ``ari-sfm-observations/1``.

    Raises:
        AriSfmError: not a mapping, no ``format``, or another format.
    """
    fmt = require(data, "format", path)
    if fmt != expected:
        raise AriSfmError(path, f"unsupported format {show(fmt)} (expected '{expected}')")


def check_ids_in_target(ids: np.ndarray, target: Target, path: Path, where: str) -> None:
    """Check that every id names a point of a target.

    Args:
        ids: the ids, (N,) int.
        target: the target.
        path: the file, for error messages.
        where: the record, for error messages.

    Raises:
        AriSfmError: naming the first id that is not a point of ``target``.
    """
    if target.type == "points3d":
        known = np.array(sorted(target.points or {}), dtype=np.int64)
        bad = ids[~np.isin(ids, known)]
        if bad.size:
            raise AriSfmError(path, f"{where}: id {int(bad[0])} is not a point of the points3d target")
        return
    n = target.num_ids()
    bad = ids[(ids < 0) | (ids >= n)]
    if bad.size:
        raise AriSfmError(path, f"{where}: id {int(bad[0])} out of range for the {target.type} target (ids 0..{n - 1})")


def check_unique_ids(ids: np.ndarray, path: Path, where: str) -> None:
    """Check that no id appears twice.

    Args:
        ids: the ids, (N,) int.
        path: the file, for error messages.
        where: the record, for error messages.

    Raises:
        AriSfmError: naming the first repeated id.
    """
    values, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        raise AriSfmError(path, f"{where}: duplicate id {int(values[counts > 1][0])} in ids")


BORDER_TOLERANCE_PX = 1.0  # a corner's sub-pixel centre may lie this far beyond the image's edge (noise, a
# centre fitted at the border); farther out it is an error


def check_pixels_in_images(observations: Iterable[Observation], image_sizes: Mapping[str, Sequence[int]],
                           path: str | Path) -> None:
    """Check that every pixel lies inside its camera's image.

    OpenCV pixel centres: the image's edges are at -0.5 and size - 0.5. A pixel at most
    BORDER_TOLERANCE_PX beyond an edge is accepted (and kept as it is).

    Args:
        observations: the observations.
        image_sizes: camera name -> (width, height) px; cameras missing here are not checked.
        path: the observations file, for error messages.

    Raises:
        AriSfmError: naming the first observation with a pixel outside.
    """
    lo = -0.5 - BORDER_TOLERANCE_PX
    for i, o in enumerate(observations):
        if o.camera not in image_sizes:
            continue
        w, h = image_sizes[o.camera]
        hi_u, hi_v = w - 0.5 + BORDER_TOLERANCE_PX, h - 0.5 + BORDER_TOLERANCE_PX
        outside = (o.pixels[:, 0] < lo) | (o.pixels[:, 0] > hi_u) | (o.pixels[:, 1] < lo) | (o.pixels[:, 1] > hi_v)
        if outside.any():
            j = int(np.argmax(outside))
            u, v = o.pixels[j]
            raise AriSfmError(
                path, f"observation {i} ({describe(o)}): pixel ({u:g}, {v:g}) of id {int(o.ids[j])} is outside the "
                      f"{w} x {h} image (more than {BORDER_TOLERANCE_PX:g} px beyond its edge)"
            )


def frame_key(set_name: str) -> str:
    """The record key that names the frame: ``pose`` for stacking, ``frame`` otherwise."""
    return "pose" if set_name == "stacking" else "frame"


def describe(obs: Observation) -> str:
    """``camera cam0, frame f003`` (stacking: ``camera cam0, pose s0, added_mm 10``)."""
    if obs.set == "stacking":
        return f"camera {obs.camera}, pose {obs.frame}, added_mm {obs.added_mm:g}"
    return f"camera {obs.camera}, frame {obs.frame}"


def _need(rec: Mapping, key: str, path: Path, ctx: str) -> Any:
    if rec.get(key) is None:
        raise AriSfmError(path, f"{ctx}: missing key '{key}'")
    return rec[key]


def _parse_record(rec: Any, i: int, path: Path, target: Target | None, cameras: set[str] | None) -> Observation:
    where = f"observation {i}"
    rec = as_mapping(rec, path, where)
    camera = as_name(_need(rec, "camera", path, where), path, f"{where}: camera")
    set_name = _need(rec, "set", path, f"{where} (camera {camera})")
    if set_name not in SETS:
        raise AriSfmError(path, f"{where}: set must be one of {', '.join(SETS)} (got {show(set_name)})")
    key = frame_key(set_name)
    if rec.get(key) is None:
        raise AriSfmError(path, f"{where} (camera {camera}): missing key '{key}' ({set_name} records name the {key})")
    frame = as_name(rec[key], path, f"{where}.{key}")
    ctx = f"{where} (camera {camera}, {key} {frame})"
    if set_name == "stacking":
        if rec.get("added_mm") is None:
            raise AriSfmError(path, f"{ctx}: missing key 'added_mm' (stacking records need it)")
        added = as_nonnegative_float(rec["added_mm"], path, f"{ctx}: added_mm")
    elif rec.get("added_mm") is not None:
        raise AriSfmError(path, f"{ctx}: added_mm is only for stacking records")
    else:
        added = None
    stage = None if rec.get("stage_mm") is None else as_finite_float(rec["stage_mm"], path, f"{ctx}: stage_mm")
    if cameras is not None and camera not in cameras:
        raise AriSfmError(path, f"{ctx}: camera '{camera}' is not declared in the rig (cameras: "
                                f"{', '.join(sorted(cameras))})")
    ids = as_int_array(_need(rec, "ids", path, ctx), path, f"{ctx}: ids")
    pixels = as_float_array(_need(rec, "pixels", path, ctx), path, f"{ctx}: pixels", (-1, 2))
    if len(ids) != len(pixels):
        raise AriSfmError(path, f"{ctx}: {len(ids)} ids but {len(pixels)} pixels")
    check_unique_ids(ids, path, ctx)
    if target is not None:
        check_ids_in_target(ids, target, path, ctx)
    return Observation(camera=camera, set=set_name, frame=frame, ids=ids, pixels=pixels, added_mm=added, stage_mm=stage)


def parse_observations(
    data: Any, path: Path, target: Target | None = None, camera_names: Iterable[str] | None = None
) -> tuple[Observation, ...]:
    """Validate the parsed content of an observations file (see :func:`load_observations`).

    Args:
        data: the file's parsed content.
        path: the file, for error messages.
        target: the target the ids must belong to; None: not checked.
        camera_names: the cameras the records may name; None: not checked.

    Returns:
        The observations, in file order.

    Raises:
        AriSfmError: a record is invalid or repeated (one line naming it).
    """
    check_format(data, path, FORMAT)
    records = as_list(require(data, "observations", path), path, "observations")
    cameras = None if camera_names is None else set(camera_names)
    out: list[Observation] = []
    seen: dict[tuple, int] = {}
    unknown: set[str] = set()
    for i, rec in enumerate(records):
        obs = _parse_record(rec, i, path, target, cameras)
        unknown.update(str(k) for k in rec if k not in RECORD_KEYS)
        key = (obs.camera, obs.set, obs.frame, obs.added_mm)
        if key in seen:
            raise AriSfmError(path, f"observation {i} ({describe(obs)}, set {obs.set}) repeats observation {seen[key]}")
        seen[key] = i
        out.append(obs)
    if unknown:
        warn_unknown_keys(dict.fromkeys(sorted(unknown)), (), path, "observations[]")
    return tuple(out)


def load_observations(
    path: str | Path, target: Target | None = None, camera_names: Iterable[str] | None = None
) -> tuple[Observation, ...]:
    """Read and validate ``observations.json``.

    Checks each record (camera, set, pose/frame, added_mm for stacking, finite stage_mm, integer ids
    unique in the record, finite (N, 2) pixels, one pixel per id), that no (camera, set, frame, added_mm)
    appears twice and, when given, that ids belong to ``target`` and cameras to ``camera_names``.

    Args:
        path: the file.
        target: the target the ids must belong to; None: not checked.
        camera_names: the cameras the records may name; None: not checked.

    Returns:
        The observations, in file order.

    Raises:
        AriSfmError: the file cannot be read or a record is invalid (one line naming it).
    """
    path = Path(path)
    return parse_observations(read_structured(path), path, target, camera_names)


def observations_to_json(observations: Sequence[Observation]) -> dict:
    """The ``observations.json`` mapping (``pose`` for stacking, ``frame`` otherwise; full precision)."""
    records = []
    for obs in observations:
        rec: dict[str, Any] = {"camera": obs.camera, "set": obs.set, frame_key(obs.set): obs.frame}
        if obs.added_mm is not None:
            rec["added_mm"] = obs.added_mm
        if obs.stage_mm is not None:
            rec["stage_mm"] = obs.stage_mm
        rec["ids"] = np.asarray(obs.ids).reshape(-1)
        rec["pixels"] = _pixels_array(obs.pixels)
        records.append(rec)
    return {"format": FORMAT, "observations": records}


def _pixels_array(pixels: Any) -> Any:
    """Pixels as an (N, 2) float array where they can be one (else as given, for the validator)."""
    try:
        arr = np.asarray(pixels, dtype=float)
    except (TypeError, ValueError):
        return pixels
    return arr.reshape(-1, 2) if arr.size == 0 else arr


def save_observations(path: str | Path, observations: Sequence[Observation], dataset: str | Path | None = None
                      ) -> None:
    """Validate and write ``observations.json`` atomically.

    Args:
        path: the file to write.
        observations: the corners.
        dataset: the rig file the corners were detected from, recorded (absolute) as the file's
            ``dataset``; None: not recorded.

    Raises:
        AriSfmError: a bad record (nothing is written), or the file cannot be written.
    """
    path = Path(path)
    data = observations_to_json(observations)
    parse_observations(data, path)  # refuse to write a file we would not read back
    if dataset is not None:
        data["dataset"] = os.path.abspath(dataset)
    write_json_atomic(path, data)


def recorded_dataset(path: str | Path) -> Path | None:
    """Read which rig file an ``observations.json`` says its corners were detected from.

    Args:
        path: the observations file.

    Returns:
        The absolute rig file path it records, or None (not recorded, or the file unreadable).
    """
    try:
        given = json.loads(Path(path).read_text()).get("dataset")
    except (OSError, ValueError, AttributeError):
        return None
    return Path(given) if isinstance(given, str) and Path(given).is_absolute() else None

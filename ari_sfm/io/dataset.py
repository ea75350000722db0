"""A dataset folder: ``rig.yaml`` / ``rig.yml`` / ``rig.json`` (format ``ari-sfm/1``), read and written.

:func:`load_dataset` validates everything (see DATASET_FORMAT.md) and raises
AriSfmError naming the file and the key at fault. :func:`dump_rig` and
:func:`save_rig` write a :class:`~ari_sfm.records.Dataset` back, so a
simulator can produce datasets that load to equal records.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ari_sfm.errors import AriSfmError
from ari_sfm.io.atomic import to_jsonable, write_json_atomic, write_text_atomic
from ari_sfm.io.observations import (
    check_format,
    check_pixels_in_images,
    describe,
    load_observations,
    observations_to_json,
    parse_observations,
)
from ari_sfm.io.structured import (
    as_finite_float,
    as_float_array,
    as_float_at_least,
    as_int_pair,
    as_list,
    as_mapping,
    as_name,
    as_nonnegative_float,
    as_positive_float,
    as_str,
    check_at_most,
    key_path,
    read_structured,
    require,
    show,
    warn_unknown_keys,
)
from ari_sfm.records import (
    SETS,
    CameraSpec,
    Dataset,
    Entry,
    Interface,
    Observation,
    Target,
    Window,
    WindowPlane,
    check_windows,
)

log = logging.getLogger(__name__)

FORMAT = "ari-sfm/1"
RIG_NAMES = ("rig.yaml", "rig.yml", "rig.json")
TARGET_TYPES = ("checkerboard", "charuco", "circles", "points3d")
CIRCLE_LAYOUTS = ("symmetric", "asymmetric")
DIST_LENGTHS = (4, 5, 8, 12, 14)
# particles: io/particles.py
TOP_KEYS = ("format", "target", "interface", "interfaces", "cameras", *SETS, "observations", "particles")
TARGET_KEYS = {
    "checkerboard": ("type", "inner_corners", "square_mm"),
    "charuco": ("type", "squares", "square_mm", "marker_mm", "dictionary"),
    "circles": ("type", "grid", "spacing_mm", "layout", "diameter_mm"),
    "points3d": ("type", "points", "diameter_mm"),
}
INTERFACE_KEYS = ("thickness_mm", "index", "medium_index", "distance_mm", "plane")
WINDOW_KEYS = ("cameras", *INTERFACE_KEYS)  # an entry of ``interfaces`` (1.3)
PLANE_KEYS = ("frame", "normal", "point_mm", "sigma_deg", "sigma_mm")
CAMERA_KEYS = ("image_size", "focal_px", "K", "dist")
ENTRY_KEYS = ("pose", "frame", "added_mm", "stage_mm", "images", "window", "manual_points")
MIN_MANUAL_POINTS = 4  # clicked body points per camera: a camera's pose and focal length need >= 4

# Sane physical bounds: a value beyond one is a typo (1e300, 1e8), refused in one line naming the key.
MAX_LENGTH_MM = 10_000.0  # thickness_mm, distance_mm, square_mm, added_mm, |stage_mm|: at most 10 m
MAX_IMAGE_SIDE_PX = 100_000  # image_size width and height
MAX_FOCAL_PX = 10_000_000.0  # focal_px, K fx and fy
MAX_INDEX = 5.0  # refractive indices (germanium, the highest common optical glass, is ~4)
MIN_LENGTH_MM = 1e-3  # thickness_mm, distance_mm, square_mm, spacing_mm: 1 um (1e-9 failed as a
MIN_FOCAL_PX = 1.0  # focal_px, K fx and fy          "non-finite Jacobian ... corner behind the window")

# cv2.aruco predefined dictionaries and their marker counts (OpenCV 4.x / 5.x).
ARUCO_DICTIONARIES: dict[str, int] = {
    **{f"DICT_{b}X{b}_{n}": n for b in (4, 5, 6, 7) for n in (50, 100, 250, 1000)},
    "DICT_ARUCO_ORIGINAL": 1024,
    "DICT_APRILTAG_16h5": 30,
    "DICT_APRILTAG_25h9": 35,
    "DICT_APRILTAG_36h10": 2320,
    "DICT_APRILTAG_36h11": 587,
    "DICT_ARUCO_MIP_36h12": 250,
}
ARUCO_DICTIONARIES.update({k.upper(): v for k, v in list(ARUCO_DICTIONARIES.items())})  # cv2 has both spellings


# --------------------------------------------------------------------------- reading


def find_rig(path: str | Path) -> Path:
    """The rig file of a dataset folder, or ``path`` itself if it is a file."""
    path = Path(path)
    if path.is_file():
        if path.suffix.lower() not in (".yaml", ".yml", ".json") and not _is_text(path):
            raise AriSfmError(path, "not a dataset: expected a dataset folder (with rig.yaml) or a rig file, "
                                    "got a binary file (an image?)")
        return path
    if not path.exists():
        raise AriSfmError(path, "no such dataset folder or rig file")
    if not path.is_dir():
        raise AriSfmError(path, "not a dataset folder or rig file (a device, pipe or socket)")
    found = [path / name for name in RIG_NAMES if (path / name).is_file()]
    if not found:
        raise AriSfmError(path, f"no {', '.join(RIG_NAMES[:-1])} or {RIG_NAMES[-1]} in this folder")
    if len(found) > 1:
        names = " and ".join(p.name for p in found)
        raise AriSfmError(path, f"both {names} in this folder: pass the rig file to use")
    return found[0]


def _is_text(path: Path) -> bool:
    """True if the file's first 4 KB are UTF-8 text without NUL bytes (unreadable: True, the reader says why)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return True
    if b"\0" in head:
        return False
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        return exc.start >= len(head) - 3  # a character cut at the 4 KB boundary
    return True


def parse_target(data: Any, path: Path, where: str = "target") -> Target:
    """Parse and check a ``target`` mapping.

    Args:
        data: the mapping, as read from the file.
        path: the rig file, for error messages.
        where: the key path of ``data`` in the file, for error messages.

    Returns:
        The target, its geometry checked.

    Raises:
        AriSfmError: a key is missing or a value is invalid (one line naming the key).
    """
    data = as_mapping(data, path, where)
    kind = require(data, "type", path, where)
    if kind not in TARGET_TYPES:
        raise AriSfmError(path, f"unknown {where}.type {show(kind)} (expected {', '.join(TARGET_TYPES)})")

    warn_unknown_keys(data, TARGET_KEYS[kind], path, where)

    def get(key: str) -> Any:
        return require(data, key, path, where)

    if kind == "checkerboard":
        corners = _grid(get("inner_corners"), path, f"{where}.inner_corners")
        return Target(
            type=kind, inner_corners=corners, square_mm=_length(get("square_mm"), path, f"{where}.square_mm")
        )
    if kind == "charuco":
        squares = _grid(get("squares"), path, f"{where}.squares")
        square = _length(get("square_mm"), path, f"{where}.square_mm")
        marker = as_positive_float(get("marker_mm"), path, f"{where}.marker_mm")
        if marker >= square:
            raise AriSfmError(path, f"{where}.marker_mm must be < square_mm ({marker:g} >= {square:g})")
        dictionary = as_str(get("dictionary"), path, f"{where}.dictionary")
        if dictionary not in ARUCO_DICTIONARIES:
            raise AriSfmError(path, f"unknown {where}.dictionary {dictionary!r} (expected a cv2.aruco DICT_* name such "
                                    "as DICT_4X4_50)")
        markers = squares[0] * squares[1] // 2
        if ARUCO_DICTIONARIES[dictionary] < markers:
            raise AriSfmError(
                path,
                f"{where}.dictionary {dictionary} has {ARUCO_DICTIONARIES[dictionary]} markers, "
                f"a {squares[0]} x {squares[1]} board needs {markers}",
            )
        return Target(type=kind, squares=squares, square_mm=square, marker_mm=marker, dictionary=dictionary)
    if kind == "circles":
        return _parse_circles(data, get, path, where)
    points = as_mapping(get("points"), path, f"{where}.points")
    if not points:
        raise AriSfmError(path, f"{where}.points must not be empty")
    out: dict[int, tuple[float, float, float]] = {}
    for raw_id, xyz in points.items():
        pid = _point_id(raw_id, path, f"{where}.points")
        if pid in out:
            raise AriSfmError(path, f"{where}.points: duplicate id {pid}")
        arr = as_float_array(xyz, path, f"{where}.points[{pid}]", (3,))
        out[pid] = (float(arr[0]), float(arr[1]), float(arr[2]))
    diameter = data.get("diameter_mm")  # 1.3: the dots' size, a hint for finding them in images
    diameter = None if diameter is None else _length(diameter, path, f"{where}.diameter_mm")
    return Target(type=kind, points=out, diameter_mm=diameter)


def _parse_circles(data: Mapping[str, Any], get: Any, path: Path, where: str) -> Target:
    """A dot board (1.1): grid [cols, rows] >= 2, spacing_mm > 0, layout, optional diameter_mm.

    The dots must not touch: diameter < spacing (the nearest neighbours of an
    asymmetric grid are spacing x sqrt(2) apart, of a symmetric one spacing).
    """
    grid = _grid(get("grid"), path, f"{where}.grid")
    spacing = _length(get("spacing_mm"), path, f"{where}.spacing_mm")
    layout = as_str(get("layout"), path, f"{where}.layout")
    if layout not in CIRCLE_LAYOUTS:
        raise AriSfmError(path, f"unknown {where}.layout {layout!r} (expected {' or '.join(CIRCLE_LAYOUTS)})")
    diameter = data.get("diameter_mm")
    if diameter is not None:
        diameter = as_positive_float(diameter, path, f"{where}.diameter_mm")
        if diameter >= spacing:
            raise AriSfmError(path, f"{where}.diameter_mm must be < spacing_mm ({diameter:g} >= {spacing:g}): the dots "
                                    "would touch")
    return Target(type="circles", circle_grid=grid, spacing_mm=spacing, layout=layout, diameter_mm=diameter)


MAX_GRID_POINTS = 1_000_000  # a board with more corners is a typo, not a target


def _grid(value: Any, path: Path, where: str) -> tuple[int, int]:
    """[cols, rows] of a board: two integers >= 2, at most MAX_GRID_POINTS in all."""
    cols, rows = as_int_pair(value, path, where, minimum=2)
    if cols * rows > MAX_GRID_POINTS:
        raise AriSfmError(path, f"{where} {[cols, rows]} is too large (at most {MAX_GRID_POINTS} points)")
    return cols, rows


def _point_id(raw: Any, path: Path, where: str) -> int:
    """A points3d id: an integer, or a string of one (JSON object keys are strings)."""
    if isinstance(raw, (int, np.integer)) and not isinstance(raw, bool):
        return int(raw)
    if isinstance(raw, str):
        try:
            return int(raw.strip())
        except ValueError:
            pass
    raise AriSfmError(path, f"{where}: ids must be integers (got {show(raw)})")


def parse_interface(data: Any, path: Path, where: str = "interface", keys: tuple[str, ...] = INTERFACE_KEYS
                    ) -> Interface:
    """Parse and check an ``interface`` mapping (or one entry of ``interfaces``).

    Args:
        data: the mapping, as read from the file.
        path: the rig file, for error messages.
        where: the key path of ``data`` in the file, for error messages.
        keys: the keys the mapping may have (others are warned about).

    Returns:
        The window's plate.

    Raises:
        AriSfmError: a key is missing or a value is invalid (one line naming the key).
    """
    data = as_mapping(data, path, where)
    warn_unknown_keys(data, keys, path, where)
    thickness = _length(require(data, "thickness_mm", path, where), path, f"{where}.thickness_mm")
    index = _index(require(data, "index", path, where), path, f"{where}.index")
    medium = data.get("medium_index")
    medium = 1.0 if medium is None else _index(medium, path, f"{where}.medium_index")
    distance = data.get("distance_mm")
    distance = None if distance is None else _length(distance, path, f"{where}.distance_mm")
    plane = data.get("plane")
    plane = None if plane is None else parse_window_plane(plane, path, f"{where}.plane")
    return Interface(thickness_mm=thickness, index=index, medium_index=medium, distance_mm=distance, plane=plane)


def parse_windows(data: Any, path: Path, cameras: Mapping[str, CameraSpec]) -> tuple[Window, ...]:
    """Parse and check an ``interfaces`` mapping (1.3): name -> a window's plate and its ``cameras``.

    Every camera of ``cameras`` must be behind exactly one window, with one medium behind all of them.

    Args:
        data: the mapping, as read from the file.
        path: the rig file, for error messages.
        cameras: the rig's cameras.

    Returns:
        The windows, in file order.

    Raises:
        AriSfmError: a key is missing or a value is invalid (one line naming the key).
    """
    data = as_mapping(data, path, "interfaces")
    if not data:
        raise AriSfmError(path, "interfaces must declare at least one window")
    windows = []
    for raw_name, item in data.items():
        name = as_name(raw_name, path, "interfaces name")
        where = key_path("interfaces", name)
        item = as_mapping(item, path, where)
        listed = as_list(require(item, "cameras", path, where), path, f"{where}.cameras")
        names = tuple(as_name(c, path, f"{where}.cameras") for c in listed)
        for c in names:
            if c not in cameras:
                raise AriSfmError(path, f"{where}.cameras: camera '{c}' is not declared in cameras "
                                        f"({', '.join(cameras)})")
        if len(set(names)) != len(names):
            raise AriSfmError(path, f"{where}.cameras lists a camera twice")
        windows.append(Window(name, parse_interface(item, path, where, WINDOW_KEYS), names))
    try:
        check_windows(tuple(windows), list(cameras))
    except ValueError as exc:
        raise AriSfmError(path, f"interfaces: {exc}") from None
    return tuple(windows)


def _length(value: Any, path: Path, where: str) -> float:
    """A length in mm: > 0, at least MIN_LENGTH_MM and at most MAX_LENGTH_MM."""
    return check_at_most(check_at_least(as_positive_float(value, path, where), MIN_LENGTH_MM, path, where, " mm"),
                         MAX_LENGTH_MM, path, where, " mm")


def check_at_least(value: float, limit: float, path: str | Path, where: str, unit: str = "") -> float:
    """Hold a value to a sane physical lower bound.

    Args:
        value: the value.
        limit: the least value allowed.
        path: the file, for error messages.
        where: the value's key, for error messages.
        unit: the unit appended to the numbers in the message (e.g. ``" mm"``).

    Returns:
        ``value`` itself.

    Raises:
        AriSfmError: ``value`` < ``limit``, naming ``where``.
    """
    if value < limit:
        raise AriSfmError(path, f"{where} must be >= {limit:g}{unit} (got {value:g}): not a physical value")
    return value


def _index(value: Any, path: Path, where: str) -> float:
    """A refractive index: >= 1 and at most MAX_INDEX."""
    return check_at_most(as_float_at_least(value, path, where, 1.0), MAX_INDEX, path, where)


def parse_window_plane(data: Any, path: Path, where: str = "interface.plane") -> WindowPlane:
    """Parse and check an ``interface.plane`` mapping (1.1).

    The mapping holds a frame, a unit normal, a point of the camera-side face and optional sigmas (absent
    or 0: held fixed).

    Args:
        data: the mapping, as read from the file.
        path: the rig file, for error messages.
        where: the key path of ``data`` in the file, for error messages.

    Returns:
        The declared window pose (its normal normalised).

    Raises:
        AriSfmError: a key is missing or a value is invalid (one line naming the key).
    """
    data = as_mapping(data, path, where)
    warn_unknown_keys(data, PLANE_KEYS, path, where)
    frame = as_name(require(data, "frame", path, where), path, f"{where}.frame")
    normal = as_float_array(require(data, "normal", path, where), path, f"{where}.normal", (3,))
    norm = float(np.linalg.norm(normal))
    if not 0.999 <= norm <= 1.001:
        raise AriSfmError(path, f"{where}.normal must be a unit vector (got length {norm:.6g})")
    point = as_float_array(require(data, "point_mm", path, where), path, f"{where}.point_mm", (3,))
    sigmas = {}
    for key in ("sigma_deg", "sigma_mm"):
        value = data.get(key)
        sigmas[key] = 0.0 if value is None else as_nonnegative_float(value, path, f"{where}.{key}")
    return WindowPlane(frame, normal / norm, point, sigmas["sigma_deg"], sigmas["sigma_mm"])


def parse_camera(name: str, data: Any, path: Path, where: str) -> CameraSpec:
    """Parse and check one ``cameras`` entry.

    The entry holds image_size [width, height] and optional hints focal_px, K, dist.

    Args:
        name: the camera's name.
        data: the entry, as read from the file.
        path: the rig file, for error messages.
        where: the key path of ``data`` in the file, for error messages.

    Returns:
        The camera as declared.

    Raises:
        AriSfmError: a key is missing or a value is invalid (one line naming the key).
    """
    data = as_mapping(data, path, where)
    warn_unknown_keys(data, CAMERA_KEYS, path, where)
    size = as_int_pair(require(data, "image_size", path, where), path, f"{where}.image_size", minimum=1)
    check_at_most(max(size), MAX_IMAGE_SIDE_PX, path, f"{where}.image_size", " px")
    focal = data.get("focal_px")
    focal = None if focal is None else check_at_most(
        check_at_least(as_positive_float(focal, path, f"{where}.focal_px"), MIN_FOCAL_PX, path, f"{where}.focal_px",
                       " px"),
        MAX_FOCAL_PX, path, f"{where}.focal_px", " px")
    K = None
    if data.get("K") is not None:
        K = as_float_array(data["K"], path, f"{where}.K", (3, 3))
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise AriSfmError(path, f"{where}.K must have positive focal lengths (got fx={K[0, 0]:g}, fy={K[1, 1]:g})")
        check_at_most(float(max(K[0, 0], K[1, 1])), MAX_FOCAL_PX, path, f"{where}.K focal length", " px")
        check_at_least(float(min(K[0, 0], K[1, 1])), MIN_FOCAL_PX, path, f"{where}.K focal length", " px")
        if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9, rtol=0):
            raise AriSfmError(path, f"{where}.K last row must be [0, 0, 1] (got {show(K[2])})")
    dist = None
    if data.get("dist") is not None:
        dist = as_float_array(data["dist"], path, f"{where}.dist", (-1,))
        if len(dist) not in DIST_LENGTHS:
            raise AriSfmError(path, f"{where}.dist must have 4, 5, 8, 12 or 14 numbers (got {len(dist)})")
    return CameraSpec(name=name, image_size=size, focal_px=focal, K=K, dist=dist)


def parse_cameras(data: Any, path: Path, where: str = "cameras") -> dict[str, CameraSpec]:
    """Parse and check the ``cameras`` mapping (non-empty).

    Args:
        data: the mapping, as read from the file.
        path: the rig file, for error messages.
        where: the key path of ``data`` in the file, for error messages.

    Returns:
        Name -> :class:`CameraSpec`, in file order.

    Raises:
        AriSfmError: no camera, a camera declared twice, or an invalid entry (one line naming the key).
    """
    data = as_mapping(data, path, where)
    if not data:
        raise AriSfmError(path, f"{where} must declare at least one camera")
    out: dict[str, CameraSpec] = {}
    for raw_name, spec in data.items():
        name = as_name(raw_name, path, f"{where} name")
        if name in out:
            raise AriSfmError(path, f"{where}: camera '{name}' declared twice")
        out[name] = parse_camera(name, spec, path, key_path(where, name))
    return out


def parse_entries(
    data: Any, set_name: str, path: Path, root: Path, cameras: Mapping[str, CameraSpec], check_files: bool = True,
    windows: tuple[Window, ...] = (), target: Target | None = None,
) -> tuple[Entry, ...]:
    """Parse and check one of the ``stacking`` / ``calibration`` / ``reconstruction`` lists.

    With several windows a stacking entry names the window its plates were added to (``window``, 1.3).

    Args:
        data: the list, as read from the file (null or absent: empty).
        set_name: ``stacking``, ``calibration`` or ``reconstruction``.
        path: the rig file, for error messages.
        root: the folder image paths are relative to; they are made absolute.
        cameras: the rig's cameras.
        check_files: the images must exist.
        windows: the rig's windows when it has several (1.3); () for one window.
        target: the rig's target, to check ``manual_points`` ids against (1.3); None: not checked.

    Returns:
        The entries, in file order.

    Raises:
        AriSfmError: an invalid or repeated entry, a missing image (one line naming the key).
    """
    if data is None:
        return ()
    items = as_list(data, path, set_name)
    key = "pose" if set_name == "stacking" else "frame"
    seen: dict[tuple, int] = {}
    out: list[Entry] = []
    for i, item in enumerate(items):
        where = f"{set_name}[{i}]"
        item = as_mapping(item, path, where)
        warn_unknown_keys(item, ENTRY_KEYS, path, where)
        name = as_name(require(item, key, path, where), path, f"{where}.{key}")
        ctx = f"{where} ({key} {name})"
        if set_name == "stacking":
            added = check_at_most(as_nonnegative_float(require(item, "added_mm", path, where), path,
                                                       f"{where}.added_mm"),
                                  MAX_LENGTH_MM, path, f"{where}.added_mm", " mm")
        elif item.get("added_mm") is not None:
            raise AriSfmError(path, f"{ctx}: added_mm is only for stacking entries")
        else:
            added = None
        stage = item.get("stage_mm")
        stage = None if stage is None else as_finite_float(stage, path, f"{where}.stage_mm")
        if stage is not None:
            check_at_most(abs(stage), MAX_LENGTH_MM, path, f"|{where}.stage_mm|", " mm")
        ident = (name, added)
        if ident in seen:
            extra = f" with added_mm {added:g}" if added is not None else ""
            raise AriSfmError(path, f"{ctx}: {key} '{name}'{extra} is already listed in {set_name}[{seen[ident]}]")
        seen[ident] = i
        images = _parse_images(item.get("images"), path, root, cameras, f"{where}.images", ctx, check_files)
        window = _entry_window(item, set_name, images, windows, path, where, ctx)
        manual = {}
        if item.get("manual_points") is not None:
            if set_name != "calibration":
                raise AriSfmError(path, f"{where}.manual_points: clicked points are for calibration entries only")
            manual = parse_manual_points(item["manual_points"], path, f"{where}.manual_points", cameras, target)
            for cam in manual:
                if images and cam not in images:
                    log.warning("%s: %s.manual_points.%s: the entry has no image of %s, its clicks are not used",
                                path, where, cam, cam)
        out.append(Entry(set=set_name, key=name, images=images, added_mm=added, stage_mm=stage, window=window,
                         manual_points=manual))
    return tuple(out)


def _entry_window(item: Mapping[str, Any], set_name: str, images: Mapping[str, Path], windows: tuple[Window, ...],
                  path: Path, where: str, ctx: str) -> str | None:
    """A stacking entry's ``window`` (1.3): required with several windows (unless its images name it), checked
    against the cameras whose images it lists; refused elsewhere."""
    raw = item.get("window")
    if raw is None:
        if set_name != "stacking" or len(windows) < 2:
            return None
        behind = {w.name for w in windows for c in images if c in w.cameras}
        if len(behind) == 1:
            return behind.pop()
        raise AriSfmError(path, f"{ctx}: with several windows a stacking entry names its window (window: "
                                f"{' | '.join(w.name for w in windows)})")
    name = as_name(raw, path, f"{where}.window")
    if set_name != "stacking":
        raise AriSfmError(path, f"{ctx}: window is only for stacking entries")
    known = [w.name for w in windows]
    if len(windows) < 2:
        raise AriSfmError(path, f"{ctx}: window names one of several windows (interfaces), and this rig has one")
    if name not in known:
        raise AriSfmError(path, f"{ctx}: window '{name}' is not declared in interfaces ({', '.join(known)})")
    window = next(w for w in windows if w.name == name)
    outside = [c for c in images if c not in window.cameras]
    if outside:
        raise AriSfmError(path, f"{ctx}: camera {outside[0]} is not behind window {name}: the plates added to a "
                                "window are seen by its own cameras")
    return name


def parse_manual_points(data: Any, path: Path, where: str, cameras: Mapping[str, CameraSpec],
                        target: Target | None) -> dict[str, dict[int, tuple[float, float]]]:
    """Parse and check a calibration entry's ``manual_points`` (1.3): {camera: {point id: [u, v]}}.

    Each camera must be declared, each id a point of the ``points3d`` target, each pixel (OpenCV
    convention) finite and inside the camera's image (its edges at -0.5 and size - 0.5), and each camera
    must have at least MIN_MANUAL_POINTS points.

    Args:
        data: the mapping, as read from the file.
        path: the rig file, for error messages.
        where: the key path of ``data`` in the file, for error messages.
        cameras: the rig's cameras.
        target: the rig's target (must be ``points3d``); None: ids not checked.

    Returns:
        {camera: {point id: (u, v)}} in OpenCV pixels.

    Raises:
        AriSfmError: any of the conditions fails (one line naming the key).
    """
    data = as_mapping(data, path, where)
    if target is not None and target.type != "points3d":
        raise AriSfmError(path, f"{where}: clicked points identify a 3D body (target type points3d), "
                                f"not a {target.type} target")
    known = set(target.points or ()) if target is not None else None
    out: dict[str, dict[int, tuple[float, float]]] = {}
    for raw_cam, points in data.items():
        cam = as_name(raw_cam, path, f"{where} camera name")
        if cam not in cameras:
            raise AriSfmError(path, f"{where}.{cam}: camera '{cam}' is not declared in cameras ({', '.join(cameras)})")
        here = key_path(where, cam)
        points = as_mapping(points, path, here)
        width, height = cameras[cam].image_size
        clicks: dict[int, tuple[float, float]] = {}
        for raw_id, uv in points.items():
            pid = _point_id(raw_id, path, here)
            if pid in clicks:
                raise AriSfmError(path, f"{here}: point {pid} given twice")
            if known is not None and pid not in known:
                raise AriSfmError(path, f"{here}: id {pid} is not a point of the target")
            u, v = as_float_array(uv, path, f"{here}[{pid}]", (2,))
            if not (-0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5):
                raise AriSfmError(path, f"{here}[{pid}]: pixel ({u:g}, {v:g}) is outside the {width} x {height} image")
            clicks[pid] = (float(u), float(v))
        if len(clicks) < MIN_MANUAL_POINTS:
            raise AriSfmError(path, f"{here}: {len(clicks)} clicked points, need >= {MIN_MANUAL_POINTS} (a camera's "
                                    "pose and focal length)")
        out[cam] = clicks
    return out


def _parse_images(
    data: Any, path: Path, root: Path, cameras: Mapping[str, CameraSpec], where: str, ctx: str, check_files: bool
) -> dict[str, Path]:
    if data is None:
        return {}
    data = as_mapping(data, path, where)
    images: dict[str, Path] = {}
    for raw_cam, rel in data.items():
        cam = as_name(raw_cam, path, f"{where} camera name")
        if cam not in cameras:
            raise AriSfmError(path, f"{ctx}: images name camera '{cam}', which is not declared in cameras "
                                    f"({', '.join(cameras)})")
        rel = as_str(rel, path, f"{where}.{cam}")
        image = Path(os.path.abspath(root / rel))
        if check_files and not image.is_file():
            raise AriSfmError(path, f"{ctx}: image of {cam} not found: {rel}")
        images[cam] = image
    return images


def parse_rig(data: Any, rig_path: Path, check_files: bool = True) -> dict[str, Any]:
    """Validate a parsed rig mapping.

    Args:
        data: the rig mapping, as read from the file.
        rig_path: the rig file; its folder is the dataset's root.
        check_files: the images named must exist.

    Returns:
        The :class:`~ari_sfm.records.Dataset` fields except ``observations``; ``observations_path`` is the
        absolute path the rig names (or None).

    Raises:
        AriSfmError: the rig is invalid (one line naming the key).
    """
    rig_path = Path(os.path.abspath(rig_path))
    root = rig_path.parent
    as_mapping(data, rig_path, "")
    warn_unknown_keys(data, TOP_KEYS, rig_path)
    check_format(data, rig_path, FORMAT)
    target = parse_target(require(data, "target", rig_path), rig_path)
    cameras = parse_cameras(require(data, "cameras", rig_path), rig_path)
    interface, windows = parse_window_keys(data, rig_path, cameras)
    fields: dict[str, Any] = dict(root=root, rig_path=rig_path, target=target, interface=interface, cameras=cameras,
                                  windows=windows)
    for set_name in SETS:
        fields[set_name] = parse_entries(data.get(set_name), set_name, rig_path, root, cameras, check_files, windows,
                                         target)
    obs = data.get("observations")
    fields["observations_path"] = None if obs is None else Path(
        os.path.abspath(root / as_str(obs, rig_path, "observations"))
    )
    return fields


def parse_window_keys(data: Mapping[str, Any], rig_path: Path, cameras: Mapping[str, CameraSpec]
                      ) -> tuple[Interface, tuple[Window, ...]]:
    """Parse a rig mapping's window keys: ``interface`` or ``interfaces`` (1.3), never both.

    Args:
        data: the rig mapping.
        rig_path: the rig file, for error messages.
        cameras: the rig's cameras.

    Returns:
        (interface, windows): with ``interface`` (or ``interfaces`` of one window) the one window for every
        camera and windows (); with several windows the first window's interface and every window.

    Raises:
        AriSfmError: both keys, neither, or an invalid window (one line naming the key).
    """
    if "interface" in data and "interfaces" in data:
        raise AriSfmError(rig_path, "give interface (one window for every camera) or interfaces (several "
                                    "windows), not both")
    if "interfaces" not in data:
        return parse_interface(require(data, "interface", rig_path), rig_path), ()
    windows = parse_windows(data["interfaces"], rig_path, cameras)
    if len(windows) == 1:  # one window for every camera, written the 1.3 way: the same as `interface`
        return windows[0].interface, ()
    return windows[0].interface, windows


def check_observations(dataset: Dataset) -> None:
    """Cross-check a dataset's observations with its rig.

    Pixels lie inside their camera's image; every entry without images has observations. (Cameras and
    ids are checked by :func:`load_observations`.) A record of a frame (stacking: pose and added_mm) that
    the rig does not list is an error when the rig lists entries of that set (a typo would split one pose
    in two); a set the rig does not list at all is taken from the observations alone (a dataset may hold
    only observations.json).

    Args:
        dataset: the loaded dataset.

    Raises:
        AriSfmError: a check fails, naming the file.
    """
    obs = dataset.observations or ()
    obs_path = dataset.observations_path or dataset.rig_path
    check_pixels_in_images(obs, {n: c.image_size for n, c in dataset.cameras.items()}, obs_path)
    check_frames_declared(dataset)
    have = {(o.set, o.frame, o.added_mm) for o in obs}
    stage = {(o.set, o.frame): o.stage_mm for o in obs if o.stage_mm is not None}
    for entry in dataset.entries():
        if not entry.images and (entry.set, entry.key, entry.added_mm) not in have:
            key = "pose" if entry.set == "stacking" else "frame"
            extra = f" added_mm {entry.added_mm:g}" if entry.added_mm is not None else ""
            if dataset.observations is None:
                why = "the rig names no observations file"
                if (dataset.root / "observations.json").is_file():
                    why += " (observations.json is in the folder: add 'observations: observations.json')"
            else:
                why = f"{Path(obs_path).name} has no record of it"
            raise AriSfmError(dataset.rig_path, f"{entry.set} {key} {entry.key}{extra} has no images and {why}")
        seen_stage = stage.get((entry.set, entry.key))
        if entry.stage_mm is not None and seen_stage is not None and seen_stage != entry.stage_mm:
            log.warning(
                "%s: %s %s has stage_mm %g in the rig but %g in the observations",
                dataset.rig_path, entry.set, entry.key, entry.stage_mm, seen_stage,
            )


def check_frames_declared(dataset: Dataset) -> None:
    """Every observation of a set the rig lists names a frame (or stacking pose and added_mm) it lists."""
    obs_path = dataset.observations_path or dataset.rig_path
    for set_name in SETS:
        entries = getattr(dataset, set_name)
        if not entries:
            continue
        declared = {(e.key, e.added_mm) for e in entries}
        for i, o in enumerate(dataset.observations or ()):
            if o.set == set_name and (o.frame, o.added_mm) not in declared:
                key = "pose" if set_name == "stacking" else "frame"
                extra = f" with added_mm {o.added_mm:g}" if o.added_mm is not None else ""
                raise AriSfmError(obs_path, f"observation {i} ({describe(o)}): {key} '{o.frame}'{extra} is not "
                                            f"listed in {set_name} of {dataset.rig_path} (a typo? declare it there)")


def load_dataset(path: str | Path, observations: str | Path | None = None) -> Dataset:
    """Load and validate a dataset folder (with rig.yaml, rig.yml or rig.json) or rig file.

    Args:
        path: the dataset folder or the rig file.
        observations: an observations file that replaces the one the rig names; None: the rig's.

    Returns:
        The dataset, with its observations when a file is named (else ``observations`` None: detect from
        the images).

    Raises:
        AriSfmError: naming the file and the problem.
    """
    rig_path = find_rig(path)
    fields = parse_rig(read_structured(rig_path), rig_path)
    if observations is not None:
        fields["observations_path"] = Path(os.path.abspath(observations))
    obs: tuple[Observation, ...] | None = None
    if fields["observations_path"] is not None:
        obs = load_observations(fields["observations_path"], fields["target"], fields["cameras"])
    dataset = Dataset(observations=obs, **fields)
    check_observations(dataset)
    return dataset


# --------------------------------------------------------------------------- writing


def target_to_json(target: Target) -> dict[str, Any]:
    """The ``target`` mapping of a rig file."""
    if target.type == "checkerboard":
        return {"type": target.type, "inner_corners": list(target.inner_corners or ()), "square_mm": target.square_mm}
    if target.type == "charuco":
        return {
            "type": target.type,
            "squares": list(target.squares or ()),
            "square_mm": target.square_mm,
            "marker_mm": target.marker_mm,
            "dictionary": target.dictionary,
        }
    if target.type == "circles":
        out = {"type": target.type, "grid": list(target.circle_grid or ()), "spacing_mm": target.spacing_mm,
               "layout": target.layout}
        if target.diameter_mm is not None:
            out["diameter_mm"] = target.diameter_mm
        return out
    out = {"type": target.type, "points": {int(k): list(v) for k, v in (target.points or {}).items()}}
    if target.diameter_mm is not None:
        out["diameter_mm"] = target.diameter_mm
    return out


def interface_to_json(interface: Interface) -> dict[str, Any]:
    """The ``interface`` mapping of a rig file."""
    out: dict[str, Any] = {
        "thickness_mm": interface.thickness_mm,
        "index": interface.index,
        "medium_index": interface.medium_index,
    }
    if interface.distance_mm is not None:
        out["distance_mm"] = interface.distance_mm
    plane = interface.plane
    if plane is not None:
        out["plane"] = {"frame": plane.frame, "normal": [float(x) for x in plane.normal],
                        "point_mm": [float(x) for x in plane.point_mm]}
        if plane.sigma_deg > 0:
            out["plane"]["sigma_deg"] = plane.sigma_deg
        if plane.sigma_mm > 0:
            out["plane"]["sigma_mm"] = plane.sigma_mm
    return out


def windows_to_json(dataset: Dataset) -> dict[str, Any]:
    """``{"interface": ...}`` of a one-window rig, ``{"interfaces": {name: ...}}`` of several (1.3)."""
    if not dataset.windows:
        return {"interface": interface_to_json(dataset.interface)}
    return {"interfaces": {w.name: {"cameras": list(w.cameras), **interface_to_json(w.interface)}
                           for w in dataset.windows}}


def camera_to_json(camera: CameraSpec) -> dict[str, Any]:
    """One ``cameras`` entry of a rig file (hints only where set)."""
    out: dict[str, Any] = {"image_size": list(camera.image_size)}
    if camera.focal_px is not None:
        out["focal_px"] = camera.focal_px
    if camera.K is not None:
        out["K"] = np.asarray(camera.K, dtype=float).tolist()
    if camera.dist is not None:
        out["dist"] = np.asarray(camera.dist, dtype=float).reshape(-1).tolist()
    return out


def _relative(path: Path, root: Path) -> str:
    return Path(os.path.relpath(os.path.abspath(path), os.path.abspath(root))).as_posix()


def entry_to_json(entry: Entry, root: Path) -> dict[str, Any]:
    """Write one stacking / calibration / reconstruction item of a rig file.

    Args:
        entry: the entry.
        root: the folder image paths are written relative to.

    Returns:
        The item's mapping.
    """
    out: dict[str, Any] = {"pose" if entry.set == "stacking" else "frame": entry.key}
    if entry.added_mm is not None:
        out["added_mm"] = entry.added_mm
    if entry.stage_mm is not None:
        out["stage_mm"] = entry.stage_mm
    if entry.images:
        out["images"] = {cam: _relative(Path(p), root) for cam, p in entry.images.items()}
    if entry.window is not None:
        out["window"] = entry.window
    if entry.manual_points:
        out["manual_points"] = {cam: {int(pid): [float(u), float(v)] for pid, (u, v) in points.items()}
                                for cam, points in entry.manual_points.items()}
    return out


def dump_rig(dataset: Dataset, root: str | Path | None = None, observations_file: str | None = None) -> dict[str, Any]:
    """Build the rig mapping of a dataset.

    The ``observations`` key is ``observations_file`` if given, else the dataset's observations_path made
    relative, else ``observations.json`` when the dataset holds observations; absent otherwise. Empty sets
    are left out.

    Args:
        dataset: the dataset.
        root: the folder paths are written relative to; None: ``dataset.root``.
        observations_file: the observations file the rig names; None: as above.

    Returns:
        The rig mapping (not yet JSON types: see :func:`~ari_sfm.io.atomic.to_jsonable`).
    """
    root = Path(root if root is not None else dataset.root)
    data: dict[str, Any] = {
        "format": FORMAT,
        "target": target_to_json(dataset.target),
        **windows_to_json(dataset),
        "cameras": {name: camera_to_json(cam) for name, cam in dataset.cameras.items()},
    }
    for set_name in SETS:
        entries = getattr(dataset, set_name)
        if entries:
            data[set_name] = [entry_to_json(e, root) for e in entries]
    if observations_file is not None:
        data["observations"] = observations_file
    elif dataset.observations_path is not None:
        data["observations"] = _relative(dataset.observations_path, root)
    elif dataset.observations is not None:
        data["observations"] = "observations.json"
    return data


def save_rig(path: str | Path, dataset: Dataset) -> Path:
    """Write a dataset as a rig file.

    If the dataset holds observations they are written next to it (as the file name of
    ``observations_path``, default ``observations.json``) and the rig names them. Image paths are written
    relative to the rig's folder. The rig is validated before writing (images need not exist yet).

    Args:
        path: the rig file (``.yaml``/``.yml``/``.json``), or a folder (gets ``rig.yaml``).
        dataset: the dataset to write.

    Returns:
        The rig file's path.

    Raises:
        AriSfmError: another suffix, an invalid rig or observations, or a file cannot be written.
    """
    path = Path(path)
    if path.is_dir() or not path.suffix:
        path = path / "rig.yaml"
    if path.suffix.lower() not in (".yaml", ".yml", ".json"):
        raise AriSfmError(path, "a rig file must end in .yaml, .yml or .json")
    root = Path(os.path.abspath(path.parent))
    obs_file = None
    if dataset.observations is not None:
        obs_file = dataset.observations_path.name if dataset.observations_path is not None else "observations.json"
    as_json = path.suffix.lower() == ".json"
    try:
        data = to_jsonable(dump_rig(dataset, root, obs_file), string_keys=as_json)
    except AriSfmError as exc:
        raise AriSfmError(path, exc.message) from None
    parse_rig(data, path, check_files=False)
    if obs_file is not None and dataset.observations is not None:
        obs_data = observations_to_json(dataset.observations)
        parse_observations(obs_data, root / obs_file, dataset.target, dataset.cameras)
        write_json_atomic(root / obs_file, obs_data)
    if as_json:
        write_json_atomic(path, data)
    else:
        text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, allow_unicode=True, width=120)
        write_text_atomic(path, text)
    return path


def _image_files(entries) -> set[str]:
    return {os.path.realpath(p) for e in entries for p in e.images.values()}


def detections_rig(out: str | Path, dataset: Dataset) -> Path:
    """Choose the rig file :func:`save_detections` writes in a folder (checked before a slow detection).

    ``out``'s own rig file is reused only when it is an earlier detection of the same images; another
    dataset's rig is never overwritten.

    Args:
        out: the output folder.
        dataset: the dataset whose corners will be detected.

    Returns:
        ``out``'s rig file, or ``out/rig.yaml`` when it has none.

    Raises:
        AriSfmError: ``out`` holds another dataset's rig file.
    """
    out = Path(out)
    present = [out / name for name in RIG_NAMES if (out / name).is_file()]
    if not present:
        return out / "rig.yaml"
    try:
        fields = parse_rig(read_structured(present[0]), present[0], check_files=False)
    except AriSfmError:
        fields = None
    same = (len(present) == 1 and fields is not None
            and fields["observations_path"] == Path(os.path.abspath(out / "observations.json"))
            and _image_files(e for s in SETS for e in fields[s]) == _image_files(dataset.entries()))
    if not same:
        raise AriSfmError(present[0], "-o/--out: holds another dataset's rig file (never overwritten): choose "
                                      "another folder")
    return present[0]


def save_detections(out: str | Path, dataset: Dataset, observations: Sequence[Observation]) -> Path:
    """Make a folder a dataset of a rig with its detected corners.

    Writes ``observations.json`` and a rig file naming it and the images (paths relative to ``out``), so
    that ``calibrate OUT`` and ``run OUT`` start from the corners instead of detecting again
    (:func:`detections_rig` says which rig file).

    Args:
        out: the output folder (created if needed).
        dataset: the dataset the corners were detected in.
        observations: the detected corners.

    Returns:
        The rig file written.

    Raises:
        AriSfmError: ``out`` holds another dataset's rig file, or a file cannot be written.
    """
    rig = detections_rig(out, dataset)
    Path(out).mkdir(parents=True, exist_ok=True)
    return save_rig(rig, dataset.with_observations(tuple(observations),
                                                   Path(os.path.abspath(Path(out) / "observations.json"))))

"""A particle experiment (DATASET_FORMAT.md, 1.2): rig.yaml ``particles:``, the detections table
``particles.parquet`` and the reconstruction table ``particles3d.parquet``.

Every reader validates fully and raises :class:`~ari_sfm.errors.AriSfmError` (file + one line);
every writer writes atomically.
"""
from __future__ import annotations

import contextlib
import io
import logging
import os
import string
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.errors import AriSfmError
from ari_sfm.io.atomic import replaced_atomically, write_bytes_atomic
from ari_sfm.io.dataset import find_rig, parse_cameras, parse_window_keys
from ari_sfm.io.observations import BORDER_TOLERANCE_PX, check_format
from ari_sfm.io.structured import (
    as_float_array,
    as_int,
    as_int_pair,
    as_mapping,
    as_name,
    as_nonnegative_float,
    as_positive_float,
    as_str,
    read_structured,
    require,
    warn_unknown_keys,
)
from ari_sfm.records import CameraSpec, Interface, Window

log = logging.getLogger(__name__)

PARTICLES_KEYS = ("detections", "images", "frames", "diameter_px", "volume_mm", "detect")
VOLUME_KEYS = ("frame", "min", "max")
DETECTION_COLUMNS = ("frame", "camera", "u", "v")  # + optional intensity
RECONSTRUCTION_COLUMNS = ("frame", "x", "y", "z", "ray_gap_mm", "cameras")  # + row_<camera>


@dataclass(frozen=True)
class VolumeSpec:
    """rig.yaml ``particles.volume_mm``: an axis-aligned box in a camera's frame, or in the target coordinates of
    a calibration frame (OpenPTV's observation volume is in its calibration body's coordinates)."""

    frame: str
    min_mm: np.ndarray
    max_mm: np.ndarray


@dataclass(frozen=True)
class DetectSettings:
    """rig.yaml ``particles.detect``: a lab's detection settings (e.g. from OpenPTV's targ_rec.par), each
    None where not given (the detector's default). detect-particles' options override them."""

    threshold: float | Mapping[str, float] | None = None  # grey levels above the local background; per camera
    threshold_sigma: float | None = None  # local noise sigmas
    min_pixels: int | None = None  # pixels above the threshold, 4-connected to the peak
    max_pixels: int | None = None
    min_span_px: int | None = None  # width along u and along v, px
    max_span_px: int | None = None
    min_sum: float | None = None  # grey sum of those pixels above the local background
    relative_floor: float | None = None  # peak at least this x the frame's bright particle images' (0: none)

    def given(self) -> dict[str, Any]:
        """The settings given, by name (DetectOptions' field names)."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__ if getattr(self, k) is not None}


DETECT_KEYS = tuple(DetectSettings.__dataclass_fields__)


@dataclass(frozen=True)
class ParticleDataset:
    """A dataset folder's rig with its ``particles`` entry (target and frame entries are not needed)."""

    root: Path
    rig_path: Path
    interface: Interface  # the first window's with several (windows)
    cameras: Mapping[str, CameraSpec]
    detections: Path | None  # absolute
    images: Mapping[str, str] | None  # camera -> absolute path pattern with {frame}
    frames: tuple[int, int] | None  # first and last frame of the images, inclusive
    diameter_px: float | None
    volume: VolumeSpec | None
    windows: tuple[Window, ...] = ()  # several windows (1.3); (): interface for every camera
    detect: DetectSettings = DetectSettings()  # particles.detect (1.2 addition)

    @property
    def camera_names(self) -> list[str]:
        return list(self.cameras)

    def image_path(self, camera: str, frame: int) -> Path:
        if self.images is None:
            raise AriSfmError(self.rig_path, "particles.images: none declared")
        return Path(self.images[camera].format(frame=frame))


@dataclass(frozen=True)
class Detections:
    """A detections table, checked. Rows in file order; ``by_frame`` indexes them, leaving out the rows that
    repeat an earlier row exactly (``repeated``: the same frame, camera, u and v; a table appended twice)."""

    path: Path
    frame: np.ndarray  # (N,) int64
    camera: np.ndarray  # (N,) str (object)
    uv: np.ndarray  # (N, 2)
    intensity: np.ndarray | None  # (N,)
    repeated: np.ndarray | None = None  # (N,) bool: the row repeats an earlier one (None: no row does)

    @property
    def frames(self) -> np.ndarray:
        return np.unique(self.frame)

    def by_frame(self, cameras: list[str]) -> dict[int, dict[str, np.ndarray]]:
        """frame -> camera -> the file rows (int64) of its detections, in file order (repeated rows left out)."""
        out: dict[int, dict[str, np.ndarray]] = {}
        kept = np.arange(len(self.frame)) if self.repeated is None else np.flatnonzero(~self.repeated)
        order = kept[np.argsort(self.frame[kept], kind="stable")]
        f_sorted = self.frame[order]
        bounds = np.flatnonzero(np.diff(f_sorted)) + 1
        for rows in np.split(order, bounds):
            if not len(rows):
                continue
            cams = self.camera[rows]
            out[int(self.frame[rows[0]])] = {c: rows[cams == c] for c in cameras}
        return out


# --------------------------------------------------------------------------- rig.yaml


def _pattern(value: Any, path: Path, where: str, root: Path) -> str:
    pattern = as_str(value, path, where)
    try:
        fields = [f for _, f, _, _ in string.Formatter().parse(pattern) if f is not None]
        pattern.format(frame=0)
    except (ValueError, KeyError, IndexError) as exc:
        raise AriSfmError(path, f"{where}: not a pattern with {{frame}} ({exc})") from None
    if fields != ["frame"]:
        raise AriSfmError(path, f"{where}: the pattern must hold {{frame}} once and no other field (got {pattern!r})")
    return os.path.abspath(root / pattern)


def load_particle_dataset(path: str | Path) -> ParticleDataset:
    """The rig of a particle experiment (a folder with rig.yaml / rig.json, or the file)."""
    rig_path = Path(os.path.abspath(find_rig(path)))
    root = rig_path.parent
    data = read_structured(rig_path)
    as_mapping(data, rig_path, "")
    check_format(data, rig_path, "ari-sfm/1")
    cameras = parse_cameras(require(data, "cameras", rig_path), rig_path)
    interface, windows = parse_window_keys(data, rig_path, cameras)
    if data.get("particles") is None:
        raise AriSfmError(rig_path, "no 'particles' entry: not a particle experiment (DATASET_FORMAT.md 1.2)")
    p = as_mapping(data["particles"], rig_path, "particles")
    warn_unknown_keys(p, PARTICLES_KEYS, rig_path, "particles")
    detections = None
    if p.get("detections") is not None:
        detections = Path(os.path.abspath(root / as_str(p["detections"], rig_path, "particles.detections")))
    images = frames = None
    if p.get("images") is not None:
        raw = as_mapping(p["images"], rig_path, "particles.images")
        images = {}
        for cam, pattern in raw.items():
            name = as_name(cam, rig_path, "particles.images camera")
            if name not in cameras:
                raise AriSfmError(rig_path, f"particles.images: camera '{name}' is not declared under cameras "
                                            f"({', '.join(cameras)})")
            images[name] = _pattern(pattern, rig_path, f"particles.images.{name}", root)
        first, last = as_int_pair(require(p, "frames", rig_path, "particles"), rig_path, "particles.frames", minimum=0)
        if last < first:
            raise AriSfmError(rig_path, f"particles.frames: last frame {last} before the first {first}")
        frames = (first, last)
    if detections is None and images is None:
        raise AriSfmError(rig_path, "particles: needs 'detections' (a parquet table) or 'images' (patterns per camera)")
    diameter = p.get("diameter_px")
    diameter = None if diameter is None else as_positive_float(diameter, rig_path, "particles.diameter_px")
    volume = None
    if p.get("volume_mm") is not None:
        v = as_mapping(p["volume_mm"], rig_path, "particles.volume_mm")
        warn_unknown_keys(v, VOLUME_KEYS, rig_path, "particles.volume_mm")
        frame = as_name(v.get("frame", next(iter(cameras))), rig_path, "particles.volume_mm.frame")
        # a camera's frame, or (1.3) a calibration frame's target coordinates: resolved with the calibration
        lo = as_float_array(require(v, "min", rig_path, "particles.volume_mm"), rig_path, "particles.volume_mm.min",
                            (3,))
        hi = as_float_array(require(v, "max", rig_path, "particles.volume_mm"), rig_path, "particles.volume_mm.max",
                            (3,))
        if not np.all(hi > lo):
            raise AriSfmError(rig_path, "particles.volume_mm: max must exceed min on every axis")
        volume = VolumeSpec(frame, lo, hi)
    detect = DetectSettings()
    if p.get("detect") is not None:
        detect = parse_detect_settings(p["detect"], rig_path, list(cameras))
    return ParticleDataset(root=root, rig_path=rig_path, interface=interface, cameras=cameras,
                           detections=detections, images=images, frames=frames, diameter_px=diameter, volume=volume,
                           windows=windows, detect=detect)


def parse_detect_settings(value: Any, path: Path, cameras: list[str]) -> DetectSettings:
    """Parse and check rig.yaml's ``particles.detect``.

    Values are numbers >= 0 (pixel counts and widths integers >= 1, the noise threshold > 0), minima not
    above maxima; ``threshold`` is a number or a mapping of declared cameras to numbers.

    Args:
        value: the ``particles.detect`` mapping, as read from the file.
        path: the rig file, for error messages.
        cameras: the names of the rig's cameras.

    Returns:
        The settings (None where not given).

    Raises:
        AriSfmError: a value is invalid (one line naming the key).
    """
    where = "particles.detect"
    d = as_mapping(value, path, where)
    warn_unknown_keys(d, DETECT_KEYS, path, where)
    out: dict[str, Any] = {}
    if d.get("threshold") is not None:
        t = d["threshold"]
        if isinstance(t, Mapping):
            per: dict[str, float] = {}
            for cam, v in t.items():
                name = as_name(cam, path, f"{where}.threshold camera")
                if name not in cameras:
                    raise AriSfmError(path, f"{where}.threshold: camera '{name}' is not declared under cameras "
                                            f"({', '.join(cameras)})")
                per[name] = as_nonnegative_float(v, path, f"{where}.threshold.{name}")
            out["threshold"] = per
        else:
            out["threshold"] = as_nonnegative_float(t, path, f"{where}.threshold")
    for key in ("min_pixels", "max_pixels", "min_span_px", "max_span_px"):
        if d.get(key) is not None:
            out[key] = as_int(d[key], path, f"{where}.{key}", minimum=1)
    for key in ("min_sum", "relative_floor"):
        if d.get(key) is not None:
            out[key] = as_nonnegative_float(d[key], path, f"{where}.{key}")
    if d.get("threshold_sigma") is not None:
        out["threshold_sigma"] = as_positive_float(d["threshold_sigma"], path, f"{where}.threshold_sigma")
    for lo, hi in (("min_pixels", "max_pixels"), ("min_span_px", "max_span_px")):
        if lo in out and hi in out and out[lo] > out[hi]:
            raise AriSfmError(path, f"{where}: {lo} {out[lo]} above {hi} {out[hi]}")
    return DetectSettings(**out)


# --------------------------------------------------------------------------- parquet


def _read_table(path: Path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    if not path.is_file():
        raise AriSfmError(path, "no such file (a particles parquet table)")
    try:
        return pq.read_table(path)
    except (pa.ArrowException, OSError) as exc:
        raise AriSfmError(path, f"not a readable parquet table ({str(exc).splitlines()[0]})") from None


def _column(table, name: str, path: Path, kind: str) -> np.ndarray:
    import pyarrow as pa

    if name not in table.column_names:
        raise AriSfmError(path, f"missing column '{name}' (columns: {', '.join(table.column_names)})")
    col = table.column(name)
    t = col.type
    if col.null_count:
        raise AriSfmError(path, f"column '{name}' has {col.null_count} empty (null) values")
    if kind == "int" and not pa.types.is_integer(t):
        raise AriSfmError(path, f"column '{name}' must be integer (got {t})")
    if kind == "float" and not (pa.types.is_floating(t) or pa.types.is_integer(t)):
        raise AriSfmError(path, f"column '{name}' must be a number (got {t})")
    if kind == "str" and not (pa.types.is_string(t) or pa.types.is_large_string(t) or pa.types.is_dictionary(t)):
        raise AriSfmError(path, f"column '{name}' must be a string (got {t})")
    if kind == "str":
        return np.asarray(col.to_pylist(), dtype=object)
    return col.to_numpy().astype(np.int64 if kind == "int" else float)


def read_detections(path: str | Path, cameras: Mapping[str, CameraSpec] | list[str]) -> Detections:
    """Read and check a detections table (``particles.parquet``) against the rig's cameras.

    Checks the contract columns, camera names, finite pixels, frames >= 0 and, when ``cameras`` is a
    mapping, pixels inside the images. Rows that repeat an earlier row exactly are marked (and a warning
    logged).

    Args:
        path: the parquet file.
        cameras: the rig's cameras (name -> spec: image sizes checked too) or their names.

    Returns:
        The detections, rows in file order.

    Raises:
        AriSfmError: the file is unreadable or a row fails a check (one line naming it).
    """
    path = Path(path)
    table = _read_table(path)
    frame = _column(table, "frame", path, "int")
    camera = _column(table, "camera", path, "str")
    u = _column(table, "u", path, "float")
    v = _column(table, "v", path, "float")
    intensity = _column(table, "intensity", path, "float") if "intensity" in table.column_names else None
    names = list(cameras)
    known = np.isin(camera, names)
    if not known.all():
        k = int(np.flatnonzero(~known)[0])
        raise AriSfmError(path, f"row {k}: camera '{camera[k]}' is not declared in rig.yaml ({', '.join(names)})")
    bad = ~(np.isfinite(u) & np.isfinite(v))
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise AriSfmError(path, f"row {k}: u, v must be finite numbers (got {u[k]}, {v[k]}); "
                                f"{int(bad.sum())} such rows")
    if (frame < 0).any():
        raise AriSfmError(path, f"row {int(np.flatnonzero(frame < 0)[0])}: frame must be >= 0")
    uv = np.stack([u, v], axis=1)
    if isinstance(cameras, Mapping):
        check_detections_in_images(path, camera, uv, {c: s.image_size for c, s in cameras.items()})
    return Detections(path, frame, camera, uv, intensity, _repeated_rows(path, frame, camera, uv))


def check_detections_in_images(path: Path, camera: np.ndarray, uv: np.ndarray,
                               image_sizes: Mapping[str, tuple[int, int]]) -> None:
    """Check that every detection centre lies in its camera's image.

    OpenCV pixel centres: the image's edges are at -0.5 and size - 0.5. A centre at most
    BORDER_TOLERANCE_PX beyond an edge is accepted; one farther out is another camera's, or another
    image size's.

    Args:
        path: the detections table, for error messages.
        camera: (N,) camera name of each row.
        uv: (N, 2) pixel centres.
        image_sizes: camera name -> (width, height) px; every camera of ``camera`` is in it.

    Raises:
        AriSfmError: naming the first row outside and how many are.
    """
    lo = -0.5 - BORDER_TOLERANCE_PX
    limits = np.zeros((len(uv), 2))
    for name, (w, h) in image_sizes.items():
        rows = camera == name
        limits[rows] = (w - 0.5 + BORDER_TOLERANCE_PX, h - 0.5 + BORDER_TOLERANCE_PX)
    outside = (uv[:, 0] < lo) | (uv[:, 1] < lo) | (uv[:, 0] > limits[:, 0]) | (uv[:, 1] > limits[:, 1])
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        w, h = image_sizes[camera[k]]
        raise AriSfmError(path, f"row {k}: camera {camera[k]}: pixel ({uv[k, 0]:g}, {uv[k, 1]:g}) is outside its "
                                f"{w} x {h} image (more than {BORDER_TOLERANCE_PX:g} px beyond its edge; rig.yaml "
                                f"cameras.{camera[k]}.image_size); {int(outside.sum())} such rows")


def _repeated_rows(path: Path, frame: np.ndarray, camera: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
    """(N,) True for a row equal to an earlier one in frame, camera, u and v (None: none is); said once."""
    if len(frame) < 2:
        return None
    names, code = np.unique(camera.astype(str), return_inverse=True)
    order = np.lexsort((np.arange(len(frame)), uv[:, 1], uv[:, 0], code, frame))
    keys = np.stack([frame[order].astype(float), code[order].astype(float), uv[order, 0], uv[order, 1]], axis=1)
    same = np.zeros(len(frame), bool)
    same[order[1:]] = (keys[1:] == keys[:-1]).all(axis=1)
    if not same.any():
        return None
    k = int(np.flatnonzero(same)[0])
    log.warning("%s: %d rows repeat an earlier row exactly (frame, camera, u, v; the first: row %d, camera %s, "
                "frame %d): each particle image is used once", path, int(same.sum()), k, camera[k], int(frame[k]))
    return same


def parquet_bytes(columns: Mapping[str, Any], metadata: Mapping[bytes, bytes] | None = None) -> bytes:
    """Write a parquet file in memory.

    Args:
        columns: column name -> values (a numpy array or a list).
        metadata: the schema's metadata; None: none.

    Returns:
        The parquet file's bytes.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    buf = io.BytesIO()
    table = pa.table(dict(columns))
    if metadata:
        table = table.replace_schema_metadata(dict(metadata))
    pq.write_table(table, buf)
    return buf.getvalue()


def write_parquet_atomic(path: str | Path, columns: Mapping[str, Any],
                         metadata: Mapping[bytes, bytes] | None = None) -> None:
    """Write a parquet table atomically (a reader never sees half of it).

    Args:
        path: the file to write.
        columns: column name -> values (a numpy array or a list).
        metadata: the schema's metadata; None: none.

    Raises:
        AriSfmError: the file cannot be written.
    """
    write_bytes_atomic(path, parquet_bytes(columns, metadata))


def write_table_atomic(path: str | Path, table: Any) -> None:
    """Write a pyarrow table as parquet, atomically.

    Args:
        path: the file to write.
        table: the pyarrow table.

    Raises:
        AriSfmError: the file cannot be written.
    """
    import pyarrow.parquet as pq

    buf = io.BytesIO()
    pq.write_table(table, buf)
    write_bytes_atomic(path, buf.getvalue())


def write_tables_atomic(path: str | Path, tables: Iterable[Any]) -> int:
    """Write pyarrow tables of one schema, in order, as one parquet table, atomically.

    Holds one table in memory at a time (a long experiment's partitions); a table of another schema is
    cast to the first one's.

    Args:
        path: the file to write.
        tables: the tables, at least one.

    Returns:
        The number of rows written.

    Raises:
        ValueError: no table.
        AriSfmError: a table cannot be written, or the file cannot be.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    rows = 0
    with replaced_atomically(path) as tmp:
        writer: Any = None
        try:
            for table in tables:
                if writer is None:
                    writer = pq.ParquetWriter(tmp, table.schema)
                elif table.schema != writer.schema:
                    table = table.cast(writer.schema)
                writer.write_table(table)
                rows += table.num_rows
            if writer is None:
                raise ValueError(f"{path}: no table to write")
            closing = writer
            writer = None
            closing.close()
        except pa.ArrowException as exc:
            if isinstance(exc, OSError):
                raise
            raise AriSfmError(path, f"cannot write the table ({str(exc).splitlines()[0]})") from None
        finally:
            if writer is not None:  # an error or an interrupt while writing: the temporary file is dropped
                with contextlib.suppress(Exception):
                    writer.close()
    return rows


def write_detections(path: str | Path, frame: np.ndarray, camera: list[str] | np.ndarray, uv: np.ndarray,
                     intensity: np.ndarray | None = None) -> None:
    """Write a detections table (contract columns, rows in the order given), atomically.

    Args:
        path: the parquet file to write.
        frame: (N,) frame numbers.
        camera: (N,) camera names.
        uv: (N, 2) pixel centres.
        intensity: (N,) intensities; None: no ``intensity`` column.

    Raises:
        AriSfmError: the file cannot be written.
    """
    cols: dict[str, Any] = {"frame": np.asarray(frame, np.int64), "camera": [str(c) for c in camera],
                            "u": np.asarray(uv, float).reshape(-1, 2)[:, 0],
                            "v": np.asarray(uv, float).reshape(-1, 2)[:, 1]}
    if intensity is not None:
        cols["intensity"] = np.asarray(intensity, float)
    write_parquet_atomic(path, cols)


def read_reconstruction(path: str | Path, cameras: list[str]) -> dict[str, np.ndarray]:
    """Read a reconstruction table (``particles3d.parquet``).

    Args:
        path: the parquet file.
        cameras: the rig's camera names (a ``row_<camera>`` column each).

    Returns:
        Column name -> array: ``frame``, ``x``, ``y``, ``z``, ``ray_gap_mm``, ``cameras`` and
        ``row_<camera>`` per camera.

    Raises:
        AriSfmError: the file is unreadable or a contract column is missing, null or of another type.
    """
    path = Path(path)
    table = _read_table(path)
    out = {name: _column(table, name, path, "int" if name in ("frame", "cameras") else "float")
           for name in RECONSTRUCTION_COLUMNS}
    for cam in cameras:
        out[f"row_{cam}"] = _column(table, f"row_{cam}", path, "int")
    return out

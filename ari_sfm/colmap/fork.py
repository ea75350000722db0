"""The refractive COLMAP fork's FLATPORT cameras (Kiel/GEOMAR ``colmap_underwater``), both ways.

Conventions, from the fork's ``src/colmap/sensor/models_refrac.h`` and ``ray3d.h``:

- ``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[] FLATPORT Nx Ny Nz int_dist int_thick na ng nw``:
  the in-air camera model's parameters, then the refractive model's name and its 8 parameters
  (later versions write a token ``REFRAC`` before the name: both are read; the
  ``colmap_underwater`` form is written).
- ``(Nx, Ny, Nz)``: the interface's unit normal in the camera frame, from the camera into the scene
  (``(0, 0, 1)`` = the optical axis); ``int_dist``: camera centre to the inner (near) face along it;
  ``int_thick``: the glass thickness; both in the model's length units (metres in the fork's
  examples: ``units_mm`` = 1000 here by default); ``na ng nw``: the indices of the housing's air,
  the glass and the water.
- ``CamFromImg``: the in-air camera model's ray from the centre, intersected with the plane
  ``N . x = int_dist``, refracted (vector Snell, ``ComputeRefraction``), intersected with
  ``N . x = int_dist + int_thick``, refracted again. ``ImgFromCam``: the in-air projection as the
  start, then Gauss-Newton on the pixel whose refracted ray passes the point at its distance.
  That is this package's exact model (:mod:`ari_sfm.models.exact`) with ``normal_cam = N``,
  ``distance_mm = int_dist units_mm``, ``thickness_mm = int_thick units_mm``, ``index = ng``,
  ``medium_index = nw``; ari-sfm has air in the housing, so ``na`` must be 1.
- Pixels: COLMAP's (origin at the pixel corner): ``cx_colmap = cx_opencv + 0.5``
  (:func:`ari_sfm.colmap.adapter.colmap_from_opencv_px`, the one place of that offset).
- In-air models: ``PINHOLE`` (no distortion), ``OPENCV`` (k1 k2 p1 p2), ``FULL_OPENCV`` (k3, with
  its k4..k6 zero) written; those and ``SIMPLE_PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL`` read.

A calibration is written as one COLMAP camera per rig camera (ids in the calibration's order) and
one image per camera and calibration frame (``<camera>/<frame>``: every image of a camera has its
``cam_from_world``, the rig being static in the calibration's world), with the target corners as
3D points when observations are at hand; without them one image per camera (``<camera>``) keeps
the rig's poses. A refine-colmap output (mount camera) is written with COLMAP's camera and image
ids, every image at its refined real pose with its 2D points, and the refined points. Reading back: the cameras' poses
from their images (equal for a static rig; one camera that moves, as in a survey, is read at its first image),
re-expressed in the first camera's frame; cameras whose FLATPORT planes coincide share a window, others get windows of
their own (a rig behind several walls, DATASET_FORMAT 1.3: each camera's FLATPORT is written from its own window).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..calibration.origin import ImportedFrom
from ..calibration.record import Calibration, CameraCalibration, WindowCalibration
from ..errors import AriSfmError
from ..geometry import Pose, angle_between_deg
from ..io import load_calibration
from ..records import Interface, Observation

if TYPE_CHECKING:
    from ..records import Dataset

log = logging.getLogger(__name__)

REFRAC_MODEL = "FLATPORT"
REFRAC_TOKEN = "REFRAC"  # written before the refractive model's name by later versions of the fork
DEFAULT_UNITS_MM = 1000.0  # mm per length unit of the fork's model: metres, as in the fork's examples
COLMAP_PIXEL_OFFSET = 0.5  # as ari_sfm.colmap.adapter (kept here so that reading needs no pycolmap)
# in-air camera models: name -> number of parameters
CAMERA_MODELS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "FULL_OPENCV": 12}
POSE_TOLERANCE = 1e-6  # rad, and relative to the rig's size: images of one static camera agree to this
WINDOW_TOLERANCE_DEG = 1e-4  # cameras' normals in the first camera's frame agree to this (one window)
WINDOW_TOLERANCE_MM = 1e-4  # and their distances to its face
UNITS_MM_RANGE = (1e-3, 1e6)  # --units-mm: from micrometres to kilometres per model unit


def check_units_mm(units_mm: float) -> float:
    """``units_mm`` if a physical length unit (UNITS_MM_RANGE), else AriSfmError naming --units-mm."""
    lo, hi = UNITS_MM_RANGE
    if not (isinstance(units_mm, (int, float)) and math.isfinite(units_mm) and lo <= units_mm <= hi):
        raise AriSfmError("--units-mm", f"must be mm per length unit of the fork's model, between {lo:g} (um) and "
                                        f"{hi:g} (km) (got {units_mm!r}; 1000 = metres)")
    return float(units_mm)


@dataclass(frozen=True)
class ForkCamera:
    """One line of the fork's cameras.txt, in ari-sfm's terms (mm, OpenCV pixels)."""

    camera_id: int
    model: str  # the in-air model's COLMAP name
    image_size: tuple[int, int]
    params: np.ndarray  # [fx fy cx cy k1 k2 p1 p2 k3], OpenCV pixels
    normal_cam: np.ndarray  # (Nx, Ny, Nz)
    distance_mm: float  # int_dist
    thickness_mm: float  # int_thick
    indices: tuple[float, float, float]  # na, ng, nw


@dataclass(frozen=True)
class ForkImage:
    """One image of images.txt (its 2D points are not needed to move a calibration)."""

    image_id: int
    camera_id: int
    name: str
    cam_from_world: Pose  # translation in mm


@dataclass(frozen=True)
class ForkExport:
    """What :func:`export_colmap_fork` wrote."""

    files: tuple[Path, ...]
    cameras: int
    images: int
    points3D: int
    units_mm: float


# --------------------------------------------------------------------------- cameras.txt lines


def colmap_camera_params(params: np.ndarray | Sequence[float]) -> tuple[str, list[float]]:
    """The smallest COLMAP model holding ``[fx fy cx cy k1 k2 p1 p2 k3]`` (OpenCV pixels) and its parameters."""
    p = np.resize(np.asarray(params, float), 9)
    fx, fy, cx, cy = p[0], p[1], p[2] + COLMAP_PIXEL_OFFSET, p[3] + COLMAP_PIXEL_OFFSET
    k1, k2, p1, p2, k3 = p[4:9]
    if not np.any(p[4:9]):
        return "PINHOLE", [fx, fy, cx, cy]
    if k3 == 0.0:
        return "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    return "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]


def params_from_colmap(model: str, values: Sequence[float], where: Path, what: str) -> np.ndarray:
    """Convert a COLMAP in-air model's parameters to ``[fx fy cx cy k1 k2 p1 p2 k3]`` (OpenCV pixels).

    Args:
        model: the COLMAP model's name (one of CAMERA_MODELS).
        values: its parameters (COLMAP pixels).
        where: the file named in an error.
        what: what is named in an error ("line 3").

    Returns:
        The 9 parameters, OpenCV pixels.

    Raises:
        AriSfmError: for an unsupported model, or FULL_OPENCV with k4 k5 k6.
    """
    v = list(values)
    if model == "SIMPLE_PINHOLE":
        f, cx, cy = v
        out = [f, f, cx, cy, 0, 0, 0, 0, 0]
    elif model == "PINHOLE":
        out = v + [0.0] * 5
    elif model == "SIMPLE_RADIAL":
        f, cx, cy, k = v
        out = [f, f, cx, cy, k, 0, 0, 0, 0]
    elif model == "RADIAL":
        f, cx, cy, k1, k2 = v
        out = [f, f, cx, cy, k1, k2, 0, 0, 0]
    elif model == "OPENCV":
        out = v + [0.0]
    elif model == "FULL_OPENCV":
        if any(v[9:12]):
            raise AriSfmError(where, f"{what}: FULL_OPENCV with k4 k5 k6 (the rational terms) is not "
                                     "supported (ari-sfm's distortion is k1 k2 p1 p2 k3)")
        out = v[:9]
    else:
        raise AriSfmError(where, f"{what}: camera model {model} is not supported "
                                 f"(supported: {', '.join(CAMERA_MODELS)})")
    params = np.asarray(out, float)
    params[2:4] -= COLMAP_PIXEL_OFFSET
    return params


def format_camera_line(camera_id: int, image_size: tuple[int, int], params: np.ndarray | Sequence[float],
                       normal_cam: np.ndarray, distance_mm: float, interface: Interface, units_mm: float) -> str:
    """Format one cameras.txt line of the fork (``colmap_underwater`` form).

    Args:
        camera_id: the COLMAP camera id.
        image_size: the image size (w, h).
        params: ``[fx fy cx cy k1 k2 p1 p2 k3]``, OpenCV pixels.
        normal_cam: the window normal in the camera frame, from the camera into the scene.
        distance_mm: the camera centre's distance to the window's near face (mm).
        interface: the window's thickness and indices.
        units_mm: the mm per length unit of the written model.

    Returns:
        The line, without a newline.

    Raises:
        AriSfmError: if the normal points away from the camera's view (Nz <= 0).
    """
    model, values = colmap_camera_params(params)
    n = np.asarray(normal_cam, float) / np.linalg.norm(normal_cam)
    if not n[2] > 0.0:  # the fork's import (and ours) refuses Nz <= 0: never write one
        raise AriSfmError(None, f"camera {camera_id}: its window normal {n.round(6).tolist()} points away from its "
                                "view (Nz <= 0): the fork's FLATPORT normal goes from the camera into the scene")
    refrac = [n[0], n[1], n[2], distance_mm / units_mm, interface.thickness_mm / units_mm, 1.0,
              interface.index, interface.medium_index]
    return " ".join([str(int(camera_id)), model, str(int(image_size[0])), str(int(image_size[1]))]
                    + [repr(float(x)) for x in values] + [REFRAC_MODEL] + [repr(float(x)) for x in refrac])


def parse_camera_line(line: str, where: Path, line_no: int, units_mm: float) -> ForkCamera:
    """Parse a cameras.txt line of the fork.

    Args:
        line: the line.
        where: the file named in an error.
        line_no: the line's number, named in an error.
        units_mm: the mm per length unit of the model.

    Returns:
        The camera, in ari-sfm's terms (mm, OpenCV pixels).

    Raises:
        AriSfmError: naming the file and line, when the line is not a supported FLATPORT camera.
    """
    what = f"line {line_no}"
    items = line.split()
    try:
        camera_id, model, width, height = int(items[0]), items[1], int(items[2]), int(items[3])
    except (IndexError, ValueError):
        raise AriSfmError(where, f"{what}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[] {REFRAC_MODEL} ...") from None
    if model not in CAMERA_MODELS:
        raise AriSfmError(where,
                          f"{what}: camera model {model} is not supported (supported: {', '.join(CAMERA_MODELS)})")
    n_params = CAMERA_MODELS[model]
    rest = items[4:]
    if len(rest) > n_params and rest[n_params] == REFRAC_TOKEN:
        rest = rest[:n_params] + rest[n_params + 1:]
    if len(rest) == n_params:
        raise AriSfmError(where, f"{what}: camera {camera_id} has no {REFRAC_MODEL} block: not a refractive camera "
                                 "(use ari-sfm refine-colmap for COLMAP models made behind a window)")
    if len(rest) < n_params + 1 or rest[n_params] != REFRAC_MODEL:
        found = rest[n_params] if len(rest) > n_params else "nothing"
        raise AriSfmError(where, f"{what}: expected {n_params} {model} parameters then {REFRAC_MODEL} (found {found}; "
                                 "DOMEPORT and other refractive models are not supported)")
    try:
        values = [float(x) for x in rest[:n_params]]
        refrac = [float(x) for x in rest[n_params + 1:]]
    except ValueError as exc:
        raise AriSfmError(where, f"{what}: not a number: {exc}") from None
    if len(refrac) != 8:
        raise AriSfmError(where, f"{what}: {REFRAC_MODEL} needs 8 parameters (Nx Ny Nz int_dist int_thick na ng nw), "
                                 f"got {len(refrac)}")
    if not all(math.isfinite(x) for x in values + refrac) or width <= 0 or height <= 0:
        raise AriSfmError(where, f"{what}: camera {camera_id} has a non-finite parameter or an image size <= 0")
    normal = np.array(refrac[:3])
    if abs(np.linalg.norm(normal) - 1.0) > 1e-6:
        raise AriSfmError(where, f"{what}: (Nx, Ny, Nz) must be a unit vector (norm {np.linalg.norm(normal):.6g})")
    na, ng, nw = refrac[5:8]
    if na != 1.0:
        raise AriSfmError(where, f"{what}: na = {na:g}: ari-sfm models air inside the housing (na = 1)")
    if not (ng >= 1.0 and nw >= 1.0):
        raise AriSfmError(where, f"{what}: the indices ng, nw must be >= 1 (got {ng:g}, {nw:g})")
    if not (refrac[3] > 0.0 and refrac[4] > 0.0):
        raise AriSfmError(where, f"{what}: int_dist and int_thick must be > 0 (got {refrac[3]:g}, {refrac[4]:g})")
    if normal[2] <= 0.0:
        raise AriSfmError(where, f"{what}: the normal {normal.tolist()} points away from the scene (Nz <= 0)")
    return ForkCamera(camera_id, model, (width, height), params_from_colmap(model, values, where, what), normal,
                      refrac[3] * units_mm, refrac[4] * units_mm, (na, ng, nw))


# --------------------------------------------------------------------------- export


def _quaternion_wxyz(R: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return [w, x, y, z]


def _rotation_from_wxyz(q: Sequence[float]) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    w, x, y, z = q
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def _camera_window(cal: Calibration, name: str) -> float:
    """A camera's distance to its window's near face (mm), also for an exact calibration in air."""
    d = cal.evaluation_distance_mm(name)
    if d is None:
        raise ValueError(f"camera {name}: no distance to its window (neither distance_mm nor fixed_distance_mm)")
    return float(d)


@dataclass(frozen=True)
class _Image:
    """An image to write: its camera, name, pose (mm) and 2D points (OpenCV pixels) with their point ids."""

    camera: str
    name: str
    cam_from_world: Pose
    uv: np.ndarray  # (n, 2)
    point_ids: np.ndarray  # (n,)


def _target_images(cal: Calibration, observations: Sequence[Observation] | None
                   ) -> tuple[list[_Image], dict[int, np.ndarray]]:
    """One image per (camera, calibration frame) with its corners, the corners as points (mm)."""
    used = [o for o in (observations or ()) if o.set == "calibration" and o.frame in cal.frames
            and o.camera in cal.cameras and len(o.ids)]
    if not used or cal.target is None:
        if used:
            log.warning("the calibration holds no target: exporting cameras and poses only")
        return [_Image(n, n, c.cam_from_world, np.zeros((0, 2)), np.zeros(0, int)) for n, c in cal.cameras.items()], {}
    ids, xyz = cal.target.points_3d_readonly
    where = {int(i): k for k, i in enumerate(ids.tolist())}
    point_ids: dict[tuple[str, int], int] = {}
    points: dict[int, np.ndarray] = {}
    images = []
    for o in used:
        pids = []
        for corner in o.ids.tolist():
            key = (o.frame, int(corner))
            if key not in point_ids:
                point_ids[key] = len(point_ids) + 1
                points[point_ids[key]] = cal.frames[o.frame].apply(xyz[where[int(corner)]])
            pids.append(point_ids[key])
        images.append(_Image(o.camera, f"{o.camera}/{o.frame}", cal.cameras[o.camera].cam_from_world,
                             np.asarray(o.pixels, float), np.asarray(pids, int)))
    return images, points


def _refined_images(cal: Calibration, model_dir: Path) -> tuple[dict[str, int], list[_Image], dict[int, np.ndarray]]:
    """A refine-colmap output (its calibration.json and the COLMAP model beside it): COLMAP's camera
    ids, every image at its real pose with its 2D points, the refined points (mm)."""
    from . import adapter

    info = cal.refine_colmap
    if info is None or info.mount != "camera":
        raise AriSfmError(model_dir / "calibration.json", "not a refine-colmap output of mount camera (refine_colmap."
                                                          "camera_ids and images_cam_from_world are needed)")
    camera_ids, poses = info.camera_ids, info.images_cam_from_world
    model = adapter.model_from_reconstruction(adapter.read_colmap(model_dir), model_dir)
    name_of = {int(cid): name for name, cid in camera_ids.items()}
    images = []
    for i, image_id in enumerate(model.image_ids.tolist()):
        sel = np.flatnonzero(model.obs_image == i)
        pose = poses.get(int(image_id))
        if pose is None:
            raise AriSfmError(model_dir / "calibration.json",
                              f"refine_colmap.images_cam_from_world has no image {image_id}")
        images.append(_Image(name_of[int(model.camera_ids[model.image_camera[i]])], model.image_names[i],
                             pose, model.obs_uv[sel], model.point3D_ids[model.obs_point[sel]]))
    points = {int(pid): model.xyz[k] for k, pid in enumerate(model.point3D_ids.tolist())}
    return {n: int(c) for n, c in camera_ids.items()}, images, points


def _dataset_observations(cal: Calibration, dataset: Dataset | str | Path, path: Path) -> Sequence[Observation]:
    """The observations of a dataset of the calibration's rig (another rig's: AriSfmError, as calibrate's)."""
    from ..io import load_dataset
    from ..reconstruction.reconstruct import check_rig

    ds = load_dataset(dataset) if isinstance(dataset, (str, Path)) else dataset
    check_rig(ds, cal, path)
    if ds.observations is None:
        raise AriSfmError(ds.rig_path, "the dataset holds no observations (images only): run `ari-sfm detect` "
                                       "and pass --dataset with its observations.json")
    return ds.observations


def export_colmap_fork(calibration: Calibration | str | Path, out_dir: str | Path,
                       observations: Sequence[Observation] | None = None,
                       units_mm: float = DEFAULT_UNITS_MM, refined_model: str | Path | None = None,
                       dataset: Dataset | str | Path | None = None,
                       calibration_path: str | Path | None = None) -> ForkExport:
    """Write an exact-Snell calibration as the fork's text model.

    cameras.txt (FLATPORT), images.txt and points3D.txt are written together: all three or none.
    Images and points come from ``refined_model`` if given, else from ``observations`` (or ``dataset``'s),
    else one image per camera (its pose) is written, with a warning.

    Args:
        calibration: the calibration (model exact), or its calibration.json path.
        out_dir: the output folder.
        observations: the calibration's observations: one image per camera and calibration frame with the
            target corners.
        units_mm: the mm per length unit of the written model (within UNITS_MM_RANGE).
        refined_model: a refine-colmap output folder (its COLMAP model beside the calibration): every image
            at its real pose and the refined points.
        dataset: a dataset of the calibration's rig (or its path), whose observations are used.
        calibration_path: the file named in errors when ``calibration`` is a record.

    Returns:
        What was written: the files and the numbers of cameras, images and points.

    Raises:
        AriSfmError: for a calibration that is not exact, a bad ``units_mm``, or observations that are not
            the calibration's.
    """
    from ..io import write_files_atomic
    from ..provenance import observations_mismatch

    path = Path(calibration) if isinstance(calibration, (str, Path)) else Path(calibration_path or "calibration.json")
    cal = load_calibration(calibration) if isinstance(calibration, (str, Path)) else calibration
    if cal.spec.projection != "exact":
        raise AriSfmError(path, f"model {cal.model}: the fork's {REFRAC_MODEL} is Snell's law at both faces; export "
                                "an exact calibration (ari-sfm calibrate --model exact)")
    units_mm = check_units_mm(units_mm)
    where = path.parent / "observations.json"
    if dataset is not None:
        observations = _dataset_observations(cal, dataset, path)
        where = Path(dataset) if isinstance(dataset, (str, Path)) else dataset.root
    if refined_model is None and observations is not None:
        why = observations_mismatch(cal, observations, cal.target)
        if why:  # the calibration's frames with another capture's corners: tracks of nonsense
            raise AriSfmError(where, why)
        if len(observations) and not any(o.set == "calibration" and o.frame in cal.frames and o.camera in cal.cameras
                                         for o in observations):
            raise AriSfmError(where, f"none of its {len(observations)} observations is of the calibration's cameras "
                                     f"({', '.join(cal.cameras)}) in its calibration frames: another rig or capture")
    elif refined_model is None:
        log.warning("no observations (no --dataset, no observations.json beside the calibration, no dataset "
                    "recorded by run.json): exporting cameras and poses only, no points3D")
    out = Path(out_dir)
    names = list(cal.cameras)
    if refined_model is not None:
        camera_ids, images, points = _refined_images(cal, Path(refined_model))
    else:
        camera_ids = {n: i + 1 for i, n in enumerate(names)}
        images, points = _target_images(cal, observations)
    cam_lines = ["# Camera list with one line of data per camera:",
                 f"#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[] {REFRAC_MODEL} Nx Ny Nz int_dist int_thick na ng nw",
                 f"# Number of cameras: {len(names)}; lengths in units of {units_mm:g} mm (written by ari-sfm)"]
    for n in names:
        c = cal.cameras[n]
        cam_lines.append(format_camera_line(camera_ids[n], c.image_size, c.params, cal.normal_cam(n),
                                            _camera_window(cal, n), cal.interface_of(n), units_mm))
    img_lines = ["# Image list with two lines of data per image:",
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                 f"# Number of images: {len(images)}"]
    tracks: dict[int, list[tuple[int, int]]] = {}
    for image_id, im in enumerate(images, start=1):
        pose = im.cam_from_world
        img_lines.append(" ".join([str(image_id)] + [repr(float(x)) for x in _quaternion_wxyz(pose.R)]
                                  + [repr(float(x)) for x in pose.t / units_mm] + [str(camera_ids[im.camera]),
                                                                                   im.name]))
        items = []
        for k, ((u, v), pid) in enumerate(zip((im.uv + COLMAP_PIXEL_OFFSET).tolist(), im.point_ids.tolist())):
            tracks.setdefault(int(pid), []).append((image_id, k))
            items += [repr(u), repr(v), str(int(pid))]
        img_lines.append(" ".join(items))
    pts_lines = ["# 3D point list with one line of data per point:",
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                 f"# Number of points: {len(tracks)}"]
    for pid in sorted(tracks):
        X = (np.asarray(points[pid], float) / units_mm).tolist()
        track = " ".join(f"{i} {k}" for i, k in tracks[pid])
        pts_lines.append(f"{pid} {X[0]!r} {X[1]!r} {X[2]!r} 150 150 150 0 {track}")
    texts = {"cameras.txt": cam_lines, "images.txt": img_lines, "points3D.txt": pts_lines}

    def writer(tmp: Path) -> None:
        for fname, lines in texts.items():
            (tmp / fname).write_text("\n".join(lines) + "\n", encoding="utf-8")

    write_files_atomic(out, writer)  # the three files together or none (a full disk at images.txt: no cameras.txt)
    files = [out / fname for fname in texts]
    return ForkExport(tuple(files), len(names), len(images), len(tracks), units_mm)


# --------------------------------------------------------------------------- import


def read_fork_cameras(path: Path, units_mm: float) -> list[ForkCamera]:
    """Read every camera of the fork's cameras.txt.

    Args:
        path: the cameras.txt.
        units_mm: the mm per length unit of the model.

    Returns:
        The cameras, in the file's order.

    Raises:
        AriSfmError: if the file is missing, holds no camera, a bad line or a CAMERA_ID twice.
    """
    if not path.is_file():
        raise AriSfmError(path, "no such file (a COLMAP text model folder holds cameras.txt, images.txt, points3D.txt)")
    cameras = []
    for i, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            cameras.append(parse_camera_line(line, path, i, units_mm))
    if not cameras:
        raise AriSfmError(path, "no camera")
    if len({c.camera_id for c in cameras}) != len(cameras):
        raise AriSfmError(path, "a CAMERA_ID appears twice")
    return cameras


def read_fork_images(path: Path, units_mm: float) -> list[ForkImage]:
    """Read the images of images.txt (pose and camera: the first line of each pair).

    Args:
        path: the images.txt.
        units_mm: the mm per length unit of the model.

    Returns:
        The images; [] without the file.

    Raises:
        AriSfmError: for a malformed line or a non-finite pose.
    """
    if not path.is_file():
        return []
    rows = [ln.strip() for ln in path.read_text(errors="replace").splitlines()]
    out = []
    i = 0
    while i < len(rows):
        line = rows[i]
        if not line or line.startswith("#"):
            i += 1
            continue
        items = line.split()
        try:
            q = [float(x) for x in items[1:5]]
            t = np.array([float(x) for x in items[5:8]])
            image = ForkImage(int(items[0]), int(items[8]), " ".join(items[9:]),
                              Pose(_rotation_from_wxyz(np.asarray(q) / np.linalg.norm(q)), t * units_mm))
        except (IndexError, ValueError, ZeroDivisionError):
            raise AriSfmError(path, f"line {i + 1}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME") from None
        if not (np.all(np.isfinite(image.cam_from_world.R)) and np.all(np.isfinite(t))):
            raise AriSfmError(path, f"line {i + 1}: a non-finite pose")
        out.append(image)
        i += 2  # the POINTS2D line follows (possibly empty)
    return out


def _camera_pose(camera: ForkCamera, images: list[ForkImage], several: bool, path: Path) -> Pose | None:
    """The camera's one cam_from_world (its images agree: a static rig), None without images."""
    mine = [im for im in images if im.camera_id == camera.camera_id]
    if not mine:
        return None
    first = mine[0].cam_from_world
    scale = max(1.0, float(np.linalg.norm(first.t)))
    for im in mine[1:]:
        p = im.cam_from_world
        cos = np.clip((np.trace(p.R @ first.R.T) - 1.0) / 2.0, -1.0, 1.0)
        if math.acos(cos) > POSE_TOLERANCE or np.linalg.norm(p.t - first.t) > POSE_TOLERANCE * scale:
            if several:
                raise AriSfmError(path, f"camera {camera.camera_id} moves between images ({mine[0].name}, {im.name}): "
                                        "a rig of several cameras is read from a static rig's images only")
            log.info("camera %d moves between images (a survey): its housing is read at %s", camera.camera_id,
                     mine[0].name)
            break
    return first


def _camera_name(camera: ForkCamera, images: list[ForkImage]) -> str:
    """``<camera>`` of ari-sfm's image names ``<camera>/<frame>`` or ``<camera>``, else cam<CAMERA_ID>."""
    prefixes = {im.name.split("/")[0] for im in images if im.camera_id == camera.camera_id}
    if len(prefixes) == 1:
        name = prefixes.pop()
        if name and "." not in name:
            return name
    return f"cam{camera.camera_id}"


def import_colmap_fork(model_dir: str | Path, units_mm: float = DEFAULT_UNITS_MM) -> Calibration:
    """Import a fork's text model as a calibration (model exact): its FLATPORT cameras and their poses.

    Args:
        model_dir: the COLMAP text model folder (cameras.txt, images.txt).
        units_mm: the mm per length unit of the model (1000: metres).

    Returns:
        The calibration, in the first camera's frame.

    Raises:
        AriSfmError: for a missing folder or file, a bad line, a rig whose cameras move or lack images,
            differing water indices, or values beyond calibration.json's bounds (a wrong ``units_mm``).
    """
    model_dir = Path(model_dir)
    units_mm = check_units_mm(units_mm)
    if not model_dir.is_dir():
        raise AriSfmError(model_dir, "no such folder (a COLMAP text model: cameras.txt, images.txt, points3D.txt)")
    cams_path = model_dir / "cameras.txt"
    fork_cams = read_fork_cameras(cams_path, units_mm)
    images = read_fork_images(model_dir / "images.txt", units_mm)
    several = len(fork_cams) > 1
    poses = {c.camera_id: _camera_pose(c, images, several, model_dir / "images.txt") for c in fork_cams}
    if several and any(p is None for p in poses.values()):
        missing = next(cid for cid, p in poses.items() if p is None)
        raise AriSfmError(model_dir / "images.txt", f"camera {missing} has no image: the poses of a rig of several "
                                                    "cameras come from their images")
    first = fork_cams[0]
    world_from_first = (poses[first.camera_id] or Pose.identity()).inverse()
    names = [_camera_name(c, images) for c in fork_cams]
    if len(set(names)) != len(names):
        names = [f"cam{c.camera_id}" for c in fork_cams]
    media = {c.indices[2] for c in fork_cams}
    if len(media) > 1:
        raise AriSfmError(cams_path, f"the cameras' water indices (nw) differ ({sorted(media)}): one tank, one medium")
    cameras = {}
    groups: list[list[Any]] = []  # [normal_world, plane offset, thickness, indices, camera names]
    for name, c in zip(names, fork_cams):
        cam_from_world = (poses[c.camera_id] or Pose.identity()).compose(world_from_first)
        n_w = cam_from_world.R.T @ c.normal_cam
        plane = c.distance_mm + float(n_w @ cam_from_world.inverse().t)  # its near face: n_w . X = plane
        same = next((g for g in groups if (g[2], g[3]) == (c.thickness_mm, c.indices)
                     and angle_between_deg(n_w, g[0]) <= WINDOW_TOLERANCE_DEG
                     and abs(plane - g[1]) <= WINDOW_TOLERANCE_MM * max(1.0, abs(g[1]))), None)
        if same is None:  # a window of its own: FLATPORT cameras behind another wall (DATASET_FORMAT 1.3)
            groups.append([n_w, plane, c.thickness_mm, c.indices, [name]])
        else:
            same[4].append(name)
        p = c.params
        K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
        cameras[name] = CameraCalibration(name, c.image_size, K, p[4:9].copy(), cam_from_world)
    in_air = first.indices[2] == 1.0
    windows = []
    for k, (n_w, plane, thickness, (_, ng, nw), members) in enumerate(groups):
        reference = float(n_w @ cameras[members[0]].cam_from_world.inverse().t)
        distance = plane - reference  # from the window's first camera, as calibration.json says
        windows.append(WindowCalibration(f"window{k + 1}" if len(groups) > 1 else "window",
                                         Interface(thickness, ng, nw, None if in_air else distance), n_w,
                                         tuple(members), distance if in_air else None))
    if len(windows) > 1:
        log.info("%s: %d windows (cameras behind different walls: %s)", cams_path, len(windows),
                 "; ".join(f"{w.name}: {', '.join(w.cameras)}" for w in windows))
    head = windows[0]
    cal = Calibration(model="exact", interface=head.interface, normal_world=head.normal_world, cameras=cameras,
                      frames={}, imported_from=ImportedFrom(f"COLMAP {REFRAC_MODEL} (colmap_underwater)",
                                                            str(model_dir), float(units_mm)),
                      fixed_distance_mm=head.fixed_distance_mm, windows=tuple(windows) if len(windows) > 1 else ())
    _check_as_calibration_json(cal, cams_path, units_mm)
    return cal


def _check_as_calibration_json(cal: Calibration, where: Path, units_mm: float) -> None:
    """The imported calibration held to calibration.json's bounds (a plate of 1e298 mm: the wrong --units-mm),
    so that what import writes, every command reads."""
    from ..io import calibration_to_json, parse_calibration

    try:
        parse_calibration(calibration_to_json(cal), where)
    except AriSfmError as exc:
        raise AriSfmError(where, f"read with --units-mm {units_mm:g}: {exc.message}") from None

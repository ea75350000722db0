"""Export a calibration as a COLMAP model: the one pycolmap adapter of ari-sfm.

Every pycolmap call of the library lives in this module; the version is
checked at import. The way back
(refine-colmap) uses it too: :func:`model_from_reconstruction` reads a model as
arrays, :func:`refined_reconstruction` writes refined values into a copy (ids
kept), :func:`pinhole_approximation`, :func:`bundle_adjust` and
:func:`structure_from_motion` run COLMAP's own bundle adjustment and SfM (these
need pycolmap >= 3.12: rigs and frames).

What is exported. With the ``ari`` model and air behind the window, each
camera is *exactly* a pinhole camera (same K, same R, same distortion) whose
centre is displaced by ``delta = d (1 - 1/n)`` along the window normal: the
scene appears at ``X_app = X - delta n``, so the virtual camera has
``cam_from_world = (R, t - delta n_cam)``. That virtual camera is what COLMAP
receives, and COLMAP's projection of the exported points then equals
``Calibration.project_world`` to rounding error.

- ``exact`` model: the export is its best ari approximation, a pinhole
  camera fitted (least squares) to the exact model's pixels of the points
  each camera sees: the shift along the normal, then fx fy cx cy and the
  pose (``approximation="pinhole"``, default; ``"shift"`` keeps the
  calibration's K and R). The remaining error (the paraxial error, growing
  like t^3 with the incidence angle t) is measured, logged as a warning and
  returned.
- A medium behind the window (``medium_index != 1``): the paraxial picture is
  an affine map (the medium column's depth scales by 1/n_m), not a pure
  shift, so the export is again the best pure-shift approximation, fitted and
  warned about the same way.

COLMAP's model: one camera per rig camera (``PINHOLE`` without distortion,
``OPENCV`` with k1 k2 p1 p2, ``FULL_OPENCV`` when k3 != 0, its k4..k6 zero);
one rig whose reference sensor is the first camera (pycolmap >= 3.12); one
frame per calibration or reconstruction frame (the rig is static, so every
frame has the same ``rig_from_world``); one image per (camera, frame) with
the detected target corners as 2D points; 3D points: the corners of every
calibration frame placed by the calibrated target pose, and the points of
``points.json`` (reconstruction frames), each with its track. Stacking
images are not exported (their thicker window is another virtual camera).

Pixels: OpenCV puts (0, 0) at the centre of the top-left pixel, COLMAP at
its corner; :data:`COLMAP_PIXEL_OFFSET` (+0.5) converts, in
:func:`colmap_from_opencv_px` and :func:`opencv_from_colmap_px` only.
"""
from __future__ import annotations

import contextlib
import logging
import os
import re
import sys
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration.record import Calibration
from ..deps import import_pycolmap
from ..errors import AriSfmError
from ..geometry import Pose
from ..io import load_calibration
from ..provenance import observations_mismatch
from ..records import Dataset, Observation

log = logging.getLogger(__name__)

MIN_PYCOLMAP = (3, 11)
RIG_PYCOLMAP = (3, 12)  # rigs and frames (COLMAP 3.12)


def _version(text: str) -> tuple[int, int]:
    parts = []
    for p in text.split(".")[:2]:
        digits = "".join(ch for ch in p if ch.isdigit())
        parts.append(int(digits or 0))
    return (parts + [0, 0])[0], (parts + [0, 0])[1]


pycolmap = import_pycolmap(MIN_PYCOLMAP)

PYCOLMAP_VERSION = _version(getattr(pycolmap, "__version__", "0.0"))
if PYCOLMAP_VERSION < MIN_PYCOLMAP:  # pragma: no cover - depends on the installed version
    raise ImportError(f"ari_sfm.colmap.adapter needs pycolmap >= {MIN_PYCOLMAP[0]}.{MIN_PYCOLMAP[1]}, "
                      f"found {pycolmap.__version__}")
HAS_RIGS = PYCOLMAP_VERSION >= RIG_PYCOLMAP and hasattr(pycolmap, "Rig") and hasattr(pycolmap, "Frame")

COLMAP_PIXEL_OFFSET = 0.5  # COLMAP pixel = OpenCV pixel + 0.5 (origin at the pixel corner)
CALIBRATION_COLOR = (150, 150, 150)  # 3D points of calibration frames (grey)
RECONSTRUCTION_COLOR = (230, 80, 20)  # 3D points of points.json (orange)
EXPORT_SETS = ("calibration", "reconstruction")


def colmap_from_opencv_px(uv: np.ndarray) -> np.ndarray:
    """COLMAP pixels of OpenCV pixels (N, 2): the one place that adds 0.5."""
    return np.asarray(uv, float) + COLMAP_PIXEL_OFFSET


def opencv_from_colmap_px(uv: np.ndarray) -> np.ndarray:
    """OpenCV pixels of COLMAP pixels (N, 2)."""
    return np.asarray(uv, float) - COLMAP_PIXEL_OFFSET


# --------------------------------------------------------------------------- virtual cameras


@dataclass(frozen=True)
class VirtualCamera:
    """The pinhole camera COLMAP receives for one calibrated camera.

    ``cam_from_world`` is the calibrated pose with its centre moved by
    ``shift_mm`` along the window normal (``t - shift_mm * n_cam``), with K
    and pose re-fitted when the approximation is ``pinhole``. ``exact`` is
    True when this camera reproduces the calibration's model exactly (ari in
    air); ``rms_px`` / ``max_px`` measure the difference to the calibration's
    model on ``num_points`` sample points.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3, OpenCV
    cam_from_world: Pose
    shift_mm: float
    exact: bool
    rms_px: float
    max_px: float
    num_points: int


def _sample_points(calibration: Calibration, camera: str, points_world: np.ndarray | None) -> np.ndarray:
    """Points to fit and judge a camera's shift on: its exported points, else the frames' corners."""
    if points_world is not None and len(points_world) >= 3:
        return np.asarray(points_world, float)
    if calibration.target is not None and calibration.frames:
        _, xyz = calibration.target.points_3d()
        return np.concatenate([p.apply(xyz) for p in calibration.frames.values()])
    if calibration.frames:
        return np.array([p.t for p in calibration.frames.values()])
    raise AriSfmError(None, f"camera {camera}: no points to fit the exported camera on (no frames, no points)")


APPROXIMATIONS = ("pinhole", "shift")  # how a non-pinhole model is approximated (see virtual_camera)


def virtual_camera(calibration: Calibration, camera: str, points_world: np.ndarray | None = None,
                   approximation: str = "pinhole") -> VirtualCamera:
    """Give the pinhole camera COLMAP receives for a calibrated camera.

    ari in air: exact, (K, R, t - delta n_cam). Otherwise (exact model, or a
    medium behind the window) the best approximation on the camera's points.

    Args:
        calibration: the calibration.
        camera: the camera's name.
        points_world: the points the camera sees (N, 3), world frame, mm; None (or fewer than 3): the
            calibration frames' corners.
        approximation: ``"shift"`` fits only the shift along the normal (K and R held); ``"pinhole"``
            then also re-fits fx fy cx cy and the pose (distortion held), the best pure-shift pinhole
            camera in the least-squares sense.

    Returns:
        The virtual camera, with its difference to the calibration's model.

    Raises:
        ValueError: for an unknown ``approximation``.
        AriSfmError: if there are no points to fit the camera on.
    """
    from scipy.optimize import least_squares

    from ..geometry import rotation_from_rotvec
    from ..models import AriModel, PinholeModel

    if approximation not in APPROXIMATIONS:
        raise ValueError(f"approximation must be one of {APPROXIMATIONS}, got {approximation!r}")
    cam = calibration.cameras[camera]
    has_normal = getattr(calibration, "normal_world", None) is not None
    n_cam = calibration.normal_cam(camera) if has_normal else np.zeros(3)
    pinhole = PinholeModel(cam.K, cam.dist)
    model = calibration.projection_model(camera)
    X_world = _sample_points(calibration, camera, points_world)
    target_px = calibration.project_world(camera, X_world)
    ok = np.all(np.isfinite(target_px), axis=1)
    if points_world is None or len(points_world) < 3:  # frame corners: keep those inside the image
        W, H = cam.image_size
        inside = ok & (target_px[:, 0] >= -0.5) & (target_px[:, 0] <= W - 0.5) & (target_px[:, 1] >= -0.5) \
            & (target_px[:, 1] <= H - 0.5)
        ok = inside if inside.sum() >= 10 else ok
    X_world, target_px = X_world[ok], target_px[ok]
    X_cam = cam.cam_from_world.apply(X_world)
    no_window = type(model) is PinholeModel  # a model that ignores the window: the camera itself
    exact = no_window or (isinstance(model, AriModel) and calibration.interface_of(camera).medium_index == 1.0)
    if no_window or not has_normal:
        shift = 0.0
    elif exact:
        shift = calibration.interface_of(camera).shift_mm
    else:
        ari = calibration.projection_model(camera, model="ari")
        start = float(np.median((X_cam - ari.apparent_points(X_cam)) @ n_cam))

        def shift_residual(x: np.ndarray) -> np.ndarray:
            r = (pinhole.project(X_cam - x[0] * n_cam) - target_px).ravel()
            return np.where(np.isfinite(r), r, 1e3)

        shift = float(least_squares(shift_residual, [start], x_scale=[max(abs(start), 1.0)]).x[0])
    K, virtual = cam.K.copy(), Pose(cam.cam_from_world.R.copy(), cam.cam_from_world.t - shift * n_cam)
    if not exact and approximation == "pinhole":
        R0, t0, dist = virtual.R, virtual.t, np.resize(cam.dist, 5)

        def pinhole_residual(x: np.ndarray) -> np.ndarray:
            p = PinholeModel.from_params(np.concatenate([x[:4], dist]))
            r = (p.project(X_world @ (rotation_from_rotvec(x[4:7]) @ R0).T + t0 + x[7:]) - target_px).ravel()
            return np.where(np.isfinite(r), r, 1e3)

        x0 = np.concatenate([cam.params[:4], np.zeros(6)])
        x = least_squares(pinhole_residual, x0, x_scale=np.r_[1, 1, 1, 1, 1e-3, 1e-3, 1e-3, 1, 1, 1]).x
        K = np.array([[x[0], 0.0, x[2]], [0.0, x[1], x[3]], [0.0, 0.0, 1.0]])
        virtual = Pose(rotation_from_rotvec(x[4:7]) @ R0, t0 + x[7:])
    exported = PinholeModel(K, cam.dist).project(virtual.apply(X_world))
    diff = np.linalg.norm(exported - target_px, axis=1)
    return VirtualCamera(camera, K, np.resize(cam.dist, 5).astype(float), virtual, float(shift), exact,
                         float(np.sqrt(np.mean(diff**2))) if len(diff) else float("nan"),
                         float(diff.max()) if len(diff) else float("nan"), int(len(diff)))


# --------------------------------------------------------------------------- pycolmap objects


def _rigid3d(pose: Pose) -> Any:
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(pose.R, float)), np.asarray(pose.t, float))


def _colmap_camera(vc: VirtualCamera, camera_id: int, image_size: tuple[int, int]) -> Any:
    """PINHOLE, OPENCV or FULL_OPENCV camera of a virtual camera (principal point in COLMAP pixels)."""
    fx, fy = vc.K[0, 0], vc.K[1, 1]
    cx, cy = colmap_from_opencv_px(vc.K[:2, 2])
    k1, k2, p1, p2, k3 = vc.dist
    if not np.any(vc.dist):
        model, params = "PINHOLE", [fx, fy, cx, cy]
    elif k3 == 0.0:
        model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    else:
        model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    return pycolmap.Camera(model=model, width=int(image_size[0]), height=int(image_size[1]),
                           params=[float(p) for p in params], camera_id=camera_id)


@dataclass
class ColmapExport:
    """What :func:`export_colmap` wrote: the model, its folder and how our names map to COLMAP ids."""

    reconstruction: Any  # pycolmap.Reconstruction
    path: Path
    cameras: dict[str, VirtualCamera]
    camera_ids: dict[str, int]
    image_ids: dict[tuple[str, str], int]  # (camera, frame) -> image_id
    point3D_ids: dict[tuple[str, int], int]  # (frame, corner id) -> point3D_id
    warnings: list[str] = field(default_factory=list)
    ply_path: Path | None = None


def _frame_points(calibration: Calibration, points: Mapping[str, Any] | None) -> dict[str, dict[int, np.ndarray]]:
    """World points to export per frame: calibration frames' corners, then points.json's frames."""
    out: dict[str, dict[int, np.ndarray]] = {}
    if calibration.target is not None:
        ids, xyz = calibration.target.points_3d()
        for frame, pose in calibration.frames.items():
            out[frame] = dict(zip((int(i) for i in ids), pose.apply(xyz)))
    if points is not None:
        for frame, rec in points["frames"].items():
            if frame in out:
                log.warning("points.json frame %s is also a calibration frame: its points replace the target's", frame)
            out[frame] = {int(i): np.asarray(x, float) for i, x in zip(rec["ids"], rec["xyz"])}
    return out


def _image_name(obs: Observation, dataset: Dataset | None) -> str:
    """The dataset's image path (relative to its folder) when known, else set/camera/frame."""
    if dataset is not None:
        for entry in dataset.calibration + dataset.reconstruction:
            if entry.key == obs.frame and obs.camera in entry.images:
                try:
                    return entry.images[obs.camera].relative_to(dataset.root.resolve()).as_posix()
                except ValueError:
                    return entry.images[obs.camera].as_posix()
    return f"{obs.set}/{obs.camera}/{obs.frame}"


def _as_points(points: Any) -> Mapping[str, Any] | None:
    """points.json content from a path, a load_points mapping or an object with to_json()."""
    if points is None:
        return None
    if isinstance(points, (str, Path)):
        from ..io import load_points

        return load_points(points)
    if isinstance(points, Mapping):
        return points
    if hasattr(points, "to_json"):
        from ..io.points import parse_points

        return parse_points(points.to_json(), Path("points.json"))
    raise TypeError(f"points must be a points.json path or mapping, got {type(points).__name__}")


def _check_points_belong(points_data: Mapping[str, Any], points: Any, calibration: Calibration,
                         cal_path: Path | None, observations: Sequence[Observation]) -> None:
    """points.json of another calibration or dataset is an error, not silently left without tracks.

    Its recorded calibration hash (:mod:`ari_sfm.provenance`) must be the
    calibration file's; every frame must have observations to give its tracks.
    """
    from ..provenance import calibration_mismatch

    where = points if isinstance(points, (str, Path)) else "points.json"
    if cal_path is not None:
        why = calibration_mismatch(points_data, cal_path, calibration.model)
        if why:
            raise AriSfmError(where, f"{why}: export it with its own calibration")
    if observations:
        seen = {o.frame for o in observations if o.set == "reconstruction"}
        missing = [f for f in points_data["frames"] if f not in seen]
        if missing:
            raise AriSfmError(where, f"frame{'s' if len(missing) > 1 else ''} {', '.join(missing[:5])} "
                                     f"{'have' if len(missing) > 1 else 'has'} no reconstruction observations in "
                                     f"the dataset exported (points of another dataset?): no track to export")


def _observations(calibration: Calibration, dataset: Dataset | str | Path | None,
                  calibration_path: Path | None) -> tuple[Dataset | None, Sequence[Observation]]:
    """The dataset (if any) and the observations to export (dataset's, else observations.json beside CAL)."""
    from ..io import load_dataset, load_observations

    if isinstance(dataset, (str, Path)):
        dataset = load_dataset(dataset)
    if dataset is not None and dataset.observations is not None:
        return dataset, dataset.observations
    if calibration_path is not None and (calibration_path.parent / "observations.json").is_file():
        path = calibration_path.parent / "observations.json"
        log.info("observations from %s", path)
        return dataset, load_observations(path, calibration.target, list(calibration.cameras))
    if dataset is not None:
        raise AriSfmError(dataset.rig_path, "the dataset holds no observations (images only): run `ari-sfm detect` "
                                            "and pass --dataset with its observations.json")
    log.warning("no dataset and no observations.json beside the calibration: exporting cameras and poses only")
    return None, ()


def export_colmap(calibration: Calibration | str | Path, out_dir: str | Path,
                  dataset: Dataset | str | Path | None = None, points: Any = None,
                  approximation: str = "pinhole") -> ColmapExport:
    """Write a COLMAP model (binary) of a calibration to a folder, plus ``points3D.ply``.

    See the module docstring for what is exported and how exact it is: with the exact model
    or a medium behind the window, a warning gives the approximation error.

    Args:
        calibration: a Calibration or calibration.json path.
        out_dir: the output folder.
        dataset: a Dataset or folder whose observations give the images' 2D points (else
            ``observations.json`` beside the calibration file).
        points: points.json (path or mapping) of reconstruction frames, or None.
        approximation: see :func:`virtual_camera`.

    Returns:
        What was written: the model, its folder and how our names map to COLMAP ids.

    Raises:
        AriSfmError: if the observations or points are not the calibration's.
    """
    cal_path = None
    if isinstance(calibration, (str, Path)):
        cal_path = Path(calibration)
        calibration = load_calibration(cal_path)
    dataset, observations = _observations(calibration, dataset, cal_path)
    why = observations_mismatch(calibration, observations, dataset.target if dataset is not None else None)
    if why:  # the calibration's frames with another capture's corners: tracks of nonsense
        raise AriSfmError(dataset.root if dataset is not None
                          else cal_path.parent / "observations.json" if cal_path is not None else None, why)
    points_data = _as_points(points)
    out_dir = Path(out_dir)
    names = list(calibration.cameras)
    if dataset is not None:
        unknown = sorted({o.camera for o in observations} - set(names))
        if unknown:
            log.warning("cameras %s are not in the calibration: their images are not exported", ", ".join(unknown))
    observations = [o for o in observations if o.set in EXPORT_SETS and o.camera in calibration.cameras]
    if points_data is not None:
        _check_points_belong(points_data, points, calibration, cal_path, observations)
    frame_points = _frame_points(calibration, points_data)

    # virtual cameras, fitted on the points each camera sees
    seen = _seen_points(names, observations, frame_points)
    virtual = {n: virtual_camera(calibration, n, np.array(seen[n]) if seen[n] else None, approximation)
               for n in names}
    warnings = _approximation_warnings(calibration, virtual, approximation)
    for w in warnings:
        log.warning("%s", w)

    rec = pycolmap.Reconstruction()
    camera_ids = {n: k + 1 for k, n in enumerate(names)}
    for n in names:
        rec.add_camera(_colmap_camera(virtual[n], camera_ids[n], calibration.cameras[n].image_size))
    if HAS_RIGS:
        _add_rig(rec, names, camera_ids, virtual)
    image_ids, tracks = _add_images(rec, observations, dataset, names, camera_ids, virtual, frame_points)
    recon_frames = set(points_data["frames"]) if points_data is not None else set()
    point3D_ids = _add_points(rec, tracks, frame_points, recon_frames)
    rec.update_point_3d_errors()
    write_model(rec, out_dir)
    ply = out_dir / "points3D.ply"
    log.info("COLMAP model: %d cameras, %d images, %d points -> %s", len(names), len(image_ids), len(point3D_ids),
             out_dir)
    return ColmapExport(rec, out_dir, virtual, camera_ids, image_ids, point3D_ids, warnings, ply)


def _seen_points(names: list[str], observations: Sequence[Observation],
                 frame_points: dict[str, dict[int, np.ndarray]]) -> dict[str, list[np.ndarray]]:
    """Each camera's 3D points (those of ``frame_points`` its observations see), in observation order."""
    seen: dict[str, list[np.ndarray]] = {n: [] for n in names}
    for o in observations:
        pts = frame_points.get(o.frame, {})
        seen[o.camera].extend(pts[int(i)] for i in o.ids if int(i) in pts)
    return seen


def _add_rig(rec: Any, names: list[str], camera_ids: dict[str, int], virtual: dict[str, VirtualCamera]) -> None:
    """The COLMAP rig (id 1): the first camera the reference sensor, the others at their virtual poses."""
    ref = names[0]
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(rec.camera(camera_ids[ref]).sensor_id)
    ref_from_world_inv = virtual[ref].cam_from_world.inverse()
    for n in names[1:]:
        sensor_from_rig = virtual[n].cam_from_world.compose(ref_from_world_inv)
        rig.add_sensor(rec.camera(camera_ids[n]).sensor_id, _rigid3d(sensor_from_rig))
    rec.add_rig(rig)


def _add_images(rec: Any, observations: Sequence[Observation], dataset: Dataset | None, names: list[str],
                camera_ids: dict[str, int], virtual: dict[str, VirtualCamera],
                frame_points: dict[str, dict[int, np.ndarray]]
                ) -> tuple[dict[tuple[str, str], int], dict[tuple[str, int], list[tuple[int, int]]]]:
    """One COLMAP frame per calibration frame (sorted by name) with an image per camera that sees it.

    Returns:
        The image id of each (camera, frame), and the track of each (frame, corner) with a 3D point:
        its (image id, 2D point index) elements.
    """
    by_frame: dict[str, list[Observation]] = {}
    for o in observations:
        by_frame.setdefault(o.frame, []).append(o)
    image_ids: dict[tuple[str, str], int] = {}
    tracks: dict[tuple[str, int], list[tuple[int, int]]] = {}
    image_id = 0
    for frame_id, (frame, obs) in enumerate(sorted(by_frame.items()), start=1):
        images = []
        for o in sorted(obs, key=lambda o: names.index(o.camera)):
            image_id += 1
            image_ids[(o.camera, frame)] = image_id
            images.append(_colmap_image(o, dataset, image_id, camera_ids[o.camera], frame_id, virtual[o.camera]))
            for idx, corner in enumerate(int(i) for i in o.ids):
                if corner in frame_points.get(frame, {}):
                    tracks.setdefault((frame, corner), []).append((image_id, idx))
        if HAS_RIGS:
            colmap_frame = pycolmap.Frame(frame_id=frame_id, rig_id=1)
            colmap_frame.rig_from_world = _rigid3d(virtual[names[0]].cam_from_world)
            for image in images:
                colmap_frame.add_data_id(image.data_id)
            rec.add_frame(colmap_frame)
        for image in images:
            rec.add_image(image)
            if not HAS_RIGS:  # pragma: no cover - pycolmap 3.11
                rec.register_image(image.image_id)
    return image_ids, tracks


def _add_points(rec: Any, tracks: dict[tuple[str, int], list[tuple[int, int]]],
                frame_points: dict[str, dict[int, np.ndarray]], recon_frames: set[str]) -> dict[tuple[str, int], int]:
    """A COLMAP 3D point per track (reconstruction frames' points coloured apart); their ids."""
    point3D_ids: dict[tuple[str, int], int] = {}
    for (frame, corner), elements in sorted(tracks.items()):
        track = pycolmap.Track()
        for img, idx in elements:
            track.add_element(img, idx)
        color = RECONSTRUCTION_COLOR if frame in recon_frames else CALIBRATION_COLOR
        point3D_ids[(frame, corner)] = rec.add_point3D(np.asarray(frame_points[frame][corner], float), track,
                                                       np.array(color, dtype=np.uint8))
    return point3D_ids


def write_model(rec: Any, out_dir: str | Path, ply: bool = True) -> None:
    """Write a reconstruction as a binary COLMAP model: every file complete or none replaced.

    Each file's size is checked against the bytes its content needs before anything is replaced.

    Args:
        rec: the pycolmap.Reconstruction.
        out_dir: the output folder.
        ply: also write ``points3D.ply``.
    """
    from ..io import write_files_atomic

    def writer(tmp: Path) -> None:
        rec.write(str(tmp))
        if ply:
            rec.export_PLY(str(tmp / "points3D.ply"))

    def check(tmp: Path) -> None:
        for name, size in _minimum_sizes(rec).items():
            if not (tmp / name).is_file() or (tmp / name).stat().st_size < size:
                raise OSError(f"{name} was written short (a full disk?)")
        if ply:
            head = (tmp / "points3D.ply").read_bytes()[:4096]
            end = head.find(b"end_header\n")
            size = end + len(b"end_header\n") + 15 * rec.num_points3D()  # float xyz, uchar rgb per vertex
            if end < 0 or (tmp / "points3D.ply").stat().st_size < size:
                raise OSError("points3D.ply was written short (a full disk?)")

    write_files_atomic(out_dir, writer, check)


def _minimum_sizes(rec: Any) -> dict[str, int]:
    """The bytes COLMAP's binary format needs for ``rec``'s cameras, images and points (uint64 counts, then
    per record: ids, model, sizes, doubles; per 2D point x, y, point3D id; per track element two uint32)."""
    sizes = {
        "cameras.bin": 8 + sum(24 + 8 * len(c.params) for c in rec.cameras.values()),
        "images.bin": 8 + sum(4 + 56 + 4 + len(i.name.encode()) + 1 + 8 + 24 * len(i.points2D)
                              for i in rec.images.values()),
        "points3D.bin": 8 + sum(51 + 8 * p.track.length() for p in rec.points3D.values()),
    }
    if HAS_RIGS:
        sizes["frames.bin"] = 8 + sum(68 + 16 * f.num_data_ids() for f in rec.frames.values())
        sizes["rigs.bin"] = 8 + 16 * len(rec.rigs)
    return sizes


def _colmap_image(obs: Observation, dataset: Dataset | None, image_id: int, camera_id: int, frame_id: int,
                  virtual: VirtualCamera) -> Any:
    keypoints = colmap_from_opencv_px(obs.pixels)
    image = pycolmap.Image(name=_image_name(obs, dataset), keypoints=keypoints, camera_id=camera_id,
                           image_id=image_id)
    if HAS_RIGS:
        image.frame_id = frame_id
    else:  # pragma: no cover - pycolmap 3.11: the pose lives on the image
        image.cam_from_world = _rigid3d(virtual.cam_from_world)
    return image


def _approximation_warnings(calibration: Calibration, virtual: Mapping[str, VirtualCamera],
                            approximation: str) -> list[str]:
    """One warning when the exported pinholes only approximate the calibration's model."""
    if all(v.exact for v in virtual.values()):
        return []
    why = []
    if calibration.model != "ari":
        why.append(f"model '{calibration.model}' is not a pinhole: the export is its best ari approximation")
    if calibration.interface.medium_index != 1.0:
        why.append(f"medium_index {calibration.interface.medium_index:g} behind the window is not a pure shift: "
                   "the export is the best pure-shift approximation")
    how = ("K and pose re-fitted" if approximation == "pinhole" else "only the shift along the normal fitted")
    errs = ", ".join(f"{v.name} rms {v.rms_px:.3f} px max {v.max_px:.3f} px over {v.num_points} points"
                     for v in virtual.values())
    return [f"COLMAP export: {'; '.join(why)}; pinhole cameras with {how}: {errs}"]


def read_colmap(path: str | Path) -> Any:
    """Read a COLMAP model folder with pycolmap (a pycolmap.Reconstruction)."""
    path = Path(path)
    if not path.is_dir():
        raise AriSfmError(path, "not a COLMAP model folder")
    return pycolmap.Reconstruction(str(path))


def summary(export: ColmapExport) -> str:
    """A few lines about an export: counts, camera models and their exactness."""
    rec = export.reconstruction
    lines = [f"COLMAP model in {export.path}: {rec.num_cameras()} cameras, {rec.num_images()} images, "
             f"{rec.num_points3D()} points3D (pycolmap {pycolmap.__version__}"
             f"{', rig and frames' if HAS_RIGS else ''})"]
    for name, vc in export.cameras.items():
        cam = rec.camera(export.camera_ids[name])
        how = (f"centre shifted {vc.shift_mm:.4f} mm along the normal, exact" if vc.exact
               else "best pinhole approximation")
        lines.append(f"  {name}: camera {export.camera_ids[name]} {cam.model_name}, {how} "
                     f"(vs the calibration: rms {vc.rms_px:.2e} px, max {vc.max_px:.2e} px over "
                     f"{vc.num_points} points)")
    if export.ply_path is not None:
        lines.append(f"  point cloud: {export.ply_path}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- the way back: reading a model


# COLMAP camera models a refractive camera can hold: name -> indices into the COLMAP parameter vector of
# [fx, fy, cx, cy, k1, k2, p1, p2, k3] (-1: zero), and the COLMAP parameters that must be zero (held).
HELD_CAMERA_MODELS: dict[str, tuple[tuple[int, ...], tuple[int, ...]]] = {
    "SIMPLE_PINHOLE": ((0, 0, 1, 2, -1, -1, -1, -1, -1), ()),
    "PINHOLE": ((0, 1, 2, 3, -1, -1, -1, -1, -1), ()),
    "SIMPLE_RADIAL": ((0, 0, 1, 2, 3, -1, -1, -1, -1), ()),
    "RADIAL": ((0, 0, 1, 2, 3, 4, -1, -1, -1), ()),
    "OPENCV": ((0, 1, 2, 3, 4, 5, 6, 7, -1), ()),
    "FULL_OPENCV": ((0, 1, 2, 3, 4, 5, 6, 7, 8), (9, 10, 11)),
}


@dataclass(frozen=True)
class ColmapModel:
    """A COLMAP reconstruction as arrays (OpenCV pixels, our intrinsics vector), ids kept.

    Poses: ``cam_from_world`` of image i = ``sensor_from_rig[i] * rig_from_world[image_frame[i]]``.
    ``param_map[c]`` (9, k) and ``param_offset[c]`` (9,) give camera c's [fx fy cx cy k1 k2 p1 p2 k3]
    = map @ colmap_params + offset (the -0.5 px of COLMAP's pixel origin is in the offset).
    """

    camera_ids: np.ndarray  # (C,)
    camera_models: tuple[str, ...]
    image_sizes: tuple[tuple[int, int], ...]
    colmap_params: tuple[np.ndarray, ...]  # per camera, COLMAP order
    param_map: tuple[np.ndarray, ...]
    param_offset: tuple[np.ndarray, ...]
    frame_ids: np.ndarray  # (F,)
    rig_from_world: tuple[Pose, ...]  # (F,)
    image_ids: np.ndarray  # (I,)
    image_names: tuple[str, ...]
    image_camera: np.ndarray  # (I,) camera index
    image_frame: np.ndarray  # (I,) frame index
    sensor_from_rig: tuple[Pose, ...]  # (I,) identity for a rig's reference sensor
    point3D_ids: np.ndarray  # (P,)
    xyz: np.ndarray  # (P, 3)
    obs_image: np.ndarray  # (M,) image index
    obs_point: np.ndarray  # (M,) point index
    obs_uv: np.ndarray  # (M, 2) OpenCV pixels
    image_is_ref: np.ndarray | None = None  # (I,) the image's camera is its rig's reference sensor

    def params9(self, c: int, colmap_params: np.ndarray | None = None) -> np.ndarray:
        """Give camera c's [fx fy cx cy k1 k2 p1 p2 k3] (OpenCV pixels) from COLMAP parameters.

        Args:
            c: the camera's index.
            colmap_params: its COLMAP parameters (default: the model's).

        Returns:
            The 9 parameters.
        """
        p = self.colmap_params[c] if colmap_params is None else colmap_params
        return self.param_map[c] @ p + self.param_offset[c]


def _pose(rigid: Any) -> Pose:
    return Pose(np.array(rigid.rotation.matrix(), float), np.array(rigid.translation, float))


def model_from_reconstruction(rec: Any, path: str | Path = "reconstruction") -> ColmapModel:
    """Read a pycolmap.Reconstruction as arrays.

    Args:
        rec: the pycolmap.Reconstruction.
        path: the model named in an error.

    Returns:
        The model's arrays, ids kept.

    Raises:
        AriSfmError: one line, for a model that cannot be refined (no points3D, no observations, a camera
            model a refractive camera cannot hold).
    """
    if rec.num_points3D() == 0:
        raise AriSfmError(path, "the COLMAP model has no points3D (run the mapper first)")
    cams = sorted(rec.cameras.items())
    camera_index = {cid: k for k, (cid, _) in enumerate(cams)}
    names, sizes, params, maps, offsets = [], [], [], [], []
    for cid, cam in cams:
        name = cam.model_name if hasattr(cam, "model_name") else str(cam.model.name)
        if name not in HELD_CAMERA_MODELS:
            raise AriSfmError(path, f"camera {cid}: COLMAP model {name} cannot be held by a refractive camera "
                                    f"(supported: {', '.join(HELD_CAMERA_MODELS)})")
        idx, zero = HELD_CAMERA_MODELS[name]
        p = np.array(cam.params, float)
        if zero and np.any(p[list(zero)] != 0.0):
            raise AriSfmError(path, f"camera {cid}: {name} with non-zero k4..k6 cannot be held (OpenCV 5 coefficients)")
        M = np.zeros((9, len(p)))
        for row, col in enumerate(idx):
            if col >= 0:
                M[row, col] = 1.0
        names.append(name)
        sizes.append((int(cam.width), int(cam.height)))
        params.append(p)
        maps.append(M)
        offsets.append(np.r_[0.0, 0.0, -COLMAP_PIXEL_OFFSET, -COLMAP_PIXEL_OFFSET, np.zeros(5)])
    frames = sorted((fid, f) for fid, f in rec.frames.items() if f.has_pose)
    frame_index = {fid: k for k, (fid, _) in enumerate(frames)}
    image_ids: list[int] = []
    image_names, image_camera, image_frame, sensor_from_rig, is_ref = [], [], [], [], []
    obs_image, obs_point, obs_uv = [], [], []
    point_ids = np.array(sorted(rec.point3D_ids()), dtype=np.int64)
    point_index = {int(p): k for k, p in enumerate(point_ids)}
    for iid, image in sorted(rec.images.items()):
        if not image.has_pose or image.frame_id not in frame_index:
            continue
        frame = rec.frame(image.frame_id)
        rig = rec.rig(frame.rig_id)
        sensor = rec.camera(image.camera_id).sensor_id
        is_ref.append(bool(rig.is_ref_sensor(sensor)))
        s_from_r = Pose.identity() if is_ref[-1] else _pose(rig.sensor_from_rig(sensor))
        k = len(image_ids)
        image_ids.append(iid)
        image_names.append(image.name)
        image_camera.append(camera_index[image.camera_id])
        image_frame.append(frame_index[image.frame_id])
        sensor_from_rig.append(s_from_r)
        for p2 in image.points2D:
            if p2.has_point3D():
                obs_image.append(k)
                obs_point.append(point_index[int(p2.point3D_id)])
                obs_uv.append(p2.xy)
    if not obs_image:
        raise AriSfmError(path, "the COLMAP model has no observations of its points3D in posed images")
    xyz = np.array([rec.point3D(int(p)).xyz for p in point_ids], float)
    return ColmapModel(
        np.array([c for c, _ in cams]), tuple(names), tuple(sizes), tuple(params), tuple(maps), tuple(offsets),
        np.array([f for f, _ in frames]), tuple(_pose(f.rig_from_world) for _, f in frames),
        np.array(image_ids), tuple(image_names), np.array(image_camera), np.array(image_frame),
        tuple(sensor_from_rig), point_ids, xyz, np.array(obs_image), np.array(obs_point),
        opencv_from_colmap_px(np.array(obs_uv, float).reshape(-1, 2)), np.array(is_ref))


def refined_reconstruction(rec: Any, model: ColmapModel, colmap_params: Sequence[np.ndarray],
                           rig_from_world: Sequence[Pose], sensor_from_rig: Mapping[int, Pose],
                           xyz: np.ndarray) -> Any:
    """Copy a reconstruction (ids kept) with new camera parameters, frame poses, rig sensors and points.

    Args:
        rec: the pycolmap.Reconstruction.
        model: its arrays (:func:`model_from_reconstruction`).
        colmap_params: each camera's new COLMAP parameters, in ``model.camera_ids`` order.
        rig_from_world: each frame's new pose, in ``model.frame_ids`` order.
        sensor_from_rig: camera id -> the new sensor_from_rig of a non-reference sensor.
        xyz: the points' new positions (P, 3), in ``model.point3D_ids`` order.

    Returns:
        The new pycolmap.Reconstruction.
    """
    out = pycolmap.Reconstruction(rec)
    for c, cid in enumerate(model.camera_ids):
        cam = out.camera(int(cid))
        cam.params = np.asarray(colmap_params[c], float)
    for f, fid in enumerate(model.frame_ids):
        out.frame(int(fid)).rig_from_world = _rigid3d(rig_from_world[f])
    for cid, pose in sensor_from_rig.items():
        sensor = out.camera(int(cid)).sensor_id
        for rig in out.rigs.values():
            if rig.has_sensor(sensor) and not rig.is_ref_sensor(sensor):
                rig.set_sensor_from_rig(sensor, _rigid3d(pose))
    for k, pid in enumerate(model.point3D_ids):
        out.point3D(int(pid)).xyz = np.asarray(xyz[k], float)
    out.update_point_3d_errors()
    return out


_GLOG_INFO = re.compile(rb"^I\d{8} ")  # a glog INFO line: I<yyyymmdd> <time> <thread> <file:line>] ...


@contextlib.contextmanager
def colmap_quiet(hold_stderr: bool = True) -> Iterator[None]:
    """Show COLMAP's own INFO lines (glog) inside only when this module logs at INFO (the CLI's -v).

    Some of its calls (the bundle adjustment's) print them whatever pycolmap.logging.minloglevel says.

    Args:
        hold_stderr: hold the standard error written meanwhile and give it back without them (warnings
            and errors kept); not for a call that shows progress there.

    Yields:
        Nothing; COLMAP is quiet until the context closes.
    """
    if log.isEnabledFor(logging.INFO):
        yield
        return
    level = getattr(pycolmap.logging, "minloglevel", None)
    if level is not None:
        pycolmap.logging.minloglevel = max(level, 1)
    if not hold_stderr:
        try:
            yield
        finally:
            if level is not None:
                pycolmap.logging.minloglevel = level
        return
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            if level is not None:
                pycolmap.logging.minloglevel = level
            held.seek(0)
            kept = [line for line in held.read().splitlines(keepends=True) if not _GLOG_INFO.match(line)]
            if kept:
                os.write(2, b"".join(kept))


def pinhole_approximation(rec: Any, opencv_params: Mapping[int, np.ndarray] | None = None) -> Any:
    """Run COLMAP's own bundle adjustment of cameras (principal point included) and poses, the points held.

    The result is the best approximation, in COLMAP's camera models, of cameras whose 3D points are right.

    Args:
        rec: the pycolmap.Reconstruction (not modified).
        opencv_params: camera_id -> OPENCV parameters [fx fy cx cy k1 k2 p1 p2] (COLMAP pixels) to turn
            those cameras into OPENCV cameras first; None for none.

    Returns:
        The adjusted copy.
    """
    out = pycolmap.Reconstruction(rec)
    for cid, params in (opencv_params or {}).items():
        cam = out.camera(int(cid))
        cam.model = pycolmap.CameraModelId.OPENCV
        cam.params = np.asarray(params, float)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_points3D = False
    options.refine_principal_point = True
    options.print_summary = False
    with colmap_quiet():
        pycolmap.bundle_adjustment(out, options)
    out.update_point_3d_errors()
    return out


def bundle_adjust(rec: Any) -> Any:
    """pycolmap's own bundle adjustment (default options) of a copy of ``rec``."""
    out = pycolmap.Reconstruction(rec)
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    with colmap_quiet():
        pycolmap.bundle_adjustment(out, options)
    return out


def image_residuals_px(rec: Any, model: ColmapModel | None = None) -> dict[int, float]:
    """Measure the RMS reprojection error per image under COLMAP's own cameras.

    Args:
        rec: the pycolmap.Reconstruction.
        model: its arrays, if already read (:func:`model_from_reconstruction`).

    Returns:
        Image id -> RMS reprojection error (px), for images with observations.
    """
    model = model_from_reconstruction(rec) if model is None else model
    X_cam = np.empty((len(model.obs_image), 3))
    for i, iid in enumerate(model.image_ids):
        sel = model.obs_image == i
        pose = _pose(rec.image(int(iid)).cam_from_world())
        X_cam[sel] = pose.apply(model.xyz[model.obs_point[sel]])
    err2 = np.zeros(len(X_cam))
    for c, cid in enumerate(model.camera_ids):
        sel = model.image_camera[model.obs_image] == c
        uv = rec.camera(int(cid)).img_from_cam(X_cam[sel], check_cheirality=False)
        err2[sel] = np.sum((opencv_from_colmap_px(uv) - model.obs_uv[sel]) ** 2, axis=1)
    sums = np.bincount(model.obs_image, err2, len(model.image_ids))
    counts = np.bincount(model.obs_image, minlength=len(model.image_ids))
    return {int(iid): float(np.sqrt(sums[i] / counts[i])) for i, iid in enumerate(model.image_ids) if counts[i]}


def reconstruction_from_arrays(params: Sequence[np.ndarray], image_size: tuple[int, int],
                               sensor_from_rig: Sequence[Pose], rig_from_world: Sequence[Pose],
                               image_camera: np.ndarray, image_frame: np.ndarray, xyz: np.ndarray,
                               obs_image: np.ndarray, obs_point: np.ndarray, obs_uv: np.ndarray) -> Any:
    """Build a pycolmap.Reconstruction of PINHOLE cameras from arrays.

    One rig (camera 0 its reference sensor), one frame per ``rig_from_world``, image i = (image_camera[i],
    image_frame[i]) with id i + 1, point k with id k + 1.

    Args:
        params: each camera's [fx fy cx cy ...], OpenCV pixels.
        image_size: the image size (w, h) of every camera.
        sensor_from_rig: each camera's pose in the rig (camera 0's unused).
        rig_from_world: each frame's pose.
        image_camera: each image's camera index (I,).
        image_frame: each image's frame index (I,).
        xyz: the points (P, 3).
        obs_image: each observation's image index (M,).
        obs_point: each observation's point index (M,).
        obs_uv: each observation's pixel (M, 2), OpenCV pixels.

    Returns:
        The pycolmap.Reconstruction.
    """
    rec = pycolmap.Reconstruction()
    for c, p in enumerate(params):
        cx, cy = colmap_from_opencv_px(np.asarray(p[2:4], float))
        rec.add_camera(pycolmap.Camera(model="PINHOLE", width=int(image_size[0]), height=int(image_size[1]),
                                       params=[float(p[0]), float(p[1]), float(cx), float(cy)], camera_id=c + 1))
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(rec.camera(1).sensor_id)
    for c in range(1, len(params)):
        rig.add_sensor(rec.camera(c + 1).sensor_id, _rigid3d(sensor_from_rig[c]))
    rec.add_rig(rig)
    order = np.argsort(obs_image, kind="stable")
    starts = np.searchsorted(obs_image[order], np.arange(len(image_camera) + 1))
    index_in_image = np.empty(len(obs_image), int)
    images = []
    for i in range(len(image_camera)):
        sel = order[starts[i]:starts[i + 1]]
        index_in_image[sel] = np.arange(len(sel))
        image = pycolmap.Image(name=f"image{i + 1:04d}.png", keypoints=colmap_from_opencv_px(obs_uv[sel]),
                               camera_id=int(image_camera[i]) + 1, image_id=i + 1)
        image.frame_id = int(image_frame[i]) + 1
        images.append(image)
    for f, pose in enumerate(rig_from_world):
        frame = pycolmap.Frame(frame_id=f + 1, rig_id=1)
        frame.rig_from_world = _rigid3d(pose)
        for idx in np.flatnonzero(np.asarray(image_frame) == f):
            frame.add_data_id(images[idx].data_id)
        rec.add_frame(frame)
    for image in images:
        rec.add_image(image)
    porder = np.argsort(obs_point, kind="stable")
    pstarts = np.searchsorted(obs_point[porder], np.arange(len(xyz) + 1))
    for k in range(len(xyz)):
        track = pycolmap.Track()
        for o in porder[pstarts[k]:pstarts[k + 1]]:
            track.add_element(int(obs_image[o]) + 1, int(index_in_image[o]))
        rec.add_point3D(np.asarray(xyz[k], float), track, np.array(CALIBRATION_COLOR, np.uint8))
    rec.update_point_3d_errors()
    return rec


SFM_MATCHERS = ("exhaustive", "sequential")  # structure_from_motion's image pairings
SFM_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


def structure_from_motion(image_dir: str | Path, work_dir: str | Path, focal_px: float | None = None,
                          max_features: int = 4000, seed: int = 0, matcher: str = "exhaustive",
                          overlap: int = 10, num_threads: int = -1, on_step: Any = None,
                          on_image: Any = None) -> Any:
    """Run COLMAP's own SfM on a folder of images: CPU SIFT, matching, incremental mapping.

    One PINHOLE camera for all images.

    Args:
        image_dir: the folder of images.
        work_dir: the working folder (its database.db is replaced; the models go under sparse/).
        focal_px: the camera's focal length prior (px), or None.
        max_features: the most SIFT features per image.
        seed: the mapper's random seed.
        matcher: ``"exhaustive"``, or ``"sequential"``: each image paired with its ``overlap`` successors
            in name order (no vocabulary tree: for long surveys).
        overlap: the successors of the sequential matcher.
        num_threads: the threads; -1: all cores.
        on_step: ``on_step(name)`` is called before each step (progress), or None.
        on_image: ``on_image()`` is called when the mapper registers an image (progress), or None.

    Returns:
        The largest reconstruction (a pycolmap.Reconstruction).

    Raises:
        ValueError: for an unknown ``matcher``.
        AriSfmError: if an image cannot be read or the mapping reconstructs nothing.
    """
    if matcher not in SFM_MATCHERS:
        raise ValueError(f"matcher must be one of {', '.join(SFM_MATCHERS)} (got {matcher!r})")
    with colmap_quiet(hold_stderr=False):  # its progress bar is on the standard error
        return _structure_from_motion(image_dir, work_dir, focal_px, max_features, seed, matcher, overlap,
                                      num_threads, on_step, on_image)


def _structure_from_motion(image_dir, work_dir, focal_px, max_features, seed, matcher, overlap, num_threads,
                           on_step, on_image) -> Any:
    image_dir, work_dir = Path(image_dir), Path(work_dir)
    step = on_step or (lambda name: None)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    if database.exists():
        database.unlink()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    if focal_px is not None:
        import cv2

        first = sorted(p for p in image_dir.iterdir() if p.suffix.lower() in SFM_IMAGE_SUFFIXES)[0]
        pixels = cv2.imread(str(first), cv2.IMREAD_GRAYSCALE)
        if pixels is None:
            raise AriSfmError(first, "cannot read image (corrupt, truncated or not an image)")
        h, w = pixels.shape
        reader.camera_params = f"{focal_px},{focal_px},{w / 2},{h / 2}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = max_features
    extraction.use_gpu = False
    extraction.num_threads = num_threads
    step("features")
    pycolmap.extract_features(database, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = num_threads
    step("matching")
    if matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = int(overlap)
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
    else:
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    options.num_threads = num_threads
    step("mapping")
    models = pycolmap.incremental_mapping(database, image_dir, work_dir / "sparse", options,
                                          next_image_callback=on_image)
    if not models:
        raise AriSfmError(work_dir, "COLMAP's incremental mapping reconstructed nothing")
    return max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))

"""Export a calibration as a COLMAP model: the one pycolmap adapter of ari-sfm.

Every pycolmap call of the library lives in this module (its API changed
between 3.11, 3.12 and 4.x); the version is checked at import.

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
  returned (binocular simulation, 10-15 deg oblique: 0.4 px RMS, 2.2 px max).
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

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from .calibration import Calibration, load_calibration
from .errors import AriSfmError
from .geometry import Pose
from .records import Dataset, Observation

log = logging.getLogger(__name__)

MIN_PYCOLMAP = (3, 11)
RIG_PYCOLMAP = (3, 12)  # rigs and frames (COLMAP 3.12)


def _version(text: str) -> tuple[int, int]:
    parts = []
    for p in text.split(".")[:2]:
        digits = "".join(ch for ch in p if ch.isdigit())
        parts.append(int(digits or 0))
    return (parts + [0, 0])[0], (parts + [0, 0])[1]


try:
    import pycolmap
except ImportError as exc:  # pragma: no cover - pycolmap is a dependency
    raise ImportError(f"ari_sfm.colmap_export needs pycolmap >= {MIN_PYCOLMAP[0]}.{MIN_PYCOLMAP[1]} "
                      f"(pip install pycolmap): {exc}") from exc

PYCOLMAP_VERSION = _version(getattr(pycolmap, "__version__", "0.0"))
if PYCOLMAP_VERSION < MIN_PYCOLMAP:  # pragma: no cover - depends on the installed version
    raise ImportError(f"ari_sfm.colmap_export needs pycolmap >= {MIN_PYCOLMAP[0]}.{MIN_PYCOLMAP[1]}, "
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
    """The pinhole camera COLMAP receives for ``camera``.

    ari in air: exact, (K, R, t - delta n_cam). Otherwise (exact model, or a
    medium behind the window) the best approximation on ``points_world`` (the
    points the camera sees; the calibration frames' corners when None):
    ``approximation="shift"`` fits only the shift along the normal (K and R
    held); ``"pinhole"`` (default) then also re-fits fx fy cx cy and the pose
    (distortion held), the best pure-shift pinhole camera in the least-squares
    sense, which absorbs about two thirds of the paraxial error.
    """
    from scipy.optimize import least_squares

    from .geometry import rotation_from_rotvec
    from .models import AriModel, PinholeModel

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
    exact = no_window or (isinstance(model, AriModel) and calibration.interface.medium_index == 1.0)
    if no_window or not has_normal:
        shift = 0.0
    elif exact:
        shift = calibration.interface.shift_mm
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
        from .io import load_points

        return load_points(points)
    if isinstance(points, Mapping):
        return points
    if hasattr(points, "to_json"):
        from .io.points import parse_points

        return parse_points(points.to_json(), Path("points.json"))
    raise TypeError(f"points must be a points.json path or mapping, got {type(points).__name__}")


def _check_points_belong(points_data: Mapping[str, Any], points: Any, calibration: Calibration,
                         cal_path: Path | None, observations: Sequence[Observation]) -> None:
    """points.json of another calibration or dataset is an error, not silently left without tracks.

    Its recorded calibration hash (:mod:`ari_sfm.provenance`) must be the
    calibration file's; every frame must have observations to give its tracks.
    """
    from .provenance import calibration_mismatch

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
    from .io import load_dataset, load_observations

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
    """Write a COLMAP model (binary) of a calibration to ``out_dir``, plus ``points3D.ply``.

    ``calibration``: a Calibration or calibration.json path; ``dataset``: a
    Dataset or folder whose observations give the images' 2D points (else
    ``observations.json`` beside the calibration file); ``points``:
    points.json (path or mapping) of reconstruction frames. See the module
    docstring for what is exported and how exact it is: with the exact model
    or a medium behind the window, a warning gives the approximation error
    (``approximation``: see :func:`virtual_camera`).
    """
    cal_path = None
    if isinstance(calibration, (str, Path)):
        cal_path = Path(calibration)
        calibration = load_calibration(cal_path)
    dataset, observations = _observations(calibration, dataset, cal_path)
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
    seen: dict[str, list[np.ndarray]] = {n: [] for n in names}
    for o in observations:
        pts = frame_points.get(o.frame, {})
        seen[o.camera].extend(pts[int(i)] for i in o.ids if int(i) in pts)
    virtual = {n: virtual_camera(calibration, n, np.array(seen[n]) if seen[n] else None, approximation)
               for n in names}
    warnings = _approximation_warnings(calibration, virtual, approximation)
    for w in warnings:
        log.warning("%s", w)

    rec = pycolmap.Reconstruction()
    camera_ids = {n: k + 1 for k, n in enumerate(names)}
    for n in names:
        rec.add_camera(_colmap_camera(virtual[n], camera_ids[n], calibration.cameras[n].image_size))
    ref = names[0]
    if HAS_RIGS:
        rig = pycolmap.Rig(rig_id=1)
        rig.add_ref_sensor(rec.camera(camera_ids[ref]).sensor_id)
        ref_from_world_inv = virtual[ref].cam_from_world.inverse()
        for n in names[1:]:
            sensor_from_rig = virtual[n].cam_from_world.compose(ref_from_world_inv)
            rig.add_sensor(rec.camera(camera_ids[n]).sensor_id, _rigid3d(sensor_from_rig))
        rec.add_rig(rig)

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
            colmap_frame.rig_from_world = _rigid3d(virtual[ref].cam_from_world)
            for image in images:
                colmap_frame.add_data_id(image.data_id)
            rec.add_frame(colmap_frame)
        for image in images:
            rec.add_image(image)
            if not HAS_RIGS:  # pragma: no cover - pycolmap 3.11
                rec.register_image(image.image_id)

    recon_frames = set(points_data["frames"]) if points_data is not None else set()
    point3D_ids: dict[tuple[str, int], int] = {}
    for (frame, corner), elements in sorted(tracks.items()):
        track = pycolmap.Track()
        for img, idx in elements:
            track.add_element(img, idx)
        color = RECONSTRUCTION_COLOR if frame in recon_frames else CALIBRATION_COLOR
        point3D_ids[(frame, corner)] = rec.add_point3D(np.asarray(frame_points[frame][corner], float), track,
                                                       np.array(color, dtype=np.uint8))
    rec.update_point_3d_errors()
    out_dir.mkdir(parents=True, exist_ok=True)
    rec.write(str(out_dir))
    ply = out_dir / "points3D.ply"
    rec.export_PLY(str(ply))
    log.info("COLMAP model: %d cameras, %d images, %d points -> %s", len(names), len(image_ids), len(point3D_ids), out_dir)
    return ColmapExport(rec, out_dir, virtual, camera_ids, image_ids, point3D_ids, warnings, ply)


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
                     f"(vs the calibration: rms {vc.rms_px:.2e} px, max {vc.max_px:.2e} px over {vc.num_points} points)")
    if export.ply_path is not None:
        lines.append(f"  point cloud: {export.ply_path}")
    return "\n".join(lines)

"""calibration.json read, validated and written (docs/DATASET_FORMAT.md).

As the rig files are by :mod:`ari_sfm.io.dataset`: :func:`load_calibration`, :func:`save_calibration`
(atomic), :func:`parse_calibration` (a parsed mapping, e.g. a simulator's truth) and
:func:`calibration_to_json`. A defect is one line, ``AriSfmError(path, message)``, naming the key; values
are held to rig.yaml's bounds (:mod:`ari_sfm.io.calibration_checks`). The record itself is
:class:`ari_sfm.calibration.record.Calibration`.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.calibration.origin import ImportedFrom, RefineColmapFrames
from ari_sfm.calibration.quality import Quality
from ari_sfm.calibration.record import Calibration, CameraCalibration, WindowCalibration
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import Pose
from ari_sfm.io.atomic import write_json_atomic
from ari_sfm.io.calibration_checks import check_calibration_values
from ari_sfm.io.dataset import MAX_FOCAL_PX, MAX_IMAGE_SIDE_PX, MAX_LENGTH_MM, parse_target, target_to_json
from ari_sfm.io.structured import check_at_most, read_structured
from ari_sfm.models.polynomial import PolynomialMap
from ari_sfm.models.registry import model_spec
from ari_sfm.particles.selfcal_report import SelfCalReport
from ari_sfm.records import Interface
from ari_sfm.results import (
    OptimizerReport,
    OutlierReport,
    PfWorld,
    ResidualStats,
    StageRecord,
    Uncertainty,
    stages_from_json,
)

FORMAT = "ari-sfm-calibration/1"


def load_calibration(path: str | Path) -> Calibration:
    """Read and validate calibration.json (or a simulator's truth.json).

    Args:
        path: the file (JSON or YAML).

    Returns:
        The calibration.

    Raises:
        AriSfmError: the file cannot be read or is not a valid calibration (one line naming the key).
    """
    return parse_calibration(read_structured(Path(path)), path)


def save_calibration(calibration: Calibration, path: str | Path) -> None:
    """Write calibration.json atomically.

    Args:
        calibration: the calibration to write.
        path: the file to write.

    Raises:
        AriSfmError: the file cannot be written, or a value is NaN or infinite.
    """
    write_json_atomic(Path(path), calibration_to_json(calibration))


def calibration_to_json(cal: Calibration) -> dict[str, Any]:
    """The calibration.json mapping of a calibration (docs/DATASET_FORMAT.md)."""
    cams = {}
    for name, c in cal.cameras.items():
        entry: dict[str, Any] = {
            "image_size": [int(s) for s in c.image_size],
            "K": c.K.tolist(),
            "dist": np.resize(c.dist, 5).tolist(),
            "cam_from_world": c.cam_from_world.to_json(),
        }
        if cal.windows:
            entry["window"] = cal.window_of(name).name
        if cal.window_of(name).normal_world is not None:
            entry["normal_cam"] = cal.normal_cam(name).tolist()
        if c.expansion_center_px is not None:
            entry["expansion_center_px"] = np.asarray(c.expansion_center_px).tolist()
        if c.expansion_center_std_px is not None:
            entry["expansion_center_std_px"] = np.asarray(c.expansion_center_std_px).tolist()
        entry["distance_mm"] = cal.distance_mm(name)
        if c.rmse_px is not None:
            entry["rmse_px"] = c.rmse_px
        if c.pf is not None:
            if cal.pf_world is None:
                raise ValueError(f"camera {name} has a pf polynomial, the calibration no pf_world")
            entry["pf"] = c.pf.to_json(cal.pf_world.model)
        entry.update(c.extra)
        cams[name] = entry
    if cal.windows:
        windows: dict[str, Any] = {"interfaces": {w.name: {"cameras": list(w.cameras), **_window_json(w)}
                                                  for w in cal.windows}}
    else:
        windows = {"interface": _window_json(cal.window_list()[0])}
        windows["interface"].pop("fixed_distance_mm", None)  # top-level in a one-window calibration
    out = {
        "format": FORMAT,
        "model": cal.model,
        **windows,
        "cameras": cams,
        "frames": {f: {"world_from_target": p.to_json()} for f, p in cal.frames.items()},
    }
    if cal.stacking_poses:
        out["stacking_poses"] = {f: {"world_from_target": p.to_json()} for f, p in cal.stacking_poses.items()}
    if cal.target is not None:
        out["target"] = target_to_json(cal.target)
    out["residuals"] = {} if cal.residuals is None else cal.residuals.to_json()
    out["time_s"] = cal.time_s
    if cal.optimizer is not None:
        out["optimizer"] = cal.optimizer.to_json()
    if cal.stages:
        out["stages"] = [st.to_json() for st in cal.stages]
    out.update(cal.extra)
    for key, record in (("pf_world", cal.pf_world), ("uncertainty", cal.uncertainty),
                        ("outliers", cal.outliers), ("quality", cal.quality),
                        ("self_calibration", cal.self_calibration), ("refine_colmap", cal.refine_colmap),
                        ("imported_from", cal.imported_from)):
        if record is not None:
            out[key] = record.to_json()
    if cal.window_ignored:
        out["window_ignored"] = True
    if cal.fixed_distance_mm is not None and not cal.windows:
        out["fixed_distance_mm"] = cal.fixed_distance_mm
    return out


def _window_json(w: WindowCalibration) -> dict[str, Any]:
    """A window's ``interface`` mapping (with ``fixed_distance_mm`` when it has one)."""
    out = {"normal_world": None if w.normal_world is None else np.asarray(w.normal_world).tolist(),
           "thickness_mm": w.interface.thickness_mm, "index": w.interface.index,
           "medium_index": w.interface.medium_index, "distance_mm": w.interface.distance_mm}
    if w.fixed_distance_mm is not None:
        out["fixed_distance_mm"] = w.fixed_distance_mm
    return out


def parse_calibration(data: Any, path: str | Path = "calibration.json") -> Calibration:
    """Parse and validate a calibration.json mapping.

    Args:
        data: the mapping, as read from the file (or built in memory, e.g. a simulator's truth).
        path: the file it came from, for error messages.

    Returns:
        The calibration.

    Raises:
        AriSfmError: ``data`` is not a valid calibration (one line naming the key).
    """
    try:
        return _parse(data, path)
    except AriSfmError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        what = f"missing key {exc}" if isinstance(exc, KeyError) else str(exc)
        raise AriSfmError(path, f"malformed calibration: {what}") from None


def _finite(a: Any, shape: tuple[int, ...], what: str, path: Any) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.shape != shape:
        raise AriSfmError(path, f"{what} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise AriSfmError(path, f"{what} contains non-finite values")
    return arr


MAX_POSE_TRANSLATION_MM = 1e9  # 1000 km: a pose farther away is a typo (1e300 projected every corner to NaN)


def _pose(d: Any, what: str, path: Any) -> Pose:
    R = _finite(d["R"], (3, 3), f"{what}.R", path)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise AriSfmError(path, f"{what}.R is not a rotation matrix")
    t = _finite(d["t"], (3,), f"{what}.t", path)
    if float(np.max(np.abs(t))) > MAX_POSE_TRANSLATION_MM:
        raise AriSfmError(path,
                          f"{what}.t: {float(np.max(np.abs(t))):.3g} mm is beyond {MAX_POSE_TRANSLATION_MM:.0e} mm "
                                "(1000 km): not a pose of this rig")
    return Pose(R, t)


def _check_bounds(cams: dict[str, CameraCalibration], thickness: float, path: Any) -> None:
    """The sane physical bounds of the rig file (io.dataset) hold for a calibration too."""
    check_at_most(thickness, MAX_LENGTH_MM, path, "interface.thickness_mm", " mm")
    for name, c in cams.items():
        if min(c.image_size) < 1:
            raise AriSfmError(path, f"cameras.{name}.image_size must be two integers >= 1 (got {list(c.image_size)})")
        check_at_most(max(c.image_size), MAX_IMAGE_SIDE_PX, path, f"cameras.{name}.image_size", " px")
        fx, fy = float(c.K[0, 0]), float(c.K[1, 1])
        if fx <= 0 or fy <= 0:
            raise AriSfmError(path, f"cameras.{name}.K must have positive focal lengths (got fx={fx:g}, fy={fy:g})")
        check_at_most(max(fx, fy), MAX_FOCAL_PX, path, f"cameras.{name}.K focal length", " px")


def _parse(data: Any, path: Any) -> Calibration:
    if not isinstance(data, dict):
        raise AriSfmError(path, "calibration must be a JSON object")
    if data.get("format") != FORMAT:
        raise AriSfmError(path, f"unknown format {data.get('format')!r} (expected {FORMAT!r})")
    spec = model_spec(data["model"], path)
    model = spec.name
    check_calibration_values(data, path, window=spec.window)  # rig.yaml's bounds (ari_sfm.io.calibration_checks)
    if "interface" in data and "interfaces" in data:
        raise AriSfmError(path, "give interface (one window) or interfaces (several), not both")
    if "interfaces" in data:
        if not isinstance(data["interfaces"], dict) or not data["interfaces"]:
            raise AriSfmError(path, "interfaces must be a non-empty object (window name -> window)")
        parsed = [(str(name), *_parse_window(w, f"interfaces.{name}", spec, path))
                  for name, w in data["interfaces"].items()]
    else:
        parsed = [("window", *_parse_window(data["interface"], "interface", spec, path))]
    cams = {}
    if not isinstance(data["cameras"], dict) or not data["cameras"]:
        raise AriSfmError(path, "cameras must be a non-empty object")
    known = {"image_size", "K", "dist", "cam_from_world", "normal_cam", "expansion_center_px",
             "expansion_center_std_px", "rmse_px", "distance_mm", "window", *spec.camera_keys}
    pf_world = _record(PfWorld, data, "pf_world", path) if spec.projection == "polynomial" else None
    if spec.projection == "polynomial" and pf_world is None:
        raise AriSfmError(path, f"pf_world is missing (model {model} names the calibration its world comes from)")
    for name, c in data["cameras"].items():
        ec = c.get("expansion_center_px")
        es = c.get("expansion_center_std_px")
        for key in spec.camera_keys:
            if key not in c:
                raise AriSfmError(path, f"cameras.{name}.{key} is missing (model {model} stores its parameters there)")
        poly = None
        # the polynomial is the model: validate it here, not at the first projection
        if spec.projection == "polynomial" and pf_world is not None:  # (pf_world is required above)
            try:
                poly = PolynomialMap.from_json(c["pf"])
            except (KeyError, TypeError, ValueError) as exc:
                raise AriSfmError(path, f"cameras.{name}.pf: {exc}") from None
            if c["pf"].get("world", pf_world.model) != pf_world.model:
                raise AriSfmError(path, f"cameras.{name}.pf.world is {c['pf']['world']!r}, pf_world.model "
                                        f"{pf_world.model!r}: one world for all cameras")
        cams[name] = CameraCalibration(
            name,
            (int(c["image_size"][0]), int(c["image_size"][1])),  # two integers (check_calibration_values)
            _finite(c["K"], (3, 3), f"cameras.{name}.K", path),
            np.resize(_finite(c.get("dist", [0] * 5), (len(c.get("dist", [0] * 5)),), f"cameras.{name}.dist", path), 5),
            _pose(c["cam_from_world"], f"cameras.{name}.cam_from_world", path),
            None if ec is None else np.asarray(ec, float),
            None if es is None else np.asarray(es, float),
            c.get("rmse_px"),
            {k: v for k, v in c.items() if k not in known},
            poly,
        )
    for _, interface, _, _listed, _ in parsed:
        _check_bounds(cams, interface.thickness_mm, path)
    frames = {f: _pose(v["world_from_target"], f"frames.{f}", path) for f, v in data.get("frames", {}).items()}
    stacking = {f: _pose(v["world_from_target"], f"stacking_poses.{f}", path)
                for f, v in data.get("stacking_poses", {}).items()}
    reserved = {"format", "model", "interface", "interfaces", "cameras", "frames", "stacking_poses", "residuals",
                "time_s", "target", "fixed_distance_mm", "uncertainty", "outliers", "pf_world", "quality", "optimizer",
                "stages", "self_calibration", "refine_colmap", "imported_from", "window_ignored"}
    windows = _windows(parsed, data, cams, path)
    if spec.window:
        _check_normals_face_the_cameras(windows, cams, path)
    for w in windows:
        if spec.needs_distance and w.interface.distance_mm is None and w.fixed_distance_mm is None:
            where = "interface" if len(windows) == 1 else f"interfaces.{w.name}"
            raise AriSfmError(path, f"fixed_distance_mm is missing: model {model} with {where}.distance_mm null is "
                                    "evaluated at the distance it was calibrated with (in air no pixel depends on it)")
    if "target" in data:
        target = parse_target(data["target"], Path(path))
    else:
        target = None
    first = windows[0]
    return Calibration(
        model, first.interface, first.normal_world, cams,
        frames, stacking, _record(ResidualStats, data, "residuals", path), float(data.get("time_s", 0.0)),
        {k: v for k, v in data.items() if k not in reserved}, target, first.fixed_distance_mm,
        _record(Uncertainty, data, "uncertainty", path), _record(OutlierReport, data, "outliers", path), pf_world,
        _record(Quality, data, "quality", path), _record(OptimizerReport, data, "optimizer", path),
        windows=windows if len(windows) > 1 else (), stages=_stages(data, path),
        self_calibration=_record(SelfCalReport, data, "self_calibration", path),
        refine_colmap=_record(RefineColmapFrames, data, "refine_colmap", path),
        imported_from=_record(ImportedFrom, data, "imported_from", path),
        window_ignored=_window_ignored(data, path),
    )


def _window_ignored(data: dict, path: Any) -> bool:
    """calibration.json's ``window_ignored`` (a pinhole baseline's), false when absent."""
    value = data.get("window_ignored", False)
    if not isinstance(value, bool):
        raise AriSfmError(path, f"window_ignored must be true or false (got {value!r})")
    return value


def _stages(data: dict, path: Any) -> tuple[StageRecord, ...]:
    """calibration.json's ``stages`` as records (() when absent or null), errors naming the key."""
    if data.get("stages") is None:
        return ()
    try:
        return stages_from_json(data["stages"])
    except (KeyError, TypeError, ValueError) as exc:
        what = f"missing key {exc}" if isinstance(exc, KeyError) else str(exc)
        raise AriSfmError(path, f"stages: {what}") from None


def _check_normals_face_the_cameras(windows: tuple[WindowCalibration, ...], cams: dict[str, CameraCalibration],
                                    path: Any) -> None:
    """Each window's normal points from its cameras into the scene (z > 0 in each camera's frame): a flipped
    normal would project every corner to NaN, and the fork's FLATPORT (Nz > 0) could not hold it."""
    for w in windows:
        if w.normal_world is None:
            continue
        where = "interface" if len(windows) == 1 else f"interfaces.{w.name}"
        for name in w.cameras:
            if name in cams and float((cams[name].cam_from_world.R @ w.normal_world)[2]) <= 0.0:
                raise AriSfmError(path, f"{where}.normal_world points away from camera {name}'s view (z <= 0 in its "
                                        "frame): the normal goes from the cameras into the scene (flipped?)")


def _parse_window(iface: Any, where: str, spec, path: Any) -> tuple[Interface, np.ndarray | None, list | None,
                                                                    float | None]:
    """(interface, normal_world, listed cameras or None, fixed_distance_mm or None) of one window mapping."""
    if not isinstance(iface, dict):
        raise AriSfmError(path, f"{where} must be an object")
    thickness, index = float(iface["thickness_mm"]), float(iface["index"])
    medium = float(iface.get("medium_index", 1.0))
    if not (math.isfinite(thickness) and thickness >= 0):
        raise AriSfmError(path, f"{where}.thickness_mm must be >= 0 (got {thickness})")
    if not (math.isfinite(index) and index >= 1) or not (math.isfinite(medium) and medium >= 1):
        raise AriSfmError(path, f"{where}.index and medium_index must be >= 1")
    distance = iface.get("distance_mm")
    if iface["normal_world"] is None and not spec.window:
        normal = None
    else:
        normal = _finite(iface["normal_world"], (3,), f"{where}.normal_world", path)
    if normal is not None and abs(np.linalg.norm(normal) - 1) > 1e-6:
        raise AriSfmError(path, f"{where}.normal_world must be a unit vector")
    listed = iface.get("cameras")
    if listed is not None and (not isinstance(listed, list) or not all(isinstance(c, str) for c in listed)):
        raise AriSfmError(path, f"{where}.cameras must be a list of camera names")
    fixed = iface.get("fixed_distance_mm")
    if fixed is not None:
        fixed = float(fixed)
        if not math.isfinite(fixed):
            raise AriSfmError(path,
                              f"{where}.fixed_distance_mm must be a finite number (got {iface['fixed_distance_mm']!r})")
    return Interface(thickness, index, medium, None if distance is None else float(distance)), normal, listed, fixed


def _windows(parsed: list, data: dict, cams: dict[str, CameraCalibration], path: Any) -> tuple[WindowCalibration, ...]:
    """The calibration's windows: one for every camera (``interface``; fixed_distance_mm top-level), or those of
    ``interfaces``, each camera behind the one it names (``cameras.<name>.window``) and listed there."""
    if len(parsed) == 1 and "interfaces" not in data:
        name, interface, normal, _, _ = parsed[0]
        fixed = data.get("fixed_distance_mm")
        if fixed is not None:
            fixed = float(fixed)
            if not math.isfinite(fixed):
                raise AriSfmError(path,
                                  f"fixed_distance_mm must be a finite number (got {data['fixed_distance_mm']!r})")
        return (WindowCalibration(name, interface, normal, tuple(cams), fixed),)
    out = []
    for name, interface, normal, listed, fixed in parsed:
        if listed is None:
            raise AriSfmError(path, f"interfaces.{name}.cameras is missing (the cameras behind this window)")
        for c in listed:
            if c not in cams:
                raise AriSfmError(path, f"interfaces.{name}.cameras names {c!r}, which is not under cameras")
            said = data["cameras"][c].get("window")
            if said is not None and said != name:
                raise AriSfmError(path, f"cameras.{c}.window is {said!r} but interfaces.{name}.cameras lists it")
        out.append(WindowCalibration(name, interface, normal, tuple(listed), fixed))
    media = {w.interface.medium_index for w in out}
    if len(media) > 1:
        raise AriSfmError(path, f"interfaces: the windows' medium_index differ ({sorted(media)}): one tank, one medium")
    placed = [c for w in out for c in w.cameras]
    for c in cams:
        if placed.count(c) != 1:
            raise AriSfmError(path, f"camera {c} is listed under {placed.count(c)} windows of interfaces (one needed)")
    return tuple(out)


def _record(cls, data: dict, key: str, path: Any):
    """``cls.from_json(data[key])`` (None when the key is absent, null or {}), errors naming the key."""
    value = data.get(key)
    if not value:
        return None
    if not isinstance(value, dict):
        raise AriSfmError(path, f"{key} must be an object")
    try:
        return cls.from_json(value)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        what = f"missing key {exc}" if isinstance(exc, KeyError) else str(exc)
        raise AriSfmError(path, f"{key}: {what}") from None

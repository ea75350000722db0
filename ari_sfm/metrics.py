"""Accuracy of a reconstruction (paper Sec. 5, Fig. 13): planes, stage distances, corner spacing, truth.

``reconstruction_metrics(points, target, truth=None)`` returns a JSON-able
dict. All lengths in mm; "stats" below means ``{"mae", "rmse", "max",
"count"}`` of the absolute values of an error list (``max`` of |error|).

- ``num_points``, ``num_frames``; ``ray_gap_mm``: ``{"mean", "rms", "max"}``;
  ``reprojection_rmse_px`` (over all corners and cameras; None when the
  points were loaded from a file).
- ``frames``: per frame ``{"stage_mm", "num_points", "plane": {"normal",
  "point", "inliers"}, "flatness_mm": stats, "inter_corner_mm": stats,
  "plane_distance_mm", "plane_distance_error_mm",
  "plane_distance_error_paper_mm", "displacement_error_mm", "plane_angle_deg"}``
  (the stage keys only for frames with a stage_mm).
- ``flatness_mm``: stats over all frames' point-to-plane distances, plus
  ``"distances"`` (signed, histogram-ready) (Fig. 13c). Each frame's plane:
  Open3D RANSAC (``segment_plane``, threshold ``plane_threshold_mm``), then a
  least-squares (SVD) plane through the RANSAC inliers; distances are of
  *all* the frame's points to that plane.
- ``stage`` (Fig. 13b), None without two frames with stage_mm: the
  reference frame is the stage_mm = 0 frame (else the middle one).
  ``plane_distance_mm`` of a frame: distance from the reference centroid,
  along the reference plane's normal, to the frame's plane. The stage moves
  the board along a line that need not be the board's normal, so the
  expected distance is ``(s - s_ref) cos(theta)``, theta the angle between
  the normal and the stage direction measured from the corners (the least
  squares travel per stage-mm of the mean displacement of corresponding
  corners: ``direction_world``, ``travel_scale`` = its length, 1 if the
  reconstruction has the right scale). ``plane_distance_error_mm`` =
  measured - expected; ``plane_distance_error_paper_mm`` = measured -
  (s - s_ref) (the paper's, exact when the stage moves along the normal);
  ``displacement_error_mm`` = |mean displacement of the frame's corners from
  the reference's| - |s - s_ref| (the stage travel measured directly).
  Each as stats; ``angle_to_normal_deg`` = theta.
- ``inter_corner_mm`` (Fig. 13d), None for targets without a corner grid:
  distances of horizontally and vertically adjacent corners (ids
  ``r cols + c`` with ``c+1`` and ``r+1``) minus ``square_mm``: stats plus
  ``"square_mm"``, ``"distances"`` and ``"errors"`` (histogram-ready).
- ``truth``, only given a truth (``truth.json`` form with
  ``reconstruction_points_world``): ``{"count", "unaligned": {"rms_mm",
  "max_mm"}, "aligned": {"rms_mm", "max_mm", "rotation_deg",
  "translation_mm"}}``; aligned = after the rigid (rotation + translation,
  no scale: Kabsch) transform of all points onto the truth that minimises
  the squared error.
"""
from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .deps import require_open3d
from .errors import AriSfmError
from .reconstruct import FramePoints, Points
from .records import Target

log = logging.getLogger(__name__)

PLANE_THRESHOLD_MM = 0.1  # RANSAC inlier distance (~5 sigma of the depth noise of a paper-like rig)
RANSAC_ITERATIONS = 1000
SEED = 0  # Open3D's RANSAC is seeded: the same points give the same metrics


def _stats(errors: np.ndarray) -> dict[str, Any]:
    e = np.abs(np.asarray(errors, dtype=float))
    if not len(e):
        return {"mae": None, "rmse": None, "max": None, "count": 0}
    return {"mae": float(e.mean()), "rmse": float(np.sqrt(np.mean(e**2))), "max": float(e.max()), "count": int(len(e))}


# --------------------------------------------------------------------------- planes


def fit_plane(xyz: np.ndarray, threshold_mm: float = PLANE_THRESHOLD_MM) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane of points (N >= 3, 3): Open3D RANSAC, then least squares (SVD) on its inliers.

    Returns the unit normal (3,), a point on the plane (the inliers' centroid)
    and the inlier mask (N,). If RANSAC keeps fewer than half the points (a
    plane much less flat than the threshold), all points are used and a
    warning is logged.
    """
    o3d = require_open3d()
    xyz = np.asarray(xyz, dtype=float)
    if len(xyz) < 3:
        raise ValueError(f"a plane needs at least 3 points, got {len(xyz)}")
    o3d.utility.random.seed(SEED)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    _, idx = cloud.segment_plane(distance_threshold=float(threshold_mm), ransac_n=3,
                                 num_iterations=RANSAC_ITERATIONS)
    inliers = np.zeros(len(xyz), dtype=bool)
    inliers[np.asarray(idx, dtype=int)] = True
    if inliers.sum() < max(3, len(xyz) / 2):
        log.warning("plane fit: RANSAC kept %d of %d points at %.3g mm; fitting all points",
                    int(inliers.sum()), len(xyz), threshold_mm)
        inliers[:] = True
    centroid = xyz[inliers].mean(axis=0)
    normal = np.linalg.svd(xyz[inliers] - centroid)[2][2]
    return normal, centroid, inliers


def _frame_plane(frame: FramePoints, threshold_mm: float) -> dict[str, Any] | None:
    if len(frame) < 3:
        return None
    normal, point, inliers = fit_plane(frame.xyz, threshold_mm)
    return {"normal": normal, "point": point, "inliers": inliers, "distances": (frame.xyz - point) @ normal}


# --------------------------------------------------------------------------- stage


def _reference_frame(staged: dict[str, float]) -> str:
    """The stage_mm = 0 frame, else the middle one by stage."""
    zero = [f for f, s in staged.items() if s == 0.0]
    if zero:
        return zero[0]
    ordered = sorted(staged, key=lambda f: staged[f])
    return ordered[len(ordered) // 2]


def _stage_metrics(points: Points, planes: dict[str, dict[str, Any] | None]) -> tuple[dict[str, Any] | None, dict]:
    staged = {f: fp.stage_mm for f, fp in points.frames.items() if fp.stage_mm is not None and planes.get(f)}
    if len(staged) < 2:
        return None, {}
    ref = _reference_frame(staged)
    rp, rf = planes[ref], points.frames[ref]
    c_ref = rf.xyz.mean(axis=0)
    # travel per stage-mm from the mean displacement of corresponding corners
    disp: dict[str, np.ndarray] = {}
    for f, s in staged.items():
        if f == ref:
            continue
        common, ia, ib = np.intersect1d(points.frames[f].ids, rf.ids, return_indices=True)
        if len(common):
            disp[f] = (points.frames[f].xyz[ia] - rf.xyz[ib]).mean(axis=0)
    ds = {f: staged[f] - staged[ref] for f in staged}
    num = sum(ds[f] * disp[f] for f in disp) if disp else None
    den = sum(ds[f] ** 2 for f in disp)
    if num is None or den == 0.0:
        return None, {}
    travel = num / den
    scale = float(np.linalg.norm(travel))
    direction = travel / scale
    n_ref = rp["normal"] if rp["normal"] @ direction >= 0 else -rp["normal"]
    cos_theta = float(n_ref @ direction)
    per_frame: dict[str, dict[str, float]] = {}
    err, err_paper, err_disp = [], [], []
    for f in staged:
        if f == ref:
            continue
        p = planes[f]
        n_f = p["normal"]
        # from c_ref along n_ref to the plane of f: n_f . (c_ref + t n_ref - p_f) = 0
        t = float(n_f @ (p["point"] - c_ref) / (n_f @ n_ref))
        e = t - ds[f] * cos_theta
        e_paper = t - ds[f]
        rec = {"plane_distance_mm": t, "plane_distance_error_mm": e, "plane_distance_error_paper_mm": e_paper,
               "plane_angle_deg": float(np.degrees(np.arccos(min(1.0, abs(float(n_f @ n_ref))))))}
        err.append(e)
        err_paper.append(e_paper)
        if f in disp:
            rec["displacement_error_mm"] = float(np.linalg.norm(disp[f]) - abs(ds[f]))
            err_disp.append(rec["displacement_error_mm"])
        per_frame[f] = rec
    per_frame[ref] = {"plane_distance_mm": 0.0, "plane_distance_error_mm": 0.0,
                      "plane_distance_error_paper_mm": 0.0, "plane_angle_deg": 0.0, "displacement_error_mm": 0.0}
    stage = {
        "reference_frame": ref,
        "direction_world": direction.tolist(),
        "travel_scale": scale,
        "angle_to_normal_deg": float(np.degrees(np.arccos(min(1.0, cos_theta)))),
        "plane_distance_error_mm": _stats(np.array(err)),
        "plane_distance_error_paper_mm": _stats(np.array(err_paper)),
        "displacement_error_mm": _stats(np.array(err_disp)),
    }
    return stage, per_frame


# --------------------------------------------------------------------------- corners


def inter_corner_distances(ids: np.ndarray, xyz: np.ndarray, cols: int) -> np.ndarray:
    """Distances (M,) of horizontally (c, c+1) and vertically (r, r+1) adjacent corners present in ``ids``."""
    ids = np.asarray(ids, dtype=int)
    index = {int(i): k for k, i in enumerate(ids)}
    pairs = []
    for k, i in enumerate(ids):
        c = int(i) % cols
        if c + 1 < cols and int(i) + 1 in index:
            pairs.append((k, index[int(i) + 1]))
        if int(i) + cols in index:
            pairs.append((k, index[int(i) + cols]))
    if not pairs:
        return np.zeros(0)
    a, b = np.array(pairs).T
    return np.linalg.norm(xyz[a] - xyz[b], axis=1)


# --------------------------------------------------------------------------- truth


def _truth_points(truth: Mapping[str, Any] | str | Path) -> tuple[dict[str, Any], str]:
    if isinstance(truth, (str, Path)):
        from .io import read_structured

        return read_structured(Path(truth)), str(truth)
    return dict(truth), "truth"


def truth_errors(points: Points, truth: Mapping[str, Any] | str | Path) -> dict[str, Any]:
    """3D errors against a truth's ``reconstruction_points_world``, unaligned and after rigid alignment."""
    data, where = _truth_points(truth)
    recon = data.get("reconstruction_points_world") if isinstance(data, Mapping) else None
    if not isinstance(recon, Mapping):
        raise AriSfmError(where, "has no reconstruction_points_world (not a simulator truth.json)")
    est, ref = [], []
    for name, fp in points.frames.items():
        if name not in recon:
            raise AriSfmError(where, f"reconstruction frame {name} is not in the truth (its frames: "
                                     f"{', '.join(map(str, recon)) or 'none'})")
        try:
            t_ids = np.asarray(recon[name]["ids"], dtype=int)
            t_xyz = np.asarray(recon[name]["xyz"], dtype=float).reshape(-1, 3)
        except (KeyError, TypeError, ValueError) as exc:
            raise AriSfmError(where, f"reconstruction_points_world.{name} is malformed ({exc})") from None
        if len(t_ids) != len(t_xyz):
            raise AriSfmError(where, f"reconstruction_points_world.{name}: {len(t_ids)} ids but {len(t_xyz)} xyz")
        pos = {int(i): k for k, i in enumerate(t_ids)}
        missing = [int(i) for i in fp.ids if int(i) not in pos]
        if missing:
            raise AriSfmError(where, f"frame {name}: corner id {missing[0]} is not in the truth")
        est.append(fp.xyz)
        ref.append(t_xyz[[pos[int(i)] for i in fp.ids]])
    A, B = np.concatenate(est), np.concatenate(ref)
    e0 = np.linalg.norm(A - B, axis=1)
    R, t = rigid_alignment(A, B)
    e1 = np.linalg.norm(A @ R.T + t - B, axis=1)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    return {"count": int(len(A)),
            "unaligned": {"rms_mm": float(np.sqrt(np.mean(e0**2))), "max_mm": float(e0.max())},
            "aligned": {"rms_mm": float(np.sqrt(np.mean(e1**2))), "max_mm": float(e1.max()),
                        "rotation_deg": angle, "translation_mm": float(np.linalg.norm(t))}}


def rigid_alignment(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising sum |R a + t - b|^2 (Kabsch, no scale; proper rotation)."""
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


# --------------------------------------------------------------------------- all


def reconstruction_metrics(points: Points, target: Target, truth: Mapping[str, Any] | str | Path | None = None,
                           plane_threshold_mm: float = PLANE_THRESHOLD_MM) -> dict[str, Any]:
    """All the metrics of the module docstring, as a JSON-able dict."""
    if not points.frames:
        raise AriSfmError(None, "no reconstructed frames to measure")
    truth_part = truth_errors(points, truth) if truth is not None else None  # checks the truth first
    planes = {f: _frame_plane(fp, plane_threshold_mm) for f, fp in points.frames.items()}
    stage, stage_frames = _stage_metrics(points, planes)
    grid = target.grid
    frames: dict[str, Any] = {}
    all_d, all_ic = [], []
    for f, fp in points.frames.items():
        p = planes[f]
        rec: dict[str, Any] = {"stage_mm": fp.stage_mm, "num_points": len(fp)}
        if p is not None:
            rec["plane"] = {"normal": p["normal"].tolist(), "point": p["point"].tolist(),
                            "inliers": int(p["inliers"].sum())}
            rec["flatness_mm"] = _stats(p["distances"])
            all_d.append(p["distances"])
        if grid is not None:
            dist = inter_corner_distances(fp.ids, fp.xyz, grid[0])
            rec["inter_corner_mm"] = _stats(dist - target.pitch_mm)
            all_ic.append(dist)
        rec.update(stage_frames.get(f, {}))
        frames[f] = rec
    d = np.concatenate(all_d) if all_d else np.zeros(0)
    flat = dict(_stats(d), distances=d.tolist())
    inter = None
    if grid is not None:
        dist = np.concatenate(all_ic) if all_ic else np.zeros(0)
        inter = dict(_stats(dist - target.pitch_mm), square_mm=float(target.pitch_mm),
                     distances=dist.tolist(), errors=(dist - target.pitch_mm).tolist())
    gaps = np.concatenate([fp.ray_gap_mm for fp in points.frames.values()])
    rmse = [fp.reprojection_rmse_px for fp in points.frames.values()]
    if all(r is not None for r in rmse):
        w = np.array([len(fp) for fp in points.frames.values()], dtype=float)
        reproj = float(np.sqrt(np.sum(w * np.square(rmse)) / w.sum()))
    else:
        reproj = None
    return {
        "num_points": int(points.num_points),
        "num_frames": len(points.frames),
        "ray_gap_mm": {"mean": float(gaps.mean()), "rms": float(np.sqrt(np.mean(gaps**2))), "max": float(gaps.max())},
        "reprojection_rmse_px": reproj,
        "flatness_mm": flat,
        "stage": stage,
        "inter_corner_mm": inter,
        "truth": truth_part,
        "frames": frames,
    }


def save_point_clouds(points: Points, out_dir: str | Path) -> dict[str, Path]:
    """Write ``<frame>.ply`` per frame and ``all.ply`` (coloured by frame) into ``out_dir``; returns the paths.

    Each file is written under a temporary name and renamed (atomic).
    """
    o3d = require_open3d()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    colors = _frame_colors(len(points.frames))
    written: dict[str, Path] = {}
    for (name, fp), color in zip(points.frames.items(), colors):
        safe = re.sub(r"[^A-Za-z0-9._-]", "_", name)
        written[name] = _write_cloud(o3d, out / f"{safe}.ply", fp.xyz, np.tile(color, (len(fp), 1)))
    xyz = np.concatenate([fp.xyz for fp in points.frames.values()])
    rgb = np.concatenate([np.tile(c, (len(fp), 1)) for fp, c in zip(points.frames.values(), colors)])
    written["all"] = _write_cloud(o3d, out / "all.ply", xyz, rgb)
    return written


def _write_cloud(o3d: Any, path: Path, xyz: np.ndarray, rgb: np.ndarray) -> Path:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz, dtype=float)))
    cloud.colors = o3d.utility.Vector3dVector(np.asarray(rgb, dtype=float))
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.ply")
    try:
        if not o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=False):
            raise AriSfmError(path, "Open3D could not write the point cloud")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _frame_colors(n: int) -> np.ndarray:
    """n distinct RGB colours in [0, 1] (hues around the wheel)."""
    h = np.arange(n) / max(n, 1)
    k = (np.array([5.0, 3.0, 1.0])[None, :] + h[:, None] * 6.0) % 6.0
    return 1.0 - 0.8 * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)

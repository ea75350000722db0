"""Accuracy of a reconstruction (paper Sec. 5, Fig. 13): planes, stage distances, corner spacing, truth.

``reconstruction_metrics(points, target, truth=None)`` returns a
:class:`ReconstructionMetrics` record; its ``to_json()`` is metrics.json's
body, laid out as below (``ReconstructionMetrics.from_json`` reads it back).
All lengths in mm; "stats" below means ``{"mae", "rmse", "max", "count"}``
(:class:`ErrorStats`) of the absolute values of an error list (``max`` of |error|).

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
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..deps import require_open3d
from ..errors import AriSfmError
from ..records import Target
from .points import FramePoints, Points
from .reference import ReferenceErrors

log = logging.getLogger(__name__)

PLANE_THRESHOLD_MM = 0.1  # RANSAC inlier distance (~5 sigma of the depth noise of a paper-like rig)
RANSAC_ITERATIONS = 1000
SEED = 0  # Open3D's RANSAC is seeded: the same points give the same metrics


# --------------------------------------------------------------------------- records (metrics.json)


def _opt(value: Any) -> float | None:
    return None if value is None else float(value)


def _floats(values: Any) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


def _vec3(values: Any) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in values)
    return x, y, z


@dataclass(frozen=True)
class ErrorStats:
    """"stats": of the absolute values of an error list (None and count 0 for an empty list)."""

    mae: float | None
    rmse: float | None
    max: float | None
    count: int

    @classmethod
    def of(cls, errors: np.ndarray) -> ErrorStats:
        e = np.abs(np.asarray(errors, dtype=float))
        if not len(e):
            return cls(None, None, None, 0)
        return cls(float(e.mean()), float(np.sqrt(np.mean(e**2))), float(e.max()), int(len(e)))

    def to_json(self) -> dict[str, Any]:
        return {"mae": self.mae, "rmse": self.rmse, "max": self.max, "count": self.count}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> ErrorStats:
        return cls(_opt(d["mae"]), _opt(d["rmse"]), _opt(d["max"]), int(d["count"]))


def _stats(errors: np.ndarray) -> ErrorStats:
    return ErrorStats.of(errors)


@dataclass(frozen=True)
class Flatness(ErrorStats):
    """Point-to-plane distances of all frames: stats plus the signed distances (histogram-ready)."""

    distances: tuple[float, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return dict(super().to_json(), distances=list(self.distances))

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Flatness:
        return cls(**vars(ErrorStats.from_json(d)), distances=_floats(d["distances"]))


@dataclass(frozen=True)
class InterCorner(ErrorStats):
    """Adjacent-corner distances minus the square: stats, the square, the distances and their errors."""

    square_mm: float = 0.0
    distances: tuple[float, ...] = ()
    errors: tuple[float, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return dict(super().to_json(), square_mm=self.square_mm, distances=list(self.distances),
                    errors=list(self.errors))

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> InterCorner:
        return cls(**vars(ErrorStats.from_json(d)), square_mm=float(d["square_mm"]),
                   distances=_floats(d["distances"]), errors=_floats(d["errors"]))


@dataclass(frozen=True)
class RayGap:
    """``ray_gap_mm`` over all points: mean, rms, max."""

    mean: float
    rms: float
    max: float

    def to_json(self) -> dict[str, Any]:
        return {"mean": self.mean, "rms": self.rms, "max": self.max}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> RayGap:
        return cls(float(d["mean"]), float(d["rms"]), float(d["max"]))


@dataclass(frozen=True)
class StageMetrics:
    """The stage experiment (Fig. 13b): see the module docstring."""

    reference_frame: str
    direction_world: tuple[float, float, float]
    travel_scale: float
    angle_to_normal_deg: float
    plane_distance_error_mm: ErrorStats
    plane_distance_error_paper_mm: ErrorStats
    displacement_error_mm: ErrorStats

    def to_json(self) -> dict[str, Any]:
        return {"reference_frame": self.reference_frame, "direction_world": list(self.direction_world),
                "travel_scale": self.travel_scale, "angle_to_normal_deg": self.angle_to_normal_deg,
                "plane_distance_error_mm": self.plane_distance_error_mm.to_json(),
                "plane_distance_error_paper_mm": self.plane_distance_error_paper_mm.to_json(),
                "displacement_error_mm": self.displacement_error_mm.to_json()}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> StageMetrics:
        return cls(str(d["reference_frame"]), _vec3(d["direction_world"]), float(d["travel_scale"]),
                   float(d["angle_to_normal_deg"]), ErrorStats.from_json(d["plane_distance_error_mm"]),
                   ErrorStats.from_json(d["plane_distance_error_paper_mm"]),
                   ErrorStats.from_json(d["displacement_error_mm"]))


@dataclass(frozen=True)
class FrameStage:
    """One frame's stage numbers (frames with a stage_mm); no displacement without corners shared with the reference."""

    plane_distance_mm: float
    plane_distance_error_mm: float
    plane_distance_error_paper_mm: float
    plane_angle_deg: float
    displacement_error_mm: float | None = None

    def to_json(self) -> dict[str, Any]:
        out = {"plane_distance_mm": self.plane_distance_mm, "plane_distance_error_mm": self.plane_distance_error_mm,
               "plane_distance_error_paper_mm": self.plane_distance_error_paper_mm,
               "plane_angle_deg": self.plane_angle_deg}
        if self.displacement_error_mm is not None:
            out["displacement_error_mm"] = self.displacement_error_mm
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> FrameStage:
        return cls(float(d["plane_distance_mm"]), float(d["plane_distance_error_mm"]),
                   float(d["plane_distance_error_paper_mm"]), float(d["plane_angle_deg"]),
                   _opt(d.get("displacement_error_mm")))


@dataclass(frozen=True)
class FramePlane:
    """A frame's fitted plane: unit normal, a point on it, how many points RANSAC kept."""

    normal: tuple[float, float, float]
    point: tuple[float, float, float]
    inliers: int

    def to_json(self) -> dict[str, Any]:
        return {"normal": list(self.normal), "point": list(self.point), "inliers": self.inliers}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> FramePlane:
        return cls(_vec3(d["normal"]), _vec3(d["point"]), int(d["inliers"]))


@dataclass(frozen=True)
class FrameMetrics:
    """One reconstruction frame: plane and flatness (>= 3 points), corner spacing (grid targets), stage numbers."""

    stage_mm: float | None
    num_points: int
    plane: FramePlane | None = None
    flatness_mm: ErrorStats | None = None
    inter_corner_mm: ErrorStats | None = None
    stage: FrameStage | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"stage_mm": self.stage_mm, "num_points": self.num_points}
        if self.plane is not None:
            out["plane"] = self.plane.to_json()
            out["flatness_mm"] = None if self.flatness_mm is None else self.flatness_mm.to_json()
        if self.inter_corner_mm is not None:
            out["inter_corner_mm"] = self.inter_corner_mm.to_json()
        if self.stage is not None:
            out.update(self.stage.to_json())
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> FrameMetrics:
        plane = FramePlane.from_json(d["plane"]) if "plane" in d else None
        return cls(_opt(d["stage_mm"]), int(d["num_points"]), plane,
                   ErrorStats.from_json(d["flatness_mm"]) if plane is not None else None,
                   ErrorStats.from_json(d["inter_corner_mm"]) if "inter_corner_mm" in d else None,
                   FrameStage.from_json(d) if "plane_distance_mm" in d else None)


@dataclass(frozen=True)
class TruthErrors:
    """3D errors against a simulator's truth, as is and after the best rigid alignment (no scale)."""

    count: int
    unaligned_rms_mm: float
    unaligned_max_mm: float
    aligned_rms_mm: float
    aligned_max_mm: float
    rotation_deg: float  # of the alignment
    translation_mm: float

    def to_json(self) -> dict[str, Any]:
        return {"count": self.count,
                "unaligned": {"rms_mm": self.unaligned_rms_mm, "max_mm": self.unaligned_max_mm},
                "aligned": {"rms_mm": self.aligned_rms_mm, "max_mm": self.aligned_max_mm,
                            "rotation_deg": self.rotation_deg, "translation_mm": self.translation_mm}}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> TruthErrors:
        u, a = d["unaligned"], d["aligned"]
        return cls(int(d["count"]), float(u["rms_mm"]), float(u["max_mm"]), float(a["rms_mm"]), float(a["max_mm"]),
                   float(a["rotation_deg"]), float(a["translation_mm"]))


@dataclass(frozen=True)
class ReconstructionMetrics:
    """Everything :func:`reconstruction_metrics` measures (metrics.json without its header keys)."""

    num_points: int
    num_frames: int
    ray_gap_mm: RayGap
    reprojection_rmse_px: float | None  # None when the points were loaded from a file
    flatness_mm: Flatness
    stage: StageMetrics | None  # None without two staged frames
    inter_corner_mm: InterCorner | None  # None for targets without a corner grid
    truth: TruthErrors | None  # only given a truth
    frames: Mapping[str, FrameMetrics] = field(default_factory=dict)
    reference: ReferenceErrors | None = None  # only given a reference geometry: reference.reference_errors

    def to_json(self) -> dict[str, Any]:
        out = {"num_points": self.num_points, "num_frames": self.num_frames, "ray_gap_mm": self.ray_gap_mm.to_json(),
               "reprojection_rmse_px": self.reprojection_rmse_px, "flatness_mm": self.flatness_mm.to_json(),
               "stage": None if self.stage is None else self.stage.to_json(),
               "inter_corner_mm": None if self.inter_corner_mm is None else self.inter_corner_mm.to_json(),
               "truth": None if self.truth is None else self.truth.to_json(),
               "frames": {f: m.to_json() for f, m in self.frames.items()}}
        if self.reference is not None:
            out["reference"] = self.reference.to_json()
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> ReconstructionMetrics:
        """Read metrics.json's body (header keys format, dataset, calibration, model are ignored)."""
        return cls(int(d["num_points"]), int(d["num_frames"]), RayGap.from_json(d["ray_gap_mm"]),
                   _opt(d["reprojection_rmse_px"]), Flatness.from_json(d["flatness_mm"]),
                   None if d["stage"] is None else StageMetrics.from_json(d["stage"]),
                   None if d["inter_corner_mm"] is None else InterCorner.from_json(d["inter_corner_mm"]),
                   None if d["truth"] is None else TruthErrors.from_json(d["truth"]),
                   {f: FrameMetrics.from_json(m) for f, m in d["frames"].items()},
                   None if d.get("reference") is None else ReferenceErrors.from_json(d["reference"]))


# --------------------------------------------------------------------------- planes


def fit_plane(xyz: np.ndarray, threshold_mm: float = PLANE_THRESHOLD_MM) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit a plane to points: Open3D RANSAC, then least squares (SVD) on its inliers.

    If RANSAC keeps fewer than half the points (a plane much less flat than the threshold), all points
    are used and a warning is logged.

    Args:
        xyz: the points (N, 3), N >= 3, mm.
        threshold_mm: RANSAC's inlier distance (mm).

    Returns:
        The unit normal (3,), a point on the plane (the inliers' centroid) and the inlier mask (N,).

    Raises:
        ValueError: with fewer than 3 points.
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


def _stage_metrics(points: Points, planes: dict[str, dict[str, Any] | None]
                   ) -> tuple[StageMetrics | None, dict[str, FrameStage]]:
    fitted = {f: p for f, p in planes.items() if p}
    staged = {f: fp.stage_mm for f, fp in points.frames.items() if fp.stage_mm is not None and f in fitted}
    if len(staged) < 2:
        return None, {}
    ref = _reference_frame(staged)
    rp, rf = fitted[ref], points.frames[ref]
    c_ref = rf.xyz.mean(axis=0)
    # travel per stage-mm from the mean displacement of corresponding corners
    disp: dict[str, np.ndarray] = {}
    for f in staged:
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
    per_frame: dict[str, FrameStage] = {}
    err, err_paper, err_disp = [], [], []
    for f in staged:
        if f == ref:
            continue
        p = fitted[f]
        n_f = p["normal"]
        # from c_ref along n_ref to the plane of f: n_f . (c_ref + t n_ref - p_f) = 0
        t = float(n_f @ (p["point"] - c_ref) / (n_f @ n_ref))
        e = t - ds[f] * cos_theta
        e_paper = t - ds[f]
        err.append(e)
        err_paper.append(e_paper)
        displacement = float(np.linalg.norm(disp[f]) - abs(ds[f])) if f in disp else None
        if displacement is not None:
            err_disp.append(displacement)
        per_frame[f] = FrameStage(t, e, e_paper, float(np.degrees(np.arccos(min(1.0, abs(float(n_f @ n_ref)))))),
                                  displacement)
    per_frame[ref] = FrameStage(0.0, 0.0, 0.0, 0.0, 0.0)
    stage = StageMetrics(ref, _vec3(direction), scale, float(np.degrees(np.arccos(min(1.0, cos_theta)))),
                         _stats(np.array(err)), _stats(np.array(err_paper)), _stats(np.array(err_disp)))
    return stage, per_frame


# --------------------------------------------------------------------------- corners


def inter_corner_distances(ids: np.ndarray, xyz: np.ndarray, cols: int) -> np.ndarray:
    """Measure the distances of adjacent grid corners.

    Args:
        ids: the corner ids (N,), ``r cols + c`` on the grid.
        xyz: their points (N, 3), mm.
        cols: the grid's columns.

    Returns:
        The distances (M,) of horizontally (c, c+1) and vertically (r, r+1) adjacent corners present in ``ids``.
    """
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
        from ..io import read_structured

        return read_structured(Path(truth)), str(truth)
    return dict(truth), "truth"


def check_truth(truth: Mapping[str, Any] | str | Path) -> tuple[Mapping[str, Any], str]:
    """Read and check a simulator's truth (``run`` calls this before calibrating).

    Args:
        truth: a truth.json path, or its loaded mapping.

    Returns:
        The truth's ``reconstruction_points_world`` mapping, and its name for messages.

    Raises:
        AriSfmError: if the file is missing, malformed or not a simulator truth.json.
    """
    data, where = _truth_points(truth)
    recon = data.get("reconstruction_points_world") if isinstance(data, Mapping) else None
    if not isinstance(recon, Mapping):
        raise AriSfmError(where, "has no reconstruction_points_world (not a simulator truth.json)")
    return recon, where


def truth_errors(points: Points, truth: Mapping[str, Any] | str | Path) -> TruthErrors:
    """Measure the 3D errors against a truth's ``reconstruction_points_world``, unaligned and after rigid alignment.

    Args:
        points: the reconstructed points.
        truth: a truth.json path, or its loaded mapping.

    Returns:
        The errors, as is and after the best rigid alignment (no scale).

    Raises:
        AriSfmError: if the truth is not a valid truth or lacks a frame or corner of the points.
    """
    recon, where = check_truth(truth)
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
    return TruthErrors(int(len(A)), float(np.sqrt(np.mean(e0**2))), float(e0.max()), float(np.sqrt(np.mean(e1**2))),
                       float(e1.max()), angle, float(np.linalg.norm(t)))


def rigid_alignment(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Find R, t minimising sum |R a + t - b|^2 (Kabsch, no scale; a proper rotation).

    Args:
        A: the points to move (N, 3).
        B: their targets (N, 3).

    Returns:
        R (3, 3) and t (3,).
    """
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


# --------------------------------------------------------------------------- all


def reconstruction_metrics(points: Points, target: Target, truth: Mapping[str, Any] | str | Path | None = None,
                           plane_threshold_mm: float = PLANE_THRESHOLD_MM) -> ReconstructionMetrics:
    """Measure all the metrics of the module docstring.

    Args:
        points: the reconstructed points.
        target: the target (its grid and pitch for the corner spacing).
        truth: a simulator's truth (a truth.json path or its mapping) for the truth errors; None for none.
        plane_threshold_mm: RANSAC's inlier distance of each frame's plane (mm).

    Returns:
        The metrics (``to_json()``: metrics.json's body).

    Raises:
        AriSfmError: with no reconstructed frame, or a truth that does not match.
    """
    if not points.frames:
        raise AriSfmError(None, "no reconstructed frames to measure")
    truth_part = truth_errors(points, truth) if truth is not None else None  # checks the truth first
    planes = {f: _frame_plane(fp, plane_threshold_mm) for f, fp in points.frames.items()}
    stage, stage_frames = _stage_metrics(points, planes)
    grid = target.grid
    frames: dict[str, FrameMetrics] = {}
    all_d, all_ic = [], []
    for f, fp in points.frames.items():
        p = planes[f]
        plane = flatness = spacing = None
        if p is not None:
            plane = FramePlane(_vec3(p["normal"]), _vec3(p["point"]), int(p["inliers"].sum()))
            flatness = _stats(p["distances"])
            all_d.append(p["distances"])
        if grid is not None:
            dist = inter_corner_distances(fp.ids, fp.xyz, grid[0])
            spacing = _stats(dist - target.pitch_mm)
            all_ic.append(dist)
        frames[f] = FrameMetrics(fp.stage_mm, len(fp), plane, flatness, spacing, stage_frames.get(f))
    d = np.concatenate(all_d) if all_d else np.zeros(0)
    flat = Flatness(**vars(_stats(d)), distances=_floats(d))
    inter = None
    if grid is not None:
        dist = np.concatenate(all_ic) if all_ic else np.zeros(0)
        inter = InterCorner(**vars(_stats(dist - target.pitch_mm)), square_mm=float(target.pitch_mm),
                            distances=_floats(dist), errors=_floats(dist - target.pitch_mm))
    gaps = np.concatenate([fp.ray_gap_mm for fp in points.frames.values()])
    rmse = [fp.reprojection_rmse_px for fp in points.frames.values() if fp.reprojection_rmse_px is not None]
    reproj = None
    if len(rmse) == len(points.frames):
        w = np.array([len(fp) for fp in points.frames.values()], dtype=float)
        reproj = float(np.sqrt(np.sum(w * np.square(rmse)) / w.sum()))
    return ReconstructionMetrics(
        int(points.num_points), len(points.frames),
        RayGap(float(gaps.mean()), float(np.sqrt(np.mean(gaps**2))), float(gaps.max())),
        reproj, flat, stage, inter, truth_part, frames,
    )


def save_point_clouds(points: Points, out_dir: str | Path) -> dict[str, Path]:
    """Write ``<frame>.ply`` per frame and ``all.ply`` (coloured by frame) into a folder.

    Each file is written under a temporary name and renamed (atomic).

    Args:
        points: the reconstructed points.
        out_dir: the folder (created if missing).

    Returns:
        Frame name (and ``all``) -> the file written.

    Raises:
        AriSfmError: if Open3D could not write a cloud.
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

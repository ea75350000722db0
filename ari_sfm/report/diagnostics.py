"""What the report's diagnostic figures show, as numbers, and the recommendations drawn from them.

Three breakdowns of a calibration's reprojection residuals (``(observation,
residual)`` pairs from :func:`ari_sfm.calibration.evaluate.observation_residuals`):

- :func:`region_grid`: RMS residual and corner count per cell of a
  ``GRID_COLS x GRID_ROWS`` grid over each camera's image (coverage = the
  share of cells holding a calibration corner);
- :func:`frame_rmse`: RMS residual per set, frame and camera;
- :func:`corner_depths`: each corner's depth along the camera's optical axis
  (its board pose in calibration.json), for residuals by depth.

:func:`recommendations` turns them, the calibration's uncertainty and
outliers and the reconstruction's depths into a short list of plain sentences.
Every threshold is a constant below; each rule has a test that triggers it
and one that does not (tests/test_report.py).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..calibration.record import Calibration
from ..records import Observation, Target

GRID_COLS, GRID_ROWS = 8, 6  # image cells for coverage and residuals by region
COVERAGE_MIN = 0.6  # below this share of cells with a calibration corner: add views near the image edges
REGION_RATIO = 1.6  # a cell's RMS above this multiple of the camera's RMS: a pattern the model misses
REGION_MIN_CORNERS = 10  # ... judged only on cells with at least this many corners (RMS of pure noise: +-16 %)
FRAME_RATIO = 3.0  # a calibration image's RMS above this multiple of the median one's: check that image
FRAME_MIN_PX = 0.1  # ... and above this (px), so that noise-level differences never trigger
DISTANCE_REL_STD = 0.05  # window distance std / distance above this: barely determined
DEPTH_MARGIN = 0.10  # reconstruction deeper or nearer than the calibrated depths by this share of their span

Residuals = Sequence[tuple[Observation, np.ndarray]]


@dataclass(frozen=True)
class RegionGrid:
    """Residuals of one camera by image cell (rows top to bottom, columns left to right)."""

    camera: str
    image_size: tuple[int, int]
    rms_px: np.ndarray  # (GRID_ROWS, GRID_COLS), NaN where a cell has no corner
    count: np.ndarray  # (GRID_ROWS, GRID_COLS) corners per cell
    calibration_count: np.ndarray  # (GRID_ROWS, GRID_COLS) calibration-set corners per cell

    @property
    def coverage(self) -> float:
        """Share of cells holding at least one calibration corner."""
        return float((self.calibration_count > 0).mean())


def rms(r: np.ndarray) -> float:
    """sqrt(mean(du^2 + dv^2)) of (N, 2) residuals (NaN for none)."""
    return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) if len(r) else float("nan")


def region_grid(calibration: Calibration, residuals: Residuals, camera: str) -> RegionGrid:
    """RMS and counts of a camera's residuals over a GRID_COLS x GRID_ROWS grid of its image.

    Args:
        calibration: The calibration (the camera's image size).
        residuals: (observation, residual (N, 2) px) pairs.
        camera: The camera's name.

    Returns:
        The camera's grid of RMS residuals and counts.
    """
    w, h = calibration.cameras[camera].image_size
    sums = np.zeros((GRID_ROWS, GRID_COLS))
    count = np.zeros((GRID_ROWS, GRID_COLS), int)
    cal_count = np.zeros((GRID_ROWS, GRID_COLS), int)
    for o, r in residuals:
        if o.camera != camera:
            continue
        col = np.clip((o.pixels[:, 0] / w * GRID_COLS).astype(int), 0, GRID_COLS - 1)
        row = np.clip((o.pixels[:, 1] / h * GRID_ROWS).astype(int), 0, GRID_ROWS - 1)
        np.add.at(sums, (row, col), np.sum(r**2, axis=1))
        np.add.at(count, (row, col), 1)
        if o.set == "calibration":
            np.add.at(cal_count, (row, col), 1)
    grid = np.full(sums.shape, np.nan)
    grid[count > 0] = np.sqrt(sums[count > 0] / count[count > 0])
    return RegionGrid(camera, (int(w), int(h)), grid, count, cal_count)


def frame_rmse(residuals: Residuals) -> dict[tuple[str, str, str], float]:
    """RMS residual per (set, frame, camera), in the order the observations come."""
    out: dict[tuple[str, str, str], list[np.ndarray]] = {}
    for o, r in residuals:
        out.setdefault((o.set, o.frame, o.camera), []).append(r)
    return {k: rms(np.concatenate(v)) for k, v in out.items()}


def corner_depths(calibration: Calibration, residuals: Residuals, target: Target) -> list[np.ndarray]:
    """Depth of every corner of each (observation, residual) pair along its camera's optical axis.

    Args:
        calibration: The calibration (its board poses and cameras).
        residuals: (observation, residual) pairs.
        target: The target (its points on the board).

    Returns:
        One array (N,) of depths (mm) per pair; NaN where the board pose is unknown.
    """
    ids_all, xyz_all = target.points_3d()
    lookup = {int(i): k for k, i in enumerate(ids_all)}
    out = []
    for o, _ in residuals:
        pose = (calibration.stacking_poses if o.set == "stacking" else calibration.frames).get(o.frame)
        if pose is None:
            out.append(np.full(len(o.ids), np.nan))
            continue
        X = pose.apply(xyz_all[[lookup[int(i)] for i in o.ids]])
        out.append(calibration.cameras[o.camera].cam_from_world.apply(X)[:, 2])
    return out


def point_depths(calibration: Calibration, points: Mapping[str, np.ndarray], camera: str) -> np.ndarray:
    """Depths of world points along a camera's optical axis.

    Args:
        calibration: The calibration.
        points: World points by frame, each (N, 3), mm.
        camera: The camera's name.

    Returns:
        Depths (M,), mm, of all the points.
    """
    if not points:
        return np.zeros(0)
    xyz = np.concatenate([np.asarray(p, float).reshape(-1, 3) for p in points.values()])
    return calibration.cameras[camera].cam_from_world.apply(xyz)[:, 2]


def region_name(row: int, col: int) -> str:
    """Name a grid cell's part of the image (the image cut in thirds each way).

    Args:
        row: The cell's row (0: top) of GRID_ROWS.
        col: The cell's column (0: left) of GRID_COLS.

    Returns:
        'top left corner', 'right edge', 'centre', ...
    """
    v = ("top", "", "bottom")[min(3 * row // GRID_ROWS, 2)]
    u = ("left", "", "right")[min(3 * col // GRID_COLS, 2)]
    if v and u:
        return f"{v} {u} corner"
    return f"{v or u} edge" if (v or u) else "centre"


def recommendations(calibration: Calibration, residuals: Residuals, target: Target | None = None,
                    points: Mapping[str, np.ndarray] | None = None) -> list[str]:
    """Plain-language advice drawn from the figures (thresholds: the module's constants).

    Args:
        calibration: The calibration.
        residuals: (observation, residual) pairs.
        target: The target, for the depth advice; None to skip it.
        points: Reconstructed world points by frame, for the depth advice; None to skip it.

    Returns:
        The advice, one sentence each (empty when nothing stands out).
    """
    out: list[str] = []
    cal = calibration
    for name in cal.cameras:
        grid = region_grid(cal, residuals, name)
        if grid.calibration_count.sum() and grid.coverage < COVERAGE_MIN:
            out.append(f"The calibration corners cover {100 * grid.coverage:.0f} % of {name}'s image "
                       f"(cells of an {GRID_COLS} x {GRID_ROWS} grid): add views with the board near the edges "
                       "and corners of its image.")
        if not grid.count.sum():
            continue
        cam_rms = rms(np.concatenate([r for o, r in residuals if o.camera == name]))
        judged = np.where(grid.count >= REGION_MIN_CORNERS, grid.rms_px, np.nan)
        if np.isfinite(judged).any() and np.nanmax(judged) > REGION_RATIO * cam_rms:
            row, col = (int(i) for i in np.unravel_index(int(np.nanargmax(judged)), judged.shape))
            spec = cal.spec
            fix = ("try --model exact (Snell's law at the window)"
                   if cal.model == "ari" or not spec.window or spec.projection == "polynomial"
                   else "try --distortion" if not np.any(cal.cameras[name].dist)
                   else "check the corner detections there")
            out.append(f"{name}'s residuals near the {region_name(row, col)} of its image are "
                       f"{judged[row, col] / cam_rms:.1f} x its RMS ({judged[row, col]:.3f} vs {cam_rms:.3f} px): "
                       f"a pattern the model does not capture; {fix}.")
    per_frame = frame_rmse([(o, r) for o, r in residuals if o.set == "calibration"])  # stacking images differ
    if len(per_frame) >= 3:  # by design (added glass): judged on the calibration images only
        median = float(np.median(list(per_frame.values())))
        bad = [(k, v) for k, v in per_frame.items() if v > FRAME_RATIO * median and v > FRAME_MIN_PX]
        for (set_name, frame, camera), value in sorted(bad, key=lambda kv: -kv[1])[:3]:
            out.append(f"The {set_name} image {frame} of {camera} has {value / median:.1f} x the median image's "
                       f"RMS ({value:.3f} vs {median:.3f} px): check its corner detection or leave it out.")
    u = cal.uncertainty
    for w in cal.window_list():
        d = w.interface.distance_mm
        s = None if u is None else (u.windows[w.name].distance_mm if w.name in u.windows else u.distance_mm)
        if u is not None and u.estimates_distance and d and s is not None and s / abs(d) > DISTANCE_REL_STD:
            which = "window" if not cal.windows else f"window {w.name}"
            out.append(f"The {which} distance is barely determined ({d:.1f} ± {s:.1f} mm, "
                       f"{100 * s / abs(d):.0f} %): declare it (its plane in rig.yaml: a board "
                       "lying on the window) or add views over a wider range of depths and angles.")
    if cal.outliers is not None and cal.outliers.corners and not cal.outliers.excluded:
        out.append(f"{len(cal.outliers.corners)} corners lie beyond {cal.outliers.threshold_sigma:g} sigma "
                   "(listed in calibration.json under outliers): check them, or re-run with --exclude-outliers.")
    if target is not None and points:
        calib = [(o, r) for o, r in residuals if o.set == "calibration"]
        depths = corner_depths(cal, calib, target)
        for name in cal.cameras:
            z = np.concatenate([d for (o, _), d in zip(calib, depths) if o.camera == name] or [np.zeros(0)])
            z = z[np.isfinite(z)]
            pz = point_depths(cal, points, name)
            if len(z) < 2 or not len(pz):
                continue
            lo, hi = float(z.min()), float(z.max())
            margin = DEPTH_MARGIN * max(hi - lo, 1e-9)
            if pz.min() < lo - margin or pz.max() > hi + margin:
                out.append(f"The reconstruction spans {pz.min():.0f}-{pz.max():.0f} mm from {name}, beyond the "
                           f"{lo:.0f}-{hi:.0f} mm its calibration views covered: add calibration views at those "
                           "depths.")
    return out

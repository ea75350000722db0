"""Find target corners in images: checkerboards, ChArUco and dot boards (OpenCV), whole datasets.

Corner ids follow DATASET_FORMAT.md and are the same for the same physical
corner in every image and camera:

- Checkerboard (``inner_corners`` (cols, rows)): id ``r * cols + c`` at board
  point (c s, r s, 0). The board is printed so that the square diagonally
  outside corner 0 (away from corners 1 and cols) is black, and it is seen
  from its printed side (the board's z axis points away from the camera, as
  in OpenCV). OpenCV may return the grid in another order (rotated by 180
  degrees; for square grids also transposed); :func:`_canonical_grid` keeps
  the orderings that are not mirror images and picks the one whose square
  colours match the print. That is unique iff cols + rows is odd, i.e. the
  number of squares along the two sides, cols + 1 and rows + 1, differ in
  parity (e.g. 11 x 8 corners = 12 x 9 squares). Other boards look the same
  after a 180 degree turn: their ids are OpenCV's guess and may differ
  between images (:func:`detect_dataset` warns).
- ChArUco: OpenCV's ids (the markers identify every corner).
- Dot boards (``circles``): OpenCV's circle-grid ids, made independent of the
  order findCirclesGrid returns: see :func:`detect_circles`,
  :func:`circle_symmetries` (which layouts have unique ids) and
  :func:`_canonical_circles` (the rule for the others).

Accuracy (see ``benchmarks/bench_detection.py``): coarse corners from
``cv2.findChessboardCorners`` refined by ``cv2.cornerSubPix`` on a lightly
smoothed image with a window scaled to the local square size; this beat
``cv2.findChessboardCornersSB`` (with or without its accuracy flag) on every
rendered view set we measured.
"""
from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor, as_completed
from functools import lru_cache
from pathlib import Path
from typing import Callable, NamedTuple

import cv2
import numpy as np
from tqdm import tqdm

from ari_sfm.errors import AriSfmError
from ari_sfm.records import Dataset, Entry, Observation, Target

log = logging.getLogger(__name__)

Detection = tuple[np.ndarray, np.ndarray]  # ids (N,) int, pixels (N, 2) float

# cornerSubPix settings (tuned with benchmarks/bench_detection.py on rendered boards)
SUBPIX_WINDOW_FRACTION = 0.45  # window half-size / local square size (px)
SUBPIX_MIN_HALF_WINDOW = 2  # px
SUBPIX_SMOOTHING_PX = 1.5  # Gaussian sigma applied before refinement: averages noise and aliasing
# ChArUco: the window must stay inside the white border around each marker, (square - marker) / 2 wide,
# and smoothing must not pull the marker edges into it (a 0.45 window and 1.5 px blur gave 0.6 px RMS).
CHARUCO_WINDOW_MARGIN = 0.9  # window half-size / marker border width
CHARUCO_SMOOTHING_PX = 0.7
CHARUCO_MAX_SHIFT_PX = 1.0  # a refinement moving OpenCV's corner further is discarded
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
_CLASSIC_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
COARSE_MIN_SIDE_PX = 600  # coarsest pyramid level for findChessboardCorners: longer side >= this


# --------------------------------------------------------------------------- single images


def detect_corners(image: np.ndarray, target: Target, method: str = "subpix") -> Detection | None:
    """The target's corners in a grayscale image: (ids, pixels), or None if the target is not found.

    ``method`` selects the checkerboard detector (``subpix``, the default and
    the most accurate; the others are kept for the benchmark): see
    :data:`CHECKERBOARD_METHODS`. ChArUco boards always use OpenCV's
    CharucoDetector followed by cornerSubPix with a window kept inside the
    white border around the markers.
    """
    image = as_gray_u8(image)
    if target.type == "checkerboard":
        try:
            find = CHECKERBOARD_METHODS[method]
        except KeyError:
            raise ValueError(f"unknown checkerboard method {method!r} (one of {', '.join(CHECKERBOARD_METHODS)})") from None
        grid = tuple(int(v) for v in target.inner_corners)
        corners = find(image, grid)
        if corners is None or not _grid_is_regular(corners, grid):
            return None
        corners = _canonical_grid(image, corners, grid)
        if corners is None:
            return None
        return np.arange(grid[0] * grid[1]), corners
    if target.type == "charuco":
        return _detect_charuco(image, target, refine=method != "charuco_raw")
    if target.type == "circles":  # dot boards: the checkerboard default "subpix" means their default
        return detect_circles(image, target, method=None if method == "subpix" else method)
    raise ValueError(f"cannot detect a target of type {target.type!r} in images")


def as_gray_u8(image: np.ndarray) -> np.ndarray:
    """A uint8 single-channel view of ``image`` (colour is converted, deeper images rescaled to their max)."""
    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if image.dtype != np.uint8:
        peak = float(image.max()) if image.size else 0.0
        image = np.clip(image.astype(np.float64) * (255.0 / peak if peak > 0 else 1.0), 0, 255).round().astype(np.uint8)
    return np.ascontiguousarray(image)


def _find_classic(image: np.ndarray, grid: tuple[int, int]) -> np.ndarray | None:
    """cv2.findChessboardCorners at full resolution (OpenCV's own refinement only), OpenCV order."""
    found, corners = cv2.findChessboardCorners(image, grid, flags=_CLASSIC_FLAGS)
    return corners.reshape(-1, 2).astype(np.float64) if found else None


def _find_coarse(image: np.ndarray, grid: tuple[int, int]) -> np.ndarray | None:
    """findChessboardCorners on an image pyramid, coarse to fine: corners to ~1 px, OpenCV order.

    findChessboardCorners is fast on small squares but can take seconds on
    large blurred ones (and on images without a board). So it first runs on a
    copy halved until its longer side is below 2 * COARSE_MIN_SIDE_PX (squares
    of ~8 px still work), then, if needed, on finer levels with FAST_CHECK
    (cheap rejection of boardless images). Coordinates are mapped back to full
    resolution (pixel centres: x = (x_level + 0.5) * 2^k - 0.5).
    """
    levels = 0
    while max(image.shape) / 2 ** (levels + 1) >= COARSE_MIN_SIDE_PX:
        levels += 1
    pyramid = [image]
    for _ in range(levels):
        pyramid.append(cv2.resize(pyramid[-1], (pyramid[-1].shape[1] // 2, pyramid[-1].shape[0] // 2), interpolation=cv2.INTER_AREA))
    for k in range(levels, -1, -1):
        flags = _CLASSIC_FLAGS if k == levels else _CLASSIC_FLAGS | cv2.CALIB_CB_FAST_CHECK
        found, corners = cv2.findChessboardCorners(pyramid[k], grid, flags=flags)
        if found:
            scale_x = image.shape[1] / pyramid[k].shape[1]
            scale_y = image.shape[0] / pyramid[k].shape[0]
            corners = corners.reshape(-1, 2).astype(np.float64)
            return np.stack([(corners[:, 0] + 0.5) * scale_x - 0.5, (corners[:, 1] + 0.5) * scale_y - 0.5], axis=1)
    return None


def _find_subpix(image: np.ndarray, grid: tuple[int, int]) -> np.ndarray | None:
    """Pyramid findChessboardCorners, then :func:`refine_corners` (the default)."""
    corners = _find_coarse(image, grid)
    if corners is None or not _grid_is_regular(corners, grid):
        return None
    return refine_corners(image, corners, _grid_spacing(corners, grid))


def _find_sb(flags: int) -> Callable[[np.ndarray, tuple[int, int]], np.ndarray | None]:
    def find(image: np.ndarray, grid: tuple[int, int]) -> np.ndarray | None:
        found, corners = cv2.findChessboardCornersSB(image, grid, flags=flags)
        return corners.reshape(-1, 2).astype(np.float64) if found else None

    find.__doc__ = f"cv2.findChessboardCornersSB with flags {flags}."
    return find


CHECKERBOARD_METHODS: dict[str, Callable[[np.ndarray, tuple[int, int]], np.ndarray | None]] = {
    "subpix": _find_subpix,  # pyramid findChessboardCorners + cornerSubPix (smoothed, scaled window)
    "classic": _find_classic,  # findChessboardCorners alone
    "sb": _find_sb(cv2.CALIB_CB_NORMALIZE_IMAGE),
    "sb_accuracy": _find_sb(cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY),
    "sb_exhaustive_accuracy": _find_sb(cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY),
}


def refine_corners(
    image: np.ndarray, corners: np.ndarray, spacing: np.ndarray,
    fraction: float | None = None, smoothing_px: float | None = None, skip_small: bool = False,
) -> np.ndarray:
    """cornerSubPix on a Gaussian-smoothed copy, each corner with a window scaled to its square size.

    ``spacing`` (N,) is each corner's distance to its nearest grid neighbour
    in pixels. Corners are refined in groups of equal window size: half-size
    ``fraction`` (default SUBPIX_WINDOW_FRACTION) x spacing, at least
    SUBPIX_MIN_HALF_WINDOW; with ``skip_small`` corners whose window would be
    smaller than that are returned unchanged instead.
    """
    fraction = SUBPIX_WINDOW_FRACTION if fraction is None else fraction
    smoothing_px = SUBPIX_SMOOTHING_PX if smoothing_px is None else smoothing_px
    smooth = image.astype(np.float32)
    if smoothing_px > 0:
        smooth = cv2.GaussianBlur(smooth, (0, 0), smoothing_px)
    half = np.rint(fraction * np.asarray(spacing, dtype=float))
    keep = half < SUBPIX_MIN_HALF_WINDOW if skip_small else np.zeros(len(half), dtype=bool)
    half = np.maximum(SUBPIX_MIN_HALF_WINDOW, half).astype(int)
    half[keep] = 0
    out = np.asarray(corners, dtype=np.float32).reshape(-1, 1, 2).copy()
    for w in np.unique(half[~keep]):
        sel = np.nonzero(half == w)[0]
        out[sel] = cv2.cornerSubPix(smooth, out[sel].copy(), (int(w), int(w)), (-1, -1), _SUBPIX_CRITERIA)
    return out.reshape(-1, 2).astype(np.float64)


def _grid_spacing(corners: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """Per corner of a full (rows x cols) grid: distance to its nearest row / column neighbour."""
    cols, rows = grid
    g = corners.reshape(rows, cols, 2)
    best = np.full((rows, cols), np.inf)
    dx = np.linalg.norm(np.diff(g, axis=1), axis=2)  # (rows, cols-1)
    dy = np.linalg.norm(np.diff(g, axis=0), axis=2)  # (rows-1, cols)
    if cols > 1:
        best[:, :-1] = np.minimum(best[:, :-1], dx)
        best[:, 1:] = np.minimum(best[:, 1:], dx)
    if rows > 1:
        best[:-1, :] = np.minimum(best[:-1, :], dy)
        best[1:, :] = np.minimum(best[1:, :], dy)
    return best.ravel()


def _grid_is_regular(corners: np.ndarray, grid: tuple[int, int], tolerance: float = 0.25) -> bool:
    """False for a grid that is not a smooth lattice (second differences above ``tolerance`` x spacing).

    Catches detectors that latch onto the board's outline: findChessboardCornersSB
    sometimes returns small boards with rows shifted by one square.
    """
    cols, rows = grid
    g = corners.reshape(rows, cols, 2)
    spacing = float(np.median(_grid_spacing(corners, grid)))
    worst = 0.0
    if cols > 2:
        worst = max(worst, float(np.linalg.norm(g[:, 2:] - 2 * g[:, 1:-1] + g[:, :-2], axis=2).max()))
    if rows > 2:
        worst = max(worst, float(np.linalg.norm(g[2:] - 2 * g[1:-1] + g[:-2], axis=2).max()))
    if cols > 1 and rows > 1:  # parallelogram rule on every cell
        worst = max(worst, float(np.linalg.norm(g[1:, 1:] - g[1:, :-1] - g[:-1, 1:] + g[:-1, :-1], axis=2).max()))
    if not worst <= tolerance * spacing:
        log.debug("rejected a corner grid: second difference %.1f px at spacing %.1f px", worst, spacing)
        return False
    return True


# --------------------------------------------------------------------------- checkerboard ids


def checkerboard_ids_unambiguous(target: Target) -> bool:
    """True if the square colours fix the corner order: cols + rows odd (see the module docstring)."""
    cols, rows = target.inner_corners
    return (cols + rows) % 2 == 1


def _grid_orderings(cols: int, rows: int) -> list[np.ndarray]:
    """Index arrays (rows, cols) into an OpenCV-ordered grid for every symmetry keeping its shape."""
    idx = np.arange(cols * rows).reshape(rows, cols)
    out = [idx, idx[::-1, ::-1], idx[:, ::-1], idx[::-1, :]]
    if cols == rows:
        t = idx.T
        out += [t, t[::-1, ::-1], t[:, ::-1], t[::-1, :]]
    return out


def _canonical_grid(image: np.ndarray, corners: np.ndarray, grid: tuple[int, int]) -> np.ndarray | None:
    """Reorder OpenCV's grid so that corner r * cols + c is board corner (c, r) (None if undecidable).

    Keeps the orderings in which board x and y map to image directions with
    the handedness of a board seen from its printed side, then picks the one
    whose predicted square colours (square between corners (c, r) and
    (c+1, r+1) is black iff c + r is even) best match the image.
    """
    cols, rows = grid
    if cols < 2 or rows < 2:
        return corners  # a single row or column: no squares between corners to check
    smooth = cv2.GaussianBlur(image, (0, 0), 1.0)
    h, w = image.shape
    best, best_score = None, 0.0
    for order in _grid_orderings(cols, rows):
        g = corners[order]  # (rows, cols, 2) in the candidate's board order
        ex = g[:, 1:, :] - g[:, :-1, :]
        ey = g[1:, :, :] - g[:-1, :, :]
        if np.sum(ex[:-1, :, 0] * ey[:, :-1, 1] - ex[:-1, :, 1] * ey[:, :-1, 0]) <= 0:
            continue  # a mirror image of the board
        centres = 0.25 * (g[:-1, :-1] + g[:-1, 1:] + g[1:, :-1] + g[1:, 1:])  # (rows-1, cols-1, 2)
        u = np.clip(np.rint(centres[..., 0]).astype(int), 0, w - 1)
        v = np.clip(np.rint(centres[..., 1]).astype(int), 0, h - 1)
        values = smooth[v, u].astype(float)
        r, c = np.mgrid[0 : rows - 1, 0 : cols - 1]
        white = np.where((r + c) % 2 == 1, 1.0, -1.0)
        score = float(np.mean((values - values.mean()) * white))
        if best is None or score > best_score + 1e-9:
            best, best_score = g, score
    if best is None or best_score <= 0:
        return None
    return best.reshape(-1, 2)


# --------------------------------------------------------------------------- ChArUco


@lru_cache(maxsize=8)
def charuco_board(squares: tuple[int, int], square_mm: float, marker_mm: float, dictionary: str) -> cv2.aruco.CharucoBoard:
    """OpenCV's ChArUco board for a target's parameters (the renderer draws the same board)."""
    if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
        raise ValueError(f"unknown ArUco dictionary {dictionary!r}")
    aruco_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.CharucoBoard(tuple(int(v) for v in squares), float(square_mm), float(marker_mm), aruco_dict)


def _charuco_detector(target: Target) -> cv2.aruco.CharucoDetector:
    board = charuco_board(tuple(target.squares), float(target.square_mm), float(target.marker_mm), str(target.dictionary))
    return cv2.aruco.CharucoDetector(board)


def _detect_charuco(image: np.ndarray, target: Target, refine: bool = True) -> Detection | None:
    """OpenCV's CharucoDetector (a new one per call: detectors are not shared between threads)."""
    corners, ids, _, _ = _charuco_detector(target).detectBoard(image)
    if ids is None or len(ids) == 0:
        return None
    ids = ids.reshape(-1).astype(int)
    pixels = corners.reshape(-1, 2).astype(np.float64)
    order = np.argsort(ids)
    ids, pixels = ids[order], pixels[order]
    if refine:
        border = 0.5 * (float(target.square_mm) - float(target.marker_mm)) / float(target.square_mm)
        refined = refine_corners(image, pixels, _charuco_spacing(ids, pixels, target.grid[0]),
                                 fraction=CHARUCO_WINDOW_MARGIN * border, smoothing_px=CHARUCO_SMOOTHING_PX, skip_small=True)
        moved = np.linalg.norm(refined - pixels, axis=1) <= CHARUCO_MAX_SHIFT_PX  # else caught by a marker edge
        pixels[moved] = refined[moved]
    return ids, pixels


def _charuco_spacing(ids: np.ndarray, pixels: np.ndarray, cols: int) -> np.ndarray:
    """Per ChArUco corner: distance to its nearest detected row / column neighbour (px)."""
    where = {int(i): k for k, i in enumerate(ids)}
    out = np.full(len(ids), np.inf)
    for k, i in enumerate(ids):
        r, c = divmod(int(i), cols)
        for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            rr, cc = r + dr, c + dc
            j = where.get(rr * cols + cc) if 0 <= cc < cols and rr >= 0 else None
            if j is not None:
                out[k] = min(out[k], float(np.linalg.norm(pixels[j] - pixels[k])))
    if np.isinf(out).all():
        return np.full(len(ids), 2.0 * (SUBPIX_MIN_HALF_WINDOW + 1) / SUBPIX_WINDOW_FRACTION)
    out[np.isinf(out)] = np.min(out)  # isolated corners: the smallest spacing seen
    return out


# --------------------------------------------------------------------------- datasets


def detect_dataset(
    dataset: Dataset, workers: int | None = None, progress: bool = True, min_calibration_views: int = 3
) -> tuple[Observation, ...]:
    """Detect the target in every image of the dataset (stacking, calibration, reconstruction).

    Images are read and searched in parallel threads (at most os.cpu_count()).
    Images without the target are skipped with a warning. A stacking pose
    whose target a camera finds at fewer than two plate thicknesses is dropped
    for that camera (warning). Raises AriSfmError for an unreadable image (the
    first in dataset order, with the count of the others) and when a camera
    keeps fewer than ``min_calibration_views`` calibration views (counting
    detections from ``dataset.observations`` for entries without images).
    Output order: entry order, then the dataset's camera order.
    """
    target = dataset.target
    if target.type == "checkerboard" and not checkerboard_ids_unambiguous(target):
        cols, rows = target.inner_corners
        log.warning(
            "%s: a %d x %d corner checkerboard looks the same turned by 180 degrees (cols + rows is even): "
            "its corner ids may differ between images; use a board with cols + rows odd",
            dataset.rig_path, cols, rows,
        )
    if target.type == "circles" and not circle_ids_unambiguous(target):
        log.warning(
            "%s: this %s dot grid looks the same turned in its plane: dot ids are fixed by the image direction "
            "of the board's x axis (see ari_sfm.detection) and may differ between images of a board turned "
            "further than 90 degrees; an asymmetric grid with an odd number of rows (e.g. 4 x 11) has unique ids",
            dataset.rig_path, target.layout,
        )
    cam_rank = {name: k for k, name in enumerate(dataset.camera_names)}
    jobs: list[tuple[Entry, str, Path]] = []
    for entry in dataset.entries():
        for cam in sorted(entry.images, key=lambda c: (cam_rank.get(c, len(cam_rank)), list(entry.images).index(c))):
            path = Path(entry.images[cam])
            jobs.append((entry, cam, path if path.is_absolute() else Path(dataset.root) / path))

    cpus = os.cpu_count() or 1
    n_workers = max(1, min(cpus, workers if workers is not None else cpus, len(jobs) or 1))
    results: list[Detection | None] = [None] * len(jobs)
    with ThreadPoolExecutor(max_workers=n_workers) as pool, tqdm(
        total=len(jobs), disable=not progress, desc="detecting corners", unit="image"
    ) as bar:
        futures = {pool.submit(_detect_file, path, target): k for k, (_, _, path) in enumerate(jobs)}
        unreadable: dict[int, AriSfmError] = {}
        try:
            for future in as_completed(futures):
                try:
                    results[futures[future]] = future.result()
                except AriSfmError as exc:
                    unreadable[futures[future]] = exc
                bar.update(1)
        except BaseException:
            for f in futures:
                f.cancel()
            raise
    if unreadable:  # the first in dataset order (not completion order), so every run names the same file
        first = unreadable[min(unreadable)]
        more = f" (and {len(unreadable) - 1} more unreadable images)" if len(unreadable) > 1 else ""
        raise AriSfmError(first.path, first.message + more)

    observations: list[Observation] = []
    for (entry, cam, path), found in zip(jobs, results):
        if found is None:
            log.warning("%s: target not found, image skipped", path)
            continue
        ids, pixels = found
        observations.append(
            Observation(
                camera=cam, set=entry.set, frame=entry.key, ids=ids, pixels=pixels,
                added_mm=entry.added_mm if entry.set == "stacking" else None, stage_mm=entry.stage_mm,
            )
        )
    observations = _drop_thin_stacking(observations)
    _check_calibration_views(dataset, jobs, observations, min_calibration_views)
    return tuple(observations)


def _detect_file(path: Path, target: Target) -> Detection | None:
    """Read one image and detect the target; AriSfmError if the file cannot be read or decoded.

    An unreadable image is an error, not a skipped view: it means a broken
    copy or a wrong file, which a warning would hide. (A truncated JPEG still
    decodes, grey below the cut: its target is then usually not found.)
    """
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise AriSfmError(path, f"cannot read image: {exc.strerror or exc}") from None
    if data.size == 0:
        raise AriSfmError(path, "cannot read image: the file is empty")
    image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
    if image is None or image.size == 0:
        raise AriSfmError(path, "cannot read image: corrupt, truncated or not an image format OpenCV decodes")
    return detect_corners(image, target)


def _drop_thin_stacking(observations: list[Observation]) -> list[Observation]:
    """Drop a camera's stacking pose seen at fewer than two plate thicknesses (warning)."""
    thicknesses: dict[tuple[str, str], set[float | None]] = {}
    for o in observations:
        if o.set == "stacking":
            thicknesses.setdefault((o.camera, o.frame), set()).add(o.added_mm)
    thin = {key for key, values in thicknesses.items() if len(values) < 2}
    for cam, pose in sorted(thin):
        log.warning(
            "stacking pose %s: camera %s shows the target at fewer than 2 plate thicknesses; its stacking images are not used",
            pose, cam,
        )
    return [o for o in observations if not (o.set == "stacking" and (o.camera, o.frame) in thin)]


def _check_calibration_views(
    dataset: Dataset, jobs: list[tuple[Entry, str, Path]], observations: list[Observation], minimum: int
) -> None:
    """Raise if a camera with calibration images keeps fewer than ``minimum`` calibration views."""
    listed: dict[str, int] = {}
    for entry, cam, _ in jobs:
        if entry.set == "calibration":
            listed[cam] = listed.get(cam, 0) + 1
    imaged = {(e.key, cam) for e, cam, _ in jobs if e.set == "calibration"}
    given = {(o.frame, o.camera) for o in dataset.observations or () if o.set == "calibration"} - imaged
    for cam in dataset.camera_names:
        if cam not in listed:
            continue
        found = sum(1 for o in observations if o.set == "calibration" and o.camera == cam)
        found_elsewhere = sum(1 for frame, c in given if c == cam)
        if found + found_elsewhere < minimum:
            raise AriSfmError(
                dataset.rig_path,
                f"only {found} of the {listed[cam]} calibration images of camera {cam} show the target "
                f"(need >= {minimum})",
            )


# --------------------------------------------------------------------------- dot boards
#
# A dot board (``type: circles``) is found by cv2.findCirclesGrid with a
# SimpleBlobDetector whose area limits are tuned to the dots of the image, then
# relabelled so that ids follow the contract (see :func:`circle_symmetries`),
# and each centre is refined as the grey-level centroid of its dot. Measured with
# benchmarks/bench_detection.py; the README gives the figures.

CIRCLE_MIN_AREA_PX = 8.0  # smallest blob taken for a dot (px^2): ~3 px across
CIRCLE_AREA_RANGE = 3.0  # tuned blob detector: area within [1/r, r] x the range of the dots found
CIRCLE_SIZE_PASS_SIDE_PX = 800  # the dot-size pass runs on a copy halved until its longer side is below 2x this
CIRCLE_MAX_BLOBS_FACTOR = 4  # more candidate blobs than this x dots: only the clustering grid search (fast)
CIRCLE_GRID_TOLERANCE = 0.3  # homography residual / dot spacing above which a grid is rejected
CIRCLE_EDGE_MARGIN_PX = 2.0  # blur margin (px) between the dot's edge and the background ring
_RING_POINTS = 64  # polygon vertices for the image of a dot's outline (perspective bias)


def detect_circles(image: np.ndarray, target: Target, method: str | None = None) -> Detection | None:
    """The dot centres of a ``circles`` target in an image: (ids, pixels), or None if not found.

    ``method`` (default CIRCLE_DEFAULT_METHOD) picks the centre estimate, see
    :data:`CIRCLE_METHODS`. Dark dots on a light board are tried first, then
    light dots on a dark board. OpenCV's plain grid search is tried before its
    CALIB_CB_CLUSTERING one: on boards tilted 45-65 degrees (640 x 480, spacing
    16-24 px) the plain search found 9 of 20 views, clustering all 20.
    """
    method = CIRCLE_DEFAULT_METHOD if method is None else method
    if method not in CIRCLE_METHODS:
        raise ValueError(f"unknown circles method {method!r} (one of {', '.join(CIRCLE_METHODS)})")
    image = as_gray_u8(image)
    cols, rows = (int(v) for v in target.circle_grid)
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if target.layout == "asymmetric" else cv2.CALIB_CB_SYMMETRIC_GRID
    for colour in (0, 255):  # dark dots, then light dots
        detector, blobs = _tuned_blob_detector(image, cols * rows, colour)
        if detector is None:
            continue
        found = False
        if blobs <= CIRCLE_MAX_BLOBS_FACTOR * cols * rows:  # the grid search is slow on many blobs (a minute on noise)
            found, centres = cv2.findCirclesGrid(image, (cols, rows), flags=flags, blobDetector=detector)
        if not found:
            found, centres = cv2.findCirclesGrid(image, (cols, rows), flags=flags | cv2.CALIB_CB_CLUSTERING,
                                                 blobDetector=detector)
        if not found:
            continue
        centres = centres.reshape(-1, 2).astype(np.float64)
        pixels = _canonical_circles(centres, target)
        if pixels is None:  # OpenCV's order is not a board order (asymmetric grids with rows even): our own
            ordered = _lattice_order(centres, target)
            pixels = None if ordered is None else _canonical_circles(ordered, target)
        if pixels is None:
            return None
        return np.arange(cols * rows), CIRCLE_METHODS[method](image, target, pixels, colour)
    return None


def _blob_params(colour: int, min_area: float, max_area: float) -> cv2.SimpleBlobDetector_Params:
    params = cv2.SimpleBlobDetector_Params()
    params.filterByColor, params.blobColor = True, colour
    params.filterByArea, params.minArea, params.maxArea = True, float(min_area), float(max_area)
    params.minDistBetweenBlobs = 2.0
    return params


def _tuned_blob_detector(image: np.ndarray, count: int, colour: int) -> tuple[cv2.SimpleBlobDetector | None, int]:
    """A blob detector whose area limits bracket the dots of this image, and the number of blobs
    within those limits ((None, n): fewer than ``count`` blobs).

    A first pass with wide limits (CIRCLE_MIN_AREA_PX to the largest dot a
    board of ``count`` dots can have in this image, area / count) finds the
    blobs; the dots are the ``count`` blobs of most similar size (the tightest
    run of sizes); the tuned limits are their size range widened by
    CIRCLE_AREA_RANGE (perspective changes dot areas across the board), which
    drops text, smudges and background clutter of other sizes.
    """
    small, scale = image, 1.0
    while max(small.shape) >= 2 * CIRCLE_SIZE_PASS_SIDE_PX:  # the wide pass runs on a smaller copy (speed)
        small = cv2.resize(small, (small.shape[1] // 2, small.shape[0] // 2), interpolation=cv2.INTER_AREA)
    sizes = _blob_sizes(small, count, colour) * (image.shape[1] / small.shape[1])
    if len(sizes) < count and small is not image:  # dots too small for the copy
        sizes = _blob_sizes(image, count, colour)
    if len(sizes) < count:
        return None, len(sizes)
    spread = np.log(sizes[count - 1:]) - np.log(sizes[: len(sizes) - count + 1])
    k = int(np.argmin(spread))
    lo = max(CIRCLE_MIN_AREA_PX, np.pi / 4 * sizes[k] ** 2 / CIRCLE_AREA_RANGE)
    hi = np.pi / 4 * sizes[k + count - 1] ** 2 * CIRCLE_AREA_RANGE
    areas = np.pi / 4 * sizes**2
    return cv2.SimpleBlobDetector_create(_blob_params(colour, lo, hi)), int(np.count_nonzero((areas >= lo) & (areas <= hi)))


def _blob_sizes(image: np.ndarray, count: int, colour: int) -> np.ndarray:
    """Sorted diameters (px) of the blobs of ``colour`` from CIRCLE_MIN_AREA_PX to area / ``count``."""
    h, w = image.shape
    wide = cv2.SimpleBlobDetector_create(_blob_params(colour, CIRCLE_MIN_AREA_PX, max(CIRCLE_MIN_AREA_PX + 1, w * h / count)))
    return np.sort([k.size for k in wide.detect(image)])


def circle_symmetries(target: Target) -> list[tuple[np.ndarray, int]]:
    """The symmetries of the dot layout: (permutation p, det) for each rotation by a multiple of
    90 degrees (det +1) or reflection (det -1) about the board centre that maps the dots onto
    themselves; dot i goes to the place of dot p[i]. The identity is first.

    A board seen from its printed side can only be confused with its proper
    rotations (det +1): the ids are unique iff the identity is the only one.
    Symmetric grids always have the 180 degree turn (square ones also 90);
    asymmetric grids have it iff rows is even (e.g. 4 x 11 is unambiguous).
    """
    _, xyz = target.points_3d_readonly
    xy = xyz[:, :2] - xyz[:, :2].mean(axis=0)
    tol = 1e-6 * max(float(target.spacing_mm), 1e-9)
    out = []
    for A in (np.eye(2), np.array([[0, -1], [1, 0]]), -np.eye(2), np.array([[0, 1], [-1, 0]]),
              np.diag([1, -1]), np.diag([-1, 1]), np.array([[0, 1], [1, 0]]), np.array([[0, -1], [-1, 0]])):
        moved = xy @ A.T
        d = np.linalg.norm(moved[:, None, :] - xy[None, :, :], axis=2)
        p = np.argmin(d, axis=1)
        if np.all(d[np.arange(len(xy)), p] < tol) and len(set(p.tolist())) == len(xy):
            out.append((p, int(round(np.linalg.det(A)))))
    return out


def circle_ids_unambiguous(target: Target) -> bool:
    """True if no turn of the board in its plane maps the dot layout onto itself (see :func:`circle_symmetries`)."""
    return sum(1 for _, det in circle_symmetries(target) if det > 0) == 1


def _board_homography(target: Target, pixels: np.ndarray) -> np.ndarray:
    """Least-squares homography from board (x, y) mm to the pixels of ids 0..N-1."""
    _, xyz = target.points_3d_readonly
    H, _ = cv2.findHomography(xyz[:, :2], pixels, 0)
    return H


def _apply_h(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.asarray(xy, float) @ H[:, :2].T + H[:, 2]
    return p[:, :2] / p[:, 2:3]


def _h_jacobian(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """d pixel / d board at board points xy (N, 2): (N, 2, 2)."""
    p = np.asarray(xy, float) @ H[:, :2].T + H[:, 2]
    w = p[:, 2:3, None]
    return (H[None, :2, :2] - (p[:, :2, None] / w) * H[None, 2:3, :2]) / w


def _canonical_circles(pixels: np.ndarray, target: Target) -> np.ndarray | None:
    """Relabel OpenCV's dot grid so that id i is board point i seen from the printed side (None if the
    grid is not a board: irregular, or only a mirror image fits).

    Among the labellings that the layout's symmetries allow, keep those whose
    board-to-image map keeps orientation (Jacobian det > 0 in OpenCV pixels: the
    board seen from its printed side, its z axis away from the camera), then take the one
    whose board x axis points most nearly to the image's right (+u): for a
    layout with a proper symmetry the ids are fixed by this rule, i.e. they
    stay the same while the board's in-image roll stays within +-90 degrees
    of upright (+-45 for 4-fold layouts).
    """
    _, xyz = target.points_3d_readonly
    centre = xyz[:, :2].mean(axis=0, keepdims=True)
    best, best_cos = None, -np.inf
    for p, _ in circle_symmetries(target):
        candidate = np.empty_like(pixels)
        candidate[p] = pixels  # the dot OpenCV called i is board dot p[i]
        H = _board_homography(target, candidate)
        if H is None:
            return None
        J = _h_jacobian(H, centre)[0]
        if np.linalg.det(J) <= 0:
            continue
        cos = J[0, 0] / np.linalg.norm(J[:, 0])
        if cos > best_cos + 1e-9:
            best, best_cos = (candidate, H), cos
    if best is None:
        log.debug("rejected a dot grid: only a mirror image of the board fits")
        return None
    candidate, H = best
    spacing = float(np.median(np.linalg.norm(_h_jacobian(H, xyz[:, :2]), axis=1))) * float(target.spacing_mm)
    residual = float(np.linalg.norm(_apply_h(H, xyz[:, :2]) - candidate, axis=1).max())
    if not residual <= CIRCLE_GRID_TOLERANCE * spacing:
        log.debug("rejected a dot grid: homography residual %.1f px at spacing %.1f px", residual, spacing)
        return None
    return candidate


def _lattice_order(pixels: np.ndarray, target: Target) -> np.ndarray | None:
    """The dots ordered as board ids by walking their lattice in the image (None if the walk fails).

    Board dots lie on a square lattice: symmetric grids with steps (s, 0),
    (0, s); asymmetric grids with the diagonal steps (s, s), (s, -s). From the
    dot nearest the middle, whose two nearest non-parallel neighbours give the
    image steps, a breadth-first walk labels each dot with integer lattice
    coordinates, predicting every neighbour from the steps measured at its
    parent (perspective changes them slowly). The labelled set must equal the
    layout under one of the 8 turns and flips of the lattice plus a shift; the
    result is one such order (:func:`_canonical_circles` picks among them).
    """
    n = len(pixels)
    d = np.linalg.norm(pixels[:, None] - pixels[None], axis=2)
    np.fill_diagonal(d, np.inf)
    seed = int(np.argmin(np.linalg.norm(pixels - pixels.mean(axis=0), axis=1)))
    near = np.argsort(d[seed])
    g1 = pixels[near[0]] - pixels[seed]
    g2 = next((pixels[j] - pixels[seed] for j in near[1:8]
               if abs(np.dot(pixels[j] - pixels[seed], g1)) < 0.7 * np.linalg.norm(g1) * np.linalg.norm(pixels[j] - pixels[seed])), None)
    if g2 is None:
        return None
    coords = {seed: (0, 0)}
    steps = {seed: np.array([g1, g2])}
    taken = np.zeros(n, dtype=bool)
    taken[seed] = True
    queue = [seed]
    while queue:
        k = queue.pop(0)
        for axis in (0, 1):
            for sign in (1, -1):
                guess = pixels[k] + sign * steps[k][axis]
                dist = np.linalg.norm(pixels - guess, axis=1)
                j = int(np.argmin(dist))
                if taken[j] or dist[j] > 0.35 * np.linalg.norm(steps[k][axis]):
                    continue
                taken[j] = True
                i0, j0 = coords[k]
                coords[j] = (i0 + sign, j0) if axis == 0 else (i0, j0 + sign)
                steps[j] = steps[k].copy()
                steps[j][axis] = sign * (pixels[j] - pixels[k])
                queue.append(j)
    if not taken.all():
        return None
    ij = np.array([coords[k] for k in range(n)])
    if target.layout == "asymmetric":  # diagonal steps: board units x = i + j, y = i - j
        ij = np.stack([ij[:, 0] + ij[:, 1], ij[:, 0] - ij[:, 1]], axis=1)
    _, xyz = target.points_3d_readonly
    board = np.rint(xyz[:, :2] / float(target.spacing_mm)).astype(int)
    where = {(int(x), int(y)): k for k, (x, y) in enumerate(board)}
    for A in (np.eye(2), np.array([[0, -1], [1, 0]]), -np.eye(2), np.array([[0, 1], [-1, 0]]),
              np.diag([1, -1]), np.diag([-1, 1]), np.array([[0, 1], [1, 0]]), np.array([[0, -1], [-1, 0]])):
        moved = ij @ A.T.astype(int)
        moved = moved - moved.min(axis=0) + board.min(axis=0)
        ids = [where.get((int(x), int(y))) for x, y in moved]
        if None not in ids and len(set(ids)) == n:
            out = np.empty_like(pixels)
            out[np.array(ids)] = pixels
            return out
    return None


def _nearest_neighbour_mm(target: Target) -> float:
    return float(target.spacing_mm) * (np.sqrt(2.0) if target.layout == "asymmetric" else 1.0)


def _dot_radius_mm(image: np.ndarray, target: Target, colour: int, H: np.ndarray) -> float:
    """The printed dot radius: half of ``diameter_mm`` if declared, else measured as the median dot area
    (weights / contrast, in board mm^2), measured twice: the second time with windows fitted to the first."""
    if target.diameter_mm is not None:
        return 0.5 * float(target.diameter_mm)
    radius = 0.25 * _nearest_neighbour_mm(target)  # a first guess, for the windows only
    for _ in range(2):
        areas = []
        for k in range(target.num_ids()):
            window = _dot_window(image, target, H, k, radius)
            if window is None:
                continue
            core = window.r_mm <= 0.5 * radius
            contrast = float(np.abs(window.values[core] - window.background).mean()) if core.any() else 0.0
            if contrast > 0:
                areas.append(float(_dot_weights(window, colour).sum()) / contrast * window.mm_per_px**2)
        if not areas:
            return radius
        radius = min(float(np.sqrt(np.median(areas) / np.pi)), 0.49 * _nearest_neighbour_mm(target))
    return radius


class DotWindow(NamedTuple):
    """The pixels around one imaged dot: centres uv (P, 2), grey values (P,), distance of each pixel's
    board point from the dot centre r_mm (P,), the window radius (mm), background grey level, mm per px."""

    uv: np.ndarray
    values: np.ndarray
    r_mm: np.ndarray
    outer_mm: float
    background: float
    mm_per_px: float


def _dot_window(image: np.ndarray, target: Target, H: np.ndarray, k: int, radius_mm: float) -> DotWindow | None:
    """The window around dot k, defined on the board through H (None if no window fits in the image).

    It holds the board points closer to the dot centre than halfway across the
    gap to the nearest neighbour (shrunk near the image border); the background
    level is the mean of its outer ring, beyond the dot edge plus
    CIRCLE_EDGE_MARGIN_PX.
    """
    _, xyz = target.points_3d_readonly
    X = xyz[k, :2]
    outer = radius_mm + 0.5 * (_nearest_neighbour_mm(target) - 2 * radius_mm)
    mm_per_px = 1.0 / np.sqrt(abs(np.linalg.det(_h_jacobian(H, X[None])[0])))
    inner = radius_mm + CIRCLE_EDGE_MARGIN_PX * mm_per_px
    angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    h, w = image.shape
    while True:  # near the image border the window shrinks (down to a ring of one pixel around the dot's edge)
        box = _apply_h(H, X + outer * ring)
        u0, v0 = np.floor(box.min(axis=0) - 1).astype(int)
        u1, v1 = np.ceil(box.max(axis=0) + 1).astype(int)
        if u0 >= 0 and v0 >= 0 and u1 < w and v1 < h:
            break
        outer *= 0.9
        if outer < inner + mm_per_px:
            return None
    vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    r = np.linalg.norm(_apply_h(np.linalg.inv(H), uv) - X, axis=1)
    values = image[vv.ravel(), uu.ravel()].astype(float)
    ring_mask = (r <= outer) & (r >= inner) if inner < outer else (r <= outer) & (r >= outer - 0.5 * mm_per_px)
    if not ring_mask.any():
        return None
    return DotWindow(uv, values, r, outer, float(values[ring_mask].mean()), float(mm_per_px))


def _dot_weights(window: DotWindow, colour: int) -> np.ndarray:
    """Per pixel: how much darker (dark dots, colour 0) or lighter than the background, 0 outside the window."""
    weights = (window.background - window.values) if colour == 0 else (window.values - window.background)
    return np.where(window.r_mm <= window.outer_mm, weights, 0.0)


def _refine_centroid(image: np.ndarray, target: Target, pixels: np.ndarray, colour: int,
                     debias: bool = False, iterations: int = 1) -> np.ndarray:
    """Each dot's centre as the grey-level centroid of its image (the imaged ellipse's centre).

    The window around each dot is shaped by the board-to-image homography
    (refitted after each pass; a second pass changed nothing measurable on
    rendered boards, so one is the default). With ``debias`` the perspective bias is
    removed: under a homography the centre of the imaged disc is not the image
    of the disc's centre; the difference, computed from the imaged outline of
    each dot (a polygon's area centroid minus H(centre)), is subtracted.
    """
    _, xyz = target.points_3d_readonly
    out = pixels.copy()
    for _ in range(iterations):
        H = _board_homography(target, out)
        radius = _dot_radius_mm(image, target, colour, H)
        new = out.copy()
        for k in range(len(out)):
            window = _dot_window(image, target, H, k, radius)
            if window is None:
                continue  # keeps OpenCV's centre
            weights = _dot_weights(window, colour)
            total = float(weights.sum())
            if total > 0:
                new[k] = weights @ window.uv / total
        if debias:
            new -= _perspective_bias(H, xyz[:, :2], radius)
        out = new
    return out


def _perspective_bias(H: np.ndarray, centres_mm: np.ndarray, radius_mm: float) -> np.ndarray:
    """Centre of the image of each disc (area centroid of its imaged outline) minus the image of its centre."""
    t = np.linspace(0, 2 * np.pi, _RING_POINTS, endpoint=False)
    circle = radius_mm * np.stack([np.cos(t), np.sin(t)], axis=1)
    out = np.empty((len(centres_mm), 2))
    for k, X in enumerate(centres_mm):
        poly = _apply_h(H, X + circle)
        x, y = poly[:, 0], poly[:, 1]
        xn, yn = np.roll(x, -1), np.roll(y, -1)
        cross = x * yn - xn * y
        area = 0.5 * cross.sum()
        centroid = np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)
        out[k] = centroid - _apply_h(H, X[None])[0]
    return out


CIRCLE_METHODS: dict[str, Callable[[np.ndarray, Target, np.ndarray, int], np.ndarray]] = {
    "blob": lambda image, target, pixels, colour: pixels,  # OpenCV's blob centres (relabelled)
    "centroid": lambda image, target, pixels, colour: _refine_centroid(image, target, pixels, colour),
    "centroid_debiased": lambda image, target, pixels, colour: _refine_centroid(image, target, pixels, colour, debias=True),
}
CIRCLE_DEFAULT_METHOD = "centroid_debiased"

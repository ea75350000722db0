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
  order findCirclesGrid returns: see :mod:`ari_sfm.circle_grid`.
- 3D bodies (``points3d``, DATASET_FORMAT 1.3): the body's dots identified from
  a calibration entry's ``manual_points`` (>= 4 clicked points per camera): see
  :mod:`ari_sfm.body`. A general 3D body cannot be identified without them.

Checkerboard corners: coarse corners from ``cv2.findChessboardCorners``
refined by ``cv2.cornerSubPix`` on a lightly smoothed image with a window
scaled to the local square size.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor, as_completed, wait
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ari_sfm.body import BodyHints, BodyWindow, ClickError, find_body
from ari_sfm.circle_grid import circle_ids_unambiguous, detect_circles
from ari_sfm.errors import AriSfmError
from ari_sfm.records import Dataset, Entry, Observation, Target

log = logging.getLogger(__name__)

Detection = tuple[np.ndarray, np.ndarray]  # ids (N,) int, pixels (N, 2) float
MIN_BODY_POINTS = 6  # a 3D body's view with fewer identified points is skipped (a camera's start needs 6)

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
    """Find the target's corners in one image.

    ChArUco boards always use OpenCV's CharucoDetector followed by cornerSubPix with a window kept
    inside the white border around the markers. Dot boards go to
    :func:`ari_sfm.circle_grid.detect_circles`.

    Args:
        image: Grayscale (or colour, converted) image of any depth.
        target: The target (checkerboard, ChArUco or circles).
        method: The checkerboard detector, a key of :data:`CHECKERBOARD_METHODS` (``subpix``, the default,
            is the most accurate; the others are kept for the benchmark). For a ChArUco board
            ``charuco_raw`` skips the refinement; for a dot board a key of
            :data:`ari_sfm.circle_grid.CIRCLE_METHODS` (``subpix`` means its default).

    Returns:
        (ids (N,) int, pixels (N, 2) float, OpenCV pixels), or None if the target is not found.

    Raises:
        ValueError: Unknown ``method`` or a target type that is not detected in images.
    """
    image = as_gray_u8(image)
    if target.type == "checkerboard":
        try:
            find = CHECKERBOARD_METHODS[method]
        except KeyError:
            raise ValueError(f"unknown checkerboard method {method!r} "
                             f"(one of {', '.join(CHECKERBOARD_METHODS)})") from None
        cols, rows = (int(v) for v in target.required(target.inner_corners, "inner_corners"))
        grid = (cols, rows)
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
        pyramid.append(cv2.resize(pyramid[-1], (pyramid[-1].shape[1] // 2, pyramid[-1].shape[0] // 2),
                                  interpolation=cv2.INTER_AREA))
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

    Corners are refined in groups of equal window size.

    Args:
        image: Grayscale uint8 image.
        corners: Coarse corners (N, 2), OpenCV pixels.
        spacing: Each corner's distance to its nearest grid neighbour (N,), px.
        fraction: Window half-size / spacing; None for SUBPIX_WINDOW_FRACTION. The half-size is at least
            SUBPIX_MIN_HALF_WINDOW.
        smoothing_px: Gaussian sigma of the smoothing (px; 0: none); None for SUBPIX_SMOOTHING_PX.
        skip_small: Return corners whose window would be smaller than SUBPIX_MIN_HALF_WINDOW unchanged
            (instead of refining them with that window).

    Returns:
        The refined corners (N, 2), float64.
    """
    fraction = SUBPIX_WINDOW_FRACTION if fraction is None else fraction
    smoothing_px = SUBPIX_SMOOTHING_PX if smoothing_px is None else smoothing_px
    smooth: np.ndarray = image.astype(np.float32)
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
    cols, rows = target.required(target.inner_corners, "inner_corners")
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
def charuco_board(squares: tuple[int, int], square_mm: float, marker_mm: float,
                  dictionary: str) -> cv2.aruco.CharucoBoard:
    """OpenCV's ChArUco board for a target's parameters (the renderer draws the same board).

    Args:
        squares: (columns, rows) of squares.
        square_mm: Square side (mm).
        marker_mm: Marker side (mm).
        dictionary: An OpenCV ArUco dictionary name (``DICT_...``).

    Returns:
        The board (cached).

    Raises:
        ValueError: Unknown dictionary.
    """
    if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
        raise ValueError(f"unknown ArUco dictionary {dictionary!r}")
    aruco_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.CharucoBoard(tuple(int(v) for v in squares), float(square_mm), float(marker_mm), aruco_dict)


def _charuco_detector(target: Target) -> cv2.aruco.CharucoDetector:
    board = charuco_board(target.required(target.squares, "squares"), float(target.square_mm),
                          float(target.required(target.marker_mm, "marker_mm")), str(target.dictionary))
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
        border = (0.5 * (float(target.square_mm) - float(target.required(target.marker_mm, "marker_mm")))
                  / float(target.square_mm))
        refined = refine_corners(image, pixels, _charuco_spacing(ids, pixels, target.required(target.grid, "grid")[0]),
                                 fraction=CHARUCO_WINDOW_MARGIN * border, smoothing_px=CHARUCO_SMOOTHING_PX,
                                 skip_small=True)
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
    dataset: Dataset, workers: int | None = None, progress: bool = True, min_calibration_views: int = 3,
    skip_observed: bool = False,
) -> tuple[Observation, ...]:
    """Detect the target in every image of the dataset (stacking, calibration, reconstruction).

    A 3D body (``points3d``) is identified in each image from its entry's ``manual_points`` for that
    camera. Images are read and searched in parallel threads (at most os.cpu_count()). Images without
    the target are skipped with a warning. A stacking pose whose target a camera finds at fewer than two
    plate thicknesses is dropped for that camera (warning).

    Args:
        dataset: The dataset.
        workers: Threads; None for os.cpu_count().
        progress: Show a progress bar.
        min_calibration_views: Calibration views each camera with calibration images must keep (planar
            targets; one view of a non-planar body is enough). Detections from ``dataset.observations``
            for entries without images count.
        skip_observed: Do not detect the views ``dataset.observations`` already hold; return those
            observations first, followed by the new ones.

    Returns:
        The observations, in entry order, then the dataset's camera order.

    Raises:
        AriSfmError: An unreadable image (the first in dataset order, with the count of the others), an
            image whose size is not its camera's, a 3D body's view whose clicked points are missing or do
            not fit the body (naming rig.yaml and the camera), or a camera keeping fewer than
            ``min_calibration_views`` calibration views.
    """
    target = dataset.target
    if target.type == "checkerboard" and not checkerboard_ids_unambiguous(target):
        cols, rows = target.required(target.inner_corners, "inner_corners")
        log.warning(
            "%s: a %d x %d corner checkerboard looks the same turned by 180 degrees (cols + rows is even): "
            "its corner ids may differ between images; use a board with cols + rows odd",
            dataset.rig_path, cols, rows,
        )
    if target.type == "circles" and not circle_ids_unambiguous(target):
        log.warning(
            "%s: this %s dot grid looks the same turned in its plane: dot ids are fixed by the image direction "
            "of the board's x axis (see ari_sfm.circle_grid) and may differ between images of a board turned "
            "further than 90 degrees; an asymmetric grid with an odd number of rows (e.g. 4 x 11) has unique ids",
            dataset.rig_path, target.layout,
        )
    cam_rank = {name: k for k, name in enumerate(dataset.camera_names)}
    observed = {(o.set, o.frame, o.added_mm, o.camera) for o in dataset.observations or ()} if skip_observed else set()
    jobs: list[tuple[Entry, str, Path]] = []
    for entry in dataset.entries():
        for cam in sorted(entry.images, key=lambda c: (cam_rank.get(c, len(cam_rank)), list(entry.images).index(c))):
            if (entry.set, entry.key, entry.added_mm, cam) in observed:
                continue
            path = Path(entry.images[cam])
            jobs.append((entry, cam, path if path.is_absolute() else Path(dataset.root) / path))
    bodies = [_body_job(dataset, entry, cam) for entry, cam, _ in jobs] if target.type == "points3d" else None

    cpus = os.cpu_count() or 1
    n_workers = max(1, min(cpus, workers if workers is not None else cpus, len(jobs) or 1))
    results: list[Detection | None] = [None] * len(jobs)
    unreadable: dict[int, AriSfmError] = {}
    pool = ThreadPoolExecutor(max_workers=n_workers)
    futures: dict = {}
    try:
        with tqdm(total=len(jobs), disable=not progress, desc="detecting corners", unit="image") as bar:
            for k, (_, cam, path) in enumerate(jobs):
                futures[pool.submit(_detect_file, path, target, dataset.cameras[cam].image_size,
                                    dataset.rig_path, cam, None if bodies is None else bodies[k])] = k
            for future in as_completed(futures):
                try:
                    results[futures[future]] = future.result()
                except AriSfmError as exc:
                    unreadable[futures[future]] = exc
                bar.update(1)
    finally:
        _stop_workers(pool, futures)
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
    minimum = min_calibration_views if target.is_planar() else 1
    _check_calibration_views(dataset, jobs, observations, minimum)
    if skip_observed:
        return tuple(dataset.observations or ()) + tuple(observations)
    return tuple(observations)


@dataclass(frozen=True)
class BodyJob:
    """What identifying a 3D body in one image needs besides the image.

    Attributes:
        clicks: The clicked points ``{id: (u, v)}``.
        hints: Focal length, window and dot size (:class:`~ari_sfm.body.BodyHints`).
        where: How to name the view in an error.
    """

    clicks: Mapping[int, tuple[float, float]]
    hints: BodyHints
    where: str  # e.g. "calibration frame f000, manual_points.cam1"


def _body_job(dataset: Dataset, entry: Entry, camera: str) -> BodyJob:
    """The clicks and hints of one view of a 3D body; AriSfmError naming rig.yaml and the camera without clicks."""
    key = "pose" if entry.set == "stacking" else "frame"
    clicks = entry.manual_points.get(camera)
    if not clicks:
        where = (f"give them as manual_points.{camera} of this calibration entry (OpenPTV's man_ori.dat)"
                 if entry.set == "calibration" else "only calibration entries give them (manual_points)")
        raise AriSfmError(dataset.rig_path, f"{entry.set} {key} {entry.key}: camera {camera}: a 3D body (target "
                                            f"points3d) is identified in its image from >= 4 clicked points: {where}")
    spec = dataset.cameras[camera]
    focal, aspect = spec.focal_px, 1.0
    if spec.K is not None:
        focal, aspect = float(spec.K[0, 0]), float(spec.K[1, 1] / spec.K[0, 0])
    hints = BodyHints(focal_px=focal, aspect=aspect, window=_body_window(dataset, entry, camera),
                      diameter_mm=dataset.target.diameter_mm)
    return BodyJob(clicks, hints, f"{entry.set} {key} {entry.key}, manual_points.{camera}")


def _body_window(dataset: Dataset, entry: Entry, camera: str) -> BodyWindow | None:
    """The window ``camera`` looks through, in the body's frame of ``entry``: from its window's ``plane`` when it
    is given in that frame (then the exact model identifies the dots), else None (a pinhole with k1 does)."""
    interface = dataset.interface_of(camera)
    plane = interface.plane
    if plane is None or plane.frame != entry.key:
        return None
    return BodyWindow(np.asarray(plane.normal, float), np.asarray(plane.point_mm, float), interface.thickness_mm,
                      interface.index, interface.medium_index)


def _stop_workers(pool: ThreadPoolExecutor, futures: Iterable[Future]) -> None:
    """Cancel the queued detections and wait until every started one has returned (each ends within one image).

    On Ctrl-C the process must not exit while a worker thread is inside
    OpenCV: the interpreter's exit then unwinds it through C++ frames and the
    process aborts (SIGABRT: "terminate called without an active exception",
    "FATAL: exception not rethrown"). It waits on the futures, not on
    ``Thread.join``: a join cut short by a second Ctrl-C marks a running thread
    as stopped (CPython gh-90882), so later joins return at once. Further
    Ctrl-Cs do not cut the wait short.
    """
    futures = list(futures)
    while True:
        try:
            pool.shutdown(wait=False, cancel_futures=True)
            pending = [f for f in futures if not f.done()]
            if not pending:
                break
            wait(pending)
        except KeyboardInterrupt:
            continue
    while True:  # the workers are out of OpenCV now: let them leave
        try:
            pool.shutdown(wait=True)
            return
        except KeyboardInterrupt:
            continue


def _detect_file(path: Path, target: Target, image_size: tuple[int, int] | None = None,
                 rig_path: Path | None = None, camera: str = "", body: BodyJob | None = None) -> Detection | None:
    """Read one image and detect the target (a 3D body: identify it from ``body``'s clicks); AriSfmError if
    the file cannot be read or decoded, or if its size is not the camera's ``image_size`` [width, height]
    (when given), or if a body's clicks do not fit it.

    An unreadable image is an error, not a skipped view: it means a broken
    copy or a wrong file, which a warning would hide. (A truncated JPEG still
    decodes, grey below the cut: its target is then usually not found.) So is
    an image of another size: calibrated as is it gives wrong intrinsics silently.
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
    if image_size is not None and (image.shape[1], image.shape[0]) != tuple(image_size):
        raise AriSfmError(path, f"image is {image.shape[1]} x {image.shape[0]} px but {rig_path or 'the rig'} "
                                f"gives cameras.{camera}.image_size [{image_size[0]}, {image_size[1]}]")
    if body is not None:
        return _identify_body(image, target, body, path, rig_path)
    return detect_corners(image, target)


def _identify_body(image: np.ndarray, target: Target, body: BodyJob, path: Path, rig_path: Path | None
                   ) -> Detection | None:
    """A 3D body's identified points in one image (None below MIN_BODY_POINTS)."""
    try:
        match = find_body(image, target, body.clicks, body.hints)
    except ClickError as exc:
        raise AriSfmError(rig_path or path, f"{body.where}: {exc} in {path.name}") from None
    log.info("%s: %d of %d body points in view identified (%d ambiguous, %d off the model left out)", path.name,
             len(match.ids), match.visible, len(match.ambiguous), len(match.off_model))
    if len(match.ids) < MIN_BODY_POINTS:
        return None
    order = np.argsort(match.ids)
    return match.ids[order], match.pixels[order]


def _drop_thin_stacking(observations: list[Observation]) -> list[Observation]:
    """Drop a camera's stacking pose seen at fewer than two plate thicknesses (warning)."""
    thicknesses: dict[tuple[str, str], set[float | None]] = {}
    for o in observations:
        if o.set == "stacking":
            thicknesses.setdefault((o.camera, o.frame), set()).add(o.added_mm)
    thin = {key for key, values in thicknesses.items() if len(values) < 2}
    for cam, pose in sorted(thin):
        log.warning(
            "stacking pose %s: camera %s shows the target at fewer than 2 plate thicknesses; its stacking images are "
            "not used",
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


def ensure_observations(dataset, workers: int | None = None, progress: bool = False):
    """The dataset with observations, detecting corners in its images (:func:`detect_dataset`) when it has none.

    A 3D body's calibration views that have an image but no observations (e.g. an OpenPTV import where
    some cameras have no ``.crd``) are identified from their clicked points and added to the observations
    it has.

    Args:
        dataset: The dataset (:class:`~ari_sfm.records.Dataset`).
        workers: Threads for the detection; None for os.cpu_count().
        progress: Show a progress bar.

    Returns:
        ``dataset`` itself if nothing is to detect, else a copy with the observations.
    """
    if dataset.observations is None:
        return dataset.with_observations(detect_dataset(dataset, workers=workers, progress=progress))
    if dataset.target.type == "points3d" and _unobserved_body_views(dataset):
        return dataset.with_observations(detect_dataset(dataset, workers=workers, progress=progress,
                                                        skip_observed=True), dataset.observations_path)
    return dataset


def _unobserved_body_views(dataset: Dataset) -> list[tuple[str, str]]:
    """(frame, camera) of calibration entries with an image but no observation."""
    observed = {(o.set, o.frame, o.camera) for o in dataset.observations or ()}
    return [(e.key, cam) for e in dataset.calibration
            for cam in e.images if ("calibration", e.key, cam) not in observed]

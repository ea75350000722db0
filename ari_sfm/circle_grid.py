"""Dot boards (``type: circles``, DATASET_FORMAT 1.1): find the grid, give the dots the contract's
ids, measure each dot's centre.

cv2.findCirclesGrid runs with a SimpleBlobDetector whose area limits are tuned
to the dots of the image (:func:`_tuned_blob_detector`); its grid is relabelled
so that ids follow the contract whatever order OpenCV returns
(:func:`circle_symmetries` says which layouts have unique ids,
:func:`_canonical_circles` gives the rule for the others, :func:`_lattice_order`
orders the dots itself where OpenCV's order is no board order); each centre is
then the grey-level centroid of its dot, corrected for perspective
(:func:`_refine_centroid`). :func:`ari_sfm.detection.detect_corners` dispatches here.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from typing import NamedTuple

import cv2
import numpy as np

from ari_sfm.records import Target

log = logging.getLogger(__name__)

Detection = tuple[np.ndarray, np.ndarray]  # ids (N,) int, pixels (N, 2) float

CIRCLE_MIN_AREA_PX = 8.0  # smallest blob taken for a dot (px^2): ~3 px across
CIRCLE_AREA_RANGE = 3.0  # tuned blob detector: area within [1/r, r] x the range of the dots found
CIRCLE_SIZE_PASS_SIDE_PX = 800  # the dot-size pass runs on a copy halved until its longer side is below 2x this
CIRCLE_MAX_BLOBS_FACTOR = 4  # more candidate blobs than this x dots: only the clustering grid search (fast)
CIRCLE_GRID_TOLERANCE = 0.3  # homography residual / dot spacing above which a grid is rejected
CIRCLE_EDGE_MARGIN_PX = 2.0  # blur margin (px) between the dot's edge and the background ring
_RING_POINTS = 64  # polygon vertices for the image of a dot's outline (perspective bias)


def detect_circles(image: np.ndarray, target: Target, method: str | None = None) -> Detection | None:
    """Find the dot centres of a ``circles`` target.

    Dark dots on a light board are tried first, then light dots on a dark board. OpenCV's plain grid
    search is tried before its CALIB_CB_CLUSTERING one.

    Args:
        image: Grayscale uint8 image.
        target: The ``circles`` target (its grid, layout, spacing).
        method: The centre estimate, a key of :data:`CIRCLE_METHODS`; None for CIRCLE_DEFAULT_METHOD.

    Returns:
        (ids (N,) int, pixels (N, 2) float, OpenCV pixels) with the contract's ids, or None if the grid
        is not found.

    Raises:
        ValueError: ``method`` is not one of :data:`CIRCLE_METHODS`.
    """
    method = CIRCLE_DEFAULT_METHOD if method is None else method
    if method not in CIRCLE_METHODS:
        raise ValueError(f"unknown circles method {method!r} (one of {', '.join(CIRCLE_METHODS)})")
    cols, rows = (int(v) for v in target.required(target.circle_grid, "circle_grid"))
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


def _blob_params(colour: int, min_area: float, max_area: float) -> cv2.SimpleBlobDetector.Params:
    params = cv2.SimpleBlobDetector.Params()
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
    small = image
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
    kept = int(np.count_nonzero((areas >= lo) & (areas <= hi)))
    return cv2.SimpleBlobDetector.create(_blob_params(colour, lo, hi)), kept


def _blob_sizes(image: np.ndarray, count: int, colour: int) -> np.ndarray:
    """Sorted diameters (px) of the blobs of ``colour`` from CIRCLE_MIN_AREA_PX to area / ``count``."""
    h, w = image.shape
    wide = cv2.SimpleBlobDetector.create(_blob_params(colour, CIRCLE_MIN_AREA_PX,
                                                      max(CIRCLE_MIN_AREA_PX + 1, w * h / count)))
    return np.sort([k.size for k in wide.detect(image)])


def circle_symmetries(target: Target) -> list[tuple[np.ndarray, int]]:
    """The symmetries of the dot layout.

    A board seen from its printed side can only be confused with its proper rotations (det +1): the ids
    are unique iff the identity is the only one. Symmetric grids always have the 180 degree turn (square
    ones also 90); asymmetric grids have it iff rows is even (e.g. 4 x 11 is unambiguous).

    Args:
        target: The ``circles`` target.

    Returns:
        (permutation p, det) for each rotation by a multiple of 90 degrees (det +1) or reflection
        (det -1) about the board centre that maps the dots onto themselves; dot i goes to the place of
        dot p[i]. The identity is first.
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
               if abs(np.dot(pixels[j] - pixels[seed], g1))
               < 0.7 * np.linalg.norm(g1) * np.linalg.norm(pixels[j] - pixels[seed])), None)
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
    """The pixels around one imaged dot.

    Attributes:
        uv: Pixel centres (P, 2).
        values: Grey values (P,).
        r_mm: Distance of each pixel's board point from the dot centre (P,), mm.
        outer_mm: The window radius (mm).
        background: Background grey level.
        mm_per_px: Board mm per image pixel at the dot.
    """

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
    (refitted after each pass). With ``debias`` the perspective bias is
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
    "centroid_debiased": lambda image, target, pixels, colour: _refine_centroid(image, target, pixels, colour,
                                                                                debias=True),
}
CIRCLE_DEFAULT_METHOD = "centroid_debiased"

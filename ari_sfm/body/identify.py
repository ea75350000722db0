"""Which dot is which body point: from a few clicked points, as OpenPTV's ``sortgrid`` does, iterated.

Start: a camera fitted to the clicked points (:func:`ari_sfm.body.camera.resection_starts`). Then, until
the matched set no longer changes:

1. project every body point; the search radius is ``tolerance_fraction`` x the median distance between
   neighbouring projected points (or ``tolerance_px``);
2. a point with exactly one dot within the radius proposes that dot; a point with two or more is
   **ambiguous**; a dot proposed by two points is ambiguous for both: they are left out, never guessed;
3. the camera is refitted to the proposals (robust loss; more parameters as more points match:
   :data:`ari_sfm.body.camera.STAGES`), and proposals farther from it than the radius are dropped.

Last, the proposals are held to the refined camera: a dot farther than ``max(reject_px, reject_sigma x
sigma)`` from its point's projection (sigma: the robust scatter of all matches) is **off the model** and
left out, and the camera refitted without it. Every start (a few coplanar clicks leave a mirror pose
nearly as good) is grown; the one matching the most points wins. Its clicked points must lie within the
radius of their final projections, and each half of its points must predict the other
(:func:`split_prediction`): else the clicks do not fit the body (a wrong id or a mistyped pixel) and
:class:`ClickError` says so.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .camera import FOCAL, POSE, BodyWindow, MatchCamera, fit_camera, free_parameters, resection_starts, rms_px

log = logging.getLogger(__name__)

RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))  # median of |2-D Gaussian residual| / sigma per axis
GROW_SPACINGS = 3.5  # each round looks this many body spacings (median nearest-neighbour distance) beyond the
# matched and clicked points; when nothing new is matched, twice as far
SPLIT_MIN_POINTS = 6  # a half of the identified points with fewer is not used to predict the other
CLICK_LIMIT_FRACTION = 1.0  # a clicked point farther than this x the search radius from its final projection: refused
# (test_cavity's clicks are up to 10 px off their dots)


class ClickError(ValueError):
    """The clicked points do not fit the body (the message says which and by how much)."""


@dataclass(frozen=True)
class IdentifyOptions:
    """How dots are matched to body points."""

    tolerance_fraction: float = 0.3  # search radius / median spacing of the projected body points
    tolerance_px: float | None = None  # or this search radius (px)
    reject_px: float = 3.0  # a final match farther than max(this, reject_sigma x sigma) from the model is left out
    reject_sigma: float = 4.0
    max_iterations: int = 60
    starts: int = 6  # starts grown (the best distinct clicked-point fits)
    max_click_rms_fraction: float = 0.5  # clicks fitting worse than this x the spacing (RMS) are refused
    min_click_spread: float = 0.5  # clicks spanning less of the body (:func:`click_spread`) are refused
    max_split_fraction: float = 0.75  # halves of the identification predicting each other worse (x the radius): refused


@dataclass(frozen=True)
class BodyMatch:
    """Identified body points in one image.

    Attributes:
        ids: Body point ids (N,).
        pixels: The matched dots' centres (N, 2), OpenCV pixels.
        dot_indices: The matched dots' rows (N,) in the dots given.
        camera: The fitted camera.
        rms_px: The camera's RMS on the matches (px).
        visible: Number of body points the camera projects into the image.
        ambiguous: Ids left out because more than one dot (or point) competed.
        off_model: Ids left out because their dot is too far from the refined camera's projection.
        tolerance_px: The search radius (px).
        iterations: Rounds of the iteration.
        start_rms_px: The start's RMS on the clicks (px).
    """

    ids: np.ndarray
    pixels: np.ndarray
    dot_indices: np.ndarray  # (N,) the matched dots' rows in the dots given
    camera: MatchCamera
    rms_px: float
    visible: int
    ambiguous: tuple[int, ...] = ()
    off_model: tuple[int, ...] = ()
    tolerance_px: float = 0.0
    iterations: int = 0
    start_rms_px: float = 0.0  # the start's RMS on the clicks


def start_cameras(ids: np.ndarray, xyz: np.ndarray, clicks: Mapping[int, tuple[float, float]],
                  image_size: tuple[int, int], focal_px: float | None = None, aspect: float = 1.0,
                  window: BodyWindow | None = None, options: IdentifyOptions = IdentifyOptions()
                  ) -> list[tuple[MatchCamera, float]]:
    """The start cameras fitted to the clicked points (:func:`~ari_sfm.body.camera.resection_starts`).

    Args:
        ids: Body point ids (N,).
        xyz: Body points (N, 3), mm.
        clicks: ``{id: (u, v)}``, >= 4 clicked points (OpenCV pixels).
        image_size: (width, height) px.
        focal_px: A start for the focal length (px), or None.
        aspect: fy / fx.
        window: The window in the body's frame (the exact model), or None (pinhole).
        options: ``min_click_spread`` and ``max_click_rms_fraction`` are read.

    Returns:
        The cameras, best first, each with its RMS on the clicks (px).

    Raises:
        ClickError: The clicks spread too little over the body, or no camera fits them to within
            ``max_click_rms_fraction`` of the body's projected spacing.
    """
    click_ids, click_xyz, click_uv = clicked_points(ids, xyz, clicks)
    spread = click_spread(click_xyz, np.asarray(xyz, float))
    if spread < options.min_click_spread:
        raise ClickError(f"the clicked points (ids {click_ids}) lie close together or nearly on a line (they span "
                         f"{spread:.0%} of the body across its second direction, need {options.min_click_spread:.0%}):"
                         " click points spread over the body, e.g. near its corners")
    starts = resection_starts(click_xyz, click_uv, image_size, focal_px, aspect, window)
    if not starts:
        raise ClickError(f"no camera fits the {len(click_ids)} clicked points (ids {click_ids})")
    spacing = projected_spacing(starts[0][0], np.asarray(xyz, float), image_size)
    if starts[0][1] > options.max_click_rms_fraction * spacing:
        raise ClickError(f"the clicked points (ids {click_ids}) do not fit the body: {starts[0][1]:.1f} px RMS "
                         f"after a camera fit, the body's points are ~{spacing:.0f} px apart (a wrong id or pixel?)")
    return starts


def click_spread(click_xyz: np.ndarray, xyz: np.ndarray) -> float:
    """How far the clicked points spread over the body.

    Args:
        click_xyz: The clicked body points (K, 3).
        xyz: All body points (N, 3).

    Returns:
        The smaller of the ratios of the clicks' RMS extent to the body's along the body's two main
        directions (principal components); 1: as spread as the whole body.
    """
    def extent(points: np.ndarray) -> np.ndarray:
        centred = points - points.mean(axis=0)
        return np.linalg.svd(centred, compute_uv=False)[:2] / math.sqrt(len(points))

    body = extent(xyz)
    if not np.all(body > 0):
        return 1.0
    centred = click_xyz - click_xyz.mean(axis=0)
    _, _, axes = np.linalg.svd(xyz - xyz.mean(axis=0), full_matrices=False)
    along = np.sqrt(np.mean((centred @ axes[:2].T) ** 2, axis=0))  # the clicks along the body's two axes
    return float(min(along / body))


def clicked_points(ids: np.ndarray, xyz: np.ndarray, clicks: Mapping[int, tuple[float, float]]
                   ) -> tuple[list[int], np.ndarray, np.ndarray]:
    """The clicked points' ids, body points and pixels.

    Args:
        ids: Body point ids (N,).
        xyz: Body points (N, 3).
        clicks: ``{id: (u, v)}``.

    Returns:
        The clicked ids (K), their body points (K, 3) and pixels (K, 2).
    """
    row = {int(i): k for k, i in enumerate(np.asarray(ids, int))}
    click_ids = [int(i) for i in clicks]
    pixels = np.array([clicks[i] for i in click_ids], float).reshape(-1, 2)
    return click_ids, np.asarray(xyz, float)[[row[i] for i in click_ids]], pixels


def identify_body(dots: np.ndarray, ids: np.ndarray, xyz: np.ndarray, clicks: Mapping[int, tuple[float, float]],
                  image_size: tuple[int, int], focal_px: float | None = None, aspect: float = 1.0,
                  window: BodyWindow | None = None, options: IdentifyOptions = IdentifyOptions(),
                  starts: list[tuple[MatchCamera, float]] | None = None) -> BodyMatch:
    """Match the dots of one image to the body points (the iteration of the module docstring).

    Args:
        dots: Dot centres (M, 2), OpenCV pixels.
        ids: Body point ids (N,).
        xyz: Body points (N, 3), mm.
        clicks: ``{id: (u, v)}``, >= 4 clicked points.
        image_size: (width, height) px.
        focal_px: A start for the focal length (px), or None.
        aspect: fy / fx.
        window: The window in the body's frame (the exact model), or None (pinhole).
        options: How dots are matched.
        starts: The start cameras (:func:`start_cameras` of the clicks); None to compute them.

    Returns:
        The identification of the start that matches the most points.

    Raises:
        ClickError: The clicks do not fit the body.
    """
    ids = np.asarray(ids, int)
    xyz = np.asarray(xyz, float)
    if starts is None:
        starts = start_cameras(ids, xyz, clicks, image_size, focal_px, aspect, window, options)
    click_ids, click_xyz, click_uv = clicked_points(ids, xyz, clicks)
    row = {int(i): k for k, i in enumerate(ids)}
    clicked_rows = [row[i] for i in click_ids]
    dots = np.asarray(dots, float).reshape(-1, 2)
    tree = cKDTree(dots) if len(dots) else None
    best: BodyMatch | None = None
    for camera, start_rms in starts[: options.starts]:
        match = _grow(camera, dots, tree, ids, xyz, image_size, options, clicked_rows)
        match = replace(match, start_rms_px=start_rms)
        log.debug("start at %.2f px RMS on the clicks: %d points matched (%.2f px RMS)", start_rms, len(match.ids),
                  match.rms_px)
        if best is None or (len(match.ids), -match.rms_px) > (len(best.ids), -best.rms_px):
            best = match
    if best is None:
        raise ValueError("no start to grow from (options.starts < 1 or no resection of the clicks)")
    _check_clicks(best, click_ids, click_xyz, click_uv)
    _check_rigid(best, ids, xyz, image_size, options)
    return best


def projected_spacing(camera: MatchCamera, xyz: np.ndarray, image_size: tuple[int, int]) -> float:
    """The body's spacing in the image.

    Args:
        camera: The camera.
        xyz: Body points (N, 3).
        image_size: (width, height) px.

    Returns:
        The median distance (px) from each projected body point in the image to its nearest projected
        neighbour (the image's longer side if fewer than two project into it).
    """
    uv = camera.project(xyz)
    uv = uv[_in_image(uv, image_size)]
    if len(uv) < 2:
        return float(max(image_size))
    d, _ = cKDTree(uv).query(uv, k=2)
    return float(np.median(d[:, 1]))


def _in_image(uv: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    w, h = image_size
    with np.errstate(invalid="ignore"):
        return np.isfinite(uv).all(axis=1) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (
            uv[:, 1] <= h - 0.5)


def _propose(camera: MatchCamera, dots: np.ndarray, tree: cKDTree | None, xyz: np.ndarray,
             image_size: tuple[int, int], radius: float, allowed: np.ndarray) -> tuple[dict[int, int], set[int], int]:
    """{row: dot} of the ``allowed`` points with exactly one dot within ``radius`` (a dot proposed twice:
    neither); the rows left out as ambiguous; the number of points projected into the image."""
    uv = camera.project(xyz)
    in_image = _in_image(uv, image_size)
    inside = np.nonzero(in_image & allowed)[0]
    proposals: dict[int, int] = {}
    ambiguous: set[int] = set()
    if tree is None or not len(inside):
        return proposals, ambiguous, int(in_image.sum())
    for row, hits in zip(inside, tree.query_ball_point(uv[inside], radius)):
        if len(hits) == 1:
            proposals[int(row)] = int(hits[0])
        elif len(hits) > 1:
            ambiguous.add(int(row))
    claimed: dict[int, list[int]] = {}
    for k, dot in proposals.items():
        claimed.setdefault(dot, []).append(k)
    for rows in claimed.values():
        if len(rows) > 1:
            ambiguous.update(rows)
            for k in rows:
                del proposals[k]
    return proposals, ambiguous, int(in_image.sum())


def _fit(camera: MatchCamera, rows: list[int], dots: np.ndarray, proposals: dict[int, int], xyz: np.ndarray,
         image_size: tuple[int, int], robust_px: float | None, prior: MatchCamera) -> MatchCamera:
    if len(rows) < 4:
        return camera
    return fit_camera(camera, xyz[rows], dots[[proposals[k] for k in rows]], free_parameters(len(rows)),
                      image_size, robust_px, prior)


def _distances(camera: MatchCamera, rows: list[int], dots: np.ndarray, proposals: dict[int, int],
               xyz: np.ndarray) -> np.ndarray:
    d = np.linalg.norm(camera.project(xyz[rows]) - dots[[proposals[k] for k in rows]], axis=1)
    return np.where(np.isfinite(d), d, np.inf)


def _grow(camera: MatchCamera, dots: np.ndarray, tree: cKDTree | None, ids: np.ndarray, xyz: np.ndarray,
          image_size: tuple[int, int], options: IdentifyOptions, clicked: list[int]) -> BodyMatch:
    """The sortgrid iteration of the module docstring from one start, grown outward from the clicked rows."""
    start = camera  # the weak priors hold the focal length, principal point and k1 to the start's
    matched: dict[int, int] = {}
    ambiguous: set[int] = set()
    visible, radius, iterations = 0, 0.0, 0
    step = float(np.median(cKDTree(xyz).query(xyz, k=2)[0][:, 1])) if len(xyz) > 1 else 1.0
    reach = GROW_SPACINGS * step
    for iterations in range(1, options.max_iterations + 1):  # noqa: B007 (the count is reported)
        support = xyz[sorted(set(clicked) | set(matched))]
        allowed = cKDTree(support).query(xyz)[0] <= reach
        radius = options.tolerance_px or options.tolerance_fraction * projected_spacing(camera, xyz, image_size)
        proposals, ambiguous, visible = _propose(camera, dots, tree, xyz, image_size, radius, allowed)
        rows = sorted(proposals)
        camera = _fit(camera, rows, dots, proposals, xyz, image_size, max(options.reject_px, 0.1 * radius), start)
        near = [k for k, d in zip(rows, _distances(camera, rows, dots, proposals, xyz)) if d <= radius]
        kept = {k: proposals[k] for k in near}
        if kept == matched:
            if allowed.all():
                break
            reach *= 2.0  # nothing new within reach (a band of the body hidden?): look farther
        matched = kept
    # hold the matches to the refined camera: drop those off the model, refit, until none is dropped
    off_model: set[int] = set()
    rows = sorted(matched)
    while len(rows) >= 4:
        camera = _fit(camera, rows, dots, matched, xyz, image_size, None, start)
        d = _distances(camera, rows, dots, matched, xyz)
        sigma = float(np.median(d)) / RAYLEIGH_MEDIAN
        limit = max(options.reject_px, options.reject_sigma * sigma)
        worst = int(np.argmax(d))
        if d[worst] <= limit:
            break
        off_model.add(rows[worst])  # one at a time: a wrong match pulls its neighbours' residuals up too
        rows = rows[:worst] + rows[worst + 1:]
    pixels = dots[[matched[k] for k in rows]].reshape(-1, 2)
    rms = rms_px(camera, xyz[rows], pixels) if rows else float("nan")
    return BodyMatch(ids=ids[rows], pixels=pixels, dot_indices=np.array([matched[k] for k in rows], int),
                     camera=camera, rms_px=rms, visible=visible,
                     ambiguous=tuple(sorted(int(ids[k]) for k in ambiguous)),
                     off_model=tuple(sorted(int(ids[k]) for k in off_model)), tolerance_px=radius,
                     iterations=iterations)


def unexplained_dots(match: BodyMatch, dots: np.ndarray, xyz: np.ndarray, margin_px: float = 2.0
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Which dots lie among the identified ones, and which of those no body point explains.

    With the right ids, only stray dots are unexplained.

    Args:
        match: The identification.
        dots: Dot centres (M, 2).
        xyz: All body points (N, 3).
        margin_px: A dot within this distance of the identified points' convex hull is among them.

    Returns:
        Two (M,) bool arrays: the dots among the identified ones, and those of them with no body point
        projected within the search radius.
    """
    dots = np.asarray(dots, float).reshape(-1, 2)
    inside = np.zeros(len(dots), bool)
    if len(match.ids) >= 3 and len(dots):
        hull = cv2.convexHull(match.pixels.astype(np.float32))
        inside = np.array([cv2.pointPolygonTest(hull, (float(u), float(v)), True) >= -margin_px for u, v in dots])
    uv = match.camera.project(xyz)
    uv = uv[np.isfinite(uv).all(axis=1)]
    near = np.zeros(len(dots), bool)
    if len(uv) and len(dots):
        near = cKDTree(uv).query(dots)[0] <= match.tolerance_px
    return inside, inside & ~near


def split_prediction(match: BodyMatch, ids: np.ndarray, xyz: np.ndarray, image_size: tuple[int, int]) -> float:
    """How well each half of the identified points predicts the other.

    The identified points are split at the median along each of the body's two main directions; a plain
    camera (the identified one's pose and focal length refitted, its principal point at the image centre,
    no k1) fitted to one half projects the other. Halves of fewer than SPLIT_MIN_POINTS are skipped.

    Args:
        match: The identification.
        ids: All body point ids (N,).
        xyz: All body points (N, 3).
        image_size: (width, height) px.

    Returns:
        The worst half's median distance (px) from its projected points to their dots.
    """
    row = {int(i): k for k, i in enumerate(ids)}
    X, uv = xyz[[row[int(i)] for i in match.ids]].reshape(-1, 3), match.pixels
    params = match.camera.params.copy()
    params[7:10] = [(image_size[0] - 1) / 2.0, (image_size[1] - 1) / 2.0, 0.0]
    plain = replace(match.camera, params=params)
    centred = X - X.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    worst = 0.0
    for axis in axes[:2]:
        along = centred @ axis
        for half in (along <= np.median(along), along > np.median(along)):
            if half.sum() < SPLIT_MIN_POINTS or (~half).sum() < SPLIT_MIN_POINTS:
                continue
            camera = fit_camera(plain, X[half], uv[half], POSE + FOCAL, image_size)
            d = np.linalg.norm(camera.project(X[~half]) - uv[~half], axis=1)
            worst = max(worst, float(np.median(np.where(np.isfinite(d), d, np.inf))))
    return worst


def _check_rigid(match: BodyMatch, ids: np.ndarray, xyz: np.ndarray, image_size: tuple[int, int],
                 options: IdentifyOptions) -> None:
    """ClickError when one half of the identified points does not predict the other (:func:`split_prediction`
    beyond ``max_split_fraction`` x the search radius)."""
    miss = split_prediction(match, ids, xyz, image_size)
    if miss > options.max_split_fraction * match.tolerance_px:
        raise ClickError(f"the {len(match.ids)} points identified from the clicked points are not one rigid body: "
                         f"each half predicts the other only to {miss:.1f} px (a wrong id among the clicks?)")


def _check_clicks(match: BodyMatch, click_ids: list[int], click_xyz: np.ndarray, click_uv: np.ndarray) -> None:
    """ClickError naming the clicked point farthest from the identified camera's projection of it, if beyond
    CLICK_LIMIT_FRACTION x the search radius (clicks are rough, to a few pixels; the camera is not)."""
    d = np.linalg.norm(match.camera.project(click_xyz) - click_uv, axis=1)
    d = np.where(np.isfinite(d), d, np.inf)
    worst = int(np.argmax(d))
    if d[worst] > CLICK_LIMIT_FRACTION * match.tolerance_px:
        u, v = click_uv[worst]
        raise ClickError(f"clicked point {click_ids[worst]} at ({u:.1f}, {v:.1f}) is {d[worst]:.1f} px from where "
                         f"the body's {len(match.ids)} identified points put it (a wrong id or pixel?)")

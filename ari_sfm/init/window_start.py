"""Starting values of the window for the exact model when the paraxial stage cannot give them.

- The distance under water (:func:`search_distance`): the ari stage can put the
  window metres away (its medium term is weak), and an exact model started
  there has corners on the camera side of the window. The distance from camera 0
  is searched inside the interval where every camera is in front of the near face
  and every corner beyond the far face, scored by the exact cost. The ari
  stage's targets sit where its own window puts them: behind water the paraxial
  apparent depth along N is ``h + t/n_g + (z - h - t)/n_m``, so moving the window
  from h0 to h with the images kept moves every target by ``(n_m - 1)(h0 - h)``
  along N (:func:`moved_window`; 360 mm on binocular_underwater_oblique seed 1,
  whose ari stage ends at 1090 mm with targets 15-180 mm from the cameras, so
  that no distance separates cameras and held targets). When the held targets
  leave no valid distance, the interval and the candidates move them with the
  window (:func:`distance_interval` with ``medium_index``); otherwise they are
  held (a moved start from a far-off normal can lead the normal search astray:
  the 2400 mm hint on seed 0).
- The normal without stacking (:func:`search_normal`): the exact model observes
  it through refraction alone; a coarse-to-fine search over a grid of tilt
  directions, each scored by the exact cost after a short refit of everything
  else (on a subset of the corners), picks the start.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import numpy as np

from ..geometry import unit
from ..records import Observation, Target

log = logging.getLogger(__name__)

TILTS_DEG = (4.0, 8.0, 12.0, 18.0)  # coarse tilt rings of the normal search (plus the start itself)
AZIMUTHS = 8  # directions per ring


def not_beyond(state, observations: Sequence[Observation], target: Target, thickness_mm: float, window: int = 0,
               cameras: Sequence[str] | None = None) -> tuple[str, str | None] | None:
    """The first (camera, frame) that window ``window`` (its plane ``state.offset(window)``) does not separate.

    A camera not in front of its near face (frame None), or a corner of that camera's view of the frame not
    beyond its far face (the exact model has no ray there).

    Args:
        state: the rig's state (its window, cameras and target poses).
        observations: the corners.
        target: the target (its points).
        thickness_mm: the plate's thickness.
        window: the window's index.
        cameras: the cameras behind it (None: all).

    Returns:
        The (camera, frame or None), or None when all are fine.
    """
    from .zhang import object_points

    n, h = np.asarray(state.normal(window), float), float(state.offset(window))
    mine = set(state.cam_from_world if cameras is None else cameras)
    for name, pose in state.cam_from_world.items():
        if name in mine and not h > n @ pose.inverse().t:
            return name, None
    views = [o for o in observations if o.set in ("calibration", "stacking") and o.frame in state.world_from_target
             and o.camera in state.cam_from_world and o.camera in mine]
    added: dict[str, float] = {}
    for o in views:
        added[o.frame] = max(added.get(o.frame, 0.0), (o.added_mm or 0.0) if o.set == "stacking" else 0.0)
    _, all_points = target.points_3d_readonly
    # fast path: every point of the target beyond the thickest plate of the frame
    doubtful = {f for f, a in added.items()
                if not (state.world_from_target[f].apply(all_points) @ n).min() > h + thickness_mm + a}
    for o in views:
        if o.frame not in doubtful:
            continue
        a = (o.added_mm or 0.0) if o.set == "stacking" else 0.0
        if not (state.world_from_target[o.frame].apply(object_points(target, o.ids)) @ n).min() > h + thickness_mm + a:
            return o.camera, o.frame
    return None


def target_shift_mm(medium_index: float, from_mm: float, to_mm: float) -> float:
    """How far the targets move when the window moves with their paraxial apparent depths kept.

    ``(n_m - 1)(from - to)`` (module docstring; 0 in air, where the distance is unobservable).

    Args:
        medium_index: n_m.
        from_mm: the window's distance before.
        to_mm: its distance after.

    Returns:
        The shift in mm along the normal, away from the cameras.
    """
    return (float(medium_index) - 1.0) * (float(from_mm) - float(to_mm))


def moved_window(state, distance_mm: float, medium_index: float, window: int = 0):
    """``state`` with window ``window`` at ``distance_mm``, every target keeping its paraxial apparent depth.

    Every target (frames and stacking poses) is moved along the normal (:func:`target_shift_mm`); a state
    without a distance only gets the distance.

    Args:
        state: the rig's state.
        distance_mm: the window's new plane offset.
        medium_index: n_m (1: the targets stay).
        window: the window's index.

    Returns:
        The moved state.
    """
    from dataclasses import replace

    from ..geometry import Pose

    h0 = state.offset(window)
    if h0 is None or not np.isfinite(h0):
        return state.with_window(window, offset=float(distance_mm))
    step = target_shift_mm(medium_index, h0, distance_mm) * np.asarray(state.normal(window), float)
    frames = {f: Pose(p.R, p.t + step) for f, p in state.world_from_target.items()}
    return replace(state, world_from_target=frames).with_window(window, offset=float(distance_mm))


def distance_interval(state, observations: Sequence[Observation], target: Target, thickness_mm: float,
                      medium_index: float | None = None, window: int = 0, cameras: Sequence[str] | None = None
                      ) -> tuple[float, float]:
    """The interval of window ``window``'s plane offset h (from camera 0 along its normal) that separates.

    Every camera in front of it (h > n . C) and every corner they observe beyond the far face
    (h < n . X - thickness - added).

    Args:
        state: the rig's state.
        observations: the corners.
        target: the target (its points).
        thickness_mm: the plate's thickness.
        medium_index: the targets move with the window (:func:`moved_window` from its offset), so a corner at
            depth z is beyond it while ``h < (z - thickness - added + (n_m - 1) h0) / n_m``; None: they stay.
        window: the window's index.
        cameras: the cameras behind it (None: all).

    Returns:
        (lo, hi); hi <= lo when no distance fits.
    """
    from .zhang import object_points

    n = np.asarray(state.normal(window), float)
    mine = set(state.cam_from_world if cameras is None else cameras)
    lo = max(float(n @ p.inverse().t) for name, p in state.cam_from_world.items() if name in mine)
    h_now = state.offset(window)
    if medium_index is not None and h_now is not None and np.isfinite(h_now):
        n_m, h0 = float(medium_index), float(h_now)
    else:
        n_m, h0 = 1.0, 0.0
    hi = np.inf
    for o in observations:
        pose = state.world_from_target.get(o.frame)
        if pose is None or o.set not in ("calibration", "stacking") or o.camera not in mine:
            continue
        added = (o.added_mm or 0.0) if o.set == "stacking" else 0.0
        depth = pose.apply(object_points(target, o.ids)) @ n
        hi = min(hi, (float(depth.min()) - thickness_mm - added + (n_m - 1.0) * h0) / n_m)
    return lo, hi


def search_distance(cost: Callable[[float], float], lo: float, hi: float, samples: int = 48,
                    current: float | None = None, refine: bool = True) -> float:
    """The distance in (lo, hi) of least ``cost``.

    A grid of ``samples`` interior points (and ``current`` when inside), then (``refine``) a bounded 1-D
    minimisation between the best point's neighbours.

    Args:
        cost: the cost of a distance.
        lo: the interval's lower end.
        hi: its upper end.
        samples: interior grid points.
        current: the current distance, scored too when inside.
        refine: whether to refine the grid's best.

    Returns:
        The distance.
    """
    from scipy.optimize import minimize_scalar

    grid = lo + (hi - lo) * np.arange(1, samples + 1) / (samples + 1)
    if current is not None and lo < current < hi:
        grid = np.sort(np.append(grid, current))
        samples += 1
    costs = np.array([cost(float(h)) for h in grid])
    if not np.isfinite(costs).any():
        return float(grid[0])
    k = int(np.nanargmin(np.where(np.isfinite(costs), costs, np.nan)))
    if not refine:
        return float(grid[k])
    a = grid[k - 1] if k > 0 else lo + 0.5 * (grid[0] - lo)
    b = grid[k + 1] if k + 1 < samples else hi - 0.5 * (hi - grid[-1])
    res = minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": 1e-3 * (b - a)})
    best = float(res.x) if np.isfinite(res.fun) and res.fun <= costs[k] else float(grid[k])
    log.debug("window distance start %.2f mm (searched %.1f..%.1f mm)", best, lo, hi)
    return best


def tilt_candidates(axis: np.ndarray, tilts_deg: Sequence[float] = TILTS_DEG, azimuths: int = AZIMUTHS
                    ) -> list[np.ndarray]:
    """``axis`` and, for each tilt, ``azimuths`` directions turned that far from it.

    Args:
        axis: the start normal.
        tilts_deg: the rings' tilts.
        azimuths: directions per ring.

    Returns:
        The unit directions: the axis first, then ring by ring.
    """
    axis = unit(np.asarray(axis, float))
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = unit(helper - (helper @ axis) * axis)
    e2 = np.cross(axis, e1)
    out = [axis]
    for t in np.radians(tilts_deg):
        for a in 2 * np.pi * np.arange(azimuths) / azimuths:
            out.append(unit(np.cos(t) * axis + np.sin(t) * (np.cos(a) * e1 + np.sin(a) * e2)))
    return out


def _grid_neighbours(k: int, rings: int, azimuths: int) -> list[int]:
    """Indices of the candidates next to candidate ``k`` of :func:`tilt_candidates`' grid: the axis
    (0) borders the first ring; ring i, azimuth j (1 + i * azimuths + j) borders azimuths j +- 1 of
    its ring and j - 1, j, j + 1 of the rings beside it."""
    if k == 0:
        return list(range(1, 1 + azimuths))
    i, j = divmod(k - 1, azimuths)
    out = [0] if i == 0 else []
    for di in (-1, 0, 1):
        if 0 <= i + di < rings:
            out += [1 + (i + di) * azimuths + (j + dj) % azimuths for dj in (-1, 0, 1) if (di, dj) != (0, 0)]
    return out


def search_normal(score: Callable[[np.ndarray], float], axis: np.ndarray,
                  tilts_deg: Sequence[float] = TILTS_DEG, azimuths: int = AZIMUTHS) -> np.ndarray:
    """The candidate normal (:func:`tilt_candidates`) of least ``score``, coarse to fine.

    Every other azimuth of each ring first, then a descent over the grid (the best's unscored neighbours,
    until the best has no better neighbour). On a landscape with one minimum over the grid this is the whole
    grid's best, from about two thirds of the scores.

    Args:
        score: the score of a normal (not finite: the worst).
        axis: the start normal.
        tilts_deg: the rings' tilts.
        azimuths: directions per ring.

    Returns:
        The best normal.
    """
    candidates = tilt_candidates(axis, tilts_deg, azimuths)
    rings = len(tilts_deg)
    scores: dict[int, float] = {}

    def scored(ks) -> None:
        for k in ks:
            if k not in scores:
                v = score(candidates[k])
                scores[k] = v if np.isfinite(v) else np.inf

    scored([0] + [1 + i * azimuths + j for i in range(rings) for j in range(0, azimuths, 2)])
    best = min(scores, key=lambda k: (scores[k], k))
    while True:
        scored(_grid_neighbours(best, rings, azimuths))
        new = min(scores, key=lambda k: (scores[k], k))
        if new == best:
            break
        best = new
    log.info("normal start: %.1f deg from the axis (coarse-to-fine search, %d of %d directions scored)",
             np.degrees(np.arccos(np.clip(candidates[best] @ unit(axis), -1, 1))), len(scores), len(candidates))
    return candidates[best]

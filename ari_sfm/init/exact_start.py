"""The exact stage's start: each window's distance and, where nothing observes it, its normal.

Each window's distance in front of its cameras is searched by the exact cost under water; a window
nothing observes gets its normal from a coarse search (the search grids and intervals:
:mod:`ari_sfm.init.window_start`). Also the check that every window lies between its cameras and
their corners.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from ..errors import AriSfmError
from ..records import Dataset, Observation, WindowPlane
from .window_start import distance_interval, moved_window, not_beyond, search_distance, search_normal, target_shift_mm

log = logging.getLogger(__name__)

NORMAL_SEARCH_DISTANCES = 8  # distances sampled for each candidate (under water; its LM refines the best)
# LM iterations refitting K and poses for each candidate normal (5 misranks a far-off ari start)
NORMAL_SEARCH_ITERATIONS = 10
NORMAL_SEARCH_FRAMES = 12  # frames (those seen by most cameras, every camera covered) scoring the candidates
NORMAL_SEARCH_CORNERS = 160  # corners per view scoring the candidates (a larger view: an even random subset)


def _observations(dataset: Dataset) -> tuple[Observation, ...]:
    """The dataset's observations (calibrate gives them before any start)."""
    assert dataset.observations is not None
    return dataset.observations


def window_cameras(dataset: Dataset, window: int) -> tuple[str, ...] | None:
    """Give the cameras behind a window.

    Args:
        dataset: the dataset.
        window: the window's index in the dataset's window order.

    Returns:
        The camera names, or None (every camera) when the rig has one window.
    """
    return dataset.window_list()[window].cameras if dataset.windows else None


def hold_normal(rg, normal: np.ndarray, window: int = 0) -> None:
    """Hold a window's normal with a prior of 1e-7 rad.

    Args:
        rg: the rig's graph (:class:`~ari_sfm.factors.rig_graph.RigGraph`); the prior is added to it.
        normal: the normal to hold (3,), world frame.
        window: the window's index (default the only one).
    """
    import gtsam

    from ..factors import keys as K_

    rg.add_factor(gtsam.PriorFactorUnit3(K_.window_normal(window), gtsam.Unit3(np.asarray(normal, float)),
                                         gtsam.noiseModel.Isotropic.Sigma(2, 1e-7)))


def hold_normals(rg, state, windows: Sequence[int]) -> None:
    """Hold the normals of some windows where the state has them (see :func:`hold_normal`).

    Args:
        rg: the rig's graph (:class:`~ari_sfm.factors.rig_graph.RigGraph`); the priors are added to it.
        state: the rig's state, giving each window's normal.
        windows: the windows' indices.
    """
    for w in windows:
        hold_normal(rg, state.normal(w), w)


def exact_start(dataset: Dataset, state, underwater: bool, planes: Sequence, unobserved: Sequence[int], build, solve,
                huber_px: float | None):
    """Give the exact stage's start from the ari result, window by window.

    In air each window gets a distance in front of its cameras (any will do); under water a distance
    searched inside the valid interval (the ari stage's can be far off). A window without stacking or
    declared plane (``unobserved``) gets its normal from a coarse search scored by the exact cost (the
    other windows held where they are).

    Args:
        dataset: the dataset (its observations loaded).
        state: the rig's state after the ari stage.
        underwater: whether the window distance is estimated (a medium other than air).
        planes: per window, its declared plane for this stage, or None.
        unobserved: the indices of the windows whose normal nothing observes.
        build: ``build(model, state, with_plane=..., observations=...)`` -> the stage's rig graph.
        solve: ``solve(rig_graph, model, max_iterations)`` -> (state, solved problem or None).
        huber_px: the Huber threshold (px), or None.

    Returns:
        The state to start the exact stage from.

    Raises:
        AriSfmError: if no window distance puts every camera in front of a window and every corner beyond it.
    """
    from ..factors.rig_graph import default_distance_mm

    def build_free(stage: str, st, observations=None):  # the searches below run only without a declared plane
        return build(stage, st, with_plane=False, observations=observations)

    for w in range(state.window_count):
        if not underwater:
            if state.offset(w) is None:
                state = state.with_window(w, offset=default_distance_mm(state.normal(w), state.cam_from_world,
                                                                        window_cameras(dataset, w)))
        elif planes[w] is None:  # the ari stage's distance (or the hint) is one candidate
            state = _searched_distance(dataset, state, build_free, huber_px, window=w)
    for w in unobserved:
        state = _searched_normal(dataset, state, w, underwater, planes[w], build_free, solve, huber_px)
    return state


def _searched_normal(dataset: Dataset, state, w: int, underwater: bool, plane, build_free, solve,
                     huber_px: float | None):
    """``state`` with window ``w``'s normal from the coarse search (:func:`exact_start`), then its distance."""
    from ..factors.rig_graph import default_distance_mm

    frames = _search_frames(dataset, state, NORMAL_SEARCH_FRAMES)
    subset = replace(state, world_from_target={f: state.world_from_target[f] for f in frames})
    scoring = _search_corners(_observations(dataset), frames, NORMAL_SEARCH_CORNERS)
    cameras = window_cameras(dataset, w)

    def build_scoring(stage: str, st):
        return build_free(stage, st, scoring)

    def score(normal: np.ndarray) -> float:
        st = subset.with_window(w, normal)
        if underwater:
            try:
                st = _searched_distance(dataset, st, build_scoring, huber_px, NORMAL_SEARCH_DISTANCES, scoring,
                                        refine=False, window=w)
            except AriSfmError:  # no window separates cameras and corners along this candidate: not a start
                return np.inf
        elif plane is None:
            st = st.with_window(w, offset=default_distance_mm(normal, st.cam_from_world, cameras))
        rg = build_scoring("exact", st)
        hold_normal(rg, normal, w)
        try:
            _, solved = solve(rg, "exact", NORMAL_SEARCH_ITERATIONS)
        except AriSfmError:
            return np.inf
        return solved.error() if solved is not None else rg.graph.error(rg.values)

    normal = search_normal(score, state.normal(w))
    state = state.with_window(w, normal)
    if underwater:
        state = _searched_distance(dataset, state, build_free, huber_px, window=w)
    elif plane is None:
        state = state.with_window(w, offset=default_distance_mm(normal, state.cam_from_world, cameras))
    return state


def _search_corners(observations: Sequence[Observation], frames: Sequence[str], per_view: int
                    ) -> tuple[Observation, ...]:
    """The calibration/stacking views of ``frames``, each cut to at most ``per_view`` corners (a fixed
    random subset, the same on every run): the candidates' scores need the refraction's pattern over
    the view, not every corner of a 1600-point body."""
    keep = set(frames)
    out = []
    for o in observations:
        if o.frame not in keep or o.set not in ("calibration", "stacking"):
            continue
        if len(o.ids) > per_view:
            idx = np.sort(np.random.default_rng(len(o.ids)).choice(len(o.ids), per_view, replace=False))
            o = replace(o, ids=o.ids[idx], pixels=o.pixels[idx])
        out.append(o)
    return tuple(out)


def _search_frames(dataset: Dataset, state, count: int) -> list[str]:
    """Up to ``count`` frames of the state seen by the most cameras, more if needed to cover every camera."""
    cams: dict[str, set[str]] = {}
    for o in _observations(dataset):
        if o.frame in state.world_from_target and o.set in ("calibration", "stacking"):
            cams.setdefault(o.frame, set()).add(o.camera)
    chosen: list[str] = []
    covered: set[str] = set()
    for f in sorted(cams, key=lambda f: (-len(cams[f]), f)):
        if len(chosen) < count or not cams[f] <= covered:
            chosen.append(f)
            covered |= cams[f]
        if len(chosen) >= count and covered >= set(dataset.camera_names):
            break
    return chosen


def _searched_distance(dataset: Dataset, state, build, huber_px: float | None, samples: int = 48,
                       observations: Sequence[Observation] | None = None, refine: bool = True, window: int = 0):
    """state with window ``window``'s distance searched by the exact cost inside the valid interval (under
    water); ``observations``: those ``build`` puts in its graph (default the dataset's); ``refine``: a 1-D
    minimisation after the grid (:func:`~ari_sfm.init.window_start.search_distance`).

    The targets are held where the state has them; when that leaves no valid distance (the ari
    stage's targets sit at the apparent depths of its own, far window), they move with the
    window, keeping those apparent depths (:func:`~ari_sfm.init.window_start.moved_window`; one window only:
    with several, moving the targets would move them for the other windows' cameras too)."""
    from ..factors.vectorized import VectorizedProblem

    observations = _observations(dataset) if observations is None else observations
    iface, cameras = dataset.window_list()[window].interface, window_cameras(dataset, window)
    n_m, t = iface.medium_index, iface.thickness_mm
    moving = None
    lo, hi = distance_interval(state, observations, dataset.target, t, window=window, cameras=cameras)
    if not hi > lo and state.offset(window) is not None and not dataset.windows:
        held = (lo, hi)
        moving = n_m
        lo, hi = distance_interval(state, observations, dataset.target, t, n_m)
        log.info("no window distance separates the cameras from the targets where they are (cameras up to %.1f mm, "
                 "corners from %.1f mm): the targets move with the window at their apparent depths (%.1f-%.1f mm)",
                 *held, lo, hi)
    if not hi > lo:
        name = "the window" if not dataset.windows else f"window {dataset.window_list()[window].name}"
        raise AriSfmError(dataset.rig_path, f"no window distance puts every camera in front of {name} and every "
                                            f"corner beyond it (cameras up to {lo:.1f} mm, corners from {hi:.1f} mm "
                                            "along the normal): check the thickness_mm and the target")
    mid = moved_window(state, 0.5 * (lo + hi), n_m if moving else 1.0, window)
    rg = build("exact", mid)
    problem = VectorizedProblem.from_rig_graph(rg, huber_px=huber_px, check=False)
    x0, normal = problem.x, np.asarray(mid.normal(window), float)

    def cost(h: float) -> float:
        if not moving:
            return problem.error(x0.with_distance(window, h))
        step = target_shift_mm(n_m, mid.offset(window), h) * normal
        return problem.error(x0.with_distance(window, h, x0.world_t_target + step))

    best = search_distance(cost, lo, hi, samples, current=state.offset(window), refine=refine)
    return moved_window(state, best, n_m if moving else 1.0, window)


def check_in_front(dataset: Dataset, state) -> None:
    """Check that every window at the exact stage's start lies between its cameras and every corner they see.

    Args:
        dataset: the dataset (its observations loaded).
        state: the rig's state at the exact stage's start.

    Raises:
        AriSfmError: a one-line error naming the camera and frame, when a window is not in between.
    """
    for w, window in enumerate(dataset.window_list()):
        bad = not_beyond(state, _observations(dataset), dataset.target, window.interface.thickness_mm, w,
                         window_cameras(dataset, w))
        if bad is not None:
            camera, frame = bad
            where = f"camera {camera}" + ("" if frame is None else f" frame {frame}")
            name = "the window" if not dataset.windows else f"window {window.name}"
            what = f"is not in front of {name}" if frame is None else f"a corner is not beyond {name}"
            key = "interface" if not dataset.windows else f"interfaces.{window.name}"
            raise AriSfmError(dataset.observations_path or dataset.rig_path,
                              f"{where}: {what} at the start of the exact stage (distance {state.offset(w):.1f} mm; "
                              f"check {key}.thickness_mm, distance_mm and plane)")


def planes_separate(dataset: Dataset, planes: Sequence[WindowPlane | None], state) -> bool:
    """Whether each declared plane, placed by its frame's pose in ``state``, lies between its cameras and their corners.

    A Snell stage can then start from the plane as placed (calibrate skips the free-window stage before it).

    Args:
        dataset: the dataset (its windows, target and observations).
        planes: each window's declared plane (None where not declared).
        state: the rig's state (its target poses place the planes).

    Returns:
        True when every declared plane separates its cameras from the corners they see.
    """
    from ..factors.window_plane import plane_in_world

    for w, (window, plane) in enumerate(zip(dataset.window_list(), planes)):
        if plane is None:
            continue
        n_w, h_w = plane_in_world(plane, state.world_from_target[plane.frame])
        if not_beyond(state.with_window(w, n_w, h_w), _observations(dataset), dataset.target,
                      window.interface.thickness_mm, w, window_cameras(dataset, w)) is not None:
            return False
    return True

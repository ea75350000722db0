"""refine-colmap's start: the window's distance searched on the cost, or a long chain's sliding start.

The distance search (:func:`distance_search`): for each candidate distance, LM on everything but the window
(the window held; the middle candidate from COLMAP's model, up to SEARCH_ITERATIONS, the others warm-started
from its result, WARM_SEARCH_ITERATIONS, moved to their distance paraxially), on a subset of the points with
about SEARCH_OBSERVATIONS observations; the lowest cost wins. A long chain (:mod:`.chain_start`) starts by
blocks slid outward from the middle instead (:func:`chain_start`). The candidates are those whose window
lies well in front of the scene (:func:`start_candidates`).
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ari_sfm.colmap import adapter
from ari_sfm.errors import AriSfmError, ErrorPath
from ari_sfm.records import Interface

from .chain_start import Block, slid_start
from .paraxial import convert, restart_at, to_scale, with_distance
from .problem import RefractiveProblem, State
from .scale_bar import Baseline, ScaleBar
from .solver import Solver
from .steps import BlockStep, SearchStep

log = logging.getLogger(__name__)

DISTANCE_CANDIDATES_MM = (10.0, 30.0, 100.0)
SEARCH_ITERATIONS = 10  # the first start distance, window held (LM stops earlier when converged)
WARM_SEARCH_ITERATIONS = 4  # the other start distances, warm-started
SEARCH_RELATIVE_TOLERANCE = 1e-2  # the search's LM stops at a relative decrease below this: it ranks the starts,
#                                   the final refinement converges (28 images: 8 search linearizations instead of 13)
AIR_DISTANCE_MM = 10.0  # held: unobservable in air
SCENE_CLEARANCE = 0.5  # a start distance's window (plus plate) must be nearer than this times the near points
SEARCH_OBSERVATIONS = 6_000  # the distance search runs on a subset of the points with about this many observations


@dataclass(frozen=True)
class Candidate:
    """A start the refinement may take: its cost after the start's solve (0 when not solved), its state."""

    cost: float
    state: State
    iterations: int


@dataclass(frozen=True)
class StartResult:
    """Where the start stage leaves the refinement: the state to refine from, the other starts (the restarts'
    candidates, cheapest first), and the figures of how it got there."""

    state: State
    others: tuple[Candidate, ...]
    search: tuple[SearchStep, ...] = ()  # the distance search's profile (refine.json ``distance_search``)
    blocks: tuple[BlockStep, ...] = ()  # a long chain's blocks


def distance_candidates(interface: Interface, virtual: State, estimate_distance: bool,
                        distances_mm: Sequence[float] | None) -> tuple[float, ...]:
    """The start distances to try.

    Args:
        interface: the plate (a declared plane, or distance_mm, gives the only candidate).
        virtual: the start state (at a declared plane: its distance).
        estimate_distance: whether the distance is estimated (in air it is held at AIR_DISTANCE_MM).
        distances_mm: the candidates given (None: DISTANCE_CANDIDATES_MM).

    Returns:
        The candidates, in the order given.
    """
    if interface.plane is not None:
        return (float(virtual.distances[0]),)
    if interface.distance_mm is not None:
        return (float(interface.distance_mm),)
    if not estimate_distance:
        return (AIR_DISTANCE_MM,)
    return tuple(distances_mm or DISTANCE_CANDIDATES_MM)


def start_candidates(model: adapter.ColmapModel, state: State, interface: Interface,
                     candidates: tuple[float, ...], units_given: bool, declared: bool,
                     path: ErrorPath) -> tuple[float, ...]:
    """The start distances whose window (plus plate) lies well in front of the near points.

    The near points are the 5th percentile of the observations' depths: in COLMAP's arbitrary units read as
    mm a scene can lie inside the port; then one line asks for units_mm or a scale bar.

    Args:
        model: the COLMAP model.
        state: the start state (virtual cameras).
        interface: the plate.
        candidates: the distances (:func:`distance_candidates`).
        units_given: whether the scale was given (the error's remedy).
        declared: a declared plane or distance: its candidate is kept as it is.
        path: the file named in errors.

    Returns:
        The candidates kept.
    """
    R, t = state.cam_from_world(model)
    depth = np.einsum("nj,nj->n", R[model.obs_image, 2, :], state.xyz[model.obs_point]) + t[model.obs_image, 2]
    near = float(np.percentile(depth, 5))
    if not near > 0:
        raise AriSfmError(path, f"most of the COLMAP model's observed points are behind their cameras "
                                f"(5th percentile depth {near:.3g} mm)")
    keep = tuple(h for h in candidates if h + interface.thickness_mm < SCENE_CLEARANCE * near)
    if declared or keep:
        return candidates if declared else keep
    how = ("check units_mm / scale_bar" if units_given else
           "the model is in COLMAP's arbitrary units: give units_mm (mm per model unit) or a scale_bar")
    raise AriSfmError(path, f"the COLMAP model's points are only {near:.3g} mm in front of its cameras (5th "
                            f"percentile, read as mm): a {interface.thickness_mm:g} mm plate {min(candidates):g} mm "
                            f"or more in front of the lens would lie among them; {how}")


def subsample(model: adapter.ColmapModel, bar: ScaleBar | None, max_observations: int
              ) -> tuple[adapter.ColmapModel, np.ndarray, ScaleBar | None]:
    """The model restricted to every k-th point3D (and the scale bar's two), about ``max_observations`` seen.

    Args:
        model: the COLMAP model.
        bar: the scale bar, if any (its points kept).
        max_observations: about how many observations the subset keeps.

    Returns:
        The sub-model, the kept point indices and the bar re-indexed.
    """
    M, P = len(model.obs_point), len(model.point3D_ids)
    if M <= max_observations:
        return model, np.arange(P), bar
    step = int(np.ceil(M / max_observations))
    chosen = np.zeros(P, bool)
    chosen[::step] = True
    if bar is not None:
        chosen[[bar.a, bar.b]] = True
    keep = np.flatnonzero(chosen)
    new_index = np.cumsum(chosen) - 1
    obs = chosen[model.obs_point]
    sub = replace(model, point3D_ids=model.point3D_ids[keep], xyz=model.xyz[keep], obs_image=model.obs_image[obs],
                  obs_point=new_index[model.obs_point[obs]], obs_uv=model.obs_uv[obs])
    sub_bar = None if bar is None else ScaleBar(int(new_index[bar.a]), int(new_index[bar.b]), bar.length_mm)
    return sub, keep, sub_bar


def search_order(candidates: tuple[float, ...]) -> list[float]:
    """The candidates in the order the search tries them: the middle one first, then outward."""
    return sorted(candidates, key=lambda h: abs(candidates.index(h) - (len(candidates) - 1) / 2))


def distance_search(model: adapter.ColmapModel, problem: RefractiveProblem, interface: Interface, mount: str,
                    estimate_distance: bool, huber_px: float | None, bar: ScaleBar | None, virtual: State,
                    candidates: tuple[float, ...], declared: bool, baseline: Baseline | None = None) -> StartResult:
    """The cost profile over the start distance, everything but the window refined (the window held).

    The middle candidate starts from COLMAP's model, the others warm-started from its result (moved to their
    distance, paraxially); the lowest cost wins. When the subset's best poses put some of the other points
    before the window, the best distance runs again on every point.

    Args:
        model: the COLMAP model.
        problem: the whole refractive problem.
        interface: the plate.
        mount: ``camera`` or ``world``.
        estimate_distance: whether the distance is estimated.
        huber_px: the Huber threshold.
        bar: the scale bar term, if any.
        virtual: the virtual cameras' start state (every point).
        candidates: the start distances.
        declared: the window starts at the declared plane (``virtual``'s).
        baseline: the baseline term, if any.

    Returns:
        The best start, the other candidates' ends (cheapest first) and the profile.
    """
    full_xyz, full_model, full_virtual, full_bar = virtual.xyz, model, virtual, bar
    model, keep, bar = subsample(model, bar, SEARCH_OBSERVATIONS)
    virtual = replace(virtual, xyz=virtual.xyz[keep])
    held = Solver(RefractiveProblem(model, interface, mount, estimate_distance, hold_window=True), huber_px, bar=bar,
                  baseline=baseline)
    sub = RefractiveProblem(model, interface, mount, estimate_distance)
    search: list[SearchStep] = []
    best: Candidate | None = None
    others: list[Candidate] = []
    warm = None
    for h in search_order(candidates):
        base = virtual if warm is None else warm
        start = convert(model, sub, base if declared else with_distance(model, base, mount, h), +1)
        res = held.run(start, SEARCH_ITERATIONS if warm is None else WARM_SEARCH_ITERATIONS,
                       relative_tolerance=SEARCH_RELATIVE_TOLERANCE)
        if warm is None:
            warm = convert(model, sub, res.state, -1)
        search.append(SearchStep(h, res.cost, res.iterations, res.linearizations, len(model.obs_point)))
        log.info("refine-colmap: start distance %g mm: cost %.6g after %d iterations with the window held",
                 h, res.cost, res.iterations)
        xyz = full_xyz.copy()
        xyz[keep] = res.state.xyz  # the subsample's points refined, the others at their start
        end = Candidate(res.cost, replace(res.state, xyz=xyz), res.iterations)
        if best is None or res.cost < best.cost:
            if best is not None:
                others.append(best)
            best = end
        else:
            others.append(end)
    if best is None:
        raise ValueError("no start distance to search")
    if len(keep) < len(full_xyz) and not np.all(np.isfinite(problem.residuals(best.state))):
        # the subsample's poses put some of the other points (at their start) before the window: the
        # best distance again, on every point
        held_full = Solver(RefractiveProblem(full_model, interface, mount, estimate_distance, hold_window=True),
                           huber_px, bar=full_bar, baseline=baseline)
        h = search[[c.cost for c in search].index(best.cost)].distance_mm
        start = convert(full_model, problem, full_virtual if declared else
                        with_distance(full_model, full_virtual, mount, h), +1)
        res = held_full.run(start, SEARCH_ITERATIONS)
        search.append(SearchStep(h, res.cost, res.iterations, res.linearizations, len(full_model.obs_point)))
        best = Candidate(res.cost, res.state, res.iterations)
    return StartResult(best.state, tuple(sorted(others, key=lambda o: o.cost)), tuple(search))


def chain_distance(candidates: tuple[float, ...]) -> float:
    """A long chain's start distance: the middle candidate."""
    return candidates[(len(candidates) - 1) // 2] if len(candidates) > 1 else candidates[0]


def chain_start(model: adapter.ColmapModel, problem: RefractiveProblem, interface: Interface, mount: str,
                huber_px: float | None, virtual: State, first: Block, distance_mm: float, declared: bool,
                candidates: tuple[float, ...], bar: ScaleBar | None, baseline: Baseline | None) -> StartResult:
    """A long chain's start: blocks slid outward from ``first`` (:func:`~.chain_start.slid_start`), rescaled.

    Args:
        model: the COLMAP model.
        problem: the whole refractive problem.
        interface: the plate.
        mount: ``camera`` (a chain is of housings).
        huber_px: the Huber threshold.
        virtual: the virtual cameras' start state.
        first: the first block (the frames nearest the middle).
        distance_mm: the distance held while the blocks slide (:func:`chain_distance`).
        declared: the window starts at the declared plane (``virtual``'s) and is held while they slide.
        candidates: the start distances (the others become the restarts' candidates, unsolved).
        bar: the scale bar term, if any: the chain is rescaled to it.
        baseline: the baseline term, if any: likewise.

    Returns:
        The start, the other candidates (cost 0: not solved) and the blocks.
    """
    whole = convert(model, problem, virtual if declared else with_distance(model, virtual, mount, distance_mm), +1)

    def block_solver(m: adapter.ColmapModel, held: np.ndarray | None) -> Solver:
        """The first block (``held`` None): the distance held, the normal free unless declared; a later
        one: its ``held`` frames, the window and the intrinsics held at the first block's (a block
        that fails cannot spoil what the others rely on)."""
        later = held is not None
        return Solver(RefractiveProblem(m, interface, mount, False, hold_window=later or declared,
                                        held_frames=held, hold_intrinsics=later), huber_px)

    start, blocks = slid_start(model, whole, first, block_solver)
    start, _ = to_scale(start, bar, baseline, not declared)
    others = tuple(Candidate(0.0, restart_at(model, problem, start, mount, c), 0) for c in candidates
                   if c != distance_mm and not declared)
    return StartResult(start, others, (), tuple(blocks))

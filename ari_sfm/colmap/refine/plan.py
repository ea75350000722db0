"""refine-colmap's plan: its stages as frozen records (:func:`plan_refinement`, no side effect) and their run
(:func:`run_stage`: each stage takes where the previous ones left the refinement, :class:`Reached`, and
returns it advanced).

The stages, in order: the start (:class:`DistanceSearch`, or :class:`ChainStart` for a long chain); with a
scale bar or a baseline, the refinement without it first (:class:`FreeScale`: the scale's near-flat valley,
then rescaled to it); the refinement (:class:`Refinement`); the other starts refined when the distance ran
toward 0 (:class:`Restarts`, where the distance is estimated and no plane declared); the sigmas
(:class:`Sigmas`); the scale term's check (:class:`ScaleCheck`).
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from ari_sfm.colmap import adapter
from ari_sfm.errors import AriSfmError, ErrorPath
from ari_sfm.records import Interface, WindowPlane

from .chain_start import Block, first_block
from .inputs import Scale
from .options import Backend, Mount, RefineColmapOptions
from .paraxial import to_scale
from .plane import window_prior
from .problem import RefractiveProblem, State
from .report import RefineUncertainty
from .solver import Solver, SolveResult
from .start import StartResult, chain_distance, chain_start, distance_search, search_order
from .steps import RestartStep
from .uncertainty import uncertainty

log = logging.getLogger(__name__)

FREE_SCALE_FIRST = True  # with a scale bar: refine without it, rescale to it, then refine with it held
DISTANCE_COLLAPSE = 0.1  # a refined distance below this fraction of the smallest start candidate "ran to 0"


@dataclass(frozen=True)
class DistanceSearch:
    """The start: the window's distance searched on the cost, the window held (:func:`.start.distance_search`)."""

    name: ClassVar[str] = "distance search"
    candidates: tuple[float, ...]  # as given (tried middle first: ``order``)
    declared: bool  # the window starts at the declared plane

    @property
    def order(self) -> list[float]:
        """The distances in the order they are tried."""
        return search_order(self.candidates)


@dataclass(frozen=True, eq=False)
class ChainStart:
    """The start of a long chain: blocks slid outward from the middle (:func:`.start.chain_start`)."""

    name: ClassVar[str] = "chain start"
    first: Block  # the first block: the frames nearest the middle
    distance_mm: float  # held while the blocks slide
    candidates: tuple[float, ...]  # the others: the restarts' candidates
    declared: bool


@dataclass(frozen=True)
class FreeScale:
    """The refinement without the scale's term (the scale free along its valley), then rescaled to it."""

    name: ClassVar[str] = "free scale"
    held_by: str  # "bar" or "baseline": the term left out, then rescaled to
    max_iterations: int
    backend: Backend


@dataclass(frozen=True)
class Refinement:
    """The refinement of everything the problem estimates, from the start (scale term held, if any)."""

    name: ClassVar[str] = "refinement"
    max_iterations: int
    backend: Backend


@dataclass(frozen=True)
class Restarts:
    """When the refined distance ran toward 0: the other starts refined too, the lowest cost wins."""

    name: ClassVar[str] = "restarts"
    candidates: tuple[float, ...]  # the start distances (the collapse is below DISTANCE_COLLAPSE of the least)


@dataclass(frozen=True)
class Sigmas:
    """The 1-sigma uncertainties at the solution (:func:`.uncertainty.uncertainty`); a distance still at ~0
    after the restarts named weak."""

    name: ClassVar[str] = "uncertainty"
    candidates: tuple[float, ...]


@dataclass(frozen=True)
class ScaleCheck:
    """The scale term's length after the refinement: a scale bar off by more than 1e-3 is a warning, a
    baseline an error (the images pull against it)."""

    name: ClassVar[str] = "scale check"
    held_by: str  # "bar" or "baseline"


RefineStage = DistanceSearch | ChainStart | FreeScale | Refinement | Restarts | Sigmas | ScaleCheck


@dataclass(frozen=True, eq=False)
class Setup:
    """What every stage of one refinement works with: the model, its problem and solver, the start."""

    model: adapter.ColmapModel
    interface: Interface
    options: RefineColmapOptions
    scale: Scale
    problem: RefractiveProblem
    solver: Solver  # the refinement's: the window prior and the scale term
    estimate_distance: bool
    hold_normal: bool
    virtual: State  # the virtual cameras' start (at a declared plane, if any)
    candidates: tuple[float, ...]  # the start distances
    window_path: ErrorPath = "WINDOW.yaml"  # the file named in errors about the start and the scale
    path: ErrorPath = "reconstruction"  # the model named in errors

    @property
    def plane(self) -> WindowPlane | None:
        """The declared window (``interface.plane``), if any."""
        return self.interface.plane


def estimates_distance(interface: Interface) -> bool:
    """Whether the window's distance is estimated: under water, unless a declared plane holds it.

    Args:
        interface: the plate (in air the distance is unobservable) and its declared plane.

    Returns:
        True when it is estimated.
    """
    plane = interface.plane
    return interface.medium_index != 1.0 and not (plane is not None and plane.sigma_mm == 0)


def setup(model: adapter.ColmapModel, interface: Interface, options: RefineColmapOptions, scale: Scale,
          virtual: State, candidates: tuple[float, ...], window_path: ErrorPath = "WINDOW.yaml",
          path: ErrorPath = "reconstruction") -> Setup:
    """The refinement's problem and solver: the distance estimated under water unless a declared plane holds it,
    the normal held when the declared plane holds it.

    Args:
        model: the COLMAP model.
        interface: the plate (and its declared plane, if any).
        options: the options.
        scale: the scale (units, bar, baseline).
        virtual: the virtual cameras' start.
        candidates: the start distances.
        window_path: the file named in errors about the start and the scale.
        path: the model named in errors.

    Returns:
        The setup the stages run with.
    """
    plane = interface.plane
    estimate_distance = estimates_distance(interface)
    hold_normal = plane is not None and plane.sigma_deg == 0
    problem = RefractiveProblem(model, interface, options.mount, estimate_distance,
                                hold_window=hold_normal and not estimate_distance, hold_normal=hold_normal)
    solver = Solver(problem, options.huber_px, window_prior(plane, estimate_distance), scale.bar, scale.baseline)
    return Setup(model, interface, options, scale, problem, solver, estimate_distance, hold_normal, virtual,
                 candidates, window_path, path)


def plan_refinement(s: Setup) -> tuple[RefineStage, ...]:
    """The stages refining ``s``'s model, in order. No side effect.

    A long chain (:func:`.chain_start.first_block`) starts by sliding blocks, anything else by the distance
    search; with a scale bar or a baseline (and no chain, which is rescaled as it starts) the refinement runs
    first without it; the restarts where the distance is estimated and no plane declared.

    Args:
        s: the refinement's setup.

    Returns:
        The stages.
    """
    opts, declared = s.options, s.plane is not None
    first = first_block(s.model, s.virtual, opts.mount)
    stages: list[RefineStage] = []
    if first is not None:
        stages.append(ChainStart(first, chain_distance(s.candidates), s.candidates, declared))
    else:
        stages.append(DistanceSearch(s.candidates, declared))
    held_by = s.scale.held_by
    if held_by is not None and FREE_SCALE_FIRST and first is None:
        stages.append(FreeScale(held_by, opts.max_iterations, opts.backend))
    stages.append(Refinement(opts.max_iterations, opts.backend))
    if s.estimate_distance and not declared:
        stages.append(Restarts(s.candidates))
    stages.append(Sigmas(s.candidates))
    if held_by is not None:
        stages.append(ScaleCheck(held_by))
    return tuple(stages)


SOLVES = (FreeScale, Refinement, Restarts)  # the stages that refine the whole problem


def last_solve(plan: tuple[RefineStage, ...]) -> int:
    """The index of the plan's last stage refining the whole problem (its end is the result)."""
    return max(k for k, stage in enumerate(plan) if isinstance(stage, SOLVES))


Tick = Callable[[int, float], None]  # told each accepted LM step (iteration, cost)
Collapsed = Callable[[State, RefractiveProblem, tuple[float, ...]], bool]


def collapsed(state: State, problem: RefractiveProblem, candidates: tuple[float, ...]) -> bool:
    """Whether the refined window distance ran toward 0 (where the cost is flat the refinement can slide there).

    Args:
        state: the refined state.
        problem: the refractive problem.
        candidates: the start distances.

    Returns:
        True when a window's distance is below DISTANCE_COLLAPSE of the smallest candidate.
    """
    return bool(np.min(problem.image_windows(state)[1]) < DISTANCE_COLLAPSE * min(candidates))


@dataclass(frozen=True)
class Reached:
    """Where the stages have left a refinement: each stage's typed result (None until it ran)."""

    start: StartResult | None = None
    free_scale: SolveResult | None = None  # the refinement without the scale term
    refinement: SolveResult | None = None  # the refinement's own solve
    result: SolveResult | None = None  # the best end: the refinement's, or a restart's with a lower cost
    restarts: tuple[RestartStep, ...] = ()
    collapsed: bool = False  # the distance ran toward 0 (the restarts ran)
    sigmas: RefineUncertainty | None = None
    counted: tuple[int, int] = (0, 0)  # (iterations, linearizations) of the solves counted so far

    @property
    def state(self) -> State:
        """The state the next stage starts from (after the refinement: the best end's)."""
        if self.result is not None:
            return self.result.state
        assert self.start is not None  # the start stage runs first
        return self.start.state

    @property
    def iterations(self) -> int:
        """Accepted LM steps of every solve: the search's, the blocks', the free-scale, the refinement, restarts."""
        start = self.start
        assert start is not None
        return self.counted[0] + sum(c.iterations for c in start.search) + sum(b.iterations for b in start.blocks)

    @property
    def linearizations(self) -> int:
        """Linearizations of every solve but the search's (refine.json counts those apart)."""
        start = self.start
        assert start is not None
        return self.counted[1] + sum(b.linearizations for b in start.blocks)

    def counting(self, res: SolveResult) -> tuple[int, int]:
        """``counted`` with ``res``'s solve added."""
        return self.counted[0] + res.iterations, self.counted[1] + res.linearizations


def _solve(solver: Solver, state: State, stage: FreeScale | Refinement, tick: Tick | None) -> SolveResult:
    """One LM solve with the stage's backend."""
    if stage.backend == Backend.NUMPY:
        return solver.run(state, stage.max_iterations, tick)
    return solver.run_gtsam(state, stage.max_iterations)


def _start(s: Setup, stage: DistanceSearch | ChainStart) -> StartResult:
    """The start stage, checked: every point beyond the window from it."""
    scale, opts = s.scale, s.options
    if isinstance(stage, ChainStart):
        out = chain_start(s.model, s.problem, s.interface, opts.mount, opts.huber_px, s.virtual, stage.first,
                          stage.distance_mm, stage.declared, stage.candidates, scale.bar, scale.baseline)
    else:
        out = distance_search(s.model, s.problem, s.interface, opts.mount, s.estimate_distance, opts.huber_px,
                              scale.bar, s.virtual, stage.candidates, stage.declared, scale.baseline)
    if not np.all(np.isfinite(s.problem.residuals(out.state))):
        raise AriSfmError(s.window_path, "no start puts every point beyond the window (the window is between a "
                                         "camera and points it sees at every candidate distance): check units_mm / "
                                         "scale_bar and the plate")
    return out


def _free_scale(s: Setup, stage: FreeScale, reached: Reached, tick: Tick | None) -> Reached:
    """The refinement without the scale term, then the state rescaled to it."""
    free = Solver(s.problem, s.options.huber_px, window_prior(s.plane, s.estimate_distance))
    pre = _solve(free, reached.state, stage, tick)
    start, factor = to_scale(pre.state, s.scale.bar, s.scale.baseline, s.plane is None)
    log.info("refine-colmap: without the %s: cost %.6g in %d iterations; rescaled by %.6g to it",
             stage.held_by, pre.cost, pre.iterations, factor)
    assert reached.start is not None  # the start stage runs first
    return replace(reached, start=replace(reached.start, state=start), free_scale=pre, counted=reached.counting(pre))


def _restarts(s: Setup, stage: Restarts, reached: Reached, tick: Tick | None, is_collapsed: Collapsed) -> Reached:
    """The other starts refined when the distance ran toward 0; the lowest cost wins."""
    result, start = reached.result, reached.start
    assert result is not None and start is not None  # after the refinement
    if not is_collapsed(result.state, s.problem, stage.candidates):
        return reached
    refine = Refinement(s.options.max_iterations, s.options.backend)
    restarts = []
    counted = reached.counted
    for other in start.others:
        res = _solve(s.solver, other.state, refine, tick)
        counted = counted[0] + res.iterations, counted[1] + res.linearizations
        restarts.append(RestartStep(s.problem.image_windows(res.state)[1].min().item(), res.cost, res.iterations,
                                    res.linearizations))
        log.info("refine-colmap: the distance ran toward 0 from the best start; restart: cost %.6g (was %.6g)",
                 res.cost, result.cost)
        if res.cost < result.cost:
            result = res
    return replace(reached, result=result, restarts=tuple(restarts), collapsed=True, counted=counted)


def camera_names(model: adapter.ColmapModel) -> list[str]:
    """The housings' names: ``camera<COLMAP camera id>``."""
    return [f"camera{int(cid)}" for cid in model.camera_ids]


def _sigmas(s: Setup, stage: Sigmas, reached: Reached, is_collapsed: Collapsed) -> Reached:
    """The sigmas at the solution; a distance still at ~0 after the restarts named weak, with a warning."""
    result = reached.result
    assert result is not None  # after the refinement
    state = result.state
    names = camera_names(s.model)
    sigmas = uncertainty(s.solver, state, names, result.system)
    if reached.collapsed and is_collapsed(state, s.problem, stage.candidates):  # still at ~0: say so, name it
        ran = (["distance_mm.world"] if s.options.mount == Mount.WORLD else
               [f"distance_mm.{names[c]}"
                for c, d in enumerate(state.distances) if d < DISTANCE_COLLAPSE * min(stage.candidates)])
        sigmas = replace(sigmas, weak=sigmas.weak + tuple(w for w in ran if w not in sigmas.weak))
        log.warning("refine-colmap: the port distance ran to %.3g mm from every start (%s mm): these images do not "
                    "determine it, and it follows the scale; declare a scale_bar or check units_mm, or declare the "
                    "port in WINDOW.yaml (interface.plane point_mm, sigma_mm for a prior)",
                    float(s.problem.image_windows(state)[1].min()), ", ".join(f"{c:g}" for c in stage.candidates))
    return replace(reached, sigmas=sigmas)


def _scale_check(s: Setup, stage: ScaleCheck, reached: Reached) -> None:
    """A scale bar's refined length off its declared one: a warning; a baseline's: an error."""
    state, bar, base = reached.state, s.scale.bar, s.scale.baseline
    if stage.held_by == "bar" and bar is not None:
        refined = bar.length(state.xyz)
        if abs(refined / bar.length_mm - 1.0) > 1e-3:
            log.warning("refine-colmap: the scale bar is %.6g mm after the refinement (declared %.6g mm): the images "
                        "pull against it", refined, bar.length_mm)
    if stage.held_by == "baseline" and base is not None:
        refined = base.length(state)
        if abs(refined / base.length_mm - 1.0) > 1e-3:
            images = s.model.image_names[base.a], s.model.image_names[base.b]
            raise AriSfmError(s.path, f"baseline: the refinement ends with images {images[0]} and {images[1]} "
                                      f"{refined:.6g} mm apart, not the {base.length_mm:.6g} mm given: the images pull "
                                      "against it (check the names and the distance)")


def run_stage(s: Setup, stage: RefineStage, reached: Reached, tick: Tick | None = None,
              is_collapsed: Collapsed = collapsed) -> Reached:
    """One stage from where the previous ones left the refinement.

    Args:
        s: the refinement's setup.
        stage: the stage (:func:`plan_refinement`).
        reached: where the previous stages left it (``Reached()`` before the start).
        tick: told each accepted LM step of the free-scale, final and restart solves (numpy backend).
        is_collapsed: whether a state's distance ran toward 0 (:func:`collapsed`).

    Returns:
        Where the refinement is after the stage.
    """
    if isinstance(stage, (DistanceSearch, ChainStart)):
        return replace(reached, start=_start(s, stage))
    if isinstance(stage, FreeScale):
        return _free_scale(s, stage, reached, tick)
    if isinstance(stage, Refinement):
        res = _solve(s.solver, reached.state, stage, tick)
        return replace(reached, refinement=res, result=res, counted=reached.counting(res))
    if isinstance(stage, Restarts):
        return _restarts(s, stage, reached, tick, is_collapsed)
    if isinstance(stage, Sigmas):
        return _sigmas(s, stage, reached, is_collapsed)
    _scale_check(s, stage, reached)
    return reached

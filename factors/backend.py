"""The bundle-adjustment backend switch: GTSAM (the graph's own optimizer) or the numpy solver.

Both solve the same RigGraph on the same Levenberg-Marquardt path (same
answer to ~1e-13): ``"gtsam"`` runs ``gtsam.LevenbergMarquardtOptimizer``,
which calls each view's Python CustomFactor at every linearisation;
``"numpy"`` packs the graph (:class:`~ari_sfm.factors.packed_problem.VectorizedProblem`)
and solves it without callbacks; ``"auto"`` (the default of calibrate) is numpy,
and GTSAM for a graph the numpy backend cannot hold (a user factor linking
several target frames).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

from ..solver.levenberg_marquardt import LMParams, LMReport
from .packed_problem import VectorizedProblem
from .variables import GraphLike, RigState

log = logging.getLogger(__name__)

BACKENDS = ("gtsam", "numpy", "auto")


@dataclass(frozen=True)
class VectorizedSolution:
    """What :func:`solve_vectorized` returns.

    Attributes:
        state: The solved state.
        report: How Levenberg-Marquardt went.
    """

    state: RigState
    report: LMReport


@dataclass(frozen=True)
class GraphSolution:
    """What :func:`solve_graph` returns.

    Attributes:
        state: The solved state.
        problem: The solved numpy problem (its residuals and marginals at the optimum), None with GTSAM.
    """

    state: RigState
    problem: VectorizedProblem | None


def solve_vectorized(
    rig_graph: GraphLike,
    max_iterations: int = 100,
    relative_tolerance: float = 1e-10,
    huber_px: float | None = None,
    check: bool = True,
    params: LMParams | None = None,
    stop: str = "converged",
) -> VectorizedSolution:
    """Optimise a built RigGraph's problem with the numpy backend (GTSAM's LM path, no callbacks).

    The graph's values and ``iterations`` are updated as RigGraph.optimize does.

    Args:
        rig_graph: the built graph.
        max_iterations: cap on the accepted LM steps.
        relative_tolerance: LM stops when the error's relative decrease is below it.
        huber_px: the Huber threshold the graph was built with (px; None: no Huber loss).
        check: compare the residuals of a few views with the graph's own factors (a mismatch, e.g. another
            ``huber_px``, raises ValueError).
        params: the LM constants (default :class:`LMParams`).
        stop: the stop rule (:meth:`VectorizedProblem.optimize`; "gtsam": GTSAM's trials one for one).

    Returns:
        The solved state and the :class:`LMReport` (final error, lambda trials, time).
    """
    problem = VectorizedProblem.from_rig_graph(rig_graph, huber_px=huber_px, check=check)
    state = problem.optimize(max_iterations, relative_tolerance, params, stop)
    _write_solution(rig_graph, problem)
    rig_graph.iterations = problem.iterations
    assert problem.report is not None  # set by optimize
    return VectorizedSolution(state, problem.report)


def _write_solution(rig_graph: GraphLike, problem: VectorizedProblem) -> None:
    """The solved variables into the graph's values.

    Written when first read if the graph makes them lazily
    (:meth:`~ari_sfm.factors.rig_graph.RigGraph.set_solution`), else now.
    """
    x = problem.x
    if hasattr(rig_graph, "set_solution"):
        rig_graph.set_solution(lambda values: problem.write_values(values, x))
    else:
        problem.write_values(rig_graph.values, x)


def resolve_backend(backend: str) -> str:
    """The solver a backend name stands for: "auto" is "numpy".

    Args:
        backend: "gtsam", "numpy" or "auto".

    Returns:
        "gtsam" or "numpy".

    Raises:
        ValueError: an unknown backend name.
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r} (known: {', '.join(BACKENDS)})")
    return "numpy" if backend == "auto" else backend


def solve_graph(rig_graph: GraphLike, backend: str = "auto", max_iterations: int = 100,
                huber_px: float | None = None, check: bool = True, stop: str = "converged",
                relative_tolerance: float = 1e-10) -> GraphSolution:
    """Optimise a RigGraph with GTSAM (``rig_graph.optimize``) or the numpy backend; same result either way.

    "auto" falls back to GTSAM for a graph the numpy backend cannot hold (a user factor linking several
    target frames).

    Args:
        rig_graph: the built graph; its values and ``iterations`` are updated.
        backend: "gtsam", "numpy" or "auto".
        max_iterations: cap on the accepted LM steps.
        huber_px: the Huber threshold the graph was built with (the numpy backend needs it, see
            :meth:`VectorizedProblem.from_rig_graph`).
        check: compare a few views with the graph's own factors (see ``from_rig_graph``); a caller that has
            just built the graph with ``huber_px`` may skip it.
        stop: the numpy backend's stop rule (:meth:`VectorizedProblem.optimize`).
        relative_tolerance: LM stops when the error's relative decrease is below it (both backends).

    Returns:
        The solved state and the solved VectorizedProblem (None with GTSAM), whose residuals and marginals at
            the optimum need no callbacks.
    """
    problem = None
    if resolve_backend(backend) == "numpy":
        try:
            problem = VectorizedProblem.from_rig_graph(rig_graph, huber_px=huber_px, check=check)
        except NotImplementedError as exc:
            if backend != "auto":
                raise
            log.info("numpy backend: %s; optimising with GTSAM", exc)
    if problem is None:
        return GraphSolution(rig_graph.optimize(max_iterations, relative_tolerance), None)
    state = problem.optimize(max_iterations, relative_tolerance, stop=stop)
    _write_solution(rig_graph, problem)
    rig_graph.iterations = problem.iterations
    return GraphSolution(state, problem)


def optimize_graph(rig_graph: GraphLike, backend: str = "auto", max_iterations: int = 100,
                   huber_px: float | None = None, check: bool = True, stop: str = "converged",
                   relative_tolerance: float = 1e-10) -> RigState:
    """The solved state of :func:`solve_graph` (the same arguments).

    Args:
        rig_graph: the built graph; its values and ``iterations`` are updated.
        backend: "gtsam", "numpy" or "auto".
        max_iterations: cap on the accepted LM steps.
        huber_px: the Huber threshold the graph was built with.
        check: compare a few views with the graph's own factors.
        stop: the numpy backend's stop rule.
        relative_tolerance: LM's relative tolerance.

    Returns:
        The solved state.
    """
    return solve_graph(rig_graph, backend, max_iterations, huber_px, check, stop, relative_tolerance).state


def optimize_vectorized(rig_graph: GraphLike, max_iterations: int = 100, relative_tolerance: float = 1e-10,
                        huber_px: float | None = None, check: bool = True, params: LMParams | None = None,
                        stop: str = "converged") -> RigState:
    """The solved state of :func:`solve_vectorized` (the same arguments).

    Args:
        rig_graph: the built graph.
        max_iterations: cap on the accepted LM steps.
        relative_tolerance: LM's relative tolerance.
        huber_px: the Huber threshold the graph was built with.
        check: compare a few views with the graph's own factors.
        params: the LM constants.
        stop: the stop rule.

    Returns:
        The solved state.
    """
    return solve_vectorized(rig_graph, max_iterations, relative_tolerance, huber_px, check, params, stop).state

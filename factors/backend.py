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

from ..solver.levenberg_marquardt import LMParams, LMReport
from .packed_problem import VectorizedProblem
from .variables import GraphLike, RigState

log = logging.getLogger(__name__)

BACKENDS = ("gtsam", "numpy", "auto")


def optimize_vectorized(
    rig_graph: GraphLike,
    max_iterations: int = 100,
    relative_tolerance: float = 1e-10,
    huber_px: float | None = None,
    check: bool = True,
    params: LMParams | None = None,
    return_report: bool = False,
    stop: str = "converged",
) -> RigState | tuple[RigState, LMReport]:
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
        return_report: also return the report.
        stop: the stop rule (:meth:`VectorizedProblem.optimize`; "gtsam": GTSAM's trials one for one).

    Returns:
        The solved state; with ``return_report`` the pair (state, :class:`LMReport`: final error, lambda
            trials, time).
    """
    problem = VectorizedProblem.from_rig_graph(rig_graph, huber_px=huber_px, check=check)
    state = problem.optimize(max_iterations, relative_tolerance, params, stop)
    _write_solution(rig_graph, problem)
    rig_graph.iterations = problem.iterations
    if return_report:
        assert problem.report is not None  # set by optimize
        return state, problem.report
    return state


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


def optimize_graph(rig_graph: GraphLike, backend: str = "auto", max_iterations: int = 100,
                   huber_px: float | None = None, return_problem: bool = False, check: bool = True,
                   stop: str = "converged", relative_tolerance: float = 1e-10
                   ) -> RigState | tuple[RigState, VectorizedProblem | None]:
    """Optimise a RigGraph with GTSAM (``rig_graph.optimize``) or the numpy backend; same result either way.

    "auto" falls back to GTSAM for a graph the numpy backend cannot hold (a user factor linking several
    target frames).

    Args:
        rig_graph: the built graph; its values and ``iterations`` are updated.
        backend: "gtsam", "numpy" or "auto".
        max_iterations: cap on the accepted LM steps.
        huber_px: the Huber threshold the graph was built with (the numpy backend needs it, see
            :meth:`VectorizedProblem.from_rig_graph`).
        return_problem: also return the solved problem, so that residuals and marginals at the optimum need
            no callbacks.
        check: compare a few views with the graph's own factors (see ``from_rig_graph``); a caller that has
            just built the graph with ``huber_px`` may skip it.
        stop: the numpy backend's stop rule (:meth:`VectorizedProblem.optimize`).
        relative_tolerance: LM stops when the error's relative decrease is below it (both backends).

    Returns:
        The solved state; with ``return_problem`` the pair (state, the solved VectorizedProblem, or None
            with GTSAM).
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
        state = rig_graph.optimize(max_iterations, relative_tolerance)
        return (state, None) if return_problem else state
    state = problem.optimize(max_iterations, relative_tolerance, stop=stop)
    _write_solution(rig_graph, problem)
    rig_graph.iterations = problem.iterations
    return (state, problem) if return_problem else state

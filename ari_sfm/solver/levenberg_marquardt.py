"""Levenberg-Marquardt as gtsam.LevenbergMarquardtOptimizer does it, generic over the problem.

The loop knows nothing of cameras: a problem supplies five operations
(:class:`LMProblem`) on opaque values x, linear systems and steps::

    linearize(x) -> system          # system.error: 0.5 |r|^2 of the linearisation at x
    solve(system, lam) -> step      # the step of (H + lam I) step = -g, or None if not positive definite
    model_decrease(system, step)    # -(g . step + 0.5 step^T H step), the decrease the linear model predicts
    retract(x, step) -> x           # x moved by the step (on the manifold)
    error(x) -> float               # the nonlinear error 0.5 |r(x)|^2

plus ``linearized_error_is_error`` (True when system.error equals error(x), i.e.
no robust noise model outside the problem's own residuals). It implements GTSAM
4.3's defaults (lambda 1e-5 times/divided by 10, damping ``H + lambda I`` on
every variable, model fidelity > 1e-3, upper bound 1e5) and takes the same path
as GTSAM, not only the same optimum.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

log = logging.getLogger(__name__)

STOP_RULES = ("converged", "gtsam")  # levenberg_marquardt's stop=


class NonFiniteJacobian(RuntimeError):
    """A linearisation point with a non-finite Jacobian entry (e.g. a corner behind the window). A problem's
    ``linearize`` raises it; a trial linearised in its place (``linearize_trials``) is then judged by its
    error instead, as any trial is without ``linearize_trials``."""


class LMProblem(Protocol):
    """What :func:`levenberg_marquardt` needs of a problem (see the module docstring)."""

    @property
    def linearized_error_is_error(self) -> bool: ...

    def linearize(self, x: Any) -> Any: ...
    def solve(self, system: Any, lam: float) -> Any | None: ...
    def model_decrease(self, system: Any, step: Any) -> float: ...
    def retract(self, x: Any, step: Any) -> Any: ...
    def error(self, x: Any) -> float: ...


@dataclass(frozen=True)
class LMParams:
    """Levenberg-Marquardt constants: gtsam.LevenbergMarquardtParams 4.3 defaults and RigGraph.optimize's
    absolute tolerance (the iteration cap and relative tolerance are arguments of optimize)."""

    absolute_tolerance: float = 1e-12  # stop when the error decrease is below this
    lambda_initial: float = 1e-5
    lambda_factor: float = 10.0
    lambda_upper_bound: float = 1e5  # give up when lambda reaches this
    lambda_lower_bound: float = 0.0
    min_model_fidelity: float = 1e-3  # accept a step when actual / predicted decrease exceeds this


@dataclass(frozen=True)
class LMReport:
    """How an optimisation went. Errors are GTSAM's: 0.5 * sum of whitened squared residuals."""

    iterations: int  # accepted steps, as gtsam's optimizer.iterations()
    inner_iterations: int  # lambda trials, as gtsam's getInnerIterations()
    linearizations: int
    initial_error: float
    error: float
    lambda_final: float
    time_s: float
    stop: str  # "converged", "max_iterations", "lambda_upper_bound", "small_cost_change", "zero_error",
    #            "no_model_decrease" (stop="converged" only: see VectorizedProblem.optimize)
    error_evaluations: int = 0  # nonlinear error evaluations (the initial one unless cached, one per tried step)



@dataclass(frozen=True)
class LMResult:
    """The final values, the report, and the last linearisation if it was taken at the final values
    (what a covariance needs; None otherwise)."""

    x: Any
    report: LMReport
    system_at_x: Any | None


@dataclass(frozen=True)
class _Trial:
    """One lambda trial at a linearisation (gtsam's tryLambda)."""

    step_ok: bool = False  # the step is accepted
    stop_searching: bool = False  # the error barely changed: LM gives up at this linearisation
    no_model_decrease: bool = False  # (stop="converged") the step predicts no decrease: no later trial could pass
    x: Any = None  # the tried values, their error and (linearize_trials) their linearisation
    error: float = math.nan
    system: Any = None
    linearizations: int = 0
    evaluations: int = 0


def _try_lambda(problem: LMProblem, sys: Any, x: Any, err: float, lam: float, rule: str, linearize_trials: bool,
                relative_tolerance: float, p: LMParams) -> _Trial:
    """The step damped by ``lam`` from the linearisation ``sys`` at ``x`` (error ``err``), tried."""
    step = problem.solve(sys, lam)
    if step is None:
        return _Trial()
    predicted = problem.model_decrease(sys, step)
    if rule == "converged" and predicted <= np.finfo(float).eps * sys.error:
        return _Trial(no_model_decrease=True)
    if predicted < 0.0:
        return _Trial()
    x_new = problem.retract(x, step)
    sys_new, linearizations = None, 0
    if linearize_trials:  # the trial's linearisation: its error, and the next system if accepted
        try:
            sys_new = problem.linearize(x_new)
            e_new = sys_new.error
            linearizations = 1
        except NonFiniteJacobian:  # e.g. a corner behind the window: its error says how bad
            sys_new, e_new = None, problem.error(x_new)
    else:
        e_new = problem.error(x_new)
    change = err - e_new
    step_ok = False
    if predicted > np.finfo(float).eps * sys.error:
        step_ok = change / predicted > p.min_model_fidelity
    return _Trial(step_ok, abs(change) < relative_tolerance * err, False, x_new, e_new, sys_new, linearizations, 1)


def levenberg_marquardt(problem: LMProblem, x: Any, max_iterations: int = 100, relative_tolerance: float = 1e-10,
                        params: LMParams | None = None, stop: str = "converged",
                        initial_error: float | None = None,
                        progress: Callable[[int, float], None] | None = None) -> LMResult:
    """Levenberg-Marquardt from x (GTSAM's algorithm).

    ``stop="gtsam"`` is GTSAM's loop trial for trial: at convergence it typically rejects a step whose
    predicted decrease is below ``eps * error`` and raises lambda tenfold, evaluating the error each time,
    until the upper bound, with the values unchanged. ``stop="converged"`` (the default) ends at the first
    such trial without evaluating it, and takes the initial error from the first linearisation instead of a
    separate evaluation when ``problem.linearized_error_is_error``. Both give the same steps, values and
    error; only the report (lambda, trials, evaluations, stop reason) differs.

    Args:
        problem: the problem's operations (:class:`LMProblem`).
        x: the starting values.
        max_iterations: cap on the accepted steps (gtsam's iterations()).
        relative_tolerance: LM stops when the relative error decrease is below it.
        params: the constants (default :class:`LMParams`).
        stop: the stop rule, one of :data:`STOP_RULES` (see above).
        initial_error: error(x) when already known (saves an evaluation).
        progress: called with (accepted steps, error) after each linearisation's trials.

    Returns:
        An :class:`LMResult`: the final values, the :class:`LMReport` and the last linearisation when it was
            taken at the final values.

    Raises:
        ValueError: an unknown ``stop`` rule.
    """
    if stop not in STOP_RULES:
        raise ValueError(f"unknown stop rule {stop!r} (known: {', '.join(STOP_RULES)})")
    p = params or LMParams()
    t0 = time.perf_counter()
    evaluations, linearizations, first = 0, 0, None
    if initial_error is not None:
        err = initial_error
    elif stop == "converged" and problem.linearized_error_is_error and max_iterations > 0:
        first = problem.linearize(x)
        err, linearizations = first.error, 1
    else:
        err, evaluations = problem.error(x), 1
    initial = err
    lam, iterations, inner = p.lambda_initial, 0, 0
    rule, stop = stop, "max_iterations"
    # A problem whose linearisation costs little more than its error (getattr: opt-in) has each trial
    # linearised instead of evaluated: an accepted step (most are) then needs no second pass.
    linearize_trials = (rule == "converged" and problem.linearized_error_is_error
                        and getattr(problem, "linearize_trials", False))
    sys, x_lin = None, None
    if err <= 0.0:
        stop = "zero_error"
    while stop != "zero_error" and iterations < max_iterations:  # gtsam's defaultOptimize
        cur_err = err
        if first is not None:
            sys, x_lin, first = first, x, None
        else:
            sys, x_lin = problem.linearize(x), x
            linearizations += 1
        gave_up = None
        while True:  # gtsam's tryLambda, until a step is accepted or LM gives up
            trial = _try_lambda(problem, sys, x, err, lam, rule, linearize_trials, relative_tolerance, p)
            linearizations += trial.linearizations
            evaluations += trial.evaluations
            if trial.no_model_decrease:
                gave_up = "no_model_decrease"  # GTSAM would reject this and every later trial
                break
            if trial.step_ok:
                x, err = trial.x, trial.error
                if linearize_trials:
                    first = trial.system  # the next linearisation, taken already (None: made at the loop's top)
                lam = max(p.lambda_lower_bound, lam / p.lambda_factor)
                iterations += 1
                inner += 1
                break
            if trial.stop_searching:
                gave_up = "small_cost_change"
                break
            lam *= p.lambda_factor
            inner += 1
            if lam >= p.lambda_upper_bound:
                gave_up = "lambda_upper_bound"
                break
        decrease = cur_err - err
        if progress is not None:
            progress(iterations, err)
        if err <= 0.0:
            stop = "zero_error"
        elif decrease / cur_err <= relative_tolerance or decrease <= p.absolute_tolerance:
            stop = gave_up or "converged"
            break
        elif not math.isfinite(cur_err):
            stop = "non_finite"
            break
    report = LMReport(iterations, inner, linearizations, initial, err, lam, time.perf_counter() - t0, stop,
                      evaluations)
    log.debug("LM: %s", report)
    at_x = first if first is not None else (sys if linearizations and x_lin is x else None)
    return LMResult(x, report, at_x)

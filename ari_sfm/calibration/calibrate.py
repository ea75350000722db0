"""calibrate(): the options, the plan of bundle adjustments, the starts the quality gate tries, the result.

Steps of :func:`calibrate`: options (:class:`CalibrationOptions`), load, plan (:func:`plan_stages`: frozen
:class:`Stage` records, no side effect), then for each start (:class:`Start`) the analytic initialisation,
the stages (:func:`run_stage` -> :class:`StageResult`) and the :class:`~ari_sfm.calibration.record.Calibration`,
judged by :mod:`ari_sfm.calibration.quality` until one passes. Design notes: docs/design/calibration.md.
"""
from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np

from ..errors import AriSfmError
from ..geometry import angle_between_deg
from ..init.exact_start import check_in_front, exact_start, hold_normals, planes_separate
from ..models.registry import model_spec
from ..options import Choice, with_overrides
from ..records import Dataset, Interface, Observation, WindowPlane
from ..results import OptimizerReport, OptimizerRun, OutlierReport, StageCamera, StageRecord, StageWindow
from .evaluate import residual_stats
from .record import Calibration, CameraCalibration, WindowCalibration

if TYPE_CHECKING:
    from gtsam import NonlinearFactor

    from ..factors.rig_graph import RigGraph, RigState  # imported lazily at run time (gtsam)
    from ..init.rig import RigInit

    # a user's factors: a sequence, or a callable of each stage's graph returning them
    ExtraFactors = Sequence[NonlinearFactor] | Callable[[RigGraph], Sequence[NonlinearFactor]] | None

log = logging.getLogger(__name__)

PLANE_ROUNDS = 5  # ari rounds holding the declared normal at its frame's refitted pose (no stacking)
DEFAULT_MODEL = "exact"  # the best model: Snell's law refined from the ari stage (distortion: resolve_distortion)
DISTORTION_MIN_VIEWS = 6  # calibration views per camera below which lens distortion is not estimated by default
DISTORTION_MIN_COVERAGE = 0.2  # fraction of a camera's image inside the convex hull of its corners, likewise
FINAL_TOLERANCE = 1e-10  # a stage's solve stops when the error's relative decrease is below this (GTSAM's use)
START_TOLERANCE = 1e-3  # ... or this, for an ari stage whose result only starts a Snell stage: the paraxial model's
# own error moves the start far more than its last 1e-3 of the error (ari 6820 vs exact 16 on a sparse arc rig), which
# come at the linear rate of the Huber reweighting (half to four fifths of its iterations); the Snell stage then
# converges to the same calibration (17 calibrations of 15 scenarios: 1e-5 relative or less, but one rig's lens terms,
# 1e-4 relative, 1e-10 absolute, and the window distance held in air, which only the ari stage sets: 0.7 um)
EASED_PLANE_DEG = 0.05  # the eased-planes start: a held declared normal first as a prior of this sigma ...
EASED_PLANE_MM = 0.5  # ... and a held face position as one of this
PRINCIPAL_POINT_MAX_SIGMA = 0.02  # auto: a principal point less determined than this share of the image is held


class PrincipalPoint(Choice):
    """How each camera's principal point is treated (``CalibrationOptions.principal_point``)."""

    AUTO = "auto"  # estimated; held at the image centre for the cameras whose views leave it undetermined
    FREE = "free"  # estimated for every camera
    CENTRE = "centre"  # held at the image centre (cameras without a K hint)


class Backend(Choice):
    """The bundle-adjustment solver (``CalibrationOptions.backend``)."""

    AUTO = "auto"  # numpy
    NUMPY = "numpy"  # the vectorised problem, GTSAM's Levenberg-Marquardt path
    GTSAM = "gtsam"  # gtsam.LevenbergMarquardtOptimizer on the factor graph



@dataclass(frozen=True)
class CalibrationOptions:
    """Options of :func:`calibrate`, each with its default (the one place: the command line's options are
    made from the fields whose metadata names a ``cli`` flag: ``ari_sfm.cli``; ``{name}`` in a help text
    is that field's default)."""

    distortion: bool | None = field(default=None, metadata={
        "cli": "--distortion/--no-distortion",
        "help": "Estimate k1 k2 p1 p2 k3, or hold them at zero. Default: estimated with the exact model when the "
                f"views support it (every camera's corners covering >= {100 * DISTORTION_MIN_COVERAGE:.0f} % of its "
                f"image; with a planar target also >= {DISTORTION_MIN_VIEWS} calibration views per camera and stacking "
                "poses; otherwise one line says why not)."})
    # None: for the exact model when the views support it (distortion_support), else off; False: as given (zero)
    huber_px: float | None = field(default=1.0, metadata={
        "cli": "--huber-px", "help": "Per-corner Huber threshold in px (0: plain least squares)."})  # None: plain
    outlier_sigma: float = 5.0  # corners beyond this many sigma after convergence are reported
    exclude_outliers: bool = field(default=False, metadata={
        "cli": "--exclude-outliers",
        "help": "Drop corners beyond {outlier_sigma:g} sigma after convergence and re-run."})
    fix_intrinsics: bool = field(default=False, metadata={
        "cli": "--fix-intrinsics",
        "help": "Hold the rig.yaml hints: a K hint holds K (and dist); a focal_px hint holds "
                "fx = fy = focal_px (principal point free)."})
    principal_point: PrincipalPoint = field(default=PrincipalPoint.AUTO, metadata={
        "cli": "--principal-point",
        "help": "Estimate each camera's principal point (free), or hold it at the image centre (centre). Default "
                "(auto): estimated, and held for the cameras whose views leave it undetermined (standard deviation "
                f"above {100 * PRINCIPAL_POINT_MAX_SIGMA:g} % of the image: one view of a shallow body cannot tell it "
                "from the camera's rotation), the calibration then solved again; one line says which."})
    max_iterations: int = 100  # Levenberg-Marquardt iterations per stage
    backend: Backend = field(default=Backend.AUTO, metadata={
        "cli": "--backend",
        "help": "Bundle-adjustment solver: numpy (vectorised, GTSAM's LM path, 5-13x faster), gtsam "
                "(gtsam.LevenbergMarquardtOptimizer on the factor graph); auto = numpy."})
    workers: int | None = None  # threads for corner detection (dataset with only images) and for the per-camera
    # analytic initialisation; None: os.cpu_count() (at most one per camera for the initialisation)
    progress: bool = False  # progress bars (the CLI turns them on)
    uncertainty: bool = True  # standard deviations of every parameter (marginal covariances, physical units)
    sigma_px: float | None = None  # the corners' pixel sigma weighting the images; None: estimated (robust,
    # from each stage's residuals; the stage is re-solved with it when priors or extra factors share the graph)
    quality: bool = True  # judge the result (ari_sfm.calibration.quality) and, when it fails, re-try from the
    # other starts

    def __post_init__(self) -> None:
        """Refuse values that would fail deep inside the solver; a mode given as its string becomes the enum.

        Raises:
            ValueError: one line naming the field, what it must be and the value given.
        """
        if self.huber_px is not None and not (math.isfinite(self.huber_px) and self.huber_px > 0):
            raise ValueError(f"huber_px must be a finite number > 0, or None (got {self.huber_px})")
        if not (math.isfinite(self.outlier_sigma) and self.outlier_sigma > 0):
            raise ValueError(f"outlier_sigma must be a finite number > 0 (got {self.outlier_sigma})")
        for name, mode in (("principal_point", PrincipalPoint), ("backend", Backend)):
            object.__setattr__(self, name, mode.parse(getattr(self, name), name))
        iterations = self.max_iterations
        if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 1:
            raise ValueError(f"max_iterations must be an integer >= 1 (got {iterations!r})")


def _options(options: CalibrationOptions | None, overrides: dict) -> CalibrationOptions:
    """``options`` (default: the defaults) with the keyword ``overrides`` applied."""
    return with_overrides(CalibrationOptions, options, overrides, "calibrate")


def distortion_support(dataset: Dataset) -> str | None:
    """Whether the dataset's views can support estimating lens distortion (k1 k2 p1 p2 k3).

    Every camera needs corners whose convex hull covers ``DISTORTION_MIN_COVERAGE`` of its image and, with a
    planar target, ``DISTORTION_MIN_VIEWS`` calibration views and stacking poses; a 3D body needs neither (one
    view with a focal length hint). Why: docs/design/calibration.md.

    Args:
        dataset: The dataset with its observations.

    Returns:
        None when they can; else why not, one sentence naming the camera or what is missing.
    """
    import cv2

    body = not dataset.target.is_planar()
    if not body and not dataset.select("stacking"):
        return ("the dataset has no stacking poses: the window normal is then found through refraction alone, "
                "which free distortion would absorb (--distortion estimates it anyway)")
    for name in dataset.camera_names:
        views = dataset.select("calibration", name)
        frames = {o.frame for o in views if len(o.ids)}
        need = 1 if body else DISTORTION_MIN_VIEWS
        if len(frames) < need:
            return (f"{name} has {len(frames)} calibration view{'s' * (len(frames) != 1)} "
                    f"(at least {need} needed)")
        spec = dataset.cameras[name]
        if body and len(frames) == 1 and spec.focal_px is None and spec.K is None:
            return (f"{name} sees the body in one view and has no focal length hint: its focal length, principal "
                    "point and lens are more than one view tells (give cameras.<name>.focal_px)")
        pixels = np.concatenate([o.pixels for o in views if len(o.ids)]).astype(np.float32)
        w, h = dataset.cameras[name].image_size
        coverage = float(cv2.contourArea(cv2.convexHull(pixels))) / float(w * h)
        if coverage < DISTORTION_MIN_COVERAGE:
            return (f"{name}'s corners cover {100 * coverage:.0f} % of its image (at least "
                    f"{100 * DISTORTION_MIN_COVERAGE:.0f} % needed: add views near its edges)")
    return None


def resolve_distortion(dataset: Dataset, model: str, opts: CalibrationOptions) -> bool:
    """Whether lens distortion is estimated: ``opts.distortion`` as given, or (None) for the exact model when
    the views support it (:func:`distortion_support`), no intrinsics are held and the target is a board; when
    it is not, one log line says why.

    Args:
        dataset: The dataset with its observations.
        model: The model calibrated.
        opts: The options.

    Returns:
        True to estimate k1 k2 p1 p2 k3, False to hold them.
    """
    if opts.distortion is not None:
        return bool(opts.distortion)
    if model != "exact":  # the paper's ari model and the baselines keep their published form
        return False
    if opts.fix_intrinsics:
        log.info("lens distortion not estimated: the intrinsics hints are held (fix_intrinsics)")
        return False
    why = distortion_support(dataset)
    if why is not None:
        log.warning("lens distortion not estimated: %s", why)
        return False
    if not dataset.target.is_planar():  # a body's lens is estimated when the data ask for it (lens_on_misfit)
        log.info("lens distortion not estimated first: estimated only if the model then fits the corners worse "
                 "than they allow")
        return False
    return True


def lens_on_misfit(dataset: Dataset, model: str, opts: CalibrationOptions) -> bool:
    """Whether a calibration whose default start fails the quality gate is tried again with lens distortion
    estimated: ``distortion`` left to the default, the exact model, a 3D body whose views support it (why:
    docs/design/calibration.md).

    Args:
        dataset: The dataset with its observations.
        model: The model calibrated.
        opts: The options.

    Returns:
        True when a start with the lens estimated follows the others.
    """
    return (opts.distortion is None and model == "exact" and not opts.fix_intrinsics
            and not dataset.target.is_planar() and distortion_support(dataset) is None)


def centred_principal_points(dataset: Dataset, opts: CalibrationOptions, undetermined: Sequence[str] = ()
                             ) -> dict[str, tuple[float, float]]:
    """The cameras whose principal point is held at the image centre, and that centre.

    Args:
        dataset: The dataset.
        opts: The options: ``principal_point`` "centre" holds every camera without a K hint, "free" none,
            "auto" the ``undetermined`` ones.
        undetermined: The cameras whose principal point a first solve left undetermined
            (:func:`undetermined_principal_points`).

    Returns:
        Camera name -> (cx, cy) of its image centre, px.
    """
    def centre(name: str) -> tuple[float, float]:
        w, h = dataset.cameras[name].image_size
        return (w - 1) / 2.0, (h - 1) / 2.0

    if opts.principal_point is PrincipalPoint.FREE:
        return {}
    names = dataset.camera_names if opts.principal_point is PrincipalPoint.CENTRE else list(undetermined)
    return {n: centre(n) for n in names if dataset.cameras[n].K is None}


def undetermined_principal_points(cal: Calibration) -> list[str]:
    """The cameras whose principal point the data leave undetermined.

    Args:
        cal: A calibration with its standard deviations (none: no camera is named).

    Returns:
        The cameras whose cx or cy has a standard deviation above ``PRINCIPAL_POINT_MAX_SIGMA`` of the image's
        larger side, or none at all (one view of a shallow body cannot tell the principal point from the
        camera's rotation).
    """
    if cal.uncertainty is None:
        return []
    out = []
    for name, cam in cal.cameras.items():
        s = cal.uncertainty.cameras[name].intrinsics
        limit = PRINCIPAL_POINT_MAX_SIGMA * max(cam.image_size)
        sigmas = [s.get("cx"), s.get("cy")]
        if any(v is None or not math.isfinite(v) or v > limit for v in sigmas):
            out.append(name)
    return out


def ensure_observations(dataset: Dataset, workers: int | None = None, progress: bool = False) -> Dataset:
    """The dataset with observations, detecting corners in its images when it has none
    (:func:`ari_sfm.detection.ensure_observations`, re-exported here).

    Args:
        dataset: The dataset.
        workers: Detection threads (None: every core).
        progress: A progress bar.

    Returns:
        The dataset with its observations.
    """
    from ..detection import ensure_observations as ensure

    return ensure(dataset, workers, progress)


def _add_factors(graph: RigGraph, extra_factors: ExtraFactors) -> None:
    """Push a user's factors (a sequence, or a callable of the RigGraph returning them) onto a stage's graph."""
    if extra_factors is None:
        return
    factors = extra_factors(graph) if callable(extra_factors) else extra_factors
    for f in factors:
        graph.graph.push_back(f)


@dataclass(frozen=True)
class Stage:
    """One bundle adjustment of calibrate()'s plan (:func:`plan_stages`)."""

    label: str  # its name in calibration.json "stages" and in the optimizer report
    model: str  # the graph's projection model (a bundle model of ari_sfm.models.registry)
    distortion: bool = False  # k1 k2 p1 p2 k3 estimated
    hold_normal: bool = False  # the normal held at its start (ari without stacking cannot observe it)
    with_plane: bool = False  # the declared plane's factor in the graph, the window placed by its frame's pose
    skippable: bool = False  # skipped (unless the start asks for a free window first) when the declared plane,
    # placed by the previous stage's poses, already separates every camera from the corners it sees

    @property
    def snell(self) -> bool:
        """Projects with Snell's law: needs a window distance in front of every camera
        (:mod:`~ari_sfm.init.exact_start`)."""
        return model_spec(self.model).needs_distance


def plan_stages(dataset: Dataset, model: str, options: CalibrationOptions = CalibrationOptions()) -> tuple[Stage, ...]:
    """The bundle adjustments calibrating ``model`` on ``dataset``, in order. No side effect: reads the
    dataset's sets and windows only.

    ari first (the analytic start's model); without stacking the normal is held in it (then, with a
    declared plane and model ari, a second ari stage with the plane). A Snell model follows, refined
    from the ari result; with a declared plane under water, a free-window Snell stage first
    ("exact_free": the ari poses can put a plane placed by them behind the cameras).

    Args:
        dataset: The dataset.
        model: The model calibrated.
        options: The options, ``distortion`` resolved (:func:`resolve_distortion`).

    Returns:
        The stages; none for the baselines, which have their own calibrators.

    Raises:
        AriSfmError: a window's normal observable neither by stacking nor by a declared plane, with a model
            that cannot observe it through refraction (ari).
    """
    spec = model_spec(model, "model", calibratable=True)
    if not spec.bundle:
        return ()
    windows = dataset.window_list()
    planes = [w.interface.plane is not None for w in windows]
    plane = any(planes)
    stacked = stacked_windows(dataset)  # as initialise_rig finds it: expansion centres
    normal_observed = all(stacked)
    if any(not (s or p) for s, p in zip(stacked, planes)) and not spec.needs_distance:
        from ..init.rig import NO_NORMAL_MESSAGE

        raise AriSfmError(dataset.rig_path, NO_NORMAL_MESSAGE)
    distortion = bool(options.distortion)
    placed_by_snell = plane and dataset.medium_index != 1.0 and spec.needs_distance
    if normal_observed:
        stages = [Stage("ari", "ari", distortion, with_plane=plane and not placed_by_snell)]
    else:
        stages = [Stage("ari_normal_held" if plane else "ari", "ari", distortion, hold_normal=True)]
        if plane and not spec.needs_distance:
            stages.append(Stage("ari", "ari", distortion, with_plane=True))
    if placed_by_snell:
        stages.append(Stage(f"{spec.name}_free", spec.name, distortion, skippable=True))
    if spec.needs_distance:
        stages.append(Stage(spec.name, spec.name, distortion, with_plane=plane))
    return tuple(stages)


def stage_tolerance(stage: Stage, plan: tuple[Stage, ...]) -> float:
    """The relative error decrease at which ``stage``'s solve stops.

    Args:
        stage: A stage of ``plan``.
        plan: The plan it belongs to.

    Returns:
        ``START_TOLERANCE`` for a paraxial stage whose result only starts a Snell stage (which refines every
        parameter of it again), else ``FINAL_TOLERANCE``.
    """
    return START_TOLERANCE if not stage.snell and plan[-1].snell else FINAL_TOLERANCE


def stacked_windows(dataset: Dataset) -> list[bool]:
    """Per window (the dataset's order): whether stacking views of its cameras observe its normal."""
    cameras = {o.camera for o in dataset.select("stacking")}
    return [bool(cameras & set(w.cameras)) for w in dataset.window_list()]


@dataclass(frozen=True)
class StageResult:
    """What one stage left: the state after it, its residuals and how the solve went."""

    stage: Stage
    state: RigState  # (ari_sfm.factors.rig_graph, imported lazily: gtsam)
    residuals: list[tuple[Observation, np.ndarray]]  # (observation, (n, 2) residuals in px)
    iterations: int
    time_s: float
    backend: str
    sigma_px: float  # the pixel sigma its last graph was whitened by
    estimated_sigma_px: float  # the images' sigma after it: given, or the robust estimate from its residuals
    error_evaluations: int | None  # numpy backend only
    graph: RigGraph  # (its last graph: uncertainty, the outlier re-run)
    solved: object | None  # the numpy backend's solved problem (None with gtsam)

    def record(self, observable_distance: bool = True) -> StageRecord:
        """Its figures for calibration.json ``stages``.

        Args:
            observable_distance: Whether the data observe the window distance (under water); in air it is
                null, as calibration.json's.

        Returns:
            The stage's model, residuals and parameters.
        """
        stats = residual_stats(r for _, r in self.residuals)
        state = self.state
        windows: tuple[StageWindow, ...] = ()
        if state.window_count > 1:  # every window: its normal and plane offset (from camera 0, the world's origin)
            offsets = [state.offset(w) for w in range(state.window_count)]
            windows = tuple(StageWindow(tuple(float(v) for v in state.normal(w)),
                                        None if offset is None or not observable_distance else float(offset))
                            for w, offset in enumerate(offsets))
        return StageRecord(
            self.stage.label, self.stage.model, bool(self.stage.distortion), stats.rmse_px, stats.max_px, stats.count,
            tuple(float(v) for v in state.normal_world),
            None if state.distance_mm is None or not observable_distance else float(state.distance_mm),
            {n: StageCamera(float(p[0]), float(p[1]), float(p[2]), float(p[3]),
                            tuple(float(v) for v in np.resize(p[4:9], 5))) for n, p in state.params.items()},
            windows)

    def report(self) -> OptimizerRun:
        """Its entry in the optimizer report.

        Returns:
            Time, backend, iterations, pixel sigma and (numpy backend) error evaluations: it stops at
            convergence without GTSAM's futile lambda trials.
        """
        return OptimizerRun(self.time_s, self.backend, self.iterations, self.sigma_px, self.error_evaluations)


def calibrate(dataset: Dataset | str | Path, model: str = DEFAULT_MODEL, extra_factors: ExtraFactors = None,
              options: CalibrationOptions | None = None, **overrides: object) -> Calibration:
    """Calibrate the cameras and the window of a dataset.

    Steps: options, load, plan (:func:`plan_stages`), then for each start of the quality gate
    (:func:`_starts`): initial state, the stages (:func:`run_stage`), the result; judged
    (:mod:`ari_sfm.calibration.quality`) until one passes.

    Args:
        dataset: The dataset, or its folder or rig file (corners detected when it has only images).
        model: "exact" (default, the best model): Snell's law at both faces, refined from the ari result, lens
            distortion estimated when the views support it (the ari stage's figures kept in ``stages``); "ari":
            the paper's paraxial model alone; the paper's baselines "rt" (ray tracing) and "pf" (polynomial),
            and "pinhole", "pinhole_dist" (window ignored): :mod:`ari_sfm.baselines`.
        extra_factors: gtsam factors on the graph's keys (:mod:`ari_sfm.factors.keys`; e.g.
            ``gtsam.PriorFactorUnit3(keys.N, ...)`` with a sigma in radians), or a callable taking each stage's
            :class:`~ari_sfm.factors.rig_graph.RigGraph` and returning them: they join every stage (ari, exact,
            the outlier re-run), the view factors whitened by the pixel sigma, so a prior weighs what its sigma
            says (docs/RESEARCH.md). Bundle-adjusted models only.
        options: The options (None: the defaults).
        overrides: Fields of :class:`CalibrationOptions` as keywords (``calibrate(ds, fix_intrinsics=True)``),
            replacing those of ``options``: the one place options are taken as keywords.

    Returns:
        The calibration, with its quality gate's verdict (bundle-adjusted models).

    Raises:
        TypeError: ``dataset`` is neither a Dataset nor a path; an unknown option keyword; ``options`` is not
            a CalibrationOptions.
        ValueError: an option's value (one line naming it); ``extra_factors`` with a baseline.
        AriSfmError: the data cannot be calibrated with this model (one line naming the file).
    """
    from ..factors.vectorized import resolve_backend
    from .quality import PARAXIAL_MODELS, corner_floor, fits, judge

    opts = _options(options, overrides)
    backend = resolve_backend(opts.backend.value)
    spec = model_spec(model, "model", calibratable=True)  # the models: ari_sfm.models.registry
    if not isinstance(dataset, Dataset):
        if not isinstance(dataset, (str, os.PathLike)):
            raise TypeError(f"calibrate needs a Dataset or a dataset folder's path (got {type(dataset).__name__})")
        from ..io import load_dataset

        dataset = load_dataset(dataset)
    dataset = ensure_observations(dataset, opts.workers, opts.progress)
    lens_retry = lens_on_misfit(dataset, model, opts)
    opts = replace(opts, distortion=resolve_distortion(dataset, model, opts))
    if not spec.bundle:
        if extra_factors is not None:
            raise ValueError(f"extra_factors need a factor-graph model (ari or exact), not {model!r}")
        return spec.calibrate(dataset, opts)
    plan = plan_stages(dataset, model, opts)
    t0 = time.perf_counter()
    tried: list[str] = []
    judged: list = []  # (Calibration with its quality)
    first_error: AriSfmError | None = None
    floor = corner_floor(dataset) if opts.quality else None  # the gate's yardstick: what the corners allow
    for start in _starts(dataset, model, opts, lens_retry):
        tried.append(start.name)
        try:
            cal, residuals, reached = _calibrate_from(_Solver(dataset, opts, backend, extra_factors), model, plan,
                                                      start)
            for _ in range(len(dataset.camera_names) if opts.principal_point is PrincipalPoint.AUTO else 0):
                loose = [n for n in undetermined_principal_points(cal) if n not in start.centred]
                if not loose:
                    break
                # what the data do not determine is held, and said so
                log.warning("principal point of %s held at the image centre: the views leave it undetermined (its "
                            "standard deviation above %g %% of the image; --principal-point free estimates it anyway)",
                            ", ".join(loose), 100 * PRINCIPAL_POINT_MAX_SIGMA)
                start = replace(start, centred=start.centred + tuple(loose))
                cal, residuals, reached = _calibrate_from(_Solver(dataset, opts, backend, extra_factors), model,
                                                          plan, start)
        except AriSfmError as exc:  # e.g. no window distance fits these poses: the next start may do better
            log.info("calibration from the %s start failed: %s", start.name, exc.message)
            first_error = first_error or exc
            continue
        if not opts.quality:
            return replace(cal, time_s=time.perf_counter() - t0)
        res = [r for _, r in residuals]
        exact_robust = None
        if model in PARAXIAL_MODELS and not fits(model, res, floor):  # its paraxial error, or a wrong window?
            exact_robust = _exact_robust_rmse(reached)
        assert cal.residuals is not None  # a bundle model's calibration has its residuals
        quality = judge(model, cal.residuals.rmse_px, res, floor, cal.uncertainty, tuple(tried), exact_robust)
        judged.append(replace(cal, quality=quality))
        if quality.ok:
            break
        log.warning("quality gate: the %s start gives a failed calibration (%s)", start.name, quality.why)
    if not judged:
        assert first_error is not None  # there is always a start (the default), and each failed
        raise first_error
    best = next((c for c in judged if c.quality.ok), None)
    if best is None:  # every start failed: the one of least robust RMSE, said to have failed
        best = min(judged, key=lambda c: (not math.isfinite(c.quality.robust_rmse_px), c.quality.robust_rmse_px))
        best = replace(best, quality=replace(best.quality, starts=tuple(tried)))
    return replace(best, time_s=time.perf_counter() - t0)


def _exact_robust_rmse(reached: _Reached) -> float | None:
    """The quality gate's re-evaluation of a paraxial result: the robust RMSE of the exact model's Snell
    stages run on from it, with the same window, hints and options; None when they cannot start there."""
    from .quality import robust_rmse_px

    solver = replace(reached.solver, opts=replace(reached.solver.opts, uncertainty=False))
    snell = tuple(stage for stage in _start_plan(reached.start, plan_stages(solver.dataset, "exact", solver.opts))
                  if stage.snell)
    try:
        results = _run_stages(solver, reached.rig, reached.state, snell, reached.start)
    except AriSfmError as exc:
        log.info("quality gate: no exact re-evaluation from the %s start (%s)", reached.start.name, exc.message)
        return None
    return robust_rmse_px(r for _, r in results[-1].residuals)


@dataclass(frozen=True)
class Start:
    """One way to start the bundle adjustment (the quality gate tries the next when a result fails)."""

    name: str
    held_hints: bool  # the analytic start holds what --fix-intrinsics holds (else K runs free in it)
    free_window_first: bool = False  # declared plane under water: exact fits a free window first (tilt and
    # distance searched), then the plane is placed by its poses
    centred: tuple[str, ...] = ()  # principal_point auto: cameras whose principal point is held at the image centre
    lens: bool = False  # lens distortion estimated (in the Snell stages) though the plan holds it
    eased_planes: bool = False  # each Snell stage solved first with the held declared planes as priors of
    # EASED_PLANE_DEG / EASED_PLANE_MM, then again held: a hold far stiffer than the images (1e-6 rad) keeps LM
    # in the basin of an ari stage gone wrong (test_cavity with OpenPTV's glass planes: 0.57 px, one camera's
    # focal length 45 % off; eased in, 0.49 px)
    lens_from_snell: bool = False  # lens distortion held at zero in the analytic start and the ari stages, left
    # to the Snell stage: a paraxial fit under water absorbs the window into free distortion (k1 +0.2..+0.36 from
    # one view of a 3D body), from which the exact stage of a 15 mm deep body ended 4-10 deg off (5 of 8 simulated
    # seeds); from this start all 8 reach the noise, but it lost one one-view particle rig the default calibrates:
    # a second start, not the default


def _corners(dataset: Dataset) -> tuple[Observation, ...]:
    """The dataset's observations, which calibrate gives it (:func:`ensure_observations`) before any start."""
    assert dataset.observations is not None
    return dataset.observations


def _starts(dataset: Dataset, model: str, opts: CalibrationOptions, lens_retry: bool = False) -> list[Start]:
    """The starts, in order: the default; a free window first (a declared plane under water, a Snell
    model); a held declared plane eased in (a Snell model); the hints free in the analytic start (with
    --fix-intrinsics); the lens left to the Snell stage (lens distortion estimated by a Snell model, or with
    ``lens_retry`` estimated there when the others fail: :func:`lens_on_misfit`)."""
    starts = [Start("default", opts.fix_intrinsics)]
    planes = any(w.interface.plane is not None for w in dataset.window_list())
    snell = model_spec(model).needs_distance
    if planes and dataset.medium_index != 1.0 and snell:
        starts.append(Start("free window", opts.fix_intrinsics, free_window_first=True))
    if snell and any(p is not None and (p.sigma_deg == 0 or p.sigma_mm == 0)
                     for p in (w.interface.plane for w in dataset.window_list())):
        starts.append(Start("declared plane eased in", opts.fix_intrinsics, eased_planes=True))
    if opts.fix_intrinsics:
        starts.append(Start("hints free in the start", False))
    if opts.distortion and snell:
        starts.append(Start("lens from the Snell stage", opts.fix_intrinsics, lens_from_snell=True))
    elif lens_retry and snell:
        starts.append(Start("lens distortion estimated", opts.fix_intrinsics, lens_from_snell=True, lens=True))
    return starts


@dataclass(frozen=True)
class _Solver:
    """What every stage of one calibration builds and solves its graphs with."""

    dataset: Dataset
    opts: CalibrationOptions
    backend: str
    extra_factors: ExtraFactors = None
    fixed: tuple[str, ...] = ()  # cameras whose K is held
    fixed_focal: dict[str, float] | None = None  # camera -> focal held as fx = fy
    centred: dict[str, tuple[float, float]] | None = None  # camera -> principal point held (its image centre)
    observed: tuple[bool, ...] | None = None  # per window: its normal observed by stacking (the start's)

    @property
    def planes(self) -> list[WindowPlane | None]:
        """Each window's declared plane (None where not declared)."""
        return [w.interface.plane for w in self.dataset.window_list()]

    @property
    def plane(self) -> WindowPlane | None:
        """Some window's declared plane (the first), None when no window declares one."""
        return next((p for p in self.planes if p is not None), None)

    @property
    def underwater(self) -> bool:
        return self.dataset.medium_index != 1.0

    @property
    def given_sigma(self) -> float:
        """The images' weight for a stage's first solve: the pixel sigma given, else 1 px."""
        return 1.0 if self.opts.sigma_px is None else float(self.opts.sigma_px)

    @property
    def reweight(self) -> bool:
        """A stage is re-solved with its estimated sigma when other factors (priors, a declared plane,
        the user's) share its graph."""
        return self.opts.sigma_px is None and (bool(self.fixed) or bool(self.fixed_focal) or bool(self.centred)
                                               or self.plane is not None
                                               or self.extra_factors is not None)

    def build(self, model: str, state, sigma: float, distortion: bool, observations=None, with_plane: bool = True):
        """The stage's RigGraph (:meth:`~ari_sfm.factors.rig_graph.RigGraph.build`) with the user's factors;
        ``distortion``: the stage's (k1 k2 p1 p2 k3 estimated, else held at the state's)."""
        from ..factors.rig_graph import RigGraph

        ds = self.dataset
        rg = RigGraph.build(
            _corners(ds) if observations is None else observations, ds.target, ds.interface, ds.camera_names,
            state, model=model, distortion=distortion, estimate_distance=self.underwater,
            huber_px=self.opts.huber_px, sigma_px=sigma, fixed_intrinsics=self.fixed,
            fixed_focal_px=self.fixed_focal, windows=ds.window_list(),
            window_planes=self.planes if with_plane else None, centred_principal_points=self.centred,
        )
        _add_factors(rg, self.extra_factors)
        return rg

    def solve(self, rg, model: str, max_iterations: int | None = None,
              relative_tolerance: float = FINAL_TOLERANCE):
        """(state, solved problem or None) of the graph; a failure inside the optimiser is one line."""
        from ..factors.vectorized import solve_graph

        if model_spec(model).needs_distance:
            check_in_front(self.dataset, rg.base_state)
        try:
            solution = solve_graph(rg, self.backend,
                                   self.opts.max_iterations if max_iterations is None else max_iterations,
                                   self.opts.huber_px, check=False,  # built with opts.huber_px
                                   relative_tolerance=relative_tolerance)
            return solution.state, solution.problem
        except RuntimeError as exc:  # e.g. non-finite Jacobian entries
            raise AriSfmError(self.dataset.observations_path or self.dataset.rig_path,
                              f"{model} stage: {exc}") from None


def _residuals_of(rg, solved) -> list:
    """From the numpy backend's solved problem (no Python callbacks); GTSAM's otherwise."""
    return solved.residuals() if solved is not None else rg.residuals()


def run_stage(solver: _Solver, stage: Stage, state: RigState, normal_observed: bool = True,
              relative_tolerance: float = FINAL_TOLERANCE) -> StageResult:
    """One stage from ``state``: its start (a Snell stage's distance, and normal without stacking), the
    solve, the declared normal's rounds (held normal), the re-solve at the estimated pixel sigma.

    Args:
        solver: What the calibration's graphs are built and solved with (dataset, options, backend, the held
            intrinsics).
        stage: The stage.
        state: The state it starts from.
        normal_observed: Whether stacking observes the window normal (when the solver does not say per window).
        relative_tolerance: Each solve stops when the error's relative decrease is below this.

    Returns:
        The state after the stage, its residuals and how its solves went.

    Raises:
        AriSfmError: the optimiser failed (e.g. non-finite Jacobian entries) or no window distance fits.
    """
    from ..factors.window_plane import plane_in_world
    from .outliers import robust_sigma_px

    planes = solver.planes
    sigma = solver.given_sigma
    # (Not started at the previous stage's sigma estimate: GTSAM's LM damping is absolute, and an ari stage far
    # off under water left the exact stage 100 iterations from converging.)
    if stage.with_plane:  # each declared window, placed by the current pose of its frame
        for w, plane in enumerate(planes):
            if plane is not None:
                n_w, h_w = plane_in_world(plane, state.world_from_target[plane.frame])
                state = state.with_window(w, n_w, h_w if solver.underwater else "keep")

    def build(model: str, st, with_plane: bool = True, observations=None):
        return solver.build(model, st, sigma, stage.distortion, observations, with_plane=with_plane)

    observed = solver.observed if solver.observed is not None else [normal_observed] * len(planes)
    if stage.snell:
        stage_planes = planes if stage.with_plane else [None] * len(planes)
        unobserved = [w for w in range(len(planes)) if not observed[w] and stage_planes[w] is None]
        state = exact_start(solver.dataset, state, solver.underwater, stage_planes, unobserved, build, solver.solve,
                            solver.opts.huber_px)
    held = [w for w in range(len(planes)) if not observed[w]]  # the ari model cannot observe them here
    graph = build(stage.model, state, with_plane=stage.with_plane)
    if stage.hold_normal:
        hold_normals(graph, state, held)
    t_stage = time.perf_counter()
    state, solved = solver.solve(graph, stage.model, relative_tolerance=relative_tolerance)
    placed = [w for w in held if planes[w] is not None]
    for _ in range(PLANE_ROUNDS if stage.hold_normal and placed else 0):
        # hold the declared normals as placed by their frames' refitted poses, until they stop moving
        moved = state
        for w in placed:
            plane = planes[w]
            assert plane is not None  # placed: declared
            moved = moved.with_window(w, plane_in_world(plane, state.world_from_target[plane.frame])[0])
        if max(angle_between_deg(moved.normal(w), state.normal(w)) for w in placed) < 1e-3:
            break
        graph = build(stage.model, moved, with_plane=False)
        hold_normals(graph, moved, held)
        state, solved = solver.solve(graph, stage.model, relative_tolerance=relative_tolerance)
    n_iterations = graph.iterations
    residuals = _residuals_of(graph, solved)
    if solver.opts.sigma_px is None:
        estimated = robust_sigma_px(r for _, r in residuals)
        if solver.reweight and abs(estimated / sigma - 1.0) > 1e-3:
            sigma = estimated
            graph = build(stage.model, state, with_plane=stage.with_plane)
            if stage.hold_normal:
                hold_normals(graph, state, held)
            state, solved = solver.solve(graph, stage.model, relative_tolerance=relative_tolerance)
            n_iterations += graph.iterations
            residuals = _residuals_of(graph, solved)
        sigma = estimated
    result = StageResult(stage, state, residuals, n_iterations, time.perf_counter() - t_stage, solver.backend,
                         graph.sigma_px, sigma, None if solved is None else solved.report.error_evaluations,
                         graph, solved)
    log.info("%s bundle adjustment: %d iterations, %.3f s%s", stage.label, n_iterations, result.time_s,
             f", window distance {state.distance_mm:.1f} mm" if solver.underwater and state.distance_mm is not None
             else "")
    return result


def _start_state(solver: _Solver, plan: tuple[Stage, ...], start: Start):
    """(analytic initialisation, the solver with the held intrinsics, the initial state) of one start."""
    from ..factors.rig_graph import held_intrinsics, initial_state
    from ..init.rig import initialise_rig

    dataset, opts = solver.dataset, solver.opts
    centred = centred_principal_points(dataset, opts, start.centred)
    rig = initialise_rig(dataset, plan[0].distortion, opts.workers, start.held_hints, frozenset(centred))
    fixed, fixed_focal = held_intrinsics(dataset, opts.fix_intrinsics)
    solver = replace(solver, fixed=tuple(fixed), fixed_focal=fixed_focal, observed=tuple(rig.normals_observed),
                     centred=centred)
    state = initial_state(dataset, rig, plan[0].model, opts.fix_intrinsics)
    for name, (cx, cy) in centred.items():  # start where it is held
        state.params[name][2:4] = cx, cy
    return rig, solver, state


def _eased(solver: _Solver) -> _Solver:
    """``solver`` with every held part of a declared plane a prior of EASED_PLANE_DEG / EASED_PLANE_MM instead."""
    def ease(interface: Interface) -> Interface:
        p = interface.plane
        if p is None:
            return interface
        return replace(interface, plane=replace(p, sigma_deg=p.sigma_deg or EASED_PLANE_DEG,
                                                sigma_mm=p.sigma_mm or EASED_PLANE_MM))

    ds = solver.dataset
    if ds.windows:
        eased = replace(ds, windows=tuple(replace(w, interface=ease(w.interface)) for w in ds.windows))
    else:
        eased = replace(ds, interface=ease(ds.interface))
    return replace(solver, dataset=eased)


@dataclass(frozen=True)
class _Reached:
    """Where a plan's run from one start ended: the quality gate's exact re-evaluation goes on from there."""

    solver: _Solver  # with the start's held intrinsics
    rig: RigInit  # the analytic initialisation
    state: RigState  # after the last stage
    start: Start


def _start_plan(start: Start, plan: tuple[Stage, ...]) -> tuple[Stage, ...]:
    """The plan as ``start`` runs it (lens_from_snell: distortion only in the Snell stages)."""
    if not start.lens_from_snell:
        return plan
    return tuple(replace(stage, distortion=stage.distortion or start.lens) if stage.snell
                 else replace(stage, distortion=False) for stage in plan)


def _run_stages(solver: _Solver, rig: RigInit, state: RigState, plan: tuple[Stage, ...], start: Start
                ) -> list[StageResult]:
    """The plan's stages from ``state``, in order (a skippable one left out where the declared plane
    already separates cameras and corners; with eased planes, each Snell stage first eased in)."""
    results: list[StageResult] = []
    for stage in plan:
        if stage.skippable and not start.free_window_first and planes_separate(solver.dataset, solver.planes,
                                                                               state):
            log.info("%s stage skipped: the declared plane at the ari poses separates cameras and corners", stage.label)
            continue
        if start.eased_planes and stage.snell and stage.with_plane:
            state = run_stage(_eased(solver), stage, state, rig.normal_observed, stage_tolerance(stage, plan)).state
        results.append(run_stage(solver, stage, state, rig.normal_observed, stage_tolerance(stage, plan)))
        state = results[-1].state
    return results


def _calibrate_from(solver: _Solver, model: str, plan: tuple[Stage, ...], start: Start
                    ) -> tuple[Calibration, list, _Reached]:
    """The plan's bundle adjustments from ``start``: the calibration, its (observation, residuals) and
    where it ended."""
    from .outliers import find_outliers, without

    t0 = time.perf_counter()
    plan = _start_plan(start, plan)
    if start.lens:
        log.warning("lens distortion estimated: without it the model fits the corners worse than they allow")
    rig, solver, state = _start_state(solver, plan, start)
    dataset, opts = solver.dataset, solver.opts
    results = _run_stages(solver, rig, state, plan, start)
    state = results[-1].state
    last = results[-1]
    outliers, robust_sigma = find_outliers(last.residuals, opts.outlier_sigma)
    if outliers and opts.exclude_outliers:
        log.info("excluding %d outlier corners and re-running the %s stage", len(outliers), last.stage.model)
        kept = without(_corners(dataset), outliers)
        seen = {o.frame for o in kept if o.set in ("calibration", "stacking") and len(o.ids) >= 4}
        lost = sorted(set(state.world_from_target) - seen)
        if lost:  # every corner of these frames was an outlier: nothing places them any more
            log.warning("frame(s) %s left out: all their corners were outliers", ", ".join(lost))
            state = replace(state, world_from_target={f: p for f, p in state.world_from_target.items() if f in seen})
        graph = solver.build(last.stage.model, state, last.estimated_sigma_px, last.stage.distortion, kept,
                             with_plane=last.stage.with_plane)
        state, solved = solver.solve(graph, last.stage.model)
        # the optimizer report keeps the stage's own solve; the stage's figures are those after the re-run
        last = replace(last, state=state, graph=graph, solved=solved, residuals=_residuals_of(graph, solved))
        results[-1] = last
    if outliers:
        # With the paraxial ari model, large residuals are mostly its own error at oblique rays.
        level = logging.WARNING if last.stage.snell else logging.INFO
        log.log(level, "%d corners beyond %.0f sigma (%.3f px) after convergence%s", len(outliers), opts.outlier_sigma,
                robust_sigma, " (excluded)" if opts.exclude_outliers else "")
    elapsed = time.perf_counter() - t0
    uncertainty = None
    if opts.uncertainty:
        from ..factors.uncertainty import marginal_covariances, rig_uncertainty

        # physical units: the graph's view factors carry the pixel sigma (rescaled to the last estimate
        # when only view factors share the graph)
        rescale = None if solver.reweight or opts.sigma_px is not None else last.estimated_sigma_px
        uncertainty = rig_uncertainty(last.graph, marginal_covariances(last.graph, last.solved, rescale), rescale)
    outlier_report = OutlierReport(robust_sigma, opts.outlier_sigma, opts.exclude_outliers, tuple(outliers))
    return (_assemble(solver, model, rig, results, uncertainty, elapsed, outlier_report), last.residuals,
            _Reached(solver, rig, state, start))


def _assemble(solver: _Solver, model: str, rig, results: list[StageResult], uncertainty, elapsed: float,
              outliers: OutlierReport) -> Calibration:
    """The Calibration of the last stage's state, with every stage's figures and the optimizer report."""
    from ..factors.window_plane import plane_in_world

    dataset, last = solver.dataset, results[-1]
    state, residuals = last.state, last.residuals
    cameras = {}
    for n in dataset.camera_names:
        p = state.params[n]
        K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
        ec = rig.cameras[n].expansion
        cameras[n] = CameraCalibration(
            n, cast("tuple[int, int]", tuple(dataset.cameras[n].image_size)), K, p[4:9].copy(), state.cam_from_world[n],
            None if ec is None else ec.center_px, None if ec is None else ec.std_px,
            residual_stats(r for o, r in residuals if o.camera == n).rmse_px,
        )
    windows = []
    for w, (window, plane) in enumerate(zip(dataset.window_list(), solver.planes)):
        offset = state.offset(w) if solver.underwater else None  # unobservable in air: null
        if plane is not None:  # declared: known in air too
            offset = plane_in_world(plane, state.world_from_target[plane.frame])[1]
        # calibration.json gives distances from the window's first camera's centre (camera 0, the origin, for one)
        reference = float(state.normal(w) @ state.cam_from_world[window.cameras[0]].inverse().t)
        distance = None if offset is None else offset - reference
        # exact in air: any distance gives the same rays; the one it was fitted at (a declared plane gives it)
        fixed = None
        if model_spec(model).needs_distance and distance is None:
            fitted = state.offset(w)
            assert fitted is not None  # a Snell model's state has every window's offset
            fixed = fitted - reference
        iface = window.interface
        windows.append(WindowCalibration(window.name, Interface(iface.thickness_mm, iface.index, iface.medium_index,
                                                                distance), state.normal(w), window.cameras, fixed))
    calib_frames = {o.frame for o in dataset.select("calibration")}
    return Calibration(
        model=model,
        interface=windows[0].interface,
        normal_world=windows[0].normal_world,
        cameras=cameras,
        frames={f: p for f, p in state.world_from_target.items() if f in calib_frames},
        stacking_poses={f: p for f, p in state.world_from_target.items() if f in rig.stacking_poses},
        residuals=residual_stats(r for _, r in residuals),
        time_s=elapsed,
        optimizer=OptimizerReport({r.stage.label: r.report() for r in results}),
        stages=tuple(r.record(solver.underwater) for r in results),
        target=dataset.target,
        fixed_distance_mm=windows[0].fixed_distance_mm,
        uncertainty=uncertainty,
        outliers=outliers,
        windows=tuple(windows) if dataset.windows else (),
    )

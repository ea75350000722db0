"""calibrate(): analytical initialisation, then the GTSAM bundle adjustment."""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from .calibration import Calibration, CameraCalibration
from .errors import AriSfmError
from .evaluate import residual_stats
from .geometry import angle_between_deg
from .models.registry import model_spec
from .records import Dataset, Interface, WindowPlane
from .results import OutlierReport

log = logging.getLogger(__name__)

PLANE_ROUNDS = 5  # ari rounds holding the declared normal at its frame's refitted pose (no stacking)
DEFAULT_MODEL = "exact"  # the best model: Snell's law refined from the ari stage (distortion: resolve_distortion)
DISTORTION_MIN_VIEWS = 6  # calibration views per camera below which lens distortion is not estimated by default
DISTORTION_MIN_COVERAGE = 0.2  # fraction of a camera's image inside the convex hull of its corners, likewise


@dataclass(frozen=True)
class CalibrationOptions:
    """Options of :func:`calibrate`, each with its default."""

    distortion: bool | None = None  # estimate k1 k2 p1 p2 k3; None: for the exact model when the views support
    # it (distortion_support), else off; False: they stay as given (normally zero)
    huber_px: float | None = 1.0  # per-corner Huber threshold in px; None: plain least squares
    outlier_sigma: float = 5.0  # corners beyond this many sigma after convergence are reported
    exclude_outliers: bool = False  # drop those corners and re-run the last stage
    fix_intrinsics: bool = False  # hold the rig.yaml hints: K (and dist) where K is given; fx = fy = focal_px
    # (principal point free) where only focal_px is
    max_iterations: int = 100  # Levenberg-Marquardt iterations per stage
    backend: str = "auto"  # bundle adjustment solver: "numpy" (vectorised, GTSAM's LM path), "gtsam", "auto" (= numpy)
    workers: int | None = None  # threads for corner detection (dataset with only images) and for the per-camera
    # analytic initialisation; None: os.cpu_count() (at most one per camera for the initialisation)
    progress: bool = False  # progress bars (the CLI turns them on)
    uncertainty: bool = True  # standard deviations of every parameter (marginal covariances, physical units)
    sigma_px: float | None = None  # the corners' pixel sigma weighting the images; None: estimated (robust,
    # from each stage's residuals; the stage is re-solved with it when priors or extra factors share the graph)
    quality: bool = True  # judge the result (ari_sfm.quality) and, when it fails, re-try from the other starts

    def __post_init__(self) -> None:
        """Refuse values that would fail deep inside the solver (huber_px -1 gave 'non-finite Jacobian')."""
        import math

        if self.huber_px is not None and not (math.isfinite(self.huber_px) and self.huber_px > 0):
            raise ValueError(f"huber_px must be a finite number > 0, or None (got {self.huber_px})")
        if not (math.isfinite(self.outlier_sigma) and self.outlier_sigma > 0):
            raise ValueError(f"outlier_sigma must be a finite number > 0 (got {self.outlier_sigma})")


def _options(options: CalibrationOptions | None, overrides: dict) -> CalibrationOptions:
    """``options`` (default: the defaults) with the keyword ``overrides`` applied."""
    names = {f.name for f in fields(CalibrationOptions)}
    unknown = set(overrides) - names
    if unknown:
        raise TypeError(f"unknown calibrate option(s): {', '.join(sorted(unknown))} (known: {', '.join(sorted(names))})")
    if options is None:
        return CalibrationOptions(**overrides)
    if not isinstance(options, CalibrationOptions):
        raise TypeError(f"options must be a CalibrationOptions (got {type(options).__name__})")
    return replace(options, **overrides)


def distortion_support(dataset: Dataset) -> str | None:
    """Why the dataset's views cannot support estimating lens distortion (k1 k2 p1 p2 k3), or None
    when they can: every camera needs DISTORTION_MIN_VIEWS calibration views and corners whose convex
    hull covers DISTORTION_MIN_COVERAGE of its image (distortion grows toward the edges), and the
    dataset stacking poses (without them the exact model finds the window normal through refraction
    alone, and free distortion absorbs part of it: simulated single camera 0.38 deg instead of 0.08;
    under water, oblique, the fit diverged)."""
    import cv2

    if not dataset.select("stacking"):
        return ("the dataset has no stacking poses: the window normal is then found through refraction alone, "
                "which free distortion would absorb (--distortion estimates it anyway)")
    for name in dataset.camera_names:
        views = dataset.select("calibration", name)
        frames = {o.frame for o in views if len(o.ids)}
        if len(frames) < DISTORTION_MIN_VIEWS:
            return (f"{name} has {len(frames)} calibration view{'s' * (len(frames) != 1)} "
                    f"(at least {DISTORTION_MIN_VIEWS} needed)")
        pixels = np.concatenate([o.pixels for o in views if len(o.ids)]).astype(np.float32)
        w, h = dataset.cameras[name].image_size
        coverage = float(cv2.contourArea(cv2.convexHull(pixels))) / float(w * h)
        if coverage < DISTORTION_MIN_COVERAGE:
            return (f"{name}'s corners cover {100 * coverage:.0f} % of its image (at least "
                    f"{100 * DISTORTION_MIN_COVERAGE:.0f} % needed: add views near its edges)")
    return None


def resolve_distortion(dataset: Dataset, model: str, opts: CalibrationOptions) -> bool:
    """``opts.distortion`` as given, or (None) estimated for the exact model when the views support
    it and no intrinsics are held; when they do not, one log line says why."""
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
    return True


def ensure_observations(dataset: Dataset, workers: int | None = None, progress: bool = False) -> Dataset:
    """The dataset with observations, detecting corners in its images when it has none."""
    if dataset.observations is not None:
        return dataset
    from .detection import detect_dataset

    return dataset.with_observations(detect_dataset(dataset, workers=workers, progress=progress))


def _add_factors(graph, extra_factors) -> None:
    """Push a user's factors (a sequence, or a callable of the RigGraph returning them) onto a stage's graph."""
    if extra_factors is None:
        return
    factors = extra_factors(graph) if callable(extra_factors) else extra_factors
    for f in factors:
        graph.graph.push_back(f)


def calibrate(dataset: Dataset | str | Path, model: str = DEFAULT_MODEL, extra_factors=None,
              options: CalibrationOptions | None = None, **overrides) -> Calibration:
    """Calibrate the cameras and the window of a dataset.

    model "exact" (default, the best model): Snell's law at both faces, refined from the ari
    result, with lens distortion estimated when the views support it (``distortion`` None; the
    ari stage's figures are kept in ``extra["stages"]``); "ari": the paper's paraxial model alone
    (analytic initialisation + bundle adjustment);
    the paper's baselines "rt" (ray tracing) and "pf" (polynomial), and "pinhole",
    "pinhole_dist" (window ignored): see :mod:`ari_sfm.baselines`.
    Options: a :class:`CalibrationOptions` as ``options=``, and/or its fields as keywords
    (``calibrate(ds, fix_intrinsics=True)``), which override ``options``.

    ``extra_factors``: gtsam factors on the graph's keys (:mod:`ari_sfm.factors.keys`; e.g.
    ``gtsam.PriorFactorUnit3(keys.N, ...)`` with a sigma in radians), or a callable taking each
    stage's :class:`~ari_sfm.factors.rig_graph.RigGraph` and returning them: they join every
    stage (ari, exact, the outlier re-run), the view factors being whitened by the pixel sigma,
    so a prior weighs what its sigma says (docs/RESEARCH.md).
    """
    from .factors.vectorized import resolve_backend
    from .quality import judge, pinhole_dist_rmse_px

    opts = _options(options, overrides)
    backend = resolve_backend(opts.backend)
    spec = model_spec(model, "model", calibratable=True)  # the models: ari_sfm.models.registry
    if not isinstance(dataset, Dataset):
        from .io import load_dataset

        dataset = load_dataset(dataset)
    dataset = ensure_observations(dataset, opts.workers, opts.progress)
    opts = replace(opts, distortion=resolve_distortion(dataset, model, opts))
    if not spec.bundle:
        if extra_factors is not None:
            raise ValueError(f"extra_factors need a factor-graph model (ari or exact), not {model!r}")
        return spec.calibrate(dataset, opts)
    t0 = time.perf_counter()
    tried: list[str] = []
    judged: list = []  # (Calibration with its quality)
    first_error = None
    pinhole = None
    for start in _starts(dataset, model, opts):
        tried.append(start.name)
        try:
            cal, residuals = _calibrate_from(dataset, model, extra_factors, opts, backend, start)
        except AriSfmError as exc:  # e.g. no window distance fits these poses: the next start may do better
            log.info("calibration from the %s start failed: %s", start.name, exc.message)
            first_error = first_error or exc
            continue
        if not opts.quality:
            return replace(cal, time_s=time.perf_counter() - t0)
        if pinhole is None:
            pinhole = (pinhole_dist_rmse_px(dataset),)
        quality = judge(model, cal.residuals.rmse_px, (r for _, r in residuals), pinhole[0], cal.uncertainty, tuple(tried))
        judged.append(replace(cal, quality=quality))
        if quality.ok:
            break
        log.warning("quality gate: the %s start gives a failed calibration (%s)", start.name, quality.why)
    if not judged:
        raise first_error
    best = next((c for c in judged if c.quality.ok), None)
    if best is None:  # every start failed: the one of least robust RMSE, said to have failed
        best = min(judged, key=lambda c: (not math.isfinite(c.quality.robust_rmse_px), c.quality.robust_rmse_px))
        best = replace(best, quality=replace(best.quality, starts=tuple(tried)))
    return replace(best, time_s=time.perf_counter() - t0)


@dataclass(frozen=True)
class Start:
    """One way to start the bundle adjustment (the quality gate tries the next when a result fails)."""

    name: str
    held_hints: bool  # the analytic start holds what --fix-intrinsics holds (else K runs free in it)
    free_window_first: bool = False  # declared plane under water: exact fits a free window first (tilt and
    # distance searched), then the plane is placed by its poses


def _starts(dataset: Dataset, model: str, opts: CalibrationOptions) -> list[Start]:
    """The starts, in order: the default; a free window first (a declared plane under water, exact);
    the hints free in the analytic start (with --fix-intrinsics)."""
    starts = [Start("default", opts.fix_intrinsics)]
    iface = dataset.interface
    if iface.plane is not None and iface.medium_index != 1.0 and model == "exact":
        starts.append(Start("free window", opts.fix_intrinsics, free_window_first=True))
    if opts.fix_intrinsics:
        starts.append(Start("hints free in the start", False))
    return starts


def _calibrate_from(dataset: Dataset, model: str, extra_factors, opts: CalibrationOptions, backend: str,
                    start: Start) -> tuple[Calibration, list]:
    """One bundle adjustment of ``model`` from ``start``: the calibration and its (observation, residuals)."""
    from .init.rig import NO_NORMAL_MESSAGE, initialise_rig
    from .factors.rig_graph import RigGraph, RigState, default_distance_mm
    from .factors.vectorized import optimize_graph
    from .factors.window_plane import plane_in_world

    t0 = time.perf_counter()
    rig = initialise_rig(dataset, opts.distortion, opts.workers, start.held_hints)
    iface = dataset.interface
    names = dataset.camera_names
    underwater = iface.medium_index != 1.0
    plane = _declared_plane(dataset, rig)
    unobserved = not rig.normal_observed and plane is None  # no stacking, no declared window
    if unobserved and model == "ari":
        raise AriSfmError(dataset.rig_path, NO_NORMAL_MESSAGE)
    state = RigState.from_initialisation(rig, iface.distance_mm)
    if plane is not None:  # the declared window is the start (and, held or with its prior, the result)
        n_w, h_w = plane_in_world(plane, state.world_from_target[plane.frame])
        state = replace(state, normal_world=n_w, distance_mm=h_w)
    elif state.distance_mm is None and underwater:
        state = replace(state, distance_mm=default_distance_mm(state.normal_world, state.cam_from_world))
    fixed, fixed_focal = _held_intrinsics(dataset, opts.fix_intrinsics)
    for n in fixed:  # start from the hint exactly
        hint = dataset.cameras[n]
        state.params[n][:4] = [hint.K[0, 0], hint.K[1, 1], hint.K[0, 2], hint.K[1, 2]]
        state.params[n][4:] = np.resize(hint.dist if hint.dist is not None else np.zeros(5), 5)
    for n, f in fixed_focal.items():
        state.params[n][:2] = f
    # (label, model, normal held at its start, declared plane in the graph)
    # Under water the ari poses can be far off along the normal, so a plane placed by its frame's ari
    # pose can put the window behind the cameras: then exact places it by its own poses ("exact_free"
    # first; skipped when the plane placed by the ari poses separates every camera from its corners).
    placed_by_exact = plane is not None and underwater and model == "exact"
    stages = [("ari", "ari", False, plane is not None and not placed_by_exact)]
    if not rig.normal_observed:  # no stacking: ari with the normal held at its start gives K and the poses
        stages = [("ari" if plane is None else "ari_normal_held", "ari", True, False)]
        if plane is not None and model == "ari":
            stages.append(("ari", "ari", False, True))
    if placed_by_exact:
        stages.append(("exact_free", "exact", False, False))
    if model == "exact":
        stages.append(("exact", "exact", False, plane is not None))

    # the images' weight: the pixel sigma, given, or 1 px for a stage's first solve and then estimated from
    # its residuals; a stage is re-solved with the estimate when other factors (priors, a declared plane,
    # the user's) share its graph. (Not started at the previous stage's estimate: GTSAM's LM damping is
    # absolute, and an ari stage far off under water left the exact stage 100 iterations from converging.)
    given_sigma = 1.0 if opts.sigma_px is None else float(opts.sigma_px)
    sigma = given_sigma
    reweight = opts.sigma_px is None and (bool(fixed) or bool(fixed_focal) or plane is not None
                                          or extra_factors is not None)

    def build(stage: str, st: RigState, observations=dataset.observations, with_plane: bool = True) -> RigGraph:
        rg = RigGraph.build(
            observations, dataset.target, iface, names, st, model=stage, distortion=opts.distortion,
            estimate_distance=underwater, huber_px=opts.huber_px, sigma_px=sigma, fixed_intrinsics=fixed,
            fixed_focal_px=fixed_focal, window_plane=plane if with_plane else None,
        )
        _add_factors(rg, extra_factors)
        return rg

    def solve(rg: RigGraph, stage: str, max_iterations: int = opts.max_iterations):
        if stage == "exact":
            _check_in_front(dataset, rg.base_state)
        try:
            return optimize_graph(rg, backend, max_iterations, opts.huber_px, return_problem=True,
                                  check=False)  # the graph was just built with opts.huber_px
        except RuntimeError as exc:  # a failure inside the optimiser (e.g. non-finite Jacobian entries): one line
            raise AriSfmError(dataset.observations_path or dataset.rig_path, f"{stage} stage: {exc}") from None

    from .outliers import find_outliers, robust_sigma_px, without

    def residuals_of(rg: RigGraph, solved) -> list:
        # from the numpy backend's solved problem (no Python callbacks); GTSAM's otherwise
        return solved.residuals() if solved is not None else rg.residuals()

    graph = None
    iterations = {}
    from .init.window_start import not_beyond

    stages_done: list[dict] = []  # each stage's model and figures (calibration.json "stages")
    for label, stage, hold_normal, with_plane in stages:
        sigma = given_sigma
        if label == "exact_free" and not start.free_window_first:
            n_w, h_w = plane_in_world(plane, state.world_from_target[plane.frame])
            if not_beyond(replace(state, normal_world=n_w, distance_mm=h_w), dataset.observations, dataset.target,
                          iface.thickness_mm) is None:
                log.info("exact_free stage skipped: the declared plane at the ari poses separates cameras and corners")
                continue
        if with_plane:  # the declared window, placed by the current pose of its frame
            n_w, h_w = plane_in_world(plane, state.world_from_target[plane.frame])
            state = replace(state, normal_world=n_w, distance_mm=h_w if underwater else state.distance_mm)
        if stage == "exact":
            stage_plane = plane if with_plane else None
            state = _exact_start(dataset, state, underwater, stage_plane,
                                 not rig.normal_observed and stage_plane is None, build, solve, opts)
        graph = build(stage, state, with_plane=with_plane)
        if hold_normal:  # the ari model cannot observe it here
            _hold_normal(graph, state.normal_world)
        t_stage = time.perf_counter()
        state, solved = solve(graph, stage)
        for _ in range(PLANE_ROUNDS if hold_normal and plane is not None else 0):
            # hold the declared normal as placed by its frame's refitted pose, until that stops moving
            n_w = plane_in_world(plane, state.world_from_target[plane.frame])[0]
            if angle_between_deg(n_w, state.normal_world) < 1e-3:
                break
            graph = build(stage, replace(state, normal_world=n_w), with_plane=False)
            _hold_normal(graph, n_w)
            state, solved = solve(graph, stage)
        n_iterations = graph.iterations
        residuals = residuals_of(graph, solved)
        if opts.sigma_px is None:
            estimated = robust_sigma_px(r for _, r in residuals)
            if reweight and abs(estimated / sigma - 1.0) > 1e-3:
                sigma = estimated
                graph = build(stage, state, with_plane=with_plane)
                if hold_normal:
                    _hold_normal(graph, state.normal_world)
                state, solved = solve(graph, stage)
                n_iterations += graph.iterations
                residuals = residuals_of(graph, solved)
            sigma = estimated
        stages_done.append(_stage_record(label, stage, state, residuals, opts.distortion))
        iterations[label] = {"iterations": n_iterations, "time_s": time.perf_counter() - t_stage, "backend": backend,
                             "sigma_px": graph.sigma_px}
        if solved is not None:  # numpy backend: it stops at convergence without GTSAM's futile lambda trials
            iterations[label]["error_evaluations"] = solved.report.error_evaluations
        log.info("%s bundle adjustment: %d iterations, %.3f s, window distance %s mm", label, n_iterations,
                 iterations[label]["time_s"], None if state.distance_mm is None else f"{state.distance_mm:.1f}")
    last_stage, last_plane = stages[-1][1], stages[-1][3]
    outliers, robust_sigma = find_outliers(residuals, opts.outlier_sigma)
    if outliers and opts.exclude_outliers:
        log.info("excluding %d outlier corners and re-running the %s stage", len(outliers), last_stage)
        graph = build(last_stage, state, without(dataset.observations, outliers), with_plane=last_plane)
        state, solved = solve(graph, last_stage)
        residuals = residuals_of(graph, solved)
        stages_done[-1] = _stage_record(stages[-1][0], last_stage, state, residuals, opts.distortion)
    if outliers:
        # With the paraxial ari model, large residuals are mostly its own error at oblique rays.
        level = logging.INFO if last_stage == "ari" else logging.WARNING
        log.log(level, "%d corners beyond %.0f sigma (%.3f px) after convergence%s", len(outliers), opts.outlier_sigma,
                robust_sigma, " (excluded)" if opts.exclude_outliers else "")
    elapsed = time.perf_counter() - t0
    uncertainty = None
    if opts.uncertainty:
        from .factors.uncertainty import marginal_covariances, rig_uncertainty

        # physical units: the graph's view factors carry the pixel sigma (rescaled to the last estimate
        # when only view factors share the graph)
        rescale = None if reweight or opts.sigma_px is not None else sigma
        uncertainty = rig_uncertainty(graph, marginal_covariances(graph, solved, rescale), rescale)
    cameras = {}
    for n in names:
        p = state.params[n]
        K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
        ec = rig.cameras[n].expansion
        cameras[n] = CameraCalibration(
            n, tuple(dataset.cameras[n].image_size), K, p[4:9].copy(), state.cam_from_world[n],
            None if ec is None else ec.center_px, None if ec is None else ec.std_px,
            residual_stats(r for o, r in residuals if o.camera == n).rmse_px,
        )
    distance = state.distance_mm if underwater else None  # unobservable in air: null
    if plane is not None:  # declared: known in air too
        distance = plane_in_world(plane, state.world_from_target[plane.frame])[1]
    calib_frames = {o.frame for o in dataset.select("calibration")}
    return Calibration(
        model=model,
        interface=Interface(iface.thickness_mm, iface.index, iface.medium_index, distance),
        normal_world=state.normal_world,
        cameras=cameras,
        frames={f: p for f, p in state.world_from_target.items() if f in calib_frames},
        stacking_poses={f: p for f, p in state.world_from_target.items() if f in rig.stacking_poses},
        residuals=residual_stats(r for _, r in residuals),
        time_s=elapsed,
        extra={"optimizer": iterations, "stages": stages_done},
        target=dataset.target,
        # exact in air: any distance gives the same rays; the one it was fitted at (a declared plane gives it)
        fixed_distance_mm=state.distance_mm if model == "exact" and distance is None else None,
        uncertainty=uncertainty,
        outliers=OutlierReport(robust_sigma, opts.outlier_sigma, opts.exclude_outliers, tuple(outliers)),
    ), residuals


def _stage_record(label: str, model: str, state, residuals, distortion: bool) -> dict:
    """One stage's figures for calibration.json ``stages``: its model, residuals and parameters."""
    stats = residual_stats(r for _, r in residuals)
    return {
        "stage": label, "model": model, "distortion": bool(distortion),
        "rmse_px": stats.rmse_px, "max_px": stats.max_px, "count": stats.count,
        "normal_world": np.asarray(state.normal_world, float).tolist(),
        "distance_mm": None if state.distance_mm is None else float(state.distance_mm),
        "cameras": {n: {"fx": float(p[0]), "fy": float(p[1]), "cx": float(p[2]), "cy": float(p[3]),
                        "dist": [float(v) for v in np.resize(p[4:9], 5)]} for n, p in state.params.items()},
    }


def _hold_normal(rg, normal: np.ndarray) -> None:
    """Hold the graph's normal at ``normal`` (a prior of 1e-7 rad)."""
    import gtsam

    from .factors import keys as K_

    rg.graph.push_back(gtsam.PriorFactorUnit3(K_.N, gtsam.Unit3(np.asarray(normal, float)),
                                              gtsam.noiseModel.Isotropic.Sigma(2, 1e-7)))


def _declared_plane(dataset: Dataset, rig) -> WindowPlane | None:
    """interface.plane, checked: its frame must be a calibration frame seen by a camera."""
    plane = dataset.interface.plane
    if plane is None:
        return None
    calib = {o.frame for o in dataset.select("calibration")}
    if plane.frame not in calib or plane.frame not in rig.world_from_target:
        known = ", ".join(sorted(calib)[:5]) + (", ..." if len(calib) > 5 else "")
        raise AriSfmError(dataset.rig_path, f"interface.plane.frame: {plane.frame!r} is not a calibration frame "
                                            f"seen by the cameras (calibration frames: {known or 'none'})")
    return plane


def _held_intrinsics(dataset: Dataset, fix: bool) -> tuple[list[str], dict[str, float]]:
    """Cameras whose K is held (a K hint) and camera -> focal held as fx = fy (a focal_px hint only)."""
    if not fix:
        return [], {}
    cams = dataset.cameras
    fixed = [n for n in dataset.camera_names if cams[n].K is not None]
    focal = {n: float(cams[n].focal_px) for n in dataset.camera_names if cams[n].K is None and cams[n].focal_px is not None}
    if not fixed and not focal:
        raise AriSfmError(dataset.rig_path, "fix_intrinsics needs a K or focal_px hint for at least one camera "
                                            "(cameras.<name>.K or cameras.<name>.focal_px)")
    return fixed, focal


def _exact_start(dataset: Dataset, state, underwater: bool, plane, unobserved: bool, build, solve,
                 opts: CalibrationOptions):
    """The exact stage's start from the ari result: a distance in front of every camera (in air any
    will do); under water a distance searched inside the valid interval (the ari stage's can be far
    off); without stacking or declared plane, the normal from a coarse search scored by the exact cost."""
    from .factors.rig_graph import default_distance_mm
    from .init.window_start import search_normal

    def build_free(stage: str, st):  # the searches below run only without a declared plane: none in their graphs
        return build(stage, st, with_plane=False)

    if not underwater:
        if state.distance_mm is None:
            state = replace(state, distance_mm=default_distance_mm(state.normal_world, state.cam_from_world))
    elif plane is None:  # the ari stage's distance (or the hint) is one candidate
        state = _searched_distance(dataset, state, build_free, opts)
    if not unobserved:
        return state

    frames = _search_frames(dataset, state, NORMAL_SEARCH_FRAMES)
    subset = replace(state, world_from_target={f: state.world_from_target[f] for f in frames})

    def score(normal: np.ndarray) -> float:
        st = replace(subset, normal_world=normal)
        if underwater:
            st = _searched_distance(dataset, st, build_free, opts, samples=12)
        elif plane is None:
            st = replace(st, distance_mm=default_distance_mm(normal, st.cam_from_world))
        rg = build_free("exact", st)
        _hold_normal(rg, normal)
        try:
            _, solved = solve(rg, "exact", NORMAL_SEARCH_ITERATIONS)
        except AriSfmError:
            return np.inf
        return solved.error() if solved is not None else rg.graph.error(rg.values)

    normal = search_normal(score, state.normal_world)
    state = replace(state, normal_world=normal)
    if underwater:
        state = _searched_distance(dataset, state, build_free, opts)
    elif plane is None:
        state = replace(state, distance_mm=default_distance_mm(normal, state.cam_from_world))
    return state


NORMAL_SEARCH_ITERATIONS = 10  # LM iterations refitting K and poses for each candidate normal
NORMAL_SEARCH_FRAMES = 12  # frames (those seen by most cameras, every camera covered) scoring the candidates


def _search_frames(dataset: Dataset, state, count: int) -> list[str]:
    """Up to ``count`` frames of the state seen by the most cameras, more if needed to cover every camera."""
    cams: dict[str, set[str]] = {}
    for o in dataset.observations:
        if o.frame in state.world_from_target and o.set in ("calibration", "stacking"):
            cams.setdefault(o.frame, set()).add(o.camera)
    chosen, covered = [], set()
    for f in sorted(cams, key=lambda f: (-len(cams[f]), f)):
        if len(chosen) < count or not cams[f] <= covered:
            chosen.append(f)
            covered |= cams[f]
        if len(chosen) >= count and covered >= set(dataset.camera_names):
            break
    return chosen


def _searched_distance(dataset: Dataset, state, build, opts: CalibrationOptions, samples: int = 48):
    """state with its distance searched by the exact cost inside the valid interval (under water)."""
    from .factors.vectorized import VectorizedProblem
    from .init.window_start import distance_interval, search_distance

    lo, hi = distance_interval(state, dataset.observations, dataset.target, dataset.interface.thickness_mm)
    if not hi > lo:
        raise AriSfmError(dataset.rig_path, f"no window distance puts every camera in front of the window and every "
                                            f"corner beyond it (cameras up to {lo:.1f} mm, corners from {hi:.1f} mm "
                                            "along the normal): check interface.thickness_mm and the target")
    rg = build("exact", replace(state, distance_mm=0.5 * (lo + hi)))
    problem = VectorizedProblem.from_rig_graph(rg, huber_px=opts.huber_px, check=False)
    best = search_distance(lambda h: problem.error(replace(problem.x, distance_mm=h)), lo, hi, samples,
                           current=state.distance_mm)
    return replace(state, distance_mm=best)


def _check_in_front(dataset: Dataset, state) -> None:
    """One-line error naming camera and frame when the window at the exact stage's start does not
    lie between every camera and every corner it sees."""
    from .init.window_start import not_beyond

    bad = not_beyond(state, dataset.observations, dataset.target, dataset.interface.thickness_mm)
    if bad is not None:
        camera, frame = bad
        where = f"camera {camera}" + ("" if frame is None else f" frame {frame}")
        what = "is not in front of the window" if frame is None else "a corner is not beyond the window"
        raise AriSfmError(dataset.observations_path or dataset.rig_path,
                          f"{where}: {what} at the start of the exact stage (distance {state.distance_mm:.1f} mm; "
                          "check interface.thickness_mm, distance_mm and plane)")

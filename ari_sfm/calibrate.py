"""calibrate(): analytical initialisation, then the GTSAM bundle adjustment."""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from .calibration import Calibration, CameraCalibration
from .errors import AriSfmError
from .evaluate import residual_stats
from .models.registry import model_spec
from .records import Dataset, Interface
from .results import OutlierReport

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationOptions:
    """Options of :func:`calibrate`, each with its default."""

    distortion: bool = False  # estimate k1 k2 p1 p2 k3 (off: they stay as given, normally zero)
    huber_px: float | None = 1.0  # per-corner Huber threshold in px; None: plain least squares
    outlier_sigma: float = 5.0  # corners beyond this many sigma after convergence are reported
    exclude_outliers: bool = False  # drop those corners and re-run the last stage
    fix_intrinsics: bool = False  # hold K (and dist) at the rig.yaml hints of the cameras that give K
    max_iterations: int = 100  # Levenberg-Marquardt iterations per stage
    backend: str = "auto"  # bundle adjustment solver: "numpy" (vectorised, GTSAM's LM path), "gtsam", "auto" (= numpy)
    workers: int | None = None  # threads for corner detection (dataset with only images) and for the per-camera
    # analytic initialisation; None: os.cpu_count() (at most one per camera for the initialisation)
    progress: bool = False  # progress bars (the CLI turns them on)
    uncertainty: bool = True  # standard deviations of every parameter (marginal covariances, physical units)
    sigma_px: float | None = None  # the corners' pixel sigma weighting the images; None: estimated (robust,
    # from each stage's residuals; the stage is re-solved with it when priors or extra factors share the graph)

    def __post_init__(self) -> None:
        """Refuse values that would fail deep inside the solver (huber_px -1 gave 'non-finite Jacobian')."""
        import math

        if self.huber_px is not None and not (math.isfinite(self.huber_px) and self.huber_px > 0):
            raise ValueError(f"huber_px must be a finite number > 0, or None (got {self.huber_px})")
        if not (math.isfinite(self.outlier_sigma) and self.outlier_sigma > 0):
            raise ValueError(f"outlier_sigma must be a finite number > 0 (got {self.outlier_sigma})")


def _options(options: dict) -> CalibrationOptions:
    names = {f.name for f in fields(CalibrationOptions)}
    unknown = set(options) - names
    if unknown:
        raise TypeError(f"unknown calibrate option(s): {', '.join(sorted(unknown))} (known: {', '.join(sorted(names))})")
    return CalibrationOptions(**options)


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


def calibrate(dataset: Dataset | str | Path, model: str = "ari", extra_factors=None, **options) -> Calibration:
    """Calibrate the cameras and the window of a dataset.

    model "ari": the paper's paraxial model (analytic initialisation + bundle
    adjustment); "exact": Snell's law at both faces, refined from the ari result;
    the paper's baselines "rt" (ray tracing) and "pf" (polynomial), and "pinhole",
    "pinhole_dist" (window ignored): see :mod:`ari_sfm.baselines`.
    Options: see :class:`CalibrationOptions`.

    ``extra_factors``: gtsam factors on the graph's keys (:mod:`ari_sfm.factors.keys`; e.g.
    ``gtsam.PriorFactorUnit3(keys.N, ...)`` with a sigma in radians), or a callable taking each
    stage's :class:`~ari_sfm.factors.rig_graph.RigGraph` and returning them: they join every
    stage (ari, exact, the outlier re-run), the view factors being whitened by the pixel sigma,
    so a prior weighs what its sigma says (docs/RESEARCH.md).
    """
    from .init.rig import initialise_rig
    from .factors.rig_graph import RigGraph, RigState, default_distance_mm
    from .factors.vectorized import optimize_graph, resolve_backend

    opts = _options(options)
    backend = resolve_backend(opts.backend)
    spec = model_spec(model, "model", calibratable=True)  # the models: ari_sfm.models.registry
    if not isinstance(dataset, Dataset):
        from .io import load_dataset

        dataset = load_dataset(dataset)
    dataset = ensure_observations(dataset, opts.workers, opts.progress)
    if not spec.bundle:
        if extra_factors is not None:
            raise ValueError(f"extra_factors need a factor-graph model (ari or exact), not {model!r}")
        return spec.calibrate(dataset, opts)
    t0 = time.perf_counter()
    rig = initialise_rig(dataset, opts.distortion, opts.workers)
    iface = dataset.interface
    names = dataset.camera_names
    underwater = iface.medium_index != 1.0
    distance = iface.distance_mm
    if distance is None and underwater:
        distance = default_distance_mm(rig.normal_world, rig.cam_from_world)
    state = RigState.from_initialisation(rig, distance)
    fixed = [n for n in names if dataset.cameras[n].K is not None] if opts.fix_intrinsics else []
    if opts.fix_intrinsics and not fixed:
        raise AriSfmError(dataset.rig_path, "fix_intrinsics needs a K hint for at least one camera (cameras.<name>.K)")
    for n in fixed:  # start from the hint exactly
        spec = dataset.cameras[n]
        state.params[n][:4] = [spec.K[0, 0], spec.K[1, 1], spec.K[0, 2], spec.K[1, 2]]
        state.params[n][4:] = np.resize(spec.dist if spec.dist is not None else np.zeros(5), 5)
    stages = ["ari"] + (["exact"] if model == "exact" else [])
    graph = None
    iterations = {}
    from .outliers import find_outliers, robust_sigma_px, without

    # the images' weight: the pixel sigma, given or estimated from each stage's residuals; a stage is
    # re-solved with the estimate when other factors (priors, the user's) share its graph
    sigma = 1.0 if opts.sigma_px is None else float(opts.sigma_px)
    reweight = opts.sigma_px is None and (bool(fixed) or extra_factors is not None)

    def solve(observations, stage: str, state: RigState, sigma: float):
        graph = RigGraph.build(
            observations, dataset.target, iface, names, state, model=stage, distortion=opts.distortion,
            estimate_distance=underwater, huber_px=opts.huber_px, sigma_px=sigma, fixed_intrinsics=fixed,
        )
        _add_factors(graph, extra_factors)
        state, solved = optimize_graph(graph, backend, opts.max_iterations, opts.huber_px, return_problem=True,
                                       check=False)  # the graph was just built with opts.huber_px
        # residuals from the numpy backend's solved problem (no Python callbacks); GTSAM's otherwise
        return graph, state, solved, solved.residuals() if solved is not None else graph.residuals()

    for stage in stages:
        if stage == "exact" and state.distance_mm is None:
            state = replace(state, distance_mm=default_distance_mm(state.normal_world, state.cam_from_world))
        t_stage = time.perf_counter()
        graph, state, solved, residuals = solve(dataset.observations, stage, state, sigma)
        n_iterations = graph.iterations
        if opts.sigma_px is None:
            estimated = robust_sigma_px(r for _, r in residuals)
            if reweight and abs(estimated / sigma - 1.0) > 1e-3:
                graph, state, solved, residuals = solve(dataset.observations, stage, state, estimated)
                n_iterations += graph.iterations
            sigma = estimated
        iterations[stage] = {"iterations": n_iterations, "time_s": time.perf_counter() - t_stage, "backend": backend,
                             "sigma_px": graph.sigma_px}
        if solved is not None:  # numpy backend: it stops at convergence without GTSAM's futile lambda trials
            iterations[stage]["error_evaluations"] = solved.report.error_evaluations
        log.info("%s bundle adjustment: %d iterations, %.3f s", stage, n_iterations, iterations[stage]["time_s"])

    outliers, robust_sigma = find_outliers(residuals, opts.outlier_sigma)
    if outliers and opts.exclude_outliers:
        log.info("excluding %d outlier corners and re-running the %s stage", len(outliers), stages[-1])
        graph, state, solved, residuals = solve(without(dataset.observations, outliers), stages[-1], state, sigma)
    if outliers:
        # With the paraxial ari model, large residuals are mostly its own error at oblique rays.
        level = logging.INFO if stages[-1] == "ari" else logging.WARNING
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
    calib_frames = {o.frame for o in dataset.select("calibration")}
    cal = Calibration(
        model=model,
        interface=Interface(iface.thickness_mm, iface.index, iface.medium_index, distance),
        normal_world=state.normal_world,
        cameras=cameras,
        frames={f: p for f, p in state.world_from_target.items() if f in calib_frames},
        stacking_poses={f: p for f, p in state.world_from_target.items() if f in rig.stacking_poses},
        residuals=residual_stats(r for _, r in residuals),
        time_s=elapsed,
        extra={"optimizer": iterations},
        target=dataset.target,
        fixed_distance_mm=state.distance_mm if model == "exact" and not underwater else None,  # any value: same rays
        uncertainty=uncertainty,
        outliers=OutlierReport(robust_sigma, opts.outlier_sigma, opts.exclude_outliers, tuple(outliers)),
    )
    return cal


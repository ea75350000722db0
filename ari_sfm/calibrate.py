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
from .records import Dataset, Interface

log = logging.getLogger(__name__)

MODELS = ("ari", "exact", "rt", "pf", "pinhole", "pinhole_dist")  # the last four: ari_sfm.baselines


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
    uncertainty: bool = True  # standard deviations of every parameter from gtsam.Marginals

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


def calibrate(dataset: Dataset | str | Path, model: str = "ari", **options) -> Calibration:
    """Calibrate the cameras and the window of a dataset.

    model "ari": the paper's paraxial model (analytic initialisation + bundle
    adjustment); "exact": Snell's law at both faces, refined from the ari result;
    the paper's baselines "rt" (ray tracing) and "pf" (polynomial), and "pinhole",
    "pinhole_dist" (window ignored): see :mod:`ari_sfm.baselines`.
    Options: see :class:`CalibrationOptions`.
    """
    from .init.rig import initialise_rig
    from .factors.rig_graph import RigGraph, RigState, default_distance_mm
    from .factors.vectorized import optimize_graph, resolve_backend

    opts = _options(options)
    backend = resolve_backend(opts.backend)
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r} (known: {', '.join(MODELS)})")
    if not isinstance(dataset, Dataset):
        from .io import load_dataset

        dataset = load_dataset(dataset)
    dataset = ensure_observations(dataset, opts.workers, opts.progress)
    if model not in ("ari", "exact"):
        from .baselines import calibrate_baseline

        return calibrate_baseline(dataset, model, opts)
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
    for stage in stages:
        if stage == "exact" and state.distance_mm is None:
            state = replace(state, distance_mm=default_distance_mm(state.normal_world, state.cam_from_world))
        graph = RigGraph.build(
            dataset.observations, dataset.target, iface, names, state, model=stage, distortion=opts.distortion,
            estimate_distance=underwater, huber_px=opts.huber_px, fixed_intrinsics=fixed,
        )
        t_stage = time.perf_counter()
        state, solved = optimize_graph(graph, backend, opts.max_iterations, opts.huber_px, return_problem=True,
                                       check=False)  # the graph was just built with opts.huber_px
        iterations[stage] = {"iterations": graph.iterations, "time_s": time.perf_counter() - t_stage, "backend": backend}
        if solved is not None:  # numpy backend: it stops at convergence without GTSAM's futile lambda trials
            iterations[stage]["error_evaluations"] = solved.report.error_evaluations
        log.info("%s bundle adjustment: %d iterations, %.3f s", stage, graph.iterations, iterations[stage]["time_s"])
    from .outliers import find_outliers, without

    # residuals and marginals from the numpy backend's solved problem (no Python callbacks); GTSAM's otherwise
    residuals = solved.residuals() if solved is not None else graph.residuals()
    outliers, robust_sigma = find_outliers(residuals, opts.outlier_sigma)
    if outliers and opts.exclude_outliers:
        log.info("excluding %d outlier corners and re-running the %s stage", len(outliers), stages[-1])
        graph = RigGraph.build(
            without(dataset.observations, outliers), dataset.target, iface, names, state, model=stages[-1],
            distortion=opts.distortion, estimate_distance=underwater, huber_px=opts.huber_px, fixed_intrinsics=fixed,
        )
        state, solved = optimize_graph(graph, backend, opts.max_iterations, opts.huber_px, return_problem=True,
                                       check=False)
        residuals = solved.residuals() if solved is not None else graph.residuals()
    if outliers:
        # With the paraxial ari model, large residuals are mostly its own error at oblique rays.
        level = logging.INFO if stages[-1] == "ari" else logging.WARNING
        log.log(level, "%d corners beyond %.0f sigma (%.3f px) after convergence%s", len(outliers), opts.outlier_sigma,
                robust_sigma, " (excluded)" if opts.exclude_outliers else "")
    elapsed = time.perf_counter() - t0
    uncertainty = None
    if opts.uncertainty:
        from .factors.uncertainty import rig_uncertainty

        uncertainty = rig_uncertainty(graph, marginals=solved.marginals() if solved is not None else None,
                                      residuals=residuals)
    cameras = {}
    for n in names:
        p = state.params[n]
        K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
        ec = rig.cameras[n].expansion
        cameras[n] = CameraCalibration(
            n, tuple(dataset.cameras[n].image_size), K, p[4:9].copy(), state.cam_from_world[n],
            None if ec is None else ec.center_px, None if ec is None else ec.std_px,
            residual_stats(r for o, r in residuals if o.camera == n)["rmse_px"],
        )
    distance = state.distance_mm if underwater else None  # unobservable in air: null
    calib_frames = {o.frame for o in dataset.select("calibration")}
    extra: dict = {"optimizer": iterations}
    if uncertainty:
        extra["uncertainty"] = uncertainty
    extra["outliers"] = {"sigma_px": robust_sigma, "threshold_sigma": opts.outlier_sigma,
                         "excluded": opts.exclude_outliers, "corners": [o.to_json() for o in outliers]}
    if model == "exact" and not underwater:
        extra["fixed_distance_mm"] = state.distance_mm  # any value gives the same rays in air
    cal = Calibration(
        model=model,
        interface=Interface(iface.thickness_mm, iface.index, iface.medium_index, distance),
        normal_world=state.normal_world,
        cameras=cameras,
        frames={f: p for f, p in state.world_from_target.items() if f in calib_frames},
        stacking_poses={f: p for f, p in state.world_from_target.items() if f in rig.stacking_poses},
        residuals={k: v for k, v in residual_stats(r for _, r in residuals).items()},
        time_s=elapsed,
        extra=extra,
        target=dataset.target,
    )
    return cal


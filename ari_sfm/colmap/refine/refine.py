"""refine-colmap: a COLMAP (pinhole) reconstruction made behind a flat window, refined with the
exact refractive model.

Start: the model as COLMAP left it, read as its paraxial virtual cameras (:mod:`.paraxial`: a camera
behind a plate with a medium n_m sees the scene as a pinhole with focal n_m f whose centre sits
``n_m a`` behind it along the normal, ``a`` the ari model's apparent offset), the window normal on
the optical axis (mount camera) or on the mean viewing direction (mount world), and the distance
found by a search on the cost (:mod:`.start`): for each candidate distance, LM on everything but the
window, the lowest cost wins; then everything is refined (air behind: the distance is unobservable and
held). The steps are a plan of typed stages (:mod:`.plan`: :func:`~.plan.plan_refinement`,
:func:`~.plan.run_stage`); this module reads the inputs, runs the plan and assembles the result.

Gauge and scale: the first frame's pose is held (the world's rotation and translation). The
scale is *not* a gauge: the plate's thickness in mm sets it through refraction, but only weakly
(a plate a few mm thick against a scene metres away; ``uncertainty.scale_rel`` says how weakly).
The input's units are taken as ``units_mm`` mm each (a start only; ``scale_bar``: its factor;
neither: 1, the model is taken to be in mm, and a scene that would then lie inside the port is
refused with one line). A scale bar is a term of the solver (:mod:`.scale_bar`): the refinement
first runs without it (the scale free, along its near-flat valley), the result is rescaled to
the bar, and the refinement runs again with the bar held (docs/design/colmap.md).
:mod:`ari_sfm.colmap.refine.problem` lists what is estimated.

A long chain (a strip survey) starts otherwise: :mod:`.chain_start`.

A declared window (``interface.plane``, :mod:`.plane`) replaces the start search: the window
starts there; a sigma of 0 holds that part, > 0 adds a prior (a held plane does not scale with the
scene when the state is rescaled to the bar; the bar, a term of the solver, is held anyway).
"""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ari_sfm.calibration.record import Calibration
from ari_sfm.colmap import adapter
from ari_sfm.errors import AriSfmError, ErrorPath
from ari_sfm.io import save_calibration
from ari_sfm.records import Interface

from .inputs import baseline_term, check_finite, check_redundancy, check_scale_options, read_model, resolve_scale
from .options import RefineColmapOptions, refine_options
from .outputs import outputs, refine_report
from .paraxial import declared_start, initial_state, scaled, with_distance
from .plan import Reached, collapsed, estimates_distance, last_solve, plan_refinement, run_stage, setup
from .problem import State
from .report import RefineReport
from .start import distance_candidates, start_candidates

log = logging.getLogger(__name__)

__all__ = ["RefineColmapOptions", "RefineResult", "read_model", "refine_colmap", "write_refined"]

_collapsed = collapsed  # the restarts' test, looked up here at each call (a test replaces it)
# the helpers' earlier names here (tests reach them)
_baseline, _check_finite, _initial_state, _scaled, _with_distance = (baseline_term, check_finite, initial_state,
                                                                     scaled, with_distance)


@dataclass(frozen=True)
class RefineResult:
    """What :func:`refine_colmap` returns.

    ``reconstruction``: the COLMAP model to hand to COLMAP's tools: the refined 3D points (mm),
    the cameras and poses as their best approximation in COLMAP's camera models (OPENCV by
    default: COLMAP's own bundle adjustment with the points held; the poses are those virtual
    cameras', not the real centres). ``refractive``: the refined model itself (real poses, the lens intrinsics
    behind the window; its cameras are NOT pinhole cameras of the images). ``calibration``: the
    refractive cameras (exact model) with each housing's normal_cam and distance.
    """

    reconstruction: Any
    refractive: Any
    calibration: Calibration
    state: State
    report: RefineReport


def _options(options: RefineColmapOptions | str | None, overrides: dict[str, Any],
             path: ErrorPath) -> RefineColmapOptions:
    """The options of a call: a record, or (the old positional form) the mount, with the keyword overrides; a
    value no option takes is one AriSfmError line naming ``path``."""
    if isinstance(options, str):  # refine_colmap(rec, interface, "camera", ...): the mount
        overrides = {"mount": options, **overrides}
        options = None
    try:
        return refine_options(options, overrides)
    except ValueError as exc:
        raise AriSfmError(path, str(exc)) from None


def _reconstruction(reconstruction: Any, path: ErrorPath) -> tuple[Any, Any]:
    """(pycolmap.Reconstruction, the path named in errors): the reconstruction given, or read from its folder."""
    if not isinstance(reconstruction, (str, Path)) and hasattr(reconstruction, "num_points3D"):
        return reconstruction, path
    folder = Path(reconstruction)
    return read_model(folder), folder


def refine_colmap(reconstruction: Any, interface: Interface, options: RefineColmapOptions | str | None = None, *,
                  path: ErrorPath = "reconstruction", plane_path: ErrorPath = "interface.plane",
                  window_path: ErrorPath = "WINDOW.yaml", progress: bool = False, **overrides: Any) -> RefineResult:
    """Refine a COLMAP reconstruction made behind a flat window with the exact refractive model.

    Steps: the options, the model read and checked, its scale, the start state (at the declared plane, if
    any), the start distances; the plan (:func:`~.plan.plan_refinement`) run stage by stage
    (:func:`~.plan.run_stage`); the outputs and the report. See the module docstring for the start, the
    gauge and the scale.

    Args:
        reconstruction: a pycolmap.Reconstruction or a model folder.
        interface: the plate (thickness_mm, index, medium_index; distance_mm, if given, is the only distance
            candidate; ``plane``, if given, the declared window (:mod:`.plane`): frame ``camera`` (mount camera:
            each camera's housing frame) or ``world`` (mount world: the COLMAP world in mm); it replaces the
            start search; a sigma of 0 holds that part, > 0 makes it a prior).
        options: a :class:`~.options.RefineColmapOptions`, or the mount as a string (``camera``: a housing per
            COLMAP camera; ``world``: one window fixed in the world); None: the defaults.
        path: the model named in errors (a folder given as ``reconstruction`` names itself).
        plane_path: the file named in errors about the declared plane.
        window_path: the file named in errors about units and the scale bar.
        progress: a progress bar over the refinement's iterations.
        **overrides: :class:`~.options.RefineColmapOptions` fields (``mount``, ``units_mm``, ``scale_bar``,
            ``baseline``, ``huber_px``, ``max_iterations``, ``distances_mm``, ``approximation``, ``backend``,
            ``model``), which override ``options``.

    Returns:
        The refined model, its COLMAP approximation, the calibration, the state and the report.
    """
    t0 = time.perf_counter()
    opts = _options(options, overrides, path)
    check_scale_options(opts, path, window_path)
    rec, path = _reconstruction(reconstruction, path)
    cmodel = adapter.model_from_reconstruction(rec, path)
    check_finite(cmodel, path)
    check_redundancy(cmodel, path)
    scale = resolve_scale(cmodel, opts, path, window_path)
    before = adapter.image_residuals_px(rec, cmodel)
    virtual = initial_state(cmodel, opts.mount, scale.units_mm)
    plane = interface.plane
    if plane is not None:  # the declared window is the start (held, or the prior's centre)
        virtual = declared_start(cmodel, virtual, opts.mount, plane, plane_path)
    candidates = start_candidates(cmodel, virtual, interface,
                                  distance_candidates(interface, virtual, estimates_distance(interface),
                                                      opts.distances_mm),
                                  opts.scale_given, plane is not None or interface.distance_mm is not None,
                                  window_path)
    s = setup(cmodel, interface, opts, scale, virtual, candidates, window_path, path)
    plan = plan_refinement(s)
    reached = run_stage(s, plan[0], Reached())  # the start
    pbar = None
    if progress:
        from tqdm import tqdm

        pbar = tqdm(total=opts.max_iterations, desc="refine-colmap", unit="it", leave=False)

    def tick(it: int, cost: float) -> None:
        if pbar is not None:
            pbar.update(1)
            pbar.set_postfix(cost=f"{cost:.4g}")

    solved = last_solve(plan)
    for k in range(1, len(plan)):
        reached = run_stage(s, plan[k], reached, tick, _collapsed)
        if k == solved:
            if pbar is not None:
                pbar.close()
            _warn_unconverged(reached, opts)
    result = reached.result
    assert result is not None  # the plan refines
    out = outputs(rec, s, result.state)
    report = refine_report(s, reached, out, before, time.perf_counter() - t0)
    log.warning("refine-colmap: the COLMAP cameras written are the best %s approximation of the refractive "
                "cameras (poses are virtual; real poses in calibration.json): %.3f px RMS (the exact model: %.3f px)",
                opts.approximation, report.pinhole_approximation.rms_px, report.after.rms_px)
    return RefineResult(out.reconstruction, out.refractive, out.calibration, result.state, report)


def _warn_unconverged(reached: Reached, opts: RefineColmapOptions) -> None:
    """One warning when the refinement's end (after any restarts) did not converge."""
    result = reached.result
    assert result is not None  # after the refinement
    if not result.converged:
        log.warning("refine-colmap: not converged in %d iterations (max_iterations %d): the result and its sigmas "
                    "describe the last state, not an optimum; raise --max-iterations, or declare the port "
                    "(interface.plane) on surveys with short tracks", result.iterations, opts.max_iterations)


def write_refined(result: RefineResult, out_dir: str | Path) -> Path:
    """OUT: the COLMAP model (the cameras' best COLMAP approximation, refined points), calibration.json, refine.json.

    Everything is written into a temporary folder inside OUT first, then renamed into place file by file
    (refine.json last): a failed write (a full disk, a signal) leaves OUT's previous files as they were and no
    partial file.

    Args:
        result: what :func:`refine_colmap` returned.
        out_dir: the output folder (made if missing).

    Returns:
        The output folder.
    """
    import shutil
    import tempfile

    from ari_sfm.io import write_json_atomic

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".refine-colmap.", dir=out))
    except OSError as exc:
        raise AriSfmError(out, f"cannot write: {exc.strerror or exc}") from None
    try:
        _write_model(result.reconstruction, tmp)
        save_calibration(result.calibration, tmp / "calibration.json")
        write_json_atomic(tmp / "refine.json", result.report.to_json())
        names = sorted(p.name for p in tmp.iterdir() if p.name != "refine.json") + ["refine.json"]
        for name in names:
            os.replace(tmp / name, out / name)
    except (OSError, RuntimeError) as exc:  # pycolmap's writer raises RuntimeError
        raise AriSfmError(out, f"cannot write: {getattr(exc, 'strerror', None) or exc}") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _write_model(reconstruction: Any, folder: Path) -> None:
    """The COLMAP model's binary files in ``folder`` (pycolmap's writer)."""
    reconstruction.write(str(folder))

"""The ari-sfm command line. Errors print as one line: ``error: <file>: <what is wrong>``."""
from __future__ import annotations

import functools
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path

import click
import numpy as np

from .cli_checks import check_number, check_output_folder
from .errors import AriSfmError
from .models.registry import BUNDLE, CALIBRATABLE, COMPARED, MODELS, model_spec

log = logging.getLogger("ari_sfm")


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s: %(message)s")


def _exit_interrupted(exit=sys.exit) -> None:
    """Ctrl-C: "interrupted" on stderr and exit 130. While worker threads are still inside OpenCV
    (a pool cut short by the signal), leave at once: the interpreter's shutdown would wait for them,
    and a second Ctrl-C during that wait ended the process in C++'s terminate (SIGABRT)."""
    click.echo("interrupted", err=True)
    me = threading.current_thread()
    if any(t.is_alive() and not t.daemon and t is not me for t in threading.enumerate()):
        if me is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    exit(130)


def user_errors(fn):
    """Turn AriSfmError (and any unexpected exception) into one line on stderr and exit 1."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except AriSfmError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(1)
        except KeyboardInterrupt:  # Ctrl-C: no traceback, the shell's code for SIGINT
            _exit_interrupted()
        except (click.ClickException, click.exceptions.Exit, SystemExit):
            raise
        except Exception as exc:  # noqa: BLE001 - never a traceback unless asked for
            if os.environ.get("ARI_SFM_DEBUG"):
                raise
            click.echo(f"error: {type(exc).__name__}: {exc} (set ARI_SFM_DEBUG=1 for the traceback)", err=True)
            sys.exit(1)

    return wrapper


class _Group(click.Group):
    """The root group: Ctrl-C outside a command's body (parsing, `scenarios`) also prints "interrupted"
    and exits 130, where click would print "Aborted!" and exit 1."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            _exit_interrupted(ctx.exit)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="ari-sfm")
@click.option("-v", "--verbose", is_flag=True, help="Log progress messages.")
def main(verbose: bool) -> None:
    """Calibrate cameras behind a flat refractive window (ARI equation) and measure them."""
    _setup_logging(verbose)


@main.command()
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), default=None, help="Output folder for observations.json (default: <name>-detections beside DATASET; the dataset's own files are never written).")
@click.option("--workers", type=int, default=None, help="Parallel detection threads (default: all cores).")
@user_errors
def detect(dataset: Path, out: Path | None, workers: int | None) -> None:
    """Detect target corners in the dataset's images; write observations.json."""
    from .detection import detect_dataset
    from .io import load_dataset, save_observations

    if out is not None:
        check_output_folder(out)
    ds = load_dataset(dataset)
    if not any(entry.images for entry in ds.entries()):
        raise AriSfmError(ds.rig_path, "no images to detect: the dataset lists no image files (its corners are "
                                       "already in observations.json; calibrate or run it directly)")
    t0 = time.perf_counter()
    obs = detect_dataset(ds, workers=workers, progress=True)
    out = out or check_output_folder(ds.root.parent / f"{ds.root.name}-detections")
    out.mkdir(parents=True, exist_ok=True)
    save_observations(out / "observations.json", obs)
    n = sum(len(o.ids) for o in obs)
    click.echo(f"{len(obs)} images, {n} corners in {time.perf_counter() - t0:.1f} s -> {out / 'observations.json'}")


_model_option = click.option("--model", default=None, metavar="|".join(CALIBRATABLE),
                             help="; ".join(f"{m}: {MODELS[m].summary}" for m in CALIBRATABLE)
                             + ". Default: ari (run: exact when the dataset has no stacking poses).")
_distortion_option = click.option("--distortion/--no-distortion", default=False, show_default=True, help="Estimate k1 k2 p1 p2 k3.")
_huber_option = click.option("--huber-px", type=float, default=1.0, show_default=True,
                             help="Per-corner Huber threshold in px (0: plain least squares).")
_outlier_option = click.option("--exclude-outliers", is_flag=True, help="Drop corners beyond 5 sigma after convergence and re-run.")
_backend_option = click.option("--backend", type=click.Choice(["auto", "numpy", "gtsam"]), default="auto", show_default=True,
                               help="Bundle-adjustment solver: numpy (vectorised, GTSAM's LM path, 5-13x faster), "
                                    "gtsam (gtsam.LevenbergMarquardtOptimizer on the factor graph); auto = numpy.")


_fix_option = click.option("--fix-intrinsics", is_flag=True,
                           help="Hold the rig.yaml hints: a K hint holds K; a focal_px hint holds fx = fy = focal_px "
                                "(principal point free).")


def _calibration_options(fn):
    """The options calibrate and run share: --model, --distortion, --huber-px, --exclude-outliers,
    --fix-intrinsics, --backend."""
    for option in reversed((_model_option, _distortion_option, _huber_option, _outlier_option, _fix_option,
                            _backend_option)):
        fn = option(fn)
    return fn


@main.command(name="calibrate")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="Output folder for calibration.json.")
@_calibration_options
@user_errors
def calibrate_cmd(dataset: Path, out: Path, model: str | None, distortion: bool, huber_px: float, exclude_outliers: bool,
                  fix_intrinsics: bool, backend: str) -> None:
    """Calibrate DATASET; write OUT/calibration.json (and OUT/observations.json when detected here)."""
    from .pipelines.calibrate_rig import main as pipeline

    model = model or "ari"
    model_spec(model, "--model", calibratable=True)  # before any loading or detection
    check_output_folder(out)
    check_number("--huber-px", huber_px, minimum=0.0)
    t0 = time.perf_counter()
    result = pipeline(dataset, out, model=model, progress=True, distortion=distortion, huber_px=huber_px or None,
                      exclude_outliers=exclude_outliers, fix_intrinsics=fix_intrinsics, backend=backend)
    _summary(result.calibration, time.perf_counter() - t0)
    if result.observations_path:
        click.echo(f"observations: {result.observations_path}")
    click.echo(f"calibration:  {result.calibration_path}")


@main.command()
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@_calibration_options
@click.option("--truth", type=click.Path(path_type=Path), default=None,
              help="A simulator's truth.json: also report the reconstruction's 3D error against it.")
@user_errors
def run(dataset: Path, out: Path, model: str | None, distortion: bool, huber_px: float, exclude_outliers: bool,
        fix_intrinsics: bool, backend: str, truth: Path | None) -> None:
    """The pipeline: detect corners when needed, calibrate, reconstruct (frames seen by two cameras), report."""
    from .pipelines.run import main as pipeline

    if model is not None:  # None: exact without stacking poses, else ari (pipelines.run.default_model)
        model_spec(model, "--model", calibratable=True)  # before any loading or detection
    check_output_folder(out)
    check_number("--huber-px", huber_px, minimum=0.0)
    t0 = time.perf_counter()
    click.echo(f"ari-sfm run: {dataset} -> {out}")
    result = pipeline(dataset, out, model=model, truth=truth, progress=True, distortion=distortion,
                      huber_px=huber_px or None, exclude_outliers=exclude_outliers, fix_intrinsics=fix_intrinsics,
                      backend=backend)
    _summary(result.calibrated.calibration, time.perf_counter() - t0)
    click.echo(f"calibration: {result.calibrated.calibration_path}")
    if result.reconstruction is None:
        click.echo(f"info: reconstruction skipped: {result.skipped_reconstruction}")
    else:
        m = result.reconstruction.metrics
        click.echo(f"reconstruction: {m.num_points} points in {m.num_frames} frames, flatness rmse "
                   f"{m.flatness_mm.rmse:.4f} mm -> {result.reconstruction.metrics_path}")
    click.echo(f"report: {result.report_path}")


@main.command(name="report")
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--dataset", type=click.Path(path_type=Path), default=None,
              help="The dataset folder (default: from OUT/run.json, else OUT/metrics.json).")
@user_errors
def report_cmd(out: Path, dataset: Path | None) -> None:
    """Write OUT/report.html: one self-contained page of the calibration, residuals and reconstruction in OUT."""
    from .report import write_report

    click.echo(f"report: {write_report(out, dataset)}")


@main.command(name="evaluate")
@click.argument("calibration", type=click.Path(path_type=Path))
@click.argument("observations", type=click.Path(path_type=Path))
@click.option("--solve-poses", is_flag=True,
              help="Held-out views: fit every frame's target pose with the rig fixed (as compare --holdout; "
                   "frame names may repeat the calibration's; stacking records are left out). Without it only "
                   "frames the calibration holds count, at its poses.")
@user_errors
def evaluate_cmd(calibration: Path, observations: Path, solve_poses: bool) -> None:
    """Reprojection errors of CALIBRATION on an OBSERVATIONS file (e.g. held-out views)."""
    from .calibration import load_calibration
    from .evaluate import evaluate, evaluate_held_out

    cal = load_calibration(calibration)
    stats = evaluate_held_out(cal, observations) if solve_poses else evaluate(cal, observations)
    if stats.count == 0:
        raise AriSfmError(observations, "no corner to judge: no observation of a calibrated camera in a frame "
                          + ("whose pose could be fitted" if solve_poses else
                             "the calibration holds (held-out views: add --solve-poses)"))
    click.echo(f"rmse {stats.rmse_px:.4f} px  mae {stats.mae_px:.4f} px  max {stats.max_px:.4f} px  ({stats.count} corners)")


@main.command(name="reconstruct")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--calibration", "calibration", type=click.Path(path_type=Path), required=True,
              help="calibration.json of the same rig.")
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: points.json, metrics.json, clouds/*.ply.")
@click.option("--truth", type=click.Path(path_type=Path), default=None,
              help="A simulator's truth.json: also report the 3D error against its points.")
@click.option("--workers", type=int, default=None, help="Parallel detection threads when the dataset has only images.")
@click.option("--reference", type=click.Path(path_type=Path), default=None,
              help="A mesh or point cloud (.ply, .obj, .stl, ...) of the true geometry: the 3D error after "
                   "registration onto it (Open3D ICP, point-to-mesh distances).")
@user_errors
def reconstruct_cmd(dataset: Path, calibration: Path, out: Path, truth: Path | None, workers: int | None,
                    reference: Path | None) -> None:
    """Triangulate the reconstruction frames of DATASET and measure them (flatness, stage, corner spacing)."""
    from .reconstruct import run_reconstruction

    check_output_folder(out)
    r = run_reconstruction(dataset, calibration, out, truth, workers=workers, progress=True, reference_path=reference)
    m = r.metrics
    click.echo(f"{m.num_points} points in {m.num_frames} frames, ray gap rms {m.ray_gap_mm.rms:.4f} mm"
               + (f", reprojection rmse {m.reprojection_rmse_px:.4f} px" if m.reprojection_rmse_px is not None else ""))
    click.echo(f"flatness: rmse {m.flatness_mm.rmse:.4f} mm, mae {m.flatness_mm.mae:.4f} mm, "
               f"max {m.flatness_mm.max:.4f} mm")
    if m.stage:
        s = m.stage
        click.echo(f"stage plane distances vs stage_mm (reference {s.reference_frame}): error rmse "
                   f"{s.plane_distance_error_mm.rmse:.4f} mm, max {s.plane_distance_error_mm.max:.4f} mm "
                   f"(stage {s.angle_to_normal_deg:.2f} deg off the normal; uncorrected max "
                   f"{s.plane_distance_error_paper_mm.max:.4f} mm)")
    if m.inter_corner_mm:
        ic = m.inter_corner_mm
        click.echo(f"inter-corner distances ({ic.count} vs {ic.square_mm:g} mm): rmse {ic.rmse:.4f} mm, "
                   f"mae {ic.mae:.4f} mm, max {ic.max:.4f} mm")
    if m.truth:
        t = m.truth
        click.echo(f"vs truth: rms {t.aligned_rms_mm:.4f} mm after rigid alignment (max {t.aligned_max_mm:.4f}), "
                   f"{t.unaligned_rms_mm:.4f} mm without")
    if m.reference:
        ref, reg = m.reference, m.reference["registration"]
        click.echo(f"vs reference {ref['kind']}: distance rms {ref['distance_mm']['rms']:.4f} mm, max "
                   f"{ref['distance_mm']['max']:.4f} mm after registration (rotation {reg['rotation_deg']:.3f} deg, "
                   f"translation {reg['translation_mm']:.3f} mm)")
    click.echo(f"points:  {r.points_path}\nmetrics: {r.metrics_path}\nclouds:  {r.clouds['all'].parent}")


@main.command(name="compare")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: compare.json, compare.md, residuals_*.png.")
@click.option("--models", default=",".join(COMPARED), show_default=True,
              help=f"Comma-separated: {', '.join(CALIBRATABLE)}.")
@click.option("--subset", default=None, help="center:COLSxROWS: fit on the central corners of each board, "
                                             "judge on all (the paper's limited-data test: center:3x4).")
@click.option("--holdout", type=click.Path(path_type=Path), default=None,
              help="Also judge each model on this observations file (frame poses solved, rig fixed).")
@click.option("--pf-world", default="ari", show_default=True, metavar="|".join(BUNDLE),
              help="Whose board poses give pf its world coordinates.")
@_distortion_option
@_backend_option
@user_errors
def compare_cmd(dataset: Path, out: Path, models: str, subset: str | None, holdout: Path | None, pf_world: str,
                distortion: bool, backend: str) -> None:
    """Calibrate DATASET with several models and compare them (the paper's Tables 2-4)."""
    from .compare import run_compare

    check_output_folder(out)
    paths = run_compare(dataset, out, models, subset, holdout, pf_world, distortion=distortion, backend=backend)
    click.echo(paths["md"].read_text())
    click.echo("\n".join(f"{k}: {v}" for k, v in paths.items()))


@main.command(name="export-colmap")
@click.argument("calibration", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="Output folder for the COLMAP model.")
@click.option("--dataset", type=click.Path(path_type=Path), default=None,
              help="Dataset whose observations become the images' 2D points (default: observations.json beside CAL, "
                   "else the dataset named by run.json / metrics.json beside CAL).")
@click.option("--points", type=click.Path(path_type=Path), default=None,
              help="points.json of the reconstruction frames (default: points.json beside CAL, if any).")
@click.option("--approximation", type=click.Choice(["pinhole", "shift"]), default="pinhole", show_default=True,
              help="exact model / medium behind the window: refit K and pose, or only the shift along the normal.")
@user_errors
def export_colmap_cmd(calibration: Path, out: Path, dataset: Path | None, points: Path | None, approximation: str) -> None:
    """Write CALIBRATION as a COLMAP model (cameras, rig, frames, images, 3D points with tracks) to OUT."""
    from .colmap_export import export_colmap, summary

    check_output_folder(out)
    folder = calibration.parent  # an `ari-sfm run` folder: its observations, dataset and points by default
    if dataset is None and not (folder / "observations.json").is_file():
        from .report import find_dataset

        dataset = find_dataset(folder)
    if points is None and (folder / "points.json").is_file():
        points = folder / "points.json"

    click.echo(summary(export_colmap(calibration, out, dataset=dataset, points=points, approximation=approximation)))


@main.command()
@click.argument("scenario")
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="Output folder: OUT/dataset and OUT/truth.json.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--sigma", type=float, default=0.05, show_default=True, help="Pixel noise per coordinate.")
@click.option("--image-scale", type=float, default=1.0, show_default=True, help="Scale of image size and focal length.")
@click.option("--images/--no-images", default=None, help="Render PNG images (default: per scenario).")
@user_errors
def simulate(scenario: str, out: Path, seed: int, sigma: float, image_scale: float, images: bool | None) -> None:
    """Write a simulated dataset (exact Snell physics) and its truth. SCENARIO: one of `ari-sfm scenarios`."""
    from .simulate import SCENARIOS, simulate as run_sim

    if scenario == "port_survey":  # structure from motion behind a flat port (refine-colmap's truth)
        from .simulate.port_survey import write_port_survey

        check_number("--image-scale", image_scale, minimum=0.0, maximum=40.0, strict_minimum=True)
        size = (max(16, int(round(640 * image_scale))), max(16, int(round(480 * image_scale))))
        write_port_survey(out, seed=seed, image_size=size, focal_px=600.0 * image_scale, progress=True)
        click.echo(f"port_survey: {out / 'images'} and {out / 'truth.json'}")
        return
    if scenario not in SCENARIOS:
        raise AriSfmError(None, f"unknown scenario {scenario!r}; known: {', '.join(SCENARIOS)}")
    check_output_folder(out)
    check_number("--sigma", sigma, minimum=0.0, maximum=100.0)
    check_number("--image-scale", image_scale, minimum=0.0, maximum=40.0, strict_minimum=True)
    ds, truth = run_sim(scenario, out, seed=seed, sigma_px=sigma, images=images, image_scale=image_scale)
    click.echo(f"dataset: {ds}\ntruth:   {truth}")


@main.command()
def scenarios() -> None:
    """List the simulator's scenarios."""
    from .simulate import SCENARIOS

    for name, text in SCENARIOS.items():
        click.echo(f"{name:28s} {text}")


@main.command()
def doctor() -> None:
    """Check that every dependency imports (open3d needs the system library libusb-1.0-0)."""
    from .deps import check_dependencies

    bad = False
    for name, version in check_dependencies().items():
        click.echo(f"{name:12s} {version}")
        bad |= version.startswith("error")
    sys.exit(1 if bad else 0)


def _summary(cal, elapsed: float) -> None:
    """A one-screen summary of a calibration."""
    from .geometry import angle_between_deg

    r = cal.residuals
    click.echo(f"\nmodel {cal.model}: {len(cal.cameras)} camera(s), {len(cal.frames)} frames, "
               f"window {cal.interface.thickness_mm:g} mm n={cal.interface.index:g} medium n={cal.interface.medium_index:g}")
    nw = cal.normal_world
    if nw is None:
        click.echo("normal: none (the window is ignored)")
    else:
        click.echo(f"normal (world) [{nw[0]:+.5f} {nw[1]:+.5f} {nw[2]:+.5f}]"
                   + (f"  distance {cal.interface.distance_mm:.3f} mm" if cal.interface.distance_mm is not None else ""))
    click.echo(f"{'camera':10s} {'fx':>9s} {'fy':>9s} {'cx':>8s} {'cy':>8s} {'tilt':>6s} {'expansion centre (px)':>26s} {'rmse':>7s}")
    for name, c in cal.cameras.items():
        tilt = float("nan") if cal.normal_world is None else angle_between_deg(cal.normal_cam(name), np.array([0, 0, 1.0]))
        ec = "-" if c.expansion_center_px is None else (
            f"{c.expansion_center_px[0]:.1f},{c.expansion_center_px[1]:.1f} ±{max(c.expansion_center_std_px):.2f}")
        click.echo(f"{name:10s} {c.K[0,0]:9.2f} {c.K[1,1]:9.2f} {c.K[0,2]:8.2f} {c.K[1,2]:8.2f} {tilt:5.2f}° {ec:>26s} {c.rmse_px:7.4f}")
    u = cal.uncertainty
    if u:
        click.echo(f"standard deviations (sigma {u.sigma_px:.3f} px): normal {_std(u.normal_deg, '.4f')}°"
                   + (f", distance {_std(u.distance_mm, '.4f')} mm" if u.estimates_distance else ""))
        for name, s in u.cameras.items():
            rel = (f"  cam_from_{next(iter(cal.cameras))} ±{_std(s.rotation_deg, '.4f')}°"
                   f" ±{_std(s.translation_mm, '.4f')} mm" if s.relative_pose else "")
            i = s.intrinsics
            click.echo(f"  {name:8s} fx ±{_std(i['fx'], '.3f')} fy ±{_std(i['fy'], '.3f')} cx ±{_std(i['cx'], '.3f')}"
                       f" cy ±{_std(i['cy'], '.3f')} px{rel}")
    if cal.outliers is not None and cal.outliers.corners:
        click.echo(f"{len(cal.outliers.corners)} corners beyond {cal.outliers.threshold_sigma:g} sigma "
                   f"({'excluded' if cal.outliers.excluded else 'listed in calibration.json under outliers'})")
    click.echo(f"residuals: rmse {r.rmse_px:.4f} px, mae {r.mae_px:.4f} px, max {r.max_px:.4f} px over {r.count} corners")
    click.echo(f"time: calibration {cal.time_s:.3f} s, total {elapsed:.2f} s")


def _std(value: float | None, spec: str) -> str:
    """A standard deviation for the summary ('n/a' when the data do not determine it)."""
    return "n/a" if value is None else format(value, spec)


@main.group(name="import")
def import_group() -> None:
    """Import another tool's experiment as an ari-sfm dataset."""


@import_group.command(name="openptv")
@click.argument("experiment", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="New dataset folder (rig.yaml, observations.json).")
@user_errors
def import_openptv_cmd(experiment: Path, out: Path) -> None:
    """Read an OpenPTV EXPERIMENT folder (ptv.par, cal_ori.par or multi_planes.par, .fix/.crd, .ori) as a dataset."""
    from .io import load_dataset
    from .openptv import import_experiment

    rig = import_experiment(experiment, out)
    ds = load_dataset(rig)
    n_obs = sum(len(o.ids) for o in ds.observations or ())
    click.echo(f"dataset: {rig}\n{len(ds.cameras)} cameras ({', '.join(ds.cameras)}), "
               f"{ds.target.num_ids()} body points, {n_obs} observations")


@main.command(name="export-openptv")
@click.argument("calibration", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="OpenPTV experiment folder: writes cal/camN.tif.ori, .addpar and parameters/ptv.par.")
@click.option("--frame", default=None, help="Calibration frame whose target coordinates become OpenPTV's world "
                                            "(default: the first; 'world': the calibration's world).")
@click.option("--pixel-size-mm", type=float, default=None,
              help="Sensor pixel size (default: OUT/parameters/ptv.par's, else 0.01).")
@user_errors
def export_openptv_cmd(calibration: Path, out: Path, frame: str | None, pixel_size_mm: float | None) -> None:
    """Write CALIBRATION as OpenPTV orientation files in OUT."""
    from .openptv import export_openptv

    summary = export_openptv(calibration, out, frame=frame, pixel_size_mm=pixel_size_mm)
    click.echo(f"frame {summary.frame}, pixel size {summary.pixel_size_mm[0]:g} x {summary.pixel_size_mm[1]:g} mm")
    for name, number in summary.numbers.items():
        fit = summary.fit_error_px.get(name)
        click.echo(f"  {name} -> cam{number}" + (f" (distortion fitted, max {fit:.2g} px)" if fit is not None else ""))
    click.echo("\n".join(str(f) for f in summary.files))


if __name__ == "__main__":
    main()


@main.command(name="refine-colmap")
@click.argument("model_dir", type=click.Path(path_type=Path))
@click.option("--window", "window", type=click.Path(path_type=Path), required=True,
              help="WINDOW.yaml: interface (thickness_mm, index, medium_index), mount (camera | world), "
                   "units_mm or scale_bar.")
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder (not MODEL_DIR): COLMAP model (the cameras' best OPENCV or PINHOLE "
                   "approximation), calibration.json, refine.json.")
@click.option("--huber-px", type=float, default=2.0, show_default=True, help="Huber threshold (px, > 0).")
@click.option("--max-iterations", type=int, default=50, show_default=True,
              help="Cap on the accepted Levenberg-Marquardt steps of the final refinement (>= 1).")
@user_errors
def refine_colmap_cmd(model_dir: Path, window: Path, out: Path, huber_px: float, max_iterations: int) -> None:
    """Refine the COLMAP model in MODEL_DIR (made behind a flat window) with the exact refractive model."""
    from .colmap_refine import refine_colmap, write_refined
    from .colmap_refine.window import load_window

    check_number("--huber-px", huber_px, 0.0, strict_minimum=True)
    check_number("--max-iterations", max_iterations, 1)
    check_output_folder(out)
    if out.exists() and model_dir.exists() and os.path.realpath(out) == os.path.realpath(model_dir):
        raise AriSfmError(out, "-o/--out: is MODEL_DIR: refine-colmap does not overwrite its input model "
                               "(write to another folder)")
    spec = load_window(window)
    result = refine_colmap(model_dir, spec.interface, mount=spec.mount, units_mm=spec.units_mm,
                           scale_bar=spec.scale_bar, huber_px=huber_px, max_iterations=max_iterations, progress=True,
                           plane_path=window, window_path=window)
    write_refined(result, out)
    r = result.report
    u = r["uncertainty"]
    click.echo(f"refine-colmap: {r['counts']['images']} images, {r['counts']['points3D']} points, "
               f"{r['iterations']} iterations ({'converged' if r['converged'] else 'NOT converged'}), "
               f"{r['time_s']:.1f} s; reprojection RMS {r['before']['rms_px']:.3f} px "
               f"(COLMAP pinhole) -> {r['after']['rms_px']:.3f} px (exact)")
    for name in u["distance_mm"] | u["normal_deg"]:
        d = r["window"]["distance_mm"].get(name) if "distance_mm" in r["window"] else r["window"]["plane_mm"]
        parts = [f"distance {d:.2f} +- {u['distance_mm'][name]:.2g} mm" if name in u["distance_mm"] else "",
                 f"normal +- {u['normal_deg'][name]:.2g} deg" if name in u["normal_deg"] else ""]
        click.echo(f"  window {name}: " + ", ".join(p for p in parts if p) + " (1 sigma)")
    if u["scale_rel"] is not None:
        click.echo(f"  scale: +- {100 * u['scale_rel']:.2g} % (1 sigma)"
                   + (f"; scale bar {r['scale_bar']['refined_mm']:.6g} mm (declared {r['scale_bar']['declared_mm']:.6g})"
                      if "scale_bar" in r else ""))
    if u["weak"]:
        click.echo(f"  barely determined by these images: {', '.join(u['weak'])} (see the warnings)")
    click.echo(f"  COLMAP cameras written as their best "
               f"{r['pinhole_approximation']['camera_model']} approximation ({r['pinhole_approximation']['rms_px']:.3f} px) "
               f"-> {out}")

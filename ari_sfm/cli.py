"""The ari-sfm command line. Errors print as one line: ``error: <file>: <what is wrong>``."""
from __future__ import annotations

import functools
import logging
import os
import sys
import time
from pathlib import Path

import click
import numpy as np

from .errors import AriSfmError

log = logging.getLogger("ari_sfm")


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s: %(message)s")


def user_errors(fn):
    """Turn AriSfmError (and any unexpected exception) into one line on stderr and exit 1."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except AriSfmError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(1)
        except (click.ClickException, click.exceptions.Exit, SystemExit, KeyboardInterrupt):
            raise
        except Exception as exc:  # noqa: BLE001 - never a traceback unless asked for
            if os.environ.get("ARI_SFM_DEBUG"):
                raise
            click.echo(f"error: {type(exc).__name__}: {exc} (set ARI_SFM_DEBUG=1 for the traceback)", err=True)
            sys.exit(1)

    return wrapper


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="ari-sfm")
@click.option("-v", "--verbose", is_flag=True, help="Log progress messages.")
def main(verbose: bool) -> None:
    """Calibrate cameras behind a flat refractive window (ARI equation) and measure them."""
    _setup_logging(verbose)


@main.command()
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), default=None, help="Where to write observations.json (default: DATASET/observations.json is NOT overwritten; OUT defaults to DATASET/../<name>-detections).")
@click.option("--workers", type=int, default=None, help="Parallel detection threads (default: all cores).")
@user_errors
def detect(dataset: Path, out: Path | None, workers: int | None) -> None:
    """Detect target corners in the dataset's images; write observations.json."""
    from .detection import detect_dataset
    from .io import load_dataset, save_observations

    ds = load_dataset(dataset)
    t0 = time.perf_counter()
    obs = detect_dataset(ds, workers=workers, progress=True)
    out = out or (ds.root.parent / f"{ds.root.name}-detections")
    out.mkdir(parents=True, exist_ok=True)
    save_observations(out / "observations.json", obs)
    n = sum(len(o.ids) for o in obs)
    click.echo(f"{len(obs)} images, {n} corners in {time.perf_counter() - t0:.1f} s -> {out / 'observations.json'}")


_model_option = click.option("--model", type=click.Choice(["ari", "exact", "rt", "pf", "pinhole", "pinhole_dist"]),
                             default="ari", show_default=True,
                             help="ari: paraxial ARI model; exact: Snell's law, refined from ari; "
                                  "rt, pf, pinhole, pinhole_dist: the baselines of `compare`.")
_distortion_option = click.option("--distortion/--no-distortion", default=False, show_default=True, help="Estimate k1 k2 p1 p2 k3.")
_huber_option = click.option("--huber-px", type=float, default=1.0, show_default=True,
                             help="Per-corner Huber threshold in px (0: plain least squares).")
_outlier_option = click.option("--exclude-outliers", is_flag=True, help="Drop corners beyond 5 sigma after convergence and re-run.")


def _calibration_options(fn):
    """The options calibrate and run share: --model, --distortion, --huber-px, --exclude-outliers."""
    for option in reversed((_model_option, _distortion_option, _huber_option, _outlier_option)):
        fn = option(fn)
    return fn


@main.command(name="calibrate")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="Output folder for calibration.json.")
@_calibration_options
@user_errors
def calibrate_cmd(dataset: Path, out: Path, model: str, distortion: bool, huber_px: float, exclude_outliers: bool) -> None:
    """Calibrate DATASET; write OUT/calibration.json (and OUT/observations.json when detected here)."""
    from .pipelines.calibrate_rig import main as pipeline

    t0 = time.perf_counter()
    result = pipeline(dataset, out, model=model, progress=True, distortion=distortion, huber_px=huber_px or None,
                      exclude_outliers=exclude_outliers)
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
def run(dataset: Path, out: Path, model: str, distortion: bool, huber_px: float, exclude_outliers: bool,
        truth: Path | None) -> None:
    """The pipeline: detect corners when needed, calibrate, reconstruct (frames seen by two cameras), report."""
    from .pipelines.run import main as pipeline

    t0 = time.perf_counter()
    click.echo(f"ari-sfm run: {dataset} -> {out}")
    result = pipeline(dataset, out, model=model, truth=truth, progress=True, distortion=distortion,
                      huber_px=huber_px or None, exclude_outliers=exclude_outliers)
    _summary(result.calibrated.calibration, time.perf_counter() - t0)
    click.echo(f"calibration: {result.calibrated.calibration_path}")
    if result.reconstruction is None:
        click.echo(f"info: reconstruction skipped: {result.skipped_reconstruction}")
    else:
        m = result.reconstruction.metrics
        click.echo(f"reconstruction: {m['num_points']} points in {m['num_frames']} frames, flatness rmse "
                   f"{m['flatness_mm']['rmse']:.4f} mm -> {result.reconstruction.metrics_path}")
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
@user_errors
def evaluate_cmd(calibration: Path, observations: Path) -> None:
    """Reprojection errors of CALIBRATION on an OBSERVATIONS file (e.g. held-out views)."""
    from .calibration import load_calibration
    from .evaluate import evaluate

    stats = evaluate(load_calibration(calibration), observations)
    click.echo(f"rmse {stats['rmse_px']:.4f} px  mae {stats['mae_px']:.4f} px  max {stats['max_px']:.4f} px  ({stats['count']} corners)")


@main.command(name="reconstruct")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--calibration", "calibration", type=click.Path(path_type=Path), required=True,
              help="calibration.json of the same rig.")
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: points.json, metrics.json, clouds/*.ply.")
@click.option("--truth", type=click.Path(path_type=Path), default=None,
              help="A simulator's truth.json: also report the 3D error against its points.")
@click.option("--workers", type=int, default=None, help="Parallel detection threads when the dataset has only images.")
@user_errors
def reconstruct_cmd(dataset: Path, calibration: Path, out: Path, truth: Path | None, workers: int | None) -> None:
    """Triangulate the reconstruction frames of DATASET and measure them (flatness, stage, corner spacing)."""
    from .reconstruct import run_reconstruction

    r = run_reconstruction(dataset, calibration, out, truth, workers=workers, progress=True)
    m = r.metrics
    click.echo(f"{m['num_points']} points in {m['num_frames']} frames, ray gap rms {m['ray_gap_mm']['rms']:.4f} mm"
               + (f", reprojection rmse {m['reprojection_rmse_px']:.4f} px" if m["reprojection_rmse_px"] is not None else ""))
    click.echo(f"flatness: rmse {m['flatness_mm']['rmse']:.4f} mm, mae {m['flatness_mm']['mae']:.4f} mm, "
               f"max {m['flatness_mm']['max']:.4f} mm")
    if m["stage"]:
        s = m["stage"]
        click.echo(f"stage plane distances vs stage_mm (reference {s['reference_frame']}): error rmse "
                   f"{s['plane_distance_error_mm']['rmse']:.4f} mm, max {s['plane_distance_error_mm']['max']:.4f} mm "
                   f"(stage {s['angle_to_normal_deg']:.2f} deg off the normal; uncorrected max "
                   f"{s['plane_distance_error_paper_mm']['max']:.4f} mm)")
    if m["inter_corner_mm"]:
        ic = m["inter_corner_mm"]
        click.echo(f"inter-corner distances ({ic['count']} vs {ic['square_mm']:g} mm): rmse {ic['rmse']:.4f} mm, "
                   f"mae {ic['mae']:.4f} mm, max {ic['max']:.4f} mm")
    if m["truth"]:
        t = m["truth"]
        click.echo(f"vs truth: rms {t['aligned']['rms_mm']:.4f} mm after rigid alignment (max {t['aligned']['max_mm']:.4f}), "
                   f"{t['unaligned']['rms_mm']:.4f} mm without")
    click.echo(f"points:  {r.points_path}\nmetrics: {r.metrics_path}\nclouds:  {r.clouds['all'].parent}")


@main.command(name="compare")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: compare.json, compare.md, residuals_*.png.")
@click.option("--models", default="ari,exact,rt,pf,pinhole", show_default=True,
              help="Comma-separated: ari, exact, rt, pf, pinhole, pinhole_dist.")
@click.option("--subset", default=None, help="center:COLSxROWS: fit on the central corners of each board, "
                                             "judge on all (the paper's limited-data test: center:3x4).")
@click.option("--holdout", type=click.Path(path_type=Path), default=None,
              help="Also judge each model on this observations file (frame poses solved, rig fixed).")
@click.option("--pf-world", type=click.Choice(["ari", "exact"]), default="ari", show_default=True,
              help="Whose board poses give pf its world coordinates.")
@_distortion_option
@user_errors
def compare_cmd(dataset: Path, out: Path, models: str, subset: str | None, holdout: Path | None, pf_world: str,
                distortion: bool) -> None:
    """Calibrate DATASET with several models and compare them (the paper's Tables 2-4)."""
    from .compare import run_compare

    paths = run_compare(dataset, out, models, subset, holdout, pf_world, distortion=distortion)
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
    """Write a simulated dataset (exact Snell physics) and its truth. SCENARIO: see --help of `ari-sfm scenarios`."""
    from .simulate import SCENARIOS, simulate as run_sim

    if scenario == "port_survey":  # structure from motion behind a flat port (refine-colmap's truth)
        from .simulate.port_survey import write_port_survey

        write_port_survey(out, seed=seed, progress=True)
        click.echo(f"port_survey: {out / 'images'} and {out / 'truth.json'}")
        return
    if scenario not in SCENARIOS:
        raise AriSfmError(None, f"unknown scenario {scenario!r}; known: {', '.join(SCENARIOS)}")
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
    u = cal.extra.get("uncertainty")
    if u:
        click.echo(f"standard deviations (sigma {u['sigma_px']:.3f} px): normal {_std(u['normal_deg'], '.4f')}°"
                   + (f", distance {_std(u['distance_mm'], '.4f')} mm" if "distance_mm" in u else ""))
        for name, s in u["cameras"].items():
            rel = (f"  cam_from_{next(iter(cal.cameras))} ±{_std(s['rotation_deg'], '.4f')}°"
                   f" ±{_std(s['translation_mm'], '.4f')} mm" if "rotation_deg" in s else "")
            click.echo(f"  {name:8s} fx ±{_std(s['fx'], '.3f')} fy ±{_std(s['fy'], '.3f')} cx ±{_std(s['cx'], '.3f')}"
                       f" cy ±{_std(s['cy'], '.3f')} px{rel}")
    outl = cal.extra.get("outliers", {}).get("corners", [])
    if outl:
        click.echo(f"{len(outl)} corners beyond {cal.extra['outliers']['threshold_sigma']:g} sigma "
                   f"({'excluded' if cal.extra['outliers']['excluded'] else 'listed in calibration.json under outliers'})")
    click.echo(f"residuals: rmse {r['rmse_px']:.4f} px, mae {r['mae_px']:.4f} px, max {r['max_px']:.4f} px over {r['count']} corners")
    click.echo(f"time: calibration {cal.time_s:.3f} s, total {elapsed:.2f} s")


def _std(value: float | None, spec: str) -> str:
    """A standard deviation for the summary ('n/a' when the data do not determine it)."""
    return "n/a" if value is None else format(value, spec)


if __name__ == "__main__":
    main()


@main.command(name="refine-colmap")
@click.argument("model_dir", type=click.Path(path_type=Path))
@click.option("--window", "window", type=click.Path(path_type=Path), required=True,
              help="WINDOW.yaml: interface (thickness_mm, index, medium_index) and mount (camera | world).")
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: COLMAP model (pinhole approximation), calibration.json, refine.json.")
@click.option("--huber-px", type=float, default=2.0, show_default=True, help="Huber threshold (px).")
@click.option("--max-iterations", type=int, default=50, show_default=True)
@user_errors
def refine_colmap_cmd(model_dir: Path, window: Path, out: Path, huber_px: float, max_iterations: int) -> None:
    """Refine the COLMAP model in MODEL_DIR (made behind a flat window) with the exact refractive model."""
    from .colmap_refine import refine_colmap, write_refined
    from .colmap_refine.window import load_window

    spec = load_window(window)
    result = refine_colmap(model_dir, spec.interface, mount=spec.mount, units_mm=spec.units_mm,
                           scale_bar=spec.scale_bar, huber_px=huber_px, max_iterations=max_iterations, progress=True)
    write_refined(result, out)
    r = result.report
    click.echo(f"refine-colmap: {r['counts']['images']} images, {r['counts']['points3D']} points, "
               f"{r['iterations']} iterations, {r['time_s']:.1f} s; reprojection RMS {r['before']['rms_px']:.3f} px "
               f"(COLMAP pinhole) -> {r['after']['rms_px']:.3f} px (exact); COLMAP cameras written as their best "
               f"pinhole approximation ({r['pinhole_approximation']['rms_px']:.3f} px) -> {out}")

"""The ari-sfm command line. Errors print as one line: ``error: <file>: <what is wrong>``."""
from __future__ import annotations

import logging
import sys
import time
from enum import Enum
from pathlib import Path

import click
import numpy as np

from .. import _startup
from ..errors import AriSfmError
from ..models.registry import BUNDLE, CALIBRATABLE, COMPARED, MODELS, model_spec
from . import colmap as colmap_commands, particles as particle_commands
from .checks import check_not_an_output, check_not_input_folder, check_number, check_output_folder
from .config import config_option
from .process import QUALITY_FAILED_EXIT, CommandGroup, exit_if_signalled, setup_logging, user_errors

log = logging.getLogger("ari_sfm")


@click.group(cls=CommandGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="ari-sfm")
@click.option("-v", "--verbose", is_flag=True, help="Log progress messages.")
def main(verbose: bool) -> None:
    """Calibrate cameras behind a flat refractive window (ARI equation) and measure them."""
    setup_logging(verbose)


@main.command()
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), default=None,
              help="Output folder: observations.json and a rig.yaml naming it and DATASET's images, a dataset that "
                   "calibrate and run take without detecting again (default: <name>-detections beside DATASET; the "
                   "dataset's own files are never written).")
@click.option("--workers", type=int, default=None, help="Parallel detection threads (default: all cores).")
@user_errors
def detect(dataset: Path, out: Path | None, workers: int | None) -> None:
    """Detect target corners in the dataset's images; write OUT/observations.json and OUT/rig.yaml (the dataset
    with its corners: `ari-sfm calibrate OUT` starts from them)."""
    from ..detection import detect_dataset
    from ..io import detections_rig, load_dataset, save_detections

    if out is not None:
        check_output_folder(out)
    check_number("--workers", workers, minimum=1)
    ds = load_dataset(dataset)
    if out is not None:
        check_not_input_folder(out, ds.root, "the dataset's own folder (its observations.json would be overwritten)")
    if not any(entry.images for entry in ds.entries()):
        raise AriSfmError(ds.rig_path, "no images to detect: the dataset lists no image files (its corners are "
                                       "already in observations.json; calibrate or run it directly)")
    out = out or check_output_folder(ds.root.parent / f"{ds.root.name}-detections")
    detections_rig(out, ds)  # another dataset's rig.yaml in -o: refused before the detection
    t0 = time.perf_counter()
    obs = detect_dataset(ds, workers=workers, progress=True)
    rig = save_detections(out, ds, obs)
    n = sum(len(o.ids) for o in obs)
    click.echo(f"{len(obs)} images, {n} corners in {time.perf_counter() - t0:.1f} s -> {out / 'observations.json'}")
    click.echo(f"dataset with its corners: {rig} (ari-sfm calibrate {out} -o OUT)")


_model_option = click.option("--model", default=None, metavar="|".join(CALIBRATABLE),
                             help="; ".join(f"{m}: {MODELS[m].summary}" for m in CALIBRATABLE)
                             + ". Default: exact, the best model (its ari stage's figures shown beside it); "
                               "ari: the paper's model alone.")
_distortion_option = click.option("--distortion/--no-distortion", default=False, show_default=True,
                                  help="Estimate k1 k2 p1 p2 k3.")


def _field_option(name: str):
    """The click option of a CalibrationOptions field: flag, default and help from the field's metadata
    (the one place each default is declared); ``{field}`` in a help text is that field's default."""
    from dataclasses import fields

    from ..calibration.calibrate import CalibrationOptions

    every = {f.name: f for f in fields(CalibrationOptions)}
    f = every[name]
    meta = f.metadata
    kwargs = {"default": f.default, "help": meta["help"].format(**{k: v.default for k, v in every.items()})}
    if "/" not in meta["cli"]:  # "--x/--no-x": True, False or the default (None: decided from the data)
        if isinstance(f.default, bool):
            kwargs["is_flag"] = True
        elif isinstance(f.default, Enum):  # a mode: its values are the choices, CalibrationOptions takes them
            kwargs.update(default=f.default.value, type=click.Choice([m.value for m in type(f.default)]),
                          show_default=True)
        else:
            kwargs.update(type=type(f.default), show_default=True)
    return click.option(meta["cli"], name, **kwargs)


def _cli_fields() -> tuple[str, ...]:
    """The CalibrationOptions fields calibrate and run offer (those with a ``cli`` flag), in field order."""
    from dataclasses import fields

    from ..calibration.calibrate import CalibrationOptions

    return tuple(f.name for f in fields(CalibrationOptions) if "cli" in f.metadata)


_backend_option = _field_option("backend")


def _calibration_options(fn):
    """--model and every CalibrationOptions field with a ``cli`` flag (--distortion, --huber-px,
    --exclude-outliers, --fix-intrinsics, --backend), made from the dataclass."""
    for option in reversed((_model_option, *(_field_option(name) for name in _cli_fields()))):
        fn = option(fn)
    return fn


def _calibration_record(values: dict, progress: bool):
    """The CalibrationOptions of the command line's values (--huber-px 0: plain least squares), checked."""
    from ..calibration.calibrate import CalibrationOptions

    check_number("--huber-px", values["huber_px"], minimum=0.0)
    return CalibrationOptions(**{**values, "huber_px": values["huber_px"] or None}, progress=progress)


@main.command(name="calibrate")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="Output folder for calibration.json.")
@_calibration_options
@config_option
@user_errors
def calibrate_cmd(dataset: Path, out: Path, model: str | None, **options) -> None:
    """Calibrate DATASET; write OUT/calibration.json (and OUT/observations.json when detected here).

    Exit code 3: the calibration converged but failed its quality gate (written with quality.ok false)."""
    from ..calibration.calibrate import DEFAULT_MODEL
    from ..pipelines.calibrate_rig import main as pipeline

    model = model or DEFAULT_MODEL
    model_spec(model, "--model", calibratable=True)  # before any loading or detection
    check_output_folder(out)
    opts = _calibration_record(options, progress=True)
    t0 = time.perf_counter()
    result = pipeline(dataset, out, model=model, progress=True, options=opts)
    _summary(result.calibration, time.perf_counter() - t0, "corner detection, calibration, files")
    if result.observations_path:
        click.echo(f"observations: {result.observations_path}")
    click.echo(f"calibration:  {result.calibration_path}")
    _exit_if_failed(result.calibration)


@main.command()
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@_calibration_options
@click.option("--truth", type=click.Path(path_type=Path), default=None,
              help="A simulator's truth.json: also report the reconstruction's 3D error against it.")
@config_option
@user_errors
def run(dataset: Path, out: Path, model: str | None, truth: Path | None, **options) -> None:
    """The pipeline: detect corners when needed, calibrate, reconstruct (frames seen by two cameras), report.

    Exit code 3: the calibration failed its quality gate (no reconstruction)."""
    from ..pipelines.run import main as pipeline

    if model is not None:  # None: the best model (calibrate.DEFAULT_MODEL)
        model_spec(model, "--model", calibratable=True)  # before any loading or detection
    check_output_folder(out)
    opts = _calibration_record(options, progress=True)
    t0 = time.perf_counter()
    click.echo(f"ari-sfm run: {dataset} -> {out}")
    result = pipeline(dataset, out, model=model, truth=truth, progress=True, options=opts)
    _summary(result.calibrated.calibration, time.perf_counter() - t0,
             "corner detection, calibration, reconstruction, report")
    if result.truth_errors is not None:
        _truth_summary(result.truth_errors)
    click.echo(f"calibration: {result.calibrated.calibration_path}")
    if result.reconstruction is None:
        click.echo(f"info: reconstruction skipped: {result.skipped_reconstruction}")
    else:
        m = result.reconstruction.metrics
        click.echo(f"reconstruction: {m.num_points} points in {m.num_frames} frames, flatness rmse "
                   f"{m.flatness_mm.rmse:.4f} mm -> {result.reconstruction.metrics_path}")
        if m.truth:
            t = m.truth
            click.echo(f"3D error vs truth: rms {t.aligned_rms_mm:.4f} mm after rigid alignment (max "
                       f"{t.aligned_max_mm:.4f} mm), {t.unaligned_rms_mm:.4f} mm without")
    click.echo(f"report: {result.report_path}")
    _exit_if_failed(result.calibrated.calibration)


@main.command(name="report")
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--dataset", type=click.Path(path_type=Path), default=None,
              help="The dataset folder (default: from OUT/run.json, else OUT/metrics.json).")
@user_errors
def report_cmd(out: Path, dataset: Path | None) -> None:
    """Write OUT/report.html: one self-contained page of the calibration, residuals and reconstruction in OUT."""
    from ..report import write_report

    if out.exists() and not out.is_dir():
        raise AriSfmError(out, "is a file, expected the output folder of `ari-sfm run` or `calibrate`")
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
    from ..calibration.evaluate import evaluate
    from ..io import load_calibration

    cal = load_calibration(calibration)
    if cal.target is None:
        raise AriSfmError(calibration, "holds no target (the board's geometry: key target), which evaluate needs to "
                                       "project the corners; calibration.json written by ari-sfm calibrate has one")
    stats = evaluate(cal, observations, solve_poses=solve_poses)  # nothing to judge or NaN: one error line
    click.echo(f"rmse {stats.rmse_px:.4f} px  mae {stats.mae_px:.4f} px  max {stats.max_px:.4f} px  ({stats.count} "
               "corners)")


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
    from ..io import find_rig
    from ..reconstruction.reconstruct import run_reconstruction

    check_output_folder(out)
    check_number("--workers", workers, minimum=1)
    check_not_input_folder(out, find_rig(dataset).parent, "the dataset's own folder (points.json, metrics.json and "
                           "detected corners would be written into the dataset)")
    for option, given in (("--reference", reference), ("--truth", truth)):
        check_not_an_output(given, out, option)
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
        ref, reg = m.reference, m.reference.registration
        click.echo(f"vs reference {ref.kind}: distance rms {ref.distance_mm.rms:.4f} mm, max "
                   f"{ref.distance_mm.max:.4f} mm after registration (rotation {reg.rotation_deg:.3f} deg, "
                   f"translation {reg.translation_mm:.3f} mm)")
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
    from dataclasses import replace

    from ..calibration.calibrate import Backend
    from ..calibration.compare import COMPARE_OPTIONS, run_compare

    check_output_folder(out)
    options = replace(COMPARE_OPTIONS, distortion=distortion, backend=Backend(backend))
    files = run_compare(dataset, out, models, subset, holdout, pf_world, options)
    click.echo(files.md.read_text())
    click.echo("\n".join(f"{label}: {path}" for label, path in files.named()))


@main.command()
@click.argument("scenario")
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: OUT/dataset and OUT/truth.json.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (>= 0).")
@click.option("--sigma", type=float, default=None, help="Pixel noise per coordinate (default 0.05; particles: 0.1; "
                                                        "not for port_survey, whose images are rendered).")
@click.option("--image-scale", type=float, default=1.0, show_default=True, help="Scale of image size and focal length.")
@click.option("--images/--no-images", default=None, help="Render PNG images (default: per scenario; port_survey: "
                                                         "always).")
@click.option("--cameras", "num_cameras", type=int, default=4, show_default=True, help="particles: cameras on a ring.")
@click.option("--particles", "particles_per_frame", type=int, default=2000, show_default=True,
              help="particles: particles per frame (60 x 40 x 30 mm volume at ~400 mm, 10 mm glass, water).")
@click.option("--frames", "num_frames", type=int, default=10, show_default=True, help="particles: frames.")
@click.option("--render-frames", type=int, default=2, show_default=True,
              help="particles: frames rendered as images (Gaussian particle images).")
@click.option("--drift-deg", type=float, default=0.05, show_default=True,
              help="particles: rotation of each drifted camera after the target calibration.")
@click.option("--drift-mm", type=float, default=0.3, show_default=True,
              help="particles: translation of each drifted camera after the target calibration.")
@click.option("--drift-cameras", default="1,2,3", show_default=True,
              help="particles: indices of the drifted cameras (comma-separated; '' for none).")
@click.option("--look", type=click.Choice(["plain", "tank"]), default="plain", show_default=True,
              help="particles: rendered images on a flat background, or as a real tank looks (uneven background, "
                   "a reflection streak, bright blobs, shot noise, particles of varying brightness and size).")
@click.option("--bit-depth", type=click.Choice(["8", "16"]), default="8", show_default=True,
              help="particles: rendered images 8-bit (PNG) or 16-bit (TIFF).")
@click.option("--k1", type=float, default=0.0, show_default=True,
              help="particles: radial lens distortion (OpenCV k1) of every camera, e.g. -0.05.")
@click.option("--windows", type=click.Choice(["1", "2"]), default="1", show_default=True,
              help="particles: 2 for a tank seen through two opposite walls, half the cameras behind each.")
@click.option("--calibration-views", type=int, default=3, show_default=True,
              help="particles: views of rig A's calibration target (more views: better principal points, and a "
                   "better self-calibration from them).")
@click.option("--calibration-target", type=click.Choice(["body", "board"]), default="body", show_default=True,
              help="particles: rig A's target: a 3D body (three levels), or a planar checkerboard tilted 10-40 deg "
                   "(one window).")
@user_errors
def simulate(scenario: str, out: Path, seed: int, sigma: float | None, image_scale: float, images: bool | None,
             num_cameras: int, particles_per_frame: int, num_frames: int, render_frames: int, drift_deg: float,
             drift_mm: float, drift_cameras: str, look: str, bit_depth: str, k1: float, windows: str,
             calibration_views: int, calibration_target: str) -> None:
    """Write a simulated dataset (exact Snell physics) and its truth. SCENARIO: one of `ari-sfm scenarios`."""
    from ..simulate import SCENARIOS, simulate as run_sim

    if scenario not in SCENARIOS and scenario not in ("port_survey", "particles"):
        raise AriSfmError(None, f"unknown scenario {scenario!r}; known: "
                                f"{', '.join([*SCENARIOS, 'port_survey', 'particles'])}")
    check_number("--seed", seed, minimum=0)
    if scenario == "particles":  # a particle experiment: rig A's target calibration, drifted rig B, particles
        _simulate_particles(out, seed, 0.1 if sigma is None else sigma, num_cameras, particles_per_frame, num_frames,
                            render_frames, drift_deg, drift_mm, drift_cameras, look, int(bit_depth), k1, int(windows),
                            calibration_views, calibration_target)
        return
    if k1:
        raise AriSfmError("--k1", "is for the particles scenario")
    if calibration_views != 3 or calibration_target != "body":
        raise AriSfmError("--calibration-views" if calibration_views != 3 else "--calibration-target",
                          "is for the particles scenario")
    if windows != "1":
        raise AriSfmError("--windows", "is for the particles scenario (tank_opposite and tank_adjacent are the "
                                       "two-window target scenarios)")
    check_output_folder(out)
    check_number("--sigma", sigma, minimum=0.0, maximum=100.0)
    check_number("--image-scale", image_scale, minimum=MIN_IMAGE_SCALE, maximum=40.0)
    if scenario == "port_survey":  # structure from motion behind a flat port (refine-colmap's truth)
        from ..simulate.port_survey import write_port_survey

        if sigma is not None:
            raise AriSfmError("--sigma", "does not apply to port_survey: its images are rendered (structure from "
                                         "motion finds the features and their noise)")
        if images is False:
            raise AriSfmError("--no-images", "port_survey is only images (structure from motion starts from them)")
        check_number("--image-scale", image_scale, maximum=MAX_PORT_SURVEY_SCALE)  # rendered supersampled
        size = (max(16, int(round(640 * image_scale))), max(16, int(round(480 * image_scale))))
        write_port_survey(out, seed=seed, image_size=size, focal_px=600.0 * image_scale, progress=True)
        click.echo(f"port_survey: {out / 'images'} and {out / 'truth.json'}")
        return
    ds, truth = run_sim(scenario, out, seed=seed, sigma_px=0.05 if sigma is None else sigma, images=images,
                        image_scale=image_scale)
    click.echo(f"dataset: {ds}\ntruth:   {truth}")


def _simulate_particles(out: Path, seed: int, sigma: float, num_cameras: int, particles_per_frame: int,
                        num_frames: int, render_frames: int, drift_deg: float, drift_mm: float, drift_cameras: str,
                        look: str = "plain", bit_depth: int = 8, k1: float = 0.0, windows: int = 1,
                        calibration_views: int = 3, calibration_target: str = "body") -> None:
    """`simulate particles`: write OUT/calibration, OUT/experiment, OUT/truth (ari_sfm.simulate.particles)."""
    from ..simulate.particles import ParticleSimOptions, simulate_particle_experiment, write_particle_experiment

    check_output_folder(out)
    check_number("--sigma", sigma, minimum=0.0, maximum=100.0)
    check_number("--cameras", num_cameras, minimum=2, maximum=8)
    check_number("--particles", particles_per_frame, minimum=1, maximum=1e6)
    check_number("--frames", num_frames, minimum=1, maximum=1e6)
    check_number("--render-frames", render_frames, minimum=0, maximum=num_frames)
    check_number("--drift-deg", drift_deg, minimum=0.0, maximum=10.0)
    check_number("--drift-mm", drift_mm, minimum=0.0, maximum=100.0)
    check_number("--k1", k1, minimum=-0.5, maximum=0.5)
    check_number("--calibration-views", calibration_views, minimum=1, maximum=100)
    if calibration_target == "board" and windows != 1:
        raise AriSfmError("--calibration-target", "board is seen from one side: it needs --windows 1")
    try:
        drifted = tuple(int(c) for c in drift_cameras.split(",") if c.strip())
    except ValueError:
        raise AriSfmError("--drift-cameras",
                          f"must be camera indices separated by commas (got {drift_cameras!r})") from None
    bad = [c for c in drifted if not 0 <= c < num_cameras]
    if bad:
        raise AriSfmError("--drift-cameras", f"{bad} not among the cameras 0..{num_cameras - 1}")
    options = ParticleSimOptions(num_cameras=num_cameras, particles_per_frame=particles_per_frame,
                                 num_frames=num_frames, sigma_px=sigma, drift_cameras=drifted, drift_deg=drift_deg,
                                 drift_mm=drift_mm, look=look, bit_depth=bit_depth, k1=k1, windows=windows, seed=seed,
                                 calibration_frames=calibration_views, calibration_target=calibration_target)
    folders = write_particle_experiment(simulate_particle_experiment(options), out, render_frames=render_frames)
    click.echo(f"calibration dataset (rig A): {folders.calibration}\nexperiment (rig B):          "
               f"{folders.experiment}\ntruth:                       {folders.truth} (rig_a.json, rig_b.json, "
               "particles.parquet, detections.parquet)")


MIN_IMAGE_SCALE = 0.05  # smaller: port_survey's 640 x 480 images become 32 x 24 px, paper_single's focal 174 px
MAX_PORT_SURVEY_SCALE = 8.0  # 5120 x 3840 px images (rendered at twice that): larger ones exhaust memory


@main.command()
def scenarios() -> None:
    """List the simulator's scenarios."""
    from ..simulate import SCENARIOS

    for name, text in [*SCENARIOS.items(), ("port_survey", PORT_SURVEY)]:
        click.echo(f"{name:28s} {text}")
    click.echo(f"{'particles':28s} a particle experiment: 4 cameras, 10 mm glass into water, 2000 particles per frame "
               "in 60 x 40 x 30 mm at ~400 mm, 0.1 px noise; rig A's body calibration, drifted rig B, images, truth")


PORT_SURVEY = ("rendered images of a lawn-mower survey by one camera in a flat-port housing over a relief "
               "(OUT/images, OUT/truth.json: structure from motion, then refine-colmap)")


@main.command()
@user_errors
def doctor() -> None:
    """Check every dependency: its version, or why it does not load (open3d needs the system library
    libusb-1.0-0); and whether the compiled kernels shipped with ari-sfm run on this machine.

    Exit code 1: a required dependency does not load (optional ones, such as optv, are only reported)."""
    import platform

    from ..deps import check_dependencies
    from ..kernel_cache import shipped_usable

    found = check_dependencies()
    exit_if_signalled()  # an import turned Ctrl-C into its own error (pycolmap: "Cannot import the C++ backend")
    from importlib import metadata

    click.echo(f"{'ari-sfm':12s} {metadata.version('ari-sfm')} (Python {platform.python_version()}, "
               f"{platform.machine()})")
    for d in found:
        if d.ok:
            state = d.version
        elif d.optional:
            state = f"not available ({d.error}; optional: {d.purpose})"
        else:
            state = f"error: {d.error}"
        click.echo(f"{d.name:12s} {state}")
    usable, why = shipped_usable()
    click.echo(f"{'kernels':12s} " + (f"compiled, shipped: {why}" if usable else
                                       f"compiled on first use by numba ({why})"))
    sys.exit(1 if any(not d.ok and not d.optional for d in found) else 0)




def _exit_if_failed(cal) -> None:
    """Exit 3 when the calibration failed its quality gate (its summary said so)."""
    if cal.quality is not None and not cal.quality.ok:
        sys.exit(QUALITY_FAILED_EXIT)


def _truth_summary(errors) -> None:
    """The calibrated parameters' errors against a simulator's truth (calibrated minus true)."""
    head = f"vs truth (calibrated - true): normal {_std(errors.normal_deg, '.4f')}°"
    if errors.distance_mm is not None:
        head += f", window distance {errors.distance_mm:+.3f} mm"
    click.echo(head)
    for w in errors.windows:
        click.echo(f"  window {w.name}: normal {_std(w.normal_deg, '.4f')}°"
                   + ("" if w.distance_mm is None else f", distance {w.distance_mm:+.3f} mm"))
    for c in errors.cameras:
        rel = ("" if c.rotation_deg is None else
               f"  cam_from_{errors.reference_camera} {c.rotation_deg:.4f}° {c.translation_mm:.4f} mm")
        click.echo(f"  {c.name:8s} fx {c.fx_pct:+.4f} % fy {c.fy_pct:+.4f} % cx {c.cx_px:+.3f} px "
                   f"cy {c.cy_px:+.3f} px k1 {c.k1:+.5f}{rel}")


def _stages_summary(cal) -> None:
    """Each stage's residuals and focal lengths beside the final model's (calibration.json ``stages``)."""
    if len(cal.stages) < 2:
        return
    click.echo("stages:")
    for st in cal.stages:
        fx = " ".join(f"{n} fx {c.fx:.2f}" for n, c in list(st.cameras.items())[:4])
        click.echo(f"  {st.stage:16s} {st.model or '?':6s} rmse {st.rmse_px or float('nan'):.4f} px, "
                   f"max {st.max_px or float('nan'):.4f} px{', distortion' if st.distortion else ''}; {fx}")


def _summary(cal, elapsed: float, covers: str = "the whole command") -> None:
    """A one-screen summary of a calibration."""
    from ..geometry import angle_between_deg

    r = cal.residuals
    q = cal.quality
    if q is not None and not q.ok:
        click.echo(f"\nQUALITY GATE FAILED (exit 3): {q.why} [starts tried: {', '.join(q.starts)}]")
    click.echo(f"\nmodel {cal.model}: {len(cal.cameras)} camera(s), {len(cal.frames)} frames, "
               + ", ".join(f"window{' ' + w.name if cal.windows else ''} {w.interface.thickness_mm:g} mm "
                           f"n={w.interface.index:g}" for w in cal.window_list())
               + f" medium n={cal.interface.medium_index:g}")
    for w in cal.window_list():
        nw, label = w.normal_world, f"window {w.name} ({', '.join(w.cameras)}): " if cal.windows else ""
        if nw is None:
            click.echo("normal: none (the window is ignored)")
        else:
            click.echo(f"{label}normal (world) [{nw[0]:+.5f} {nw[1]:+.5f} {nw[2]:+.5f}]"
                       + (f"  distance {w.interface.distance_mm:.3f} mm"
                          + (f" from {w.cameras[0]}" if cal.windows else "")
                          if w.interface.distance_mm is not None else ""))
    click.echo(f"{'camera':10s} {'fx':>9s} {'fy':>9s} {'cx':>8s} {'cy':>8s} {'tilt':>6s} "
               f"{'expansion centre (px)':>26s} {'rmse':>7s}")
    for name, c in cal.cameras.items():
        tilt = (float("nan") if cal.window_of(name).normal_world is None
                else angle_between_deg(cal.normal_cam(name), np.array([0, 0, 1.0])))
        ec = "-" if c.expansion_center_px is None else (
            f"{c.expansion_center_px[0]:.1f},{c.expansion_center_px[1]:.1f} ±{max(c.expansion_center_std_px):.2f}")
        click.echo(f"{name:10s} {c.K[0,0]:9.2f} {c.K[1,1]:9.2f} {c.K[0,2]:8.2f} {c.K[1,2]:8.2f} {tilt:5.2f}° {ec:>26s} "
                   f"{c.rmse_px:7.4f}")
    u = cal.uncertainty
    if u:
        if u.windows:
            click.echo(f"standard deviations (sigma {u.sigma_px:.3f} px): "
                       + "; ".join(f"window {n} normal {_std(w.normal_deg, '.4f')}°"
                                   + (f", distance {_std(w.distance_mm, '.4f')} mm" if u.estimates_distance else "")
                                   for n, w in u.windows.items()))
        else:
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
    click.echo(f"residuals: rmse {r.rmse_px:.4f} px, mae {r.mae_px:.4f} px, max {r.max_px:.4f} px over {r.count} "
               "corners")
    if q is not None and q.ok:
        floor = "n/a" if q.floor_rmse_px is None else f"{q.floor_rmse_px:.4f} px" + (
            "" if q.allowance_px is None else f", at most {q.allowance_px:.4f} px")
        exact = ("" if q.exact_robust_rmse_px is None
                 else f"; exact model with the same window {q.exact_robust_rmse_px:.4f} px")
        click.echo(f"quality: ok (robust rmse {q.robust_rmse_px:.4f} px; the corners' floor {floor}{exact})")
    _stages_summary(cal)
    click.echo(f"time: calibration {cal.time_s:.3f} s (analytic start and bundle-adjustment stages), "
               f"total {elapsed:.2f} s ({covers})")


def _std(value: float | None, spec: str) -> str:
    """A standard deviation for the summary ('n/a' when the data do not determine it)."""
    return "n/a" if value is None else format(value, spec)


@main.group(name="import")
def import_group() -> None:
    """Import another tool's experiment as an ari-sfm dataset."""


@import_group.command(name="openptv")
@click.argument("experiment", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="New dataset folder (rig.yaml, observations.json where .crd files exist, the calibration images).")
@click.option("--windows", "window_groups", default=None,
              help="Which cameras share a window, e.g. 'cam1,cam2;cam3,cam4' (default: told from the .ori glass "
                   "vectors, else from the cameras' viewing directions resected from their clicked points).")
@user_errors
def import_openptv_cmd(experiment: Path, out: Path, window_groups: str | None) -> None:
    """Read an OpenPTV EXPERIMENT folder (ptv.par, cal_ori.par or multi_planes.par, .fix/.crd, the calibration
    images with man_ori.dat's clicked points, .ori when present) as a dataset."""
    from ..io import load_dataset
    from ..openptv import import_experiment

    check_output_folder(out)
    rig = import_experiment(experiment, out, window_groups)
    ds = load_dataset(rig)
    n_obs = sum(len(o.ids) for o in ds.observations or ())
    images = sum(len(e.images) for e in ds.calibration)
    clicked = sum(len(e.manual_points) for e in ds.calibration)
    extra = f", {images} calibration images, clicked points for {clicked} cameras" if images else ""
    click.echo(f"dataset: {rig}\n{len(ds.cameras)} cameras ({', '.join(ds.cameras)}), "
               f"{ds.target.num_ids()} body points, {n_obs} observations{extra}")
    if ds.windows:
        click.echo("windows: " + "; ".join(f"{w.name} ({', '.join(w.cameras)})" for w in ds.windows))


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
    from ..openptv import export_openptv

    check_output_folder(out)
    summary = export_openptv(calibration, out, frame=frame, pixel_size_mm=pixel_size_mm)
    click.echo(f"frame {summary.frame}, pixel size {summary.pixel_size_mm[0]:g} x {summary.pixel_size_mm[1]:g} mm")
    for name, number in summary.numbers.items():
        fit = summary.fit_error_px.get(name)
        click.echo(f"  {name} -> cam{number}" + (f" (distortion fitted, max {fit:.2g} px)" if fit is not None else ""))
    click.echo("\n".join(str(f) for f in summary.files))


main.add_command(colmap_commands.export_colmap_cmd)
main.add_command(colmap_commands.sfm_cmd)
main.add_command(colmap_commands.export_colmap_fork_cmd)
main.add_command(colmap_commands.import_colmap_fork_cmd)
main.add_command(colmap_commands.refine_colmap_cmd)
main.add_command(particle_commands.detect_particles_cmd)
main.add_command(particle_commands.particles_cmd)
main.add_command(particle_commands.self_calibrate_cmd)
_startup.loaded()  # every command is defined: the commands' own handlers (user_errors) from here on

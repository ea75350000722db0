"""The COLMAP commands: export-colmap, sfm, export-colmap-fork, import-colmap-fork and refine-colmap
(registered on the command line's group by :mod:`ari_sfm.cli`)."""
from __future__ import annotations

import os
from pathlib import Path

import click

from ..colmap.refine import settings as REFINE
from ..errors import AriSfmError
from .checks import check_number, check_output_folder
from .process import user_errors


@click.command(name="export-colmap")
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
def export_colmap_cmd(calibration: Path, out: Path, dataset: Path | None, points: Path | None,
                      approximation: str) -> None:
    """Write CALIBRATION as a COLMAP model (cameras, rig, frames, images, 3D points with tracks) to OUT."""
    from ..colmap.adapter import export_colmap, summary

    check_output_folder(out)
    folder = calibration.parent  # an `ari-sfm run` folder: its observations, dataset and points by default
    if dataset is None and not (folder / "observations.json").is_file():
        from ..report import find_dataset

        dataset = find_dataset(folder)
    if points is None and (folder / "points.json").is_file():
        points = folder / "points.json"

    click.echo(summary(export_colmap(calibration, out, dataset=dataset, points=points, approximation=approximation)))



@click.command(name="sfm")
@click.argument("images", type=click.Path(path_type=Path))
@click.option("--window", "window", type=click.Path(path_type=Path), required=True,
              help="WINDOW.yaml: interface (thickness_mm, index, medium_index), mount (camera | world), and the "
                   "scale: units_mm or scale_bar (see refine-colmap), unless --baseline gives it.")
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: colmap/ (COLMAP's database and pinhole model), refined/ (refine-colmap's "
                   "model, calibration.json, refine.json), sfm.json.")
@click.option("--matcher", type=click.Choice(["auto", "exhaustive", "sequential"]), default="auto", show_default=True,
              help="Image pairs to match: all (exhaustive), or each image with its --overlap successors in name "
                   "order (sequential: long surveys, no vocabulary tree); auto: exhaustive up to 200 images.")
@click.option("--overlap", type=int, default=10, show_default=True, help="Sequential matching: successors per image.")
@click.option("--focal-px", type=float, default=None, help="Focal length prior (px) of the camera behind the window.")
@click.option("--baseline", type=(str, str, float), default=None, metavar="IMAGE IMAGE MM",
              help="The scale: the distance (mm) between two images' camera centres (e.g. from navigation).")
@click.option("--max-features", type=int, default=4000, show_default=True, help="SIFT features per image.")
@click.option("--huber-px", type=float, default=REFINE.HUBER_PX, show_default=True,
              help="refine-colmap's Huber threshold (px).")
@click.option("--max-iterations", type=int, default=REFINE.MAX_ITERATIONS, show_default=True,
              help="Cap on refine-colmap's accepted Levenberg-Marquardt steps (>= 1).")
@click.option("--threads", type=int, default=-1, show_default=True, help="COLMAP's threads (-1: all cores).")
@user_errors
def sfm_cmd(images: Path, window: Path, out: Path, matcher: str, overlap: int, focal_px: float | None,
            baseline: tuple[str, str, float] | None, max_features: int, huber_px: float, max_iterations: int,
            threads: int) -> None:
    """Structure from motion behind a flat window: COLMAP's SIFT, matching and incremental mapping (CPU),
    then refine-colmap with the exact refractive model, in one command."""
    from ..colmap.sfm import Matcher, SfmOptions, run_sfm

    check_output_folder(out)
    check_number("--overlap", overlap, minimum=1)
    check_number("--focal-px", focal_px, minimum=0.0, strict_minimum=True)
    check_number("--max-features", max_features, minimum=1)
    check_number("--huber-px", huber_px, minimum=0.0, strict_minimum=True)
    check_number("--max-iterations", max_iterations, minimum=1)
    if baseline is not None:
        check_number("--baseline", baseline[2], minimum=0.0, strict_minimum=True)
    result = run_sfm(images, window, out, SfmOptions(
        matcher=Matcher(matcher), overlap=overlap, max_features=max_features, focal_px=focal_px, baseline=baseline,
        huber_px=huber_px, max_iterations=max_iterations, num_threads=threads, progress=True))
    report = result.refine.report
    rms = (f"; reprojection RMS {report.before.rms_px:.3f} px (COLMAP pinhole) -> "
           f"{report.after.rms_px:.3f} px (exact)")
    click.echo(f"COLMAP: {result.registered} of {result.images} images registered, {result.points3D} points "
               f"-> {result.colmap_model}"
               + (f" (not registered: {', '.join(result.unregistered)})" if result.unregistered else ""))
    click.echo(f"refine-colmap{rms} -> {result.refined}")
    click.echo(f"summary: {result.summary_path}")

_units_option = click.option("--units-mm", type=float, default=1000.0, show_default=True,
                             help="mm per length unit of the fork's model (int_dist, int_thick, poses, points): "
                                  "1000 = metres, as in the fork's examples.")


@click.command(name="export-colmap-fork")
@click.argument("calibration", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: cameras.txt (FLATPORT), images.txt, points3D.txt of the refractive COLMAP fork.")
@click.option("--dataset", type=click.Path(path_type=Path), default=None,
              help="Dataset whose calibration corners become the images' 2D points and the 3D points (default: a "
                   "refine-colmap output's COLMAP model beside CAL, its images at their real poses and the refined "
                   "points; else observations.json beside CAL; else cameras and poses only).")
@_units_option
@user_errors
def export_colmap_fork_cmd(calibration: Path, out: Path, dataset: Path | None, units_mm: float) -> None:
    """Write an exact CALIBRATION as a model of the refractive COLMAP fork (colmap_underwater, FLATPORT cameras)."""
    from ..colmap.fork import check_units_mm, export_colmap_fork
    from ..io import load_calibration, load_observations
    from ..report import find_dataset

    check_output_folder(out)
    check_units_mm(units_mm)
    cal = load_calibration(calibration)
    observations, refined = None, None
    folder = calibration.parent
    if dataset is None and cal.refine_colmap is not None and any((folder / f"cameras.{x}").is_file()
                                                                for x in ("bin", "txt")):
        refined = folder  # a refine-colmap output: its images at their real poses and the refined points
    elif dataset is None and (folder / "observations.json").is_file():
        observations = load_observations(folder / "observations.json", cal.target, list(cal.cameras))
    elif dataset is None:
        dataset = find_dataset(folder)  # an `ari-sfm run` folder: the dataset its run.json / metrics.json name
    done = export_colmap_fork(cal, out, observations, units_mm, refined_model=refined, dataset=dataset,
                              calibration_path=calibration)
    click.echo(f"{done.cameras} FLATPORT camera(s), {done.images} images, {done.points3D} points3D "
               f"(lengths in units of {units_mm:g} mm) -> {out}")


@click.command(name="import-colmap-fork")
@click.argument("model_dir", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True, help="Output folder for calibration.json.")
@_units_option
@user_errors
def import_colmap_fork_cmd(model_dir: Path, out: Path, units_mm: float) -> None:
    """Read the FLATPORT cameras of a refractive COLMAP fork text model (MODEL_DIR/cameras.txt, images.txt) as
    an exact-model calibration.json."""
    from ..colmap.fork import check_units_mm, import_colmap_fork
    from ..io import save_calibration

    check_output_folder(out)
    check_units_mm(units_mm)
    if out.resolve() == model_dir.resolve():
        raise AriSfmError(out, "-o/--out: is the input model folder (choose another folder)")
    cal = import_colmap_fork(model_dir, units_mm)
    save_calibration(cal, out / "calibration.json")
    def plate(w) -> str:
        name = f"window {w.name} ({', '.join(w.cameras)})" if cal.windows else "window"
        return f"{name} {w.interface.thickness_mm:g} mm n={w.interface.index:g} medium n={w.interface.medium_index:g}"

    windows = "; ".join(plate(w) for w in cal.window_list())
    click.echo(f"{len(cal.cameras)} camera(s) ({', '.join(cal.cameras)}), {windows} -> {out / 'calibration.json'}")


@click.command(name="refine-colmap")
@click.argument("model_dir", type=click.Path(path_type=Path))
@click.option("--window", "window", type=click.Path(path_type=Path), required=True,
              help="WINDOW.yaml: interface (thickness_mm, index, medium_index), mount (camera | world), "
                   "units_mm or scale_bar.")
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder (not MODEL_DIR): COLMAP model (the cameras' best OPENCV or PINHOLE "
                   "approximation), calibration.json, refine.json.")
@click.option("--huber-px", type=float, default=REFINE.HUBER_PX, show_default=True, help="Huber threshold (px, > 0).")
@click.option("--max-iterations", type=int, default=REFINE.MAX_ITERATIONS, show_default=True,
              help="Cap on the accepted Levenberg-Marquardt steps of the final refinement (>= 1).")
@user_errors
def refine_colmap_cmd(model_dir: Path, window: Path, out: Path, huber_px: float, max_iterations: int) -> None:
    """Refine the COLMAP model in MODEL_DIR (made behind a flat window) with the exact refractive model."""
    from ..colmap.refine import refine_colmap, write_refined
    from ..colmap.refine.options import RefineColmapOptions
    from ..colmap.refine.window import load_window

    check_number("--huber-px", huber_px, 0.0, strict_minimum=True)
    check_number("--max-iterations", max_iterations, 1)
    check_output_folder(out)
    if out.exists() and model_dir.exists() and os.path.realpath(out) == os.path.realpath(model_dir):
        raise AriSfmError(out, "-o/--out: is MODEL_DIR: refine-colmap does not overwrite its input model "
                               "(write to another folder)")
    spec = load_window(window)
    options = RefineColmapOptions(mount=spec.mount, units_mm=spec.units_mm, scale_bar=spec.scale_bar,
                                  huber_px=huber_px, max_iterations=max_iterations)
    result = refine_colmap(model_dir, spec.interface, options, progress=True, plane_path=window, window_path=window)
    write_refined(result, out)
    r = result.report
    u = r.uncertainty
    click.echo(f"refine-colmap: {r.counts.images} images, {r.counts.points3D} points, "
               f"{r.iterations} iterations ({'converged' if r.converged else 'NOT converged'}), "
               f"{r.time_s:.1f} s; reprojection RMS {r.before.rms_px:.3f} px "
               f"(COLMAP pinhole) -> {r.after.rms_px:.3f} px (exact)")
    for name in {**u.distance_mm, **u.normal_deg}:
        d = r.window.distance_of(name)
        parts = [f"distance {d:.2f} +- {u.distance_mm[name]:.2g} mm" if name in u.distance_mm else "",
                 f"normal +- {u.normal_deg[name]:.2g} deg" if name in u.normal_deg else ""]
        click.echo(f"  window {name}: " + ", ".join(p for p in parts if p) + " (1 sigma)")
    if u.scale_rel is not None:
        click.echo(f"  scale: +- {100 * u.scale_rel:.2g} % (1 sigma)"
                   + (f"; scale bar {r.scale_bar.refined_mm:.6g} mm (declared {r.scale_bar.declared_mm:.6g})"
                      if r.scale_bar is not None else ""))
    if u.weak:
        click.echo(f"  barely determined by these images: {', '.join(u.weak)} (see the warnings)")
    click.echo(f"  COLMAP cameras written as their best "
               f"{r.pinhole_approximation.model} approximation ({r.pinhole_approximation.rms_px:.3f} px) "
               f"-> {out}")

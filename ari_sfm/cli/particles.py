"""The particle commands: detect-particles, particles and self-calibrate (their Dask options; registered on
the command line's group by :mod:`ari_sfm.cli`)."""
from __future__ import annotations

import sys
from pathlib import Path

import click

from ..errors import AriSfmError
from .checks import check_number, check_output_folder
from .config import config_option
from .process import QUALITY_FAILED_EXIT, user_errors

_workers_option = click.option("--workers", type=int, default=1, show_default=True,
                               help="Dask LocalCluster worker processes, one thread each (0: in this process).")


def _set_worker_timeout(ctx: click.Context, param: click.Parameter, value: float) -> float:
    from ..particles.engine import worker_timeout

    token = worker_timeout.set(float(value))  # checked by dask_client, inside the command (one error line)
    ctx.call_on_close(lambda: worker_timeout.reset(token))  # for this command only
    return value


def _scheduler_option(fn):
    """--scheduler, and --worker-timeout (how long a run waits with no Dask worker; read by
    ari_sfm.particles.engine.dask_client through its context variable, so the command passes nothing)."""
    from ..particles.engine import WORKER_TIMEOUT_S

    fn = click.option("--worker-timeout", type=float, default=WORKER_TIMEOUT_S, show_default=True,
                      expose_value=False, callback=_set_worker_timeout, metavar="SECONDS",
                      help="Stop (one error line) when no Dask worker has been connected for this long; "
                           "a worker joining before then: the run goes on.")(fn)
    return click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
                        help="An existing Dask scheduler (e.g. a SLURM cluster via dask-jobqueue) "
                             "instead of a LocalCluster.")(fn)


@click.command(name="detect-particles")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: particles.parquet, detect-particles.json, parts/ (resumable).")
@click.option("--diameter-px", type=float, default=None, help="Particle image diameter (default: rig.yaml's, else 3).")
@click.option("--threshold-sigma", type=float, default=None,
              help="Peaks above the local background by this many local noise sigmas (default 5).")
@click.option("--min-peak", type=float, default=None,
              help="And at least this many grey levels above it (default 0: the noise alone decides).")
@click.option("--threshold", type=float, default=None,
              help="Grey levels above the local background for a peak and for a pixel of an image, every camera "
                   "(OpenPTV's grey threshold; default: rig.yaml's particles.detect, else none).")
@click.option("--min-pixels", type=int, default=None,
              help="Pixels above the threshold an image needs (default: rig.yaml's, else half the hint's e^-2 disc).")
@click.option("--max-pixels", type=int, default=None,
              help="Pixels above the threshold an image may have (default: rig.yaml's, else from the hint).")
@click.option("--min-sum", type=float, default=None,
              help="Grey sum of an image's pixels above the local background (OpenPTV's sumg_min; default 0).")
@click.option("--relative-floor", type=float, default=None,
              help="Peak at least this fraction of the frame's bright particle images' "
                   "(default e^-2 = 0.135; 0: none).")
@click.option("--frames-per-partition", type=int, default=20, show_default=True)
@_workers_option
@_scheduler_option
@user_errors
def detect_particles_cmd(dataset: Path, out: Path, diameter_px: float | None, threshold_sigma: float | None,
                         min_peak: float | None, threshold: float | None, min_pixels: int | None,
                         max_pixels: int | None, min_sum: float | None, relative_floor: float | None,
                         frames_per_partition: int, workers: int, scheduler: str | None) -> None:
    """Find the particle images of DATASET's particles.images; write OUT/particles.parquet. The options
    override rig.yaml's particles.detect."""
    from ..io.particles import load_particle_dataset
    from ..particles.detect import detect_experiment, detect_options

    check_output_folder(out)
    check_number("--diameter-px", diameter_px, minimum=0.0, maximum=1000.0, strict_minimum=True)
    check_number("--threshold-sigma", threshold_sigma, minimum=0.0, strict_minimum=True)
    check_number("--min-peak", min_peak, minimum=0.0)
    check_number("--threshold", threshold, minimum=0.0)
    check_number("--min-pixels", min_pixels, minimum=1)
    check_number("--max-pixels", max_pixels, minimum=1)
    check_number("--min-sum", min_sum, minimum=0.0)
    check_number("--relative-floor", relative_floor, minimum=0.0)
    check_number("--frames-per-partition", frames_per_partition, minimum=1)
    check_number("--workers", workers, minimum=0, maximum=1024)
    options = detect_options(load_particle_dataset(dataset), diameter_px=diameter_px, threshold_sigma=threshold_sigma,
                             min_peak=min_peak, threshold=threshold, min_pixels=min_pixels, max_pixels=max_pixels,
                             min_sum=min_sum, relative_floor=relative_floor)
    lo, hi, _, _ = options.pixel_limits()
    if lo > hi:
        raise AriSfmError("--min-pixels", f"{lo} pixels above the most an image may have ({hi}: --max-pixels or "
                                          "rig.yaml's particles.detect.max_pixels)")
    s = detect_experiment(dataset, out, options,
                          frames_per_partition=frames_per_partition, workers=workers, scheduler=scheduler,
                          progress=True)
    click.echo(f"{s.detections} particle images in frames {s.frames[0]}..{s.frames[1]} "
               f"({', '.join(f'{c}: {n}' for c, n in s.per_camera.items())}) in {s.time_s:.1f} s "
               f"-> {out / 'particles.parquet'}")


@click.command(name="particles")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--calibration", type=click.Path(path_type=Path), required=True, help="calibration.json of the rig.")
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: particles3d.parquet, particles3d.json, parts/ (resumable).")
@click.option("--detections", type=click.Path(path_type=Path), default=None,
              help="A particles.parquet (default: the one rig.yaml names; e.g. detect-particles' output).")
@click.option("--tolerance-px", type=float, default=0.5, show_default=True,
              help="Distance of a candidate from the refracted epipolar curve, and of each ray from the point.")
@click.option("--min-cameras", type=int, default=3, show_default=True, help="Images per particle.")
@click.option("--depth-range", type=float, nargs=2, default=None, metavar="ZMIN ZMAX",
              help="World z range (mm) of the particles, instead of rig.yaml's particles.volume_mm.")
@click.option("--frames-per-partition", type=int, default=50, show_default=True)
@_workers_option
@_scheduler_option
@config_option
@user_errors
def particles_cmd(dataset: Path, calibration: Path, out: Path, detections: Path | None, tolerance_px: float,
                  min_cameras: int, depth_range: tuple[float, float] | None, frames_per_partition: int, workers: int,
                  scheduler: str | None) -> None:
    """Match particle images through the window and triangulate them: OUT/particles3d.parquet."""
    from ..particles.reconstruct import MatchOptions, reconstruct_particles

    check_output_folder(out)
    check_number("--tolerance-px", tolerance_px, minimum=0.0, maximum=100.0, strict_minimum=True)
    check_number("--min-cameras", min_cameras, minimum=2, maximum=64)
    check_number("--frames-per-partition", frames_per_partition, minimum=1)
    check_number("--workers", workers, minimum=0, maximum=1024)
    _check_depth_range(depth_range)
    options = MatchOptions(tolerance_px=tolerance_px, min_cameras=min_cameras,
                           depth_range_mm=None if depth_range is None else (depth_range[0], depth_range[1]),
                           frames_per_partition=frames_per_partition)
    s = reconstruct_particles(dataset, calibration, out, options, detections_path=detections, workers=workers,
                              scheduler=scheduler, progress=True)
    gap = "n/a" if s.mean_ray_gap_mm is None else f"{s.mean_ray_gap_mm:.4f} mm"
    click.echo(f"{s.particles} particles in {len(s.frames)} frames, triangulated from {s.detections_used} of the "
               f"{s.detections_total} detections (2-D particle images; {100 * s.matched_fraction:.1f} % used), "
               f"mean ray gap {gap}, {s.time_s:.1f} s ({s.particles_per_second:.0f} particles/s)"
               + (f", {len(s.partitions_skipped)} partitions resumed" if s.partitions_skipped else ""))
    click.echo(f"particles: {out / 'particles3d.parquet'}\nsummary:   {out / 'particles3d.json'}")


@click.command(name="self-calibrate")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--calibration", type=click.Path(path_type=Path), required=True,
              help="calibration.json of the rig (exact model), e.g. from its target calibration.")
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: calibration.json (corrected), disparity.json.")
@click.option("--detections", type=click.Path(path_type=Path), default=None,
              help="A particles.parquet (default: the one rig.yaml names).")
@click.option("--frames", type=int, default=10, show_default=True, help="Frames used (spread over the experiment).")
@click.option("--coarse-frames", type=int, default=3, show_default=True,
              help="Frames matched in the loose rounds (tolerance > 2 px): the slow, ghost-ridden ones.")
@click.option("--tolerance-px", type=float, default=5.0, show_default=True,
              help="First round's matching tolerance: the drift must fit in it.")
@click.option("--max-tolerance-px", type=float, default=12.0, show_default=True,
              help="The first round widens its tolerance (x1.6) up to this while it finds no disparity peak.")
@click.option("--final-tolerance-px", type=float, default=0.5, show_default=True,
              help="The tolerance the rounds tighten to (halving).")
@click.option("--min-cameras", type=int, default=4, show_default=True, help="Images per match used.")
@click.option("--cells", type=int, nargs=3, default=(3, 3, 3), show_default=True, metavar="NX NY NZ",
              help="Sub-volumes of the disparity maps.")
@click.option("--peak-radius-px", type=float, default=0.5, show_default=True,
              help="A match is on its cell's disparity peak within this distance in every camera.")
@click.option("--max-rounds", type=int, default=6, show_default=True)
@click.option("--intrinsics", type=click.Choice(["prior", "held", "free"]), default="prior", show_default=True,
              help="fx fy cx cy (and k1 when CAL has distortion): estimated with CAL's sigmas as priors, held, "
                   "or estimated without priors.")
@click.option("--refine-intrinsics", is_flag=True, hidden=True, help="Old name of --intrinsics free.")
@click.option("--refine-window", is_flag=True, hidden=True,
              help="Old option: the window's pose relative to the cameras is now always estimated.")
@click.option("--backend", type=click.Choice(["numpy", "gtsam"]), default="numpy", show_default=True,
              help="Bundle-adjustment solver (the same problem; gtsam: at most 400 particles per round, its time "
                   "growing as their cube).")
@click.option("--depth-range", type=float, nargs=2, default=None, metavar="ZMIN ZMAX",
              help="World z range (mm) of the particles, instead of rig.yaml's particles.volume_mm.")
@_workers_option
@_scheduler_option
@config_option
@user_errors
def self_calibrate_cmd(dataset: Path, calibration: Path, out: Path, detections: Path | None, frames: int,
                       coarse_frames: int, tolerance_px: float, max_tolerance_px: float, final_tolerance_px: float,
                       min_cameras: int, cells: tuple[int, int, int], peak_radius_px: float, max_rounds: int,
                       intrinsics: str, refine_intrinsics: bool, refine_window: bool, backend: str,
                       depth_range: tuple[float, float] | None, workers: int, scheduler: str | None) -> None:
    """Volume self-calibration through the window: correct a drifted calibration from particle images."""
    from ..colmap.refine.options import Backend
    from ..particles.selfcal import Intrinsics, SelfCalOptions, check_not_input, self_calibrate_dataset

    check_output_folder(out)
    check_not_input(out, [calibration, dataset, detections])
    check_number("--frames", frames, minimum=1)
    check_number("--coarse-frames", coarse_frames, minimum=1)
    check_number("--tolerance-px", tolerance_px, minimum=0.0, maximum=100.0, strict_minimum=True)
    check_number("--max-tolerance-px", max_tolerance_px, minimum=tolerance_px, maximum=100.0)
    check_number("--final-tolerance-px", final_tolerance_px, minimum=0.0, maximum=tolerance_px, strict_minimum=True)
    check_number("--min-cameras", min_cameras, minimum=3, maximum=64)
    for n in cells:
        check_number("--cells", n, minimum=1, maximum=50)
    check_number("--peak-radius-px", peak_radius_px, minimum=0.0, maximum=100.0, strict_minimum=True)
    check_number("--max-rounds", max_rounds, minimum=1, maximum=100)
    check_number("--workers", workers, minimum=0, maximum=1024)
    _check_depth_range(depth_range)
    options = SelfCalOptions(tolerance_px=tolerance_px, max_tolerance_px=max_tolerance_px,
                             final_tolerance_px=final_tolerance_px, min_cameras=min_cameras,
                             cells=(cells[0], cells[1], cells[2]), peak_radius_px=peak_radius_px, max_rounds=max_rounds,
                             coarse_frames=coarse_frames,
                             intrinsics=Intrinsics.FREE if refine_intrinsics else Intrinsics(intrinsics),
                             backend=Backend(backend))
    if refine_window:
        click.echo("note: --refine-window is no longer needed: the window is held in the world and every camera "
                   "moves, so the window's pose relative to the cameras is always estimated", err=True)
    r = self_calibrate_dataset(dataset, calibration, out, options, detections_path=detections, frames=frames,
                               depth_range_mm=None if depth_range is None else (depth_range[0], depth_range[1]),
                               workers=workers,
                               scheduler=scheduler, progress=True)
    rep = r.report
    for name, d in rep.disparity_rms_px.items():
        s = rep.sigmas[name]
        rel = ("" if s.rotation_rel_deg is None
               else f" (relative to the first camera: sigma {s.rotation_rel_deg:.4f} deg)")
        click.echo(f"{name}: disparity RMS {d.before:.3f} px -> {d.after:.3f} px, rotated "
                   f"{rep.rotation_change_deg[name]:.4f} deg{rel}")
    click.echo(f"{len(r.rounds)} rounds, {rep.particles_used} particles in {len(rep.frames)} frames, "
               f"{100 * rep.matched_share:.1f} % of the particle images matched at the end, {rep.time_s:.1f} s")
    click.echo("held: " + "; ".join(rep.held))
    click.echo("estimated: " + "; ".join(rep.estimated))
    for a in (rd.adjustment for rd in r.rounds if rd.adjustment is not None):
        if a.stop == "max_iterations":
            click.echo(f"warning: a bundle adjustment ({a.landmarks} particles) stopped at its {a.iterations}-"
                       "iteration cap without converging", err=True)
    for c in rep.checks:
        if not c.passed:
            click.echo(f"{'FAILED' if c.fatal else 'warning'}: {c.what}: {c.value:.4g} (limit {c.limit:.4g})",
                       err=True)
    if not rep.passed:
        click.echo("self-calibration FAILED its checks: the start calibration cannot be trusted for these images "
                   "or the result is wrong (written with self_calibration.passed false; see its checks)", err=True)
    click.echo(f"calibration: {out / 'calibration.json'}\ndisparity:   {out / 'disparity.json'}")
    if not rep.passed:
        sys.exit(QUALITY_FAILED_EXIT)


MAX_DEPTH_MM = 1e5  # --depth-range: world z within 100 m (-1e300 1e300 sampled the epipolar curves over nothing)


def _check_depth_range(depth_range: tuple[float, float] | None) -> None:
    """--depth-range ZMIN ZMAX: finite, within MAX_DEPTH_MM, ZMAX > ZMIN."""
    if depth_range is None:
        return
    for v in depth_range:
        check_number("--depth-range", v, minimum=-MAX_DEPTH_MM, maximum=MAX_DEPTH_MM)
    if not depth_range[1] > depth_range[0]:
        raise AriSfmError("--depth-range", f"ZMAX must exceed ZMIN (got {depth_range[0]:g} {depth_range[1]:g})")

"""refine-colmap against pycolmap.bundle_adjustment: accuracy on the simulated port survey, time ratio, growth.

    python benchmarks/bench_refine_colmap.py [--sizes 28:1500,100:12000,200:50000] [--focal 1300] [--layout strip]

For each size (images:points) a camera in a flat-port housing (port 22 mm in front of the lens,
8 mm acrylic n 1.49, water 1.333, port tilted 1.5 deg) flies a lawn-mower grid 2 m above a relief
(area growing with the image count; sigma 0.5 px; ari_sfm.simulate.port_survey). COLMAP's side:
PINHOLE cameras at focal n_m f on the simulated correspondences, then pycolmap.bundle_adjustment
(its pinhole optimum, timed). Then refine_colmap (mount camera, exact model, a scale bar between
the two farthest-apart points; timed, including the distance search and the written
approximation). Printed: errors against the truth after similarity alignment (points, camera
centres, scale), port normal and distance errors, reprojection RMS, times and the ratio
refine / bundle_adjustment.

``--layout strip``: a long survey with short tracks instead (two lines of images ``--spacing`` mm
apart along a strip 2 m wide; each point seen by ~3-14 images, mean ~4.5 at 400 mm, ~6.3 at
250 mm; about 60 % of the drawn points are seen 3 times or more and kept): the way to 200 images / 50 k points
on a small machine (``--sizes 200:75000 --layout strip --spacing 250``). COLMAP's pinhole optimum of such a strip is
bent (the 100-image one turns ~120 deg end to end); refine-colmap then slides its start outward from a
middle block (more than 41 frames: ``chain_start.slid_start``), so the 100- and 200-image strips converge.
``--declared-port``: the true port declared (``interface.plane``, held). ``--truth-start``: also the
refinement started at the truth (the same solver, scale bar and loss; the yardstick of what the data
allow), its errors and cost printed.

Speed (``--repeats N``, default 3): pycolmap.bundle_adjustment (Ceres, its default options and threads)
started from COLMAP's model with every point perturbed (N(0, 0.2 % of the camera altitude) per
coordinate, so that it iterates) and refine_colmap from COLMAP's model, run alternately N times each.
Printed: the medians and spreads (min-max) of both times, the whole-solve ratio, the per-iteration ratio
(seconds per Jacobian evaluation: refine-colmap's final refinement, including its share of the start
search's evaluations at their smaller size, against Ceres' ``num_jacobian_evaluations``), the ratio
of CPU times (Ceres runs on every core; on a loaded machine this one is the steadier), and the
process's peak RSS.

Where refine-colmap's time goes (profile it with ``python -m cProfile -s cumtime``): per
linearization the exact projection and the chain rule (``ari_sfm/colmap/refine/problem.py``, compiled in
``chain_kernels.py``), the normal equations and the reduced camera system of the shared
bundle-adjustment core (``ari_sfm/solver/schur.py``, ``schur_kernels.py``), one Cholesky per lambda trial;
then the start search (its LM on ~6k observations, stopped at a 1e-2 relative decrease), the
sigmas and the written OPENCV approximation (pycolmap's own bundle adjustment, points held).
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from dataclasses import replace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from ari_sfm.colmap import adapter
from ari_sfm.colmap.refine import refine_colmap
from ari_sfm.colmap.refine.problem import RefractiveProblem
from ari_sfm.colmap.refine.scale_bar import ScaleBar
from ari_sfm.colmap.refine.solver import Solver
from ari_sfm.colmap.refine.truth import colmap_truth_errors, truth_errors, truth_state, window_errors
from ari_sfm.geometry import Pose
from ari_sfm.records import WindowPlane
from ari_sfm.simulate.port_survey import port_survey


def _timed_pycolmap_ba(start, rng: np.random.Generator, sigma: float) -> tuple[float, int]:
    """pycolmap's bundle adjustment (default options) of a copy of ``start`` with its points perturbed:
    wall and CPU seconds (all of Ceres' threads) and Ceres' Jacobian evaluations."""
    import pycolmap

    rec = pycolmap.Reconstruction(start)
    for pid in rec.point3D_ids():
        rec.point3D(pid).xyz = rec.point3D(pid).xyz + rng.normal(0.0, sigma, 3)
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    config = pycolmap.BundleAdjustmentConfig()
    for i in rec.reg_image_ids():
        config.add_image(i)
    t0, c0 = time.perf_counter(), time.process_time()
    summary = pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    return (time.perf_counter() - t0, time.process_time() - c0, int(summary.ceres_summary.num_jacobian_evaluations))


def _truth_started(truth, model, interface, bar: tuple[int, int, float]) -> None:
    """The refinement started at the truth (everything free, the bar held, refine-colmap's loss), printed."""
    where = {int(p): k for k, p in enumerate(model.point3D_ids)}
    problem = RefractiveProblem(model, interface, "camera", interface.plane is None)
    solver = Solver(problem, 2.0, None, ScaleBar(where[bar[0]], where[bar[1]], bar[2]))
    t0 = time.perf_counter()
    res = solver.run(truth_state(truth, model), 100)
    R, t = res.state.cam_from_world(model)
    got = truth_errors(truth, model, res.state.xyz, {int(i): Pose(R[k], t[k]) for k, i in enumerate(model.image_ids)})
    got.update(window_errors(truth, res.state.normals, res.state.distances))
    rms = float(np.sqrt(np.mean(np.sum(problem.residuals(res.state) ** 2, axis=1))))
    print(f"  truth-started     : points {got['points_rms_mm']:.2f} mm RMS, centres {got['centres_rms_mm']:.1f} mm, "
          f"scale {got['scale_error_pct']:+.3f} %, normal {got['normal_deg']:.3f} deg, distance "
          f"{got['distance_mm']:.2f} mm, reprojection {rms:.3f} px RMS, cost {res.cost:.2f}, {res.iterations} "
          f"iterations, converged {res.converged}, {time.perf_counter() - t0:.0f} s")


def survey_start(num_images: int, num_points: int, focal: float, layout: str = "grid", spacing: float = 400.0,
                 declared_port: bool = False, sigma_px: float = 0.5):
    """The simulated survey (truth), COLMAP's pinhole optimum of it (start, model), the scale bar between the
    two farthest-apart points and the interface refine-colmap gets."""
    if layout == "strip":
        area = (num_images / 2 * spacing + 2400.0, 2000.0)
    else:
        side = 1800.0 * np.sqrt(num_images / 10.0)
        area = (side, side * 2.0 / 3.0)
    truth = port_survey(num_images=num_images, num_points=num_points, focal_px=focal, area_mm=area, sigma_px=sigma_px,
                        layout=layout)
    params = [np.r_[p[:2] * truth.interface.medium_index, p[2:4]] for p in truth.params]
    rec = adapter.reconstruction_from_arrays(params, truth.image_size, truth.sensor_from_rig, truth.rig_from_world,
                                             truth.image_camera, truth.image_frame, truth.xyz, truth.obs_image,
                                             truth.obs_point, truth.obs_uv)
    start = adapter.bundle_adjust(rec)
    model = adapter.model_from_reconstruction(start)
    X = truth.xyz[model.point3D_ids - 1]
    a, b = int(np.argmin(X[:, 0] + X[:, 1])), int(np.argmax(X[:, 0] + X[:, 1]))
    bar = (int(model.point3D_ids[a]), int(model.point3D_ids[b]), float(np.linalg.norm(X[a] - X[b])))
    interface = truth.interface
    if declared_port:  # the housing's port as built, held (interface.plane in the camera frame)
        n = truth.normal_cam[0]
        interface = replace(interface, plane=WindowPlane("camera", n, n * truth.distance_mm[0]))
    return truth, start, model, bar, interface


def alternate_timings(start, model, interface, bar: tuple[int, int, float], repeats: int) -> tuple[dict, object]:
    """pycolmap's bundle adjustment (points perturbed) and refine_colmap run alternately ``repeats`` times:
    lists of wall and CPU seconds and seconds per iteration of each ("ba", "ref", "cpu_ba", "cpu_ref", "it_ba",
    "it_ref"), and the last refinement's result."""
    times = {k: [] for k in ("ba", "ref", "cpu_ba", "cpu_ref", "it_ba", "it_ref")}
    rng = np.random.default_rng(1)
    for _ in range(repeats):  # alternately, so that both see the same machine load
        seconds, cpu, evaluations = _timed_pycolmap_ba(start, rng, 0.002 * 2000.0)
        times["ba"].append(seconds)
        times["cpu_ba"].append(cpu)
        times["it_ba"].append(seconds / max(evaluations, 1))
        t0, c0 = time.perf_counter(), time.process_time()
        result = refine_colmap(start, interface, "camera", scale_bar=bar)
        times["ref"].append(time.perf_counter() - t0)
        times["cpu_ref"].append(time.process_time() - c0)
        search_obs = sum(c["linearizations"] * c["observations"] for c in result.report.distance_search)
        # search evaluations at their size
        equivalent = result.report.linearizations + search_obs / len(model.obs_image)
        times["it_ref"].append(times["ref"][-1] / max(equivalent, 1.0))
    return times, result


def run(num_images: int, num_points: int, focal: float, layout: str = "grid", spacing: float = 400.0,
        declared_port: bool = False, repeats: int = 3, truth_start: bool = False) -> None:
    truth, start, model, bar, interface = survey_start(num_images, num_points, focal, layout, spacing, declared_port)
    times, result = alternate_timings(start, model, interface, bar, repeats)
    t_ba, t_ref, it_ba, it_ref, cpu_ba, cpu_ref = (times[k] for k in ("ba", "ref", "it_ba", "it_ref", "cpu_ba",
                                                                       "cpu_ref"))
    R, t = result.state.cam_from_world(model)
    got = truth_errors(truth, model, result.state.xyz,
                       {int(i): Pose(R[k], t[k]) for k, i in enumerate(model.image_ids)})
    got.update(window_errors(truth, result.state.normals, result.state.distances))
    before = colmap_truth_errors(truth, start)
    r = result.report
    track = np.bincount(model.obs_point)
    print(f"{num_images} images ({layout}), {len(model.point3D_ids)} points, {len(model.obs_image)} observations, "
          f"track length mean {track.mean():.1f} max {track.max()} (focal {focal:g} px, "
          f"{truth.image_size[0]}x{truth.image_size[1]})")
    print(f"  COLMAP pinhole BA : points {before['points_rms_mm']:.2f} mm RMS, "
          f"centres {before['centres_rms_mm']:.1f} mm, "
          f"scale {before['scale_error_pct']:+.2f} %, reprojection {r.before.rms_px:.3f} px RMS "
          f"({start.compute_mean_reprojection_error():.3f} px mean)")
    u = r.uncertainty
    print(f"  sigmas (1 sigma): normal {u.normal_deg['camera1']:.3f} deg, distance {u.distance_mm['camera1']:.2f} mm, "
          f"scale {100 * u.scale_rel:.3f} %, fx {u.fx_px['camera1']:.2f} px; weak: {', '.join(u.weak) or 'none'}")
    print(f"  refine-colmap     : points {got['points_rms_mm']:.2f} mm RMS, centres {got['centres_rms_mm']:.1f} mm, "
          f"scale {got['scale_error_pct']:+.3f} %, normal {got['normal_deg']:.3f} deg, distance "
          f"{got['distance_mm']:.2f} mm (true 22), reprojection {r.after.rms_px:.3f} px RMS "
          f"(sigma sqrt2 = {0.5 * np.sqrt(2):.3f}), {r.iterations} iterations, converged {r.converged}, "
          f"cost {r.cost_final:.2f}")
    if truth_start:
        _truth_started(truth, model, interface, bar)
    print(f"  written OPENCV approximation: {r.pinhole_approximation.rms_px:.3f} px RMS")
    med = {k: float(np.median(v)) for k, v in (("ba", t_ba), ("ref", t_ref), ("it_ba", it_ba), ("it_ref", it_ref))}
    ratio = np.array(t_ref) / np.array(t_ba)
    per_it = np.array(it_ref) / np.array(it_ba)
    print(f"  time ({repeats} alternating runs, median [min-max]): pycolmap BA {med['ba']:.2f} s "
          f"[{min(t_ba):.2f}-{max(t_ba):.2f}], {1e3 * med['it_ba']:.0f} ms/iteration; refine-colmap {med['ref']:.2f} s "
          f"[{min(t_ref):.2f}-{max(t_ref):.2f}], {1e3 * med['it_ref']:.0f} ms/iteration "
          f"({r.linearizations} + {r.search_linearizations} search linearizations)")
    print(f"  ratio refine-colmap / pycolmap.bundle_adjustment: whole solve {np.median(ratio):.2f} "
          f"[{ratio.min():.2f}-{ratio.max():.2f}], per iteration {np.median(per_it):.2f} "
          f"[{per_it.min():.2f}-{per_it.max():.2f}]; CPU time (both of Ceres' threads counted) "
          f"{np.median(np.array(cpu_ref) / np.array(cpu_ba)):.2f}; "
          f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    sys.stdout.flush()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="28:1500,100:12000,200:50000")
    ap.add_argument("--focal", type=float, default=1300.0)
    ap.add_argument("--layout", choices=("grid", "strip"), default="grid")
    ap.add_argument("--declared-port", action="store_true",
                    help="declare the true port as interface.plane, held")
    ap.add_argument("--spacing", type=float, default=400.0, help="strip: mm between images along a line")
    ap.add_argument("--repeats", type=int, default=3, help="alternating timed runs of each solver")
    ap.add_argument("--truth-start", action="store_true", help="also the refinement started at the truth")
    args = ap.parse_args()
    for size in args.sizes.split(","):
        n, p = (int(v) for v in size.split(":"))
        run(n, p, args.focal, args.layout, args.spacing, args.declared_port, args.repeats, args.truth_start)


if __name__ == "__main__":
    main()

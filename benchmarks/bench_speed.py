"""Issue 15's speed figures from one run: each a ratio of two commands run alternately.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_speed.py            # all figures, ~7 min on 2 cores
    python benchmarks/bench_speed.py --only triangulate,forward --repeats 9

For every figure the two commands run in alternation, ``--repeats`` pairs (after one
warm-up of each); the ratio of each pair is taken and the median ratio printed with its
spread (min-max over the pairs), next to the median times and the goal, and the median
ratio of the process CPU times (all threads), which a loaded machine disturbs less (for a
multi-threaded command it is the cost, not the wall time, on an idle machine). Then the cold
start (``--only cold_start``, ~3 min: the wheel built with its compiled kernels and installed
into a fresh venv; the first process after the install (imports, a calibration and a
triangulation) against the next two, and the same process with numba's target set, which
leaves the shipped code unused and compiles every kernel it calls) and the peak memory
(ru_maxrss) of this process.

Figures (ours / reference):

- ``calibrate_single``: ``calibrate(model="ari")`` on paper_single (seed 0) / one
  ``cv2.calibrateCamera`` on its 12 calibration views (bench_calibrate.py's baseline: no
  distortion; what a user who ignores the window runs); also the bundle adjustment alone / cv2,
  and, for the record, cv2 given the 6 stacking views too (the 1584 corners calibrate uses).
- ``calibrate_4x100``: ``calibrate(model="exact")`` on scale16 with 4 cameras x 100 frames
  / four cv2.calibrateCamera calls (one per camera).
- ``triangulate_2``, ``triangulate_4``: ``triangulate_pixels`` with the true exact
  calibration (binocular; arc4) on 20k random points of the boards' volume, as points per
  second / ``cv2.triangulatePoints`` (DLT, pinhole: the window ignored) on the same points'
  pixels (4 cameras: each point from the first two cameras that see it, one call per camera
  pair; bench_triangulate.cv2_pairs); printed as a throughput ratio (>= 1: at least cv2's
  points per second).
- ``forward``, ``forward_jac``: ``exact_project`` of 20k points (6 mm glass into water, no
  lens distortion) without and with Jacobians / the numpy pinhole projection of the same
  points (ari_sfm.models.pinhole's project_points as it was in numpy, kept below as the
  baseline); ``forward_dist*``: the same with lens distortion on both sides. Each timing is
  five calls (a single one lasts about a millisecond).
- ``openptv``: ``calibrate(model="exact")`` on a simulated 4-camera PTV body (body3d_water
  with 1600 points on three levels, 6 mm glass into water, one view) / liboptv's
  ``full_calibration`` (the optv wheel; exterior orientation + xh, yh, as the real experiment)
  of the same four cameras on the same points, started from the ari-sfm result exported by
  ``export_openptv``.

Rigs shaped unlike those (each beside the figure it checks):

- ``calibrate_arc_sparse``: ``calibrate(model="exact")`` on a sparse arc rig (arc4 with
  ``run_lengths=(2, 3, 4)``: 20 frames, each seen by a run of 2, 3 or 4 of the 4 cameras, 50 mm
  window tilted ~20 deg) / four cv2.calibrateCamera calls on each camera's views.
- ``triangulate_dist``, ``triangulate_dist_noisy``: ``triangulate_pixels`` through the exact model of 2
  cameras of a distorted PTV rig (``simulate particles --k1 -0.05``: OpenCV k1 -0.05 on every camera,
  10 mm glass into water), 188k points of its volume, their exact pixels, then with 0.1 px of noise
  (the particle detections'), points/s / ``cv2.triangulatePoints`` on the same pixels (pinhole: window
  and lens ignored); for the record also ``cv2.undistortPoints`` + ``cv2.triangulatePoints``.
- ``openptv_multiplane``: ``calibrate(model="exact")`` of an OpenPTV multi-plane body as ``import
  openptv`` gives it (ptv_multiplane with a 27 x 15 dot plate at 4 depths: 1620 points, 6480
  observations; declared plane, focal hints) / liboptv's ``full_calibration`` x 4 started from
  the ari-sfm result (as ``openptv``); ``openptv_multiplane_placed``: the same body with each plane
  placed 0.1 mm / 0.05 deg off (the declared body nominal) and 0.1 px of noise, as a real plate.
- ``refine_colmap_port``, ``refine_colmap_port_it``: refine-colmap / pycolmap BA on a 28-image
  flat-port survey with 0.25 px noise (port_survey, ~2200 points seen >= 3 times).
- ``selfcal``: ``self_calibrate`` of the README's experiment (``simulate particles``, started from
  ``calibrate --model exact`` of its calibration folder) / bench_selfcal's minimal plain self-calibration
  from the same start; the goal is absolute: <= 20 s wall, <= 30 s CPU.
- ``particles``: ``match_frame`` (>= 3 of 4 cameras, 0.5 px) / liboptv's ``correspondences`` +
  ``point_positions`` on the same detections and calibration (bench_particles.openptv), 2000
  particles a frame (``--particle-frames``, 5), per core: the ratio of the CPU times is the headline
  (both run on one thread here: the final triangulation of 2000 points takes one), inverted to a
  throughput (>= 1.5: half again OpenPTV's C per core); the wall-time ratio beside it.
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import llvmlite.binding  # noqa: E402
import numba.core.codegen  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_calibrate import cv2_baseline  # noqa: E402
from bench_triangulate import _points_and_pixels, cv2_pairs  # noqa: E402

from ari_sfm.calibration.calibrate import calibrate  # noqa: E402
from ari_sfm.io import parse_calibration, save_calibration  # noqa: E402
from ari_sfm.simulate import ScenarioOverrides, make_scene  # noqa: E402

GOALS: dict[str, tuple[str, str | None, Callable[[float], bool] | None]] = {
    # figure: (what the ratio is, goal text, ratio meets the goal; None: no goal on the ratio)
    "calibrate_single": ("time ratio", "<= 1.0", lambda r: r <= 1.0),
    "calibrate_4x100": ("time ratio", "<= 1.0", lambda r: r <= 1.0),
    "triangulate_2": ("points/s ratio", ">= 1.0", lambda r: r >= 1.0),
    "triangulate_4": ("points/s ratio", ">= 1.0", lambda r: r >= 1.0),
    "forward": ("time ratio", "<= 10", lambda r: r <= 10.0),
    "forward_jac": ("time ratio", "<= 10", lambda r: r <= 10.0),
    "forward_dist": ("time ratio", "<= 10", lambda r: r <= 10.0),
    "forward_dist_jac": ("time ratio", "<= 10", lambda r: r <= 10.0),
    "openptv": ("time ratio", "<= 10", lambda r: r <= 10.0),
    "refine_colmap": ("time ratio", "<= 2", lambda r: r <= 2.0),
    "refine_colmap_it": ("time ratio", "<= 3", lambda r: r <= 3.0),
    "calibrate_arc_sparse": ("time ratio", "<= 1.0", lambda r: r <= 1.0),
    "triangulate_dist": ("points/s ratio", ">= 1.0", lambda r: r >= 1.0),
    "triangulate_dist_noisy": ("points/s ratio", ">= 1.0", lambda r: r >= 1.0),
    "openptv_multiplane_placed": ("time ratio", "<= 10", lambda r: r <= 10.0),
    "openptv_multiplane": ("time ratio", "<= 10", lambda r: r <= 10.0),
    "refine_colmap_port": ("time ratio", "<= 2", lambda r: r <= 2.0),
    "refine_colmap_port_it": ("time ratio", "<= 3", lambda r: r <= 3.0),
    "particles": ("per-core ratio", ">= 1.5", lambda r: r >= 1.5),
    "selfcal": ("time ratio", None, None),  # the goal is in seconds (the note)
}


def alternate(ours: Callable[[], object], reference: Callable[[], object], repeats: int) -> dict:
    """Run both once (warm-up), then ``repeats`` alternating pairs; per-pair times and ratios."""
    ours(), reference()
    t_ours, t_ref, c_ours, c_ref, extra = [], [], [], [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        out = ours()
        t_ours.append(time.perf_counter() - t)
        c_ours.append(time.process_time() - c)
        extra.append(out)
        t, c = time.perf_counter(), time.process_time()
        reference()
        t_ref.append(time.perf_counter() - t)
        c_ref.append(time.process_time() - c)
    return {"ours": t_ours, "ref": t_ref, "ours_cpu": c_ours, "ratios": [a / b for a, b in zip(t_ours, t_ref)],
            "cpu_ratios": [a / b for a, b in zip(c_ours, c_ref)], "extra": extra}


def report(name: str, what: str, run: dict, invert: bool = False, note: str = "", by_cpu: bool = False) -> dict:
    """Print one figure's line; ``invert``: the ratio is a throughput (reference time / ours); ``by_cpu``:
    the headline (median, spread) is the CPU-time ratio (a per-core figure), the wall ratio given aside."""
    ratios = [1.0 / r for r in run["ratios"]] if invert else run["ratios"]
    cpu = statistics.median(1.0 / r if invert else r for r in run["cpu_ratios"])
    other = "CPU-time ratio"
    if by_cpu:  # the headline is the CPU-time ratio; the wall-time one aside
        other, cpu = "wall-time ratio", statistics.median(ratios)
        ratios = [1.0 / r for r in run["cpu_ratios"]] if invert else run["cpu_ratios"]
    med = statistics.median(ratios)
    kind, goal, ok = GOALS[name]
    print(f"{name:17s} {what:58s} {1e3 * statistics.median(run['ours']):9.1f} "
          f"{1e3 * statistics.median(run['ref']):9.1f} "
          f"{med:7.3f} [{min(ratios):.3f}-{max(ratios):.3f}] {kind} "
          + (f"goal {goal}: {'met' if ok(med) else 'NOT met'}" if ok is not None else "(no goal on the ratio)")
          + f"; {other} {cpu:.3f}" + (f"  ({note})" if note else ""))
    return {"median": med, "min": min(ratios), "max": max(ratios)}


# --------------------------------------------------------------------------- figures


def fig_calibrate_single(repeats: int) -> None:
    dataset = make_scene("paper_single", seed=0).dataset
    run = alternate(lambda: calibrate(dataset, model="ari"), cv2_baseline(dataset), repeats)
    report("calibrate_single", "calibrate(ari) paper_single / cv2.calibrateCamera", run)
    ba = [sum(s["time_s"] for s in cal.optimizer.to_json().values()) for cal in run["extra"]]
    its = "+".join(str(s["iterations"]) for s in run["extra"][0].optimizer.to_json().values())
    print(f"{'':17s} {'  of which the bundle adjustment (' + its + ' iterations) / cv2':58s} "
          f"{1e3 * statistics.median(ba):9.1f} {'':9s} {statistics.median(a / b for a, b in zip(ba, run['ref'])):7.3f}")
    every = alternate(lambda: calibrate(dataset, model="ari"), cv2_baseline(dataset, ("calibration", "stacking")),
                      repeats)
    print(f"{'':17s} {'  the same, cv2 given the stacking views too (every corner used)':58s} "
          f"{1e3 * statistics.median(every['ours']):9.1f} {1e3 * statistics.median(every['ref']):9.1f} "
          f"{statistics.median(every['ratios']):7.3f} [{min(every['ratios']):.3f}-{max(every['ratios']):.3f}] "
          "(for the record: the goal is the line above's)")


def fig_calibrate_4x100(repeats: int) -> None:
    dataset = make_scene("scale16", seed=0, overrides=ScenarioOverrides(num_cameras=4, num_frames=100)).dataset
    run = alternate(lambda: calibrate(dataset, model="exact"), cv2_baseline(dataset), repeats)
    report("calibrate_4x100", "calibrate(exact) 4 cameras x 100 frames / 4 x cv2.calibrateCamera", run)
    ba = [sum(s["time_s"] for s in cal.optimizer.to_json().values()) for cal in run["extra"]]
    print(f"{'':17s} {'  of which the bundle adjustment / cv2':58s} {1e3 * statistics.median(ba):9.1f} {'':9s} "
          f"{statistics.median(a / b for a, b in zip(ba, run['ref'])):7.3f}")


def fig_triangulate(repeats: int, points: int) -> None:
    from ari_sfm.reconstruction.triangulate import triangulate_pixels

    binocular = parse_calibration(make_scene("binocular", seed=0, sigma_px=0.0).truth)
    arc4 = parse_calibration(make_scene("arc4", seed=0, sigma_px=0.0).truth)
    for name, cal in (("triangulate_2", binocular), ("triangulate_4", arc4)):
        X, tracks = _points_and_pixels(cal, points)
        run_cv2, _ = cv2_pairs(cal, tracks)  # the same points' pixels; 4 cameras: the first two that see each
        run = alternate(lambda cal=cal, tracks=tracks: triangulate_pixels(cal, tracks), run_cv2, repeats)
        err = np.sqrt(np.nanmean(np.sum((run["extra"][0][0] - X) ** 2, axis=1)))
        pps = len(X) / statistics.median(run["ours"])
        report(name, f"exact, {len(cal.cameras)} cameras, {len(X)} points / cv2 (2 of them) points/s", run,
               invert=True, note=f"{pps:,.0f} points/s, RMS error {err:.1e} mm")


def fig_calibrate_arc_sparse(repeats: int) -> None:
    dataset = make_scene("arc4", seed=0, overrides=ScenarioOverrides(run_lengths=(2, 3, 4))).dataset
    run = alternate(lambda: calibrate(dataset, model="exact"), cv2_baseline(dataset), repeats)
    n_obs = sum(len(o.ids) for o in dataset.observations)
    report("calibrate_arc_sparse", "calibrate(exact) sparse arc, 20 frames 2-4 cameras / 4 x cv2", run,
           note=f"{n_obs} corners")
    ba = [sum(s["time_s"] for s in cal.optimizer.to_json().values()) for cal in run["extra"]]
    print(f"{'':17s} {'  of which the bundle adjustment / cv2':58s} {1e3 * statistics.median(ba):9.1f} {'':9s} "
          f"{statistics.median(a / b for a, b in zip(ba, run['ref'])):7.3f}")


def distorted_ptv_rig(points: int, seed: int = 0):
    """The calibration (rig B's truth) of ``simulate particles --k1 -0.05`` and ``points`` random points of its
    volume seen by its first two cameras: (calibration of those two cameras, X, tracks)."""
    from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment

    exp = simulate_particle_experiment(ParticleSimOptions(k1=-0.05, num_frames=1, particles_per_frame=10, seed=seed))
    cal = exp.truth_b
    two = list(cal.cameras)[:2]
    rng = np.random.default_rng(seed)
    X_all, tracks_all, count = [], {c: [] for c in two}, 0
    while count < points:
        X = rng.uniform(exp.volume_min_mm, exp.volume_max_mm, size=(points, 3))
        tracks = {c: cal.project_world(c, X) for c in two}
        keep = np.ones(len(X), bool)
        for c in two:
            w, h = cal.cameras[c].image_size
            uv = tracks[c]
            keep &= (np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0)
                     & (uv[:, 1] <= h - 1))
        X_all.append(X[keep])
        for c in two:
            tracks_all[c].append(tracks[c][keep])
        count += int(keep.sum())
    return cal, np.concatenate(X_all)[:points], {c: np.concatenate(v)[:points] for c, v in tracks_all.items()}


def fig_triangulate_dist(repeats: int, points: int) -> None:
    """Exact pixels (as triangulate_2, _4), then with 0.1 px of noise (the particle detections'): Levenberg-Marquardt
    then takes a second evaluation per point."""
    from ari_sfm.reconstruction.triangulate import triangulate_pixels

    cal, X, exact = distorted_ptv_rig(points)
    rng = np.random.default_rng(1)
    noisy = {c: t + rng.normal(0.0, 0.1, t.shape) for c, t in exact.items()}
    for name, tracks, label in (("triangulate_dist", exact, "exact pixels"),
                                ("triangulate_dist_noisy", noisy, "0.1 px noise")):
        run_cv2, _ = cv2_pairs(cal, tracks)
        run = alternate(lambda tracks=tracks: triangulate_pixels(cal, tracks), run_cv2, repeats)
        err = np.sqrt(np.nanmean(np.sum((run["extra"][0][0] - X) ** 2, axis=1)))
        pps = len(X) / statistics.median(run["ours"])
        report(name, f"exact, 2 cameras k1 -0.05, {len(X)} points, {label} / cv2 points/s", run, invert=True,
               note=f"{pps:,.0f} points/s, RMS error {err:.1e} mm")
    names = list(noisy)
    K = [cal.cameras[c].K for c in names]
    dist = [np.asarray(cal.cameras[c].dist, float) for c in names]
    P = [np.hstack([cal.cameras[c].cam_from_world.R, cal.cameras[c].cam_from_world.t[:, None]]) for c in names]
    uv = [noisy[c].reshape(-1, 1, 2) for c in names]

    def cv2_undistorted() -> None:
        a, b = (cv2.undistortPoints(uv[k], K[k], dist[k]).reshape(-1, 2).T for k in (0, 1))
        cv2.triangulatePoints(P[0], P[1], a, b)

    und = alternate(lambda: triangulate_pixels(cal, noisy), cv2_undistorted, max(3, repeats // 2))
    r = [1.0 / x for x in und["ratios"]]
    print(f"{'':17s} {'  the same / cv2.undistortPoints + triangulatePoints':58s} "
          f"{1e3 * statistics.median(und['ours']):9.1f} "
          f"{1e3 * statistics.median(und['ref']):9.1f} {statistics.median(r):7.3f} [{min(r):.3f}-{max(r):.3f}] "
          "(for the record)")


def _numpy_pinhole(D: np.ndarray, params: np.ndarray, jacobians: bool) -> tuple:
    """The baseline: ari_sfm's pinhole projection as it was in numpy (main 3807e0e, models/pinhole.py's
    project_points, which skips the distortion polynomial when every coefficient is zero)."""
    Z = D[:, 2]
    xy = D[:, :2] / Z[:, None]
    f = params[:2]
    if not params[4:].any():
        uv = xy * f + params[2:4]
        if not jacobians:
            return uv, None, None
        m = len(D)
        inv_z = 1.0 / Z
        J_point = np.zeros((m, 2, 3))
        J_point[:, 0, 0] = f[0] * inv_z
        J_point[:, 1, 1] = f[1] * inv_z
        J_point[:, :, 2] = f * (-xy * inv_z[:, None])
        J_params = np.zeros((m, 2, 9))
        J_params[:, 0, 0] = xy[:, 0]
        J_params[:, 1, 1] = xy[:, 1]
        J_params[:, 0, 2] = 1.0
        J_params[:, 1, 3] = 1.0
        return uv, J_point, J_params
    k1, k2, p1, p2, k3 = params[4:]
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xyd = np.empty_like(xy)
    xyd[:, 0] = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    xyd[:, 1] = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    uv = xyd * f + params[2:4]
    if not jacobians:
        return uv, None, None
    m = len(D)
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    J_xy = np.empty((m, 2, 2))
    cross = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    J_xy[:, 0, 0] = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    J_xy[:, 0, 1] = cross
    J_xy[:, 1, 0] = cross
    J_xy[:, 1, 1] = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    J_dist = np.empty((m, 2, 5))
    J_dist[:, 0, 0], J_dist[:, 1, 0] = x * r2, y * r2
    J_dist[:, 0, 1], J_dist[:, 1, 1] = x * r2**2, y * r2**2
    J_dist[:, 0, 2], J_dist[:, 1, 2] = 2.0 * x * y, r2 + 2.0 * y * y
    J_dist[:, 0, 3], J_dist[:, 1, 3] = r2 + 2.0 * x * x, 2.0 * x * y
    J_dist[:, 0, 4], J_dist[:, 1, 4] = x * r2**3, y * r2**3
    inv_z = 1.0 / Z
    J_norm = np.zeros((m, 2, 3))
    J_norm[:, 0, 0] = inv_z
    J_norm[:, 1, 1] = inv_z
    J_norm[:, :, 2] = -xy * inv_z[:, None]
    J_point = (f[None, :, None] * J_xy) @ J_norm
    J_params = np.zeros((m, 2, 9))
    J_params[:, 0, 0] = xyd[:, 0]
    J_params[:, 1, 1] = xyd[:, 1]
    J_params[:, 0, 2] = 1.0
    J_params[:, 1, 3] = 1.0
    J_params[:, :, 4:] = f[None, :, None] * J_dist
    return uv, J_point, J_params


def fig_forward(repeats: int, points: int) -> None:
    from ari_sfm.models.exact import exact_pixels, exact_project
    from ari_sfm.models.pinhole import pinhole_pixels

    rng = np.random.default_rng(0)
    z = rng.uniform(150.0, 900.0, points)
    X = np.c_[rng.uniform(-0.3, 0.3, (points, 2)) * z[:, None], z]
    normal = np.array([0.05, -0.03, 1.0])
    lens = np.array([-0.08, 0.12, 4e-4, -3e-4, -0.05])
    for name, jac, dist in (("forward", False, 0.0), ("forward_jac", True, 0.0), ("forward_dist", False, 1.0),
                            ("forward_dist_jac", True, 1.0)):
        params = np.r_[3478.0, 3480.0, 1230.0, 1020.0, dist * lens]
        uv_np = _numpy_pinhole(X, params, False)[0]
        assert np.abs(pinhole_pixels(X, params) - uv_np).max() < 1e-9  # the baseline is the same pinhole
        exact = exact_project if jac else exact_pixels
        run = alternate(lambda params=params, exact=exact: [exact(X, params, normal, 6.0, 1.5168, 1.333, 40.0)
                                                            for _ in range(5)],
                        lambda params=params, jac=jac: [_numpy_pinhole(X, params, jac) for _ in range(5)], repeats)
        report(name, f"exact_project {points} points{' + Jacobians' if jac else ''}"
                     f"{', distortion' if dist else ''} / numpy pinhole (x5)", run)


def _ptv_body():
    """The simulated PTV body: body3d_water (4 cameras, 6 mm glass into water, one view) with 40 x 40
    points 4 mm apart on three levels (1600 points, 6400 observations)."""
    return make_scene("body3d_water", seed=0, overrides=ScenarioOverrides(cells=40, pitch_mm=4.0))


def fig_openptv(repeats: int) -> None:
    optv_alternate("openptv", "calibrate(exact) PTV body {n} obs / optv full_calibration x 4", _ptv_body().dataset,
                   repeats)


def fig_openptv_multiplane(repeats: int) -> None:
    dataset = make_scene("ptv_multiplane", seed=0,
                         overrides=ScenarioOverrides(grid=(27, 15))).dataset  # what `import openptv` reads of it
    optv_alternate("openptv_multiplane", "calibrate(exact) multiplane, 4 planes, {n} obs / optv x 4", dataset, repeats)


def placed_multiplane():
    """ptv_multiplane (27 x 15 dots, 4 planes) as a real plate is placed: each plane moved by 0.1 mm and turned by
    0.05 deg RMS (scenarios.ptv_misplaced) while the declared body stays the nominal one, and 0.1 px of pixel
    noise on the 0.5 px quantisation (a calibration that does not fit to the quantisation: its Huber tail)."""
    from ari_sfm.simulate import PLACEHOLDER_ROOT
    from ari_sfm.simulate.scenarios import build_geometry, ptv_misplaced
    from ari_sfm.simulate.scene import observe, to_dataset

    geometry = build_geometry("ptv_multiplane", np.random.default_rng(0), overrides=ScenarioOverrides(grid=(27, 15)))
    moved = observe(replace(geometry, target=ptv_misplaced(geometry.target, 0.1, 0.05, np.random.default_rng(1))))
    rng = np.random.default_rng(2)
    noisy = tuple(replace(o, pixels=o.pixels + rng.normal(0.0, 0.1, o.pixels.shape)) for o in moved)
    return to_dataset(geometry, noisy, PLACEHOLDER_ROOT, seen=moved)


def fig_openptv_multiplane_placed(repeats: int) -> None:
    optv_alternate("openptv_multiplane_placed", "  the same, planes placed 0.1 mm off, 0.1 px noise, {n} obs / optv",
                   placed_multiplane(), repeats)


def optv_alternate(name: str, what: str, dataset, repeats: int) -> None:
    """calibrate(model="exact") of ``dataset`` (one view of a 3D body, 4 cameras) / liboptv's full_calibration of
    each camera on the same points, started from our result exported by export_openptv."""
    from optv.calibration import Calibration as OptvCalibration
    from optv.orientation import full_calibration
    from optv.parameters import ControlParams
    from optv.tracking_framebuf import TargetArray

    from ari_sfm.init.zhang import object_points
    from ari_sfm.openptv import export_openptv

    n_obs = sum(len(o.ids) for o in dataset.observations)
    cal = calibrate(dataset, model="exact")
    folder = Path(tempfile.mkdtemp(prefix="bench_speed_optv_"))
    save_calibration(cal, folder / "calibration.json")
    summary = export_openptv(folder / "calibration.json", folder / "optv")
    cpar = ControlParams(len(dataset.camera_names))
    cpar.read_control_par(str(folder / "optv" / "parameters" / "ptv.par"))
    per_camera = []
    for camera in dataset.camera_names:
        obs = next(o for o in dataset.observations if o.camera == camera)
        number = summary.numbers[camera]
        ori = folder / "optv" / "cal" / f"cam{number}.tif.ori"
        addpar = folder / "optv" / "cal" / f"cam{number}.tif.addpar"
        ref = np.ascontiguousarray(object_points(dataset.target, obs.ids), dtype=np.float64)
        targets = TargetArray(len(obs.ids))
        for k, (u, v) in enumerate(obs.pixels - (-0.5)):  # OpenCV -> OpenPTV pixels (segmentation.c: +0.5)
            t = targets[k]
            t.set_pos((u, v))
            t.set_pnr(k)
        per_camera.append((str(ori), str(addpar), ref, targets))

    def run_optv() -> None:
        for ori, addpar, ref, targets in per_camera:
            c = OptvCalibration()
            c.from_file(ori, addpar)
            full_calibration(c, ref, targets, cpar, ["xh", "yh"])

    run = alternate(lambda: calibrate(dataset, model="exact"), run_optv, repeats)
    report(name, what.format(n=n_obs), run, note=f"RMSE {run['extra'][0].residuals.rmse_px:.3f} px")


def fig_refine_colmap(repeats: int) -> None:
    from bench_refine_colmap import alternate_timings, survey_start

    _, start, model, bar, interface = survey_start(28, 1500, 1300.0)
    alternate_timings(start, model, interface, bar, 1)  # warm-up of both
    times, result = alternate_timings(start, model, interface, bar, repeats)
    n_obs = len(model.obs_image)
    whole = {"ours": times["ref"], "ref": times["ba"], "ratios": [a / b for a, b in zip(times["ref"], times["ba"])],
             "cpu_ratios": [a / b for a, b in zip(times["cpu_ref"], times["cpu_ba"])]}
    report("refine_colmap", f"refine-colmap 28-image survey ({n_obs} obs) / pycolmap BA", whole,
           note=f"{result.report.iterations} iterations, converged {result.report.converged}")
    per_it = {"ours": times["it_ref"], "ref": times["it_ba"],
              "ratios": [a / b for a, b in zip(times["it_ref"], times["it_ba"])], "cpu_ratios": whole["cpu_ratios"]}
    report("refine_colmap_it", "  the same, per iteration (Jacobian evaluation)", per_it,
           note="CPU-time ratio: of the whole solves")


PORT_POINTS = 2500  # relief points drawn; ~2200 seen by >= 3 images


def fig_refine_colmap_port(repeats: int) -> None:
    """The 28-image flat-port survey at 0.25 px noise (2500 relief points drawn, those seen >= 3 times kept)."""
    from bench_refine_colmap import alternate_timings, survey_start

    _, start, model, bar, interface = survey_start(28, PORT_POINTS, 900.0, sigma_px=0.25)
    alternate_timings(start, model, interface, bar, 1)  # warm-up of both
    times, result = alternate_timings(start, model, interface, bar, repeats)
    n_obs = len(model.obs_image)
    whole = {"ours": times["ref"], "ref": times["ba"], "ratios": [a / b for a, b in zip(times["ref"], times["ba"])],
             "cpu_ratios": [a / b for a, b in zip(times["cpu_ref"], times["cpu_ba"])]}
    report("refine_colmap_port", f"refine-colmap port survey, {len(model.point3D_ids)} points ({n_obs} obs) / "
           "pycolmap BA", whole, note=f"{result.report.iterations} iterations, converged {result.report.converged}")
    per_it = {"ours": times["it_ref"], "ref": times["it_ba"],
              "ratios": [a / b for a, b in zip(times["it_ref"], times["it_ba"])], "cpu_ratios": whole["cpu_ratios"]}
    report("refine_colmap_port_it", "  the same, per iteration (Jacobian evaluation)", per_it,
           note="CPU-time ratio: of the whole solves")


def fig_particles(repeats: int, frames: int) -> None:
    """match_frame / OpenPTV's correspondences + point_positions, per core (CPU time), ``frames`` frames of 2000
    particles of bench_particles' experiment (true calibration)."""
    from bench_particles import openptv, ours

    from ari_sfm.particles.volume import Volume
    from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment, write_particle_experiment

    exp = simulate_particle_experiment(ParticleSimOptions(particles_per_frame=2000, num_frames=frames, seed=0))
    folder = Path(tempfile.mkdtemp(prefix="bench_speed_particles_"))
    write_particle_experiment(exp, folder, render_frames=0)
    volume = Volume(exp.volume_min_mm, exp.volume_max_mm)
    path = folder / "truth" / "rig_b.json"
    scores = {}

    def run_ours() -> None:
        scores["ours"] = ours(exp, exp.truth_b, volume)[0]

    def run_optv() -> None:
        scores["optv"] = openptv(exp, path, Path(tempfile.mkdtemp(prefix="bench_speed_optv_")), volume)[0]

    run = alternate(run_ours, run_optv, repeats)
    a, b = scores["ours"], scores["optv"]
    report("particles", f"match_frame / optv correspondences + point_positions, {frames} x 2000, CPU", run,
           invert=True, by_cpu=True,
           note=f"found {a.found_fraction:.4f} / {b.found_fraction:.4f}, ghosts {a.ghost_fraction:.4f} / "
                f"{b.ghost_fraction:.4f}; {frames * 2000 / statistics.median(run['ours']):,.0f} particles/s")


def fig_selfcal(repeats: int) -> None:
    """``self_calibrate`` of the README's experiment (``simulate particles``: 10 frames x 2000 particles, 4
    cameras, cameras 1-3 moved 0.05 deg), started as the README does from ``calibrate --model exact`` of its
    calibration folder, / bench_selfcal's minimal plain self-calibration from the same start, alternately;
    the goal is the issue's: <= 20 s wall (<= 30 s CPU) on 2 cores."""
    from bench_selfcal import plain_self_calibration, relative_rotation_deg

    from ari_sfm.particles.selfcal import SelfCalOptions, self_calibrate
    from ari_sfm.particles.volume import Volume
    from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment, write_particle_experiment

    exp = simulate_particle_experiment(ParticleSimOptions())
    folder = Path(tempfile.mkdtemp(prefix="bench_speed_selfcal_"))
    write_particle_experiment(exp, folder, render_frames=0)
    start = calibrate(folder / "calibration", model="exact")
    volume = Volume(exp.volume_min_mm, exp.volume_max_mm)
    frames = dict(enumerate(exp.detections))
    plain = {}

    def reference() -> None:
        plain["cal"] = plain_self_calibration(start, exp, volume)

    run = alternate(lambda: self_calibrate(start, frames, SelfCalOptions(), volume=volume).calibration, reference,
                    repeats)
    names = list(exp.truth_b.cameras)[1:]
    err = max(relative_rotation_deg(run["extra"][0], exp.truth_b, n) for n in names)
    err_plain = max(relative_rotation_deg(plain["cal"], exp.truth_b, n) for n in names)
    wall, cpu = statistics.median(run["ours"]), statistics.median(run["ours_cpu"])
    report("selfcal", f"self_calibrate README experiment, {len(frames)} x 2000 / plain reference", run,
           note=f"{wall:.1f} s wall, {cpu:.1f} s CPU: goal <= 20 s wall, <= 30 s CPU: "
                f"{'met' if wall <= 20.0 and cpu <= 30.0 else 'NOT met'}; largest relative rotation error "
                f"{err:.4f} deg, the plain reference's {err_plain:.4f} deg")


def reset_peak_memory() -> None:
    """Start a new peak-RSS window (Linux: /proc/self/clear_refs 5; elsewhere the process peak stays)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def peak_memory_mb() -> float:
    """Peak RSS since the last reset_peak_memory (VmHWM), else the process peak (ru_maxrss)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


COLD_START = """
import time
w0, c0 = time.perf_counter(), time.process_time()
def lap(label):
    global w0, c0
    w, c = time.perf_counter(), time.process_time()
    print(f"{label}|{w - w0:.2f}|{c - c0:.2f}")
    w0, c0 = w, c
import numpy as np
from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.io import parse_calibration
from ari_sfm.models.exact import exact_project
from ari_sfm.simulate import make_scene
from ari_sfm.reconstruction.triangulate import triangulate_pixels
lap("import ari_sfm (numba included)")
exact_project(np.array([[1.0, 2.0, 400.0]]), np.r_[3000., 3000, 1000, 800, np.zeros(5)], np.array([0, 0, 1.0]),
              6.0, 1.5168, 1.333, 40.0)
lap("first exact_project (+ Jacobians)")
scene = make_scene("binocular", seed=0)
lap("make_scene binocular")
calibrate(scene.dataset, model="exact")
lap("first calibrate(exact)")
truth = parse_calibration(scene.truth)
X = np.array([p.t for p in truth.frames.values()])
triangulate_pixels(truth, {c: truth.project_world(c, X) for c in truth.cameras})
lap("first triangulate_pixels (exact)")
calibrate(scene.dataset, model="exact")
lap("calibrate(exact) again")
for line in open("/proc/self/status"):
    if line.startswith("VmHWM:"):
        print(f"peak RSS MB|{int(line.split()[1]) / 1024:.0f}|")
"""


ROOT = Path(__file__).resolve().parents[1]


def fresh_wheel_install(tmp: Path) -> Path:
    """This tree built as a wheel (as .ci/run builds it: its kernels compiled into it) and installed into a
    fresh venv (dependencies from the package index / pip's cache); the venv's python."""
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    for folder in ("ari_sfm", "factors", "pipelines"):
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__", "_compiled"))
    quiet = dict(check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp / "wheel")], **quiet)
    subprocess.run([str(Path(sys.base_prefix) / "bin" / "python3"), "-m", "venv", str(tmp / "venv")], **quiet)
    python = tmp / "venv" / "bin" / "python"
    subprocess.run([str(python), "-m", "pip", "install", "-q", *map(str, (tmp / "wheel").glob("ari_sfm-*.whl"))],
                   **quiet)
    return python


def cold_start_run(python: Path, cwd: Path, env: dict[str, str]) -> tuple[float, float, list[list[str]]]:
    """COLD_START in a fresh process: its wall and CPU seconds (children included) and its rows."""
    t, c = time.perf_counter(), os.times()
    out = subprocess.run([str(python), "-c", COLD_START], env=env, cwd=cwd, capture_output=True, text=True,
                         check=True)
    c2 = os.times()
    cpu = c2.children_user + c2.children_system - c.children_user - c.children_system
    return time.perf_counter() - t, cpu, [line.split("|") for line in out.stdout.strip().splitlines()]


def cold_start() -> None:
    """The first run after a fresh install of the built wheel (its kernels shipped compiled) against the next
    two runs; then, for the record, what numba's compilation costs a first run without them; wall and CPU
    seconds per step and of the whole process."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        python = fresh_wheel_install(Path(tmp))
        print(f"\ncold start: the wheel built and installed into a fresh venv in {time.perf_counter() - t:.0f} s")
        runs = [cold_start_run(python, Path(tmp), env) for _ in ("first", "second", "third")]
        # numba's target named as it is by default (this CPU): the shipped code is not used, numba compiles
        compiling = {**env, "NUMBA_CPU_NAME": llvmlite.binding.get_host_cpu_name(),
                     "NUMBA_CPU_FEATURES": numba.core.codegen.get_host_cpu_features()}
        runs.append(cold_start_run(python, Path(tmp), compiling))
    labels = ("installed, first", "second", "third", "compiling")
    print("wall / CPU s of fresh processes: the installed wheel's first run after the install, its second and third "
          "runs, and a fourth with numba's target set to this CPU's (the shipped code unused: numba compiles)")
    print(f"{'step':36s}" + "".join(f" {label:>17s}" for label in labels))
    for i, (label, *_) in enumerate(runs[0][2]):
        cells = [f"{r[2][i][1]:>8s} {r[2][i][2] or '':>8s}" for r in runs]
        print(f"{label:36s} " + " ".join(f"{c:>17s}" for c in cells))
    print(f"{'whole process (python start included)':36s} "
          + " ".join(f"{f'{w:.2f} {c:.2f}':>17s}" for w, c, _ in runs))
    warm_wall = statistics.median([runs[1][0], runs[2][0]])
    warm_cpu = statistics.median([runs[1][1], runs[2][1]])
    print(f"first run after the install / warm runs: {runs[0][0] / warm_wall:.2f} wall, "
          f"{runs[0][1] / warm_cpu:.2f} CPU (goal <= 1.3); without the shipped kernels: "
          f"{runs[3][0] / warm_wall:.1f} wall, {runs[3][1] / warm_cpu:.1f} CPU")


FIGURES = ("calibrate_single", "calibrate_4x100", "calibrate_arc_sparse", "triangulate", "triangulate_dist", "forward",
           "openptv", "openptv_multiplane", "openptv_multiplane_placed", "refine_colmap", "refine_colmap_port",
           "particles", "selfcal")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default=",".join(FIGURES) + ",cold_start",
                    help=f"comma-separated subset of {', '.join(FIGURES)}, cold_start")
    ap.add_argument("--repeats", type=int, default=7, help="alternating pairs per figure (default 7)")
    ap.add_argument("--points", type=int, default=20000, help="points for triangulate and forward")
    ap.add_argument("--dist-points", type=int, default=188000, help="points for triangulate_dist")
    ap.add_argument("--particle-frames", type=int, default=5, help="frames of 2000 particles for particles")
    args = ap.parse_args()
    only = set(args.only.split(","))
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.2f}; {args.repeats} alternating pairs per figure")
    print(f"{'figure':17s} {'ours / reference':58s} {'ours ms':>9s} {'ref ms':>9s} {'median':>7s} [min-max]")
    runs = {"calibrate_single": lambda: fig_calibrate_single(args.repeats),
            "calibrate_4x100": lambda: fig_calibrate_4x100(max(3, args.repeats // 2)),
            "triangulate": lambda: fig_triangulate(args.repeats, args.points),
            "forward": lambda: fig_forward(args.repeats, args.points),
            "openptv": lambda: fig_openptv(max(3, args.repeats // 2)),
            "refine_colmap": lambda: fig_refine_colmap(max(3, args.repeats // 2)),
            "calibrate_arc_sparse": lambda: fig_calibrate_arc_sparse(args.repeats),
            "triangulate_dist": lambda: fig_triangulate_dist(args.repeats, args.dist_points),
            "openptv_multiplane": lambda: fig_openptv_multiplane(max(3, args.repeats // 2)),
            "openptv_multiplane_placed": lambda: fig_openptv_multiplane_placed(max(3, args.repeats // 2)),
            "refine_colmap_port": lambda: fig_refine_colmap_port(max(3, args.repeats // 2)),
            "particles": lambda: fig_particles(args.repeats, args.particle_frames),
            "selfcal": lambda: fig_selfcal(max(2, args.repeats // 3))}
    peaks = {}
    for name in FIGURES:
        if name in only:
            reset_peak_memory()
            runs[name]()
            peaks[name] = peak_memory_mb()
    print("peak RSS MB while each ran (both commands): " + ", ".join(f"{k} {v:.0f}" for k, v in peaks.items()))
    if "cold_start" in only:
        cold_start()
    print(f"\nload average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()

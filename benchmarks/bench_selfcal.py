"""Volume self-calibration through the window on a simulated drifted experiment.

    python benchmarks/bench_selfcal.py [--particles 2000] [--frames 10] [--seed 0] [--start truth|body]
                                       [--start-frames 3] [--workers 0] [--backend numpy]
                                       [--drift-cameras 1,2,3] [--drift-deg 0.05] [--k1 0]
    python benchmarks/bench_selfcal.py --cases [NAME ...] [--start-frames 3 6 10] [--start-target body|board] [--seed S]
                                       [--particles 2000] [--frames 10]
    python benchmarks/bench_selfcal.py --priors [NAME ...] [--start-frames 3 6 10] [--seed S]
    python benchmarks/bench_selfcal.py --list
    python benchmarks/bench_selfcal.py --reference [--particles 2000] [--frames 10]

``--cases``: a table over seeds, drift sizes, which cameras drift (camera 0 alone, all) and lens
distortion (``--list`` names them; ``--cases NAME ...`` runs those alone, one at a time), each started
from rig A's body calibration with ``calibrate --model exact --distortion`` as a user would, from
``--start-frames`` views of the body (several numbers: each case from each): the largest error of a
camera's rotation relative to camera 0 against rig B's, at the start and after, the sigma of that
camera (calibration.json's uncertainty) and the largest error / sigma over the cameras, the checks,
CPU and wall seconds of the self-calibration alone.
``--priors``: per case the last bundle adjustment again on the same particles with the start's
intrinsics weighed by their sigmas (as shipped), by the target calibration's joint covariance (the
same parameters; every intrinsic parameter free), and with the exact intrinsics held (the floor).
``--reference``: ari-sfm's self-calibration beside a minimal plain one (this file: loose matching at
5 px on every frame, disparity peaks by a 2-D histogram per camera, a plain bundle adjustment with
camera 0 and the intrinsics held), both in this process, alternately.

The experiment of ari_sfm.simulate.particles (4 cameras ~400 mm from a 60 x 40 x 30 mm volume in
water behind 10 mm of glass, 0.1 px detection noise, cameras 1-3 turned by 0.05 deg and moved by
0.3 mm after the target calibration). Self-calibration starts from rig A: its true calibration
(``--start truth``) or the exact-model calibration of the simulated body views (``--start body``,
what a lab has; ``--start-frames`` views). Prints the disparity RMS per camera before/after, each
camera's rotation relative to camera 0 against rig B's (and the drifted start's), the centres' errors,
and matching at 0.5 px (>= 3 cameras) with the true (rig B), the drifted and the self-calibrated
calibrations: found and ghost fractions, the fraction of reconstructed particles whose images are all
one particle's (``rows``), the 3D RMS error of the correct ones after a rigid alignment onto the truth;
and times.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from ari_sfm.geometry import rotation_angle_deg  # noqa: E402
from ari_sfm.models.pinhole import PARAM_NAMES  # noqa: E402
from ari_sfm.particles.match import match_frame  # noqa: E402
from ari_sfm.particles.selfcal import SelfCalOptions, dask_map, self_calibrate  # noqa: E402
from ari_sfm.particles.truth import score_experiment  # noqa: E402
from ari_sfm.particles.volume import Volume  # noqa: E402
from ari_sfm.simulate.particles import (  # noqa: E402
    ParticleSimOptions,
    simulate_particle_experiment,
    write_particle_experiment,
)

TOLERANCE_PX = 0.5


def relative_rotation_deg(cal, truth, name: str) -> float:
    first = next(iter(cal.cameras))

    def rel(c):
        return c.cameras[name].cam_from_world.R @ c.cameras[first].cam_from_world.R.T

    return rotation_angle_deg(rel(cal), rel(truth))


def body_calibration(exp, distortion: bool = True):
    """Rig A calibrated from the simulated target's views (the body's, or a board's) with the exact model (as
    `ari-sfm calibrate --model exact --distortion`)."""
    from ari_sfm.calibration.calibrate import calibrate
    from ari_sfm.io import load_calibration, load_dataset, save_calibration

    folder = Path(tempfile.mkdtemp())
    write_particle_experiment(exp, folder, render_frames=0)
    cal = calibrate(load_dataset(folder / "calibration"), model="exact", distortion=distortion)
    save_calibration(cal, folder / "cal.json")
    return load_calibration(folder / "cal.json")


@dataclass(frozen=True)
class Case:
    """One simulated drift: the seed, which cameras moved, by how much, the lenses' k1."""

    seed: int
    drift_cameras: tuple[int, ...]
    drift_deg: float
    drift_mm: float
    k1: float = 0.0


CASES = {
    "cams123-s0": Case(0, (1, 2, 3), 0.05, 0.3),
    "cams123-s1": Case(1, (1, 2, 3), 0.05, 0.3),
    "cams123-s2": Case(2, (1, 2, 3), 0.05, 0.3),
    "cams123-0.08deg-s3": Case(3, (1, 2, 3), 0.08, 0.3),
    "cam0-s4": Case(4, (0,), 0.05, 0.3),
    "all-s5": Case(5, (0, 1, 2, 3), 0.05, 0.3),
    "all-0.03deg-s6": Case(6, (0, 1, 2, 3), 0.03, 0.2),
    "all-k1-0.03-s7": Case(7, (0, 1, 2, 3), 0.05, 0.3, -0.03),
    "all-k1-0.06-s8": Case(8, (0, 1, 2, 3), 0.05, 0.3, -0.06),
}


def simulate_case(case: Case, particles: int, frames: int, start_frames: int = 3, start_target: str = "body"):
    """The experiment of ``case``, rig A's target seen in ``start_frames`` views."""
    return simulate_particle_experiment(ParticleSimOptions(
        particles_per_frame=particles, num_frames=frames, seed=case.seed, drift_cameras=case.drift_cameras,
        drift_deg=case.drift_deg, drift_mm=case.drift_mm, k1=case.k1, calibration_frames=start_frames,
        calibration_target=start_target))


def run_case(case: Case, particles: int, frames: int, start_frames: int = 3, start_target: str = "body",
             options: SelfCalOptions = SelfCalOptions()) -> dict:
    """One simulated drift self-calibrated from the target calibration of ``start_frames`` views of
    ``start_target`` (the body, or a board): errors, sigmas, checks, times."""
    exp = simulate_case(case, particles, frames, start_frames, start_target)
    volume = Volume(exp.volume_min_mm, exp.volume_max_mm)
    start = body_calibration(exp)
    w0, c0 = time.perf_counter(), time.process_time()
    res = self_calibrate(start, dict(enumerate(exp.detections)), options, volume=volume)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    b, c = exp.truth_b, res.calibration
    names = list(b.cameras)[1:]
    unc = c.uncertainty.cameras
    errors = {n: relative_rotation_deg(c, b, n) for n in names}
    worst = max(names, key=errors.get)
    return {"start": max(relative_rotation_deg(start, b, n) for n in names), "after": errors[worst],
            "sigma": unc[worst].rotation_deg, "ratio": max(errors[n] / unc[n].rotation_deg for n in names),
            "passed": res.report.passed,
            "warnings": [k.name for k in res.report.checks if not k.passed and not k.fatal],
            "disparity": float(max(d.after for d in res.report.disparity_rms_px.values())),
            "wall": wall, "cpu": cpu}


def cases(names, particles: int, frames: int, start_frames, start_target: str = "body") -> None:
    print(f"{frames} frames x {particles} particles, 0.1 px noise; started from rig A's calibration "
          f"(calibrate --model exact --distortion) of N views of the {start_target}; errors of each camera's "
          "rotation relative to camera 0 against rig B: the largest over the cameras, that camera's sigma, the largest "
          "error / sigma")
    print(f"| case | {start_target} views | start error (deg) | after (deg) | sigma (deg) | largest error / sigma "
          "| disparity after (px) | checks | CPU s | wall s |\n|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        for n in start_frames:
            r = run_case(CASES[name], particles, frames, n, start_target)
            print(f"| {name} | {n} | {r['start']:.4f} | {r['after']:.4f} | {r['sigma']:.4f} | {r['ratio']:.2f} | "
                  f"{r['disparity']:.3f} | {'passed' if r['passed'] else 'FAILED'}"
                  + "".join(f", warned {w}" for w in r["warnings"]) + f" | {r['cpu']:.1f} | {r['wall']:.1f} |",
                  flush=True)


# --------------------------------------------------------------------------- the intrinsics priors compared


def body_calibration_and_covariance(exp) -> tuple:
    """body_calibration(exp) and the joint covariance (C 9, C 9) of every camera's intrinsics [fx fy cx cy k1 k2
    p1 p2 k3] (camera-major) from its normal equations, the poses, the window and the body's views marginalised,
    in the units of calibration.json's uncertainty (whose sigmas are its diagonal's roots)."""
    import ari_sfm.factors.uncertainty as uncertainty
    from ari_sfm.solver.schur import global_covariance

    kept = {}
    original = uncertainty.marginal_covariances

    def capture(rg, solved=None, sigma_px=None):
        scale = 1.0 if sigma_px is None else (sigma_px / rg.sigma_px) ** 2
        cov = global_covariance(solved.linearize(solved.x), solved.fixed_cols) * scale
        idx = np.concatenate([c * solved.camera_block + np.arange(solved.n_params)
                              for c in range(len(solved.camera_names))])
        kept["cov"] = cov[np.ix_(idx, idx)]
        return original(rg, solved, sigma_px)

    uncertainty.marginal_covariances = capture
    try:
        start = body_calibration(exp)
    finally:
        uncertainty.marginal_covariances = original
    cov = kept["cov"]
    sigmas = np.concatenate([[start.uncertainty.cameras[n].intrinsics[k] for k in PARAM_NAMES] for n in start.cameras])
    if not np.allclose(np.sqrt(np.diag(cov)), sigmas, rtol=1e-6):
        raise RuntimeError("the captured covariance is not the one calibration.json's sigmas come from")
    return start, cov


def compare_priors(names, particles: int, frames: int, start_frames, start_target: str = "body") -> None:
    """Per case: the self-calibration as shipped, then its last bundle adjustment again on the same particles
    (every frame matched at 0.5 px with its result, the disparity peaks' inliers) with the start's intrinsics
    weighed otherwise: its sigmas alone (as shipped), its joint covariance over the same parameters, every
    intrinsic parameter free under the joint covariance, and the exact intrinsics held (the floor)."""
    from ari_sfm.particles.disparity import Cells, ParticleSet, disparity_map, particle_disparities
    from ari_sfm.particles.landmarks import Gauge, IntrinsicsPrior, free_intrinsics, refine_with_landmarks
    from ari_sfm.particles.selfcal import match_particles

    print(f"{frames} frames x {particles} particles; the relative rotations' errors (deg) against rig B: the largest "
          "over the cameras / their RMS, and the largest sigma")
    print(f"| case | {start_target} views | as shipped (sigmas) | joint covariance, same parameters "
          "| every intrinsic free, joint covariance | exact intrinsics held |\n|---|---|---|---|---|---|")
    for name in names:
        case = CASES[name]
        for n_views in start_frames:
            exp = simulate_case(case, particles, frames, n_views, start_target)
            volume = Volume(exp.volume_min_mm, exp.volume_max_mm)
            start, cov = body_calibration_and_covariance(exp)
            result = self_calibrate(start, dict(enumerate(exp.detections)), SelfCalOptions(), volume=volume).calibration
            found = [match_particles(result, f, det, 0.5, 4, volume) for f, det in enumerate(exp.detections)]
            pixels = np.concatenate([f.pixels for f in found])
            xyz = np.concatenate([f.xyz for f in found])
            particles_all = ParticleSet(pixels, xyz, np.concatenate([np.full(len(f.xyz), f.frame) for f in found]))
            dmap = disparity_map(exp.cameras, Cells.around(xyz, (3, 3, 3)), particles_all,
                                 particle_disparities(result, particles_all), 0.5, 1.5, 0)
            keep = np.flatnonzero(dmap.inlier)
            landmarks = ParticleSet(pixels[keep], xyz[keep], particles_all.frame[keep])
            centre = np.median(landmarks.xyz, axis=0)
            length = float(np.mean([np.linalg.norm(c.cam_from_world.inverse().t - centre)
                                    for c in start.cameras.values()]))
            gauge = Gauge.of(start, [False], length)
            free = free_intrinsics(start, "prior")
            sel = np.concatenate([c * 9 + np.array(free) for c in range(len(exp.cameras))])
            exact = replace(result, cameras={n: replace(cam, K=exp.truth_a.cameras[n].K,
                                                        dist=np.asarray(exp.truth_a.cameras[n].dist, float))
                                             for n, cam in result.cameras.items()})
            runs = [(result, IntrinsicsPrior.of(start, free, "prior")),
                    (result, IntrinsicsPrior.of(start, free, "prior").with_covariance(cov[np.ix_(sel, sel)])),
                    (result, IntrinsicsPrior.of(start, tuple(range(9)), "prior").with_covariance(cov)),
                    (exact, IntrinsicsPrior.of(exact, (), "held"))]
            cells = []
            for cal, prior in runs:
                r = refine_with_landmarks(cal, landmarks, gauge, prior)
                errors = np.array([relative_rotation_deg(r.calibration, exp.truth_b, n) for n in exp.cameras[1:]])
                sigma = max(r.covariance.cameras[n].rotation_rel_deg for n in exp.cameras[1:])
                cells.append(f"{errors.max():.4f} / {np.sqrt(np.mean(errors ** 2)):.4f}, sigma {sigma:.4f}")
            print(f"| {name} | {n_views} | " + " | ".join(cells) + " |", flush=True)


# --------------------------------------------------------------------------- a minimal plain reference


def _plain_peak(d: np.ndarray, bin_px: float = 0.25, radius_px: float = 0.5) -> np.ndarray:
    """(M,) inliers of matches with disparities d (M, C, 2): per camera the fullest bin of a 2-D histogram,
    a match on every camera's bin within the radius."""
    ok = np.ones(len(d), bool)
    for c in range(d.shape[1]):
        x, y = d[:, c, 0], d[:, c, 1]
        edges = np.arange(-12.0, 12.0 + bin_px, bin_px)
        H, ex, ey = np.histogram2d(x, y, bins=[edges, edges])
        i, j = np.unravel_index(np.argmax(H), H.shape)
        peak = np.array([0.5 * (ex[i] + ex[i + 1]), 0.5 * (ey[j] + ey[j + 1])])
        ok &= np.linalg.norm(d[:, c] - peak, axis=1) <= radius_px
    return ok


def _plain_adjust(cal, pixels: np.ndarray, xyz: np.ndarray):
    """A plain bundle adjustment (scipy least_squares, finite differences on a sparse pattern): cameras 1..C-1
    (rotation vector, translation) and the points; camera 0, the intrinsics and the window held."""
    from dataclasses import replace as dc_replace

    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    from ari_sfm.geometry import Pose, rotation_from_rotvec

    names = list(cal.cameras)
    C, P = len(names), len(xyz)

    def with_poses(x):
        cams = dict(cal.cameras)
        for k, n in enumerate(names[1:]):
            w, v = x[6 * k:6 * k + 3], x[6 * k + 3:6 * k + 6]
            p = cal.cameras[n].cam_from_world
            cams[n] = dc_replace(cams[n], cam_from_world=Pose(rotation_from_rotvec(w) @ p.R, p.t + v))
        return dc_replace(cal, cameras=cams)

    def residuals(x):
        c = with_poses(x)
        X = x[6 * (C - 1):].reshape(P, 3)
        r = np.stack([c.project_world(n, X) - pixels[:, k] for k, n in enumerate(names)], axis=1)
        return np.nan_to_num(r, nan=100.0).ravel()

    pattern = lil_matrix((P * C * 2, 6 * (C - 1) + 3 * P), dtype=int)
    for k in range(C):
        rows = (np.arange(P)[:, None] * C * 2 + k * 2 + np.arange(2)).ravel()
        if k:
            for col in range(6 * (k - 1), 6 * k):
                pattern[rows, col] = 1
        for a in range(3):
            pattern[(np.arange(P)[:, None] * C * 2 + k * 2 + np.arange(2)),
                    (6 * (C - 1) + 3 * np.arange(P) + a)[:, None]] = 1
    x0 = np.concatenate([np.zeros(6 * (C - 1)), xyz.ravel()])
    # a drift is small: each pose's change bounded (0.05 rad, 20 mm), so that no trial step moves a camera
    # through its window (where the exact model has no projection)
    step = np.tile(np.r_[np.full(3, 0.05), np.full(3, 20.0)], C - 1)
    lower = np.r_[-step, np.full(3 * P, -np.inf)]
    upper = np.r_[step, np.full(3 * P, np.inf)]
    sol = least_squares(residuals, x0, jac_sparsity=pattern, loss="huber", f_scale=1.0, x_scale="jac",
                        bounds=(lower, upper), max_nfev=30)
    return with_poses(sol.x)


def plain_self_calibration(start, exp, volume, loose_px: float = 5.0):
    """Disparity maps by loose matching (every frame), histogram peaks, a plain bundle adjustment; then once
    more at 0.5 px."""
    cal = start
    for tol in (loose_px, TOLERANCE_PX):
        pix, X = [], []
        for det in exp.detections:
            m = match_frame(cal, det, tol, volume=volume, min_cameras=4)
            p = np.stack([det[n][m.rows[:, k]] for k, n in enumerate(exp.cameras)], axis=1)
            pix.append(p)
            X.append(m.xyz)
        pix, X = np.concatenate(pix), np.concatenate(X)
        d = np.stack([pix[:, k] - cal.project_world(n, X) for k, n in enumerate(exp.cameras)], axis=1)
        ok = _plain_peak(d)
        cal = _plain_adjust(cal, pix[ok], X[ok])
    return cal


def reference_comparison(particles: int, frames: int, seed: int, repeats: int = 2) -> None:
    """ari-sfm's self-calibration and the plain reference on one experiment, alternately, in this process."""
    exp = simulate_particle_experiment(ParticleSimOptions(particles_per_frame=particles, num_frames=frames, seed=seed))
    volume = Volume(exp.volume_min_mm, exp.volume_max_mm)
    start = exp.truth_a
    print(f"{frames} frames x {particles} particles, seed {seed}, from rig A's true calibration")
    for _ in range(repeats):
        for label, fn in (("ari-sfm", lambda: self_calibrate(start, dict(enumerate(exp.detections)), SelfCalOptions(),
                                                               volume=volume).calibration),
                          ("plain reference", lambda: plain_self_calibration(start, exp, volume))):
            w0, c0 = time.perf_counter(), time.process_time()
            cal = fn()
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
            err = max(relative_rotation_deg(cal, exp.truth_b, n) for n in list(exp.truth_b.cameras)[1:])
            print(f"{label:16s} wall {wall:6.1f} s  CPU {cpu:6.1f} s  largest relative rotation error {err:.4f} deg",
                  flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=2000)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--seed", type=int, default=None, help="the simulation's seed (default 0; with --cases or "
                                                             "--priors: instead of each case's own)")
    ap.add_argument("--start", choices=("truth", "body"), default="truth")
    ap.add_argument("--workers", type=int, default=0, help="Dask LocalCluster workers for the matching (0: in process)")
    ap.add_argument("--backend", choices=("numpy", "gtsam"), default="numpy")
    ap.add_argument("--drift-cameras", default="1,2,3")
    ap.add_argument("--drift-deg", type=float, default=0.05)
    ap.add_argument("--k1", type=float, default=0.0)
    ap.add_argument("--start-frames", type=int, nargs="+", default=None,
                    help="views of the calibration body rig A is calibrated from (--start body, --cases; default 3; "
                         "--cases: several numbers run each case from each)")
    ap.add_argument("--start-target", choices=("body", "board"), default="body",
                    help="rig A's target (--start body, --cases, --priors): the simulated 3D body, or a planar "
                         "checkerboard tilted 10-40 deg")
    ap.add_argument("--cases", nargs="*", default=None, metavar="NAME",
                    help="the table over drifts, seeds and distortion (no name: every case; --list names them)")
    ap.add_argument("--priors", nargs="*", default=None, metavar="NAME",
                    help="per case, the last bundle adjustment again with the start's intrinsics weighed otherwise "
                         "(its joint covariance; exact intrinsics)")
    ap.add_argument("--list", action="store_true", help="the cases' names")
    ap.add_argument("--reference", action="store_true", help="beside a minimal plain self-calibration")
    args = ap.parse_args()
    start_frames = args.start_frames or [3]
    if args.seed is not None:  # the cases with another seed
        CASES.update({n: replace(c, seed=args.seed) for n, c in CASES.items()})
    if args.list:
        for name, c in CASES.items():
            print(f"{name}: seed {c.seed}, cameras {','.join(map(str, c.drift_cameras))} moved by {c.drift_deg:g} deg "
                  f"and {c.drift_mm:g} mm, k1 {c.k1:g}")
        return
    seed = 0 if args.seed is None else args.seed
    for chosen in (args.cases, args.priors):
        unknown = [n for n in chosen or () if n not in CASES]
        if unknown:
            ap.error(f"unknown case(s) {', '.join(unknown)} (known: {', '.join(CASES)})")
    if args.cases is not None:
        cases(args.cases or list(CASES), args.particles, args.frames, start_frames, args.start_target)
        return
    if args.priors is not None:
        compare_priors(args.priors or list(CASES), args.particles, args.frames, start_frames, args.start_target)
        return
    if args.reference:
        reference_comparison(args.particles, args.frames, seed)
        return
    exp = simulate_particle_experiment(ParticleSimOptions(
        particles_per_frame=args.particles, num_frames=args.frames, seed=seed, drift_deg=args.drift_deg,
        drift_cameras=tuple(int(c) for c in args.drift_cameras.split(",") if c.strip()), k1=args.k1,
        calibration_frames=start_frames[0], calibration_target=args.start_target))
    volume = Volume(exp.volume_min_mm, exp.volume_max_mm)
    start = exp.truth_a if args.start == "truth" else body_calibration(exp)
    what = ("true calibration" if args.start == "truth" else
            f"{args.start_target} calibration (exact model, {start_frames[0]} views)")
    print(f"{args.frames} frames x {args.particles} particles, seed {seed}, start: rig A's {what}, "
          f"backend {args.backend}")
    t0 = time.perf_counter()
    if args.workers:
        from ari_sfm.particles.engine import dask_client

        with dask_client(args.workers, None) as client:
            res = self_calibrate(start, dict(enumerate(exp.detections)), SelfCalOptions(backend=args.backend),
                                 volume=volume, map_frames=dask_map(client))
    else:
        res = self_calibrate(start, dict(enumerate(exp.detections)), SelfCalOptions(backend=args.backend),
                             volume=volume)
    wall = time.perf_counter() - t0
    rounds = res.report.rounds
    print(f"self-calibration: {wall:.1f} s wall, {len(rounds)} rounds "
          + ", ".join(f"{r.tolerance_px:g} px: {r.matches} matches / {int(r.disparity.inlier.sum())} inliers"
                     for r in rounds))
    c, a, b = res.calibration, start, exp.truth_b
    print(f"{'camera':7s} {'disp before':>11s} {'disp after':>10s} {'rot err start':>13s} {'rot err after':>13s} "
          f"{'centre err mm':>13s}")
    for name in b.cameras:
        d = res.report.disparity_rms_px[name]
        centre = np.linalg.norm(c.cameras[name].cam_from_world.inverse().t - b.cameras[name].cam_from_world.inverse().t)
        print(f"{name:7s} {d.before:11.3f} {d.after:10.3f} {relative_rotation_deg(a, b, name):13.4f} "
              f"{relative_rotation_deg(c, b, name):13.4f} {centre:13.3f}")
    print(f"{'calibration':15s} {'particles':>9s} {'found':>7s} {'ghosts':>7s} {'right rows':>10s} {'3D rms mm':>10s}"
          " (after a rigid alignment)")
    for label, cal in (("true (rig B)", b), ("drifted start", a), ("self-calibrated", c)):
        s, rms = score_experiment(exp, volume, cal)
        print(f"{label:15s} {s.reconstructed:9d} {s.found_fraction:7.4f} {s.ghost_fraction:7.4f} "
              f"{1 - s.ghost_fraction:10.4f} {rms:10.4f}")


if __name__ == "__main__":
    main()

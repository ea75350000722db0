"""Volume self-calibration through the window on a simulated drifted experiment.

    python benchmarks/bench_selfcal.py [--particles 2000] [--frames 10] [--seed 0] [--start truth|body]
                                       [--workers 0] [--backend numpy] [--drift-cameras 1,2,3] [--drift-deg 0.05]
                                       [--k1 0]
    python benchmarks/bench_selfcal.py --cases [--particles 2000] [--frames 10]
    python benchmarks/bench_selfcal.py --reference [--particles 2000] [--frames 10]

``--cases``: a table over seeds, drift sizes, which cameras drift (camera 0 alone, all) and lens
distortion, each started from rig A's body calibration with ``calibrate --distortion`` as a user would:
the largest error of a camera's rotation relative to camera 0 against rig B's, at the start and after,
the largest error / sigma (calibration.json's uncertainty), the checks, CPU and wall seconds.
``--reference``: ari-sfm's self-calibration beside a minimal plain one (this file: loose matching at
5 px on every frame, disparity peaks by a 2-D histogram per camera, a plain bundle adjustment with
camera 0 and the intrinsics held), both in this process, alternately.

The experiment of ari_sfm.simulate.particles (4 cameras ~400 mm from a 60 x 40 x 30 mm volume in
water behind 10 mm of glass, 0.1 px detection noise, cameras 1-3 turned by 0.05 deg and moved by
0.3 mm after the target calibration). Self-calibration starts from rig A: its true calibration
(``--start truth``) or the exact-model calibration of the simulated body views (``--start body``,
what a lab has). Prints the disparity RMS per camera before/after, each camera's rotation relative to
camera 0 against rig B's (and the drifted start's), the centres' errors, and matching at 0.5 px
(>= 3 cameras) with the true (rig B), the drifted and the self-calibrated calibrations: found and
ghost fractions, the fraction of reconstructed particles whose images are all one particle's
(``rows``), the 3D RMS error of the correct ones after a rigid alignment onto the truth; and times.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from ari_sfm.geometry import rotation_angle_deg  # noqa: E402
from ari_sfm.metrics import rigid_alignment  # noqa: E402
from ari_sfm.particles.match import match_frame  # noqa: E402
from ari_sfm.particles.selfcal import SelfCalOptions, dask_map, self_calibrate  # noqa: E402
from ari_sfm.particles.truth import score_frame, true_ids  # noqa: E402
from ari_sfm.particles.volume import Volume  # noqa: E402
from ari_sfm.simulate.particles import (  # noqa: E402
    ParticleSimOptions,
    simulate_particle_experiment,
    write_particle_experiment,
)

TOLERANCE_PX = 0.5


def judge(exp, volume, calibration) -> tuple:
    """Score of matching every frame at 0.5 px, and the aligned 3D RMS (mm) of the correct particles."""
    total, P, Q = None, [], []
    for f, det in enumerate(exp.detections):
        m = match_frame(calibration, det, TOLERANCE_PX, volume=volume, min_cameras=3)
        s = score_frame(m.xyz, m.rows, exp.cameras, exp.particle_ids[f], exp.positions[f])
        total = s if total is None else total + s
        ids = true_ids(m.rows, exp.cameras, exp.particle_ids[f])
        first = ids.max(axis=1)
        ok = np.all((ids < 0) | (ids == first[:, None]), axis=1)
        P.append(m.xyz[ok])
        Q.append(exp.positions[f][first[ok]])
    P, Q = np.concatenate(P), np.concatenate(Q)
    if len(P) < 3:
        return total, float("nan")
    R, t = rigid_alignment(P, Q)
    return total, float(np.sqrt(np.mean(np.sum((P @ R.T + t - Q) ** 2, axis=1))))


def relative_rotation_deg(cal, truth, name: str) -> float:
    first = next(iter(cal.cameras))
    rel = lambda c: c.cameras[name].cam_from_world.R @ c.cameras[first].cam_from_world.R.T
    return rotation_angle_deg(rel(cal), rel(truth))


def body_calibration(exp, distortion: bool = True):
    """Rig A calibrated from the simulated body views with the exact model (as `ari-sfm calibrate
    --distortion`)."""
    from ari_sfm.calibrate import calibrate
    from ari_sfm.io import load_calibration, save_calibration
    from ari_sfm.io import load_dataset

    folder = Path(tempfile.mkdtemp())
    write_particle_experiment(exp, folder, render_frames=0)
    cal = calibrate(load_dataset(folder / "calibration"), model="exact", distortion=distortion)
    save_calibration(cal, folder / "cal.json")
    return load_calibration(folder / "cal.json")


CASES = (  # (label, seed, drift_cameras, drift_deg, drift_mm, k1)
    ("cams 1-3, 0.05 deg, seed 0", 0, (1, 2, 3), 0.05, 0.3, 0.0),
    ("cams 1-3, 0.05 deg, seed 1", 1, (1, 2, 3), 0.05, 0.3, 0.0),
    ("cams 1-3, 0.05 deg, seed 2", 2, (1, 2, 3), 0.05, 0.3, 0.0),
    ("cams 1-3, 0.08 deg, seed 3", 3, (1, 2, 3), 0.08, 0.3, 0.0),
    ("cam 0 alone, 0.05 deg, seed 4", 4, (0,), 0.05, 0.3, 0.0),
    ("all cams, 0.05 deg, seed 5", 5, (0, 1, 2, 3), 0.05, 0.3, 0.0),
    ("all cams, 0.03 deg, seed 6", 6, (0, 1, 2, 3), 0.03, 0.2, 0.0),
    ("all cams, 0.05 deg, k1 -0.03, seed 7", 7, (0, 1, 2, 3), 0.05, 0.3, -0.03),
    ("all cams, 0.05 deg, k1 -0.06, seed 8", 8, (0, 1, 2, 3), 0.05, 0.3, -0.06),
)


def run_case(particles: int, frames: int, seed: int, drift_cameras, drift_deg: float, drift_mm: float, k1: float,
             options: SelfCalOptions = SelfCalOptions()) -> dict:
    """One simulated drift self-calibrated from the body calibration: errors, sigmas, checks, times."""
    exp = simulate_particle_experiment(ParticleSimOptions(particles_per_frame=particles, num_frames=frames, seed=seed,
                                                          drift_cameras=tuple(drift_cameras), drift_deg=drift_deg,
                                                          drift_mm=drift_mm, k1=k1))
    volume = Volume(exp.volume_min_mm, exp.volume_max_mm)
    start = body_calibration(exp)
    w0, c0 = time.perf_counter(), time.process_time()
    res = self_calibrate(start, dict(enumerate(exp.detections)), options, volume=volume)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    b, c = exp.truth_b, res.calibration
    names = list(b.cameras)[1:]
    unc = c.uncertainty.cameras
    ratio = max(relative_rotation_deg(c, b, n) / unc[n].rotation_deg for n in names)
    return {"start": max(relative_rotation_deg(start, b, n) for n in names),
            "after": max(relative_rotation_deg(c, b, n) for n in names),
            "sigma": max(unc[n].rotation_deg for n in names), "ratio": ratio, "passed": res.report.passed,
            "disparity": float(max(d.after for d in res.report.disparity_rms_px.values())), "wall": wall, "cpu": cpu}


def cases(particles: int, frames: int) -> None:
    print(f"{frames} frames x {particles} particles, 0.1 px noise; started from rig A's body calibration "
          "(calibrate --model exact --distortion); errors of each camera's rotation relative to camera 0 "
          "against rig B, the largest over the cameras")
    print(f"| case | start error (deg) | after (deg) | sigma after (deg) | largest error / sigma | disparity after (px) "
          f"| checks | CPU s | wall s |\n|---|---|---|---|---|---|---|---|---|")
    for label, seed, cams, deg, mm, k1 in CASES:
        r = run_case(particles, frames, seed, cams, deg, mm, k1)
        print(f"| {label} | {r['start']:.4f} | {r['after']:.4f} | {r['sigma']:.4f} | {r['ratio']:.2f} | "
              f"{r['disparity']:.3f} | {'passed' if r['passed'] else 'FAILED'} | {r['cpu']:.1f} | {r['wall']:.1f} |",
              flush=True)


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
            pattern[(np.arange(P)[:, None] * C * 2 + k * 2 + np.arange(2)), (6 * (C - 1) + 3 * np.arange(P) + a)[:, None]] = 1
    x0 = np.concatenate([np.zeros(6 * (C - 1)), xyz.ravel()])
    sol = least_squares(residuals, x0, jac_sparsity=pattern, loss="huber", f_scale=1.0, x_scale="jac",
                        max_nfev=30)
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
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start", choices=("truth", "body"), default="truth")
    ap.add_argument("--workers", type=int, default=0, help="Dask LocalCluster workers for the matching (0: in process)")
    ap.add_argument("--backend", choices=("numpy", "gtsam"), default="numpy")
    ap.add_argument("--drift-cameras", default="1,2,3")
    ap.add_argument("--drift-deg", type=float, default=0.05)
    ap.add_argument("--k1", type=float, default=0.0)
    ap.add_argument("--cases", action="store_true", help="the table over drifts, seeds and distortion")
    ap.add_argument("--reference", action="store_true", help="beside a minimal plain self-calibration")
    args = ap.parse_args()
    if args.cases:
        cases(args.particles, args.frames)
        return
    if args.reference:
        reference_comparison(args.particles, args.frames, args.seed)
        return
    exp = simulate_particle_experiment(ParticleSimOptions(
        particles_per_frame=args.particles, num_frames=args.frames, seed=args.seed, drift_deg=args.drift_deg,
        drift_cameras=tuple(int(c) for c in args.drift_cameras.split(",") if c.strip()), k1=args.k1))
    volume = Volume(exp.volume_min_mm, exp.volume_max_mm)
    start = exp.truth_a if args.start == "truth" else body_calibration(exp)
    print(f"{args.frames} frames x {args.particles} particles, seed {args.seed}, start: rig A's "
          f"{'true calibration' if args.start == 'truth' else 'body calibration (exact model)'}, backend {args.backend}")
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
    for k, name in enumerate(b.cameras):
        d = res.report.disparity_rms_px[name]
        centre = np.linalg.norm(c.cameras[name].cam_from_world.inverse().t - b.cameras[name].cam_from_world.inverse().t)
        print(f"{name:7s} {d.before:11.3f} {d.after:10.3f} {relative_rotation_deg(a, b, name):13.4f} "
              f"{relative_rotation_deg(c, b, name):13.4f} {centre:13.3f}")
    print(f"{'calibration':15s} {'particles':>9s} {'found':>7s} {'ghosts':>7s} {'right rows':>10s} {'3D rms mm':>10s}"
          " (after a rigid alignment)")
    for label, cal in (("true (rig B)", b), ("drifted start", a), ("self-calibrated", c)):
        s, rms = judge(exp, volume, cal)
        print(f"{label:15s} {s.reconstructed:9d} {s.found_fraction:7.4f} {s.ghost_fraction:7.4f} "
              f"{1 - s.ghost_fraction:10.4f} {rms:10.4f}")


if __name__ == "__main__":
    main()

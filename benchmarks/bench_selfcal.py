"""Volume self-calibration through the window on a simulated drifted experiment.

    python benchmarks/bench_selfcal.py [--particles 2000] [--frames 10] [--seed 0] [--start truth|body]
                                       [--workers 0] [--backend numpy]

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


def body_calibration(exp):
    """Rig A calibrated from the simulated body views with the exact model (as `ari-sfm calibrate`)."""
    from ari_sfm.calibrate import calibrate
    from ari_sfm.io import load_calibration, save_calibration
    from ari_sfm.io import load_dataset

    folder = Path(tempfile.mkdtemp())
    write_particle_experiment(exp, folder, render_frames=0)
    cal = calibrate(load_dataset(folder / "calibration"), model="exact")
    save_calibration(cal, folder / "cal.json")
    return load_calibration(folder / "cal.json")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=2000)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start", choices=("truth", "body"), default="truth")
    ap.add_argument("--workers", type=int, default=0, help="Dask LocalCluster workers for the matching (0: in process)")
    ap.add_argument("--backend", choices=("numpy", "gtsam"), default="numpy")
    args = ap.parse_args()
    exp = simulate_particle_experiment(ParticleSimOptions(particles_per_frame=args.particles, num_frames=args.frames,
                                                          seed=args.seed))
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

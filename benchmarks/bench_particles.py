"""Particles through the window: ari-sfm's matching beside OpenPTV's, and 1 vs 2 Dask workers.

    python benchmarks/bench_particles.py [--particles 2000] [--frames 4] [--skip-dask]

On a simulated experiment (ari_sfm.simulate.particles: 4 cameras ~400 mm from a
60 x 40 x 30 mm volume in water behind 10 mm of glass, 0.1 px detection noise)
prints, for the true calibration (rig B) and the drifted one (rig A):
found fraction (of the particles seen by >= 3 cameras), ghost fraction, 3D RMS
error of the correct ones, and particles per second per core (CPU time), for

- ari-sfm: ``match_frame`` (refracted epipolar curves of the exact model,
  0.5 px tolerance, >= 3 cameras), and
- OpenPTV (liboptv through ``optv``): ``correspondences`` + ``point_positions``
  on the same detections (OpenPTV pixel convention: +0.5 px) and the same
  calibration written by ``ari-sfm export-openptv`` (world = the body frame
  f000), epipolar band eps0 = the same 0.5 px, the same volume (its bounding
  box in that frame).

Then ``reconstruct_particles`` on a LocalCluster of 1 and of 2 single-threaded
workers: wall time, particles per second and the speed-up (on this machine).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ari_sfm.particles.match import match_frame  # noqa: E402
from ari_sfm.particles.truth import ParticleScore, score_frame  # noqa: E402
from ari_sfm.particles.volume import Volume  # noqa: E402
from ari_sfm.simulate.particles import (  # noqa: E402
    ParticleSimOptions,
    simulate_particle_experiment,
    write_particle_experiment,
)

TOLERANCE_PX = 0.5


def ours(exp, calibration, volume) -> tuple[ParticleScore, float]:
    total, cpu = None, 0.0
    for f in range(len(exp.positions)):
        t = time.process_time()
        m = match_frame(calibration, exp.detections[f], TOLERANCE_PX, volume=volume)
        cpu += time.process_time() - t
        s = score_frame(m.xyz, m.rows, exp.cameras, exp.particle_ids[f], exp.positions[f])
        total = s if total is None else total + s
    return total, cpu


def openptv(exp, calibration_path: Path, folder: Path, volume: Volume) -> tuple[ParticleScore, float]:
    """liboptv's correspondences + point positions on the same detections and calibration
    (``openptv_matching``; the targets' making timed with them)."""
    from openptv_matching import openptv_match, openptv_rig, targets_from_pixels

    rig = openptv_rig(calibration_path, folder, volume, TOLERANCE_PX)
    total, cpu = None, 0.0
    for f in range(len(exp.positions)):
        t = time.process_time()
        made = [targets_from_pixels(exp.detections[f][cam]) for cam in rig.cameras]
        X, rows = openptv_match(rig, [targs for targs, _ in made])
        cpu += time.process_time() - t
        for k, (_, order) in enumerate(made):  # back to the rows of the detections
            used = rows[:, k] >= 0
            rows[used, k] = order[rows[used, k]]
        s = score_frame(X, rows, list(rig.cameras), exp.particle_ids[f], exp.positions[f])
        total = s if total is None else total + s
    return total, cpu


def _warm_up() -> None:
    """Imports on a worker, out of the timing."""
    import scipy.spatial  # noqa: F401

    import ari_sfm.particles.reconstruct  # noqa: F401


def dask_speedup(folder: Path, frames: int) -> None:
    """reconstruct_particles on a LocalCluster of 1 and 2 workers: the cluster's start (processes, imports)
    apart from the run on the started cluster (``scheduler=``: what a long experiment sees)."""
    import dask
    from dask.distributed import Client, LocalCluster

    from ari_sfm.particles.engine import local_worker_environ
    from ari_sfm.particles.reconstruct import MatchOptions, reconstruct_particles

    t, cpu = time.perf_counter(), time.process_time()
    s = reconstruct_particles(folder / "experiment", folder / "truth" / "rig_b.json", Path(tempfile.mkdtemp()),
                              MatchOptions(frames_per_partition=1), workers=0)
    wall, cpu = time.perf_counter() - t, time.process_time() - cpu
    print(f"in process (--workers 0): {s.particles} particles in {frames} frames in {wall:.1f} s wall, "
          f"{s.particles / wall:.0f} particles/s (CPU {cpu:.1f} s: {s.particles / cpu:.0f} per CPU second)")
    walls = {}
    for workers in (1, 2):
        t0 = time.perf_counter()
        with dask.config.set({"distributed.nanny.pre-spawn-environ": local_worker_environ()}), \
                LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                             dashboard_address=None) as cluster, \
                Client(cluster) as client:  # as engine.dask_client starts it
            client.run(_warm_up)
            started = time.perf_counter() - t0
            cpu0 = sum(client.run(time.process_time).values())
            t = time.perf_counter()
            s = reconstruct_particles(folder / "experiment", folder / "truth" / "rig_b.json", Path(tempfile.mkdtemp()),
                                      MatchOptions(frames_per_partition=1), scheduler=cluster.scheduler_address)
            walls[workers] = time.perf_counter() - t
            cpu = sum(client.run(time.process_time).values()) - cpu0
        print(f"dask LocalCluster {workers} worker(s): start {started:.1f} s; {s.particles} particles in {frames} "
              f"frames in {walls[workers]:.1f} s wall, {s.particles / walls[workers]:.0f} particles/s "
              f"(workers' CPU {cpu:.1f} s: {s.particles / cpu:.0f} particles per CPU second)")
    print(f"speed-up 1 -> 2 workers: {walls[1] / walls[2]:.2f}x (2 cores shared with other work: load average "
          f"{os.getloadavg()[0]:.1f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=2000)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-dask", action="store_true")
    ap.add_argument("--skip-compare", action="store_true", help="only the Dask part")
    ap.add_argument("--dask-frames", type=int, default=8, help="frames of the Dask run")
    args = ap.parse_args()
    exp = simulate_particle_experiment(ParticleSimOptions(particles_per_frame=args.particles, num_frames=args.frames,
                                                          seed=args.seed))
    folder = Path(tempfile.mkdtemp())
    write_particle_experiment(exp, folder, render_frames=0)
    volume = Volume(exp.volume_min_mm, exp.volume_max_mm)
    if args.skip_compare:
        args.frames = 0
    match_frame(exp.truth_b, exp.detections[0], TOLERANCE_PX, volume=volume)  # warm-up: imports out of the timing
    n = args.particles * args.frames
    print(f"{args.frames} frames x {args.particles} particles, 4 cameras, 10 mm glass into water, "
          f"0.1 px noise, tolerance {TOLERANCE_PX} px")
    print(f"{'calibration':10s} {'method':8s} {'particles':>9s} {'found':>7s} {'ghosts':>7s} {'3D rms mm':>10s} "
          f"{'particles/s/core':>17s}")
    for label, cal, path in () if args.skip_compare else (("true", exp.truth_b, folder / "truth" / "rig_b.json"),
                             ("drifted", exp.truth_a, folder / "truth" / "rig_a.json")):
        for method, run in (("ari-sfm", lambda cal=cal: ours(exp, cal, volume)),
                            ("OpenPTV", lambda path=path: openptv(exp, path, Path(tempfile.mkdtemp()), volume))):
            s, cpu = run()
            print(f"{label:10s} {method:8s} {s.reconstructed:9d} {s.found_fraction:7.4f} {s.ghost_fraction:7.4f} "
                  f"{s.rms_error_mm:10.4f} {n / cpu:17.0f}")
    if not args.skip_dask:
        exp = simulate_particle_experiment(ParticleSimOptions(particles_per_frame=args.particles,
                                                              num_frames=args.dask_frames, seed=args.seed))
        folder = Path(tempfile.mkdtemp())
        write_particle_experiment(exp, folder, render_frames=0)
        dask_speedup(folder, args.dask_frames)


if __name__ == "__main__":
    main()

"""Cameras behind two walls of a tank: the simulated tanks calibrated, against their truth.

    python benchmarks/bench_windows.py [--seeds 6] [--sigma 0.05]

For each of ``tank_opposite`` (2 + 2 cameras through two opposite walls, like OpenPTV's test_cavity) and
``tank_adjacent`` (through two walls at 90 deg), exact Snell physics, 6 mm glass into water, cameras 12-26 deg
oblique, a 16 mm deep dot body in 5 poses, no stacking and no declared plane: ``calibrate(model="exact")``
from the analytic start, and per seed the residual RMSE (the floor is sigma sqrt 2), each window's normal
error (in its first camera's frame) and distance error with their sigmas, and the largest relative camera
rotation error with its sigma.
"""
from __future__ import annotations

import argparse
import math
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=6)
    parser.add_argument("--sigma", type=float, default=0.05)
    args = parser.parse_args()

    from ari_sfm.calibration.calibrate import calibrate
    from ari_sfm.geometry import angle_between_deg
    from ari_sfm.simulate import make_scene

    print(f"sigma {args.sigma} px: floor {args.sigma * math.sqrt(2):.4f} px")
    print(f"{'scenario':15}{'seed':>5}{'rmse px':>9}{'normal err / sigma (deg)':>34}{'distance err / sigma (mm)':>32}"
          f"{'worst rotation err / sigma (deg)':>34}{'s':>6}")
    for name in ("tank_opposite", "tank_adjacent"):
        for seed in range(args.seeds):
            scene = make_scene(name, seed=seed, sigma_px=args.sigma)
            t0 = time.perf_counter()
            cal = calibrate(scene.dataset, model="exact")
            elapsed = time.perf_counter() - t0
            g, u = scene.geometry, cal.uncertainty
            normals, distances = [], []
            for w in cal.windows:
                truth, first = g.window_of(w.cameras[0]), g.camera(w.cameras[0])
                s = u.windows[w.name]
                normals.append(f"{angle_between_deg(cal.normal_cam(w.cameras[0]), truth.normal_cam(first)):.3f}/"
                               f"{s.normal_deg:.3f}")
                distances.append(f"{w.interface.distance_mm - truth.camera_distance_mm(first):+.2f}/"
                                 f"{s.distance_mm:.2f}")
            worst = (0.0, 0.0)
            for c in g.cameras[1:]:
                rel = cal.cameras[c.name].cam_from_world.R @ c.cam_from_world.R.T
                err = math.degrees(math.acos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
                worst = max(worst, (err, u.cameras[c.name].rotation_deg))
            print(f"{name:15}{seed:>5}{cal.residuals.rmse_px:>9.4f}{'  '.join(normals):>34}{'  '.join(distances):>32}"
                  f"{worst[0]:>24.3f}/{worst[1]:.3f}{elapsed:>10.1f}")


if __name__ == "__main__":
    main()

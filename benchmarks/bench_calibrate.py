"""Time calibrate(model="ari") against cv2.calibrateCamera on the same observations.

    python benchmarks/bench_calibrate.py [--repeats 5] [--scenario paper_single]

Prints, side by side from one run, the median time of cv2.calibrateCamera
(Zhang, no distortion: what a user who ignores the window runs), of our
bundle adjustment alone, and of the whole calibrate() call (analytic
initialisation, which itself runs cv2.calibrateCamera, plus the bundle
adjustment), and their ratios to cv2.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2
import numpy as np

from ari_sfm.calibrate import calibrate
from ari_sfm.init.zhang import object_points
from ari_sfm.simulate import make_scene


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--scenario", default="paper_single")
    ap.add_argument("--models", default="ari,exact")
    args = ap.parse_args()
    scene = make_scene(args.scenario, seed=0)
    ds = scene.dataset
    calib = [o for o in ds.observations if o.set == "calibration"]
    cams = ds.camera_names
    flags = cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST

    def run_cv2() -> None:
        for cam in cams:
            views = [o for o in calib if o.camera == cam]
            cv2.calibrateCamera([object_points(ds.target, v.ids).astype(np.float32) for v in views],
                                [v.pixels.astype(np.float32) for v in views], tuple(ds.cameras[cam].image_size), None, None,
                                flags=flags)

    calibrate(ds, model="ari")  # warm-up (imports, first-call costs)
    t_cv2 = _median_time(run_cv2, args.repeats)
    n_corners = sum(len(o.ids) for o in ds.observations if o.set in ("calibration", "stacking"))
    print(f"scenario {args.scenario}: {len(cams)} camera(s), {len(calib)} calibration images, "
          f"{n_corners} corners incl. stacking; median of {args.repeats} runs")
    print(f"{'what':34s} {'time ms':>9s} {'ratio to cv2':>13s}")
    print(f"{'cv2.calibrateCamera':34s} {t_cv2 * 1e3:9.1f} {1.0:13.2f}")
    for model in args.models.split(","):
        results = []
        t_total = _median_time(lambda: results.append(calibrate(ds, model=model)), args.repeats)
        opt = results[-1].extra["optimizer"]
        t_ba = statistics.median([sum(s["time_s"] for s in r.extra["optimizer"].values()) for r in results])
        iters = "+".join(str(s["iterations"]) for s in opt.values())
        print(f"{model + ' bundle adjustment (' + iters + ' it)':34s} {t_ba * 1e3:9.1f} {t_ba / t_cv2:13.2f}")
        print(f"{model + ' calibrate() total':34s} {t_total * 1e3:9.1f} {t_total / t_cv2:13.2f}")


if __name__ == "__main__":
    main()

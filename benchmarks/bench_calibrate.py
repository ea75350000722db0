"""Time calibrate() against cv2.calibrateCamera on the same observations.

    python benchmarks/bench_calibrate.py                    # the three cases below, ~1 min
    python benchmarks/bench_calibrate.py --case paper_single --repeats 9
    python benchmarks/bench_calibrate.py --backend gtsam    # calibrate(backend=...)

Cases (all simulated with seed 0, sigma 0.05 px):

- ``paper_single`` (issue 3, item 10): one camera, 12 calibration views,
  one stacking pose x 6 plates. calibrate(model="ari"): its bundle adjustment
  alone and the whole call, against cv2.calibrateCamera. Target: <= 1.0x.
- ``binocular`` (issue 4, item 10): the paper-like binocular rig; the whole
  calibrate(model="exact") against the whole calibrate(model="ari").
  Target: exact <= 2.5x ari.
- ``4x100`` (issue 4, item 10): scale16 with 4 cameras x 100 frames (partial
  visibility); one joint calibrate() against four cv2.calibrateCamera calls
  (one per camera, on its calibration views). Target: <= 1.5x.

The cv2 baseline is what a user who ignores the window runs: Zhang with
OpenCV's default criteria, no distortion (k1 k2 k3 fixed, zero tangential),
on the calibration views only (it has no use for the stacking records).
"calibrate() total" is the whole call: analytic initialisation (which itself
runs cv2.calibrateCamera per camera), the bundle adjustment stage(s), outlier
report, residuals and uncertainties. "BA" is the sum of the stages' solver
time (optimizer.runs[stage].time_s); "it" its accepted steps and "ev"
its nonlinear error evaluations, per stage. cv2 and the calibrate() calls
are interleaved within each repeat, so that load on the machine hits them
alike; the table gives medians and the ratios of the medians.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2
import numpy as np

from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.init.zhang import object_points
from ari_sfm.simulate import ScenarioOverrides, make_scene

CASES = {  # name: (scenario, overrides, what the issues ask)
    "paper_single": ("paper_single", {}, "issue 3: ari BA and ari total <= 1.0x cv2"),
    "binocular": ("binocular", {}, "issue 4: exact total <= 2.5x ari total"),
    "4x100": ("scale16", {"num_cameras": 4, "num_frames": 100},
              "issue 4: joint calibration <= 1.5x four cv2.calibrateCamera calls"),
}
CV2_FLAGS = cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST


def cv2_baseline(dataset, sets: tuple[str, ...] = ("calibration",)):
    """A function running cv2.calibrateCamera once per camera on its views of ``sets`` (default: the
    calibration views, what a user who ignores the window runs)."""
    calib = [o for o in dataset.observations if o.set in sets]
    per_camera = []
    for cam in dataset.camera_names:
        views = [o for o in calib if o.camera == cam]
        per_camera.append(([object_points(dataset.target, v.ids).astype(np.float32) for v in views],
                           [v.pixels.astype(np.float32) for v in views], tuple(dataset.cameras[cam].image_size)))

    def run() -> None:
        for obj, img, size in per_camera:
            cv2.calibrateCamera(obj, img, size, None, None, flags=CV2_FLAGS)

    return run


def time_case(dataset, models=("ari", "exact"), repeats: int = 5, backends=("auto",)) -> dict:
    """Medians over ``repeats`` interleaved runs: cv2 (all cameras), and per (model, backend) the
    calibrate() total, the BA time, the iterations per stage; one warm-up call of each first."""
    run_cv2 = cv2_baseline(dataset)
    keys = [(m, b) for m in models for b in backends]
    for m, b in keys:  # warm-up: imports, first-call costs
        calibrate(dataset, model=m, backend=b)
    run_cv2()
    t_cv2, totals, bas, its = [], {k: [] for k in keys}, {k: [] for k in keys}, {}
    for _ in range(repeats):
        t = time.perf_counter()
        run_cv2()
        t_cv2.append(time.perf_counter() - t)
        for k in keys:
            t = time.perf_counter()
            cal = calibrate(dataset, model=k[0], backend=k[1])
            totals[k].append(time.perf_counter() - t)
            bas[k].append(sum(s["time_s"] for s in cal.optimizer.to_json().values()))
            its[k] = "+".join(str(s["iterations"]) for s in cal.optimizer.to_json().values())
            if all("error_evaluations" in s for s in cal.optimizer.to_json().values()):  # numpy backend
                its[k] += " it, " + "+".join(str(s["error_evaluations"])
                                             for s in cal.optimizer.to_json().values()) + " ev"
            else:
                its[k] += " it"
    med = statistics.median
    return {"cv2": med(t_cv2), "total": {k: med(v) for k, v in totals.items()},
            "ba": {k: med(v) for k, v in bas.items()}, "iterations": its}


def print_case(name: str, dataset, result: dict, repeats: int, note: str = "") -> None:
    cams = dataset.camera_names
    calib = [o for o in dataset.observations if o.set == "calibration"]
    corners = sum(len(o.ids) for o in dataset.observations if o.set in ("calibration", "stacking"))
    print(f"\n{name}: {len(cams)} camera(s), {len(calib)} calibration images, {corners} corners incl. stacking; "
          f"median of {repeats} interleaved runs" + (f"  [{note}]" if note else ""))
    print(f"{'what':42s} {'time ms':>9s} {'ratio to cv2':>13s}")
    t_cv2 = result["cv2"]
    print(f"{f'cv2.calibrateCamera x {len(cams)}':42s} {t_cv2 * 1e3:9.1f} {1.0:13.2f}")
    multi_backend = len({b for _, b in result["total"]}) > 1
    for (model, backend), total in result["total"].items():
        tag = f"{model}, {backend}" if multi_backend else model
        ba = result["ba"][(model, backend)]
        it = result["iterations"][(model, backend)]
        print(f"{f'{tag} bundle adjustment ({it})':42s} {ba * 1e3:9.1f} {ba / t_cv2:13.2f}")
        print(f"{f'{tag} calibrate() total':42s} {total * 1e3:9.1f} {total / t_cv2:13.2f}")
    backends = sorted({b for _, b in result["total"]})
    for backend in backends:
        ari, exact = result["total"].get(("ari", backend)), result["total"].get(("exact", backend))
        if ari and exact:
            tag = f" ({backend})" if multi_backend else ""
            print(f"{'exact total / ari total' + tag:42s} {'':9s} {exact / ari:13.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", action="append", choices=sorted(CASES), help="a case to run (repeatable; default all)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--models", default="ari,exact")
    ap.add_argument("--backend", action="append", choices=("auto", "numpy", "gtsam"),
                    help="calibrate(backend=...) (repeatable; default auto)")
    args = ap.parse_args()
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.2f}")
    for name in args.case or list(CASES):
        scenario, overrides, note = CASES[name]
        dataset = make_scene(scenario, seed=0, overrides=ScenarioOverrides(**overrides)).dataset
        result = time_case(dataset, tuple(args.models.split(",")), args.repeats, tuple(args.backend or ["auto"]))
        print_case(name, dataset, result, args.repeats, note)
    print(f"\nload average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()

"""The two bundle-adjustment backends side by side: GTSAM CustomFactors vs the vectorised numpy solver.

    python benchmarks/bench_backends.py                 # default run, ~10 min on 2 cores
    python benchmarks/bench_backends.py --quick         # paper_single, binocular, 4 x 100 and the cv2 ratio
    python benchmarks/bench_backends.py --gtsam-max-corners 400000   # GTSAM on the full 16 x 500 rig too

Workload of every case: the exact model (the stage every ``calibrate(model=
"exact")`` ends with) with Huber 1 px (calibrate's default), built by
RigGraph.build from the analytic initialisation (ari_sfm.init.rig, window
distance 10 mm in front of the nearest camera), then Levenberg-Marquardt with
RigGraph.optimize's tolerances. Both backends take the same LM path (same
iterations; the numpy side with stop="gtsam", i.e. GTSAM's trials at
convergence too, not calibrate's default stop="converged"), so ms/iteration
compares like with like. Scenes: paper_single,
binocular, and the scale16 grid (2-16 cameras, 50-1000 frames, each frame
seen by >= 2 cameras, 88 corners per view, one stacking pose x 6 plates).

Each (case, backend) runs in a fresh subprocess (scene and initialisation
are made once per case and pickled): "peak MB" is the rise of the peak
resident set (VmHWM reset through /proc/self/clear_refs) from just before
RigGraph.build to the end of the optimisation. "numpy" includes packing
the graph's problem (VectorizedProblem.from_rig_graph with its check).

The growth exponent is the slope of log(ms/iteration) against log(corners)
over the scaling cases. The last table times calibrate() on paper_single
(whole call: analytic initialisation, which itself runs cv2.calibrateCamera,
both stages, outlier report, uncertainty) and its bundle adjustment alone
with each backend against cv2.calibrateCamera on the calibration views (no
distortion): bench_calibrate.py's table, which also has the binocular and
4 x 100 cases of issue 4.
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

FRAMES_SERIES = (50, 100, 200, 500, 1000)  # scale16 with 2 cameras
CAMERAS_SERIES = (2, 4, 8, 16)  # scale16 with 200 frames


# --------------------------------------------------------------------------- worker side


def _initial_state(dataset):
    from ari_sfm.factors.rig_graph import RigState, default_distance_mm
    from ari_sfm.init.rig import initialise_rig

    rig = initialise_rig(dataset, False)
    distance = dataset.interface.distance_mm
    if distance is None:
        distance = default_distance_mm(rig.normal_world, rig.cam_from_world)
    return RigState.from_initialisation(rig, distance)


def prepare(case: dict, path: str) -> dict:
    """Make the scene and its initial state, pickle them; return the timings."""
    from ari_sfm.simulate import ScenarioOverrides, make_scene

    t0 = time.perf_counter()
    dataset = make_scene(case["scenario"], seed=0, overrides=ScenarioOverrides(**case["overrides"])).dataset
    t1 = time.perf_counter()
    state = _initial_state(dataset)
    t2 = time.perf_counter()
    with open(path, "wb") as f:
        pickle.dump((dataset, state), f)
    return {"scene_s": t1 - t0, "init_s": t2 - t1}


def _peak_reset() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _rss_kb() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024


def measure(path: str, backend: str, model: str, huber_px: float | None, max_iterations: int) -> dict:
    """Build the graph and optimise it with one backend; timings, iterations, error, peak memory."""
    import gc

    from ari_sfm.factors.rig_graph import RigGraph
    from ari_sfm.factors.vectorized import solve_vectorized

    with open(path, "rb") as f:
        dataset, state = pickle.load(f)
    gc.collect()
    reset = _peak_reset()
    rss0 = _rss_kb()
    t0 = time.perf_counter()
    rg = RigGraph.build(dataset.observations, dataset.target, dataset.interface, dataset.camera_names, state,
                        model=model, estimate_distance=dataset.interface.medium_index != 1.0, huber_px=huber_px)
    t1 = time.perf_counter()
    if backend == "gtsam":
        rg.optimize(max_iterations)
    else:
        report = solve_vectorized(rg, max_iterations, huber_px=huber_px,
                                  stop="gtsam").report  # GTSAM's trials too: like for like per iteration
    t2 = time.perf_counter()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    error = rg.graph.error(rg.values) if backend == "gtsam" else report.error  # equal: tests/test_vectorized.py
    return {
        "cameras": len(dataset.camera_names), "views": len(rg.factor_data),
        "corners": int(sum(len(d.points_target) for d, _ in rg.factor_data)),
        "build_s": t1 - t0, "opt_s": t2 - t1, "iterations": rg.iterations, "error": float(error),
        "peak_mb": (peak - rss0) / 1024 if reset else float("nan"),
    }


def worker(argv: list[str]) -> None:
    kind, spec = argv[0], json.loads(argv[1])
    out = prepare(spec["case"], spec["path"]) if kind == "prepare" else measure(
        spec["path"], spec["backend"], spec["model"], spec["huber_px"], spec["max_iterations"])
    print("RESULT " + json.dumps(out))


# --------------------------------------------------------------------------- driver side


def _run(kind: str, spec: dict, timeout_s: float) -> dict | None:
    cmd = [sys.executable, __file__, "--worker", kind, json.dumps(spec)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=os.environ.copy())
    except subprocess.TimeoutExpired:
        print(f"  ({kind} {spec.get('backend', '')} timed out after {timeout_s:.0f} s)", flush=True)
        return None
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    print(f"  ({kind} failed: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode})",
          flush=True)
    return None


def run_case(label: str, case: dict, backends: list[str], args, tmp: Path) -> dict:
    path = str(tmp / f"{label.replace(' ', '_')}.pkl")
    prep = _run("prepare", {"case": case, "path": path}, args.timeout)
    row = {"label": label, "prep": prep}
    if prep is None:
        return row
    for backend in backends:
        row[backend] = _run("measure", {"path": path, "backend": backend, "model": "exact", "huber_px": 1.0,
                                        "max_iterations": case.get("max_iterations", args.max_iterations)},
                            args.timeout)
    os.unlink(path)
    _print_row(row)
    return row


HEADER = (f"{'case':22s} {'cams':>4s} {'views':>6s} {'corners':>8s} {'build s':>7s} | "
          f"{'gtsam it':>8s} {'total s':>8s} {'ms/it':>8s} {'peak MB':>8s} | "
          f"{'numpy it':>8s} {'total s':>8s} {'ms/it':>8s} {'peak MB':>8s} | {'speed-up':>8s} {'cost diff':>9s}")


def _cols(r: dict | None) -> str:
    if not r:
        return f"{'-':>8s} {'-':>8s} {'-':>8s} {'-':>8s}"
    it = r["iterations"]
    return f"{it:8d} {r['opt_s']:8.2f} {1e3 * r['opt_s'] / max(it, 1):8.1f} {r['peak_mb']:8.0f}"


def _print_row(row: dict) -> None:
    g, n = row.get("gtsam"), row.get("numpy")
    any_r = n or g
    if not any_r:
        print(f"{row['label']:22s} (failed)", flush=True)
        return
    speed = f"{g['opt_s'] / n['opt_s']:8.1f}" if g and n else f"{'-':>8s}"
    speed += f" {abs(g['error'] - n['error']) / g['error']:9.1e}" if g and n else f" {'-':>9s}"
    print(f"{row['label']:22s} {any_r['cameras']:4d} {any_r['views']:6d} {any_r['corners']:8d} {any_r['build_s']:7.2f} "
          f"| {_cols(g)} | {_cols(n)} | {speed}", flush=True)


def growth_exponent(rows: list[dict], backend: str) -> float | None:
    pts = [(r[backend]["corners"], r[backend]["opt_s"] / max(r[backend]["iterations"], 1))
           for r in rows if r.get(backend)]
    if len(pts) < 3:
        return None
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def cv2_table(repeats: int) -> None:
    """calibrate() on paper_single with each backend against cv2.calibrateCamera (bench_calibrate's table)."""
    from bench_calibrate import print_case, time_case  # benchmarks/ is on sys.path when run as a script

    from ari_sfm.simulate import make_scene

    ds = make_scene("paper_single", seed=0).dataset
    print_case("paper_single, calibrate() per backend", ds,
               time_case(ds, ("ari", "exact"), repeats, ("gtsam", "numpy")),
               repeats)


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        worker(sys.argv[2:])
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the three fixed cases and the cv2 table only")
    ap.add_argument("--gtsam-max-corners", type=int, default=200_000,
                    help="run the GTSAM backend only on cases with at most this many corners (default 200000)")
    ap.add_argument("--max-iterations", type=int, default=100, help="LM iteration cap of the fixed cases")
    ap.add_argument("--scaling-max-iterations", type=int, default=10, help="LM iteration cap of the scaling cases")
    ap.add_argument("--repeats", type=int, default=5, help="repeats of the cv2 / calibrate() timings")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per subprocess")
    args = ap.parse_args()

    import gtsam

    t_start = time.perf_counter()
    print(f"numpy {np.__version__}, gtsam {getattr(gtsam, '__version__', '4.3')}, OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS')}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    print("workload: exact model, Huber 1 px, from the analytic initialisation; same LM path on both backends\n")
    fixed = [("paper_single", {"scenario": "paper_single", "overrides": {}}),
             ("binocular", {"scenario": "binocular", "overrides": {}}),
             ("4 cams x 100 frames", {"scenario": "scale16", "overrides": {"num_cameras": 4, "num_frames": 100}})]
    frames = [(f"2 cams x {f} frames", {"scenario": "scale16", "overrides": {"num_cameras": 2, "num_frames": f}})
              for f in FRAMES_SERIES]
    cams = [(f"{c} cams x 200 frames", {"scenario": "scale16", "overrides": {"num_cameras": c, "num_frames": 200}})
            for c in CAMERAS_SERIES if c != 2]
    full = [("16 cams x 500 frames", {"scenario": "scale16", "overrides": {}})]
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        print(HEADER)
        for label, case in fixed:
            run_case(label, case, ["gtsam", "numpy"], args, tmp)
        if not args.quick:
            print(f"\nscaling (LM capped at {args.scaling_max_iterations} iterations; GTSAM up to "
                  f"{args.gtsam_max_corners} corners)")
            print(HEADER)
            est = {"2 cams": 2, "4 cams": 4, "8 cams": 8, "16 cams": 16}
            rows_frames, rows_cams = [], []
            for group, out in ((frames, rows_frames), (cams, rows_cams), (full, [])):
                for label, case in group:
                    case = dict(case, max_iterations=args.scaling_max_iterations)
                    n_cams = est[label.split(" x ")[0]]
                    n_frames = case["overrides"].get("num_frames", 500)
                    guess = 88 * (n_frames * min(n_cams, 6) + 6 * n_cams)  # a rough upper bound of the corners
                    backends = ["gtsam", "numpy"] if guess <= args.gtsam_max_corners else ["numpy"]
                    out.append(run_case(label, case, backends, args, tmp))
            rows_cams = [r for r in rows_frames if r["label"] == "2 cams x 200 frames"] + rows_cams
            print("\ngrowth exponent p of ms/iteration ~ corners^p")
            for name, rows in (("2 cameras, 50-1000 frames", rows_frames), ("2-16 cameras, 200 frames", rows_cams),
                               ("all scaling cases", rows_frames + rows_cams[1:])):
                g, n = growth_exponent(rows, "gtsam"), growth_exponent(rows, "numpy")
                fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
                print(f"  {name:28s} gtsam {fmt(g):>5s}   numpy {fmt(n):>5s}")
    cv2_table(args.repeats)
    print(f"\nbenchmark wall time {time.perf_counter() - t_start:.0f} s, load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()

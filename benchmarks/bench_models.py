"""The paper's Tables 2-4 on simulated data: every model on the same observations, times as ratios to ari.

    python benchmarks/bench_models.py [--repeats 3] [--models ari,exact,rt,pf,pinhole,pinhole_dist]

Three cases, each one run of :func:`ari_sfm.compare.compare` per repeat (the
median time is reported): the single camera (``paper_single``, Table 2), the
binocular rig (``binocular``, Table 3) and the limited-data experiment
(``binocular`` rotary-stage-like boards, fit on the central 3x4 corners,
judged on all: Table 4). Errors in px (in-sample and on all calibration
corners), T = the calibration itself in ms (pf: its polynomial fit; its world
is the ari fit's), next to the paper's figures where it gives them.
"""
from __future__ import annotations

import argparse
import os
import statistics

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ari_sfm.calibration.compare import PAPER, Subset, compare, parse_models  # noqa: E402
from ari_sfm.simulate import ScenarioOverrides, make_scene  # noqa: E402

CASES = (
    ("single", "paper_single", {}, None),
    ("binocular", "binocular", {}, None),
    ("subset", "binocular", {"num_frames": 8, "depth_band_mm": 20.0, "lateral_scale": 0.2}, Subset(3, 4)),
)


def run_case(label: str, scenario: str, overrides: dict, subset: Subset | None, models: tuple[str, ...],
             repeats: int) -> None:
    scene = make_scene(scenario, seed=0, overrides=ScenarioOverrides(**overrides))
    runs = [compare(scene.dataset, models, subset) for _ in range(repeats)]
    times = {m: statistics.median(r.time_ms for run in runs for r in run if r.model == m) for m in models}
    first = {r.model: r for r in runs[0]}
    ref = times.get("ari")
    n = sum(len(o.ids) for o in scene.dataset.select("calibration"))
    print(f"\n{label}: {scenario} {overrides or ''} {len(scene.dataset.camera_names)} camera(s), {n} calibration "
          f"corners{f', fit on the central {subset.cols}x{subset.rows}' if subset else ''}; median of {repeats}")
    print(f"{'model':13s} {'para':>4s} {'fit rmse':>9s} {'all mae':>8s} {'all max':>8s} {'all rmse':>9s} "
          f"{'T ms':>8s} {'T/ari':>6s}   paper (mae max rmse T)")
    for m in models:
        r = first[m]
        paper = PAPER[label].get(m)
        ratio = f"{times[m] / ref:6.2f}" if ref else "     -"
        print(f"{m:13s} {r.params_per_camera:4d} {r.fit['rmse_px']:9.3f} {r.all['mae_px']:8.3f} {r.all['max_px']:8.3f} "
              f"{r.all['rmse_px']:9.3f} {times[m]:8.1f} {ratio}   "
              + ("" if paper is None else f"{paper[0]:.2f} {paper[1]:.2f} {paper[2]:.2f} {paper[3]:.0f}"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--models", default="ari,exact,rt,pf,pinhole,pinhole_dist")
    args = ap.parse_args()
    models = parse_models(args.models)
    compare(make_scene("paper_single", seed=0).dataset, models)  # warm-up: imports, first-call costs
    for case in CASES:
        run_case(*case, models, args.repeats)


if __name__ == "__main__":
    main()

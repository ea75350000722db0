"""Triangulation throughput through the window against cv2.triangulatePoints.

    python benchmarks/bench_triangulate.py [--points 20000] [--repeats 5] [--noise-px 0.5]

Pixels: random world points in the volume of the simulated calibration
boards, projected with exact Snell physics (the truth of ``binocular`` seed 0
for 2 cameras; of ``arc4`` seed 0, written as truth.json and read back with
``load_calibration``, for 4 cameras, NaN where a camera does not see a point;
kept if seen by >= 2 cameras). Each method triangulates the same pixels with
the true calibration: ``exact`` (Snell), ``ari`` (the paper's paraxial model
with the same parameters), linear (rays only) and refined (Levenberg-Marquardt
on the reprojection error); cv2.triangulatePoints (DLT, pinhole P = K [R | t],
i.e. ignoring the window) is the reference, on the same points' pixels: it
takes two cameras, so with 4 cameras each point comes from the first two
cameras that see it (one call per camera pair, the pairs grouped outside the
timing: cv2 does less than we do, which uses every camera). ``--noise-px``
adds Gaussian noise to the pixels (the Levenberg-Marquardt then iterates).
Printed side by side from one run: median time, points per second, time ratio
to cv2 on the same points and the RMS 3D error against the true points.
"""
from __future__ import annotations

import argparse
import functools
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2
import numpy as np

from ari_sfm.calibration.record import Calibration
from ari_sfm.io import load_calibration, parse_calibration, write_json_atomic
from ari_sfm.reconstruction.triangulate import triangulate_pixels
from ari_sfm.simulate import make_scene


def _median_time(fn, repeats: int) -> tuple[float, object]:
    out, times = None, []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def _points_and_pixels(cal: Calibration, n: int, seed: int = 0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """n world points in the boards' volume seen by >= 2 cameras, and their pixels (NaN where unseen)."""
    rng = np.random.default_rng(seed)
    centres = np.array([p.t for p in cal.frames.values()])
    lo, hi = centres.min(axis=0) - 30.0, centres.max(axis=0) + 30.0
    X_all, tracks_all = [], {c: [] for c in cal.cameras}
    count = 0
    while count < n:
        X = rng.uniform(lo, hi, size=(4 * n, 3))
        tracks = {}
        for c, cam in cal.cameras.items():
            with np.errstate(invalid="ignore"):
                uv = cal.project_world(c, X)
            w, h = cam.image_size
            inside = (np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0)
                      & (uv[:, 1] <= h - 1))
            uv[~inside] = np.nan
            tracks[c] = uv
        keep = sum(np.isfinite(t[:, 0]) for t in tracks.values()) >= 2
        X_all.append(X[keep])
        for c in cal.cameras:
            tracks_all[c].append(tracks[c][keep])
        count += int(keep.sum())
    X = np.concatenate(X_all)[:n]
    return X, {c: np.concatenate(v)[:n] for c, v in tracks_all.items()}


def cv2_pairs(cal: Calibration, tracks: dict[str, np.ndarray]
              ) -> tuple[Callable[[], list], Callable[[list], np.ndarray]]:
    """cv2.triangulatePoints (DLT, pinhole P = K [R | t]: the window ignored) on the same points: each point
    from the first two cameras that see it, one call per camera pair on that pair's pixels (grouped here,
    outside the timing). Returns the timed call and the assembly of its outputs into (P, 3) points."""
    names = list(tracks)
    uv = np.stack([tracks[c] for c in names], axis=1)
    seen = np.isfinite(uv).all(axis=2)
    order = np.argsort(~seen, axis=1, kind="stable")  # the cameras that see a point first
    proj = [cal.cameras[c].K @ np.hstack([cal.cameras[c].cam_from_world.R, cal.cameras[c].cam_from_world.t[:, None]])
            for c in names]
    groups = []
    for a, b in sorted({(int(i), int(j)) for i, j in order[:, :2]}):
        rows = np.flatnonzero((order[:, 0] == a) & (order[:, 1] == b) & (seen.sum(axis=1) >= 2))
        if len(rows):
            groups.append((rows, proj[a], proj[b], uv[rows, a].T.copy(), uv[rows, b].T.copy()))

    def run() -> list:
        return [cv2.triangulatePoints(Pa, Pb, ua, ub) for _, Pa, Pb, ua, ub in groups]

    def points(outs: list) -> np.ndarray:
        X = np.full((len(uv), 3), np.nan)
        for (rows, *_), Xh in zip(groups, outs):
            X[rows] = (Xh[:3] / Xh[3]).T
        return X

    return run, points


def _rms(Y: np.ndarray, X: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(np.sum((Y - X) ** 2, axis=1))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--noise-px", type=float, default=0.0, help="Gaussian pixel noise added to every track")
    args = ap.parse_args()

    binocular = parse_calibration(make_scene("binocular", seed=0, sigma_px=0.0).truth)
    with tempfile.TemporaryDirectory() as tmp:  # arc4's truth through the file a user would hold
        path = Path(tmp) / "truth.json"
        write_json_atomic(path, make_scene("arc4", seed=0, sigma_px=0.0).truth)
        arc4 = load_calibration(path)

    rows = []
    for _label, cal, (X, tracks) in (("2 cameras", binocular, _points_and_pixels(binocular, args.points)),
                                    ("4 cameras", arc4, _points_and_pixels(arc4, args.points))):
        if args.noise_px:
            rng = np.random.default_rng(1)
            tracks = {k: v + rng.normal(0.0, args.noise_px, v.shape) for k, v in tracks.items()}
        run_cv2, cv2_points = cv2_pairs(cal, tracks)
        t_cv2, outs = _median_time(run_cv2, args.repeats)
        rows.append(("cv2.triangulatePoints (pinhole)", len(cal.cameras), len(X), t_cv2, t_cv2,
                     _rms(cv2_points(outs), X)))
        for model in ("exact", "ari"):
            c = replace(cal, model=model)
            triangulate_pixels(c, {k: v[:10] for k, v in tracks.items()})  # warm-up
            for refine in (False, True):
                t, out = _median_time(functools.partial(triangulate_pixels, c, tracks, refine=refine), args.repeats)
                what = f"{model} {'rays + LM' if refine else 'rays only'}"
                rows.append((what, len(cal.cameras), len(X), t, t_cv2, _rms(out[0], X)))

    print(f"triangulation of the same exact-physics pixels (noise {args.noise_px} px), median of {args.repeats} runs, "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")
    print(f"{'method':32s} {'cams':>4s} {'points':>7s} {'time ms':>9s} {'points/s':>11s} {'time / cv2':>10s} "
          f"{'RMS err mm':>11s}")
    for what, cams, n, t, t_cv2, err in rows:
        print(f"{what:32s} {cams:4d} {n:7d} {t * 1e3:9.2f} {n / t:11.0f} {t / t_cv2:10.2f} {err:11.2e}")
    print("time / cv2: relative to cv2.triangulatePoints on the same points' pixels (4 cameras: each point from "
          "the first two cameras that see it, one call per camera pair)")


if __name__ == "__main__":
    main()

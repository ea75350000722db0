"""Corner detector accuracy and speed on rendered boards, every variant on the same images.

    python benchmarks/bench_detection.py [--views 16] [--size 1224 1024] [--supersample 4]
                                         [--noise 1.0] [--tune] [--dots-scenario SCALE]

Renders random pinhole views of an 11 x 8 corner checkerboard, a 12 x 9
square ChArUco board and two dot boards (9 x 7 symmetric, 5 x 11 asymmetric;
ari_sfm.simulate.render), runs each detector variant and compares its corners
(dot centres) with the exact projections of the board points.
Prints, per variant: images found, RMS and max error (px), ms per image, and
the ratios to the chosen variant (``subpix``, ``charuco``, ``centroid_debiased``).
For dot boards it also prints the perspective bias of the views: the centre of
each imaged dot (area centroid of its exactly projected outline) minus the
projection of the dot's centre, and the same bias in the ``paper_single_dots``
scenario (exact Snell projection of each dot's outline, full size).
``--dots-scenario SCALE`` also renders that scenario at image scale SCALE
(through the window) and scores the dot detectors against its exact centres.
``--tune`` also sweeps the cornerSubPix window fraction and pre-smoothing.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from ari_sfm import circle_grid, detection
from ari_sfm.detection import CHECKERBOARD_METHODS, detect_corners
from ari_sfm.geometry import rotation_from_rotvec
from ari_sfm.records import Target
from ari_sfm.simulate.render import plane_pixel_to_target, project_pinhole, render_target

CHECKERBOARD = Target(type="checkerboard", square_mm=10.0, inner_corners=(11, 8))
CHARUCO = Target(type="charuco", square_mm=10.0, squares=(12, 9), marker_mm=7.5, dictionary="DICT_5X5_100")
DOTS = (Target(type="circles", circle_grid=(9, 7), spacing_mm=10.0, layout="symmetric", diameter_mm=5.0),
        Target(type="circles", circle_grid=(5, 11), spacing_mm=10.0, layout="asymmetric", diameter_mm=6.0))


@dataclass(frozen=True)
class View:
    image: np.ndarray
    exact: np.ndarray  # (N, 2) exact pixels of every target id
    square_px: float  # median square size (dot spacing) in the image
    bias: np.ndarray | None = None  # dot boards: imaged dot centre - projected dot centre (N, 2), exact


def render_views(target: Target, count: int, size: tuple[int, int], supersample: int,
                 noise: float, seed: int) -> list[View]:
    """Random views: roll 0..360 deg, tilt up to 50 deg, square size ~15-50 px, half with optical blur."""
    rng = np.random.default_rng(seed)
    width, height = size
    f = 1.25 * width
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    ids, xyz = target.points_3d()
    centre = xyz.mean(axis=0)
    views = []
    while len(views) < count:
        roll = rng.uniform(0, 2 * np.pi)
        tilt = np.deg2rad(rng.uniform(-50, 50, 2))
        square_px = rng.uniform(15, 50)
        dist = f * target.pitch_mm / square_px
        R = rotation_from_rotvec(np.array([tilt[0], tilt[1], 0])) @ rotation_from_rotvec(np.array([0, 0, roll]))
        t = np.array([*rng.uniform(-0.1, 0.1, 2) * dist, dist]) - R @ centre
        exact = project_pinhole(K, R, t, xyz)
        margin = 2.5 * square_px
        if exact.min() < margin or (exact[:, 0].max() > width - margin) or (exact[:, 1].max() > height - margin):
            continue  # keep the whole board with its margin inside the image
        blur = 0.0 if len(views) % 2 == 0 else 0.7
        image = render_target(target, plane_pixel_to_target(K, R, t), size, supersample=supersample,
                              noise_sigma=noise, seed=len(views), blur_sigma_px=blur)
        bias = perspective_bias(target, K, R, t, exact) if target.type == "circles" else None
        views.append(View(image, exact, square_px, bias))
    return views


def perspective_bias(target: Target, K: np.ndarray, R: np.ndarray, t: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """Area centroid of each dot's exactly projected outline (720 points) minus its projected centre."""
    _, xyz = target.points_3d()
    a = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    ring = 0.5 * target.diameter_mm * np.stack([np.cos(a), np.sin(a), 0 * a], axis=1)
    out = np.empty((len(xyz), 2))
    for k, X in enumerate(xyz):
        x, y = project_pinhole(K, R, t, X + ring).T
        xn, yn = np.roll(x, -1), np.roll(y, -1)
        cross = x * yn - xn * y
        out[k] = np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (3.0 * cross.sum()) - exact[k]
    return out


@dataclass(frozen=True)
class Score:
    found: int
    wrong: int  # detections with an error > 2 px (a wrong grid or wrong ids)
    rms: float
    max: float
    ms: float


def score(views: list[View], target: Target, method: str) -> Score:
    """Errors against the exact points; a dot grid that looks the same turned (symmetric layouts) is
    scored under the turned ids that fit best (the detector's rule picks one of them)."""
    turns = [np.arange(target.num_ids())]
    if target.type == "circles":
        turns = [p for p, det in circle_grid.circle_symmetries(target) if det > 0]
    errors, wrong, found, elapsed = [], 0, 0, 0.0
    for view in views:
        t0 = time.perf_counter()
        result = detect_corners(view.image, target, method=method)
        elapsed += time.perf_counter() - t0
        if result is None:
            continue
        found += 1
        ids, pixels = result
        err = min((np.linalg.norm(pixels - view.exact[p[ids]], axis=1) for p in turns), key=lambda e: e.max())
        if err.max() > 2.0:
            wrong += 1
            continue
        errors.append(err)
    e = np.concatenate(errors) if errors else np.array([np.nan])
    return Score(found, wrong, float(np.sqrt(np.mean(e**2))), float(e.max()), 1000 * elapsed / len(views))


def print_table(title: str, scores: dict[str, Score], chosen: str, count: int) -> None:
    ref = scores[chosen]
    print(f"\n{title}")
    print(f"{'variant':26s} {'found':>7s} {'wrong':>5s} {'rms px':>8s} {'max px':>8s} {'ms/img':>8s} {'rms/ref':>8s} "
          f"{'max/ref':>8s} {'time/ref':>8s}")
    for name, s in scores.items():
        mark = " <- chosen" if name == chosen else ""
        print(f"{name:26s} {s.found:>3d}/{count:<3d} {s.wrong:>5d} {s.rms:8.4f} {s.max:8.4f} {s.ms:8.1f} "
              f"{s.rms / ref.rms:8.2f} {s.max / ref.max:8.2f} {s.ms / ref.ms:8.2f}{mark}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--size", type=int, nargs=2, default=(1224, 1024))
    parser.add_argument("--supersample", type=int, default=4,
                        help="renderer samples per pixel side (8+ isolates the detector)")
    parser.add_argument("--noise", type=float, default=1.0, help="sensor noise sigma, grey levels")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--tune", action="store_true", help="also sweep the cornerSubPix window and smoothing")
    parser.add_argument("--dots-scenario", type=float, default=0.0, metavar="SCALE",
                        help="also render paper_single_dots at this image scale and score the dot detectors on it")
    args = parser.parse_args()
    size = tuple(args.size)

    print(f"{args.views} views {size[0]} x {size[1]}, supersample {args.supersample}, noise {args.noise} grey levels "
          f"(contrast 215), half the views blurred 0.7 px")
    views = render_views(CHECKERBOARD, args.views, size, args.supersample, args.noise, args.seed)
    print(f"square size {min(v.square_px for v in views):.0f}-{max(v.square_px for v in views):.0f} px")
    scores = {name: score(views, CHECKERBOARD, name) for name in CHECKERBOARD_METHODS}
    print_table(f"checkerboard {CHECKERBOARD.inner_corners[0]} x {CHECKERBOARD.inner_corners[1]} corners", scores,
                "subpix", len(views))

    if args.tune:
        tuned = {}
        base = (detection.SUBPIX_WINDOW_FRACTION, detection.SUBPIX_SMOOTHING_PX)
        for fraction in (0.25, 0.35, 0.45, 0.55, 0.65):
            for smoothing in (0.0, 0.7, 1.0, 1.5, 2.0):
                detection.SUBPIX_WINDOW_FRACTION, detection.SUBPIX_SMOOTHING_PX = fraction, smoothing
                tuned[f"subpix w={fraction} s={smoothing}"] = score(views, CHECKERBOARD, "subpix")
        detection.SUBPIX_WINDOW_FRACTION, detection.SUBPIX_SMOOTHING_PX = base
        tuned["subpix"] = scores["subpix"]
        print_table("cornerSubPix window fraction (w) and pre-smoothing sigma (s)", tuned, "subpix", len(views))

    views = render_views(CHARUCO, max(4, args.views // 2), size, args.supersample, args.noise, args.seed + 1)
    charuco = {"charuco": score(views, CHARUCO, "charuco"),
               "charuco_raw (OpenCV only)": score(views, CHARUCO, "charuco_raw")}
    print_table(f"ChArUco {CHARUCO.squares[0]} x {CHARUCO.squares[1]} squares {CHARUCO.dictionary}", charuco, "charuco",
                len(views))

    for k, dots in enumerate(DOTS):
        views = render_views(dots, args.views, size, args.supersample, args.noise, args.seed + 2 + k)
        scores = {name: score(views, dots, name) for name in circle_grid.CIRCLE_METHODS}
        cols, rows = dots.circle_grid
        print_table(f"dot board {cols} x {rows} {dots.layout}, {dots.diameter_mm:g} mm dots at {dots.spacing_mm:g} mm "
                    f"(spacing {min(v.square_px for v in views):.0f}-{max(v.square_px for v in views):.0f} px)",
                    scores, circle_grid.CIRCLE_DEFAULT_METHOD, len(views))
        bias = np.linalg.norm(np.concatenate([v.bias for v in views]), axis=1)
        print("perspective bias of these views (imaged dot centre - projected centre): "
              f"rms {np.sqrt(np.mean(bias**2)):.4f} px, max {bias.max():.4f} px")
    bias = scenario_bias()
    print("\nperspective bias in paper_single_dots seed 0 (2448 x 2048, f 3478 px, 6 mm dots 300-500 mm away, "
          f"exact Snell): rms {np.sqrt(np.mean(bias**2)):.4f} px, max {bias.max():.4f} px over {len(bias)} dots")
    if args.dots_scenario > 0:
        score_scenario(args.dots_scenario)


def scenario_bias(name: str = "paper_single_dots", seed: int = 0) -> np.ndarray:
    """|imaged dot centre - projected dot centre| (px) of every record of a dot-board scenario, exact Snell."""
    from ari_sfm.simulate import make_scene
    from ari_sfm.simulate.scene import project

    scene = make_scene(name, seed=seed, sigma_px=0.0)
    geometry, target = scene.geometry, scene.geometry.target
    frames = geometry.frames()
    _, xyz = target.points_3d()
    a = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    ring = 0.5 * target.diameter_mm * np.stack([np.cos(a), np.sin(a), 0 * a], axis=1)
    out = []
    for o in scene.exact_observations:
        X = frames[o.frame].apply((xyz[:, None, :] + ring[None]).reshape(-1, 3))
        uv = project(geometry.window, geometry.camera(o.camera), X, o.added_mm or 0.0).reshape(len(xyz), -1, 2)
        x, y = uv[..., 0], uv[..., 1]
        xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
        cross = x * yn - xn * y
        centre = (np.stack([((x + xn) * cross).sum(1), ((y + yn) * cross).sum(1)], axis=1)
                  / (3.0 * cross.sum(1))[:, None])
        out.append(np.linalg.norm(centre - o.pixels[o.ids], axis=1))
    return np.concatenate(out)


def score_scenario(scale: float, name: str = "paper_single_dots", seed: int = 0) -> None:
    """Render a dot-board scenario through the window and score every dot detector on its images."""
    import tempfile
    from pathlib import Path

    import cv2

    from ari_sfm.io import load_dataset, load_observations
    from ari_sfm.simulate import simulate

    with tempfile.TemporaryDirectory() as tmp:
        dataset_dir, _ = simulate(name, Path(tmp), seed=seed, image_scale=scale)
        dataset = load_dataset(dataset_dir)
        exact = {(o.set, o.frame, o.added_mm, o.camera): o
                 for o in load_observations(Path(tmp) / "truth_observations.json")}
        views = [View(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), exact[(e.set, e.key, e.added_mm, cam)].pixels, 0.0)
                 for e in dataset.entries() for cam, path in e.images.items()]
        scores = {m: score(views, dataset.target, m) for m in circle_grid.CIRCLE_METHODS}
        w, h = dataset.cameras["cam0"].image_size
        print_table(f"{name} seed {seed} rendered through the window, {w} x {h} (exact Snell centres)",
                    scores, circle_grid.CIRCLE_DEFAULT_METHOD, len(views))


if __name__ == "__main__":
    main()

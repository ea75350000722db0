"""Particle image detection: ari-sfm's detector, a plain reference detector and OpenPTV's, on the same frames.

    python benchmarks/bench_particle_detection.py [--size 1024 1024] [--frames 2] [--ppp 0.005 0.01 0.02]
                                                  [--looks plain tank tank16 faint hot] [--diameter 3] [--seed 0]
                                                  [--real /work/shared/real/test_cavity]
                                                  [--experiment plain tank tank16]

Renders frames of random particle images at each density (particles per pixel,
uniform over the frame, 5 px from the border) in each look
(ari_sfm.simulate.particle_images):

- ``plain``: flat background 10, Gaussian noise 2, peaks 120-220, 8-bit
  (``simulate particles``' images);
- ``tank``: a real tank's look (``TankLook()``, after OpenPTV's test_cavity
  images): uneven background 6-40, a reflection streak, three big bright blobs
  (saturated cores), a glass wall's glare near saturation, read noise 1 and
  shot noise (~1.3-1.6 grey levels), particle peaks 30-220 (log-uniform),
  diameters +-25 %, and faint sharp specks (0.01 per pixel, 1-2 px, peaks 6-25)
  and dust (blurred discs), 8-bit;
- ``tank16``: the same scene, 16-bit;
- ``faint``: faint particles on a dark noisy background with a few bright
  blobs: background 2-6, read noise 1.5, peaks 6-60, four saturated blobs, no
  streak, glare, specks or dust, 16-bit;
- ``hot``: ``tank`` with 2 % of the pixels saturated hot pixels.

Detectors, on the same frames:

- ari-sfm: ``detect_particles_in_image`` (default options, ``diameter_px`` the hint);
- reference: a plain detector written here (global median background and MAD
  noise, local maxima of the image smoothed at sigma / 2 above 5 noise sigmas,
  a three-point Gaussian fit at each maximum, so overlapping images with their
  own maxima are split);
- OpenPTV: liboptv's ``target_recognition`` through ``optv`` after its
  high-pass (``preprocess_image(img, 0, cpar, 25)``, what pyptv runs with
  ``hp_flag`` set), with test_cavity's ``targ_rec.par`` (grey threshold 9,
  4-500 pixels, 2-100 px wide and high, grey sum > 150, discontinuity 100);
  16-bit frames are given to it as 8-bit (divided by 257, as a user converts
  them); its centres moved by -0.5 px (OpenPTV's pixel origin is the top-left
  pixel's corner).

A second OpenPTV row (``OpenPTV-3σ``) sets its grey threshold at 3 noise
sigmas of the frame (8-bit levels, >= 2), >= 3 pixels, no grey-sum floor: what
a user would set for faint particles.

Prints, per look and density: the true images not under a blob, a streak's
core or glare (the others count for no detector), the share of them with
another true image within one diameter (overlap), and per detector the recall
(true images with their own detection within 0.5 px, one to one), ghosts
(detections with no true image within 0.5 px; within 1 px), the RMS centre
error of the found ones, detections on specks (more than 1 px from every
particle and within 1 px of a speck, per 1000 specks) and images per second
per core (CPU time, OpenCV on one thread; the detectors run one after the
other on each frame, best of ``--repeat``).

With ``--experiment LOOK [LOOK ...]`` it runs the default ``simulate particles``
experiment (4 cameras, 2448 x 2048 px, 2000 particles a frame, rig B's true
calibration) with ``--frames`` rendered frames in each look (``plain``;
``tank``, 8-bit PNG; ``tank16``, the tank's scene in 16-bit TIFF) through three
pipelines, the tools alternating on each image and each frame in one process:

- ari-sfm: the calls ``detect-particles`` and ``particles --detections`` make
  (``detect_particles_in_image`` with the dataset's options, ``match_frame`` at
  0.5 px in rig.yaml's volume, >= 3 cameras);
- OpenPTV: liboptv's detector as above (sorted by y, as pyptv leaves it), then
  its ``correspondences`` and ``point_positions`` on the same calibration
  written by ``export-openptv --frame f000``, the same 0.5 px epipolar band
  and volume, >= 3 cameras (``openptv_matching``);
- OpenPTV-3σ: the same with the 3-sigma detector.

It prints the share of the images with another within one diameter (the
particles fill ~700 x 450 px of each image: ~0.006 particles per px there),
per camera the true images found within 0.5 px (of all of them,
those under glare and blobs included), the ghost detections and the RMS
centre error; per pipeline the particles found (a reconstructed point within
0.1 mm of a true one; of those seen by >= 3 cameras), the ghosts (points with
no true particle within 0.1 mm), the 3D RMS error of the others, and particles
(of the frames) per second per core (CPU time) of detection (all cameras),
of matching and triangulation, and of both.

With ``--real DIR`` (OpenPTV's test_cavity: ``DIR/cal/cam*.tif``, their
``cam*.tif_targets`` and ``DIR/parameters/targ_rec.par``) it also prints, per
camera, the particle images each detector finds on the calibration images
(a look only: these are no particle frames), the share of OpenPTV's own
detections (the ``_targets`` files) within 1 px of one of them, and images
per second per core: ari-sfm with its defaults and with targ_rec.par's
settings (``particles.detect`` from
``ari_sfm.openptv.conventions.detect_settings_from_target_par``), and
OpenPTV's ``target_recognition`` with targ_rec.par.
"""
from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from ari_sfm.particles.detect import DetectOptions, detect_particles_in_image  # noqa: E402
from ari_sfm.particles.truth import ImageScore, score_image  # noqa: E402
from ari_sfm.simulate.particle_images import TankLook, render_particle_image, render_tank_frame  # noqa: E402

MARGIN_PX = 5.0
TOLERANCE_PX = 0.5
# test_cavity's parameters/targ_rec.par (OpenPTV's test experiment): thresholds per camera, discontinuity,
# pixel count min/max, x size min/max, y size min/max, minimum grey sum, cross size
OPENPTV_TARG_REC = dict(discont=100, gvthresh=[9, 9, 9, 11], pixel_count_bounds=(4, 500), xsize_bounds=(2, 100),
                        ysize_bounds=(2, 100), min_sum_grey=150, cross_size=2)
OPENPTV_HIGHPASS = 25  # pyptv's highpass filter size

LOOKS = {
    "tank": TankLook(),
    "tank16": TankLook(bit_depth=16),
    "faint": TankLook(bit_depth=16, background=(2.0, 6.0), read_noise=1.5, shot_gain=0.02, peak=(6.0, 60.0),
                      streaks=0, blobs=4, blob_radius_px=(6.0, 20.0), blob_peak=2000.0, specks=0.0, dust=0.0,
                      glare=0),
    "hot": TankLook(hot_pixels=0.02),
}


def render(look: str, uv: np.ndarray, size: tuple[int, int], diameter: float, rng: np.random.Generator
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The frame, which of its particle images are not under a blob, a streak's core or glare, and its
    specks' centres."""
    if look == "plain":
        return render_particle_image(uv, size, diameter, rng.uniform(120.0, 220.0, len(uv)), rng=rng), \
            np.ones(len(uv), bool), np.empty((0, 2))
    frame = render_tank_frame(uv, size, diameter, LOOKS[look], rng)
    return frame.image, ~frame.covered, frame.specks


def on_specks(found: np.ndarray, uv: np.ndarray, specks: np.ndarray) -> int:
    """Detections more than 1 px from every particle image and within 1 px of a speck."""
    from scipy.spatial import cKDTree

    if not len(found) or not len(specks):
        return 0
    stray = found[cKDTree(uv).query(found)[0] > 1.0] if len(uv) else found
    return int((cKDTree(specks).query(stray)[0] <= 1.0).sum()) if len(stray) else 0


def cpu_time(detect, image: np.ndarray, repeat: int) -> tuple[np.ndarray, float]:
    """What ``detect`` finds on ``image`` and its best CPU time over ``repeat`` runs."""
    best, found = np.inf, None
    for _ in range(repeat):
        t0 = time.process_time()
        found = detect(image)
        best = min(best, time.process_time() - t0)
    return found, best


def real_look(root: str, repeat: int) -> None:
    """OpenPTV's test_cavity calibration images: counts per camera, OpenPTV's detections among each
    detector's, images per second per core (see the module docstring)."""
    from pathlib import Path

    import cv2
    from scipy.spatial import cKDTree

    from ari_sfm.openptv.conventions import detect_settings_from_target_par
    from ari_sfm.openptv.files import read_target_par

    root_path = Path(root)
    par = read_target_par(root_path / "parameters" / "targ_rec.par")
    cams = [f"cam{k}" for k in range(1, 5)]
    with_par = replace(DetectOptions(), **detect_settings_from_target_par(par, cams))
    targ = dict(OPENPTV_TARG_REC, discont=par.discont, pixel_count_bounds=(par.nnmin, par.nnmax),
                xsize_bounds=(par.nxmin, par.nxmax), ysize_bounds=(par.nymin, par.nymax), min_sum_grey=par.sumg_min)
    print(f"\nOpenPTV's test_cavity calibration images ({root}/cal), a look: particle images found, OpenPTV's "
          "own detections (cam*.tif_targets) among them within 1 px, images/s per core")
    print(f"{'camera':7s} {'OpenPTV file':>12s}  {'ari-sfm':>22s}  {'ari-sfm, targ_rec.par':>22s}  "
          f"{'OpenPTV (optv)':>22s}")
    for k, cam in enumerate(cams):
        image = cv2.imread(str(root_path / "cal" / f"{cam}.tif"), cv2.IMREAD_UNCHANGED)
        ref = np.loadtxt(root_path / "cal" / f"{cam}.tif_targets", skiprows=1, ndmin=2)[:, 1:3] - 0.5
        detectors = {"ari": lambda img: detect_particles_in_image(img, DetectOptions())[0],
                     "par": lambda img, c=cam: detect_particles_in_image(img, with_par.for_camera(c))[0],
                     "optv": lambda img, t=par.gvthres[k]: openptv_detector(img, dict(targ, gvthresh=[t] * 4))}
        cells = []
        for detect in detectors.values():
            found, t = cpu_time(detect, image, repeat)
            among = (cKDTree(found).query(ref)[0] <= 1.0).mean() if len(found) else 0.0
            cells.append(f"{len(found):6d} ({among:4.0%}) {1.0 / t:6.1f}/s")
        print(f"{cam:7s} {len(ref):12d}  " + "  ".join(f"{c:>22s}" for c in cells))


def reference_detector(image: np.ndarray, diameter_px: float, threshold_sigma: float = 5.0) -> np.ndarray:
    """Local maxima above a global threshold and a three-point Gaussian fit at each (the plain detector)."""
    import cv2

    img = np.asarray(image, np.float32)
    background = float(np.median(img))
    noise = 1.4826 * float(np.median(np.abs(img - background))) or 1.0
    sig = img - background
    smooth = cv2.GaussianBlur(sig, (0, 0), max(diameter_px / 8.0, 0.3))
    local = cv2.dilate(smooth, np.ones((3, 3), np.uint8))
    peak = (smooth >= local) & (smooth >= threshold_sigma * noise)
    peak[0, :] = peak[-1, :] = peak[:, 0] = peak[:, -1] = False
    ys, xs = np.nonzero(peak)

    def log_at(dy: int, dx: int) -> np.ndarray:
        return np.log(np.maximum(sig[ys + dy, xs + dx].astype(float), 1e-3))

    def offset(lm: np.ndarray, l0: np.ndarray, lp: np.ndarray) -> np.ndarray:
        den = 2.0 * (lm - 2.0 * l0 + lp)
        with np.errstate(divide="ignore", invalid="ignore"):
            off = (lm - lp) / den
        return np.where(np.isfinite(off) & (den < 0), np.clip(off, -0.5, 0.5), 0.0)

    c = log_at(0, 0)
    return np.stack([xs + offset(log_at(0, -1), c, log_at(0, 1)), ys + offset(log_at(-1, 0), c, log_at(1, 0))], 1)


def openptv_targets(image: np.ndarray, targ_rec: dict = OPENPTV_TARG_REC) -> Any:
    """OpenPTV's high-pass and target_recognition (liboptv), sorted by y as pyptv's detection leaves them
    (what correspondences wants); OpenPTV's pixel convention."""
    from optv.image_processing import preprocess_image
    from optv.parameters import ControlParams, TargetParams
    from optv.segmentation import target_recognition

    img = image if image.dtype == np.uint8 else np.rint(image / 257.0).astype(np.uint8)
    h, w = img.shape
    cpar = ControlParams(1, image_size=(w, h), pixel_size=(0.01, 0.01))
    cpar.set_hp_flag(True)
    tpar = TargetParams(**targ_rec)
    targets = target_recognition(preprocess_image(np.ascontiguousarray(img), 0, cpar, OPENPTV_HIGHPASS), tpar, 0, cpar)
    targets.sort_y()
    return targets


def openptv_detector(image: np.ndarray, targ_rec: dict = OPENPTV_TARG_REC) -> np.ndarray:
    """OpenPTV's detections (:func:`openptv_targets`), centres in the OpenCV convention."""
    from openptv_matching import target_pixels

    return target_pixels(openptv_targets(image, targ_rec))


def the_noise_targ_rec(noise: float) -> dict:
    """targ_rec with the grey threshold at 3 noise sigmas (8-bit levels, >= 2), >= 3 pixels, >= 2 px wide and
    high, no grey-sum floor: what a user would set for faint particles."""
    return dict(OPENPTV_TARG_REC, gvthresh=[max(2, int(round(3.0 * noise)))] * 4, pixel_count_bounds=(3, 500),
                min_sum_grey=0)


def openptv_for_the_noise(image: np.ndarray, noise: float) -> np.ndarray:
    """OpenPTV with :func:`the_noise_targ_rec`."""
    return openptv_detector(image, the_noise_targ_rec(noise))


def overlap_fraction(uv: np.ndarray, within_px: float) -> float:
    """The share of the true images with another true image within ``within_px``."""
    from scipy.spatial import cKDTree

    if len(uv) < 2:
        return 0.0
    d = cKDTree(uv).query(uv, k=2)[0][:, 1]
    return float((d < within_px).mean())


EXPERIMENTS = {"plain": dict(look="plain"), "tank": dict(look="tank"), "tank16": dict(look="tank", bit_depth=16)}
PARTICLE_TOLERANCE_MM = 0.1  # a reconstructed point this close to a true particle found it


@dataclass(frozen=True)
class Pipeline:
    """A detector and a matcher: ``detect(image, camera)`` gives what ``match`` takes (a camera each, in the
    calibration's order; it returns (M, 3) world points) and ``pixels`` reads as (N, 2) OpenCV pixels."""

    name: str
    detect: Callable[[np.ndarray, str], Any]
    pixels: Callable[[Any], np.ndarray]
    match: Callable[[list[Any]], np.ndarray]


@dataclass
class Tally:
    """A pipeline's figures over the frames."""

    images: dict[str, ImageScore]  # camera -> its detections against the true images
    detect_s: float = 0.0  # CPU
    match_s: float = 0.0
    found: int = 0  # true particles with a reconstructed point within PARTICLE_TOLERANCE_MM
    reconstructed: int = 0
    ghosts: int = 0  # reconstructed points with no true particle within PARTICLE_TOLERANCE_MM
    squared_error: float = 0.0  # of the others


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    """``fn()`` and its CPU time."""
    t0 = time.process_time()
    out = fn()
    return out, time.process_time() - t0


def pipelines(calibration, volume, options: DetectOptions, rig, noise_8bit: float) -> list[Pipeline]:
    """ari-sfm (detect-particles' and particles' calls), OpenPTV and OpenPTV-3σ (liboptv's detector, then its
    correspondences and point positions)."""
    from openptv_matching import openptv_match, target_pixels

    from ari_sfm.particles.match import match_frame

    cameras = list(calibration.cameras)
    faint = the_noise_targ_rec(noise_8bit)
    return [
        Pipeline("ari-sfm", lambda img, cam: detect_particles_in_image(img, options.for_camera(cam))[0],
                 lambda uv: uv, lambda dets: match_frame(calibration, dict(zip(cameras, dets)), TOLERANCE_PX,
                                                         volume=volume).xyz),
        Pipeline("OpenPTV", lambda img, cam: openptv_targets(img), target_pixels,
                 lambda dets: openptv_match(rig, dets)[0]),
        Pipeline("OpenPTV-3σ", lambda img, cam: openptv_targets(img, faint), target_pixels,
                 lambda dets: openptv_match(rig, dets)[0]),
    ]


def experiment(name: str, frames: int, seed: int) -> None:
    """The default simulated experiment's rendered frames through each pipeline (see the module docstring)."""
    import tempfile
    from pathlib import Path

    from openptv_matching import openptv_match, openptv_rig, targets_from_pixels
    from scipy.spatial import cKDTree

    from ari_sfm.io import load_calibration
    from ari_sfm.io.particles import load_particle_dataset
    from ari_sfm.particles.detect import detect_options, read_image
    from ari_sfm.particles.match import match_frame
    from ari_sfm.particles.reconstruct import volume_for
    from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment, write_particle_experiment

    exp = simulate_particle_experiment(ParticleSimOptions(num_frames=frames, seed=seed, **EXPERIMENTS[name]))
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_particle_experiment(exp, root / "sim", render_frames=frames)
        ds = load_particle_dataset(root / "sim" / "experiment")
        truth_b = root / "sim" / "truth" / "rig_b.json"
        calibration = load_calibration(truth_b)
        volume = volume_for(ds, calibration, None)
        rig = openptv_rig(truth_b, root / "openptv", volume, TOLERANCE_PX)
        cameras = list(calibration.cameras)
        runs = pipelines(calibration, volume, detect_options(ds), rig,
                         2.0 if EXPERIMENTS[name]["look"] == "plain" else LOOKS["tank"].read_noise)
        match_frame(calibration, exp.detections[0], TOLERANCE_PX, volume=volume)  # warm-up: out of the timing
        openptv_match(rig, [targets_from_pixels(exp.detections[0][cam])[0] for cam in cameras])
        tally = {p.name: Tally({}) for p in runs}
        seen, overlap = 0, []
        for f in range(frames):
            dets: dict[str, list[Any]] = {p.name: [] for p in runs}
            for cam in cameras:
                image = read_image(ds.image_path(cam, f))
                for p in runs:  # the tools alternate on each image
                    found, t = timed(lambda p=p, image=image, cam=cam: p.detect(image, cam))
                    dets[p.name].append(found)
                    t_ = tally[p.name]
                    t_.detect_s += t
                    score = score_image(p.pixels(found), exp.exact_pixels[f][cam], TOLERANCE_PX)
                    t_.images[cam] = t_.images[cam] + score if cam in t_.images else score
            n_views = np.zeros(len(exp.positions[f]), int)
            for cam in cameras:
                n_views[exp.particle_ids[f][cam]] += 1
                overlap.append(overlap_fraction(exp.exact_pixels[f][cam], exp.options.diameter_px))
            seen += int((n_views >= 3).sum())
            for p in runs:
                xyz, t = timed(lambda p=p, dets=dets: p.match(dets[p.name]))
                t_ = tally[p.name]
                t_.match_s += t
                d, idx = cKDTree(exp.positions[f]).query(xyz) if len(xyz) else (np.empty(0), np.empty(0, int))
                correct = d < PARTICLE_TOLERANCE_MM
                t_.found += len(np.unique(idx[correct]))
                t_.reconstructed += len(xyz)
                t_.ghosts += int((~correct).sum())
                t_.squared_error += float(np.sum(d[correct] ** 2))
    o = exp.options
    w, h = exp.rig_b.cameras[0].image_size
    n = frames * o.particles_per_frame
    print(f"\nsimulate particles --look {o.look}{' --bit-depth 16' if o.bit_depth == 16 else ''}: {len(cameras)} "
          f"cameras, {w} x {h} px, {frames} frames, {o.particles_per_frame} particles a frame ({seen} of the {n} "
          f"seen by >= 3 cameras; {np.mean(overlap):.0%} of the images with another within one diameter); rig B's true "
          f"calibration, {TOLERANCE_PX} px epipolar band")
    print(f"  true images found within {TOLERANCE_PX} px / ghosts (detections with none within {TOLERANCE_PX} px) / "
          "RMS px of the found, per camera")
    print(f"  {'detector':11s} " + " ".join(f"{cam:>23s}" for cam in cameras))
    for p in runs:
        cells = [f"{s.recall:6.1%} / {s.ghost_fraction:5.1%} / {s.rms_error_px:5.3f}"
                 for s in tally[p.name].images.values()]
        print(f"  {p.name:11s} " + " ".join(f"{c:>23s}" for c in cells))
    print(f"  particles found (a point within {PARTICLE_TOLERANCE_MM} mm) of those seen by >= 3 cameras, ghosts (none "
          "within it) of the reconstructed points, 3D RMS error; particles per second per core (CPU time)")
    print(f"  {'pipeline':11s} {'found':>7s} {'points':>7s} {'ghosts':>7s} {'RMS mm':>7s} {'detection':>10s} "
          f"{'s/image':>8s} {'matching':>9s} {'both':>7s}")
    for p in runs:
        t_ = tally[p.name]
        rms = np.sqrt(t_.squared_error / (t_.reconstructed - t_.ghosts)) if t_.reconstructed > t_.ghosts else np.nan
        ghosts = t_.ghosts / t_.reconstructed if t_.reconstructed else 0.0
        print(f"  {p.name:11s} {t_.found / seen:7.1%} {t_.reconstructed:7d} {ghosts:7.2%} {rms:7.4f} "
              f"{n / t_.detect_s:10.0f} {t_.detect_s / (frames * len(cameras)):8.3f} {n / t_.match_s:9.0f} "
              f"{n / (t_.detect_s + t_.match_s):7.0f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, nargs=2, default=(1024, 1024), metavar=("W", "H"))
    ap.add_argument("--frames", type=int, default=2, help="frames per look and density")
    ap.add_argument("--ppp", type=float, nargs="+", default=(0.005, 0.01, 0.02))
    ap.add_argument("--looks", nargs="*", default=("plain", "tank", "tank16", "faint", "hot"),
                    choices=("plain", *LOOKS))
    ap.add_argument("--diameter", type=float, default=3.0, help="particle image e^-2 diameter (px)")
    ap.add_argument("--repeat", type=int, default=2, help="timing runs per frame (the best is kept)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--real", default=None, metavar="DIR", help="OpenPTV's test_cavity folder: its calibration "
                                                                "images as a look")
    ap.add_argument("--experiment", nargs="+", default=(), choices=tuple(EXPERIMENTS),
                    help="the default simulated experiment in these looks through each pipeline")
    args = ap.parse_args()
    import cv2

    cv2.setNumThreads(1)
    w, h = args.size
    options = DetectOptions(diameter_px=args.diameter)
    detectors = {"ari-sfm": lambda img: detect_particles_in_image(img, options)[0],
                 "reference": lambda img: reference_detector(img, args.diameter),
                 "OpenPTV": openptv_detector,
                 "OpenPTV-3σ": lambda img: openptv_for_the_noise(img, noise_8bit)}
    warm = np.random.default_rng(1)  # compile (or load) the detector's kernels before any timing
    warm_uv = warm.uniform(5, 250, (300, 2))
    detect_particles_in_image(render_tank_frame(warm_uv, (256, 256), args.diameter, TankLook(), warm).image, options)
    if args.looks:
        print(f"{w} x {h} px frames, {args.frames} per row, particle images {args.diameter:g} px (e^-2 diameter), "
              f"recall and ghosts within {TOLERANCE_PX} px\n")
        print(f"{'look':7s} {'ppp':>6s} {'images':>7s} {'overlap':>7s}  {'detector':11s} {'recall':>7s} "
              f"{'ghosts':>7s} {'(1 px)':>7s} {'RMS px':>7s} {'specks':>7s} {'images/s':>9s}")
    for look in args.looks:
        per_look = {name: [] for name in detectors}
        for ppp in args.ppp:
            rng = np.random.default_rng([args.seed, int(ppp * 1e6), len(look)])
            n = int(round(ppp * w * h))
            scores: dict[str, ImageScore | None] = dict.fromkeys(detectors)
            best = {name: [] for name in detectors}
            speck_hits = dict.fromkeys(detectors, 0)
            images = overlap = speck_count = 0
            for _ in range(args.frames):
                uv_all = rng.uniform([MARGIN_PX, MARGIN_PX], [w - 1 - MARGIN_PX, h - 1 - MARGIN_PX], (n, 2))
                frame, visible, specks = render(look, uv_all, (w, h), args.diameter, rng)
                noise_8bit = 2.0 if look == "plain" else LOOKS[look].read_noise
                overlap += overlap_fraction(uv_all, args.diameter) * len(uv_all[visible])
                uv = uv_all[visible]
                images += len(uv)
                speck_count += len(specks)
                for name, detect in detectors.items():
                    found, t = cpu_time(detect, frame, args.repeat)
                    best[name].append(t)
                    per_look[name].append(t)
                    s = score_image(found, uv, TOLERANCE_PX)
                    scores[name] = s if scores[name] is None else scores[name] + s
                    speck_hits[name] += on_specks(found, uv_all, specks)
            for k, (name, s) in enumerate(scores.items()):
                head = f"{look:7s} {ppp:6.3f} {images:7d} {overlap / images:7.1%}" if k == 0 else " " * 30
                specks_per_mille = f"{1000.0 * speck_hits[name] / speck_count:6.1f}‰" if speck_count else "      -"
                print(f"{head}  {name:11s} {s.recall:7.1%} {s.ghost_fraction:7.1%} {s.ghost_fraction_1px:7.1%} "
                      f"{s.rms_error_px:7.3f} {specks_per_mille} {len(best[name]) / sum(best[name]):9.1f}")
        rate = {name: len(t) / sum(t) for name, t in per_look.items()}
        ours = rate["ari-sfm"]
        print(f"{look}: images/s per core over the look: ari-sfm {ours:.1f}, reference {rate['reference']:.1f}, "
              f"OpenPTV {rate['OpenPTV']:.1f} (ari-sfm at {ours / rate['OpenPTV']:.2f} x OpenPTV's, "
              f"{ours / rate['reference']:.2f} x the reference's)")
    if args.real:
        real_look(args.real, args.repeat)
    for name in args.experiment:
        experiment(name, args.frames, args.seed)


if __name__ == "__main__":
    main()

"""Particle image detection: ari-sfm's detector, a plain reference detector and OpenPTV's, on the same frames.

    python benchmarks/bench_particle_detection.py [--size 1024 1024] [--frames 2] [--ppp 0.005 0.01 0.02]
                                                  [--looks plain tank tank16 faint hot] [--diameter 3] [--seed 0]
                                                  [--real /work/shared/real/test_cavity]

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

With ``--experiment LOOK`` it runs the default ``simulate particles`` experiment
(4 cameras, 2448 x 2048 px, 2000 particles a frame) with ``--frames`` rendered
frames in that look through ``detect-particles`` and ``particles
--detections`` (rig B's true calibration): the true images found within
0.5 px and ghosts per camera, the particles found (a reconstructed point
within 0.1 mm of a true one) and ghosts (none within 0.1 mm), the 3D RMS error,
and the detector's CPU time per image.

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
from dataclasses import replace

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


def openptv_detector(image: np.ndarray, targ_rec: dict = OPENPTV_TARG_REC) -> np.ndarray:
    """OpenPTV's high-pass and target_recognition (liboptv), centres in the OpenCV convention."""
    from optv.image_processing import preprocess_image
    from optv.parameters import ControlParams, TargetParams
    from optv.segmentation import target_recognition

    img = image if image.dtype == np.uint8 else np.rint(image / 257.0).astype(np.uint8)
    h, w = img.shape
    cpar = ControlParams(1, image_size=(w, h), pixel_size=(0.01, 0.01))
    cpar.set_hp_flag(True)
    tpar = TargetParams(**targ_rec)
    targets = target_recognition(preprocess_image(np.ascontiguousarray(img), 0, cpar, OPENPTV_HIGHPASS), tpar, 0, cpar)
    return np.array([t.pos() for t in targets], float).reshape(-1, 2) - 0.5


def openptv_for_the_noise(image: np.ndarray, noise: float) -> np.ndarray:
    """OpenPTV with its grey threshold at 3 noise sigmas (8-bit levels, >= 2), >= 3 pixels, >= 2 px wide and
    high, no grey-sum floor: what a user would set for faint particles."""
    params = dict(OPENPTV_TARG_REC, gvthresh=[max(2, int(round(3.0 * noise)))] * 4, pixel_count_bounds=(3, 500),
                  min_sum_grey=0)
    return openptv_detector(image, params)


def overlap_fraction(uv: np.ndarray, within_px: float) -> float:
    """The share of the true images with another true image within ``within_px``."""
    from scipy.spatial import cKDTree

    if len(uv) < 2:
        return 0.0
    d = cKDTree(uv).query(uv, k=2)[0][:, 1]
    return float((d < within_px).mean())


def experiment(look: str, frames: int, seed: int) -> None:
    """The default simulated experiment through detect-particles and particles (see the module docstring)."""
    import tempfile
    from pathlib import Path

    import pyarrow.parquet as pq
    from scipy.spatial import cKDTree

    from ari_sfm.io.particles import load_particle_dataset
    from ari_sfm.particles.detect import detect_experiment, detect_options, read_image
    from ari_sfm.particles.reconstruct import MatchOptions, reconstruct_particles
    from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment, write_particle_experiment

    exp = simulate_particle_experiment(ParticleSimOptions(num_frames=frames, look=look, seed=seed))
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_particle_experiment(exp, root / "sim", render_frames=frames)
        dataset = root / "sim" / "experiment"
        detect_experiment(dataset, root / "det", workers=0)
        ds = load_particle_dataset(dataset)
        options = detect_options(ds)
        times = []
        for cam in ds.images:
            image = read_image(ds.image_path(cam, 0))
            t0 = time.process_time()
            detect_particles_in_image(image, options.for_camera(cam))
            times.append(time.process_time() - t0)
        det = pq.read_table(root / "det" / "particles.parquet")
        frame_col = det.column("frame").to_numpy()
        camera_col = np.asarray(det.column("camera").to_pylist())
        uv_det = np.stack([det.column("u").to_numpy(), det.column("v").to_numpy()], 1)
        print(f"simulate particles --look {look}: {len(exp.cameras)} cameras, {frames} frames, "
              f"{len(exp.positions[0])} particles a frame")
        for cam in exp.cameras:
            total = None
            for f in range(frames):
                one = score_image(uv_det[(frame_col == f) & (camera_col == cam)], exp.exact_pixels[f][cam])
                total = one if total is None else total + one
            print(f"  {cam}: {total.found} of {total.true_images} images ({total.recall:.1%}), ghosts "
                  f"{total.ghost_fraction:.1%}, RMS {total.rms_error_px:.3f} px")
        reconstruct_particles(dataset, root / "sim" / "truth" / "rig_b.json", root / "p3d", MatchOptions(),
                              detections_path=root / "det" / "particles.parquet", workers=0)
        t = pq.read_table(root / "p3d" / "particles3d.parquet")
        xyz = np.stack([t.column(c).to_numpy() for c in "xyz"], 1)
        f3 = t.column("frame").to_numpy()
        for f in range(frames):
            d, idx = cKDTree(exp.positions[f]).query(xyz[f3 == f])
            correct = d < 0.1
            print(f"  frame {f}: {len(np.unique(idx[correct])) / len(exp.positions[f]):.1%} of the particles, "
                  f"ghosts {1 - correct.mean():.2%}, RMS {np.sqrt(np.mean(d[correct] ** 2)):.4f} mm")
        print(f"  detection {min(times):.2f}-{max(times):.2f} s CPU per {exp.rig_b.cameras[0].image_size[0]} x "
              f"{exp.rig_b.cameras[0].image_size[1]} image")


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
    ap.add_argument("--experiment", default=None, choices=("plain", "tank"),
                    help="the default simulated experiment in this look through detect-particles and particles")
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
    if args.experiment:
        experiment(args.experiment, args.frames, args.seed)


if __name__ == "__main__":
    main()

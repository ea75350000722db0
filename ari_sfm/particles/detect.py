"""Particle images -> sub-pixel centres (``ari-sfm detect-particles``).

Per image (8 or 16 bit, read without losing the 16-bit range; float images as
they are; colour: the mean of the channels):

1. the local background and noise (:mod:`ari_sfm.particles.background`): an
   uneven background, glare, big bright blobs and dense particles move
   neither;
2. hot pixels (sharper along u and along v than any image through a lens:
   HOT_SIGMA_PX) are replaced by their neighbours' median, also on a
   particle's skirt;
3. candidates: local maxima (3 x 3) of the residual smoothed at half a
   particle's sigma, above the threshold: ``threshold_sigma`` times that
   smoothed image's local noise, and ``min_peak`` and ``threshold`` grey
   levels (none by default); not within an opening disc of a saturated region
   wider than it (a blob's rim), not on glare (a background above GLARE_LEVEL
   of full scale, or a local noise GLARE_NOISE times the frame's typical);
4. a candidate must look like an image, not a cluster of hot pixels (a pair,
   a line, an L): support along u and along v, and on the diagonal between
   (:func:`_supported`); and be one a PTV lab can use (:func:`_usable`): its
   pixels above the threshold, 4-connected to its brightest (as OpenPTV's
   target_recognition counts them), between ``min_pixels`` and ``max_pixels``
   and at least ``min_span_px`` wide along u and v (by default from the
   diameter hint), their grey sum at least ``min_sum``, and (step 7) its
   fitted peak at least ``relative_floor`` (e^-2) times the frame's bright
   images' (the BRIGHT_QUANTILE of the fitted peaks): fainter specks are
   seeding out of the light sheet (beyond its e^-2 edge), out of focus, or
   dust (a candidate's brightest pixel is held to half that floor before
   the fits);
5. centres: three-point Gaussian fits along u and along v (exact for a
   Gaussian sampled at pixel centres; ``diameter_px`` is the e^-2 diameter,
   sigma = diameter / 4), refined by DEBLEND_ITERATIONS rounds in which every
   other particle's fitted Gaussian is subtracted first: overlapping images
   that keep their own maxima are split, each centre freed of its
   neighbour's tail; a saturated peak (flat top) is centred on its own
   pixels' intensity centroid;
6. an image elongated beyond the noise (``max_elongation``; its shape from a
   weighted fit of the log intensities of its 3 x 3 pixels,
   :func:`image_shape`) is fitted as one elliptical Gaussian and as two
   round ones: two images merged into one maximum are split where the data
   show two (SPLIT_EVIDENCE), else it stays one, centred by the elliptical fit;
7. dropped: images on a ridge (a streak, a blob's rim: :func:`_on_ridge`),
   wider than ``max_width_ratio`` times the hint, sharper than any optical
   image along every axis (hot pixels beside a particle), or fainter than the
   relative floor of step 4.

Two images closer than ~0.8 px (MIN_SPLIT_PX) stay one. The per-pixel and
per-candidate arithmetic is compiled (:mod:`ari_sfm.particles.detect_kernels`).
A lab's settings: rig.yaml's ``particles.detect`` (:func:`detect_options`;
from OpenPTV's targ_rec.par: :func:`ari_sfm.openptv.conventions.detect_settings_from_target_par`).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.particles.background import Background, estimate_background, opening_size
from ari_sfm.particles.engine import PartitionError

log = logging.getLogger(__name__)

MIN_SIGNAL = 1e-3  # floor of background-subtracted intensities before the log of the Gaussian fit
SMOOTH_FRACTION = 0.5  # the candidates' image: the residual smoothed at this fraction of a particle's sigma
AXIS_SUPPORT = 0.1  # a particle image (e^-2 diameter >= ~1.5 px) lends each axis' brighter neighbour this of its peak
DIAGONAL_SUPPORT = 0.25  # and its diagonal pixel >= this fraction of the separable profile's value there
HOT_SIGMA_PX = 0.4  # a pixel sharper than a Gaussian image of this sigma (px, pixel-integrated >= 0.29) is hot
SUPPORT_SIGMAS = 2.0  # the support tests' allowance for noise, in noise sigmas
SIGNIFICANT_SIGMAS = 3.0  # or a bright sharp image's neighbours along an axis stand this far above the noise
DEBLEND_ITERATIONS = 2  # rounds of centre fits with the other particles' Gaussians subtracted
SIGMA_RANGE = (0.5, 2.0)  # a fitted sigma is clipped to this range times the hint's
RIDGE_RADIUS_SIGMAS = 3.5  # a ridge (a streak, a blob's rim): both sides this far along a line stay ...
RIDGE_LEVEL = 0.35  # ... above this fraction of the peak (two noise sigmas allowed); a particle image falls to ~0
SPLIT_RANGE_PX = (0.4, 1.5)  # half the distance of a split pair's first centres
PAIR_WINDOW_SIGMAS = 2.0  # a merged pair's two-Gaussian fit uses the pixels within this many sigmas (+ 0.5 px)
FIT_ITERATIONS = 10  # Levenberg-Marquardt iterations of the fits of elongated images, at most
FIT_TOLERANCE = 1e-4  # a fit stops once a step lowers its cost by less than this fraction (centres settle < 0.01 px)
SPLIT_EVIDENCE = 9.0  # two Gaussians must fit an elongated image better than one by this (squared noise sigmas)
MIN_SPLIT_PX = 0.8  # a pair fitted closer than this stays one image
MAX_LOG_OVERSHOOT = 1.0  # a fitted Gaussian's peak is at most e times its peak pixel (a flat fit's cap)
MODEL_NOISE = 0.03  # the shape fit's relative noise floor per pixel (shot noise, a profile not quite Gaussian)
MODEL_RADIUS_SIGMAS = 4.0  # a particle's fitted Gaussian is subtracted out to this many of the hint's sigmas
GLARE_LEVEL = 0.5  # no image where the background is above this fraction of full scale (glare, near saturation)
GLARE_NOISE = 4.0  # nor where the local noise exceeds this many times the frame's typical (glare, texture)
BRIGHT_QUANTILE = 0.99  # the frame's bright particle images: this quantile of the candidates' peaks ...
BRIGHT_COUNT = 10  # ... or the BRIGHT_COUNT-th brightest in a frame of fewer than BRIGHT_COUNT / (1 - quantile)
SHEET_EDGE = math.exp(-2.0)  # a light sheet's edge (its e^-2 thickness): the default relative brightness floor
PRE_FLOOR = 0.5  # before the fits, a candidate's brightest pixel against that floor times this: an image's sampled
# maximum is at least half its fitted peak (sigma >= 0.6 px, centred anywhere in its pixel), a speck's is its peak


@dataclass(frozen=True)
class DetectSummary:
    """What :func:`detect_experiment` found; ``to_json()`` is detect-particles.json."""

    dataset: str
    frames: tuple[int, int]  # first, last
    detections: int
    per_camera: Mapping[str, int]
    time_s: float
    workers: int | None  # None with a scheduler
    scheduler: str | None
    options: Mapping[str, Any] = field(default_factory=dict)  # the DetectOptions used
    warnings: tuple[str, ...] = ()  # e.g. a camera with no particle image in any frame

    def to_json(self) -> dict[str, Any]:
        return {"format": "ari-sfm-detect-particles/1", "dataset": self.dataset, "frames": list(self.frames),
                "detections": self.detections, "per_camera": dict(self.per_camera), "options": dict(self.options),
                "time_s": self.time_s, "workers": self.workers, "scheduler": self.scheduler,
                "warnings": list(self.warnings)}


@dataclass(frozen=True)
class DetectOptions:
    """How particle images are found.

    The threshold: ``threshold_sigma`` local noise sigmas of the image smoothed at half a particle's sigma,
    at least ``min_peak`` and ``threshold`` grey levels above the local background. An image's pixels:
    those 4-connected to its brightest above the threshold (as OpenPTV's target_recognition counts them);
    sizes left None follow the diameter hint.
    """

    diameter_px: float = 3.0  # e^-2 diameter hint (rig.yaml particles.diameter_px)
    threshold_sigma: float = 5.0  # smoothed peak above the local background, in units of its local noise
    min_peak: float = 0.0  # and at least this many grey levels above it (0: the noise alone decides)
    max_width_ratio: float = 2.5  # a blob wider than this times the hint's image (its sigma) is none: dropped
    max_elongation: float = 1.2  # longer than wide by this beyond the noise: fitted as one or two (step 6)
    background_px: int = 32  # blocks of the local background's offset and of the local noise
    # grey levels above the local background for a peak and for a pixel of an image (OpenPTV's grey
    # threshold); a mapping: per camera (cameras not in it: none); None: the noise alone decides
    threshold: float | Mapping[str, float] | None = None
    min_pixels: int | None = None  # at least this many pixels (None: half the hint's e^-2 disc, pi d^2 / 8)
    max_pixels: int | None = None  # at most (None: twice the e^-2 disc of an image max_width_ratio x the hint)
    min_span_px: int | None = None  # at least this wide along u and along v (None: d / sqrt 2, >= 1)
    max_span_px: int | None = None  # at most (None: no limit but max_pixels)
    min_sum: float = 0.0  # their grey sum above the local background at least this (OpenPTV's sumg_min)
    relative_floor: float = SHEET_EDGE  # peak >= this x the frame's bright images' (0: none; see step 4)

    def for_camera(self, camera: str) -> DetectOptions:
        """These options with ``threshold`` resolved for one camera."""
        from dataclasses import replace

        if isinstance(self.threshold, Mapping):
            value = self.threshold.get(camera)
            return replace(self, threshold=None if value is None else float(value))
        return self

    def pixel_limits(self) -> tuple[int, int, int, int]:
        """min_pixels, max_pixels, min_span_px, max_span_px with the hint's defaults filled in."""
        d = self.diameter_px
        lo = self.min_pixels if self.min_pixels is not None else max(1, math.ceil(math.pi * d * d / 8.0 - 1e-9))
        hi = (self.max_pixels if self.max_pixels is not None
              else math.ceil(math.pi * (self.max_width_ratio * d) ** 2 / 2.0))
        span_lo = self.min_span_px if self.min_span_px is not None else max(1, int(d / math.sqrt(2.0) + 1e-9))
        span_hi = self.max_span_px if self.max_span_px is not None else 1 << 30
        return int(lo), int(hi), int(span_lo), int(span_hi)


def _grey(image: np.ndarray) -> tuple[np.ndarray, float, float, np.ndarray | None]:
    """A float32 grey image (colour: the mean of the colour channels, an alpha channel left out), its grey
    level step (1 integer, 0 float), its saturation level and the grey image in its integer type (None for
    colour or float images)."""
    img = np.asarray(image)
    dtype = img.dtype
    source = img if img.ndim == 2 and dtype in (np.uint8, np.uint16) else None
    if img.ndim == 3:
        img = img[:, :, :3 if img.shape[2] >= 3 else 1].mean(axis=2)
    if np.issubdtype(dtype, np.integer):
        return img.astype(np.float32), 1.0, float(np.iinfo(dtype).max), source
    return np.nan_to_num(img.astype(np.float32)), 0.0, math.inf, None


def detect_particles_in_image(image: np.ndarray, options: DetectOptions = DetectOptions()
                              ) -> tuple[np.ndarray, np.ndarray]:
    """Find the particle images of one image (the steps of the module docstring).

    Args:
        image: The image: 8 or 16 bit, float, or colour (the mean of the channels).
        options: How particle images are found; ``options.threshold`` must be a number or None here
            (:meth:`DetectOptions.for_camera`).

    Returns:
        (centres (N, 2), OpenCV pixel convention; peak intensities (N,) above the local background, in the
        image's grey levels).

    Raises:
        ValueError: ``options.threshold`` is a mapping per camera.
    """
    import cv2

    from ari_sfm.particles import detect_kernels as K

    img, quantum, saturation, source = _grey(image)
    h, w = img.shape
    empty = (np.empty((0, 2)), np.empty(0))
    if h < 3 or w < 3:
        return empty
    if isinstance(options.threshold, Mapping):
        raise ValueError("DetectOptions.threshold is a mapping per camera: resolve it with for_camera()")
    grey_threshold = float(options.threshold or 0.0)
    sigma = options.diameter_px / 4.0
    background = estimate_background(img, options.diameter_px, int(options.background_px), quantum, source)
    res = img - background.level
    noise = background.noise
    clean = K.without_hot_pixels(res, noise, 1.0 / (HOT_SIGMA_PX * HOT_SIGMA_PX))
    s_smooth = max(SMOOTH_FRACTION * sigma, 0.3)
    smooth = cv2.GaussianBlur(clean, (0, 0), s_smooth, borderType=cv2.BORDER_REPLICATE)
    factor = options.threshold_sigma * _smoothing_gain(s_smooth)  # the threshold in pixel noise sigmas
    floor = max(float(options.min_peak), grey_threshold)
    ys, xs = K.local_maxima(smooth, noise, factor, floor)
    if len(xs):
        blob = _near_saturated_blob(img, saturation, options.diameter_px)
        ok = _supported(clean, ys, xs, noise[ys, xs]) & ~blob[ys, xs] & ~_in_glare(background, ys, xs, saturation)
        ys, xs = ys[ok], xs[ok]
    if len(xs):
        ok = _usable(clean, noise, ys, xs, options, factor, floor)
        ys, xs = ys[ok], xs[ok]
    if not len(xs):
        return empty
    saturated = img[ys, xs] >= saturation
    fit = _deblended_fit(clean, noise, ys, xs, sigma, saturated, options.max_elongation)
    single = _single(fit, sigma, options.max_width_ratio, options.max_elongation)
    uv, peak = fit.uv[single], fit.peak[single]
    if options.relative_floor > 0 and len(peak):  # the fitted peaks: the images' brightness, wherever centred
        keep = peak >= options.relative_floor * _bright(peak)
        uv, peak = uv[keep], peak[keep]
    return uv, peak


def _bright(peaks: np.ndarray) -> float:
    """The frame's bright particle images' peak: the BRIGHT_QUANTILE of ``peaks``, the BRIGHT_COUNT-th
    brightest in a sparse frame."""
    ranked = np.sort(peaks)[::-1]
    k = max(BRIGHT_COUNT, math.ceil((1.0 - BRIGHT_QUANTILE) * len(ranked)))
    return float(ranked[min(k, len(ranked)) - 1])


def _in_glare(background: Background, ys: np.ndarray, xs: np.ndarray, saturation: float) -> np.ndarray:
    """(N,) True where the background is glare: above GLARE_LEVEL of full scale (a particle there clips
    within half the range, and what stands out is noise on the glare), or its local noise GLARE_NOISE
    times the frame's typical (texture, a wall's streaks: structure, not noise)."""
    level = background.level[ys, xs]
    noisy = background.noise[ys, xs] >= GLARE_NOISE * max(background.typical_noise, 1e-12)
    return (level >= GLARE_LEVEL * saturation) | noisy


def _usable(clean: np.ndarray, noise: np.ndarray, ys: np.ndarray, xs: np.ndarray, options: DetectOptions,
            factor: float, floor: float) -> np.ndarray:
    """(N,) True where a candidate is a particle image a PTV lab can use: its pixels (4-connected to its
    brightest pixel, above ``factor`` local noise sigmas and ``floor`` grey levels: the threshold) within
    :meth:`DetectOptions.pixel_limits` and summing to ``min_sum``, and its brightest pixel at least PRE_FLOOR
    x ``relative_floor`` times the frame's bright images' (:func:`_bright` of the candidates that pass; the
    fitted peaks are held to ``relative_floor`` itself after the fits). Fainter specks are out of the light
    (beyond the sheet's e^-2 edge), out of focus or dust; 1-2 px specks cannot be centred to a fraction of
    a pixel."""
    from ari_sfm.particles.detect_kernels import connected_regions

    lo, hi, span_lo, span_hi = options.pixel_limits()
    count, width_u, width_v, total, peak = connected_regions(clean, noise, factor, floor, ys.astype(np.int64),
                                                             xs.astype(np.int64), hi)
    ok = ((count >= lo) & (count <= hi) & (np.minimum(width_u, width_v) >= span_lo)
          & (np.maximum(width_u, width_v) <= span_hi) & (total >= options.min_sum))
    if options.relative_floor > 0 and ok.any():
        ok &= peak >= PRE_FLOOR * options.relative_floor * _bright(peak[ok])
    return ok


def _smoothing_gain(sigma: float) -> float:
    """How much a Gaussian blur of ``sigma`` px lowers white noise: the root sum of its squared weights."""
    import cv2

    k = cv2.getGaussianKernel(2 * int(math.ceil(4 * sigma)) + 1, sigma)
    return float(np.sum(k * k))  # (sum of squares in 1-D) squared under the root: the 2-D blur is separable


def _near_saturated_blob(img: np.ndarray, saturation: float, diameter_px: float) -> np.ndarray:
    """(h, w) bool: within an opening disc of a saturated region wider than that disc (a blob, a glare:
    its rim is no particle, and a particle there cannot be measured)."""
    import cv2

    saturated = (img >= saturation).astype(np.uint8)
    if not saturated.any():
        return np.zeros(img.shape, bool)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (opening_size(diameter_px),) * 2)
    big = cv2.morphologyEx(saturated, cv2.MORPH_OPEN, disc)
    return cv2.dilate(big, disc).astype(bool) if big.any() else np.zeros(img.shape, bool)


def _supported(res: np.ndarray, ys: np.ndarray, xs: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """(N,) True where a candidate's 3 x 3 pixels look like a particle image, not a hot cluster (a pair,
    a line or an L of hot pixels): along u and along v, its brighter neighbour holds AXIS_SUPPORT of its
    peak (SUPPORT_SIGMAS noise sigmas allowed: a faint image) or its two neighbours together stand
    SIGNIFICANT_SIGMAS above the noise (a bright sharp image); and the diagonal pixel between the two
    brighter neighbours holds DIAGONAL_SUPPORT of what a separable profile puts there."""
    r0 = res[ys, xs]
    left, right = res[ys, xs - 1], res[ys, xs + 1]
    up, down = res[ys - 1, xs], res[ys + 1, xs]
    su, sv = np.maximum(left, right), np.maximum(up, down)
    margin = SUPPORT_SIGMAS * noise
    significant = SIGNIFICANT_SIGMAS * math.sqrt(2.0) * noise  # the two neighbours' sum against its noise
    axes = (((su + margin >= AXIS_SUPPORT * r0) | (left + right >= significant))
            & ((sv + margin >= AXIS_SUPPORT * r0) | (up + down >= significant)))
    du = np.where(right >= left, 1, -1)
    dv = np.where(down >= up, 1, -1)
    diag = res[ys + dv, xs + du]
    with np.errstate(divide="ignore", invalid="ignore"):
        separable = np.where(r0 > 0, np.maximum(su, 0) * np.maximum(sv, 0) / r0, 0.0)
    return axes & (diag + margin >= DIAGONAL_SUPPORT * separable)


@dataclass(frozen=True)
class _State:
    """Particle images being fitted (arrays over the images)."""

    anchor_y: np.ndarray  # the pixel each started from; its peak pixel stays within one pixel of it
    anchor_x: np.ndarray
    y0: np.ndarray  # its peak pixel
    x0: np.ndarray
    u: np.ndarray  # its Gaussian: centre, peak above the background, sigmas along u and v
    v: np.ndarray
    A: np.ndarray
    su: np.ndarray
    sv: np.ndarray
    saturated: np.ndarray  # bool: its peak pixel is saturated (a flat top: centred by its centroid)
    fixed: np.ndarray  # bool: one of a split pair, fitted as such: held in the rounds of fits

    def take(self, rows: np.ndarray) -> _State:
        return _State(*(getattr(self, f)[rows] for f in self.__dataclass_fields__))

    def join(self, other: _State) -> _State:
        return _State(*(np.concatenate([getattr(self, f), getattr(other, f)]) for f in self.__dataclass_fields__))


@dataclass(frozen=True)
class _Fit:
    """The fitted particle images of a frame."""

    uv: np.ndarray  # (N, 2) centres
    peak: np.ndarray  # (N,) Gaussian peaks above the background (a saturated one: its brightest pixel)
    shape: ImageShape  # from its own 3 x 3 pixels, the others' Gaussians subtracted
    ridge: np.ndarray  # (N,) bool: on a ridge (a streak, a blob's rim), not a particle image
    saturated: np.ndarray  # (N,) bool
    fixed: np.ndarray  # (N,) bool: an elongated image fitted as one elliptical Gaussian or as two round ones


@dataclass(frozen=True)
class ImageShape:
    """The Gaussian shape of particle images (arrays over the images), see :func:`image_shape`."""

    sigma_major: np.ndarray  # sigma along the widest axis (inf: not a peak)
    elongation: np.ndarray  # widest over narrowest sigma (inf: not a peak)
    sigma_major_sure: np.ndarray  # the widest sigma with the curvature two standard errors up
    elongation_sure: np.ndarray  # the elongation with the anisotropy two standard errors down (1: none)
    axis: np.ndarray  # (N, 2) the widest axis (unit vector, u v)
    half_split: np.ndarray  # half the distance of two equal round images that would look like this one

    def take(self, rows: np.ndarray) -> ImageShape:
        return ImageShape(*(getattr(self, f)[rows] for f in self.__dataclass_fields__))

    def join(self, other: ImageShape) -> ImageShape:
        return ImageShape(*(np.concatenate([getattr(self, f), getattr(other, f)]) for f in self.__dataclass_fields__))


def _offsets(r: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column offsets of a (2 r + 1)^2 window, row-major."""
    off = np.arange(-r, r + 1)
    dy, dx = np.meshgrid(off, off, indexing="ij")
    return dy.ravel(), dx.ravel()


def _deblended_fit(res: np.ndarray, noise: np.ndarray, ys: np.ndarray, xs: np.ndarray, sigma: float,
                   saturated: np.ndarray, max_elongation: float) -> _Fit:
    """Centres by three-point Gaussian fits, every other particle's Gaussian subtracted; merged pairs
    split (step 5)."""
    n = len(ys)
    A = np.maximum(res[ys, xs].astype(float), MIN_SIGNAL)
    state = _State(ys, xs, ys, xs, xs.astype(float), ys.astype(float), A, np.full(n, sigma), np.full(n, sigma),
                   saturated, np.zeros(n, bool))
    model = _Model(res.shape, _model_radius(sigma))
    state = _fit_rounds(res, state, sigma, DEBLEND_ITERATIONS, model)
    shape = image_shape(_own_pixels(res, model.image, state, *_offsets(1)), noise[state.y0, state.x0])
    ridge = _on_ridge(res, noise, state, sigma, shape.axis)
    elongated = (shape.elongation_sure > max_elongation) & np.isfinite(shape.elongation) & ~ridge & ~state.saturated
    if elongated.any():
        state, kept = _fit_elongated(res, noise, model.image, state, shape, elongated)
        ridge = np.concatenate([ridge[kept], np.zeros(len(state.u) - len(kept), bool)])
        model.draw(state)
        twins = state.take(np.arange(len(kept), len(state.u)))
        shape = shape.take(kept).join(image_shape(_own_pixels(res, model.image, twins, *_offsets(1)),
                                                  noise[twins.y0, twins.x0]))
        state = _fit_rounds(res, state, sigma, 1, model, render_last=False)  # the neighbours of split pairs
    return _Fit(uv=np.stack([state.u, state.v], axis=1), peak=state.A, shape=shape, ridge=ridge,
                saturated=state.saturated, fixed=state.fixed)


class _Model:
    """The sum of the particles' fitted Gaussians over a frame, redrawn in place (one array per frame)."""

    def __init__(self, shape: tuple[int, int], radius: int) -> None:
        self.image = np.zeros((0, 0))  # none drawn yet (the kernels' stand-in)
        self.shape = shape
        self.radius = radius
        self.cx = self.cy = np.empty(0, np.int64)

    def draw(self, s: _State) -> None:
        """The Gaussians of ``s``, each over a (2 radius + 1)^2 window."""
        from ari_sfm.particles.detect_kernels import render

        if not self.image.size:
            self.image = np.zeros(self.shape)
        self.cx, self.cy = render(self.image, self.cx, self.cy, *(np.asarray(getattr(s, f), float)
                                                                  for f in ("u", "v", "A", "su", "sv")), self.radius)


def _fit_rounds(res: np.ndarray, state: _State, sigma: float, rounds: int, model: _Model,
                render_last: bool = True) -> _State:
    """``rounds`` rounds of three-point Gaussian fits along u and v, each particle's own pixels being the
    residual minus the other particles' Gaussians of the round before (``model``: those of the start, none
    drawn: no others), redrawn after each round (not after the last unless ``render_last``)."""
    from ari_sfm.particles.detect_kernels import fit_round

    s_lo, s_hi = SIGMA_RANGE[0] * sigma, max(SIGMA_RANGE[1] * sigma, 0.5)
    centroid_r = int(math.ceil(2.0 * sigma + 1.0))
    f = {name: getattr(state, name).copy() for name in ("y0", "x0", "u", "v", "A", "su", "sv")}
    f["u"], f["v"], f["A"], f["su"], f["sv"] = (f[k].astype(float) for k in ("u", "v", "A", "su", "sv"))
    f["y0"], f["x0"] = f["y0"].astype(np.int64), f["x0"].astype(np.int64)
    anchor_y, anchor_x = state.anchor_y.astype(np.int64), state.anchor_x.astype(np.int64)
    for k in range(rounds):
        fit_round(res, model.image, anchor_y, anchor_x, f["y0"], f["x0"], f["u"], f["v"], f["A"], f["su"], f["sv"],
                  state.saturated, state.fixed, float(sigma), s_lo, s_hi, centroid_r, MIN_SIGNAL, MAX_LOG_OVERSHOOT)
        state = _State(state.anchor_y, state.anchor_x, f["y0"], f["x0"], f["u"], f["v"], f["A"], f["su"], f["sv"],
                       state.saturated, state.fixed)
        if render_last or k < rounds - 1:
            model.draw(state)
        f = {name: getattr(state, name).copy() for name in ("y0", "x0", "u", "v", "A", "su", "sv")}
    return state


def _no_model(model: np.ndarray | None) -> np.ndarray:
    """The kernels' stand-in for no model: an empty array."""
    return np.zeros((0, 0)) if model is None else model


def _model_radius(sigma: float) -> int:
    """The half-width of the window over which a particle's fitted Gaussian is subtracted from the others'."""
    return max(2, int(math.ceil(MODEL_RADIUS_SIGMAS * sigma)))


def _fit_elongated(res: np.ndarray, noise: np.ndarray, model: np.ndarray, state: _State, shape: ImageShape,
                   elongated: np.ndarray) -> tuple[_State, np.ndarray]:
    """Each elongated image fitted two ways to its own pixels (the other particles' Gaussians subtracted):
    as one elliptical Gaussian and as two round ones (both centres, both peaks, one sigma; started
    ``half_split`` either side of its centre along its widest axis), by Levenberg-Marquardt. It becomes
    two images where two fit better by more than SPLIT_EVIDENCE (squared noise sigmas), both peaks stand
    above SUPPORT_SIGMAS noise sigmas and the centres lie at least MIN_SPLIT_PX apart; else it stays one,
    centred by the elliptical fit. Either way it is held (``fixed``) from then on. Returns the state (the
    images not split, in their order, then the first and the second of each split pair) and the rows of
    ``state`` it keeps."""
    from ari_sfm.particles.detect_kernels import levenberg_marquardt

    rows = np.flatnonzero(elongated)
    s = state.take(rows)
    dy, dx = _offsets(max(2, int(math.ceil(PAIR_WINDOW_SIGMAS * float(np.median(s.su)) + 0.5))))
    data = _own_pixels(res, model, s, dy, dx)
    h, w = res.shape
    X = np.clip(s.x0[:, None] + dx, 0, w - 1).astype(float)
    Y = np.clip(s.y0[:, None] + dy, 0, h - 1).astype(float)
    # one elliptical Gaussian: u, v, A and the inverse covariance (a, b, c), started from the shape's Hessian
    a0, b0 = _inverse_covariance(shape, rows)
    one = np.stack([s.u, s.v, s.A, a0[:, 0], a0[:, 1], b0], axis=1)
    one, ssr_one = levenberg_marquardt(0, one, X, Y, data, FIT_ITERATIONS, FIT_TOLERANCE)
    # two round Gaussians: u1, v1, u2, v2, A1, A2, sigma
    half = np.clip(shape.half_split[rows], SPLIT_RANGE_PX[0], SPLIT_RANGE_PX[1])
    du, dv = half * shape.axis[rows, 0], half * shape.axis[rows, 1]
    two = np.stack([s.u - du, s.v - dv, s.u + du, s.v + dv, 0.6 * s.A, 0.6 * s.A,
                    np.sqrt(0.5 * (s.su ** 2 + s.sv ** 2))], axis=1)
    two, ssr_two = levenberg_marquardt(1, two, X, Y, data, FIT_ITERATIONS, FIT_TOLERANCE)
    sep = np.hypot(two[:, 2] - two[:, 0], two[:, 3] - two[:, 1])
    n2 = noise[s.y0, s.x0] ** 2
    split = ((ssr_one - ssr_two > SPLIT_EVIDENCE * n2) & (sep >= MIN_SPLIT_PX)
             & (np.minimum(two[:, 4], two[:, 5]) >= SUPPORT_SIGMAS * np.sqrt(n2))
             & (np.hypot(0.5 * (two[:, 0] + two[:, 2]) - s.u, 0.5 * (two[:, 1] + two[:, 3]) - s.v) <= 1.0))
    # the ones that stay one: the elliptical centre (where it converged near the start), held
    held = np.ones(len(rows), bool)
    good = np.isfinite(one).all(axis=1) & (np.hypot(one[:, 0] - s.u, one[:, 1] - s.v) <= 1.0)
    det = one[:, 3] * one[:, 5] - one[:, 4] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        su = np.where(good & (det > 0), np.sqrt(one[:, 5] / det), s.su)  # the ellipse's marginal sigmas
        sv = np.where(good & (det > 0), np.sqrt(one[:, 3] / det), s.sv)
    single = _State(s.anchor_y, s.anchor_x, s.y0, s.x0, np.where(good, one[:, 0], s.u), np.where(good, one[:, 1], s.v),
                    np.where(good, one[:, 2], s.A), su, sv, s.saturated, held)
    keep = np.ones(len(state.u), bool)
    keep[rows[split]] = False
    out = state.take(np.flatnonzero(keep))
    # write the singles back in place
    rows_kept = np.flatnonzero(keep)
    pos = np.searchsorted(rows_kept, rows[~split])
    fields = {f: getattr(out, f).copy() for f in out.__dataclass_fields__}
    for f in fields:
        fields[f][pos] = getattr(single, f)[~split]
    out = _State(**fields)
    if split.any():
        p, t = two[split], s.take(split)
        twins = []
        for k in (0, 1):
            u, v = p[:, 2 * k], p[:, 2 * k + 1]
            y0 = np.clip(np.rint(v).astype(int), 1, h - 2)
            x0 = np.clip(np.rint(u).astype(int), 1, w - 2)
            twins.append(_State(y0, x0, y0, x0, u, v, p[:, 4 + k], p[:, 6], p[:, 6], t.saturated,
                                np.ones(len(p), bool)))
        out = out.join(twins[0]).join(twins[1])
    return out, rows_kept


def _inverse_covariance(shape: ImageShape, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) the diagonal (a, c) and (N,) the off-diagonal b of each image's inverse covariance, from
    its widest sigma, elongation and axis (round at the hint where those are not finite)."""
    major = shape.sigma_major[rows]
    el = shape.elongation[rows]
    ok = np.isfinite(major) & np.isfinite(el) & (el > 0)
    lam_low = np.where(ok, 1.0 / np.where(ok, major, 1.0) ** 2, 1.0)
    lam_high = np.where(ok, lam_low * np.where(ok, el, 1.0) ** 2, 1.0)
    cu, cv = shape.axis[rows, 0], shape.axis[rows, 1]  # the widest axis: eigenvalue lam_low
    a = lam_low * cu * cu + lam_high * cv * cv
    c = lam_low * cv * cv + lam_high * cu * cu
    b = (lam_low - lam_high) * cu * cv
    return np.stack([a, c], axis=1), b


def _own_pixels(res: np.ndarray, model: np.ndarray | None, s: _State, dy: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """(N, len(dy)) the residual at each particle's pixels (y0 + dy, x0 + dx), clamped to the frame,
    minus the other particles' Gaussians (the whole model minus its own)."""
    from ari_sfm.particles.detect_kernels import own_pixels

    return own_pixels(res, _no_model(model), *(np.asarray(a, np.int64) for a in (s.y0, s.x0)),
                      *(np.asarray(a, float) for a in (s.u, s.v, s.A, s.su, s.sv)),
                      np.asarray(dy, np.int64), np.asarray(dx, np.int64))


def _on_ridge(res: np.ndarray, noise: np.ndarray, s: _State, sigma: float, axis: np.ndarray) -> np.ndarray:
    """(N,) True where an image lies on a ridge (a streak, a blob's rim): along its widest axis (``axis``,
    (N, 2)) or one of u, v and the two diagonals, the residual (other candidates kept: a streak is a chain
    of them) stays above RIDGE_LEVEL of its peak on both sides at r and half that at 2 r
    (r = RIDGE_RADIUS_SIGMAS sigmas, nearest pixels), two noise sigmas allowed."""
    from ari_sfm.particles.detect_kernels import on_ridge

    r = max(2, int(math.ceil(RIDGE_RADIUS_SIGMAS * sigma)))
    return on_ridge(res, noise[s.y0, s.x0].astype(float), *(np.asarray(a, float) for a in (s.u, s.v, s.A)),
                    np.ascontiguousarray(axis, float), r, RIDGE_LEVEL, SUPPORT_SIGMAS, MIN_SIGNAL)


def image_shape(own: np.ndarray, noise: np.ndarray) -> ImageShape:
    """The Gaussian shape of particle images from their own 3 x 3 pixels.

    The Hessian of the log intensities by weighted least squares (a quadratic in the pixel offsets;
    weights: each log's inverse variance, (I / noise)^2 with a MODEL_NOISE relative floor for shot noise
    and the profile's departure from a Gaussian). Exact for a Gaussian of any orientation, wherever its
    centre lies in the peak pixel. Two equal round images of sigma s, 2 a apart, look like one with log
    curvatures 1 / s^2 across and 1 / s^2 - a^2 / s^4 along: ``half_split`` is that a.

    Args:
        own: (N, 9) each image's 3 x 3 pixels, row-major around the peak pixel, above the background.
        noise: (N,) the noise at each peak pixel.

    Returns:
        The images' shapes.
    """
    from ari_sfm.particles.detect_kernels import shape_hessians

    n = len(own)
    hess, c3 = shape_hessians(np.ascontiguousarray(own, float), np.asarray(noise, float), MODEL_NOISE)
    h_uu, h_uv, h_vv = hess[:, 0], hess[:, 1], hess[:, 2]
    m = -0.5 * (h_uu + h_vv)  # the eigenvalues of -H: m -/+ d
    q = 0.5 * (h_uu - h_vv)
    d = np.hypot(q, h_uv)
    with np.errstate(divide="ignore", invalid="ignore"):
        gd = np.stack([q / (2 * d), h_uv / d, -q / (2 * d)], axis=1)  # d(d) / d(h_uu, h_uv, h_vv)
        gd = np.where((d > 0)[:, None], gd, np.array([0.5, 1.0, 0.5]) / math.sqrt(1.5))
        gl = np.stack([-0.5 - gd[:, 0], -gd[:, 1], -0.5 - gd[:, 2]], axis=1)  # d(m - d)
        sd_d = np.sqrt(np.einsum("ni,nij,nj->n", gd, c3, gd))
        sd_low = np.sqrt(np.einsum("ni,nij,nj->n", gl, c3, gl))
        low, high = m - d, m + d  # the smallest and largest curvature of -log I
        peak = (low > 0) & np.isfinite(m)
        sigma_major = np.where(peak, 1.0 / np.sqrt(low), np.inf)
        elongation = np.where(peak, np.sqrt(high / low), np.inf)
        low_sure = low + 2.0 * sd_low
        sigma_sure = np.where(low_sure > 0, 1.0 / np.sqrt(low_sure), np.inf)
        d_sure = np.maximum(d - 2.0 * sd_d, 0.0)
        el_sure = np.where(m > d_sure, np.sqrt((m + d_sure) / (m - d_sure)), np.inf)
        half_split = np.where(high > 0, np.sqrt(np.maximum(2.0 * d, 0.0)) / high, 0.0)
        # the widest axis: the eigenvector of -H for its smallest eigenvalue, at angle atan2(.) / 2 + 90 deg
        angle = 0.5 * np.arctan2(-2.0 * h_uv, -(h_uu - h_vv)) + 0.5 * math.pi
    bad = ~np.isfinite(m)
    inf = np.full(n, np.inf)
    return ImageShape(sigma_major=np.where(bad, inf, sigma_major), elongation=np.where(bad, inf, elongation),
                      sigma_major_sure=np.where(bad, inf, sigma_sure), elongation_sure=np.where(bad, inf, el_sure),
                      axis=np.stack([np.cos(angle), np.sin(angle)], axis=1), half_split=np.nan_to_num(half_split))


def _single(fit: _Fit, sigma: float, max_width_ratio: float, max_elongation: float) -> np.ndarray:
    """(N,) False where a blob is not one particle image (step 6): longer than wide by more than
    ``max_elongation`` beyond the noise (two images merged into one maximum that would not split), wider
    than ``max_width_ratio`` times the hint's sigma, or on a ridge. A saturated (flat-topped) image is kept."""
    eff = math.sqrt(sigma * sigma + 1.0 / 12.0)  # a pixel-integrated image of the hint's sigma
    shape = fit.shape
    round_enough = (shape.elongation_sure <= max_elongation) | fit.fixed | fit.saturated
    small_enough = (shape.sigma_major_sure <= max_width_ratio * eff) | fit.saturated
    not_hot = shape.sigma_major >= HOT_SIGMA_PX  # sharper than any optical image along every axis: hot pixels
    return round_enough & small_enough & not_hot & ~fit.ridge


def image_size(path: Path) -> tuple[int, int] | None:
    """An image's size from its header, without decoding it.

    Args:
        path: The image file.

    Returns:
        (width, height); None when the header is not one Pillow reads (OpenCV may still decode the file).
        Beyond Pillow's decompression-bomb limit (179 MP), which refuses to read the header:
        ``(limit, 0)``, a size no rig declares.
    """
    import warnings

    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                return int(im.size[0]), int(im.size[1])
    except Image.DecompressionBombError:
        return 2 * int(Image.MAX_IMAGE_PIXELS or 0), 0
    except (UnidentifiedImageError, OSError, ValueError):
        return None


def read_image(path: Path, size: tuple[int, int] | None = None, camera: str = "") -> np.ndarray:
    """Read a particle image as it is stored (8 or 16 bit).

    Args:
        path: The image file.
        size: The expected (width, height), its camera's in rig.yaml; checked on the header before the
            image is decoded, so a huge image costs no memory. None: not checked.
        camera: The camera's name, for the error.

    Returns:
        The image.

    Raises:
        PartitionError: The file cannot be read, or has another size than ``size``.
    """
    import cv2

    def check(w: int, h: int) -> None:
        if size is not None and (w, h) != tuple(size):
            found = f"{w} x {h} px" if h else f"more than {w / 1e6:.0f} MP"
            raise PartitionError(path, f"the image is {found}, but {camera or 'its camera'}'s images are "
                                       f"{size[0]} x {size[1]} (rig.yaml cameras.{camera}.image_size)")

    if size is not None:
        header = image_size(path)
        if header is not None:
            check(*header)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise PartitionError(path, "not a readable image")
    check(img.shape[1], img.shape[0])
    return img


def detect_partition(patterns: dict[str, str], frames: list[int], options: DetectOptions,
                     sizes: Mapping[str, tuple[int, int]] | None = None) -> dict[str, np.ndarray]:
    """Detections of every camera in a partition's frames (a Dask task).

    Args:
        patterns: Camera -> image path pattern with ``{frame}``.
        frames: The partition's frames.
        options: How particle images are found (resolved per camera).
        sizes: Each camera's (width, height); an image of another size is refused. None: not checked.

    Returns:
        The contract's columns: frame, camera, u, v, intensity.

    Raises:
        PartitionError: An image cannot be read or has another size.
    """
    frame, camera, u, v, inten = [], [], [], [], []
    for f in frames:
        for cam, pattern in patterns.items():
            image = read_image(Path(pattern.format(frame=f)), None if sizes is None else sizes[cam], cam)
            uv, peak = detect_particles_in_image(image, options.for_camera(cam))
            frame.append(np.full(len(uv), f, np.int64))
            camera += [cam] * len(uv)
            u.append(uv[:, 0])
            v.append(uv[:, 1])
            inten.append(peak)
    cat = lambda a, dt=float: np.concatenate(a).astype(dt) if a else np.empty(0, dt)  # noqa: E731
    import pyarrow as pa

    return {"frame": cat(frame, np.int64), "camera": pa.array(camera, type=pa.string()),  # typed when empty
            "u": cat(u), "v": cat(v), "intensity": cat(inten)}


MAX_IMAGE_PIXELS = 40_000_000  # detection holds ~40 bytes per pixel at its peak (measured): ~1.6 GB an image
# of this size; larger images are refused (their own size, or their camera's in rig.yaml)


def _check_image_sizes(dataset: Any) -> dict[str, tuple[int, int]]:
    """Each imaged camera's (width, height) from rig.yaml, within MAX_IMAGE_PIXELS."""
    from ari_sfm.errors import AriSfmError

    sizes = {}
    for cam in dataset.images:
        w, h = (int(x) for x in dataset.cameras[cam].image_size)
        if w * h > MAX_IMAGE_PIXELS:
            raise AriSfmError(dataset.rig_path, f"cameras.{cam}.image_size: {w} x {h} px ({w * h / 1e6:.0f} MP) is "
                                                f"more than detect-particles handles ({MAX_IMAGE_PIXELS / 1e6:.0f} MP: "
                                                f"~40 bytes of memory per pixel): crop the images")
        sizes[cam] = (w, h)
    return sizes


def _image_stats(dataset: Any, frames: list[int]) -> str:
    """The key of a partition's images: a hash of each one's path, size and modification time, so a re-run
    makes a partition again when one of its images changed. AriSfmError naming a missing image."""
    import hashlib
    import json

    from ari_sfm.errors import AriSfmError

    stats = []
    for f in frames:
        for cam in dataset.images:
            path = dataset.image_path(cam, f)
            try:
                st = path.stat()
            except OSError:
                raise AriSfmError(dataset.rig_path, f"particles.images.{cam}: frame {f}: no such image {path}") \
                    from None
            if not path.is_file():
                raise AriSfmError(dataset.rig_path, f"particles.images.{cam}: frame {f}: not a file: {path}")
            stats.append([str(path), st.st_size, st.st_mtime_ns])
    return hashlib.sha256(json.dumps(stats).encode()).hexdigest()


def detect_options(dataset: Any, **overrides: Any) -> DetectOptions:
    """The options of a dataset's detection.

    Args:
        dataset: The particle dataset (:class:`~ari_sfm.io.particles.ParticleDataset`): rig.yaml's
            ``particles.diameter_px`` and ``particles.detect`` override the defaults.
        **overrides: The command line's options, overriding those (None: not given).

    Returns:
        The options.
    """
    from dataclasses import replace

    options = DetectOptions(diameter_px=dataset.diameter_px or DetectOptions.diameter_px)
    options = replace(options, **dataset.detect.given())
    return replace(options, **{k: v for k, v in overrides.items() if v is not None})


def detect_experiment(dataset_path: str | Path, out: str | Path, options: DetectOptions | None = None,
                      frames_per_partition: int = 20, workers: int = 0, scheduler: str | None = None,
                      progress: bool = False, worker_timeout_s: float | None = None) -> DetectSummary:
    """Detect the particle images of every frame of ``particles.images``.

    Writes OUT/particles.parquet (through OUT/parts/, resumable: a partition whose images changed is
    detected again) and OUT/detect-particles.json.

    Args:
        dataset_path: The particle dataset.
        out: The output folder (OUT); not the dataset's own folder.
        options: How particle images are found; None for :func:`detect_options` of the dataset.
        frames_per_partition: Frames per task and per partition file.
        workers: LocalCluster processes (0: this process).
        scheduler: An existing Dask scheduler's address, instead of ``workers``.
        progress: Show a progress bar.
        worker_timeout_s: How long a run waits with no Dask worker
            (:func:`ari_sfm.particles.engine.dask_client`).

    Returns:
        The summary (its to_json() is detect-particles.json).

    Raises:
        AriSfmError: Bad options, no images or frames in rig.yaml, a missing or oversized image, or no
            particle image in any image (blank images, or a threshold too high: nothing is written then
            but the partitions).
    """
    import os
    import time

    from tqdm import tqdm

    from ari_sfm.errors import AriSfmError
    from ari_sfm.io import write_json_atomic
    from ari_sfm.io.particles import load_particle_dataset
    from ari_sfm.particles.engine import (
        Partition,
        check_run_settings,
        check_workers,
        dask_client,
        frame_ranges,
        merge_partitions,
        run_partitions,
    )

    t0 = time.perf_counter()
    out = Path(out)
    check_workers(workers)
    if isinstance(frames_per_partition, bool) or not isinstance(frames_per_partition, int) or frames_per_partition < 1:
        raise AriSfmError("--frames-per-partition", f"must be a whole number >= 1 (got {frames_per_partition!r})")
    dataset = load_particle_dataset(dataset_path)
    if Path(os.path.realpath(out)) == Path(os.path.realpath(dataset.root)):
        raise AriSfmError(out, "-o/--out is the dataset folder: write the results elsewhere")
    if dataset.images is None:
        raise AriSfmError(dataset.rig_path, "particles.images is not given: no particle images to detect")
    if dataset.frames is None:
        raise AriSfmError(dataset.rig_path, "particles.frames is not given: no particle images to detect")
    if options is None:
        options = detect_options(dataset)
    first, last = dataset.frames
    sizes = _check_image_sizes(dataset)
    _image_stats(dataset, sorted({first, last}))  # the first and last images exist (a typo in frames: at once)
    patterns = dict(dataset.images)
    settings: dict[str, Any] = {
        "task": "detect-particles", "options": {k: getattr(options, k) for k in options.__dataclass_fields__},
        "frames": [first, last], "frames_per_partition": frames_per_partition, "images": patterns}
    out.mkdir(parents=True, exist_ok=True)
    check_run_settings(out, settings)
    partitions = (Partition(c[0], c[-1], (patterns, c, options, sizes), _image_stats(dataset, c))
                  for c in frame_ranges(first, last, frames_per_partition))
    total = -(-(last - first + 1) // frames_per_partition)
    with dask_client(workers, scheduler, worker_timeout_s) as client, \
            tqdm(total=total, disable=not progress, desc="detecting", unit="partition") as bar:
        paths = run_partitions(detect_partition, partitions, out, client, lambda p, s: bar.update(1))
    counts = dict.fromkeys(patterns, 0)
    rows = _count_detections(paths, counts)
    images = (last - first + 1) * len(patterns)
    if rows == 0:  # an earlier run's table in OUT (other images at the same paths) would contradict this
        for stale in (out / "particles.parquet", out / "detect-particles.json"):
            stale.unlink(missing_ok=True)
        raise AriSfmError(dataset.rig_path, f"particles.images: no particle image found in any of the {images} "
                                            f"images (frames {first}..{last}): blank images, or --threshold-sigma / "
                                            f"--min-peak too high (the partitions are in {out / 'parts'})")
    warnings = [f"{cam}: no particle image found in any of its {last - first + 1} images (blank, covered, or "
                f"another threshold needed)" for cam, n in counts.items() if n == 0]
    for w in warnings:
        log.warning(w)
    merge_partitions(paths, out / "particles.parquet")
    summary = DetectSummary(str(dataset.rig_path), (first, last), rows, counts,
                            time.perf_counter() - t0, workers if scheduler is None else None, scheduler,
                            settings["options"], tuple(warnings))
    write_json_atomic(out / "detect-particles.json", summary.to_json())
    return summary


def _count_detections(paths: list[Path], counts: dict[str, int]) -> int:
    """The partitions' rows, adding each camera's to ``counts`` (one partition's camera column at a time)."""
    import pyarrow.parquet as pq

    rows = 0
    for path in paths:
        cams = pq.read_table(path, columns=["camera"]).column("camera").to_numpy(zero_copy_only=False)
        names, n = np.unique(cams.astype(str), return_counts=True)
        for name, k in zip(names.tolist(), n.tolist()):
            counts[name] = counts.get(name, 0) + int(k)
        rows += len(cams)
    return rows

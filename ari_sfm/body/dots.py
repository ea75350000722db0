"""Bright dots in a real tank image: the marks of a 3D calibration body, found among walls and particles.

Per image (8- or 16-bit, or float):

1. background: a grey opening (erosion then dilation) with a disc wider than a dot (a dot vanishes,
   anything broader stays: walls, glare, an uneven light), smoothed; the signal is the image minus it;
2. noise: per tile of TILE_PX x TILE_PX the median and the MAD of the signal (the dots are too few to
   move them), interpolated over the image: a dot must stand ``threshold_sigma`` local noise sigmas above
   the local median, and at least ``min_contrast`` grey levels;
3. connected components (8-connected) of the pixels above it; per component its area, the second
   moments of its pixels (elongation: the ratio of the principal axes) and the intensity-weighted
   centroid of its signal (OpenCV pixel centres: (0, 0) is the centre of the top-left pixel);
4. limits: the equivalent diameter sqrt(4 area / pi) within [MIN_SIZE_RATIO, MAX_SIZE_RATIO] x the dot
   diameter (particles are smaller, glare is larger), elongation at most ``max_elongation`` (a wall's
   bright streak, or a dot merged with it, is long), not touching the image border (its centre would be
   cut).

What it cannot tell apart: a particle or a reflection of the size and shape of a dot. Those are left to
the identification (:mod:`ari_sfm.body.identify`), which takes only dots where the body predicts one.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

log = logging.getLogger(__name__)

TILE_PX = 64  # side of the tiles the local noise is measured in
MIN_SIZE_RATIO = 0.4  # equivalent diameter / dot diameter: smaller blobs are particles or noise
MAX_SIZE_RATIO = 2.5  # larger ones are glare, bubbles, or dots merged with something
DEFAULT_MIN_DIAMETER_PX = 2.5  # without a dot diameter: blobs of fewer pixels are noise
DEFAULT_BACKGROUND_PX = 31  # without a dot diameter: the opening's disc (a dot up to ~15 px)
MAD_TO_SIGMA = 1.4826
ALIKE_SIZE = 1.4  # dots alike: diameter within this factor of the reference dots' median
ALIKE_SIGNAL = 2.0  # and signal within this factor of theirs


@dataclass(frozen=True)
class DotOptions:
    """How dots are found (defaults suit saturated or unsaturated dots of 4-40 px)."""

    diameter_px: float | None = None  # the dots' diameter in the image; None: any size from 2.5 px
    threshold_sigma: float = 6.0  # a dot pixel stands this many local noise sigmas above the local median
    min_contrast: float = 0.05  # and at least this fraction of the image's dynamic range (its 99.9th percentile)
    max_elongation: float = 2.0  # principal axes' ratio of a dot's pixels (an oblique dot is an ellipse)


@dataclass(frozen=True)
class Dots:
    """Dots found in one image.

    Attributes:
        centres: (N, 2) OpenCV pixels.
        diameters_px: Equivalent diameters (N,), px.
        elongations: Ratios of the principal axes (N,).
        signal: Signal sums (N,): the grey levels above the background.
    """

    centres: np.ndarray
    diameters_px: np.ndarray
    elongations: np.ndarray
    signal: np.ndarray

    def __len__(self) -> int:
        return len(self.centres)


def as_float_image(image: np.ndarray) -> np.ndarray:
    """A single-channel float32 copy of an 8- or 16-bit (or float) image; colour is averaged."""
    image = np.asarray(image)
    if image.ndim == 3:
        image = image.mean(axis=2)
    if image.ndim != 2:
        raise ValueError(f"expected a 2-D grey image, got shape {image.shape}")
    return np.ascontiguousarray(image, dtype=np.float32)


def background_size_px(diameter_px: float | None) -> int:
    """The opening disc's diameter (odd, px): twice a dot's, at least 7."""
    if diameter_px is None:
        return DEFAULT_BACKGROUND_PX
    size = max(7, int(math.ceil(2.0 * diameter_px)))
    return size + 1 - size % 2


def signal_and_threshold(image: np.ndarray, diameter_px: float | None, options: DotOptions
                         ) -> tuple[np.ndarray, np.ndarray]:
    """The background-subtracted signal and the per-pixel threshold a dot pixel must exceed.

    Steps 1 and 2 of the module docstring.

    Args:
        image: Grey image (8- or 16-bit, or float; colour is averaged).
        diameter_px: The dots' diameter (px), which sizes the background's disc; None for the default disc.
        options: ``threshold_sigma`` and ``min_contrast`` are read.

    Returns:
        The signal and the threshold, each float32 of the image's shape.
    """
    img = as_float_image(image)
    size = background_size_px(diameter_px)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    background = cv2.morphologyEx(img, cv2.MORPH_OPEN, disc, borderType=cv2.BORDER_REPLICATE)
    background = cv2.GaussianBlur(background, (0, 0), size / 4.0)
    signal = img - background
    median, sigma = local_noise(signal)
    span = float(np.percentile(img, 99.9) - np.percentile(img, 0.1))
    threshold = median + np.maximum(options.threshold_sigma * sigma, options.min_contrast * max(span, 1e-12))
    return signal, threshold


def local_noise(signal: np.ndarray, tile: int = TILE_PX) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel the median and robust sigma of the signal in the surrounding tiles.

    Tile values are bilinearly interpolated; the sigma is 1.4826 MAD, at least the grey-level
    quantisation's 1/sqrt(12).

    Args:
        signal: The background-subtracted signal (H, W).
        tile: Side of the tiles (px).

    Returns:
        The median and the sigma, each float32 (H, W).
    """
    h, w = signal.shape
    ny, nx = max(1, h // tile), max(1, w // tile)
    ty, tx = h // ny, w // nx
    blocks = signal[: ny * ty, : nx * tx].reshape(ny, ty, nx, tx).transpose(0, 2, 1, 3).reshape(ny, nx, -1)
    med = np.median(blocks, axis=2)
    mad = np.median(np.abs(blocks - med[..., None]), axis=2)
    sigma = np.maximum(MAD_TO_SIGMA * mad, 1.0 / math.sqrt(12.0)).astype(np.float32)
    resize = lambda a: cv2.resize(a.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)  # noqa: E731
    return resize(med), resize(sigma)


def components(signal: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                               np.ndarray]:
    """Measure the 8-connected components of a mask.

    Args:
        signal: The background-subtracted signal (H, W), the centroids' weights.
        mask: Boolean (H, W), the pixels above the threshold.

    Returns:
        Per component: signal-weighted centres (N, 2) (OpenCV pixels), areas (N,) px, elongations (N,)
        (ratio of the principal axes), signal sums (N,), and whether it touches the image border (N,).
    """
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if count <= 1:
        empty = np.empty(0)
        return np.empty((0, 2)), empty, empty, empty, np.empty(0, bool)
    ys, xs = np.nonzero(labels)
    lab = labels[ys, xs] - 1
    n = count - 1
    wts = np.maximum(signal[ys, xs].astype(np.float64), 1e-9)
    xs_f, ys_f = xs.astype(np.float64), ys.astype(np.float64)
    area = np.bincount(lab, minlength=n).astype(float)
    total = np.bincount(lab, wts, n)
    centres = np.stack([np.bincount(lab, wts * xs_f, n) / total, np.bincount(lab, wts * ys_f, n) / total], axis=1)
    mx, my = np.bincount(lab, xs_f, n) / area, np.bincount(lab, ys_f, n) / area
    cxx = np.bincount(lab, xs_f * xs_f, n) / area - mx * mx + 1.0 / 12.0  # + a pixel's own extent
    cyy = np.bincount(lab, ys_f * ys_f, n) / area - my * my + 1.0 / 12.0
    cxy = np.bincount(lab, xs_f * ys_f, n) / area - mx * my
    half_sum, root = 0.5 * (cxx + cyy), np.sqrt(0.25 * (cxx - cyy) ** 2 + cxy ** 2)
    elongation = np.sqrt((half_sum + root) / np.maximum(half_sum - root, 1e-12))
    h, w = mask.shape
    x0, y0, bw, bh = stats[1:, 0], stats[1:, 1], stats[1:, 2], stats[1:, 3]
    border = (x0 == 0) | (y0 == 0) | (x0 + bw == w) | (y0 + bh == h)
    return centres, area, elongation, total, border


def find_dots(image: np.ndarray, options: DotOptions = DotOptions()) -> Dots:
    """Find the bright dots of an image (the steps of the module docstring).

    Args:
        image: Grey image (8- or 16-bit, or float; colour is averaged).
        options: How dots are found.

    Returns:
        The dots found.
    """
    signal, threshold = signal_and_threshold(image, options.diameter_px, options)
    centres, area, elongation, total, border = components(signal, signal > threshold)
    diameter = np.sqrt(4.0 * area / math.pi)
    if options.diameter_px is None:
        low, high = DEFAULT_MIN_DIAMETER_PX, DEFAULT_BACKGROUND_PX / 2.0
    else:
        low, high = MIN_SIZE_RATIO * options.diameter_px, MAX_SIZE_RATIO * options.diameter_px
    keep = (diameter >= low) & (diameter <= high) & (elongation <= options.max_elongation) & ~border
    log.debug("%d bright blobs, %d dots (diameter %.3g-%.3g px, elongation <= %g)", len(area), int(keep.sum()),
              low, high, options.max_elongation)
    return Dots(centres[keep], diameter[keep], elongation[keep], total[keep])


def dot_diameter_at(image: np.ndarray, pixels: np.ndarray, search_px: float,
                    options: DotOptions = DotOptions()) -> float | None:
    """The dots' diameter measured at clicked dots.

    Used when the target declares no dot size. The background's disc starts at DEFAULT_BACKGROUND_PX and
    grows while the dots found fill half of it.

    Args:
        image: Grey image.
        pixels: Clicked dots (N, 2), OpenCV pixels.
        search_px: The blob nearest to each pixel counts if within this distance (px).
        options: ``threshold_sigma``, ``min_contrast`` and ``max_elongation`` are read.

    Returns:
        The median diameter (px) of the blobs found, or None if none is found.
    """
    img = as_float_image(image)
    size, diameter = DEFAULT_BACKGROUND_PX, None
    for _ in range(3):
        diameter = _median_blob_at(img, np.asarray(pixels, float).reshape(-1, 2), search_px, size, options)
        if diameter is None or 2.5 * diameter <= size:
            break
        size = background_size_px(1.25 * diameter)
    return diameter


def _median_blob_at(img: np.ndarray, pixels: np.ndarray, search_px: float, size: int,
                    options: DotOptions) -> float | None:
    h, w = img.shape
    margin = int(math.ceil(search_px)) + size
    found = []
    for u, v in pixels:
        x0, x1 = max(0, int(u) - margin), min(w, int(u) + margin + 1)
        y0, y1 = max(0, int(v) - margin), min(h, int(v) + margin + 1)
        if x1 - x0 < 8 or y1 - y0 < 8:
            continue
        crop = img[y0:y1, x0:x1]
        signal, threshold = signal_and_threshold(crop, size / 2.0, options)
        centres, area, elongation, _, _ = components(signal, signal > threshold)
        ok = (np.sqrt(4.0 * area / math.pi) >= DEFAULT_MIN_DIAMETER_PX) & (elongation <= options.max_elongation)
        if not ok.any():
            continue
        d = np.hypot(centres[:, 0] + x0 - u, centres[:, 1] + y0 - v)
        d[~ok] = np.inf
        k = int(np.argmin(d))
        if d[k] <= search_px:
            found.append(math.sqrt(4.0 * area[k] / math.pi))
    return float(np.median(found)) if found else None


def alike(dots: Dots, reference: np.ndarray) -> np.ndarray:
    """Which dots have the size and brightness of reference dots (a body's own, not particles or glints).

    Args:
        dots: The dots.
        reference: Indices into ``dots`` of the reference dots.

    Returns:
        (N,) bool: diameter within ALIKE_SIZE and signal within ALIKE_SIGNAL of the reference's medians
        (all False if ``reference`` is empty).
    """
    if not len(reference):
        return np.zeros(len(dots), bool)
    d = float(np.median(dots.diameters_px[reference]))
    g = float(np.median(dots.signal[reference]))
    return ((dots.diameters_px >= d / ALIKE_SIZE) & (dots.diameters_px <= d * ALIKE_SIZE)
            & (dots.signal >= g / ALIKE_SIGNAL) & (dots.signal <= g * ALIKE_SIGNAL))

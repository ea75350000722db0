"""The local background of a particle frame and its noise, robust to particles, blobs and hot pixels.

Background: a grey opening with a disc wider than a particle image (a
particle, a hot pixel or a thin streak is removed, anything wider than the
disc, a big blob, a glare band, the uneven illumination, is kept), smoothed by
a box of the disc's size; the opening sits on the noise's lower envelope, so
the median of the residual in blocks of ``block_px`` (particles are a minority
of a block's pixels) is added back. Noise: in the same blocks, the standard
deviation of the residual clipped at 3 robust sigmas (the MAD, floored at two
grey levels so that an 8-bit frame whose dark background sits on one or two
levels still has a noise), interpolated between block centres. A few bright
blobs or a dense cloud of particles thus move neither the background nor the
noise of the rest of the frame, as a global median and MAD would.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

LINE_LENGTH = 1.7  # the line segments of the opening, in opening discs
LINE_DIRECTIONS = 8  # their directions over 180 degrees
_VARIANT: dict = {}
HIGH_PASS_GAIN = math.sqrt(1.25)  # the noise of a pixel minus its four neighbours' mean, per unit noise
CLIP_SIGMAS = 3.0  # the noise: residuals within this many robust sigmas of the block's median
CLIP_FLOOR = 2.0  # and at least this many grey level steps (quantised dark frames: the MAD can be 0)
CLIPPED_STD_FACTOR = 0.9866  # std of a unit Gaussian clipped at +-3 sigma (sqrt of 0.97333)


def opening_size(diameter_px: float) -> int:
    """The opening's disc (odd, px): wider than a particle image with its faint skirt."""
    return 2 * int(math.ceil(1.25 * diameter_px)) + 1


@dataclass(frozen=True)
class Background:
    """A frame's local background and the noise about it, per pixel."""

    level: np.ndarray  # (h, w) float32
    noise: np.ndarray  # (h, w) float32: the standard deviation of a pixel about the level


def estimate_background(img: np.ndarray, diameter_px: float, block_px: int, quantum: float) -> Background:
    """The background and noise of a grey float32 image (see the module docstring); ``quantum``: the grey
    level step (1 for integer images, 0 for float ones)."""
    import cv2

    opened = None
    for element in structuring_elements(diameter_px):
        o = cv2.morphologyEx(img, cv2.MORPH_OPEN, element, borderType=cv2.BORDER_REPLICATE)
        opened = o if opened is None else np.maximum(opened, o, out=opened)
    if _VARIANT.get("blur"):
        k = opening_size(diameter_px)
        opened = cv2.blur(opened, (k, k), borderType=cv2.BORDER_REPLICATE)
    residual = img - opened
    grid = BlockGrid(img.shape, block_px)
    offset = grid.values(residual, "median", quantum)
    level = opened + grid.interpolate(offset)
    block_noise = grid.values(_pixel_differences(img), "noise", quantum) / HIGH_PASS_GAIN
    block_level = grid.values(level, "median", quantum)
    a, b = _noise_model(block_level.ravel(), block_noise.ravel() ** 2, quantum)
    noise = np.sqrt(np.maximum(a + b * level, max(quantum * quantum / 12.0, 1e-12)))
    noise = np.maximum(noise, grid.interpolate(block_noise))
    return Background(level=level, noise=noise.astype(np.float32))


def _pixel_differences(img: np.ndarray) -> np.ndarray:
    """Each pixel minus the mean of its four neighbours: white noise of sigma s gives sigma s * HIGH_PASS_GAIN,
    a smooth background nothing."""
    import cv2

    kernel = np.array([[0, -0.25, 0], [-0.25, 1.0, -0.25], [0, -0.25, 0]], np.float32)
    return cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REFLECT)


def _noise_model(level: np.ndarray, variance: np.ndarray, quantum: float) -> tuple[float, float]:
    """A sensor's noise: variance = a + b level (read noise and shot noise), fitted over the blocks
    (twice: the blocks more than twice the first fit's variance, structure rather than noise, left out)."""
    keep = np.isfinite(variance) & np.isfinite(level)
    a, b = float(np.median(variance[keep])) if keep.any() else 0.0, 0.0
    for _ in range(2):
        if keep.sum() < 3 or np.ptp(level[keep]) <= max(quantum, 1e-9):
            break
        b, a = np.polyfit(level[keep], variance[keep], 1)
        b = max(float(b), 0.0)
        a = float(np.median(variance[keep] - b * level[keep]))
        keep &= variance <= 2.0 * np.maximum(a + b * level, 1e-12)
    return a, b


@lru_cache(maxsize=8)
def structuring_elements(diameter_px: float) -> tuple[np.ndarray, ...]:
    """The opening's elements: a disc of :func:`opening_size` and LINE_DIRECTIONS line segments of
    LINE_LENGTH discs (a streak, however thin, holds one of them; a particle image holds none)."""
    import cv2

    k = opening_size(diameter_px)
    length = int(round(LINE_LENGTH * k)) | 1
    c = length // 2
    t = np.linspace(-c, c, 4 * length)
    lines = []
    for angle in np.arange(LINE_DIRECTIONS) * math.pi / LINE_DIRECTIONS:
        line = np.zeros((length, length), np.uint8)
        line[np.rint(c + t * math.sin(angle)).astype(int), np.rint(c + t * math.cos(angle)).astype(int)] = 1
        lines.append(line)
    return (cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)), *lines)


class BlockGrid:
    """Blocks of ~``block_px`` covering a frame; a statistic per block, bilinear between block centres."""

    def __init__(self, shape: tuple[int, int], block_px: int) -> None:
        h, w = shape
        b = int(max(4, min(block_px, h, w)))
        self.shape = (h, w)
        self.ny, self.nx = max(1, round(h / b)), max(1, round(w / b))
        self.ys = np.linspace(0, h, self.ny + 1).astype(int)
        self.xs = np.linspace(0, w, self.nx + 1).astype(int)

    def values(self, img: np.ndarray, what: str, quantum: float = 1.0) -> np.ndarray:
        """(ny, nx) the statistic (``median`` or ``noise``) of each block of ``img``."""
        out = np.empty((self.ny, self.nx), np.float32)
        for i in range(self.ny):
            rows = img[self.ys[i]:self.ys[i + 1]]
            for j in range(self.nx):
                out[i, j] = _statistic(rows[:, self.xs[j]:self.xs[j + 1]].ravel(), what, quantum)
        return out

    def interpolate(self, values: np.ndarray) -> np.ndarray:
        """(h, w) float32: ``values`` at the block centres, bilinear between them, constant beyond."""
        import cv2

        h, w = self.shape
        if self.ny == 1 and self.nx == 1:
            return np.full((h, w), values[0, 0], np.float32)
        cy = 0.5 * (self.ys[:-1] + self.ys[1:]) - 0.5
        cx = 0.5 * (self.xs[:-1] + self.xs[1:]) - 0.5
        fy = np.interp(np.arange(h), cy, np.arange(self.ny)).astype(np.float32)
        fx = np.interp(np.arange(w), cx, np.arange(self.nx)).astype(np.float32)
        map_x, map_y = np.meshgrid(fx, fy)
        return cv2.remap(np.asarray(values, np.float32), map_x, map_y, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)


def _statistic(values: np.ndarray, what: str, quantum: float) -> float:
    med = float(np.median(values))
    if what == "median":
        return med
    mad = 1.4826 * float(np.median(np.abs(values - med)))
    half = max(CLIP_SIGMAS * mad, CLIP_FLOOR * quantum)
    kept = values[np.abs(values - med) <= half]
    floor = max(quantum / math.sqrt(12.0), 1e-6)  # a flat block: the quantisation's own noise
    if len(kept) < 2:
        return max(mad, floor)
    return max(float(kept.std()) / (CLIPPED_STD_FACTOR if half == CLIP_SIGMAS * mad else 1.0), floor)

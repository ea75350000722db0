"""The local background of a particle frame and its noise, robust to particles, blobs and hot pixels.

Background: a grey opening with a disc wider than a particle image (a
particle, a hot pixel, anything narrower than the disc is removed; the uneven
illumination, glare, a big blob are kept); the opening sits on the noise's
lower envelope, so the median of the residual in blocks of ``block_px``
(particles are a minority of a block's pixels) is added back. Noise: per
block, the standard deviation of each pixel minus the mean of its four
neighbours (a smooth background gives nothing; clipped at 3 robust sigmas,
or two grey levels so that an 8-bit frame whose dark background sits on one
or two levels still has a noise), and a sensor's noise model fitted over the
blocks (variance = read + gain x level: the shot noise on a bright blob's
skirt), the larger of the two at each pixel. A few bright blobs or a dense
cloud of particles thus move neither the background nor the noise of the rest
of the frame, as a global median and MAD would.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

HIGH_PASS_GAIN = math.sqrt(1.25)  # the noise of a pixel minus its four neighbours' mean, per unit noise
BLOCK_SAMPLE_STEP = 2  # a block's statistics from every second pixel along rows and columns
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

    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (opening_size(diameter_px),) * 2)
    opened = cv2.morphologyEx(img, cv2.MORPH_OPEN, disc, borderType=cv2.BORDER_REPLICATE)
    grid = BlockGrid(img.shape, block_px)
    level = opened + grid.interpolate(grid.values(img - opened, "median", quantum))
    block_noise = grid.values(_pixel_differences(img), "noise", quantum) / HIGH_PASS_GAIN
    block_level = grid.at_centres(level)
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


class BlockGrid:
    """Blocks of ``block_px`` (fewer, overlapping a little, where the frame is not a whole number of them)
    covering a frame; a statistic per block, bilinear between block centres."""

    def __init__(self, shape: tuple[int, int], block_px: int) -> None:
        h, w = shape
        self.shape = (h, w)
        self.by, self.bx = int(max(2, min(block_px, h))), int(max(2, min(block_px, w)))
        ny, nx = max(1, math.ceil(h / self.by)), max(1, math.ceil(w / self.bx))
        self.y0 = np.rint(np.linspace(0, h - self.by, ny)).astype(int)  # first row of each block
        self.x0 = np.rint(np.linspace(0, w - self.bx, nx)).astype(int)

    def values(self, img: np.ndarray, what: str, quantum: float = 1.0) -> np.ndarray:
        """(ny, nx) the statistic of each block of ``img``: ``median``, or ``noise`` (the standard deviation
        of the values within CLIP_SIGMAS robust sigmas, or CLIP_FLOOR grey level steps, of the median)."""
        step = BLOCK_SAMPLE_STEP if min(self.by, self.bx) >= 8 * BLOCK_SAMPLE_STEP else 1
        rows = self.y0[:, None] + np.arange(0, self.by, step)
        cols = self.x0[:, None] + np.arange(0, self.bx, step)
        blocks = img[rows[:, :, None, None], cols[None, None, :, :]]  # (ny, by, nx, bx)
        values = blocks.transpose(0, 2, 1, 3).reshape(len(self.y0), len(self.x0), -1).astype(np.float32)
        med = np.median(values, axis=-1)
        if what == "median":
            return med
        dev = np.abs(values - med[..., None])
        mad = 1.4826 * np.median(dev, axis=-1)
        robust = CLIP_SIGMAS * mad >= CLIP_FLOOR * quantum
        half = np.where(robust, CLIP_SIGMAS * mad, CLIP_FLOOR * quantum)
        kept = dev <= half[..., None]
        count = np.maximum(kept.sum(axis=-1), 1)
        mean = np.where(kept, values, 0.0).sum(axis=-1) / count
        var = np.where(kept, (values - mean[..., None]) ** 2, 0.0).sum(axis=-1) / np.maximum(count - 1, 1)
        std = np.sqrt(var) / np.where(robust, CLIPPED_STD_FACTOR, 1.0)
        return np.maximum(std, max(quantum / math.sqrt(12.0), 1e-6)).astype(np.float32)  # flat: quantisation

    def at_centres(self, img: np.ndarray) -> np.ndarray:
        """(ny, nx) ``img`` at the pixel nearest each block's centre."""
        cy = np.rint(self.y0 + 0.5 * (self.by - 1)).astype(int)
        cx = np.rint(self.x0 + 0.5 * (self.bx - 1)).astype(int)
        return img[cy[:, None], cx[None, :]]

    def interpolate(self, values: np.ndarray) -> np.ndarray:
        """(h, w) float32: ``values`` at the block centres, bilinear between them, constant beyond."""
        import cv2

        h, w = self.shape
        if values.size == 1:
            return np.full((h, w), float(values.ravel()[0]), np.float32)
        cy = self.y0 + 0.5 * (self.by - 1)
        cx = self.x0 + 0.5 * (self.bx - 1)
        fy = np.interp(np.arange(h), cy, np.arange(len(cy))).astype(np.float32)
        fx = np.interp(np.arange(w), cx, np.arange(len(cx))).astype(np.float32)
        map_x, map_y = np.meshgrid(fx, fy)
        return cv2.remap(np.asarray(values, np.float32), map_x, map_y, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)

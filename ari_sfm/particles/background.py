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
of the frame.
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
    typical_noise: float = 0.0  # the median of the blocks' noise: the frame's noise where nothing is lit


def estimate_background(img: np.ndarray, diameter_px: float, block_px: int, quantum: float,
                        source: np.ndarray | None = None) -> Background:
    """The background and noise of a grey image (the method is in the module docstring).

    Args:
        img: Grey image (h, w), float32.
        diameter_px: A particle image's diameter (px); sizes the opening's disc (:func:`opening_size`).
        block_px: Side of the blocks the statistics are taken in (px).
        quantum: The grey level step (1 for integer images, 0 for float ones).
        source: The same image in its integer type (uint8 or uint16: the opening is exact and faster
            there), or None.

    Returns:
        The level and noise per pixel, and the frame's typical noise.
    """
    import cv2

    from ari_sfm.particles.detect_kernels import block_statistics, level_and_noise

    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (opening_size(diameter_px),) * 2)
    if source is not None and source.dtype in (np.uint8, np.uint16) and source.shape == img.shape:
        opened = cv2.morphologyEx(source, cv2.MORPH_OPEN, disc, borderType=cv2.BORDER_REPLICATE)
        opened = opened.astype(np.float32)
    else:
        opened = cv2.morphologyEx(img, cv2.MORPH_OPEN, disc, borderType=cv2.BORDER_REPLICATE)
    grid = BlockGrid(img.shape, block_px)
    block_median, block_noise = block_statistics(img, opened, grid.y0, grid.x0, grid.by, grid.bx, grid.step,
                                                 float(quantum), CLIP_SIGMAS, CLIP_FLOOR, CLIPPED_STD_FACTOR,
                                                 HIGH_PASS_GAIN)
    cy, cx = grid.centres()
    py, px = np.rint(cy).astype(int), np.rint(cx).astype(int)  # the pixel nearest each block's centre
    level_at_centres = opened[py[:, None], px[None, :]] + _bilinear(block_median, cy, cx, py, px)
    a, b = _noise_model(level_at_centres.ravel(), block_noise.ravel().astype(float) ** 2, quantum)
    level, noise = level_and_noise(opened, block_median, block_noise, cy, cx, a, b,
                                   max(quantum * quantum / 12.0, 1e-12))
    return Background(level=level, noise=noise, typical_noise=float(np.median(block_noise)))


def _bilinear(values: np.ndarray, cy: np.ndarray, cx: np.ndarray, py: np.ndarray, px: np.ndarray) -> np.ndarray:
    """(len(py), len(px)) ``values`` at the block centres, bilinear between them (constant beyond), at rows
    ``py`` and columns ``px``."""
    def axis(p: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        f = np.interp(p, c, np.arange(len(c), dtype=float))
        lo = np.clip(np.floor(f).astype(int), 0, max(len(c) - 2, 0))
        return lo, np.minimum(lo + 1, len(c) - 1), f - lo

    i0, i1, fy = axis(py, cy)
    j0, j1, fx = axis(px, cx)
    fy, fx = fy[:, None], fx[None, :]
    return ((1 - fy) * ((1 - fx) * values[i0][:, j0] + fx * values[i0][:, j1])
            + fy * ((1 - fx) * values[i1][:, j0] + fx * values[i1][:, j1]))


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
    """Blocks of ``block_px`` covering a frame; a statistic per block, bilinear between block centres.

    Where the frame is not a whole number of blocks, the blocks overlap a little.
    """

    def __init__(self, shape: tuple[int, int], block_px: int) -> None:
        h, w = shape
        self.shape = (h, w)
        self.by, self.bx = int(max(2, min(block_px, h))), int(max(2, min(block_px, w)))
        ny, nx = max(1, math.ceil(h / self.by)), max(1, math.ceil(w / self.bx))
        self.y0 = np.rint(np.linspace(0, h - self.by, ny)).astype(np.int64)  # first row of each block
        self.x0 = np.rint(np.linspace(0, w - self.bx, nx)).astype(np.int64)
        # a block's statistics from every second pixel along rows and columns (every pixel in small blocks)
        self.step = BLOCK_SAMPLE_STEP if min(self.by, self.bx) >= 8 * BLOCK_SAMPLE_STEP else 1

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """The block centres' rows and columns (float)."""
        return self.y0 + 0.5 * (self.by - 1), self.x0 + 0.5 * (self.bx - 1)

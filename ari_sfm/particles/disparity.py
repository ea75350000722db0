"""Disparity maps of volume self-calibration (Wieneke 2008), through the window.

A matched particle has an image in each of 3-4 cameras; its point is triangulated with the
calibration's own (exact) model. Its *disparity* in camera c is ``uv_detected - project_c(X)``
(pixels): zero up to the detection noise when the calibration is right, a smooth field over the
volume when a camera has moved since the target calibration.

The volume is cut into cells (e.g. 3 x 3 x 3); per camera and cell the map holds the robust
centre of the disparities of the particles in that cell and how many supported it. Loose matches
(a few px of tolerance) contain ghosts whose disparities spread over the tolerance disc, while the
true matches pile up at the camera's systematic offset: the centre is the peak of a 2-D histogram
refined by a flat-kernel mean shift (``peak_radius_px``), not the mean, so ghosts do not bias it.
A match is an *inlier* when, in every camera it uses, its disparity lies within the peak radius
of its cell's centre.

RMS per camera: ``sqrt(mean |d|^2)`` over the inliers (pixel distances, PHYSICS.md); with the
right calibration and noise sigma per coordinate it is about ``1.1 sigma`` for 4 cameras.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..calibration import Calibration

HISTOGRAM_BIN_PX = 0.1  # the peak search's histogram bins (then refined by mean shift)
MEAN_SHIFT_STEPS = 20
MAX_HISTOGRAM_PX = 20.0  # the peak is searched within this many px of zero (drifts are a few px)
MIN_PEAK_COUNT = 3  # fewer supporting particles: the cell has no estimate (NaN, count 0)


@dataclass(frozen=True)
class Cells:
    """An axis-aligned box of the world cut into ``shape`` = (nx, ny, nz) cells."""

    lower: np.ndarray  # (3,) mm
    upper: np.ndarray  # (3,) mm
    shape: tuple[int, int, int]

    @staticmethod
    def around(xyz: np.ndarray, shape: Sequence[int], quantile: float = 0.005) -> "Cells":
        """The box of the points (their ``quantile`` and ``1 - quantile``: stray ghosts ignored)."""
        finite = xyz[np.isfinite(xyz).all(axis=1)]
        lower, upper = np.quantile(finite, quantile, axis=0), np.quantile(finite, 1.0 - quantile, axis=0)
        return Cells(lower, np.maximum(upper, lower + 1e-6), tuple(int(s) for s in shape))

    @property
    def count(self) -> int:
        return int(np.prod(self.shape))

    def index(self, xyz: np.ndarray) -> np.ndarray:
        """Flat cell index (N,) of points (N, 3) (x fastest); points outside the box go to the nearest cell."""
        n = np.asarray(self.shape)
        with np.errstate(invalid="ignore"):
            frac = (xyz - self.lower) / (self.upper - self.lower)
        ijk = np.clip(np.floor(np.nan_to_num(frac, nan=0.0) * n).astype(int), 0, n - 1)
        return ijk[:, 0] + n[0] * (ijk[:, 1] + n[1] * ijk[:, 2])

    def centres(self) -> np.ndarray:
        """(count, 3) cell centres in the order of :meth:`index`."""
        n = np.asarray(self.shape)
        k = np.arange(self.count)
        ijk = np.stack([k % n[0], (k // n[0]) % n[1], k // (n[0] * n[1])], axis=1)
        return self.lower + (ijk + 0.5) / n * (self.upper - self.lower)

    def to_json(self) -> dict[str, Any]:
        return {"lower_mm": self.lower.tolist(), "upper_mm": self.upper.tolist(), "shape": list(self.shape)}


@dataclass(frozen=True)
class ParticleSet:
    """Matched particles: their images and the points triangulated from them."""

    pixels: np.ndarray  # (P, C, 2) detected image centres, NaN where a camera is not used
    xyz: np.ndarray  # (P, 3) world, triangulated with the calibration the disparities refer to
    frame: np.ndarray  # (P,) frame number

    @property
    def used(self) -> np.ndarray:
        """(P, C) whether camera c's image is part of the match."""
        return np.isfinite(self.pixels).all(axis=2)


@dataclass(frozen=True)
class DisparityMap:
    """Per camera and cell: the robust disparity (px) and its support; per match: inlier or not."""

    cameras: tuple[str, ...]
    cells: Cells
    vector_px: np.ndarray  # (C, K, 2) robust centre per camera and cell (NaN: too few particles)
    count: np.ndarray  # (C, K) particles supporting the centre (within peak_radius_px)
    total: np.ndarray  # (C, K) matched particle images in the cell
    inlier: np.ndarray  # (P,) matches consistent with their cells' peaks in every camera they use
    rms_px: np.ndarray  # (C,) RMS disparity over the inliers
    peak_radius_px: float

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"peak_radius_px": self.peak_radius_px, "inliers": int(self.inlier.sum()),
                               "matches": int(len(self.inlier)), "cameras": {}}
        for c, name in enumerate(self.cameras):
            out["cameras"][name] = {
                "rms_px": float(self.rms_px[c]),
                "vector_px": [[None if not np.isfinite(v).all() else float(v[0]),
                               None if not np.isfinite(v).all() else float(v[1])] for v in self.vector_px[c]],
                "count": self.count[c].astype(int).tolist(),
                "total": self.total[c].astype(int).tolist(),
            }
        return out


def particle_disparities(calibration: Calibration, particles: ParticleSet) -> np.ndarray:
    """(P, C, 2) detected minus reprojected pixels (NaN where a camera is not used or X is invalid)."""
    names = list(calibration.cameras)
    out = np.full(particles.pixels.shape, np.nan)
    used = particles.used & np.isfinite(particles.xyz).all(axis=1)[:, None]
    for c, name in enumerate(names):
        m = used[:, c]
        if m.any():
            out[m, c] = particles.pixels[m, c] - calibration.project_world(name, particles.xyz[m])
    return out


def _peak(d: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Robust centre of 2-D disparities d (n, 2): the top of the smoothed histogram, then a flat-kernel mean
    shift of the given radius. Returns the centre and the mask of the points within the radius."""
    extent = min(float(np.quantile(np.abs(d), 0.9)), MAX_HISTOGRAM_PX) + radius  # far strays cannot be the peak
    bins = max(3, int(np.ceil(2 * extent / HISTOGRAM_BIN_PX)))
    hist, xe, ye = np.histogram2d(d[:, 0], d[:, 1], bins=bins, range=[[-extent, extent], [-extent, extent]])
    from scipy.ndimage import gaussian_filter

    # a Gaussian (not a box: a box's plateau has no single top) of half the kernel radius
    smooth = gaussian_filter(hist, sigma=max(1.0, 0.5 * radius / HISTOGRAM_BIN_PX), mode="constant")
    i, j = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    centre = np.array([0.5 * (xe[i] + xe[i + 1]), 0.5 * (ye[j] + ye[j + 1])])
    for _ in range(MEAN_SHIFT_STEPS):
        inside = np.einsum("ni,ni->n", d - centre, d - centre) <= radius * radius
        if not inside.any():
            break
        new = d[inside].mean(axis=0)
        moved = float(np.linalg.norm(new - centre))
        centre = new
        if moved < 1e-4 * radius:
            break
    inside = np.einsum("ni,ni->n", d - centre, d - centre) <= radius * radius
    return centre, inside


def disparity_map(cameras: Sequence[str], cells: Cells, particles: ParticleSet, disparities: np.ndarray,
                  peak_radius_px: float) -> DisparityMap:
    """Robust per-cell disparity of every camera (module docstring) and the inlier matches."""
    C, K = len(cameras), cells.count
    cell = cells.index(particles.xyz)
    valid = np.isfinite(disparities).all(axis=2)
    vector = np.full((C, K, 2), np.nan)
    count = np.zeros((C, K), int)
    total = np.zeros((C, K), int)
    consistent = np.ones(valid.shape, dtype=bool)  # (P, C): within the peak where used
    for c in range(C):
        for k in range(K):
            sel = np.flatnonzero(valid[:, c] & (cell == k))
            total[c, k] = len(sel)
            if len(sel) < MIN_PEAK_COUNT:
                consistent[sel, c] = False
                continue
            centre, inside = _peak(disparities[sel, c], peak_radius_px)
            if inside.sum() < MIN_PEAK_COUNT:
                consistent[sel, c] = False
                continue
            vector[c, k], count[c, k] = centre, int(inside.sum())
            consistent[sel[~inside], c] = False
    inlier = (consistent | ~valid).all(axis=1) & valid.any(axis=1)
    rms = np.full(C, np.nan)
    for c in range(C):
        m = inlier & valid[:, c]
        if m.any():
            rms[c] = float(np.sqrt(np.mean(np.einsum("ni,ni->n", disparities[m, c], disparities[m, c]))))
    return DisparityMap(tuple(cameras), cells, vector, count, total, inlier, rms, float(peak_radius_px))

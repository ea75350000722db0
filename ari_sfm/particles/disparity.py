"""Disparity maps of volume self-calibration (Wieneke 2008), through the window.

A matched particle has an image in each of 3-4 cameras; its point is triangulated with the
calibration's own (exact) model. Its *disparity* in camera c is ``uv_detected - project_c(X)``
(pixels): zero up to the detection noise when the calibration is right, a smooth field over the
volume when a camera has moved since the target calibration.

The volume is cut into cells (e.g. 3 x 3 x 3); per camera and cell the map holds the robust
centre of the disparities of the particles in that cell and how many supported it. Loose matches
(a few px of tolerance) are mostly ghosts, whose disparities spread over the tolerance disc, while
the true matches pile up at each camera's systematic offset. The peak is searched in all cameras
at once: the match with the most others within ``peak_radius_px`` in every camera they share,
refined by a flat-kernel mean shift (a ghost may land near the peak in one camera, almost never in
all). A match is an *inlier* when, in every
camera it uses, its disparity lies within the peak radius of its cell's centre.

RMS per camera: ``sqrt(mean |d|^2)`` over the inliers (pixel distances, PHYSICS.md); with the
right calibration and noise sigma per coordinate it is about ``1.1 sigma`` for 4 cameras.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..calibration.record import Calibration
from .disparity_kernels import joint_counts, joint_counts_against

MEAN_SHIFT_STEPS = 20
GLOBAL_SAMPLE = 4000  # matches the whole-volume peak is searched among
PEAK_CANDIDATES = 1500  # matches whose neighbours are counted in the peak search (a random subset beyond)
MIN_PEAK_COUNT = 3  # fewer supporting particles: the cell has no estimate (NaN, count 0)


@dataclass(frozen=True)
class Cells:
    """An axis-aligned box of the world cut into ``shape`` = (nx, ny, nz) cells."""

    lower: np.ndarray  # (3,) mm
    upper: np.ndarray  # (3,) mm
    shape: tuple[int, int, int]

    @staticmethod
    def around(xyz: np.ndarray, shape: Sequence[int], quantile: float = 0.005) -> Cells:
        """The box of the points, stray ghosts ignored.

        Args:
            xyz: Points (N, 3), world, mm (non-finite rows ignored).
            shape: Cells along x, y, z.
            quantile: The box runs from the points' ``quantile`` to their ``1 - quantile`` on each axis.

        Returns:
            The cells.
        """
        finite = xyz[np.isfinite(xyz).all(axis=1)]
        lower, upper = np.quantile(finite, quantile, axis=0), np.quantile(finite, 1.0 - quantile, axis=0)
        nx, ny, nz = (int(s) for s in shape)
        return Cells(lower, np.maximum(upper, lower + 1e-6), (nx, ny, nz))

    @property
    def count(self) -> int:
        """The number of cells."""
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
    """Each match's disparities: detected minus reprojected pixels.

    Args:
        calibration: The calibration the points were triangulated with (its camera order is the columns').
        particles: The matched particles.

    Returns:
        (P, C, 2) px; NaN where a camera is not used or the point is not finite.
    """
    names = list(calibration.cameras)
    out = np.full(particles.pixels.shape, np.nan)
    used = particles.used & np.isfinite(particles.xyz).all(axis=1)[:, None]
    for c, name in enumerate(names):
        m = used[:, c]
        if m.any():
            out[m, c] = particles.pixels[m, c] - calibration.project_world(name, particles.xyz[m])
    return out


def _joint_distance(d: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(n,) largest pixel distance over the cameras a match uses between its disparities d (n, C, 2) and
    a centre (C, 2) (cameras where the centre is NaN are not compared)."""
    diff = np.linalg.norm(d - centre[None], axis=2)
    return np.where(np.isnan(diff), 0.0, diff).max(axis=1)


def _joint_peak(d: np.ndarray, radius: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Robust centre (C, 2) of the disparities d (n, C, 2) (NaN: camera unused) of one cell's matches,
    all cameras at once: the match with the most others within ``radius`` in every camera they share
    (ghosts, spread over the tolerance disc in each camera, almost never agree in all of them), then a
    flat-kernel mean shift. Returns the centre and the mask of the matches within the radius."""
    d = np.ascontiguousarray(d, dtype=np.float64)
    if len(d) > PEAK_CANDIDATES:  # the densest of a random subset, counted against all: O(k n), not O(n^2)
        pick = np.sort(np.random.default_rng(seed).choice(len(d), PEAK_CANDIDATES, replace=False))
        counts = np.full(len(d), -1, np.int64)
        counts[pick] = joint_counts_against(d[pick], d, float(radius))
    else:
        counts = joint_counts(d, float(radius))
    best = int(np.argmax(counts + 0.5 * np.isfinite(d).all(axis=(1, 2))))  # ties: a match with every camera
    centre = d[best].copy()
    for _ in range(MEAN_SHIFT_STEPS):
        inside = _joint_distance(d, centre) <= radius
        with np.errstate(invalid="ignore"):
            new = np.nanmean(np.where(inside[:, None, None], d, np.nan), axis=0) if inside.any() else centre
        new = np.where(np.isnan(new), centre, new)
        moved = float(np.nanmax(np.abs(new - centre))) if np.isfinite(new).any() else 0.0
        centre = new
        if moved < 1e-4 * radius:
            break
    return centre, _joint_distance(d, centre) <= radius


def disparity_map(cameras: Sequence[str], cells: Cells, particles: ParticleSet, disparities: np.ndarray,
                  peak_radius_px: float, field_radius_px: float | None = None, seed: int = 0) -> DisparityMap:
    """Robust per-cell disparity of every camera (the method is in the module docstring) and the inlier matches.

    Args:
        cameras: The C cameras' names, in the columns' order.
        cells: The volume's cells.
        particles: The matched particles.
        disparities: (P, C, 2) px (:func:`particle_disparities`).
        peak_radius_px: Radius of the peak search and of an inlier (px).
        field_radius_px: When given, the peak of the whole volume is found first (among at most
            ``GLOBAL_SAMPLE`` matches) and each cell's peak is searched only among the matches within this
            radius of it (px), so that a cell with few true matches cannot elect a chance cluster of ghosts.
        seed: Seed of the random subsets.

    Returns:
        The map.
    """
    C, K = len(cameras), cells.count
    cell = cells.index(particles.xyz)
    used = np.isfinite(disparities).all(axis=2)
    d = np.where(used[:, :, None], disparities, np.nan)
    valid, field = used, None
    if field_radius_px is not None and valid.any():
        pool = np.flatnonzero(valid.any(axis=1))
        sample = pool if len(pool) <= GLOBAL_SAMPLE else np.random.default_rng(seed).choice(pool, GLOBAL_SAMPLE, False)
        field, _ = _joint_peak(d[sample], peak_radius_px, seed)
        near_field = _joint_distance(d, field) <= field_radius_px
        valid = valid & near_field[:, None]
    vector = np.full((C, K, 2), np.nan)
    count = np.zeros((C, K), int)
    total = np.zeros((C, K), int)
    inlier = np.zeros(len(d), dtype=bool)
    for k in range(K):
        sel = np.flatnonzero((cell == k) & valid.any(axis=1))
        total[:, k] = used[cell == k].sum(axis=0)
        if len(sel) < MIN_PEAK_COUNT:
            continue
        centre, inside = _joint_peak(d[sel], peak_radius_px, seed + k)
        if inside.sum() < MIN_PEAK_COUNT:
            continue
        inlier[sel[inside]] = True
        count[:, k] = valid[sel[inside]].sum(axis=0)
        vector[:, k] = np.where((count[:, k] >= MIN_PEAK_COUNT)[:, None], centre, np.nan)
    rms = np.full(C, np.nan)
    for c in range(C):
        m = inlier & valid[:, c]
        if m.any():
            rms[c] = float(np.sqrt(np.mean(np.einsum("ni,ni->n", disparities[m, c], disparities[m, c]))))
    return DisparityMap(tuple(cameras), cells, vector, count, total, inlier, rms, float(peak_radius_px))

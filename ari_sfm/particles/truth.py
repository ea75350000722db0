"""Reconstructed particles judged against a simulation's truth (tests, benchmarks, self-calibration)."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ParticleScore:
    """Found / ghost fractions and the 3D error of one or more frames."""

    found: int  # true particles reconstructed from their own images only
    seen: int  # true particles with images in >= min_cameras cameras
    reconstructed: int
    ghosts: int  # reconstructed from images of different particles
    rms_error_mm: float  # over the correct ones, against the true positions

    @property
    def found_fraction(self) -> float:
        return self.found / self.seen if self.seen else 0.0

    @property
    def ghost_fraction(self) -> float:
        return self.ghosts / self.reconstructed if self.reconstructed else 0.0

    def __add__(self, other: ParticleScore) -> ParticleScore:
        n1, n2 = self.found, other.found
        sq = (self.rms_error_mm ** 2 * n1 if n1 else 0.0) + (other.rms_error_mm ** 2 * n2 if n2 else 0.0)
        return ParticleScore(n1 + n2, self.seen + other.seen, self.reconstructed + other.reconstructed,
                             self.ghosts + other.ghosts, float(np.sqrt(sq / (n1 + n2))) if n1 + n2 else float("nan"))


def true_ids(rows: np.ndarray, cameras: list[str], particle_ids: Mapping[str, np.ndarray]) -> np.ndarray:
    """The true particle of each image the reconstructions use.

    Args:
        rows: (M, C) each reconstruction's detection row per camera (-1: none).
        cameras: The C cameras' names, in the columns' order.
        particle_ids: The true particle of each detection, per camera.

    Returns:
        (M, C) true particle ids (-1 where a reconstruction uses no image).
    """
    out = np.full(rows.shape, -1, np.int64)
    for k, cam in enumerate(cameras):
        used = rows[:, k] >= 0
        out[used, k] = np.asarray(particle_ids[cam])[rows[used, k]]
    return out


def score_frame(xyz: np.ndarray, rows: np.ndarray, cameras: list[str], particle_ids: Mapping[str, np.ndarray],
                positions: np.ndarray, min_cameras: int = 3) -> ParticleScore:
    """Score one frame's reconstruction against the truth.

    A reconstruction is correct when all its images are of one true particle; the others are ghosts.

    Args:
        xyz: Reconstructed points (M, 3), mm.
        rows: (M, C) each point's detection row per camera (-1: none).
        cameras: The C cameras' names, in the columns' order.
        particle_ids: The true particle of each detection, per camera (rows of ``positions``).
        positions: True particle positions (P, 3), mm.
        min_cameras: A true particle with images in at least this many cameras counts as seen.

    Returns:
        The frame's score.
    """
    ids = true_ids(rows, cameras, particle_ids)
    used = ids >= 0
    first = np.where(used, ids, -1).max(axis=1)
    correct = np.all(~used | (ids == first[:, None]), axis=1) & (first >= 0)
    n_views = np.zeros(len(positions), int)
    for cam in cameras:
        n_views[np.unique(np.asarray(particle_ids[cam]))] += 1
    seen = int((n_views >= min_cameras).sum())
    found = len(np.unique(first[correct]))
    err = np.linalg.norm(xyz[correct] - positions[first[correct]], axis=1)
    rms = float(np.sqrt(np.mean(err ** 2))) if len(err) else float("nan")
    return ParticleScore(found=found, seen=seen, reconstructed=len(rows), ghosts=int((~correct).sum()),
                         rms_error_mm=rms)


@dataclass(frozen=True)
class ImageScore:
    """Particle images found in one or more frames against the true image centres."""

    true_images: int
    detections: int
    found: int  # true images with their own detection within ``tolerance_px`` (one detection each)
    ghosts: int  # detections with no true image within ``tolerance_px``
    ghosts_1px: int  # detections with no true image within 1 px
    rms_error_px: float  # over the found ones
    tolerance_px: float

    @property
    def recall(self) -> float:
        return self.found / self.true_images if self.true_images else 0.0

    @property
    def ghost_fraction(self) -> float:
        return self.ghosts / self.detections if self.detections else 0.0

    @property
    def ghost_fraction_1px(self) -> float:
        return self.ghosts_1px / self.detections if self.detections else 0.0

    def __add__(self, other: ImageScore) -> ImageScore:
        n1, n2 = self.found, other.found
        sq = (self.rms_error_px ** 2 * n1 if n1 else 0.0) + (other.rms_error_px ** 2 * n2 if n2 else 0.0)
        return ImageScore(self.true_images + other.true_images, self.detections + other.detections, n1 + n2,
                          self.ghosts + other.ghosts, self.ghosts_1px + other.ghosts_1px,
                          float(np.sqrt(sq / (n1 + n2))) if n1 + n2 else float("nan"), self.tolerance_px)


def score_image(found_uv: np.ndarray, true_uv: np.ndarray, tolerance_px: float = 0.5) -> ImageScore:
    """Score detections against true image centres, one to one.

    The closest pairs within ``tolerance_px`` are taken first (a detection between two true images counts
    for one of them at most).

    Args:
        found_uv: Detections (N, 2), px.
        true_uv: True image centres (M, 2), px.
        tolerance_px: A detection within this distance of a true image finds it (px).

    Returns:
        The score.
    """
    from scipy.spatial import cKDTree

    found_uv = np.asarray(found_uv, float).reshape(-1, 2)
    true_uv = np.asarray(true_uv, float).reshape(-1, 2)
    n, m = len(found_uv), len(true_uv)
    if n == 0 or m == 0:
        return ImageScore(m, n, 0, n, n, float("nan"), tolerance_px)
    tree = cKDTree(true_uv)
    pairs = tree.query_ball_point(found_uv, r=tolerance_px)
    det = np.repeat(np.arange(n), [len(p) for p in pairs])
    tru = np.fromiter((t for p in pairs for t in p), np.int64, len(det))
    dist = np.linalg.norm(found_uv[det] - true_uv[tru], axis=1)
    used_d, used_t = np.zeros(n, bool), np.zeros(m, bool)
    err = []
    for k in np.argsort(dist, kind="stable"):
        if not used_d[det[k]] and not used_t[tru[k]]:
            used_d[det[k]] = used_t[tru[k]] = True
            err.append(dist[k])
    nearest = tree.query(found_uv)[0]
    rms = float(np.sqrt(np.mean(np.square(err)))) if err else float("nan")
    return ImageScore(m, n, len(err), int((nearest > tolerance_px).sum()), int((nearest > 1.0).sum()), rms,
                      tolerance_px)


def score_experiment(experiment, volume, calibration, tolerance_px: float = 0.5,
                     min_cameras: int = 3) -> tuple[ParticleScore | None, float]:
    """Match every frame of a simulated experiment through a calibration and score it.

    The 3D error is taken after a rigid alignment onto the true positions, so that a calibration right up to
    a rigid motion of the rig scores as right.

    Args:
        experiment: The simulated experiment (:class:`~ari_sfm.simulate.particles.ParticleExperiment`).
        volume: The measured volume (:class:`~ari_sfm.particles.volume.Volume`).
        calibration: The calibration to match through.
        tolerance_px: Matching tolerance (px), as :func:`~ari_sfm.particles.match.match_frame`.
        min_cameras: Cameras a particle needs, as :func:`~ari_sfm.particles.match.match_frame`.

    Returns:
        (the summed found / ghost score, or None without frames; the 3D RMS (mm) of the correctly matched
        particles after the alignment, NaN with fewer than 3).
    """
    from ..reconstruction.metrics import rigid_alignment
    from .match import match_frame

    total, P, Q = None, [], []
    for f, det in enumerate(experiment.detections):
        m = match_frame(calibration, det, tolerance_px, volume=volume, min_cameras=min_cameras)
        s = score_frame(m.xyz, m.rows, experiment.cameras, experiment.particle_ids[f], experiment.positions[f])
        total = s if total is None else total + s
        ids = true_ids(m.rows, experiment.cameras, experiment.particle_ids[f])
        first = ids.max(axis=1)
        ok = np.all((ids < 0) | (ids == first[:, None]), axis=1)
        P.append(m.xyz[ok])
        Q.append(experiment.positions[f][first[ok]])
    p, q = np.concatenate(P), np.concatenate(Q)
    if len(p) < 3:
        return total, float("nan")
    R, t = rigid_alignment(p, q)
    return total, float(np.sqrt(np.mean(np.sum((p @ R.T + t - q) ** 2, axis=1))))

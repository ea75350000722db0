"""The expansion centre: the common point of the corner trajectories under plate stacking.

Adding glass plates to the window moves every target corner along a straight
image line through the expansion centre e ~ K n_cam (paper Sec. 2.1, Fig. 4).
Each trajectory is fitted by total least squares; the centre is the weighted
least-squares intersection of the lines, with iterative outlier rejection.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..records import Observation

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrajectoryLine:
    """A TLS line through one corner's trajectory: points p with normal . p = offset."""

    id: int
    centroid: np.ndarray  # (2,)
    direction: np.ndarray  # (2,) unit
    normal: np.ndarray  # (2,) unit, perpendicular to direction
    offset: float
    spread: float  # sum of squared positions along the line about the centroid (px^2)
    count: int
    rms_px: float  # perpendicular RMS of the points about the line


@dataclass(frozen=True)
class ExpansionCenter:
    """The measured expansion centre of one camera, in pixels."""

    center_px: np.ndarray  # (2,)
    std_px: np.ndarray  # (2,) standard error of u and v
    lines: tuple[TrajectoryLine, ...]
    inliers: np.ndarray  # (len(lines),) bool
    residual_rms_px: float  # RMS perpendicular distance of the inlier lines to the centre


def fit_line_tls(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Total-least-squares line through points (K, 2): (centroid, unit direction, spread, rms)."""
    centroid = points.mean(axis=0)
    centered = points - centroid
    _, s, vt = np.linalg.svd(centered, full_matrices=False)
    direction = vt[0]
    spread = float(s[0] ** 2)
    rms = float(s[1] / np.sqrt(len(points))) if len(s) > 1 else 0.0
    return centroid, direction, spread, rms


def trajectories(observations: Sequence[Observation]) -> dict[tuple[str, int], np.ndarray]:
    """Corner tracks of one camera's stacking records: {(pose, id): (K, 2) pixels by added_mm}."""
    tracks: dict[tuple[str, int], list[tuple[float, np.ndarray]]] = {}
    for obs in observations:
        for i, px in zip(obs.ids.tolist(), obs.pixels):
            tracks.setdefault((obs.frame, int(i)), []).append((float(obs.added_mm or 0.0), px))
    return {k: np.array([p for _, p in sorted(v, key=lambda e: e[0])]) for k, v in tracks.items() if len(v) >= 2}


def fit_lines(observations: Sequence[Observation], min_length_px: float = 1e-3) -> list[TrajectoryLine]:
    """One TLS line per corner trajectory with at least two thicknesses and a visible motion."""
    tracks = list(trajectories(observations).items())
    fits: list = [None] * len(tracks)
    by_length: dict[int, list[int]] = {}
    for k, (_, pts) in enumerate(tracks):
        by_length.setdefault(len(pts), []).append(k)
    for count, idx in by_length.items():  # fit_line_tls on all tracks of one length at once (batched SVD)
        pts = np.stack([tracks[k][1] for k in idx])
        centroid = pts.mean(axis=1)
        _, sv, vt = np.linalg.svd(pts - centroid[:, None, :], full_matrices=False)
        for j, k in enumerate(idx):
            rms = float(sv[j, 1] / np.sqrt(count)) if sv.shape[1] > 1 else 0.0
            fits[k] = (centroid[j], vt[j, 0], float(sv[j, 0] ** 2), rms)
    lines = []
    for ((_, corner_id), pts), (centroid, direction, spread, rms) in zip(tracks, fits):
        if np.sqrt(spread) < min_length_px:
            continue
        normal = np.array([-direction[1], direction[0]])
        lines.append(TrajectoryLine(corner_id, centroid, direction, normal, float(normal @ centroid), spread, len(pts), rms))
    return lines


def intersect_lines(
    lines: Sequence[TrajectoryLine], reject_sigma: float = 3.0, max_rounds: int = 10
) -> ExpansionCenter:
    """Weighted least-squares common point of the lines with outlier rejection.

    A line's perpendicular error at the centre grows with the centre's distance D
    from the trajectory's centroid: var ~ s^2 (1/k + D^2 / spread). The weights
    use it (iterated, since D depends on the centre); lines beyond reject_sigma
    robust standard deviations are dropped and the fit repeated.
    """
    if len(lines) < 2:
        raise ValueError(f"need at least 2 corner trajectories for the expansion centre, got {len(lines)}")
    A = np.array([ln.normal for ln in lines])
    b = np.array([ln.offset for ln in lines])
    centroids = np.array([ln.centroid for ln in lines])
    spread = np.array([ln.spread for ln in lines])
    count = np.array([ln.count for ln in lines], dtype=float)
    inliers = np.ones(len(lines), dtype=bool)
    center = _solve(A, b, np.ones(len(lines)), inliers)
    for _ in range(max_rounds):
        for _ in range(3):  # the weights depend on the centre
            dist2 = np.sum((centroids - center) ** 2, axis=1)
            var = 1.0 / count + dist2 / np.maximum(spread, 1e-12)
            weights = 1.0 / var
            center = _solve(A, b, weights, inliers)
        resid = (A @ center - b) * np.sqrt(weights)  # normalised residuals
        scale = 1.4826 * np.median(np.abs(resid[inliers])) + 1e-15
        new_inliers = np.abs(resid) <= reject_sigma * scale
        if new_inliers.sum() < 2 or np.array_equal(new_inliers, inliers):
            break
        inliers = new_inliers
    w = weights * inliers
    normal_matrix = (A * w[:, None]).T @ A
    dof = max(int(inliers.sum()) - 2, 1)
    sigma2 = float(np.sum(w * (A @ center - b) ** 2) / dof)
    cov = sigma2 * np.linalg.inv(normal_matrix)
    perp = (A @ center - b)[inliers]
    if (~inliers).any():
        log.info("expansion centre: rejected %d of %d trajectories", int((~inliers).sum()), len(lines))
    return ExpansionCenter(center, np.sqrt(np.diag(cov)), tuple(lines), inliers, float(np.sqrt(np.mean(perp**2))))


def _solve(A: np.ndarray, b: np.ndarray, weights: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    w = weights * inliers
    M = (A * w[:, None]).T @ A
    if np.linalg.cond(M) > 1e12:
        raise ValueError("corner trajectories are (nearly) parallel: the expansion centre is undetermined")
    return np.linalg.solve(M, (A * w[:, None]).T @ b)


def expansion_center(observations: Sequence[Observation]) -> ExpansionCenter:
    """Measure one camera's expansion centre from its stacking observations."""
    return intersect_lines(fit_lines(observations))


def normal_from_expansion_center(center_px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The window normal in the camera frame from the expansion centre (paper Eq. 5).

    Eq. 5 is n ~ K^-1 [u_s, v_s, 1]^T normalised, written out for a skew-free K.
    The normal points from the camera into the scene (n_z > 0).
    """
    fu, fv, u0, v0 = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    du, dv = center_px[0] - u0, center_px[1] - v0
    norm = np.sqrt(fu**2 * dv**2 + fv**2 * du**2 + fu**2 * fv**2)
    return np.array([fv * du, fu * dv, fu * fv]) / norm

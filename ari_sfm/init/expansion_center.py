"""The expansion centre: the common point of the corner trajectories under plate stacking.

Adding glass plates to the window moves every target corner along a straight
image line through the expansion centre e ~ K n_cam (paper Sec. 2.1, Fig. 4).
Each trajectory is fitted by total least squares; the centre is the weighted
least-squares intersection of the lines, with iterative outlier rejection.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..records import Observation

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrajectoryLines:
    """TLS lines through corner trajectories, one row each: points p with normal . p = offset."""

    id: np.ndarray  # (T,) corner ids
    centroid: np.ndarray  # (T, 2)
    direction: np.ndarray  # (T, 2) unit
    normal: np.ndarray  # (T, 2) unit, perpendicular to direction
    offset: np.ndarray  # (T,)
    spread: np.ndarray  # (T,) sum of squared positions along the line about the centroid (px^2)
    count: np.ndarray  # (T,) points
    rms_px: np.ndarray  # (T,) perpendicular RMS of the points about the line

    def __len__(self) -> int:
        return len(self.id)


@dataclass(frozen=True)
class ExpansionCenter:
    """The measured expansion centre of one camera, in pixels."""

    center_px: np.ndarray  # (2,)
    std_px: np.ndarray  # (2,) standard error of u and v
    lines: TrajectoryLines
    inliers: np.ndarray  # (len(lines),) bool
    residual_rms_px: float  # RMS perpendicular distance of the inlier lines to the centre


def _track_lines(points: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, ...]:
    """Total-least-squares lines through tracks: points (N, 2), track t = points[start[t]:start[t + 1]].
    Closed form of the 2 x 2 scatter S = sum q q^T (q = p - centroid): the direction (cos a, sin a) with
    a = atan2(2 S_xy, S_xx - S_yy) / 2 (S's first eigenvector); the spread sum (d . q)^2 and the
    perpendicular RMS sqrt(mean (n . q)^2) summed from the points. Returns (centroid (T, 2), direction
    (T, 2), spread (T,), rms (T,), count (T,))."""
    count = np.diff(start)
    centroid = np.add.reduceat(points, start[:-1], axis=0) / count[:, None]
    q = points - np.repeat(centroid, count, axis=0)
    sxx, syy, sxy = (np.add.reduceat(v, start[:-1]) for v in (q[:, 0] ** 2, q[:, 1] ** 2, q[:, 0] * q[:, 1]))
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    direction = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    d = np.repeat(direction, count, axis=0)
    along = q[:, 0] * d[:, 0] + q[:, 1] * d[:, 1]
    across = q[:, 1] * d[:, 0] - q[:, 0] * d[:, 1]
    spread = np.add.reduceat(along * along, start[:-1])
    rms = np.sqrt(np.add.reduceat(across * across, start[:-1]) / count)
    return centroid, direction, spread, rms, count


def fit_line_tls(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Total-least-squares line through points (K, 2): (centroid, unit direction, spread, rms)."""
    centroid, direction, spread, rms, _ = _track_lines(np.asarray(points, float), np.array([0, len(points)]))
    return centroid[0], direction[0], float(spread[0]), float(rms[0])


def _tracks(observations: Sequence[Observation]) -> tuple[list[tuple[str, int]], np.ndarray, np.ndarray]:
    """Corner tracks of one camera's stacking records, in order of first appearance: their (pose, id),
    the pixels (N, 2) sorted by track then added_mm (records in order for equal thickness), and the
    tracks' starts (T + 1,); tracks of one point are left out."""
    if not observations:
        return [], np.zeros((0, 2)), np.zeros(1, dtype=np.int64)
    frames = list(dict.fromkeys(o.frame for o in observations))
    frame_of = {f: i for i, f in enumerate(frames)}
    size = [len(o.ids) for o in observations]
    frame = np.repeat([frame_of[o.frame] for o in observations], size)
    ids = np.concatenate([np.asarray(o.ids, dtype=np.int64).reshape(-1) for o in observations])
    added = np.repeat([float(o.added_mm or 0.0) for o in observations], size)
    pixels = np.concatenate([np.asarray(o.pixels, float).reshape(-1, 2) for o in observations])
    low = int(ids.min())
    span = int(ids.max()) - low + 1
    _, first, track = np.unique(frame * span + (ids - low), return_index=True, return_inverse=True)
    by_appearance = np.argsort(first, kind="stable")
    rank = np.empty(len(first), dtype=np.int64)
    rank[by_appearance] = np.arange(len(first))
    order = np.lexsort((np.arange(len(ids)), added, rank[track]))
    count = np.bincount(rank[track], minlength=len(first))
    keep = np.repeat(count >= 2, count)
    firsts = first[by_appearance]
    names = [(frames[f], i) for f, i, n in zip(frame[firsts].tolist(), ids[firsts].tolist(), count.tolist()) if n >= 2]
    kept = count[count >= 2]
    return names, pixels[order][keep], np.concatenate([[0], np.cumsum(kept)])


def trajectories(observations: Sequence[Observation]) -> dict[tuple[str, int], np.ndarray]:
    """Corner tracks of one camera's stacking records: {(pose, id): (K, 2) pixels by added_mm}."""
    names, pixels, start = _tracks(observations)
    return {name: pixels[start[k]:start[k + 1]] for k, name in enumerate(names)}


def fit_lines(observations: Sequence[Observation], min_length_px: float = 1e-3) -> TrajectoryLines:
    """Fit one TLS line per corner trajectory with at least two thicknesses and a visible motion.

    Args:
        observations: one camera's stacking records.
        min_length_px: the least spread of a trajectory along its line (px) for it to be kept.

    Returns:
        The lines, one row per kept trajectory.
    """
    names, pixels, start = _tracks(observations)
    centroid, direction, spread, rms, count = _track_lines(pixels, start)
    normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1).reshape(-1, 2)
    keep = np.sqrt(spread) >= min_length_px
    ids = np.array([corner_id for _, corner_id in names], dtype=np.int64)
    return TrajectoryLines(ids[keep], centroid[keep], direction[keep], normal[keep],
                           np.einsum("ij,ij->i", normal[keep], centroid[keep]), spread[keep], count[keep], rms[keep])


def intersect_lines(lines: TrajectoryLines, reject_sigma: float = 3.0, max_rounds: int = 10) -> ExpansionCenter:
    """Find the weighted least-squares common point of the lines, with outlier rejection.

    A line's perpendicular error at the centre grows with the centre's distance D
    from the trajectory's centroid: var ~ s^2 (1/k + D^2 / spread). The weights
    use it (iterated, since D depends on the centre); lines beyond ``reject_sigma``
    robust standard deviations are dropped and the fit repeated.

    Args:
        lines: the trajectories' lines.
        reject_sigma: the rejection threshold, in robust standard deviations.
        max_rounds: the most rejection rounds.

    Returns:
        The expansion centre (px), its standard error and the inlier lines.

    Raises:
        ValueError: with fewer than 2 lines, or when the lines are (nearly) parallel.
    """
    if len(lines) < 2:
        raise ValueError(f"need at least 2 corner trajectories for the expansion centre, got {len(lines)}")
    A, b, centroids, spread = lines.normal, lines.offset, lines.centroid, lines.spread
    count = lines.count.astype(float)
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
    return ExpansionCenter(center, np.sqrt(np.diag(cov)), lines, inliers, float(np.sqrt(np.mean(perp**2))))


def _solve(A: np.ndarray, b: np.ndarray, weights: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    w = weights * inliers
    Aw = A * w[:, None]
    M = Aw.T @ A
    # M's condition number in closed form (symmetric 2x2: its eigenvalues m +- r)
    m, r = 0.5 * (M[0, 0] + M[1, 1]), np.hypot(0.5 * (M[0, 0] - M[1, 1]), M[0, 1])
    if not (m - r > 0.0 and (m + r) / (m - r) <= 1e12):
        raise ValueError("corner trajectories are (nearly) parallel: the expansion centre is undetermined")
    return np.linalg.solve(M, Aw.T @ b)


def expansion_center(observations: Sequence[Observation]) -> ExpansionCenter:
    """Measure one camera's expansion centre from its stacking observations."""
    return intersect_lines(fit_lines(observations))


def normal_from_expansion_center(center_px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Give the window normal in the camera frame from the expansion centre (paper Eq. 5).

    Eq. 5 is n ~ K^-1 [u_s, v_s, 1]^T normalised, written out for a skew-free K.

    Args:
        center_px: the expansion centre (2,), px.
        K: the 3x3 intrinsic matrix (no skew).

    Returns:
        The unit normal (3,), camera frame, pointing from the camera into the scene (n_z > 0).
    """
    fu, fv, u0, v0 = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    du, dv = center_px[0] - u0, center_px[1] - v0
    norm = np.sqrt(fu**2 * dv**2 + fv**2 * du**2 + fu**2 * fv**2)
    return np.array([fv * du, fu * dv, fu * fv]) / norm

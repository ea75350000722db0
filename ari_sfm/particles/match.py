"""Particle correspondences through the window, one frame at a time.

Which particle image in one camera belongs to which in the others? Behind a
window the epipolar line of a particle image is a curve (the ray bends at both
faces), so it is built from the exact model itself:

1. every detection of a reference camera is back-projected to its medium-side
   ray (``Calibration.rays_world``) and the ray is clipped to the measured
   volume; K points along the clipped ray are projected into each other camera
   (``Calibration.project_world``): the refracted epipolar curve as a polyline
   of segments at most ``SEGMENT_PX`` long;
2. candidates: detections within ``tolerance_px`` of that polyline (a
   ``scipy.spatial.cKDTree`` per camera, queried at segment midpoints, then the
   exact point-to-segment distance);
3. combinations of one candidate (or none) per other camera with at least
   ``min_cameras`` images in all are scored by their rays
   (:func:`ari_sfm.triangulate.triangulate_rays`): each ray's distance from
   the point, in pixels of its camera (mm / the camera's footprint at the
   volume), must be within the tolerance, and the point inside the volume;
4. accepted combinations are taken best first (more cameras first, then the
   smaller RMS distance), each particle image used once;
5. the chosen ones are triangulated with the exact model
   (:func:`ari_sfm.triangulate.triangulate_pixels`).

Each combination is enumerated once: its reference is its lowest camera.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ari_sfm.calibration import Calibration
from ari_sfm.particles.volume import Volume
from ari_sfm.triangulate import triangulate_pixels, triangulate_rays

log = logging.getLogger(__name__)

SEGMENT_PX = 8.0  # longest segment of a sampled epipolar curve (the curve is near straight over this)
MAX_SAMPLES = 256  # samples along one ray at most
COMBO_CHUNK = 200_000  # combinations scored at once (bounds memory with loose tolerances)


@dataclass(frozen=True)
class FrameMatches:
    """The particles found in one frame (camera order = the calibration's)."""

    xyz: np.ndarray  # (M, 3) mm, world frame of the calibration
    ray_gap_mm: np.ndarray  # (M,) RMS distance of its rays from the point
    rows: np.ndarray  # (M, n_cameras) int64: row index into that camera's detections array, -1 if unused

    @property
    def num_cameras(self) -> np.ndarray:
        """(M,) how many cameras' images each particle uses."""
        return (self.rows >= 0).sum(axis=1)


def _empty(C: int) -> FrameMatches:
    return FrameMatches(np.empty((0, 3)), np.empty(0), np.empty((0, C), np.int64))


def footprint_mm_per_px(calibration: Calibration, cameras: list[str], point_world: np.ndarray) -> np.ndarray:
    """(C,) lateral mm per pixel of each camera at a world point (through the window, from the model)."""
    out = np.empty(len(cameras))
    for k, cam in enumerate(cameras):
        centre = calibration.cameras[cam].cam_from_world.inverse().t
        view = point_world - centre
        side = np.cross(view, [0.0, 0.0, 1.0] if abs(view[2]) < 0.9 * np.linalg.norm(view) else [1.0, 0.0, 0.0])
        side = 0.5 * side / np.linalg.norm(side)
        uv = calibration.project_world(cam, np.stack([point_world - side, point_world + side]))
        px = float(np.linalg.norm(uv[1] - uv[0]))
        if not np.isfinite(px) or px <= 0:
            raise ValueError(f"camera {cam} does not see the volume's centre {np.round(point_world, 1).tolist()}")
        out[k] = 1.0 / px
    return out


def _candidates(calibration: Calibration, camera: str, uv: np.ndarray, tree, origins: np.ndarray,
                directions: np.ndarray, s0: np.ndarray, s1: np.ndarray, tolerance_px: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j): detection j of ``camera`` within the tolerance of reference ray i's epipolar curve."""
    n = len(origins)
    if n == 0 or len(uv) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    ends = calibration.project_world(camera, np.concatenate([origins + s0[:, None] * directions,
                                                             origins + s1[:, None] * directions]))
    length = np.linalg.norm(ends[n:] - ends[:n], axis=1)
    longest = np.nanmax(length) if np.isfinite(length).any() else 0.0
    K = int(np.clip(np.ceil(longest / SEGMENT_PX) + 1, 2, MAX_SAMPLES))
    t = np.linspace(0.0, 1.0, K)
    s = s0[:, None] + (s1 - s0)[:, None] * t[None, :]  # (n, K)
    X = origins[:, None, :] + s[..., None] * directions[:, None, :]
    p = calibration.project_world(camera, X.reshape(-1, 3)).reshape(n, K, 2)
    a, b = p[:, :-1].reshape(-1, 2), p[:, 1:].reshape(-1, 2)
    ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    seg = np.flatnonzero(ok)
    if not len(seg):
        return np.empty(0, np.int64), np.empty(0, np.int64)
    mid = 0.5 * (a[seg] + b[seg])
    radius = 0.5 * np.linalg.norm(b[seg] - a[seg], axis=1) + tolerance_px
    hits = tree.query_ball_point(mid, radius, return_sorted=False)
    counts = np.fromiter((len(h) for h in hits), np.int64, len(hits))
    if not counts.sum():
        return np.empty(0, np.int64), np.empty(0, np.int64)
    seg_of = np.repeat(seg, counts)
    j = np.fromiter((x for h in hits for x in h), np.int64, int(counts.sum()))
    A, B, P = a[seg_of], b[seg_of], uv[j]
    AB = B - A
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = np.clip(np.einsum("ij,ij->i", P - A, AB) / np.einsum("ij,ij->i", AB, AB), 0.0, 1.0)
    lam = np.nan_to_num(lam)
    dist = np.linalg.norm(A + lam[:, None] * AB - P, axis=1)
    keep = dist <= tolerance_px
    i = seg_of[keep] // (K - 1)
    key = np.unique(i * len(uv) + j[keep])
    return key // len(uv), key % len(uv)


def _join(combos: np.ndarray, pair_i: np.ndarray, pair_j: np.ndarray, col: int) -> np.ndarray:
    """Cross join of ``combos`` (Q, C) (column 0 .. : rows, ``combos[:, ref]`` the reference detection,
    stored in the last column) with pairs (i, j) on i, plus the option "none" (-1) in column ``col``."""
    ref = combos[:, -1]
    order = np.argsort(pair_i, kind="stable")
    pi, pj = pair_i[order], pair_j[order]
    start = np.searchsorted(pi, ref, side="left")
    stop = np.searchsorted(pi, ref, side="right")
    count = stop - start + 1  # + the "none" option
    rows = np.repeat(np.arange(len(combos)), count)
    out = combos[rows].copy()
    first = np.repeat(np.cumsum(count) - count, count)
    k = np.arange(len(rows)) - first  # 0 .. count-1 within each group; the last is "none"
    real = k < (stop - start)[rows]
    out[:, col] = -1
    out[real, col] = pj[(start[rows] + k)[real]]
    return out


def match_frame(calibration: Calibration, detections: Mapping[str, np.ndarray], tolerance_px: float,
                depth_range_mm: tuple[float, float] | None = None, volume: Volume | None = None,
                min_cameras: int = 3) -> FrameMatches:
    """Particles of one frame from their images in every camera (see the module docstring).

    ``detections``: camera name -> (N_c, 2) pixels (a camera absent: no images).
    ``volume``: where particles can be (world); else ``depth_range_mm``: the slab of world z
    (camera 0's depth). ``min_cameras`` >= 2 images per particle.
    """
    from scipy.spatial import cKDTree

    cameras = list(calibration.cameras)
    C = len(cameras)
    unknown = [c for c in detections if c not in calibration.cameras]
    if unknown:
        raise ValueError(f"detections of camera(s) {', '.join(unknown)} not in the calibration ({', '.join(cameras)})")
    if not 2 <= min_cameras <= C:
        raise ValueError(f"min_cameras must be 2..{C} (got {min_cameras})")
    if not tolerance_px > 0:
        raise ValueError(f"tolerance_px must be > 0 (got {tolerance_px})")
    if volume is None:
        if depth_range_mm is None:
            raise ValueError("match_frame needs a volume or a depth range")
        volume = Volume.depth_range(*depth_range_mm)
    uv = [np.asarray(detections.get(c, np.empty((0, 2))), float).reshape(-1, 2) for c in cameras]
    for c, a in zip(cameras, uv):
        if not np.isfinite(a).all():
            raise ValueError(f"detections of camera {c} hold non-finite pixels")
    footprint = footprint_mm_per_px(calibration, cameras, volume.center_world)
    rays = []
    for c, a in zip(cameras, uv):
        if len(a):
            o, d = calibration.rays_world(c, a)
        else:
            o, d = np.empty((0, 3)), np.empty((0, 3))
        rays.append((o, d))
    trees = [cKDTree(a) if len(a) else None for a in uv]

    chosen: list[np.ndarray] = []
    for r in range(C - min_cameras + 1):
        o, d = rays[r]
        if not len(o):
            continue
        s0, s1 = volume.clip_rays(o, d)
        live = np.flatnonzero(np.isfinite(s0) & np.isfinite(d).all(axis=1))
        combos = np.full((len(live), C + 1), -1, np.int64)
        combos[:, r] = live
        combos[:, -1] = live
        for c in range(r + 1, C):
            if trees[c] is None:
                pi = pj = np.empty(0, np.int64)
            else:
                i_loc, pj = _candidates(calibration, cameras[c], uv[c], trees[c], o[live], d[live], s0[live],
                                        s1[live], tolerance_px)
                pi = live[i_loc]
            combos = _join(combos, pi, pj, c)
            # prune: not enough cameras left to reach min_cameras
            have = (combos[:, :C] >= 0).sum(axis=1)
            combos = combos[have + (C - 1 - c) >= min_cameras]
        combos = combos[(combos[:, :C] >= 0).sum(axis=1) >= min_cameras, :C]
        chosen.append(combos)
    combos = np.concatenate(chosen) if chosen else np.empty((0, C), np.int64)
    if not len(combos):
        return _empty(C)

    accepted, scores = [], []
    for k0 in range(0, len(combos), COMBO_CHUNK):
        part = combos[k0:k0 + COMBO_CHUNK]
        ok, score = _score(part, rays, footprint, volume, tolerance_px)
        accepted.append(part[ok])
        scores.append(score[ok])
    combos = np.concatenate(accepted)
    score = np.concatenate(scores)
    rows = _greedy(combos, score, [len(a) for a in uv])
    if not len(rows):
        return _empty(C)

    tracks = {}
    for k, c in enumerate(cameras):
        t = np.full((len(rows), 2), np.nan)
        used = rows[:, k] >= 0
        t[used] = uv[k][rows[used, k]]
        tracks[c] = t
    X, _, _ = triangulate_pixels(calibration, tracks)
    good = np.isfinite(X).all(axis=1)
    rows, X = rows[good], X[good]
    gap = _rms_ray_distance(X, rows, rays)
    return FrameMatches(X, gap, rows)


def _ray_arrays(combos: np.ndarray, rays: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Origins, directions (Q, C, 3) and valid (Q, C) of the rays a combination uses."""
    Q, C = combos.shape
    O = np.zeros((Q, C, 3))
    D = np.zeros((Q, C, 3))
    valid = combos >= 0
    for c in range(C):
        m = valid[:, c]
        if m.any():
            O[m, c] = rays[c][0][combos[m, c]]
            D[m, c] = rays[c][1][combos[m, c]]
    return O, D, valid


def _ray_distances(X: np.ndarray, O: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(Q, C) distance of X (Q, 3) from each unit ray."""
    r = X[:, None, :] - O
    perp = r - np.einsum("qci,qci->qc", r, D)[..., None] * D
    return np.linalg.norm(perp, axis=2)


def _score(combos: np.ndarray, rays, footprint: np.ndarray, volume: Volume, tolerance_px: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """Accepted (Q,) and score (Q,): RMS over the rays of their distance from the point, in pixels."""
    O, D, valid = _ray_arrays(combos, rays)
    X, _ = triangulate_rays(O, D, valid)
    with np.errstate(invalid="ignore"):
        dist_px = np.where(valid, _ray_distances(X, O, D) / footprint[None, :], 0.0)
        n = valid.sum(axis=1)
        score = np.sqrt((dist_px ** 2).sum(axis=1) / n)
        ok = np.isfinite(X).all(axis=1) & (dist_px.max(axis=1) <= tolerance_px)
    ok[ok] &= volume.contains(X[ok], margin_mm=tolerance_px * float(footprint.max()))
    return ok, score


def _greedy(combos: np.ndarray, score: np.ndarray, sizes: list[int]) -> np.ndarray:
    """Best first (more cameras, then smaller score), each detection used once: the chosen rows."""
    if not len(combos):
        return combos
    ncam = (combos >= 0).sum(axis=1)
    order = np.lexsort((score, -ncam))
    used = [np.zeros(n + 1, bool) for n in sizes]  # the extra slot absorbs -1
    keep = []
    C = combos.shape[1]
    for q in order:
        row = combos[q]
        if any(used[c][row[c]] for c in range(C) if row[c] >= 0):
            continue
        for c in range(C):
            if row[c] >= 0:
                used[c][row[c]] = True
        keep.append(q)
    return combos[np.asarray(keep, np.int64)]


def _rms_ray_distance(X: np.ndarray, rows: np.ndarray, rays) -> np.ndarray:
    """(M,) RMS distance of each particle's rays from its (refined) point (mm)."""
    O, D, valid = _ray_arrays(rows, rays)
    d = np.where(valid, _ray_distances(X, O, D), 0.0)
    return np.sqrt((d ** 2).sum(axis=1) / valid.sum(axis=1))

"""Particle correspondences through the window, one frame at a time.

Which particle image in one camera belongs to which in the others? Behind a
window the epipolar line of a particle image is a curve (the ray bends at both
faces), so it is built from the exact model itself:

1. every detection of a reference camera is back-projected to its medium-side
   ray (``Calibration.rays_world``) and the ray is clipped to the measured
   volume; K points along the clipped ray are projected into each other camera
   (``Calibration.project_world``): the refracted epipolar curve as a polyline
   of segments at most ``SEGMENT_PX`` long;
2. candidates: detections within ``tolerance_px`` of that polyline (the
   detections bucketed in a grid of ``GRID_CELL_PX`` cells; each segment looks
   only at the cells near it and measures the exact point-to-segment distance);
3. combinations of one candidate (or none) per other camera with at least
   ``min_cameras`` images in all (built camera by camera; a partial one whose
   newest ray passes farther from another than any accepted combination's could
   is dropped before the next camera is joined) are scored by their rays (their least-squares
   point, as :func:`ari_sfm.reconstruction.triangulate.triangulate_rays` forms it): each ray's
   distance from the point, in pixels of its camera (mm / the camera's
   footprint at the volume), must be within the tolerance, and the point inside
   the volume;
4. accepted combinations are taken best first (more cameras first, then the
   smaller RMS distance), each particle image used once;
5. the chosen ones are triangulated with the exact model
   (:func:`ari_sfm.reconstruction.triangulate.triangulate_pixels`).

Each combination is enumerated once: its reference is its lowest camera. Steps 2-4
are compiled (:mod:`ari_sfm.particles.match_kernels`).
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ari_sfm.calibration.record import Calibration
from ari_sfm.particles import match_kernels
from ari_sfm.particles.volume import Volume
from ari_sfm.reconstruction.triangulate import MIN_DET, triangulate_pixels

log = logging.getLogger(__name__)

SEGMENT_PX = 20.0  # longest segment of a sampled epipolar curve (it bows < 0.01 px over this)
MAX_SAMPLES = 256  # samples along one ray at most
COMBO_CHUNK = 200_000  # combinations scored at once (bounds memory with loose tolerances)
GRID_CELL_PX = 16.0  # cell of the detections' grid the curves' segments look up (at least the tolerance)


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
    """Lateral mm per pixel of each camera at a world point (through the window, from the model).

    Args:
        calibration: The calibration.
        cameras: The C cameras' names.
        point_world: The point (3,), world frame, mm.

    Returns:
        (C,) mm per pixel.

    Raises:
        ValueError: A camera does not see the point.
    """
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


def _candidates(calibration: Calibration, camera: str, uv: np.ndarray, origins: np.ndarray,
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
    i, j = match_kernels.band_pairs(np.ascontiguousarray(p), np.ascontiguousarray(uv), float(tolerance_px),
                                    max(GRID_CELL_PX, float(tolerance_px)))
    return i, j


def _reference_pairs(calibration: Calibration, cameras: list[str], uv: list[np.ndarray], rays,
                     volume: Volume, r: int, wanted: np.ndarray, tolerance_px: float
                     ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Candidate pairs (reference detection, detection) of the ``wanted`` detections of camera r
    whose ray crosses the volume, in every camera after r."""
    o, d = rays[r]
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    live = np.empty(0, np.int64)
    if len(o):
        s0, s1 = volume.clip_rays(o, d)
        live = np.flatnonzero(wanted & np.isfinite(s0) & np.isfinite(d).all(axis=1))
    for c in range(r + 1, len(cameras)):
        if not len(uv[c]) or not len(live):
            out[c] = (np.empty(0, np.int64), np.empty(0, np.int64))
            continue
        i_loc, pj = _candidates(calibration, cameras[c], uv[c], o[live], d[live], s0[live], s1[live], tolerance_px)
        out[c] = (live[i_loc], pj)
    return out


def _join(combos: np.ndarray, pair_i: np.ndarray, pair_j: np.ndarray, col: int, allow_none: bool, n: int,
          check: bool, packed: _PackedRays, footprint: np.ndarray, tolerance_px: float) -> np.ndarray:
    """Cross join of ``combos`` (Q, C + 1) (the reference detection in the last column) with pairs (i, j)
    on i into column ``col``, plus (``allow_none``) the option "none" (-1) there, keeping the rows that can
    still make an ``n``-camera combination; with ``check``, the new ray against the row's others
    (:func:`ari_sfm.particles.match_kernels.join_within_reach`)."""
    ref = combos[:, -1]
    order = np.argsort(pair_i, kind="stable")
    pi, pj = pair_i[order], pair_j[order]
    start = np.searchsorted(pi, ref, side="left").astype(np.int64)
    stop = np.searchsorted(pi, ref, side="right").astype(np.int64)
    return match_kernels.join_within_reach(np.ascontiguousarray(combos, dtype=np.int64),
                                           np.ascontiguousarray(pj, dtype=np.int64), start, stop, col, allow_none,
                                           n, check, packed.origins, packed.directions, packed.offsets,
                                           np.ascontiguousarray(footprint, dtype=float), float(tolerance_px))


def match_frame(calibration: Calibration, detections: Mapping[str, np.ndarray], tolerance_px: float,
                depth_range_mm: tuple[float, float] | None = None, volume: Volume | None = None,
                min_cameras: int = 3) -> FrameMatches:
    """Particles of one frame from their images in every camera (the steps are in the module docstring).

    Args:
        calibration: The calibration; its model must have rays through the window (exact, ari or rt).
        detections: Camera name -> (N_c, 2) pixels (a camera absent: no images).
        tolerance_px: How far (px) a ray may pass from a combination's point, and a detection from an
            epipolar curve.
        depth_range_mm: (z_min, z_max), the slab of world z (camera 0's depth) where particles can be;
            used when ``volume`` is None.
        volume: Where particles can be (world frame); None for ``depth_range_mm``.
        min_cameras: Images a particle needs, 2 to the number of cameras.

    Returns:
        The particles found, with their detection rows per camera (the calibration's camera order).

    Raises:
        ValueError: Detections of a camera not in the calibration, non-finite pixels, ``min_cameras`` or
            ``tolerance_px`` out of range, a model without rays through the window, or neither a volume
            nor a depth range.
    """
    cameras = list(calibration.cameras)
    C = len(cameras)
    unknown = [c for c in detections if c not in calibration.cameras]
    if unknown:
        raise ValueError(f"detections of camera(s) {', '.join(unknown)} not in the calibration ({', '.join(cameras)})")
    if not 2 <= min_cameras <= C:
        raise ValueError(f"min_cameras must be 2..{C} (got {min_cameras})")
    if not tolerance_px > 0:
        raise ValueError(f"tolerance_px must be > 0 (got {tolerance_px})")
    if not (calibration.spec.rays and calibration.spec.window):
        raise ValueError(f"model {calibration.model} has no rays through the window: particles need exact, ari or rt")
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
    packed = _PackedRays.of(rays)

    used = [np.zeros(len(a), bool) for a in uv]
    pairs: dict[int, dict[int, tuple[np.ndarray, np.ndarray]]] = {}  # ref camera -> camera -> candidate pairs
    chosen: list[np.ndarray] = []
    for n in range(C, min_cameras - 1, -1):  # all n-camera particles before any (n-1)-camera one
        stage = []
        for r in range(C - n + 1):  # a combination's reference is its lowest camera
            if r not in pairs:  # once, for the reference images still free when first needed
                pairs[r] = _reference_pairs(calibration, cameras, uv, rays, volume, r, ~used[r], tolerance_px)
            free_ref = np.flatnonzero(~used[r])
            combos = np.full((len(free_ref), C + 1), -1, np.int64)
            combos[:, r] = free_ref
            combos[:, -1] = free_ref
            for col in range(r + 1, C):
                pi, pj = pairs[r][col]
                free = ~used[col][pj]
                # (from the third camera on, the new ray against the others chosen, not only the reference's)
                combos = _join(combos, pi[free], pj[free], col, n < C - r, n, col > r + 1, packed, footprint,
                               tolerance_px)
            stage.append(combos[:, :C])
        combos = np.concatenate(stage)
        if not len(combos):
            continue
        acc_c, acc_s = [], []
        for k0 in range(0, len(combos), COMBO_CHUNK):
            part = combos[k0:k0 + COMBO_CHUNK]
            ok, score = _score(part, packed, footprint, volume, tolerance_px)
            acc_c.append(part[ok])
            acc_s.append(score[ok])
        chosen.append(_greedy(np.concatenate(acc_c), np.concatenate(acc_s), used, packed.offsets))
    rows = np.concatenate(chosen) if chosen else np.empty((0, C), np.int64)
    if not len(rows):
        return _empty(C)

    tracks = {}
    for k, c in enumerate(cameras):
        t = np.full((len(rows), 2), np.nan)
        seen = rows[:, k] >= 0
        t[seen] = uv[k][rows[seen, k]]
        tracks[c] = t
    X, _, _ = triangulate_pixels(calibration, tracks)
    good = np.isfinite(X).all(axis=1)
    rows, X = rows[good], X[good]
    gap = _rms_ray_distance(X, rows, rays)
    return FrameMatches(X, gap, rows)


def _ray_arrays(combos: np.ndarray, rays: list[tuple[np.ndarray, np.ndarray]]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Origins, directions (Q, C, 3) and valid (Q, C) of the rays a combination uses."""
    Q, C = combos.shape
    origins = np.zeros((Q, C, 3))
    directions = np.zeros((Q, C, 3))
    valid = combos >= 0
    for c in range(C):
        m = valid[:, c]
        if m.any():
            origins[m, c] = rays[c][0][combos[m, c]]
            directions[m, c] = rays[c][1][combos[m, c]]
    return origins, directions, valid


def _ray_distances(X: np.ndarray, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(Q, C) distance of X (Q, 3) from each unit ray."""
    r = X[:, None, :] - origins
    perp = r - np.einsum("qci,qci->qc", r, directions)[..., None] * directions
    return np.linalg.norm(perp, axis=2)


@dataclass(frozen=True)
class _PackedRays:
    """Every camera's rays in one array (what the compiled scoring reads): camera c's ray k at
    ``offsets[c] + k``."""

    origins: np.ndarray  # (sum N_c, 3)
    directions: np.ndarray  # (sum N_c, 3)
    offsets: np.ndarray  # (C + 1,) int64

    @staticmethod
    def of(rays: list[tuple[np.ndarray, np.ndarray]]) -> _PackedRays:
        counts = [len(o) for o, _ in rays]
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        return _PackedRays(np.ascontiguousarray(np.concatenate([o for o, _ in rays]).reshape(-1, 3), dtype=float),
                           np.ascontiguousarray(np.concatenate([d for _, d in rays]).reshape(-1, 3), dtype=float),
                           offsets)


def _score(combos: np.ndarray, packed: _PackedRays, footprint: np.ndarray, volume: Volume, tolerance_px: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """Accepted (Q,) and score (Q,): RMS over the rays of their distance from their least-squares point,
    in pixels; accepted when every ray is within the tolerance and the point inside the volume grown by the
    tolerance's footprint (compiled: :func:`ari_sfm.particles.match_kernels.score_combos`)."""
    box = volume.box_from_world
    return match_kernels.score_combos(
        np.ascontiguousarray(combos, dtype=np.int64), packed.origins, packed.directions, packed.offsets,
        np.ascontiguousarray(footprint, dtype=float), np.ascontiguousarray(box.R, dtype=float),
        np.ascontiguousarray(box.t, dtype=float), np.asarray(volume.min_mm, dtype=float),
        np.asarray(volume.max_mm, dtype=float), float(tolerance_px * float(footprint.max())), float(tolerance_px),
        MIN_DET)


def _greedy(combos: np.ndarray, score: np.ndarray, used: list[np.ndarray], offsets: np.ndarray) -> np.ndarray:
    """Best first (smaller score), each detection used once (``used`` per camera, updated): the chosen rows."""
    flat = np.concatenate(used) if used else np.zeros(0, bool)
    keep = match_kernels.greedy_rows(np.ascontiguousarray(combos, dtype=np.int64),
                                     np.argsort(score, kind="stable").astype(np.int64), flat, offsets)
    for c, u in enumerate(used):
        u[:] = flat[offsets[c]:offsets[c + 1]]
    return combos[keep]


def _rms_ray_distance(X: np.ndarray, rows: np.ndarray, rays) -> np.ndarray:
    """(M,) RMS distance of each particle's rays from its (refined) point (mm)."""
    origins, directions, valid = _ray_arrays(rows, rays)
    d = np.where(valid, _ray_distances(X, origins, directions), 0.0)
    return np.sqrt((d ** 2).sum(axis=1) / valid.sum(axis=1))

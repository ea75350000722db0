"""The particle matching's compiled steps against the numpy code they replaced (kept here as the reference):
the same candidate pairs, the same accepted combinations and scores, the same greedy choice."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ari_sfm.geometry import Pose, rotation_from_rotvec
from ari_sfm.particles import match_kernels
from ari_sfm.particles.match import _greedy, _PackedRays, _score
from ari_sfm.particles.volume import Volume
from ari_sfm.reconstruction.triangulate import triangulate_rays


def reference_band_pairs(p: np.ndarray, uv: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """The numpy version: a k-d tree of the segments' midpoints against one of the detections, then the exact
    point-to-segment distance."""
    n, K = p.shape[:2]
    a, b = p[:, :-1].reshape(-1, 2), p[:, 1:].reshape(-1, 2)
    seg = np.flatnonzero(np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1))
    if not len(seg):
        return np.empty(0, np.int64), np.empty(0, np.int64)
    mid = 0.5 * (a[seg] + b[seg])
    reach = float(0.5 * np.linalg.norm(b[seg] - a[seg], axis=1).max()) + tolerance
    near = cKDTree(mid).sparse_distance_matrix(cKDTree(uv), reach, output_type="ndarray")
    seg_of = seg[near["i"]]
    j = near["j"].astype(np.int64)
    A, B, P = a[seg_of], b[seg_of], uv[j]
    AB = B - A
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = np.clip(np.einsum("ij,ij->i", P - A, AB) / np.einsum("ij,ij->i", AB, AB), 0.0, 1.0)
    lam = np.nan_to_num(lam)
    dist = np.linalg.norm(A + lam[:, None] * AB - P, axis=1)
    keep = dist <= tolerance
    key = np.unique(seg_of[keep] // (K - 1) * len(uv) + j[keep])
    return key // len(uv), key % len(uv)


def reference_score(combos, rays, footprint, volume, tolerance_px):
    """The numpy version of the scoring (triangulate_rays, then each ray's distance in pixels)."""
    Q, C = combos.shape
    origins, directions = np.zeros((Q, C, 3)), np.zeros((Q, C, 3))
    valid = combos >= 0
    for c in range(C):
        m = valid[:, c]
        origins[m, c], directions[m, c] = rays[c][0][combos[m, c]], rays[c][1][combos[m, c]]
    X, _ = triangulate_rays(origins, directions, valid)
    r = X[:, None, :] - origins
    perp = r - np.einsum("qci,qci->qc", r, directions)[..., None] * directions
    with np.errstate(invalid="ignore"):
        dist_px = np.where(valid, np.linalg.norm(perp, axis=2) / footprint[None, :], 0.0)
        score = np.sqrt((dist_px ** 2).sum(axis=1) / valid.sum(axis=1))
        ok = np.isfinite(X).all(axis=1) & (dist_px.max(axis=1) <= tolerance_px)
    ok[ok] &= volume.contains(X[ok], margin_mm=tolerance_px * float(footprint.max()))
    return ok, score


def reference_greedy(combos, score, used):
    keep = []
    for q in np.argsort(score, kind="stable"):
        cams = [c for c in range(combos.shape[1]) if combos[q, c] >= 0]
        if any(used[c][combos[q, c]] for c in cams):
            continue
        for c in cams:
            used[c][combos[q, c]] = True
        keep.append(q)
    return combos[np.asarray(keep, np.int64)]


@pytest.mark.parametrize("tolerance", [0.5, 2.0, 30.0])
def test_band_pairs_are_the_k_d_tree_pairs(tolerance):
    """Curves of random segments (some with a NaN end, some of zero length) over 3000 detections: the grid
    finds exactly the pairs the k-d trees found, sorted by curve then detection."""
    rng = np.random.default_rng(7)
    n, K, N = 400, 12, 3000
    start = rng.uniform(0, 1280, (n, 1, 2))
    step = rng.normal(0, 12.0, (n, 1, 2)) + rng.normal(0, 0.3, (n, K, 2))
    p = start + np.cumsum(step, axis=1)
    p[rng.random((n, K)) < 0.03] = np.nan
    p[:5, 3] = p[:5, 2]  # zero-length segments
    uv = rng.uniform(0, 1280, (N, 2))
    uv[:50] = p[rng.integers(0, n, 50), rng.integers(0, K, 50)] + rng.normal(0, 0.2, (50, 2))
    uv = uv[np.isfinite(uv).all(axis=1)]
    for cell in (16.0, 3.0):
        i, j = match_kernels.band_pairs(p, uv, tolerance, max(cell, tolerance))
        ri, rj = reference_band_pairs(p, uv, tolerance)
        assert len(ri) > 0
        np.testing.assert_array_equal(i, ri)
        np.testing.assert_array_equal(j, rj)


def _rays(rng, C: int, N: int):
    """Rays of C cameras ~400 mm from a box, through points of the box (some detections of each camera on the
    same points), with a few non-finite rays."""
    points = rng.uniform([-30, -20, 385], [30, 20, 415], (N, 3))
    rays = []
    for c in range(C):
        centre = np.array([100 * np.cos(c), 100 * np.sin(c), 0.0])
        target = points[rng.permutation(N)] + rng.normal(0, 0.02, (N, 3))
        d = target - centre
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = centre + 30.0 * d
        o[rng.random(N) < 0.02] = np.nan
        rays.append((o, d))
    return rays


def test_scoring_and_greedy_are_the_numpy_ones():
    """Random combinations of 4 cameras' rays (-1: unused), the box turned and moved: the same accepted set,
    the same scores to rounding, and then the same greedy choice."""
    rng = np.random.default_rng(3)
    C, N, Q = 4, 300, 20000
    rays = _rays(rng, C, N)
    combos = rng.integers(0, N, (Q, C))
    combos[rng.random((Q, C)) < 0.3] = -1
    same = rng.integers(0, N, Q // 4)  # combinations of the same point (rays meet)
    combos[: Q // 4] = np.stack([np.argsort(rng.permutation(N))[same] for _ in range(C)], 1)
    footprint = np.array([0.06, 0.065, 0.07, 0.058])
    box = Pose(rotation_from_rotvec(np.array([0.01, -0.02, 0.3])), np.array([1.0, -2.0, -400.0]))
    volume = Volume(np.array([-28.0, -18.0, -14.0]), np.array([28.0, 18.0, 14.0]), box)
    for tolerance in (0.5, 40.0):
        ok, score = _score(combos, _PackedRays.of(rays), footprint, volume, tolerance)
        rok, rscore = reference_score(combos, rays, footprint, volume, tolerance)
        assert 0 < ok.sum() < Q
        np.testing.assert_array_equal(ok, rok)
        np.testing.assert_allclose(score[ok], rscore[ok], rtol=1e-9, atol=1e-12)
        used = [np.zeros(N, bool) for _ in range(C)]
        ref_used = [np.zeros(N, bool) for _ in range(C)]
        chosen = _greedy(combos[ok], rscore[ok], used, _PackedRays.of(rays).offsets)
        np.testing.assert_array_equal(chosen, reference_greedy(combos[ok], rscore[ok], ref_used))
        for a, b in zip(used, ref_used):
            np.testing.assert_array_equal(a, b)


def test_band_pairs_far_off_curves_and_spread_detections():
    """Segments far off the image (1e30 px) and detections spread over 1e7 px (the grid's cell grows) give
    the k-d trees' pairs, without an index overflow."""
    rng = np.random.default_rng(11)
    uv = np.concatenate([rng.uniform(0, 1000, (500, 2)), [[1e7, 1e7], [-5e6, 3e6]]])
    p = np.concatenate([rng.uniform(0, 1000, (60, 1, 2)) + np.cumsum(rng.normal(0, 10, (60, 8, 2)), axis=1),
                        np.full((2, 8, 2), 1e30), np.linspace([9.99e6, 9.99e6], [1.001e7, 1.001e7], 8)[None]])
    i, j = match_kernels.band_pairs(p, uv, 3.0, 16.0)
    ri, rj = reference_band_pairs(p, uv, 3.0)
    assert 0 < len(ri) and (61 + 1) in set(ri.tolist())  # the last curve passes through the far detection
    np.testing.assert_array_equal(i, ri)
    np.testing.assert_array_equal(j, rj)


def reference_join(combos, pair_i, pair_j, col, allow_none, n):
    """The numpy cross join (every candidate, then the rows that can still make an n-camera combination)."""
    C = combos.shape[1] - 1
    ref = combos[:, -1]
    order = np.argsort(pair_i, kind="stable")
    pi, pj = pair_i[order], pair_j[order]
    start, stop = np.searchsorted(pi, ref, side="left"), np.searchsorted(pi, ref, side="right")
    count = stop - start + (1 if allow_none else 0)
    rows = np.repeat(np.arange(len(combos)), count)
    out = combos[rows].copy()
    k = np.arange(len(rows)) - np.repeat(np.cumsum(count) - count, count)
    real = k < (stop - start)[rows]
    out[:, col] = -1
    out[real, col] = pj[(start[rows] + k)[real]]
    have = (out[:, :C] >= 0).sum(axis=1)
    return out[(have <= n) & (have + (C - 1 - col) >= n)]


@pytest.mark.parametrize("tolerance,n", [(0.5, 4), (12.0, 4), (12.0, 3)])
def test_the_pruned_join_keeps_what_the_scoring_accepts_in_its_order(tolerance, n):
    """Combinations built camera by camera from candidate pairs (each reference's own particle and random
    others): leaving out the partial ones whose newest ray misses another by more than any accepted one's
    could changes neither the accepted combinations nor their order (so the greedy choice is the same),
    and leaves out most of the rest."""
    from ari_sfm.particles.match import _join

    rng = np.random.default_rng(7)
    C, N = 4, 300
    points = rng.uniform([-30, -20, 385], [30, 20, 415], (N, 3))
    rays, of_point = [], []
    for c in range(C):
        perm = rng.permutation(N)  # detection k of camera c is the image of point perm[k]
        centre = np.array([100 * np.cos(c), 100 * np.sin(c), 0.0])
        d = points[perm] + rng.normal(0, 0.01, (N, 3)) - centre
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        rays.append((centre + 30.0 * d, d))
        of_point.append(np.argsort(perm))  # point -> its detection in camera c
    packed = _PackedRays.of(rays)
    footprint = np.array([0.06, 0.065, 0.07, 0.058])
    volume = Volume(np.array([-30.0, -20.0, 385.0]), np.array([30.0, 20.0, 415.0]))
    start = np.full((N, C + 1), -1, np.int64)
    start[:, 0] = start[:, -1] = np.arange(N)
    pruned, plain = start, start
    ref_point = np.empty(N, np.int64)
    ref_point[of_point[0]] = np.arange(N)  # reference detection -> its point
    for col in range(1, C):
        i = np.repeat(np.arange(N), 8)
        j = rng.integers(0, N, len(i))
        j[::8] = of_point[col][ref_point]  # the reference's own particle among its candidates
        pruned = _join(pruned, i, j, col, n < C, n, col > 1, packed, footprint, tolerance)
        plain_next = reference_join(plain, i, j, col, n < C, n)
        if col == 1:  # the reference's candidates: nothing to check yet
            np.testing.assert_array_equal(pruned, plain_next)
        plain = plain_next
    assert len(pruned) < 0.5 * len(plain)
    ok_p, score_p = _score(pruned[:, :C], packed, footprint, volume, tolerance)
    ok, score = _score(plain[:, :C], packed, footprint, volume, tolerance)
    assert ok.sum() > 0.5 * N
    np.testing.assert_array_equal(pruned[ok_p, :C], plain[ok, :C])
    np.testing.assert_array_equal(score_p[ok_p], score[ok])

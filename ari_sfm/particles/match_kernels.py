"""The particle matching's inner loops, compiled (numba, ``cache=True``): :mod:`ari_sfm.particles.match`
calls them, the algorithm is described there.

- :func:`band_pairs`: which detections lie within the tolerance of each reference ray's sampled epipolar
  curve. The detections are bucketed in a grid of square cells (a counting sort, no tree); each segment
  of a curve visits only the cells its box grown by the tolerance overlaps and measures the exact
  point-to-segment distance there.
- :func:`score_combos`: the least-squares point of each combination's rays (as
  :func:`ari_sfm.reconstruction.triangulate.triangulate_rays` forms it), each ray's distance from it in pixels of its
  camera, the acceptance (every ray within the tolerance, the point inside the volume grown by the
  margin) and the RMS score; one pass, no (Q, C, 3) temporaries.
- :func:`join_within_reach`: the combinations built camera by camera, a partial one whose newest ray misses
  another by more than any accepted combination's could left out before the next camera is joined.
- :func:`greedy_rows`: the combinations taken best first, each detection used once.
"""
from __future__ import annotations

import math

import numpy as np

from ..kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first

_JIT = dict(cache=True, nogil=True, error_model="numpy")
MAX_GRID_SIDE = 4096  # cells along a side of the detections' grid at most (the cell grows beyond)


@njit(inline="always", **_JIT)
def _cell_index(x, n):
    """floor(x) as a cell index, held to [-1, n] (a coordinate far off the grid, however large)."""
    if x < 0.0:
        return -1
    if x >= n:
        return n
    return int(math.floor(x))


# C901: a compiled kernel kept in one piece: the detections' grid and the curves' search over it share its local
# arrays in one compiled loop nest (no calls passing them)
@njit(**_JIT)
def band_pairs(p, uv, tolerance, cell):  # noqa: C901
    """The detections within the tolerance of each sampled epipolar curve.

    Args:
        p: The curves, polylines (n, K, 2) px; a segment with a non-finite end is skipped.
        uv: The detections (N, 2) px.
        tolerance: Largest distance (px) from a segment of the curve.
        cell: The grid's cell size (px); at least the tolerance keeps the visited cells few. It grows so
            that the grid has at most MAX_GRID_SIDE cells a side.

    Returns:
        (i, j), each (P,) int64, sorted by i then j, each pair once: detection ``uv[j]`` lies within
        ``tolerance`` of curve ``p[i]``.
    """
    n, K = p.shape[0], p.shape[1]
    N = uv.shape[0]
    out_i = np.empty(0, np.int64)
    out_j = np.empty(0, np.int64)
    if n == 0 or N == 0 or K < 2:
        return out_i, out_j
    x0, y0 = uv[0, 0], uv[0, 1]
    x1, y1 = x0, y0
    for j in range(N):
        x0, x1 = min(x0, uv[j, 0]), max(x1, uv[j, 0])
        y0, y1 = min(y0, uv[j, 1]), max(y1, uv[j, 1])
    cell = max(cell, (x1 - x0) / MAX_GRID_SIDE, (y1 - y0) / MAX_GRID_SIDE)  # a bounded grid for any spread
    nx = int((x1 - x0) / cell) + 1
    ny = int((y1 - y0) / cell) + 1
    start = np.zeros(nx * ny + 1, np.int64)
    cell_of = np.empty(N, np.int64)
    for j in range(N):
        k = int((uv[j, 1] - y0) / cell) * nx + int((uv[j, 0] - x0) / cell)
        cell_of[j] = k
        start[k + 1] += 1
    for k in range(nx * ny):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    members = np.empty(N, np.int64)
    for j in range(N):  # ascending j within each cell
        members[fill[cell_of[j]]] = j
        fill[cell_of[j]] += 1
    stamp = np.full(N, -1, np.int64)  # the last curve that took detection j
    found = np.empty(N, np.int64)
    cap = 4 * n + 16
    out_i = np.empty(cap, np.int64)
    out_j = np.empty(cap, np.int64)
    m = 0
    for i in range(n):
        nf = 0
        for s in range(K - 1):
            ax, ay, bx, by = p[i, s, 0], p[i, s, 1], p[i, s + 1, 0], p[i, s + 1, 1]
            if not (math.isfinite(ax) and math.isfinite(ay) and math.isfinite(bx) and math.isfinite(by)):
                continue
            c0 = _cell_index((min(ax, bx) - tolerance - x0) / cell, nx)
            c1 = _cell_index((max(ax, bx) + tolerance - x0) / cell, nx)
            r0 = _cell_index((min(ay, by) - tolerance - y0) / cell, ny)
            r1 = _cell_index((max(ay, by) + tolerance - y0) / cell, ny)
            if c1 < 0 or c0 >= nx or r1 < 0 or r0 >= ny:  # the segment's box misses the detections' grid
                continue
            c0, c1, r0, r1 = max(c0, 0), min(c1, nx - 1), max(r0, 0), min(r1, ny - 1)
            abx, aby = bx - ax, by - ay
            den = abx * abx + aby * aby
            for r in range(r0, r1 + 1):
                for c in range(c0, c1 + 1):
                    k = r * nx + c
                    for q in range(start[k], start[k + 1]):
                        j = members[q]
                        if stamp[j] == i:
                            continue
                        px, py = uv[j, 0], uv[j, 1]
                        lam = ((px - ax) * abx + (py - ay) * aby) / den
                        if lam != lam:
                            lam = 0.0
                        elif lam < 0.0:
                            lam = 0.0
                        elif lam > 1.0:
                            lam = 1.0
                        dx = ax + lam * abx - px
                        dy = ay + lam * aby - py
                        if math.sqrt(dx * dx + dy * dy) <= tolerance:
                            stamp[j] = i
                            found[nf] = j
                            nf += 1
        if nf == 0:
            continue
        js = np.sort(found[:nf])
        if m + nf > cap:
            cap = max(2 * cap, m + nf)
            grown_i = np.empty(cap, np.int64)
            grown_j = np.empty(cap, np.int64)
            grown_i[:m] = out_i[:m]
            grown_j[:m] = out_j[:m]
            out_i, out_j = grown_i, grown_j
        for q in range(nf):
            out_i[m + q] = i
            out_j[m + q] = js[q]
        m += nf
    return out_i[:m].copy(), out_j[:m].copy()


@njit(**_JIT)
def score_combos(combos, origins, directions, offsets, footprint, box_R, box_t, box_min, box_max, margin,
                 tolerance, min_det):
    """Score combinations by their rays' least-squares point.

    For each combination: the least-squares point X of its used rays (none with < 2 finite rays, a used
    ray that is not finite, or det <= ``min_det``), each used ray's distance from X over ``footprint[c]``
    (mm per px); accepted when every one is within ``tolerance`` and ``box_R X + box_t`` is within
    [box_min - margin, box_max + margin].

    Args:
        combos: (Q, C) a detection row per camera, -1: unused.
        origins: All cameras' ray origins (sum N_c, 3); camera c's ray of row k is at ``offsets[c] + k``.
        directions: The rays' directions (sum N_c, 3) (normalised here).
        offsets: (C + 1,) int64 start of each camera's rays.
        footprint: (C,) mm per px of each camera at the volume.
        box_R: (3, 3) rotation of the volume's box_from_world.
        box_t: (3,) its translation.
        box_min: (3,) the box's lower bounds (mm).
        box_max: (3,) its upper bounds (mm).
        margin: The box is grown by this (mm).
        tolerance: Largest distance of a ray from X (px).
        min_det: Smallest determinant of the normal equations.

    Returns:
        (accepted (Q,) bool, score (Q,): the RMS of the rays' distances in px, NaN where there is no point).
    """
    Q, C = combos.shape
    ok = np.zeros(Q, np.bool_)
    score = np.empty(Q)
    o = np.empty((C, 3))
    d = np.empty((C, 3))
    used = np.zeros(C, np.bool_)
    fin = np.zeros(C, np.bool_)
    for q in range(Q):
        a00 = a01 = a02 = a11 = a12 = a22 = 0.0
        b0 = b1 = b2 = 0.0
        n_used = 0
        n_fin = 0
        for c in range(C):
            row = combos[q, c]
            used[c] = row >= 0
            fin[c] = False
            if not used[c]:
                continue
            n_used += 1
            k = offsets[c] + row
            for i in range(3):
                o[c, i] = origins[k, i]
            norm = math.sqrt(directions[k, 0] * directions[k, 0] + directions[k, 1] * directions[k, 1]
                             + directions[k, 2] * directions[k, 2])
            for i in range(3):
                d[c, i] = directions[k, i] / norm
            fin[c] = (math.isfinite(o[c, 0]) and math.isfinite(o[c, 1]) and math.isfinite(o[c, 2])
                      and math.isfinite(d[c, 0]) and math.isfinite(d[c, 1]) and math.isfinite(d[c, 2]))
            if not fin[c]:
                continue
            n_fin += 1
            d0, d1, d2 = d[c, 0], d[c, 1], d[c, 2]
            do = d0 * o[c, 0] + d1 * o[c, 1] + d2 * o[c, 2]
            a00 += 1.0 - d0 * d0
            a01 -= d0 * d1
            a02 -= d0 * d2
            a11 += 1.0 - d1 * d1
            a12 -= d1 * d2
            a22 += 1.0 - d2 * d2
            b0 += o[c, 0] - d0 * do
            b1 += o[c, 1] - d1 * do
            b2 += o[c, 2] - d2 * do
        score[q] = np.nan
        if n_fin < 2 or n_fin < n_used:  # a used ray that is not finite: no acceptable point
            continue
        c00, c01, c02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
        c11, c12, c22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
        det = a00 * c00 + a01 * c01 + a02 * c02
        if not det > min_det:
            continue
        inv = 1.0 / det
        X0 = (c00 * b0 + c01 * b1 + c02 * b2) * inv
        X1 = (c01 * b0 + c11 * b1 + c12 * b2) * inv
        X2 = (c02 * b0 + c12 * b1 + c22 * b2) * inv
        if not (math.isfinite(X0) and math.isfinite(X1) and math.isfinite(X2)):
            continue
        worst = 0.0
        sq = 0.0
        for c in range(C):
            if not used[c]:
                continue
            r0, r1, r2 = X0 - o[c, 0], X1 - o[c, 1], X2 - o[c, 2]
            s = r0 * d[c, 0] + r1 * d[c, 1] + r2 * d[c, 2]
            q0, q1, q2 = r0 - s * d[c, 0], r1 - s * d[c, 1], r2 - s * d[c, 2]
            px = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2) / footprint[c]
            worst = max(worst, px)
            sq += px * px
        score[q] = math.sqrt(sq / n_used)
        if not worst <= tolerance:
            continue
        inside = True
        for i in range(3):
            x = box_R[i, 0] * X0 + box_R[i, 1] * X1 + box_R[i, 2] * X2 + box_t[i]
            if not (x >= box_min[i] - margin and x <= box_max[i] + margin):
                inside = False
        ok[q] = inside
    return ok, score


@njit(inline="always", **_JIT)
def _within_reach(combos, q, col, kb, origins, directions, offsets, footprint, tolerance):
    """Whether ray ``kb`` (column ``col``'s) passes within tolerance (footprint[a] + footprint[col]) mm of
    the ray of every other used column a of row q (:func:`join_within_reach`); nearly parallel rays pass."""
    C = offsets.shape[0] - 1
    ob0, ob1, ob2 = origins[kb, 0], origins[kb, 1], origins[kb, 2]
    db0, db1, db2 = directions[kb, 0], directions[kb, 1], directions[kb, 2]
    for a in range(C):
        if a == col or combos[q, a] < 0:
            continue
        ka = offsets[a] + combos[q, a]
        da0, da1, da2 = directions[ka, 0], directions[ka, 1], directions[ka, 2]
        n0, n1, n2 = da1 * db2 - da2 * db1, da2 * db0 - da0 * db2, da0 * db1 - da1 * db0
        nn = n0 * n0 + n1 * n1 + n2 * n2
        scale = (da0 * da0 + da1 * da1 + da2 * da2) * (db0 * db0 + db1 * db1 + db2 * db2)
        if not nn > 1e-12 * scale:  # (nearly) parallel, or not finite: the scoring decides
            continue
        gap = abs((ob0 - origins[ka, 0]) * n0 + (ob1 - origins[ka, 1]) * n1 + (ob2 - origins[ka, 2]) * n2)
        if gap * gap > nn * (tolerance * (footprint[a] + footprint[col]) * (1.0 + 1e-9)) ** 2:
            return False
    return True


@njit(**_JIT)
def join_within_reach(combos, pj_sorted, start, stop, col, allow_none, n, check, origins, directions, offsets,
                      footprint, tolerance):
    """Join a camera's candidates to partial combinations, leaving out those no accepted one can hold.

    Each row of ``combos`` is joined with each of its candidates in column ``col``, then (``allow_none``)
    with the option -1 there, in that order; only the rows that can still make an ``n``-camera combination
    are kept. With ``check``, a candidate whose ray misses another of the row's by more than any accepted
    combination's could is left out: every ray within tolerance x footprint[c] of one point (what
    :func:`score_combos` accepts) puts any two within the sum of theirs, so the accepted combinations,
    and their order, are those of the whole join.

    Args:
        combos: (Q, C + 1) partial combinations, the reference detection in the last column.
        pj_sorted: Candidate detections of camera ``col``, grouped by reference detection.
        start: (Q,) first candidate of each row in ``pj_sorted``.
        stop: (Q,) end of each row's candidates in ``pj_sorted``.
        col: The column (camera) joined.
        allow_none: Also join the option "no detection" (-1).
        n: The number of cameras the combinations must reach.
        check: Leave out candidates whose ray is out of reach of the row's others.
        origins: All cameras' ray origins (sum N_c, 3).
        directions: Their directions (sum N_c, 3).
        offsets: (C + 1,) int64 start of each camera's rays.
        footprint: (C,) mm per px of each camera at the volume.
        tolerance: The matching tolerance (px).

    Returns:
        The joined rows (Q', C + 1) int64.
    """
    Q, W = combos.shape
    C = offsets.shape[0] - 1
    cap = max(16, 2 * Q)
    out = np.empty((cap, W), np.int64)
    m = 0
    for q in range(Q):
        h0 = 0
        for a in range(C):
            if combos[q, a] >= 0:
                h0 += 1
        for option in range(stop[q] - start[q] + (1 if allow_none else 0)):
            real = option < stop[q] - start[q]
            have = h0 + 1 if real else h0
            if not (have <= n and have + (C - 1 - col) >= n):
                continue
            j = pj_sorted[start[q] + option] if real else -1
            if real and check and not _within_reach(combos, q, col, offsets[col] + j, origins, directions, offsets,
                                                    footprint, tolerance):
                continue
            if m == cap:
                cap *= 2
                grown = np.empty((cap, W), np.int64)
                grown[:m] = out[:m]
                out = grown
            for a in range(W):
                out[m, a] = combos[q, a]
            out[m, col] = j
            m += 1
    return out[:m].copy()

@njit(**_JIT)
def greedy_rows(combos, order, used, offsets):
    """Take combinations best first, each detection used once.

    Args:
        combos: (Q, C) a detection row per camera, -1: unused.
        order: Indices into ``combos``, best first.
        used: The cameras' flags, camera c's detection k at ``offsets[c] + k``; updated in place.
        offsets: (C + 1,) int64 start of each camera's flags.

    Returns:
        The indices into ``combos`` taken, in the order taken.
    """
    Q, C = combos.shape
    keep = np.empty(Q, np.int64)
    m = 0
    for q in order:
        free = True
        for c in range(C):
            row = combos[q, c]
            if row >= 0 and used[offsets[c] + row]:
                free = False
                break
        if not free:
            continue
        for c in range(C):
            row = combos[q, c]
            if row >= 0:
                used[offsets[c] + row] = True
        keep[m] = q
        m += 1
    return keep[:m].copy()

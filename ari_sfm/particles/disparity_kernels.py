"""The disparity peak search's pairwise count, compiled (numba, ``cache=True``): for every match, how many
matches lie within a radius of it in every camera both use (:func:`ari_sfm.particles.disparity._joint_peak`).

The joint distance of matches i and j is the largest over the cameras both use of the pixel distance
between their disparities, ``sqrt(dx^2 + dy^2)`` as ``numpy.linalg.norm`` forms it; a pair counts when it
is within the radius and shares at least two cameras. O(n^2) pairs, no temporaries.
"""
from __future__ import annotations

import math

import numpy as np

from ..kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def joint_counts(d, radius):
    """Count each match's neighbours in every camera.

    Args:
        d: Disparities (n, C, 2) px, NaN where a camera is unused.
        radius: Largest joint distance (px).

    Returns:
        (n,) int64: per match i the matches j (i itself included) whose joint distance is <= ``radius``
        over at least two shared cameras.
    """
    return joint_counts_against(d, d, radius)


@njit(**_JIT)
def joint_counts_against(q, d, radius):
    """Count the neighbours of query matches among other matches (as :func:`joint_counts`).

    Args:
        q: Query disparities (k, C, 2) px, NaN where a camera is unused.
        d: Disparities (n, C, 2) px.
        radius: Largest joint distance (px).

    Returns:
        (k,) int64: per query match the matches of ``d`` within ``radius`` over at least two shared cameras.
    """
    k, n, C = q.shape[0], d.shape[0], d.shape[1]
    out = np.zeros(k, np.int64)
    for i in range(k):
        count = 0
        for j in range(n):
            worst = 0.0
            shared = 0
            for c in range(C):
                dx = q[i, c, 0] - d[j, c, 0]
                dy = q[i, c, 1] - d[j, c, 1]
                if math.isnan(dx) or math.isnan(dy):
                    continue
                dist = math.sqrt(dx * dx + dy * dy)
                shared += 1
                if dist > worst:
                    worst = dist
                    if worst > radius:
                        break
            if worst <= radius and shared >= 2:
                count += 1
        out[i] = count
    return out

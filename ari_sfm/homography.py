"""Plane-to-image homographies by the normalised direct linear transform, many views at once.

Used by the quality gate's floor (:mod:`ari_sfm.quality`: every plane of up to eight views mapped
by its own homography). Points are normalised per view (Hartley: centred, RMS radius sqrt(2)),
so the estimate is that of ``cv2.findHomography(..., 0)`` before its iterative refinement of the
geometric error. (Zhang's start keeps OpenCV's refined homographies: started from these, the
exact stage's coarse normal search of a far-off under-water case picked another direction.)
"""
from __future__ import annotations

import math

import numpy as np


def normalised(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Views' points (V, N, 2) centred and scaled to an RMS radius of sqrt(2) (Hartley), and those
    3x3 maps (V, 3, 3)."""
    c = p.mean(axis=1)
    q = p - c[:, None]
    radius = np.sqrt(np.einsum("vnk,vnk->v", q, q) / p.shape[1])
    scale = math.sqrt(2.0) / np.maximum(radius, 1e-12)
    T = np.zeros((len(p), 3, 3))
    T[:, 0, 0], T[:, 1, 1], T[:, 2, 2] = scale, scale, 1.0
    T[:, :2, 2] = -scale[:, None] * c
    return q * scale[:, None, None], T


def homographies(xy: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The homographies (V, 3, 3) mapping V views' plane points ``xy`` to their pixels ``uv`` (each
    (V, N, 2), N >= 4), each up to scale; not finite when points are not."""
    V, n = xy.shape[:2]
    a, Ta = normalised(np.asarray(xy, float))
    b, Tb = normalised(np.asarray(uv, float))
    one, zero = np.ones((V, n)), np.zeros((V, n))
    ax, ay, bx, by = a[..., 0], a[..., 1], b[..., 0], b[..., 1]
    rows = np.concatenate([np.stack([ax, ay, one, zero, zero, zero, -bx * ax, -bx * ay, -bx], axis=2),
                           np.stack([zero, zero, zero, ax, ay, one, -by * ax, -by * ay, -by], axis=2)], axis=1)
    try:  # the least eigenvector of A^T A (normalised points keep it well conditioned; 3x faster than A's SVD)
        h = np.linalg.eigh(np.swapaxes(rows, 1, 2) @ rows)[1][:, :, 0]
    except np.linalg.LinAlgError:  # non-finite points
        return np.full((V, 3, 3), np.nan)
    return np.linalg.solve(Tb, h.reshape(V, 3, 3) @ Ta)

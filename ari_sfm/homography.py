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

INVERSE_ITERATIONS = 4  # each shrinks the error by the DLT's eigenvalue ratio (1e-3 even at 10 px of noise)
SHIFT = 1e-13  # of A^T A's trace, added to its diagonal: exact points (a zero eigenvalue) stay invertible


def normalised(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Views' points (V, N, 2) centred and scaled to an RMS radius of sqrt(2) (Hartley), with each
    view's centre (V, 2) and scale (V,)."""
    c = p.sum(axis=1) / p.shape[1]
    q = p - c[:, None]
    radius = np.sqrt(np.einsum("vnk,vnk->v", q, q) / p.shape[1])
    scale = math.sqrt(2.0) / np.maximum(radius, 1e-12)
    return q * scale[:, None, None], c, scale


def homographies_normalised(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The DLT homographies (V, 3, 3), each of unit norm, mapping normalised plane points ``a`` to
    normalised pixels ``b`` (each (V, N, 2)): the least eigenvector of ``A^T A`` of the DLT rows,
    by inverse iteration (a 9x9 inverse per view; LAPACK's eigen-solver is 5x slower here); not
    finite when points are not."""
    V, n = a.shape[:2]
    rows = np.zeros((V, 2, n, 9))
    rows[:, 0, :, 0:2] = a
    rows[:, 1, :, 3:5] = a
    rows[:, 0, :, 2] = rows[:, 1, :, 5] = 1.0
    rows[:, 0, :, 6:8] = -b[..., 0, None] * a
    rows[:, 1, :, 6:8] = -b[..., 1, None] * a
    rows[:, 0, :, 8] = -b[..., 0]
    rows[:, 1, :, 8] = -b[..., 1]
    rows = rows.reshape(V, 2 * n, 9)
    M = np.swapaxes(rows, 1, 2) @ rows
    M += (SHIFT * np.trace(M, axis1=1, axis2=2))[:, None, None] * np.eye(9)
    try:
        M_inv = np.linalg.inv(M)
    except np.linalg.LinAlgError:  # non-finite points
        return np.full((V, 3, 3), np.nan)
    h = M_inv[:, :, 8]  # the first step from h = e9
    for _ in range(INVERSE_ITERATIONS):
        h = h / np.linalg.norm(h, axis=1, keepdims=True)
        h = np.einsum("vij,vj->vi", M_inv, h)
    return (h / np.linalg.norm(h, axis=1, keepdims=True)).reshape(V, 3, 3)


def homographies(xy: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The homographies (V, 3, 3) mapping V views' plane points ``xy`` to their pixels ``uv`` (each
    (V, N, 2), N >= 4), each up to scale; not finite when points are not."""
    a, ca, sa = normalised(np.asarray(xy, float))
    b, cb, sb = normalised(np.asarray(uv, float))
    return denormalised(homographies_normalised(a, b), ca, sa, cb, sb)


def denormalised(h: np.ndarray, ca: np.ndarray, sa: np.ndarray, cb: np.ndarray, sb: np.ndarray) -> np.ndarray:
    """``Tb^-1 h Ta`` of normalised homographies h (V, 3, 3), T = [[s, 0, -s cx], [0, s, -s cy], [0, 0, 1]]."""
    H = h * sa[:, None, None]  # h Ta: the columns scaled, the last one shifted
    H[:, :, 2] = h[:, :, 2] - np.einsum("vij,vj->vi", H[:, :, :2], ca)
    H[:, :2, :] = H[:, :2, :] / sb[:, None, None] + cb[:, :, None] * H[:, 2, None, :]  # Tb^-1 applied
    return H

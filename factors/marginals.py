"""Marginal covariances of the numpy backend's global variables, keyed as gtsam.Marginals.

What ``gtsam.Marginals(graph, values).marginalCovariance(key)`` gives for the
intrinsics K(c), the camera poses C(c) (c > 0), the normal N and the distance
H: the same tangent spaces, from the inverse Schur complement of the frames
(:func:`~ari_sfm.solver.schur.global_covariance`). The units are those of the
graph's factors: physical when they carry the pixel sigma (see
:func:`ari_sfm.factors.uncertainty.marginal_covariances`, the documented entry).
"""
from __future__ import annotations

import gtsam
import numpy as np

from ..solver.schur import NormalEquations, global_covariance
from . import keys as K_
from .variables import PackedColumns


class CovarianceTable:
    """Marginal covariances by key, with gtsam.Marginals' ``marginalCovariance(key)``."""

    def __init__(self, covariances: dict[int, np.ndarray]) -> None:
        self.covariances = covariances

    def marginalCovariance(self, key: int) -> np.ndarray:  # noqa: N802 (gtsam's name)
        try:
            return self.covariances[key]
        except KeyError:
            raise KeyError(f"no marginal covariance for key {gtsam.DefaultKeyFormatter(key)} "
                           "(the numpy backend gives them for K, C, N(w) and H(w))") from None


def covariances_by_key(problem: PackedColumns, sys: NormalEquations) -> dict[int, np.ndarray]:
    """The marginal covariance of each global variable of a packed problem.

    Args:
        problem: the packed problem's column layout.
        sys: its normal equations at the linearisation point.

    Returns:
        The covariances by gtsam key: K(c), C(c) (c > 0), N(w) and, when estimated, H(w).
    """
    cov = global_covariance(sys, problem.fixed_cols)
    out = {}
    for c in range(len(problem.camera_names)):
        b = c * problem.camera_block
        out[K_.K(c)] = cov[b:b + problem.n_params, b:b + problem.n_params].copy()
        if c > 0:
            b += problem.n_params
            out[K_.C(c)] = cov[b:b + 6, b:b + 6].copy()
    for w, n in enumerate(problem.normal_cols):
        out[K_.window_normal(w)] = cov[n:n + 2, n:n + 2].copy()
        if problem.estimate_distance and problem.distance_cols is not None:
            d = problem.distance_cols[w]
            out[K_.window_plane(w)] = cov[d:d + 1, d:d + 1].copy()
    return out

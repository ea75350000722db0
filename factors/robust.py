"""The Huber loss on each corner's pixel distance: the one copy both backends and refine-colmap use.

For a corner with residual r (2,), distance d = |r| and threshold k:

- loss rho(d) = d^2 / 2 (d <= k), k d - k^2 / 2 (d > k); its IRLS weight w = rho'(d) / d = min(1, k / d);
- inside a least-squares factor (GTSAM's error is 0.5 ||residual||^2) the corner's residual is
  ``s r`` with s = sqrt(2 rho(d)) / d, so 0.5 |s r|^2 = rho(d) exactly, and its Jacobian rows are
  ``(w / s) J``, so the linearisation's gradient (w/s J)^T (s r) = w J^T r is rho's true gradient.
  Beyond k: s = sqrt(k (2 d - k)) / d and w / s = sqrt(k / (2 d - k)); both are 1 at d = k (no kink)
  and the Gauss-Newton matrix (w/s)^2 J^T J = k / (2 d - k) J^T J stays positive semi-definite.

Square-root IRLS weights (residual and Jacobian both times sqrt(w)) would make the error
0.5 w d^2 = k d / 2, whose gradient is half the linear system's: LM then rejects its steps near the
optimum and stops at a point that is not the Huber M-estimate (issue 15).
"""
from __future__ import annotations

import numpy as np


def huber_loss(dist: np.ndarray, huber_px: float | None) -> np.ndarray:
    """rho(d) per corner (d^2 / 2 without a threshold)."""
    dist = np.asarray(dist, float)
    if huber_px is None:
        return 0.5 * dist * dist
    k = float(huber_px)
    return np.where(dist <= k, 0.5 * dist * dist, k * dist - 0.5 * k * k)


def huber_weight(dist: np.ndarray, huber_px: float | None) -> np.ndarray:
    """The IRLS weight rho'(d) / d = min(1, k / d) per corner (1 without a threshold)."""
    dist = np.asarray(dist, float)
    if huber_px is None:
        return np.ones(dist.shape)
    return np.where(dist <= huber_px, 1.0, huber_px / np.maximum(dist, 1e-300))


def huber_scales(dist: np.ndarray, huber_px: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(residual scale s, Jacobian scale w / s) per corner (module docstring); (1, 1) inside the threshold.

    A non-finite distance gives a non-finite or zero scale: callers replace non-finite residuals.
    """
    dist = np.asarray(dist, float)
    res_scale, jac_scale = np.ones(dist.shape), np.ones(dist.shape)
    if huber_px is None:
        return res_scale, jac_scale
    k = float(huber_px)
    big = dist > k
    if big.any():
        d = dist[big]
        excess = 2.0 * d - k  # > k > 0
        with np.errstate(invalid="ignore"):  # d = inf: s = inf / inf, replaced by the caller
            res_scale[big] = np.sqrt(k * excess) / d
        jac_scale[big] = np.sqrt(k / excess)
    return res_scale, jac_scale


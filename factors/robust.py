"""The Huber loss on each corner's pixel distance: the one copy both backends and refine-colmap use.

For a corner with residual r (2,), distance d = |r| and threshold k: the loss is
rho(d) = d^2 / 2 (d <= k), k d - k^2 / 2 (d > k); its IRLS weight w = rho'(d) / d = min(1, k / d).
Every optimiser's error is the sum of rho and its linear system's gradient is rho's, sum w J^T r:

- a GTSAM CustomFactor's error is 0.5 ||residual||^2, so the corner's residual is ``s r`` with
  s = sqrt(2 rho(d)) / d (0.5 |s r|^2 = rho(d) exactly) and its Jacobian rows ``(w / s) J``
  (:func:`huber_scales`; beyond k: s = sqrt(k (2 d - k)) / d, w / s = sqrt(k / (2 d - k)), both 1
  at d = k). Its Gauss-Newton curvature k / (2 d - k) is about half the IRLS weight for far
  outliers;
- the numpy backend evaluates the error apart from its linear system, as Ceres does (its
  ``Corrector`` for rho'' <= 0): residual and Jacobian times sqrt(w), curvature w, and the error
  the sum of rho (:func:`huber_irls` gives sqrt(w) and rho - w d^2 / 2 per corner). From a start
  hundreds of pixels off (binocular_underwater's ari stage) the half curvature let LM's model
  promise decreases no step gave, up to lambda's bound; the IRLS system does not.

Both give the same optimum (the same gradient). Square-root IRLS weights with the error
0.5 ||sqrt(w) r||^2 = k d / 2 (before issue 15) had half the system's gradient: LM rejected its
steps near the optimum and stopped at a point that was not the Huber M-estimate.
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



def huber_irls(dist: np.ndarray, huber_px: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(sqrt(w), rho(d) - w d^2 / 2) per corner: the IRLS scale of residual and Jacobian, and what the
    error adds to the scaled residual's 0.5 w d^2 (0 inside the threshold; k (d - k) / 2 beyond)."""
    dist = np.asarray(dist, float)
    sqrt_w, excess = np.ones(dist.shape), np.zeros(dist.shape)
    if huber_px is None:
        return sqrt_w, excess
    k = float(huber_px)
    big = dist > k
    if big.any():
        d = dist[big]
        sqrt_w[big] = np.sqrt(k / d)
        excess[big] = 0.5 * k * (d - k)
    return sqrt_w, excess

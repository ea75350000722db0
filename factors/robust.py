"""The Huber loss on each corner's pixel distance: the one copy both backends and refine-colmap use.

For a corner with residual r (2,), distance d = |r| and threshold k: the loss is
rho(d) = d^2 / 2 (d <= k), k d - k^2 / 2 (d > k); its IRLS weight w = rho'(d) / d = min(1, k / d).
Every optimiser's error is the sum of rho, and its linear system is the IRLS one, as Ceres'
``Corrector`` builds it for rho'' <= 0: residual and Jacobian rows times sqrt(w), so the gradient
sum w J^T r is rho's and the curvature w J^T J. The error exceeds those rows' 0.5 w d^2 by
rho - w d^2 / 2 = k (d - k) / 2 per corner beyond k (:func:`huber_irls`):

- the numpy backend adds that excess to its system's error (it evaluates the error apart);
- a GTSAM CustomFactor's error is 0.5 ||residual||^2, so a view's factor carries it as one more
  row, sqrt(2 sum of the excess), whose Jacobian is zero (:func:`huber_view_residual`): its error
  is the sum of rho and its linearisation the same IRLS system.
"""
from __future__ import annotations

import numpy as np

from ..kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first

_JIT = dict(cache=True, nogil=True, error_model="numpy")


def huber_loss(dist: np.ndarray, huber_px: float | None) -> np.ndarray:
    """The Huber loss rho(d) per corner.

    Args:
        dist: the corners' pixel distances.
        huber_px: the threshold k (px); None: no threshold (d^2 / 2).

    Returns:
        rho(d), the shape of ``dist``.
    """
    dist = np.asarray(dist, float)
    if huber_px is None:
        return 0.5 * dist * dist
    k = float(huber_px)
    return np.where(dist <= k, 0.5 * dist * dist, k * dist - 0.5 * k * k)


def huber_weight(dist: np.ndarray, huber_px: float | None) -> np.ndarray:
    """The IRLS weight ``rho'(d) / d = min(1, k / d)`` per corner.

    Args:
        dist: the corners' pixel distances.
        huber_px: the threshold k (px); None: no threshold (weight 1).

    Returns:
        The weights, the shape of ``dist``.
    """
    dist = np.asarray(dist, float)
    if huber_px is None:
        return np.ones(dist.shape)
    return np.where(dist <= huber_px, 1.0, huber_px / np.maximum(dist, 1e-300))


def huber_residual_scale(dist: np.ndarray, huber_px: float) -> np.ndarray:
    """The residual scale ``s = sqrt(2 rho(d)) / d`` per corner, so that ``0.5 |s r|^2 = rho(d)``.

    A non-finite distance gives a non-finite scale: callers replace non-finite residuals.

    Args:
        dist: the corners' pixel distances.
        huber_px: the threshold k (px).

    Returns:
        The scales (1 inside the threshold), the shape of ``dist``.
    """
    dist = np.asarray(dist, float)
    scale = np.ones(dist.shape)
    k = float(huber_px)
    big = dist > k
    if big.any():
        d = dist[big]
        with np.errstate(invalid="ignore"):  # d = inf: inf / inf
            scale[big] = np.sqrt(k * (2.0 * d - k)) / d
    return scale


@njit(inline="always", **_JIT)
def _irls_one(d: float, k: float) -> tuple[float, float]:
    """(sqrt(w), rho(d) - w d^2 / 2) of one corner's distance d beyond threshold k; (1, 0) within."""
    if d > k:
        return np.sqrt(k / d), 0.5 * k * (d - k)
    return 1.0, 0.0


@njit(**_JIT)
def _irls_batch(dist, k):
    sqrt_w, excess = np.ones(len(dist)), np.zeros(len(dist))
    for i in range(len(dist)):
        sqrt_w[i], excess[i] = _irls_one(dist[i], k)
    return sqrt_w, excess


def huber_irls(dist: np.ndarray, huber_px: float | None) -> tuple[np.ndarray, np.ndarray]:
    """The IRLS scale per corner and what the error adds to the scaled residual.

    Args:
        dist: the corners' pixel distances.
        huber_px: the threshold k (px); None: no threshold.

    Returns:
        sqrt(w) per corner, the scale of residual and Jacobian rows, and the excess ``rho(d) - w d^2 / 2``
            (0 inside the threshold; k (d - k) / 2 beyond), both flat (M,).
    """
    dist = np.ascontiguousarray(dist, dtype=np.float64).reshape(-1)
    if huber_px is None:
        return np.ones(dist.shape), np.zeros(dist.shape)
    return _irls_batch(dist, float(huber_px))


@njit(**_JIT)
def weighted_residuals(uv, measured, huber_px, inv_sigma, whitened, invalid) -> tuple:
    """One camera's IRLS rows in one pass (the numpy backend's linearisation).

    Per corner: r = uv - measured, its distance, the Jacobian scale sqrt(w) (times ``inv_sigma`` when
    ``whitened``), the scaled residual and the error's excess.

    Args:
        uv (ndarray): projected pixels (m, 2).
        measured (ndarray): measured pixels (m, 2).
        huber_px (float): the threshold k (px); < 0: Huber off.
        inv_sigma (ndarray): each corner's 1 / sigma (m,), used when ``whitened``.
        whitened (bool): scale by ``inv_sigma`` too.
        invalid (float): the value of non-finite residual entries (times the corner's ``inv_sigma`` when
            whitened).

    Returns:
        The scale (m,), the scaled residual (m, 2), the distance (m,), the excess (m,) and whether any
            corner is beyond the threshold.
    """
    m = uv.shape[0]
    scale, res, dist, excess = np.empty(m), np.empty((m, 2)), np.empty(m), np.zeros(m)
    beyond = False
    for i in range(m):
        rx, ry = uv[i, 0] - measured[i, 0], uv[i, 1] - measured[i, 1]
        d = np.sqrt(rx * rx + ry * ry)
        s = 1.0
        if huber_px >= 0.0:
            s, excess[i] = _irls_one(d, huber_px)
            beyond |= d > huber_px
        if whitened:
            s = s * inv_sigma[i]
        dist[i], scale[i] = d, s
        for j, r in ((0, rx), (1, ry)):
            v = r * s
            res[i, j] = v if np.isfinite(v) else invalid * (inv_sigma[i] if whitened else 1.0)
    return scale, res, dist, excess, beyond


def huber_view_residual(r: np.ndarray, huber_px: float) -> tuple[np.ndarray, np.ndarray]:
    """One view's factor residual with the Huber loss (module docstring).

    The corners' rows are sqrt(w) r, then one row sqrt(2 sum of the excess); a corner whose distance is not
    finite adds no excess.

    Args:
        r: the corners' pixel residuals (M, 2).
        huber_px: the threshold k (px).

    Returns:
        The residual (2M + 1,), and the rows' scale sqrt(w) (M,), also the Jacobian rows' (the last row's
            Jacobian is zero).
    """
    dist = np.linalg.norm(r, axis=1)
    sqrt_w, excess = huber_irls(dist, huber_px)
    with np.errstate(invalid="ignore"):  # inf * 0 where a corner fell behind the window: the caller's 1e6
        rows = (r * sqrt_w[:, None]).reshape(-1)
    return np.append(rows, np.sqrt(2.0 * np.sum(excess[np.isfinite(dist)]))), sqrt_w

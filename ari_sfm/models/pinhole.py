"""The plain pinhole camera with OpenCV lens distortion.

Conventions (stated once for all models):
- camera frame OpenCV: x right, y down, z forward; lengths in mm;
- pixels OpenCV: the centre of the top-left pixel is (0, 0);
- intrinsic parameter vector ``params = [fx, fy, cx, cy, k1, k2, p1, p2, k3]``
  (the OpenCV 5-coefficient distortion model, no skew).

Projection of a camera-frame point X = (X, Y, Z), Z > 0::

    x, y   = X / Z, Y / Z                                   (normalised)
    r2     = x^2 + y^2,   R = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    xd     = x R + 2 p1 x y + p2 (r2 + 2 x^2)
    yd     = y R + p1 (r2 + 2 y^2) + 2 p2 x y
    u, v   = fx xd + cx,  fy yd + cy

Points with Z <= 0 (behind the camera) project to NaN: a mirrored pixel would
be a silently wrong answer.
"""
from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np

from . import kernels

logger = logging.getLogger(__name__)

NUM_PARAMS = 9
PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")



def as_points(X: np.ndarray, dim: int) -> np.ndarray:
    """Points as a float (N, dim) array; a single (dim,) point becomes (1, dim).

    Args:
        X: points (N, dim) or one point (dim,).
        dim: the number of coordinates per point.

    Returns:
        A float array (N, dim).

    Raises:
        ValueError: ``X`` has another shape.
    """
    X = np.asarray(X, dtype=float)
    if X.ndim == 1:
        X = X[None, :]
    if X.ndim != 2 or X.shape[1] != dim:
        raise ValueError(f"expected points of shape (N, {dim}), got {X.shape}")
    return X


def _dist5(dist: np.ndarray | None) -> np.ndarray:
    """OpenCV distortion coefficients as [k1, k2, p1, p2, k3]."""
    if dist is None:
        return np.zeros(5)
    dist = np.asarray(dist, dtype=float).ravel()
    if dist.size < 4:
        raise ValueError(f"distortion needs at least 4 coefficients (k1 k2 p1 p2), got {dist.size}")
    if dist.size > 5 and np.any(dist[5:] != 0.0):
        raise ValueError("only the 5-coefficient OpenCV model (k1 k2 p1 p2 k3) is supported; "
                         f"got non-zero higher coefficients {dist[5:].tolist()}")
    out = np.zeros(5)
    out[: min(5, dist.size)] = dist[:5]
    return out


def _f64(a: np.ndarray, dim: int) -> np.ndarray:
    """A writable C-contiguous float64 (N, dim) array for the kernels (copied only if needed)."""
    a = np.asarray(a, dtype=np.float64)
    if not (a.flags.c_contiguous and a.flags.writeable):
        a = np.array(a, dtype=np.float64, order="C")
    return a.reshape(-1, dim)


class PinholeJacobians(NamedTuple):
    """Pixels and their derivatives for N points (:func:`project_points`)."""

    uv: np.ndarray  # (N, 2) pixels; NaN where Z <= 0
    J_point: np.ndarray  # (N, 2, 3) d uv / d D
    J_params: np.ndarray  # (N, 2, n_params) d uv / d params[:n_params]


def project_points(D: np.ndarray, params: np.ndarray, n_params: int = NUM_PARAMS) -> PinholeJacobians:
    """The pinhole projection of camera-frame points with its derivatives: the one implementation (the
    compiled :func:`ari_sfm.models.kernels.pinhole_point`), used by :class:`PinholeModel`, the window models
    and the numpy bundle adjustment; :func:`pinhole_pixels` gives the pixels alone.

    Args:
        D: Camera-frame points or directions (m, 3).
        params: The intrinsics ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]``.
        n_params: The leading parameters the derivatives are taken with respect to.

    Returns:
        Pixels (m, 2) (NaN where Z <= 0), ``J_point`` = d uv / d D (m, 2, 3) and ``J_params`` = d uv /
        d params[:n_params] (m, 2, n_params).
    """
    uv, J_point, J_params = kernels.pinhole_batch(_f64(D, 3), np.array(params, dtype=np.float64), int(n_params), True)
    return PinholeJacobians(uv, J_point, J_params)


def pinhole_pixels(D: np.ndarray, params: np.ndarray) -> np.ndarray:
    """The pixels of camera-frame points, without derivatives (the same arithmetic as :func:`project_points`).

    Args:
        D: Camera-frame points or directions (m, 3).
        params: The intrinsics ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]``.

    Returns:
        Pixels (m, 2); NaN where Z <= 0.
    """
    return kernels.pinhole_batch(_f64(D, 3), np.array(params, dtype=np.float64), NUM_PARAMS, False)[0]


def _distort(xy: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV distortion of normalised coordinates xy (N, 2) with ``dist`` = [k1, k2, p1, p2, k3]:
    ``xyd`` (N, 2), ``J_xy`` (N, 2, 2) = d xyd / d xy, ``J_dist`` (N, 2, 5) = d xyd / d dist."""
    return kernels.distort_batch(_f64(xy, 2), np.array(dist, dtype=np.float64))


class PinholeModel:
    """A pinhole camera with K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] and OpenCV distortion."""

    def __init__(self, K: np.ndarray, dist: np.ndarray | None = None) -> None:
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got {K.shape}")
        if K[0, 1] != 0.0 or K[1, 0] != 0.0 or K[2, 0] != 0.0 or K[2, 1] != 0.0 or abs(K[2, 2] - 1.0) > 1e-12:
            raise ValueError("K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
        self._params = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], _dist5(dist)])
        self._params.setflags(write=False)

    # ----------------------------------------------------------------- params
    @classmethod
    def from_params(cls, params: np.ndarray) -> PinholeModel:
        """Model from ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]``."""
        p = np.array(params, dtype=float).ravel()  # a copy
        if p.size != NUM_PARAMS:
            raise ValueError(f"params must have {NUM_PARAMS} entries {PARAM_NAMES}, got {p.size}")
        model = cls.__new__(cls)  # skips K validation: called once per factor evaluation
        p.setflags(write=False)
        model._params = p
        return model

    @property
    def params(self) -> np.ndarray:
        """(9,) ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]`` (read-only)."""
        return self._params

    @property
    def K(self) -> np.ndarray:
        fx, fy, cx, cy = self._params[:4]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """(5,) OpenCV distortion ``[k1, k2, p1, p2, k3]``."""
        return self._params[4:].copy()

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self._params[4:] != 0.0))

    def __repr__(self) -> str:
        return f"PinholeModel(params={np.array2string(self._params, precision=6)})"

    # ------------------------------------------------------------- distortion
    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Distorted normalised coordinates (N, 2) of undistorted ones (N, 2)."""
        return self.distort_with_jacobians(xy)[0]

    def distort_with_jacobians(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distort normalised coordinates.

        Args:
            xy: undistorted normalised coordinates (N, 2).

        Returns:
            ``xyd`` (N, 2), ``J_xy`` (N, 2, 2) = d xyd / d xy and ``J_dist`` (N, 2, 5) = d xyd / d [k1, k2, p1,
                p2, k3].
        """
        return _distort(as_points(xy, 2), self._params[4:])

    def undistort(self, xyd: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (N, 2) of distorted ones.

        Newton's method on ``distort(xy) = xyd`` from ``xy = xyd`` with the
        analytic 2x2 Jacobian, iterated until the step is below 1e-12 px.
        Points whose final residual exceeds 1e-9 px (distortion not invertible
        there, e.g. far outside the calibrated field) come back as NaN and a
        warning is logged: never a silently wrong ray.

        Args:
            xyd: distorted normalised coordinates (N, 2).

        Returns:
            The undistorted normalised coordinates (N, 2), NaN where Newton failed.
        """
        xyd = as_points(xyd, 2)
        if not self.has_distortion:
            return xyd.copy()
        xy, failed = kernels.undistort_batch(_f64(xyd, 2), np.array(self._params[4:]), self._params[0],
                                             self._params[1])
        if failed.any():
            logger.warning("undistortion did not converge for %d of %d points; returning NaN",
                           int(failed.sum()), len(xyd))
        return xy

    # ------------------------------------------------------------- projection
    def pixels_from_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of undistorted normalised coordinates (N, 2)."""
        return self.project_normalized_with_jacobians(xy)[0]

    def project_normalized_with_jacobians(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixels of normalised coordinates with ``J_xy`` (N, 2, 2) and ``J_params`` (N, 2, 9)."""
        fx, fy = self._params[:2]
        xyd, J_xy, J_dist = self.distort_with_jacobians(xy)
        uv = xyd * self._params[:2] + self._params[2:4]
        fdiag = np.array([fx, fy])[None, :, None]
        J_params = np.zeros((len(uv), 2, NUM_PARAMS))
        J_params[:, 0, 0] = xyd[:, 0]  # du/dfx
        J_params[:, 1, 1] = xyd[:, 1]  # dv/dfy
        J_params[:, 0, 2] = 1.0  # du/dcx
        J_params[:, 1, 3] = 1.0  # dv/dcy
        J_params[:, :, 4:] = fdiag * J_dist
        return uv, fdiag * J_xy, J_params

    def project(self, X_cam: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of camera-frame points (N, 3); NaN for Z <= 0."""
        return pinhole_pixels(as_points(X_cam, 3), self._params)

    def project_with_jacobians(self, X_cam: np.ndarray) -> PinholeJacobians:
        """Pixels and analytic Jacobians of camera-frame points (see :func:`project_points`).

        Args:
            X_cam: camera-frame points (N, 3).

        Returns:
            Pixels (N, 2), ``J_point`` (N, 2, 3) = d uv / d X_cam and ``J_params`` (N, 2, 9).
        """
        return project_points(as_points(X_cam, 3), self._params)

    def backproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays of pixels through the camera centre.

        The pixel is undistorted (see :meth:`undistort`) and lifted by K^-1.

        Args:
            uv: pixels (N, 2).

        Returns:
            Ray origins (N, 3) (the camera centre: zeros) and unit directions (N, 3), camera frame.
        """
        uv = as_points(uv, 2)
        xyd = (uv - self._params[2:4]) / self._params[:2]
        xy = self.undistort(xyd)
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.zeros_like(d), d

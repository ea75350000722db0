"""The exact refractive camera: Snell's law at both faces of a flat plate.

Window as in :mod:`ari_sfm.models.ari`: unit normal n_c (camera frame, into the
scene), near face at distance h, thickness d, glass index n, medium index n_m.

Forward projection. Decompose a point X into depth z = n_c . X and radial
vector r = X - z n_c (rho = |r|); L = z - h - d is the length of the medium
column. A camera ray at incidence t, u = tan t, reaches radial offset::

    rho(u) = h u + d g_n(u) + L g_m(u),   g_k(u) = tan t_k = u / sqrt(k^2 + (k^2 - 1) u^2)

(from sin t = n sin t_g = n_m sin t_m and sin t = u / sqrt(1 + u^2)). For fixed
rho, L, rho(u) is increasing and concave in u (g'' < 0 for k > 1), so Newton on
rho(u) = rho started at u = 0 stays below the root and climbs to it
monotonically; its first step is the paraxial (ARI) answer
u = rho / (h + d/n + L/n_m).

To treat rho -> 0 without a 0/0 we solve for w = u / rho instead: with
G_k(u) = 1/sqrt(k^2 + (k^2 - 1) u^2), g_k(u) = u G_k(u), the equation divided by
rho reads::

    Psi(w) = w H(w rho) - 1 = 0,   H(u) = h + d G_n(u) + L G_m(u),

with Psi'(w) = rho'(u) = h + d n^2 / q_n^1.5 + L n_m^2 / q_m^1.5,
q_k = k^2 + (k^2 - 1) u^2. Newton in w takes exactly the steps of Newton in u
(scaled by 1/rho) and is smooth at rho = 0 (one step: w = 1/rho'(0)).
The camera-side ray direction is n_c + u r/rho = n_c + w r; the pinhole
projects it.

Derivatives (implicit function theorem on Psi(w; rho, L, h, d) = 0, with
K(u) = d (n^2 - 1)/q_n^1.5 + L (n_m^2 - 1)/q_m^1.5 so that H'(u) = -u K)::

    dPsi/drho = -w^3 rho K,   dPsi/dL = w G_m,   dPsi/dh = w,   dPsi/dd = w G_n,
    dw = -(dPsi/drho drho + dPsi/dL dL + dPsi/dh dh + dPsi/dd dd) / rho'(u),

and rho drho = r . dr (smooth at r = 0).

Points not beyond the far face (L <= 0) have no refracted ray: their pixels
are NaN. A Newton iteration that does not converge raises
:class:`ConvergenceError` (never a silently wrong pixel).

The arithmetic runs in the compiled kernels of :mod:`ari_sfm.models.kernels` (one point at a
time, no temporaries); the functions here are their checked Python entry points.
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from . import kernels
from .ari import check_window, unit_normal_and_projector
from .pinhole import NUM_PARAMS, PinholeModel, as_points

if TYPE_CHECKING:
    from ari_sfm.records import Interface

logger = logging.getLogger(__name__)

NEWTON_MAX_ITER = kernels.NEWTON_MAX_ITER  # a cap; the paper camera needs 5 (air) to 6 (water) over its whole image
NEWTON_REL_TOL = kernels.NEWTON_REL_TOL  # stop when |step| <= tol * w


class ConvergenceError(RuntimeError):
    """The forward-projection Newton iteration did not converge."""


class ExactJacobians(NamedTuple):
    """Projection and analytic derivatives for N points (``J_normal`` as in AriJacobians)."""

    uv: np.ndarray  # (N, 2) pixels
    J_point: np.ndarray  # (N, 2, 3) d uv / d X_cam
    J_normal: np.ndarray  # (N, 2, 3) d uv / d normal_cam (the 3-vector passed in)
    J_params: np.ndarray  # (N, 2, 9) d uv / d [fx, fy, cx, cy, k1, k2, p1, p2, k3]
    J_thickness: np.ndarray  # (N, 2) d uv / d thickness_mm
    J_distance: np.ndarray  # (N, 2) d uv / d distance_mm (zero in air: h unobservable)


def _thickness_array(d: float | np.ndarray, m: int) -> np.ndarray:
    """The plate thickness as the kernels take it: (1,) for all points or (m,) one per point."""
    d = np.array(d, dtype=np.float64).reshape(-1)  # a fresh writable contiguous copy
    if d.size not in (1, m):
        raise ValueError(f"thickness_mm must be one value or one per point ({m}), got {d.size}")
    return d


def _check_newton(status: int, failures: int, max_iter: int, h: float, d, n: float, n_m: float) -> int:
    """The slowest point's Newton steps, or ConvergenceError when a kernel reported failures."""
    if failures:
        if status == kernels.NEWTON_NOT_FINITE:
            raise ConvergenceError(f"exact projection: non-finite Newton step for {failures} points")
        raise ConvergenceError(
            f"exact projection: Newton not converged for {failures} points after "
            f"{max_iter} iterations (h={h}, d={d}, n={n}, n_m={n_m})")
    return status


def solve_incidence(rho: np.ndarray, L: np.ndarray, h: float, d: float | np.ndarray, n: float, n_m: float,
                    max_iter: int = NEWTON_MAX_ITER) -> tuple[np.ndarray, int]:
    """Solve rho(u) = rho for w = u / rho (see the module docstring).

    Args:
        rho: radial offsets (N,), >= 0.
        L: medium column lengths (N,), > 0.
        h: near-face distance (mm).
        d: plate thickness, one for all points or (N,) one per point.
        n: glass index.
        n_m: medium index.
        max_iter: the cap on Newton steps.

    Returns:
        w (N,) and the number of Newton steps the slowest point took (including the final step whose
            size met the tolerance).

    Raises:
        ConvergenceError: a point is not converged after ``max_iter`` steps, or a step is not finite.
    """
    rho = np.array(rho, dtype=np.float64).reshape(-1)
    L = np.array(L, dtype=np.float64).reshape(-1)
    w, status, failures = kernels.solve_w_batch(rho, L, float(h), _thickness_array(d, len(rho)), float(n),
                                                float(n_m), int(max_iter))
    return w, _check_newton(status, failures, max_iter, h, d, n, n_m)


def incidence(X: np.ndarray, nc: np.ndarray, h: float, d: float | np.ndarray, n: float, n_m: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Depth, radial vector, medium column and solved w of camera-frame points.

    Args:
        X: camera-frame points (m, 3).
        nc: unit window normal (3,) in the camera frame.
        h: near-face distance (mm).
        d: plate thickness, one for all points or (m,) one per point.
        n: glass index.
        n_m: medium index.

    Returns:
        Depth ``z = n_c . X`` (m,), radial vector r (m, 3), medium column L (m,), the solved w (m,) (NaN
            where L <= 0 or X is not finite), and the Newton steps of the slowest point.

    Raises:
        ConvergenceError: a point's Newton iteration did not converge.
    """
    X = _points(X)
    z, r, L, w, status, failures = kernels.incidence_batch(X, np.array(nc, dtype=np.float64), float(h),
                                                           _thickness_array(d, len(X)), float(n), float(n_m),
                                                           NEWTON_MAX_ITER)
    return z, r, L, w, _check_newton(status, failures, NEWTON_MAX_ITER, h, d, n, n_m)


def _points(X: np.ndarray) -> np.ndarray:
    """X as the kernels take it: a writable C-contiguous float64 (m, 3) array (copied only if needed)."""
    X = np.asarray(X, dtype=np.float64)
    if not (X.flags.c_contiguous and X.flags.writeable):
        X = np.array(X, dtype=np.float64, order="C")
    return X


def exact_project(X: np.ndarray, params: np.ndarray, normal_cam: np.ndarray, thickness_mm: float | np.ndarray,
                  index: float, medium_index: float, distance_mm: float,
                  n_params: int = NUM_PARAMS) -> ExactJacobians:
    """The exact projection of camera-frame points with its Jacobians: the one implementation.

    It runs the compiled :func:`ari_sfm.models.kernels.exact_point` and is used by :class:`ExactModel` and by the
    numpy bundle adjustment (all corners of a camera in one call); :func:`exact_pixels` gives the pixels alone.

    Args:
        X: camera-frame points (m, 3), mm.
        params: intrinsics (9,) ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]``.
        normal_cam: window normal in the camera frame, any non-zero vector (``J_normal`` is w.r.t. its
            3 components).
        thickness_mm: one plate thickness for all points, or (m,) one per point (stacked plates).
        index: glass index n.
        medium_index: index n_m of the medium behind the window.
        distance_mm: near-face distance h > 0 (mm).
        n_params: number of leading ``params`` columns kept in ``J_params``.

    Returns:
        An :class:`ExactJacobians` (NaN pixels for points not beyond the far face).

    Raises:
        ValueError: ``distance_mm`` is None.
        ConvergenceError: a point's Newton iteration did not converge.
    """
    return ExactJacobians(*_exact_batch(X, params, normal_cam, thickness_mm, index, medium_index, distance_mm, True,
                                        n_params))


def exact_pixels(X: np.ndarray, params: np.ndarray, normal_cam: np.ndarray, thickness_mm: float | np.ndarray,
                 index: float, medium_index: float, distance_mm: float) -> np.ndarray:
    """The exact projection of camera-frame points, the pixels alone (:func:`exact_project`'s arithmetic).

    Args:
        X: camera-frame points (m, 3), mm.
        params: intrinsics (9,).
        normal_cam: window normal in the camera frame, any non-zero vector.
        thickness_mm: one plate thickness for all points, or (m,) one per point.
        index: glass index n.
        medium_index: index n_m of the medium behind the window.
        distance_mm: near-face distance h > 0 (mm).

    Returns:
        Pixels (m, 2) (NaN for points not beyond the far face).

    Raises:
        ValueError: ``distance_mm`` is None.
        ConvergenceError: a point's Newton iteration did not converge.
    """
    return _exact_batch(X, params, normal_cam, thickness_mm, index, medium_index, distance_mm, False, NUM_PARAMS)[0]


def _exact_batch(X: np.ndarray, params: np.ndarray, normal_cam: np.ndarray, thickness_mm: float | np.ndarray,
                 index: float, medium_index: float, distance_mm: float, jacobians: bool,
                 n_params: int) -> tuple[np.ndarray, ...]:
    """The compiled batch (:func:`ari_sfm.models.kernels.exact_batch`), its Newton failures checked: pixels
    and, with ``jacobians``, the Jacobians."""
    if distance_mm is None:
        raise ValueError("ExactModel needs distance_mm (camera centre to near face, > 0)")
    nc, dn_dv = unit_normal_and_projector(normal_cam)
    X = _points(X)
    h = float(distance_mm)
    uv, J_point, J_normal, J_params, J_thickness, J_distance, status, failures = kernels.exact_batch(
        X, np.array(params, dtype=np.float64), nc, dn_dv, h, _thickness_array(thickness_mm, len(X)),
        float(index), float(medium_index), int(n_params), bool(jacobians))
    _check_newton(status, failures, NEWTON_MAX_ITER, h, thickness_mm, index, medium_index)
    return uv, J_point, J_normal, J_params, J_thickness, J_distance


class ExactModel:
    """Refractive camera with Snell's law at both faces of the plate (see module docstring)."""

    def __init__(self, pinhole: PinholeModel, normal_cam: np.ndarray, thickness_mm: float,
                 index: float, medium_index: float = 1.0, distance_mm: float | None = None) -> None:
        if distance_mm is None:
            raise ValueError("ExactModel needs distance_mm (camera centre to near face, > 0)")
        check_window(thickness_mm, index, medium_index, distance_mm)
        self.pinhole = pinhole
        self.normal_cam = unit_normal_and_projector(normal_cam)[0]
        self._normal_arg = np.array(normal_cam, dtype=float).reshape(3)  # J_normal is w.r.t. this vector
        self.thickness_mm = float(thickness_mm)
        self.index = float(index)
        self.medium_index = float(medium_index)
        self.distance_mm = float(distance_mm)

    @classmethod
    def from_interface(cls, pinhole: PinholeModel, normal_cam: np.ndarray, interface: Interface,
                       distance_mm: float | None = None) -> ExactModel:
        """Model from a :class:`ari_sfm.records.Interface`.

        Args:
            pinhole: the camera's pinhole model (intrinsics and distortion).
            normal_cam: window normal in the camera frame.
            interface: thickness, indices and distance hint of the window.
            distance_mm: near-face distance (mm) overriding the interface's hint; None: the hint.

        Returns:
            The :class:`ExactModel`.
        """
        h = interface.distance_mm if distance_mm is None else distance_mm
        return cls(pinhole, normal_cam, interface.thickness_mm, interface.index,
                   interface.medium_index, h)

    def __repr__(self) -> str:
        return (f"ExactModel({self.pinhole!r}, normal_cam={self.normal_cam.tolist()}, "
                f"thickness_mm={self.thickness_mm}, index={self.index}, "
                f"medium_index={self.medium_index}, distance_mm={self.distance_mm})")

    # ---------------------------------------------------------------- forward
    def _solve(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
        """Common forward part: z, r, L, w (NaN where L <= 0) and the Newton step count."""
        return incidence(X, self.normal_cam, self.distance_mm, self.thickness_mm, self.index, self.medium_index)

    def newton_iterations(self, X_cam: np.ndarray) -> int:
        """Newton steps the slowest of these points needs (diagnostics)."""
        return self._solve(as_points(X_cam, 3))[4]

    def _directions(self, X: np.ndarray) -> np.ndarray:
        """Unnormalised camera-side directions n_c + w r (NaN where invalid)."""
        _, r, _, w, _ = self._solve(X)
        return self.normal_cam + w[:, None] * r

    def ray_directions(self, X_cam: np.ndarray) -> np.ndarray:
        """Unit directions (N, 3) of the camera-side rays that reach X_cam (NaN if L <= 0)."""
        D = self._directions(as_points(X_cam, 3))
        return D / np.linalg.norm(D, axis=1, keepdims=True)

    def project(self, X_cam: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of camera-frame points (N, 3); NaN for points not beyond the far face."""
        return exact_pixels(as_points(X_cam, 3), self.pinhole.params, self.normal_cam, self.thickness_mm,
                            self.index, self.medium_index, self.distance_mm)

    def project_with_jacobians(self, X_cam: np.ndarray) -> ExactJacobians:
        """Pixels and analytic Jacobians (implicit function theorem; see the module docstring).

        Args:
            X_cam: camera-frame points (N, 3).

        Returns:
            An :class:`ExactJacobians` (see :func:`exact_project`).
        """
        return exact_project(as_points(X_cam, 3), self.pinhole.params, self._normal_arg, self.thickness_mm,
                             self.index, self.medium_index, self.distance_mm)

    # --------------------------------------------------------------- backward
    def backproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Medium-side rays of pixels.

        Vector Snell at each face (normal n_c along the light, ratio eta = n1/n2,
        cos_i = n_c . v):  ``v' = eta v + (cos_t - eta cos_i) n_c`` with
        ``cos_t = sqrt(1 - eta^2 (1 - cos_i^2))``. Pixels whose ray does not
        head into the window (n_c . v <= 0) give NaN.

        Args:
            uv: pixels (N, 2).

        Returns:
            Ray origins (N, 3) on the far face and unit directions (N, 3), camera frame.
        """
        origins, directions, failed = kernels.exact_rays_batch(
            np.array(as_points(uv, 2), dtype=np.float64), np.array(self.pinhole.params), self.normal_cam,
            self.distance_mm, self.thickness_mm, self.index, self.medium_index)
        if failed.any():
            logger.warning("undistortion did not converge for %d of %d points; returning NaN",
                           int(failed.sum()), len(failed))
        return origins, directions

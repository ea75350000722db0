"""The ARI model (paper Eq. 1): a pinhole camera that sees the scene shifted along the window normal.

Window: a plane-parallel plate with unit normal n_c (camera frame, from the
camera into the scene), near face at distance h from the camera centre,
thickness d, glass index n, medium index n_m behind it.

Paraxial derivation. Write a scene point as depth z = n_c . X along the normal
plus a radial offset r (r . n_c = 0, rho = |r|), L = z - h - d the length of
the medium column. A camera ray at incidence t has radial offset at depth z::

    rho(t) = h tan t + d tan t_g + L tan t_m,   sin t = n sin t_g = n_m sin t_m.

For small angles tan ~ sin ~ t, so tan t_g ~ t/n, tan t_m ~ t/n_m and::

    rho ~ t (h + d/n + L/n_m).

A pinhole camera sees the same ray (rho = t z_app) if the point sits at the
*apparent depth*::

    z_app = h + d/n + (z - h - d)/n_m,        lateral offset r unchanged,

i.e. ``X_app = X + (z_app - z) n_c``. This is affine in X:
``X_app = A X + a n_c`` with ``A = I + b n_c n_c^T``, ``b = 1/n_m - 1``,
``a = h + d/n - (h + d)/n_m``.

- Air behind (n_m = 1): b = 0, a = -d (1 - 1/n): every point moves by
  ``delta = d (1 - 1/n)`` toward the camera, independent of h (paper Eq. 2's
  translation ``d - d/n``). The ARI camera is then exactly a pinhole whose
  centre is moved by delta along n_c.
- A medium behind (n_m != 1): the medium column's depth scales by 1/n_m, so
  the map is not a pure shift and h is needed (``distance_mm``).

The exact model (:mod:`ari_sfm.models.exact`) differs by O(t^3) in the
incidence angle t. In air the third-order term is
``fx d (n^2 - 1) t^3 / (2 n^3 (z - delta))`` px for a normal on the optical
axis. The first Newton step of the exact solve, started at u = 0, is exactly
this paraxial model.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from . import kernels
from .pinhole import NUM_PARAMS, PinholeModel, as_points

if TYPE_CHECKING:
    from ari_sfm.records import Interface


def ari_shift_mm(thickness_mm: float, index: float) -> float:
    """The paraxial shift ``delta = d (1 - 1/n)`` of the scene toward the camera (air behind).

    Args:
        thickness_mm: plate thickness d (mm).
        index: glass refractive index n.

    Returns:
        The shift delta in mm.
    """
    return float(thickness_mm) * (1.0 - 1.0 / float(index))


def unit_normal_and_projector(normal_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normal ``n = v / |v|`` and its derivative ``d n / d v = (I - n n^T) / |v|`` of a free 3-vector v.

    Computed in scalar arithmetic with the rounding of ``np.linalg.norm`` and ``np.outer``.

    Args:
        normal_cam: the free 3-vector v (any non-zero length).

    Returns:
        The unit normal (3,) and the projector ``d n / d v`` (3, 3).

    Raises:
        ValueError: ``normal_cam`` is zero or not finite.
    """
    v0, v1, v2 = np.asarray(normal_cam, dtype=float).reshape(3).tolist()
    norm = math.sqrt((v0 * v0 + v1 * v1) + v2 * v2)  # norm's v.dot(v), in its order
    if not math.isfinite(norm) or norm == 0.0:
        raise ValueError(f"normal_cam must be a non-zero finite 3-vector, got {[v0, v1, v2]}")
    n = (v0 / norm, v1 / norm, v2 / norm)
    return np.array(n), np.array([[((1.0 if i == j else 0.0) - n[i] * n[j]) / norm for j in range(3)]
                                  for i in range(3)])


def check_window(thickness_mm: float, index: float, medium_index: float,
                 distance_mm: float | None) -> None:
    """Check that the window parameters are physical.

    Args:
        thickness_mm: plate thickness (mm), must be >= 0.
        index: glass index, must be >= 1.
        medium_index: index of the medium behind the window, must be >= 1.
        distance_mm: camera centre to near face (mm), > 0 when given; None: not modelled.

    Raises:
        ValueError: a parameter is out of its range.
    """
    if not thickness_mm >= 0.0:
        raise ValueError(f"thickness_mm must be >= 0, got {thickness_mm}")
    if not index >= 1.0:
        raise ValueError(f"index must be >= 1, got {index}")
    if not medium_index >= 1.0:
        raise ValueError(f"medium_index must be >= 1, got {medium_index}")
    if distance_mm is not None and not distance_mm > 0.0:
        raise ValueError(f"distance_mm must be > 0, got {distance_mm}")


class AriJacobians(NamedTuple):
    """Projection and its derivatives for N points.

    ``J_normal`` is d uv / d normal_cam, the 3 components of the vector passed
    to the constructor (which normalises it); chain it with a Unit3 tangent
    basis B (3, 2) as ``J_normal @ B``.
    """

    uv: np.ndarray  # (N, 2) pixels
    J_point: np.ndarray  # (N, 2, 3) d uv / d X_cam
    J_normal: np.ndarray  # (N, 2, 3) d uv / d normal_cam
    J_params: np.ndarray  # (N, 2, 9) d uv / d [fx, fy, cx, cy, k1, k2, p1, p2, k3]
    J_thickness: np.ndarray  # (N, 2) d uv / d thickness_mm
    J_distance: np.ndarray  # (N, 2) d uv / d distance_mm (zeros in air)


def ari_project(X: np.ndarray, params: np.ndarray, normal_cam: np.ndarray, thickness_mm: float | np.ndarray,
                index: float, medium_index: float = 1.0, distance_mm: float | None = None,
                n_params: int = NUM_PARAMS) -> AriJacobians:
    """The ARI projection of camera-frame points with its Jacobians: the one implementation.

    Used by :class:`AriModel` and by the numpy bundle adjustment (all corners of a camera in one call);
    :func:`ari_pixels` gives the pixels alone. The window's numbers are checked by the model
    (:func:`check_window`), not here.

    Args:
        X: camera-frame points (m, 3), mm.
        params: intrinsics (9,) ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]``.
        normal_cam: window normal in the camera frame, any non-zero vector (``J_normal`` is the
            derivative w.r.t. its 3 components).
        thickness_mm: one plate thickness for all points, or (m,) one per point (stacked plates).
        index: glass index n.
        medium_index: index n_m of the medium behind the window.
        distance_mm: near-face distance h (mm); needed with a medium behind, unused in air.
        n_params: number of leading ``params`` columns kept in ``J_params``.

    Returns:
        An :class:`AriJacobians`.

    Raises:
        ValueError: ``medium_index != 1`` without ``distance_mm``, or ``normal_cam`` zero or not finite.
    """
    return AriJacobians(*_ari_batch(X, params, normal_cam, thickness_mm, index, medium_index, distance_mm, True,
                                    n_params))


def ari_pixels(X: np.ndarray, params: np.ndarray, normal_cam: np.ndarray, thickness_mm: float | np.ndarray,
               index: float, medium_index: float = 1.0, distance_mm: float | None = None) -> np.ndarray:
    """The ARI projection of camera-frame points, the pixels alone (:func:`ari_project`'s arithmetic).

    Args:
        X: camera-frame points (m, 3), mm.
        params: intrinsics (9,).
        normal_cam: window normal in the camera frame, any non-zero vector.
        thickness_mm: one plate thickness for all points, or (m,) one per point.
        index: glass index n.
        medium_index: index n_m of the medium behind the window.
        distance_mm: near-face distance h (mm); needed with a medium behind, unused in air.

    Returns:
        Pixels (m, 2).
    """
    return _ari_batch(X, params, normal_cam, thickness_mm, index, medium_index, distance_mm, False, NUM_PARAMS)[0]


def _ari_batch(X: np.ndarray, params: np.ndarray, normal_cam: np.ndarray, thickness_mm: float | np.ndarray,
               index: float, medium_index: float, distance_mm: float | None, jacobians: bool,
               n_params: int) -> tuple[np.ndarray, ...]:
    """The compiled batch (:func:`ari_sfm.models.kernels.ari_batch`): pixels and, with ``jacobians``, the
    Jacobians (zeros without)."""
    if medium_index != 1.0 and distance_mm is None:
        raise ValueError("distance_mm is required when a medium (medium_index != 1) is behind the window")
    nc, dn_dv = unit_normal_and_projector(normal_cam)
    h = 0.0 if distance_mm is None else float(distance_mm)  # unused in air (b = 0, a = -delta)
    X = np.ascontiguousarray(X, dtype=np.float64).reshape(-1, 3)
    d = np.ascontiguousarray(np.broadcast_to(np.asarray(thickness_mm, dtype=np.float64), (len(X),)))
    return tuple(kernels.ari_batch(
        X, np.array(params, dtype=np.float64), nc, np.ascontiguousarray(dn_dv), d, float(index), float(medium_index), h,
        int(n_params), bool(jacobians)))


class AriModel:
    """Paraxial refractive camera: ``uv = pinhole(X_app)``, ``X_app = X + (z_app - z) n_c``."""

    def __init__(self, pinhole: PinholeModel, normal_cam: np.ndarray, thickness_mm: float,
                 index: float, medium_index: float = 1.0, distance_mm: float | None = None) -> None:
        check_window(thickness_mm, index, medium_index, distance_mm)
        if medium_index != 1.0 and distance_mm is None:
            raise ValueError("distance_mm is required when a medium (medium_index != 1) is behind the window")
        self.pinhole = pinhole
        self.normal_cam = unit_normal_and_projector(normal_cam)[0]
        self._normal_arg = np.array(normal_cam, dtype=float).reshape(3)  # J_normal is w.r.t. this vector
        self.thickness_mm = float(thickness_mm)
        self.index = float(index)
        self.medium_index = float(medium_index)
        self.distance_mm = None if distance_mm is None else float(distance_mm)
        h = 0.0 if self.distance_mm is None else self.distance_mm  # unused in air (b = 0, a = -delta)
        d, n, nm = self.thickness_mm, self.index, self.medium_index
        # X_app = X + (a + b z) n_c with z = n_c . X
        self._a = h + d / n - (h + d) / nm
        self._b = 1.0 / nm - 1.0
        self._da_dd = 1.0 / n - 1.0 / nm
        self._da_dh = 1.0 - 1.0 / nm

    @classmethod
    def from_interface(cls, pinhole: PinholeModel, normal_cam: np.ndarray, interface: Interface) -> AriModel:
        """Model from a :class:`ari_sfm.records.Interface`.

        Args:
            pinhole: the camera's pinhole model (intrinsics and distortion).
            normal_cam: window normal in the camera frame.
            interface: thickness, indices and distance hint of the window.

        Returns:
            The :class:`AriModel`.
        """
        return cls(pinhole, normal_cam, interface.thickness_mm, interface.index,
                   interface.medium_index, interface.distance_mm)

    @property
    def shift_mm(self) -> float:
        """delta = d (1 - 1/n), the shift toward the camera in air."""
        return ari_shift_mm(self.thickness_mm, self.index)

    def __repr__(self) -> str:
        return (f"AriModel({self.pinhole!r}, normal_cam={self.normal_cam.tolist()}, "
                f"thickness_mm={self.thickness_mm}, index={self.index}, "
                f"medium_index={self.medium_index}, distance_mm={self.distance_mm})")

    def apparent_points(self, X_cam: np.ndarray) -> np.ndarray:
        """Apparent points (N, 3): ``X + (z_app - z) n_c`` (air: ``X - delta n_c``)."""
        X = as_points(X_cam, 3)
        s = self._a + self._b * (X @ self.normal_cam)
        return X + s[:, None] * self.normal_cam

    def project(self, X_cam: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of camera-frame points (N, 3)."""
        return self.pinhole.project(self.apparent_points(X_cam))

    def project_with_jacobians(self, X_cam: np.ndarray) -> AriJacobians:
        """Pixels and analytic Jacobians (see :class:`AriJacobians`, :func:`ari_project`)."""
        return ari_project(as_points(X_cam, 3), self.pinhole.params, self._normal_arg, self.thickness_mm,
                           self.index, self.medium_index, self.distance_mm)

    def backproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scene-side rays of pixels.

        The pinhole ray ``X_app = t v`` maps through the inverse affine map
        ``X = A^-1 (X_app - a n_c)``, ``A^-1 = I + (n_m - 1) n_c n_c^T``, to the
        line ``X = -a n_m n_c + t (v + (n_m - 1)(n_c . v) n_c)``. In air the
        origin is the virtual centre ``delta n_c`` and the direction is v.
        With a medium the origin ``-a n_m n_c`` is a virtual point on the line
        (not where light physically leaves the window).

        Args:
            uv: pixels (N, 2).

        Returns:
            Ray origins (N, 3) and unit directions (N, 3), camera frame.
        """
        _, v = self.pinhole.backproject(uv)
        nc, nm = self.normal_cam, self.medium_index
        direction = v + (nm - 1.0) * (v @ nc)[:, None] * nc
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        origins = np.broadcast_to(-self._a * nm * nc, direction.shape).copy()
        return origins, direction

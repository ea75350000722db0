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
"""
from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from .ari import check_window, unit_normal_and_projector
from .pinhole import NUM_PARAMS, PinholeModel, as_points, project_points

if TYPE_CHECKING:
    from ari_sfm.records import Interface

NEWTON_MAX_ITER = 20  # a cap; the paper camera needs 5 (air) to 6 (water) over its whole image
NEWTON_REL_TOL = 1e-12  # stop when |step| <= tol * w; quadratic convergence leaves ~1e-24 + rounding


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


def _q_terms(u: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """G_k(u) = q^-1/2 and q^-3/2 with q = k^2 + (k^2 - 1) u^2."""
    q = k * k + (k * k - 1.0) * u * u
    G = 1.0 / np.sqrt(q)
    return G, G * G * G


def solve_incidence(rho: np.ndarray, L: np.ndarray, h: float, d: float | np.ndarray, n: float, n_m: float,
                    max_iter: int = NEWTON_MAX_ITER) -> tuple[np.ndarray, int]:
    """Solve rho(u) = rho for w = u / rho (see the module docstring).

    ``rho`` (N,) >= 0 radial offsets, ``L`` (N,) > 0 medium column lengths,
    ``d`` the plate thickness, one for all points or (N,) one per point
    (each point's Newton iteration is independent of the others').
    Returns w (N,) and the number of Newton steps the slowest point took
    (including the final step whose size met the tolerance). Raises
    :class:`ConvergenceError` if a point is not converged after ``max_iter``.
    """
    rho = np.asarray(rho, dtype=float)
    L = np.asarray(L, dtype=float)
    w = np.zeros_like(rho)
    active = np.ones(rho.shape, dtype=bool)
    per_point = np.ndim(d) > 0
    if per_point:
        d = np.broadcast_to(np.asarray(d, dtype=float), rho.shape)
    iterations = 0
    while active.any():
        if iterations >= max_iter:
            raise ConvergenceError(
                f"exact projection: Newton not converged for {int(active.sum())} points after "
                f"{max_iter} iterations (h={h}, d={d}, n={n}, n_m={n_m})")
        iterations += 1
        wa, ra, La = w[active], rho[active], L[active]
        da = d[active] if per_point else d
        u = wa * ra
        Gn, Gn3 = _q_terms(u, n)
        Gm, Gm3 = _q_terms(u, n_m)
        psi = wa * (h + da * Gn + La * Gm) - 1.0
        dpsi = h + da * n * n * Gn3 + La * n_m * n_m * Gm3  # = rho'(u) > 0
        step = psi / dpsi
        w[active] = wa - step
        done = np.abs(step) <= NEWTON_REL_TOL * np.abs(w[active])
        bad = ~np.isfinite(step)
        if bad.any():
            raise ConvergenceError(f"exact projection: non-finite Newton step for {int(bad.sum())} points")
        idx = np.flatnonzero(active)
        active[idx[done]] = False
    return w, iterations


def incidence_jacobians(X: np.ndarray, z: np.ndarray, r: np.ndarray, L: np.ndarray, w: np.ndarray,
                        nc: np.ndarray, h: float, d: float | np.ndarray, n: float, n_m: float, J_pin: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel Jacobians of the exact projection through D = n_c + w r (implicit function theorem on
    the incidence equation, see the module docstring), shared by ExactModel and the numpy backend.

    ``X`` (N, 3) camera-frame points, ``z = X . n_c``, ``r = X - z n_c``, ``L`` the medium column,
    ``w`` the solved incidence variable, ``J_pin`` (N, 2, 3) the pinhole's d uv / d D. Returns
    d uv / d X (N, 2, 3), d uv / d n_c for a free (unnormalised) normal (N, 2, 3), d uv / d d and
    d uv / d h (N, 2).
    """
    u = w * np.sqrt(np.einsum("ni,ni->n", r, r))
    Gn, Gn3 = _q_terms(u, n)
    Gm, Gm3 = _q_terms(u, n_m)
    P = h + d * n * n * Gn3 + L * n_m * n_m * Gm3  # rho'(u) = dPsi/dw
    K = d * (n * n - 1.0) * Gn3 + L * (n_m * n_m - 1.0) * Gm3  # H'(u) = -u K
    w3K = w**3 * K
    # dw/dX = (w^3 K r^T - w G_m n^T) / P
    dw_dX = (w3K[:, None] * r - (w * Gm)[:, None] * nc) / P[:, None]
    # dw/dn (free n) = (-w^3 K z r^T - w G_m X^T) / P   (uses r . n = 0)
    dw_dn = (-(w3K * z)[:, None] * r - (w * Gm)[:, None] * X) / P[:, None]
    m = len(X)
    J_pin_r = np.einsum("nij,nj->ni", J_pin, r)  # J_pin @ r
    J_pin_n = (J_pin.reshape(2 * m, 3) @ nc).reshape(m, 2)
    # dD/dX = w (I - n n^T) + r dw/dX^T
    J_point = (w[:, None, None] * (J_pin - J_pin_n[:, :, None] * nc[None, None, :])
               + J_pin_r[:, :, None] * dw_dX[:, None, :])
    # dD/dn = I - w z I - w n X^T + r dw/dn^T   (dr/dn = -z I - n X^T)
    J_n_free = ((1.0 - w * z)[:, None, None] * J_pin
                - w[:, None, None] * J_pin_n[:, :, None] * X[:, None, :]
                + J_pin_r[:, :, None] * dw_dn[:, None, :])
    J_thickness = J_pin_r * (w * (Gm - Gn) / P)[:, None]
    J_distance = J_pin_r * (w * (Gm - 1.0) / P)[:, None]
    return J_point, J_n_free, J_thickness, J_distance


def incidence(X: np.ndarray, nc: np.ndarray, h: float, d: float | np.ndarray, n: float, n_m: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Depth z = n_c . X, radial vector r, medium column L and the solved w of points X (m, 3)
    (NaN where L <= 0 or X is not finite), and the Newton steps of the slowest point."""
    z = X @ nc
    r = X - z[:, None] * nc
    L = z - h - d
    valid = (L > 0.0) & np.isfinite(X.sum(axis=1))
    rho = np.sqrt(r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1] + r[:, 2] * r[:, 2])  # np.linalg.norm's arithmetic
    w = np.full(len(X), np.nan)
    if valid.all():
        w[:], iterations = solve_incidence(rho, L, h, d, n, n_m)
    else:
        w[valid], iterations = solve_incidence(rho[valid], L[valid], h, d[valid] if np.ndim(d) else d, n, n_m)
    return z, r, L, w, iterations


def exact_project(X: np.ndarray, params: np.ndarray, normal_cam: np.ndarray, thickness_mm: float | np.ndarray,
                  index: float, medium_index: float, distance_mm: float, jacobians: bool = True,
                  n_params: int = NUM_PARAMS) -> ExactJacobians:
    """The exact projection of camera-frame points X (m, 3): the one implementation, used by
    :class:`ExactModel` and by the numpy bundle adjustment (all corners of a camera in one call).

    ``params`` (9,) intrinsics; ``thickness_mm`` one plate for all points or (m,) one per point
    (stacked plates); ``distance_mm`` h > 0. Returns an :class:`ExactJacobians` (NaN pixels for
    points not beyond the far face); without ``jacobians`` only ``uv`` is set; ``J_params``
    holds the first ``n_params`` columns; ``J_normal`` is w.r.t. the 3 components of ``normal_cam``.
    """
    if distance_mm is None:
        raise ValueError("ExactModel needs distance_mm (camera centre to near face, > 0)")
    nc, dn_dv = unit_normal_and_projector(normal_cam)
    h, d, n, nm = float(distance_mm), thickness_mm, index, medium_index
    z, r, L, w, _ = incidence(X, nc, h, d, n, nm)
    uv, J_pin, J_params = project_points(nc + w[:, None] * r, params, n_params, jacobians)
    if not jacobians:
        return ExactJacobians(uv, None, None, None, None, None)
    J_point, J_n_free, J_thickness, J_distance = incidence_jacobians(X, z, r, L, w, nc, h, d, n, nm, J_pin)
    m = len(X)
    J_normal = (J_n_free.reshape(2 * m, 3) @ dn_dv).reshape(m, 2, 3)
    return ExactJacobians(uv, J_point, J_normal, J_params, J_thickness, J_distance)


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
    def from_interface(cls, pinhole: PinholeModel, normal_cam: np.ndarray, interface: "Interface",
                       distance_mm: float | None = None) -> "ExactModel":
        """Model from a :class:`ari_sfm.records.Interface` (``distance_mm`` overrides its hint)."""
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
        return self.pinhole.project(self._directions(as_points(X_cam, 3)))

    def project_with_jacobians(self, X_cam: np.ndarray) -> ExactJacobians:
        """Pixels and analytic Jacobians (implicit function theorem; see module docstring and
        :func:`exact_project`)."""
        return exact_project(as_points(X_cam, 3), self.pinhole.params, self._normal_arg, self.thickness_mm,
                             self.index, self.medium_index, self.distance_mm)

    # --------------------------------------------------------------- backward
    def backproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Medium-side rays of pixels: origins (N, 3) on the far face, unit directions (N, 3).

        Vector Snell at each face (normal n_c along the light, ratio eta = n1/n2,
        cos_i = n_c . v):  ``v' = eta v + (cos_t - eta cos_i) n_c`` with
        ``cos_t = sqrt(1 - eta^2 (1 - cos_i^2))``. Pixels whose ray does not
        head into the window (n_c . v <= 0) give NaN.
        """
        _, v = self.pinhole.backproject(uv)
        nc, h, d = self.normal_cam, self.distance_mm, self.thickness_mm
        n, nm = self.index, self.medium_index
        c = v @ nc
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.where(c > 0.0, c, np.nan)
            p_near = v * (h / c)[:, None]  # hits the near face n_c . X = h
            eta = 1.0 / n
            c_g = np.sqrt(1.0 - eta * eta * (1.0 - c * c))
            v_g = eta * v + (c_g - eta * c)[:, None] * nc
            p_far = p_near + v_g * (d / c_g)[:, None]  # n_c . v_g = c_g
            eta = n / nm
            c_m = np.sqrt(1.0 - eta * eta * (1.0 - c_g * c_g))
            v_m = eta * v_g + (c_m - eta * c_g)[:, None] * nc
        v_m /= np.linalg.norm(v_m, axis=1, keepdims=True)
        return p_far, v_m

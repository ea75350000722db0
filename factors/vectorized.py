"""A vectorised numpy backend for the rig bundle adjustment: RigGraph's problem without Python callbacks.

:class:`~ari_sfm.factors.rig_graph.RigGraph` holds one ``gtsam.CustomFactor``
per (camera, image); GTSAM calls back into Python for every factor at every
linearisation and error evaluation, and that overhead dominates the time.
This module solves *the same problem*:

- the same variables and tangent spaces: intrinsics K(c) (additive),
  world_T_cam C(c) for c > 0 and world_T_target X(f) (Pose3, right-perturbed
  ``T Exp([w, v])`` with GTSAM's SE(3) exponential), the normal N (a
  ``gtsam.Unit3``, retracted by ``Unit3.retract`` in its own basis), the
  distance H (additive, optional); camera 0 is the world;
- the same residuals and Jacobians as :func:`~ari_sfm.factors.view_factor.view_residuals`
  (per-corner Huber square-root weights computed at the linearisation point,
  non-finite residuals replaced by 1e6, a camera beyond the window gives 1e6
  and zero Jacobians), whitened by each factor's isotropic sigma;
- the same Levenberg-Marquardt as ``gtsam.LevenbergMarquardtOptimizer`` with
  its 4.3 defaults (lambda 1e-5 times/divided by 10, ``H + lambda I`` damping
  on every variable, model fidelity > 1e-3, upper bound 1e5) and the
  tolerances of :meth:`RigGraph.optimize`. Taking GTSAM's own path (not just
  its optimum) matters with Huber weights: their Gauss-Newton fixed point is
  not the minimum of the cost, so where LM stops depends on the path.

How: the corners are packed once into flat arrays sorted by (camera, window
thickness, view); one kernel call per camera evaluates all its corners, the
plate thickness being a per-corner array (the models' arithmetic, written
out in :func:`_ari_eval` / :func:`_exact_eval`; per (camera, plate) group
only if a camera's groups differ in more than the thickness); the chain rule
of ``view_residuals`` is applied to all corners, with one batched matmul per
view where a view's rotation enters. The normal equations are formed per view
with one batched matmul of the padded view Jacobians ``[J_frame J_global r]``,
the 6x6 frame blocks are eliminated (Schur complement; frames are independent
given the intrinsics, camera poses, normal and distance), the reduced dense
system is solved by Cholesky and the frame steps are back-substituted.

Other factors added to a RigGraph (priors, between factors on the global
variables, or factors on a single frame) are linearised by GTSAM itself at
every iteration and added to the normal equations.

Entry points: :func:`optimize_vectorized` (optimise a built RigGraph in
place), :meth:`VectorizedProblem.from_rig_graph` (the packed problem, its
state, residuals, per-view Jacobians and marginal covariances),
:func:`optimize_graph` (the backend switch of ``calibrate``).

There is deliberately no builder that skips the GTSAM graph: RigGraph.build
costs ~60 us per view (0.2 s for 16 cameras x 500 frames, 2 % of the numpy
optimisation there), the graph stays the researcher's API (priors,
gtsam.Marginals), and a second copy of the view selection would drift from
RigGraph.build.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from typing import Sequence

import gtsam
import numpy as np
import scipy.linalg
import scipy.linalg.lapack

from ..geometry import Pose
from ..models import PinholeModel
from ..models.ari import check_window, unit_normal_and_projector
from ..models.exact import incidence_jacobians, solve_incidence
from ..records import Observation
from . import keys as K_
from .rig_graph import MODELS, RigGraph, RigState
from .view_factor import ViewData, ViewKeys, factor_keys

log = logging.getLogger(__name__)

BACKENDS = ("gtsam", "numpy", "auto")
STOP_RULES = ("converged", "gtsam")  # VectorizedProblem.optimize's stop=
INVALID_RESIDUAL = 1e6  # what view_residuals puts for a non-finite residual or a camera beyond the window


# --------------------------------------------------------------------------- records


@dataclass(frozen=True)
class LMParams:
    """Levenberg-Marquardt constants: gtsam.LevenbergMarquardtParams 4.3 defaults and RigGraph.optimize's
    absolute tolerance (the iteration cap and relative tolerance are arguments of optimize)."""

    absolute_tolerance: float = 1e-12  # stop when the error decrease is below this
    lambda_initial: float = 1e-5
    lambda_factor: float = 10.0
    lambda_upper_bound: float = 1e5  # give up when lambda reaches this
    lambda_lower_bound: float = 0.0
    min_model_fidelity: float = 1e-3  # accept a step when actual / predicted decrease exceeds this


@dataclass(frozen=True)
class LMReport:
    """How an optimisation went. Errors are GTSAM's: 0.5 * sum of whitened squared residuals."""

    iterations: int  # accepted steps, as gtsam's optimizer.iterations()
    inner_iterations: int  # lambda trials, as gtsam's getInnerIterations()
    linearizations: int
    initial_error: float
    error: float
    lambda_final: float
    time_s: float
    stop: str  # "converged", "max_iterations", "lambda_upper_bound", "small_cost_change", "zero_error",
    #            "no_model_decrease" (stop="converged" only: see VectorizedProblem.optimize)
    error_evaluations: int = 0  # nonlinear error evaluations (the initial one unless cached, one per tried step)


@dataclass
class Variables:
    """The current values of every variable, in numpy (plus the Unit3 normal)."""

    intrinsics: np.ndarray  # (C, n_params)
    world_R_cam: np.ndarray  # (C, 3, 3); camera 0 is the identity (not a variable)
    world_t_cam: np.ndarray  # (C, 3)
    normal: gtsam.Unit3  # the window normal in the world
    world_R_target: np.ndarray  # (F, 3, 3)
    world_t_target: np.ndarray  # (F, 3)
    distance_mm: float | None  # h0: a variable when estimated, else the fixed value (or None)


@dataclass(frozen=True)
class _Group:
    """Corners [start, stop) of one camera seen through one plate: one model call."""

    camera: int
    thickness_mm: float
    index: float
    medium_index: float
    base_params: np.ndarray  # (9,); the first n_params come from the variables
    start: int
    stop: int


@dataclass
class _Transforms:
    """Per-view and per-camera quantities of a Variables, shared by all corners."""

    R_cam_target: np.ndarray  # (V, 3, 3)
    t_cam_target: np.ndarray  # (V, 3)
    R_cam_world: np.ndarray  # (C, 3, 3)
    normal_world: np.ndarray  # (3,)
    normal_cam: np.ndarray  # (C, 3)
    basis: np.ndarray  # (3, 2) Unit3 tangent basis of the normal
    distance_cam: np.ndarray | None  # (C,) h_c = h0 - n . C_c


@dataclass
class _System:
    """Normal equations J^T J, J^T r (whitened) split into frame and global blocks."""

    V: np.ndarray  # (F, 6, 6)
    g_frame: np.ndarray  # (F, 6)
    W: np.ndarray  # (F, 6, G) frame-global coupling
    U: np.ndarray  # (G, G)
    g_global: np.ndarray  # (G,)
    error: float  # 0.5 r^T r of the linearised system at zero (gtsam's oldLinearizedError)


# --------------------------------------------------------------------------- SE(3)


def se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM's Pose3.Expmap of twists xi (N, 6) = [w, v]: rotations (N, 3, 3) and translations (N, 3).

    R = I + A W + B W^2, t = v + B w x v + C w x (w x v) with A = sin t / t,
    B = (1 - cos t) / t^2, C = (t - sin t) / t^3 (Taylor series for small t).
    """
    xi = np.asarray(xi, float).reshape(-1, 6)
    w, v = xi[:, :3], xi[:, 3:]
    th2 = np.einsum("ni,ni->n", w, w)
    small = th2 < 1e-6
    th = np.sqrt(th2)
    safe = np.where(small, 1.0, th)
    s2 = np.sin(0.5 * safe)
    A = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(safe) / safe)
    B = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, 2.0 * s2 * s2 / (safe * safe))
    C = np.where(small, 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0, (1.0 - A) / (safe * safe))
    Wm = np.zeros((len(xi), 3, 3))
    Wm[:, 0, 1], Wm[:, 0, 2], Wm[:, 1, 0] = -w[:, 2], w[:, 1], w[:, 2]
    Wm[:, 1, 2], Wm[:, 2, 0], Wm[:, 2, 1] = -w[:, 0], -w[:, 1], w[:, 0]
    W2 = Wm @ Wm
    R = np.eye(3) + A[:, None, None] * Wm + B[:, None, None] * W2
    wxv = _cross(w, v)
    t = v + B[:, None] * wxv + C[:, None] * _cross(w, wxv)
    return R, t


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of (N, 3) arrays (np.cross's arithmetic without its overhead)."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _retract_poses(R: np.ndarray, t: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Right perturbation T Exp(xi) of poses (R (N,3,3), t (N,3)), as Pose3.retract."""
    dR, dt = se3_exp(xi)
    return R @ dR, t + np.einsum("nij,nj->ni", R, dt)


def _rows_cross(J: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise J_a x v for J (M, 2, 3), v (M, 3): the rows of J @ skew(v)."""
    out = np.empty_like(J)
    vx, vy, vz = v[:, None, 0], v[:, None, 1], v[:, None, 2]
    jx, jy, jz = J[:, :, 0], J[:, :, 1], J[:, :, 2]
    out[:, :, 0] = jy * vz - jz * vy
    out[:, :, 1] = jz * vx - jx * vz
    out[:, :, 2] = jx * vy - jy * vx
    return out


def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


# --------------------------------------------------------------------------- the models on all corners of a camera
#
# The arithmetic of PinholeModel / AriModel / ExactModel.project(_with_jacobians),
# written once for all corners of a camera whatever plate they are seen through:
# the plate thickness d is a per-corner array, so one call replaces one model call
# per (camera, plate). Only what the solver uses is computed (no J_thickness, no
# distortion Jacobian when the distortion is not estimated). tests/test_vectorized.py
# checks residuals and Jacobians against view_residuals (the models) to 1e-9.


def _pinhole_eval(D: np.ndarray, params: np.ndarray, n_p: int, jacobians: bool):
    """PinholeModel(params).project(_with_jacobians) of points D (m, 3): uv (m, 2) and, with
    ``jacobians``, d uv / d D (m, 2, 3) and d uv / d params[:n_p] (m, 2, n_p); NaN where Z <= 0.

    With the distortion neither estimated nor present (n_p == 4, k1..k3 p1 p2 all zero) the
    distortion polynomial is the identity (exactly, in floating point) and is skipped."""
    Z = D[:, 2]
    behind = ~(Z > 0.0)
    if behind.any():
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = D[:, :2] / Z[:, None]
        xy[behind] = np.nan
    else:  # every Z > 0: nothing to silence
        xy = D[:, :2] / Z[:, None]
    f = params[:2]
    if n_p > 4 or params[4:].any():
        xyd, J_xy, J_dist = PinholeModel.from_params(params).distort_with_jacobians(xy)
    else:
        xyd, J_xy, J_dist = xy, None, None
    uv = xyd * f + params[2:4]
    if not jacobians:
        return uv, None, None
    m = len(D)
    inv_z = 1.0 / Z
    if J_xy is None:  # diag(f) @ [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
        J_pin = np.zeros((m, 2, 3))
        J_pin[:, 0, 0] = f[0] * inv_z
        J_pin[:, 1, 1] = f[1] * inv_z
        J_pin[:, :, 2] = f * (-xy * inv_z[:, None])
    else:
        J_norm = np.zeros((m, 2, 3))
        J_norm[:, 0, 0] = inv_z
        J_norm[:, 1, 1] = inv_z
        J_norm[:, :, 2] = -xy * inv_z[:, None]
        J_pin = (f[None, :, None] * J_xy) @ J_norm
    J_params = np.zeros((m, 2, n_p))
    J_params[:, 0, 0] = xyd[:, 0]  # du/dfx
    J_params[:, 1, 1] = xyd[:, 1]  # dv/dfy
    J_params[:, 0, 2] = 1.0  # du/dcx
    J_params[:, 1, 3] = 1.0  # dv/dcy
    if n_p > 4:
        J_params[:, :, 4:] = f[None, :, None] * J_dist
    return uv, J_pin, J_params


def _ari_eval(X, params, n_p, normal_cam, d, index, medium_index, h, jacobians):
    """AriModel.project(_with_jacobians) of camera-frame points X (m, 3) seen through plates of
    thickness d (m,): uv and, with ``jacobians``, (J_point, J_normal, J_params, J_distance)."""
    if medium_index != 1.0 and h is None:
        raise ValueError("distance_mm is required when a medium (medium_index != 1) is behind the window")
    nc, dn_dv = unit_normal_and_projector(normal_cam)
    hh = 0.0 if h is None else float(h)  # unused in air (b = 0, a = -delta)
    b = 1.0 / medium_index - 1.0
    s = hh + d / index - (hh + d) / medium_index  # X_app = X + (a + b z) n_c
    if b != 0.0:
        s = s + b * (X @ nc)
    uv, J_pin, J_params = _pinhole_eval(X + s[:, None] * nc, params, n_p, jacobians)
    if not jacobians:
        return uv, None
    m = len(X)
    J_pin_n = (J_pin.reshape(2 * m, 3) @ nc).reshape(m, 2)
    if b != 0.0:
        J_point = J_pin + b * J_pin_n[:, :, None] * nc[None, None, :]
        J_n_free = s[:, None, None] * J_pin + b * J_pin_n[:, :, None] * X[:, None, :]
    else:  # air: d X_app / d X = I
        J_point = J_pin
        J_n_free = s[:, None, None] * J_pin
    J_normal = (J_n_free.reshape(2 * m, 3) @ dn_dv).reshape(m, 2, 3)
    return uv, (J_point, J_normal, J_params, (1.0 - 1.0 / medium_index) * J_pin_n)


def _exact_eval(X, params, n_p, normal_cam, d, index, medium_index, h, jacobians):
    """ExactModel.project(_with_jacobians) of camera-frame points X (m, 3) seen through plates of
    thickness d (m,): uv and, with ``jacobians``, (J_point, J_normal, J_params, J_distance)."""
    if h is None:
        raise ValueError("ExactModel needs distance_mm (camera centre to near face, > 0)")
    nc, dn_dv = unit_normal_and_projector(normal_cam)
    n, nm = index, medium_index
    z = X @ nc
    r = X - z[:, None] * nc
    L = z - h - d
    valid = (L > 0.0) & np.isfinite(X.sum(axis=1))
    rho = np.sqrt(r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1] + r[:, 2] * r[:, 2])  # np.linalg.norm's arithmetic
    w = np.full(len(X), np.nan)
    if valid.all():
        w[:], _ = solve_incidence(rho, L, h, d, n, nm)
    else:
        w[valid], _ = solve_incidence(rho[valid], L[valid], h, d[valid], n, nm)
    uv, J_pin, J_params = _pinhole_eval(nc + w[:, None] * r, params, n_p, jacobians)
    if not jacobians:
        return uv, None
    J_point, J_n_free, _, J_distance = incidence_jacobians(X, z, r, L, w, nc, h, d, n, nm, J_pin)
    m = len(X)
    J_normal = (J_n_free.reshape(2 * m, 3) @ dn_dv).reshape(m, 2, 3)
    return uv, (J_point, J_normal, J_params, J_distance)


_KERNELS = {"ari": _ari_eval, "exact": _exact_eval}


# --------------------------------------------------------------------------- the problem


class VectorizedProblem:
    """RigGraph's problem packed into flat arrays, with a Levenberg-Marquardt Schur solver.

    Mirrors RigGraph: :meth:`optimize` (updates :attr:`x`, sets
    :attr:`iterations` and :attr:`report`), :meth:`state`, :meth:`residuals`;
    :meth:`write_values` copies the values into a gtsam.Values.
    """

    def __init__(
        self,
        views: Sequence[tuple[ViewData, ViewKeys, float]],
        observations: Sequence[tuple[str, Observation] | None],
        variables: Variables,
        camera_names: Sequence[str],
        frame_names: Sequence[str],
        n_params: int,
        base_state: RigState,
        estimate_distance: bool,
        model: str,
        huber_px: float | None,
        extra_factors: Sequence[gtsam.NonlinearFactor] = (),
        graph_index: Sequence[int] | None = None,
    ) -> None:
        """``views``: (ViewData, ViewKeys, sigma_px) per view factor; ``observations``: (camera, obs) per
        view factor; ``graph_index``: each view factor's index in its gtsam graph (for checks)."""
        if model not in MODELS:
            raise ValueError(f"unknown model {model!r} (known: {', '.join(MODELS)})")
        self.model = model
        self.factory = MODELS[model]
        self.camera_names = list(camera_names)
        self.frame_names = list(frame_names)
        self.n_params = int(n_params)
        self.base_state = base_state
        self.estimate_distance = bool(estimate_distance)
        self.huber_px = huber_px
        self.factor_views = list(observations)
        self.x = variables
        self.iterations = 0
        self.report: LMReport | None = None
        self.graph_index = np.arange(len(views)) if graph_index is None else np.asarray(graph_index, dtype=np.int64)
        self._error_cache: tuple[Variables, float] | None = None
        self._system_cache: tuple[Variables, _System] | None = None  # optimize's last linearisation, if at self.x
        self._pack(views)
        self._extra = _ExtraFactors(self, extra_factors)

    # ------------------------------------------------------------------ from a graph
    @staticmethod
    def from_rig_graph(rg: RigGraph, huber_px: float | None = None, check: bool = True) -> "VectorizedProblem":
        """The problem of a built RigGraph at its current values (its view factors and any factors added to it).

        RigGraph does not record the Huber threshold its factors were built
        with: pass the same ``huber_px``. With ``check`` the residuals of a few
        views (one per camera and plate, and the worst ones) are compared with
        the graph's own factors and a mismatch raises ValueError.
        """
        views, view_factor_index, k = [], [], 0
        for i in range(rg.graph.size()):  # the view factors, in factor_data order (priors may come first)
            factor = rg.graph.at(i)
            if k < len(rg.factor_data) and isinstance(factor, gtsam.CustomFactor):
                data, vkeys = rg.factor_data[k]
                if list(factor.keys()) == factor_keys(vkeys) and factor.dim() == 2 * len(data.points_target):
                    sigmas = np.asarray(factor.noiseModel().sigmas())
                    if np.ptp(sigmas) != 0.0:
                        raise ValueError(f"view factor {i} has a non-isotropic noise model")
                    views.append((data, vkeys, float(sigmas[0])))
                    view_factor_index.append(i)
                    k += 1
        if k != len(rg.factor_data):
            raise ValueError(f"found {k} of the graph's {len(rg.factor_data)} view factors")
        v = rg.values
        C, F = len(rg.camera_names), len(rg.frame_names)
        R_wc, t_wc = np.tile(np.eye(3), (C, 1, 1)), np.zeros((C, 3))
        for c in range(1, C):
            p = v.atPose3(K_.C(c))
            R_wc[c], t_wc[c] = p.rotation().matrix(), np.asarray(p.translation())
        R_wt, t_wt = np.empty((F, 3, 3)), np.empty((F, 3))
        for f in range(F):
            p = v.atPose3(K_.X(f))
            R_wt[f], t_wt[f] = p.rotation().matrix(), np.asarray(p.translation())
        distance = float(v.atVector(K_.H)[0]) if rg.estimate_distance else rg.base_state.distance_mm
        variables = Variables(np.array([v.atVector(K_.K(c)) for c in range(C)], float).reshape(C, rg.n_params),
                              R_wc, t_wc, v.atUnit3(K_.N), R_wt, t_wt, distance)
        extra = [rg.graph.at(i) for i in sorted(set(range(rg.graph.size())) - set(view_factor_index))]
        problem = VectorizedProblem(views, rg.factor_views, variables, rg.camera_names, rg.frame_names, rg.n_params,
                                    rg.base_state, rg.estimate_distance, rg.model, huber_px, extra, view_factor_index)
        if check:
            problem._check_against(rg)
        return problem

    # ------------------------------------------------------------------ packing
    def _pack(self, views: Sequence[tuple[ViewData, ViewKeys, float]]) -> None:
        C, F, n_p = len(self.camera_names), len(self.frame_names), self.n_params
        entries = []
        for k, (data, vkeys, sigma) in enumerate(views):
            c, f = _index(vkeys.intrinsics, "k"), _index(vkeys.frame, "x")
            if (vkeys.camera is None) != (c == 0) or (vkeys.camera is not None and _index(vkeys.camera, "c") != c):
                raise ValueError(f"view {k}: camera key does not match intrinsics key (camera 0 is the world)")
            if vkeys.normal != K_.N or (vkeys.distance is not None and vkeys.distance != K_.H):
                raise ValueError(f"view {k}: unexpected normal or distance key")
            if (vkeys.distance is not None) != self.estimate_distance:
                raise ValueError(f"view {k}: distance key does not match estimate_distance={self.estimate_distance}")
            if data.n_params != n_p or not 0 <= c < C or not 0 <= f < F:
                raise ValueError(f"view {k}: n_params {data.n_params}, camera {c} or frame {f} out of range")
            if not self.estimate_distance and vkeys.fixed_distance_mm != self.x.distance_mm:
                raise ValueError(f"view {k}: fixed distance {vkeys.fixed_distance_mm} differs from "
                                 f"{self.x.distance_mm}")
            tail = tuple(float(p) for p in np.asarray(data.base_params, float)[n_p:])
            group = (float(data.thickness_mm), float(data.index), float(data.medium_index), tail)
            entries.append((c, group, k, f, data, sigma))
        entries.sort(key=lambda e: (e[0], e[1], e[2]))
        self.n_views = len(entries)
        self.view_order = np.array([e[2] for e in entries], dtype=np.int64)  # packed view -> factor index
        self.view_camera = np.array([e[0] for e in entries], dtype=np.int64)
        self.view_frame = np.array([e[3] for e in entries], dtype=np.int64)
        sizes = np.array([len(e[4].points_target) for e in entries], dtype=np.int64)
        self.view_start = np.concatenate([[0], np.cumsum(sizes)])
        M = int(self.view_start[-1])
        self.n_corners = M
        self.points = np.concatenate([e[4].points_target for e in entries]).reshape(M, 3) if M else np.zeros((0, 3))
        self.measured = np.concatenate([e[4].measured for e in entries]).reshape(M, 2) if M else np.zeros((0, 2))
        self.corner_view = np.repeat(np.arange(self.n_views), sizes)
        self.corner_inv_sigma = np.repeat(np.array([1.0 / e[5] for e in entries]), sizes)
        self.unit_sigma = bool(np.all(self.corner_inv_sigma == 1.0))  # whitening is the identity
        self.groups: list[_Group] = []
        first = 0
        for k in range(1, len(entries) + 1):  # runs of equal (camera, plate) in the sorted views
            if k == len(entries) or entries[k][:2] != entries[first][:2]:
                c, (d, n, nm, _) = entries[first][0], entries[first][1]
                base = np.asarray(entries[first][4].base_params, float).copy()
                self.groups.append(_Group(c, d, n, nm, base, int(self.view_start[first]), int(self.view_start[k])))
                first = k
        # camera slices of views and corners; padded slots for the per-view batched products
        self.camera_views = np.searchsorted(self.view_camera, np.arange(C + 1))
        self.camera_corners = self.view_start[self.camera_views]
        self.camera_max_corners = np.zeros(C, dtype=np.int64)
        self.corner_slot = np.empty(M, dtype=np.int64)
        for c in range(C):
            vs, ve = self.camera_views[c], self.camera_views[c + 1]
            if ve == vs:
                continue
            mx = int(sizes[vs:ve].max())
            self.camera_max_corners[c] = mx
            for_view = np.repeat(np.arange(ve - vs) * mx - self.view_start[vs:ve] + self.view_start[vs], sizes[vs:ve])
            s, e = self.camera_corners[c], self.camera_corners[c + 1]
            self.corner_slot[s:e] = np.arange(s, e) - self.view_start[vs] + for_view
        # global tangent layout: per camera [intrinsics, pose] (camera 0's pose fixed: zero columns), normal, distance
        self.camera_block = n_p + 6
        self.normal_col = C * self.camera_block
        self.distance_col = self.normal_col + 2 if self.estimate_distance else None
        self.n_global = self.normal_col + 2 + (1 if self.estimate_distance else 0)
        self.local_dim = n_p + 6 + 2 + (1 if self.estimate_distance else 0)
        tail_cols = [self.normal_col, self.normal_col + 1] + ([self.distance_col] if self.estimate_distance else [])
        self.camera_cols = [np.concatenate([c * self.camera_block + np.arange(self.camera_block),
                                            tail_cols]).astype(np.int64) for c in range(C)]
        self.fixed_cols = np.arange(n_p, n_p + 6)  # camera 0's pose
        # one kernel call per camera (or per group when a camera's groups differ in more than the thickness)
        self.corner_thickness = np.empty(M)
        self._camera_runs: list[list[_Group]] = []
        for c in range(C):
            groups = [g for g in self.groups if g.camera == c]
            for g in groups:
                check_window(g.thickness_mm, g.index, g.medium_index, None)
                self.corner_thickness[g.start:g.stop] = g.thickness_mm
            same = len({(g.index, g.medium_index, tuple(g.base_params[n_p:])) for g in groups}) == 1
            self._camera_runs.append([replace(groups[0], stop=groups[-1].stop)] if same else groups)

    # ------------------------------------------------------------------ evaluation
    def _transforms(self, x: Variables) -> _Transforms:
        R_cw = np.swapaxes(x.world_R_cam, 1, 2)
        vc, vf = self.view_camera, self.view_frame
        R_ct = R_cw[vc] @ x.world_R_target[vf]
        t_ct = np.einsum("vij,vj->vi", R_cw[vc], x.world_t_target[vf] - x.world_t_cam[vc])
        n_w = np.asarray(x.normal.point3(), float)
        n_c = R_cw @ n_w
        h_c = None if x.distance_mm is None else x.distance_mm - x.world_t_cam @ n_w
        return _Transforms(R_ct, t_ct, R_cw, n_w, n_c, np.asarray(x.normal.basis(), float), h_c)

    def _camera_eval(self, x: Variables, tr: _Transforms, c: int, jacobians: bool,
                     huber_px: float | None, whiten: bool = False) -> np.ndarray:
        """Camera c's corners as view_residuals computes them (Huber-weighted; whitened by the
        factors' sigmas with ``whiten``).

        Without ``jacobians``: the residuals (m, 2). With: one array (m, 2, 6 + local_dim + 1)
        holding [J_frame | J_global (camera-local columns) | residual] per corner row.
        """
        s, e = int(self.camera_corners[c]), int(self.camera_corners[c + 1])
        m, n_p, L = e - s, self.n_params, self.local_dim
        cv = self.corner_view[s:e]
        P = self.points[s:e]
        h = None if tr.distance_cam is None else float(tr.distance_cam[c])
        if h is not None and h <= 0.0:  # an LM trial put the camera beyond the window: 1e6, zero Jacobians
            if not jacobians:
                return np.full((m, 2), INVALID_RESIDUAL)
            out = np.zeros((m, 2, 6 + L + 1))
            out[:, :, -1] = INVALID_RESIDUAL
            return out
        vs, ve = int(self.camera_views[c]), int(self.camera_views[c + 1])
        R_v = tr.R_cam_target[vs:ve]  # (nv, 3, 3), one per view of camera c
        X = self._per_view(c, P, np.swapaxes(R_v, 1, 2), tr.t_cam_target[vs:ve])  # R_ct P + t_ct
        kernel = _KERNELS[self.model]
        runs = self._camera_runs[c]
        if jacobians:
            out = np.zeros((m, 2, 6 + L + 1))
            Jg = out[:, :, 6:6 + L]
        if len(runs) == 1:  # the usual case: every plate of the camera in one call
            params = runs[0].base_params.copy()
            params[:n_p] = x.intrinsics[c]
            uv, J = kernel(X, params, n_p, tr.normal_cam[c], self.corner_thickness[s:e], runs[0].index,
                           runs[0].medium_index, h, jacobians)
            if jacobians:
                Jp, Jn, Jg[:, :, :n_p], Jd = J
        else:
            uv = np.empty((m, 2))
            if jacobians:
                Jp, Jn, Jd = np.empty((m, 2, 3)), np.empty((m, 2, 3)), np.empty((m, 2))
            for g in runs:
                a, b = g.start - s, g.stop - s
                params = g.base_params.copy()
                params[:n_p] = x.intrinsics[c]
                uv[a:b], J = kernel(X[a:b], params, n_p, tr.normal_cam[c], self.corner_thickness[g.start:g.stop],
                                    g.index, g.medium_index, h, jacobians)
                if jacobians:
                    Jp[a:b], Jn[a:b], Jg[a:b, :, :n_p], Jd[a:b] = J
        r = uv - self.measured[s:e]
        w = np.ones(m)
        if huber_px is not None:
            rx, ry = r[:, 0], r[:, 1]
            dist = np.sqrt(rx * rx + ry * ry)  # np.linalg.norm(r, axis=1)'s arithmetic, 5x faster
            big = dist > huber_px
            w[big] = np.sqrt(huber_px / dist[big])
        if not jacobians:
            res = r * w[:, None]
            if not np.isfinite(res.sum()):  # (the sum: one fast check)
                res[~np.isfinite(res)] = INVALID_RESIDUAL  # a point fell behind the window
            return res * self.corner_inv_sigma[s:e, None] if whiten and not self.unit_sigma else res
        # the Jacobians unweighted; every column (and the residual) scaled by the weight once at the end
        out[:, :, -1] = r
        R_cw, n_c, B = tr.R_cam_world[c], tr.normal_cam[c], tr.basis
        Jn2 = Jn.reshape(2 * m, 3)
        if c > 0:
            R_wc, t_wc = x.world_R_cam[c], x.world_t_cam[c]
            Jg[:, :, n_p:n_p + 3] = _rows_cross(Jp, X) + (Jn2 @ _skew(n_c)).reshape(m, 2, 3)
            Jg[:, :, n_p + 3:n_p + 6] = Jd[:, :, None] * (-(tr.normal_world @ R_wc)) - Jp
        else:
            t_wc = x.world_t_cam[0]
        Jg[:, :, n_p + 6:n_p + 8] = (Jn2 @ (R_cw @ B)).reshape(m, 2, 2) + Jd[:, :, None] * (-(t_wc @ B))
        if self.estimate_distance:
            Jg[:, :, n_p + 8] = Jd
        JA = self._per_view(c, Jp, R_v)  # d uv / d t of the target pose: J_point R_cam_target
        out[:, :, :3] = _rows_cross(JA, -P)  # -JA [P]x
        out[:, :, 3:6] = JA
        out *= (w * self.corner_inv_sigma[s:e])[:, None, None] if whiten and not self.unit_sigma else w[:, None, None]
        res = out[:, :, -1]
        bad = ~np.isfinite(res)
        if bad.any():  # a point fell behind the window
            res[bad] = INVALID_RESIDUAL * (self.corner_inv_sigma[s:e, None].repeat(2, 1)[bad] if whiten else 1.0)
        if not np.isfinite(out.sum()) and not np.all(np.isfinite(out[:, :, :-1])):  # (the sum: one fast check)
            bad_rows = ~np.isfinite(out[:, :, :-1]).all(axis=(1, 2))
            factors = np.unique(self.view_order[cv[bad_rows]])[:10].tolist()
            raise RuntimeError(f"non-finite Jacobian entries in factor(s) {factors} "
                               "(a corner behind the window at the linearisation point)")
        return out

    def _per_view(self, c: int, A: np.ndarray, M: np.ndarray, offset: np.ndarray | None = None) -> np.ndarray:
        """Each corner's rows A (m, ..., 3) of camera c times its view's matrix M (nv, 3, k), plus its view's
        offset (nv, k) if given: one batched matmul over the views (padded when their corner counts differ)."""
        s, e = int(self.camera_corners[c]), int(self.camera_corners[c + 1])
        nv, mx = int(self.camera_views[c + 1] - self.camera_views[c]), int(self.camera_max_corners[c])
        inner = A.shape[1:-1]
        if nv * mx == e - s:
            out = A.reshape(nv, -1, 3) @ M
        else:
            slot = self.corner_slot[s:e]
            pad = np.zeros((nv * mx,) + A.shape[1:])
            pad[slot] = A
            out = pad.reshape(nv, -1, 3) @ M
        if offset is not None:
            out += offset[:, None, :]
        out = out.reshape((-1,) + inner + (M.shape[-1],))
        return out if nv * mx == e - s else out[slot]

    def error(self, x: Variables | None = None) -> float:
        """GTSAM's graph error at x (default: the current values): 0.5 * sum of whitened squared residuals."""
        x = self.x if x is None else x
        tr = self._transforms(x)
        total = 0.0
        for c in range(len(self.camera_names)):
            if self.camera_corners[c + 1] == self.camera_corners[c]:
                continue
            rw = self._camera_eval(x, tr, c, False, self.huber_px, whiten=True)
            total += 0.5 * float(np.einsum("ij,ij->", rw, rw))
        return total + self._extra.error(x)

    def _linearize(self, x: Variables) -> _System:
        C, F, G, K = len(self.camera_names), len(self.frame_names), self.n_global, 6 + self.local_dim
        tr = self._transforms(x)
        V, g_f = np.zeros((F, 6, 6)), np.zeros((F, 6))
        W, U, g_g = np.zeros((F, 6, G)), np.zeros((G, G)), np.zeros(G)
        err2 = 0.0
        for c in range(C):
            s, e = int(self.camera_corners[c]), int(self.camera_corners[c + 1])
            if e == s:
                continue
            vs, ve = int(self.camera_views[c]), int(self.camera_views[c + 1])
            nv, mx = ve - vs, int(self.camera_max_corners[c])
            out = self._camera_eval(x, tr, c, True, self.huber_px, whiten=True)
            if nv * mx == e - s:  # every view has the same number of corners: no padding
                A = out.reshape(nv, 2 * mx, K + 1)
            else:
                A = np.zeros((nv * mx, 2, K + 1))
                A[self.corner_slot[s:e]] = out
                A = A.reshape(nv, 2 * mx, K + 1)
            Hv = np.matmul(np.swapaxes(A, 1, 2), A)  # (nv, K+1, K+1): [H g; g^T r^T r] per view
            fr = self.view_frame[vs:ve]
            np.add.at(V, fr, Hv[:, :6, :6])
            np.add.at(g_f, fr, Hv[:, :6, K])
            Wc = np.zeros((F, 6, self.local_dim))
            np.add.at(Wc, fr, Hv[:, :6, 6:K])
            cols = self.camera_cols[c]
            W[:, :, cols] += Wc
            U[np.ix_(cols, cols)] += Hv[:, 6:K, 6:K].sum(axis=0)
            g_g[cols] += Hv[:, 6:K, K].sum(axis=0)
            err2 += float(Hv[:, K, K].sum())
        system = _System(V, g_f, W, U, g_g, 0.5 * err2)
        self._extra.add_to(system, x)
        return system

    # ------------------------------------------------------------------ solve and retract
    def _solve(self, sys: _System, lam: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(global step, frame steps) of (H + lam I) delta = -g via the Schur complement; None if not PD."""
        F, G = sys.V.shape[0], self.n_global
        Vd = sys.V + lam * np.eye(6)
        try:
            np.linalg.cholesky(Vd)
        except np.linalg.LinAlgError:
            return None
        V_inv = np.linalg.inv(Vd)
        Y = np.matmul(V_inv, sys.W)  # (F, 6, G)
        W2, Y2 = sys.W.reshape(6 * F, G), Y.reshape(6 * F, G)
        S = sys.U - W2.T @ Y2
        S[np.diag_indices(G)] += lam
        rhs = -sys.g_global + Y2.T @ sys.g_frame.reshape(6 * F)  # W^T V^-1 g_f
        # scipy.linalg.cho_factor / cho_solve (upper), without their wrappers' overhead
        c, info = scipy.linalg.lapack.dpotrf(S, lower=0, clean=0, overwrite_a=1)
        if info != 0:
            return None
        d_global, info = scipy.linalg.lapack.dpotrs(c, rhs, lower=0)
        if info != 0:
            return None
        if not np.all(np.isfinite(d_global)):
            return None
        d_frame = -np.einsum("fij,fj->fi", V_inv, sys.g_frame + sys.W @ d_global)
        return d_global, d_frame

    @staticmethod
    def _model_decrease(sys: _System, d_global: np.ndarray, d_frame: np.ndarray) -> float:
        """Decrease of the linearised error 0.5 |J d + r|^2 from d = 0: -(g.d + 0.5 d^T H d)."""
        Wd = sys.W @ d_global  # (F, 6)
        quad = d_global @ sys.U @ d_global + 2.0 * np.einsum("fi,fi->", d_frame, Wd)
        quad += np.einsum("fi,fij,fj->", d_frame, sys.V, d_frame)
        lin = sys.g_global @ d_global + np.einsum("fi,fi->", sys.g_frame, d_frame)
        return -(lin + 0.5 * quad)

    def _retract(self, x: Variables, d_global: np.ndarray, d_frame: np.ndarray) -> Variables:
        C, n_p, B = len(self.camera_names), self.n_params, self.camera_block
        blocks = d_global[: C * B].reshape(C, B)
        R_wc, t_wc = x.world_R_cam.copy(), x.world_t_cam.copy()
        if C > 1:
            R_wc[1:], t_wc[1:] = _retract_poses(x.world_R_cam[1:], x.world_t_cam[1:], blocks[1:, n_p:])
        R_wt, t_wt = _retract_poses(x.world_R_target, x.world_t_target, d_frame)
        normal = x.normal.retract(d_global[self.normal_col:self.normal_col + 2])
        h = x.distance_mm + float(d_global[self.distance_col]) if self.estimate_distance else x.distance_mm
        return Variables(x.intrinsics + blocks[:, :n_p], R_wc, t_wc, normal, R_wt, t_wt, h)

    # ------------------------------------------------------------------ LM
    def optimize(self, max_iterations: int = 100, relative_tolerance: float = 1e-10,
                 params: LMParams | None = None, stop: str = "converged") -> RigState:
        """Levenberg-Marquardt from the current values (GTSAM's algorithm); updates them and returns the state.

        ``max_iterations`` caps the accepted steps (gtsam's iterations()); LM
        stops when the relative error decrease is below ``relative_tolerance``.

        ``stop="gtsam"`` is GTSAM's loop trial for trial: at convergence it
        typically rejects a step whose predicted decrease is below
        ``eps * error`` (GTSAM then never accepts it) and raises lambda
        tenfold, evaluating the error each time, until the upper bound, with
        the values unchanged. ``stop="converged"`` (the default) ends at the
        first such trial without evaluating it: the predicted decrease of the
        damped step never grows with lambda (its derivative is
        ``-lambda * sum g_i^2 / (h_i + lambda)^3`` in H's eigenbasis), so no
        later trial at this linearisation could be accepted and GTSAM would
        end on the same values. It also takes the initial error from the
        first linearisation (the same sum in another order, ~1e-15 relative)
        instead of a separate evaluation, unless the graph has user factors.
        Same steps, same values, same error; only :attr:`report` (lambda,
        trials, evaluations, stop reason) differs.
        """
        if stop not in STOP_RULES:
            raise ValueError(f"unknown stop rule {stop!r} (known: {', '.join(STOP_RULES)})")
        p = params or LMParams()
        t0 = time.perf_counter()
        x = self.x
        cached = self._error_cache
        evaluations, linearizations, first = 0, 0, None
        if cached is not None and cached[0] is x:
            err = cached[1]
        elif stop == "converged" and not self._extra.factors and max_iterations > 0:
            # the first linearisation's 0.5 r^T r is the error (the same sum, rounded in another order:
            # ~1e-15 relative); user factors' linearised error may not be their error (robust noise models)
            first = self._linearize(x)
            err, linearizations = first.error, 1
        else:
            err, evaluations = self.error(x), 1
        initial = err
        lam, iterations, inner = p.lambda_initial, 0, 0
        rule, stop = stop, "max_iterations"
        if err <= 0.0:
            stop = "zero_error"
        while stop != "zero_error" and iterations < max_iterations:  # gtsam's defaultOptimize
            cur_err = err
            if first is not None:
                sys, x_lin, first = first, x, None
            else:
                sys, x_lin = self._linearize(x), x
                linearizations += 1
            gave_up = None
            while True:  # gtsam's tryLambda, until a step is accepted or LM gives up
                step_ok, stop_searching = False, False
                sol = self._solve(sys, lam)
                if sol is not None:
                    d_global, d_frame = sol
                    predicted = self._model_decrease(sys, d_global, d_frame)
                    if rule == "converged" and predicted <= np.finfo(float).eps * sys.error:
                        gave_up = "no_model_decrease"  # GTSAM would reject this and every later trial
                        break
                    if predicted >= 0.0:
                        x_new = self._retract(x, d_global, d_frame)
                        e_new = self.error(x_new)
                        evaluations += 1
                        change = err - e_new
                        if predicted > np.finfo(float).eps * sys.error:
                            step_ok = change / predicted > p.min_model_fidelity
                        stop_searching = abs(change) < relative_tolerance * err
                if step_ok:
                    x, err = x_new, e_new
                    lam = max(p.lambda_lower_bound, lam / p.lambda_factor)
                    iterations += 1
                    inner += 1
                    break
                if stop_searching:
                    gave_up = "small_cost_change"
                    break
                lam *= p.lambda_factor
                inner += 1
                if lam >= p.lambda_upper_bound:
                    gave_up = "lambda_upper_bound"
                    break
            decrease = cur_err - err
            if err <= 0.0:
                stop = "zero_error"
            elif decrease / cur_err <= relative_tolerance or decrease <= p.absolute_tolerance:
                stop = gave_up or "converged"
                break
            elif not math.isfinite(cur_err):
                stop = "non_finite"
                break
        self.x = x
        self._system_cache = (x, sys) if linearizations and x_lin is x else None  # for marginal_covariances
        self.iterations = iterations
        self.report = LMReport(iterations, inner, linearizations, initial, err, lam, time.perf_counter() - t0, stop,
                               evaluations)
        log.debug("numpy LM: %s", self.report)
        return self.state()

    # ------------------------------------------------------------------ reading back
    def state(self, x: Variables | None = None) -> RigState:
        """The RigState of the current (or given) values, as RigGraph.state."""
        x = self.x if x is None else x
        params, cams = {}, {}
        for c, name in enumerate(self.camera_names):
            p = np.asarray(self.base_state.params[name], float).copy()
            p[: self.n_params] = x.intrinsics[c]
            params[name] = p
            cams[name] = Pose(x.world_R_cam[c].copy(), x.world_t_cam[c].copy()).inverse() if c > 0 else Pose.identity()
        frames = {f: Pose(x.world_R_target[i].copy(), x.world_t_target[i].copy())
                  for i, f in enumerate(self.frame_names)}
        distance = x.distance_mm if self.estimate_distance else self.base_state.distance_mm
        return RigState(params, cams, np.asarray(x.normal.point3(), float), frames, distance)

    def residuals(self) -> list[tuple[Observation, np.ndarray]]:
        """Unweighted pixel residuals (M, 2) of every view at the current values, in factor order (as RigGraph)."""
        res = self._all_residuals(self.x, None)
        out = [None] * self.n_views
        for k in range(self.n_views):
            out[self.view_order[k]] = res[self.view_start[k]:self.view_start[k + 1]]
        return [(obs, r) for (_, obs), r in zip(self.factor_views, out)]

    def _all_residuals(self, x: Variables, huber_px: float | None) -> np.ndarray:
        tr = self._transforms(x)
        res = np.empty((self.n_corners, 2))
        for c in range(len(self.camera_names)):
            s, e = self.camera_corners[c], self.camera_corners[c + 1]
            if e > s:
                res[s:e] = self._camera_eval(x, tr, c, False, huber_px)
        return res

    def evaluate_views(self, x: Variables | None = None) -> list[tuple[np.ndarray, list[np.ndarray]]]:
        """Per factor (factor order): residual (2M,) and Jacobians in the factor's key order, as view_residuals.

        Not whitened by sigma (view_residuals is not either). For tests.
        """
        x = self.x if x is None else x
        tr = self._transforms(x)
        n_p = self.n_params
        out = [None] * self.n_views
        for c in range(len(self.camera_names)):
            s = int(self.camera_corners[c])
            if self.camera_corners[c + 1] == s:
                continue
            full = self._camera_eval(x, tr, c, True, self.huber_px)
            res, Jf, Jg = full[:, :, -1], full[:, :, :6], full[:, :, 6:-1]
            for k in range(self.camera_views[c], self.camera_views[c + 1]):
                a, b = self.view_start[k] - s, self.view_start[k + 1] - s
                m2 = 2 * (b - a)
                blocks = [Jg[a:b, :, :n_p].reshape(m2, n_p)]
                if c > 0:
                    blocks.append(Jg[a:b, :, n_p:n_p + 6].reshape(m2, 6))
                blocks += [Jg[a:b, :, n_p + 6:n_p + 8].reshape(m2, 2), Jf[a:b].reshape(m2, 6)]
                if self.estimate_distance:
                    blocks.append(Jg[a:b, :, n_p + 8:n_p + 9].reshape(m2, 1))
                out[self.view_order[k]] = (res[a:b].reshape(-1), blocks)
        return out

    def write_values(self, values: gtsam.Values, x: Variables | None = None) -> None:
        """Update a gtsam.Values (holding this problem's keys) to x (default: the current values)."""
        x = self.x if x is None else x
        for c in range(len(self.camera_names)):
            values.update(K_.K(c), np.asarray(x.intrinsics[c], float))
            if c > 0:
                values.update(K_.C(c), gtsam.Pose3(gtsam.Rot3(x.world_R_cam[c]), x.world_t_cam[c]))
        values.update(K_.N, x.normal)
        for f in range(len(self.frame_names)):
            values.update(K_.X(f), gtsam.Pose3(gtsam.Rot3(x.world_R_target[f]), x.world_t_target[f]))
        if self.estimate_distance:
            values.update(K_.H, np.array([float(x.distance_mm)]))

    def marginal_covariances(self) -> dict[int, np.ndarray]:
        """Marginal covariances (J^T J)^-1 of the global variables at the current values, by key.

        What ``gtsam.Marginals(graph, values).marginalCovariance(key)`` gives
        for K(c), C(c), N and H (same tangent spaces, unit pixel sigma scaled
        by the factors' sigmas), from the Schur complement of the frames.
        """
        cached = self._system_cache  # optimize's last linearisation when it was at the final values
        sys = cached[1] if cached is not None and cached[0] is self.x else self._linearize(self.x)
        F, G = sys.V.shape[0], self.n_global
        V_inv = np.linalg.inv(sys.V)
        W2 = sys.W.reshape(6 * F, G)
        S = sys.U - W2.T @ np.matmul(V_inv, sys.W).reshape(6 * F, G)
        free = np.setdiff1d(np.arange(G), self.fixed_cols)
        cov = np.zeros((G, G))
        cov[np.ix_(free, free)] = np.linalg.inv(S[np.ix_(free, free)])
        out = {}
        for c in range(len(self.camera_names)):
            b = c * self.camera_block
            out[K_.K(c)] = cov[b:b + self.n_params, b:b + self.n_params].copy()
            if c > 0:
                b += self.n_params
                out[K_.C(c)] = cov[b:b + 6, b:b + 6].copy()
        n = self.normal_col
        out[K_.N] = cov[n:n + 2, n:n + 2].copy()
        if self.estimate_distance:
            out[K_.H] = cov[self.distance_col:self.distance_col + 1, self.distance_col:self.distance_col + 1].copy()
        return out

    def marginals(self) -> "CovarianceTable":
        """The marginal covariances as a ``gtsam.Marginals`` stand-in (``marginalCovariance(key)``
        for the intrinsics, camera poses, normal and distance), e.g. for
        :func:`ari_sfm.factors.uncertainty.rig_uncertainty`."""
        return CovarianceTable(self.marginal_covariances())

    # ------------------------------------------------------------------ consistency with a graph
    def _check_against(self, rg: RigGraph, worst: int = 3) -> None:
        """Compare the residuals of a few factors with GTSAM's (catches a wrong huber_px)."""
        res = self._all_residuals(self.x, self.huber_px)
        rw = res * self.corner_inv_sigma[:, None]
        self._error_cache = (self.x, 0.5 * float(np.einsum("ij,ij->", rw, rw)) + self._extra.error(self.x))
        view_norm = np.add.reduceat(np.abs(res).sum(axis=1), self.view_start[:-1]) if self.n_corners else np.zeros(0)
        C = len(self.camera_names)
        picks = {int(self.camera_views[c]) for c in range(C) if self.camera_views[c + 1] > self.camera_views[c]}
        picks |= set(np.argsort(view_norm)[-worst:].tolist())
        for k in sorted(picks):
            mine = res[self.view_start[k]:self.view_start[k + 1]].reshape(-1)
            theirs = np.asarray(rg.graph.at(int(self.graph_index[self.view_order[k]])).unwhitenedError(rg.values))
            if not np.allclose(mine, theirs, rtol=1e-9, atol=1e-9):
                raise ValueError(f"factor {int(self.view_order[k])}: vectorised residuals differ from the graph's "
                                 f"(max {np.max(np.abs(mine - theirs)):.3g}); "
                                 f"was the graph built with huber_px={self.huber_px}?")


class CovarianceTable:
    """Marginal covariances by key, with gtsam.Marginals' ``marginalCovariance(key)``."""

    def __init__(self, covariances: dict[int, np.ndarray]) -> None:
        self.covariances = covariances

    def marginalCovariance(self, key: int) -> np.ndarray:  # noqa: N802 (gtsam's name)
        try:
            return self.covariances[key]
        except KeyError:
            raise KeyError(f"no marginal covariance for key {gtsam.DefaultKeyFormatter(key)} "
                           "(the numpy backend gives them for K, C, N and H)") from None


# --------------------------------------------------------------------------- other factors of a graph


class _ExtraFactors:
    """Factors a user added to a RigGraph: linearised by GTSAM, added to the normal equations.

    Supported: factors on global variables (K, C, N, H) and at most one frame X(f).
    """

    def __init__(self, problem: VectorizedProblem, factors: Sequence[gtsam.NonlinearFactor]) -> None:
        self.problem = problem
        self.factors = list(factors)
        self.keys = sorted({k for f in self.factors for k in f.keys()})
        for f in self.factors:
            frames = {k for k in f.keys() if chr(gtsam.Symbol(k).chr()) == "x"}
            if len(frames) > 1:
                raise NotImplementedError("the numpy backend supports added factors on at most one target frame "
                                          f"(keys {[gtsam.DefaultKeyFormatter(k) for k in f.keys()]})")
            for k in f.keys():
                self._columns(k)  # validates the key

    def _columns(self, key: int) -> tuple[str, np.ndarray | int]:
        """('global', column indices) or ('frame', frame index) of a key."""
        p = self.problem
        ch, i = chr(gtsam.Symbol(key).chr()), gtsam.Symbol(key).index()
        if ch == "k" and i < len(p.camera_names):
            return "global", i * p.camera_block + np.arange(p.n_params)
        if ch == "c" and 0 < i < len(p.camera_names):
            return "global", i * p.camera_block + p.n_params + np.arange(6)
        if key == K_.N:
            return "global", p.normal_col + np.arange(2)
        if key == K_.H and p.estimate_distance:
            return "global", np.array([p.distance_col])
        if ch == "x" and i < len(p.frame_names):
            return "frame", int(i)
        raise ValueError(f"added factor uses key {gtsam.DefaultKeyFormatter(key)}, not a variable of this problem")

    def _values(self, x: Variables) -> gtsam.Values:
        v = gtsam.Values()
        for key in self.keys:
            ch, i = chr(gtsam.Symbol(key).chr()), gtsam.Symbol(key).index()
            if ch == "k":
                v.insert(key, np.asarray(x.intrinsics[i], float))
            elif ch == "c":
                v.insert(key, gtsam.Pose3(gtsam.Rot3(x.world_R_cam[i]), x.world_t_cam[i]))
            elif ch == "x":
                v.insert(key, gtsam.Pose3(gtsam.Rot3(x.world_R_target[i]), x.world_t_target[i]))
            elif key == K_.N:
                v.insert(key, x.normal)
            else:
                v.insert(key, np.array([float(x.distance_mm)]))
        return v

    def error(self, x: Variables) -> float:
        if not self.factors:
            return 0.0
        v = self._values(x)
        return float(sum(f.error(v) for f in self.factors))

    def add_to(self, sys: _System, x: Variables) -> None:
        if not self.factors:
            return
        v = self._values(x)
        for f in self.factors:
            lin = f.linearize(v)
            A, b = lin.jacobian()
            g_cols, f_cols, frame, col = [], [], None, 0
            for key in lin.keys():
                kind, where = self._columns(key)
                d = 6 if kind == "frame" else len(where)
                if kind == "frame":
                    frame, f_cols = where, list(range(col, col + 6))
                else:
                    g_cols.append((where, list(range(col, col + d))))
                col += d
            r = -np.asarray(b, float)
            gi = np.concatenate([w for w, _ in g_cols]) if g_cols else np.zeros(0, dtype=np.int64)
            Ag = A[:, [c for _, cs in g_cols for c in cs]] if g_cols else np.zeros((len(r), 0))
            sys.U[np.ix_(gi, gi)] += Ag.T @ Ag
            sys.g_global[gi] += Ag.T @ r
            if frame is not None:
                Af = A[:, f_cols]
                sys.V[frame] += Af.T @ Af
                sys.g_frame[frame] += Af.T @ r
                sys.W[frame][:, gi] += Af.T @ Ag
            sys.error += 0.5 * float(r @ r)


# --------------------------------------------------------------------------- helpers and entry points


def _index(key: int, expected: str) -> int:
    sym = gtsam.Symbol(key)
    if chr(sym.chr()) != expected:
        raise ValueError(f"key {gtsam.DefaultKeyFormatter(key)} is not a {expected!r} key")
    return int(sym.index())


def optimize_vectorized(
    rig_graph: RigGraph,
    max_iterations: int = 100,
    relative_tolerance: float = 1e-10,
    huber_px: float | None = None,
    check: bool = True,
    params: LMParams | None = None,
    return_report: bool = False,
    stop: str = "converged",
) -> RigState | tuple[RigState, LMReport]:
    """Optimise a built RigGraph's problem with the numpy backend (GTSAM's LM path, no callbacks).

    ``huber_px`` must be the one the graph was built with (checked when
    ``check``). The graph's values and ``iterations`` are updated as
    RigGraph.optimize does; returns the state, and the :class:`LMReport`
    (final error, lambda trials, time) with ``return_report``. ``stop``:
    see :meth:`VectorizedProblem.optimize` ("gtsam": GTSAM's trials one for one).
    """
    problem = VectorizedProblem.from_rig_graph(rig_graph, huber_px=huber_px, check=check)
    state = problem.optimize(max_iterations, relative_tolerance, params, stop)
    problem.write_values(rig_graph.values)
    rig_graph.iterations = problem.iterations
    return (state, problem.report) if return_report else state


def resolve_backend(backend: str) -> str:
    """The solver a backend name stands for: "auto" is "numpy", faster at every size measured
    (benchmarks/bench_backends.py: 4-6x on one or two cameras, 8-12x on larger rigs, same LM path)."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r} (known: {', '.join(BACKENDS)})")
    return "numpy" if backend == "auto" else backend


def optimize_graph(rig_graph: RigGraph, backend: str = "auto", max_iterations: int = 100,
                   huber_px: float | None = None, return_problem: bool = False, check: bool = True,
                   stop: str = "converged") -> RigState | tuple[RigState, VectorizedProblem | None]:
    """Optimise a RigGraph with GTSAM (``rig_graph.optimize``) or the numpy backend; same result either way.

    ``huber_px``: the threshold the graph was built with (the numpy backend
    needs it, see :meth:`VectorizedProblem.from_rig_graph`). With
    ``return_problem``: (state, the solved VectorizedProblem, or None with
    GTSAM), so that residuals and marginals at the optimum need no callbacks.
    ``check``: compare a few views with the graph's own factors (see
    from_rig_graph); a caller that has just built the graph with ``huber_px``
    may skip it. ``stop``: the numpy backend's stop rule (:meth:`VectorizedProblem.optimize`).
    "auto" falls back to GTSAM for a graph the numpy backend cannot hold (a
    user factor linking several target frames).
    """
    problem = None
    if resolve_backend(backend) == "numpy":
        try:
            problem = VectorizedProblem.from_rig_graph(rig_graph, huber_px=huber_px, check=check)
        except NotImplementedError as exc:
            if backend != "auto":
                raise
            log.info("numpy backend: %s; optimising with GTSAM", exc)
    if problem is None:
        state = rig_graph.optimize(max_iterations)
        return (state, None) if return_problem else state
    state = problem.optimize(max_iterations, stop=stop)
    problem.write_values(rig_graph.values)
    rig_graph.iterations = problem.iterations
    return (state, problem) if return_problem else state

"""RigGraph's problem packed into flat numpy arrays: residuals and Jacobians without Python callbacks.

:class:`~ari_sfm.factors.rig_graph.RigGraph` holds one ``gtsam.CustomFactor`` per (camera, image);
:class:`VectorizedProblem` holds *the same problem*:

- the same variables and tangent spaces: intrinsics K(c) (additive),
  world_T_cam C(c) for c > 0 and world_T_target X(f) (Pose3, right-perturbed
  ``T Exp([w, v])``, :func:`ari_sfm.geometry.se3_exp`), the normal N (a
  ``gtsam.Unit3``, retracted by ``Unit3.retract``), the distance H (additive,
  optional); camera 0 is the world (no pose variable);
- the same residuals and Jacobians as :func:`~ari_sfm.factors.view_factor.view_residuals`:
  the projection is the model's own batched kernel
  (:func:`ari_sfm.models.ari.ari_project`, :func:`ari_sfm.models.exact.exact_project`,
  one call per camera for all its corners, the plate thickness a per-corner
  array when stacked plates differ), chained to the tangent spaces by the compiled
  :mod:`~ari_sfm.factors.view_kernels` (the one copy, the GTSAM factor's too);
  the per-corner Huber loss of :mod:`~ari_sfm.factors.robust` (the error its sum, the linear
  system IRLS-weighted, as view_residuals' rows and excess row), non-finite
  residuals replaced by 1e6, a camera beyond the window gives 1e6 and zero
  Jacobians; whitened by each factor's isotropic sigma (the pixel sigma).

The normal equations are formed per camera in one compiled pass
(:func:`~ari_sfm.factors.view_kernels.accumulate_views`: the chain rule and each view's
``A^T A`` of its rows ``[J_frame J_global r]``) and solved by :mod:`~ari_sfm.solver.schur`;
:mod:`~ari_sfm.solver.levenberg_marquardt` drives the iterations (this class is its :class:`LMProblem`); factors a user
added to the graph join through :mod:`~ari_sfm.factors.extra_factors`.

It is built from what RigGraph.build selected (:meth:`RigGraph.packed_factors`: each view's
data, keys and sigma, and the other factors); the GTSAM view factors are not made for it (RigGraph
makes its graph on first access, e.g. a researcher's ``rg.graph.push_back``; then the graph is read).
"""
from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from ..geometry import Pose, retract_poses
from ..helper_thread import shared_map
from ..models.ari import AriJacobians, ari_pixels, ari_project, check_window
from ..models.exact import ExactJacobians, exact_pixels, exact_project
from ..records import Observation
from ..solver.bundle import BundleAdjustment
from ..solver.levenberg_marquardt import LMParams, LMReport, NonFiniteJacobian, levenberg_marquardt
from ..solver.schur import NormalEquations, model_decrease, solve_damped
from . import keys as K_
from .extra_factors import ExtraFactors
from .marginals import CovarianceTable, covariances_by_key
from .robust import huber_residual_scale, huber_view_residual, weighted_residuals
from .variables import MODELS, GraphLike, RigState, Variables, estimated_offset
from .view_factor import ViewData, ViewKeys, camera_terms
from .view_kernels import accumulate_views, add_camera, chain_rows, rig_transforms, transform_points

log = logging.getLogger(__name__)

INVALID_RESIDUAL = 1e6  # what view_residuals puts for a non-finite residual or a camera beyond the window
PARALLEL_MIN_CORNERS = 2000  # corners from which linearize forms its cameras' equations on two threads
# the models' batched projections
_KERNELS: dict[str, tuple[Callable[..., AriJacobians | ExactJacobians], Callable[..., np.ndarray]]] = {
    "ari": (ari_project, ari_pixels), "exact": (exact_project, exact_pixels)}  # (with Jacobians, pixels alone)



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


@dataclass(frozen=True)
class _CameraModel:
    """The model at one camera's corners: camera-frame points and pixels, with Jacobians the model's derivatives."""

    X: np.ndarray  # (m, 3)
    uv: np.ndarray  # (m, 2)
    J_point: np.ndarray | None = None  # (m, 2, 3)
    J_normal: np.ndarray | None = None  # (m, 2, 3)
    J_params: np.ndarray | None = None  # (m, 2, n_params)
    J_distance: np.ndarray | None = None  # (m, 2)


@dataclass(frozen=True)
class _CameraSystem:
    """One camera's share of the normal equations (:func:`~ari_sfm.factors.view_kernels.accumulate_views`'
    arrays: V, g_frame, W, U, g_camera; None for a camera beyond the window), its squared whitened
    residuals, the Huber excess over them and where a Jacobian entry was not finite."""

    err2: float
    excess: float
    arrays: tuple[np.ndarray, ...] | None
    bad: np.ndarray | None


@dataclass
class _Transforms:
    """Per-view and per-camera quantities of a Variables, shared by all corners."""

    R_cam_target: np.ndarray  # (V, 3, 3)
    t_cam_target: np.ndarray  # (V, 3)
    R_cam_world: np.ndarray  # (C, 3, 3)
    normal_world: np.ndarray  # (W, 3) each window's
    normal_cam: np.ndarray  # (C, 3) each camera's window's normal
    basis: list[np.ndarray]  # per window: the (3, 2) Unit3 tangent basis of its normal
    distance_cam: np.ndarray | None  # (C,) h_c = h_w - n_w . C_c for the camera's window w


def _variables_of(rg: GraphLike) -> Variables:
    """The packed variables of a graph's values, or of its base state while its values are still to be
    made (a RigGraph's, on first access): the same numbers (a Pose3 or Unit3 stored in a gtsam.Values
    reads back exactly as made)."""
    C, F, n_p = len(rg.camera_names), len(rg.frame_names), rg.n_params
    W = max(rg.camera_windows) + 1
    R_wc, t_wc = np.tile(np.eye(3), (C, 1, 1)), np.zeros((C, 3))
    R_wt, t_wt = np.empty((F, 3, 3)), np.empty((F, 3))
    if getattr(rg, "made_values", True) is None and getattr(rg, "unwritten", None) is None:
        st = rg.base_state
        for c in range(1, C):
            inv = st.cam_from_world[rg.camera_names[c]].inverse()  # world_T_cam, as pose3_from_cam_from_world
            R_wc[c], t_wc[c] = inv.R, inv.t
        for f, name in enumerate(rg.frame_names):
            R_wt[f], t_wt[f] = st.world_from_target[name].R, np.asarray(st.world_from_target[name].t, float)
        intrinsics = np.array([np.asarray(st.params[n][:n_p], float) for n in rg.camera_names]).reshape(C, n_p)
        normals = tuple(gtsam.Unit3(np.asarray(st.normal(w), float)) for w in range(W))
        distances = tuple(estimated_offset(st.offset(w)) if rg.estimate_distance else st.offset(w) for w in range(W))
        return Variables(intrinsics, R_wc, t_wc, normals, R_wt, t_wt, distances)
    v = rg.values
    for c in range(1, C):
        p = v.atPose3(K_.C(c))
        R_wc[c], t_wc[c] = p.rotation().matrix(), np.asarray(p.translation())
    for f in range(F):
        p = v.atPose3(K_.X(f))
        R_wt[f], t_wt[f] = p.rotation().matrix(), np.asarray(p.translation())
    distances = tuple(float(v.atVector(K_.window_plane(w))[0]) if rg.estimate_distance else rg.base_state.offset(w)
                      for w in range(W))
    return Variables(np.array([v.atVector(K_.K(c)) for c in range(C)], float).reshape(C, n_p),
                     R_wc, t_wc, tuple(v.atUnit3(K_.window_normal(w)) for w in range(W)), R_wt, t_wt, distances)


class _RigViews:
    """A VectorizedProblem's views as the observation block of its :class:`~ari_sfm.solver.bundle.BundleAdjustment`."""

    linearized_error_is_error = True
    linearize_trials = True

    def __init__(self, problem: VectorizedProblem) -> None:
        self.problem = problem

    def error(self, x: Variables) -> float:
        return self.problem.views_error(x)

    def linearize(self, x: Variables) -> NormalEquations:
        return self.problem.linearize_views(x)

    def retract(self, x: Variables, step: tuple[np.ndarray, np.ndarray]) -> Variables:
        return self.problem.retract(x, step)


class VectorizedProblem:
    """RigGraph's problem packed into flat arrays: the numpy backend's LM problem.

    The :class:`~ari_sfm.solver.levenberg_marquardt.LMProblem` of the numpy backend (linearize, solve,
    model_decrease, retract, error). Mirrors RigGraph: :meth:`optimize` (updates :attr:`x`, sets
    :attr:`iterations` and :attr:`report`), :meth:`state`, :meth:`residuals`;
    :meth:`write_values` copies the values into a gtsam.Values.
    """

    def __init__(
        self,
        views: Sequence[tuple[ViewData, ViewKeys, float]],
        observations: Sequence[tuple[str, Observation]],
        variables: Variables,
        camera_names: Sequence[str],
        frame_names: Sequence[str],
        n_params: int,
        base_state: RigState,
        estimate_distance: bool,
        model: str,
        huber_px: float | None,
        extra_factors: Sequence[gtsam.NonlinearFactor] = (),
        camera_windows: Sequence[int] | None = None,
    ) -> None:
        """Pack the views.

        Args:
            views: (ViewData, ViewKeys, sigma_px) per view factor.
            observations: (camera, obs) per view factor.
            variables: The start values.
            camera_names: The cameras, camera 0 (the world) first.
            frame_names: The target frames.
            n_params: How many of the 9 intrinsic parameters are variables (the first ones).
            base_state: The state the held values come from (the other parameters, a held distance).
            estimate_distance: Whether the windows' distances are variables.
            model: The model's name (a key of ``MODELS``).
            huber_px: The Huber threshold the view factors were built with (px); None: no loss.
            extra_factors: The graph's other factors (a researcher's), added as a term.
            camera_windows: Each camera's window index (default: one window for all).

        Raises:
            ValueError: an unknown model, or a view whose keys or data do not match the problem.
        """
        if model not in MODELS:
            raise ValueError(f"unknown model {model!r} (known: {', '.join(MODELS)})")
        self.model = model
        self.factory = MODELS[model]
        self.camera_names = list(camera_names)
        self.frame_names = list(frame_names)
        self.n_params = int(n_params)
        self.base_state = base_state
        self.camera_windows = ([0] * len(self.camera_names) if camera_windows is None
                               else [int(w) for w in camera_windows])
        self.n_windows = max(self.camera_windows) + 1
        self.estimate_distance = bool(estimate_distance)
        self.huber_px = huber_px
        self.factor_views = list(observations)
        self.x = variables
        self.iterations = 0
        self.report: LMReport | None = None
        self._error_cache: tuple[Variables, float] | None = None
        # optimize's last linearisation, if at self.x
        self._system_cache: tuple[Variables, NormalEquations] | None = None
        self._transforms_cache: tuple[Variables, _Transforms] | None = None
        self._pack(views)
        self._extra = ExtraFactors(self, extra_factors)
        # the one bundle-adjustment problem: the views (target frames eliminated), the user factors a term
        self.adjustment = BundleAdjustment(_RigViews(self), [self._extra])

    # ------------------------------------------------------------------ from a graph
    @staticmethod
    def from_rig_graph(rg: GraphLike, huber_px: float | None = None, check: bool = True) -> VectorizedProblem:
        """The problem of a built RigGraph at its current values (its view factors and any factors added to it).

        Args:
            rg: The built graph.
            huber_px: The Huber threshold the view factors were built with (``rg.huber_px`` after
                RigGraph.build; the factors themselves do not tell).
            check: Compare the residuals of a few views (one per camera and plate, and the worst ones) with
                the graph's own factors.

        Returns:
            The packed problem.

        Raises:
            ValueError: with ``check``, the residuals differ from the graph's (e.g. a wrong ``huber_px``).
        """
        views, extra = rg.packed_factors()
        variables = _variables_of(rg)
        problem = VectorizedProblem(views, rg.factor_views, variables, rg.camera_names, rg.frame_names, rg.n_params,
                                    rg.base_state, rg.estimate_distance, rg.model, huber_px, extra, rg.camera_windows)
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
            if data.n_params != n_p or not 0 <= c < C or not 0 <= f < F:
                raise ValueError(f"view {k}: n_params {data.n_params}, camera {c} or frame {f} out of range")
            w = self.camera_windows[c]
            if vkeys.normal != K_.window_normal(w) or (vkeys.distance is not None
                                                       and vkeys.distance != K_.window_plane(w)):
                raise ValueError(f"view {k}: its normal or distance key is not its camera's window's ({w})")
            if (vkeys.distance is not None) != self.estimate_distance:
                raise ValueError(f"view {k}: distance key does not match estimate_distance={self.estimate_distance}")
            if not self.estimate_distance and vkeys.fixed_distance_mm != self.x.distances[w]:
                raise ValueError(f"view {k}: fixed distance {vkeys.fixed_distance_mm} differs from "
                                 f"{self.x.distances[w]}")
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
        # camera slices of views and corners
        self.camera_views = np.searchsorted(self.view_camera, np.arange(C + 1))
        self.camera_corners = self.view_start[self.camera_views]
        # global tangent layout: per camera [intrinsics, pose] (camera 0's pose fixed: zero columns), then per
        # window [normal (2), distance (1, if estimated)]
        self.camera_block = n_p + 6
        window_block = 2 + (1 if self.estimate_distance else 0)
        self.normal_cols = [C * self.camera_block + w * window_block for w in range(self.n_windows)]
        self.distance_cols = [n + 2 for n in self.normal_cols] if self.estimate_distance else None
        self.n_global = C * self.camera_block + self.n_windows * window_block
        self.local_dim = n_p + 6 + window_block
        self.camera_cols = [np.concatenate([c * self.camera_block + np.arange(self.camera_block),
                                            self.normal_cols[self.camera_windows[c]] + np.arange(window_block)]
                                           ).astype(np.int64) for c in range(C)]
        self.fixed_cols = np.arange(n_p, n_p + 6)  # camera 0's pose
        # the columns of each camera's rows in linearize (camera 0's without its pose)
        self.camera_row_cols = [cols if c > 0 else np.delete(cols, np.arange(n_p, n_p + 6))
                                for c, cols in enumerate(self.camera_cols)]
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
        """The per-view and per-camera quantities of x (the last x's kept: LM evaluates the error at a
        trial step, then linearises there)."""
        cached = self._transforms_cache
        if cached is not None and cached[0] is x:
            return cached[1]
        tr = self._compute_transforms(x)
        self._transforms_cache = (x, tr)
        return tr

    def _compute_transforms(self, x: Variables) -> _Transforms:
        normals = np.array([np.asarray(n.point3(), float) for n in x.normals])
        with_distance = x.distances[0] is not None
        offsets = x.offsets() if with_distance else (0.0,) * self.n_windows
        R_ct, t_ct, n_c, h_c = rig_transforms(
            x.world_R_cam, x.world_t_cam, x.world_R_target, x.world_t_target, self.view_camera, self.view_frame,
            normals[0], offsets[0], with_distance)
        for w in range(1, self.n_windows):  # the other windows' cameras: their own normal and plane
            _, _, n_w, h_w = rig_transforms(x.world_R_cam, x.world_t_cam, x.world_R_target[:0], x.world_t_target[:0],
                                            self.view_camera[:0], self.view_frame[:0], normals[w], offsets[w],
                                            with_distance)
            mine = np.array(self.camera_windows) == w
            n_c[mine] = n_w[mine]
            if with_distance:
                h_c[mine] = h_w[mine]
        bases = [np.asarray(n.basis(), float) for n in x.normals]  # (their own memory layout: the BLAS path)
        return _Transforms(R_ct, t_ct, np.swapaxes(x.world_R_cam, 1, 2), normals, n_c, bases,
                           h_c if with_distance else None)

    def _camera_model(self, x: Variables, tr: _Transforms, c: int, jacobians: bool) -> _CameraModel | None:
        """The model at camera c's corners (one kernel call per run of its plates); None when the camera is
        beyond the window (h <= 0: an LM trial put it there)."""
        s, e = int(self.camera_corners[c]), int(self.camera_corners[c + 1])
        m, n_p = e - s, self.n_params
        h = None if tr.distance_cam is None else float(tr.distance_cam[c])
        if h is not None and h <= 0.0:
            return None
        vs, ve = int(self.camera_views[c]), int(self.camera_views[c + 1])
        X = transform_points(self.points[s:e], tr.R_cam_target[vs:ve], tr.t_cam_target[vs:ve],
                             self.view_start[vs:ve + 1] - s)
        with_jacobians, pixels = _KERNELS[self.model]
        runs = self._camera_runs[c]
        if len(runs) == 1:  # the usual case: every plate of the camera in one call
            params = runs[0].base_params.copy()
            params[:n_p] = x.intrinsics[c]
            args = (X, params, tr.normal_cam[c], self.corner_thickness[s:e], runs[0].index, runs[0].medium_index, h)
            if not jacobians:
                return _CameraModel(X, pixels(*args))
            J = with_jacobians(*args, n_p)
            return _CameraModel(X, J.uv, J.J_point, J.J_normal, J.J_params, np.ascontiguousarray(J.J_distance))
        uv = np.empty((m, 2))
        if jacobians:
            Jp, Jn, Jpar, Jd = np.empty((m, 2, 3)), np.empty((m, 2, 3)), np.empty((m, 2, n_p)), np.empty((m, 2))
        for g in runs:
            a, b = g.start - s, g.stop - s
            params = g.base_params.copy()
            params[:n_p] = x.intrinsics[c]
            args = (X[a:b], params, tr.normal_cam[c], self.corner_thickness[g.start:g.stop], g.index,
                    g.medium_index, h)
            if not jacobians:
                uv[a:b] = pixels(*args)
                continue
            J = with_jacobians(*args, n_p)
            uv[a:b] = J.uv
            Jp[a:b], Jn[a:b], Jpar[a:b], Jd[a:b] = J.J_point, J.J_normal, J.J_params, J.J_distance
        return _CameraModel(X, uv) if not jacobians else _CameraModel(X, uv, Jp, Jn, Jpar, Jd)

    def _camera_residuals(self, x: Variables, tr: _Transforms, c: int, huber_px: float | None,
                          whiten: bool = False) -> np.ndarray:
        """Camera c's residuals (m, 2), whitened by the factors' sigmas with ``whiten``; Huber: s r, so
        that 0.5 |.|^2 is the loss (what error() sums; view_residuals' factor holds sqrt(w) r and the
        excess row instead). A corner behind the window gives 1e6, a camera beyond it 1e6 everywhere."""
        s, e = int(self.camera_corners[c]), int(self.camera_corners[c + 1])
        model = self._camera_model(x, tr, c, False)
        if model is None:
            return np.full((e - s, 2), INVALID_RESIDUAL)
        r = model.uv - self.measured[s:e]
        if huber_px is not None:
            rx, ry = r[:, 0], r[:, 1]
            dist = np.sqrt(rx * rx + ry * ry)  # np.linalg.norm(r, axis=1)'s arithmetic, 5x faster
            r = r * huber_residual_scale(dist, huber_px)[:, None]  # 0.5 |.|^2 = rho
        if not np.isfinite(r.sum()):  # (the sum: one fast check)
            r[~np.isfinite(r)] = INVALID_RESIDUAL  # a point fell behind the window
        return r * self.corner_inv_sigma[s:e, None] if whiten and not self.unit_sigma else r

    def _camera_weights(self, model: _CameraModel, c: int, huber_px: float | None, whiten: bool
                        ) -> tuple[np.ndarray, np.ndarray, float]:
        """(each corner's Jacobian scale sqrt(w) / sigma (m,), the scaled residuals (m, 2), the error's
        excess over their 0.5 r^T r): Huber as IRLS (:func:`~ari_sfm.factors.robust.weighted_residuals`), a
        corner behind the window at 1e6 (whitened)."""
        s, e = int(self.camera_corners[c]), int(self.camera_corners[c + 1])
        inv_sigma = self.corner_inv_sigma[s:e]
        scale, res, dist, extra, beyond = weighted_residuals(
            model.uv, self.measured[s:e], -1.0 if huber_px is None else float(huber_px), inv_sigma, whiten,
            INVALID_RESIDUAL)
        excess = 0.0
        if beyond:  # (numpy's pairwise sum over the corners beyond the threshold, as before)
            ok = np.isfinite(dist)  # a corner behind the window counts as its 1e6 residual
            excess = float(np.sum(extra[ok] if not whiten or self.unit_sigma else extra[ok] * inv_sigma[ok] ** 2))
        return scale, res, excess

    def _camera_terms(self, x: Variables, tr: _Transforms, c: int) -> tuple:
        """The chain rule's per-camera arguments (:func:`~ari_sfm.factors.view_factor.camera_terms`, then
        whether the camera has a pose and the window distance is estimated)."""
        R_wc = x.world_R_cam[c] if c > 0 else None  # camera 0 is the world: no pose columns
        w = self.camera_windows[c]
        return camera_terms(tr.normal_world[w], tr.basis[w], R_wc, x.world_t_cam[c]) + (c > 0, self.estimate_distance)

    def _camera_rows(self, x: Variables, tr: _Transforms, c: int, huber_px: float | None) -> np.ndarray:
        """Camera c's rows (m, 2, 6 + local_dim + 1): [J_frame | J_global (camera-local columns) | residual],
        Huber as IRLS (rows times sqrt(w)), not whitened; the excess row left out. For evaluate_views:
        linearize forms the same rows inside :func:`~ari_sfm.factors.view_kernels.accumulate_views`."""
        s, e = int(self.camera_corners[c]), int(self.camera_corners[c + 1])
        m, n_p, L = e - s, self.n_params, self.local_dim
        out = np.zeros((m, 2, 6 + L + 1))
        model = self._camera_model(x, tr, c, True)
        if model is None:
            out[:, :, -1] = INVALID_RESIDUAL
            return out
        vs, ve = int(self.camera_views[c]), int(self.camera_views[c + 1])
        chain_rows(model.J_point, model.J_normal, model.J_distance, model.X, self.points[s:e],
                   tr.R_cam_target[vs:ve], self.view_start[vs:ve + 1] - s, *self._camera_terms(x, tr, c), n_p, out)
        out[:, :, 6:6 + n_p] = model.J_params
        scale, res, _ = self._camera_weights(model, c, huber_px, whiten=False)
        out[:, :, :-1] *= scale[:, None, None]
        out[:, :, -1] = res
        return out

    def error(self, x: Variables | None = None) -> float:
        """GTSAM's graph error at x (default: the current values): 0.5 * sum of whitened squared residuals.

        Args:
            x: The values (default: the current ones).

        Returns:
            The views' error plus the user factors' (:attr:`adjustment`).
        """
        return self.adjustment.error(self.x if x is None else x)

    def views_error(self, x: Variables) -> float:
        """The views' share of the error at ``x`` (the observation block's).

        Args:
            x: The values.

        Returns:
            0.5 * the sum of the views' whitened squared residuals (Huber: the loss).
        """
        tr = self._transforms(x)
        total = 0.0
        for c in range(len(self.camera_names)):
            if self.camera_corners[c + 1] == self.camera_corners[c]:
                continue
            rw = self._camera_residuals(x, tr, c, self.huber_px, whiten=True)
            total += 0.5 * float(np.einsum("ij,ij->", rw, rw))
        return total

    def _camera_system(self, x: Variables, tr: _Transforms, c: int) -> _CameraSystem:
        """Camera c's share of the whitened normal equations at x (in its own arrays: threads may form
        several cameras' at once)."""
        s, e = int(self.camera_corners[c]), int(self.camera_corners[c + 1])
        model = self._camera_model(x, tr, c, True)
        if model is None:  # the camera beyond the window: residuals 1e6, Jacobians zero
            return _CameraSystem(2 * (e - s) * INVALID_RESIDUAL ** 2, 0.0, None, None)
        scale, res, excess = self._camera_weights(model, c, self.huber_px, whiten=True)
        vs, ve = int(self.camera_views[c]), int(self.camera_views[c + 1])
        nv, L = ve - vs, len(self.camera_row_cols[c])
        arrays = (np.zeros((nv, 6, 6)), np.zeros((nv, 6)), np.zeros((nv, 6, L)), np.zeros((L, L)), np.zeros(L))
        bad = np.zeros(e - s, dtype=np.bool_)
        err2 = accumulate_views(model.J_point, model.J_normal, model.J_distance, model.J_params, model.X,
                                self.points[s:e], tr.R_cam_target[vs:ve], self.view_start[vs:ve + 1] - s,
                                *self._camera_terms(x, tr, c), scale, res, *arrays, bad)
        return _CameraSystem(err2, excess, arrays, bad)

    def linearize(self, x: Variables) -> NormalEquations:
        """The whitened normal equations at x: the views' and the user factors' (:attr:`adjustment`).

        Args:
            x: The linearisation point.

        Returns:
            The system.
        """
        return self.adjustment.linearize(x)

    def linearize_views(self, x: Variables) -> NormalEquations:
        """The views' whitened normal equations at x (the observation block's).

        Per camera, the model's derivatives chained to the tangent spaces and each view's A^T A summed in one
        compiled pass (:func:`~ari_sfm.factors.view_kernels.accumulate_views`; two cameras at once on two
        threads from :data:`PARALLEL_MIN_CORNERS` corners), then the cameras added to the system in their order
        (:func:`~ari_sfm.factors.view_kernels.add_camera`): the same numbers on one thread or two.

        Args:
            x: The linearisation point.

        Returns:
            The system: the target frames as the blocks (6 columns each), ``n_global`` global columns.

        Raises:
            NonFiniteJacobian: a Jacobian entry is not finite (a corner behind the window).
        """
        C, F, G = len(self.camera_names), len(self.frame_names), self.n_global
        tr = self._transforms(x)
        V, g_f = np.zeros((F, 6, 6)), np.zeros((F, 6))
        W, U, g_g = np.zeros((F, 6, G)), np.zeros((G, G)), np.zeros(G)
        err2, err_excess = 0.0, 0.0
        cameras = [c for c in range(C) if self.camera_corners[c + 1] > self.camera_corners[c]]
        threads = 2 if self.camera_corners[-1] >= PARALLEL_MIN_CORNERS else 1
        systems = shared_map(lambda c: self._camera_system(x, tr, c), cameras, threads=threads, min_items=2)
        for c, cs in zip(cameras, systems):
            err2 += cs.err2
            if cs.arrays is None or cs.bad is None:  # the camera beyond the window
                continue
            err_excess += cs.excess
            if cs.bad.any():
                s, e = int(self.camera_corners[c]), int(self.camera_corners[c + 1])
                factors = np.unique(self.view_order[self.corner_view[s:e][cs.bad]])[:10].tolist()
                raise NonFiniteJacobian(f"non-finite Jacobian entries in factor(s) {factors} "
                                        "(a corner behind the window at the linearisation point)")
            vs, ve = int(self.camera_views[c]), int(self.camera_views[c + 1])
            add_camera(*cs.arrays, self.view_frame[vs:ve], self.camera_row_cols[c], V, g_f, W, U, g_g)
        return NormalEquations(V, g_f, W, U, g_g, 0.5 * err2 + err_excess)

    # ------------------------------------------------------------------ the LMProblem interface
    linearize_trials = True  # a linearisation costs ~2 error evaluations: LM linearises its trials

    @property
    def linearized_error_is_error(self) -> bool:
        """The linearisation's 0.5 r^T r is the error unless user factors (robust noise models) join."""
        return self.adjustment.linearized_error_is_error

    @staticmethod
    def solve(sys: NormalEquations, lam: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The step of the damped system (:func:`~ari_sfm.solver.schur.solve_damped`).

        Args:
            sys: The normal equations.
            lam: The damping.

        Returns:
            (global step, frame steps), or None when the damped system cannot be solved.
        """
        return solve_damped(sys, lam)

    @staticmethod
    def model_decrease(sys: NormalEquations, step: tuple[np.ndarray, np.ndarray]) -> float:
        return model_decrease(sys, *step)

    def retract(self, x: Variables, step: tuple[np.ndarray, np.ndarray]) -> Variables:
        """x moved by a step: Pose3 right perturbations, Unit3.retract, the rest additive.

        Args:
            x: The values.
            step: (global step (n_global,), frame steps (F, 6)).

        Returns:
            The moved values.
        """
        d_global, d_frame = step
        C, n_p, B = len(self.camera_names), self.n_params, self.camera_block
        blocks = d_global[: C * B].reshape(C, B)
        R_wc, t_wc = x.world_R_cam.copy(), x.world_t_cam.copy()
        if C > 1:
            R_wc[1:], t_wc[1:] = retract_poses(x.world_R_cam[1:], x.world_t_cam[1:], blocks[1:, n_p:])
        R_wt, t_wt = retract_poses(x.world_R_target, x.world_t_target, d_frame)
        normals = tuple(n.retract(d_global[col:col + 2]) for n, col in zip(x.normals, self.normal_cols))
        distances: tuple[float | None, ...] = x.distances
        if self.distance_cols is not None:  # estimate_distance
            distances = tuple(h + float(d_global[col]) for h, col in zip(x.offsets(), self.distance_cols))
        return Variables(x.intrinsics + blocks[:, :n_p], R_wc, t_wc, normals, R_wt, t_wt, distances)

    # ------------------------------------------------------------------ LM
    def optimize(self, max_iterations: int = 100, relative_tolerance: float = 1e-10,
                 params: LMParams | None = None, stop: str = "converged") -> RigState:
        """Levenberg-Marquardt from the current values (GTSAM's algorithm).

        Updates the values, :attr:`iterations` and :attr:`report`.

        Args:
            max_iterations: Cap on the accepted steps.
            relative_tolerance: LM stops when the relative error decrease is below it.
            params: LM's constants (default :class:`~ari_sfm.solver.levenberg_marquardt.LMParams`).
            stop: The stop rule (see :func:`~ari_sfm.solver.levenberg_marquardt.levenberg_marquardt`).

        Returns:
            The state at the solution.
        """
        cached = self._error_cache
        initial = cached[1] if cached is not None and cached[0] is self.x else None
        result = levenberg_marquardt(self, self.x, max_iterations, relative_tolerance, params, stop, initial)
        self.x = result.x
        self._system_cache = None if result.system_at_x is None else (result.x, result.system_at_x)
        self.iterations = result.report.iterations
        self.report = result.report
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
        distances = [x.distances[w] if self.estimate_distance else self.base_state.offset(w)
                     for w in range(self.n_windows)]
        more = tuple((np.asarray(x.normals[w].point3(), float), distances[w]) for w in range(1, self.n_windows))
        return RigState(params, cams, np.asarray(x.normal.point3(), float), frames, distances[0], more)

    def residuals(self) -> list[tuple[Observation, np.ndarray]]:
        """Unweighted pixel residuals (M, 2) of every view at the current values, in factor order (as RigGraph)."""
        res = self._all_residuals(self.x, None)
        by_factor = {int(self.view_order[k]): res[self.view_start[k]:self.view_start[k + 1]]
                     for k in range(self.n_views)}
        return [(obs, by_factor[i]) for i, (_, obs) in enumerate(self.factor_views)]

    def _all_residuals(self, x: Variables, huber_px: float | None) -> np.ndarray:
        tr = self._transforms(x)
        res = np.empty((self.n_corners, 2))
        for c in range(len(self.camera_names)):
            s, e = self.camera_corners[c], self.camera_corners[c + 1]
            if e > s:
                res[s:e] = self._camera_residuals(x, tr, c, huber_px)
        return res

    def evaluate_views(self, x: Variables | None = None) -> list[tuple[np.ndarray, list[np.ndarray]]]:
        """Per factor (factor order): residual (2M,) and Jacobians in the factor's key order, as view_residuals.

        Not whitened by sigma (view_residuals is not either). For tests.

        Args:
            x: The values (default: the current ones).

        Returns:
            Per view factor, its residual and its Jacobian blocks (with Huber, the excess row appended).
        """
        x = self.x if x is None else x
        tr = self._transforms(x)
        n_p = self.n_params
        by_factor: dict[int, tuple[np.ndarray, list[np.ndarray]]] = {}
        for c in range(len(self.camera_names)):
            s = int(self.camera_corners[c])
            if self.camera_corners[c + 1] == s:
                continue
            full = self._camera_rows(x, tr, c, self.huber_px)  # rows times sqrt(w)
            res, Jf, Jg = full[:, :, -1], full[:, :, :6], full[:, :, 6:-1]
            raw = self._camera_residuals(x, tr, c, None)
            for k in range(self.camera_views[c], self.camera_views[c + 1]):
                a, b = self.view_start[k] - s, self.view_start[k + 1] - s
                m2 = 2 * (b - a)
                blocks = [Jg[a:b, :, :n_p].reshape(m2, n_p)]
                if c > 0:
                    blocks.append(Jg[a:b, :, n_p:n_p + 6].reshape(m2, 6))
                blocks += [Jg[a:b, :, n_p + 6:n_p + 8].reshape(m2, 2), Jf[a:b].reshape(m2, 6)]  # its window's N
                if self.estimate_distance:
                    blocks.append(Jg[a:b, :, n_p + 8:n_p + 9].reshape(m2, 1))
                r = res[a:b].reshape(-1)
                if self.huber_px is not None:  # the excess row, its Jacobian zero
                    r = np.append(r, huber_view_residual(raw[a:b], self.huber_px)[0][-1])
                    blocks = [np.vstack([B, np.zeros((1, B.shape[1]))]) for B in blocks]
                by_factor[int(self.view_order[k])] = (r, blocks)
        return [by_factor[i] for i in range(self.n_views)]

    def write_values(self, values: gtsam.Values, x: Variables | None = None) -> None:
        """Update a gtsam.Values (holding this problem's keys) to x.

        Args:
            values: The values, changed in place.
            x: The values to write (default: the current ones).
        """
        x = self.x if x is None else x
        for c in range(len(self.camera_names)):
            values.update(K_.K(c), np.asarray(x.intrinsics[c], float))
            if c > 0:
                values.update(K_.C(c), gtsam.Pose3(gtsam.Rot3(x.world_R_cam[c]), x.world_t_cam[c]))
        for w in range(self.n_windows):
            values.update(K_.window_normal(w), x.normals[w])
            if self.estimate_distance:
                values.update(K_.window_plane(w), np.array([x.offsets()[w]]))
        for f in range(len(self.frame_names)):
            values.update(K_.X(f), gtsam.Pose3(gtsam.Rot3(x.world_R_target[f]), x.world_t_target[f]))

    def marginal_covariances(self) -> dict[int, np.ndarray]:
        """Marginal covariances of the global variables at the current values, by key.

        What ``gtsam.Marginals(graph, values).marginalCovariance(key)`` gives, in the units of the factors'
        sigmas (see :mod:`~ari_sfm.factors.marginals`).

        Returns:
            The covariances by gtsam key: K(c), C(c) for c > 0, N(w) and, when estimated, H(w) (GTSAM's
            tangent spaces).
        """
        cached = self._system_cache  # optimize's last linearisation when it was at the final values
        sys = cached[1] if cached is not None and cached[0] is self.x else self.linearize(self.x)
        return covariances_by_key(self, sys)

    def marginals(self) -> CovarianceTable:
        """The marginal covariances as a ``gtsam.Marginals`` stand-in.

        E.g. for :func:`ari_sfm.factors.uncertainty.rig_uncertainty`.

        Returns:
            A table answering ``marginalCovariance(key)`` for the intrinsics, camera poses, normal and distance.
        """
        return CovarianceTable(self.marginal_covariances())

    # ------------------------------------------------------------------ consistency with a graph
    def _check_against(self, rg: GraphLike, worst: int = 3) -> None:
        """Compare the residuals of a few factors with GTSAM's (catches a wrong huber_px)."""
        res = self._all_residuals(self.x, self.huber_px)
        rw = res * self.corner_inv_sigma[:, None]
        self._error_cache = (self.x, 0.5 * float(np.einsum("ij,ij->", rw, rw)) + self._extra.error(self.x))
        view_norm = np.add.reduceat(np.abs(res).sum(axis=1), self.view_start[:-1]) if self.n_corners else np.zeros(0)
        C = len(self.camera_names)
        picks = {int(self.camera_views[c]) for c in range(C) if self.camera_views[c + 1] > self.camera_views[c]}
        picks |= set(np.argsort(view_norm)[-worst:].tolist())
        raw = self._all_residuals(self.x, None)
        for k in sorted(picks):
            r = raw[self.view_start[k]:self.view_start[k + 1]]
            if self.huber_px is not None and np.any(np.abs(r) >= INVALID_RESIDUAL):
                continue  # a corner behind the window: 1e6 here, its weighted row there
            mine = r.reshape(-1) if self.huber_px is None else huber_view_residual(r, self.huber_px)[0]
            theirs = np.asarray(rg.view_factor_at(int(self.view_order[k])).unwhitenedError(rg.values))
            if mine.shape != theirs.shape or not np.allclose(mine, theirs, rtol=1e-9, atol=1e-9):
                size = (f"{theirs.size} rows, not {mine.size}" if mine.shape != theirs.shape
                        else f"max {np.max(np.abs(mine - theirs)):.3g}")
                raise ValueError(f"factor {int(self.view_order[k])}: vectorised residuals differ from the graph's "
                                 f"({size}); was the graph built with huber_px={self.huber_px}?")


@functools.lru_cache(maxsize=4096)  # a rig's few keys, looked up once per view and packing
def _index(key: int, expected: str) -> int:
    sym = gtsam.Symbol(key)
    if chr(sym.chr()) != expected:
        raise ValueError(f"key {gtsam.DefaultKeyFormatter(key)} is not a {expected!r} key")
    return int(sym.index())


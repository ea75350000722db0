"""The same refinement as a GTSAM factor graph: one CustomFactor per image holding all its observations.

Variables (keys, from the one key table :mod:`ari_sfm.factors.keys`): ``f(k)`` Pose3 rig_from_world of
frame k >= 1 (frame 0 held: the gauge, not a variable), ``s(c)`` Pose3 sensor_from_rig of camera c
(non-reference sensors), ``k(c)`` Vector of camera c's free COLMAP intrinsics, ``n(w)`` Unit3 window
normal and ``d(w)`` Vector1 distance (mount camera: w = camera; mount world: w = the window), ``p(j)`` Point3 per
COLMAP point3D.

The residuals and Jacobians are :meth:`RefractiveProblem.linearize`'s, restricted to the image's
observations and chained to GTSAM's tangent spaces: a Pose3 ``a_from_b`` moves as
``T Exp([w, v])`` (R' = R exp(w), t' = t + R v), i.e. this module's left perturbation
(exp(R w) R, t + R v); a Unit3 by its own basis. Huber as the rig graph does (per observation inside
the factor, :func:`ari_sfm.factors.robust.huber_view_residual`: IRLS rows and an excess row, the
error the Huber loss). GTSAM's LM eliminates the points itself (its ordering).
"""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from ari_sfm.factors import keys as K_
from ari_sfm.factors.robust import huber_view_residual
from ari_sfm.geometry import Pose
from ari_sfm.solver.bundle import RowTerm

from .plane import WindowPrior
from .problem import RefractiveProblem, State
from .scale_bar import ScaleBar
from .settings import HUBER_PX
from .terms import ScaleBarTerm, WindowPriorTerm

KEY_OF = {"f": K_.rig_frame, "s": K_.sensor, "k": K_.K, "n": K_.window_normal, "d": K_.window_distance,
          "p": K_.point}  # a variable kind's key


def _column_owners(problem: RefractiveProblem, bar: ScaleBar | None = None) -> dict[int, tuple[str, int, int]]:
    """Reduced column -> (kind, variable index, column within the variable); a scale bar's two points
    at the columns after the layout's (:class:`~ari_sfm.colmap.refine.solver.PointObservations`)."""
    lay = problem.layout
    out: dict[int, tuple[str, int, int]] = {}
    for c, ix in enumerate(lay.intrinsics):
        out.update({int(g): ("k", c, j) for j, g in enumerate(ix)})
    for kind, table in (("f", lay.frames), ("s", lay.sensors)):
        for v, row in enumerate(table):
            out.update({int(g): (kind, v, j) for j, g in enumerate(row) if g >= 0})
    for w, row in enumerate(lay.window):
        out.update({int(g): ("n" if j < 2 else "d", w, j if j < 2 else 0) for j, g in enumerate(row) if g >= 0})
    if bar is not None:
        for k, p in enumerate((bar.a, bar.b)):
            out.update({lay.size + 3 * k + j: ("p", int(p), j) for j in range(3)})
    return out


def _to_gtsam_tangents(blocks: dict[tuple[str, int], np.ndarray], state: State, image_camera: np.ndarray) -> None:
    """Turn Jacobian blocks on this problem's tangents into GTSAM's, in place.

    A pose's columns ``[w, v]`` (left perturbation ``(exp(w) R, t + v)``) become GTSAM's right
    perturbation ``T Exp([w', v'])``, i.e. ``[R w', R v']``: the block times R on both halves. A normal's
    basis is GTSAM's Unit3 basis already (:func:`ari_sfm.geometry.unit3_basis`); the rest is additive.

    Args:
        blocks: (kind, variable) -> its Jacobian block (rows, dim); kinds "f" (frame) and "s" (sensor) change.
        state: The state the Jacobians were taken at.
        image_camera: (I,) each image's camera (a sensor's pose is read from its first image).
    """
    for (kind, v), B in blocks.items():
        if kind in ("f", "s"):
            Rv = (state.rig_from_world[v].R if kind == "f"
                  else state.sensor_from_rig[int(np.flatnonzero(image_camera == v)[0])].R)
            B[:, :3], B[:, 3:] = B[:, :3] @ Rv, B[:, 3:] @ Rv


class GtsamRefinement:
    """Build the graph from a state, optimise with GTSAM's LM, read the state back.

    The terms are the numpy backend's (:class:`~ari_sfm.solver.bundle.RowTerm`), each one factor
    (:meth:`term_factor`).

    Args:
        problem: The refractive problem.
        huber_px: The Huber threshold (px); None: plain least squares.
        prior: A declared window plane's prior (a term; alternatively among ``terms``).
        bar: A scale bar (a term; its two points' columns follow the layout's).
        terms: The terms, as the numpy backend's solver holds them (``prior`` and ``bar`` are then in them).
        diagonal_damping: GTSAM's LM with Marquardt's diagonal damping (self-calibration's stiff rows).
    """

    def __init__(self, problem: RefractiveProblem, huber_px: float | None = HUBER_PX, prior: WindowPrior | None = None,
                 bar: ScaleBar | None = None, terms: list[RowTerm] | tuple[RowTerm, ...] | None = None,
                 diagonal_damping: bool = False) -> None:
        self.problem = problem
        self.huber_px = huber_px
        self.bar = bar
        if terms is None:
            terms = ([WindowPriorTerm(prior, problem.layout)] if prior is not None else []) + (
                [ScaleBarTerm(bar, problem.layout.size)] if bar is not None else [])
        self.terms = list(terms)
        self.diagonal_damping = diagonal_damping
        self.owners = _column_owners(problem, bar)

    # -------------------------------------------------------------- values
    def values(self, state: State) -> gtsam.Values:
        m, lay = self.problem.model, self.problem.layout
        v = gtsam.Values()
        for f, p in enumerate(state.rig_from_world):
            if lay.frames[f, 0] >= 0:
                v.insert(K_.rig_frame(f), gtsam.Pose3(gtsam.Rot3(p.R), p.t))
        for c in range(len(m.camera_ids)):
            if lay.sensors[c, 0] >= 0:
                p = state.sensor_from_rig[int(np.flatnonzero(m.image_camera == c)[0])]
                v.insert(K_.sensor(c), gtsam.Pose3(gtsam.Rot3(p.R), p.t))
            free = np.flatnonzero(m.param_map[c].any(axis=0))
            if len(free):  # a camera with every intrinsic held has no variable
                v.insert(K_.K(c), np.asarray(state.colmap_params[c][free], float))
        for w in range(len(state.normals)):
            if lay.window[w, 0] >= 0:
                v.insert(K_.window_normal(w), gtsam.Unit3(state.normals[w]))
            if lay.window[w, 2] >= 0:
                v.insert(K_.window_distance(w), np.array([state.distances[w]]))
        for j, X in enumerate(state.xyz):
            v.insert(K_.point(j), gtsam.Point3(*X))
        return v

    def state(self, values: gtsam.Values, template: State) -> State:
        """The state held by ``values``.

        Args:
            values: The graph's values.
            template: The state the held variables (those with no key) are read from.

        Returns:
            The state.
        """
        m, lay = self.problem.model, self.problem.layout

        def pose(key: int) -> Pose:
            p = values.atPose3(key)
            return Pose(p.rotation().matrix(), np.asarray(p.translation(), float))

        frames = tuple(pose(K_.rig_frame(f)) if lay.frames[f, 0] >= 0 else p
                       for f, p in enumerate(template.rig_from_world))
        sensors = tuple(pose(K_.sensor(int(c))) if lay.sensors[c, 0] >= 0 else s
                        for c, s in zip(m.image_camera, template.sensor_from_rig))
        params = []
        for c, p in enumerate(template.colmap_params):
            p = p.copy()
            free = np.flatnonzero(m.param_map[c].any(axis=0))
            if len(free):
                p[free] = values.atVector(K_.K(c))
            params.append(p)
        normals = np.array([values.atUnit3(K_.window_normal(w)).point3() if lay.window[w, 0] >= 0
                            else template.normals[w] for w in range(len(template.normals))])
        dists = np.array([values.atVector(K_.window_distance(w))[0] if lay.window[w, 2] >= 0 else template.distances[w]
                          for w in range(len(template.distances))])
        xyz = np.array([values.atPoint3(K_.point(j)) for j in range(len(template.xyz))])
        return replace(template, colmap_params=tuple(params), rig_from_world=frames, sensor_from_rig=sensors,
                       normals=normals, distances=dists, xyz=xyz)

    # -------------------------------------------------------------- factors
    def _factor(self, image: int, template: State) -> gtsam.CustomFactor:
        m, problem = self.problem.model, self.problem
        obs = np.flatnonzero(m.obs_image == image)
        points = m.obs_point[obs]
        unique_points = np.unique(points)
        probe = problem.linearize(template, obs)
        columns = sorted({int(g) for g in probe.index.ravel() if g >= 0})
        var_keys: list[tuple[str, int]] = []
        for g in columns:
            kind, v, _ = self.owners[g]
            if (kind, v) not in var_keys:
                var_keys.append((kind, v))
        keys = [KEY_OF[kind](v) for kind, v in var_keys] + [K_.point(int(j)) for j in unique_points]
        rows = 2 * len(obs)
        huber = self.huber_px
        total = rows + (huber is not None)  # Huber: the excess row (factors.robust.huber_view_residual)
        noise = gtsam.noiseModel.Unit.Create(total)
        owners = self.owners

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
            state = self.state_subset(values, template, var_keys, unique_points)
            if not np.all(problem.image_windows(state)[1][image] > 0.0):  # a trial step beyond the window
                if H is not None:
                    for i, vk in enumerate(var_keys):
                        H[i] = np.zeros((total, self._dim(vk, state)))
                    for i in range(len(unique_points)):
                        H[len(var_keys) + i] = np.zeros((total, 3))
                return np.full(total, 1e6)
            lin = problem.linearize(state, obs)
            r = lin.residuals
            if huber is None:
                residual, wgt = r.reshape(-1), np.ones(len(r))
            else:  # rows times sqrt(w), the Jacobians too; the excess row's Jacobian zero
                residual, wgt = huber_view_residual(r, huber)
            if H is not None:
                blocks = {vk: np.zeros((rows, self._dim(vk, state))) for vk in var_keys}
                Jg = lin.J_g * wgt[:, None, None]
                for col in range(lin.index.shape[1]):
                    for g in np.unique(lin.index[:, col]):
                        if g < 0:
                            continue
                        kind, v, j = owners[int(g)]
                        sel = lin.index[:, col] == g
                        rsel = np.repeat(sel, 2)
                        blocks[(kind, v)][rsel, j] += Jg[sel, :, col].reshape(-1)
                _to_gtsam_tangents(blocks, state, m.image_camera)
                for i, vk in enumerate(var_keys):
                    H[i] = blocks[vk]
                Jp = lin.J_p * wgt[:, None, None]
                for i, j in enumerate(unique_points):
                    Hp = np.zeros((rows, 3))
                    sel = points == j
                    Hp[np.repeat(sel, 2)] = Jp[sel].reshape(-1, 3)
                    H[len(var_keys) + i] = Hp
                if huber is not None:
                    for i in range(len(H)):
                        H[i] = np.vstack([H[i], np.zeros((1, H[i].shape[1]))])
            return residual

        return gtsam.CustomFactor(noise, keys, error)

    def _dim(self, vk: tuple[str, int], state: State) -> int:
        kind, v = vk
        if kind in ("f", "s"):
            return 6
        if kind == "p":
            return 3
        if kind == "n":
            return 2
        if kind == "d":
            return 1
        return int(self.problem.model.param_map[v].any(axis=0).sum())

    def state_subset(self, values: gtsam.Values, template: State, var_keys: list[tuple[str, int]],
                     points: np.ndarray) -> State:
        """``template`` with the variables one factor touches read from ``values``.

        Args:
            values: The values GTSAM passes the factor.
            template: The state the other variables are read from.
            var_keys: The factor's non-point variables, as (kind, index) pairs (kinds of :data:`KEY_OF`).
            points: The indices of the factor's points.

        Returns:
            The state.
        """
        m = self.problem.model
        frames = list(template.rig_from_world)
        sensors = list(template.sensor_from_rig)
        params = list(template.colmap_params)
        normals, dists = template.normals.copy(), template.distances.copy()
        for kind, v in var_keys:
            if kind == "f":
                p = values.atPose3(K_.rig_frame(v))
                frames[v] = Pose(p.rotation().matrix(), np.asarray(p.translation(), float))
            elif kind == "s":
                p = values.atPose3(K_.sensor(v))
                pose = Pose(p.rotation().matrix(), np.asarray(p.translation(), float))
                for i in np.flatnonzero(m.image_camera == v):
                    sensors[i] = pose
            elif kind == "k":
                p = params[v].copy()
                p[np.flatnonzero(m.param_map[v].any(axis=0))] = values.atVector(K_.K(v))
                params[v] = p
            elif kind == "n":
                normals[v] = values.atUnit3(K_.window_normal(v)).point3()
            else:
                dists[v] = values.atVector(K_.window_distance(v))[0]
        xyz = template.xyz.copy()
        for j in points:
            xyz[j] = values.atPoint3(K_.point(int(j)))
        return replace(template, colmap_params=tuple(params), rig_from_world=tuple(frames),
                       sensor_from_rig=tuple(sensors), normals=normals, distances=dists, xyz=xyz)

    def term_factor(self, term: RowTerm, template: State) -> gtsam.CustomFactor:
        """One term (the numpy backend's rows) as a factor on the variables of its columns.

        Args:
            term: The term; its :meth:`~ari_sfm.solver.bundle.RowTerm.columns` name the factor's keys.
            template: The state the held variables are read from.

        Returns:
            The factor (unit noise: the rows are whitened).
        """
        owners, m = self.owners, self.problem.model
        allowed = [int(g) for g in term.columns()]
        var_keys: list[tuple[str, int]] = []
        for g in allowed:
            kind, v, _ = owners[g]
            if (kind, v) not in var_keys:
                var_keys.append((kind, v))
        keys = [KEY_OF[kind](v) for kind, v in var_keys]
        others = [vk for vk in var_keys if vk[0] != "p"]
        points = np.array([v for kind, v in var_keys if kind == "p"], int)
        allowed_set = set(allowed)
        n_rows = len(term.rows(template).e)

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
            state = self.state_subset(values, template, others, points)
            r = term.rows(state)
            if H is not None:
                blocks = {vk: np.zeros((n_rows, self._dim(vk, state))) for vk in var_keys}
                for k, g in enumerate(r.cols):
                    if int(g) in allowed_set:
                        kind, v, j = owners[int(g)]
                        blocks[(kind, v)][:, j] += r.J[:, k]
                _to_gtsam_tangents(blocks, state, m.image_camera)
                for i, vk in enumerate(var_keys):
                    H[i] = blocks[vk]
            return r.e

        return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(n_rows), keys, error)

    def graph(self, state: State) -> gtsam.NonlinearFactorGraph:
        g = gtsam.NonlinearFactorGraph()
        for i in range(len(self.problem.model.image_ids)):
            g.add(self._factor(i, state))
        for term in self.terms:
            if len(term.columns()):
                g.add(self.term_factor(term, state))
        return g

    def optimize(self, state: State, max_iterations: int = 100) -> tuple[State, int]:
        """GTSAM Levenberg-Marquardt from ``state`` (relative and absolute error tolerances 1e-12).

        Args:
            state: The start.
            max_iterations: Cap on GTSAM's iterations.

        Returns:
            The refined state and the number of iterations.
        """
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(1e-12)
        params.setAbsoluteErrorTol(1e-12)
        if self.diagonal_damping:
            params.setDiagonalDamping(True)
        opt = gtsam.LevenbergMarquardtOptimizer(self.graph(state), self.values(state), params)
        values = opt.optimize()
        return self.state(values, state), int(opt.iterations())

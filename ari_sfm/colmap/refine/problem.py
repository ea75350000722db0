"""The refractive structure-from-motion problem: variables, residuals and their Jacobians.

Variables (what is estimated):

- per COLMAP camera: its free COLMAP intrinsic parameters (all of the camera model's, in COLMAP
  order; FULL_OPENCV's k4..k6 held at 0);
- per rig frame: ``rig_from_world`` (6 dof), except the first frame, held fixed (the gauge:
  rotation and translation of the world);
- per non-reference rig sensor: ``sensor_from_rig`` (6 dof);
- the window: mount ``camera``: per camera its housing's ``normal_cam`` (2 dof) and distance h
  (1 dof); mount ``world``: one ``normal_world`` (2 dof) and the near face's offset ``plane_mm``
  (near face: ``normal_world . X = plane_mm``; 1 dof). The distance is held when air is behind the
  plate (medium_index 1: it is unobservable, PHYSICS.md);
- per COLMAP point3D: its position (3 dof), eliminated by the Schur complement.

Not estimated: the plate (thickness, indices: WINDOW.yaml). The scale is not a gauge here: the
plate's thickness (mm) fixes it through refraction, weakly (see ``refine.py``).

Perturbations (the tangent space): a pose ``(R, t)`` (X_a = R X_b + t) moves to
``(exp(w) R, t + v)``; a unit normal as gtsam.Unit3 (``geometry.unit3_basis`` / ``unit3_retract``, the
rig's chart too);
everything else additively. Image i's ``cam_from_world = sensor_from_rig * rig_from_world``.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ari_sfm.colmap.adapter import ColmapModel
from ari_sfm.factors.robust import huber_loss, huber_weight
from ari_sfm.geometry import Pose, rotation_from_rotvec, unit3_basis, unit3_retract
from ari_sfm.models import ExactModel, PinholeModel
from ari_sfm.models.exact import ConvergenceError
from ari_sfm.records import Interface
from ari_sfm.solver.bundle import Selection

from .chain_kernels import chain_observations

MOUNTS = ("camera", "world")


def huber_weights(residuals: np.ndarray, huber_px: float | None) -> np.ndarray:
    """IRLS weights of the Huber loss on each observation's pixel distance.

    :func:`ari_sfm.factors.robust.huber_weight` of the residuals' norms.

    Args:
        residuals: The residuals (M, 2), px.
        huber_px: The Huber threshold (px); None: no loss.

    Returns:
        The weights (M,); 1 without a loss.
    """
    return huber_weight(np.linalg.norm(residuals, axis=1), huber_px)


def huber_cost(residuals: np.ndarray, huber_px: float | None) -> float:
    """Sum over observations of rho(|r|) (:func:`ari_sfm.factors.robust.huber_loss`).

    Args:
        residuals: The residuals (M, 2), px.
        huber_px: The Huber threshold (px); None: plain least squares.

    Returns:
        The cost; inf if a residual is not finite.
    """
    s = np.linalg.norm(residuals, axis=1)
    if not np.all(np.isfinite(s)):
        return float("inf")
    return float(np.sum(huber_loss(s, huber_px)))


@dataclass(frozen=True)
class State:
    """Values of every variable (lengths in mm)."""

    colmap_params: tuple[np.ndarray, ...]  # per camera, COLMAP order
    rig_from_world: tuple[Pose, ...]  # per frame
    sensor_from_rig: tuple[Pose, ...]  # per image (constant per camera within its rig)
    normals: np.ndarray  # (W, 3) unit: per camera (mount camera) or (1, 3) world
    distances: np.ndarray  # (W,) h per camera (mount camera) or (1,) plane_mm (mount world)
    xyz: np.ndarray  # (P, 3)

    def cam_from_world(self, model: ColmapModel) -> tuple[np.ndarray, np.ndarray]:
        """(I, 3, 3) rotations and (I, 3) translations of every image's cam_from_world."""
        R = np.array([s.R @ self.rig_from_world[f].R for s, f in zip(self.sensor_from_rig, model.image_frame)])
        t = np.array([s.R @ self.rig_from_world[f].t + s.t for s, f in zip(self.sensor_from_rig, model.image_frame)])
        return R, t


@dataclass(frozen=True)
class Layout:
    """Where each variable lives in the reduced (non-point) tangent vector of size ``size``."""

    intrinsics: tuple[np.ndarray, ...]  # per camera: indices of its free COLMAP params
    frames: np.ndarray  # (F, 6) indices, -1 for the gauge frame
    sensors: np.ndarray  # (C, 6) indices, -1 for reference sensors
    window: np.ndarray  # (W, 3) indices [normal e1, e2, distance], -1 where held
    size: int


def make_layout(model: ColmapModel, mount: str, image_is_ref: np.ndarray, selection: Selection,
                windows: int = 1) -> Layout:
    """Index the reduced variables: intrinsics, frames, non-reference sensors, windows, as ``selection`` says.

    Args:
        model: The COLMAP model.
        mount: "camera" (a window per camera) or "world" (``windows`` windows in the world).
        image_is_ref: (I,) whether each image's sensor is its rig's reference (no pose variable).
        selection: What is estimated (the rest held).
        windows: The number of windows (mount world).

    Returns:
        The layout.
    """
    k = 0
    intr = []
    for c, _p in enumerate(model.colmap_params):
        free = np.flatnonzero(model.param_map[c].any(axis=0))
        intr.append(np.arange(k, k + len(free)) if selection.intrinsics else -np.ones(len(free), int))
        k += len(free) if selection.intrinsics else 0
    F = len(model.frame_ids)
    frames = -np.ones((F, 6), int)
    for f in np.flatnonzero(~selection.frames_held(F)):
        frames[f] = np.arange(k, k + 6)
        k += 6
    C = len(model.camera_ids)
    sensors = -np.ones((C, 6), int)
    for c in range(C):
        if not np.all(image_is_ref[model.image_camera == c]):
            sensors[c] = np.arange(k, k + 6)
            k += 6
    W = C if mount == "camera" else windows
    window = -np.ones((W, 3), int)
    for w in range(W if selection.window else 0):
        if selection.window_normal:
            window[w, :2] = (k, k + 1)
            k += 2
        if selection.window_distance:
            window[w, 2] = k
            k += 1
    return Layout(tuple(intr), frames, sensors, window, k)


def selection_of(estimate_distance: bool, hold_window: bool = False, hold_normal: bool = False,
                 held_frames: np.ndarray | None = None, hold_intrinsics: bool = False) -> Selection:
    """The selection the problem's keyword flags describe.

    Args:
        estimate_distance: Estimate the windows' distances.
        hold_window: Hold the windows.
        hold_normal: Hold the windows' normals.
        held_frames: The held frames' indices (default: the first).
        hold_intrinsics: Hold the intrinsics.

    Returns:
        The selection.
    """
    return Selection(intrinsics=not hold_intrinsics, window=not hold_window, window_normal=not hold_normal,
                     window_distance=bool(estimate_distance),
                     held_frames=None if held_frames is None else tuple(int(f) for f in held_frames))


@dataclass(frozen=True)
class Linearization:
    """Residuals and Jacobians of M observations.

    Attributes:
        residuals: (M, 2) px.
        J_g: (M, 2, q) the reduced variables' Jacobians, at columns ``index``.
        index: (M, q) the reduced column of each of ``J_g``'s; -1 = none.
        J_p: (M, 2, 3) the points' Jacobians.
    """

    residuals: np.ndarray
    J_g: np.ndarray
    index: np.ndarray
    J_p: np.ndarray


class RefractiveProblem:
    """Residuals ``project(X) - observed`` of every COLMAP observation through the exact model."""

    def __init__(self, model: ColmapModel, interface: Interface, mount: str, estimate_distance: bool,
                 hold_window: bool = False, hold_normal: bool = False, held_frames: np.ndarray | None = None,
                 hold_intrinsics: bool = False, camera_windows: Sequence[int] | None = None,
                 interfaces: Sequence[Interface] | None = None, selection: Selection | None = None) -> None:
        """Index the variables and check the mount.

        Args:
            model: The COLMAP model (cameras, images, points, observations).
            interface: The plate (thickness, indices).
            mount: "camera" (a window per camera, in its frame) or "world" (windows in the world).
            estimate_distance: Estimate the windows' distances (a flag of ``selection``).
            hold_window: Hold the windows (a flag of ``selection``).
            hold_normal: Hold the windows' normals (a flag of ``selection``).
            held_frames: The held frames (a field of ``selection``; default the first).
            hold_intrinsics: Hold the intrinsics (a flag of ``selection``).
            camera_windows: Mount world: each camera's window index into ``State.normals`` and
                ``distances`` (default: one window, 0, for every camera).
            interfaces: Each window's plate (default ``interface`` for all).
            selection: What is estimated; when given, the five flags above are ignored.

        Raises:
            ValueError: an unknown mount, or ``camera_windows`` with mount camera.
        """
        if mount not in MOUNTS:
            raise ValueError(f"mount must be one of {MOUNTS}, got {mount!r}")
        self.model = model
        self.interface = interface
        self.mount = mount
        C = len(model.camera_ids)
        self.camera_windows = np.zeros(C, int) if camera_windows is None else np.asarray(camera_windows, int)
        if mount == "camera" and camera_windows is not None:
            raise ValueError("camera_windows is for mount world (mount camera: one window per camera)")
        W = int(self.camera_windows.max()) + 1 if C else 1
        self.interfaces = tuple(interfaces) if interfaces is not None else (interface,) * W
        self.image_is_ref = (model.image_is_ref if model.image_is_ref is not None else
                             np.array([np.allclose(s.R, np.eye(3)) and not np.any(s.t) for s in model.sensor_from_rig]))
        if selection is None:
            selection = selection_of(estimate_distance, hold_window, hold_normal, held_frames, hold_intrinsics)
        self.selection = selection
        self.layout = make_layout(model, mount, self.image_is_ref, selection, W)
        self._cam_of_obs = model.image_camera[model.obs_image]
        self._all_columns: tuple[np.ndarray, np.ndarray] | None = None  # linearize's columns of every observation

    # ------------------------------------------------------------------ models
    def _exact(self, state: State, c: int, normal_cam: np.ndarray, h: float) -> ExactModel:
        pin = PinholeModel.from_params(self.model.params9(c, state.colmap_params[c]))
        plate = self.interface if self.mount == "camera" else self.interfaces[self.camera_windows[c]]
        return ExactModel.from_interface(pin, normal_cam, plate, distance_mm=h)

    def image_windows(self, state: State) -> tuple[np.ndarray, np.ndarray]:
        """(I, 3) normal_cam and (I,) distance h of every image's window in its camera frame."""
        m = self.model
        if self.mount == "camera":
            return state.normals[m.image_camera], state.distances[m.image_camera]
        R, t = state.cam_from_world(m)
        centres = -np.einsum("nji,nj->ni", R, t)
        if len(state.normals) == 1:
            n_w = state.normals[0]
            return R @ n_w, state.distances[0] - centres @ n_w
        w = self.camera_windows[m.image_camera]  # each image's camera's window
        n_w = state.normals[w]
        return np.einsum("nij,nj->ni", R, n_w), state.distances[w] - np.einsum("ni,ni->n", centres, n_w)

    def _groups(self, obs_image: np.ndarray) -> list[tuple[np.ndarray, int, int]]:
        """Groups of observations (positions in ``obs_image``) sharing one exact model:
        (positions, camera, image or -1)."""
        m = self.model
        if self.mount == "camera":
            cam = m.image_camera[obs_image]
            return [(np.flatnonzero(cam == c), c, -1) for c in range(len(m.camera_ids))]
        order = np.argsort(obs_image, kind="stable")
        starts = np.searchsorted(obs_image[order], np.arange(len(m.image_ids) + 1))
        return [(order[starts[i]:starts[i + 1]], int(m.image_camera[i]), i) for i in range(len(m.image_ids))]

    # -------------------------------------------------------------- residuals
    def residuals(self, state: State) -> np.ndarray:
        """(M, 2) projected minus observed pixels (NaN where a point is not beyond the window)."""
        m = self.model
        R, t = state.cam_from_world(m)
        X_cam = np.einsum("nij,nj->ni", R[m.obs_image], state.xyz[m.obs_point]) + t[m.obs_image]
        normals, dists = self.image_windows(state)
        if not np.all(dists > 0.0):  # a trial step put a camera beyond its window
            return np.full((len(X_cam), 2), np.nan)
        uv = np.empty((len(X_cam), 2))
        for obs, c, i in self._groups(m.obs_image):
            if len(obs) == 0:
                continue
            j = i if i >= 0 else m.obs_image[obs[0]]
            try:
                uv[obs] = self._exact(state, c, normals[j], float(dists[j])).project(X_cam[obs])
            except (ConvergenceError, ValueError):  # an unphysical trial step: rejected by its cost
                return np.full((len(X_cam), 2), np.nan)
        return uv - m.obs_uv

    def linearize(self, state: State, obs: np.ndarray | None = None) -> Linearization:
        """Residuals and analytic Jacobians of the observations (see module docstring).

        Args:
            state: The linearisation point.
            obs: The indices of the observations (default: every one).

        Returns:
            The linearization: the reduced columns in the order [frame, sensor, intrinsics, window], those no
            observation uses dropped; the poses' columns of the left perturbation (exp(w) R, t + v).
        """
        m, lay = self.model, self.layout
        sub = slice(None) if obs is None else obs
        oi, op, cam_of_obs = m.obs_image[sub], m.obs_point[sub], self._cam_of_obs[sub]
        R, t = state.cam_from_world(m)
        Ro, to = R[oi], t[oi]
        a = np.einsum("nij,nj->ni", Ro, state.xyz[op])  # R X
        X_cam = a + to
        normals, dists = self.image_windows(state)
        M = len(X_cam)
        uv = np.empty((M, 2))
        J_X = np.empty((M, 2, 3))
        J_n = np.empty((M, 2, 3))
        J_h = np.empty((M, 2))
        kmax = max(len(ix) for ix in lay.intrinsics)
        frame0, sensor0, intr0, window0 = 0, 6, 12, 12 + kmax
        J_all = np.zeros((M, 2, window0 + 3))  # [frame 6, sensor 6, intrinsics kmax, window 3]
        for grp, c, i in self._groups(oi):
            if len(grp) == 0:
                continue
            j = i if i >= 0 else oi[grp[0]]
            jac = self._exact(state, c, normals[j], float(dists[j])).project_with_jacobians(X_cam[grp])
            uv[grp], J_X[grp], J_n[grp], J_h[grp] = jac.uv, jac.J_point, jac.J_normal, jac.J_distance
            free = np.flatnonzero(m.param_map[c].any(axis=0))
            J_all[grp, :, intr0:intr0 + len(free)] = jac.J_params @ m.param_map[c][:, free]
        # the chain to the tangent spaces (chain_kernels' docstring)
        world = self.mount == "world"
        S_img = np.array([s.R for s in state.sensor_from_rig])
        StP_img = np.array([s.R @ state.rig_from_world[f].t for s, f in zip(state.sensor_from_rig, m.image_frame)])
        if world:
            n_cam = normals[oi]
            bases = np.array([unit3_basis(n) for n in state.normals])
            B = bases[self.camera_windows[cam_of_obs]]
            centres = -np.einsum("nji,nj->ni", Ro, to)
        else:
            n_cam = centres = np.zeros((1, 3))
            B = np.array([unit3_basis(n) for n in state.normals])[cam_of_obs]
        J_p = np.empty((M, 2, 3))
        chain_observations(J_X, J_n, J_h, a, np.ascontiguousarray(Ro), np.ascontiguousarray(to), S_img[oi], StP_img[oi],
                           world, np.ascontiguousarray(n_cam), np.ascontiguousarray(B), np.ascontiguousarray(centres),
                           J_all, frame0, sensor0, window0, J_p)
        index, used = self._columns(obs)
        return Linearization(uv - m.obs_uv[sub], J_all[:, :, used], index, J_p)

    def _columns(self, obs: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The reduced columns (M, q) of the observations ``obs`` (all: cached) in linearize's layout
        [frame, sensor, intrinsics, window], and which of those columns any observation uses."""
        if obs is None and self._all_columns is not None:
            return self._all_columns
        m, lay = self.model, self.layout
        sub = slice(None) if obs is None else obs
        cam_of_obs = self._cam_of_obs[sub]
        kmax = max(len(ix) for ix in lay.intrinsics)
        index = np.concatenate([lay.frames[m.image_frame[m.obs_image[sub]]], lay.sensors[cam_of_obs],
                                _pad([lay.intrinsics[c] for c in range(len(lay.intrinsics))], kmax)[cam_of_obs],
                                lay.window[cam_of_obs] if self.mount == "camera" else
                                lay.window[self.camera_windows[cam_of_obs]]], axis=1)
        used = np.asarray((index >= 0).any(axis=0))  # drop columns no observation uses (e.g. no rig sensors)
        out = (np.ascontiguousarray(index[:, used]), used)
        out[0].flags.writeable = False  # shared by every linearization
        if obs is None:
            self._all_columns = out
        return out

    # ---------------------------------------------------------------- retract
    def retract(self, state: State, dg: np.ndarray, dp: np.ndarray) -> State:
        """The state moved by a step: poses as ``(exp(w) R, t + v)``, normals by ``unit3_retract``, the rest additively.

        Args:
            state: The state.
            dg: The reduced step (layout.size,).
            dp: The point steps (P, 3).

        Returns:
            The moved state.
        """
        m, lay = self.model, self.layout
        g = np.append(dg, 0.0)  # index -1 reads 0

        def pose(p: Pose, idx: np.ndarray) -> Pose:
            d = g[idx]
            return Pose(rotation_from_rotvec(d[:3]) @ p.R, p.t + d[3:])

        params = tuple(p + _scatter_free(m.param_map[c], g[lay.intrinsics[c]])
                       for c, p in enumerate(state.colmap_params))
        frames = tuple(pose(p, lay.frames[f]) for f, p in enumerate(state.rig_from_world))
        sensors_by_cam = {c: pose(state.sensor_from_rig[int(np.flatnonzero(m.image_camera == c)[0])], lay.sensors[c])
                          for c in range(len(m.camera_ids)) if lay.sensors[c, 0] >= 0}
        sensors = tuple(sensors_by_cam.get(int(c), s) for c, s in zip(m.image_camera, state.sensor_from_rig))
        normals = state.normals.copy()
        distances = state.distances.copy()
        for w in range(len(normals)):
            normals[w] = unit3_retract(normals[w], g[lay.window[w, :2]])
            distances[w] += g[lay.window[w, 2]]
        return replace(state, colmap_params=params, rig_from_world=frames, sensor_from_rig=sensors,
                       normals=normals, distances=distances, xyz=state.xyz + dp)


def _pad(rows: list[np.ndarray], width: int) -> np.ndarray:
    out = -np.ones((len(rows), width), int)
    for k, r in enumerate(rows):
        out[k, :len(r)] = r
    return out


def _scatter_free(param_map: np.ndarray, step: np.ndarray) -> np.ndarray:
    """A step on the free COLMAP parameters as a full COLMAP parameter vector."""
    out = np.zeros(param_map.shape[1])
    out[np.flatnonzero(param_map.any(axis=0))] = step
    return out

"""The rig factor graph: N cameras behind one window (or several), each window's normal shared by its cameras.

Variables (:mod:`~ari_sfm.factors.keys`): each camera's intrinsics K(c), each
camera's pose C(c) = world_T_cam for c > 0 (camera 0 *is* the world: it has
no pose variable), each window's normal N(w) (a Unit3 in the world; N = N(0) for
one window), each target pose X(f), and under water each window's plane H(w). One
factor per (camera, image), on the camera's own window's N(w) and H(w), whitened by
the pixel sigma ``sigma_px`` (per coordinate): a prior in
physical units (radians, mm, px) then weighs what it says against the images.

Build it from a :class:`RigState` (e.g. the analytical initialisation), add
your own factors if you like (a prior on the normal from a level, a known
baseline, ...), optimise with Levenberg-Marquardt and read the state back::

    problem = RigGraph.from_dataset(dataset, model="ari")     # analytic initialisation, sigma_px estimated
    noise = gtsam.noiseModel.Isotropic.Sigma(2, np.radians(0.05))  # a level, 0.05 deg
    problem.graph.push_back(gtsam.PriorFactorUnit3(keys.N, gtsam.Unit3(n_level), noise))
    state = problem.optimize()                                # a RigState

The production path takes the same factors: ``calibrate(dataset, extra_factors=[...])``
(docs/RESEARCH.md).
"""
from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import cast

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import gtsam
import numpy as np

from ..errors import AriSfmError
from ..geometry import Pose, cam_from_world_from_pose3, pose3_from_cam_from_world, pose3_from_pose, pose_from_pose3
from ..models.registry import model_spec
from ..records import Interface, Observation, Target, Window, WindowPlane
from . import keys as K_
from .backend import solve_graph
from .variables import MODELS, RigState, estimated_offset
from .view_factor import ViewData, ViewKeys, factor_keys, view_factor, view_residuals

log = logging.getLogger(__name__)

def default_distance_mm(normal_world: np.ndarray, cam_from_world: dict[str, Pose],
                        cameras: Sequence[str] | None = None) -> float:
    """A starting plane offset of a window when the dataset gives none (from camera 0, the world's origin).

    In air the exact model does not depend on it (the plate shifts each ray sideways by an amount set by the
    angle and the thickness only), so any value that keeps every camera in front of the window will do: 10 mm
    in front of the camera nearest to it. Under water it is estimated from this start.

    Args:
        normal_world: the window's unit normal in the world.
        cam_from_world: each camera's pose.
        cameras: the cameras behind the window (default all).

    Returns:
        The plane offset ``normal . X`` (mm) of the window's near face in the world.
    """
    centres = [p.inverse().t for n, p in cam_from_world.items() if cameras is None or n in cameras]
    return float(max(normal_world @ c for c in centres)) + 10.0


def window_key(dataset, w: int) -> str:
    """How rig.yaml names window ``w``: ``interface``, or ``interfaces.<name>`` with several.

    Args:
        dataset (Dataset): the dataset.
        w: the window's index.

    Returns:
        The rig.yaml key, for error messages.
    """
    return "interface" if not dataset.windows else f"interfaces.{dataset.window_list()[w].name}"


def declared_plane(dataset, rig, window: int = 0) -> WindowPlane | None:
    """A window's declared plane (interface.plane), checked: its frame must be a calibration frame the
    initialisation placed.

    Args:
        dataset (Dataset): the dataset.
        rig (RigInit): the analytic initialisation (:func:`ari_sfm.init.rig.initialise_rig`).
        window: the window's index.

    Returns:
        The plane, or None when the window declares none.

    Raises:
        AriSfmError: the plane's frame is not a calibration frame seen by the cameras.
    """
    plane = dataset.window_list()[window].interface.plane
    if plane is None:
        return None
    calib = {o.frame for o in dataset.select("calibration")}
    if plane.frame not in calib or plane.frame not in rig.world_from_target:
        known = ", ".join(sorted(calib)[:5]) + (", ..." if len(calib) > 5 else "")
        raise AriSfmError(dataset.rig_path, f"{window_key(dataset, window)}.plane.frame: {plane.frame!r} is not a "
                                            f"calibration frame seen by the cameras (calibration frames: "
                                            f"{known or 'none'})")
    return plane


def declared_planes(dataset, rig) -> list[WindowPlane | None]:
    """Every window's declared plane (see :func:`declared_plane`).

    Args:
        dataset (Dataset): the dataset.
        rig (RigInit): the analytic initialisation.

    Returns:
        One plane per window, None where it has none.
    """
    return [declared_plane(dataset, rig, w) for w in range(len(dataset.window_list()))]


def held_intrinsics(dataset, fix: bool) -> tuple[list[str], dict[str, float]]:
    """The intrinsics held by ``fix_intrinsics``.

    Args:
        dataset (Dataset): the dataset, with its cameras' hints.
        fix: whether intrinsics are held at all (False: nothing held).

    Returns:
        The cameras whose K is held (a K hint), and camera -> focal held as fx = fy (a focal_px hint only).

    Raises:
        AriSfmError: ``fix`` without a K or focal_px hint for any camera.
    """
    if not fix:
        return [], {}
    cams = dataset.cameras
    fixed = [n for n in dataset.camera_names if cams[n].K is not None]
    focal = {n: float(cams[n].focal_px)
             for n in dataset.camera_names if cams[n].K is None and cams[n].focal_px is not None}
    if not fixed and not focal:
        raise AriSfmError(dataset.rig_path, "fix_intrinsics needs a K or focal_px hint for at least one camera "
                                            "(cameras.<name>.K or cameras.<name>.focal_px)")
    return fixed, focal


def initial_state(dataset, rig, model: str = "ari", fix_intrinsics: bool = False) -> RigState:
    """The one starting state of a bundle adjustment from an analytic initialisation.

    A declared plane (interface.plane) gives the normal and the distance, placed by its frame's initial
    pose, in air too (there the rays do not depend on the distance, but the plane says where the window
    is); else the rig.yaml distance, or (None) :func:`default_distance_mm` where the first graph needs
    one: under water (estimated) or for a Snell model.

    Args:
        dataset (Dataset): the dataset.
        rig (RigInit): the analytic initialisation (:func:`ari_sfm.init.rig.initialise_rig`).
        model: the first graph's model.
        fix_intrinsics: the held hints (:func:`held_intrinsics`) replace the initialisation's K (and
            distortion).

    Returns:
        The :class:`RigState`.
    """
    from .window_plane import plane_in_world

    state = RigState.from_initialisation(rig)
    for w, window in enumerate(dataset.window_list()):
        plane = declared_plane(dataset, rig, w)
        hint = window.interface.distance_mm  # from the window's first camera
        if plane is not None:
            n_w, h_w = plane_in_world(plane, state.world_from_target[plane.frame])
            state = state.with_window(w, n_w, h_w)
        elif hint is not None:
            first = state.cam_from_world[window.cameras[0]].inverse().t
            state = state.with_window(w, offset=float(hint + state.normal(w) @ first))
        elif dataset.medium_index != 1.0 or model_spec(model).needs_distance:
            state = state.with_window(w, offset=default_distance_mm(state.normal(w), state.cam_from_world,
                                                                    window.cameras))
    fixed, fixed_focal = held_intrinsics(dataset, fix_intrinsics)
    for n in fixed:  # start from the hint exactly
        hint = dataset.cameras[n]
        state.params[n][:4] = [hint.K[0, 0], hint.K[1, 1], hint.K[0, 2], hint.K[1, 2]]
        state.params[n][4:] = np.resize(hint.dist if hint.dist is not None else np.zeros(5), 5)
    for n, f in fixed_focal.items():
        state.params[n][:2] = f
    return state


@dataclass
class RigGraph:
    """A factor graph with its initial values and the bookkeeping to read them back.

    Its gtsam graph (:attr:`graph`: the view factors and every other factor, in the order added) is
    made on first access: the numpy backend packs the views' data (:attr:`factor_data`) and the other
    factors (:attr:`other_factors`) without it. Factors pushed onto :attr:`graph` join as before;
    :meth:`add_factor` adds one without making the graph.
    """

    made_values: gtsam.Values | None  # None: :attr:`values` made from base_state on first access
    camera_names: list[str]
    frame_names: list[str]
    n_params: int
    base_state: RigState
    estimate_distance: bool
    camera_windows: list[int] = field(default_factory=list)  # each camera's window index (N(w), H(w))
    window_names: list[str] = field(default_factory=list)  # the windows' names, by index
    factor_views: list[tuple[str, Observation]] = field(default_factory=list)
    factor_data: list[tuple[ViewData, ViewKeys]] = field(default_factory=list)
    model: str = "ari"
    iterations: int = 0
    sigma_px: float = 1.0  # the view factors' isotropic pixel sigma (per coordinate)
    huber_px: float | None = None  # the view factors' per-corner Huber threshold (px)
    other_factors: list[gtsam.NonlinearFactor] = field(default_factory=list)  # priors, the plane, the user's
    views_at: int = 0  # the view factors' place among other_factors (the ones before them: build's priors, plane)
    built_graph: gtsam.NonlinearFactorGraph | None = field(default=None, repr=False)  # once made: the graph
    unwritten: Callable[[gtsam.Values], None] | None = field(default=None, repr=False)  # a numpy solve's result

    @property
    def values(self) -> gtsam.Values:
        """The graph's values: made from :attr:`base_state` on first access (the numpy backend reads the
        state without them), a numpy solve's result written in then (:meth:`set_solution`)."""
        if self.made_values is None:
            self.made_values = self._values_of(self.base_state)
        if self.unwritten is not None:
            write, self.unwritten = self.unwritten, None
            write(self.made_values)
        return self.made_values

    @values.setter
    def values(self, values: gtsam.Values) -> None:
        self.made_values, self.unwritten = values, None

    def set_solution(self, write: Callable[[gtsam.Values], None]) -> None:
        """Take a solver's result: done now if the values exist, else when they are first read.

        Args:
            write: updates every variable of the values it is given.
        """
        if self.made_values is None:
            self.unwritten = write
        else:
            self.unwritten = None
            write(self.made_values)

    def values_copy(self) -> gtsam.Values | None:
        """A copy of the values for a copy of the graph (None while they are still to be made)."""
        return None if self.made_values is None and self.unwritten is None else gtsam.Values(self.values)

    @property
    def n_windows(self) -> int:
        return max(self.camera_windows, default=0) + 1

    def _values_of(self, state: RigState) -> gtsam.Values:
        """The gtsam.Values of a state: K(c), C(c) (c > 0), N(w), X(i) and H(w) (estimated distances)."""
        values = gtsam.Values()
        for c, name in enumerate(self.camera_names):
            values.insert(K_.K(c), np.asarray(state.params[name][:self.n_params], float))
            if c > 0:
                values.insert(K_.C(c), pose3_from_cam_from_world(state.cam_from_world[name]))
        for w in range(self.n_windows):
            values.insert(K_.window_normal(w), gtsam.Unit3(np.asarray(state.normal(w), float)))
        for i, f in enumerate(self.frame_names):
            values.insert(K_.X(i), pose3_from_pose(state.world_from_target[f]))
        if self.estimate_distance:
            for w in range(self.n_windows):
                values.insert(K_.window_plane(w), np.array([estimated_offset(state.offset(w))]))
        return values

    @property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        """The gtsam graph (made on first access; from then on it holds every factor)."""
        if self.built_graph is None:
            graph = gtsam.NonlinearFactorGraph()
            for f in self.other_factors[:self.views_at]:
                graph.push_back(f)
            for k in range(len(self.factor_data)):
                graph.push_back(self.view_factor_at(k))
            for f in self.other_factors[self.views_at:]:
                graph.push_back(f)
            self.built_graph = graph
        return self.built_graph

    def add_factor(self, factor: gtsam.NonlinearFactor) -> None:
        """Add a factor (a prior, the user's) after those already there."""
        if not isinstance(factor, gtsam.NonlinearFactor):  # gtsam's own TypeError lists every overload and the graph
            raise TypeError(f"add_factor takes a gtsam.NonlinearFactor (e.g. gtsam.PriorFactorPose3, "
                            f"gtsam.CustomFactor), got {type(factor).__name__}")
        if self.built_graph is None:
            self.other_factors.append(factor)
        else:
            self.built_graph.push_back(factor)

    def view_factor_at(self, k: int) -> gtsam.CustomFactor:
        """The k-th view's factor (factor_data order): the graph's once made, else a new one."""
        if self.built_graph is not None:
            return cast(gtsam.CustomFactor, self.built_graph.at(self.view_factor_indices()[k]))  # the graph's own
        data, vkeys = self.factor_data[k]
        return view_factor(MODELS[self.model], data, vkeys, self.sigma_px, self.huber_px)

    def packed_factors(self) -> tuple[list[tuple[ViewData, ViewKeys, float]], list[gtsam.NonlinearFactor]]:
        """What the numpy backend packs, read from the graph once made.

        Returns:
            (data, keys, isotropic pixel sigma) per view, and the other factors.

        Raises:
            ValueError: a view factor has a non-isotropic noise model.
        """
        if self.built_graph is None:
            return [(data, vkeys, self.sigma_px) for data, vkeys in self.factor_data], list(self.other_factors)
        index = self.view_factor_indices()  # priors and user factors may sit among them
        views = []
        for i, (data, vkeys) in zip(index, self.factor_data):
            sigmas = np.asarray(cast(gtsam.CustomFactor, self.built_graph.at(i)).noiseModel().sigmas())
            if np.ptp(sigmas) != 0.0:
                raise ValueError(f"view factor {i} has a non-isotropic noise model")
            views.append((data, vkeys, float(sigmas[0])))
        views_set = set(index)
        other = [self.built_graph.at(i) for i in range(self.built_graph.size()) if i not in views_set]
        return views, other

    @staticmethod
    def build(
        observations: Sequence[Observation],
        target: Target,
        interface: Interface,
        camera_names: Sequence[str],
        state: RigState,
        model: str = "ari",
        distortion: bool = False,
        estimate_distance: bool = False,
        huber_px: float | None = None,
        sigma_px: float = 1.0,
        min_corners: int = 4,
        fixed_intrinsics: Sequence[str] = (),
        fixed_focal_px: Mapping[str, float] | None = None,
        window_plane: WindowPlane | None = None,
        windows: Sequence[Window] | None = None,
        window_planes: Sequence[WindowPlane | None] | None = None,
        centred_principal_points: Mapping[str, tuple[float, float]] | None = None,
    ) -> RigGraph:
        """The graph of one factor per (camera, calibration or stacking image), whitened by ``sigma_px``.

        The variables start at ``state``. Camera 0 is the world frame (no pose variable): ``state.cam_from_world``
        of the first camera must be the identity.

        Args:
            observations: the corner observations; calibration and stacking records of the state's frames and
                cameras are used.
            target: the calibration target.
            interface: the window of every camera when ``windows`` is not given.
            camera_names: the cameras, camera 0 first.
            state: the starting values.
            model: the projection model ("ari" or "exact").
            distortion: estimate k1 k2 p1 p2 k3 (9 intrinsics per camera, else 4).
            estimate_distance: the windows' planes H(w) are variables (under water).
            huber_px: the per-corner Huber threshold (px); None: no Huber loss.
            sigma_px: the isotropic pixel sigma of the view factors (per coordinate).
            min_corners: images with fewer corners get no factor.
            fixed_intrinsics: cameras whose intrinsics are held at the state's.
            fixed_focal_px: camera -> focal held as fx = fy (principal point and distortion free).
            window_plane: the declared window (:mod:`ari_sfm.factors.window_plane`), its frame one of the state's.
            windows: several windows (each camera's factors on its own window's N(w), H(w) and plate); default
                one window, ``interface``, for every camera.
            window_planes: the windows' declared planes (None where not declared); replaces ``window_plane``.
            centred_principal_points: camera -> (cx, cy) held there (the image centre of a camera whose views
                cannot separate it from its rotation).

        Returns:
            The :class:`RigGraph`.

        Raises:
            ValueError: ``sigma_px`` not positive, a camera behind no window, a state with another number of
                windows, or camera 0's pose not the identity.
        """
        if not (np.isfinite(sigma_px) and sigma_px > 0.0):
            raise ValueError(f"sigma_px must be a positive pixel sigma, got {sigma_px}")
        names = list(camera_names)
        if windows is None:
            windows = (Window("window", interface, tuple(names)),)
        window_of = {c: w for w, win in enumerate(windows) for c in win.cameras}
        missing = [n for n in names if n not in window_of]
        if missing:
            raise ValueError(f"camera {missing[0]} is behind none of the windows")
        camera_windows = [window_of[n] for n in names]
        if state.window_count != len(windows):
            raise ValueError(f"the state has {state.window_count} window(s), the rig {len(windows)}")
        planes = list(window_planes) if window_planes is not None else [window_plane] + [None] * (len(windows) - 1)
        world = state.cam_from_world[names[0]]
        if not (np.abs(world.R - np.eye(3)).max() <= 1e-9 and np.abs(world.t).max() <= 1e-9):  # (NaN: not)
            raise ValueError(f"camera 0 ({names[0]}) is the world frame (it has no pose variable): its "
                             "cam_from_world must be the identity; express the state in its frame")
        frames = sorted(state.world_from_target)
        frame_index = {f: i for i, f in enumerate(frames)}
        n_params = 9 if distortion else 4
        other: list[gtsam.NonlinearFactor] = []
        for name in fixed_intrinsics:  # known K: a prior far tighter than anything the images say
            c = names.index(name)
            other.append(gtsam.PriorFactorVector(K_.K(c), np.asarray(state.params[name][:n_params], float),
                                                 gtsam.noiseModel.Isotropic.Sigma(n_params, 1e-4)))
        for name, focal in (fixed_focal_px or {}).items():  # fx = fy = focal, the rest free
            c = names.index(name)
            prior = np.asarray(state.params[name][:n_params], float).copy()
            prior[:2] = focal
            sigmas = np.full(n_params, 1e6)
            sigmas[:2] = 1e-4
            other.append(gtsam.PriorFactorVector(K_.K(c), prior, gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
        for name, centre in (centred_principal_points or {}).items():  # cx, cy held, the rest free
            if name in fixed_intrinsics:
                continue
            c = names.index(name)
            prior = np.asarray(state.params[name][:n_params], float).copy()
            prior[2:4] = centre
            sigmas = np.full(n_params, 1e6)
            sigmas[2:4] = 1e-4
            other.append(gtsam.PriorFactorVector(K_.K(c), prior, gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
        for w, plane in enumerate(planes):
            if plane is not None:
                from .window_plane import window_plane_factor

                other.append(window_plane_factor(plane, frame_index[plane.frame], estimate_distance, w))
        from ..init.zhang import object_points
        rg = RigGraph(None, names, frames, n_params, state, estimate_distance, camera_windows,
                      [win.name for win in windows], model=model,
                      sigma_px=float(sigma_px), huber_px=huber_px, other_factors=other, views_at=len(other))
        for obs in observations:
            if obs.set not in ("calibration", "stacking") or obs.frame not in frame_index or obs.camera not in names:
                continue
            if len(obs.ids) < min_corners:
                continue
            c = names.index(obs.camera)
            w = camera_windows[c]
            iface = windows[w].interface
            thickness = iface.thickness_mm + ((obs.added_mm or 0.0) if obs.set == "stacking" else 0.0)
            data = ViewData(
                object_points(target, obs.ids), np.asarray(obs.pixels, float), thickness,
                iface.index, iface.medium_index, np.asarray(state.params[obs.camera], float), n_params,
            )
            vkeys = ViewKeys(
                K_.K(c), K_.X(frame_index[obs.frame]), K_.window_normal(w), K_.C(c) if c > 0 else None,
                K_.window_plane(w) if estimate_distance else None, state.offset(w),
            )
            rg.factor_views.append((obs.camera, obs))
            rg.factor_data.append((data, vkeys))
        return rg

    @staticmethod
    def from_dataset(dataset, model: str = "ari", distortion: bool = False, huber_px: float | None = 1.0,
                     sigma_px: float | None = None, workers: int | None = None) -> RigGraph:
        """The graph of a dataset, initialised by the analytic pipeline.

        The initialisation: expansion centre, Zhang, Eq. 5, Eqs. 11-12, spanning tree over shared frames. A dataset
        with images only has its corners detected first (:func:`ari_sfm.detection.ensure_observations`). The
        values stay at the initialisation. With interface.plane, its factor is added (start: the plane at its
        frame's initial pose). Without stacking or plane the normal starts at camera 0's axis (exact only; ari
        refuses).

        Args:
            dataset (Dataset | str | os.PathLike): the dataset, or its folder.
            model: the projection model ("ari" or "exact").
            distortion: estimate k1 k2 p1 p2 k3.
            huber_px: the per-corner Huber threshold (px); None: no Huber loss.
            sigma_px: the pixel sigma of the view factors; None estimates it (the robust sigma of the residuals
                after a first numpy solve of this graph, :func:`estimate_sigma_px`) so that factors you add in
                physical units weigh what they say.
            workers: threads for the corner detection (None: one per CPU).

        Returns:
            The :class:`RigGraph`.

        Raises:
            TypeError: ``dataset`` is neither a Dataset nor a folder.
            ValueError: ``huber_px`` or ``sigma_px`` not a finite number > 0.
            AriSfmError: the data do not observe a window's normal and the model needs it.
        """
        from ..detection import ensure_observations
        from ..init.rig import NO_NORMAL_MESSAGE, initialise_rig
        from ..io import load_dataset
        from ..records import Dataset

        if isinstance(dataset, (str, os.PathLike)):
            dataset = load_dataset(Path(dataset))
        if not isinstance(dataset, Dataset):
            raise TypeError(f"dataset must be an ari_sfm Dataset or a dataset folder (got {type(dataset).__name__})")
        for name, value in (("huber_px", huber_px), ("sigma_px", sigma_px)):
            if value is not None and not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, or None (got {value!r})")
        dataset = ensure_observations(dataset, workers)
        rig = initialise_rig(dataset, distortion)
        planes = declared_planes(dataset, rig)
        unobserved = [w for w, p in enumerate(planes) if not rig.normals_observed[w] and p is None]
        if unobserved and not model_spec(model).needs_distance:
            raise AriSfmError(dataset.rig_path, NO_NORMAL_MESSAGE)
        underwater = dataset.medium_index != 1.0
        state = initial_state(dataset, rig, model)

        def build(sigma: float) -> RigGraph:
            return RigGraph.build(dataset.observations, dataset.target, dataset.interface, dataset.camera_names,
                                  state, model=model, distortion=distortion, estimate_distance=underwater,
                                  huber_px=huber_px, sigma_px=sigma, windows=dataset.window_list(),
                                  window_planes=planes)

        rg = build(1.0 if sigma_px is None else sigma_px)
        return rg if sigma_px is not None else build(estimate_sigma_px(rg))

    def with_sigma(self, sigma_px: float) -> RigGraph:
        """The same graph (values, added factors) with its view factors whitened by ``sigma_px`` instead."""
        if not (np.isfinite(sigma_px) and sigma_px > 0.0):
            raise ValueError(f"sigma_px must be a positive pixel sigma, got {sigma_px}")
        copy = replace(self, made_values=self.values_copy(), unwritten=None, sigma_px=float(sigma_px),
                       factor_views=list(self.factor_views), factor_data=list(self.factor_data),
                       other_factors=list(self.other_factors), built_graph=None)
        if self.built_graph is None:
            return copy
        views = set(self.view_factor_indices())
        graph = gtsam.NonlinearFactorGraph()
        k = 0
        for i in range(self.built_graph.size()):
            if i in views:
                graph.push_back(copy.view_factor_at(k))
                k += 1
            else:
                graph.push_back(self.built_graph.at(i))
        copy.built_graph = graph
        return copy

    def view_factor_indices(self) -> list[int]:
        """The graph indices of the view factors, in factor_data order (other factors may sit among them)."""
        if self.built_graph is None:
            return list(range(self.views_at, self.views_at + len(self.factor_data)))
        out, k = [], 0
        for i in range(self.built_graph.size()):
            if k < len(self.factor_data) and isinstance(self.built_graph.at(i), gtsam.CustomFactor):
                data, vkeys = self.factor_data[k]
                f = self.built_graph.at(i)
                rows = 2 * len(data.points_target) + (self.huber_px is not None)  # Huber: the excess row
                if list(f.keys()) == factor_keys(vkeys) and f.dim() == rows:
                    out.append(i)
                    k += 1
        if k != len(self.factor_data):
            raise ValueError(f"found {k} of the graph's {len(self.factor_data)} view factors")
        return out

    def optimize(self, max_iterations: int = 100, relative_tolerance: float = 1e-10) -> RigState:
        """Levenberg-Marquardt (GTSAM) from the current values; updates them.

        Args:
            max_iterations: cap on the iterations, >= 1.
            relative_tolerance: LM stops when the error's relative decrease is below it.

        Returns:
            The solved :class:`RigState`.

        Raises:
            ValueError: ``max_iterations`` is not an integer >= 1.
        """
        if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) or max_iterations < 1:
            raise ValueError(f"max_iterations must be an integer >= 1 (got {max_iterations!r})")
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(relative_tolerance)
        params.setAbsoluteErrorTol(1e-12)
        optimizer = gtsam.LevenbergMarquardtOptimizer(self.graph, self.values, params)
        self.values = optimizer.optimize()
        self.iterations = optimizer.iterations()
        return self.state()

    def state(self, values: gtsam.Values | None = None) -> RigState:
        """The RigState of the current (or given) values."""
        v = values if values is not None else self.values
        params, cams = {}, {}
        for c, name in enumerate(self.camera_names):
            p = np.asarray(self.base_state.params[name], float).copy()
            p[: self.n_params] = v.atVector(K_.K(c))
            params[name] = p
            cams[name] = cam_from_world_from_pose3(v.atPose3(K_.C(c))) if c > 0 else Pose.identity()
        frames = {f: pose_from_pose3(v.atPose3(K_.X(i))) for i, f in enumerate(self.frame_names)}
        offsets = [float(v.atVector(K_.window_plane(w))[0]) if self.estimate_distance else self.base_state.offset(w)
                   for w in range(self.n_windows)]
        more = tuple((v.atUnit3(K_.window_normal(w)).point3(), offsets[w]) for w in range(1, self.n_windows))
        return RigState(params, cams, v.atUnit3(K_.N).point3(), frames, offsets[0], more)

    def residuals(self) -> list[tuple[Observation, np.ndarray]]:
        """Unweighted pixel residuals (M, 2) of every factor's image at the current values."""
        factory = MODELS[self.model]
        out = []
        for (_camera, obs), (data, vkeys) in zip(self.factor_views, self.factor_data):
            r, _ = view_residuals(factory, data, vkeys, self.values, False, None)
            out.append((obs, r.reshape(-1, 2)))
        return out


def estimate_sigma_px(rg: RigGraph) -> float:
    """The pixel sigma of a graph's images.

    The robust sigma (1.4826 MAD per coordinate, :func:`ari_sfm.calibration.outliers.robust_sigma_px`) of the residuals
    after solving a copy of the graph with the numpy backend (GTSAM when the graph has factors the numpy
    backend cannot hold). ``rg`` itself is not changed.

    Args:
        rg: the graph.

    Returns:
        The pixel sigma (px, per coordinate).
    """
    from ..calibration.outliers import robust_sigma_px

    copy = replace(rg, made_values=rg.values_copy(), unwritten=None, factor_views=list(rg.factor_views),
                   factor_data=list(rg.factor_data), other_factors=list(rg.other_factors))
    solved = solve_graph(copy, "auto", huber_px=rg.huber_px, check=False).problem
    residuals = solved.residuals() if solved is not None else copy.residuals()
    return robust_sigma_px(r for _, r in residuals)

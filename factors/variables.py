"""The bottom layer of factors/: the variables' values and what the solver reads of a graph.

:class:`RigState` (every estimated quantity in plain numpy) and :class:`Variables`
(the packed problem's current values) are shared by the graph
(:mod:`~ari_sfm.factors.rig_graph`), the numpy backend
(:mod:`~ari_sfm.factors.packed_problem`, :mod:`~ari_sfm.factors.backend`) and its helpers
(:mod:`~ari_sfm.factors.extra_factors`, :mod:`~ari_sfm.factors.marginals`). The two protocols say
what those modules read of a RigGraph and of a packed problem, so that none of them imports
the module above it: rig_graph -> backend -> packed_problem -> extra_factors, marginals -> here.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import gtsam
import numpy as np

from ..geometry import Pose
from ..models.registry import bundle_factories
from ..records import Observation

MODELS = bundle_factories()  # the models the graph adjusts: name -> projection class (ari_sfm.models.registry)


def estimated_offset(offset: float | None) -> float:
    """A window's plane offset where it is estimated (and so set)."""
    if offset is None:
        raise ValueError("an estimated window's plane offset is not set")
    return float(offset)


@dataclass(frozen=True)
class RigState:
    """Every estimated quantity in plain numpy (world = camera 0).

    A window is its normal and its near face's plane ``normal . X = offset`` in the world (for the window
    of camera 0, the world's origin, the offset is camera 0's distance to it). ``normal_world`` and
    ``distance_mm`` are window 0's (the only one of a one-window rig); ``more_windows`` holds windows 1.. as
    (normal, offset) pairs: :meth:`normal`, :meth:`offset` and :meth:`with_window` treat all alike."""

    params: dict[str, np.ndarray]  # camera -> (9,) [fx fy cx cy k1 k2 p1 p2 k3]
    cam_from_world: dict[str, Pose]
    normal_world: np.ndarray
    world_from_target: dict[str, Pose]  # calibration frames and stacking poses
    distance_mm: float | None = None  # window 0's plane offset: camera 0 centre to near surface (None: not modelled)
    more_windows: tuple[tuple[np.ndarray, float | None], ...] = ()  # windows 1..: (normal_world, plane offset)

    @property
    def window_count(self) -> int:
        return 1 + len(self.more_windows)

    def normal(self, window: int) -> np.ndarray:
        """Window ``window``'s unit normal in the world."""
        return self.normal_world if window == 0 else self.more_windows[window - 1][0]

    def offset(self, window: int) -> float | None:
        """Window ``window``'s near face offset ``normal . X`` in the world (None: not modelled)."""
        return self.distance_mm if window == 0 else self.more_windows[window - 1][1]

    def with_window(self, window: int, normal: np.ndarray | None = None, offset: float | None | str = "keep"
                    ) -> RigState:
        """The state with window ``window``'s normal and/or offset replaced.

        Args:
            window: the window's index.
            normal: the new unit normal in the world; None: unchanged.
            offset: the new plane offset ``normal . X`` (mm; None: not modelled); ``"keep"``: unchanged.

        Returns:
            A new :class:`RigState`.
        """
        from dataclasses import replace

        n = self.normal(window) if normal is None else np.asarray(normal, float)
        h = self.offset(window) if isinstance(offset, str) else offset
        if window == 0:
            return replace(self, normal_world=n, distance_mm=h)
        more = list(self.more_windows)
        more[window - 1] = (n, h)
        return replace(self, more_windows=tuple(more))

    def camera_distance_mm(self, window: int, camera: str) -> float | None:
        """A camera's distance to window ``window``'s near face (offset minus normal . centre).

        Args:
            window: the window's index.
            camera: the camera's name.

        Returns:
            The distance (mm), or None when the window's offset is not modelled.
        """
        h = self.offset(window)
        if h is None:
            return None
        return float(h - self.normal(window) @ self.cam_from_world[camera].inverse().t)

    @classmethod
    def from_initialisation(cls, rig, distance_mm: float | None = None,
                            more_offsets: Sequence[float | None] = ()) -> RigState:
        """The state of an analytic initialisation.

        Params are [fx fy cx cy] plus the distortion padded to 5 per camera; poses and normals are the
        initialisation's.

        Args:
            rig (RigInit): the initialisation (:class:`ari_sfm.init.rig.RigInit`).
            distance_mm: window 0's plane offset (see :func:`ari_sfm.factors.rig_graph.default_distance_mm`);
                None: not modelled.
            more_offsets: the other windows' plane offsets, in order (missing ones None).

        Returns:
            The :class:`RigState`.
        """
        params = {n: np.concatenate([[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]], np.resize(c.dist, 5)])
                  for n, c in rig.cameras.items()}
        normals = rig.window_normals
        offsets = list(more_offsets) + [None] * (len(normals) - 1 - len(more_offsets))
        more = tuple((np.asarray(n, float), h) for n, h in zip(normals[1:], offsets))
        return cls(params, rig.cam_from_world, rig.normal_world, rig.world_from_target, distance_mm, more)


@dataclass
class Variables:
    """The current values of every variable, in numpy (plus the Unit3 normals)."""

    intrinsics: np.ndarray  # (C, n_params)
    world_R_cam: np.ndarray  # (C, 3, 3); camera 0 is the identity (not a variable)
    world_t_cam: np.ndarray  # (C, 3)
    normals: tuple[gtsam.Unit3, ...]  # each window's normal in the world
    world_R_target: np.ndarray  # (F, 3, 3)
    world_t_target: np.ndarray  # (F, 3)
    distances: tuple[float | None, ...]  # each window's plane offset: a variable when estimated, else fixed (or None)

    @property
    def normal(self) -> gtsam.Unit3:
        """Window 0's normal (the only one of a one-window rig)."""
        return self.normals[0]

    @property
    def distance_mm(self) -> float | None:
        """Window 0's plane offset."""
        return self.distances[0]

    def offsets(self) -> tuple[float, ...]:
        """Every window's plane offset, when they are set (variables: estimate_distance)."""
        out = tuple(d for d in self.distances if d is not None)
        if len(out) != len(self.distances):
            raise ValueError("a window's plane offset is not set")
        return out

    def with_distance(self, window: int, offset: float, world_t_target: np.ndarray | None = None) -> Variables:
        """A copy with one window's offset replaced (and, if given, every frame's translation).

        Args:
            window: the window's index.
            offset: its new plane offset (mm).
            world_t_target: every frame's new translation (F, 3); None: unchanged.

        Returns:
            The new :class:`Variables`.
        """
        from dataclasses import replace

        distances = list(self.distances)
        distances[window] = offset
        return replace(self, distances=tuple(distances),
                       world_t_target=self.world_t_target if world_t_target is None else world_t_target)


class GraphLike(Protocol):
    """What the numpy backend reads of a :class:`~ari_sfm.factors.rig_graph.RigGraph`."""

    values: gtsam.Values
    camera_names: list[str]
    frame_names: list[str]
    n_params: int
    model: str
    estimate_distance: bool
    camera_windows: list[int]  # each camera's window index
    base_state: RigState
    factor_views: list[tuple[str, Observation]]
    factor_data: list[tuple[Any, Any]]
    iterations: int

    def packed_factors(self) -> tuple[list[tuple[Any, Any, float]], list[gtsam.NonlinearFactor]]: ...

    def view_factor_at(self, k: int) -> gtsam.CustomFactor: ...

    def optimize(self, max_iterations: int = 100, relative_tolerance: float = 1e-10) -> RigState: ...


class PackedColumns(Protocol):
    """The column layout of a packed problem's global variables (what extra factors and marginals index)."""

    @property
    def camera_names(self) -> Sequence[str]: ...
    @property
    def frame_names(self) -> Sequence[str]: ...
    @property
    def n_params(self) -> int: ...
    @property
    def camera_block(self) -> int:  # columns per camera: n_params, then its pose (6; camera 0's unused)
        ...
    @property
    def normal_cols(self) -> Sequence[int]:  # per window: its normal's first column (2 columns)
        ...
    @property
    def distance_cols(self) -> Sequence[int] | None:  # per window: its offset's column; None unless estimate_distance
        ...
    @property
    def estimate_distance(self) -> bool: ...
    @property
    def fixed_cols(self) -> np.ndarray: ...

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

from dataclasses import dataclass
from typing import Any, Protocol, Sequence

import gtsam
import numpy as np

from ..geometry import Pose
from ..models.registry import bundle_factories
from ..records import Observation

MODELS = bundle_factories()  # the models the graph adjusts: name -> projection class (ari_sfm.models.registry)


@dataclass(frozen=True)
class RigState:
    """Every estimated quantity in plain numpy (world = camera 0)."""

    params: dict[str, np.ndarray]  # camera -> (9,) [fx fy cx cy k1 k2 p1 p2 k3]
    cam_from_world: dict[str, Pose]
    normal_world: np.ndarray
    world_from_target: dict[str, Pose]  # calibration frames and stacking poses
    distance_mm: float | None = None  # camera 0 centre to near surface (None: not modelled)

    @classmethod
    def from_initialisation(cls, rig, distance_mm: float | None = None) -> "RigState":
        """The state of an analytic initialisation (:class:`ari_sfm.init.rig.RigInit`):
        params [fx fy cx cy] + the distortion padded to 5 per camera, its poses and
        normal, and ``distance_mm`` (see :func:`ari_sfm.factors.rig_graph.default_distance_mm`)."""
        params = {n: np.concatenate([[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]], np.resize(c.dist, 5)])
                  for n, c in rig.cameras.items()}
        return cls(params, rig.cam_from_world, rig.normal_world, rig.world_from_target, distance_mm)


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


class GraphLike(Protocol):
    """What the numpy backend reads of a :class:`~ari_sfm.factors.rig_graph.RigGraph`."""

    values: gtsam.Values
    camera_names: list[str]
    frame_names: list[str]
    n_params: int
    model: str
    estimate_distance: bool
    base_state: RigState
    factor_views: list[tuple[str, Observation]]
    factor_data: list[tuple[Any, Any]]
    iterations: int

    def packed_factors(self) -> tuple[list[tuple[Any, Any, float]], list[gtsam.NonlinearFactor]]: ...

    def view_factor_at(self, k: int) -> gtsam.NonlinearFactor: ...

    def optimize(self, max_iterations: int = 100, relative_tolerance: float = 1e-10) -> RigState: ...


class PackedColumns(Protocol):
    """The column layout of a packed problem's global variables (what extra factors and marginals index)."""

    camera_names: Sequence[str]
    frame_names: Sequence[str]
    n_params: int
    camera_block: int  # columns per camera: n_params, then its pose (6; camera 0's unused)
    normal_col: int
    distance_col: int | None  # None unless estimate_distance
    estimate_distance: bool
    fixed_cols: np.ndarray

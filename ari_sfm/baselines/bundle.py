"""What the least-squares baselines (rt, pinhole) share.

- Zhang per camera (``cv2.calibrateCamera`` on the calibration views, the
  window ignored) and the cameras joined through shared frames into camera
  0's world (chordal mean of the relative poses over a breadth-first tree);
- the points of a dataset packed into flat arrays (camera, frame, target
  point, pixel per corner);
- a numeric Jacobian by forward differences whose columns are grouped by the
  sparsity of a bundle adjustment (columns that touch disjoint corners are
  perturbed together), for ``scipy.optimize.least_squares(method="lm")``;
- :class:`RigBundle`, the parameter vector of a rig around its start and its solve.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import AriSfmError
from ..geometry import Pose
from ..init.rig import join_rig
from ..init.zhang import ZhangResult, calibrate_views, object_points
from ..records import Dataset, Observation

if TYPE_CHECKING:
    from ..calibration.record import CameraCalibration

log = logging.getLogger(__name__)

MIN_VIEWS = 3
MIN_CORNERS = 6


def calibration_views(dataset: Dataset, camera: str) -> list[Observation]:
    """The camera's calibration records with enough corners for Zhang.

    Args:
        dataset: the dataset, with observations.
        camera: the camera's name.

    Returns:
        The records with at least MIN_CORNERS corners.
    """
    return [o for o in dataset.select("calibration", camera) if len(o.ids) >= MIN_CORNERS]


def zhang_cameras(dataset: Dataset, distortion: bool = False) -> dict[str, ZhangResult]:
    """``cv2.calibrateCamera`` per camera on its calibration views (the window ignored).

    Args:
        dataset: the dataset, with observations.
        distortion: estimate k1 k2 p1 p2 k3.

    Returns:
        Each camera's Zhang result, by name.

    Raises:
        AriSfmError: a camera has fewer than MIN_VIEWS calibration views with MIN_CORNERS corners.
    """
    out = {}
    for name in dataset.camera_names:
        views = calibration_views(dataset, name)
        if len(views) < MIN_VIEWS:
            raise AriSfmError(dataset.rig_path, f"camera {name} has {len(views)} calibration views with "
                                                f">= {MIN_CORNERS} corners (need >= {MIN_VIEWS})")
        out[name] = calibrate_views(dataset.target, dataset.cameras[name], views, distortion)
    return out


def rotations(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation matrices (M, 3, 3) and translations (M, 3) of pose vectors (M, 6)."""
    v = np.asarray(vectors, float).reshape(-1, 6)
    if len(v) == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    return Rotation.from_rotvec(v[:, :3]).as_matrix(), v[:, 3:].copy()


@dataclass(frozen=True)
class Points:
    """The corners of a set of records as flat arrays (one row per corner)."""

    records: tuple[Observation, ...]
    camera: np.ndarray  # (N,) camera index
    frame: np.ndarray  # (N,) frame index (into ``frames``)
    xyz: np.ndarray  # (N, 3) target-frame points
    uv: np.ndarray  # (N, 2) observed pixels
    frames: tuple[str, ...]
    slices: tuple[slice, ...]  # rows of each record

    @staticmethod
    def build(dataset: Dataset, records: Sequence[Observation], names: Sequence[str], frames: Sequence[str]) -> Points:
        cam_index = {n: i for i, n in enumerate(names)}
        frame_index = {f: i for i, f in enumerate(frames)}
        records = tuple(o for o in records if o.camera in cam_index and o.frame in frame_index)
        cams, fr, xyz, uv, slices = [], [], [], [], []
        start = 0
        for o in records:
            m = len(o.ids)
            cams.append(np.full(m, cam_index[o.camera]))
            fr.append(np.full(m, frame_index[o.frame]))
            xyz.append(object_points(dataset.target, o.ids))
            uv.append(np.asarray(o.pixels, float))
            slices.append(slice(start, start + m))
            start += m
        def cat(a: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
            return np.concatenate(a) if a else np.zeros(shape)

        return Points(records, cat(cams, (0,)).astype(int), cat(fr, (0,)).astype(int), cat(xyz, (0, 3)),
                      cat(uv, (0, 2)), tuple(frames), tuple(slices))

    def __len__(self) -> int:
        return len(self.uv)


def sparsity(num_params: int, columns: Sequence[np.ndarray]) -> np.ndarray:
    """The Jacobian's sparsity pattern: which columns each corner's two rows depend on.

    Args:
        num_params: the number of parameters P.
        columns: groups of column indices, each (N,) or (N, n): corner k's rows depend on ``columns[j][k]``
            (-1: none).

    Returns:
        The boolean pattern (2N, P).
    """
    n = len(columns[0])
    pattern = np.zeros((2 * n, num_params), dtype=bool)
    rows = np.arange(n)
    for cols in columns:
        cols = np.asarray(cols).reshape(n, -1)
        for j in range(cols.shape[1]):
            ok = cols[:, j] >= 0
            pattern[2 * rows[ok], cols[ok, j]] = True
            pattern[2 * rows[ok] + 1, cols[ok, j]] = True
    return pattern


def column_groups(pattern: np.ndarray) -> list[np.ndarray]:
    """Greedy grouping of columns that touch disjoint rows (perturbed together in one evaluation)."""
    groups: list[list[int]] = []
    used: list[np.ndarray] = []
    for j in range(pattern.shape[1]):
        rows = pattern[:, j]
        for g, u in zip(groups, used):
            if not np.any(u & rows):
                g.append(j)
                u |= rows
                break
        else:
            groups.append([j])
            used.append(rows.copy())
    return [np.array(g) for g in groups]


def numeric_jacobian(fun: Callable[[np.ndarray], np.ndarray],
                     pattern: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A dense forward-difference Jacobian of ``fun`` using the column grouping of ``pattern``.

    Step per column: sqrt(machine eps) * max(1, |x_j|) (scipy's '2-point' rule).

    Args:
        fun: the residual function.
        pattern: its sparsity pattern (rows, parameters) (see :func:`sparsity`).

    Returns:
        The Jacobian function ``jac(x)``; its ``groups`` attribute is the number of column groups.
    """
    groups = column_groups(pattern)
    step_rel = np.sqrt(np.finfo(float).eps)

    def jac(x: np.ndarray) -> np.ndarray:
        f0 = fun(x)
        J = np.zeros((len(f0), len(x)))
        h = step_rel * np.maximum(1.0, np.abs(x))
        for g in groups:
            xp = x.copy()
            xp[g] += h[g]
            step = xp - x  # the step actually taken (rounding)
            df = fun(xp) - f0
            for j in g:
                rows = pattern[:, j]
                J[rows, j] = df[rows] / step[j]
        return J

    jac.groups = len(groups)  # type: ignore[attr-defined]
    return jac


@dataclass(frozen=True)
class RigBundle:
    """The parameter vector of a rig bundle adjustment around a start, and its solve.

    Layout of ``x`` (every pose an increment on its start: ``R = R0 exp(w)``, ``t = t0 + dt``)::

        [intrinsics (C x n_intr)] [camera poses 1..C-1 (6 each)] [globals (G)] [frame poses (F x 6)]

    Camera 0 is the world (fixed). The model (rt, pinhole) supplies the pixels
    of the camera-frame points from the intrinsics and the globals.
    """

    points: Points
    names: tuple[str, ...]
    n_intr: int
    n_glob: int
    cam_start: tuple[Pose, ...]  # cam_from_world
    frame_start: tuple[Pose, ...]  # world_from_target

    @property
    def size(self) -> int:
        return len(self.names) * self.n_intr + 6 * (len(self.names) - 1) + self.n_glob + 6 * len(self.frame_start)

    def split(self, x: np.ndarray) -> tuple[np.ndarray, list[Pose], np.ndarray, list[Pose]]:
        """intrinsics (C, n_intr), cam_from_world per camera, globals (G,), world_from_target per frame."""
        C, F = len(self.names), len(self.frame_start)
        i = C * self.n_intr
        intr = x[:i].reshape(C, self.n_intr)
        cam_inc = x[i:i + 6 * (C - 1)].reshape(-1, 6)
        i += 6 * (C - 1)
        glob = x[i:i + self.n_glob]
        frame_inc = x[i + self.n_glob:].reshape(F, 6)

        def moved(starts: Sequence[Pose], inc: np.ndarray) -> list[Pose]:
            R, _ = rotations(np.c_[inc[:, :3], np.zeros((len(inc), 3))])
            return [Pose(s.R @ R[k], s.t + inc[k, 3:]) for k, s in enumerate(starts)]

        cams = [self.cam_start[0]] + moved(self.cam_start[1:], cam_inc)
        return intr, cams, glob, moved(self.frame_start, frame_inc)

    def cam_points(self, cams: Sequence[Pose], frames: Sequence[Pose]) -> np.ndarray:
        """Camera-frame coordinates of every corner.

        Args:
            cams: cam_from_world per camera.
            frames: world_from_target per frame.

        Returns:
            The points (N, 3), one per corner.
        """
        p = self.points
        Rf = np.stack([f.R for f in frames])[p.frame]
        tf = np.stack([f.t for f in frames])[p.frame]
        Xw = np.einsum("nij,nj->ni", Rf, p.xyz) + tf
        Rc = np.stack([c.R for c in cams])[p.camera]
        tc = np.stack([c.t for c in cams])[p.camera]
        return np.einsum("nij,nj->ni", Rc, Xw) + tc

    def pattern(self) -> np.ndarray:
        """Which parameters move each corner's two residuals."""
        p, C = self.points, len(self.names)
        intr = p.camera[:, None] * self.n_intr + np.arange(self.n_intr)
        base = C * self.n_intr
        cam = np.where(p.camera[:, None] > 0, base + (p.camera[:, None] - 1) * 6 + np.arange(6), -1)
        base += 6 * (C - 1)
        glob = np.broadcast_to(base + np.arange(self.n_glob), (len(p), self.n_glob))
        frame = base + self.n_glob + p.frame[:, None] * 6 + np.arange(6)
        return sparsity(self.size, [intr, cam, glob, frame])

    def solve(self, x0: np.ndarray, residuals: Callable[[np.ndarray], np.ndarray], max_nfev: int | None = None):
        """Levenberg-Marquardt (MINPACK, scipy.optimize.least_squares) with the grouped numeric Jacobian.

        Non-finite residuals (a corner without a ray) are replaced by a large, flat 1e3.

        Args:
            x0: the start (:attr:`size`,).
            residuals: the residual function of x.
            max_nfev: cap on the function evaluations (None: scipy's default).

        Returns:
            scipy's ``OptimizeResult``.
        """
        from scipy.optimize import least_squares

        def finite(x: np.ndarray) -> np.ndarray:
            r = residuals(x)
            return np.where(np.isfinite(r), r, 1e3)  # a corner without a ray: a large, flat residual

        jac = numeric_jacobian(finite, self.pattern())
        return least_squares(finite, x0, jac=jac, method="lm", x_scale="jac", max_nfev=max_nfev)


def start_bundle(dataset: Dataset, distortion: bool, n_glob: int) -> tuple[RigBundle, dict[str, ZhangResult]]:
    """Zhang per camera, the rig joined in camera 0's world, the calibration corners packed.

    Args:
        dataset: the dataset, with observations.
        distortion: estimate k1 k2 p1 p2 k3 (9 intrinsics per camera, else 4).
        n_glob: the number of global parameters of the model.

    Returns:
        The :class:`RigBundle` and each camera's Zhang result.

    Raises:
        AriSfmError: a camera has too few calibration views, or the cameras share no frames.
    """
    names = tuple(dataset.camera_names)
    zhang = zhang_cameras(dataset, distortion)
    cam_from_world, world_from_target = join_rig(names, {n: z.cam_from_target for n, z in zhang.items()},
                                                 dataset.rig_path)
    frames = tuple(sorted(world_from_target))
    points = Points.build(dataset, dataset.select("calibration"), names, frames)
    bundle = RigBundle(points, names, 9 if distortion else 4, n_glob, tuple(cam_from_world[n] for n in names),
                       tuple(world_from_target[f] for f in frames))
    return bundle, zhang


def intrinsics_vector(z: ZhangResult, distortion: bool) -> np.ndarray:
    """The intrinsics of a Zhang result as a parameter vector.

    Args:
        z: the Zhang result.
        distortion: append the distortion.

    Returns:
        [fx fy cx cy], with ``distortion`` followed by k1 k2 p1 p2 k3.
    """
    K = z.K
    base = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    return np.array(base + (list(np.resize(z.dist, 5)) if distortion else []), float)


def project_directions(intr: np.ndarray, camera: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Pixels of camera-frame directions or points, each through its camera's intrinsics.

    Args:
        intr: the intrinsics (C, 4) or (C, 9).
        camera: each row's camera index (N,).
        D: the directions or points (N, 3).

    Returns:
        The pixels (N, 2).
    """
    from ..models import PinholeModel

    uv = np.full((len(D), 2), np.nan)
    for c in np.unique(camera):
        rows = camera == c
        p = np.resize(intr[c], 9) if intr.shape[1] == 9 else np.r_[intr[c], np.zeros(5)]
        uv[rows] = PinholeModel.from_params(p).project(D[rows])
    return uv


def camera_calibrations(dataset: Dataset, bundle: RigBundle, intr: np.ndarray, cams: Sequence[Pose],
                        per_camera_residuals: dict[str, np.ndarray]) -> dict[str, CameraCalibration]:
    """The CameraCalibration of every camera from a solved bundle.

    Args:
        dataset: the dataset.
        bundle: the bundle.
        intr: the solved intrinsics (C, n_intr).
        cams: the solved cam_from_world per camera.
        per_camera_residuals: each camera's pixel residuals (M, 2), for its RMSE.

    Returns:
        The calibrations by camera name.
    """
    from ..calibration import CameraCalibration
    from ..calibration.evaluate import residual_stats

    out = {}
    for c, name in enumerate(bundle.names):
        p = intr[c]
        K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
        dist = np.resize(p[4:], 5) if len(p) == 9 else np.zeros(5)
        out[name] = CameraCalibration(name, dataset.cameras[name].image_size, K, dist, cams[c],
                                      rmse_px=residual_stats([per_camera_residuals[name]]).rmse_px)
    return out

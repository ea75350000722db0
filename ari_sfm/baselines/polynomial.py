"""The PF baseline: Paolillo et al.'s 3x3x3 polynomial from world points to pixels (paper Eq. 14).

Per camera, u and v are each a polynomial with every monomial x^i y^j z^k of
total degree i + j + k <= 3 (20 terms each, 40 parameters per camera), in
*normalised* world coordinates ``(X - mean) / scale`` (per axis), fitted to
the observed pixels by linear least squares. The coefficients have no
physical meaning and no ray: PF can project, not back-project, and it knows
nothing of added glass (stacking records).

World coordinates: the paper's PF needs the world position of every corner.
Here they come from the frame poses (``world_from_target``) of an ari
calibration of the same data; the PF calibration keeps that calibration's
K, cam_from_world and normal only to name its world frame (and to start the
pose solve of held-out frames), and stores its polynomial per camera under
the camera's ``pf`` key of calibration.json::

    "pf": {"world": "ari", "exponents": [[i, j, k], ...],
           "mean": [mx, my, mz], "scale": [sx, sy, sz],
           "coef_u": [20 numbers], "coef_v": [20 numbers], "rank": 20}
"""
from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from ..errors import AriSfmError
from ..geometry import Pose
from ..init.zhang import object_points
from ..models.polynomial import DEGREE, EXPONENTS, NUM_TERMS, PolynomialMap, PolynomialModel, design_matrix  # noqa: F401 (re-exported: the pf projection lives in models/)
from ..records import Dataset, Observation
from ..results import PfWorld

if TYPE_CHECKING:
    from ..calibration.calibrate import CalibrationOptions
    from ..calibration.record import Calibration

log = logging.getLogger(__name__)


def fit_polynomial(X_world: np.ndarray, uv: np.ndarray) -> PolynomialMap:
    """Linear least squares of the 40 coefficients on world points and their pixels.

    A design matrix of rank below 20 (points that do not span the volume) logs a warning: the minimum-norm
    fit is not unique.

    Args:
        X_world: world points (N, 3), N >= 20.
        uv: their pixels (N, 2).

    Returns:
        The :class:`PolynomialMap`.

    Raises:
        ValueError: fewer than 20 points.
    """
    X = np.asarray(X_world, float).reshape(-1, 3)
    uv = np.asarray(uv, float).reshape(-1, 2)
    if len(X) < NUM_TERMS:
        raise ValueError(f"pf needs >= {NUM_TERMS} points per camera, got {len(X)}")
    mean = X.mean(axis=0)
    scale = X.std(axis=0)
    scale = np.where(scale > 1e-9 * max(1.0, float(np.abs(X).max())), scale, 1.0)  # a flat axis keeps scale 1
    A = design_matrix((X - mean) / scale)
    coef, _, rank, _ = np.linalg.lstsq(A, uv, rcond=None)
    if rank < NUM_TERMS:
        log.warning("pf: design matrix has rank %d < %d (points do not span the volume): "
                    "the minimum-norm fit is not unique", rank, NUM_TERMS)
    return PolynomialMap(mean, scale, coef[:, 0].copy(), coef[:, 1].copy(), int(rank))


def world_points(observations: Sequence[Observation], frames: dict[str, Pose],
                 dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """World points and pixels of the calibration records whose frame has a pose.

    Args:
        observations: the records.
        frames: world_from_target by frame name.
        dataset: the dataset (its target).

    Returns:
        The world points (N, 3) and their pixels (N, 2).
    """
    X, uv = [], []
    for o in observations:
        if o.set == "calibration" and o.frame in frames:
            X.append(frames[o.frame].apply(object_points(dataset.target, o.ids)))
            uv.append(o.pixels)
    if not X:
        return np.zeros((0, 3)), np.zeros((0, 2))
    return np.concatenate(X), np.concatenate(uv)


def calibrate_pf(dataset: Dataset, world: Calibration | None = None,
                 options: CalibrationOptions | None = None) -> Calibration:
    """PF per camera on the calibration records, in the world of an ari calibration.

    ``time_s`` is the polynomial fit alone, as in the paper's Table 2.

    Args:
        dataset: The dataset with its observations.
        world: The calibration whose frame poses give the world coordinates; None: ``calibrate(dataset,
            model="ari", options=options)`` first (its time is not pf's: reported under ``pf_world``).
        options: The options of that ari calibration (None: the defaults); unused when ``world`` is given.

    Returns:
        The pf calibration: each camera's polynomial (``CameraCalibration.pf``), the world's poses.

    Raises:
        AriSfmError: a camera has fewer calibration corners with a world position than the polynomial's terms.
    """
    from ..calibration.calibrate import calibrate
    from ..calibration.evaluate import residual_stats

    t_world = 0.0
    if world is None:
        t0 = time.perf_counter()
        world = calibrate(dataset, model="ari", options=options)
        t_world = time.perf_counter() - t0
    data = {name: world_points(dataset.select("calibration", name), world.frames, dataset)
            for name in dataset.camera_names}
    t0 = time.perf_counter()
    polys = {}
    for name, (X, uv) in data.items():
        if len(X) < NUM_TERMS:
            raise AriSfmError(dataset.rig_path, f"pf: camera {name} has {len(X)} calibration corners with a "
                                                f"world position, the polynomial needs >= {NUM_TERMS}")
        polys[name] = fit_polynomial(X, uv)
    elapsed = time.perf_counter() - t0
    cameras = {}
    for name, cam in world.cameras.items():
        X, uv = data[name]
        rmse = residual_stats([polys[name].project_world(X) - uv]).rmse_px
        cameras[name] = replace(cam, expansion_center_px=None, expansion_center_std_px=None, rmse_px=rmse, extra={},
                                pf=polys[name])
    calib_obs = dataset.select("calibration")
    residuals = [polys[o.camera].project_world(world.frames[o.frame].apply(object_points(dataset.target, o.ids)))
                 - o.pixels
                 for o in calib_obs if o.frame in world.frames]
    log.info("pf: %d cameras fitted in %.1f ms", len(polys), elapsed * 1e3)
    return replace(
        world, model="pf", cameras=cameras, stacking_poses={}, residuals=residual_stats(residuals), time_s=elapsed,
        # pf is not judged
        fixed_distance_mm=None, extra={}, optimizer=None, uncertainty=None, outliers=None, quality=None,
        pf_world=PfWorld(world.model, t_world or world.time_s),
    )

"""The "ignore the window" baselines: plain OpenCV pinhole cameras, with or without lens distortion.

Zhang per camera (cv2.calibrateCamera), the rig joined in camera 0's world,
then one pinhole bundle adjustment of every camera and board pose on the
calibration records (scipy Levenberg-Marquardt). ``pinhole``: K only;
``pinhole_dist``: K and k1 k2 p1 p2 k3, which absorb part of the window's
radial effect but not its dependence on depth. The calibration stores no
window normal (``normal_world`` null).
"""
from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from ..calibration.evaluate import residual_stats
from ..records import Dataset
from ..results import OptimizerReport, OptimizerRun
from .bundle import camera_calibrations, intrinsics_vector, project_directions, start_bundle

if TYPE_CHECKING:
    from ..calibration.record import Calibration

log = logging.getLogger(__name__)


def calibrate_pinhole(dataset: Dataset, distortion: bool = False, max_iterations: int = 100) -> Calibration:
    """A pinhole rig that ignores the window: model ``pinhole``, or ``pinhole_dist`` with distortion.

    Args:
        dataset: the dataset, with observations.
        distortion: estimate k1 k2 p1 p2 k3 (model ``pinhole_dist``).
        max_iterations: scipy's evaluations are capped at twice this.

    Returns:
        The :class:`~ari_sfm.calibration.record.Calibration` (no window normal).
    """
    from ..calibration import Calibration

    t0 = time.perf_counter()
    bundle, zhang = start_bundle(dataset, distortion, 0)
    pts = bundle.points

    def pixels(x: np.ndarray) -> np.ndarray:
        intr, cams, _, frames = bundle.split(x)
        return project_directions(intr, pts.camera, bundle.cam_points(cams, frames))

    x0 = np.concatenate([np.concatenate([intrinsics_vector(zhang[n], distortion) for n in bundle.names]),
                         np.zeros(6 * (len(bundle.names) - 1) + 6 * len(bundle.frame_start))])
    result = bundle.solve(x0, lambda x: (pixels(x) - pts.uv).ravel(), max_nfev=max_iterations * 2)
    elapsed = time.perf_counter() - t0
    intr, cams, _, frames = bundle.split(result.x)
    res = pixels(result.x) - pts.uv
    model = "pinhole_dist" if distortion else "pinhole"
    log.info("%s: %d function evaluations, %.1f ms, rmse %.4f px", model, result.nfev, elapsed * 1e3,
             residual_stats([res]).rmse_px)
    return Calibration(
        model=model,
        interface=dataset.interface,
        normal_world=None,
        cameras=camera_calibrations(dataset, bundle, intr, cams,
                                    {n: res[pts.camera == c] for c, n in enumerate(bundle.names)}),
        frames=dict(zip(pts.frames, frames)),
        residuals=residual_stats([res]),
        time_s=elapsed,
        optimizer=OptimizerReport({model: OptimizerRun(elapsed, "scipy.least_squares(lm), numeric Jacobian",
                                                       nfev=int(result.nfev), status=int(result.status))}),
        window_ignored=True,
        target=dataset.target,
    )

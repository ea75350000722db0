"""The quality gate of a calibration: is the optimum what the data allow?

A bundle adjustment that converged can still sit in a wrong minimum (a mirrored start, a
window placed behind the cameras): its residuals are then far above what the same corners
allow. After convergence a window-model calibration (ari, exact) is judged on:

- the fit against a free pinhole + distortion fit of the same corners (cv2.calibrateCamera per
  camera, k1 k2 p1 p2 k3 free): a refractive model that fits much worse than that has failed.
  Both sides are robust RMSEs (``sqrt(2) * 1.4826 * MAD`` of the residual coordinates), so a few
  outlier corners (reported apart, see :mod:`ari_sfm.outliers`) do not decide it; failed when
  ``robust_rmse_px > ratio * pinhole_dist_rmse_px + margin`` (:data:`PINHOLE_TOLERANCE` per model);
- physically absurd standard deviations: a camera's pose relative to camera 0 known to worse
  than ``MAX_POSE_SIGMA_DEG`` (a flat, wrong minimum: +-40 deg was seen);
- a non-finite RMSE.

The pinhole + distortion fit has more freedom than the window models (it also fits their
paraxial error, PHYSICS.md), which is why the test is a ratio with a margin, not equality.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping

import numpy as np

log = logging.getLogger(__name__)

# model -> (ratio, margin px): the model may fit up to ratio x worse than a free pinhole + distortion, plus the
# margin. exact is the physics (at its optimum it fits like the pinhole + distortion or better: 0.69-0.87 x on
# the bundled scenarios); ari keeps its paraxial error (up to 5 x, 1.6 px, on binocular_underwater).
PINHOLE_TOLERANCE = {"exact": (2.0, 0.25), "ari": (3.0, 1.0)}
MAX_POSE_SIGMA_DEG = 5.0  # a relative camera rotation less determined than this is not a calibration
MAD_TO_SIGMA = 1.4826
MAX_PINHOLE_VIEWS = 20  # views per camera in the pinhole + distortion fit (evenly picked: bounded cost)


@dataclass(frozen=True)
class Quality:
    """The gate's verdict (``calibration.json`` key ``quality``) and the figures it was judged on."""

    ok: bool
    why: str | None  # None when ok; else each failed test, '; '-joined
    rmse_px: float
    robust_rmse_px: float  # sqrt(2) * 1.4826 * MAD of the residual coordinates
    pinhole_dist_rmse_px: float | None  # robust RMSE of the free pinhole + distortion fit (None: not fitted)
    max_pose_sigma_deg: float | None  # largest relative camera rotation sigma (None: no uncertainty)
    starts: tuple[str, ...] = field(default_factory=tuple)  # the starts tried, the kept one last

    def to_json(self) -> dict[str, Any]:
        return {"ok": self.ok, "why": self.why, "rmse_px": self.rmse_px, "robust_rmse_px": self.robust_rmse_px,
                "pinhole_dist_rmse_px": self.pinhole_dist_rmse_px, "max_pose_sigma_deg": self.max_pose_sigma_deg,
                "starts": list(self.starts)}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Quality":
        def num(key: str) -> float | None:
            v = d.get(key)
            return None if v is None else float(v)

        if not isinstance(d.get("ok"), bool):
            raise ValueError("ok must be true or false")
        return cls(d["ok"], d.get("why"), float(d.get("rmse_px", math.nan)), float(d.get("robust_rmse_px", math.nan)),
                   num("pinhole_dist_rmse_px"), num("max_pose_sigma_deg"), tuple(str(s) for s in d.get("starts", ())))


def robust_rmse_px(residuals: Iterable[np.ndarray]) -> float:
    """sqrt(2) * 1.4826 * MAD of the residual coordinates: the RMSE the bulk of the corners has."""
    r = np.concatenate([np.asarray(x, float).reshape(-1) for x in residuals] or [np.zeros(0)])
    return float(math.sqrt(2.0) * MAD_TO_SIGMA * np.median(np.abs(r))) if r.size else math.nan


def pinhole_dist_rmse_px(dataset) -> float | None:
    """Robust RMSE of a free pinhole + distortion fit (cv2, per camera, from the hints) of the
    calibration and stacking corners; None when no camera could be fitted."""
    import cv2

    from .init.zhang import calibrate_views, object_points

    residuals = []
    for name in dataset.camera_names:
        views = [o for o in dataset.observations if o.camera == name and o.set in ("calibration", "stacking")
                 and len(o.ids) >= 6]
        # stacking records of one pose are separate views (the plate moved the pattern, not the target)
        views = [v if v.set == "calibration" else _renamed(v) for v in views]
        if len(views) > MAX_PINHOLE_VIEWS:
            views = [views[i] for i in np.linspace(0, len(views) - 1, MAX_PINHOLE_VIEWS).round().astype(int)]
        try:
            z = calibrate_views(dataset.target, dataset.cameras[name], views, distortion=True)
        except (ValueError, cv2.error) as exc:
            log.info("quality: no pinhole + distortion fit of camera %s (%s)", name, str(exc).splitlines()[-1])
            continue
        for v in views:
            pose = z.cam_from_target[v.frame]
            uv, _ = cv2.projectPoints(object_points(dataset.target, v.ids), cv2.Rodrigues(pose.R)[0], pose.t,
                                      z.K, z.dist)
            residuals.append(uv.reshape(-1, 2) - v.pixels)
    return robust_rmse_px(residuals) if residuals else None


def _renamed(o):
    from dataclasses import replace

    return replace(o, frame=f"{o.frame}@{o.added_mm or 0.0:g}")


def judge(model: str, rmse_px: float, residuals: Iterable[np.ndarray], pinhole_rmse: float | None, uncertainty,
          starts: tuple[str, ...] = ()) -> Quality:
    """The verdict on one result of ``model`` (module docstring)."""
    robust = robust_rmse_px(residuals)
    ratio, margin = PINHOLE_TOLERANCE.get(model, PINHOLE_TOLERANCE["ari"])
    why = []
    if not math.isfinite(rmse_px):
        why.append(f"the residual RMSE is {rmse_px}")
    if pinhole_rmse is not None and robust > ratio * pinhole_rmse + margin:
        why.append(f"it fits the corners far worse than a free pinhole + distortion model of each camera "
                   f"(robust RMSE {robust:.3f} px vs {pinhole_rmse:.3f} px): a wrong minimum, or a wrong "
                   "declared window or hint")
    sigma = None
    if uncertainty is not None:
        sigmas = [c.rotation_deg for c in uncertainty.cameras.values() if c.relative_pose]
        sigmas = [math.inf if s is None or not math.isfinite(s) else s for s in sigmas]
        sigma = max(sigmas) if sigmas else None
        if sigma is not None and sigma > MAX_POSE_SIGMA_DEG:
            why.append(f"a camera's pose is undetermined (rotation sigma {sigma:.1f} deg)")
    return Quality(not why, "; ".join(why) or None, float(rmse_px), robust, pinhole_rmse,
                   None if sigma is None or not math.isfinite(sigma) else float(sigma), tuple(starts))

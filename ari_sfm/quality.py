"""The quality gate of a calibration: is the optimum what the data allow?

A bundle adjustment that converged can still sit in a wrong minimum (a mirrored start, a
window placed behind the cameras, a wrong declared window): its residuals are then far above
what the same corners allow. After convergence a window-model calibration (ari, exact) is judged on:

- the fit against the corners' floor (:func:`floor_rmse_px`): each plane of each view mapped to
  its image by a homography plus a smooth polynomial warp, a free map that any camera behind any
  flat window (and any lens distortion) is, so its residuals are the detection noise. Both sides
  are robust RMSEs (``sqrt(2) * 1.4826 * MAD`` of the residual coordinates), so a few outlier
  corners (reported apart, see :mod:`ari_sfm.outliers`) do not decide. A result fits when
  ``robust_rmse_px <= ratio * floor_rmse_px + margin`` (:data:`FLOOR_TOLERANCE`);
- the paraxial model's own error: an ``ari`` result above that allowance is re-evaluated by the
  exact model with the same window and hints (``exact_robust_rmse_px``, computed by
  :func:`ari_sfm.calibrate.calibrate`): when the exact model fits within the allowance, the excess
  is ari's paraxial error at this geometry (PHYSICS.md: ~t^3, 1.4-2 px on binocular_underwater)
  and the result passes; when it does not, the window or a hint is wrong and ari fails too;
- physically absurd standard deviations: a camera's pose relative to camera 0 known to worse
  than ``MAX_POSE_SIGMA_DEG`` (a flat, wrong minimum: +-40 deg was seen), or not determined at all
  (no finite sigma: a singular or indefinite information matrix, see
  :func:`ari_sfm.factors.schur.global_covariance`);
- a non-finite RMSE.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping

import numpy as np

log = logging.getLogger(__name__)

# The model may fit up to ratio x the floor plus the margin (exact at its optimum: 0.9-1.1 x the floor on the
# bundled scenarios; the margin covers a sub-pixel systematic misfit, e.g. lens distortion not estimated).
FLOOR_TOLERANCE = (2.0, 0.25)
PARAXIAL_MODELS = ("ari",)  # models whose excess over the allowance is re-evaluated by the exact model
MAX_POSE_SIGMA_DEG = 5.0  # a relative camera rotation less determined than this is not a calibration
MAD_TO_SIGMA = 1.4826
WARP_DEGREE = 4  # highest degree of the floor's polynomial warp (image coordinates), lowered for small planes
MIN_PLANE_CORNERS = 12  # corners of one plane of one view needed to fit its warp
CORNERS_PER_TERM = 3  # at least this many corners per polynomial term (else a lower degree)
MAX_FLOOR_VIEWS = 8  # views in the floor's fit (evenly picked: a noise estimate needs no more, bounded cost)


@dataclass(frozen=True)
class Quality:
    """The gate's verdict (``calibration.json`` key ``quality``) and the figures it was judged on."""

    ok: bool
    why: str | None  # None when ok; else each failed test, '; '-joined
    rmse_px: float
    robust_rmse_px: float  # sqrt(2) * 1.4826 * MAD of the residual coordinates
    pinhole_dist_rmse_px: float | None  # kept for older files (their yardstick); None since the floor replaced it
    max_pose_sigma_deg: float | None  # largest relative camera rotation sigma (None: no uncertainty)
    starts: tuple[str, ...] = field(default_factory=tuple)  # the starts tried, the kept one last
    floor_rmse_px: float | None = None  # robust RMSE of the free per-plane warps (None: no plane could be fitted)
    exact_robust_rmse_px: float | None = None  # ari only: the exact model's robust RMSE with the same window

    def to_json(self) -> dict[str, Any]:
        return {"ok": self.ok, "why": self.why, "rmse_px": self.rmse_px, "robust_rmse_px": self.robust_rmse_px,
                "pinhole_dist_rmse_px": self.pinhole_dist_rmse_px, "max_pose_sigma_deg": self.max_pose_sigma_deg,
                "starts": list(self.starts), "floor_rmse_px": self.floor_rmse_px,
                "exact_robust_rmse_px": self.exact_robust_rmse_px}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Quality":
        def num(key: str) -> float | None:
            v = d.get(key)
            return None if v is None else float(v)

        if not isinstance(d.get("ok"), bool):
            raise ValueError("ok must be true or false")
        return cls(d["ok"], d.get("why"), float(d.get("rmse_px", math.nan)), float(d.get("robust_rmse_px", math.nan)),
                   num("pinhole_dist_rmse_px"), num("max_pose_sigma_deg"), tuple(str(s) for s in d.get("starts", ())),
                   num("floor_rmse_px"), num("exact_robust_rmse_px"))


def robust_rmse_px(residuals: Iterable[np.ndarray]) -> float:
    """sqrt(2) * 1.4826 * MAD of the residual coordinates: the RMSE the bulk of the corners has."""
    r = np.concatenate([np.asarray(x, float).reshape(-1) for x in residuals] or [np.zeros(0)])
    return float(math.sqrt(2.0) * MAD_TO_SIGMA * np.median(np.abs(r))) if r.size else math.nan


def _warp_terms(degree: int) -> int:
    """The polynomial warp's terms s_x^i s_y^j, i + j <= degree."""
    return (degree + 1) * (degree + 2) // 2


def _warp_residuals(xy: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (V, N, 2) of V planes' corners ``xy`` (target plane) against their pixels ``uv`` (each
    (V, N, 2)) after a homography and a polynomial warp in image coordinates, scaled for the parameters
    fitted (:func:`ari_sfm.floor_fit.warp_residuals`; the warp's degree lowered for small planes: at
    least ``CORNERS_PER_TERM`` corners per term); and which planes were fitted (V,)."""
    from .floor_fit import warp_residuals

    V, n = xy.shape[:2]
    degree = WARP_DEGREE
    while degree > 0 and _warp_terms(degree) * CORNERS_PER_TERM > n:
        degree -= 1
    if n <= _warp_terms(degree) + 4:  # the warp's and the homography's 4 per coordinate: nothing left
        return np.full((V, n, 2), np.nan), np.zeros(V, dtype=bool)
    return warp_residuals(np.ascontiguousarray(xy, dtype=np.float64), np.ascontiguousarray(uv, dtype=np.float64),
                          degree)


def floor_rmse_px(dataset) -> float | None:
    """The robust RMSE the corners allow (module docstring): every plane of up to ``MAX_FLOOR_VIEWS``
    calibration and stacking views (evenly picked) with >= ``MIN_PLANE_CORNERS`` corners fitted by its
    own homography + polynomial warp (planes of the same corner count at once); a 3D body's planes are its
    corners' distinct target z. None when no plane was fitted."""
    from .init.zhang import object_points

    planar = dataset.target.is_planar()
    views = [o for o in dataset.observations if o.set in ("calibration", "stacking") and len(o.ids) >= MIN_PLANE_CORNERS]
    if len(views) > MAX_FLOOR_VIEWS:
        views = [views[i] for i in np.linspace(0, len(views) - 1, MAX_FLOOR_VIEWS).round().astype(int)]
    by_size: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for o in views:
        X, uv = object_points(dataset.target, o.ids), np.asarray(o.pixels, float)
        planes = [slice(None)] if planar else [X[:, 2] == z for z in np.unique(X[:, 2])]
        for on in planes:
            if len(X[on]) >= MIN_PLANE_CORNERS:
                by_size.setdefault(len(X[on]), []).append((X[on, :2], uv[on]))
    residuals = []
    for planes in by_size.values():
        r, fitted = _warp_residuals(np.array([xy for xy, _ in planes]), np.array([uv for _, uv in planes]))
        residuals += list(r[fitted])
    return robust_rmse_px(residuals) if residuals else None


def allowance_px(floor_rmse: float) -> float:
    """The largest robust RMSE a result may have over corners of this floor (:data:`FLOOR_TOLERANCE`)."""
    ratio, margin = FLOOR_TOLERANCE
    return ratio * floor_rmse + margin


def fits(model: str, residuals: Iterable[np.ndarray], floor_rmse: float | None) -> bool:
    """Whether a result's residuals are within the allowance (before any exact re-evaluation)."""
    return floor_rmse is None or robust_rmse_px(residuals) <= allowance_px(floor_rmse)


def judge(model: str, rmse_px: float, residuals: Iterable[np.ndarray], floor_rmse: float | None, uncertainty,
          starts: tuple[str, ...] = (), exact_robust: float | None = None) -> Quality:
    """The verdict on one result of ``model`` (module docstring); ``exact_robust``: the exact model's
    robust RMSE with the same window and hints (a paraxial model's re-evaluation), None if not run."""
    robust = robust_rmse_px(residuals)
    why = []
    if not math.isfinite(rmse_px):
        why.append(f"the residual RMSE is {rmse_px}")
    if floor_rmse is not None and robust > allowance_px(floor_rmse):
        paraxial = model in PARAXIAL_MODELS and exact_robust is not None and exact_robust <= allowance_px(floor_rmse)
        if not paraxial:
            also = "" if exact_robust is None else f", and the exact model with the same window does not ({exact_robust:.3f} px)"
            why.append(f"it fits the corners far worse than the data allow (robust RMSE {robust:.3f} px vs a floor of "
                       f"{floor_rmse:.3f} px{also}): a wrong minimum, or a wrong declared window or hint")
    sigma = None
    if uncertainty is not None:
        sigmas = {name: math.inf if c.rotation_deg is None or not math.isfinite(c.rotation_deg) else c.rotation_deg
                  for name, c in uncertainty.cameras.items() if c.relative_pose}
        sigma = max(sigmas.values()) if sigmas else None
        undetermined = [name for name, s in sigmas.items() if not math.isfinite(s)]
        if undetermined:
            why.append(f"the relative pose of {', '.join(undetermined)} is not determined by the data (no finite "
                       "rotation sigma: a singular or indefinite information matrix)")
        elif sigma is not None and sigma > MAX_POSE_SIGMA_DEG:
            why.append(f"a camera's pose is undetermined (rotation sigma {sigma:.1f} deg)")
    return Quality(not why, "; ".join(why) or None, float(rmse_px), robust, None,
                   None if sigma is None or not math.isfinite(sigma) else float(sigma), tuple(starts), floor_rmse,
                   exact_robust)

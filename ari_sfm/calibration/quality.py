"""The quality gate of a calibration: is the optimum what the data allow?

A bundle adjustment that converged can still sit in a wrong minimum (a mirrored start, a
window placed behind the cameras, a wrong declared window): its residuals are then far above
what the same corners allow. After convergence a window-model calibration (ari, exact) is judged on:

- the fit against the corners' floor (:func:`corner_floor`): what the data allow under the model's
  own assumptions, measured the same way on every kind of target. Each view is mapped by the most
  flexible free map of the calibration model's structure (:mod:`ari_sfm.calibration.floor_fit`): a planar view
  (a board) by a homography and a smooth image warp, which any camera behind any flat window with
  any lens is; a view of a 3D body (every plane of a multi-plane body at once: one frame is one rigid
  body seen once; a dataset giving each plane its own frame says they were placed independently, and
  each is then a planar view) by one free projective camera, a smooth image warp and an inverse-depth
  term (a window under water is not a central camera). Its residuals are scaled for the parameters
  fitted: the detection noise, plus what no single rigid body explains (a plane's placement error).
  Both sides are robust RMSEs (``sqrt(2) * 1.4826 * MAD`` of the residual coordinates), so a few
  outlier corners (reported apart, see :mod:`ari_sfm.calibration.outliers`) do not decide. A correct model's
  robust RMSE is the floor times ~1 with the spread of two MAD estimates, which shrinks with the
  corners: a result fits when ``robust_rmse_px <= FLOOR_RATIO (1 + FLOOR_SIGMAS s) floor + MARGIN_PX``,
  s = 1.166 sqrt(1 / its residual coordinates + 1 / the floor's residual dof) (:func:`allowance_px`);
- the paraxial model's own error: an ``ari`` result above that allowance is re-evaluated by the
  exact model with the same window and hints (``exact_robust_rmse_px``, computed by
  :func:`ari_sfm.calibrate.calibrate`): when the exact model fits within the allowance, the excess
  is ari's paraxial error at this geometry and the result passes; when it does not, the window or
  a hint is wrong and ari fails too;
- physically absurd standard deviations: a camera's pose relative to camera 0 known to worse
  than ``MAX_POSE_SIGMA_DEG`` (a flat, wrong minimum), or not determined at all
  (no finite sigma: a singular or indefinite information matrix, see
  :func:`ari_sfm.solver.schur.global_covariance`);
- a non-finite RMSE.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from ..records import Dataset
    from ..results import Uncertainty

log = logging.getLogger(__name__)

# A correct model's robust RMSE is the floor times ~1 (0.94-1.04 measured on exact-physics scenarios:
# benchmarks/bench_quality_floor.py), spread by two MAD estimates; FLOOR_RATIO allows for what one rigid model
# legitimately fits worse than a free map per view (ptv_multiplane's plate placed with errors of 0.1-0.3 mm and
# 0.05-0.3 deg, 8 seeds x 6 kinds: rigid fit 0.92-1.36 x the floor), FLOOR_SIGMAS standard deviations of the ratio's
# statistical spread on top, MARGIN_PX the free map's own residual on noise-free simulations (< 0.004 px).
FLOOR_RATIO = 1.4
FLOOR_SIGMAS = 4.0
MARGIN_PX = 0.005
MAD_SPREAD = 1.166  # sqrt(count) x the relative standard deviation of a MAD sigma (normal residuals)
PARAXIAL_MODELS = ("ari",)  # models whose excess over the allowance is re-evaluated by the exact model
MAX_POSE_SIGMA_DEG = 5.0  # a relative camera rotation less determined than this is not a calibration
MAD_TO_SIGMA = 1.4826
WARP_DEGREE = 4  # highest degree of a planar view's polynomial warp W (image coordinates), lowered for small planes
BODY_WARP_DEGREE = 5  # the same of a body's view (noise-free, under water: 4 left 0.005-0.012 px, 5 0.003-0.004)
MIN_VIEW_CORNERS = 12  # corners of one view needed to fit its free map
CORNERS_PER_TERM = 2  # at least this many corners per polynomial term (else a lower degree; 3 left a 25-corner
# view of a 3D body under water 26 x its noise: the warp too low for the window's refraction)
MIN_RESIDUAL_SHARE = 0.1  # of a view's 2n coordinates left after the map's parameters (else a lower degree)
PLANAR_THICKNESS = 1e-6  # a view's points whose thinnest extent is below this share of the widest are a plane
MAX_FLOOR_VIEWS = 8  # views in the floor's fit (evenly picked: a noise estimate needs no more, bounded cost)


@dataclass(frozen=True)
class Floor:
    """What the corners allow: the robust RMSE of the free per-view maps (:func:`corner_floor`)."""

    rmse_px: float
    dof: int  # residual coordinates less the parameters fitted: what the estimate's spread goes with


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
    floor_rmse_px: float | None = None  # robust RMSE of the free per-view maps (None: no view could be fitted)
    exact_robust_rmse_px: float | None = None  # ari only: the exact model's robust RMSE with the same window
    allowance_px: float | None = None  # the largest robust RMSE the result could have had (None: no floor)

    def to_json(self) -> dict[str, Any]:
        return {"ok": self.ok, "why": self.why, "rmse_px": self.rmse_px, "robust_rmse_px": self.robust_rmse_px,
                "pinhole_dist_rmse_px": self.pinhole_dist_rmse_px, "max_pose_sigma_deg": self.max_pose_sigma_deg,
                "starts": list(self.starts), "floor_rmse_px": self.floor_rmse_px,
                "exact_robust_rmse_px": self.exact_robust_rmse_px, "allowance_px": self.allowance_px}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Quality:
        def num(key: str) -> float | None:
            v = d.get(key)
            return None if v is None else float(v)

        if not isinstance(d.get("ok"), bool):
            raise ValueError("ok must be true or false")
        return cls(d["ok"], d.get("why"), float(d.get("rmse_px", math.nan)), float(d.get("robust_rmse_px", math.nan)),
                   num("pinhole_dist_rmse_px"), num("max_pose_sigma_deg"), tuple(str(s) for s in d.get("starts", ())),
                   num("floor_rmse_px"), num("exact_robust_rmse_px"), num("allowance_px"))


def robust_rmse_px(residuals: Iterable[np.ndarray]) -> float:
    """sqrt(2) * 1.4826 * MAD of the residual coordinates: the RMSE the bulk of the corners has."""
    r = np.concatenate([np.asarray(x, float).reshape(-1) for x in residuals] or [np.zeros(0)])
    return float(math.sqrt(2.0) * MAD_TO_SIGMA * np.median(np.abs(r))) if r.size else math.nan


def _warp_terms(degree: int) -> int:
    """The polynomial warp's terms s_x^i s_y^j, i + j <= degree (none for degree -1)."""
    return (degree + 1) * (degree + 2) // 2


def _warp_of(n: int, planar: bool) -> tuple[int, bool, int] | None:
    """The free map of a view of n corners: (W's degree, the non-central term on, parameters fitted): W the most
    flexible with at least ``CORNERS_PER_TERM`` corners per term; None when the map's parameters would leave
    nothing to measure."""
    from .floor_fit import RADIAL_PARAMETERS

    def parameters(degree: int) -> int:
        return 2 * _warp_terms(degree) + (8 if planar else 11 + RADIAL_PARAMETERS)

    degree = WARP_DEGREE if planar else BODY_WARP_DEGREE
    while degree > 0 and (_warp_terms(degree) * CORNERS_PER_TERM > n
                          or 2 * n - parameters(degree) < MIN_RESIDUAL_SHARE * 2 * n):
        degree -= 1
    return (degree, not planar, parameters(degree)) if 2 * n > parameters(degree) else None


def _warp_residuals(src: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Residuals (V, n, 2) of V views' points ``src`` (V, n, 2: a plane's coordinates; V, n, 3: a body's)
    against their pixels ``uv`` (V, n, 2) after the free map (:func:`ari_sfm.calibration.floor_fit.warp_residuals`,
    W's degree lowered for small views: :func:`_warp_of`), scaled for the parameters fitted; which views
    were fitted (V,); and the parameters fitted per view."""
    from .floor_fit import warp_residuals

    V, n, k = src.shape
    warp = _warp_of(n, k == 2)
    if warp is None:
        return np.full((V, n, 2), np.nan), np.zeros(V, dtype=bool), 0
    degree, radial, parameters = warp
    r, fitted = warp_residuals(np.ascontiguousarray(src, dtype=np.float64), np.ascontiguousarray(uv, dtype=np.float64),
                               degree, radial)
    return r, fitted, parameters


def _view_points(X: np.ndarray) -> np.ndarray:
    """A view's target points (n, 3) as the free map takes them: a plane's 2D coordinates (n, 2) (its
    own axes when it is not z = 0), else the body's (n, 3)."""
    if np.ptp(X[:, 2]) == 0.0:
        return X[:, :2]
    centred = X - X.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    return centred @ vt[:2].T if s[2] <= PLANAR_THICKNESS * s[0] else X


def corner_floor(dataset: Dataset) -> Floor | None:
    """Measure what the corners allow (module docstring).

    Each of up to ``MAX_FLOOR_VIEWS`` calibration and stacking views (evenly picked) with >=
    ``MIN_VIEW_CORNERS`` corners is fitted by its own free map: a planar view by a homography and a warp,
    a body's view (every plane of it at once: one rigid body seen once) by a projective camera and a warp
    with an inverse-depth term.

    Args:
        dataset: the dataset (its observations loaded).

    Returns:
        The floor (robust RMSE of the free maps' residuals, and their dof), or None when no view was fitted.
    """
    from ..init.zhang import object_points

    views = [o for o in dataset.observations or ()
             if o.set in ("calibration", "stacking") and len(o.ids) >= MIN_VIEW_CORNERS]
    if len(views) > MAX_FLOOR_VIEWS:
        views = [views[i] for i in np.linspace(0, len(views) - 1, MAX_FLOOR_VIEWS).round().astype(int)]
    by_shape: dict[tuple[int, int], list[tuple[np.ndarray, np.ndarray]]] = {}
    for o in views:
        src = _view_points(object_points(dataset.target, o.ids))
        by_shape.setdefault(src.shape, []).append((src, np.asarray(o.pixels, float)))
    residuals, dof = [], 0
    for (n, _), group in by_shape.items():
        r, fitted, parameters = _warp_residuals(np.array([src for src, _ in group]), np.array([uv for _, uv in group]))
        residuals += list(r[fitted])
        dof += int(fitted.sum()) * (2 * n - parameters)
    return Floor(robust_rmse_px(residuals), dof) if residuals else None


def floor_rmse_px(dataset) -> float | None:
    """The robust RMSE the corners allow (:func:`corner_floor`), None when no view was fitted."""
    floor = corner_floor(dataset)
    return None if floor is None else floor.rmse_px


def allowance_px(floor: Floor | float, coordinates: int) -> float:
    """Give the largest robust RMSE a result may have against the floor (module docstring).

    Args:
        floor: the corners' floor (:func:`corner_floor`); a bare float: a floor RMSE (px) measured on as many
            coordinates as the result.
        coordinates: the result's residual coordinates.

    Returns:
        The allowance (px).
    """
    if not isinstance(floor, Floor):
        floor = Floor(float(floor), int(coordinates))
    spread = MAD_SPREAD * math.sqrt(1.0 / max(coordinates, 1) + 1.0 / max(floor.dof, 1))
    return FLOOR_RATIO * (1.0 + FLOOR_SIGMAS * spread) * floor.rmse_px + MARGIN_PX


def _coordinates(residuals: list[np.ndarray]) -> int:
    return int(sum(np.asarray(r).size for r in residuals))


def fits(model: str, residuals: Iterable[np.ndarray], floor: Floor | float | None) -> bool:
    """Tell whether a result's residuals are within the allowance (before any exact re-evaluation).

    Args:
        model: the calibration model's name.
        residuals: the result's residuals (px), any shapes.
        floor: the corners' floor (:func:`corner_floor`), a bare floor RMSE (px), or None (no floor: fits).

    Returns:
        True if the robust RMSE is within :func:`allowance_px`.
    """
    residuals = list(residuals)
    return floor is None or robust_rmse_px(residuals) <= allowance_px(floor, _coordinates(residuals))


def judge(model: str, rmse_px: float, residuals: Iterable[np.ndarray], floor: Floor | float | None,
          uncertainty: Uncertainty | None,
          starts: tuple[str, ...] = (), exact_robust: float | None = None) -> Quality:
    """Give the gate's verdict on one result (module docstring).

    Args:
        model: the calibration model's name (``ari`` results may pass on ``exact_robust``).
        rmse_px: the result's residual RMSE (px).
        residuals: the result's residuals (px), any shapes.
        floor: the corners' floor (:func:`corner_floor`); a bare float: a floor RMSE (px) measured on as many
            coordinates as the result; None: no floor test.
        uncertainty: the result's :class:`~ari_sfm.results.Uncertainty`, or None (no sigma test).
        starts: the starts tried, the kept one last.
        exact_robust: the exact model's robust RMSE (px) with the same window and hints (a paraxial model's
            re-evaluation), None if not run.

    Returns:
        The verdict and the figures it was judged on.
    """
    residuals = list(residuals)
    robust = robust_rmse_px(residuals)
    allowed = None if floor is None else allowance_px(floor, _coordinates(residuals))
    floor_rmse = None if floor is None else float(floor.rmse_px if isinstance(floor, Floor) else floor)
    why = []
    if not math.isfinite(rmse_px):
        why.append(f"the residual RMSE is {rmse_px}")
    if allowed is not None and not robust <= allowed:
        paraxial = model in PARAXIAL_MODELS and exact_robust is not None and exact_robust <= allowed
        if not paraxial:
            also = ("" if exact_robust is None
                    else f", and the exact model with the same window does not ({exact_robust:.3f} px)")
            why.append(f"it fits the corners far worse than the data allow (robust RMSE {robust:.3f} px vs a floor of "
                       f"{floor_rmse:.3f} px, at most {allowed:.3f} px{also}): a wrong minimum, a wrong declared "
                       "window or hint, or a lens distortion not estimated")
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
                   exact_robust, allowed)

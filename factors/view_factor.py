"""One GTSAM CustomFactor per (camera, image): the reprojection of all its corners.

The error is the stacked pixel residuals (projected - measured), 2M long. The
projection model (:class:`~ari_sfm.models.AriModel` or
:class:`~ari_sfm.models.ExactModel`) supplies the derivatives w.r.t. the point,
the normal, the intrinsics and the window distance; this module chains them to
the GTSAM tangent spaces:

- Pose3 (right perturbation T Exp([w, v])): for world_T_cam,
  dX_cam = [X_cam]x w - v and dn_cam = [n_cam]x w; for world_T_target,
  dX_cam = R_cam_from_world R_world_from_target ([-P]x w + v).
- Unit3: dn_world = B dxi with B the Unit3 tangent basis.
- The camera's distance to the near surface is h_c = h_0 - n_world . C_c,
  C_c the camera centre in the world.

Optional Huber weighting is per corner (on the pixel distance), applied as
square-root weights inside the factor, because a robust noise model on a
2M-vector would down-weight whole images instead of single corners.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import gtsam
import numpy as np

from ..geometry import skew
from ..models import PinholeModel

ModelFactory = Callable[..., object]


@dataclass(frozen=True)
class ViewData:
    """What one factor needs besides the variables: points, pixels and the plate."""

    points_target: np.ndarray  # (M, 3) target-frame corners
    measured: np.ndarray  # (M, 2) pixels
    thickness_mm: float  # the window plus any stacked plates
    index: float
    medium_index: float
    base_params: np.ndarray  # (9,) the intrinsics; the first n_params are variables
    n_params: int  # 4 (no distortion) or 9


@dataclass(frozen=True)
class ViewKeys:
    intrinsics: int
    frame: int
    normal: int
    camera: int | None = None  # None: the camera is the world frame (identity)
    distance: int | None = None  # None: distance fixed at fixed_distance_mm
    fixed_distance_mm: float | None = None


def view_residuals(
    model_factory: ModelFactory, data: ViewData, keys: ViewKeys, values: gtsam.Values, want_jacobians: bool, huber_px: float | None = None
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Residuals (2M,) of one view and, if asked, the Jacobians in key order."""
    params = data.base_params.copy()
    params[: data.n_params] = values.atVector(keys.intrinsics)
    if keys.camera is not None:
        world_T_cam = values.atPose3(keys.camera)
        R_wc, t_wc = world_T_cam.rotation().matrix(), np.asarray(world_T_cam.translation())
    else:
        R_wc, t_wc = np.eye(3), np.zeros(3)
    normal = values.atUnit3(keys.normal)
    n_w = normal.point3()
    world_T_target = values.atPose3(keys.frame)
    R_wt, t_wt = world_T_target.rotation().matrix(), np.asarray(world_T_target.translation())
    h0 = float(values.atVector(keys.distance)[0]) if keys.distance is not None else keys.fixed_distance_mm
    R_cw = R_wc.T
    P = data.points_target
    X_c = (P @ R_wt.T + t_wt - t_wc) @ R_wc
    n_c = R_cw @ n_w
    h_c = None if h0 is None else h0 - float(n_w @ t_wc)
    if h_c is not None and h_c <= 0:
        # An LM trial step put the camera beyond the window: a huge error rejects the step.
        M = len(P)
        dims = [data.n_params] + ([6] if keys.camera is not None else []) + [2, 6] + ([1] if keys.distance is not None else [])
        return np.full(2 * M, 1e6), [np.zeros((2 * M, d)) for d in dims] if want_jacobians else []
    model = model_factory(PinholeModel.from_params(params), n_c, data.thickness_mm, data.index, data.medium_index, h_c)
    J = model.project_with_jacobians(X_c)
    r = J.uv - data.measured
    weights = np.ones(len(r))
    if huber_px is not None:
        dist = np.linalg.norm(r, axis=1)
        big = dist > huber_px
        weights[big] = np.sqrt(huber_px / dist[big])
    residual = (r * weights[:, None]).reshape(-1)
    if not np.all(np.isfinite(residual)):
        residual = np.where(np.isfinite(residual), residual, 1e6)  # a point fell behind the window
    if not want_jacobians:
        return residual, []
    M = len(P)
    w = weights[:, None, None]
    Jp, Jn = J.J_point * w, J.J_normal * w
    Jd = np.asarray(J.J_distance).reshape(M, 2, 1) * w
    Hs = [(J.J_params[:, :, : data.n_params] * w).reshape(2 * M, data.n_params)]
    if keys.camera is not None:
        H_cam = np.concatenate([Jp @ skew(X_c), -Jp], axis=2)
        H_cam[:, :, :3] += Jn @ skew(n_c)
        H_cam[:, :, 3:] += Jd @ (-(n_w @ R_wc))[None, None, :]
        Hs.append(H_cam.reshape(2 * M, 6))
    B = normal.basis()
    H_n = Jn @ (R_cw @ B) + Jd @ (-(t_wc @ B))[None, None, :]
    Hs.append(H_n.reshape(2 * M, 2))
    JA = Jp @ (R_cw @ R_wt)  # (M, 2, 3)
    H_x = np.concatenate([-JA @ skew(P), JA], axis=2)
    Hs.append(H_x.reshape(2 * M, 6))
    if keys.distance is not None:
        Hs.append(Jd.reshape(2 * M, 1))
    return residual, Hs


def factor_keys(keys: ViewKeys) -> list[int]:
    """The factor's keys in the order of its Jacobians."""
    out = [keys.intrinsics]
    if keys.camera is not None:
        out.append(keys.camera)
    out += [keys.normal, keys.frame]
    if keys.distance is not None:
        out.append(keys.distance)
    return out


def view_factor(
    model_factory: ModelFactory, data: ViewData, keys: ViewKeys, sigma_px: float = 1.0, huber_px: float | None = None
) -> gtsam.CustomFactor:
    """A CustomFactor for all corners of one image (model: AriModel or ExactModel)."""
    key_list = factor_keys(keys)
    dims = [data.n_params] + ([6] if keys.camera is not None else []) + [2, 6] + ([1] if keys.distance is not None else [])
    rows = 2 * len(data.points_target)
    noise = gtsam.noiseModel.Isotropic.Sigma(rows, sigma_px)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        residual, Hs = view_residuals(model_factory, data, keys, values, H is not None, huber_px)
        if H is not None:
            for i, (Hi, dim) in enumerate(zip(Hs, dims)):
                if Hi.shape != (rows, dim) or not np.all(np.isfinite(Hi)):
                    raise RuntimeError(f"Jacobian {i} has shape {Hi.shape} or non-finite entries, expected ({rows}, {dim})")
                H[i] = Hi
        return residual

    return gtsam.CustomFactor(noise, key_list, error)

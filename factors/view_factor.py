"""One GTSAM CustomFactor per (camera, image): the reprojection of all its corners.

The error is the stacked pixel residuals (projected - measured), 2M long. The
projection model (:class:`~ari_sfm.models.AriModel` or
:class:`~ari_sfm.models.ExactModel`) supplies the derivatives w.r.t. the point,
the normal, the intrinsics and the window distance; :func:`chain_to_tangents`
(the one copy, compiled in :mod:`~ari_sfm.factors.view_kernels`, also used by the numpy backend)
chains them to the GTSAM tangent spaces:

- Pose3 (right perturbation T Exp([w, v])): for world_T_cam,
  dX_cam = [X_cam]x w - v and dn_cam = [n_cam]x w; for world_T_target,
  dX_cam = R_cam_from_world R_world_from_target ([-P]x w + v).
- Unit3: dn_world = B dxi with B the Unit3 tangent basis.
- The camera's distance to the near surface is h_c = h_0 - n_world . C_c,
  C_c the camera centre in the world.

Optional Huber loss per corner (on the pixel distance), applied inside the
factor so that it down-weights single corners: the corners' rows IRLS-weighted and one more
row that makes the error the Huber loss
(:func:`~ari_sfm.factors.robust.huber_view_residual`).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from ..models import AriModel, ExactModel, PinholeModel
from .robust import huber_view_residual
from .view_kernels import chain_rows

ModelFactory = Callable[..., AriModel | ExactModel]  # (pinhole, normal, thickness, index, medium index, distance)


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


def camera_terms(normal_world: np.ndarray, basis: np.ndarray, R_wc: np.ndarray | None, t_wc: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the chain rule needs of one camera (:mod:`~ari_sfm.factors.view_kernels`).

    Args:
        normal_world: the window's unit normal in the world (3,).
        basis: its Unit3 tangent basis B (3, 2).
        R_wc: the camera's world_T_cam rotation (3, 3); None for camera 0 (the world: R_cw = I).
        t_wc: the camera's world_T_cam translation (3,).

    Returns:
        ``n_cam`` = R_cw n_world (3,), ``a`` = -(n_world R_wc) (3,), ``M`` = R_cw B (3, 2) and
            ``b`` = -(t_wc B) (2,).
    """
    R_cw = np.eye(3) if R_wc is None else R_wc.T
    n_cam = R_cw @ normal_world
    cam_shift = np.zeros(3) if R_wc is None else -(normal_world @ R_wc)
    return n_cam, cam_shift, np.ascontiguousarray(R_cw @ basis), -(t_wc @ basis)


def chain_to_tangents(out: np.ndarray, n_params: int, J_point: np.ndarray, J_normal: np.ndarray,
                      J_distance: np.ndarray, X_cam: np.ndarray, P: np.ndarray, R_view: np.ndarray,
                      view_start: np.ndarray, normal_world: np.ndarray, basis: np.ndarray, R_wc: np.ndarray | None,
                      t_wc: np.ndarray, distance: bool) -> None:
    """The chain rule from the model's derivatives to the variables' tangent spaces (module docstring).

    Compiled: :func:`~ari_sfm.factors.view_kernels.chain_rows`. For M corners of one camera grouped by view,
    written into ``out`` (M, 2, >= 6 + n_params + 8 (+1)) laid out as
    ``[X(f) (6) | K(c) (n_params, left to the caller) | C(c) (6, zero for camera 0) | N (2) | H (1, with
    distance)]``.

    Args:
        out: the output Jacobian rows (M, 2, >= 6 + n_params + 8 (+1)).
        n_params: the number of intrinsics columns.
        J_point: d uv / d X_cam (M, 2, 3) from the model.
        J_normal: d uv / d n_cam (M, 2, 3) from the model.
        J_distance: d uv / d h_c (M, 2) from the model.
        X_cam: the camera-frame points (M, 3).
        P: the target-frame points (M, 3).
        R_view: each view's R_cam_target (V, 3, 3).
        view_start: view v's corners are ``view_start[v]:view_start[v + 1]`` (V + 1,).
        normal_world: the window's unit normal in the world (3,).
        basis: its Unit3 tangent basis (3, 2).
        R_wc: the camera's world_T_cam rotation; None for camera 0.
        t_wc: the camera's world_T_cam translation (3,).
        distance: fill the H column (the distance is a variable).
    """
    n_cam, cam_shift, normal_map, normal_shift = camera_terms(normal_world, basis, R_wc, t_wc)
    chain_rows(J_point, J_normal, J_distance, X_cam, P, R_view, view_start, n_cam, cam_shift, normal_map,
               normal_shift, R_wc is not None, bool(distance), int(n_params), out)


def view_residuals(
    model_factory: ModelFactory, data: ViewData, keys: ViewKeys, values: gtsam.Values, want_jacobians: bool,
    huber_px: float | None = None
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Residuals of one view and, if asked, the Jacobians in key order (:func:`factor_keys`).

    A camera put beyond the window by an LM trial step gets residuals of 1e6 (a huge error rejects the
    step); a corner that falls behind the window gets 1e6 entries.

    Args:
        model_factory: the projection class (AriModel or ExactModel).
        data: the view's points, pixels and plate.
        keys: the view's variable keys.
        values: the variables' values.
        want_jacobians: compute the Jacobians.
        huber_px: the per-corner Huber threshold (px); None: no Huber loss.

    Returns:
        The residual (2M,), or (2M + 1,) with the Huber row, and the Jacobians (empty without
            ``want_jacobians``).
    """
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
        rows = 2 * len(P) + (huber_px is not None)
        dims = ([data.n_params] + ([6] if keys.camera is not None else []) + [2, 6]
                + ([1] if keys.distance is not None else []))
        return np.full(rows, 1e6), [np.zeros((rows, d)) for d in dims] if want_jacobians else []
    model = model_factory(PinholeModel.from_params(params), n_c, data.thickness_mm, data.index, data.medium_index, h_c)
    J = model.project_with_jacobians(X_c)
    r = J.uv - data.measured
    if huber_px is None:
        residual, scale = r.reshape(-1), None
    else:
        residual, scale = huber_view_residual(r, huber_px)
    if not np.all(np.isfinite(residual)):
        residual = np.where(np.isfinite(residual), residual, 1e6)  # a point fell behind the window
    if not want_jacobians:
        return residual, []
    M, n_p = len(P), data.n_params
    out = np.zeros((M, 2, 6 + n_p + 6 + 2 + 1))
    out[:, :, 6:6 + n_p] = J.J_params[:, :, :n_p]
    chain_to_tangents(out, n_p, J.J_point, J.J_normal, np.ascontiguousarray(J.J_distance).reshape(M, 2), X_c,
                      np.ascontiguousarray(P, float), (R_cw @ R_wt)[None], np.array([0, M]), np.asarray(n_w, float),
                      np.asarray(normal.basis(), float), R_wc if keys.camera is not None else None, t_wc,
                      keys.distance is not None)
    k = 6 + n_p
    blocks = [out[:, :, 6:k]] + ([out[:, :, k:k + 6]] if keys.camera is not None else [])
    blocks += [out[:, :, k + 6:k + 8], out[:, :, :6]] + ([out[:, :, k + 8:k + 9]] if keys.distance is not None else [])
    Hs = [b.reshape(2 * M, b.shape[2]) for b in blocks]
    if scale is not None:  # the rows times sqrt(w); the excess row's Jacobian is zero
        Hs = [np.vstack([H * np.repeat(scale, 2)[:, None], np.zeros((1, H.shape[1]))]) for H in Hs]
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
    """A CustomFactor for all corners of one image.

    Args:
        model_factory: the projection class (AriModel or ExactModel).
        data: the view's points, pixels and plate.
        keys: the view's variable keys.
        sigma_px: the isotropic pixel sigma (per coordinate).
        huber_px: the per-corner Huber threshold (px); None: no Huber loss.

    Returns:
        The factor; its error function raises RuntimeError on a Jacobian of the wrong shape or with
            non-finite entries.
    """
    key_list = factor_keys(keys)
    dims = ([data.n_params] + ([6] if keys.camera is not None else []) + [2, 6]
            + ([1] if keys.distance is not None else []))
    rows = 2 * len(data.points_target) + (huber_px is not None)  # (Huber: the excess row)
    noise = gtsam.noiseModel.Isotropic.Sigma(rows, sigma_px)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        residual, Hs = view_residuals(model_factory, data, keys, values, H is not None, huber_px)
        if H is not None:
            for i, (Hi, dim) in enumerate(zip(Hs, dims)):
                if Hi.shape != (rows, dim) or not np.all(np.isfinite(Hi)):
                    raise RuntimeError(f"Jacobian {i} has shape {Hi.shape} or non-finite entries, expected ({rows}, "
                                       f"{dim})")
                H[i] = Hi
        return residual

    return gtsam.CustomFactor(noise, key_list, error)

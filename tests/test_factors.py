"""The per-view CustomFactor: analytic Jacobians against numerical ones, the
no-glass limit against GTSAM's own projection factor, and shape checks."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from ari_sfm.factors import keys as K_
from ari_sfm.factors.view_factor import ViewData, ViewKeys, view_factor
from ari_sfm.geometry import rotation_from_rotvec
from ari_sfm.models import AriModel, ExactModel

RNG = np.random.default_rng(7)


def _values(with_camera: bool, with_distance: bool, n_params: int) -> gtsam.Values:
    v = gtsam.Values()
    v.insert(K_.K(1), np.array([1500.0, 1510.0, 640.0, 500.0, -0.05, 0.01, 1e-4, -2e-4, 0.001])[:n_params])
    v.insert(K_.C(1), gtsam.Pose3(gtsam.Rot3(rotation_from_rotvec([0.02, 0.2, -0.01])), np.array([-150.0, 5.0, 12.0])))
    v.insert(K_.N, gtsam.Unit3(np.array([0.05, -0.08, 1.0])))
    v.insert(K_.X(0), gtsam.Pose3(gtsam.Rot3(rotation_from_rotvec([0.3, -0.2, 0.1])), np.array([-60.0, -40.0, 420.0])))
    v.insert(K_.H, np.array([35.0]))
    return v


def _data(thickness: float, medium: float, n_params: int) -> ViewData:
    c, r = np.meshgrid(np.arange(5), np.arange(4))
    pts = np.stack([c.ravel() * 20.0, r.ravel() * 20.0, np.zeros(c.size)], axis=1)
    return ViewData(pts, RNG.normal(600, 100, (len(pts), 2)), thickness, 1.5168, medium,
                    np.array([1500.0, 1510.0, 640.0, 500.0, 0, 0, 0, 0, 0]), n_params)


def _dim(values: gtsam.Values, key: int) -> int:
    """Tangent dimension: Vector keys (k, h) their size, Unit3 2, Pose3 6."""
    ch = chr(gtsam.Symbol(key).chr())
    return values.atVector(key).size if ch in "kh" else (2 if ch == "n" else 6)


def _update(values: gtsam.Values, key: int, delta: np.ndarray) -> None:
    ch = chr(gtsam.Symbol(key).chr())
    if ch in "cx":
        values.update(key, values.atPose3(key).retract(delta))
    elif ch == "n":
        values.update(key, values.atUnit3(key).retract(delta))
    else:
        values.update(key, values.atVector(key) + delta)


def _analytic_jacobians(factor: gtsam.CustomFactor, values: gtsam.Values) -> list[np.ndarray]:
    lin = factor.linearize(values)
    A, _ = lin.jacobian()  # whitened; sigma = 1 in these tests
    out, col = [], 0
    for key in factor.keys():
        d = _dim(values, key)
        out.append(A[:, col : col + d])
        col += d
    return out


@pytest.mark.parametrize("model,medium,with_camera,n_params", [
    (AriModel, 1.0, False, 4), (AriModel, 1.0, True, 9), (AriModel, 1.333, True, 4),
    (ExactModel, 1.0, True, 4), (ExactModel, 1.333, True, 9), (ExactModel, 1.333, False, 4),
])
def test_view_factor_jacobians_match_numerical(model, medium, with_camera, n_params):
    values = _values(with_camera, True, n_params)
    estimate_distance = medium != 1.0 or model is ExactModel
    keys = ViewKeys(K_.K(1), K_.X(0), K_.N, K_.C(1) if with_camera else None,
                    K_.H if estimate_distance else None, None if estimate_distance else None)
    factor = view_factor(model, _data(50.0, medium, n_params), keys, sigma_px=1.0)
    analytic = _analytic_jacobians(factor, values)
    numerical = [_numerical_fd(factor, values, k) for k in factor.keys()]
    for key, a, n in zip(factor.keys(), analytic, numerical):
        scale = np.abs(n).max() + 1e-9
        assert np.abs(a - n).max() / scale < 2e-5, (gtsam.Symbol(key).string(), np.abs(a - n).max(), scale)


def _numerical_fd(factor, values, key, step=1e-5):
    ch = chr(gtsam.Symbol(key).chr())
    d = _dim(values, key)
    cols = []
    for j in range(d):
        e = np.zeros(d)
        e[j] = step * (max(1.0, abs(values.atVector(key)[j])) if ch in "kh" else 1.0)
        vp, vm = gtsam.Values(values), gtsam.Values(values)
        _update(vp, key, e)
        _update(vm, key, -e)
        cols.append((factor.unwhitenedError(vp) - factor.unwhitenedError(vm)) / (2 * e[j]))
    return np.array(cols).T


def test_zero_thickness_equals_gtsam_projection_factor():
    """With no glass the ARI factor is a plain pinhole: compare with GTSAM's built-in factor."""
    values = _values(True, False, 4)
    data = _data(0.0, 1.0, 4)
    factor = view_factor(AriModel, data, ViewKeys(K_.K(1), K_.X(0), K_.N, K_.C(1)), sigma_px=1.0)
    ours = factor.unwhitenedError(values).reshape(-1, 2)
    fx, fy, cx, cy = values.atVector(K_.K(1))
    cal = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
    camera = gtsam.PinholeCameraCal3_S2(values.atPose3(K_.C(1)), cal)
    world_T_target = values.atPose3(K_.X(0))
    for p, m, r in zip(data.points_target, data.measured, ours):
        uv = camera.project(world_T_target.transformFrom(p))
        np.testing.assert_allclose(uv - m, r, atol=1e-9)


def test_wrong_shaped_jacobian_is_caught_in_python():
    """A Jacobian of the wrong shape would crash gtsam; the factor raises instead."""
    values = _values(True, False, 4)
    data = _data(50.0, 1.0, 4)
    bad = ViewData(data.points_target, data.measured, 50.0, 1.5168, 1.0, data.base_params, 5)  # 5 != 4 stored
    factor = view_factor(AriModel, bad, ViewKeys(K_.K(1), K_.X(0), K_.N, K_.C(1)), sigma_px=1.0)
    with pytest.raises((RuntimeError, ValueError)):  # the shape check's, or numpy's on the wrong-sized parameters
        factor.linearize(values)

"""Physics and numbers of the projection models (pinhole, ARI, exact Snell).

Reference camera: the paper's (12 mm lens, 3.45 um pixels: fx = 3478 px,
2448 x 2048 px) behind a 50 mm plate of n = 1.5168 tilted ~6 deg, near face at
h = 40 mm. Depths 100-800 mm along the normal.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from ari_sfm.geometry import rotation_from_rotvec
from ari_sfm.models import AriModel, ConvergenceError, ExactModel, PinholeModel, ari_shift_mm, solve_incidence
from ari_sfm.models.ari import ari_pixels, ari_project
from ari_sfm.models.exact import exact_pixels, exact_project

WIDTH, HEIGHT = 2448, 2048
FX = 12.0 / 3.45e-3  # 3478.26 px
THICKNESS, INDEX, DISTANCE = 50.0, 1.5168, 40.0
WATER = 1.333
DEPTHS = (100.0, 200.0, 400.0, 800.0)
DIST = np.array([-0.08, 0.12, 4e-4, -3e-4, -0.05])  # k1 k2 p1 p2 k3, a typical 12 mm lens


@pytest.fixture(scope="module")
def K() -> np.ndarray:
    return np.array([[FX, 0.0, 1230.3], [0.0, FX * 1.0005, 1019.8], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def pinhole(K) -> PinholeModel:
    return PinholeModel(K)


@pytest.fixture(scope="module")
def distorted(K) -> PinholeModel:
    return PinholeModel(K, DIST)


@pytest.fixture(scope="module")
def normal() -> np.ndarray:
    """Window normal tilted ~6 deg from the optical axis."""
    n = rotation_from_rotvec(np.radians([4.0, -4.5, 0.0])) @ np.array([0.0, 0.0, 1.0])
    assert 5.5 < np.degrees(np.arccos(n[2])) < 6.5
    return n


def image_grid(nu: int = 49, nv: int = 41) -> np.ndarray:
    """Pixels over the whole image, corners included."""
    u, v = np.meshgrid(np.linspace(0.0, WIDTH - 1.0, nu), np.linspace(0.0, HEIGHT - 1.0, nv))
    return np.stack([u.ravel(), v.ravel()], axis=1)


def points_at_depth(origins: np.ndarray, directions: np.ndarray, normal: np.ndarray, z: float) -> np.ndarray:
    """Points of the rays at depth z along the normal."""
    s = (z - origins @ normal) / (directions @ normal)
    return origins + s[:, None] * directions


def scene_points(normal: np.ndarray, seed: int = 0, n: int = 40) -> np.ndarray:
    """Random points in the field of view (through the pinhole) at depths 100-800 mm."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0.0, 0.0], [WIDTH, HEIGHT], (n, 2))
    xy = (uv - [1224.0, 1024.0]) / FX
    z = rng.uniform(100.0, 800.0, n)
    return np.concatenate([xy * z[:, None], z[:, None]], axis=1)


def central_diff(f, x0: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(N, 2, k) central differences of f: R^k -> (N, 2) around x0 with per-coordinate steps."""
    cols = []
    for i, h in enumerate(steps):
        e = np.zeros_like(x0)
        e[i] = h
        cols.append((f(x0 + e) - f(x0 - e)) / (2.0 * h))
    return np.stack(cols, axis=-1)


def assert_jacobian(J: np.ndarray, J_fd: np.ndarray, rtol: float = 1e-6, name: str = "") -> None:
    """Agreement relative to the largest entry of the block."""
    scale = max(np.max(np.abs(J_fd)), 1e-12)
    err = np.max(np.abs(J - J_fd))
    assert err <= rtol * scale, f"{name}: max error {err:.3e} vs scale {scale:.3e}"


def point_jacobian_fd(project, X: np.ndarray, step: float = 1e-3) -> np.ndarray:
    """(N, 2, 3) per-point central differences w.r.t. the point."""
    cols = []
    for i in range(3):
        e = np.zeros(3)
        e[i] = step
        cols.append((project(X + e) - project(X - e)) / (2.0 * step))
    return np.stack(cols, axis=-1)


# --------------------------------------------------------------------- pinhole
def test_pinhole_matches_opencv(distorted, K):
    X = scene_points(np.array([0.0, 0.0, 1.0]), n=200)
    uv_cv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, DIST)
    assert np.max(np.abs(distorted.project(X) - uv_cv.reshape(-1, 2))) < 1e-9


def test_pinhole_params_round_trip(distorted, K):
    p = distorted.params
    assert p.shape == (9,)
    assert np.array_equal(PinholeModel.from_params(p).params, p)
    assert np.allclose(distorted.K, K) and np.allclose(distorted.dist, DIST)


@pytest.mark.parametrize("model_name", ["pinhole", "distorted"])
def test_pinhole_round_trip(request, model_name):
    model = request.getfixturevalue(model_name)
    uv = image_grid()
    origins, d = model.backproject(uv)
    assert np.all(origins == 0.0)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-15)
    assert np.max(np.abs(model.project(d * 500.0) - uv)) < 1e-9


def test_pinhole_behind_camera_is_nan(pinhole):
    uv = pinhole.project(np.array([[1.0, 2.0, -5.0], [1.0, 2.0, 0.0], [1.0, 2.0, 5.0]]))
    assert np.all(np.isnan(uv[:2])) and np.all(np.isfinite(uv[2]))


def test_pinhole_jacobians(distorted):
    X = scene_points(np.array([0.0, 0.0, 1.0]))
    uv, J_point, J_params = distorted.project_with_jacobians(X)
    assert uv.shape == (len(X), 2) and J_point.shape == (len(X), 2, 3) and J_params.shape == (len(X), 2, 9)
    assert np.allclose(uv, distorted.project(X), rtol=0, atol=1e-12)
    assert_jacobian(J_point, point_jacobian_fd(distorted.project, X), name="J_point")
    p0 = distorted.params
    steps = np.where(np.arange(9) < 4, 1e-3, 1e-6)
    J_fd = central_diff(lambda p: PinholeModel.from_params(p).project(X), p0, steps)
    assert_jacobian(J_params, J_fd, name="J_params")


# ------------------------------------------------------------------------- ARI
def test_ari_shift_in_air_is_independent_of_distance(pinhole, normal):
    X = scene_points(normal)
    delta = ari_shift_mm(THICKNESS, INDEX)
    assert delta == pytest.approx(THICKNESS * (1 - 1 / INDEX))
    for h in (None, 10.0, 40.0):
        ari = AriModel(pinhole, normal, THICKNESS, INDEX, distance_mm=h)
        assert np.allclose(ari.apparent_points(X), X - delta * normal, rtol=0, atol=1e-12)


def test_ari_medium_apparent_depth(pinhole, normal):
    """z_app = h + d/n + (z - h - d)/n_m along the normal, lateral offset unchanged."""
    ari = AriModel(pinhole, normal, THICKNESS, INDEX, WATER, DISTANCE)
    X = scene_points(normal)
    X_app = ari.apparent_points(X)
    z, z_app = X @ normal, X_app @ normal
    expected = DISTANCE + THICKNESS / INDEX + (z - DISTANCE - THICKNESS) / WATER
    assert np.allclose(z_app, expected, rtol=0, atol=1e-12)
    assert np.allclose(X_app - z_app[:, None] * normal, X - z[:, None] * normal, rtol=0, atol=1e-12)
    with pytest.raises(ValueError):
        AriModel(pinhole, normal, THICKNESS, INDEX, WATER)


@pytest.mark.parametrize("medium", [1.0, WATER])
def test_ari_round_trip(distorted, normal, medium):
    ari = AriModel(distorted, normal, THICKNESS, INDEX, medium, DISTANCE)
    uv = image_grid()
    origins, d = ari.backproject(uv)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-15)
    if medium == 1.0:  # the virtual centre delta n_c
        assert np.allclose(origins, ari_shift_mm(THICKNESS, INDEX) * normal, rtol=0, atol=1e-12)
    for z in DEPTHS:
        X = points_at_depth(origins, d, normal, z)
        assert np.max(np.abs(ari.project(X) - uv)) < 1e-9


def test_ari_thickness_zero_is_pinhole(distorted, normal):
    X = scene_points(normal)
    ari = AriModel(distorted, normal, 0.0, INDEX)
    assert np.max(np.abs(ari.project(X) - distorted.project(X))) < 1e-12


def assert_window_jacobians(cls, X, distorted, normal, medium):
    """A window model's analytic Jacobians (point, normal, intrinsics, thickness, distance) against
    central differences; returns them. In air the distance must not matter (J_distance == 0)."""
    model = cls(distorted, normal, THICKNESS, INDEX, medium, DISTANCE)
    jac = model.project_with_jacobians(X)
    assert np.allclose(jac.uv, model.project(X), rtol=0, atol=1e-12)
    assert_jacobian(jac.J_point, point_jacobian_fd(model.project, X), name="J_point")

    def with_(normal_=normal, params=distorted.params, d=THICKNESS, h=DISTANCE):
        return cls(PinholeModel.from_params(params), normal_, d, INDEX, medium, h).project(X)

    assert_jacobian(jac.J_normal, central_diff(lambda v: with_(normal_=v), normal, [1e-7] * 3), name="J_normal")
    steps = np.where(np.arange(9) < 4, 1e-3, 1e-6)
    assert_jacobian(jac.J_params, central_diff(lambda p: with_(params=p), distorted.params, steps), name="J_params")
    J_d = central_diff(lambda v: with_(d=v[0]), np.array([THICKNESS]), [1e-3])[..., 0]
    assert_jacobian(jac.J_thickness, J_d, name="J_thickness")
    J_h = central_diff(lambda v: with_(h=v[0]), np.array([DISTANCE]), [1e-3])[..., 0]
    if medium == 1.0:
        assert np.max(np.abs(jac.J_distance)) < 1e-12 and np.max(np.abs(J_h)) < 1e-6
    else:
        assert_jacobian(jac.J_distance, J_h, name="J_distance")
    return jac


@pytest.mark.parametrize("medium", [1.0, WATER])
def test_ari_jacobians(distorted, normal, medium):
    X = scene_points(normal, seed=1)
    jac = assert_window_jacobians(AriModel, X, distorted, normal, medium)
    if medium == 1.0:
        assert np.all(jac.J_distance == 0.0)  # in air the paraxial shift does not depend on the distance at all


# ----------------------------------------------------------------------- exact
@pytest.mark.parametrize("medium", [1.0, WATER])
def test_exact_round_trip_whole_image(pinhole, normal, medium):
    exact = ExactModel(pinhole, normal, THICKNESS, INDEX, medium, DISTANCE)
    uv = image_grid()
    origins, d = exact.backproject(uv)
    # origins on the far face, unit directions obeying Snell: sin t = n_m sin t_m
    assert np.allclose(origins @ normal, DISTANCE + THICKNESS, rtol=0, atol=1e-10)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-15)
    _, v = pinhole.backproject(uv)
    sin_t = np.linalg.norm(np.cross(v, normal), axis=1)
    sin_tm = np.linalg.norm(np.cross(d, normal), axis=1)
    assert np.allclose(sin_t, medium * sin_tm, rtol=1e-12, atol=1e-15)
    for z in DEPTHS:
        X = points_at_depth(origins, d, normal, z)
        assert np.max(np.abs(exact.project(X) - uv)) < 1e-9


def test_exact_round_trip_with_distortion(distorted, normal):
    exact = ExactModel(distorted, normal, THICKNESS, INDEX, WATER, DISTANCE)
    uv = image_grid(25, 21)
    origins, d = exact.backproject(uv)
    X = points_at_depth(origins, d, normal, 300.0)
    assert np.max(np.abs(exact.project(X) - uv)) < 1e-9


def test_exact_thickness_zero_is_pinhole(distorted, normal):
    X = scene_points(normal)
    exact = ExactModel(distorted, normal, 0.0, INDEX, 1.0, DISTANCE)
    assert np.max(np.abs(exact.project(X) - distorted.project(X))) < 1e-12
    uv = image_grid(13, 11)
    origins, d = exact.backproject(uv)
    _, v = distorted.backproject(uv)
    assert np.max(np.abs(d - v)) < 1e-15 and np.max(np.abs(np.cross(origins, v))) < 1e-12


def test_exact_distance_unobservable_in_air(pinhole, normal):
    X = scene_points(normal)
    uv = [ExactModel(pinhole, normal, THICKNESS, INDEX, 1.0, h).project(X) for h in (5.0, 20.0, 40.0)]
    assert np.max(np.abs(uv[0] - uv[1])) < 1e-9 and np.max(np.abs(uv[2] - uv[1])) < 1e-9
    uv_w = [ExactModel(pinhole, normal, THICKNESS, INDEX, WATER, h).project(X) for h in (30.0, 40.0)]
    assert np.max(np.abs(uv_w[0] - uv_w[1])) > 1.0  # with water behind, h matters


def points_at_incidence(normal: np.ndarray, t: np.ndarray, z: float, medium: float) -> np.ndarray:
    """Points at depth z whose exact camera ray has incidence t (closed form from rho(t))."""
    u = np.tan(t)
    rho = DISTANCE * u
    for k in (INDEX, medium):
        length = THICKNESS if k == INDEX else z - DISTANCE - THICKNESS
        rho = rho + length * np.sin(t) / np.sqrt(k * k - np.sin(t) ** 2)
    side = np.cross(normal, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    return z * normal + rho[:, None] * side


@pytest.mark.parametrize("medium", [1.0, WATER])
def test_exact_equals_ari_as_incidence_goes_to_zero(pinhole, normal, medium):
    exact = ExactModel(pinhole, normal, THICKNESS, INDEX, medium, DISTANCE)
    ari = AriModel(pinhole, normal, THICKNESS, INDEX, medium, DISTANCE)
    t = np.array([1e-2, 1e-3, 1e-4, 0.0])
    X = points_at_incidence(normal, t, 450.0, medium)
    # the exact ray really has incidence t
    assert np.allclose(np.arccos(np.clip(exact.ray_directions(X) @ normal, -1, 1)), t, atol=1e-7)
    err = np.linalg.norm(exact.project(X) - ari.project(X), axis=1)
    assert np.all(err[1:] < 1e-6)
    assert err[3] < 1e-9
    # and the difference is O(t^3): err / t^3 about constant
    c = err[:2] / t[:2] ** 3
    assert 0.5 < c[1] / c[0] < 2.0


def test_paraxial_error_grows_like_t_cubed(pinhole):
    """Air, normal on the optical axis, z = 450 mm: ARI misses by ~75 t^3 px at fx = 3478.

    Expanding g(u) = u / sqrt(n^2 + (n^2 - 1) u^2) to third order gives
    du = d (n^2 - 1) u^3 / (2 n^3 (z - delta)), i.e. fx du px.
    """
    axis = np.array([0.0, 0.0, 1.0])
    exact = ExactModel(pinhole, axis, THICKNESS, INDEX, 1.0, DISTANCE)
    ari = AriModel(pinhole, axis, THICKNESS, INDEX)
    z = 450.0
    t = np.array([0.025, 0.05, 0.1, 0.2])
    X = points_at_incidence(axis, t, z, 1.0)
    err = np.linalg.norm(exact.project(X) - ari.project(X), axis=1)
    assert err[2] == pytest.approx(0.076, rel=1.0)  # within a factor 2
    assert 0.038 < err[2] < 0.152
    coeff = FX * THICKNESS * (INDEX**2 - 1) / (2 * INDEX**3 * (z - ari_shift_mm(THICKNESS, INDEX)))
    assert coeff == pytest.approx(75.0, rel=0.05)
    assert np.allclose(err[:3] / np.tan(t[:3]) ** 3, coeff, rtol=0.1)
    assert 7.0 < err[2] / err[1] < 9.0  # cubic growth


def test_newton_converges_in_few_iterations(pinhole, normal):
    uv = image_grid()
    for medium in (1.0, WATER):
        exact = ExactModel(pinhole, normal, THICKNESS, INDEX, medium, DISTANCE)
        origins, d = exact.backproject(uv)
        for z in DEPTHS:
            assert exact.newton_iterations(points_at_depth(origins, d, normal, z)) <= 8
    # the solution is exact to rounding: rho(u) = rho with relative residual ~1e-16
    rng = np.random.default_rng(3)
    rho, L = rng.uniform(0.0, 500.0, 1000), rng.uniform(1.0, 700.0, 1000)
    w, iterations = solve_incidence(rho, L, DISTANCE, THICKNESS, INDEX, WATER)
    assert iterations <= 8
    u = w * rho
    g = [u / np.sqrt(k * k + (k * k - 1) * u * u) for k in (INDEX, WATER)]
    residual = DISTANCE * u + THICKNESS * g[0] + L * g[1] - rho
    assert np.max(np.abs(residual) / np.maximum(rho, 1.0)) < 1e-14
    with pytest.raises(ConvergenceError):  # a capped solve raises rather than returning a guess
        solve_incidence(rho, L, DISTANCE, THICKNESS, INDEX, WATER, max_iter=2)


def test_exact_points_before_far_face_are_nan(pinhole, normal):
    exact = ExactModel(pinhole, normal, THICKNESS, INDEX, WATER, DISTANCE)
    X = np.array([normal * 20.0, normal * 60.0, normal * (DISTANCE + THICKNESS - 1e-6), normal * 300.0 + [5.0, 0, 0]])
    uv = exact.project(X)
    assert np.all(np.isnan(uv[:3])) and np.all(np.isfinite(uv[3]))
    jac = exact.project_with_jacobians(X)
    assert np.all(np.isnan(jac.J_point[:3])) and np.all(np.isfinite(jac.J_point[3]))
    with pytest.raises(ValueError):
        ExactModel(pinhole, normal, THICKNESS, INDEX, WATER)


@pytest.mark.parametrize("medium", [1.0, WATER])
def test_exact_jacobians(distorted, normal, medium):
    X = scene_points(normal, seed=2)
    X[0] = 333.0 * normal  # on the normal axis: rho = 0
    jac = assert_window_jacobians(ExactModel, X, distorted, normal, medium)
    assert np.all(np.isfinite(jac.J_point))


def test_jacobian_normal_chains_with_tangent_basis(pinhole, normal):
    """J_normal @ B equals the derivative along the tangent directions of the normal."""
    B = np.linalg.svd(normal[None, :])[2][1:].T  # (3, 2) orthonormal, orthogonal to normal
    X = scene_points(normal, seed=4)
    for model in (AriModel(pinhole, normal, THICKNESS, INDEX, WATER, DISTANCE),
                  ExactModel(pinhole, normal, THICKNESS, INDEX, WATER, DISTANCE)):
        J = model.project_with_jacobians(X).J_normal @ B
        cls, args = type(model), (THICKNESS, INDEX, WATER, DISTANCE)

        def along(xi, cls=cls, args=args):
            n = normal + B @ xi
            return cls(pinhole, n / np.linalg.norm(n), *args).project(X)

        assert_jacobian(J, central_diff(along, np.zeros(2), [1e-7, 1e-7]), name=cls.__name__)


@pytest.mark.parametrize("medium", [1.0, WATER])
def test_ari_is_the_first_newton_step(pinhole, normal, medium):
    """Newton from u = 0 first lands on w = 1/rho'(0) = 1/z_app: the ARI ray n_c + r / z_app."""
    ari = AriModel(pinhole, normal, THICKNESS, INDEX, medium, DISTANCE)
    X = scene_points(normal, seed=5)
    z = X @ normal
    r = X - z[:, None] * normal
    w1 = 1.0 / (DISTANCE + THICKNESS / INDEX + (z - DISTANCE - THICKNESS) / medium)
    assert np.max(np.abs(pinhole.project(normal + w1[:, None] * r) - ari.project(X))) < 1e-9


@pytest.mark.parametrize("medium", [1.0, 1.333])
@pytest.mark.parametrize("kernel,cls", [(ari_project, AriModel), (exact_project, ExactModel)])
def test_batched_kernel_with_per_point_thickness_is_the_model(kernel, cls, distorted, normal, medium):
    """The kernel the numpy bundle adjustment calls, with one plate thickness per point (stacked plates),
    gives what the model gives plate by plate; with n_params=4 its intrinsics Jacobian is the first 4 columns."""
    X = scene_points(normal, seed=3, n=60)
    d = np.where(np.arange(60) % 3 == 0, 50.0, 70.0)
    p = distorted.params
    for n_params in (9, 4):
        params = p if n_params == 9 else np.concatenate([p[:4], np.zeros(5)])
        J = kernel(X, params, 2.0 * normal, d, 1.5168, medium, 30.0, n_params)
        for t in (50.0, 70.0):
            rows = d == t
            ref = cls(PinholeModel.from_params(params), 2.0 * normal, t, 1.5168,
                      medium, 30.0).project_with_jacobians(X[rows])
            for name in ref._fields:
                want = getattr(ref, name)[..., :n_params] if name == "J_params" else getattr(ref, name)
                np.testing.assert_allclose(getattr(J, name)[rows], want, rtol=1e-12, atol=1e-12 * np.abs(want).max(),
                                           err_msg=name)
        pixels = {ari_project: ari_pixels, exact_project: exact_pixels}[kernel]  # the pixels alone: the same
        np.testing.assert_array_equal(pixels(X, params, 2.0 * normal, d, 1.5168, medium, 30.0), J.uv)

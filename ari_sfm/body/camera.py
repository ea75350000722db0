"""The camera that matches a 3D body's points to its dots: a pinhole with one radial term, or the
exact refractive model through a declared window; fitted to matched points, started from clicked ones.

Parameters ``[r (3), t (3), log f, cx, cy, k1]``: ``r`` the rotation vector of ``cam_from_body``, ``t``
its translation (mm), ``f`` the focal length (px; fy = aspect x f), (cx, cy) the principal point (OpenCV
pixels), ``k1`` the first radial coefficient (OpenCV's). When the window's plane is known in the body's
frame (:class:`BodyWindow`) the exact Snell model (:func:`ari_sfm.models.exact.exact_project`) projects
instead of the pinhole, the window placed by the camera's pose.

Which parameters are free grows with the matched points (:data:`STAGES`). The focal length, the principal
point and k1 carry weak priors toward their start (one pixel of residual for FOCAL_SIGMA_LOG in log f,
PRINCIPAL_POINT_SIGMA x the image width, K1_SIGMA) and bounds (the focal length within FOCAL_BOUNDS x the
image's longer side, the principal point inside the image's central half-size box, |k1| <= K1_BOUND).

The start (:func:`resection_starts`) is fitted to >= 4 clicked points: the distinct cameras found over a
sweep of focal lengths, best first.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.optimize import least_squares

from ari_sfm.geometry import rotation_angle_deg, rotation_from_rotvec, skew
from ari_sfm.models.exact import ConvergenceError, exact_pixels, exact_project
from ari_sfm.models.pinhole import pinhole_pixels, project_points

log = logging.getLogger(__name__)

POSE, FOCAL, CENTRE, K1 = (0, 1, 2, 3, 4, 5), (6,), (7, 8), (9,)
STAGES = ((0, POSE + FOCAL), (10, POSE + FOCAL + CENTRE), (20, POSE + FOCAL + CENTRE + K1))  # (>= matches, free)
PRINCIPAL_POINT_SIGMA = 0.1  # prior: the principal point within ~10 % of the longer side of the start's (the centre)
PRINCIPAL_POINT_BOUND = 0.5  # and never farther than half the width (height) from the image centre
K1_SIGMA = 0.5  # prior on k1
K1_BOUND = 2.0  # |k1| at most this
FOCAL_SIGMA_LOG = 0.7  # prior: the focal length within a factor ~2 of its start (few points leave it loose)
FOCAL_BOUNDS = (0.1, 100.0)  # x the image's longer side
FOCAL_SWEEP = np.geomspace(0.25, 25.0, 41)  # x the image's longer side: the focal lengths tried without a hint
DISTINCT_DEG = 5.0  # starts whose rotations differ less and whose focal lengths differ less than
DISTINCT_LOG_FOCAL = 0.2  # 20 % are one start
# clicks are good to a few pixels: sweep focal lengths fitting them this close to the best are tried
CLICK_NOISE_PX = 3.0
MAX_SPREAD = 5  # at most this many of them
UNPROJECTABLE_PX = 1e4  # residual of a point the model cannot project (behind the camera or the window)


@dataclass(frozen=True)
class BodyWindow:
    """A flat window in the body's frame.

    Attributes:
        normal: Unit normal (3,), pointing from the cameras toward the body.
        point_mm: A point (3,) of the window's camera-side face (mm, body frame).
        thickness_mm: Plate thickness (mm).
        index: Refractive index of the glass.
        medium_index: Refractive index of the medium behind the window.
    """

    normal: np.ndarray
    point_mm: np.ndarray
    thickness_mm: float
    index: float
    medium_index: float


@dataclass(frozen=True)
class MatchCamera:
    """A camera for matching (parameters as in the module docstring).

    Attributes:
        params: ``[r (3), t (3), log f, cx, cy, k1]`` (10,).
        aspect: fy / fx.
        window: The window in the body's frame; None for a pinhole with k1.
    """

    params: np.ndarray
    aspect: float = 1.0
    window: BodyWindow | None = None

    @property
    def focal_px(self) -> float:
        """Focal length fx (px)."""
        return float(math.exp(self.params[6]))

    @property
    def rotation(self) -> np.ndarray:
        """cam_from_body rotation."""
        return rotation_from_rotvec(self.params[:3])

    def intrinsics(self) -> np.ndarray:
        """[fx, fy, cx, cy, k1, k2, p1, p2, k3] (ari-sfm's intrinsic vector)."""
        f = self.focal_px
        return np.array([f, self.aspect * f, self.params[7], self.params[8], self.params[9], 0, 0, 0, 0.0])

    def project(self, xyz: np.ndarray) -> np.ndarray:
        """Project body points to pixels.

        Args:
            xyz: Body points (N, 3), mm, body frame.

        Returns:
            Pixels (N, 2) (OpenCV convention); NaN where the model has no image of a point.
        """
        return _project(self.rotation, self.params, self, np.asarray(xyz, float), jacobian=False)[0]

    def with_window(self, window: BodyWindow | None) -> MatchCamera:
        """This camera projecting through ``window`` (None: a pinhole with k1)."""
        return replace(self, window=window)


def free_parameters(matches: int) -> tuple[int, ...]:
    """The parameters fitted with ``matches`` matched points (:data:`STAGES`)."""
    return [free for need, free in STAGES if matches >= need][-1]


def fit_camera(camera: MatchCamera, xyz: np.ndarray, uv: np.ndarray, free: tuple[int, ...],
               image_size: tuple[int, int], robust_px: float | None = None,
               prior: MatchCamera | None = None) -> MatchCamera:
    """Fit some of a camera's parameters to matched points.

    The focal length, the principal point and k1 are held to ``prior``'s by the weak priors and bounds of
    the module docstring. The rotation is fitted as a left increment of the start's (``Exp(d) R``), with
    an analytic Jacobian.

    Args:
        camera: The start.
        xyz: Body points (N, 3), mm.
        uv: Their measured pixels (N, 2).
        free: Indices of the parameters fitted (e.g. an entry of :data:`STAGES`).
        image_size: (width, height) px, for the priors and bounds.
        robust_px: Scale of a soft-L1 loss (a few wrong matches do not pull the fit); None for least squares.
        prior: The camera whose focal length, principal point and k1 the priors hold to; None for ``camera``.

    Returns:
        ``camera`` with its ``free`` parameters fitted.
    """
    columns = np.array(sorted(free))
    R0 = camera.rotation
    start = camera.params.copy()
    start[:3] = 0.0  # the increment d
    held = (camera if prior is None else prior).params
    sigmas = np.array([FOCAL_SIGMA_LOG, PRINCIPAL_POINT_SIGMA * max(image_size), PRINCIPAL_POINT_SIGMA *
                       max(image_size), K1_SIGMA])
    xyz, uv = np.asarray(xyz, float), np.asarray(uv, float)

    def unpack(x: np.ndarray) -> np.ndarray:
        p = start.copy()
        p[columns] = x
        return p

    def residuals(x: np.ndarray) -> np.ndarray:
        p = unpack(x)
        projected, _ = _project(rotation_from_rotvec(p[:3]) @ R0, p, camera, xyz, jacobian=False)
        r = (projected - uv).ravel()
        return np.concatenate([np.where(np.isfinite(r), r, UNPROJECTABLE_PX), (p[6:10] - held[6:10]) / sigmas])

    def jacobian(x: np.ndarray) -> np.ndarray:
        p = unpack(x)
        _, J = _project(rotation_from_rotvec(p[:3]) @ R0, p, camera, xyz, jacobian=True)
        assert J is not None  # asked for
        J = np.nan_to_num(J.reshape(-1, 10), nan=0.0, posinf=0.0, neginf=0.0)
        weak = np.zeros((4, 10))
        weak[np.arange(4), np.arange(6, 10)] = 1.0 / sigmas
        return np.concatenate([J, weak])[:, columns]

    lower, upper = _bounds(image_size)
    x0 = np.clip(start[columns], lower[columns] + 1e-9, upper[columns] - 1e-9)
    result = least_squares(residuals, x0, jac=jacobian, bounds=(lower[columns], upper[columns]), method="trf",
                           x_scale="jac", loss="linear" if robust_px is None else "soft_l1",
                           f_scale=robust_px or 1.0, max_nfev=50 * len(columns))
    params = unpack(result.x)
    params[:3] = cv2.Rodrigues(rotation_from_rotvec(params[:3]) @ R0)[0].ravel()
    return replace(camera, params=params)


def _project(R: np.ndarray, params: np.ndarray, camera: MatchCamera, xyz: np.ndarray, jacobian: bool
             ) -> tuple[np.ndarray, np.ndarray | None]:
    """Pixels (N, 2) of body points for the rotation ``R`` and ``params[3:]`` (NaN where no image) and, with
    ``jacobian``, their derivatives (N, 2, 10) with respect to [d (a left rotation increment), t, log f, cx,
    cy, k1]: the models' analytic Jacobians chained (``X = Exp(d) R xyz + t``; through a window ``n_c =
    Exp(d) R n`` and ``h = n . p + n_c . t``)."""
    t = params[3:6]
    f = math.exp(params[6])
    intrinsics = np.array([f, camera.aspect * f, params[7], params[8], params[9], 0, 0, 0, 0.0])
    X = xyz @ R.T + t
    J_distance = J_normal = normal = None
    if camera.window is None:
        if not jacobian:
            return pinhole_pixels(X, intrinsics), None
        uv, J_point, J_params = project_points(X, intrinsics, n_params=5)
    else:
        w = camera.window
        normal = R @ w.normal
        h = float(w.normal @ w.point_mm + normal @ t)
        if not h > 0:
            return np.full((len(X), 2), np.nan), (np.zeros((len(X), 2, 10)) if jacobian else None)
        try:
            if not jacobian:
                return exact_pixels(X, intrinsics, normal, w.thickness_mm, w.index, w.medium_index,
                                    h).reshape(-1, 2), None
            out = exact_project(X, intrinsics, normal, w.thickness_mm, w.index, w.medium_index, h, n_params=5)
        except ConvergenceError:
            return np.full((len(X), 2), np.nan), (np.zeros((len(X), 2, 10)) if jacobian else None)
        uv, J_point, J_params, J_normal, J_distance = out.uv, out.J_point, out.J_params, out.J_normal, out.J_distance
    uv = uv.reshape(-1, 2)
    if not jacobian:
        return uv, None
    assert J_point is not None and J_params is not None  # asked for (jacobian)
    J = np.empty((len(X), 2, 10))
    J[:, :, 0:3] = -np.einsum("nij,njk->nik", J_point, skew(X - t))  # d(Exp(d) R xyz)/dd = -[R xyz]x
    J[:, :, 3:6] = J_point
    J[:, :, 6] = f * (J_params[:, :, 0] + camera.aspect * J_params[:, :, 1])
    J[:, :, 7:10] = J_params[:, :, 2:5]
    if normal is not None:
        assert J_normal is not None and J_distance is not None  # through a window
        J[:, :, 0:3] -= J_normal @ skew(normal)  # d n_c / dd = -[n_c]x
        J[:, :, 0:3] += J_distance[:, :, None] * np.cross(normal, t)  # dh/dd = (n_c x t)^T
        J[:, :, 3:6] += J_distance[:, :, None] * normal  # dh/dt = n_c^T
    return uv, J


def _bounds(image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of the 10 parameters (the focal length, the principal point and k1 are bounded)."""
    width, height = image_size
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    half = PRINCIPAL_POINT_BOUND * np.array([width, height], float)
    lower = np.full(10, -np.inf)
    upper = np.full(10, np.inf)
    lower[6], upper[6] = (math.log(b * max(width, height)) for b in FOCAL_BOUNDS)
    lower[7:9], upper[7:9] = centre - half, centre + half
    lower[9], upper[9] = -K1_BOUND, K1_BOUND
    return lower, upper


def camera_residuals(camera: MatchCamera, xyz: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Projection minus measurement for each point.

    Args:
        camera: The camera.
        xyz: Body points (N, 3), mm.
        uv: Their measured pixels (N, 2).

    Returns:
        Residuals flattened (2N,), px; UNPROJECTABLE_PX where a point has no image.
    """
    r = (camera.project(xyz) - uv).ravel()
    return np.where(np.isfinite(r), r, UNPROJECTABLE_PX)


def rms_px(camera: MatchCamera, xyz: np.ndarray, uv: np.ndarray) -> float:
    r = camera_residuals(camera, xyz, uv)
    return float(np.sqrt(np.mean(r.reshape(-1, 2) ** 2) * 2.0))


def resection_starts(xyz: np.ndarray, uv: np.ndarray, image_size: tuple[int, int], focal_px: float | None = None,
                     aspect: float = 1.0, window: BodyWindow | None = None) -> list[tuple[MatchCamera, float]]:
    """Start cameras fitted to >= 4 clicked points.

    Pose and focal length are fitted; the principal point is the image centre and k1 zero. The focal
    lengths tried: the hint, the local minima over :data:`FOCAL_SWEEP` of the SQPnP pose's RMS, and,
    where the clicks leave the focal length loose (every sweep value whose RMS is within CLICK_NOISE_PX
    of the best: three clicks in a row, a small cluster), up to MAX_SPREAD values spread over that range;
    each is refined on the clicks. With a ``window`` each is refitted with the exact model.

    Args:
        xyz: Clicked body points (N, 3), mm.
        uv: Their clicked pixels (N, 2).
        image_size: (width, height) px.
        focal_px: A focal length to try first (px), or None.
        aspect: fy / fx.
        window: The window in the body's frame, or None (pinhole).

    Returns:
        The distinct cameras (rotations more than DISTINCT_DEG or focal lengths more than
        DISTINCT_LOG_FOCAL apart), each with its RMS on the clicks (px), best first.
    """
    xyz, uv = np.asarray(xyz, float), np.asarray(uv, float)
    width, height = image_size
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    sweep = [_pnp(xyz, uv, f, centre, aspect) for f in FOCAL_SWEEP * max(width, height)]
    errors = np.array([np.inf if c is None else rms_px(c, xyz, uv) for c in sweep])
    padded = np.concatenate([[np.inf], errors, [np.inf]])
    chosen = {k for k in range(len(sweep)) if np.isfinite(errors[k]) and padded[k + 1] <= padded[k]
              and padded[k + 1] <= padded[k + 2]}
    loose = np.nonzero(errors <= np.min(errors) + CLICK_NOISE_PX)[0]
    if len(loose) > 1:
        chosen |= {int(loose[round(j)]) for j in np.linspace(0, len(loose) - 1, MAX_SPREAD)}
    candidates = [sweep[k] for k in sorted(chosen)]
    if focal_px is not None:
        candidates.insert(0, _pnp(xyz, uv, float(focal_px), centre, aspect))
    found: list[tuple[MatchCamera, float]] = []
    for camera in candidates:
        if camera is None:
            continue
        camera = fit_camera(camera, xyz, uv, POSE + FOCAL, image_size)
        if window is not None:
            camera = fit_camera(camera.with_window(window), xyz, uv, POSE + FOCAL, image_size)
        error = rms_px(camera, xyz, uv)
        if np.isfinite(error) and error < UNPROJECTABLE_PX / 10:
            found.append((camera, error))
    found.sort(key=lambda c: c[1])
    distinct: list[tuple[MatchCamera, float]] = []
    for camera, error in found:
        if all(rotation_angle_deg(camera.rotation, other.rotation) > DISTINCT_DEG
               or abs(camera.params[6] - other.params[6]) > DISTINCT_LOG_FOCAL for other, _ in distinct):
            distinct.append((camera, error))
    return distinct


def _pnp(xyz: np.ndarray, uv: np.ndarray, focal_px: float, centre: np.ndarray, aspect: float) -> MatchCamera | None:
    """OpenCV's SQPnP pose for a pinhole of focal length ``focal_px`` and principal point ``centre``."""
    K = np.array([[focal_px, 0, centre[0]], [0, aspect * focal_px, centre[1]], [0, 0, 1.0]])
    try:
        ok, rvec, tvec = cv2.solvePnP(xyz.reshape(-1, 1, 3), uv.reshape(-1, 1, 2), K, None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return None
    if not ok:
        return None
    return MatchCamera(np.concatenate([rvec.ravel(), tvec.ravel(), [math.log(focal_px)], centre, [0.0]]), aspect)

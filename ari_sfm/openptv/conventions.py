"""OpenPTV's camera conventions and their conversion to ari-sfm's (OpenCV / COLMAP).

Taken from liboptv's sources (OpenPTV/openptv):

- Rotation (``calibration.c: rotation_matrix``): ``dm`` from omega, phi, kappa
  (radians) as written there; ``dm`` maps camera axes to world axes: a ray of
  sensor point (x, y) has world direction ``dm (x, y, -cc)``
  (``ray_tracing.c: old_ray_tracing``), and a world point X images at
  ``x = -cc X_c / Z_c``, ``y = -cc Y_c / Z_c`` with ``X_c = dm^T (X - X0)``
  (``imgcoord.c: flat_image_coord``). So OpenPTV's camera frame has x right,
  y up and looks along -z: ``R_opencv = diag(1, -1, -1) dm^T``, the centre is X0.
- Sensor (``trafo.c``): metric (mm) coordinates, y up, origin at pixel
  (imx/2, imy/2): ``x_pix = x / pix_x + imx / 2``, ``y_pix = imy / 2 - y / pix_y``
  (``old_metric_to_pixel``). The principal point is at metric (xh, yh), cc is
  the focal length in mm. Distortion (``flat_to_dist``, ``distort_brown_affin``)
  acts on the flat point shifted by (xh, yh), i.e. about the *sensor centre*, in
  mm: Brown radial k1 k2 k3 (r in mm), decentering p1 p2 (OpenPTV's p1 is
  OpenCV's p2 up to sign and scale), then ``x' = scx x - sin(she) y``,
  ``y' = cos(she) y``.
- Pixels (``segmentation.c: targ_rec, peak_fit_new``): a target's centre is
  ``0.5 + sum(i g) / sum(g)`` over pixel indices i: OpenPTV's pixel (0, 0) is
  the top-left *corner* of the image; OpenCV's is the centre of the top-left
  pixel. ``u_opencv = x_openptv - 0.5``.
- Window (``multimed.c: trans_Cam_Point``, ``ray_tracing.c``): the glass
  vector G points from the water toward the cameras; |G| is the distance from
  the world origin to the glass-water face (``G . X = |G|^2``); the camera-side
  face is ``d`` further, at ``G^ . X = |G| + d``. Light goes n1 (camera side)
  -> n2 (glass, thickness d) -> n3 (``ptv.par``).

ari-sfm's window normal points from the cameras into the scene: ``normal = -G^``,
and ``point_mm`` on the camera-side face is ``(|G| + d) G^``.

- Particle detection (``segmentation.c: targ_rec``, ``parameters/targ_rec.par``): a
  target is a local maximum above the camera's grey threshold on the high-passed
  image (``preprocess_image``: the image minus its local background), grown over
  4-connected pixels above that threshold; kept with nnmin..nnmax pixels, a width
  nxmin..nxmax and a height nymin..nymax (px), and a grey sum of its pixels above
  sumg_min. ari-sfm's detector counts an image's pixels the same way, above its
  own threshold (the local noise's) and the lab's grey threshold, on the image
  minus its local background (``detect_settings_from_target_par``).
"""
from __future__ import annotations

import numpy as np

from ari_sfm.geometry import Pose

from .files import AddPar, Orientation, TargetPar

OPENPTV_PIXEL_OFFSET = 0.5  # u_opencv = x_openptv - OPENPTV_PIXEL_OFFSET (segmentation.c adds 0.5)
FLIP_YZ = np.diag([1.0, -1.0, -1.0])  # OpenPTV camera axes (x right, y up, looking along -z) -> OpenCV


def rotation_matrix(omega: float, phi: float, kappa: float) -> np.ndarray:
    """Compute liboptv's ``rotation_matrix`` (calibration.c).

    Args:
        omega: the first angle (rad).
        phi: the second angle (rad).
        kappa: the third angle (rad).

    Returns:
        dm, (3, 3): OpenPTV camera axes -> world axes.
    """
    co, so = np.cos(omega), np.sin(omega)
    cp, sp = np.cos(phi), np.sin(phi)
    ck, sk = np.cos(kappa), np.sin(kappa)
    return np.array([
        [cp * ck, -cp * sk, sp],
        [co * sk + so * sp * ck, co * ck - so * sp * sk, -so * cp],
        [so * sk - co * sp * ck, so * ck + co * sp * sk, co * cp],
    ])


def angles_from_matrix(dm: np.ndarray) -> np.ndarray:
    """omega, phi, kappa (rad, phi in [-pi/2, pi/2]) with ``rotation_matrix(*angles) == dm``."""
    phi = np.arcsin(np.clip(dm[0, 2], -1.0, 1.0))
    omega = np.arctan2(-dm[1, 2], dm[2, 2])
    kappa = np.arctan2(-dm[0, 1], dm[0, 0])
    return np.array([omega, phi, kappa])


def cam_from_world(ori: Orientation) -> Pose:
    """The OpenCV camera pose of an ``.ori`` (dm from its angles, as liboptv's read_calibration does)."""
    R = FLIP_YZ @ rotation_matrix(*ori.angles).T
    return Pose(R, -R @ ori.position)


def exterior(pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position X0, angles, dm) of an OpenCV cam_from_world pose, in the pose's world frame."""
    dm = pose.R.T @ FLIP_YZ
    return pose.inverse().t, angles_from_matrix(dm), rotation_matrix(*angles_from_matrix(dm))


def window_plane(glass: np.ndarray, thickness_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Convert an OpenPTV glass vector to ari-sfm's window plane.

    Args:
        glass: the glass vector G, (3,) mm (from the water toward the cameras, |G| the distance of the
            glass-water face from the world origin).
        thickness_mm: the glass thickness d.

    Returns:
        (normal, point_mm): the unit normal into the scene (``-G^``) and a point of the camera-side face
        (``(|G| + d) G^``), both (3,).
    """
    length = float(np.linalg.norm(glass))
    unit = np.asarray(glass, float) / length
    return 0.0 - unit, unit * (length + thickness_mm)  # 0.0 - x: no -0.0 in files


def glass_vector(normal: np.ndarray, point_mm: np.ndarray, thickness_mm: float) -> np.ndarray:
    """Convert a window plane to OpenPTV's glass vector (the inverse of :func:`window_plane`).

    Args:
        normal: the window's normal into the scene, (3,).
        point_mm: a point of the camera-side face, (3,) mm.
        thickness_mm: the glass thickness.

    Returns:
        The glass vector G, (3,) mm.

    Raises:
        ValueError: the world origin is not behind the glass-water face (|G| would be <= 0: OpenPTV cannot
            express that window).
    """
    unit = -np.asarray(normal, float) / np.linalg.norm(normal)
    length = float(unit @ np.asarray(point_mm, float)) - thickness_mm
    if length <= 0:
        raise ValueError(f"the origin is {-length:.3f} mm on the camera side of the glass-water face")
    return unit * length


# --------------------------------------------------------------------------- interior orientation


def flat_to_pixel(x_flat: np.ndarray, y_flat: np.ndarray, xh: float, yh: float, addpar: AddPar,
                  imx: int, imy: int, pix_x: float, pix_y: float) -> np.ndarray:
    """Image flat sensor points to OpenCV pixels, as liboptv does.

    liboptv's ``flat_to_dist`` then ``metric_to_pixel``, minus the half-pixel offset.

    Args:
        x_flat: (N,) flat sensor x, mm.
        y_flat: (N,) flat sensor y, mm (y up).
        xh: the principal point's metric x, mm.
        yh: the principal point's metric y, mm.
        addpar: the distortion and affine parameters.
        imx: the image width, px.
        imy: the image height, px.
        pix_x: the pixel width, mm.
        pix_y: the pixel height, mm.

    Returns:
        (N, 2) OpenCV pixels.
    """
    x = np.asarray(x_flat, float) + xh
    y = np.asarray(y_flat, float) + yh
    r2 = x * x + y * y
    radial = addpar.k1 * r2 + addpar.k2 * r2 * r2 + addpar.k3 * r2 * r2 * r2
    xd = x + x * radial + addpar.p1 * (r2 + 2 * x * x) + 2 * addpar.p2 * x * y
    yd = y + y * radial + addpar.p2 * (r2 + 2 * y * y) + 2 * addpar.p1 * x * y
    x1 = addpar.scx * xd - np.sin(addpar.she) * yd
    y1 = np.cos(addpar.she) * yd
    u = x1 / pix_x + imx / 2.0 - OPENPTV_PIXEL_OFFSET
    v = imy / 2.0 - y1 / pix_y - OPENPTV_PIXEL_OFFSET
    return np.stack([u, v], axis=-1)


def interior_from_opencv(K: np.ndarray, dist: np.ndarray, image_size: tuple[int, int], pix_x: float,
                         pix_y: float) -> tuple[float, float, float, AddPar]:
    """Convert OpenCV's K and dist to an OpenPTV interior orientation in closed form.

    Exact when the distortion is zero or the principal point is at the sensor centre (OpenPTV distorts
    about the sensor centre, OpenCV about the principal point; else see :func:`fit_interior`).
    cc = fy pix_y; scx = fx pix_x / cc; xh, yh put the principal point at (cx, cy).

    Args:
        K: the (3, 3) camera matrix, px.
        dist: OpenCV's [k1 k2 p1 p2 k3] (shorter: zero-padded); None: no distortion.
        image_size: (width, height) px.
        pix_x: the pixel width, mm.
        pix_y: the pixel height, mm.

    Returns:
        (xh, yh, cc, addpar): principal point and focal length in mm, distortion and affine parameters.
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    imx, imy = image_size
    cc = fy * pix_y
    scx = fx * pix_x / cc
    xh = (cx + OPENPTV_PIXEL_OFFSET - imx / 2.0) * pix_x / scx
    yh = (imy / 2.0 - cy - OPENPTV_PIXEL_OFFSET) * pix_y
    k1, k2, p1, p2, k3 = np.resize(np.asarray(dist, float), 5) if dist is not None else np.zeros(5)
    # x_mm = cc x_n, y_mm = -cc y_n (before scx): r_mm = cc r_n; OpenCV's p2 is OpenPTV's p1 (see module)
    addpar = AddPar(k1 / cc**2, k2 / cc**4, k3 / cc**6, p2 / cc, -p1 / cc, scx, 0.0)
    return xh, yh, cc, addpar


def fit_interior(K: np.ndarray, dist: np.ndarray, image_size: tuple[int, int], pix_x: float, pix_y: float,
                 grid: int = 25) -> tuple[float, float, float, AddPar, float]:
    """Fit an OpenPTV interior orientation to OpenCV's K and dist by least squares.

    Fits xh, yh, cc, k1 k2 k3 p1 p2 and scx (she = 0) so that the normalised rays of a pixel grid image
    where OpenCV's K and dist image them; starts from :func:`interior_from_opencv`.

    Args:
        K: the (3, 3) camera matrix, px.
        dist: OpenCV's distortion coefficients.
        image_size: (width, height) px.
        pix_x: the pixel width, mm.
        pix_y: the pixel height, mm.
        grid: the grid's points per side (``grid`` x ``grid`` over the image).

    Returns:
        (xh, yh, cc, addpar, max error px): the interior and its largest pixel error on the grid.
    """
    from scipy.optimize import least_squares

    from ari_sfm.models import PinholeModel

    w, h = image_size
    pinhole = PinholeModel(K, dist)
    uu, vv = np.meshgrid(np.linspace(-0.5, w - 0.5, grid), np.linspace(-0.5, h - 0.5, grid))
    target = np.stack([uu.ravel(), vv.ravel()], axis=1)
    _, rays = pinhole.backproject(target)
    ok = np.all(np.isfinite(rays), axis=1)
    target, rays = target[ok], rays[ok]
    xn, yn = rays[:, 0] / rays[:, 2], rays[:, 1] / rays[:, 2]
    xh, yh, cc, start = interior_from_opencv(K, dist, image_size, pix_x, pix_y)
    scale = np.array([pix_x, pix_y, cc, 1 / cc**2, 1 / cc**4, 1 / cc**6, 1 / cc, 1 / cc, 1.0])

    def unpack(p):
        q = p * scale
        return q[0], q[1], q[2], AddPar(q[3], q[4], q[5], q[6], q[7], q[8], 0.0)

    def residual(p):
        xh_, yh_, cc_, ap = unpack(p)
        return (flat_to_pixel(cc_ * xn, -cc_ * yn, xh_, yh_, ap, w, h, pix_x, pix_y) - target).ravel()

    p0 = np.array([xh, yh, cc, start.k1, start.k2, start.k3, start.p1, start.p2, start.scx]) / scale
    sol = least_squares(residual, p0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    xh, yh, cc, addpar = unpack(sol.x)
    err = np.linalg.norm(residual(sol.x).reshape(-1, 2), axis=1)
    return float(xh), float(yh), float(cc), addpar, float(err.max())


def detect_settings_from_target_par(par: TargetPar, cameras: list[str]) -> dict:
    """Translate OpenPTV's targ_rec.par to rig.yaml's ``particles.detect`` mapping (DATASET_FORMAT.md 1.2).

    ``threshold`` per camera (grey levels above the local background), ``min_pixels`` / ``max_pixels``
    (nnmin, nnmax), ``min_span_px`` / ``max_span_px`` (the looser of nxmin, nymin and of nxmax, nymax:
    ari-sfm holds one width for both axes), ``min_sum`` (sumg_min). discont (targ_rec's split of touching
    targets; ari-sfm splits overlapping images by fits) and cr_sz (drawing) have no counterpart.

    Args:
        par: the parsed targ_rec.par.
        cameras: the rig's cameras in OpenPTV's order (cam1..camN: the first N grey thresholds).

    Returns:
        The ``particles.detect`` mapping.

    Raises:
        ValueError: more cameras than grey thresholds.
    """
    if len(cameras) > len(par.gvthres):
        raise ValueError(f"targ_rec.par holds {len(par.gvthres)} grey thresholds, the rig {len(cameras)} cameras")
    return {"threshold": {cam: int(t) for cam, t in zip(cameras, par.gvthres)},
            "min_pixels": max(1, int(par.nnmin)), "max_pixels": max(1, int(par.nnmax)),
            "min_span_px": max(1, min(int(par.nxmin), int(par.nymin))),
            "max_span_px": max(1, max(int(par.nxmax), int(par.nymax))), "min_sum": int(par.sumg_min)}

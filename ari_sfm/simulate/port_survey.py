"""Simulated structure-from-motion behind flat windows: truth for ``refine-colmap``.

Two scenes, both with exact Snell physics (every pixel from
:class:`~ari_sfm.models.exact.ExactModel`):

- :func:`port_survey` (mount ``camera``): one camera in an underwater housing
  with a flat port (normal ``normal_cam`` and distance ``distance_mm`` fixed in
  the camera frame) flies a lawn-mower grid at ``altitude_mm`` over a relief
  (a heightfield ``relief_height``); the relief's points are the structure.
- :func:`tank_rig` (mount ``world``): a 2-camera rig moved along a tank wall
  (a window fixed in the world) looks at a relief under water.

World frame: x, y horizontal, z down (depth); cameras look along +z.
Lengths in mm, pixels OpenCV.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ari_sfm.geometry import Pose, rotation_from_rotvec
from ari_sfm.models import ExactModel, PinholeModel
from ari_sfm.records import Interface

ACRYLIC_INDEX = 1.49
WATER_INDEX = 1.333
STRIP_PITCH_DEG = 10.0  # layout "strip": images pitched alternately forward and back along the line


@dataclass(frozen=True)
class SfmTruth:
    """A simulated SfM experiment: cameras, windows, poses, structure and noisy observations.

    Image i is taken by camera ``image_camera[i]`` in frame ``image_frame[i]``:
    ``cam_from_world = sensor_from_rig[camera] * rig_from_world[frame]``.
    Window: ``mount == "camera"``: ``normal_cam[c]``, ``distance_mm[c]`` per camera (its housing);
    ``mount == "world"``: ``normal_world`` and the near face ``normal_world . X = plane_mm``.
    """

    mount: str
    interface: Interface
    params: tuple[np.ndarray, ...]  # per camera [fx fy cx cy k1 k2 p1 p2 k3]
    image_size: tuple[int, int]
    sensor_from_rig: tuple[Pose, ...]  # per camera
    rig_from_world: tuple[Pose, ...]  # per frame
    image_camera: np.ndarray
    image_frame: np.ndarray
    xyz: np.ndarray  # (P, 3) structure
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_uv: np.ndarray  # noisy pixels
    obs_uv_exact: np.ndarray
    sigma_px: float
    normal_cam: tuple[np.ndarray, ...] = ()
    distance_mm: tuple[float, ...] = ()
    normal_world: np.ndarray | None = None
    plane_mm: float | None = None

    def cam_from_world(self, i: int) -> Pose:
        return self.sensor_from_rig[self.image_camera[i]].compose(self.rig_from_world[self.image_frame[i]])

    def model(self, i: int) -> ExactModel:
        """The exact model of image i in its camera frame."""
        c = int(self.image_camera[i])
        pin = PinholeModel.from_params(self.params[c])
        if self.mount == "camera":
            n, h = self.normal_cam[c], self.distance_mm[c]
        else:
            pose = self.cam_from_world(i)
            n = pose.R @ self.normal_world
            h = float(self.plane_mm - self.normal_world @ pose.inverse().t)
        return ExactModel.from_interface(pin, n, self.interface, distance_mm=h)


def relief_height(xy: np.ndarray, depth_mm: float, amplitude_mm: float) -> np.ndarray:
    """Give the relief's depth at horizontal positions: a few smooth bumps and a slope.

    Args:
        xy: the horizontal positions (N, 2), mm, world frame.
        depth_mm: the relief's mean depth (mm).
        amplitude_mm: the bumps' amplitude (mm).

    Returns:
        The depths z (N,), mm (z down).
    """
    x, y = xy[:, 0] / 1000.0, xy[:, 1] / 1000.0
    bumps = (np.sin(2.1 * x + 0.3) * np.cos(1.7 * y - 0.2) + 0.5 * np.exp(-((x - 0.4) ** 2 + (y + 0.3) ** 2) / 0.3)
             - 0.4 * np.exp(-((x + 0.8) ** 2 + (y - 0.4) ** 2) / 0.2) + 0.15 * x)
    return depth_mm + amplitude_mm * bumps


def _observe(truth_args: dict, rng: np.random.Generator, min_views: int) -> SfmTruth:
    """Project the structure into every image, keep points seen >= min_views times, add noise."""
    t = SfmTruth(**truth_args, obs_image=np.zeros(0, int), obs_point=np.zeros(0, int), obs_uv=np.zeros((0, 2)),
                 obs_uv_exact=np.zeros((0, 2)))
    w, hgt = t.image_size
    imgs, pts, uvs = [], [], []
    for i in range(len(t.image_camera)):
        near = _maybe_visible(t, i)  # a superset of the visible points (the exact projection is the costly part)
        uv = t.model(i).project(t.cam_from_world(i).apply(t.xyz[near]))
        ok = (np.all(np.isfinite(uv), axis=1) & (uv[:, 0] > 2) & (uv[:, 0] < w - 3) & (uv[:, 1] > 2)
              & (uv[:, 1] < hgt - 3))
        idx = near[np.flatnonzero(ok)]
        uv = uv[np.flatnonzero(ok)]
        imgs.append(np.full(len(idx), i))
        pts.append(idx)
        uvs.append(uv)
    obs_image, obs_point, uv = np.concatenate(imgs), np.concatenate(pts), np.concatenate(uvs)
    views = np.bincount(obs_point, minlength=len(t.xyz))
    keep_pt = views >= min_views
    new_index = np.cumsum(keep_pt) - 1
    keep = keep_pt[obs_point]
    args = dict(truth_args, xyz=t.xyz[keep_pt])
    noisy = uv[keep] + rng.normal(0.0, t.sigma_px, (int(keep.sum()), 2))
    return SfmTruth(**args, obs_image=obs_image[keep], obs_point=new_index[obs_point[keep]], obs_uv=noisy,
                    obs_uv_exact=uv[keep])


def _maybe_visible(t: SfmTruth, i: int, margin: float = 0.5) -> np.ndarray:
    """Indices of the points whose central projection through the lens (no window) falls within the
    image widened by ``margin`` of its size on each side: a superset of what the exact model sees
    (a flat window into a denser medium narrows the field of view; the margin covers the plate's
    lateral shift and the port's tilt)."""
    X = t.cam_from_world(i).apply(t.xyz)
    fx, fy, cx, cy = t.params[int(t.image_camera[i])][:4]
    w, h = t.image_size
    z = np.where(X[:, 2] > 0, X[:, 2], np.inf)
    u, v = fx * X[:, 0] / z + cx, fy * X[:, 1] / z + cy
    return np.flatnonzero((X[:, 2] > 0) & (u > -margin * w) & (u < (1 + margin) * w)
                          & (v > -margin * h) & (v < (1 + margin) * h))


def _look_at(centre: np.ndarray, target: np.ndarray, rng: np.random.Generator, jitter_deg: float) -> np.ndarray:
    """cam_from_world rotation of a camera at ``centre`` looking at ``target`` (image y toward +y),
    with a random rotation of ``jitter_deg`` RMS per axis."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x = x / np.linalg.norm(x)
    R = np.vstack([x, np.cross(z, x), z])
    return rotation_from_rotvec(rng.normal(0.0, np.radians(jitter_deg), 3)) @ R


def port_survey(seed: int = 0, num_images: int = 28, num_points: int = 1500, sigma_px: float = 0.5,
                image_size: tuple[int, int] = (1280, 960), focal_px: float = 900.0,
                altitude_mm: float = 2000.0, area_mm: tuple[float, float] = (3000.0, 2000.0),
                relief_mm: float = 150.0, distance_mm: float = 22.0, thickness_mm: float = 8.0,
                index: float = ACRYLIC_INDEX, medium_index: float = WATER_INDEX, port_tilt_deg: float = 1.5,
                min_views: int = 3, convergence: float = 0.4, layout: str = "grid",
                strip_lines: int = 2) -> SfmTruth:
    """Simulate a camera in a flat-port housing surveying a relief (mount ``camera``; see module docstring).

    Layout ``grid``: images on a lawn-mower grid (rows along x) covering ``area_mm`` at ``altitude_mm``
    above the relief's mean depth, each looking at ``convergence`` times its own horizontal position.
    Layout ``strip``: a long survey with short tracks: ``strip_lines`` parallel lines along x over
    ``area_mm`` (lines at y spread over the middle half of the width), images evenly spaced along each
    line, pitched alternately +-``STRIP_PITCH_DEG`` along the line and looking toward the strip's centre
    line (``convergence`` of the line's offset), so each point is seen by a few neighbouring images of
    one or two lines.

    Args:
        seed: the random seed.
        num_images: the number of images.
        num_points: the number of relief points drawn (before keeping those seen ``min_views`` times).
        sigma_px: the observation noise per coordinate (px).
        image_size: the image size (w, h) in px.
        focal_px: the focal length (px).
        altitude_mm: the cameras' height above the relief's mean depth (mm).
        area_mm: the surveyed area (x, y) in mm.
        relief_mm: the relief's amplitude (mm).
        distance_mm: the port's distance from the camera centre (mm).
        thickness_mm: the port's thickness (mm).
        index: the port's refractive index.
        medium_index: the water's refractive index.
        port_tilt_deg: the tilt of the port normal from the optical axis (degrees).
        min_views: the least number of images a kept point is seen in.
        convergence: how far the views turn toward the middle (0: straight down).
        layout: ``"grid"`` or ``"strip"``.
        strip_lines: the number of lines of the ``strip`` layout.

    Returns:
        The simulated experiment.

    Raises:
        ValueError: if ``layout`` is neither ``grid`` nor ``strip``.
    """
    rng = np.random.default_rng(seed)
    if layout not in ("grid", "strip"):
        raise ValueError(f"layout must be grid or strip, got {layout!r}")
    poses: list[Pose] = []
    if layout == "strip":
        per_line = int(np.ceil(num_images / strip_lines))
        xs = np.linspace(-0.5, 0.5, per_line) * (area_mm[0] - 1.2 * altitude_mm)
        ys = (np.linspace(-0.25, 0.25, strip_lines) if strip_lines > 1 else np.zeros(1)) * area_mm[1]
        pitch = altitude_mm * np.tan(np.radians(STRIP_PITCH_DEG))
        for r, y in enumerate(ys):
            for k, x in enumerate(xs if r % 2 == 0 else xs[::-1]):
                if len(poses) == num_images:
                    break
                C = np.array([x, y, 0.0]) + rng.normal(0.0, 30.0, 3)
                target = np.array([x + (pitch if k % 2 == 0 else -pitch), (1.0 - convergence) * y, altitude_mm])
                R = _look_at(C, target, rng, 2.0)
                poses.append(Pose(R, -R @ C))
    else:
        cols = max(2, int(round(np.sqrt(num_images * area_mm[0] / area_mm[1]))))
        rows = int(np.ceil(num_images / cols))
        xs = np.linspace(-0.4, 0.4, cols) * area_mm[0]
        ys = np.linspace(-0.4, 0.4, rows) * area_mm[1]
        for r, y in enumerate(ys):
            for x in (xs if r % 2 == 0 else xs[::-1]):
                if len(poses) == num_images:
                    break
                C = np.array([x, y, 0.0]) + rng.normal(0.0, 30.0, 3)
                R = _look_at(C, np.array([convergence * x, convergence * y, altitude_mm]), rng, 2.0)
                poses.append(Pose(R, -R @ C))
    xy = rng.uniform(-0.5, 0.5, (num_points, 2)) * np.array(area_mm)
    xyz = np.column_stack([xy, relief_height(xy, altitude_mm, relief_mm)])
    az = rng.uniform(0.0, 2.0 * np.pi)
    tilt = np.radians(port_tilt_deg)
    normal = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    fx = focal_px
    params = np.array([fx, fx * 1.001, image_size[0] / 2 - 0.5 + 3.0, image_size[1] / 2 - 0.5 - 2.0, 0, 0, 0, 0, 0])
    args = dict(mount="camera", interface=Interface(thickness_mm, index, medium_index), params=(params,),
                image_size=image_size, sensor_from_rig=(Pose.identity(),), rig_from_world=tuple(poses),
                image_camera=np.zeros(len(poses), int), image_frame=np.arange(len(poses)), xyz=xyz,
                sigma_px=sigma_px, normal_cam=(normal,), distance_mm=(float(distance_mm),))
    return _observe(args, np.random.default_rng(seed + 1000), min_views)


def tank_rig(seed: int = 0, num_frames: int = 8, num_points: int = 800, sigma_px: float = 0.3,
             image_size: tuple[int, int] = (1024, 768), focal_px: float = 1000.0, baseline_mm: float = 150.0,
             wall_mm: float = 60.0, thickness_mm: float = 10.0, index: float = 1.5168,
             medium_index: float = WATER_INDEX, depth_mm: float = 900.0, min_views: int = 3) -> SfmTruth:
    """Simulate a 2-camera rig moved along a tank wall (mount ``world``).

    The wall's normal is ~5 deg off the rig's z axis; the second camera is yawed 6 deg.

    Args:
        seed: the random seed.
        num_frames: the number of rig positions.
        num_points: the number of relief points drawn (before keeping those seen ``min_views`` times).
        sigma_px: the observation noise per coordinate (px).
        image_size: the image size (w, h) in px.
        focal_px: the focal length (px).
        baseline_mm: the distance between the two cameras (mm).
        wall_mm: the distance of the wall's near face in front of the first frame's rig origin (mm).
        thickness_mm: the wall's thickness (mm).
        index: the wall's refractive index.
        medium_index: the water's refractive index.
        depth_mm: the relief's mean depth (mm).
        min_views: the least number of images a kept point is seen in.

    Returns:
        The simulated experiment.
    """
    rng = np.random.default_rng(seed)
    yaw = np.radians(6.0)
    sensor = (Pose.identity(), Pose(rotation_from_rotvec([0.0, -yaw, 0.0]),
                                    -rotation_from_rotvec([0.0, -yaw, 0.0]) @ np.array([baseline_mm, 0.0, 0.0])))
    frames = []
    for k in range(num_frames):
        R = rotation_from_rotvec(rng.normal(0.0, np.radians(2.0), 3))
        C = np.array([(k - (num_frames - 1) / 2) * 70.0, rng.normal(0.0, 40.0), rng.normal(0.0, 10.0)])
        frames.append(Pose(R, -R @ C))
    normal = rotation_from_rotvec([np.radians(4.0), np.radians(3.0), 0.0]) @ np.array([0.0, 0.0, 1.0])
    xy = rng.uniform(-0.5, 0.5, (num_points, 2)) * np.array([1200.0, 800.0])
    xyz = np.column_stack([xy, relief_height(xy, depth_mm, 80.0)])
    params = np.array([focal_px, focal_px, image_size[0] / 2 - 0.5, image_size[1] / 2 - 0.5, 0, 0, 0, 0, 0])
    args = dict(mount="world", interface=Interface(thickness_mm, index, medium_index), params=(params, params.copy()),
                image_size=image_size, sensor_from_rig=sensor, rig_from_world=tuple(frames),
                image_camera=np.tile([0, 1], num_frames), image_frame=np.repeat(np.arange(num_frames), 2), xyz=xyz,
                sigma_px=sigma_px, normal_world=normal, plane_mm=float(wall_mm))
    return _observe(args, np.random.default_rng(seed + 1000), min_views)


# --------------------------------------------------------------------------- rendering (mount camera)

TEXTURE_MM_PER_TEXEL = 2.0


def relief_texture(area_mm: tuple[float, float], seed: int = 0,
                   margin_mm: float = 600.0) -> tuple[np.ndarray, np.ndarray]:
    """Make a grey texture over the relief, with blobs at several scales.

    Args:
        area_mm: the surveyed area (x, y) in mm.
        seed: the random seed.
        margin_mm: the texture's margin beyond the area on each side (mm).

    Returns:
        The texture (H, W) float32 in [0, 1], one texel TEXTURE_MM_PER_TEXEL mm, and its origin (x0, y0) in mm.
    """
    import cv2

    rng = np.random.default_rng(seed + 7)
    w = int((area_mm[0] + 2 * margin_mm) / TEXTURE_MM_PER_TEXEL)
    h = int((area_mm[1] + 2 * margin_mm) / TEXTURE_MM_PER_TEXEL)
    tex = np.zeros((h, w), np.float32)
    for sigma, weight in ((12.0, 1.0), (5.0, 0.8), (2.5, 0.6)):
        noise = rng.normal(0.0, 1.0, (h, w)).astype(np.float32)
        band = cv2.GaussianBlur(noise, (0, 0), sigma)
        tex += weight * band / band.std()
    tex = 1.0 / (1.0 + np.exp(-1.5 * tex))  # contrast, bounded
    return tex.astype(np.float32), np.array([-area_mm[0] / 2 - margin_mm, -area_mm[1] / 2 - margin_mm])


def _hit_relief(origins: np.ndarray, directions: np.ndarray, depth_mm: float, amplitude_mm: float) -> np.ndarray:
    """World points where rays (z increasing) meet the relief z = relief_height(x, y): Newton on the ray
    parameter with a numerical slope, started at the mean depth."""
    s = (depth_mm - origins[:, 2]) / directions[:, 2]
    for _ in range(30):
        P = origins + s[:, None] * directions
        f = P[:, 2] - relief_height(P[:, :2], depth_mm, amplitude_mm)
        eps = 1e-3
        P2 = origins + (s + eps)[:, None] * directions
        df = ((P2[:, 2] - relief_height(P2[:, :2], depth_mm, amplitude_mm)) - f) / eps
        step = f / df
        s = s - step
        if np.max(np.abs(step)) < 1e-6:
            break
    return origins + s[:, None] * directions


def render_survey_image(truth: SfmTruth, i: int, texture: np.ndarray, origin_mm: np.ndarray,
                        depth_mm: float, amplitude_mm: float, supersample: int = 2) -> np.ndarray:
    """Render image i of a port survey.

    Every (sub)pixel is back-projected through the port with the exact model, intersected with the
    relief, the texture sampled (bilinear), and the samples averaged per pixel.

    Args:
        truth: the survey (mount ``camera``).
        i: the image's index.
        texture: the relief's texture (see :func:`relief_texture`).
        origin_mm: the texture's origin (x0, y0) in mm.
        depth_mm: the relief's mean depth (mm).
        amplitude_mm: the relief's amplitude (mm).
        supersample: the subpixels per pixel along each axis.

    Returns:
        The (h, w) uint8 image.
    """
    import cv2

    w, h = truth.image_size
    k = supersample
    offs = (np.arange(k) + 0.5) / k - 0.5
    u, v = np.meshgrid(np.arange(w * k) / k + offs[0], np.arange(h * k) / k + offs[0])
    uv = np.column_stack([u.ravel(), v.ravel()])
    origins, directions = truth.model(i).backproject(uv)
    world_from_cam = truth.cam_from_world(i).inverse()
    P = _hit_relief(world_from_cam.apply(origins), directions @ world_from_cam.R.T, depth_mm, amplitude_mm)
    tx = ((P[:, 0] - origin_mm[0]) / TEXTURE_MM_PER_TEXEL).astype(np.float32).reshape(h * k, w * k)
    ty = ((P[:, 1] - origin_mm[1]) / TEXTURE_MM_PER_TEXEL).astype(np.float32).reshape(h * k, w * k)
    sub = cv2.remap(texture, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    img = sub.reshape(h, k, w, k).mean(axis=(1, 3))
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)


def write_port_survey(out_dir, seed: int = 0, num_images: int = 12, image_size: tuple[int, int] = (640, 480),
                      focal_px: float = 600.0, area_mm: tuple[float, float] = (1600.0, 1200.0),
                      altitude_mm: float = 2000.0, relief_mm: float = 150.0, supersample: int = 2,
                      progress: bool = False) -> tuple[SfmTruth, Path]:
    """Render a port survey to ``out_dir/images/imageNNNN.png`` with its truth in ``out_dir/truth.json``.

    The truth holds the housing, the lens intrinsics, every image's cam_from_world and the relief.

    Args:
        out_dir: the output folder (created if missing).
        seed: the random seed.
        num_images: the number of images.
        image_size: the image size (w, h) in px.
        focal_px: the focal length (px).
        area_mm: the surveyed area (x, y) in mm.
        altitude_mm: the cameras' height above the relief's mean depth (mm).
        relief_mm: the relief's amplitude (mm).
        supersample: the subpixels per pixel along each axis.
        progress: show a progress bar.

    Returns:
        The truth and the images folder.
    """
    import cv2

    from ari_sfm.io import write_bytes_atomic, write_json_atomic

    out = Path(out_dir)
    images = out / "images"
    images.mkdir(parents=True, exist_ok=True)
    truth = port_survey(seed=seed, num_images=num_images, num_points=10, image_size=image_size, focal_px=focal_px,
                        altitude_mm=altitude_mm, area_mm=area_mm, relief_mm=relief_mm, min_views=1)
    texture, origin = relief_texture(area_mm, seed)
    names = []
    steps = range(num_images)
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, desc="port_survey", unit="image")
    for i in steps:
        name = f"image{i + 1:04d}.png"
        img = render_survey_image(truth, i, texture, origin, altitude_mm, relief_mm, supersample)
        ok, buf = cv2.imencode(".png", img)
        write_bytes_atomic(images / name, buf.tobytes())  # a full disk leaves no truncated PNG
        names.append(name)
    write_json_atomic(out / "truth.json", {
        "scenario": "port_survey", "seed": seed, "mount": "camera",
        "interface": {"thickness_mm": truth.interface.thickness_mm, "index": truth.interface.index,
                      "medium_index": truth.interface.medium_index},
        "camera": {"image_size": list(image_size), "params": truth.params[0].tolist(),
                   "normal_cam": truth.normal_cam[0].tolist(), "distance_mm": truth.distance_mm[0]},
        "relief": {"depth_mm": altitude_mm, "amplitude_mm": relief_mm, "area_mm": list(area_mm)},
        "images": {n: truth.cam_from_world(i).to_json() for i, n in enumerate(names)}})
    return truth, images

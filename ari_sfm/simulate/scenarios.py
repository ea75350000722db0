"""The simulated experiments: random but valid geometries, deterministic for a seed.

Each builder takes a numpy Generator and keyword options and returns a
:class:`~ari_sfm.simulate.scene.Geometry`; :data:`REGISTRY` names the builder
of each scenario and the options it fixes, and :func:`build_geometry` builds
one with the :class:`ScenarioOverrides` a caller gives.  Random target poses that a
camera that must see them does not see (a corner within 10 px of the border,
or a point not beyond the window) are drawn again.  Geometry comes from its
own random stream, so the noise level never changes the poses.

Rig frames used while building: x right, y down, z forward (OpenCV-like);
the world frame of the result is camera 0's frame.
"""
from __future__ import annotations

import inspect
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace

import numpy as np

from ari_sfm.geometry import Pose, rotation_from_rotvec, unit
from ari_sfm.records import Target
from ari_sfm.simulate.render import dot_diameter_mm
from ari_sfm.simulate.scene import (
    MARGIN_PX,
    CameraTruth,
    Geometry,
    ReconstructionFrame,
    StackingPose,
    WindowGroup,
    WindowTruth,
    check_geometry,
    inside,
)

logger = logging.getLogger(__name__)

# ----------------------------------------------------------------- paper-like constants
PAPER_IMAGE_SIZE = (2448, 2048)  # Daheng MER2-503-36U3M
PAPER_FOCAL_PX = 12.0 / 3.45e-3  # 12 mm lens, 3.45 um pixels: 3478.3 px
NBK7_INDEX = 1.5168
WATER_INDEX = 1.333
# the paper: 10 mm corner spacing (Fig. 14)
PAPER_TARGET = Target(type="checkerboard", inner_corners=(11, 8), square_mm=10.0)
# a dot board of about the checkerboard's size: 5 x 11 asymmetric dots (rows odd: ids unambiguous), 10 mm spacing
DOT_TARGET = Target(type="circles", circle_grid=(5, 11), spacing_mm=10.0, layout="asymmetric", diameter_mm=6.0)
STACK_ADDED_MM = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0)
STAGE_MM = tuple(float(s) for s in range(-10, 11, 2))
MAX_TRIES = 4000  # draws per random pose before giving up (raise, never a silent bad pose)

SCENARIOS: dict[str, str] = {
    "paper_single": "one paper-like camera (2448x2048, f~3478 px) behind a 50 mm N-BK7 window "
                    "tilted 4-8 deg; 12 calibration poses, stacking 0..50 mm",
    "paper_single_images": "paper_single rendered to PNG images (corners must be detected)",
    "paper_single_dots": "paper_single with a 5 x 11 asymmetric dot board (6 mm dots, 10 mm spacing) "
                         "rendered to PNG images (dots must be detected)",
    "paper_single_perpendicular": "paper_single with the window normal within 0.05 deg of the optical axis",
    "binocular": "two cameras 120-200 mm apart, yawed 10-15 deg inward, one 50 mm window; "
                 "15 calibration frames, stacking, 11 stage frames (-10..10 mm)",
    "binocular_underwater": "binocular behind a 10 mm glass port with water (n=1.333) behind it",
    "arc4": "4 cameras on an arc, window tilted ~20 deg (an outer expansion centre outside "
            "its image), partial visibility",
    "scale16": "16 cameras in a 4x4 grid, 500 frames (observations only) for scale tests",
    "paper_single_nostack": "paper_single without the stacking pose (the same geometry for a seed)",
    "binocular_nostack": "binocular without the stacking pose (the same geometry for a seed)",
    "binocular_underwater_oblique": "binocular behind a 10 mm glass port with water, the window 10 deg "
                                    "oblique, no stacking (the ari stage puts the window far off)",
    "body3d_water": "a PTV-like 3D calibration body (3 levels, 40 mm deep) in one view of 4 cameras "
                    "through 6 mm glass into water, no stacking",
    "body3d_shallow": "body3d_water with a body 15 mm deep at 600 mm (too shallow for DLT without a focal hint)",
    "tank_opposite": "a tank seen through two opposite walls (like OpenPTV's test_cavity): 2 + 2 cameras 12-26 "
                     "deg oblique to 6 mm glass walls 120 mm either side of the centre, water between; a 3D dot "
                     "body (5 rows on 3 levels, 16 mm deep) in 5 poses, each seen by every camera",
    "tank_adjacent": "a tank seen through two adjacent walls at 90 deg: 2 + 2 cameras 12-26 deg oblique to 6 mm "
                     "glass walls, water inside; the 3D dot body turned 45 deg to face both walls, 5 poses",
    "ptv_multiplane": "an OpenPTV multi-plane experiment: 4 cameras 12-26 deg oblique to 6 mm glass, 560-620 mm "
                      "from a 130 x 70 mm dot plate at 4 depths (15 mm) 7-25 mm into water, one view; pixels "
                      "quantised to 0.5 px, focal hints, interface.plane declared in the body's (OpenPTV's) frame",
}


# --------------------------------------------------------------------------- helpers


def _rot(axis: Sequence[float] | np.ndarray, angle_rad: float) -> np.ndarray:
    return rotation_from_rotvec(unit(np.asarray(axis, float)) * angle_rad)


def _rot_y(angle_rad: float) -> np.ndarray:
    return _rot((0.0, 1.0, 0.0), angle_rad)


def _tilted(axis: np.ndarray, tilt_rad: float, azimuth_rad: float) -> np.ndarray:
    """``axis`` turned by ``tilt_rad`` toward the perpendicular direction at ``azimuth_rad``."""
    axis = unit(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = unit(helper - (helper @ axis) * axis)
    e2 = np.cross(axis, e1)  # for an axis near z: e1 ~ x, e2 ~ y, the azimuth reads as usual
    return unit(math.cos(tilt_rad) * axis
                + math.sin(tilt_rad) * (math.cos(azimuth_rad) * e1 + math.sin(azimuth_rad) * e2))


def _intrinsics(rng: np.random.Generator, size: tuple[int, int] = PAPER_IMAGE_SIZE,
                focal_px: float = PAPER_FOCAL_PX, focal_spread: float = 0.01,
                pp_spread_px: float = 20.0) -> np.ndarray:
    """K with square pixels, fx within +-focal_spread of nominal, principal point near the centre."""
    w, h = size
    f = focal_px * (1.0 + rng.uniform(-focal_spread, focal_spread))
    cx = (w - 1) / 2.0 + rng.uniform(-pp_spread_px, pp_spread_px)
    cy = (h - 1) / 2.0 + rng.uniform(-pp_spread_px, pp_spread_px)
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def _board_outline(target: Target, per_edge: int = 6) -> np.ndarray:
    """Points along the outer edge of the board's squares (target frame): the printed
    pattern that must be inside an image for a detector to find the board.
    For a dot board: the bounding box of its dots."""
    if target.type == "circles":
        _, xyz = target.points_3d()
        r = 0.5 * dot_diameter_mm(target)
        (x0, y0), (x1, y1) = xyz[:, :2].min(axis=0) - r, xyz[:, :2].max(axis=0) + r
        t = np.linspace(0.0, 1.0, per_edge, endpoint=False)
        xy = np.concatenate([np.stack([x0 + (x1 - x0) * t, np.full_like(t, y0)], 1),
                             np.stack([np.full_like(t, x1), y0 + (y1 - y0) * t], 1),
                             np.stack([x1 - (x1 - x0) * t, np.full_like(t, y1)], 1),
                             np.stack([np.full_like(t, x0), y1 - (y1 - y0) * t], 1)])
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
    cols, rows = target.required(target.grid, "grid")
    s = target.square_mm
    x0, y0, x1, y1 = -s, -s, cols * s, rows * s
    t = np.linspace(0.0, 1.0, per_edge, endpoint=False)
    edges = [np.stack([x0 + (x1 - x0) * t, np.full_like(t, y0)], 1),
             np.stack([np.full_like(t, x1), y0 + (y1 - y0) * t], 1),
             np.stack([x1 - (x1 - x0) * t, np.full_like(t, y1)], 1),
             np.stack([np.full_like(t, x0), y1 - (y1 - y0) * t], 1)]
    xy = np.concatenate(edges)
    return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)


def _board_pose(target: Target, center_world: np.ndarray, facing_world: np.ndarray,
                down_world: np.ndarray, tilt_rad: float = 0.0, tilt_azimuth_rad: float = 0.0,
                roll_rad: float = 0.0) -> Pose:
    """world_from_target of a board whose corner-grid centre is at ``center_world``.

    With no tilt, the board's z axis is ``facing_world`` (away from the
    viewer) and its y axis (rows) follows ``down_world``, so a camera sees
    corner 0 top-left as OpenCV orders it.  The tilt turns the board about an
    in-plane axis at ``tilt_azimuth_rad``; the roll turns it about its normal.
    """
    z = unit(facing_world)
    x = unit(np.cross(down_world, z))
    y = np.cross(z, x)
    R0 = np.column_stack([x, y, z])
    axis = math.cos(tilt_azimuth_rad) * x + math.sin(tilt_azimuth_rad) * y
    R = _rot(axis, tilt_rad) @ R0 @ _rot((0.0, 0.0, 1.0), roll_rad)
    if target.type == "circles":  # the centre of the dots' bounding box
        _, xyz = target.points_3d()
        c_local = 0.5 * (xyz.min(axis=0) + xyz.max(axis=0))
    else:
        cols, rows = target.required(target.grid, "grid")
        c_local = np.array([(cols - 1) * target.square_mm / 2.0, (rows - 1) * target.square_mm / 2.0, 0.0])
    return Pose(R, np.asarray(center_world, float) - R @ c_local)


@dataclass(frozen=True)
class _Checker:
    """Visibility tests for one window (or one per camera) and a camera set (exact projection)."""

    target: Target
    window: WindowTruth
    cameras: tuple[CameraTruth, ...]
    margin_px: float = MARGIN_PX
    clearance_mm: float = 10.0  # every board point this far beyond the far face
    _models: dict = field(default_factory=dict, compare=False, repr=False)  # (camera, added) -> ExactModel
    windows: Mapping[str, WindowTruth] | None = None  # camera -> its window (several windows)

    def window_of(self, cam: CameraTruth) -> WindowTruth:
        return self.window if self.windows is None else self.windows[cam.name]

    def project(self, cam: CameraTruth, X_world: np.ndarray, added: float = 0.0) -> np.ndarray:
        """Exact pixels of world points (the model of each camera and stack is built once)."""
        key = (cam.name, float(added))
        if key not in self._models:
            self._models[key] = self.window_of(cam).model(cam, added)
        return self._models[key].project(cam.cam_from_world.apply(X_world))

    def sees(self, cam: CameraTruth, pose: Pose, added: Sequence[float] = (0.0,),
             outline: bool = False) -> bool:
        """All corners (and with ``outline`` the board's edge) inside ``cam``'s image for every stack."""
        _, pts = self.target.points_3d()
        if outline:
            pts = np.concatenate([pts, _board_outline(self.target)])
        X = pose.apply(pts)
        if self.window_of(cam).depth_beyond_far_face(X, max(added)).min() < self.clearance_mm:
            return False
        # A corner moves monotonically along a straight image line as glass is added (the
        # stacking physics), so inside the image for the thinnest and the thickest stack
        # means inside for every stack in between.
        ends = sorted({float(min(added)), float(max(added))}, reverse=True)
        return all(inside(self.project(cam, X, a), cam.image_size, self.margin_px) for a in ends)

    def seen_by(self, pose: Pose, added: Sequence[float] = (0.0,), outline: bool = False) -> tuple[int, ...]:
        return tuple(i for i, c in enumerate(self.cameras) if self.sees(c, pose, added, outline))

    def point_at(self, cam: CameraTruth, uv: Sequence[float], depth_mm: float) -> np.ndarray:
        """World point seen at pixel ``uv`` whose camera-frame z is ``depth_mm`` (exact ray)."""
        origins, dirs = self.window_of(cam).model(cam).backproject(np.asarray(uv, float)[None, :])
        o, d = origins[0], dirs[0]
        X_cam = o + (depth_mm - o[2]) / d[2] * d
        return cam.cam_from_world.inverse().apply(X_cam)


def _draw(name: str, sample: Callable[[], Pose | None], tries: int = MAX_TRIES) -> Pose:
    """Call ``sample`` until it returns a pose (it returns None for a rejected draw)."""
    for _ in range(tries):
        pose = sample()
        if pose is not None:
            return pose
    raise RuntimeError(f"simulator could not place {name} after {tries} draws; relax the scenario")


def _in_world(rig_from_cam: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[Pose]:
    """cam_from_world of each camera, world = camera 0, from (R rig_from_cam, centre in rig)."""
    R0, C0 = rig_from_cam[0]
    rig_from_world = Pose(R0, np.asarray(C0, float))
    out = []
    for R, C in rig_from_cam:
        cam_from_rig = Pose(R, np.asarray(C, float)).inverse()
        out.append(cam_from_rig.compose(rig_from_world))
    out[0] = Pose.identity()
    return out


def _rig_cameras(rig: Sequence[tuple[np.ndarray, np.ndarray]], rng: np.random.Generator
                 ) -> tuple[tuple[CameraTruth, ...], Pose]:
    """Paper-like cameras (intrinsics drawn from rng in camera order) at the rig's (R, centre) poses,
    world = camera 0; and rig_from_world."""
    cam_from_world = _in_world(rig)
    cameras = tuple(CameraTruth(name=f"cam{i}", K=_intrinsics(rng), image_size=PAPER_IMAGE_SIZE,
                                cam_from_world=cam_from_world[i], focal_hint_px=round(PAPER_FOCAL_PX, 1))
                    for i in range(len(rig)))
    return cameras, Pose(rig[0][0], rig[0][1])


def _window_in_world(normal_rig: np.ndarray, distance_rig_mm: float, rig_from_world: Pose,
                     thickness_mm: float, index: float, medium_index: float) -> WindowTruth:
    """A window given in the rig frame, expressed in the world frame (camera 0)."""
    n_w = rig_from_world.R.T @ normal_rig
    return WindowTruth(normal_world=unit(n_w), distance_mm=float(distance_rig_mm - normal_rig @ rig_from_world.t),
                       thickness_mm=thickness_mm, index=index, medium_index=medium_index)


def _frame_names(prefix: str, n: int) -> list[str]:
    width = max(3, len(str(max(n - 1, 0))))
    return [f"{prefix}{k:0{width}d}" for k in range(n)]


# --------------------------------------------------------------------------- paper_single


def paper_single(rng: np.random.Generator, num_frames: int = 12, perpendicular: bool = False,
                 stack_added_mm: Sequence[float] = STACK_ADDED_MM, target: Target = PAPER_TARGET) -> Geometry:
    """One paper-like camera behind a 50 mm N-BK7 plate in air (section 3 of the paper).

    Poses are drawn so the whole printed board (not only the corners) is in the image: the rendered images
    then detect. Board centres are spread over a 4 x 3 grid of image cells for coverage.

    Args:
        rng: The geometry's random stream (the intrinsics and every pose are drawn from it, in order).
        num_frames: Calibration frames.
        perpendicular: The window normal within 0.05 deg of the optical axis (else tilted 4-8 deg).
        stack_added_mm: The glass added in each record of the stacking pose.
        target: The calibration board.

    Returns:
        The geometry: the camera, the window, the stacking pose and the calibration frames.
    """
    K = _intrinsics(rng)
    cam = CameraTruth(name="cam0", K=K, image_size=PAPER_IMAGE_SIZE, cam_from_world=Pose.identity(),
                      focal_hint_px=round(PAPER_FOCAL_PX, 1))
    tilt = rng.uniform(0.0, 0.04) if perpendicular else rng.uniform(4.0, 8.0)
    normal = _tilted(np.array([0.0, 0.0, 1.0]), math.radians(tilt), rng.uniform(0.0, 2 * math.pi))
    window = WindowTruth(normal_world=normal, distance_mm=float(rng.uniform(30.0, 60.0)),
                         thickness_mm=50.0, index=NBK7_INDEX, medium_index=1.0)
    chk = _Checker(target, window, (cam,))
    w, h = cam.image_size
    down = np.array([0.0, 1.0, 0.0])

    def stacking_sample() -> Pose | None:
        uv = (K[0, 2] + rng.uniform(-40, 40), K[1, 2] + rng.uniform(-40, 40))
        center = chk.point_at(cam, uv, rng.uniform(390.0, 410.0))
        facing = _tilted(normal, math.radians(rng.uniform(0.0, 2.0)), rng.uniform(0, 2 * math.pi))
        pose = _board_pose(target, center, facing, down, roll_rad=math.radians(rng.uniform(-2, 2)))
        return pose if chk.sees(cam, pose, stack_added_mm, outline=True) else None

    s0 = StackingPose("s0", _draw("stacking pose s0", stacking_sample), tuple(float(a) for a in stack_added_mm))

    # Spread: frame k aims at cell k of a 4 x 3 grid.  A board 300-500 mm away fills much of
    # the image, so the cell picks a place within the range of centres where this board
    # (depth, tilt, roll drawn first) fits, not within the whole image.
    cells = [(i / 3.0, j / 2.0) for j in range(3) for i in range(4)]  # 0 .. 1 across the feasible range
    outline = _board_outline(target)
    calibration: dict[str, Pose] = {}
    for k, name in enumerate(_frame_names("f", num_frames)):
        cu, cv = cells[k % len(cells)]

        def calib_sample(cu: float = cu, cv: float = cv) -> Pose | None:
            depth = rng.uniform(300.0, 500.0)
            tilt = math.radians(rng.uniform(8.0, 35.0))
            azimuth = rng.uniform(0.0, 2 * math.pi)
            roll = math.radians(rng.uniform(-10.0, 10.0))

            def pose_at(u: float, v: float) -> Pose:
                center = chk.point_at(cam, (u, v), depth)
                return _board_pose(target, center, center - cam.center_world, down, tilt, azimuth, roll)

            uv = chk.project(cam, pose_at(K[0, 2], K[1, 2]).apply(outline))
            if not np.all(np.isfinite(uv)):
                return None
            lo = chk.margin_px + 5.0 - (uv.min(axis=0) - K[:2, 2])  # feasible centre range, 5 px spare
            hi = np.array([w - 1.0, h - 1.0]) - chk.margin_px - 5.0 - (uv.max(axis=0) - K[:2, 2])
            if np.any(hi < lo):
                return None
            a = np.clip([cu + rng.uniform(-0.1, 0.1), cv + rng.uniform(-0.12, 0.12)], 0.0, 1.0)
            u, v = lo + a * (hi - lo)
            pose = pose_at(u, v)
            return pose if chk.sees(cam, pose, outline=True) else None

        calibration[name] = _draw(f"calibration frame {name}", calib_sample)

    return Geometry(target=target, window=window, cameras=(cam,), calibration=calibration, stacking=(s0,))


# --------------------------------------------------------------------------- binocular


def binocular(rng: np.random.Generator, num_frames: int = 15, underwater: bool = False,
              stack_added_mm: Sequence[float] = STACK_ADDED_MM,
              stage_mm: Sequence[float] = STAGE_MM, depth_band_mm: float = 180.0,
              lateral_scale: float = 1.0, tilt_deg: float | None = None) -> Geometry:
    """Two paper-like cameras toed in 10-15 deg, one window (sections 4-5 of the paper).

    The baseline is drawn so that the optical axes cross at least 350 mm ahead (a toe-in aimed at the working
    distance). Calibration frames, the stacking pose and the stage frames are each seen whole (board outline
    included) by both cameras; they are placed in the depth band where a board facing the rig first fits both
    views (:func:`_overlap_start`).

    Args:
        rng: The geometry's random stream (the intrinsics and every pose are drawn from it, in order).
        num_frames: Calibration frames.
        underwater: A 10 mm N-BK7 port with water behind (else 50 mm N-BK7 in air).
        stack_added_mm: The glass added in each record of the stacking pose.
        stage_mm: The stage frames' positions along the rig's axis (reconstruction frames).
        depth_band_mm: The depth band of the calibration boards' centres.
        lateral_scale: The scale of their sideways spread (+-50 x +-40 mm); a few mm of depth band and ~0 here
            mimic the paper's rotary stage (boards turned about one point).
        tilt_deg: The window's tilt from the rig's z axis (None: drawn in 2-5 deg).

    Returns:
        The geometry: the two cameras, the window, the stacking pose, the calibration and stage frames.
    """
    tan_yaws = np.tan(np.radians(rng.uniform(10.0, 15.0, size=2)))
    baseline = rng.uniform(max(120.0, 350.0 * float(tan_yaws.sum())), 200.0)
    rig = []
    for sign, tan_yaw in zip((+1.0, -1.0), tan_yaws):  # cam0 on the left turns right (+x), cam1 left
        jitter = _rot(rng.normal(size=3), math.radians(rng.uniform(0.0, 0.7)))
        rig.append((_rot_y(sign * math.atan(tan_yaw)) @ jitter,
                    np.array([-sign * baseline / 2.0, rng.uniform(-2, 2), rng.uniform(-2, 2)])))
    cameras, rig_from_world = _rig_cameras(rig, rng)

    tilt = rng.uniform(2.0, 5.0)  # drawn in any case: the same stream with or without tilt_deg
    normal_rig = _tilted(np.array([0.0, 0.0, 1.0]), math.radians(tilt if tilt_deg is None else tilt_deg),
                         rng.uniform(0, 2 * math.pi))
    near = max(normal_rig @ c for _, c in rig) + rng.uniform(40.0, 60.0)
    if underwater:
        window = _window_in_world(normal_rig, near, rig_from_world, 10.0, NBK7_INDEX, WATER_INDEX)
    else:
        window = _window_in_world(normal_rig, near, rig_from_world, 50.0, NBK7_INDEX, 1.0)
    chk = _Checker(PAPER_TARGET, window, cameras)
    world_from_rig = rig_from_world.inverse()
    down = world_from_rig.R @ np.array([0.0, 1.0, 0.0])
    rig_origin = world_from_rig.t
    depth0, x0 = _overlap_start(chk, world_from_rig, stack_added_mm)
    depth_range = (depth0 + 20.0, depth0 + 20.0 + float(depth_band_mm))
    mid_depth = depth0 + 60.0
    logger.debug("binocular: baseline %.1f mm, boards fit both views from %.0f mm (rig x %.0f mm)",
                 baseline, depth0, x0)

    def both(pose: Pose, added: Sequence[float] = (0.0,)) -> bool:
        return all(chk.sees(c, pose, added, outline=True) for c in cameras)

    def calib_sample() -> Pose | None:
        c_rig = np.array([x0 + lateral_scale * rng.uniform(-50, 50), lateral_scale * rng.uniform(-40, 40),
                          rng.uniform(*depth_range)])
        center = world_from_rig.apply(c_rig)
        pose = _board_pose(PAPER_TARGET, center, center - rig_origin, down,
                           tilt_rad=math.radians(rng.uniform(8.0, 35.0)),
                           tilt_azimuth_rad=rng.uniform(0.0, 2 * math.pi),
                           roll_rad=math.radians(rng.uniform(-10.0, 10.0)))
        return pose if both(pose) else None

    calibration = {name: _draw(f"calibration frame {name}", calib_sample)
                   for name in _frame_names("f", num_frames)}

    normal_w = window.normal_world

    def stacking_sample() -> Pose | None:
        center = world_from_rig.apply(np.array([x0 + rng.uniform(-20, 20), rng.uniform(-20, 20), mid_depth]))
        facing = _tilted(normal_w, math.radians(rng.uniform(0.0, 2.0)), rng.uniform(0, 2 * math.pi))
        pose = _board_pose(PAPER_TARGET, center, facing, down, roll_rad=math.radians(rng.uniform(-2, 2)))
        return pose if both(pose, stack_added_mm) else None

    s0 = StackingPose("s0", _draw("stacking pose s0", stacking_sample), tuple(float(a) for a in stack_added_mm))

    stage_dir = _tilted(normal_w, math.radians(rng.uniform(0.0, 1.5)), rng.uniform(0, 2 * math.pi))

    def stage_sample() -> Pose | None:
        center = world_from_rig.apply(np.array([x0 + rng.uniform(-20, 20), rng.uniform(-20, 20), mid_depth]))
        facing = _tilted(center - rig_origin, math.radians(rng.uniform(0.0, 10.0)), rng.uniform(0, 2 * math.pi))
        base = _board_pose(PAPER_TARGET, center, facing, down, roll_rad=math.radians(rng.uniform(-3, 3)))
        ok = all(both(Pose(base.R, base.t + s * stage_dir)) for s in stage_mm)
        return base if ok else None

    base = _draw("reconstruction stage pose", stage_sample)
    reconstruction = tuple(ReconstructionFrame(name, Pose(base.R, base.t + s * stage_dir), float(s))
                           for name, s in zip(_frame_names("r", len(stage_mm)), stage_mm))
    return Geometry(target=PAPER_TARGET, window=window, cameras=cameras, calibration=calibration,
                    stacking=(s0,), reconstruction=reconstruction, stage_direction_world=stage_dir)


def _overlap_start(chk: _Checker, world_from_rig: Pose, added: Sequence[float]) -> tuple[float, float]:
    """The smallest depth (rig z, mm) at which a board facing the rig origin is whole in every
    camera for every stack, and the mean rig x of the places where it fits there."""
    down = world_from_rig.R @ np.array([0.0, 1.0, 0.0])
    for depth in np.arange(300.0, 1500.0, 20.0):
        fits = []
        for x in np.arange(-100.0, 101.0, 25.0):
            center = world_from_rig.apply(np.array([x, 0.0, depth]))
            pose = _board_pose(chk.target, center, center - world_from_rig.t, down)
            if all(chk.sees(c, pose, added, outline=True) for c in chk.cameras):
                fits.append(x)
        if fits:
            return float(depth), float(np.mean(fits))
    raise RuntimeError("simulator: no depth up to 1.5 m where the board fits every camera; relax the scenario")


# --------------------------------------------------------------------------- arc4


def arc(rng: np.random.Generator, num_frames: int = 20, num_cameras: int = 4,
        stack_added_mm: Sequence[float] = STACK_ADDED_MM, run_lengths: Sequence[int] = (2, 3)) -> Geometry:
    """Cameras on an 800 mm arc (-18..18 deg) behind one window tilted ~20 deg.

    The window tilts toward camera 0's side away from camera 0's view, so the expansion centre of camera 0
    (an outer camera) falls outside its image.

    Args:
        rng: The geometry's random stream (the intrinsics and every pose are drawn from it, in order).
        num_frames: Calibration frames.
        num_cameras: Cameras on the arc.
        stack_added_mm: The glass added in each record of the stacking pose.
        run_lengths: Each calibration frame is drawn for a run of this many neighbouring cameras (the lengths
            taken in turn) and kept only if exactly those cameras see it (partial visibility); ``(2, 3, 4)``
            adds frames seen by all four.

    Returns:
        The geometry.
    """
    if not run_lengths or any(not 1 <= k <= num_cameras for k in run_lengths):
        raise ValueError(f"run_lengths must be 1..{num_cameras} cameras (got {tuple(run_lengths)})")
    if num_cameras < 2:
        raise ValueError("arc needs at least 2 cameras")
    radius = 800.0
    angles = np.radians(np.linspace(-18.0, 18.0, num_cameras))
    rig = []
    for a in angles:  # camera i at angle a on the arc, looking at the arc centre (0, 0, radius)
        center = np.array([radius * math.sin(a), rng.uniform(-3, 3), radius * (1.0 - math.cos(a))])
        jitter = _rot(rng.normal(size=3), math.radians(rng.uniform(0.0, 0.7)))
        rig.append((_rot_y(-a) @ jitter, center))
    cameras, rig_from_world = _rig_cameras(rig, rng)
    world_from_rig = rig_from_world.inverse()

    normal_rig = _tilted(np.array([0.0, 0.0, 1.0]), math.radians(rng.uniform(19.0, 21.0)),
                         math.pi + rng.uniform(-0.1, 0.1))
    near = max(normal_rig @ c for _, c in rig) + rng.uniform(40.0, 60.0)
    window = _window_in_world(normal_rig, near, rig_from_world, 50.0, NBK7_INDEX, 1.0)
    chk = _Checker(PAPER_TARGET, window, cameras)
    down = world_from_rig.R @ np.array([0.0, 1.0, 0.0])
    axes_rig = [(R[:, 2], c) for R, c in rig]

    def axis_x_at(i: int, depth: float) -> float:
        d, c = axes_rig[i]
        return float(c[0] + (depth - c[2]) / d[2] * d[0])

    runs = ([tuple(range(s, s + k)) for k in run_lengths for s in range(num_cameras - k + 1)]
            or [tuple(range(num_cameras))])
    calibration: dict[str, Pose] = {}
    for k, name in enumerate(_frame_names("f", num_frames)):
        run = runs[k % len(runs)]

        def calib_sample(run: tuple[int, ...] = run) -> Pose | None:
            depth = rng.uniform(400.0, 750.0)
            x = np.mean([axis_x_at(i, depth) for i in run]) + rng.uniform(-40, 40)
            c_rig = np.array([x, rng.uniform(-40, 40), depth])
            center = world_from_rig.apply(c_rig)
            viewer = np.mean([cameras[i].center_world for i in run], axis=0)
            pose = _board_pose(PAPER_TARGET, center, center - viewer, down,
                               tilt_rad=math.radians(rng.uniform(8.0, 35.0)),
                               tilt_azimuth_rad=rng.uniform(0.0, 2 * math.pi),
                               roll_rad=math.radians(rng.uniform(-10.0, 10.0)))
            return pose if chk.seen_by(pose) == run else None

        calibration[name] = _draw(f"calibration frame {name} for cameras {run}", calib_sample)

    best: tuple[int, Pose | None] = (0, None)
    for _ in range(300):  # the stacking pose seen by as many cameras as can see it
        center = world_from_rig.apply(np.array([rng.uniform(-60, 60), rng.uniform(-20, 20), rng.uniform(600, 800)]))
        facing = _tilted(window.normal_world, math.radians(rng.uniform(0.0, 2.0)), rng.uniform(0, 2 * math.pi))
        pose = _board_pose(PAPER_TARGET, center, facing, down, roll_rad=math.radians(rng.uniform(-2, 2)))
        n_seen = len(chk.seen_by(pose, stack_added_mm))
        if n_seen > best[0]:
            best = (n_seen, pose)
        if n_seen == num_cameras:
            break
    if best[0] < 2:
        raise RuntimeError("simulator could not place a stacking pose seen by two cameras")
    assert best[1] is not None  # seen by two cameras or more: placed
    s0 = StackingPose("s0", best[1], tuple(float(a) for a in stack_added_mm))
    return Geometry(target=PAPER_TARGET, window=window, cameras=cameras, calibration=calibration, stacking=(s0,))


# --------------------------------------------------------------------------- scale16


def grid(rng: np.random.Generator, num_frames: int = 500, num_cameras: int = 16,
         spacing_mm: float = 120.0, min_views: int = 2,
         stack_added_mm: Sequence[float] = STACK_ADDED_MM) -> Geometry:
    """A near-square grid of paper-like cameras behind one large window (scale tests).

    Args:
        rng: The geometry's random stream (the intrinsics and every pose are drawn from it, in order).
        num_frames: Calibration frames.
        num_cameras: Cameras in the grid.
        spacing_mm: The cameras' spacing; they toe in toward a point 1.5 m ahead.
        min_views: A frame is kept if at least this many cameras see it.
        stack_added_mm: The glass added in each record of the stacking pose.

    Returns:
        The geometry.
    """
    cols = math.ceil(math.sqrt(num_cameras))
    rows = math.ceil(num_cameras / cols)
    rig = []
    for i in range(num_cameras):
        r, c = divmod(i, cols)
        center = np.array([(c - (cols - 1) / 2.0) * spacing_mm, (r - (rows - 1) / 2.0) * spacing_mm, 0.0])
        forward = unit(np.array([0.0, 0.0, 1500.0]) - center)
        x = unit(np.cross(np.array([0.0, 1.0, 0.0]), forward))
        R = np.column_stack([x, np.cross(forward, x), forward])
        jitter = _rot(rng.normal(size=3), math.radians(rng.uniform(0.0, 1.0)))
        rig.append((R @ jitter, center))
    cameras, rig_from_world = _rig_cameras(rig, rng)
    world_from_rig = rig_from_world.inverse()
    normal_rig = _tilted(np.array([0.0, 0.0, 1.0]), math.radians(rng.uniform(2.0, 5.0)), rng.uniform(0, 2 * math.pi))
    near = max(normal_rig @ c for _, c in rig) + rng.uniform(40.0, 60.0)
    window = _window_in_world(normal_rig, near, rig_from_world, 50.0, NBK7_INDEX, 1.0)
    chk = _Checker(PAPER_TARGET, window, cameras)
    down = world_from_rig.R @ np.array([0.0, 1.0, 0.0])
    half_x = (cols - 1) / 2.0 * spacing_mm + 60.0
    half_y = (rows - 1) / 2.0 * spacing_mm + 60.0

    def sample(min_views: int = min_views) -> Pose | None:
        c_rig = np.array([rng.uniform(-half_x, half_x), rng.uniform(-half_y, half_y), rng.uniform(550.0, 900.0)])
        center = world_from_rig.apply(c_rig)
        viewer = world_from_rig.apply(np.array([c_rig[0], c_rig[1], 0.0]))
        pose = _board_pose(PAPER_TARGET, center, center - viewer, down,
                           tilt_rad=math.radians(rng.uniform(8.0, 35.0)),
                           tilt_azimuth_rad=rng.uniform(0.0, 2 * math.pi),
                           roll_rad=math.radians(rng.uniform(-10.0, 10.0)))
        return pose if len(chk.seen_by(pose)) >= min_views else None

    calibration = {name: _draw(f"calibration frame {name}", sample) for name in _frame_names("f", num_frames)}

    best: tuple[int, Pose | None] = (0, None)
    for _ in range(30):
        center = world_from_rig.apply(np.array([rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(700, 900)]))
        facing = _tilted(window.normal_world, math.radians(rng.uniform(0.0, 2.0)), rng.uniform(0, 2 * math.pi))
        pose = _board_pose(PAPER_TARGET, center, facing, down)
        n_seen = len(chk.seen_by(pose, stack_added_mm))
        if n_seen > best[0]:
            best = (n_seen, pose)
    if best[0] < 2:
        raise RuntimeError("simulator could not place a stacking pose seen by two cameras")
    assert best[1] is not None  # seen by two cameras or more: placed
    s0 = StackingPose("s0", best[1], tuple(float(a) for a in stack_added_mm))
    return Geometry(target=PAPER_TARGET, window=window, cameras=cameras, calibration=calibration, stacking=(s0,))


# --------------------------------------------------------------------------- without stacking, 3D bodies


def paper_single_nostack(rng: np.random.Generator, num_frames: int = 12) -> Geometry:
    """paper_single's geometry for the seed, without its stacking pose (most real data).

    Args:
        rng: The geometry's random stream (the intrinsics and every pose are drawn from it, in order).
        num_frames: Calibration frames.

    Returns:
        The geometry.
    """
    return replace(paper_single(rng, num_frames), stacking=())


def binocular_nostack(rng: np.random.Generator, num_frames: int = 15, underwater: bool = False,
                      tilt_deg: float | None = None) -> Geometry:
    """binocular's geometry for the seed (and options), without its stacking pose.

    Args:
        rng: The geometry's random stream (the intrinsics and every pose are drawn from it, in order).
        num_frames: Calibration frames.
        underwater: A 10 mm N-BK7 port with water behind (else 50 mm N-BK7 in air).
        tilt_deg: The window's tilt from the rig's z axis (None: drawn in 2-5 deg).

    Returns:
        The geometry.
    """
    return replace(binocular(rng, num_frames, underwater=underwater, tilt_deg=tilt_deg), stacking=())


def _step_body(depth_mm: float, cells: int = 11, pitch_mm: float = 15.0) -> Target:
    """A PTV-like body: ``cells`` x ``cells`` points, ``pitch_mm`` apart, on three levels
    (0, depth/2, depth toward the cameras, i.e. target z = 0, -depth/2, -depth) in a diagonal pattern."""
    pts = {}
    for r in range(cells):
        for c in range(cells):
            pts[r * cells + c] = (c * pitch_mm, r * pitch_mm, -depth_mm * ((r + c) % 3) / 2.0)
    return Target(type="points3d", points=pts)


def _look_at(center: np.ndarray, point: np.ndarray) -> np.ndarray:
    """rig_from_cam rotation of a camera at ``center`` whose optical axis goes through ``point`` (y down)."""
    z = unit(np.asarray(point, float) - center)
    x = unit(np.cross(np.array([0.0, 1.0, 0.0]), z))
    return np.column_stack([x, np.cross(z, x), z])


def body3d(rng: np.random.Generator, depth_mm: float = 40.0, distance_mm: float = 500.0,
           spacing_mm: float = 160.0, glass_mm: float = 6.0, cells: int = 11, pitch_mm: float = 15.0) -> Geometry:
    """Four paper-like cameras in a 2 x 2 grid aimed at a 3D body behind one N-BK7 window (tilted 1-3 deg,
    30-50 mm ahead) with water behind; one calibration frame (the body, tilted up to 5 deg), seen whole by
    every camera.

    Args:
        rng: The geometry's random stream (the intrinsics and every pose are drawn from it, in order).
        depth_mm: The body's depth (its three levels span it).
        distance_mm: The body's distance ahead of the rig.
        spacing_mm: The cameras' spacing.
        glass_mm: The window's thickness.
        cells: Body points per side of each level.
        pitch_mm: The body points' spacing.

    Returns:
        The geometry.
    """
    target = _step_body(depth_mm, cells, pitch_mm)
    ahead = np.array([0.0, 0.0, distance_mm])
    rig = []
    for i in range(4):
        r, c = divmod(i, 2)
        center = np.array([(c - 0.5) * spacing_mm, (r - 0.5) * spacing_mm * 0.75, 0.0])
        jitter = _rot(rng.normal(size=3), math.radians(rng.uniform(0.0, 0.5)))
        rig.append((_look_at(center, ahead) @ jitter, center))
    cameras, rig_from_world = _rig_cameras(rig, rng)
    normal_rig = _tilted(np.array([0.0, 0.0, 1.0]), math.radians(rng.uniform(1.0, 3.0)), rng.uniform(0, 2 * math.pi))
    near = max(normal_rig @ c for _, c in rig) + rng.uniform(30.0, 50.0)
    window = _window_in_world(normal_rig, near, rig_from_world, glass_mm, NBK7_INDEX, WATER_INDEX)
    world_from_rig = rig_from_world.inverse()
    _, pts = target.points_3d()
    centroid = pts.mean(axis=0)
    chk = _Checker(target, window, cameras)

    def sample() -> Pose | None:
        R = world_from_rig.R @ _rot(rng.normal(size=3), math.radians(rng.uniform(0.0, 5.0)))
        center = world_from_rig.apply(ahead + np.array([rng.uniform(-10, 10), rng.uniform(-10, 10), 0.0]))
        pose = Pose(R, center - R @ centroid)
        return pose if len(chk.seen_by(pose)) == len(cameras) else None

    return Geometry(target=target, window=window, cameras=cameras, calibration={"f000": _draw("the 3D body", sample)})


# --------------------------------------------------------------------------- ptv_multiplane

PTV_IMAGE_SIZE = (1280, 1024)
PTV_FOCAL_PX = 3400.0  # nominal: a 130 mm body about 700 px wide at 600 mm
PTV_PLANE_ID_STEP = 1000  # id of dot i of plane p: p * step + i (as `import openptv` numbers multi_planes)
PTV_PIXEL_STEP_PX = 0.5  # OpenPTV's .crd centres as found on real data: quantised to half pixels


def ptv_plate_body(grid: tuple[int, int] = (14, 8), size_mm: tuple[float, float] = (130.0, 70.0),
                   plane_z_mm: Sequence[float] = (0.0, -5.0, -10.0, -15.0)) -> Target:
    """OpenPTV's multi-plane body in its own world frame: one dot plate imaged at several depths, all one rigid
    body.

    Args:
        grid: The plate's dots (columns, rows).
        size_mm: The plate's size, centred on the z axis.
        plane_z_mm: The z of each plane (z toward the cameras).

    Returns:
        A ``points3d`` target; dot i of plane p has id ``p * PTV_PLANE_ID_STEP + i``.

    Raises:
        ValueError: more dots per plane than ``PTV_PLANE_ID_STEP``.
    """
    cols, rows = grid
    xs = np.linspace(-size_mm[0] / 2, size_mm[0] / 2, cols)
    ys = np.linspace(-size_mm[1] / 2, size_mm[1] / 2, rows)
    if cols * rows > PTV_PLANE_ID_STEP:
        raise ValueError(f"at most {PTV_PLANE_ID_STEP} dots per plane")
    pts = {}
    for p, z in enumerate(plane_z_mm):
        for i, (y, x) in enumerate((y, x) for y in ys for x in xs):
            pts[p * PTV_PLANE_ID_STEP + i] = (float(x), float(y), float(z))
    return Target(type="points3d", points=pts)


def ptv_plane_of(ids: np.ndarray) -> np.ndarray:
    """The plane index of each dot id of :func:`ptv_plate_body`."""
    return np.asarray(ids, dtype=np.int64) // PTV_PLANE_ID_STEP


def ptv_misplaced(target: Target, shift_mm: float, tilt_deg: float, rng: np.random.Generator) -> Target:
    """:func:`ptv_plate_body`'s target where a real plate's placements put its dots. Observed in place of the
    declared body, one frame (one rigid body) then carries each placement's error, as OpenPTV's multi-plane
    calibrations do.

    Args:
        target: The declared body (:func:`ptv_plate_body`).
        shift_mm: Each plane is moved rigidly by a shift of this RMS (random direction).
        tilt_deg: ... and turned by this RMS about its centre (random axis).
        rng: The random stream.

    Returns:
        The misplaced body, the same ids.
    """
    ids, pts = target.points_3d()
    plane = ptv_plane_of(ids)
    moved = pts.copy()
    for p in np.unique(plane):
        on = plane == p
        centre = pts[on].mean(axis=0)
        R = rotation_from_rotvec(math.radians(tilt_deg) * rng.normal(size=3) / math.sqrt(3.0))
        moved[on] = (pts[on] - centre) @ R.T + centre + shift_mm * rng.normal(size=3) / math.sqrt(3.0)
    return Target(type="points3d", points={int(i): (float(x[0]), float(x[1]), float(x[2])) for i, x in zip(ids, moved)})


def ptv_multiplane(rng: np.random.Generator, grid: tuple[int, int] = (14, 8), glass_mm: float = 6.0,
                   tilt_range_deg: tuple[float, float] = (12.0, 26.0),
                   range_mm: tuple[float, float] = (560.0, 620.0)) -> Geometry:
    """An OpenPTV multi-plane calibration as a user imports it (``ari-sfm import openptv``).

    Built in OpenPTV's world frame, which is the body's frame ``f000``: the dot plate at 4 depths
    (:func:`ptv_plate_body`), the glass vector G (OpenPTV's: from the water toward the cameras, |G|
    the distance of the glass-water face from the origin, 7-10 mm, tilted 0-1 deg from z), 4 cameras
    oblique to the window, each aimed near the body's centre. The window is declared as the importer
    declares it (:func:`ari_sfm.openptv.conventions.window_plane` of G and the thickness, in frame
    ``f000``); the focal hints are the true focal lengths (OpenPTV's own cc, rounded to 0.1 px); pixels
    are quantised to 0.5 px (``pixel_step_px``).

    Args:
        rng: The geometry's random stream (the intrinsics and every pose are drawn from it, in order).
        grid: The plate's dots (columns, rows).
        glass_mm: The window's thickness.
        tilt_range_deg: The cameras' obliquity to the window, drawn in this range.
        range_mm: The cameras' distance from the body, drawn in this range.

    Returns:
        The geometry, with its declared window plane.

    Raises:
        RuntimeError: the body is not whole in some camera.
    """
    from ari_sfm.openptv.conventions import window_plane
    from ari_sfm.records import WindowPlane

    target = ptv_plate_body(grid)
    _, pts = target.points_3d()
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    g_hat = _tilted(np.array([0.0, 0.0, 1.0]), math.radians(rng.uniform(0.0, 1.0)), rng.uniform(0, 2 * math.pi))
    glass = g_hat * rng.uniform(7.0, 10.0)  # the glass-water face 7-10 mm above the top plane (z = 0)
    normal_body, point_body = window_plane(glass, glass_mm)
    rig = []  # (body_from_cam rotation, centre in the body frame)
    for k in range(4):
        tilt = math.radians(rng.uniform(*tilt_range_deg))
        azimuth = math.radians(45.0 + 90.0 * k + rng.uniform(-15.0, 15.0))
        centre_k = centre + rng.uniform(*range_mm) * _tilted(g_hat, tilt, azimuth)
        aim = centre + np.array([rng.uniform(-10, 10), rng.uniform(-10, 10), 0.0])
        roll = _rot((0.0, 0.0, 1.0), math.radians(rng.uniform(-5.0, 5.0)))
        rig.append((_look_at(centre_k, aim) @ roll, centre_k))
    cam_from_world = _in_world(rig)
    cameras = []
    for i in range(4):
        K = _intrinsics(rng, PTV_IMAGE_SIZE, PTV_FOCAL_PX, focal_spread=0.03)
        K[1, 1] = K[0, 0] = round(float(K[0, 0]), 1)  # the hint is OpenPTV's cc: the focal length itself
        cameras.append(CameraTruth(name=f"cam{i + 1}", K=K, image_size=PTV_IMAGE_SIZE,
                                   cam_from_world=cam_from_world[i], focal_hint_px=float(K[0, 0])))
    rig_from_world = Pose(rig[0][0], rig[0][1])  # body_from_cam1: world = cam1
    window = _window_in_world(normal_body, float(normal_body @ point_body), rig_from_world, glass_mm,
                              NBK7_INDEX, WATER_INDEX)
    world_from_body = rig_from_world.inverse()
    geometry = Geometry(target=target, window=window, cameras=tuple(cameras), calibration={"f000": world_from_body},
                        declared_plane=WindowPlane("f000", normal_body, point_body),
                        pixel_step_px=PTV_PIXEL_STEP_PX)
    chk = _Checker(target, window, geometry.cameras, clearance_mm=3.0)
    missing = [c.name for c in geometry.cameras if not chk.sees(c, world_from_body)]
    if missing:
        raise RuntimeError(f"simulator: the body is not whole in {', '.join(missing)}; relax the scenario")
    return geometry


# --------------------------------------------------------------------------- two-window tanks

TANK_IMAGE_SIZE = (1280, 1024)  # test_cavity's cameras
TANK_FOCAL_PX = 4800.0  # an 80 mm body about 700 px wide at 550 mm


def cavity_body(columns: int = 15, pitch_mm: float = 5.0) -> Target:
    """A test_cavity-like 3D body: 5 rows of dots (y = -25, -15, 0, 15, 25 mm) on three levels (z = 8, 0, -8,
    0, 8 mm), centred on the origin; dots visible from both sides.

    Args:
        columns: Dots per row, along x.
        pitch_mm: Their spacing.

    Returns:
        A ``points3d`` target, ids from 1.
    """
    rows = ((-25.0, 8.0), (-15.0, 0.0), (0.0, -8.0), (15.0, 0.0), (25.0, 8.0))
    xs = (np.arange(columns) - (columns - 1) / 2.0) * pitch_mm
    pts, k = {}, 1
    for y, z in rows:
        for x in xs:
            pts[k] = (float(x), y, z)
            k += 1
    return Target(type="points3d", points=pts)


def _tank_camera(rng: np.random.Generator, wall_normal: np.ndarray, azimuth_deg: float,
                 tilt_range_deg: tuple[float, float], range_mm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(tank_from_cam rotation, centre) of a camera looking through the wall whose inward normal is
    ``wall_normal``, tilted 12-26 deg from it toward ``azimuth_deg``, aimed near the tank's centre."""
    tilt = math.radians(rng.uniform(*tilt_range_deg))
    axis = _tilted(wall_normal, tilt, math.radians(azimuth_deg + rng.uniform(-15.0, 15.0)))
    centre = -rng.uniform(*range_mm) * axis
    aim = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-5, 5)])
    roll = _rot((0.0, 0.0, 1.0), math.radians(rng.uniform(-5.0, 5.0)))
    return _look_at(centre, aim) @ roll, centre


def tank(rng: np.random.Generator, adjacent: bool = False, frames: int = 5, glass_mm: float = 6.0,
         wall_mm: float = 120.0, tilt_range_deg: tuple[float, float] = (12.0, 26.0),
         range_mm: tuple[float, float] = (480.0, 600.0)) -> Geometry:
    """A tank seen through two walls, 2 + 2 cameras (test_cavity's shape), in the tank's frame first.

    Walls: the ``front`` wall's inner (glass-water) face at z = -wall_mm, normal +z (cameras at z < 0); the
    ``back`` wall at z = +wall_mm, normal -z (``adjacent``: the ``side`` wall at x = -wall_mm, normal +x);
    each wall tilted 0-1 deg; N-BK7, water inside. Two cameras per wall, oblique to it (one to each side).
    The :func:`cavity_body` in several poses near the centre (shifted up to 12 mm, turned up to 8 deg;
    facing 45 deg between the walls when adjacent), each seen whole by every camera. World = the first camera.

    Args:
        rng: The geometry's random stream (the intrinsics and every pose are drawn from it, in order).
        adjacent: The second wall at 90 deg to the first (else opposite it).
        frames: The body's poses.
        glass_mm: The walls' thickness.
        wall_mm: The walls' inner faces' distance from the tank's centre.
        tilt_range_deg: The cameras' obliquity to their wall, drawn in this range.
        range_mm: The cameras' distance from the centre, drawn in this range.

    Returns:
        The geometry, with its two windows.
    """
    target = cavity_body()
    inward = [np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]) if adjacent else np.array([0.0, 0.0, -1.0])]
    names = ["front", "side" if adjacent else "back"]
    rig, groups = [], []
    for w, n in enumerate(inward):
        n_w = _tilted(n, math.radians(rng.uniform(0.0, 1.0)), rng.uniform(0, 2 * math.pi))
        inward[w] = n_w
        for side in (0.0, 180.0):
            rig.append(_tank_camera(rng, n_w, side + (90.0 if adjacent and w == 1 else 0.0), tilt_range_deg,
                                    range_mm))
        groups.append((names[w], (f"cam{2 * w + 1}", f"cam{2 * w + 2}")))
    cam_from_world = _in_world(rig)
    cameras = []
    for i in range(4):
        K = _intrinsics(rng, TANK_IMAGE_SIZE, TANK_FOCAL_PX, focal_spread=0.03)
        cameras.append(CameraTruth(name=f"cam{i + 1}", K=K, image_size=TANK_IMAGE_SIZE,
                                   cam_from_world=cam_from_world[i], focal_hint_px=round(float(K[0, 0]), 1)))
    rig_from_world = Pose(rig[0][0], rig[0][1])  # tank_from_cam1: world = cam1
    windows = []
    for (name, cams), n_w in zip(groups, inward):
        # near (camera-side) face: the inner face at wall_mm from the centre, the glass outside it
        near = -(wall_mm + glass_mm)
        windows.append(WindowGroup(name, _window_in_world(n_w, near, rig_from_world, glass_mm, NBK7_INDEX,
                                                          WATER_INDEX), cams))
    by_camera = {c: g.window for g in windows for c in g.cameras}
    world_from_tank = rig_from_world.inverse()
    _, pts = target.points_3d()
    chk = _Checker(target, windows[0].window, tuple(cameras), clearance_mm=20.0, windows=by_camera)
    facing = unit(inward[0] + inward[1]) if adjacent else inward[0]
    base = _look_at(np.zeros(3), -facing)  # the body's z axis toward the cameras of the first wall

    def sample() -> Pose | None:
        turn = _rot(rng.normal(size=3), math.radians(rng.uniform(0.0, 8.0)))
        R = world_from_tank.R @ base @ turn
        centre = world_from_tank.apply(rng.uniform(-12.0, 12.0, 3))
        pose = Pose(R, centre - R @ pts.mean(axis=0))
        return pose if len(chk.seen_by(pose)) == len(cameras) else None

    calibration = {name: _draw(f"the body's pose {name}", sample) for name in _frame_names("f", frames)}
    return Geometry(target=target, window=windows[0].window, cameras=tuple(cameras), calibration=calibration,
                    windows=tuple(windows))


# --------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class ScenarioOverrides:
    """Options of a scenario's geometry, each None where the scenario keeps its own value.

    The fields are the builders' keyword options (``paper_single``, ``binocular``, ``arc``, ``grid``,
    ``body3d``, ``ptv_multiplane``, ``tank``); a scenario accepts those its builder takes and its
    registry entry does not fix (:func:`check_overrides`)."""

    num_frames: int | None = None  # calibration frames (paper_single, binocular, arc, grid)
    num_cameras: int | None = None  # cameras (arc, grid)
    frames: int | None = None  # the body's poses (tank)
    perpendicular: bool | None = None  # the window normal within 0.05 deg of the optical axis (paper_single)
    underwater: bool | None = None  # a 10 mm glass port with water behind it (binocular)
    adjacent: bool | None = None  # the two walls at 90 deg instead of opposite (tank)
    target: Target | None = None  # the calibration target (paper_single)
    stack_added_mm: tuple[float, ...] | None = None  # glass added in the stacking pose (paper_single, binocular, ...)
    stage_mm: tuple[float, ...] | None = None  # the stage frames' positions (binocular)
    depth_band_mm: float | None = None  # depth range of the calibration frames (binocular)
    lateral_scale: float | None = None  # lateral spread of the calibration frames (binocular)
    tilt_deg: float | None = None  # the window's tilt (binocular; None there: drawn)
    run_lengths: tuple[int, ...] | None = None  # consecutive cameras a frame is seen by (arc)
    spacing_mm: float | None = None  # camera spacing (grid, body3d)
    min_views: int | None = None  # cameras each frame is seen by, at least (grid)
    depth_mm: float | None = None  # the body's depth (body3d)
    distance_mm: float | None = None  # the body's distance (body3d)
    glass_mm: float | None = None  # window thickness (body3d, ptv_multiplane, tank)
    cells: int | None = None  # body points per side (body3d)
    pitch_mm: float | None = None  # body point spacing (body3d)
    grid: tuple[int, int] | None = None  # dots of the plate (ptv_multiplane)
    tilt_range_deg: tuple[float, float] | None = None  # cameras' obliquity to the window (ptv_multiplane, tank)
    range_mm: tuple[float, float] | None = None  # cameras' distance (ptv_multiplane, tank)
    wall_mm: float | None = None  # the walls' distance from the tank's centre (tank)

    def given(self) -> tuple[str, ...]:
        """The names of the fields set (not None), in field order."""
        return tuple(f.name for f in fields(self) if getattr(self, f.name) is not None)

    def merged(self, other: ScenarioOverrides) -> ScenarioOverrides:
        """These overrides with ``other``'s set fields on top."""
        return replace(self, **{name: getattr(other, name) for name in other.given()})


@dataclass(frozen=True)
class ScenarioSpec:
    """How a scenario name is built: builder, its fixed options, images by default."""

    build: Callable[..., Geometry]
    options: ScenarioOverrides = ScenarioOverrides()  # fixed by the scenario (not offered to its users)
    images: bool = False
    rng_name: str = ""  # scenarios sharing a stream (paper_single*) get the same geometry for a seed


REGISTRY: dict[str, ScenarioSpec] = {
    "paper_single": ScenarioSpec(paper_single, rng_name="paper_single"),
    "paper_single_images": ScenarioSpec(paper_single, images=True, rng_name="paper_single"),
    "paper_single_dots": ScenarioSpec(paper_single, ScenarioOverrides(target=DOT_TARGET), images=True,
                                      rng_name="paper_single_dots"),
    "paper_single_perpendicular": ScenarioSpec(paper_single, ScenarioOverrides(perpendicular=True),
                                               rng_name="paper_single_perpendicular"),
    "binocular": ScenarioSpec(binocular, rng_name="binocular"),
    "binocular_underwater": ScenarioSpec(binocular, ScenarioOverrides(underwater=True),
                                         rng_name="binocular_underwater"),
    "arc4": ScenarioSpec(arc, rng_name="arc4"),
    "scale16": ScenarioSpec(grid, rng_name="scale16"),
    "paper_single_nostack": ScenarioSpec(paper_single_nostack, rng_name="paper_single"),
    "binocular_nostack": ScenarioSpec(binocular_nostack, rng_name="binocular"),
    "binocular_underwater_oblique": ScenarioSpec(binocular_nostack, ScenarioOverrides(underwater=True, tilt_deg=10.0),
                                                 rng_name="binocular_underwater_oblique"),
    "body3d_water": ScenarioSpec(body3d, rng_name="body3d"),
    "body3d_shallow": ScenarioSpec(body3d, ScenarioOverrides(depth_mm=15.0, distance_mm=600.0), rng_name="body3d"),
    "ptv_multiplane": ScenarioSpec(ptv_multiplane, rng_name="ptv_multiplane"),
    "tank_opposite": ScenarioSpec(tank, rng_name="tank_opposite"),
    "tank_adjacent": ScenarioSpec(tank, ScenarioOverrides(adjacent=True), rng_name="tank_adjacent"),
}
assert set(REGISTRY) == set(SCENARIOS)


def scenario_options(name: str) -> tuple[str, ...]:
    """The overrides scenario ``name`` accepts: its builder's options less those its registry entry fixes.

    Args:
        name: A scenario of :data:`REGISTRY`.

    Returns:
        The :class:`ScenarioOverrides` field names, in the builder's order.
    """
    spec = REGISTRY[name]
    fixed = spec.options.given()
    return tuple(p for p in inspect.signature(spec.build).parameters if p != "rng" and p not in fixed)


def check_overrides(name: str, overrides: ScenarioOverrides) -> None:
    """Refuse the overrides scenario ``name`` does not accept (:func:`scenario_options`).

    Args:
        name: A scenario of :data:`REGISTRY`.
        overrides: The overrides asked for.

    Raises:
        ValueError: one line naming the options given that the scenario does not have, and those it has.
    """
    allowed = scenario_options(name)
    bad = [k for k in overrides.given() if k not in allowed]
    if bad:
        raise ValueError(f"scenario {name!r} has no option {', '.join(bad)}; options: {', '.join(allowed)}")


def build_geometry(name: str, rng: np.random.Generator, overrides: ScenarioOverrides | None = None) -> Geometry:
    """The truth geometry of scenario ``name``, checked (:func:`~ari_sfm.simulate.scene.check_geometry`).

    Args:
        name: A scenario of :data:`REGISTRY`.
        rng: The geometry's random stream.
        overrides: Options of its builder (None: the scenario as registered); checked by :func:`check_overrides`.

    Returns:
        The geometry.

    Raises:
        ValueError: an option the scenario does not have.
        RuntimeError: the simulator could not place a pose the scenario needs.
    """
    spec = REGISTRY[name]
    overrides = overrides or ScenarioOverrides()
    check_overrides(name, overrides)
    options = spec.options.merged(overrides)
    geometry = spec.build(rng, **{k: getattr(options, k) for k in options.given()})
    check_geometry(geometry)
    return geometry

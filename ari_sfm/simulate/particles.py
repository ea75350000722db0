"""A simulated particle experiment behind a window, with exact Snell physics.

A lab calibrates its rig (rig A) on a 3D calibration body (or a planar board,
``calibration_target="board"``), then records tracer particles in the water behind the window. Between the
two, some cameras may drift (rig B = rig A with those cameras moved by a small rigid motion; the
window and camera 0, the world, stay). :func:`simulate_particle_experiment`
builds the whole experiment in memory; :func:`write_particle_experiment`
writes it in the data contract's form (DATASET_FORMAT.md, 1.2)::

    OUT/calibration/   rig.yaml + observations.json: the target calibration of rig A
    OUT/experiment/    rig.yaml (interface, cameras, particles:), particles.parquet,
                       images/<camera>/<frame:05d>.png (Gaussian particle images, a few frames;
                       ``look="tank"``: as a real tank looks, ``bit_depth=16``: .tif)
    OUT/truth/         rig_a.json, rig_b.json (calibration.json form, model truth),
                       particles.parquet (frame, particle, x, y, z),
                       detections.parquet (row-aligned with experiment/particles.parquet:
                       frame, camera, particle: the true particle of each detection)

Every pixel comes from :class:`~ari_sfm.models.exact.ExactModel`.
"""
from __future__ import annotations

import logging
import math
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ari_sfm.calibration.record import Calibration
from ari_sfm.geometry import Pose, rotation_from_rotvec, unit
from ari_sfm.io import calibration_to_json, parse_calibration
from ari_sfm.records import Dataset, Target
from ari_sfm.simulate.particle_images import TankLook, render_particle_image, render_tank_frame
from ari_sfm.simulate.scenarios import (
    NBK7_INDEX,
    WATER_INDEX,
    _board_pose,
    _Checker,
    _draw,
    _frame_names,
    _look_at,
    _rig_cameras,
    _rot,
    _step_body,
    _tilted,
    _window_in_world,
)
from ari_sfm.simulate.scene import Geometry, WindowGroup, check_geometry, observe, project, to_dataset, truth_dict

log = logging.getLogger(__name__)

IMAGE_MARGIN_PX = 5.0  # a particle image closer than this to the border is not detected
LOOKS = ("plain", "tank")  # how the particle images are rendered (ParticleSimOptions.look)
CALIBRATION_TARGETS = ("body", "board")  # what rig A is calibrated on (ParticleSimOptions.calibration_target)
BOARD = Target(type="checkerboard", inner_corners=(11, 8), square_mm=8.0)  # "board": 80 x 56 mm of corners
BOARD_TILT_DEG = (10.0, 40.0)  # "board": each view tilted this much from facing the rig, about a random in-plane axis


@dataclass(frozen=True)
class ParticleSimOptions:
    """What :func:`simulate_particle_experiment` builds (defaults: 4 cameras, 10 frames x 2000 particles)."""

    num_cameras: int = 4  # on a ring around the volume's axis
    particles_per_frame: int = 2000
    num_frames: int = 10
    sigma_px: float = 0.1  # detection noise per coordinate
    volume_mm: tuple[float, float, float] = (60.0, 40.0, 30.0)  # box size, centred on the rig's axis
    distance_mm: float = 400.0  # rig to the volume's centre
    ring_radius_mm: float = 100.0  # camera centres on this circle around the axis
    glass_mm: float = 10.0  # window thickness (N-BK7), water behind
    drift_cameras: tuple[int, ...] = (1, 2, 3)  # camera indices moved after the target calibration
    drift_deg: float = 0.05  # rotation of each drifted camera (random axis)
    drift_mm: float = 0.3  # translation of each drifted camera (random direction)
    calibration_frames: int = 3  # views of the calibration target
    calibration_target: str = "body"  # "body": a 3D body (three levels); "board": a planar checkerboard, tilted
    calibration_sigma_px: float = 0.05  # corner noise of the calibration body
    diameter_px: float = 3.0  # particle image diameter (e^-2) for rendering
    look: str = "plain"  # rendered images: "plain" (flat background, 8-bit noise) or "tank" (TankLook: a real tank's)
    bit_depth: int = 8  # of the rendered images: 8 (PNG) or 16 (TIFF)
    k1: float = 0.0  # radial lens distortion of every camera (OpenCV k1; e.g. -0.03..-0.06)
    windows: int = 1  # 2: a tank seen through two opposite walls, half the cameras behind each (DATASET_FORMAT 1.3)
    seed: int = 0


@dataclass(frozen=True)
class ParticleExperiment:
    """The experiment in memory. Frames are numbered 0 .. num_frames - 1."""

    options: ParticleSimOptions
    rig_a: Geometry  # the target calibration: cameras, window, body poses
    rig_b: Geometry  # the experiment: rig A with the drifted cameras (body poses as in rig A)
    calibration_dataset: Dataset  # rig A's noisy body observations (root: a placeholder)
    truth_a: Calibration  # model truth
    truth_b: Calibration
    volume_min_mm: np.ndarray  # (3,) the box, world frame (= camera 0's)
    volume_max_mm: np.ndarray
    positions: tuple[np.ndarray, ...]  # per frame (P, 3) world
    detections: tuple[dict[str, np.ndarray], ...]  # per frame: camera -> (N, 2) noisy pixels (shuffled)
    particle_ids: tuple[dict[str, np.ndarray], ...]  # per frame: camera -> (N,) row of positions[frame]
    exact_pixels: tuple[dict[str, np.ndarray], ...] = field(default=(), repr=False)  # noise-free, same rows

    @property
    def cameras(self) -> list[str]:
        return [c.name for c in self.rig_a.cameras]


def _rng(seed: int, stream: int) -> np.random.Generator:
    """0 geometry, 1 particles, 2 detection noise, 3 image noise."""
    return np.random.default_rng([int(seed), zlib.crc32(b"particles"), stream])


def _check(options: ParticleSimOptions) -> None:
    o = options
    if not 2 <= o.num_cameras <= 8:
        raise ValueError(f"num_cameras must be 2..8 (got {o.num_cameras})")
    if o.particles_per_frame < 1 or o.num_frames < 1:
        raise ValueError("particles_per_frame and num_frames must be >= 1")
    if not (o.sigma_px >= 0 and o.drift_deg >= 0 and o.drift_mm >= 0 and o.diameter_px > 0):
        raise ValueError("sigma_px, drift_deg, drift_mm must be >= 0 and diameter_px > 0")
    if o.calibration_frames < 1:
        raise ValueError(f"calibration_frames must be >= 1 (got {o.calibration_frames})")
    if o.calibration_target not in CALIBRATION_TARGETS:
        raise ValueError(f"calibration_target must be one of {', '.join(CALIBRATION_TARGETS)} "
                         f"(got {o.calibration_target!r})")
    if o.calibration_target == "board" and o.windows != 1:
        raise ValueError("a board is seen from one side: calibration_target 'board' needs windows 1")
    if o.look not in LOOKS:
        raise ValueError(f"look must be one of {', '.join(LOOKS)} (got {o.look!r})")
    if o.bit_depth not in (8, 16):
        raise ValueError(f"bit_depth must be 8 or 16 (got {o.bit_depth})")
    if o.windows not in (1, 2) or (o.windows == 2 and o.num_cameras < 4):
        raise ValueError(f"windows must be 1, or 2 with at least 4 cameras (got {o.windows}, {o.num_cameras} cameras)")
    bad = [c for c in o.drift_cameras if not 0 <= c < o.num_cameras]
    if bad:
        raise ValueError(f"drift_cameras {bad} not among the {o.num_cameras} cameras")


def _rig_a(options: ParticleSimOptions, rng: np.random.Generator) -> tuple[Geometry, np.ndarray]:
    """Cameras on a ring aimed at the volume's centre, the window, the body views; and that centre (world).
    With two windows the second half of the ring faces the volume from the other side, through the
    opposite wall (the volume's centre between the walls)."""
    o = options
    ahead = np.array([0.0, 0.0, o.distance_mm])
    back = o.windows == 2
    rig = []
    for i in range(o.num_cameras):
        a = math.pi / 4 + 2 * math.pi * i / o.num_cameras
        center = np.array([o.ring_radius_mm * math.cos(a), o.ring_radius_mm * math.sin(a), 0.0])
        if back and i >= o.num_cameras // 2:  # mirrored through the volume's centre along the axis
            center = center * np.array([1.0, 1.0, 0.0]) + np.array([0.0, 0.0, 2 * o.distance_mm])
        jitter = _rot(rng.normal(size=3).tolist(), math.radians(rng.uniform(0.0, 0.5)))
        rig.append((_look_at(center, ahead) @ jitter, center))
    cameras, rig_from_world = _rig_cameras(rig, rng)
    if o.k1:
        cameras = tuple(replace(c, dist=np.array([o.k1, 0.0, 0.0, 0.0, 0.0])) for c in cameras)
    normal_rig = _tilted(np.array([0.0, 0.0, 1.0]), math.radians(rng.uniform(1.0, 3.0)), rng.uniform(0, 2 * math.pi))
    front = [c for k, (_, c) in enumerate(rig) if not back or k < o.num_cameras // 2]
    near = max(normal_rig @ c for c in front) + rng.uniform(30.0, 50.0)
    window = _window_in_world(normal_rig, near, rig_from_world, o.glass_mm, NBK7_INDEX, WATER_INDEX)
    groups: tuple[WindowGroup, ...] = ()
    by_camera = None
    if back:  # the opposite wall as far beyond the volume's centre as the front one is before it
        half = o.num_cameras // 2
        normal_back = _tilted(np.array([0.0, 0.0, -1.0]), math.radians(rng.uniform(1.0, 3.0)),
                              rng.uniform(0, 2 * math.pi))
        far = max(normal_back @ c for _, c in rig[half:]) + rng.uniform(30.0, 50.0)
        second = _window_in_world(normal_back, far, rig_from_world, o.glass_mm, NBK7_INDEX, WATER_INDEX)
        names = [c.name for c in cameras]
        groups = (WindowGroup("front", window, tuple(names[:half])), WindowGroup("back", second, tuple(names[half:])))
        by_camera = {c: g.window for g in groups for c in g.cameras}
    world_from_rig = rig_from_world.inverse()
    board = o.calibration_target == "board"
    target = BOARD if board else _step_body(depth_mm=40.0, cells=9, pitch_mm=12.0)
    _, pts = target.points_3d()
    centroid = pts.mean(axis=0)
    chk = _Checker(target, window, cameras, windows=by_camera)

    def sample() -> Pose | None:
        if board:  # facing the rig (its z along the rig's axis, away from the cameras), tilted, rolled a little
            c = world_from_rig.apply(ahead + rng.uniform(-15, 15, size=3))
            pose = _board_pose(target, c, world_from_rig.R[:, 2], world_from_rig.R[:, 1],
                               tilt_rad=math.radians(rng.uniform(*BOARD_TILT_DEG)),
                               tilt_azimuth_rad=rng.uniform(0.0, 2 * math.pi),
                               roll_rad=math.radians(rng.uniform(-15, 15)))
        else:
            R = world_from_rig.R @ _rot(rng.normal(size=3).tolist(), math.radians(rng.uniform(0.0, 8.0)))
            pose = Pose(R, world_from_rig.apply(ahead + rng.uniform(-15, 15, size=3)) - R @ centroid)
        return pose if len(chk.seen_by(pose)) == len(cameras) else None

    frames = {name: _draw(f"the calibration {o.calibration_target}", sample)
              for name in _frame_names("f", o.calibration_frames)}
    geometry = Geometry(target=target, window=window, cameras=cameras, calibration=frames, windows=groups)
    check_geometry(geometry)
    return geometry, world_from_rig.apply(ahead)


def _drifted(rig_a: Geometry, options: ParticleSimOptions, rng: np.random.Generator) -> Geometry:
    """Rig B: each drifted camera turned by ``drift_deg`` about its centre and moved by ``drift_mm``."""
    cams = []
    for i, cam in enumerate(rig_a.cameras):
        if i in options.drift_cameras and (options.drift_deg > 0 or options.drift_mm > 0):
            R_d = rotation_from_rotvec(unit(rng.normal(size=3)) * math.radians(options.drift_deg))
            move_world = unit(rng.normal(size=3)) * options.drift_mm
            centre = cam.center_world + move_world
            R = R_d @ cam.cam_from_world.R
            cam = replace(cam, cam_from_world=Pose(R, -R @ centre))
        cams.append(cam)
    return replace(rig_a, cameras=tuple(cams))  # the body poses stay (camera 0, the world, does not move)


def _calibration(geometry: Geometry, seed: int) -> Calibration:
    from ari_sfm.io.dataset import target_to_json

    data = truth_dict(geometry, "particles", seed, 0.0)
    data["target"] = target_to_json(geometry.target)  # scene's truth form lists points3d as arrays
    for key in ("scenario", "seed", "sigma_px", "image_scale", "stacking", "reconstruction_points_world"):
        data.pop(key, None)
    return parse_calibration(data, "<simulated truth>")


def simulate_particle_experiment(options: ParticleSimOptions = ParticleSimOptions()) -> ParticleExperiment:
    """Build rig A, its body calibration, rig B, the particles and their detections (see the module doc)."""
    from ari_sfm.simulate import PLACEHOLDER_ROOT

    _check(options)
    o = options
    rig_a, centre = _rig_a(o, _rng(o.seed, 0))
    rig_b = _drifted(rig_a, o, _rng(o.seed, 0))
    exact_obs = observe(rig_a)
    noise = _rng(o.seed, 4)
    noisy = tuple(replace(ob, pixels=ob.pixels + noise.normal(0.0, o.calibration_sigma_px, ob.pixels.shape))
                  for ob in exact_obs)
    dataset = to_dataset(rig_a, noisy, PLACEHOLDER_ROOT, seen=exact_obs)
    half = 0.5 * np.asarray(o.volume_mm, float)
    vmin, vmax = centre - half, centre + half
    rng_p, rng_n = _rng(o.seed, 1), _rng(o.seed, 2)
    positions, detections, ids, exact = [], [], [], []
    for _ in range(o.num_frames):
        X = rng_p.uniform(vmin, vmax, size=(o.particles_per_frame, 3))
        det, pid, ex = {}, {}, {}
        for cam in rig_b.cameras:
            uv = project(rig_b.window_of(cam.name), cam, X)
            w, h = cam.image_size
            seen = np.flatnonzero(np.isfinite(uv).all(axis=1)
                                  & (uv[:, 0] >= IMAGE_MARGIN_PX) & (uv[:, 0] <= w - 1 - IMAGE_MARGIN_PX)
                                  & (uv[:, 1] >= IMAGE_MARGIN_PX) & (uv[:, 1] <= h - 1 - IMAGE_MARGIN_PX))
            order = rng_n.permutation(len(seen))  # row order carries no identity
            rows = seen[order]
            pid[cam.name] = rows
            ex[cam.name] = uv[rows]
            det[cam.name] = uv[rows] + rng_n.normal(0.0, o.sigma_px, (len(rows), 2))
        positions.append(X)
        detections.append(det)
        ids.append(pid)
        exact.append(ex)
    return ParticleExperiment(options=o, rig_a=rig_a, rig_b=rig_b, calibration_dataset=dataset,
                              truth_a=_calibration(rig_a, o.seed), truth_b=_calibration(rig_b, o.seed),
                              volume_min_mm=vmin, volume_max_mm=vmax, positions=tuple(positions),
                              detections=tuple(detections), particle_ids=tuple(ids), exact_pixels=tuple(exact))


# --------------------------------------------------------------------------- images


# --------------------------------------------------------------------------- writing


def image_pattern(camera: str, bit_depth: int = 8) -> str:
    """Give the path pattern of a camera's rendered images in the experiment folder (as in rig.yaml).

    Args:
        camera: the camera's name.
        bit_depth: 8 (PNG) or 16 (TIFF).

    Returns:
        The pattern, relative to the experiment folder, with a ``{frame:05d}`` field.
    """
    return f"images/{camera}/{{frame:05d}}.{'png' if bit_depth == 8 else 'tif'}"


def render_frame_images(exp: ParticleExperiment, frame: int, peaks: np.ndarray, rng: np.random.Generator
                        ) -> dict[str, np.ndarray]:
    """Render the images of one frame, in the experiment's look.

    Args:
        exp: the experiment.
        frame: the frame's index.
        peaks: each particle's peak above the background (8-bit grey levels; used by the plain look),
            by the rows of the frame's positions.
        rng: the random generator of the image noise.

    Returns:
        Camera name -> the 8- or 16-bit image.
    """
    o = exp.options
    out = {}
    if o.look == "tank":
        look = TankLook(bit_depth=o.bit_depth)
        lo, hi = look.peak  # the tank's particles: brightness log-uniform, sizes spread (per particle)
        tank_rng = _rng(o.seed, 6 + frame)
        n = len(exp.positions[frame])
        tank_peak = np.exp(tank_rng.uniform(np.log(lo), np.log(hi), n))
        diameter = o.diameter_px * tank_rng.uniform(1.0 - look.diameter_spread, 1.0 + look.diameter_spread, n)
    for cam in exp.rig_b.cameras:
        uv = exp.exact_pixels[frame][cam.name]
        ids = exp.particle_ids[frame][cam.name]
        if o.look == "tank":
            out[cam.name] = render_tank_frame(uv, cam.image_size, o.diameter_px, look, rng, peak=tank_peak[ids],
                                              diameter_px_each=diameter[ids]).image
            continue
        img = render_particle_image(uv, cam.image_size, o.diameter_px, peaks[ids], rng=rng)
        out[cam.name] = img if o.bit_depth == 8 else img.astype(np.uint16) * np.uint16(257)
    return out


@dataclass(frozen=True)
class ParticleExperimentFolders:
    """Where :func:`write_particle_experiment` wrote a particle experiment."""

    calibration: Path  # rig A's calibration dataset
    experiment: Path  # rig B's particle experiment (rig.yaml, particles.parquet, the images)
    truth: Path  # the truth: rig_a.json, rig_b.json, particles.parquet, detections.parquet, simulation.json


def write_particle_experiment(exp: ParticleExperiment, out_dir: str | Path,
                              render_frames: int = 2) -> ParticleExperimentFolders:
    """Write ``exp`` under ``out_dir`` (layout in the module docstring).

    Args:
        exp: The simulated experiment.
        out_dir: The output folder.
        render_frames: Frames rendered as images (the first ones).

    Returns:
        The three folders written.
    """
    import cv2
    import yaml

    from ari_sfm.io import save_rig, write_bytes_atomic, write_json_atomic, write_text_atomic
    from ari_sfm.io.dataset import camera_to_json, windows_to_json
    from ari_sfm.io.particles import parquet_bytes

    out = Path(out_dir)
    o = exp.options
    calib_dir, exp_dir, truth_dir = out / "calibration", out / "experiment", out / "truth"
    for d in (calib_dir, exp_dir, truth_dir):
        d.mkdir(parents=True, exist_ok=True)
    ds = replace(exp.calibration_dataset, root=calib_dir, rig_path=calib_dir / "rig.yaml",
                 observations_path=calib_dir / "observations.json")
    save_rig(calib_dir / "rig.yaml", ds)
    write_json_atomic(truth_dir / "rig_a.json", calibration_to_json(exp.truth_a))
    write_json_atomic(truth_dir / "rig_b.json", calibration_to_json(exp.truth_b))

    frame, camera, u, v, inten, pid = [], [], [], [], [], []
    intensity_rng = _rng(o.seed, 3)
    peaks = [intensity_rng.uniform(120.0, 220.0, len(X)) for X in exp.positions]
    for f, (det, ids) in enumerate(zip(exp.detections, exp.particle_ids)):
        for cam in exp.cameras:
            n = len(det[cam])
            frame.append(np.full(n, f, np.int64))
            camera += [cam] * n
            u.append(det[cam][:, 0])
            v.append(det[cam][:, 1])
            inten.append(peaks[f][ids[cam]])
            pid.append(ids[cam].astype(np.int64))
    frame_a = np.concatenate(frame)
    write_bytes_atomic(exp_dir / "particles.parquet", parquet_bytes(
        {"frame": frame_a, "camera": camera, "u": np.concatenate(u), "v": np.concatenate(v),
         "intensity": np.concatenate(inten)}))
    write_bytes_atomic(truth_dir / "detections.parquet", parquet_bytes(
        {"frame": frame_a, "camera": camera, "particle": np.concatenate(pid)}))
    P = np.concatenate(exp.positions)
    write_bytes_atomic(truth_dir / "particles.parquet", parquet_bytes(
        {"frame": np.repeat(np.arange(len(exp.positions), dtype=np.int64), [len(X) for X in exp.positions]),
         "particle": np.concatenate([np.arange(len(X), dtype=np.int64) for X in exp.positions]),
         "x": P[:, 0], "y": P[:, 1], "z": P[:, 2]}))

    render_frames = max(0, min(int(render_frames), len(exp.positions)))
    img_rng = _rng(o.seed, 5)
    for f in range(render_frames):
        for name, img in render_frame_images(exp, f, peaks[f], img_rng).items():
            path = image_pattern(name, o.bit_depth).format(frame=f)
            ok, data = cv2.imencode(Path(path).suffix, img)
            if not ok:
                raise OSError(f"could not encode the image of {name} frame {f}")
            write_bytes_atomic(exp_dir / path, data.tobytes())

    rig = {
        "format": "ari-sfm/1",
        **windows_to_json(ds),
        "cameras": {name: camera_to_json(spec) for name, spec in ds.cameras.items()},
        "particles": {
            "detections": "particles.parquet",
            **({"images": {c: image_pattern(c, o.bit_depth) for c in exp.cameras}, "frames": [0, render_frames - 1]}
               if render_frames else {}),
            "diameter_px": float(o.diameter_px),
            "volume_mm": {"frame": exp.cameras[0], "min": exp.volume_min_mm.tolist(),
                          "max": exp.volume_max_mm.tolist()},
        },
    }
    write_text_atomic(exp_dir / "rig.yaml", yaml.safe_dump(rig, sort_keys=False))
    summary = {"format": "ari-sfm-particle-simulation/1", "options": {k: getattr(o, k) for k in o.__dataclass_fields__},
               "frames": len(exp.positions), "cameras": exp.cameras,
               "detections_per_camera": {c: int(sum(len(d[c]) for d in exp.detections)) for c in exp.cameras},
               "files": {"calibration_dataset": "calibration", "experiment": "experiment",
                         "truth_rig_a": "truth/rig_a.json", "truth_rig_b": "truth/rig_b.json",
                         "truth_particles": "truth/particles.parquet", "truth_detections": "truth/detections.parquet"}}
    write_json_atomic(truth_dir / "simulation.json", summary)
    log.info("particle experiment written to %s", out)
    return ParticleExperimentFolders(calib_dir, exp_dir, truth_dir)

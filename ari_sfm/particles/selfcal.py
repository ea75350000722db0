"""Volume self-calibration through the window (Wieneke 2008 with the exact refractive model).

A target calibration drifts: a camera bumped by 0.05 deg moves its particle images by 1-4 px and
strict matching then finds almost nothing (PHYSICS.md). Self-calibration corrects it from the
particle images themselves, in rounds:

1. match the frames with the current calibration at the round's tolerance
   (``particles.match.match_frame``; loose at first, e.g. 5 px, all 4 cameras: then only
   ``coarse_frames`` of them (more with sparse seeding), the loose matching being slow and a few
   hundred inliers enough; while the first round finds no disparity peak its tolerance is widened
   by ``WIDEN`` up to ``max_tolerance_px``), each match triangulated with the exact model;
2. disparity maps per camera per cell of the volume (:mod:`.disparity`): the robust peak of
   ``detected - reprojected``; the matches on their cells' peaks in every camera are the inliers
   (ghosts spread over the tolerance disc and fall out);
3. bundle adjustment with the inlier particles as landmarks: the refractive problem of
   ``refine-colmap`` (:class:`ari_sfm.colmap_refine.problem.RefractiveProblem`, the exact model's
   analytic Jacobians, the points eliminated by its Schur complement, the project's
   Levenberg-Marquardt; GTSAM selectable) with one rig frame (all particle frames share the
   rig's pose) whose reference sensor is camera 0, so that

   - camera 0's pose is held (the rig frame is the gauge frame, never a variable),
   - the window is held (``refine_window``: its normal and, under water, its distance estimated),
   - the intrinsics are held (``refine_intrinsics``: fx fy cx cy estimated, distortion held),
   - the scale is held by a prior (sigma ``SCALE_SIGMA_MM``) on the sum of the distances from
     camera 0's centre to every other camera's centre, at the starting calibration's value:
     particles barely determine the scale (PHYSICS.md: ~1.3 mm on that sum for 35k particles), and
     one sum spreads the drift of single cameras over all baselines;
   - the other cameras' poses (sensor_from_rig) and the particles are estimated (Huber loss);
4. the next round matches again with a tighter tolerance (halved, down to ``final_tolerance_px``;
   straight to it once the inliers' disparity RMS falls by less than ``min_improvement``); the
   rounds stop when it no longer falls at the final tolerance (or after ``max_rounds``). The
   disparity maps "after" are the last round's: the final calibration at the final tolerance.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..calibration import Calibration
from ..io import save_calibration
from ..errors import AriSfmError
from ..geometry import Pose, rotation_angle_deg
from ..models import PinholeModel
from .disparity import Cells, DisparityMap, ParticleSet, disparity_map, particle_disparities

log = logging.getLogger(__name__)

SCALE_SIGMA_MM = 1e-4  # the scale prior's sigma on the sum of camera-0 baselines (effectively held)
BACKENDS = ("numpy", "gtsam")
COARSE_PX = 2.0  # rounds with a tolerance above this match only the coarse frames (_coarse_frames)
FIRST_PEAK_MIN = 30  # inliers the first round needs (else its tolerance is widened by WIDEN)
WIDEN = 1.6
COARSE_IMAGES = 5000  # ... at least options.coarse_frames, more until the first camera has this many images
MIN_MATCHES = 10  # fewer matches (or inliers) in a round: no correction from it
PROJECTING_EXACT = ("exact", "rt", "truth")  # models whose projection is the exact Snell model

Detections = Mapping[str, np.ndarray]  # camera name -> (N_c, 2) pixels of one frame


@dataclass(frozen=True)
class SelfCalOptions:
    """What self-calibration does (defaults for the 4-camera PTV set-up of PHYSICS.md)."""

    tolerance_px: float = 5.0  # first round's matching tolerance (loose: the drift must fit in it)
    max_tolerance_px: float = 12.0  # the first round widens its tolerance up to this while it finds no peak
    final_tolerance_px: float = 0.5  # the tolerance the rounds tighten to (halving)
    min_cameras: int = 4  # cameras a match must use (4: ghosts are rare, the peak is clear)
    cells: tuple[int, int, int] = (3, 3, 3)  # sub-volumes (x, y, z) of the disparity maps
    peak_radius_px: float = 0.5  # a match is on its cell's peak within this many px in every camera
    field_radius_px: float = 1.5  # cells' peaks searched within this many px of the whole volume's peak
    max_rounds: int = 6
    min_improvement: float = 0.05  # stop when the inlier RMS falls by less than this fraction
    coarse_frames: int = 3  # at least this many frames (more while the first camera has < COARSE_IMAGES images)
    # are matched in rounds looser than COARSE_PX (the slow, ghost-ridden matching:
    # a few hundred inliers suffice for the first correction)
    max_landmarks: int = 20000  # particles in one bundle adjustment (random subset beyond)
    huber_px: float = 1.0  # Huber threshold of the bundle adjustment
    max_iterations: int = 30  # Levenberg-Marquardt iterations per round
    refine_window: bool = False
    refine_intrinsics: bool = False
    backend: str = "numpy"  # "numpy" (points Schur + the project's LM) or "gtsam"
    seed: int = 0  # the landmark subset


@dataclass(frozen=True)
class FrameParticles:
    """One frame's matches: detection rows per camera and the triangulated points."""

    frame: int
    rows: np.ndarray  # (M, C) int64 detection index per camera, -1 unused
    pixels: np.ndarray  # (M, C, 2) NaN where unused
    xyz: np.ndarray  # (M, 3)


@dataclass(frozen=True)
class Adjustment:
    """One bundle adjustment with the particles as landmarks (:func:`refine_with_landmarks`)."""

    landmarks: int
    observations: int
    iterations: int
    cost_start: float
    cost_final: float
    rms_px: float
    sum_baselines_held_mm: float  # the scale prior's value: camera 0 to the others, summed
    sum_baselines_final_mm: float
    rotation_change_deg: Mapping[str, float]
    time_s: float

    def to_json(self) -> dict[str, Any]:
        return {"landmarks": self.landmarks, "observations": self.observations, "iterations": self.iterations,
                "cost": {"start": self.cost_start, "final": self.cost_final}, "rms_px": self.rms_px,
                "sum_baselines_mm": {"held": self.sum_baselines_held_mm, "final": self.sum_baselines_final_mm},
                "rotation_change_deg": dict(self.rotation_change_deg), "time_s": self.time_s}


@dataclass(frozen=True)
class Round:
    """One round: its tolerance, the disparity measured with the calibration it started from, and the
    bundle adjustment that followed (None for the final check)."""

    tolerance_px: float
    matches: int
    disparity: DisparityMap
    adjustment: Adjustment | None

    def to_json(self) -> dict[str, Any]:
        """The round as the report lists it."""
        return {"tolerance_px": self.tolerance_px, "matches": self.matches,
                "inliers": int(self.disparity.inlier.sum()),
                "disparity_rms_px": [float(v) for v in self.disparity.rms_px],
                "adjustment": None if self.adjustment is None else self.adjustment.to_json()}


@dataclass(frozen=True)
class BeforeAfter:
    """A camera's disparity RMS (px) with the starting and the corrected calibration."""

    before: float
    after: float


@dataclass(frozen=True)
class SelfCalInputs:
    """The files a dataset's self-calibration read (:func:`self_calibrate_dataset`), absolute."""

    dataset: str
    calibration: str
    detections: str
    workers: int | None  # None with a scheduler
    scheduler: str | None


@dataclass(frozen=True)
class SelfCalReport:
    """What self-calibration did: ``to_json()`` is calibration.json's ``self_calibration``."""

    frames: tuple[int, ...]
    particles_used: int  # landmarks of the largest round
    landmarks_all_rounds: int
    held: tuple[str, ...]  # what was not estimated, in words
    scale_how: str
    scale_sum_mm: float
    scale_sigma_mm: float
    backend: str
    options: Mapping[str, Any]  # the SelfCalOptions, as JSON
    disparity_rms_px: Mapping[str, BeforeAfter]
    converged: bool  # the final disparities are one noise level (:func:`converged`)
    rounds: tuple[Round, ...]
    rotation_change_deg: Mapping[str, float]
    time_s: float
    inputs: SelfCalInputs | None = None  # from a dataset's files

    def to_json(self) -> dict[str, Any]:
        out = {"frames": list(self.frames), "particles_used": self.particles_used,
               "landmarks_all_rounds": self.landmarks_all_rounds, "held": list(self.held),
               "scale": {"how": self.scale_how, "sum_mm": self.scale_sum_mm, "sigma_mm": self.scale_sigma_mm},
               "backend": self.backend, "options": dict(self.options),
               "disparity_rms_px": {n: {"before": d.before, "after": d.after} for n, d in self.disparity_rms_px.items()},
               "converged": self.converged, "rounds": [r.to_json() for r in self.rounds],
               "rotation_change_deg": dict(self.rotation_change_deg), "time_s": self.time_s}
        if self.inputs is not None:
            i = self.inputs
            out.update({"dataset": i.dataset, "calibration": i.calibration, "detections": i.detections,
                        "workers": i.workers, "scheduler": i.scheduler})
        return out


@dataclass(frozen=True)
class SelfCalResult:
    """The corrected calibration (its ``self_calibration`` key = ``report.to_json()``) and the disparity maps:
    with the starting calibration (first round), with the corrected one (last round), and every round's."""

    calibration: Calibration
    before: DisparityMap
    after: DisparityMap
    rounds: tuple[Round, ...]
    report: SelfCalReport


# --------------------------------------------------------------------------- matching


def check_calibration(calibration: Calibration, cameras: Sequence[str], path: Any) -> None:
    """The calibration projects with the exact model and is of the rig that recorded the particles."""
    if calibration.model not in PROJECTING_EXACT:
        raise AriSfmError(path, f"self-calibration uses the exact refractive model; this calibration's model is "
                                f"{calibration.model!r} (calibrate the target with --model exact)")
    missing = [c for c in cameras if c not in calibration.cameras]
    if missing:
        raise AriSfmError(path, f"a calibration of another rig: camera(s) {', '.join(missing)} of the particle "
                                f"detections are not in it (its cameras: {', '.join(calibration.cameras)})")
    if len(calibration.cameras) < 3:
        raise AriSfmError(path, f"self-calibration needs at least 3 cameras (this calibration has "
                                f"{len(calibration.cameras)})")


def match_particles(calibration: Calibration, frame: int, detections: Detections, tolerance_px: float,
                    min_cameras: int, volume: Any = None, depth_range_mm: Any = None,
                    match: Callable | None = None) -> FrameParticles:
    """Match one frame (``match``: ``match_frame``'s signature, default the particles package's) and
    triangulate the matches with the exact model."""
    from ..triangulate import triangulate_pixels

    if match is None:
        from .match import match_frame as match
    names = list(calibration.cameras)
    found = match(calibration, {n: np.asarray(detections[n], float).reshape(-1, 2) for n in names},
                  tolerance_px, depth_range_mm=depth_range_mm, volume=volume, min_cameras=min_cameras)
    rows = np.asarray(found.rows, dtype=np.int64).reshape(-1, len(names))
    pixels = np.full(rows.shape + (2,), np.nan)
    for c, n in enumerate(names):
        m = rows[:, c] >= 0
        pixels[m, c] = np.asarray(detections[n], float)[rows[m, c]]
    xyz = getattr(found, "xyz", None)  # match_frame triangulates with the exact model already
    if xyz is None or len(xyz) != len(rows):
        xyz = (triangulate_pixels(calibration, {n: pixels[:, c] for c, n in enumerate(names)})[0] if len(rows)
               else np.zeros((0, 3)))
    return FrameParticles(int(frame), rows, pixels, xyz)


def _stack(frames: Sequence[FrameParticles]) -> ParticleSet:
    C = frames[0].pixels.shape[1] if frames else 0
    pixels = np.concatenate([f.pixels for f in frames]) if frames else np.zeros((0, C, 2))
    xyz = np.concatenate([f.xyz for f in frames]) if frames else np.zeros((0, 3))
    frame = np.concatenate([np.full(len(f.xyz), f.frame) for f in frames]) if frames else np.zeros(0, int)
    ok = np.isfinite(xyz).all(axis=1)
    return ParticleSet(pixels[ok], xyz[ok], frame[ok])


# --------------------------------------------------------------------------- bundle adjustment


def _landmark_model(calibration: Calibration, particles: ParticleSet, refine_intrinsics: bool):
    """The particles as a one-frame COLMAP-like model: one image per camera, camera 0 the rig's reference."""
    from ..colmap_export import ColmapModel

    names = list(calibration.cameras)
    C = len(names)
    cam0 = calibration.cameras[names[0]].cam_from_world
    params, maps, offsets = [], [], []
    for n in names:
        p9 = calibration.cameras[n].params
        if refine_intrinsics:  # fx fy cx cy free, distortion held
            M = np.zeros((9, 4))
            M[:4, :4] = np.eye(4)
            off = p9.copy()
            off[:4] = 0.0
            params.append(p9[:4].copy())
        else:
            M, off = np.zeros((9, 0)), p9.copy()
            params.append(np.zeros(0))
        maps.append(M)
        offsets.append(off)
    used = particles.used
    obs_point, obs_image = np.nonzero(used)
    return ColmapModel(
        camera_ids=np.arange(C), camera_models=("OPENCV",) * C,
        image_sizes=tuple(tuple(calibration.cameras[n].image_size) for n in names),
        colmap_params=tuple(params), param_map=tuple(maps), param_offset=tuple(offsets),
        frame_ids=np.zeros(1, int), rig_from_world=(cam0,), image_ids=np.arange(C), image_names=tuple(names),
        image_camera=np.arange(C), image_frame=np.zeros(C, int),
        sensor_from_rig=tuple(calibration.cameras[n].cam_from_world.compose(cam0.inverse()) for n in names),
        point3D_ids=np.arange(len(particles.xyz)), xyz=particles.xyz.copy(),
        obs_image=obs_image, obs_point=obs_point, obs_uv=particles.pixels[obs_point, obs_image],
        image_is_ref=np.arange(C) == 0)


def _window_planes(calibration: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """Every window's normal (W, 3) and near face offset (W,) in the world (``normal . X = plane`` on the face)."""
    windows = calibration.window_list()
    return (np.array([np.asarray(w.normal_world, float) for w in windows]),
            np.array([w.plane_mm(calibration) for w in windows], dtype=float))


def _with_windows(calibration: Calibration, normals: np.ndarray, planes: np.ndarray, estimated: bool) -> Calibration:
    """``calibration`` (its cameras already moved) with each window at ``normals``, ``planes`` in the world; the
    distances (from each window's first camera, as calibration.json gives them) follow the cameras; a window whose
    distance was not observed (``estimated`` False in air) keeps it as the evaluation distance."""
    windows = []
    for w, n, h in zip(calibration.window_list(), normals, planes):
        centre = calibration.cameras[w.cameras[0]].cam_from_world.inverse().t
        d = float(h - n @ centre)
        if w.interface.distance_mm is not None:
            w = replace(w, interface=replace(w.interface, distance_mm=d), normal_world=n.copy())
        else:
            w = replace(w, normal_world=n.copy(), fixed_distance_mm=d if w.fixed_distance_mm is not None else None)
        windows.append(w)
    first = windows[0]
    return replace(calibration, interface=first.interface, normal_world=first.normal_world,
                   fixed_distance_mm=first.fixed_distance_mm, windows=tuple(windows) if calibration.windows else ())


def sum_baselines_mm(calibration: Calibration) -> float:
    """Sum of the distances from the first camera's centre to every other camera's centre (the held scale)."""
    centres = np.array([c.cam_from_world.inverse().t for c in calibration.cameras.values()])
    return float(np.linalg.norm(centres[1:] - centres[0], axis=1).sum())


def _sum_baselines(state) -> tuple[float, np.ndarray]:
    """Sum over cameras c >= 1 of |centre_c - centre_0| = |t of sensor_from_rig_c| and its gradient
    w.r.t. each translation (C, 3) (the rotation does not change it)."""
    t = np.array([s.t for s in state.sensor_from_rig])
    norms = np.linalg.norm(t, axis=1)
    grad = np.zeros_like(t)
    grad[1:] = t[1:] / norms[1:, None]
    return float(norms[1:].sum()), grad


def _solvers():
    """The numpy solver with the scale prior (a subclass of refine-colmap's Solver)."""
    from ..colmap_refine.refine import Solver

    class ScaleHeldSolver(Solver):
        """refine-colmap's Solver plus one prior row: the sum of camera-0 baselines at ``baseline_mm``."""

        def __init__(self, problem, huber_px, baseline_mm: float, sigma_mm: float = SCALE_SIGMA_MM) -> None:
            super().__init__(problem, huber_px)
            self.baseline_mm, self.sigma_mm = baseline_mm, sigma_mm

        def _scale_error(self, state) -> float:
            return (_sum_baselines(state)[0] - self.baseline_mm) / self.sigma_mm

        def cost(self, state) -> float:
            return super().cost(state) + 0.5 * self._scale_error(state) ** 2

        error = cost

        def linearize(self, state):
            ne = super().linearize(state)
            e = self._scale_error(state)
            _, grad = _sum_baselines(state)
            lay = self.problem.layout
            cols = lay.sensors[:, 3:]  # translation columns per sensor (-1: reference)
            free = cols[:, 0] >= 0
            idx = cols[free].ravel()
            J = (grad[free] / self.sigma_mm).ravel()
            ne.U[np.ix_(idx, idx)] += np.outer(J, J)
            ne.g_global[idx] += J * e
            ne.error += 0.5 * e * e
            return ne

    return ScaleHeldSolver


def _gtsam_refinement(problem, huber_px: float | None, baseline_mm: float, state):
    """refine-colmap's GTSAM graph plus the scale prior as a CustomFactor on the sensors' Pose3."""
    import gtsam

    from ..colmap_refine import gtsam_graph as gg

    lay = problem.layout
    cams = [c for c in range(len(lay.sensors)) if lay.sensors[c, 0] >= 0]

    class ScaleHeldRefinement(gg.GtsamRefinement):
        def values(self, st):
            v = super().values(st)
            for c in range(len(problem.model.camera_ids)):  # held intrinsics: no variable
                if not problem.model.param_map[c].any():
                    v.erase(gg._intrinsics_key(c))
            return v

        def state(self, values, template):
            v = gtsam.Values(values)
            for c in range(len(problem.model.camera_ids)):
                if not problem.model.param_map[c].any():
                    v.insert(gg._intrinsics_key(c), np.zeros(0))
            return super().state(v, template)

        def optimize(self, st, max_iterations: int = 100):
            """GTSAM's LM with Marquardt's diagonal damping, as the numpy solver (the stiff scale prior
            beside the points makes lambda I crawl)."""
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(max_iterations)
            params.setRelativeErrorTol(1e-12)
            params.setAbsoluteErrorTol(1e-12)
            params.setDiagonalDamping(True)
            opt = gtsam.LevenbergMarquardtOptimizer(self.graph(st), self.values(st), params)
            values = opt.optimize()
            return self.state(values, st), int(opt.iterations())

        def graph(self, st):
            g = super().graph(st)
            keys = [gg._sensor_key(c) for c in cams]

            def error(this, values, H):
                poses = [values.atPose3(k) for k in keys]
                t = [np.asarray(p.translation(), float) for p in poses]
                if H is not None:
                    for i, (p, ti) in enumerate(zip(poses, t)):  # t' = t + R v (right perturbation)
                        H[i] = np.concatenate([np.zeros(3), ti / np.linalg.norm(ti) @ p.rotation().matrix()])[None, :]
                return np.array([sum(np.linalg.norm(ti) for ti in t) - baseline_mm])

            g.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, SCALE_SIGMA_MM), keys, error))
            return g

    return ScaleHeldRefinement(problem, huber_px)


def refine_with_landmarks(calibration: Calibration, particles: ParticleSet, options: SelfCalOptions,
                          baseline_mm: float | None = None) -> tuple[Calibration, Adjustment]:
    """The calibration corrected by a bundle adjustment with the particles as landmarks (module
    docstring, step 3). ``baseline_mm``: the held sum of camera-0 baselines (default: this calibration's)."""
    from ..colmap_refine.problem import RefractiveProblem, State

    t0 = time.perf_counter()
    names = list(calibration.cameras)
    model = _landmark_model(calibration, particles, options.refine_intrinsics)
    estimate_distance = options.refine_window and calibration.interface.medium_index != 1.0
    windows = calibration.window_list()
    window_of = [next(k for k, w in enumerate(windows) if n in w.cameras) for n in names]
    normals0, planes0 = _window_planes(calibration)
    problem = RefractiveProblem(model, calibration.interface, "world", estimate_distance,
                                camera_windows=window_of, interfaces=[w.interface for w in windows],
                                hold_window=not options.refine_window)
    state = State(model.colmap_params, model.rig_from_world, model.sensor_from_rig,
                  normals0, planes0,
                  model.xyz.copy())
    held = _sum_baselines(state)[0] if baseline_mm is None else baseline_mm
    if options.backend == "numpy":
        solver = _solvers()(problem, options.huber_px, held)
        res = solver.run(state, options.max_iterations)
        final, iterations, cost0, cost1 = res.state, res.iterations, res.initial_cost, res.cost
    elif options.backend == "gtsam":
        refinement = _gtsam_refinement(problem, options.huber_px, held, state)
        final, iterations = refinement.optimize(state, options.max_iterations)
        solver = _solvers()(problem, options.huber_px, held)
        cost0, cost1 = solver.cost(state), solver.cost(final)
    else:
        raise AriSfmError(None, f"backend must be one of {', '.join(BACKENDS)} (got {options.backend!r})")
    R, t = final.cam_from_world(model)
    cameras = {}
    for c, n in enumerate(names):
        cam = calibration.cameras[n]
        p9 = model.params9(c, final.colmap_params[c])
        cameras[n] = replace(cam, K=PinholeModel.from_params(p9).K, dist=p9[4:].copy(), cam_from_world=Pose(R[c], t[c]),
                             rmse_px=None)
    normals, planes = (final.normals, final.distances) if options.refine_window else (normals0, planes0)
    corrected = _with_windows(replace(calibration, cameras=cameras), np.asarray(normals, float),
                              np.asarray(planes, float), estimate_distance)
    corrected = replace(corrected, model="exact" if calibration.model == "truth" else calibration.model)
    e = np.linalg.norm(problem.residuals(final), axis=1)
    report = Adjustment(int(len(particles.xyz)), int(len(e)), int(iterations), float(cost0), float(cost1),
                        float(np.sqrt(np.mean(e ** 2))), float(held), float(_sum_baselines(final)[0]),
                        {n: rotation_angle_deg(calibration.cameras[n].cam_from_world.R, R[c])
                         for c, n in enumerate(names)}, time.perf_counter() - t0)
    log.info("self-calibration: bundle adjustment of %d particles: %.3f px RMS after %d iterations",
             len(particles.xyz), report.rms_px, iterations)
    return corrected, report


# --------------------------------------------------------------------------- the rounds


def _subset(particles: ParticleSet, mask: np.ndarray, limit: int, seed: int) -> ParticleSet:
    idx = np.flatnonzero(mask)
    if len(idx) > limit:
        idx = np.sort(np.random.default_rng(seed).choice(idx, limit, replace=False))
    return ParticleSet(particles.pixels[idx], particles.xyz[idx], particles.frame[idx])


MapFrames = Callable[[Callable[..., FrameParticles], list[tuple]], list[FrameParticles]]


def _coarse_frames(frames: Sequence[int], detections: Mapping[int, Detections], first: str, minimum: int) -> list[int]:
    """The frames of the loose rounds: ``minimum`` spread over the experiment, more (spread) until the first
    camera has COARSE_IMAGES images in them (sparse seeding needs more frames for the same peaks)."""
    count = min(minimum, len(frames))
    while True:
        use = pick_frames(frames, count)
        if count >= len(frames) or sum(len(detections[f].get(first, ())) for f in use) >= COARSE_IMAGES:
            return use
        count += 1


def _serial(fn: Callable[..., FrameParticles], args: list[tuple]) -> list[FrameParticles]:
    return [fn(*a) for a in args]


def dask_map(client: Any) -> MapFrames:
    """Run the frames' matching as tasks on a dask.distributed Client (one task per frame), in frame order."""
    def run(fn: Callable[..., FrameParticles], args: list[tuple]) -> list[FrameParticles]:
        return client.gather([client.submit(fn, *a, pure=False) for a in args])
    return run


def self_calibrate(calibration: Calibration, detections: Mapping[int, Detections],
                   options: SelfCalOptions = SelfCalOptions(), volume: Any = None, depth_range_mm: Any = None,
                   match: Callable | None = None, map_frames: MapFrames | None = None,
                   cells_box: Cells | None = None, path: Any = "calibration") -> SelfCalResult:
    """Volume self-calibration (module docstring) from ``detections`` {frame: {camera: (N, 2) px}}.

    ``match``: match_frame's signature (default: :func:`ari_sfm.particles.match.match_frame`);
    ``map_frames(fn, args)``: how the frames' matching tasks ``fn(*a)`` run (default in this process;
    :func:`dask_map` on a Client);
    ``cells_box``: the disparity maps' box (default: the first round's matched particles).
    """
    t0 = time.perf_counter()
    names = list(calibration.cameras)
    if not detections:
        raise AriSfmError(path, "no particle detections to self-calibrate from")
    check_calibration(calibration, list(next(iter(detections.values()))), path)
    if options.backend not in BACKENDS:
        raise AriSfmError(None, f"--backend must be one of {', '.join(BACKENDS)} (got {options.backend!r})")
    if options.min_cameras > len(names):
        raise AriSfmError(None, f"--min-cameras {options.min_cameras} exceeds the rig's {len(names)} cameras")
    frames = sorted(detections)
    run = map_frames or _serial

    def matched(cal: Calibration, tol: float) -> ParticleSet:
        use = coarse if tol > COARSE_PX else frames
        return _stack(run(match_particles, [(cal, f, detections[f], tol, options.min_cameras, volume, depth_range_mm,
                                             match) for f in use]))

    coarse = _coarse_frames(frames, detections, names[0], options.coarse_frames)
    baseline = sum_baselines_mm(calibration)
    current, rounds, cells, prev_rms, tol = calibration, [], cells_box, None, float(options.tolerance_px)
    exhausted = False
    def measure(cal: Calibration, tol: float, box: Cells | None):
        """One round's matches, its cells' box and disparity map (None with too few matches)."""
        particles = matched(cal, tol)
        if len(particles.xyz) < MIN_MATCHES:
            return particles, box, None
        box = box or Cells.around(particles.xyz, options.cells)
        dmap = disparity_map(names, box, particles, particle_disparities(cal, particles),
                             options.peak_radius_px, options.field_radius_px, options.seed)
        log.info("self-calibration: tolerance %.3g px, %d matches, %d inliers, disparity RMS %s px",
                 tol, len(particles.xyz), int(dmap.inlier.sum()), np.round(dmap.rms_px, 3).tolist())
        return particles, box, dmap

    for r in range(options.max_rounds):
        particles, box, dmap = measure(current, tol, cells)
        # the first round: no clear peak yet -> the drift may exceed the tolerance: widen it (up to max_tolerance_px)
        while r == 0 and (dmap is None or dmap.inlier.sum() < FIRST_PEAK_MIN) and tol < options.max_tolerance_px:
            tol = min(WIDEN * tol, options.max_tolerance_px)
            log.info("self-calibration: no clear disparity peak: tolerance widened to %.3g px", tol)
            particles, box, dmap = measure(current, tol, cells)
        if dmap is None or dmap.inlier.sum() < (FIRST_PEAK_MIN if r == 0 else MIN_MATCHES):
            if r == 0:
                used = len(coarse) if tol > COARSE_PX else len(frames)
                what = (f"{len(particles.xyz)} particles matched" if dmap is None else
                        f"{len(particles.xyz)} matches but no disparity peak ({int(dmap.inlier.sum())} on it)")
                raise AriSfmError(path, f"no confident matches: {what} in {options.min_cameras} cameras at up to "
                                        f"{tol:g} px over {used} frames; try a larger --max-tolerance-px (the drift "
                                        "must fit in it), more --coarse-frames, fewer --cells, --min-cameras 3, or "
                                        "check that the calibration is of this rig")
            break
        cells = box
        rms = float(np.nanmax(dmap.rms_px))
        stalled = prev_rms is not None and rms > (1.0 - options.min_improvement) * prev_rms
        if stalled and tol <= options.final_tolerance_px:  # the disparities stopped falling: done
            rounds.append(Round(tol, len(particles.xyz), dmap, None))
            break
        prev_rms = rms
        landmarks = _subset(particles, dmap.inlier, options.max_landmarks, options.seed + r)
        current, adjustment = refine_with_landmarks(current, landmarks, options, baseline)
        rounds.append(Round(tol, len(particles.xyz), dmap, adjustment))
        # tighter next round: halved, or straight to the final tolerance once the disparities stall
        tol = options.final_tolerance_px if stalled else max(options.final_tolerance_px, tol / 2.0)
    else:
        exhausted = True  # max_rounds reached: the final check at the next round's tolerance
    if not rounds:
        raise AriSfmError(path, "no confident matches (see the log)")
    last = rounds[-1]
    if last.adjustment is not None:  # the final check: match with the final calibration
        tol = tol if exhausted else last.tolerance_px  # (after a round that found too little: the last good one's)
        particles = matched(current, tol)
        dmap = disparity_map(names, cells, particles, particle_disparities(current, particles),
                             options.peak_radius_px, options.field_radius_px, options.seed)
        rounds.append(Round(tol, len(particles.xyz), dmap, None))
    before, after = rounds[0].disparity, rounds[-1].disparity
    report = _report(calibration, current, options, frames, rounds, baseline, time.perf_counter() - t0)
    if not report.converged:
        log.warning("self-calibration: the disparity RMS after (%s px) is not one noise level in every camera: "
                    "the correction may be wrong", np.round(after.rms_px, 3).tolist())
    corrected = replace(current, extra={**current.extra, "self_calibration": report.to_json()})
    return SelfCalResult(corrected, before, after, tuple(rounds), report)


def converged(after: DisparityMap, options: SelfCalOptions) -> bool:
    """Whether the final disparities are one noise level: every camera's RMS finite, within 1.5x of the
    smallest and below half the peak radius (a correction from a ghost peak leaves px in some cameras)."""
    rms = after.rms_px
    return bool(np.all(np.isfinite(rms)) and rms.max() <= 1.5 * rms.min() and rms.max() < 0.5 * options.peak_radius_px)


def _report(start: Calibration, final: Calibration, options: SelfCalOptions, frames: Sequence[int],
            rounds: Sequence[Round], baseline: float, seconds: float) -> SelfCalReport:
    names = list(start.cameras)
    before, after = rounds[0].disparity, rounds[-1].disparity
    held = ["camera 0's pose (" + names[0] + ", the world frame)"]
    held.append("the window (normal and distance)" if not options.refine_window else
                "nothing of the window (normal and distance estimated)")
    held.append("the intrinsics" if not options.refine_intrinsics else "the distortion (fx fy cx cy estimated)")
    landmarks = sum(r.adjustment.landmarks for r in rounds if r.adjustment)
    return SelfCalReport(
        frames=tuple(int(f) for f in frames),
        particles_used=int(max((r.adjustment.landmarks for r in rounds if r.adjustment), default=0)),
        landmarks_all_rounds=int(landmarks), held=tuple(held),
        scale_how="prior on the sum of the distances from camera 0's centre to the other cameras' centres, "
                  "at the starting calibration's value", scale_sum_mm=baseline, scale_sigma_mm=SCALE_SIGMA_MM,
        backend=options.backend,
        options={k: (list(v) if isinstance(v, tuple) else v) for k, v in options.__dict__.items()},
        disparity_rms_px={n: BeforeAfter(float(before.rms_px[c]), float(after.rms_px[c])) for c, n in enumerate(names)},
        converged=converged(after, options), rounds=tuple(rounds),
        rotation_change_deg={n: rotation_angle_deg(start.cameras[n].cam_from_world.R, final.cameras[n].cam_from_world.R)
                             for n in names},
        time_s=seconds)


def disparity_json(result: SelfCalResult) -> dict[str, Any]:
    """``disparity.json``: the cells and, per camera and cell, the disparity before and after."""
    return {"format": "ari-sfm-disparity/1", "cells": result.before.cells.to_json(),
            "cell_centres_mm": result.before.cells.centres().tolist(),
            "before": result.before.to_json(), "after": result.after.to_json(),
            "rounds": [r.disparity.to_json() for r in result.rounds]}


def write_self_calibration(result: SelfCalResult, out_dir) -> None:
    """OUT/calibration.json and OUT/disparity.json, atomically."""
    from pathlib import Path

    from ..io import write_json_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "disparity.json", disparity_json(result))
    save_calibration(result.calibration, out / "calibration.json")


# --------------------------------------------------------------------------- a dataset


def pick_frames(frames: Sequence[int], count: int | None) -> list[int]:
    """``count`` frames spread evenly over ``frames`` (all of them when None or more than there are)."""
    frames = sorted(int(f) for f in frames)
    if count is None or count >= len(frames):
        return frames
    return [frames[int(round(k))] for k in np.linspace(0, len(frames) - 1, count)]


def self_calibrate_dataset(dataset_path, calibration_path, out, options: SelfCalOptions = SelfCalOptions(),
                           detections_path=None, frames: int | None = 10,
                           depth_range_mm: tuple[float, float] | None = None, workers: int = 0,
                           scheduler: str | None = None) -> SelfCalResult:
    """``ari-sfm self-calibrate``: a particle experiment (DATASET_FORMAT 1.2) and its rig's calibration ->
    OUT/calibration.json (the corrected calibration, ``self_calibration`` key) and OUT/disparity.json.
    ``frames``: how many of the detections' frames to use (spread evenly); ``workers``/``scheduler``: the
    frames' matching on Dask (:func:`ari_sfm.particles.engine.dask_client`)."""
    import os
    from pathlib import Path

    from ..io.particles import read_detections
    from .engine import dask_client
    from .reconstruct import load_experiment, volume_for

    out = Path(out)
    calibration_path = Path(calibration_path)
    dataset, calibration = load_experiment(dataset_path, calibration_path, out)
    check_calibration(calibration, list(dataset.cameras), calibration_path)
    det_path = Path(detections_path) if detections_path is not None else dataset.detections
    if det_path is None:
        raise AriSfmError(dataset.rig_path, "particles: names no detections table: run `ari-sfm detect-particles` "
                                            "and pass its particles.parquet with --detections")
    cameras = list(calibration.cameras)
    det = read_detections(det_path, dataset.cameras)
    by_frame = det.by_frame(cameras)
    if not by_frame:
        raise AriSfmError(det_path, "holds no particle detections")
    chosen = pick_frames(by_frame, frames)
    detections = {f: {c: det.uv[by_frame[f][c]] for c in cameras} for f in chosen}
    volume = volume_for(dataset, calibration, depth_range_mm)
    with dask_client(workers, scheduler) as client:
        result = self_calibrate(calibration, detections, options, volume=volume,
                                map_frames=None if client is None else dask_map(client), path=calibration_path)
    report = replace(result.report, inputs=SelfCalInputs(
        str(Path(os.path.abspath(dataset.rig_path))), str(Path(os.path.abspath(calibration_path))),
        str(Path(os.path.abspath(det_path))), workers if scheduler is None else None, scheduler))
    result = replace(result, report=report,
                     calibration=replace(result.calibration, extra={**result.calibration.extra,
                                                                    "self_calibration": report.to_json()}))
    write_self_calibration(result, out)
    return result

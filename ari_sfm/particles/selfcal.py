"""Volume self-calibration through the window (Wieneke 2008 with the exact refractive model).

A target calibration drifts: a camera bumped by 0.05 deg moves its particle images by 1-4 px and
strict matching then finds almost nothing (PHYSICS.md). Self-calibration corrects it from the
particle images themselves, in rounds:

1. match the frames with the current calibration at the round's tolerance
   (``particles.match.match_frame``; loose at first, e.g. 5 px, all 4 cameras: then only
   ``coarse_frames`` of them (more with sparse seeding), the loose matching being slow and a few
   hundred inliers enough; while the first round finds no disparity peak its tolerance is widened
   by ``WIDEN`` up to ``max_tolerance_px``), each match triangulated with the exact model; the
   frames run in parallel (threads, or Dask tasks);
2. disparity maps per camera per cell of the volume (:mod:`.disparity`): the robust peak of
   ``detected - reprojected``; the matches on their cells' peaks in every camera are the inliers
   (ghosts spread over the tolerance disc and fall out);
3. bundle adjustment with the inlier particles as landmarks (:mod:`.landmarks`): every camera's pose
   estimated (camera 0 too: any camera may be bumped), the window's plane held in the world (the lab:
   it does not move), the motions that keep it (rotation about its normal, translation within it)
   and the scale (the sum of all pairwise camera distances) held at the start's values, the
   intrinsics estimated with the start calibration's sigmas as priors;
4. the next round matches again: straight at ``final_tolerance_px`` once the adjustment fits its
   landmarks at the noise (else at half the tolerance); the rounds stop when the disparity no longer
   falls there (or after ``max_rounds``). The disparity maps "after" are the last round's: the final
   calibration at the final tolerance.

Then the result is judged (:func:`trust_checks`): a low disparity is not enough (a start far off can
be "corrected" onto ghosts that agree with each other), so the share of the particle images the
final calibration matches, whether the correction stayed within the first round's tolerance of the
start, and the disparities' noise level are checked; ``SelfCalReport.passed`` says whether all held.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.errors import ErrorPath

from ..calibration.record import Calibration
from ..errors import AriSfmError
from ..geometry import rotation_angle_deg
from .disparity import Cells, DisparityMap, ParticleSet, disparity_map, particle_disparities
from .landmarks import (
    UNKNOWN_PRIOR_PX,
    Gauge,
    IntrinsicsPrior,
    Refined,
    free_intrinsics,
    guessed_principal_points,
    refine_with_landmarks,
)
from .selfcal_report import (
    Adjustment,
    BeforeAfter,
    Check,
    Intrinsics,
    RoundSummary,
    SelfCalInputs,
    SelfCalOptions,
    SelfCalReport,
)

log = logging.getLogger(__name__)

COARSE_PX = 2.0  # rounds with a tolerance above this match only the coarse frames (_coarse_frames)
FIRST_PEAK_MIN = 30  # inliers the first round needs (else its tolerance is widened by WIDEN)
WIDEN = 1.6
COARSE_IMAGES = 5000  # ... at least options.coarse_frames, more until the first camera has this many images
MIN_MATCHES = 10  # fewer matches (or inliers) in a round: no correction from it
PROJECTING_EXACT = ("exact", "rt", "truth")  # models whose projection is the exact Snell model
JUMP_NOISE = 2.0  # an adjustment whose landmarks' RMS is below final_tolerance_px / JUMP_NOISE: the next
# round matches at the final tolerance (the correction fits at the noise; halving would only cost rounds)
MIN_MATCHED_SHARE = 0.5  # trust: the final matches use at least this share of the (fewest) camera's images
# that a particle seen by every camera could give (a right calibration: ~0.9; onto ghosts: ~0)
MIN_IN_REACH = 0.5  # trust: the final matches whose start disparities were within the first tolerance
REACH_MARGIN = 1.5  # ... times this (the start's triangulation spreads a drift over the cameras)
CHANGE_SIGMAS = 10.0  # trust (warning only): a relative rotation changed by more than this many start sigmas

Detections = Mapping[str, np.ndarray]  # camera name -> (N_c, 2) pixels of one frame
Progress = Callable[[str], None]  # told each step's description (round, tolerance, disparity)


@dataclass(frozen=True)
class FrameParticles:
    """One frame's matches: detection rows per camera and the triangulated points."""

    frame: int
    rows: np.ndarray  # (M, C) int64 detection index per camera, -1 unused
    pixels: np.ndarray  # (M, C, 2) NaN where unused
    xyz: np.ndarray  # (M, 3)


@dataclass(frozen=True)
class Round:
    """One round: its tolerance, the disparity measured with the calibration it started from, and the
    bundle adjustment that followed (None for the final check)."""

    tolerance_px: float
    matches: int
    disparity: DisparityMap
    adjustment: Adjustment | None

    def summary(self) -> RoundSummary:
        """The round as the report keeps it."""
        return RoundSummary(self.tolerance_px, self.matches, int(self.disparity.inlier.sum()),
                            tuple(float(v) for v in self.disparity.rms_px), self.adjustment)


@dataclass(frozen=True)
class SelfCalResult:
    """The corrected calibration (its ``self_calibration`` the report) and the disparity maps:
    with the starting calibration (first round), with the corrected one (last round), and every round's."""

    calibration: Calibration
    before: DisparityMap
    after: DisparityMap
    rounds: tuple[Round, ...]
    report: SelfCalReport


# --------------------------------------------------------------------------- matching


def check_calibration(calibration: Calibration, cameras: Sequence[str], path: ErrorPath) -> None:
    """The calibration projects with the exact model and is of the rig that recorded the particles.

    Args:
        calibration: the start.
        cameras: the cameras of the particle detections.
        path: the calibration named in errors.
    """
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
    """Match one frame and triangulate the matches with the exact model.

    Args:
        calibration: the calibration matched with.
        frame: the frame's number.
        detections: its detections per camera.
        tolerance_px: the matching tolerance.
        min_cameras: the cameras a match must use.
        volume: the measured box, if any.
        depth_range_mm: the particles' world z range, if any.
        match: ``match_frame``'s signature (default the particles package's).

    Returns:
        The frame's matches.
    """
    from ..reconstruction.triangulate import triangulate_pixels

    if match is None:
        from .match import match_frame

        match = match_frame
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



# --------------------------------------------------------------------------- the rounds


MapFrames = Callable[[Callable[..., FrameParticles], list[tuple]], list[FrameParticles]]


def _subset(particles: ParticleSet, mask: np.ndarray, limit: int, seed: int) -> ParticleSet:
    idx = np.flatnonzero(mask)
    if len(idx) > limit:
        idx = np.sort(np.random.default_rng(seed).choice(idx, limit, replace=False))
    return ParticleSet(particles.pixels[idx], particles.xyz[idx], particles.frame[idx])


def _coarse_frames(frames: Sequence[int], detections: Mapping[int, Detections], first: str, minimum: int) -> list[int]:
    """The frames of the loose rounds: ``minimum`` spread over the experiment, more (spread) until the first
    camera has COARSE_IMAGES images in them (sparse seeding needs more frames for the same peaks)."""
    count = min(minimum, len(frames))
    while True:
        use = pick_frames(frames, count)
        if count >= len(frames) or sum(len(detections[f].get(first, ())) for f in use) >= COARSE_IMAGES:
            return use
        count += 1


class RoundProgress:
    """A tqdm bar over each round's frames: its description the round and tolerance, its postfix the
    disparity (disabled: does nothing)."""

    def __init__(self, enabled: bool = True) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=0, disable=not enabled, unit="frame", leave=True)

    def stage(self, desc: str, total: int) -> None:
        self.bar.reset(total=total)
        self.bar.set_description(desc)

    def advance(self, n: int = 1) -> None:
        self.bar.update(n)

    def note(self, text: str) -> None:
        self.bar.set_postfix_str(text)

    def close(self) -> None:
        self.bar.close()


class _Silent:
    def stage(self, desc: str, total: int) -> None:
        log.info("self-calibration: %s (%d frames)", desc, total)

    def advance(self, n: int = 1) -> None:
        pass

    def note(self, text: str) -> None:
        log.info("self-calibration: %s", text)


def _threaded(threads: int, progress) -> MapFrames:
    """Frames matched by ``threads`` threads of this process (numpy and the compiled kernels release the
    GIL), in frame order."""
    def run(fn: Callable[..., FrameParticles], args: list[tuple]) -> list[FrameParticles]:
        if threads <= 1 or len(args) <= 1:
            out = []
            for a in args:
                out.append(fn(*a))
                progress.advance()
            return out
        from concurrent.futures import ThreadPoolExecutor, as_completed

        with ThreadPoolExecutor(max_workers=threads) as pool:
            futures = {pool.submit(fn, *a): k for k, a in enumerate(args)}
            done: dict[int, FrameParticles] = {}
            for fut in as_completed(futures):
                done[futures[fut]] = fut.result()
                progress.advance()
        return [done[k] for k in range(len(args))]
    return run


def dask_map(client: Any) -> MapFrames:
    """Run the frames' matching as tasks on a dask.distributed Client (one task per frame), in frame order."""
    def run(fn: Callable[..., FrameParticles], args: list[tuple]) -> list[FrameParticles]:
        return client.gather([client.submit(fn, *a, pure=False) for a in args])
    return run


def _first_noise(dmap: DisparityMap) -> float:
    """A first guess of the pixel noise per coordinate from the inliers' disparity RMS (a 2-D RMS)."""
    rms = dmap.rms_px[np.isfinite(dmap.rms_px)]
    return float(max(np.median(rms) / math.sqrt(2.0), 0.02)) if len(rms) else 0.1


def _gauge_length_mm(calibration: Calibration, particles: ParticleSet) -> float:
    """The rig's distance to the particles: the mean distance of the camera centres from their median."""
    centre = np.median(particles.xyz, axis=0)
    centres = np.array([c.cam_from_world.inverse().t for c in calibration.cameras.values()])
    return float(np.mean(np.linalg.norm(centres - centre, axis=1)))


class FrameMatching:
    """How the rounds match: the frames (all, or the coarse ones in the loose rounds), the matcher, how the
    frames' tasks run, the progress; each matching is a numbered step of the progress."""

    def __init__(self, calibration: Calibration, detections: Mapping[int, Detections], options: SelfCalOptions,
                 volume: Any, depth_range_mm: Any, match: Callable | None, map_frames: MapFrames | None,
                 bar: Any) -> None:
        self.names = list(calibration.cameras)
        self.detections = detections
        self.options = options
        self.volume = volume
        self.depth_range_mm = depth_range_mm
        self.match = match
        self.map_frames = map_frames
        self.bar = bar
        self.run = map_frames or _threaded(options.threads, bar)
        self.frames = sorted(detections)
        self.coarse = _coarse_frames(self.frames, detections, self.names[0], options.coarse_frames)
        self.step = 0

    def frames_at(self, tolerance_px: float) -> list[int]:
        """The frames matched at ``tolerance_px``: the coarse ones above COARSE_PX, else all.

        Args:
            tolerance_px: the matching tolerance.

        Returns:
            The frames.
        """
        return self.coarse if tolerance_px > COARSE_PX else self.frames

    def matched(self, cal: Calibration, tolerance_px: float) -> ParticleSet:
        """Every frame's matches at ``tolerance_px`` with ``cal``, triangulated, stacked.

        Args:
            cal: the calibration matched with.
            tolerance_px: the matching tolerance.

        Returns:
            The matched particles.
        """
        use = self.frames_at(tolerance_px)
        self.step += 1
        self.bar.stage(f"self-calibration round {self.step}: matching at {tolerance_px:.3g} px", len(use))
        o = self.options
        found = self.run(match_particles, [(cal, f, self.detections[f], tolerance_px, o.min_cameras, self.volume,
                                            self.depth_range_mm, self.match) for f in use])
        if self.map_frames is not None:
            self.bar.advance(len(use))
        return _stack(found)

    def disparity(self, cal: Calibration, box: Cells, particles: ParticleSet) -> DisparityMap:
        """The disparity map of ``particles`` with ``cal`` in ``box``'s cells.

        Args:
            cal: the calibration.
            box: the cells.
            particles: the matched particles.

        Returns:
            The map (its inliers: the matches on their cells' peaks).
        """
        o = self.options
        return disparity_map(self.names, box, particles, particle_disparities(cal, particles), o.peak_radius_px,
                             o.field_radius_px, o.seed)

    def measure(self, cal: Calibration, tolerance_px: float, box: Cells | None) -> Measurement:
        """One round's matching: its matches, its cells' box and disparity map (None with too few matches).

        Args:
            cal: the calibration matched with.
            tolerance_px: the matching tolerance.
            box: the cells (None: around these matches).

        Returns:
            The measurement.
        """
        particles = self.matched(cal, tolerance_px)
        if len(particles.xyz) < MIN_MATCHES:
            return Measurement(tolerance_px, particles, box, None)
        box = box or Cells.around(particles.xyz, self.options.cells)
        dmap = self.disparity(cal, box, particles)
        self.bar.note(f"{len(particles.xyz)} matches, {int(dmap.inlier.sum())} inliers, disparity "
                      f"{_largest(dmap.rms_px):.3f} px")
        log.info("self-calibration: tolerance %.3g px, %d matches, %d inliers, disparity RMS %s px",
                 tolerance_px, len(particles.xyz), int(dmap.inlier.sum()), np.round(dmap.rms_px, 3).tolist())
        return Measurement(tolerance_px, particles, box, dmap)


@dataclass(frozen=True)
class Measurement:
    """One matching at a tolerance: the matches, the cells' box, the disparity map (None: too few matches)."""

    tolerance_px: float
    particles: ParticleSet
    box: Cells | None
    disparity: DisparityMap | None

    @property
    def inliers(self) -> int:
        """Matches on their cells' disparity peaks (0 without a map)."""
        return 0 if self.disparity is None else int(self.disparity.inlier.sum())


@dataclass(frozen=True)
class Rounds:
    """Where the rounds have left a self-calibration: the calibration the next round matches with and at what
    tolerance, the rounds so far and what the adjustments share (the cells, the gauge, the last fit)."""

    current: Calibration
    tolerance_px: float  # the next round's
    first_tolerance_px: float  # the first round's, once widened
    cells: Cells | None = None  # the disparity maps' box (the first adjusted round's, or the one given)
    rounds: tuple[Round, ...] = ()
    previous_rms_px: float | None = None  # the last adjusted round's largest disparity RMS
    gauge: Gauge | None = None
    refined: Refined | None = None  # the last bundle adjustment
    last_particles: ParticleSet | None = None  # the last round's matches
    stopped: bool = False  # a round found too little, or the disparities stopped falling
    exhausted: bool = False  # max_rounds ran without a stop


@dataclass(frozen=True)
class Adjusting:
    """What every round's bundle adjustment holds: the start, the intrinsics prior, which windows are in air."""

    start: Calibration
    prior: IntrinsicsPrior
    in_air: list[bool]


def _first_measurement(m: FrameMatching, at: Rounds, path: ErrorPath) -> Measurement:
    """The first round's matching: its tolerance widened by WIDEN (up to max_tolerance_px) while it finds no
    clear disparity peak; no confident matches even then is one error line."""
    o = m.options
    tol = at.tolerance_px
    got = m.measure(at.current, tol, at.cells)
    # no clear peak yet -> the drift may exceed the tolerance: widen it (up to max_tolerance_px)
    while (got.disparity is None or got.inliers < FIRST_PEAK_MIN) and tol < o.max_tolerance_px:
        tol = min(WIDEN * tol, o.max_tolerance_px)
        log.info("self-calibration: no clear disparity peak: tolerance widened to %.3g px", tol)
        got = m.measure(at.current, tol, at.cells)
    if got.disparity is None or got.inliers < FIRST_PEAK_MIN:
        used = len(m.frames_at(tol))
        what = (f"{len(got.particles.xyz)} particles matched" if got.disparity is None else
                f"{len(got.particles.xyz)} matches but no disparity peak ({got.inliers} on it)")
        raise AriSfmError(path, f"no confident matches: {what} in {o.min_cameras} cameras at up to "
                                f"{tol:g} px over {used} frames; try a larger --max-tolerance-px (the drift "
                                "must fit in it), more --coarse-frames, fewer --cells, --min-cameras 3, or "
                                "check that the calibration is of this rig")
    return got


def run_round(m: FrameMatching, a: Adjusting, at: Rounds, r: int, path: ErrorPath) -> Rounds:
    """Round ``r``: match at the round's tolerance, measure the disparity, adjust on its inliers.

    The rounds stop (``stopped``) when a later round finds too few inliers, or when the disparities stopped
    falling at the final tolerance (that round kept as the final check). The next round matches at the final
    tolerance once the adjustment fits at the noise (or the disparities stalled), else at half the tolerance.

    Args:
        m: how the rounds match.
        a: what the adjustments hold.
        at: where the previous rounds left the self-calibration.
        r: the round's index (0: the first, whose tolerance widens).
        path: the calibration named in errors.

    Returns:
        Where this round leaves it.
    """
    o = m.options
    if r == 0:
        got = _first_measurement(m, at, path)
        at = replace(at, tolerance_px=got.tolerance_px, first_tolerance_px=got.tolerance_px)
    else:
        got = m.measure(at.current, at.tolerance_px, at.cells)
        if got.disparity is None or got.inliers < MIN_MATCHES:
            return replace(at, stopped=True)
    dmap, particles, tol = got.disparity, got.particles, at.tolerance_px
    assert dmap is not None  # a round with a disparity peak
    at = replace(at, cells=got.box, last_particles=particles)
    rms = _largest(dmap.rms_px)
    stalled = at.previous_rms_px is not None and rms > (1.0 - o.min_improvement) * at.previous_rms_px
    if stalled and tol <= o.final_tolerance_px:  # the disparities stopped falling: done
        return replace(at, rounds=at.rounds + (Round(tol, len(particles.xyz), dmap, None),), stopped=True)
    landmarks = _subset(particles, dmap.inlier, o.max_landmarks, o.seed + r)
    gauge = at.gauge if at.gauge is not None else Gauge.of(a.start, a.in_air, _gauge_length_mm(a.start, landmarks))
    m.bar.note(f"adjusting {len(landmarks.xyz)} particles")
    noise = at.refined.adjustment.noise_px if at.refined else _first_noise(dmap)
    refined = refine_with_landmarks(at.current, landmarks, gauge, a.prior, o.huber_px, o.max_iterations,
                                    o.backend, noise)
    adjustment = refined.adjustment
    m.bar.note(f"adjusted: {adjustment.rms_px:.3f} px RMS on {adjustment.landmarks} particles")
    # the next round: at the final tolerance once the correction fits at the noise, else halved
    fits = adjustment.rms_px < o.final_tolerance_px / JUMP_NOISE
    return replace(at, current=refined.calibration, previous_rms_px=rms, gauge=gauge, refined=refined,
                   rounds=at.rounds + (Round(tol, len(particles.xyz), dmap, adjustment),),
                   tolerance_px=o.final_tolerance_px if (stalled or fits) else max(o.final_tolerance_px, tol / 2.0))


def final_check(m: FrameMatching, at: Rounds) -> Rounds:
    """The final check: after a round that adjusted, the frames matched again with the corrected calibration.

    At the next round's tolerance when max_rounds ran out, else at the last adjusted round's (after a round
    that found too little: the last good one's).

    Args:
        m: how the rounds match.
        at: where the rounds left the self-calibration.

    Returns:
        It with the final check's round.
    """
    last = at.rounds[-1]
    if last.adjustment is None:  # the rounds ended on a check already
        return at
    tol = at.tolerance_px if at.exhausted else last.tolerance_px
    particles = m.matched(at.current, tol)
    assert at.cells is not None  # set by the round that adjusted
    dmap = m.disparity(at.current, at.cells, particles)
    m.bar.note(f"final: {len(particles.xyz)} matches, disparity {_largest(dmap.rms_px):.3f} px")
    return replace(at, rounds=at.rounds + (Round(tol, len(particles.xyz), dmap, None),), last_particles=particles)


def self_calibrate(calibration: Calibration, detections: Mapping[int, Detections],
                   options: SelfCalOptions = SelfCalOptions(), volume: Any = None, depth_range_mm: Any = None,
                   match: Callable | None = None, map_frames: MapFrames | None = None,
                   cells_box: Cells | None = None, path: ErrorPath = "calibration",
                   progress: Any = None) -> SelfCalResult:
    """Volume self-calibration (module docstring) from ``detections``.

    Steps: the rounds (:func:`run_round`, each matching, measuring and adjusting) until they stop or
    ``options.max_rounds`` ran, the final check (:func:`final_check`), the trust checks (:func:`trust_checks`),
    the report.

    Args:
        calibration: the start (exact model) of the rig that recorded the particles.
        detections: {frame: {camera: (N, 2) px}}.
        options: the options.
        volume: the measured box (the matcher's depth limits), if any.
        depth_range_mm: the particles' world z range, if any (instead of ``volume``).
        match: ``match_frame``'s signature (default: :func:`ari_sfm.particles.match.match_frame`).
        map_frames: ``map_frames(fn, args)``: how the frames' matching tasks ``fn(*a)`` run (default:
            ``options.threads`` threads of this process; :func:`dask_map` on a Client).
        cells_box: the disparity maps' box (default: the first round's matched particles).
        path: the calibration named in errors.
        progress: a :class:`RoundProgress` (default: the log).

    Returns:
        The corrected calibration, the disparity maps before and after, every round and the report.
    """
    t0 = time.perf_counter()
    names = list(calibration.cameras)
    if not detections:
        raise AriSfmError(path, "no particle detections to self-calibrate from")
    check_calibration(calibration, list(next(iter(detections.values()))), path)
    _check_options(options, len(names))
    m = FrameMatching(calibration, detections, options, volume, depth_range_mm, match, map_frames,
                      progress or _Silent())
    free = free_intrinsics(calibration, options.intrinsics)
    a = Adjusting(calibration, IntrinsicsPrior.of(calibration, free, options.intrinsics),
                  [w.interface.medium_index == 1.0 for w in calibration.window_list()])
    tol = float(options.tolerance_px)
    at = Rounds(calibration, tol, tol, cells_box)
    for r in range(options.max_rounds):
        at = run_round(m, a, at, r, path)
        if at.stopped:
            break
    else:
        at = replace(at, exhausted=True)  # max_rounds reached: the final check at the next round's tolerance
    if not at.rounds:
        raise AriSfmError(path, "no confident matches (see the log)")
    at = final_check(m, at)
    refined, current, rounds = at.refined, at.current, at.rounds
    if refined is None:
        raise AriSfmError(path, "no bundle adjustment ran (see the log)")
    assert at.gauge is not None and at.last_particles is not None  # set by the round that adjusted
    after = rounds[-1].disparity
    checks = trust_checks(calibration, current, detections, m.frames_at(rounds[-1].tolerance_px), at.last_particles,
                          after, at.first_tolerance_px, options)
    report = _report(calibration, current, options, m.frames, rounds, at.gauge, refined, checks,
                     time.perf_counter() - t0)
    for c in checks:
        if not c.passed:
            log.warning("self-calibration: %s: %s (%.4g, limit %.4g)", "failed" if c.fatal else "warning", c.what,
                        c.value, c.limit)
    corrected = result_calibration(current, refined, report)
    return SelfCalResult(corrected, rounds[0].disparity, after, tuple(rounds), report)


def _check_options(options: SelfCalOptions, cameras: int) -> None:
    """The cameras the options ask for, checked before self-calibration starts (the modes are checked by
    :class:`SelfCalOptions` itself)."""
    if options.min_cameras > cameras:
        raise AriSfmError(None, f"--min-cameras {options.min_cameras} exceeds the rig's {cameras} cameras")


def _largest(values: np.ndarray) -> float:
    """The largest finite value (NaN when none)."""
    finite = values[np.isfinite(values)]
    return float(finite.max()) if len(finite) else float("nan")


def converged(after: DisparityMap, options: SelfCalOptions) -> bool:
    """Whether the final disparities are one noise level.

    Every camera's RMS finite, within 1.5x of the smallest and below half the peak radius (a correction from a
    ghost peak leaves px in some cameras).

    Args:
        after: the final disparity map.
        options: the options (the peak radius).

    Returns:
        True when they are.
    """
    rms = after.rms_px
    return bool(np.all(np.isfinite(rms)) and rms.max() <= 1.5 * rms.min() and rms.max() < 0.5 * options.peak_radius_px)


def _relative_rotation_deg(a: Calibration, b: Calibration, name: str) -> float:
    """The angle between camera ``name``'s rotation relative to the first camera in ``a`` and in ``b``."""
    first = next(iter(a.cameras))

    def rel(c: Calibration) -> np.ndarray:
        return c.cameras[name].cam_from_world.R @ c.cameras[first].cam_from_world.R.T

    return rotation_angle_deg(rel(a), rel(b))


def trust_checks(start: Calibration, final: Calibration, detections: Mapping[int, Detections],
                 frames: Sequence[int], particles: ParticleSet, after: DisparityMap, first_tolerance_px: float,
                 options: SelfCalOptions) -> tuple[Check, ...]:
    """Whether the result can be trusted, beyond its low disparity:

    - ``noise_level``: the final disparities are one noise level in every camera (:func:`converged`);
    - ``matched_share``: the final matches use at least MIN_MATCHED_SHARE of the images of the camera with
      the fewest (a calibration fitted onto ghosts agreeing with each other matches almost nothing);
    - ``in_reach``: at least MIN_IN_REACH of the final particles were within REACH_MARGIN x the first
      round's tolerance of the start calibration (else the correction went where the start could not
      have matched them: the start cannot be trusted, or the result is not of its rig);
    - ``rig_change`` (a warning): each camera's rotation relative to the first changed by less than
      CHANGE_SIGMAS of the start's sigma (or 0.2 deg): a larger change is a camera knocked hard, or a
      start of another rig state;
    - ``start_quality``: the start calibration passed its quality gate (a start the gate failed, e.g. a
      lens left out, is refitted by the particles into cameras as wrong as it, at a low disparity): its
      robust RMSE against the gate's allowance; a start without a verdict passes.
    - ``start_principal_points`` (a warning): the start estimated every principal point
      (:func:`~ari_sfm.particles.landmarks.guessed_principal_points`).

    Args:
        start: the start calibration.
        final: the corrected calibration.
        detections: {frame: {camera: (N, 2) px}}.
        frames: the frames the final matching used.
        particles: the final matches.
        after: the final disparity map.
        first_tolerance_px: the first round's tolerance (once widened).
        options: the options.

    Returns:
        The checks.
    """
    names = list(final.cameras)
    images = min(sum(len(detections[f][n]) for f in frames) for n in names)
    share = float(len(particles.xyz) / images) if images else 0.0
    checks = [
        Check("noise_level", _largest(after.rms_px), 0.5 * options.peak_radius_px, converged(after, options),
              "the final disparities are one noise level in every camera"),
        Check("matched_share", share, MIN_MATCHED_SHARE, share >= MIN_MATCHED_SHARE,
              "share of the particle images (camera with the fewest) the final calibration matches"),
    ]
    from ..reconstruction.triangulate import triangulate_pixels

    if len(particles.xyz):
        xyz = triangulate_pixels(start, {n: particles.pixels[:, c] for c, n in enumerate(names)})[0]
        d = particle_disparities(start, ParticleSet(particles.pixels, xyz, particles.frame))
        dist = np.linalg.norm(d, axis=2)
        worst = np.where(np.isfinite(dist).any(axis=1), np.max(np.where(np.isfinite(dist), dist, -1.0), axis=1),
                         np.nan)
        reach = float(np.mean(np.nan_to_num(worst, nan=np.inf) <= REACH_MARGIN * first_tolerance_px))
    else:
        reach = 0.0
    checks.append(Check("in_reach", reach, MIN_IN_REACH, reach >= MIN_IN_REACH,
                        f"share of the final particles within {REACH_MARGIN:g} x the first tolerance "
                        f"({first_tolerance_px:g} px) of the start calibration"))
    unc = start.uncertainty
    worst_ratio, worst_change = 0.0, 0.0
    for n in names[1:]:
        change = _relative_rotation_deg(start, final, n)
        sigma = None if unc is None or n not in unc.cameras else unc.cameras[n].rotation_deg
        limit = max(0.2, CHANGE_SIGMAS * sigma) if sigma else 0.2
        if change / limit > worst_ratio:
            worst_ratio, worst_change = change / limit, change
    checks.append(Check("rig_change", worst_change, worst_change / worst_ratio if worst_ratio else 0.2,
                        worst_ratio <= 1.0, "largest change of a camera's rotation relative to the first (deg) "
                        f"against {CHANGE_SIGMAS:g} start sigmas (or 0.2 deg)", fatal=False))
    q = start.quality
    if q is not None:
        checks.append(Check("start_quality", q.robust_rmse_px, q.allowance_px or 0.0, q.ok,
                            "the start calibration's robust RMSE (px) against its quality gate's allowance: "
                            + ("passed" if q.ok else f"failed ({q.why}): calibrate it again")))
    guessed = guessed_principal_points(start)
    checks.append(Check("start_principal_points", float(len(guessed)), 0.0, not guessed,
                        "cameras whose principal point the start held at a guess (e.g. the image centre) rather "
                        "than estimated: the relative rotations are only as good as that guess, weighed as a "
                        f"{UNKNOWN_PRIOR_PX:g} px prior" + (f" ({', '.join(guessed)})" if guessed else ""),
                        fatal=False))
    return tuple(checks)


def _report(start: Calibration, final: Calibration, options: SelfCalOptions, frames: Sequence[int],
            rounds: Sequence[Round], gauge: Gauge, refined: Refined, checks: Sequence[Check],
            seconds: float) -> SelfCalReport:
    names = list(start.cameras)
    before, after = rounds[0].disparity, rounds[-1].disparity
    windows = start.window_list()
    in_air = all(w.interface.medium_index == 1.0 for w in windows)
    held = [("the window's plane (normal and position) in the world" if len(windows) == 1 else
             "every window's plane (normal and position) in the world"),
            f"the rig's mean motion along the {len(gauge.twists)} "
            + ("motion that keeps " if len(gauge.twists) == 1 else "motions that keep ")
            + ("the window" if len(windows) == 1 else "the windows")
            + (" (rotation about its normal, translation within its plane"
               + (" and along its normal: in air the distance is not observed)" if in_air else ")")
               if len(windows) == 1 else ""),
            "the scale: the sum of the distances between every pair of camera centres"]
    free = refined.covariance.cameras[names[0]].intrinsics
    if options.intrinsics == Intrinsics.HELD or not free:
        held.append("the intrinsics" + ("" if options.intrinsics == Intrinsics.HELD else
                                        " (the start has no uncertainty to weigh them with)"))
    else:
        held.append("the lens distortion but " + "/".join(free) if free else "the intrinsics")
    estimated = ["every camera's pose (camera 0 included)", "the particles"]
    if free:
        estimated.append(" ".join(free) + (" with the start calibration's sigmas as priors"
                                           if options.intrinsics == Intrinsics.PRIOR else " (no prior)"))
    adjustments = [r.adjustment for r in rounds if r.adjustment]
    fatal = [c for c in checks if c.fatal]
    return SelfCalReport(
        frames=tuple(int(f) for f in frames),
        particles_used=int(max((a.landmarks for a in adjustments), default=0)),
        landmarks_all_rounds=int(sum(a.landmarks for a in adjustments)), held=tuple(held),
        estimated=tuple(estimated),
        scale_how="prior on the sum of the distances between every pair of camera centres, at the starting "
                  "calibration's value", scale_sum_mm=gauge.scale_sum_mm,
        scale_sigma_mm=_stiff_sigma(), backend=options.backend.value,
        options=options,
        disparity_rms_px={n: BeforeAfter(float(before.rms_px[c]), float(after.rms_px[c])) for c, n in enumerate(names)},
        converged=converged(after, options), passed=all(c.passed for c in fatal), checks=tuple(checks),
        rounds=tuple(r.summary() for r in rounds),
        rotation_change_deg={n: rotation_angle_deg(start.cameras[n].cam_from_world.R, final.cameras[n].cam_from_world.R)
                             for n in names},
        sigmas=dict(refined.covariance.cameras),
        matched_share=float(next(c.value for c in checks if c.name == "matched_share")), time_s=seconds)


def _stiff_sigma() -> float:
    from .landmarks import STIFF_SIGMA_MM

    return STIFF_SIGMA_MM


def result_calibration(current: Calibration, refined: Refined, report: SelfCalReport) -> Calibration:
    """The corrected calibration as calibration.json holds it.

    The self-calibration's own residuals (its particles' reprojection residuals) and uncertainty (relative
    poses, estimated intrinsics); the target calibration's stages, optimizer report, quality verdict, outliers
    and body poses dropped (they are of the start, whose cameras have moved since).

    Args:
        current: the corrected calibration as the last adjustment left it.
        refined: the last adjustment (residuals, covariance).
        report: the self-calibration's report (``self_calibration``).

    Returns:
        The calibration.
    """
    from ..results import CameraUncertainty, ResidualStats, Uncertainty

    cov = refined.covariance
    cams = {n: CameraUncertainty(dict(s.intrinsics), s.rotation_rel_deg is not None, s.rotation_rel_deg,
                                 s.translation_rel_mm) for n, s in cov.cameras.items()}
    uncertainty = Uncertainty(cov.sigma_px, cams, None)
    return replace(current, residuals=ResidualStats.of([refined.residuals_px]), uncertainty=uncertainty,
                   frames={}, stacking_poses={},
                   quality=None, outliers=None, optimizer=None, stages=(), self_calibration=report)


def disparity_json(result: SelfCalResult) -> dict[str, Any]:
    """``disparity.json``: the cells and, per camera and cell, the disparity before and after."""
    return {"format": "ari-sfm-disparity/1", "cells": result.before.cells.to_json(),
            "cell_centres_mm": result.before.cells.centres().tolist(),
            "before": result.before.to_json(), "after": result.after.to_json(),
            "rounds": [r.disparity.to_json() for r in result.rounds]}


def write_self_calibration(result: SelfCalResult, out_dir: str | Path) -> None:
    """OUT/calibration.json and OUT/disparity.json, both or neither.

    Written in a temporary folder inside OUT, then renamed into place: a full disk or an interrupt leaves
    OUT's old files.

    Args:
        result: the self-calibration.
        out_dir: OUT.
    """
    from ..io import calibration_to_json, write_files_atomic
    from ..io.atomic import format_json, to_jsonable

    def writer(tmp: Path) -> None:
        (tmp / "disparity.json").write_text(format_json(to_jsonable(disparity_json(result))))
        (tmp / "calibration.json").write_text(format_json(to_jsonable(calibration_to_json(result.calibration))))

    write_files_atomic(Path(out_dir), writer)


# --------------------------------------------------------------------------- a dataset


def pick_frames(frames: Iterable[int], count: int | None) -> list[int]:
    """``count`` frames spread evenly over ``frames``.

    Args:
        frames: the frames.
        count: how many (None, or more than there are: all).

    Returns:
        The frames, sorted.
    """
    frames = sorted(int(f) for f in frames)
    if count is None or count >= len(frames):
        return frames
    return [frames[int(round(k))] for k in np.linspace(0, len(frames) - 1, count)]


def check_not_input(out: str | Path, inputs: Sequence[Any]) -> None:
    """-o must neither be nor hold an input (its calibration.json would overwrite the start calibration).

    Args:
        out: the output folder.
        inputs: the input paths (None entries ignored).
    """
    import os

    target = Path(os.path.realpath(out))
    for p in inputs:
        if p is None:
            continue
        real = Path(os.path.realpath(p))
        if real == target or target in real.parents:
            raise AriSfmError(out, f"-o/--out would hold an input ({p}): write the self-calibration elsewhere")


def self_calibrate_dataset(dataset_path: str | Path, calibration_path: str | Path, out: str | Path,
                           options: SelfCalOptions = SelfCalOptions(), detections_path: str | Path | None = None,
                           frames: int | None = 10,
                           depth_range_mm: tuple[float, float] | None = None, workers: int = 0,
                           scheduler: str | None = None, progress: bool = False) -> SelfCalResult:
    """``ari-sfm self-calibrate``: a particle experiment and its rig's calibration -> OUT.

    OUT/calibration.json (the corrected calibration, ``self_calibration`` key) and OUT/disparity.json, written
    together or not at all.

    Args:
        dataset_path: the particle experiment (DATASET_FORMAT 1.2).
        calibration_path: its rig's calibration.json (exact model).
        out: OUT.
        options: the options.
        detections_path: a particles.parquet (default: the one rig.yaml names).
        frames: how many of the detections' frames to use (spread evenly; None: all).
        depth_range_mm: the particles' world z range, instead of rig.yaml's volume.
        workers: Dask workers matching the frames (:func:`ari_sfm.particles.engine.dask_client`; 0:
            ``options.threads`` threads in this process).
        scheduler: a Dask scheduler's address, instead of local workers.
        progress: a progress bar on stderr.

    Returns:
        The self-calibration (its report with the inputs).
    """
    import os

    from ..io.particles import read_detections
    from .engine import dask_client
    from .reconstruct import load_experiment, volume_for

    out = Path(out)
    calibration_path = Path(calibration_path)
    check_not_input(out, [calibration_path, dataset_path, detections_path])
    dataset, calibration = load_experiment(dataset_path, calibration_path, out)
    check_calibration(calibration, list(dataset.cameras), calibration_path)
    det_path = Path(detections_path) if detections_path is not None else dataset.detections
    if det_path is None:
        raise AriSfmError(dataset.rig_path, "particles: names no detections table: run `ari-sfm detect-particles` "
                                            "and pass its particles.parquet with --detections")
    check_not_input(out, [det_path, dataset.rig_path])
    cameras = list(calibration.cameras)
    det = read_detections(det_path, dataset.cameras)
    by_frame = det.by_frame(cameras)
    if not by_frame:
        raise AriSfmError(det_path, "holds no particle detections")
    chosen = pick_frames(by_frame, frames)
    detections = {f: {c: det.uv[by_frame[f][c]] for c in cameras} for f in chosen}
    volume = volume_for(dataset, calibration, depth_range_mm)
    bar = RoundProgress(progress) if progress else None
    try:
        with dask_client(workers, scheduler) as client:
            result = self_calibrate(calibration, detections, options, volume=volume,
                                    map_frames=None if client is None else dask_map(client), path=calibration_path,
                                    progress=bar)
    finally:
        if bar is not None:
            bar.close()
    report = replace(result.report, inputs=SelfCalInputs(
        str(Path(os.path.abspath(dataset.rig_path))), str(Path(os.path.abspath(calibration_path))),
        str(Path(os.path.abspath(det_path))), workers if scheduler is None else None, scheduler))
    result = replace(result, report=report, calibration=replace(result.calibration, self_calibration=report))
    write_self_calibration(result, out)
    return result

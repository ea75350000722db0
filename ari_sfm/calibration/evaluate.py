"""Reprojection errors of a calibration on observations (its own or held-out ones)."""
from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import AriSfmError
from ..geometry import Pose, rotation_from_rotvec
from ..records import Dataset, Observation, Target
from ..results import ResidualStats
from .record import Calibration


def residual_stats(residuals: Iterable[np.ndarray]) -> ResidualStats:
    """rmse_px = sqrt(mean(du^2 + dv^2)), mae_px = mean distance, max_px, count."""
    return ResidualStats.of(residuals)


def project_target(calibration: Calibration, camera: str, pose_world_from_target, points_target: np.ndarray,
                   added_mm: float = 0.0) -> np.ndarray:
    """Project target points into a camera through the window.

    Args:
        calibration: the calibration.
        camera: the camera's name.
        pose_world_from_target: the target's world_from_target pose.
        points_target: the target points (M, 3), target frame, mm.
        added_mm: the glass stacked on the window (mm).

    Returns:
        The pixels (M, 2), NaN where a point projects to no pixel.
    """
    X_c = calibration.cameras[camera].cam_from_world.apply(pose_world_from_target.apply(points_target))
    return calibration.projection_model(camera, added_mm).project(X_c)


def observation_residuals(calibration: Calibration, observations: Sequence[Observation],
                          target: Target) -> list[tuple[Observation, np.ndarray]]:
    """Give the reprojection residuals of every observation whose pose the calibration holds.

    Args:
        calibration: the calibration.
        observations: the records.
        target: the target (its points).

    Returns:
        (observation, residual (M, 2) = projected - observed pixels) pairs.
    """
    ids_all, xyz_all = target.points_3d()
    lookup = {int(i): k for k, i in enumerate(ids_all)}
    out = []
    for obs in observations:
        if obs.camera not in calibration.cameras:
            continue
        if obs.set == "stacking":
            pose, added = calibration.stacking_poses.get(obs.frame), obs.added_mm or 0.0
        else:
            pose, added = calibration.frames.get(obs.frame), 0.0
        if pose is None:
            continue
        pts = xyz_all[[lookup[int(i)] for i in obs.ids]]
        out.append((obs, project_target(calibration, obs.camera, pose, pts, added) - obs.pixels))
    return out


def solve_frame_poses(calibration: Calibration, observations: Sequence[Observation], target: Target,
                      sets: tuple[str, ...] = ("calibration", "reconstruction")) -> dict[str, Pose]:
    """Fit world_from_target of every frame the calibration does not hold, with the rig fixed.

    PnP in the first camera that sees the frame (window removed as in Eqs. 11-12),
    then a least-squares refinement through the calibration's own model over all
    cameras that see it. Used to judge a calibration on held-out poses.

    Args:
        calibration: the calibration (the rig held fixed).
        observations: the records; those with 4 or more corners of a calibrated camera count.
        target: the target (its points).
        sets: the observation sets whose frames are fitted.

    Returns:
        Frame -> its world_from_target (frames whose PnP fails are left out).
    """
    import cv2
    from scipy.optimize import least_squares

    from ..init.interface_pose import real_cam_from_target

    ids_all, xyz_all = target.points_3d()
    lookup = {int(i): k for k, i in enumerate(ids_all)}
    by_frame: dict[str, list[Observation]] = {}
    for o in observations:
        if o.set in sets and o.frame not in calibration.frames and o.camera in calibration.cameras and len(o.ids) >= 4:
            by_frame.setdefault(o.frame, []).append(o)
    poses = {}
    for frame, obs in by_frame.items():
        first = obs[0]
        cam = calibration.cameras[first.camera]
        pts = [xyz_all[[lookup[int(i)] for i in o.ids]] for o in obs]
        ok, rvec, tvec = cv2.solvePnP(pts[0], first.pixels.astype(float), cam.K, cam.dist)
        if not ok:
            continue
        cam_from_target = real_cam_from_target(Pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3)),
                                               calibration.normal_cam(first.camera),
                                               calibration.interface_of(first.camera).shift_mm)
        start = cam.cam_from_world.inverse().compose(cam_from_target)
        models = [calibration.projection_model(o.camera) for o in obs]
        x = least_squares(_held_pose_residuals, np.zeros(6), x_scale=np.r_[1e-3, 1e-3, 1e-3, 1.0, 1.0, 1.0],
                          args=(start, calibration, models, obs, pts)).x
        poses[frame] = _moved(start, x)
    return poses


def _moved(start: Pose, x: np.ndarray) -> Pose:
    """``start`` (world_from_target) moved by ``x`` = [rotation vector, translation mm]."""
    return Pose(start.R @ rotation_from_rotvec(x[:3]), start.t + x[3:])


def _held_pose_residuals(x: np.ndarray, start: Pose, calibration: Calibration, models: list,
                         obs: list[Observation], pts: list[np.ndarray]) -> np.ndarray:
    """The pixel residuals of one frame's observations at the pose ``_moved(start, x)`` (1e3 px for no ray)."""
    pose = _moved(start, x)
    out = [m.project(calibration.cameras[o.camera].cam_from_world.apply(pose.apply(p))) - o.pixels
           for m, o, p in zip(models, obs, pts)]
    r = np.concatenate(out).ravel()
    return np.where(np.isfinite(r), r, 1e3)


def evaluate(calibration: Calibration, observations: str | Path | Dataset | Sequence[Observation],
             target: Target | None = None, solve_poses: bool = False) -> ResidualStats:
    """Give a calibration's reprojection errors on observations.

    Only records of frames whose poses the calibration holds (and its stacking poses) count, unless
    ``solve_poses``. Never NaN: nothing to judge, a corner that projects to no pixel through the window,
    or no target geometry is an error.

    Args:
        calibration: the calibration (or a calibration.json path).
        observations: an observations.json path, a Dataset, or loaded records.
        target: the target geometry (default: the Dataset's or the calibration's).
        solve_poses: fit every frame's pose with the rig held fixed (:func:`evaluate_held_out`: held-out
            views; the calibration's own frame poses and stacking records are not used), the same as
            ``ari-sfm evaluate --solve-poses``.

    Returns:
        The statistics: rmse_px, mae_px, max_px, count and per_camera.

    Raises:
        AriSfmError: naming the observations, when nothing is judged (no record of a calibrated camera in a
            frame whose pose is known or could be fitted), a corner projects to no pixel, or there is no target.
        TypeError: if ``calibration`` or ``observations`` is of another kind.
    """
    if solve_poses:
        return evaluate_held_out(calibration, observations, target)
    calibration = _as_calibration(calibration)
    return _checked(reprojection_stats(calibration, observations, target), observations,
                    "the calibration holds (held-out views: add --solve-poses)")


def _as_calibration(calibration: Calibration | str | Path) -> Calibration:
    """A Calibration, or the one a calibration.json path holds (anything else: TypeError saying what is wanted)."""
    if isinstance(calibration, (str, Path)):
        from ..io import load_calibration

        return load_calibration(calibration)
    if not isinstance(calibration, Calibration):
        raise TypeError(f"calibration must be an ari_sfm Calibration or a calibration.json path "
                        f"(got {type(calibration).__name__})")
    return calibration


def _as_records(observations) -> list[Observation]:
    """Observation records given as such (anything else: TypeError saying what is wanted)."""
    wanted = "observations must be an observations.json path, a Dataset or a list of Observation records"
    if isinstance(observations, (bytes, Mapping)) or not isinstance(observations, Iterable):
        raise TypeError(f"{wanted} (got {type(observations).__name__})")
    records = list(observations)
    other = next((o for o in records if not isinstance(o, Observation)), None)
    if other is not None:
        raise TypeError(f"{wanted} (got a {type(observations).__name__} holding a {type(other).__name__})")
    return records


def _source(observations: str | Path | Dataset | Sequence[Observation]) -> str | Path:
    """What to name in an error about ``observations``."""
    if isinstance(observations, Dataset):
        return observations.rig_path
    return observations if isinstance(observations, (str, Path)) else "observations"


def _checked(stats: ResidualStats, observations, which: str) -> ResidualStats:
    """``stats`` unless nothing was judged or a residual is not finite (AriSfmError naming the observations)."""
    if stats.count == 0:
        raise AriSfmError(_source(observations), f"no corner to judge: no observation of a calibrated camera in a "
                                                 f"frame {which}")
    if not np.isfinite(stats.rmse_px):
        bad = [c for c, st in (stats.per_camera or {}).items() if not np.isfinite(st.rmse_px)]
        raise AriSfmError(_source(observations), f"corners of {', '.join(bad) or 'a camera'} project to no pixel "
                                                 "through the window at their frame poses (the board behind the "
                                                 "window or beyond reach): these views do not fit this calibration")
    return stats


def reprojection_stats(calibration: Calibration, observations: str | Path | Dataset | Sequence[Observation],
              target: Target | None = None, solve_poses: bool = False) -> ResidualStats:
    """Give :func:`evaluate`'s statistics as they come: count 0 and NaN when nothing is judged, NaN where a
    corner does not project.

    Args:
        calibration: the calibration.
        observations: an observations.json path, a Dataset, or loaded records.
        target: the target geometry (default: the Dataset's or the calibration's).
        solve_poses: fit the frames the calibration does not hold (its own kept).

    Returns:
        The statistics: rmse_px, mae_px, max_px, count and per_camera.

    Raises:
        AriSfmError: if the dataset holds no observations, a pixel lies outside its image, or there is no target.
    """
    if isinstance(observations, Dataset):
        target = target or observations.target
        if observations.observations is None:
            raise AriSfmError(observations.rig_path, "the dataset holds no observations (images only): run "
                                                     "`ari-sfm detect` first, or pass its observations.json")
        records: Sequence[Observation] = observations.observations
    elif isinstance(observations, (str, Path)):
        from ..io import load_observations
        from ..io.observations import check_pixels_in_images

        target = target or calibration.target
        records = load_observations(Path(observations), target, list(calibration.cameras))
        check_pixels_in_images(records, {n: c.image_size for n, c in calibration.cameras.items()}, observations)
    else:
        records = _as_records(observations)
    if not isinstance(observations, (str, Path)):  # a file was checked as it was read
        from ..io.observations import check_pixels_in_images

        check_pixels_in_images(records, {n: c.image_size for n, c in calibration.cameras.items()},
                               _source(observations))
    target = target or calibration.target
    if target is None:
        raise AriSfmError(_source(observations), "no target geometry to judge these corners: the calibration holds "
                                                 "none (pass target=, or a Dataset whose rig.yaml has it)")
    if solve_poses:
        extra = solve_frame_poses(calibration, records, target)
        calibration = replace(calibration, frames={**calibration.frames, **extra})
        records = [o if o.set != "reconstruction" else replace(o, set="calibration") for o in records]
    pairs = observation_residuals(calibration, records, target)
    per_camera = {c: residual_stats(r for o, r in pairs if o.camera == c) for c in calibration.cameras}
    return replace(residual_stats(r for _, r in pairs), per_camera=per_camera)


def evaluate_held_out(calibration: Calibration, observations: str | Path | Dataset | Sequence[Observation],
                      target: Target | None = None) -> ResidualStats:
    """Give the reprojection errors on held-out views, every frame's pose fitted with the rig fixed.

    The calibration's own frame poses are not used (see :func:`solve_frame_poses`), so held-out frames
    may repeat its frame names; stacking records are left out.

    Args:
        calibration: the calibration (or a calibration.json path).
        observations: an observations.json path, a Dataset, or loaded records.
        target: the target geometry (default: the Dataset's or the calibration's).

    Returns:
        The statistics: rmse_px, mae_px, max_px, count and per_camera.

    Raises:
        AriSfmError: naming the observations, when nothing is judged or a corner projects to no pixel.
    """
    fresh = replace(_as_calibration(calibration), frames={}, stacking_poses={})
    return _checked(reprojection_stats(fresh, observations, target, solve_poses=True), observations,
                    "whose pose could be fitted (4 or more corners)")

"""Reconstruct the target corners of a dataset's reconstruction frames (paper Sec. 5).

``reconstruct(dataset, calibration)`` matches each reconstruction frame's
corner ids across the cameras that saw it and triangulates every corner seen
by at least two cameras (:func:`ari_sfm.reconstruction.triangulate.triangulate_pixels`:
rays through the window, then the reprojection error through the
calibration's own model). The result, :class:`Points`, reads and writes
``points.json`` (DATASET_FORMAT.md).
"""
from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..calibration.record import Calibration
from ..errors import AriSfmError
from ..records import Dataset
from .points import FramePoints, Points  # noqa: F401 (the records: points.py; re-exported)

if TYPE_CHECKING:
    from .metrics import ReconstructionMetrics

log = logging.getLogger(__name__)

MISFIT_PX = 2.0  # median reprojection error (px) above which the calibration is suspected not to fit


def check_rig(dataset: Dataset, calibration: Calibration, calibration_path: str | Path | None = None) -> None:
    """Raise a one-line AriSfmError unless the calibration is of the dataset's rig.

    The same camera names, each with the same image size, and behind each camera the same window
    (thickness, glass index, medium index).

    Args:
        dataset: the dataset.
        calibration: the calibration.
        calibration_path: the calibration's file, named in the error (default: the dataset's rig.yaml).

    Raises:
        AriSfmError: if the calibration is from another rig.
    """
    where = calibration_path if calibration_path is not None else dataset.rig_path
    cal_names = list(calibration.cameras)
    if set(cal_names) != set(dataset.cameras):
        raise AriSfmError(where, f"calibration is from another rig: its cameras {', '.join(cal_names)} are not "
                                 f"the cameras {', '.join(dataset.cameras)} of {dataset.rig_path}")
    if not calibration.spec.window:  # a model that ignores the window (pinhole): nothing more to compare
        pass
    elif len(calibration.window_list()) != len(dataset.window_list()):
        raise AriSfmError(where, f"calibration is from another rig: {len(calibration.window_list())} window(s) there "
                                 f"but {len(dataset.window_list())} in {dataset.rig_path}")
    for name in dataset.cameras if calibration.spec.window else ():
        a, b = calibration.interface_of(name), dataset.interface_of(name)
        for what, x, y in (("thickness_mm", a.thickness_mm, b.thickness_mm), ("index", a.index, b.index),
                           ("medium_index", a.medium_index, b.medium_index)):
            if not np.isclose(x, y, rtol=1e-6, atol=1e-9):
                raise AriSfmError(where, f"calibration is from another rig: camera {name}'s window {what} {x:g} "
                                         f"there but {y:g} in {dataset.rig_path}")
        if dataset.windows and set(calibration.window_of(name).cameras) != set(dataset.window_of(name).cameras):
            raise AriSfmError(where, f"calibration is from another rig: camera {name} shares its window with other "
                                     f"cameras there than in {dataset.rig_path}")
    for name, spec in dataset.cameras.items():
        size = tuple(int(s) for s in calibration.cameras[name].image_size)
        if size != tuple(int(s) for s in spec.image_size):
            raise AriSfmError(where, f"calibration is from another rig: camera {name} has image size "
                                     f"{size[0]}x{size[1]} there but {spec.image_size[0]}x{spec.image_size[1]} "
                                     f"in {dataset.rig_path}")


def reconstruct(dataset: Dataset, calibration: Calibration, refine: bool = True,
                calibration_path: str | Path | None = None) -> Points:
    """Triangulate every corner of every reconstruction frame seen by >= 2 cameras.

    A frame seen by one camera only is skipped with a warning.

    Args:
        dataset: the dataset; it must hold observations (``calibrate.ensure_observations`` detects them).
        calibration: the calibration of the dataset's rig.
        refine: refine each point on its reprojection error (see
            :func:`~ari_sfm.reconstruction.triangulate.triangulate_pixels`).
        calibration_path: only names the calibration in error messages.

    Returns:
        The reconstructed points, per frame.

    Raises:
        AriSfmError: one line, when the dataset holds no observations or no reconstruction frame, the
            calibration is of another rig, or no frame can be triangulated.
    """
    from .triangulate import triangulate_pixels

    if dataset.observations is None:
        raise AriSfmError(dataset.rig_path, "no observations: detect corners first (calibrate.ensure_observations)")
    check_rig(dataset, calibration, calibration_path)
    records = dataset.select("reconstruction")
    if not records:
        raise AriSfmError(dataset.observations_path or dataset.rig_path,
                          "no reconstruction frames to triangulate (add a `reconstruction:` list of target "
                          "poses to rig.yaml)")
    order = list(dict.fromkeys(o.frame for o in records))
    stages = {e.key: e.stage_mm for e in dataset.reconstruction}
    cameras = list(dict.fromkeys(o.camera for o in records))
    # one big batch: (frame, id) rows x cameras
    rows: list[tuple[str, np.ndarray, np.ndarray]] = []  # (frame, ids, pixels (N, C, 2))
    skipped: list[str] = []
    for frame in order:
        recs = [o for o in records if o.frame == frame]
        ids = np.unique(np.concatenate([o.ids for o in recs]))
        uv = np.full((len(ids), len(cameras), 2), np.nan)
        for o in recs:
            uv[np.searchsorted(ids, o.ids), cameras.index(o.camera)] = o.pixels
        seen = np.isfinite(uv).all(axis=2).sum(axis=1)
        if not (seen >= 2).any():
            who = sorted({o.camera for o in recs})
            skipped.append(f"{frame} (seen by {', '.join(who)} only)" if len(who) == 1
                           else f"{frame} (no corner seen by two of {', '.join(who)})")
            continue
        if (seen < 2).any():
            log.info("frame %s: %d of %d corners seen by one camera only are not triangulated",
                     frame, int((seen < 2).sum()), len(ids))
        rows.append((frame, ids[seen >= 2], uv[seen >= 2]))
        stage = stages.get(frame)
        if stage is None:
            stage = next((o.stage_mm for o in recs if o.stage_mm is not None), None)
        stages[frame] = stage
    where = dataset.observations_path or dataset.rig_path
    if not rows:
        raise AriSfmError(where, "no reconstruction frame can be triangulated (each needs corners seen by two "
                                 f"cameras): {'; '.join(skipped)}")
    for s in skipped:
        log.warning("reconstruction frame %s: skipped, it needs corners seen by two cameras", s)
    uv = np.concatenate([r[2] for r in rows])
    X, gap, rmse = triangulate_pixels(calibration, {c: uv[:, k] for k, c in enumerate(cameras)}, refine=refine)
    bad = ~np.isfinite(X).all(axis=1)
    if bad.any():
        log.warning("%d corners could not be triangulated (parallel rays or outside the model's domain)",
                    int(bad.sum()))
    median_rmse = float(np.nanmedian(rmse)) if np.isfinite(rmse).any() else float("nan")
    if median_rmse > MISFIT_PX:
        log.warning("median reprojection error of the triangulated corners is %.2f px: is the calibration of "
                    "this rig (and of its present state)?", median_rmse)
    frames: dict[str, FramePoints] = {}
    start = 0
    for frame, ids, fuv in rows:
        sl = slice(start, start + len(ids))
        start += len(ids)
        ok = ~bad[sl]
        ncam = np.isfinite(fuv).all(axis=2).sum(axis=1)
        r = rmse[sl][ok]
        frame_rmse = float(np.sqrt(np.sum(r**2 * ncam[ok]) / np.sum(ncam[ok]))) if ok.any() else None
        frames[frame] = FramePoints(stages[frame], ids[ok].astype(int), X[sl][ok], gap[sl][ok], frame_rmse, ncam[ok])
    points = Points(frames)
    log.info("reconstructed %d corners in %d frames (%d skipped)", points.num_points, len(frames), len(skipped))
    return points


METRICS_FORMAT = "ari-sfm-reconstruction-metrics/1"


@dataclass(frozen=True)
class ReconstructionRun:
    """What :func:`run_reconstruction` wrote."""

    points: Points
    metrics: ReconstructionMetrics  # ari_sfm.reconstruction.metrics, imported when needed (it imports open3d lazily)
    points_path: Path
    metrics_path: Path
    clouds: dict[str, Path]
    observations_path: Path | None  # written when corners were detected here


def check_same_capture(dataset: Dataset, calibration: Calibration, where: str | Path | None = None) -> None:
    """Check that the dataset's corners are the ones the calibration was made from.

    Catches a byte-identical rig.yaml of another capture (:func:`ari_sfm.provenance.observations_mismatch`).
    For ``report`` and ``export-colmap``, which show or export the calibration's frames with these corners;
    ``reconstruct`` may triangulate another capture of a calibrated rig. A dataset without observations
    passes.

    Args:
        dataset: the dataset.
        calibration: the calibration.
        where: the file named in the error (default: the dataset's folder).

    Raises:
        AriSfmError: if the corners are not the calibration's.
    """
    from ..provenance import observations_mismatch

    if dataset.observations is None:
        return
    why = observations_mismatch(calibration, dataset.observations, dataset.target)
    if why:
        raise AriSfmError(where or dataset.root, why)


def check_truth_matches(dataset: Dataset, truth_path: str | Path) -> None:
    """Check that a simulator's truth.json is this dataset's.

    ``run`` calls this before calibrating, so the truth of another dataset leaves no calibration.json behind.

    Args:
        dataset: the dataset.
        truth_path: the truth.json.

    Raises:
        AriSfmError: if the truth does not hold a reconstruction frame (from rig.yaml, or observed) or an
            observed corner id, or is not a valid truth file.
    """
    from .metrics import check_truth

    recon, where = check_truth(truth_path)
    frames = [e.key for e in dataset.reconstruction]
    observed = dataset.select("reconstruction") if dataset.observations is not None else []
    frames += [o.frame for o in observed if o.frame not in frames]
    missing = [f for f in frames if f not in recon]
    if missing:
        raise AriSfmError(where, f"not the truth of {dataset.rig_path}: its reconstruction frame "
                                 f"{missing[0]} is not in the truth (frames: {', '.join(map(str, recon)) or 'none'})")
    for o in observed:
        ids = recon[o.frame].get("ids") if isinstance(recon[o.frame], Mapping) else None
        known = {int(i) for i in ids} if isinstance(ids, list) else set()
        extra = [int(i) for i in o.ids if int(i) not in known]
        if extra:
            raise AriSfmError(where, f"not the truth of {dataset.rig_path}: corner id {extra[0]} of frame {o.frame} "
                                     "is not in the truth")


def run_reconstruction(dataset_path: str | Path, calibration_path: str | Path, out_dir: str | Path,
                       truth_path: str | Path | None = None, workers: int | None = None,
                       progress: bool = False, observations: str | Path | None = None,
                       reference_path: str | Path | None = None, dataset: Dataset | None = None,
                       calibration: Calibration | None = None) -> ReconstructionRun:
    """Load, detect corners if needed, reconstruct, measure; then write OUT/points.json, metrics.json, clouds/.

    Everything is checked and computed before the first file is written, so a
    bad input (another rig's calibration, a truth without a frame, no frame
    seen by two cameras) leaves OUT without points.json.

    Args:
        dataset_path: the dataset's rig.yaml (or its folder).
        calibration_path: the calibration.json.
        out_dir: the output folder OUT (created if missing).
        truth_path: a simulator's truth.json, for the errors against the truth; None for none.
        workers: the parallel workers of the corner detection (None: its default).
        progress: show the detection's progress.
        observations: replaces the dataset's observations file (e.g. corners detected earlier).
        reference_path: a mesh or point cloud of the true geometry; metrics.json then holds ``reference``,
            the 3D error after registration onto it (:func:`ari_sfm.reconstruction.reference.reference_errors`).
        dataset: the records already loaded from ``dataset_path`` (with ``observations``), not read again.
        calibration: the records already loaded from ``calibration_path``, not read again.

    Returns:
        What was written: the points, the metrics, their paths, the clouds and the observations file (when
        corners were detected here).

    Raises:
        AriSfmError: one line, on a bad input (see above).
    """
    from ..detection import ensure_observations
    from ..io import load_calibration, load_dataset, save_observations, write_json_atomic
    from ..provenance import provenance
    from .metrics import reconstruction_metrics, save_point_clouds

    dataset = load_dataset(dataset_path, observations) if dataset is None else dataset
    calibration = load_calibration(calibration_path) if calibration is None else calibration
    check_rig(dataset, calibration, calibration_path)  # before a slow detection
    if truth_path is not None:
        check_truth_matches(dataset, truth_path)
    if reference_path is not None:
        from .reference import load_reference

        load_reference(reference_path)  # a bad reference fails before the work, not after
    if dataset.observations is None and not dataset.reconstruction:
        raise AriSfmError(dataset.rig_path, "no reconstruction frames to triangulate (add a `reconstruction:` "
                                            "list of target poses to rig.yaml)")
    detected = dataset.observations is None
    dataset = ensure_observations(dataset, workers, progress)
    points = reconstruct(dataset, calibration, calibration_path=calibration_path)
    metrics = reconstruction_metrics(points, dataset.target, truth_path)
    if reference_path is not None:
        from .reference import reference_errors

        metrics = replace(metrics, reference=reference_errors(points, reference_path))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    obs_path = None
    if detected and dataset.observations is not None:  # detect wrote them into the dataset
        obs_path = out / "observations.json"
        save_observations(obs_path, dataset.observations)
    points_path = out / "points.json"
    name = os.path.relpath(Path(calibration_path).resolve(), out.resolve())
    made_by = provenance(calibration_path, calibration.model, dataset)
    points.save(points_path, name, made_by)
    metrics_path = out / "metrics.json"
    write_json_atomic(metrics_path, {"format": METRICS_FORMAT, "dataset": str(Path(dataset_path).resolve()),
                                     "calibration": name, "model": calibration.model, "provenance": made_by,
                                     **metrics.to_json()})
    clouds = save_point_clouds(points, out / "clouds")
    return ReconstructionRun(points, metrics, points_path, metrics_path, clouds, obs_path)

"""``ari-sfm particles``: every frame of a particle experiment matched and triangulated.

Writes ``OUT/particles3d.parquet`` (DATASET_FORMAT.md 1.2: frame, x, y, z,
ray_gap_mm, cameras, row_<camera>) and ``OUT/particles3d.json`` (counts per
frame, matched fraction, mean ray gap, tolerance, time), through partitions
(:mod:`ari_sfm.particles.engine`) so a long run resumes.
"""
from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.calibration.record import Calibration
from ari_sfm.errors import AriSfmError
from ari_sfm.io import calibration_to_json, load_calibration, parse_calibration, write_json_atomic
from ari_sfm.io.particles import ParticleDataset, load_particle_dataset, read_detections
from ari_sfm.particles.engine import (
    Partition,
    check_run_settings,
    check_workers,
    dask_client,
    merge_partitions,
    run_partitions,
    split_frames,
)
from ari_sfm.particles.match import match_frame
from ari_sfm.particles.volume import Volume

log = logging.getLogger(__name__)

SUMMARY_FORMAT = "ari-sfm-particles3d/1"


@dataclass(frozen=True)
class FrameSummary:
    """One frame of :class:`ParticlesSummary`."""

    particles: int
    detections: Mapping[str, int]  # particle images per camera
    matched_fraction: float  # of its particle images, the share in a reconstructed particle

    def to_json(self) -> dict[str, Any]:
        return {"particles": self.particles, "detections": dict(self.detections),
                "matched_fraction": self.matched_fraction}


@dataclass(frozen=True)
class ParticlesSummary:
    """What :func:`reconstruct_particles` did and found; ``to_json()`` is particles3d.json."""

    dataset: str
    calibration: str
    detections: str
    tolerance_px: float
    min_cameras: int
    volume: Mapping[str, Any]  # {"min_mm", "max_mm"} or {"depth_range_mm"}
    particles: int
    cameras_per_particle: Mapping[str, int]  # number of cameras -> particles
    matched_fraction: float
    mean_ray_gap_mm: float | None  # None without particles
    time_s: float
    particles_per_second: float | None
    workers: int | None  # None with a scheduler
    scheduler: str | None
    partitions_total: int
    partitions_skipped: tuple[str, ...]  # resumed from an earlier run
    frames: Mapping[str, FrameSummary] = field(default_factory=dict)
    detections_total: int = 0  # particle images in the table (rows repeating another exactly counted once)
    detections_used: int = 0  # of them, those a reconstructed particle uses (matched_fraction = used / total)
    matched_fraction_per_camera: Mapping[str, float] = field(default_factory=dict)
    repeated_rows: int = 0  # table rows equal to an earlier row (frame, camera, u, v): left out
    warnings: tuple[str, ...] = ()  # e.g. a matched fraction too low for the calibration to fit the images

    def to_json(self) -> dict[str, Any]:
        return {"format": SUMMARY_FORMAT, "dataset": self.dataset, "calibration": self.calibration,
                "detections": self.detections, "tolerance_px": self.tolerance_px, "min_cameras": self.min_cameras,
                "volume": dict(self.volume), "particles": self.particles,
                "cameras_per_particle": dict(self.cameras_per_particle), "matched_fraction": self.matched_fraction,
                "mean_ray_gap_mm": self.mean_ray_gap_mm, "time_s": self.time_s,
                "particles_per_second": self.particles_per_second, "workers": self.workers,
                "scheduler": self.scheduler,
                "partitions": {"total": self.partitions_total, "skipped": list(self.partitions_skipped)},
                "detections_total": self.detections_total, "detections_used": self.detections_used,
                "matched_fraction_per_camera": dict(self.matched_fraction_per_camera),
                "repeated_rows": self.repeated_rows, "warnings": list(self.warnings),
                "frames": {f: m.to_json() for f, m in self.frames.items()}}


@dataclass(frozen=True)
class MatchOptions:
    """How frames are matched."""

    tolerance_px: float = 0.5  # distance of a candidate from the refracted epipolar curve; of each ray from the point
    min_cameras: int = 3  # images per particle
    depth_range_mm: tuple[float, float] | None = None  # world z slab, instead of rig.yaml volume_mm
    frames_per_partition: int = 50  # one task and one parts/ file per this many frames


def _sha256(path: Path) -> str:
    """A file's content hash (a resumed run must use the same calibration and detections)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def load_experiment(dataset_path: str | Path, calibration_path: Path, out: Path) -> tuple[ParticleDataset, Calibration]:
    """Load a particle dataset and the calibration of its rig, for a command writing to ``out``.

    A calibration that failed its quality gate is loaded with a warning (:func:`failed_gate_warning`).

    Args:
        dataset_path: The particle dataset (its folder or rig.yaml).
        calibration_path: The calibration.json.
        out: The output folder; it must not be the dataset's own folder.

    Returns:
        (the dataset, the calibration).

    Raises:
        AriSfmError: ``out`` is the dataset folder, or the calibration is not of the dataset's rig or has no
            rays through the window (:func:`check_calibration_fits`).
    """
    dataset = load_particle_dataset(dataset_path)
    if Path(os.path.realpath(out)) == Path(os.path.realpath(dataset.root)):
        raise AriSfmError(out, "-o/--out is the dataset folder: write the results elsewhere")
    calibration = load_calibration(calibration_path)
    check_calibration_fits(calibration, dataset, calibration_path)
    failed = failed_gate_warning(calibration, calibration_path)
    if failed:
        log.warning(failed)
    return dataset, calibration


def failed_gate_warning(calibration: Calibration, path: Path) -> str | None:
    """The warning for a calibration that failed its quality gate when it was made.

    Such a calibration (``quality.ok`` false: a wrong minimum, window or lens model) gives particles, and
    self-calibrations, that look as right as a good one's.

    Args:
        calibration: The calibration.
        path: Its file, named in the warning.

    Returns:
        The warning, or None if the calibration has no quality record or passed its gate.
    """
    q = calibration.quality
    if q is None or q.ok:
        return None
    return (f"{path}: this calibration failed its quality gate when it was made ({q.why or 'see its report'}): "
            "what is computed from it cannot be trusted: calibrate again")


def check_calibration_fits(calibration: Calibration, dataset: ParticleDataset, path: Path) -> None:
    """Check that the calibration is of the dataset's rig and can match particles.

    Args:
        calibration: The calibration.
        dataset: The particle dataset.
        path: The calibration's file, named in errors.

    Raises:
        AriSfmError: Other camera names or image sizes than the dataset's, or a model without rays through
            the window.
    """
    if set(calibration.cameras) != set(dataset.cameras):
        raise AriSfmError(path, f"a calibration of another rig: cameras {', '.join(calibration.cameras)}, "
                                f"the dataset's are {', '.join(dataset.cameras)}")
    for name, spec in dataset.cameras.items():
        if tuple(calibration.cameras[name].image_size) != tuple(spec.image_size):
            raise AriSfmError(path, f"a calibration of another rig: {name} has image size "
                                    f"{list(calibration.cameras[name].image_size)}, the dataset's "
                                    f"{list(spec.image_size)}")
    if not (calibration.spec.rays and calibration.spec.window):
        what = "ignores the window (a plain camera)" if calibration.spec.rays else "has no rays through the window"
        raise AriSfmError(path, f"model {calibration.model} {what}: particles need a model with rays through the "
                                "window (exact, ari, rt)")


def volume_for(dataset: ParticleDataset, calibration: Calibration, depth_range_mm: tuple[float, float] | None
               ) -> Volume:
    """The measured volume in the calibration's world.

    Args:
        dataset: The particle dataset (rig.yaml's ``particles.volume_mm``, in a camera's frame or a
            calibration frame's target coordinates).
        calibration: The calibration.
        depth_range_mm: ``--depth-range`` (world z, mm); when given it is used instead of rig.yaml's volume.

    Returns:
        The volume.

    Raises:
        AriSfmError: No volume is given, or its frame is neither a camera nor a calibration frame.
    """
    if depth_range_mm is not None:
        return Volume.depth_range(*depth_range_mm)
    if dataset.volume is None:
        raise AriSfmError(dataset.rig_path, "particles.volume_mm is not given: declare the measured volume there "
                                            "or pass --depth-range ZMIN ZMAX (mm, world z)")
    v = dataset.volume
    if v.frame in calibration.cameras:
        return Volume(v.min_mm, v.max_mm, calibration.cameras[v.frame].cam_from_world)
    if v.frame in calibration.frames:  # a calibration frame: the box in its target coordinates
        return Volume(v.min_mm, v.max_mm, calibration.frames[v.frame].inverse())
    known = ", ".join(list(calibration.cameras) + list(calibration.frames)[:5])
    raise AriSfmError(dataset.rig_path, f"particles.volume_mm.frame: '{v.frame}' is neither a camera nor a calibration "
                                        f"frame of the calibration ({known})")


def match_partition(calibration_json: dict, volume: Volume, tolerance_px: float, min_cameras: int,
                    frames: list[int], pixels: list[dict[str, np.ndarray]], rows: list[dict[str, np.ndarray]]
                    ) -> dict[str, np.ndarray]:
    """One partition's particles3d columns (a Dask task: plain arguments, no files).

    Args:
        calibration_json: The calibration as JSON (:func:`ari_sfm.io.calibration_to_json`).
        volume: The measured volume.
        tolerance_px: Matching tolerance (px), as :func:`~ari_sfm.particles.match.match_frame`.
        min_cameras: Images a particle needs.
        frames: The partition's frame numbers.
        pixels: Per frame, camera -> detections (N_c, 2) px.
        rows: Per frame, camera -> the detections' rows in the detections table.

    Returns:
        Column name -> array: frame, x, y, z, ray_gap_mm, cameras, and row_<camera> (-1: unused).
    """
    calibration = parse_calibration(calibration_json)
    cameras = list(calibration.cameras)
    cols: dict[str, list] = {k: [] for k in ("frame", "x", "y", "z", "ray_gap_mm", "cameras")}
    file_rows: list[np.ndarray] = []
    for frame, px, rw in zip(frames, pixels, rows):
        m = match_frame(calibration, px, tolerance_px, volume=volume, min_cameras=min_cameras)
        n = len(m.xyz)
        cols["frame"].append(np.full(n, frame, np.int64))
        for k, axis in enumerate("xyz"):
            cols[axis].append(m.xyz[:, k])
        cols["ray_gap_mm"].append(m.ray_gap_mm)
        cols["cameras"].append(m.num_cameras.astype(np.int64))
        g = np.full(m.rows.shape, -1, np.int64)
        for k, cam in enumerate(cameras):
            used = m.rows[:, k] >= 0
            g[used, k] = rw[cam][m.rows[used, k]]
        file_rows.append(g)
    out = {k: np.concatenate(v) if v else np.empty(0) for k, v in cols.items()}
    out["frame"] = out["frame"].astype(np.int64)
    out["cameras"] = out["cameras"].astype(np.int64)
    g = np.concatenate(file_rows) if file_rows else np.empty((0, len(cameras)), np.int64)
    for k, cam in enumerate(cameras):
        out[f"row_{cam}"] = g[:, k]
    return out


LOW_MATCHED_FRACTION = 0.2  # fewer of the particle images in a particle (all, or one camera's): the calibration
# does not fit them (a drifted rig: 0 % at 0.5 px; another experiment's detections 0.1 %, random pixels 1.5 %;
# a good calibration 84-100 % of simulated plain and tank-look images)


def reconstruct_particles(dataset_path: str | Path, calibration_path: str | Path, out: str | Path,
                          options: MatchOptions = MatchOptions(), detections_path: str | Path | None = None,
                          workers: int = 0, scheduler: str | None = None, progress: bool = False,
                          worker_timeout_s: float | None = None) -> ParticlesSummary:
    """Match and triangulate every frame; write OUT/particles3d.parquet and OUT/particles3d.json.

    Frames run in partitions (:mod:`ari_sfm.particles.engine`), so a run with the same settings resumes.

    Args:
        dataset_path: The particle dataset.
        calibration_path: The calibration.json of its rig.
        out: The output folder (OUT).
        options: How frames are matched.
        detections_path: The detections table (particles.parquet); None for the dataset's.
        workers: LocalCluster processes (0: this process).
        scheduler: An existing Dask scheduler's address, instead of ``workers``.
        progress: Show a progress bar.
        worker_timeout_s: How long a run waits with no Dask worker
            (:func:`ari_sfm.particles.engine.dask_client`).

    Returns:
        The summary (its to_json() is particles3d.json); its ``warnings`` (also logged) say when few
        particle images matched: a calibration that does not fit.

    Raises:
        AriSfmError: Bad options, a calibration that does not fit the dataset, no detections table or an
            empty one, no volume, or an output folder of a run with other settings.
    """
    t0 = time.perf_counter()
    out = Path(out)
    check_workers(workers)
    fpp = options.frames_per_partition
    if isinstance(fpp, bool) or not isinstance(fpp, int) or fpp < 1:
        raise AriSfmError("--frames-per-partition", f"must be a whole number >= 1 (got {fpp!r})")
    calibration_path = Path(calibration_path)
    dataset, calibration = load_experiment(dataset_path, calibration_path, out)
    if not 2 <= options.min_cameras <= len(calibration.cameras):
        raise AriSfmError("--min-cameras", f"must be 2..{len(calibration.cameras)} for this rig "
                                           f"(got {options.min_cameras})")
    det_path = Path(detections_path) if detections_path is not None else dataset.detections
    if det_path is None:
        raise AriSfmError(dataset.rig_path, "particles: names no detections table: run `ari-sfm detect-particles` "
                                            "and pass its particles.parquet with --detections")
    detections = read_detections(det_path, dataset.cameras)
    cameras = list(calibration.cameras)
    by_frame = detections.by_frame(cameras)
    if not by_frame:
        raise AriSfmError(det_path, "holds no particle image (0 rows): nothing to match (blank images? "
                                    "see detect-particles' summary)")
    volume = volume_for(dataset, calibration, options.depth_range_mm)
    gate = failed_gate_warning(calibration, calibration_path)
    cal_json = calibration_to_json(calibration)
    settings = {"task": "particles", "tolerance_px": options.tolerance_px, "min_cameras": options.min_cameras,
                "depth_range_mm": None if options.depth_range_mm is None else list(options.depth_range_mm),
                "frames_per_partition": fpp,
                "calibration": str(Path(os.path.abspath(calibration_path))),
                "calibration_sha256": _sha256(calibration_path),
                "detections": str(Path(os.path.abspath(det_path))),
                "detections_sha256": _sha256(det_path)}
    out.mkdir(parents=True, exist_ok=True)
    check_run_settings(out, settings)
    chunks = split_frames(by_frame, fpp)

    def partitions() -> Iterator[Partition]:  # made as submitted: the pixels of a few partitions at a time
        for chunk in chunks:
            pixels = [{c: detections.uv[by_frame[f][c]] for c in cameras} for f in chunk]
            rows = [{c: by_frame[f][c] for c in cameras} for f in chunk]
            yield Partition(chunk[0], chunk[-1], (cal_json, volume, options.tolerance_px, options.min_cameras,
                                                  chunk, pixels, rows))

    skipped = []
    from tqdm import tqdm

    with dask_client(workers, scheduler, worker_timeout_s) as client, \
            tqdm(total=len(chunks), disable=not progress, desc="matching", unit="partition") as bar:
        def done(p: Partition, was_skipped: bool) -> None:
            bar.update(1)
            if was_skipped:
                skipped.append(p.name)

        paths = run_partitions(match_partition, partitions(), out, client, done)
    tally = _Tally(cameras)
    merge_partitions(paths, out / "particles3d.parquet", tally.add)
    elapsed = time.perf_counter() - t0
    summary = _summary(tally, by_frame, cameras, options, volume, elapsed, workers, scheduler, skipped,
                       len(chunks), calibration_path, det_path, dataset,
                       0 if detections.repeated is None else int(detections.repeated.sum()), gate)
    for w in summary.warnings:
        if w != gate:  # said when the calibration was read, before the run
            log.warning(w)
    write_json_atomic(out / "particles3d.json", summary.to_json())
    log.info("%d particles in %d frames -> %s", summary.particles, len(by_frame), out)
    return summary


class _Tally:
    """What particles3d.json says of the particles, added up one partition's table at a time."""

    def __init__(self, cameras: list[str]) -> None:
        self.cameras = cameras
        self.per_frame: dict[int, tuple[int, int]] = {}  # frame -> (particles, particle images used)
        self.used_per_camera = dict.fromkeys(cameras, 0)
        self.cameras_per_particle = np.zeros(len(cameras) + 1, np.int64)
        self.gap_sum = 0.0
        self.particles = 0

    def add(self, table: Any) -> None:
        frame = table.column("frame").to_numpy().astype(np.int64)
        ncam = table.column("cameras").to_numpy().astype(np.int64)
        uniq, inverse = np.unique(frame, return_inverse=True)
        n = np.bincount(inverse, minlength=len(uniq))
        used = np.bincount(inverse, weights=ncam, minlength=len(uniq)).astype(np.int64)
        for f, k, u in zip(uniq.tolist(), n.tolist(), used.tolist()):
            old = self.per_frame.get(f, (0, 0))
            self.per_frame[f] = (old[0] + k, old[1] + u)
        for cam in self.cameras:
            self.used_per_camera[cam] += int((table.column(f"row_{cam}").to_numpy() >= 0).sum())
        self.cameras_per_particle += np.bincount(ncam, minlength=len(self.cameras) + 1)[:len(self.cameras) + 1]
        self.gap_sum += float(np.sum(table.column("ray_gap_mm").to_numpy()))
        self.particles += len(frame)


def _summary(tally: _Tally, by_frame: dict[int, dict[str, np.ndarray]], cameras: list[str],
             options: MatchOptions, volume: Volume, elapsed: float, workers: int, scheduler: str | None,
             skipped: list[str], n_partitions: int, calibration_path: Path, det_path: Path,
             dataset: ParticleDataset, repeated_rows: int, gate: str | None = None) -> ParticlesSummary:
    frames = {}
    used_total = det_total = 0
    det_per_camera = dict.fromkeys(cameras, 0)
    for f, per_cam in sorted(by_frame.items()):
        n_det = sum(len(r) for r in per_cam.values())
        n, used = tally.per_frame.get(f, (0, 0))
        frames[str(f)] = FrameSummary(n, {c: int(len(per_cam[c])) for c in cameras}, used / n_det if n_det else 0.0)
        used_total += used
        det_total += n_det
        for c in cameras:
            det_per_camera[c] += len(per_cam[c])
    fraction = used_total / det_total if det_total else 0.0
    per_camera = {c: tally.used_per_camera[c] / det_per_camera[c] for c in cameras if det_per_camera[c]}
    return ParticlesSummary(
        dataset=str(dataset.rig_path), calibration=str(calibration_path), detections=str(det_path),
        tolerance_px=options.tolerance_px, min_cameras=options.min_cameras,
        volume={"min_mm": volume.min_mm.tolist(), "max_mm": volume.max_mm.tolist()}
        if np.isfinite(volume.min_mm).all() and np.isfinite(volume.max_mm).all()
        else {"depth_range_mm": None if options.depth_range_mm is None else list(options.depth_range_mm)},
        particles=tally.particles,
        cameras_per_particle={str(k): int(v) for k, v in enumerate(tally.cameras_per_particle) if v},
        matched_fraction=fraction,
        mean_ray_gap_mm=tally.gap_sum / tally.particles if tally.particles else None,
        time_s=elapsed, particles_per_second=tally.particles / elapsed if elapsed > 0 else None,
        workers=workers if scheduler is None else None, scheduler=scheduler,
        partitions_total=n_partitions, partitions_skipped=tuple(skipped), frames=frames,
        detections_total=det_total, detections_used=used_total, matched_fraction_per_camera=per_camera,
        repeated_rows=repeated_rows,
        warnings=tuple(([gate] if gate else [])
                       + _match_warnings(fraction, per_camera, det_per_camera, det_total, dataset, calibration_path)))


def _match_warnings(fraction: float, per_camera: Mapping[str, float], det_per_camera: Mapping[str, int],
                    det_total: int, dataset: ParticleDataset, calibration_path: Path) -> list[str]:
    """What a low matched fraction means, and what to do."""
    fix = (f"run ari-sfm self-calibrate {dataset.root} --calibration {calibration_path} -o OUT and match with "
           "OUT/calibration.json (or check that the detections are this experiment's)")
    if fraction < LOW_MATCHED_FRACTION:
        return [f"only {100 * fraction:.1f} % of the {det_total} particle images (detections) were matched into "
                f"particles: the calibration does not fit these images; {fix}"]
    out = [f"{cam}: only {100 * f:.1f} % of its particle images were matched: the calibration does not fit this "
           f"camera's images (drifted?); {fix}" for cam, f in per_camera.items() if f < LOW_MATCHED_FRACTION]
    out += [f"{cam}: no particle image in the detections" for cam, n in det_per_camera.items() if n == 0]
    return out

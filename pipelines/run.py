"""Pipeline: detect corners when needed, calibrate, reconstruct when possible, write the report.

    python -m ari_sfm.pipelines.run DATASET OUT [--model ari|exact] [--truth TRUTH]

Without --model: the best model (exact refined from ari, lens distortion estimated when the views
support it: :func:`ari_sfm.calibration.calibrate.resolve_distortion`); ``--model ari``: the paper's model alone.
With a truth: the calibrated parameters' errors against it (:mod:`ari_sfm.calibration.truth_errors`, also
in run.json ``calibration_vs_truth``) and the reconstruction's 3D error (metrics.json).

OUT gets calibration.json (+ observations.json when detected here), then,
when the dataset has reconstruction frames seen by two or more cameras,
points.json, metrics.json and clouds/; then run.json (what ran, and the
dataset's absolute path, which ``ari-sfm report OUT`` reads) and report.html.
"""
from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..calibration.calibrate import DEFAULT_MODEL, CalibrationOptions
from ..calibration.truth_errors import CalibrationErrors, calibration_errors
from ..io import calibration_to_json, load_calibration, load_dataset, parse_calibration, write_json_atomic
from ..models.registry import CALIBRATABLE
from ..reconstruction.reconstruct import ReconstructionRun, run_reconstruction
from ..records import Dataset
from ..report import RUN_FILE, RUN_FORMAT, write_report
from .calibrate_rig import PipelineResult, main as calibrate_rig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunReconstruction:
    """What the run reconstructed (run.json ``reconstruction``)."""

    frames: int
    points: int

    def to_json(self) -> dict[str, Any]:
        """run.json's ``reconstruction``."""
        return {"frames": self.frames, "points": self.points}


@dataclass(frozen=True)
class RunRecord:
    """What a run did: run.json, which ``ari-sfm report OUT`` reads (its dataset)."""

    dataset: Path  # the dataset's absolute path
    observations: Path | None  # the observations calibrated, absolute (None: the dataset's own)
    model: str
    calibration: str  # calibration.json's file name, in OUT
    reconstruction: RunReconstruction | None  # None when skipped
    reconstruction_skipped: str | None  # why it was skipped
    truth: Path | None  # the truth.json given, absolute
    calibration_vs_truth: CalibrationErrors | None  # the calibration's errors against it

    def to_json(self) -> dict[str, Any]:
        """run.json."""
        return {
            "format": RUN_FORMAT,
            "dataset": str(self.dataset),
            "observations": None if self.observations is None else str(self.observations),
            "model": self.model,
            "calibration": self.calibration,
            "reconstruction": None if self.reconstruction is None else self.reconstruction.to_json(),
            "reconstruction_skipped": self.reconstruction_skipped,
            "truth": None if self.truth is None else str(self.truth),
            "calibration_vs_truth": None if self.calibration_vs_truth is None else self.calibration_vs_truth.to_json(),
        }


@dataclass(frozen=True)
class RunResult:
    """What :func:`main` ran and wrote."""

    calibrated: PipelineResult
    reconstruction: ReconstructionRun | None  # None when skipped
    skipped_reconstruction: str | None  # why it was skipped
    run_path: Path
    report_path: Path
    truth_errors: CalibrationErrors | None = None  # the calibration against --truth
    record: RunRecord | None = None  # what run_path holds


def reconstruction_frames(dataset: Dataset) -> tuple[list[str], str | None]:
    """The reconstruction frames seen by two or more cameras.

    Args:
        dataset: The dataset with its observations.

    Returns:
        (the frames, None), or ([], why there are none).
    """
    if not dataset.reconstruction:
        return [], "the dataset has no reconstruction frames"
    cams: dict[str, set[str]] = {}
    for o in dataset.select("reconstruction"):
        cams.setdefault(o.frame, set()).add(o.camera)
    frames = [f for f, c in cams.items() if len(c) >= 2]
    if not frames:
        return [], "no reconstruction frame is seen by two cameras"
    return frames, None


RECONSTRUCTION_FILES = ("points.json", "metrics.json")


def _dataset_folder(path: str | Path) -> Path:
    """The dataset folder of a folder or rig-file path, symbolic links resolved."""
    path = Path(path).resolve()
    return path.parent if path.is_file() else path


def check_run_folder(out_dir: Path, dataset_path: str | Path) -> None:
    """Refuse an output folder holding another dataset's run: a second run would leave run.json of one and
    results of the other.

    Args:
        out_dir: The output folder.
        dataset_path: The dataset folder or rig file of this run.

    Raises:
        AriSfmError: ``out_dir`` holds the run (run.json) or reconstruction (metrics.json, points.json) of
            another dataset.
    """
    from ..errors import AriSfmError
    from ..io import read_structured
    from ..provenance import recorded_dataset_path

    here = _dataset_folder(dataset_path)
    for name in (RUN_FILE, *RECONSTRUCTION_FILES):
        path = out_dir / name
        if not path.is_file():
            continue
        try:
            data = read_structured(path)
        except AriSfmError:
            continue  # unreadable: replaced by this run
        recorded = data.get("dataset") if name == RUN_FILE and isinstance(data, dict) else recorded_dataset_path(data)
        if isinstance(recorded, (str, Path)) and _dataset_folder(recorded) != here:
            raise AriSfmError(out_dir, f"-o/--out: holds the results of another dataset ({recorded}, in {name}): "
                                       "choose an empty folder")


def remove_stale_reconstruction(out_dir: Path) -> None:
    """Remove points.json, metrics.json and clouds/ of an earlier run of this dataset (this run has none).

    Args:
        out_dir: The output folder.
    """
    import shutil

    for name in RECONSTRUCTION_FILES:
        if (out_dir / name).is_file():
            log.info("removing %s of an earlier run", out_dir / name)
            (out_dir / name).unlink()
    shutil.rmtree(out_dir / "clouds", ignore_errors=True)


def remove_earlier_run(out_dir: Path) -> None:
    """Remove an earlier run's run.json, report.html and reconstruction before this run writes.

    A run that fails half-way then never leaves run.json (or a report) of the earlier run beside its own
    calibration.

    Args:
        out_dir: The output folder.
    """
    from ..report import REPORT_FILE

    for name in (RUN_FILE, REPORT_FILE):
        if (out_dir / name).is_file():
            (out_dir / name).unlink()
    remove_stale_reconstruction(out_dir)


def main(dataset_path: Path, out_dir: Path, model: str | None = None, truth: Path | None = None,
         progress: bool = False, options: CalibrationOptions | None = None) -> RunResult:
    """Calibrate, reconstruct when possible, write run.json and report.html (the module docstring).

    Args:
        dataset_path: The dataset folder or rig file.
        out_dir: The output folder (held for the run: a second command writing into it is refused).
        model: The model to calibrate; None: the best model (``DEFAULT_MODEL``).
        truth: A simulator's truth.json: the calibration's errors against it and the reconstruction's 3D error.
        progress: Progress bars.
        options: The calibration's options (None: the defaults).

    Returns:
        What ran: the calibration, the reconstruction or why it was skipped, the paths written.

    Raises:
        AriSfmError: ``out_dir`` holds another dataset's results; the truth does not match the dataset; any
            error of the calibration or the reconstruction.
    """
    from ..io import exclusive_folder

    out_dir = Path(out_dir)
    check_run_folder(out_dir, dataset_path)  # another dataset's run there: refused before any work
    dataset = load_dataset(dataset_path)  # read once; the records travel in memory
    if truth is not None:
        from ..reconstruction.reconstruct import check_truth_matches

        check_truth_matches(dataset, truth)  # before the calibration, not after it
    with exclusive_folder(out_dir):  # a second command writing into OUT meanwhile: refused, not interleaved
        check_run_folder(out_dir, dataset_path)  # again, now that OUT is held
        remove_earlier_run(out_dir)
        return _run(dataset_path, dataset, out_dir, model, truth, progress, options)


def _run(dataset_path: Path, dataset: Dataset, out_dir: Path, model: str | None, truth: Path | None, progress: bool,
         options: CalibrationOptions | None) -> RunResult:
    """:func:`main` once OUT is held."""
    model = model or DEFAULT_MODEL
    # the files written are what the records in memory hold
    calibrated = calibrate_rig(dataset_path, out_dir, model=model, progress=progress, dataset=dataset,
                               options=options)
    obs_path = calibrated.observations_path
    if calibrated.dataset is not None:  # with the observations detected
        dataset = calibrated.dataset
    frames, why = reconstruction_frames(dataset)
    quality = calibrated.calibration.quality
    if quality is not None and not quality.ok:  # stop before reconstructing with a failed calibration
        why = f"the calibration failed its quality gate: {quality.why}"
    rec = None
    if why is None:
        # the calibration as calibration.json holds it (its poses are written as JSON): the points are then
        # those `ari-sfm reconstruct` gives from that file, which the provenance names by its hash
        as_saved = parse_calibration(calibration_to_json(calibrated.calibration), calibrated.calibration_path)
        rec = run_reconstruction(dataset_path, calibrated.calibration_path, out_dir, truth, progress=progress,
                                 observations=obs_path, dataset=dataset, calibration=as_saved)
    else:
        log.info("reconstruction skipped: %s", why)
    errors = None
    if truth is not None:
        errors = calibration_errors(calibrated.calibration, load_calibration(truth))
    run_path = out_dir / RUN_FILE
    record = RunRecord(Path(dataset_path).resolve(), obs_path.resolve() if obs_path else None, model,
                       calibrated.calibration_path.name,
                       None if rec is None else RunReconstruction(len(rec.points.frames), rec.points.num_points), why,
                       Path(truth).resolve() if truth else None, errors)
    write_json_atomic(run_path, record.to_json())
    report = write_report(out_dir)
    return RunResult(calibrated, rec, why, run_path, report, errors, record)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--model", default=None, choices=CALIBRATABLE)
    ap.add_argument("--truth", type=Path, default=None)
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    r = main(a.dataset, a.out, a.model, a.truth)
    print(r.report_path)

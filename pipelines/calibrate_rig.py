"""Pipeline: detect corners when needed, calibrate, write the results.

    python -m ari_sfm.pipelines.calibrate_rig DATASET OUT [--model exact|ari]  (default exact)
"""
from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass, replace
from pathlib import Path

from ..calibration.calibrate import DEFAULT_MODEL, CalibrationOptions, calibrate
from ..calibration.record import Calibration
from ..detection import ensure_observations
from ..io import load_dataset, save_calibration, save_observations
from ..models.registry import CALIBRATABLE
from ..records import Dataset

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineResult:
    """What :func:`main` calibrated and wrote."""

    calibration: Calibration
    calibration_path: Path
    observations_path: Path | None  # written when corners were detected here
    dataset: Dataset | None = None  # the dataset calibrated, with its observations (detected or read)


def main(dataset_path: Path, out_dir: Path, model: str = DEFAULT_MODEL, progress: bool = False,
         dataset: Dataset | None = None, options: CalibrationOptions | None = None) -> PipelineResult:
    """Load, detect corners when the dataset has only images, calibrate and write calibration.json.

    Args:
        dataset_path: The dataset folder or rig file (read unless ``dataset`` is given).
        out_dir: The output folder: calibration.json, and observations.json when corners were detected here.
        model: The model to calibrate (a name of :mod:`ari_sfm.models.registry`).
        progress: Progress bars for the detection and the calibration (``options.progress`` is replaced by it).
        dataset: The dataset already loaded from ``dataset_path``, or None to load it.
        options: The calibration's options (None: the defaults).

    Returns:
        The calibration, the paths written and the dataset calibrated (with its observations).
    """
    opts = replace(options or CalibrationOptions(), progress=progress)
    dataset = load_dataset(dataset_path) if dataset is None else dataset
    detected = dataset.observations is None
    dataset = ensure_observations(dataset, opts.workers, progress)
    out_dir.mkdir(parents=True, exist_ok=True)
    obs_path = None
    if detected and dataset.observations is not None:  # detect wrote them into the dataset
        obs_path = out_dir / "observations.json"
        save_observations(obs_path, dataset.observations, dataset.rig_path if dataset.rig_path.is_file() else None)
    cal = calibrate(dataset, model=model, options=opts)
    cal_path = out_dir / "calibration.json"
    save_calibration(cal, cal_path)
    return PipelineResult(cal, cal_path, obs_path, dataset)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--model", default=DEFAULT_MODEL, choices=CALIBRATABLE)
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    r = main(a.dataset, a.out, a.model)
    print(r.calibration_path)

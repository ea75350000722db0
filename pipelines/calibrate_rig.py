"""Pipeline: detect corners when needed, calibrate, write the results.

    python -m ari_sfm.pipelines.calibrate_rig DATASET OUT [--model exact|ari]  (default exact)
"""
from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path

from ..calibrate import DEFAULT_MODEL, calibrate, ensure_observations
from ..calibration import Calibration
from ..io import load_dataset, save_observations
from ..models.registry import CALIBRATABLE

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineResult:
    calibration: Calibration
    calibration_path: Path
    observations_path: Path | None  # written when corners were detected here


def main(dataset_path: Path, out_dir: Path, model: str = DEFAULT_MODEL, progress: bool = False, **options) -> PipelineResult:
    """Load, detect (if the dataset has only images), calibrate; write calibration.json."""
    dataset = load_dataset(dataset_path)
    detected = dataset.observations is None
    dataset = ensure_observations(dataset, options.get("workers"), progress)
    out_dir.mkdir(parents=True, exist_ok=True)
    obs_path = None
    if detected:
        obs_path = out_dir / "observations.json"
        save_observations(obs_path, dataset.observations)
    cal = calibrate(dataset, model=model, progress=progress, **options)
    cal_path = out_dir / "calibration.json"
    cal.save(cal_path)
    return PipelineResult(cal, cal_path, obs_path)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--model", default=DEFAULT_MODEL, choices=CALIBRATABLE)
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    r = main(a.dataset, a.out, a.model)
    print(r.calibration_path)

"""ari-sfm: calibrate cameras behind a flat refractive window (the ARI equation).

    import ari_sfm
    dataset = ari_sfm.load_dataset("datasets/sample")
    calibration = ari_sfm.calibrate(dataset, model="ari")   # or "exact"
    calibration.save("out/calibration.json")
    ari_sfm.evaluate(ari_sfm.load_calibration("out/calibration.json"), dataset)
"""
from __future__ import annotations

import os

# GTSAM's linear algebra is faster single-threaded on the small blocks of a
# bundle adjustment; set before numpy/gtsam load OpenBLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from .calibrate import CalibrationOptions, calibrate  # noqa: E402
from .calibration import Calibration, CameraCalibration, load_calibration  # noqa: E402
from .errors import AriSfmError  # noqa: E402
from .evaluate import evaluate  # noqa: E402
from .io import load_dataset, load_observations  # noqa: E402
from .records import Dataset, Interface, Observation, Target  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "AriSfmError", "Calibration", "CalibrationOptions", "CameraCalibration", "Dataset", "Interface",
    "Observation", "Target", "calibrate", "evaluate", "load_calibration", "load_dataset", "load_observations",
]

"""ari-sfm: calibrate cameras behind a flat refractive window (the ARI equation).

    import ari_sfm
    dataset = ari_sfm.load_dataset("datasets/sample")
    calibration = ari_sfm.calibrate(dataset, model="ari")   # or "exact"
    calibration.save("out/calibration.json")
    ari_sfm.evaluate(ari_sfm.load_calibration("out/calibration.json"), dataset)
    points = ari_sfm.reconstruct(dataset, calibration)          # frames seen by >= 2 cameras
    X, gap_mm, rmse_px = ari_sfm.triangulate_pixels(calibration, {"cam0": uv0, "cam1": uv1})  # PTV tracks
"""
from __future__ import annotations

import os

# GTSAM's linear algebra is faster single-threaded on the small blocks of a
# bundle adjustment; set before numpy/gtsam load OpenBLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from .calibrate import CalibrationOptions, calibrate  # noqa: E402
from .calibration import Calibration, CameraCalibration, load_calibration  # noqa: E402
from .compare import compare  # noqa: E402
from .errors import AriSfmError  # noqa: E402
from .evaluate import evaluate  # noqa: E402
from .io import load_dataset, load_observations  # noqa: E402
from .reconstruct import Points, reconstruct  # noqa: E402
from .records import Dataset, Interface, Observation, Target  # noqa: E402
from .triangulate import triangulate_pixels  # noqa: E402

__version__ = "0.1.0"


def __getattr__(name: str):
    """``ari_sfm.refine_colmap`` without importing pycolmap at package import."""
    if name == "refine_colmap":
        from .colmap_refine import refine_colmap

        return refine_colmap
    raise AttributeError(f"module 'ari_sfm' has no attribute {name!r}")


__all__ = [
    "AriSfmError", "Calibration", "CalibrationOptions", "CameraCalibration", "Dataset", "Interface",
    "Observation", "Points", "Target", "calibrate", "compare", "evaluate", "load_calibration", "load_dataset",
    "load_observations", "reconstruct", "refine_colmap", "triangulate_pixels",
]

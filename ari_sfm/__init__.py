"""ari-sfm: calibrate cameras behind a flat refractive window (the ARI equation).

    import ari_sfm
    dataset = ari_sfm.load_dataset("datasets/sample")
    calibration = ari_sfm.calibrate(dataset, model="ari")   # or "exact"
    ari_sfm.save_calibration(calibration, "out/calibration.json")
    ari_sfm.evaluate(ari_sfm.load_calibration("out/calibration.json"), dataset)
    points = ari_sfm.reconstruct(dataset, calibration)          # frames seen by >= 2 cameras
    X, gap_mm, rmse_px = ari_sfm.triangulate_pixels(calibration, {"cam0": uv0, "cam1": uv1})  # PTV tracks

COLMAP behind glass: ``ari_sfm.refine_colmap`` (README, COLMAP users).
The factor graph (researchers, docs/RESEARCH.md): ``ari_sfm.RigGraph``, ``ari_sfm.RigState``,
``ari_sfm.keys`` (variable keys), ``ari_sfm.marginal_covariances``; loaded on first use (gtsam).
"""
from __future__ import annotations

import os

# GTSAM's linear algebra is faster single-threaded on the small blocks of a
# bundle adjustment; set before numpy/gtsam load OpenBLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from . import _startup  # noqa: E402

_startup.guard_loading()  # Ctrl-C while `ari-sfm` loads: "interrupted", exit 130 (no traceback)

from .calibration.calibrate import CalibrationOptions, calibrate  # noqa: E402
from .calibration.compare import compare  # noqa: E402
from .calibration.evaluate import evaluate  # noqa: E402
from .calibration.record import Calibration, CameraCalibration  # noqa: E402
from .errors import AriSfmError  # noqa: E402
from .io import load_calibration, load_dataset, load_observations, save_calibration  # noqa: E402
from .reconstruction.reconstruct import Points, reconstruct  # noqa: E402
from .reconstruction.triangulate import triangulate_pixels  # noqa: E402
from .records import Dataset, Interface, Observation, Target  # noqa: E402

__version__ = "0.1.0"

_LAZY_EXPORTS = {  # name -> module: imported on first use, so that `import ari_sfm` loads neither gtsam nor pycolmap
    "RigGraph": "ari_sfm.factors.rig_graph",
    "RigState": "ari_sfm.factors.rig_graph",
    "keys": "ari_sfm.factors.keys",
    "marginal_covariances": "ari_sfm.factors.uncertainty",
    "refine_colmap": "ari_sfm.colmap.refine",
}


def __getattr__(name: str):
    module = _LAZY_EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'ari_sfm' has no attribute {name!r}")
    import importlib

    mod = importlib.import_module(module)
    return mod if name == "keys" else getattr(mod, name)


__all__ = [
    "AriSfmError", "Calibration", "CalibrationOptions", "CameraCalibration", "Dataset", "Interface",
    "Observation", "Points", "Target", "calibrate", "compare", "evaluate", "load_calibration", "load_dataset",
    "load_observations", "reconstruct", "refine_colmap", "save_calibration", "triangulate_pixels", "RigGraph",
    "RigState", "keys",
    "marginal_covariances",
]

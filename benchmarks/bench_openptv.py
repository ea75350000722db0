"""OpenPTV export: how closely liboptv's formulas reproduce ari-sfm's exact projection.

    python benchmarks/bench_openptv.py

For the simulated two-camera rigs of tests/test_openptv.py (water or air behind a
6 mm window, with or without distortion, principal point centred or not) the
calibration is exported with :func:`ari_sfm.openptv.export_openptv`, the 73-point
test_cavity body is projected through the exported files with the tests'
transcription of liboptv's ``img_coord`` (converged, and with liboptv's own
stopping rule |rdiff| <= 0.001 mm, at most 40 iterations) and compared with
``Calibration.project_world``. Prints the largest pixel differences, the fit
error of an off-centre distortion, and the export time.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import numpy as np  # noqa: E402
import test_openptv as T  # noqa: E402

from ari_sfm.io import save_calibration
from ari_sfm.openptv import export_openptv  # noqa: E402

CASES = (
    ("water, no distortion, pp off-centre", (0,) * 5, False, 1.333),
    ("water, distortion, pp centred", (-0.08, 0.12, 3e-4, -2e-4, 0.01), True, 1.333),
    ("air, no distortion", (0,) * 5, False, 1.0),
    ("water, distortion, pp off-centre (fitted)", (-0.08, 0.12, 3e-4, -2e-4, 0.0), False, 1.333),
)


def main() -> None:
    _, body = T._body()
    print(f"{'case':44s} {'camera':6s} {'converged px':>13s} {'liboptv tol px':>15s} {'fit px':>8s} {'export ms':>10s}")
    for label, dist0, centred, medium in CASES:
        folder = Path(tempfile.mkdtemp())
        cal = T.simulated_calibration(dist0, centred=centred, medium=medium,
                                      distance=None if medium == 1.0 else 300.0)
        save_calibration(cal, folder / "calibration.json")
        start = time.perf_counter()
        summary = export_openptv(folder / "calibration.json", folder / "optv")
        elapsed_ms = 1e3 * (time.perf_counter() - start)
        X_world = cal.frames["f000"].apply(body)
        for number, name in enumerate(cal.cameras, start=1):
            cam = T.read_liboptv_camera(folder / "optv" / "cal" / f"cam{number}.tif.ori",
                                        folder / "optv" / "parameters" / "ptv.par")
            ours = cal.project_world(name, X_world)
            converged = np.abs(ours - T.liboptv_pixels(body, cam) - T.OPENCV_FROM_OPENPTV_PX).max()
            liboptv = np.abs(ours - T.liboptv_pixels(body, cam, tol=1e-3, n_iter=40) - T.OPENCV_FROM_OPENPTV_PX).max()
            fit = summary.fit_error_px.get(name)
            print(f"{label:44s} {name:6s} {converged:13.2e} {liboptv:15.2e} "
                  f"{'-' if fit is None else format(fit, '.3f'):>8s} {elapsed_ms:10.1f}")


if __name__ == "__main__":
    main()

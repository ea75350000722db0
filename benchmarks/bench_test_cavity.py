"""OpenPTV's test_cavity calibrated from what the lab has on disk, side by side with OpenPTV's own calibration.

    python benchmarks/bench_test_cavity.py [EXPERIMENT]   (default /work/shared/real/test_cavity)

A measurement, not a test. The experiment is copied without what OpenPTV made of it (``cal/*.ori``,
``*.addpar``, ``*.tif_targets``, ``*.crd``) and run as a user would: ``ari-sfm import openptv COPY -o DS``
(ptv.par, cal_ori.par's body and calibration images, man_ori's 4 clicked points per camera: the windows
told from the cameras' viewing directions) and ``ari-sfm calibrate DS -o CAL`` (the body's dots found and
identified in the images, then the exact model with one normal and distance per window, no focal length
hint). Then OpenPTV's own ``.ori`` / ``.addpar`` are read with liboptv (``pip install optv``, the ``bench``
extra) and reprojected on the SAME identified points (:func:`validate_body_test_cavity.openptv_pixels`).

Prints per camera: the identified points, ari-sfm's RMS and OpenPTV's RMS on them; the quality gate's
verdict; and each window against OpenPTV's glass vector in the body's frame (OpenPTV's world): the angle
between the normals, the glass-water face's distance from the body's origin, and ari-sfm's sigmas.
test_cavity's ptv.par writes n2 (glass) 1.33 and n3 (water) 1.46 (the two look swapped); both
calibrations use them as written.
"""
from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from validate_body_test_cavity import openptv_pixels, raw_copy  # noqa: E402


def main(experiment: Path) -> None:
    from click.testing import CliRunner

    from ari_sfm.cli import main as cli
    from ari_sfm.geometry import angle_between_deg
    from ari_sfm.io import load_calibration
    from ari_sfm.openptv.conventions import window_plane
    from ari_sfm.openptv.files import read_control_par, read_ori

    with tempfile.TemporaryDirectory() as tmp:
        copy = raw_copy(experiment, Path(tmp))
        for command in (["import", "openptv", str(copy), "-o", str(Path(tmp) / "ds")],
                        ["calibrate", str(Path(tmp) / "ds"), "-o", str(Path(tmp) / "cal")]):
            t0 = time.perf_counter()
            result = CliRunner().invoke(cli, command)
            if result.exit_code not in (0, 3):
                sys.exit(result.output)
            print(f"ari-sfm {' '.join(command[:2])}: {time.perf_counter() - t0:.1f} s (exit {result.exit_code})")
        cal = load_calibration(Path(tmp) / "cal" / "calibration.json")
        records = json.loads((Path(tmp) / "cal" / "observations.json").read_text())["observations"]

    body = np.loadtxt(experiment / "cal" / "target_on_a_side.txt")
    ids, xyz = body[:, 0].astype(int), body[:, 1:]
    theirs = openptv_pixels(experiment, len(cal.cameras), xyz)
    frame = cal.frames["f000"]  # world_from_body
    print(f"\n{'camera':8}{'points':>8}{'ari-sfm RMS px':>16}{'OpenPTV RMS px':>16}")
    ours_sq, their_sq = [], []
    for record in records:
        name, found, pixels = record["camera"], np.array(record["ids"]), np.array(record["pixels"])
        k = int(name[3:]) - 1
        mine = cal.project_world(name, frame.apply(xyz[np.searchsorted(ids, found)])) - pixels
        other = theirs[k][np.searchsorted(ids, found)] - pixels
        ours_sq += list(np.sum(mine ** 2, axis=1))
        their_sq += list(np.sum(other ** 2, axis=1))
        print(f"{name:8}{len(found):>8}{np.sqrt(np.mean(np.sum(mine ** 2, 1))):>16.3f}"
              f"{np.sqrt(np.mean(np.sum(other ** 2, 1))):>16.3f}")
    print(f"{'all':8}{len(ours_sq):>8}{np.sqrt(np.mean(ours_sq)):>16.3f}{np.sqrt(np.mean(their_sq)):>16.3f}")
    q = cal.quality
    print(f"\nquality: {'ok' if q.ok else 'FAILED'} (robust RMSE {q.robust_rmse_px:.3f} px, floor "
          f"{q.floor_rmse_px if q.floor_rmse_px is None else round(q.floor_rmse_px, 3)} "
          f"px){'' if q.ok else ': ' + q.why}")
    control = read_control_par(experiment / "parameters" / "ptv.par")
    print(f"\n{'window':10}{'cameras':>12}{'normal vs OpenPTV deg':>23}{'sigma deg':>11}"
          f"{'glass-water face mm':>21}{'OpenPTV mm':>12}{'sigma mm':>10}")
    for w in cal.window_list():
        n_body = frame.R.T @ w.normal_world
        first = int(w.cameras[0][3:])
        glass = read_ori(experiment / "cal" / f"cam{first}.tif.ori").glass
        n_ptv, point = window_plane(glass, control.d)
        plane = w.plane_mm(cal)  # near face: n_w . X = plane (world)
        face = -(plane - w.normal_world @ frame.t + w.interface.thickness_mm)  # water face's distance from the origin
        sigma = cal.uncertainty.windows.get(w.name) if cal.uncertainty is not None and cal.uncertainty.windows else None
        print(f"{w.name:10}{','.join(w.cameras):>12}{angle_between_deg(n_body, n_ptv):>23.2f}"
              f"{'' if sigma is None else f'{sigma.normal_deg:.2f}':>11}{face:>21.1f}{np.linalg.norm(glass):>12.1f}"
              f"{'' if sigma is None or sigma.distance_mm is None else f'{sigma.distance_mm:.1f}':>10}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("/work/shared/real/test_cavity"))

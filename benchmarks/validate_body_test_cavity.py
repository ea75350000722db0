"""The 3D body of OpenPTV's test_cavity identified from its images and clicks, checked against OpenPTV's own
calibration.

    python benchmarks/validate_body_test_cavity.py [EXPERIMENT]   (default /work/shared/real/test_cavity)

A measurement, not a test: the experiment is copied without what OpenPTV made of it (``cal/*.ori``,
``*.addpar``, ``*.tif_targets``, ``*.crd``), imported (``ari-sfm import openptv``: ptv.par, cal_ori.par, the
body file, the four calibration images, man_ori.dat / man_ori.par) and its images detected (``ari-sfm
detect``: the dots found and identified from the 4 clicked points per camera). Only then are OpenPTV's
files read, with liboptv (``pip install optv``, the ``bench`` extra): the body projected by each camera's
``.ori`` / ``.addpar`` with ptv.par's multimedia parameters (``optv.imgcoord.image_coordinates``,
``optv.transforms.convert_arr_metric_to_pixel``, minus 0.5 for OpenCV pixels).

Per camera it prints: the points identified, how many lie within 3 px of OpenPTV's projection of their id,
the wrong ids (an identified dot nearer another point's OpenPTV projection than its own), the median and
largest distance; beside it, OpenPTV's own identified points (its detector's targets within 3 px of its
own projection of a body point) and their RMS.
"""
from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

AGREE_PX = 3.0


def openptv_pixels(root: Path, num_cams: int, xyz: np.ndarray) -> list[np.ndarray]:
    """Each camera's OpenCV pixels (N, 2) of the body by OpenPTV's own calibration (liboptv)."""
    from optv.calibration import Calibration
    from optv.imgcoord import image_coordinates
    from optv.parameters import ControlParams
    from optv.transforms import convert_arr_metric_to_pixel

    control = ControlParams(num_cams)
    control.read_control_par(str(root / "parameters" / "ptv.par"))
    out = []
    for k in range(1, num_cams + 1):
        cal = Calibration()
        cal.from_file(str(root / "cal" / f"cam{k}.tif.ori").encode(), str(root / "cal" / f"cam{k}.tif.addpar").encode())
        metric = image_coordinates(np.ascontiguousarray(xyz), cal, control.get_multimedia_params())
        out.append(convert_arr_metric_to_pixel(metric, control) - 0.5)
    return out


def raw_copy(experiment: Path, folder: Path) -> Path:
    """``experiment`` copied into ``folder`` as a lab has it before calibrating: without OpenPTV's results
    (.ori, .addpar, the targets and .crd files of its own detection)."""
    copy = folder / "experiment"
    shutil.copytree(experiment, copy)
    for pattern in ("*.ori", "*.addpar", "*.tif_targets", "*.crd"):
        for path in (copy / "cal").glob(pattern):
            path.unlink()
    return copy


def main(experiment: Path) -> None:
    from click.testing import CliRunner

    from ari_sfm.cli import main as cli

    with tempfile.TemporaryDirectory() as tmp:
        copy = raw_copy(experiment, Path(tmp))
        for command in (["import", "openptv", str(copy), "-o", str(Path(tmp) / "ds")],
                        ["detect", str(Path(tmp) / "ds"), "-o", str(Path(tmp) / "det"), "--workers", "1"]):
            t0 = time.perf_counter()
            result = CliRunner().invoke(cli, command)
            if result.exit_code:
                sys.exit(result.output)
            print(f"ari-sfm {' '.join(command[:2])}: {time.perf_counter() - t0:.1f} s")
        records = json.loads((Path(tmp) / "det" / "observations.json").read_text())["observations"]

    body = np.loadtxt(experiment / "cal" / "target_on_a_side.txt")
    ids, xyz = body[:, 0].astype(int), body[:, 1:]
    projected = openptv_pixels(experiment, len(records), xyz)
    print(f"\n{'camera':8}{'identified':>11}{'within 3 px':>12}{'wrong ids':>10}{'median px':>10}{'max px':>8}"
          f"{'OpenPTV':>9}{'its RMS px':>11}")
    total = agree = wrong = theirs = 0
    their_sq = []
    for k, (record, uv) in enumerate(zip(records, projected), start=1):
        found, pixels = np.array(record["ids"]), np.array(record["pixels"])
        d = np.linalg.norm(uv[np.searchsorted(ids, found)] - pixels, axis=1)
        nearest = ids[np.argmin(np.linalg.norm(uv[None] - pixels[:, None], axis=2), axis=1)]
        targets = np.loadtxt(experiment / "cal" / f"cam{k}.tif_targets", skiprows=1)[:, 1:3] - 0.5
        to_target = np.linalg.norm(uv[:, None] - targets[None], axis=2).min(axis=1)
        own = to_target[to_target <= AGREE_PX]
        their_sq += list(own ** 2)
        print(f"{record['camera']:8}{len(found):>11}{int(np.sum(d <= AGREE_PX)):>12}{int(np.sum(nearest != found)):>10}"
              f"{np.median(d):>10.2f}{d.max():>8.2f}{len(own):>9}{np.sqrt(np.mean(own ** 2)):>11.2f}")
        total, agree, wrong, theirs = (total + len(found), agree + int(np.sum(d <= AGREE_PX)),
                                       wrong + int(np.sum(nearest != found)), theirs + len(own))
    print(f"{'all':8}{total:>11}{agree:>12}{wrong:>10}{'':>18}{theirs:>9}{np.sqrt(np.mean(their_sq)):>11.2f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("/work/shared/real/test_cavity"))

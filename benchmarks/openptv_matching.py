"""OpenPTV's correspondences and point positions (liboptv through ``optv``) on an ari-sfm calibration.

The benchmarks' one copy of OpenPTV's matching (``bench_particles``, ``bench_particle_detection``):
the calibration is written by ``export_openptv`` in the coordinates of the body
frame ``f000`` (OpenPTV's world), the measured volume is its bounding box in that
frame, the epipolar band ``eps0`` is the given tolerance in pixels on the sensor,
and the similarity criteria (pixel counts, grey sums, ``corrmin``) are off, so
that both tools choose among the same candidates. OpenPTV's pixels put (0, 0) at
the top-left pixel's corner: +0.5 px from ari-sfm's (OpenCV's) convention.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.geometry import Pose
from ari_sfm.particles.volume import Volume


@dataclass(frozen=True)
class OpenptvRig:
    """liboptv's parameters and calibrations of a rig, in the calibration's camera order."""

    cameras: tuple[str, ...]
    cpar: Any  # optv.parameters.ControlParams (ptv.par as export_openptv wrote it)
    vpar: Any  # optv.parameters.VolumeParams
    cals: tuple[Any, ...]  # optv.calibration.Calibration per camera
    world_from_target: Pose  # OpenPTV's world is the body frame f000


def openptv_rig(calibration_path: Path, folder: Path, volume: Volume, tolerance_px: float) -> OpenptvRig:
    """Export ``calibration_path`` into ``folder`` (``export-openptv --frame f000``) and read it back with optv;
    the volume's bounding box in that frame and the epipolar band of ``tolerance_px``."""
    from optv.calibration import Calibration as OptvCalibration
    from optv.parameters import ControlParams, VolumeParams

    from ari_sfm.io import load_calibration
    from ari_sfm.openptv import export_openptv

    summary = export_openptv(calibration_path, folder, frame="f000")
    cal = load_calibration(calibration_path)
    world_from_target = cal.frames["f000"]
    cameras = tuple(cal.cameras)
    cpar = ControlParams(len(cameras))
    cpar.read_control_par(str(folder / "parameters" / "ptv.par"))
    cals = []
    for name in cameras:
        c = OptvCalibration()
        base = folder / "cal" / f"cam{summary.numbers[name]}.tif"
        c.from_file(f"{base}.ori".encode(), f"{base}.addpar".encode())
        cals.append(c)
    lo, hi = volume.min_mm, volume.max_mm
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    box = world_from_target.inverse().apply(volume.box_from_world.inverse().apply(corners))
    vpar = VolumeParams()
    vpar.set_X_lay([box[:, 0].min(), box[:, 0].max()])
    vpar.set_Zmin_lay([box[:, 2].min(), box[:, 2].min()])
    vpar.set_Zmax_lay([box[:, 2].max(), box[:, 2].max()])
    vpar.set_eps0(tolerance_px * cpar.get_pixel_size()[0])  # the band half-width on the sensor, mm
    for criterion in (vpar.set_cn, vpar.set_cnx, vpar.set_cny, vpar.set_csumg):
        criterion(0.0)  # similarity ratios (0..1) off
    vpar.set_corrmin(0.0)
    return OpenptvRig(cameras, cpar, vpar, tuple(cals), world_from_target)


def targets_from_pixels(uv: np.ndarray) -> tuple[Any, np.ndarray]:
    """A y-sorted ``TargetArray`` of pixels (OpenCV convention) with neutral pixel counts and grey sums, and
    ``order``: target ``i`` is row ``order[i]`` of ``uv``."""
    from optv.tracking_framebuf import TargetArray

    order = np.argsort(uv[:, 1], kind="stable")  # liboptv wants targets sorted by y
    targs = TargetArray(len(uv))
    for i, j in enumerate(order):
        targs[i].set_pos((uv[j, 0] + 0.5, uv[j, 1] + 0.5))  # OpenPTV pixel convention
        targs[i].set_pnr(i)
        targs[i].set_pixel_counts(9, 3, 3)
        targs[i].set_sum_grey_value(1000)
        targs[i].set_tnr(-1)
    return targs, order


def target_pixels(targets: Any) -> np.ndarray:
    """(N, 2) a ``TargetArray``'s centres in the OpenCV convention (OpenPTV's - 0.5 px)."""
    return np.array([t.pos() for t in targets], float).reshape(-1, 2) - 0.5


def openptv_match(rig: OpenptvRig, targets: list[Any], min_cameras: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """One frame: ``correspondences`` on each camera's y-sorted ``TargetArray`` (clobbered: its ``tnr``), then
    ``point_positions`` of the cliques of >= ``min_cameras`` cameras.

    Returns (M, 3) points in the calibration's world and (M, C) rows: the index of each camera's target
    (-1: none)."""
    from optv.correspondences import MatchedCoords, correspondences
    from optv.orientation import point_positions

    C = len(rig.cameras)
    flat = [MatchedCoords(targets[k], rig.cpar, rig.cals[k]) for k in range(C)]
    _, sorted_corresp, _ = correspondences(list(targets), flat, list(rig.cals), rig.vpar, rig.cpar)
    cliques = [np.asarray(sc) for sc in sorted_corresp if sc is not None]
    corresp = np.concatenate(cliques, axis=1) if cliques else np.empty((C, 0), np.int64)
    corresp = corresp[:, (corresp >= 0).sum(axis=0) >= min_cameras]
    if not corresp.shape[1]:
        return np.empty((0, 3)), np.empty((0, C), np.int64)
    # correspondences gives target numbers (pnr); point_positions wants flat (metric, undistorted) coordinates
    pos_flat = np.array([flat[k].get_by_pnrs(np.ascontiguousarray(corresp[k], dtype=np.int64)) for k in range(C)])
    X_target, _ = point_positions(pos_flat.transpose(1, 0, 2), rig.cpar, list(rig.cals), rig.vpar)
    return rig.world_from_target.apply(X_target), np.ascontiguousarray(corresp.T, dtype=np.int64)

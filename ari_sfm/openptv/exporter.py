"""``ari-sfm export-openptv``: a calibration.json as OpenPTV orientation files.

Writes ``cal/camN.tif.ori``, ``cal/camN.tif.addpar`` and ``parameters/ptv.par``
(its pixel size and multimedia part: n1 = 1, n2 = index, n3 = medium_index,
d = thickness_mm) in the coordinates of one calibration frame's target (default:
the first; for an imported experiment that is OpenPTV's own world), so that
OpenPTV's correspondence and tracking run on an ari-sfm calibration. Each camera's glass vector is
its own window's (a rig with several windows, DATASET_FORMAT 1.3). An existing
``parameters/ptv.par`` in the folder keeps its other lines (image names, flags)
and lends its pixel size unless ``pixel_size_mm`` is given; its image size must
match. Cameras named ``cam1``..``camN`` keep their numbers; others are numbered
in the calibration's order.

The interior orientation is exact when the calibration has no distortion or its
principal point is at the sensor centre; otherwise OpenPTV's distortion (about
the sensor centre) is fitted to OpenCV's (about the principal point) and the
largest pixel error of that fit is reported.
"""
from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ari_sfm.calibration.record import Calibration, WindowCalibration
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import Pose
from ari_sfm.io import load_calibration, write_text_atomic

from .conventions import exterior, fit_interior, glass_vector, interior_from_opencv
from .files import (
    ControlPar,
    Orientation,
    format_addpar,
    format_control_par,
    format_ori,
    read_control_par,
    update_control_par,
)

log = logging.getLogger(__name__)

WORLD = "world"  # --frame world: the calibration's own world frame
DEFAULT_PIXEL_SIZE_MM = 0.01  # any size images the same (cc and xh, yh scale with it); OpenPTV needs one
FIT_WARN_PX = 1e-3  # a fitted interior orientation worse than this is reported as a warning
CENTRE_TOLERANCE_MM = 1e-9  # |xh|, |yh| below this: the distortion converts exactly


@dataclass(frozen=True)
class ExportSummary:
    """What export_openptv wrote: the folder, frame, pixel size, files and per-camera fit errors (px)."""

    out: Path
    frame: str
    pixel_size_mm: tuple[float, float]
    files: tuple[Path, ...]
    numbers: dict[str, int] = field(default_factory=dict)
    fit_error_px: dict[str, float] = field(default_factory=dict)


def _camera_numbers(names: list[str]) -> dict[str, int]:
    """cam1..camN keep their numbers; any other naming is numbered in order from 1."""
    found = [m for m in (re.fullmatch(r"cam(\d+)", n) for n in names) if m is not None]
    numbers = [int(m.group(1)) for m in found]
    if len(numbers) == len(names) and sorted(numbers) == list(range(1, len(names) + 1)):
        return dict(zip(names, numbers))
    return {n: k + 1 for k, n in enumerate(names)}


def _target_pose(cal: Calibration, frame: str | None, path: Path) -> tuple[str, Pose]:
    """(frame name, world_from_target) of the export frame."""
    if frame is None:
        frame = next(iter(cal.frames), WORLD)
    if frame == WORLD:
        return frame, Pose.identity()
    if frame not in cal.frames:
        known = ", ".join(list(cal.frames)[:8]) or "none"
        raise AriSfmError(path, f"no calibration frame {frame!r} (frames: {known}; or 'world')")
    return frame, cal.frames[frame]


def _near_face_offset(cal: Calibration, window: WindowCalibration) -> float:
    """n . X of a window's near face in the world frame. Without a distance (air on both sides:
    unobservable, and the projection does not depend on it) the face is where the model was fitted
    (``fixed_distance_mm``, as Calibration.projection_model puts it), else (the paraxial ari model,
    which has no face) 10 mm beyond the camera nearest to it (default_distance_mm)."""
    plane = window.plane_mm(cal)
    if plane is not None:
        return plane
    if window.normal_world is None:
        raise ValueError(f"window {window.name} has no normal")
    from ari_sfm.factors.rig_graph import default_distance_mm

    return default_distance_mm(window.normal_world, {n: c.cam_from_world for n, c in cal.cameras.items()},
                               window.cameras)


def _control_par(existing: ControlPar | None, numbers: dict[str, int], size: tuple[int, int],
                 pix: tuple[float, float], cal: Calibration, path: Path) -> ControlPar:
    n = len(numbers)
    plates = {(w.interface.index, w.interface.medium_index, w.interface.thickness_mm) for w in cal.window_list()}
    if len(plates) > 1:
        raise AriSfmError(path, "the windows differ in thickness or index, and ptv.par holds one glass for every "
                                f"camera ({sorted(plates)})")
    iface = cal.interface
    if existing is not None:
        images, cal_images, flags, chfield = (existing.image_names, existing.cal_image_names, existing.flags,
                                              existing.chfield)
    else:
        images = tuple(f"img/cam{k}." for k in range(1, n + 1))
        cal_images = tuple(f"cal/cam{k}.tif" for k in range(1, n + 1))
        flags, chfield = (1, 0, 1), 0
    return ControlPar(images, cal_images, flags, size[0], size[1], pix[0], pix[1], chfield,
                      1.0, iface.index, iface.medium_index, iface.thickness_mm)


def export_openptv(calibration: str | Path, out: str | Path, frame: str | None = None,
                   pixel_size_mm: float | None = None) -> ExportSummary:
    """Write the OpenPTV files of a calibration into a folder (see the module docstring).

    Everything is computed and checked before the first file is written; each file is written
    atomically.

    Args:
        calibration: the calibration.json file.
        out: the folder to write into (an existing ``parameters/ptv.par`` there is updated).
        frame: the calibration frame whose target coordinates become OpenPTV's world, or ``world`` for the
            calibration's own world frame; None: the first calibration frame.
        pixel_size_mm: the sensor's pixel size; None: the existing ptv.par's, else DEFAULT_PIXEL_SIZE_MM.

    Returns:
        What was written: the folder, frame, pixel size, files, camera numbers and interior fit errors.

    Raises:
        AriSfmError: a model without a window, an unknown frame, a window OpenPTV cannot express, an existing
            ptv.par that does not match, or a file that cannot be written.
    """
    path = Path(calibration)
    cal = load_calibration(path)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise AriSfmError(out, "exists and is not a folder")
    if not cal.spec.window or not cal.spec.rays or cal.normal_world is None:
        raise AriSfmError(path, f"model {cal.model} has no window to export (OpenPTV needs one)")
    if cal.model == "ari":
        log.warning("%s: model ari is paraxial; OpenPTV traces rays exactly, so the exported cameras project like "
                    "ari-sfm's exact model with these parameters", path)
    if pixel_size_mm is not None:
        check_pixel_size(pixel_size_mm, "--pixel-size-mm")
    frame, world_from_target = _target_pose(cal, frame, path)
    names = list(cal.cameras)
    numbers = _camera_numbers(names)
    sizes = {(int(c.image_size[0]), int(c.image_size[1])) for c in cal.cameras.values()}
    if len(sizes) != 1:
        raise AriSfmError(path, f"cameras have different image sizes {sorted(sizes)}: ptv.par holds one")
    size = sizes.pop()
    ptv_par = out / "parameters" / "ptv.par"
    existing = read_control_par(ptv_par) if ptv_par.is_file() else None
    if existing is not None:
        if existing.num_cams != len(names):
            raise AriSfmError(ptv_par, f"{existing.num_cams} cameras, the calibration has {len(names)}")
        if (existing.imx, existing.imy) != size:
            raise AriSfmError(ptv_par, f"image size {existing.imx} x {existing.imy}, the calibration's is "
                                       f"{size[0]} x {size[1]}")
    if pixel_size_mm is not None:
        pix = (float(pixel_size_mm), float(pixel_size_mm))
    elif existing is not None:
        pix = (check_pixel_size(existing.pix_x, ptv_par, "pixel size x"),
               check_pixel_size(existing.pix_y, ptv_par, "pixel size y"))
    else:
        pix = (DEFAULT_PIXEL_SIZE_MM, DEFAULT_PIXEL_SIZE_MM)
        log.info("pixel size %g mm (no --pixel-size-mm, no ptv.par in %s)", DEFAULT_PIXEL_SIZE_MM, out)
    control = _control_par(existing, numbers, size, pix, cal, path)

    target_from_world = world_from_target.inverse()
    glasses = {}
    for window in cal.window_list():  # OpenPTV gives every camera its own glass vector: its window's
        if window.normal_world is None:  # cal.normal_world is checked above: every window has one
            raise AriSfmError(path, f"window {window.name} has no normal (OpenPTV needs one)")
        normal_t = world_from_target.R.T @ window.normal_world
        face_point_t = target_from_world.apply(_near_face_offset(cal, window) * window.normal_world)
        try:
            glass = glass_vector(normal_t, face_point_t, window.interface.thickness_mm)
        except ValueError as exc:
            which = "" if not cal.windows else f" (window {window.name})"
            raise AriSfmError(path, f"frame {frame}: {exc}{which}; OpenPTV's glass vector cannot express this "
                                    "window (choose another --frame)") from None
        glasses.update({c: glass for c in window.cameras})
    ptv_text = update_control_par(ptv_par, control) if existing else format_control_par(control)
    texts: dict[Path, str] = {ptv_par: ptv_text}
    fit_errors: dict[str, float] = {}
    for name in names:
        cam = cal.cameras[name]
        position, angles, dm = exterior(cam.cam_from_world.compose(world_from_target))
        dist = np.resize(cam.dist, 5)
        xh, yh, cc, addpar = interior_from_opencv(cam.K, dist, size, *pix)
        if np.any(dist != 0) and max(abs(xh), abs(yh)) > CENTRE_TOLERANCE_MM:
            xh, yh, cc, addpar, fit_errors[name] = fit_interior(cam.K, dist, size, *pix)
            level = logging.WARNING if fit_errors[name] > FIT_WARN_PX else logging.INFO
            log.log(level, "%s: OpenPTV's distortion (about the sensor centre) fitted to the calibration's "
                           "(about the principal point): max error %.2g px", name, fit_errors[name])
        base = out / control.cal_image_names[numbers[name] - 1]
        texts[base.with_name(base.name + ".ori")] = format_ori(Orientation(position, angles, dm, xh, yh, cc,
                                                                           glasses[name]))
        texts[base.with_name(base.name + ".addpar")] = format_addpar(addpar)
    _check_targets(out, texts, ptv_par)
    for file, text in [*texts.items()][1:] + [(ptv_par, ptv_text)]:  # ptv.par last: it names the others
        write_text_atomic(file, text)
    return ExportSummary(out, frame, pix, tuple(texts), numbers, fit_errors)


MIN_PIXEL_SIZE_MM, MAX_PIXEL_SIZE_MM = 1e-4, 1.0  # 0.1 um .. 1 mm: sensor pixels are ~1-20 um


def check_pixel_size(value: float, where: str | Path, what: str | None = None) -> float:
    """Check that a value is a physical pixel size in mm (finite, MIN_PIXEL_SIZE_MM..MAX_PIXEL_SIZE_MM).

    Args:
        value: the pixel size, mm.
        where: the option or file named in the error.
        what: the value's name, prefixed to the message; None: none.

    Returns:
        ``value`` as a float.

    Raises:
        AriSfmError: ``value`` is not finite or out of range.
    """
    prefix = f"{what} " if what else ""
    if not (np.isfinite(value) and MIN_PIXEL_SIZE_MM <= value <= MAX_PIXEL_SIZE_MM):
        raise AriSfmError(where, f"{prefix}must be a pixel size in mm between {MIN_PIXEL_SIZE_MM:g} and "
                                 f"{MAX_PIXEL_SIZE_MM:g} (got {value:g})")
    return float(value)


def _check_targets(out: Path, texts: dict[Path, str], ptv_par: Path) -> None:
    """Before the first write: every file lies inside ``out`` (an existing ptv.par's calibration image names
    may point elsewhere: '../x', '/abs'), no folder on the way is a file, and every number is finite."""
    root = Path(os.path.realpath(out))
    for file, text in texts.items():
        resolved = Path(os.path.realpath(file))
        if root != resolved.parent and root not in resolved.parents:
            raise AriSfmError(ptv_par, f"calibration image name leads outside {out} ({file}): the export writes "
                                       "only inside -o; fix the names in ptv.par")
        folder = file.parent
        while folder != out and folder not in out.parents:
            if folder.exists() and not folder.is_dir():
                raise AriSfmError(folder, f"is a file, so {file.name} cannot be written there")
            folder = folder.parent
        if file != ptv_par and re.search(r"(?<![A-Za-z])(nan|inf)(?![A-Za-z])", text, re.IGNORECASE):
            raise AriSfmError(file, "would hold a non-finite number (nan or inf): nothing written")

"""``ari-sfm import openptv``: an OpenPTV experiment folder as an ari-sfm dataset.

What is read (see :mod:`.files` for the formats, :mod:`.conventions` for the
conversions):

- ``parameters/ptv.par``: cameras (named ``cam1``..``camN`` in ptv.par's order,
  as OpenPTV numbers them), image size, pixel size, n1 n2 n3 and the glass
  thickness d;
- ``parameters/multi_planes.par`` if present and every file it names is there
  (each plane's ``<base>k.tif.fix`` and ``.crd`` for camera k), else
  ``parameters/cal_ori.par`` (a multi_planes.par naming files the lab never made
  is left aside with a warning): its target file, and per camera the
  ``<calibration image>.crd`` where it exists and the calibration image itself.
  All planes together are one rigid ``points3d`` body seen once: calibration
  frame ``f000`` in OpenPTV's world;
- ``man_ori.dat`` (the experiment folder, or ``parameters/``) with
  ``parameters/man_ori.par``: OpenPTV's 4 clicked points per camera become the
  entry's ``manual_points`` (DATASET_FORMAT 1.3; cal_ori.par's body only), from
  which ``detect`` / ``calibrate`` identify the body in the images;
- ``<calibration image>.ori`` per camera, when present (never required): cc /
  pixel size becomes the ``focal_px`` hint; when every camera has one, its glass
  vector tells its window and the window's plane, declared as OpenPTV holds it
  (:mod:`.windows`); else the windows are told from the cameras' viewing directions
  resected from their clicked points, their planes left for calibrate to estimate.
  Cameras behind different walls (test_cavity's two) give several windows
  (``interfaces``, DATASET_FORMAT 1.3); ``window_groups`` gives them explicitly.

The dataset lists the calibration images, copied into it at their path in the
experiment (``cal/cam1.tif``; an image outside the experiment folder goes to
``images/``), so that it stands alone; observations come only from the
``.crd`` files that exist. The ``.crd`` and ``man_ori.dat`` pixels are OpenPTV
pixels (origin at the top-left pixel's corner): 0.5 is subtracted. Undetected
points (-999) are left out. With n1 != 1 the window is written with index n2 /
n1 and medium_index n3 / n1 (Snell's law depends on the ratios only). Point ids
of plane p (0-based) are ``p * PLANE_ID_STEP + id`` when there are several planes.
"""
from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ari_sfm.errors import AriSfmError
from ari_sfm.io.dataset import MAX_LENGTH_MM
from ari_sfm.io.observations import BORDER_TOLERANCE_PX
from ari_sfm.records import CameraSpec, Dataset, Entry, Interface, Observation, Target, Window

from .conventions import OPENPTV_PIXEL_OFFSET, detect_settings_from_target_par
from .files import (
    MAN_ORI_POINTS,
    ControlPar,
    read_addpar,
    read_cal_ori_par,
    read_control_par,
    read_man_ori,
    read_multi_planes_par,
    read_ori,
    read_points,
    read_sequence_par,
    read_target_par,
    read_volume_par,
)
from .windows import parse_window_groups, windows_from_axes, windows_from_glass, windows_from_groups

log = logging.getLogger(__name__)

FRAME = "f000"
UNDETECTED = -999.0  # OpenPTV's mark of a target not found in an image
FIX_TOLERANCE_MM = 1e-6  # two cameras' .fix files must agree on a point to this


@dataclass(frozen=True)
class PlaneFiles:
    """The .fix and .crd files of one plane (or the single target) for one camera."""

    fix: Path
    crd: Path


def _plane_files(root: Path, control: ControlPar) -> tuple[list[list[PlaneFiles]], Path]:
    """Per plane, per camera: the fix/crd files; and the parameter file that named them: multi_planes.par
    when every file it names exists, else cal_ori.par (whose .crd files may be missing: the images then)."""
    params = root / "parameters"
    multi = params / "multi_planes.par"
    cal_ori = params / "cal_ori.par"
    if multi.is_file():
        bases = read_multi_planes_par(multi)
        planes = [[PlaneFiles(root / f"{b}{k + 1}.tif.fix", root / f"{b}{k + 1}.tif.crd")
                   for k in range(control.num_cams)] for b in bases]
        missing = [f for plane in planes for files in plane for f in (files.fix, files.crd) if not f.is_file()]
        if not missing:
            return planes, multi
        if not cal_ori.is_file():
            raise AriSfmError(missing[0], "file not found (named by multi_planes.par; no cal_ori.par to read the "
                                          "body from instead)")
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        log.warning("%s names files that do not exist (%s%s): the body is read from cal_ori.par", multi,
                    os.path.relpath(missing[0], root), more)
    if not cal_ori.is_file():
        raise AriSfmError(params, "neither multi_planes.par nor cal_ori.par: no calibration body to import")
    par = read_cal_ori_par(cal_ori, control.num_cams)
    return [[PlaneFiles(root / par.fixp_name, root / f"{img}.crd") for img in par.img_names]], cal_ori


def _read_fix(fix_path: Path, offset: int, body: dict[int, np.ndarray], sources: dict[int, Path]
              ) -> dict[int, np.ndarray]:
    """Add a camera's .fix points to the body (ids + ``offset``); return the file's points."""
    fix = read_points(fix_path, 3)
    for pid, xyz in fix.items():
        key = offset + pid
        if not np.all(np.abs(xyz) <= MAX_LENGTH_MM):  # 1e300 imported, then failed inside OpenCV
            raise AriSfmError(fix_path, f"point {pid} at {xyz.tolist()}: beyond {MAX_LENGTH_MM:g} mm, not a "
                                        "body coordinate in mm")
        if key in body and np.max(np.abs(body[key] - xyz)) > FIX_TOLERANCE_MM:
            raise AriSfmError(fix_path, f"point {pid} is at {xyz.tolist()} but at {body[key].tolist()} in "
                                        f"{sources[key]}")
        body.setdefault(key, xyz)
        sources.setdefault(key, fix_path)
    return fix


def _read_plane(files: PlaneFiles, offset: int, body: dict[int, np.ndarray], sources: dict[int, Path],
                image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Add a camera's .fix points to the body; return its detected (ids, OpenCV pixels)."""
    fix = read_points(files.fix, 3)
    crd = read_points(files.crd, 2)
    if set(fix) != set(crd):
        extra = sorted(set(crd) - set(fix)) or sorted(set(fix) - set(crd))
        where = "not in" if set(crd) - set(fix) else "missing from"
        raise AriSfmError(files.crd, f"ids do not match {files.fix.name}: id {extra[0]} {where} this file")
    _read_fix(files.fix, offset, body, sources)
    ids, pixels = [], []
    for pid in fix:
        key = offset + pid
        if np.all(crd[pid] != UNDETECTED):
            margin = BORDER_TOLERANCE_PX  # as the dataset's own pixel check: a centre just beyond the edge is kept
            if not (-margin <= crd[pid][0] <= image_size[0] + margin
                    and -margin <= crd[pid][1] <= image_size[1] + margin):
                raise AriSfmError(files.crd, f"id {pid} at ({crd[pid][0]:g}, {crd[pid][1]:g}) is outside the "
                                             f"{image_size[0]} x {image_size[1]} image (.crd files hold OpenPTV "
                                             "pixels; metric ones are not read)")
            ids.append(key)
            pixels.append(crd[pid] - OPENPTV_PIXEL_OFFSET)
    return np.array(ids, dtype=int), np.array(pixels, dtype=float).reshape(-1, 2)


def _plate(control: ControlPar, ptv_par: Path) -> tuple[float, float, float]:
    """(thickness, index, medium index) of ptv.par's glass: d, n2 / n1, n3 / n1 (Snell's law depends on the
    ratios only); one error line when there is no plate."""
    if control.d <= 0 or control.n2 == control.n1:
        raise AriSfmError(ptv_par, f"no window to calibrate (glass thickness {control.d:g} mm, n1 {control.n1:g}, "
                                   f"n2 {control.n2:g}): ari-sfm needs a glass plate")
    if control.n1 != 1.0:
        log.warning("%s: n1 = %g: the window is written with index n2/n1 = %g and medium_index n3/n1 = %g "
                    "(Snell's law depends on the ratios only)", ptv_par, control.n1, control.n2 / control.n1,
                    control.n3 / control.n1)
    return control.d, control.n2 / control.n1, control.n3 / control.n1


def _windows(root: Path, control: ControlPar, names: list[str], glasses: list[np.ndarray], target: Target,
             images: dict[str, Path], manual: dict[str, dict[int, tuple[float, float]]], cameras: dict[str, CameraSpec],
             groups: str | None) -> tuple[Window, ...]:
    """The experiment's windows (:mod:`.windows`): the user's ``groups``; else every camera's .ori glass
    vector; else the cameras' viewing directions resected from their clicked points; else (a camera without
    clicks) one window for all, said so."""
    ptv_par = root / "parameters" / "ptv.par"
    plate = _plate(control, ptv_par)
    if groups is not None:
        return windows_from_groups(parse_window_groups(groups, names), *plate)
    if len(glasses) == len(names):
        return windows_from_glass(names, glasses, [root / f"{cal}.ori" for cal in control.cal_image_names], *plate,
                                  FRAME)
    axes = _viewing_axes(target, manual, cameras)
    if len(axes) == len(names):
        return windows_from_axes(names, [axes[n] for n in names], *plate)
    if len(names) > 1:
        log.warning("%s: no .ori glass vectors and no clicked points for %s: one window for every camera is assumed "
                    "(cameras behind different walls: give them with --windows)", root,
                    ", ".join(n for n in names if n not in axes))
    return (Window("window", Interface(*plate), tuple(names)),)


def _viewing_axes(target: Target, manual: dict[str, dict[int, tuple[float, float]]],
                  cameras: dict[str, CameraSpec]) -> dict[str, np.ndarray]:
    """Each clicked camera's optical axis in the body's frame, from a resection of its clicks (cameras whose clicks
    fit no camera are left out)."""
    from ari_sfm.body.identify import ClickError, start_cameras

    ids, xyz = target.points_3d()
    axes = {}
    for name, clicks in manual.items():
        try:
            camera, _ = start_cameras(ids, xyz, clicks, cameras[name].image_size, cameras[name].focal_px)[0]
        except (ClickError, ValueError) as exc:
            log.warning("%s: its clicked points give no camera (%s): its window cannot be told", name, exc)
            continue
        axes[name] = camera.rotation.T @ np.array([0.0, 0.0, 1.0])
    return axes


def _cameras(root: Path, control: ControlPar, names: list[str]) -> tuple[dict[str, CameraSpec], list[np.ndarray]]:
    """The cameras (image size; focal_px from its .ori when there is one) and the glass vectors of the .ori
    files found (all cameras' or fewer)."""
    cameras, glasses = {}, []
    size = (control.imx, control.imy)
    for name, cal in zip(names, control.cal_image_names):
        ori_path = root / f"{cal}.ori"
        if not ori_path.is_file():
            log.info("%s: no orientation file %s.ori: no focal length hint", name, cal)
            cameras[name] = CameraSpec(name, size)
            continue
        ori = read_ori(ori_path)
        addpar = read_addpar(root / f"{cal}.addpar")
        if not addpar.is_identity():
            log.info("%s: distortion in %s.addpar is not imported (calibrate fits its own)", name, cal)
        glasses.append(ori.glass)
        if control.pix_x == control.pix_y:
            cameras[name] = CameraSpec(name, size, focal_px=ori.cc / control.pix_x)
        else:  # non-square pixels: a K hint (fx != fy) instead of focal_px
            K = np.array([[ori.cc / control.pix_x, 0, control.imx / 2 - OPENPTV_PIXEL_OFFSET],
                          [0, ori.cc / control.pix_y, control.imy / 2 - OPENPTV_PIXEL_OFFSET], [0, 0, 1.0]])
            cameras[name] = CameraSpec(name, size, K=K)
    return cameras, glasses


def _calibration_images(root: Path, cal_ori: Path, control: ControlPar, names: list[str]) -> dict[str, Path]:
    """The calibration images cal_ori.par names that exist, by camera."""
    par = read_cal_ori_par(cal_ori, control.num_cams)
    return {name: root / img for name, img in zip(names, par.img_names) if (root / img).is_file()}


def _man_ori_dat(root: Path) -> Path:
    """Where the clicked pixels are: the experiment folder's man_ori.dat (the GUI writes it there), else parameters/."""
    here = root / "man_ori.dat"
    return here if here.is_file() else root / "parameters" / "man_ori.dat"


def _manual_points(root: Path, control: ControlPar, names: list[str], body: dict[int, np.ndarray],
                   images: dict[str, Path]) -> dict[str, dict[int, tuple[float, float]]]:
    """OpenPTV's clicked points (man_ori.par, man_ori.dat) in OpenCV pixels, for the cameras with an image and
    4 clicked points; {} without the two files."""
    par, dat = root / "parameters" / "man_ori.par", _man_ori_dat(root)
    if not (par.is_file() and dat.is_file()):
        if images:
            log.warning("%s: no %s: the dataset has no clicked points, which identifying the body in the images "
                        "needs", root, "man_ori.par" if not par.is_file() else "man_ori.dat")
        return {}
    out: dict[str, dict[int, tuple[float, float]]] = {}
    for name, clicks in zip(names, read_man_ori(par, dat, control.num_cams)):
        for pid, (x, y) in clicks.items():
            if pid not in body:
                raise AriSfmError(par, f"{name}: clicked point {pid} is not a point of the calibration body")
            if not (0.0 <= x <= control.imx and 0.0 <= y <= control.imy):
                raise AriSfmError(dat, f"{name}: clicked point {pid} at ({x:g}, {y:g}) is outside the "
                                       f"{control.imx} x {control.imy} image")
        if name not in images:
            continue
        if len(clicks) < MAN_ORI_POINTS:
            log.warning("%s: %s has %d clicked points (need %d): none imported", name, dat, len(clicks),
                        MAN_ORI_POINTS)
            continue
        out[name] = {pid: (float(x - OPENPTV_PIXEL_OFFSET), float(y - OPENPTV_PIXEL_OFFSET))
                     for pid, (x, y) in clicks.items()}
    return out


def read_experiment(root: str | Path, window_groups: str | None = None) -> Dataset:
    """Read an OpenPTV experiment folder as a dataset (records only; nothing is written).

    Args:
        root: the experiment folder (with ``parameters/ptv.par``).
        window_groups: which cameras share a window, ``cam1,cam2;cam3,cam4``; None: told from the .ori
            glass vectors or the clicked points (see :mod:`.windows`).

    Returns:
        The dataset; its ``rig_path`` is ``root/rig.yaml`` (not written).

    Raises:
        AriSfmError: a missing or malformed OpenPTV file, an unsupported setting, or no glass plate.
    """
    root = Path(os.path.abspath(root))
    if root.exists() and not root.is_dir():
        raise AriSfmError(root, "is a file, expected an OpenPTV experiment folder (with parameters/ptv.par)")
    if not root.is_dir():
        raise AriSfmError(root, "no such OpenPTV experiment folder")
    ptv_par = root / "parameters" / "ptv.par"
    control = read_control_par(ptv_par)
    if control.chfield != 0:
        raise AriSfmError(ptv_par, f"chfield {control.chfield}: interlaced fields are not supported")
    names = [f"cam{k + 1}" for k in range(control.num_cams)]
    cameras, glasses = _cameras(root, control, names)
    _plate(control, ptv_par)  # a window to calibrate, before anything else is read
    planes, source = _plane_files(root, control)
    images = _calibration_images(root, source, control, names) if source.name == "cal_ori.par" else {}
    step = 10 ** len(str(max(1, _max_id(planes)))) if len(planes) > 1 else 0
    body: dict[int, np.ndarray] = {}
    sources: dict[int, Path] = {}
    per_camera: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {n: [] for n in names}
    for p, plane in enumerate(planes):
        for name, files in zip(names, plane):
            if not files.crd.is_file() and name in images:  # cal_ori.par: the body is found in the image
                _read_fix(files.fix, p * step, body, sources)
                continue
            if not files.crd.is_file() and source.name == "cal_ori.par":
                raise AriSfmError(files.crd, f"file not found, and no calibration image {files.crd.name[:-4]} to "
                                             "find the body in")
            per_camera[name].append(_read_plane(files, p * step, body, sources, (control.imx, control.imy)))
    observations = []
    for name in names:
        if not per_camera[name]:
            continue
        ids = np.concatenate([i for i, _ in per_camera[name]])
        pixels = np.concatenate([px for _, px in per_camera[name]])
        if len(ids):
            observations.append(Observation(name, "calibration", FRAME, ids, pixels))
    manual = _manual_points(root, control, names, body, images) if source.name == "cal_ori.par" else {}
    log.info("%s: %d cameras, %d body points on %d plane(s) (from %s), %d calibration images, clicked points for "
             "%d cameras, .crd detections for %d", root, len(names), len(body), len(planes), source.name,
             len(images), len(manual), len(observations))
    target = Target(type="points3d",
                    points={k: (float(v[0]), float(v[1]), float(v[2])) for k, v in sorted(body.items())})
    has_crd = any(per_camera.values())
    windows = _windows(root, control, names, glasses, target, images, manual, cameras, window_groups)
    return Dataset(root=root, rig_path=root / "rig.yaml", target=target,
                   interface=windows[0].interface, cameras=cameras,
                   calibration=(Entry("calibration", FRAME, images=images, manual_points=manual),),
                   observations=tuple(observations) if has_crd else None,
                   windows=windows if len(windows) > 1 else ())


def _source_of(message: str, root: Path, dataset: Dataset) -> Path:
    """The OpenPTV file a rig.yaml key came from: interface.plane from cam1's .ori glass vector, the rest of
    interface and image sizes from ptv.par, a camera's focal_px / K from its .ori (cc / pixel size), target
    points from the .fix files, observations from the .crd files."""
    control = read_control_par(root / "parameters" / "ptv.par")
    oris = {f"cam{k + 1}": root / f"{cal}.ori" for k, cal in enumerate(control.cal_image_names)}
    key = message.split()[0] if message else ""
    if key.startswith("interface.plane"):
        return oris["cam1"]
    if key.startswith("cameras."):
        name = key.split(".")[1]
        return root / "parameters" / "ptv.par" if ".image_size" in key or name not in oris else oris[name]
    if key.startswith("target"):
        return _plane_files(root, control)[1]
    if key.startswith("observation"):
        return root / "cal"
    if ".manual_points" in key:
        return _man_ori_dat(root)
    return root / "parameters" / "ptv.par"


def _max_id(planes: list[list[PlaneFiles]]) -> int:
    """The largest point id of all planes' .fix files (for the id step between planes)."""
    return max(max(read_points(f.fix, 3)) for plane in planes for f in plane)


def _copied_images(dataset: Dataset, folder: Path) -> Dataset:
    """``dataset`` with its calibration images copied into ``folder``: at their path in the experiment
    (``cal/cam1.tif``), or under ``images/`` for an image outside the experiment folder."""
    entries = []
    for entry in dataset.calibration:
        images = {}
        for cam, path in entry.images.items():
            rel = Path(os.path.relpath(path, dataset.root))
            if rel.parts[0] == os.pardir:
                rel = Path("images") / f"{cam}_{path.name}"
            (folder / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, folder / rel)
            images[cam] = folder / rel
        entries.append(replace(entry, images=images))
    return replace(dataset, calibration=tuple(entries))


def import_experiment(root: str | Path, out: str | Path, window_groups: str | None = None) -> Path:
    """Write the dataset of an OpenPTV experiment to a new folder.

    Writes rig.yaml (with ``particles:`` when the experiment has a sequence.par), observations.json where
    .crd files exist, and a copy of the calibration images, in a temporary folder beside ``out`` that is
    then renamed.

    Args:
        root: the experiment folder (with ``parameters/ptv.par``).
        out: the dataset folder to create (absent or empty).
        window_groups: which cameras share a window, ``cam1,cam2;cam3,cam4``; None: told from the
            experiment (see :func:`read_experiment`).

    Returns:
        The rig file written, ``out/rig.yaml``.

    Raises:
        AriSfmError: ``out`` is not empty, or the experiment cannot be read or imported (naming the
            OpenPTV file at fault).
    """
    from ari_sfm.io import save_rig

    out = Path(os.path.abspath(out))
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise AriSfmError(out, "already exists and is not empty: give a new folder")
    dataset = read_experiment(root, window_groups)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; the dataset is an ordinary folder
        dataset = _copied_images(dataset, tmp)
        try:
            save_rig(tmp / "rig.yaml", dataset)
        except AriSfmError as exc:  # named the temporary rig.yaml, deleted below: name the OpenPTV file instead
            if exc.path is None or Path(exc.path).parent != tmp:
                raise
            raise AriSfmError(_source_of(exc.message, Path(os.path.abspath(root)), dataset),
                              f"not importable: {exc.message}") from None
        _add_particles(Path(os.path.abspath(root)), tmp / "rig.yaml", out, dataset)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out / "rig.yaml"


def particles_entry(root: Path, dataset_dir: Path, control: ControlPar) -> dict | None:
    """Build rig.yaml's ``particles:`` entry (DATASET_FORMAT 1.2) of an experiment.

    From ``sequence.par``: each camera's image pattern and the frames first..last. From ``criteria.par``
    when present: the observation volume as ``volume_mm`` in the body's frame (OpenPTV's world, frame
    f000: x X_lay[0]..X_lay[1], z its depth range, y as wide as the widest of the two, which OpenPTV does
    not bound). From ``targ_rec.par`` when present: the detector settings as ``detect``.

    Args:
        root: the experiment folder.
        dataset_dir: the folder the dataset ends up in; image paths are written relative to it.
        control: the experiment's parsed ptv.par.

    Returns:
        The ``particles`` mapping, or None without a sequence.par.
    """
    params = root / "parameters"
    if not (params / "sequence.par").is_file():
        return None
    seq = read_sequence_par(params / "sequence.par", control.num_cams)
    images = {f"cam{k + 1}": os.path.relpath(root / seq.pattern(k), dataset_dir) for k in range(control.num_cams)}
    entry: dict = {"images": images, "frames": [seq.first, seq.last]}
    if (params / "criteria.par").is_file():
        vol = read_volume_par(params / "criteria.par")
        z = (min(vol.z_min_lay), max(vol.z_max_lay))
        half = max(abs(v) for v in (*vol.x_lay, *z))
        entry["volume_mm"] = {"frame": FRAME, "min": [vol.x_lay[0], -half, z[0]], "max": [vol.x_lay[1], half, z[1]]}
    if (params / "targ_rec.par").is_file():
        entry["detect"] = detect_settings_from_target_par(read_target_par(params / "targ_rec.par"), list(images))
    return entry


def _add_particles(root: Path, rig_path: Path, out: Path, dataset: Dataset) -> None:
    """The experiment's particle images (:func:`particles_entry`) added to the written rig.yaml, checked by the
    particle experiment's own reader."""
    import yaml

    from ari_sfm.io import write_text_atomic
    from ari_sfm.io.particles import load_particle_dataset

    entry = particles_entry(root, out, read_control_par(root / "parameters" / "ptv.par"))
    if entry is None:
        return
    data = yaml.safe_load(rig_path.read_text())
    data["particles"] = entry
    write_text_atomic(rig_path, yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120))
    particles = load_particle_dataset(rig_path)  # (paths relative to out: checked from there once renamed)
    log.info("particle images of %d cameras, frames %d..%d%s%s", len(particles.cameras), *entry["frames"],
             ", the observation volume from criteria.par" if "volume_mm" in entry else "",
             ", the detector's settings from targ_rec.par" if "detect" in entry else "")

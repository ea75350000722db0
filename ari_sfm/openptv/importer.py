"""``ari-sfm import openptv``: an OpenPTV experiment folder as an ari-sfm dataset.

What is read (see :mod:`.files` for the formats, :mod:`.conventions` for the
conversions):

- ``parameters/ptv.par``: cameras (named ``cam1``..``camN`` in ptv.par's order,
  as OpenPTV numbers them), image size, pixel size, n1 n2 n3 and the glass
  thickness d;
- ``parameters/multi_planes.par`` if present (each plane's ``<base>k.tif.fix``
  and ``.crd`` for camera k), else ``parameters/cal_ori.par`` (its target file
  and ``<calibration image>.crd`` per camera). All planes together are one rigid
  ``points3d`` body seen once: calibration frame ``f000`` in OpenPTV's world;
- ``<calibration image>.ori`` per camera: cc / pixel size becomes the
  ``focal_px`` hint, the glass vector becomes ``interface.plane``.

The ``.crd`` pixels are OpenPTV pixels (origin at the top-left pixel's corner):
0.5 is subtracted. Undetected points (-999) are left out. With n1 != 1 the
window is written with index n2 / n1 and medium_index n3 / n1 (Snell's law
depends on the ratios only). Point ids of plane p (0-based) are
``p * PLANE_ID_STEP + id`` when there are several planes.
"""
from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ari_sfm.errors import AriSfmError
from ari_sfm.io.dataset import MAX_LENGTH_MM
from ari_sfm.io.observations import BORDER_TOLERANCE_PX
from ari_sfm.records import CameraSpec, Dataset, Entry, Interface, Observation, Target, WindowPlane

from .conventions import OPENPTV_PIXEL_OFFSET, window_plane
from .files import ControlPar, read_addpar, read_cal_ori_par, read_control_par, read_multi_planes_par, read_ori, \
    read_points

log = logging.getLogger(__name__)

FRAME = "f000"
UNDETECTED = -999.0  # OpenPTV's mark of a target not found in an image
FIX_TOLERANCE_MM = 1e-6  # two cameras' .fix files must agree on a point to this
GLASS_TOLERANCE = 1e-9  # relative: cameras whose glass vectors differ more get a plane prior, not a fixed plane
SAME_WINDOW_DEG = 5.0  # glass normals further apart than this are different windows (the contract has one)


@dataclass(frozen=True)
class PlaneFiles:
    """The .fix and .crd files of one plane (or the single target) for one camera."""

    fix: Path
    crd: Path


def _plane_files(root: Path, control: ControlPar) -> tuple[list[list[PlaneFiles]], Path]:
    """Per plane, per camera: the fix/crd files; and the parameter file that named them."""
    params = root / "parameters"
    multi = params / "multi_planes.par"
    if multi.is_file():
        bases = read_multi_planes_par(multi)
        return [[PlaneFiles(root / f"{b}{k + 1}.tif.fix", root / f"{b}{k + 1}.tif.crd")
                 for k in range(control.num_cams)] for b in bases], multi
    cal_ori = params / "cal_ori.par"
    if not cal_ori.is_file():
        raise AriSfmError(params, "neither multi_planes.par nor cal_ori.par: no calibration body to import")
    par = read_cal_ori_par(cal_ori, control.num_cams)
    return [[PlaneFiles(root / par.fixp_name, root / f"{img}.crd") for img in par.img_names]], cal_ori


def _read_plane(files: PlaneFiles, offset: int, body: dict[int, np.ndarray], sources: dict[int, Path],
                image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Add a camera's .fix points to the body; return its detected (ids, OpenCV pixels)."""
    fix = read_points(files.fix, 3)
    crd = read_points(files.crd, 2)
    if set(fix) != set(crd):
        extra = sorted(set(crd) - set(fix)) or sorted(set(fix) - set(crd))
        where = "not in" if set(crd) - set(fix) else "missing from"
        raise AriSfmError(files.crd, f"ids do not match {files.fix.name}: id {extra[0]} {where} this file")
    ids, pixels = [], []
    for pid, xyz in fix.items():
        key = offset + pid
        if not np.all(np.abs(xyz) <= MAX_LENGTH_MM):  # 1e300 imported, then failed inside OpenCV
            raise AriSfmError(files.fix, f"point {pid} at {xyz.tolist()}: beyond {MAX_LENGTH_MM:g} mm, not a "
                                         "body coordinate in mm")
        if key in body and np.max(np.abs(body[key] - xyz)) > FIX_TOLERANCE_MM:
            raise AriSfmError(files.fix, f"point {pid} is at {xyz.tolist()} but at {body[key].tolist()} in "
                                         f"{sources[key]}")
        body.setdefault(key, xyz)
        sources.setdefault(key, files.fix)
        if np.all(crd[pid] != UNDETECTED):
            margin = BORDER_TOLERANCE_PX  # as the dataset's own pixel check: a centre just beyond the edge is kept
            if not (-margin <= crd[pid][0] <= image_size[0] + margin and -margin <= crd[pid][1] <= image_size[1] + margin):
                raise AriSfmError(files.crd, f"id {pid} at ({crd[pid][0]:g}, {crd[pid][1]:g}) is outside the "
                                             f"{image_size[0]} x {image_size[1]} image (.crd files hold OpenPTV "
                                             "pixels; metric ones are not read)")
            ids.append(key)
            pixels.append(crd[pid] - OPENPTV_PIXEL_OFFSET)
    return np.array(ids, dtype=int), np.array(pixels, dtype=float).reshape(-1, 2)


def _interface(control: ControlPar, glasses: list[np.ndarray], ori_paths: list[Path], ptv_par: Path) -> Interface:
    """The window: n2 / n1, n3 / n1, d; the plane from cam1's glass vector (a prior if cameras differ)."""
    if control.d <= 0 or control.n2 == control.n1:
        raise AriSfmError(ptv_par, f"no window to calibrate (glass thickness {control.d:g} mm, n1 {control.n1:g}, "
                                   f"n2 {control.n2:g}): ari-sfm needs a glass plate")
    if control.n1 != 1.0:
        log.warning("%s: n1 = %g: the window is written with index n2/n1 = %g and medium_index n3/n1 = %g "
                    "(Snell's law depends on the ratios only)", ptv_par, control.n1, control.n2 / control.n1,
                    control.n3 / control.n1)
    planes = []
    for glass, path in zip(glasses, ori_paths):
        if not np.linalg.norm(glass) > 0:
            raise AriSfmError(path, "glass vector is zero: OpenPTV needs it to place the window")
        planes.append(window_plane(glass, control.d))
    normal, point = planes[0]
    angles = [np.degrees(np.arccos(np.clip(n @ normal, -1, 1))) for n, _ in planes]
    for angle, path in zip(angles, ori_paths):
        if angle > SAME_WINDOW_DEG:
            raise AriSfmError(path, f"glass vector is {angle:.1f} deg from {ori_paths[0].name}'s: the cameras look "
                                    "through different windows, and an ari-sfm dataset has one")
    offsets = [abs(normal @ (p - point)) for _, p in planes]
    sigma_deg, sigma_mm = max(angles), max(offsets)
    scale = max(1.0, float(np.linalg.norm(glasses[0])))
    if sigma_deg <= np.degrees(GLASS_TOLERANCE) and sigma_mm <= GLASS_TOLERANCE * scale:
        sigma_deg = sigma_mm = 0.0
    else:
        log.warning("the cameras' glass vectors differ (up to %.3g deg, %.3g mm): interface.plane is cam1's, "
                    "as a prior with those sigmas", sigma_deg, sigma_mm)
    return Interface(thickness_mm=control.d, index=control.n2 / control.n1, medium_index=control.n3 / control.n1,
                     plane=WindowPlane(FRAME, normal, point, float(sigma_deg), float(sigma_mm)))


def read_experiment(root: str | Path) -> Dataset:
    """The dataset of an OpenPTV experiment folder (records only; nothing is written)."""
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
    ori_paths = [root / f"{cal}.ori" for cal in control.cal_image_names]
    cameras, glasses = {}, []
    for name, ori_path, cal in zip(names, ori_paths, control.cal_image_names):
        if not ori_path.is_file():
            raise AriSfmError(ori_path, f"no orientation file for {name} (ptv.par names calibration image {cal})")
        ori = read_ori(ori_path)
        addpar = read_addpar(root / f"{cal}.addpar")
        if not addpar.is_identity():
            log.info("%s: distortion in %s.addpar is not imported (calibrate fits its own)", name, cal)
        glasses.append(ori.glass)
        size = (control.imx, control.imy)
        if control.pix_x == control.pix_y:
            cameras[name] = CameraSpec(name, size, focal_px=ori.cc / control.pix_x)
        else:  # non-square pixels: a K hint (fx != fy) instead of focal_px
            K = np.array([[ori.cc / control.pix_x, 0, control.imx / 2 - OPENPTV_PIXEL_OFFSET],
                          [0, ori.cc / control.pix_y, control.imy / 2 - OPENPTV_PIXEL_OFFSET], [0, 0, 1.0]])
            cameras[name] = CameraSpec(name, size, K=K)
    interface = _interface(control, glasses, ori_paths, ptv_par)
    planes, source = _plane_files(root, control)
    step = 10 ** len(str(max(1, _max_id(planes)))) if len(planes) > 1 else 0
    body: dict[int, np.ndarray] = {}
    sources: dict[int, Path] = {}
    per_camera: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {n: [] for n in names}
    for p, plane in enumerate(planes):
        for name, files in zip(names, plane):
            per_camera[name].append(_read_plane(files, p * step, body, sources, (control.imx, control.imy)))
    observations = []
    for name in names:
        ids = np.concatenate([i for i, _ in per_camera[name]])
        pixels = np.concatenate([px for _, px in per_camera[name]])
        if len(ids):
            observations.append(Observation(name, "calibration", FRAME, ids, pixels))
    log.info("%s: %d cameras, %d body points on %d plane(s) (from %s)", root, len(names), len(body), len(planes),
             source.name)
    target = Target(type="points3d", points={k: tuple(float(c) for c in v) for k, v in sorted(body.items())})
    return Dataset(root=root, rig_path=root / "rig.yaml", target=target,
                   interface=interface, cameras=cameras,
                   calibration=(Entry("calibration", FRAME),), observations=tuple(observations))


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
    return root / "parameters" / "ptv.par"


def _max_id(planes: list[list[PlaneFiles]]) -> int:
    """The largest point id of all planes' .fix files (for the id step between planes)."""
    return max(max(read_points(f.fix, 3)) for plane in planes for f in plane)


def import_experiment(root: str | Path, out: str | Path) -> Path:
    """Write the dataset of an OpenPTV experiment to the new folder ``out`` (rig.yaml and
    observations.json, written in a temporary folder beside it, then renamed). Returns the rig path."""
    from ari_sfm.io import save_rig

    out = Path(os.path.abspath(out))
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise AriSfmError(out, "already exists and is not empty: give a new folder")
    dataset = read_experiment(root)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; the dataset is an ordinary folder
        try:
            save_rig(tmp / "rig.yaml", dataset)
        except AriSfmError as exc:  # named the temporary rig.yaml, deleted below: name the OpenPTV file instead
            if exc.path is None or Path(exc.path).parent != tmp:
                raise
            raise AriSfmError(_source_of(exc.message, Path(os.path.abspath(root)), dataset),
                              f"not importable: {exc.message}") from None
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out / "rig.yaml"

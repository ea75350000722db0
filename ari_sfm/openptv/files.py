"""OpenPTV's text files, read and written as liboptv reads and writes them.

Formats (liboptv ``parameters.c``, ``calibration.c``; pyptv's multi-plane calibration):

- ``parameters/ptv.par`` (``read_control_par``): number of cameras; per camera the
  image base name and the calibration image name (the Tcl/Tk layout pads these to
  four cameras); then hp_flag, allCam_flag, tiff_flag, imx, imy (pixels), pix_x,
  pix_y (mm), chfield (interlace), n1 (camera side), n2 (glass), n3 (medium),
  d (glass thickness, mm): one value a line.
- ``parameters/cal_ori.par``: the target (fix) file; per camera the calibration
  image and its ``.ori`` file; tiff_flag, pair_flag, chfield.
- ``parameters/multi_planes.par``: number of planes, then one base name a plane;
  plane p of camera k is ``<base>k.tif.fix`` (id x y z, mm) and ``<base>k.tif.crd``
  (id x y, OpenPTV pixels).
- ``<cal image>.ori`` (``read_ori``): x0 y0 z0 omega phi kappa, the 3 x 3 matrix
  dm, xh yh cc, the glass vector: 21 numbers.
- ``<cal image>.addpar``: k1 k2 k3 p1 p2 scx she (absent: liboptv's defaults,
  no distortion, scx = 1).
- ``parameters/man_ori.par``: the 4 body point ids clicked in each camera, one a
  line, camera after camera; ``man_ori.dat`` (the experiment folder, where the GUI
  writes it, or ``parameters/``): their pixels, ``x y`` a line in the same order
  (OpenPTV pixels). The Tcl/Tk GUI pads both to four cameras.
- ``parameters/targ_rec.par`` (``read_target_par``): the particle detector's
  integers: four grey thresholds (one a camera, the file always holds four),
  discont, nnmin nnmax (pixels a target), nxmin nxmax, nymin nymax (its width
  and height, px), sumg_min (grey sum), cr_sz (cross size, drawing only).

Every reader raises :class:`~ari_sfm.errors.AriSfmError` naming the file.
"""
from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ari_sfm.errors import AriSfmError

log = logging.getLogger(__name__)

CONTROL_NUMBERS = ("hp_flag", "allCam_flag", "tiff_flag", "imx", "imy", "pix_x", "pix_y", "chfield",
                   "n1", "n2", "n3", "d")
CAL_ORI_FLAGS = ("tiff_flag", "pair_flag", "chfield")
ADDPAR_NAMES = ("k1", "k2", "k3", "p1", "p2", "scx", "she")
TCL_CAMERAS = 4  # the Tcl/Tk GUI pads the name lines of ptv.par / cal_ori.par to four cameras


@dataclass(frozen=True)
class ControlPar:
    """``ptv.par``: image names, image size (px), pixel size (mm) and the multimedia part."""

    image_names: tuple[str, ...]
    cal_image_names: tuple[str, ...]
    flags: tuple[int, int, int]  # hp_flag, allCam_flag, tiff_flag
    imx: int
    imy: int
    pix_x: float
    pix_y: float
    chfield: int
    n1: float
    n2: float
    n3: float
    d: float

    @property
    def num_cams(self) -> int:
        return len(self.cal_image_names)


@dataclass(frozen=True)
class Orientation:
    """One ``.ori`` file: exterior (x0, angles in rad, dm), interior (xh, yh, cc in mm), glass vector."""

    position: np.ndarray  # (3,) x0 y0 z0
    angles: np.ndarray  # (3,) omega phi kappa (rad)
    dm: np.ndarray  # (3, 3) as written in the file (liboptv recomputes it from the angles)
    xh: float
    yh: float
    cc: float
    glass: np.ndarray  # (3,)


@dataclass(frozen=True)
class AddPar:
    """``.addpar``: Brown distortion (mm units) and the affine scx, she (rad)."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    scx: float = 1.0
    she: float = 0.0

    def is_identity(self) -> bool:
        return self == AddPar()


def _lines(path: Path) -> list[str]:
    """The non-blank lines of a text file (stripped)."""
    if not path.is_file():
        raise AriSfmError(path, "file not found")
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise AriSfmError(path, f"cannot read file: {exc.strerror or exc}") from None
    return [line.strip() for line in text.splitlines() if line.strip()]


def _number(token: str, path: Path, what: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise AriSfmError(path, f"{what}: {token!r} is not a number") from None
    if not math.isfinite(value):
        raise AriSfmError(path, f"{what}: {token!r} is not finite")
    return value


def _integer(token: str, path: Path, what: str) -> int:
    value = _number(token, path, what)
    if value != int(value):
        raise AriSfmError(path, f"{what}: {token!r} is not an integer")
    return int(value)


def _numbers(path: Path, count: int, what: str) -> list[float]:
    """All whitespace-separated numbers of a file (fscanf style), exactly ``count`` of them."""
    tokens = " ".join(_lines(path)).split()
    if len(tokens) != count:
        raise AriSfmError(path, f"expected {count} numbers ({what}), found {len(tokens)}")
    return [_number(t, path, f"number {i + 1}") for i, t in enumerate(tokens)]


# --------------------------------------------------------------------------- ptv.par


def read_control_par(path: Path) -> ControlPar:
    """``parameters/ptv.par`` (see the module docstring)."""
    lines = _lines(path)
    if not lines:
        raise AriSfmError(path, "empty file")
    n = _integer(lines[0].split()[0], path, "line 1 (number of cameras)")
    if n < 1:
        raise AriSfmError(path, f"line 1: number of cameras must be >= 1 (got {n})")
    names = len(lines) - 1 - len(CONTROL_NUMBERS)
    allowed = {2 * n, 2 * max(n, TCL_CAMERAS)}
    if names not in allowed:
        raise AriSfmError(path, f"{len(lines)} lines for {n} cameras: expected {1 + 2 * n + len(CONTROL_NUMBERS)} "
                                f"(number of cameras, two names a camera, {len(CONTROL_NUMBERS)} values)")
    name_lines = lines[1:1 + 2 * n]
    tail = lines[1 + names:]
    values: dict[str, float] = {}
    integers: dict[str, int] = {}
    for i, (key, line) in enumerate(zip(CONTROL_NUMBERS, tail)):
        where = f"line {2 + names + i} ({key})"
        token = line.split()[0]
        if key.startswith(("pix", "n", "d")):
            values[key] = _number(token, path, where)
        else:
            integers[key] = _integer(token, path, where)
    par = ControlPar(tuple(name_lines[0::2]), tuple(name_lines[1::2]),
                     (integers["hp_flag"], integers["allCam_flag"], integers["tiff_flag"]),
                     integers["imx"], integers["imy"], values["pix_x"], values["pix_y"], integers["chfield"],
                     values["n1"], values["n2"], values["n3"], values["d"])
    if par.imx < 1 or par.imy < 1:
        raise AriSfmError(path, f"image size must be positive (got {par.imx} x {par.imy})")
    if par.pix_x <= 0 or par.pix_y <= 0:
        raise AriSfmError(path, f"pixel size must be > 0 mm (got {par.pix_x:g} x {par.pix_y:g})")
    for key in ("n1", "n2", "n3"):
        if getattr(par, key) < 1.0:
            raise AriSfmError(path, f"refractive index {key} must be >= 1 (got {getattr(par, key):g})")
    if par.d < 0:
        raise AriSfmError(path, f"glass thickness d must be >= 0 mm (got {par.d:g})")
    return par


def format_control_par(par: ControlPar) -> str:
    """``ptv.par`` text, the line layout ``read_control_par`` expects (no padding)."""
    lines = [str(par.num_cams)]
    for img, cal in zip(par.image_names, par.cal_image_names):
        lines += [img, cal]
    lines += [str(f) for f in par.flags]
    lines += [str(par.imx), str(par.imy), repr(par.pix_x), repr(par.pix_y), str(par.chfield),
              repr(par.n1), repr(par.n2), repr(par.n3), repr(par.d)]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- cal_ori.par, multi_planes.par


@dataclass(frozen=True)
class CalOriPar:
    """``cal_ori.par``: the target (fix) file and, per camera, the calibration image and .ori file."""

    fixp_name: str
    img_names: tuple[str, ...]
    ori_names: tuple[str, ...]


def read_cal_ori_par(path: Path, num_cams: int) -> CalOriPar:
    lines = _lines(path)
    pairs = len(lines) - 1 - len(CAL_ORI_FLAGS)
    if pairs not in {2 * num_cams, 2 * max(num_cams, TCL_CAMERAS)}:
        raise AriSfmError(path, f"{len(lines)} lines for {num_cams} cameras: expected {2 + 2 * num_cams + 2} "
                                "(target file, image and .ori a camera, 3 flags)")
    names = lines[1:1 + 2 * num_cams]
    return CalOriPar(lines[0], tuple(names[0::2]), tuple(names[1::2]))


def read_multi_planes_par(path: Path) -> tuple[str, ...]:
    lines = _lines(path)
    if not lines:
        raise AriSfmError(path, "empty file")
    n = _integer(lines[0], path, "line 1 (number of planes)")
    if n < 1 or len(lines) < n + 1:
        raise AriSfmError(path, f"{len(lines)} lines: expected the number of planes ({lines[0]}) and one name a plane")
    if len(lines) > n + 1:
        log.warning("%s: %d names after the count %d: the first %d are read (as liboptv does)", path,
                    len(lines) - 1, n, n)
    return tuple(lines[1:n + 1])


# --------------------------------------------------------------------------- targ_rec.par


TARGET_PAR_NAMES = ("gvthres1", "gvthres2", "gvthres3", "gvthres4", "discont", "nnmin", "nnmax", "nxmin", "nxmax",
                    "nymin", "nymax", "sumg_min", "cr_sz")


@dataclass(frozen=True)
class TargetPar:
    """``targ_rec.par`` (liboptv's target_par): what ``target_recognition`` keeps (grey levels of the
    high-passed image; pixels above the camera's threshold, 4-connected to a peak)."""

    gvthres: tuple[int, int, int, int]  # grey threshold per camera (the file holds four)
    discont: int  # a neighbour joins a target while at most this many levels above the pixel it grows from
    nnmin: int  # pixels a target, at least
    nnmax: int  # and at most
    nxmin: int  # its width (px), at least
    nxmax: int
    nymin: int  # its height (px), at least
    nymax: int
    sumg_min: int  # the grey sum of its pixels must exceed this
    cr_sz: int  # the GUI's cross size (drawing only)


def read_target_par(path: Path) -> TargetPar:
    """Read ``parameters/targ_rec.par`` (or detect_plate.par, the same layout).

    The file holds 13 integers, whitespace-separated, in liboptv's order (``read_target_par``); numbers
    after them are ignored (with a warning), as liboptv does.

    Args:
        path: the file.

    Returns:
        The detector's parameters.

    Raises:
        AriSfmError: too few integers, a negative one, or a minimum above its maximum.
    """
    path = Path(path)
    tokens = " ".join(_lines(path)).split()
    if len(tokens) < len(TARGET_PAR_NAMES):
        raise AriSfmError(path, f"expected {len(TARGET_PAR_NAMES)} integers (4 grey thresholds, discont, nnmin nnmax, "
                                f"nxmin nxmax, nymin nymax, sumg_min, cr_sz), found {len(tokens)}")
    if len(tokens) > len(TARGET_PAR_NAMES):
        log.warning("%s: %d numbers: the first %d are read (as liboptv does)", path, len(tokens),
                    len(TARGET_PAR_NAMES))
    v = [_integer(t, path, name) for t, name in zip(tokens, TARGET_PAR_NAMES)]
    par = TargetPar(tuple(v[0:4]), *v[4:])  # type: ignore[arg-type]
    for name, value in zip(TARGET_PAR_NAMES, v):
        if value < 0:
            raise AriSfmError(path, f"{name} must be >= 0 (got {value})")
    for lo, hi in (("nnmin", "nnmax"), ("nxmin", "nxmax"), ("nymin", "nymax")):
        if getattr(par, lo) > getattr(par, hi):
            raise AriSfmError(path, f"{lo} {getattr(par, lo)} above {hi} {getattr(par, hi)}: no target can pass")
    return par


# --------------------------------------------------------------------------- .ori, .addpar


def read_ori(path: Path) -> Orientation:
    v = np.array(_numbers(path, 21, "x0 y0 z0, omega phi kappa, 3 x 3 dm, xh yh cc, glass vector"))
    ori = Orientation(v[0:3], v[3:6], v[6:15].reshape(3, 3), float(v[15]), float(v[16]), float(v[17]), v[18:21])
    if ori.cc <= 0:
        raise AriSfmError(path, f"focal length cc must be > 0 mm (got {ori.cc:g})")
    return ori


def format_ori(ori: Orientation) -> str:
    """``.ori`` text in ``write_ori``'s layout, with more digits (liboptv reads them with %lf)."""
    x0, y0, z0 = ori.position
    om, ph, ka = ori.angles
    rows = "".join(f"    {r[0]:.12f} {r[1]:.12f} {r[2]:.12f}\n" for r in ori.dm)
    g = ori.glass
    return (f"{x0:.10f} {y0:.10f} {z0:.10f}\n    {om:.12f}  {ph:.12f}  {ka:.12f}\n\n{rows}"
            f"\n    {ori.xh:.10f} {ori.yh:.10f}\n    {ori.cc:.10f}\n"
            f"\n    {g[0]:.15f} {g[1]:.15f}  {g[2]:.15f}\n")


def read_addpar(path: Path) -> AddPar:
    """``.addpar``; a missing file gives liboptv's defaults (as ``read_ori`` does)."""
    if not path.is_file():
        log.info("%s: not found, no distortion (liboptv's default)", path)
        return AddPar()
    par = AddPar(*_numbers(path, 7, " ".join(ADDPAR_NAMES)))
    if par.scx <= 0:
        raise AriSfmError(path, f"scx must be > 0 (got {par.scx:g})")
    return par


def format_addpar(par: AddPar) -> str:
    return " ".join(f"{getattr(par, k):.15g}" for k in ADDPAR_NAMES) + "\n"


# --------------------------------------------------------------------------- man_ori.par, man_ori.dat

MAN_ORI_POINTS = 4  # OpenPTV's manual orientation: four clicked points per camera


def read_man_ori(par_path: Path, dat_path: Path, num_cams: int) -> list[dict[int, np.ndarray]]:
    """Read the clicked points of OpenPTV's manual orientation.

    The first ``4 num_cams`` lines of each file are read; more are the GUI's padding. A point at (0, 0)
    was never clicked and is left out.

    Args:
        par_path: ``man_ori.par``, the clicked point ids.
        dat_path: ``man_ori.dat``, their pixels.
        num_cams: the number of cameras.

    Returns:
        Per camera, in order, {id: (x, y) in OpenPTV pixels}.

    Raises:
        AriSfmError: too few lines, a malformed line, or a point listed twice for a camera.
    """
    need = MAN_ORI_POINTS * num_cams
    ids = [line.split()[0] for line in _lines(par_path)]
    if len(ids) < need:
        raise AriSfmError(par_path, f"{len(ids)} ids for {num_cams} cameras: expected {MAN_ORI_POINTS} a camera, "
                                    "one a line")
    pixels = [line.split() for line in _lines(dat_path)]
    if len(pixels) < need:
        raise AriSfmError(dat_path, f"{len(pixels)} lines for {num_cams} cameras: expected {MAN_ORI_POINTS} a camera "
                                    "(x y, one point a line)")
    out: list[dict[int, np.ndarray]] = []
    for cam in range(num_cams):
        points: dict[int, np.ndarray] = {}
        for k in range(cam * MAN_ORI_POINTS, (cam + 1) * MAN_ORI_POINTS):
            pid = _integer(ids[k], par_path, f"line {k + 1} (camera {cam + 1}'s point id)")
            if len(pixels[k]) < 2:
                raise AriSfmError(dat_path, f"line {k + 1}: expected x y, found {len(pixels[k])} number(s)")
            xy = np.array([_number(t, dat_path, f"line {k + 1}") for t in pixels[k][:2]])
            if pid in points:
                raise AriSfmError(par_path, f"line {k + 1}: camera {cam + 1} lists point {pid} twice")
            if np.any(xy != 0.0):
                points[pid] = xy
        out.append(points)
    return out


# --------------------------------------------------------------------------- .fix, .crd


def read_points(path: Path, columns: int) -> dict[int, np.ndarray]:
    """Read a ``.fix`` (id x y z, mm) or ``.crd`` (id x y, OpenPTV pixels) file.

    Args:
        path: the file.
        columns: the coordinates per line: 3 for ``.fix``, 2 for ``.crd``.

    Returns:
        {id: (columns,) coordinates}, in file order.

    Raises:
        AriSfmError: a malformed line, a repeated id, or no point.
    """
    out: dict[int, np.ndarray] = {}
    for i, line in enumerate(_lines(path)):
        tokens = line.split()
        if len(tokens) != columns + 1:
            raise AriSfmError(path, f"line {i + 1}: expected {columns + 1} numbers (id and {columns} coordinates), "
                                    f"found {len(tokens)}")
        pid = _integer(tokens[0], path, f"line {i + 1}: id")
        if pid in out:
            raise AriSfmError(path, f"line {i + 1}: id {pid} repeated")
        out[pid] = np.array([_number(t, path, f"line {i + 1}") for t in tokens[1:]])
    if not out:
        raise AriSfmError(path, "no points")
    return out


def update_control_par(path: Path, par: ControlPar) -> str:
    """Write new values into the numeric lines of an existing ``ptv.par``.

    The name lines (and any Tcl/Tk padding of them) are kept as they are.

    Args:
        path: the existing ptv.par.
        par: the values to write.

    Returns:
        The file's new text (not written).

    Raises:
        AriSfmError: the existing file cannot be read or is malformed.
    """
    lines = _lines(path)
    read_control_par(path)  # the layout is valid
    tail = len(lines) - len(CONTROL_NUMBERS)
    values = [*par.flags, par.imx, par.imy, repr(par.pix_x), repr(par.pix_y), par.chfield,
              repr(par.n1), repr(par.n2), repr(par.n3), repr(par.d)]
    lines[tail:] = [str(v) for v in values]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- sequence.par, criteria.par


@dataclass(frozen=True)
class SequencePar:
    """``sequence.par``: each camera's image base name (``img/cam1.%d``, or ``img/cam1.`` with the frame number
    appended as OpenPTV's C code does) and the first and last frame."""

    base_names: tuple[str, ...]
    first: int
    last: int

    def pattern(self, camera: int) -> str:
        """The image name of camera ``camera`` (0-based) with ``{frame}`` for the frame number (Python format)."""
        base = self.base_names[camera].replace("{", "{{").replace("}", "}}")
        spec = re.search(r"%(0?\d*)d", base)
        if spec is None:
            return base + "{frame}"
        width = spec.group(1)
        return base[:spec.start()] + ("{frame:" + width + "d}" if width else "{frame}") + base[spec.end():]


def read_sequence_par(path: Path, num_cams: int) -> SequencePar:
    """Read ``sequence.par`` as liboptv's ``read_sequence_par`` does.

    The file holds ``num_cams`` base names (the Tcl/Tk layout pads them to four), then the first and last
    frame.

    Args:
        path: the file.
        num_cams: the number of cameras.

    Returns:
        The base names and the frame range.

    Raises:
        AriSfmError: another number of lines, or frames not in order or negative.
    """
    lines = _lines(path)
    if len(lines) not in {num_cams + 2, max(num_cams, TCL_CAMERAS) + 2}:
        raise AriSfmError(path, f"{len(lines)} lines for {num_cams} cameras: expected {num_cams + 2} (a base name "
                                "a camera, the first and the last frame)")
    first = _integer(lines[-2], path, "first frame")
    last = _integer(lines[-1], path, "last frame")
    if last < first or first < 0:
        raise AriSfmError(path, f"frames {first}..{last}: the last must not come before the first, both >= 0")
    return SequencePar(tuple(lines[:num_cams]), first, last)


@dataclass(frozen=True)
class VolumePar:
    """``criteria.par``'s observation volume (liboptv's ``read_volume_par``): at x = X_lay[0] and X_lay[1]
    the depth range Zmin_lay..Zmax_lay (OpenPTV's world, mm); then the correspondence criteria."""

    x_lay: tuple[float, float]
    z_min_lay: tuple[float, float]
    z_max_lay: tuple[float, float]
    cnx: float
    cny: float
    cn: float
    csumg: float
    corrmin: float
    eps0: float  # the epipolar band's half width, mm on the sensor


def read_volume_par(path: Path) -> VolumePar:
    """Read ``criteria.par``, in liboptv's order.

    The order: X_lay[0], Zmin_lay[0], Zmax_lay[0], X_lay[1], Zmin_lay[1], Zmax_lay[1], cnx, cny, cn,
    csumg, corrmin, eps0.

    Args:
        path: the file.

    Returns:
        The observation volume and the correspondence criteria.

    Raises:
        AriSfmError: not 12 numbers, or an empty observation volume.
    """
    v = _numbers(path, 12, "X, Zmin, Zmax of two layers and six correspondence criteria")
    if not (v[0] < v[3] and v[1] < v[2] and v[4] < v[5]):
        raise AriSfmError(path, f"the observation volume is empty (x {v[0]:g}..{v[3]:g}, z {v[1]:g}..{v[2]:g} and "
                                f"{v[4]:g}..{v[5]:g})")
    return VolumePar((v[0], v[3]), (v[1], v[4]), (v[2], v[5]), *v[6:])

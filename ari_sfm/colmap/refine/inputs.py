"""refine-colmap's inputs, checked: the COLMAP model (readable, finite, redundant enough) and its scale
(units_mm, a scale bar or a baseline, resolved into mm per model unit and the solver's terms)."""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.colmap import adapter
from ari_sfm.errors import AriSfmError, ErrorPath

from .options import Backend, RefineColmapOptions
from .paraxial import initial_state
from .scale_bar import Baseline, ScaleBar

log = logging.getLogger(__name__)

MODEL_FILES = ("cameras", "images", "points3D")
MIN_REDUNDANCY = 1.5  # observations (coordinates) per unknown below which refine-colmap refuses
MAX_COORDINATE_MM = 1e9  # 1000 km: a units_mm beyond this is a typo
EDGE_TOLERANCE_PX = 1.0  # a keypoint this far beyond the image's edge is kept (sub-pixel centres)


def read_model(path: Path) -> Any:
    """A COLMAP model folder as a pycolmap.Reconstruction.

    Args:
        path: the model folder (cameras, images, points3D as .bin or .txt).

    Returns:
        The reconstruction.

    Raises:
        AriSfmError: one line naming the folder or the file that is missing, unreadable or truncated (a binary
            file must be what pycolmap writes back from it).
    """
    import tempfile

    if not path.is_dir():
        raise AriSfmError(path, "not a COLMAP model folder" + (" (it is a file)" if path.exists() else " (missing)"))
    text = (sum((path / f"{n}.txt").exists() for n in MODEL_FILES)
            > sum((path / f"{n}.bin").exists() for n in MODEL_FILES))
    kind = "txt" if text else "bin"
    for n in MODEL_FILES:
        f = path / f"{n}.{kind}"
        if not f.is_file():
            raise AriSfmError(f, "not a file" if f.exists() else
                              "missing: a COLMAP model folder holds cameras, images and points3D (.bin or .txt)")
        if not os.access(path / f"{n}.{kind}", os.R_OK):
            raise AriSfmError(path / f"{n}.{kind}", "no permission to read")
    try:
        rec = adapter.read_colmap(path)
    except AriSfmError:
        raise
    except Exception as exc:  # noqa: BLE001 - pycolmap's reader raises plain errors for damaged files
        why = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise AriSfmError(path, f"cannot read the COLMAP model (a truncated or damaged file?): {why}") from None
    if kind == "bin":  # a truncated file reads as fewer or garbled records: compare with what they write back
        with tempfile.TemporaryDirectory() as tmp:
            rec.write(tmp)
            for n in MODEL_FILES + ("rigs", "frames"):
                f, back = path / f"{n}.bin", Path(tmp) / f"{n}.bin"
                if f.is_file() and back.is_file() and f.stat().st_size != back.stat().st_size:
                    raise AriSfmError(f, f"truncated or damaged: its {f.stat().st_size} bytes read as records that "
                                         f"take {back.stat().st_size}")
    return rec


def check_redundancy(model: adapter.ColmapModel, path: ErrorPath) -> None:
    """Refuse a model with too few observations for its unknowns (it would "converge" to 0 px).

    Args:
        model: the COLMAP model.
        path: the model named in the error.
    """
    unknowns = (sum(len(p) for p in model.colmap_params) + 6 * (len(model.frame_ids) - 1) + 3
                + 3 * len(model.point3D_ids))
    coordinates = 2 * len(model.obs_point)
    if coordinates < MIN_REDUNDANCY * unknowns:
        raise AriSfmError(path, f"too few observations to refine: {len(model.point3D_ids)} points3D seen "
                                f"{len(model.obs_point)} times give {coordinates} coordinates for {unknowns} unknowns "
                                f"(cameras, poses, window, points); at least {MIN_REDUNDANCY:g} per unknown needed")


def check_finite(model: adapter.ColmapModel, path: ErrorPath) -> None:
    """One line naming the first point3D, camera or image with a non-finite value, or a keypoint off its image.

    Args:
        model: the COLMAP model.
        path: the model named in the error.
    """
    bad = np.flatnonzero(~np.all(np.isfinite(model.xyz), axis=1))
    if len(bad):
        raise AriSfmError(path, f"point3D {int(model.point3D_ids[bad[0]])} has a non-finite position "
                                f"({len(bad)} such points3D)")
    for c, p in enumerate(model.colmap_params):
        if not np.all(np.isfinite(p)):
            raise AriSfmError(path, f"camera {int(model.camera_ids[c])}: non-finite parameters {p.tolist()}")
    for f, pose in enumerate(model.rig_from_world):
        if not (np.all(np.isfinite(pose.R)) and np.all(np.isfinite(pose.t))):
            raise AriSfmError(path, f"frame {int(model.frame_ids[f])}: non-finite pose")
    if not np.all(np.isfinite(model.obs_uv)):
        raise AriSfmError(path, "an image has a non-finite keypoint observed by a point3D")
    size = np.array(model.image_sizes, float)[model.image_camera[model.obs_image]]  # (M, 2) width, height
    outside = np.any((model.obs_uv < -0.5 - EDGE_TOLERANCE_PX) | (model.obs_uv > size - 0.5 + EDGE_TOLERANCE_PX),
                     axis=1)
    if outside.any():
        k = int(np.argmax(outside))
        i = int(model.obs_image[k])
        raise AriSfmError(path, f"image {model.image_names[i]}: a keypoint observed by point3D "
                                f"{int(model.point3D_ids[model.obs_point[k]])} at ({model.obs_uv[k, 0]:.6g}, "
                                f"{model.obs_uv[k, 1]:.6g}) px is outside its {int(size[k, 0])} x {int(size[k, 1])} "
                                f"image ({int(outside.sum())} such observations)")


def check_scale_options(options: RefineColmapOptions, path: ErrorPath, window_path: ErrorPath) -> None:
    """The scale given once, and a baseline only where the solver holds it.

    Args:
        options: the options.
        path: the model named in errors about the backend.
        window_path: the file named in errors about the scale.
    """
    if options.baseline is not None and (options.units_mm is not None or options.scale_bar is not None):
        raise AriSfmError(window_path, "gives units_mm or scale_bar and a baseline gives the scale too: give it once")
    if options.baseline is not None and options.backend != Backend.NUMPY:
        raise AriSfmError(path, "baseline: a term of the numpy backend only (backend numpy, or a scale_bar)")


def units_mm(model: adapter.ColmapModel, units: float | None, scale_bar: tuple[int, int, float] | None,
             path: ErrorPath, baseline: Baseline | None = None) -> float:
    """mm per unit of the COLMAP model: from the baseline, the scale bar or ``units`` (else 1, with a warning).

    Args:
        model: the COLMAP model as COLMAP left it.
        units: the given mm per model unit, if any.
        scale_bar: ``(point3D_id, point3D_id, mm)``, if any.
        path: the WINDOW.yaml named in errors.
        baseline: the scale from two images' camera centres, if any (it wins).

    Returns:
        mm per model unit.
    """
    if baseline is not None:
        start = initial_state(model, "camera", 1.0)
        length = baseline.length(start)
        if not length > 0:
            raise AriSfmError(path, f"baseline: images {model.image_names[baseline.a]} and "
                                    f"{model.image_names[baseline.b]} have the same camera centre in the model")
        factor = baseline.length_mm / length
    elif scale_bar is not None:
        a, b, mm = scale_bar
        where = {int(p): k for k, p in enumerate(model.point3D_ids)}
        missing = [int(i) for i in (a, b) if int(i) not in where]
        if missing:
            raise AriSfmError(path,
                              f"scale_bar.point3D_ids: {', '.join(map(str, missing))} not in the model's points3D")
        if int(a) == int(b):
            raise AriSfmError(path, "scale_bar.point3D_ids: the two ids are the same point")
        length = float(np.linalg.norm(model.xyz[where[int(a)]] - model.xyz[where[int(b)]]))
        if not length > 0 or not mm > 0:
            raise AriSfmError(path, "scale_bar: its points coincide in the model or its distance_mm is not positive")
        factor = mm / length
    elif units is None:
        log.warning("refine-colmap: no units_mm or scale bar: the COLMAP model's units are taken as mm")
        factor = 1.0
    elif not units > 0:
        raise AriSfmError(path, f"units_mm must be > 0, got {units}")
    else:
        factor = float(units)
    extent = float(np.max(np.abs(model.xyz))) * factor
    if not (np.isfinite(factor) and np.isfinite(extent) and extent < MAX_COORDINATE_MM):
        what = "baseline" if baseline is not None else "scale_bar" if scale_bar is not None else "units_mm"
        raise AriSfmError(path, f"{what}: {factor:.6g} mm per model unit puts the model's points up to {extent:.3g} "
                                f"mm from its origin (more than {MAX_COORDINATE_MM:.0e} mm)")
    return factor


def baseline_term(model: adapter.ColmapModel, baseline: tuple[str | int, str | int, float],
                  path: ErrorPath) -> Baseline:
    """The baseline term of two images named by their names (or COLMAP image ids) and their centres' distance.

    Args:
        model: the COLMAP model.
        baseline: ``(image, image, mm)``.
        path: the file named in errors.

    Returns:
        The solver's baseline term.
    """
    a, b, mm = baseline
    index = {}
    for name in (a, b):
        hits = np.flatnonzero(model.image_ids == name) if isinstance(name, (int, np.integer)) else \
            [k for k, n in enumerate(model.image_names) if n == str(name)]
        if len(hits) == 0:
            raise AriSfmError(path, f"baseline: image {name} is not among the model's (registered) images")
        index[name] = int(hits[0])
    if index[a] == index[b]:
        raise AriSfmError(path, f"baseline: names image {a} twice (two images are needed)")
    if not (np.isfinite(mm) and mm > 0):
        raise AriSfmError(path, f"baseline: the distance must be a positive number of mm (got {mm})")
    i, j = index[a], index[b]
    return Baseline(i, j, (int(model.image_frame[i]), int(model.image_frame[j])),
                    (int(model.image_camera[i]), int(model.image_camera[j])), float(mm))


@dataclass(frozen=True)
class Scale:
    """The scale of a refinement: mm per model unit and the solver's term holding it (a bar or a baseline)."""

    units_mm: float
    bar: ScaleBar | None = None
    baseline: Baseline | None = None

    @property
    def held_by(self) -> str | None:
        """``bar`` or ``baseline``: the term of the solver holding the scale; None when refraction alone does."""
        return "bar" if self.bar is not None else "baseline" if self.baseline is not None else None


def resolve_scale(model: adapter.ColmapModel, options: RefineColmapOptions, path: ErrorPath,
                  window_path: ErrorPath) -> Scale:
    """The scale the options give, checked: mm per model unit, the scale bar and the baseline terms.

    Args:
        model: the COLMAP model as COLMAP left it.
        options: the options (units_mm, scale_bar, baseline).
        path: the model named in errors about the baseline's images.
        window_path: the WINDOW.yaml named in errors about units and the scale bar.

    Returns:
        The scale.
    """
    base = None if options.baseline is None else baseline_term(model, options.baseline, path)
    units = units_mm(model, options.units_mm, options.scale_bar, window_path, base)
    bar = None
    if options.scale_bar is not None:
        where = {int(p): k for k, p in enumerate(model.point3D_ids)}
        bar = ScaleBar(where[int(options.scale_bar[0])], where[int(options.scale_bar[1])],
                       float(options.scale_bar[2]))
    return Scale(units, bar, base)

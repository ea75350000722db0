"""``ari-sfm sfm``: images taken behind a flat window -> COLMAP's SfM -> the exact refractive refinement.

    ari-sfm sfm IMAGES --window WINDOW.yaml -o OUT

Steps: COLMAP's CPU SIFT features, matching (exhaustive, or sequential for long image sequences),
incremental mapping (one PINHOLE camera shared by all images: a camera in its housing), all through
the pycolmap adapter (:func:`ari_sfm.colmap_export.structure_from_motion`); then refine-colmap
(:func:`ari_sfm.colmap_refine.refine_colmap`) with the WINDOW.yaml plate and mount.

OUT gets ``colmap/`` (COLMAP's database and its pinhole model, ``colmap/sparse/<n>``), ``refined/``
(refine-colmap's outputs: the COLMAP model of the refined cameras, calibration.json, refine.json)
and ``sfm.json`` (what ran, counts, times). COLMAP's work happens in ``OUT/colmap.partial`` and is
renamed when it succeeds: a failed run leaves no half-made model behind.

Scale (required: COLMAP's model has no unit, and refraction through a plate of so many mm depends on
it): WINDOW.yaml's ``units_mm`` or ``scale_bar``, or a known distance between two images' camera
centres (``baseline``, e.g. from navigation), held by the refinement as a term of its solver (the result
keeps it).
"""
from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .colmap_refine import settings as REFINE
from .errors import AriSfmError

if TYPE_CHECKING:
    from .colmap_refine.refine import RefineResult

log = logging.getLogger(__name__)

MIN_IMAGES = 3  # images in the folder, and images COLMAP must register, for a refinement
EXHAUSTIVE_MAX_IMAGES = 200  # matcher "auto": exhaustive up to this many images, sequential beyond
SFM_FORMAT = "ari-sfm-sfm/1"


@dataclass(frozen=True)
class SfmOptions:
    """Options of :func:`run_sfm`, each with its default."""

    matcher: str = "auto"  # exhaustive | sequential | auto (exhaustive up to EXHAUSTIVE_MAX_IMAGES images)
    overlap: int = 10  # sequential matching: each image with this many successors (name order)
    max_features: int = 4000  # SIFT features per image
    focal_px: float | None = None  # the camera's focal length prior (px); None: COLMAP's (1.2 x the larger side)
    baseline: tuple[str, str, float] | None = None  # (image name, image name, mm between their camera centres)
    huber_px: float = REFINE.HUBER_PX  # refine-colmap's Huber threshold
    max_iterations: int = REFINE.MAX_ITERATIONS  # refine-colmap's cap on accepted LM steps
    num_threads: int = -1  # COLMAP's threads; -1: all cores
    seed: int = 0  # COLMAP's mapper random seed
    progress: bool = False  # a progress bar while the mapper registers images


@dataclass(frozen=True)
class SfmResult:
    """What :func:`run_sfm` made."""

    images: int  # in the folder
    registered: int  # registered by COLMAP
    points3D: int
    colmap_model: Path  # COLMAP's own (pinhole) model
    refined: Path  # refine-colmap's outputs
    summary_path: Path  # sfm.json
    refine: RefineResult  # its report: refine.json's record (RefineResult.report)


def list_images(folder: Path) -> list[Path]:
    """The image files COLMAP will read in ``folder`` (checked: a folder with at least MIN_IMAGES)."""
    from .colmap_export import SFM_IMAGE_SUFFIXES

    if not folder.is_dir():
        raise AriSfmError(folder, "no such folder of images" if not folder.exists() else "is a file, expected a "
                                                                                         "folder of images")
    images = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SFM_IMAGE_SUFFIXES)
    if not images:
        raise AriSfmError(folder, f"no images ({', '.join(SFM_IMAGE_SUFFIXES)}) in this folder")
    if len(images) < MIN_IMAGES:
        raise AriSfmError(folder, f"{len(images)} image(s): structure from motion needs at least {MIN_IMAGES}")
    return images


def check_sfm_paths(images: Path, out: Path) -> None:
    """-o must not be the images folder nor inside it (COLMAP would find our files among the images)."""
    img, o = Path(os.path.realpath(images)), Path(os.path.realpath(out))
    if o == img or img in o.parents:
        raise AriSfmError(out, "-o/--out: is (inside) the images folder: choose a folder outside it")


def run_sfm(images: str | Path, window: str | Path, out: str | Path, options: SfmOptions = SfmOptions()) -> SfmResult:
    """Structure from motion behind a flat window: COLMAP's SfM, then refine-colmap; see the module docstring."""
    from .colmap_export import structure_from_motion
    from .colmap_refine import refine_colmap, write_refined
    from .colmap_refine.window import load_window
    from .io import write_json_atomic

    images, window, out = Path(images), Path(window), Path(out)
    check_sfm_paths(images, out)
    files = list_images(images)
    spec = load_window(window)  # before any COLMAP work
    if options.baseline is not None and (spec.units_mm is not None or spec.scale_bar is not None):
        raise AriSfmError(window, "gives units_mm or scale_bar and --baseline gives the scale too: give it once")
    if options.baseline is None and spec.units_mm is None and spec.scale_bar is None:
        raise AriSfmError(window, "no scale: COLMAP's model has no unit and the refraction depends on it (the plate "
                                  "is in mm): give units_mm or scale_bar here, or --baseline IMAGE IMAGE MM")
    if options.baseline is not None:
        names = {p.name for p in files}
        missing = [n for n in options.baseline[:2] if n not in names]
        if missing:
            raise AriSfmError(images, f"--baseline: no image {missing[0]} in this folder")
    matcher = options.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(files) <= EXHAUSTIVE_MAX_IMAGES else "sequential"
    if matcher not in ("exhaustive", "sequential"):
        raise AriSfmError(None, f"--matcher must be exhaustive, sequential or auto (got {options.matcher!r})")

    partial, final = out / "colmap.partial", out / "colmap"
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    if partial.exists():
        shutil.rmtree(partial)
    t0 = time.perf_counter()
    times: dict[str, float] = {}
    bar = None  # progress: one bar for the steps, then the images the mapper registers
    what = {"features": f"SIFT features of {len(files)} images (CPU)", "matching": f"{matcher} matching",
            "mapping": "incremental mapping"}
    clock = {"step": None, "t": t0}

    def on_step(name: str) -> None:
        nonlocal bar
        now = time.perf_counter()
        if clock["step"] is not None:
            times[clock["step"]] = now - clock["t"]
        clock.update(step=name, t=now)
        log.info("COLMAP %s (%s)", what[name], images)
        if options.progress:
            from tqdm import tqdm

            if bar is not None:
                bar.close()
            mapping = name == "mapping"
            bar = tqdm(total=len(files) if mapping else None, desc=f"COLMAP {what[name]}", leave=False,
                       unit="image" if mapping else "it", bar_format=None if mapping else "{desc} ({elapsed})")

    try:
        try:
            rec = structure_from_motion(images, partial, focal_px=options.focal_px, max_features=options.max_features,
                                        seed=options.seed, matcher=matcher, overlap=options.overlap,
                                        num_threads=options.num_threads, on_step=on_step,
                                        on_image=(lambda: bar.update(1)) if bar is not None else None)
        except AriSfmError:  # the mapper reconstructed nothing
            raise AriSfmError(images, f"COLMAP registered none of the {len(files)} images (at least {MIN_IMAGES} "
                                      "needed): the images need more overlap or texture") from None
        finally:
            if bar is not None:
                bar.close()
        times["mapping"] = time.perf_counter() - clock["t"]
        registered = rec.num_reg_images()
        if registered < MIN_IMAGES:
            raise AriSfmError(images, f"COLMAP registered {registered} of {len(files)} images (at least {MIN_IMAGES} "
                                      "needed): the images need more overlap or texture")
        t_refine = time.perf_counter()
        log.info("refine-colmap: %d images, %d points, the exact refractive model", registered, rec.num_points3D())
        result = refine_colmap(rec, spec.interface, mount=spec.mount, units_mm=spec.units_mm, scale_bar=spec.scale_bar,
                               baseline=options.baseline,
                               huber_px=options.huber_px, max_iterations=options.max_iterations,
                               progress=options.progress, path=images, plane_path=window)
        times["refine"] = time.perf_counter() - t_refine
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        if created and out.exists() and not any(out.iterdir()):
            out.rmdir()
        raise
    if final.exists():
        shutil.rmtree(final)
    partial.rename(final)
    model_dirs = sorted(p for p in (final / "sparse").iterdir() if p.is_dir()) if (final / "sparse").is_dir() else []
    colmap_model = next((p for p in model_dirs if _same_model(p, rec)), model_dirs[0] if model_dirs else final)
    refined = write_refined(result, out / "refined")
    summary = out / "sfm.json"
    write_json_atomic(summary, {
        "format": SFM_FORMAT,
        "images": str(images.resolve()), "window": str(window.resolve()),
        "matcher": matcher, "num_images": len(files), "registered": registered, "points3D": rec.num_points3D(),
        "units_mm": result.report.units_mm, "scale": "units_mm" if spec.units_mm is not None else
        "scale_bar" if spec.scale_bar is not None else "baseline" if options.baseline is not None else None,
        "baseline": None if result.report.baseline is None else result.report.baseline.to_json(),
        "colmap_model": str(colmap_model.relative_to(out)), "refined": "refined",
        "time_s": {k: round(v, 3) for k, v in times.items()} | {"total": round(time.perf_counter() - t0, 3)},
    })
    return SfmResult(len(files), registered, rec.num_points3D(), colmap_model, refined, summary, result)


def _same_model(folder: Path, rec: Any) -> bool:
    """Whether the model COLMAP wrote in ``folder`` is ``rec`` (the largest one): same image count."""
    from .colmap_export import read_colmap

    try:
        return read_colmap(folder).num_reg_images() == rec.num_reg_images()
    except Exception:  # noqa: BLE001 - a folder that is not a model is simply not it
        return False

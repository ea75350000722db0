"""``ari-sfm sfm``: images taken behind a flat window -> COLMAP's SfM -> the exact refractive refinement.

    ari-sfm sfm IMAGES --window WINDOW.yaml -o OUT

Steps: COLMAP's CPU SIFT features, matching (exhaustive, or sequential for long image sequences),
incremental mapping (one PINHOLE camera shared by all images: a camera in its housing), all through
the pycolmap adapter (:func:`ari_sfm.colmap.adapter.structure_from_motion`); then refine-colmap
(:func:`ari_sfm.colmap.refine.refine_colmap`) with the WINDOW.yaml plate and mount.

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

from ..errors import AriSfmError
from ..options import Choice
from .refine import settings as REFINE

if TYPE_CHECKING:
    from .refine.refine import RefineResult

log = logging.getLogger(__name__)

MIN_IMAGES = 3  # images in the folder, and images COLMAP must register, for a refinement
EXHAUSTIVE_MAX_IMAGES = 200  # matcher "auto": exhaustive up to this many images, sequential beyond
SFM_FORMAT = "ari-sfm-sfm/1"


class Matcher(Choice):
    """The image pairs COLMAP matches: all of them, or each image with its successors in name order (long
    surveys, no vocabulary tree); auto: exhaustive up to EXHAUSTIVE_MAX_IMAGES images, sequential beyond."""

    AUTO = "auto"
    EXHAUSTIVE = "exhaustive"
    SEQUENTIAL = "sequential"

    def resolved(self, images: int) -> Matcher:
        """The matcher run on ``images`` images (auto resolved).

        Args:
            images: how many images.

        Returns:
            EXHAUSTIVE or SEQUENTIAL.
        """
        if self != Matcher.AUTO:
            return self
        return Matcher.EXHAUSTIVE if images <= EXHAUSTIVE_MAX_IMAGES else Matcher.SEQUENTIAL


@dataclass(frozen=True)
class SfmOptions:
    """Options of :func:`run_sfm`, each with its default (a string mode is converted: ``matcher="auto"``)."""

    matcher: Matcher = Matcher.AUTO  # exhaustive | sequential | auto (exhaustive up to EXHAUSTIVE_MAX_IMAGES images)
    overlap: int = 10  # sequential matching: each image with this many successors (name order)
    max_features: int = 4000  # SIFT features per image
    focal_px: float | None = None  # the camera's focal length prior (px); None: COLMAP's (1.2 x the larger side)
    baseline: tuple[str, str, float] | None = None  # (image name, image name, mm between their camera centres)
    huber_px: float = REFINE.HUBER_PX  # refine-colmap's Huber threshold
    max_iterations: int = REFINE.MAX_ITERATIONS  # refine-colmap's cap on accepted LM steps
    num_threads: int = -1  # COLMAP's threads; -1: all cores
    seed: int = 0  # COLMAP's mapper random seed
    progress: bool = False  # a progress bar while the mapper registers images

    def __post_init__(self) -> None:
        """The matcher's string converted; one that names no matcher is one line of ValueError."""
        object.__setattr__(self, "matcher", Matcher.parse(self.matcher, "matcher"))


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
    unregistered: tuple[str, ...] = ()  # the images COLMAP did not register (names)


def list_images(folder: Path) -> list[Path]:
    """The image files COLMAP will read in ``folder`` (checked: a folder with at least MIN_IMAGES)."""
    from .adapter import SFM_IMAGE_SUFFIXES

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
    """-o must not be the images folder nor inside it (COLMAP would find our files among the images).

    Args:
        images: the images folder.
        out: the output folder.
    """
    img, o = Path(os.path.realpath(images)), Path(os.path.realpath(out))
    if o == img or img in o.parents:
        raise AriSfmError(out, "-o/--out: is (inside) the images folder: choose a folder outside it")


def check_images(files: list[Path]) -> tuple[int, int]:
    """Every image decodes and has the first one's size (one PINHOLE camera for all, as COLMAP is run here).

    Args:
        files: the images.

    Returns:
        (width, height).

    Raises:
        AriSfmError: naming the first bad image (and how many more).
    """
    from PIL import Image, UnidentifiedImageError

    size: tuple[int, int] | None = None
    bad: list[Path] = []
    why: str | None = None
    for path in files:
        try:
            with Image.open(path) as im:
                this = im.size
                im.draft("L", (max(1, this[0] // 8), max(1, this[1] // 8)))  # JPEG: decode at 1/8
                im.load()
        except (OSError, UnidentifiedImageError, ValueError, Image.DecompressionBombError) as exc:
            bad.append(path)
            why = why or f"cannot be read as an image ({exc.__class__.__name__}: {str(exc).splitlines()[0][:80]})"
            continue
        if size is None:
            size = this
        elif this != size:
            bad.append(path)
            why = why or (f"is {this[0]} x {this[1]} px, the first image ({files[0].name}) {size[0]} x {size[1]}: "
                          "one camera takes all the images (resized or cropped?)")
    if bad:
        more = f" (and {len(bad) - 1} more: {', '.join(p.name for p in bad[1:4])}{', ...' if len(bad) > 4 else ''})" \
            if len(bad) > 1 else ""
        raise AriSfmError(bad[0], f"{why}{more}: remove or replace it, structure from motion would drop it")
    if size is None:
        raise ValueError("no image to check")
    return size


FOCAL_RANGE = (0.1, 100.0)  # --focal-px, in units of the images' larger side (fisheye ... 0.6 deg field of view)
MAX_THREADS = 1024


def check_sfm_options(options: SfmOptions, image_size: tuple[int, int] | None = None) -> None:
    """The options' values, before any COLMAP work (COLMAP itself aborts on some, e.g. threads < -1).

    Args:
        options: the options.
        image_size: the images' (width, height), once known: the focal prior is checked against it.
    """
    if options.num_threads != -1 and not 1 <= options.num_threads <= MAX_THREADS:
        raise AriSfmError("--threads", f"must be -1 (all cores) or 1..{MAX_THREADS} (got {options.num_threads})")
    for option, value, low in (("--overlap", options.overlap, 1), ("--max-features", options.max_features, 1),
                               ("--max-iterations", options.max_iterations, 1)):
        if not value >= low:
            raise AriSfmError(option, f"must be >= {low} (got {value})")
    if options.focal_px is not None and image_size is not None:
        side = max(image_size)
        lo, hi = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
        if not lo <= options.focal_px <= hi:
            raise AriSfmError("--focal-px", f"{options.focal_px:g} px is not a focal length of {image_size[0]} x "
                                            f"{image_size[1]} px images ({lo:g} to {hi:g} px)")


def run_sfm(images: str | Path, window: str | Path, out: str | Path, options: SfmOptions = SfmOptions()) -> SfmResult:
    """Structure from motion behind a flat window: COLMAP's SfM, then refine-colmap; see the module docstring.

    Everything is checked before any COLMAP work (the options, the paths, the images, WINDOW.yaml and the
    scale); then the steps (SFM_STEPS: :func:`colmap_step`, :func:`refine_step`) run with ``out`` held.

    Args:
        images: the folder of images (one camera, one size).
        window: WINDOW.yaml (the plate, the mount, the scale unless ``options.baseline`` gives it).
        out: the output folder.
        options: the options.

    Returns:
        The counts, the output paths and refine-colmap's result.
    """
    from ..io import exclusive_folder
    from .refine.window import load_window

    images, window, out = Path(images), Path(window), Path(out)
    check_sfm_options(options)
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
    matcher = options.matcher.resolved(len(files))
    for name in ("colmap.partial", "colmap", "refined"):
        if (out / name).exists() and not (out / name).is_dir():
            raise AriSfmError(out / name, "is a file where sfm writes a folder: move it away or choose another -o")
    check_sfm_options(options, check_images(files))
    with exclusive_folder(out) as held:  # a second sfm into the same -o meanwhile: refused, not interleaved
        return _run_sfm(images, window, out, options, files, spec, matcher, held.created)


class SfmStep(Choice):
    """The steps of ``ari-sfm sfm``, in order."""

    COLMAP = "colmap"  # COLMAP's SfM in a child process (:func:`colmap_step`)
    REFINE = "refine"  # refine-colmap on its model (:func:`refine_step`)


SFM_STEPS = (SfmStep.COLMAP, SfmStep.REFINE)


@dataclass(frozen=True)
class ColmapStep:
    """What COLMAP's SfM left in ``partial``: its largest model, read, and how it went."""

    reconstruction: Any  # pycolmap.Reconstruction: the model with the most registered images (then points)
    model_dir: Path  # its folder (``partial/sparse/<n>``)
    registered: int
    unregistered: tuple[str, ...]  # the images COLMAP did not register (names)
    times: dict[str, float]  # s per COLMAP step: features, matching, mapping


@dataclass(frozen=True)
class RefineStep:
    """refine-colmap's result on COLMAP's model and its time."""

    result: RefineResult
    time_s: float


def colmap_step(images: Path, partial: Path, options: SfmOptions, matcher: Matcher, files: list[Path]) -> ColmapStep:
    """COLMAP's SfM on ``images`` in a child process (:func:`_colmap_in_child`), its models in ``partial``.

    Args:
        images: the images folder.
        partial: the work folder (``OUT/colmap.partial``).
        options: the options (features, matching, threads, seed, focal prior, progress).
        matcher: the matcher resolved (exhaustive or sequential).
        files: the images COLMAP will read.

    Returns:
        The largest model and how the steps went.

    Raises:
        AriSfmError: COLMAP registered fewer than MIN_IMAGES images, or stopped (one line).
    """
    from .adapter import read_colmap

    times: dict[str, float] = {}
    bar = None  # progress: one bar for the steps, then the images the mapper registers
    what = {"features": f"SIFT features of {len(files)} images (CPU)", "matching": f"{matcher} matching",
            "mapping": "incremental mapping"}
    step: str | None = None  # the step running, since step_t0
    step_t0 = time.perf_counter()

    def on_step(name: str) -> None:
        nonlocal bar, step, step_t0
        now = time.perf_counter()
        if step is not None:
            times[step] = now - step_t0
        step, step_t0 = name, now
        log.info("COLMAP %s (%s)", what[name], images)
        if options.progress:
            from tqdm import tqdm

            if bar is not None:
                bar.close()
            mapping = name == "mapping"
            bar = tqdm(total=len(files) if mapping else None, desc=f"COLMAP {what[name]}", leave=False,
                       unit="image" if mapping else "it", bar_format=None if mapping else "{desc} ({elapsed})")

    focal_hint = "" if options.focal_px is None else f", or --focal-px {options.focal_px:g} is not their focal length"
    try:
        _colmap_in_child(images, partial, options, matcher, on_step,
                         (lambda: bar.update(1)) if bar is not None else None)
    except _NothingReconstructed:
        raise AriSfmError(images, f"COLMAP registered none of the {len(files)} images (at least {MIN_IMAGES} "
                                  f"needed): the images need more overlap or texture{focal_hint}") from None
    finally:
        if bar is not None:
            bar.close()
    times["mapping"] = time.perf_counter() - step_t0
    model_dirs = sorted(p for p in (partial / "sparse").iterdir() if p.is_dir())
    models = [(read_colmap(p), p) for p in model_dirs]
    rec, model_dir = max(models, key=lambda m: (m[0].num_reg_images(), m[0].num_points3D()))
    registered = rec.num_reg_images()
    names = {im.name for im in rec.images.values() if _registered(im)}
    unregistered = [p.name for p in files if p.name not in names]
    if registered < MIN_IMAGES:
        raise AriSfmError(images, f"COLMAP registered {registered} of {len(files)} images (at least {MIN_IMAGES} "
                                  f"needed): the images need more overlap or texture{focal_hint}")
    if unregistered:
        log.warning("COLMAP did not register %d of the %d images: %s", len(unregistered), len(files),
                    ", ".join(unregistered))
    return ColmapStep(rec, model_dir, registered, tuple(unregistered), times)


def refine_step(colmap: ColmapStep, spec: Any, options: SfmOptions, images: Path, window: Path) -> RefineStep:
    """refine-colmap on COLMAP's model with WINDOW.yaml's plate, mount and scale (or the baseline).

    Args:
        colmap: COLMAP's step.
        spec: the parsed WINDOW.yaml (:class:`~ari_sfm.colmap.refine.window.WindowSpec`).
        options: the options (baseline, Huber threshold, iterations, progress).
        images: the images folder (named in errors about the model).
        window: WINDOW.yaml (named in errors about the declared plane).

    Returns:
        The refinement and its time.
    """
    from .refine import refine_colmap
    from .refine.options import RefineColmapOptions

    t_refine = time.perf_counter()
    rec = colmap.reconstruction
    log.info("refine-colmap: %d images, %d points, the exact refractive model", colmap.registered, rec.num_points3D())
    refine_options = RefineColmapOptions(mount=spec.mount, units_mm=spec.units_mm, scale_bar=spec.scale_bar,
                                         baseline=options.baseline, huber_px=options.huber_px,
                                         max_iterations=options.max_iterations)
    result = refine_colmap(rec, spec.interface, refine_options, progress=options.progress, path=images,
                           plane_path=window)
    return RefineStep(result, time.perf_counter() - t_refine)


def _run_sfm(images: Path, window: Path, out: Path, options: SfmOptions, files: list[Path], spec: Any,
             matcher: Matcher, created: bool) -> SfmResult:
    """:func:`run_sfm` once its inputs are checked and ``out`` is held: the steps (SFM_STEPS), then the outputs
    (COLMAP's model renamed into place, refine-colmap's, sfm.json)."""
    from ..io import write_json_atomic
    from .refine import write_refined

    partial, final = out / "colmap.partial", out / "colmap"
    if partial.exists():  # a killed run's (this folder is held: no other run is using it)
        shutil.rmtree(partial)
    t0 = time.perf_counter()
    try:
        colmap = colmap_step(images, partial, options, matcher, files)
        refined = refine_step(colmap, spec, options, images, window)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    if final.exists():
        shutil.rmtree(final)
    partial.rename(final)
    colmap_model = final / colmap.model_dir.relative_to(partial)
    result = refined.result
    refined_dir = write_refined(result, out / "refined")
    summary = out / "sfm.json"
    rec = colmap.reconstruction
    times = colmap.times | {"refine": refined.time_s}
    write_json_atomic(summary, {
        "format": SFM_FORMAT,
        "images": str(images.resolve()), "window": str(window.resolve()),
        "matcher": matcher.value, "num_images": len(files), "registered": colmap.registered,
        "points3D": rec.num_points3D(), "unregistered": list(colmap.unregistered),
        "units_mm": result.report.units_mm, "scale": "units_mm" if spec.units_mm is not None else
        "scale_bar" if spec.scale_bar is not None else "baseline" if options.baseline is not None else None,
        "baseline": None if result.report.baseline is None else result.report.baseline.to_json(),
        "colmap_model": str(colmap_model.relative_to(out)), "refined": "refined",
        "time_s": {k: round(v, 3) for k, v in times.items()} | {"total": round(time.perf_counter() - t0, 3)},
    })
    return SfmResult(len(files), colmap.registered, rec.num_points3D(), colmap_model, refined_dir, summary, result,
                     colmap.unregistered)


def _registered(image: Any) -> bool:
    """Whether COLMAP registered ``image`` (pycolmap 3.11: ``registered``; later: ``has_pose``)."""
    flag = getattr(image, "has_pose", None)
    if flag is None:
        flag = getattr(image, "registered", True)
    return bool(flag() if callable(flag) else flag)


class _NothingReconstructed(Exception):
    """COLMAP's mapper reconstructed nothing (the child's exit code NOTHING_EXIT)."""


NOTHING_EXIT = 3  # the COLMAP child: the mapper made no model
ERROR_EXIT = 4  # the COLMAP child: an AriSfmError, said on its stdout
# what the COLMAP child runs (argv[1]: its JSON)
CHILD_CODE = "from ari_sfm.colmap.sfm import _child_main; _child_main()"
STDERR_KEPT = 40  # the COLMAP child's last stderr lines kept for the error message


def _colmap_in_child(images: Path, partial: Path, options: SfmOptions, matcher: Matcher, on_step, on_image) -> None:
    """COLMAP's steps (:func:`ari_sfm.colmap.adapter.structure_from_motion`) in a child process, its models in
    ``partial/sparse``: a native abort (COLMAP's CHECK on a full disk, SQLite failing) ends the child, not this
    command, and becomes one AriSfmError line. The child reports its steps and registered images on stdout."""
    import collections
    import json
    import subprocess
    import sys
    import threading

    args = {"images": str(images), "work": str(partial), "focal_px": options.focal_px,
            "max_features": options.max_features, "seed": options.seed, "matcher": matcher.value,
            "overlap": options.overlap, "num_threads": options.num_threads,
            "verbose": logging.getLogger("ari_sfm").isEnabledFor(logging.INFO)}
    cmd = [sys.executable, "-c", CHILD_CODE, json.dumps(args)]
    tail: collections.deque[str] = collections.deque(maxlen=STDERR_KEPT)
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            errors="replace")

    assert proc.stdout is not None and proc.stderr is not None  # both piped

    def read_stderr() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            tail.append(line.rstrip())
            if args["verbose"]:
                sys.stderr.write(line)

    said = None  # an AriSfmError the child reported: [path, message]
    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    try:
        for line in proc.stdout:
            kind, _, value = line.strip().partition(" ")
            if kind == "step" and on_step is not None:
                on_step(value)
            elif kind == "image" and on_image is not None:
                on_image()
            elif kind == "error":
                said = json.loads(value)
        code = proc.wait()
    except BaseException:  # Ctrl-C, SIGTERM, an error in a callback: the child goes too
        proc.kill()
        proc.wait()
        raise
    finally:
        reader.join(timeout=5)
    if code == 0:
        return
    if code == NOTHING_EXIT:
        raise _NothingReconstructed
    if code == ERROR_EXIT and said is not None:
        raise AriSfmError(*said)
    raise AriSfmError(partial.parent, _child_failure(list(tail), partial, code))


def _child_failure(lines: list[str], partial: Path, code: int) -> str:
    """One line saying why the COLMAP child stopped (its glog ``Check failed``/``F...`` line, a full disk)."""
    text = "\n".join(lines)
    try:
        free = shutil.disk_usage(partial.parent).free
    except OSError:
        free = None
    if "No space left" in text or "disk is full" in text or "SQLITE_FULL" in text or (free is not None
                                                                                         and free < 1 << 20):
        return "no space left on the device: COLMAP's database could not be written (free some space)"
    fatal = [ln for ln in lines if "Check failed" in ln or ln.startswith(("F2", "E2", "Error", "error"))
             or "Exception" in ln or "Error:" in ln]
    why = fatal[-1] if fatal else (lines[-1] if lines else f"exit code {code}")
    why = why.split("] ", 1)[-1].strip()  # glog's "F20261127 12:00:00.0 123 file.cc:45] " prefix
    return f"COLMAP stopped ({'signal ' + str(-code) if code < 0 else 'exit code ' + str(code)}): {why[:300]}"


def _child_main() -> None:
    """The COLMAP child of :func:`_colmap_in_child`: argv[1] its JSON arguments."""
    import json
    import sys

    from .adapter import structure_from_motion

    a = json.loads(sys.argv[1])
    logging.basicConfig(level=logging.INFO if a["verbose"] else logging.WARNING, format="%(levelname)s: %(message)s")

    def say(*words: str) -> None:
        print(*words, flush=True)

    try:
        structure_from_motion(a["images"], a["work"], focal_px=a["focal_px"], max_features=a["max_features"],
                              seed=a["seed"], matcher=a["matcher"], overlap=a["overlap"],
                              num_threads=a["num_threads"], on_step=lambda name: say("step", name),
                              on_image=lambda: say("image"))
    except AriSfmError as exc:
        if "reconstructed nothing" in exc.message:
            sys.exit(NOTHING_EXIT)
        say("error", json.dumps([exc.path, exc.message]))  # raised again by the parent
        sys.exit(ERROR_EXIT)

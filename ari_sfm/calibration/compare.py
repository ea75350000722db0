"""The paper's comparison of calibration methods (Section 3.3, Tables 2-4, Figs. 6, 9-11) on any dataset.

Every model calibrates the same data; each is judged by its reprojection
errors on the calibration corners it was fitted on (in-sample) and on all
calibration corners (with ``--subset``: the limited-data experiment, fit on
the central corners of each board, judge on all of them), and optionally on
a held-out observations file (frame poses solved with the rig fixed).
Outputs: ``compare.json``, ``compare.md`` (the tables) and two PNG figures
(residual vectors per model; error distributions side by side). Each model is calibrated twice and
timed by its faster run: the first calibration of a model in a process also pays its one-time costs
(imports, compiled kernels loaded), which would otherwise be charged to whichever model runs first.

Parameters per camera count what describes a camera and its window:
intrinsics (4, or 9 with distortion) plus the window normal (2) and, under
water, its distance (1); pf has its 40 coefficients. Board poses and the
6 of each camera's pose in the rig are not counted.
"""
from __future__ import annotations

import logging
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import AriSfmError
from ..models.registry import BUNDLE, CALIBRATABLE, COMPARED, model_spec
from ..records import Dataset, Observation
from ..results import ResidualStats
from .calibrate import CalibrationOptions
from .evaluate import evaluate_held_out, observation_residuals, residual_stats
from .record import Calibration

if TYPE_CHECKING:
    from matplotlib.figure import Figure

log = logging.getLogger(__name__)
FIGURES = ("residuals_scatter.png", "residuals_distribution.png")  # written beside compare.json

FORMAT = "ari-sfm-compare/1"
TIMED_RUNS = 2  # each model calibrated this many times; its time the fastest (not the process's start-up)
DEFAULT_MODELS = COMPARED  # the models: ari_sfm.models.registry
COMPARE_OPTIONS = CalibrationOptions(uncertainty=False)  # compare's default: marginals are not part of a method's time
# The paper's figures (px, ms) where it gives them: Table 2 (single camera), 3 (binocular), 4 (3x4 subset).
PAPER = {
    "single": {"rt": (0.31, 1.42, 0.37, 298), "pf": (0.01, 0.08, 0.02, 7), "ari": (0.03, 0.12, 0.04, 10)},
    "binocular": {"rt": (0.35, 1.39, 0.41, 527), "pf": (0.01, 0.08, 0.02, 12), "ari": (0.04, 0.16, 0.05, 15)},
    "subset": {"pf": (12.67, 51.57, 20.74, 6), "ari": (0.05, 0.25, 0.07, 7)},
}


@dataclass(frozen=True)
class Subset:
    """The central ``cols`` x ``rows`` corners of a planar board (the paper's 3x4 limited-data fit)."""

    cols: int
    rows: int

    @staticmethod
    def parse(text: str) -> Subset:
        """The subset a ``--subset`` text names.

        Args:
            text: ``center:COLSxROWS``, e.g. ``center:3x4``.

        Returns:
            The subset.

        Raises:
            AriSfmError: (``--subset``) the text is not of that form.
        """
        m = re.fullmatch(r"center:(\d+)x(\d+)", text.strip())
        if not m or int(m.group(1)) < 1 or int(m.group(2)) < 1:
            raise AriSfmError("--subset", f"expected center:COLSxROWS (e.g. center:3x4), got {text!r}")
        return Subset(int(m.group(1)), int(m.group(2)))

    def ids(self, dataset: Dataset) -> np.ndarray:
        """The corner ids in the board's central block."""
        grid = dataset.target.grid
        if grid is None:
            raise AriSfmError(dataset.rig_path,
                              "--subset center:... needs a planar grid target (checkerboard or charuco)")
        cols, rows = grid
        if self.cols > cols or self.rows > rows:
            raise AriSfmError(dataset.rig_path, f"--subset {self.cols}x{self.rows} is larger than the board's "
                                                f"{cols}x{rows} corners")
        c0, r0 = (cols - self.cols) // 2, (rows - self.rows) // 2
        c, r = np.meshgrid(np.arange(c0, c0 + self.cols), np.arange(r0, r0 + self.rows))
        return np.sort((r * cols + c).ravel())

    def apply(self, dataset: Dataset) -> Dataset:
        """The dataset with each calibration record cut to the central block (stacking records kept whole)."""
        keep = self.ids(dataset)
        out = []
        for o in dataset.observations or ():
            if o.set == "calibration":
                mask = np.isin(o.ids, keep)
                if mask.sum() < 4:
                    continue
                o = replace(o, ids=o.ids[mask], pixels=o.pixels[mask])
            out.append(o)
        return dataset.with_observations(tuple(out), dataset.observations_path)


@dataclass(frozen=True)
class ModelResult:
    """One model's calibration and its errors."""

    model: str
    calibration: Calibration
    params_per_camera: int
    time_ms: float  # the calibration itself (pf: the polynomial fit, as the paper times it)
    wall_ms: float  # everything this model needed (pf: including its ari world)
    fit: ResidualStats  # errors on the corners it was fitted on
    all: ResidualStats  # errors on all calibration corners
    holdout: ResidualStats | None
    residuals: np.ndarray  # (N, 2) on all calibration corners
    in_fit: np.ndarray  # (N,) bool: the corner was in the fit


def params_per_camera(cal: Calibration, distortion: bool) -> int:
    """The parameters describing one camera and its window (module docstring): what the paper's tables count.

    Args:
        cal: The model's calibration.
        distortion: Whether lens distortion was estimated.

    Returns:
        Intrinsics (4, or 9 with distortion) plus the window normal (2) and, under water, its distance (1);
        the registry's count for a model that has its own (pf: 40).
    """
    spec = cal.spec
    if spec.params_per_camera is not None:
        return spec.params_per_camera
    intr = 9 if (distortion or spec.distortion) else 4
    if not spec.window:
        return intr
    return intr + 2 + (1 if cal.interface.medium_index != 1.0 else 0)


def parse_models(text: str | Sequence[str]) -> tuple[str, ...]:
    """Model names from ``ari,exact,...`` (unknown or repeated names are an error)."""
    names = [m.strip() for m in text.split(",")] if isinstance(text, str) else list(text)
    bad = [m for m in names if m not in CALIBRATABLE]
    if bad or not names or len(set(names)) != len(names):
        raise AriSfmError("--models", f"expected a comma-separated list of distinct models from "
                                      f"{', '.join(CALIBRATABLE)}; got {text!r}")
    return tuple(names)


def _judge(cal: Calibration, dataset: Dataset, fit_ids: np.ndarray | None
           ) -> tuple[ResidualStats, ResidualStats, np.ndarray, np.ndarray]:
    """In-sample and all-corner errors on the calibration records (all corners of the full dataset)."""
    pairs = observation_residuals(cal, dataset.select("calibration"), dataset.target)
    res = np.concatenate([r for _, r in pairs]) if pairs else np.zeros((0, 2))
    in_fit = (np.concatenate([np.isin(o.ids, fit_ids) for o, _ in pairs]) if fit_ids is not None and pairs
              else np.ones(len(res), bool))
    return residual_stats([res[in_fit]]), residual_stats([res]), res, in_fit


def _holdout(cal: Calibration, records: Sequence[Observation], dataset: Dataset) -> ResidualStats:
    """Errors on held-out records, every frame's pose solved with the rig fixed."""
    return replace(evaluate_held_out(cal, records, dataset.target), per_camera=None)


def check_holdout_of_this_rig(cal: Calibration, holdout: Sequence[Observation], dataset: Dataset,
                              where: str | Path = "--holdout") -> ResidualStats:
    """The held-out errors of ``cal``, checked to be views of its rig.

    Args:
        cal: The calibration judged.
        holdout: The held-out views.
        dataset: The dataset it was calibrated on (its target; the calibration's own errors on its corners).
        where: What to name in the error (the option or the file the views came from).

    Returns:
        The errors on the held-out views, every frame's pose fitted with the rig held.

    Raises:
        AriSfmError: (``where``) no frame's pose can be fitted, or the errors are far above the calibration's
            own (another rig's or another target's views: scoring them would be meaningless).
    """
    from ..provenance import RESIDUAL_MISMATCH_FACTOR, RESIDUAL_MISMATCH_PX

    stats = _holdout(cal, holdout, dataset)
    own = _judge(cal, dataset, None)[1].rmse_px  # on all the dataset's calibration corners (a --subset fit's too)
    if stats.count == 0:
        raise AriSfmError(where, "no held-out view to judge: no frame of a calibrated camera with 4 or more corners "
                                 "whose pose could be fitted")
    if stats.rmse_px > RESIDUAL_MISMATCH_FACTOR * own + RESIDUAL_MISMATCH_PX:
        raise AriSfmError(where, f"not views of this rig: rmse {stats.rmse_px:.4g} px with their frame poses fitted "
                                 f"and the {cal.model} calibration's rig held, against {own:.4g} px on the dataset's "
                                 "own corners (another rig's observations?)")
    return stats


def compare(dataset: Dataset, models: Sequence[str] = DEFAULT_MODELS, subset: Subset | None = None,
            holdout: Sequence[Observation] | None = None, pf_world: str = "ari", holdout_path: str | Path | None = None,
            options: CalibrationOptions | None = None) -> list[ModelResult]:
    """Calibrate ``dataset`` with every model and judge each (see module docstring).

    Args:
        dataset: The dataset (corners detected first when it has only images).
        models: The models to compare (names of :mod:`ari_sfm.models.registry`); with several windows the
            one-window baselines are left out, said so.
        subset: Fit on the central corners of each board only (judged on all of them), or None: every corner.
        holdout: Views of the same rig to judge each model on too (frame poses solved, the rig held); checked
            to be of this rig on the first model calibrated, before the others (:func:`check_holdout_of_this_rig`).
        pf_world: Whose frame poses give pf its world coordinates: "ari" or "exact" (made first when not among
            ``models``); pf's errors include that world's pose errors.
        holdout_path: The file ``holdout`` came from, named in its errors.
        options: The calibrations' options (None: ``COMPARE_OPTIONS``, the defaults without the standard
            deviations: marginals are not part of a method's time).

    Returns:
        One result per model calibrated, in the order of ``models``.

    Raises:
        AriSfmError: unknown models or ``pf_world``; no model could be calibrated; a bundle model's (or pf's
            world's) calibration failed; ``holdout`` is not of this rig.
    """
    from ..baselines.polynomial import calibrate_pf
    from .calibrate import calibrate, ensure_observations

    opts = COMPARE_OPTIONS if options is None else options
    models = parse_models(models)
    if dataset.windows:  # several windows: the one-window baselines cannot be fitted to this rig
        left_out = [m for m in models if model_spec(m).one_window]
        models = tuple(m for m in models if m not in left_out)
        if not models:
            raise AriSfmError("--models", f"{', '.join(left_out)} model(s) one window for every camera; this rig "
                                          "has several (interfaces): compare exact, ari, pf or pinhole")
        if left_out:
            log.warning("compare: %s left out: it models one window for every camera, and this rig has %d",
                        ", ".join(left_out), len(dataset.windows))
    if pf_world not in BUNDLE:
        raise AriSfmError("--pf-world", f"expected one of {', '.join(BUNDLE)}, got {pf_world!r}")
    dataset = ensure_observations(dataset)
    fit_data = subset.apply(dataset) if subset else dataset
    fit_ids = subset.ids(dataset) if subset else None
    cals: dict[str, tuple[Calibration, float]] = {}
    needed = list(models) + ([pf_world] if "pf" in models and pf_world not in models else [])
    for model in sorted(needed, key=lambda m: m == "pf"):  # pf last: it needs its world
        runs = []
        try:
            for _ in range(TIMED_RUNS):  # the first run of a model in a process also pays its one-time costs
                t0 = time.perf_counter()
                if model_spec(model).projection == "polynomial":
                    cal = calibrate_pf(fit_data, world=cals[pf_world][0])
                    wall = time.perf_counter() - t0 + cals[pf_world][1]
                else:
                    cal = calibrate(fit_data, model=model, options=opts)
                    wall = time.perf_counter() - t0
                runs.append((cal, wall))
        except AriSfmError as exc:
            if model_spec(model).bundle or model == pf_world:
                raise
            # a baseline these data cannot support (e.g. OpenCV's camera from one view of a 3D body)
            log.warning("compare: %s left out: %s", model, exc.message)
            continue
        cal, wall = min(runs, key=lambda r: r[0].time_s)
        if holdout and not cals:  # another rig's views: refused before the other models are calibrated
            check_holdout_of_this_rig(cal, holdout, dataset, holdout_path or "--holdout")
        cals[model] = (cal, min(w for _, w in runs))
        log.info("compare: %s in %.1f ms", model, cal.time_s * 1e3)
    if not any(m in cals for m in models):
        raise AriSfmError(dataset.rig_path, f"no model of {', '.join(models)} could be calibrated on these data")
    out = []
    for model in (m for m in models if m in cals):
        cal, wall = cals[model]
        fit, all_, res, in_fit = _judge(cal, dataset, fit_ids)
        out.append(ModelResult(model, cal, params_per_camera(cal, bool(opts.distortion)), cal.time_s * 1e3,
                               wall * 1e3, fit, all_, _holdout(cal, holdout, dataset) if holdout else None, res,
                               in_fit))
    return out


# ---------------------------------------------------------------- outputs


def to_json(results: Sequence[ModelResult], subset: Subset | None, dataset: Dataset) -> dict[str, Any]:
    """compare.json: per model, parameters, times and errors (px).

    Args:
        results: The models' results (:func:`compare`).
        subset: The subset fitted on, or None.
        dataset: The dataset compared on.

    Returns:
        The file's content.
    """
    pf = [r.calibration.pf_world.model for r in results if r.calibration.pf_world is not None]
    return {
        "format": FORMAT,
        "dataset": str(dataset.root),
        "cameras": dataset.camera_names,
        "subset": None if subset is None else f"center:{subset.cols}x{subset.rows}",
        "pf_world": pf[0] if pf else None,
        "models": {r.model: {
            "params_per_camera": r.params_per_camera, "time_ms": r.time_ms, "wall_ms": r.wall_ms,
            "fit": r.fit.to_json(), "all_corners": r.all.to_json(),
            "holdout": None if r.holdout is None else r.holdout.to_json(),
            "per_camera_rmse_px": {n: c.rmse_px for n, c in r.calibration.cameras.items()},
        } for r in results},
    }


def _row(name: str, p: int | str, s: ResidualStats, t: float | str) -> str:
    t = t if isinstance(t, str) else f"{t:.0f}"
    return f"| {name} | {p} | {s.mae_px:.3f} | {s.max_px:.3f} | {s.rmse_px:.3f} | {t} |"


def to_markdown(results: Sequence[ModelResult], subset: Subset | None, dataset: Dataset) -> str:
    """compare.md: the paper's Table 2-4 layout, one table per set of corners judged.

    Args:
        results: The models' results (:func:`compare`).
        subset: The subset fitted on, or None.
        dataset: The dataset compared on.

    Returns:
        The file's text.
    """
    head = "| Method | # of para | MAE (px) | Max (px) | RMSE (px) | T (ms) |\n|---|---|---|---|---|---|"
    n = len(dataset.camera_names)
    pf = [r.calibration.pf_world.model for r in results if r.calibration.pf_world is not None]
    lines = [f"# Calibration methods compared: {dataset.root}", "",
             f"{n} camera(s); # of para: per camera, intrinsics and window (board and rig poses not counted); "
             "T: the calibration itself" + (f" (pf: its polynomial fit, in the world of the {pf[0]} fit)" if pf else "")
             + ".", ""]
    sections = [("In-sample (corners each model was fitted on)", "fit")]
    if subset is not None:
        lines.insert(3, f"Fitted on the central {subset.cols}x{subset.rows} corners of each calibration board "
                        "(the paper's limited-data experiment, Table 4).")
        lines.insert(4, "")
        sections.append(("All calibration corners", "all"))
    for title, key in sections:
        lines += [f"## {title}", "", head]
        lines += [_row(r.model.upper(), r.params_per_camera, getattr(r, key), r.time_ms) for r in results]
        lines.append("")
    if any(r.holdout for r in results):
        lines += ["## Held-out observations (frame poses solved with the rig fixed)", "", head]
        lines += [_row(r.model.upper(), r.params_per_camera, r.holdout, "-") for r in results if r.holdout]
        lines.append("")
    return "\n".join(lines)


@dataclass(frozen=True)
class CompareFigures:
    """compare's two figures as PNG bytes (:func:`figures`)."""

    residuals_scatter: bytes  # every model's residual vectors, one panel each
    residuals_distribution: bytes  # the error distributions side by side

    def files(self) -> tuple[tuple[str, bytes], ...]:
        """(file name, PNG bytes) of each figure, in the order of ``FIGURES``."""
        return tuple(zip(FIGURES, (self.residuals_scatter, self.residuals_distribution)))


@dataclass(frozen=True)
class CompareFiles:
    """What :func:`run_compare` wrote."""

    json: Path  # compare.json
    md: Path  # compare.md
    figures: tuple[Path, ...]  # the PNG figures (``FIGURES``), beside them

    def named(self) -> tuple[tuple[str, Path], ...]:
        """(label, path) of each file: ``json``, ``md``, then each figure by its file name."""
        return (("json", self.json), ("md", self.md), *((p.name, p) for p in self.figures))


def figures(results: Sequence[ModelResult]) -> CompareFigures:
    """The figures of :func:`draw_figures` as PNG bytes.

    Args:
        results: The models' results (:func:`compare`).

    Returns:
        The residual scatter per model and the error distributions.
    """
    from ..report.figures import to_png

    scatter, distribution = draw_figures(results)
    return CompareFigures(to_png(scatter), to_png(distribution))


def draw_figures(results: Sequence[ModelResult]) -> tuple[Figure, Figure]:
    """The two figures, in the report's figures' print style.

    Args:
        results: The models' results (:func:`compare`).

    Returns:
        Every model's residuals on one shared range (fitted corners red, others blue; dv down as in the
        image; dashed circle: RMSE), and the error distributions side by side.
    """
    import matplotlib.pyplot as plt

    from ..report.figures import FIG_WIDTH_IN, STYLE, panels

    with plt.rc_context(STYLE):
        k = len(results)
        cols = min(max(k, 2), 3)
        allres = np.concatenate([r.residuals for r in results]) if results else np.zeros((0, 2))
        finite = allres[np.all(np.isfinite(allres), axis=1)]
        lim = max(float(np.abs(finite).max()) if len(finite) else 1.0, 1e-3) * 1.05
        fig, axes = panels(k, FIG_WIDTH_IN / cols * 0.85 + 1.0, sharex=True, sharey=True)
        for ax, r in zip(axes, results):
            res, fit = r.residuals, r.in_fit
            if (~fit).any():
                ax.scatter(res[~fit, 0], res[~fit, 1], s=3, c="tab:blue", label="not fitted", rasterized=True)
            ax.scatter(res[fit, 0], res[fit, 1], s=3, c="tab:red", label="fitted", rasterized=True)
            ax.add_patch(plt.Circle((0, 0), r.all.rmse_px, fill=False, color="k", lw=1, ls="--"))
            ax.set_title(f"{r.model.upper()}: RMSE {r.all.rmse_px:.3f} px")
            ax.set_box_aspect(1)
        for i, ax in enumerate(axes):
            if i + cols >= k:  # the lowest panel of its column: its own ticks and label
                ax.tick_params(labelbottom=True)
                ax.set_xlabel("du (px), + right")
        for row_start in range(0, k, cols):
            axes[row_start].set_ylabel("dv (px), + down")
        axes[0].set(xlim=(-lim, lim), ylim=(lim, -lim))  # shared by every panel: one scale for all models
        if any((~r.in_fit).any() for r in results):
            axes[0].legend(markerscale=3)
        scatter = fig

        fig, ax = plt.subplots(figsize=(FIG_WIDTH_IN, 3.4), layout="constrained")
        data = [np.maximum(np.linalg.norm(r.residuals, axis=1), 1e-6) for r in results]
        ax.boxplot(data, whis=(0, 100))
        ax.set_xticks(range(1, k + 1), [r.model.upper() for r in results])
        ax.set_yscale("log")
        ax.set_ylabel("reprojection error,\nall corners (px)")
        return scatter, fig


def run_compare(dataset_path: str | Path, out: str | Path, models: str | Sequence[str] = DEFAULT_MODELS,
                subset: str | None = None, holdout: str | Path | None = None, pf_world: str = "ari",
                options: CalibrationOptions | None = None) -> CompareFiles:
    """Load, compare, write compare.json, compare.md and the figures to ``out``.

    Arguments are checked before any calibration runs and nothing is written on error.

    Args:
        dataset_path: The dataset folder or rig file.
        out: The output folder.
        models: The models, as ``ari,exact,...`` or a sequence of names.
        subset: ``center:COLSxROWS``: fit on the central corners of each board, judge on all; None: every corner.
        holdout: An observations file of the same rig to judge each model on too.
        pf_world: Whose frame poses give pf its world coordinates ("ari" or "exact").
        options: The calibrations' options (None: :data:`COMPARE_OPTIONS`).

    Returns:
        The files written.

    Raises:
        AriSfmError: a bad argument (named by its option), a dataset or observations file that cannot be read,
            or an error of :func:`compare`.
    """
    from ..io import load_dataset, load_observations, write_bytes_atomic, write_json_atomic, write_text_atomic

    names = parse_models(models)
    if pf_world not in BUNDLE:
        raise AriSfmError("--pf-world", f"expected one of {', '.join(BUNDLE)}, got {pf_world!r}")
    sub = Subset.parse(subset) if subset else None
    dataset = load_dataset(dataset_path)
    if sub:
        sub.ids(dataset)
    held = None
    if holdout:
        from ..io.observations import check_pixels_in_images

        held = load_observations(Path(holdout), dataset.target, dataset.camera_names)
        check_pixels_in_images(held, {n: c.image_size for n, c in dataset.cameras.items()}, holdout)
    results = compare(dataset, names, sub, held, pf_world, holdout_path=holdout, options=options)
    out = Path(out)
    files = CompareFiles(out / "compare.json", out / "compare.md", tuple(out / name for name in FIGURES))
    pngs = figures(results)
    write_json_atomic(files.json, to_json(results, sub, dataset))
    write_text_atomic(files.md, to_markdown(results, sub, dataset))
    for name, data in pngs.files():
        write_bytes_atomic(out / name, data)
    return files

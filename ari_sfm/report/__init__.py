"""The accuracy report: one self-contained ``report.html`` for an output folder.

``write_report(out)`` reads what ``ari-sfm run`` (or ``calibrate``,
``reconstruct``, ``compare``) wrote to OUT and renders one HTML file with
every figure embedded as a base64 PNG and the interactive 3D view's
plotly.js inlined (no external resource: it opens offline and can be mailed):

- OUT/calibration.json (required): rig summary and the calibration table,
  every parameter with its standard deviation (``uncertainty``); its
  ``stages`` list, when present, as a table of the stages side by side.
- the observations: OUT/observations.json when corners were detected
  there, else the dataset's own; the residual figures (per camera, by image
  region, by frame, by depth), the recommendations and the stacking tracks
  (paper Fig. 4) need them.
- OUT/points.json and OUT/metrics.json (optional): Figs. 13 and 14.
- OUT/compare.md or OUT/compare.json (optional): the model comparison, and its PNG figures.

The page is a list of sections, :data:`SECTIONS`: functions of a
:class:`ReportContext` returning HTML (or "" when they have nothing to show).
A module adds one with a single call, ``add_section(name, render, after=...)``.

The dataset is found from, in order: the ``dataset`` argument, OUT/run.json
(written by ``ari-sfm run``: ``{"format": "ari-sfm-run/1", "dataset":
<absolute path>, ...}``), metrics.json's ``provenance.dataset.path``, then its
``dataset`` if absolute (a relative one is not guessed: a warning asks for
``--dataset``), then the rig file OUT/observations.json names (``calibrate``
records it when it detected the corners). Without it the report still has
the calibration and, from OUT/observations.json, the residuals.

What does not belong together is refused or labelled: a dataset of another
rig than calibration.json (other cameras, image sizes or window) is an error;
points.json / metrics.json made with another calibration (their recorded
content hash, :mod:`ari_sfm.provenance`; for older files their model) or from
another dataset are shown under a label saying so.
"""
from __future__ import annotations

import base64
import html
import json
import logging
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration.record import Calibration
from ..errors import AriSfmError
from ..io import load_calibration
from ..reconstruction.reference import ReferenceErrors
from ..records import Dataset, Observation, Target
from ..results import StageRecord

log = logging.getLogger(__name__)

RUN_FILE = "run.json"
RUN_FORMAT = "ari-sfm-run/1"
REPORT_FILE = "report.html"


@dataclass(frozen=True)
class ReportInputs:
    """Everything the report shows, loaded and validated."""

    out: Path
    calibration: Calibration
    dataset: Dataset | None  # None when the dataset is not found
    dataset_path: Path | None
    observations: tuple[Observation, ...]  # () when none are found
    metrics: dict | None = None
    points: dict[str, np.ndarray] = field(default_factory=dict)  # frame -> (N, 3) xyz
    compare_md: str | None = None
    compare_json: dict | None = None
    compare_figures: dict[str, bytes] = field(default_factory=dict)  # compare's PNGs by file name
    notes: tuple[str, ...] = ()  # what is missing or does not belong, shown at the top as a warning
    reconstruction_label: str | None = None  # why the reconstruction does not belong to this calibration / dataset
    info: tuple[str, ...] = ()  # why the reconstruction section is empty (neutral wording, not a warning)


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise AriSfmError(path, f"cannot read: {exc}") from None
    if not isinstance(data, dict):
        raise AriSfmError(path, "expected a JSON object")
    return data


def find_dataset(out: Path, dataset: str | Path | None = None) -> Path | None:
    """The dataset folder of an output folder (the search order is in the module docstring).

    Args:
        out: The output folder.
        dataset: The dataset given by the caller; when not None it is returned as is.

    Returns:
        The dataset folder, or None if none is found.
    """
    from ..provenance import recorded_dataset_path

    if dataset is not None:
        return Path(dataset)
    candidates: list[Path] = []
    if (out / RUN_FILE).exists():
        given = _read_json(out / RUN_FILE).get("dataset")
        if isinstance(given, str) and Path(given).is_absolute():
            candidates.append(Path(given))
    if (out / "metrics.json").exists():
        metrics = _read_json(out / "metrics.json")
        recorded = recorded_dataset_path(metrics)
        if recorded is not None:
            candidates.append(recorded)
        given = metrics.get("dataset")
        if isinstance(given, str) and Path(given).is_absolute():
            candidates.append(Path(given))
        elif isinstance(given, str):
            log.warning("%s: dataset %r is a relative path of an unknown working folder: pass --dataset",
                        out / "metrics.json", given)
    found = next((c for c in candidates if c.exists()), None)
    if found is None and (out / "observations.json").exists():  # calibrate's corners name the rig they came from
        from ..io.observations import recorded_dataset

        rig = recorded_dataset(out / "observations.json")
        found = rig if rig is not None and rig.exists() else None
    return found


def load_inputs(out: str | Path, dataset: str | Path | None = None) -> ReportInputs:
    """Load an output folder's files for the report.

    Args:
        out: The output folder (OUT).
        dataset: The dataset folder; None to find it (:func:`find_dataset`).

    Returns:
        The inputs, with notes on what is missing or does not belong.

    Raises:
        AriSfmError: OUT is not a folder, calibration.json is missing, a file cannot be read, or the
            dataset is of another rig or capture than calibration.json.
    """
    from ..io import load_dataset, load_observations, load_points

    out = Path(out)
    if not out.is_dir():
        raise AriSfmError(out, "no such output folder")
    cal_path = out / "calibration.json"
    if not cal_path.exists():
        raise AriSfmError(cal_path, "missing: run `ari-sfm run` or `ari-sfm calibrate` with -o to this folder first")
    cal = load_calibration(cal_path)
    notes: list[str] = []
    selfcal = cal.self_calibration is not None  # `self-calibrate`'s folder: particles, no target dataset
    ds_path = find_dataset(out, dataset) if not selfcal or dataset is not None else None
    obs_path = out / "observations.json"
    ds = None
    if ds_path is not None:
        from ..reconstruction.reconstruct import check_rig, check_same_capture

        ds = load_dataset(ds_path, obs_path if obs_path.exists() else None)
        check_rig(ds, cal, cal_path)  # another rig's dataset: refused, not mixed in
        check_same_capture(ds, cal)  # nor another capture of the same rig
    elif not selfcal:
        notes.append("dataset not found (pass --dataset): no dataset summary")
    if ds is not None and ds.observations is not None:
        observations = ds.observations
    elif obs_path.exists():
        observations = load_observations(obs_path, cal.target, list(cal.cameras))
    else:
        observations = ()
        if not selfcal:
            notes.append("no observations found: no residual or expansion-centre figures")
    metrics = _read_json(out / "metrics.json") if (out / "metrics.json").exists() else None
    points = {}
    points_data = None
    if (out / "points.json").exists():
        points_data = load_points(out / "points.json")
        points = {name: np.asarray(f["xyz"], float) for name, f in points_data["frames"].items()}
    label = _reconstruction_label(out, cal_path, cal, ds, metrics, points_data)
    if label:
        notes.append(f"reconstruction: {label}")
    info: list[str] = []
    skipped = _read_json(out / RUN_FILE).get("reconstruction_skipped") if (out / RUN_FILE).exists() else None
    if metrics is None and not points:
        if selfcal:
            info.append("Not applicable: a self-calibration folder (its particles: the section below).")
        elif ds is not None and not ds.reconstruction:
            info.append("Not applicable: the dataset has no reconstruction frames.")
        elif skipped:
            info.append(f"Not run: {skipped}.")
        else:
            info.append("None in this folder (run `ari-sfm reconstruct` or `ari-sfm run` to add "
                        "points.json and metrics.json).")
    elif skipped:
        notes.append("the last `ari-sfm run` here skipped the reconstruction: points.json and metrics.json "
                     "are older than its calibration")
    md = (out / "compare.md").read_text() if (out / "compare.md").exists() else None
    cj = _read_json(out / "compare.json") if (out / "compare.json").exists() else None
    from ..calibration.compare import FIGURES

    figs = {name: (out / name).read_bytes() for name in FIGURES if (out / name).exists()}
    return ReportInputs(out, cal, ds, ds_path, tuple(observations), metrics, points, md, cj, figs, tuple(notes), label,
                        tuple(info))


def _reconstruction_label(out: Path, cal_path: Path, cal: Calibration, ds: Dataset | None,
                          metrics: dict | None, points: dict | None) -> str | None:
    """Why OUT's points.json / metrics.json do not belong to its calibration.json or the dataset, or None."""
    from ..provenance import calibration_mismatch, dataset_mismatch

    why: list[str] = []
    for name, result in (("points.json", points), ("metrics.json", metrics)):
        if result is None:
            continue
        for reason in (calibration_mismatch(result, cal_path, cal.model),
                       None if ds is None else dataset_mismatch(result, ds)):
            if reason:
                why.append(f"{name} was {reason}")
    return "; ".join(why) or None


# --------------------------------------------------------------------------- HTML pieces

CSS = """
body{font-family:sans-serif;max-width:1200px;margin:1.5em auto;padding:0 1.5em;color:#222;line-height:1.35}
table{border-collapse:collapse;margin:0.6em 0}
td,th{border:1px solid #bbb;padding:2px 8px;text-align:left;font-size:0.92em}
th{background:#eee}
td.n{text-align:right;font-variant-numeric:tabular-nums}
figure{margin:1em 0;break-inside:avoid}
img{width:100%;height:auto;display:block}
figcaption{font-size:0.9em;color:#444;margin-top:0.3em}
.note{color:#a40}
.info{color:#555;font-style:italic}
ul.advice li{margin:0.25em 0}
h2{border-bottom:1px solid #ccc;padding-bottom:0.15em;margin-top:1.6em;break-after:avoid}
thead{display:table-header-group}
tr,figure,img{break-inside:avoid}
h2,h3{break-after:avoid}
@media print{body{max-width:none;margin:0;padding:0}#rig-3d-section{break-inside:avoid}
img,figure,table,.js-plotly-plot{max-width:100%}}
"""


def _fmt(x: Any, digits: int = 4) -> str:
    if x is None:
        return "&ndash;"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        if not np.isfinite(x):
            return "nan"
        if x != 0.0 and abs(x) < 0.5 * 10.0 ** -digits:  # e.g. tangential distortion: significant digits, not 0.0000
            return f"{x:.{digits - 1}e}".replace("e-0", "e-")
        return f"{x:.{digits}f}"
    return html.escape(str(x))


def _table(header: list[str], rows: list[list[Any]], digits: int = 4, align_numbers: bool = True) -> str:
    """An HTML table; numbers right-aligned in their column unless ``align_numbers`` is False (a key-value
    table, whose value column mixes numbers and text)."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)

    def cell(v: Any) -> str:
        num = align_numbers and (isinstance(v, (int, float, np.integer, np.floating)) or v is None or (
            isinstance(v, str) and re.fullmatch(r"[-+]?\d+(\.\d+)?", v.strip()) is not None))  # e.g. compare.md's
        return f'<td class="n">{_fmt(v, digits)}</td>' if num else f"<td>{_fmt(v, digits)}</td>"

    body = "".join("<tr>" + "".join(cell(v) for v in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"  # thead: repeated on each printed page


def _img(png: bytes, alt: str, caption: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return (f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def markdown_tables(text: str) -> str:
    """compare.md as HTML: '#' headings, '|' tables (separator rows dropped), other lines as paragraphs."""
    parts: list[str] = []
    table: list[list[str]] = []

    def flush() -> None:
        if table:
            parts.append(_table(table[0], table[1:]))
            table.clear()

    for line in text.splitlines():
        s = line.strip()
        if s.startswith("|"):
            cells = [c.strip() for c in s.strip("|").split("|")]
            if not all(re.fullmatch(r":?-{2,}:?", c) for c in cells if c):
                table.append(cells)
            continue
        flush()
        if s.startswith("#"):
            parts.append(f"<h3>{html.escape(s.lstrip('#').strip())}</h3>")
        elif s:
            parts.append(f"<p>{html.escape(s)}</p>")
    flush()
    return "\n".join(parts)


def calibration_rows(cal: Calibration) -> list[list[Any]]:
    """[camera, parameter, value, std dev] for every calibrated parameter (std from ``uncertainty``)."""
    # the table reads the records' fields by name
    unc = cal.uncertainty.to_json() if cal.uncertainty is not None else {}
    cam_unc = unc.get("cameras", {})
    rows: list[list[Any]] = []
    dist_names = ("k1", "k2", "p1", "p2", "k3")
    first = next(iter(cal.cameras))
    for name, cam in cal.cameras.items():
        u = cam_unc.get(name, {})
        for key, value in zip(("fx", "fy", "cx", "cy"), cam.params[:4]):
            rows.append([name, f"{key} (px)", float(value), u.get(key)])
        for key, value in zip(dist_names, cam.params[4:]):
            if value != 0.0 or key in u:
                rows.append([name, key, float(value), u.get(key)])
        if cal.window_of(name).normal_world is not None:
            n = cal.normal_cam(name)
            tilt = float(np.degrees(np.arccos(np.clip(n[2], -1, 1))))
            sigma = unc.get("windows", {}).get(cal.window_of(name).name, {}).get("normal_deg", unc.get("normal_deg"))
            label = "window tilt to the optical axis (deg)" if not cal.windows else \
                f"window {cal.window_of(name).name}: tilt to the optical axis (deg)"
            rows.append([name, label, tilt, sigma])
        if cam.expansion_center_px is not None:
            std = cam.expansion_center_std_px if cam.expansion_center_std_px is not None else (None, None)
            rows.append([name, "expansion centre u (px)", float(cam.expansion_center_px[0]), std[0]])
            rows.append([name, "expansion centre v (px)", float(cam.expansion_center_px[1]), std[1]])
        if name != first:
            rel = cam.cam_from_world.compose(cal.cameras[first].cam_from_world.inverse())
            rows.append([name, f"baseline to {first} (mm)", float(np.linalg.norm(rel.inverse().t)),
                         u.get("translation_mm")])
            angle = float(np.degrees(np.arccos(np.clip((np.trace(rel.R) - 1) / 2, -1, 1))))
            rows.append([name, f"rotation from {first} (deg)", angle, u.get("rotation_deg")])
        rows.append([name, "reprojection rmse (px)", cam.rmse_px, None])
    for w in cal.window_list():
        label = "window" if not cal.windows else f"window {w.name}"
        wu = unc.get("windows", {}).get(w.name, unc if not cal.windows else {})
        if w.normal_world is not None:
            n = w.normal_world
            rows.append([label, "normal (world); std: angle (deg)", f"[{n[0]:+.5f} {n[1]:+.5f} {n[2]:+.5f}]",
                         wu.get("normal_deg")])
        if w.interface.distance_mm is not None:
            rows.append([label, f"distance from {w.cameras[0]} (mm)" if cal.windows else "distance (mm)",
                         w.interface.distance_mm, wu.get("distance_mm")])
    return rows



# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class ReportContext:
    """What every section reads: the loaded inputs and, computed once, the residuals of the observations."""

    inputs: ReportInputs
    target: Target | None
    residuals: tuple[tuple[Observation, np.ndarray], ...]  # evaluate.observation_residuals

    @property
    def calibration(self) -> Calibration:
        return self.inputs.calibration


Section = Callable[[ReportContext], str]  # returns HTML ("" when it has nothing to show)


def _summary_section(ctx: ReportContext) -> str:
    inp = ctx.inputs
    cal = inp.calibration
    rows: list[list[Any]] = [["model", cal.model], ["cameras", ", ".join(cal.cameras)]]
    for w in cal.window_list():
        i = w.interface
        rows.append(["window" if not cal.windows else f"window {w.name} ({', '.join(w.cameras)})",
                     f"{i.thickness_mm:g} mm, n = {i.index:g}, medium n = {i.medium_index:g}"])
    target = ctx.target
    if target is not None:
        grid = target.inner_corners or target.squares or target.circle_grid
        rows.append(["target", f"{target.type}" + (f" {grid[0]}x{grid[1]}" if grid else "")
                     + (f", {target.square_mm:g} mm squares" if target.square_mm else "")
                     + (f" {target.layout}, {target.spacing_mm:g} mm spacing" if target.type == "circles" else "")])
    if inp.dataset is not None:
        ds = inp.dataset
        rows.insert(0, ["dataset", str(inp.dataset_path)])
        for cam, spec in ds.cameras.items():
            rows.append([f"camera {cam}", f"{spec.image_size[0]}x{spec.image_size[1]} px"])
        added = sorted({e.added_mm for e in ds.stacking if e.added_mm is not None})
        rows.append(["glass stacking", f"{len({e.key for e in ds.stacking})} pose(s), added glass "
                                       + ", ".join(f"{a:g}" for a in added) + " mm" if ds.stacking else "none"])
        rows.append(["calibration frames", len(ds.calibration)])
        stages = [e.stage_mm for e in ds.reconstruction if e.stage_mm is not None]
        rows.append(["reconstruction frames", f"{len(ds.reconstruction)}"
                     + (f", stage {min(stages):g} .. {max(stages):g} mm" if stages else "")])
    counts: dict[str, int] = {}
    for o in inp.observations:
        counts[o.set] = counts.get(o.set, 0) + len(o.ids)
    if counts:
        rows.append(["corners", ", ".join(f"{n} {s}" for s, n in counts.items())])
    r = cal.residuals
    if r is not None:
        rows.append(["reprojection error", f"RMSE {r.rmse_px:.4f} px, MAE {r.mae_px:.4f} px, max {r.max_px:.4f} px "
                                           f"over {r.count} corners"])
    if cal.uncertainty is not None:
        rows.append(["residual sigma", f"{cal.uncertainty.sigma_px:.4f} px (scales the standard deviations below)"])
    table = _table(["", ""], rows, align_numbers=False)
    return "<h2>Dataset and rig</h2>" + table.replace("<thead><tr><th></th><th></th></tr></thead>", "", 1)


def _advice_section(ctx: ReportContext) -> str:
    from .diagnostics import recommendations

    if not ctx.residuals:
        return ""
    advice = recommendations(ctx.calibration, ctx.residuals, ctx.target, ctx.inputs.points)
    parts = ["<h2>Recommendations</h2>"]
    if advice:
        parts.append('<ul class="advice">' + "".join(f"<li>{html.escape(a)}</li>" for a in advice) + "</ul>")
    else:
        parts.append('<p class="info">None: the corners cover the images, no image region, frame or depth stands '
                     "out in the residuals, and every estimated quantity is determined (thresholds in "
                     "ari_sfm/report/diagnostics.py).</p>")
    return "\n".join(parts)


def _calibration_section(ctx: ReportContext) -> str:
    return ("<h2>Calibration</h2>"
            + _table(["camera", "parameter", "value", "std dev"], calibration_rows(ctx.calibration)))


def stage_table(stages: Sequence[StageRecord]) -> tuple[list[str], list[list[Any]]]:
    """The table of a calibration's stages.

    Args:
        stages: The calibration's stage records.

    Returns:
        (header, rows): per stage its name, model, distortion, reprojection RMSE / max / corner count,
        window distance (a column only when any stage has one) and each camera's fx.
    """
    cameras = list(dict.fromkeys(n for st in stages for n in st.cameras))
    with_distance = any(st.distance_mm is not None for st in stages)
    header = ["stage", "model", "distortion", "RMSE (px)", "max (px)", "corners"]
    header += ["window distance (mm)"] if with_distance else []
    header += [f"{c} fx (px)" for c in cameras]
    rows = []
    for st in stages:
        row: list[Any] = [st.stage, st.model or "?",
                          "" if st.distortion is None else ("yes" if st.distortion else "no"),
                          st.rmse_px, st.max_px, st.count]
        row += [st.distance_mm] if with_distance else []
        row += [st.cameras[c].fx if c in st.cameras else None for c in cameras]
        rows.append(row)
    return header, rows


def _stages_section(ctx: ReportContext) -> str:
    """The stages the calibration went through (e.g. ari, then exact), side by side; nothing without them."""
    header, rows = stage_table(ctx.calibration.stages)
    if len(rows) < 2:
        return ""
    return ("<h3>Calibration stages</h3><p>Each stage starts from the one before; the last is the calibration "
            "above. Reprojection errors on the corners each stage was fitted on.</p>" + _table(header, rows))


def _residuals_section(ctx: ReportContext) -> str:
    from .diagnostics import GRID_COLS, GRID_ROWS
    from .figures import (
        map_magnification,
        residual_by_depth,
        residual_by_frame,
        residual_map,
        residual_regions,
        residual_scatter,
    )

    cal, res = ctx.calibration, list(ctx.residuals)
    if not res:
        return ""
    mag = map_magnification(cal, res)
    parts = ["<h2>Reprojection residuals</h2>",
             _img(residual_scatter(cal, res), "residual scatter",
                  "Residuals (projected minus detected pixel) of every corner, one panel per camera on the same "
                  "scale; dv is positive downwards, as v runs in the image. Dashed circle: the camera's RMSE."),
             _img(residual_map(cal, res), "residual map",
                  f"Residuals as arrows at their corners, magnified {mag:g} times (the same for every camera; the "
                  f"key arrow above each panel is drawn {mag:g} times its labelled length). Colour: the residual's "
                  "length, one scale for all cameras. A random pattern is noise; arrows that line up show what the "
                  "model misses."),
             _img(residual_regions(cal, res), "residuals by image region",
                  f"RMS residual in each cell of a {GRID_COLS} x {GRID_ROWS} grid over the image; hatched: no "
                  "corner there, where the calibration is extrapolated. Covered: the share of cells with a "
                  "calibration corner. The colour scale ends at twice the overall RMS (or the worst cell): "
                  "noise alone is mid-scale."),
             _img(residual_by_frame(cal, res), "residuals by frame",
                  "RMS residual of each image (one marker per camera, colour: calibration or glass-stacking set); "
                  "dashed: the median image. An image far above the line has a detection problem."),
             ]
    if ctx.target is not None:
        parts.append(_img(residual_by_depth(cal, res, ctx.target, ctx.inputs.points or None), "residuals by depth",
                          "Corners (top) and their RMS residual (bottom) by depth along each camera's optical axis; "
                          "shaded: the depths of the reconstructed points. Depths with few corners are where the "
                          "calibration is weakest."))
    return "\n".join(parts)


def _expansion_section(ctx: ReportContext) -> str:
    from .figures import expansion_centre_figure

    inp, cal = ctx.inputs, ctx.calibration
    stacking = {c: [o for o in inp.observations if o.set == "stacking" and o.camera == c] for c in cal.cameras}
    if not any(len({o.added_mm for o in v}) >= 2 for v in stacking.values()):
        return ""
    return ("<h2>Expansion centre</h2>"
            + _img(expansion_centre_figure(cal, stacking), "expansion centre",
                   "Paper Fig. 4: corner tracks as glass is added (red), their fitted lines (yellow; grey: "
                   "rejected), the lines' common point (green), the centre in calibration.json (blue x) and the "
                   "image of the fitted window normal, K n (+). Image axes: v down."))


def board_corners(calibration: Calibration, target: Target | None) -> np.ndarray:
    """The target's points on every calibration board pose.

    Args:
        calibration: The calibration (its board poses, ``frames``).
        target: The target, or None.

    Returns:
        World coordinates (N, 3), mm; empty (0, 3) without a target or board poses.
    """
    if target is None or not calibration.frames:
        return np.zeros((0, 3))
    _, xyz = target.points_3d()
    return np.concatenate([pose.apply(xyz) for pose in calibration.frames.values()])


def _view_3d_section(ctx: ReportContext) -> str:
    from .view_3d import rig_view_html

    cal = ctx.calibration
    boards = board_corners(cal, ctx.target)
    if not ctx.inputs.points and not len(boards):
        return ""
    return ('<section id="rig-3d-section"><h2>Rig in 3D (interactive)</h2>'
            "<p>Drag to turn, scroll to zoom, click a legend entry to hide it. World frame: cam0's (x right, "
            "y down, z along its optical axis), mm. Rays: a grid of pixels of each camera traced through the "
            "window with the exact (Snell) model's back-projection.</p>"
            + rig_view_html(cal, ctx.inputs.points, boards) + "</section>")


def _reconstruction_rows(m: Mapping[str, Any]) -> list[list[Any]]:
    """[quantity, MAE, RMSE, max] of metrics.json; a row whose three numbers repeat the previous one's
    (to the table's 4 decimals) is folded into it."""
    rows: list[list[Any]] = []
    for label, key in (("flatness: distance of each point to its frame's fitted plane (mm)", "flatness_mm"),
                       ("spacing of neighbouring corners vs the square size (mm)", "inter_corner_mm")):
        s = m.get(key)
        if s:
            rows.append([label, s["mae"], s["rmse"], s["max"]])
    st = m.get("stage")
    if st:
        for label, key in (("distance between stage planes vs the stage travel along their normal (mm)",
                            "plane_distance_error_mm"),
                           ("distance between stage planes vs the stage reading, as in the paper (mm)",
                            "plane_distance_error_paper_mm"),
                           ("stage travel measured from the corners' displacement vs the stage reading (mm)",
                            "displacement_error_mm")):
            s = st[key]
            row = [label, s["mae"], s["rmse"], s["max"]]
            same = [r for r in rows if [_fmt(v) for v in r[1:]] == [_fmt(v) for v in row[1:]]]
            if same:
                same[0][0] += f"; {label.removesuffix(' (mm)')}: the same numbers"
            else:
                rows.append(row)
    if m.get("truth"):
        t = m["truth"]
        rows.append(["3D error vs the truth after the best rigid alignment (mm)", None, t["aligned"]["rms_mm"],
                     t["aligned"]["max_mm"]])
        rows.append(["3D error vs the truth as reconstructed (mm)", None, t["unaligned"]["rms_mm"],
                     t["unaligned"]["max_mm"]])
    if m.get("reference"):
        ref = ReferenceErrors.from_json(m["reference"])
        rows.append([f"3D error vs reference {ref.kind} {Path(ref.path).name}: distance to its surface after "
                     "registration (mm)", ref.distance_mm.mean, ref.distance_mm.rms, ref.distance_mm.max])
    return rows


def _reconstruction_section(ctx: ReportContext) -> str:
    from .figures import error_histograms, point_cloud_figure, rig_figure

    inp = ctx.inputs
    m = inp.metrics
    if m is None and not inp.points:
        return "".join(f'<h2>Reconstruction</h2><p class="info">{html.escape(i)}</p>' for i in inp.info[:1])
    parts = ["<h2>Reconstruction</h2>"]
    if inp.reconstruction_label:
        parts[0] = "<h2>Reconstruction (not of this calibration or dataset)</h2>"
        parts.append(f'<p class="note">{html.escape(inp.reconstruction_label)}: its numbers are not '
                     f"those of the calibration above.</p>")
    if m is not None:
        parts.append(f"<p>{_fmt(m.get('num_points'))} points in {_fmt(m.get('num_frames'))} frames "
                     "(every corner seen by two or more cameras, triangulated through the window).</p>")
        parts.append(_table(["error", "MAE", "RMSE", "max"], _reconstruction_rows(m)))
        parts.append("<p>Paper (Sec. 5, real binocular rig): flatness MAE 0.07 mm, RMSE 0.10 mm; 10 mm corner "
                     "spacing MAE 0.008 mm, RMSE 0.011 mm; stage plane distances within 0.07 mm.</p>")
    if inp.points:
        planes = {k: f.get("plane") for k, f in (m or {}).get("frames", {}).items() if f.get("plane")}
        parts.append(_img(point_cloud_figure(inp.points, planes), "reconstructed planes",
                          "Paper Fig. 13(a): representative reconstructed frames and their fitted planes."))
        parts.append(_img(rig_figure(inp.calibration, inp.points), "rig and reconstruction",
                          "Paper Fig. 14, true to scale: the cameras (centre and optical axis), a section through "
                          "the window and the reconstructed points (colour: frame), seen from above and from the "
                          "side; y runs down as in cam0's image."))
    if m is not None:
        parts.append(_img(error_histograms(m), "reconstruction errors",
                          "Paper Fig. 13(b-d): (b) error of each stage plane's distance from the reference plane, "
                          "against the stage travel along the plane's normal and against the stage reading itself; "
                          "(c) distance of each point to its frame's plane; (d) spacing of neighbouring corners "
                          "minus the square size."))
    return "\n".join(parts)


def _comparison_section(ctx: ReportContext) -> str:
    inp = ctx.inputs
    parts = []
    if inp.compare_md is not None:
        parts.append("<h2>Model comparison</h2>" + markdown_tables(inp.compare_md))
    elif inp.compare_json is not None:
        parts.append("<h2>Model comparison</h2><pre>" + html.escape(json.dumps(inp.compare_json, indent=1)) + "</pre>")
    captions = {"residuals_scatter.png": "Residuals of every calibration corner per model, all on the same "
                                         "scale (paper Figs. 6, 9, 11); dv positive downwards as in the image.",
                "residuals_distribution.png": "Distribution of the reprojection error per model (box: quartiles, "
                                              "whiskers: min and max; log scale)."}
    for name, png in inp.compare_figures.items():
        parts.append(_img(png, f"model comparison: {name.removesuffix('.png')}",
                          "ari-sfm compare: " + captions.get(name, name.removesuffix(".png").replace("_", " "))))
    return "\n".join(parts)


def _self_calibration_section(ctx: ReportContext) -> str:
    """Volume self-calibration's disparity maps before/after (OUT/disparity.json of `self-calibrate`), if any."""
    from ..particles.figures import self_calibration_section

    return self_calibration_section(ctx.inputs.out, _img, ctx.inputs.calibration)


# The report's sections in order: (name, function). A module adding a section appends or inserts one
# entry, e.g. ``add_section("disparity", disparity_section, after="residuals")``.
SECTIONS: list[tuple[str, Section]] = [
    ("summary", _summary_section),
    ("recommendations", _advice_section),
    ("calibration", _calibration_section),
    ("stages", _stages_section),
    ("residuals", _residuals_section),
    ("expansion_centre", _expansion_section),
    ("view_3d", _view_3d_section),
    ("reconstruction", _reconstruction_section),
    ("comparison", _comparison_section),
    ("self_calibration", _self_calibration_section),
]


def add_section(name: str, render: Section, after: str | None = None) -> None:
    """Add a section to every report; a name already there is replaced in place.

    Args:
        name: The section's name in :data:`SECTIONS`.
        render: The function of a :class:`ReportContext` returning the section's HTML ("" for nothing).
        after: The name of the section to insert after; None to append at the end.
    """
    names = [n for n, _ in SECTIONS]
    if name in names:
        SECTIONS[names.index(name)] = (name, render)
        return
    SECTIONS.insert(names.index(after) + 1 if after is not None else len(SECTIONS), (name, render))


def report_context(inp: ReportInputs) -> ReportContext:
    """The inputs with their residuals computed (once, for every section)."""
    from ..calibration.evaluate import observation_residuals

    target = inp.dataset.target if inp.dataset else inp.calibration.target
    residuals = observation_residuals(inp.calibration, inp.observations, target) if inp.observations and target else []
    return ReportContext(inp, target, tuple(residuals))


def render_html(inp: ReportInputs) -> str:
    """The whole report as one HTML string."""
    ctx = report_context(inp)
    parts = [f"<h1>ari-sfm report: {html.escape(inp.out.name)}</h1>"]
    parts += [f'<p class="note">{html.escape(n)}</p>' for n in inp.notes]
    parts += [html_part for _, section in SECTIONS if (html_part := section(ctx))]
    body = "\n".join(parts)
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>ari-sfm report: "
            f"{html.escape(inp.out.name)}</title><style>{CSS}</style></head><body>\n{body}\n</body></html>\n")


def write_report(out: str | Path, dataset: str | Path | None = None) -> Path:
    """Render OUT/report.html atomically.

    Args:
        out: The output folder (OUT).
        dataset: The dataset folder; None to find it (:func:`find_dataset`).

    Returns:
        The path of report.html.

    Raises:
        AriSfmError: As :func:`load_inputs`.
    """
    from ..io import write_text_atomic

    inputs = load_inputs(out, dataset)
    text = render_html(inputs)
    path = Path(out) / REPORT_FILE
    write_text_atomic(path, text)
    return path

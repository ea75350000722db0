"""The accuracy report: one self-contained ``report.html`` for an output folder.

``write_report(out)`` reads what ``ari-sfm run`` (or ``calibrate``,
``reconstruct``, ``compare``) wrote to OUT and renders one HTML file with
every figure embedded as a base64 PNG (no external resource: it opens
offline and can be mailed):

- OUT/calibration.json (required): rig summary and the calibration table,
  every parameter with its standard deviation (``uncertainty``).
- the observations: OUT/observations.json when corners were detected
  there, else the dataset's own; residuals per camera and the stacking
  tracks (paper Fig. 4) need them.
- OUT/points.json and OUT/metrics.json (optional): Figs. 13 and 14.
- OUT/compare.md or OUT/compare.json (optional): the model comparison, and its PNG figures.

The dataset is found from, in order: the ``dataset`` argument, OUT/run.json
(written by ``ari-sfm run``: ``{"format": "ari-sfm-run/1", "dataset":
<absolute path>, ...}``), metrics.json's ``provenance.dataset.path``, then its
``dataset`` if absolute (a relative one, written by older versions, was
relative to a working folder nobody recorded: it is not guessed). Without it
the report still has the calibration and, from OUT/observations.json, the residuals.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .calibration import Calibration, load_calibration
from .errors import AriSfmError
from .records import Dataset, Observation

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
    notes: tuple[str, ...] = ()  # what is missing, shown at the top
    reconstruction_label: str | None = None  # why the reconstruction does not belong to this calibration / dataset


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise AriSfmError(path, f"cannot read: {exc}") from None
    if not isinstance(data, dict):
        raise AriSfmError(path, "expected a JSON object")
    return data


def find_dataset(out: Path, dataset: str | Path | None = None) -> Path | None:
    """The dataset folder of an output folder (see the module docstring), or None."""
    from .provenance import recorded_dataset_path

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
    return next((c for c in candidates if c.exists()), None)


def load_inputs(out: str | Path, dataset: str | Path | None = None) -> ReportInputs:
    """Load OUT's files for the report; a missing calibration.json or a bad file raise AriSfmError."""
    from .io import load_dataset, load_observations, load_points

    out = Path(out)
    if not out.is_dir():
        raise AriSfmError(out, "no such output folder")
    cal_path = out / "calibration.json"
    if not cal_path.exists():
        raise AriSfmError(cal_path, "missing: run `ari-sfm run` or `ari-sfm calibrate` with -o to this folder first")
    cal = load_calibration(cal_path)
    notes: list[str] = []
    ds_path = find_dataset(out, dataset)
    obs_path = out / "observations.json"
    ds = None
    if ds_path is not None:
        from .reconstruct import check_rig

        ds = load_dataset(ds_path, obs_path if obs_path.exists() else None)
        check_rig(ds, cal, cal_path)  # another rig's dataset: refused, not mixed in
    else:
        notes.append("dataset not found (pass --dataset): no dataset summary")
    if ds is not None and ds.observations is not None:
        observations = ds.observations
    elif obs_path.exists():
        observations = load_observations(obs_path, cal.target, list(cal.cameras))
    else:
        observations = ()
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
    if metrics is None and not points:
        notes.append("no reconstruction (points.json, metrics.json) in this folder")
    elif (out / RUN_FILE).exists() and _read_json(out / RUN_FILE).get("reconstruction_skipped"):
        notes.append("the last `ari-sfm run` here skipped the reconstruction: points.json and metrics.json "
                     "are older than its calibration")
    md = (out / "compare.md").read_text() if (out / "compare.md").exists() else None
    cj = _read_json(out / "compare.json") if (out / "compare.json").exists() else None
    from .compare import FIGURES

    figs = {name: (out / name).read_bytes() for name in FIGURES if (out / name).exists()}
    return ReportInputs(out, cal, ds, ds_path, tuple(observations), metrics, points, md, cj, figs, tuple(notes), label)


def _reconstruction_label(out: Path, cal_path: Path, cal: Calibration, ds: Dataset | None,
                          metrics: dict | None, points: dict | None) -> str | None:
    """Why OUT's points.json / metrics.json do not belong to its calibration.json or the dataset, or None."""
    from .provenance import calibration_mismatch, dataset_mismatch

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
body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:0.6em 0}
td,th{border:1px solid #bbb;padding:2px 8px;text-align:left;font-size:0.9em}
th{background:#eee}
td.n{text-align:right;font-variant-numeric:tabular-nums}
img{max-width:100%;display:block;margin:0.5em 0}
.note{color:#a40}
figcaption{font-size:0.85em;color:#555}
"""


def _fmt(x: Any, digits: int = 4) -> str:
    if x is None:
        return "&ndash;"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        return "nan" if not np.isfinite(x) else f"{x:.{digits}f}"
    return html.escape(str(x))


def _table(header: list[str], rows: list[list[Any]], digits: int = 4) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    def cell(v: Any) -> str:
        num = isinstance(v, (int, float, np.integer, np.floating)) or v is None
        return f'<td class="n">{_fmt(v, digits)}</td>' if num else f"<td>{_fmt(v, digits)}</td>"

    body = "".join("<tr>" + "".join(cell(v) for v in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


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
    unc = cal.uncertainty.to_json() if cal.uncertainty is not None else {}  # the table reads the records' fields by name
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
        if cal.normal_world is not None:
            n = cal.normal_cam(name)
            tilt = float(np.degrees(np.arccos(np.clip(n[2], -1, 1))))
            rows.append([name, "window tilt to the optical axis (deg)", tilt, unc.get("normal_deg")])
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
    if cal.normal_world is not None:
        n = cal.normal_world
        rows.append(["window", "normal (world); std: angle (deg)", f"[{n[0]:+.5f} {n[1]:+.5f} {n[2]:+.5f}]",
                     unc.get("normal_deg")])
    if cal.interface.distance_mm is not None:
        rows.append(["window", "distance (mm)", cal.interface.distance_mm, unc.get("distance_mm")])
    return rows


def _summary_section(inp: ReportInputs) -> str:
    cal = inp.calibration
    i = cal.interface
    rows: list[list[Any]] = [["model", cal.model], ["cameras", ", ".join(cal.cameras)],
                             ["window", f"{i.thickness_mm:g} mm, n = {i.index:g}, medium n = {i.medium_index:g}"]]
    target = inp.dataset.target if inp.dataset else cal.target
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
        rows.append(["stacking", f"{len({e.key for e in ds.stacking})} pose(s), added glass "
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
        rows.append(["reprojection", f"rmse {r.rmse_px:.4f} px, mae {r.mae_px:.4f} px, max {r.max_px:.4f} px "
                                     f"over {r.count} corners"])
    if cal.uncertainty is not None:
        rows.append(["residual sigma", f"{cal.uncertainty.sigma_px:.4f} px (scales the standard deviations below)"])
    return "<h2>Dataset and rig</h2>" + _table(["", ""], rows).replace("<tr><th></th><th></th></tr>", "", 1)


def _reconstruction_section(inp: ReportInputs) -> str:
    from .report_figures import error_histograms, point_cloud_figure, rig_figure

    m = inp.metrics
    parts = ["<h2>Reconstruction</h2>"]
    if inp.reconstruction_label:
        parts[0] = "<h2>Reconstruction (not of this calibration or dataset)</h2>"
        parts.append(f'<p class="note">{html.escape(inp.reconstruction_label)}: its numbers are not '
                     f"those of the calibration above.</p>")
    if m is not None:
        rows: list[list[Any]] = [["points", m.get("num_points"), "", ""], ["frames", m.get("num_frames"), "", ""]]
        for label, key in (("flatness (point to plane)", "flatness_mm"), ("inter-corner distance error", "inter_corner_mm")):
            s = m.get(key)
            if s:
                rows.append([f"{label} (mm)", s["mae"], s["rmse"], s["max"]])
        if m.get("stage"):
            for label, key in (("plane distance error (mm)", "plane_distance_error_mm"),
                               ("plane distance error vs s - s_ref (mm)", "plane_distance_error_paper_mm"),
                               ("stage displacement error (mm)", "displacement_error_mm")):
                s = m["stage"][key]
                rows.append([label, s["mae"], s["rmse"], s["max"]])
        if m.get("truth"):
            t = m["truth"]
            rows.append(["3D error vs truth after rigid alignment (mm)", None, t["aligned"]["rms_mm"], t["aligned"]["max_mm"]])
            rows.append(["3D error vs truth, unaligned (mm)", None, t["unaligned"]["rms_mm"], t["unaligned"]["max_mm"]])
        if m.get("reference"):
            ref = m["reference"]
            rows.append([f"3D error vs reference {ref['kind']} {Path(ref['path']).name}, point to surface after "
                         f"registration (mm)", ref["distance_mm"]["mean"], ref["distance_mm"]["rms"],
                         ref["distance_mm"]["max"]])
        parts.append(_table(["", "MAE", "RMSE", "max"], rows))
        parts.append("<p>Paper (Sec. 5, real binocular rig): flatness MAE 0.07 mm, RMSE 0.10 mm; 10 mm inter-corner "
                     "distances MAE 0.008 mm, RMSE 0.011 mm; plane distances within 0.07 mm.</p>")
    if inp.points:
        planes = {k: f.get("plane") for k, f in (m or {}).get("frames", {}).items() if f.get("plane")}
        parts.append(_img(point_cloud_figure(inp.points, planes), "reconstructed planes",
                          "Fig. 13(a) style: representative reconstructed frames and their fitted planes."))
        parts.append(_img(rig_figure(inp.calibration, inp.points), "rig and reconstruction",
                          "Fig. 14 style: cameras (axes x red, y green, z blue), window and reconstructed points "
                          "(the window dashed, at a schematic depth, where the calibration cannot observe its "
                          "distance: in air)."))
    if m is not None:
        parts.append(_img(error_histograms(m), "reconstruction errors",
                          "Fig. 13(b-d) style: plane-distance error per stage frame, flatness, inter-corner errors."))
    return "\n".join(parts)


def render_html(inp: ReportInputs) -> str:
    """The whole report as one HTML string."""
    from .evaluate import observation_residuals
    from .report_figures import expansion_centre_figure, residual_map, residual_scatter

    cal = inp.calibration
    target = inp.dataset.target if inp.dataset else cal.target
    parts = [f"<h1>ari-sfm report: {html.escape(inp.out.name)}</h1>"]
    parts += [f'<p class="note">{html.escape(n)}</p>' for n in inp.notes]
    parts.append(_summary_section(inp))
    parts.append("<h2>Calibration</h2>")
    parts.append(_table(["camera", "parameter", "value", "std dev"], calibration_rows(cal)))
    residuals = observation_residuals(cal, inp.observations, target) if inp.observations and target else []
    if residuals:
        parts.append("<h2>Reprojection residuals</h2>")
        parts.append(_img(residual_scatter(cal, residuals), "residual scatter",
                          "Residuals (projected - detected) per camera; dashed circle: RMSE."))
        parts.append(_img(residual_map(cal, residuals), "residual map",
                          "Residual vectors across each image (magnified), coloured by length."))
    stacking = {c: [o for o in inp.observations if o.set == "stacking" and o.camera == c] for c in cal.cameras}
    if any(len({o.added_mm for o in v}) >= 2 for v in stacking.values()):
        parts.append("<h2>Expansion centre</h2>")
        parts.append(_img(expansion_centre_figure(cal, stacking), "expansion centre",
                          "Fig. 4 style: corner tracks as glass is added (red), TLS lines (yellow), their common "
                          "point (green), the centre in calibration.json (blue x) and K n of the fitted normal (+)."))
    if inp.metrics is not None or inp.points:
        parts.append(_reconstruction_section(inp))
    if inp.compare_md is not None:
        parts.append("<h2>Model comparison</h2>" + markdown_tables(inp.compare_md))
    elif inp.compare_json is not None:
        parts.append("<h2>Model comparison</h2><pre>" + html.escape(json.dumps(inp.compare_json, indent=1)) + "</pre>")
    for name, png in inp.compare_figures.items():
        parts.append(_img(png, f"model comparison: {name.removesuffix('.png')}",
                          "ari-sfm compare (paper Figs. 6, 9, 11 style): " + name.removesuffix(".png").replace("_", " ")))
    from .particles.figures import self_calibration_section

    parts.append(self_calibration_section(inp.out, _img))  # OUT/disparity.json of `self-calibrate`, if any
    body = "\n".join(parts)
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>ari-sfm report: "
            f"{html.escape(inp.out.name)}</title><style>{CSS}</style></head><body>\n{body}\n</body></html>\n")


def write_report(out: str | Path, dataset: str | Path | None = None) -> Path:
    """Render OUT/report.html atomically; return its path."""
    from .io import write_text_atomic

    inputs = load_inputs(out, dataset)
    text = render_html(inputs)
    path = Path(out) / REPORT_FILE
    write_text_atomic(path, text)
    return path

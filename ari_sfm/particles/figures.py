"""Self-calibration's figures for the report: disparity maps before and after (PNG bytes)."""
from __future__ import annotations

import html
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from ari_sfm.calibration.record import Calibration

DISPARITY_FILE = "disparity.json"


def disparity_figure(disparity: dict[str, Any]) -> bytes:
    """Disparity maps before and after self-calibration, one row per camera.

    Each cell's disparity vector (px) is drawn at the cell's centre (world x, y; z layers in colour, side
    by side), on one arrow scale for every panel (the longest arrow about half a cell), so corrected arrows
    look as small as they are; a scale arrow of 1 px in each panel.

    Args:
        disparity: The content of OUT/disparity.json (``cells``, ``cell_centres_mm``, ``before``, ``after``).

    Returns:
        The figure's PNG bytes.
    """
    from ..report.figures import plt, to_png

    centres = np.asarray(disparity["cell_centres_mm"], float)
    lower, upper = (np.asarray(disparity["cells"][k], float) for k in ("lower_mm", "upper_mm"))
    shape = disparity["cells"]["shape"]
    layer = np.arange(len(centres)) // (shape[0] * shape[1])
    cameras = list(disparity["before"]["cameras"])

    def vectors(when: str, cam: str) -> np.ndarray:
        return np.array([[np.nan, np.nan] if v[0] is None else v for v in disparity[when]["cameras"][cam]["vector_px"]],
                        float)

    cell = float(np.min((upper - lower)[:2] / np.asarray(shape[:2])))
    longest = max(float(np.nanmax(np.linalg.norm(vectors(w, c), axis=1), initial=0.0))
                  for w in ("before", "after") for c in cameras)
    one = 0.45 * cell / longest if longest > 0 else 1.0  # mm per px: the longest arrow about half a cell
    scale = {"before": one, "after": one}
    shift = (layer - 0.5 * (shape[2] - 1)) * 0.12 * cell  # z layers side by side
    fig, axes = plt.subplots(len(cameras), 2, figsize=(9.0, 3.2 * len(cameras)), squeeze=False)
    colours = plt.cm.viridis(np.linspace(0.0, 0.85, max(shape[2], 1)))
    for row, cam in enumerate(cameras):
        for col, when in enumerate(("before", "after")):
            ax = axes[row][col]
            v = vectors(when, cam)
            ok = np.isfinite(v).all(axis=1)
            for z in range(shape[2]):
                m = ok & (layer == z)
                ax.quiver(centres[m, 0] + shift[m], centres[m, 1], v[m, 0] * scale[when], v[m, 1] * scale[when],
                          angles="xy",
                          scale_units="xy", scale=1.0, color=colours[z], width=0.006,
                          label=f"z {centres[layer == z, 2].mean():.0f} mm" if row == 0 and col == 0 else None)
            ax.plot(centres[~ok, 0], centres[~ok, 1], "x", color="0.6", ms=4)
            ax.set_xlim(lower[0], upper[0])
            ax.set_ylim(upper[1], lower[1])  # y down, as in the images
            ax.set_aspect("equal")
            rms = disparity[when]["cameras"][cam]["rms_px"]
            ax.annotate("", xy=(lower[0] + 0.04 * (upper[0] - lower[0]) + one, lower[1] + 0.06 * (upper[1] - lower[1])),
                        xytext=(lower[0] + 0.04 * (upper[0] - lower[0]), lower[1] + 0.06 * (upper[1] - lower[1])),
                        arrowprops={"arrowstyle": "->", "color": "k", "lw": 1.0})
            ax.text(lower[0] + 0.04 * (upper[0] - lower[0]), lower[1] + 0.13 * (upper[1] - lower[1]), "1 px",
                    fontsize=7)
            ax.set_title(f"{cam} {when}: RMS {rms:.3f} px (1 px = {one:.2g} mm)", fontsize=9)
            ax.tick_params(labelsize=7)
            if row == len(cameras) - 1:
                ax.set_xlabel("world x (mm)", fontsize=8)
            if col == 0:
                ax.set_ylabel("world y (mm)", fontsize=8)
    axes[0][0].legend(fontsize=7, loc="upper right")
    fig.suptitle("disparity per cell, detected minus reprojected (x: too few particles)", fontsize=10)
    fig.tight_layout()
    return to_png(fig)


def self_calibration_section(out: Path, image: Any, calibration: Calibration | None = None) -> str:
    """The report's section for a self-calibration folder.

    Args:
        out: The output folder (OUT), holding disparity.json.
        image: Renders a figure as the report does: ``image(png, alt, caption)`` -> HTML.
        calibration: The folder's calibration (its ``self_calibration`` record), or None.

    Returns:
        The section's HTML, or "" without OUT/disparity.json.
    """
    path = Path(out) / DISPARITY_FILE
    if not path.is_file():
        return ""
    disparity = json.loads(path.read_text())
    sc = None if calibration is None else calibration.self_calibration

    def num(v: float | None, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    def sigma(cam: str, rotation: bool) -> float | None:
        s = None if sc is None else sc.sigmas.get(cam)
        return None if s is None else (s.rotation_rel_deg if rotation else s.translation_rel_mm)

    rows = "".join(f"<tr><td>{html.escape(cam)}</td><td>{disparity['before']['cameras'][cam]['rms_px']:.3f}</td>"
                   f"<td>{disparity['after']['cameras'][cam]['rms_px']:.3f}</td>"
                   f"<td>{num(None if sc is None else sc.rotation_change_deg.get(cam), '.4f')}</td>"
                   f"<td>{num(sigma(cam, True), '.4f')}</td><td>{num(sigma(cam, False), '.3f')}</td></tr>"
                   for cam in disparity["before"]["cameras"])
    table = ("<table><tr><th>camera</th><th>disparity RMS before (px)</th><th>after (px)</th>"
             "<th>rotated (deg)</th><th>sigma of its rotation relative to the first camera (deg)</th>"
             f"<th>sigma of its position relative to the first camera (mm)</th></tr>{rows}</table>")
    parts = ["<h2>Volume self-calibration</h2>"]
    if sc is not None:
        verdict = "passed its checks" if sc.passed else "FAILED its checks: do not use it"
        parts.append(f"<p>The self-calibration {html.escape(verdict)}; {sc.particles_used} particles in "
                     f"{len(sc.frames)} frames, {100 * sc.matched_share:.1f} % of the particle images matched at "
                     "the end.</p>")
        parts.append("<p>Held: " + html.escape("; ".join(sc.held)) + ". Estimated: "
                     + html.escape("; ".join(sc.estimated)) + ".</p>")
    parts.append(table)
    if sc is not None and sc.checks:
        parts.append("<table><tr><th>check</th><th>value</th><th>limit</th><th>result</th><th>what</th></tr>"
                     + "".join(f"<tr><td>{html.escape(c.name)}</td><td>{c.value:.4g}</td><td>{c.limit:.4g}</td>"
                               f"<td>{'passed' if c.passed else ('FAILED' if c.fatal else 'warning')}</td>"
                               f"<td>{html.escape(c.what)}</td></tr>" for c in sc.checks) + "</table>")
    parts.append(image(disparity_figure(disparity), "disparity maps",
                       "Mean disparity (detected minus reprojected particle image) per cell of the volume and "
                       "camera, with the starting calibration (loose matches) and the corrected one, on one "
                       "arrow scale."))
    return "\n".join(parts)

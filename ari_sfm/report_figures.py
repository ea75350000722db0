"""The report's figures (matplotlib, Agg): each function returns PNG bytes.

- :func:`residual_scatter` and :func:`residual_map`: reprojection residuals
  per camera, as (du, dv) scatter and as vectors across the image.
- :func:`expansion_centre_figure`: the paper's Fig. 4, corner tracks under
  plate stacking, their TLS lines and common point.
- :func:`point_cloud_figure`: Fig. 13a, the reconstructed frames in 3D with
  their fitted planes; :func:`rig_figure`: Fig. 14, the cameras, the window
  and the reconstruction in one frame.
- :func:`error_histograms`: Fig. 13b-d, plane-distance errors per stage
  frame, flatness and inter-corner distance errors.
"""
from __future__ import annotations

import io
from typing import Any, Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .calibration import Calibration  # noqa: E402
from .records import Observation  # noqa: E402

DPI = 90
SET_COLORS = {"calibration": "tab:blue", "stacking": "tab:orange", "reconstruction": "tab:green"}


def to_png(fig: Any) -> bytes:
    """PNG bytes of a figure (closed afterwards)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def _grid(n: int, width: float = 5.0, height: float = 4.2, projection: str | None = None,
          layout: str | None = None) -> tuple[Any, list]:
    cols = min(n, 2)
    rows = (n + cols - 1) // cols
    fig = plt.figure(figsize=(width * cols, height * rows), layout=layout)
    axes = [fig.add_subplot(rows, cols, k + 1, projection=projection) for k in range(n)]
    return fig, axes


Residuals = Sequence[tuple[Observation, np.ndarray]]  # evaluate.observation_residuals


def residual_scatter(calibration: Calibration, residuals: Residuals) -> bytes:
    """(du, dv) of every corner, one panel per camera, coloured by set, with the RMSE circle."""
    names = list(calibration.cameras)
    fig, axes = _grid(len(names), 4.6, 4.4)
    for ax, name in zip(axes, names):
        mine = [(o, r) for o, r in residuals if o.camera == name]
        allr = np.concatenate([r for _, r in mine]) if mine else np.zeros((0, 2))
        for set_name, color in SET_COLORS.items():
            r = [r for o, r in mine if o.set == set_name]
            if r:
                r = np.concatenate(r)
                ax.scatter(r[:, 0], r[:, 1], s=3, alpha=0.5, color=color, label=f"{set_name} ({len(r)})")
        rmse = float(np.sqrt(np.mean(np.sum(allr**2, axis=1)))) if len(allr) else float("nan")
        ax.add_patch(plt.Circle((0, 0), rmse, fill=False, color="k", lw=1, ls="--"))
        lim = max(float(np.abs(allr).max()) * 1.1, 1e-3) if len(allr) else 1.0
        ax.set(xlim=(-lim, lim), ylim=(lim, -lim), aspect="equal", xlabel="du (px)", ylabel="dv (px)",
               title=f"{name}: rmse {rmse:.4f} px")
        ax.axhline(0, color="0.7", lw=0.5)
        ax.axvline(0, color="0.7", lw=0.5)
        ax.legend(loc="upper right", fontsize=7, markerscale=3)
    return to_png(fig)


def residual_map(calibration: Calibration, residuals: Residuals) -> bytes:
    """Each corner's residual as a vector at its pixel (magnified), coloured by its length."""
    return to_png(draw_residual_map(calibration, residuals))


def draw_residual_map(calibration: Calibration, residuals: Residuals) -> Any:
    """The figure of :func:`residual_map`. Constrained layout keeps each colour bar and its label clear
    of the next panel (they overlapped its axis)."""
    names = list(calibration.cameras)
    fig, axes = _grid(len(names), 5.4, 4.6, layout="constrained")
    for ax, name in zip(axes, names):
        w, h = calibration.cameras[name].image_size
        mine = [(o, r) for o, r in residuals if o.camera == name]
        ax.add_patch(plt.Rectangle((0, 0), w, h, fill=False, color="k", lw=1))
        if mine:
            uv = np.concatenate([o.pixels for o, _ in mine])
            r = np.concatenate([r for _, r in mine])
            mag = np.linalg.norm(r, axis=1)
            scale = 0.04 * max(w, h) / max(float(np.percentile(mag, 95)), 1e-9)  # p95 residual = 4% of the image
            sc = ax.scatter(uv[:, 0], uv[:, 1], c=mag, s=4, cmap="viridis")
            ax.quiver(uv[:, 0], uv[:, 1], r[:, 0] * scale, r[:, 1] * scale, mag, angles="xy", scale_units="xy",
                      scale=1, cmap="viridis", width=0.002)
            fig.colorbar(sc, ax=ax, label="|residual| (px)")
            ax.set_title(f"{name}: residuals x{scale:.0f}")
        else:
            ax.set_title(f"{name}: no corners")
        ax.set(xlim=(0, w), ylim=(h, 0), aspect="equal", xlabel="u (px)", ylabel="v (px)")
    return fig


def expansion_centre_figure(calibration: Calibration, stacking: Mapping[str, Sequence[Observation]]) -> bytes:
    """Fig. 4: corner tracks under stacking (points), TLS lines, measured and calibrated expansion centres."""
    from .init.expansion_center import fit_lines, intersect_lines, trajectories

    names = [n for n in calibration.cameras if stacking.get(n)]
    fig, axes = _grid(len(names), 5.4, 4.6)
    for ax, name in zip(axes, names):
        w, h = calibration.cameras[name].image_size
        obs = stacking[name]
        tracks = trajectories(obs)
        lines = fit_lines(obs)
        ax.add_patch(plt.Rectangle((0, 0), w, h, fill=False, color="k", lw=1))
        for pts in tracks.values():
            ax.plot(pts[:, 0], pts[:, 1], ".", color="tab:red", ms=2)
        xs = [0.0, float(w)]
        ys = [0.0, float(h)]
        title = name
        if len(lines) >= 2:
            ec = intersect_lines(lines)
            c = ec.center_px
            for ln, ok in zip(lines, ec.inliers):
                t = (c - ln.centroid) @ ln.direction
                seg = ln.centroid + np.outer([0.0, t], ln.direction)
                ax.plot(seg[:, 0], seg[:, 1], "-", color="gold" if ok else "0.6", lw=0.4, alpha=0.7)
            ax.plot(*c, "o", color="tab:green", ms=7, label=f"measured ({c[0]:.1f}, {c[1]:.1f}) ±{max(ec.std_px):.2f}")
            xs.append(float(c[0]))
            ys.append(float(c[1]))
            title = f"{name}: {len(lines)} tracks, {int(ec.inliers.sum())} inliers"
        cal_c = calibration.cameras[name].expansion_center_px
        if cal_c is not None:
            ax.plot(*cal_c, "x", color="tab:blue", ms=9, mew=2, label="in calibration.json")
            xs.append(float(cal_c[0]))
            ys.append(float(cal_c[1]))
        if calibration.normal_world is not None:  # the model's own centre: K n_cam
            n = calibration.normal_cam(name)
            if n[2] > 1e-6:
                p = calibration.cameras[name].K @ (n / n[2])
                ax.plot(p[0], p[1], "+", color="tab:purple", ms=11, mew=1.5, label="K n (fitted normal)")
        pad = 0.05 * max(w, h)
        ax.set(xlim=(min(xs) - pad, max(xs) + pad), ylim=(max(ys) + pad, min(ys) - pad), aspect="equal",
               xlabel="u (px)", ylabel="v (px)", title=title)
        ax.legend(loc="lower left", fontsize=7)
    return to_png(fig)


def _representative(names: Sequence[str], k: int = 6) -> list[str]:
    """Up to k frames spread evenly over the list (the paper shows 6 of 11)."""
    if len(names) <= k:
        return list(names)
    return [names[int(round(i))] for i in np.linspace(0, len(names) - 1, k)]


def _plane_patch(ax: Any, xyz: np.ndarray, normal: np.ndarray, point: np.ndarray, color: Any) -> None:
    """Draw the fitted plane over the extent of the frame's points."""
    c = _plane_outline(xyz, normal, point)
    P = np.array([[c[0], c[1]], [c[3], c[2]]])  # (2, 2, 3) grid of the rectangle's corners
    ax.plot_surface(P[..., 0], P[..., 1], P[..., 2], color=color, alpha=0.15, linewidth=0)


def _plane_outline(xyz: np.ndarray, normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """The closed outline (5, 3) of the patch :func:`_plane_patch` draws for the same points."""
    n = np.asarray(normal, float)
    a = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    s, t = (xyz - point) @ a, (xyz - point) @ b
    corners = [(s.min(), t.min()), (s.max(), t.min()), (s.max(), t.max()), (s.min(), t.max()), (s.min(), t.min())]
    return np.array([point + u * a + v * b for u, v in corners])


def point_cloud_figure(frames: Mapping[str, np.ndarray], planes: Mapping[str, Mapping[str, Any]]) -> bytes:
    """Fig. 13a: representative reconstructed frames (points and fitted planes), world frame, mm."""
    fig = plt.figure(figsize=(7.5, 6))
    ax = fig.add_subplot(111, projection="3d")
    chosen = _representative(list(frames))
    cmap = plt.get_cmap("viridis")
    for k, name in enumerate(chosen):
        xyz = frames[name]
        color = cmap(k / max(len(chosen) - 1, 1))
        ax.scatter(xyz[:, 0], xyz[:, 1], xyz[:, 2], s=4, color=color, label=name)
        plane = planes.get(name)
        if plane and plane.get("normal") is not None:
            _plane_patch(ax, xyz, np.asarray(plane["normal"]), np.asarray(plane["point"]), color)
    ax.set(xlabel="x (mm)", ylabel="y (mm)", zlabel="z (mm)",
           title=f"{len(chosen)} of {len(frames)} reconstructed frames")
    ax.legend(fontsize=7, loc="upper left")
    return to_png(fig)


def rig_figure(calibration: Calibration, frames: Mapping[str, np.ndarray]) -> bytes:
    """Fig. 14: camera centres and axes, the window (near surface) and the reconstructed points."""
    return to_png(draw_rig(calibration, frames))


def draw_rig(calibration: Calibration, frames: Mapping[str, np.ndarray]) -> Any:
    """The figure of :func:`rig_figure`. Where the calibration does not observe the window's distance
    (in air it does not change any pixel), the window is drawn dashed halfway to the target and the
    legend says its depth is schematic."""
    fig = plt.figure(figsize=(7.5, 6))
    ax = fig.add_subplot(111, projection="3d")
    allxyz = np.concatenate(list(frames.values())) if frames else np.zeros((0, 3))
    centres = []
    for name, cam in calibration.cameras.items():
        world_from_cam = cam.cam_from_world.inverse()
        c = world_from_cam.t
        centres.append(c)
        ax.scatter(*c, color="k", s=20)
        ax.text(*c, f" {name}", fontsize=8)
        axis_len = 40.0
        for k, color in enumerate(("r", "g", "b")):
            tip = c + world_from_cam.R[:, k] * axis_len
            ax.plot(*np.c_[c, tip], color=color, lw=1.2)
    if len(allxyz):
        ax.scatter(allxyz[:, 0], allxyz[:, 1], allxyz[:, 2], s=1, color="tab:gray", alpha=0.6)
    n = calibration.normal_world
    if n is not None:
        centres_arr = np.array(centres)
        d = calibration.interface.distance_mm
        schematic = d is None
        if schematic:  # not observable in air: draw it halfway to the target for orientation only
            d = 0.5 * float(np.median(allxyz @ n)) if len(allxyz) else 50.0
        pts = np.vstack([centres_arr, allxyz]) if len(allxyz) else centres_arr
        foot = pts - np.outer(pts @ n - d, n)  # projections onto the near surface
        _plane_patch(ax, foot, n, n * d, "tab:cyan")
        label = f"window ({calibration.interface.thickness_mm:g} mm)"
        if schematic:
            outline = _plane_outline(foot, n, n * d)
            ax.plot(outline[:, 0], outline[:, 1], outline[:, 2], ls="--", color="tab:cyan", lw=1)
            label += ", depth schematic: its distance is not observable in air"
        else:
            label += f" at {d:.1f} mm"
        ax.plot([], [], color="tab:cyan", lw=4, alpha=0.4, ls="--" if schematic else "-", label=label)
        ax.legend(fontsize=7, loc="upper left")
    span = np.vstack([np.array(centres), allxyz]) if len(allxyz) else np.array(centres)
    ax.set_box_aspect(np.maximum(np.ptp(span, axis=0), 1e-3 * np.ptp(span).max() + 1e-9))  # true proportions
    ax.set(xlabel="x (mm)", ylabel="y (mm)", zlabel="z (mm)", title="rig, window and reconstruction (world frame)")
    return fig


def error_histograms(metrics: Mapping[str, Any]) -> bytes:
    """Fig. 13b-d: plane-distance error per stage frame, flatness and inter-corner distance errors."""
    panels = []
    stage_frames = {k: f for k, f in metrics.get("frames", {}).items() if f.get("plane_distance_error_mm") is not None}
    if stage_frames:
        panels.append("stage")
    if metrics.get("flatness_mm", {}).get("distances"):
        panels.append("flatness")
    if metrics.get("inter_corner_mm") and metrics["inter_corner_mm"].get("errors"):
        panels.append("corners")
    fig, axes = plt.subplots(1, max(len(panels), 1), figsize=(4.6 * max(len(panels), 1), 3.8), squeeze=False)
    axes = axes[0]
    for ax, panel in zip(axes, panels):
        if panel == "stage":
            names = list(stage_frames)
            err = [stage_frames[n]["plane_distance_error_mm"] for n in names]
            paper = [stage_frames[n]["plane_distance_error_paper_mm"] for n in names]
            x = np.arange(len(names))
            ax.bar(x - 0.2, err, 0.4, label="vs (s - s_ref) cos(theta)")
            ax.bar(x + 0.2, paper, 0.4, label="vs s - s_ref (paper)")
            ax.set_xticks(x, [f"{stage_frames[n]['stage_mm']:g}" for n in names], fontsize=7)
            ax.set(xlabel="stage (mm)", ylabel="plane distance error (mm)", title="(b) plane distances")
            ax.axhline(0, color="k", lw=0.5)
            ax.legend(fontsize=7)
        elif panel == "flatness":
            d = np.asarray(metrics["flatness_mm"]["distances"], float)
            f = metrics["flatness_mm"]
            ax.hist(d, bins=40, color="tab:blue")
            ax.set(xlabel="point-to-plane distance (mm)", ylabel="corners",
                   title=f"(c) flatness: MAE {f['mae']:.4f}, RMSE {f['rmse']:.4f} mm")
        else:
            ic = metrics["inter_corner_mm"]
            ax.hist(np.asarray(ic["errors"], float), bins=40, color="tab:green")
            ax.set(xlabel=f"distance - {ic['square_mm']:g} mm (mm)", ylabel="pairs",
                   title=f"(d) inter-corner: MAE {ic['mae']:.4f}, RMSE {ic['rmse']:.4f} mm")
    if not panels:
        axes[0].text(0.5, 0.5, "no errors to show", ha="center", va="center")
        axes[0].set_axis_off()
    fig.tight_layout()
    return to_png(fig)

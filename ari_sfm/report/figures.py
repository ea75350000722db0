"""The report's figures (matplotlib, Agg): each ``draw_*`` returns a Figure, each public name its PNG bytes.

Made for print: every figure is ``FIG_WIDTH_IN`` wide and shown at the page's
full width, so its fonts print at ``size * PRINT_WIDTH_IN / FIG_WIDTH_IN``
(>= 9 pt with :data:`STYLE`; tests/test_report_figures.py checks every text).
Panels of several cameras share their axis ranges, tick steps and colour
scales; image axes run like the image (u right, v down) and say so.

- :func:`residual_scatter`, :func:`residual_map`: reprojection residuals per
  camera, as (du, dv) scatter and as magnified vectors across the image;
- :func:`residual_regions`: RMS residual per image cell (and where no corner
  fell); :func:`residual_by_frame`; :func:`residual_by_depth`;
- :func:`expansion_centre_figure`: the paper's Fig. 4, corner tracks under
  plate stacking, their TLS lines and common point;
- :func:`point_cloud_figure`: Fig. 13a; :func:`rig_figure`: Fig. 14, the rig,
  the window and the reconstruction seen from above and from the side;
- :func:`error_histograms`: Fig. 13b-d.
"""
from __future__ import annotations

import functools
import io
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from ..calibration.record import Calibration  # noqa: E402
from ..records import Observation, Target  # noqa: E402
from .diagnostics import corner_depths, frame_rmse, point_depths, region_grid, rms  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.typing import RcKeyType

DPI = 150
FIG_WIDTH_IN = 8.0  # every figure; shown at the page's width
PRINT_WIDTH_IN = 7.0  # the text width of an A4 / letter page: what FIG_WIDTH_IN prints at
STYLE: dict[RcKeyType, Any] = {  # smallest 10.5 pt -> 9.2 pt printed
    "font.size": 11, "axes.titlesize": 11.5, "axes.labelsize": 11, "xtick.labelsize": 10.5, "ytick.labelsize": 10.5,
    "legend.fontsize": 10.5, "figure.titlesize": 12, "figure.dpi": DPI, "axes.titlelocation": "left"}
SET_COLORS = {"calibration": "tab:blue", "stacking": "tab:orange", "reconstruction": "tab:green"}
CAMERA_MARKERS = "os^Dv<>p"

Residuals = Sequence[tuple[Observation, np.ndarray]]  # evaluate.observation_residuals


def styled(draw: Callable[..., Any]) -> Callable[..., Any]:
    """Run a ``draw_*`` function under :data:`STYLE` (fonts are fixed when artists are made)."""
    @functools.wraps(draw)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with plt.rc_context(STYLE):
            return draw(*args, **kwargs)
    return wrapper


def to_png(fig: Any) -> bytes:
    """PNG bytes of a figure at its own size (no tight crop: the print size stays FIG_WIDTH_IN); closes it."""
    buf = io.BytesIO()
    with plt.rc_context(STYLE):
        fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    return buf.getvalue()


def panels(n: int, height_per_row: float, cols: int | None = None, **kw: Any) -> tuple[Any, list]:
    """A full-width figure with panels, constrained layout.

    Args:
        n: Number of panels.
        height_per_row: Height of a row of panels (inches).
        cols: Panels a row; None for 2 or 3 (one camera takes half the width).
        **kw: Passed to ``plt.subplots``.

    Returns:
        (figure, the n visible axes).
    """
    cols = cols or min(max(n, 2), 3)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(FIG_WIDTH_IN, height_per_row * rows), squeeze=False,
                             layout="constrained", **kw)
    flat = list(axes.ravel())
    for ax in flat[n:]:
        ax.set_visible(False)
    return fig, flat[:n]


def _camera_residuals(residuals: Residuals, camera: str) -> tuple[np.ndarray, np.ndarray]:
    """(pixels, residuals) of one camera, each (N, 2)."""
    mine = [(o, r) for o, r in residuals if o.camera == camera]
    if not mine:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate([o.pixels for o, _ in mine]), np.concatenate([r for _, r in mine])


# --------------------------------------------------------------------------- residuals


def residual_scatter(calibration: Calibration, residuals: Residuals) -> bytes:
    """PNG of :func:`draw_residual_scatter`.

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.

    Returns:
        The figure's PNG bytes.
    """
    return to_png(draw_residual_scatter(calibration, residuals))


@styled
def draw_residual_scatter(calibration: Calibration, residuals: Residuals) -> Any:
    """(du, dv) of every corner, one panel per camera on one shared range, coloured by set, RMSE circle.

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.

    Returns:
        The matplotlib Figure.
    """
    names = list(calibration.cameras)
    allr = np.concatenate([r for _, r in residuals]) if residuals else np.zeros((0, 2))
    lim = max(float(np.abs(allr).max()) * 1.08, 1e-3) if len(allr) else 1.0
    cols = min(max(len(names), 2), 3)
    fig, axes = panels(len(names), FIG_WIDTH_IN / cols * 0.85 + 1.2, sharex=True, sharey=True)
    for ax, name in zip(axes, names):
        mine = [(o, r) for o, r in residuals if o.camera == name]
        for set_name, color in SET_COLORS.items():
            parts = [r for o, r in mine if o.set == set_name]
            if parts:
                r = np.concatenate(parts)
                ax.scatter(r[:, 0], r[:, 1], s=3, alpha=0.5, color=color, label=f"{set_name} ({len(r)})",
                           rasterized=True)
        value = rms(_camera_residuals(residuals, name)[1])
        ax.add_patch(plt.Circle((0, 0), value, fill=False, color="k", lw=1, ls="--"))
        ax.axhline(0, color="0.7", lw=0.5)
        ax.axvline(0, color="0.7", lw=0.5)
        ax.set_title(f"{name}: RMSE {value:.3f} px")
        ax.set_xlabel("du (px), + right")
        ax.legend(loc="upper right", markerscale=3, handletextpad=0.2, borderpad=0.3)
    axes[0].set_ylabel("dv (px), + down")
    axes[0].set(xlim=(-lim, lim), ylim=(lim, -lim))  # v down, as in the image
    for ax in axes:
        ax.set_box_aspect(1)  # equal scales: the limits are equal
        ax.xaxis.set_major_locator(MaxNLocator(5, symmetric=True))
        ax.yaxis.set_major_locator(MaxNLocator(5, symmetric=True))
    return fig


def residual_map(calibration: Calibration, residuals: Residuals) -> bytes:
    """PNG of :func:`draw_residual_map`.

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.

    Returns:
        The figure's PNG bytes.
    """
    return to_png(draw_residual_map(calibration, residuals))


def map_magnification(calibration: Calibration, residuals: Residuals) -> float:
    """How much :func:`draw_residual_map` lengthens the residual arrows (the same for every camera).

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.

    Returns:
        The magnification: the 95th-percentile residual drawn as 8 % of the largest image side, rounded
        down to 1, 2 or 5 x 10^k (1 without residuals).
    """
    allr = np.concatenate([r for _, r in residuals]) if residuals else np.zeros((0, 2))
    if not len(allr):
        return 1.0
    side = max(max(c.image_size) for c in calibration.cameras.values())
    raw = 0.08 * side / max(float(np.percentile(np.linalg.norm(allr, axis=1), 95)), 1e-9)
    k = 10.0 ** np.floor(np.log10(raw))
    return float(max(m for m in (1, 2, 5, 10) if m * k <= raw) * k)


def _nice(x: float) -> float:
    """The smallest 1, 2 or 5 x 10^k not below x (x > 0)."""
    k = 10.0 ** np.floor(np.log10(max(x, 1e-12)))
    return float(min(m for m in (1, 2, 5, 10) if m * k >= x * (1 - 1e-9)) * k)


@styled
def draw_residual_map(calibration: Calibration, residuals: Residuals) -> Any:
    """Each corner's residual as an arrow at its pixel, magnified the same for every camera.

    The arrows are coloured by their length on one shared colour scale (one colour bar); the
    magnification is :func:`map_magnification`.

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.

    Returns:
        The matplotlib Figure.
    """
    names = list(calibration.cameras)
    scale = map_magnification(calibration, residuals)
    mags = [np.linalg.norm(r, axis=1) for _, r in residuals]
    vmax = float(np.percentile(np.concatenate(mags), 99)) if mags else 1.0
    fig, axes = panels(len(names), 3.0 if len(names) >= 3 else 3.6, sharex=True, sharey=True)
    sc = None
    for ax, name in zip(axes, names):
        w, h = calibration.cameras[name].image_size
        uv, r = _camera_residuals(residuals, name)
        ax.add_patch(plt.Rectangle((0, 0), w, h, fill=False, color="k", lw=1))
        if len(r):
            mag = np.linalg.norm(r, axis=1)
            q = ax.quiver(uv[:, 0], uv[:, 1], r[:, 0] * scale, r[:, 1] * scale, mag, angles="xy",
                          scale_units="xy", scale=1, cmap="viridis", clim=(0, vmax), width=0.003)
            sc = q
            ref = _nice(float(np.percentile(np.concatenate(mags), 95)))
            ax.quiverkey(q, 0.97, 0.94, ref * scale, f"{ref:g} px", labelpos="W", coordinates="axes",
                         color="k")
            ax.set_title(name)
        else:
            ax.set_title(f"{name}: no corners")
        ax.set_xlabel("u (px)")
    for ax in axes:
        ax.xaxis.set_major_locator(MaxNLocator(4))
        ax.yaxis.set_major_locator(MaxNLocator(4))
    w_max = max(c.image_size[0] for c in calibration.cameras.values())
    h_max = max(c.image_size[1] for c in calibration.cameras.values())
    axes[0].set(xlim=(0, w_max), ylim=(h_max, 0), ylabel="v (px), down")
    for ax in axes:
        ax.set_aspect("equal")
    if sc is not None:
        fig.colorbar(sc, ax=axes, label="|residual| (px)", shrink=0.9)
    return fig


def residual_regions(calibration: Calibration, residuals: Residuals) -> bytes:
    """PNG of :func:`draw_residual_regions`.

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.

    Returns:
        The figure's PNG bytes.
    """
    return to_png(draw_residual_regions(calibration, residuals))


@styled
def draw_residual_regions(calibration: Calibration, residuals: Residuals) -> Any:
    """RMS residual per cell of a GRID_COLS x GRID_ROWS grid over each image.

    One colour scale for all cameras (its top: twice the overall RMS, or the worst cell of >= 5 corners
    if higher); cells without a corner hatched grey (coverage: the share of cells with a calibration
    corner, in each title).

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.

    Returns:
        The matplotlib Figure.
    """
    names = list(calibration.cameras)
    grids = [region_grid(calibration, residuals, n) for n in names]
    judged = np.concatenate([g.rms_px[g.count >= 5] for g in grids])  # a cell of 1-4 corners is noise
    overall = rms(np.concatenate([r for _, r in residuals])) if residuals else 1.0
    vmax = max(float(judged.max()) if len(judged) else 0.0, 2.0 * overall)  # pure noise: mid-scale
    fig, axes = panels(len(names), 3.0 if len(names) >= 3 else 3.5)
    im = None
    for ax, g in zip(axes, grids):
        w, h = g.image_size
        ax.add_patch(plt.Rectangle((0, 0), w, h, facecolor="0.85", hatch="//", edgecolor="0.6", lw=0,
                                   zorder=0))
        im = ax.imshow(np.ma.masked_invalid(g.rms_px), extent=(0, w, h, 0), cmap="magma_r", vmin=0, vmax=vmax,
                       interpolation="nearest", zorder=1)
        ax.set(xlim=(0, w), ylim=(h, 0), aspect="equal", xlabel="u (px)",
               title=f"{g.camera}: {100 * g.coverage:.0f} % covered")
        ax.xaxis.set_major_locator(MaxNLocator(4))
        ax.yaxis.set_major_locator(MaxNLocator(4))
    axes[0].set_ylabel("v (px), down")
    if im is not None:
        fig.colorbar(im, ax=axes, label="RMS residual (px)", shrink=0.9, extend="max")
    return fig


def residual_by_frame(calibration: Calibration, residuals: Residuals) -> bytes:
    """PNG of :func:`draw_residual_by_frame`.

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.

    Returns:
        The figure's PNG bytes.
    """
    return to_png(draw_residual_by_frame(calibration, residuals))


@styled
def draw_residual_by_frame(calibration: Calibration, residuals: Residuals) -> Any:
    """RMS residual of every image (camera x frame).

    Frames in the order observed (calibration, then stacking), one marker per camera, coloured by set;
    dashed: the median image.

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.

    Returns:
        The matplotlib Figure.
    """
    per = frame_rmse(residuals)
    order = list(SET_COLORS)
    frames = sorted(dict.fromkeys((s, f) for s, f, _ in per), key=lambda sf: order.index(sf[0]) if sf[0] in order
                    else len(order))  # calibration, then stacking, each in the order observed
    x = {k: i for i, k in enumerate(frames)}
    fig, ax = plt.subplots(figsize=(FIG_WIDTH_IN, 3.4), layout="constrained")
    for k, name in enumerate(calibration.cameras):
        for set_name, color in SET_COLORS.items():
            pts = [(x[(s, f)], v) for (s, f, c), v in per.items() if c == name and s == set_name]
            if pts:
                xs, ys = zip(*pts)
                ax.plot(xs, ys, CAMERA_MARKERS[k % len(CAMERA_MARKERS)], color=color, ms=6, mfc="none", mew=1.4,
                        label=f"{name}, {set_name}")
    if per:
        ax.axhline(float(np.median(list(per.values()))), color="0.4", ls="--", lw=1, label="median image")
    step = max(1, len(frames) // 16)
    ax.set_xticks(range(0, len(frames), step), [frames[i][1] for i in range(0, len(frames), step)],
                  rotation=90)
    ax.set(xlabel="frame (calibration frames, then stacking poses)", ylabel="RMS residual (px)",
           ylim=(0, _headroom(per.values())))
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), borderaxespad=0, markerscale=1)
    return fig


def _headroom(values) -> float | None:
    """An axis top 10 % above the largest finite value (from 0, matplotlib's margin left the largest markers
    cut by the frame); None (automatic) without one."""
    v = np.array([x for x in values if np.isfinite(x)], float)
    return 1.1 * float(v.max()) if v.size and v.max() > 0 else None


def residual_by_depth(calibration: Calibration, residuals: Residuals, target: Target,
                      points: Mapping[str, np.ndarray] | None = None) -> bytes:
    """PNG of :func:`draw_residual_by_depth`.

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.
        target: The target (its points on the board).
        points: Reconstructed world points by frame, each (N, 3), mm; None for none.

    Returns:
        The figure's PNG bytes.
    """
    return to_png(draw_residual_by_depth(calibration, residuals, target, points))


@styled
def draw_residual_by_depth(calibration: Calibration, residuals: Residuals, target: Target,
                           points: Mapping[str, np.ndarray] | None = None, bins: int = 10) -> Any:
    """Corners per depth bin (top) and their RMS residual (bottom), per camera.

    Shaded: the depths of the reconstructed points, where the calibration is used.

    Args:
        calibration: The calibration.
        residuals: (observation, residual (N, 2) px) pairs.
        target: The target (its points on the board).
        points: Reconstructed world points by frame, each (N, 3), mm; None for none.
        bins: Number of depth bins.

    Returns:
        The matplotlib Figure.
    """
    depths = corner_depths(calibration, residuals, target)
    allz = np.concatenate(depths) if depths else np.zeros(0)
    allz = allz[np.isfinite(allz)]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(FIG_WIDTH_IN, 4.6), sharex=True, layout="constrained",
                                      height_ratios=(1, 1.3))
    if not len(allz):
        return fig
    edges = np.linspace(allz.min(), allz.max() + 1e-9, bins + 1)
    centres = 0.5 * (edges[1:] + edges[:-1])
    names = list(calibration.cameras)
    width = (edges[1] - edges[0]) / (len(names) + 1)
    for k, name in enumerate(names):
        z = np.concatenate([d for (o, _), d in zip(residuals, depths) if o.camera == name] or [np.zeros(0)])
        r = np.concatenate([r for o, r in residuals if o.camera == name] or [np.zeros((0, 2))])
        ok = np.isfinite(z)
        z, r = z[ok], r[ok]
        idx = np.clip(np.searchsorted(edges, z, side="right") - 1, 0, bins - 1)
        count = np.bincount(idx, minlength=bins)
        value = np.array([rms(r[idx == b]) if count[b] else np.nan for b in range(bins)])
        color = f"C{k}"
        top.bar(centres + (k - (len(names) - 1) / 2) * width, count, width, color=color, label=name)
        bottom.plot(centres, value, "-" + CAMERA_MARKERS[k % len(CAMERA_MARKERS)], color=color, label=name)
        if points:
            pz = point_depths(calibration, points, name)
            for ax in (top, bottom):
                ax.axvspan(pz.min(), pz.max(), color=color, alpha=0.08, lw=0)
    if points:
        bottom.plot([], [], color="0.5", alpha=0.3, lw=8, label="reconstructed points")
    top.set(ylabel="corners")
    bottom.set(xlabel="depth of the corner along the camera's optical axis (mm)", ylabel="RMS residual (px)",
               ylim=(0, _headroom(v for line in bottom.get_lines() for v in np.asarray(line.get_ydata(), float))))
    top.legend(loc="upper right", ncols=len(names))
    bottom.legend(loc="lower right", ncols=len(names) + (1 if points else 0))
    return fig


# --------------------------------------------------------------------------- Fig. 4


def expansion_centre_figure(calibration: Calibration, stacking: Mapping[str, Sequence[Observation]]) -> bytes:
    """PNG of :func:`draw_expansion_centre`.

    Args:
        calibration: The calibration.
        stacking: The stacking observations by camera.

    Returns:
        The figure's PNG bytes.
    """
    return to_png(draw_expansion_centre(calibration, stacking))


@styled
def draw_expansion_centre(calibration: Calibration, stacking: Mapping[str, Sequence[Observation]]) -> Any:
    """Fig. 4: corner tracks under stacking (points), TLS lines, measured and calibrated expansion centres.

    Args:
        calibration: The calibration.
        stacking: The stacking observations by camera.

    Returns:
        The matplotlib Figure.
    """
    from ..init.expansion_center import fit_lines, intersect_lines, trajectories

    names = [n for n in calibration.cameras if stacking.get(n)]
    fig, axes = panels(max(len(names), 1), 3.4 if len(names) >= 3 else 4.0, cols=2)
    if not names:
        axes[0].text(0.5, 0.5, "no stacking observations", ha="center", va="center", transform=axes[0].transAxes)
        axes[0].set_axis_off()
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
            for centroid, direction, ok in zip(lines.centroid, lines.direction, ec.inliers):
                t = (c - centroid) @ direction
                seg = centroid + np.outer([0.0, t], direction)
                ax.plot(seg[:, 0], seg[:, 1], "-", color="gold" if ok else "0.6", lw=0.4, alpha=0.7)
            ax.plot(*c, "o", color="tab:green", ms=7, label=f"measured ±{max(ec.std_px):.2f} px")
            xs.append(float(c[0]))
            ys.append(float(c[1]))
            title = f"{name}: {len(lines)} tracks, {int(ec.inliers.sum())} inliers"
        cal_c = calibration.cameras[name].expansion_center_px
        if cal_c is not None:
            ax.plot(*cal_c, "x", color="tab:blue", ms=9, mew=2, label="in calibration.json")
            xs.append(float(cal_c[0]))
            ys.append(float(cal_c[1]))
        if calibration.window_of(name).normal_world is not None:  # the model's own centre: K n_cam
            n = calibration.normal_cam(name)
            if n[2] > 1e-6:
                p = calibration.cameras[name].K @ (n / n[2])
                ax.plot(p[0], p[1], "+", color="tab:purple", ms=11, mew=1.5, label="K n (fitted normal)")
        pad = 0.05 * max(w, h)
        ax.set(xlim=(min(xs) - pad, max(xs) + pad), ylim=(max(ys) + pad, min(ys) - pad), aspect="equal",
               xlabel="u (px)", ylabel="v (px), down", title=title)
        ax.xaxis.set_major_locator(MaxNLocator(4))
        ax.yaxis.set_major_locator(MaxNLocator(4))
        ax.legend(loc="lower left", handletextpad=0.3, borderpad=0.3)
    return fig


# --------------------------------------------------------------------------- Figs. 13, 14


def _representative(names: Sequence[str], k: int = 6) -> list[str]:
    """Up to k frames spread evenly over the list (the paper shows 6 of 11)."""
    if len(names) <= k:
        return list(names)
    return [names[int(round(i))] for i in np.linspace(0, len(names) - 1, k)]


def _plane_outline(xyz: np.ndarray, normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """The closed outline (5, 3) of the plane through ``point`` over the extent of the points xyz."""
    n = np.asarray(normal, float)
    a = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    s, t = (xyz - point) @ a, (xyz - point) @ b
    corners = [(s.min(), t.min()), (s.max(), t.min()), (s.max(), t.max()), (s.min(), t.max()), (s.min(), t.min())]
    return np.array([point + u * a + v * b for u, v in corners])


def point_cloud_figure(frames: Mapping[str, np.ndarray], planes: Mapping[str, Mapping[str, Any]]) -> bytes:
    """PNG of :func:`draw_point_cloud`.

    Args:
        frames: Reconstructed world points by frame, each (N, 3), mm.
        planes: Fitted planes by frame (``normal`` and ``point``; metrics.json's ``plane``).

    Returns:
        The figure's PNG bytes.
    """
    return to_png(draw_point_cloud(frames, planes))


@styled
def draw_point_cloud(frames: Mapping[str, np.ndarray], planes: Mapping[str, Mapping[str, Any]]) -> Any:
    """Fig. 13a: representative reconstructed frames (points and fitted planes), world frame, mm.

    Args:
        frames: Reconstructed world points by frame, each (N, 3), mm.
        planes: Fitted planes by frame (``normal`` and ``point``; metrics.json's ``plane``).

    Returns:
        The matplotlib Figure.
    """
    fig = plt.figure(figsize=(FIG_WIDTH_IN, 4.4), layout="constrained")
    ax = fig.add_subplot(111, projection="3d")
    ax.set_zlabel("z (mm)", labelpad=10)
    chosen = _representative(list(frames))
    cmap = plt.get_cmap("viridis")
    for k, name in enumerate(chosen):
        xyz = frames[name]
        color = cmap(k / max(len(chosen) - 1, 1))
        ax.scatter(xyz[:, 0], xyz[:, 1], xyz[:, 2], s=5, color=color, label=name)
        plane = planes.get(name)
        if plane and plane.get("normal") is not None:
            c = _plane_outline(xyz, np.asarray(plane["normal"]), np.asarray(plane["point"]))
            P = np.array([[c[0], c[1]], [c[3], c[2]]])
            ax.plot_surface(P[..., 0], P[..., 1], P[..., 2], color=color, alpha=0.15, linewidth=0)
    allxyz = np.concatenate([frames[n] for n in chosen])
    ax.set_box_aspect(np.maximum(np.ptp(allxyz, axis=0), 0.25 * np.ptp(allxyz, axis=0).max()), zoom=1.15)
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_major_locator(MaxNLocator(4))
    ax.set(xlabel="x (mm)", ylabel="y (mm)")
    ax.zaxis.set_tick_params(pad=6)
    fig.suptitle(f"{len(chosen)} of {len(frames)} reconstructed frames")
    fig.legend(*ax.get_legend_handles_labels(), loc="outside right center")
    return fig


def rig_figure(calibration: Calibration, frames: Mapping[str, np.ndarray]) -> bytes:
    """PNG of :func:`draw_rig`.

    Args:
        calibration: The calibration.
        frames: Reconstructed world points by frame, each (N, 3), mm.

    Returns:
        The figure's PNG bytes.
    """
    return to_png(draw_rig(calibration, frames))


def window_depth(calibration: Calibration, points: np.ndarray, window=None) -> tuple[float, bool]:
    """Where a window's near face is drawn.

    Where the calibration does not observe the distance (in air it changes no pixel) it is where an exact
    model was evaluated (fixed_distance_mm), else halfway from its first camera to the points.

    Args:
        calibration: The calibration.
        points: World points (N, 3), mm.
        window: The window; None for the first.

    Returns:
        (the near face as the plane offset ``normal . X`` in the world (mm), whether it is schematic).
    """
    w = calibration.window_list()[0] if window is None else window
    n = w.normal_world
    plane = w.plane_mm(calibration)
    if plane is not None:
        return plane, w.interface.distance_mm is None
    first = calibration.cameras[w.cameras[0]].cam_from_world.inverse().t
    return (float(n @ first + 0.5 * (np.median(points @ n) - n @ first)) if len(points)
            else float(n @ first) + 50.0), True


@styled
def draw_rig(calibration: Calibration, frames: Mapping[str, np.ndarray]) -> Any:
    """Fig. 14 as two true-scale views on one depth axis: from above (z, x) and from the side (z, y, down).

    Cameras (centre and optical axis), the window's section through the rig's middle (near and far faces;
    dashed where its depth is schematic, see :func:`window_depth`) and the points coloured by frame.

    Args:
        calibration: The calibration.
        frames: Reconstructed world points by frame, each (N, 3), mm.

    Returns:
        The matplotlib Figure.
    """
    names = list(frames)
    allxyz = np.concatenate([np.asarray(frames[f], float) for f in names]) if names else np.zeros((0, 3))
    centres = {n: c.cam_from_world.inverse().t for n, c in calibration.cameras.items()}
    optical = {n: c.cam_from_world.R[2] for n, c in calibration.cameras.items()}  # optical axes in the world
    span = np.vstack([np.array(list(centres.values())), allxyz]) if len(allxyz) else np.array(list(centres.values()))
    # (window, its normal, plane offset, schematic, thickness)
    windows = [(w, w.normal_world, *window_depth(calibration, allxyz, w), w.interface.thickness_mm)
               for w in calibration.window_list() if w.normal_world is not None]
    z_lo, z_hi = span[:, 2].min(), span[:, 2].max()
    for _, n, d, _, t in windows:  # the faces' depths along z at the rig's middle
        if abs(n[2]) > 1e-6:
            z_mid = (d - n[:2] @ span[:, :2].mean(axis=0)) / n[2]
            z_lo, z_hi = min(z_lo, z_mid - 5, z_mid + t / n[2] - 5), max(z_hi, z_mid + 5, z_mid + t / n[2] + 5)
    pad = 0.04 * (z_hi - z_lo)
    zlim = (z_lo - pad, z_hi + pad)
    margin = [0.15 * max(float(np.ptp(span[:, k])), 20.0) for k in (0, 1)]
    lims = [(span[:, k].min() - margin[k], span[:, k].max() + margin[k]) for k in (0, 1)]
    heights = np.array([hi - lo for lo, hi in lims]) / (zlim[1] - zlim[0]) * (FIG_WIDTH_IN - 1.2)
    heights = np.clip(heights, 1.2, 3.5)
    fig, axes = plt.subplots(2, 1, figsize=(FIG_WIDTH_IN, heights.sum() + 2.4), layout="constrained",
                             height_ratios=heights)
    cmap = plt.get_cmap("viridis")
    for ax, k, label in zip(axes, (0, 1), ("x (mm)", "y (mm), down")):
        for i, f in enumerate(names):
            xyz = np.asarray(frames[f], float)
            ax.scatter(xyz[:, 2], xyz[:, k], s=2, color=cmap(i / max(len(names) - 1, 1)), rasterized=True)
        for j, (name, c) in enumerate(centres.items()):
            tip = c + optical[name] * 0.12 * (zlim[1] - zlim[0])
            ax.annotate("", xy=(tip[2], tip[k]), xytext=(c[2], c[k]), arrowprops=dict(arrowstyle="->", lw=1.2))
            ax.plot(c[2], c[k], CAMERA_MARKERS[j % len(CAMERA_MARKERS)], color="k", ms=7, mfc="w" if j % 2 else "k")
        for _, n, d, schematic, t in windows:
            if abs(n[2]) <= 1e-6:  # a wall seen edge-on in this section
                continue
            other = 1 - k  # the coordinate held at the rig's middle for this section
            s = np.array(lims[k])
            mid = span[:, other].mean()
            z_near = (d - n[k] * s - n[other] * mid) / n[2]
            for z in (z_near, z_near + t / n[2]):
                ax.plot(z, s, ls="--" if schematic else "-", color="tab:cyan", lw=1.5)
            ax.fill_betweenx(s, z_near, z_near + t / n[2], color="tab:cyan", alpha=0.3, lw=0)
        ax.set(xlim=zlim, ylim=lims[k], ylabel=label)
        ax.set_aspect("equal", adjustable="box")
    axes[1].invert_yaxis()
    axes[0].set_title("seen from above")
    axes[1].set_title("seen from the side")
    axes[1].set_xlabel("z (mm), depth from cam0")
    handles = [axes[0].plot([], [], CAMERA_MARKERS[j % len(CAMERA_MARKERS)], color="k", ms=7,
                            mfc="w" if j % 2 else "k", label=f"{name} (arrow: optical axis)" if j == 0 else name)[0]
               for j, name in enumerate(centres)]
    for w, _, _, schematic, t in windows:
        name = "window" if not calibration.windows else f"window {w.name}"
        label = f"{name} ({t:g} mm)" + (", depth schematic: its distance is not observable in air" if schematic
                                        else f" at {w.interface.distance_mm:.1f} mm from {w.cameras[0]}")
        handles += axes[0].plot([], [], color="tab:cyan", lw=4, alpha=0.5, ls="--" if schematic else "-", label=label)
    if names:
        handles += axes[0].plot([], [], "o", color=cmap(0.0), ms=5, label=f"points, frame {names[0]}")
        handles += axes[0].plot([], [], "o", color=cmap(1.0), ms=5, label=f"... to frame {names[-1]}")
    if handles:
        fig.legend(handles=handles, loc="outside lower center", ncols=2, frameon=False)
    return fig


def error_histograms(metrics: Mapping[str, Any]) -> bytes:
    """PNG of :func:`draw_error_histograms`."""
    return to_png(draw_error_histograms(metrics))


@styled
def draw_error_histograms(metrics: Mapping[str, Any]) -> Any:
    """Fig. 13b-d: plane-distance error per stage frame (full width), flatness and inter-corner errors."""
    stage_frames = {k: f for k, f in metrics.get("frames", {}).items() if f.get("plane_distance_error_mm") is not None}
    hists = [p for p, ok in (("flatness", metrics.get("flatness_mm", {}).get("distances")),
                             ("corners", (metrics.get("inter_corner_mm") or {}).get("errors"))) if ok]
    layout = ([["stage"] * max(len(hists), 1)] if stage_frames else []) + ([hists] if hists else [])
    if not layout:
        fig, ax = plt.subplots(figsize=(FIG_WIDTH_IN, 1.5), layout="constrained")
        ax.text(0.5, 0.5, "no errors to show", ha="center", va="center")
        ax.set_axis_off()
        return fig
    # matplotlib's stub: HashableList is invariant, so a list[list[str]] mosaic (valid) does not match it
    fig, axd = plt.subplot_mosaic(layout, figsize=(FIG_WIDTH_IN, 3.3 * len(layout)),  # type: ignore[arg-type]
                                  layout="constrained")
    if stage_frames:
        ax = axd["stage"]
        names = sorted(stage_frames, key=lambda n: stage_frames[n]["stage_mm"])
        err = [stage_frames[n]["plane_distance_error_mm"] for n in names]
        paper = [stage_frames[n]["plane_distance_error_paper_mm"] for n in names]
        x = np.arange(len(names))
        ax.bar(x - 0.2, err, 0.4, label="vs the stage travel along the plane's normal")
        ax.bar(x + 0.2, paper, 0.4, label="vs the stage reading itself (the paper's comparison)")
        ax.set_xticks(x, [f"{stage_frames[n]['stage_mm']:g}" for n in names])
        ax.set(xlabel="stage position (mm)", ylabel="error (mm)",
               title="(b) distance of each stage plane from the reference plane: error")
        ax.axhline(0, color="k", lw=0.5)
        ax.yaxis.set_major_locator(MaxNLocator(5))
        ax.legend(loc="best")
    if "flatness" in hists:
        ax = axd["flatness"]
        f = metrics["flatness_mm"]
        ax.hist(np.asarray(f["distances"], float), bins=30, color="tab:blue")
        ax.set(xlabel="point to fitted plane (mm)", ylabel="points", title=f"(c) flatness, RMSE {f['rmse']:.4f} mm")
        ax.xaxis.set_major_locator(MaxNLocator(4, symmetric=True))
    if "corners" in hists:
        ax = axd["corners"]
        ic = metrics["inter_corner_mm"]
        ax.hist(np.asarray(ic["errors"], float), bins=30, color="tab:green")
        ax.set(xlabel=f"neighbour distance - {ic['square_mm']:g} mm (mm)", ylabel="pairs",
               title=f"(d) corner spacing, RMSE {ic['rmse']:.4f} mm")
        ax.xaxis.set_major_locator(MaxNLocator(4, symmetric=True))
    return fig

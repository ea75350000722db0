"""The report's interactive 3D view: the rig, its window, sample rays through it and the points (plotly).

:func:`rig_view_html` returns an HTML fragment holding plotly.js itself
(``include_plotlyjs=True``, once per page) so the report opens
offline; the figure is WebGL (``Scatter3d``) and can be turned, zoomed and
hovered. World frame = camera 0's (x right, y down, z along its optical axis),
mm.

Rays are traced with the exact (Snell) model's back-projection,
:meth:`ari_sfm.models.exact.ExactModel.backproject` (no second physics): for a
grid of pixels of each camera, the camera-side ray from the centre to the near
face (the pinhole ray up to that plane), through the glass to the far face
where the model puts its origin, then along its medium-side direction to the
depth of the points. Where the calibration does not observe the window's
distance (in air) the window is drawn at the distance an exact model was
evaluated at (or halfway to the points) and the legend says it is schematic.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from ..calibration.record import Calibration
from .figures import window_depth

log = logging.getLogger(__name__)

RAY_GRID = (4, 3)  # pixels per camera: columns x rows, inset from the image border
RAY_INSET = 0.08  # share of the image width / height left out at each border
PRINT_WIDTH_PX = 680  # the view's width while printing: fits A4 and Letter at the browser's default margins
# The view keeps the pixel width it was drawn at on screen: printed from a wide window it would stick out of the
# page and Chromium would shrink the whole report to fit it. Redrawn at PRINT_WIDTH_PX for the print (beforeprint
# runs before the print layout; Plotly.relayout draws synchronously), back to the window's width after it.
PRINT_FIT_SCRIPT = (
    "<script>(function(){var d=document.getElementById('rig-3d');if(!d||!window.Plotly)return;"
    f"window.addEventListener('beforeprint',function(){{Plotly.relayout(d,{{width:{PRINT_WIDTH_PX:d}}});}});"
    "window.addEventListener('afterprint',function(){Plotly.relayout(d,{width:null,autosize:true});});})();</script>")
RAY_COLOURS = ("#d62728", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#bcbd22")  # per camera
MAX_POINTS = 20000  # reconstructed points drawn (an even subsample beyond)


def _tracing_calibration(calibration: Calibration, points: np.ndarray) -> tuple[Calibration, bool]:
    """The calibration the rays are traced with (exact needs a window distance) and whether it is schematic."""
    windows, schematic = [], False
    for w in calibration.window_list():
        d, guessed = window_depth(calibration, points, w)
        schematic |= guessed
        if w.interface.distance_mm is None:  # as a distance from the window's first camera
            d -= float(w.normal_world @ calibration.cameras[w.cameras[0]].cam_from_world.inverse().t)
            w = replace(w, fixed_distance_mm=d)
        windows.append(w)
    first = windows[0]
    return replace(calibration, fixed_distance_mm=first.fixed_distance_mm,
                   windows=tuple(windows) if calibration.windows else ()), schematic


def sample_rays(calibration: Calibration, camera: str, end_depth_mm: float,
                grid: tuple[int, int] = RAY_GRID) -> np.ndarray:
    """Sample rays of one camera through its window (exact model; straight rays without a window).

    Args:
        calibration: The calibration (with a window distance, as :func:`_tracing_calibration` makes it).
        camera: The camera's name.
        end_depth_mm: Depth along the camera's optical axis (mm) where the rays end.
        grid: Pixels per camera, (columns, rows), inset from the image border by RAY_INSET.

    Returns:
        Polylines (P, 4, 3), world frame, mm: camera centre, near face, far face, medium-side point at
        ``end_depth_mm``; rays that are not finite are left out.
    """
    cam = calibration.cameras[camera]
    w, h = cam.image_size
    u, v = np.meshgrid(np.linspace(RAY_INSET * w, (1 - RAY_INSET) * w, grid[0]),
                       np.linspace(RAY_INSET * h, (1 - RAY_INSET) * h, grid[1]))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    if calibration.window_of(camera).normal_world is None:
        from ..models import PinholeModel

        _, ray = PinholeModel(cam.K, cam.dist).backproject(uv)
        near = far = np.zeros_like(ray)
        direction = ray
    else:
        model = calibration.projection_model(camera, model="exact")
        _, ray = model.pinhole.backproject(uv)
        near = ray * (model.distance_mm / (ray @ model.normal_cam))[:, None]  # the pinhole ray meets the near face
        far, direction = model.backproject(uv)
    with np.errstate(invalid="ignore", divide="ignore"):
        length = (end_depth_mm - far[:, 2]) / direction[:, 2]
    end = far + direction * np.maximum(length, 0.0)[:, None]
    paths = np.stack([np.zeros_like(near), near, far, end], axis=1)  # (P, 4, 3), camera frame
    world_from_cam = cam.cam_from_world.inverse()
    out = world_from_cam.apply(paths.reshape(-1, 3)).reshape(paths.shape)
    return out[np.all(np.isfinite(out), axis=(1, 2))]


def _window_box(window, d: float, extent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and triangles (12, 3) of a window's plate between n.X = d and n.X = d + t, over the
    extent of the given points projected on the near face (plus a margin)."""
    n = window.normal_world
    a = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    s, t_ = extent @ a, extent @ b
    ms, mt = 0.25 * max(np.ptp(s), 20.0), 0.25 * max(np.ptp(t_), 20.0)
    corners = [(s.min() - ms, t_.min() - mt), (s.max() + ms, t_.min() - mt), (s.max() + ms, t_.max() + mt),
               (s.min() - ms, t_.max() + mt)]
    thickness = window.interface.thickness_mm
    verts = np.array([n * (d + off) + p * a + q * b for off in (0.0, thickness) for p, q in corners])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                      [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    return verts, faces


def rig_view_figure(calibration: Calibration, points: Mapping[str, np.ndarray],
                    boards: np.ndarray | None = None) -> Any:
    """The 3D view as a plotly Figure.

    Args:
        calibration: The calibration.
        points: Reconstructed world points by frame, each (N, 3), mm.
        boards: The calibration boards' corners (M, 3), world frame, mm; None for none.

    Returns:
        A ``plotly.graph_objects.Figure``: cameras (centre, optical axis, name), windows, sample rays,
        points by frame and the boards' corners.
    """
    import plotly.graph_objects as go

    names = list(points)
    xyz = np.concatenate([np.asarray(points[f], float).reshape(-1, 3) for f in names]) if names else np.zeros((0, 3))
    frame_of = np.concatenate([np.full(len(points[f]), i) for i, f in enumerate(names)]) if names else np.zeros(0)
    boards = np.zeros((0, 3)) if boards is None else np.asarray(boards, float).reshape(-1, 3)
    scene = xyz if len(xyz) else boards
    traced, schematic = _tracing_calibration(calibration, scene) if calibration.normal_world is not None \
        else (calibration, False)
    centres = {n: c.cam_from_world.inverse().t for n, c in calibration.cameras.items()}
    end_depth = float(np.median(scene[:, 2])) if len(scene) else 500.0
    fig = go.Figure()
    ray_ends: dict[str, list[np.ndarray]] = {}
    for k, name in enumerate(calibration.cameras):
        try:
            rays = sample_rays(traced, name, end_depth)
        except ValueError as exc:  # e.g. a schematic window that this camera does not look through
            log.warning("3D view: no rays for %s: %s", name, exc)
            continue
        ray_ends.setdefault(calibration.window_of(name).name, []).append(rays[:, 1:3].reshape(-1, 3))
        line = np.concatenate([np.vstack([r, [np.nan] * 3]) for r in rays]) if len(rays) else np.zeros((0, 3))
        fig.add_trace(go.Scatter3d(x=line[:, 0], y=line[:, 1], z=line[:, 2], mode="lines",
                                   line=dict(color=RAY_COLOURS[k % len(RAY_COLOURS)], width=2),
                                   name=f"rays of {name} (exact model)", hoverinfo="skip"))
    for w in calibration.window_list():  # every window, over its own cameras and rays
        if w.normal_world is None:
            continue
        d, _ = window_depth(calibration, scene, w)
        ends = ray_ends.get(w.name, [])
        near_far = np.concatenate(ends) if ends else np.zeros((0, 3))
        verts, faces = _window_box(w, d, np.vstack([near_far, np.array([centres[c] for c in w.cameras])]))
        label = "window" if not calibration.windows else f"window {w.name}"
        fig.add_trace(go.Mesh3d(x=verts[:, 0], y=verts[:, 1], z=verts[:, 2], i=faces[:, 0], j=faces[:, 1],
                                k=faces[:, 2], color="#17becf", opacity=0.25, flatshading=True, hoverinfo="name",
                                name=f"{label}, {w.interface.thickness_mm:g} mm"
                                     + (" (depth schematic: not observable in air)" if schematic else ""),
                                showlegend=True))
    span = np.vstack([scene, np.array(list(centres.values()))])
    axis_len = 0.12 * float(np.ptp(span[:, 2]) or 100.0)
    for name, cam in calibration.cameras.items():
        c = centres[name]
        tip = c + cam.cam_from_world.R[2] * axis_len
        fig.add_trace(go.Scatter3d(x=[c[0], tip[0]], y=[c[1], tip[1]], z=[c[2], tip[2]], mode="lines+markers+text",
                                   text=[name, ""], textposition="top center", textfont=dict(size=15),
                                   marker=dict(size=[5, 2], color="black"),
                                   line=dict(color="black", width=5), name=name, showlegend=False))
    if len(boards):
        fig.add_trace(go.Scatter3d(x=boards[:, 0], y=boards[:, 1], z=boards[:, 2], mode="markers",
                                   marker=dict(size=1.5, color="rgb(150,150,150)"), name="calibration board corners",
                                   visible=True if not len(xyz) else "legendonly"))
    if len(xyz):
        keep = np.linspace(0, len(xyz) - 1, min(len(xyz), MAX_POINTS)).astype(int)
        fig.add_trace(go.Scatter3d(
            x=xyz[keep, 0], y=xyz[keep, 1], z=xyz[keep, 2], mode="markers",
            marker=dict(size=2, color=frame_of[keep], colorscale="Viridis", cmin=0, cmax=max(len(names) - 1, 1)),
            text=[names[int(i)] for i in frame_of[keep]], hovertemplate="%{text}<br>%{x:.1f}, %{y:.1f}, %{z:.1f} mm",
            name=f"reconstructed points ({len(xyz)}"
                 + (f", every {len(xyz) // len(keep)}th shown)" if len(keep) < len(xyz) else ")")))
    fig.update_layout(
        height=620, margin=dict(l=0, r=0, t=30, b=0), legend=dict(x=0, y=1, bgcolor="rgba(255,255,255,0.7)"),
        font=dict(size=14),
        scene=dict(aspectmode="data", xaxis_title="x (mm)", yaxis_title="y (mm)", zaxis_title="z (mm)",
                   camera=dict(up=dict(x=0, y=-1, z=0), eye=dict(x=1.45, y=-1.15, z=-1.35))))
    return fig


def rig_view_html(calibration: Calibration, points: Mapping[str, np.ndarray],
                  boards: np.ndarray | None = None, include_plotlyjs: bool = True) -> str:
    """The 3D view as an HTML fragment.

    Args:
        calibration: The calibration.
        points: Reconstructed world points by frame, each (N, 3), mm.
        boards: The calibration boards' corners (M, 3), world frame, mm; None for none.
        include_plotlyjs: Passed to plotly's ``to_html`` (True: plotly.js inlined).

    Returns:
        A div and its scripts (including the script that fits the view to the printed page).
    """
    fig = rig_view_figure(calibration, points, boards)
    return fig.to_html(full_html=False, include_plotlyjs=include_plotlyjs, div_id="rig-3d",
                       config={"displaylogo": False, "responsive": True}) + PRINT_FIT_SCRIPT

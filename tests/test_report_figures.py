"""The report's figures read when printed (issue 17, item 2): fonts >= 9 pt at print size, no text clipped
or overlapping another, shared ranges between cameras, an honest window depth."""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.text import Text

from ari_sfm.calibration.compare import draw_figures
from ari_sfm.calibration.evaluate import observation_residuals
from ari_sfm.io import parse_calibration
from ari_sfm.report.figures import (
    FIG_WIDTH_IN,
    PRINT_WIDTH_IN,
    draw_error_histograms,
    draw_expansion_centre,
    draw_point_cloud,
    draw_residual_by_depth,
    draw_residual_by_frame,
    draw_residual_map,
    draw_residual_regions,
    draw_residual_scatter,
    draw_rig,
)


@pytest.fixture(scope="module")
def binocular_residuals():
    from ari_sfm.simulate import make_scene

    scene = make_scene("binocular", seed=0)
    cal = parse_calibration(scene.truth, "truth.json")
    return cal, observation_residuals(cal, scene.dataset.observations, scene.dataset.target), scene.dataset


def _points(cal, dataset) -> dict[str, np.ndarray]:
    """Two planes 5 mm apart at the depth of the boards (stand-ins for a reconstruction)."""
    z = np.median([p.t[2] for p in cal.frames.values()])
    g = np.stack(np.meshgrid(np.linspace(-40, 40, 9), np.linspace(-30, 30, 7)), -1).reshape(-1, 2)
    return {f"r{k}": np.c_[g, np.full(len(g), z + 5 * k)] for k in range(2)}


def _metrics(rng) -> dict:
    frames = {f"r{k}": {"stage_mm": float(s), "plane_distance_error_mm": float(rng.normal(0, 0.002)),
                        "plane_distance_error_paper_mm": float(rng.normal(0, 0.005))}
              for k, s in enumerate(range(-10, 11, 2))}
    return {"frames": frames,
            "flatness_mm": {"mae": 0.012, "rmse": 0.016, "distances": rng.normal(0, 0.016, 900).tolist()},
            "inter_corner_mm": {"mae": 0.004, "rmse": 0.0055, "square_mm": 10.0,
                                "errors": rng.normal(0, 0.0055, 1500).tolist()}}


def _figures(cal, residuals, dataset):
    stacking = {c: [o for o in dataset.observations if o.set == "stacking" and o.camera == c] for c in cal.cameras}
    points = _points(cal, dataset)
    return {
        "scatter": draw_residual_scatter(cal, residuals),
        "map": draw_residual_map(cal, residuals),
        "regions": draw_residual_regions(cal, residuals),
        "frames": draw_residual_by_frame(cal, residuals),
        "depth": draw_residual_by_depth(cal, residuals, dataset.target, points),
        "expansion": draw_expansion_centre(cal, stacking),
        "cloud": draw_point_cloud(points, {}),
        "rig": draw_rig(cal, points),
        "errors": draw_error_histograms(_metrics(np.random.default_rng(0))),
    }


def _drawn_texts(fig) -> list[Text]:
    """Every text the figure draws (tick labels only for ticks inside the view)."""
    fig.canvas.draw()
    hidden = set()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            for loc, label in zip(axis.get_majorticklocs(), axis.get_majorticklabels()):
                if not lo - 1e-9 * abs(hi - lo) <= loc <= hi + 1e-9 * abs(hi - lo):
                    hidden.add(id(label))
    candidates = [t for ax in fig.axes if ax.get_visible() for t in ax.findobj(Text)]
    candidates += [t for lg in fig.legends for t in lg.findobj(Text)] + list(fig.texts)
    if fig._suptitle is not None:
        candidates.append(fig._suptitle)
    out = []
    for t in dict.fromkeys(candidates):
        if id(t) not in hidden and t.get_visible() and t.get_text().strip():
            out.append(t)
    return out


def _overlap(a, b) -> float:
    """Area of the intersection of two display-space bounding boxes (pixels^2)."""
    w = min(a.x1, b.x1) - max(a.x0, b.x0)
    h = min(a.y1, b.y1) - max(a.y0, b.y0)
    return max(w, 0.0) * max(h, 0.0)


def _check_print(name: str, fig) -> None:
    """Fonts >= 9 pt at print size; no text clipped by the figure's edge or overlapping another (3D: fonts only)."""
    assert fig.get_figwidth() == pytest.approx(FIG_WIDTH_IN), name
    renderer = fig.canvas.get_renderer()
    texts = _drawn_texts(fig)
    assert texts, name
    frame = fig.bbox
    is_3d = any(ax.name == "3d" for ax in fig.axes)  # a 3D projection's labels follow matplotlib's own 3D layout
    boxes = []
    for t in texts:
        printed = t.get_fontsize() * PRINT_WIDTH_IN / FIG_WIDTH_IN
        assert printed >= 9.0, (name, t.get_text(), printed)
        box = t.get_window_extent(renderer)
        boxes.append(box)
        if not is_3d:
            assert box.x0 >= frame.x0 - 1 and box.x1 <= frame.x1 + 1 and box.y0 >= frame.y0 - 1 \
                and box.y1 <= frame.y1 + 1, (name, t.get_text(), "clipped")
    if not is_3d:
        for i in range(len(texts)):
            for j in range(i + 1, len(texts)):
                assert _overlap(boxes[i], boxes[j]) < 4.0, (name, texts[i].get_text(), texts[j].get_text())
    plt.close(fig)


@pytest.mark.parametrize("rig", ["binocular", "one camera", "arc4"])
def test_every_figure_prints_at_9pt_with_no_text_clipped_or_overlapping(binocular_residuals, rig):
    cal, residuals, dataset = binocular_residuals
    if rig == "one camera":  # the sample's layout
        cal = replace(cal, cameras={"cam0": cal.cameras["cam0"]})
        residuals = [(o, r) for o, r in residuals if o.camera == "cam0"]
    elif rig == "arc4":  # four cameras: two rows of panels
        from ari_sfm.simulate import make_scene

        scene = make_scene("arc4", seed=0)
        cal = parse_calibration(scene.truth, "truth.json")
        dataset = scene.dataset
        residuals = observation_residuals(cal, dataset.observations, dataset.target)
    for name, fig in _figures(cal, residuals, dataset).items():
        _check_print(name, fig)


def test_compared_models_share_one_range(binocular_residuals):
    """compare's scatter: every model on the same axes, so that they compare by eye (and print like the report)."""
    rng = np.random.default_rng(1)
    results = [SimpleNamespace(model=m, residuals=rng.normal(0, s, (400, 2)), in_fit=np.arange(400) < 300,
                               all=SimpleNamespace(rmse_px=s * np.sqrt(2)))
               for m, s in (("ari", 0.3), ("exact", 0.05), ("rt", 0.05), ("pf", 0.6))]
    scatter, distribution = draw_figures(results)
    panels = [ax for ax in scatter.axes if ax.get_visible()]
    assert len(panels) == 4
    assert len({ax.get_xlim() for ax in panels}) == 1 and len({ax.get_ylim() for ax in panels}) == 1
    lim = max(np.abs(r.residuals).max() for r in results)
    assert panels[0].get_xlim()[1] >= lim and panels[0].get_ylim()[0] >= lim  # v down, as in the image
    _check_print("compare scatter", scatter)
    _check_print("compare distribution", distribution)


def test_cameras_share_ranges_ticks_and_colour_scales(binocular_residuals):
    cal, residuals, _ = binocular_residuals
    fig = draw_residual_scatter(cal, residuals)
    a, b = fig.axes[:2]
    assert a.get_xlim() == b.get_xlim() and a.get_ylim() == b.get_ylim()
    assert a.get_ylim()[0] > a.get_ylim()[1]  # dv runs down, as v in the image ...
    assert "down" in a.get_ylabel()  # ... and the label says so
    assert list(a.get_xticks()) == list(b.get_xticks())
    plt.close(fig)
    for draw in (draw_residual_map, draw_residual_regions):
        fig = draw(cal, residuals)
        mappables = [m for ax in fig.axes for m in ax.collections + ax.images if m.get_array() is not None]
        assert len({m.get_clim() for m in mappables}) == 1  # one colour scale for both cameras
        assert sum(ax.get_label() == "<colorbar>" for ax in fig.axes) == 1  # and one colour bar
        plt.close(fig)


def _window_label(fig) -> str:
    legends = fig.legends or [fig.axes[0].get_legend()]
    return " ".join(t.get_text() for lg in legends for t in lg.get_texts())


def test_rig_figure_says_the_window_depth_is_schematic_in_air(binocular_residuals):
    cal, _, _ = binocular_residuals
    frames = {"r": np.array([[0.0, 0.0, 500.0], [50.0, 0.0, 500.0], [0.0, 50.0, 510.0]])}
    air = replace(cal, interface=replace(cal.interface, distance_mm=None), fixed_distance_mm=30.0)  # as exact in air
    fig = draw_rig(air, frames)
    assert "depth schematic: its distance is not observable in air" in _window_label(fig)
    assert any(line.get_linestyle() == "--" for line in fig.axes[0].get_lines())  # the dashed faces
    plt.close(fig)
    known = replace(cal, interface=replace(cal.interface, distance_mm=80.0))
    fig = draw_rig(known, frames)
    assert "schematic" not in _window_label(fig) and "at 80.0 mm" in _window_label(fig)
    assert not any(line.get_linestyle() == "--" for line in fig.axes[0].get_lines())
    plt.close(fig)


def test_per_frame_and_depth_residuals_leave_room_above_the_largest_value(binocular_residuals):
    """The largest RMS marker sits below the frame's top (from 0, matplotlib's margin put it on the frame,
    half cut), and every value is inside the view."""
    cal, residuals, dataset = binocular_residuals
    figs = {"frames": draw_residual_by_frame(cal, residuals),
            "depth": draw_residual_by_depth(cal, residuals, dataset.target, _points(cal, dataset))}
    for name, fig in figs.items():
        ax = fig.axes[-1]
        values = np.concatenate([np.asarray(ln.get_ydata(), float) for ln in ax.get_lines()
                                 if len(ln.get_ydata()) and ln.get_linestyle() != "--"])
        values = values[np.isfinite(values)]
        lo, hi = ax.get_ylim()
        assert lo == 0.0 and values.max() <= hi / 1.05, (name, values.max(), hi)
        plt.close(fig)

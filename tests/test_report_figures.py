"""The report's figure cosmetics (issue 10, item 9): no overlapping panels, an honest window depth."""
from __future__ import annotations

from dataclasses import replace

import matplotlib.pyplot as plt
import numpy as np
import pytest

from ari_sfm.evaluate import observation_residuals
from ari_sfm.report_figures import draw_residual_map, draw_rig


@pytest.fixture(scope="module")
def binocular_residuals():
    from ari_sfm.calibration import Calibration
    from ari_sfm.simulate import make_scene

    scene = make_scene("binocular", seed=0)
    cal = Calibration.from_json(scene.truth, "truth.json")
    return cal, observation_residuals(cal, scene.dataset.observations, scene.dataset.target)


def _overlap(a, b) -> float:
    """Area of the intersection of two display-space bounding boxes (pixels^2)."""
    w = min(a.x1, b.x1) - max(a.x0, b.x0)
    h = min(a.y1, b.y1) - max(a.y0, b.y0)
    return max(w, 0.0) * max(h, 0.0)


def test_residual_map_colour_bars_and_labels_do_not_overlap_other_axes(binocular_residuals):
    """Every pair of axes (panels and colour bars, with their tick labels and axis labels) is disjoint."""
    cal, residuals = binocular_residuals
    fig = draw_residual_map(cal, residuals)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = [ax.get_tightbbox(renderer) for ax in fig.axes]
    assert len(boxes) == 4  # two panels, two colour bars
    assert any(ax.get_ylabel() == "|residual| (px)" for ax in fig.axes)
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            assert _overlap(boxes[i], boxes[j]) < 1.0, (fig.axes[i], fig.axes[j])
    plt.close(fig)


def _window_label(fig) -> str:
    legend = fig.axes[0].get_legend()
    return " ".join(t.get_text() for t in legend.get_texts())


def test_rig_figure_says_the_window_depth_is_schematic_in_air(binocular_residuals):
    cal, _ = binocular_residuals
    frames = {"r": np.array([[0.0, 0.0, 500.0], [50.0, 0.0, 500.0], [0.0, 50.0, 510.0]])}
    air = replace(cal, interface=replace(cal.interface, distance_mm=None), fixed_distance_mm=30.0)  # as exact in air
    fig = draw_rig(air, frames)
    assert "depth schematic: its distance is not observable in air" in _window_label(fig)
    assert any(line.get_linestyle() == "--" for line in fig.axes[0].get_lines())  # the dashed outline
    plt.close(fig)
    known = replace(cal, interface=replace(cal.interface, distance_mm=80.0))
    fig = draw_rig(known, frames)
    assert "schematic" not in _window_label(fig) and "at 80.0 mm" in _window_label(fig)
    plt.close(fig)

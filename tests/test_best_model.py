"""The best model by default: exact refined from ari, lens distortion estimated when the views support
it (one line says why not), each stage's figures kept, `run --truth` printing the errors."""
from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.calibration.calibrate import calibrate, distortion_support
from ari_sfm.calibration.truth_errors import calibration_errors
from ari_sfm.cli import main
from ari_sfm.io import parse_calibration
from ari_sfm.simulate import make_scene

ROOT = Path(__file__).resolve().parents[1]
SIGMA = 0.05
FLOOR = SIGMA * np.sqrt(2)
K1 = -0.05  # a mild, common barrel distortion


def test_run_default_on_the_sample_reaches_the_exact_figures(tmp_path):
    """`ari-sfm run datasets/sample` (no --model): the exact model's 0.020 px and fx within 0.01 % of the
    truth (the paraxial ari stage, shown beside it, is worse); the console prints the errors."""
    r = CliRunner().invoke(main, ["run", str(ROOT / "datasets" / "sample"), "-o", str(tmp_path / "s"),
                                  "--truth", str(ROOT / "datasets" / "sample_truth.json")])
    assert r.exit_code == 0, r.output
    cal = json.loads((tmp_path / "s" / "calibration.json").read_text())
    assert cal["model"] == "exact" and cal["residuals"]["rmse_px"] <= 0.0205
    stages = cal["stages"]
    assert [s["model"] for s in stages] == ["ari", "exact"] and stages[0]["rmse_px"] > 2 * stages[1]["rmse_px"]
    truth = json.loads((ROOT / "datasets" / "sample_truth.json").read_text())
    fx, fx_true = cal["cameras"]["cam0"]["K"][0][0], truth["cameras"]["cam0"]["K"][0][0]
    assert abs(fx / fx_true - 1) < 1e-4
    assert "vs truth (calibrated - true): normal" in r.output and "stages:" in r.output
    assert "(analytic start and bundle-adjustment stages)" in r.output
    errors = json.loads((tmp_path / "s" / "run.json").read_text())["calibration_vs_truth"]
    assert errors["normal_deg"] < 0.05 and abs(errors["cameras"][0]["fx_pct"]) < 0.01


@pytest.mark.parametrize("scenario", ["arc4", "binocular_underwater"])
def test_distortion_by_default_reaches_the_floor(scenario):
    """Lenses with k1 = -0.05: the default estimates the distortion and reaches the noise floor with the
    relative rotations right; held at zero (the old default) the fit stays well above the floor."""
    scene = make_scene(scenario, seed=0, sigma_px=SIGMA, dist=[K1, 0, 0, 0, 0])
    truth = parse_calibration(scene.truth)
    cal = calibrate(scene.dataset, uncertainty=False)
    assert cal.model == "exact" and all(s.distortion for s in cal.stages)
    assert cal.residuals.rmse_px <= 1.05 * FLOOR, cal.residuals
    e = calibration_errors(cal, truth)
    assert max(c.rotation_deg for c in e.cameras if c.rotation_deg is not None) < 0.03, e
    assert max(abs(c.k1) for c in e.cameras) < 0.005 and e.normal_deg < 0.05, e
    held = calibrate(scene.dataset, distortion=False, uncertainty=False)
    assert held.residuals.rmse_px > 1.5 * FLOOR


def _fallback(dataset, caplog, needle):
    with caplog.at_level(logging.WARNING, logger="ari_sfm.calibration.calibrate"):
        cal = calibrate(dataset, uncertainty=False)
    lines = [r.getMessage() for r in caplog.records if "lens distortion not estimated" in r.getMessage()]
    assert len(lines) == 1 and needle in lines[0] and "\n" not in lines[0], lines
    assert not any(s.distortion for s in cal.stages)
    assert all(not np.any(c.dist) for c in cal.cameras.values())
    return cal


def test_too_few_views_fall_back_with_one_line(caplog):
    scene = make_scene("binocular", seed=0, sigma_px=SIGMA)
    keep = sorted({o.frame for o in scene.dataset.select("calibration")})[:4]
    obs = tuple(o for o in scene.dataset.observations if o.set != "calibration" or o.frame in keep)
    cal = _fallback(replace(scene.dataset, observations=obs), caplog, "4 calibration views (at least 6 needed)")
    assert cal.residuals.rmse_px <= 1.2 * FLOOR  # no distortion in this scene: the exact model still fits


def test_corners_in_the_image_centre_fall_back_with_one_line(caplog):
    """Only the corners seen in the central 40 % x 40 % of the image (16 % of it)."""
    scene = make_scene("paper_single", seed=0, sigma_px=SIGMA)
    w, h = scene.dataset.cameras["cam0"].image_size

    def centre(o):
        if o.set != "calibration":
            return o
        keep = (np.abs(o.pixels[:, 0] - w / 2) < 0.2 * w) & (np.abs(o.pixels[:, 1] - h / 2) < 0.2 * h)
        return replace(o, ids=o.ids[keep], pixels=o.pixels[keep])

    obs = tuple(o for o in map(centre, scene.dataset.observations) if len(o.ids) >= 12)
    ds = replace(scene.dataset, observations=obs)
    assert "cover" in distortion_support(ds)
    _fallback(ds, caplog, "% of its image (at least 20 % needed: add views near its edges)")


def test_no_stacking_falls_back_and_distortion_can_be_forced(caplog):
    scene = make_scene("paper_single_nostack", seed=0, sigma_px=SIGMA)
    assert "no stacking poses" in distortion_support(scene.dataset)
    with caplog.at_level(logging.WARNING, logger="ari_sfm.calibration.calibrate"):
        forced = calibrate(scene.dataset, distortion=True, uncertainty=False)
    assert not [r for r in caplog.records if "lens distortion" in r.getMessage()]
    assert all(s.distortion for s in forced.stages)


def test_paper_model_alone_without_distortion():
    """--model ari: the paper's model alone, one stage, no distortion (even where the views would support it)."""
    scene = make_scene("paper_single", seed=0, sigma_px=SIGMA)
    assert distortion_support(scene.dataset) is None
    cal = calibrate(scene.dataset, model="ari", uncertainty=False)
    assert [s.model for s in cal.stages] == ["ari"] and not cal.stages[0].distortion

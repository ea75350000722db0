"""The bundled sample dataset (rendered images, exact physics): the README's first command."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.geometry import angle_between_deg

ROOT = Path(__file__).resolve().parents[1] / "datasets"


@pytest.mark.parametrize("model,normal_tol,fx_tol", [("ari", 1.0, 0.015), ("exact", 0.1, 5e-4)])
def test_sample_from_images(tmp_path, model, normal_tol, fx_tol):
    r = CliRunner().invoke(main, ["run", str(ROOT / "sample"), "-o", str(tmp_path), "--model", model])
    assert r.exit_code == 0, r.output
    cal = json.loads((tmp_path / "calibration.json").read_text())
    truth = json.loads((ROOT / "sample_truth.json").read_text())
    assert (tmp_path / "observations.json").exists()  # detected from the images
    c, t = cal["cameras"]["cam0"], truth["cameras"]["cam0"]
    assert angle_between_deg(cal["interface"]["normal_world"], truth["interface"]["normal_world"]) < normal_tol
    assert abs(c["K"][0][0] / t["K"][0][0] - 1) < fx_tol
    assert np.linalg.norm(np.subtract(c["expansion_center_px"], t["expansion_center_px"])) < 1.0
    assert cal["residuals"]["count"] >= 0.95 * 18 * 88  # (almost) every corner of every image found


def test_bundled_binocular_pipeline_meets_the_accuracy_of_issue_6(tmp_path):
    """The README's third command: calibrate (ari -> exact), reconstruct the stage frames, report."""
    r = CliRunner().invoke(main, ["run", str(ROOT / "binocular"), "-o", str(tmp_path), "--model", "exact",
                                  "--truth", str(ROOT / "binocular_truth.json")])
    assert r.exit_code == 0, r.output
    cal = json.loads((tmp_path / "calibration.json").read_text())
    truth = json.loads((ROOT / "binocular_truth.json").read_text())
    assert angle_between_deg(cal["interface"]["normal_world"], truth["interface"]["normal_world"]) < 0.1
    assert cal["residuals"]["rmse_px"] < 1.2 * 0.05 * np.sqrt(2)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["flatness_mm"]["rmse"] < 0.03
    assert m["stage"]["plane_distance_error_mm"]["max"] < 0.02
    assert m["inter_corner_mm"]["rmse"] < 0.02
    assert m["truth"]["aligned"]["rms_mm"] < 0.05
    assert (tmp_path / "report.html").stat().st_size > 100_000  # figures embedded
    # export-colmap finds the run folder's dataset and points.json by itself
    r = CliRunner().invoke(main, ["export-colmap", str(tmp_path / "calibration.json"), "-o", str(tmp_path / "colmap")])
    assert r.exit_code == 0, r.output
    import pycolmap

    rec = pycolmap.Reconstruction(str(tmp_path / "colmap"))
    points = json.loads((tmp_path / "points.json").read_text())
    n_points = sum(len(f["ids"]) for f in points["frames"].values())
    assert rec.num_images() > 0 and rec.num_reg_images() == rec.num_images()
    assert rec.num_points3D() > n_points  # reconstruction points + calibration corners

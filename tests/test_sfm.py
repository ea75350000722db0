"""`ari-sfm sfm`: rendered images behind a flat port -> COLMAP's SfM (CPU SIFT, matching, mapping) ->
refine-colmap, in one command; and its bad inputs (one line each, nothing left behind)."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.geometry import Pose, angle_between_deg
from ari_sfm.io import load_calibration

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def window_yaml(meta: dict) -> str:
    i = meta["interface"]
    return (f"interface:\n  thickness_mm: {i['thickness_mm']}\n  index: {i['index']}\n"
            f"  medium_index: {i['medium_index']}\nmount: camera\n")


def baseline_args(meta: dict) -> list[str]:
    """--baseline: the first and last images and the distance of their true camera centres (mm)."""
    names = sorted(meta["images"])
    centres = [Pose.from_json(meta["images"][n]).inverse().t for n in (names[0], names[-1])]
    return [names[0], names[-1], str(float(np.linalg.norm(centres[1] - centres[0])))]


@pytest.fixture(scope="module")
def survey_run(tmp_path_factory):
    """10 rendered 640 x 480 images of a relief behind a flat port (exact physics), through `ari-sfm sfm`,
    the scale from the first and last camera centres (as navigation would give)."""
    from ari_sfm.simulate.port_survey import write_port_survey

    tmp = tmp_path_factory.mktemp("sfm")
    _, images = write_port_survey(tmp / "survey", num_images=10, supersample=1)
    meta = json.loads((tmp / "survey" / "truth.json").read_text())
    (tmp / "WINDOW.yaml").write_text(window_yaml(meta))
    r = CliRunner().invoke(main, ["sfm", str(images), "--window", str(tmp / "WINDOW.yaml"), "-o", str(tmp / "out"),
                                  "--focal-px", str(600 * 1.333), "--max-features", "1000", "--threads", "2",
                                  "--baseline", *baseline_args(meta)])
    return tmp, meta, r


def test_sfm_end_to_end_recovers_the_port(survey_run):
    """COLMAP registers the images; refine-colmap recovers the housing's port normal and lowers the
    reprojection error below COLMAP's pinhole; the outputs are where sfm.json says."""
    tmp, meta, r = survey_run
    assert r.exit_code == 0, r.output
    out = tmp / "out"
    summary = json.loads((out / "sfm.json").read_text())
    assert summary["registered"] >= 9 and summary["num_images"] == 10 and summary["matcher"] == "exhaustive"
    assert summary["scale"] == "baseline" and summary["units_mm"] > 0
    assert (out / summary["colmap_model"]).is_dir() and not (out / "colmap.partial").exists()
    cal = load_calibration(out / "refined" / "calibration.json")
    assert cal.model == "exact"
    normal = cal.cameras[next(iter(cal.cameras))].extra.get("normal_cam") or cal.normal_cam(next(iter(cal.cameras)))
    assert angle_between_deg(np.asarray(normal), np.array(meta["camera"]["normal_cam"])) < 1.0
    refine = json.loads((out / "refined" / "refine.json").read_text())
    assert refine["after"]["rms_px"] < 0.6 * refine["before"]["rms_px"]
    assert "registered" in r.output and "refine-colmap" in r.output


def test_sfm_sequential_matcher_on_the_same_images(survey_run, tmp_path):
    """Sequential matching (each image with 3 successors) on a survey in flight order registers the images too."""
    tmp, meta, _ = survey_run
    r = CliRunner().invoke(main, ["sfm", str(tmp / "survey" / "images"), "--window", str(tmp / "WINDOW.yaml"),
                                  "-o", str(tmp_path / "seq"), "--focal-px", str(600 * 1.333), "--max-features",
                                  "1000", "--threads", "2", "--matcher", "sequential", "--overlap", "3",
                                  "--max-iterations", "5", "--baseline", *baseline_args(meta)])
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "seq" / "sfm.json").read_text())
    assert summary["matcher"] == "sequential" and summary["registered"] >= 8


def _one_error_line(r, *needles):
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip() and not ln.startswith("COLMAP")]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert "Traceback" not in r.output


def test_sfm_bad_inputs_one_line(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "imgs").mkdir()
    for i in range(3):
        (tmp_path / "imgs" / f"i{i}.png").write_bytes(b"")
    (tmp_path / "W.yaml").write_text("interface: {thickness_mm: 8, index: 1.49, medium_index: 1.333}\nmount: camera\n"
                                     "units_mm: 10\n")
    (tmp_path / "noscale.yaml").write_text("interface: {thickness_mm: 8, index: 1.49}\nmount: camera\n")
    runner = CliRunner()
    r = runner.invoke(main, ["sfm", str(tmp_path / "imgs"), "--window", str(tmp_path / "noscale.yaml"),
                             "-o", str(tmp_path / "o")])
    _one_error_line(r, "noscale.yaml", "no scale", "--baseline")
    r = runner.invoke(main,
                      ["sfm", str(tmp_path / "empty"), "--window", str(tmp_path / "W.yaml"), "-o", str(tmp_path / "o")])
    _one_error_line(r, "empty", "no images")
    r = runner.invoke(main, ["sfm", str(tmp_path / "imgs"), "--window", str(tmp_path / "none.yaml"), "-o",
                             str(tmp_path / "o")])
    _one_error_line(r, "none.yaml", "not found")
    r = runner.invoke(main, ["sfm", str(tmp_path / "imgs"), "--window", str(tmp_path / "W.yaml"), "-o",
                             str(tmp_path / "imgs")])
    _one_error_line(r, "imgs", "images folder")
    r = runner.invoke(main, ["sfm", str(tmp_path / "imgs"), "--window", str(tmp_path / "W.yaml"),
                             "-o", str(tmp_path / "imgs" / "out")])
    _one_error_line(r, "images folder")
    r = runner.invoke(main,
                      ["sfm", str(tmp_path / "imgs"), "--window", str(tmp_path / "W.yaml"), "-o", str(tmp_path / "o"),
                             "--baseline", "i0.png", "i1.png", "100"])
    _one_error_line(r, "W.yaml", "give it once")
    r = runner.invoke(main, ["sfm", str(tmp_path / "imgs"), "--window", str(tmp_path / "noscale.yaml"),
                             "-o", str(tmp_path / "o"), "--baseline", "i0.png", "nope.png", "100"])
    _one_error_line(r, "imgs", "--baseline: no image nope.png")
    assert not (tmp_path / "o").exists() and not (tmp_path / "imgs" / "out").exists()


def test_sfm_too_few_registered_images(tmp_path):
    """Three unrelated noise images: COLMAP registers none; one line naming the folder, no output left."""
    import cv2

    rng = np.random.default_rng(0)
    (tmp_path / "noise").mkdir()
    for i in range(3):
        cv2.imwrite(str(tmp_path / "noise" / f"n{i}.png"), rng.integers(0, 255, (120, 160), dtype=np.uint8))
    (tmp_path / "W.yaml").write_text("interface: {thickness_mm: 8, index: 1.49, medium_index: 1.333}\nmount: camera\n"
                                     "units_mm: 10\n")
    r = CliRunner().invoke(main, ["sfm", str(tmp_path / "noise"), "--window", str(tmp_path / "W.yaml"),
                                  "-o", str(tmp_path / "o"), "--threads", "1"])
    _one_error_line(r, "noise", "registered", "of the 3 images")
    assert not (tmp_path / "o").exists()

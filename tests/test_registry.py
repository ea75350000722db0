"""The model registry: every model named once, each one's calibration.json round trip, unknown names as one line."""
from __future__ import annotations

import importlib
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.calibration.compare import parse_models
from ari_sfm.calibration.evaluate import evaluate
from ari_sfm.calibration.record import Calibration
from ari_sfm.errors import AriSfmError
from ari_sfm.io import calibration_to_json, load_calibration, load_dataset, save_calibration
from ari_sfm.models import AriModel, ExactModel, PinholeModel
from ari_sfm.models.registry import CALIBRATABLE, MODELS, ModelSpec, model_spec

ROOT = Path(__file__).resolve().parents[1]
BINOCULAR = ROOT / "datasets" / "binocular"
TRUTH = ROOT / "datasets" / "binocular_truth.json"
SIGMA_PX = 0.05  # the bundled binocular dataset's pixel noise per coordinate (datasets/README.md)
FLOOR = SIGMA_PX * np.sqrt(2)  # rmse_px of a perfect model


def assert_same_json(a, b, path: str = "") -> None:
    """Equal keys, strings and lengths; numbers equal to 1e-12 relative (floats recomputed on load)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), f"{path}: keys {list(a)} != {list(b)}"
        for k in a:
            assert_same_json(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), f"{path}: lengths differ"
        for i, (u, v) in enumerate(zip(a, b)):
            assert_same_json(u, v, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, (int, float)) and not isinstance(b, bool):
        assert b == pytest.approx(a, rel=1e-12, abs=1e-12), f"{path}: {a} != {b}"
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


@pytest.fixture(scope="module")
def binocular():
    return load_dataset(BINOCULAR)


@pytest.fixture(scope="module")
def calibrations(binocular_calibrations) -> dict[str, Calibration]:
    """Every calibratable model on the bundled binocular dataset (air behind the window)."""
    return binocular_calibrations


def test_registry_names_every_model_once():
    assert tuple(MODELS) == ("ari", "exact", "rt", "pf", "pinhole", "pinhole_dist", "truth")
    assert CALIBRATABLE == ("ari", "exact", "rt", "pf", "pinhole", "pinhole_dist")
    assert not MODELS["truth"].calibratable
    for spec in MODELS.values():
        assert spec.name and spec.summary
        if spec.calibrator is not None:  # every calibrator named resolves to a function
            module, function = spec.calibrator.split(":")
            assert callable(getattr(importlib.import_module(module), function)), spec.calibrator
    with pytest.raises(ValueError, match="projection must be one of"):
        ModelSpec("x", "a model projecting with nothing known", "fisheye", bundle=True, calibrator=None)


@pytest.mark.parametrize("model", CALIBRATABLE)
def test_every_model_round_trips_its_calibration_json(calibrations, binocular, tmp_path, model):
    cal = calibrations[model]
    spec = model_spec(model)
    assert cal.model == model and cal.spec is spec
    assert (cal.normal_world is not None) == spec.window
    path = tmp_path / "calibration.json"
    save_calibration(cal, path)
    back = load_calibration(path)
    # the file says everything the record holds (derived numbers, e.g. normal_cam = R normal_world, to the last bits)
    assert_same_json(calibration_to_json(back), json.loads(path.read_text()))
    assert back.fixed_distance_mm == cal.fixed_distance_mm
    # the loaded calibration projects like the one in memory, through the class the registry names
    for name in cal.cameras:
        projector = back.projection_model(name)
        if spec.projection != "polynomial":
            assert type(projector) is spec.projection_class()
        X = np.array([[5.0, -3.0, 420.0], [-40.0, 25.0, 380.0]])
        assert np.allclose(back.project_world(name, X), cal.project_world(name, X), atol=1e-9)
    assert evaluate(back, binocular).rmse_px == pytest.approx(cal.residuals.rmse_px, rel=1e-6)


def test_classes_and_capabilities_per_model(calibrations):
    expected = {"ari": AriModel, "exact": ExactModel, "rt": ExactModel, "pinhole": PinholeModel,
                "pinhole_dist": PinholeModel}
    for model, cls in expected.items():
        assert type(calibrations[model].projection_model("cam0")) is cls
    assert MODELS["pf"].camera_keys == ("pf",) and not MODELS["pf"].rays
    with pytest.raises(ValueError, match="no rays"):
        calibrations["pf"].rays_world("cam0", np.array([[100.0, 200.0]]))
    for model in ("ari", "exact", "rt", "pinhole"):
        origins, directions = calibrations[model].rays_world("cam0", np.array([[100.0, 200.0]]))
        assert np.allclose(np.linalg.norm(directions, axis=1), 1.0)


def test_exact_in_air_stores_the_distance_it_used_and_no_pixel_depends_on_it(calibrations, tmp_path):
    # In air a plate shifts rays sideways by an amount set by angle and thickness only: the exact model's pixels
    # do not depend on the window distance, which is why it is stored (fixed_distance_mm), never defaulted.
    for model in ("exact", "rt"):
        cal = calibrations[model]
        assert cal.interface.medium_index == 1.0 and cal.interface.distance_mm is None
        assert cal.fixed_distance_mm is not None and cal.fixed_distance_mm > 0
        assert calibration_to_json(cal)["fixed_distance_mm"] == cal.fixed_distance_mm
        X = np.array([[5.0, -3.0, 420.0], [-40.0, 25.0, 380.0], [60.0, 50.0, 500.0]])
        far = replace(cal, fixed_distance_mm=cal.fixed_distance_mm + 30.0)
        for name in cal.cameras:
            assert np.allclose(far.project_world(name, X), cal.project_world(name, X), atol=1e-8)
    for model in ("ari", "pf", "pinhole"):
        assert calibrations[model].fixed_distance_mm is None
        assert "fixed_distance_mm" not in calibration_to_json(calibrations[model])


def test_exact_without_its_distance_is_one_line_error(calibrations, tmp_path):
    data = calibration_to_json(calibrations["exact"])
    del data["fixed_distance_mm"]
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(data))
    with pytest.raises(AriSfmError, match="fixed_distance_mm is missing") as err:
        load_calibration(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ValueError, match="needs fixed_distance_mm"):
        replace(calibrations["exact"], fixed_distance_mm=None)


@pytest.mark.parametrize("name", ["Exact", "bogus", "", 3, None])
def test_unknown_model_in_calibration_json_is_one_line_error(tmp_path, name):
    data = json.loads(TRUTH.read_text())
    data["model"] = name
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(data))
    with pytest.raises(AriSfmError, match="unknown model") as err:
        load_calibration(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_case_matters_exact_is_not_evaluated_as_ari(calibrations, binocular, tmp_path):
    # The old loader read any unknown name as ari: "Exact" scored the exact calibration at ~3 px instead of
    # its ~0.07 px. The exact one scores at the noise floor; a misspelt one does not load at all.
    cal = calibrations["exact"]
    assert evaluate(cal, binocular).rmse_px < 1.2 * FLOOR
    assert evaluate(replace(cal, model="ari"), binocular).rmse_px > 10 * FLOOR
    with pytest.raises(AriSfmError, match="unknown model 'Exact'"):
        replace(cal, model="Exact")


def test_unknown_model_in_the_api_is_one_line_error(binocular):
    for bad, what in (("bogus", "unknown model 'bogus'"), ("Exact", "unknown model 'Exact'"),
                      ("truth", "model 'truth' is loaded, never calibrated")):
        with pytest.raises(AriSfmError, match=what) as err:
            calibrate(binocular, model=bad)
        assert "\n" not in str(err.value)
    with pytest.raises(AriSfmError, match="--models"):
        parse_models("ari,bogus")
    assert parse_models("pf,ari") == ("pf", "ari")


@pytest.mark.parametrize("args, what", [
    (["calibrate", str(BINOCULAR), "-o", "{tmp}/out", "--model", "bogus"], "--model: unknown model 'bogus'"),
    (["run", str(BINOCULAR), "-o", "{tmp}/out", "--model", "Exact"], "--model: unknown model 'Exact'"),
    (["compare", str(BINOCULAR), "-o", "{tmp}/out", "--models", "ari,bogus"], "--models: expected"),
    (["compare", str(BINOCULAR), "-o", "{tmp}/out", "--pf-world", "pf"], "--pf-world: expected one of ari, exact"),
    (["evaluate", "{tmp}/calibration.json", str(BINOCULAR / "observations.json")], "unknown model 'bogus'"),
])
def test_unknown_model_on_the_command_line_is_one_line_error(tmp_path, args, what):
    data = json.loads(TRUTH.read_text())
    data["model"] = "bogus"
    (tmp_path / "calibration.json").write_text(json.dumps(data))
    run = subprocess.run([sys.executable, "-m", "ari_sfm.cli", *[a.format(tmp=tmp_path) for a in args]],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 1
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and what in lines[0], lines
    assert not (tmp_path / "out").exists()

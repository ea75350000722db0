"""Which calibration and dataset made points.json / metrics.json (issue 10, item 7): recorded by
`reconstruct`, and `report` / `export-colmap` refuse or label what does not belong together."""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.io import load_dataset
from ari_sfm.provenance import observations_sha256
from ari_sfm.simulate import simulate


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """`ari-sfm run` (model ari) on the simulated binocular rig: (dataset folder, OUT)."""
    base = tmp_path_factory.mktemp("prov")
    ds, _ = simulate("binocular", base / "sim", seed=0, images=False)
    out = base / "out"
    r = CliRunner().invoke(main, ["run", str(ds), "-o", str(out), "--model", "ari"])
    assert r.exit_code == 0, r.output
    return Path(ds), out


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _copy(out: Path, dst: Path) -> Path:
    shutil.copytree(out, dst)
    return dst


def test_points_and_metrics_record_their_calibration_and_dataset(run_dir):
    ds, out = run_dir
    for name in ("points.json", "metrics.json"):
        prov = json.loads((out / name).read_text())["provenance"]
        assert prov["calibration"] == {"path": str((out / "calibration.json").resolve()),
                                       "sha256": _sha(out / "calibration.json"), "model": "ari"}
        assert prov["dataset"] == {"path": str(ds.resolve()), "rig": str((ds / "rig.yaml").resolve()),
                                   "rig_sha256": _sha(ds / "rig.yaml"),
                                   "observations_sha256": observations_sha256(load_dataset(ds).observations)}
    assert json.loads((out / "metrics.json").read_text())["dataset"] == str(ds.resolve())  # absolute


def _report(out: Path, *extra: str):
    r = CliRunner().invoke(main, ["report", str(out), *extra])
    return r, (out / "report.html").read_text() if (out / "report.html").exists() else ""


def test_report_of_matching_results_has_no_label(run_dir, tmp_path):
    out = _copy(run_dir[1], tmp_path / "out")
    r, text = _report(out)
    assert r.exit_code == 0, r.output
    assert "not of this calibration" not in text and "made with another calibration" not in text


def test_report_labels_an_older_reconstruction_under_a_newer_calibration(run_dir, tmp_path):
    """calibrate --model exact into a run folder: metrics.json is still ari's; the report says so."""
    ds, out = run_dir
    out = _copy(out, tmp_path / "out")
    r = CliRunner().invoke(main, ["calibrate", str(ds), "-o", str(out), "--model", "exact"])
    assert r.exit_code == 0, r.output
    r, text = _report(out)
    assert r.exit_code == 0, r.output
    assert "<h2>Reconstruction (not of this calibration or dataset)</h2>" in text
    assert "metrics.json was made with another calibration" in text and "model ari" in text and "model exact" in text


def test_report_labels_results_of_an_older_file_by_model(run_dir, tmp_path):
    """Files written before provenance: the metrics' model decides."""
    out = _copy(run_dir[1], tmp_path / "out")
    for name in ("points.json", "metrics.json"):
        data = json.loads((out / name).read_text())
        del data["provenance"]
        (out / name).write_text(json.dumps(data))
    cal = json.loads((out / "calibration.json").read_text())
    cal["model"] = "exact"
    cal["fixed_distance_mm"] = 30.0  # an exact calibration in air says where it put the window
    (out / "calibration.json").write_text(json.dumps(cal))
    r, text = _report(out)
    assert r.exit_code == 0, r.output
    assert "made with a model ari calibration" in text


def test_report_refuses_a_dataset_of_another_rig(run_dir, tmp_path):
    other, _ = simulate("paper_single", tmp_path / "single", seed=0, images=False)
    out = _copy(run_dir[1], tmp_path / "out")
    r, _ = _report(out, "--dataset", str(other))
    assert r.exit_code == 1 and r.output.count("\n") == 1
    assert r.output.startswith(f"error: {out / 'calibration.json'}: calibration is from another rig")


def test_report_labels_another_dataset_of_the_same_rig(run_dir, tmp_path):
    ds, out = run_dir
    other = shutil.copytree(ds, tmp_path / "other")
    (other / "rig.yaml").write_text((other / "rig.yaml").read_text() + "# edited\n")
    out = _copy(out, tmp_path / "out")
    r, text = _report(out, "--dataset", str(other))
    assert r.exit_code == 0, r.output
    assert "points.json was made from the dataset" in text and str(ds.resolve()) in text


def test_report_does_not_resolve_a_relative_dataset_against_the_working_folder(run_dir, tmp_path, monkeypatch):
    """An older metrics.json naming the dataset relative to an unknown folder: not guessed."""
    ds, out = run_dir
    out = _copy(out, tmp_path / "out")
    (out / "run.json").unlink()
    data = json.loads((out / "metrics.json").read_text())
    del data["provenance"]
    data["dataset"] = "sim"
    (out / "metrics.json").write_text(json.dumps(data))
    other, _ = simulate("paper_single", tmp_path / "cwd" / "sim", seed=0, images=False)  # another rig there
    monkeypatch.chdir(tmp_path / "cwd")
    r, text = _report(out)
    assert r.exit_code == 0, r.output
    assert "dataset not found (pass --dataset)" in text


def test_export_colmap_refuses_points_of_another_calibration(run_dir, tmp_path):
    ds, out = run_dir
    other = tmp_path / "exact"
    r = CliRunner().invoke(main, ["calibrate", str(ds), "-o", str(other), "--model", "exact"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["export-colmap", str(other / "calibration.json"), "-o", str(tmp_path / "model"),
                                  "--dataset", str(ds), "--points", str(out / "points.json")])
    assert r.exit_code == 1, r.output
    assert r.output.strip().splitlines()[-1].startswith(f"error: {out / 'points.json'}: made with another calibration")
    assert not (tmp_path / "model").exists()


def test_export_colmap_refuses_points_of_frames_the_dataset_does_not_have(run_dir, tmp_path):
    ds, out = run_dir
    out = _copy(out, tmp_path / "out")
    data = json.loads((out / "points.json").read_text())
    del data["provenance"]
    data["frames"] = {f"x{name}": frame for name, frame in data["frames"].items()}
    (out / "points.json").write_text(json.dumps(data))
    r = CliRunner().invoke(main, ["export-colmap", str(out / "calibration.json"), "-o", str(tmp_path / "model"),
                                  "--dataset", str(ds), "--points", str(out / "points.json")])
    assert r.exit_code == 1 and "have no reconstruction observations in the dataset exported" in r.output

"""Every CLI path: --help, simulate -> calibrate -> evaluate, and bad inputs that must give
one line `error: <file>: <problem>`, exit code 1 and no result file."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from ari_sfm.cli import main


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim")
    r = CliRunner().invoke(main, ["simulate", "paper_single", "-o", str(out), "--no-images", "--seed", "0"])
    assert r.exit_code == 0, r.output
    return out


@pytest.mark.parametrize("cmd", [[], ["detect"], ["calibrate"], ["run"], ["evaluate"], ["simulate"], ["scenarios"],
                                 ["doctor"]])
def test_help(cmd):
    r = CliRunner().invoke(main, cmd + ["--help"])
    assert r.exit_code == 0 and "Usage" in r.output


def test_calibrate_then_evaluate(sim_dir, tmp_path):
    runner = CliRunner()
    r = runner.invoke(main, ["calibrate", str(sim_dir / "dataset"), "-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    assert "rmse" in r.output and "cam0" in r.output
    cal = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert cal["format"] == "ari-sfm-calibration/1" and cal["model"] == "exact"  # the default: the best model
    assert [st["model"] for st in cal["stages"]] == ["ari", "exact"] and "stages:" in r.output
    assert len(cal["cameras"]["cam0"]["expansion_center_px"]) == 2
    assert len(cal["cameras"]["cam0"]["expansion_center_std_px"]) == 2
    assert not (tmp_path / "out" / "observations.json").exists()  # nothing was detected here
    r = runner.invoke(main, ["evaluate", str(tmp_path / "out" / "calibration.json"),
                             str(sim_dir / "dataset" / "observations.json")])
    assert r.exit_code == 0, r.output
    rmse = float(r.output.split()[1])
    assert abs(rmse - cal["residuals"]["rmse_px"]) < 1e-4  # printed to 4 decimals



def test_evaluate_solve_poses_judges_held_out_views(sim_dir, tmp_path):
    """--solve-poses fits every frame's pose with the rig fixed: exact stays at the noise floor (sigma 0.05 px per
    coordinate: 0.071 px) on 4 new poses of the same rig, also when they reuse the calibration's frame names.
    Without it only the calibration's frames count; a file of none of them is one error line."""
    from dataclasses import replace

    from ari_sfm.io import save_observations
    from ari_sfm.simulate import ScenarioOverrides, make_scene

    r = CliRunner().invoke(main,
                           ["calibrate", str(sim_dir / "dataset"), "-o", str(tmp_path / "out"), "--model", "exact"])
    assert r.exit_code == 0, r.output
    cal_path = str(tmp_path / "out" / "calibration.json")
    held = make_scene("paper_single", seed=0, overrides=ScenarioOverrides(num_frames=16))  # the same rig, 4 more poses
    cal = json.loads((tmp_path / "out" / "calibration.json").read_text())
    new = [o for o in held.dataset.observations if o.set == "calibration" and o.frame not in cal["frames"]]
    assert len(new) == 4
    renamed = [replace(o, frame=f) for o, f in zip(new, sorted(cal["frames"]))]  # another session's f000..f003
    corners = sum(len(o.ids) for o in new)

    def run(records, *flag):
        save_observations(tmp_path / "held.json", records)
        return CliRunner().invoke(main, ["evaluate", cal_path, str(tmp_path / "held.json"), *flag])

    for records in (new, renamed):
        r = run(records, "--solve-poses")
        assert r.exit_code == 0, r.output
        assert int(r.output.split("(")[1].split()[0]) == corners and float(r.output.split()[1]) < 1.3 * 0.0707, r.output
    r = run(renamed)  # judged at the calibration's poses of f000..f003: far off
    assert r.exit_code == 0 and float(r.output.split()[1]) > 10, r.output
    r = run(new)  # frames the calibration does not hold
    assert r.exit_code == 1 and "--solve-poses" in r.output and "nan" not in r.output, r.output


def test_backend_option_picks_the_solver(sim_dir, tmp_path):
    """--backend gtsam runs gtsam.LevenbergMarquardtOptimizer, numpy the vectorised solver: the same calibration."""
    cals = {}
    for backend in ("gtsam", "numpy"):
        r = CliRunner().invoke(main, ["calibrate", str(sim_dir / "dataset"), "-o", str(tmp_path / backend),
                                      "--model", "exact", "--backend", backend])
        assert r.exit_code == 0, r.output
        cals[backend] = json.loads((tmp_path / backend / "calibration.json").read_text())
        assert {s["backend"] for s in cals[backend]["optimizer"].values()} == {backend}
    K_g, K_n = cals["gtsam"]["cameras"]["cam0"]["K"], cals["numpy"]["cameras"]["cam0"]["K"]
    assert sum(K_n, []) == pytest.approx(sum(K_g, []), rel=1e-9)
    r = CliRunner().invoke(main,
                           ["calibrate", str(sim_dir / "dataset"), "-o", str(tmp_path / "x"), "--backend", "cuda"])
    assert r.exit_code != 0 and "cuda" in r.output


def test_console_script_runs(sim_dir, tmp_path):
    """The installed `ari-sfm` entry point (not only the click object) works."""
    exe = Path(sys.executable).parent / "ari-sfm"
    p = subprocess.run([str(exe), "calibrate", str(sim_dir / "dataset"), "-o", str(tmp_path / "o"), "--model", "exact"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert json.loads((tmp_path / "o" / "calibration.json").read_text())["model"] == "exact"


def _copy_dataset(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def _edit_rig(ds: Path, fn) -> None:
    rig = yaml.safe_load((ds / "rig.yaml").read_text())
    fn(rig)
    (ds / "rig.yaml").write_text(yaml.safe_dump(rig))


def _edit_obs(ds: Path, fn) -> None:
    obs = json.loads((ds / "observations.json").read_text())
    fn(obs)
    (ds / "observations.json").write_text(json.dumps(obs))


BAD = {
    "missing dataset": (lambda ds: None, "nonexistent", "no such"),
    "malformed yaml": (lambda ds: (ds / "rig.yaml").write_text("format: ari-sfm/1\ntarget: [unclosed\n"), None,
                       "rig.yaml"),
    "unknown format": (lambda ds: _edit_rig(ds, lambda r: r.update(format="ari-sfm/99")), None, "format"),
    "thickness <= 0": (lambda ds: _edit_rig(ds, lambda r: r["interface"].update(thickness_mm=0)), None, "thickness"),
    "index < 1": (lambda ds: _edit_rig(ds, lambda r: r["interface"].update(index=0.9)), None, "index"),
    "missing key": (lambda ds: _edit_rig(ds, lambda r: r.pop("target")), None, "target"),
    "nan pixel": (lambda ds: _edit_obs(ds, lambda o: o["observations"][0]["pixels"][0].__setitem__(0, float("nan"))),
                  None, "observations.json"),
    "id out of range": (lambda ds: _edit_obs(ds, lambda o: o["observations"][0]["ids"].__setitem__(0, 500)), None,
                        "observations.json"),
    "unknown camera": (lambda ds: _edit_obs(ds, lambda o: o["observations"][0].update(camera="cam9")), None, "cam9"),
    "malformed json": (lambda ds: (ds / "observations.json").write_text(
        '{"format": "ari-sfm-observations/1", "observations": [}'), None, "observations.json"),
    "no stacking": (lambda ds: (_edit_rig(ds, lambda r: r.pop("stacking", None)),
                                _edit_obs(ds, lambda o: o.update(observations=[r for r in o["observations"]
                                                                               if r["set"] != "stacking"]))),
                    None, "normal"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_gives_one_line_error_and_no_result(case, sim_dir, tmp_path):
    mutate, path_override, needle = BAD[case]
    ds = _copy_dataset(sim_dir / "dataset", tmp_path / "ds")
    mutate(ds)
    target = tmp_path / path_override if path_override else ds
    out = tmp_path / "out"
    model = ["--model", "ari"] if case == "no stacking" else []  # the paper's model cannot see the normal then
    r = CliRunner().invoke(main, ["calibrate", str(target), "-o", str(out)] + model)
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()] if hasattr(r, "stderr") else r.output.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    assert needle.lower() in lines[0].lower(), lines[0]
    assert "Traceback" not in r.output
    assert not (out / "calibration.json").exists()
    assert not list(out.glob("*.tmp*")) if out.exists() else True


def test_detect_without_images_is_one_line_and_writes_nothing(sim_dir, tmp_path):
    """A corners-only dataset (the simulator's --no-images) has nothing to detect: one line, no empty
    observations.json beside it."""
    ds = _copy_dataset(sim_dir / "dataset", tmp_path / "ds")
    r = CliRunner().invoke(main, ["detect", str(ds)])
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "rig.yaml" in lines[0] and "no images" in lines[0]
    assert not (tmp_path / "ds-detections").exists()


# --------------------------------------------------------------------------- --config FILE


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_config_file_sets_options_and_the_command_line_overrides_it(sim_dir, tmp_path):
    """`model: ari` and `distortion: true` from the file are applied (the calibration is the paper's model with
    a lens); `--model exact --no-distortion` on the command line win over the same file; `out` may come
    from it too."""
    cfg = _write(tmp_path / "run.yaml", f"model: ari\ndistortion: true\nhuber-px: 0.5\nout: {tmp_path / 'a'}\n")
    r = CliRunner().invoke(main, ["calibrate", str(sim_dir / "dataset"), "--config", str(cfg)])
    assert r.exit_code == 0, r.output
    cal = json.loads((tmp_path / "a" / "calibration.json").read_text())
    assert cal["model"] == "ari" and any(abs(k) > 1e-6 for k in cal["cameras"]["cam0"]["dist"])
    r = CliRunner().invoke(main, ["calibrate", str(sim_dir / "dataset"), "--config", str(cfg), "-o",
                                  str(tmp_path / "b"), "--model", "exact", "--no-distortion"])
    assert r.exit_code == 0, r.output
    assert not (tmp_path / "a" / "b").exists()
    cal = json.loads((tmp_path / "b" / "calibration.json").read_text())
    assert cal["model"] == "exact" and cal["cameras"]["cam0"]["dist"] == [0.0] * 5


def test_config_values_reach_the_particle_commands(tmp_path):
    """particles and self-calibrate take --config: their values go through each option's own checks, and a
    value the command refuses is told against the file and the key."""
    for command, text, needle in (
            ("particles", "tolerance_px: -2\n", "tolerance_px: must be > 0"),
            ("self-calibrate", "cells: [3, 3, 0]\n", "cells: must be >= 1"),
            ("particles", "depth_range: [5, -5]\n", "ZMAX must exceed ZMIN")):
        cfg = _write(tmp_path / f"{command}.yaml", text)
        r = CliRunner().invoke(main, [command, str(tmp_path), "--calibration", str(tmp_path / "c.json"),
                                      "-o", str(tmp_path / "out"), "--config", str(cfg)])
        lines = [ln for ln in r.output.splitlines() if ln.strip()]
        assert r.exit_code == 1 and len(lines) == 1 and needle in lines[0], (command, r.output)
        if "ZMAX" not in needle:  # --depth-range's pair check names the option, not one value
            assert lines[0].startswith(f"error: {cfg}: "), r.output
    assert not (tmp_path / "out").exists()


CONFIG_ERRORS = {
    "unknown key": ("huber: 1\n", "huber: not an option of `ari-sfm calibrate`"),
    "argument": ("dataset: x\n", "dataset: is an argument"),
    "bad float": ("huber_px: abc\n", "huber_px: 'abc' is not a valid float"),
    "bool for a number": ("huber_px: true\n", "huber_px: must be a number"),
    "bad choice": ("backend: fast\n", "backend: 'fast' is not one of"),
    "bad flag": ("distortion: 3\n", "distortion: must be true or false"),
    "out of range": ("huber_px: -1\n", "huber_px: must be >= 0"),
    "not a mapping": ("[1, 2]\n", "must be a mapping"),
    "malformed": ("model: [ari\n", "malformed YAML"),
}


@pytest.mark.parametrize("case", sorted(CONFIG_ERRORS))
def test_config_errors_are_one_line_naming_the_file_and_the_key(case, sim_dir, tmp_path):
    text, needle = CONFIG_ERRORS[case]
    cfg = _write(tmp_path / "bad.yaml", text)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["calibrate", str(sim_dir / "dataset"), "-o", str(out), "--config", str(cfg)])
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code == 1 and len(lines) == 1, r.output
    assert lines[0].startswith(f"error: {cfg}: ") and needle in lines[0], lines[0]
    assert not (out / "calibration.json").exists()


def test_config_option_is_in_each_commands_help():
    for command in ("calibrate", "run", "particles", "self-calibrate"):
        r = CliRunner().invoke(main, [command, "--help"])
        assert r.exit_code == 0 and "--config FILE" in r.output and "override" in r.output, command


# --------------------------------------------------------------------------- doctor


def test_doctor_prints_every_dependency_with_its_version_and_the_kernels():
    from importlib import metadata

    from ari_sfm.deps import DEPENDENCIES
    from ari_sfm.kernel_cache import shipped_usable

    r = CliRunner().invoke(main, ["doctor"])
    assert r.exit_code == 0, r.output
    lines = {ln.split()[0]: ln.split(None, 1)[1] for ln in r.output.splitlines() if ln.strip()}
    assert [name for name, *_ in DEPENDENCIES] == [n for n in lines if n not in ("ari-sfm", "kernels")]
    for name in ("numpy", "scipy", "numba", "gtsam", "pycolmap", "open3d", "pyarrow", "dask", "distributed",
                 "plotly", "tqdm", "click", "matplotlib"):
        assert lines[name] == metadata.version(name), (name, lines[name])  # gtsam too: it has no __version__
    assert lines["pyyaml"] == metadata.version("pyyaml")
    assert lines["opencv"].split(".")[:2] == metadata.version("opencv-contrib-python-headless").split(".")[:2]
    try:
        assert lines["optv"] == metadata.version("optv")
    except metadata.PackageNotFoundError:  # optional: reported, not an error
        assert lines["optv"].startswith("not available (not installed; optional")
    usable, why = shipped_usable()
    assert lines["kernels"].startswith("compiled, shipped" if usable else "compiled on first use")
    assert why in lines["kernels"]


def test_doctor_fails_when_a_required_dependency_does_not_import(monkeypatch):
    """A missing required library: its line says so and doctor exits 1; a missing optional one does not fail."""
    import sys as _sys

    monkeypatch.setitem(_sys.modules, "tqdm", None)  # import tqdm -> ModuleNotFoundError
    monkeypatch.setitem(_sys.modules, "optv", None)
    r = CliRunner().invoke(main, ["doctor"])
    assert r.exit_code == 1, r.output
    lines = {ln.split()[0]: ln.split(None, 1)[1] for ln in r.output.splitlines() if ln.strip()}
    assert lines["tqdm"] == "error: not installed" and lines["optv"].startswith("not available")
    assert lines["numpy"] and not lines["numpy"].startswith("error")

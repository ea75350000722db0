"""calibrate() as a plan of stages (issue 17 item 4): plan_stages, the StageResults behind calibration.json's
``stages`` and ``optimizer``, and the one initial state RigGraph.from_dataset and calibrate() share."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ari_sfm.calibration.calibrate import CalibrationOptions, Stage, plan_stages
from ari_sfm.errors import AriSfmError
from ari_sfm.io import calibration_to_json, load_calibration, save_calibration
from ari_sfm.records import WindowPlane

OPTS = CalibrationOptions(distortion=False)


def _without_stacking(dataset):
    return replace(dataset, observations=tuple(o for o in dataset.observations if o.set != "stacking"))


def _with_true_plane(scene, frame: str = None):
    """The scene's dataset declaring its true window (interface.plane) in the target frame of ``frame``."""
    g = scene.geometry
    frame = frame or sorted(g.calibration)[0]
    target_from_world = g.calibration[frame].inverse()
    n_w = np.asarray(g.window.normal_world, float)
    plane = WindowPlane(frame, target_from_world.R @ n_w,
                        target_from_world.apply((n_w * g.window.distance_mm)[None])[0])
    ds = scene.dataset
    return replace(ds, interface=replace(ds.interface, plane=plane))


def test_the_plans(single_scene):
    """Each model's stages, as the paper and the declared window ask; pure (twice the same, the dataset untouched)."""
    ds = single_scene.dataset
    assert plan_stages(ds, "ari", OPTS) == (Stage("ari", "ari"),)
    assert plan_stages(ds, "exact", OPTS) == (Stage("ari", "ari"), Stage("exact", "exact"))
    assert plan_stages(ds, "exact", replace(OPTS, distortion=True))[-1].distortion
    assert plan_stages(ds, "pf", OPTS) == () and plan_stages(ds, "rt", OPTS) == ()  # their own calibrators
    bare = _without_stacking(ds)
    assert plan_stages(bare, "exact", OPTS) == (Stage("ari", "ari", hold_normal=True), Stage("exact", "exact"))
    with pytest.raises(AriSfmError, match="no stacking observations and no interface.plane"):
        plan_stages(bare, "ari", OPTS)  # the paraxial model cannot observe the normal
    declared = _with_true_plane(single_scene)
    assert plan_stages(declared, "exact", OPTS) == (Stage("ari", "ari", with_plane=True),
                                                    Stage("exact", "exact", with_plane=True))
    bare_declared = _without_stacking(declared)
    assert plan_stages(bare_declared, "ari", OPTS) == (Stage("ari_normal_held", "ari", hold_normal=True),
                                                       Stage("ari", "ari", with_plane=True))
    wet = replace(declared, interface=replace(declared.interface, medium_index=1.333))
    assert plan_stages(wet, "exact", OPTS) == (Stage("ari", "ari"), Stage("exact_free", "exact", skippable=True),
                                               Stage("exact", "exact", with_plane=True))
    assert plan_stages(wet, "exact", OPTS) == plan_stages(wet, "exact", OPTS)
    assert wet.interface.plane == declared.interface.plane and ds.interface.plane is None
    assert all(s.snell == (s.model == "exact") for s in plan_stages(wet, "exact", OPTS))


def test_the_stage_records_are_the_plans(single_exact, single_scene):
    """calibration.json's stages and optimizer report: one entry per planned stage, in order, the last
    stage's figures those of the result."""
    plan = plan_stages(single_scene.dataset, "exact", OPTS)
    d = calibration_to_json(single_exact)
    assert [s["stage"] for s in d["stages"]] == [s.label for s in plan]
    assert [s["model"] for s in d["stages"]] == [s.model for s in plan]
    assert list(single_exact.optimizer.runs) == list(d["optimizer"]) == [s.label for s in plan]
    assert all(r.iterations > 0 and r.sigma_px > 0 and r.backend == "numpy"
               for r in single_exact.optimizer.runs.values())
    last = d["stages"][-1]
    assert last["rmse_px"] == pytest.approx(single_exact.residuals.rmse_px, rel=1e-12)
    assert last["cameras"]["cam0"]["fx"] == pytest.approx(single_exact.cameras["cam0"].K[0, 0], rel=1e-12)
    # the ari stage keeps the paraxial error, the exact stage reaches the noise floor (sigma 0.05 px: 0.0707)
    assert d["stages"][0]["rmse_px"] > 1.5 * last["rmse_px"] and last["rmse_px"] < 1.05 * 0.05 * np.sqrt(2)


@pytest.mark.parametrize("model", ["ari", "exact"])
@pytest.mark.parametrize("declared", [False, True])
def test_one_initial_state(single_scene, model, declared):
    """RigGraph.from_dataset starts where calibrate() starts (the one initial_state); a declared plane in air
    gives the start its true normal and distance (the plane says where the window is, even where the rays do
    not depend on it)."""
    from ari_sfm.calibration.calibrate import Start, _Solver, _start_state
    from ari_sfm.factors.rig_graph import RigGraph
    from ari_sfm.factors.window_plane import plane_in_world

    ds = _with_true_plane(single_scene) if declared else single_scene.dataset
    solver = _Solver(ds, OPTS, "numpy")
    plan = plan_stages(ds, model, OPTS)
    rig, _, state = _start_state(solver, plan, Start("default", False))
    graph_state = RigGraph.from_dataset(ds, model=plan[0].model, sigma_px=1.0).base_state
    for name in ds.camera_names:
        np.testing.assert_array_equal(graph_state.params[name], state.params[name])
        np.testing.assert_array_equal(graph_state.cam_from_world[name].R, state.cam_from_world[name].R)
    np.testing.assert_array_equal(graph_state.normal_world, state.normal_world)
    assert graph_state.distance_mm == state.distance_mm
    window = single_scene.geometry.window
    if declared:  # the true plane placed by the analytic pose of its frame, in air too
        plane = ds.interface.plane
        assert state.distance_mm == plane_in_world(plane, state.world_from_target[plane.frame])[1]
        assert np.degrees(np.arccos(min(1.0, state.normal_world @ window.normal_world))) < 1.0
        # the analytic poses lie within the paraxial shift d (1 - 1/n) of the truth along the normal
        assert abs(state.distance_mm - window.distance_mm) < window.thickness_mm * (1 - 1 / window.index)
    else:  # air, no plane: the ari start has no distance (nothing depends on it)
        assert state.distance_mm is None


@pytest.mark.parametrize("command", ["calibrate", "run"])
def test_the_command_line_options_are_the_dataclass_fields(command, tmp_path, monkeypatch):
    """calibrate and run offer every CalibrationOptions field with a ``cli`` flag, default and help from the
    field; the flags given arrive at calibrate() as one CalibrationOptions record (--huber-px 0: None)."""
    import importlib
    from dataclasses import fields

    from click.testing import CliRunner

    C = importlib.import_module("ari_sfm.calibration.calibrate")
    from ari_sfm.calibration.calibrate import CalibrationOptions
    from ari_sfm.cli import main

    cmd = main.commands[command]
    params = {p.name: p for p in cmd.params}
    offered = [f for f in fields(CalibrationOptions) if "cli" in f.metadata]
    assert {f.name for f in offered} == {"distortion", "huber_px", "exclude_outliers", "fix_intrinsics", "backend",
                                         "principal_point"}
    for f in offered:
        assert params[f.name].default == f.default and f.metadata["cli"].split("/")[0] in params[f.name].opts
    seen = []

    def spy(dataset, model=C.DEFAULT_MODEL, extra_factors=None, options=None, **overrides):
        seen.append(C._options(options, overrides))
        raise C.AriSfmError("spy", "stopped")

    monkeypatch.setattr("ari_sfm.pipelines.calibrate_rig.calibrate", spy)
    # observations: no detection
    dataset = str(__import__("pathlib").Path(__file__).resolve().parents[1] / "datasets" / "binocular")
    r = CliRunner().invoke(main, [command, dataset, "-o", str(tmp_path / "a")])
    assert r.exit_code == 1 and "error: spy: stopped" in r.output, r.output
    assert seen[-1] == CalibrationOptions(progress=True)
    r = CliRunner().invoke(main, [command, dataset, "-o", str(tmp_path / "b"), "--huber-px", "0", "--no-distortion",
                                  "--exclude-outliers", "--backend", "gtsam"])
    assert r.exit_code == 1, r.output
    assert seen[-1] == CalibrationOptions(distortion=False, huber_px=None, exclude_outliers=True, backend="gtsam",
                                          progress=True)


def test_the_optimizer_report_is_a_record(single_exact, tmp_path):
    """calibration.json's optimizer report read back as the same record, written as the same JSON."""
    from ari_sfm.results import OptimizerReport, OptimizerRun

    save_calibration(single_exact, tmp_path / "c.json")
    back = load_calibration(tmp_path / "c.json")
    assert back.optimizer == single_exact.optimizer and "optimizer" not in back.extra
    assert calibration_to_json(back)["optimizer"] == calibration_to_json(single_exact)["optimizer"]
    scipy_run = {"nfev": 12, "status": 2, "time_s": 0.5, "backend": "scipy", "note": "kept"}
    run = OptimizerRun.from_json(scipy_run)
    assert (run.nfev, run.status, run.iterations, run.extra) == (12, 2, None, {"note": "kept"})
    assert list(OptimizerReport.from_json({"rt": scipy_run}).to_json()["rt"].items()) == list(scipy_run.items())
    with pytest.raises(KeyError):
        OptimizerRun.from_json({"iterations": 3})  # no time_s nor backend


def test_run_reads_the_dataset_once(tmp_path, monkeypatch):
    """`run` loads the dataset once and passes the records on: calibration.json is not read back, and the
    points carry the hash of the calibration.json written (the file they are reproducible from)."""
    import json
    from pathlib import Path

    import ari_sfm.io as io_module
    import ari_sfm.io.calibration_file as calibration_file
    from ari_sfm.pipelines import calibrate_rig, run
    from ari_sfm.provenance import file_sha256

    loads, cal_reads = [], []
    load_dataset, load_calibration = io_module.load_dataset, calibration_file.load_calibration

    def counting_load(*args, **kwargs):
        loads.append(args)
        return load_dataset(*args, **kwargs)

    def counting_cal(path, *args, **kwargs):
        cal_reads.append(Path(path))
        return load_calibration(path, *args, **kwargs)

    for module in (io_module, run, calibrate_rig):
        monkeypatch.setattr(module, "load_dataset", counting_load)
    for module in (io_module, calibration_file, run):  # every name calibration.json is read through
        monkeypatch.setattr(module, "load_calibration", counting_cal)
    monkeypatch.setattr(run, "write_report", lambda out: Path(out) / "report.html")  # the report reads its files
    dataset = Path(__file__).resolve().parents[1] / "datasets" / "binocular"
    result = run.main(dataset, tmp_path, model="ari", options=CalibrationOptions(uncertainty=False))
    assert len(loads) == 1 and not [p for p in cal_reads if p.name == "calibration.json"]
    points = json.loads((tmp_path / "points.json").read_text())
    assert points["provenance"]["calibration"]["sha256"] == file_sha256(tmp_path / "calibration.json")
    assert result.reconstruction.metrics.num_points > 900  # 11 frames of 88 corners seen by both cameras


def test_the_modes_are_enums_read_as_their_strings():
    """principal_point and backend: a Python caller's string becomes the enum, which compares, prints and is
    written as that string; anything else is one line naming the allowed values."""
    import json

    from ari_sfm.calibration.calibrate import Backend, PrincipalPoint

    opts = CalibrationOptions(principal_point="centre", backend="gtsam")
    assert opts.principal_point is PrincipalPoint.CENTRE and opts.backend is Backend.GTSAM
    assert opts == CalibrationOptions(principal_point=PrincipalPoint.CENTRE, backend=Backend.GTSAM)
    assert opts.backend == "gtsam" and f"{opts.backend}" == str(opts.backend) == "gtsam"
    assert json.dumps({"backend": opts.backend}) == '{"backend": "gtsam"}'
    assert CalibrationOptions().principal_point is PrincipalPoint.AUTO and CalibrationOptions().backend is Backend.AUTO
    for name, allowed in (("principal_point", "auto, free, centre"), ("backend", "auto, numpy, gtsam")):
        with pytest.raises(ValueError) as exc:
            CalibrationOptions(**{name: "middle"})
        assert str(exc.value) == f"{name} must be one of {allowed} (got 'middle')"


def test_the_pipelines_take_the_options_record(tmp_path, monkeypatch):
    """calibrate_rig passes its CalibrationOptions to calibrate as one record (progress replaced by its own
    argument), and takes no option keywords."""
    from pathlib import Path

    import ari_sfm.calibration.calibrate as C
    from ari_sfm.pipelines import calibrate_rig

    seen = []

    def spy(dataset, model=C.DEFAULT_MODEL, extra_factors=None, options=None, **overrides):
        seen.append((options, overrides))
        raise C.AriSfmError("spy", "stopped")

    monkeypatch.setattr(calibrate_rig, "calibrate", spy)
    dataset = Path(__file__).resolve().parents[1] / "datasets" / "binocular"
    with pytest.raises(C.AriSfmError):
        calibrate_rig.main(dataset, tmp_path, "ari", options=CalibrationOptions(huber_px=0.5, backend="gtsam"))
    assert seen == [(CalibrationOptions(huber_px=0.5, backend="gtsam"), {})]
    with pytest.raises(TypeError):
        calibrate_rig.main(dataset, tmp_path, "ari", uncertainty=False)

"""No silent wrong result, no traceback: cases found by using the newer commands as documented.

Each test is one case of the bad-input and misuse matrix, fixed at its root.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.io import load_calibration

ROOT = Path(__file__).resolve().parents[1]


def _run(args: list[str]):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_exclude_outliers_drops_a_frame_whose_every_corner_was_wrong(tmp_path):
    """One camera's view of a frame shifted 30 px drags the frame's pose until the other camera's view of it is
    beyond 5 sigma too: the frame is left out (said so), the covariances still come out, no traceback."""
    ds = tmp_path / "ds"
    shutil.copytree(ROOT / "datasets" / "binocular", ds)
    data = json.loads((ds / "observations.json").read_text())
    shifted = next(o for o in data["observations"] if o["camera"] == "cam0" and o.get("frame") == "f014")
    shifted["pixels"] = [[u + 30.0, v] for u, v in shifted["pixels"]]
    (ds / "observations.json").write_text(json.dumps(data))
    r = _run(["calibrate", ds, "-o", tmp_path / "out", "--exclude-outliers"])
    assert r.exit_code == 0, r.output
    cal = load_calibration(tmp_path / "out" / "calibration.json")
    assert "f014" not in cal.frames and cal.quality.ok
    assert cal.residuals.rmse_px < 0.08 and cal.uncertainty is not None
    assert all(s.rotation_deg is not None and np.isfinite(s.rotation_deg)
               for s in cal.uncertainty.cameras.values() if s.relative_pose)


def test_run_reads_the_simulators_own_truth(tmp_path):
    assert _run(["simulate", "body3d_water", "-o", tmp_path / "sim"]).exit_code == 0
    r = _run(["run", tmp_path / "sim" / "dataset", "-o", tmp_path / "out", "--truth", tmp_path / "sim" / "truth.json"])
    assert r.exit_code == 0, r.output
    assert "vs truth" in r.output and "error" not in r.output.lower().replace("errors", "")


def test_stages_give_no_window_distance_in_air(tmp_path):
    """In air the window distance is not observable: calibration.json says null, and so do its stages."""
    r = _run(["calibrate", ROOT / "datasets" / "binocular", "-o", tmp_path / "out"])
    assert r.exit_code == 0, r.output
    data = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert data["interface"]["distance_mm"] is None
    assert data["stages"] and all(st["distance_mm"] is None for st in data["stages"])


# ----------------------------------------------------------------------------- sfm --baseline: the scale held

def _rigid_rms(a: np.ndarray, b: np.ndarray) -> float:
    """RMS of b - (R a + t) after the best rotation and translation (no scale)."""
    a0, b0 = a - a.mean(0), b - b.mean(0)
    U, _, Vt = np.linalg.svd(b0.T @ a0)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    moved = a0 @ (U @ D @ Vt).T
    return float(np.sqrt(np.mean(np.sum((moved - b0) ** 2, axis=1))))


def _similarity(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """RMS of b - (s R a + t) after the best similarity, and its scale s."""
    a0, b0 = a - a.mean(0), b - b.mean(0)
    U, S, Vt = np.linalg.svd(b0.T @ a0)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    s = float(np.sum(S * np.diag(D)) / np.sum(a0 ** 2))
    return float(np.sqrt(np.mean(np.sum((s * a0 @ (U @ D @ Vt).T - b0) ** 2, axis=1)))), s


@pytest.fixture(scope="module")
def small_survey():
    """A camera in a flat-port housing over a relief (6 images), COLMAP's pinhole optimum of it."""
    from ari_sfm.colmap import adapter
    from ari_sfm.simulate.port_survey import port_survey

    truth = port_survey(num_images=6, num_points=300, focal_px=1300, area_mm=(1200, 800), sigma_px=0.3)
    params = [np.r_[p[:2] * truth.interface.medium_index, p[2:4]] for p in truth.params]
    rec = adapter.reconstruction_from_arrays(params, truth.image_size, truth.sensor_from_rig, truth.rig_from_world,
                                             truth.image_camera, truth.image_frame, truth.xyz, truth.obs_image,
                                             truth.obs_point, truth.obs_uv)
    return truth, adapter.bundle_adjust(rec)


def _true_centres(truth, model) -> np.ndarray:
    return np.array([-(truth.rig_from_world[truth.image_frame[i - 1]].R.T
                       @ truth.rig_from_world[truth.image_frame[i - 1]].t)
                     for i in model.image_ids])


def test_baseline_is_held_by_the_refinement_and_the_centres_need_no_rescaling(small_survey):
    """--baseline (two images' camera centres, e.g. from navigation) is a term of the solver: the refined
    centres keep the given distance (1e-3) and match the true ones after a rigid motion, without a scale."""
    from ari_sfm.colmap import adapter
    from ari_sfm.colmap.refine import refine_colmap

    truth, start = small_survey
    model = adapter.model_from_reconstruction(start)
    C_true = _true_centres(truth, model)
    a, b = 0, len(model.image_ids) - 1
    mm = float(np.linalg.norm(C_true[a] - C_true[b]))
    result = refine_colmap(start, truth.interface, "camera",
                           baseline=(model.image_names[a], model.image_names[b], mm))
    r = result.report
    assert r.baseline.refined_mm == pytest.approx(mm, rel=1e-3) and r.baseline.declared_mm == mm
    R, t = result.state.cam_from_world(model)
    C = -np.einsum("nji,nj->ni", R, t)
    assert np.linalg.norm(C[a] - C[b]) == pytest.approx(mm, rel=1e-3)
    # the shape's noise: the centres' RMS after the best similarity (1.0 mm here); without rescaling the
    # error stays within it (before: the refinement ran the scale 15 % off the baseline, 74 mm RMS)
    shape_rms, scale = _similarity(C, C_true)
    assert abs(scale - 1.0) < 5e-3
    assert _rigid_rms(C, C_true) < 1.5 * shape_rms
    assert r.to_json()["baseline"]["images"] == [model.image_names[a], model.image_names[b]]


def test_baseline_jacobian_matches_central_differences(small_survey):
    from ari_sfm.colmap import adapter
    from ari_sfm.colmap.refine.problem import RefractiveProblem
    from ari_sfm.colmap.refine.refine import _baseline, _initial_state, _with_distance

    truth, start = small_survey
    model = adapter.model_from_reconstruction(start)
    problem = RefractiveProblem(model, truth.interface, "camera", estimate_distance=True)
    state = _with_distance(model, _initial_state(model, "camera", 1.0), "camera", 20.0)
    base = _baseline(model, (model.image_names[1], model.image_names[4], 1000.0), "x")
    cols, J = base.jacobian(state, problem.layout)
    rng = np.random.default_rng(0)
    for _ in range(3):
        dg = rng.normal(0.0, 1e-6, problem.layout.size)
        dp = np.zeros_like(state.xyz)
        numeric = (base.error(problem.retract(state, dg, dp)) - base.error(problem.retract(state, -dg, -dp))) / 2
        assert numeric == pytest.approx(J @ dg[cols], rel=1e-6)


@pytest.mark.parametrize("baseline, words", [
    (("nope.png", 0, 100.0), ["nope.png", "not among"]),
    ((0, 0, 100.0), ["twice"]),
    ((0, 1, -5.0), ["positive"]),
])
def test_bad_baseline_one_error(small_survey, baseline, words):
    from ari_sfm.colmap import adapter
    from ari_sfm.colmap.refine import refine_colmap
    from ari_sfm.errors import AriSfmError

    truth, start = small_survey
    model = adapter.model_from_reconstruction(start)
    names = [b if isinstance(b, str) or isinstance(b, float) else model.image_names[b] for b in baseline[:2]]
    with pytest.raises(AriSfmError) as err:
        refine_colmap(start, truth.interface, "camera", baseline=(*names, baseline[2]))
    assert all(w in str(err.value) for w in words), str(err.value)


# ----------------------------------------------------------------------------- export/import-colmap-fork

def _one_error(r, *words) -> str:
    """The result is one `error: ...` line holding ``words``, exit 1, no traceback."""
    assert r.exit_code == 1, r.output
    lines = [ln.split("\r")[-1] for ln in r.output.split("\n")]  # a progress bar redraws its line after \r
    lines = [ln for ln in lines if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]


def _run_folder(tmp_path: Path) -> Path:
    """An `ari-sfm run` folder of the bundled binocular rig: calibration.json and run.json naming the dataset."""
    out = tmp_path / "bino"
    out.mkdir()
    shutil.copy(ROOT / "tests" / "data" / "calibration_e6e8196" / "exact.json", out / "calibration.json")
    run = {"format": "ari-sfm-run/1", "dataset": str(ROOT / "datasets" / "binocular"),
           "calibration": "calibration.json"}
    (out / "run.json").write_text(json.dumps(run))
    return out


def test_fork_export_of_a_run_folder_takes_the_runs_corners(tmp_path):
    """README's `export-colmap-fork out/bino/calibration.json -o fork_model`: the dataset run.json names gives the
    target corners (was: 2 images and 0 points3D, no warning); the fork model reads back."""
    out = _run_folder(tmp_path)
    r = _run(["export-colmap-fork", out / "calibration.json", "-o", tmp_path / "fork"])
    assert r.exit_code == 0, r.output
    data = json.loads((ROOT / "datasets" / "binocular" / "observations.json").read_text())
    frames = {o["frame"] for o in data["observations"] if o.get("set", "calibration") == "calibration"}
    images = [ln for ln in (tmp_path / "fork" / "images.txt").read_text().splitlines()[4::2]]
    assert len(images) >= 2 * len(frames) - 2 and "points3D" in r.output
    assert int(r.output.split(" points3D")[0].split()[-1]) == 88 * len(frames)  # every frame's 11 x 8 corners
    assert _run(["import-colmap-fork", tmp_path / "fork", "-o", tmp_path / "back"]).exit_code == 0


def test_fork_export_without_corners_says_so(tmp_path, caplog):
    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy(ROOT / "tests" / "data" / "calibration_e6e8196" / "exact.json", lone / "calibration.json")
    with caplog.at_level("WARNING"):
        r = _run(["export-colmap-fork", lone / "calibration.json", "-o", tmp_path / "fork"])
    assert r.exit_code == 0 and "0 points3D" in r.output
    assert any("cameras and poses only" in rec.getMessage() for rec in caplog.records)


def test_fork_export_refuses_another_rigs_dataset(tmp_path):
    other = tmp_path / "other"
    shutil.copytree(ROOT / "datasets" / "binocular", other)
    rig = other / "rig.yaml"
    rig.write_text(rig.read_text().replace("thickness_mm: 50.0", "thickness_mm: 12.0"))
    out = _run_folder(tmp_path)
    r = _run(["export-colmap-fork", out / "calibration.json", "-o", tmp_path / "fork", "--dataset", other])
    _one_error(r, "calibration.json", "another rig", "thickness_mm")
    assert not (tmp_path / "fork").exists()


@pytest.mark.parametrize("command", ["export", "import"])
@pytest.mark.parametrize("units", ["1e-300", "1e300", "0", "-5", "nan"])
def test_fork_units_bounded(tmp_path, command, units):
    out = _run_folder(tmp_path)
    if command == "export":
        r = _run(["export-colmap-fork", out / "calibration.json", "-o", tmp_path / "fork", "--units-mm", units])
    else:
        assert _run(["export-colmap-fork", out / "calibration.json", "-o", tmp_path / "m"]).exit_code == 0
        r = _run(["import-colmap-fork", tmp_path / "m", "-o", tmp_path / "fork", "--units-mm", units])
    _one_error(r, "--units-mm", "between")
    assert not (tmp_path / "fork").exists()


def test_fork_import_refuses_lengths_calibration_json_would_refuse(tmp_path):
    """A plate of 80 m (int_thick 80 in metres): the import writes nothing that calibration.json's reader refuses."""
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "cameras.txt").write_text(
        "1 PINHOLE 640 480 500 500 320 240 FLATPORT 0 0 1 0.02 80 1 1.5 1.33\n")
    r = _run(["import-colmap-fork", tmp_path / "m", "-o", tmp_path / "out"])
    _one_error(r, "cameras.txt", "thickness_mm", "--units-mm 1000")
    assert not (tmp_path / "out").exists()


def test_flipped_normal_refused_when_read_so_the_fork_never_gets_nz_below_0(tmp_path):
    """A calibration.json whose window normal points away from the cameras: every corner projected to NaN
    (evaluate printed 'rmse nan px') and the fork's FLATPORT got Nz < 0 that import refuses. Now the reading
    refuses it, naming the key; the export's writer refuses Nz <= 0 as the import does."""
    from ari_sfm.colmap.fork import format_camera_line
    from ari_sfm.errors import AriSfmError
    from ari_sfm.records import Interface

    data = json.loads((ROOT / "tests" / "data" / "calibration_e6e8196" / "exact.json").read_text())
    data["interface"]["normal_world"] = [-x for x in data["interface"]["normal_world"]]
    (tmp_path / "flip.json").write_text(json.dumps(data))
    for args in (["export-colmap-fork", tmp_path / "flip.json", "-o", tmp_path / "fork"],
                 ["evaluate", tmp_path / "flip.json", ROOT / "datasets" / "binocular" / "observations.json"]):
        _one_error(_run(args), "flip.json", "interface.normal_world", "points away")
    assert not (tmp_path / "fork").exists()
    with pytest.raises(AriSfmError, match="Nz <= 0"):
        format_camera_line(1, (640, 480), [500, 500, 320, 240], np.array([0.0, 0.1, -1.0]), 20.0,
                           Interface(8.0, 1.5, 1.33), 1000.0)


# ----------------------------------------------------------------------------- compare --holdout

def _split_binocular(tmp_path: Path) -> tuple[Path, Path]:
    """The bundled rig with its last 4 calibration frames moved out into a held-out observations file."""
    ds = tmp_path / "ds"
    shutil.copytree(ROOT / "datasets" / "binocular", ds)
    data = json.loads((ds / "observations.json").read_text())
    frames = sorted({o["frame"] for o in data["observations"] if o.get("set") == "calibration"})[-4:]
    held = [o for o in data["observations"] if o.get("set") == "calibration" and o["frame"] in frames]
    data["observations"] = [o for o in data["observations"] if o not in held]
    (ds / "observations.json").write_text(json.dumps(data))
    rig = ds / "rig.yaml"
    rig.write_text("".join(ln for ln in rig.read_text().splitlines(keepends=True)
                           if not any(f"frame: {f}}}" in ln for f in frames)))
    (tmp_path / "held.json").write_text(json.dumps({"format": "ari-sfm-observations/1", "observations": held}))
    return ds, tmp_path / "held.json"


def test_compare_holdout_of_this_rig_is_scored_and_another_rigs_refused(tmp_path):
    ds, held = _split_binocular(tmp_path)
    r = _run(["compare", ds, "-o", tmp_path / "cmp", "--models", "ari", "--holdout", held])
    assert r.exit_code == 0, r.output
    scored = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    row = scored["models"]["ari"]
    assert 0.0 < row["holdout"]["rmse_px"] < 1.0  # ari on this rig: ~0.35 px
    # another rig: the same cameras, target and image sizes, the second camera 30 mm further right
    other = json.loads(held.read_text())
    for o in other["observations"]:
        if o["camera"] == "cam1":
            o["pixels"] = [[u - 3478.3 * 30.0 / 500.0, v] for u, v in o["pixels"]]
    (tmp_path / "other.json").write_text(json.dumps(other))
    r = _run(["compare", ds, "-o", tmp_path / "cmp2", "--models", "ari", "--holdout", tmp_path / "other.json"])
    _one_error(r, "other.json", "not views of this rig")
    assert not (tmp_path / "cmp2").exists()


# ----------------------------------------------------------------------------- detect -> calibrate, evaluate

def test_detect_output_is_a_dataset_that_calibrate_takes_without_detecting_again(tmp_path):
    """README: `ari-sfm detect DATASET -o det` then `ari-sfm calibrate det -o cal` (was: no rig.yaml in det)."""
    sample = ROOT / "datasets" / "sample"
    r = _run(["detect", sample, "-o", tmp_path / "det", "--workers", "2"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "det" / "rig.yaml").is_file() and (tmp_path / "det" / "observations.json").is_file()
    r = _run(["calibrate", tmp_path / "det", "-o", tmp_path / "cal", "--model", "ari"])
    assert r.exit_code == 0, r.output
    assert "observations:" not in r.output  # the corners were read, not detected again
    assert not (tmp_path / "cal" / "observations.json").exists()
    cal = load_calibration(tmp_path / "cal" / "calibration.json")
    assert cal.residuals.rmse_px < 0.5 and cal.residuals.count == sum(
        len(o["ids"]) for o in json.loads((tmp_path / "det" / "observations.json").read_text())["observations"])
    # again into the same folder: its own earlier output is replaced; another dataset's rig.yaml never is
    assert _run(["detect", sample, "-o", tmp_path / "det", "--workers", "2"]).exit_code == 0
    other = tmp_path / "other"
    shutil.copytree(ROOT / "datasets" / "binocular", other)
    before = (other / "rig.yaml").read_text()
    _one_error(_run(["detect", sample, "-o", other, "--workers", "2"]), "rig.yaml", "another dataset")
    assert (other / "rig.yaml").read_text() == before


def test_evaluate_solve_poses_is_one_behaviour_in_the_cli_and_the_api(tmp_path):
    from ari_sfm import evaluate

    cal_path = ROOT / "tests" / "data" / "calibration_e6e8196" / "exact.json"
    obs = ROOT / "datasets" / "binocular" / "observations.json"
    r = _run(["evaluate", cal_path, obs, "--solve-poses"])
    assert r.exit_code == 0, r.output
    cli_count = int(r.output.split("(")[-1].split()[0])
    api = evaluate(load_calibration(cal_path), obs, solve_poses=True)
    assert api.count == cli_count and f"{api.rmse_px:.4f}" in r.output
    data = json.loads(obs.read_text())["observations"]
    assert cli_count == sum(len(o["ids"]) for o in data if o.get("set") != "stacking")  # held-out views: no stacking


def test_evaluate_never_prints_nan(tmp_path):
    """A frame 1e300 mm away printed 'rmse nan px' (exit 0): refused when read; a frame whose corners project to
    no pixel, and a dataset without observations (the API returned NaN statistics): one error each."""
    from dataclasses import replace

    from ari_sfm import evaluate
    from ari_sfm.errors import AriSfmError
    from ari_sfm.geometry import Pose
    from ari_sfm.io import load_dataset

    src = ROOT / "tests" / "data" / "calibration_e6e8196" / "exact.json"
    obs = ROOT / "datasets" / "binocular" / "observations.json"
    data = json.loads(src.read_text())
    frame = next(iter(data["frames"]))
    data["frames"][frame]["world_from_target"]["t"] = [0.0, 0.0, 1e300]
    (tmp_path / "far.json").write_text(json.dumps(data))
    _one_error(_run(["evaluate", tmp_path / "far.json", obs]), "far.json", f"frames.{frame}.t", "beyond")
    cal = load_calibration(src)
    behind = replace(cal, frames={**cal.frames, frame: Pose(np.eye(3), np.array([0.0, 0.0, -500.0]))})
    with pytest.raises(AriSfmError, match="project to no pixel"):
        evaluate(behind, obs)
    images_only = tmp_path / "sample"
    shutil.copytree(ROOT / "datasets" / "sample", images_only)
    with pytest.raises(AriSfmError, match="no observations"):
        evaluate(cal, load_dataset(images_only))
    with pytest.raises(AriSfmError, match="no corner to judge"):
        evaluate(cal, [])


# ----------------------------------------------------------------------------- sfm: inputs, COLMAP's failures, -o

WINDOW = "interface: {thickness_mm: 8, index: 1.49, medium_index: 1.333}\nmount: camera\n"


def _noise_images(folder: Path, names: list[str], size=(64, 48)) -> Path:
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for n in names:
        cv2.imwrite(str(folder / n), rng.integers(0, 255, (size[1], size[0]), dtype=np.uint8))
    return folder


def _sfm(tmp_path: Path, images: Path, *extra, out=None):
    (tmp_path / "W.yaml").write_text(WINDOW + "units_mm: 1\n")
    return _run(["sfm", images, "--window", tmp_path / "W.yaml", "-o", out or tmp_path / "o", "--threads", "1", *extra])


@pytest.mark.parametrize("bad, words", [
    ("text", ["text.png", "cannot be read as an image"]),
    ("empty", ["empty.png", "cannot be read"]),
    ("truncated", ["truncated.png", "cannot be read"]),
    ("resized", ["resized.png", "32 x 24 px", "one camera"]),
])
def test_sfm_names_the_images_it_would_drop(tmp_path, bad, words):
    """Ten text files named .png gave an AttributeError; resized, truncated and 0-byte images were dropped by
    COLMAP silently ('9 of 10 registered'): one line naming the image, before any COLMAP work."""
    images = _noise_images(tmp_path / "imgs", [f"i{k}.png" for k in range(4)])
    if bad == "text":
        (images / "text.png").write_text("not an image\n")
    elif bad == "empty":
        (images / "empty.png").write_bytes(b"")
    elif bad == "truncated":
        (images / "truncated.png").write_bytes((images / "i0.png").read_bytes()[:200])
    else:
        _noise_images(images, ["resized.png"], size=(32, 24))
    _one_error(_sfm(tmp_path, images), *words)
    assert not (tmp_path / "o").exists()


def test_sfm_ten_text_files_one_line(tmp_path):
    images = tmp_path / "imgs"
    images.mkdir()
    for k in range(10):
        (images / f"t{k}.png").write_text("text\n")
    _one_error(_sfm(tmp_path, images), "t0.png", "cannot be read", "and 9 more")


@pytest.mark.parametrize("extra, words", [
    (["--threads", "-5"], ["--threads", "-1 (all cores)"]),
    (["--threads", "0"], ["--threads"]),
    (["--focal-px", "1e9"], ["--focal-px", "not a focal length", "64 x 48"]),
])
def test_sfm_options_checked_before_colmap(tmp_path, extra, words):
    images = _noise_images(tmp_path / "imgs", [f"i{k}.png" for k in range(4)])
    (tmp_path / "W.yaml").write_text(WINDOW + "units_mm: 1\n")
    r = _run(["sfm", images, "--window", tmp_path / "W.yaml", "-o", tmp_path / "o", *extra])
    _one_error(r, *words)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", ["colmap.partial", "colmap", "refined"])
def test_sfm_a_file_where_it_writes_a_folder(tmp_path, name):
    images = _noise_images(tmp_path / "imgs", [f"i{k}.png" for k in range(4)])
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / name).write_text("mine\n")
    _one_error(_sfm(tmp_path, images), name, "is a file")
    assert (tmp_path / "o" / name).read_text() == "mine\n"


@pytest.mark.parametrize("stderr, words", [
    ("F20261127 10:00:00.000000 1 database.cc:12] Check failed: database or disk is full", ["no space left"]),
    ("F20261127 10:00:00.000000 1 feature.cc:99] Check failed: num_threads >= -1", ["COLMAP stopped",
                                                                                    "num_threads >= -1"]),
])
def test_sfm_colmap_native_abort_is_one_line_and_leaves_nothing(tmp_path, monkeypatch, stderr, words):
    """COLMAP aborting natively (a glog CHECK on a full disk) printed a 25-line stack and left colmap.partial/
    database.db, -wal, -shm: COLMAP runs in a child process now; its abort is one line, nothing is left."""
    from ari_sfm.colmap import sfm

    code = ("import json, os, sys; a = json.loads(sys.argv[1]); os.makedirs(a['work'], exist_ok=True); "
            "[open(os.path.join(a['work'], 'database.db' + x), 'w').close() for x in ('', '-wal', '-shm')]; "
            f"print('step features', flush=True); sys.stderr.write({stderr!r} + '\\n'); "
            "sys.stderr.write('*** Check failure stack trace: ***\\n' * 20); sys.stderr.flush(); os.abort()")
    monkeypatch.setattr(sfm, "CHILD_CODE", code)
    images = _noise_images(tmp_path / "imgs", [f"i{k}.png" for k in range(4)])
    line = _one_error(_sfm(tmp_path, images), *words)
    assert "stack trace" not in line
    assert not (tmp_path / "o").exists()  # created by this run, removed with colmap.partial and its database


def test_sfm_second_run_into_the_same_out_is_refused(tmp_path):
    """Two sfm runs into one -o both failed and -o was removed: the second is refused, the first's folder kept."""
    from ari_sfm.io import exclusive_folder

    images = _noise_images(tmp_path / "imgs", [f"i{k}.png" for k in range(4)])
    with exclusive_folder(tmp_path / "o"):  # the first run, holding -o
        (tmp_path / "o" / "sfm.json").write_text("{}")
        _one_error(_sfm(tmp_path, images), "another ari-sfm command is writing into this folder")
        assert (tmp_path / "o" / "sfm.json").exists()


def test_sfm_baseline_held_and_unregistered_images_named(tmp_path, monkeypatch, small_survey):
    """`sfm --baseline` end to end with COLMAP's model given (a child that writes the simulated survey's pinhole
    optimum): sfm.json's baseline is refined to the given distance (was 18 % off); an image COLMAP did not
    register is named in the summary and sfm.json."""
    from ari_sfm.colmap import adapter, sfm

    truth, start = small_survey
    model = adapter.model_from_reconstruction(start)
    (tmp_path / "model").mkdir()
    start.write(str(tmp_path / "model"))
    code = ("import json, shutil, sys; a = json.loads(sys.argv[1]); "
            f"shutil.copytree({str(tmp_path / 'model')!r}, a['work'] + '/sparse/0')")
    monkeypatch.setattr(sfm, "CHILD_CODE", code)
    images = _noise_images(tmp_path / "imgs", [*model.image_names, "zzz_lost.png"], size=tuple(truth.image_size))
    C = _true_centres(truth, model)
    mm = float(np.linalg.norm(C[0] - C[-1]))
    (tmp_path / "W.yaml").write_text(
        f"interface: {{thickness_mm: {truth.interface.thickness_mm}, index: {truth.interface.index}, "
        f"medium_index: {truth.interface.medium_index}}}\nmount: camera\n")
    r = _run(["sfm", images, "--window", tmp_path / "W.yaml", "-o", tmp_path / "o", "--threads", "1",
              "--baseline", model.image_names[0], model.image_names[-1], str(mm)])
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "o" / "sfm.json").read_text())
    assert summary["scale"] == "baseline" and summary["baseline"]["refined_mm"] == pytest.approx(mm, rel=1e-3)
    assert summary["unregistered"] == ["zzz_lost.png"] and "not registered: zzz_lost.png" in r.output
    refine = json.loads((tmp_path / "o" / "refined" / "refine.json").read_text())
    assert refine["baseline"]["refined_mm"] == pytest.approx(mm, rel=1e-3)
    assert not (tmp_path / "o" / "colmap.partial").exists() and (tmp_path / "o" / summary["colmap_model"]).is_dir()


# ----------------------------------------------------------------------------- run: one run per -o at a time

def test_run_into_a_folder_another_command_is_writing_is_refused(tmp_path):
    """Two runs into one -o at once left run.json of one and the results of the other: the second is refused."""
    from ari_sfm.io import exclusive_folder

    with exclusive_folder(tmp_path / "o"):
        r = _run(["run", ROOT / "datasets" / "binocular", "-o", tmp_path / "o"])
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code == 1 and len(lines) == 2 and lines[0].startswith("ari-sfm run: "), r.output
    assert lines[1].startswith("error: ") and "another ari-sfm command is writing into this folder" in lines[1]
    assert list((tmp_path / "o").iterdir()) == []


def test_a_run_that_fails_leaves_no_run_json_of_the_earlier_run(tmp_path, monkeypatch):
    """An earlier run's run.json and report are removed before this run writes: a failure half-way leaves this
    run's calibration without a run.json describing the earlier run's results."""
    from ari_sfm.pipelines import run as run_pipeline

    ds = tmp_path / "ds"
    shutil.copytree(ROOT / "datasets" / "binocular", ds)
    out = tmp_path / "o"
    out.mkdir()
    (out / "run.json").write_text(json.dumps({"format": "ari-sfm-run/1", "dataset": str(ds.resolve()),
                                              "model": "ari", "calibration": "calibration.json"}))
    (out / "report.html").write_text("<html>earlier</html>")

    def fails(*args, **kwargs):
        raise RuntimeError("disk gone")

    monkeypatch.setattr(run_pipeline, "run_reconstruction", fails)
    r = _run(["run", ds, "-o", out, "--model", "ari"])
    assert r.exit_code == 1 and "disk gone" in r.output
    assert (out / "calibration.json").is_file()
    assert not (out / "run.json").exists() and not (out / "report.html").exists()


# ----------------------------------------------------------------------------- clear errors (one line, a file named)

CAL = ROOT / "tests" / "data" / "calibration_e6e8196" / "exact.json"
OBS = ROOT / "datasets" / "binocular" / "observations.json"


def _edited_calibration(tmp_path: Path, name: str, edit) -> Path:
    data = json.loads(CAL.read_text())
    edit(data)
    (tmp_path / name).write_text(json.dumps(data))
    return tmp_path / name


def test_observations_at_dev_zero_one_line():
    """/dev/zero was read until a MemoryError."""
    _one_error(_run(["evaluate", CAL, "/dev/zero"]), "/dev/zero", "not a regular file")
    _one_error(_run(["evaluate", "/dev/zero", OBS]), "/dev/zero", "not a regular file")
    _one_error(_run(["calibrate", "/dev/zero", "-o", "/tmp/never-written"]), "/dev/zero", "not a dataset folder")


def test_calibration_without_target_named_by_evaluate(tmp_path):
    cal = _edited_calibration(tmp_path, "notarget.json", lambda d: d.pop("target"))
    _one_error(_run(["evaluate", cal, OBS]), "notarget.json", "holds no target")


def test_fixed_distance_behind_the_cameras_refused_when_read(tmp_path):
    """fixed_distance_mm -50 ended in 'ValueError: distance_mm must be > 0' from deep inside."""
    cal = _edited_calibration(tmp_path, "fixed.json", lambda d: d.update(fixed_distance_mm=-50.0))
    _one_error(_run(["evaluate", cal, OBS]), "fixed.json", "fixed_distance_mm -50", "in front of it")


def test_stdout_full_is_one_line_naming_it():
    """`evaluate ... > /dev/full` printed 'error: OSError: [Errno 28] ...' naming nothing."""
    import subprocess
    import sys

    exe = Path(sys.executable).parent / "ari-sfm"
    with open("/dev/full", "w") as full:
        p = subprocess.run([str(exe), "evaluate", str(CAL), str(OBS)], stdout=full, stderr=subprocess.PIPE,
                           text=True, timeout=300)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 1 and lines == ["error: standard output: cannot write: No space left on device"], p.stderr


@pytest.mark.parametrize("command", ["particles", "self-calibrate"])
def test_depth_range_bounded(tmp_path, command):
    r = _run([command, tmp_path, "--calibration", CAL, "-o", tmp_path / "o", "--depth-range", "-1e300", "1e300"])
    _one_error(r, "--depth-range", "-100000")


def test_pixels_far_outside_the_image_refused_by_evaluate_and_refine_colmap(tmp_path, small_survey):
    from dataclasses import replace

    from ari_sfm import evaluate
    from ari_sfm.colmap import adapter
    from ari_sfm.colmap.refine.refine import _check_finite
    from ari_sfm.errors import AriSfmError
    from ari_sfm.io import load_observations

    cal = load_calibration(CAL)
    records = list(load_observations(OBS, cal.target, list(cal.cameras)))
    records[3] = replace(records[3], pixels=records[3].pixels + [5000.0, 0.0])
    with pytest.raises(AriSfmError, match="outside the 2448 x 2048 image"):
        evaluate(cal, records)
    _, start = small_survey
    model = adapter.model_from_reconstruction(start)
    uv = model.obs_uv.copy()
    uv[7] += 5000.0
    with pytest.raises(AriSfmError, match="outside its"):
        _check_finite(replace(model, obs_uv=uv), "sparse")


def test_api_misuse_says_what_is_wanted():
    """RigGraph / evaluate given wrong types raised AttributeError, add_factor gtsam's TypeError listing every
    overload; CalibrationOptions(max_iterations=-3) was accepted."""
    import ari_sfm
    from ari_sfm import CalibrationOptions, evaluate
    from ari_sfm.factors.rig_graph import RigGraph

    with pytest.raises(TypeError, match="Dataset or a dataset folder"):
        RigGraph.from_dataset(42)
    with pytest.raises(TypeError, match="calibrate needs a Dataset or a dataset folder's path"):
        ari_sfm.calibrate(42)
    with pytest.raises(ValueError, match="sigma_px"):
        RigGraph.from_dataset(ROOT / "datasets" / "binocular", sigma_px=-1.0)
    with pytest.raises(TypeError, match="Calibration or a calibration.json path"):
        evaluate(42, OBS)
    assert evaluate(str(CAL), OBS).count > 0  # a path is read
    for bad in (42, {"observations": []}, [1, 2]):  # was: 'int' object is not iterable, ...
        with pytest.raises(TypeError, match="observations.json path, a Dataset or a list of Observation"):
            evaluate(CAL, bad)
        with pytest.raises(TypeError, match="observations.json path, a Dataset or a list of Observation"):
            evaluate(CAL, bad, solve_poses=True)
    for bad in (-3, 0, 2.5, True):
        with pytest.raises(ValueError, match="max_iterations"):
            CalibrationOptions(max_iterations=bad)
    assert CalibrationOptions(max_iterations=np.int64(7)).max_iterations == 7


def test_rig_graph_add_factor_and_optimize_checked():
    import gtsam

    from ari_sfm.factors.rig_graph import RigGraph

    rg = RigGraph.from_dataset(ROOT / "datasets" / "binocular", sigma_px=1.0)
    with pytest.raises(TypeError, match="gtsam.NonlinearFactor"):
        rg.add_factor("not a factor")
    with pytest.raises(ValueError, match="max_iterations"):
        rg.optimize(max_iterations=-3)
    rg.add_factor(gtsam.PriorFactorPoint3(gtsam.symbol("z", 0), gtsam.Point3(0, 0, 0), gtsam.noiseModel.Unit.Create(3)))


# ----------------------------------------------------------------------------- a calibration that failed its gate


def test_a_calibration_that_failed_its_gate_is_said_so_by_particles_and_self_calibrate(tmp_path, caplog):
    """The simulated 4-camera PTV rig (10 mm glass into water, three views of its 3D body) with lenses of k1
    -0.05: the default calibration estimates the lens (the first start fails the gate) and ends within 0.1 deg
    (was: 'quality: ok' at 1.8 x the floor, 0.24-0.82 deg off). With --no-distortion the gate fails it (exit 3,
    ~0.5 deg off); particles and self-calibrate from it (self-calibration then fits the particles at the noise,
    particles says that this calibration failed its gate (particles3d.json records it); self-calibrate's own
    check on its start fails it (exit 3)."""
    from ari_sfm.calibration.truth_errors import calibration_errors

    sim, cal = tmp_path / "sim", tmp_path / "cal"
    assert _run(["simulate", "particles", "-o", sim, "--particles", "300", "--frames", "2", "--k1", "-0.05",
                 "--render-frames", "0"]).exit_code == 0
    r = _run(["calibrate", sim / "calibration", "-o", tmp_path / "default"])
    assert r.exit_code == 0 and "quality: ok" in r.output, r.output
    good = load_calibration(tmp_path / "default" / "calibration.json")
    assert good.quality.starts[-1] == "lens distortion estimated" and abs(good.cameras["cam0"].dist[0] + 0.05) < 0.01
    errors = calibration_errors(good, load_calibration(sim / "truth" / "rig_a.json"))
    assert max(c.rotation_deg for c in errors.cameras if c.rotation_deg is not None) < 0.1
    assert _run(["calibrate", sim / "calibration", "-o", cal, "--no-distortion"]).exit_code == 3
    failed = str(cal / "calibration.json")
    with caplog.at_level("WARNING"):
        r = _run(["particles", sim / "experiment", "--calibration", failed, "-o", tmp_path / "p", "--workers", "0"])
    assert r.exit_code == 0, r.output
    said = [m for m in caplog.messages if m.startswith(f"{failed}: this calibration failed its quality gate")]
    assert len(said) == 1 and "cannot be trusted" in said[0] and "lens distortion" in said[0]
    assert json.loads((tmp_path / "p" / "particles3d.json").read_text())["warnings"][0] == said[0]
    caplog.clear()
    with caplog.at_level("WARNING"):
        r = _run(["self-calibrate", sim / "experiment", "--calibration", failed, "-o", tmp_path / "sc", "--workers",
                  "0", "--cells", 2, 2, 1])
    assert said[0] in caplog.messages
    assert r.exit_code == 3 and "FAILED" in r.output, r.output  # its own check on the start: written, not trusted
    checks = json.loads((tmp_path / "sc" / "calibration.json").read_text())["self_calibration"]["checks"]
    assert [c["passed"] for c in checks if c["name"] == "start_quality"] == [False]
    caplog.clear()
    with caplog.at_level("WARNING"):  # a calibration that passed: not said
        r = _run(["particles", sim / "experiment", "--calibration", sim / "truth" / "rig_b.json", "-o",
                  tmp_path / "p2", "--workers", "0"])
    assert r.exit_code == 0 and not [m for m in caplog.messages if "quality gate" in m]


# ----------------------------------------------------------------------------- self-calibration's report


def test_disparity_maps_before_and_after_share_one_arrow_scale(monkeypatch):
    """The report's disparity maps drew the corrected arrows at another scale than the drifted ones ('1 px =
    1.2 mm' against '1 px = 8.5e+02 mm'), so they looked as large: one scale (mm per px) for every panel, the
    longest arrow (before) about half a cell, and each panel's title says the same scale."""
    import re

    from matplotlib.quiver import Quiver

    import ari_sfm.report.figures as rf
    from ari_sfm.particles.figures import disparity_figure

    cells = {"lower_mm": [-30.0, -20.0, 400.0], "upper_mm": [30.0, 20.0, 420.0], "shape": [2, 2, 1]}
    centres = [[-15.0, -10.0, 410.0], [15.0, -10.0, 410.0], [-15.0, 10.0, 410.0], [15.0, 10.0, 410.0]]
    rng = np.random.default_rng(0)
    vectors = {"before": rng.normal(0.0, 3.0, (2, 4, 2)), "after": rng.normal(0.0, 0.05, (2, 4, 2))}
    disparity = {"cells": cells, "cell_centres_mm": centres}
    for when, v in vectors.items():
        disparity[when] = {"cameras": {f"cam{c}": {"rms_px": float(np.sqrt(np.mean(np.sum(v[c] ** 2, axis=1)))),
                                                   "vector_px": v[c].tolist()} for c in range(2)}}
    figures = []
    monkeypatch.setattr(rf, "to_png", lambda fig: figures.append(fig) or b"")
    disparity_figure(disparity)
    axes = [ax for ax in figures[0].axes if ax.get_title()]
    assert len(axes) == 4
    scales, titles = [], set()
    for ax in axes:
        cam, when = ax.get_title().split(":")[0].split()
        drawn = np.concatenate([np.c_[q.U, q.V] for q in ax.collections if isinstance(q, Quiver)])
        scales.append(np.linalg.norm(drawn, axis=1) / np.linalg.norm(vectors[when][int(cam[3:])], axis=1))
        titles.add(re.search(r"1 px = ([^ ]+) mm", ax.get_title()).group(1))
    scales = np.concatenate(scales)
    assert np.allclose(scales, scales[0], rtol=1e-9) and len(titles) == 1
    longest = max(np.linalg.norm(v, axis=2).max() for v in vectors.values())
    assert scales[0] * longest == pytest.approx(0.45 * 20.0)  # about half the smaller cell side (40 mm / 2)
    assert float(titles.pop()) == pytest.approx(scales[0], rel=0.05)  # printed with 2 digits


def test_a_self_calibration_round_stopped_at_its_iteration_cap_says_so(caplog):
    """A round's bundle adjustment ended at its iteration cap without a word: a warning naming the cap, the
    round's stop recorded as max_iterations (in calibration.json's self_calibration.rounds)."""
    from ari_sfm.particles.selfcal import SelfCalOptions, self_calibrate
    from ari_sfm.particles.volume import Volume
    from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment

    exp = simulate_particle_experiment(ParticleSimOptions(particles_per_frame=300, num_frames=2, seed=11))
    with caplog.at_level("WARNING"):
        result = self_calibrate(exp.truth_a, dict(enumerate(exp.detections)),
                                SelfCalOptions(max_iterations=1, max_rounds=2, cells=(2, 2, 1)),
                                volume=Volume(exp.volume_min_mm, exp.volume_max_mm))
    capped = [r.adjustment for r in result.rounds if r.adjustment is not None and r.adjustment.stop == "max_iterations"]
    assert capped and all(a.iterations >= 1 for a in capped)
    said = [m for m in caplog.messages if "stopped at its 1-iteration cap (not converged)" in m]
    assert len(said) >= len(capped)
    rounds = result.report.to_json()["rounds"]
    assert any(r["adjustment"] and r["adjustment"]["stop"] == "max_iterations" for r in rounds)


def test_colmaps_bundle_adjustment_prints_no_info_lines_without_verbose(capfd):
    """pycolmap's bundle adjustment prints glog INFO lines whatever its minloglevel: without -v (ari_sfm
    logging at WARNING) they are dropped and a warning it writes is kept; with -v they show."""
    import logging

    from ari_sfm.colmap import adapter
    from ari_sfm.simulate.port_survey import port_survey

    truth = port_survey(seed=0, num_images=4, num_points=50)
    rec = adapter.reconstruction_from_arrays(
        [np.r_[p[:2] * 1.02, p[2:4]] for p in truth.params], truth.image_size, truth.sensor_from_rig,
        truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz, truth.obs_image, truth.obs_point,
        truth.obs_uv)
    logger = logging.getLogger("ari_sfm.colmap.adapter")
    before = logger.level
    try:
        logger.setLevel(logging.WARNING)
        capfd.readouterr()
        with adapter.colmap_quiet():
            adapter.bundle_adjust(rec)
            import pycolmap
            pycolmap.logging.warning("a warning of COLMAP's")
        quiet = capfd.readouterr().err
        logger.setLevel(logging.INFO)
        adapter.bundle_adjust(rec)
        verbose = capfd.readouterr().err
    finally:
        logger.setLevel(before)
    assert "Global bundle adjustment" not in quiet and "a warning of COLMAP's" in quiet
    assert "Global bundle adjustment" in verbose

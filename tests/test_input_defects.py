"""The defects found by fuzzing the command line (issue 10, item 7): each bad input gives one line
naming the file (or option) and the field, exit 1, and no result file."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from test_detection import H, W, checker_views, write_dataset  # noqa: F401 - the module fixture

from ari_sfm.cli import main
from ari_sfm.detection import detect_dataset
from ari_sfm.errors import AriSfmError
from ari_sfm.io import load_dataset


@pytest.mark.parametrize("scale", [0.5, 2.0])
def test_image_of_another_size_than_image_size_is_an_error_naming_it(checker_views, tmp_path, scale):  # noqa: F811
    """Half size calibrated silently gave 0.43 px instead of 0.10; double size wrote an unloadable file."""
    root = write_dataset(tmp_path / "ds", [checker_views[k][0] for k in range(4)])
    resized = cv2.resize(checker_views[2][0], (int(W * scale), int(H * scale)), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(root / "img" / "c2.png"), resized)
    with pytest.raises(AriSfmError) as info:
        detect_dataset(load_dataset(root), workers=2, progress=False)
    assert info.value.path == str(root / "img" / "c2.png")
    assert f"image is {int(W * scale)} x {int(H * scale)} px" in info.value.message
    assert f"cameras.cam0.image_size [{W}, {H}]" in info.value.message
    r = CliRunner().invoke(main, ["calibrate", str(root), "-o", str(tmp_path / "out")])
    last = r.output.strip().splitlines()[-1]  # after the progress bar
    assert r.exit_code == 1 and last.startswith(f"error: {root / 'img' / 'c2.png'}: image is")
    assert not (tmp_path / "out" / "calibration.json").exists()
    assert not (tmp_path / "out" / "observations.json").exists()


# --------------------------------------------------------------------------- options and output folders


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    r = CliRunner().invoke(main, ["simulate", "paper_single", "-o", str(out), "--no-images", "--seed", "0"])
    assert r.exit_code == 0, r.output
    return out


def _one_error_line(r, start: str) -> None:
    assert r.exit_code == 1, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(start), r.output


@pytest.mark.parametrize("where, message", [
    ("file", "-o/--out: is a file, expected a folder"),
    ("under a file", "is a file, so it cannot hold the output folder"),
    ("/proc/ari", "-o/--out: /proc is a kernel file system"),
    ("/sys/ari", "-o/--out: /sys is a kernel file system"),
])
@pytest.mark.parametrize("command", ["calibrate", "run", "simulate"])
def test_bad_output_folder_is_one_line_before_any_work(sim_dir, tmp_path, where, message, command):
    (tmp_path / "a_file").write_text("x")
    out = {"file": tmp_path / "a_file", "under a file": tmp_path / "a_file" / "sub" / "out"}.get(where, where)
    args = [command, "paper_single" if command == "simulate" else str(sim_dir / "dataset"), "-o", str(out)]
    r = CliRunner().invoke(main, args)
    _one_error_line(r, f"error: {out}: ")
    assert message in r.output
    assert (tmp_path / "a_file").read_text() == "x"


@pytest.mark.parametrize("value, message", [("-1", "--huber-px: must be >= 0 (got -1)"),
                                            ("nan", "--huber-px: must be a finite number (got nan)"),
                                            ("inf", "--huber-px: must be a finite number (got inf)")])
def test_bad_huber_is_named(sim_dir, tmp_path, value, message):
    """-1 was reported as 'non-finite Jacobian entries'; nan was accepted."""
    r = CliRunner().invoke(main,
                           ["calibrate", str(sim_dir / "dataset"), "-o", str(tmp_path / "o"), "--huber-px", value])
    _one_error_line(r, f"error: {message}")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("option, value, message", [
    ("--sigma", "nan", "--sigma: must be a finite number"),
    ("--sigma", "-0.1", "--sigma: must be >= 0"),
    ("--image-scale", "0", "--image-scale: must be >= 0.05"),
    ("--image-scale", "1e8", "--image-scale: must be <= 40"),
])
def test_bad_simulate_option_is_named_not_a_file(tmp_path, option, value, message):
    """simulate --sigma nan was blamed on a rig file never written."""
    r = CliRunner().invoke(main, ["simulate", "paper_single", "-o", str(tmp_path / "s"), option, value])
    _one_error_line(r, f"error: {message}")
    assert not (tmp_path / "s").exists()


def test_run_checks_the_truth_before_calibrating(sim_dir, tmp_path):
    r = CliRunner().invoke(main, ["run", str(sim_dir / "dataset"), "-o", str(tmp_path / "o"),
                                  "--truth", str(tmp_path / "missing.json")])
    assert r.exit_code == 1 and f"error: {tmp_path / 'missing.json'}: file not found" in r.output
    assert "model ari" not in r.output  # no calibration summary: it failed first
    assert not (tmp_path / "o" / "calibration.json").exists()
    (tmp_path / "other.json").write_text('{"format": "x"}')
    r = CliRunner().invoke(main, ["run", str(sim_dir / "dataset"), "-o", str(tmp_path / "o"),
                                  "--truth", str(tmp_path / "other.json")])
    assert r.exit_code == 1 and "has no reconstruction_points_world" in r.output
    assert not (tmp_path / "o" / "calibration.json").exists()


@pytest.fixture(scope="module")
def calibrated(sim_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("cal")
    r = CliRunner().invoke(main, ["calibrate", str(sim_dir / "dataset"), "-o", str(out)])
    assert r.exit_code == 0, r.output
    return out / "calibration.json"


def test_evaluate_checks_pixels_like_calibrate(sim_dir, calibrated, tmp_path):
    """A pixel at (-5000, 99999) gave 1631 px with exit 0."""
    data = json.loads((sim_dir / "dataset" / "observations.json").read_text())
    rec = next(o for o in data["observations"] if o["set"] == "calibration")
    rec["pixels"][0] = [-5000.0, 99999.0]
    bad = tmp_path / "obs.json"
    bad.write_text(json.dumps(data))
    r = CliRunner().invoke(main, ["evaluate", str(calibrated), str(bad)])
    _one_error_line(r, f"error: {bad}: observation ")
    assert "pixel (-5000, 99999)" in r.output and "is outside the" in r.output


@pytest.mark.parametrize("edit, message", [
    (lambda c: c["cameras"]["cam0"]["K"][0].__setitem__(0, 1e308), "cameras.cam0.K focal length must be <= 1e+07 px"),
    (lambda c: c["cameras"]["cam0"]["K"][1].__setitem__(1, -5.0), "cameras.cam0.K must have positive focal lengths"),
    (lambda c: c["cameras"]["cam0"].__setitem__("image_size", [100_000_000, 10]),
     "cameras.cam0.image_size must be <= 100000 px"),
    (lambda c: c["interface"].__setitem__("thickness_mm", 1e300), "interface.thickness_mm must be <= 10000 mm"),
    # issue 14: these printed numbers (distance 1e6: rmse nan)
    (lambda c: c["interface"].__setitem__("index", 6), "interface.index must be <= 5 (got 6.0): not a physical value"),
    (lambda c: c["interface"].__setitem__("medium_index", 0.5), "interface.medium_index must be >= 1 (got 0.5)"),
    (lambda c: c["cameras"]["cam0"].__setitem__("dist", [0.1, 0.0, 0.0]),
     "cameras.cam0.dist must have 4 or 5 numbers, k1 k2 p1 p2 [k3] (got 3)"),
    (lambda c: c["interface"].__setitem__("distance_mm", 1e6),
     "|interface.distance_mm| must be <= 10000 mm (got 1000000.0)"),
    (lambda c: c["interface"].__setitem__("distance_mm", -5.0),
     "interface.distance_mm -5 puts camera cam0 -5 mm from the window's near face (must be in front of it"),
    (lambda c: c["interface"].__setitem__("thickness_mm", 0), "interface.thickness_mm must be > 0 (got 0)"),
    (lambda c: c["cameras"]["cam0"].__setitem__("image_size", [2448.5, 2048]),
     "cameras.cam0.image_size must be two integers >= 1 (got [2448.5, 2048])"),
])
def test_evaluate_refuses_an_impossible_calibration(sim_dir, calibrated, tmp_path, edit, message):
    """fx = 1e308 gave rmse inf with exit 0."""
    cal = json.loads(calibrated.read_text())
    edit(cal)
    bad = tmp_path / "calibration.json"
    bad.write_text(json.dumps(cal))
    r = CliRunner().invoke(main, ["evaluate", str(bad), str(sim_dir / "dataset" / "observations.json")])
    _one_error_line(r, f"error: {bad}: {message}")


# --------------------------------------------------------------------------- Ctrl-C


def test_ctrl_c_while_open3d_initialises_is_an_interrupt_not_a_missing_package(monkeypatch):
    """Ctrl-C during open3d's extension init surfaces as ImportError('initialization failed')
    whose context is the KeyboardInterrupt; it was reported as "open3d: not installed"."""
    import builtins

    from ari_sfm.deps import require_open3d

    real_import = builtins.__import__

    def interrupted_import(name, *args, **kwargs):
        if name == "open3d":
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt:
                raise ImportError("initialization failed")  # noqa: B904 - keeps the context, as pybind11 does
        return real_import(name, *args, **kwargs)

    monkeypatch.delitem(sys.modules, "open3d", raising=False)
    monkeypatch.setattr(builtins, "__import__", interrupted_import)
    with pytest.raises(KeyboardInterrupt):
        require_open3d()

    def broken_import(name, *args, **kwargs):
        if name == "open3d":
            raise ImportError("initialization failed")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", broken_import)
    with pytest.raises(AriSfmError, match="installed but cannot load"):
        require_open3d()


def test_keyboard_interrupt_in_a_command_exits_130_with_one_line(monkeypatch, tmp_path):
    import ari_sfm.pipelines.calibrate_rig as pipeline

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "main", interrupted)
    r = CliRunner().invoke(main, ["calibrate", str(tmp_path), "-o", str(tmp_path / "o")])
    assert r.exit_code == 130 and r.output.strip() == "interrupted"


SAMPLE = Path(__file__).resolve().parents[1] / "datasets" / "sample"


@pytest.mark.parametrize("delay_s, second_s", [(0.0, None), (0.3, None), (0.0, 0.05), (0.2, 0.02), (0.1, 0.08)])
def test_sigint_during_detect_exits_130_without_abort(tmp_path, delay_s, second_s):
    """SIGINT while detection threads run OpenCV: exit 130 and 'interrupted'. A second Ctrl-C soon after
    aborted the process (SIGABRT, "terminate called without an active exception") in 6 of 25 tries with the
    original pool and 5 of 25 with a Thread.join wait, still ~1 in 3 runs of this test when the workers were
    awaited through their futures (the second signal cut that wait short), 0 in 50 runs since the CLI leaves
    by os._exit(130) while workers are still alive; a second SIGINT may end it by SIGINT (-2), never SIGABRT."""
    exe = Path(sys.executable).parent / "ari-sfm"
    p = subprocess.Popen([str(exe), "detect", str(SAMPLE), "-o", str(tmp_path / "det"), "--workers", "2"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # not ignored, as in `cmd &`
    seen = b""
    while b"detecting corners" not in seen:  # the progress bar: worker threads are running
        chunk = p.stderr.read1(256)
        assert chunk, "detect ended before detection started"
        seen += chunk
    time.sleep(delay_s)
    p.send_signal(signal.SIGINT)
    if second_s is not None:
        time.sleep(second_s)
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    err = (seen + err).decode(errors="replace")
    assert p.returncode != -signal.SIGABRT and "Traceback" not in err and "core dumped" not in err
    assert "terminate called" not in err and "FATAL" not in err, err
    if delay_s > 0 and (p.returncode == 0 or "18/18" in err):  # all 18 images done before the signal (it may
        return  # then land in the interpreter's shutdown and end it by SIGINT): no abort is all there is to check
    assert p.returncode in ((130, -signal.SIGINT) if second_s else (130,)), (p.returncode, err)
    assert err.strip().splitlines()[-1].endswith("interrupted"), err
    assert not (tmp_path / "det" / "observations.json").exists()


def test_keyboard_interrupt_outside_a_command_body_exits_130(monkeypatch):
    import ari_sfm.simulate as sim

    class Interrupting(dict):
        def items(self):
            raise KeyboardInterrupt

    monkeypatch.setattr(sim, "SCENARIOS", Interrupting())
    r = CliRunner().invoke(main, ["scenarios"])
    assert r.exit_code == 130 and r.output.strip() == "interrupted"


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf"), 0.0])
def test_calibration_options_refuse_a_bad_huber(value):
    """The library refuses what the CLI refuses (-1 failed as 'non-finite Jacobian entries'); the CLI maps 0 to None."""
    from ari_sfm.calibration.calibrate import CalibrationOptions

    with pytest.raises(ValueError, match="huber_px must be a finite number > 0"):
        CalibrationOptions(huber_px=value)
    assert CalibrationOptions(huber_px=None).huber_px is None and CalibrationOptions(huber_px=0.5).huber_px == 0.5


# ---------------------------------------------------------------- issue 14: the newer commands as strict as the old

ARI_SFM = Path(sys.executable).parent / "ari-sfm"
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}


def test_python_m_ari_sfm_cli_knows_every_command():
    """`python -m ari_sfm.cli refine-colmap` said "No such command": main() ran before it was defined."""
    for module in ("ari_sfm.cli", "ari_sfm"):
        r = subprocess.run([sys.executable, "-m", module, "refine-colmap", "--help"], capture_output=True, text=True,
                           env=ENV, timeout=120)
        assert r.returncode == 0 and "MODEL_DIR" in r.stdout, r.stderr


def test_scenarios_lists_port_survey():
    r = CliRunner().invoke(main, ["scenarios"])
    assert r.exit_code == 0 and any(line.split()[0] == "port_survey" for line in r.output.splitlines())


def test_detect_refuses_to_write_into_the_dataset(sim_dir):
    """detect -o DATASET overwrote the dataset's own observations.json."""
    ds = sim_dir / "dataset"
    before = (ds / "observations.json").read_bytes()
    r = CliRunner().invoke(main, ["detect", str(ds), "-o", str(ds)])
    _one_error_line(r, f"error: {ds}: -o/--out: is the dataset's own folder")
    assert (ds / "observations.json").read_bytes() == before


def test_output_folder_symlink_loop_and_dangling_link_are_named(sim_dir, tmp_path):
    """A symlink loop as -o gave "FileExistsError: [Errno 17] File exists"."""
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    for out, message in [(tmp_path / "loop", "-o/--out: a loop of symbolic links"),
                         (tmp_path / "loop" / "sub", "-o/--out: a loop of symbolic links"),
                         (tmp_path / "dangling",
                          f"-o/--out: a symbolic link to {tmp_path / 'nowhere'}, which does not exist")]:
        r = CliRunner().invoke(main, ["calibrate", str(sim_dir / "dataset"), "-o", str(out)])
        _one_error_line(r, f"error: {out}: {message}")
    assert not (tmp_path / "nowhere").exists()


def test_an_image_given_as_dataset_is_named_not_a_dataset(tmp_path):
    """A PNG as DATASET said 'not UTF-8 text (byte 0)'."""
    png = tmp_path / "view.png"
    ok, buf = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    png.write_bytes(buf.tobytes())
    for command in (["calibrate", str(png), "-o", str(tmp_path / "o")], ["detect", str(png)]):
        r = CliRunner().invoke(main, command)
        _one_error_line(r, f"error: {png}: not a dataset: expected a dataset folder (with rig.yaml) or a rig file")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("args, message", [
    (["--sigma", "nan"], "--sigma: must be a finite number"),
    (["--sigma", "0.1"], "--sigma: does not apply to port_survey"),
    (["--no-images"], "--no-images: port_survey is only images"),
    (["--image-scale", "1e-6"], "--image-scale: must be >= 0.05 (got 1e-06)"),
    (["--image-scale", "30"], "--image-scale: must be <= 8 (got 30)"),
    (["--seed", "-1"], "--seed: must be >= 0 (got -1)"),
])
def test_simulate_port_survey_options_are_checked(tmp_path, args, message):
    """port_survey ignored --sigma nan and --no-images, rendered at --image-scale 1e-6, failed inside numpy
    at --seed -1."""
    r = CliRunner().invoke(main, ["simulate", "port_survey", "-o", str(tmp_path / "s"), *args])
    _one_error_line(r, f"error: {message}")
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("where, message", [("file", "-o/--out: is a file, expected a folder"),
                                            ("/proc/ari", "-o/--out: /proc is a kernel file system"),
                                            ("read-only", "-o/--out: no permission to write in")])
def test_simulate_port_survey_output_folder_is_checked(tmp_path, monkeypatch, where, message):
    import ari_sfm.cli.checks as checks

    (tmp_path / "a_file").write_text("x")
    (tmp_path / "ro").mkdir()
    (tmp_path / "ro").chmod(0o500)
    out = {"file": tmp_path / "a_file", "read-only": tmp_path / "ro" / "s"}.get(where, where)
    real_access = os.access
    # root may write anywhere: the folder then answers as a read-only one would
    monkeypatch.setattr(checks.os, "access",
                        lambda p, mode: False if Path(p) == tmp_path / "ro" else real_access(p, mode))
    try:
        r = CliRunner().invoke(main, ["simulate", "port_survey", "-o", str(out)])
        _one_error_line(r, f"error: {out}: {message}")
    finally:
        (tmp_path / "ro").chmod(0o700)


def test_sigterm_in_a_command_exits_143_with_one_line(monkeypatch, tmp_path):
    import ari_sfm.pipelines.calibrate_rig as pipeline

    def terminated(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises in the main thread before this ends
        raise AssertionError("SIGTERM not delivered")

    monkeypatch.setattr(pipeline, "main", terminated)
    before = signal.getsignal(signal.SIGTERM)
    r = CliRunner().invoke(main, ["calibrate", str(tmp_path), "-o", str(tmp_path / "o")])
    assert r.exit_code == 143 and r.output.strip() == "terminated"
    assert signal.getsignal(signal.SIGTERM) is before  # restored after the command


def test_ctrl_c_that_a_library_turns_into_another_error_still_exits_130(monkeypatch, tmp_path):
    """Ctrl-C while open3d loads exited 1 in 4 of 45 runs: its init turned the interrupt into an ImportError
    (not always chained to the KeyboardInterrupt), reported as a failed import."""
    import ari_sfm.pipelines.calibrate_rig as pipeline

    def open3d_like_init(*args, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        except KeyboardInterrupt:
            raise ImportError("initialization failed") from None  # the interrupt is not its context
        raise AssertionError("SIGINT not delivered")

    monkeypatch.setattr(pipeline, "main", open3d_like_init)
    r = CliRunner().invoke(main, ["calibrate", str(tmp_path), "-o", str(tmp_path / "o")])
    assert r.exit_code == 130 and r.output.strip() == "interrupted"


@pytest.mark.parametrize("failure", ["write raises ENOSPC", "write truncates silently", "ply raises ENOSPC"])
def test_export_colmap_on_a_full_disk_leaves_no_truncated_model(sim_dir, calibrated, tmp_path, monkeypatch, failure):
    """A full disk left truncated images.bin / points3D.bin / points3D.ply and export-colmap exited 0."""
    import errno

    import pycolmap

    out = tmp_path / "colmap"
    r = CliRunner().invoke(main,
                           ["export-colmap", str(calibrated), "--dataset", str(sim_dir / "dataset"), "-o", str(out)])
    assert r.exit_code == 0, r.output
    good = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {"cameras.bin", "images.bin", "points3D.bin", "points3D.ply"} <= set(good)
    write, export_ply = pycolmap.Reconstruction.write, pycolmap.Reconstruction.export_PLY

    def full_disk_write(self, path):
        write(self, path)
        if failure == "write raises ENOSPC":
            raise OSError(errno.ENOSPC, "No space left on device")
        points = Path(path) / "points3D.bin"  # what pycolmap left on a full disk, with no error
        points.write_bytes(points.read_bytes()[:100])

    def full_disk_ply(self, path):
        Path(path).write_bytes(b"ply\n")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pycolmap.Reconstruction, "write", full_disk_write if failure != "ply raises ENOSPC" else write)
    monkeypatch.setattr(pycolmap.Reconstruction, "export_PLY",
                        full_disk_ply if failure == "ply raises ENOSPC" else export_ply)
    for target in (out, tmp_path / "fresh"):
        r = CliRunner().invoke(main, ["export-colmap", str(calibrated), "--dataset", str(sim_dir / "dataset"),
                                      "-o", str(target)])
        expected = "No space left on device" if "ENOSPC" in failure else "points"
        _one_error_line(r, f"error: {target}: cannot write the files: ")
        assert expected in r.output
    assert {p.name: p.read_bytes() for p in out.iterdir()} == good  # the older model untouched, no temporary left
    assert not list((tmp_path / "fresh").iterdir())


def test_sigterm_during_export_colmap_is_clean(sim_dir, calibrated, tmp_path):
    """SIGTERM during export-colmap printed pycolmap's native stack dump (glog's failure handler): now
    "terminated", exit 143 and no model file, or (signal too late) a complete model and exit 0."""
    import shutil

    cal = tmp_path / "cal"
    cal.mkdir()
    shutil.copy(calibrated, cal / "calibration.json")
    shutil.copy(sim_dir / "dataset" / "observations.json", cal / "observations.json")
    for delay_s in (0.0, 0.05):
        out = tmp_path / f"colmap{delay_s}"
        p = subprocess.Popen([str(ARI_SFM), "-v", "export-colmap", str(cal / "calibration.json"), "-o", str(out)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV)
        seen = b""
        while b"observations from" not in seen:  # logged after pycolmap is imported
            chunk = p.stderr.read1(256)
            assert chunk, "export-colmap ended early: " + seen.decode(errors="replace")
            seen += chunk
        time.sleep(delay_s)
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=60)
        err = (seen + err).decode(errors="replace")
        assert "stack trace" not in err and "Aborted at" not in err and "Traceback" not in err, err
        assert p.returncode in (143, 0), (p.returncode, err)
        files = sorted(f.name for f in out.iterdir()) if out.exists() else []
        model = ["cameras.bin", "frames.bin", "images.bin", "points3D.bin", "points3D.ply", "rigs.bin"]
        if p.returncode == 143:
            assert err.strip().splitlines()[-1] == "terminated", err
            assert files in ([], model), files  # nothing, or (signal during the renames) the whole model
        else:
            assert files == model


SWALLOWED_SIGNAL = """
import ctypes, os, signal
from ari_sfm.cli import user_errors

@ctypes.CFUNCTYPE(None)
def callback():  # as numba's compiler calls back into Python while it caches an object
    os.kill(os.getpid(), signal.SIGTERM)
    for _ in range(10000):  # the handler runs here, inside the C callback: its exception cannot propagate
        pass

@user_errors
def command():
    callback()
    print("finished")

command()
"""


def test_a_sigterm_swallowed_inside_a_c_callback_still_ends_as_terminated():
    """SIGTERM while numba compiled (a ctypes callback of llvmlite) printed "Exception ignored ... Traceback"
    and the command went on to exit 0: now no traceback, the command's writes finish (atomic), exit 143."""
    p = subprocess.run([sys.executable, "-c", SWALLOWED_SIGNAL], capture_output=True, text=True, env=ENV, timeout=60)
    assert p.returncode == 143, (p.returncode, p.stderr)
    assert p.stdout.strip() == "finished" and p.stderr.strip().splitlines() == ["terminated"], p.stderr


def test_simulate_port_survey_on_a_full_disk_leaves_no_truncated_png(tmp_path, monkeypatch):
    """A full disk left a truncated PNG."""
    import errno

    import ari_sfm.io.atomic as atomic

    real_open = open
    calls = []

    def full_disk_open(file, mode="r", *args, **kwargs):
        f = real_open(file, mode, *args, **kwargs)
        if mode == "wb":
            calls.append(1)
            if len(calls) == 2:  # the second image
                f.write(b"\x89PNG\r\n")
                f.flush()
                f.close()
                raise OSError(errno.ENOSPC, "No space left on device")
        return f

    monkeypatch.setattr(atomic, "open", full_disk_open, raising=False)  # the writer's open(tmp, "wb")
    out = tmp_path / "s"
    r = CliRunner().invoke(main, ["simulate", "port_survey", "-o", str(out), "--image-scale", "0.1"])
    last = r.output.strip().splitlines()[-1]  # after the progress bar
    assert r.exit_code == 1
    assert last == f"error: {out / 'images' / 'image0002.png'}: cannot write file: No space left on device"
    assert sorted(p.name for p in (out / "images").iterdir()) == ["image0001.png"]  # complete; no partial second
    assert cv2.imread(str(out / "images" / "image0001.png")) is not None and not (out / "truth.json").exists()


@pytest.fixture(scope="module")
def binocular_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("binocular")
    r = CliRunner().invoke(main, ["simulate", "binocular", "-o", str(out), "--no-images"])
    assert r.exit_code == 0, r.output
    return out


def _run_refused(r, start: str) -> None:
    """`run` prints its first line ("ari-sfm run: DATASET -> OUT"), then the one error line."""
    assert r.exit_code == 1, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith("ari-sfm run: ") and lines[1].startswith(start), r.output


def test_run_refuses_the_truth_of_another_dataset_before_calibrating(sim_dir, binocular_dir, tmp_path):
    """The truth of another dataset was found out only after calibrating (calibration.json left behind)."""
    out = tmp_path / "o"
    r = CliRunner().invoke(main, ["run", str(binocular_dir / "dataset"), "-o", str(out),
                                  "--truth", str(sim_dir / "truth.json")])
    _run_refused(r, f"error: {sim_dir / 'truth.json'}: not the truth of {binocular_dir / 'dataset' / 'rig.yaml'}: "
                    "its reconstruction frame r000 is not in the truth")
    assert not out.exists() or not any(out.iterdir())


def test_two_runs_of_different_datasets_into_one_folder(sim_dir, binocular_dir, tmp_path):
    """Two runs into one -o left run.json of one and points/metrics of the other: a run into a folder holding
    another dataset's results is refused before any work; the stale reconstruction of an earlier run of the
    same dataset is removed when this run has none."""
    out = tmp_path / "o"
    (out / "clouds").mkdir(parents=True)
    (out / "clouds" / "all.ply").write_text("ply")
    made_by = {"provenance": {"dataset": {"path": str((sim_dir / "dataset").resolve())}}}
    for name in ("points.json", "metrics.json"):
        (out / name).write_text(json.dumps(made_by))
    r = CliRunner().invoke(main, ["run", str(binocular_dir / "dataset"), "-o", str(out)])
    _run_refused(r, f"error: {out}: -o/--out: holds the results of another dataset "
                    f"({(sim_dir / 'dataset').resolve()}, in points.json): choose an empty folder")
    r = CliRunner().invoke(main, ["run", str(sim_dir / "dataset"), "-o", str(out)])  # paper_single: no reconstruction
    assert r.exit_code == 0 and "reconstruction skipped" in r.output, r.output
    assert sorted(p.name for p in out.iterdir()) == ["calibration.json", "report.html", "run.json"]
    r = CliRunner().invoke(main, ["run", str(binocular_dir / "dataset"), "-o", str(out)])
    _run_refused(r, f"error: {out}: -o/--out: holds the results of another dataset "
                    f"({(sim_dir / 'dataset').resolve()}, in run.json): choose an empty folder")
    assert json.loads((out / "run.json").read_text())["dataset"] == str((sim_dir / "dataset").resolve())


@pytest.fixture(scope="module")
def other_capture(sim_dir, tmp_path_factory):
    """sim_dir's dataset with a byte-identical rig.yaml but the corners of another capture (seed 1)."""
    import shutil

    out = tmp_path_factory.mktemp("capture")
    r = CliRunner().invoke(main, ["simulate", "paper_single", "-o", str(out / "sim1"), "--no-images", "--seed", "1"])
    assert r.exit_code == 0, r.output
    shutil.copytree(sim_dir / "dataset", out / "dataset")
    shutil.copy(out / "sim1" / "dataset" / "observations.json", out / "dataset" / "observations.json")
    return out / "dataset"


def test_report_and_export_colmap_refuse_another_capture_of_the_same_rig(sim_dir, calibrated, other_capture, tmp_path):
    """A byte-identical rig.yaml with other corners: the report's table said 0.070 px, its figure 489 px."""
    assert (other_capture / "rig.yaml").read_bytes() == (sim_dir / "dataset" / "rig.yaml").read_bytes()
    r = CliRunner().invoke(main, ["report", str(calibrated.parent), "--dataset", str(other_capture)])
    _one_error_line(r, f"error: {other_capture}: its corners are not the ones the calibration was made from: rmse ")
    r = CliRunner().invoke(main, ["export-colmap", str(calibrated), "--dataset", str(other_capture),
                                  "-o", str(tmp_path / "colmap")])
    _one_error_line(r, f"error: {other_capture}: its corners are not the ones the calibration was made from")
    assert not (tmp_path / "colmap").exists() or not any((tmp_path / "colmap").iterdir())
    r = CliRunner().invoke(main, ["report", str(calibrated.parent), "--dataset", str(sim_dir / "dataset")])
    assert r.exit_code == 0, r.output  # its own capture


def test_provenance_covers_the_corners_and_images_not_only_rig_yaml(sim_dir, other_capture):
    from ari_sfm.provenance import dataset_mismatch, dataset_record

    own, other = load_dataset(sim_dir / "dataset"), load_dataset(other_capture)
    result = {"provenance": {"dataset": dataset_record(own)}}
    assert dataset_record(own)["rig_sha256"] == dataset_record(other)["rig_sha256"]
    assert dataset_mismatch(result, own) is None
    why = dataset_mismatch(result, other)
    assert why is not None and why.startswith(f"made from other corners than {other.root}'s")


def test_provenance_covers_the_image_files(tmp_path):
    import shutil

    from ari_sfm.provenance import dataset_mismatch, dataset_record

    shutil.copytree(SAMPLE, tmp_path / "sample")
    result = {"provenance": {"dataset": dataset_record(load_dataset(tmp_path / "sample"))}}
    assert dataset_mismatch(result, load_dataset(tmp_path / "sample")) is None
    image = sorted((tmp_path / "sample").rglob("*.png"))[0]
    cv2.imwrite(str(image), 255 - cv2.imread(str(image)))  # another capture under the same name
    why = dataset_mismatch(result, load_dataset(tmp_path / "sample"))
    assert why is not None and why.startswith("made from other images than")


@pytest.mark.parametrize("old, new, message", [
    ("square_mm: 10.0", "square_mm: 1.0e-9", "target.square_mm must be >= 0.001 mm (got 1e-09): not a physical value"),
    ("focal_px: 3478.3", "focal_px: 1.0e-6", "cameras.cam0.focal_px must be >= 1 px (got 1e-06): not a physical value"),
    ("thickness_mm: 50.0", "thickness_mm: 1.0e-9", "interface.thickness_mm must be >= 0.001 mm (got 1e-09)"),
])
def test_unphysically_small_sizes_are_named_up_front(sim_dir, tmp_path, old, new, message):
    """A 1e-9 mm square or a 1e-6 px focal failed as "non-finite Jacobian ... a corner behind the window"."""
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(sim_dir / "dataset", ds)
    rig = (ds / "rig.yaml").read_text()
    assert old in rig
    (ds / "rig.yaml").write_text(rig.replace(old, new))
    r = CliRunner().invoke(main, ["calibrate", str(ds), "-o", str(tmp_path / "o")])
    _one_error_line(r, f"error: {ds / 'rig.yaml'}: {message}")
    assert not (tmp_path / "o").exists()


def test_evaluate_refuses_a_calibration_with_a_sub_pixel_focal(sim_dir, calibrated, tmp_path):
    cal = json.loads(calibrated.read_text())
    cal["cameras"]["cam0"]["K"][0][0] = 1e-6
    bad = tmp_path / "calibration.json"
    bad.write_text(json.dumps(cal))
    r = CliRunner().invoke(main, ["evaluate", str(bad), str(sim_dir / "dataset" / "observations.json")])
    _one_error_line(r, f"error: {bad}: cameras.cam0.K focal length must be >= 1 px (got 1e-06)")


@pytest.mark.parametrize("pixel, kept", [((-0.6, None), True), ((None, 2047.9), True), ((-1.4, None), True),
                                         ((-1.6, None), False), ((-5.0, None), False), ((None, 2100.0), False)])
def test_a_corner_just_beyond_the_border_is_kept_a_far_one_is_an_error(sim_dir, tmp_path, pixel, kept):
    """A corner 0.1 px outside the image (a sub-pixel centre at the border, or noise) made calibrate refuse the
    whole dataset: within 1 px of the edge (-0.5 .. size - 0.5) it is kept, as it is; beyond, an error."""
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(sim_dir / "dataset", ds)
    data = json.loads((ds / "observations.json").read_text())
    rec = next(o for o in data["observations"] if o["set"] == "calibration")
    u, v = rec["pixels"][0]
    rec["pixels"][0] = [u if pixel[0] is None else pixel[0], v if pixel[1] is None else pixel[1]]
    (ds / "observations.json").write_text(json.dumps(data))
    r = CliRunner().invoke(main, ["calibrate", str(ds), "-o", str(tmp_path / "o")])
    if kept:
        assert r.exit_code == 0, r.output
        assert load_dataset(ds).observations is not None  # loads, the pixel unchanged:
        first = next(o for o in load_dataset(ds).observations if o.set == "calibration")
        assert tuple(first.pixels[0]) == tuple(rec["pixels"][0])
    else:
        _one_error_line(r, f"error: {ds / 'observations.json'}: observation ")
        assert "is outside the 2448 x 2048 image (more than 1 px beyond its edge)" in r.output
        assert not (tmp_path / "o" / "calibration.json").exists()


def test_reconstruct_refuses_to_write_into_the_dataset(sim_dir, calibrated):
    ds = sim_dir / "dataset"
    before = sorted(p.name for p in ds.iterdir())
    r = CliRunner().invoke(main, ["reconstruct", str(ds), "--calibration", str(calibrated), "-o", str(ds)])
    _one_error_line(r, f"error: {ds}: -o/--out: is the dataset's own folder")
    assert sorted(p.name for p in ds.iterdir()) == before


@pytest.mark.parametrize("where, message", [("file", "-o/--out: is a file, expected a folder"),
                                            ("/proc/ari", "-o/--out: /proc is a kernel file system")])
def test_import_openptv_and_export_openptv_check_the_output_folder(calibrated, tmp_path, where, message):
    (tmp_path / "a_file").write_text("x")
    out = tmp_path / "a_file" if where == "file" else where
    for args in (["import", "openptv", str(tmp_path), "-o", str(out)],
                 ["export-openptv", str(calibrated), "-o", str(out)]):
        r = CliRunner().invoke(main, args)
        _one_error_line(r, f"error: {out}: {message}")


def test_a_binary_file_given_for_a_json_file_is_named_binary(sim_dir, calibrated, tmp_path):
    png = tmp_path / "view.png"
    ok, buf = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    png.write_bytes(buf.tobytes())
    for args in (["evaluate", str(png), str(sim_dir / "dataset" / "observations.json")],
                 ["evaluate", str(calibrated), str(png)], ["export-openptv", str(png), "-o", str(tmp_path / "o")]):
        r = CliRunner().invoke(main, args)
        _one_error_line(r, f"error: {png}: a binary file (an image?), not YAML or JSON text (byte 0 is not UTF-8)")
    broken = tmp_path / "calibration.json"
    broken.write_bytes(b'{"format": "ari-sfm-calibration/1", "model": "caf\xe9"}')
    r = CliRunner().invoke(main, ["evaluate", str(broken), str(sim_dir / "dataset" / "observations.json")])
    _one_error_line(r, f"error: {broken}: not UTF-8 text (byte 49 is not UTF-8)")


def test_a_file_given_for_a_folder_is_named_a_file(tmp_path):
    (tmp_path / "a_file").write_text("x")
    r = CliRunner().invoke(main, ["report", str(tmp_path / "a_file")])
    _one_error_line(r, f"error: {tmp_path / 'a_file'}: is a file, expected the output folder")
    r = CliRunner().invoke(main, ["import", "openptv", str(tmp_path / "a_file"), "-o", str(tmp_path / "ds")])
    _one_error_line(r, f"error: {tmp_path / 'a_file'}: is a file, expected an OpenPTV experiment folder")


@pytest.mark.parametrize("command", ["detect", "reconstruct"])
def test_workers_below_one_is_an_error(sim_dir, calibrated, tmp_path, command):
    """--workers -3 silently ran on one thread."""
    args = [command, str(sim_dir / "dataset"), "-o", str(tmp_path / "o"), "--workers", "-3"]
    if command == "reconstruct":
        args += ["--calibration", str(calibrated)]
    r = CliRunner().invoke(main, args)
    _one_error_line(r, "error: --workers: must be >= 1 (got -3)")


def test_reconstruct_refuses_a_reference_it_would_overwrite(sim_dir, calibrated, tmp_path):
    out = tmp_path / "o"
    (out / "clouds").mkdir(parents=True)
    (out / "clouds" / "all.ply").write_bytes(b"ply\n")
    r = CliRunner().invoke(main, ["reconstruct", str(sim_dir / "dataset"), "--calibration", str(calibrated),
                                  "-o", str(out), "--reference", str(out / "clouds" / "all.ply")])
    _one_error_line(r, f"error: {out / 'clouds' / 'all.ply'}: --reference: is a file this command writes in -o")
    assert (out / "clouds" / "all.ply").read_bytes() == b"ply\n"


DOCTOR_THEN_SIGTERM = """
import os, signal, sys, time
signal.signal(signal.SIGTERM, lambda *a: sys.exit(143))
from ari_sfm.deps import check_dependencies
check_dependencies()  # what `ari-sfm doctor` runs: imports pycolmap
os.kill(os.getpid(), signal.SIGTERM)
time.sleep(5)
"""


def test_doctor_keeps_python_sigterm_handler_over_glogs():
    """`doctor` imported pycolmap plainly: glog's failure-signal handler then answered SIGTERM with a native
    stack dump ("*** Aborted at ... SIGTERM ... stack trace"); through deps.import_pycolmap it does not."""
    p = subprocess.run([sys.executable, "-c", DOCTOR_THEN_SIGTERM], capture_output=True, text=True, env=ENV,
                       timeout=120)
    assert p.returncode == 143 and "stack trace" not in p.stderr and "Aborted at" not in p.stderr, p.stderr

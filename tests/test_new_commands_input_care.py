"""The input care of the newer commands (sfm's own cases are in test_sfm.py): -o on their own input is
refused with one line and nothing written, a full disk leaves no truncated result, SIGTERM leaves cleanly
("terminated", 143) without a partial result."""
from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from ari_sfm.cli import main

ARI_SFM = Path(sys.executable).parent / "ari-sfm"
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    """A small simulated particle experiment, its rig's true calibration (exact) and a fork export of it."""
    root = tmp_path_factory.mktemp("care")
    r = CliRunner().invoke(main, ["simulate", "particles", "-o", str(root / "sim"), "--particles", "200",
                                  "--frames", "2", "--render-frames", "1"])
    assert r.exit_code == 0, r.output
    cal = root / "sim" / "truth" / "rig_b.json"
    fork = root / "fork"
    r = CliRunner().invoke(main, ["export-colmap-fork", str(cal), "-o", str(fork)])
    assert r.exit_code == 0, r.output
    return root / "sim" / "experiment", cal, fork


def _args(command: str, experiment) -> list[str]:
    dataset, cal, fork = experiment
    return {"detect-particles": ["detect-particles", str(dataset), "-o", str(dataset)],
            "particles": ["particles", str(dataset), "--calibration", str(cal), "-o", str(dataset)],
            "self-calibrate": ["self-calibrate", str(dataset), "--calibration", str(cal), "-o", str(dataset)],
            "import-colmap-fork": ["import-colmap-fork", str(fork), "-o", str(fork)]}[command]


@pytest.mark.parametrize("command", ["detect-particles", "particles", "self-calibrate", "import-colmap-fork"])
def test_output_on_its_own_input_is_refused_and_nothing_written(experiment, command):
    args = _args(command, experiment)
    folder = Path(args[-1])
    before = sorted(p.name for p in folder.iterdir())
    r = CliRunner().invoke(main, args)
    lines = r.output.strip().splitlines()
    assert r.exit_code == 1 and len(lines) == 1 and lines[0].startswith(f"error: {folder}"), r.output
    assert "-o/--out" in lines[0]
    assert sorted(p.name for p in folder.iterdir()) == before


def _full_disk(monkeypatch):
    import ari_sfm.io.atomic as atomic

    real_open = open

    def full_disk_open(file, mode="r", *args, **kwargs):
        f = real_open(file, mode, *args, **kwargs)
        if mode == "wb":  # the atomic writer's temporary file
            f.close()
            raise OSError(errno.ENOSPC, "No space left on device")
        return f

    monkeypatch.setattr(atomic, "open", full_disk_open, raising=False)


def test_particles_on_a_full_disk_leaves_no_table(experiment, tmp_path, monkeypatch):
    dataset, cal, _ = experiment
    _full_disk(monkeypatch)
    out = tmp_path / "p3d"
    r = CliRunner().invoke(main, ["particles", str(dataset), "--calibration", str(cal), "-o", str(out),
                                  "--workers", "0"])
    assert r.exit_code == 1 and r.output.strip().splitlines()[-1].endswith("No space left on device"), r.output
    left = [p.name for p in out.rglob("*") if p.is_file()] if out.exists() else []
    assert not any(n.endswith(".parquet") or n.endswith(".tmp") for n in left), left


def _full_disk_at(monkeypatch, name: str) -> None:
    """The disk fills up while ``name`` is written (its fsync fails), after the files before it were written."""
    real_fsync = os.fsync

    def fsync(fd):
        if name in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)


@pytest.mark.parametrize("existing", [False, True])
def test_export_colmap_fork_on_a_full_disk_leaves_no_model_file(experiment, tmp_path, monkeypatch, existing):
    """The disk full at images.txt, the second of the three files (cameras.txt was left alone before): no file
    of the model, or an earlier export's three files as they were."""
    _, cal, _ = experiment
    out = tmp_path / "fork"
    if existing:
        assert CliRunner().invoke(main, ["export-colmap-fork", str(cal), "-o", str(out)]).exit_code == 0
        for f in out.iterdir():
            f.write_text(f"earlier {f.name}\n")
    _full_disk_at(monkeypatch, "images.txt")
    r = CliRunner().invoke(main, ["export-colmap-fork", str(cal), "-o", str(out)])
    lines = r.output.strip().splitlines()
    assert r.exit_code == 1 and len(lines) == 1 and lines[0] == f"error: {out}: cannot write the files: No space " \
                                                                "left on device", r.output
    left = sorted(p.name for p in out.iterdir()) if out.exists() else []
    if existing:
        assert left == ["cameras.txt", "images.txt", "points3D.txt"]
        assert all((out / n).read_text() == f"earlier {n}\n" for n in left)
    else:
        assert left == []


def _sigterm_once_started(args: list[str]) -> tuple[int, str]:
    """Run ``ari-sfm -v ARGS``, send SIGTERM once it has logged its first line, and return its exit code and
    stderr (checked to hold no traceback)."""
    p = subprocess.Popen([str(ARI_SFM), "-v", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV)
    seen = b""
    while b"INFO" not in seen:
        chunk = p.stderr.read1(256)
        if not chunk:
            break
        seen += chunk
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    text = (seen + err).decode(errors="replace")
    assert "Traceback" not in text and "stack trace" not in text, text
    return p.returncode, text


def test_sigterm_during_particles_leaves_cleanly(experiment, tmp_path):
    """SIGTERM once the command has started (its first log line): 'terminated' and 143 with no partial table
    (nothing, or when the signal lands at the end the whole result), or a complete run and 0."""
    dataset, cal, _ = experiment
    out = tmp_path / "p3d"
    returncode, err = _sigterm_once_started(["particles", str(dataset), "--calibration", str(cal), "-o", str(out),
                                             "--workers", "0"])
    assert returncode in (143, 0), (returncode, err)
    files = [q.name for q in out.rglob("*") if q.is_file()] if out.exists() else []
    assert not any(n.endswith(".tmp") for n in files), files
    complete = {"particles3d.parquet", "particles3d.json"} <= set(files)
    if complete:  # written through atomic renames: a complete table, never a truncated one
        import pyarrow.parquet as pq

        assert pq.read_table(out / "particles3d.parquet").num_rows > 0
    if returncode == 143:
        assert err.strip().splitlines()[-1] == "terminated", err
        assert complete or "particles3d.parquet" not in files  # nothing, or (signal at the end) the whole result
    else:
        assert complete


def test_sigterm_after_a_finished_command_is_not_a_kill(experiment, tmp_path):
    """A SIGTERM landing after the command's work, while the interpreter shuts down (here: sent by an object
    of the script's destroyed with its module, after CPython reset the signal handlers to the defaults),
    killed the process (-15). The command line now ends its process explicitly once the command is done:
    exit 0 with the complete result (or "terminated" and 143 had the signal come before)."""
    dataset, cal, _ = experiment
    out = tmp_path / "p3d"
    script = (
        "import os, signal, sys, time\n"
        f"sys.argv = ['ari-sfm', 'particles', {str(dataset)!r}, '--calibration', {str(cal)!r}, '-o', {str(out)!r},"
        " '--workers', '0']\n"
        "class Late:\n"
        "    def __del__(self):\n"
        "        os.kill(os.getpid(), signal.SIGTERM)\n"
        "        time.sleep(1)\n"
        "late = Late()\n"
        "from ari_sfm.cli import main\n"
        "main()\n")
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, env=ENV, timeout=300)
    err = p.stderr.decode(errors="replace")
    assert p.returncode == 0, (p.returncode, err)
    assert {"particles3d.parquet", "particles3d.json"} <= {q.name for q in out.iterdir()}


@pytest.mark.parametrize("command,results", [
    ("self-calibrate", {"calibration.json", "disparity.json"}),
    ("detect-particles", {"particles.parquet", "detect-particles.json"}),
])
def test_sigterm_during_the_other_long_commands_leaves_cleanly(experiment, tmp_path, command, results):
    """As for particles: SIGTERM once the command has started gives 'terminated' and 143 with none of its
    results or all of them (never one without the other, never a temporary file), or a complete run and 0."""
    dataset, cal, _ = experiment
    out = tmp_path / "out"
    args = [command, str(dataset), "-o", str(out), "--workers", "0"]
    if command == "self-calibrate":
        args += ["--calibration", str(cal)]
    returncode, err = _sigterm_once_started(args)
    assert returncode in (143, 0, 3), (returncode, err)  # 3: a self-calibration that fails its checks
    files = {q.name for q in out.iterdir() if q.is_file()} if out.exists() else set()
    assert not any(n.endswith(".tmp") for n in files), files
    assert files & results in (set(), results), files  # written together
    if returncode == 143:
        assert err.strip().splitlines()[-1] == "terminated", err
    else:
        assert results <= files


def test_refine_colmap_into_its_own_model_is_refused_and_nothing_written(tmp_path):
    """-o MODEL_DIR: one line naming the folder, exit 1, the model's files as they were."""
    model = tmp_path / "model"
    model.mkdir()
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        (model / name).write_text("# a COLMAP model\n")
    (tmp_path / "WINDOW.yaml").write_text("interface: {thickness_mm: 8, index: 1.49, medium_index: 1.333}\n"
                                          "mount: camera\nunits_mm: 1000\n")
    before = {p.name: p.read_text() for p in model.iterdir()}
    r = CliRunner().invoke(main, ["refine-colmap", str(model), "--window", str(tmp_path / "WINDOW.yaml"),
                                  "-o", str(model)])
    lines = r.output.strip().splitlines()
    assert r.exit_code == 1 and len(lines) == 1 and lines[0].startswith(f"error: {model}"), r.output
    assert "is MODEL_DIR" in lines[0]
    assert {p.name: p.read_text() for p in model.iterdir()} == before


@pytest.mark.parametrize("command", ["export-colmap", "export-colmap-fork"])
def test_an_export_onto_its_own_calibration_file_is_refused_and_it_is_kept(experiment, tmp_path, command):
    """-o naming the calibration.json being exported: one line naming it, exit 1, the file as it was."""
    _, cal, _ = experiment
    target = tmp_path / "calibration.json"
    target.write_bytes(cal.read_bytes())
    r = CliRunner().invoke(main, [command, str(target), "-o", str(target)])
    lines = r.output.strip().splitlines()
    assert r.exit_code == 1 and len(lines) == 1 and lines[0].startswith(f"error: {target}"), r.output
    assert target.read_bytes() == cal.read_bytes()


def test_import_colmap_fork_on_a_full_disk_leaves_no_calibration(experiment, tmp_path, monkeypatch):
    """The disk full while calibration.json is written: one line, exit 1, no calibration.json, no temporary."""
    _, _, fork = experiment
    _full_disk(monkeypatch)
    out = tmp_path / "imported"
    r = CliRunner().invoke(main, ["import-colmap-fork", str(fork), "-o", str(out)])
    assert r.exit_code == 1 and r.output.strip().splitlines()[-1].endswith("No space left on device"), r.output
    left = [p.name for p in out.rglob("*") if p.is_file()] if out.exists() else []
    assert not any(n == "calibration.json" or n.endswith(".tmp") for n in left), left

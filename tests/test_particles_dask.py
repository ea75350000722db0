"""Frames on Dask: a LocalCluster and a real `dask scheduler` + `dask worker` give the serial run's
particles to the bit; partitions are written one by one and a run resumes from them."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import cloudpickle
import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.particles.reconstruct import MatchOptions, reconstruct_particles
from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment, write_particle_experiment

OPTIONS = ParticleSimOptions(particles_per_frame=150, num_frames=4, seed=5)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("particles_dask")
    write_particle_experiment(simulate_particle_experiment(OPTIONS), out, render_frames=0)
    return out


def _table(path: Path) -> dict[str, np.ndarray]:
    t = pq.read_table(path)
    return {c: t.column(c).to_numpy() for c in t.column_names}


def _same(a: dict, b: dict) -> None:
    assert list(a) == list(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.fixture(scope="module")
def serial(sim, tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    reconstruct_particles(sim / "experiment", sim / "truth" / "rig_b.json", out,
                          MatchOptions(frames_per_partition=1), workers=0)
    return _table(out / "particles3d.parquet")


def test_local_cluster_equals_serial(sim, serial, tmp_path):
    s = reconstruct_particles(sim / "experiment", sim / "truth" / "rig_b.json", tmp_path,
                              MatchOptions(frames_per_partition=1), workers=2)
    _same(_table(tmp_path / "particles3d.parquet"), serial)
    assert s.workers == 2 and s.partitions_total == 4
    assert sorted(p.name for p in (tmp_path / "parts").glob("*.parquet")) == [
        f"frames_{f:05d}-{f:05d}.parquet" for f in range(4)]
    assert len(serial["frame"]) >= 0.95 * 4 * OPTIONS.particles_per_frame


def test_resume_skips_an_existing_partition(sim, serial, tmp_path):
    """A partition file already there (as a killed run leaves it) is not recomputed: a run whose frame-1
    partition holds only its first two particles keeps exactly that."""
    first = reconstruct_particles(sim / "experiment", sim / "truth" / "rig_b.json", tmp_path,
                                  MatchOptions(frames_per_partition=1), workers=0)
    assert first.partitions_skipped == ()
    part = tmp_path / "parts" / "frames_00001-00001.parquet"
    pq.write_table(pq.read_table(part).slice(0, 2), part)
    (tmp_path / "parts" / "frames_00002-00002.parquet").unlink()  # not finished before the kill
    (tmp_path / "particles3d.parquet").unlink()
    again = reconstruct_particles(sim / "experiment", sim / "truth" / "rig_b.json", tmp_path,
                                  MatchOptions(frames_per_partition=1), workers=0)
    assert list(again.partitions_skipped) == ["frames_00000-00000", "frames_00001-00001", "frames_00003-00003"]
    t = _table(tmp_path / "particles3d.parquet")
    assert (t["frame"] == 1).sum() == 2
    for f in (0, 2, 3):
        np.testing.assert_array_equal(t["x"][t["frame"] == f], serial["x"][serial["frame"] == f])


def test_partitions_of_another_run_are_refused(sim, tmp_path):
    reconstruct_particles(sim / "experiment", sim / "truth" / "rig_b.json", tmp_path,
                          MatchOptions(frames_per_partition=2), workers=0)
    r = CliRunner().invoke(main, ["particles", str(sim / "experiment"), "--calibration",
                                  str(sim / "truth" / "rig_b.json"), "-o", str(tmp_path), "--workers", "0",
                                  "--frames-per-partition", "2", "--tolerance-px", "0.7"])
    assert r.exit_code == 1 and r.output.count("\n") == 1
    assert "another run" in r.output and "tolerance_px" in r.output
    other = tmp_path / "cal.json"  # the same path's content changed: also another run
    other.write_text((sim / "truth" / "rig_a.json").read_text())
    reconstruct_particles(sim / "experiment", other, tmp_path / "b", MatchOptions(frames_per_partition=2), workers=0)
    other.write_text((sim / "truth" / "rig_b.json").read_text())
    r = CliRunner().invoke(main, ["particles", str(sim / "experiment"), "--calibration", str(other),
                                  "-o", str(tmp_path / "b"), "--workers", "0", "--frames-per-partition", "2"])
    assert r.exit_code == 1 and "calibration_sha256" in r.output


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


DASK_CLI = [sys.executable, "-m", "dask"]  # this interpreter's dask (a venv's bin/dask may name another python)
ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1")


def _start_scheduler(procs: list) -> str:
    port = _free_port()
    procs.append(subprocess.Popen([*DASK_CLI, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                   "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV,
                                  start_new_session=True))
    return f"tcp://127.0.0.1:{port}"


def _start_worker(procs: list, address: str) -> subprocess.Popen:
    """`dask worker` (a nanny and its worker process, in a session of their own: killed together)."""
    p = subprocess.Popen([*DASK_CLI, "worker", address, "--nthreads", "1", "--nworkers", "1", "--no-dashboard",
                          "--memory-limit", "0"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV,
                         start_new_session=True)
    procs.append(p)
    return p


def _wait_for_workers(address: str, n: int) -> None:
    from dask.distributed import Client

    deadline = time.monotonic() + 90
    while True:  # the scheduler up and n workers registered
        try:
            with Client(address, timeout="5s") as c:
                if len(c.scheduler_info()["workers"]) >= n:
                    return
        except OSError:
            pass
        if time.monotonic() > deadline:
            pytest.fail("dask scheduler / worker did not start")
        time.sleep(0.5)


def _stop(procs: list) -> None:
    for p in reversed(procs):
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


@pytest.fixture
def cluster():
    """Processes started by a test (scheduler, workers), stopped after it."""
    procs: list = []
    yield procs
    _stop(procs)


def test_cli_on_a_real_scheduler_and_worker(sim, serial, tmp_path, cluster):
    """`dask scheduler` and `dask worker` processes on localhost (random free port, one thread);
    `ari-sfm particles --scheduler` on them gives the serial particles."""
    address = _start_scheduler(cluster)
    _start_worker(cluster, address)
    _wait_for_workers(address, 1)
    r = CliRunner().invoke(main, ["particles", str(sim / "experiment"), "--calibration",
                                  str(sim / "truth" / "rig_b.json"), "-o", str(tmp_path), "--scheduler", address,
                                  "--frames-per-partition", "1"])
    assert r.exit_code == 0, r.output
    _same(_table(tmp_path / "particles3d.parquet"), serial)


def _ari_sfm(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "ari_sfm", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=ENV)


def _one_error_line(p: subprocess.Popen, timeout: float = 180) -> str:
    """The command ends (within ``timeout``: a hang fails the test) with exit 1 and one error line."""
    out, err = p.communicate(timeout=timeout)
    text = err.decode(errors="replace")
    assert p.returncode == 1, (p.returncode, text)
    assert "Traceback" not in text, text
    errors = [line for line in text.replace("\r", "\n").splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and text.rstrip().endswith(errors[0]), text
    return errors[0]


def test_killing_the_only_worker_mid_run_ends_with_one_line(sim, tmp_path, cluster):
    """SIGKILL of the only `dask worker` (nanny and worker) while it runs a partition: the command stops
    after --worker-timeout with one error line naming the scheduler, writes no table, and a later run with
    a worker resumes from the partitions written before the kill."""
    from dask.distributed import Client

    address = _start_scheduler(cluster)
    worker = _start_worker(cluster, address)
    _wait_for_workers(address, 1)
    out = tmp_path / "p3d"
    p = _ari_sfm("particles", sim / "experiment", "--calibration", sim / "truth" / "rig_b.json", "-o", out,
                 "--scheduler", address, "--frames-per-partition", "1", "--worker-timeout", "3")
    with Client(address, timeout="10s") as c:
        deadline = time.monotonic() + 120
        while not any(c.processing().values()):  # a partition on the worker
            assert p.poll() is None and time.monotonic() < deadline, "no partition reached the worker"
            time.sleep(0.02)
        os.killpg(worker.pid, signal.SIGKILL)
    line = _one_error_line(p)
    assert line.startswith(f"error: --scheduler: no Dask worker connected to {address} for 3 s"), line
    assert not (out / "particles3d.parquet").exists()
    assert not [q for q in out.rglob("*.tmp")]
    _start_worker(cluster, address)
    _wait_for_workers(address, 1)
    r = CliRunner().invoke(main, ["particles", str(sim / "experiment"), "--calibration",
                                  str(sim / "truth" / "rig_b.json"), "-o", str(out), "--scheduler", address,
                                  "--frames-per-partition", "1"])
    assert r.exit_code == 0, r.output
    assert json.loads((out / "particles3d.json").read_text())["partitions"]["total"] == 4


@pytest.mark.parametrize("command", ["self-calibrate", "detect-particles"])
def test_killing_the_only_worker_of_the_other_commands_ends_with_one_line(command, images, tmp_path, cluster):
    """The same SIGKILL of the only `dask worker` while it runs a task of self-calibrate (a frame's matching,
    gathered) or detect-particles (a partition's images): one error line naming the scheduler after
    --worker-timeout, and no result file."""
    from dask.distributed import Client

    address = _start_scheduler(cluster)
    worker = _start_worker(cluster, address)
    _wait_for_workers(address, 1)
    out = tmp_path / "out"
    extra = ["--calibration", images / "truth" / "rig_a.json"] if command == "self-calibrate" else []
    p = _ari_sfm(command, images / "experiment", *extra, "-o", out, "--scheduler", address, "--worker-timeout", "3")
    with Client(address, timeout="10s") as c:
        deadline = time.monotonic() + 120
        while not any(c.processing().values()):  # a task on the worker
            assert p.poll() is None and time.monotonic() < deadline, "no task reached the worker"
            time.sleep(0.02)
        os.killpg(worker.pid, signal.SIGKILL)
    line = _one_error_line(p)
    assert line.startswith(f"error: --scheduler: no Dask worker connected to {address} for 3 s"), line
    left = sorted(q.name for q in out.rglob("*") if q.is_file()) if out.exists() else []
    assert not [n for n in left if n.endswith((".tmp", ".json")) and n != "run.json"], left
    assert "particles.parquet" not in left and "calibration.json" not in left, left


def test_a_worker_joining_in_time_lets_the_run_go_on(sim, serial, tmp_path, cluster):
    """A scheduler with no worker: the command says it waits; a worker joining before --worker-timeout:
    it says so and the run ends with the serial particles."""
    address = _start_scheduler(cluster)
    _wait_for_workers(address, 0)
    out = tmp_path / "p3d"
    p = _ari_sfm("particles", sim / "experiment", "--calibration", sim / "truth" / "rig_b.json", "-o", out,
                 "--scheduler", address, "--frames-per-partition", "1", "--worker-timeout", "300")
    seen = b""
    while b"waiting up to 300 s" not in seen:
        chunk = p.stderr.read1(256)
        assert chunk, seen.decode(errors="replace")
        seen += chunk
    _start_worker(cluster, address)
    _, err = p.communicate(timeout=300)
    text = (seen + err).decode(errors="replace")
    assert p.returncode == 0, text
    assert f"no Dask worker connected to {address}" in text and "again" in text and "going on" in text
    _same(_table(out / "particles3d.parquet"), serial)


@pytest.mark.parametrize("command", ["particles", "detect-particles", "self-calibrate"])
def test_a_scheduler_without_workers_is_one_line(command, images, tmp_path, cluster):
    """Every command on Dask stops after --worker-timeout when no worker ever connects."""
    address = _start_scheduler(cluster)
    _wait_for_workers(address, 0)
    cal = images / "truth" / "rig_b.json"
    args = {"particles": ["--calibration", cal], "detect-particles": [], "self-calibrate": ["--calibration", cal]}
    p = _ari_sfm(command, images / "experiment", *args[command], "-o", tmp_path / "out", "--scheduler", address,
                 "--worker-timeout", "2")
    line = _one_error_line(p)
    assert line.startswith(f"error: --scheduler: no Dask worker connected to {address} for 2 s"), line


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """A small experiment with one rendered frame (for detect-particles)."""
    out = tmp_path_factory.mktemp("particles_images")
    write_particle_experiment(simulate_particle_experiment(ParticleSimOptions(particles_per_frame=100, num_frames=2,
                                                                              seed=5)), out, render_frames=1)
    return out


def test_unreachable_scheduler_is_one_line(sim, tmp_path, monkeypatch):
    monkeypatch.setattr("ari_sfm.particles.engine.SCHEDULER_TIMEOUT_S", 1.0)
    r = CliRunner().invoke(main, ["particles", str(sim / "experiment"), "--calibration",
                                  str(sim / "truth" / "rig_b.json"), "-o", str(tmp_path),
                                  "--scheduler", f"tcp://127.0.0.1:{_free_port()}"])
    assert r.exit_code == 1 and r.output.startswith("error: --scheduler") and r.output.count("\n") == 1


def test_an_http_server_is_not_a_scheduler(sim, tmp_path, monkeypatch):
    """A server that accepts the connection and says nothing (an HTTP server, the dashboard's port): Dask's
    handshake waited forever; now one line within SCHEDULER_TIMEOUT_S."""
    import http.server
    import threading

    monkeypatch.setattr("ari_sfm.particles.engine.SCHEDULER_TIMEOUT_S", 1.0)
    server = http.server.HTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        address = f"tcp://127.0.0.1:{server.server_address[1]}"
        r = CliRunner().invoke(main, ["particles", str(sim / "experiment"), "--calibration",
                                      str(sim / "truth" / "rig_b.json"), "-o", str(tmp_path), "--scheduler", address])
    finally:
        server.shutdown()
        server.server_close()
    assert r.exit_code == 1 and r.output.count("\n") == 1, r.output
    assert r.output.startswith(f"error: --scheduler: {address} accepts connections but is not a Dask scheduler")


@pytest.mark.parametrize("address, words", [
    ("not-an-address", ["not a Dask scheduler address tcp://HOST:PORT"]),
    ("tcp://", ["not a Dask scheduler address"]),
    ("http://127.0.0.1:8787", ["unknown address scheme 'http'"]),
    ("udp://127.0.0.1:1", ["unknown address scheme 'udp'"]),
    ("tls://127.0.0.1:1", ["cannot connect to the Dask scheduler tls://127.0.0.1:1", "TLS settings"]),
    ("ucx://127.0.0.1:1", ["cannot connect to the Dask scheduler ucx://127.0.0.1:1"]),
])
def test_an_address_that_is_no_scheduler_is_one_line(sim, tmp_path, address, words):
    """Bad addresses and schemes (tls:// without Dask's TLS settings and ucx:// without UCX raised a
    TypeError from inside Dask): one line naming --scheduler, and no particles written."""
    r = CliRunner().invoke(main, ["particles", str(sim / "experiment"), "--calibration",
                                  str(sim / "truth" / "rig_b.json"), "-o", str(tmp_path / "o"), "--scheduler", address])
    assert r.exit_code == 1 and r.output.count("\n") == 1, r.output
    assert r.output.startswith("error: --scheduler: ") and all(w in r.output for w in words), r.output
    assert not (tmp_path / "o" / "particles3d.parquet").exists()


def test_a_run_that_made_no_partition_does_not_hold_its_folder(sim, serial, tmp_path, monkeypatch):
    """A run that failed before making a partition (an unreachable scheduler) left parts/run.json, and the
    next run with other settings into the same -o was refused as 'another run': its record is replaced."""
    monkeypatch.setattr("ari_sfm.particles.engine.SCHEDULER_TIMEOUT_S", 1.0)
    out = tmp_path / "p3d"
    args = ["particles", str(sim / "experiment"), "--calibration", str(sim / "truth" / "rig_b.json"), "-o", str(out),
            "--frames-per-partition", "1"]
    r = CliRunner().invoke(main, [*args, "--scheduler", f"tcp://127.0.0.1:{_free_port()}", "--tolerance-px", "0.7"])
    assert r.exit_code == 1 and r.output.startswith("error: --scheduler"), r.output
    r = CliRunner().invoke(main, [*args, "--workers", "0"])
    assert r.exit_code == 0, r.output
    _same(_table(out / "particles3d.parquet"), serial)
    r = CliRunner().invoke(main, [*args, "--workers", "0", "--tolerance-px", "0.7"])  # partitions now: refused
    assert r.exit_code == 1 and "another run" in r.output, r.output


def test_a_damaged_partition_is_made_again(sim, serial, tmp_path):
    """A partition file damaged after its header (its schema still reads; pyarrow's error blamed the final
    table in several lines): a resumed run makes it again and gives the serial particles; merging it names it."""
    import pyarrow.parquet as pq

    from ari_sfm.errors import AriSfmError
    from ari_sfm.particles.engine import merge_partitions

    out = tmp_path / "p3d"
    args = ["particles", str(sim / "experiment"), "--calibration", str(sim / "truth" / "rig_b.json"), "-o", str(out),
            "--frames-per-partition", "1", "--workers", "0"]
    assert CliRunner().invoke(main, args).exit_code == 0
    part = out / "parts" / "frames_00001-00001.parquet"
    data = bytearray(part.read_bytes())
    data[8:400] = b"\xab" * 392  # the first column's pages; the footer intact
    part.write_bytes(bytes(data))
    assert pq.read_schema(part).names  # the schema still reads
    with pytest.raises(AriSfmError, match="a damaged partition") as err:
        merge_partitions([part], tmp_path / "merged.parquet")
    assert err.value.path == str(part) and "\n" not in err.value.message
    assert not (tmp_path / "merged.parquet").exists()
    (out / "particles3d.parquet").unlink()
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0 and "3 partitions resumed" in r.output, r.output
    _same(_table(out / "particles3d.parquet"), serial)


def test_negative_workers_are_refused(sim, images, tmp_path):
    """workers=-1 made a LocalCluster that never ran anything: refused, as is a worker timeout <= 0."""
    from ari_sfm.errors import AriSfmError
    from ari_sfm.particles.detect import detect_experiment
    from ari_sfm.particles.engine import dask_client

    with pytest.raises(AriSfmError, match="--workers: must be >= 0"):
        reconstruct_particles(sim / "experiment", sim / "truth" / "rig_b.json", tmp_path / "a", workers=-1)
    with pytest.raises(AriSfmError, match="--workers: must be >= 0"):
        detect_experiment(images / "experiment", tmp_path / "b", workers=-1)
    with pytest.raises(AriSfmError, match="--workers: must be a whole number"):
        with dask_client(1.5, None):
            pass
    with pytest.raises(AriSfmError, match="--worker-timeout"):
        with dask_client(0, "tcp://127.0.0.1:1", worker_timeout_s=0):
            pass
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    r = CliRunner().invoke(main, ["particles", str(sim / "experiment"), "--calibration",
                                  str(sim / "truth" / "rig_b.json"), "-o", str(tmp_path / "c"),
                                  "--worker-timeout", "0"])
    assert r.exit_code == 1 and r.output.startswith("error: --worker-timeout") and r.output.count("\n") == 1


def _kill_my_worker(frame: int) -> dict:
    os._exit(1)


def test_a_task_that_kills_its_workers_is_one_error(tmp_path):
    """A partition whose worker dies each time it runs (out of memory, a crash): Dask gives up after
    allowed-failures restarts (KilledWorker); the run ends with one error naming --workers."""
    import dask
    import distributed  # noqa: F401 - its configuration defaults in place before they are changed

    from ari_sfm.errors import AriSfmError
    from ari_sfm.particles.engine import Partition, dask_client, run_partitions

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the task travels by value (no tests/ there)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        with pytest.raises(AriSfmError, match="--workers: a task killed every Dask worker that ran it"):
            with dask_client(1, None) as client:
                run_partitions(_kill_my_worker, [Partition(0, 0, (0,))], tmp_path, client)
    assert not list((tmp_path / "parts").glob("*.parquet"))


def test_partitions_are_made_as_they_are_submitted(tmp_path):
    """A long experiment's partitions are not all made up front: in this process one at a time, on Dask
    at most the in-flight bound ahead of those written."""
    from ari_sfm.particles.engine import MIN_IN_FLIGHT, Partition, dask_client, run_partitions

    made, ahead = [], []

    def partitions(n):
        for f in range(n):
            made.append(f)
            yield Partition(f, f, (f,))

    def done(p, skipped):
        ahead.append(len(made) - (p.first + 1))

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    run_partitions(_one_row, partitions(30), tmp_path / "serial", None, done)
    assert len(ahead) == 30 and max(ahead) == 0
    made.clear()
    ahead.clear()
    with dask_client(1, None) as client:
        paths = run_partitions(_one_row, partitions(30), tmp_path / "dask", client, done)
    assert len(paths) == 30 and len(ahead) == 30 and max(ahead) <= max(MIN_IN_FLIGHT, 2)
    assert [pq.read_table(p).column("frame").to_pylist() for p in paths] == [[f] for f in range(30)]


def _one_row(frame: int) -> dict:
    return {"frame": np.array([frame], np.int64)}


def test_a_local_cluster_run_is_quiet_unless_verbose(sim, tmp_path):
    """Dask's INFO lines (its cluster's start and stop, "please install jupyter-server-proxy") and glog's
    only with -v."""
    args = ["particles", sim / "experiment", "--calibration", sim / "truth" / "rig_b.json", "--workers", "1"]
    p = _ari_sfm(*args, "-o", tmp_path / "quiet")
    _, err = p.communicate(timeout=300)
    text = err.decode(errors="replace")
    assert p.returncode == 0, text
    lines = [line for line in text.replace("\r", "\n").splitlines() if line and not line.startswith("matching")]
    assert lines == [], text
    p = _ari_sfm("-v", *args, "-o", tmp_path / "verbose")
    _, err = p.communicate(timeout=300)
    assert p.returncode == 0 and "INFO: Register worker" in err.decode(errors="replace")

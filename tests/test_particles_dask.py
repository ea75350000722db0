"""Frames on Dask: a LocalCluster and a real `dask scheduler` + `dask worker` give the serial run's
particles to the bit; partitions are written one by one and a run resumes from them."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

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


def test_cli_on_a_real_scheduler_and_worker(sim, serial, tmp_path):
    """`dask scheduler` and `dask worker` processes on localhost (random free port, one thread);
    `ari-sfm particles --scheduler` on them gives the serial particles."""
    dask_cli = [sys.executable, "-m", "dask"]  # this interpreter's dask (a venv's bin/dask may name another python)
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    procs = []
    try:
        procs.append(subprocess.Popen([*dask_cli, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                       "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      env=env))
        procs.append(subprocess.Popen([*dask_cli, "worker", address, "--nthreads", "1", "--nworkers", "1",
                                       "--no-dashboard", "--memory-limit", "0"], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL, env=env))
        from dask.distributed import Client

        deadline = time.monotonic() + 60
        while True:  # the scheduler up and the worker registered
            try:
                with Client(address, timeout="5s") as c:
                    if c.scheduler_info()["workers"]:
                        break
            except OSError:
                pass
            if time.monotonic() > deadline:
                pytest.fail("dask scheduler / worker did not start")
            time.sleep(0.5)
        r = CliRunner().invoke(main, ["particles", str(sim / "experiment"), "--calibration",
                                      str(sim / "truth" / "rig_b.json"), "-o", str(tmp_path), "--scheduler", address,
                                      "--frames-per-partition", "1"])
        assert r.exit_code == 0, r.output
        _same(_table(tmp_path / "particles3d.parquet"), serial)
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_unreachable_scheduler_is_one_line(sim, tmp_path, monkeypatch):
    monkeypatch.setattr("ari_sfm.particles.engine.SCHEDULER_TIMEOUT_S", 1.0)
    r = CliRunner().invoke(main, ["particles", str(sim / "experiment"), "--calibration",
                                  str(sim / "truth" / "rig_b.json"), "-o", str(tmp_path),
                                  "--scheduler", f"tcp://127.0.0.1:{_free_port()}"])
    assert r.exit_code == 1 and r.output.startswith("error: --scheduler") and r.output.count("\n") == 1

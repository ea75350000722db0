"""Ctrl-C and SIGTERM sent to a real `ari-sfm` process at any moment of its start, including while the
package, numpy/OpenCV and open3d's native extension load: one line ("interrupted" 130, "terminated" 143),
never Python's traceback, never exit 1 (open3d cut short in its initialisation ran C++ destructors at
exit that turned 130 into 1; an interrupt before the CLI's handlers printed a KeyboardInterrupt traceback;
pycolmap's import turned Ctrl-C into "Cannot import the C++ backend" and `doctor` reported a broken install).
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ARI_SFM = Path(sys.executable).parent / "ari-sfm"
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
# From the first import to open3d's initialisation (doctor imports every dependency, open3d among the last).
DELAYS_S = (0.15, 0.3, 0.5, 0.8, 1.2, 1.7)


def _signal_after(cmd: list[str], delay_s: float, signum: int) -> tuple[int | None, str]:
    """Run cmd, send signum after delay_s; (exit code, stderr), exit code None if it ended before the signal."""
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    time.sleep(delay_s)
    ended_before = p.poll() is not None
    if not ended_before:
        p.send_signal(signum)
    _, err = p.communicate(timeout=120)
    if "init_import_site" in err:  # the signal came while Python itself started: before any code of ours
        pytest.skip(f"Python was still starting after {delay_s} s")
    return (None if ended_before else p.returncode), err


@pytest.mark.parametrize("delay_s", DELAYS_S)
def test_ctrl_c_while_ari_sfm_loads_exits_130_with_one_line(delay_s):
    code, err = _signal_after([str(ARI_SFM), "doctor"], delay_s, signal.SIGINT)
    if code is None:
        pytest.skip(f"doctor ended within {delay_s} s")
    assert code == 130 and "Traceback" not in err and err.strip().splitlines()[-1] == "interrupted", (code, err)


@pytest.mark.parametrize("delay_s", DELAYS_S[2::2])  # from 0.5 s: Python itself has started
def test_sigterm_while_ari_sfm_loads_exits_143_with_one_line(delay_s):
    code, err = _signal_after([str(ARI_SFM), "doctor"], delay_s, signal.SIGTERM)
    if code is None:
        pytest.skip(f"doctor ended within {delay_s} s")
    assert code == 143 and "Traceback" not in err and err.strip().splitlines()[-1] == "terminated", (code, err)


def test_ctrl_c_while_python_m_ari_sfm_loads_exits_130():
    code, err = _signal_after([sys.executable, "-m", "ari_sfm", "doctor"], 0.3, signal.SIGINT)
    assert code == 130 and "Traceback" not in err, (code, err)


def test_importing_the_library_leaves_the_signal_handlers_alone():
    """`import ari_sfm` in a user's script is not the command line: Python's own SIGINT handler stays."""
    code = ("import signal, ari_sfm, ari_sfm._startup as s; "
            "assert signal.getsignal(signal.SIGINT) is signal.default_int_handler; "
            "assert not s.is_command_line(); print('ok')")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    assert p.returncode == 0 and p.stdout.strip() == "ok", p.stderr


def test_a_signal_during_pycolmaps_import_reaches_pythons_handler(tmp_path):
    """pycolmap's import installs glog's SIGTERM handler, which deps.import_pycolmap replaces with Python's
    again; a SIGTERM arriving in between (here: sent by the module itself, after installing a stand-in for
    glog's handler) must reach Python's handler once the import is done, never the stand-in (which, as glog's,
    would dump a native stack or hang)."""
    (tmp_path / "pycolmap.py").write_text(
        "import os, signal\n"
        "signal.signal(signal.SIGTERM, lambda *a: os._exit(99))  # glog's handler, installed by the import\n"
        "os.kill(os.getpid(), signal.SIGTERM)  # a SIGTERM arriving while the import runs\n")
    code = ("import signal, sys; seen = []; signal.signal(signal.SIGTERM, lambda *a: seen.append('python')); "
            "from ari_sfm.deps import import_pycolmap; m = import_pycolmap(); "
            "assert m.__file__.startswith(sys.path[0]), m.__file__; print(seen)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**ENV, "PYTHONPATH": str(tmp_path)})
    assert p.returncode == 0 and p.stdout.strip() == "['python']", (p.returncode, p.stdout, p.stderr)


@pytest.mark.parametrize("signum, code, line",
                         [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")])
def test_a_signal_after_the_command_returned_leaves_with_its_code(signum, code, line):
    """A signal after a command's body (its results written; the interpreter shutting down, which can take
    seconds with dask or numba loaded): one line and the signal's code, not a process killed by it (-15)."""
    script = ("import os, signal, sys, time; sys.argv[0] = 'ari-sfm'; "
              "from ari_sfm.cli import user_errors; "
              "user_errors(lambda: print('done', flush=True))(); "
              f"os.kill(os.getpid(), {int(signum)}); time.sleep(5); print('not left')")
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=ENV, timeout=120)
    assert p.returncode == code and p.stdout.strip() == "done", (p.returncode, p.stdout, p.stderr)
    assert p.stderr.strip().splitlines()[-1] == line and "Traceback" not in p.stderr, p.stderr

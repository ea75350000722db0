"""The built wheel: every module of the source tree under the one import root ari_sfm, and the compiled
kernels (ari_sfm/_compiled, written by ari_sfm.kernel_build when the wheel is built) that a fresh install
runs without compiling, with the same numbers as numba's own compilation, which takes over whenever the
shipped code does not match.

The editable install (scripts/setup.sh) imports from the source tree and hides a package the
wheel forgets; this builds the real wheel offline once (no build isolation: the
test extras pin setuptools; ~1 min, most of it compiling the kernels) from a copy of the tree.
"""
from __future__ import annotations

import configparser
import hashlib
import importlib
import json
import os
import pickle
import shutil
import stat
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from ari_sfm import kernel_cache
from ari_sfm.kernel_signatures import SIGNATURES

ROOT = Path(__file__).resolve().parents[1]
SOURCES = {"ari_sfm": "ari_sfm", "factors": "ari_sfm/factors", "pipelines": "ari_sfm/pipelines"}  # folder -> in wheel


def test_factors_and_pipelines_are_relative_links_under_ari_sfm() -> None:
    """ari_sfm/factors and ari_sfm/pipelines are relative symbolic links (as git checks them out) to the top-level
    folders: the one import root that every tool reads as it is, without a package-dir remap."""
    for name in ("factors", "pipelines"):
        link = ROOT / "ari_sfm" / name
        assert link.is_symlink() and os.readlink(link) == f"../{name}", f"ari_sfm/{name} is not the link ../{name}"
        assert link.resolve() == (ROOT / name).resolve()


def expected_modules() -> set[str]:
    """Every .py file under the three source folders, as its path inside the wheel."""
    out = set()
    for folder, installed in SOURCES.items():
        for f in (ROOT / folder).rglob("*.py"):
            if "__pycache__" not in f.parts:
                out.add(f"{installed}/{f.relative_to(ROOT / folder).as_posix()}")
    return out


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel built from a copy of the tree (its links kept, as `cp -r` keeps them), as .ci/run builds it."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    for folder in SOURCES:
        shutil.copytree(ROOT / folder, src / folder, symlinks=True,
                        ignore=shutil.ignore_patterns("__pycache__", "_compiled"))
    run = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "-w", str(tmp / "wheel"), "--no-deps",
                          "--no-build-isolation", "-q"], capture_output=True, text=True, timeout=1200)
    assert run.returncode == 0, run.stderr
    (path,) = (tmp / "wheel").glob("ari_sfm-*.whl")
    return path


def test_wheel_contains_every_package(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    py = {n for n in names if n.endswith(".py")}
    expected = expected_modules()
    assert {"ari_sfm/baselines/__init__.py", "ari_sfm/factors/rig_graph.py", "ari_sfm/pipelines/run.py"} <= expected
    assert expected - py == set(), "modules missing from the wheel"
    assert py - expected == set(), "modules in the wheel that are not in the source tree (e.g. a bare factors/)"
    links = [i.filename for i in zipfile.ZipFile(wheel).infolist() if stat.S_ISLNK(i.external_attr >> 16)]
    assert links == [], "the wheel holds symbolic links, not the files"
    (meta,) = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
    entry = configparser.ConfigParser()
    entry.read_string(zipfile.ZipFile(wheel).read(meta).decode())
    assert entry["console_scripts"]["ari-sfm"] == "ari_sfm.cli:main"


def shipped_index(zf: zipfile.ZipFile, module: str, kernel: str) -> tuple[bytes, dict]:
    """The source stamp and the entries (key -> data file) of a kernel's index in the wheel's ari_sfm/_compiled."""
    line = getattr(importlib.import_module(module), kernel).py_func.__code__.co_firstlineno
    base = f"{module.rsplit('.', 1)[1]}.{kernel}-{line}.py{sys.version_info[0]}{sys.version_info[1]}"
    with zf.open(f"ari_sfm/_compiled/{module}/{base}.nbi") as f:
        assert pickle.load(f) == kernel_cache.target_record()["numba"]
        return pickle.loads(f.read())


def test_wheel_ships_every_kernel_compiled_for_the_target(wheel: Path) -> None:
    """Each signature of kernel_signatures has an entry in the wheel, keyed on the target CPU (not the building
    host's) and on the content of the wheel's own copy of its source file."""
    zf = zipfile.ZipFile(wheel)
    assert json.loads(zf.read("ari_sfm/_compiled/target.json")) == kernel_cache.target_record()
    names = set(zf.namelist())
    for module, kernels in SIGNATURES.items():
        source = zf.read(module.replace(".", "/") + ".py")
        for kernel, sigs in kernels.items():
            stamp, entries = shipped_index(zf, module, kernel)
            assert stamp == hashlib.sha256(source).digest(), f"{module}.{kernel}: stamp of another source"
            keys = {sig: magic for sig, magic, _ in entries}
            for sig in sigs:
                assert keys.get(sig, ("", ""))[1:] == (kernel_cache.TARGET_CPU, kernel_cache.TARGET_CPU_FEATURES), \
                    f"{module}.{kernel}{sig} not shipped for {kernel_cache.TARGET_CPU}"
            assert {f"ari_sfm/_compiled/{module}/{name}" for name in entries.values()} <= names


# A calibration (the bundled binocular dataset, exact model), a triangulation through the window and a short
# refine-colmap, in a fresh process whose shipped kernels are those in sys.argv[1] and numba's own cache
# NUMBA_CACHE_DIR: prints the results (calibration.json without its times) and the kernels' cache statistics.
WORKLOAD = """
import json, sys
from pathlib import Path
import numpy as np
from ari_sfm import kernel_cache
kernel_cache.SHIPPED_DIR = Path(sys.argv[1])
from numba.core.dispatcher import Dispatcher
from ari_sfm.colmap import adapter
from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.colmap.refine import refine_colmap
from ari_sfm.io import calibration_to_json, load_dataset
from ari_sfm.simulate.port_survey import port_survey
from ari_sfm.reconstruction.triangulate import triangulate_pixels

def untimed(d):
    if isinstance(d, dict):
        return {k: untimed(v) for k, v in d.items() if k != "time_s"}
    return [untimed(v) for v in d] if isinstance(d, list) else d

cal = calibrate(load_dataset(sys.argv[2]), model="exact")
X = np.array([p.t for p in cal.frames.values()])
Xt = triangulate_pixels(cal, {c: cal.project_world(c, X) for c in cal.cameras})[0]
truth = port_survey(seed=0, num_images=6, num_points=150)
rec = adapter.reconstruction_from_arrays(
    [np.r_[p[:2] * 1.02, p[2:4]] for p in truth.params], truth.image_size, truth.sensor_from_rig,
    truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz, truth.obs_image, truth.obs_point,
    truth.obs_uv)
refined = refine_colmap(adapter.bundle_adjust(rec), truth.interface, "camera", max_iterations=3)
stats = [d.stats for m, mod in list(sys.modules.items()) if m.startswith("ari_sfm.")
         for d in vars(mod).values() if isinstance(d, Dispatcher) and d.__module__ == m]
print(json.dumps({"calibration": untimed(calibration_to_json(cal)), "triangulated": Xt.tolist(),
                  "refined": untimed(calibration_to_json(refined.calibration)),
                  "refined_points": refined.state.xyz.tolist(),
                  "shipped": kernel_cache.shipped_usable()[0],
                  "loaded": sum(sum(s.cache_hits.values()) for s in stats),
                  "compiled": sum(sum(s.cache_misses.values()) for s in stats)}))
"""


def run_workload(shipped: Path, numba_cache: Path | None = None) -> dict:
    """WORKLOAD in a fresh process (numba's own cache: ``numba_cache``, else the source tree's)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    if numba_cache is not None:
        env["NUMBA_CACHE_DIR"] = str(numba_cache)
    run = subprocess.run([sys.executable, "-c", WORKLOAD, str(shipped), str(ROOT / "datasets" / "binocular")],
                         capture_output=True, text=True, timeout=900, env=env, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


def host_runs_target() -> bool:
    import llvmlite.binding as ll

    features = ll.get_host_cpu_features()
    return all(features.get(f, False) for f in kernel_cache.TARGET_FEATURES)


@pytest.fixture(scope="module")
def shipped(wheel: Path, tmp_path_factory) -> Path:
    """The wheel's ari_sfm/_compiled, unpacked (this tree's sources are the wheel's: the entries match them)."""
    out = tmp_path_factory.mktemp("shipped")
    with zipfile.ZipFile(wheel) as zf:
        zf.extractall(out, [n for n in zf.namelist() if n.startswith("ari_sfm/_compiled/")])
    return out / "ari_sfm" / "_compiled"


@pytest.fixture(scope="module")
def shipped_run(shipped: Path, tmp_path_factory) -> dict:
    if not host_runs_target():
        pytest.skip(f"this CPU cannot run {kernel_cache.TARGET_CPU} code")
    return run_workload(shipped, tmp_path_factory.mktemp("empty_numba_cache"))


def test_shipped_kernels_run_without_compiling(shipped_run: dict) -> None:
    """With numba's own cache empty, a calibration, a triangulation and refine-colmap load every kernel from
    the shipped code (kernel_signatures covers their calls)."""
    assert shipped_run["shipped"]
    assert shipped_run["compiled"] == 0
    assert shipped_run["loaded"] >= 10


def test_without_matching_shipped_kernels_numba_compiles_the_same_numbers(shipped: Path, shipped_run: dict,
                                                                          tmp_path: Path) -> None:
    """No shipped folder, one built with another numba, one with a damaged entry: numba's own cache or
    compilation (on this host's CPU) takes over, never an error, and every number is the shipped code's, to
    the last bit."""
    other_numba = shutil.copytree(shipped, tmp_path / "other_numba")
    record = json.loads((other_numba / kernel_cache.TARGET_FILE).read_text())
    (other_numba / kernel_cache.TARGET_FILE).write_text(json.dumps({**record, "numba": "0.0.1"}))
    damaged = shutil.copytree(shipped, tmp_path / "damaged")
    for data in damaged.rglob("*.nbc"):
        data.write_bytes(data.read_bytes()[:100])
    for folder in (tmp_path / "missing", other_numba, damaged):
        run = run_workload(folder)
        assert run["shipped"] == (folder == damaged)
        assert run["loaded"] + run["compiled"] >= 10
        for key in ("calibration", "triangulated", "refined", "refined_points"):
            assert run[key] == shipped_run[key], f"{folder.name}: {key} differs from the shipped kernels'"

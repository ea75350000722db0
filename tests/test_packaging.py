"""The built wheel holds every module of the source tree under the one import root ari_sfm.

The editable install (scripts/setup.sh) maps folders and hides a package the
wheel forgets; this builds the real wheel offline (no build isolation: the
test extras pin setuptools) from a copy of the tree and lists it.
"""
from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = {"ari_sfm": "ari_sfm", "factors": "ari_sfm/factors", "pipelines": "ari_sfm/pipelines"}  # folder -> in wheel


def expected_modules() -> set[str]:
    """Every .py file under the three source folders, as its path inside the wheel."""
    out = set()
    for folder, installed in SOURCES.items():
        for f in (ROOT / folder).rglob("*.py"):
            if "__pycache__" not in f.parts:
                out.add(f"{installed}/{f.relative_to(ROOT / folder).as_posix()}")
    return out


def test_wheel_contains_every_package(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    for folder in SOURCES:
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    run = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "-w", str(tmp_path / "wheel"), "--no-deps",
                          "--no-build-isolation", "-q"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    (wheel,) = (tmp_path / "wheel").glob("ari_sfm-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    py = {n for n in names if n.endswith(".py")}
    expected = expected_modules()
    assert {"ari_sfm/baselines/__init__.py", "ari_sfm/factors/rig_graph.py", "ari_sfm/pipelines/run.py"} <= expected
    assert expected - py == set(), "modules missing from the wheel"
    assert py - expected == set(), "modules in the wheel that are not in the source tree (e.g. a bare factors/)"
    (meta,) = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
    entry = configparser.ConfigParser()
    entry.read_string(zipfile.ZipFile(wheel).read(meta).decode())
    assert entry["console_scripts"]["ari-sfm"] == "ari_sfm.cli:main"

"""Package discovery (all metadata is in pyproject.toml) and the compiled kernels of a built wheel.

Every folder with an ``__init__.py`` under ``ari_sfm/``, ``factors/`` and
``pipelines/`` is a package; the last two install as ``ari_sfm.factors`` and
``ari_sfm.pipelines`` (``[tool.setuptools.package-dir]``), a renaming that
``[tool.setuptools.packages.find]`` cannot express.

``build_py`` then compiles the numba kernels of the built package into
``ari_sfm/_compiled/`` (``python -m ari_sfm.kernel_build``, ~1 min on 2 cores), so that an
installed wheel does not compile on its first run. It needs the package's dependencies in
the building Python (``pip wheel --no-build-isolation``, as .ci/run builds); without them,
or with ``ARI_SFM_NO_KERNEL_BUILD=1``, or for an editable install, the wheel has no compiled
kernels and numba compiles them on first use, as it does for a source tree.
"""
import os
import shutil
import subprocess
import sys
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

PREFIXED = ("factors", "pipelines")  # folders installed under ari_sfm.


class build_py_with_kernels(build_py):
    """build_py, then the compiled kernels of the built package (never a failed build for want of them)."""

    def run(self):
        super().run()
        if getattr(self, "editable_mode", False) or os.environ.get("ARI_SFM_NO_KERNEL_BUILD") or self.dry_run:
            return
        lib = Path(self.build_lib).resolve()
        out = lib / "ari_sfm" / "_compiled"
        shutil.rmtree(out, ignore_errors=True)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(lib), os.environ.get("PYTHONPATH")]))}
        env.pop("NUMBA_DISABLE_JIT", None)
        try:
            done = subprocess.run([sys.executable, "-m", "ari_sfm.kernel_build", str(out)], cwd=lib, env=env,
                                  timeout=1800).returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            done = False
        if not done:
            shutil.rmtree(out, ignore_errors=True)
            print("warning: ari-sfm's kernels were not compiled into the build: numba compiles them on first use",
                  file=sys.stderr)


setup(packages=find_packages(include=["ari_sfm", "ari_sfm.*"])
      + [f"ari_sfm.{p}" for p in find_packages(include=[f"{d}{s}" for d in PREFIXED for s in ("", ".*")])],
      cmdclass={"build_py": build_py_with_kernels})

"""The compiled kernels of a built wheel (all metadata and package discovery are in pyproject.toml).

``build_py`` copies the packages (``ari_sfm/factors`` and ``ari_sfm/pipelines``, symbolic links to
the top-level ``factors/`` and ``pipelines/``, become real folders in the build), then compiles the
numba kernels of the built package into ``ari_sfm/_compiled/`` (``python -m ari_sfm.kernel_build``,
~1 min on 2 cores), so that an installed wheel does not compile on its first run. It needs the package's dependencies in
the building Python (``pip wheel --no-build-isolation``, as .ci/run builds); without them,
or with ``ARI_SFM_NO_KERNEL_BUILD=1``, or for an editable install, the wheel has no compiled
kernels and numba compiles them on first use, as it does for a source tree.
"""
import os
import shutil
import subprocess
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


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


setup(cmdclass={"build_py": build_py_with_kernels})

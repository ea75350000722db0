"""Compile the kernels for the wheel: every signature of :mod:`ari_sfm.kernel_signatures`, for
:data:`~ari_sfm.kernel_cache.TARGET_CPU`, into a folder that ships as ``ari_sfm/_compiled/``.

setup.py runs it when the wheel is built (``python -m ari_sfm.kernel_build BUILD_LIB/ari_sfm/_compiled``
in the build folder, so that the package compiled is the one packed). The process must have numba's
target set before numba is imported; :func:`main` starts itself again with it when it is not.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numba
from numba.core import config
from numba.core.dispatcher import Dispatcher

from . import kernel_cache
from .kernel_signatures import SIGNATURES


@dataclass(frozen=True)
class BuildSummary:
    """What :func:`build` wrote."""
    folder: Path
    kernels: int  # dispatchers compiled
    signatures: int  # signatures compiled (their callees' come with them)
    seconds: float


def target_environment() -> dict[str, str]:
    """numba's environment variables for :data:`~ari_sfm.kernel_cache.TARGET_CPU`."""
    return {"NUMBA_CPU_NAME": kernel_cache.TARGET_CPU, "NUMBA_CPU_FEATURES": kernel_cache.TARGET_CPU_FEATURES}


def build(folder: Path) -> BuildSummary:
    """Compile every signature of SIGNATURES into ``folder``.

    Args:
        folder: where to write the compiled kernels (made if missing; existing entries are replaced).

    Returns:
        A :class:`BuildSummary` of what was written.

    Raises:
        RuntimeError: numba's target is not :data:`~ari_sfm.kernel_cache.TARGET_CPU`, or JIT is disabled.
    """
    # numba.core.config sets its options at run time (from the environment): its stub does not list them
    target = (config.CPU_NAME, config.CPU_FEATURES)  # type: ignore[attr-defined]
    if target != (kernel_cache.TARGET_CPU, kernel_cache.TARGET_CPU_FEATURES):
        raise RuntimeError(f"numba's target is {target[0]!r} {target[1]!r}: set "
                           + " ".join(f"{k}={v!r}" for k, v in target_environment().items()))
    t0 = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    kernels = signatures = 0
    kernel_cache._building = folder
    try:
        for module_name, functions in cast(Mapping[str, Mapping[str, Sequence[Any]]], SIGNATURES).items():
            module = importlib.import_module(module_name)
            for name, sigs in functions.items():
                dispatcher = getattr(module, name)
                if not isinstance(dispatcher, Dispatcher):
                    raise RuntimeError(f"{module_name}.{name} is not compiled (NUMBA_DISABLE_JIT?)")
                for sig in sigs:
                    dispatcher.compile(sig)
                kernels += 1
                signatures += len(sigs)
    finally:
        kernel_cache._building = None
    (folder / kernel_cache.TARGET_FILE).write_text(json.dumps(kernel_cache.target_record(), indent=1) + "\n")
    return BuildSummary(folder, kernels, signatures, time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ari_sfm.kernel_build", description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path, help="where to write the compiled kernels (ari_sfm/_compiled of a build)")
    args = ap.parse_args(argv)
    env = target_environment()
    if any(os.environ.get(k) != v for k, v in env.items()):  # numba read its target at import: start again
        return subprocess.run([sys.executable, "-m", __spec__.name, str(args.folder)],
                              env={**os.environ, **env}).returncode
    summary = build(args.folder.resolve())
    print(f"ari_sfm.kernel_build: {summary.signatures} signatures of {summary.kernels} kernels compiled for "
          f"{kernel_cache.TARGET_CPU} (numba {numba.__version__}) in {summary.seconds:.0f} s -> {summary.folder}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

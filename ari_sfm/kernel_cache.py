"""The compiled kernels shipped in the wheel: numba's on-disk cache written once when the wheel is built
(:mod:`ari_sfm.kernel_build`) and read before numba's own, so that a fresh install does not compile.

Every compiled kernel module decorates with :func:`njit` from here: numba's ``njit``, whose dispatcher
(with ``cache=True``) gets a :class:`ShippedCache`. Loading a signature, it looks first in
``ari_sfm/_compiled/`` (:data:`SHIPPED_DIR`: in a built wheel, or compiled into a source tree by
``scripts/setup.sh``), then in numba's own cache (``NUMBA_CACHE_DIR``, else ``__pycache__`` beside the
module, else ``~/.cache/numba``), and only then compiles; what it compiles goes to numba's own cache.

The wheel's code is compiled for :data:`TARGET_CPU` (the x86-64-v3 level: AVX2, FMA, BMI2, every x86-64 CPU
since 2013-2015) with LLVM's own feature set for it, so it runs on any host that has those features; the
shipped entries carry that CPU in their key, and :class:`ShippedCache` asks for it instead of the host's.
Another architecture or OS (the process triple), a CPU without one of :data:`TARGET_FEATURES`, another
numba, llvmlite or Python version (:func:`target_record`), a changed source file, or a target the user
chose (``NUMBA_CPU_NAME``, ``NUMBA_CPU_FEATURES``, ``NUMBA_ENABLE_AVX=0``): the shipped code is not used
and numba compiles (``ari-sfm -v`` logs which). Never an error: a shipped entry that fails to load is
skipped (logged at debug level).

The numbers do not depend on the target: calibrations from the shipped code and from a host-compiled run
are the same to the last bit.
"""
from __future__ import annotations

import functools
import json
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
from numba.core import config
from numba.core.caching import FunctionCache, IndexDataCacheFile
from numba.core.dispatcher import Dispatcher

log = logging.getLogger(__name__)

SHIPPED_DIR = Path(__file__).with_name("_compiled")  # written by ari_sfm.kernel_build when the wheel is built
TARGET_FILE = "target.json"  # in SHIPPED_DIR: the versions and target it was compiled with
TARGET_CPU = "x86-64-v3"  # LLVM's name of the x86-64 psABI level 3
TARGET_CPU_FEATURES = ""  # LLVM's own features of TARGET_CPU (numba's NUMBA_CPU_FEATURES="")
# What the host needs for TARGET_CPU's code, in LLVM's feature names (llvmlite's get_host_cpu_features):
# x86-64-v1 (cmov cx8 fxsr mmx sse sse2), v2 (cx16 sahf popcnt sse3 ssse3 sse4.1 sse4.2) and v3's own
# (avx avx2 bmi bmi2 f16c fma lzcnt movbe xsave).
TARGET_FEATURES = ("64bit", "cmov", "cx8", "fxsr", "mmx", "sse", "sse2", "cx16", "sahf", "popcnt", "sse3",
                   "ssse3", "sse4.1", "sse4.2", "avx", "avx2", "bmi", "bmi2", "f16c", "fma", "lzcnt", "movbe",
                   "xsave")

_building: Path | None = None  # set by ari_sfm.kernel_build: compile everything, save into this folder


def njit(func: Callable | None = None, /, **options: Any) -> Any:
    """numba's ``njit`` (same options); with ``cache=True`` the dispatcher's cache is a :class:`ShippedCache`.

    Usable bare (``@njit``) or with options (``@njit(cache=True, ...)``).

    Args:
        func: the function to compile; None when called with options only.
        options: numba's ``njit`` options.

    Returns:
        The dispatcher, or (without ``func``) the decorator that makes it.
    """
    def decorate(f: Callable) -> Any:
        dispatcher = numba.njit(**options)(f)
        if options.get("cache") and isinstance(dispatcher, Dispatcher):  # NUMBA_DISABLE_JIT: the Python function
            dispatcher._cache = ShippedCache(f)  # type: ignore[attr-defined]  # numba's own attribute, unlisted
        return dispatcher
    return decorate if func is None else decorate(func)


def target_record() -> dict[str, str]:
    """What the shipped code is compiled for: the versions and the target.

    The build writes it to :data:`TARGET_FILE`; at run time a record that differs from this process's means
    the shipped code is not used.

    Returns:
        The numba, llvmlite and Python versions, the process triple, the CPU and its features, by name.
    """
    import llvmlite
    import llvmlite.binding as ll

    return {"numba": numba.__version__, "llvmlite": llvmlite.__version__,
            "python": f"{sys.version_info[0]}.{sys.version_info[1]}{getattr(sys, 'abiflags', '')}",
            "triple": ll.get_process_triple(), "cpu": TARGET_CPU, "cpu_features": TARGET_CPU_FEATURES}


@functools.cache
def shipped_usable() -> tuple[bool, str]:
    """Whether this process can run the shipped code, and what it runs or why not (once per process)."""
    usable, why = _shipped_usable()
    log.info("compiled kernels: %s", why if usable else f"compiled on first use ({why})")
    return usable, why


def _shipped_usable() -> tuple[bool, str]:
    if _building is not None:
        return False, "building it"
    # numba.core.config sets its options at run time (from the environment): its stub does not list them
    if config.CPU_NAME is not None or config.CPU_FEATURES is not None or not config.ENABLE_AVX:  # type: ignore[attr-defined]
        return False, "the compilation target is set (NUMBA_CPU_NAME, NUMBA_CPU_FEATURES or NUMBA_ENABLE_AVX)"
    try:
        built = json.loads((SHIPPED_DIR / TARGET_FILE).read_text())
    except (OSError, ValueError):
        return False, f"no shipped compiled kernels ({SHIPPED_DIR / TARGET_FILE})"
    if built != target_record():
        return False, f"compiled for {built}, this is {target_record()}"
    import llvmlite.binding as ll

    try:
        features = ll.get_host_cpu_features()
    except RuntimeError:
        return False, "the host CPU's features are unknown"
    missing = [f for f in TARGET_FEATURES if not features.get(f, False)]
    if missing:
        return False, f"this CPU lacks {', '.join(missing)} of {TARGET_CPU}"
    return True, f"{TARGET_CPU} code from {SHIPPED_DIR}"


class ShippedCache(FunctionCache):
    """numba's per-function cache, with the shipped entries (:data:`SHIPPED_DIR`) read first and, while
    :mod:`ari_sfm.kernel_build` runs, written there instead."""

    def __init__(self, py_func: Callable) -> None:
        super().__init__(py_func)
        self._shipped_files: dict[Path, IndexDataCacheFile] = {}

    def _shipped(self, folder: Path) -> IndexDataCacheFile:
        """The index and data files of this function in ``folder``'s subfolder for its module."""
        if folder not in self._shipped_files:
            self._shipped_files[folder] = IndexDataCacheFile(cache_path=str(folder / self._py_func.__module__),
                                                             filename_base=self._impl.filename_base,
                                                             source_stamp=self._impl.locator.get_source_stamp())
        return self._shipped_files[folder]

    def _shipped_key(self, sig, codegen) -> tuple:
        """The key the build wrote for ``sig``: numba's, with the target's CPU in place of the host's."""
        sig_key, magic, code_hashes = self._index_key(sig, codegen)
        return sig_key, (magic[0], TARGET_CPU, TARGET_CPU_FEATURES), code_hashes

    def load_overload(self, sig, target_context):
        if _building is not None:
            return None  # the build compiles every signature afresh
        if shipped_usable()[0]:
            target_context.refresh()
            try:
                data = self._shipped(SHIPPED_DIR).load(self._shipped_key(sig, target_context.codegen()))
                if data is not None:
                    return self._impl.rebuild(target_context, data)
            except Exception as exc:  # a damaged or foreign entry: numba's own cache, else a compilation
                log.debug("shipped %s %s not loaded: %s", self._py_func.__qualname__, sig, exc)
        return super().load_overload(sig, target_context)

    def save_overload(self, sig, data):
        if _building is None:
            return super().save_overload(sig, data)
        if data.codegen.magic_tuple()[1:] != (TARGET_CPU, TARGET_CPU_FEATURES):
            raise RuntimeError(f"building the shipped kernels for {data.codegen.magic_tuple()}, not {TARGET_CPU}: "
                               f"run with NUMBA_CPU_NAME={TARGET_CPU} NUMBA_CPU_FEATURES={TARGET_CPU_FEATURES!r}")
        if self._impl.check_cachable(data):
            (_building / self._py_func.__module__).mkdir(parents=True, exist_ok=True)
            self._shipped(_building).save(self._index_key(sig, data.codegen), self._impl.reduce(data))

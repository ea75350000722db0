"""Optional heavy dependencies, imported with one clear message when they cannot load."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from .errors import AriSfmError


def _interrupted(exc: BaseException) -> bool:
    """True if a KeyboardInterrupt is in the cause / context chain of ``exc``."""
    seen: set[int] = set()
    link: BaseException | None = exc
    while link is not None and id(link) not in seen:
        if isinstance(link, KeyboardInterrupt):
            return True
        seen.add(id(link))
        link = link.__cause__ or link.__context__
    return False


def require_open3d():
    """Import open3d, or fail in one line naming the missing system library.

    A Ctrl-C while open3d's extension initialises is re-raised as KeyboardInterrupt (the CLI prints
    "interrupted", exit 130), not reported as a missing package; "not installed" only when no open3d
    package is found.

    Returns:
        The open3d module.

    Raises:
        AriSfmError: open3d is not installed, or is installed but cannot load (e.g. libusb-1.0 missing).
        KeyboardInterrupt: interrupted while open3d loaded.
    """
    import importlib.util

    try:
        import open3d
    except OSError as exc:  # e.g. libusb-1.0.so.0: cannot open shared object file
        if _interrupted(exc):
            raise KeyboardInterrupt from None
        raise AriSfmError(
            "open3d", f"cannot load ({exc}); install the system library: apt-get install libusb-1.0-0"
        ) from None
    except ImportError as exc:
        if _interrupted(exc):
            raise KeyboardInterrupt from None
        try:
            found = importlib.util.find_spec("open3d") is not None
        except (ValueError, ImportError):  # sys.modules["open3d"] is None or has no spec
            found = False
        if found:
            raise AriSfmError("open3d", f"installed but cannot load ({exc})") from None
        raise AriSfmError("open3d", f"not installed ({exc}); run scripts/setup.sh") from None
    return open3d


def import_pycolmap(min_version: tuple[int, int] = (3, 11)) -> Any:
    """Import pycolmap, keeping Python's SIGTERM handler.

    SIGINT and SIGTERM are blocked while the import runs and until Python's handlers are back; a signal
    arriving in between is delivered to Python's handler afterwards, not to glog's.

    Args:
        min_version: the (major, minor) pycolmap version named in the error message.

    Returns:
        The pycolmap module.

    Raises:
        ImportError: pycolmap cannot be imported.
    """
    import signal
    import threading

    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGTERM) if main else None
    held = {signal.SIGINT, signal.SIGTERM}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, held) if main else None
    try:
        import pycolmap
    except ImportError as exc:  # pragma: no cover - pycolmap is a dependency
        raise ImportError(f"ari-sfm needs pycolmap >= {min_version[0]}.{min_version[1]} "
                          f"(pip install pycolmap): {exc}") from exc
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if mask is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a pending signal reaches Python's handler now
    return pycolmap


@dataclass(frozen=True)
class Dependency:
    """One library ari-sfm rests on, as ``ari-sfm doctor`` found it.

    Attributes:
        name: the name a user installs it by (pip's, or the system library's for libusb).
        version: its version when it loaded, else None.
        error: why it did not load (one line), else None.
        optional: not needed by ari-sfm itself (``optv``: OpenPTV's library, for the benchmarks).
        purpose: what ari-sfm uses it for.
    """

    name: str
    version: str | None
    error: str | None
    optional: bool
    purpose: str

    @property
    def ok(self) -> bool:
        return self.error is None


# (install name, import name, purpose, optional): every dependency of pyproject.toml, and the optional optv
DEPENDENCIES: tuple[tuple[str, str, str, bool], ...] = (
    ("numpy", "numpy", "arrays", False),
    ("scipy", "scipy", "least squares, KD-trees", False),
    ("numba", "numba", "the compiled physics", False),
    ("opencv", "cv2", "detection, Zhang, PnP", False),
    ("gtsam", "gtsam", "the factor graph", False),
    ("pycolmap", "pycolmap", "COLMAP models, sfm", False),
    ("open3d", "open3d", "reconstruction metrics, references (needs libusb-1.0-0)", False),
    ("pyyaml", "yaml", "rig.yaml, --config", False),
    ("click", "click", "the command line", False),
    ("tqdm", "tqdm", "progress bars", False),
    ("matplotlib", "matplotlib", "the report's figures", False),
    ("pyarrow", "pyarrow", "particle tables (parquet)", False),
    ("dask", "dask", "frames on a cluster", False),
    ("distributed", "distributed", "dask's scheduler and workers", False),
    ("plotly", "plotly", "the report's 3D view", False),
    ("optv", "optv", "OpenPTV's library: benchmarks beside OpenPTV (pip install optv)", True),
)


def _version(install_name: str, module: Any) -> str:
    """The installed distribution's version (gtsam has no ``__version__``; cv2's comes from
    opencv-contrib-python-headless), else the module's ``__version__``."""
    from importlib import metadata

    import_name = getattr(module, "__name__", install_name)
    for dist in (install_name, *metadata.packages_distributions().get(import_name, [])):
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            continue
    version = getattr(module, "__version__", None)
    return version if isinstance(version, str) and version else "installed (version unknown)"


def _load(install_name: str, import_name: str) -> Any:
    if import_name == "open3d":
        return require_open3d()
    if import_name == "pycolmap":
        return import_pycolmap()  # without glog's SIGTERM handler
    import importlib

    return importlib.import_module(import_name)


def check_dependencies() -> list[Dependency]:
    """Import every library ari-sfm rests on (and the optional ones): each one's version, or why it fails."""
    out = []
    for name, import_name, purpose, optional in DEPENDENCIES:
        try:
            module = _load(name, import_name)
            out.append(Dependency(name, _version(name, module), None, optional, purpose))
        except AriSfmError as exc:
            out.append(Dependency(name, None, exc.message, optional, purpose))
        except Exception as exc:  # noqa: BLE001 - report every failure in one line
            what = "not installed" if isinstance(exc, ModuleNotFoundError) else f"{type(exc).__name__}: {exc}"
            out.append(Dependency(name, None, " ".join(what.split()), optional, purpose))
    return out

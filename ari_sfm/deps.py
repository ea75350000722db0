"""Optional heavy dependencies, imported with one clear message when they cannot load."""
from __future__ import annotations

from typing import Any

from .errors import AriSfmError


def _interrupted(exc: BaseException) -> bool:
    """True if a KeyboardInterrupt is in the cause / context chain of ``exc``."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def require_open3d():
    """Import open3d, or fail in one line naming the missing system library.

    Ctrl-C while open3d's extension initialises surfaces as ImportError
    ('initialization failed') with the KeyboardInterrupt as its context: that is
    re-raised as KeyboardInterrupt (the CLI prints "interrupted", exit 130), not
    reported as a missing package; "not installed" only when no open3d package is found.
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
    """Import pycolmap, keeping Python's SIGTERM handler: pycolmap installs glog's failure-signal handler,
    which answers a plain SIGTERM with a native stack dump (and so does not let the CLI leave cleanly).
    SIGINT and SIGTERM are blocked while the import runs and Python's handlers are back, so that one
    arriving in between is delivered to Python's handler afterwards, not to glog's."""
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


def check_dependencies() -> dict[str, str]:
    """Versions of the libraries ari-sfm rests on, or the one-line reason one fails."""
    out = {}
    for name in ("numpy", "scipy", "cv2", "gtsam", "pycolmap", "open3d", "yaml", "matplotlib"):
        try:
            if name == "open3d":
                mod = require_open3d()
            elif name == "pycolmap":
                mod = import_pycolmap()  # without glog's SIGTERM handler
            else:
                mod = __import__(name)
            out[name] = getattr(mod, "__version__", "installed")
        except AriSfmError as exc:
            out[name] = f"error: {exc}"
        except Exception as exc:  # noqa: BLE001 - report every failure in one line
            out[name] = f"error: {type(exc).__name__}: {exc}"
    return out

"""Optional heavy dependencies, imported with one clear message when they cannot load."""
from __future__ import annotations

from .errors import AriSfmError


def require_open3d():
    """Import open3d, or fail in one line naming the missing system library."""
    try:
        import open3d
    except OSError as exc:  # e.g. libusb-1.0.so.0: cannot open shared object file
        raise AriSfmError(
            "open3d", f"cannot load ({exc}); install the system library: apt-get install libusb-1.0-0"
        ) from None
    except ImportError as exc:
        raise AriSfmError("open3d", f"not installed ({exc}); run scripts/setup.sh") from None
    return open3d


def check_dependencies() -> dict[str, str]:
    """Versions of the libraries ari-sfm rests on, or the one-line reason one fails."""
    out = {}
    for name in ("numpy", "scipy", "cv2", "gtsam", "pycolmap", "open3d", "yaml", "matplotlib"):
        try:
            if name == "open3d":
                mod = require_open3d()
            else:
                mod = __import__(name)
            out[name] = getattr(mod, "__version__", "installed")
        except AriSfmError as exc:
            out[name] = f"error: {exc}"
        except Exception as exc:  # noqa: BLE001 - report every failure in one line
            out[name] = f"error: {type(exc).__name__}: {exc}"
    return out

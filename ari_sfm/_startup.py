"""Ctrl-C and SIGTERM while the command line is still loading its libraries.

``ari-sfm`` imports its libraries before any command installs its signal handlers
(``cli.user_errors``). Only when this process is the command line (the ``ari-sfm`` script or
``python -m ari_sfm``), :func:`guard_loading` makes a signal in that window print
"interrupted" / "terminated" and exit 130 / 143 at once (nothing is written
yet); :func:`loaded` puts the previous handlers back when the CLI is loaded.
A library import (``import ari_sfm`` in a script) is never touched.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Callable
    from types import FrameType
    from typing import Any

_previous: dict[int, Callable[[int, FrameType | None], Any] | int | None] = {}


def is_command_line() -> bool:
    """True when this interpreter runs the ari-sfm command line."""
    if sys.argv and os.path.basename(sys.argv[0]) == "ari-sfm":
        return True
    argv = list(getattr(sys, "orig_argv", []))
    return "-m" in argv[:-1] and argv[argv.index("-m") + 1] in ("ari_sfm", "ari_sfm.cli")


def leave(signum: int, frame) -> None:
    """Leave at once with the signal's exit code (130 for SIGINT, 143 for SIGTERM).

    Safe while the libraries load (nothing has been written yet) and after a command
    (:func:`ari_sfm.cli.process.user_errors`: everything has been written).

    Args:
        signum: the signal received.
        frame: the interrupted frame (unused; a signal handler's signature).
    """
    os.write(2, b"interrupted\n" if signum == signal.SIGINT else b"terminated\n")
    os._exit(130 if signum == signal.SIGINT else 143)


def guard_loading() -> None:
    """Install :func:`leave` for SIGINT and SIGTERM while the command line loads (a signal ignored by the
    parent, ``cmd &``, stays ignored)."""
    if _previous or threading.current_thread() is not threading.main_thread() or not is_command_line():
        return
    for signum in (signal.SIGINT, signal.SIGTERM):
        handler = signal.getsignal(signum)
        if handler is not signal.SIG_IGN and handler is not None:
            _previous[signum] = handler
            signal.signal(signum, leave)


def loaded() -> None:
    """The command line is loaded: the handlers from before :func:`guard_loading` again."""
    while _previous:
        signum, handler = _previous.popitem()
        signal.signal(signum, handler)

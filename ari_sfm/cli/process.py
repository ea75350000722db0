"""How a command runs in its process: the log levels (ours, Dask's, glog's), SIGINT and SIGTERM turned into
"interrupted" (130) and "terminated" (143), every error as one line ``error: <file>: <what is wrong>``
(exit 1), and the command line's own exit (:class:`CommandGroup`)."""
from __future__ import annotations

import errno
import functools
import logging
import os
import signal
import sys
import threading
from typing import TYPE_CHECKING

import click

from .. import _startup
from ..errors import AriSfmError
from .config import blame_config

if TYPE_CHECKING:
    from collections.abc import Callable
    from types import FrameType
    from typing import Any

    Handler = Callable[[int, FrameType | None], Any] | int | None  # what signal.getsignal returns


QUALITY_FAILED_EXIT = 3  # the calibration was written but failed its quality gate (ari_sfm.calibration.quality)


def setup_logging(verbose: bool) -> None:
    """Set the log level: warnings and errors, or with -v progress messages too.

    The same level is set for Dask (distributed logs its cluster's start and stop at INFO, in this process
    and in a LocalCluster's workers) and glog (pycolmap): through the environment they read when they load
    (workers inherit it), and their levels if loaded.

    Args:
        verbose: log progress messages (INFO) too.
    """
    level = logging.INFO if verbose else logging.WARNING
    logging.basicConfig(level=level, format="%(levelname)s: %(message)s")
    os.environ["DASK_LOGGING__DISTRIBUTED"] = "info" if verbose else "warning"
    os.environ["GLOG_minloglevel"] = "0" if verbose else "1"
    if "distributed" in sys.modules:
        logging.getLogger("distributed").setLevel(level)
    pycolmap = sys.modules.get("pycolmap")
    if pycolmap is not None and hasattr(getattr(pycolmap, "logging", None), "minloglevel"):
        pycolmap.logging.minloglevel = 0 if verbose else 1


class Terminated(BaseException):
    """SIGTERM, raised in the main thread by the CLI's handler (a BaseException, as KeyboardInterrupt: no
    ``except Exception`` of a library swallows it), so atomic writes drop their temporary files."""


_signalled: list[int] = []  # the signals received while the current command ran (SIGINT, SIGTERM)


def _on_signal(signum: int, frame) -> None:
    """SIGINT -> KeyboardInterrupt, SIGTERM -> Terminated, both remembered in ``_signalled``: an exception a
    library turns the interrupt into (open3d's extension init: ImportError 'initialization failed', sometimes
    without the interrupt as its context) is still reported as the interrupt it is."""
    _signalled.append(signum)
    raise KeyboardInterrupt if signum == signal.SIGINT else Terminated


def _install_signal_handlers() -> dict[signal.Signals, Handler] | None:
    """Install :func:`_on_signal` for SIGINT and SIGTERM (main thread only); the previous handlers, or None.
    A SIGINT ignored by the parent (``cmd &`` in a non-interactive shell) stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    _signalled.clear()
    sys.unraisablehook = _unraisable
    for signum, handler in previous.items():
        if handler is not signal.SIG_IGN:
            signal.signal(signum, _on_signal)
    return previous


def _unraisable(args) -> None:
    """A signal whose exception was raised inside a C callback (numba's compiler caching an object) cannot
    propagate there: Python would print it as "Exception ignored ... Traceback". It is already in
    ``_signalled``; :func:`user_errors` acts on it when the command returns."""
    if isinstance(args.exc_value, (KeyboardInterrupt, Terminated)):
        return
    sys.__unraisablehook__(args)


def _restore_signal_handlers(previous: dict[signal.Signals, Handler] | None) -> None:
    """The handlers from before the command; on the command line, where those are the defaults, a signal
    after the command (the interpreter's shutdown) leaves at once with "terminated"/143 or
    "interrupted"/130 (:func:`ari_sfm._startup.leave`): its results are written, and the default SIGTERM
    would end the process as killed (-15)."""
    sys.unraisablehook = sys.__unraisablehook__
    command_line = _startup.is_command_line()
    for signum, handler in (previous or {}).items():
        if handler is None:
            continue
        if command_line and handler in (signal.SIG_DFL, signal.default_int_handler):
            handler = _startup.leave
        signal.signal(signum, handler)


def _exit_interrupted(exit=sys.exit, terminated: bool = False) -> None:
    """Ctrl-C: "interrupted" on stderr and exit 130; SIGTERM: "terminated" and exit 143. While worker threads
    are still inside OpenCV (a pool cut short by the signal), leave at once: the interpreter's shutdown would
    wait for them, and a second Ctrl-C during that wait ended the process in C++'s terminate (SIGABRT).
    By then every atomic write has dropped its temporary file (the exception unwound through it)."""
    code = 143 if terminated else 130
    _signalled.clear()  # acted on: the SystemExit below is not a second interrupt
    click.echo("terminated" if terminated else "interrupted", err=True)
    me = threading.current_thread()
    # The command line itself leaves at once too: a native library cut short while loading (open3d) ran
    # its C++ destructors at the interpreter's exit and turned 130 into 1.
    if _startup.is_command_line() or any(t.is_alive() and not t.daemon and t is not me
                                         for t in threading.enumerate()):
        if me is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    exit(code)


def exit_if_signalled() -> None:
    """Leave as interrupted or terminated when a signal arrived while the command ran and a library turned it
    into something else (an error of its own, or nothing: swallowed inside a C callback)."""
    if _signalled:
        _exit_interrupted(terminated=_signalled[-1] == signal.SIGTERM)


def user_errors(fn):
    """Wrap a command so that errors and signals end it in one line.

    AriSfmError (and any unexpected exception) becomes one line on stderr and exit 1; Ctrl-C
    "interrupted" (exit 130) and SIGTERM "terminated" (exit 143), also when a library turned the
    signal into an error of its own. Set ARI_SFM_DEBUG=1 for an unexpected exception's traceback.

    Args:
        fn: the command's function.

    Returns:
        The wrapped function.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        previous = _install_signal_handlers()
        try:
            result = fn(*args, **kwargs)
            exit_if_signalled()  # swallowed inside a C callback (see _unraisable): the command ran to its end
            return result
        except KeyboardInterrupt:  # Ctrl-C: no traceback, the shell's code for SIGINT
            _exit_interrupted()
        except Terminated:
            _exit_interrupted(terminated=True)
        except (click.ClickException, click.exceptions.Exit, SystemExit):
            exit_if_signalled()  # the command ended on its own after a library swallowed the signal
            raise
        except Exception as exc:  # noqa: BLE001 - never a traceback unless asked for
            exit_if_signalled()  # the signal surfaced as another error (e.g. inside a native import)
            if isinstance(exc, AriSfmError):
                click.echo(f"error: {blame_config(exc)}", err=True)
                sys.exit(1)
            if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EPIPE, errno.EIO, errno.EDQUOT):
                # the results are written (atomically); what failed is writing the summary to a full or closed
                # stdout (`> /dev/full`), or a file a library wrote without naming it
                where = exc.filename or "standard output"
                click.echo(f"error: {where}: cannot write: {exc.strerror or exc}", err=True)
                sys.exit(1)
            if os.environ.get("ARI_SFM_DEBUG"):
                raise
            click.echo(f"error: {type(exc).__name__}: {exc} (set ARI_SFM_DEBUG=1 for the traceback)", err=True)
            sys.exit(1)
        finally:
            _restore_signal_handlers(previous)

    return wrapper


def _leave_process(code: object) -> None:
    """End the command line's process with ``code`` (as ``sys.exit`` would) without the interpreter's own
    shutdown: that resets the signal handlers to the defaults before it ends, and a SIGTERM arriving then
    killed the process (-15) after a complete run. The exit handlers (atexit: logging, multiprocessing,
    Dask) run first, under the command line's handlers ("terminated", 143)."""
    import atexit

    if code is None:
        code = 0
    elif not isinstance(code, int):
        click.echo(code, err=True)
        code = 1
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


class CommandGroup(click.Group):
    """The root group: Ctrl-C outside a command's body (parsing, `scenarios`) also prints "interrupted"
    and exits 130, where click would print "Aborted!" and exit 1. On the command line the process ends
    explicitly once the command is done (:func:`_leave_process`)."""

    def main(self, *args: Any, **kwargs: Any) -> Any:
        if not _startup.is_command_line() or kwargs.get("standalone_mode") is False:
            return super().main(*args, **kwargs)
        try:
            super().main(*args, **kwargs)
            code: object = 0
        except SystemExit as exc:
            code = exc.code
        _leave_process(code)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            _exit_interrupted(ctx.exit)
        except Terminated:
            _exit_interrupted(ctx.exit, terminated=True)

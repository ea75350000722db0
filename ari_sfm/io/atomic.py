"""Atomic file writes: a reader sees the old file or the new one, never half of one.

The text goes to a temporary file in the target's directory, is flushed and
fsynced, then ``os.replace`` swaps it in. On any exception the temporary file
is removed and the target is left as it was.
"""
from __future__ import annotations

import errno
import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path, PurePath
from types import ModuleType
from typing import Any

import numpy as np

from ari_sfm.errors import AriSfmError


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_current_umask()  # what open() would give a new file


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write text (UTF-8) to a file atomically, creating missing parent folders.

    Keeps the mode of an existing file.

    Args:
        path: the file to write.
        text: its new content.

    Raises:
        AriSfmError: the file cannot be written (``path`` is left as it was).
    """
    if not isinstance(text, str):
        raise TypeError(f"write_text_atomic needs str, got {type(text).__name__}")
    write_bytes_atomic(path, text.encode("utf-8"))


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """Write bytes (e.g. a PNG) to a file atomically, as :func:`write_text_atomic` does.

    Args:
        path: the file to write.
        data: its new content.

    Raises:
        AriSfmError: the file cannot be written (``path`` is left as it was).
    """
    with replaced_atomically(path) as tmp, open(tmp, "wb") as f:
        f.write(data)


@contextmanager
def replaced_atomically(path: str | Path) -> Iterator[Path]:
    """Give a writer that streams into a path of its own (pyarrow's ParquetWriter) a temporary file.

    When the block ends the temporary file is fsynced and renamed over ``path``; on any exception or
    interrupt it is removed and ``path`` is left as it was.

    Args:
        path: the file to write.

    Yields:
        The temporary file's path, beside ``path``.

    Raises:
        AriSfmError: an OSError while preparing, writing or renaming, naming ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        mode = path.stat().st_mode & 0o7777 if path.exists() else _FILE_MODE
        fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.close(fd)
    except OSError as exc:
        raise AriSfmError(path, f"cannot write file: {exc.strerror or exc}") from None
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise AriSfmError(path, f"cannot write file: {exc.strerror or exc}") from None
        raise
    _fsync_dir(path.parent)


def _fsync_dir(folder: Path) -> None:
    """Make the rename durable (POSIX); a no-op where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def to_jsonable(obj: Any, where: str = "", string_keys: bool = True) -> Any:
    """Turn numpy arrays and scalars, tuples and paths into JSON types.

    Args:
        obj: the value to convert (mappings and lists are converted recursively).
        where: the key path of ``obj``, for error messages ("" at the top level).
        string_keys: turn integer mapping keys into strings; False keeps them (YAML).

    Returns:
        ``obj`` made of JSON types only.

    Raises:
        AriSfmError: a NaN or an infinity (path None; the message names its key path).
        TypeError: an object JSON cannot hold, or a non-string, non-integer key.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        value = float(obj)
        if not math.isfinite(value):
            raise AriSfmError(None, f"cannot write {value} at {where or 'top level'} (JSON has no NaN or infinity)")
        return value
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "biuf" and obj.ndim in (1, 2):
            if obj.dtype.kind == "f" and not np.isfinite(obj).all():
                index = np.unravel_index(int(np.argmin(np.isfinite(obj))), obj.shape)
                return to_jsonable(float(obj[index]), where + "".join(f"[{i}]" for i in index))
            return _NumberBlock(obj.tolist())
        return to_jsonable(obj.tolist(), where, string_keys)
    if isinstance(obj, PurePath):
        return obj.as_posix()
    if isinstance(obj, Mapping):
        out = {}
        for key, value in obj.items():
            if isinstance(key, (np.integer, int)) and not isinstance(key, bool):
                key = str(int(key)) if string_keys else int(key)
            elif not isinstance(key, str):
                raise TypeError(f"JSON keys must be strings, got {key!r} at {where or 'top level'}")
            out[key] = to_jsonable(value, f"{where}.{key}" if where else str(key), string_keys)
        return out
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v, f"{where}[{i}]", string_keys) for i, v in enumerate(obj)]
    raise TypeError(f"object of type {type(obj).__name__} at {where or 'top level'} is not JSON serializable")


class _NumberBlock(list):
    """A 1-D or 2-D list of finite numbers (from an array): formatted in one C-level dump."""


def format_json(obj: Any, indent: int = 2) -> str:
    """Format JSON-native data as indented JSON; lists of numbers stay on one line.

    A K matrix or a pixel list prints one row per line. Floats keep full precision (the shortest repr
    that reads back exactly).

    Args:
        obj: the data, of JSON types (see :func:`to_jsonable`).
        indent: spaces per level.

    Returns:
        The JSON text, ending with a newline.
    """
    return _format(obj, 0, indent) + "\n"


def _is_scalar(v: Any) -> bool:
    return v is None or isinstance(v, (bool, int, float, str))


def _format(obj: Any, level: int, indent: int) -> str:
    pad, inner = " " * (indent * level), " " * (indent * (level + 1))
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{inner}{json.dumps(k)}: {_format(v, level + 1, indent)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, _NumberBlock):
        text = json.dumps(obj, allow_nan=False)
        if not obj or not isinstance(obj[0], list):
            return text
        return "[\n" + inner + text[1:-1].replace("], [", "],\n" + inner + "[") + "\n" + pad + "]"
    if isinstance(obj, list):
        if all(_is_scalar(v) for v in obj):
            return "[" + ", ".join(json.dumps(v, allow_nan=False) for v in obj) + "]"
        items = [inner + _format(v, level + 1, indent) for v in obj]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return json.dumps(obj, allow_nan=False)


def write_json_atomic(path: str | Path, obj: Any) -> None:
    """Write data as indented JSON, atomically (see :func:`write_text_atomic`).

    numpy arrays and scalars are converted. On an error nothing is written.

    Args:
        path: the file to write.
        obj: the data.

    Raises:
        AriSfmError: a NaN or infinity (naming the file and the key), or the file cannot be written.
        TypeError: an object JSON cannot hold.
    """
    try:
        text = format_json(to_jsonable(obj))
    except AriSfmError as exc:
        raise AriSfmError(path, exc.message) from None
    write_text_atomic(path, text)


def write_files_atomic(out_dir: str | Path, writer: Callable[[Path], None],
                       check: Callable[[Path], None] | None = None) -> list[Path]:
    """Let a native writer put files in a folder (a COLMAP model, a .ply), each complete or not there at all.

    The writer writes into a fresh temporary folder inside ``out_dir``; then each file is fsynced and
    renamed into ``out_dir``, replacing an older one. On any failure or interrupt the temporary folder is
    removed and ``out_dir`` keeps its old files.

    Args:
        out_dir: the folder to write into (created if needed).
        writer: called with the temporary folder; writes the files there.
        check: called with the temporary folder after the writer (e.g. reading the model back); may raise
            to reject what was written (a full disk that the writer did not report). None: no check.

    Returns:
        The paths written in ``out_dir``.

    Raises:
        AriSfmError: an OSError while writing, naming ``out_dir``.
    """
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=out_dir, prefix=".partial-"))
    except OSError as exc:
        raise AriSfmError(out_dir, f"cannot write in this folder: {exc.strerror or exc}") from None
    try:
        try:
            writer(tmp)
            if check is not None:
                check(tmp)
            names = sorted(p.name for p in tmp.iterdir() if p.is_file())
            for name in names:
                with open(tmp / name, "rb") as f:
                    os.fsync(f.fileno())
        except OSError as exc:
            raise AriSfmError(out_dir, f"cannot write the files: {exc.strerror or exc}") from None
        written = []
        with _signals_held():  # Ctrl-C or SIGTERM waits until every file is in place: all old or all new
            for name in names:
                os.replace(tmp / name, out_dir / name)
                written.append(out_dir / name)
        _fsync_dir(out_dir)
        return written
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


class _signals_held:
    """Block SIGINT and SIGTERM for a few renames (main thread, POSIX); they are delivered on leaving."""

    def __enter__(self) -> None:
        import signal
        import threading

        self.mask = None
        if hasattr(signal, "pthread_sigmask") and threading.current_thread() is threading.main_thread():
            self.mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})

    def __exit__(self, *exc: object) -> None:
        import signal

        if self.mask is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, self.mask)


def _fcntl() -> ModuleType | None:
    """POSIX's fcntl (file locks); None where the platform has none."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        return None
    return fcntl


class exclusive_folder:
    """A command's hold on its output folder (``with exclusive_folder(out, "-o/--out"):``).

    A second command writing into the same folder at the same time is refused with an
    :class:`~ari_sfm.errors.AriSfmError`. The hold is an advisory lock on the folder itself (flock; no lock
    file), released when the command ends, also when it is killed. The folder is created if needed;
    ``created`` says whether it was (a failed command removes it again when it is still empty).
    """

    def __init__(self, out: str | Path, option: str = "-o/--out") -> None:
        self.out, self.option = Path(out), option
        self.fd: int | None = None
        self.created = False

    def __enter__(self) -> exclusive_folder:
        fcntl = _fcntl()
        try:
            self.created = not self.out.exists()
            self.out.mkdir(parents=True, exist_ok=True)
            self.fd = os.open(self.out, os.O_RDONLY)
        except OSError as exc:
            raise AriSfmError(self.out, f"{self.option}: cannot write in this folder: {exc.strerror or exc}") from None
        if fcntl is None:
            return self
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):  # a file system without locks: go on unheld
                return self
            os.close(self.fd)
            self.fd = None
            raise AriSfmError(self.out, f"{self.option}: another ari-sfm command is writing into this folder now: "
                                        "wait for it, or choose another folder") from None
        return self

    def __exit__(self, exc_type, *exc: object) -> None:
        if self.fd is not None:
            os.close(self.fd)  # releases the lock
            self.fd = None
        if exc_type is not None and self.created:
            try:
                self.out.rmdir()  # only when nothing was left in it
            except OSError:
                pass

"""Checks of command-line values before any work starts: one AriSfmError line naming the option.

The CLI calls these first thing, so a bad ``-o`` or ``--huber-px`` fails in one
line before a slow detection or calibration, and never as an error from deep
inside (``non-finite Jacobian entries``) or about a file that was never written.
"""
from __future__ import annotations

import errno
import math
import os
from pathlib import Path

from ..errors import AriSfmError

PSEUDO_FILE_SYSTEMS = ("/proc", "/sys", "/dev")  # kernel interfaces, not places for results


def check_output_folder(out: str | Path, option: str = "-o/--out") -> Path:
    """Check that an output folder is, or can be created as, a writable folder.

    Refused: an existing file; a path under a file; a path inside /proc, /sys
    or /dev; a folder whose nearest existing ancestor is not writable.

    Args:
        out: the output folder.
        option: the option named in the error.

    Returns:
        ``out`` as a Path.

    Raises:
        AriSfmError: naming the folder and the option, when it is refused.
    """
    out = Path(out)
    try:
        os.stat(out)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise AriSfmError(out, f"{option}: a loop of symbolic links, not a folder") from None
        if os.path.islink(out):
            raise AriSfmError(out, f"{option}: a symbolic link to {os.readlink(out)}, which does not exist") from None
    resolved = Path(os.path.realpath(out))
    for root in PSEUDO_FILE_SYSTEMS:
        if resolved == Path(root) or Path(root) in resolved.parents:
            raise AriSfmError(out, f"{option}: {root} is a kernel file system, not a place for results")
    if out.exists() and not out.is_dir():
        raise AriSfmError(out, f"{option}: is a file, expected a folder")
    ancestor = resolved
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise AriSfmError(out, f"{option}: {ancestor} is a file, so it cannot hold the output folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise AriSfmError(out, f"{option}: no permission to write in {ancestor}")
    return out


def check_number(option: str, value: float | None, minimum: float | None = None, maximum: float | None = None,
                 strict_minimum: bool = False) -> float | None:
    """Check that an option's number is finite and within [minimum, maximum]; None passes.

    Args:
        option: the option named in the error.
        value: the value, or None.
        minimum: the least value allowed, or None.
        maximum: the largest value allowed, or None.
        strict_minimum: require value > minimum.

    Returns:
        ``value``.

    Raises:
        AriSfmError: naming the option, when the value is not finite or out of range.
    """
    if value is None:
        return None
    if not math.isfinite(value):
        raise AriSfmError(option, f"must be a finite number (got {value})")
    if minimum is not None and (value <= minimum if strict_minimum else value < minimum):
        raise AriSfmError(option, f"must be {'>' if strict_minimum else '>='} {minimum:g} (got {value:g})")
    if maximum is not None and value > maximum:
        raise AriSfmError(option, f"must be <= {maximum:g} (got {value:g})")
    return value


def check_not_input_folder(out: str | Path, input_folder: str | Path, what: str, option: str = "-o/--out") -> None:
    """Check that an output folder is not the input folder (after symbolic links): a command never writes into
    its input.

    Args:
        out: the output folder.
        input_folder: the command's input folder.
        what: what the input folder is, in the error ("the dataset folder").
        option: the option named in the error.

    Raises:
        AriSfmError: if ``out`` is ``input_folder``.
    """
    if Path(os.path.realpath(out)) == Path(os.path.realpath(input_folder)):
        raise AriSfmError(out, f"{option}: is {what}: choose another folder")


RECONSTRUCTION_OUTPUTS = ("points.json", "metrics.json", "observations.json")  # and clouds/*.ply


def check_not_an_output(given: str | Path | None, out: str | Path, option: str) -> None:
    """Check that an input file is not one ``reconstruct -o OUT`` would overwrite.

    Args:
        given: the input file, or None (passes).
        out: the output folder OUT.
        option: the option named in the error.

    Raises:
        AriSfmError: if the file is OUT/points.json, metrics.json, observations.json or under clouds/.
    """
    if given is None:
        return
    resolved = Path(os.path.realpath(given))
    out = Path(os.path.realpath(out))
    if resolved in [out / name for name in RECONSTRUCTION_OUTPUTS] or out / "clouds" in resolved.parents:
        raise AriSfmError(given, f"{option}: is a file this command writes in -o: copy it elsewhere first")

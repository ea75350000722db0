"""Read YAML / JSON files and check their values with one-line, user-facing errors.

Every function here raises :class:`~ari_sfm.errors.AriSfmError` naming the file
and the offending key path (``interface.thickness_mm must be > 0 (got -5.0)``);
no ``KeyError``, ``TypeError`` or parser exception reaches the caller.

``where`` arguments are dotted key paths used in messages (``target.square_mm``,
``calibration[3].images``).
"""
from __future__ import annotations

import json
import logging
import math
import numbers
import os
import re
import stat
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

from ari_sfm.errors import AriSfmError

log = logging.getLogger(__name__)
T = TypeVar("T")

_MISSING = object()


# --------------------------------------------------------------------------- parsing


_SafeLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml's parser when built


class _YamlLoader(_SafeLoader):  # type: ignore[misc, valid-type]
    """SafeLoader that rejects duplicate keys and reads ``1e-3`` as a float (YAML 1.2)."""


def _construct_mapping(loader: _YamlLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen: dict[Any, None] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            duplicate = key in seen
        except TypeError:  # unhashable key: let SafeConstructor report it
            continue
        if duplicate:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        seen[key] = None
    return yaml.constructor.SafeConstructor.construct_mapping(loader, node, deep=deep)


_YamlLoader.add_constructor("tag:yaml.org,2002:map", _construct_mapping)
# YAML 1.1 reads 1e-3 (no dot) as a string; YAML 1.2 and JSON read it as a number.
_YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _reject_duplicate_pairs(pairs: list[tuple[str, Any]]) -> dict:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateJsonKey(key)
        out[key] = value
    return out


class _DuplicateJsonKey(Exception):
    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.key = key


MAX_STRUCTURED_BYTES = 4 * 2**30  # a rig, calibration or observations file larger than this is not one


def read_structured(path: str | Path) -> Any:
    """Parse a YAML (``.yaml``/``.yml``) or JSON (``.json``) file; other suffixes are read as YAML.

    Duplicate keys are errors in both. YAML reads ``1e-3`` as a float (as YAML 1.2 and JSON do).

    Args:
        path: the file.

    Returns:
        The parsed content (never None).

    Raises:
        AriSfmError: a missing, unreadable, binary, too large, empty or malformed file (with line and
            column).
    """
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
        if not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):  # /dev/zero was read until memory ran out
            raise AriSfmError(path, "not a regular file (a device, pipe or socket): give a YAML or JSON file")
        if os.stat(path).st_size > MAX_STRUCTURED_BYTES:
            raise AriSfmError(path, f"{os.stat(path).st_size / 2**30:.1f} GiB: too large for a YAML or JSON file "
                                    f"(at most {MAX_STRUCTURED_BYTES / 2**30:g} GiB)")
        text = path.read_text(encoding="utf-8")
    except MemoryError:
        raise AriSfmError(path, "too large to read into memory") from None
    except FileNotFoundError:
        raise AriSfmError(path, "file not found") from None
    except IsADirectoryError:
        raise AriSfmError(path, "is a directory, expected a file") from None
    except UnicodeDecodeError as exc:
        binary = b"\0" in exc.object[:4096] or exc.start < 16  # an image or other binary file, not broken text
        what = "a binary file (an image?), not YAML or JSON text" if binary else "not UTF-8 text"
        raise AriSfmError(path, f"{what} (byte {exc.start} is not UTF-8)") from None
    except OSError as exc:
        raise AriSfmError(path, f"cannot read file: {exc.strerror or exc}") from None
    if path.suffix.lower() == ".json":
        return _parse_json(text, path)
    return _parse_yaml(text, path)


def _parse_json(text: str, path: Path) -> Any:
    if not text.strip():
        raise AriSfmError(path, "file is empty")
    try:
        return json.loads(text, object_pairs_hook=_reject_duplicate_pairs)
    except json.JSONDecodeError as exc:
        raise AriSfmError(path, f"malformed JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    except _DuplicateJsonKey as exc:
        raise AriSfmError(path, f"malformed JSON: duplicate key {exc.key!r}") from None
    except RecursionError:
        raise AriSfmError(path, "malformed JSON: nested too deeply") from None


def _parse_yaml(text: str, path: Path) -> Any:
    try:
        data = yaml.load(text, Loader=_YamlLoader)  # noqa: S506 - SafeLoader subclass
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        what = " ".join(str(exc.problem or exc.context or "syntax error").split())
        raise AriSfmError(path, f"malformed YAML{where}: {what}") from None
    except (yaml.YAMLError, RecursionError) as exc:
        raise AriSfmError(path, f"malformed YAML: {' '.join(str(exc).split())}") from None
    if data is None:
        raise AriSfmError(path, "file is empty")
    return data


# --------------------------------------------------------------------------- getters


def show(value: Any, limit: int = 60) -> str:
    """Format a file value for an error message: a short, one-line repr.

    Args:
        value: the value (a numpy array is shown as a list).
        limit: the most characters; a longer repr is cut and ends with ``...``.

    Returns:
        The repr.
    """
    if isinstance(value, np.ndarray):
        value = value.tolist()
    text = " ".join(repr(value).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def key_path(where: str, key: Any) -> str:
    """Join a key path and a key.

    Args:
        where: the key path ("" at the top level).
        key: the key.

    Returns:
        ``where.key``, or ``key`` at the top level.
    """
    return f"{where}.{key}" if where else str(key)


def as_mapping(value: Any, path: str | Path, where: str) -> Mapping:
    """Check that a value is a mapping.

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.

    Returns:
        ``value`` itself.

    Raises:
        AriSfmError: ``value`` is not a mapping.
    """
    if not isinstance(value, Mapping):
        raise AriSfmError(path, f"{where or 'the file'} must be a mapping (got {show(value)})")
    return value


def as_list(value: Any, path: str | Path, where: str) -> list:
    """Check that a value is a list (a YAML sequence / JSON array).

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.

    Returns:
        ``value`` as a list.

    Raises:
        AriSfmError: ``value`` is not a list or tuple.
    """
    if not isinstance(value, (list, tuple)):
        raise AriSfmError(path, f"{where} must be a list (got {show(value)})")
    return list(value)


def require(mapping: Any, key: str, path: str | Path, where: str = "") -> Any:
    """Get a key that must be present.

    Args:
        mapping: the mapping read from the file.
        key: the key.
        path: the file, for error messages.
        where: the mapping's key path, for error messages ("" at the top level).

    Returns:
        ``mapping[key]``.

    Raises:
        AriSfmError: ``missing key 'where.key'``, or ``mapping`` is not a mapping.
    """
    mapping = as_mapping(mapping, path, where)
    if key not in mapping:
        raise AriSfmError(path, f"missing key '{key_path(where, key)}'")
    return mapping[key]


def optional(
    mapping: Mapping,
    key: str,
    convert: Callable[[Any, str | Path, str], T],
    path: str | Path,
    where: str = "",
    default: Any = None,
) -> T | Any:
    """Get and convert a key that may be absent.

    Args:
        mapping: the mapping read from the file.
        key: the key.
        convert: a getter of this module, called as ``convert(value, path, key path)``.
        path: the file, for error messages.
        where: the mapping's key path, for error messages ("" at the top level).
        default: the value when the key is absent or null.

    Returns:
        ``convert(mapping[key])`` if the key is present and not null, else ``default``.
    """
    value = mapping.get(key)
    if value is None:
        return default
    return convert(value, path, key_path(where, key))


def warn_unknown_keys(mapping: Mapping, known: Iterable[str], path: str | Path, where: str = "") -> None:
    """Log a warning for keys the format does not define (allowed, but often a typo).

    Args:
        mapping: the mapping read from the file.
        known: the keys the format defines.
        path: the file, named in the warning.
        where: the mapping's key path ("" at the top level).
    """
    unknown = [str(k) for k in mapping if k not in set(known)]
    if unknown:
        log.warning("%s: unknown key%s %s ignored", path, "s" if len(unknown) > 1 else "",
                    ", ".join(f"'{key_path(where, k)}'" for k in unknown))


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def as_finite_float(value: Any, path: str | Path, where: str) -> float:
    """Check that a value is a finite real number (ints accepted, bools and strings not).

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.

    Returns:
        The number as a float.

    Raises:
        AriSfmError: not a number, or not finite.
    """
    if not _is_number(value):
        raise AriSfmError(path, f"{where} must be a number (got {show(value)})")
    out = float(value)
    if not math.isfinite(out):
        raise AriSfmError(path, f"{where} must be finite (got {show(value)})")
    return out


def as_float_at_least(value: Any, path: str | Path, where: str, minimum: float) -> float:
    """Check that a value is a finite number >= ``minimum``.

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.
        minimum: the least value allowed.

    Returns:
        The number as a float.

    Raises:
        AriSfmError: not a finite number, or below ``minimum``.
    """
    out = as_finite_float(value, path, where)
    if out < minimum:
        raise AriSfmError(path, f"{where} must be >= {minimum:g} (got {show(value)})")
    return out


def as_positive_float(value: Any, path: str | Path, where: str) -> float:
    """Check that a value is a finite number > 0.

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.

    Returns:
        The number as a float.

    Raises:
        AriSfmError: not a finite number, or <= 0.
    """
    out = as_finite_float(value, path, where)
    if out <= 0:
        raise AriSfmError(path, f"{where} must be > 0 (got {show(value)})")
    return out


def as_nonnegative_float(value: Any, path: str | Path, where: str) -> float:
    """Check that a value is a finite number >= 0.

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.

    Returns:
        The number as a float.

    Raises:
        AriSfmError: not a finite number, or < 0.
    """
    return as_float_at_least(value, path, where, 0.0)


def check_at_most(value: float, limit: float, path: str | Path, where: str, unit: str = "") -> float:
    """Hold a value to a sane physical upper bound.

    Args:
        value: the value.
        limit: the largest value allowed.
        path: the file, for error messages.
        where: the value's key path, for error messages.
        unit: the unit appended to the numbers in the message (e.g. ``" mm"``).

    Returns:
        ``value`` itself.

    Raises:
        AriSfmError: ``value`` > ``limit``, naming ``where``.
    """
    if value > limit:
        raise AriSfmError(path, f"{where} must be <= {limit:g}{unit} (got {show(value)}): not a physical value")
    return value


def as_int(value: Any, path: str | Path, where: str, minimum: int | None = None) -> int:
    """Check that a value is an integer (not a bool, not 3.0), optionally >= ``minimum``.

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.
        minimum: the least value allowed; None: any.

    Returns:
        The integer.

    Raises:
        AriSfmError: not an integer, or below ``minimum``.
    """
    if not isinstance(value, (numbers.Integral, np.integer)) or isinstance(value, (bool, np.bool_)):
        raise AriSfmError(path, f"{where} must be an integer (got {show(value)})")
    out = int(value)
    if minimum is not None and out < minimum:
        raise AriSfmError(path, f"{where} must be >= {minimum} (got {out})")
    return out


def as_int_pair(value: Any, path: str | Path, where: str, minimum: int = 1) -> tuple[int, int]:
    """Check that a value is two integers (``[cols, rows]``, ``[width, height]``).

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.
        minimum: the least value allowed for each.

    Returns:
        The two integers.

    Raises:
        AriSfmError: not a list of two integers each >= ``minimum``.
    """
    ok = isinstance(value, (list, tuple)) and len(value) == 2
    if ok:
        ok = all(
            isinstance(v, (numbers.Integral, np.integer)) and not isinstance(v, (bool, np.bool_)) and int(v) >= minimum
            for v in value
        )
    if not ok:
        raise AriSfmError(path, f"{where} must be two integers >= {minimum} (got {show(value)})")
    return int(value[0]), int(value[1])


def as_str(value: Any, path: str | Path, where: str) -> str:
    """Check that a value is a non-empty string.

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.

    Returns:
        ``value`` itself.

    Raises:
        AriSfmError: not a string, or empty or blank.
    """
    if not isinstance(value, str) or not value.strip():
        raise AriSfmError(path, f"{where} must be a non-empty string (got {show(value)})")
    return value


def as_name(value: Any, path: str | Path, where: str) -> str:
    """Check that a value is a frame / pose / camera name: a non-empty string.

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.

    Returns:
        The name; a YAML integer like ``7`` becomes ``'7'``.

    Raises:
        AriSfmError: neither a non-empty string nor an integer.
    """
    if isinstance(value, (numbers.Integral, np.integer)) and not isinstance(value, (bool, np.bool_)):
        return str(int(value))
    return as_str(value, path, where)


def as_float_array(value: Any, path: str | Path, where: str, shape: tuple[int, ...]) -> np.ndarray:
    """Check that a value is a finite float array of a shape, from nested lists of numbers.

    Messages say which rule failed: not numbers, wrong shape, null, NaN or infinity. An empty list is an
    empty (0, ...) array when ``shape`` starts with -1.

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.
        shape: the shape; -1 matches any length.

    Returns:
        The float array.

    Raises:
        AriSfmError: naming the rule that failed.
    """
    arr = _numeric_array(value, path, where, integers=False)
    if arr.size == 0 and arr.ndim == 1 and len(shape) > 1 and shape[0] == -1 and -1 not in shape[1:]:
        arr = arr.reshape((0,) + tuple(shape[1:]))  # [] is an empty (0, 2) list of pairs
    if arr.ndim != len(shape) or any(s not in (-1, n) for s, n in zip(shape, arr.shape)):
        want = " x ".join("N" if s == -1 else str(s) for s in shape)
        got = " x ".join(map(str, arr.shape)) or "scalar"
        raise AriSfmError(path, f"{where} must have shape {want} (got {got})")
    arr = arr.astype(float)
    if np.isnan(arr).any():
        raise AriSfmError(path, f"{where} contain NaN")
    if np.isinf(arr).any():
        raise AriSfmError(path, f"{where} contain infinity")
    return arr


def as_int_array(value: Any, path: str | Path, where: str) -> np.ndarray:
    """Check that a value is a flat list of integers.

    Args:
        value: the value read from the file.
        path: the file, for error messages.
        where: the value's key path, for error messages.

    Returns:
        The (N,) int64 array.

    Raises:
        AriSfmError: not a flat list of integers, or an integer out of range.
    """
    arr = _numeric_array(value, path, where, integers=True)
    if arr.ndim != 1:
        raise AriSfmError(path, f"{where} must be a flat list of integers")
    return arr.astype(np.int64)


def _flatten(value: Any):
    if isinstance(value, (list, tuple, np.ndarray)):
        for v in value:
            yield from _flatten(v)
    else:
        yield value


def _numeric_array(value: Any, path: str | Path, where: str, integers: bool) -> np.ndarray:
    """Nested lists of numbers (ints only if ``integers``) as a regular array, else a precise error."""
    what = "integers" if integers else "numbers"
    if not isinstance(value, (list, tuple, np.ndarray)):
        raise AriSfmError(path, f"{where} must be a list of {what} (got {show(value)})")
    try:  # fast path: a regular array of numbers
        arr = np.asarray(value)
    except (ValueError, TypeError):
        arr = None
    if arr is not None and arr.dtype.kind in ("iu" if integers else "iuf"):
        return arr
    for v in _flatten(value):
        if v is None:
            raise AriSfmError(path, f"{where} contain null")
        ok = (
            isinstance(v, (numbers.Integral, np.integer))
            if integers
            else isinstance(v, (numbers.Real, np.floating, np.integer))
        )
        if not ok or isinstance(v, (bool, np.bool_)):
            raise AriSfmError(path, f"{where} must be {what} (got {show(v)})")
    if isinstance(value, np.ndarray):
        return value
    try:
        arr = np.asarray(value, dtype=np.int64 if integers else float)
    except OverflowError:
        raise AriSfmError(path, f"{where} contain an integer out of range") from None
    except (ValueError, TypeError):
        raise AriSfmError(path, f"{where} must be a regular list of {what} (rows of equal length)") from None
    return arr

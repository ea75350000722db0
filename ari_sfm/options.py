"""What every options record shares: its modes' enum base and its keyword overrides.

A mode is a :class:`Choice`, a ``(str, Enum)``: it equals its string (``Mount.CAMERA == "camera"``), prints,
formats and is written to JSON as it, so files, messages and string comparisons are what they were with
plain strings. A record built from strings converts them with :meth:`Choice.parse`; a string that names no
mode is one line of ``ValueError`` naming the allowed values.
"""
from __future__ import annotations

from dataclasses import fields, replace
from enum import Enum
from typing import Any, TypeVar

C = TypeVar("C", bound="Choice")
R = TypeVar("R")


class Choice(str, Enum):
    """A mode of an options record: its value is its string (``str()``, f-strings, JSON and ``==`` see it)."""

    def __str__(self) -> str:
        """The mode's string."""
        return str(self.value)

    @classmethod
    def parse(cls: type[C], value: object, name: str) -> C:
        """``value`` (a mode or its string) as a mode of this enum.

        Args:
            value: a member of this enum, or the string of one.
            name: the option's name, for the error.

        Returns:
            The member.

        Raises:
            ValueError: one line naming the option and the allowed values.
        """
        try:
            return cls(value)
        except ValueError:
            allowed = ", ".join(m.value for m in cls)
            raise ValueError(f"{name} must be one of {allowed} (got {value!r})") from None


def with_overrides(record_type: type[R], options: R | None, overrides: dict[str, Any], what: str) -> R:
    """An options record (default: the defaults) with keyword ``overrides`` applied.

    Args:
        record_type: the record's dataclass.
        options: the record, or None for the defaults.
        overrides: field names and values (a function's keyword form).
        what: the function's name, for the error.

    Returns:
        The record.

    Raises:
        TypeError: an unknown field name, or ``options`` not a ``record_type``.
    """
    names = {f.name for f in fields(record_type)}  # type: ignore[arg-type]  # record_type is a dataclass
    unknown = set(overrides) - names
    if unknown:
        raise TypeError(f"unknown {what} option(s): {', '.join(sorted(unknown))} (known: {', '.join(sorted(names))})")
    if options is None:
        return record_type(**overrides)
    if not isinstance(options, record_type):
        raise TypeError(f"options must be a {record_type.__name__} (got {type(options).__name__})")
    return replace(options, **overrides)  # type: ignore[type-var]  # a dataclass instance

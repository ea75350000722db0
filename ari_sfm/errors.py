"""The one error type users see: a file and what is wrong with it."""
from __future__ import annotations

from pathlib import Path

ErrorPath = str | Path | None  # what an error names: a file, an option ("--backend"), or nothing


class AriSfmError(Exception):
    """A user-facing error; the CLI prints it as ``error: <file>: <what is wrong>``."""

    def __init__(self, path: ErrorPath, message: str) -> None:
        self.path = str(path) if path is not None else None
        self.message = message
        super().__init__(str(self))

    def __str__(self) -> str:
        return f"{self.path}: {self.message}" if self.path else self.message

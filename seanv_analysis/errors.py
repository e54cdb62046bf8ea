"""Exception family of seanv-analysis.

Library code raises these; only the CLI turns them into a one-line message
and an exit code (2 for bad input).
"""
from __future__ import annotations

__all__ = ["SeanvError", "DataError", "ConfigError", "FitError", "OutputError",
           "os_error_line"]


class SeanvError(Exception):
    """Base class of every error this package raises on purpose."""


class DataError(SeanvError):
    """Input data break the data contract.

    The message names the file, and the column and row where they apply,
    the bad value and what was expected.
    """

    def __init__(self, message: str, *, path: object = None, column: str | None = None,
                 row: int | None = None):
        parts = []
        if path is not None:
            parts.append(str(path))
        if column is not None:
            parts.append(f"column '{column}'")
        if row is not None:
            parts.append(f"row {row}")
        prefix = ", ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)
        self.path = path
        self.column = column
        self.row = row


class ConfigError(SeanvError):
    """A rig config, pipeline file or option is invalid."""


class FitError(SeanvError):
    """A fit cannot be done (too few points, no convergence)."""


class OutputError(SeanvError):
    """An output cannot be written: the output folder is not writable, lies
    under a file, or the disk is full. The message names the path."""


def os_error_line(exc: OSError) -> str:
    """One line for an operating-system error: the path(s), then why
    (``Permission denied``, ``No space left on device``...)."""
    paths = " -> ".join(str(p) for p in (exc.filename, exc.filename2) if p is not None)
    why = exc.strerror or str(exc) or type(exc).__name__
    line = f"{paths}: {why}" if paths else why
    return " ".join(line.split())

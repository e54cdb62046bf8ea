"""Logging and progress of the package: one ``logging`` tree, quiet by default.

Library code logs to ``logging.getLogger(__name__)`` (under
``seanv_analysis``): INFO for what a user watching a long command wants to
see (a stage starting, a fit's resamples), DEBUG for details. Nothing is
printed unless a handler is configured: the CLI does it (:func:`configure`:
``-q`` / default, the steps on a terminal / ``-v``, the steps and details
anywhere); a notebook user can call ``configure()`` too, or attach their own
handler.

Progress bars (tqdm, on stderr) are drawn only when stderr is a terminal,
INFO is enabled and ``CI`` is not set (:func:`progress_enabled`); a line
logged while a bar is drawn clears the bars, is written, and the bars are
drawn again below it (:class:`_BarSafeHandler`), so lines and bars never
write over each other.
"""
from __future__ import annotations

import logging
import os
import sys

__all__ = ["logger", "configure", "progress_enabled", "progress"]

logger = logging.getLogger("seanv_analysis")
logger.addHandler(logging.NullHandler())

_HANDLER_NAME = "seanv-analyze-stderr"


def configure(*, quiet: bool = False, verbose: int = 0) -> int:
    """Log the package to stderr, one line per message; returns the level.

    ``quiet``: warnings and errors only. Default: the steps (INFO) when stderr
    is a terminal (and ``CI`` is not set), else warnings and errors only, so a
    piped or scripted command's stderr holds nothing but what went wrong
    (bad input stays one line). ``verbose`` 1: the steps and their details
    (DEBUG) wherever stderr goes; 2: each line with its time and module.
    """
    if quiet:
        level = logging.WARNING
    elif verbose:
        level = logging.DEBUG
    else:
        level = logging.INFO if _terminal() else logging.WARNING
    for h in list(logger.handlers):
        if h.get_name() == _HANDLER_NAME:
            logger.removeHandler(h)
    handler = _BarSafeHandler(sys.stderr)
    handler.set_name(_HANDLER_NAME)
    handler.setFormatter(logging.Formatter("%(message)s" if verbose < 2 else
                                           "%(asctime)s %(name)s %(levelname)s: %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False
    return level


class _BarSafeHandler(logging.StreamHandler):
    """A stderr handler that clears the progress bars drawn on the same
    stream before a line and draws them again after it (tqdm's
    ``external_write_mode``; tqdm is not imported for this: no bar can be
    drawn before it is)."""

    def emit(self, record: logging.LogRecord) -> None:
        tqdm_std = sys.modules.get("tqdm.std")
        if tqdm_std is None or not tqdm_std.tqdm._instances:
            super().emit(record)
            return
        with tqdm_std.tqdm.external_write_mode(file=self.stream):
            super().emit(record)


def _terminal() -> bool:
    return bool(getattr(sys.stderr, "isatty", lambda: False)()) and not os.environ.get("CI")


def progress_enabled() -> bool:
    """True when a progress bar would be seen: stderr is a terminal, INFO is
    enabled for the package and ``CI`` is not set."""
    return (logger.isEnabledFor(logging.INFO) and _terminal()
            and any(h.get_name() == _HANDLER_NAME for h in logger.handlers))


def progress(iterable=None, *, total: int | None = None, desc: str | None = None,
             unit: str = "run", disable: bool = False):
    """``tqdm`` over ``iterable`` on stderr when :func:`progress_enabled` (and
    not ``disable``); else a bar that draws nothing (tqdm is then not even
    imported)."""
    if disable or not progress_enabled():
        return _NoBar(iterable)
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit=unit, file=sys.stderr, leave=False,
                dynamic_ncols=True)


class _NoBar:
    """The methods of a tqdm bar the package calls, drawing nothing."""

    def __init__(self, iterable=None) -> None:
        self.iterable = iterable

    def __iter__(self):
        return iter(self.iterable if self.iterable is not None else ())

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def update(self, n: int = 1) -> None:
        return None

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        return None

    def refresh(self) -> None:
        return None

    def close(self) -> None:
        return None

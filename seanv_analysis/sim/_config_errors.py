"""The simulator's boundary for bad parameters the user gave.

The models (:mod:`seanv_analysis.models`) raise :class:`ValueError` for a
bad value (a needle geometry whose eq. (4) is not monotonic, an effect
parameter out of range); where such a value comes from the rig config or
an effect spec, the simulator re-raises it as
:class:`~seanv_analysis.errors.ConfigError` with the same text, which the
command line prints as one line (exit code 2).
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

from ..errors import ConfigError

__all__ = ["config_errors"]


@contextmanager
def config_errors() -> Iterator[None]:
    """Re-raise a :class:`ValueError` of the block as ConfigError (same message)."""
    try:
        yield
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
